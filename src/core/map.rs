//! The evidence map: sparse blocks of fixed-point evidence, and the integrator that turns scans
//! into it.
//!
//! A cell stores only `A = Σ_hits q` and `B = Σ_free q` (unit kernel, fixed point). Everything a
//! reader wants — probability, variance, log-odds, state — is derived on demand from
//! `α = α0 + σ0·A/2^F`, `β = β0 + σ0·B/2^F` (Eq. 1, 2, 7, 9). Cells that never received evidence
//! (both sums zero) answer with the prior (p = 0.5).

use super::block_table::BlockTable;
use super::evidence::{BlockEvidence, BlockSummary, PairGeometry, ScanDelta, Scatter};
use super::integrate::kernel::{FIXED_ONE, KernelTable};
use super::key::{BlockKey, CellKey};
use super::params::{MapParams, Thresholds};
use super::integrate::scatter::CellPoint;
use super::integrate::training::{TrainingBuilder, TrainingSet};
use std::sync::{Arc, OnceLock};

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

pub use super::evidence::Evidence;

/// What a reader gets for one cell. `repr(C)`: see [`super::query::PointAnswer`].
#[derive(Debug, Clone, Copy, PartialEq)]
#[repr(C)]
pub struct CellEstimate {
    pub probability: f64,
    pub variance: f64,
    pub state: CellState,
    pub evidence: Evidence,
}

impl CellEstimate {
    /// Eq. 1, 2 and 9 from the stored sums.
    pub fn from_evidence(e: Evidence, params: &MapParams, th: &Thresholds) -> Self {
        Self::from_moments(e, probability_variance(e, params), th)
    }

    /// The estimate of evidence `e` whose [`probability_variance`] is `(probability, variance)`.
    #[inline(always)]
    pub(crate) fn from_moments(e: Evidence, (probability, variance): (f64, f64), th: &Thresholds) -> Self {
        let state = if probability < th.p_free && variance < th.var_max {
            CellState::Free
        } else if probability > th.p_occ && variance < th.var_max {
            CellState::Occupied
        } else {
            CellState::Unknown
        };
        Self { probability, variance, state, evidence: e }
    }

    /// The Beta posterior's parameters `(α, β)`: prior plus kernel-weighted hit / free mass.
    pub fn alpha_beta(&self, params: &MapParams) -> (f64, f64) {
        alpha_beta(self.evidence, params)
    }

    /// Eq. 7: `log(α/β)`.
    pub fn log_odds(&self, params: &MapParams) -> f64 {
        let (alpha, beta) = alpha_beta(self.evidence, params);
        (alpha / beta).ln()
    }
}

/// Eq. 1 and 2: the Beta posterior's mean and variance (the one place they are computed, so a
/// block summary and a cell estimate agree to the bit).
#[inline]
pub(crate) fn probability_variance(e: Evidence, params: &MapParams) -> (f64, f64) {
    let (alpha, beta) = alpha_beta(e, params);
    mean_variance(alpha, beta)
}

/// The mean and variance of Beta(`alpha`, `beta`).
#[inline(always)]
pub(crate) fn mean_variance(alpha: f64, beta: f64) -> (f64, f64) {
    let w = alpha + beta;
    (alpha / w, alpha * beta / (w * w * (w + 1.0)))
}

#[inline(always)]
pub(crate) fn alpha_beta(e: Evidence, params: &MapParams) -> (f64, f64) {
    (
        params.prior_a + params.sf2 * (e.a as f64 / FIXED_ONE),
        params.prior_b + params.sf2 * (e.b as f64 / FIXED_ONE),
    )
}

/// A zero block shared by every caller on this thread (one per thread, so workers do not
/// contend on its reference count): what a map entry holds while its block is taken out.
fn placeholder_block() -> Arc<BlockEvidence> {
    thread_local! {
        static ZERO: Arc<BlockEvidence> = BlockEvidence::zeroed_arc(false);
    }
    ZERO.with(Arc::clone)
}

/// Somewhere a scan's evidence can be added in place, block by block: the map itself or an
/// edit of it. The fast evidence path takes each block it adds to out, changes it (copying it
/// first only if a snapshot shares it) and puts it back, so no per-scan delta is built.
pub trait BlockSink {
    /// Block `key` with its current content (zero if it has none), taken out to be changed;
    /// `wide` says a new block will receive hit mass (a hint: blocks the sink has are taken as
    /// they are, and [`BlockEvidence::make_mut`] widens them).
    fn take_block(&mut self, key: BlockKey, wide: bool) -> Arc<BlockEvidence>;
    /// Puts back a block taken with [`Self::take_block`] after adding evidence to it (so it
    /// holds some: the fast path takes a block only to add mass to it).
    fn put_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>);
    /// Adds (`sign` ≥ 0) or subtracts (`sign` < 0) a scan's delta.
    fn add_delta(&mut self, delta: &ScanDelta, sign: i64);

    /// Block `key` taken out (as [`Self::take_block`]) if the sink has one; `None`, changing
    /// nothing, if it has none.
    fn take_existing_block(&mut self, key: BlockKey) -> Option<Arc<BlockEvidence>>;

    /// Adds a whole block of evidence (another map's, so it holds some) to block `key`; a
    /// block the sink lacks is taken as it is.
    fn add_whole_block(&mut self, key: BlockKey, mut block: Arc<BlockEvidence>) {
        match self.take_existing_block(key) {
            Some(mut mine) => {
                add_whole(&mut mine, &mut block);
                self.put_block(key, mine);
            }
            // Not an emptiness test first: a map's blocks hold evidence, and reading all of
            // one (up to 8 KiB, a block another core has just written) was about a quarter of
            // adding a worker's map in.
            None => self.put_block(key, block),
        }
    }
}

/// `mine += theirs`, leaving the sum in `mine`: added into `theirs` instead (and swapped) where
/// `theirs` is not shared and `mine` is (a snapshot's) or is narrow where `theirs` is wide, so
/// no block is copied or widened that need not be; the sum is the same integers either way.
pub(crate) fn add_whole(mine: &mut Arc<BlockEvidence>, theirs: &mut Arc<BlockEvidence>) {
    let theirs_better = (theirs.is_wide() && !mine.is_wide()) || Arc::get_mut(mine).is_none();
    if theirs_better && Arc::get_mut(theirs).is_some() {
        std::mem::swap(mine, theirs);
    }
    BlockEvidence::make_mut(mine, theirs.is_wide()).add_scaled(theirs, 1);
}

impl BlockSink for EvidenceMap {
    fn take_block(&mut self, key: BlockKey, wide: bool) -> Arc<BlockEvidence> {
        // `put_block` notes the change. The entry stays, holding a shared zero block until
        // `put_block` returns the block: a block that is only updated costs two lookups and no
        // change to the table's layout (removing and re-inserting moved another entry and its
        // slot each time).
        match self.blocks.get_mut(&key) {
            Some(s) => std::mem::replace(&mut s.block, placeholder_block()),
            None => BlockEvidence::zeroed_arc(wide),
        }
    }

    fn put_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>) {
        // Not `insert_shared_block`: its emptiness test reads the whole block (4 or 8 KiB), and a
        // block put back here holds evidence (2% of sample-scan ingest).
        debug_assert!(!block.is_empty(), "a block is put back without evidence");
        self.changes.note(key);
        self.blocks.insert(key, Slot::new(block));
    }

    fn add_delta(&mut self, delta: &ScanDelta, sign: i64) {
        self.apply(delta, sign);
    }

    fn take_existing_block(&mut self, key: BlockKey) -> Option<Arc<BlockEvidence>> {
        self.blocks.get_mut(&key).map(|s| std::mem::replace(&mut s.block, placeholder_block()))
    }
}

/// A sparse map of evidence blocks with its parameters.
///
/// Blocks are shared (`Arc`) and copied on write, so a clone is a cheap immutable snapshot for
/// readers (one reference count per block) while the writer goes on updating its own copy.
#[derive(Debug, Clone)]
pub struct EvidenceMap {
    params: MapParams,
    blocks: BlockTable<Slot>,
    changes: ChangeLog,
}

/// The keys of the blocks changed since [`EvidenceMap::take_changes`] last ran, so whoever
/// publishes snapshots of a map learns what changed from the changes themselves, not by
/// comparing every block of two maps (which cost the server milliseconds per scan on a map of
/// 30k blocks, and grew with the map). A key may be noted for a block that in the end did not
/// change; no changed block goes unnoted.
#[derive(Debug, Default)]
struct ChangeLog {
    keys: Vec<BlockKey>,
    /// False until the first [`EvidenceMap::take_changes`], and after an overflow: what changed
    /// is then unknown.
    complete: bool,
}

impl ChangeLog {
    /// Keys kept at most; past this many the log gives up (and takers compare maps instead).
    const MAX_KEYS: usize = 1 << 20;

    #[inline]
    fn note(&mut self, key: BlockKey) {
        if self.complete {
            if self.keys.len() < Self::MAX_KEYS {
                self.keys.push(key);
            } else {
                (self.complete, self.keys) = (false, Vec::new());
            }
        }
    }
}

/// A clone starts with an unknown history: it is a different map from whatever its
/// changes were counted against.
impl Clone for ChangeLog {
    fn clone(&self) -> Self {
        Self::default()
    }
}

/// A map block and its [`BlockSummary`], computed by the first reader that asks and dropped by
/// every change. It lives beside the block's pointer, so a ray reads it with the hash lookup
/// it makes anyway.
#[derive(Debug, Clone)]
struct Slot {
    block: Arc<BlockEvidence>,
    summary: OnceLock<BlockSummary>,
}

// A block's table entry (its key and slot) fills one cache line, which a batched lookup
// prefetches whole (`block_table::Entry`); a larger slot would take two lines a block.
const _: () = assert!(std::mem::size_of::<super::block_table::Entry<Slot>>() == 64, "entry > 64 bytes");

impl Slot {
    fn new(block: Arc<BlockEvidence>) -> Self {
        Self { block, summary: OnceLock::new() }
    }

    /// A slot with a zero block (`wide` or narrow).
    fn zeroed(wide: bool) -> Self {
        Self::new(BlockEvidence::zeroed_arc(wide))
    }

    /// The block, to change it (copied first if a snapshot shares it, widened first if `wide`:
    /// [`BlockEvidence::make_mut`]).
    fn block_mut(&mut self, wide: bool) -> &mut BlockEvidence {
        self.summary.take();
        BlockEvidence::make_mut(&mut self.block, wide)
    }
}

impl EvidenceMap {
    /// Bytes of block table per block (key, block pointer, summary and slots) at the table's
    /// worst load, for memory figures.
    pub const TABLE_BYTES_PER_BLOCK: usize = BlockTable::<Slot>::WORST_BYTES_PER_ENTRY;

    /// An empty map. `params` must be valid ([`MapParams::validate`]).
    pub fn new(params: MapParams) -> Self {
        Self { params, blocks: BlockTable::default(), changes: ChangeLog::default() }
    }

    /// The keys (sorted, distinct) of every block that may have changed since the last call,
    /// or `None` the first time, after a clone and when too many changed to list: then any
    /// block may have. Starts a new log either way.
    pub fn take_changes(&mut self) -> Option<Vec<BlockKey>> {
        let log = std::mem::replace(&mut self.changes, ChangeLog { keys: Vec::new(), complete: true });
        log.complete.then(|| {
            let mut keys = log.keys;
            keys.sort_unstable();
            keys.dedup();
            keys
        })
    }

    pub fn params(&self) -> &MapParams {
        &self.params
    }

    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    pub fn cells_with_evidence(&self) -> usize {
        self.blocks.values().map(|s| s.block.cells_with_evidence()).sum()
    }

    pub fn block(&self, key: BlockKey) -> Option<&BlockEvidence> {
        self.blocks.get(&key).map(|s| &*s.block)
    }

    /// Keys one [`Self::blocks_of`] call takes at most.
    pub const MAX_BATCH_LOOKUPS: usize = 64;

    /// The blocks of a batch of at most [`Self::MAX_BATCH_LOOKUPS`] keys into `out` (same
    /// length), their lookups staged so the cache misses of the whole batch overlap: all table
    /// slots, then all entries (see [`BlockTable`]).
    pub fn blocks_of<'a>(&'a self, keys: &[Option<BlockKey>], out: &mut [Option<&'a BlockEvidence>]) {
        const MAX: usize = EvidenceMap::MAX_BATCH_LOOKUPS;
        assert!(keys.len() <= MAX && out.len() == keys.len(), "batches of at most {MAX} keys");
        let mut hashes = [None; MAX];
        for (h, k) in hashes.iter_mut().zip(keys) {
            *h = k.map(|k| self.blocks.home(k));
        }
        let mut candidates = [None; MAX];
        for (c, h) in candidates.iter_mut().zip(&hashes[..keys.len()]) {
            *c = h.and_then(|h| self.blocks.candidate(h));
        }
        for ((o, k), c) in out.iter_mut().zip(keys).zip(&candidates) {
            *o = k.and_then(|k| self.blocks.confirm(k, *c)).map(|s| &*s.block);
        }
    }

    /// A block with its [`BlockSummary`] (computed now if no reader asked since it changed).
    pub fn block_with_summary(&self, key: BlockKey) -> Option<(&BlockEvidence, BlockSummary)> {
        self.blocks
            .get(&key)
            .map(|s| (&*s.block, *s.summary.get_or_init(|| BlockSummary::of(&s.block, &self.params))))
    }

    /// A shared handle to one block (cheap: a reference count).
    pub fn block_arc(&self, key: BlockKey) -> Option<Arc<BlockEvidence>> {
        self.blocks.get(&key).map(|s| s.block.clone())
    }

    /// Blocks in table order (callers that emit anything sort first; see [`Self::block_keys_sorted`]).
    pub fn blocks_unsorted(&self) -> impl Iterator<Item = (&BlockKey, &BlockEvidence)> {
        self.blocks.iter().map(|(k, s)| (k, &*s.block))
    }

    pub fn block_keys_sorted(&self) -> Vec<BlockKey> {
        let mut keys: Vec<BlockKey> = self.blocks.keys().copied().collect();
        keys.sort_unstable();
        keys
    }

    pub fn evidence(&self, cell: CellKey) -> Evidence {
        match self.blocks.get(&cell.block()) {
            Some(s) => s.block.get(cell.index_in_block()),
            None => Evidence::default(),
        }
    }

    pub fn estimate(&self, cell: CellKey, th: &Thresholds) -> CellEstimate {
        CellEstimate::from_evidence(self.evidence(cell), &self.params, th)
    }

    /// Adds (`sign` = 1) or removes (`sign` = −1) a scan's evidence. Blocks left without any
    /// evidence are dropped, so removing a scan restores the map exactly.
    pub fn apply(&mut self, delta: &ScanDelta, sign: i64) {
        for (key, d, rows) in delta.iter() {
            self.changes.note(key);
            let wide = rows[0] != 0;
            let blk = self.blocks.get_or_insert_with(key, || Slot::zeroed(wide)).block_mut(wide);
            blk.add_delta(d, sign, rows);
            if sign < 0 && blk.is_empty() {
                self.blocks.remove(&key);
            }
        }
    }

    /// The blocks a delta would produce, without changing the map: `(key, new block)`, `None`
    /// where the block would be left without evidence. Apply them with [`Self::set_blocks`].
    pub fn blocks_after(&self, delta: &ScanDelta, sign: i64) -> Vec<(BlockKey, Option<Arc<BlockEvidence>>)> {
        delta
            .iter()
            .map(|(key, d, rows)| {
                // Wide from the start when the delta brings hit mass.
                let wide = rows[0] != 0;
                let mut b = match self.blocks.get(&key) {
                    Some(old) => old.block.to_box_widened(wide),
                    None if wide => BlockEvidence::zeroed_wide(),
                    None => BlockEvidence::zeroed(),
                };
                b.add_delta(d, sign, rows);
                (key, (!b.is_empty()).then(|| Arc::from(b)))
            })
            .collect()
    }

    /// Replaces blocks (from [`Self::blocks_after`]); `None` removes a block.
    pub fn set_blocks(&mut self, blocks: Vec<(BlockKey, Option<Arc<BlockEvidence>>)>) {
        for (key, b) in blocks {
            self.changes.note(key);
            match b {
                Some(b) => self.blocks.insert(key, Slot::new(b)),
                None => self.blocks.remove(&key),
            };
        }
    }

    /// Inserts a whole block (used by the store when loading). Empty blocks are not kept.
    pub fn insert_block(&mut self, key: BlockKey, block: Box<BlockEvidence>) {
        self.changes.note(key);
        if block.is_empty() {
            self.blocks.remove(&key);
        } else {
            self.blocks.insert(key, Slot::new(Arc::from(block)));
        }
    }

    /// Inserts a block shared with another map (copied on its first write). Empty blocks are
    /// not kept.
    pub fn insert_shared_block(&mut self, key: BlockKey, block: Arc<BlockEvidence>) {
        self.changes.note(key);
        if block.is_empty() {
            self.blocks.remove(&key);
        } else {
            self.blocks.insert(key, Slot::new(block));
        }
    }

    /// Makes blocks `keys` what they are in `other` (shared with it, summaries and all; absent
    /// where `other` has none). A snapshot kept from an earlier version of `other` is brought
    /// up to date this way in the time of what changed since, not of the whole map.
    pub fn copy_blocks_from(&mut self, other: &EvidenceMap, keys: &[BlockKey]) {
        for &key in keys {
            self.changes.note(key);
            match other.blocks.get(&key) {
                Some(slot) => self.blocks.insert(key, slot.clone()),
                None => self.blocks.remove(&key),
            };
        }
    }

    /// Adds every block of this map into `sink` ([`BlockSink::add_whole_block`]: moved in where
    /// `sink` has none): how maps of per-thread work go into the map they were for.
    pub fn add_into<K: BlockSink + ?Sized>(self, sink: &mut K) {
        for (key, block) in self.into_blocks() {
            sink.add_whole_block(key, block);
        }
    }

    /// The map's blocks, taken apart.
    pub(crate) fn into_blocks(self) -> impl Iterator<Item = (BlockKey, Arc<BlockEvidence>)> {
        self.blocks.into_iter().map(|(key, slot)| (key, slot.block))
    }

    /// True when both maps hold the same blocks with the same evidence, cell by cell (tests).
    #[cfg(test)]
    pub(crate) fn same_blocks_as(&self, other: &EvidenceMap) -> bool {
        self.block_keys_sorted() == other.block_keys_sorted()
            && self.block_keys_sorted().into_iter().all(|k| self.block(k) == other.block(k))
    }

    /// True when both maps hold the same keys and share every block (not merely equal ones):
    /// what a map and a fresh clone of it satisfy.
    pub fn shares_blocks_with(&self, other: &EvidenceMap) -> bool {
        self.params == other.params
            && self.blocks.len() == other.blocks.len()
            && self
                .blocks
                .iter()
                .all(|(k, s)| other.blocks.get(k).is_some_and(|o| Arc::ptr_eq(&s.block, &o.block)))
    }

    /// Adds another map's evidence cell by cell (exact). Parameters must be equal.
    pub fn merge_from(&mut self, other: &EvidenceMap) -> Result<(), Vec<String>> {
        let diff = self.params.differences(&other.params);
        if !diff.is_empty() {
            return Err(diff);
        }
        for (key, b) in other.blocks.iter() {
            self.add_whole_block(*key, b.block.clone());
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
    /// With several threads per scan: the training points in cell units, each thread's slab
    /// of them, and the scatters of the threads beyond the first.
    cells: Vec<CellPoint>,
    slabs: Vec<Vec<CellPoint>>,
    helpers: Vec<Scatter>,
}

impl Integrator {
    pub fn new(params: MapParams) -> Self {
        Self {
            geometry: PairGeometry::of(&params),
            params,
            table: KernelTable::new(),
            training: TrainingBuilder::default(),
            set: TrainingSet::default(),
            scatter: Scatter::default(),
            cells: Vec::new(),
            slabs: Vec::new(),
            helpers: Vec::new(),
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
    pub fn scan_delta(
        &mut self,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
    ) -> ScanDelta {
        self.scan_delta_with_range(points_world, origin_world, threads, None)
    }

    /// As [`Self::scan_delta`] with the scan's own maximum range (m), if it has one: the map's
    /// `max_range_m` caps it (0 = unlimited on either side).
    pub fn scan_delta_with_range(
        &mut self,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
        scan_max_range_m: Option<f64>,
    ) -> ScanDelta {
        let params = self.scan_params(scan_max_range_m);
        self.training.build_into(points_world, origin_world, &params, &mut self.set);
        self.training_delta(threads)
    }

    /// The map's parameters with a scan's own maximum range (m), if it has one, capped by the
    /// map's (0 = unlimited on either side).
    fn scan_params(&self, scan_max_range_m: Option<f64>) -> MapParams {
        let mut params = self.params;
        if let Some(r) = scan_max_range_m.filter(|r| *r > 0.0) {
            params.max_range_m = if params.max_range_m > 0.0 { params.max_range_m.min(r) } else { r };
        }
        params
    }

    /// The evidence of the training set built by the last [`Self::training`] call.
    pub fn training_delta(&mut self, threads: usize) -> ScanDelta {
        if threads <= 1 {
            return self.scatter.delta(&self.set, &self.geometry, &self.table);
        }
        let delta_of = |scatter: &mut Scatter,
                        slab: &[CellPoint],
                        geo: &PairGeometry,
                        table: &KernelTable| { scatter.delta_of(slab, geo, table) };
        let (mine, theirs) = self.on_slabs(threads, delta_of, delta_of);
        let parts = std::iter::once(mine).chain(theirs).collect();
        ScanDelta::sum(parts)
    }

    /// Adds the evidence of the training set built by the last [`Self::training`] call to
    /// `sink`, straight into its blocks. The same bits as applying [`Self::training_delta`],
    /// for any number of threads.
    ///
    /// With several threads the points are cut into slabs of whole blocks along x, each with
    /// about as many points. The first slab goes into `sink` on this thread; every other slab
    /// into a map of its own on a thread of its own, whose blocks are then added into `sink`
    /// (new blocks are moved in; only the blocks where the windows of two slabs meet are added
    /// cell by cell). Sums are integers, so the split changes no bit.
    /// Per-thread deltas, summed and then applied, were more than twice as slow as one thread.
    pub fn add_training_into<S: BlockSink + ?Sized>(&mut self, sink: &mut S, threads: usize) {
        if threads <= 1 {
            self.scatter.add_into(&self.set, &self.geometry, &self.table, sink);
            return;
        }
        let params = self.params;
        let (_, maps) = self.on_slabs(
            threads,
            |scatter, slab, geo, table| scatter.add_cells_into(slab, geo, table, sink),
            |scatter, slab, geo, table| {
                let mut own = EvidenceMap::new(params);
                scatter.add_cells_into(slab, geo, table, &mut own);
                own
            },
        );
        for map in maps {
            map.add_into(sink);
        }
    }

    /// Cuts the last training set's points into `threads` slabs of whole blocks along x
    /// ([`slabs_by_block_x`]) and runs `first` on the first slab with this integrator's scatter,
    /// on the calling thread, and `other` on every other non-empty slab with a scatter of its
    /// own (kept between scans), each on a thread of its own. Returns `first`'s result and the
    /// others', in slab order.
    fn on_slabs<A, R: Send>(
        &mut self,
        threads: usize,
        first: impl FnOnce(&mut Scatter, &[CellPoint], &PairGeometry, &KernelTable) -> A,
        other: impl Fn(&mut Scatter, &[CellPoint], &PairGeometry, &KernelTable) -> R + Sync,
    ) -> (A, Vec<R>) {
        let (geo, table) = (&self.geometry, &self.table);
        super::evidence::labelled_cell_points(&self.set, geo, &mut self.cells);
        slabs_by_block_x(&self.cells, threads, &mut self.slabs);
        self.helpers.resize_with(threads.saturating_sub(1), Scatter::default);
        let (head, others) = self.slabs.split_at(1.min(self.slabs.len()));
        let first_slab = head.first().map_or(&[][..], Vec::as_slice);
        std::thread::scope(|scope| {
            let other = &other;
            let handles: Vec<_> = others
                .iter()
                .zip(&mut self.helpers)
                .filter(|(slab, _)| !slab.is_empty())
                .map(|(slab, scatter)| scope.spawn(move || other(scatter, slab, geo, table)))
                .collect();
            let mine = first(&mut self.scatter, first_slab, geo, table);
            let theirs = handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
                .collect();
            (mine, theirs)
        })
    }

    /// Adds one scan's evidence to `sink` ([`Self::scan_delta_with_range`]'s, without the delta).
    pub fn add_scan_into<S: BlockSink + ?Sized>(
        &mut self,
        sink: &mut S,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
        scan_max_range_m: Option<f64>,
    ) {
        let params = self.scan_params(scan_max_range_m);
        self.training.build_into(points_world, origin_world, &params, &mut self.set);
        self.add_training_into(sink, threads);
    }

    /// Returns a delta's block buffers for reuse by later scans.
    pub fn recycle(&mut self, delta: ScanDelta) {
        self.scatter.recycle(delta);
    }

    /// Integrates one scan into `map`.
    pub fn integrate(
        &mut self,
        map: &mut EvidenceMap,
        points_world: &[[f32; 3]],
        origin_world: [f64; 3],
        threads: usize,
    ) {
        self.add_scan_into(map, points_world, origin_world, threads, None);
    }
}

/// Cuts `pts` into `n` slabs of whole blocks along x (block column `x >> BLOCK_SHIFT` of each
/// point's cell), each holding about `1/n` of the points, into `slabs` (cleared first; some
/// may end up empty). Points keep their order within a slab.
fn slabs_by_block_x(pts: &[CellPoint], n: usize, slabs: &mut Vec<Vec<CellPoint>>) {
    use super::key::BLOCK_SHIFT;
    slabs.resize_with(n, Vec::new);
    slabs.iter_mut().for_each(Vec::clear);
    let column = |p: &[f64; 3]| super::evidence::split_point(*p).0[0] >> BLOCK_SHIFT;
    let (Some(lo), Some(hi)) =
        (pts.iter().map(|(p, _)| column(p)).min(), pts.iter().map(|(p, _)| column(p)).max())
    else {
        return;
    };
    // Points per block column, then the first column of each slab: where the running count
    // passes the next multiple of 1/n of the points.
    let mut count = vec![0usize; (i64::from(hi) - i64::from(lo) + 1) as usize];
    for (p, _) in pts {
        count[(column(p) - lo) as usize] += 1;
    }
    let mut slab_of = vec![0usize; count.len()];
    let (mut seen, mut slab) = (0usize, 0usize);
    for (c, &k) in count.iter().enumerate() {
        while slab + 1 < n && seen * n >= (slab + 1) * pts.len() {
            slab += 1;
        }
        slab_of[c] = slab;
        seen += k;
    }
    for &(p, hit) in pts {
        slabs[slab_of[(column(&p) - lo) as usize]].push((p, hit));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::integrate::kernel::unit_kernel;

    fn wall_scan() -> (Vec<[f32; 3]>, [f64; 3]) {
        // A 2 m × 2 m wall at x = 3, sampled every 2 cm, seen from the origin.
        let mut pts = Vec::new();
        for i in 0..100 {
            for j in 0..100 {
                pts.push([3.0, -1.0 + i as f32 * 0.02, -1.0 + j as f32 * 0.02]);
            }
        }
        (pts, [0.05, 0.05, 0.05])
    }

    #[test]
    fn zeroed_blocks_are_empty_in_either_layout() {
        // Dirty chunks of about a block's size first, so some blocks come from memory the
        // allocator reuses rather than from fresh pages.
        for wide in [false, true] {
            let bytes = (8 * crate::core::key::BLOCK_CELLS) << usize::from(wide);
            let dirty: Vec<_> = (0..8).map(|_| vec![0xA5u8; bytes + 16]).collect();
            drop(dirty);
            for _ in 0..8 {
                let b = BlockEvidence::zeroed_arc(wide);
                assert_eq!((b.is_wide(), b.data_bytes()), (wide, bytes));
                assert!(b.is_empty() && b.cells().all(|e| e.is_empty()));
            }
        }
    }

    /// Blocks no hit reaches are kept narrow (half the bytes), through both evidence paths and
    /// a snapshot; the map answers the same either way.
    #[test]
    fn blocks_without_hit_mass_are_narrow() {
        let params = MapParams::default();
        let (pts, o) = wall_scan();
        let mut map = EvidenceMap::new(params);
        let mut integ = Integrator::new(params);
        integ.integrate(&mut map, &pts, o, 1);
        let no_hits = |b: &BlockEvidence| b.cells().all(|e| e.a == 0);
        let count = |m: &EvidenceMap, f: &dyn Fn(&BlockEvidence) -> bool| {
            m.blocks_unsorted().filter(|(_, b)| f(b)).count()
        };
        let (narrow, without_hits) = (count(&map, &|b| !b.is_wide()), count(&map, &no_hits));
        // The free space between the sensor and the wall: most blocks. A block that only a
        // hit window's margin reached may be wide with no hit mass (rounded to 0), not more.
        assert!(narrow > map.block_count() / 2, "{narrow} narrow of {}", map.block_count());
        assert!(narrow * 10 >= without_hits * 9, "{narrow} narrow of {without_hits} without hits");
        // The same scan's delta applied (the general path) widens no block without hit mass,
        // and gives the same cells.
        let mut applied = EvidenceMap::new(params);
        let delta = integ.scan_delta(&pts, o, 1);
        applied.apply(&delta, 1);
        assert!(applied.same_blocks_as(&map));
        assert_eq!(count(&applied, &|b| !b.is_wide()), without_hits);
        // Hits into narrow blocks a snapshot shares: widened copies, the snapshot untouched.
        let snapshot = map.clone();
        let before = snapshot.clone();
        let closer: Vec<[f32; 3]> = pts.iter().map(|p| [1.5, p[1], p[2]]).collect();
        integ.integrate(&mut map, &closer, o, 2);
        assert!(snapshot.same_blocks_as(&before));
        let mut want = before.clone();
        want.apply(&integ.scan_delta(&closer, o, 1), 1);
        assert!(map.same_blocks_as(&want));
        let widened = snapshot
            .blocks_unsorted()
            .filter(|(k, b)| !b.is_wide() && map.block(**k).is_some_and(|m| m.is_wide()))
            .count();
        assert!(widened > 0, "the second wall lies in blocks the first scan left narrow");
    }

    #[test]
    fn cells_far_from_training_data_answer_the_prior() {
        let params = MapParams::default();
        let mut map = EvidenceMap::new(params);
        let (pts, o) = wall_scan();
        Integrator::new(params).integrate(&mut map, &pts, o, 1);
        let th = Thresholds::default();
        for cell in [CellKey::new(100, 100, 100), CellKey::new(30, 0, 20), CellKey::new(-40, 0, 0)] {
            let e = map.estimate(cell, &th);
            assert!(e.evidence.is_empty());
            assert_eq!(e.probability, 0.5);
            assert!((e.variance - 0.2495).abs() < 1e-4, "prior variance α0β0/((α0+β0)²(α0+β0+1))");
            assert_eq!(e.state, CellState::Unknown);
        }
    }

    /// Eq. 8 over the training points where the map holds them: at sub-cell centres by default,
    /// exactly where they are with `sub_cells = 0`.
    #[test]
    fn well_observed_cells_follow_nadaraya_watson() {
        for sub_cells in [8, 0] {
            let params = MapParams { sub_cells, ..MapParams::default() };
            let mut map = EvidenceMap::new(params);
            let (pts, o) = wall_scan();
            let mut integ = Integrator::new(params);
            integ.integrate(&mut map, &pts, o, 1);
            let set = integ.training(&pts, o).clone();
            let geo = PairGeometry::of(&params);
            let placed = |pts: &[[f64; 3]]| -> Vec<[f64; 3]> {
                pts.iter().map(|&p| super::super::evidence::to_cell_units(p, &geo)).collect()
            };
            let (hits, frees) = (placed(&set.hits), placed(&set.frees));
            let mut checked = 0;
            let keys = map.block_keys_sorted();
            let cells = keys.iter().flat_map(|k| (0..crate::core::key::BLOCK_CELLS).map(move |i| k.cell(i)));
            for cell in cells {
                // In cell units: the centre of cell i is i + ½.
                let c = [cell.x, cell.y, cell.z].map(|v| f64::from(v) + 0.5);
                let dist = |p: &[f64; 3]| {
                    ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt()
                };
                let y: f64 = hits.iter().map(|p| unit_kernel(dist(p), geo.ell_cells)).sum();
                let k: f64 = y + frees.iter().map(|p| unit_kernel(dist(p), geo.ell_cells)).sum::<f64>();
                // Eq. 8 holds where the evidence dwarfs the priors (α0 + β0 = 0.002).
                if k < 1.0 {
                    continue;
                }
                let p = map.estimate(cell, &Thresholds::default()).probability;
                assert!((p - y / k).abs() < 1e-3, "cell {cell:?}: p {p} vs Nadaraya–Watson {}", y / k);
                checked += 1;
            }
            assert!(checked > 500, "only {checked} well-observed cells");
            assert_eq!(
                map.estimate(CellKey::new(30, 0, 0), &Thresholds::default()).state,
                CellState::Occupied
            );
            assert_eq!(map.estimate(CellKey::new(15, 0, 0), &Thresholds::default()).state, CellState::Free);
        }
    }

    /// Station keeping: N insertions of one scan give exactly N times its evidence.
    #[test]
    fn repeated_scan_multiplies_evidence_exactly_and_removal_restores() {
        let params = MapParams::default();
        let (pts, o) = wall_scan();
        let mut integ = Integrator::new(params);
        let delta = integ.scan_delta(&pts, o, 1);
        let mut map = EvidenceMap::new(params);
        for _ in 0..15 {
            map.apply(&delta, 1);
        }
        for (key, d) in &delta.blocks {
            let b = map.block(*key).unwrap();
            for i in 0..crate::core::key::BLOCK_CELLS {
                assert_eq!((b.get(i).a, b.get(i).b), (15 * d.a[i], 15 * d.b[i]));
            }
        }
        for _ in 0..15 {
            map.apply(&delta, -1);
        }
        assert_eq!(map.block_count(), 0, "removing every insertion restores the empty map");
    }

    /// Every way of changing a map notes the blocks it changed: after each, the keys whose
    /// blocks differ from a clone taken before are among those `take_changes` lists.
    #[test]
    fn the_change_log_names_every_changed_block() {
        let params = MapParams::default();
        let (pts, o) = wall_scan();
        let mut integ = Integrator::new(params);
        let mut map = EvidenceMap::new(params);
        assert_eq!(map.take_changes(), None, "a new map's history is unknown");
        let delta = integ.scan_delta(&pts, [o[0], o[1] + 0.5, o[2]], 1);
        let mut other = EvidenceMap::new(params);
        integ.integrate(&mut other, &pts, [o[0] + 0.3, o[1], o[2]], 1);
        type Step<'a> = (&'static str, Box<dyn Fn(&mut EvidenceMap) + 'a>);
        let steps: Vec<Step> = vec![
            ("integrate", Box::new(|m| Integrator::new(params).integrate(m, &pts, o, 1))),
            (
                "integrate on 3 threads",
                Box::new(|m| Integrator::new(params).integrate(m, &pts, [o[0], o[1], 0.4], 3)),
            ),
            ("apply", Box::new(|m| m.apply(&delta, 1))),
            ("remove", Box::new(|m| m.apply(&delta, -1))),
            ("merge", Box::new(|m| m.merge_from(&other).unwrap())),
            (
                "edit",
                Box::new(|m| {
                    let blocks = m.blocks_after(&delta, 1);
                    m.set_blocks(blocks);
                }),
            ),
            (
                "insert",
                Box::new(|m| {
                    m.insert_block(
                        BlockKey::new(50, 0, 0),
                        m.block(m.block_keys_sorted()[0]).unwrap().to_box(),
                    )
                }),
            ),
            ("empty", Box::new(|m| m.insert_block(BlockKey::new(50, 0, 0), BlockEvidence::zeroed()))),
        ];
        for (what, step) in &steps {
            let before = map.clone();
            step(&mut map);
            let noted = map.take_changes().expect("the log is complete after a take");
            let keys: std::collections::BTreeSet<BlockKey> =
                before.block_keys_sorted().into_iter().chain(map.block_keys_sorted()).collect();
            let changed: Vec<BlockKey> =
                keys.into_iter().filter(|k| before.block(*k) != map.block(*k)).collect();
            assert!(!changed.is_empty(), "{what} changed something");
            for k in &changed {
                assert!(noted.binary_search(k).is_ok(), "{what} changed {k:?} without noting it");
            }
            let mut copy = before.clone();
            copy.copy_blocks_from(&map, &noted);
            assert!(copy.shares_blocks_with(&map), "{what}: the noted blocks bring a copy up to date");
        }
    }

    #[test]
    fn threads_do_not_change_the_bits() {
        let params = MapParams::default();
        let (pts, o) = wall_scan();
        let mut integ = Integrator::new(params);
        assert_eq!(integ.scan_delta(&pts, o, 1), integ.scan_delta(&pts, o, 2));
        assert_eq!(integ.scan_delta(&pts, o, 1), integ.scan_delta(&pts, o, 5));
    }

    /// A scan split across threads (slabs of blocks, the first straight into the map, the others
    /// through maps of their own) adds the same bits as one thread, scan after scan on a map that
    /// already holds the blocks, and leaves a snapshot taken between scans as it was.
    #[test]
    fn threads_per_scan_add_the_same_bits_into_the_map() {
        let params = MapParams::default();
        let (_, sim) = crate::sim::simulate(3, 6, &crate::sim::Lidar::default());
        let mut scans: Vec<(Vec<[f32; 3]>, [f64; 3])> =
            sim.into_iter().map(|s| (s.points_world, s.origin)).collect();
        scans.push(wall_scan());
        let build = |threads: usize, upto: usize| {
            let (mut map, mut integ) = (EvidenceMap::new(params), Integrator::new(params));
            for (pts, o) in &scans[..upto] {
                integ.integrate(&mut map, pts, *o, threads);
            }
            map
        };
        let one = build(1, scans.len());
        for threads in [2, 3, 8] {
            let (mut map, mut integ) = (EvidenceMap::new(params), Integrator::new(params));
            let mut held = Vec::new();
            for (i, (pts, o)) in scans.iter().enumerate() {
                integ.integrate(&mut map, pts, *o, threads);
                held.push(map.clone());
                assert_eq!(map.take_changes().is_some(), i > 0, "the log is complete after the first take");
            }
            assert!(EvidenceMap::same_blocks_as(&map, &one), "{threads} threads");
            for (i, snap) in held.iter().enumerate().step_by(3) {
                assert!(
                    snap.same_blocks_as(&build(1, i + 1)),
                    "{threads} threads: snapshot after scan {}",
                    i + 1
                );
            }
        }
    }

    #[test]
    fn slabs_split_points_by_block_column_into_even_parts() {
        let mut slabs = Vec::new();
        // Columns of very different weight: 1000 points in block column 0, 10 in each of 1..=40.
        let mut pts: Vec<CellPoint> = (0..1000).map(|i| ([0.5 + (i % 8) as f64, 3.0, 1.0], true)).collect();
        pts.extend((0..400).map(|i| ([8.0 * (1 + i % 40) as f64 + 0.5, 0.0, 0.0], i % 2 == 0)));
        for n in [1, 2, 3, 7] {
            slabs_by_block_x(&pts, n, &mut slabs);
            assert_eq!(slabs.len(), n);
            assert_eq!(slabs.iter().map(Vec::len).sum::<usize>(), pts.len());
            let column = |p: &[f64; 3]| (p[0] as i32) >> super::super::key::BLOCK_SHIFT;
            let mut last = i32::MIN;
            for slab in slabs.iter().filter(|s| !s.is_empty()) {
                let (lo, hi) = (
                    slab.iter().map(|(p, _)| column(p)).min().unwrap(),
                    slab.iter().map(|(p, _)| column(p)).max().unwrap(),
                );
                assert!(lo > last, "slabs of {n} overlap or are out of order");
                last = hi;
            }
            // Each slab past the heavy first column holds at most its share plus one column.
            for slab in slabs.iter().skip(1) {
                assert!(
                    slab.len() <= pts.len() / n + 10,
                    "{n} slabs: {:?}",
                    slabs.iter().map(Vec::len).collect::<Vec<_>>()
                );
            }
        }
        slabs_by_block_x(&[], 3, &mut slabs);
        assert!(slabs.iter().all(Vec::is_empty));
    }

    #[test]
    fn merge_refuses_different_parameters() {
        let a = EvidenceMap::new(MapParams::default());
        let mut b = EvidenceMap::new(MapParams { ell_m: 0.3, ..Default::default() });
        let err = b.merge_from(&a).unwrap_err();
        assert!(err[0].starts_with("ell"), "{err:?}");
    }

    #[test]
    fn log_odds_is_logit_of_probability() {
        let params = MapParams::default();
        let e =
            CellEstimate::from_evidence(Evidence { a: 3 << 24, b: 1 << 24 }, &params, &Thresholds::default());
        let p = e.probability;
        assert!((e.log_odds(&params) - (p / (1.0 - p)).ln()).abs() < 1e-12);
    }
}
