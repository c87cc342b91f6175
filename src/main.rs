//! `spinscan`: the command-line tool.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, Parser, Subcommand};
use serde_json::json;

use spinscan::assist::{AssistMode, AssistParams};
use spinscan::calib::StereoCalib;
use spinscan::io::{self, LoadedImage};
use spinscan::pipeline::{Pipeline, PipelineOptions};
use spinscan::recording::Recording;
use spinscan::register::{self, IcpParams};
use spinscan::pipeline::replay::{self, ReplayOptions};
use spinscan::hw::sim::{RenderOptions, SimObject};
use spinscan::segment::ChromaKey;
use spinscan::stereo::{DisparityMap, GrayView, MatchParams, StereoMatcher};

mod daemon_cmds;

/// Exit codes, so scripts and systemd can tell kinds of failure apart.
mod exit {
    /// Bad input: unreadable or inconsistent files, impossible parameters.
    pub const INPUT: u8 = 3;
    /// An output could not be written.
    pub const OUTPUT: u8 = 4;
}

#[derive(Parser)]
#[command(name = "spinscan", version, about = "Registration-assisted stereo scanning for turntable labs")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Disparity map of a stereo pair (rectified, or raw with --calib).
    Disparity(DisparityArgs),
    /// Writes the rectified pair of a calibrated raw pair.
    Rectify(RectifyArgs),
    /// Coloured point cloud (PLY, mm, left raw camera frame) of a calibrated raw pair.
    Points(PointsArgs),
    /// Renders a short scan in the simulated lab, records it, and replays it through the
    /// pipeline, scored against the ground truth. Needs no devices and no files.
    Demo(DemoArgs),
    /// The simulated lab.
    #[command(subcommand)]
    Sim(SimCommand),
    /// Runs the pipeline on a recording and writes the results folder (views, disparity,
    /// report, manifest).
    Replay(ReplayArgs),
    /// Registers two scans by ICP (SOURCE onto TARGET), or, with --ring, a ring of scans into
    /// Stanford .conf poses.
    Register(RegisterArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// The daemon's state and the running scan's progress.
    Status(daemon_cmds::SocketArg),
    /// Cameras (with formats), serial ports and the turntable, as the daemon sees them
    /// (--local: this machine's V4L2 devices and serial ports, without the daemon).
    Devices(daemon_cmds::DevicesArgs),
    /// Starts, stops or shows a scan on the daemon.
    #[command(subcommand)]
    Scan(daemon_cmds::ScanCommand),
    /// The daemon's scans with their status.
    Scans(daemon_cmds::SocketArg),
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Throughput of the live pipeline (the daemon's: bounded channel, matcher pool,
    /// registration thread) fed a recording from memory at camera-like paces, and unpaced.
    Live(LiveArgs),
    /// The paper's Table 1 on a recording: matcher time per frame without registration
    /// assistance, with it at each weighting factor w, and with the Kalman-predicted search;
    /// plus accuracy, valid fraction and search width per row, and a Fig. 4-style image.
    Table1(Table1Args),
}

#[derive(Args)]
struct Table1Args {
    /// Recording folder (e.g. from `spinscan sim render`).
    recording: PathBuf,
    /// Weighting factors of the paper's rows, comma-separated.
    #[arg(long, default_value = "0.6,0.8,1,2", value_delimiter = ',')]
    weights: Vec<f64>,
    /// Write the table as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// The Fig. 4-style image (left image, then each row's disparity map).
    #[arg(long, default_value = "table1-fig4.png")]
    fig: PathBuf,
    /// Frame shown in the figure (1-based, as in the table).
    #[arg(long, default_value_t = 5)]
    fig_frame: usize,
    /// Use at most this many frames.
    #[arg(long)]
    frames: Option<usize>,
    /// Runs per frame and row (the median is reported).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Let registration run this many views behind the matcher (the daemon's situation).
    #[arg(long, default_value_t = 0)]
    lag: u64,
    /// Frame columns printed (all are in the JSON).
    #[arg(long, default_value_t = 10)]
    columns: usize,
    /// Leave out the predicted row.
    #[arg(long)]
    no_predicted: bool,
    #[command(flatten)]
    assist: AssistArgs,
    #[command(flatten)]
    matching: MatchArgs,
}

/// Knobs of registration-assisted matching (see docs/assisted-matching.md).
#[derive(Args)]
struct LiveArgs {
    /// A recording (e.g. `spinscan sim render --frames 90 --deg-per-frame 2 -o REC`).
    recording: PathBuf,
    /// Paced runs, pairs per second.
    #[arg(long, default_value = "15,30", value_delimiter = ',')]
    pace: Vec<f64>,
    /// Pairs fed per run (the recording is cycled when shorter).
    #[arg(long, default_value_t = 90)]
    pairs: usize,
    /// Skip the unpaced run.
    #[arg(long)]
    no_unpaced: bool,
    /// Matcher threads (default: one per core).
    #[arg(long, default_value_t = 0)]
    matcher_threads: usize,
    /// Pairs waiting for the matchers.
    #[arg(long, default_value_t = 16)]
    queue_depth: usize,
    /// Disparities searched.
    #[arg(long, default_value_t = 128)]
    num_disparities: u32,
    /// Registration keeps at most this many points of a view (0 = all).
    #[arg(long, default_value_t = 20_000)]
    register_max_points: usize,
    /// Assistance: predicted, paper or none.
    #[arg(long, default_value = "predicted")]
    assist: String,
    /// Write the runs as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
}

#[derive(Args, Clone)]
struct AssistArgs {
    /// Smallest half-width of an assisted interval, pixels.
    #[arg(long, default_value_t = AssistParams::default().min_half_width_px)]
    assist_min_half_width: f64,
    /// Predicted mode: the matcher's own disparity noise σ, pixels.
    #[arg(long, default_value_t = AssistParams::default().predicted_sigma_px)]
    predict_sigma_px: f64,
    /// Predicted mode: interval half-width in σ.
    #[arg(long, default_value_t = AssistParams::default().predicted_k)]
    predict_k: f64,
    /// Self-correction: rematch a frame over the full range when its valid fraction falls
    /// below this share of the recent median.
    #[arg(long, default_value_t = AssistParams::default().fallback_valid_ratio)]
    fallback_valid_ratio: f64,
    /// Self-correction: do not let a registration with lower ICP fitness guide the next frame.
    #[arg(long, default_value_t = AssistParams::default().min_fitness)]
    assist_min_fitness: f64,
    /// Self-correction: nor one whose ICP RMSE exceeds this many times the recent median.
    #[arg(long, default_value_t = AssistParams::default().max_rmse_ratio)]
    assist_max_rmse_ratio: f64,
}

/// How `replay` and `demo` choose each frame's search range.
#[derive(Args, Clone)]
struct AssistModeArgs {
    /// Search range per frame: `predicted` (the Kalman-predicted disparity ± its
    /// uncertainty; default), `paper` (the paper's registration constraint, weight
    /// --assist-w), or `none` (the full range). Needs registration.
    #[arg(long)]
    assist: Option<String>,
    /// The paper's weighting factor w (with --assist paper).
    #[arg(long, default_value_t = 0.8)]
    assist_w: f64,
    #[command(flatten)]
    knobs: AssistArgs,
}

impl AssistModeArgs {
    /// The assistance to run (None: full range), given whether registration runs.
    fn params(&self, registering: bool) -> Result<Option<AssistParams>, Failure> {
        let mode = AssistMode::parse(self.assist.as_deref().unwrap_or("predicted"), self.assist_w).map_err(|e| input(format!("--assist: {e}")))?;
        match (mode, registering) {
            (AssistMode::None, _) => Ok(None),
            (_, true) => Ok(Some(self.knobs.params(mode)?)),
            (_, false) if self.assist.is_some() => Err(input(format!("--assist {} uses the registered motion, which --no-register turns off", mode.name()))),
            (_, false) => Ok(None),
        }
    }
}

impl AssistArgs {
    fn params(&self, mode: AssistMode) -> Result<AssistParams, Failure> {
        let positive = |name: &str, v: f64| if v > 0.0 && v.is_finite() { Ok(v) } else { Err(input(format!("--{name} must be a positive number, got {v}"))) };
        let share = |name: &str, v: f64| if (0.0..=1.0).contains(&v) { Ok(v) } else { Err(input(format!("--{name} must lie in 0…1, got {v}"))) };
        Ok(AssistParams {
            mode,
            min_half_width_px: positive("assist-min-half-width", self.assist_min_half_width)?,
            predicted_sigma_px: positive("predict-sigma-px", self.predict_sigma_px)?,
            predicted_k: positive("predict-k", self.predict_k)?,
            fallback_valid_ratio: share("fallback-valid-ratio", self.fallback_valid_ratio)?,
            min_fitness: share("assist-min-fitness", self.assist_min_fitness)?,
            max_rmse_ratio: positive("assist-max-rmse-ratio", self.assist_max_rmse_ratio)?,
            ..AssistParams::default()
        })
    }
}

#[derive(Subcommand)]
enum SimCommand {
    /// Renders a recording (calib.yaml, frames.jsonl, left/, right/) with ground truth (gt/).
    Render(SimRenderArgs),
}

#[derive(Args)]
struct SimRenderArgs {
    /// Built-in object: sphere, egg, vase or torus.
    #[arg(long, conflicts_with = "mesh")]
    object: Option<String>,
    /// A triangle mesh (PLY) to put on the turntable instead, +y up.
    #[arg(long)]
    mesh: Option<PathBuf>,
    /// Scale applied to the mesh's coordinates to get millimetres (e.g. 1000 for metres).
    #[arg(long, default_value_t = 1.0, requires = "mesh")]
    mesh_scale: f64,
    /// Triangles of a built-in object's tessellation.
    #[arg(long, default_value_t = 100_000)]
    triangles: usize,
    /// Number of stereo pairs.
    #[arg(long, default_value_t = 30)]
    frames: usize,
    /// Turntable rotation between consecutive pairs, degrees (counterclockwise from above).
    #[arg(long, default_value_t = 2.0, allow_hyphen_values = true)]
    deg_per_frame: f64,
    /// Turntable angle of the first pair, degrees.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    start_deg: f64,
    /// Ideal rectified rig (no distortion, no misalignment) with gt/disparity/.
    #[arg(long)]
    ideal: bool,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Contrast of the object's texture, 0 (plain) … 1.
    #[arg(long, default_value_t = 0.8)]
    texture_contrast: f64,
    /// Sensor noise, grey levels (standard deviation).
    #[arg(long, default_value_t = 1.5)]
    noise: f64,
    /// Probability that a pair is dropped (a gap in seq), 0 … <1.
    #[arg(long, default_value_t = 0.0)]
    drop_probability: f64,
    /// Output folder (must not hold a recording already).
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
}

#[derive(Args)]
struct ReplayArgs {
    /// Recording folder (calib.yaml or intrinsics.yml + extrinsics.yml, frames.jsonl, images).
    dir: PathBuf,
    /// Results folder (may be the recording folder itself).
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
    /// Process at most this many frames.
    #[arg(long)]
    frames: Option<usize>,
    /// Match every pixel instead of segmenting the blue screen.
    #[arg(long)]
    no_segment: bool,
    #[command(flatten)]
    key: KeyArgs,
    /// Rectification alpha: 0 (valid pixels only), 1 (all pixels), −1 (unscaled).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    alpha: f64,
    #[command(flatten)]
    matching: MatchArgs,
    #[command(flatten)]
    reg: RegistrationArgs,
    #[command(flatten)]
    assist: AssistModeArgs,
}

#[derive(Args)]
struct RegisterArgs {
    /// SOURCE.ply TARGET.ply; with --ring, the scans of the ring in order around it.
    #[arg(required = true)]
    files: Vec<PathBuf>,
    /// Register a ring of scans (each to the one before it, then the last to the first, and
    /// close the loop) and write their poses with --conf-out.
    #[arg(long)]
    ring: bool,
    /// Initial guess, {"target_from_source": [[4x4 row-major]]}; default identity.
    #[arg(long, conflicts_with = "ring")]
    init: Option<PathBuf>,
    /// Initial poses of the ring's scans (Stanford .conf); default identity for all.
    #[arg(long, requires = "ring")]
    init_conf: Option<PathBuf>,
    /// Where the ring's registered poses go (Stanford .conf).
    #[arg(long, requires = "ring")]
    conf_out: Option<PathBuf>,
    /// point-to-plane (Chen–Medioni) or point-to-point (Besl–McKay, the paper's).
    #[arg(long, default_value = "point-to-plane")]
    method: String,
    /// Largest distance between corresponding points, in the files' units. Default: 10 × the
    /// target's median point spacing.
    #[arg(long, allow_hyphen_values = true)]
    max_distance: Option<f64>,
    /// Run the registration K times and report the median time.
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// At most this many source points take part, evenly spread (0 = all). The target keeps
    /// every point.
    #[arg(long, default_value_t = 5_000)]
    max_source_points: usize,
    /// ICP iterations at most.
    #[arg(long, default_value_t = 60)]
    max_iterations: usize,
    /// Keep only this fraction of the closest pairs each iteration (1 = no trimming).
    #[arg(long, default_value_t = 1.0)]
    trim: f64,
    /// Result JSON: target_from_source, fitness, rmse, iterations, register_ms, …
    #[arg(short = 'o', long = "out")]
    out: Option<PathBuf>,
}

/// Registration knobs of `replay` and `demo`.
#[derive(Args, Clone)]
struct RegistrationArgs {
    /// Only match: no registration, no poses.jsonl, model.ply or turntable_estimated.yaml.
    #[arg(long)]
    no_register: bool,
    /// m of the paper's block registration: every m views are registered together to the
    /// model of the views before them (0 = pairwise only).
    #[arg(long = "block-views", id = "block_views", default_value_t = 5)]
    block_views: usize,
    /// ICP correspondence distance between consecutive views, mm.
    #[arg(long, default_value_t = 8.0)]
    icp_max_distance: f64,
    /// ICP method: point-to-plane or point-to-point (the paper's).
    #[arg(long, default_value = "point-to-plane")]
    icp_method: String,
    /// Voxel side of model.ply, mm.
    #[arg(long, default_value_t = 1.0)]
    voxel: f64,
    /// Keep isolated points in model.ply (no noise removal).
    #[arg(long)]
    no_denoise: bool,
    /// Do not close the loop after a full turn.
    #[arg(long)]
    no_loop_closure: bool,
    /// Keep the registered poses even when every step agrees with the turntable's angles
    /// (by default the turntable's predictions about the estimated axis replace them then).
    #[arg(long)]
    no_turntable_poses: bool,
}

impl RegistrationArgs {
    fn options(&self, pipeline: PipelineOptions) -> Result<ReplayOptions, Failure> {
        let mut opts = ReplayOptions::with_registration(pipeline);
        if !(self.voxel > 0.0 && self.voxel.is_finite()) {
            return Err(input(format!("--voxel must be a positive number of mm, got {}", self.voxel)));
        }
        if !(self.icp_max_distance > 0.0 && self.icp_max_distance.is_finite()) {
            return Err(input(format!("--icp-max-distance must be a positive number of mm, got {}", self.icp_max_distance)));
        }
        opts.model.voxel_mm = self.voxel;
        if self.no_denoise {
            opts.model.denoise = None;
        }
        if self.no_register {
            opts.registration = None;
        } else if let Some(r) = opts.registration.as_mut() {
            r.block = self.block_views;
            r.close_loop = !self.no_loop_closure;
            r.turntable_poses = !self.no_turntable_poses;
            let method = self.icp_method.parse().map_err(input)?;
            let keep = r.icp.clone();
            r.icp = IcpParams { method, ..IcpParams::new(self.icp_max_distance) };
            r.icp.max_source_points = keep.max_source_points;
            r.icp.kernel = keep.kernel;
            r.icp.max_iterations = keep.max_iterations;
        }
        Ok(opts)
    }
}

/// Matcher knobs shared by the commands that match.
#[derive(Args, Clone)]
struct MatchArgs {
    /// First disparity searched (may be negative). Default: 0, or −(N−1) on a calibrated rig
    /// whose rectified disparities are negative.
    #[arg(long, allow_hyphen_values = true)]
    min_disparity: Option<i32>,
    /// Number of disparities N: the search covers D … D+N−1. Default: 64 for single pairs;
    /// 128 for `demo`, `sim` and `replay` (the simulated lab's disparities span 0…127).
    #[arg(long)]
    max_disparity: Option<u32>,
    /// Correlation window side (odd, 3…31).
    #[arg(long, default_value_t = MatchParams::default().block)]
    block: u32,
    /// Worker threads; default all cores.
    #[arg(long)]
    threads: Option<usize>,
    /// Uniqueness ratio in percent (0 disables).
    #[arg(long, default_value_t = MatchParams::default().uniqueness_ratio)]
    uniqueness: u32,
    /// Texture threshold: minimum summed |x-gradient| in the window (0 disables).
    #[arg(long, default_value_t = MatchParams::default().texture_threshold)]
    texture_threshold: u32,
    /// Left–right check tolerance in pixels; a negative value disables the check.
    #[arg(long, default_value_t = 1, allow_hyphen_values = true)]
    lr_max_diff: i32,
    /// Speckle filter: largest blob (pixels) removed; 0 disables.
    #[arg(long, default_value_t = MatchParams::default().speckle_window)]
    speckle_window: u32,
    /// Speckle filter: largest disparity step inside a blob, pixels.
    #[arg(long, default_value_t = MatchParams::default().speckle_range_px)]
    speckle_range: f32,
}

impl MatchArgs {
    fn params(&self) -> MatchParams {
        self.params_with_default(64)
    }

    /// The parameters, with `num_disparities` defaulting to `default_range`.
    fn params_with_default(&self, default_range: u32) -> MatchParams {
        MatchParams {
            min_disparity: self.min_disparity.unwrap_or(0),
            num_disparities: self.max_disparity.unwrap_or(default_range),
            block: self.block,
            uniqueness_ratio: self.uniqueness,
            texture_threshold: self.texture_threshold,
            lr_max_diff: u32::try_from(self.lr_max_diff).ok(),
            speckle_window: self.speckle_window,
            speckle_range_px: self.speckle_range,
            threads: self.threads.unwrap_or(0),
            ..MatchParams::default()
        }
    }
}

#[derive(Args)]
struct DisparityArgs {
    /// Left image (PNG, JPEG or PNM; colour is converted to grey).
    #[arg(long)]
    left: PathBuf,
    /// Right image, the same size.
    #[arg(long)]
    right: PathBuf,
    /// Calibration (file or folder); without it the pair is taken as rectified.
    #[arg(long)]
    calib: Option<PathBuf>,
    /// Rectification alpha: 0 (valid pixels only), 1 (all pixels), −1 (unscaled).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    alpha: f64,
    #[command(flatten)]
    matching: MatchArgs,
    /// Times the matcher K times and reports the median as `match_ms`; with K > 1 an untimed
    /// warm-up run comes first (as the peer script does for OpenCV).
    #[arg(long, default_value_t = 1)]
    repeat: u32,
    /// Disparity as 16-bit PNG (|d| × 256, 0 = none).
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
    /// Signed disparity as PFM.
    #[arg(long)]
    pfm: Option<PathBuf>,
    /// False-colour disparity PNG.
    #[arg(long)]
    color: Option<PathBuf>,
}

#[derive(Args)]
struct RectifyArgs {
    /// Calibration: calib.yaml, or a folder with it or with intrinsics.yml + extrinsics.yml.
    #[arg(long)]
    calib: PathBuf,
    /// Raw left image.
    #[arg(long)]
    left: PathBuf,
    /// Raw right image, the same size.
    #[arg(long)]
    right: PathBuf,
    /// Rectification alpha: 0 (valid pixels only), 1 (all pixels), −1 (unscaled).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    alpha: f64,
    /// Output folder: left.png, right.png, rectification.json.
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
}

#[derive(Args)]
struct PointsArgs {
    /// Calibration: calib.yaml, or a folder with it or with intrinsics.yml + extrinsics.yml.
    #[arg(long)]
    calib: PathBuf,
    /// Raw left image (colours the points).
    #[arg(long)]
    left: PathBuf,
    /// Raw right image, the same size.
    #[arg(long)]
    right: PathBuf,
    /// `auto` (blue-screen chroma key) or a mask image in raw left coordinates (non-zero = object).
    #[arg(long)]
    mask: Option<String>,
    #[command(flatten)]
    key: KeyArgs,
    /// Rectification alpha: 0 (valid pixels only), 1 (all pixels), −1 (unscaled).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    alpha: f64,
    #[command(flatten)]
    matching: MatchArgs,
    /// Output point cloud: binary PLY, x y z float (mm, left raw camera frame), red green blue.
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
    /// Also write the disparity (16-bit PNG).
    #[arg(long)]
    disparity: Option<PathBuf>,
    /// Also write the rectified mask used (PNG).
    #[arg(long)]
    mask_out: Option<PathBuf>,
}

/// Blue-screen segmentation knobs (used by `--mask auto`).
#[derive(Args, Clone)]
struct KeyArgs {
    /// Background colour to key out, as R,G,B (0…255 each).
    #[arg(long, value_parser = parse_rgb, default_value = "40,70,190")]
    key_color: [u8; 3],
    /// Largest chromaticity distance from the key colour still counted as background (0…1).
    #[arg(long, default_value_t = ChromaKey::default().tolerance)]
    key_tolerance: f32,
    /// Image of the empty scene (raw left camera): pixels close to it are background too.
    #[arg(long)]
    plate: Option<PathBuf>,
}

impl KeyArgs {
    fn chroma(&self) -> ChromaKey {
        ChromaKey { key_rgb: self.key_color, tolerance: self.key_tolerance, ..ChromaKey::default() }
    }
}

fn parse_rgb(s: &str) -> Result<[u8; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let err = || format!("`{s}` is not a colour: expected R,G,B with three numbers 0…255, e.g. 40,70,190");
    if parts.len() != 3 {
        return Err(err());
    }
    let mut rgb = [0u8; 3];
    for (c, p) in rgb.iter_mut().zip(parts) {
        *c = p.parse().map_err(|_| err())?;
    }
    Ok(rgb)
}

#[derive(Args)]
struct DemoArgs {
    /// Output folder: the recording in `recording/`, the results in `results/`.
    #[arg(short = 'o', long = "out", default_value = "out/demo")]
    out: PathBuf,
    /// Built-in object: sphere, egg, vase or torus.
    #[arg(long, default_value = "torus")]
    object: String,
    /// Number of stereo pairs.
    #[arg(long, default_value_t = 8)]
    frames: usize,
    /// Turntable rotation between pairs, degrees.
    #[arg(long, default_value_t = 3.0, allow_hyphen_values = true)]
    deg_per_frame: f64,
    /// Use the realistic rig (distortion, misalignment; no ground-truth disparity) instead of
    /// the ideal one.
    #[arg(long)]
    realistic: bool,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    #[command(flatten)]
    matching: MatchArgs,
    #[command(flatten)]
    reg: RegistrationArgs,
    #[command(flatten)]
    assist: AssistModeArgs,
}

/// A failure with the exit code it maps to.
struct Failure {
    code: u8,
    message: String,
}

fn input<E: std::fmt::Display>(e: E) -> Failure {
    Failure { code: exit::INPUT, message: e.to_string() }
}

fn output<E: std::fmt::Display>(e: E) -> Failure {
    Failure { code: exit::OUTPUT, message: e.to_string() }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Warnings (and more with RUST_LOG=info|debug) go to stderr. A benchmark registers every
    // row's views: their registration warnings only with RUST_LOG=warn.
    let default_level = if matches!(cli.command, Command::Bench(_)) { "error" } else { "warn" };
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level)))
        .init();
    let result = match cli.command {
        Command::Disparity(a) => cmd_disparity(a),
        Command::Rectify(a) => cmd_rectify(a),
        Command::Points(a) => cmd_points(a),
        Command::Demo(a) => cmd_demo(a),
        Command::Sim(SimCommand::Render(a)) => cmd_sim_render(a),
        Command::Replay(a) => cmd_replay(a),
        Command::Register(a) => cmd_register(a),
        Command::Bench(BenchCommand::Table1(a)) => cmd_table1(a),
        Command::Bench(BenchCommand::Live(a)) => cmd_bench_live(a),
        Command::Status(a) => daemon_cmds::status(a).map_err(from_daemon),
        Command::Devices(a) => daemon_cmds::devices(a).map_err(from_daemon),
        Command::Scan(c) => daemon_cmds::scan(c).map_err(from_daemon),
        Command::Scans(a) => daemon_cmds::scans(a).map_err(from_daemon),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => {
            eprintln!("spinscan: error: {}", f.message);
            ExitCode::from(f.code)
        }
    }
}

fn from_daemon(f: daemon_cmds::Failure) -> Failure {
    Failure { code: f.code, message: f.message }
}

fn load_pair(left: &Path, right: &Path) -> Result<(LoadedImage, LoadedImage), Failure> {
    let l = io::load_image(left).map_err(input)?;
    let r = io::load_image(right).map_err(input)?;
    if (l.width, l.height) != (r.width, r.height) {
        return Err(input(format!(
            "{} is {}×{} but {} is {}×{}; a stereo pair must have one size",
            left.display(),
            l.width,
            l.height,
            right.display(),
            r.width,
            r.height
        )));
    }
    Ok((l, r))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

fn write_disparity_outputs(disp: &DisparityMap, png: &Path, pfm: Option<&Path>, color: Option<&Path>, range: (f32, f32)) -> Result<(), Failure> {
    io::write_disparity_png(png, disp).map_err(output)?;
    if let Some(p) = pfm {
        io::write_pfm(p, disp).map_err(output)?;
    }
    if let Some(p) = color {
        io::write_rgb_png(p, disp.width, disp.height, &io::disparity_false_color(disp, range)).map_err(output)?;
    }
    Ok(())
}

fn cmd_disparity(a: DisparityArgs) -> Result<(), Failure> {
    if a.repeat == 0 {
        return Err(input("--repeat must be at least 1"));
    }
    let (l, r) = load_pair(&a.left, &a.right)?;
    let (w, h) = (l.width, l.height);
    // Rectify first (not timed), then time the matcher alone on grey images.
    let (left_gray, right_gray, params, sign) = match &a.calib {
        Some(path) => {
            let calib = StereoCalib::load(path).map_err(input)?;
            let opts = PipelineOptions {
                alpha: a.alpha,
                min_disparity: a.matching.min_disparity,
                matching: a.matching.params(),
                ..Default::default()
            };
            let pipe = Pipeline::new(&calib, (w as u32, h as u32), opts).map_err(input)?;
            let (lr, rr) = pipe.rectify_rgb(&l.rgb, &r.rgb);
            let params = (**pipe.matcher().params()).clone();
            (io::rgb_to_gray(&lr), io::rgb_to_gray(&rr), params, pipe.rect.disparity_sign)
        }
        None => {
            let params = a.matching.params();
            let sign = if params.min_disparity + params.num_disparities as i32 - 1 <= 0 { -1 } else { 1 };
            (l.gray, r.gray, params, sign)
        }
    };
    let valid = params.clone().validate().map_err(input)?;
    let threads = valid.thread_count();
    let mut matcher = StereoMatcher::new(valid);
    let intervals = matcher.full_intervals(w, h, None);
    let (lv, rv) = (GrayView::new(w, h, &left_gray).unwrap(), GrayView::new(w, h, &right_gray).unwrap());
    let mut disp = DisparityMap::new(w, h);
    let mut times = Vec::new();
    let mut stats = Default::default();
    if a.repeat > 1 {
        // One untimed warm-up (buffers, caches), as the peer script does for OpenCV.
        matcher.compute(lv, rv, &intervals, &mut disp).map_err(input)?;
    }
    for _ in 0..a.repeat {
        let t0 = Instant::now();
        stats = matcher.compute(lv, rv, &intervals, &mut disp).map_err(input)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let lo = params.min_disparity as f32;
    let hi = (params.min_disparity + params.num_disparities as i32 - 1) as f32;
    let range = (lo.abs().min(hi.abs()), lo.abs().max(hi.abs()));
    write_disparity_outputs(&disp, &a.out, a.pfm.as_deref(), a.color.as_deref(), range)?;
    let report = json!({
        "match_ms": median(times),
        "valid_fraction": stats.valid_fraction(),
        "disparity_sign": sign,
        "width": w,
        "height": h,
        "min_disparity": params.min_disparity,
        "num_disparities": params.num_disparities,
        "block": params.block,
        "threads": threads,
        "repeat": a.repeat,
        "matched": stats.matched,
        "searched": stats.searched,
        "mean_search_px": stats.mean_search_px(),
    });
    println!("{report}");
    Ok(())
}

fn cmd_rectify(a: RectifyArgs) -> Result<(), Failure> {
    let (l, r) = load_pair(&a.left, &a.right)?;
    let calib = StereoCalib::load(&a.calib).map_err(input)?;
    let opts = PipelineOptions { alpha: a.alpha, ..Default::default() };
    let pipe = Pipeline::new(&calib, (l.width as u32, l.height as u32), opts).map_err(input)?;
    let (lr, rr) = pipe.rectify_rgb(&l.rgb, &r.rgb);
    std::fs::create_dir_all(&a.out).map_err(|e| output(format!("cannot create {}: {e}", a.out.display())))?;
    io::write_rgb_png(&a.out.join("left.png"), l.width, l.height, &lr).map_err(output)?;
    io::write_rgb_png(&a.out.join("right.png"), l.width, l.height, &rr).map_err(output)?;
    let m = |m: nalgebra::DMatrixView<f64>| -> Vec<Vec<f64>> { (0..m.nrows()).map(|i| m.row(i).iter().copied().collect()).collect() };
    let rect = &pipe.rect;
    let doc = json!({
        "alpha": a.alpha,
        "R1": m(rect.r1.as_view()), "R2": m(rect.r2.as_view()),
        "P1": m(rect.p1.as_view()), "P2": m(rect.p2.as_view()), "Q": m(rect.q.as_view()),
        "disparity_sign": rect.disparity_sign,
    });
    io::write_atomic(&a.out.join("rectification.json"), serde_json::to_string_pretty(&doc).unwrap().as_bytes()).map_err(output)?;
    println!("{}", json!({"left": a.out.join("left.png"), "right": a.out.join("right.png"), "disparity_sign": rect.disparity_sign, "focal_px": rect.p1[(0, 0)]}));
    Ok(())
}

fn cmd_points(a: PointsArgs) -> Result<(), Failure> {
    let (l, r) = load_pair(&a.left, &a.right)?;
    let calib = StereoCalib::load(&a.calib).map_err(input)?;
    let opts = PipelineOptions {
        alpha: a.alpha,
        min_disparity: a.matching.min_disparity,
        matching: a.matching.params(),
        chroma: a.key.chroma(),
    };
    let mut pipe = Pipeline::new(&calib, (l.width as u32, l.height as u32), opts).map_err(input)?;
    let plate = match &a.key.plate {
        Some(p) => {
            let img = io::load_image(p).map_err(input)?;
            if (img.width, img.height) != (l.width, l.height) {
                return Err(input(format!("plate {} is {}×{} but the images are {}×{}", p.display(), img.width, img.height, l.width, l.height)));
            }
            Some(img.rgb)
        }
        None => None,
    };
    if plate.is_some() && a.mask.as_deref() != Some("auto") {
        return Err(input("--plate is used by the blue-screen segmentation: add --mask auto"));
    }
    let view = match a.mask.as_deref() {
        None => pipe.process_rgb(&l.rgb, &r.rgb, false),
        Some("auto") => pipe.process_rgb_with_plate(&l.rgb, &r.rgb, true, plate.as_deref()),
        Some(file) => {
            let m = io::load_image(Path::new(file)).map_err(input)?;
            if (m.width, m.height) != (l.width, l.height) {
                return Err(input(format!("mask {file} is {}×{} but the images are {}×{}", m.width, m.height, l.width, l.height)));
            }
            let raw: Vec<u8> = m.gray.iter().map(|&v| if v > 0 { 255 } else { 0 }).collect();
            let mask = pipe.rectify_left_mask(&raw);
            let (lr, rr) = pipe.rectify_rgb(&l.rgb, &r.rgb);
            pipe.process_rectified(lr, &rr, Some(mask))
        }
    }
    .map_err(input)?;
    io::ply::write_ply(&a.out, &view.cloud).map_err(output)?;
    if let Some(p) = &a.disparity {
        io::write_disparity_png(p, &view.disparity).map_err(output)?;
    }
    if let (Some(p), Some(mask)) = (&a.mask_out, &view.mask) {
        io::write_gray_png(p, l.width, l.height, mask).map_err(output)?;
    }
    println!(
        "{}",
        json!({"points": view.cloud.len(), "match_ms": view.match_ms, "valid_fraction": view.stats.valid_fraction(),
               "disparity_sign": pipe.rect.disparity_sign, "out": a.out})
    );
    Ok(())
}

fn cmd_sim_render(a: SimRenderArgs) -> Result<(), Failure> {
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
        image_size: (640, 480),
    };
    let t0 = Instant::now();
    let rec = spinscan::hw::sim::render_recording(&opts, &a.out, &mut |done, total| eprint!("\rsim render: {done}/{total} pairs")).map_err(|e| match e {
        spinscan::hw::sim::SimError::Recording(
            spinscan::recording::RecordingError::Io { .. } | spinscan::recording::RecordingError::Write { .. } | spinscan::recording::RecordingError::Exists(_),
        ) => output(e),
        other => input(other),
    })?;
    eprintln!();
    let seconds = t0.elapsed().as_secs_f64();
    println!(
        "{}",
        json!({"out": a.out, "frames": rec.frames.len(), "ideal": a.ideal, "width": rec.image_size.0, "height": rec.image_size.1,
               "seconds": seconds, "gt_disparity": a.ideal})
    );
    Ok(())
}

fn cmd_replay(a: ReplayArgs) -> Result<(), Failure> {
    let rec = Recording::open(&a.dir).map_err(input)?;
    if let Some(line) = rec.torn_line {
        eprintln!("replay: warning: skipped the torn last line {line} of {}", a.dir.join("frames.jsonl").display());
    }
    let plate = match &a.key.plate {
        Some(p) if a.no_segment => return Err(input(format!("--plate {} is used by the blue-screen segmentation, which --no-segment turns off", p.display()))),
        Some(p) => {
            let img = io::load_image(p).map_err(input)?;
            if (img.width as u32, img.height as u32) != rec.image_size {
                return Err(input(format!("plate {} is {}×{} but the recording's images are {}×{}", p.display(), img.width, img.height, rec.image_size.0, rec.image_size.1)));
            }
            Some(img.rgb)
        }
        None => None,
    };
    let opts = ReplayOptions {
        max_frames: a.frames,
        segment: !a.no_segment,
        plate,
        assist: a.assist.params(!a.reg.no_register)?,
        ..a.reg.options(PipelineOptions {
            alpha: a.alpha,
            min_disparity: a.matching.min_disparity,
            matching: a.matching.params_with_default(128),
            chroma: a.key.chroma(),
        })?
    };
    let total = a.frames.map_or(rec.frames.len(), |m| m.min(rec.frames.len()));
    let summary = replay::run_recording(rec, &a.out, &opts, &mut |done, seq, ms| {
        eprint!("\rreplay: {done}/{total} frames (seq {seq}, matched in {ms:.0} ms)")
    });
    eprintln!();
    let summary = summary.map_err(|e| {
        let why = format!("{e} (results so far are in {}, manifest status `failed`)", a.out.display());
        if e.is_output() {
            output(why)
        } else {
            input(why)
        }
    })?;
    println!("{}", summary_json(&summary, &a.out));
    Ok(())
}

fn summary_json(s: &replay::ReplaySummary, out: &Path) -> serde_json::Value {
    let mut j = json!({"out": out, "frames": s.frames, "mean_match_ms": s.mean_match_ms, "disparity_sign": s.disparity_sign});
    if let Some(gt) = s.gt {
        j["gt_coverage"] = json!(gt.coverage);
        j["gt_bad2_of_matched"] = json!(gt.bad2_of_matched);
        j["gt_mean_abs_err_px"] = json!(gt.mean_abs_err_px);
    }
    if let Some(r) = &s.registration {
        j["registration"] = r.clone();
    }
    j
}

fn cmd_demo(a: DemoArgs) -> Result<(), Failure> {
    let (rec_dir, results_dir) = (a.out.join("recording"), a.out.join("results"));
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
    let rec = spinscan::hw::sim::render_recording(&opts, &rec_dir, &mut |done, total| eprint!("\rdemo: rendered {done}/{total}")).map_err(input)?;
    eprintln!("\ndemo: replaying {} (segment the blue screen, rectify, match, triangulate)…", rec_dir.display());
    let replay_opts = ReplayOptions {
        assist: a.assist.params(!a.reg.no_register)?,
        ..a.reg.options(PipelineOptions { min_disparity: a.matching.min_disparity, matching: a.matching.params_with_default(128), ..Default::default() })?
    };
    let summary = replay::run_recording(rec, &results_dir, &replay_opts, &mut |done, seq, ms| {
        eprint!("\rdemo: replayed {done}/{} (seq {seq}, {ms:.0} ms)", a.frames)
    })
    .map_err(input)?;
    eprintln!("\ndemo: recording in {}, results in {} (views/*.ply open in MeshLab or Open3D)", rec_dir.display(), results_dir.display());
    println!("{}", summary_json(&summary, &results_dir));
    Ok(())
}

fn read_scan(path: &Path) -> Result<Vec<[f32; 3]>, Failure> {
    let mesh = io::ply::read_ply(path).map_err(input)?;
    if mesh.cloud.points.is_empty() {
        return Err(input(format!("{}: the PLY file has no vertices", path.display())));
    }
    Ok(mesh.cloud.points)
}

fn icp_params_of(a: &RegisterArgs, max_distance: f64) -> Result<IcpParams, Failure> {
    let mut p = IcpParams::new(max_distance);
    p.method = a.method.parse().map_err(input)?;
    p.max_iterations = a.max_iterations;
    p.max_source_points = a.max_source_points;
    p.trim = a.trim;
    Ok(p)
}

fn cmd_register(a: RegisterArgs) -> Result<(), Failure> {
    if a.repeat == 0 {
        return Err(input("--repeat must be at least 1"));
    }
    if a.ring {
        return cmd_register_ring(a);
    }
    let [source_path, target_path] = a.files.as_slice() else {
        return Err(input(format!("expected SOURCE.ply TARGET.ply, got {} files (use --ring for more than two)", a.files.len())));
    };
    let Some(out) = &a.out else { return Err(input("missing -o OUT.json")) };
    let source = read_scan(source_path)?;
    let target = read_scan(target_path)?;
    let init = match &a.init {
        Some(p) => io::poses::read_transform_json(p).map_err(input)?,
        None => nalgebra::Isometry3::identity(),
    };
    let max_distance = match a.max_distance {
        Some(d) => d,
        None => {
            let tree = register::KdTree::build(target.clone(), &target_path.display().to_string()).map_err(input)?;
            10.0 * tree.median_spacing()
        }
    };
    let params = icp_params_of(&a, max_distance)?;
    let mut times = Vec::new();
    let mut result = None;
    for _ in 0..a.repeat {
        let t0 = Instant::now();
        let tree = register::KdTree::build(target.clone(), &target_path.display().to_string()).map_err(input)?;
        let mut tgt = register::icp::Target::new(tree, params.normals);
        let r = register::icp(&source, &mut tgt, &init, &params).map_err(input)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        result = Some(r);
    }
    let r = result.unwrap();
    if let Some(w) = r.degeneracy_warning() {
        eprintln!("register: warning: {w}");
    }
    if !r.converged {
        eprintln!("register: warning: ICP did not converge within {} iterations", params.max_iterations);
    }
    let mut j = io::poses::transform_json(&r.transform);
    j["fitness"] = json!(r.fitness);
    j["rmse"] = json!(r.rmse);
    j["iterations"] = json!(r.iterations);
    j["register_ms"] = json!(median(times.clone()));
    j["register_ms_runs"] = json!(times);
    j["converged"] = json!(r.converged);
    j["correspondences"] = json!(r.correspondences);
    j["method"] = json!(a.method);
    j["max_distance"] = json!(max_distance);
    j["source_points"] = json!(source.len());
    j["target_points"] = json!(target.len());
    j["degenerate"] = json!(r.degenerate.iter().map(|d| d.to_string()).collect::<Vec<_>>());
    j["conditioning"] = json!(r.conditioning);
    io::write_atomic(out, serde_json::to_string_pretty(&j).unwrap().as_bytes()).map_err(|e| output(format!("{}: {e}", out.display())))?;
    println!("{}", json!({"out": out, "fitness": r.fitness, "rmse": r.rmse, "iterations": r.iterations, "register_ms": j["register_ms"], "converged": r.converged}));
    Ok(())
}

fn cmd_register_ring(a: RegisterArgs) -> Result<(), Failure> {
    let Some(conf_out) = &a.conf_out else { return Err(input("--ring needs --conf-out OUT.conf")) };
    if a.files.len() < 3 {
        return Err(input(format!("a ring needs at least 3 scans, got {}", a.files.len())));
    }
    let names: Vec<String> = a.files.iter().map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()).collect();
    let init_conf = match &a.init_conf {
        Some(p) => Some(io::poses::Conf::read(p).map_err(input)?),
        None => None,
    };
    let init_world: Vec<nalgebra::Isometry3<f64>> = match &init_conf {
        Some(conf) => names
            .iter()
            .map(|n| conf.get(n).map(|p| p.world_from_scan).ok_or_else(|| input(format!("{} has no `bmesh {n}` line", a.init_conf.as_ref().unwrap().display()))))
            .collect::<Result<_, _>>()?,
        None => vec![nalgebra::Isometry3::identity(); names.len()],
    };
    let scans: Vec<Vec<[f32; 3]>> = a.files.iter().map(|p| read_scan(p)).collect::<Result<_, _>>()?;
    let max_distance = match a.max_distance {
        Some(d) => d,
        None => 10.0 * register::KdTree::build(scans[0].clone(), &names[0]).map_err(input)?.median_spacing(),
    };
    let params = icp_params_of(&a, max_distance)?;
    let t0 = Instant::now();
    let ring = register::ring::register_ring(&scans, &init_world, &params).map_err(input)?;
    for (k, e) in ring.edges.iter().enumerate() {
        let (i, j) = (e.source, e.target);
        eprintln!("register: {} → {}: fitness {:.3}, rmse {:.6}, {} iterations{}", names[i], names[j], e.icp.fitness, e.icp.rmse, e.icp.iterations, if e.icp.converged { "" } else { " (not converged)" });
        if let Some(w) = e.icp.degeneracy_warning() {
            eprintln!("register: warning: edge {k}: {w}");
        }
    }
    eprintln!("register: loop closed: {:.4}° and {:.6} apart before spreading", ring.loop_error_deg, ring.loop_error_translation);
    let conf = io::poses::Conf {
        camera: init_conf.and_then(|c| c.camera),
        poses: names.iter().zip(&ring.world_from_scan).map(|(n, w)| io::poses::ConfPose { name: n.clone(), world_from_scan: *w }).collect(),
    };
    io::write_atomic(conf_out, conf.to_text().as_bytes()).map_err(|e| output(format!("{}: {e}", conf_out.display())))?;
    println!("{}", json!({"conf_out": conf_out, "scans": names.len(), "loop_error_deg": ring.loop_error_deg, "loop_error_translation": ring.loop_error_translation, "register_ms": t0.elapsed().as_secs_f64() * 1e3}));
    Ok(())
}

fn cmd_bench_live(a: LiveArgs) -> Result<(), Failure> {
    use spinscan::daemon::config::Config;
    let mut config = Config::default();
    config.scan.matcher_threads = a.matcher_threads;
    config.scan.queue_depth = a.queue_depth;
    config.scan.register_max_points = a.register_max_points;
    config.matching.num_disparities = a.num_disparities;
    config.matching.assist = a.assist.clone();
    config.validate(Path::new("bench live flags")).map_err(input)?;
    if a.pairs == 0 || a.pace.iter().any(|p| !(*p > 0.0)) {
        return Err(input("--pairs must be at least 1 and every --pace positive"));
    }
    let opts = spinscan::daemon::throughput::LiveOptions { settings: spinscan::daemon::pipeline_settings(&config), pairs: a.pairs, paces: a.pace.clone(), unpaced: !a.no_unpaced };
    let work = std::env::temp_dir().join(format!("spinscan-bench-live-{}", std::process::id()));
    let runs = spinscan::daemon::throughput::live(&a.recording, &opts, &work, &mut |what| eprintln!("bench live: {what}")).map_err(input);
    let _ = std::fs::remove_dir_all(&work);
    let runs = runs?;
    let threads = if a.matcher_threads == 0 { std::thread::available_parallelism().map_or(2, |n| n.get()) } else { a.matcher_threads };
    println!("live pipeline: {} matcher threads, queue {}, {} disparities, assist {}, registration ≤ {} points/view", threads, a.queue_depth, a.num_disparities, a.assist, a.register_max_points);
    print!("{}", spinscan::daemon::throughput::render(&runs));
    if let Some(path) = &a.json {
        let v = json!({"matcher_threads": threads, "queue_depth": a.queue_depth, "num_disparities": a.num_disparities, "assist": a.assist, "runs": runs.iter().map(|r| r.to_json()).collect::<Vec<_>>()});
        io::write_atomic(path, serde_json::to_string_pretty(&v).unwrap().as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    Ok(())
}

fn cmd_table1(a: Table1Args) -> Result<(), Failure> {
    if let Some(w) = a.weights.iter().find(|w| !(**w > 0.0 && w.is_finite())) {
        return Err(input(format!("--weights: {w} is not a weighting factor (expected positive numbers, e.g. 0.6,0.8,1,2)")));
    }
    if a.repeat == 0 {
        return Err(input("--repeat must be at least 1"));
    }
    if a.fig_frame == 0 {
        return Err(input("--fig-frame counts from 1"));
    }
    let mut matching = a.matching.params_with_default(128);
    // One thread unless asked: steadier timings on a shared machine.
    matching.threads = a.matching.threads.unwrap_or(1);
    let opts = spinscan::bench::Table1Options {
        pipeline: PipelineOptions { min_disparity: a.matching.min_disparity, matching, ..Default::default() },
        weights: a.weights.clone(),
        predicted: !a.no_predicted,
        max_frames: a.frames,
        repeat: a.repeat,
        lag: a.lag,
        assist: a.assist.params(AssistMode::Predicted)?,
        fig_frame: Some(a.fig_frame - 1),
        ..Default::default()
    };
    let table = spinscan::bench::table1(&a.recording, &opts, &mut |row, done, total| eprint!("\rbench table1: {row:<10} {done}/{total}   ")).map_err(input)?;
    eprintln!();
    print!("{}", table.render(a.columns));
    table.write_figure(&a.fig).map_err(output)?;
    println!("figure: {} (left image of frame {}, then {})", a.fig.display(), opts.fig_frame.unwrap_or(0).min(table.frames.len() - 1) + 1, table.to_json()["fig_tiles"].as_array().map(|t| t[1..].iter().filter_map(|v| v.as_str()).collect::<Vec<_>>().join(", ")).unwrap_or_default());
    if let Some(path) = &a.json {
        io::write_atomic(path, serde_json::to_string_pretty(&table.to_json()).unwrap().as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    Ok(())
}
