//! `floor` without a libm call or a saturating conversion, for the pipeline's hot loops (voxel
//! keys, sub-cell centres, cell keys). Exact within the documented ranges; imports nothing of
//! the pipeline but the rounding constant, so every step can use it without a loop.

use super::kernel::ROUND_MAGIC;

/// [`floor_i64`] as a double, `floor_i64(v) as f64` for the same values, without the
/// integer-to-float conversion (baseline x86-64 has none for packed i64), so a loop of it
/// vectorises: `(v + 1.5·2^52) − 1.5·2^52` is round(v), exactly, then one less where that
/// rounded up.
#[inline(always)]
pub(crate) fn floor_f64(v: f64) -> f64 {
    debug_assert!(v.abs() < (1u64 << 51) as f64, "floor of {v} out of range");
    let r = (v + ROUND_MAGIC) - ROUND_MAGIC;
    r - if r > v { 1.0 } else { 0.0 }
}

/// `floor` to i64 without a libm call (baseline x86-64 has no SSE4.1 `roundsd`) and without a
/// saturating conversion (`as` adds two compares and two selects for NaN and overflow): round to
/// the nearest integer by adding 1.5·2^52, as [`round_to_i64`](super::kernel::round_to_i64)
/// does, then step down where that rounded up. Exact for |v| < 2^51, which every caller's values
/// are (points inside the voxel key range; the callers range-test anything else first).
#[inline(always)]
pub(crate) fn floor_i64(v: f64) -> i64 {
    debug_assert!(v.abs() < (1u64 << 51) as f64, "floor of {v} out of range");
    // `t`'s low mantissa bits hold round(v), and `t − 1.5·2^52` is round(v) as a double, exactly
    // (no integer-to-float conversion): all of it vectorises, even on baseline x86-64.
    let t = v + ROUND_MAGIC;
    let r = t.to_bits() as i64 - ROUND_MAGIC.to_bits() as i64;
    r - i64::from(t - ROUND_MAGIC > v)
}

/// `floor` for values whose floor fits an i32 (|v| < 2^31: the key range), computed as the
/// crate's `floor_i64` computes it.
#[inline(always)]
pub fn floor_i32(v: f64) -> i32 {
    debug_assert!(v.abs() < (1u64 << 31) as f64, "floor of {v} out of range");
    floor_i64(v) as i32
}
