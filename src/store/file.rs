//! A map file opened for writing in place (WAL, `synchronous = FULL`): journal new scans, and
//! commit changes (blocks, journal statuses, records, imported rows, the map version) in one
//! transaction each.

use super::journal::{JournalEntry, JournalIndex, ScanStatus};
use super::reader::{CorruptBlock, for_each_block, read_record};
use super::record::{encode_record, fingerprint};
use super::schema::{create_schema, open_with, read_params, read_version};
use super::{StoreError, encode_block, sql};
use crate::core::{EditedBlocks, EvidenceMap, MapParams, RawScan};
use rusqlite::{Connection, OpenFlags, Transaction, TransactionBehavior, params};
use std::path::{Path, PathBuf};

/// A scan to journal.
#[derive(Debug, Clone)]
pub struct NewScan {
    pub source: String,
    pub seq: u64,
    /// The scan's time (Unix ns): the client's stamp, else the arrival time.
    pub stamp_nanos: i64,
    pub received_nanos: i64,
    pub scan: RawScan,
}

/// A journal row copied from another map (merge), with its record if it has one.
#[derive(Debug, Clone)]
pub struct ImportedScan {
    pub source: String,
    pub seq: u64,
    pub entry: JournalEntry,
    pub record: Option<Vec<u8>>,
}

/// One atomic change of a map file.
#[derive(Debug, Default)]
pub struct Commit<'a> {
    /// Blocks to write (`None` deletes the row).
    pub blocks: &'a [(crate::core::BlockKey, Option<std::sync::Arc<crate::core::block::BlockEvidence>>)],
    /// New statuses of journal rows by id; `Pruned` and `Retracted` also drop the record.
    pub status: Vec<(i64, ScanStatus)>,
    /// Replaced records (re-posed scans): id, encoded record, fingerprint.
    pub records: Vec<(i64, Vec<u8>, u32)>,
    /// Rows to add (merge); they get new ids, returned by [`MapFile::commit`].
    pub imports: &'a [ImportedScan],
    /// The map version to record.
    pub version: u64,
}

/// A map file opened for writing, with what it holds.
#[derive(Debug)]
pub struct OpenedMap {
    pub file: MapFile,
    /// Every block that passed its checks.
    pub map: EvidenceMap,
    /// Blocks that failed their checks (absent from `map`).
    pub corrupt: Vec<CorruptBlock>,
    pub journal: JournalIndex,
    pub version: u64,
}

/// A writable map file. Hold its [`super::lock::MapLock`] while it is open.
#[derive(Debug)]
pub struct MapFile {
    pub(super) conn: Connection,
    path: PathBuf,
}

impl MapFile {
    /// Creates a new, empty map file; refuses to replace an existing file.
    pub fn create(path: &Path, map_params: &MapParams) -> Result<Self, StoreError> {
        if path.exists() {
            let error = std::io::Error::new(std::io::ErrorKind::AlreadyExists, "map file already exists");
            return Err(StoreError::Io { path: path.to_path_buf(), error });
        }
        let tmp = super::temp_sibling(path);
        let _ = std::fs::remove_file(&tmp);
        let result = (|| {
            let mut conn = Connection::open(&tmp).map_err(sql(&tmp))?;
            create_schema(&mut conn, &tmp, map_params)?;
            conn.close().map_err(|(_, err)| sql(&tmp)(err))?;
            std::fs::rename(&tmp, path).map_err(|error| StoreError::Io { path: path.to_path_buf(), error })
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        result?;
        Self::connect(path)
    }

    /// A writable connection (WAL, `synchronous = FULL`) without loading anything.
    pub fn connect(path: &Path) -> Result<Self, StoreError> {
        let conn = open_with(path, OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_NO_MUTEX)?;
        conn.execute_batch("PRAGMA journal_mode = WAL; PRAGMA synchronous = FULL;").map_err(sql(path))?;
        Ok(Self { conn, path: path.to_path_buf() })
    }

    /// Opens an existing map file for writing and loads it. Corrupt blocks are reported, not
    /// fatal (the map answers DATA_LOSS around them).
    pub fn open(path: &Path) -> Result<OpenedMap, StoreError> {
        let file = Self::connect(path)?;
        let mut map = EvidenceMap::new(read_params(&file.conn, path)?);
        let mut corrupt = Vec::new();
        for_each_block(
            &file.conn,
            path,
            |k, b| map.insert_block(k, b),
            |key, reason| {
                corrupt.push(CorruptBlock { key, reason });
                Ok(())
            },
        )?;
        let journal = JournalIndex::read(&file.conn, path)?;
        let version = read_version(&file.conn, path)?;
        Ok(OpenedMap { file, map, corrupt, journal, version })
    }

    /// Wraps a connection to a file whose schema is already written.
    pub(super) fn from_conn(conn: Connection, path: &Path) -> Self {
        Self { conn, path: path.to_path_buf() }
    }

    /// Closes the file, reporting a failure to flush it.
    pub fn close(self) -> Result<(), StoreError> {
        let path = self.path;
        self.conn.close().map_err(|(_, err)| sql(&path)(err))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Limits the file to `pages` database pages (`PRAGMA max_page_count`, this connection
    /// only): writes beyond fail as on a full disk.
    pub fn set_max_pages(&self, pages: u64) -> Result<(), StoreError> {
        self.conn
            .pragma_update(None, "max_page_count", i64::try_from(pages).unwrap_or(i64::MAX))
            .map_err(sql(&self.path))
    }

    /// The verified raw scan of a journal row (`None` when pruned or retracted).
    pub fn record(
        &self,
        source: &str,
        seq: u64,
        entry: &JournalEntry,
    ) -> Result<Option<RawScan>, StoreError> {
        read_record(&self.conn, &self.path, source, seq, entry)
    }

    /// Journals scans (status journaled) in one durable transaction. Per scan: its new row, or
    /// `None` when the map already has that `(source, seq)` (a duplicate; nothing written).
    pub fn journal(&mut self, scans: &[NewScan]) -> Result<Vec<Option<JournalEntry>>, StoreError> {
        let e = sql(&self.path);
        let encoded: Vec<(Vec<u8>, u32)> =
            scans.iter().map(|s| (encode_record(&s.scan), fingerprint(&s.source, s.seq, &s.scan))).collect();
        // IMMEDIATE takes the write lock up front: a writer on another connection of the same
        // file (the server journals and integrates on two) waits for it instead of failing.
        let tx = self.conn.transaction_with_behavior(TransactionBehavior::Immediate).map_err(&e)?;
        let mut out = Vec::with_capacity(scans.len());
        for (s, (record, crc)) in scans.iter().zip(&encoded) {
            let entry = JournalEntry {
                id: 0,
                stamp_nanos: s.stamp_nanos,
                received_nanos: s.received_nanos,
                status: ScanStatus::Journaled,
                record_bytes: record.len() as u64,
                crc32: *crc,
            };
            out.push(insert_row(&tx, &self.path, &s.source, s.seq, entry, Some(record))?);
        }
        tx.commit().map_err(&e)?;
        Ok(out)
    }

    /// Applies one change atomically; returns the ids of the imported rows, in order.
    pub fn commit(&mut self, c: &Commit<'_>) -> Result<Vec<i64>, StoreError> {
        let e = sql(&self.path);
        let tx = self.conn.transaction_with_behavior(TransactionBehavior::Immediate).map_err(&e)?;
        write_blocks(&tx, &self.path, c.blocks)?;
        {
            let mut status = tx.prepare_cached("UPDATE scans SET status = ?2 WHERE id = ?1").map_err(&e)?;
            let mut drop_record = tx.prepare_cached("DELETE FROM scan_records WHERE id = ?1").map_err(&e)?;
            for (id, s) in &c.status {
                status.execute(params![id, *s as i64]).map_err(&e)?;
                if !s.has_record() {
                    drop_record.execute([id]).map_err(&e)?;
                }
            }
            let mut row = tx
                .prepare_cached("UPDATE scans SET record_bytes = ?2, crc32 = ?3 WHERE id = ?1")
                .map_err(&e)?;
            let mut rec = tx
                .prepare_cached("INSERT OR REPLACE INTO scan_records (id, record) VALUES (?1, ?2)")
                .map_err(&e)?;
            for (id, record, crc) in &c.records {
                row.execute(params![id, record.len() as i64, i64::from(*crc)]).map_err(&e)?;
                rec.execute(params![id, record]).map_err(&e)?;
            }
        }
        let mut ids = Vec::with_capacity(c.imports.len());
        for s in c.imports {
            let inserted = insert_row(&tx, &self.path, &s.source, s.seq, s.entry, s.record.as_deref())?;
            let entry = inserted.ok_or_else(|| StoreError::CorruptRecord {
                path: self.path.clone(),
                source_name: s.source.clone(),
                seq: s.seq,
                reason: "imported scan is already in the journal".into(),
            })?;
            ids.push(entry.id);
        }
        set_version(&tx, &self.path, c.version)?;
        tx.commit().map_err(&e)?;
        Ok(ids)
    }
}

/// Inserts a journal row (and its record); `None` when `(source, seq)` is already there.
fn insert_row(
    tx: &Transaction<'_>,
    path: &Path,
    source: &str,
    seq: u64,
    mut entry: JournalEntry,
    record: Option<&[u8]>,
) -> Result<Option<JournalEntry>, StoreError> {
    let e = sql(path);
    let mut row = tx
        .prepare_cached(
            "INSERT INTO scans (source, seq, stamp_nanos, received_nanos, status, record_bytes, crc32)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7) ON CONFLICT (source, seq) DO NOTHING",
        )
        .map_err(&e)?;
    let n = row
        .execute(params![
            source,
            seq as i64,
            entry.stamp_nanos,
            entry.received_nanos,
            entry.status as i64,
            entry.record_bytes as i64,
            i64::from(entry.crc32)
        ])
        .map_err(&e)?;
    if n == 0 {
        return Ok(None);
    }
    entry.id = tx.last_insert_rowid();
    if let (Some(record), true) = (record, entry.status.has_record()) {
        tx.prepare_cached("INSERT INTO scan_records (id, record) VALUES (?1, ?2)")
            .and_then(|mut s| s.execute(params![entry.id, record]))
            .map_err(&e)?;
    }
    Ok(Some(entry))
}

/// Upserts or deletes blocks.
fn write_blocks(
    tx: &Transaction<'_>,
    path: &Path,
    blocks: &[(crate::core::BlockKey, Option<std::sync::Arc<crate::core::block::BlockEvidence>>)],
) -> Result<(), StoreError> {
    let e = sql(path);
    let mut upsert = tx
        .prepare_cached(
            "INSERT INTO blocks (bx, by, bz, data, crc32) VALUES (?1, ?2, ?3, ?4, ?5)
             ON CONFLICT (bx, by, bz) DO UPDATE SET data = excluded.data, crc32 = excluded.crc32",
        )
        .map_err(&e)?;
    let mut delete =
        tx.prepare_cached("DELETE FROM blocks WHERE bx = ?1 AND by = ?2 AND bz = ?3").map_err(&e)?;
    let mut buf = Vec::new();
    for (key, block) in blocks {
        match block.as_deref().filter(|b| !b.is_empty()) {
            Some(b) => {
                buf.clear();
                encode_block(b, &mut buf);
                upsert.execute(params![key.x, key.y, key.z, &buf, crc32fast::hash(&buf)]).map_err(&e)?;
            }
            None => {
                delete.execute(params![key.x, key.y, key.z]).map_err(&e)?;
            }
        }
    }
    Ok(())
}

fn set_version(tx: &Transaction<'_>, path: &Path, version: u64) -> Result<(), StoreError> {
    tx.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('version', ?1)", [version.to_string()])
        .map(|_| ())
        .map_err(sql(path))
}

/// Writes a whole new map file (rollback journal; the caller renames it into place).
pub(super) fn write_new(
    path: &Path,
    map: &EvidenceMap,
    scans: &[NewScan],
    version: u64,
) -> Result<(), StoreError> {
    let _ = std::fs::remove_file(path);
    let mut conn = Connection::open(path).map_err(sql(path))?;
    create_schema(&mut conn, path, map.params())?;
    let mut file = MapFile::from_conn(conn, path);
    let ids = file.journal(scans)?;
    let keys = map.block_keys_sorted();
    let blocks: EditedBlocks = keys.iter().map(|k| (*k, map.block_arc(*k))).collect();
    let status = ids.iter().flatten().map(|e| (e.id, ScanStatus::Applied)).collect();
    file.commit(&Commit { blocks: &blocks, status, version, ..Default::default() })?;
    file.close()
}
