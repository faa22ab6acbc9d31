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
//!
//! Transparent huge pages: a map is hundreds of megabytes of 4–8 KiB blocks, and with 4 KiB
//! pages nearly every random point query or fresh voxel-table probe also misses the TLB (a
//! page walk, nested under a VM). glibc hands its heaps to the kernel's huge pages when the
//! tunable `glibc.malloc.hugetlb=1` is set, and tunables are read only when a process starts,
//! so [`use_huge_pages`] starts the process again with it. Measured 2026-12-05 (2.3 GHz Xeon VM,
//! THP `madvise`, four alternated runs each): in-process point queries into a vector
//! 17.6–18.3 → 19.3–21.3 M/s, visited 19.3–20.0 → 20.7–22.7 M/s; dense 64-beam scans
//! 44.3–44.7 → 39.6–40.6 ms (a busy host); sample scans and rays unchanged. (On 2026-12-04 a
//! busier host showed no gain on points: 13.7–15.1 against 15.1–15.4 M/s.) Any
//! `glibc.malloc.hugetlb` in `GLIBC_TUNABLES` wins, `=0` included, which is how to turn it off.

/// The glibc tunable that puts malloc's heaps on transparent huge pages.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const HUGE_PAGES_TUNABLE: &str = "glibc.malloc.hugetlb";

/// Starts this process again (same arguments, same PID) with `glibc.malloc.hugetlb=1` added to
/// `GLIBC_TUNABLES`, unless the variable already names that tunable or the kernel's
/// transparent huge pages are off; returns (doing nothing) off glibc, in those cases, or when
/// the restart fails. Call first thing in `main`, before any thread starts.
pub fn use_huge_pages() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::os::unix::process::CommandExt;
        let tuned = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
        let Some(tunables) = tunables_with_huge_pages(&tuned) else {
            return;
        };
        if !huge_pages_available() {
            return;
        }
        let mut args = std::env::args_os();
        let (Some(arg0), Ok(exe)) = (args.next(), std::env::current_exe()) else {
            return;
        };
        // Returns only if the process could not be replaced; it then goes on as it is.
        let _ = std::process::Command::new(exe).arg0(arg0).args(args).env("GLIBC_TUNABLES", tunables).exec();
    }
}

/// `GLIBC_TUNABLES` (`tuned`) with huge pages asked for, or `None` when it names the tunable
/// already (whatever its value).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn tunables_with_huge_pages(tuned: &str) -> Option<String> {
    let names_it = tuned.split(':').any(|t| t.split('=').next() == Some(HUGE_PAGES_TUNABLE));
    let sep = if tuned.is_empty() { "" } else { ":" };
    (!names_it).then(|| format!("{tuned}{sep}{HUGE_PAGES_TUNABLE}=1"))
}

/// True when the kernel gives transparent huge pages to regions that ask (`always` or
/// `madvise`, not `never`).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn huge_pages_available() -> bool {
    std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled")
        .is_ok_and(|mode| mode.contains("[always]") || mode.contains("[madvise]"))
}

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

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::tunables_with_huge_pages;

    #[test]
    fn huge_pages_are_added_to_the_tunables_unless_named() {
        assert_eq!(tunables_with_huge_pages("").as_deref(), Some("glibc.malloc.hugetlb=1"));
        assert_eq!(
            tunables_with_huge_pages("glibc.malloc.arena_max=4").as_deref(),
            Some("glibc.malloc.arena_max=4:glibc.malloc.hugetlb=1")
        );
        for named in ["glibc.malloc.hugetlb=0", "glibc.malloc.arena_max=4:glibc.malloc.hugetlb=2"] {
            assert_eq!(tunables_with_huge_pages(named), None, "{named}");
        }
        // A tunable whose name only starts the same is another one.
        assert!(tunables_with_huge_pages("glibc.malloc.hugetlbx=1").is_some());
    }
}
