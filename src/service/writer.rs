//! The single writer of one map: integrate, persist, publish.

use super::scan::PreparedScan;
use super::{Ack, Done, ServiceConfig, ServiceError, Snapshot, SourceStats};
use crate::core::{EvidenceMap, Integrator};
use crate::store::MapFile;
use std::collections::{BTreeMap, HashSet};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex, PoisonError, RwLock};

pub(super) struct Job {
    pub scan: PreparedScan,
    pub done: Done,
}

/// State the writer shares with readers of the service.
pub(super) struct Shared {
    pub snapshot: Arc<RwLock<Arc<Snapshot>>>,
    pub sources: Arc<Mutex<BTreeMap<String, SourceStats>>>,
    pub queued: Arc<AtomicUsize>,
    pub integration_micros: Arc<AtomicU64>,
}

pub(super) struct Writer {
    file: MapFile,
    map: EvidenceMap,
    integrator: Integrator,
    applied: HashSet<(String, u64)>,
    version: u64,
    threads: usize,
    shared: Shared,
}

impl Writer {
    pub fn new(
        file: MapFile,
        map: EvidenceMap,
        scans: Vec<(String, u64)>,
        shared: Shared,
        config: &ServiceConfig,
    ) -> Self {
        Self {
            integrator: Integrator::new(*map.params()),
            version: scans.len() as u64,
            applied: scans.into_iter().collect(),
            file,
            map,
            threads: config.threads_per_scan.max(1),
            shared,
        }
    }

    /// Runs until every sender is gone and the queue is drained.
    pub fn run(mut self, rx: Receiver<Job>) {
        while let Ok(job) = rx.recv() {
            let result = self.apply(&job.scan);
            self.shared.queued.fetch_sub(1, Ordering::Relaxed);
            self.count(&job.scan, &result);
            (job.done)(result);
        }
    }

    fn apply(&mut self, scan: &PreparedScan) -> Result<Ack, ServiceError> {
        let id = (scan.source.clone(), scan.seq);
        let ack = |applied, version| Ack { applied, version, dropped_points: scan.dropped_points };
        if self.applied.contains(&id) {
            return Ok(ack(false, self.version));
        }
        let t0 = std::time::Instant::now();
        let delta = self.integrator.scan_delta_with_range(
            &scan.points_world,
            scan.origin_world,
            self.threads,
            scan.max_range_m,
        );
        let updated = self.map.blocks_after(&delta, 1);
        self.shared.integration_micros.fetch_add(t0.elapsed().as_micros() as u64, Ordering::Relaxed);
        self.integrator.recycle(delta);
        // Persist first: the map only moves on once the file holds the scan.
        let rows: Vec<_> = updated.iter().map(|(k, b)| (*k, b.as_deref())).collect();
        self.file.commit(&rows, &[(scan.source.as_str(), scan.seq)])?;
        self.map.set_blocks(updated);
        self.applied.insert(id);
        self.version += 1;
        let snap = Arc::new(Snapshot { version: self.version, map: self.map.clone() });
        *self.shared.snapshot.write().unwrap_or_else(PoisonError::into_inner) = snap;
        Ok(ack(true, self.version))
    }

    fn count(&self, scan: &PreparedScan, result: &Result<Ack, ServiceError>) {
        let mut sources = self.shared.sources.lock().unwrap_or_else(PoisonError::into_inner);
        let s = sources.entry(scan.source.clone()).or_default();
        s.received += 1;
        match result {
            Ok(a) if a.applied => {
                s.applied += 1;
                s.dropped_points += a.dropped_points as u64;
                s.highest_seq = Some(s.highest_seq.map_or(scan.seq, |h| h.max(scan.seq)));
            }
            Ok(_) => s.duplicates += 1,
            Err(_) => s.rejected += 1,
        }
    }
}
