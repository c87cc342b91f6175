//! The data path of one view, and the drivers that run it over many.
//!
//! ```text
//!  StereoFrame ─decode, size check─> raw RGB ─rectify, segment─> Prepared
//!      ─assisted (Assistant + PoseSnapshot, self-correction) or full-range match─> disparity
//!      ─triangulate─> View ──> results::ResultsWriter (views/, disparity/, poses, model, report)
//! ```
//!
//! [`Pipeline::process_frame`] is that path in one function; `spinscan replay`
//! ([`replay`]), the daemon's live scans ([`live`]) and `bench table1` (which prepares each
//! frame once and matches it per row) all go through the same [`Pipeline::prepare_frame`],
//! [`Pipeline::match_frame`] and [`Pipeline::finish_view`].

pub mod live;
pub mod mesh;
pub mod range;
pub mod registered;
pub mod replay;
pub mod results;
pub mod truth;

use std::sync::Arc;
use std::time::Instant;

use crate::assist::{AssistParams, Assistant, Plan};
use crate::calib::StereoCalib;
use crate::cloud::PointCloud;
use crate::hw::{DecodeError, StereoFrame};
use crate::io::rgb_to_gray;
use crate::recording::TurntableAxis;
use crate::register::posestore::{PoseSnapshot, PoseStore};
use crate::register::ring::{Registrar, RegistrationParams};
use crate::segment::{ChromaKey, KeyUsed, SegmentError};
use crate::stereo::{
    triangulate::triangulate, DisparityIntervals, DisparityMap, GrayView, MatchError, MatchParams, MatchStats, ParamError,
    Rectification, RectifyError, RemapTable, StereoMatcher,
};

/// How a view is processed.
#[derive(Debug, Clone)]
pub struct PipelineOptions {
    /// Rectification scaling: 0 keeps only valid pixels, 1 keeps all, −1 unscaled; `None`
    /// (the default) the least alpha from 0 that keeps the middle of both cameras' views
    /// ([`Rectification::compute_keeping_views`]: 0 unless the rig is toed in).
    pub alpha: Option<f64>,
    /// First disparity searched. `None` picks it from the rig: 0 when rectified disparities
    /// are positive, `−(N − 1)` when they are negative, so the N disparities cover the
    /// rig's side of zero.
    pub min_disparity: Option<i32>,
    /// Matcher settings; its `min_disparity` is replaced by the one resolved above.
    pub matching: MatchParams,
    /// Foreground segmentation (used when a view asks for it).
    pub chroma: ChromaKey,
    /// A scan's driver probes its first frame and widens the range where it does not hold
    /// the object ([`range`]; `replay` and `demo` where no range is given, the daemon's
    /// `[matching] fit_range`).
    pub fit_range: bool,
    /// The right images' contrast is scaled by this before matching: the gain between the
    /// cameras, where a scan's first frame found them more than 10 % apart
    /// ([`crate::stereo::gain`], [`range::fit`]).
    pub right_gain: Option<f64>,
    /// Refine each view's sub-pixel disparities with a window that follows the surface
    /// ([`crate::stereo::follow`]) before they are triangulated; registration takes the
    /// matcher's own (docs/matcher.md, "The window that follows the surface").
    pub follow_surface: bool,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        PipelineOptions { alpha: None, min_disparity: None, matching: MatchParams::default(), chroma: ChromaKey::default(), fit_range: false, right_gain: None, follow_surface: true }
    }
}

/// Why a view could not be processed.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("rectification: {0}")]
    Rectify(#[from] RectifyError),
    #[error("matcher parameter {0}")]
    Param(#[from] ParamError),
    #[error("matching: {0}")]
    Match(#[from] MatchError),
    #[error("segmentation: {0}")]
    Segment(#[from] SegmentError),
    #[error("image is {0}×{1} but the calibration is for {2}×{3}")]
    ImageSize(usize, usize, u32, u32),
    #[error("the calibration's cameras are stacked vertically (the baseline T runs more along y than x): spinscan matches along rectified rows, so the cameras must sit side by side; for a rig mounted on its side, turn both cameras' images and their calibration by 90° first")]
    VerticalRig,
}

/// Why one frame produced no view.
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error("{side} image: {source}")]
    Decode { side: &'static str, source: DecodeError },
    #[error("images are {0}×{1} and {2}×{3}, expected {4}×{5}")]
    Size(usize, usize, usize, usize, usize, usize),
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
}

/// Registration assistance for one frame: the matcher's own assistant and the poses
/// registration has published so far.
pub struct Assist<'a> {
    pub assistant: &'a mut Assistant,
    pub poses: &'a PoseSnapshot,
}

/// A registrar seeded with the recording's calibrated turntable axis, where it has one, and
/// with the rig's rectified left camera for the texture tracks (`rect`; None keeps the
/// camera `params` has).
pub fn registrar(mut params: RegistrationParams, calibrated_axis: Option<&TurntableAxis>, rect: Option<&Rectification>, store: Arc<PoseStore>) -> Registrar {
    if let Some(rect) = rect {
        params.track_camera = track_camera(rect);
    }
    if let Some(axis) = calibrated_axis {
        params.calibrated_axis = Some((nalgebra::Vector3::from(axis.axis_point_mm), nalgebra::Vector3::from(axis.axis_dir)));
    }
    Registrar::new(params, store)
}

/// The rectified left camera as the texture tracks see it (`register::tracks`).
pub fn track_camera(rect: &Rectification) -> Option<crate::register::tracks::TrackCamera> {
    crate::register::tracks::TrackCamera::new(rect.r1, rect.q)
}

/// Everything one view produced.
#[derive(Debug, Clone)]
pub struct View {
    pub disparity: DisparityMap,
    /// Rectified left image, RGB.
    pub left_rgb: Vec<u8>,
    /// Foreground mask in rectified left coordinates (255 = object), when segmentation ran.
    pub mask: Option<Vec<u8>>,
    pub cloud: PointCloud,
    pub stats: MatchStats,
    /// Time of the matcher alone, milliseconds (with assistance: every matcher call of the
    /// frame, a full-range redo included).
    pub match_ms: f64,
    /// How the search range was chosen, when an [`Assistant`] chose it.
    pub assist: Option<AssistOutcome>,
    /// The key the mask was made with, when segmentation ran.
    pub key: Option<KeyUsed>,
    /// Pixels of the right image at or near white.
    pub right_near_white: usize,
    /// Matches dropped because a camera clipped them to white ([`crate::stereo::gain::drop_clipped`]).
    pub clipped_px: usize,
    /// What registration takes ([`View::registration_cloud`]) where it is not `cloud`: every
    /// point of the matcher's own map, in pixel order — the rim's too (those within
    /// [`ChromaKey::rim_px`] of the object's silhouette, left out of `cloud`, what is fused),
    /// and before the surface-following refinement (`disparity` and `cloud` are after it).
    /// `None` where no rim was cut and no refinement ran.
    pub for_registration: Option<PointCloud>,
    /// What the surface-following refinement looked at and moved (all 0 where it is off).
    pub followed: crate::stereo::follow::FollowStats,
    /// What the rim's profile moved ([`crate::stereo::follow::extrapolate_rim`]); its time is
    /// within `follow_ms`.
    pub rim_profile: crate::stereo::follow::RimStats,
    /// Its time, milliseconds.
    pub follow_ms: f64,
    /// The matcher's own map where the refinement changed `disparity`: the texture tracks'
    /// depths, as registration's points, come from it ([`View::registration_disparity`]).
    pub matched_disparity: Option<DisparityMap>,
}

impl View {
    /// What registration takes of the view: every point, its rim's too, of the matcher's own
    /// map.
    pub fn registration_cloud(&self) -> &PointCloud {
        self.for_registration.as_ref().unwrap_or(&self.cloud)
    }

    /// The disparities registration takes (the texture tracks' depths): the matcher's own.
    pub fn registration_disparity(&self) -> &DisparityMap {
        self.matched_disparity.as_ref().unwrap_or(&self.disparity)
    }

    /// How many points the rim held (left out of `cloud`).
    pub fn rim_points(&self) -> usize {
        self.for_registration.as_ref().map_or(0, |all| all.len().saturating_sub(self.cloud.len()))
    }
}

/// A background plate (an image of the empty scene) in rectified left coordinates, RGB, from
/// [`Pipeline::rectify_plate`].
#[derive(Debug, Clone)]
pub struct RectifiedPlate(Vec<u8>);

/// A rectified, segmented pair ready to match.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub left_rgb: Vec<u8>,
    pub left_gray: Vec<u8>,
    pub right_gray: Vec<u8>,
    pub mask: Option<Vec<u8>>,
    /// The key the mask was made with, when segmentation ran.
    pub key: Option<KeyUsed>,
    /// Pixels of the right image at or near white (before any scaling).
    pub right_near_white: usize,
    /// The gain the right image's contrast was scaled by ([`Pipeline::balance`]).
    pub right_gain: Option<f64>,
    /// The right image's level from which it is clipped to white (after the scaling).
    pub right_clip: u8,
}

impl Prepared {
    fn new(left_rgb: Vec<u8>, left_gray: Vec<u8>, right_gray: Vec<u8>, mask: Option<Vec<u8>>, key: Option<KeyUsed>) -> Prepared {
        let right_near_white = crate::stereo::gain::near_white(&right_gray);
        Prepared { left_gray, right_gray, left_rgb, mask, key, right_near_white, right_gain: None, right_clip: crate::stereo::gain::NEAR_WHITE }
    }

    /// An already rectified RGB pair, with an optional rectified mask (given, not keyed); not
    /// yet balanced ([`Pipeline::balance`]).
    pub fn from_rectified(left_rgb: Vec<u8>, right_rgb: &[u8], mask: Option<Vec<u8>>) -> Prepared {
        let left_gray = rgb_to_gray(&left_rgb);
        Prepared::new(left_rgb, left_gray, rgb_to_gray(right_rgb), mask, None)
    }
}

/// One frame matched with registration assistance.
#[derive(Debug, Clone)]
pub struct AssistedMatch {
    pub seq: u64,
    pub disparity: DisparityMap,
    pub stats: MatchStats,
    pub outcome: AssistOutcome,
    /// Whether an assistant planned the frame (else: full range, no assistance).
    pub assisted: bool,
}

/// What the assistant did for one frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AssistOutcome {
    /// Why the frame was planned over the full range (None: assisted).
    pub full_range: Option<String>,
    /// Why an assisted result was rejected and the frame matched again over the full range.
    pub fallback: Option<String>,
    pub single_px: usize,
    pub union_px: usize,
    pub filled_px: usize,
    pub uncovered_px: usize,
    pub lag: u64,
    /// Building the intervals and keeping the frame for the next one, ms.
    pub interval_ms: f64,
    /// Of which checking the result and keeping the frame, ms.
    pub accept_ms: f64,
    /// The first (assisted) matcher call alone, ms.
    pub first_match_ms: f64,
    /// Every matcher call of the frame, ms (left–right check included).
    pub match_ms: f64,
    /// The assisted attempt's statistics when it was rejected.
    pub rejected: Option<MatchStats>,
}

impl AssistOutcome {
    /// Whether this frame's result came from the full range.
    pub fn searched_full_range(&self) -> bool {
        self.full_range.is_some() || self.fallback.is_some()
    }

    fn of(plan: &Plan) -> AssistOutcome {
        AssistOutcome {
            full_range: plan.full_range.clone(),
            single_px: plan.single_px,
            union_px: plan.union_px,
            filled_px: plan.filled_px,
            uncovered_px: plan.uncovered_px,
            lag: plan.lag,
            interval_ms: plan.build_ms,
            ..Default::default()
        }
    }
}

/// The stereo core set up for one rig: rectification, remap tables and a matcher whose
/// buffers are reused from view to view.
pub struct Pipeline {
    pub rect: Rectification,
    maps: (RemapTable, RemapTable),
    matcher: StereoMatcher,
    chroma: ChromaKey,
    size: (usize, usize),
    right_gain: Option<f64>,
    follow_surface: bool,
}

impl Pipeline {
    pub fn new(calib: &StereoCalib, size: (u32, u32), opts: PipelineOptions) -> Result<Pipeline, PipelineError> {
        if let Some((w, h)) = calib.image_size {
            if (w, h) != size {
                return Err(PipelineError::ImageSize(size.0 as usize, size.1 as usize, w, h));
            }
        }
        let rect = match opts.alpha {
            Some(alpha) => Rectification::compute(calib, size, alpha)?,
            None => Rectification::compute_keeping_views(calib, size)?,
        };
        if rect.is_vertical() {
            return Err(PipelineError::VerticalRig);
        }
        let n = opts.matching.num_disparities as i32;
        let min_disparity = opts.min_disparity.unwrap_or(if rect.disparity_sign < 0 { -(n - 1) } else { 0 });
        let params = MatchParams { min_disparity, ..opts.matching }.validate()?;
        let maps = rect.maps(calib);
        // A view's points at the range's end are not where the object is (`drop_range_edges`).
        let matcher = StereoMatcher::new(params).drop_range_edges(true);
        Ok(Pipeline { rect, maps, matcher, chroma: opts.chroma, size: (size.0 as usize, size.1 as usize), right_gain: opts.right_gain, follow_surface: opts.follow_surface })
    }

    pub fn matcher(&self) -> &StereoMatcher {
        &self.matcher
    }

    /// Whether views are refined by a window that follows the surface
    /// ([`PipelineOptions::follow_surface`]).
    pub fn follows_surface(&self) -> bool {
        self.follow_surface
    }

    /// An assistant for this rig's rectification and this matcher's search range.
    pub fn assistant(&self, params: AssistParams) -> Assistant {
        let p = self.matcher.params();
        Assistant::new(params, &self.rect, (p.min_disparity, p.max_disparity()))
    }

    /// Decodes a frame and checks it has the size the pipeline was built for: the raw RGB
    /// pair.
    pub fn decode(&self, frame: &StereoFrame) -> Result<(Vec<u8>, Vec<u8>), FrameError> {
        let (lw, lh, left) = frame.left.to_rgb().map_err(|source| FrameError::Decode { side: "left", source })?;
        let (rw, rh, right) = frame.right.to_rgb().map_err(|source| FrameError::Decode { side: "right", source })?;
        if (lw, lh) != self.size || (rw, rh) != self.size {
            return Err(FrameError::Size(lw, lh, rw, rh, self.size.0, self.size.1));
        }
        Ok((left, right))
    }

    /// Decodes, rectifies and (with `segment`) segments a frame for matching.
    pub fn prepare_frame(&self, frame: &StereoFrame, segment: bool, plate: Option<&RectifiedPlate>) -> Result<Prepared, FrameError> {
        let (left, right) = self.decode(frame)?;
        Ok(self.prepare_rgb(&left, &right, segment, plate)?)
    }

    /// Matches a prepared frame: over the intervals the assistant plans, with
    /// self-correction, or over the full range without one.
    pub fn match_frame(&mut self, seq: u64, frame: &Prepared, assist: Option<Assist>) -> Result<AssistedMatch, PipelineError> {
        match assist {
            Some(a) => self.match_assisted(seq, frame, a.assistant, a.poses),
            None => {
                let (w, h) = self.size;
                let intervals = self.matcher.full_intervals(w, h, frame.mask.as_deref());
                let (disparity, stats, match_ms) = self.match_gray(&frame.left_gray, &frame.right_gray, &intervals)?;
                Ok(AssistedMatch { seq, disparity, stats, outcome: AssistOutcome { match_ms, first_match_ms: match_ms, ..Default::default() }, assisted: false })
            }
        }
    }

    /// One frame's whole path: decode and size check → rectify and segment → assisted or
    /// full-range match → triangulate.
    pub fn process_frame(&mut self, frame: &StereoFrame, segment: bool, plate: Option<&RectifiedPlate>, assist: Option<Assist>) -> Result<View, FrameError> {
        let prepared = self.prepare_frame(frame, segment, plate)?;
        let m = self.match_frame(frame.seq, &prepared, assist)?;
        Ok(self.finish_view(prepared, m))
    }

    /// Rectifies a raw RGB pair.
    pub fn rectify_rgb(&self, left: &[u8], right: &[u8]) -> (Vec<u8>, Vec<u8>) {
        let (w, h) = (self.size.0 as u32, self.size.1 as u32);
        (self.maps.0.remap::<3>(left, w, h), self.maps.1.remap::<3>(right, w, h))
    }

    /// Rectifies a background plate (raw left image of the empty scene, RGB, the cameras'
    /// size), once for all the frames it keys.
    pub fn rectify_plate(&self, raw: &[u8]) -> RectifiedPlate {
        RectifiedPlate(self.maps.0.remap::<3>(raw, self.size.0 as u32, self.size.1 as u32))
    }

    /// Rectifies a mask given in raw left coordinates.
    pub fn rectify_left_mask(&self, mask: &[u8]) -> Vec<u8> {
        let m = self.maps.0.remap::<1>(mask, self.size.0 as u32, self.size.1 as u32);
        m.into_iter().map(|v| if v >= 128 { 255 } else { 0 }).collect()
    }

    /// Rectifies (and, with `segment`, segments) a raw RGB pair for matching.
    pub fn prepare_rgb(&self, left: &[u8], right: &[u8], segment: bool, plate: Option<&RectifiedPlate>) -> Result<Prepared, PipelineError> {
        let (w, h) = self.size;
        // The right image is matched in grey only: sampled and converted in one pass.
        let (left_rgb, left_gray) = self.maps.0.remap_rgb_gray(left, w as u32, h as u32);
        let right_gray = self.maps.1.remap_gray(right, w as u32, h as u32);
        let (mask, key) = if segment {
            let (mask, key) = self.chroma.segment_keyed(&left_rgb, w, h, plate.map(|p| &p.0[..]))?;
            (Some(mask), Some(key))
        } else {
            (None, None)
        };
        let mut prepared = Prepared::new(left_rgb, left_gray, right_gray, mask, key);
        self.balance(&mut prepared);
        Ok(prepared)
    }

    /// Sets the gain every right image is scaled by ([`PipelineOptions::right_gain`]).
    pub fn set_right_gain(&mut self, gain: Option<f64>) {
        self.right_gain = gain;
    }

    /// Scales a prepared pair's right image by the scan's contrast gain
    /// ([`PipelineOptions::right_gain`]), once.
    pub fn balance(&self, frame: &mut Prepared) {
        if let (Some(g), None) = (self.right_gain, frame.right_gain) {
            frame.right_clip = crate::stereo::gain::scale_contrast(&mut frame.right_gray, g);
            frame.right_gain = Some(g);
        }
    }

    /// Matches frame `seq` over the intervals the assistant plans from `poses`; a result the
    /// assistant rejects is matched again over the full range (both calls are timed).
    fn match_assisted(&mut self, seq: u64, frame: &Prepared, assistant: &mut Assistant, poses: &crate::register::posestore::PoseSnapshot) -> Result<AssistedMatch, PipelineError> {
        let plan = assistant.plan(seq, frame.mask.as_deref(), poses);
        let mut outcome = AssistOutcome::of(&plan);
        let (mut disparity, mut stats, ms) = self.match_gray(&frame.left_gray, &frame.right_gray, &plan.intervals)?;
        outcome.match_ms = ms;
        outcome.first_match_ms = ms;
        let t0 = Instant::now();
        let verdict = assistant.accept(seq, &plan, &disparity, frame.mask.as_deref(), &stats);
        outcome.accept_ms = t0.elapsed().as_secs_f64() * 1e3;
        outcome.interval_ms += outcome.accept_ms;
        if let Some(why) = verdict {
            let full = Plan { intervals: self.matcher.full_intervals(self.size.0, self.size.1, frame.mask.as_deref()), full_range: Some(why.clone()), ..plan };
            let (d, s, ms) = self.match_gray(&frame.left_gray, &frame.right_gray, &full.intervals)?;
            let accepted = assistant.accept(seq, &full, &d, frame.mask.as_deref(), &s);
            debug_assert!(accepted.is_none(), "a full-range result is always accepted");
            outcome.rejected = Some(stats);
            outcome.fallback = Some(why);
            outcome.match_ms += ms;
            (disparity, stats) = (d, s);
        } else {
            assistant.recycle(plan);
        }
        Ok(AssistedMatch { seq, disparity, stats, outcome, assisted: true })
    }

    /// Triangulates a matched frame into a [`View`].
    pub fn finish_view(&self, frame: Prepared, mut m: AssistedMatch) -> View {
        let clipped_px = crate::stereo::gain::drop_clipped(&mut m.disparity, &frame.left_gray, &frame.right_gray, frame.right_clip);
        m.stats.matched -= clipped_px;
        // How far inside the silhouette each pixel lies: the fusion weighs the points near it
        // down (FuseParams::rim_weight_px), and those within ChromaKey::rim_px are registered
        // with, not fused.
        let rim = frame.mask.as_deref().map(|mask| crate::segment::rim_distance(mask, m.disparity.width, m.disparity.height));
        // Registration takes the matcher's own map: on the refined one a sphere's ICP slid
        // and a realistic recording's fitted axis moved (docs/matcher.md, "The window that
        // follows the surface").
        let (mut followed, mut follow_ms, mut rim_profile) = (Default::default(), 0.0, Default::default());
        let unrefined = self.follow_surface.then(|| {
            let own = m.disparity.clone();
            let t0 = Instant::now();
            // The silhouette's edge lends the windows no samples (stereo::follow::SILHOUETTE_PX).
            followed = crate::stereo::follow::refine_following(&frame.left_gray, &frame.right_gray, frame.mask.as_deref(), &mut m.disparity);
            // And the pixels nearest the silhouette take the rim's profile.
            if let Some(rim) = rim.as_deref() {
                rim_profile = crate::stereo::follow::extrapolate_rim(&mut m.disparity, rim, self.rect.disparity_sign);
            }
            follow_ms = t0.elapsed().as_secs_f64() * 1e3;
            own
        });
        let (all, inner) = triangulate(&m.disparity, &self.rect, &frame.left_rgb, rim.as_deref().map(|d| (d, self.chroma.rim_px)));
        let (cloud, for_registration) = match (inner, &unrefined) {
            (inner, Some(own)) => (inner.unwrap_or(all), Some(triangulate(own, &self.rect, &frame.left_rgb, None).0)),
            (Some(inner), None) => (inner, Some(all)),
            (None, None) => (all, None),
        };
        let match_ms = m.outcome.match_ms;
        View {
            disparity: m.disparity,
            left_rgb: frame.left_rgb,
            mask: frame.mask,
            cloud,
            stats: m.stats,
            match_ms,
            assist: m.assisted.then_some(m.outcome),
            key: frame.key,
            right_near_white: frame.right_near_white,
            clipped_px,
            for_registration,
            followed,
            rim_profile,
            follow_ms,
            matched_disparity: unrefined,
        }
    }

    /// Processes a raw RGB pair. `segment`: match only the chroma-keyed foreground.
    pub fn process_rgb(&mut self, left: &[u8], right: &[u8], segment: bool) -> Result<View, PipelineError> {
        let frame = self.prepare_rgb(left, right, segment, None)?;
        self.process_prepared(frame)
    }

    /// Matches a prepared pair over the full range and triangulates it.
    pub fn process_prepared(&mut self, frame: Prepared) -> Result<View, PipelineError> {
        let m = self.match_frame(0, &frame, None)?;
        Ok(self.finish_view(frame, m))
    }

    /// Runs the matcher alone on rectified grey images and times it.
    pub fn match_gray(&mut self, left: &[u8], right: &[u8], intervals: &DisparityIntervals) -> Result<(DisparityMap, MatchStats, f64), PipelineError> {
        let (w, h) = self.size;
        let mut out = DisparityMap::new(w, h);
        let lv = GrayView::new(w, h, left).ok_or(MatchError::Buffer(left.len(), w * h))?;
        let rv = GrayView::new(w, h, right).ok_or(MatchError::Buffer(right.len(), w * h))?;
        let t0 = Instant::now();
        let stats = self.matcher.compute(lv, rv, intervals, &mut out)?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok((out, stats, ms))
    }
}
