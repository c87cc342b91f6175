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
//!   circles whose left projections contain it, found by splatting each sphere into an
//!   interval map (only spheres that reach such a pixel, found with a summed-area table).
//! - `predicted`: a constant-velocity Kalman filter over SE(3) ([`motion::MotionFilter`])
//!   predicts the motion n−1 → n; every point of frame n−1 is moved by it, projected, and
//!   its predicted disparity splatted (hull over the 2 × 2 pixels around it) with a
//!   half-width of `k·σ`, `σ² = σ_motion² + σ_px²` (the twist covariance carried to
//!   disparity, and the matcher's own noise); holes of the forward warp are filled from
//!   neighbours within 2 px.
//!
//! In both modes foreground pixels no interval reaches are searched over the full range,
//! and a half-width never drops below `min_half_width_px`.
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

use nalgebra::{Isometry3, Matrix3, Point3, UnitQuaternion, Vector3, Vector6};

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
    pub fn parse(name: &str, w: f64) -> Result<AssistMode, String> {
        match name {
            "none" => Ok(AssistMode::None),
            "paper" if w > 0.0 && w.is_finite() => Ok(AssistMode::Paper { w }),
            "paper" => Err(format!("weighting factor w = {w}: expected a positive number (the paper used 0.6, 0.8, 1 and 2)")),
            "predicted" => Ok(AssistMode::Predicted),
            other => Err(format!("assist mode `{other}`: expected none, paper or predicted")),
        }
    }
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

    /// `∂d/∂Z` at depth `z`.
    fn dd_dz(&self, z: f64) -> f64 {
        self.tx / (z * z)
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
    /// Pixels given the union of projected circles (or a hole-filled prediction).
    pub union_px: usize,
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

struct PrevFrame {
    seq: u64,
    disparity: DisparityMap,
    mask: Option<Vec<u8>>,
}

/// One registered step in the rectified frame, per frame of motion.
#[derive(Clone, Copy)]
struct Step {
    /// The view the step arrives at.
    seq: u64,
    /// `next_from_prev` over one frame.
    per_frame: Isometry3<f64>,
}

/// Follows one scan; see the module docs.
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
    recent_valid: VecDeque<f64>,
    lo: Vec<f32>,
    hi: Vec<f32>,
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
            recent_valid: VecDeque::new(),
            lo: Vec::new(),
            hi: Vec::new(),
        }
    }

    pub fn params(&self) -> &AssistParams {
        &self.params
    }

    /// Tells the assistant how well view `seq` registered (ICP fitness of its step).
    pub fn observe_registration(&mut self, seq: u64, fitness: f64) {
        self.last_fitness = Some((seq, fitness));
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
        let (w, h) = self.size;
        match mask {
            Some(m) => DisparityIntervals::masked(w, h, m, self.range.0, self.range.1),
            None => DisparityIntervals::full(w, h, self.range.0, self.range.1),
        }
    }

    /// The search intervals of frame `seq` (foreground `mask`, rectified left; None = every
    /// pixel), from the previous accepted frame and the poses registered so far.
    pub fn plan(&mut self, seq: u64, mask: Option<&[u8]>, poses: &PoseSnapshot) -> Plan {
        let t0 = Instant::now();
        self.ingest(poses);
        let mut plan = Plan { intervals: DisparityIntervals::full(0, 0, 0, 0), full_range: None, single_px: 0, union_px: 0, uncovered_px: 0, lag: 0, build_ms: 0.0 };
        let reason = match (&self.params.mode, &self.prev, self.steps.back()) {
            (AssistMode::None, _, _) => Some("assistance off".to_string()),
            (_, None, _) => Some("no previous frame".to_string()),
            (_, _, None) => Some("no registered motion yet".to_string()),
            (_, Some(prev), _) if prev.seq >= seq => Some(format!("frame seq {seq} does not follow seq {}", prev.seq)),
            _ => match self.last_fitness {
                Some((s, f)) if f < self.params.min_fitness => Some(format!("registration of seq {s} has ICP fitness {f:.2}, below {:.2}", self.params.min_fitness)),
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
        self.lo.clear();
        self.lo.resize(w * h, f32::INFINITY);
        self.hi.clear();
        self.hi.resize(w * h, f32::NEG_INFINITY);
        let mut iv = DisparityIntervals::full(w, h, self.range.0, self.range.1);
        let fg = |i: usize| mask.is_none_or(|m| m[i] != 0);
        match self.params.mode {
            AssistMode::Paper { w: weight } => self.plan_paper(weight, gap, plan.lag, mask, &mut iv, &mut plan),
            AssistMode::Predicted => self.plan_predicted(gap, plan.lag, mask, &mut iv, &mut plan),
            AssistMode::None => unreachable!("handled above"),
        }
        // Foreground pixels nothing reached: full range. Background: nothing.
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !fg(i) {
                    iv.set(x, y, None);
                } else if iv.get(x, y).is_none() {
                    iv.set(x, y, Some(self.range));
                    plan.uncovered_px += 1;
                }
            }
        }
        plan.intervals = iv;
        plan.build_ms = t0.elapsed().as_secs_f64() * 1e3;
        plan
    }

    fn plan_paper(&mut self, weight: f64, gap: u64, lag: u64, mask: Option<&[u8]>, iv: &mut DisparityIntervals, plan: &mut Plan) {
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
        let back = step.inverse();
        let cam = self.cam;
        let fg = |i: usize| mask.is_none_or(|m| m[i] != 0);
        let prev_fg = |i: usize| prev.mask.as_ref().is_none_or(|m| m[i] != 0);
        let min_half = self.params.min_half_width_px;
        let (max_radius, range) = (self.params.max_radius_px, self.range);
        // Projected radius (pixels) of the sphere of each previous pixel with a disparity.
        let radius = |x: usize, y: usize, d: f64| -> Option<f64> {
            let p = cam.point(x as f64, y as f64, d)?;
            let r = (p - (back * Point3::from(p)).coords).norm();
            Some((cam.fx * weight * r * widen / p.z).min(max_radius))
        };
        // Case 1: a single circle around the previous correspondence.
        let mut union_needed = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !fg(i) {
                    continue;
                }
                let single = prev_fg(i).then(|| prev.disparity.get(x, y)).flatten().and_then(|d| Some((d as f64, radius(x, y, d as f64)?)));
                match single.and_then(|(d, rho)| interval(range, d - rho.max(min_half), d + rho.max(min_half))) {
                    Some(range) => {
                        iv.set(x, y, Some(range));
                        plan.single_px += 1;
                    }
                    None => {
                        iv.set(x, y, None);
                        union_needed[i] = 1;
                    }
                }
            }
        }
        // Case 2: splat the spheres that reach a pixel needing the union.
        let sat = summed_area(&union_needed, w, h);
        let any_in = |x0: i64, y0: i64, x1: i64, y1: i64| -> bool {
            let (x0, y0) = (x0.max(0) as usize, y0.max(0) as usize);
            let (x1, y1) = (x1.min(w as i64 - 1), y1.min(h as i64 - 1));
            if x1 < x0 as i64 || y1 < y0 as i64 {
                return false;
            }
            let (x1, y1) = (x1 as usize + 1, y1 as usize + 1);
            sat[y1 * (w + 1) + x1] + sat[y0 * (w + 1) + x0] > sat[y0 * (w + 1) + x1] + sat[y1 * (w + 1) + x0]
        };
        let (lo, hi) = (&mut self.lo, &mut self.hi);
        for y in 0..h {
            for x in 0..w {
                let Some(d) = prev.disparity.get(x, y) else { continue };
                let d = d as f64;
                let Some(rho) = radius(x, y, d) else { continue };
                let rho = rho.max(min_half);
                let reach = rho.ceil() as i64;
                let (xi, yi) = (x as i64, y as i64);
                if !any_in(xi - 2 * reach, yi - reach, xi + 2 * reach, yi + reach) {
                    continue;
                }
                // Row yy of the left circle: half-chord c; its left pixels xx map onto the
                // right circle's chord, d_xx ∈ d + (xx − x) ± c.
                for yy in (yi - reach).max(0)..=(yi + reach).min(h as i64 - 1) {
                    let dy = (yy - yi) as f64;
                    let c2 = rho * rho - dy * dy;
                    if c2 < 0.0 {
                        continue;
                    }
                    let c = c2.sqrt();
                    for xx in ((xi as f64 - c).ceil() as i64).max(0)..=((xi as f64 + c).floor() as i64).min(w as i64 - 1) {
                        let j = yy as usize * w + xx as usize;
                        if union_needed[j] == 0 {
                            continue;
                        }
                        let base = d + (xx - xi) as f64;
                        lo[j] = lo[j].min((base - c) as f32);
                        hi[j] = hi[j].max((base + c) as f32);
                    }
                }
            }
        }
        for y in 0..h {
            for x in 0..w {
                let j = y * w + x;
                if union_needed[j] != 0 && lo[j] <= hi[j] {
                    if let Some(r) = interval(range, lo[j] as f64, hi[j] as f64) {
                        iv.set(x, y, Some(r));
                        plan.union_px += 1;
                    }
                }
            }
        }
    }

    fn plan_predicted(&mut self, gap: u64, lag: u64, mask: Option<&[u8]>, iv: &mut DisparityIntervals, plan: &mut Plan) {
        let (w, h) = self.size;
        let prev = self.prev.as_ref().expect("planned with a previous frame");
        let Some((m, cov)) = self.filter.predict(gap, lag) else { return };
        let cam = self.cam;
        let (k, s_px) = (self.params.predicted_k, self.params.predicted_sigma_px);
        let min_half = self.params.min_half_width_px as f32;
        let range = self.range;
        let (lo, hi) = (&mut self.lo, &mut self.hi);
        for y in 0..h {
            for x in 0..w {
                let Some(d) = prev.disparity.get(x, y) else { continue };
                let Some(p) = cam.point(x as f64, y as f64, d as f64) else { continue };
                let q = m * Point3::from(p);
                let Some((px, py, pd)) = cam.project(&q.coords) else { continue };
                // σ of the predicted depth: δZ = (δω × Q)_z + δv_z.
                let j = Vector6::new(q.y, -q.x, 0.0, 0.0, 0.0, 1.0);
                let var_z = (j.transpose() * cov * j)[(0, 0)].max(0.0);
                let sd = cam.dd_dz(q.z).abs() * var_z.sqrt();
                let half = ((k * (sd * sd + s_px * s_px).sqrt()) as f32).max(min_half);
                let (a, b) = ((pd as f32) - half, (pd as f32) + half);
                let (x0, y0) = (px.floor() as i64, py.floor() as i64);
                for (xx, yy) in [(x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)] {
                    if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                        continue;
                    }
                    let i = yy as usize * w + xx as usize;
                    lo[i] = lo[i].min(a);
                    hi[i] = hi[i].max(b);
                }
            }
        }
        let fg = |i: usize| mask.is_none_or(|m| m[i] != 0);
        const FILL: i64 = 2;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !fg(i) {
                    continue;
                }
                if lo[i] <= hi[i] {
                    if let Some(r) = interval(range, lo[i] as f64, hi[i] as f64) {
                        iv.set(x, y, Some(r));
                        plan.single_px += 1;
                        continue;
                    }
                }
                // A hole of the forward warp: the hull of the predictions around it.
                let (mut a, mut b) = (f32::INFINITY, f32::NEG_INFINITY);
                for yy in (y as i64 - FILL).max(0)..=(y as i64 + FILL).min(h as i64 - 1) {
                    for xx in (x as i64 - FILL).max(0)..=(x as i64 + FILL).min(w as i64 - 1) {
                        let j = yy as usize * w + xx as usize;
                        a = a.min(lo[j]);
                        b = b.max(hi[j]);
                    }
                }
                match (a <= b).then(|| interval(range, a as f64, b as f64)).flatten() {
                    Some(r) => {
                        iv.set(x, y, Some(r));
                        plan.union_px += 1;
                    }
                    None => iv.set(x, y, None),
                }
            }
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
        self.prev = Some(PrevFrame { seq, disparity: disparity.clone(), mask: mask.map(<[u8]>::to_vec) });
        None
    }
}

/// `[lo, hi]` rounded outwards and clipped to `range`; `None` when it misses the range.
fn interval(range: (i32, i32), lo: f64, hi: f64) -> Option<(i32, i32)> {
    let (a, b) = (lo.floor().max(range.0 as f64), hi.ceil().min(range.1 as f64));
    (a <= b).then_some((a as i32, b as i32))
}

/// Summed-area table of a 0/1 map, `(w + 1) × (h + 1)`.
fn summed_area(m: &[u8], w: usize, h: usize) -> Vec<u32> {
    let mut s = vec![0u32; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0u32;
        for x in 0..w {
            row += m[y * w + x] as u32;
            s[(y + 1) * (w + 1) + x + 1] = s[y * (w + 1) + x + 1] + row;
        }
    }
    s
}

#[cfg(test)]
mod tests;
