//! A cache prefetch hint, the model's one `unsafe`: batched lookups (the block table, point
//! queries, the voxel table) issue it for a whole round first, so their misses overlap.
//!
//! Depends on nothing.
#![allow(unsafe_code)]

/// Asks the CPU to start loading the cache line holding `*p` (a hint: no fault, no effect on
/// any value). Lookups that will miss issue this for a whole batch first, so the misses overlap.
#[inline(always)]
pub fn prefetch<T>(p: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE is part of x86-64; a prefetch of any address is architecturally a no-op.
    unsafe {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        _mm_prefetch::<_MM_HINT_T0>((p as *const T).cast::<i8>());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}
