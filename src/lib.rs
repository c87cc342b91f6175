//! spinscan: 3D shape recovery on a turntable with registration-assisted stereo matching
//! (Lin, Liang & Wu, IbPRIA 2007).
//!
//! ```text
//!  raw pair ──[calib: undistort + rectify]──> rectified pair ──[segment: blue screen]──> mask
//!                                                   │                                      │
//!                                                   └──[stereo::matcher: intervals]<───────┘
//!                                                                  │
//!                                       disparity ──[triangulate: Q, R1ᵀ]──> coloured points
//!                                                                  │          (left raw frame, mm)
//!                                                        PNG16 / PFM / PLY
//! ```
//!
//! Quick start on the simulated lab (no devices, no files):
//!
//! ```
//! use spinscan::pipeline::{Pipeline, PipelineOptions};
//! use spinscan::stereo::MatchParams;
//! let scene = spinscan::hw::sim::small_scene("egg", 160, 120, 175.0);
//! let calib = spinscan::hw::sim::calib_of(&scene.rig);
//! let (left, right) = spinscan::hw::sim::render_pair(&scene, 30.0).unwrap();
//! let mut pipe = Pipeline::new(&calib, (160, 120), PipelineOptions { matching: MatchParams { num_disparities: 48, ..Default::default() }, ..Default::default() }).unwrap();
//! let view = pipe.process_rgb(&left, &right, true).unwrap();
//! assert!(view.cloud.len() > 1000);
//! ```

pub mod assist;
pub mod bench;
pub mod calib;
pub mod cloud;
pub mod control;
pub mod daemon;
mod disjoint;
pub mod fuse;
pub mod fuzz;
pub mod hw;
pub mod io;
pub mod pipeline;
pub mod recording;
pub mod register;
pub mod segment;
pub mod stereo;
#[cfg(test)]
mod testing;
