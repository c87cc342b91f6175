//! The `spinscan` CLI's commands, one module per subcommand family, and the arguments they
//! share (declared once here): the matcher's, the blue-screen key's, registration's and the
//! assistant's.

pub mod bench;
pub mod calibrate;
pub mod daemon;
pub mod mesh;
pub mod progress;
pub mod register;
pub mod replay;
pub mod sim;
pub mod stereo;
pub mod turntable;

use std::path::{Path, PathBuf};

use clap::Args;

use spinscan::assist::{AssistMode, AssistParams, Granularity};
use spinscan::io::{self, LoadedImage};
use spinscan::pipeline::replay::ReplayOptions;
use spinscan::pipeline::PipelineOptions;
use spinscan::register::IcpParams;
use spinscan::segment::{ChromaKey, KeyColour};
use spinscan::stereo::{MatchParams, Method};

/// Exit codes, so scripts and systemd can tell kinds of failure apart.
pub mod exit {
    /// Bad input: unreadable or inconsistent files, impossible parameters.
    pub const INPUT: u8 = 3;
    /// An output could not be written.
    pub const OUTPUT: u8 = 4;
    /// The daemon cannot be reached or refuses a request.
    pub const DAEMON: u8 = 5;
    /// A device (the turntable) did not do what it was asked; the message has its words.
    pub const DEVICE: u8 = 6;
}

/// A failure with the exit code it maps to.
pub struct Failure {
    pub code: u8,
    pub message: String,
}

pub fn input<E: std::fmt::Display>(e: E) -> Failure {
    Failure { code: exit::INPUT, message: e.to_string() }
}

pub fn output<E: std::fmt::Display>(e: E) -> Failure {
    Failure { code: exit::OUTPUT, message: e.to_string() }
}

pub fn load_pair(left: &Path, right: &Path) -> Result<(LoadedImage, LoadedImage), Failure> {
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

pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// Matcher knobs shared by the commands that match.
#[derive(Args, Clone)]
pub struct MatchArgs {
    /// The matcher: `bm` (correlation, the default) or `sgm` (semi-global matching: slower at
    /// full range, more accurate in weak texture and on slanted surfaces; docs/matcher.md).
    /// `bench table1` takes a comma-separated list (`bm,sgm`) and runs every row for each.
    #[arg(long, default_value = "bm", value_delimiter = ',')]
    pub method: Vec<Method>,
    /// SGM: penalty for a disparity change of one between neighbours (in the cost's unit:
    /// census bits plus grey levels of the intensity term).
    #[arg(long, default_value_t = MatchParams::default().p1)]
    pub p1: u16,
    /// SGM: penalty for a larger disparity jump between neighbours.
    #[arg(long, default_value_t = MatchParams::default().p2)]
    pub p2: u16,
    /// SGM: aggregation paths, 4 (rows and columns), 8 (and the diagonals), or 5 (the row both
    /// ways and the three from above, in one pass down the image: memory of one row instead of
    /// a volume of the image times the range, for large images; less accurate).
    #[arg(long, default_value_t = MatchParams::default().sgm_paths)]
    pub sgm_paths: u8,
    /// SGM: cap, in grey levels, of the per-pixel intensity term |left − right| added to the
    /// census cost (the right image matched to the left's mean and spread first); 0 = census
    /// alone, at most 100.
    #[arg(long, default_value_t = MatchParams::default().sgm_ad_cap)]
    pub sgm_ad_cap: u8,
    /// SGM: keep the sub-pixel disparities of SGM's own sums instead of refining them with the
    /// correlation cost around each winner (faster, less precise on slanted surfaces).
    #[arg(long)]
    pub no_sgm_refine: bool,
    /// Seed wide searches (64 disparities a pixel or more) from the pair matched
    /// at half size, each tile then searching only around that (faster, fewer gross errors;
    /// bm's seeded maps are denser, with a slightly larger median error in a scan's views;
    /// docs/matcher.md, "Seeded from the pair at half size"): on or off. Default: on for
    /// sgm, off for bm.
    #[arg(long, value_name = "on|off", value_parser = on_off)]
    pub coarse_to_fine: Option<bool>,
    /// SGM: side of the refinement's correlation window (odd, 3…31; `--block` is bm's). Larger
    /// gives smoother single views but more bias on curved surfaces, which a fused model keeps
    /// (docs/matcher.md, "The rim").
    #[arg(long, default_value_t = MatchParams::default().sgm_refine_block)]
    pub sgm_refine_block: u32,
    /// SGM: how close (pixels, 0.1…2) the refinement's correlation value must come to SGM's own
    /// to keep a scan's match (on a whole image, SGM's value stays where they disagree). 0.5
    /// keeps 6–10 % fewer pixels in a scan's views, closer to the surface, and gives closer
    /// fused meshes; the default (1.25) keeps the denser maps (docs/matcher.md, "How close
    /// the two values must agree", "The agreement limit on realistic rigs").
    #[arg(long, value_name = "PX", default_value_t = MatchParams::default().sgm_refine_agree)]
    pub sgm_refine_agree: f32,
    /// Leave each view's sub-pixel disparities as the matcher gives them, instead of refining
    /// them by a second correlation whose window follows the surface (fused models 8–50 %
    /// and views up to 44 % closer to the truth on the recordings measured; docs/matcher.md,
    /// "The window that follows the surface"), and giving the pixels within 6.5 px of the
    /// silhouette the rim's square-root profile (docs/matcher.md, "The rim's profile"). Used
    /// where views are made: `points`,
    /// `replay`, `demo`, `bench table1`'s errors and `bench live`; `disparity` writes the
    /// matcher's own map either way.
    #[arg(long)]
    pub no_follow_surface: bool,
    /// First disparity searched (may be negative). Default: 0, or −(N−1) on a calibrated rig
    /// whose rectified disparities are negative.
    #[arg(long, allow_hyphen_values = true)]
    pub min_disparity: Option<i32>,
    /// Number of disparities N (a count): the search covers D … D+N−1. Default: 64 for single
    /// pairs; 128 for `demo`, `replay` and `bench table1` (the simulated lab's disparities
    /// span 0…127), which `replay`, `demo` and `points`, given neither this nor
    /// `--min-disparity`, widen where the (first) frame's object lies beyond it.
    /// `--max-disparity` is the older name of this same count.
    #[arg(long = "num-disparities", visible_alias = "max-disparity", value_name = "N")]
    pub num_disparities: Option<u32>,
    /// Correlation window side (odd, 3…31; bm only).
    #[arg(long, default_value_t = MatchParams::default().block)]
    pub block: u32,
    /// Worker threads; default all cores.
    #[arg(long)]
    pub threads: Option<usize>,
    /// Uniqueness ratio in percent (0 disables). Default: 15 for bm, 0 for sgm.
    #[arg(long)]
    pub uniqueness: Option<u32>,
    /// Texture threshold: minimum summed |x-gradient| in the window (0 disables; bm only).
    /// Default: 10 for bm.
    #[arg(long)]
    pub texture_threshold: Option<u32>,
    /// Left–right check tolerance in pixels; a negative value disables the check.
    #[arg(long, default_value_t = 1, allow_hyphen_values = true)]
    pub lr_max_diff: i32,
    /// Speckle filter: largest blob (pixels) removed; 0 disables.
    #[arg(long, default_value_t = MatchParams::default().speckle_window)]
    pub speckle_window: u32,
    /// Speckle filter: largest disparity step inside a blob, pixels. Default: 0.5 for bm,
    /// 2 for sgm.
    #[arg(long)]
    pub speckle_range: Option<f32>,
}

/// A switch's value that was neither `on` nor `off`.
#[derive(Debug, thiserror::Error)]
#[error("expected on or off")]
struct NotOnOff;

/// `on` or `off` (a switch whose default depends on other flags).
fn on_off(s: &str) -> Result<bool, NotOnOff> {
    match s {
        "on" => Ok(true),
        "off" => Ok(false),
        _ => Err(NotOnOff),
    }
}

impl MatchArgs {
    pub fn params(&self) -> Result<MatchParams, Failure> {
        self.params_with_default(64)
    }

    /// The parameters, with `num_disparities` defaulting to `default_range`; one `--method`.
    pub fn params_with_default(&self, default_range: u32) -> Result<MatchParams, Failure> {
        match self.method.as_slice() {
            [m] => self.checked_params_for(*m, default_range),
            _ => Err(input(format!("--method {}: this command runs one matcher (bm or sgm); only `bench table1` takes a list", self.method.iter().map(|m| m.name()).collect::<Vec<_>>().join(",")))),
        }
    }

    /// Neither `--num-disparities` nor `--min-disparity` given: `replay`, `demo` and `points`
    /// then fit the range to the object (`pipeline::range`).
    pub fn range_unset(&self) -> bool {
        self.num_disparities.is_none() && self.min_disparity.is_none()
    }

    /// [`MatchArgs::params_for`], checked before any work starts: a value out of range is
    /// reported by its flag (`--p1 0: must be at least 1 and below p2`), not by the
    /// matcher's field once a recording is loaded.
    pub fn checked_params_for(&self, method: Method, default_range: u32) -> Result<MatchParams, Failure> {
        let p = self.params_for(method, default_range);
        match p.clone().validate() {
            Ok(_) => Ok(p),
            Err(e) => Err(input(match flag_of(e.name) {
                Some(flag) => format!("{flag} {}: {}", e.value, e.expected),
                None => e.to_string(),
            })),
        }
    }

    /// The parameters of matcher `method`: its defaults where a flag is not given.
    pub fn params_for(&self, method: Method, default_range: u32) -> MatchParams {
        let base = MatchParams::for_method(method);
        MatchParams {
            p1: self.p1,
            p2: self.p2,
            sgm_paths: self.sgm_paths,
            sgm_ad_cap: self.sgm_ad_cap,
            sgm_refine: !self.no_sgm_refine,
            coarse_to_fine: self.coarse_to_fine.unwrap_or(base.coarse_to_fine),
            sgm_refine_block: self.sgm_refine_block,
            sgm_refine_agree: self.sgm_refine_agree,
            min_disparity: self.min_disparity.unwrap_or(0),
            num_disparities: self.num_disparities.unwrap_or(default_range),
            block: self.block,
            uniqueness_ratio: self.uniqueness.unwrap_or(base.uniqueness_ratio),
            texture_threshold: self.texture_threshold.unwrap_or(base.texture_threshold),
            lr_max_diff: u32::try_from(self.lr_max_diff).ok(),
            speckle_window: self.speckle_window,
            speckle_range_px: self.speckle_range.unwrap_or(base.speckle_range_px),
            threads: self.threads.unwrap_or(0),
            ..base
        }
    }

}

/// The flag that sets the matcher parameter `name` ([`spinscan::stereo::ParamError::name`]),
/// where one does.
fn flag_of(name: &str) -> Option<&'static str> {
    Some(match name {
        "num_disparities" => "--num-disparities",
        "min_disparity" => "--min-disparity",
        "block" => "--block",
        "sgm_refine_block" => "--sgm-refine-block",
        "sgm_refine_agree" => "--sgm-refine-agree",
        "uniqueness_ratio" => "--uniqueness",
        "speckle_range_px" => "--speckle-range",
        "p1" => "--p1",
        "p2" => "--p2",
        "sgm_ad_cap" => "--sgm-ad-cap",
        "sgm_paths" => "--sgm-paths",
        "threads" => "--threads",
        _ => return None,
    })
}

/// A raw pair and its calibration (`rectify`, `points`).
#[derive(Args, Clone)]
pub struct RawPairArgs {
    /// Calibration: calib.yaml, or a folder with it or with intrinsics.yml + extrinsics.yml.
    #[arg(long)]
    pub calib: PathBuf,
    /// Raw left image (it also colours the points).
    #[arg(long)]
    pub left: PathBuf,
    /// Raw right image, the same size.
    #[arg(long)]
    pub right: PathBuf,
}

/// How a calibrated pair is rectified (`disparity --calib`, `rectify`, `points`, `replay`).
#[derive(Args, Clone)]
pub struct RectArgs {
    /// Rectification alpha: 0 (valid pixels only), 1 (all pixels), −1 (unscaled). Default: 0,
    /// or on a toed-in rig the least alpha that keeps the middle 60 % of both cameras' views
    /// in the rectified images (docs/calibration.md, "Toed-in rigs")
    #[arg(long, allow_hyphen_values = true)]
    pub alpha: Option<f64>,
}

/// The chroma key's colour and tolerance.
#[derive(Args, Clone)]
pub struct KeyColourArgs {
    /// Background colour to key out: `auto` (found in each frame: the most common blue or green
    /// of the left image's border, where the screen shows; where it shows no coloured screen,
    /// a plain backdrop keyed by its lack of texture — grey cameras, a white, grey or black
    /// backdrop; 40,70,190 where the border shows neither) or R,G,B (0…255 each).
    #[arg(long, default_value = "auto")]
    pub key_color: KeyColour,
    /// Largest chromaticity distance from the key colour still counted as background (0…1).
    #[arg(long, default_value_t = ChromaKey::default().tolerance)]
    pub key_tolerance: f32,
    /// The points within this many pixels of the object's silhouette (the mask's edge, not the
    /// image's) are left out of the fused model and mesh, the views' clouds and `points`'
    /// cloud, and kept for registration: their windows reach across the outline, and they are
    /// the least accurate a view has. 3 brings the mesh 4–16 % closer to the surface but covers
    /// up to 2.6 % less of it; parts of the object narrower than 2 N + 1 pixels are left out. 0
    /// fuses every point (docs/segmentation.md, "The silhouette's rim").
    #[arg(long, value_name = "N", default_value_t = ChromaKey::default().rim_px, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=spinscan::segment::MAX_RIM_PX as u64))]
    pub rim_px: usize,
}

impl KeyColourArgs {
    pub fn chroma(&self) -> ChromaKey {
        ChromaKey { key: self.key_color, tolerance: self.key_tolerance, rim_px: self.rim_px, ..ChromaKey::default() }
    }
}

/// Blue-screen segmentation knobs (used by `--mask auto`).
#[derive(Args, Clone)]
pub struct KeyArgs {
    #[command(flatten)]
    pub colour: KeyColourArgs,
    /// Image of the empty scene (raw left camera): pixels close to it are background too.
    #[arg(long)]
    pub plate: Option<PathBuf>,
}

impl KeyArgs {
    pub fn chroma(&self) -> ChromaKey {
        self.colour.chroma()
    }

    /// The plate's RGB, checked against the size of the images it keys (`what`: the images
    /// named in the message).
    pub fn load_plate(&self, size: (usize, usize), what: &str) -> Result<Option<Vec<u8>>, Failure> {
        let Some(p) = &self.plate else { return Ok(None) };
        let img = spinscan::io::load_image(p).map_err(input)?;
        if (img.width, img.height) != size {
            return Err(input(format!("plate {} is {}×{} but {what} are {}×{}", p.display(), img.width, img.height, size.0, size.1)));
        }
        Ok(Some(img.rgb))
    }
}

#[derive(Args, Clone)]
pub struct AssistArgs {
    /// Smallest half-width of an assisted interval, pixels.
    #[arg(long, default_value_t = AssistParams::default().min_half_width_px)]
    pub assist_min_half_width: f64,
    /// Predicted mode: the matcher's own disparity noise σ, pixels.
    #[arg(long, default_value_t = AssistParams::default().predicted_sigma_px)]
    pub predict_sigma_px: f64,
    /// Predicted mode: interval half-width in σ.
    #[arg(long, default_value_t = AssistParams::default().predicted_k)]
    pub predict_k: f64,
    /// Self-correction: rematch a frame over the full range when its valid fraction falls
    /// below this share of the recent median.
    #[arg(long, default_value_t = AssistParams::default().fallback_valid_ratio)]
    pub fallback_valid_ratio: f64,
    /// Self-correction: do not let a registration with lower ICP fitness guide the next frame.
    #[arg(long, default_value_t = AssistParams::default().min_fitness)]
    pub assist_min_fitness: f64,
    /// Self-correction: nor one whose ICP RMSE exceeds this many times the recent median.
    #[arg(long, default_value_t = AssistParams::default().max_rmse_ratio)]
    pub assist_max_rmse_ratio: f64,
}

/// How `replay` and `demo` choose each frame's search range.
#[derive(Args, Clone)]
pub struct AssistModeArgs {
    /// Search range per frame: `predicted` (the Kalman-predicted disparity ± its
    /// uncertainty; default), `paper` (the paper's registration constraint, weight
    /// --assist-w), or `none` (the full range). Needs registration.
    #[arg(long)]
    pub assist: Option<String>,
    /// The paper's weighting factor w (with --assist paper).
    #[arg(long, default_value_t = 0.8)]
    pub assist_w: f64,
    /// How finely the search range is set: `pixel` (each pixel its own interval), `tile`
    /// (one interval per 16 × 8 tile, the hull of its pixels'), `plane` (a tile's interval
    /// sloped along a plane fitted to the previous frame's disparities there), or `auto`
    /// (planes for predicted, pixels for paper: what measured best for each).
    #[arg(long, default_value = "auto")]
    pub assist_granularity: String,
    #[command(flatten)]
    pub knobs: AssistArgs,
}

impl AssistModeArgs {
    /// The assistance to run (None: full range), given whether registration runs.
    pub fn params(&self, registering: bool) -> Result<Option<AssistParams>, Failure> {
        let mode = AssistMode::parse(self.assist.as_deref().unwrap_or("predicted"), self.assist_w).map_err(|e| input(format!("--assist: {e}")))?;
        match (mode, registering) {
            (AssistMode::None, _) => Ok(None),
            (_, true) => {
                let granularity = Granularity::parse(&self.assist_granularity).map_err(|e| input(format!("--assist-granularity: {e}")))?;
                Ok(Some(AssistParams { granularity, ..self.knobs.params(mode)? }))
            }
            (_, false) if self.assist.is_some() => Err(input(format!("--assist {} uses the registered motion, which --no-register turns off", mode.name()))),
            (_, false) => Ok(None),
        }
    }
}

impl AssistArgs {
    pub fn params(&self, mode: AssistMode) -> Result<AssistParams, Failure> {
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

/// Registration knobs of `replay` and `demo`.
#[derive(Args, Clone)]
pub struct RegistrationArgs {
    /// Only match: no registration, no poses.jsonl, model.ply or turntable_estimated.yaml.
    #[arg(long)]
    pub no_register: bool,
    /// m of the paper's block registration: every m views are registered together to the
    /// model of the views before them (0 = pairwise only).
    #[arg(long = "block-views", id = "block_views", default_value_t = 5)]
    pub block_views: usize,
    /// ICP correspondence distance between consecutive views, mm.
    #[arg(long, default_value_t = 8.0)]
    pub icp_max_distance: f64,
    /// ICP method: point-to-plane or point-to-point (the paper's).
    #[arg(long, default_value = "point-to-plane")]
    pub icp_method: String,
    /// Voxel side of the fused surface (mesh.ply, model.ply), mm; the mesh's field uses a
    /// coarser one where the views are sampled coarser (docs/meshing.md).
    #[arg(long, default_value_t = 1.0)]
    pub voxel: f64,
    /// Do not fuse the views: no mesh.ply, and model.ply is the voxel-merged points (the
    /// model before fusion; docs/registration.md).
    #[arg(long)]
    pub no_mesh: bool,
    /// With --no-mesh: keep isolated points in model.ply (no noise removal).
    #[arg(long)]
    pub no_denoise: bool,
    /// Do not close the loop after a full turn.
    #[arg(long)]
    pub no_loop_closure: bool,
    /// Keep the registered poses even when every step agrees with the turntable's angles
    /// (by default the turntable's predictions about the estimated axis replace them then).
    #[arg(long)]
    pub no_turntable_poses: bool,
    /// Fit the turntable's axis to the views' points only, without tracking the object's
    /// texture from view to view (by default an axis fitted to the texture tracks replaces
    /// the points' fit when it is known well enough; docs/registration.md).
    #[arg(long)]
    pub no_texture_tracks: bool,
}

impl RegistrationArgs {
    pub fn options(&self, pipeline: PipelineOptions) -> Result<ReplayOptions, Failure> {
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
        match opts.model.mesh.as_mut() {
            Some(_) if self.no_mesh => opts.model.mesh = None,
            Some(m) => m.voxel_mm = self.voxel,
            None => {}
        }
        if self.no_register {
            opts.registration = None;
        } else if let Some(r) = opts.registration.as_mut() {
            r.block = self.block_views;
            r.close_loop = !self.no_loop_closure;
            r.turntable_poses = !self.no_turntable_poses;
            if self.no_texture_tracks {
                r.tracks = None;
            }
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
