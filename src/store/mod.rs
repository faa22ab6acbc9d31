//! The map file: one SQLite database per map (bundled SQLite), holding the map's evidence blocks
//! and the journal of the scans that made them.
//!
//! A map file is a public format: other programs (and a Python user with `sqlite3`) may read it.
//! This module must not depend on anything above the core (no service, no network); it uses the
//! core to recompute a scan's evidence from its journal record.
//!
//! # Format version 3
//!
//! Version 3 is version 2 plus block encoding `2` (below), for blocks without hit mass. This
//! build reads both. A version 2 file opened for writing is upgraded in place first (its
//! `user_version` and `meta.format_version` set to 3 in one transaction; its blocks stay as they
//! are, since encoding `1` is valid in version 3), so a file that may hold encoding `2` never
//! claims version 2. (Version 1, without the journal, was never released; files of version 1
//! are refused like any other version.)
//!
//! SQLite header fields:
//! - `PRAGMA application_id` = `0x42474B4D` (ASCII "BGKM"): identifies a bgkmap map file.
//! - `PRAGMA user_version` = format version ([`FORMAT_VERSION`]). A file of another version is
//!   refused with [`StoreError::Version`], which says whether it is older or newer.
//! - Page size: new files use 32 KiB pages so each `blocks` row stays
//!   in its B-tree leaf; the format does not depend on it and files with any page size open.
//!
//! Tables (the `sql` of `sqlite_master` is exactly this text; [`SCHEMA`]):
//!
//! ```sql
//! CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
//! CREATE TABLE params (name TEXT PRIMARY KEY, value TEXT NOT NULL) WITHOUT ROWID;
//! CREATE TABLE blocks (bx INTEGER NOT NULL, by INTEGER NOT NULL, bz INTEGER NOT NULL,
//!   data BLOB NOT NULL, crc32 INTEGER NOT NULL, PRIMARY KEY (bx, by, bz)) WITHOUT ROWID;
//! CREATE TABLE scans (id INTEGER PRIMARY KEY, source TEXT NOT NULL, seq INTEGER NOT NULL,
//!   stamp_nanos INTEGER NOT NULL, received_nanos INTEGER NOT NULL, status INTEGER NOT NULL,
//!   record_bytes INTEGER NOT NULL, crc32 INTEGER NOT NULL, UNIQUE (source, seq));
//! CREATE TABLE scan_records (id INTEGER PRIMARY KEY, record BLOB NOT NULL);
//! ```
//!
//! - `meta`: `format` = `bgkmap`, `format_version` = `3`, `block_edge` = `8` (cells per block
//!   edge), `fixed_shift` = `24` (fractional bits of the evidence sums), `writer` = the crate
//!   version that created the file, `version` = the map version (decimal): +1 for every scan
//!   integrated and for every retraction, re-posing or merge; it never decreases.
//! - `params`: every map parameter by its CLI flag name ([`MapParams::to_pairs`]), values in
//!   Rust's shortest round-trip decimal form (parsing gives the same f64 bits).
//! - `blocks`: one row per block holding evidence. `(bx, by, bz)` is the block key: cell key
//!   `>> 3` per axis (cell key = `floor(x / resolution)`). `crc32` is the CRC-32 (IEEE, as zlib)
//!   of `data`.
//! - `scans`: the journal, one row per scan identity `(source, seq)` the map ever accepted, in
//!   arrival order (`id`). `seq` is in `[0, 2^63)`. `stamp_nanos` is the scan's time (the
//!   client's, else the arrival time; Unix nanoseconds), `received_nanos` its arrival time.
//!   `status`: `0` journaled (durable, evidence not yet in `blocks`), `1` applied (evidence in
//!   `blocks`, raw scan kept), `2` applied with the raw scan pruned (retention), `3` retracted
//!   (evidence removed; the identity stays, so the scan is never accepted again).
//!   `record_bytes` is the length of the record as written. `crc32` is the scan's fingerprint:
//!   CRC-32 of `source` (UTF-8) ‖ `0x00` ‖ `seq` (u64 LE) ‖ the record's *canonical* bytes (the
//!   record with points codec `0`, see below). It is kept after pruning, so two maps can tell
//!   whether they hold the same scan; stamps and status are not covered.
//! - `scan_records`: the raw scan of journal row `id` (status `0` and `1` only).
//!
//! Block `data`, byte by byte:
//!
//! | offset | size | content |
//! |---|---|---|
//! | 0 | 1 | encoding, `1` or `2` |
//! | 1 | 64 | presence bitmap: bit `i` (byte `i / 8`, LSB first) set ⇔ cell `i` holds evidence |
//! | 65 | … | for each present cell in increasing `i`: encoding `1`: `A` then `B` as zigzag LEB128 varints; encoding `2`: `B` alone (`A = 0`) |
//!
//! Cell `i` within a block is local `(x, y, z)` with `i = x + 8·y + 64·z`. `A` and `B` are the
//! occupied and free unit-kernel evidence sums in fixed point (`value / 2^24`). A cell holds
//! evidence when `A ≠ 0` or `B ≠ 0`; absent cells have `A = B = 0`. The encoding must consume the
//! blob exactly. Writers use encoding `2` exactly when every `A` of the block is 0 (free space:
//! half the blocks of an outdoor drive), so the bytes of a block are a function of its cells.
//!
//! Scan `record`, byte by byte (little-endian):
//!
//! | offset | size | content |
//! |---|---|---|
//! | 0 | 1 | record encoding, `1` |
//! | 1 | 1 | frame of the points: `0` world, `1` sensor (`p_world = q·p + t`) |
//! | 2 | 1 | points codec: `0` raw, `1` XOR-shuffle-LZF |
//! | 3 | 1 | flags: bit 0 set ⇔ the scan has its own max range; other bits 0 |
//! | 4 | 24 | `world_from_sensor` translation x, y, z (f64, metres) |
//! | 28 | 32 | `world_from_sensor` rotation w, x, y, z (f64 unit quaternion) |
//! | 60 | 8 | the scan's max range (f64, metres); `0` when flag bit 0 is clear |
//! | 68 | 4 | `n`, the number of points (u32) |
//! | 72 | … | the points |
//!
//! Points, codec `0`: `12·n` bytes, x y z f32 per point, in the order received (only finite
//! points are journaled). Codec `1`: an LZF stream (as `io::lzf`, liblzf's format) that decodes
//! to exactly `12·n` bytes `s`; with `w[i]` the u32 bits of value `i` of the raw sequence
//! `x0 y0 z0 x1 …` and `d[i] = w[i] XOR w[i−3]` (`d[i] = w[i]` for `i < 3`),
//! `s[k·3n + i]` = byte `k` (0 = least significant) of `d[i]`. Writers pick codec 1 only when it
//! is smaller. The canonical bytes of a record are the first 72 bytes with byte 2 set to `0`,
//! followed by the `12·n` raw point bytes.
//!
//! The evidence of a scan is a pure function of its record and the map parameters
//! ([`RawScan::delta`](crate::core::RawScan::delta)), so `blocks` = the sum of the deltas of every
//! applied scan (plus evidence from maps merged in without a journal, e.g. `bgkmap build` without
//! `--source`). That is what makes replay, retraction, re-posing and merges exact.
//!
//! # Writing
//!
//! A process writing a map file in place (the server, `bgkmap retract`, `repose`) holds an
//! exclusive lock on the sibling file `<file>-lock` ([`lock::MapLock`]) and uses WAL mode with
//! `synchronous = FULL`: a committed transaction is on disk, which is what an acknowledgement
//! means. A scan is journaled (status `0`) in one transaction before it is acknowledged; its
//! evidence goes into `blocks` together with the status change to `1` in a later transaction.
//! Opening a file replays journaled scans. New files (`bgkmap build`, `merge`) are written whole
//! to a temporary sibling and renamed into place, so a failed command never leaves a
//! half-written map. Readers need no lock.

use crate::core::{EvidenceMap, MapParams};
use std::path::{Path, PathBuf};

pub mod check;
mod codec;
mod durable;
pub mod edits;
mod file;
pub mod journal;
pub mod lock;
mod reader;
pub mod record;
mod schema;

pub use codec::{decode_block, encode_block};
pub use durable::{Change, DurableMap, Pending, Recovered, Retention};
pub use edits::{OpError, ScanSelector};
pub use file::{Commit, ImportedScan, MapFile, NewScan, OpenedMap};
pub use journal::{JournalEntry, JournalIndex, ScanId, ScanStatus};
pub use reader::{CorruptBlock, MapReader};
pub use schema::SCHEMA;

/// The format version this build writes (and reads).
pub const FORMAT_VERSION: i64 = 3;
/// The oldest format version this build reads; such a file opened for writing is upgraded to
/// [`FORMAT_VERSION`] first (see the format's docs).
pub const OLDEST_FORMAT_VERSION: i64 = 2;
/// `PRAGMA application_id` of a bgkmap map file ("BGKM").
pub const APPLICATION_ID: i64 = 0x4247_4B4D;

/// Errors of the map file layer; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: not a bgkmap map file ({reason})")]
    NotAMap { path: PathBuf, reason: String },
    #[error(
        "{path}: map file format version {found} is not supported (this build reads versions {OLDEST_FORMAT_VERSION} to {FORMAT_VERSION}){hint}"
    )]
    Version { path: PathBuf, found: i64, hint: &'static str },
    #[error("{path}: block ({x}, {y}, {z}) is corrupt: {reason}")]
    CorruptBlock { path: PathBuf, x: i32, y: i32, z: i32, reason: String },
    #[error("{path}: journal record of scan ({source_name}, {seq}) is corrupt: {reason}")]
    CorruptRecord { path: PathBuf, source_name: String, seq: u64, reason: String },
    #[error("{path}: bad map parameters: {reason}")]
    Params { path: PathBuf, reason: String },
    #[error("{path}: the map file is in use by another process (lock {lock} is held)")]
    Locked { path: PathBuf, lock: PathBuf },
    // The cause is part of the message (not a `source`), so it is printed once.
    #[error("{path}: {error}")]
    Sqlite { path: PathBuf, error: rusqlite::Error },
    #[error("{path}: {error}")]
    Io { path: PathBuf, error: std::io::Error },
}

impl StoreError {
    /// True for errors that mean stored data is damaged (a checksum or decoding failure).
    pub fn is_corruption(&self) -> bool {
        matches!(self, Self::CorruptBlock { .. } | Self::CorruptRecord { .. })
    }
}

pub(crate) fn sql(path: &Path) -> impl Fn(rusqlite::Error) -> StoreError + '_ {
    move |error| StoreError::Sqlite { path: path.to_path_buf(), error }
}

/// Writes `map` to a new file at `path` atomically (temporary file + rename), without journal;
/// its version is 1 (0 if it is empty). An existing file is replaced.
pub fn save_map(path: &Path, map: &EvidenceMap) -> Result<(), StoreError> {
    save_map_with_scans(path, map, &[], u64::from(map.block_count() > 0))
}

/// As [`save_map`], journaling `scans` (whose evidence `map` holds) as applied scans, with map
/// version `version`.
pub fn save_map_with_scans(
    path: &Path,
    map: &EvidenceMap,
    scans: &[NewScan],
    version: u64,
) -> Result<(), StoreError> {
    let tmp = temp_sibling(path);
    let result = file::write_new(&tmp, map, scans, version).and_then(|()| {
        std::fs::rename(&tmp, path).map_err(|error| StoreError::Io { path: path.to_path_buf(), error })
    });
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// The current time as Unix nanoseconds (the journal's clock).
pub fn now_nanos() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// The temporary sibling a file is written to before it is renamed over `path`.
pub fn temp_sibling(path: &Path) -> PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".tmp-{}", std::process::id()));
    path.with_file_name(name)
}

/// Reads the parameters of a map file without loading its blocks.
pub fn load_params(path: &Path) -> Result<MapParams, StoreError> {
    Ok(*MapReader::open(path)?.params())
}

/// Loads a whole map for reading: every block (checksums and encodings verified; a corrupt
/// block is an error) plus the evidence of journaled scans not yet applied (replayed in memory,
/// so a file left by a crashed server reads as everything it acknowledged).
pub fn load_map(path: &Path) -> Result<EvidenceMap, StoreError> {
    MapReader::open(path)?.load_map()
}

#[cfg(test)]
mod durable_tests;
#[cfg(test)]
mod tests;
