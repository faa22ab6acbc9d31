//! Training points → per-cell evidence (the exact kernel sum of algorithm.md §5).
//!
//! Every cell centre within `ell` of a training point receives that point's quantised unit
//! kernel mass ([`KernelTable::quantized`]): hits add to `A`, free samples to `B`. Sums are
//! `i64` fixed-point with [`FIXED_SHIFT`](super::kernel::FIXED_SHIFT) fractional bits, so they
//! are associative: any scan order, thread count or merge order gives identical bits.
//!
//! The fast path scatters: each training point visits the lattice cells of its support ball and
//! adds into a dense per-scan block accumulator (a slot grid over the scan's block bounding box,
//! no hashing per cell). [`brute_force_cell`] is the gather-side reference used by tests.

use super::kernel::KernelTable;
use super::key::{BLOCK_CELLS, BLOCK_SHIFT, BlockKey, CellKey};
use super::training::TrainingSet;

/// Evidence of one block: occupied mass `a` and free mass `b` per cell (fixed-point, unit kernel).
#[derive(Clone, PartialEq, Eq)]
pub struct BlockEvidence {
    pub a: [i64; BLOCK_CELLS],
    pub b: [i64; BLOCK_CELLS],
}

impl std::fmt::Debug for BlockEvidence {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "BlockEvidence {{ cells with evidence: {} }}", self.cells_with_evidence())
    }
}

impl BlockEvidence {
    pub fn zeroed() -> Box<Self> {
        Box::new(Self { a: [0; BLOCK_CELLS], b: [0; BLOCK_CELLS] })
    }

    pub fn is_empty(&self) -> bool {
        self.a.iter().all(|&v| v == 0) && self.b.iter().all(|&v| v == 0)
    }

    pub fn cells_with_evidence(&self) -> usize {
        self.a.iter().zip(&self.b).filter(|(a, b)| **a != 0 || **b != 0).count()
    }

    /// `self += other` (or `-=` with `sign = -1`), wrapping never expected within i64 range.
    pub fn add_scaled(&mut self, other: &BlockEvidence, sign: i64) {
        for (x, y) in self.a.iter_mut().zip(&other.a) {
            *x += sign * y;
        }
        for (x, y) in self.b.iter_mut().zip(&other.b) {
            *x += sign * y;
        }
    }
}

/// The evidence one scan adds: blocks sorted by key.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScanDelta {
    pub blocks: Vec<(BlockKey, Box<BlockEvidence>)>,
}

impl ScanDelta {
    /// Number of training-point / cell pairs is not kept; this counts cells with evidence.
    pub fn cells_with_evidence(&self) -> usize {
        self.blocks.iter().map(|(_, b)| b.cells_with_evidence()).sum()
    }

    /// Sums several deltas (e.g. per-thread partial results) into one, sorted by block key.
    pub fn sum(parts: Vec<ScanDelta>) -> ScanDelta {
        let mut all: Vec<(BlockKey, Box<BlockEvidence>)> = parts.into_iter().flat_map(|d| d.blocks).collect();
        all.sort_by_key(|(k, _)| *k);
        let mut out: Vec<(BlockKey, Box<BlockEvidence>)> = Vec::with_capacity(all.len());
        for (k, b) in all {
            match out.last_mut() {
                Some((lk, lb)) if *lk == k => lb.add_scaled(&b, 1),
                _ => out.push((k, b)),
            }
        }
        ScanDelta { blocks: out }
    }
}

/// Training points converted to cell units (`x / res`), the coordinates every pair uses.
#[inline]
pub fn to_cell_units(p_m: [f64; 3], res_m: f64) -> [f64; 3] {
    [p_m[0] / res_m, p_m[1] / res_m, p_m[2] / res_m]
}

/// `t = (d/ell)²` for a training point (cell units) and a cell: the one definition of a pair's
/// distance, shared by the fast path and the reference.
#[inline(always)]
pub fn pair_t(p_cells: [f64; 3], cell: CellKey, inv_ell2_cells: f64) -> f64 {
    let dz = f64::from(cell.z) + 0.5 - p_cells[2];
    let dy = f64::from(cell.y) + 0.5 - p_cells[1];
    let dx = f64::from(cell.x) + 0.5 - p_cells[0];
    ((dz * dz + dy * dy) + dx * dx) * inv_ell2_cells
}

/// Geometry shared by the scatter and the reference: resolution and kernel length in cells.
#[derive(Debug, Clone, Copy)]
pub struct PairGeometry {
    pub res_m: f64,
    pub ell_cells: f64,
    pub inv_ell2_cells: f64,
}

impl PairGeometry {
    pub fn new(res_m: f64, ell_m: f64) -> Self {
        let ell_cells = ell_m / res_m;
        Self { res_m, ell_cells, inv_ell2_cells: 1.0 / (ell_cells * ell_cells) }
    }
}

/// Reference: the evidence of one cell by summing over *all* training points (gather, O(N)).
pub fn brute_force_cell(set: &TrainingSet, cell: CellKey, geo: &PairGeometry, table: &KernelTable) -> (i64, i64) {
    let sum = |pts: &[[f64; 3]]| -> i64 {
        pts.iter().map(|&p| table.quantized(pair_t(to_cell_units(p, geo.res_m), cell, geo.inv_ell2_cells))).sum()
    };
    (sum(&set.hits), sum(&set.frees))
}

/// Dense accumulator over the block bounding box of one scan's support.
#[derive(Debug, Default)]
pub struct Accumulator {
    min_block: [i32; 3],
    dims: [i64; 3],
    slots: Vec<u32>,
    blocks: Vec<(BlockKey, Box<BlockEvidence>)>,
    spare: Vec<Box<BlockEvidence>>,
}

const NO_SLOT: u32 = u32::MAX;
/// Above this many block slots the bounding box is split (points are processed in tiles).
const MAX_SLOTS: i64 = 1 << 22;

impl Accumulator {
    /// Prepares for points whose support lies within cell keys `lo..=hi`.
    fn reset(&mut self, lo: [i64; 3], hi: [i64; 3]) {
        let b = |v: i64| (v >> BLOCK_SHIFT) as i32;
        self.min_block = [b(lo[0]), b(lo[1]), b(lo[2])];
        self.dims = [0, 1, 2].map(|i| i64::from(b(hi[i]) - self.min_block[i]) + 1);
        self.slots.clear();
        self.slots.resize((self.dims[0] * self.dims[1] * self.dims[2]) as usize, NO_SLOT);
    }

    #[inline(always)]
    fn grid_index(&self, x: i32, y: i32, z: i32) -> usize {
        let bx = i64::from((x >> BLOCK_SHIFT) - self.min_block[0]);
        let by = i64::from((y >> BLOCK_SHIFT) - self.min_block[1]);
        let bz = i64::from((z >> BLOCK_SHIFT) - self.min_block[2]);
        (bx + self.dims[0] * (by + self.dims[1] * bz)) as usize
    }

    /// The slot of the block holding cell (x, y, z), allocating a zeroed block on first use.
    #[inline(always)]
    fn slot_of(&mut self, x: i32, y: i32, z: i32) -> usize {
        let s = self.grid_index(x, y, z);
        let mut slot = self.slots[s];
        if slot == NO_SLOT {
            slot = self.blocks.len() as u32;
            self.slots[s] = slot;
            let key = BlockKey::new(x >> BLOCK_SHIFT, y >> BLOCK_SHIFT, z >> BLOCK_SHIFT);
            let block = self.spare.pop().unwrap_or_else(BlockEvidence::zeroed);
            self.blocks.push((key, block));
        }
        slot as usize
    }

    /// A view of one (y, z) row of cells, caching its block slots.
    #[inline(always)]
    fn row_mut(&mut self, y: i32, z: i32) -> Row<'_> {
        Row { acc: self, y, z, cached_bx: i32::MIN, cached_slot: 0 }
    }

    /// Returns a delta's blocks for reuse (they are zeroed here, off the hot path's allocator).
    pub fn recycle(&mut self, delta: ScanDelta) {
        for (_, mut b) in delta.blocks {
            b.a.fill(0);
            b.b.fill(0);
            self.spare.push(b);
        }
    }
}

/// One row of cells along x; consecutive x mostly stay in one block, so the slot is cached.
struct Row<'a> {
    acc: &'a mut Accumulator,
    y: i32,
    z: i32,
    cached_bx: i32,
    cached_slot: usize,
}

impl Row<'_> {
    #[inline(always)]
    fn cell_mut(&mut self, x: i32) -> (&mut i64, &mut i64) {
        let bx = x >> BLOCK_SHIFT;
        if bx != self.cached_bx {
            self.cached_bx = bx;
            self.cached_slot = self.acc.slot_of(x, self.y, self.z);
        }
        let i = CellKey::new(x, self.y, self.z).index_in_block();
        let blk = &mut self.acc.blocks[self.cached_slot].1;
        (&mut blk.a[i], &mut blk.b[i])
    }
}

/// Scatters a training set into a [`ScanDelta`]. Reusable across scans.
#[derive(Debug, Default)]
pub struct Scatter {
    acc: Accumulator,
    cells: Vec<([f64; 3], bool)>,
}

impl Scatter {
    /// The exact evidence of `set`: for every cell within `ell` of a training point, the sum of
    /// quantised kernel values over all training points within `ell`.
    pub fn delta(&mut self, set: &TrainingSet, geo: &PairGeometry, table: &KernelTable) -> ScanDelta {
        self.cells.clear();
        self.cells.extend(set.hits.iter().map(|&p| (to_cell_units(p, geo.res_m), true)));
        self.cells.extend(set.frees.iter().map(|&p| (to_cell_units(p, geo.res_m), false)));
        let pts = std::mem::take(&mut self.cells);
        let out = self.delta_of(&pts, geo, table);
        self.cells = pts;
        out
    }

    /// As [`Scatter::delta`] for points already in cell units, labelled (true = hit).
    pub fn delta_of(&mut self, pts: &[([f64; 3], bool)], geo: &PairGeometry, table: &KernelTable) -> ScanDelta {
        let mut parts = Vec::new();
        for tile in tiles(pts, geo.ell_cells) {
            let (lo, hi) = support_bounds(tile, geo.ell_cells);
            self.acc.reset(lo, hi);
            for &(p, hit) in tile {
                scatter_point(&mut self.acc, p, hit, geo, table);
            }
            let mut blocks = std::mem::take(&mut self.acc.blocks);
            blocks.sort_unstable_by_key(|(k, _)| *k);
            parts.push(ScanDelta { blocks });
        }
        if parts.len() == 1 { parts.pop().unwrap_or_default() } else { ScanDelta::sum(parts) }
    }

    pub fn recycle(&mut self, delta: ScanDelta) {
        self.acc.recycle(delta);
    }
}

/// Splits points into runs whose support box has at most `MAX_SLOTS` blocks (a scan with a far
/// outlier would otherwise need a huge slot grid). Most scans are one tile.
fn tiles(pts: &[([f64; 3], bool)], ell_cells: f64) -> Vec<&[([f64; 3], bool)]> {
    let mut out = Vec::new();
    let mut rest = pts;
    while !rest.is_empty() {
        let mut n = rest.len();
        while n > 1 && slot_count(support_bounds(&rest[..n], ell_cells)) > MAX_SLOTS {
            n = n.div_ceil(2);
        }
        out.push(&rest[..n]);
        rest = &rest[n..];
    }
    out
}

fn slot_count((lo, hi): ([i64; 3], [i64; 3])) -> i64 {
    (0..3).map(|i| (hi[i] >> BLOCK_SHIFT) - (lo[i] >> BLOCK_SHIFT) + 1).product()
}

fn support_bounds(pts: &[([f64; 3], bool)], ell_cells: f64) -> ([i64; 3], [i64; 3]) {
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    for (p, _) in pts {
        for i in 0..3 {
            lo[i] = lo[i].min((p[i] - ell_cells - 0.5).floor() as i64);
            hi[i] = hi[i].max((p[i] + ell_cells - 0.5).ceil() as i64);
        }
    }
    (lo, hi)
}

/// Floor without a libm call (baseline x86-64 has no SSE4.1 `roundsd`); exact for |v| < 2^52.
#[inline(always)]
fn floor_i32(v: f64) -> i32 {
    let i = v as i64;
    (if (i as f64) > v { i - 1 } else { i }) as i32
}

#[inline(always)]
fn ceil_i32(v: f64) -> i32 {
    let i = v as i64;
    (if (i as f64) < v { i + 1 } else { i }) as i32
}

/// Slack (cells) on the candidate range so rounding in the square root never loses a cell; the
/// exact membership test is `t < 1` inside [`KernelTable::quantized`].
const RANGE_SLACK: f64 = 1e-6;

#[inline(always)]
fn scatter_point(acc: &mut Accumulator, p: [f64; 3], hit: bool, geo: &PairGeometry, table: &KernelTable) {
    let l = geo.ell_cells + RANGE_SLACK;
    let l2 = l * l;
    // Cell centres sit at k + ½: candidates satisfy |k + ½ − p| < l on each axis.
    let (cz, cy, cx) = (p[2] - 0.5, p[1] - 0.5, p[0] - 0.5);
    for z in ceil_i32(cz - l)..=floor_i32(cz + l) {
        let dz = f64::from(z) + 0.5 - p[2];
        let rz = l2 - dz * dz;
        if rz < 0.0 {
            continue;
        }
        let hy = rz.sqrt();
        for y in ceil_i32(cy - hy)..=floor_i32(cy + hy) {
            let dy = f64::from(y) + 0.5 - p[1];
            let ry = rz - dy * dy;
            if ry < 0.0 {
                continue;
            }
            let hx = ry.sqrt();
            let mut row = acc.row_mut(y, z);
            for x in ceil_i32(cx - hx)..=floor_i32(cx + hx) {
                let q = table.quantized(pair_t(p, CellKey::new(x, y, z), geo.inv_ell2_cells));
                if q != 0 {
                    let (a, b) = row.cell_mut(x);
                    *if hit { a } else { b } += q;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::kernel::FIXED_ONE;
    use crate::core::params::MapParams;
    use crate::core::training::TrainingBuilder;
    use proptest::prelude::*;
    use std::collections::BTreeMap;

    fn delta_cells(d: &ScanDelta) -> BTreeMap<CellKey, (i64, i64)> {
        let mut m = BTreeMap::new();
        for (k, b) in &d.blocks {
            for i in 0..BLOCK_CELLS {
                if b.a[i] != 0 || b.b[i] != 0 {
                    m.insert(k.cell(i), (b.a[i], b.b[i]));
                }
            }
        }
        m
    }

    /// Every cell whose centre is within ell of some training point, by exhaustive search.
    fn candidate_cells(set: &TrainingSet, geo: &PairGeometry) -> Vec<CellKey> {
        let mut out = std::collections::BTreeSet::new();
        let r = geo.ell_cells.ceil() as i32 + 1;
        for p in set.hits.iter().chain(&set.frees) {
            let c = CellKey::from_point(*p, geo.res_m).unwrap();
            for z in -r..=r {
                for y in -r..=r {
                    for x in -r..=r {
                        out.insert(CellKey::new(c.x + x, c.y + y, c.z + z));
                    }
                }
            }
        }
        out.into_iter().collect()
    }

    fn random_scan() -> impl Strategy<Value = (Vec<[f32; 3]>, [f64; 3], f64, f64)> {
        (
            prop::collection::vec((-4.0f32..4.0, -4.0f32..4.0, -2.0f32..2.0), 1..20),
            (-2.0f64..2.0, -2.0f64..2.0, -1.0f64..1.0),
            prop::sample::select(vec![0.1, 0.2]),
            prop::sample::select(vec![0.1, 0.2, 0.3, 0.45]),
        )
            .prop_map(|(pts, o, res, ell)| (pts.into_iter().map(|(x, y, z)| [x, y, z]).collect(), [o.0, o.1, o.2], res, ell))
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// The scatter equals the brute-force gather over all training points, cell by cell.
        #[test]
        fn scatter_equals_brute_force((pts, origin, res, ell) in random_scan()) {
            let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, free_resolution_m: 0.3, max_range_m: 3.0, ..Default::default() };
            let set = TrainingBuilder::default().build(&pts, origin, &params);
            let geo = PairGeometry::new(res, ell);
            let table = KernelTable::new();
            let fast = delta_cells(&Scatter::default().delta(&set, &geo, &table));
            let mut brute = BTreeMap::new();
            // Any cell outside the candidates is farther than ell from every point, so gets 0.
            for cell in candidate_cells(&set, &geo) {
                let (a, b) = brute_force_cell(&set, cell, &geo, &table);
                if a != 0 || b != 0 {
                    brute.insert(cell, (a, b));
                }
            }
            prop_assert_eq!(fast, brute);
        }

        /// Splitting the points across threads (partial deltas summed) gives the same bits.
        #[test]
        fn partial_deltas_sum_to_the_whole((pts, origin, res, ell) in random_scan(), split in 0usize..200) {
            let params = MapParams { resolution_m: res, ell_m: ell, ds_resolution_m: res, ..Default::default() };
            let set = TrainingBuilder::default().build(&pts, origin, &params);
            let geo = PairGeometry::new(res, ell);
            let table = KernelTable::new();
            let labelled: Vec<_> = set.hits.iter().map(|&p| (to_cell_units(p, res), true))
                .chain(set.frees.iter().map(|&p| (to_cell_units(p, res), false))).collect();
            let k = split.min(labelled.len());
            let whole = Scatter::default().delta_of(&labelled, &geo, &table);
            let parts = ScanDelta::sum(vec![
                Scatter::default().delta_of(&labelled[k..], &geo, &table),
                Scatter::default().delta_of(&labelled[..k], &geo, &table),
            ]);
            prop_assert_eq!(delta_cells(&whole), delta_cells(&parts));
        }
    }

    #[test]
    fn far_outliers_are_tiled_not_allocated_densely() {
        let set = TrainingSet { hits: vec![[0.0, 0.0, 0.0], [5000.0, -4000.0, 3000.0]], ..Default::default() };
        let geo = PairGeometry::new(0.1, 0.2);
        let d = Scatter::default().delta(&set, &geo, &KernelTable::new());
        let cells = delta_cells(&d);
        assert!(cells.keys().any(|c| c.x > 40000) && cells.keys().any(|c| c.x < 10));
        // One isolated point at a cell centre: 33 lattice centres within 2 cells, minus those at exactly 2.
        let set = TrainingSet { hits: vec![[0.05, 0.05, 0.05]], ..Default::default() };
        let cells = delta_cells(&Scatter::default().delta(&set, &geo, &KernelTable::new()));
        assert_eq!(cells.len(), 27, "offsets with |d|² < 4 cells²: 1 + 6 + 12 + 8");
        assert_eq!(cells[&CellKey::new(0, 0, 0)].0, FIXED_ONE as i64);
    }
}
