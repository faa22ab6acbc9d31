//! Ingest: validation and admission of scans ([`MapService::submit`]), and the journal thread
//! that makes them durable in batches and acknowledges them.

use super::scan::PreparedScan;
use super::writer::{Waiting, Work};
use super::{Ack, Done, MapService, ServiceError, Shared, SubmitOptions};
use crate::store::{MapFile, NewScan, Pending, now_nanos};
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, Sender, TryRecvError, TrySendError};

/// Most scans journaled in one transaction.
const JOURNAL_BATCH: usize = 64;

pub(super) struct Job {
    scan: PreparedScan,
    options: SubmitOptions,
    done: Done,
}

impl MapService {
    /// Validates a scan and queues it; `done` is called once the scan is durable in the
    /// journal (or found to be a duplicate, or failed). Errors returned here (unknown map,
    /// invalid scan, busy, read-only) mean the scan was not queued and `done` is not called.
    pub fn submit_scan(&self, name: &str, scan: super::ScanInput, done: Done) -> Result<(), ServiceError> {
        self.submit(name, scan, SubmitOptions::default(), done)
    }

    /// As [`Self::submit_scan`], with options (e.g. answer only once integrated).
    pub fn submit(
        &self,
        name: &str,
        scan: super::ScanInput,
        options: SubmitOptions,
        done: Done,
    ) -> Result<(), ServiceError> {
        let h = self.handle(name)?;
        let sh = &h.shared;
        let refuse = |e: ServiceError| {
            sh.count(&scan.source, |c| c.rejected += 1);
            Err(e)
        };
        let prepared = match scan.prepare(&self.config.limits) {
            Ok(p) => p,
            Err(e) => return refuse(e),
        };
        if let Err(reason) = sh.faults.admit() {
            return refuse(ServiceError::ReadOnly { map: name.to_string(), reason });
        }
        let backlog = sh.backlog.load(Ordering::Relaxed);
        if backlog >= self.config.max_unapplied_scans {
            let retry_after_ms = 100 * (1 + backlog as u64 / 64);
            return Err(ServiceError::Busy { map: name.to_string(), queued: backlog, retry_after_ms });
        }
        let queue = super::lock(&h.queue);
        let Some(tx) = queue.as_ref() else { return Err(ServiceError::ShuttingDown) };
        sh.queued.fetch_add(1, Ordering::Relaxed);
        match tx.try_send(Job { scan: prepared, options, done }) {
            Ok(()) => Ok(()),
            Err(err) => {
                let queued = sh.queued.fetch_sub(1, Ordering::Relaxed) - 1;
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
        let max = self.config.limits.max_source_len;
        if source.is_empty() || source.len() > max {
            return Err(ServiceError::invalid("source", format!("must be 1–{max} bytes")));
        }
        h.shared.count(source, |c| c.rejected += 1);
        Ok(())
    }

    /// Submits a scan and waits until it is integrated (read-your-writes; for synchronous
    /// callers and tests).
    pub fn insert_scan_blocking(&self, name: &str, scan: super::ScanInput) -> Result<Ack, ServiceError> {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        let options = SubmitOptions { wait_applied: true };
        self.submit(name, scan, options, Box::new(move |r| drop(tx.send(r))))?;
        rx.recv().unwrap_or(Err(ServiceError::ShuttingDown))
    }
}

/// The journal thread of one map.
pub(super) struct Journaler {
    file: MapFile,
    to_writer: Sender<Work>,
    shared: Arc<Shared>,
    map: String,
}

impl Journaler {
    pub fn new(file: MapFile, to_writer: Sender<Work>, shared: Arc<Shared>) -> Self {
        let map = file.path().file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        Self { file, to_writer, shared, map }
    }

    /// Runs until the queue is closed and drained.
    pub fn run(mut self, rx: Receiver<Job>) {
        while let Ok(first) = rx.recv() {
            let mut batch = vec![first];
            while batch.len() < JOURNAL_BATCH {
                match rx.try_recv() {
                    Ok(job) => batch.push(job),
                    Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
                }
            }
            self.journal(batch);
        }
    }

    fn journal(&mut self, batch: Vec<Job>) {
        let n = batch.len();
        let received_nanos = now_nanos();
        let mut tails = Vec::with_capacity(n);
        let scans: Vec<NewScan> = batch
            .into_iter()
            .map(|j| {
                tails.push((j.options, j.done, j.scan.dropped_points));
                NewScan {
                    source: j.scan.source,
                    seq: j.scan.seq,
                    stamp_nanos: j.scan.stamp_nanos.unwrap_or(received_nanos),
                    received_nanos,
                    scan: j.scan.raw,
                }
            })
            .collect();
        let result = self.file.journal(&scans);
        self.shared.queued.fetch_sub(n, Ordering::Relaxed);
        let entries = match result {
            Ok(entries) => entries,
            Err(e) => {
                let reason = e.to_string();
                self.shared.faults.journal_failed(reason.clone());
                for (s, (_, done, _)) in scans.iter().zip(tails) {
                    self.shared.count(&s.source, |c| c.rejected += 1);
                    done(Err(ServiceError::ReadOnly { map: self.map.clone(), reason: reason.clone() }));
                }
                return;
            }
        };
        self.shared.faults.journal_ok();
        let version = self.shared.snapshot().version;
        let mut work = Vec::new();
        let mut acks = Vec::new();
        for ((s, entry), (options, done, dropped)) in scans.into_iter().zip(entries).zip(tails) {
            let ack = |applied| Ack { applied, integrated: false, version, dropped_points: dropped };
            self.shared.count(&s.source, |c| {
                c.received += 1;
                c.duplicates += u64::from(entry.is_none());
                if entry.is_some() {
                    c.dropped_points += dropped as u64;
                }
            });
            let Some(entry) = entry else {
                acks.push((done, ack(false)));
                continue;
            };
            let pending = Pending { source: s.source, seq: s.seq, entry, scan: s.scan };
            if options.wait_applied {
                work.push(Waiting { pending, done: Some(done), dropped_points: dropped });
            } else {
                work.push(Waiting { pending, done: None, dropped_points: dropped });
                acks.push((done, ack(true)));
            }
        }
        if !work.is_empty() {
            self.shared.backlog.fetch_add(work.len(), Ordering::Relaxed);
            // Counted before anyone hears of it, so a scan is never missing from the stats.
            let mut st = super::lock(&self.shared.stats);
            for w in &work {
                *st.in_flight.entry(w.pending.source.clone()).or_default() += 1;
            }
            drop(st);
            if let Err(lost) = self.to_writer.send(Work::Scans(work)) {
                // The writer is gone (a bug or a panic): the scans are durable and replay on
                // the next start; tell those who wait.
                if let Work::Scans(w) = lost.0 {
                    for d in w.into_iter().filter_map(|w| w.done) {
                        d(Err(ServiceError::ShuttingDown));
                    }
                }
            }
        }
        for (done, ack) in acks {
            done(Ok(ack));
        }
    }
}
