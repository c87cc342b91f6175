//! Disparity → 3D points with `Q`, expressed in the LEFT raw (unrectified) camera frame.

use nalgebra::{Vector3, Vector4};

use super::disparity::DisparityMap;
use super::rectify::Rectification;
use crate::cloud::PointCloud;

/// Triangulates every pixel with a disparity. `colors` is the rectified left image as
/// interleaved RGB (same size as the map). Points are in millimetres in the left raw camera
/// frame (`left_from_rectleft = R1ᵀ`); pixels whose point falls behind the camera are skipped.
/// With `inner` (one byte per pixel), also the cloud of the pixels where it is not 0 (the
/// view less the silhouette's rim: [`crate::segment::inside_rim`]). Both in pixel order.
pub fn triangulate(disp: &DisparityMap, rect: &Rectification, colors: &[u8], inner: Option<&[u8]>) -> (PointCloud, Option<PointCloud>) {
    let (mut cloud, mut kept) = (PointCloud::default(), inner.map(|_| PointCloud::default()));
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
            let i = y * disp.width + x;
            let (point, color) = ([p.x as f32, p.y as f32, p.z as f32], [colors[3 * i], colors[3 * i + 1], colors[3 * i + 2]]);
            cloud.points.push(point);
            cloud.colors.push(color);
            if let (Some(kept), Some(inner)) = (kept.as_mut(), inner) {
                if inner[i] != 0 {
                    kept.points.push(point);
                    kept.colors.push(color);
                }
            }
        }
    }
    (cloud, kept)
}
