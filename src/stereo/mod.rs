//! The stereo core: rectification, correlation matching and triangulation. Pure
//! computation on in-memory images — this module does no IO.

mod kernels;
pub mod matcher;
pub mod params;
pub mod rectify;
pub mod speckle;
pub mod triangulate;

pub use matcher::{DisparityIntervals, DisparityMap, GrayView, MatchError, MatchStats, StereoMatcher};
pub use params::{MatchParams, ParamError, ValidMatchParams};
pub use rectify::{Rectification, RectifyError, RemapTable};
