//! The turntable's axis from a chessboard standing on the table, seen by the calibrated rig
//! at several table angles (the paper's checkerboard on the table; Horus's method).
//!
//! 1. Each pair gives the board's pose in the left camera frame, solved from both images at
//!    once with the rig held (Levenberg–Marquardt on the reprojection error, started from the
//!    left image's homography).
//! 2. A start for the axis: the relative rotations between the first pose and each other one
//!    turn about the axis (their rotation axes, signed by the table's turn, averaged), and a
//!    point on it solves `(I − R_k) c = t_k − R_k t_0` in least squares.
//! 3. Everything at once: the axis (direction and point) and the board's pose at the first
//!    angle, every corner of every pair predicted by turning the board by the table's own
//!    angle about the axis and projected into both cameras. The residual is the fit's RMS in
//!    pixels; each pair's angle seen from its own pose is compared with the table's.
//!
//! The axis point reported is the foot, on the axis, of the perpendicular from the board's
//! centre at the first angle; only the line matters to registration. The direction is up:
//! the table's angles turn the board right-handed about it (counterclockwise from above).

use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

use super::lm::{self, BlockProblem};
use super::solve::{homography, pose_from_homography, TargetView};
use super::{Distortion, StereoCalib};

/// One pair of a board on the table.
#[derive(Debug, Clone)]
pub struct TablePair {
    pub table_deg: f64,
    pub left: TargetView,
    pub right: TargetView,
}

/// The fitted axis.
#[derive(Debug, Clone)]
pub struct AxisFit {
    /// A point on the axis, left camera frame, mm.
    pub point_mm: Vector3<f64>,
    /// Unit direction, up.
    pub dir: Vector3<f64>,
    /// RMS reprojection distance of every corner of every pair at the fit, pixels.
    pub rms_px: f64,
    /// Per pair: its RMS, pixels, and the table angle its own pose shows minus the table's
    /// (relative to the first pair), degrees.
    pub pairs: Vec<(f64, f64)>,
}

/// Why no axis.
#[derive(Debug, thiserror::Error)]
pub enum AxisError {
    #[error("{found} pairs with the board found; the axis needs at least 3, at table angles spanning 20° or more")]
    TooFewPairs { found: usize },
    #[error("the table angles span only {span:.1}°: turn the table through 20° or more (e.g. −45° … +45°)")]
    NarrowSweep { span: f64 },
    #[error("the board's poses do not turn about one axis (their rotations disagree by {deg:.1}°): did the board move on the table, or is --calib the wrong rig?")]
    NotARotation { deg: f64 },
    #[error("the board's poses do not determine an axis ({0}): did the table turn between the pairs?")]
    Degenerate(&'static str),
}

fn project(k: &Matrix3<f64>, d: &Distortion, p: &Vector3<f64>) -> [f64; 2] {
    let (x, y) = d.distort(p.x / p.z, p.y / p.z);
    [k[(0, 0)] * x + k[(0, 2)], k[(1, 1)] * y + k[(1, 2)]]
}

fn residuals(calib: &StereoCalib, pts: impl Fn(&[f64; 3]) -> Vector3<f64>, pair: &TablePair, out: &mut Vec<f64>) {
    for (view, right) in [(&pair.left, false), (&pair.right, true)] {
        for (o, q) in view.object.iter().zip(&view.image) {
            let x = pts(o);
            let (cam, x) = if right { (&calib.right, calib.r * x + calib.t_mm) } else { (&calib.left, x) };
            let uv = project(&cam.k, &cam.distortion, &x);
            out.push(uv[0] - q[0]);
            out.push(uv[1] - q[1]);
        }
    }
}

fn pose(b: &[f64]) -> (Rotation3<f64>, Vector3<f64>) {
    (Rotation3::new(Vector3::new(b[0], b[1], b[2])), Vector3::new(b[3], b[4], b[5]))
}

/// One pair's board pose, both cameras, the rig held.
struct PairPose<'a> {
    calib: &'a StereoCalib,
    pairs: &'a [TablePair],
}

impl BlockProblem for PairPose<'_> {
    fn residuals(&self, _g: &[f64], b: &[f64], view: usize, out: &mut Vec<f64>) {
        out.clear();
        let (r, t) = pose(b);
        residuals(self.calib, |o| r * Vector3::new(o[0], o[1], o[2]) + t, &self.pairs[view], out);
    }
}

/// The whole fit: global = axis direction (2 angles about `dir0`'s normals), axis point (2
/// offsets in the plane normal to `dir0` through `point0`), board pose at the first angle (6).
struct Axis<'a> {
    calib: &'a StereoCalib,
    pairs: &'a [TablePair],
    dir0: Vector3<f64>,
    point0: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
}

impl Axis<'_> {
    fn axis(&self, g: &[f64]) -> (Vector3<f64>, Vector3<f64>) {
        let dir = (self.dir0 + self.e1 * g[0] + self.e2 * g[1]).normalize();
        (dir, self.point0 + self.e1 * g[2] + self.e2 * g[3])
    }
}

impl BlockProblem for Axis<'_> {
    fn residuals(&self, g: &[f64], _b: &[f64], view: usize, out: &mut Vec<f64>) {
        out.clear();
        let (dir, c) = self.axis(g);
        let (r0, t0) = pose(&g[4..10]);
        let p = &self.pairs[view];
        let turn = Rotation3::from_axis_angle(&Unit::new_unchecked(dir), (p.table_deg - self.pairs[0].table_deg).to_radians());
        residuals(self.calib, |o| turn * (r0 * Vector3::new(o[0], o[1], o[2]) + t0 - c) + c, p, out);
    }
    fn global_step(&self, i: usize, value: f64) -> f64 {
        if i < 2 || (4..7).contains(&i) {
            1e-7
        } else {
            1e-6 * value.abs().max(1.0)
        }
    }
}

/// A first pose from the left image alone: its homography on undistorted, normalised points.
fn initial_pose(calib: &StereoCalib, view: &TargetView) -> Option<[f64; 6]> {
    let k = &calib.left.k;
    let norm = TargetView {
        object: view.object.clone(),
        image: view
            .image
            .iter()
            .map(|q| {
                let (x, y) = calib.left.distortion.undistort((q[0] - k[(0, 2)]) / k[(0, 0)], (q[1] - k[(1, 2)]) / k[(1, 1)], 20);
                [x, y]
            })
            .collect(),
    };
    pose_from_homography(&homography(&norm)?, &Matrix3::identity())
}

/// Fits the turntable axis to the pairs (the board found in both images of each).
pub fn fit_axis(calib: &StereoCalib, pairs: &[TablePair]) -> Result<AxisFit, AxisError> {
    if pairs.len() < 3 {
        return Err(AxisError::TooFewPairs { found: pairs.len() });
    }
    let (lo, hi) = pairs.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| (lo.min(p.table_deg), hi.max(p.table_deg)));
    if hi - lo < 20.0 {
        return Err(AxisError::NarrowSweep { span: hi - lo });
    }
    // 1. Each pair's pose.
    let starts: Vec<Vec<f64>> = pairs.iter().map(|p| initial_pose(calib, &p.left).map(|v| v.to_vec()).ok_or(AxisError::Degenerate("a board's corners give no pose"))).collect::<Result<_, _>>()?;
    let poses = lm::solve(&PairPose { calib, pairs }, Vec::new(), starts, 50).blocks;
    let poses: Vec<(Rotation3<f64>, Vector3<f64>)> = poses.iter().map(|b| pose(b)).collect();
    // 2. The axis's start from the relative rotations.
    let (r0, t0) = poses[0];
    let mut dir = Vector3::zeros();
    for (k, (r, _)) in poses.iter().enumerate().skip(1) {
        let rel = r * r0.inverse();
        let sa = rel.scaled_axis();
        let turn = pairs[k].table_deg - pairs[0].table_deg;
        if sa.norm() > 1e-9 && turn.abs() > 1e-9 {
            dir += sa * turn.signum();
        }
    }
    if dir.norm() < 1e-12 {
        return Err(AxisError::Degenerate("no pose turned from the first"));
    }
    let dir0 = dir.normalize();
    // (I − R_k) c = t_k − R_k t_0, with c's component along the axis pinned to the board's.
    let centre0 = {
        let n = pairs[0].left.object.len() as f64;
        let m = pairs[0].left.object.iter().fold(Vector3::zeros(), |a, o| a + Vector3::new(o[0], o[1], o[2])) / n;
        r0 * m + t0
    };
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for (r, t) in poses.iter().skip(1) {
        let rel = r * r0.inverse();
        let a = Matrix3::identity() - rel.matrix();
        let b = t - rel * t0;
        ata += a.transpose() * a;
        atb += a.transpose() * b;
    }
    ata += dir0 * dir0.transpose();
    atb += dir0 * dir0.dot(&centre0);
    let point0 = ata.try_inverse().map(|inv| inv * atb).ok_or(AxisError::Degenerate("no point on the axis fits the turns"))?;
    // 3. The joint fit.
    let e1 = dir0.cross(&if dir0.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() }).normalize();
    let e2 = dir0.cross(&e1);
    let problem = Axis { calib, pairs, dir0, point0, e1, e2 };
    let rv = r0.scaled_axis();
    let g = vec![0.0, 0.0, 0.0, 0.0, rv.x, rv.y, rv.z, t0.x, t0.y, t0.z];
    let sol = lm::solve(&problem, g, vec![Vec::new(); pairs.len()], 200);
    let (dir, c) = problem.axis(&sol.global);
    // The reported point: the foot of the board centre's perpendicular on the axis.
    let (rb, tb) = pose(&sol.global[4..10]);
    let n = pairs[0].left.object.len() as f64;
    let centre = rb * (pairs[0].left.object.iter().fold(Vector3::zeros(), |a, o| a + Vector3::new(o[0], o[1], o[2])) / n) + tb;
    let point = c + dir * dir.dot(&(centre - c));
    let mut all = Vec::new();
    let mut per = Vec::new();
    let mut r = Vec::new();
    for (k, (rk, _)) in poses.iter().enumerate() {
        problem.residuals(&sol.global, &[], k, &mut r);
        let pts = r.len() / 2;
        let rms = (r.iter().map(|x| x * x).sum::<f64>() / pts as f64).sqrt();
        all.extend_from_slice(&r);
        // The angle this pair's own pose turned from the first, about the fitted axis.
        let rel = rk * r0.inverse();
        let seen = rel.scaled_axis().dot(&dir).to_degrees();
        per.push((rms, seen - (pairs[k].table_deg - pairs[0].table_deg)));
    }
    let worst = per.iter().map(|p| p.1.abs()).fold(0.0, f64::max);
    if worst > 5.0 {
        return Err(AxisError::NotARotation { deg: worst });
    }
    let rms_px = (all.iter().map(|x| x * x).sum::<f64>() / (all.len() / 2) as f64).sqrt();
    Ok(AxisFit { point_mm: point, dir, rms_px, pairs: per })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::solve::board_points;
    use crate::calib::{Camera, Distortion};

    fn rig() -> StereoCalib {
        let k = Matrix3::new(700.0, 0.0, 319.5, 0.0, 700.0, 239.5, 0.0, 0.0, 1.0);
        let cam = Camera { k, distortion: Distortion::new(&[-0.1, 0.05, 0.0, 0.0, 0.0]).unwrap() };
        StereoCalib { left: cam.clone(), right: cam, r: Matrix3::identity(), t_mm: Vector3::new(-60.0, 0.0, 0.0), image_size: Some((640, 480)) }
    }

    /// Pairs of a 9 × 6 board turning about `dir` through `point` at `angles`; `moved` turns
    /// one pair's board by an extra 10° (the board slid on the table).
    fn pairs(calib: &StereoCalib, point: Vector3<f64>, dir: Vector3<f64>, angles: &[f64], moved: Option<usize>) -> Vec<TablePair> {
        let obj = board_points(9, 6, 20.0);
        let (r0, t0) = (Rotation3::from_axis_angle(&Vector3::x_axis(), 0.2), Vector3::new(-80.0, -40.0, 470.0));
        angles
            .iter()
            .enumerate()
            .map(|(k, &deg)| {
                let extra = if moved == Some(k) { 10.0 } else { 0.0 };
                let turn = Rotation3::from_axis_angle(&Unit::new_normalize(dir), (deg + extra).to_radians());
                let view = |right: bool| TargetView {
                    object: obj.clone(),
                    image: obj
                        .iter()
                        .map(|o| {
                            let x = turn * (r0 * Vector3::new(o[0], o[1], o[2]) + t0 - point) + point;
                            let (cam, x) = if right { (&calib.right, calib.r * x + calib.t_mm) } else { (&calib.left, x) };
                            project(&cam.k, &cam.distortion, &x)
                        })
                        .collect(),
                };
                TablePair { table_deg: deg, left: view(false), right: view(true) }
            })
            .collect()
    }

    #[test]
    fn the_axis_is_recovered_from_exact_corners() {
        let calib = rig();
        let (point, dir) = (Vector3::new(5.0, 60.0, 480.0), Vector3::new(0.02, -0.97, -0.22).normalize());
        let angles: Vec<f64> = (0..7).map(|k| -30.0 + 10.0 * k as f64).collect();
        let fit = fit_axis(&calib, &pairs(&calib, point, dir, &angles, None)).unwrap();
        assert!(fit.dir.dot(&dir) > (1e-4f64).to_radians().cos(), "{}", fit.dir);
        let off = (point - fit.point_mm) - fit.dir * fit.dir.dot(&(point - fit.point_mm));
        assert!(off.norm() < 1e-3 && fit.rms_px < 1e-4, "{off} {}", fit.rms_px);
    }

    #[test]
    fn a_narrow_sweep_and_a_board_that_slid_are_refused() {
        let calib = rig();
        let (point, dir) = (Vector3::new(5.0, 60.0, 480.0), Vector3::new(0.0, -0.98, -0.2).normalize());
        let narrow = fit_axis(&calib, &pairs(&calib, point, dir, &[0.0, 5.0, 10.0], None)).unwrap_err();
        assert!(matches!(narrow, AxisError::NarrowSweep { .. }), "{narrow}");
        let angles: Vec<f64> = (0..7).map(|k| -30.0 + 10.0 * k as f64).collect();
        let slid = fit_axis(&calib, &pairs(&calib, point, dir, &angles, Some(3))).unwrap_err();
        assert!(matches!(slid, AxisError::NotARotation { .. }), "{slid}");
    }
}
