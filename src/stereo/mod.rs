//! The stereo core: rectification, correlation matching and triangulation. Pure
//! computation on in-memory images — this module does no IO.

mod buffer;
pub mod disparity;
pub mod follow;
pub mod gain;
pub(crate) mod kernels;
pub mod matcher;
pub mod params;
pub mod rectify;
pub mod remap;
mod sgm;
pub mod speckle;
pub mod triangulate;
pub mod truth;

pub use disparity::{DisparityIntervals, DisparityMap, GrayView, MatchStats};
pub use matcher::{MatchError, StereoMatcher, BAND_TILE};
pub use params::{MatchParams, Method, ParamError, ValidMatchParams};
pub use rectify::{Rectification, RectifyError};
pub use remap::{luma, RemapTable};

/// The vector extensions of this CPU that the matchers choose their code by: `avx2`, and the
/// AVX-512 subsets that `bm`'s searches of 128 disparities or more (`avx512f`, `avx512bw`) and
/// SGM's census costs (`avx512vl`, `avx512vpopcntdq`) use. Timings, and the ratios between
/// the two matchers' rows, depend on them (docs/assisted-matching.md, "The row without
/// assistance as the product runs it"), so reports name them.
pub fn vector_extensions() -> Vec<&'static str> {
    #[cfg(target_arch = "x86_64")]
    {
        let found = [
            ("avx2", std::is_x86_feature_detected!("avx2")),
            ("avx512f", std::is_x86_feature_detected!("avx512f")),
            ("avx512bw", std::is_x86_feature_detected!("avx512bw")),
            ("avx512vl", std::is_x86_feature_detected!("avx512vl")),
            ("avx512vpopcntdq", std::is_x86_feature_detected!("avx512vpopcntdq")),
        ];
        found.into_iter().filter(|(_, on)| *on).map(|(name, _)| name).collect()
    }
    #[cfg(not(target_arch = "x86_64"))]
    Vec::new()
}
