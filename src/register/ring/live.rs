//! The turntable's poses while the views come, without a calibrated axis.
//!
//! A chain of ICP steps carries every step's error into every later pose. Where the views'
//! points cannot fix the turn — a smooth, nearly symmetric object, faint texture, noisy
//! clouds — every step under-turns alike, and the published poses wander by a degree a view
//! (the independent renderer's faint, dim object: 10° off at the median, 20° at the end of a
//! 38° scan) while the turntable's poses at the end of the scan are 0.2–0.3° off. Those
//! poses feed the matchers' assisted search and the daemon's live model.
//!
//! So the refinement that [`Registrar::finish`] runs at the end of a scan
//! (`register::refine`: the axis fitted to every kept view's points at once, placed by the
//! table's angles) also runs while the views come, each time the kept views have doubled
//! (from [`LIVE_MIN_VIEWS`] over [`LIVE_MIN_SPAN_DEG`] of turn on). Its axis gives the
//! published poses when it passes the final poses' test ([`Registrar::verdict`]: no slip,
//! an axis known well enough or poses that fit the views as well as the registered ones —
//! or, on an object too faint to track, a chain that turned more than [`LIVE_TURN_GAP`]
//! apart from the table, whose closer fit is its under-turn's),
//! is known to within [`LIVE_MAX_SIGMA_DEG`], and — the first time — when the registered
//! poses have wandered from its poses well beyond what its uncertainty allows
//! ([`LIVE_WANDER_MARGIN`]): where the chain is as good, it stays. Then every view with a
//! table angle is published at the turntable's pose about that axis, and so is every later
//! view, as with a calibrated axis; when a later fit fails, or a single step disagrees with
//! the table's as a slip would ([`Registrar::check_live_step`]), the registered poses are
//! published again. The chain itself is left as registered: the block steps, loop closure
//! and the final test work on it, and the final poses are [`Registrar::finish`]'s.

use nalgebra::{Isometry3, Vector3};

use super::turntable::best_fit;
use super::Registrar;
use crate::register::posestore::ViewPose;
use crate::register::refine::{RefineSet, RefineView};
use crate::register::angle_deg;

/// Fewest kept views for a fit while the views come (the fit at the end needs 3; its σ, from
/// leaving one pair of views out, means little with fewer than six pairs).
pub(super) const LIVE_MIN_VIEWS: usize = 6;

/// Smallest turn the kept views span, degrees, before a fit while the views come: the
/// chain's own axis needs `axis_min_span_deg` (9°) to seed the fit at all.
pub(super) const LIVE_MIN_SPAN_DEG: f64 = 10.0;

/// Most kept views a fit while the views come takes (spread evenly over them), so that one
/// fit costs about what the fit over 24 views costs (0.1–0.2 s on a 2-core machine) however
/// long the scan: the views wait for it, and a continuous scan skips registering those that
/// waited too long.
pub(super) const LIVE_MAX_VIEWS: usize = 24;

/// The fit runs again each time the kept views have grown this many times over: at 6, 12,
/// 24, 48, … kept views, a handful of fits in a scan.
pub(super) const LIVE_REFIT_GROWTH: usize = 2;

/// Largest uncertainty (one σ of the direction, degrees) of an axis whose turntable poses are
/// published while the views come. A sphere's and a torus's first fits (±1.5–5.4°) still put
/// the views onto each other as well as the registered poses, and would have published poses
/// 6–10° off where the chain's were 1°.
pub(super) const LIVE_MAX_SIGMA_DEG: f64 = 1.0;

/// The first axis gives the published poses only where the registered poses lie further from
/// its poses (the median view) than this many times the furthest view's expected error of its
/// poses (the kept views' span, radians, times its direction's σ): where the chain has
/// wandered, not where it is about as good. Measured at the first fits: 7.6–27 × where the
/// chains had wandered 1–10° (the independent renderer's recordings, the simulated egg
/// ring), 2.0–2.4 × where they were 0.3° off (the simulated 19.6° toed-in rig, whose poses
/// a margin of 2 published 0.68° off against the chain's 0.31°; the independent 120 mm
/// toed-in rig, whose live poses a margin of 2 took from 0.33° to 0.09° — the margin's
/// price).
pub(super) const LIVE_WANDER_MARGIN: f64 = 3.0;

/// Share of the table's turn (first view to the last with an angle) by which the registered
/// chain's turn about the fitted axis must differ from it before the chain's closer fit of
/// the views stops counting against an uncertain axis while the views come — on an object
/// whose texture the tracker cannot follow ([`LIVE_MIN_TRACKS`]). Such a chain is ICP held
/// towards "no motion" by the clouds' camera-fixed errors, which also make its poses score
/// closer: on the independent renderer's faint, dim recording with `sgm` the chain had
/// turned 14.05° of the table's 22° (36 % short) at the twelfth view, with 7 tracks followed,
/// and scored 1.1 % closer (0.7 % with the build before, whose views differed by thousandths
/// of a millimetre), across the 1 % tie (`SCORE_TIE`). At the live fits of 25 other
/// recordings the chains lay 0–10 % from their tables on the textured ones (up to 16 % at a
/// first fit of six views), 19–37 % on faint or dim ones and 3–35 % on spheres, whose axes
/// the σ bound refuses (docs/registration.md, Known limits).
pub(super) const LIVE_TURN_GAP: f64 = 0.10;

/// Fewest texture tracks followed through three views or more (with table angles) for an
/// object whose texture can be followed: there the chain's closer score keeps its say against
/// a table its turn strays from ([`LIVE_TURN_GAP`]). A torus whose table angles read 12 % over
/// had its chain 19 % short of them, scoring 1.5 % closer, and it was right (212 tracks at
/// the twelfth view). Counted at the live fits of eight recordings: 64–157 at the first fit
/// of six views and 82–261 at the twelfth view on those with texture (a faint simulated egg
/// and a sphere among them, whose chains also stray: there the score and the σ bound decide,
/// as before); 51–57 on the dim JPEG recording; 6–7 on the faint, dim one. 30 is also the
/// default of `bundle.min_tracks`, the tracks a fit of their own needs; those must span 9°
/// besides, which none can at a first fit over 10°, so here they are counted over any turn.
pub(super) const LIVE_MIN_TRACKS: usize = 30;

/// Whether a chain that turned `chain_deg` strays from the table's `table_deg` (first view to
/// the last with an angle, either sign) by more than [`LIVE_TURN_GAP`] of the table's turn.
pub(super) fn chain_turn_strays(chain_deg: f64, table_deg: f64) -> bool {
    table_deg != 0.0 && (chain_deg.abs() - table_deg.abs()).abs() > LIVE_TURN_GAP * table_deg.abs()
}

impl Registrar {
    /// Fits the turntable's axis to the views kept so far when they have grown enough since
    /// the last fit (module docs), and keeps its poses for publication when they pass the
    /// final poses' test. Returns a note for the view's report when the published poses
    /// change from the registered ones to the turntable's or back.
    pub(super) fn refit_live_axis(&mut self) -> Option<String> {
        let (n, span) = (self.kept.len(), self.kept_span_deg());
        if self.params.calibrated_axis.is_some() || !self.params.turntable_poses || n < LIVE_MIN_VIEWS || n < LIVE_REFIT_GROWTH * self.live_fitted_views || !(span >= LIVE_MIN_SPAN_DEG) {
            return None;
        }
        self.live_fitted_views = n;
        let started = std::time::Instant::now();
        // At most LIVE_MAX_VIEWS of the kept views, spread evenly over them.
        let m = n.min(LIVE_MAX_VIEWS);
        let views: Vec<usize> = (0..m).map(|i| (i * (n - 1) + (m - 1) / 2) / (m - 1)).collect();
        let subset: Vec<RefineView> = views.iter().map(|&v| self.kept[v].clone()).collect();
        let Ok(set) = RefineSet::new(&subset, &self.kept_refine_params()) else { return None };
        // From the axis the last fit gave, else from every axis known (as at the end).
        let starts: Vec<(Vector3<f64>, Vector3<f64>)> = match self.live_axis {
            Some(axis) => vec![axis],
            None => self.axis.iter().map(|a| (a.point, a.dir)).chain(self.symmetry_axis).collect(),
        };
        let before = self.live_axis;
        let fit = best_fit(&set, &starts, &self.params.refine, &mut Vec::new());
        let (mut refused, mut typical, mut overruled) = (None, 0.0, None);
        self.live_axis = fit.and_then(|fit| {
            let scores = self.scores(&set, &fit, &views);
            let mut verdict = self.verdict((fit.point, fit.dir), "refined", Some(&fit), Some(scores), false)?;
            if verdict.axis_uncertain && self.followed_tracks_so_far() < LIVE_MIN_TRACKS {
                // A chain that turned far less (or more) than the table on an object whose
                // texture cannot be followed: its closer score is no reason against the
                // table's poses (LIVE_TURN_GAP); the other tests stand.
                if let Some((chain, table)) = self.chain_and_table_turn_deg(&fit.dir).filter(|&(c, t)| chain_turn_strays(c, t)) {
                    overruled = Some(format!("the registered chain turned {chain:.2}° against the table's {table:.2}° (more than {:.0} % apart) on an object too faint to track, so its closer fit of the views ({:.3} against {:.3} mm) does not keep it", LIVE_TURN_GAP * 100.0, scores.1, scores.0));
                    verdict = self.verdict((fit.point, fit.dir), "refined", Some(&fit), Some(scores), true)?;
                }
            }
            // How far the registered poses lie from the turntable's (median over the views),
            // against how far the turntable's may lie from the truth at the furthest view.
            let wander = self.wander_deg((fit.point, fit.dir));
            let expected = span.to_radians() * fit.sigma_dir_deg;
            typical = verdict.typical;
            let why = if let Some(why) = verdict.kept_because {
                Some(why)
            } else if !(fit.sigma_dir_deg <= LIVE_MAX_SIGMA_DEG) {
                Some(format!("the axis is known only to ±{:.3}° (more than {LIVE_MAX_SIGMA_DEG}°)", fit.sigma_dir_deg))
            } else if before.is_none() && !(wander >= LIVE_WANDER_MARGIN * expected) {
                Some(format!("the registered poses lie {wander:.3}° from its poses, less than {LIVE_WANDER_MARGIN} × the {expected:.3}° its poses may be off"))
            } else {
                None
            };
            tracing::debug!("live turntable fit over {n} views in {:.0} ms: ±{:.3}° over {:.1}°, the registered poses {wander:.3}° from its poses, scores {:.3} / {:.3} mm: {}", started.elapsed().as_secs_f64() * 1e3, fit.sigma_dir_deg, span, scores.0, scores.1, why.as_deref().unwrap_or("published"));
            refused = why.clone();
            why.is_none().then_some((fit.point, fit.dir))
        });
        self.live_typical_deg = typical;
        match (before, self.live_axis) {
            (None, Some(_)) => Some(format!("the turntable's poses about the axis fitted to {n} views so far are published from here on (the registered poses stay for the final test){}", overruled.map_or(String::new(), |why| format!(": {why}")))),
            (Some(_), None) => Some(format!("the registered poses are published again, as the axis fitted to {n} views so far does not pass: {}", refused.unwrap_or_else(|| "it could not be fitted, or compared with fewer than three steps".into()))),
            _ => None,
        }
    }

    /// After a new view's step: with an axis giving the published poses, a step that
    /// disagrees with the turntable's predicted step about it by more than
    /// `max_turntable_deviation_deg` beyond the typical step's disagreement at the last fit —
    /// the final test's sign of a slip — puts the registered poses back at once (the next fit
    /// decides again), so that a turntable that slipped, or an object that moved on it, costs
    /// the published poses no more than that view. Returns a note for the view's report.
    pub(super) fn check_live_step(&mut self) -> Option<String> {
        let off = self.step_off_deg(self.poses.len() - 1, &self.turntable_poses(self.live_axis?))?;
        let bound = self.live_typical_deg + self.params.max_turntable_deviation_deg;
        if off <= bound {
            return None;
        }
        self.live_axis = None;
        Some(format!("its step is {off:.2}° from the turntable's predicted step (more than {bound:.2}°): the table may have slipped or the object moved; the registered poses are published again"))
    }

    /// The registered chain's turn about `dir` and the table's, degrees, from the first view
    /// to the last view with a table angle; None without the first view's angle.
    fn chain_and_table_turn_deg(&self, dir: &Vector3<f64>) -> Option<(f64, f64)> {
        let first = self.poses.first()?.table_deg?;
        let (k, last) = self.poses.iter().enumerate().rev().find_map(|(k, p)| p.table_deg.map(|d| (k, d)))?;
        Some((self.chained_turn_deg(dir)[k], last - first))
    }

    /// The median angle, degrees, between a view's registered pose and its turntable pose
    /// about `axis` (the views with a table angle).
    fn wander_deg(&self, axis: (Vector3<f64>, Vector3<f64>)) -> f64 {
        let mut apart: Vec<f64> = self.turntable_poses(axis).iter().zip(&self.poses).filter_map(|(turned, p)| turned.map(|t| angle_deg(&(p.first_from_view.inverse() * t)))).collect();
        apart.sort_by(f64::total_cmp);
        apart.get(apart.len() / 2).copied().unwrap_or(0.0)
    }

    /// The poses published while the views come (to the pose store, and what a scan's live
    /// model and its `poses.jsonl` use until the end): the registered ones, or — with an axis
    /// from [`Registrar::refit_live_axis`] — the turntable's about it for every view with a
    /// table angle, and for a view without one its nearest earlier view's turntable pose
    /// moved by the registered motion between the two. After [`Registrar::finish`],
    /// [`Registrar::poses`] holds the final poses.
    pub fn published(&self) -> Vec<ViewPose> {
        let Some(axis) = self.live_axis else { return self.poses.clone() };
        let mut anchor: Option<(Isometry3<f64>, Isometry3<f64>)> = None;
        self.poses
            .iter()
            .zip(self.turntable_poses(axis))
            .map(|(p, turned)| {
                let pose = match (turned, anchor) {
                    (Some(turned), _) => {
                        anchor = Some((p.first_from_view, turned));
                        turned
                    }
                    (None, Some((registered, turned))) => turned * registered.inverse() * p.first_from_view,
                    (None, None) => p.first_from_view,
                };
                ViewPose { first_from_view: pose, ..p.clone() }
            })
            .collect()
    }
}
