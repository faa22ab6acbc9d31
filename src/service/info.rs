//! What the service reports about its maps: parameters, sizes, per-source statistics, health.

use super::{MapService, ServiceError, lock};
use crate::core::MapParams;
use std::collections::BTreeMap;
use std::sync::PoisonError;
use std::sync::atomic::Ordering;

/// Per-source statistics: `received`, `duplicates` and `rejected` count since the server
/// started; the rest describe what the map holds (they survive restarts).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SourceStats {
    pub received: u64,
    /// Scans whose evidence is in the map.
    pub applied: u64,
    pub duplicates: u64,
    pub rejected: u64,
    /// Of the scans the writer has taken in (integrated, or replayed on open).
    pub highest_seq: Option<u64>,
    /// Journaled (acknowledged), not yet integrated; `applied + pending` counts every scan the
    /// map has acknowledged.
    pub pending: u64,
    /// Sequence numbers missing between the lowest and the highest (as `highest_seq`).
    pub gaps: u64,
    /// Applied scans whose raw scan was pruned (they cannot be retracted or re-posed).
    pub pruned: u64,
    pub retracted: u64,
    /// Non-finite input points dropped from this source's scans journaled since the server
    /// started (duplicates not counted).
    pub dropped_points: u64,
}

/// Session counters of one source.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SessionCounts {
    pub received: u64,
    pub duplicates: u64,
    pub rejected: u64,
    pub dropped_points: u64,
}

/// What `GetMap` / `ListMaps` report.
#[derive(Debug, Clone)]
pub struct MapInfo {
    pub name: String,
    pub params: MapParams,
    /// The map version (+1 per integrated scan and per retract / re-pose / merge).
    pub version: u64,
    /// Scans whose evidence is in the map.
    pub scans: u64,
    pub blocks: usize,
    pub cells_with_evidence: usize,
    /// Scans waiting to be journaled plus journaled scans waiting to be integrated.
    pub queued: usize,
    /// Time the writer spent integrating scans (training data, evidence, map update), seconds.
    pub integration_seconds_total: f64,
    /// Bytes of raw scans kept in the journal.
    pub journal_bytes: u64,
    pub corrupt_blocks: usize,
    /// Why the map refuses ingest, when it does.
    pub read_only: Option<String>,
    pub sources: BTreeMap<String, SourceStats>,
}

impl MapService {
    /// Every map, by name.
    pub fn list_maps(&self) -> Vec<MapInfo> {
        let names: Vec<String> =
            self.maps.read().unwrap_or_else(PoisonError::into_inner).keys().cloned().collect();
        names.iter().filter_map(|n| self.map_info(n).ok()).collect()
    }

    /// Parameters and statistics of one map.
    pub fn map_info(&self, name: &str) -> Result<MapInfo, ServiceError> {
        let h = self.handle(name)?;
        let sh = &h.shared;
        let snap = sh.snapshot();
        let (content, journal_bytes, in_flight) = {
            let st = lock(&sh.stats);
            (st.content.clone(), st.journal_bytes, st.in_flight.clone())
        };
        let mut sources: BTreeMap<String, SourceStats> = content
            .iter()
            .map(|(s, c)| {
                let stats = SourceStats {
                    applied: c.applied,
                    highest_seq: c.highest_seq,
                    pending: c.pending,
                    gaps: c.gaps,
                    pruned: c.pruned,
                    retracted: c.retracted,
                    ..Default::default()
                };
                (s.clone(), stats)
            })
            .collect();
        for (s, n) in in_flight {
            sources.entry(s).or_default().pending += n;
        }
        for (s, n) in lock(&sh.session).iter() {
            let e = sources.entry(s.clone()).or_default();
            (e.received, e.duplicates, e.rejected, e.dropped_points) =
                (n.received, n.duplicates, n.rejected, n.dropped_points);
        }
        Ok(MapInfo {
            name: name.to_string(),
            params: h.params,
            version: snap.version,
            scans: content.values().map(|c| c.applied).sum(),
            blocks: snap.map.block_count(),
            cells_with_evidence: snap.map.cells_with_evidence(),
            queued: sh.queued.load(Ordering::Relaxed) + sh.backlog.load(Ordering::Relaxed),
            integration_seconds_total: sh.integration_micros.load(Ordering::Relaxed) as f64 / 1e6,
            journal_bytes,
            corrupt_blocks: snap.corrupt.len(),
            read_only: sh.faults.read_only(),
            sources,
        })
    }

    /// Maps that refuse ingest, with the reason (for `/readyz`).
    pub fn degraded(&self) -> Vec<(String, String)> {
        let maps = self.maps.read().unwrap_or_else(PoisonError::into_inner);
        maps.iter().filter_map(|(n, h)| h.shared.faults.read_only().map(|r| (n.clone(), r))).collect()
    }
}
