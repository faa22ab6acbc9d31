//! The evidence map: sparse blocks of fixed-point evidence, and the integrator that turns scans
//! into it.
//!
//! A cell stores only `A = Σ_hits q` and `B = Σ_free q` (unit kernel, fixed point). Everything a
//! reader wants — probability, variance, log-odds, state — is derived on demand from
//! `α = α0 + σ0·A/2^F`, `β = β0 + σ0·B/2^F` (Eq. 1, 2, 7, 9). Cells that never received evidence
//! (both sums zero) answer with the prior (p = 0.5).

use super::evidence::{BlockEvidence, PairGeometry, ScanDelta, Scatter};
use super::kernel::{FIXED_ONE, KernelTable};
use super::key::{BlockKey, CellKey};
use super::params::{MapParams, Thresholds};
use super::training::{TrainingBuilder, TrainingSet};
use rustc_hash::FxHashMap;

/// Free / occupied / unknown under a set of thresholds (Eq. 9).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum CellState {
    Free,
    Occupied,
    Unknown,
}

impl CellState {
    pub fn as_str(self) -> &'static str {
        match self {
            CellState::Free => "free",
            CellState::Occupied => "occupied",
            CellState::Unknown => "unknown",
        }
    }
}

/// The raw evidence of one cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Evidence {
    pub a: i64,
    pub b: i64,
}

impl Evidence {
    pub fn is_empty(self) -> bool {
        self.a == 0 && self.b == 0
    }
}

/// What a reader gets for one cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CellEstimate {
    pub probability: f64,
    pub variance: f64,
    pub state: CellState,
    pub evidence: Evidence,
}

impl CellEstimate {
    /// Eq. 1, 2 and 9 from the stored sums.
    pub fn from_evidence(e: Evidence, params: &MapParams, th: &Thresholds) -> Self {
        let (alpha, beta) = alpha_beta(e, params);
        let w = alpha + beta;
        let probability = alpha / w;
        let variance = alpha * beta / (w * w * (w + 1.0));
        let state = if probability < th.p_free && variance < th.var_max {
            CellState::Free
        } else if probability > th.p_occ && variance < th.var_max {
            CellState::Occupied
        } else {
            CellState::Unknown
        };
        Self { probability, variance, state, evidence: e }
    }

    /// Eq. 7: `log(α/β)`.
    pub fn log_odds(&self, params: &MapParams) -> f64 {
        let (alpha, beta) = alpha_beta(self.evidence, params);
        (alpha / beta).ln()
    }
}

fn alpha_beta(e: Evidence, params: &MapParams) -> (f64, f64) {
    (
        params.prior_a + params.sf2 * (e.a as f64 / FIXED_ONE),
        params.prior_b + params.sf2 * (e.b as f64 / FIXED_ONE),
    )
}

/// A sparse map of evidence blocks with its parameters.
#[derive(Debug, Clone)]
pub struct EvidenceMap {
    params: MapParams,
    blocks: FxHashMap<BlockKey, Box<BlockEvidence>>,
}

impl EvidenceMap {
    /// An empty map. `params` must be valid ([`MapParams::validate`]).
    pub fn new(params: MapParams) -> Self {
        Self { params, blocks: FxHashMap::default() }
    }

    pub fn params(&self) -> &MapParams {
        &self.params
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    pub fn cells_with_evidence(&self) -> usize {
        self.blocks.values().map(|b| b.cells_with_evidence()).sum()
    }

    pub fn block(&self, key: BlockKey) -> Option<&BlockEvidence> {
        self.blocks.get(&key).map(|b| &**b)
    }

    /// Blocks in hash order (callers that emit anything sort first; see [`Self::block_keys_sorted`]).
    pub fn blocks_unsorted(&self) -> impl Iterator<Item = (&BlockKey, &BlockEvidence)> {
        self.blocks.iter().map(|(k, b)| (k, &**b))
    }

    pub fn block_keys_sorted(&self) -> Vec<BlockKey> {
        let mut keys: Vec<BlockKey> = self.blocks.keys().copied().collect();
        keys.sort_unstable();
        keys
    }

    pub fn evidence(&self, cell: CellKey) -> Evidence {
        match self.blocks.get(&cell.block()) {
            Some(b) => {
                let i = cell.index_in_block();
                Evidence { a: b.a[i], b: b.b[i] }
            }
            None => Evidence::default(),
        }
    }

    pub fn estimate(&self, cell: CellKey, th: &Thresholds) -> CellEstimate {
        CellEstimate::from_evidence(self.evidence(cell), &self.params, th)
    }

    /// Adds (`sign` = 1) or removes (`sign` = −1) a scan's evidence. Blocks left without any
    /// evidence are dropped, so removing a scan restores the map exactly.
    pub fn apply(&mut self, delta: &ScanDelta, sign: i64) {
        for (key, d) in &delta.blocks {
            let blk = self.blocks.entry(*key).or_insert_with(BlockEvidence::zeroed);
            blk.add_scaled(d, sign);
            if sign < 0 && blk.is_empty() {
                self.blocks.remove(key);
            }
        }
    }

    /// Inserts a whole block (used by the store when loading). Empty blocks are not kept.
    pub fn insert_block(&mut self, key: BlockKey, block: Box<BlockEvidence>) {
        if block.is_empty() {
            self.blocks.remove(&key);
        } else {
            self.blocks.insert(key, block);
        }
    }

    /// Adds another map's evidence cell by cell (exact). Parameters must be equal.
    pub fn merge_from(&mut self, other: &EvidenceMap) -> Result<(), Vec<String>> {
        let diff = self.params.differences(&other.params);
        if !diff.is_empty() {
            return Err(diff);
        }
        for (key, b) in &other.blocks {
            self.blocks.entry(*key).or_insert_with(BlockEvidence::zeroed).add_scaled(b, 1);
        }
        Ok(())
    }
}

/// Turns scans into evidence deltas. Holds the kernel table and scratch buffers, so a long
/// sequence of scans allocates (almost) nothing.
#[derive(Debug)]
pub struct Integrator {
    params: MapParams,
    geometry: PairGeometry,
    table: KernelTable,
    training: TrainingBuilder,
    set: TrainingSet,
    scatter: Scatter,
}

impl Integrator {
    pub fn new(params: MapParams) -> Self {
        Self {
            geometry: PairGeometry::new(params.resolution_m, params.ell_m),
            params,
            table: KernelTable::new(),
            training: TrainingBuilder::default(),
            set: TrainingSet::default(),
            scatter: Scatter::default(),
        }
    }

    pub fn params(&self) -> &MapParams {
        &self.params
    }

    pub fn geometry(&self) -> &PairGeometry {
        &self.geometry
    }

    pub fn table(&self) -> &KernelTable {
        &self.table
    }

    /// Training data for one scan (world frame, metres).
    pub fn training(&mut self, points_world: &[[f32; 3]], origin_world: [f64; 3]) -> &TrainingSet {
        self.training.build_into(points_world, origin_world, &self.params, &mut self.set);
        &self.set
    }

    /// The evidence one scan adds, computed on `threads` threads (same bits for any count).
    pub fn scan_delta(&mut self, points_world: &[[f32; 3]], origin_world: [f64; 3], threads: usize) -> ScanDelta {
        self.training.build_into(points_world, origin_world, &self.params, &mut self.set);
        if threads <= 1 {
            return self.scatter.delta(&self.set, &self.geometry, &self.table);
        }
        let (geo, table) = (&self.geometry, &self.table);
        let mut pts: Vec<([f64; 3], bool)> = Vec::with_capacity(self.set.len());
        pts.extend(self.set.hits.iter().map(|&p| (super::evidence::to_cell_units(p, geo.res_m), true)));
        pts.extend(self.set.frees.iter().map(|&p| (super::evidence::to_cell_units(p, geo.res_m), false)));
        let chunk = pts.len().div_ceil(threads).max(1);
        let parts = std::thread::scope(|s| {
            let handles: Vec<_> = pts
                .chunks(chunk)
                .map(|c| s.spawn(move || Scatter::default().delta_of(c, geo, table)))
                .collect();
            handles.into_iter().map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect::<Vec<_>>()
        });
        ScanDelta::sum(parts)
    }

    /// Integrates one scan into `map` and returns the number of blocks it touched.
    pub fn integrate(&mut self, map: &mut EvidenceMap, points_world: &[[f32; 3]], origin_world: [f64; 3], threads: usize) -> usize {
        let delta = self.scan_delta(points_world, origin_world, threads);
        let touched = delta.blocks.len();
        map.apply(&delta, 1);
        self.scatter.recycle(delta);
        touched
    }
}
