//! `MapService`: the one API every transport (gRPC, HTTP, zenoh) calls.
//!
//! It owns the named maps of a data directory (one map file `<name>.bgkmap` each, see
//! [`crate::store`]). Per map, two threads:
//! - the **journal** thread (`ingest`) takes validated scans (`scan`) from a bounded queue,
//!   writes each batch to the map file's journal in one durable transaction (group commit: one
//!   fsync per batch) and acknowledges them — *acknowledged means durable*. A scan whose
//!   `(source, seq)` the map already holds is acknowledged as a duplicate and not applied again;
//! - the **writer** thread (`writer`) integrates journaled scans in batches, commits their
//!   evidence and status in one transaction, and publishes a new immutable [`Snapshot`]. It also
//!   runs the exact edits (`edits`: retract, re-pose, merge) in order with
//!   the scans, and journal retention.
//!
//! A caller may ask to be answered only once its scan is integrated (read-your-writes). Readers
//! take the current snapshot (an `Arc`): they never wait for a writer nor see a half-applied
//! scan. Every read goes through one front door, [`query`]: validation, limits and whether a
//! query may run on the caller's thread, the same for every transport. A full queue (or too many
//! journaled scans waiting for integration) is an answer ([`ServiceError::Busy`]), not a wait. A
//! failed write makes the map read-only until writing works again (`health`). Every new
//! snapshot also produces an update, which says which blocks changed ([`updates`]: the map's
//! change stream). On open, journaled scans not yet integrated are replayed before the map
//! serves, so the first snapshot holds every acknowledged scan.
//!
//! The service is synchronous (std threads and channels) and knows nothing of any runtime or
//! wire format; transports adapt the completion callbacks and the runtime-neutral waits to
//! their own runtime.

mod edits;
mod health;
mod info;
mod ingest;
pub mod query;
mod scan;
mod snapshot;
pub mod updates;
mod writer;

pub use edits::MergeSource;
pub use info::{MapInfo, SourceStats};
pub use query::{QueryError, QueryLimits};
pub use scan::{ScanInput, ScanLimits};
pub use snapshot::Snapshot;
pub use updates::{BlockBox, BlockVersions, MapUpdate, Next, ScanPose, Subscription, UpdateKind, Watch};

use crate::core::MapParams;
use crate::store::journal::SourceContent;
use crate::store::{DurableMap, MapFile, Retention, StoreError};
use health::Faults;
use info::SessionCounts;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, AtomicUsize};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use std::time::Duration;

/// Service settings (defaults documented per field).
#[derive(Debug, Clone)]
pub struct ServiceConfig {
    /// Scans waiting per map to be journaled before submissions are refused as busy. Default 64.
    pub queue_capacity: usize,
    /// Journaled scans per map waiting to be integrated before submissions are refused as
    /// busy. Default 256.
    pub max_unapplied_scans: usize,
    /// Threads integrating each map's scans: a batch of several scans is spread over them one
    /// scan per thread, a lone scan is split across them (results are bit-identical for any
    /// count). Default 1.
    pub threads_per_scan: usize,
    /// Limits on one scan.
    pub limits: ScanLimits,
    /// Limits on the read-only queries (every transport's).
    pub queries: QueryLimits,
    /// How long raw scans stay in the journal. Default: all of them.
    pub retention: Retention,
    /// After a failed write, how long before writing is tried again. Default 1 s.
    pub write_retry: Duration,
    /// Updates each map keeps for live subscribers (one per published change); one that falls
    /// further behind is resynchronised from the snapshot. Default 256.
    pub updates_capacity: usize,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            queue_capacity: 64,
            max_unapplied_scans: 256,
            threads_per_scan: 1,
            limits: ScanLimits::default(),
            queries: QueryLimits::default(),
            retention: Retention::All,
            write_retry: Duration::from_secs(1),
            updates_capacity: 256,
        }
    }
}

/// Errors of the service layer; transports map each variant to one status code.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("map {0:?} not found")]
    NotFound(String),
    #[error("{0}")]
    ScansNotFound(String),
    #[error("map {0:?} already exists")]
    AlreadyExists(String),
    #[error("invalid {field}: {reason}")]
    InvalidArgument { field: String, reason: String },
    #[error("map {map:?} is busy: {queued} scans queued; retry in {retry_after_ms} ms")]
    Busy { map: String, queued: usize, retry_after_ms: u64 },
    #[error(
        "map {map:?} is read-only: {reason}; queries still work; ingest resumes by itself once writing succeeds again"
    )]
    ReadOnly { map: String, reason: String },
    /// The operation cannot be done exactly (raw scans pruned, conflicting scans, …).
    #[error("{0}")]
    Precondition(String),
    /// Stored data is damaged (a corrupt block or journal record).
    #[error("{0}")]
    DataLoss(String),
    #[error("the service is shutting down")]
    ShuttingDown,
    #[error(transparent)]
    Storage(StoreError),
}

impl From<StoreError> for ServiceError {
    fn from(e: StoreError) -> Self {
        if e.is_corruption() { Self::DataLoss(e.to_string()) } else { Self::Storage(e) }
    }
}

impl ServiceError {
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidArgument { field: field.into(), reason: reason.into() }
    }
}

/// The outcome of one scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ack {
    /// False when the map already held this `(source, seq)`: nothing new was journaled.
    pub applied: bool,
    /// True when answered after integration: `version` then includes the scan.
    pub integrated: bool,
    /// The map version when answered.
    pub version: u64,
    /// Input points dropped because they were not finite.
    pub dropped_points: usize,
}

/// How a scan is acknowledged.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SubmitOptions {
    /// Answer only once the scan is integrated and visible to queries (read-your-writes);
    /// otherwise once it is durable in the journal.
    pub wait_applied: bool,
}

/// A completion callback for a submitted scan.
pub type Done = Box<dyn FnOnce(Result<Ack, ServiceError>) + Send>;

pub use crate::store::Change;

/// State one map's threads share with the service.
#[derive(Debug)]
pub(super) struct Shared {
    pub snapshot: RwLock<Arc<Snapshot>>,
    /// Submitted, not yet journaled.
    pub queued: AtomicUsize,
    /// Journaled, not yet integrated.
    pub backlog: AtomicUsize,
    pub integration_micros: AtomicU64,
    pub session: Mutex<BTreeMap<String, SessionCounts>>,
    /// What the journal holds.
    pub stats: Mutex<JournalStats>,
    pub faults: Faults,
    /// The recent updates (see the `updates` module).
    pub updates: updates::UpdateRing,
}

/// What a map's journal holds, kept so that a scan counts the moment it is acknowledged.
#[derive(Debug, Default)]
pub(super) struct JournalStats {
    /// Per source, as of the writer's last change.
    pub content: Arc<BTreeMap<String, SourceContent>>,
    /// Bytes of raw scans stored, as of the writer's last change.
    pub journal_bytes: u64,
    /// Per source: journaled by the journal thread, not yet integrated by the writer.
    pub in_flight: BTreeMap<String, u64>,
}

impl Shared {
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.snapshot.read().unwrap_or_else(PoisonError::into_inner).clone()
    }

    pub fn count(&self, source: &str, f: impl FnOnce(&mut SessionCounts)) {
        f(lock(&self.session).entry(source.to_string()).or_default());
    }
}

struct MapHandle {
    params: MapParams,
    path: PathBuf,
    queue: Mutex<Option<std::sync::mpsc::SyncSender<ingest::Job>>>,
    /// The writer's queue, for edits (the journal thread holds its own sender).
    work: Mutex<Option<std::sync::mpsc::Sender<writer::Work>>>,
    shared: Arc<Shared>,
    threads: Mutex<Vec<std::thread::JoinHandle<()>>>,
}

/// The maps of one data directory.
pub struct MapService {
    data_dir: PathBuf,
    config: ServiceConfig,
    maps: RwLock<BTreeMap<String, Arc<MapHandle>>>,
    /// Called with the name of every map created (see [`MapService::on_map_created`]).
    created_hooks: Mutex<Vec<MapCreatedHook>>,
}

/// A callback told the name of each newly created map.
type MapCreatedHook = Box<dyn Fn(&str) + Send + Sync>;

impl std::fmt::Debug for MapService {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MapService").field("data_dir", &self.data_dir).finish_non_exhaustive()
    }
}

const MAP_FILE_EXTENSION: &str = "bgkmap";

/// Map names: 1–64 of `[A-Za-z0-9_-]`, so they are safe as file names and zenoh key chunks.
pub fn validate_map_name(name: &str) -> Result<(), ServiceError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
    if ok {
        Ok(())
    } else {
        Err(ServiceError::invalid("map", "names are 1–64 characters of A–Z, a–z, 0–9, _ and -"))
    }
}

pub(super) fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl MapService {
    /// Opens every map file in `data_dir` (created if missing), replays their journals and
    /// starts their threads.
    pub fn open(data_dir: &Path, config: ServiceConfig) -> Result<Self, ServiceError> {
        std::fs::create_dir_all(data_dir)
            .map_err(|error| StoreError::Io { path: data_dir.to_path_buf(), error })?;
        let service = Self {
            data_dir: data_dir.to_path_buf(),
            config,
            maps: RwLock::default(),
            created_hooks: Mutex::default(),
        };
        let entries = std::fs::read_dir(data_dir)
            .map_err(|error| StoreError::Io { path: data_dir.to_path_buf(), error })?;
        let mut paths: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == MAP_FILE_EXTENSION))
            .collect();
        paths.sort();
        for path in paths {
            let Some(name) = path.file_stem().and_then(|s| s.to_str()).map(str::to_string) else { continue };
            if validate_map_name(&name).is_err() {
                continue;
            }
            service.start(name, &path)?;
        }
        Ok(service)
    }

    /// Opens one map file, replays its journal and starts its threads.
    fn start(&self, name: String, path: &Path) -> Result<(), ServiceError> {
        let c = &self.config;
        let recovered = DurableMap::open(path, c.threads_per_scan, c.retention)?;
        let journal = MapFile::connect(path)?;
        let (shared, writer) = writer::Writer::recover(recovered, c)?;
        let (work_tx, work_rx) = std::sync::mpsc::channel();
        let (job_tx, job_rx) = std::sync::mpsc::sync_channel(c.queue_capacity.max(1));
        let spawn = |what: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(format!("bgkmap-{what}-{name}"))
                .spawn(f)
                .map_err(|error| ServiceError::Storage(StoreError::Io { path: path.to_path_buf(), error }))
        };
        let journaler = ingest::Journaler::new(journal, work_tx.clone(), shared.clone());
        let threads = vec![
            spawn("writer", Box::new(move || writer.run(work_rx)))?,
            spawn("journal", Box::new(move || journaler.run(job_rx)))?,
        ];
        let handle = MapHandle {
            params: *shared.snapshot().map.params(),
            path: path.to_path_buf(),
            queue: Mutex::new(Some(job_tx)),
            work: Mutex::new(Some(work_tx)),
            shared,
            threads: Mutex::new(threads),
        };
        self.maps.write().unwrap_or_else(PoisonError::into_inner).insert(name, Arc::new(handle));
        Ok(())
    }

    fn handle(&self, name: &str) -> Result<Arc<MapHandle>, ServiceError> {
        let maps = self.maps.read().unwrap_or_else(PoisonError::into_inner);
        maps.get(name).cloned().ok_or_else(|| ServiceError::NotFound(name.to_string()))
    }

    /// Creates a new map with `params` (validated) in its own map file.
    pub fn create_map(&self, name: &str, params: MapParams) -> Result<MapInfo, ServiceError> {
        validate_map_name(name)?;
        params.validate().map_err(|e| ServiceError::invalid(e.name, e.reason))?;
        // Held from the check to the hooks, so a hook registered meanwhile sees the map either
        // in its list or through its call, never both and never neither.
        let hooks = lock(&self.created_hooks);
        if self.handle(name).is_ok() {
            return Err(ServiceError::AlreadyExists(name.to_string()));
        }
        let path = self.data_dir.join(format!("{name}.{MAP_FILE_EXTENSION}"));
        let file = MapFile::create(&path, &params).map_err(|e| match e {
            StoreError::Io { error, .. } if error.kind() == std::io::ErrorKind::AlreadyExists => {
                ServiceError::AlreadyExists(name.to_string())
            }
            other => other.into(),
        })?;
        file.close()?;
        self.start(name.to_string(), &path)?;
        for hook in hooks.iter() {
            hook(name);
        }
        drop(hooks);
        self.map_info(name)
    }

    /// Registers `hook`, called with the name of every map created from now on (on the creating
    /// thread, once the map takes scans; it must not create maps or register hooks itself), and
    /// returns the names of the maps that exist already: together, every map exactly once. A
    /// transport that follows every map's updates (zenoh) registers once at start-up.
    pub fn on_map_created(&self, hook: impl Fn(&str) + Send + Sync + 'static) -> Vec<String> {
        let mut hooks = lock(&self.created_hooks);
        hooks.push(Box::new(hook));
        self.maps.read().unwrap_or_else(PoisonError::into_inner).keys().cloned().collect()
    }

    /// The current snapshot of a map: whole scans only; never blocks on the writer.
    pub fn snapshot(&self, name: &str) -> Result<Arc<Snapshot>, ServiceError> {
        Ok(self.handle(name)?.shared.snapshot())
    }

    /// Stops accepting scans, lets every map's threads drain their queues (each scan journaled
    /// and integrated), and joins them.
    pub fn shutdown(&self) {
        let handles: Vec<Arc<MapHandle>> =
            self.maps.read().unwrap_or_else(PoisonError::into_inner).values().cloned().collect();
        for h in &handles {
            lock(&h.queue).take();
            lock(&h.work).take();
        }
        for h in &handles {
            for j in lock(&h.threads).drain(..) {
                let _ = j.join();
            }
            h.shared.updates.close();
        }
    }
}

impl Drop for MapService {
    fn drop(&mut self) {
        self.shutdown();
    }
}

#[cfg(test)]
mod tests;
#[cfg(test)]
mod updates_tests;
