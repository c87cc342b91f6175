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
