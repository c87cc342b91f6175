//! Runs the pipeline over any [`StereoSource`] and writes the results folder of the
//! recording spec: `manifest.json`, `views/`, `disparity/`, `report.json`.
//!
//! The manifest says `running` from the first frame on and is rewritten after every frame,
//! so an interrupted run leaves its finished views and an honest status behind; it ends
//! `complete`, or `failed` with the reason. Registration (model.ply, poses.jsonl) is not part
//! of this stage; per-frame `register_ms` is null until it runs.

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::{json, Value};

use crate::capture::{CaptureError, StereoSource};
use crate::io;
use crate::pipeline::{Pipeline, PipelineError, PipelineOptions};
use crate::stereo::DisparityMap;

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error("frame seq {seq}: {source}")]
    Pipeline { seq: u64, source: PipelineError },
    #[error("frame seq {seq}: {what}")]
    Frame { seq: u64, what: String },
    #[error("cannot write {path}: {what}")]
    Output { path: PathBuf, what: String },
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
}

/// Ground-truth comparison of one disparity map (recordings of ideal rigs carry it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GtScore {
    /// Ground-truth pixels.
    pub gt_pixels: usize,
    /// Fraction of them that got a disparity.
    pub coverage: f64,
    /// Fraction of the covered ones off by more than 2 px.
    pub bad2_of_matched: f64,
    /// Mean |error| over covered pixels, px.
    pub mean_abs_err_px: f64,
}

/// Scores `disp` against `gt` (non-finite = no truth) by magnitude.
pub fn score_against_gt(disp: &DisparityMap, gt: &DisparityMap) -> GtScore {
    let (mut n, mut covered, mut bad, mut err) = (0usize, 0usize, 0usize, 0f64);
    for y in 0..gt.height {
        for x in 0..gt.width {
            let Some(t) = gt.get(x, y) else { continue };
            n += 1;
            if let Some(d) = disp.get(x, y) {
                covered += 1;
                let e = (d.abs() - t.abs()).abs();
                err += e as f64;
                bad += (e > 2.0) as usize;
            }
        }
    }
    GtScore {
        gt_pixels: n,
        coverage: covered as f64 / n.max(1) as f64,
        bad2_of_matched: bad as f64 / covered.max(1) as f64,
        mean_abs_err_px: err / covered.max(1) as f64,
    }
}

/// The results folder, kept consistent on disk after every frame.
pub struct ResultsWriter {
    dir: PathBuf,
    source: String,
    frames: Vec<Value>,
    disparity_sign: i32,
    started: Instant,
}

impl ResultsWriter {
    pub fn create(dir: &Path, source: &str, disparity_sign: i32) -> Result<ResultsWriter, ReplayError> {
        for sub in ["views", "disparity"] {
            let d = dir.join(sub);
            std::fs::create_dir_all(&d).map_err(|e| ReplayError::Output { path: d, what: e.to_string() })?;
        }
        let w = ResultsWriter { dir: dir.to_path_buf(), source: source.to_string(), frames: Vec::new(), disparity_sign, started: Instant::now() };
        w.write_manifest("running", None)?;
        Ok(w)
    }

    fn write_json(&self, name: &str, value: &Value) -> Result<(), ReplayError> {
        let path = self.dir.join(name);
        io::write_atomic(&path, serde_json::to_string_pretty(value).unwrap().as_bytes()).map_err(|e| ReplayError::Output { path, what: e.to_string() })
    }

    fn write_manifest(&self, status: &str, reason: Option<&str>) -> Result<(), ReplayError> {
        let mut m = json!({
            "format": 1,
            "status": status,
            "frames": self.frames.len(),
            "source": self.source,
            "written_by": format!("spinscan {}", env!("CARGO_PKG_VERSION")),
            "elapsed_s": self.started.elapsed().as_secs_f64(),
        });
        if let Some(r) = reason {
            m["reason"] = json!(r);
        }
        self.write_json("manifest.json", &m)
    }

    fn write_report(&self) -> Result<(), ReplayError> {
        let scored: Vec<&Value> = self.frames.iter().filter(|f| f.get("gt_coverage").is_some()).collect();
        let mean = |key: &str, list: &[&Value]| -> Option<f64> {
            let v: Vec<f64> = list.iter().filter_map(|f| f[key].as_f64()).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        let all: Vec<&Value> = self.frames.iter().collect();
        let report = json!({
            "disparity_sign": self.disparity_sign,
            "frames": self.frames,
            "summary": {
                "frames": self.frames.len(),
                "mean_match_ms": mean("match_ms", &all),
                "mean_valid_fraction": mean("valid_fraction", &all),
                "gt_frames": scored.len(),
                "mean_gt_coverage": mean("gt_coverage", &scored),
                "mean_gt_bad2_of_matched": mean("gt_bad2_of_matched", &scored),
            },
        });
        self.write_json("report.json", &report)
    }

    /// Ends the run: `complete`, or `failed` with the reason.
    pub fn finish(&self, failure: Option<&str>) -> Result<(), ReplayError> {
        self.write_report()?;
        match failure {
            None => self.write_manifest("complete", None),
            Some(reason) => self.write_manifest("failed", Some(reason)),
        }
    }
}

/// Summary of a finished run.
#[derive(Debug, Clone)]
pub struct ReplaySummary {
    pub frames: usize,
    pub mean_match_ms: f64,
    pub gt: Option<GtScore>,
    pub disparity_sign: i32,
}

/// Replays a recording into `out`, scoring each frame against its `gt/disparity` file where
/// the recording has one.
pub fn run_recording(recording: crate::recording::Recording, out: &Path, opts: &ReplayOptions, progress: &mut dyn FnMut(usize, u64, f64)) -> Result<ReplaySummary, ReplayError> {
    let dir = recording.dir.clone();
    let gt_for = move |seq: u64| crate::recording::gt_disparity_path(&dir, seq);
    run(&mut crate::recording::ReplaySource::new(recording), out, opts, &gt_for, progress)
}

/// Processes every frame of `source` into `out`. `gt_for(seq)` gives a ground-truth
/// disparity file where one exists. `progress(done, seq)` is called after each frame.
pub fn run(
    source: &mut dyn StereoSource,
    out: &Path,
    opts: &ReplayOptions,
    gt_for: &dyn Fn(u64) -> Option<PathBuf>,
    progress: &mut dyn FnMut(usize, u64, f64),
) -> Result<ReplaySummary, ReplayError> {
    let calib = source.calibration().clone();
    let first = source.next_frame()?;
    let Some(first) = first else {
        let w = ResultsWriter::create(out, &source.describe(), 1)?;
        w.finish(None)?;
        return Ok(ReplaySummary { frames: 0, mean_match_ms: 0.0, gt: None, disparity_sign: 1 });
    };
    let (w, h, _) = first.left.to_rgb().map_err(|what| ReplayError::Frame { seq: first.seq, what })?;
    let mut pipe = Pipeline::new(&calib, (w as u32, h as u32), opts.pipeline.clone()).map_err(|source| ReplayError::Pipeline { seq: first.seq, source })?;
    let mut results = ResultsWriter::create(out, &source.describe(), pipe.rect.disparity_sign)?;
    let outcome = process_all(source, first, &mut pipe, &mut results, opts, gt_for, progress);
    let failure = outcome.as_ref().err().map(|e| e.to_string());
    results.finish(failure.as_deref())?;
    outcome
}

fn process_all(
    source: &mut dyn StereoSource,
    first: crate::capture::StereoFrame,
    pipe: &mut Pipeline,
    results: &mut ResultsWriter,
    opts: &ReplayOptions,
    gt_for: &dyn Fn(u64) -> Option<PathBuf>,
    progress: &mut dyn FnMut(usize, u64, f64),
) -> Result<ReplaySummary, ReplayError> {
    let (mut match_ms, mut gt_sum, mut gt_frames) = (0.0, (0usize, 0.0, 0.0, 0.0), 0usize);
    let mut next = Some(first);
    let size = (pipe.rect.size.0 as usize, pipe.rect.size.1 as usize);
    while let Some(frame) = next.take() {
        let seq = frame.seq;
        let bad = |what: String| ReplayError::Frame { seq, what };
        let (lw, lh, left) = frame.left.to_rgb().map_err(|e| bad(format!("left image: {e}")))?;
        let (rw, rh, right) = frame.right.to_rgb().map_err(|e| bad(format!("right image: {e}")))?;
        if (lw, lh) != size || (rw, rh) != size {
            return Err(bad(format!("images are {lw}×{lh} and {rw}×{rh}, expected {}×{}", size.0, size.1)));
        }
        let view = pipe.process_rgb_with_plate(&left, &right, opts.segment, opts.plate.as_deref()).map_err(|source| ReplayError::Pipeline { seq, source })?;
        let view_path = results.dir.join("views").join(format!("{seq:06}.ply"));
        io::ply::write_ply(&view_path, &view.cloud).map_err(|e| ReplayError::Output { path: view_path, what: e.to_string() })?;
        let disp_path = results.dir.join("disparity").join(format!("{seq:06}.png"));
        io::write_disparity_png(&disp_path, &view.disparity).map_err(|e| ReplayError::Output { path: disp_path, what: e.to_string() })?;
        let mut entry = json!({
            "seq": seq,
            "match_ms": view.match_ms,
            "register_ms": null,
            "mean_search_px": view.stats.mean_search_px(),
            "valid_fraction": view.stats.valid_fraction(),
            // Every frame here is matched with the full search range (no registration yet).
            "fallback": true,
            "points": view.cloud.len(),
            "table_deg": frame.table_deg,
            "t_left_ns": frame.t_left_ns,
            "skew_ns": frame.t_right_ns as i64 - frame.t_left_ns as i64,
        });
        if let Some(gt_path) = gt_for(seq) {
            let gt = io::read_disparity_png(&gt_path, pipe.rect.disparity_sign as f32).map_err(|e| bad(format!("ground truth: {e}")))?;
            if (gt.width, gt.height) != size {
                return Err(bad(format!("ground truth {} is {}×{}, expected {}×{}", gt_path.display(), gt.width, gt.height, size.0, size.1)));
            }
            let s = score_against_gt(&view.disparity, &gt);
            entry["gt_coverage"] = json!(s.coverage);
            entry["gt_bad2_of_matched"] = json!(s.bad2_of_matched);
            entry["gt_mean_abs_err_px"] = json!(s.mean_abs_err_px);
            gt_sum = (gt_sum.0 + s.gt_pixels, gt_sum.1 + s.coverage, gt_sum.2 + s.bad2_of_matched, gt_sum.3 + s.mean_abs_err_px);
            gt_frames += 1;
        }
        match_ms += view.match_ms;
        results.frames.push(entry);
        results.write_manifest("running", None)?;
        progress(results.frames.len(), seq, view.match_ms);
        if opts.max_frames.is_some_and(|m| results.frames.len() >= m) {
            break;
        }
        next = source.next_frame()?;
    }
    let n = results.frames.len();
    let gt = (gt_frames > 0).then(|| {
        let k = gt_frames as f64;
        GtScore { gt_pixels: gt_sum.0, coverage: gt_sum.1 / k, bad2_of_matched: gt_sum.2 / k, mean_abs_err_px: gt_sum.3 / k }
    });
    Ok(ReplaySummary { frames: n, mean_match_ms: match_ms / n.max(1) as f64, gt, disparity_sign: results.disparity_sign })
}
