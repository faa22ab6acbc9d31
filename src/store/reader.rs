//! Reading a map file: header, parameters, blocks (checked), journal rows and records. Shared by
//! the read-only [`MapReader`] and the writable [`super::MapFile`].

use super::journal::{JournalEntry, JournalIndex, ScanStatus};
use super::record::{decode_record, fingerprint};
use super::schema::{open_with, read_params, read_version};
use super::{StoreError, decode_block, sql};
use crate::core::block::BlockEvidence;
use crate::core::{BlockKey, EvidenceMap, Integrator, MapParams, RawScan};
use rusqlite::{Connection, OpenFlags, OptionalExtension};
use std::path::{Path, PathBuf};

/// A block that failed its checksum or decoding.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CorruptBlock {
    pub key: BlockKey,
    pub reason: String,
}

/// A map file opened read-only (no lock needed: SQLite gives a consistent view per statement;
/// [`MapReader::snapshot`] pins one across several).
#[derive(Debug)]
pub struct MapReader {
    conn: Connection,
    path: PathBuf,
    params: MapParams,
}

impl MapReader {
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        let conn = open_with(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)?;
        let params = read_params(&conn, path)?;
        Ok(Self { conn, path: path.to_path_buf(), params })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn params(&self) -> &MapParams {
        &self.params
    }

    /// Starts a read transaction: every read until [`Self::end_snapshot`] sees one state of the
    /// file, even while a server writes to it.
    pub fn snapshot(&self) -> Result<(), StoreError> {
        self.conn.execute_batch("BEGIN").map_err(sql(&self.path))?;
        // A read transaction starts at its first read.
        read_version(&self.conn, &self.path).map(|_| ())
    }

    pub fn end_snapshot(&self) -> Result<(), StoreError> {
        self.conn.execute_batch("COMMIT").map_err(sql(&self.path))
    }

    /// Writes a compacted, consistent copy of the file to `dest` (which must not exist).
    pub fn copy_to(&self, dest: &Path) -> Result<(), StoreError> {
        let dest_str = dest.to_str().ok_or_else(|| StoreError::Io {
            path: dest.to_path_buf(),
            error: std::io::Error::other("the path is not valid UTF-8"),
        })?;
        self.conn.execute("VACUUM INTO ?1", [dest_str]).map(|_| ()).map_err(sql(dest))
    }

    pub fn version(&self) -> Result<u64, StoreError> {
        read_version(&self.conn, &self.path)
    }

    pub fn journal(&self) -> Result<JournalIndex, StoreError> {
        JournalIndex::read(&self.conn, &self.path)
    }

    /// Calls `f` for every block, verified; a corrupt block is an error.
    pub fn for_each_block(&self, f: impl FnMut(BlockKey, Box<BlockEvidence>)) -> Result<(), StoreError> {
        for_each_block(&self.conn, &self.path, f, |key, reason| Err(corrupt_block(&self.path, key, reason)))
    }

    /// The raw scan of a journal row (`None` when it has none), verified against its fingerprint.
    pub fn record(
        &self,
        source: &str,
        seq: u64,
        entry: &JournalEntry,
    ) -> Result<Option<RawScan>, StoreError> {
        read_record(&self.conn, &self.path, source, seq, entry)
    }

    /// The whole map: blocks plus the replayed evidence of journaled scans.
    pub fn load_map(&self) -> Result<EvidenceMap, StoreError> {
        self.snapshot()?;
        let result = (|| {
            let mut map = EvidenceMap::new(self.params);
            self.for_each_block(|k, b| map.insert_block(k, b))?;
            let journal = self.journal()?;
            let mut integ = Integrator::new(self.params);
            for (source, seq, e) in journal.iter().filter(|(_, _, e)| e.status == ScanStatus::Journaled) {
                let scan =
                    self.record(source, seq, e)?.ok_or_else(|| missing_record(&self.path, source, seq))?;
                scan.add_into(&mut integ, &mut map, 1)
                    .map_err(|err| bad_record(&self.path, source, seq, err))?;
            }
            Ok(map)
        })();
        let _ = self.end_snapshot();
        result
    }
}

pub(super) fn corrupt_block(path: &Path, key: BlockKey, reason: String) -> StoreError {
    StoreError::CorruptBlock { path: path.to_path_buf(), x: key.x, y: key.y, z: key.z, reason }
}

pub(super) fn bad_record(path: &Path, source: &str, seq: u64, reason: impl ToString) -> StoreError {
    StoreError::CorruptRecord {
        path: path.to_path_buf(),
        source_name: source.to_string(),
        seq,
        reason: reason.to_string(),
    }
}

pub(super) fn missing_record(path: &Path, source: &str, seq: u64) -> StoreError {
    bad_record(path, source, seq, "the raw scan of a journaled scan is missing")
}

/// Reads every block, calling `ok` for good ones and `bad` for those failing their checksum or
/// decoding (`bad` decides whether that ends the read).
pub(super) fn for_each_block(
    conn: &Connection,
    path: &Path,
    mut ok: impl FnMut(BlockKey, Box<BlockEvidence>),
    mut bad: impl FnMut(BlockKey, String) -> Result<(), StoreError>,
) -> Result<(), StoreError> {
    let e = sql(path);
    let mut stmt = conn.prepare("SELECT bx, by, bz, data, crc32 FROM blocks").map_err(&e)?;
    let mut rows = stmt.query([]).map_err(&e)?;
    while let Some(row) = rows.next().map_err(&e)? {
        let key = BlockKey::new(row.get(0).map_err(&e)?, row.get(1).map_err(&e)?, row.get(2).map_err(&e)?);
        let data = row.get_ref(3).map_err(&e)?.as_blob().unwrap_or(&[]);
        let crc: i64 = row.get(4).map_err(&e)?;
        if i64::from(crc32fast::hash(data)) != crc {
            bad(key, "checksum mismatch".into())?;
            continue;
        }
        match decode_block(data) {
            Ok(block) => ok(key, block),
            Err(reason) => bad(key, reason)?,
        }
    }
    Ok(())
}

/// Reads and verifies the record of a journal row.
pub(super) fn read_record(
    conn: &Connection,
    path: &Path,
    source: &str,
    seq: u64,
    entry: &JournalEntry,
) -> Result<Option<RawScan>, StoreError> {
    if !entry.status.has_record() {
        return Ok(None);
    }
    let data: Option<Vec<u8>> = conn
        .prepare_cached("SELECT record FROM scan_records WHERE id = ?1")
        .and_then(|mut s| s.query_row([entry.id], |r| r.get(0)).optional())
        .map_err(sql(path))?;
    let data = data.ok_or_else(|| missing_record(path, source, seq))?;
    let scan = decode_record(&data).map_err(|reason| bad_record(path, source, seq, reason))?;
    if fingerprint(source, seq, &scan) != entry.crc32 {
        return Err(bad_record(path, source, seq, "checksum mismatch"));
    }
    Ok(Some(scan))
}
