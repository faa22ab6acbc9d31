fn main() -> std::process::ExitCode {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if !cpu_has_x86_64_v3() {
        eprintln!(
            "bgkmap: this build needs an x86-64-v3 CPU (AVX2, BMI2, FMA, LZCNT: Intel Haswell, AMD Zen \
             or later), and this one lacks some of it. Rebuild for baseline x86-64 with \
             RUSTFLAGS=\"-C target-cpu=x86-64\" cargo build --release"
        );
        return std::process::ExitCode::from(2);
    }
    bgkmap::cli::main()
}

/// Whether the CPU (and the OS, for the AVX registers) has what x86-64-v3 builds use: the build
/// targets it (`.cargo/config.toml`), so a CPU without it is refused with a clear message rather
/// than stopped by an illegal instruction somewhere later. Asked of CPUID itself:
/// `is_x86_feature_detected!` answers true without asking for features the build enables. This
/// runs before any of the crate's code; std's start-up code is built for baseline x86-64.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[allow(unsafe_code)]
fn cpu_has_x86_64_v3() -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
    let bit = |word: u32, b: u32| word >> b & 1 == 1;
    // Leaves above the maxima the CPU reports are not asked.
    let (max, max_ext) = (__cpuid(0).eax, __cpuid(0x8000_0000).eax);
    if max < 7 || max_ext < 0x8000_0001 {
        return false;
    }
    let (l1, l7, ext) = (__cpuid(1), __cpuid_count(7, 0), __cpuid(0x8000_0001));
    let (fma, osxsave, avx, f16c) = (bit(l1.ecx, 12), bit(l1.ecx, 27), bit(l1.ecx, 28), bit(l1.ecx, 29));
    let (bmi1, avx2, bmi2) = (bit(l7.ebx, 3), bit(l7.ebx, 5), bit(l7.ebx, 8));
    let lzcnt = bit(ext.ecx, 5);
    // SAFETY: XGETBV exists when the OS has enabled XSAVE (OSXSAVE, tested first).
    let ymm_enabled = osxsave && unsafe { _xgetbv(0) } & 0b110 == 0b110;
    fma && avx && f16c && bmi1 && avx2 && bmi2 && lzcnt && ymm_enabled
}
