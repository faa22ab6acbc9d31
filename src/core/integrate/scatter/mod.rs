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

use super::cell_points::{CellPoint, PairGeometry, SubPoint};
use super::delta::{DeltaBlock, RowMask, ScanDelta};
use super::kernel::KernelTable;
use super::sink::BlockSink;
use super::window::{Brick, S, SB, SnappedWindows, window_shape};
use crate::core::block::TakenBlock;
use crate::core::key::{BLOCK_EDGE, BLOCK_SHIFT, BlockKey};

/// Above this many block slots the scan is split into tiles of points.
const MAX_SLOTS: i64 = 1 << 22;
const NO_SLOT: u32 = u32::MAX;
const B: i32 = BLOCK_EDGE;

mod fold;
mod points;
mod stencil;

use fold::{DeltaTarget, FoldTarget, SinkTarget, fold_brick};
pub use points::ScanPoint;
use stencil::{Targets, scatter_point};

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
mod tests;
