//! The map file: one SQLite database per map (bundled SQLite).
//!
//! A map file is a public format: other programs (and a Python user with `sqlite3`) may read it.
//! It must not depend on anything above the core.
//!
//! # Format version 1
//!
//! SQLite header fields:
//! - `PRAGMA application_id` = `0x42474B4D` (ASCII "BGKM"): identifies a bgkmap map file.
//! - `PRAGMA user_version` = format version ([`FORMAT_VERSION`]). A file of another version is
//!   refused with [`StoreError::Version`].
//!
//! Tables:
//!
//! ```sql
//! CREATE TABLE meta   (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
//! CREATE TABLE params (name TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
//! CREATE TABLE blocks (bx INTEGER NOT NULL, by INTEGER NOT NULL, bz INTEGER NOT NULL,
//!                      data BLOB NOT NULL, crc32 INTEGER NOT NULL,
//!                      PRIMARY KEY (bx, by, bz)) WITHOUT ROWID;
//! CREATE TABLE scans  (source TEXT NOT NULL, seq INTEGER NOT NULL,
//!                      PRIMARY KEY (source, seq)) WITHOUT ROWID;
//! ```
//!
//! - `meta`: `format` = `bgkmap`, `format_version` = `1`, `block_edge` = `8` (cells per block edge),
//!   `fixed_shift` = `24` (fractional bits of the evidence sums), `writer` = the crate version.
//! - `params`: every map parameter by its CLI flag name ([`MapParams::to_pairs`]), values in
//!   Rust's shortest round-trip decimal form (parsing gives the same f64 bits).
//! - `scans`: the identities `(source, seq)` of the scans whose evidence the blocks hold (maps
//!   built offline from files leave it empty). A server never applies a listed scan again.
//! - `blocks`: one row per block holding evidence. `(bx, by, bz)` is the block key: cell key
//!   `>> 3` per axis (cell key = `floor(x / resolution)`). `crc32` is the CRC-32 (IEEE, as zlib)
//!   of `data`.
//!
//! Block `data`, byte by byte:
//!
//! | offset | size | content |
//! |---|---|---|
//! | 0 | 1 | encoding, `1` |
//! | 1 | 64 | presence bitmap: bit `i` (byte `i / 8`, LSB first) set ⇔ cell `i` holds evidence |
//! | 65 | … | for each present cell in increasing `i`: `A` then `B` as zigzag LEB128 varints |
//!
//! Cell `i` within a block is local `(x, y, z)` with `i = x + 8·y + 64·z`. `A` and `B` are the
//! occupied and free unit-kernel evidence sums in fixed point (`value / 2^24`). A cell holds
//! evidence when `A ≠ 0` or `B ≠ 0`; absent cells have `A = B = 0`. The encoding must consume the
//! blob exactly.
//!
//! Files are written whole to a temporary sibling and renamed into place, so a failed write never
//! leaves a half-written map. (The scan journal and in-place incremental updates of a later
//! format version add tables; readers of version 1 refuse those files by version.)

use crate::core::kernel::FIXED_SHIFT;
use crate::core::key::{BLOCK_CELLS, BLOCK_EDGE, BlockKey};
use crate::core::{EvidenceMap, MapParams};
use rusqlite::{Connection, OpenFlags, OptionalExtension, params};
use std::path::{Path, PathBuf};

mod codec;
mod file;
pub use codec::{decode_block, encode_block};
pub use file::{MapFile, OpenedMap, ScanId};

/// The format version this build reads and writes.
pub const FORMAT_VERSION: i64 = 1;
/// `PRAGMA application_id` of a bgkmap map file ("BGKM").
pub const APPLICATION_ID: i64 = 0x4247_4B4D;

/// Errors of the map file layer; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: not a bgkmap map file ({reason})")]
    NotAMap { path: PathBuf, reason: String },
    #[error(
        "{path}: map file format version {found} is not supported (this build reads version {FORMAT_VERSION})"
    )]
    Version { path: PathBuf, found: i64 },
    #[error("{path}: block ({x}, {y}, {z}) is corrupt: {reason}")]
    CorruptBlock { path: PathBuf, x: i32, y: i32, z: i32, reason: String },
    #[error("{path}: bad map parameters: {reason}")]
    Params { path: PathBuf, reason: String },
    // The cause is part of the message (not a `source`), so it is printed once.
    #[error("{path}: {error}")]
    Sqlite { path: PathBuf, error: rusqlite::Error },
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
}

fn sql(path: &Path) -> impl Fn(rusqlite::Error) -> StoreError + '_ {
    move |error| StoreError::Sqlite { path: path.to_path_buf(), error }
}

/// Writes `map` to `path` atomically (temporary file + rename). An existing file is replaced.
pub fn save_map(path: &Path, map: &EvidenceMap) -> Result<(), StoreError> {
    let tmp = temp_sibling(path);
    let result = write_new(&tmp, map).and_then(|()| {
        std::fs::rename(&tmp, path).map_err(|error| StoreError::Io { path: path.to_path_buf(), error })
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// The temporary sibling a file is written to before it is renamed over `path`.
pub fn temp_sibling(path: &Path) -> PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".tmp-{}", std::process::id()));
    path.with_file_name(name)
}

fn write_new(path: &Path, map: &EvidenceMap) -> Result<(), StoreError> {
    let _ = std::fs::remove_file(path);
    let mut conn = Connection::open(path).map_err(sql(path))?;
    create_schema(&mut conn, path, map.params())?;
    let mut file = MapFile::from_conn(conn, path);
    let keys = map.block_keys_sorted();
    let rows: Vec<_> = keys.iter().map(|k| (*k, map.block(*k))).collect();
    file.commit(&rows, &[])?;
    file.close()
}

/// Creates the tables and writes the format header and parameters of a new, empty map file.
fn create_schema(conn: &mut Connection, path: &Path, map_params: &MapParams) -> Result<(), StoreError> {
    let e = sql(path);
    conn.execute_batch(&format!(
        "PRAGMA application_id = {APPLICATION_ID}; PRAGMA user_version = {FORMAT_VERSION};
         CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
         CREATE TABLE params (name TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
         CREATE TABLE blocks (bx INTEGER NOT NULL, by INTEGER NOT NULL, bz INTEGER NOT NULL,
                              data BLOB NOT NULL, crc32 INTEGER NOT NULL,
                              PRIMARY KEY (bx, by, bz)) WITHOUT ROWID;
         CREATE TABLE scans (source TEXT NOT NULL, seq INTEGER NOT NULL,
                             PRIMARY KEY (source, seq)) WITHOUT ROWID;"
    ))
    .map_err(&e)?;
    let tx = conn.transaction().map_err(&e)?;
    {
        let mut meta = tx.prepare("INSERT INTO meta (key, value) VALUES (?1, ?2)").map_err(&e)?;
        for (k, v) in [
            ("format", "bgkmap".to_string()),
            ("format_version", FORMAT_VERSION.to_string()),
            ("block_edge", BLOCK_EDGE.to_string()),
            ("fixed_shift", FIXED_SHIFT.to_string()),
            ("writer", format!("bgkmap {}", env!("CARGO_PKG_VERSION"))),
        ] {
            meta.execute(params![k, v]).map_err(&e)?;
        }
        let mut p = tx.prepare("INSERT INTO params (name, value) VALUES (?1, ?2)").map_err(&e)?;
        for (k, v) in map_params.to_pairs() {
            p.execute(params![k, v]).map_err(&e)?;
        }
    }
    tx.commit().map_err(&e)
}

/// Opens `path` read-only, checks it is a bgkmap file of this version, and returns the connection.
fn open_checked(path: &Path) -> Result<Connection, StoreError> {
    open_with(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)
}

fn open_with(path: &Path, flags: OpenFlags) -> Result<Connection, StoreError> {
    if !path.is_file() {
        let error = std::io::Error::new(std::io::ErrorKind::NotFound, "no such map file");
        return Err(StoreError::Io { path: path.to_path_buf(), error });
    }
    let not_a_map = |reason: String| StoreError::NotAMap { path: path.to_path_buf(), reason };
    let conn = Connection::open_with_flags(path, flags).map_err(|err| not_a_map(err.to_string()))?;
    let app: i64 = conn
        .query_row("PRAGMA application_id", [], |r| r.get(0))
        .map_err(|err| not_a_map(err.to_string()))?;
    if app != APPLICATION_ID {
        return Err(not_a_map(format!("application_id is {app:#x}, expected {APPLICATION_ID:#x}")));
    }
    let version: i64 = conn.query_row("PRAGMA user_version", [], |r| r.get(0)).map_err(sql(path))?;
    if version != FORMAT_VERSION {
        return Err(StoreError::Version { path: path.to_path_buf(), found: version });
    }
    Ok(conn)
}

/// Reads the parameters of a map file without loading its blocks.
pub fn load_params(path: &Path) -> Result<MapParams, StoreError> {
    read_params(&open_checked(path)?, path)
}

fn read_params(conn: &Connection, path: &Path) -> Result<MapParams, StoreError> {
    let e = sql(path);
    let mut stmt = conn.prepare("SELECT name, value FROM params").map_err(&e)?;
    let pairs: Vec<(String, String)> = stmt
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .map_err(&e)?
        .collect::<Result<_, _>>()
        .map_err(&e)?;
    MapParams::from_pairs(pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())))
        .map_err(|err| StoreError::Params { path: path.to_path_buf(), reason: err.to_string() })
}

/// Loads a whole map, verifying every block's checksum and encoding.
pub fn load_map(path: &Path) -> Result<EvidenceMap, StoreError> {
    read_map(&open_checked(path)?, path)
}

fn read_map(conn: &Connection, path: &Path) -> Result<EvidenceMap, StoreError> {
    let e = sql(path);
    let edge: Option<String> = conn
        .query_row("SELECT value FROM meta WHERE key = 'block_edge'", [], |r| r.get(0))
        .optional()
        .map_err(&e)?;
    if edge.as_deref() != Some(&BLOCK_EDGE.to_string()) {
        return Err(StoreError::NotAMap { path: path.to_path_buf(), reason: format!("block_edge {edge:?}") });
    }
    let mut map = EvidenceMap::new(read_params(conn, path)?);
    let mut stmt = conn.prepare("SELECT bx, by, bz, data, crc32 FROM blocks").map_err(&e)?;
    let mut rows = stmt.query([]).map_err(&e)?;
    while let Some(row) = rows.next().map_err(&e)? {
        let key = BlockKey::new(row.get(0).map_err(&e)?, row.get(1).map_err(&e)?, row.get(2).map_err(&e)?);
        let data: Vec<u8> = row.get(3).map_err(&e)?;
        let crc: i64 = row.get(4).map_err(&e)?;
        let corrupt = |reason: String| StoreError::CorruptBlock {
            path: path.to_path_buf(),
            x: key.x,
            y: key.y,
            z: key.z,
            reason,
        };
        if i64::from(crc32fast::hash(&data)) != crc {
            return Err(corrupt("checksum mismatch".into()));
        }
        let block = decode_block(&data).map_err(corrupt)?;
        map.insert_block(key, block);
    }
    Ok(map)
}

const _: () = assert!(BLOCK_CELLS == 512);

#[cfg(test)]
mod tests;
