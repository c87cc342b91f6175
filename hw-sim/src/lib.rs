//! The simulated lab for spinscan: stereo cameras looking at an object on a turntable in
//! front of a blue screen, and the turntable's firmware on a pseudo-terminal. Deterministic
//! for a seed; needs no devices and no files.
//!
//! ```text
//!  Mesh ──SceneConfig──> Renderer ──> SimStereoCamera ──frames (timestamps, faults)──> spinscan
//!                                          ▲ reads
//!                                     TableAngle
//!                                          │ writes
//!  spinscan's serial driver ──/dev/pts/N──> turntable::Emulator (Horus firmware, faults)
//! ```
//!
//! This crate knows nothing of spinscan (the dependency points the other way): it produces
//! images, timestamps, serial bytes and ground truth; spinscan consumes them through its
//! device seams. Frames and units: the turntable frame has `+y` up; camera frames are
//! OpenCV's (x right, y down, z forward); lengths are millimetres; the right camera is
//! `X_right = right_from_left · X_left` (OpenCV's R, T).
//!
//! ```
//! let object = hw_sim::Mesh::builtin("egg", 5_000).unwrap();
//! let mut scene = hw_sim::SceneConfig::ideal(object);
//! scene.rig = hw_sim::Rig::ideal(160, 120, 175.0, 60.0);
//! let mut renderer = hw_sim::Renderer::new(scene).unwrap();
//! let pair = renderer.render(30.0, 0);
//! assert!(pair.gt_disparity.unwrap().iter().any(|d| d.is_finite()));
//! ```

pub mod camera;
pub mod math;
pub mod mesh;
pub mod render;
pub mod rig;
pub mod target;
pub mod turntable;

pub use camera::{CameraFault, Side, SimCameraError, SimFrame, SimStereoCamera, TableAngle, Timing};
pub use math::Pose;
pub use mesh::{Mesh, MeshError, BUILTIN_OBJECTS};
pub use render::{RenderedPair, Renderer, SceneConfig};
pub use rig::{Intrinsics, Rig};
pub use target::{Chessboard, TargetPair, TargetRenderer};
pub use turntable::{Emulator, FirmwareConfig, TurntableFault};
