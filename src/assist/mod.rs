//! Registration-assisted matching (paper section 4, and the Kalman prediction it names as
//! future work): the registered motion of the previous views bounds where each left pixel's
//! correspondence can lie in the next frame, so the matcher searches a few disparities
//! instead of the whole range.
//!
//! An [`Assistant`] follows one scan. For each frame it builds a [`Plan`] — the disparity
//! interval of every foreground pixel — from the previous frame's disparity map and the
//! poses in the [`PoseSnapshot`] (spinscan's own registration, never ground truth), then
//! checks the result ([`Assistant::accept`]): a frame that looks wrong is matched again over
//! the full range.
//!
//! # Modes
//! - `paper` (weighting factor `w`): a point `P` of frame n−1 was at `M⁻¹·P` in frame n−2
//!   (Eq. 1, `M` the registered motion n−2 → n−1), `r = |P − M⁻¹·P|`, and lies in frame n
//!   inside the sphere of radius `w·r` around `P`. A left pixel foreground in both frames
//!   with a disparity in frame n−1 searches the single circle around its previous
//!   correspondence: on the epipolar line, `d_prev ± ρ` with `ρ = f·w·r/Z` the sphere's
//!   projected radius. Every other foreground pixel searches the union of the projected
//!   circles whose left projections contain it, intersected with its epipolar line: an
//!   interval map filled from the spheres within the largest projected radius of each such
//!   pixel (the same union as splatting every sphere's disc, visiting only what can reach).
//! - `predicted`: a constant-velocity Kalman filter over SE(3) ([`motion::MotionFilter`])
//!   predicts the motion n−1 → n; every point of frame n−1 is moved by it, projected, and
//!   its predicted disparity splatted (hull over the 2 × 2 pixels around it) with a
//!   half-width of `k·σ`, `σ² = σ_motion² + σ_px²` (the twist covariance carried to
//!   disparity, and the matcher's own noise).
//!
//! In both modes a foreground pixel no interval reaches (a hole of the forward warp, a
//! pixel without a previous disparity beyond every sphere) takes the hull of the intervals
//! within 6 px widened by 2 px; only where there is none it searches the full range. A
//! half-width never drops below `min_half_width_px`. All work is confined to the bounding
//! box of this frame's foreground and the previous frame's disparities.
//!
//! # Lag
//! A matcher may run ahead of registration: the previous frame's pose may not be published
//! yet. The motion is then extrapolated at constant velocity from the latest registered
//! step, and the search widened: `paper` scales the sphere by `1 + lag·κ` (κ the relative
//! change between the last two registered steps, at least 0.1); `predicted` grows the
//! filter's covariance by the process noise of the frames since its last measurement.
//! Nothing ever waits for a pose.

pub mod motion;

use std::collections::VecDeque;
use std::time::Instant;

use nalgebra::{Isometry3, Matrix3, UnitQuaternion, Vector3};

use crate::register::posestore::PoseSnapshot;
use crate::stereo::{DisparityIntervals, DisparityMap, MatchStats, Rectification};
use motion::{MotionFilter, MotionNoise};

/// How the search range of a frame is chosen.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AssistMode {
    /// The full range everywhere (no assistance).
    None,
    /// The paper's registration constraint with weighting factor `w`.
    Paper { w: f64 },
    /// Centred on the Kalman-predicted disparity, as wide as its uncertainty.
    Predicted,
}

impl AssistMode {
    /// `"none"`, `"paper"` or `"predicted"` (the `mode` of `bench table1`'s rows).
    pub fn name(&self) -> &'static str {
        match self {
            AssistMode::None => "none",
            AssistMode::Paper { .. } => "paper",
            AssistMode::Predicted => "predicted",
        }
    }

    /// The weighting factor of `paper`.
    pub fn w(&self) -> Option<f64> {
        match self {
            AssistMode::Paper { w } => Some(*w),
            _ => None,
        }
    }

    /// Parses `none`, `paper` (with `w`) or `predicted`.
    pub fn parse(name: &str, w: f64) -> Result<AssistMode, AssistModeError> {
        match name {
            "none" => Ok(AssistMode::None),
            "paper" if w > 0.0 && w.is_finite() => Ok(AssistMode::Paper { w }),
            "paper" => Err(AssistModeError::Weight(w)),
            "predicted" => Ok(AssistMode::Predicted),
            other => Err(AssistModeError::Mode(other.to_string())),
        }
    }
}

/// An assist mode that does not exist, or a weight the paper's rule cannot use.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AssistModeError {
    #[error("weighting factor w = {0}: expected a positive number (the paper used 0.6, 0.8, 1 and 2)")]
    Weight(f64),
    #[error("assist mode `{0}`: expected none, paper or predicted")]
    Mode(String),
}

/// Knobs of the assisted matcher; see `docs/assisted-matching.md`.
#[derive(Debug, Clone, PartialEq)]
pub struct AssistParams {
    pub mode: AssistMode,
    /// Smallest half-width of an interval, pixels (the sub-pixel fit needs a neighbour on
    /// each side of the best disparity).
    pub min_half_width_px: f64,
    /// Largest projected sphere radius, pixels (a wild registration cannot make one pixel
    /// splat over the whole image).
    pub max_radius_px: f64,
    /// `predicted`: the matcher's own disparity noise, pixels.
    pub predicted_sigma_px: f64,
    /// `predicted`: half-width in standard deviations.
    pub predicted_k: f64,
    /// `predicted`: the Kalman filter's noise model.
    pub motion_noise: MotionNoise,
    /// Self-correction: a frame whose valid fraction falls below this share of the median of
    /// the last accepted frames is matched again over the full range.
    pub fallback_valid_ratio: f64,
    /// Self-correction: registrations with ICP fitness below this are not trusted to guide
    /// the next frame (it is matched over the full range).
    pub min_fitness: f64,
    /// Self-correction: nor are those whose ICP RMSE exceeds this many times the median of
    /// the last five.
    pub max_rmse_ratio: f64,
}

impl Default for AssistParams {
    fn default() -> Self {
        AssistParams {
            mode: AssistMode::Predicted,
            min_half_width_px: 1.0,
            max_radius_px: 32.0,
            predicted_sigma_px: 0.5,
            predicted_k: 3.0,
            motion_noise: MotionNoise::default(),
            fallback_valid_ratio: 0.85,
            min_fitness: 0.3,
            max_rmse_ratio: 3.0,
        }
    }
}

/// The rectified geometry: projection of rectified-left-frame points and back.
#[derive(Debug, Clone, Copy)]
pub struct RectCamera {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    /// `cx_left − cx_right` of the rectified projections.
    dcx: f64,
    /// `P2[0][3]` (= fx · Tx, −fx·baseline on an ordinary rig).
    tx: f64,
    rect_from_left: Matrix3<f64>,
}

impl RectCamera {
    pub fn new(rect: &Rectification) -> RectCamera {
        RectCamera {
            fx: rect.p1[(0, 0)],
            fy: rect.p1[(1, 1)],
            cx: rect.p1[(0, 2)],
            cy: rect.p1[(1, 2)],
            dcx: rect.p1[(0, 2)] - rect.p2[(0, 2)],
            tx: rect.p2[(0, 3)],
            rect_from_left: rect.r1,
        }
    }

    /// The rectified-left-frame point of pixel `(x, y)` at disparity `d`, if in front.
    pub fn point(&self, x: f64, y: f64, d: f64) -> Option<Vector3<f64>> {
        let z = -self.tx / (d - self.dcx);
        (z > 0.0 && z.is_finite()).then(|| Vector3::new((x - self.cx) * z / self.fx, (y - self.cy) * z / self.fy, z))
    }

    /// Pixel and disparity of a rectified-left-frame point, if in front.
    pub fn project(&self, p: &Vector3<f64>) -> Option<(f64, f64, f64)> {
        (p.z > 1e-9).then(|| (self.fx * p.x / p.z + self.cx, self.fy * p.y / p.z + self.cy, self.dcx - self.tx / p.z))
    }

    /// A motion of LEFT raw camera points carried into the rectified left frame.
    pub fn to_rect(&self, m: &Isometry3<f64>) -> Isometry3<f64> {
        let r = UnitQuaternion::from_matrix(&self.rect_from_left);
        Isometry3::from_parts((self.rect_from_left * m.translation.vector).into(), r * m.rotation * r.inverse())
    }
}

/// What the assistant decided for one frame.
#[derive(Debug, Clone)]
pub struct Plan {
    pub intervals: DisparityIntervals,
    /// Why the whole frame searches the full range (None: assisted).
    pub full_range: Option<String>,
    /// Pixels given the paper's single circle (or, `predicted`, a predicted interval).
    pub single_px: usize,
    /// Pixels given the union of projected circles.
    pub union_px: usize,
    /// Pixels nothing reached, given the hull of the intervals around them (6 px, ±2 px).
    pub filled_px: usize,
    /// Foreground pixels no interval reached: searched over the full range.
    pub uncovered_px: usize,
    /// Frames by which the pose of the previous frame was missing (0: registered).
    pub lag: u64,
    /// Time to build the intervals, milliseconds.
    pub build_ms: f64,
}

impl Plan {
    pub fn assisted(&self) -> bool {
        self.full_range.is_none()
    }
}

#[derive(Clone)]
struct PrevFrame {
    seq: u64,
    disparity: DisparityMap,
    mask: Option<Vec<u8>>,
    /// Bounding box of the disparities.
    region: Region,
}

/// One registered step in the rectified frame, per frame of motion.
#[derive(Clone, Copy)]
struct Step {
    /// The view the step arrives at.
    seq: u64,
    /// `next_from_prev` over one frame.
    per_frame: Isometry3<f64>,
}

/// Follows one scan; see the module docs. Cloning copies the state (to time a frame again
/// without moving the scan on).
#[derive(Clone)]
pub struct Assistant {
    params: AssistParams,
    cam: RectCamera,
    /// The full disparity range `(min, max)`.
    range: (i32, i32),
    size: (usize, usize),
    prev: Option<PrevFrame>,
    filter: MotionFilter,
    /// The last two registered steps taken from the pose store.
    steps: VecDeque<Step>,
    /// Seq of the newest view whose step was taken in.
    ingested: Option<u64>,
    /// ICP fitness of the newest registration, when told.
    last_fitness: Option<(u64, f64)>,
    /// ICP RMSE of the last registrations, and the newest when it jumped: (seq, rmse, median).
    recent_rmse: VecDeque<f64>,
    rmse_jump: Option<(u64, f64, f64)>,
    recent_valid: VecDeque<f64>,
    /// Splatted bounds per pixel, valid inside `region`.
    lo: Vec<f32>,
    hi: Vec<f32>,
    region: Region,
    /// `paper`: projected sphere radius per previous pixel, and the pixels needing the union.
    rho: Vec<f32>,
    union_needed: Vec<u8>,
    /// An interval buffer handed back, with the region it was written in.
    spare: Option<(DisparityIntervals, Region)>,
}

impl Assistant {
    /// `range`: the matcher's full disparity range, inclusive.
    pub fn new(params: AssistParams, rect: &Rectification, range: (i32, i32)) -> Assistant {
        let size = (rect.size.0 as usize, rect.size.1 as usize);
        Assistant {
            filter: MotionFilter::new(params.motion_noise),
            params,
            cam: RectCamera::new(rect),
            range,
            size,
            prev: None,
            steps: VecDeque::new(),
            ingested: None,
            last_fitness: None,
            recent_rmse: VecDeque::new(),
            rmse_jump: None,
            recent_valid: VecDeque::new(),
            lo: Vec::new(),
            hi: Vec::new(),
            region: Region::default(),
            rho: Vec::new(),
            union_needed: Vec::new(),
            spare: None,
        }
    }

    pub fn params(&self) -> &AssistParams {
        &self.params
    }

    /// Tells the assistant how well view `seq` registered: the ICP fitness and inlier RMSE
    /// (mm) of its step.
    pub fn observe_registration(&mut self, seq: u64, fitness: f64, rmse: f64) {
        self.last_fitness = Some((seq, fitness));
        let median = {
            let mut v: Vec<f64> = self.recent_rmse.iter().copied().collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len() / 2).copied()
        };
        self.rmse_jump = median.filter(|m| rmse.is_finite() && rmse > self.params.max_rmse_ratio * m.max(1e-6)).map(|m| (seq, rmse, m));
        if rmse.is_finite() {
            self.recent_rmse.push_back(rmse);
            while self.recent_rmse.len() > 5 {
                self.recent_rmse.pop_front();
            }
        }
    }

    /// Takes in the steps of views registered since the last call.
    fn ingest(&mut self, poses: &PoseSnapshot) {
        for pair in poses.views.windows(2) {
            let (a, b) = (&pair[0], &pair[1]);
            if self.ingested.is_some_and(|s| b.seq <= s) || b.seq <= a.seq {
                continue;
            }
            let frames = b.seq - a.seq;
            // Points of view a, in view b's frame: b_from_a = first_from_b⁻¹ · first_from_a.
            let step = self.cam.to_rect(&(b.first_from_view.inverse() * a.first_from_view));
            self.filter.update(&step, frames);
            let per_frame = if frames == 1 { step } else { motion::exp(&(motion::log(&step) / frames as f64)) };
            self.steps.push_back(Step { seq: b.seq, per_frame });
            while self.steps.len() > 2 {
                self.steps.pop_front();
            }
            self.ingested = Some(b.seq);
        }
    }

    fn full(&self, mask: Option<&[u8]>) -> DisparityIntervals {
        DisparityIntervals::within(self.size.0, self.size.1, mask, self.range.0, self.range.1)
    }

    /// The search intervals of frame `seq` (foreground `mask`, rectified left; None = every
    /// pixel), from the previous accepted frame and the poses registered so far.
    pub fn plan(&mut self, seq: u64, mask: Option<&[u8]>, poses: &PoseSnapshot) -> Plan {
        let t0 = Instant::now();
        self.ingest(poses);
        let mut plan = Plan { intervals: DisparityIntervals::full(0, 0, 0, 0), full_range: None, single_px: 0, union_px: 0, filled_px: 0, uncovered_px: 0, lag: 0, build_ms: 0.0 };
        let reason = match (&self.params.mode, &self.prev, self.steps.back()) {
            (AssistMode::None, _, _) => Some("assistance off".to_string()),
            (_, None, _) => Some("no previous frame".to_string()),
            (_, _, None) => Some("no registered motion yet".to_string()),
            (_, Some(prev), _) if prev.seq >= seq => Some(format!("frame seq {seq} does not follow seq {}", prev.seq)),
            _ => match (self.last_fitness, self.rmse_jump) {
                (Some((s, f)), _) if f < self.params.min_fitness => Some(format!("registration of seq {s} has ICP fitness {f:.2}, below {:.2}", self.params.min_fitness)),
                (_, Some((s, r, m))) => Some(format!("registration of seq {s} has ICP RMSE {r:.2} mm, over {:.1} × the recent median {m:.2} mm", self.params.max_rmse_ratio)),
                _ => None,
            },
        };
        if let Some(reason) = reason {
            plan.intervals = self.full(mask);
            plan.full_range = Some(reason);
            plan.build_ms = t0.elapsed().as_secs_f64() * 1e3;
            return plan;
        }
        let prev = self.prev.as_ref().expect("checked above");
        let newest = self.steps.back().expect("checked above").seq;
        plan.lag = prev.seq.saturating_sub(newest);
        let gap = seq - prev.seq;
        let (w, h) = self.size;
        // Work only where the object is: this frame's foreground and the previous frame's
        // disparities, with room for the largest sphere and the hole fill.
        // (Spheres and predictions that land outside it land outside the foreground.)
        let Some(region) = Region::of(mask, w, h).map(|r| r.union(&prev.region).grow(FILL + 1, w, h)) else {
            plan.intervals = DisparityIntervals::empty(w, h);
            plan.build_ms = t0.elapsed().as_secs_f64() * 1e3;
            return plan;
        };
        self.region = region;
        self.lo.resize(w * h, f32::INFINITY);
        self.hi.resize(w * h, f32::NEG_INFINITY);
        for y in region.ys() {
            self.lo[y * w + region.x0..y * w + region.x1].fill(f32::INFINITY);
            self.hi[y * w + region.x0..y * w + region.x1].fill(f32::NEG_INFINITY);
        }
        match self.params.mode {
            AssistMode::Paper { w: weight } => self.splat_paper(weight, gap, plan.lag, mask, &mut plan),
            AssistMode::Predicted => self.splat_predicted(gap, plan.lag, mask, &mut plan),
            AssistMode::None => unreachable!("handled above"),
        }
        plan.intervals = self.intervals(mask, &mut plan);
        plan.build_ms = t0.elapsed().as_secs_f64() * 1e3;
        plan
    }

    /// The intervals from the splatted bounds: foreground pixels with bounds search them;
    /// those without take the hull of the bounds within `FILL` pixels, widened by `MARGIN`
    /// (the disparity of a surface continues across a small gap); the rest the full range.
    fn intervals(&mut self, mask: Option<&[u8]>, plan: &mut Plan) -> DisparityIntervals {
        const MARGIN: f32 = 2.0;
        let (w, h) = self.size;
        let (lo, hi, range, region) = (&self.lo, &self.hi, self.range, self.region);
        let mut iv = match self.spare.take() {
            // A buffer handed back by `recycle`: only its old region holds intervals.
            Some((mut iv, old)) if (iv.width(), iv.height()) == (w, h) => {
                iv.clear_rect(old.xs(), old.ys());
                iv
            }
            _ => DisparityIntervals::empty(w, h),
        };
        let (r0, r1) = (range.0 as f32, range.1 as f32);
        let mut holes = Vec::new();
        for y in region.ys() {
            let (out_lo, out_hi) = iv.row_mut(y);
            let row = y * w;
            let mrow = mask.map(|m| &m[row..row + w]);
            for x in region.xs() {
                let i = row + x;
                if mrow.is_some_and(|m| m[x] == 0) {
                    continue;
                }
                // Clipped, then rounded outwards (the range's ends are whole, so the order does
                // not matter); nothing reached (lo = +∞, hi = −∞) fails `a <= b`.
                let (a, b) = (lo[i].max(r0), hi[i].min(r1));
                if a <= b {
                    let (ta, tb) = (a as i32, b as i32);
                    out_lo[x] = (ta - (ta as f32 > a) as i32) as i16;
                    out_hi[x] = (tb + ((tb as f32) < b) as i32) as i16;
                } else {
                    holes.push((x, y));
                }
            }
        }
        for (x, y) in holes {
            let (mut a, mut b) = (f32::INFINITY, f32::NEG_INFINITY);
            for yy in y.saturating_sub(FILL).max(region.y0)..(y + FILL + 1).min(region.y1) {
                let row = yy * w;
                for xx in x.saturating_sub(FILL).max(region.x0)..(x + FILL + 1).min(region.x1) {
                    a = a.min(lo[row + xx]);
                    b = b.max(hi[row + xx]);
                }
            }
            match (a <= b).then(|| interval(range, a - MARGIN, b + MARGIN)).flatten() {
                Some(r) => {
                    iv.set(x, y, Some(r));
                    plan.filled_px += 1;
                }
                None => {
                    iv.set(x, y, Some(range));
                    plan.uncovered_px += 1;
                }
            }
        }
        iv
    }

    /// The paper's two cases into `lo`/`hi` (see the module docs).
    fn splat_paper(&mut self, weight: f64, gap: u64, lag: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        let (w, h) = self.size;
        let prev = self.prev.as_ref().expect("planned with a previous frame");
        let step = self.steps.back().expect("planned with a step").per_frame;
        // Lag: widen by the relative change between the last two steps (at least 10 %).
        let kappa = match (self.steps.len(), self.steps.front()) {
            (2, Some(older)) => {
                let (a, b) = (motion::log(&older.per_frame), motion::log(&step));
                ((b - a).norm() / b.norm().max(1e-12)).max(0.1)
            }
            _ => 0.1,
        };
        let widen = gap as f64 * (1.0 + lag as f64 * kappa);
        // P − M⁻¹·P = A·P + b with A = I − R⁻¹, b = R⁻¹·t.
        let back = step.inverse();
        let a_m = Matrix3::identity() - back.rotation.to_rotation_matrix().into_inner();
        let b_v = -back.translation.vector;
        let cam = self.cam;
        let min_half = self.params.min_half_width_px as f32;
        let (max_radius, scale) = (self.params.max_radius_px as f32, cam.fx * weight * widen);
        let prev_d = prev.disparity.values();
        let (lo, hi, region) = (&mut self.lo, &mut self.hi, self.region);
        // The projected radius (pixels) of every previous point's sphere, once:
        // ρ = fx·w·r/Z = fx·w·|A·(u, v, 1) + b/Z|, at least `min_half`; NaN where no point.
        self.rho.resize(w * h, f32::NAN);
        let rho = &mut self.rho;
        let mut max_rho = 0f32;
        let (a_m, b_v, scale) = (a_m.cast::<f32>(), b_v.cast::<f32>(), scale as f32);
        let (cx, cy, dcx) = (cam.cx as f32, cam.cy as f32, cam.dcx as f32);
        let (ifx, ify, inv_mtx) = (1.0 / cam.fx as f32, 1.0 / cam.fy as f32, -1.0 / cam.tx as f32);
        for y in region.ys() {
            let v = (y as f32 - cy) * ify;
            // A·(u, v, 1) = A·(0, v, 1) + u·A[:, 0].
            let base = a_m * Vector3::new(0.0, v, 1.0);
            let col0 = a_m.column(0).into_owned();
            for x in region.xs() {
                let i = y * w + x;
                let inv_z = (prev_d[i] - dcx) * inv_mtx;
                // NaN (no disparity) and points behind the camera fail here.
                if !(inv_z > 0.0) {
                    rho[i] = f32::NAN;
                    continue;
                }
                let u = (x as f32 - cx) * ifx;
                let r = (base + col0 * u + b_v * inv_z).norm();
                rho[i] = (scale * r).min(max_radius).max(min_half);
                max_rho = max_rho.max(rho[i]);
            }
        }
        let prev_fg = |i: usize| prev.mask.as_ref().is_none_or(|m| m[i] != 0);
        // Case 1: a single circle around the previous correspondence.
        self.union_needed.resize(w * h, 0);
        let union_needed = &mut self.union_needed;
        let mut any_union = false;
        for y in region.ys() {
            for x in region.xs() {
                let i = y * w + x;
                union_needed[i] = 0;
                if mask.is_some_and(|m| m[i] == 0) {
                    continue;
                }
                let r = rho[i];
                if r.is_finite() && prev_fg(i) {
                    let d = prev_d[i];
                    lo[i] = d - r;
                    hi[i] = d + r;
                    plan.single_px += 1;
                } else {
                    union_needed[i] = 1;
                    any_union = true;
                }
            }
        }
        if !any_union {
            return;
        }
        // Case 2: the union of the spheres whose left projections contain the pixel. Most
        // spheres are small: each such pixel gathers from the points within `reach` (the
        // 99th percentile of the radii); the few larger spheres are splatted onto the pixels
        // their discs cover. (The hull of a union does not mind a sphere counted twice.)
        let mut hist = [0u32; 66];
        let mut count = 0u32;
        for y in region.ys() {
            for &r in &rho[y * w + region.x0..y * w + region.x1] {
                if r.is_finite() {
                    hist[((r * 2.0) as usize).min(65)] += 1;
                    count += 1;
                }
            }
        }
        let (mut acc, mut bin) = (0u32, 0usize);
        while bin < 65 && (acc + hist[bin]) * 100 < count * 99 {
            acc += hist[bin];
            bin += 1;
        }
        let reach_f = ((bin + 1) as f32 * 0.5).min(max_rho);
        let reach = reach_f.ceil() as i64;
        for y in region.ys() {
            for x in region.xs() {
                let r = rho[y * w + x];
                if !(r > reach_f) {
                    continue;
                }
                let d = prev_d[y * w + x];
                let (xi, yi, rr) = (x as i64, y as i64, r.ceil() as i64);
                for yy in (yi - rr).max(region.y0 as i64)..=(yi + rr).min(region.y1 as i64 - 1) {
                    let dy = (yy - yi) as f32;
                    let c2 = r * r - dy * dy;
                    if c2 < 0.0 {
                        continue;
                    }
                    let c = c2.sqrt();
                    for xx in (ceil(xi as f32 - c) as i64).max(region.x0 as i64)..=(floor(xi as f32 + c) as i64).min(region.x1 as i64 - 1) {
                        let j = yy as usize * w + xx as usize;
                        if union_needed[j] != 0 {
                            let base = d + (xx - xi) as f32;
                            lo[j] = lo[j].min(base - c);
                            hi[j] = hi[j].max(base + c);
                        }
                    }
                }
            }
        }
        for y in region.ys() {
            for x in region.xs() {
                let j = y * w + x;
                if union_needed[j] == 0 {
                    continue;
                }
                let (xi, yi) = (x as i64, y as i64);
                for sy in (yi - reach).max(region.y0 as i64)..=(yi + reach).min(region.y1 as i64 - 1) {
                    let dy = (yi - sy) as f32;
                    let row = sy as usize * w;
                    for sx in (xi - reach).max(region.x0 as i64)..=(xi + reach).min(region.x1 as i64 - 1) {
                        let r = rho[row + sx as usize];
                        // NaN (no point) fails the comparison.
                        let c2 = r * r - dy * dy;
                        if !(c2 >= 0.0) {
                            continue;
                        }
                        let c = c2.sqrt();
                        let dx = (xi - sx) as f32;
                        if dx.abs() > c {
                            continue;
                        }
                        // Left pixel x lies on the sphere's left chord of row y; the right
                        // chord maps it to d_prev + (x − sx) ± c.
                        let base = prev_d[row + sx as usize] + dx;
                        lo[j] = lo[j].min(base - c);
                        hi[j] = hi[j].max(base + c);
                    }
                }
            }
        }
        plan.union_px = region.ys().flat_map(|y| region.xs().map(move |x| y * w + x)).filter(|&i| union_needed[i] != 0 && lo[i] <= hi[i]).count();
    }

    /// The Kalman prediction of every previous point into `lo`/`hi`.
    fn splat_predicted(&mut self, gap: u64, lag: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        let w = self.size.0;
        let prev = self.prev.as_ref().expect("planned with a previous frame");
        let Some((m, cov)) = self.filter.predict(gap, lag) else { return };
        let cam = self.cam;
        let (k, s2) = (self.params.predicted_k as f32, self.params.predicted_sigma_px.powi(2) as f32);
        let min_half = self.params.min_half_width_px as f32;
        // In f32, per previous point with ray (u, v, 1) and 1/Z = (d − dcx)/(−tx):
        // Q·(1/Z) = R·(u, v, 1) + t/Z, so one division gives the projection of the moved point.
        let rot = m.rotation.to_rotation_matrix().into_inner().cast::<f32>();
        let t = m.translation.vector.cast::<f32>();
        // Var(Z) of a moved point q under a twist perturbation: δZ = δω_x·q_y − δω_y·q_x + δv_z.
        let c = |i: usize, j: usize| cov[(i, j)] as f32;
        let (c00, c01, c11, c05, c15, c55) = (c(0, 0), c(0, 1), c(1, 1), c(0, 5), c(1, 5), c(5, 5));
        let (fx, fy, cx, cy, dcx, tx) = (cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32, cam.dcx as f32, cam.tx as f32);
        let prev_d = prev.disparity.values();
        let (lo, hi, region) = (&mut self.lo, &mut self.hi, self.region);
        let (ifx, ify, inv_mtx) = (1.0 / fx, 1.0 / fy, -1.0 / tx);
        for y in region.ys() {
            let v = (y as f32 - cy) * ify;
            let base = rot.column(1) * v + rot.column(2);
            let col0 = rot.column(0);
            for x in region.xs() {
                let d = prev_d[y * w + x];
                let iz = (d - dcx) * inv_mtx;
                // NaN (no disparity) and points behind the camera fail here.
                if !(iz > 0.0) {
                    continue;
                }
                let u = (x as f32 - cx) * ifx;
                let q = base + col0 * u + t * iz; // the moved point times 1/Z
                if !(q.z > 0.0) {
                    continue;
                }
                let s = 1.0 / q.z;
                let (px, py, pd) = (fx * q.x * s + cx, fy * q.y * s + cy, dcx - tx * iz * s);
                // Var(d) = (∂d/∂Z)²·Var(Z) with the moved point Q = q/iz (mm) and
                // ∂d/∂Z = tx/Q_z² = tx·iz²·s², written without dividing by iz:
                // Var(d) = tx²·s⁴·[iz²·(q_y²c00 − 2q_xq_y c01 + q_x²c11) + 2·iz³·(q_y c05 − q_x c15) + iz⁴·c55].
                let (iz2, s2q) = (iz * iz, s * s);
                let var_d = (tx * tx * s2q * s2q * iz2 * ((q.y * q.y * c00 - 2.0 * q.x * q.y * c01 + q.x * q.x * c11) + 2.0 * iz * (q.y * c05 - q.x * c15) + iz2 * c55)).max(0.0);
                let half = (k * (var_d + s2).sqrt()).max(min_half);
                let (a, b) = (pd - half, pd + half);
                let (x0, y0) = (floor(px) as i64, floor(py) as i64);
                if x0 < region.x0 as i64 || y0 < region.y0 as i64 || x0 + 1 >= region.x1 as i64 || y0 + 1 >= region.y1 as i64 {
                    continue;
                }
                let i = y0 as usize * w + x0 as usize;
                for j in [i, i + 1, i + w, i + w + 1] {
                    lo[j] = lo[j].min(a);
                    hi[j] = hi[j].max(b);
                }
            }
        }
        plan.single_px = region.ys().flat_map(|y| region.xs().map(move |x| y * w + x)).filter(|&i| mask.is_none_or(|m| m[i] != 0) && lo[i] <= hi[i]).count();
    }

    /// Hands a plan's interval buffer back for the next plan (saves allocating and clearing
    /// a full-size map per frame).
    pub fn recycle(&mut self, plan: Plan) {
        if plan.assisted() {
            self.spare = Some((plan.intervals, self.region));
        }
    }

    /// Checks a matched frame. `None`: accepted (it becomes the previous frame). `Some(why)`:
    /// the assisted result looks wrong; match the frame again over the full range and call
    /// this again with that result (a full-range result is always accepted).
    pub fn accept(&mut self, seq: u64, plan: &Plan, disparity: &DisparityMap, mask: Option<&[u8]>, stats: &MatchStats) -> Option<String> {
        let valid = stats.valid_fraction();
        if plan.assisted() && !self.recent_valid.is_empty() {
            let mut v: Vec<f64> = self.recent_valid.iter().copied().collect();
            v.sort_by(f64::total_cmp);
            let median = v[v.len() / 2];
            if valid < self.params.fallback_valid_ratio * median {
                return Some(format!("valid fraction {valid:.3} below {:.2} × the recent median {median:.3}", self.params.fallback_valid_ratio));
            }
        }
        self.recent_valid.push_back(valid);
        while self.recent_valid.len() > 5 {
            self.recent_valid.pop_front();
        }
        // Disparities exist only where something was searched: inside the plan's region.
        let region = if plan.assisted() { self.region } else { Region::of_disparity(disparity) };
        match &mut self.prev {
            Some(p) if (p.disparity.width, p.disparity.height) == (disparity.width, disparity.height) => {
                p.seq = seq;
                p.disparity.values_mut().copy_from_slice(disparity.values());
                match (&mut p.mask, mask) {
                    (Some(old), Some(new)) if old.len() == new.len() => old.copy_from_slice(new),
                    (slot, new) => *slot = new.map(<[u8]>::to_vec),
                }
                p.region = region;
            }
            slot => *slot = Some(PrevFrame { seq, disparity: disparity.clone(), mask: mask.map(<[u8]>::to_vec), region }),
        }
        None
    }
}

/// `x.floor()` without a libm call (the baseline x86-64 target has no rounding instruction);
/// exact for |x| < 2²³, where every value here lies, and ±∞ stays ±∞.
#[inline(always)]
fn floor(x: f32) -> f32 {
    if !(x.abs() < 8_388_608.0) {
        return x;
    }
    let t = x as i32 as f32;
    t - (t > x) as i32 as f32
}

/// `x.ceil()`, as [`floor`].
#[inline(always)]
fn ceil(x: f32) -> f32 {
    -floor(-x)
}

/// `[lo, hi]` rounded outwards and clipped to `range`; `None` when it misses the range.
#[inline]
fn interval(range: (i32, i32), lo: f32, hi: f32) -> Option<(i32, i32)> {
    // floor and ceil without a libm call (the baseline x86-64 target has no rounding
    // instruction); the bounds are far inside i32.
    let (tl, th) = (lo as i32, hi as i32);
    let (a, b) = ((tl - (lo < tl as f32) as i32).max(range.0), (th + (hi > th as f32) as i32).min(range.1));
    (a <= b).then_some((a, b))
}

/// Pixels nothing reached take the hull of the intervals within this many pixels.
const FILL: usize = 6;

/// A rectangle of the image, `x0..x1` × `y0..y1`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Region {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
}

impl Region {
    /// The bounding box of the non-zero pixels of `mask` (the whole image without one).
    fn of(mask: Option<&[u8]>, w: usize, h: usize) -> Option<Region> {
        match mask {
            Some(m) => Region::bbox(m, w, |&v| v != 0),
            None => Some(Region { x0: 0, x1: w, y0: 0, y1: h }),
        }
    }

    /// The bounding box of the finite values of a disparity map (empty region if none).
    fn of_disparity(d: &DisparityMap) -> Region {
        Region::bbox(d.values(), d.width, |v| v.is_finite()).unwrap_or_default()
    }

    /// The bounding box of the values `keep` accepts in a row-major `w`-wide image.
    fn bbox<T>(values: &[T], w: usize, keep: impl Fn(&T) -> bool) -> Option<Region> {
        let mut r: Option<Region> = None;
        for (y, row) in values.chunks_exact(w).enumerate() {
            let Some(first) = row.iter().position(&keep) else { continue };
            let last = w - row.iter().rev().position(&keep).expect("one exists");
            r = Some(match r {
                None => Region { x0: first, x1: last, y0: y, y1: y + 1 },
                Some(r) => Region { x0: r.x0.min(first), x1: r.x1.max(last), y0: r.y0, y1: y + 1 },
            });
        }
        r
    }

    fn union(&self, o: &Region) -> Region {
        if o.x1 == 0 {
            return *self;
        }
        Region { x0: self.x0.min(o.x0), x1: self.x1.max(o.x1), y0: self.y0.min(o.y0), y1: self.y1.max(o.y1) }
    }

    fn grow(&self, by: usize, w: usize, h: usize) -> Region {
        Region { x0: self.x0.saturating_sub(by), x1: (self.x1 + by).min(w), y0: self.y0.saturating_sub(by), y1: (self.y1 + by).min(h) }
    }

    fn xs(&self) -> std::ops::Range<usize> {
        self.x0..self.x1
    }

    fn ys(&self) -> std::ops::Range<usize> {
        self.y0..self.y1
    }
}

#[cfg(test)]
mod tests;
