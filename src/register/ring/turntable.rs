//! The turntable side of [`Registrar`]: the views kept for the refinement, the refinement
//! itself (`register::refine`) from every axis known, and whether the turntable's poses
//! replace the registered ones.

use nalgebra::{Isometry3, Vector3};

use super::{Registrar, TurntableFit, MAX_KEPT};
use crate::register::refine::{AxisFit, RefineSet, RefineView};
use crate::register::{rotation_about_axis, subsample_indices};

impl Registrar {
    /// Keeps a subsample of view `k`'s points for the refinement.
    pub(super) fn keep_for_refinement(&mut self, k: usize, table_deg: Option<f64>, pts: &[[f32; 3]]) {
        let Some(table_deg) = table_deg else { return };
        if k % self.kept_stride != 0 {
            return;
        }
        let points = subsample_indices(pts.len(), self.params.refine_points).into_iter().map(|i| pts[i]).collect();
        self.kept.push(RefineView { table_deg, points });
        self.kept_index.push(k);
        if self.kept.len() > MAX_KEPT {
            // Every other view: those at multiples of the doubled stride.
            self.kept_stride *= 2;
            let stride = self.kept_stride;
            let keep: Vec<bool> = self.kept_index.iter().map(|&k| k % stride == 0).collect();
            let mut it = keep.iter();
            self.kept.retain(|_| *it.next().expect("one flag per view"));
            self.kept_index.retain(|&k| k % stride == 0);
        }
    }

    /// Fits the axis to every view at once (`register::refine`), from each axis known so far
    /// — the one estimated from the long steps, `extra` (the one from the chained poses), the
    /// symmetry axis ICP found — keeping the fit with the smallest residual. Not with a calibrated axis, nor without table angles. (Also
    /// with turntable poses off: the report still says how the poses compare.)
    pub(super) fn refine_axis(&mut self, extra: Option<(Vector3<f64>, Vector3<f64>)>) {
        if self.params.calibrated_axis.is_some() || self.kept.len() < 3 {
            return;
        }
        let started = std::time::Instant::now();
        // On an arc shorter than twice `pair_deg`, few views have a partner that far round:
        // the long pairs are taken half the arc apart instead (an egg turned 78°: its last
        // view 1.15° off with 60° pairs, 0.56° with 39°).
        let mut params = self.params.refine.clone();
        let span = self.kept.iter().map(|v| v.table_deg).fold(f64::NEG_INFINITY, f64::max) - self.kept.iter().map(|v| v.table_deg).fold(f64::INFINITY, f64::min);
        if span.is_finite() && span > 0.0 {
            params.pair_deg = params.pair_deg.min(span / 2.0);
        }
        let set = match RefineSet::new(&self.kept, &params) {
            Ok(set) => set,
            Err(e) => {
                self.refine_errors.push(e.to_string());
                return;
            }
        };
        let mut starts: Vec<(Vector3<f64>, Vector3<f64>)> = self.axis.iter().map(|a| (a.point, a.dir)).collect();
        // (A start within 0.01° and 0.1 mm of one already there would land on the same fit.)
        for axis in extra.into_iter().chain(self.symmetry_axis) {
            if !starts.iter().any(|(p, d)| d.angle(&axis.1).to_degrees() < 0.01 && (p - axis.0).norm() < 0.1) {
                starts.push(axis);
            }
        }
        let mut best: Option<AxisFit> = None;
        for start in starts {
            match set.fit_axis(start, &self.params.refine) {
                Ok(fit) if best.as_ref().is_none_or(|b| fit.rms_mm < b.rms_mm) => best = Some(fit),
                Ok(_) => {}
                Err(e) => self.refine_errors.push(e.to_string()),
            }
        }
        if let Some(fit) = &best {
            // The turntable's poses of the kept views against the registered ones, by one
            // measure.
            let first_deg = self.kept[0].table_deg;
            let first_index = self.kept_index[0];
            let base = self.poses[first_index].first_from_view;
            let turned: Vec<Isometry3<f64>> = self.kept.iter().map(|v| rotation_about_axis(&fit.point, &fit.dir, -(v.table_deg - first_deg))).collect();
            let registered: Vec<Isometry3<f64>> = self.kept_index.iter().map(|&k| base.inverse() * self.poses[k].first_from_view).collect();
            self.refine_scores = Some((set.score(&turned, &self.params.refine), set.score(&registered, &self.params.refine)));
            tracing::info!("turntable refinement: the axis fitted to {} views in {:.1} s (direction ±{:.3}°, fit RMS {:.2} mm)", self.kept.len(), started.elapsed().as_secs_f64(), fit.sigma_dir_deg, fit.rms_mm);
        }
        self.refined = best;
    }

    /// Compares every pose with the turntable's prediction and uses the predictions when every
    /// step agrees and the axis is calibrated, or refined to within `max_axis_sigma_deg`, or
    /// refined with poses that put the views onto each other better than the registered ones.
    pub(super) fn fit_turntable(&mut self) {
        let Some(first_deg) = self.poses.first().and_then(|p| p.table_deg) else { return };
        let (axis, source) = match (self.params.calibrated_axis, self.refined.as_ref()) {
            (Some(a), _) => (a, "calibrated"),
            (None, Some(f)) => ((f.point, f.dir), "refined"),
            (None, None) => {
                if self.params.turntable_poses && !self.refine_errors.is_empty() {
                    tracing::warn!("the turntable's axis could not be fitted to the views ({}): keeping the registered poses", self.refine_errors.join("; "));
                }
                return;
            }
        };
        let predicted: Vec<Option<Isometry3<f64>>> = self.poses.iter().map(|p| p.table_deg.map(|d| rotation_about_axis(&axis.0, &axis.1, -(d - first_deg)))).collect();
        let mut devs = Vec::new();
        for k in 1..self.poses.len() {
            if let (Some(step), Some(a), Some(b)) = (self.steps[k], predicted[k - 1], predicted[k]) {
                let predicted_step = a.inverse() * b;
                devs.push((self.poses[k].seq, (predicted_step.inverse() * step).rotation.angle().to_degrees()));
            }
        }
        if devs.len() < 3 {
            return;
        }
        let (worst_seq, max) = devs.iter().copied().fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a });
        let rms = (devs.iter().map(|d| d.1 * d.1).sum::<f64>() / devs.len() as f64).sqrt();
        let refined = if source == "refined" { self.refined.clone() } else { None };
        let kept_because = if !self.params.turntable_poses {
            Some("turntable poses are off".to_string())
        } else if let (Some(f), Some((turned, registered))) = (refined.as_ref().filter(|f| !(f.sigma_dir_deg <= self.params.max_axis_sigma_deg)), self.refine_scores.filter(|(t, r)| !(t < r))) {
            Some(format!("the turntable's axis is known only to ±{:.3}° (more than {:.3}°), and its poses put the views onto each other no better than the registered ones ({turned:.3} against {registered:.3} mm)", f.sigma_dir_deg, self.params.max_axis_sigma_deg))
        } else if source == "refined" && self.refine_scores.is_none() {
            Some("the turntable's poses could not be scored against the registered ones".to_string())
        } else if max > self.params.max_turntable_deviation_deg {
            Some(format!("the step to view {worst_seq} is {max:.2}° from the turntable's prediction (more than {:.2}°): the object may have moved on the table, or the table angles are off", self.params.max_turntable_deviation_deg))
        } else {
            None
        };
        let applied = kept_because.is_none();
        if applied {
            for (p, pred) in self.poses.iter_mut().zip(predicted) {
                if let Some(pred) = pred {
                    p.first_from_view = pred;
                }
            }
        } else if self.params.turntable_poses {
            tracing::warn!("{}; keeping the registered poses", kept_because.as_deref().unwrap_or_default());
        }
        let scores = if source == "refined" { self.refine_scores } else { None };
        self.turntable_fit = Some(TurntableFit { steps: devs.len(), rms_deviation_deg: rms, max_deviation_deg: max, worst_seq, applied, axis_source: source, refined, scores, kept_because });
    }
}
