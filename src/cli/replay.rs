//! `spinscan replay`: a recording through the pipeline into a results folder.

use std::path::{Path, PathBuf};

use clap::Args;
use serde_json::json;

use super::{input, output, progress, AssistModeArgs, Failure, KeyArgs, MatchArgs, RectArgs, RegistrationArgs};
use spinscan::pipeline::replay::{self, ReplayOptions};
use spinscan::pipeline::PipelineOptions;
use spinscan::recording::Recording;

#[derive(Args)]
pub struct ReplayArgs {
    /// Recording folder (calib.yaml or intrinsics.yml + extrinsics.yml, frames.jsonl, images).
    pub dir: PathBuf,
    /// Results folder (may be the recording folder itself).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Process at most this many frames.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Match every pixel instead of segmenting the blue screen.
    #[arg(long)]
    pub no_segment: bool,
    #[command(flatten)]
    pub key: KeyArgs,
    #[command(flatten)]
    pub rect: RectArgs,
    #[command(flatten)]
    pub matching: MatchArgs,
    #[command(flatten)]
    pub reg: RegistrationArgs,
    #[command(flatten)]
    pub assist: AssistModeArgs,
    /// Register with this calibrated turntable axis (a turntable.yaml from `spinscan
    /// calibrate turntable`) instead of the recording's own turntable.yaml, if any.
    #[arg(long, value_name = "FILE")]
    pub turntable: Option<PathBuf>,
}

pub fn cmd_replay(a: ReplayArgs) -> Result<(), Failure> {
    let turntable_axis = match &a.turntable {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(|e| input(format!("--turntable {}: {e} (expected a turntable.yaml from `spinscan calibrate turntable`)", path.display())))?;
            Some(spinscan::recording::TurntableAxis::parse(path, &text).map_err(input)?)
        }
        None => None,
    };
    let rec = Recording::open(&a.dir).map_err(input)?;
    if let Some(line) = rec.torn_line {
        eprintln!("replay: warning: skipped the torn last line {line} of {}", a.dir.join("frames.jsonl").display());
    }
    if let (Some(p), true) = (&a.key.plate, a.no_segment) {
        return Err(input(format!("--plate {} is used by the blue-screen segmentation, which --no-segment turns off", p.display())));
    }
    let plate = a.key.load_plate((rec.image_size.0 as usize, rec.image_size.1 as usize), "the recording's images")?;
    let opts = ReplayOptions {
        max_frames: a.frames,
        segment: !a.no_segment,
        plate,
        assist: a.assist.params(!a.reg.no_register)?,
        turntable_axis,
        ..a.reg.options(PipelineOptions {
            alpha: a.rect.alpha,
            min_disparity: a.matching.min_disparity,
            matching: a.matching.params_with_default(128)?,
            chroma: a.key.chroma(),
            fit_range: a.matching.range_unset(),
            right_gain: None,
            follow_surface: !a.matching.no_follow_surface,
        })?
    };
    let total = a.frames.map_or(rec.frames.len(), |m| m.min(rec.frames.len()));
    let summary = replay::run_recording(rec, &a.out, &opts, &mut |done, seq, ms| {
        progress::show(format!("replay: {done}/{total} frames (seq {seq}, matched in {ms:.0} ms)"))
    });
    progress::finish();
    let summary = summary.map_err(|e| {
        // (A run that stopped before writing anything has no results to point to.)
        let why = if e.wrote_results() { format!("{e} (results so far are in {}, manifest status `failed`)", a.out.display()) } else { e.to_string() };
        if e.is_output() {
            output(why)
        } else {
            input(why)
        }
    })?;
    println!("{}", summary_json(&summary, &a.out));
    Ok(())
}

pub fn summary_json(s: &replay::ReplaySummary, out: &Path) -> serde_json::Value {
    let mut j = json!({"out": out, "frames": s.frames, "mean_match_ms": s.mean_match_ms, "disparity_sign": s.disparity_sign});
    if let Some(gt) = s.gt {
        j["gt_coverage"] = json!(gt.coverage);
        j["gt_bad2_of_matched"] = json!(gt.bad2_of_matched);
        j["gt_mean_abs_err_px"] = json!(gt.mean_abs_err_px);
        j["gt_disparity"] = json!(s.gt_disparity);
    }
    if let Some(r) = &s.registration {
        j["registration"] = r.clone();
    }
    j
}
