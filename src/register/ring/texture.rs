//! The texture side of [`Registrar`]: the object's texture tracked from view to view while
//! the views come (`register::tracks`), and the axis fitted to those tracks at the end of the
//! scan (`register::bundle`), started from the axis fitted to the views' points.

use std::time::Instant;

use nalgebra::Vector3;

use super::Registrar;
use crate::register::bundle::fit_axis_to_tracks;
use crate::register::refine::AxisFit;
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
}

impl Registrar {
    /// Follows the object's texture into the view just registered by
    /// [`Registrar::add_view`] (`seq`: its rectified left image and disparity map), by the
    /// step registration found. Does nothing without a camera (`track_camera`), tracking
    /// settings or the view's table angle, or with a calibrated axis, which needs no tracks.
    /// Returns the time taken, ms.
    pub fn track_view(&mut self, seq: u64, image: TrackImage<'_>) -> f64 {
        let started = Instant::now();
        let (Some(camera), Some(params)) = (self.params.track_camera, self.params.tracks.as_ref()) else { return 0.0 };
        if self.params.calibrated_axis.is_some() {
            return 0.0;
        }
        let n = self.poses.len();
        let Some(last) = self.poses.last().filter(|p| p.seq == seq) else { return 0.0 };
        let Some(table_deg) = last.table_deg else { return 0.0 };
        // The step from the view tracked last: None (the tracks end) when a view between was
        // not tracked (no table angle).
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
}
