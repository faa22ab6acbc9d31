//! The exact operations on a [`DurableMap`]: retract scans, re-pose scans, merge another map.
//!
//! Each recomputes the evidence of the scans involved from their journal records (so it needs
//! the raw scans: an operation that would need a pruned one is refused, naming it), builds the
//! change aside, and commits it in one transaction. The result is bit-identical to a map built
//! from scratch with the resulting set of scans, because evidence is an integer sum.

use super::StoreError;
use super::durable::{Change, DurableMap};
use super::file::{Commit, ImportedScan};
use super::journal::{JournalEntry, ScanId, ScanStatus};
use super::reader::{MapReader, bad_record};
use super::record::{encode_record, fingerprint};
use crate::core::{MapEdit, Pose, RawScan};
use std::path::Path;

/// Why an operation was refused or failed.
#[derive(Debug, thiserror::Error)]
pub enum OpError {
    /// It cannot be done exactly (raw scans pruned, conflicting scans, corrupt blocks, …).
    #[error("{0}")]
    Refused(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Which scans to retract: the listed ones, or those matching every given filter.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ScanSelector {
    pub scans: Vec<ScanId>,
    pub source: Option<String>,
    /// Scans with `stamp ≥ from` (Unix ns).
    pub from_stamp_nanos: Option<i64>,
    /// Scans with `stamp < to` (Unix ns).
    pub to_stamp_nanos: Option<i64>,
}

const NAMED: usize = 5;

/// "(a, 1), (b, 2), … and N more".
fn list(ids: &[ScanId]) -> String {
    let mut s: Vec<String> = ids.iter().take(NAMED).map(|(src, q)| format!("({src}, {q})")).collect();
    if ids.len() > NAMED {
        s.push(format!("and {} more", ids.len() - NAMED));
    }
    s.join(", ")
}

impl DurableMap {
    fn refuse_if_corrupt(&self) -> Result<(), OpError> {
        match self.corrupt.first() {
            None => Ok(()),
            Some(c) => Err(OpError::Refused(format!(
                "the map has {} corrupt blocks (first at ({}, {}, {})); changing it could not be exact — run `bgkmap check`",
                self.corrupt.len(),
                c.key.x,
                c.key.y,
                c.key.z
            ))),
        }
    }

    /// The applied scans a selector names, with their rows; errors name missing scans.
    fn select(&self, sel: &ScanSelector) -> Result<Vec<(ScanId, JournalEntry)>, OpError> {
        let filtered = sel.source.is_some() || sel.from_stamp_nanos.is_some() || sel.to_stamp_nanos.is_some();
        if sel.scans.is_empty() != filtered {
            return Err(OpError::Invalid(
                "give either a list of scans or a filter (source and/or stamp range), not both or neither"
                    .into(),
            ));
        }
        if !sel.scans.is_empty() {
            let mut out = Vec::new();
            let mut missing = Vec::new();
            for (s, q) in &sel.scans {
                match self.journal.get(s, *q) {
                    Some(e) if e.status.in_map() => out.push(((s.clone(), *q), *e)),
                    _ => missing.push((s.clone(), *q)),
                }
            }
            if !missing.is_empty() {
                return Err(OpError::NotFound(format!("scans not in the map: {}", list(&missing))));
            }
            out.sort_unstable_by_key(|(_, e)| e.id);
            out.dedup_by_key(|(_, e)| e.id);
            return Ok(out);
        }
        let in_range = |e: &JournalEntry| {
            sel.from_stamp_nanos.is_none_or(|f| e.stamp_nanos >= f)
                && sel.to_stamp_nanos.is_none_or(|t| e.stamp_nanos < t)
        };
        let rows: Box<dyn Iterator<Item = (&str, u64, &JournalEntry)>> = match &sel.source {
            Some(src) => Box::new(self.journal.of_source(src).map(move |(q, e)| (src.as_str(), q, e))),
            None => Box::new(self.journal.iter()),
        };
        let mut out: Vec<_> = rows
            .filter(|(_, _, e)| e.status.in_map() && in_range(e))
            .map(|(s, q, e)| ((s.to_string(), q), *e))
            .collect();
        out.sort_unstable_by_key(|(_, e)| e.id);
        Ok(out)
    }

    /// The verified raw scan of a row this map holds; refused when pruned.
    fn raw(&self, id: &ScanId, e: &JournalEntry) -> Result<RawScan, OpError> {
        self.file.record(&id.0, id.1, e)?.ok_or_else(|| {
            OpError::Refused(format!(
                "scan ({}, {}) has no raw scan (pruned by journal retention)",
                id.0, id.1
            ))
        })
    }

    fn refuse_pruned(&self, rows: &[(ScanId, JournalEntry)], what: &str) -> Result<(), OpError> {
        if let Some(((s, q), _)) = rows.iter().find(|(_, e)| e.status == ScanStatus::Journaled) {
            return Err(OpError::Refused(format!(
                "cannot {what} scan ({s}, {q}) yet: it is journaled but not integrated; try again"
            )));
        }
        let pruned: Vec<ScanId> =
            rows.iter().filter(|(_, e)| !e.status.has_record()).map(|(id, _)| id.clone()).collect();
        if pruned.is_empty() {
            return Ok(());
        }
        Err(OpError::Refused(format!(
            "cannot {what} exactly: {} of the scans have no raw scan any more (pruned by journal retention): {}",
            pruned.len(),
            list(&pruned)
        )))
    }

    fn delta_into(
        &mut self,
        edit: &mut MapEdit<'_>,
        id: &ScanId,
        scan: &RawScan,
        sign: i64,
    ) -> Result<(), OpError> {
        let bad = |e| OpError::Store(bad_record(self.file.path(), &id.0, id.1, e));
        if sign >= 0 {
            return scan.add_into(&mut self.integrator, edit, self.threads).map_err(bad);
        }
        let delta = scan.delta(&mut self.integrator, self.threads).map_err(bad)?;
        edit.add_delta(&delta, sign);
        self.integrator.recycle(delta);
        Ok(())
    }

    /// Removes the selected scans' evidence; they stay in the journal as retracted.
    pub fn retract(&mut self, sel: &ScanSelector) -> Result<Change, OpError> {
        self.refuse_if_corrupt()?;
        let rows = self.select(sel)?;
        if rows.is_empty() {
            return Ok(Change { version: self.version, ..Default::default() });
        }
        self.refuse_pruned(&rows, "retract")?;
        let base = self.map.clone();
        let mut edit = base.edit();
        for (id, e) in &rows {
            let scan = self.raw(id, e)?;
            self.delta_into(&mut edit, id, &scan, -1)?;
        }
        let blocks = edit.finish();
        let status = rows.iter().map(|(_, e)| (e.id, ScanStatus::Retracted)).collect();
        let version = self.version + 1;
        self.file.commit(&Commit { blocks: &blocks, status, version, ..Default::default() })?;
        let change =
            Change { scans: rows.len() as u64, shared: 0, blocks_changed: blocks.len() as u64, version };
        self.map.commit_edit(blocks);
        self.version = version;
        for ((s, q), _) in &rows {
            self.set_status(s, *q, ScanStatus::Retracted);
        }
        Ok(change)
    }

    /// Re-integrates scans under corrected poses: old evidence out, new evidence in.
    pub fn repose(&mut self, poses: &[(ScanId, Pose)]) -> Result<Change, OpError> {
        self.refuse_if_corrupt()?;
        let ids: Vec<ScanId> = poses.iter().map(|(id, _)| id.clone()).collect();
        let rows = self.select(&ScanSelector { scans: ids, ..Default::default() })?;
        if rows.len() != poses.len() {
            return Err(OpError::Invalid("a scan is listed twice".into()));
        }
        self.refuse_pruned(&rows, "re-pose")?;
        let base = self.map.clone();
        let mut edit = base.edit();
        let mut records = Vec::with_capacity(poses.len());
        for (id, pose) in poses {
            let Some((_, e)) = rows.iter().find(|(r, _)| r == id) else { continue };
            let old = self.raw(id, e)?;
            let new = old
                .reposed(*pose)
                .map_err(|err| OpError::Invalid(format!("pose of scan ({}, {}): {err}", id.0, id.1)))?;
            self.delta_into(&mut edit, id, &old, -1)?;
            self.delta_into(&mut edit, id, &new, 1)?;
            records.push((id.clone(), e.id, encode_record(&new), fingerprint(&id.0, id.1, &new)));
        }
        let blocks = edit.finish();
        let version = self.version + 1;
        let commit_records = records.iter().map(|(_, id, r, c)| (*id, r.clone(), *c)).collect();
        self.file.commit(&Commit {
            blocks: &blocks,
            records: commit_records,
            version,
            ..Default::default()
        })?;
        let change =
            Change { scans: records.len() as u64, shared: 0, blocks_changed: blocks.len() as u64, version };
        self.map.commit_edit(blocks);
        self.version = version;
        for ((s, q), _, r, crc) in records {
            if let Some(old) = self.journal.set_record(&s, q, r.len() as u64, crc) {
                self.stored_bytes = self.stored_bytes - old + r.len() as u64;
            }
        }
        Ok(change)
    }

    /// Adds the evidence of the map file at `other`, counting scans both maps hold once.
    pub fn merge_from(&mut self, other: &Path) -> Result<Change, OpError> {
        self.refuse_if_corrupt()?;
        let same = |a: &Path, b: &Path| {
            a.canonicalize().ok().zip(b.canonicalize().ok()).is_some_and(|(a, b)| a == b)
        };
        if same(other, self.file.path()) {
            return Err(OpError::Invalid("a map cannot be merged into itself".into()));
        }
        let reader = MapReader::open(other).map_err(|e| OpError::Invalid(e.to_string()))?;
        let diff = self.map.params().differences(reader.params());
        if !diff.is_empty() {
            return Err(OpError::Refused(format!(
                "cannot merge {}: map parameters differ ({})",
                other.display(),
                diff.join("; ")
            )));
        }
        reader.snapshot()?;
        let result = self.merge_reader(&reader);
        let _ = reader.end_snapshot();
        result
    }

    fn merge_reader(&mut self, reader: &MapReader) -> Result<Change, OpError> {
        let theirs = reader.journal()?;
        let base = self.map.clone();
        let mut edit = base.edit();
        let mut shared = Vec::new();
        let mut imports = Vec::new();
        let (mut conflicts, mut retracted, mut unrecoverable) = (Vec::new(), Vec::new(), Vec::new());
        for (s, q, e) in theirs.iter().filter(|(_, _, e)| e.status.in_map()) {
            let id = (s.to_string(), q);
            let Some(mine) = self.journal.get(s, q).copied() else {
                // Theirs only: import; a journaled one is replayed from its record.
                let record = reader.record(s, q, e)?;
                if e.status == ScanStatus::Journaled {
                    let scan =
                        record.clone().ok_or_else(|| super::reader::missing_record(reader.path(), s, q))?;
                    self.delta_into(&mut edit, &id, &scan, 1)?;
                }
                imports.push((id, *e, record));
                continue;
            };
            if mine.status == ScanStatus::Retracted {
                retracted.push(id);
            } else if mine.crc32 != e.crc32 {
                conflicts.push(id);
            } else if e.status != ScanStatus::Journaled {
                // In both maps' evidence: subtract one copy.
                let scan = match self.file.record(s, q, &mine)? {
                    Some(scan) => Some(scan),
                    None => reader.record(s, q, e)?,
                };
                match scan {
                    Some(scan) => self.delta_into(&mut edit, &id, &scan, -1)?,
                    None => unrecoverable.push(id.clone()),
                }
                shared.push(id);
            } else {
                shared.push(id);
            }
        }
        refuse_merge(&retracted, &conflicts, &unrecoverable)?;
        reader.for_each_block(|k, b| edit.add_block(k, &b, 1))?;
        self.commit_merge(edit, imports, shared.len() as u64)
    }

    fn commit_merge(
        &mut self,
        edit: MapEdit<'_>,
        imports: Vec<(ScanId, JournalEntry, Option<RawScan>)>,
        shared: u64,
    ) -> Result<Change, OpError> {
        let blocks = edit.finish();
        let keep_raw = self.retention != super::durable::Retention::None;
        let rows: Vec<ImportedScan> = imports
            .iter()
            .map(|((s, q), e, scan)| {
                let record = scan.as_ref().filter(|_| keep_raw).map(encode_record);
                let status = if record.is_some() { ScanStatus::Applied } else { ScanStatus::Pruned };
                let record_bytes = record.as_ref().map_or(e.record_bytes, |r| r.len() as u64);
                let entry = JournalEntry { status, record_bytes, ..*e };
                ImportedScan { source: s.clone(), seq: *q, entry, record }
            })
            .collect();
        let version = self.version + 1;
        let ids =
            self.file.commit(&Commit { blocks: &blocks, imports: &rows, version, ..Default::default() })?;
        let change =
            Change { scans: rows.len() as u64, shared, blocks_changed: blocks.len() as u64, version };
        self.map.commit_edit(blocks);
        self.version = version;
        for (row, id) in rows.into_iter().zip(ids) {
            self.note_journaled(&row.source, row.seq, JournalEntry { id, ..row.entry });
            if !row.entry.status.has_record() {
                self.stored_bytes -= row.entry.record_bytes;
            }
        }
        Ok(change)
    }
}

/// Refuses a merge that cannot count every scan exactly once.
fn refuse_merge(retracted: &[ScanId], conflicts: &[ScanId], unrecoverable: &[ScanId]) -> Result<(), OpError> {
    if !retracted.is_empty() {
        return Err(OpError::Refused(format!(
            "the other map holds scans this map retracted: {}; retract them there first",
            list(retracted)
        )));
    }
    if !conflicts.is_empty() {
        return Err(OpError::Refused(format!(
            "both maps hold these scans with different content (pose or points): {}; re-pose or retract them in one map first",
            list(conflicts)
        )));
    }
    if !unrecoverable.is_empty() {
        return Err(OpError::Refused(format!(
            "cannot merge exactly: {} scans are in both maps but neither kept their raw scan (pruned by journal retention): {}",
            unrecoverable.len(),
            list(unrecoverable)
        )));
    }
    Ok(())
}
