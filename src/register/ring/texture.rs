//! The texture side of [`Registrar`]: the object's texture tracked from view to view while
//! the views come (`register::tracks`), and the axis fitted to those tracks at the end of the
//! scan (`register::bundle`), started from the axis fitted to the views' points. In a scan
//! without the table's angles, the angles too (`register::angles`).

use std::time::Instant;

use nalgebra::Vector3;

use super::turntable::{tracks_follow_turn, tracks_stray};
use super::Registrar;
use crate::register::angles::fit_angles_to_tracks;
use crate::register::bundle::{fit_axis_to_tracks, usable_tracks, BundleParams};
use crate::register::refine::{AxisFit, TrackFigures};
use crate::register::rotation_about_axis;
use crate::register::tracks::{TrackImage, TrackObs, Tracker};
use crate::register::RegisterError;

/// The tracks, and what became of the axis fitted to them.
#[derive(Default)]
pub(super) struct Texture {
    tracker: Option<Tracker>,
    /// The view the tracker saw last.
    last_seq: Option<u64>,
    /// The axis fitted to the views' points, when the tracks' axis replaced it.
    pub(super) points_fit: Option<AxisFit>,
    /// Why there is no axis from the tracks, or why it was not used.
    pub(super) note: Option<String>,
    /// In a scan without the table's angles: the turn fitted to the tracks.
    pub(super) turn: Option<TrackedTurn>,
}

/// The turn of a scan without the table's angles, fitted to the texture tracks at its end
/// ([`Registrar::tracked_turn`]).
#[derive(Debug, Clone, PartialEq)]
pub struct TrackedTurn {
    /// The tracks' fit (with the angles fitted).
    pub figures: TrackFigures,
    /// The whole turn, first to last view, degrees: as ICP's chain had it, and as fitted.
    pub chained_deg: f64,
    pub fitted_deg: f64,
    /// The largest change of a view's angle from the chain's, degrees.
    pub max_change_deg: f64,
    /// The poses became turns about the tracks' axis by the fitted angles.
    pub applied: bool,
    /// Why they did not (None when they did).
    pub kept_because: Option<String>,
}

/// How many times closer to the table's angles than to the registered chain's the tracks' own
/// angles must lie (RMS over the views) to side with the table ([`TurnCheck`]). The tracks'
/// own turn is off by −1.1 … +0.8 % of a scan's turn on the recordings measured (below, and
/// docs/registration.md), the chain by up to −24 %: on the independent renderer's ideal
/// 30-view recording the tracks turned 58.19° of 58°, where the chain under-turned to 56.23°.
const TRACKS_SIDE_RATIO: f64 = 3.0;

/// The tracks' angles' RMS distance from the table's and from the chain's (one per view,
/// degrees), and whether they side with the table: the tracks follow their turn (`follows`),
/// lie [`TRACKS_SIDE_RATIO`] times closer to the table's angles than to the chain's, and the
/// chain lies at least `min_gap_deg` from them — further than the axis's uncertainty could
/// move the table's poses, so that the turn, not the axis, is what the two disagree on.
fn sides_with_table(tracked: &[f64], table: &[f64], chained: &[f64], follows: bool, min_gap_deg: f64) -> (f64, f64, bool) {
    let (from_table, from_registered) = (rms_apart(tracked, table), rms_apart(tracked, chained));
    (from_table, from_registered, follows && TRACKS_SIDE_RATIO * from_table < from_registered && from_registered >= min_gap_deg)
}

/// The RMS difference of two turns, view by view, degrees.
fn rms_apart(a: &[f64], b: &[f64]) -> f64 {
    (a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len() as f64).sqrt()
}

/// Sets of tracks (interleaved by track) for the jackknife of the tracks' own turn.
const TURN_GROUPS: usize = 8;
/// The least share of the turn by which the table's whole turn must differ from the tracks'
/// for [`TurnCheck::warning`]: on 28 simulated and independent recordings with true angles,
/// both matchers, the tracks' own turn came out −1.1 … +0.8 % of the truth — and +3.0 %
/// (0.89°) on a 16-view scan of a 180 mm toed-in rig with `bm`, whose jackknife put it at
/// ±0.29°: 3.1 σ, hence the bound below at 4.
const TABLE_SCALE_SHARE: f64 = 0.02;
/// …and by how many of the tracks' turn's standard deviations.
const TABLE_SCALE_SIGMAS: f64 = 4.0;

/// The tracks' RMS distance from the table's angles scaled to them, degrees, up to which the
/// scaled table gives the poses where the table's angles are off: the table's steps then
/// differ from the tracks' by a scale alone, and keep their even spacing, which the tracks'
/// angles (jittering by 0.05–0.1° from view to view) do not.
const SCALED_TABLE_RMS_DEG: f64 = 0.25;

/// The delete-a-group jackknife's standard deviation from the estimates `est` left by each
/// of `groups` groups in turn (those that failed left out); NaN with fewer than half of them.
fn jackknife_sigma(est: &[f64], groups: usize) -> f64 {
    if est.len() * 2 < groups || est.len() < 2 {
        return f64::NAN;
    }
    let g = est.len() as f64;
    let mean = est.iter().sum::<f64>() / g;
    ((g - 1.0) / g * est.iter().map(|e| (e - mean).powi(2)).sum::<f64>()).sqrt()
}

/// The texture tracks' own turn (every view's angle fitted) beside the table's and the
/// registered chain's ([`Registrar::check_turn_with_texture`]), at the end of a scan with a
/// fitted axis. It decides where the turntable's axis is known only to more than
/// `max_axis_sigma_deg` and the registered poses put the views onto each other a little
/// closer than its poses: ICP's chain under-turns a smooth object, and a table whose angles
/// are on a wrong scale over- or under-turns it; the score alone cannot tell which, and the
/// tracks' angles, free of both, can. And it warns of a table on a wrong scale.
#[derive(Debug, Clone, PartialEq)]
pub struct TurnCheck {
    /// The whole turn, first to last view, degrees: the table's, the registered chain's about
    /// the axis, the tracks'.
    pub table_deg: f64,
    pub registered_deg: f64,
    pub tracked_deg: f64,
    /// The tracks' whole turn's standard deviation, degrees (a jackknife over [`TURN_GROUPS`]
    /// sets of tracks), where the table's turn differs from theirs by more than
    /// [`TABLE_SCALE_SHARE`]; NaN elsewhere, and where fewer than half the sets could be
    /// fitted.
    pub tracked_sigma_deg: f64,
    /// RMS over the views of the tracks' angles from the table's and from the chain's, degrees.
    pub rms_from_table_deg: f64,
    pub rms_from_registered_deg: f64,
    /// The tracks follow their own turn as closely as they must follow a table's
    /// (`tracks_follow_turn`).
    pub tracks_follow: bool,
    /// They follow it and side with the table ([`sides_with_table`]): the table's angles
    /// stand.
    pub sides_with_table: bool,
    /// Where the tracks follow their turn and the table's whole turn differs from it by more
    /// than [`TABLE_SCALE_SHARE`] of it and [`TABLE_SCALE_SIGMAS`] × its σ: that the table's
    /// angles may be on a wrong scale, with the figures.
    pub warning: Option<String>,
    /// The scale that takes the table's angles closest to the tracks' (least squares over
    /// the views), and the tracks' RMS distance from the table's angles so scaled, degrees.
    pub table_scale: f64,
    pub scaled_rms_deg: f64,
    /// The turn the poses take where the table's angles are off ([`TurnCheck::warning`]),
    /// view by view from the first (degrees about `axis.1`): the table's angles scaled by
    /// `table_scale` where the tracks lie within [`SCALED_TABLE_RMS_DEG`] of them (the table's
    /// steps keep their even spacing, only their scale was wrong), else the tracks' own
    /// angles; and the axis fitted with the tracks' angles: (point, direction).
    pub angles_deg: Vec<f64>,
    pub axis: (Vector3<f64>, Vector3<f64>),
    /// The poses became those turns (with [`TurnCheck::warning`]).
    pub applied: bool,
}

impl Registrar {
    /// Follows the object's texture into the view just registered by
    /// [`Registrar::add_view`] (`seq`: its rectified left image and disparity map), by the
    /// step registration found. Does nothing without a camera (`track_camera`) or tracking
    /// settings, or with a calibrated axis, which needs no tracks. A view without a table
    /// angle in a scan with them is tracked through, its observations left out of the fits;
    /// in a scan without the table's angles every view is tracked and the tracks give the
    /// angles at the end ([`Registrar::tracked_turn`]).
    /// Returns the time taken, ms.
    pub fn track_view(&mut self, seq: u64, image: TrackImage<'_>) -> f64 {
        let started = Instant::now();
        let (Some(camera), Some(params)) = (self.params.track_camera, self.params.tracks.as_ref()) else { return 0.0 };
        if self.params.calibrated_axis.is_some() {
            return 0.0;
        }
        let n = self.poses.len();
        let Some(last) = self.poses.last().filter(|p| p.seq == seq) else { return 0.0 };
        // Without angles the tracker keeps the chain's turn so far (the fit at the end
        // replaces it); in a scan with them, a view without one is tracked through, its
        // angle unknown (NaN) to the fits.
        let blind = self.poses[0].table_deg.is_none();
        let table_deg = last.table_deg.unwrap_or(if blind { self.turned_deg } else { f64::NAN });
        // The step from the view tracked last: None (the tracks end) when a view between was
        // not tracked.
        let new_from_prev = (n >= 2 && self.texture.last_seq == Some(self.poses[n - 2].seq)).then(|| last.first_from_view.inverse() * self.poses[n - 2].first_from_view);
        self.texture.last_seq = Some(seq);
        let tracker = self.texture.tracker.get_or_insert_with(|| Tracker::new(camera, params.clone()));
        tracker.add(image, table_deg, new_from_prev.as_ref());
        started.elapsed().as_secs_f64() * 1e3
    }

    /// The axis fitted to the views' points at the end of the scan, when the texture tracks'
    /// axis replaced it ([`Registrar::refined_axis`] is then the tracks' axis).
    pub fn points_axis(&self) -> Option<&AxisFit> {
        self.texture.points_fit.as_ref()
    }

    /// Why the texture tracks gave no axis, or why theirs was not used.
    pub fn texture_note(&self) -> Option<&str> {
        self.texture.note.as_deref()
    }

    /// The axis fitted to the texture tracks from `start` = (point, direction); None when
    /// nothing was tracked.
    pub(super) fn fit_axis_to_texture(&self, start: (Vector3<f64>, Vector3<f64>)) -> Option<Result<AxisFit, RegisterError>> {
        let tracker = self.texture.tracker.as_ref()?;
        let started = Instant::now();
        let fit = fit_axis_to_tracks(tracker.observations(), tracker.table_deg(), tracker.camera(), start, &self.params.bundle);
        match &fit {
            Ok(AxisFit { tracks: Some(t), sigma_dir_deg, dir, .. }) => {
                let off = dir.angle(&start.1).to_degrees();
                tracing::info!("texture tracks: the axis fitted to {} tracks ({} observations) in {:.1} s (direction ±{sigma_dir_deg:.3}°, {off:.3}° from where it started, RMS {:.2} px)", t.tracks, t.observations, started.elapsed().as_secs_f64(), t.rms_px);
            }
            Ok(_) => {}
            Err(e) => tracing::info!("texture tracks: no axis ({e})"),
        }
        Some(fit)
    }

    /// The turn fitted to the texture tracks in a scan without the table's angles.
    pub fn tracked_turn(&self) -> Option<&TrackedTurn> {
        self.texture.turn.as_ref()
    }

    /// For a scan without the table's angles (none of its views has one): fits every view's
    /// angle about the turntable's axis, and the axis, to the texture tracks, from the
    /// chain's turn about the axis estimated from its poses. When the tracks follow the
    /// fitted turn as closely as they must follow a table's angles for the turntable's poses
    /// to be used (`tracks_follow_turn`), the poses become those turns: texture moves with
    /// the object, while ICP's chain under-turns a smooth one (module `register::angles`).
    pub(super) fn fit_turn_to_texture(&mut self) {
        if self.poses.len() < 3 || self.poses.iter().any(|p| p.table_deg.is_some()) || self.params.calibrated_axis.is_some() {
            return;
        }
        // Every view tracked, in turn: the tracker's views are then the poses.
        let tracked = self.texture.tracker.as_ref().map_or(0, |t| t.table_deg().len());
        if tracked != self.poses.len() {
            self.no_tracked_turn(format!("{tracked} of {} views were tracked (tracking is off, or a view's image could not be used)", self.poses.len()));
            return;
        }
        let Some(start) = self.axis.as_ref().map(|a| (a.point, a.dir)) else {
            self.no_tracked_turn("no axis was estimated from the poses".into());
            return;
        };
        let started = Instant::now();
        let chained = self.chained_turn_deg(&start.1);
        let Some(tracker) = self.texture.tracker.as_ref() else { return };
        let fitted = match fit_angles_to_tracks(tracker.observations(), &chained, &[], tracker.camera(), start, false, &self.params.bundle) {
            Ok(f) => f,
            Err(e) => {
                self.no_tracked_turn(e.to_string());
                return;
            }
        };
        let axis = fitted.axis;
        let f = fitted.figures;
        let follows = tracks_follow_turn(&f);
        let kept_because = (!follows).then(|| tracks_stray(&f));
        let last = self.poses.len() - 1;
        let turn = TrackedTurn {
            figures: f,
            chained_deg: chained[last],
            fitted_deg: fitted.deg[last],
            max_change_deg: fitted.deg.iter().zip(&chained).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max),
            applied: follows,
            kept_because,
        };
        tracing::info!(
            "texture tracks: the turn fitted to {} tracks in {:.1} s ({} rounds): {:.2}° first to last view, against {:.2}° chained (views up to {:.2}° apart); RMS {:.2} px{}",
            f.tracks,
            started.elapsed().as_secs_f64(),
            fitted.rounds,
            turn.fitted_deg,
            turn.chained_deg,
            turn.max_change_deg,
            f.rms_px,
            if follows { "" } else { "; not used" }
        );
        if let Some(why) = &turn.kept_because {
            tracing::warn!("no angles from the texture tracks: {why}; the poses stay ICP's chain, which under-turns a smooth object");
        }
        if follows {
            for (p, deg) in self.poses.iter_mut().zip(&fitted.deg) {
                p.first_from_view = rotation_about_axis(&axis.0, &axis.1, -deg);
            }
            self.turned_deg = turn.fitted_deg.abs();
            // The axis reported and written (turntable_estimated.yaml) is the tracks'. Its
            // uncertainty is not estimated here (NaN: null in the report).
            self.refined = Some(AxisFit { point: axis.0, dir: axis.1, sigma_dir_deg: f64::NAN, sigma_point_mm: f64::NAN, rms_mm: f64::NAN, pairs: 0, correspondences: 0, tracks: Some(f) });
        }
        self.texture.turn = Some(turn);
    }

    /// In a scan with the table's angles, the angles of the views whose reading is missing
    /// (`held[k]` false), fitted to the tracks about the turntable's `axis`, the others held
    /// at `start` (one per pose, the turn since the first view). None when the tracks do not
    /// cover every view, cannot fix a missing one (too few observations in it) or do not
    /// follow the turn as they must follow a table's angles.
    pub(super) fn missing_angles_from_texture(&self, start: &[f64], held: &[bool], axis: (Vector3<f64>, Vector3<f64>)) -> Option<Vec<f64>> {
        let tracker = self.texture.tracker.as_ref().filter(|t| t.table_deg().len() == self.poses.len())?;
        let fit = fit_angles_to_tracks(tracker.observations(), start, held, tracker.camera(), axis, true, &self.params.bundle).map_err(|e| tracing::info!("texture tracks: no angles for the views without one ({e})")).ok()?;
        tracks_follow_turn(&fit.figures).then_some(fit.deg)
    }

    /// How many texture tracks the views so far have followed through three views or more
    /// (with table angles; over any turn, unlike the `bundle.min_span_deg` a fit of their own
    /// needs, so that the count means something from the first views on); 0 without tracking.
    pub(super) fn followed_tracks_so_far(&self) -> usize {
        let p = BundleParams { min_span_deg: 0.0, ..self.params.bundle.clone() };
        self.texture.tracker.as_ref().map_or(0, |t| usable_tracks(t.observations(), t.table_deg(), t.camera(), &p).len())
    }

    /// The registered chain's turn about direction `dir` since the first view, view by view
    /// (unwrapped), degrees: `first_from_view` turns by −θ about the axis.
    pub(super) fn chained_turn_deg(&self, dir: &Vector3<f64>) -> Vec<f64> {
        let mut chained = vec![0.0];
        for k in 1..self.poses.len() {
            let step = self.poses[k - 1].first_from_view.inverse() * self.poses[k].first_from_view;
            chained.push(chained[k - 1] - step.rotation.scaled_axis().dot(dir).to_degrees());
        }
        chained
    }

    /// In a scan with the table's angles, every view's: the turn the texture tracks give with
    /// every angle free ([`fit_angles_to_tracks`], from the registered chain's turn about
    /// `axis`, the axis free too), set beside the table's and the chain's; `sigma_deg`, the
    /// axis's uncertainty. None when a view has no angle or was not tracked, or the fit fails.
    pub(super) fn check_turn_with_texture(&self, axis: (Vector3<f64>, Vector3<f64>), sigma_deg: f64) -> Option<TurnCheck> {
        let tracker = self.texture.tracker.as_ref().filter(|t| t.table_deg().len() == self.poses.len())?;
        let first = self.poses.first()?.table_deg?;
        let table: Vec<f64> = self.poses.iter().map(|p| p.table_deg.map(|d| d - first)).collect::<Option<_>>()?;
        let chained = self.chained_turn_deg(&axis.1);
        let fit = fit_angles_to_tracks(tracker.observations(), &chained, &[], tracker.camera(), axis, false, &self.params.bundle).map_err(|e| tracing::info!("texture tracks: no turn of their own to check the table's with ({e})")).ok()?;
        // The fitted angles turn about the fitted direction, which stays on its start's side.
        let sign = fit.axis.1.dot(&axis.1).signum();
        let tracked: Vec<f64> = fit.deg.iter().map(|d| sign * (d - fit.deg[0])).collect();
        let follows = tracks_follow_turn(&fit.figures);
        let span = table.iter().copied().fold(f64::NEG_INFINITY, f64::max) - table.iter().copied().fold(f64::INFINITY, f64::min);
        let (from_table, from_registered, sides) = sides_with_table(&tracked, &table, &chained, follows, TRACKS_SIDE_RATIO * span.to_radians() * sigma_deg);
        let last = table.len() - 1;
        // The table's angles on the tracks' scale (signed as the tracks' angles).
        let scale = tracked.iter().zip(&table).map(|(t, a)| t * a).sum::<f64>() / table.iter().map(|a| a * a).sum::<f64>();
        let scaled: Vec<f64> = table.iter().map(|a| scale * a).collect();
        let scaled_rms_deg = rms_apart(&tracked, &scaled);
        let off = table[last] - tracked[last];
        // The whole turn's uncertainty, where the warning needs it (the turns differ by more
        // than the share): a delete-a-group jackknife over the tracks, eight more fits (13 s
        // more at the end of a 450-view scan, whose one fit takes 1.5 s).
        let suspect = follows && off.abs() > TABLE_SCALE_SHARE * table[last].abs();
        let tracked_sigma_deg = if suspect {
            let turns: Vec<f64> = (0..TURN_GROUPS)
                .filter_map(|g| {
                    let subset: Vec<TrackObs> = tracker.observations().iter().filter(|o| o.track as usize % TURN_GROUPS != g).copied().collect();
                    let f = fit_angles_to_tracks(&subset, &fit.deg, &[], tracker.camera(), fit.axis, false, &self.params.bundle).ok()?;
                    Some(f.axis.1.dot(&fit.axis.1).signum() * (f.deg[last] - f.deg[0]))
                })
                .collect();
            jackknife_sigma(&turns, TURN_GROUPS)
        } else {
            f64::NAN
        };
        let warning = (suspect && off.abs() > TABLE_SCALE_SIGMAS * tracked_sigma_deg).then(|| {
            format!(
                "the table's angles turn {:.1} % {} than the object's texture did ({:.2}° against {:.2}° ± {tracked_sigma_deg:.2}° from the first view to the last): the turntable's steps per degree (`$100`), or the recording's table_deg, may be on a wrong scale, or the table slipped",
                100.0 * off.abs() / tracked[last].abs(),
                if off.signum() == table[last].signum() { "more" } else { "less" },
                table[last],
                tracked[last]
            )
        });
        let check = TurnCheck {
            table_deg: table[last],
            registered_deg: chained[last],
            tracked_deg: tracked[last],
            tracked_sigma_deg,
            rms_from_table_deg: from_table,
            rms_from_registered_deg: from_registered,
            tracks_follow: follows,
            sides_with_table: sides,
            warning,
            table_scale: scale,
            scaled_rms_deg,
            // About the fitted direction: the tracks' angles unsigned.
            angles_deg: if scaled_rms_deg <= SCALED_TABLE_RMS_DEG { scaled.iter().map(|a| sign * a).collect() } else { fit.deg.iter().map(|d| d - fit.deg[0]).collect() },
            axis: fit.axis,
            applied: false,
        };
        tracing::info!(
            "texture tracks: their own turn {:.2}°{} first to last view, against the table's {:.2}° and the registered {:.2}° (views {from_table:.3}° and {from_registered:.3}° RMS from them; RMS {:.2} px): {}",
            check.tracked_deg,
            if tracked_sigma_deg.is_finite() { format!(" ± {tracked_sigma_deg:.2}°") } else { String::new() },
            check.table_deg,
            check.registered_deg,
            fit.figures.rms_px,
            if check.sides_with_table { "the table's angles stand" } else { "no verdict" }
        );
        Some(check)
    }

    /// A scan without the table's angles whose turn the tracks could not give: says why.
    fn no_tracked_turn(&mut self, why: String) {
        tracing::warn!("no angles from the texture tracks: {why}; the poses stay ICP's chain, which under-turns a smooth object");
        self.texture.note = Some(format!("no angles from the texture tracks: {why}"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every 2° over `n` views, times `scale`.
    fn turn(n: usize, scale: f64) -> Vec<f64> {
        (0..n).map(|k| 2.0 * k as f64 * scale).collect()
    }

    #[test]
    fn the_tracks_side_with_the_table_only_when_clearly_nearer_it_than_the_chain() {
        // The independent renderer's ideal 30 views: the chain under-turned to 56.23° of the
        // table's 58°, the tracks turned 58.19°.
        let (table, chain, tracks) = (turn(30, 1.0), turn(30, 56.23 / 58.0), turn(30, 58.19 / 58.0));
        let (t, c, sides) = sides_with_table(&tracks, &table, &chain, true, 0.23);
        assert!(sides && t < 0.15 && c > 1.0, "{t} {c}");
        // …not when the tracks stray from their own turn, nor when the chain lies within what
        // the axis's uncertainty explains.
        assert!(!sides_with_table(&tracks, &table, &chain, false, 0.23).2);
        assert!(!sides_with_table(&tracks, &table, &chain, true, 1.5).2);
        // A table 5 % over the truth (a simulated torus, 16 views): the tracks 30.26° and the
        // chain 29.88° of 30°, the table 31.5°; and the realistic rig's tracks 2 % over.
        let (table, chain) = (turn(16, 1.05), turn(16, 29.88 / 30.0));
        assert!(!sides_with_table(&turn(16, 30.26 / 30.0), &table, &chain, true, 0.0).2);
        assert!(!sides_with_table(&turn(16, 30.6 / 30.0), &table, &chain, true, 0.0).2);
        // Three turns that agree give no verdict on the turn.
        assert!(!sides_with_table(&table, &table, &table, true, 0.0).2);
    }

    #[test]
    fn the_jackknife_spreads_the_groups_estimates_by_the_groups_less_one() {
        assert_eq!(jackknife_sigma(&[30.0; 8], 8), 0.0);
        // Eight estimates ±0.1 about their mean: σ = √(7/8 · 8 · 0.01) = √0.07.
        let est = [30.1, 29.9, 30.1, 29.9, 30.1, 29.9, 30.1, 29.9];
        assert!((jackknife_sigma(&est, 8) - 0.07f64.sqrt()).abs() < 1e-9);
        // Fewer than half the groups fitted: unknown.
        assert!(jackknife_sigma(&est[..3], 8).is_nan());
        assert!(jackknife_sigma(&est[..4], 8).is_finite());
    }
}
