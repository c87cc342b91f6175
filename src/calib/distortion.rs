//! OpenCV's lens model: radial (rational), tangential, thin-prism and tilted-sensor terms.
//!
//! Coefficient order as OpenCV stores it: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [τx τy]]]].
//! Points here are normalised image coordinates (x = X/Z, y = Y/Z) unless a function says
//! otherwise.

use nalgebra::{Matrix3, Vector3};

/// A validated distortion vector of 4, 5, 8, 12 or 14 coefficients (missing ones are zero).
#[derive(Debug, Clone, PartialEq)]
pub struct Distortion {
    k: [f64; 14],
    count: usize,
    /// The tilted-sensor matrix (identity when τx = τy = 0), and its inverse.
    tilt: Matrix3<f64>,
    tilt_inv: Matrix3<f64>,
}

impl Distortion {
    /// The accepted coefficient counts, as OpenCV defines them.
    pub const COUNTS: [usize; 6] = [0, 4, 5, 8, 12, 14];

    /// No distortion at all.
    pub fn none() -> Distortion {
        Distortion::new(&[]).expect("zero coefficients are valid")
    }

    /// Builds the model from OpenCV's coefficient vector; `None` for an unsupported length.
    pub fn new(coeffs: &[f64]) -> Option<Distortion> {
        if !Self::COUNTS.contains(&coeffs.len()) {
            return None;
        }
        let mut k = [0.0; 14];
        k[..coeffs.len()].copy_from_slice(coeffs);
        let tilt = tilt_matrix(k[12], k[13]);
        let tilt_inv = tilt.try_inverse().unwrap_or_else(Matrix3::identity);
        Some(Distortion { k, count: coeffs.len(), tilt, tilt_inv })
    }

    /// The coefficients as given (length 0, 4, 5, 8, 12 or 14).
    pub fn coeffs(&self) -> &[f64] {
        &self.k[..self.count]
    }

    /// k1, the first radial coefficient.
    pub fn k1(&self) -> f64 {
        self.k[0]
    }

    /// Distorts a normalised point, including the sensor tilt: the result is what
    /// `K⁻¹ · pixel` would give for the raw image.
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let k = &self.k;
        let r2 = x * x + y * y;
        let r4 = r2 * r2;
        let r6 = r4 * r2;
        let cdist = 1.0 + k[0] * r2 + k[1] * r4 + k[4] * r6;
        let icdist2 = 1.0 / (1.0 + k[5] * r2 + k[6] * r4 + k[7] * r6);
        let a1 = 2.0 * x * y;
        let a2 = r2 + 2.0 * x * x;
        let a3 = r2 + 2.0 * y * y;
        let xd = x * cdist * icdist2 + k[2] * a1 + k[3] * a2 + k[8] * r2 + k[9] * r4;
        let yd = y * cdist * icdist2 + k[2] * a3 + k[3] * a1 + k[10] * r2 + k[11] * r4;
        let v = self.tilt * Vector3::new(xd, yd, 1.0);
        let inv = if v.z != 0.0 { 1.0 / v.z } else { 1.0 };
        (v.x * inv, v.y * inv)
    }

    /// Inverts [`Distortion::distort`] by OpenCV's fixed-point iteration, `iterations` times
    /// (OpenCV's `undistortPoints` default is 5; more converges further).
    pub fn undistort(&self, xd: f64, yd: f64, iterations: usize) -> (f64, f64) {
        let k = &self.k;
        let v = self.tilt_inv * Vector3::new(xd, yd, 1.0);
        let inv = if v.z != 0.0 { 1.0 / v.z } else { 1.0 };
        let (x0, y0) = (v.x * inv, v.y * inv);
        let (mut x, mut y) = (x0, y0);
        if self.count == 0 {
            return (x, y);
        }
        for _ in 0..iterations {
            let r2 = x * x + y * y;
            let icdist = (1.0 + ((k[7] * r2 + k[6]) * r2 + k[5]) * r2) / (1.0 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2);
            if icdist < 0.0 {
                // OpenCV gives up on points outside the model's valid radius.
                return (x0, y0);
            }
            let dx = 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x) + k[8] * r2 + k[9] * r2 * r2;
            let dy = k[2] * (r2 + 2.0 * y * y) + 2.0 * k[3] * x * y + k[10] * r2 + k[11] * r2 * r2;
            x = (x0 - dx) * icdist;
            y = (y0 - dy) * icdist;
        }
        (x, y)
    }
}

/// OpenCV's `computeTiltProjectionMatrix(τx, τy)`.
fn tilt_matrix(tau_x: f64, tau_y: f64) -> Matrix3<f64> {
    let (s_x, c_x) = tau_x.sin_cos();
    let (s_y, c_y) = tau_y.sin_cos();
    let rot_x = Matrix3::new(1.0, 0.0, 0.0, 0.0, c_x, s_x, 0.0, -s_x, c_x);
    let rot_y = Matrix3::new(c_y, 0.0, -s_y, 0.0, 1.0, 0.0, s_y, 0.0, c_y);
    let rot_xy = rot_y * rot_x;
    let proj_z = Matrix3::new(
        rot_xy[(2, 2)],
        0.0,
        -rot_xy[(0, 2)],
        0.0,
        rot_xy[(2, 2)],
        -rot_xy[(1, 2)],
        0.0,
        0.0,
        1.0,
    );
    proj_z * rot_xy
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn undistort_inverts_distort_for_every_model_size() {
        let full = [-0.2, 0.05, 1e-3, -5e-4, 0.01, 0.02, -0.01, 0.005, 1e-3, -1e-3, 2e-3, 1e-4, 0.01, -0.02];
        for n in Distortion::COUNTS {
            let d = Distortion::new(&full[..n]).unwrap();
            for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.45, 0.35)] {
                let (xd, yd) = d.distort(x, y);
                let (xu, yu) = d.undistort(xd, yd, 50);
                assert!((xu - x).abs() < 1e-9 && (yu - y).abs() < 1e-9, "n={n}: ({x},{y}) -> ({xu},{yu})");
            }
        }
    }

    #[test]
    fn rejects_unsupported_lengths() {
        assert!(Distortion::new(&[0.0; 6]).is_none());
        assert!(Distortion::new(&[0.0; 3]).is_none());
    }
}
