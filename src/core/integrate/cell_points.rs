//! Training points in cell units and the one definition of a pair's distance.
//!
//! Every cell centre within `ell` of a training point receives that point's quantised unit
//! kernel mass ([`KernelTable::quantized`]): hits add to `A`, free samples to `B` (the exact
//! kernel sum of docs/algorithm.md §5). This module converts training points to cell units (at
//! sub-cell centres by default, [`SubPoint`]s), splits them into cell and offset, and computes
//! a pair's table coordinate ([`pair_coord`]) the same way for the fast paths and for
//! [`brute_force_cell`], the gather-side reference the tests compare against.

use super::floor::{floor_f64, floor_i32};
use super::kernel::{COORD_SHIFT, KernelTable, TABLE_INTERVALS};
use super::training::TrainingSet;
use crate::core::key::CellKey;
use crate::core::params::MapParams;

/// A labelled training point in cell units (true = hit).
pub type CellPoint = ([f64; 3], bool);

/// Training points converted to cell units (`x / res`), the coordinates every pair uses; with
/// `sub_cells = n > 0`, each moved to the centre of its sub-cell (`floor(x·n) + ½) / n` per axis,
/// so it stays in its cell, at most `1/(2n)` of a cell away. `n` is a power of two, so every
/// step is exact in f64.
#[inline]
pub fn to_cell_units(p_m: [f64; 3], geo: &PairGeometry) -> [f64; 3] {
    let cells = p_m.map(|v| v / geo.res_m);
    if geo.sub_cells == 0 {
        return cells;
    }
    let n = f64::from(geo.sub_cells);
    // `/ n` is `* (1/n)` exactly (n is a power of two), and a multiplication is cheaper.
    let inv_n = 1.0 / n;
    cells.map(|v| (floor_f64(v * n) + 0.5) * inv_n)
}

/// Fractional bits of a [`SubPoint`]'s coordinates: the centre of sub-cell `k` of `n` (a power
/// of two up to [`MAX_SUB_CELLS`](crate::core::params::MAX_SUB_CELLS)) is `(2k + 1) / 2n` of a cell,
/// a multiple of `2^-SUB_FRAC`.
pub const SUB_FRAC: u32 = crate::core::params::MAX_SUB_CELLS.trailing_zeros() + 1;

/// A labelled training point at a sub-cell centre (true = hit): its coordinates in cell units
/// as fixed point with [`SUB_FRAC`] fractional bits, exactly what [`to_cell_units`] gives for
/// `sub_cells > 0`, in 16 bytes where a `([f64; 3], bool)` takes 32. The evidence path's
/// passes over the points (bounds, bucketing, placing the windows) read and move half the
/// bytes and find cells and sub-cells with shifts.
pub type SubPoint = ([i32; 3], bool);

/// [`labelled_cell_points`] as [`SubPoint`]s (`geo.sub_cells > 0`), replacing `out`; false
/// (and `out` unusable) when some point lies 2^23 cells or more from the origin, beyond what
/// the fixed point holds.
pub fn labelled_sub_points(set: &TrainingSet, geo: &PairGeometry, out: &mut Vec<SubPoint>) -> bool {
    use super::kernel::ROUND_MAGIC;
    assert!(geo.sub_cells > 0, "sub-cell points need sub-cells");
    let shift = geo.sub_cells.trailing_zeros();
    let n = f64::from(geo.sub_cells);
    // Sub-cell k's centre is k·step + half in units of 2^-SUB_FRAC cells: an integer, exact in
    // a double, whose low 32 bits after adding 1.5·2^52 are its two's complement (no
    // saturating conversion, with its tests for NaN and overflow). Below `limit` sub-cells
    // every coordinate stays under 2^30 (and its cell under 2^23); the farthest is tested
    // once at the end (one pass over the points: a dense scan's do not fit the caches), and a
    // point beyond it leaves `out` unusable.
    let limit = (1u64 << (30 - SUB_FRAC + shift)) as f64;
    let (step, half) = ((1u32 << (SUB_FRAC - shift)) as f64, (1u32 << (SUB_FRAC - shift - 1)) as f64);
    let res = geo.res_m;
    // The farthest coordinate so far, per lane of a chunk (reduced at the end): every axis has
    // the same limit.
    let mut far = [0.0f64; 3 * SUB_CHUNK];
    let mut q = [0i32; 3 * SUB_CHUNK];
    out.clear();
    out.reserve(set.len());
    for (points, hit) in [(&set.hits, true), (&set.frees, false)] {
        // Chunks of points as flat runs of coordinates, so the divisions go four to an
        // instruction (a dense scan converts ~360k points, and scalar divisions were what the
        // loop waited on).
        for chunk in points.chunks(SUB_CHUNK) {
            let flat = chunk.as_flattened();
            for ((q, f), &v) in q.iter_mut().zip(&mut far).zip(flat) {
                // As `to_cell_units`: cells, then times n, then the floor.
                let k = v / res * n;
                // A plain comparison, not `f64::max` (whose NaN rules cost instructions).
                *f = if k.abs() > *f { k.abs() } else { *f };
                *q = (floor_f64(k) * step + half + ROUND_MAGIC).to_bits() as u32 as i32;
            }
            out.extend(q[..flat.len()].chunks_exact(3).map(|c| ([c[0], c[1], c[2]], hit)));
        }
    }
    far.iter().all(|&f| f + 1.0 < limit)
}

/// Points [`labelled_sub_points`] converts at a time.
const SUB_CHUNK: usize = 64;

/// A [`SubPoint`]'s coordinates in cell units (exact).
#[inline(always)]
pub fn sub_point_cell_units(q: [i32; 3]) -> [f64; 3] {
    q.map(|v| f64::from(v) / f64::from(1u32 << SUB_FRAC))
}

/// A training set as labelled points in cell units (hits first, `true`), replacing `out`.
pub fn labelled_cell_points(set: &TrainingSet, geo: &PairGeometry, out: &mut Vec<([f64; 3], bool)>) {
    out.clear();
    out.extend(set.hits.iter().map(|&p| (to_cell_units(p, geo), true)));
    out.extend(set.frees.iter().map(|&p| (to_cell_units(p, geo), false)));
}

/// A training point (cell units) split into its cell and its offset from that cell's centre:
/// `p = cell + ½ + offset`, offset in [−½, ½).
#[inline(always)]
pub fn split_point(p_cells: [f64; 3]) -> ([i32; 3], [f64; 3]) {
    let c = p_cells.map(floor_i32);
    (c, [0, 1, 2].map(|i| (p_cells[i] - f64::from(c[i])) - 0.5))
}

/// The kernel-table coordinate of a training point (cell units) and a cell: the one definition
/// of a pair's distance, shared by the fast path and the reference. Per axis the distance is
/// `(k − c) − offset` with `(c, offset)` from [`split_point`]; squares are summed z, y, then x,
/// and the sum goes through [`KernelTable::coordinate`].
#[inline(always)]
pub fn pair_coord(p_cells: [f64; 3], cell: CellKey, scale: f64) -> i64 {
    let (c, f) = split_point(p_cells);
    let d2 = |k: i32, i: usize| {
        let d = (i64::from(k) - i64::from(c[i])) as f64 - f[i];
        d * d
    };
    KernelTable::coordinate((d2(cell.z, 2) + d2(cell.y, 1)) + d2(cell.x, 0), scale)
}

/// Geometry shared by the scatter and the reference: resolution and kernel length in cells.
#[derive(Debug, Clone, Copy)]
pub struct PairGeometry {
    pub res_m: f64,
    pub ell_cells: f64,
    /// `N·2^COORD_SHIFT / ell_cells²`: turns a squared distance (cells²) into a fixed-point
    /// kernel-table coordinate.
    pub scale: f64,
    /// Training points sit at sub-cell centres, `sub_cells` per cell edge (0: where they are);
    /// see [`to_cell_units`].
    pub sub_cells: u32,
}

impl PairGeometry {
    pub fn new(res_m: f64, ell_m: f64, sub_cells: u32) -> Self {
        assert!(
            sub_cells == 0 || sub_cells.is_power_of_two(),
            "sub_cells {sub_cells} is not 0 or a power of two"
        );
        let ell_cells = ell_m / res_m;
        Self {
            res_m,
            ell_cells,
            scale: TABLE_INTERVALS as f64 * f64::from(1u32 << COORD_SHIFT) / (ell_cells * ell_cells),
            sub_cells,
        }
    }

    /// The geometry of a map's parameters.
    pub fn of(params: &MapParams) -> Self {
        Self::new(params.resolution_m, params.ell_m, params.sub_cells)
    }

    /// Stencil radius: cells within `ell` of a point differ from its cell by at most this.
    pub fn radius_cells(&self) -> i32 {
        floor_i32(self.ell_cells + 0.5)
    }
}

/// Reference: the evidence of one cell by summing over *all* training points (gather, O(N)).
pub fn brute_force_cell(
    set: &TrainingSet,
    cell: CellKey,
    geo: &PairGeometry,
    table: &KernelTable,
) -> (i64, i64) {
    let sum = |pts: &[[f64; 3]]| -> i64 {
        pts.iter().map(|&p| table.quantized_coord(pair_coord(to_cell_units(p, geo), cell, geo.scale))).sum()
    };
    (sum(&set.hits), sum(&set.frees))
}
