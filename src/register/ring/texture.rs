//! The texture side of [`Registrar`]: the object's texture tracked from view to view while
//! the views come (`register::tracks`), and the axis fitted to those tracks at the end of the
//! scan (`register::bundle`), started from the axis fitted to the views' points. In a scan
//! without the table's angles, the angles too (`register::angles`).

use std::time::Instant;

use nalgebra::Vector3;

use super::turntable::{tracks_follow_turn, tracks_stray};
use super::Registrar;
use crate::register::angles::fit_angles_to_tracks;
use crate::register::bundle::fit_axis_to_tracks;
use crate::register::refine::{AxisFit, TrackFigures};
use crate::register::rotation_about_axis;
use crate::register::tracks::{TrackImage, Tracker};
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
        // The chain's turn about the axis, view by view (unwrapped): first_from_view turns by
        // −θ about the axis.
        let mut chained = vec![0.0];
        for k in 1..self.poses.len() {
            let step = self.poses[k - 1].first_from_view.inverse() * self.poses[k].first_from_view;
            chained.push(chained[k - 1] - step.rotation.scaled_axis().dot(&start.1).to_degrees());
        }
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

    /// A scan without the table's angles whose turn the tracks could not give: says why.
    fn no_tracked_turn(&mut self, why: String) {
        tracing::warn!("no angles from the texture tracks: {why}; the poses stay ICP's chain, which under-turns a smooth object");
        self.texture.note = Some(format!("no angles from the texture tracks: {why}"));
    }
}
