//! Iterative closest point: Besl–McKay point-to-point (the paper's method) and
//! point-to-plane (Chen–Medioni), with distance rejection, optional trimming and robust
//! kernels, convergence on relative change, and a degeneracy check.
//!
//! Each iteration pairs every (sub-sampled) source point, moved by the current estimate,
//! with its nearest target point within `max_distance` (exact, from a grid of cubic cells, or
//! the nearest near its line of sight, from a view's range grid: [`Target`]), and
//! with `trim < 1` only that fraction of the closest pairs is kept. Point-to-point solves
//! the weighted absolute-orientation problem in closed form (SVD of the cross-covariance);
//! point-to-plane solves the linearised 6×6 normal equations for a small rotation about the
//! moved source's centroid and a translation. The iteration stops when the update is tiny
//! (rotation below `min_step_rad`, translation below `min_step_rel` × the source's size;
//! 100× smaller for point-to-point, which creeps), or
//! when fitness and RMSE come back to within `rel_change` (relative) of one of the last
//! four iterations' (no change, or a cycle among a few pair sets), or after
//! `max_iterations`.
//!
//! **Degeneracy.** Point-to-plane's normal matrix, with rotations scaled by the source's RMS
//! radius so its entries share units, has an eigenvalue near zero for every motion the
//! surface does not constrain — rotation of a surface of revolution about its axis, sliding
//! along a cylinder or a plane. Directions whose eigenvalue is below `degeneracy_ratio` ×
//! the largest are reported in [`IcpResult::degenerate`] and *not moved*: the solve is
//! restricted to the well-constrained subspace, so the answer keeps the initial guess (the
//! turntable's step, when the caller has one) along them instead of drifting. For
//! point-to-point the same directions are measured from the target's normals at the end, and
//! the motion along them is taken back out of the result.

use nalgebra::{Isometry3, Matrix6, Point3, SymmetricEigen, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;

use super::normals::NormalParams;
pub use super::target::Target;
use super::{rigid_fit, RegisterError};

/// Which error ICP minimises.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IcpMethod {
    /// Sum of squared point distances (Besl & McKay 1992).
    PointToPoint,
    /// Sum of squared distances to the target's tangent planes (Chen & Medioni 1992).
    PointToPlane,
}

/// An ICP method name that is not one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("unknown ICP method `{0}`; expected point-to-plane or point-to-point")]
pub struct UnknownMethod(pub String);

impl std::str::FromStr for IcpMethod {
    type Err = UnknownMethod;
    fn from_str(s: &str) -> Result<Self, UnknownMethod> {
        match s {
            "point-to-point" => Ok(IcpMethod::PointToPoint),
            "point-to-plane" => Ok(IcpMethod::PointToPlane),
            other => Err(UnknownMethod(other.to_string())),
        }
    }
}

/// Weights of pairs by their residual `r` (units of the clouds).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kernel {
    /// Every kept pair weighs 1 (least squares).
    None,
    /// Huber: weight `min(1, k / |r|)`.
    Huber(f64),
    /// Tukey's biweight: `(1 − (r/k)²)²` inside `k`, 0 outside.
    Tukey(f64),
}

impl Kernel {
    #[inline]
    fn weight(self, r: f64) -> f64 {
        match self {
            Kernel::None => 1.0,
            Kernel::Huber(k) => {
                let a = r.abs();
                if a <= k {
                    1.0
                } else {
                    k / a
                }
            }
            Kernel::Tukey(k) => {
                let u = r / k;
                if u.abs() >= 1.0 {
                    0.0
                } else {
                    (1.0 - u * u).powi(2)
                }
            }
        }
    }
}

/// ICP settings. Distances are in the clouds' units.
#[derive(Debug, Clone)]
pub struct IcpParams {
    pub method: IcpMethod,
    /// Pairs farther apart than this are not correspondences.
    pub max_distance: f64,
    pub max_iterations: usize,
    /// Fraction of the closest pairs kept each iteration (1 = no trimming).
    pub trim: f64,
    pub kernel: Kernel,
    /// Converged when fitness and RMSE both change by less than this, relative.
    pub rel_change: f64,
    /// Converged when the update rotates less than this (radians) …
    pub min_step_rad: f64,
    /// … and translates less than this × the source's RMS radius.
    pub min_step_rel: f64,
    /// Use at most this many source points, evenly spread (0 = all).
    pub max_source_points: usize,
    /// Neighbourhood of the target's normals (point-to-plane, and the degeneracy check).
    pub normals: NormalParams,
    /// Directions whose eigenvalue is below this fraction of the largest are degenerate.
    pub degeneracy_ratio: f64,
    /// Directions below this fraction are probed with a finite move (see [`Degeneracy`]).
    pub degeneracy_probe_ratio: f64,
}

impl IcpParams {
    /// Defaults for a given correspondence distance: point-to-plane, 60 iterations, no
    /// trimming or kernel, normals from up to 30 neighbours within 4 × `max_distance`
    /// (Open3D's settings in `peer_icp.py`), all source points.
    pub fn new(max_distance: f64) -> IcpParams {
        IcpParams {
            method: IcpMethod::PointToPlane,
            max_distance,
            max_iterations: 60,
            trim: 1.0,
            kernel: Kernel::None,
            rel_change: 1e-6,
            min_step_rad: 2e-5,
            min_step_rel: 2e-5,
            max_source_points: 0,
            normals: NormalParams { radius: (4.0 * max_distance) as f32, max_nn: 30 },
            degeneracy_ratio: 2e-3,
            degeneracy_probe_ratio: 0.08,
        }
    }

    /// The cells' side for a [`Target::cells`] target: half the correspondence distance, so
    /// that a query near the surface is answered from its own cell's 3 × 3 × 3 block
    /// (measured on the bunny pairs: a third, a quarter or two thirds were slower).
    pub fn cell_size(&self) -> f32 {
        (self.max_distance / 2.0) as f32
    }

    /// Refuses settings ICP cannot run with, naming the bad one.
    pub fn check(&self) -> Result<(), RegisterError> {
        let bad = |s: String| Err(RegisterError::Param(s));
        if !(self.max_distance.is_finite() && self.max_distance > 0.0) {
            return bad(format!("max distance must be a positive number, got {}", self.max_distance));
        }
        if self.max_iterations == 0 {
            return bad("max iterations must be at least 1".into());
        }
        if !(self.trim > 0.0 && self.trim <= 1.0) {
            return bad(format!("trim fraction must be in (0, 1], got {}", self.trim));
        }
        if !(self.normals.radius > 0.0) || self.normals.max_nn < 3 {
            return bad("normal neighbourhood needs a positive radius and at least 3 neighbours".into());
        }
        Ok(())
    }
}

/// A motion the geometry does not constrain.
#[derive(Debug, Clone, PartialEq)]
pub struct Degeneracy {
    /// Rotation part of the unconstrained twist (unit axis × its share).
    pub rotation: [f64; 3],
    /// Translation part (unit direction × its share).
    pub translation: [f64; 3],
    /// Its eigenvalue over the largest.
    pub ratio: f64,
    /// When the free motion is a rotation: the line it turns about (point, unit direction),
    /// e.g. the symmetry axis of a surface of revolution.
    pub axis: Option<([f64; 3], [f64; 3])>,
}

impl std::fmt::Display for Degeneracy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = Vector3::from(self.rotation);
        let t = Vector3::from(self.translation);
        if r.norm() >= t.norm() {
            let a = r.normalize();
            write!(f, "rotation about ({:.3}, {:.3}, {:.3})", a.x, a.y, a.z)?;
        } else {
            let a = t.normalize();
            write!(f, "translation along ({:.3}, {:.3}, {:.3})", a.x, a.y, a.z)?;
        }
        write!(f, " is unconstrained (eigenvalue ratio {:.1e})", self.ratio)
    }
}

/// What ICP found.
#[derive(Debug, Clone)]
pub struct IcpResult {
    /// Maps source points onto the target.
    pub transform: Isometry3<f64>,
    /// Correspondences over source points used (Open3D's "fitness").
    pub fitness: f64,
    /// RMS distance of the correspondences (inlier RMSE).
    pub rmse: f64,
    pub iterations: usize,
    /// False when `max_iterations` ran out first.
    pub converged: bool,
    pub correspondences: usize,
    /// Motions the surfaces cannot fix; left at the initial guess.
    pub degenerate: Vec<Degeneracy>,
    /// Smallest over largest eigenvalue of the point-to-plane normal matrix at the result
    /// (rotations scaled by the source's RMS radius): 0 = some motion is free, larger = every
    /// motion is pinned down. Degenerate below `degeneracy_ratio`.
    pub conditioning: f64,
    /// The least constrained motion at the result.
    pub weakest: Option<Degeneracy>,
}

impl IcpResult {
    /// A person-readable warning when the result is degenerate.
    pub fn degeneracy_warning(&self) -> Option<String> {
        if self.degenerate.is_empty() {
            return None;
        }
        let parts: Vec<String> = self.degenerate.iter().map(|d| d.to_string()).collect();
        Some(format!("registration is degenerate: {}; kept the initial guess along it", parts.join("; ")))
    }
}

struct Pair {
    src: usize,
    tgt: usize,
    d2: f32,
}

fn v3(p: &[f32; 3]) -> Vector3<f64> {
    Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

/// How many past iterations a repeat of the pairs' fitness and RMSE is looked for in (1 would
/// be the plain "no change" test; on the bunny pairs 2000 source points fell into 2-cycles).
const CYCLE: usize = 4;

/// Registers `source` onto the target starting from `init`.
pub fn icp(source: &[[f32; 3]], target: &mut Target, init: &Isometry3<f64>, params: &IcpParams) -> Result<IcpResult, RegisterError> {
    params.check()?;
    super::check_points(source, "source")?;
    let idx = super::subsample_indices(source.len(), params.max_source_points);
    let mut src: Vec<[f32; 3]> = idx.iter().map(|&i| source[i]).collect();
    target.order_queries(&mut src, init);
    let centroid = src.iter().map(v3).sum::<Vector3<f64>>() / src.len() as f64;
    let scale = (src.iter().map(|p| (v3(p) - centroid).norm_squared()).sum::<f64>() / src.len() as f64).sqrt().max(1e-12);

    let mut t = *init;
    // The last few iterations' (fitness, RMSE): when the pairs come back to a set seen a few
    // steps ago, ICP is cycling and will not get any closer.
    let mut seen: std::collections::VecDeque<(f64, f64)> = std::collections::VecDeque::with_capacity(CYCLE + 1);
    let mut iterations = 0;
    let mut converged = false;
    let mut degenerate = Vec::new();
    let mut last_pairs;
    loop {
        let pairs = correspondences(&src, target, &t, params);
        let (fitness, rmse) = stats(&pairs, src.len());
        last_pairs = pairs;
        if converged || iterations >= params.max_iterations {
            break;
        }
        let same = |&(pf, pr): &(f64, f64)| (fitness - pf).abs() / pf.max(1e-12) < params.rel_change && (rmse - pr).abs() / pr.max(1e-300) < params.rel_change;
        if seen.iter().any(same) {
            converged = true;
            break;
        }
        if seen.len() == CYCLE {
            seen.pop_front();
        }
        seen.push_back((fitness, rmse));
        if last_pairs.len() < 6 {
            break;
        }
        iterations += 1;
        let step = match params.method {
            IcpMethod::PointToPoint => point_to_point_step(&src, target, &t, &last_pairs, params),
            IcpMethod::PointToPlane => {
                target.ensure_normals(last_pairs.iter().map(|p| p.tgt));
                let (step, deg) = point_to_plane_step(&src, target, &t, &last_pairs, params, scale);
                degenerate = deg;
                step
            }
        };
        let Some(step) = step else { break };
        t = step * t;
        let rot = step.rotation.angle();
        let trans = step.translation.vector.norm();
        // Point-to-point creeps along smooth surfaces in steps far smaller than its remaining
        // error, so a small step says little there: its step test is 100× tighter.
        let tighten = if params.method == IcpMethod::PointToPoint { 0.01 } else { 1.0 };
        if rot < params.min_step_rad * tighten && trans < params.min_step_rel * tighten * scale {
            converged = true;
        }
    }
    let (mut conditioning, mut weakest) = (0.0, None);
    if last_pairs.len() >= 6 {
        // Measure what the surfaces constrain, and take back any motion along what they don't.
        let found = constraints(&src, target, &t, &last_pairs, params, scale);
        conditioning = found.conditioning;
        weakest = found.weakest.map(|(v, ratio)| as_degeneracy(&v, ratio, &found.centroid, scale));
        if !found.free.is_empty() {
            degenerate = found.free.iter().map(|(v, ratio)| as_degeneracy(v, *ratio, &found.centroid, scale)).collect();
            t = remove_motion_along(&t, init, &found.free, &found.centroid, scale);
            last_pairs = correspondences(&src, target, &t, params);
        } else if params.method == IcpMethod::PointToPoint {
            degenerate.clear();
        }
    }
    let (fitness, rmse) = stats(&last_pairs, src.len());
    Ok(IcpResult { transform: t, fitness, rmse, iterations, converged, correspondences: last_pairs.len(), degenerate, conditioning, weakest })
}

fn correspondences(src: &[[f32; 3]], target: &Target, t: &Isometry3<f64>, params: &IcpParams) -> Vec<Pair> {
    let max2 = (params.max_distance * params.max_distance) as f32;
    // In single precision: the pairing only needs the moved point to a fraction of the
    // clouds' spacing, and f32 keeps four lanes of the transform in a register.
    let m = t.to_homogeneous().cast::<f32>();
    let mut pairs: Vec<Pair> = src
        .par_iter()
        .enumerate()
        .with_min_len(1024)
        .filter_map(|(i, p)| {
            let q = [
                m[(0, 0)] * p[0] + m[(0, 1)] * p[1] + m[(0, 2)] * p[2] + m[(0, 3)],
                m[(1, 0)] * p[0] + m[(1, 1)] * p[1] + m[(1, 2)] * p[2] + m[(1, 3)],
                m[(2, 0)] * p[0] + m[(2, 1)] * p[1] + m[(2, 2)] * p[2] + m[(2, 3)],
            ];
            let (j, d2) = target.nearest_within(&q, max2)?;
            Some(Pair { src: i, tgt: j, d2 })
        })
        .collect();
    if params.trim < 1.0 && pairs.len() > 8 {
        let keep = ((pairs.len() as f64 * params.trim).ceil() as usize).clamp(6, pairs.len());
        pairs.select_nth_unstable_by(keep - 1, |a, b| a.d2.total_cmp(&b.d2));
        pairs.truncate(keep);
    }
    pairs
}

fn stats(pairs: &[Pair], n: usize) -> (f64, f64) {
    if pairs.is_empty() {
        return (0.0, 0.0);
    }
    let mse = pairs.iter().map(|p| p.d2 as f64).sum::<f64>() / pairs.len() as f64;
    (pairs.len() as f64 / n.max(1) as f64, mse.sqrt())
}

fn point_to_point_step(src: &[[f32; 3]], target: &Target, t: &Isometry3<f64>, pairs: &[Pair], params: &IcpParams) -> Option<Isometry3<f64>> {
    let moved: Vec<(Vector3<f64>, Vector3<f64>, f64)> = pairs
        .iter()
        .map(|p| {
            let a = (t * Point3::from(v3(&src[p.src]))).coords;
            let b = v3(&target.points()[p.tgt]);
            (a, b, params.kernel.weight((p.d2 as f64).sqrt()))
        })
        .collect();
    rigid_fit(&moved)
}

/// The point-to-plane normal equations `H x = b` in the twist `x = (ω·s, v)` about the
/// moved source centroid `c` (s = the source's RMS radius). Returns (H, b, c).
fn plane_system(src: &[[f32; 3]], target: &Target, t: &Isometry3<f64>, pairs: &[Pair], params: &IcpParams, scale: f64) -> (Matrix6<f64>, Vector6<f64>, Vector3<f64>) {
    let moved: Vec<Vector3<f64>> = pairs.iter().map(|p| (t * Point3::from(v3(&src[p.src]))).coords).collect();
    let c = moved.iter().sum::<Vector3<f64>>() / moved.len().max(1) as f64;
    let (h, b) = pairs
        .par_iter()
        .zip(moved.par_iter())
        .with_min_len(512)
        .fold(
            || (Matrix6::zeros(), Vector6::zeros()),
            |(mut h, mut b), (p, a)| {
                if let Some(n) = target.normal(p.tgt) {
                    let n = v3(&n);
                    let q = v3(&target.points()[p.tgt]);
                    let r = n.dot(&(a - q));
                    let w = params.kernel.weight(r);
                    let rc = (a - c).cross(&n) / scale;
                    let j = Vector6::new(rc.x, rc.y, rc.z, n.x, n.y, n.z);
                    h += j * j.transpose() * w;
                    b -= j * (r * w);
                }
                (h, b)
            },
        )
        .reduce(|| (Matrix6::zeros(), Vector6::zeros()), |x, y| (x.0 + y.0, x.1 + y.1));
    (h, b, c)
}

/// RMS point-to-plane residual of `pairs` under `t`.
fn plane_rms(src: &[[f32; 3]], target: &Target, t: &Isometry3<f64>, pairs: &[Pair]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for p in pairs {
        if let Some(nrm) = target.normal(p.tgt) {
            let a = (t * Point3::from(v3(&src[p.src]))).coords;
            sum += v3(&nrm).dot(&(a - v3(&target.points()[p.tgt]))).powi(2);
            n += 1;
        }
    }
    if n == 0 {
        0.0
    } else {
        (sum / n as f64).sqrt()
    }
}

/// What the surfaces constrain at a result.
struct Constraints {
    /// Free twists with their eigenvalue ratios.
    free: Vec<(Vector6<f64>, f64)>,
    /// Smallest over largest eigenvalue, and its twist.
    conditioning: f64,
    weakest: Option<(Vector6<f64>, f64)>,
    /// The moved source's centroid the twists turn about.
    centroid: Vector3<f64>,
}

/// The motions the surfaces leave free at `t`: eigen-directions of the point-to-plane normal
/// matrix below `degeneracy_ratio`, and — because sensor noise in the normals lifts the
/// eigenvalue of a truly free motion to a few percent — those below `degeneracy_probe_ratio`
/// along which a finite move of 10 × the residual (at the source's RMS radius, either way,
/// with fresh correspondences) leaves the residual below twice what it was.
fn constraints(src: &[[f32; 3]], target: &mut Target, t: &Isometry3<f64>, pairs: &[Pair], params: &IcpParams, scale: f64) -> Constraints {
    target.ensure_normals(pairs.iter().map(|p| p.tgt));
    let (h, _, c) = plane_system(src, target, t, pairs, params, scale);
    let eig = SymmetricEigen::new(h);
    let max = eig.eigenvalues.max();
    if !(max > 0.0) {
        return Constraints { free: Vec::new(), conditioning: 0.0, weakest: None, centroid: c };
    }
    let k = (0..6).min_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j])).unwrap_or(0);
    let conditioning = eig.eigenvalues[k].max(0.0) / max;
    let weakest = Some((eig.eigenvectors.column(k).into_owned(), conditioning));
    let base = plane_rms(src, target, t, pairs).max(1e-9 * scale);
    let fitness = pairs.len();
    let mut free = Vec::new();
    for k in 0..6 {
        let ratio = eig.eigenvalues[k].max(0.0) / max;
        let v: Vector6<f64> = eig.eigenvectors.column(k).into_owned();
        if ratio < params.degeneracy_ratio {
            free.push((v, ratio));
            continue;
        }
        if ratio >= params.degeneracy_probe_ratio {
            continue;
        }
        let moved_rms = [1.0, -1.0]
            .iter()
            .map(|sign| {
                let tt = twist_to_step(&(v * (10.0 * base * sign)), &c, scale) * t;
                let pp = correspondences(src, target, &tt, params);
                if (pp.len() as f64) < 0.9 * fitness as f64 {
                    return f64::INFINITY;
                }
                target.ensure_normals(pp.iter().map(|p| p.tgt));
                plane_rms(src, target, &tt, &pp)
            })
            .fold(f64::INFINITY, f64::min);
        if moved_rms < 2.0 * base {
            free.push((v, ratio));
        }
    }
    Constraints { free, conditioning, weakest, centroid: c }
}

/// A twist `v = (ω·s, t)` about `c` as a [`Degeneracy`], with its screw axis when it has a
/// real rotation part: the line through `c + ω × t / |ω|²` along ω.
fn as_degeneracy(v: &Vector6<f64>, ratio: f64, c: &Vector3<f64>, scale: f64) -> Degeneracy {
    let (rot, trans) = (Vector3::new(v[0], v[1], v[2]), Vector3::new(v[3], v[4], v[5]));
    // A rotation about a line away from the centroid carries a translation too (of about
    // the same size when the line is a radius away): any real rotation part has an axis.
    let axis = (rot.norm() >= 0.2 * (rot.norm_squared() + trans.norm_squared()).sqrt()).then(|| {
        let w = rot / scale;
        let point = c + w.cross(&trans) / w.norm_squared();
        (point.into(), w.normalize().into())
    });
    Degeneracy { rotation: rot.into(), translation: trans.into(), ratio, axis }
}

/// The update for a twist `x = (ω·s, v)` about `c`: p ↦ R(ω)(p − c) + c + v.
fn twist_to_step(x: &Vector6<f64>, c: &Vector3<f64>, scale: f64) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_scaled_axis(Vector3::new(x[0], x[1], x[2]) / scale);
    let v = Vector3::new(x[3], x[4], x[5]);
    Isometry3::from_parts(Translation3::from(c - rot * c + v), rot)
}

fn step_to_twist(step: &Isometry3<f64>, c: &Vector3<f64>, scale: f64) -> Vector6<f64> {
    let w = step.rotation.scaled_axis();
    // step(p) = R p + t = R (p − c) + c + v  ⇒  v = t − c + R c
    let v = step.translation.vector - c + step.rotation * c;
    Vector6::new(w.x * scale, w.y * scale, w.z * scale, v.x, v.y, v.z)
}

fn point_to_plane_step(src: &[[f32; 3]], target: &Target, t: &Isometry3<f64>, pairs: &[Pair], params: &IcpParams, scale: f64) -> (Option<Isometry3<f64>>, Vec<Degeneracy>) {
    let (h, b, c) = plane_system(src, target, t, pairs, params, scale);
    let eig = SymmetricEigen::new(h);
    let max = eig.eigenvalues.max();
    if !(max > 0.0) {
        return (None, Vec::new());
    }
    let mut x = Vector6::zeros();
    let mut degenerate = Vec::new();
    let mut dirs = Vec::new();
    for k in 0..6 {
        let v = eig.eigenvectors.column(k).into_owned();
        let l = eig.eigenvalues[k];
        if l < params.degeneracy_ratio * max {
            degenerate.push(as_degeneracy(&v, l.max(0.0) / max, &c, scale));
            dirs.push(v);
        } else {
            x += v * (v.dot(&b) / l);
        }
    }
    let x = least_rotation(&x, &dirs);
    (Some(twist_to_step(&x, &c, scale)), degenerate)
}

/// Among `x + Σ αᵢ dᵢ` (the data cannot tell these apart), the one that rotates least: an
/// unconstrained spin stays where the initial guess put it, and only the translation that
/// the surfaces pin down moves.
fn least_rotation(x: &Vector6<f64>, dirs: &[Vector6<f64>]) -> Vector6<f64> {
    if dirs.is_empty() {
        return *x;
    }
    let d = nalgebra::DMatrix::from_fn(3, dirs.len(), |r, c| dirs[c][r]);
    let rhs = nalgebra::DVector::from_vec(vec![-x[0], -x[1], -x[2]]);
    let Ok(alpha) = d.svd(true, true).solve(&rhs, 1e-6) else { return *x };
    let mut out = *x;
    for (k, v) in dirs.iter().enumerate() {
        out += v * alpha[k];
    }
    out
}

/// `t` with its motion relative to `init` along the degenerate twists removed.
fn remove_motion_along(t: &Isometry3<f64>, init: &Isometry3<f64>, dirs: &[(Vector6<f64>, f64)], c: &Vector3<f64>, scale: f64) -> Isometry3<f64> {
    let delta = t * init.inverse();
    let x = step_to_twist(&delta, c, scale);
    let dirs: Vec<Vector6<f64>> = dirs.iter().map(|(v, _)| *v).collect();
    twist_to_step(&least_rotation(&x, &dirs), c, scale) * init
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::register::rotation_about_axis;

    /// A bumpy, asymmetric height field 100 × 100 mm seen from 400 mm, `n`² points.
    fn bumpy(n: usize) -> Vec<[f32; 3]> {
        let mut pts = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (i as f64 / n as f64 * 100.0 - 50.0, j as f64 / n as f64 * 100.0 - 50.0);
                let z = 400.0 - 15.0 * (x / 20.0).sin() * (y / 25.0 + 0.4).cos() - 10.0 * (-(x - 10.0).powi(2) / 300.0 - (y + 15.0).powi(2) / 200.0).exp() + 0.1 * x;
                pts.push([x as f32, y as f32, z as f32]);
            }
        }
        pts
    }

    fn target_of(pts: &[[f32; 3]], params: &IcpParams) -> Target {
        Target::cells(pts.to_vec(), params.cell_size(), params.normals, "target").unwrap()
    }

    #[test]
    fn both_methods_recover_a_known_motion() {
        let tgt = bumpy(120);
        let truth = Isometry3::translation(1.5, -1.0, 0.5) * rotation_about_axis(&Vector3::new(20.0, 0.0, 380.0), &Vector3::new(0.1, 1.0, 0.2), 3.0);
        // source = truth⁻¹ · target, so target_from_source = truth.
        let src: Vec<[f32; 3]> = tgt.iter().map(|p| crate::register::apply(&truth.inverse(), p)).collect();
        for method in [IcpMethod::PointToPoint, IcpMethod::PointToPlane] {
            let mut params = IcpParams::new(10.0);
            params.method = method;
            let mut target = target_of(&tgt, &params);
            let r = icp(&src, &mut target, &Isometry3::identity(), &params).unwrap();
            let err = r.transform * truth.inverse();
            // Point-to-point pairs samples with samples, which biases it by a fraction of the
            // 0.8 mm spacing (and the frame origin is 400 mm from the patch, so that tilt moves
            // the translation); point-to-plane slides along the surface and lands on the truth.
            let (max_deg, max_mm) = if method == IcpMethod::PointToPoint { (0.15, 1.0) } else { (0.01, 0.05) };
            assert!(err.rotation.angle().to_degrees() < max_deg, "{method:?}: {:.4}°", err.rotation.angle().to_degrees());
            assert!(err.translation.vector.norm() < max_mm, "{method:?}: {}", err.translation.vector.norm());
            assert!(r.fitness > 0.97 && r.rmse < 0.5, "{method:?}: fitness {} rmse {}", r.fitness, r.rmse);
            assert!(r.converged && r.degenerate.is_empty(), "{method:?}: {r:?}");
        }
    }

    #[test]
    fn a_surface_of_revolution_is_flagged_and_keeps_the_guess() {
        // A cylinder of radius 50 about y, seen from the front; rotated 3° about its axis.
        let mut tgt = Vec::new();
        for i in 0..200 {
            for j in 0..100 {
                let a = (i as f64 / 200.0 - 0.5) * 2.4;
                tgt.push([(50.0 * a.sin()) as f32, j as f32, (400.0 - 50.0 * a.cos()) as f32]);
            }
        }
        let axis = Vector3::new(0.0, 1.0, 0.0);
        let centre = Vector3::new(0.0, 0.0, 400.0);
        let spin = rotation_about_axis(&centre, &axis, 3.0);
        let src: Vec<[f32; 3]> = tgt.iter().map(|p| crate::register::apply(&spin, p)).collect();
        // The turntable says the truth is a 3° turn back (target_from_source = spin⁻¹); start
        // from it plus a small translation error the geometry can fix.
        let guess = Isometry3::from_parts(Translation3::new(0.5, 0.0, 0.3), nalgebra::UnitQuaternion::identity()) * spin.inverse();
        for method in [IcpMethod::PointToPlane, IcpMethod::PointToPoint] {
            let mut params = IcpParams::new(5.0);
            params.method = method;
            let mut target = target_of(&tgt, &params);
            let r = icp(&src, &mut target, &guess, &params).unwrap();
            assert!(!r.degenerate.is_empty(), "{method:?}: no degeneracy reported");
            let w = r.degeneracy_warning().unwrap();
            assert!(w.contains("rotation about (") || w.contains("translation along ("), "{w}");
            // The spin about the axis stays where the guess put it.
            let residual = r.transform * spin;
            assert!(residual.rotation.angle().to_degrees() < 0.05, "{method:?}: {:.3}°", residual.rotation.angle().to_degrees());
        }
    }

    #[test]
    fn bad_parameters_and_far_clouds() {
        let tgt = bumpy(30);
        let mut params = IcpParams::new(-1.0);
        let mut target = target_of(&tgt, &IcpParams::new(1.0));
        assert!(icp(&tgt, &mut target, &Isometry3::identity(), &params).unwrap_err().to_string().contains("max distance"));
        params = IcpParams::new(1.0);
        // A source a metre away has no correspondences: fitness 0, no panic.
        let far: Vec<[f32; 3]> = tgt.iter().map(|p| [p[0] + 1000.0, p[1], p[2]]).collect();
        let r = icp(&far, &mut target, &Isometry3::identity(), &params).unwrap();
        assert_eq!(r.fitness, 0.0);
        assert!(!r.converged);
    }
}
