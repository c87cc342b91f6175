//! The turntable refinement at the end of a scan: one axis for every view at once.
//!
//! Chained registrations carry each pair's error into every later pose, and an axis fitted to
//! those poses inherits it; an object that hides part of its motion from ICP (a surface of
//! revolution standing on the table, a smooth blob) can leave the chain, and the axis fitted to
//! it, far off while every step looks right. On a turntable the poses are not free: view k is
//! the first view turned by −(θ_k − θ_first) about one line, θ the recorded table angles. This
//! module fits that line — four numbers, its direction and its position across itself — to
//! every view's points at once: point-to-plane distances between each view and the next one,
//! and between each view and the one about [`RefineParams::pair_deg`] further round, each
//! placed by the turn between them about the current line. Gauss–Newton with Levenberg
//! damping and Huber weights; correspondences are renewed every round with a reach that
//! shrinks from `reach_mm.0` to `reach_mm.1`.
//!
//! A surface of revolution about the table's own axis fixes the line too: every turn about
//! the right line fits, while a tilted line tilts the object between views.
//!
//! The uncertainty: a delete-one-pair jackknife of the solution — how far it moves when one
//! pair of views is left out (the correspondences of one pair share that pair's errors, so
//! they are not independent observations; the pairs nearly are). One standard deviation of
//! the direction's tilt and of the position across the axis.

use nalgebra::{Isometry3, Matrix2, Matrix4, SymmetricEigen, Vector3, Vector4};
use rayon::prelude::*;

use super::normals::{normal_at, NormalParams};
use super::{rotation_about_axis, subsample_indices, KdTree, RegisterError};

/// One view for the refinement: its table angle and a subsample of its points, in its own
/// frame.
#[derive(Debug, Clone)]
pub struct RefineView {
    pub table_deg: f64,
    pub points: Vec<[f32; 3]>,
}

/// Settings of [`fit_axis`]; distances in the views' units (mm).
#[derive(Debug, Clone)]
pub struct RefineParams {
    /// Each view is also paired with the view about this many degrees further round (the
    /// registrar takes half the arc instead when the views span less than twice this).
    pub pair_deg: f64,
    /// Source points per pair of views.
    pub source_points: usize,
    /// Largest correspondence distance, first round and last round.
    pub reach_mm: (f64, f64),
    /// Gauss–Newton rounds (each with fresh correspondences).
    pub rounds: usize,
    /// Residuals beyond this get Huber weights.
    pub huber_mm: f64,
    pub normals: NormalParams,
}

impl Default for RefineParams {
    /// Pairs 60° apart and neighbours, 1000 points a pair, reach 8 → 2 mm over 15 rounds, Huber
    /// beyond 1 mm, normals from 20 neighbours within 10 mm.
    fn default() -> Self {
        RefineParams { pair_deg: 60.0, source_points: 1000, reach_mm: (8.0, 2.0), rounds: 15, huber_mm: 1.0, normals: NormalParams { radius: 10.0, max_nn: 20 } }
    }
}

/// A fitted axis and how well it is known.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisFit {
    /// A point on the axis (the one nearest the initial point) and its unit direction, the
    /// one the table's angles turn the views about (right-handed): its sign is the turn's
    /// sense, fitted like the rest, not taken from the start.
    pub point: Vector3<f64>,
    pub dir: Vector3<f64>,
    /// One standard deviation of the direction (the larger of its two tilts), degrees, and
    /// of the position across the axis, mm.
    pub sigma_dir_deg: f64,
    pub sigma_point_mm: f64,
    /// RMS point-to-plane distance of the last round's correspondences, mm (NaN for an axis
    /// fitted to texture tracks).
    pub rms_mm: f64,
    /// Pairs of views and correspondences of the last round (0 for an axis fitted to
    /// texture tracks).
    pub pairs: usize,
    pub correspondences: usize,
    /// Set when the axis was fitted to texture tracks (`register::bundle`) instead.
    pub tracks: Option<TrackFigures>,
}

/// How an axis fitted to texture tracks was found.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackFigures {
    /// Tracks used and their observations.
    pub tracks: usize,
    pub observations: usize,
    /// RMS of the tracked places' residuals (x and y), pixels.
    pub rms_px: f64,
    /// The largest, over the views, of the median distance between where a view's tracked
    /// places are and where the table's angle about the axis puts them (tracks that started
    /// in an earlier view), pixels: a view where the object moved on the table stands out.
    pub worst_view_px: f64,
    /// Views after the first that fewer than ten such places fall in (their turn is not
    /// confirmed by the texture).
    pub views_unconfirmed: usize,
}

/// `|x|` of an angle difference taken into (−180°, 180°].
fn wrapped(deg: f64) -> f64 {
    ((deg + 180.0).rem_euclid(360.0) - 180.0).abs()
}

/// The pairs of views compared: each view with the next, and with the view nearest
/// `pair_deg` further round (within a third of it), each pair once.
pub fn view_pairs(angles: &[f64], pair_deg: f64) -> Vec<(usize, usize)> {
    let n = angles.len();
    let mut pairs: Vec<(usize, usize)> = (1..n).map(|i| (i - 1, i)).collect();
    for i in 0..n {
        let best = (0..n).filter(|&j| j != i).min_by(|&a, &b| wrapped(angles[a] - angles[i] - pair_deg).total_cmp(&wrapped(angles[b] - angles[i] - pair_deg)));
        if let Some(j) = best.filter(|&j| wrapped(angles[j] - angles[i] - pair_deg) <= pair_deg / 3.0) {
            let p = (i.min(j), i.max(j));
            if !pairs.contains(&p) {
                pairs.push(p);
            }
        }
    }
    pairs
}

/// A view's k-d tree and the normal of each of its points (None: too few neighbours).
struct Surface {
    tree: KdTree,
    normals: Vec<Option<[f32; 3]>>,
}

/// One correspondence: pair, source point (view i's frame), target point and normal (view
/// j's frame).
struct Corr {
    pair: usize,
    p: Vector3<f64>,
    q: Vector3<f64>,
    n: Vector3<f64>,
}

/// The axis as parameters around a base line: tilts `(x0, x1)` of the direction along two
/// unit vectors across it, shifts `(x2, x3)` of the point along them.
/// (Also the line of `register::bundle`.)
#[derive(Clone, Copy)]
pub(super) struct Line {
    pub(super) point: Vector3<f64>,
    pub(super) dir: Vector3<f64>,
    u: Vector3<f64>,
    v: Vector3<f64>,
}

impl Line {
    pub(super) fn new(point: Vector3<f64>, dir: Vector3<f64>) -> Line {
        let dir = dir.normalize();
        let seed = if dir.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        let u = dir.cross(&seed).normalize();
        let v = dir.cross(&u);
        Line { point, dir, u, v }
    }

    pub(super) fn moved(&self, x: &Vector4<f64>) -> (Vector3<f64>, Vector3<f64>) {
        ((self.point + self.u * x[2] + self.v * x[3]), (self.dir + self.u * x[0] + self.v * x[1]).normalize())
    }

    /// The line moved by `x` (see [`Line::moved`]).
    pub(super) fn moved_line(&self, x: &Vector4<f64>) -> Line {
        let (point, dir) = self.moved(x);
        Line::new(point, dir)
    }
}

/// The views prepared for the refinement: each one's k-d tree and normals, the pairs compared
/// and their source points. Built once, then used to fit axes ([`RefineSet::fit_axis`]) and to
/// score any set of poses ([`RefineSet::score`]).
pub struct RefineSet<'a> {
    views: &'a [RefineView],
    surfaces: Vec<Surface>,
    pairs: Vec<(usize, usize)>,
    sources: Vec<Vec<Vector3<f64>>>,
}

impl<'a> RefineSet<'a> {
    /// Needs at least three views; fails on a view whose points cannot make a k-d tree.
    pub fn new(views: &'a [RefineView], p: &RefineParams) -> Result<RefineSet<'a>, RegisterError> {
        if views.len() < 3 {
            return Err(RegisterError::TooFew { what: "views".into(), got: views.len(), need: 3, purpose: "the turntable refinement (fitting the axis to every view)".into() });
        }
        if !(p.pair_deg > 0.0 && p.rounds > 0 && p.source_points > 0 && p.reach_mm.0 > 0.0 && p.reach_mm.1 > 0.0 && p.huber_mm > 0.0) {
            return Err(RegisterError::Param(format!("turntable refinement: pair_deg {}, rounds {}, source_points {}, reach {:?}, huber {}: expected positive values", p.pair_deg, p.rounds, p.source_points, p.reach_mm, p.huber_mm)));
        }
        let surfaces: Vec<Surface> = views
            .par_iter()
            .enumerate()
            .map(|(k, v)| {
                let tree = KdTree::build(v.points.clone(), &format!("refinement view {k}"))?;
                let normals = tree.points.iter().map(|q| normal_at(&tree, q, p.normals).map(|(n, _)| n)).collect();
                Ok(Surface { tree, normals })
            })
            .collect::<Result<_, RegisterError>>()?;
        let angles: Vec<f64> = views.iter().map(|v| v.table_deg).collect();
        let pairs = view_pairs(&angles, p.pair_deg);
        let sources = pairs.iter().map(|&(i, _)| subsample_indices(views[i].points.len(), p.source_points).into_iter().map(|k| v3(&views[i].points[k])).collect()).collect();
        Ok(RefineSet { views, surfaces, pairs, sources })
    }

    /// The correspondences of every pair within `reach`, with `view_j_from_view_i` given
    /// per pair.
    fn correspondences(&self, relative: &(dyn Fn(usize) -> Isometry3<f64> + Sync), reach: f64) -> Vec<Corr> {
        (0..self.pairs.len())
            .into_par_iter()
            .flat_map_iter(|k| {
                let m = relative(k);
                let target = &self.surfaces[self.pairs[k].1];
                self.sources[k]
                    .iter()
                    .filter_map(|s| {
                        let moved = m * nalgebra::Point3::from(*s);
                        let (idx, d2) = target.tree.nearest(&[moved.x as f32, moved.y as f32, moved.z as f32]);
                        let n = target.normals[idx]?;
                        ((d2 as f64) <= reach * reach).then(|| Corr { pair: k, p: *s, q: v3(&target.tree.points[idx]), n: v3(&n) })
                    })
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    /// How well poses (`first_from_view` of every view) put the views onto each other: the
    /// RMS over every pair's source points of the point-to-plane distance to the partner
    /// view, capped at the last round's reach (a point with no partner within it counts as
    /// the reach). Lower is better; the same measure for any poses.
    pub fn score(&self, poses: &[Isometry3<f64>], p: &RefineParams) -> f64 {
        let reach = p.reach_mm.1;
        let relative = |k: usize| {
            let (i, j) = self.pairs[k];
            poses[j].inverse() * poses[i]
        };
        let corr = self.correspondences(&relative, reach);
        let total: usize = self.sources.iter().map(Vec::len).sum();
        let matched: f64 = corr.iter().map(|c| c.n.dot(&((relative(c.pair) * nalgebra::Point3::from(c.p)).coords - c.q)).abs().min(reach).powi(2)).sum();
        ((matched + (total - corr.len()) as f64 * reach * reach) / total.max(1) as f64).sqrt()
    }

    /// Fits the turntable's axis to every view at once, from `init` = (point, direction);
    /// see the module docs.
    pub fn fit_axis(&self, init: (Vector3<f64>, Vector3<f64>), p: &RefineParams) -> Result<AxisFit, RegisterError> {
        if !(init.1.norm() > 0.0 && init.0.iter().chain(init.1.iter()).all(|v| v.is_finite())) {
            return Err(RegisterError::Param(format!("turntable refinement: initial axis point {:?}, direction {:?}: expected finite values and a non-zero direction", init.0, init.1)));
        }
        let (views, pairs) = (self.views, &self.pairs);
        // view_j_from_view_i: the turn θ_j − θ_i about the line.
        let relative = |line: (Vector3<f64>, Vector3<f64>), pair: usize| {
            let (i, j) = pairs[pair];
            rotation_about_axis(&line.0, &line.1, views[j].table_deg - views[i].table_deg)
        };
        let weight = |r: f64| if r.abs() <= p.huber_mm { 1.0 } else { p.huber_mm / r.abs() };
        let cost = |r: &[f64]| r.iter().map(|&r| if r.abs() <= p.huber_mm { 0.5 * r * r } else { p.huber_mm * (r.abs() - 0.5 * p.huber_mm) }).sum::<f64>();
        let mut line = Line::new(init.0, init.1);
        let mut lambda = 1e-3;
        // The last round's per-pair normal equations, for the jackknife.
        let (mut per_pair, mut rms, mut count) = (Vec::new(), f64::NAN, 0usize);
        for round in 0..p.rounds {
            let t = if p.rounds > 1 { round as f64 / (p.rounds - 1) as f64 } else { 1.0 };
            let reach = p.reach_mm.0 + (p.reach_mm.1 - p.reach_mm.0) * t;
            let base = (line.point, line.dir);
            let corr = self.correspondences(&|k| relative(base, k), reach);
            if corr.len() < 8 {
                return Err(RegisterError::TooFew { what: "correspondences".into(), got: corr.len(), need: 8, purpose: format!("the turntable refinement's fit of the axis (the views do not overlap within {reach:.1} mm about the axis tried)") });
            }
            let residuals = |x: &Vector4<f64>| -> Vec<f64> {
                let l = line.moved(x);
                let ms: Vec<Isometry3<f64>> = (0..pairs.len()).map(|k| relative(l, k)).collect();
                corr.iter().map(|c| c.n.dot(&((ms[c.pair] * nalgebra::Point3::from(c.p)).coords - c.q))).collect()
            };
            let r0 = residuals(&Vector4::zeros());
            // Central differences: radians for the tilts, mm for the shifts.
            let steps = [1e-6, 1e-6, 1e-4, 1e-4];
            let mut jac = vec![Vector4::zeros(); corr.len()];
            for (a, &st) in steps.iter().enumerate() {
                let mut e = Vector4::zeros();
                e[a] = st;
                let (plus, minus) = (residuals(&e), residuals(&(-e)));
                for (j, (rp, rm)) in jac.iter_mut().zip(plus.iter().zip(&minus)) {
                    j[a] = (rp - rm) / (2.0 * st);
                }
            }
            per_pair = vec![(Matrix4::zeros(), Vector4::zeros()); pairs.len()];
            for ((j, &r), c) in jac.iter().zip(&r0).zip(&corr) {
                let w = weight(r);
                let (h, g) = &mut per_pair[c.pair];
                *h += j * j.transpose() * w;
                *g += j * (r * w);
            }
            let hh: Matrix4<f64> = per_pair.iter().map(|(h, _)| h).sum();
            let g: Vector4<f64> = per_pair.iter().map(|(_, g)| g).sum();
            let c0 = cost(&r0);
            let mut moved = false;
            for _ in 0..8 {
                let damped = hh + Matrix4::from_diagonal(&hh.diagonal()) * lambda;
                let Some(dx) = damped.lu().solve(&(-g)) else { break };
                if cost(&residuals(&dx)) < c0 {
                    let (pt, dir) = line.moved(&dx);
                    line = Line::new(pt, dir);
                    lambda = (lambda / 3.0).max(1e-9);
                    moved = true;
                    break;
                }
                lambda *= 10.0;
            }
            count = corr.len();
            rms = (r0.iter().map(|&r| weight(r) * r * r).sum::<f64>() / count as f64).sqrt();
            if !moved && round + 1 >= p.rounds / 2 {
                break;
            }
        }
        // Delete-one-pair jackknife of the last round's step: how far the solution moves when
        // one pair of views is left out.
        let hh: Matrix4<f64> = per_pair.iter().map(|(h, _)| h).sum();
        let g: Vector4<f64> = per_pair.iter().map(|(_, g)| g).sum();
        let left_out: Vec<Vector4<f64>> = per_pair.iter().filter_map(|(h, gk)| (hh - h).lu().solve(&(-(g - gk)))).collect();
        let cov = if left_out.len() >= 2 {
            let k = left_out.len() as f64;
            let mean: Vector4<f64> = left_out.iter().sum::<Vector4<f64>>() / k;
            Some(left_out.iter().map(|d| (d - mean) * (d - mean).transpose()).sum::<Matrix4<f64>>() * ((k - 1.0) / k))
        } else {
            None
        };
        let spread = |block: Matrix2<f64>| SymmetricEigen::new(block).eigenvalues.iter().fold(0.0f64, |m, &e| m.max(e)).max(0.0).sqrt();
        let (sigma_dir_deg, sigma_point_mm) = match cov {
            Some(c) => (spread(c.fixed_view::<2, 2>(0, 0).into_owned()).to_degrees(), spread(c.fixed_view::<2, 2>(2, 2).into_owned())),
            None => (f64::INFINITY, f64::INFINITY),
        };
        // The point nearest the initial one. The direction as fitted: the views are turned by
        // the table's angles about it, so its sign is the turn's sense (the start's sign would
        // reverse the turn wherever the fit came more than a right angle round).
        let dir = line.dir;
        let point = line.point + dir * dir.dot(&(init.0 - line.point));
        Ok(AxisFit { point, dir, sigma_dir_deg, sigma_point_mm, rms_mm: rms, pairs: pairs.len(), correspondences: count, tracks: None })
    }
}

/// [`RefineSet::fit_axis`] on views prepared for the one fit.
pub fn fit_axis(views: &[RefineView], init: (Vector3<f64>, Vector3<f64>), p: &RefineParams) -> Result<AxisFit, RegisterError> {
    RefineSet::new(views, p)?.fit_axis(init, p)
}

fn v3(p: &[f32; 3]) -> Vector3<f64> {
    Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points of an ellipsoid (semi-axes 30, 45, 30 mm, the long one along `up`) standing on
    /// the axis, seen from a camera: the visible half of each view, in the view's frame.
    fn views(axis_point: Vector3<f64>, up: Vector3<f64>, angles: &[f64]) -> Vec<RefineView> {
        let up = up.normalize();
        let side = up.cross(&Vector3::z()).normalize();
        let front = side.cross(&up);
        let centre = axis_point + up * 10.0;
        let mut surface = Vec::new();
        for i in 0..60 {
            for j in 0..60 {
                let (th, ph) = (std::f64::consts::PI * (i as f64 + 0.5) / 60.0, 2.0 * std::f64::consts::PI * j as f64 / 60.0);
                // A bump breaks the symmetry about the long axis only slightly.
                let r = 1.0 + 0.02 * (3.0 * ph).sin() * th.sin();
                surface.push(centre + (side * (30.0 * th.sin() * ph.cos()) + front * (30.0 * th.sin() * ph.sin()) + up * (45.0 * th.cos())) * r);
            }
        }
        angles
            .iter()
            .map(|&a| {
                // view_from_first: the object turned by +a about the axis.
                let m = rotation_about_axis(&axis_point, &up, a);
                let points = surface.iter().map(|s| m * nalgebra::Point3::from(*s)).filter(|q| (q.coords - (m * nalgebra::Point3::from(centre)).coords).dot(&Vector3::z()) < 0.0).map(|q| [q.x as f32, q.y as f32, q.z as f32]).collect();
                RefineView { table_deg: a, points }
            })
            .collect()
    }

    #[test]
    fn pairs_are_neighbours_and_views_a_set_angle_apart() {
        let angles: Vec<f64> = (0..12).map(|k| 30.0 * k as f64).collect();
        let pairs = view_pairs(&angles, 60.0);
        assert!(pairs.contains(&(0, 1)) && pairs.contains(&(10, 11)));
        assert!(pairs.contains(&(0, 2)) && pairs.contains(&(9, 11)));
        // Round the turn: 330° + 60° is 30°.
        assert!(pairs.contains(&(1, 11)), "{pairs:?}");
        assert_eq!(pairs.len(), 11 + 12);
    }

    #[test]
    fn a_tilted_guess_converges_to_the_true_axis_with_a_small_uncertainty() {
        let (point, up) = (Vector3::new(0.0, 78.0, 466.0), Vector3::new(0.0, -0.978, -0.208).normalize());
        let angles: Vec<f64> = (0..40).map(|k| 3.0 * k as f64).collect();
        let views = views(point, up, &angles);
        // 8° off in direction and 6 mm off in position.
        let guess_dir = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::x() * 8f64.to_radians()) * up;
        let guess_point = point + Vector3::new(6.0, 0.0, 0.0);
        let fit = fit_axis(&views, (guess_point, guess_dir), &RefineParams::default()).unwrap();
        let err_deg = fit.dir.dot(&up).clamp(-1.0, 1.0).acos().to_degrees();
        let off = (fit.point - point) - up * up.dot(&(fit.point - point));
        assert!(err_deg < 0.05, "direction {err_deg}° off");
        assert!(off.norm() < 0.2, "point {} mm off", off.norm());
        assert!(fit.sigma_dir_deg < 0.05, "σ {}", fit.sigma_dir_deg);
        assert!(fit.rms_mm < 0.05, "rms {}", fit.rms_mm);
        // Started just over a right angle off, the fit comes round to the axis the views turn
        // about, and keeps the direction that turns them (not the start's side of it).
        let across = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::x() * 91f64.to_radians()) * up;
        let far = fit_axis(&views, (guess_point, across), &RefineParams::default()).unwrap();
        assert!(far.dir.angle(&up).to_degrees() < 0.05, "started 91° off: direction {}° off", far.dir.angle(&up).to_degrees());
    }

    #[test]
    fn bad_input_is_refused_with_a_reason() {
        let views = views(Vector3::new(0.0, 0.0, 400.0), -Vector3::y(), &[0.0, 3.0]);
        assert!(matches!(fit_axis(&views, (Vector3::zeros(), -Vector3::y()), &RefineParams::default()), Err(RegisterError::TooFew { .. })));
        let views = views.into_iter().chain(std::iter::once(RefineView { table_deg: 6.0, points: vec![[0.0; 3]; 10] })).collect::<Vec<_>>();
        let e = fit_axis(&views, (Vector3::zeros(), Vector3::zeros()), &RefineParams::default()).unwrap_err();
        assert!(e.to_string().contains("non-zero direction"), "{e}");
    }
}
