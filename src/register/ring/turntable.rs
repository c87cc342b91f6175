//! The turntable side of [`Registrar`]: the views kept for the refinement, the refinement
//! itself (`register::refine`) from every axis known, and whether the turntable's poses
//! replace the registered ones.

use nalgebra::{Isometry3, Vector3};

use super::{Registrar, TurntableFit, MAX_KEPT};
use crate::register::refine::{AxisFit, RefineParams, RefineSet, RefineView, TrackFigures};
use crate::register::{angle_deg, rotation_about_axis, subsample_indices};

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
        let params = self.kept_refine_params();
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
        let mut best = best_fit(&set, &starts, &self.params.refine, &mut self.refine_errors);
        if let Some(fit) = &best {
            tracing::info!("turntable refinement: the axis fitted to {} views in {:.1} s (direction ±{:.3}°, fit RMS {:.2} mm)", self.kept.len(), started.elapsed().as_secs_f64(), fit.sigma_dir_deg, fit.rms_mm);
        }
        // The axis fitted to the texture tracks, started from the points' fit (else from the
        // axis estimated from the poses), replaces it when it is known to within
        // `max_axis_sigma_deg`, or at least as well as the points' fit: the points' fit
        // carries the stereo clouds' bias, which its σ does not hold.
        let start = best.as_ref().map(|f| (f.point, f.dir)).or_else(|| self.axis.as_ref().map(|a| (a.point, a.dir)));
        let points_deg = best.as_ref().map(|f| f.sigma_dir_deg);
        match start.and_then(|s| self.fit_axis_to_texture(s)) {
            Some(Ok(tracked)) if tracks_replace_points(tracked.sigma_dir_deg, points_deg, self.params.max_axis_sigma_deg) => self.texture.points_fit = best.replace(tracked),
            Some(Ok(tracked)) => {
                let rival = points_deg.map_or(String::new(), |p| format!(", and than the views' points' fit's ±{p:.3}° with its {POINTS_BIAS_DEG}° bias, ±{:.3}°", p.hypot(POINTS_BIAS_DEG)));
                let why = format!("the axis fitted to the texture tracks is known only to ±{:.3}° (more than {:.3}°{rival}): the axis fitted to the views' points is used", tracked.sigma_dir_deg, self.params.max_axis_sigma_deg);
                tracing::info!("{why}");
                self.texture.note = Some(why);
            }
            Some(Err(e)) => self.texture.note = Some(format!("no axis from the texture tracks: {e}")),
            None => {}
        }
        if let Some(fit) = &best {
            self.refine_scores = Some(self.scores(&set, fit, &(0..self.kept.len()).collect::<Vec<_>>()));
        }
        self.refined = best;
    }

    /// The refinement's settings for the kept views: on an arc shorter than twice
    /// `pair_deg`, few views have a partner that far round, so the long pairs are taken half
    /// the arc apart instead (an egg turned 78°: its last view 1.15° off with 60° pairs, 0.56°
    /// with 39°).
    pub(super) fn kept_refine_params(&self) -> RefineParams {
        let mut params = self.params.refine.clone();
        let span = self.kept_span_deg();
        if span.is_finite() && span > 0.0 {
            params.pair_deg = params.pair_deg.min(span / 2.0);
        }
        params
    }

    /// The arc the kept views' table angles span, degrees (−∞ with none).
    pub(super) fn kept_span_deg(&self) -> f64 {
        self.kept.iter().map(|v| v.table_deg).fold(f64::NEG_INFINITY, f64::max) - self.kept.iter().map(|v| v.table_deg).fold(f64::INFINITY, f64::min)
    }

    /// How well the turntable's poses about `fit`'s axis and the registered poses put the
    /// kept views `views` (indices into the kept ones, those `set` was built from) onto each
    /// other, by one measure ([`RefineSet::score`], mm): (turntable, registered).
    pub(super) fn scores(&self, set: &RefineSet, fit: &AxisFit, views: &[usize]) -> (f64, f64) {
        let first_deg = self.kept[views[0]].table_deg;
        let base = self.poses[self.kept_index[views[0]]].first_from_view;
        let turned: Vec<Isometry3<f64>> = views.iter().map(|&v| rotation_about_axis(&fit.point, &fit.dir, -(self.kept[v].table_deg - first_deg))).collect();
        let registered: Vec<Isometry3<f64>> = views.iter().map(|&v| base.inverse() * self.poses[self.kept_index[v]].first_from_view).collect();
        (set.score(&turned, &self.params.refine), set.score(&registered, &self.params.refine))
    }

    /// Compares every pose with the turntable's prediction and uses the predictions when every
    /// step agrees and the axis is calibrated, or refined to within `max_axis_sigma_deg`, or
    /// refined with poses that put the views onto each other as well as the registered ones
    /// (within [`SCORE_TIE`]).
    pub(super) fn fit_turntable(&mut self) {
        let Some(first_deg) = self.poses.first().and_then(|p| p.table_deg) else { return };
        let (axis, source) = match (self.params.calibrated_axis, self.refined.as_ref()) {
            (Some(a), _) => (a, "calibrated"),
            (None, Some(f)) => ((f.point, f.dir), if f.tracks.is_some() { "tracked" } else { "refined" }),
            (None, None) => {
                if self.params.turntable_poses && !self.refine_errors.is_empty() {
                    tracing::warn!("the turntable's axis could not be fitted to the views ({}): keeping the registered poses", self.refine_errors.join("; "));
                }
                return;
            }
        };
        let refined = if source != "calibrated" { self.refined.clone() } else { None };
        let scores = scores_of(source, self.refine_scores);
        // The texture tracks' own turn, beside the table's and the chain's (with a fitted
        // axis: a calibrated one tracks nothing). Where the axis is uncertain and the
        // registered poses score a little better, it says whose angles to believe.
        let mut turn_check = refined.as_ref().and_then(|f| self.check_turn_with_texture(axis, f.sigma_dir_deg));
        let Some(mut verdict) = self.verdict(axis, source, refined.as_ref(), scores, turn_check.as_ref().is_some_and(|c| c.sides_with_table)) else { return };
        if let (true, Some(c)) = (verdict.axis_uncertain, &turn_check) {
            let why = verdict.kept_because.take().unwrap_or_default();
            verdict.kept_because = Some(format!("{why}; and the texture tracks' own turn, {:.2}° first to last view, does not side with the table's {:.2}° against the registered {:.2}° ({:.3}° and {:.3}° RMS from them{})", c.tracked_deg, c.table_deg, c.registered_deg, c.rms_from_table_deg, c.rms_from_registered_deg, if c.tracks_follow { "" } else { "; the tracks do not follow it closely enough" }));
        }
        let Verdict { steps, rms, max, worst_seq, mut kept_because, .. } = verdict;
        // Table angles that disagree with the texture's turn beyond its uncertainty (a wrong
        // scale, a slip): the tracks' turn gives the poses, as in a scan without angles.
        if let Some(c) = turn_check.as_mut().filter(|c| c.warning.is_some()) {
            let warning = c.warning.clone().unwrap_or_default();
            if self.params.turntable_poses {
                tracing::warn!("{warning}; the poses follow the texture's turn");
                for (p, deg) in self.poses.iter_mut().zip(&c.angles_deg) {
                    p.first_from_view = rotation_about_axis(&c.axis.0, &c.axis.1, -deg);
                }
                self.turned_deg = c.angles_deg.last().map_or(0.0, |d| d.abs());
                c.applied = true;
                kept_because = Some(match kept_because {
                    Some(why) => format!("{why}; and {warning}: the poses follow the texture's turn"),
                    None => format!("{warning}: the poses follow the texture's turn"),
                });
            } else {
                tracing::warn!("{warning}");
            }
        }
        let applied = kept_because.is_none();
        if applied {
            let mut turn: Vec<Option<f64>> = self.poses.iter().map(|p| p.table_deg.map(|d| d - first_deg)).collect();
            let held: Vec<bool> = turn.iter().map(Option::is_some).collect();
            if !held.iter().all(|h| *h) {
                // A view without an angle (a reading the turntable missed) turns from its
                // nearest view with one by the registered motion between them, about the axis:
                // left as registered, it kept the chain's wander (3.3° off, mid-scan, on the
                // independent renderer's recording with three angles removed). Then the
                // texture tracks, which went on through such a view, fit its angle.
                let known: Vec<usize> = (0..held.len()).filter(|&k| held[k]).collect();
                for k in (0..turn.len()).filter(|&k| !held[k]) {
                    if let Some(&j) = known.iter().min_by_key(|&&j| j.abs_diff(k)) {
                        let rel = self.poses[j].first_from_view.inverse() * self.poses[k].first_from_view;
                        turn[k] = turn[j].map(|t| t - rel.rotation.scaled_axis().dot(&axis.1).to_degrees());
                    }
                }
                let start: Vec<f64> = turn.iter().map(|t| t.unwrap_or(f64::NAN)).collect();
                if let Some(fitted) = self.missing_angles_from_texture(&start, &held, axis) {
                    turn = fitted.into_iter().map(Some).collect();
                }
            }
            for (p, t) in self.poses.iter_mut().zip(&turn) {
                if let Some(deg) = t {
                    p.first_from_view = rotation_about_axis(&axis.0, &axis.1, -deg);
                }
            }
        } else if self.params.turntable_poses && !turn_check.as_ref().is_some_and(|c| c.applied) {
            tracing::warn!("{}; keeping the registered poses", kept_because.as_deref().unwrap_or_default());
        }
        self.turntable_fit = Some(TurntableFit { steps, rms_deviation_deg: rms, max_deviation_deg: max, worst_seq, applied, axis_source: source, refined, scores, kept_because, turn_check });
    }

    /// Each view's turntable pose about `axis`: the first view turned by −(θ_k − θ_first).
    /// None for a view without a table angle (for every view when the first has none).
    pub(super) fn turntable_poses(&self, axis: (Vector3<f64>, Vector3<f64>)) -> Vec<Option<Isometry3<f64>>> {
        let first = self.poses.first().and_then(|p| p.table_deg);
        self.poses.iter().map(|p| first.zip(p.table_deg).map(|(first, deg)| rotation_about_axis(&axis.0, &axis.1, -(deg - first)))).collect()
    }

    /// How far, degrees, view `k`'s registered step lies from the turntable's step between
    /// the `predicted` poses ([`Registrar::turntable_poses`]) of views k − 1 and k; None where
    /// either has no table angle or the step was distrusted.
    pub(super) fn step_off_deg(&self, k: usize, predicted: &[Option<Isometry3<f64>>]) -> Option<f64> {
        let (step, a, b) = (self.steps[k]?, predicted[k.checked_sub(1)?]?, predicted[k]?);
        Some(angle_deg(&((a.inverse() * b).inverse() * step)))
    }

    /// How every registered step compares with the turntable's predicted step about `axis`
    /// (from `source`: "calibrated", "refined", "tracked"; `refined`, its fit; `scores`, its
    /// poses' and the registered ones', see [`Registrar::scores`]), and why its poses must
    /// not replace the registered ones, if they must not. `turn_confirmed`: the texture
    /// tracks' own turn sided with the table's ([`super::TurnCheck`]), so an uncertain axis is no
    /// reason. None with fewer than three steps to compare.
    pub(super) fn verdict(&self, axis: (Vector3<f64>, Vector3<f64>), source: &str, refined: Option<&AxisFit>, scores: Option<(f64, f64)>, turn_confirmed: bool) -> Option<Verdict> {
        let predicted = self.turntable_poses(axis);
        let devs: Vec<(u64, f64)> = (1..self.poses.len()).filter_map(|k| self.step_off_deg(k, &predicted).map(|d| (self.poses[k].seq, d))).collect();
        if devs.len() < 3 {
            return None;
        }
        let (worst_seq, max) = worst_step(&devs);
        let typical = typical_step(&devs);
        let rms = (devs.iter().map(|d| d.1 * d.1).sum::<f64>() / devs.len() as f64).sqrt();
        let uncertain = refined.and_then(|f| axis_too_uncertain(f.sigma_dir_deg, self.params.max_axis_sigma_deg, scores)).filter(|_| self.params.turntable_poses);
        let kept_because = if !self.params.turntable_poses {
            Some("turntable poses are off".to_string())
        } else if let Some(why) = uncertain.clone().filter(|_| !turn_confirmed) {
            Some(why)
        } else if source != "calibrated" && scores.is_none() {
            Some("the turntable's poses could not be scored against the registered ones".to_string())
        } else {
            // Texture tracks that follow the table's angles about their axis to a fraction of
            // a pixel have seen the object turn by those angles, whatever ICP made of its
            // steps (a ball's, a smooth blob's).
            let texture_follows_table = refined.and_then(|f| f.tracks).is_some_and(|t| tracks_follow_turn(&t));
            steps_disagree((worst_seq, max), typical, self.params.max_turntable_deviation_deg, scores, texture_follows_table)
        };
        Some(Verdict { steps: devs.len(), rms, max, typical, worst_seq, axis_uncertain: uncertain.is_some() && !turn_confirmed, kept_because })
    }
}

/// [`Registrar::verdict`]: the steps compared, their RMS, largest and median (typical)
/// disagreement with the turntable's predicted steps (degrees) and the view of the largest,
/// and why the turntable's poses must not replace the registered ones (None: they may);
/// `axis_uncertain`, when that is an axis known only to more than `max_axis_sigma_deg` with
/// registered poses that score better beyond the tie.
pub(super) struct Verdict {
    pub steps: usize,
    pub rms: f64,
    pub max: f64,
    pub typical: f64,
    pub worst_seq: u64,
    pub axis_uncertain: bool,
    pub kept_because: Option<String>,
}

/// The refinement from each of `starts`, keeping the fit with the smallest residual; the
/// fits that fail say why in `errors`.
pub(super) fn best_fit(set: &RefineSet, starts: &[(Vector3<f64>, Vector3<f64>)], p: &RefineParams, errors: &mut Vec<String>) -> Option<AxisFit> {
    let mut best: Option<AxisFit> = None;
    for &start in starts {
        match set.fit_axis(start, p) {
            Ok(fit) if best.as_ref().is_none_or(|b| fit.rms_mm < b.rms_mm) => best = Some(fit),
            Ok(_) => {}
            Err(e) => errors.push(e.to_string()),
        }
    }
    best
}

/// The texture tracks' RMS residual, pixels, up to which (with the worst view's, below)
/// their fit shows that the object turned by the table's angles: the tracked places' own
/// noise is ≈ 0.05–0.1 px on the simulated rigs; table angles on a wrong scale or an object
/// that moved leave residuals of pixels.
const TRACKS_FOLLOW_TABLE_PX: f64 = 0.5;
/// The bound on the worst view's median residual: 0.06–0.07 px on the simulated rings, 0.5 px
/// for an object that moved 2° on the table 40 mm from the axis (`register::bundle`'s test).
const TRACKS_VIEW_FOLLOWS_TABLE_PX: f64 = 0.3;

/// Whether texture tracks follow the turn they were fitted with (the table's angles, or
/// angles fitted to them) closely enough to show that the object turned so: both bounds
/// above, and every view after the first confirmed.
pub(super) fn tracks_follow_turn(t: &TrackFigures) -> bool {
    t.rms_px <= TRACKS_FOLLOW_TABLE_PX && t.worst_view_px <= TRACKS_VIEW_FOLLOWS_TABLE_PX && t.views_unconfirmed == 0
}

/// Why texture tracks fitted with angles of their own (every view confirmed) do not follow
/// that turn ([`tracks_follow_turn`]).
pub(super) fn tracks_stray(t: &TrackFigures) -> String {
    format!(
        "the texture tracks do not follow one turn about one axis closely enough (RMS {:.2} px, worst view's median {:.2} px; at most {TRACKS_FOLLOW_TABLE_PX} and {TRACKS_VIEW_FOLLOWS_TABLE_PX} px): the object may have moved on the table",
        t.rms_px, t.worst_view_px
    )
}

/// How much closer, as a share, the registered poses must put the views onto each other than
/// the turntable's poses (`RefineSet::score`) to be kept over them where the score decides.
/// Within it the two tie, and the table's angles — a measurement, where ICP on a nearly
/// symmetric object only repeats its seed — stand: the faint egg's registered poses, about
/// 6° under-turned, scored 1.497 against 1.501 mm (0.3 %) and 1.5047 against 1.5054 mm.
const SCORE_TIE: f64 = 0.01;

/// Whether the turntable's poses put the views onto each other as well as the registered
/// ones, within [`SCORE_TIE`] (scores: lower is better).
fn fits_as_well(turned: f64, registered: f64) -> bool {
    turned <= registered * (1.0 + SCORE_TIE)
}

/// The bias, degrees, that the views' points' fit carries beyond its σ: the stereo clouds'
/// own errors, which its jackknife does not see and the texture tracks do not share.
/// Measured as the points' axis's error where its σ was about the tracks': a vase at 5° a
/// frame 0.15° (σ 0.065°, the tracks' 0.05° off), partial arcs 0.17–0.68° off on four of
/// five, an independent renderer's realistic recording with `sgm` poses 0.144° off against
/// the tracks' 0.037° (σ 0.111° against 0.113°).
const POINTS_BIAS_DEG: f64 = 0.1;

/// Whether the axis fitted to the texture tracks (its direction's σ, degrees) replaces the
/// views' points' fit (its σ; None without one): when known to within `max_deg`, or at
/// least as well as the points' fit, its σ and [`POINTS_BIAS_DEG`] taken together.
fn tracks_replace_points(tracked_deg: f64, points_deg: Option<f64>, max_deg: f64) -> bool {
    tracked_deg <= max_deg.max(points_deg.map_or(0.0, |p| p.hypot(POINTS_BIAS_DEG)))
}

/// Why a refined axis must not give the poses because it is known only to more than
/// `max_deg` (`sigma_deg`, degrees), or None: it must not when its poses put the views onto
/// each other worse than the registered ones, beyond [`SCORE_TIE`] (`scores`: turntable,
/// registered). Without scores the caller says so itself. (Texture tracks that follow the
/// table do not overrule this: with table angles 5 % too large, a torus's tracks still
/// fitted them to 0.09 px RMS — the tracked points sit closer to the axis — while its
/// registered poses scored 2 % better, and were 0.12° off against the turntable's 1.0°.)
fn axis_too_uncertain(sigma_deg: f64, max_deg: f64, scores: Option<(f64, f64)>) -> Option<String> {
    let (turned, registered) = scores?;
    (!(sigma_deg <= max_deg) && !fits_as_well(turned, registered)).then(|| format!("the turntable's axis is known only to ±{sigma_deg:.3}° (more than {max_deg:.3}°), and the registered poses put the views onto each other more than {:.0} % closer than its poses ({registered:.3} against {turned:.3} mm)", SCORE_TIE * 100.0))
}

/// The step (`(seq, degrees)`) that disagrees most with the turntable's prediction.
fn worst_step(devs: &[(u64, f64)]) -> (u64, f64) {
    devs.iter().copied().fold((0, 0.0), |a, b| if b.1 > a.1 { b } else { a })
}

/// The typical step's disagreement with the turntable's prediction: the median of `devs`
/// (`(seq, degrees)`, at least one).
fn typical_step(devs: &[(u64, f64)]) -> f64 {
    let mut sorted: Vec<f64> = devs.iter().map(|d| d.1).collect();
    sorted.sort_by(f64::total_cmp);
    sorted[sorted.len() / 2]
}

/// The refinement's scores (turntable, registered) when the axis was fitted at the end of
/// the scan (to the views' points or to the texture tracks).
fn scores_of(source: &str, scores: Option<(f64, f64)>) -> Option<(f64, f64)> {
    if source != "calibrated" {
        scores
    } else {
        None
    }
}

/// Why the turntable's poses must not replace the registered ones, judged from the steps'
/// disagreement with the turntable's predicted steps (`(worst_seq, worst)`, the largest;
/// `typical`, the median: [`worst_step`], [`typical_step`]), or None. A slip — the
/// object moved on the table — shows as a step that disagrees by more than `max_deg` beyond
/// the typical (median) step, and leaves the turntable's poses fitting the views worse than
/// the registered ones: the views after it are turned away from those before. Where the
/// turntable's poses fit the views as well, within [`SCORE_TIE`], that step is ICP's failure
/// (a smooth object's step registered wrong by two degrees, the later ones right), not the
/// table's. All steps disagreeing alike is not a slip: a nearly symmetric
/// object's steps all under-turn (ICP cannot see its turn), and so would table angles on the
/// wrong scale; the turntable's poses are then used only when they put the views onto each
/// other as well as the registered ones, within [`SCORE_TIE`] (`scores`: turntable, registered — never with a
/// calibrated axis, which has none).
/// `texture_follows_table`: the texture tracks fitted the table's angles about the axis in
/// every view (see [`TRACKS_FOLLOW_TABLE_PX`]): the object turned by those angles, so steps
/// that disagree — all of them, or one — are ICP's failure (a ball, the first steps before
/// the axis seeds ICP), not the table's, nor a slip.
fn steps_disagree((worst_seq, worst): (u64, f64), typical: f64, max_deg: f64, scores: Option<(f64, f64)>, texture_follows_table: bool) -> Option<String> {
    if texture_follows_table {
        return None;
    }
    if worst - typical > max_deg {
        let step = format!("the step to view {worst_seq} is {worst:.2}° from the turntable's prediction, {:.2}° more than the typical step's {typical:.2}° (more than {max_deg:.2}°)", worst - typical);
        return match scores {
            Some((turned, registered)) if fits_as_well(turned, registered) => None,
            Some((turned, registered)) => Some(format!("{step}, and the registered poses put the views onto each other more than {:.0} % closer than its poses ({registered:.3} against {turned:.3} mm): the object may have moved on the table", SCORE_TIE * 100.0)),
            None => Some(format!("{step}: the object may have moved on the table")),
        };
    }
    if typical > max_deg {
        return match scores {
            Some((turned, registered)) if fits_as_well(turned, registered) => None,
            Some((turned, registered)) => Some(format!("the steps are typically {typical:.2}° from the turntable's prediction (more than {max_deg:.2}°), and the registered poses put the views onto each other more than {:.0} % closer than its poses ({registered:.3} against {turned:.3} mm): the table angles may be off", SCORE_TIE * 100.0)),
            None => Some(format!("the steps are typically {typical:.2}° from the turntable's prediction (more than {max_deg:.2}°): the table angles or the calibrated axis may be off")),
        };
    }
    None
}

#[cfg(test)]
mod tests {
    /// [`super::steps_disagree`] with the worst and typical steps found as `verdict` finds them.
    fn steps_disagree(devs: &[(u64, f64)], max_deg: f64, scores: Option<(f64, f64)>) -> Option<String> {
        super::steps_disagree(super::worst_step(devs), super::typical_step(devs), max_deg, scores, false)
    }

    #[test]
    fn a_slip_is_one_step_off_and_a_symmetric_object_all_of_them() {
        let calm: Vec<(u64, f64)> = (1..40).map(|k| (k, 0.1 + 0.01 * (k % 5) as f64)).collect();
        assert_eq!(steps_disagree(&calm, 1.5, None), None);
        // One step 3° off: a slip where the registered poses fit the views better (a torus
        // whose table slipped 2°: 1.361 against 1.462 mm) or nothing says how they fit…
        let mut slipped = calm.clone();
        slipped[20].1 = 3.0;
        let why = steps_disagree(&slipped, 1.5, Some((1.462, 1.361))).unwrap();
        assert!(why.contains("view 21") && why.contains("1 % closer") && why.contains("moved on the table"), "{why}");
        assert!(steps_disagree(&slipped, 1.5, None).unwrap().contains("moved on the table"));
        // …but ICP's failure where the turntable's poses fit them as well (a smooth object's
        // first step registered 1.8° wrong: 0.814 against 0.818 mm).
        assert_eq!(steps_disagree(&slipped, 1.5, Some((0.814, 0.818))), None);
        assert_eq!(steps_disagree(&slipped, 1.5, Some((1.0, 0.995))), None);
        // Every step under-turned by about 1.6° (a nearly symmetric object): the turntable's
        // poses when they fit the views better, not when they fit them worse, nor without a
        // score to tell.
        let under: Vec<(u64, f64)> = (1..40).map(|k| (k, 1.55 + 0.01 * (k % 5) as f64)).collect();
        assert_eq!(steps_disagree(&under, 1.5, Some((1.40, 1.62))), None);
        assert!(steps_disagree(&under, 1.5, Some((1.70, 1.62))).unwrap().contains("1 % closer"));
        // Within 1 % the two tie, and the table's angles stand.
        assert_eq!(steps_disagree(&under, 1.5, Some((1.63, 1.62))), None);
        assert!(steps_disagree(&under, 1.5, None).unwrap().contains("typically"));
        // Texture tracks that followed the table's angles in every view overrule the steps:
        // under-turned ones (a ball: ICP sees no turn) and a single wrong one alike.
        assert_eq!(super::steps_disagree(super::worst_step(&under), super::typical_step(&under), 1.5, Some((1.70, 1.62)), true), None);
        assert_eq!(super::steps_disagree(super::worst_step(&slipped), super::typical_step(&slipped), 1.5, None, true), None);
    }

    #[test]
    fn the_better_known_axis_is_used_and_an_uncertain_one_only_where_its_poses_fit_as_well() {
        use super::{axis_too_uncertain, tracks_replace_points};
        // The tracks' axis: within the limit, or no less certain than the points' fit.
        assert!(tracks_replace_points(0.04, Some(0.02), 0.05));
        assert!(tracks_replace_points(0.056, Some(0.065), 0.05));
        // About as well as the points' σ: the tracks (0.113° against 0.111°, the tracks'
        // poses 0.037° off, the points' 0.144°); clearly less well: the points.
        assert!(tracks_replace_points(0.113, Some(0.111), 0.05));
        assert!(!tracks_replace_points(0.355, Some(0.132), 0.05));
        assert!(!tracks_replace_points(0.15, Some(0.05), 0.05));
        assert!(!tracks_replace_points(0.06, None, 0.05));
        assert!(!tracks_replace_points(f64::NAN, Some(0.1), 0.05));
        // An axis known to more than the limit gives no poses that fit the views more than
        // 1 % worse than the registered ones (a torus under table angles 5 % too large:
        // 1.396 against 1.367 mm)…
        let why = axis_too_uncertain(0.058, 0.05, Some((1.396, 1.367))).unwrap();
        assert!(why.contains("±0.058°") && why.contains("1 % closer"), "{why}");
        assert!(axis_too_uncertain(f64::NAN, 0.05, Some((1.396, 1.367))).is_some());
        // …but does when they fit better or tie (a vase at 5° a frame: 1.310 against 1.309),
        // or when it is known well enough; without scores this rule has nothing to say.
        assert_eq!(axis_too_uncertain(0.056, 0.05, Some((1.30, 1.309))), None);
        assert_eq!(axis_too_uncertain(0.056, 0.05, Some((1.310, 1.309))), None);
        assert_eq!(axis_too_uncertain(0.04, 0.05, Some((1.396, 1.367))), None);
        assert_eq!(axis_too_uncertain(0.056, 0.05, None), None);
    }
}
