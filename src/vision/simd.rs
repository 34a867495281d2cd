//! The instruction set of the dense stages, chosen once at run time: the
//! hot loops (the dense chain bound, HOG) are written once and compiled
//! for AVX-512, AVX2 and the portable baseline; every path performs the
//! same IEEE operations in the same order (no fused multiply-adds), so
//! their results are bit-identical.

/// The instruction set the dense stages run on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Simd {
    /// AVX-512 F, BW, DQ and VL (16 lanes per instruction).
    Avx512,
    /// AVX2 and FMA (8 lanes).
    Avx2,
    Portable,
}

/// The best instruction set of this processor, found once: AVX-512 where
/// there is one (the dense bound of 16 positions in one register: 14.1
/// ms instead of 19.7 per CMU_KO8 image with one model, 71.6 instead of
/// 119.9 with eight, on one core), unless `SDHOP_SIMD=avx2` or
/// `SDHOP_SIMD=portable` asks for less.
pub fn level() -> Simd {
    static LEVEL: std::sync::OnceLock<Simd> = std::sync::OnceLock::new();
    *LEVEL.get_or_init(|| {
        let cap = std::env::var("SDHOP_SIMD").unwrap_or_default();
        #[cfg(target_arch = "x86_64")]
        {
            let avx2 = std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma");
            let avx512 = avx2
                && std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512dq")
                && std::arch::is_x86_feature_detected!("avx512vl");
            match cap.as_str() {
                "portable" => Simd::Portable,
                "avx2" if avx2 => Simd::Avx2,
                _ if avx512 => Simd::Avx512,
                _ if avx2 => Simd::Avx2,
                _ => Simd::Portable,
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = cap;
            Simd::Portable
        }
    })
}
