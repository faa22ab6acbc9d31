//! Explicit AVX2 for the one loop the compiler cannot vectorise: a W = 4 window's 64 kernel
//! lookups (the table reads are gathers). This is the crate's only `unsafe`: the function needs
//! AVX2, which [`window_values_w4`] checks at run time (once, cached by std), and every gather
//! index is clamped to the table before it is read.
//!
//! The lanes do exactly the scalar path's operations — IEEE f64 add, multiply and min, the
//! `1.5·2^52` rounding, i32 interpolation — so both paths give the same bits (tested below and by
//! the brute-force property tests, which run whichever path the machine picks).
#![allow(unsafe_code)]

use super::kernel::{COORD_CUTOFF, COORD_SHIFT, KernelTable, ROUND_MAGIC, TABLE_INTERVALS};

/// The 64 pair values of a W = 4 window (z-major, then y, then x) into `out`, using AVX2 when the
/// CPU has it; returns false (and leaves `out` alone) when it does not.
#[inline]
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

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;
    use std::arch::x86_64::*;

    /// # Safety
    /// The CPU must support AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn window_values_w4(
        axis: &[[f64; 4]; 3],
        scale: f64,
        table: &KernelTable,
        out: &mut [i32; 64],
    ) {
        let (values, slopes) = table.lanes();
        // SAFETY (loads/stores below): `axis[0]` holds 4 f64; `out` holds 64 i32 and row pair
        // `k < 8` writes lanes 8k..8k+8.
        let dx = unsafe { _mm256_loadu_pd(axis[0].as_ptr()) };
        let scale = _mm256_set1_pd(scale);
        let cutoff = _mm256_set1_pd(f64::from(COORD_CUTOFF));
        let magic = _mm256_set1_pd(ROUND_MAGIC);
        // Low 32 bits of each 64-bit lane, gathered into the low 128 bits.
        let low_halves = _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6);
        let frac_mask = _mm256_set1_epi32((1 << COORD_SHIFT) - 1);
        let half = _mm256_set1_epi32(1 << (COORD_SHIFT - 1));
        let coords = |z: usize, y: usize| -> __m128i {
            let row = _mm256_set1_pd(axis[2][z] + axis[1][y]);
            let v = _mm256_min_pd(_mm256_mul_pd(_mm256_add_pd(row, dx), scale), cutoff);
            let bits = _mm256_castpd_si256(_mm256_add_pd(v, magic));
            _mm256_castsi256_si128(_mm256_permutevar8x32_epi32(bits, low_halves))
        };
        for k in 0..8 {
            let (z, y) = (k / 2, (k % 2) * 2);
            let xq = _mm256_set_m128i(coords(z, y + 1), coords(z, y));
            let j = _mm256_srli_epi32::<COORD_SHIFT_I32>(xq);
            let frac = _mm256_and_si256(xq, frac_mask);
            // SAFETY: xq ≤ COORD_CUTOFF, so every index j ≤ TABLE_INTERVALS < table length.
            debug_assert!(values.len() == TABLE_INTERVALS + 1 && slopes.len() == TABLE_INTERVALS + 1);
            let (v, s) = unsafe {
                (
                    _mm256_i32gather_epi32::<4>(values.as_ptr(), j),
                    _mm256_i32gather_epi32::<4>(slopes.as_ptr(), j),
                )
            };
            let interp =
                _mm256_srai_epi32::<COORD_SHIFT_I32>(_mm256_add_epi32(_mm256_mullo_epi32(s, frac), half));
            let lanes = _mm256_add_epi32(v, interp);
            unsafe { _mm256_storeu_si256(out.as_mut_ptr().add(8 * k).cast(), lanes) };
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
        }
    }
}
