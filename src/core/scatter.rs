//! The fast evidence path: training points → per-cell kernel sums, block by block.
//!
//! Points are bucketed by the block of their own cell (a counting sort over the scan's block
//! grid). Each bucket is scattered into a dense local *brick* — the block grown by the stencil
//! radius R on every side, `(B + 2R)³` cells, small enough to stay in L1 — with no hashing and
//! no block lookup per pair. Per point, squared axis distances are computed once per offset;
//! each (y, z) row inside the ball visits only the x offsets whose pair is inside the ball. The
//! brick is then added into the scan's delta blocks.
//!
//! Every pair's value comes from [`pair_coord`](super::evidence::pair_coord)'s arithmetic and
//! [`KernelTable::quantized_coord`], so the result equals the brute-force reference bit for bit.

use super::evidence::{BlockEvidence, PairGeometry, ScanDelta, split_point};
use super::kernel::KernelTable;
use super::key::{BLOCK_EDGE, BLOCK_SHIFT, BlockKey, CellKey};

/// Above this many block slots the scan is split into tiles of points.
const MAX_SLOTS: i64 = 1 << 22;
const NO_SLOT: u32 = u32::MAX;
const B: i32 = BLOCK_EDGE;

/// A labelled training point in cell units (true = hit).
pub type CellPoint = ([f64; 3], bool);

/// Scatters training points into a [`ScanDelta`]; keeps scratch space between scans.
#[derive(Debug, Default)]
pub struct Scatter {
    grid: SlotGrid,
    /// Per point: its bucket (block slot).
    bucket_of: Vec<u32>,
    /// Bucket start offsets into `order` (counting sort).
    starts: Vec<u32>,
    order: Vec<u32>,
    brick_a: Vec<i64>,
    brick_b: Vec<i64>,
    delta: SlotGrid,
    spare: Vec<Box<BlockEvidence>>,
    cells: Vec<CellPoint>,
}

/// A dense grid of block slots over a box of block keys.
#[derive(Debug, Default)]
struct SlotGrid {
    min: [i32; 3],
    dims: [i64; 3],
    slots: Vec<u32>,
    blocks: Vec<(BlockKey, Box<BlockEvidence>)>,
}

impl SlotGrid {
    fn reset(&mut self, lo: [i32; 3], hi: [i32; 3]) {
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

    /// The block at key `b`, allocated (zeroed) on first use.
    fn block_mut(&mut self, b: [i32; 3], spare: &mut Vec<Box<BlockEvidence>>) -> &mut BlockEvidence {
        let s = self.index(b);
        if self.slots[s] == NO_SLOT {
            self.slots[s] = self.blocks.len() as u32;
            let fresh = spare.pop().unwrap_or_else(BlockEvidence::zeroed);
            self.blocks.push((BlockKey::new(b[0], b[1], b[2]), fresh));
        }
        &mut self.blocks[self.slots[s] as usize].1
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
        let mut cells = std::mem::take(&mut self.cells);
        cells.clear();
        let to_cells = |p: &[f64; 3]| super::evidence::to_cell_units(*p, geo.res_m);
        cells.extend(set.hits.iter().map(|p| (to_cells(p), true)));
        cells.extend(set.frees.iter().map(|p| (to_cells(p), false)));
        let out = self.delta_of(&cells, geo, table);
        self.cells = cells;
        out
    }

    /// As [`Scatter::delta`] for points already in cell units.
    pub fn delta_of(&mut self, pts: &[CellPoint], geo: &PairGeometry, table: &KernelTable) -> ScanDelta {
        let r = geo.radius_cells();
        let mut parts = Vec::new();
        let mut rest = pts;
        while !rest.is_empty() {
            let n = tile_len(rest, r);
            let (tile, tail) = rest.split_at(n);
            parts.push(self.delta_of_tile(tile, geo, table, r));
            rest = tail;
        }
        if parts.len() == 1 { parts.pop().unwrap_or_default() } else { ScanDelta::sum(parts) }
    }

    /// Returns a delta's blocks for reuse by later scans.
    pub fn recycle(&mut self, delta: ScanDelta) {
        for (_, mut b) in delta.blocks {
            b.a.fill(0);
            b.b.fill(0);
            self.spare.push(b);
        }
    }

    fn delta_of_tile(
        &mut self,
        pts: &[CellPoint],
        geo: &PairGeometry,
        table: &KernelTable,
        r: i32,
    ) -> ScanDelta {
        let (lo, hi) = block_bounds(pts);
        self.bucket(pts, lo, hi);
        // Delta blocks reach R cells beyond the points' blocks: at most ⌈R/B⌉ blocks further.
        let m = (r + B - 1) / B;
        self.delta.reset(lo.map(|v| v - m), hi.map(|v| v + m));
        let w = (B + 2 * r) as usize;
        self.brick_a.resize(w * w * w, 0);
        self.brick_b.resize(w * w * w, 0);
        for s in 0..self.grid.slots.len() {
            let (start, end) = (self.starts[s] as usize, self.starts[s + 1] as usize);
            if start == end {
                continue;
            }
            let block = self.grid_block_of_slot(s);
            // Map cells the bucket's stencils reach: its points' cells ± R.
            let (mut lo, mut hi) = ([i32::MAX; 3], [i32::MIN; 3]);
            for k in start..end {
                let (p, hit) = pts[self.order[k] as usize];
                let (c, _) = split_point(p);
                for i in 0..3 {
                    lo[i] = lo[i].min(c[i] - r);
                    hi[i] = hi[i].max(c[i] + r);
                }
                let brick = if hit { &mut self.brick_a } else { &mut self.brick_b };
                scatter_point(brick, w, block, p, r, geo, table);
            }
            self.flush_brick(block, r, w, (lo, hi));
        }
        let mut blocks = std::mem::take(&mut self.delta.blocks);
        // A block reached only by pairs whose mass rounds to 0 holds nothing: drop it.
        blocks.retain(|(_, b)| !b.is_empty());
        blocks.sort_unstable_by_key(|(k, _)| *k);
        ScanDelta { blocks }
    }

    fn grid_block_of_slot(&self, s: usize) -> [i32; 3] {
        let d = self.grid.dims;
        let s = s as i64;
        let o = [s % d[0], (s / d[0]) % d[1], s / (d[0] * d[1])];
        [0, 1, 2].map(|i| (i64::from(self.grid.min[i]) + o[i]) as i32)
    }

    /// Counting sort of point indices by the block slot of their cell.
    fn bucket(&mut self, pts: &[CellPoint], lo: [i32; 3], hi: [i32; 3]) {
        self.grid.reset(lo, hi);
        let n_slots = self.grid.slots.len();
        self.starts.clear();
        self.starts.resize(n_slots + 1, 0);
        self.bucket_of.clear();
        for (p, _) in pts {
            let (c, _) = split_point(*p);
            let s = self.grid.index(c.map(|v| v >> BLOCK_SHIFT)) as u32;
            self.bucket_of.push(s);
            self.starts[s as usize + 1] += 1;
        }
        for s in 0..n_slots {
            self.starts[s + 1] += self.starts[s];
        }
        self.order.clear();
        self.order.resize(pts.len(), 0);
        let mut next: Vec<u32> = self.starts[..n_slots].to_vec();
        for (i, &s) in self.bucket_of.iter().enumerate() {
            self.order[next[s as usize] as usize] = i as u32;
            next[s as usize] += 1;
        }
    }

    /// Adds the touched region `(lo, hi)` (map cells) of the brick around `block` into the delta
    /// blocks, and zeroes that region.
    fn flush_brick(&mut self, block: [i32; 3], r: i32, w: usize, (lo, hi): ([i32; 3], [i32; 3])) {
        // Brick cell (i, j, k) is map cell block·B − R + (i, j, k).
        let origin = block.map(|b| b * B - r);
        let index = move |x: i32, y: i32, z: i32| {
            (((z - origin[2]) as usize * w) + (y - origin[1]) as usize) * w + (x - origin[0]) as usize
        };
        let n = (hi[0] - lo[0] + 1) as usize;
        for bz in (lo[2] >> BLOCK_SHIFT)..=(hi[2] >> BLOCK_SHIFT) {
            for by in (lo[1] >> BLOCK_SHIFT)..=(hi[1] >> BLOCK_SHIFT) {
                for bx in (lo[0] >> BLOCK_SHIFT)..=(hi[0] >> BLOCK_SHIFT) {
                    let b = [bx, by, bz];
                    let from = [0, 1, 2].map(|i| (b[i] * B).max(lo[i]));
                    let to = [0, 1, 2].map(|i| (b[i] * B + B - 1).min(hi[i]));
                    let m = (to[0] - from[0] + 1) as usize;
                    let dst = self.delta.block_mut(b, &mut self.spare);
                    for z in from[2]..=to[2] {
                        for y in from[1]..=to[1] {
                            let i0 = index(from[0], y, z);
                            let d0 = CellKey::new(from[0], y, z).index_in_block();
                            for (d, s) in dst.a[d0..d0 + m].iter_mut().zip(&self.brick_a[i0..i0 + m]) {
                                *d += s;
                            }
                            for (d, s) in dst.b[d0..d0 + m].iter_mut().zip(&self.brick_b[i0..i0 + m]) {
                                *d += s;
                            }
                        }
                    }
                }
            }
        }
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                let i0 = index(lo[0], y, z);
                self.brick_a[i0..i0 + n].fill(0);
                self.brick_b[i0..i0 + n].fill(0);
            }
        }
    }
}

/// Adds one point's kernel mass to the brick of `block` (edge `w`, radius `r`).
#[inline(always)]
fn scatter_point(
    brick: &mut [i64],
    w: usize,
    block: [i32; 3],
    p: [f64; 3],
    r: i32,
    geo: &PairGeometry,
    table: &KernelTable,
) {
    // Constant stencil sizes let the compiler unroll the short loops.
    match r {
        1 => scatter_point_n::<3>(brick, w, block, p, 3, geo, table),
        2 => scatter_point_n::<5>(brick, w, block, p, 5, geo, table),
        3 => scatter_point_n::<7>(brick, w, block, p, 7, geo, table),
        _ => scatter_point_n::<MAX_STENCIL>(brick, w, block, p, (2 * r + 1) as usize, geo, table),
    }
}

/// The stencil of edge `n ≤ N`: rows (fixed y, z offsets) outside the ball are skipped; inside
/// a row only the run of x offsets inside the ball is evaluated. Squared axis distances grow
/// away from offset 0, so that run is contiguous and found by counting, without branches.
#[inline(always)]
fn scatter_point_n<const N: usize>(
    brick: &mut [i64],
    w: usize,
    block: [i32; 3],
    p: [f64; 3],
    n: usize,
    geo: &PairGeometry,
    table: &KernelTable,
) {
    let (c, f) = split_point(p);
    let r = n / 2;
    // Brick index of the stencil's first cell (offset −R on each axis).
    let local = [0, 1, 2].map(|i| (c[i] - block[i] * B) as usize);
    let base = (local[2] * w + local[1]) * w + local[0];
    // Squared axis distances for offsets o = i − R, exactly as `pair_coord` computes them.
    let axis = |a: usize| -> [f64; N] {
        std::array::from_fn(|i| {
            let d = f64::from(i as i32 - r as i32) - f[a];
            d * d
        })
    };
    let (dx, dy, dz) = (axis(0), axis(1), axis(2));
    let ell2 = geo.ell_cells * geo.ell_cells * (1.0 + 1e-12);
    for iz in 0..n {
        for iy in 0..n {
            let row_d2 = dz[iz] + dy[iy];
            let rem = ell2 - row_d2;
            if rem <= 0.0 {
                continue;
            }
            // Offsets left of centre outside the ball form a prefix, right of it a suffix.
            let x0: usize = (0..r).map(|i| usize::from(dx[i] >= rem)).sum();
            let x1 = n - 1 - (r + 1..n).map(|i| usize::from(dx[i] >= rem)).sum::<usize>();
            let start = base + (iz * w + iy) * w;
            for ix in x0..=x1 {
                brick[start + ix] +=
                    table.quantized_coord(KernelTable::coordinate(row_d2 + dx[ix], geo.scale));
            }
        }
    }
}

/// Largest stencil edge, 2R + 1 for R = ⌊MAX_ELL_IN_CELLS + ½⌋.
const MAX_STENCIL: usize = 2 * (super::params::MAX_ELL_IN_CELLS as usize) + 3;

/// Block-key bounds of the points' own cells.
fn block_bounds(pts: &[CellPoint]) -> ([i32; 3], [i32; 3]) {
    let mut lo = [i32::MAX; 3];
    let mut hi = [i32::MIN; 3];
    for (p, _) in pts {
        let (c, _) = split_point(*p);
        for i in 0..3 {
            lo[i] = lo[i].min(c[i] >> BLOCK_SHIFT);
            hi[i] = hi[i].max(c[i] >> BLOCK_SHIFT);
        }
    }
    (lo, hi)
}

/// Length of the next tile: as many points as keep both slot grids within `MAX_SLOTS`.
fn tile_len(pts: &[CellPoint], r: i32) -> usize {
    let m = i64::from((r + B - 1) / B);
    let slots = |n: usize| {
        let (lo, hi) = block_bounds(&pts[..n]);
        (0..3).map(|i| i64::from(hi[i]) - i64::from(lo[i]) + 1 + 2 * m).product::<i64>()
    };
    let mut n = pts.len();
    while n > 1 && slots(n) > MAX_SLOTS {
        n = n.div_ceil(2);
    }
    n
}
