//! The lane-wise evidence path: fixed W³ windows per point, accumulated in a per-bucket brick.
//!
//! A training point at `p = c + ½ + f` (cell `c`, offset `f ∈ [−½, ½)` per axis, cell units)
//! reaches only cells whose axis offset `o` from `c` satisfies `|o − f| < L` (`L` = ell in
//! cells). Per axis those are at most `W = ⌈2L⌉` consecutive offsets starting at
//! `⌊f − L⌋ + 1`. So every point evaluates the same W×W×W window — 64 pairs for la3dm's
//! defaults (L = 2) — with no branches: pairs outside the ball land on the table's cut-off and
//! add exactly 0. The loop over a window's lanes vectorises (coordinates in f64, the table
//! interpolation in i32 lanes, see [`KernelTable::quantized_lane`]).
//!
//! Points arrive bucketed by the block of their cell (see [`super::scatter`]). A bucket's
//! windows all fall inside a brick of `(B + 2M)³` cells — its block plus a margin of `M`
//! cells — so a window is `W²` contiguous rows of `W` cells in the brick, added without any
//! block lookup. When the bucket is done, the brick is folded into the (up to 27) delta blocks
//! it overlaps, only the regions some window touched, and zeroed on the way.
//!
//! The brick holds `i32` (half the memory traffic of the blocks' `i64`, and 8 lanes per AVX2
//! add): one pair adds at most `2^F` ([`FIXED_SHIFT`]), so up to [`BRICK_POINTS`] points fit
//! without overflow; a bucket with more is folded every [`BRICK_POINTS`] points.
//!
//! Bits equal the reference: every lane computes `(o − f)²` per axis and sums z, y, then x,
//! exactly as [`pair_coord`](super::evidence::pair_coord).

use super::evidence::{PairGeometry, floor_i32, split_point};
use super::kernel::{FIXED_SHIFT, KernelTable};
use super::key::BLOCK_EDGE;
use super::scatter::CellPoint;

const B: usize = BLOCK_EDGE as usize;

/// Points a brick takes between folds: each adds at most `2^F` to a cell, and
/// `BRICK_POINTS · 2^F ≤ i32::MAX`.
pub const BRICK_POINTS: u32 = (i32::MAX as u32) >> FIXED_SHIFT;

/// `SPREAD[axis][mask]`: the 27-bit region mask (bit `9z + 3y + x`) of every region whose
/// coordinate along `axis` is in the 3-bit `mask`.
const SPREAD: [[u32; 8]; 3] = {
    let mut t = [[0u32; 8]; 3];
    let mut axis = 0;
    while axis < 3 {
        let mut mask = 0;
        while mask < 8 {
            let mut bit = 0;
            while bit < 27 {
                let r = [bit % 3, bit / 3 % 3, bit / 9];
                if mask >> r[axis] & 1 != 0 {
                    t[axis][mask] |= 1 << bit;
                }
                bit += 1;
            }
            mask += 1;
        }
        axis += 1;
    }
    t
};

/// Window size `W` and brick margin `M` for a kernel length (cells), if the lane path has a
/// compiled width for it.
pub fn window_shape(ell_cells: f64) -> Option<(usize, usize)> {
    let w = (2.0 * ell_cells).ceil();
    if !(1.0..=6.0).contains(&w) {
        return None;
    }
    let w = w as i32;
    // Smallest start offset (f → −½) and largest end offset (f → ½).
    let left = -(floor_i32(-0.5 - ell_cells) + 1);
    let right = floor_i32(0.5 - ell_cells) + w;
    Some((w as usize, left.max(right).max(0) as usize))
}

/// Accumulates one bucket's windows (occupied mass `a`, free mass `b`) in a dense brick.
#[derive(Debug, Default)]
pub struct Brick {
    /// Brick edge `B + 2M` and margin `M`.
    edge: usize,
    margin: usize,
    pub a: Vec<i32>,
    pub b: Vec<i32>,
    /// Points added since the last fold (at most [`BRICK_POINTS`]).
    points: u32,
    /// Per label (0 = a, 1 = b): bit `9z + 3y + x` set when a window touched region (x, y, z),
    /// region 0 = low margin, 1 = the bucket's block, 2 = high margin.
    pub touched: [u32; 2],
}

impl Brick {
    pub fn reset(&mut self, margin: usize) {
        let edge = B + 2 * margin;
        if self.edge != edge {
            *self = Self { edge, margin, ..Self::default() };
            self.a = vec![0; edge * edge * edge];
            self.b = vec![0; edge * edge * edge];
        }
        self.touched = [0; 2];
        self.points = 0;
    }

    /// True when the brick must be folded before it takes another point.
    pub fn full(&self) -> bool {
        self.points >= BRICK_POINTS
    }

    /// Marks the brick folded (its cells are zero again).
    pub fn folded(&mut self) {
        self.touched = [0; 2];
        self.points = 0;
    }

    pub fn edge(&self) -> usize {
        self.edge
    }

    pub fn margin(&self) -> usize {
        self.margin
    }

    /// The region (0, 1, 2) of brick coordinate `i` along an axis.
    #[inline(always)]
    fn region(&self, i: usize) -> u32 {
        u32::from(i >= self.margin) + u32::from(i >= self.margin + B)
    }

    /// Points the brick takes before it must be folded.
    pub fn room(&self) -> usize {
        (BRICK_POINTS - self.points) as usize
    }

    /// Where the window of the point `p` (cell units) lies: its offset `f` from its cell's
    /// centre, the first window offset per axis, the brick index of the window's first cell
    /// and the regions it touches. `block_origin` is the first cell of the bucket's block (the
    /// point's cell must lie in that block).
    #[inline(always)]
    pub(crate) fn place<const W: usize>(
        &self,
        p: [f64; 3],
        block_origin: [i32; 3],
        ell_cells: f64,
    ) -> Placement {
        let (c, f) = split_point(p);
        let mut start = [0i32; 3];
        let mut base = [0usize; 3];
        let mut regions = [0u32; 3];
        for a in 0..3 {
            start[a] = floor_i32(f[a] - ell_cells) + 1;
            // In the brick: the cell sits at margin + its offset in the block.
            let b = (c[a] - block_origin[a] + start[a]) as isize + self.margin as isize;
            debug_assert!(b >= 0 && b as usize + W <= self.edge, "window outside the brick");
            base[a] = b as usize;
            // Regions first..=last along this axis, as a 3-bit mask.
            let (r0, r1) = (self.region(base[a]), self.region(base[a] + W - 1));
            regions[a] = (0b111 >> (2 - (r1 - r0))) << r0;
        }
        let e = self.edge;
        Placement {
            f,
            start,
            at: (base[2] * e + base[1]) * e + base[0],
            regions: SPREAD[0][regions[0] as usize]
                & SPREAD[1][regions[1] as usize]
                & SPREAD[2][regions[2] as usize],
        }
    }

    /// Records one added window of label `hit` that touched `regions`.
    #[inline(always)]
    pub(crate) fn note(&mut self, hit: bool, regions: u32) {
        debug_assert!(self.points < BRICK_POINTS, "brick not folded in time");
        self.points += 1;
        self.touched[usize::from(!hit)] |= regions;
    }

    /// Adds the windows of `pts` (at most [`Self::room`] of them), all in the block starting at
    /// cell `block_origin`.
    pub fn add_points<const W: usize, const W3: usize>(
        &mut self,
        pts: &[CellPoint],
        block_origin: [i32; 3],
        geo: &PairGeometry,
        table: &KernelTable,
    ) {
        assert!(pts.len() <= self.room(), "brick not folded in time");
        for &(p, hit) in pts {
            self.add_point::<W, W3>(p, hit, block_origin, geo, table);
        }
    }

    /// Adds one point's window. `p` is in cell units; `block_origin` is the first cell of the
    /// bucket's block (the point's cell must lie in that block).
    #[inline(always)]
    pub fn add_point<const W: usize, const W3: usize>(
        &mut self,
        p: [f64; 3],
        hit: bool,
        block_origin: [i32; 3],
        geo: &PairGeometry,
        table: &KernelTable,
    ) {
        let pl = self.place::<W>(p, block_origin, geo.ell_cells);
        let axis: [[f64; W]; 3] = std::array::from_fn(|a| {
            std::array::from_fn(|k| {
                let d = f64::from(pl.start[a] + k as i32) - pl.f[a];
                d * d
            })
        });
        let e = self.edge;
        let cells = if hit { &mut self.a } else { &mut self.b };
        add_window::<W, W3>(&axis, geo.scale, table, cells, pl.at, e);
        self.note(hit, pl.regions);
    }
}

/// Where one point's window lies in a brick (see [`Brick::place`]).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Placement {
    /// The point's offset from its cell's centre, per axis, in [−½, ½).
    pub f: [f64; 3],
    /// The window's first offset from the point's cell, per axis.
    pub start: [i32; 3],
    /// Brick index of the window's first cell.
    pub at: usize,
    /// Regions the window touches (bit `9z + 3y + x`).
    pub regions: u32,
}

/// Adds one window's W³ pair values to the brick `cells` (edge `e`), whose first cell is `at`.
#[inline(always)]
fn add_window<const W: usize, const W3: usize>(
    axis: &[[f64; W]; 3],
    scale: f64,
    table: &KernelTable,
    cells: &mut [i32],
    at: usize,
    e: usize,
) {
    if W == 4 {
        let axis4: [[f64; 4]; 3] = std::array::from_fn(|a| std::array::from_fn(|k| axis[a][k]));
        if super::simd::add_window_w4(&axis4, scale, table, cells, at, e) {
            return;
        }
    }
    let mut vals = [0i32; W3];
    window_values_portable::<W, W3>(axis, scale, table, &mut vals);
    for z in 0..W {
        for y in 0..W {
            let from = at + (z * e + y) * e;
            let row = &mut cells[from..from + W];
            let v = &vals[(z * W + y) * W..(z * W + y + 1) * W];
            for x in 0..W {
                row[x] += v[x];
            }
        }
    }
}

/// The W³ pair values of one window, z-major then y then x (the reference for the AVX2 path).
pub(crate) fn window_values_portable<const W: usize, const W3: usize>(
    axis: &[[f64; W]; 3],
    scale: f64,
    table: &KernelTable,
    out: &mut [i32; W3],
) {
    let mut d2 = [0f64; W3];
    for z in 0..W {
        for y in 0..W {
            let row = axis[2][z] + axis[1][y];
            for x in 0..W {
                d2[(z * W + y) * W + x] = row + axis[0][x];
            }
        }
    }
    for (o, &d) in out.iter_mut().zip(&d2) {
        *o = table.quantized_lane(KernelTable::lane_coordinate(d, scale));
    }
}
