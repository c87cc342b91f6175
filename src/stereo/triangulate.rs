//! Disparity → 3D points with `Q`, expressed in the LEFT raw (unrectified) camera frame.

use nalgebra::{Vector3, Vector4};

use super::disparity::DisparityMap;
use super::rectify::Rectification;
use crate::cloud::PointCloud;

/// Triangulates every pixel with a disparity. `colors` is the rectified left image as
/// interleaved RGB (same size as the map). Points are in millimetres in the left raw camera
/// frame (`left_from_rectleft = R1ᵀ`); pixels whose point falls behind the camera are skipped.
pub fn triangulate(disp: &DisparityMap, rect: &Rectification, colors: &[u8]) -> PointCloud {
    let mut cloud = PointCloud::default();
    let left_from_rect = rect.r1.transpose();
    for y in 0..disp.height {
        for x in 0..disp.width {
            let Some(d) = disp.get(x, y) else { continue };
            let h = rect.q * Vector4::new(x as f64, y as f64, d as f64, 1.0);
            if h.w == 0.0 {
                continue;
            }
            let p_rect = Vector3::new(h.x / h.w, h.y / h.w, h.z / h.w);
            if !(p_rect.z > 0.0) {
                continue;
            }
            let p = left_from_rect * p_rect;
            let i = (y * disp.width + x) * 3;
            cloud.points.push([p.x as f32, p.y as f32, p.z as f32]);
            cloud.colors.push([colors[i], colors[i + 1], colors[i + 2]]);
        }
    }
    cloud
}
