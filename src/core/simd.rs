//! Explicit AVX2 for the one loop the compiler cannot vectorise: a W = 4 window's 64 kernel
//! lookups (the table reads are gathers), added straight into the brick's rows. This is the
//! crate's only `unsafe`: the functions need AVX2, which they check at run time (once, cached by
//! std), every gather index is clamped to the table before it is read, and the brick rows are
//! bounds-checked once per window before they are written.
//!
//! The lanes do exactly the scalar path's operations — IEEE f64 add, multiply and min, the
//! `1.5·2^52` rounding, i32 interpolation — so both paths give the same bits (tested below and by
//! the brute-force property tests, which run whichever path the machine picks).
#![allow(unsafe_code)]

use super::evidence::PairGeometry;
use super::kernel::{COORD_CUTOFF, COORD_SHIFT, KernelTable, ROUND_MAGIC, TABLE_INTERVALS};
use super::scatter::CellPoint;
use super::window::Brick;

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
    cells: &mut [i32],
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

/// Adds the W = 4 windows of `pts` (all in the block starting at cell `block_origin`, at most
/// [`Brick::room`] of them) to `brick` with AVX-512 when the CPU has it: each row pair's 8 lanes
/// read their table entry and its successor with one 64-bit gather (8 gathers per point instead
/// of AVX2's 16), and everything stays in registers from the point to the brick rows. Returns
/// false (and changes nothing) without AVX-512.
#[inline]
pub fn add_points_w4(
    brick: &mut Brick,
    pts: &[CellPoint],
    block_origin: [i32; 3],
    geo: &PairGeometry,
    table: &KernelTable,
) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        if avx512_enabled() {
            assert!(brick.edge() >= 4, "a W = 4 window needs a brick of edge 4 or more");
            // SAFETY: AVX-512F is present; every window is bounds-checked before it is written.
            unsafe { x86_512::add_points_w4(brick, pts, block_origin, geo, table) };
            return true;
        }
    }
    let _ = (brick, pts, block_origin, geo, table);
    false
}

/// AVX-512F present and not switched off by `BGKMAP_NO_AVX512` (set it to compare the paths).
#[cfg(target_arch = "x86_64")]
fn avx512_enabled() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| {
        std::arch::is_x86_feature_detected!("avx512f") && std::env::var_os("BGKMAP_NO_AVX512").is_none()
    })
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
        slopes: &'a [i32; TABLE_INTERVALS + 1],
    }

    impl<'a> Window<'a> {
        #[target_feature(enable = "avx2")]
        fn new(axis: &'a [[f64; 4]; 3], scale: f64, table: &'a KernelTable) -> Self {
            let (values, slopes) = table.lanes();
            // SAFETY: `axis[0]` holds 4 f64.
            let dx = unsafe { _mm256_loadu_pd(axis[0].as_ptr()) };
            Self { axis, dx, scale: _mm256_set1_pd(scale), values, slopes }
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

        #[target_feature(enable = "avx2")]
        fn row_pair(&self, k: usize) -> __m256i {
            let (z, y) = (k / 2, (k % 2) * 2);
            let xq = _mm256_set_m128i(self.coords(z, y + 1), self.coords(z, y));
            let j = _mm256_srli_epi32::<COORD_SHIFT_I32>(xq);
            let frac = _mm256_and_si256(xq, _mm256_set1_epi32((1 << COORD_SHIFT) - 1));
            // SAFETY: xq ≤ COORD_CUTOFF, so every index j ≤ TABLE_INTERVALS < table length.
            let (v, s) = unsafe {
                (
                    _mm256_i32gather_epi32::<4>(self.values.as_ptr(), j),
                    _mm256_i32gather_epi32::<4>(self.slopes.as_ptr(), j),
                )
            };
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
        cells: &mut [i32],
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

#[cfg(target_arch = "x86_64")]
mod x86_512 {
    use super::*;
    use std::arch::x86_64::*;

    /// # Safety
    /// The CPU must support AVX-512F; `pts` must lie in the block at `block_origin` and number
    /// at most `brick.room()`.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn add_points_w4(
        brick: &mut Brick,
        pts: &[CellPoint],
        block_origin: [i32; 3],
        geo: &PairGeometry,
        table: &KernelTable,
    ) {
        let (values, _) = table.lanes();
        let e = brick.edge();
        let len = brick.a.len().min(brick.b.len());
        let k4 = _mm256_setr_pd(0.0, 1.0, 2.0, 3.0);
        let scale = _mm512_set1_pd(geo.scale);
        let cutoff = _mm512_set1_pd(f64::from(COORD_CUTOFF));
        let magic = _mm512_set1_pd(ROUND_MAGIC);
        let low32 = _mm512_set1_epi64(0xFFFF_FFFF);
        let frac_mask = _mm512_set1_epi64((1 << COORD_SHIFT) - 1);
        let half = _mm512_set1_epi64(1 << (COORD_SHIFT - 1));
        // Lane i of a row pair takes row sum y + i / 4 (of the 4 in a 256-bit half).
        let pair_rows = [0, 2].map(|y: i64| _mm512_setr_epi64(y, y, y, y, y + 1, y + 1, y + 1, y + 1));
        for &(p, hit) in pts {
            let pl = brick.place::<4>(p, block_origin, geo.ell_cells);
            // Squared axis distances `(start + k − f)²`, exactly as the portable path.
            let axis = |a: usize| {
                let first = _mm256_add_pd(_mm256_set1_pd(f64::from(pl.start[a])), k4);
                let d = _mm256_sub_pd(first, _mm256_set1_pd(pl.f[a]));
                _mm256_mul_pd(d, d)
            };
            let (dx, dy, dz) = (axis(0), axis(1), axis(2));
            let dx2 = _mm512_broadcast_f64x4(dx);
            let mut dzs = [0f64; 4];
            // SAFETY: `dzs` holds 4 f64.
            unsafe { _mm256_storeu_pd(dzs.as_mut_ptr(), dz) };
            assert!(pl.at + (3 * e + 3) * e + 4 <= len, "window outside the brick");
            let cells = if hit { brick.a.as_mut_ptr() } else { brick.b.as_mut_ptr() };
            for (z, &dzz) in dzs.iter().enumerate() {
                // Row sums dz + dy for y = 0..4, in the low 256 bits.
                let rows = _mm512_castpd256_pd512(_mm256_add_pd(_mm256_set1_pd(dzz), dy));
                for (h, idx) in pair_rows.iter().enumerate() {
                    let y = 2 * h;
                    let d2 = _mm512_add_pd(_mm512_permutexvar_pd(*idx, rows), dx2);
                    let v = _mm512_min_pd(_mm512_mul_pd(d2, scale), cutoff);
                    let xq = _mm512_and_si512(_mm512_castpd_si512(_mm512_add_pd(v, magic)), low32);
                    let j = _mm512_srli_epi64::<COORD_SHIFT>(xq);
                    let frac = _mm512_and_si512(xq, frac_mask);
                    // SAFETY: xq ≤ COORD_CUTOFF, so j ≤ N and the 8 bytes at j (entries j and
                    // j + 1) lie in `values` (N + 2 entries).
                    let pair = unsafe { _mm512_i64gather_epi64::<4>(j, values.as_ptr().cast()) };
                    let value = _mm512_srai_epi64::<32>(_mm512_slli_epi64::<32>(pair));
                    let slope = _mm512_sub_epi64(_mm512_srai_epi64::<32>(pair), value);
                    let product = _mm512_add_epi64(_mm512_mul_epi32(slope, frac), half);
                    let interp = _mm512_srai_epi64::<COORD_SHIFT>(product);
                    let lanes = _mm512_cvtepi64_epi32(_mm512_add_epi64(value, interp));
                    // SAFETY: rows (z, y) and (z, y + 1) start at most at the last row's start
                    // and hold 4 cells each, inside the brick (asserted above).
                    unsafe {
                        let r0 = cells.add(pl.at + (z * e + y) * e).cast::<__m128i>();
                        let r1 = cells.add(pl.at + (z * e + y + 1) * e).cast::<__m128i>();
                        let lo = _mm_add_epi32(_mm_loadu_si128(r0), _mm256_castsi256_si128(lanes));
                        let hi = _mm_add_epi32(_mm_loadu_si128(r1), _mm256_extracti128_si256::<1>(lanes));
                        _mm_storeu_si128(r0, lo);
                        _mm_storeu_si128(r1, hi);
                    }
                }
            }
            brick.note(hit, pl.regions);
        }
    }
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
            let mut brick: Vec<i32> = (0..6 * 6 * 6).map(|_| rng.random_range(0..1000)).collect();
            let before = brick.clone();
            if add_window_w4(&axis, scale, &table, &mut brick, at, e) {
                for (i, v) in slow.iter().enumerate() {
                    let (z, y, x) = (i / 16, i / 4 % 4, i % 4);
                    let c = at + (z * e + y) * e + x;
                    assert_eq!(brick[c], before[c] + v, "f = {f:?}, lane {i}");
                    brick[c] = before[c];
                }
                assert_eq!(brick, before, "only the window's cells change");
            }
        }
    }

    /// The AVX-512 bucket path leaves the brick exactly as adding the same points one by one
    /// through the AVX2 / portable window does: cells, touched regions and room.
    #[test]
    fn avx512_buckets_equal_point_by_point_windows() {
        use super::super::window::window_shape;
        let table = KernelTable::new();
        let geo = PairGeometry::new(0.1, 0.2);
        let (w, margin) = window_shape(geo.ell_cells).unwrap();
        assert_eq!(w, 4);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let (mut fast, mut slow) = (Brick::default(), Brick::default());
        for trial in 0..300 {
            let origin: [i32; 3] = std::array::from_fn(|_| rng.random_range(-50..50) * 8);
            let n = rng.random_range(1..=90);
            let pts: Vec<CellPoint> = (0..n)
                .map(|i| {
                    let p = std::array::from_fn(|a| {
                        let o = f64::from(origin[a]);
                        match (i + trial + a) % 5 {
                            // Cell edges and centres, and the block's own edges.
                            0 => o + f64::from(rng.random_range(0..8)),
                            1 => o + f64::from(rng.random_range(0..8)) + 0.5,
                            2 => o + 7.999_999_999,
                            _ => o + rng.random_range(0.0..8.0),
                        }
                    });
                    (p, rng.random_bool(0.5))
                })
                .collect();
            fast.reset(margin);
            slow.reset(margin);
            if !add_points_w4(&mut fast, &pts, origin, &geo, &table) {
                eprintln!("skipped: no AVX-512 on this machine");
                return;
            }
            for &(p, hit) in &pts {
                slow.add_point::<4, 64>(p, hit, origin, &geo, &table);
            }
            assert!(fast.a == slow.a && fast.b == slow.b, "trial {trial}: cells differ");
            assert_eq!((fast.touched, fast.room()), (slow.touched, slow.room()), "trial {trial}");
            // Bricks are reused zeroed: clear both for the next trial.
            for b in [&mut fast, &mut slow] {
                b.a.fill(0);
                b.b.fill(0);
            }
        }
    }
}
