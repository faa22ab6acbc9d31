//! The sparse kernel of Eq. 10 and its deterministic fixed-point form.
//!
//! `k(d) = σ0·[(2 + cos 2πu)/3·(1 − u) + sin(2πu)/(2π)]` for `u = d/l < 1`, else 0.
//! σ0 factors out of every sum, so evidence is accumulated for the unit kernel (σ0 = 1) and
//! scaled when a cell is read.
//!
//! Evidence must be bit-identical on every machine and in every order, so each pair's
//! contribution is an integer `q = round(k̃ · 2^F)` ([`FIXED_SHIFT`]) computed by
//! [`KernelTable::quantized`]: a table of the unit kernel over `t = u²` (built with the pure-Rust
//! `libm`, not the platform's `sin`/`cos`), linearly interpolated in plain IEEE f64 arithmetic.
//! Indexing by `u²` means no square root per pair. Interpolation error is below 4e-7 (largest near
//! `u = 0.01`), far below the 1e-6 of the reference table.

/// Fractional bits of the fixed-point evidence sums (algorithm.md §7).
pub const FIXED_SHIFT: u32 = 24;
/// `2^FIXED_SHIFT` as f64: one unit of kernel mass.
pub const FIXED_ONE: f64 = (1u64 << FIXED_SHIFT) as f64;

const TABLE_INTERVALS: usize = 4096;

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

/// The unit kernel as a function of `t = (d/l)²`, tabulated for the fixed-point evidence path.
#[derive(Debug, Clone)]
pub struct KernelTable {
    /// `k̃(√(j/N))·2^F` for j = 0..=N; the last entry is 0 (the cut-off).
    values: Vec<f64>,
}

impl Default for KernelTable {
    fn default() -> Self {
        Self::new()
    }
}

impl KernelTable {
    pub fn new() -> Self {
        let n = TABLE_INTERVALS;
        let values = (0..=n)
            .map(|j| if j == n { 0.0 } else { unit_kernel_of_u(libm::sqrt(j as f64 / n as f64)) * FIXED_ONE })
            .collect();
        Self { values }
    }

    /// Fixed-point unit-kernel mass for a pair with `t = (d/l)² `; 0 when `t ≥ 1`.
    /// This is *the* definition of a pair's evidence: the fast path and every reference
    /// implementation call it.
    #[inline(always)]
    pub fn quantized(&self, t: f64) -> i64 {
        if !(t < 1.0) {
            return 0;
        }
        let x = t * TABLE_INTERVALS as f64;
        let j = x as usize; // t ≥ 0 by construction (a sum of squares)
        let frac = x - j as f64;
        let lo = self.values[j];
        let hi = self.values[j + 1];
        (lo + (hi - lo) * frac + 0.5) as i64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// algorithm.md §3 reference values.
    #[test]
    fn kernel_matches_reference_table() {
        let head = [(0.0, 1.0), (0.05, 0.659155), (0.10, 0.166667), (0.15, 0.007512), (0.20, 0.0), (0.25, 0.0), (0.30, 0.0)];
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
}
