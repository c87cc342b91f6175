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
mod paper;
mod region;
mod splat;
mod tiles;

use std::collections::VecDeque;
use std::time::Instant;

use nalgebra::{Isometry3, Matrix3, UnitQuaternion, Vector3};

use crate::register::posestore::PoseSnapshot;
use crate::stereo::{DisparityIntervals, DisparityMap, MatchStats, Rectification};
use motion::{MotionFilter, MotionNoise};
use region::{for_each_set, interval, round_row, MaskRows, Region, FILL};
pub use tiles::Granularity;

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
    #[error("assist granularity `{0}`: expected auto, pixel, tile or plane")]
    Granularity(String),
}

/// Knobs of the assisted matcher; see `docs/assisted-matching.md`.
#[derive(Debug, Clone, PartialEq)]
pub struct AssistParams {
    pub mode: AssistMode,
    /// One interval per pixel, or per plan tile of 16 × 8 pixels (the hull of its pixels';
    /// tiles.rs), flat or sloped, or whichever measured best for the mode (`Auto`).
    pub granularity: Granularity,
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
            granularity: Granularity::default(),
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
    /// The frame's mask, kept for the paper's rule only (the predicted splat reads none).
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
    /// `paper`: the largest ρ of each 8 × 8 block of `rho` (see `paper::Spheres`).
    rho_blocks: Vec<u32>,
    /// An interval buffer handed back, with the region it was written in.
    spare: Option<(DisparityIntervals, Region)>,
    /// Tile granularity: the hull of each tile's bounds.
    tiles: tiles::TileBounds,
}

impl Assistant {
    /// `range`: the matcher's full disparity range, inclusive.
    pub fn new(params: AssistParams, rect: &Rectification, range: (i32, i32)) -> Assistant {
        let params = AssistParams { granularity: params.granularity.resolve(params.mode), ..params };
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
            rho_blocks: Vec::new(),
            spare: None,
            tiles: tiles::TileBounds::default(),
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
        // (Tiles fill no holes per pixel: one pixel of room, for the 2 × 2 splats that
        // straddle the foreground's edge.)
        let fill_room = if self.params.granularity.tiled() { 1 } else { FILL + 1 };
        let Some(region) = Region::of(mask, w, h).map(|r| r.union(&prev.region).grow(fill_room, w, h)) else {
            plan.intervals = DisparityIntervals::empty(w, h);
            plan.build_ms = t0.elapsed().as_secs_f64() * 1e3;
            return plan;
        };
        self.region = region;
        self.lo.resize(w * h, f32::INFINITY);
        self.hi.resize(w * h, f32::NEG_INFINITY);
        if self.params.granularity.tiled() {
            self.tiles.reset(w, h);
        }
        if self.params.mode == AssistMode::Predicted && self.params.granularity == Granularity::Pixel {
            // (`paper` writes every pixel of the region itself; tiles need no per-pixel map.)
            for y in region.ys() {
                self.lo[y * w + region.x0..y * w + region.x1].fill(f32::INFINITY);
                self.hi[y * w + region.x0..y * w + region.x1].fill(f32::NEG_INFINITY);
            }
        }
        self.build_fastest(gap, mask, &mut plan);
        plan.build_ms = t0.elapsed().as_secs_f64() * 1e3;
        plan
    }

    /// [`Assistant::build`] in the widest vector code the CPU runs.
    fn build_fastest(&mut self, gap: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { self.build_avx2(gap, mask, plan) };
        }
        self.build(gap, mask, plan)
    }

    /// [`Assistant::build`] compiled for AVX2: its per-pixel passes are written branch-free
    /// so that they vectorise, eight `f32` lanes here instead of the baseline's four. The
    /// same operations in the same order (no fused multiply-add), so the same intervals.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn build_avx2(&mut self, gap: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        self.build(gap, mask, plan)
    }

    /// The splats of the mode, then the intervals from them.
    #[inline(always)]
    fn build(&mut self, gap: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        if self.params.granularity == Granularity::Plane {
            let prev = self.prev.as_ref().expect("planned with a previous frame");
            self.tiles.fit_planes(&prev.disparity, &prev.region);
        }
        match self.params.mode {
            AssistMode::Paper { w: weight } if !self.params.granularity.tiled() => {
                // Straight into the plan's map: no per-pixel pass after the splat.
                let (mut iv, mut holes) = (self.spare_intervals(), Vec::new());
                self.splat_paper(weight, gap, plan.lag, mask, plan, Some(paper::PixelOut { iv: &mut iv, holes: &mut holes }));
                self.fill_holes(&mut iv, &holes, plan);
                plan.intervals = iv;
                return;
            }
            AssistMode::Paper { w: weight } => self.splat_paper(weight, gap, plan.lag, mask, plan, None),
            AssistMode::Predicted => self.splat_predicted(gap, plan.lag, mask, plan),
            AssistMode::None => unreachable!("handled by plan"),
        }
        plan.intervals = match self.params.granularity {
            Granularity::Tile | Granularity::Plane => self.tile_intervals(mask, plan),
            // (`Auto` was resolved by `new`.)
            Granularity::Pixel | Granularity::Auto => self.intervals(mask, plan),
        };
    }

    /// Tile granularity: the tiles' hulls (the predicted splat filled them; the paper's
    /// per-pixel bounds are reduced here) into every foreground pixel (tiles.rs).
    #[inline(always)]
    fn tile_intervals(&mut self, mask: Option<&[u8]>, plan: &mut Plan) -> DisparityIntervals {
        let w = self.size.0;
        let region = self.region;
        let masks = MaskRows::new(mask, w, &region);
        match self.params.mode {
            AssistMode::Paper { .. } => self.tiles.reduce(&self.lo, &self.hi, &masks, w, &region),
            _ => self.tiles.count(&masks, &region),
        }
        let mut iv = self.spare_intervals();
        self.tiles.intervals(&mut iv, &masks, &region, self.range, plan);
        let fg = self.tiles.fg_total(&region);
        let rest = fg.saturating_sub(plan.filled_px + plan.uncovered_px);
        match self.params.mode {
            // At tile resolution every foreground pixel of a tile a prediction reached counts
            // as predicted.
            AssistMode::Predicted => plan.single_px = rest,
            // Pixels the paper's cases did not reach search their tile's interval: filled.
            _ => plan.filled_px += rest.saturating_sub(plan.single_px + plan.union_px),
        }
        iv
    }

    /// A full-size interval buffer that searches nothing outside this plan's region, for a
    /// caller that then writes every pixel of the region: the one handed back by `recycle`
    /// (only its old region holds intervals, and only the part of that outside this region
    /// is cleared: consecutive regions mostly overlap) or a new one.
    fn spare_intervals(&mut self) -> DisparityIntervals {
        let (w, h) = self.size;
        let region = self.region;
        match self.spare.take() {
            Some((mut iv, old)) if (iv.width(), iv.height()) == (w, h) => {
                iv.clear_rect_but(old.xs(), old.ys(), region.xs(), region.ys());
                iv
            }
            _ => DisparityIntervals::empty(w, h),
        }
    }

    /// The intervals from the splatted bounds: foreground pixels with bounds search them;
    /// those without are holes (`fill_holes`).
    #[inline(always)]
    fn intervals(&mut self, mask: Option<&[u8]>, plan: &mut Plan) -> DisparityIntervals {
        let w = self.size.0;
        let mut iv = self.spare_intervals();
        let (lo, hi, region) = (&self.lo, &self.hi, self.region);
        let mut holes = Vec::new();
        let n = region.x1 - region.x0;
        let (mut hole_row, none) = (vec![0u8; n], vec![0u8; n]);
        let masks = MaskRows::new(mask, w, &region);
        let xs = region.xs();
        for y in region.ys() {
            let (out_lo, out_hi) = iv.row_cols_mut(y, xs.clone());
            let row = y * w + xs.start..y * w + xs.end;
            if round_row(masks.row(y), &none, &lo[row.clone()], &hi[row], out_lo, out_hi, &mut hole_row, self.range) {
                for_each_set(&hole_row, |k| holes.push((xs.start + k, y)));
            }
        }
        self.fill_holes(&mut iv, &holes, plan);
        iv
    }

    /// Each hole (`(x, y)`, sorted by row, then column) takes the hull of the bounds within
    /// `FILL` pixels, widened by `MARGIN` (the disparity of a surface continues across a
    /// small gap), or the full range where there are none.
    #[inline(always)]
    fn fill_holes(&self, iv: &mut DisparityIntervals, holes: &[(usize, usize)], plan: &mut Plan) {
        let w = self.size.0;
        let (lo, hi, range, region) = (&self.lo, &self.hi, self.range, self.region);
        // Per row holding holes: the bounds' extremes down each column of the FILL rows
        // around it (element-wise over the holes' columns, so that it vectorises), then per
        // hole across the FILL columns around it. (The bounds are never NaN. `min` and `max`,
        // not a comparison that keeps the old value: LLVM makes a store of `v < m ? v : m` to
        // m's place an AVX masked store, which is slow on AMD's cores.)
        let (mut col_lo, mut col_hi) = (Vec::new(), Vec::new());
        let mut start = 0;
        while start < holes.len() {
            let y = holes[start].1;
            let end = start + holes[start..].iter().take_while(|h| h.1 == y).count();
            let cols = holes[start].0.saturating_sub(FILL).max(region.x0)..(holes[end - 1].0 + FILL + 1).min(region.x1);
            col_lo.clear();
            col_lo.resize(cols.len(), f32::INFINITY);
            col_hi.clear();
            col_hi.resize(cols.len(), f32::NEG_INFINITY);
            let rows = y.saturating_sub(FILL).max(region.y0)..(y + FILL + 1).min(region.y1);
            // Only the columns some hole's window covers (holes of a row are often far apart),
            // as runs of overlapping windows.
            let mut k = start;
            while k < end {
                let seg_start = holes[k].0.saturating_sub(FILL).max(region.x0);
                let mut seg_end = (holes[k].0 + FILL + 1).min(region.x1);
                k += 1;
                while k < end && holes[k].0.saturating_sub(FILL) <= seg_end {
                    seg_end = (holes[k].0 + FILL + 1).min(region.x1);
                    k += 1;
                }
                let (ca, cb) = (seg_start - cols.start, seg_end - cols.start);
                for yy in rows.clone() {
                    let row = yy * w;
                    for (m, &v) in col_lo[ca..cb].iter_mut().zip(&lo[row + seg_start..row + seg_end]) {
                        *m = m.min(v);
                    }
                    for (m, &v) in col_hi[ca..cb].iter_mut().zip(&hi[row + seg_start..row + seg_end]) {
                        *m = m.max(v);
                    }
                }
            }
            for &(x, _) in &holes[start..end] {
                let xs = x.saturating_sub(FILL).max(region.x0) - cols.start..(x + FILL + 1).min(region.x1) - cols.start;
                let a = col_lo[xs.clone()].iter().fold(f32::INFINITY, |m, &v| if v < m { v } else { m });
                let b = col_hi[xs].iter().fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m });
                fill_hole(iv, plan, range, (x, y), a, b);
            }
            start = end;
        }
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
    /// this again with that result (a full-range result is always accepted). With assistance
    /// off nothing is kept: no plan reads a previous frame then.
    pub fn accept(&mut self, seq: u64, plan: &Plan, disparity: &DisparityMap, mask: Option<&[u8]>, stats: &MatchStats) -> Option<String> {
        if self.params.mode == AssistMode::None {
            return None;
        }
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
        // The bounding box of the disparities: the next frame's spheres start there. (Not the
        // plan's region, which is grown for the fill: taken as the next bound, it would creep
        // outwards frame after frame.) Disparities exist only where something was searched:
        // inside the plan's region when assisted.
        let within = if plan.assisted() { self.region } else { Region { x0: 0, x1: disparity.width, y0: 0, y1: disparity.height } };
        let region = Region::of_disparity(disparity, within);
        let keep_mask = matches!(self.params.mode, AssistMode::Paper { .. });
        match &mut self.prev {
            Some(p) if (p.disparity.width, p.disparity.height) == (disparity.width, disparity.height) => {
                p.seq = seq;
                // Both maps are NaN outside their bounding boxes: copying the hull of the two
                // boxes makes the kept map equal to the new one everywhere.
                let hull = if p.region.x1 == 0 { region } else { p.region.union(&region) };
                let w = disparity.width;
                for y in hull.ys() {
                    p.disparity.values_mut()[y * w + hull.x0..y * w + hull.x1].copy_from_slice(&disparity.values()[y * w + hull.x0..y * w + hull.x1]);
                }
                match (&mut p.mask, mask.filter(|_| keep_mask)) {
                    (Some(old), Some(new)) if old.len() == new.len() => old.copy_from_slice(new),
                    (slot, new) => *slot = new.map(<[u8]>::to_vec),
                }
                p.region = region;
            }
            slot => *slot = Some(PrevFrame { seq, disparity: disparity.clone(), mask: mask.filter(|_| keep_mask).map(<[u8]>::to_vec), region }),
        }
        None
    }
}

/// A hole's interval: the hull `a..=b` of the bounds around it widened by `MARGIN`, or the
/// full range where there are none (counted in the plan).
fn fill_hole(iv: &mut DisparityIntervals, plan: &mut Plan, range: (i32, i32), (x, y): (usize, usize), a: f32, b: f32) {
    const MARGIN: f32 = 2.0;
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

#[cfg(test)]
mod tests;
