//! How the process's allocator keeps freed memory (glibc only).
//!
//! glibc returns the free top of a heap to the kernel once it exceeds the trim threshold
//! (128 KiB until the first large free). The worker threads of an ingest keep their blocks in
//! their own heap (a thread's arena) and hand them to the map when they finish; a map that is
//! dropped frees them, the arena trims, and the next batch's blocks fault every page in again.
//! `bgkmap bench ingest --threads 2` took 116k page faults and 0.2 s of kernel time for 100
//! passes over the sample scans (13.6k with one thread), and a pass 4.0–4.8 ms instead of
//! 3.6–3.7 ms: the kernel's page-fault path, not the map, was what two cores shared.
//!
//! The thresholds set here are where glibc's own dynamic thresholds end up in a long-running
//! process once it has freed a large chunk (mmap threshold at its 32 MiB ceiling, trim threshold
//! twice that): set from the start, so a short batch does not pay for the warm-up. A heap keeps
//! at most 64 MiB free at its top. A `GLIBC_TUNABLES` that sets either threshold wins.

/// Sets the allocator's thresholds (see the module docs); a no-op off glibc.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let tuned = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
        if tuned.contains("trim_threshold") || tuned.contains("mmap_threshold") {
            return;
        }
        const MMAP_THRESHOLD: libc::c_int = 32 << 20;
        set(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
        set(libc::M_TRIM_THRESHOLD, 2 * MMAP_THRESHOLD);
    }
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)]
fn set(param: libc::c_int, value: libc::c_int) {
    // SAFETY: `mallopt` takes two integers and changes only the allocator's thresholds, which
    // glibc reads under the arena locks; it returns 0 for a parameter it rejects, which only
    // leaves glibc's default in place.
    let _ = unsafe { libc::mallopt(param, value) };
}
