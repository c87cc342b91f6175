//! Adapters from the simulated lab (`hw-sim`) to spinscan's types.

use nalgebra::{Matrix3, Vector3};

use crate::calib::{Camera, Distortion, StereoCalib};

/// The calibration of hw-sim's ideal rectified rig: identical pinhole cameras, no
/// distortion, `R = I`, `T = (−baseline, 0, 0)` mm.
pub fn ideal_calib(scene: &hw_sim::SceneConfig) -> StereoCalib {
    let (cx, cy) = scene.principal_point();
    let k = Matrix3::new(scene.focal_px, 0.0, cx, 0.0, scene.focal_px, cy, 0.0, 0.0, 1.0);
    StereoCalib {
        left: Camera { k, distortion: Distortion::none() },
        right: Camera { k, distortion: Distortion::none() },
        r: Matrix3::identity(),
        t_mm: Vector3::new(-scene.baseline_mm, 0.0, 0.0),
        image_size: Some((scene.width as u32, scene.height as u32)),
    }
}
