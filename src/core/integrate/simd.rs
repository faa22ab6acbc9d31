//! Explicit AVX2 for the one loop the compiler cannot vectorise: a W = 4 window's 64 kernel
//! lookups (the table reads are indexed loads), added straight into the brick's rows. Most of
//! the crate's `unsafe` is here (the other uses: the zeroed allocation of blocks in
//! [`crate::core::block`], the prefetch hint of [`crate::core::prefetch`], the lifetime of
//! [`super::workers`]'s jobs, and the allocator thresholds the command line sets): the
//! functions need AVX2, which they check at run time (once, cached by std), every table index
//! is clamped to the table before it is read, and the brick rows are bounds-checked once per
//! window before they are written.
//!
//! The lanes do exactly the scalar path's operations — IEEE f64 add, multiply and min, the
//! `1.5·2^52` rounding, i32 interpolation — so both paths give the same bits (tested below and by
//! the brute-force property tests, which run whichever path the machine picks).
#![allow(unsafe_code)]

use super::kernel::{COORD_CUTOFF, COORD_SHIFT, KernelTable, ROUND_MAGIC, TABLE_INTERVALS};

/// The 64 pair values of a W = 4 window (z-major, then y, then x) into `out`, using AVX2 when the
/// CPU has it; returns false (and leaves `out` alone) when it does not. Tests compare these lanes
/// with the portable path; ingest uses [`add_window_w4`].
#[cfg(test)]
pub fn window_values_w4(axis: &[[f64; 4]; 3], scale: f64, table: &KernelTable, out: &mut [i32; 64]) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is present (checked just above).
            unsafe { x86::window_values_w4(axis, scale, table, out) };
            return true;
        }
    }
    let _ = (axis, scale, table, out);
    false
}

/// Adds a W = 4 window's pair values to the 16 rows of 4 cells at `cells[at + (z·e + y)·e ..]`
/// (a brick of edge `e`), using AVX2 when the CPU has it; returns false (and changes nothing)
/// when it does not.
#[inline]
pub fn add_window_w4(
    axis: &[[f64; 4]; 3],
    scale: f64,
    table: &KernelTable,
    cells: &mut [u32],
    at: usize,
    e: usize,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        // The last row's end; every other row ends before it.
        let end = at + (3 * e + 3) * e + 4;
        assert!(end <= cells.len() && e >= 4, "window outside the brick");
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: AVX2 is present; every row lies in `cells` (asserted just above).
            unsafe { x86::add_window_w4(axis, scale, table, cells, at, e) };
            return true;
        }
    }
    let _ = (axis, scale, table, cells, at, e);
    false
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;
    use std::arch::x86_64::*;

    /// The lanes of row pair `k < 8` of a W = 4 window: rows (z, y) and (z, y + 1) for
    /// z = k / 2, y = 2·(k % 2), four x lanes each.
    #[derive(Clone, Copy)]
    struct Window<'a> {
        axis: &'a [[f64; 4]; 3],
        dx: __m256d,
        scale: __m256d,
        values: &'a [i32; TABLE_INTERVALS + 2],
    }

    impl<'a> Window<'a> {
        #[target_feature(enable = "avx2")]
        fn new(axis: &'a [[f64; 4]; 3], scale: f64, table: &'a KernelTable) -> Self {
            let values = table.values();
            // SAFETY: `axis[0]` holds 4 f64.
            let dx = unsafe { _mm256_loadu_pd(axis[0].as_ptr()) };
            Self { axis, dx, scale: _mm256_set1_pd(scale), values }
        }

        /// The clamped table coordinates of row (z, y), in the low 128 bits.
        #[target_feature(enable = "avx2")]
        fn coords(&self, z: usize, y: usize) -> __m128i {
            let row = _mm256_set1_pd(self.axis[2][z] + self.axis[1][y]);
            let v = _mm256_min_pd(
                _mm256_mul_pd(_mm256_add_pd(row, self.dx), self.scale),
                _mm256_set1_pd(f64::from(COORD_CUTOFF)),
            );
            let bits = _mm256_castpd_si256(_mm256_add_pd(v, _mm256_set1_pd(ROUND_MAGIC)));
            // Low 32 bits of each 64-bit lane, gathered into the low 128 bits.
            let low_halves = _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6);
            _mm256_castsi256_si128(_mm256_permutevar8x32_epi32(bits, low_halves))
        }

        /// Table entries `j` and `j + 1` of 4 lanes as 4 × (value, next) 64-bit pairs: one
        /// 8-byte load per lane, not two 4-byte ones for value and slope. Four scalar loads
        /// and inserts, not `vpgatherdq`: the gather stalled the whole window (the instruction
        /// after it waited), and the loads made evidence ~10% faster.
        #[target_feature(enable = "avx2")]
        fn pairs(&self, j: __m128i) -> __m256i {
            // SAFETY: every j ≤ TABLE_INTERVALS (clamped coordinates), so the 8 bytes at j —
            // entries j and j + 1 — lie in `values` (TABLE_INTERVALS + 2 entries).
            unsafe {
                let base = self.values.as_ptr();
                let at = |k: i32| base.add(k as u32 as usize).cast::<i64>().read_unaligned();
                _mm256_set_epi64x(
                    at(_mm_extract_epi32::<3>(j)),
                    at(_mm_extract_epi32::<2>(j)),
                    at(_mm_extract_epi32::<1>(j)),
                    at(_mm_extract_epi32::<0>(j)),
                )
            }
        }

        #[target_feature(enable = "avx2")]
        fn row_pair(&self, k: usize) -> __m256i {
            let (z, y) = (k / 2, (k % 2) * 2);
            let (q0, q1) = (self.coords(z, y), self.coords(z, y + 1));
            let xq = _mm256_set_m128i(q1, q0);
            let frac = _mm256_and_si256(xq, _mm256_set1_epi32((1 << COORD_SHIFT) - 1));
            let (p0, p1) = (
                self.pairs(_mm_srli_epi32::<COORD_SHIFT_I32>(q0)),
                self.pairs(_mm_srli_epi32::<COORD_SHIFT_I32>(q1)),
            );
            // Each pair's value to the low 128 bits, its successor to the high 128 bits.
            let split = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
            let (p0, p1) = (_mm256_permutevar8x32_epi32(p0, split), _mm256_permutevar8x32_epi32(p1, split));
            let v = _mm256_permute2x128_si256::<0x20>(p0, p1);
            let next = _mm256_permute2x128_si256::<0x31>(p0, p1);
            // values[j + 1] − values[j] is slopes[j] (asserted when the table is built).
            let s = _mm256_sub_epi32(next, v);
            let half = _mm256_set1_epi32(1 << (COORD_SHIFT - 1));
            let interp =
                _mm256_srai_epi32::<COORD_SHIFT_I32>(_mm256_add_epi32(_mm256_mullo_epi32(s, frac), half));
            _mm256_add_epi32(v, interp)
        }
    }

    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(test)]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn window_values_w4(
        axis: &[[f64; 4]; 3],
        scale: f64,
        table: &KernelTable,
        out: &mut [i32; 64],
    ) {
        let w = Window::new(axis, scale, table);
        for k in 0..8 {
            // SAFETY: `out` holds 64 i32 and row pair `k < 8` writes lanes 8k..8k+8.
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().add(8 * k).cast(), w.row_pair(k)) };
        }
    }

    /// # Safety
    /// The CPU must support AVX2, and `cells` must hold the row ending at
    /// `at + (3e + 3)e + 4` (the window's last).
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn add_window_w4(
        axis: &[[f64; 4]; 3],
        scale: f64,
        table: &KernelTable,
        cells: &mut [u32],
        at: usize,
        e: usize,
    ) {
        let w = Window::new(axis, scale, table);
        let base = cells.as_mut_ptr();
        for k in 0..8 {
            let (z, y) = (k / 2, (k % 2) * 2);
            let lanes = w.row_pair(k);
            // SAFETY: rows (z, y) and (z, y + 1) start at most at the last row's start and
            // hold 4 cells each, inside `cells` by the caller's contract.
            unsafe {
                let r0 = base.add(at + (z * e + y) * e).cast::<__m128i>();
                let r1 = base.add(at + (z * e + y + 1) * e).cast::<__m128i>();
                let lo = _mm_add_epi32(_mm_loadu_si128(r0), _mm256_castsi256_si128(lanes));
                let hi = _mm_add_epi32(_mm_loadu_si128(r1), _mm256_extracti128_si256::<1>(lanes));
                _mm_storeu_si128(r0, lo);
                _mm_storeu_si128(r1, hi);
            }
        }
    }

    const COORD_SHIFT_I32: i32 = COORD_SHIFT as i32;
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Whatever path this machine takes, it gives the portable path's bits (windows of points at
    /// random offsets, including the cut-off and offsets on cell edges).
    #[test]
    fn simd_lanes_equal_the_portable_lanes() {
        let table = KernelTable::new();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let scale = (TABLE_INTERVALS as f64) * f64::from(1u32 << COORD_SHIFT) / 4.0;
        for i in 0..20_000 {
            let f: [f64; 3] = std::array::from_fn(|_| match i % 4 {
                0 => -0.5,
                1 => 0.0,
                _ => rng.random_range(-0.5..0.5),
            });
            let axis: [[f64; 4]; 3] = std::array::from_fn(|a| {
                let start = if f[a] < 0.0 { -2.0 } else { -1.0 };
                std::array::from_fn(|k| {
                    let d = start + k as f64 - f[a];
                    d * d
                })
            });
            let mut fast = [0i32; 64];
            let mut slow = [0i32; 64];
            window_values_w4(&axis, scale, &table, &mut fast);
            super::super::window::window_values_portable::<4, 64>(&axis, scale, &table, &mut slow);
            if std::arch::is_x86_feature_detected!("avx2") {
                assert_eq!(fast, slow, "f = {f:?}");
            }
            // Added into a brick of edge 6 at a random corner, on top of what is there.
            let (e, at) = (6, rng.random_range(0..2) * 37 + 1);
            let mut brick: Vec<u32> = (0..6 * 6 * 6).map(|_| rng.random_range(0..1000)).collect();
            let before = brick.clone();
            if add_window_w4(&axis, scale, &table, &mut brick, at, e) {
                for (i, v) in slow.iter().enumerate() {
                    let (z, y, x) = (i / 16, i / 4 % 4, i % 4);
                    let c = at + (z * e + y) * e + x;
                    assert_eq!(brick[c], before[c] + *v as u32, "f = {f:?}, lane {i}");
                    brick[c] = before[c];
                }
                assert_eq!(brick, before, "only the window's cells change");
            }
        }
    }
}
