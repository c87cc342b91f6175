//! Camera and stereo calibration from views of a planar target: Zhang's closed form for a
//! start, then Levenberg–Marquardt on the reprojection error ([`super::lm`]), per camera and
//! then for the rig jointly, as OpenCV's `calibrateCamera` + `stereoCalibrate` with the
//! intrinsics refined (`CALIB_USE_INTRINSIC_GUESS`).
//!
//! Parameters of one camera, in this order: fx, fy, cx, cy, then the distortion
//! coefficients in OpenCV's order (5: k1 k2 p1 p2 k3; 8: … k4 k5 k6; 14: … s1–s4 τx τy).
//! A view's pose is a rotation vector and a translation (target → camera, the target's units).
//! RMS figures are OpenCV's: the root mean square of the corners' reprojection distances (one
//! camera), and over the corners of both cameras for the rig.

use nalgebra::{Matrix3, Rotation3, Vector3, SVD};

use super::lm::{self, BlockProblem};
use super::{Camera, Distortion, StereoCalib};

/// The lens model: how many distortion coefficients are solved for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LensModel {
    /// k1 k2 p1 p2 k3 (OpenCV's default).
    Five,
    /// Rational: k1 k2 p1 p2 k3 k4 k5 k6.
    Eight,
    /// Rational, thin prism and tilted sensor: all 14.
    Fourteen,
}

impl LensModel {
    pub fn coefficients(self) -> usize {
        match self {
            LensModel::Five => 5,
            LensModel::Eight => 8,
            LensModel::Fourteen => 14,
        }
    }

    /// 5, 8 or 14.
    pub fn from_count(n: u32) -> Option<LensModel> {
        match n {
            5 => Some(LensModel::Five),
            8 => Some(LensModel::Eight),
            14 => Some(LensModel::Fourteen),
            _ => None,
        }
    }
}

/// One view of the target: its points on the target plane (z = 0) and where they were seen.
#[derive(Debug, Clone)]
pub struct TargetView {
    pub object: Vec<[f64; 3]>,
    pub image: Vec<[f64; 2]>,
}

/// A camera solved from its views.
#[derive(Debug, Clone)]
pub struct CameraSolution {
    pub camera: Camera,
    /// Per view: rotation vector and translation, target → camera.
    pub poses: Vec<([f64; 3], [f64; 3])>,
    pub rms: f64,
    /// Per view: RMS reprojection distance, pixels.
    pub view_rms: Vec<f64>,
}

/// A rig solved from pairs of views.
#[derive(Debug, Clone)]
pub struct StereoSolution {
    pub calib: StereoCalib,
    pub rms_left: f64,
    pub rms_right: f64,
    pub rms_stereo: f64,
    /// Per pair: (left, right) RMS reprojection distance at the joint solution, pixels.
    pub pair_rms: Vec<(f64, f64)>,
    /// Per pair: the left camera's pose of the target.
    pub poses: Vec<([f64; 3], [f64; 3])>,
}

/// Why a calibration could not be solved.
#[derive(Debug, thiserror::Error)]
pub enum SolveError {
    #[error("{found} usable views; a calibration needs at least {needed}")]
    TooFewViews { found: usize, needed: usize },
    #[error("the views do not determine the focal length (the boards all face the camera square-on, or the corners are degenerate): tilt the board between views")]
    Degenerate,
}

/// The fewest views a calibration is attempted from.
pub const MIN_VIEWS: usize = 4;

/// Projects target point `p` with camera parameters `cam` (fx fy cx cy d…), its distortion
/// already built, and a pose.
fn project(cam: &[f64], dist: &Distortion, rot: &Rotation3<f64>, t: &Vector3<f64>, p: &[f64; 3]) -> [f64; 2] {
    let x = rot * Vector3::new(p[0], p[1], p[2]) + t;
    let (xn, yn) = (x.x / x.z, x.y / x.z);
    let (xd, yd) = dist.distort(xn, yn);
    [cam[0] * xd + cam[2], cam[1] * yd + cam[3]]
}

fn distortion_of(cam: &[f64]) -> Distortion {
    Distortion::new(&cam[4..]).expect("the solver keeps 5, 8 or 14 coefficients")
}

fn pose_of(b: &[f64]) -> (Rotation3<f64>, Vector3<f64>) {
    (Rotation3::new(Vector3::new(b[0], b[1], b[2])), Vector3::new(b[3], b[4], b[5]))
}

fn residuals_into(cam: &[f64], dist: &Distortion, rot: &Rotation3<f64>, t: &Vector3<f64>, view: &TargetView, out: &mut Vec<f64>) {
    for (p, q) in view.object.iter().zip(&view.image) {
        let uv = project(cam, dist, rot, t, p);
        out.push(uv[0] - q[0]);
        out.push(uv[1] - q[1]);
    }
}

fn rms_of(res: &[f64]) -> f64 {
    let pts = res.len() / 2;
    if pts == 0 {
        return 0.0;
    }
    (res.iter().map(|r| r * r).sum::<f64>() / pts as f64).sqrt()
}

/// The homography taking target (x, y) to pixels, by the normalised DLT.
pub fn homography(view: &TargetView) -> Option<Matrix3<f64>> {
    let n = view.object.len();
    if n < 4 {
        return None;
    }
    let norm = |pts: &mut dyn Iterator<Item = (f64, f64)>| -> Matrix3<f64> {
        let v: Vec<(f64, f64)> = pts.collect();
        let (mx, my) = (v.iter().map(|p| p.0).sum::<f64>() / n as f64, v.iter().map(|p| p.1).sum::<f64>() / n as f64);
        let d = v.iter().map(|p| ((p.0 - mx).powi(2) + (p.1 - my).powi(2)).sqrt()).sum::<f64>() / n as f64;
        let s = if d > 0.0 { std::f64::consts::SQRT_2 / d } else { 1.0 };
        Matrix3::new(s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0)
    };
    let ta = norm(&mut view.object.iter().map(|p| (p[0], p[1])));
    let tb = norm(&mut view.image.iter().map(|p| (p[0], p[1])));
    let mut a = nalgebra::DMatrix::<f64>::zeros(2 * n, 9);
    for (k, (p, q)) in view.object.iter().zip(&view.image).enumerate() {
        let x = ta * Vector3::new(p[0], p[1], 1.0);
        let u = tb * Vector3::new(q[0], q[1], 1.0);
        let (x, y) = (x.x / x.z, x.y / x.z);
        let (u, v) = (u.x / u.z, u.y / u.z);
        let r0 = [-x, -y, -1.0, 0.0, 0.0, 0.0, u * x, u * y, u];
        let r1 = [0.0, 0.0, 0.0, -x, -y, -1.0, v * x, v * y, v];
        for c in 0..9 {
            a[(2 * k, c)] = r0[c];
            a[(2 * k + 1, c)] = r1[c];
        }
    }
    // The right singular vector of the smallest singular value (AᵀA's smallest eigenvector).
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (imin, _) = eig.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eig.eigenvectors.column(imin);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let hm = tb.try_inverse()? * hn * ta;
    let s = hm[(2, 2)];
    (s.abs() > 1e-12).then(|| hm / s)
}

/// Zhang's closed form with the principal point at the image centre (as OpenCV's
/// `initIntrinsicParams2D`): fx, fy from the homographies' orthogonality constraints.
fn initial_focal(homographies: &[Matrix3<f64>], size: (u32, u32)) -> Option<(f64, f64)> {
    let (cx, cy) = ((size.0 as f64 - 1.0) / 2.0, (size.1 as f64 - 1.0) / 2.0);
    let shift = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let mut rows: Vec<([f64; 2], f64)> = Vec::new();
    for h in homographies {
        let h = shift * h;
        let (h1, h2) = (h.column(0).into_owned(), h.column(1).into_owned());
        // Unknowns a = 1/fx², b = 1/fy²; the third term (z·z) is known.
        let r1 = ([h1.x * h2.x, h1.y * h2.y], -h1.z * h2.z);
        let r2 = ([h1.x * h1.x - h2.x * h2.x, h1.y * h1.y - h2.y * h2.y], -(h1.z * h1.z - h2.z * h2.z));
        for (a, b) in [r1, r2] {
            let n = (a[0] * a[0] + a[1] * a[1]).sqrt();
            if n > 0.0 {
                rows.push(([a[0] / n, a[1] / n], b / n));
            }
        }
    }
    let (mut s00, mut s01, mut s11, mut t0, mut t1) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (a, b) in &rows {
        s00 += a[0] * a[0];
        s01 += a[0] * a[1];
        s11 += a[1] * a[1];
        t0 += a[0] * b;
        t1 += a[1] * b;
    }
    let det = s00 * s11 - s01 * s01;
    if det.abs() > 1e-300 {
        let a = (s11 * t0 - s01 * t1) / det;
        let b = (s00 * t1 - s01 * t0) / det;
        if a > 0.0 && b > 0.0 {
            return Some((1.0 / a.sqrt(), 1.0 / b.sqrt()));
        }
    }
    // One focal length for both axes (a = b).
    let (s, t): (f64, f64) = rows.iter().fold((0.0, 0.0), |(s, t), (a, b)| (s + (a[0] + a[1]).powi(2), t + (a[0] + a[1]) * b));
    let a = t / s;
    (a > 0.0 && a.is_finite()).then(|| (1.0 / a.sqrt(), 1.0 / a.sqrt()))
}

/// A view's pose from its homography and the camera matrix (distortion ignored).
pub(super) fn pose_from_homography(h: &Matrix3<f64>, k: &Matrix3<f64>) -> Option<[f64; 6]> {
    let kinv = k.try_inverse()?;
    let m = kinv * h;
    let lambda = 1.0 / m.column(0).norm();
    let sign = if (m.column(2) * lambda).z < 0.0 { -1.0 } else { 1.0 };
    let r1 = m.column(0) * lambda * sign;
    let r2 = m.column(1) * lambda * sign;
    let t = m.column(2) * lambda * sign;
    let r3 = r1.cross(&r2);
    let approx = Matrix3::from_columns(&[r1, r2, r3]);
    let svd = SVD::new(approx, true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut r = u * vt;
    if r.determinant() < 0.0 {
        r = -r;
    }
    let rv = Rotation3::from_matrix_unchecked(r).scaled_axis();
    Some([rv.x, rv.y, rv.z, t.x, t.y, t.z])
}

struct Mono<'a> {
    views: &'a [TargetView],
}

impl BlockProblem for Mono<'_> {
    fn residuals(&self, cam: &[f64], block: &[f64], view: usize, out: &mut Vec<f64>) {
        out.clear();
        let (rot, t) = pose_of(block);
        residuals_into(cam, &distortion_of(cam), &rot, &t, &self.views[view], out);
    }
}

/// Calibrates one camera from its views of the target (`size`: the image's pixels).
pub fn calibrate_camera(views: &[TargetView], size: (u32, u32), model: LensModel) -> Result<CameraSolution, SolveError> {
    if views.len() < MIN_VIEWS {
        return Err(SolveError::TooFewViews { found: views.len(), needed: MIN_VIEWS });
    }
    let hs: Vec<Matrix3<f64>> = views.iter().map(homography).collect::<Option<_>>().ok_or(SolveError::Degenerate)?;
    let (fx, fy) = initial_focal(&hs, size).ok_or(SolveError::Degenerate)?;
    let (cx, cy) = ((size.0 as f64 - 1.0) / 2.0, (size.1 as f64 - 1.0) / 2.0);
    let k = Matrix3::new(fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0);
    let poses: Vec<Vec<f64>> = hs.iter().map(|h| pose_from_homography(h, &k).map(|p| p.to_vec())).collect::<Option<_>>().ok_or(SolveError::Degenerate)?;
    let mut cam = vec![fx, fy, cx, cy];
    cam.extend(std::iter::repeat_n(0.0, model.coefficients()));
    let problem = Mono { views };
    // Poses first with the initial camera, then everything.
    let poses = lm::solve(&FixedGlobal(&problem), cam.clone(), poses, 30).blocks;
    let sol = lm::solve(&problem, cam, poses, 200);
    let cam = sol.global;
    if !(cam[0] > 0.0 && cam[1] > 0.0) || cam.iter().any(|v| !v.is_finite()) {
        return Err(SolveError::Degenerate);
    }
    let mut all = Vec::new();
    let mut view_rms = Vec::new();
    let mut r = Vec::new();
    for (v, b) in sol.blocks.iter().enumerate() {
        problem.residuals(&cam, b, v, &mut r);
        view_rms.push(rms_of(&r));
        all.extend_from_slice(&r);
    }
    Ok(CameraSolution {
        camera: camera_of(&cam),
        poses: sol.blocks.iter().map(|b| ([b[0], b[1], b[2]], [b[3], b[4], b[5]])).collect(),
        rms: rms_of(&all),
        view_rms,
    })
}

/// A problem with every global parameter held: only the poses move.
struct FixedGlobal<'a, P>(&'a P);

impl<P: BlockProblem> BlockProblem for FixedGlobal<'_, P> {
    fn residuals(&self, global: &[f64], block: &[f64], view: usize, out: &mut Vec<f64>) {
        self.0.residuals(global, block, view, out)
    }
    fn global_fixed(&self, _i: usize) -> bool {
        true
    }
}

fn camera_of(p: &[f64]) -> Camera {
    Camera { k: Matrix3::new(p[0], 0.0, p[2], 0.0, p[1], p[3], 0.0, 0.0, 1.0), distortion: distortion_of(p) }
}

fn params_of(c: &Camera) -> Vec<f64> {
    let mut p = vec![c.k[(0, 0)], c.k[(1, 1)], c.k[(0, 2)], c.k[(1, 2)]];
    p.extend_from_slice(c.distortion.coeffs());
    p
}

/// Both cameras and the rig: global = left camera, right camera, rig rotation vector, rig
/// translation; block = the left camera's pose of the target.
struct Rig<'a> {
    left: &'a [TargetView],
    right: &'a [TargetView],
    ncam: usize,
}

impl BlockProblem for Rig<'_> {
    fn residuals(&self, g: &[f64], block: &[f64], view: usize, out: &mut Vec<f64>) {
        out.clear();
        let (cl, cr) = (&g[..self.ncam], &g[self.ncam..2 * self.ncam]);
        let rig = &g[2 * self.ncam..];
        let (rot, t) = pose_of(block);
        residuals_into(cl, &distortion_of(cl), &rot, &t, &self.left[view], out);
        let (rr, tr) = pose_of(rig);
        residuals_into(cr, &distortion_of(cr), &(rr * rot), &(rr * t + tr), &self.right[view], out);
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// Calibrates a stereo rig from pairs of views of the same target (`left[i]` and `right[i]`
/// seen at once; same corner order): each camera alone, the rig's start as the median over
/// pairs, then all of it jointly. `X_right = R · X_left + T`, T in the target's units.
pub fn calibrate_stereo(left: &[TargetView], right: &[TargetView], size: (u32, u32), model: LensModel) -> Result<StereoSolution, SolveError> {
    assert_eq!(left.len(), right.len(), "views come in pairs");
    let l = calibrate_camera(left, size, model)?;
    let r = calibrate_camera(right, size, model)?;
    // The rig from each pair: R = R_r R_lᵀ, T = t_r − R t_l; the median of each component.
    let mut comps: [Vec<f64>; 6] = Default::default();
    for (pl, pr) in l.poses.iter().zip(&r.poses) {
        let (rl, tl) = pose_of(&[pl.0[0], pl.0[1], pl.0[2], pl.1[0], pl.1[1], pl.1[2]]);
        let (rr, tr) = pose_of(&[pr.0[0], pr.0[1], pr.0[2], pr.1[0], pr.1[1], pr.1[2]]);
        let rot = rr * rl.inverse();
        let t = tr - rot * tl;
        let rv = rot.scaled_axis();
        for (k, v) in [rv.x, rv.y, rv.z, t.x, t.y, t.z].into_iter().enumerate() {
            comps[k].push(v);
        }
    }
    let rig: Vec<f64> = comps.into_iter().map(median).collect();
    let mut g = params_of(&l.camera);
    let ncam = g.len();
    g.extend(params_of(&r.camera));
    g.extend(rig);
    let blocks: Vec<Vec<f64>> = l.poses.iter().map(|p| vec![p.0[0], p.0[1], p.0[2], p.1[0], p.1[1], p.1[2]]).collect();
    let problem = Rig { left, right, ncam };
    let sol = lm::solve(&problem, g, blocks, 200);
    let g = sol.global;
    if g.iter().any(|v| !v.is_finite()) || g[0] <= 0.0 || g[ncam] <= 0.0 {
        return Err(SolveError::Degenerate);
    }
    let mut all = Vec::new();
    let mut pair_rms = Vec::new();
    let mut res = Vec::new();
    for (v, b) in sol.blocks.iter().enumerate() {
        problem.residuals(&g, b, v, &mut res);
        let half = 2 * left[v].object.len();
        pair_rms.push((rms_of(&res[..half]), rms_of(&res[half..])));
        all.extend_from_slice(&res);
    }
    let (rr, tr) = pose_of(&g[2 * ncam..]);
    Ok(StereoSolution {
        calib: StereoCalib {
            left: camera_of(&g[..ncam]),
            right: camera_of(&g[ncam..2 * ncam]),
            r: *rr.matrix(),
            t_mm: tr,
            image_size: Some(size),
        },
        rms_left: l.rms,
        rms_right: r.rms,
        rms_stereo: rms_of(&all),
        pair_rms,
        poses: sol.blocks.iter().map(|b| ([b[0], b[1], b[2]], [b[3], b[4], b[5]])).collect(),
    })
}

/// The target's corner positions: `cols × rows` points `square` apart, row by row, z = 0.
pub fn board_points(cols: usize, rows: usize, square: f64) -> Vec<[f64; 3]> {
    (0..rows).flat_map(|r| (0..cols).map(move |c| [c as f64 * square, r as f64 * square, 0.0])).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Synthetic views of a 9 × 6 board through a known camera.
    fn synthetic(cam: &[f64], poses: &[[f64; 6]]) -> Vec<TargetView> {
        let obj = board_points(9, 6, 24.0);
        let d = distortion_of(cam);
        poses
            .iter()
            .map(|p| {
                let (rot, t) = pose_of(p);
                TargetView { object: obj.clone(), image: obj.iter().map(|o| project(cam, &d, &rot, &t, o)).collect() }
            })
            .collect()
    }

    fn poses() -> Vec<[f64; 6]> {
        (0..8)
            .map(|i| {
                let a = i as f64;
                [0.3 * (a * 0.9).sin(), 0.35 * (a * 1.3).cos(), 0.1 * a - 0.3, -100.0 + 10.0 * a, -60.0 + 5.0 * (a * 0.7).sin(), 500.0 + 30.0 * a]
            })
            .collect()
    }

    #[test]
    fn a_camera_is_recovered_from_exact_corners() {
        let cam = [520.0, 518.0, 315.0, 250.0, -0.25, 0.12, 0.001, -0.0005, -0.02];
        let views = synthetic(&cam, &poses());
        let sol = calibrate_camera(&views, (640, 512), LensModel::Five).unwrap();
        let got = params_of(&sol.camera);
        for (g, w) in got.iter().zip(&cam).take(4) {
            assert!((g - w).abs() < 1e-4, "{got:?}");
        }
        assert!(sol.rms < 1e-6, "{}", sol.rms);
    }

    #[test]
    fn a_rig_is_recovered_from_exact_corners() {
        let cl = [520.0, 518.0, 315.0, 250.0, -0.25, 0.12, 0.001, -0.0005, -0.02];
        let cr = [515.0, 516.0, 325.0, 262.0, -0.22, 0.10, -0.001, 0.0004, -0.01];
        let rig = [0.01, -0.05, 0.02, -92.0, 1.5, 3.0];
        let left_poses = poses();
        let (rr, tr) = pose_of(&rig);
        let right_poses: Vec<[f64; 6]> = left_poses
            .iter()
            .map(|p| {
                let (r, t) = pose_of(p);
                let rv = (rr * r).scaled_axis();
                let tt = rr * t + tr;
                [rv.x, rv.y, rv.z, tt.x, tt.y, tt.z]
            })
            .collect();
        let sol = calibrate_stereo(&synthetic(&cl, &left_poses), &synthetic(&cr, &right_poses), (640, 512), LensModel::Five).unwrap();
        assert!((sol.calib.t_mm - Vector3::new(rig[3], rig[4], rig[5])).norm() < 1e-3, "{}", sol.calib.t_mm);
        assert!(sol.rms_stereo < 1e-6);
    }
}
