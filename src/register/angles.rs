//! The table's angles from texture tracks ([`super::tracks`]), for a turntable that reports
//! none (`table_deg` null in the recording).
//!
//! Why: without the table's angles a view's pose is ICP's chain, and ICP under-turns a
//! smooth object by 5–9 % a step — the stereo clouds' errors are fixed to the camera, not to
//! the object, and pull every step towards "no motion" (docs/registration.md, Known limits,
//! "without the table's angles"). Texture moves with the object: where a tracked point
//! appears in each view fixes how far the object turned.
//!
//! How: the object turns about one line, the axis; view v sees each track's point `X` (in the
//! frame of angle 0) turned by its angle θ_v about it. The line's four numbers, the angles
//! and the points are fitted together to the tracked places and disparities, weighted and
//! Huber-robust as in [`super::bundle`], by Levenberg–Marquardt with the points eliminated per
//! track (the Schur complement: one system of the line and the angles a round). The first
//! view's angle stays where it started (the turn is relative). Tried first and dropped:
//! descent by blocks (every point with the angles held, then every angle) crept — all the
//! angles moving one way and the points the other is a motion only the first view's few
//! tracks resist — and so did alternating the angles with the axis of [`super::bundle`]
//! (0.18° median pose error on the independent renderer's ideal recording after 3 rounds,
//! 0.10° after 12, against 0.048° fitted together).

use nalgebra::{DMatrix, DVector, Matrix3, Point3, Vector3, Vector4};

use super::bundle::{usable_tracks, BundleParams};
use super::refine::{Line, TrackFigures};
use super::tracks::{TrackCamera, TrackObs};
use super::{rotation_about_axis, RegisterError};

/// Rounds at most; the fit stops earlier when no angle moves by more than [`SETTLED_DEG`].
const MAX_ROUNDS: usize = 50;
/// An angle step below this many degrees is no step.
const SETTLED_DEG: f64 = 1e-5;
/// A view whose angle the tracks fix needs at least this many observations of tracks also
/// seen in another view.
const MIN_VIEW_OBSERVATIONS: usize = 10;

/// Angles fitted to the tracks.
#[derive(Debug, Clone, PartialEq)]
pub struct AngleFit {
    /// Per view (the tracker's views), degrees; the first as it started.
    pub deg: Vec<f64>,
    /// The axis fitted with them: (point, direction).
    pub axis: (Vector3<f64>, Vector3<f64>),
    pub figures: TrackFigures,
    /// Rounds the fit took.
    pub rounds: usize,
}

/// Fits each view's angle, and the axis, to the tracks, from `start_deg` (one per view of
/// the observations) and `axis` = (point, direction). Tracks with fewer than three
/// observations or over less than `p.min_span_deg` of the start angles are not used; fewer
/// than `p.min_tracks` tracks, or a view after the first without [`MIN_VIEW_OBSERVATIONS`]
/// observations, is an error (its angle would be a guess).
///
/// `held[v]`: view v's angle is known and stays (missing entries: free); `hold_axis`: the
/// axis is known and stays too (then only the free views' angles and the points move).
pub fn fit_angles_to_tracks(obs: &[TrackObs], start_deg: &[f64], held: &[bool], camera: &TrackCamera, axis: (Vector3<f64>, Vector3<f64>), hold_axis: bool, p: &BundleParams) -> Result<AngleFit, RegisterError> {
    let dir = axis.1.try_normalize(1e-12).filter(|d| d.iter().chain(axis.0.iter()).all(|v| v.is_finite()));
    let Some(dir) = dir else {
        return Err(RegisterError::Param(format!("angles from tracks: axis point {:?}, direction {:?}: expected finite values and a non-zero direction", axis.0, axis.1)));
    };
    let views = start_deg.len();
    // Each track's point in the frame of angle 0.
    let (tracks, mut points): (Vec<Vec<usize>>, Vec<Vector3<f64>>) = usable_tracks(obs, start_deg, camera, p)
        .into_iter()
        .map(|(ids, seen)| {
            let back = rotation_about_axis(&axis.0, &dir, -start_deg[obs[ids[0]].view as usize]);
            let point = (back * Point3::from(seen)).coords;
            (ids, point)
        })
        .unzip();
    if tracks.len() < p.min_tracks.max(1) {
        return Err(RegisterError::TooFew { what: format!("texture tracks over at least {:.0}° of turn", p.min_span_deg), got: tracks.len(), need: p.min_tracks.max(1), purpose: "fitting the table's angles to the tracks".into() });
    }
    let mut per_view = vec![0usize; views];
    for ids in &tracks {
        for &i in ids {
            per_view[obs[i].view as usize] += 1;
        }
    }
    let first_view = obs[tracks.iter().map(|ids| ids[0]).min_by_key(|&i| obs[i].view).unwrap_or(0)].view as usize;
    let free = |v: usize| v != first_view && !held.get(v).copied().unwrap_or(false);
    if let Some(v) = (0..views).find(|&v| free(v) && per_view[v] < MIN_VIEW_OBSERVATIONS) {
        return Err(RegisterError::TooFew { what: format!("tracked places in view {v} of the tracks"), got: per_view[v], need: MIN_VIEW_OBSERVATIONS, purpose: "fitting its angle to the tracks".into() });
    }

    let sigma = Vector3::new(p.sigma_px, p.sigma_px, p.sigma_disparity_px);
    let scale = Matrix3::from_diagonal(&sigma.map(|s| 1.0 / s));
    let huber_w = |r: f64| if r.abs() <= p.huber { 1.0 } else { p.huber / r.abs() };
    let huber_cost = |r: f64| if r.abs() <= p.huber { 0.5 * r * r } else { p.huber * (r.abs() - 0.5 * p.huber) };
    // Scaled residual of observation `i` for the line, point `x` and angle `deg`, with its
    // derivatives by the point and by the angle (per degree).
    let residual = |l: &Line, i: usize, x: &Vector3<f64>, deg: f64| -> Option<(Vector3<f64>, Matrix3<f64>, Vector3<f64>)> {
        let o = &obs[i];
        let m = rotation_about_axis(&l.point, &l.dir, deg);
        let q = (m * Point3::from(*x)).coords;
        let (pred, jac) = camera.project_with_jacobian(&q)?;
        let r = Vector3::new(pred.x - o.x as f64, pred.y - o.y as f64, pred.z - o.d as f64).component_div(&sigma);
        let jx = scale * jac * m.rotation.to_rotation_matrix().matrix();
        let jt = scale * jac * l.dir.cross(&(q - l.point)) * 1f64.to_radians();
        Some((r, jx, jt))
    };
    let cost = |l: &Line, deg: &[f64], points: &[Vector3<f64>]| -> f64 {
        let one = |i: usize, x: &Vector3<f64>| residual(l, i, x, deg[obs[i].view as usize]).map_or(p.huber * p.huber, |(r, _, _)| r.iter().map(|&v| huber_cost(v)).sum());
        tracks.iter().zip(points).map(|(ids, x)| ids.iter().map(|&i| one(i, x)).sum::<f64>()).sum()
    };
    // The unknowns besides the points: the line's four numbers (`Line::moved`) unless it is
    // held, then the free views' angles; `slot[v]` is view v's.
    let line_cols = if hold_axis { 0 } else { 4 };
    let slot: Vec<Option<usize>> = {
        let mut next = line_cols;
        (0..views).map(|v| (free(v) && per_view[v] > 0).then(|| { next += 1; next - 1 })).collect()
    };
    let n = line_cols + slot.iter().flatten().count();
    let line_steps = &[1e-6, 1e-6, 1e-4, 1e-4][..line_cols];
    let mut line = Line::new(axis.0, dir);
    let mut deg = start_deg.to_vec();
    let mut lambda = 1e-3;
    let mut rounds = 0;
    let mut current = cost(&line, &deg, &points);
    while rounds < MAX_ROUNDS && n > 0 {
        rounds += 1;
        // The normal equations, each track's point eliminated (its Schur complement).
        let (mut s, mut rhs) = (DMatrix::<f64>::zeros(n, n), DVector::<f64>::zeros(n));
        let mut per_track = Vec::with_capacity(tracks.len());
        for (ids, x) in tracks.iter().zip(&points) {
            let (mut u, mut gx) = (Matrix3::zeros(), Vector3::zeros());
            // Per unknown this track depends on: Jₓᵀ W J of that column.
            let mut cross: Vec<(usize, Vector3<f64>)> = Vec::new();
            for &i in ids {
                let v = obs[i].view as usize;
                let Some((r, jx, jt)) = residual(&line, i, x, deg[v]) else { continue };
                let w = Matrix3::from_diagonal(&r.map(huber_w));
                u += jx.transpose() * w * jx;
                gx += jx.transpose() * w * r;
                // This observation's columns: the line's (numerical), and its view's angle.
                let mut cols: Vec<(usize, Vector3<f64>)> = Vec::with_capacity(line_cols + 1);
                for (k, &st) in line_steps.iter().enumerate() {
                    let mut e = Vector4::zeros();
                    e[k] = st;
                    let (plus, minus) = (line.moved_line(&e), line.moved_line(&(-e)));
                    if let (Some((rp, _, _)), Some((rm, _, _))) = (residual(&plus, i, x, deg[v]), residual(&minus, i, x, deg[v])) {
                        cols.push((k, (rp - rm) / (2.0 * st)));
                    }
                }
                if let Some(k) = slot[v] {
                    cols.push((k, jt));
                }
                for &(a, ja) in &cols {
                    let wja = w * ja;
                    rhs[a] += wja.dot(&r);
                    for &(b, jb) in &cols {
                        s[(a, b)] += wja.dot(&jb);
                    }
                    let c = jx.transpose() * wja;
                    match cross.iter_mut().find(|(k, _)| *k == a) {
                        Some((_, sum)) => *sum += c,
                        None => cross.push((a, c)),
                    }
                }
            }
            per_track.push((u, gx, cross));
        }
        let mut inverses = Vec::with_capacity(tracks.len());
        for (u, gx, cross) in &per_track {
            let damped = u + Matrix3::from_diagonal(&u.diagonal()) * lambda + Matrix3::identity() * 1e-9;
            let ui = damped.try_inverse().unwrap_or_else(Matrix3::zeros);
            for &(a, wa) in cross {
                let uwa = ui * wa;
                rhs[a] -= uwa.dot(gx);
                for &(b, wb) in cross {
                    s[(a, b)] -= uwa.dot(&wb);
                }
            }
            inverses.push(ui);
        }
        let mut moved = None;
        for _ in 0..10 {
            let mut damped = s.clone();
            for k in 0..n {
                damped[(k, k)] += damped[(k, k)].abs() * lambda + 1e-12;
            }
            let Some(dm) = damped.lu().solve(&(-&rhs)) else { break };
            let new_line = if hold_axis { line } else { line.moved_line(&Vector4::new(dm[0], dm[1], dm[2], dm[3])) };
            let mut new_deg = deg.clone();
            for (v, k) in slot.iter().enumerate() {
                if let Some(k) = k {
                    new_deg[v] += dm[*k];
                }
            }
            let new_points: Vec<Vector3<f64>> = points
                .iter()
                .zip(&per_track)
                .zip(&inverses)
                .map(|((x, (_, gx, cross)), ui)| x - ui * (gx + cross.iter().map(|&(k, w)| w * dm[k]).sum::<Vector3<f64>>()))
                .collect();
            let new_cost = cost(&new_line, &new_deg, &new_points);
            if new_cost < current {
                let step = dm.rows(line_cols, n - line_cols).amax();
                (line, deg, points, current) = (new_line, new_deg, new_points, new_cost);
                lambda = (lambda / 3.0).max(1e-9);
                moved = Some(step);
                break;
            }
            lambda *= 10.0;
        }
        if moved.is_none_or(|step| step < SETTLED_DEG) {
            break;
        }
    }

    // The places' residuals: overall, and per view its median, as `register::bundle` reports.
    let (mut ss, mut count) = (0.0, 0usize);
    let mut offs: Vec<Vec<f64>> = vec![Vec::new(); views];
    for (ids, x) in tracks.iter().zip(&points) {
        for &i in ids {
            count += 1;
            if let Some((r, _, _)) = residual(&line, i, x, deg[obs[i].view as usize]) {
                let off2 = (r.x * r.x + r.y * r.y) * p.sigma_px * p.sigma_px;
                ss += off2 / 2.0;
                offs[obs[i].view as usize].push(off2.sqrt());
            }
        }
    }
    let mut worst_view_px = 0.0f64;
    for o in offs.iter_mut().filter(|o| !o.is_empty()) {
        o.sort_by(f64::total_cmp);
        worst_view_px = worst_view_px.max(o[o.len() / 2]);
    }
    let figures = TrackFigures { tracks: tracks.len(), observations: count, rms_px: (ss / count.max(1) as f64).sqrt(), worst_view_px, views_unconfirmed: 0 };
    // The point nearest the start's, as `register::bundle` gives it.
    let point = line.point + line.dir * line.dir.dot(&(axis.0 - line.point));
    Ok(AngleFit { deg, axis: (point, line.dir), figures, rounds })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::register::bundle::tests::ball_tracks;
    use crate::register::tracks::tests::camera;

    /// Points on a 40 mm ball about a tilted axis 450 mm away, seen over 30 views turning by
    /// uneven steps, with noise on the places: started from angles 8 % short (as ICP's chain
    /// under-turns a smooth object) about an axis 1° off, the fit comes back to the true turn
    /// and axis; with most angles and the axis known, the missing angles come back.
    #[test]
    fn the_angles_come_back_from_tracks_started_short() {
        let cam = camera();
        let axis = (Vector3::new(5.0, -10.0, 450.0), Vector3::new(0.02, -0.97, -0.2).normalize());
        let truth: Vec<f64> = (0..30).map(|k| 3.0 * k as f64 + (k as f64 * 0.7).sin()).collect();
        let obs = ball_tracks(axis, &truth, 17, 14, 11);
        let start: Vec<f64> = truth.iter().map(|d| 0.92 * d).collect();
        // The axis started 1° and 3 mm off.
        let tilt = nalgebra::UnitQuaternion::from_scaled_axis(Vector3::new(1.0f64.to_radians(), 0.0, 0.0));
        let off_axis = (axis.0 + Vector3::new(3.0, 0.0, 0.0), tilt * axis.1);
        let fit = fit_angles_to_tracks(&obs, &start, &[], &cam, off_axis, false, &BundleParams::default()).unwrap();
        let err = fit.axis.1.angle(&axis.1).to_degrees();
        let miss = (fit.axis.0 - axis.0 - axis.1 * axis.1.dot(&(fit.axis.0 - axis.0))).norm();
        assert!(err < 0.05 && miss < 0.3, "axis {err:.4}° and {miss:.3} mm off");
        // Within noise everywhere (the views at the ends, seen by the fewest tracks, to
        // 0.08°), and to hundredths of a degree typically.
        let mut off: Vec<f64> = fit.deg.iter().zip(&truth).map(|(got, want)| (got - want).abs()).collect();
        for (v, o) in off.iter().enumerate() {
            assert!(*o < 0.1, "view {v}: {:.4}° against {:.4}° (started at {:.4}°, {} rounds)", fit.deg[v], truth[v], start[v], fit.rounds);
        }
        off.sort_by(f64::total_cmp);
        assert!(off[off.len() / 2] < 0.015, "median {:.4}°", off[off.len() / 2]);
        assert!(fit.figures.rms_px < 0.1 && fit.figures.worst_view_px < 0.1, "{:?}", fit.figures);
        // Most angles known (held) and the axis too: the three missing ones, started 1° off,
        // come back.
        let held: Vec<bool> = (0..truth.len()).map(|v| ![10, 11, 20].contains(&v)).collect();
        let near: Vec<f64> = truth.iter().zip(&held).map(|(d, h)| if *h { *d } else { d + 1.0 }).collect();
        let missing = fit_angles_to_tracks(&obs, &near, &held, &cam, axis, true, &BundleParams::default()).unwrap();
        for v in [10, 11, 20] {
            assert!((missing.deg[v] - truth[v]).abs() < 0.05, "view {v}: {:.4}° against {:.4}°", missing.deg[v], truth[v]);
        }
        assert!(missing.deg.iter().zip(&near).zip(&held).all(|((a, b), h)| !h || a == b) && missing.axis.1 == axis.1, "held angles or axis moved");
        // A view the tracks hardly see: a clear error, not a guess.
        let sparse: Vec<TrackObs> = obs.iter().filter(|o| o.view != 12 || o.track < 3).copied().collect();
        let err = fit_angles_to_tracks(&sparse, &start, &[], &cam, off_axis, false, &BundleParams::default()).unwrap_err().to_string();
        assert!(err.contains("view 12") && err.contains("at least 10"), "{err}");
    }
}
