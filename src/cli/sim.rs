//! `spinscan sim render` and `spinscan demo`: the simulated lab, and the README's demo on it.

use std::path::PathBuf;
use std::time::Instant;

use clap::{Args, Subcommand};
use serde_json::json;

use super::replay::summary_json;
use super::{input, output, progress, AssistModeArgs, Failure, MatchArgs, RegistrationArgs};
use spinscan::hw::sim::{Lab, RenderOptions, SimObject};
use spinscan::io;
use spinscan::pipeline::replay::{self, ReplayOptions};
use spinscan::pipeline::PipelineOptions;

#[derive(Subcommand)]
pub enum SimCommand {
    /// Renders a recording (calib.yaml, frames.jsonl, left/, right/) with ground truth (gt/).
    Render(SimRenderArgs),
}

#[derive(Args)]
pub struct SimRenderArgs {
    /// Built-in object: sphere, egg, vase or torus.
    #[arg(long, conflicts_with = "mesh")]
    pub object: Option<String>,
    /// A calibration target instead of an object: `chessboard` (the board held at varied
    /// poses, for `calibrate stereo`) or `chessboard-on-table` (the board standing on the
    /// turntable as it turns, for `calibrate turntable`). The truth is under gt/.
    /// With `chessboard-on-table`, `--object NAME` sets the lab up as for that object's
    /// recordings (the cameras aimed at its middle), so the axis calibrated is theirs.
    #[arg(long, conflicts_with = "mesh")]
    pub target: Option<TargetArg>,
    /// Target: inner corners of the board, along a row × rows.
    #[arg(long, default_value = "9x6", requires = "target")]
    pub board: spinscan::calib::board::BoardSize,
    /// Target: side of one square, mm.
    #[arg(long, default_value_t = 20.0, requires = "target")]
    pub square_mm: f64,
    /// `chessboard`: the board's distance from the left camera, mm.
    #[arg(long, default_value_t = 600.0, requires = "target")]
    pub distance_mm: f64,
    /// `chessboard-on-table`: the table turns from −SWEEP to +SWEEP degrees over the frames.
    #[arg(long, default_value_t = 50.0, requires = "target")]
    pub sweep_deg: f64,
    /// A triangle mesh (PLY) to put on the turntable instead, +y up.
    #[arg(long)]
    pub mesh: Option<PathBuf>,
    /// Scale applied to the mesh's coordinates to get millimetres (e.g. 1000 for metres).
    #[arg(long, default_value_t = 1.0, requires = "mesh")]
    pub mesh_scale: f64,
    /// Triangles of a built-in object's tessellation.
    #[arg(long, default_value_t = 100_000)]
    pub triangles: usize,
    /// Number of stereo pairs.
    #[arg(long, default_value_t = 30)]
    pub frames: usize,
    /// Turntable rotation between consecutive pairs, degrees (counterclockwise from above).
    #[arg(long, default_value_t = 2.0, allow_hyphen_values = true)]
    pub deg_per_frame: f64,
    /// Turntable angle of the first pair, degrees.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub start_deg: f64,
    /// Ideal rectified rig (no distortion, no misalignment) with gt/disparity/.
    #[arg(long)]
    pub ideal: bool,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Contrast of the object's texture, 0 (plain) … 1.
    #[arg(long, default_value_t = 0.8)]
    pub texture_contrast: f64,
    /// Sensor noise, grey levels (standard deviation).
    #[arg(long, default_value_t = 1.5)]
    pub noise: f64,
    /// Probability that a pair is dropped (a gap in seq), 0 … <1.
    #[arg(long, default_value_t = 0.0)]
    pub drop_probability: f64,
    /// Image size, WIDTH×HEIGHT pixels (`x` or `×`).
    #[arg(long, default_value = "640x480", value_parser = parse_size)]
    pub size: (usize, usize),
    /// The cameras' focal length, pixels. Default: 700 at a width of 640, in proportion at
    /// other widths (the same view at another resolution).
    #[arg(long)]
    pub focal_px: Option<f64>,
    /// Distance between the two cameras, mm; negative puts the right camera left of the left
    /// one (a rig whose disparities are negative; no gt/disparity/ then).
    #[arg(long, default_value_t = 60.0, allow_hyphen_values = true)]
    pub baseline_mm: f64,
    /// Distance from the left camera to the object's middle on the turntable's axis, mm.
    /// The object's disparities are about focal × baseline / distance at its middle: the
    /// printed `object_disparity_px` gives their span, to set `--num-disparities` by. With
    /// `--target chessboard-on-table`: the lab the board stands in.
    #[arg(long, default_value_t = 450.0)]
    pub object_distance_mm: f64,
    /// How far the cameras look down at the object, degrees below the horizontal (with
    /// `--target chessboard-on-table`: at the table the board stands on).
    #[arg(long, default_value_t = 12.0, allow_hyphen_values = true)]
    pub camera_tilt_deg: f64,
    /// Where the object stands off the turntable's axis, X,Z mm in the table's plane (X to the
    /// cameras' right, Z towards them at 0°): it swings around the axis as the table turns,
    /// as an object placed by hand does.
    #[arg(long, default_value = "0,0", value_parser = parse_offset, allow_hyphen_values = true, conflicts_with = "target")]
    pub object_offset_mm: [f64; 2],
    /// How far the right camera is turned towards the left one's line of sight, degrees: a
    /// toed-in rig, both cameras aimed at the object at atan(baseline / distance) (7.6° at
    /// the default 60 mm and 450 mm). Such a rig writes no gt/disparity/.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub toe_in_deg: f64,
    /// Output folder (must not hold a recording already).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct DemoArgs {
    /// Output folder: the recording in `recording/`, the results in `results/`.
    #[arg(short = 'o', long = "out", default_value = "out/demo")]
    pub out: PathBuf,
    /// Built-in object: sphere, egg, vase or torus.
    #[arg(long, default_value = "torus")]
    pub object: String,
    /// Number of stereo pairs.
    #[arg(long, default_value_t = 8)]
    pub frames: usize,
    /// Turntable rotation between pairs, degrees.
    #[arg(long, default_value_t = 3.0, allow_hyphen_values = true)]
    pub deg_per_frame: f64,
    /// Use the realistic rig (distortion, misalignment; no ground-truth disparity) instead of
    /// the ideal one.
    #[arg(long)]
    pub realistic: bool,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[command(flatten)]
    pub matching: MatchArgs,
    #[command(flatten)]
    pub reg: RegistrationArgs,
    #[command(flatten)]
    pub assist: AssistModeArgs,
}

/// `sim render --target`.
#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum TargetArg {
    Chessboard,
    ChessboardOnTable,
}

pub fn cmd_sim_render(a: SimRenderArgs) -> Result<(), Failure> {
    if let Some(target) = a.target {
        return render_target(&a, target);
    }
    let object = match (&a.object, &a.mesh) {
        (_, Some(path)) => {
            let mesh = io::ply::read_ply(path).map_err(input)?;
            if mesh.triangles.is_empty() {
                return Err(input(format!("{} has no faces: `sim render --mesh` needs a triangle mesh, not a point cloud", path.display())));
            }
            if !(a.mesh_scale.is_finite() && a.mesh_scale > 0.0) {
                return Err(input(format!("--mesh-scale must be a positive number, got {}", a.mesh_scale)));
            }
            SimObject::Mesh(mesh, a.mesh_scale)
        }
        (name, None) => SimObject::Builtin { name: name.clone().unwrap_or_else(|| "egg".into()), triangles: a.triangles },
    };
    let opts = RenderOptions {
        object,
        frames: a.frames,
        start_deg: a.start_deg,
        deg_per_frame: a.deg_per_frame,
        ideal: a.ideal,
        seed: a.seed,
        texture_contrast: a.texture_contrast,
        noise_sigma: a.noise,
        drop_probability: a.drop_probability,
        image_size: a.size,
        lab: Lab { focal_px: a.focal_px, baseline_mm: a.baseline_mm, object_distance_mm: a.object_distance_mm, camera_tilt_deg: a.camera_tilt_deg, object_offset_mm: a.object_offset_mm, toe_in_deg: a.toe_in_deg },
    };
    let prepared = spinscan::hw::sim::PreparedRender::new(&opts).map_err(input)?;
    let disparities = prepared.object_disparities();
    // The default range of `replay`, `demo` and `bench table1`, on the rig's side of zero.
    let range = if a.baseline_mm > 0.0 { (0.0, 127.0) } else { (-127.0, 0.0) };
    if disparities.0 < range.0 || disparities.1 > range.1 {
        eprintln!(
            "sim render: note: the object's disparities span {:.1} … {:.1} px; `replay`, `demo` and `bench table1` search {} … {} by default: set --min-disparity and --num-disparities to cover them",
            disparities.0, disparities.1, range.0, range.1
        );
    }
    let t0 = Instant::now();
    let rec = prepared.render(&a.out, &mut |done, total| progress::show(format!("sim render: {done}/{total} pairs")));
    progress::finish();
    let rec = rec.map_err(|e| match e {
        spinscan::hw::sim::SimError::Recording(
            spinscan::recording::RecordingError::Io { .. } | spinscan::recording::RecordingError::Write { .. } | spinscan::recording::RecordingError::Exists(_),
        ) => output(e),
        other => input(other),
    })?;
    let seconds = t0.elapsed().as_secs_f64();
    println!(
        "{}",
        json!({"out": a.out, "frames": rec.frames.len(), "ideal": a.ideal, "width": rec.image_size.0, "height": rec.image_size.1,
               "seconds": seconds, "gt_disparity": a.out.join("gt/disparity").is_dir(), "object_disparity_px": [disparities.0, disparities.1]})
    );
    Ok(())
}

fn render_target(a: &SimRenderArgs, target: TargetArg) -> Result<(), Failure> {
    if a.object.is_some() && target == TargetArg::Chessboard {
        return Err(input("--object with --target chessboard: a held board needs no object (--object goes with chessboard-on-table: the lab of that object's recordings)"));
    }
    let lab = Lab { focal_px: a.focal_px, baseline_mm: a.baseline_mm, object_distance_mm: a.object_distance_mm, camera_tilt_deg: a.camera_tilt_deg, object_offset_mm: [0.0, 0.0], toe_in_deg: a.toe_in_deg };
    let default = Lab::default();
    if target == TargetArg::Chessboard && (lab.object_distance_mm, lab.camera_tilt_deg) != (default.object_distance_mm, default.camera_tilt_deg) {
        return Err(input("--object-distance-mm and --camera-tilt-deg place the cameras around the turntable: they go with --target chessboard-on-table (a held board's distance is --distance-mm)"));
    }
    use spinscan::hw::sim_target::{render_target_recording, TargetKind, TargetOptions};
    let opts = TargetOptions {
        kind: match target {
            TargetArg::Chessboard => TargetKind::Chessboard,
            TargetArg::ChessboardOnTable => TargetKind::ChessboardOnTable,
        },
        board: spinscan::hw::TargetScene { cols: a.board.cols, rows: a.board.rows, square_mm: a.square_mm, on_table: target == TargetArg::ChessboardOnTable },
        frames: a.frames,
        ideal: a.ideal,
        seed: a.seed,
        noise_sigma: a.noise,
        distance_mm: a.distance_mm,
        sweep_deg: a.sweep_deg,
        object: a.object.clone(),
        image_size: a.size,
        lab,
        ..TargetOptions::default()
    };
    let t0 = Instant::now();
    let done = render_target_recording(&opts, &a.out, &mut |done, total| progress::show(format!("sim render: {done}/{total} target pairs")));
    progress::finish();
    done.map_err(|e| match e {
        spinscan::hw::sim::SimError::Recording(
            spinscan::recording::RecordingError::Io { .. } | spinscan::recording::RecordingError::Write { .. } | spinscan::recording::RecordingError::Exists(_),
        ) => output(e),
        other => input(other),
    })?;
    println!("{}", json!({"out": a.out, "frames": a.frames, "target": a.out.join("gt/board.json"), "ideal": a.ideal, "seconds": t0.elapsed().as_secs_f64()}));
    Ok(())
}

pub fn cmd_demo(a: DemoArgs) -> Result<(), Failure> {
    let (rec_dir, results_dir) = (a.out.join("recording"), a.out.join("results"));
    // The replay's options first: a bad flag costs no render, and leaves the previous demo.
    let replay_opts = ReplayOptions {
        assist: a.assist.params(!a.reg.no_register)?,
        ..a.reg.options(PipelineOptions { min_disparity: a.matching.min_disparity, matching: a.matching.params_with_default(128)?, fit_range: a.matching.range_unset(), follow_surface: !a.matching.no_follow_surface, ..Default::default() })?
    };
    if rec_dir.join("frames.jsonl").exists() {
        std::fs::remove_dir_all(&rec_dir).map_err(|e| output(format!("cannot clear the previous demo in {}: {e}", rec_dir.display())))?;
    }
    let opts = RenderOptions {
        object: SimObject::Builtin { name: a.object.clone(), triangles: 100_000 },
        frames: a.frames,
        deg_per_frame: a.deg_per_frame,
        ideal: !a.realistic,
        seed: a.seed,
        ..RenderOptions::default()
    };
    eprintln!("demo: rendering {} stereo pairs of the `{}` turning on the simulated turntable…", a.frames, a.object);
    let rec = spinscan::hw::sim::render_recording(&opts, &rec_dir, &mut |done, total| progress::show(format!("demo: rendered {done}/{total}")));
    progress::finish();
    let rec = rec.map_err(input)?;
    eprintln!("demo: replaying {} (segment the blue screen, rectify, match, triangulate)…", rec_dir.display());
    let summary = replay::run_recording(rec, &results_dir, &replay_opts, &mut |done, seq, ms| {
        progress::show(format!("demo: replayed {done}/{} (seq {seq}, {ms:.0} ms)", a.frames))
    });
    progress::finish();
    let summary = summary.map_err(input)?;
    eprintln!("demo: recording in {}, results in {} (views/*.ply open in MeshLab or Open3D)", rec_dir.display(), results_dir.display());
    println!("{}", summary_json(&summary, &results_dir));
    Ok(())
}

/// An offset that is not X,Z in millimetres.
#[derive(Debug, thiserror::Error)]
#[error("expected X,Z in mm (e.g. 25,-10), got {0:?}")]
pub struct OffsetSyntax(String);

/// `25,-10` → [25, −10].
fn parse_offset(s: &str) -> Result<[f64; 2], OffsetSyntax> {
    let bad = || OffsetSyntax(s.to_string());
    let (x, z) = s.split_once(',').ok_or_else(bad)?;
    Ok([x.trim().parse().map_err(|_| bad())?, z.trim().parse().map_err(|_| bad())?])
}

/// An image size that is not WIDTHxHEIGHT in whole pixels.
#[derive(Debug, thiserror::Error)]
#[error("expected WIDTHxHEIGHT in whole pixels (e.g. 640x480), got {0:?}")]
pub struct SizeSyntax(String);

/// `640x480` (or `640×480`) → (640, 480).
fn parse_size(s: &str) -> Result<(usize, usize), SizeSyntax> {
    let bad = || SizeSyntax(s.to_string());
    let (w, h) = s.split_once(['x', '×', 'X']).ok_or_else(bad)?;
    Ok((w.trim().parse().map_err(|_| bad())?, h.trim().parse().map_err(|_| bad())?))
}
