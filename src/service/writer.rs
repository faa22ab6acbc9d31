//! The writer thread of one map: integrate journaled scans in batches, run the exact edits in
//! order with them, apply retention, publish snapshots and the updates that say what changed.
//!
//! It owns its work queue's vocabulary ([`Work`], [`Edit`]); the modules that fill the queue
//! (`ingest`, `edits`) depend on it, never the other way round.

use super::health::Faults;
use super::updates::{BlockVersions, MapUpdate, ScanPose, UpdateKind, UpdateRing};
use super::{Ack, Done, JournalStats, ServiceConfig, ServiceError, Shared, Snapshot};
use crate::core::{BlockKey, EvidenceMap, Pose};
use crate::store::{
    Change, DurableMap, OpError, Pending, Recovered, Retention, ScanId, ScanSelector, now_nanos,
};
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, TryRecvError};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::{Duration, Instant};

/// Most scans integrated (and committed) together.
const APPLY_BATCH: usize = 32;
/// How often time-based retention runs.
const PRUNE_EVERY: Duration = Duration::from_secs(10);

/// A journaled scan on its way to integration, with whoever waits for it.
pub(super) struct Waiting {
    pub pending: Pending,
    pub done: Option<Done>,
    pub dropped_points: usize,
}

/// An exact edit for a map's writer (validated by the `edits` module).
#[derive(Debug)]
pub(super) enum Edit {
    Retract(ScanSelector),
    Repose(Vec<(ScanId, Pose)>),
    Merge(PathBuf),
}

/// What the writer is asked to do, in order.
pub(super) enum Work {
    Scans(Vec<Waiting>),
    Edit(Edit, Box<dyn FnOnce(Result<Change, ServiceError>) + Send>),
}

pub(super) struct Writer {
    map: DurableMap,
    shared: Arc<Shared>,
    /// Journaled scans not yet integrated, and (in step) who waits for each.
    pending: Vec<Pending>,
    /// Who waits, dropped points, and whether the scan is counted in flight (it came from the
    /// journal thread, not from the replay on open).
    waiters: Vec<(Option<Done>, usize, bool)>,
    last_prune: Instant,
    retry: Duration,
    /// Snapshots replaced while readers still held them, and the last one replaced. The writer
    /// frees each once it holds the last reference, so a query never pays for freeing a whole
    /// map (thousands of block reference counts and the block table: milliseconds on a large
    /// map), or recycles it into the next snapshot ([`Self::recycled`]). The last one keeps
    /// the old copies of the blocks one publish changed alive until the next publish.
    retired: Mutex<Vec<Arc<Snapshot>>>,
    /// The last [`HISTORY`] publishes that moved the version: (from version, to version, the
    /// blocks changed), oldest first, for [`Self::recycled`].
    history: VecDeque<(u64, u64, Vec<BlockKey>)>,
}

/// Publishes remembered for recycling snapshots.
const HISTORY: usize = 64;

impl Writer {
    /// Replays the journaled scans of an opened map and sets up its shared state; a damaged
    /// map (corrupt blocks, unreadable journaled scans) is read-only.
    pub fn recover(
        recovered: Recovered,
        config: &ServiceConfig,
    ) -> Result<(Arc<Shared>, Self), ServiceError> {
        let Recovered { mut map, pending, lost } = recovered;
        let faults = Faults::new(config.write_retry);
        let mut left = Vec::new();
        if !map.corrupt().is_empty() {
            // Integrating next to a corrupt block would overwrite it: keep the scans journaled.
            left = pending;
        } else if !pending.is_empty()
            && let Err(e) = map.apply(&pending)
        {
            // Cannot write now (e.g. a full disk): serve what is integrated, retry later.
            faults.apply_failed(e.to_string());
            left = pending;
        }
        if let Some(c) = map.corrupt().first() {
            faults.set_damaged(format!(
                "{} corrupt blocks (first at ({}, {}, {}): {}); run `bgkmap check`",
                map.corrupt().len(),
                c.key.x,
                c.key.y,
                c.key.z,
                c.reason
            ));
        }
        if let Some(e) = lost.first() {
            faults.set_damaged(format!("{} acknowledged scans cannot be replayed: {e}", lost.len()));
        }
        // The per-block history is not stored: every block counts as changed at the version the
        // map opens at (see the `updates` module).
        let version = map.version();
        let block_versions: BlockVersions = map.map().blocks_unsorted().map(|(k, _)| (*k, version)).collect();
        // The first snapshot is the map as it is: changes count from here.
        map.take_changes();
        let snapshot = Snapshot {
            version,
            map: map.map().clone(),
            corrupt: Arc::new(map.corrupt().to_vec()),
            block_versions: Arc::new(block_versions),
            history_from: version,
        };
        let shared = Arc::new(Shared {
            snapshot: RwLock::new(Arc::new(snapshot)),
            queued: AtomicUsize::new(0),
            backlog: AtomicUsize::new(left.len()),
            integration_micros: AtomicU64::new(0),
            session: Mutex::new(BTreeMap::new()),
            stats: Mutex::new(JournalStats {
                content: Arc::new(map.journal().content()),
                journal_bytes: map.stored_bytes(),
                in_flight: BTreeMap::new(),
            }),
            faults,
            updates: UpdateRing::new(config.updates_capacity),
        });
        let waiters = left.iter().map(|_| (None, 0, false)).collect();
        let last_prune = Instant::now().checked_sub(PRUNE_EVERY).unwrap_or_else(Instant::now);
        let writer = Self {
            map,
            shared: shared.clone(),
            pending: left,
            waiters,
            last_prune,
            retired: Mutex::new(Vec::new()),
            history: VecDeque::new(),
            retry: config.write_retry,
        };
        Ok((shared, writer))
    }

    /// Runs until every sender is gone and all work is done (or cannot be written).
    pub fn run(mut self, rx: Receiver<Work>) {
        loop {
            let wait = if self.pending.is_empty() { PRUNE_EVERY } else { self.retry };
            match rx.recv_timeout(wait) {
                Ok(work) => self.take(work),
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
            while self.pending.len() < APPLY_BATCH {
                match rx.try_recv() {
                    Ok(work) => self.take(work),
                    Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
                }
            }
            self.flush();
            self.housekeeping();
        }
        self.flush();
        self.fail_waiters(|| ServiceError::ShuttingDown);
    }

    fn take(&mut self, work: Work) {
        match work {
            Work::Scans(w) => {
                for w in w {
                    self.pending.push(w.pending);
                    self.waiters.push((w.done, w.dropped_points, true));
                }
            }
            Work::Edit(edit, done) => {
                // Edits see every scan journaled before them.
                self.flush();
                if self.pending.is_empty() {
                    done(self.run_edit(edit));
                } else {
                    let reason = self.shared.faults.read_only().unwrap_or_default();
                    done(Err(ServiceError::ReadOnly { map: self.name(), reason }));
                }
            }
        }
    }

    /// Runs one edit on the writer's map and publishes the result.
    fn run_edit(&mut self, edit: Edit) -> Result<Change, ServiceError> {
        if let Some(reason) = self.shared.faults.read_only() {
            return Err(ServiceError::ReadOnly { map: self.name(), reason });
        }
        let result = match edit {
            Edit::Retract(sel) => self.map.retract(&sel),
            Edit::Repose(poses) => self.map.repose(&poses),
            Edit::Merge(path) => self.map.merge_from(&path),
        };
        match result {
            Ok(change) => {
                if change.scans > 0 || change.blocks_changed > 0 {
                    self.publish();
                }
                Ok(change)
            }
            Err(OpError::Refused(m)) => Err(ServiceError::Precondition(m)),
            Err(OpError::NotFound(m)) => Err(ServiceError::ScansNotFound(m)),
            Err(OpError::Invalid(m)) => Err(ServiceError::invalid("request", m)),
            Err(OpError::Store(e)) if e.is_corruption() => Err(e.into()),
            Err(OpError::Store(e)) => {
                let reason = e.to_string();
                self.shared.faults.apply_failed(reason.clone());
                Err(ServiceError::ReadOnly { map: self.name(), reason })
            }
        }
    }

    fn name(&self) -> String {
        self.map.path().file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
    }

    /// Integrates the pending scans (unless backing off after a failed write).
    fn flush(&mut self) {
        if self.pending.is_empty() || self.shared.faults.apply_backing_off() || !self.map.corrupt().is_empty()
        {
            return;
        }
        let t0 = Instant::now();
        match self.map.apply(&self.pending) {
            Ok(change) => {
                let us = t0.elapsed().as_micros() as u64;
                self.shared.integration_micros.fetch_add(us, Ordering::Relaxed);
                self.shared.faults.apply_ok();
                self.shared.backlog.fetch_sub(self.pending.len(), Ordering::Relaxed);
                // Out of `self` while publishing, which takes the map's change log.
                let (mut pending, waiters) =
                    (std::mem::take(&mut self.pending), std::mem::take(&mut self.waiters));
                let in_flight =
                    pending.iter().zip(&waiters).filter(|(_, w)| w.2).map(|(p, _)| p.source.as_str());
                let first = change.version - pending.len() as u64;
                let poses = pending
                    .iter()
                    .zip(first + 1..)
                    .map(|(p, version)| ScanPose {
                        version,
                        source: p.source.clone(),
                        seq: p.seq,
                        world_from_sensor: p.scan.world_from_sensor,
                    })
                    .collect();
                self.publish_applied(in_flight, poses);
                pending.clear();
                (self.pending, self.waiters) = (pending, waiters);
                for (done, dropped_points, _) in self.waiters.drain(..) {
                    if let Some(done) = done {
                        done(Ok(Ack {
                            applied: true,
                            integrated: true,
                            version: change.version,
                            dropped_points,
                        }));
                    }
                }
            }
            Err(e) => {
                let reason = e.to_string();
                self.shared.faults.apply_failed(reason.clone());
                let map = self.name();
                // The scans are durable; those waiting for integration learn it is delayed.
                self.fail_waiters(|| ServiceError::ReadOnly {
                    map: map.clone(),
                    reason: format!("journaled but not yet integrated: {reason}"),
                });
            }
        }
    }

    fn fail_waiters(&mut self, err: impl Fn() -> ServiceError) {
        for (done, _, _) in &mut self.waiters {
            if let Some(done) = done.take() {
                done(Err(err()));
            }
        }
    }

    /// The newest retired snapshot no reader holds, brought up to the writer's map by the
    /// blocks changed since its version ([`Self::history`]): the next snapshot's map and block
    /// versions without copying the whole block table and version map (milliseconds per scan
    /// on a large map, during which queries shared the cores with the copy). `None` when every
    /// retired snapshot is still read, or the history does not reach back to it.
    fn recycled(&mut self) -> Option<(EvidenceMap, BlockVersions)> {
        let free = {
            let mut retired = self.retired.lock().unwrap_or_else(PoisonError::into_inner);
            let newest = retired.iter().rposition(|s| Arc::strong_count(s) == 1)?;
            retired.remove(newest)
        };
        let snap = Arc::try_unwrap(free).ok()?;
        let start = self.history.iter().position(|(from, _, _)| *from == snap.version)?;
        let Snapshot { mut map, block_versions, .. } = snap;
        let mut bv = Arc::try_unwrap(block_versions).unwrap_or_else(|shared| BlockVersions::clone(&shared));
        let mut keys = Vec::new();
        for (_, to, changed) in self.history.range(start..) {
            bv.extend(changed.iter().map(|k| (*k, *to)));
            keys.extend_from_slice(changed);
        }
        keys.sort_unstable();
        keys.dedup();
        map.copy_blocks_from(self.map.map(), &keys);
        debug_assert!(map.shares_blocks_with(self.map.map()), "a recycled snapshot missed a change");
        Some((map, bv))
    }

    /// Publishes the map as it is now: the journal's content and, when the version moved, a new
    /// snapshot and an update for the map's subscribers.
    fn publish(&mut self) {
        self.publish_applied(std::iter::empty(), Vec::new());
    }

    /// Replaces the snapshot `old` by one of the map's new version, retires `old` and tells the
    /// subscribers which blocks changed and where the scans `poses` were taken.
    fn publish_snapshot(&mut self, old: Arc<Snapshot>, poses: Vec<ScanPose>) {
        let version = self.map.version();
        let noted = self.map.take_changes();
        let blocks = changed_blocks(&old.map, self.map.map(), noted);
        self.history.push_back((old.version, version, blocks.clone()));
        if self.history.len() > HISTORY {
            self.history.pop_front();
        }
        let next_versions = || {
            let mut bv = BlockVersions::clone(&old.block_versions);
            bv.extend(blocks.iter().map(|k| (*k, version)));
            bv
        };
        let (map, block_versions) = match self.recycled() {
            Some((map, bv)) => {
                debug_assert!(bv == next_versions(), "a recycled snapshot's block versions went astray");
                (map, bv)
            }
            None => (self.map.map().clone(), next_versions()),
        };
        let snap = Snapshot {
            version,
            map,
            corrupt: old.corrupt.clone(),
            block_versions: Arc::new(block_versions),
            history_from: old.history_from,
        };
        let from_version = old.version;
        drop(old);
        let replaced = std::mem::replace(
            &mut *self.shared.snapshot.write().unwrap_or_else(PoisonError::into_inner),
            Arc::new(snap),
        );
        {
            // Readers get snapshots only from `shared`, so a retired one whose only reference is
            // ours can gain no other: dropping it here frees it on this thread. The one just
            // replaced stays even so, to be recycled by the next publish.
            let mut retired = self.retired.lock().unwrap_or_else(PoisonError::into_inner);
            retired.retain(|s| Arc::strong_count(s) > 1);
            retired.push(replaced);
        }
        // After the snapshot: a subscriber never hears of a version it cannot read.
        let kind = UpdateKind::Live;
        let update = MapUpdate { kind, from_version, version, blocks, poses, reset: false };
        self.shared.updates.publish(update);
    }

    /// As [`Self::publish`], with the scans of `applied` sources (just integrated) no longer in
    /// flight and the `poses` of the scans just integrated.
    fn publish_applied<'a>(&mut self, applied: impl Iterator<Item = &'a str>, poses: Vec<ScanPose>) {
        let old = self.shared.snapshot();
        if self.map.version() > old.version {
            self.publish_snapshot(old, poses);
        } else {
            // Blocks change only with the version (every store commit moves it), so the
            // snapshot readers have is still the map: it stays.
            debug_assert!(old.map.shares_blocks_with(self.map.map()), "blocks changed without a new version");
        }
        let content = Arc::new(self.map.journal().content());
        let mut st = super::lock(&self.shared.stats);
        st.content = content;
        st.journal_bytes = self.map.stored_bytes();
        for source in applied {
            if let Some(n) = st.in_flight.get_mut(source) {
                *n = n.saturating_sub(1);
            }
        }
        st.in_flight.retain(|_, n| *n > 0);
    }

    /// Journal retention: after every batch for size limits, every [`PRUNE_EVERY`] for age.
    fn housekeeping(&mut self) {
        let due = match self.map_retention() {
            Retention::All => false,
            Retention::None | Retention::MaxAgeSeconds(_) => self.last_prune.elapsed() >= PRUNE_EVERY,
            Retention::MaxBytes(max) => self.map.stored_bytes() > max,
        };
        if !due || !self.pending.is_empty() {
            return;
        }
        self.last_prune = Instant::now();
        match self.map.prune(now_nanos()) {
            Ok(0) => {}
            Ok(_) => self.publish(),
            Err(e) => self.shared.faults.apply_failed(e.to_string()),
        }
    }

    fn map_retention(&self) -> Retention {
        self.map.retention()
    }
}

/// The sorted keys of the blocks that differ between two versions of a map. A change installs
/// new blocks for exactly the blocks whose evidence changed and shares the others, so comparing
/// block identities finds them without comparing evidence. `noted`, when known, holds every key
/// that may differ (sorted, from [`EvidenceMap::take_changes`]): only those are compared, so a
/// scan costs what it changed, not what the map holds.
fn changed_blocks(old: &EvidenceMap, new: &EvidenceMap, noted: Option<Vec<BlockKey>>) -> Vec<BlockKey> {
    if let Some(mut keys) = noted {
        keys.retain(|k| match (old.block(*k), new.block(*k)) {
            (Some(o), Some(n)) => !std::ptr::eq(o, n),
            (None, None) => false,
            _ => true,
        });
        return keys;
    }
    let mut keys: Vec<BlockKey> = new
        .blocks_unsorted()
        .filter(|(k, b)| old.block(**k).is_none_or(|o| !std::ptr::eq(o, *b)))
        .map(|(k, _)| *k)
        .collect();
    keys.extend(old.blocks_unsorted().filter(|(k, _)| new.block(**k).is_none()).map(|(k, _)| *k));
    keys.sort_unstable();
    keys
}
