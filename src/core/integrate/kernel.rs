//! The sparse kernel of Eq. 10 and its deterministic fixed-point form.
//!
//! `k(d) = σ0·[(2 + cos 2πu)/3·(1 − u) + sin(2πu)/(2π)]` for `u = d/l < 1`, else 0.
//! σ0 factors out of every sum, so evidence is accumulated for the unit kernel (σ0 = 1) and
//! scaled when a cell is read.
//!
//! Evidence must be bit-identical on every machine and in every order, so each pair's
//! contribution is an integer `q = round(k̃ · 2^F)`
//! ([`FIXED_SHIFT`](crate::core::posterior::FIXED_SHIFT)) computed by [`KernelTable::quantized`]:
//! a table of the unit kernel over `t = u²` (built with the pure-Rust `libm`, not the
//! platform's `sin`/`cos`), linearly interpolated in plain IEEE f64 arithmetic.
//! Indexing by `u²` means no square root per pair. Interpolation error is below 4e-7 (largest near
//! `u = 0.01`), far below the 1e-6 of the reference table.

use crate::core::posterior::FIXED_ONE;

/// The unit sparse kernel (σ0 = 1) at distance `d_m` for kernel length `ell_m`, in f64 with an
/// explicit cut-off (la3dm clamps an f32 evaluation instead).
pub fn unit_kernel(d_m: f64, ell_m: f64) -> f64 {
    let u = d_m / ell_m;
    if !(u < 1.0) || u < 0.0 {
        return 0.0;
    }
    unit_kernel_of_u(u)
}

/// The sparse kernel with amplitude `sf2` (σ0).
pub fn sparse_kernel(d_m: f64, ell_m: f64, sf2: f64) -> f64 {
    sf2 * unit_kernel(d_m, ell_m)
}

fn unit_kernel_of_u(u: f64) -> f64 {
    let two_pi = 2.0 * std::f64::consts::PI;
    (2.0 + libm::cos(two_pi * u)) / 3.0 * (1.0 - u) + libm::sin(two_pi * u) / two_pi
}

/// Intervals of the kernel table over `t ∈ [0, 1)`.
pub const TABLE_INTERVALS: usize = 4096;
/// Fractional bits of a table coordinate: a pair's `x = N·(d/l)²` is rounded once to a
/// fixed-point integer with this many fractional bits; everything after is integer arithmetic.
pub const COORD_SHIFT: u32 = 16;
/// `1.5·2^52`: adding it rounds an f64 of magnitude < 2^51 to an integer (ties to even) in the
/// low mantissa bits — a branch-free, platform-independent rounding.
pub(crate) const ROUND_MAGIC: f64 = 6_755_399_441_055_744.0;

/// Rounds `v` (|v| < 2^51) to the nearest integer, ties to even.
#[inline(always)]
pub fn round_to_i64(v: f64) -> i64 {
    (v + ROUND_MAGIC).to_bits() as i64 - ROUND_MAGIC.to_bits() as i64
}

/// The unit kernel as a function of `x = N·(d/l)²`, tabulated for the fixed-point evidence path.
#[derive(Debug, Clone)]
pub struct KernelTable {
    /// `[k̃(√(j/N))·2^F rounded, slope to the next entry]` for j = 0..N, as i32 (32 KiB, so it
    /// stays in L1); entries from N on are zero (the cut-off), so clamping to N gives 0 for every
    /// pair at or beyond `l`.
    entries: Box<[[i32; 2]; TABLE_INTERVALS + 2]>,
    /// The same table split into values and slopes, for lane-wise (SIMD) evaluation. `values`
    /// has one more zero at `N + 1`, so entry `j ≤ N` and its successor read as one 8-byte pair
    /// whose difference is `slopes[j]`.
    values: Box<[i32; TABLE_INTERVALS + 2]>,
    slopes: Box<[i32; TABLE_INTERVALS + 1]>,
}

/// Table coordinates are clamped here: `N·2^COORD_SHIFT`, the cut-off (`u = 1`), where the
/// kernel is 0. Fits an i32 (2^28).
pub const COORD_CUTOFF: i32 = (TABLE_INTERVALS as i32) << COORD_SHIFT;

impl Default for KernelTable {
    fn default() -> Self {
        Self::new()
    }
}

impl KernelTable {
    pub fn new() -> Self {
        let n = TABLE_INTERVALS;
        let value = |j: usize| {
            if j < n {
                round_to_i64(unit_kernel_of_u(libm::sqrt(j as f64 / n as f64)) * FIXED_ONE) as i32
            } else {
                0
            }
        };
        let mut entries = Box::new([[0i32; 2]; TABLE_INTERVALS + 2]);
        for (j, e) in entries.iter_mut().enumerate().take(n) {
            *e = [value(j), value(j + 1) - value(j)];
        }
        let values: Box<[i32; TABLE_INTERVALS + 2]> = Box::new(std::array::from_fn(|j| entries[j][0]));
        let slopes: Box<[i32; TABLE_INTERVALS + 1]> = Box::new(std::array::from_fn(|j| entries[j][1]));
        // The lane-wise path interpolates in i32: slope·frac + ½ must not overflow.
        assert!(slopes.iter().all(|s| s.unsigned_abs() < 1 << (31 - COORD_SHIFT)), "kernel slope too steep");
        assert!(
            (0..=TABLE_INTERVALS).all(|j| values[j + 1] - values[j] == slopes[j]),
            "slopes are differences"
        );
        Self { entries, values, slopes }
    }

    /// [`Self::quantized_coord`] for a coordinate `x·2^COORD_SHIFT` already clamped to
    /// `0..=COORD_CUTOFF`, in i32 lane arithmetic (same result: the slope bound asserted in
    /// [`Self::new`] keeps the product in range). Written so that a loop over lanes vectorises.
    #[inline(always)]
    pub fn quantized_lane(&self, xq: i32) -> i32 {
        let j = (xq >> COORD_SHIFT) as usize;
        let frac = xq & ((1 << COORD_SHIFT) - 1);
        let j = j.min(TABLE_INTERVALS);
        self.values[j] + ((self.slopes[j] * frac + (1 << (COORD_SHIFT - 1))) >> COORD_SHIFT)
    }

    /// The table's values for lane-wise reads (index `N` is the cut-off, 0, and one more zero
    /// follows at `N + 1`): `values[j + 1] − values[j]` is the slope of interval `j ≤ N`.
    pub fn values(&self) -> &[i32; TABLE_INTERVALS + 2] {
        &self.values
    }

    /// The clamped lane coordinate of a squared distance `d2_cells` (≥ 0): `round(d2·scale)`
    /// capped at [`COORD_CUTOFF`]. Clamping before rounding equals clamping after (rounding is
    /// monotone and the cap is an integer), and the rounded integer is read from the low 32
    /// mantissa bits of `v + 1.5·2^52`.
    #[inline(always)]
    pub fn lane_coordinate(d2_cells: f64, scale: f64) -> i32 {
        let v = (d2_cells * scale).min(f64::from(COORD_CUTOFF));
        (v + ROUND_MAGIC).to_bits() as u32 as i32
    }

    /// The fixed-point table coordinate of a pair: `round(x·2^COORD_SHIFT)` for
    /// `x = N·(d/l)²`, computed as `round(d2 · scale)` with `scale = N·2^COORD_SHIFT / l²`.
    #[inline(always)]
    pub fn coordinate(d2_cells: f64, scale: f64) -> i64 {
        round_to_i64(d2_cells * scale)
    }

    /// Fixed-point unit-kernel mass for a pair at table coordinate `xq` (see
    /// [`Self::coordinate`]); 0 at or beyond the cut-off. This is *the* definition of a pair's
    /// evidence: the fast path and every reference implementation call it.
    #[inline(always)]
    pub fn quantized_coord(&self, xq: i64) -> i64 {
        let xq = xq.min((TABLE_INTERVALS as i64) << COORD_SHIFT);
        let j = (xq >> COORD_SHIFT) as usize;
        let frac = xq & ((1 << COORD_SHIFT) - 1);
        let [v, slope] = self.entries[j.min(TABLE_INTERVALS)];
        i64::from(v) + ((i64::from(slope) * frac + (1 << (COORD_SHIFT - 1))) >> COORD_SHIFT)
    }

    /// Mass for `t = (d/l)²` (tests and reference use).
    pub fn quantized(&self, t: f64) -> i64 {
        self.quantized_coord(Self::coordinate(t, (TABLE_INTERVALS as f64) * f64::from(1u32 << COORD_SHIFT)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::posterior::FIXED_SHIFT;

    /// docs/algorithm.md §3 reference values.
    #[test]
    fn kernel_matches_reference_table() {
        let head = [
            (0.0, 1.0),
            (0.05, 0.659155),
            (0.10, 0.166667),
            (0.15, 0.007512),
            (0.20, 0.0),
            (0.25, 0.0),
            (0.30, 0.0),
        ];
        for (d, k) in head {
            assert!((sparse_kernel(d, 0.2, 1.0) - k).abs() < 1e-6, "d={d}: {}", sparse_kernel(d, 0.2, 1.0));
        }
        let paper = [
            (0.0, 10.0),
            (0.05, 8.322767),
            (0.10, 4.711656),
            (0.15, 1.666667),
            (0.20, 0.288345),
            (0.25, 0.010566),
            (0.30, 0.0),
            (0.35, 0.0),
        ];
        for (d, k) in paper {
            assert!((sparse_kernel(d, 0.3, 10.0) - k).abs() < 1e-6, "d={d}: {}", sparse_kernel(d, 0.3, 10.0));
        }
    }

    #[test]
    fn kernel_is_monotone_with_smooth_cutoff() {
        let mut prev = f64::INFINITY;
        for i in 0..=1000 {
            let k = unit_kernel(i as f64 * 0.2 / 1000.0, 0.2);
            assert!(k <= prev && k >= 0.0);
            prev = k;
        }
        assert_eq!(unit_kernel(0.2, 0.2), 0.0);
        assert_eq!(unit_kernel(f64::NAN, 0.2), 0.0);
    }

    #[test]
    fn table_is_within_4e7_of_the_exact_kernel() {
        let table = KernelTable::new();
        for i in 0..20_000 {
            let u = i as f64 / 20_000.0;
            let q = table.quantized(u * u) as f64 / FIXED_ONE;
            assert!((q - unit_kernel(u, 1.0)).abs() < 4e-7, "u={u}");
        }
        assert_eq!(table.quantized(1.0), 0);
        assert_eq!(table.quantized(0.0), 1 << FIXED_SHIFT);
    }

    /// The i32 lane path is the same function as the i64 definition, at every table entry's
    /// edges and at random points of every interval, and beyond the cut-off.
    #[test]
    fn lane_path_equals_the_definition() {
        use rand::{Rng, SeedableRng};
        let table = KernelTable::new();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let n = TABLE_INTERVALS as i64;
        for j in 0..=n {
            let base = j << COORD_SHIFT;
            let mut fracs =
                vec![0, 1, (1 << (COORD_SHIFT - 1)) - 1, 1 << (COORD_SHIFT - 1), (1 << COORD_SHIFT) - 1];
            fracs.extend((0..16).map(|_| rng.random_range(0..1i64 << COORD_SHIFT)));
            for f in fracs {
                let xq = (base + f).min(i64::from(COORD_CUTOFF));
                assert_eq!(i64::from(table.quantized_lane(xq as i32)), table.quantized_coord(xq), "xq={xq}");
            }
        }
        let scale = 4096.0 * 65536.0 / 4.0;
        for _ in 0..100_000 {
            let d2: f64 = rng.random_range(0.0..9.0);
            let lane = KernelTable::lane_coordinate(d2, scale);
            let full = KernelTable::coordinate(d2, scale);
            assert_eq!(table.quantized_lane(lane), table.quantized_coord(full) as i32, "d2={d2}");
            assert_eq!(i64::from(lane), full.min(i64::from(COORD_CUTOFF)));
        }
    }
}
