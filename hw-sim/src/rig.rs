//! The simulated stereo rig: two pinhole cameras with OpenCV's 5-coefficient lens
//! distortion, and the right camera's pose relative to the left.

use crate::math::{rotation, Pose};

/// One camera's intrinsics in OpenCV's model: `K = [fx 0 cx; 0 fy cy; 0 0 1]`, distortion
/// `(k1, k2, p1, p2, k3)`, pixel centres at integer coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: [f64; 5],
}

impl Intrinsics {
    /// Normalised undistorted coordinates → distorted normalised coordinates.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)
    }

    /// Pixel → normalised undistorted coordinates (fixed-point iteration, as OpenCV's
    /// `undistortPoints`, run to convergence).
    pub fn undistort_pixel(&self, u: f64, v: f64) -> (f64, f64) {
        let (xd, yd) = ((u - self.cx) / self.fx, (v - self.cy) / self.fy);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..50 {
            let (dx, dy) = self.distort(x, y);
            let (ex, ey) = (dx - xd, dy - yd);
            x -= ex;
            y -= ey;
            if ex.abs() < 1e-14 && ey.abs() < 1e-14 {
                break;
            }
        }
        (x, y)
    }

    /// Camera-frame point → pixel, through the lens model.
    pub fn project(&self, p: [f64; 3]) -> (f64, f64) {
        let (x, y) = self.distort(p[0] / p[2], p[1] / p[2]);
        (self.fx * x + self.cx, self.fy * y + self.cy)
    }

    pub fn is_pinhole(&self) -> bool {
        self.distortion.iter().all(|&d| d == 0.0)
    }
}

/// A stereo pair of cameras: `X_right = right_from_left · X_left` (OpenCV's R, T; mm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rig {
    pub width: usize,
    pub height: usize,
    pub left: Intrinsics,
    pub right: Intrinsics,
    pub right_from_left: Pose,
}

impl Rig {
    /// The ideal rectified rig: identical distortion-free cameras, parallel axes, the right
    /// camera `baseline_mm` to the right (`R = I`, `T = (−B, 0, 0)`).
    pub fn ideal(width: usize, height: usize, focal_px: f64, baseline_mm: f64) -> Rig {
        let k = Intrinsics {
            fx: focal_px,
            fy: focal_px,
            cx: (width as f64 - 1.0) / 2.0,
            cy: (height as f64 - 1.0) / 2.0,
            distortion: [0.0; 5],
        };
        Rig { width, height, left: k, right: k, right_from_left: Pose { r: crate::math::IDENTITY, t: [-baseline_mm, 0.0, 0.0] } }
    }

    /// A rig as it comes out of a real calibration: slightly different focal lengths and
    /// principal points, barrel distortion, and the right camera turned by a few tenths of
    /// a degree and offset by a fraction of a millimetre from the ideal position.
    pub fn realistic(width: usize, height: usize, focal_px: f64, baseline_mm: f64) -> Rig {
        let ideal = Rig::ideal(width, height, focal_px, baseline_mm);
        let left = Intrinsics {
            fx: focal_px * 1.003,
            fy: focal_px * 0.998,
            cx: ideal.left.cx + 4.2,
            cy: ideal.left.cy - 3.1,
            distortion: [-0.11, 0.09, 0.0007, -0.0004, -0.02],
        };
        let right = Intrinsics {
            fx: focal_px * 0.996,
            fy: focal_px * 1.001,
            cx: ideal.right.cx - 5.3,
            cy: ideal.right.cy + 2.4,
            distortion: [-0.095, 0.07, -0.0005, 0.0006, -0.01],
        };
        let r = crate::math::mat_mul(&rotation([0.0, 1.0, 0.0], 0.45f64.to_radians()), &rotation([1.0, 0.0, 0.2], 0.3f64.to_radians()));
        Rig { width, height, left, right, right_from_left: Pose { r, t: [-baseline_mm, 0.6, -0.9] } }
    }

    /// This rig with the right camera turned about its own vertical axis by `deg` towards the
    /// left camera's line of sight (its centre stays where it is): a toed-in rig, whose
    /// cameras both aim at the object. `atan(baseline / distance)` aims it at the point of
    /// the left camera's axis that far away.
    pub fn toed_in(self, deg: f64) -> Rig {
        if deg == 0.0 {
            return self;
        }
        let p = self.right_from_left;
        // The right camera's centre in the left camera's frame: −Rᵀ·t.
        let rt = crate::math::transpose(&p.r);
        let c = crate::math::scale(crate::math::mat_vec(&rt, p.t), -1.0);
        // Towards −x when the right camera sits to the left camera's right (x > 0).
        let turn = rotation([0.0, 1.0, 0.0], deg.to_radians() * c[0].signum());
        let r = crate::math::mat_mul(&turn, &p.r);
        let t = crate::math::scale(crate::math::mat_vec(&r, c), -1.0);
        Rig { right_from_left: Pose { r, t }, ..self }
    }

    pub fn baseline_mm(&self) -> f64 {
        crate::math::norm(self.right_from_left.t)
    }

    /// True for the rig [`Rig::ideal`] builds (the only one with ground-truth disparity).
    pub fn is_ideal(&self) -> bool {
        let p = &self.right_from_left;
        self.left == self.right
            && self.left.is_pinhole()
            && p.r == crate::math::IDENTITY
            && p.t[1] == 0.0
            && p.t[2] == 0.0
            && p.t[0] < 0.0
            && self.left.fx == self.left.fy
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort() {
        let rig = Rig::realistic(640, 480, 700.0, 60.0);
        for &(u, v) in &[(0.0, 0.0), (639.0, 479.0), (320.0, 10.0), (17.0, 400.0)] {
            let (x, y) = rig.left.undistort_pixel(u, v);
            let (u2, v2) = rig.left.project([x, y, 1.0]);
            assert!((u - u2).abs() < 1e-9 && (v - v2).abs() < 1e-9, "({u}, {v}) → ({u2}, {v2})");
        }
        assert!(Rig::ideal(640, 480, 700.0, 60.0).is_ideal());
        assert!(!rig.is_ideal());
    }

    /// Toed in by atan(B / Z), the right camera looks at the point of the left camera's axis
    /// Z away, from where it stood; on either side of the left camera.
    #[test]
    fn a_toed_in_right_camera_aims_at_the_left_camera_s_axis() {
        for baseline in [120.0, -120.0] {
            let rig = Rig::ideal(640, 480, 700.0, baseline);
            let toed = rig.toed_in((baseline.abs() / 400.0f64).atan().to_degrees());
            let aimed = toed.right_from_left.apply([0.0, 0.0, 400.0]);
            assert!(aimed[0].abs() < 1e-9 && aimed[1].abs() < 1e-9 && aimed[2] > 0.0, "{baseline}: {aimed:?}");
            let centre = |p: &Pose| crate::math::mat_vec(&crate::math::transpose(&p.r), crate::math::scale(p.t, -1.0));
            let (a, b) = (centre(&rig.right_from_left), centre(&toed.right_from_left));
            assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-9), "{a:?} against {b:?}");
            assert!(!toed.is_ideal());
        }
        assert_eq!(Rig::realistic(640, 480, 700.0, 60.0).toed_in(0.0), Rig::realistic(640, 480, 700.0, 60.0));
    }
}
