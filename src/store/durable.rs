//! [`DurableMap`]: a map file opened for writing together with its evidence in memory and its
//! journal index — the one implementation of integrating journaled scans, retention, and the
//! exact operations of [`super::edits`] (retract, re-pose, merge), used by the server's writer and
//! by the offline commands alike.
//!
//! Every change is computed aside ([`MapEdit`](crate::core::MapEdit)), committed to the file in
//! one transaction, and only then installed in memory; a failed commit changes nothing.

use super::StoreError;
use super::file::{Commit, MapFile};
use super::journal::{JournalEntry, JournalIndex, ScanStatus};
use super::lock::MapLock;
use super::reader::{CorruptBlock, bad_record, missing_record};
use crate::core::{BlockKey, BlockSink, EvidenceMap, Integrator, RawScan, Workers, integrate_parallel};
use std::path::Path;

/// How long raw scans stay in the journal once their evidence is applied.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Retention {
    /// Keep every raw scan (default): every operation stays exact.
    #[default]
    All,
    /// Keep none: raw scans are dropped as they are applied.
    None,
    /// Keep the raw scans received in the last this many seconds.
    MaxAgeSeconds(u64),
    /// Keep at most this many bytes of raw scans (the oldest go first).
    MaxBytes(u64),
}

impl std::str::FromStr for Retention {
    type Err = String;

    /// `all`, `none`, an age (`7d`, `12h`, `30m`, `90s`) or a size (`500MB`, `2GiB`, `1000000B`).
    fn from_str(s: &str) -> Result<Self, String> {
        let t = s.trim();
        match t.to_ascii_lowercase().as_str() {
            "all" => return Ok(Self::All),
            "none" => return Ok(Self::None),
            _ => {}
        }
        let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.')).unwrap_or(t.len());
        let (num, unit) = t.split_at(split);
        let n: f64 = num.parse().map_err(|_| format!("journal retention {s:?}: expected all, none, an age (7d, 12h, 30m, 90s) or a size (500MB, 2GiB)"))?;
        let scale = |k: f64| {
            let v = n * k;
            if (0.0..1.8e19).contains(&v) {
                Ok(v as u64)
            } else {
                Err(format!("journal retention {s:?} is out of range"))
            }
        };
        match unit.trim() {
            "d" => scale(86_400.0).map(Self::MaxAgeSeconds),
            "h" => scale(3_600.0).map(Self::MaxAgeSeconds),
            "m" => scale(60.0).map(Self::MaxAgeSeconds),
            "s" => scale(1.0).map(Self::MaxAgeSeconds),
            "B" => scale(1.0).map(Self::MaxBytes),
            "KB" => scale(1e3).map(Self::MaxBytes),
            "MB" => scale(1e6).map(Self::MaxBytes),
            "GB" => scale(1e9).map(Self::MaxBytes),
            "TB" => scale(1e12).map(Self::MaxBytes),
            "KiB" => scale(1024.0).map(Self::MaxBytes),
            "MiB" => scale(1024.0 * 1024.0).map(Self::MaxBytes),
            "GiB" => scale(1024.0 * 1024.0 * 1024.0).map(Self::MaxBytes),
            "TiB" => scale(1024.0f64.powi(4)).map(Self::MaxBytes),
            other => Err(format!(
                "journal retention {s:?}: unknown unit {other:?} (d, h, m, s, B, KB, MB, GB, TB, KiB, MiB, GiB, TiB)"
            )),
        }
    }
}

/// A journaled scan waiting to be integrated.
#[derive(Debug, Clone)]
pub struct Pending {
    pub source: String,
    pub seq: u64,
    pub entry: JournalEntry,
    pub scan: RawScan,
}

/// What an operation changed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Change {
    /// Scans integrated, retracted, re-posed, or added by a merge.
    pub scans: u64,
    /// Merge only: scans both maps held (counted once).
    pub shared: u64,
    pub blocks_changed: u64,
    /// The map version after the change.
    pub version: u64,
}

/// A writable map: file (locked), evidence, journal index.
#[derive(Debug)]
pub struct DurableMap {
    pub(super) file: MapFile,
    pub(super) map: EvidenceMap,
    pub(super) corrupt: Vec<CorruptBlock>,
    pub(super) journal: JournalIndex,
    pub(super) version: u64,
    pub(super) integrator: Integrator,
    /// One integrator per thread for batches of scans, and their threads (started on first use).
    workers: Option<Workers>,
    pub(super) threads: usize,
    pub(super) retention: Retention,
    /// Bytes of raw scans stored (journaled and applied rows).
    pub(super) stored_bytes: u64,
    _lock: MapLock,
}

/// An opened map and what its journal still has to replay.
#[derive(Debug)]
pub struct Recovered {
    pub map: DurableMap,
    /// Journaled scans not yet integrated, in journal order.
    pub pending: Vec<Pending>,
    /// Journaled scans whose record is damaged (acknowledged data that cannot be replayed).
    pub lost: Vec<StoreError>,
}

impl DurableMap {
    /// Takes the writer lock, opens and loads `path`; journaled scans are returned for replay.
    pub fn open(path: &Path, threads: usize, retention: Retention) -> Result<Recovered, StoreError> {
        let lock = MapLock::acquire(path)?;
        let opened = MapFile::open(path)?;
        let mut pending = Vec::new();
        let mut lost = Vec::new();
        for (source, seq, e) in opened.journal.iter().filter(|(_, _, e)| e.status == ScanStatus::Journaled) {
            match opened.file.record(source, seq, e) {
                Ok(Some(scan)) => pending.push(Pending { source: source.into(), seq, entry: *e, scan }),
                Ok(None) => lost.push(missing_record(path, source, seq)),
                Err(err) => lost.push(err),
            }
        }
        pending.sort_by_key(|p| p.entry.id);
        let params = *opened.map.params();
        let stored_bytes = opened.journal.record_bytes();
        let map = DurableMap {
            file: opened.file,
            map: opened.map,
            corrupt: opened.corrupt,
            journal: opened.journal,
            version: opened.version,
            integrator: Integrator::new(params),
            workers: None,
            threads: threads.max(1),
            retention,
            stored_bytes,
            _lock: lock,
        };
        Ok(Recovered { map, pending, lost })
    }

    /// Opens `path` and integrates its journaled scans (the offline commands' way in); a damaged
    /// journaled scan is an error.
    pub fn open_recovered(path: &Path) -> Result<Self, StoreError> {
        let Recovered { mut map, pending, lost } = Self::open(path, 1, Retention::All)?;
        if let Some(err) = lost.into_iter().next() {
            return Err(err);
        }
        if let Some(err) = map.corrupt.first() {
            return Err(super::reader::corrupt_block(map.file.path(), err.key, err.reason.clone()));
        }
        if !pending.is_empty() {
            map.apply(&pending)?;
        }
        Ok(map)
    }

    pub fn map(&self) -> &EvidenceMap {
        &self.map
    }

    /// The blocks that may have changed since the last call (see [`EvidenceMap::take_changes`]).
    pub fn take_changes(&mut self) -> Option<Vec<BlockKey>> {
        self.map.take_changes()
    }

    pub fn version(&self) -> u64 {
        self.version
    }

    pub fn journal(&self) -> &JournalIndex {
        &self.journal
    }

    pub fn corrupt(&self) -> &[CorruptBlock] {
        &self.corrupt
    }

    pub fn path(&self) -> &Path {
        self.file.path()
    }

    pub fn stored_bytes(&self) -> u64 {
        self.stored_bytes
    }

    pub fn retention(&self) -> Retention {
        self.retention
    }

    pub fn set_retention(&mut self, retention: Retention) {
        self.retention = retention;
    }

    /// Closes the file (flushing it).
    pub fn close(self) -> Result<(), StoreError> {
        self.file.close()
    }

    /// Records a row journaled through another connection (the server's journal writer).
    pub fn note_journaled(&mut self, source: &str, seq: u64, entry: JournalEntry) {
        self.stored_bytes += entry.record_bytes;
        self.journal.insert(source.to_string(), seq, entry);
    }

    /// Integrates journaled scans: their evidence and status go to the file in one transaction,
    /// then into memory. On error nothing changed (the scans stay journaled).
    pub fn apply(&mut self, scans: &[Pending]) -> Result<Change, StoreError> {
        let path = self.file.path().to_path_buf();
        if let Some(c) = self.corrupt.first() {
            // The block's true content is unknown: adding to it would overwrite it.
            return Err(super::reader::corrupt_block(&path, c.key, c.reason.clone()));
        }
        let mut edit = self.map.edit();
        if self.threads > 1 && scans.len() > 1 {
            // Several scans: one per thread at a time (integer evidence: any order, same bits).
            let params = *self.map.params();
            let threads = self.threads;
            let workers = self.workers.get_or_insert_with(|| Workers::new(params, threads));
            let add = |integ: &mut Integrator, p: &Pending, sink: &mut dyn BlockSink| {
                p.scan.add_into(integ, sink, 1).map_err(|e| bad_record(&path, &p.source, p.seq, e))
            };
            integrate_parallel(workers, scans, &mut edit, add)?;
        } else {
            for p in scans {
                p.scan
                    .add_into(&mut self.integrator, &mut edit, self.threads)
                    .map_err(|e| bad_record(&path, &p.source, p.seq, e))?;
            }
        }
        let blocks = edit.finish();
        let applied =
            if self.retention == Retention::None { ScanStatus::Pruned } else { ScanStatus::Applied };
        let status = scans.iter().map(|p| (p.entry.id, applied)).collect();
        let version = self.version + scans.len() as u64;
        self.file.commit(&Commit { blocks: &blocks, status, version, ..Default::default() })?;
        let change =
            Change { scans: scans.len() as u64, shared: 0, blocks_changed: blocks.len() as u64, version };
        self.map.commit_edit(blocks);
        self.version = version;
        for p in scans {
            if !self.journal.contains(&p.source, p.seq) {
                self.note_journaled(&p.source, p.seq, p.entry);
            }
            self.set_status(&p.source, p.seq, applied);
        }
        Ok(change)
    }

    /// Updates a row's status in the index (and the stored-bytes count).
    pub(super) fn set_status(&mut self, source: &str, seq: u64, status: ScanStatus) {
        if let Some(old) = self.journal.set_status(source, seq, status)
            && old.status.has_record()
            && !status.has_record()
        {
            self.stored_bytes = self.stored_bytes.saturating_sub(old.record_bytes);
        }
    }

    /// Applies the retention policy at `now_nanos`: drops raw scans of applied scans that fall
    /// outside it. Returns how many were pruned.
    pub fn prune(&mut self, now_nanos: i64) -> Result<u64, StoreError> {
        let applied = || self.journal.iter().filter(|(_, _, e)| e.status == ScanStatus::Applied);
        let mut victims: Vec<(String, u64, i64)> = match self.retention {
            Retention::All => return Ok(0),
            Retention::None => applied().map(|(s, q, e)| (s.to_string(), q, e.id)).collect(),
            Retention::MaxAgeSeconds(secs) => {
                let cutoff = now_nanos
                    .saturating_sub(i64::try_from(secs).unwrap_or(i64::MAX).saturating_mul(1_000_000_000));
                applied()
                    .filter(|(_, _, e)| e.received_nanos < cutoff)
                    .map(|(s, q, e)| (s.to_string(), q, e.id))
                    .collect()
            }
            Retention::MaxBytes(max) => {
                if self.stored_bytes <= max {
                    return Ok(0);
                }
                let mut rows: Vec<_> =
                    applied().map(|(s, q, e)| (e.id, s.to_string(), q, e.record_bytes)).collect();
                rows.sort_unstable_by_key(|r| r.0);
                let mut excess = self.stored_bytes - max;
                rows.into_iter()
                    .take_while(|r| {
                        let take = excess > 0;
                        excess = excess.saturating_sub(r.3);
                        take
                    })
                    .map(|(id, s, q, _)| (s, q, id))
                    .collect()
            }
        };
        if victims.is_empty() {
            return Ok(0);
        }
        victims.sort_unstable_by_key(|v| v.2);
        let status = victims.iter().map(|v| (v.2, ScanStatus::Pruned)).collect();
        self.file.commit(&Commit { status, version: self.version, ..Default::default() })?;
        for (s, q, _) in &victims {
            self.set_status(s, *q, ScanStatus::Pruned);
        }
        Ok(victims.len() as u64)
    }
}
