//! The turntable's axis from texture tracks ([`super::tracks`]): a bundle adjustment whose
//! only motion parameters are the axis's four numbers.
//!
//! View k sees a tracked point turned by `θ_k − θ_ref` (table angles, degrees) about the axis
//! from where the track's first view `ref` saw it; each observation's rectified `(x, y)` and
//! disparity are predicted from the point (three unknowns per track, in its first view's
//! frame) and the line, and the line and every point are fitted by Levenberg–Marquardt with
//! Huber weights, the points eliminated per track (the Schur complement: a 4 × 4 system per
//! round, whatever the number of tracks). `(x, y)` are weighted by `sigma_px`, the
//! disparity by `sigma_disparity_px`: the turn, not the stereo depth, triangulates a point
//! seen over tens of degrees.
//!
//! The uncertainty is a delete-a-group jackknife over the tracks (tracks in `groups`
//! interleaved sets): neighbouring tracks share texture and view, so single observations are
//! not independent, while sets spread over the whole object nearly are.

use nalgebra::{Isometry3, Matrix2, Matrix3, Matrix3x4, Matrix4, Point3, SymmetricEigen, Vector3, Vector4};

use super::axis::estimate_axis;
use super::rigid_fit;
use super::refine::{AxisFit, Line, TrackFigures};
use super::tracks::{TrackCamera, TrackObs};
use super::{rotation_about_axis, RegisterError};

/// A view is confirmed by the tracks (see [`TrackFigures::views_unconfirmed`]) when at least
/// this many observations of tracks that started earlier fall in it.
const MIN_VIEW_OBSERVATIONS: usize = 10;

/// Settings of [`fit_axis_to_tracks`].
#[derive(Debug, Clone, PartialEq)]
pub struct BundleParams {
    /// Expected error of a tracked place, pixels.
    pub sigma_px: f64,
    /// Expected error of a disparity, pixels.
    pub sigma_disparity_px: f64,
    /// Residuals beyond this many sigmas get Huber weights.
    pub huber: f64,
    /// Levenberg–Marquardt rounds at most.
    pub rounds: usize,
    /// A track is used when it spans at least this many degrees of turn.
    pub min_span_deg: f64,
    /// Fewer usable tracks than this: no fit.
    pub min_tracks: usize,
    /// Sets of tracks for the jackknife.
    pub groups: usize,
}

impl Default for BundleParams {
    /// Places to 0.2 px, disparities to 0.5 px, Huber beyond 2 σ, 30 rounds; tracks over at
    /// least 9° of turn, 30 of them at least; 20 sets for the jackknife.
    fn default() -> Self {
        BundleParams { sigma_px: 0.2, sigma_disparity_px: 0.5, huber: 2.0, rounds: 30, min_span_deg: 9.0, min_tracks: 30, groups: 20 }
    }
}

/// One track: its observations (indices into the observations used) and its point, in its
/// first view's frame.
struct Track {
    obs: Vec<usize>,
    reference: usize,
}

/// The normal equations of one round: the line's block, and per track the point's block,
/// the cross block and the gradients.
struct Normal {
    a: Matrix4<f64>,
    g: Vector4<f64>,
    per_track: Vec<(Matrix3<f64>, Matrix3x4<f64>, Vector3<f64>)>,
    cost: f64,
    /// Per track: its contribution to the reduced system, for the jackknife.
    reduced: Vec<(Matrix4<f64>, Vector4<f64>)>,
}

/// The tracks a fit can use: their observations (indices into `obs`, in view order) with at
/// least three, over at least `p.min_span_deg` of `angles` (one per view; observations of
/// later views, and of views whose angle is NaN — unknown —, are left out), and the point of
/// each track's first observation in that view's frame. (Also `register::angles`.)
pub(super) fn usable_tracks(obs: &[TrackObs], angles: &[f64], camera: &TrackCamera, p: &BundleParams) -> Vec<(Vec<usize>, Vector3<f64>)> {
    let mut by_track: std::collections::BTreeMap<u32, Vec<usize>> = std::collections::BTreeMap::new();
    for (i, o) in obs.iter().enumerate() {
        if angles.get(o.view as usize).is_some_and(|a| a.is_finite()) && o.x.is_finite() && o.y.is_finite() && o.d.is_finite() {
            by_track.entry(o.track).or_default().push(i);
        }
    }
    by_track
        .into_values()
        .filter_map(|ids| {
            let seen = ids.iter().map(|&i| angles[obs[i].view as usize]);
            let span = seen.clone().fold(f64::NEG_INFINITY, f64::max) - seen.fold(f64::INFINITY, f64::min);
            if ids.len() < 3 || !(span >= p.min_span_deg) {
                return None;
            }
            let first = obs[ids[0]];
            let point = camera.unproject(first.x as f64, first.y as f64, first.d as f64)?;
            Some((ids, point))
        })
        .collect()
}

/// Fits the axis to the tracks from `init` = (point, direction). `table_deg[v]` is view v's
/// table angle.
pub fn fit_axis_to_tracks(obs: &[TrackObs], table_deg: &[f64], camera: &TrackCamera, init: (Vector3<f64>, Vector3<f64>), p: &BundleParams) -> Result<AxisFit, RegisterError> {
    if !(init.1.norm() > 0.0 && init.0.iter().chain(init.1.iter()).all(|v| v.is_finite())) {
        return Err(RegisterError::Param(format!("axis from tracks: initial axis point {:?}, direction {:?}: expected finite values and a non-zero direction", init.0, init.1)));
    }
    let (tracks, points): (Vec<Track>, Vec<Vector3<f64>>) = usable_tracks(obs, table_deg, camera, p).into_iter().map(|(ids, point)| (Track { reference: obs[ids[0]].view as usize, obs: ids }, point)).unzip();
    if tracks.len() < p.min_tracks {
        return Err(RegisterError::TooFew { what: format!("texture tracks over at least {:.0}° of turn", p.min_span_deg), got: tracks.len(), need: p.min_tracks, purpose: "fitting the axis to the tracks".into() });
    }
    // view_from_ref for a turn of `deg` about the line.
    let turn = |l: &Line, deg: f64| rotation_about_axis(&l.point, &l.dir, deg);
    let sigma = [p.sigma_px, p.sigma_px, p.sigma_disparity_px];
    let huber_w = |r: f64| if r.abs() <= p.huber { 1.0 } else { p.huber / r.abs() };
    let huber_cost = |r: f64| if r.abs() <= p.huber { 0.5 * r * r } else { p.huber * (r.abs() - 0.5 * p.huber) };
    // Scaled residuals of one observation for a line and a point.
    let residual = |l: &Line, t: &Track, i: usize, point: &Vector3<f64>| -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let o = &obs[i];
        let m: Isometry3<f64> = turn(l, table_deg[o.view as usize] - table_deg[t.reference]);
        let (pred, jac) = camera.project_with_jacobian(&(m * nalgebra::Point3::from(*point)).coords)?;
        let r = Vector3::new((pred.x - o.x as f64) / sigma[0], (pred.y - o.y as f64) / sigma[1], (pred.z - o.d as f64) / sigma[2]);
        let jp = jac * m.rotation.to_rotation_matrix().matrix();
        let scale = Matrix3::from_diagonal(&Vector3::new(1.0 / sigma[0], 1.0 / sigma[1], 1.0 / sigma[2]));
        Some((r, scale * jp))
    };
    let total_cost = |l: &Line, points: &[Vector3<f64>]| -> f64 {
        tracks.iter().zip(points).map(|(t, pt)| t.obs.iter().map(|&i| residual(l, t, i, pt).map_or(p.huber * p.huber, |(r, _)| r.iter().map(|&v| huber_cost(v)).sum())).sum::<f64>()).sum()
    };
    let normal = |l: &Line, points: &[Vector3<f64>]| -> Normal {
        let steps = [1e-6, 1e-6, 1e-4, 1e-4];
        let (mut a, mut g, mut cost) = (Matrix4::zeros(), Vector4::zeros(), 0.0);
        let mut per_track = Vec::with_capacity(tracks.len());
        let mut reduced = Vec::with_capacity(tracks.len());
        for (t, point) in tracks.iter().zip(points) {
            let (mut u, mut w, mut gx) = (Matrix3::zeros(), Matrix3x4::zeros(), Vector3::zeros());
            let (mut at, mut gt) = (Matrix4::zeros(), Vector4::zeros());
            for &i in &t.obs {
                let Some((r, jp)) = residual(l, t, i, point) else {
                    cost += p.huber * p.huber;
                    continue;
                };
                let mut ja = Matrix3x4::zeros();
                for (k, &st) in steps.iter().enumerate() {
                    let mut e = Vector4::zeros();
                    e[k] = st;
                    if let (Some((rp, _)), Some((rm, _))) = (residual(&l.moved_line(&e), t, i, point), residual(&l.moved_line(&(-e)), t, i, point)) {
                        ja.set_column(k, &((rp - rm) / (2.0 * st)));
                    }
                }
                let wts = Matrix3::from_diagonal(&r.map(huber_w));
                cost += r.iter().map(|&v| huber_cost(v)).sum::<f64>();
                u += jp.transpose() * wts * jp;
                w += jp.transpose() * wts * ja;
                gx += jp.transpose() * wts * r;
                at += ja.transpose() * wts * ja;
                gt += ja.transpose() * wts * r;
            }
            a += at;
            g += gt;
            // The track's share of the reduced system, its point eliminated.
            let share = match (u + Matrix3::identity() * 1e-9).try_inverse() {
                Some(ui) => (at - w.transpose() * ui * w, gt - w.transpose() * ui * gx),
                None => (Matrix4::zeros(), Vector4::zeros()),
            };
            reduced.push(share);
            per_track.push((u, w, gx));
        }
        Normal { a, g, per_track, cost, reduced }
    };
    // Levenberg–Marquardt from a start: the line, the points and the last round's system.
    let solve = |start: (Vector3<f64>, Vector3<f64>), mut points: Vec<Vector3<f64>>| -> (Line, Vec<Vector3<f64>>, Normal) {
        let mut line = Line::new(start.0, start.1);
        let mut lambda = 1e-3;
        let mut last = normal(&line, &points);
        for _ in 0..p.rounds {
            let mut moved = false;
            for _ in 0..10 {
                // The reduced system with damping on both blocks.
                let mut s = last.a + Matrix4::from_diagonal(&last.a.diagonal()) * lambda;
                let mut rhs = last.g;
                let mut inverses = Vec::with_capacity(tracks.len());
                for (u, w, gx) in &last.per_track {
                    let damped = u + Matrix3::from_diagonal(&u.diagonal()) * lambda + Matrix3::identity() * 1e-9;
                    let ui = damped.try_inverse().unwrap_or_else(Matrix3::zeros);
                    s -= w.transpose() * ui * w;
                    rhs -= w.transpose() * ui * gx;
                    inverses.push(ui);
                }
                let Some(da) = s.lu().solve(&(-rhs)) else { break };
                let new_line = line.moved_line(&da);
                let moved_points: Vec<Vector3<f64>> = points.iter().zip(&last.per_track).zip(&inverses).map(|((pt, (_, w, gx)), ui)| pt - ui * (gx + w * da)).collect();
                if total_cost(&new_line, &moved_points) < last.cost {
                    line = new_line;
                    points = moved_points;
                    lambda = (lambda / 3.0).max(1e-9);
                    moved = true;
                    break;
                }
                lambda *= 10.0;
            }
            let previous_cost = last.cost;
            last = normal(&line, &points);
            if !moved || previous_cost - last.cost < 1e-9 * previous_cost {
                break;
            }
        }
        (line, points, last)
    };
    // From the start given, and from the motion the tracks themselves show between two views
    // (`motion_start`): a start far round from the axis — the points' fit of a ball, which
    // leaves the axis free — can end in another minimum. The lower cost is kept.
    let mut best = solve(init, points.clone());
    if let Some(own) = motion_start(obs, &tracks, table_deg, camera).filter(|own| own.1.angle(&best.0.dir).to_degrees() > SAME_START_DEG) {
        let other = solve(own, points);
        if other.2.cost < best.2.cost {
            best = other;
        }
    }
    let (line, points, last) = best;
    // Jackknife over interleaved sets of tracks: the step each leave-one-set-out system
    // takes from the solution.
    let groups = p.groups.clamp(2, tracks.len());
    let mut sets = vec![(Matrix4::zeros(), Vector4::zeros()); groups];
    for (k, share) in last.reduced.iter().enumerate() {
        sets[k % groups].0 += share.0;
        sets[k % groups].1 += share.1;
    }
    let (hh, gg): (Matrix4<f64>, Vector4<f64>) = sets.iter().fold((Matrix4::zeros(), Vector4::zeros()), |(h, g), s| (h + s.0, g + s.1));
    let left_out: Vec<Vector4<f64>> = sets.iter().filter_map(|(h, g)| (hh - h).lu().solve(&(-(gg - g)))).collect();
    let spread = |block: Matrix2<f64>| SymmetricEigen::new(block).eigenvalues.iter().fold(0.0f64, |m, &e| m.max(e)).max(0.0).sqrt();
    let (sigma_dir_deg, sigma_point_mm) = if left_out.len() >= 2 {
        let k = left_out.len() as f64;
        let mean: Vector4<f64> = left_out.iter().sum::<Vector4<f64>>() / k;
        let c = left_out.iter().map(|d| (d - mean) * (d - mean).transpose()).sum::<Matrix4<f64>>() * ((k - 1.0) / k);
        (spread(c.fixed_view::<2, 2>(0, 0).into_owned()).to_degrees(), spread(c.fixed_view::<2, 2>(2, 2).into_owned()))
    } else {
        (f64::INFINITY, f64::INFINITY)
    };
    let count: usize = tracks.iter().map(|t| t.obs.len()).sum();
    // RMS of the places' residuals, pixels.
    // Per view, the places of tracks that started in an earlier view: how far they are from
    // where the table's angle about the line puts them.
    let mut ss = 0.0;
    let mut per_view: Vec<Vec<f64>> = vec![Vec::new(); table_deg.len()];
    for (t, point) in tracks.iter().zip(&points) {
        for &i in &t.obs {
            if let Some((r, _)) = residual(&line, t, i, point) {
                let off2 = (r.x * r.x + r.y * r.y) * p.sigma_px * p.sigma_px;
                ss += off2 / 2.0;
                if obs[i].view as usize != t.reference {
                    per_view[obs[i].view as usize].push(off2.sqrt());
                }
            }
        }
    }
    let (mut worst_view_px, mut views_unconfirmed) = (0.0f64, 0usize);
    // (A view whose angle is unknown has nothing to confirm.)
    for (offs, _) in per_view.iter_mut().zip(table_deg).skip(1).filter(|(_, a)| a.is_finite()) {
        if offs.len() < MIN_VIEW_OBSERVATIONS {
            views_unconfirmed += 1;
        } else {
            offs.sort_by(f64::total_cmp);
            worst_view_px = worst_view_px.max(offs[offs.len() / 2]);
        }
    }
    // The direction as fitted, whatever the start's sign: the table's angles turn the points
    // about it, so its sign is the turn's sense, which the tracks decide. (Taking the start's
    // sign, as this did, turned the model the wrong way wherever the fit came more than a
    // right angle round: a ball's views 2θ off.)
    let dir = line.dir;
    let point = line.point + dir * dir.dot(&(init.0 - line.point));
    let figures = TrackFigures { tracks: tracks.len(), observations: count, rms_px: (ss / count.max(1) as f64).sqrt(), worst_view_px, views_unconfirmed };
    Ok(AxisFit { point, dir, sigma_dir_deg, sigma_point_mm, rms_mm: f64::NAN, pairs: 0, correspondences: 0, tracks: Some(figures) })
}

/// Two starts whose directions lie within this many degrees end in the same minimum: the
/// tracks' own start ([`motion_start`]) is tried only when the fit from the start given ended
/// further from it.
const SAME_START_DEG: f64 = 5.0;

/// The fewest tracks two views must share to give [`motion_start`] their motion.
const MIN_SHARED_TRACKS: usize = 12;

/// The smallest turn, degrees, between two views whose motion gives [`motion_start`] an axis:
/// over a smaller one the stereo points' noise swamps the rotation.
const MIN_START_TURN_DEG: f64 = 5.0;

/// An axis from the tracks alone, for a start that does not depend on the object's shape:
/// the two views whose shared tracks and turn between them give the most rotation to see
/// (tracks × |sin turn|, at least [`MIN_SHARED_TRACKS`] tracks over [`MIN_START_TURN_DEG`]),
/// the rigid motion between their tracks' points ([`rigid_fit`]; once more without the points
/// further than three times the median from it), and its axis as [`estimate_axis`] takes
/// one from poses: signed by the table's turn, its point nearest the points. None when no two
/// views qualify.
fn motion_start(obs: &[TrackObs], tracks: &[Track], table_deg: &[f64], camera: &TrackCamera) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let key = |a: u32, b: u32| (a.min(b), a.max(b));
    let mut shared: std::collections::HashMap<(u32, u32), usize> = std::collections::HashMap::new();
    for t in tracks {
        for (k, &i) in t.obs.iter().enumerate() {
            for &j in &t.obs[k + 1..] {
                *shared.entry(key(obs[i].view, obs[j].view)).or_default() += 1;
            }
        }
    }
    let turn = |(a, b): (u32, u32)| table_deg[b as usize] - table_deg[a as usize];
    let ((a, b), _) = shared
        .into_iter()
        .filter(|&(pair, n)| n >= MIN_SHARED_TRACKS && turn(pair).abs() >= MIN_START_TURN_DEG)
        .map(|(pair, n)| (pair, n as f64 * turn(pair).to_radians().sin().abs()))
        .max_by(|x, y| x.1.total_cmp(&y.1).then(y.0.cmp(&x.0)))?;
    // Each shared track's point in view a and in view b, weighed alike.
    let place = |i: usize| camera.unproject(obs[i].x as f64, obs[i].y as f64, obs[i].d as f64);
    let mut pairs: Vec<(Vector3<f64>, Vector3<f64>, f64)> = tracks
        .iter()
        .filter_map(|t| {
            let at = |v: u32| t.obs.iter().copied().find(|&i| obs[i].view == v);
            Some((place(at(a)?)?, place(at(b)?)?, 1.0))
        })
        .collect();
    if pairs.len() < MIN_SHARED_TRACKS {
        return None;
    }
    // b's points from a's: p_b = b_from_a · p_a.
    let mut b_from_a = rigid_fit(&pairs)?;
    let miss = |t: &Isometry3<f64>, (pa, pb, _): &(Vector3<f64>, Vector3<f64>, f64)| (t * Point3::from(*pa) - Point3::from(*pb)).norm();
    let mut off: Vec<f64> = pairs.iter().map(|p| miss(&b_from_a, p)).collect();
    off.sort_by(f64::total_cmp);
    let limit = 3.0 * off[off.len() / 2];
    pairs.retain(|p| miss(&b_from_a, p) <= limit);
    if pairs.len() >= MIN_SHARED_TRACKS {
        b_from_a = rigid_fit(&pairs)?;
    }
    // The axis of that motion as `register::axis` finds one from the two views' poses in a's
    // frame (a's own, the identity, adds nothing): `a_from_b` turns by −(θ_b − θ_a) about
    // the axis, whose sign the table's turn sets; its point is the one nearest the points'
    // centroid. (Any rotation at all gives an axis: the pair's turn was checked above.)
    let a_from_b = b_from_a.inverse();
    let m = pairs.iter().map(|p| p.0).sum::<Vector3<f64>>() / pairs.len() as f64;
    let axis = estimate_axis(&[(Isometry3::identity(), Some(0.0)), (a_from_b, Some(turn((a, b))))], &m, 1e-6f64.to_degrees())?;
    (axis.point.iter().chain(axis.dir.iter()).all(|v| v.is_finite())).then_some((axis.point, axis.dir))
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::register::tracks::tests::camera;

    /// 400 tracks of points on a 40 mm ball about `axis` = (point, direction), seen by
    /// [`camera`] as the object turns by `turn_deg[v]` in view v: track t from view
    /// `(7 t) mod first_every` over `length` views, its places and disparity with uniform noise
    /// of ±0.1 px (`seed`). (`register::bundle`'s and `register::angles`' tests.)
    pub(in crate::register) fn ball_tracks(axis: (Vector3<f64>, Vector3<f64>), turn_deg: &[f64], first_every: usize, length: usize, seed: u64) -> Vec<TrackObs> {
        let cam = camera();
        let mut seed = seed;
        let mut noise = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 0.2
        };
        let mut obs = Vec::new();
        for t in 0..400u32 {
            let (a, b) = (t as f64 * 0.37, t as f64 * 1.13);
            let base = axis.0 + Vector3::new(40.0 * a.cos() * b.sin(), 40.0 * a.sin() * b.sin(), -40.0 * b.cos().abs());
            let first = (t as usize * 7) % first_every;
            for (v, &deg) in turn_deg.iter().enumerate().skip(first).take(length) {
                let m = crate::register::rotation_about_axis(&axis.0, &axis.1, deg);
                let q = cam.project(&(m * nalgebra::Point3::from(base)).coords).unwrap();
                obs.push(TrackObs { track: t, view: v as u32, x: (q.x + noise()) as f32, y: (q.y + noise()) as f32, d: (q.z + noise()) as f32 });
            }
        }
        obs
    }

    /// Points on a 40 mm ball about a tilted axis 450 mm away, seen over 40 views 3° apart
    /// with noise on the places and a bias on the disparities.
    #[test]
    fn the_axis_comes_back_from_noisy_tracks_started_off() {
        let cam = camera();
        let truth = (Vector3::new(5.0, -10.0, 450.0), Vector3::new(0.02, -0.97, -0.2).normalize());
        let angles: Vec<f64> = (0..50).map(|k| 3.0 * k as f64).collect();
        // `slipped`: from view 30 on, the object sits 2° further round than the table says.
        let obs = ball_tracks(truth, &angles, 27, 24, 7);
        let slipped_turn: Vec<f64> = angles.iter().enumerate().map(|(v, a)| if v >= 30 { a + 2.0 } else { *a }).collect();
        let slipped = ball_tracks(truth, &slipped_turn, 27, 24, 8);
        // Started 1° and 3 mm off.
        let tilt = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(1.0f64.to_radians(), 0.0, 0.0));
        let init = (truth.0 + Vector3::new(3.0, 0.0, 0.0), tilt * truth.1);
        let fit = fit_axis_to_tracks(&obs, &angles, &cam, init, &BundleParams::default()).unwrap();
        let err = fit.dir.angle(&truth.1).to_degrees();
        let off = (fit.point - truth.0 - truth.1 * truth.1.dot(&(fit.point - truth.0))).norm();
        assert!(err < 0.02 && off < 0.2, "direction {err}° off, point {off} mm off (σ {}°)", fit.sigma_dir_deg);
        assert!(fit.sigma_dir_deg < 0.05 && fit.sigma_dir_deg > 0.0, "σ {}", fit.sigma_dir_deg);
        let t = fit.tracks.unwrap();
        assert!(t.rms_px < 0.2 && t.worst_view_px < 0.15 && t.views_unconfirmed == 0, "{t:?}");
        // A view whose angle is unknown (NaN): its observations are left out, and it has
        // nothing to confirm.
        let mut lost = angles.clone();
        lost[10] = f64::NAN;
        let without = fit_axis_to_tracks(&obs, &lost, &cam, init, &BundleParams::default()).unwrap();
        assert!(without.dir.angle(&truth.1).to_degrees() < 0.02, "{without:?}");
        let t = without.tracks.unwrap();
        assert!(t.views_unconfirmed == 0 && t.observations < fit.tracks.unwrap().observations, "{t:?}");
        // An object that moved on the table: the views after it stand out.
        let moved = fit_axis_to_tracks(&slipped, &angles, &cam, init, &BundleParams::default()).unwrap().tracks.unwrap();
        assert!(moved.worst_view_px > 0.4, "{moved:?}");
        // Started more than a right angle off (as from the points' fit of a ball, which
        // leaves the axis free): the tracks still decide the turn's sense, so the fit must
        // come back to the axis the table turns about, not to the line's other direction.
        // (From 91° the fit comes round by itself; from further, and from the very opposite
        // direction, it needs the start the tracks' own motion gives.)
        for deg in [91.0f64, 100.0, 180.0] {
            let across = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(deg.to_radians(), 0.0, 0.0));
            let far = fit_axis_to_tracks(&obs, &angles, &cam, (init.0 + Vector3::new(0.0, 0.0, 30.0), across * truth.1), &BundleParams::default()).unwrap();
            let err = far.dir.angle(&truth.1).to_degrees();
            let off = (far.point - truth.0 - truth.1 * truth.1.dot(&(far.point - truth.0))).norm();
            assert!(err < 0.05 && off < 0.2, "started {deg}° off: direction {err}° from the axis the table turns about, point {off} mm off (σ {}°)", far.sigma_dir_deg);
        }
        // Too few tracks: a clear error.
        let few: Vec<TrackObs> = obs.iter().filter(|o| o.track < 5).copied().collect();
        let err = fit_axis_to_tracks(&few, &angles, &cam, init, &BundleParams::default()).unwrap_err().to_string();
        assert!(err.contains("texture tracks") && err.contains("at least 30"), "{err}");
    }
}
