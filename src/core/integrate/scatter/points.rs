//! What the evidence path needs of a training point ([`ScanPoint`]), for the two point
//! types it takes: [`CellPoint`]s anywhere and the compact [`SubPoint`]s at sub-cell centres.

use super::Scatter;
use crate::core::integrate::cell_points::{CellPoint, PairGeometry, SUB_FRAC, SubPoint};
use crate::core::integrate::kernel::KernelTable;
use crate::core::integrate::window::{Brick, SnappedWindows};
use crate::core::key::BLOCK_SHIFT;

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
        self.0.map(crate::core::integrate::floor::floor_i32)
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
        crate::core::integrate::cell_points::sub_point_cell_units(self.0)
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
    let block = |v: f64| crate::core::integrate::floor::floor_i32(v) >> BLOCK_SHIFT;
    let lo: [f64; 3] = std::array::from_fn(|i| if lo[1][i] < lo[0][i] { lo[1][i] } else { lo[0][i] });
    let hi: [f64; 3] = std::array::from_fn(|i| if hi[1][i] > hi[0][i] { hi[1][i] } else { hi[0][i] });
    (lo.map(block), hi.map(block))
}
