//! Motion between frames: SE(3) exponential and logarithm, and a constant-velocity Kalman
//! filter on the per-frame twist (the paper's future work).
//!
//! A rigid motion `M` (points: `P' = M·P`) is written as the twist `ξ = (ω, v)` with
//! `M = exp(ξ)`: `ω` the rotation vector (radians), `v` such that `t = V(ω)·v`. A motion over
//! `k` frames at constant velocity is `exp(k·ξ)`; one over a gap of `k` frames is brought back
//! to one frame by `exp(log(M) / k)`.

use nalgebra::{Isometry3, Matrix3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};

fn hat(w: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -w.z, w.y, w.z, 0.0, -w.x, -w.y, w.x, 0.0)
}

/// `V(ω)`, the matrix with `t = V·v` (Rodrigues' series for the translation).
fn v_matrix(w: &Vector3<f64>) -> Matrix3<f64> {
    let th = w.norm();
    let k = hat(w);
    if th < 1e-9 {
        return Matrix3::identity() + k * 0.5;
    }
    let (s, c) = th.sin_cos();
    Matrix3::identity() + k * ((1.0 - c) / (th * th)) + k * k * ((th - s) / (th * th * th))
}

/// The twist of a motion.
pub fn log(m: &Isometry3<f64>) -> Vector6<f64> {
    let w = m.rotation.scaled_axis();
    let v = v_matrix(&w).try_inverse().unwrap_or_else(Matrix3::identity) * m.translation.vector;
    Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
}

/// The motion of a twist.
pub fn exp(xi: &Vector6<f64>) -> Isometry3<f64> {
    let w = Vector3::new(xi[0], xi[1], xi[2]);
    let v = Vector3::new(xi[3], xi[4], xi[5]);
    Isometry3::from_parts(Translation3::from(v_matrix(&w) * v), UnitQuaternion::from_scaled_axis(w))
}

/// The noise model of [`MotionFilter`]; standard deviations per frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionNoise {
    /// How much the rotation rate may change from one frame to the next, degrees.
    pub accel_deg: f64,
    /// How much the translation rate may change from one frame to the next, mm.
    pub accel_mm: f64,
    /// Error of one registered step's rotation, degrees.
    pub measure_deg: f64,
    /// Error of one registered step's translation, mm.
    pub measure_mm: f64,
}

impl Default for MotionNoise {
    fn default() -> Self {
        // A turntable turns at a steady rate; ICP between consecutive stereo views is good to
        // about 0.1–0.4° (docs/registration.md), and its translation error follows from the
        // rotation error times the lever arm to the axis (≈ 0.5 mm at 450 mm, 0.05°).
        MotionNoise { accel_deg: 0.05, accel_mm: 0.3, measure_deg: 0.2, measure_mm: 1.5 }
    }
}

/// Constant-velocity Kalman filter over SE(3): the state is the per-frame twist, assumed
/// constant up to a random change per frame; every registered step measures it.
#[derive(Debug, Clone)]
pub struct MotionFilter {
    noise: MotionNoise,
    state: Option<(Vector6<f64>, Matrix6<f64>)>,
}

fn diag(deg: f64, mm: f64) -> Matrix6<f64> {
    let (r, t) = (deg.to_radians().powi(2), mm * mm);
    Matrix6::from_diagonal(&Vector6::new(r, r, r, t, t, t))
}

impl MotionFilter {
    pub fn new(noise: MotionNoise) -> MotionFilter {
        MotionFilter { noise, state: None }
    }

    /// Folds in one registered step `next_from_prev` that spans `frames` frames (> 0).
    pub fn update(&mut self, next_from_prev: &Isometry3<f64>, frames: u64) {
        let k = frames.max(1) as f64;
        let z = log(next_from_prev) / k;
        // The measurement of a rate over k frames is k times more precise per frame.
        let r = diag(self.noise.measure_deg, self.noise.measure_mm) / (k * k);
        let q = diag(self.noise.accel_deg, self.noise.accel_mm) * k;
        self.state = Some(match self.state {
            None => (z, r),
            Some((x, p)) => {
                let p = p + q;
                let gain = p * (p + r).try_inverse().unwrap_or_else(Matrix6::identity);
                let x = x + gain * (z - x);
                let p = (Matrix6::identity() - gain) * p;
                (x, (p + p.transpose()) * 0.5)
            }
        });
    }

    /// The predicted motion over `frames` frames starting `lag` frames after the last
    /// measurement, with the covariance of its twist; `None` before the first measurement.
    pub fn predict(&self, frames: u64, lag: u64) -> Option<(Isometry3<f64>, Matrix6<f64>)> {
        let (x, p) = self.state?;
        let k = frames.max(1) as f64;
        let q = diag(self.noise.accel_deg, self.noise.accel_mm);
        // The rate drifts for `lag` frames, then for each of the k frames predicted.
        let p = p + q * (lag as f64 + 0.5 * k);
        Some((exp(&(x * k)), p * (k * k)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn motion(deg: f64, t: [f64; 3]) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::new(t[0], t[1], t[2]), UnitQuaternion::from_scaled_axis(Vector3::new(0.1, 1.0, 0.2).normalize() * deg.to_radians()))
    }

    #[test]
    fn exp_inverts_log() {
        for m in [motion(0.0, [1.0, 2.0, 3.0]), motion(3.0, [-5.0, 0.4, 20.0]), motion(170.0, [0.0, 0.0, -7.0])] {
            let back = exp(&log(&m));
            assert!((back.to_homogeneous() - m.to_homogeneous()).norm() < 1e-9);
        }
    }

    #[test]
    fn twice_the_twist_is_the_motion_applied_twice() {
        let m = motion(2.0, [10.0, -1.0, 3.0]);
        let twice = exp(&(log(&m) * 2.0));
        assert!((twice.to_homogeneous() - (m * m).to_homogeneous()).norm() < 1e-9);
    }

    #[test]
    fn filter_converges_on_a_steady_motion_and_predicts_over_gaps() {
        let step = motion(2.0, [15.0, 0.0, -1.0]);
        let mut f = MotionFilter::new(MotionNoise::default());
        assert!(f.predict(1, 0).is_none());
        let mut noisy = 0.0f64;
        for i in 0..20 {
            // ±0.1° of alternating measurement error.
            let e = if i % 2 == 0 { 0.1 } else { -0.1 };
            let measured = motion(2.0 + e, [15.0, 0.0, -1.0]);
            noisy = noisy.max(e.abs());
            f.update(&measured, 1);
        }
        let (one, cov1) = f.predict(1, 0).unwrap();
        let err = (one.inverse() * step).rotation.angle().to_degrees();
        assert!(err < noisy, "{err}");
        // Over three frames the motion is the step three times; the uncertainty grows.
        let (three, cov3) = f.predict(3, 0).unwrap();
        assert!(((three.inverse() * step * step * step).rotation.angle().to_degrees()) < 3.0 * noisy);
        assert!(cov3.trace() > cov1.trace());
        // Lag widens too.
        let (_, lagged) = f.predict(1, 4).unwrap();
        assert!(lagged.trace() > cov1.trace());
        // A step measured over a gap of two frames counts as two of one.
        let mut g = MotionFilter::new(MotionNoise::default());
        g.update(&(step * step), 2);
        let (per_frame, _) = g.predict(1, 0).unwrap();
        assert!((per_frame.inverse() * step).rotation.angle() < 1e-9);
    }
}
