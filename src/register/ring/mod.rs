//! Registering a sequence of views: block registration (the paper's Algorithm 1), the
//! turntable seed, the running model, and loop closure.
//!
//! ## How Algorithm 1 is read
//! The paper registers m consecutive sets S_i … S_{i+m−1} at a time. S_i is first moved by
//! the transform carried over from before the block; each following set S_{i+j} is moved by
//! the chain of transforms found so far and then registered by ICP to S_{i+j−1}, which is
//! already in place. Moving a set by the chain so far and then registering it to its
//! predecessor is the same as registering it to its predecessor *in its own frame* starting
//! from the predecessor's pose, and composing — which is what [`Registrar::add_view`] does for
//! every view (`first_from_view(k) = first_from_view(k−1) · ICP(view k → view k−1)`), so the
//! chain never re-transforms stored clouds.
//!
//! What the block adds: once m views are chained, the block — the union of their clouds, now
//! in the first view's frame — is registered as one rigid set to the model built from every
//! view before it, and the correction is applied to all m poses. A larger m costs more per
//! block and gives ICP more overlapping surface; that is the paper's "computation and
//! correctness both grow with m". m = 1 registers every view to the model too.
//!
//! ## Seeds
//! ICP starts from the identity (the paper: consecutive views differ little) until the
//! turntable's axis is known — calibrated (`turntable.yaml` of the recording) or estimated
//! from the poses so far (after `axis_min_span_deg` of rotation) — and both views carry
//! `table_deg`; from then on it starts from the table's step about that axis. When the
//! surface cannot fix a rotation (a surface of revolution about the axis), ICP keeps the
//! seed along it and the view's report carries the warning.
//!
//! With a calibrated axis and the table's angles, a view's pose is the turntable's (the
//! table's angle about that axis), published at once; ICP still runs (its steps feed the
//! final check between the turntable's poses and the registered ones, and the seeds of
//! views without an angle), and the block step leaves such views alone: they have no drift.
//! Without a calibration, an axis fitted to the views so far gives the published poses the
//! same way once it passes the final poses' test (`live.rs`); the chain stays as registered.
//!
//! ## Per-view cost
//! Every view is registered as it comes, within a camera's frame period: its target (the
//! chain's next step, the long steps, and the model in the block step, seen from the
//! block's last view) is a range grid paired by projection (`register::grid`), built in one
//! pass, instead of a k-d tree per view; ICP takes 4000 source points and at most 12
//! iterations. The pose is published after the chain step; the long and block steps refine
//! it afterwards. Loop closure and the turntable refinement run once, at the end, on exact
//! nearest neighbours. `RegistrationParams::projective = false` restores exact search
//! (`register::cells`) for the per-view targets too.
//!
//! ## Loop closure
//! When the views complete a turn (the last view within 1.5 steps of 360° from the first),
//! [`Registrar::finish`] registers the closing views directly to the opening ones — the union
//! of the last `loop_views` views (placed relative to the last by the chain) onto the union of
//! the first `loop_views` — and spreads the disagreement between that edge and the chain over
//! the ring's edges in proportion to each edge's variance (RMSE² over overlap) — the
//! closed-form optimum of a single-cycle pose graph, to first order; with equal variances
//! view k of N gets k/N of the correction. The default is
//! one view a side; more give ICP more surface but carry the chain's own errors within each
//! side (on simulated scans they did not help).
//!
//! ## Turntable poses (`turntable.rs`)
//! With table angles recorded, every view's pose is also predicted by the turntable: a turn
//! of −(θ_k − θ_first) about the axis — calibrated, or, without a calibration, fitted to every
//! view at once at the end of the scan (`register::refine`, started from the axis estimated
//! from the poses and from ICP's symmetry axis) and then to the object's texture tracked from
//! view to view (`texture.rs`: `register::tracks`, `register::bundle`), whose axis replaces
//! the points' fit when it is known to within `max_axis_sigma_deg`, or at least as well as the
//! points' fit. Stereo views register to each other only to
//! about 0.1°–0.4° per pair on the simulated rig (the clouds' own errors: Open3D lands in the
//! same place), and the chain wanders by up to a degree mid-ring, while the refined axis is
//! good to a few hundredths of a degree. So [`Registrar::finish`] replaces the poses with the
//! predictions when no pairwise registration disagrees with the turntable's predicted step by
//! more than `max_turntable_deviation_deg` beyond the typical step's disagreement — nothing
//! slipped — or one does but the turntable's poses put the views onto each other as well as
//! (within 1 %) the registered ones — ICP lost that step, the object did not move — and the
//! typical step agrees to that bound too, or (a nearly symmetric object,
//! whose steps all under-turn) the turntable's poses put the views onto each other as well as (within 1 %)
//! the registered ones; and the axis is calibrated, or refined to within
//! `max_axis_sigma_deg`, or refined with poses that put the views onto each other as well as (within 1 %)
//! the registered ones; otherwise it keeps the registered poses and says why. (Steps, not
//! whole poses, are compared: a slip shows as one step that disagrees, while the chain's slow
//! wander would fail a whole-pose test on good data.) Texture tracks that follow the table's
//! angles about their axis in every view show that the object turned by those angles: the
//! turntable's poses are then used whatever ICP's steps say (a ball, which ICP cannot see
//! turn); an object that moved on the table shows in the tracks of the views after it.
//!
//! ## Without the table's angles (`texture.rs`, `register::angles`)
//! A recording may have none (`table_deg` null). Then ICP's steps start from the identity
//! and solve even the motions the surfaces fix only weakly ([`without_angles`]); every view
//! is tracked; and at the end the tracks give each view's angle and the axis, fitted
//! together from the chain's turn. When the tracks follow that turn as closely as they must
//! follow a table's angles (above), the poses become those turns — and a whole turn, which
//! the under-turning chain never reached, can close its loop. In a scan with angles, a view
//! whose reading is missing is tracked through (its angle NaN to the axis's fits) and, when
//! the turntable's poses apply, gets its angle from the tracks with the others held, or
//! else its nearest neighbour's plus the registered motion between them.

use std::time::Instant;

use nalgebra::{Isometry3, Vector3};

use super::axis::{estimate_axis, explained_degeneracy, AxisEstimate};
use super::icp::{icp, IcpResult, Target};
use super::posestore::{PoseStore, ViewPose};
use super::refine::{AxisFit, RefineView};
use super::voxel::VoxelModel;
pub use super::loops::{distribute_loop_error, distribute_loop_error_weighted, edge_variance, register_ring, RingEdge, RingResult};
use super::grid::RangeGrid;
use super::{rotation_about_axis, subsample_indices, RegisterError};
use crate::cloud::PointCloud;
use weak::{screw_line, without_angles, MAX_SYMMETRY_TESTS, SOLVED_TURN_LINE_DEG, WEAK_FIT_GAIN, WEAK_FIT_MIN_FITNESS};
pub use params::RegistrationParams;
pub use texture::{TrackedTurn, TurnCheck};

mod closing;
mod live;
mod params;
#[cfg(test)]
mod tests;
mod texture;
mod turntable;
mod weak;

/// How one view was registered.
#[derive(Debug, Clone)]
pub struct ViewRegistration {
    pub seq: u64,
    /// As published when the view arrived: registered, or the turntable's pose (`live.rs`);
    /// later block steps, fits and loop closure refine it ([`Registrar::poses`] has the
    /// registered chain, and after [`Registrar::finish`] the final poses).
    pub first_from_view: Isometry3<f64>,
    /// ICP of this view onto the previous one (None for the first view).
    pub icp: Option<IcpResult>,
    /// `"none"` (first view), `"identity"` or `"turntable"`.
    pub seed: &'static str,
    /// A block of m views ended here and was registered to the model.
    pub block: Option<IcpResult>,
    pub register_ms: f64,
    /// From the call to the first publication of the view's pose (chained, before the long
    /// and block steps refine it).
    pub publish_ms: f64,
    /// Where the time went, ms.
    pub split: RegisterSplit,
    /// Conditions that make the result doubtful.
    pub warnings: Vec<String>,
    /// Expected conditions of the set-up, handled (e.g. an object of revolution whose free
    /// turn the guess supplies): worth a line in the report, not a warning.
    pub notes: Vec<String>,
}

/// The time of one view's registration by stage, ms: indexing the view as a target, ICP
/// onto the previous view (with any second try from the turntable's step), the long step for
/// the axis, and the block step onto the model. The pose is published after `chain_ms`.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct RegisterSplit {
    pub prepare_ms: f64,
    pub chain_ms: f64,
    pub long_ms: f64,
    pub block_ms: f64,
}

/// How well the registered poses agree with the turntable's predictions.
#[derive(Debug, Clone)]
pub struct TurntableFit {
    /// Steps between views that both have a table angle and a trusted registration.
    pub steps: usize,
    pub rms_deviation_deg: f64,
    pub max_deviation_deg: f64,
    /// The view whose step from the one before disagrees most.
    pub worst_seq: u64,
    /// The predictions replaced the registered poses.
    pub applied: bool,
    /// "calibrated", "refined" (fitted to every view's points at the end of the scan) or
    /// "tracked" (fitted to the texture tracks then).
    pub axis_source: &'static str,
    /// The fitted axis's uncertainty and fit (None with a calibrated axis).
    pub refined: Option<AxisFit>,
    /// How well the refined axis's turntable poses and the registered poses put the views
    /// onto each other, mm (lower is better): (turntable, registered).
    pub scores: Option<(f64, f64)>,
    /// Why the predictions were not applied (None when they were).
    pub kept_because: Option<String>,
    /// The texture tracks' own turn beside the table's and the chain's (a fitted axis, tracks).
    pub turn_check: Option<TurnCheck>,
}

/// The outcome of loop closure.
#[derive(Debug, Clone)]
pub struct LoopClosure {
    /// Views in the ring.
    pub views: usize,
    /// Disagreement between the chain and the direct last→first registration.
    pub error_deg: f64,
    pub error_translation: f64,
    pub icp: IcpResult,
}

struct Stored {
    seq: u64,
    table_deg: Option<f64>,
    target: Target,
}

/// Registers views one at a time (see the module docs) and publishes poses to a store.
pub struct Registrar {
    params: RegistrationParams,
    store: std::sync::Arc<PoseStore>,
    poses: Vec<ViewPose>,
    prev: Option<Stored>,
    /// Sub-sampled points of the first and of the latest `loop_views` views (index into
    /// poses, points in their own frame), for loop closure.
    opening: Vec<(usize, Vec<[f32; 3]>)>,
    closing: std::collections::VecDeque<(usize, Vec<[f32; 3]>)>,
    /// Views of the current block: (index into poses, subsampled points in their own frame).
    block: Vec<(usize, Vec<[f32; 3]>)>,
    model: VoxelModel,
    axis: Option<AxisEstimate>,
    reference: Vector3<f64>,
    turned_deg: f64,
    turntable_fit: Option<TurntableFit>,
    /// Recent views as ICP targets for the long steps: (index into poses, table angle, target).
    history: std::collections::VecDeque<(usize, Option<f64>, Target)>,
    /// Long steps `earlier_from_view` with their table-angle differences.
    long_steps: Vec<(Isometry3<f64>, Option<f64>)>,
    /// The symmetry axis of a surface of revolution, found by ICP's degeneracy.
    symmetry_axis: Option<(Vector3<f64>, Vector3<f64>)>,
    /// The line (point, direction) the last step that solved a weak turn turned about: near
    /// the table's axis, which stands still in the camera's frame (see `add_view`).
    turn_line: Option<(Vector3<f64>, Vector3<f64>)>,
    /// `prev_from_view` found by ICP for each view (None: first view, or ICP distrusted).
    steps: Vec<Option<Isometry3<f64>>>,
    /// [`edge_variance`] of each view's step (first view: unused).
    step_variance: Vec<f64>,
    /// Subsampled points of the views with a table angle, for the refinement: every
    /// `kept_stride`-th view (the stride doubles when too many are kept, so memory stays
    /// bounded on long scans).
    kept: Vec<RefineView>,
    kept_index: Vec<usize>,
    kept_stride: usize,
    /// The axis fitted to every view by [`Registrar::finish`], and the error of the fits
    /// tried from every starting axis.
    refined: Option<AxisFit>,
    refine_errors: Vec<String>,
    /// How well the refined axis's turntable poses and the registered poses put the views
    /// onto each other ([`RefineSet::score`], mm): (turntable, registered).
    refine_scores: Option<(f64, f64)>,
    /// Steps whose free rotation was looked at with exact pairs so far.
    symmetry_tests: usize,
    /// The axis fitted while the views come whose turntable poses are published (`live.rs`),
    /// and the kept views it was last fitted to.
    live_axis: Option<(Vector3<f64>, Vector3<f64>)>,
    live_fitted_views: usize,
    /// The typical step's disagreement with the turntable's at the last fit, degrees.
    live_typical_deg: f64,
    texture: texture::Texture,
}

/// `t` with its rotation renormalised: chained products drift from unit length (by ≈ 1e-8 a
/// view here), and a pose whose matrix is not orthonormal to 1e-6 is refused when read back.
fn unit(mut t: Isometry3<f64>) -> Isometry3<f64> {
    t.rotation = nalgebra::UnitQuaternion::new_normalize(t.rotation.into_inner());
    t
}

/// Most views kept for the refinement.
const MAX_KEPT: usize = 360;

impl Registrar {
    pub fn new(params: RegistrationParams, store: std::sync::Arc<PoseStore>) -> Registrar {
        let model = VoxelModel::new(params.model_voxel);
        Registrar { params, store, poses: Vec::new(), prev: None, opening: Vec::new(), closing: std::collections::VecDeque::new(), block: Vec::new(), model, axis: None, reference: Vector3::zeros(), turned_deg: 0.0, turntable_fit: None, history: std::collections::VecDeque::new(), long_steps: Vec::new(), symmetry_axis: None, turn_line: None, steps: Vec::new(), step_variance: Vec::new(), kept: Vec::new(), kept_index: Vec::new(), kept_stride: 1, refined: None, refine_errors: Vec::new(), refine_scores: None, symmetry_tests: 0, live_axis: None, live_fitted_views: 0, live_typical_deg: 0.0, texture: Default::default() }
    }

    /// The latest pose of every view: while views come the registered chain (what is
    /// published may be the turntable's poses instead: [`Registrar::published`]), after
    /// [`Registrar::finish`] the final poses.
    pub fn poses(&self) -> &[ViewPose] {
        &self.poses
    }

    /// The comparison with the turntable's predictions made by [`Registrar::finish`].
    pub fn turntable_fit(&self) -> Option<&TurntableFit> {
        self.turntable_fit.as_ref()
    }

    /// The axis estimated from the poses so far.
    pub fn estimated_axis(&self) -> Option<&AxisEstimate> {
        self.axis.as_ref()
    }

    /// The axis fitted to every view by [`Registrar::finish`] (no calibrated axis, table
    /// angles recorded).
    pub fn refined_axis(&self) -> Option<&AxisFit> {
        self.refined.as_ref()
    }

    /// Degrees turned since the first view (from table angles when recorded, else summed
    /// from the registered motion).
    pub fn turned_deg(&self) -> f64 {
        self.turned_deg
    }

    /// The view as a target, and its points in their scan order (at most
    /// `max_target_points`). The target may reorder its points (a range grid sorts them by
    /// cell); every other use samples the scan-order copy: sampling every n-th point of the
    /// cell order picks the same image rows in every view, a camera-fixed pattern that
    /// biased the turntable refinement by 0.1° on the egg.
    fn prepare(&self, cloud: &PointCloud, what: &str) -> Result<(Target, Vec<[f32; 3]>), RegisterError> {
        let idx = subsample_indices(cloud.len(), self.params.max_target_points);
        let pts: Vec<[f32; 3]> = idx.iter().map(|&i| cloud.points[i]).collect();
        Ok((self.target_of(pts.clone(), what)?, pts))
    }

    /// An ICP target of points in the frame of the camera that saw them: a range grid
    /// (`projective`), else a k-d tree.
    fn target_of(&self, pts: Vec<[f32; 3]>, what: &str) -> Result<Target, RegisterError> {
        Ok(if self.params.projective {
            Target::grid(RangeGrid::build(pts, what)?, self.params.icp.normals)
        } else {
            Target::cells(pts, self.params.icp.cell_size(), self.params.icp.normals, what)?
        })
    }

    fn seed_axis(&self) -> Option<(Vector3<f64>, Vector3<f64>)> {
        self.params.calibrated_axis.or(self.symmetry_axis).or_else(|| self.axis.as_ref().map(|a| (a.point, a.dir)))
    }


    /// Registers the next view (its cloud in its own LEFT raw camera frame).
    pub fn add_view(&mut self, seq: u64, table_deg: Option<f64>, cloud: &PointCloud) -> Result<ViewRegistration, RegisterError> {
        let started = Instant::now();
        let what = format!("view {seq}");
        if cloud.len() < 10 {
            return Err(RegisterError::TooFew { what: format!("points in {what}"), got: cloud.len(), need: 10, purpose: "registration".into() });
        }
        let (target, own) = self.prepare(cloud, &what)?;
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        let mut split = RegisterSplit { prepare_ms: ms(started), ..Default::default() };
        let mut warnings = Vec::new();
        let mut notes = Vec::new();
        let Some(prev) = self.prev.take() else {
            // The first view defines the frame.
            let c = cloud.points.iter().map(|p| Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)).sum::<Vector3<f64>>() / cloud.len() as f64;
            self.reference = c;
            self.poses.push(ViewPose { seq, first_from_view: Isometry3::identity(), table_deg });
            self.steps.push(None);
            self.step_variance.push(1.0);
            let (publish_ms, _) = self.publish_and_refine(seq, table_deg, own, target, started, &mut split, &mut warnings, &mut notes);
            return Ok(ViewRegistration { seq, first_from_view: Isometry3::identity(), icp: None, seed: "none", block: None, register_ms: ms(started), publish_ms, split, warnings, notes });
        };

        let (seed, seed_kind) = match (self.seed_axis(), table_deg, prev.table_deg) {
            (Some((point, up)), Some(now), Some(before)) => (rotation_about_axis(&point, &up, -(now - before)), "turntable"),
            _ => (Isometry3::identity(), "identity"),
        };
        let blind = table_deg.is_none() || prev.table_deg.is_none();
        let mut prev_target = prev.target;
        let mut result = match icp(&own, &mut prev_target, &seed, &without_angles(&self.params.icp, blind)) {
            Ok(r) => r,
            Err(e) => {
                // Keep the previous view, so the next one registers to it.
                self.prev = Some(Stored { seq: prev.seq, table_deg: prev.table_deg, target: prev_target });
                return Err(e);
            }
        };
        // Before an axis is known the seed is the identity, which knows nothing of the turn:
        // a weak motion held there (the probe's, not a truly free one) may be most of the
        // turn — an object of two ellipsoids turned 2° registered as 0.8° about a line 60° off
        // the table's axis. So that motion is solved too, and kept when the views fit
        // clearly closer (WEAK_FIT_GAIN); a torus's spin about its own axis, which the turn
        // does not move, fits no closer and stays held (docs/registration.md, Known limits,
        // "The first steps held 'no turn'").
        let mut turn_seen = false;
        if seed_kind == "identity" && !blind && result.degenerate.iter().any(|d| d.ratio >= self.params.icp.degeneracy_ratio) {
            if let Ok(solved) = icp(&own, &mut prev_target, &seed, &without_angles(&self.params.icp, true)) {
                if solved.rmse <= WEAK_FIT_GAIN * result.rmse && solved.fitness >= WEAK_FIT_MIN_FITNESS * result.fitness {
                    notes.push(format!("view {seq}: ICP from the identity held a weak motion; solving it fits the views closer (RMSE {:.3} against {:.3} mm), so the step solves it", solved.rmse, result.rmse));
                    result = solved;
                    turn_seen = true;
                    self.turn_line = screw_line(&result.transform).or(self.turn_line);
                }
            }
        }
        let mut seed = seed;
        let mut seed_kind = seed_kind;
        // A surface of revolution turning about its own axis: ICP cannot see the turn. With
        // no axis known yet, a free rotation about a line that stands roughly upright in the
        // image (within 45° of the image's vertical) is the table's axis — an object off the
        // axis would not be degenerate — so lean on the table's step about it. (A free
        // rotation about another line, such as a ring facing the camera, is left alone.)
        // A nearly free one (an egg: the weakest motion is such a rotation, conditioning below
        // the probe ratio) gets the same second try, kept when it fits as well (RMSE within
        // 5 %): ICP from the identity would settle on "no turn" there.
        let upright = |d: &super::icp::Degeneracy| d.axis.filter(|(_, dir)| dir[1].abs() > std::f64::consts::FRAC_1_SQRT_2);
        // Once a step has solved a weak turn (this one: `turn_seen`, or an earlier one), the
        // line the weak motion turns about — an egg's own axis — need not be the table's: it
        // is taken only within `SOLVED_TURN_LINE_DEG` of the line that step turned about
        // (`turn_line`), and its table step kept only when it fits the views as well as the
        // solved step (within 5 %, measured on the same pairs). Further off, this step keeps
        // its solution; a step that held the turn instead tries the table's step about the
        // solved step's line, kept when it fits as well as the held result.
        if let (None, Some(now), Some(before)) = (self.seed_axis(), table_deg, prev.table_deg) {
            let weak_or_free = |r: &IcpResult| {
                let free = r.degenerate.iter().find_map(upright);
                let weak = r.weakest.as_ref().filter(|_| r.conditioning < self.params.icp.degeneracy_probe_ratio).and_then(upright);
                (free, weak)
            };
            let (mut free, mut weak) = weak_or_free(&result);
            // The axis of that free rotation needs exact nearest neighbours: with projective
            // pairs a nearly symmetric egg's came out 30° off the table's axis (the clouds'
            // camera-fixed errors pull pairs made along the line of sight towards "no
            // motion"), and every step seeded about it turned the views about the wrong line.
            // So this test looks again with exact pairs (a cell grid) — only while no axis is
            // known, and on at most the first `MAX_SYMMETRY_TESTS` steps that ask.
            let mut exact = None;
            if (free.is_some() || weak.is_some()) && self.params.projective && self.symmetry_tests < MAX_SYMMETRY_TESTS {
                self.symmetry_tests += 1;
                // (Should the tree fail, the projective result stands: the previous view must
                // stay for the next one.)
                let tree = Target::cells(prev_target.points().to_vec(), self.params.icp.cell_size(), self.params.icp.normals, &format!("view {}", prev.seq));
                if let Ok(mut tree) = tree {
                    if let Ok(again) = icp(&own, &mut tree, &seed, &self.params.icp) {
                        (free, weak) = weak_or_free(&again);
                        let base = if turn_seen { icp(&own, &mut tree, &seed, &without_angles(&self.params.icp, true)).map_or(again.rmse, |r| r.rmse) } else { again.rmse };
                        exact = Some((tree, base));
                    }
                }
            }
            let upwards = |d: Vector3<f64>| if d.y > 0.0 { -d } else { d };
            let candidate = free.or(weak).map(|(point, dir)| (Vector3::from(point), upwards(Vector3::from(dir))));
            // A step that solved the turn turned about (nearly) the table's axis: a line
            // further from that is the object's own axis.
            let off_turn = |dir: &Vector3<f64>| self.turn_line.is_some_and(|(_, t)| t.dot(dir).abs().min(1.0).acos().to_degrees() > SOLVED_TURN_LINE_DEG);
            let line = match candidate {
                Some(c) if !off_turn(&c.1) => Some((c, true)),
                Some(_) if !turn_seen => self.turn_line.map(|(p, d)| ((p, upwards(d)), false)),
                _ => None,
            };
            if let Some(((point, up), symmetric)) = line {
                let table_seed = rotation_about_axis(&point, &up, -(now - before));
                let (retry, base_rmse) = match exact.as_mut() {
                    Some((tree, rmse)) => (icp(&own, tree, &table_seed, &self.params.icp), *rmse),
                    None => (icp(&own, &mut prev_target, &table_seed, &self.params.icp), result.rmse),
                };
                let fits = |r: &IcpResult| (free.is_some() && symmetric && self.turn_line.is_none()) || r.rmse <= 1.05 * base_rmse;
                if let Some(retry) = retry.ok().filter(fits) {
                    if symmetric {
                        self.symmetry_axis = Some((point, up));
                    }
                    seed = table_seed;
                    seed_kind = "turntable";
                    result = retry;
                }
            }
        }
        let prev_from_view = if result.fitness < self.params.min_fitness {
            warnings.push(format!("view {seq}: ICP onto view {} found too little overlap (fitness {:.2} < {:.2}); kept the {seed_kind} guess", prev.seq, result.fitness, self.params.min_fitness));
            seed
        } else {
            result.transform
        };
        if let Some(w) = result.degeneracy_warning() {
            if let Some(why) = self.degeneracy_expected(&result.degenerate, seed_kind) {
                notes.push(format!("view {seq}: {w} (expected: {why})"));
            } else {
                warnings.push(format!("view {seq}: {w}"));
            }
        }
        let prev_pose = self.poses.last().map(|p| p.first_from_view).unwrap_or_else(Isometry3::identity);
        // A calibrated axis with the table's angles places a view better than a chain of ICP
        // steps (module docs); the final check still decides between the two, so a table
        // that slipped costs only this scan's live poses.
        let pose = match (self.params.calibrated_axis, table_deg, self.poses.first().and_then(|p| p.table_deg)) {
            (Some((point, up)), Some(now), Some(first)) => rotation_about_axis(&point, &up, -(now - first)),
            _ => unit(prev_pose * prev_from_view),
        };
        self.turned_deg = match (table_deg, self.poses.first().and_then(|p| p.table_deg)) {
            (Some(now), Some(first)) => (now - first).abs(),
            _ => self.turned_deg + prev_from_view.rotation.angle().to_degrees(),
        };
        self.poses.push(ViewPose { seq, first_from_view: pose, table_deg });
        self.steps.push((result.fitness >= self.params.min_fitness).then_some(result.transform));
        // A distrusted step kept its seed: it takes (nearly) all of any loop correction.
        self.step_variance.push(if result.fitness >= self.params.min_fitness { edge_variance(&result) } else { 1e12 });
        let (publish_ms, block) = self.publish_and_refine(seq, table_deg, own, target, started, &mut split, &mut warnings, &mut notes);
        split.chain_ms = publish_ms - split.prepare_ms;
        self.update_axis();
        if let Some(note) = self.check_live_step().or_else(|| self.refit_live_axis()) {
            notes.push(format!("view {seq}: {note}"));
        }
        let published = self.published();
        let first_from_view = published.last().unwrap().first_from_view;
        self.store.publish(published);
        Ok(ViewRegistration {
            seq,
            first_from_view,
            icp: Some(result),
            seed: seed_kind,
            block,
            register_ms: ms(started),
            publish_ms,
            split,
            warnings,
            notes,
        })
    }

    /// After the newest view's pose is in `self.poses`: keeps the view (its scan-order points
    /// `own`) for the loop and the refinement, publishes the poses — the matchers get the pose
    /// as soon as the view is chained —, then runs the long step and makes the view the next
    /// one's target, and ends the block when it is full (both refine the store afterwards).
    /// Returns the time from `started` to the publication and the block step's result.
    #[allow(clippy::too_many_arguments)]
    fn publish_and_refine(&mut self, seq: u64, table_deg: Option<f64>, own: Vec<[f32; 3]>, target: Target, started: Instant, split: &mut RegisterSplit, warnings: &mut Vec<String>, notes: &mut Vec<String>) -> (f64, Option<IcpResult>) {
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        let k = self.poses.len() - 1;
        self.remember(k, &own);
        self.keep_for_refinement(k, table_deg, &own);
        self.store.publish(self.published());
        let publish_ms = ms(started);
        let t = Instant::now();
        if let Err(e) = self.long_step(k, table_deg, &own) {
            warnings.push(format!("view {seq}: long step for the axis: {e}"));
        }
        split.long_ms = ms(t);
        self.prev = Some(Stored { seq, table_deg, target });
        let t = Instant::now();
        self.block.push((k, own));
        let block = self.end_block_if_full(warnings, notes);
        split.block_ms = ms(t);
        (publish_ms, block)
    }

    /// Why ICP's free directions are expected here ([`explained_degeneracy`]), with the
    /// table's axis as far as it is known.
    fn degeneracy_expected(&self, degenerate: &[super::icp::Degeneracy], seed_kind: &str) -> Option<&'static str> {
        explained_degeneracy(degenerate, self.seed_axis().map(|(_, up)| up), seed_kind == "turntable")
    }

    fn remember(&mut self, index: usize, points: &[[f32; 3]]) {
        let keep = self.params.loop_views.max(1);
        let pts = subsample_indices(points.len(), self.params.max_target_points / keep).into_iter().map(|i| points[i]).collect::<Vec<_>>();
        if self.opening.len() < keep {
            self.opening.push((index, pts.clone()));
        }
        self.closing.push_back((index, pts));
        while self.closing.len() > keep {
            self.closing.pop_front();
        }
    }

    fn update_axis(&mut self) {
        self.update_axis_from(false)
    }

    /// The axis from the chained poses (while views come: it seeds the next ones) or, with
    /// `long` and at least three long steps, from the long steps (at the end: it is the
    /// better estimate, but early in a scan it rests on too few steps to seed with).
    fn update_axis_from(&mut self, long: bool) {
        if long && self.long_steps.len() >= 3 {
            self.axis = estimate_axis(&self.long_steps, &self.reference, self.params.axis_min_span_deg);
            if self.axis.is_some() {
                return;
            }
        }
        let first_deg = self.poses.first().and_then(|p| p.table_deg);
        let poses: Vec<(Isometry3<f64>, Option<f64>)> = self.poses.iter().skip(1).map(|p| (p.first_from_view, p.table_deg.zip(first_deg).map(|(a, b)| a - b))).collect();
        self.axis = estimate_axis(&poses, &self.reference, self.params.axis_min_span_deg);
    }

    /// Registers the newest view (index `k`, points `pts`) to the recent view closest to
    /// `axis_baseline_deg` before it, keeps the result as a long step, and remembers the view.
    fn long_step(&mut self, k: usize, table_deg: Option<f64>, pts: &[[f32; 3]]) -> Result<(), RegisterError> {
        const MAX_BACK: usize = 32;
        let baseline = self.params.axis_baseline_deg;
        if baseline <= 0.0 {
            return Ok(());
        }
        let step = if k > 0 { self.turned_deg / k as f64 } else { 0.0 };
        let pick = self
            .history
            .iter()
            .enumerate()
            .map(|(h, (j, deg, _))| {
                let apart = match (table_deg, deg) {
                    (Some(a), Some(b)) => (a - b).abs(),
                    _ => (k - j) as f64 * step,
                };
                (h, apart)
            })
            .filter(|(_, apart)| *apart >= baseline / 2.0 && *apart <= baseline * 1.25)
            .min_by(|a, b| (a.1 - baseline).abs().total_cmp(&(b.1 - baseline).abs()));
        if let Some((h, _)) = pick.filter(|_| k % self.params.axis_long_step_every.max(1) == 0) {
            let (j, deg) = (self.history[h].0, self.history[h].1);
            let init = self.poses[j].first_from_view.inverse() * self.poses[k].first_from_view;
            let r = icp(pts, &mut self.history[h].2, &init, &without_angles(&self.params.icp, table_deg.is_none() || deg.is_none()))?;
            // A step that cannot see the turn about an upright line (a surface of revolution on
            // the table) kept its seed's turn, and with it the seed's axis: it says nothing new.
            // Other free motions (a ring spinning about its own axis) leave the tilt it measures.
            let blind = r.degenerate.iter().any(|d| d.axis.is_some_and(|(_, dir)| dir[1].abs() > std::f64::consts::FRAC_1_SQRT_2));
            if r.fitness >= self.params.min_fitness && !blind {
                self.long_steps.push((r.transform, table_deg.zip(deg).map(|(a, b)| a - b)));
            }
        }
        let keep = subsample_indices(pts.len(), 20_000).into_iter().map(|i| pts[i]).collect();
        self.history.push_back((k, table_deg, self.target_of(keep, "view")?));
        while self.history.len() > MAX_BACK {
            self.history.pop_front();
        }
        Ok(())
    }

    /// Algorithm 1's block step: once m views are chained, register their union to the model
    /// of everything before them, correct their poses, and add them to the model.
    fn end_block_if_full(&mut self, warnings: &mut Vec<String>, notes: &mut Vec<String>) -> Option<IcpResult> {
        let m = self.params.block;
        if m == 0 || self.block.len() < m {
            if m == 0 {
                self.block.clear();
            }
            return None;
        }
        let block = std::mem::take(&mut self.block);
        let mut outcome = None;
        // Views placed by a calibrated axis and the table's angles have no drift for a block
        // step to take out (and ICP onto the model is the less precise of the two).
        let by_table = self.params.calibrated_axis.is_some() && self.poses.first().is_some_and(|p| p.table_deg.is_some()) && block.iter().all(|(k, _)| self.poses[*k].table_deg.is_some());
        if !self.model.is_empty() && !by_table {
            match self.block_icp(&block) {
                Ok(r) if r.fitness >= self.params.min_fitness => {
                    for (k, _) in &block {
                        self.poses[*k].first_from_view = unit(r.transform * self.poses[*k].first_from_view);
                    }
                    if let Some(w) = r.degeneracy_warning() {
                        let line = format!("block ending at view {}: {w}", self.poses.last().unwrap().seq);
                        // With the axis known and every view's table angle, the chain the
                        // block starts from turned by the table's steps about that axis.
                        let seeded = if self.seed_axis().is_some() && block.iter().all(|(k, _)| self.poses[*k].table_deg.is_some()) { "turntable" } else { "chained" };
                        if let Some(why) = self.degeneracy_expected(&r.degenerate, seeded) {
                            notes.push(format!("{line} (expected: {why})"));
                        } else {
                            warnings.push(line);
                        }
                    }
                    outcome = Some(r);
                }
                Ok(r) => warnings.push(format!("block ending at view {}: too little overlap with the model (fitness {:.2}); not corrected", self.poses.last().unwrap().seq, r.fitness)),
                Err(e) => warnings.push(format!("block ending at view {}: {e}", self.poses.last().unwrap().seq)),
            }
        }
        for (k, pts) in &block {
            let cloud = PointCloud { points: pts.clone(), colors: Vec::new(), normals: None, rim_px: None };
            self.model.add(&cloud, &self.poses[*k].first_from_view);
        }
        outcome
    }

    /// ICP of a block's union onto the model; the result's transform is the correction in the
    /// first view's frame (`first_from_first`). With `projective`, both are moved into the
    /// frame of the block's last view, where the model is a range image the way that camera
    /// would see it (its nearest surface), and the correction is carried back.
    fn block_icp(&self, block: &[(usize, Vec<[f32; 3]>)]) -> Result<IcpResult, RegisterError> {
        let (model_cloud, _) = self.model.to_cloud();
        let last = block.last().map_or(0, |(k, _)| *k);
        let into = if self.params.projective { self.poses[last].first_from_view.inverse() } else { Isometry3::identity() };
        let union: Vec<[f32; 3]> = block.iter().flat_map(|(k, pts)| pts.iter().map(|p| super::apply(&(into * self.poses[*k].first_from_view), p)).collect::<Vec<_>>()).collect();
        let params = without_angles(&self.params.icp, block.iter().any(|(k, _)| self.poses[*k].table_deg.is_none()));
        let mut r = if self.params.projective {
            let seen: Vec<[f32; 3]> = model_cloud.points.iter().map(|p| super::apply(&into, p)).filter(|p| p[2] > 0.0).collect();
            let mut target = Target::grid(RangeGrid::build(seen, "model")?, self.params.icp.normals);
            icp(&union, &mut target, &Isometry3::identity(), &params)?
        } else {
            let mut target = Target::cells(model_cloud.points, self.params.icp.cell_size(), self.params.icp.normals, "model")?;
            icp(&union, &mut target, &Isometry3::identity(), &params)?
        };
        r.transform = into.inverse() * r.transform * into;
        Ok(r)
    }

    /// Ends the sequence: closes the loop when the views complete a turn (and loop closure is
    /// on), compares the poses with the turntable, publishes the final poses, and returns the
    /// closure. A loop that cannot be closed leaves the chained poses and a warning.
    pub fn finish(&mut self) -> Result<Option<LoopClosure>, RegisterError> {
        // Without the table's angles, the turn the texture tracks show replaces the chain's
        // first (a chain that under-turned never reaches the loop's end).
        self.fit_turn_to_texture();
        let closure = match self.close_loop() {
            Ok(c) => c,
            Err(e) => {
                tracing::warn!("loop closure: {e}; poses left as chained");
                None
            }
        };
        // The refinement starts from every axis known: the one from the chained poses (kept
        // here), the one from the long steps, the symmetry axis.
        let from_poses = self.axis.as_ref().map(|a| (a.point, a.dir));
        self.update_axis_from(true);
        self.refine_axis(from_poses);
        self.fit_turntable();
        self.store.publish(self.poses.clone());
        Ok(closure)
    }
}
