//! `bgkmap check`: verifies a map file — SQLite's own structure (`PRAGMA quick_check`), the
//! header and parameters, every block (checksum and encoding) and every journal record
//! (decoding and fingerprint), and that each journal row has a record exactly when its status
//! says so.

use super::journal::{JournalIndex, ScanId, ScanStatus};
use super::reader::{CorruptBlock, for_each_block, read_record};
use super::schema::{open_with, read_params, read_version};
use super::{StoreError, sql};
use rusqlite::OpenFlags;
use std::collections::BTreeMap;
use std::path::Path;

/// What `check` found.
#[derive(Debug, Clone, Default)]
pub struct CheckReport {
    /// The map version recorded in the file.
    pub version: u64,
    pub blocks: u64,
    pub corrupt_blocks: Vec<CorruptBlock>,
    /// Journal rows by status.
    pub scans: BTreeMap<&'static str, u64>,
    /// Bytes of raw scans stored.
    pub record_bytes: u64,
    pub corrupt_records: Vec<(ScanId, String)>,
    /// Anything else wrong (SQLite structure, parameters, records where none belong, …).
    pub problems: Vec<String>,
}

impl CheckReport {
    pub fn is_ok(&self) -> bool {
        self.corrupt_blocks.is_empty() && self.corrupt_records.is_empty() && self.problems.is_empty()
    }
}

fn status_name(s: ScanStatus) -> &'static str {
    match s {
        ScanStatus::Journaled => "journaled",
        ScanStatus::Applied => "applied",
        ScanStatus::Pruned => "pruned",
        ScanStatus::Retracted => "retracted",
    }
}

/// Verifies the map file at `path`. Errors only when it cannot be read as a map file at all.
pub fn check_map(path: &Path) -> Result<CheckReport, StoreError> {
    let conn = open_with(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)?;
    let e = sql(path);
    conn.execute_batch("BEGIN").map_err(&e)?;
    let mut report = CheckReport::default();
    let mut stmt = conn.prepare("PRAGMA quick_check").map_err(&e)?;
    let quick: Vec<String> =
        stmt.query_map([], |r| r.get(0)).map_err(&e)?.collect::<Result<_, _>>().map_err(&e)?;
    drop(stmt);
    if quick != ["ok"] {
        report.problems.extend(quick.into_iter().map(|m| format!("SQLite: {m}")));
    }
    if let Err(err) = read_params(&conn, path) {
        report.problems.push(err.to_string());
    }
    report.version = read_version(&conn, path)?;
    let mut blocks = 0u64;
    for_each_block(
        &conn,
        path,
        |_, _| blocks += 1,
        |key, reason| {
            report.corrupt_blocks.push(CorruptBlock { key, reason });
            Ok(())
        },
    )?;
    report.blocks = blocks + report.corrupt_blocks.len() as u64;
    match JournalIndex::read(&conn, path) {
        Ok(journal) => check_journal(&conn, path, &journal, &mut report)?,
        Err(err) => report.problems.push(err.to_string()),
    }
    conn.execute_batch("COMMIT").map_err(&e)?;
    Ok(report)
}

fn check_journal(
    conn: &rusqlite::Connection,
    path: &Path,
    journal: &JournalIndex,
    report: &mut CheckReport,
) -> Result<(), StoreError> {
    let e = sql(path);
    let mut with_record = std::collections::HashSet::new();
    for (source, seq, entry) in journal.iter() {
        *report.scans.entry(status_name(entry.status)).or_default() += 1;
        if entry.status.has_record() {
            with_record.insert(entry.id);
            report.record_bytes += entry.record_bytes;
            if let Err(err) = read_record(conn, path, source, seq, entry) {
                let reason = match err {
                    StoreError::CorruptRecord { reason, .. } => reason,
                    other => other.to_string(),
                };
                report.corrupt_records.push(((source.to_string(), seq), reason));
            }
        }
    }
    let mut stmt = conn.prepare("SELECT id FROM scan_records").map_err(&e)?;
    let ids: Vec<i64> =
        stmt.query_map([], |r| r.get(0)).map_err(&e)?.collect::<Result<_, _>>().map_err(&e)?;
    let stray = ids.iter().filter(|id| !with_record.contains(id)).count();
    if stray > 0 {
        report.problems.push(format!("{stray} scan records belong to no journaled or applied scan"));
    }
    Ok(())
}
