//! The stencil path for kernels longer than the window path takes: each point's ball of cells
//! added straight into the delta blocks around its bucket ([`Targets`]).

use super::{B, NO_SLOT, Scatter};
use crate::core::integrate::cell_points::{PairGeometry, split_point};
use crate::core::integrate::kernel::KernelTable;
use crate::core::key::{BLOCK_SHIFT, CellKey};

/// The delta blocks around one bucket's block, found through the neighbour cache.
pub(super) struct Targets<'a> {
    pub(super) block: [i32; 3],
    pub(super) m: i32,
    pub(super) side: usize,
    pub(super) scatter: &'a mut Scatter,
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
pub(super) fn scatter_point(
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
