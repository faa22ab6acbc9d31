//! The updates of a map (its change stream): which blocks changed at which version, for caches
//! kept elsewhere (a planner's local copy of a region, the web viewer, zenoh subscribers). The
//! transports put them on the wire as gRPC `WatchUpdates`, HTTP `…/updates` (SSE) and zenoh
//! `bgkmap/<map>/updates`.
//!
//! Every published change of the map — a batch of integrated scans (the version moves up by one
//! per scan), a merge, a retraction or a re-pose (one each) — produces one [`MapUpdate`]: the
//! versions it spans, the sorted keys of the blocks whose evidence changed, and the sensor poses
//! of the scans it integrated. There are two ways to follow the map:
//! - **From the snapshot** ([`MapService::changes_since`]). Every snapshot carries, per block,
//!   the version at which that block last changed ([`BlockVersions`], which also keeps blocks
//!   that lost all evidence), so "the blocks changed since version N" is answered for any N
//!   from the current state alone: a late subscriber catches up without any history.
//! - **Live** ([`MapService::watch`]): a [`Subscription`] that yields updates in version order,
//!   starting with the catch-up since the version asked for. The map keeps only the last
//!   [`ServiceConfig::updates_capacity`](super::ServiceConfig) updates in one shared ring, so the
//!   writer never waits for a reader and memory stays bounded. A subscriber that falls further
//!   behind is resynchronised from the snapshot (an update of kind [`UpdateKind::Resync`]
//!   carrying every block changed since its last version): it never silently misses a block.
//!
//! Waiting is runtime-neutral: [`Subscription::poll_next`] takes a `std::task::Context` (any
//! async runtime), [`Subscription::next_timeout`] blocks a thread.
//!
//! The per-block history is not stored in the map file: after a restart (versions resume from
//! the file) every stored block counts as changed at the version the map was opened at
//! ([`Snapshot::history_from`]). Blocks removed before the restart are not known any more, so a
//! `since` older than that is answered with every block the map holds and
//! [`MapUpdate::reset`] set: the cache must drop every block not listed. A subscriber never
//! silently misses a block.

use super::{MapService, ServiceError, Shared, Snapshot};
use crate::core::{BlockKey, CellKey, Pose};
use rustc_hash::FxHashMap;
use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::task::{Context, Poll, Waker};
use std::time::{Duration, Instant};

/// Per block, the map version at which its evidence last changed (blocks that lost all
/// evidence stay listed).
pub type BlockVersions = FxHashMap<BlockKey, u64>;

/// Where a scan's sensor was when it was integrated.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanPose {
    /// The map version this scan produced.
    pub version: u64,
    pub source: String,
    pub seq: u64,
    pub world_from_sensor: Pose,
}

/// How an update came about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UpdateKind {
    /// The first answer of a watch: every block changed since the version asked for.
    CatchUp,
    /// One published change (a batch of scans, a merge, a retraction, a re-pose).
    Live,
    /// The subscriber fell behind the ring; every block changed since its last version.
    Resync,
}

/// The blocks that changed between `from_version` (exclusive) and `version` (inclusive).
#[derive(Debug, Clone, PartialEq)]
pub struct MapUpdate {
    pub kind: UpdateKind,
    pub from_version: u64,
    pub version: u64,
    /// Sorted block keys (inside the subscription's box, if it has one).
    pub blocks: Vec<BlockKey>,
    /// Sensor poses of the scans in `(from_version, version]` that the ring still holds (all of
    /// them for live updates; the most recent ones for catch-ups), in version order.
    pub poses: Vec<ScanPose>,
    /// `from_version` predates the server's knowledge of the map's history (it was opened at a
    /// later version): `blocks` lists every block the map holds (inside the filter) and a cache
    /// must drop every block it holds that is not listed.
    pub reset: bool,
}

/// An inclusive range of block keys (a box filter).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockBox {
    pub min: BlockKey,
    pub max: BlockKey,
}

impl BlockBox {
    /// The blocks overlapping the world box `[min_world, max_world]` (metres) at `res_m`.
    pub fn from_world(min_world: [f64; 3], max_world: [f64; 3], res_m: f64) -> Result<Self, ServiceError> {
        match (CellKey::from_point(min_world, res_m), CellKey::from_point(max_world, res_m)) {
            (Some(lo), Some(hi)) if lo.x <= hi.x && lo.y <= hi.y && lo.z <= hi.z => {
                Ok(Self { min: lo.block(), max: hi.block() })
            }
            _ => Err(ServiceError::invalid(
                "box",
                "min and max must be finite, inside the key range, with min ≤ max on every axis",
            )),
        }
    }

    pub fn contains(&self, k: BlockKey) -> bool {
        (self.min.x..=self.max.x).contains(&k.x)
            && (self.min.y..=self.max.y).contains(&k.y)
            && (self.min.z..=self.max.z).contains(&k.z)
    }
}

/// The ring of recent updates of one map, shared (in [`Shared`]) by its writer and its
/// subscribers.
#[derive(Debug)]
pub(crate) struct UpdateRing {
    state: Mutex<RingState>,
    published: Condvar,
    capacity: usize,
}

#[derive(Debug, Default)]
struct RingState {
    /// Consecutive updates, oldest first: each one's `from_version` is the previous one's
    /// `version`.
    ring: VecDeque<Arc<MapUpdate>>,
    closed: bool,
    next_id: u64,
    /// Wakers of subscribers waiting in `poll_next`, by subscription id (one each).
    wakers: BTreeMap<u64, Waker>,
}

impl UpdateRing {
    pub fn new(capacity: usize) -> Self {
        Self { state: Mutex::default(), published: Condvar::new(), capacity: capacity.max(1) }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, RingState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Appends an update (called by the writer after the snapshot that holds it is published)
    /// and wakes every waiting subscriber.
    pub fn publish(&self, update: MapUpdate) {
        let wakers = {
            let mut st = self.lock();
            st.ring.push_back(Arc::new(update));
            while st.ring.len() > self.capacity {
                st.ring.pop_front();
            }
            std::mem::take(&mut st.wakers)
        };
        self.published.notify_all();
        wakers.into_values().for_each(Waker::wake);
    }

    /// Ends every subscription (they answer [`Next::Closed`] once caught up).
    pub fn close(&self) {
        let wakers = {
            let mut st = self.lock();
            st.closed = true;
            std::mem::take(&mut st.wakers)
        };
        self.published.notify_all();
        wakers.into_values().for_each(Waker::wake);
    }

    /// Poses of the retained scans with a version in `(after, up_to]`.
    fn poses(&self, after: u64, up_to: u64) -> Vec<ScanPose> {
        let st = self.lock();
        st.ring
            .iter()
            .flat_map(|u| u.poses.iter())
            .filter(|p| p.version > after && p.version <= up_to)
            .cloned()
            .collect()
    }
}

/// Every block changed after `since` in `snap` (and inside `filter`), as one update.
fn changes_in(
    ring: &UpdateRing,
    snap: &Snapshot,
    since: u64,
    filter: Option<&BlockBox>,
    kind: UpdateKind,
) -> Result<MapUpdate, ServiceError> {
    if since > snap.version {
        return Err(ServiceError::invalid(
            "since_version",
            format!("{since} is ahead of the map's version {}", snap.version),
        ));
    }
    let mut blocks: Vec<BlockKey> = snap
        .block_versions
        .iter()
        .filter(|(k, v)| **v > since && filter.is_none_or(|f| f.contains(**k)))
        .map(|(k, _)| *k)
        .collect();
    blocks.sort_unstable();
    let poses = ring.poses(since, snap.version);
    let reset = since < snap.history_from;
    Ok(MapUpdate { kind, from_version: since, version: snap.version, blocks, poses, reset })
}

/// What [`Subscription::poll_next`] yields.
#[derive(Debug, Clone, PartialEq)]
pub enum Next {
    Update(Arc<MapUpdate>),
    /// The service is shutting down; no more updates.
    Closed,
}

/// A live view of one map's changes; see the module docs.
#[derive(Debug)]
pub struct Subscription {
    shared: Arc<Shared>,
    id: u64,
    /// The version this subscriber is up to date with.
    seen: u64,
    filter: Option<BlockBox>,
}

enum Step {
    Ready(Arc<MapUpdate>),
    Lagged,
    Closed,
    Pending,
}

impl Subscription {
    /// The version this subscriber has seen everything up to.
    pub fn version(&self) -> u64 {
        self.seen
    }

    /// Looks at the ring once; registers `waker` when there is nothing new.
    fn step(&mut self, waker: Option<&Waker>) -> Step {
        let mut st = self.shared.updates.lock();
        if let Some(first) = st.ring.front()
            && first.from_version > self.seen
        {
            return Step::Lagged;
        }
        // The first update past `seen` (updates are in version order).
        let i = st.ring.partition_point(|u| u.version <= self.seen);
        match st.ring.get(i).cloned() {
            Some(u) => Step::Ready(u),
            None if st.closed => Step::Closed,
            None => {
                if let Some(w) = waker {
                    st.wakers.insert(self.id, w.clone());
                }
                Step::Pending
            }
        }
    }

    /// Turns one ring entry or a lag into what the caller gets, moving `seen` on.
    fn deliver(&mut self, step: Step) -> Option<Next> {
        match step {
            Step::Ready(u) => {
                self.seen = u.version;
                Some(Next::Update(self.filtered(u)))
            }
            Step::Lagged => {
                let snap = self.shared.snapshot();
                // `seen` never passes the snapshot (it is published before the update), so this
                // only fails if that invariant broke: end the subscription rather than guess.
                let Ok(update) = changes_in(
                    &self.shared.updates,
                    &snap,
                    self.seen,
                    self.filter.as_ref(),
                    UpdateKind::Resync,
                ) else {
                    return Some(Next::Closed);
                };
                self.seen = update.version;
                Some(Next::Update(Arc::new(update)))
            }
            Step::Closed => Some(Next::Closed),
            Step::Pending => None,
        }
    }

    fn filtered(&self, u: Arc<MapUpdate>) -> Arc<MapUpdate> {
        match &self.filter {
            None => u,
            Some(f) => Arc::new(MapUpdate {
                kind: u.kind,
                from_version: u.from_version,
                version: u.version,
                blocks: u.blocks.iter().copied().filter(|k| f.contains(*k)).collect(),
                poses: u.poses.clone(),
                reset: u.reset,
            }),
        }
    }

    /// The next update, or `Pending` (the context's waker is woken when one is published).
    pub fn poll_next(&mut self, cx: &mut Context<'_>) -> Poll<Next> {
        let step = self.step(Some(cx.waker()));
        self.deliver(step).map_or(Poll::Pending, Poll::Ready)
    }

    /// The next update, waiting at most `timeout`; `None` when none came in time.
    pub fn next_timeout(&mut self, timeout: Duration) -> Option<Next> {
        let deadline = Instant::now() + timeout;
        loop {
            let step = self.step(None);
            if let Some(next) = self.deliver(step) {
                return Some(next);
            }
            let left = deadline.checked_duration_since(Instant::now()).filter(|d| !d.is_zero())?;
            let ring = &self.shared.updates;
            let st = ring.lock();
            // Re-check under the lock before sleeping, so a publish in between is not missed.
            let behind = st.ring.back().is_some_and(|u| u.version > self.seen);
            if !behind && !st.closed {
                drop(ring.published.wait_timeout(st, left).unwrap_or_else(PoisonError::into_inner));
            }
        }
    }
}

impl Drop for Subscription {
    fn drop(&mut self) {
        self.shared.updates.lock().wakers.remove(&self.id);
    }
}

/// One follower of a map as every transport streams it: the catch-up first, then the live
/// subscription, then `None` once the service closed its updates (shutdown).
#[derive(Debug)]
pub struct Watch {
    first: Option<MapUpdate>,
    sub: Subscription,
    /// The map's resolution (m), which every wire message carries.
    pub resolution_m: f64,
    closed: bool,
}

impl Watch {
    /// A watch from what [`MapService::watch`] returned, for a map of resolution `resolution_m`.
    pub fn new((first, sub): (MapUpdate, Subscription), resolution_m: f64) -> Self {
        Self { first: Some(first), sub, resolution_m, closed: false }
    }

    /// The next update to send; `None` once the service has closed the map's updates.
    pub fn poll_update(&mut self, cx: &mut Context<'_>) -> Poll<Option<Arc<MapUpdate>>> {
        if let Some(first) = self.first.take() {
            return Poll::Ready(Some(Arc::new(first)));
        }
        if self.closed {
            return Poll::Ready(None);
        }
        match self.sub.poll_next(cx) {
            Poll::Ready(Next::Update(u)) => Poll::Ready(Some(u)),
            Poll::Ready(Next::Closed) => {
                self.closed = true;
                Poll::Ready(None)
            }
            Poll::Pending => Poll::Pending,
        }
    }
}

impl MapService {
    /// Every block of `map` changed after version `since` (inside `filter`), answered from the
    /// current snapshot, with the poses of those scans the ring still holds.
    pub fn changes_since(
        &self,
        map: &str,
        since: u64,
        filter: Option<&BlockBox>,
    ) -> Result<MapUpdate, ServiceError> {
        let h = self.handle(map)?;
        changes_in(&h.shared.updates, &h.shared.snapshot(), since, filter, UpdateKind::CatchUp)
    }

    /// Starts following `map`: the catch-up since `since` (the current version when `None`:
    /// no blocks), and a subscription whose updates continue right after it.
    pub fn watch(
        &self,
        map: &str,
        since: Option<u64>,
        filter: Option<BlockBox>,
    ) -> Result<(MapUpdate, Subscription), ServiceError> {
        let h = self.handle(map)?;
        let snap = h.shared.snapshot();
        let catch_up = changes_in(
            &h.shared.updates,
            &snap,
            since.unwrap_or(snap.version),
            filter.as_ref(),
            UpdateKind::CatchUp,
        )?;
        let id = {
            let mut st = h.shared.updates.lock();
            st.next_id += 1;
            st.next_id
        };
        let sub = Subscription { shared: h.shared.clone(), id, seen: snap.version, filter };
        Ok((catch_up, sub))
    }

    /// The sensor poses of the most recent scans of `map` the ring holds, oldest first.
    pub fn recent_poses(&self, map: &str) -> Result<Vec<ScanPose>, ServiceError> {
        let h = self.handle(map)?;
        Ok(h.shared.updates.poses(0, u64::MAX))
    }

    /// Ends every subscription of every map (transports close their streams), e.g. before a
    /// graceful shutdown waits for open connections.
    pub fn close_updates(&self) {
        let maps = self.maps.read().unwrap_or_else(PoisonError::into_inner);
        for h in maps.values() {
            h.shared.updates.close();
        }
    }
}
