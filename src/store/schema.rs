//! The tables and header of a map file: creating them, and checking them on open.

use super::{APPLICATION_ID, FORMAT_VERSION, OLDEST_FORMAT_VERSION, StoreError, sql};
use crate::core::MapParams;
use crate::core::key::BLOCK_EDGE;
use crate::core::posterior::FIXED_SHIFT;
use rusqlite::{Connection, OpenFlags, OptionalExtension, params};
use std::path::Path;

/// The `CREATE` statements of format versions 2 and 3, exactly as stored in `sqlite_master.sql`.
pub const SCHEMA: [&str; 5] = [
    "CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID",
    "CREATE TABLE params (name TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID",
    "CREATE TABLE blocks (bx INTEGER NOT NULL, by INTEGER NOT NULL, bz INTEGER NOT NULL,
  data BLOB NOT NULL, crc32 INTEGER NOT NULL, PRIMARY KEY (bx, by, bz)) WITHOUT ROWID",
    "CREATE TABLE scans (id INTEGER PRIMARY KEY, source TEXT NOT NULL, seq INTEGER NOT NULL,
  stamp_nanos INTEGER NOT NULL, received_nanos INTEGER NOT NULL, status INTEGER NOT NULL,
  record_bytes INTEGER NOT NULL, crc32 INTEGER NOT NULL, UNIQUE (source, seq))",
    "CREATE TABLE scan_records (id INTEGER PRIMARY KEY, record BLOB NOT NULL)",
];

/// SQLite page size of new map files. A `blocks` row lives in its B-tree leaf only up to about a
/// quarter of a page (`WITHOUT ROWID` rows are index entries); above that the rest spills to an
/// overflow page of its own, mostly empty. With SQLite's default 4 KiB pages that limit is about
/// 1 KB, so most blocks took two pages and a file was twice its blocks. 32 KiB pages keep rows up
/// to 8 KB in the leaf: every block of a young map (about 3 KB when all 512 cells hold evidence)
/// and of a long-lived one, whose sums grow to 5–6 bytes per varint (16 KiB pages would spill
/// those). The price is 32 KiB per table of a nearly empty map. Files with other page sizes
/// (earlier files) open and work the same.
pub const PAGE_SIZE: u32 = 32768;

/// Creates the tables and writes the format header and parameters of a new, empty map file.
pub(super) fn create_schema(
    conn: &mut Connection,
    path: &Path,
    map_params: &MapParams,
) -> Result<(), StoreError> {
    let e = sql(path);
    conn.execute_batch(&format!(
        "PRAGMA page_size = {PAGE_SIZE}; PRAGMA application_id = {APPLICATION_ID}; PRAGMA user_version = {FORMAT_VERSION};"
    ))
    .map_err(&e)?;
    let tx = conn.transaction().map_err(&e)?;
    for stmt in SCHEMA {
        tx.execute(stmt, []).map_err(&e)?;
    }
    {
        let mut meta = tx.prepare("INSERT INTO meta (key, value) VALUES (?1, ?2)").map_err(&e)?;
        for (k, v) in [
            ("format", "bgkmap".to_string()),
            ("format_version", FORMAT_VERSION.to_string()),
            ("block_edge", BLOCK_EDGE.to_string()),
            ("fixed_shift", FIXED_SHIFT.to_string()),
            ("writer", format!("bgkmap {}", env!("CARGO_PKG_VERSION"))),
            ("version", "0".to_string()),
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

/// Opens `path` with `flags` and checks it is a bgkmap file of a version this build reads; a
/// writable open upgrades an older version first (see the format's docs).
pub(super) fn open_with(path: &Path, flags: OpenFlags) -> Result<Connection, StoreError> {
    if !path.is_file() {
        let error = std::io::Error::new(std::io::ErrorKind::NotFound, "no such map file");
        return Err(StoreError::Io { path: path.to_path_buf(), error });
    }
    let not_a_map = |reason: String| StoreError::NotAMap { path: path.to_path_buf(), reason };
    let conn = Connection::open_with_flags(path, flags).map_err(|err| not_a_map(err.to_string()))?;
    conn.busy_timeout(std::time::Duration::from_secs(30)).map_err(sql(path))?;
    let app: i64 = conn
        .query_row("PRAGMA application_id", [], |r| r.get(0))
        .map_err(|err| not_a_map(err.to_string()))?;
    if app != APPLICATION_ID {
        return Err(not_a_map(format!("application_id is {app:#x}, expected {APPLICATION_ID:#x}")));
    }
    let version: i64 = conn.query_row("PRAGMA user_version", [], |r| r.get(0)).map_err(sql(path))?;
    if !(OLDEST_FORMAT_VERSION..=FORMAT_VERSION).contains(&version) {
        let hint = if version > FORMAT_VERSION { "; it was written by a newer bgkmap: upgrade" } else { "" };
        return Err(StoreError::Version { path: path.to_path_buf(), found: version, hint });
    }
    let edge = meta_value(&conn, path, "block_edge")?;
    if edge.as_deref() != Some(&BLOCK_EDGE.to_string()) {
        return Err(not_a_map(format!("meta block_edge is {edge:?}, expected {BLOCK_EDGE}")));
    }
    if version < FORMAT_VERSION && flags.contains(OpenFlags::SQLITE_OPEN_READ_WRITE) {
        // Before anything can write a block encoding the old version lacks. The header and
        // `meta` change together or not at all.
        conn.execute_batch(&format!(
            "BEGIN IMMEDIATE; PRAGMA user_version = {FORMAT_VERSION};
             UPDATE meta SET value = '{FORMAT_VERSION}' WHERE key = 'format_version'; COMMIT;"
        ))
        .map_err(sql(path))?;
    }
    Ok(conn)
}

pub(super) fn meta_value(conn: &Connection, path: &Path, key: &str) -> Result<Option<String>, StoreError> {
    conn.query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get(0)).optional().map_err(sql(path))
}

/// The map version recorded in `meta` (0 when absent).
pub(super) fn read_version(conn: &Connection, path: &Path) -> Result<u64, StoreError> {
    match meta_value(conn, path, "version")? {
        None => Ok(0),
        Some(v) => v.parse().map_err(|_| StoreError::NotAMap {
            path: path.to_path_buf(),
            reason: format!("meta version {v:?} is not a number"),
        }),
    }
}

pub(super) fn read_params(conn: &Connection, path: &Path) -> Result<MapParams, StoreError> {
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
