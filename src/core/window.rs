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
//! Bits equal the reference: every lane computes `(o − f)²` per axis and sums z, y, then x,
//! exactly as [`pair_coord`](super::evidence::pair_coord).

use super::evidence::{PairGeometry, floor_i32, split_point};
use super::kernel::KernelTable;
use super::key::BLOCK_EDGE;

const B: usize = BLOCK_EDGE as usize;

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
    pub a: Vec<i64>,
    pub b: Vec<i64>,
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
        let (c, f) = split_point(p);
        let mut base = [0usize; 3];
        let mut axis = [[0f64; W]; 3];
        let mut regions = [0u32; 3];
        for a in 0..3 {
            let start = floor_i32(f[a] - geo.ell_cells) + 1;
            for (k, d2) in axis[a].iter_mut().enumerate() {
                let d = f64::from(start + k as i32) - f[a];
                *d2 = d * d;
            }
            // In the brick: the cell sits at margin + its offset in the block.
            let b = (c[a] - block_origin[a] + start) as isize + self.margin as isize;
            debug_assert!(b >= 0 && b as usize + W <= self.edge, "window outside the brick");
            base[a] = b as usize;
            // Regions first..=last along this axis, as a 3-bit mask.
            let (r0, r1) = (self.region(base[a]), self.region(base[a] + W - 1));
            regions[a] = (0b111 >> (2 - (r1 - r0))) << r0;
        }
        let vals = window_values::<W, W3>(&axis, geo.scale, table);
        let e = self.edge;
        let cells = if hit { &mut self.a } else { &mut self.b };
        for z in 0..W {
            for y in 0..W {
                let at = ((base[2] + z) * e + base[1] + y) * e + base[0];
                let row = &mut cells[at..at + W];
                let v = &vals[(z * W + y) * W..(z * W + y + 1) * W];
                for x in 0..W {
                    row[x] += i64::from(v[x]);
                }
            }
        }
        let mut mask = 0u32;
        for z in 0..3 {
            for y in 0..3 {
                if regions[2] >> z & regions[1] >> y & 1 != 0 {
                    mask |= regions[0] << (9 * z + 3 * y);
                }
            }
        }
        self.touched[usize::from(!hit)] |= mask;
    }
}

/// The W³ pair values of one window, z-major then y then x: the lane-wise loop.
#[inline(always)]
fn window_values<const W: usize, const W3: usize>(
    axis: &[[f64; W]; 3],
    scale: f64,
    table: &KernelTable,
) -> [i32; W3] {
    debug_assert_eq!(W3, W * W * W);
    let mut out = [0i32; W3];
    if W == 4
        && let Ok(out4) = <&mut [i32; 64]>::try_from(&mut out[..])
    {
        let axis4: [[f64; 4]; 3] = std::array::from_fn(|a| std::array::from_fn(|k| axis[a][k]));
        if super::simd::window_values_w4(&axis4, scale, table, out4) {
            return out;
        }
    }
    window_values_portable::<W, W3>(axis, scale, table, &mut out);
    out
}

/// [`window_values`] without the SIMD lookups (the reference for the AVX2 path).
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
