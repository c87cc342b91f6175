//! The texture side of [`Registrar`]: the object's texture tracked from view to view while
//! the views come (`register::tracks`), and the axis fitted to those tracks at the end of the
//! scan (`register::bundle`), started from the axis refined on the views' points.

use std::time::Instant;

use super::Registrar;
use crate::register::bundle::fit_axis_to_tracks;
use crate::register::refine::AxisFit;
use crate::register::tracks::{TrackImage, Tracker};

/// The tracks and what was fitted to them.
#[derive(Default)]
pub(super) struct Texture {
    tracker: Option<Tracker>,
    pub(super) fit: Option<AxisFit>,
    pub(super) error: Option<String>,
}

impl Registrar {
    /// Follows the object's texture into the view just registered by
    /// [`Registrar::add_view`] (its rectified left image and disparity map), by the step
    /// registration found. Does nothing without a camera, tracking settings or the view's
    /// table angle, or with a calibrated axis (which needs no tracks). Returns the time
    /// taken, ms.
    pub fn track_view(&mut self, seq: u64, image: TrackImage<'_>) -> f64 {
        let started = Instant::now();
        let (Some(camera), Some(params)) = (self.params.track_camera, self.params.tracks.as_ref()) else { return 0.0 };
        if self.params.calibrated_axis.is_some() {
            return 0.0;
        }
        let n = self.poses.len();
        let Some(last) = self.poses.last().filter(|p| p.seq == seq) else { return 0.0 };
        let Some(table_deg) = last.table_deg else { return 0.0 };
        let new_from_prev = (n >= 2).then(|| last.first_from_view.inverse() * self.poses[n - 2].first_from_view);
        let tracker = self.texture.tracker.get_or_insert_with(|| Tracker::new(camera, params.clone()));
        tracker.add(image, table_deg, new_from_prev.as_ref());
        started.elapsed().as_secs_f64() * 1e3
    }

    /// The axis fitted to the texture tracks by [`Registrar::finish`].
    pub fn tracked_axis(&self) -> Option<&AxisFit> {
        self.texture.fit.as_ref()
    }

    /// Fits the axis to the tracks, from the refined axis (else the estimated one).
    pub(super) fn fit_axis_to_texture(&mut self) {
        let Some(tracker) = &self.texture.tracker else { return };
        let Some(init) = self.refined.as_ref().map(|f| (f.point, f.dir)).or_else(|| self.axis.as_ref().map(|a| (a.point, a.dir))) else { return };
        let started = Instant::now();
        if let Ok(path) = std::env::var("SPINSCAN_DUMP_TRACKS") {
            let rows: Vec<String> = tracker.observations().iter().map(|o| format!("{} {} {} {} {}", o.track, o.view, o.x, o.y, o.d)).collect();
            let _ = std::fs::write(&path, rows.join("\n"));
            let _ = std::fs::write(format!("{path}.deg"), tracker.table_deg().iter().map(|d| d.to_string()).collect::<Vec<_>>().join("\n"));
        }
        let mut bp = self.params.bundle.clone();
        let init = match std::env::var("SS_INIT").ok().map(|v| v.split(',').map(|x| x.parse::<f64>().unwrap()).collect::<Vec<f64>>()) {
            Some(v) => (nalgebra::Vector3::new(v[0], v[1], v[2]), nalgebra::Vector3::new(v[3], v[4], v[5])),
            None => init,
        };
        let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
        if let Some(v) = env("SS_SIGMA_D") { bp.sigma_disparity_px = v; }
        if let Some(v) = env("SS_HUBER") { bp.huber = v; }
        if let Some(v) = env("SS_SPAN") { bp.min_span_deg = v; }
        match fit_axis_to_tracks(tracker.observations(), tracker.table_deg(), tracker.camera(), init, &bp) {
            Ok(fit) => {
                tracing::info!(
                    "texture tracks: the axis fitted to {} tracks ({} observations) in {:.1} s (direction ±{:.3}°, {:.3}° from the refined axis, RMS {:.2} px)",
                    fit.pairs,
                    fit.correspondences,
                    started.elapsed().as_secs_f64(),
                    fit.sigma_dir_deg,
                    fit.dir.angle(&init.1).to_degrees(),
                    fit.rms_mm
                );
                self.texture.fit = Some(fit);
            }
            Err(e) => {
                tracing::info!("texture tracks: no axis ({e})");
                self.texture.error = Some(e.to_string());
            }
        }
    }
}
