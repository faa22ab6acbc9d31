//! The fast evidence path: training points → per-cell kernel sums, block by block.
//!
//! Points are bucketed by the block of their own cell (a counting sort over the scan's block
//! grid). A point's stencil reaches at most ⌈R/B⌉ blocks beyond its own, so each bucket keeps a
//! small cache of its neighbour delta blocks and every row of a stencil finds its target block
//! with a few shifts — no hashing and no grid lookup per pair. Per point, squared axis distances
//! are computed once per offset; each (y, z) row inside the ball visits only the x offsets whose
//! pair is inside the ball (found by counting, without branches).
//!
//! Every pair's value comes from [`pair_coord`](super::cell_points::pair_coord)'s arithmetic and
//! [`KernelTable::quantized_coord`], so the result equals the brute-force reference bit for bit.
//!
//! Kernel lengths up to 3 cells (la3dm's defaults are 2) take the lane-wise path of
//! [`super::window`]: fixed W³ windows per point in a per-bucket brick, a bucket being
//! [`S`]³ blocks. Longer kernels take the stencil path below, bucketed by
//! block.
//!
//! On one thread, [`Scatter::add_into`] folds the bricks straight into the blocks of a
//! [`BlockSink`] (the map or an edit of it): each block is taken out once per tile, changed in
//! place (copied first only if a snapshot shares it) and put back — no delta blocks to fill,
//! read back into the map and clear. Several threads per scan do the same, each on a slab of
//! the scan's blocks (see `Integrator::add_training_into`). Deltas ([`Scatter::delta`]) remain
//! for removing a scan.
//!
//! # Why it is shaped this way
//!
//! - Buckets of [`S`]³ = 2×2×2 blocks with a brick edge known at compile time: no margins
//!   inside a bucket, and every brick row is a fixed-length vector operation.
//! - Points at sub-cell centres travel as [`SubPoint`]s (16 bytes of fixed point, not 32 of
//!   `f64`), with cells and sub-cells found by shifts: dense scans do not fit the caches, and
//!   every pass over their points waits on memory.
//! - Points are counted straight into bucket order; floors avoid saturating casts and
//!   int-to-float conversions so that their loops vectorise.
//! - A fold region is bounds-checked once, and a block is copied (`Arc::make_mut`) once per
//!   region rather than once per row: the atomic compare-exchange per row was a quarter of
//!   the fold.
//! - Divisions stay divisions (no multiplied reciprocals): retracting a scan recomputes its
//!   evidence, so every version must compute the same bits from the same scan.

use super::cell_points::{CellPoint, PairGeometry, SUB_FRAC, SubPoint, split_point};
use super::delta::{DeltaBlock, RowMask, ScanDelta};
use super::kernel::KernelTable;
use super::sink::BlockSink;
use super::window::{Brick, S, SB, SnappedWindows, window_shape};
use crate::core::block::{BlockEvidence, TakenBlock};
use crate::core::key::{BLOCK_EDGE, BLOCK_SHIFT, BlockKey, CellKey};

/// Above this many block slots the scan is split into tiles of points.
const MAX_SLOTS: i64 = 1 << 22;
const NO_SLOT: u32 = u32::MAX;
const B: i32 = BLOCK_EDGE;

/// What the evidence path needs of a training point: [`CellPoint`]s anywhere, or the compact
/// [`SubPoint`]s when points sit at sub-cell centres (their windows then come from
/// [`SnappedWindows`]).
pub trait ScanPoint: Copy + Default {
    /// The point's coordinates in cell units.
    fn cell_units(&self) -> [f64; 3];
    /// The cell the point lies in.
    fn cell(&self) -> [i32; 3];
    fn is_hit(&self) -> bool;
    /// Block-key bounds of the points' own cells.
    fn block_bounds(pts: &[Self]) -> ([i32; 3], [i32; 3]);
    /// The scatter's buffer of points in bucket order.
    fn sorted(scatter: &mut Scatter) -> &mut Vec<Self>;
    /// Adds the windows of `pts` (all in the bucket starting at cell `origin`) to `brick`, up
    /// to the first that needs a fold first; returns how many it added (see
    /// [`Brick::add_points`]). `snapped` is `Some` whenever the points' geometry has them.
    fn add_to_brick<const W: usize, const W3: usize>(
        brick: &mut Brick,
        pts: &[Self],
        origin: [i32; 3],
        geo: &PairGeometry,
        table: &KernelTable,
        snapped: Option<&SnappedWindows>,
    ) -> usize;
}

impl ScanPoint for CellPoint {
    #[inline(always)]
    fn cell_units(&self) -> [f64; 3] {
        self.0
    }

    #[inline(always)]
    fn cell(&self) -> [i32; 3] {
        self.0.map(super::cell_points::floor_i32)
    }

    #[inline(always)]
    fn is_hit(&self) -> bool {
        self.1
    }

    fn block_bounds(pts: &[Self]) -> ([i32; 3], [i32; 3]) {
        block_bounds(pts)
    }

    fn sorted(scatter: &mut Scatter) -> &mut Vec<Self> {
        &mut scatter.cells_sorted
    }

    #[inline(always)]
    fn add_to_brick<const W: usize, const W3: usize>(
        brick: &mut Brick,
        pts: &[Self],
        origin: [i32; 3],
        geo: &PairGeometry,
        table: &KernelTable,
        snapped: Option<&SnappedWindows>,
    ) -> usize {
        brick.add_points::<W, W3>(pts, origin, geo, table, snapped)
    }
}

impl ScanPoint for SubPoint {
    #[inline(always)]
    fn cell_units(&self) -> [f64; 3] {
        super::cell_points::sub_point_cell_units(self.0)
    }

    #[inline(always)]
    fn cell(&self) -> [i32; 3] {
        self.0.map(|v| v >> SUB_FRAC)
    }

    #[inline(always)]
    fn is_hit(&self) -> bool {
        self.1
    }

    fn block_bounds(pts: &[Self]) -> ([i32; 3], [i32; 3]) {
        let mut lo = [i32::MAX; 3];
        let mut hi = [i32::MIN; 3];
        for (q, _) in pts {
            for i in 0..3 {
                lo[i] = lo[i].min(q[i]);
                hi[i] = hi[i].max(q[i]);
            }
        }
        let block = |v: i32| v >> (SUB_FRAC + BLOCK_SHIFT);
        (lo.map(block), hi.map(block))
    }

    fn sorted(scatter: &mut Scatter) -> &mut Vec<Self> {
        &mut scatter.subs_sorted
    }

    #[inline(always)]
    fn add_to_brick<const W: usize, const W3: usize>(
        brick: &mut Brick,
        pts: &[Self],
        _origin: [i32; 3],
        _geo: &PairGeometry,
        _table: &KernelTable,
        snapped: Option<&SnappedWindows>,
    ) -> usize {
        brick.add_sub_points::<W, W3>(pts, snapped.expect("sub-cell points have snapped windows"))
    }
}

/// Scatters training points into a [`ScanDelta`]; keeps scratch space between scans.
#[derive(Debug, Default)]
pub struct Scatter {
    grid: SlotGrid,
    /// Per point: its bucket (block slot).
    bucket_of: Vec<u32>,
    /// Bucket start offsets into `cells_sorted` (counting sort), and the next free place of
    /// each bucket while sorting.
    starts: Vec<u32>,
    next: Vec<u32>,
    /// The same for the second half of the points (see [`Self::bucket`]).
    next_b: Vec<u32>,
    /// The slots of the bucket grid in the order the window path visits them.
    order: Vec<u32>,
    /// Per bucket: delta-block index of each neighbour offset ((2M+1)³ entries, M = ⌈R/B⌉).
    neighbours: Vec<u32>,
    delta: SlotGrid,
    spare: Vec<Box<DeltaBlock>>,
    cells: Vec<CellPoint>,
    /// The points of the current tile in bucket order.
    cells_sorted: Vec<CellPoint>,
    /// The same for sub-cell points.
    subs: Vec<SubPoint>,
    subs_sorted: Vec<SubPoint>,
    brick: Brick,
    /// The precomputed windows of points at sub-cell centres (built on first use).
    snapped: SnappedWindows,
    /// Blocks taken out of a [`BlockSink`] while a tile is folded into them.
    taken: Vec<(BlockKey, TakenBlock)>,
}

/// A dense grid of block slots over a box of block keys.
#[derive(Debug, Default)]
struct SlotGrid {
    min: [i32; 3],
    dims: [i64; 3],
    slots: Vec<u32>,
    blocks: Vec<(BlockKey, Box<DeltaBlock>)>,
    /// Per block, the rows written so far (see [`ScanDelta::rows`]).
    rows: Vec<RowMask>,
}

impl SlotGrid {
    fn reset(&mut self, lo: [i32; 3], hi: [i32; 3]) {
        debug_assert!(self.blocks.is_empty() && self.rows.is_empty(), "blocks handed out before a reset");
        self.min = lo;
        self.dims = [0, 1, 2].map(|i| i64::from(hi[i]) - i64::from(lo[i]) + 1);
        self.slots.clear();
        self.slots.resize((self.dims[0] * self.dims[1] * self.dims[2]) as usize, NO_SLOT);
    }

    #[inline(always)]
    fn index(&self, b: [i32; 3]) -> usize {
        let o = [0, 1, 2].map(|i| i64::from(b[i]) - i64::from(self.min[i]));
        (o[0] + self.dims[0] * (o[1] + self.dims[1] * o[2])) as usize
    }

    /// The index (into `blocks`) of the block at key `b`, allocated (zeroed) on first use.
    fn block_index(&mut self, b: [i32; 3], spare: &mut Vec<Box<DeltaBlock>>) -> u32 {
        let s = self.index(b);
        if self.slots[s] == NO_SLOT {
            self.slots[s] = self.blocks.len() as u32;
            let fresh = spare.pop().unwrap_or_else(DeltaBlock::zeroed);
            self.blocks.push((BlockKey::new(b[0], b[1], b[2]), fresh));
            self.rows.push([0; 2]);
        }
        self.slots[s]
    }
}

impl Scatter {
    /// The exact evidence of a training set (world metres): for every cell within `ell` of a
    /// training point, the sum of quantised kernel values over all training points within `ell`.
    pub fn delta(
        &mut self,
        set: &super::training::TrainingSet,
        geo: &PairGeometry,
        table: &KernelTable,
    ) -> ScanDelta {
        let mut subs = std::mem::take(&mut self.subs);
        let compact = self.sub_points(set, geo, table, &mut subs);
        let out = if compact {
            self.delta_of(&subs, geo, table)
        } else {
            let mut cells = std::mem::take(&mut self.cells);
            super::cell_points::labelled_cell_points(set, geo, &mut cells);
            let out = self.delta_of(&cells, geo, table);
            self.cells = cells;
            out
        };
        self.subs = subs;
        out
    }

    /// The training set as [`SubPoint`]s into `out` when the window path with snapped windows
    /// takes it (points at sub-cell centres, a kernel of at most 3 cells, a window table that
    /// fits, no point beyond the fixed point's range); false otherwise.
    fn sub_points(
        &mut self,
        set: &super::training::TrainingSet,
        geo: &PairGeometry,
        table: &KernelTable,
        out: &mut Vec<SubPoint>,
    ) -> bool {
        let Some((w, _)) = window_shape(geo.ell_cells).filter(|&(_, m)| m <= B as usize) else {
            return false;
        };
        geo.sub_cells > 0
            && self.prepare_snapped(w, geo, table)
            && super::cell_points::labelled_sub_points(set, geo, out)
    }

    /// Builds the snapped windows of width `w` for `geo` (see [`SnappedWindows::prepare`]).
    fn prepare_snapped(&mut self, w: usize, geo: &PairGeometry, table: &KernelTable) -> bool {
        match w {
            1 => self.snapped.prepare::<1, 1>(geo, table),
            2 => self.snapped.prepare::<2, 8>(geo, table),
            3 => self.snapped.prepare::<3, 27>(geo, table),
            4 => self.snapped.prepare::<4, 64>(geo, table),
            5 => self.snapped.prepare::<5, 125>(geo, table),
            _ => self.snapped.prepare::<6, 216>(geo, table),
        }
    }

    /// As [`Scatter::delta`] for points already in cell units, as
    /// [`labelled_cell_points`](super::cell_points::labelled_cell_points) gives them for `geo`
    /// (with `geo.sub_cells > 0`, at sub-cell centres: their windows are looked up by sub-cell).
    pub fn delta_of<P: ScanPoint>(
        &mut self,
        pts: &[P],
        geo: &PairGeometry,
        table: &KernelTable,
    ) -> ScanDelta {
        let r = geo.radius_cells();
        let mut parts = Vec::new();
        let mut rest = pts;
        while !rest.is_empty() {
            let (n, bounds) = tile_len(rest, r);
            let (tile, tail) = rest.split_at(n);
            parts.push(self.delta_of_tile(tile, bounds, geo, table, r));
            rest = tail;
        }
        if parts.len() == 1 { parts.pop().unwrap_or_default() } else { ScanDelta::sum(parts) }
    }

    /// Adds the exact evidence of a training set (as [`Scatter::delta`] computes it) straight
    /// into `sink`'s blocks: the same bits as applying the delta, without building one.
    pub fn add_into<S: BlockSink + ?Sized>(
        &mut self,
        set: &super::training::TrainingSet,
        geo: &PairGeometry,
        table: &KernelTable,
        sink: &mut S,
    ) {
        let mut subs = std::mem::take(&mut self.subs);
        if self.sub_points(set, geo, table, &mut subs) {
            self.add_cells_into(&subs, geo, table, sink);
        } else {
            let mut cells = std::mem::take(&mut self.cells);
            super::cell_points::labelled_cell_points(set, geo, &mut cells);
            self.add_cells_into(&cells, geo, table, sink);
            self.cells = cells;
        }
        self.subs = subs;
    }

    /// As [`Scatter::add_into`] for points already in cell units, as
    /// [`labelled_cell_points`](super::cell_points::labelled_cell_points) gives them for `geo`
    /// (with `geo.sub_cells > 0`, at sub-cell centres: their windows are looked up by sub-cell).
    pub fn add_cells_into<P: ScanPoint, S: BlockSink + ?Sized>(
        &mut self,
        pts: &[P],
        geo: &PairGeometry,
        table: &KernelTable,
        sink: &mut S,
    ) {
        let r = geo.radius_cells();
        let Some((w, margin)) = window_shape(geo.ell_cells).filter(|&(_, m)| m <= B as usize) else {
            // Long kernels: the stencil path builds a delta.
            let delta = self.delta_of(pts, geo, table);
            sink.add_delta(&delta, 1);
            self.recycle(delta);
            return;
        };
        let mut rest = pts;
        while !rest.is_empty() {
            let (n, (lo, hi)) = tile_len(rest, r);
            let (tile, tail) = rest.split_at(n);
            let blocks = self.bucket_windows(tile, lo, hi);
            let mut slots = std::mem::take(&mut self.delta);
            slots.reset(blocks.0, blocks.1);
            let mut taken = std::mem::take(&mut self.taken);
            let mut target = SinkTarget { slots: &mut slots, taken: &mut taken, sink: &mut *sink };
            self.windows_of_width::<P>(w, geo, table, margin, &mut target);
            for (key, block) in taken.drain(..) {
                sink.put_block(key, block.into_inner());
            }
            (self.delta, self.taken) = (slots, taken);
            rest = tail;
        }
    }

    /// Returns a delta's blocks for reuse by later scans.
    pub fn recycle(&mut self, delta: ScanDelta) {
        let rows: Vec<RowMask> = (0..delta.blocks.len()).map(|i| delta.rows_of(i)).collect();
        for ((_, mut b), r) in delta.blocks.into_iter().zip(rows) {
            b.clear_rows(r);
            self.spare.push(b);
        }
    }

    fn delta_of_tile<P: ScanPoint>(
        &mut self,
        pts: &[P],
        (lo, hi): ([i32; 3], [i32; 3]),
        geo: &PairGeometry,
        table: &KernelTable,
        r: i32,
    ) -> ScanDelta {
        let shape = window_shape(geo.ell_cells).filter(|&(_, m)| m <= B as usize);
        let exact_blocks = shape.is_some();
        match shape {
            Some((w, margin)) => {
                let blocks = self.bucket_windows(pts, lo, hi);
                self.delta.reset(blocks.0, blocks.1);
                let mut delta = std::mem::take(&mut self.delta);
                let mut spare = std::mem::take(&mut self.spare);
                let mut target = DeltaTarget { delta: &mut delta, spare: &mut spare };
                self.windows_of_width::<P>(w, geo, table, margin, &mut target);
                (self.delta, self.spare) = (delta, spare);
            }
            None => {
                self.bucket(pts, lo, hi, BLOCK_SHIFT);
                // Delta blocks reach R cells beyond the points' blocks: at most M = ⌈R/B⌉
                // blocks further.
                let m = (r + B - 1) / B;
                self.delta.reset(lo.map(|v| v - m), hi.map(|v| v + m));
                self.stencils::<P>(geo, table, r, m);
            }
        }
        let blocks = std::mem::take(&mut self.delta.blocks);
        let rows = std::mem::take(&mut self.delta.rows);
        let mut all: Vec<_> = blocks.into_iter().zip(rows).collect();
        // A block reached only by pairs whose mass rounds to 0 holds nothing: drop it. (The
        // window path allocates only blocks that receive mass; masses are never negative.)
        if !exact_blocks {
            all.retain(|((_, b), _)| !b.is_empty());
        }
        all.sort_unstable_by_key(|((k, _), _)| *k);
        let (blocks, rows) = all.into_iter().unzip();
        ScanDelta { blocks, rows }
    }

    /// The general path: per point, the rows of its stencil inside the ball.
    fn stencils<P: ScanPoint>(&mut self, geo: &PairGeometry, table: &KernelTable, r: i32, m: i32) {
        let side = (2 * m + 1) as usize;
        for s in 0..self.grid.slots.len() {
            let (start, end) = (self.starts[s] as usize, self.starts[s + 1] as usize);
            if start == end {
                continue;
            }
            let block = self.grid_block_of_slot(s);
            self.neighbours.clear();
            self.neighbours.resize(side * side * side, NO_SLOT);
            let mut target = Targets { block, m, side, scatter: self };
            for k in start..end {
                let point = P::sorted(target.scatter)[k];
                scatter_point(&mut target, point.cell_units(), point.is_hit(), r, geo, table);
            }
        }
    }

    /// The lane-wise path ([`super::window`]): one brick per bucket, folded into `target`.
    fn windows<const W: usize, const W3: usize, P: ScanPoint>(
        &mut self,
        geo: &PairGeometry,
        table: &KernelTable,
        margin: usize,
        target: &mut impl FoldTarget,
    ) {
        self.brick.reset(margin);
        let snapped = self.snapped.prepare::<W, W3>(geo, table);
        // Points in bucket order (see `bucket`), so each bucket reads one contiguous run.
        let sorted = std::mem::take(P::sorted(self));
        // Buckets in Morton order (see `morton_order`).
        let mut order = std::mem::take(&mut self.order);
        morton_order(self.grid.dims, &mut order);
        for &s in &order {
            let s = s as usize;
            let (start, end) = (self.starts[s] as usize, self.starts[s + 1] as usize);
            if start == end {
                continue;
            }
            // The bucket's first cell and first block.
            let bucket = self.grid_block_of_slot(s);
            let (origin, block) = (bucket.map(|v| v * SB as i32), bucket.map(|v| v * S as i32));
            // Folded when done, and before any point the brick cannot take.
            let mut rest = &sorted[start..end];
            let windows = snapped.then_some(&self.snapped);
            loop {
                let n = P::add_to_brick::<W, W3>(&mut self.brick, rest, origin, geo, table, windows);
                rest = &rest[n..];
                fold_brick(&mut self.brick, block, target);
                if rest.is_empty() {
                    break;
                }
            }
        }
        *P::sorted(self) = sorted;
        self.order = order;
    }

    /// Runs the window path of width `w` (1..=6) into `target`.
    fn windows_of_width<P: ScanPoint>(
        &mut self,
        w: usize,
        geo: &PairGeometry,
        table: &KernelTable,
        margin: usize,
        target: &mut impl FoldTarget,
    ) {
        match w {
            1 => self.windows::<1, 1, P>(geo, table, margin, target),
            2 => self.windows::<2, 8, P>(geo, table, margin, target),
            3 => self.windows::<3, 27, P>(geo, table, margin, target),
            4 => self.windows::<4, 64, P>(geo, table, margin, target),
            5 => self.windows::<5, 125, P>(geo, table, margin, target),
            _ => self.windows::<6, 216, P>(geo, table, margin, target),
        }
    }

    fn grid_block_of_slot(&self, s: usize) -> [i32; 3] {
        let d = self.grid.dims;
        let s = s as i64;
        let o = [s % d[0], (s / d[0]) % d[1], s / (d[0] * d[1])];
        [0, 1, 2].map(|i| (i64::from(self.grid.min[i]) + o[i]) as i32)
    }

    /// Buckets the points of the window path by the `S`³ blocks their cell lies in (`lo`, `hi`:
    /// the block bounds of their cells), and returns the bounds of the blocks their windows
    /// reach: those buckets' blocks and one more each side (a window reaches its margin,
    /// at most 3 cells, beyond its bucket).
    fn bucket_windows<P: ScanPoint>(
        &mut self,
        pts: &[P],
        lo: [i32; 3],
        hi: [i32; 3],
    ) -> ([i32; 3], [i32; 3]) {
        let shift = S.trailing_zeros();
        let (lo, hi) = (lo.map(|v| v >> shift), hi.map(|v| v >> shift));
        self.bucket(pts, lo, hi, BLOCK_SHIFT + shift);
        (lo.map(|v| v * S as i32 - 1), hi.map(|v| v * S as i32 + S as i32))
    }

    /// Counting sort of the points by the slot of the bucket (`2^shift` cells a side) of their
    /// cell, into the buffer of their type ([`ScanPoint::sorted`]), where a bucket is one
    /// contiguous run, from `starts[s]` to `starts[s + 1]`; `lo`, `hi` are the bucket bounds.
    fn bucket<P: ScanPoint>(&mut self, pts: &[P], lo: [i32; 3], hi: [i32; 3], shift: u32) {
        self.grid.reset(lo, hi);
        let n_slots = self.grid.slots.len();
        self.starts.clear();
        self.starts.resize(n_slots + 1, 0);
        // Slots in a loop of their own (no pushes or counts in it), so that its floors
        // vectorise; then the counts.
        self.bucket_of.clear();
        let grid = &self.grid;
        self.bucket_of.extend(pts.iter().map(|p| grid.index(p.cell().map(|v| v >> shift)) as u32));
        // The two halves of the points counted and placed side by side, each with counters of
        // its own: neighbouring points mostly share a bucket, and with one set of counters
        // every count and every place waited for the previous one's store.
        let half = pts.len() / 2;
        // Every place is written below (the sort is a permutation), so what a previous call
        // left there needs no zeroing.
        let mut sorted = std::mem::take(P::sorted(self));
        sorted.resize(pts.len(), P::default());
        let (first, second) = self.bucket_of.split_at(half);
        // The second half's counts, turned into its places below.
        let mut next_b = std::mem::take(&mut self.next_b);
        next_b.clear();
        next_b.resize(n_slots, 0);
        for (&s, &t) in first.iter().zip(second) {
            self.starts[s as usize + 1] += 1;
            next_b[t as usize] += 1;
        }
        if let Some(&t) = second.get(half) {
            next_b[t as usize] += 1;
        }
        // Bucket s: the first half's points from `starts[s]`, then the second half's from
        // `next_b[s]` (so a bucket keeps the points' order).
        for s in 0..n_slots {
            let (a, b) = (self.starts[s + 1], next_b[s]);
            next_b[s] = self.starts[s] + a;
            self.starts[s + 1] = self.starts[s] + a + b;
        }
        let next = &mut self.next;
        next.clear();
        next.extend_from_slice(&self.starts[..n_slots]);
        let (pts_a, pts_b) = pts.split_at(half);
        for (((&s, &t), &p), &q) in first.iter().zip(second).zip(pts_a).zip(pts_b) {
            let at = &mut next[s as usize];
            sorted[*at as usize] = p;
            *at += 1;
            let at = &mut next_b[t as usize];
            sorted[*at as usize] = q;
            *at += 1;
        }
        if let (Some(&t), Some(&q)) = (second.get(half), pts_b.get(half)) {
            sorted[next_b[t as usize] as usize] = q;
        }
        *P::sorted(self) = sorted;
        self.next_b = next_b;
    }
}

/// Where a folded brick's rows go: the blocks of a per-scan delta, or a map's own blocks.
trait FoldTarget {
    type Block<'a>: FoldBlock
    where
        Self: 'a;
    /// The block at key `b`, taken or allocated on first use; `hits` when the rows to come
    /// may hold hit mass.
    fn block(&mut self, b: [i32; 3], hits: bool) -> Self::Block<'_>;
}

/// One block of a [`FoldTarget`], open for adding rows.
trait FoldBlock {
    /// Adds the hit mass `a` and the free mass `b` to row `row` (`8z + y`) from cell `x` on,
    /// and zeroes both.
    fn add_row<const N: usize>(&mut self, row: usize, x: usize, a: &mut [u32; N], b: &mut [u32; N]);
    /// As [`Self::add_row`] for a row whose hit mass is zero: adds and zeroes `b` only.
    fn add_free_row<const N: usize>(&mut self, row: usize, x: usize, b: &mut [u32; N]);
}

/// Folds into the scatter's delta blocks.
struct DeltaTarget<'a> {
    delta: &'a mut SlotGrid,
    spare: &'a mut Vec<Box<DeltaBlock>>,
}

/// A delta block and its row mask.
struct DeltaRows<'a> {
    block: &'a mut DeltaBlock,
    rows: &'a mut RowMask,
}

impl FoldTarget for DeltaTarget<'_> {
    type Block<'a>
        = DeltaRows<'a>
    where
        Self: 'a;

    #[inline(always)]
    fn block(&mut self, b: [i32; 3], _hits: bool) -> DeltaRows<'_> {
        let i = self.delta.block_index(b, self.spare) as usize;
        DeltaRows { block: &mut self.delta.blocks[i].1, rows: &mut self.delta.rows[i] }
    }
}

impl DeltaRows<'_> {
    /// Adds `src` to label `label`'s row `row` from cell `x` on and zeroes it.
    #[inline(always)]
    fn add_label_row<const N: usize>(&mut self, label: usize, row: usize, x: usize, src: &mut [u32; N]) {
        if src.iter().any(|&v| v != 0) {
            self.rows[label] |= 1 << row;
            let at = row * B as usize + x;
            let dst = if label == 0 { &mut self.block.a } else { &mut self.block.b };
            for (d, s) in dst[at..at + N].iter_mut().zip(src.iter_mut()) {
                *d += i64::from(*s);
                *s = 0;
            }
        }
    }
}

impl FoldBlock for DeltaRows<'_> {
    #[inline(always)]
    fn add_row<const N: usize>(&mut self, row: usize, x: usize, a: &mut [u32; N], b: &mut [u32; N]) {
        self.add_label_row(0, row, x, a);
        self.add_label_row(1, row, x, b);
    }

    #[inline(always)]
    fn add_free_row<const N: usize>(&mut self, row: usize, x: usize, b: &mut [u32; N]) {
        self.add_label_row(1, row, x, b);
    }
}

/// Folds straight into the blocks of a [`BlockSink`], each taken out once per tile.
struct SinkTarget<'a, S: BlockSink + ?Sized> {
    slots: &'a mut SlotGrid,
    taken: &'a mut Vec<(BlockKey, TakenBlock)>,
    sink: &'a mut S,
}

impl<S: BlockSink + ?Sized> FoldTarget for SinkTarget<'_, S> {
    type Block<'a>
        = &'a mut BlockEvidence
    where
        Self: 'a;

    #[inline(always)]
    fn block(&mut self, b: [i32; 3], hits: bool) -> &mut BlockEvidence {
        let s = self.slots.index(b);
        if self.slots.slots[s] == NO_SLOT {
            self.slots.slots[s] = self.taken.len() as u32;
            let key = BlockKey::new(b[0], b[1], b[2]);
            self.taken.push((key, TakenBlock::new(self.sink.take_block(key, hits))));
        }
        // Copies the block first only if a snapshot shares it, widens it if hit mass comes to
        // a narrow one.
        self.taken[self.slots.slots[s] as usize].1.get(hits)
    }
}

impl FoldBlock for &mut BlockEvidence {
    #[inline(always)]
    fn add_row<const N: usize>(&mut self, row: usize, x: usize, a: &mut [u32; N], b: &mut [u32; N]) {
        self.fold_row(row * B as usize + x, a, b);
    }

    #[inline(always)]
    fn add_free_row<const N: usize>(&mut self, row: usize, x: usize, b: &mut [u32; N]) {
        self.fold_free_row(row * B as usize + x, b);
    }
}

/// Adds the touched regions of the brick into the blocks around `block` (the bucket's) in
/// `target`, zeroing them.
///
fn fold_brick(brick: &mut Brick, block: [i32; 3], target: &mut impl FoldTarget) {
    // The margin is 1 to 3 cells for every width the window path compiles (`window_shape`);
    // a margin and edge known at compile time make every row a fixed-length vector operation.
    match brick.margin() {
        1 => fold_brick_with::<1, { SB + 2 }>(brick, block, target),
        2 => fold_brick_with::<2, { SB + 4 }>(brick, block, target),
        3 => fold_brick_with::<3, { SB + 6 }>(brick, block, target),
        m => unreachable!("brick margin {m} outside 1..=3"),
    }
}

/// Folds a brick of margin `M` and edge `E = S·B + 2M` whose first block is `block`, by rows
/// of regions: the regions that share a y and a z range (along x the low margin, the `S`
/// blocks and the high margin) are tested together, one brick row of `E` cells at a time
/// (when no margin of them was touched, just the blocks' cells), and then each x region's rows
/// with mass are folded into its block. Testing a row's parts in one pass, not region by
/// with mass are folded into its block. Testing a row's parts in one pass, not region by
/// region, matters because the margins' rows are two cells wide: testing them on their own
/// costs as much as testing the block's.
///
/// Rows no hit window reached (half the blocks of an outdoor drive see free mass only) are
/// tested on their `b` cells and folded as free rows, `a` neither read, added nor zeroed.
fn fold_brick_with<const M: usize, const E: usize>(
    brick: &mut Brick,
    block: [i32; 3],
    target: &mut impl FoldTarget,
) {
    const R: usize = S + 2;
    let b = B as usize;
    debug_assert_eq!((brick.edge(), E), (SB + 2 * M, SB + 2 * M));
    // Per region along an axis: (first brick cell, first target cell, length).
    let span = |r: usize| match r {
        0 => (0, b - M, M),
        r if r <= S => (M + (r - 1) * b, 0, b),
        _ => (M + SB, 0, M),
    };
    let touched = brick.touched[0] | brick.touched[1];
    let hit_touched = brick.touched[0];
    let (cells_a, cells_b) = (&mut brick.a[..], &mut brick.b[..]);
    for rz in 0..R {
        for ry in 0..R {
            let xs = touched >> (R * (ry + R * rz)) & ((1 << R) - 1);
            if xs == 0 {
                continue;
            }
            let (y, z) = (span(ry), span(rz));
            let at = |zi: usize, yi: usize| ((z.0 + zi) * E + y.0 + yi) * E;
            // Rows with mass per x region, bit 8z + y (a region is at most 8 × 8 rows). Where no
            // hit window touched the regions of these rows, their `a` cells are all zero and
            // only the `b` cells are read.
            let hits = hit_touched >> (R * (ry + R * rz));
            let rows = if hits & ((1 << R) - 1) == 0 {
                rows_with_mass::<M, E, false>(cells_a, cells_b, xs, y, z, at)
            } else {
                rows_with_mass::<M, E, true>(cells_a, cells_b, xs, y, z, at)
            };
            // Per x region, its block's key and whether a hit window touched the region (else
            // its `a` cells are zero, and the block may stay narrow).
            let key =
                |rx: usize| ([0, 1, 2].map(|i| block[i] + [rx, ry, rz][i] as i32 - 1), hits >> rx & 1 != 0);
            let rows_of = (y, z, at);
            fold_rows::<M>(cells_a, cells_b, rows[0], (0, b - M), rows_of, key(0), target);
            for rx in 1..=S {
                fold_rows::<8>(cells_a, cells_b, rows[rx], (M + (rx - 1) * b, 0), rows_of, key(rx), target);
            }
            fold_rows::<M>(cells_a, cells_b, rows[R - 1], (M + SB, 0), rows_of, key(R - 1), target);
        }
    }
    brick.folded();
}

/// Per x region of a fold's rows `y`, `z` (the region spans along y and z, their rows
/// starting at brick index `at(z, y)`; `xs` the x regions touched), the rows with mass: bit
/// `8z + y` of entry `rx`. With `HITS` false the `a` cells are known to be zero and are not
/// read.
#[inline(always)]
fn rows_with_mass<const M: usize, const E: usize, const HITS: bool>(
    cells_a: &[u32],
    cells_b: &[u32],
    xs: u64,
    y: (usize, usize, usize),
    z: (usize, usize, usize),
    at: impl Fn(usize, usize) -> usize,
) -> [u64; S + 2] {
    const R: usize = S + 2;
    let b = B as usize;
    let mut rows = [0u64; R];
    // Every row lies before the last one's end: checked once here, which spares the
    // rows most of their own bounds checks.
    let end = at(z.2 - 1, y.2 - 1) + E;
    let (ca, cb) = (&cells_a[..end], &cells_b[..end]);
    let margins = 1 | 1 << (R - 1);
    let any = |cells: &[u32]| u64::from(cells.iter().fold(0, |acc, &v| acc | v) != 0);
    for zi in 0..z.2 {
        for yi in 0..y.2 {
            let i = at(zi, yi);
            let bit = zi * 8 + yi;
            if xs & margins == 0 {
                let rb: &[u32; SB] = cb[i + M..i + M + SB].try_into().expect("S·B cells");
                let or: [u32; SB] = if HITS {
                    let ra: &[u32; SB] = ca[i + M..i + M + SB].try_into().expect("S·B cells");
                    std::array::from_fn(|k| ra[k] | rb[k])
                } else {
                    *rb
                };
                for (r, cells) in rows[1..=S].iter_mut().zip(or.chunks_exact(b)) {
                    *r |= any(cells) << bit;
                }
            } else {
                let rb: &[u32; E] = cb[i..i + E].try_into().expect("E cells");
                let or: [u32; E] = if HITS {
                    let ra: &[u32; E] = ca[i..i + E].try_into().expect("E cells");
                    std::array::from_fn(|k| ra[k] | rb[k])
                } else {
                    *rb
                };
                rows[0] |= any(&or[..M]) << bit;
                for (r, cells) in rows[1..=S].iter_mut().zip(or[M..M + SB].chunks_exact(b)) {
                    *r |= any(cells) << bit;
                }
                rows[R - 1] |= any(&or[M + SB..]) << bit;
            }
        }
    }
    rows
}

/// Folds the brick rows in `rows` (bit 8z + y of the region's rows `y`, `z`, which start at
/// brick index `at(z, y)`) — `N` cells each from brick cell `x.0`, to cell `x.1` of the
/// target's rows — into block `key` of `target`, zeroing them. The block is taken only if
/// some row has mass.
#[inline(always)]
fn fold_rows<const N: usize>(
    a: &mut [u32],
    b: &mut [u32],
    mut rows: u64,
    x: (usize, usize),
    (y, z, at): ((usize, usize, usize), (usize, usize, usize), impl Fn(usize, usize) -> usize),
    (key, hits): ([i32; 3], bool),
    target: &mut impl FoldTarget,
) {
    if rows == 0 {
        return;
    }
    let mut dst = target.block(key, hits);
    while rows != 0 {
        let r = rows.trailing_zeros() as usize;
        rows &= rows - 1;
        let (zi, yi) = (r >> 3, r & 7);
        let i = at(zi, yi) + x.0;
        let rb: &mut [u32; N] = (&mut b[i..i + N]).try_into().expect("N cells");
        let row = (z.1 + zi) * B as usize + y.1 + yi;
        if hits {
            let ra: &mut [u32; N] = (&mut a[i..i + N]).try_into().expect("N cells");
            dst.add_row(row, x.1, ra, rb);
        } else {
            dst.add_free_row(row, x.1, rb);
        }
    }
}

/// The delta blocks around one bucket's block, found through the neighbour cache.
struct Targets<'a> {
    block: [i32; 3],
    m: i32,
    side: usize,
    scatter: &'a mut Scatter,
}

impl Targets<'_> {
    /// The 8 cells of the block row holding the cells at block offset `(ox, oy, oz)` (from the
    /// bucket's block) and local (y, z) `(y7, z7)`: `A` for hits, `B` for frees.
    #[inline(always)]
    fn row(&mut self, o: [i32; 3], y7: i32, z7: i32, hit: bool) -> &mut [i64] {
        let side = self.side as i32;
        let ni = (((o[2] + self.m) * side + (o[1] + self.m)) * side + (o[0] + self.m)) as usize;
        let mut idx = self.scatter.neighbours[ni];
        if idx == NO_SLOT {
            let key = [0, 1, 2].map(|i| self.block[i] + o[i]);
            idx = self.scatter.delta.block_index(key, &mut self.scatter.spare);
            self.scatter.neighbours[ni] = idx;
        }
        let blk = &mut self.scatter.delta.blocks[idx as usize].1;
        let base = CellKey::new(0, y7, z7).index_in_block();
        self.scatter.delta.rows[idx as usize][usize::from(!hit)] |= 1 << (base / B as usize);
        let cells = if hit { &mut blk.a } else { &mut blk.b };
        &mut cells[base..base + B as usize]
    }
}

/// Adds one point's kernel mass to the delta blocks around its bucket.
#[inline(always)]
fn scatter_point(
    t: &mut Targets<'_>,
    p: [f64; 3],
    hit: bool,
    r: i32,
    geo: &PairGeometry,
    table: &KernelTable,
) {
    // Constant stencil sizes let the compiler unroll the short loops.
    match r {
        1 => scatter_point_n::<3>(t, p, hit, 3, geo, table),
        2 => scatter_point_n::<5>(t, p, hit, 5, geo, table),
        3 => scatter_point_n::<7>(t, p, hit, 7, geo, table),
        _ => scatter_point_n::<MAX_STENCIL>(t, p, hit, (2 * r + 1) as usize, geo, table),
    }
}

/// The stencil of edge `n ≤ N`: rows (fixed y, z offsets) outside the ball are skipped; inside
/// a row only the run of x offsets inside the ball is evaluated. Squared axis distances grow
/// away from offset 0, so that run is contiguous and found by counting, without branches.
#[inline(always)]
fn scatter_point_n<const N: usize>(
    t: &mut Targets<'_>,
    p: [f64; 3],
    hit: bool,
    n: usize,
    geo: &PairGeometry,
    table: &KernelTable,
) {
    let (c, f) = split_point(p);
    let r = (n / 2) as i32;
    // Cell coordinates relative to the bucket block's first cell, at offset −R.
    let local = [0, 1, 2].map(|i| c[i] - t.block[i] * B - r);
    // Squared axis distances for offsets o = i − R, exactly as `pair_coord` computes them.
    let axis = |a: usize| -> [f64; N] {
        std::array::from_fn(|i| {
            let d = f64::from(i as i32 - r) - f[a];
            d * d
        })
    };
    let (dx, dy, dz) = (axis(0), axis(1), axis(2));
    let ell2 = geo.ell_cells * geo.ell_cells * (1.0 + 1e-12);
    let half = n / 2;
    for iz in 0..n {
        let z = local[2] + iz as i32;
        for iy in 0..n {
            let row_d2 = dz[iz] + dy[iy];
            let rem = ell2 - row_d2;
            if rem <= 0.0 {
                continue;
            }
            // Offsets left of centre outside the ball form a prefix, right of it a suffix.
            let x0: usize = (0..half).map(|i| usize::from(dx[i] >= rem)).sum();
            let x1 = n - 1 - (half + 1..n).map(|i| usize::from(dx[i] >= rem)).sum::<usize>();
            let y = local[1] + iy as i32;
            let mut ix = x0;
            while ix <= x1 {
                // The part of the run inside one block.
                let x = local[0] + ix as i32;
                let end = x1.min(ix + (B - 1 - (x & (B - 1))) as usize);
                let o = [x >> BLOCK_SHIFT, y >> BLOCK_SHIFT, z >> BLOCK_SHIFT];
                let row = t.row(o, y & (B - 1), z & (B - 1), hit);
                for k in ix..=end {
                    let cell = (local[0] + k as i32) & (B - 1);
                    row[cell as usize] +=
                        table.quantized_coord(KernelTable::coordinate(row_d2 + dx[k], geo.scale));
                }
                ix = end + 1;
            }
        }
    }
}

/// Largest stencil edge, 2R + 1 for R = ⌊MAX_ELL_IN_CELLS + ½⌋.
const MAX_STENCIL: usize = 2 * (crate::core::params::MAX_ELL_IN_CELLS as usize) + 3;

/// Block-key bounds of the points' own cells (the floor of the least and greatest coordinates:
/// floor is monotone, so one floor per axis, not one per point).
fn block_bounds(pts: &[CellPoint]) -> ([i32; 3], [i32; 3]) {
    // Two points a step, each into its own bounds (merged at the end): a running min / max is
    // a chain through every point, and one chain per axis left the loop waiting on it
    // (`tile_len` was ~4% of sample-scan ingest).
    let mut lo = [[f64::INFINITY; 3]; 2];
    let mut hi = [[f64::NEG_INFINITY; 3]; 2];
    let pairs = pts.chunks_exact(2);
    let last = pairs.remainder();
    for pair in pairs.chain(std::iter::once(last)) {
        for (k, (p, _)) in pair.iter().enumerate() {
            // Plain comparisons, not `f64::min` (whose NaN rules cost instructions; the
            // points are finite).
            for i in 0..3 {
                lo[k][i] = if p[i] < lo[k][i] { p[i] } else { lo[k][i] };
                hi[k][i] = if p[i] > hi[k][i] { p[i] } else { hi[k][i] };
            }
        }
    }
    let block = |v: f64| super::cell_points::floor_i32(v) >> BLOCK_SHIFT;
    let lo: [f64; 3] = std::array::from_fn(|i| if lo[1][i] < lo[0][i] { lo[1][i] } else { lo[0][i] });
    let hi: [f64; 3] = std::array::from_fn(|i| if hi[1][i] > hi[0][i] { hi[1][i] } else { hi[0][i] });
    (lo.map(block), hi.map(block))
}

/// The slots of a grid of `dims` (x fastest) in Morton order: the cube of side 2^k that holds
/// the grid, visited octant by octant (x, then y, then z), slots outside the grid skipped.
///
/// The window path visits its buckets in this order. A map block takes the rows of up to
/// eight buckets' bricks (its own and, through their margins, those of its neighbours below on
/// each axis); in slot order a neighbour along z comes a whole x–y layer of buckets later, when
/// the block's 8 KiB have left the caches. In Morton order most neighbours come a few buckets
/// apart. The general path (`stencils`) keeps slot order.
fn morton_order(dims: [i64; 3], out: &mut Vec<u32>) {
    fn visit(dims: [i64; 3], at: [i64; 3], side: i64, out: &mut Vec<u32>) {
        if (0..3).any(|i| at[i] >= dims[i]) {
            return;
        }
        if side == 1 {
            out.push((at[0] + dims[0] * (at[1] + dims[1] * at[2])) as u32);
            return;
        }
        let h = side / 2;
        for o in 0..8 {
            visit(dims, [at[0] + (o & 1) * h, at[1] + (o >> 1 & 1) * h, at[2] + (o >> 2) * h], h, out);
        }
    }
    out.clear();
    let side = dims.iter().copied().max().unwrap_or(1).max(1) as u64;
    visit(dims, [0; 3], side.next_power_of_two() as i64, out);
}

/// Length of the next tile (as many points as keep both slot grids within `MAX_SLOTS`) and
/// its block bounds.
fn tile_len<P: ScanPoint>(pts: &[P], r: i32) -> (usize, ([i32; 3], [i32; 3])) {
    let m = i64::from((r + B - 1) / B);
    let slots = |(lo, hi): ([i32; 3], [i32; 3])| {
        (0..3).map(|i| i64::from(hi[i]) - i64::from(lo[i]) + 1 + 2 * m).product::<i64>()
    };
    let mut n = pts.len();
    let mut bounds = P::block_bounds(pts);
    while n > 1 && slots(bounds) > MAX_SLOTS {
        n = n.div_ceil(2);
        bounds = P::block_bounds(&pts[..n]);
    }
    (n, bounds)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every slot once, for cubes, flat and elongated grids and a single slot; and neighbours
    /// close: in a 16³ grid, each slot's neighbour along z comes within 8·8·8 slots of it in
    /// the order where slot order puts it 256 apart for every slot.
    #[test]
    fn morton_order_visits_every_slot_once() {
        let mut order = Vec::new();
        for dims in [[1, 1, 1], [16, 16, 16], [38, 38, 10], [5, 1, 300], [1, 7, 2], [64, 3, 3]] {
            morton_order(dims, &mut order);
            let mut seen = order.clone();
            seen.sort_unstable();
            let n = (dims[0] * dims[1] * dims[2]) as u32;
            assert_eq!(seen, (0..n).collect::<Vec<_>>(), "dims {dims:?}");
        }
        morton_order([16, 16, 16], &mut order);
        let mut place = vec![0usize; order.len()];
        for (i, &s) in order.iter().enumerate() {
            place[s as usize] = i;
        }
        let near = (0..16 * 16 * 15).filter(|&s| place[s].abs_diff(place[s + 256]) < 512).count();
        assert!(near >= 16 * 16 * 15 * 7 / 8, "{near} of the z neighbours within 512 slots");
    }

    /// The bucket sort is the stable counting sort, with an even and an odd number of points
    /// (the two halves it sorts side by side then differ in length).
    #[test]
    fn bucket_sort_is_stable() {
        for n in [0usize, 1, 2, 7, 1000, 1001] {
            // Cells spread over a 5 × 3 × 2 grid of buckets of 4 cells, in a scrambled order,
            // each point told apart by its sub-cell offset along x (no two alike below 1920).
            let pts: Vec<SubPoint> = (0..n)
                .map(|i| {
                    let mut c = [(i * 7) % 20, (i * 13) % 12, (i * 5) % 8].map(|v| (v as i32) << SUB_FRAC);
                    c[0] |= (i % (1 << SUB_FRAC)) as i32;
                    (c, i % 3 == 0)
                })
                .collect();
            let mut scatter = Scatter::default();
            scatter.bucket(&pts, [0, 0, 0], [4, 2, 1], 2);
            let slot = |p: &SubPoint| scatter.grid.index(p.cell().map(|v| v >> 2));
            let mut want = pts.clone();
            want.sort_by_key(slot);
            assert_eq!(scatter.subs_sorted, want, "{n} points");
            for s in 0..scatter.grid.slots.len() {
                let (a, b) = (scatter.starts[s] as usize, scatter.starts[s + 1] as usize);
                assert!(want[a..b].iter().all(|p| slot(p) == s), "bucket {s} of {n} points");
            }
        }
    }
}
