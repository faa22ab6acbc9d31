//! `MapService`: the one API every transport (gRPC, HTTP, zenoh) calls.
//!
//! It owns the named maps of a data directory (one map file `<name>.bgkmap` each) and, per map,
//! a single writer thread that takes scans from a bounded queue, integrates them, persists the
//! touched blocks together with the scan's identity, and publishes a new immutable snapshot.
//! Readers take the current snapshot (an `Arc`) and never wait for the writer nor see a
//! half-applied scan. A scan whose `(source, seq)` the map already holds is acknowledged as a
//! duplicate and not applied again. A full queue is an answer ([`ServiceError::Busy`]), not a
//! wait.
//!
//! The service is synchronous (std threads and channels); transports adapt the completion
//! callback of [`MapService::submit_scan`] to their own runtime. It knows nothing of any wire
//! format.

mod scan;
mod writer;

pub use scan::{ScanInput, ScanLimits};

use crate::core::{EvidenceMap, MapParams};
use crate::store::{MapFile, StoreError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{SyncSender, TrySendError};
use std::sync::{Arc, Mutex, PoisonError, RwLock};
use writer::{Job, Writer};

/// Service settings (defaults documented per field).
#[derive(Debug, Clone)]
pub struct ServiceConfig {
    /// Scans waiting per map before submissions are refused as busy. Default 64.
    pub queue_capacity: usize,
    /// Threads per scan integration (results are bit-identical for any count). Default 1.
    pub threads_per_scan: usize,
    /// Limits on one scan.
    pub limits: ScanLimits,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self { queue_capacity: 64, threads_per_scan: 1, limits: ScanLimits::default() }
    }
}

/// Errors of the service layer; transports map each variant to one status code.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("map {0:?} not found")]
    NotFound(String),
    #[error("map {0:?} already exists")]
    AlreadyExists(String),
    #[error("invalid {field}: {reason}")]
    InvalidArgument { field: String, reason: String },
    #[error("map {map:?} is busy: {queued} scans queued; retry in {retry_after_ms} ms")]
    Busy { map: String, queued: usize, retry_after_ms: u64 },
    #[error("the service is shutting down")]
    ShuttingDown,
    #[error(transparent)]
    Storage(#[from] StoreError),
}

impl ServiceError {
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::InvalidArgument { field: field.into(), reason: reason.into() }
    }
}

/// The outcome of one scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ack {
    /// False when the map already held this `(source, seq)`; nothing was applied.
    pub applied: bool,
    /// The map version after this scan (the number of scans applied so far).
    pub version: u64,
    /// Input points dropped because they were not finite.
    pub dropped_points: usize,
}

/// A completion callback for a submitted scan.
pub type Done = Box<dyn FnOnce(Result<Ack, ServiceError>) + Send>;

/// An immutable view of a map after a whole number of scans.
#[derive(Debug)]
pub struct Snapshot {
    pub version: u64,
    pub map: EvidenceMap,
}

/// Per-source ingest counters.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SourceStats {
    pub received: u64,
    pub applied: u64,
    pub duplicates: u64,
    pub rejected: u64,
    pub highest_seq: Option<u64>,
    /// Non-finite input points dropped from this source's applied scans.
    pub dropped_points: u64,
}

/// What `GetMap` / `ListMaps` report.
#[derive(Debug, Clone)]
pub struct MapInfo {
    pub name: String,
    pub params: MapParams,
    pub version: u64,
    pub blocks: usize,
    pub cells_with_evidence: usize,
    pub queued: usize,
    /// Time the writer spent integrating scans (training data, evidence, map update), seconds.
    pub integration_seconds_total: f64,
    pub sources: BTreeMap<String, SourceStats>,
}

struct MapHandle {
    params: MapParams,
    queue: Mutex<Option<SyncSender<Job>>>,
    queued: Arc<std::sync::atomic::AtomicUsize>,
    integration_micros: Arc<std::sync::atomic::AtomicU64>,
    snapshot: Arc<RwLock<Arc<Snapshot>>>,
    sources: Arc<Mutex<BTreeMap<String, SourceStats>>>,
    writer: Mutex<Option<std::thread::JoinHandle<()>>>,
}

/// The maps of one data directory.
pub struct MapService {
    data_dir: PathBuf,
    config: ServiceConfig,
    maps: RwLock<BTreeMap<String, Arc<MapHandle>>>,
}

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

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl MapService {
    /// Opens every map file in `data_dir` (created if missing) and starts their writers.
    pub fn open(data_dir: &Path, config: ServiceConfig) -> Result<Self, ServiceError> {
        std::fs::create_dir_all(data_dir)
            .map_err(|error| StoreError::Io { path: data_dir.to_path_buf(), error })?;
        let service = Self { data_dir: data_dir.to_path_buf(), config, maps: RwLock::default() };
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
            let opened = MapFile::open(&path)?;
            service.start(name, opened.file, opened.map, opened.scans);
        }
        Ok(service)
    }

    fn start(&self, name: String, file: MapFile, map: EvidenceMap, scans: Vec<(String, u64)>) {
        let (tx, rx) = std::sync::mpsc::sync_channel(self.config.queue_capacity.max(1));
        let snapshot =
            Arc::new(RwLock::new(Arc::new(Snapshot { version: scans.len() as u64, map: map.clone() })));
        let params = *map.params();
        let sources = Arc::new(Mutex::new(BTreeMap::new()));
        let queued = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let integration_micros = Arc::new(std::sync::atomic::AtomicU64::new(0));
        let shared = writer::Shared {
            snapshot: snapshot.clone(),
            sources: sources.clone(),
            queued: queued.clone(),
            integration_micros: integration_micros.clone(),
        };
        let writer = Writer::new(file, map, scans, shared, &self.config);
        let join = std::thread::Builder::new()
            .name(format!("bgkmap-writer-{name}"))
            .spawn(move || writer.run(rx))
            .ok();
        let handle = MapHandle {
            params,
            queue: Mutex::new(Some(tx)),
            queued,
            integration_micros,
            snapshot,
            sources,
            writer: Mutex::new(join),
        };
        self.maps.write().unwrap_or_else(PoisonError::into_inner).insert(name, Arc::new(handle));
    }

    fn handle(&self, name: &str) -> Result<Arc<MapHandle>, ServiceError> {
        let maps = self.maps.read().unwrap_or_else(PoisonError::into_inner);
        maps.get(name).cloned().ok_or_else(|| ServiceError::NotFound(name.to_string()))
    }

    /// Creates a new map with `params` (validated) in its own map file.
    pub fn create_map(&self, name: &str, params: MapParams) -> Result<MapInfo, ServiceError> {
        validate_map_name(name)?;
        params.validate().map_err(|e| ServiceError::invalid(e.name, e.reason))?;
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
        self.start(name.to_string(), file, EvidenceMap::new(params), Vec::new());
        self.map_info(name)
    }

    /// Every map, by name.
    pub fn list_maps(&self) -> Vec<MapInfo> {
        let names: Vec<String> =
            self.maps.read().unwrap_or_else(PoisonError::into_inner).keys().cloned().collect();
        names.iter().filter_map(|n| self.map_info(n).ok()).collect()
    }

    /// Parameters and statistics of one map.
    pub fn map_info(&self, name: &str) -> Result<MapInfo, ServiceError> {
        let h = self.handle(name)?;
        let snap = h.snapshot.read().unwrap_or_else(PoisonError::into_inner).clone();
        Ok(MapInfo {
            name: name.to_string(),
            params: h.params,
            version: snap.version,
            blocks: snap.map.block_count(),
            cells_with_evidence: snap.map.cells_with_evidence(),
            queued: h.queued.load(std::sync::atomic::Ordering::Relaxed),
            integration_seconds_total: h.integration_micros.load(std::sync::atomic::Ordering::Relaxed) as f64
                / 1e6,
            sources: lock(&h.sources).clone(),
        })
    }

    /// The current snapshot of a map: whole scans only; never blocks on the writer.
    pub fn snapshot(&self, name: &str) -> Result<Arc<Snapshot>, ServiceError> {
        let h = self.handle(name)?;
        let snap = h.snapshot.read().unwrap_or_else(PoisonError::into_inner).clone();
        Ok(snap)
    }

    /// Validates a scan and queues it for the map's writer; `done` is called once the scan is
    /// applied and persisted (or found to be a duplicate, or failed). Errors returned here
    /// (unknown map, invalid scan, busy) mean the scan was not queued and `done` is not called.
    pub fn submit_scan(&self, name: &str, scan: ScanInput, done: Done) -> Result<(), ServiceError> {
        let h = self.handle(name)?;
        let prepared = match scan.prepare(&self.config.limits) {
            Ok(p) => p,
            Err(e) => {
                lock(&h.sources).entry(scan.source.clone()).or_default().rejected += 1;
                return Err(e);
            }
        };
        let queue = lock(&h.queue);
        let Some(tx) = queue.as_ref() else { return Err(ServiceError::ShuttingDown) };
        h.queued.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        match tx.try_send(Job { scan: prepared, done }) {
            Ok(()) => Ok(()),
            Err(err) => {
                let queued = h.queued.fetch_sub(1, std::sync::atomic::Ordering::Relaxed) - 1;
                match err {
                    TrySendError::Full(_) => Err(ServiceError::Busy {
                        map: name.to_string(),
                        queued,
                        retry_after_ms: 50 * (1 + queued as u64 / 8),
                    }),
                    TrySendError::Disconnected(_) => Err(ServiceError::ShuttingDown),
                }
            }
        }
    }

    /// Counts a scan of `source` that a transport refused before it reached the map (a payload
    /// that does not decode), as `rejected` like a scan that fails validation. The map must
    /// exist and the source name be valid (1–`max_source_len` bytes), so a stranger cannot grow
    /// the per-source table with names of any length.
    pub fn count_rejected(&self, name: &str, source: &str) -> Result<(), ServiceError> {
        let h = self.handle(name)?;
        if source.is_empty() || source.len() > self.config.limits.max_source_len {
            let max = self.config.limits.max_source_len;
            return Err(ServiceError::invalid("source", format!("must be 1–{max} bytes")));
        }
        lock(&h.sources).entry(source.to_string()).or_default().rejected += 1;
        Ok(())
    }

    /// Submits a scan and waits for its outcome (for synchronous callers and tests).
    pub fn insert_scan_blocking(&self, name: &str, scan: ScanInput) -> Result<Ack, ServiceError> {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        self.submit_scan(name, scan, Box::new(move |r| drop(tx.send(r))))?;
        rx.recv().unwrap_or(Err(ServiceError::ShuttingDown))
    }

    /// Stops accepting scans, lets every writer drain its queue (each scan is persisted as it is
    /// applied), and joins the writers.
    pub fn shutdown(&self) {
        let handles: Vec<Arc<MapHandle>> =
            self.maps.read().unwrap_or_else(PoisonError::into_inner).values().cloned().collect();
        for h in &handles {
            lock(&h.queue).take();
        }
        for h in &handles {
            if let Some(j) = lock(&h.writer).take() {
                let _ = j.join();
            }
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
