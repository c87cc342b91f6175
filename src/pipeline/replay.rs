//! Runs the pipeline over any [`StereoSource`] and writes the results folder of the
//! recording spec: `manifest.json`, `views/`, `disparity/`, `report.json`.
//!
//! The manifest says `running` from the first frame on and is rewritten after every frame,
//! so an interrupted run leaves its finished views and an honest status behind; it ends
//! `complete`, or `failed` with the reason.
//!
//! With registration on, every view is registered as it comes ([`crate::register::ring`]) and
//! `poses.jsonl` is rewritten after each frame; at the end the loop is closed (when the views
//! complete a turn), the model is merged from `views/` with the final poses into 1 mm voxels,
//! cleaned of isolated points, and written as `model.ply`, and the axis estimated from the
//! poses as `turntable_estimated.yaml`. Where the recording has `gt/poses.jsonl` (and
//! `gt/mesh.ply`), the poses (and the model) are scored against them in `report.json`.

use std::path::Path;
use std::sync::Arc;

use serde_json::{json, Value};

use super::registered::{finish_registration, register_view, ModelOptions, RegistrationInputs};
use super::results::{score_against_gt, GtScore, ResultsError, ResultsWriter};
use super::truth::{GtDisparities, TruthError};
use super::{Assist, FrameError, Pipeline, PipelineError, PipelineOptions, RectifiedPlate};
use crate::assist::{AssistParams, Assistant};
use crate::hw::{CaptureError, StereoFrame, StereoSource};
use crate::recording::TurntableAxis;
use crate::register::posestore::PoseStore;
use crate::register::ring::{Registrar, RegistrationParams};

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    /// The rig's pipeline cannot be set up (parameters, the calibration against the frames).
    #[error("{0}")]
    Setup(PipelineError),
    #[error("frame seq {seq}: {source}")]
    Frame { seq: u64, source: FrameError },
    #[error("frame seq {seq}: {source}")]
    GroundTruth { seq: u64, source: TruthError },
    /// The recording's ground truth cannot be opened.
    #[error(transparent)]
    Truth(#[from] TruthError),
    #[error(transparent)]
    Results(#[from] ResultsError),
    /// A file beside the frames (calibrated axis, ground truth) is unusable.
    #[error("{0}")]
    SideFile(String),
    /// The run stopped before it wrote anything into its results folder.
    #[error(transparent)]
    BeforeResults(Box<ReplayError>),
}

impl ReplayError {
    /// Whether the run stopped because its results could not be written (not because of
    /// its input).
    pub fn is_output(&self) -> bool {
        match self {
            ReplayError::BeforeResults(e) => e.is_output(),
            e => matches!(e, ReplayError::Results(ResultsError::Output { .. })),
        }
    }

    /// Whether the results folder holds what the run wrote before it stopped (its manifest
    /// `failed`, with this error as the reason).
    pub fn wrote_results(&self) -> bool {
        !matches!(self, ReplayError::BeforeResults(_))
    }

    /// `e`, met before the run wrote anything into its results folder.
    fn before_results(e: impl Into<ReplayError>) -> ReplayError {
        ReplayError::BeforeResults(Box::new(e.into()))
    }
}

/// What to do besides matching.
#[derive(Debug, Clone, Default)]
pub struct ReplayOptions {
    pub pipeline: PipelineOptions,
    /// Stop after this many frames.
    pub max_frames: Option<usize>,
    /// Segment the blue screen (else every pixel is matched).
    pub segment: bool,
    /// An image of the empty scene (raw left camera, RGB) that segmentation also keys against.
    pub plate: Option<Vec<u8>>,
    /// Register the views and build the model (None: views only).
    pub registration: Option<RegistrationParams>,
    /// How `model.ply` is merged and cleaned.
    pub model: ModelOptions,
    /// Registration-assisted matching (needs `registration`; None: every frame searches the
    /// full range).
    pub assist: Option<AssistParams>,
    /// A calibrated turntable axis to register with instead of the recording's own
    /// `turntable.yaml` (`spinscan calibrate turntable`'s, for a recording made before it).
    pub turntable_axis: Option<TurntableAxis>,
}

impl ReplayOptions {
    /// What `spinscan replay` does by default: segment, register, a 1 mm model cleaned with
    /// the default thresholds.
    pub fn with_registration(pipeline: PipelineOptions) -> ReplayOptions {
        ReplayOptions { pipeline, segment: true, registration: Some(RegistrationParams::default()), model: ModelOptions::default(), assist: Some(AssistParams::default()), ..Default::default() }
    }
}

/// Summary of a finished run.
#[derive(Debug, Clone)]
pub struct ReplaySummary {
    pub frames: usize,
    pub mean_match_ms: f64,
    pub gt: Option<GtScore>,
    /// Where `gt`'s truth came from: `recorded`, `rendered` or `mixed` (`GtSource::name`).
    pub gt_disparity: Option<&'static str>,
    pub disparity_sign: i32,
    /// The `registration` section of `report.json`, when registration ran.
    pub registration: Option<Value>,
}

/// Replays a recording into `out`, scoring each frame against its ground-truth disparity
/// where the recording has one (`gt/disparity/`, or rendered from `gt/mesh.ply`).
pub fn run_recording(recording: crate::recording::Recording, out: &Path, opts: &ReplayOptions, progress: &mut dyn FnMut(usize, u64, f64)) -> Result<ReplaySummary, ReplayError> {
    let dir = recording.dir.clone();
    // The files beside the frames, read before anything is written.
    let (inputs, gt) = (|| -> Result<_, ReplayError> {
        let calibrated_axis = match &opts.turntable_axis {
            Some(axis) => Some(axis.clone()),
            None => TurntableAxis::read_calibrated(&dir).map_err(|e| ReplayError::SideFile(format!("calibrated turntable axis: {e}")))?,
        };
        let mut inputs = RegistrationInputs { calibrated_axis, ..Default::default() };
        let gt = GtDisparities::open(&dir)?;
        if opts.registration.is_some() {
            inputs.gt_poses = crate::recording::read_gt_cam_from_obj(&dir).map_err(|e| ReplayError::SideFile(format!("ground truth: {e}")))?;
            inputs.gt_mesh = gt.mesh();
        }
        Ok((inputs, gt))
    })()
    .map_err(ReplayError::before_results)?;
    run(&mut crate::hw::replay::ReplaySource::new(recording), out, opts, gt.any().then_some(&gt), &inputs, progress)
}

/// Processes every frame of `source` into `out`, scoring each frame's disparities against
/// `gt` where it has that frame's. `progress(done, seq)` is called after each frame.
pub fn run(
    source: &mut dyn StereoSource,
    out: &Path,
    opts: &ReplayOptions,
    gt: Option<&GtDisparities>,
    inputs: &RegistrationInputs,
    progress: &mut dyn FnMut(usize, u64, f64),
) -> Result<ReplaySummary, ReplayError> {
    let calib = source.calibration().clone();
    // Everything up to the results folder's creation: an error here has written nothing.
    let started = (|| -> Result<_, ReplayError> {
        let Some(first) = source.next_frame()? else {
            return Ok(None);
        };
        let (w, h, _) = first.left.to_rgb().map_err(|source| ReplayError::Frame { seq: first.seq, source: FrameError::Decode { side: "left", source } })?;
        let pipe = Pipeline::new(&calib, (w as u32, h as u32), opts.pipeline.clone()).map_err(ReplayError::Setup)?;
        let plate = opts.plate.as_deref().map(|p| pipe.rectify_plate(p));
        let fitted = super::range::fit(pipe, &calib, &first, opts.segment, plate.as_ref(), &opts.pipeline).map_err(|source| ReplayError::Frame { seq: first.seq, source })?;
        let results = ResultsWriter::create(out, &source.describe(), fitted.pipe.rect.disparity_sign)?;
        Ok(Some((first, plate, fitted, results)))
    })()
    .map_err(ReplayError::before_results)?;
    let Some((first, plate, fitted, mut results)) = started else {
        let w = ResultsWriter::create(out, &source.describe(), 1).map_err(ReplayError::before_results)?;
        w.finish(None)?;
        return Ok(ReplaySummary { frames: 0, mean_match_ms: 0.0, gt: None, gt_disparity: None, disparity_sign: 1, registration: None });
    };
    let (mut pipe, fit, contrast) = (fitted.pipe, fitted.range, fitted.contrast);
    let store = Arc::new(PoseStore::new());
    let mut registrar = opts.registration.clone().map(|p| super::registrar(p, inputs.calibrated_axis.as_ref(), Some(&pipe.rect), store.clone()));
    // Assistance needs the registered motion: without registration every frame is full range.
    let mut assistant = match (&opts.assist, &registrar) {
        (Some(a), Some(_)) => Some(pipe.assistant(a.clone())),
        _ => None,
    };
    results.set_matching(super::results::matching_entry(&pipe, assistant.as_ref().map(|a| a.params()), fit.as_ref(), contrast.as_ref()));
    let run = Run { pipe: &mut pipe, plate: plate.as_ref(), results: &mut results, opts, gt, registrar: registrar.as_mut(), assistant: assistant.as_mut(), store: &store, progress };
    let outcome = run.all(source, first).and_then(|mut summary| {
        if let Some(reg) = registrar.as_mut() {
            summary.registration = Some(finish_registration(reg, &mut results, &opts.model, inputs)?);
        }
        Ok(summary)
    });
    let failure = outcome.as_ref().err().map(|e| e.to_string());
    results.finish(failure.as_deref())?;
    outcome
}

/// One run's pipeline, results, registration and assistance.
struct Run<'a> {
    pipe: &'a mut Pipeline,
    /// `opts.plate`, rectified.
    plate: Option<&'a RectifiedPlate>,
    results: &'a mut ResultsWriter,
    opts: &'a ReplayOptions,
    gt: Option<&'a GtDisparities>,
    registrar: Option<&'a mut Registrar>,
    assistant: Option<&'a mut Assistant>,
    store: &'a PoseStore,
    progress: &'a mut dyn FnMut(usize, u64, f64),
}

impl Run<'_> {
    fn all(mut self, source: &mut dyn StereoSource, first: StereoFrame) -> Result<ReplaySummary, ReplayError> {
        let (mut match_ms, mut gt_sum) = (0.0, (0usize, 0.0, 0.0, 0.0));
        // Per scored frame, where its truth came from.
        let mut gt_sources = Vec::new();
        let mut next = Some(first);
        while let Some(frame) = next.take() {
            let seq = frame.seq;
            let poses = self.store.snapshot();
            let assist = self.assistant.as_deref_mut().map(|assistant| Assist { assistant, poses: &poses });
            let view = self.pipe.process_frame(&frame, self.opts.segment, self.plate, assist).map_err(|source| ReplayError::Frame { seq, source })?;
            let mut entry = self.results.write_view(&frame, &view, self.opts.assist.as_ref())?;
            let truth = match self.gt {
                Some(g) => g.get(seq, &self.pipe.rect).map_err(|source| ReplayError::GroundTruth { seq, source })?,
                None => None,
            };
            if let Some((gt, source)) = truth {
                let s = score_against_gt(&view.disparity, &gt);
                entry["gt_coverage"] = json!(s.coverage);
                entry["gt_bad2_of_matched"] = json!(s.bad2_of_matched);
                entry["gt_mean_abs_err_px"] = json!(s.mean_abs_err_px);
                entry["gt_disparity"] = json!(source.name());
                gt_sources.push(source);
                gt_sum = (gt_sum.0 + s.gt_pixels, gt_sum.1 + s.coverage, gt_sum.2 + s.bad2_of_matched, gt_sum.3 + s.mean_abs_err_px);
            }
            if let Some(reg) = self.registrar.as_deref_mut() {
                if let (Some((fitness, rmse)), Some(a)) = (register_view(reg, &frame, &view, &mut entry), self.assistant.as_deref_mut()) {
                    a.observe_registration(seq, fitness, rmse);
                }
                self.results.write_poses(reg.poses())?;
            }
            match_ms += view.match_ms;
            self.results.push_frame(entry)?;
            let done = self.results.frame_count();
            (self.progress)(done, seq, view.match_ms);
            if self.opts.max_frames.is_some_and(|m| done >= m) {
                break;
            }
            next = source.next_frame()?;
        }
        let n = self.results.frame_count();
        let gt = (!gt_sources.is_empty()).then(|| {
            let k = gt_sources.len() as f64;
            GtScore { gt_pixels: gt_sum.0, coverage: gt_sum.1 / k, bad2_of_matched: gt_sum.2 / k, mean_abs_err_px: gt_sum.3 / k }
        });
        Ok(ReplaySummary { frames: n, mean_match_ms: match_ms / n.max(1) as f64, gt, gt_disparity: super::truth::sources_name(gt_sources), disparity_sign: self.results.disparity_sign(), registration: None })
    }
}
