//! The journal's rows (`scans` table) in memory: which scans a map holds, in which state.

use super::{StoreError, sql};
use rusqlite::Connection;
use std::collections::BTreeMap;
use std::path::Path;

/// The identity of a scan in a map: `(source, seq)`.
pub type ScanId = (String, u64);

/// The state of a journaled scan (`scans.status`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ScanStatus {
    /// Durable; evidence not yet in the blocks.
    Journaled = 0,
    /// Evidence in the blocks; raw scan kept.
    Applied = 1,
    /// Evidence in the blocks; raw scan pruned by retention.
    Pruned = 2,
    /// Evidence removed; the identity stays (never accepted again).
    Retracted = 3,
}

impl ScanStatus {
    pub fn from_code(code: i64) -> Option<Self> {
        Some(match code {
            0 => Self::Journaled,
            1 => Self::Applied,
            2 => Self::Pruned,
            3 => Self::Retracted,
            _ => return None,
        })
    }

    /// True when the scan's evidence is (or, once replayed, will be) part of the map.
    pub fn in_map(self) -> bool {
        !matches!(self, Self::Retracted)
    }

    /// True when the raw scan is stored.
    pub fn has_record(self) -> bool {
        matches!(self, Self::Journaled | Self::Applied)
    }
}

/// One journal row without its record.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JournalEntry {
    pub id: i64,
    pub stamp_nanos: i64,
    pub received_nanos: i64,
    pub status: ScanStatus,
    pub record_bytes: u64,
    pub crc32: u32,
}

/// Per-source counts of a journal.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SourceContent {
    /// Scans whose evidence is in the blocks (applied, with or without raw scan).
    pub applied: u64,
    /// Scans journaled, not yet integrated.
    pub pending: u64,
    /// Applied scans whose raw scan was pruned.
    pub pruned: u64,
    pub retracted: u64,
    pub highest_seq: Option<u64>,
    /// Sequence numbers missing between the lowest and the highest ever accepted.
    pub gaps: u64,
}

/// Every journal row of a map, by source and seq.
#[derive(Debug, Clone, Default)]
pub struct JournalIndex {
    sources: BTreeMap<String, SourceRows>,
}

/// One source's rows by seq, and their status counts for [`JournalIndex::content`], kept up to
/// date by every change of a row's status: the server publishes the content after every scan,
/// and counting a long-running map's whole journal each time grew with every scan ever received.
#[derive(Debug, Clone, Default)]
struct SourceRows {
    rows: BTreeMap<u64, JournalEntry>,
    counts: SourceContent,
}

/// Adds (`n` = 1) or takes away (`n` = −1) one row of `status` from `c`.
fn tally(c: &mut SourceContent, status: ScanStatus, n: i64) {
    let add = |v: &mut u64| *v = v.wrapping_add_signed(n);
    match status {
        ScanStatus::Journaled => add(&mut c.pending),
        ScanStatus::Applied => add(&mut c.applied),
        ScanStatus::Pruned => {
            add(&mut c.applied);
            add(&mut c.pruned);
        }
        ScanStatus::Retracted => add(&mut c.retracted),
    }
}

impl JournalIndex {
    /// Reads every row of the `scans` table.
    pub(super) fn read(conn: &Connection, path: &Path) -> Result<Self, StoreError> {
        let e = sql(path);
        let mut stmt = conn
            .prepare(
                "SELECT id, source, seq, stamp_nanos, received_nanos, status, record_bytes, crc32 FROM scans",
            )
            .map_err(&e)?;
        let mut rows = stmt.query([]).map_err(&e)?;
        let mut index = Self::default();
        while let Some(r) = rows.next().map_err(&e)? {
            let source: String = r.get(1).map_err(&e)?;
            let seq: i64 = r.get(2).map_err(&e)?;
            let code: i64 = r.get(5).map_err(&e)?;
            let bad = |reason: String| StoreError::CorruptRecord {
                path: path.to_path_buf(),
                source_name: source.clone(),
                seq: seq as u64,
                reason,
            };
            let status = ScanStatus::from_code(code).ok_or_else(|| bad(format!("unknown status {code}")))?;
            if seq < 0 {
                return Err(bad("negative seq".into()));
            }
            let entry = JournalEntry {
                id: r.get(0).map_err(&e)?,
                stamp_nanos: r.get(3).map_err(&e)?,
                received_nanos: r.get(4).map_err(&e)?,
                status,
                record_bytes: r.get::<_, i64>(6).map_err(&e)?.max(0) as u64,
                crc32: r.get::<_, i64>(7).map_err(&e)? as u32,
            };
            index.insert(source, seq as u64, entry);
        }
        Ok(index)
    }

    pub fn insert(&mut self, source: String, seq: u64, entry: JournalEntry) {
        let s = self.sources.entry(source).or_default();
        tally(&mut s.counts, entry.status, 1);
        if let Some(old) = s.rows.insert(seq, entry) {
            tally(&mut s.counts, old.status, -1);
        }
    }

    /// Sets a row's status; returns the row as it was, `None` if there is no such row.
    pub fn set_status(&mut self, source: &str, seq: u64, status: ScanStatus) -> Option<JournalEntry> {
        let s = self.sources.get_mut(source)?;
        let e = s.rows.get_mut(&seq)?;
        let old = *e;
        tally(&mut s.counts, old.status, -1);
        tally(&mut s.counts, status, 1);
        e.status = status;
        Some(old)
    }

    /// Sets a row's raw-scan size and checksum (a re-posed scan's new record); returns the old
    /// size, `None` if there is no such row.
    pub fn set_record(&mut self, source: &str, seq: u64, bytes: u64, crc32: u32) -> Option<u64> {
        let e = self.sources.get_mut(source)?.rows.get_mut(&seq)?;
        let old = e.record_bytes;
        (e.record_bytes, e.crc32) = (bytes, crc32);
        Some(old)
    }

    pub fn get(&self, source: &str, seq: u64) -> Option<&JournalEntry> {
        self.sources.get(source)?.rows.get(&seq)
    }

    pub fn contains(&self, source: &str, seq: u64) -> bool {
        self.get(source, seq).is_some()
    }

    /// Every row, by source then seq.
    pub fn iter(&self) -> impl Iterator<Item = (&str, u64, &JournalEntry)> {
        self.sources.iter().flat_map(|(s, m)| m.rows.iter().map(move |(q, e)| (s.as_str(), *q, e)))
    }

    /// The rows of one source.
    pub fn of_source(&self, source: &str) -> impl Iterator<Item = (u64, &JournalEntry)> {
        self.sources.get(source).into_iter().flat_map(|m| m.rows.iter().map(|(q, e)| (*q, e)))
    }

    pub fn len(&self) -> usize {
        self.sources.values().map(|s| s.rows.len()).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.sources.is_empty()
    }

    /// Bytes of raw scans stored (journaled and applied scans).
    pub fn record_bytes(&self) -> u64 {
        self.iter().filter(|(_, _, e)| e.status.has_record()).map(|(_, _, e)| e.record_bytes).sum()
    }

    /// Counts per source (in time of the number of sources, not of rows).
    pub fn content(&self) -> BTreeMap<String, SourceContent> {
        self.sources
            .iter()
            .map(|(source, s)| {
                let (mut c, seqs) = (s.counts.clone(), &s.rows);
                if let (Some((lo, _)), Some((hi, _))) = (seqs.first_key_value(), seqs.last_key_value()) {
                    c.highest_seq = Some(*hi);
                    c.gaps = (hi - lo + 1).saturating_sub(seqs.len() as u64);
                }
                (source.clone(), c)
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The counts kept up to date row by row equal a count of every row, after any sequence of
    /// inserts (new rows and replaced ones) and status changes.
    #[test]
    fn kept_counts_equal_a_recount() {
        let statuses =
            [ScanStatus::Journaled, ScanStatus::Applied, ScanStatus::Pruned, ScanStatus::Retracted];
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut index = JournalIndex::default();
        for step in 0..3000 {
            let source = ["a", "b", "c"][rng.random_range(0..3)].to_string();
            let seq = rng.random_range(0..200u64);
            let status = statuses[rng.random_range(0..4)];
            if rng.random_bool(0.5) {
                let entry = JournalEntry {
                    id: step,
                    stamp_nanos: 0,
                    received_nanos: 0,
                    status,
                    record_bytes: 10,
                    crc32: 0,
                };
                index.insert(source, seq, entry);
            } else {
                let had = index.contains(&source, seq);
                assert_eq!(index.set_status(&source, seq, status).is_some(), had);
            }
            if step % 100 == 0 {
                let mut recount: BTreeMap<String, SourceContent> = BTreeMap::new();
                for (s, _, e) in index.iter() {
                    tally(recount.entry(s.to_string()).or_default(), e.status, 1);
                }
                let kept = index.content();
                for (s, c) in &recount {
                    let k = &kept[s];
                    assert_eq!(
                        (k.applied, k.pending, k.pruned, k.retracted),
                        (c.applied, c.pending, c.pruned, c.retracted),
                        "source {s} at step {step}"
                    );
                }
                assert_eq!(kept.len(), recount.len());
            }
        }
    }
}
