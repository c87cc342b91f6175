//! Bouguet rectification, computed the way OpenCV 5's `stereoRectify(…, CALIB_ZERO_DISPARITY,
//! alpha)` computes it; the remap tables it makes are [`super::remap`]'s.
//!
//! Frames: the rectified left camera is `R1 · (raw left camera)`; `P1`, `P2` project rectified
//! camera-frame points (of the left rectified frame) to rectified pixels; `Q` maps
//! `[x y d 1]` (rectified left pixel + disparity `d = x_left − x_right`) to homogeneous
//! rectified-left points in millimetres.

use nalgebra::{Matrix3, Matrix3x4, Matrix4, Rotation3, Vector3};

use super::remap::RemapTable;
use crate::calib::{Camera, StereoCalib};

/// Iterations of the undistortion fixed point that OpenCV's `undistortPoints` uses by default;
/// `stereoRectify` depends on it, so reproducing OpenCV's matrices needs the same count.
pub const OPENCV_UNDISTORT_ITERATIONS: usize = 5;

/// Iterations used when undistorting points for measurement (converged for real lenses).
pub const PRECISE_UNDISTORT_ITERATIONS: usize = 50;

/// The rectifying transforms of a stereo rig.
#[derive(Debug, Clone, PartialEq)]
pub struct Rectification {
    /// `rectleft_from_left`: rotates raw left camera coordinates into the rectified frame.
    pub r1: Matrix3<f64>,
    /// `rectright_from_right`.
    pub r2: Matrix3<f64>,
    pub p1: Matrix3x4<f64>,
    pub p2: Matrix3x4<f64>,
    pub q: Matrix4<f64>,
    /// +1 when rectified disparities `x_left − x_right` are positive, −1 when the rectified
    /// right camera sits left of the left one (see "Disparity sign" in the recording spec).
    pub disparity_sign: i32,
    /// `(width, height)` of the raw and rectified images.
    pub size: (u32, u32),
    /// The alpha it was computed with (the one found, by
    /// [`Rectification::compute_keeping_views`]).
    pub alpha: f64,
}

/// Share of each raw image's width and height, about its centre, that
/// [`Rectification::compute_keeping_views`] keeps in view.
pub const KEPT_VIEW: f64 = 0.6;

/// Rotation vector → matrix (OpenCV `Rodrigues`).
fn rodrigues(v: &Vector3<f64>) -> Matrix3<f64> {
    Rotation3::from_scaled_axis(*v).into_inner()
}

/// Rotation matrix → rotation vector (OpenCV `Rodrigues`), orthonormalising first.
fn rodrigues_inv(r: &Matrix3<f64>) -> Vector3<f64> {
    Rotation3::from_matrix_eps(r, 1e-15, 100, Rotation3::identity()).scaled_axis()
}

/// `undistortPoints(pts, K, D, R, P)` for one pixel: raw pixel → pixel of the camera
/// `P[:, :3]` after rotating by `R`.
pub fn undistort_point(cam: &Camera, r: &Matrix3<f64>, p: &Matrix3<f64>, uv: (f64, f64), iterations: usize) -> (f64, f64) {
    let k = &cam.k;
    let xd = (uv.0 - k[(0, 2)]) / k[(0, 0)];
    let yd = (uv.1 - k[(1, 2)]) / k[(1, 1)];
    let (x, y) = cam.distortion.undistort(xd, yd, iterations);
    let v = p * r * Vector3::new(x, y, 1.0);
    (v.x / v.z, v.y / v.z)
}

/// A rectangle as `(x0, y0, x1, y1)`.
type Rect = (f64, f64, f64, f64);

/// OpenCV's `getUndistortRectangles`: the largest rectangle inside, and the smallest around,
/// the undistorted + rectified image of a 9×9 grid over the raw image.
fn undistort_rectangles(cam: &Camera, r: &Matrix3<f64>, p: &Matrix3<f64>, size: (u32, u32)) -> (Rect, Rect) {
    const N: usize = 9;
    let (w, h) = (size.0 as f64, size.1 as f64);
    let (mut ix0, mut ix1, mut iy0, mut iy1) = (f64::MIN, f64::MAX, f64::MIN, f64::MAX);
    let (mut ox0, mut ox1, mut oy0, mut oy1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for y in 0..N {
        for x in 0..N {
            let uv = (x as f64 * (w - 1.0) / (N - 1) as f64, y as f64 * (h - 1.0) / (N - 1) as f64);
            let (px, py) = undistort_point(cam, r, p, uv, OPENCV_UNDISTORT_ITERATIONS);
            ox0 = ox0.min(px);
            ox1 = ox1.max(px);
            oy0 = oy0.min(py);
            oy1 = oy1.max(py);
            if x == 0 {
                ix0 = ix0.max(px);
            }
            if x == N - 1 {
                ix1 = ix1.min(px);
            }
            if y == 0 {
                iy0 = iy0.max(py);
            }
            if y == N - 1 {
                iy1 = iy1.min(py);
            }
        }
    }
    ((ix0, iy0, ix1, iy1), (ox0, oy0, ox1, oy1))
}

/// The smallest rectangle around the rectified image of the raw image's middle
/// ([`KEPT_VIEW`] of its width and height: its corners and the middles of its sides).
fn middle_rectangle(cam: &Camera, r: &Matrix3<f64>, p: &Matrix3<f64>, size: (u32, u32)) -> Rect {
    let (w, h) = (size.0 as f64 - 1.0, size.1 as f64 - 1.0);
    let margin = (1.0 - KEPT_VIEW) / 2.0;
    let mut out = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for (fx, fy) in [(0.0, 0.0), (0.5, 0.0), (1.0, 0.0), (0.0, 0.5), (1.0, 0.5), (0.0, 1.0), (0.5, 1.0), (1.0, 1.0)] {
        let uv = (w * (margin + KEPT_VIEW * fx), h * (margin + KEPT_VIEW * fy));
        let (px, py) = undistort_point(cam, r, p, uv, OPENCV_UNDISTORT_ITERATIONS);
        out = (out.0.min(px), out.1.min(py), out.2.max(px), out.3.max(py));
    }
    out
}

/// Why rectification is impossible.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RectifyError {
    #[error("alpha must be −1 (OpenCV's default scaling) or within 0…1, got {0}")]
    Alpha(f64),
    #[error("the baseline T is zero")]
    ZeroBaseline,
    #[error("image size {0}×{1} is too small to rectify")]
    Size(u32, u32),
}

impl Rectification {
    /// Bouguet's method, as OpenCV 5's `stereoRectify(M1, D1, M2, D2, size, R, T, R1, R2, P1,
    /// P2, Q, CALIB_ZERO_DISPARITY, alpha)`.
    ///
    /// `alpha`: 0 crops to valid pixels only, 1 keeps every raw pixel, −1 keeps OpenCV's
    /// unscaled focal length.
    pub fn compute(calib: &StereoCalib, size: (u32, u32), alpha: f64) -> Result<Rectification, RectifyError> {
        if !(alpha == -1.0 || (0.0..=1.0).contains(&alpha)) {
            return Err(RectifyError::Alpha(alpha));
        }
        Self::build(calib, size, Some(alpha))
    }

    /// spinscan's default: as [`Rectification::compute`] with the least alpha from 0 that
    /// keeps the middle of both cameras' views ([`KEPT_VIEW`] of each raw image's width and
    /// height, where a turntable rig aims at its object) inside the rectified images.
    ///
    /// That is alpha 0 — valid pixels only, every matched pixel with real image data behind
    /// it — on a rig whose cameras look nearly the same way. On a toed-in rig, whose cameras
    /// both aim at the object, the pixels valid in both rectified images are a narrow strip
    /// between the two views (the object sits right of the middle in the left image and left
    /// of it in the right one, by its disparity), and alpha 0 zooms into that strip and cuts
    /// the object out of one image or both; the alpha found instead zooms out just enough to
    /// hold both views' middles, leaving pixels at the images' sides with no data (black).
    pub fn compute_keeping_views(calib: &StereoCalib, size: (u32, u32)) -> Result<Rectification, RectifyError> {
        Self::build(calib, size, None)
    }

    /// `alpha` None: the one [`Rectification::compute_keeping_views`] finds.
    fn build(calib: &StereoCalib, size: (u32, u32), alpha: Option<f64>) -> Result<Rectification, RectifyError> {
        if size.0 < 2 || size.1 < 2 {
            return Err(RectifyError::Size(size.0, size.1));
        }
        let (nx, ny) = (size.0 as f64, size.1 as f64);
        // Half of the rotation for each camera, so both turn by the same amount.
        let om = rodrigues_inv(&calib.r) * -0.5;
        let r_r = rodrigues(&om);
        let t = r_r * calib.t_mm;
        let idx = if t.x.abs() > t.y.abs() { 0 } else { 1 };
        let c = t[idx];
        let nt = t.norm();
        if nt == 0.0 {
            return Err(RectifyError::ZeroBaseline);
        }
        let mut uu = Vector3::zeros();
        uu[idx] = if c > 0.0 { 1.0 } else { -1.0 };
        // The global rotation that brings the baseline onto the image x (or y) axis.
        let mut ww = t.cross(&uu);
        let nw = ww.norm();
        if nw > 0.0 {
            ww *= (c.abs() / nt).acos() / nw;
        }
        let w_r = rodrigues(&ww);
        let r1 = w_r * r_r.transpose();
        let r2 = w_r * r_r;
        let t = r2 * calib.t_mm;

        let fy = |cam: &Camera| cam.k[(idx ^ 1, idx ^ 1)];
        let mut fc_new = (fy(&calib.left) + fy(&calib.right)) * 0.5;

        // Principal points: centre the undistorted image corners.
        let mut cc_new = [(0.0, 0.0); 2];
        for (k, (cam, rk)) in [(&calib.left, &r1), (&calib.right, &r2)].into_iter().enumerate() {
            let mut avg = (0.0, 0.0);
            for i in 0..4 {
                let j = if i < 2 { 0.0 } else { 1.0 };
                let uv = ((i % 2) as f64 * (nx - 1.0), j * (ny - 1.0));
                let (x, y) = undistort_point(cam, &Matrix3::identity(), &Matrix3::identity(), uv, OPENCV_UNDISTORT_ITERATIONS);
                let v = rk * Vector3::new(x, y, 1.0);
                avg.0 += fc_new * v.x / v.z / 4.0;
                avg.1 += fc_new * v.y / v.z / 4.0;
            }
            cc_new[k] = ((nx - 1.0) / 2.0 - avg.0, (ny - 1.0) / 2.0 - avg.1);
        }
        // CALIB_ZERO_DISPARITY: both principal points at their average.
        let cc = ((cc_new[0].0 + cc_new[1].0) * 0.5, (cc_new[0].1 + cc_new[1].1) * 0.5);
        cc_new = [cc, cc];

        let t_idx = t[idx];
        let proj = |f: f64, cc: (f64, f64)| Matrix3::new(f, 0.0, cc.0, 0.0, f, cc.1, 0.0, 0.0, 1.0);
        let (inner1, outer1) = undistort_rectangles(&calib.left, &r1, &proj(fc_new, cc_new[0]), size);
        let (inner2, outer2) = undistort_rectangles(&calib.right, &r2, &proj(fc_new, cc_new[1]), size);

        // Scale so that the inner rectangle fills the image (alpha 0) or the outer one fits
        // inside it (alpha 1), for both cameras. `fill`: the least scale at which rectangle `r`
        // (about the principal point `cc`) covers the image; `keep`: the largest at which it
        // stays inside it (a side beyond the centre, as a toed-in rig's middle has, does not
        // bound it).
        let fill = |cc: (f64, f64), r: Rect| {
            let a = cc.0 / (cc.0 - r.0);
            let b = cc.1 / (cc.1 - r.1);
            let c = (nx - 1.0 - cc.0) / (r.2 - cc.0);
            let d = (ny - 1.0 - cc.1) / (r.3 - cc.1);
            a.max(b).max(c).max(d)
        };
        let keep = |cc: (f64, f64), r: Rect| {
            let bound = |room: f64, reach: f64| if reach > 0.0 { room / reach } else { f64::INFINITY };
            bound(cc.0, cc.0 - r.0).min(bound(cc.1, cc.1 - r.1)).min(bound(nx - 1.0 - cc.0, r.2 - cc.0)).min(bound(ny - 1.0 - cc.1, r.3 - cc.1))
        };
        let s0 = fill(cc_new[1], inner2).max(fill(cc_new[0], inner1));
        let s1 = keep(cc_new[1], outer2).min(keep(cc_new[0], outer1));
        let alpha = alpha.unwrap_or_else(|| {
            // The largest scale at which both views' middles stay inside the images, and the
            // alpha that gives it (scales fall from s0 at alpha 0 to s1 at alpha 1).
            let middle1 = middle_rectangle(&calib.left, &r1, &proj(fc_new, cc_new[0]), size);
            let middle2 = middle_rectangle(&calib.right, &r2, &proj(fc_new, cc_new[1]), size);
            let s_kept = keep(cc_new[0], middle1).min(keep(cc_new[1], middle2));
            if s_kept >= s0 || s0 <= s1 {
                0.0
            } else {
                ((s0 - s_kept) / (s0 - s1)).min(1.0)
            }
        });
        let s = if alpha >= 0.0 { s0 * (1.0 - alpha) + s1 * alpha } else { 1.0 };
        fc_new *= s;

        let mut p1 = Matrix3x4::zeros();
        p1.fixed_view_mut::<3, 3>(0, 0).copy_from(&proj(fc_new, cc_new[0]));
        let mut p2 = Matrix3x4::zeros();
        p2.fixed_view_mut::<3, 3>(0, 0).copy_from(&proj(fc_new, cc_new[1]));
        p2[(idx, 3)] = t_idx * fc_new;

        let (cx1, cy1) = cc_new[0];
        let q = Matrix4::new(
            1.0,
            0.0,
            0.0,
            -cx1,
            0.0,
            1.0,
            0.0,
            -cy1,
            0.0,
            0.0,
            0.0,
            fc_new,
            0.0,
            0.0,
            -1.0 / t_idx,
            if idx == 0 { cc_new[0].0 - cc_new[1].0 } else { cc_new[0].1 - cc_new[1].1 } / t_idx,
        );
        // x_right = x_left + f·t_idx/Z, so d = x_left − x_right has the sign of −t_idx.
        let disparity_sign = if t_idx < 0.0 { 1 } else { -1 };
        Ok(Rectification { r1, r2, p1, p2, q, disparity_sign, size, alpha })
    }

    /// The cameras are stacked vertically: the baseline runs along the rectified y axis (as
    /// OpenCV rectifies a rig whose T is more vertical than horizontal), and corresponding
    /// points share a column, not a row.
    pub fn is_vertical(&self) -> bool {
        self.p2[(1, 3)] != 0.0
    }

    /// Maps a raw left pixel to its rectified position.
    pub fn rectify_left_point(&self, calib: &StereoCalib, uv: (f64, f64)) -> (f64, f64) {
        undistort_point(&calib.left, &self.r1, &self.p1.fixed_view::<3, 3>(0, 0).into(), uv, PRECISE_UNDISTORT_ITERATIONS)
    }

    /// Maps a raw right pixel to its rectified position.
    pub fn rectify_right_point(&self, calib: &StereoCalib, uv: (f64, f64)) -> (f64, f64) {
        undistort_point(&calib.right, &self.r2, &self.p2.fixed_view::<3, 3>(0, 0).into(), uv, PRECISE_UNDISTORT_ITERATIONS)
    }

    /// Remap tables for the left and right cameras.
    pub fn maps(&self, calib: &StereoCalib) -> (RemapTable, RemapTable) {
        (
            RemapTable::new(&calib.left, &self.r1, &self.p1.fixed_view::<3, 3>(0, 0).into(), self.size),
            RemapTable::new(&calib.right, &self.r2, &self.p2.fixed_view::<3, 3>(0, 0).into(), self.size),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::Distortion;

    fn rig(t: Vector3<f64>) -> StereoCalib {
        let k = Matrix3::new(700.0, 0.0, 320.0, 0.0, 700.0, 240.0, 0.0, 0.0, 1.0);
        StereoCalib {
            left: Camera { k, distortion: Distortion::none() },
            right: Camera { k, distortion: Distortion::none() },
            r: Matrix3::identity(),
            t_mm: t,
            image_size: None,
        }
    }

    #[test]
    fn ideal_rig_rectifies_to_itself() {
        let r = Rectification::compute(&rig(Vector3::new(-60.0, 0.0, 0.0)), (640, 480), -1.0).unwrap();
        assert!((r.r1 - Matrix3::identity()).norm() < 1e-12);
        assert!((r.p1[(0, 0)] - 700.0).abs() < 1e-9);
        assert!((r.p2[(0, 3)] - -60.0 * 700.0).abs() < 1e-6);
        assert_eq!(r.disparity_sign, 1);
        // Q maps a disparity back to the depth it came from: Z = f·B/d.
        let p = r.q * nalgebra::Vector4::new(320.0, 240.0, 700.0 * 60.0 / 450.0, 1.0);
        assert!((p.z / p.w - 450.0).abs() < 1e-9);
    }

    #[test]
    fn swapped_rig_has_negative_disparities() {
        let r = Rectification::compute(&rig(Vector3::new(60.0, 0.0, 0.0)), (640, 480), 0.0).unwrap();
        assert_eq!(r.disparity_sign, -1);
    }

    /// A rig whose right camera, 160 mm to the left one's right, is turned to look at the
    /// point of the left camera's axis 450 mm away (the object of a toed-in turntable rig).
    fn toed_in_rig() -> StereoCalib {
        let (b, z) = (160.0f64, 450.0f64);
        let r = *Rotation3::from_axis_angle(&Vector3::y_axis(), (b / z).atan()).matrix();
        StereoCalib { r, t_mm: -(r * Vector3::new(b, 0.0, 0.0)), ..rig(Vector3::new(-b, 0.0, 0.0)) }
    }

    /// Where a raw pixel of each camera lands in the rectified images, and whether inside.
    fn inside(r: &Rectification, calib: &StereoCalib, uv: (f64, f64)) -> [bool; 2] {
        let (w, h) = (r.size.0 as f64 - 1.0, r.size.1 as f64 - 1.0);
        let within = |(x, y): (f64, f64)| (0.0..=w).contains(&x) && (0.0..=h).contains(&y);
        [within(r.rectify_left_point(calib, uv)), within(r.rectify_right_point(calib, uv))]
    }

    /// On a toed-in rig alpha 0 zooms into the strip both cameras see and cuts the middle of
    /// their views out of the rectified images; the default keeps the middle of both (at an
    /// alpha between 0 and 1, OpenCV's for that alpha). On a rig whose cameras look the same
    /// way the default is alpha 0 itself.
    #[test]
    fn the_default_keeps_the_middle_of_a_toed_in_rig_s_views() {
        let calib = toed_in_rig();
        let cropped = Rectification::compute(&calib, (640, 480), 0.0).unwrap();
        assert!(!inside(&cropped, &calib, (319.5, 239.5)).iter().all(|&v| v), "alpha 0 keeps both centres");
        let kept = Rectification::compute_keeping_views(&calib, (640, 480)).unwrap();
        assert!(kept.alpha > 0.0 && kept.alpha < 1.0, "{}", kept.alpha);
        assert_eq!(kept, Rectification::compute(&calib, (640, 480), kept.alpha).unwrap());
        let m = (1.0 - KEPT_VIEW) / 2.0;
        for (fx, fy) in [(m, m), (1.0 - m, m), (m, 1.0 - m), (1.0 - m, 1.0 - m), (0.5, 0.5)] {
            let uv = (639.0 * fx, 479.0 * fy);
            assert_eq!(inside(&kept, &calib, uv), [true, true], "{uv:?}");
        }
        // Zoomed out no further than it takes: a slightly larger middle does not fit.
        let edge = (1.0 - KEPT_VIEW * 1.1) / 2.0;
        let corners = [(edge, edge), (1.0 - edge, edge), (edge, 1.0 - edge), (1.0 - edge, 1.0 - edge)];
        assert!(corners.iter().any(|&(fx, fy)| inside(&kept, &calib, (639.0 * fx, 479.0 * fy)) != [true, true]));
        for t in [Vector3::new(-60.0, 0.0, 0.0), Vector3::new(60.0, 0.0, 0.0)] {
            assert_eq!(Rectification::compute_keeping_views(&rig(t), (640, 480)).unwrap(), Rectification::compute(&rig(t), (640, 480), 0.0).unwrap());
        }
    }

    #[test]
    fn rejects_bad_alpha() {
        assert_eq!(
            Rectification::compute(&rig(Vector3::new(-60.0, 0.0, 0.0)), (640, 480), 1.5),
            Err(RectifyError::Alpha(1.5))
        );
    }
}
