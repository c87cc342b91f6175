//! `spinscand`'s configuration: a TOML file whose every key has a built-in default
//! (`config/spinscand.toml` lists them all, with units and meaning; a test keeps the two
//! equal). Unknown keys are errors, so a typo never silently falls back to a default.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::assist::{AssistMode, AssistModeError, AssistParams, Granularity};
use crate::hw::sim::SimSection;
use crate::hw::DriverConfig;
use crate::pipeline::live::{check_step_deg, check_total_deg, PipelineSettings, SpecError, MAX_MATCHER_THREADS, MAX_QUEUE_DEPTH};
use crate::segment::KeyColour;

/// Why a configuration cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config {path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("config {path}: {what}")]
    Parse { path: PathBuf, what: String },
    #[error("config {path}: `{key}` {what}")]
    Invalid { path: PathBuf, key: &'static str, what: String },
}

/// Which devices the daemon drives (`[backend] kind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum BackendKind {
    /// Two V4L2 cameras and the Horus turntable on a serial port (the lab).
    V4l2,
    /// hw-sim's cameras and its turntable firmware on a pseudo-terminal.
    Sim,
    /// A recording played back as if captured (`[backend] replay`); no turntable.
    Replay,
}

impl BackendKind {
    pub fn name(self) -> &'static str {
        match self {
            BackendKind::V4l2 => "v4l2",
            BackendKind::Sim => "sim",
            BackendKind::Replay => "replay",
        }
    }
}

/// The whole file.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    pub daemon: DaemonSection,
    pub backend: BackendSection,
    pub cameras: CameraSection,
    pub turntable: TurntableSection,
    pub scan: ScanSection,
    pub matching: MatchingSection,
    pub sim: SimSection,
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct DaemonSection {
    /// The control socket.
    pub socket: PathBuf,
    /// Permission bits of the socket, octal.
    pub socket_mode: String,
    /// Group that owns the socket and may control the daemon ("" = the daemon's own group
    /// only; root and the daemon's user may always).
    pub group: String,
    /// One folder per scan below this.
    pub state_dir: PathBuf,
    /// Longest request line accepted, bytes.
    pub max_request_bytes: usize,
    /// Most clients connected at once (the last few kept for peers with control rights).
    pub max_clients: usize,
    /// A connection that sends no request for this long is closed (event subscribers
    /// excepted), seconds.
    pub idle_timeout_s: f64,
    /// A scan whose pipeline makes no progress for this long is unhealthy (the systemd
    /// watchdog stops being fed), seconds.
    pub stall_s: f64,
}

impl Default for DaemonSection {
    fn default() -> Self {
        DaemonSection {
            socket: "/run/spinscan/control.sock".into(),
            socket_mode: "0660".into(),
            group: "spinscan".into(),
            state_dir: "/var/lib/spinscan/scans".into(),
            max_request_bytes: 65_536,
            max_clients: 32,
            idle_timeout_s: 300.0,
            stall_s: 10.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct BackendSection {
    pub kind: BackendKind,
    /// The recording the `replay` backend plays.
    pub replay: PathBuf,
    /// Pace the replay at the cameras' frame rate (else as fast as the pipeline takes it).
    pub replay_paced: bool,
}

impl Default for BackendSection {
    fn default() -> Self {
        BackendSection { kind: BackendKind::V4l2, replay: PathBuf::new(), replay_paced: true }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraSection {
    pub left: PathBuf,
    pub right: PathBuf,
    /// The rig's calibration (recording spec `calib.yaml`, or OpenCV intrinsics.yml +
    /// extrinsics.yml named by the intrinsics file).
    pub calibration: PathBuf,
    /// The turntable's axis (`turntable.yaml` from `spinscan calibrate turntable`); empty =
    /// none: scans then estimate it from the views.
    pub turntable_axis: PathBuf,
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    /// "MJPG" (stored as delivered) or "YUYV" (stored as PNG).
    pub pixel_format: String,
    /// mmap buffers per camera.
    pub buffers: u32,
    /// Left and right frames further apart than this are not a pair, ms (0 = half a frame
    /// period).
    pub pair_tolerance_ms: f64,
    /// A camera silent this long has stopped, ms.
    pub frame_timeout_ms: u64,
    /// Auto exposure on (true) or off (false); absent = leave the camera's setting.
    pub auto_exposure: Option<bool>,
    /// Exposure time in the V4L2 unit (100 µs); absent = leave.
    pub exposure_100us: Option<i64>,
    /// Analogue gain in the camera's unit; absent = leave.
    pub gain: Option<i64>,
}

impl Default for CameraSection {
    fn default() -> Self {
        CameraSection {
            left: "/dev/spinscan-left".into(),
            right: "/dev/spinscan-right".into(),
            calibration: "/etc/spinscan/calib.yaml".into(),
            turntable_axis: PathBuf::new(),
            width: 640,
            height: 480,
            fps: 15,
            pixel_format: "MJPG".into(),
            buffers: 4,
            pair_tolerance_ms: 0.0,
            frame_timeout_ms: 1000,
            auto_exposure: None,
            exposure_100us: None,
            gain: None,
        }
    }
}

impl CameraSection {
    /// `pixel_format` as a fourcc (validated to be 4 ASCII letters).
    pub fn fourcc(&self) -> [u8; 4] {
        let mut fourcc = [b' '; 4];
        for (d, s) in fourcc.iter_mut().zip(self.pixel_format.bytes()) {
            *d = s;
        }
        fourcc
    }

    /// The pairing tolerance in ns (half a frame period unless set).
    pub fn pair_tolerance_ns(&self) -> u64 {
        if self.pair_tolerance_ms > 0.0 {
            (self.pair_tolerance_ms * 1e6) as u64
        } else {
            (0.5e9 / self.fps.max(1) as f64) as u64
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct TurntableSection {
    pub port: String,
    pub baud: u32,
    pub reply_timeout_ms: u64,
    pub tries: u32,
    /// +1 when positive firmware X turns the table counterclockwise seen from above.
    pub direction: i8,
    /// Feed for step moves, degrees per second.
    pub feed_deg_s: f64,
    pub accel_deg_s2: f64,
    pub stall_tolerance_deg: f64,
    /// Wait after arrival before capturing, ms.
    pub settle_ms: u64,
    /// Wait for the board's power-on greeting after opening the port (opening resets it), ms.
    pub boot_wait_ms: u64,
    /// Rotation speed of a continuous scan, degrees per second (6 °/s at 15 fps = 0.4° per
    /// pair).
    pub continuous_deg_s: f64,
}

impl Default for TurntableSection {
    fn default() -> Self {
        let d = DriverConfig::default();
        TurntableSection {
            port: "/dev/spinscan-table".into(),
            baud: d.baud,
            reply_timeout_ms: d.reply_timeout.as_millis() as u64,
            tries: d.tries,
            direction: d.direction,
            feed_deg_s: d.feed_deg_s,
            accel_deg_s2: d.accel_deg_s2,
            stall_tolerance_deg: d.stall_tolerance_deg,
            settle_ms: d.settle.as_millis() as u64,
            boot_wait_ms: d.boot_wait.as_millis() as u64,
            continuous_deg_s: 6.0,
        }
    }
}

impl TurntableSection {
    pub fn driver(&self) -> DriverConfig {
        DriverConfig {
            baud: self.baud,
            reply_timeout: Duration::from_millis(self.reply_timeout_ms),
            tries: self.tries,
            direction: self.direction,
            feed_deg_s: self.feed_deg_s,
            accel_deg_s2: self.accel_deg_s2,
            stall_tolerance_deg: self.stall_tolerance_deg,
            settle: Duration::from_millis(self.settle_ms),
            boot_wait: Duration::from_millis(self.boot_wait_ms),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScanSection {
    /// Step between views of a step scan, degrees.
    pub step_deg: f64,
    /// How far a scan turns, degrees.
    pub total_deg: f64,
    /// Pairs waiting for the matcher pool (the bounded channel's capacity).
    pub queue_depth: usize,
    /// Matcher threads (0 = one per core).
    pub matcher_threads: usize,
    /// Register the views and build the model.
    pub register: bool,
    /// Registration keeps at most this many points of each view (subsampled), 0 = all.
    pub register_max_points: usize,
    /// Track the object's texture from view to view and fit the turntable's axis to the
    /// tracks at the end of a scan without a calibrated axis (docs/registration.md).
    pub texture_tracks: bool,
}

impl Default for ScanSection {
    fn default() -> Self {
        ScanSection { step_deg: 2.0, total_deg: 360.0, queue_depth: 16, matcher_threads: 0, register: true, register_max_points: 20_000, texture_tracks: true }
    }
}

#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct MatchingSection {
    /// The matcher: "bm" (correlation) or "sgm" (semi-global).
    pub method: crate::stereo::Method,
    pub num_disparities: u32,
    /// Widen the range where a scan's first frame shows the object outside it (`pipeline::range`).
    pub fit_range: bool,
    pub block: u32,
    /// SGM's penalties and paths (method "sgm").
    pub p1: u16,
    pub p2: u16,
    pub sgm_paths: u8,
    /// SGM's intensity term: cap in grey levels (0 = census alone).
    pub sgm_ad_cap: u8,
    /// SGM's sub-pixel disparities from the correlation cost around each winner.
    pub sgm_refine: bool,
    /// That correlation's window side (odd, 3 … 31).
    pub sgm_refine_block: u32,
    /// How close (pixels, 0.1 … 2) that correlation's value must come to SGM's own to keep
    /// a view's match.
    pub sgm_refine_agree: f32,
    /// Wide searches seeded from the pair matched at half size: "auto" (the method's
    /// default: on for sgm, off for bm), "on" or "off".
    pub coarse_to_fine: CoarseToFine,
    /// "predicted", "paper" or "none".
    pub assist: String,
    /// The paper's weighting factor w (mode "paper").
    pub assist_w: f64,
    /// "auto" (planes for "predicted", pixels for "paper"), "pixel" (each pixel its own
    /// search interval), "tile" (one per 16 × 8 tile) or "plane" (one per tile, sloped
    /// along the previous frame's disparities there).
    pub assist_granularity: String,
    /// Segment the blue screen.
    pub segment: bool,
    /// The screen's colour: "auto" (found in each frame's border) or "R,G,B".
    pub key_color: String,
    /// Points this near the object's silhouette are not fused, only registered (0 … 32 px).
    pub rim_px: usize,
    /// Refine each view's sub-pixel disparities with a window that follows the surface before
    /// they are triangulated (registration takes the matcher's own).
    pub follow_surface: bool,
    /// An image of the empty scene from the left camera (PNG or JPEG), "" for none.
    pub plate: PathBuf,
}

/// `[matching] coarse_to_fine`: whether wide searches are seeded from the half-size pair. Written
/// `"auto"`, `"on"` or `"off"`; `true` and `false` are read as on and off.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase", try_from = "CoarseToFineWritten")]
pub enum CoarseToFine {
    /// The method's default (`MatchParams::for_method`): on for sgm, off for bm.
    #[default]
    Auto,
    On,
    Off,
}

/// `coarse_to_fine` as a config file may write it.
#[derive(serde::Deserialize)]
#[serde(untagged)]
enum CoarseToFineWritten {
    Flag(bool),
    Word(String),
    Other(serde::de::IgnoredAny),
}

/// A `coarse_to_fine` value that is none of the accepted ones.
#[derive(Debug, thiserror::Error)]
pub enum BadCoarseToFine {
    /// A string, as written.
    #[error("coarse_to_fine = {0}: expected \"auto\", \"on\", \"off\", true or false")]
    Word(String),
    /// Neither a string nor a boolean.
    #[error("coarse_to_fine: expected \"auto\", \"on\", \"off\", true or false")]
    Other,
}

impl TryFrom<CoarseToFineWritten> for CoarseToFine {
    type Error = BadCoarseToFine;
    fn try_from(v: CoarseToFineWritten) -> Result<Self, BadCoarseToFine> {
        match v {
            CoarseToFineWritten::Flag(on) => Ok(if on { CoarseToFine::On } else { CoarseToFine::Off }),
            CoarseToFineWritten::Word(w) => match w.as_str() {
                "auto" => Ok(CoarseToFine::Auto),
                "on" => Ok(CoarseToFine::On),
                "off" => Ok(CoarseToFine::Off),
                _ => Err(BadCoarseToFine::Word(format!("{w:?}"))),
            },
            CoarseToFineWritten::Other(_) => Err(BadCoarseToFine::Other),
        }
    }
}

impl CoarseToFine {
    pub fn resolve(self, method: crate::stereo::Method) -> bool {
        match self {
            CoarseToFine::Auto => crate::stereo::MatchParams::for_method(method).coarse_to_fine,
            CoarseToFine::On => true,
            CoarseToFine::Off => false,
        }
    }
}

impl Default for MatchingSection {
    fn default() -> Self {
        // 128 disparities: the lab rig (60 mm baseline, f ≈ 700 px) sees the object from
        // about 330 mm on.
        let m = crate::stereo::MatchParams::default();
        MatchingSection { method: m.method, num_disparities: 128, fit_range: true, block: m.block, p1: m.p1, p2: m.p2, sgm_paths: m.sgm_paths, sgm_ad_cap: m.sgm_ad_cap, sgm_refine: m.sgm_refine, sgm_refine_block: m.sgm_refine_block, sgm_refine_agree: m.sgm_refine_agree, coarse_to_fine: CoarseToFine::Auto, assist: "predicted".into(), assist_w: 0.8, assist_granularity: Granularity::default().name().into(), segment: true, key_color: KeyColour::Auto.to_string(), rim_px: crate::segment::DEFAULT_RIM_PX, follow_surface: true, plate: PathBuf::new() }
    }
}

impl Default for Config {
    fn default() -> Self {
        Config {
            daemon: DaemonSection::default(),
            backend: BackendSection::default(),
            cameras: CameraSection::default(),
            turntable: TurntableSection::default(),
            scan: ScanSection::default(),
            matching: MatchingSection::default(),
            sim: SimSection::default(),
        }
    }
}

impl Config {
    /// What `spinscand --sim` runs: the defaults with the simulated lab, a socket and state
    /// folder in the working directory, no group.
    pub fn sim() -> Config {
        let mut c = Config::default();
        c.backend.kind = BackendKind::Sim;
        c.daemon.socket = "spinscan.sock".into();
        c.daemon.state_dir = "scans".into();
        c.daemon.group = String::new();
        c
    }

    /// Reads and checks a config file.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read { path: path.to_path_buf(), source })?;
        Config::parse(path, &text)
    }

    pub fn parse(path: &Path, text: &str) -> Result<Config, ConfigError> {
        let c: Config = toml::from_str(text).map_err(|e| ConfigError::Parse { path: path.to_path_buf(), what: e.to_string().trim_end().to_string() })?;
        c.validate(path)?;
        Ok(c)
    }

    /// Checks values a type cannot: every number within a range that keeps the daemon
    /// healthy (the ranges are documented in `config/spinscand.toml`), the matcher's
    /// parameters by the matcher's own rules, and the scan bounds by `scan.start`'s.
    pub fn validate(&self, path: &Path) -> Result<(), ConfigError> {
        let bad = |key: &'static str, what: String| Err(ConfigError::Invalid { path: path.to_path_buf(), key, what });
        // Whole numbers within lo…hi.
        fn whole(v: u64, lo: u64, hi: u64) -> Option<String> {
            (!(lo..=hi).contains(&v)).then(|| format!("must be {lo} … {hi}, got {v}"))
        }
        // Finite numbers within lo…hi (lo excluded when `open`).
        fn real(v: f64, lo: f64, hi: f64, open: bool) -> Option<String> {
            let ok = v.is_finite() && v <= hi && if open { v > lo } else { v >= lo };
            (!ok).then(|| format!("must be {}{lo}, {hi}], got {v}", if open { "within (" } else { "within [" }))
        }
        let d = &self.daemon;
        let c = &self.cameras;
        let t = &self.turntable;
        let s = &self.scan;
        let checks: [(&'static str, Option<String>); 28] = [
            ("daemon.max_request_bytes", whole(d.max_request_bytes as u64, 256, 16 << 20)),
            ("daemon.max_clients", whole(d.max_clients as u64, 1, 1024)),
            ("daemon.stall_s", real(d.stall_s, 0.5, 3600.0, false)),
            ("daemon.idle_timeout_s", real(d.idle_timeout_s, 0.1, 86_400.0, false)),
            ("cameras.width", whole(c.width as u64, 32, 8192)),
            ("cameras.height", whole(c.height as u64, 32, 8192)),
            ("cameras.fps", whole(c.fps as u64, 1, 240)),
            ("cameras.buffers", whole(c.buffers as u64, 2, 32)),
            ("cameras.pair_tolerance_ms", real(c.pair_tolerance_ms, 0.0, 1000.0, false)),
            ("cameras.frame_timeout_ms", whole(c.frame_timeout_ms, 50, 60_000)),
            ("turntable.baud", whole(t.baud as u64, 1200, 4_000_000)),
            ("turntable.reply_timeout_ms", whole(t.reply_timeout_ms, 10, 30_000)),
            ("turntable.tries", whole(t.tries as u64, 1, 20)),
            ("turntable.feed_deg_s", real(t.feed_deg_s, 0.0, 3600.0, true)),
            ("turntable.accel_deg_s2", real(t.accel_deg_s2, 0.0, 100_000.0, true)),
            ("turntable.stall_tolerance_deg", real(t.stall_tolerance_deg, 0.0, 10.0, false)),
            ("turntable.settle_ms", whole(t.settle_ms, 0, 10_000)),
            ("turntable.boot_wait_ms", whole(t.boot_wait_ms, 0, 30_000)),
            ("turntable.continuous_deg_s", real(t.continuous_deg_s, 0.0, 360.0, true)),
            ("scan.queue_depth", whole(s.queue_depth as u64, 1, MAX_QUEUE_DEPTH as u64)),
            ("scan.matcher_threads", whole(s.matcher_threads as u64, 0, MAX_MATCHER_THREADS as u64)),
            ("scan.register_max_points", whole(s.register_max_points as u64, 0, 1_000_000)),
            ("matching.assist_w", real(self.matching.assist_w, 0.0, 100.0, true)),
            ("sim.width", whole(self.sim.width as u64, 32, 4096)),
            ("sim.height", whole(self.sim.height as u64, 32, 4096)),
            ("sim.time_scale", real(self.sim.time_scale, 0.0, 1000.0, true)),
            ("cameras.exposure_100us", c.exposure_100us.filter(|e| !(1..=10_000_000).contains(e)).map(|e| format!("must be 1 … 10000000, got {e}"))),
            ("cameras.gain", c.gain.filter(|g| !(0..=1_000_000).contains(g)).map(|g| format!("must be 0 … 1000000, got {g}"))),
        ];
        for (key, problem) in checks {
            if let Some(what) = problem {
                return bad(key, what);
            }
        }
        if self.socket_mode().is_none() {
            return bad("daemon.socket_mode", format!("must be octal permission bits like \"0660\", got {:?}", self.daemon.socket_mode));
        }
        if self.backend.kind == BackendKind::Replay && self.backend.replay.as_os_str().is_empty() {
            return bad("backend.replay", "must name a recording when backend.kind = \"replay\"".into());
        }
        if !["MJPG", "YUYV"].contains(&c.pixel_format.as_str()) {
            return bad("cameras.pixel_format", format!("must be \"MJPG\" or \"YUYV\", got {:?}", c.pixel_format));
        }
        if t.direction != 1 && t.direction != -1 {
            return bad("turntable.direction", format!("must be 1 or -1, got {}", t.direction));
        }
        // The same bounds `scan.start` applies (ScanSpec::validate).
        if let Err(SpecError::Range { expected, got, .. }) = check_step_deg(s.step_deg) {
            return bad("scan.step_deg", format!("must be {expected}, got {got}"));
        }
        if let Err(SpecError::Range { expected, got, .. }) = check_total_deg(s.total_deg) {
            return bad("scan.total_deg", format!("must be {expected}, got {got}"));
        }
        // The matcher's own rules (MatchParams::validate), on the parameters a scan will use.
        if let Err(e) = self.pipeline_settings().pipeline.matching.validate() {
            let key = match e.name {
                "num_disparities" => "matching.num_disparities",
                "block" => "matching.block",
                "p1" => "matching.p1",
                "p2" => "matching.p2",
                "sgm_paths" => "matching.sgm_paths",
                "sgm_ad_cap" => "matching.sgm_ad_cap",
                "sgm_refine_block" => "matching.sgm_refine_block",
                "sgm_refine_agree" => "matching.sgm_refine_agree",
                _ => "matching",
            };
            return bad(key, format!("{}, got {}", e.expected, e.value));
        }
        if let Err(e) = self.matching.key_color.parse::<KeyColour>() {
            return bad("matching.key_color", e.to_string());
        }
        if self.matching.rim_px > crate::segment::MAX_RIM_PX {
            return bad("matching.rim_px", format!("expected 0 … {} pixels, got {}", crate::segment::MAX_RIM_PX, self.matching.rim_px));
        }
        if let Err(e) = self.plate() {
            return bad("matching.plate", format!("{e} (expected an image of the empty scene from the left camera, PNG or JPEG, or \"\" for none)"));
        }
        if let Err(e) = self.assist() {
            let key = if matches!(e, AssistModeError::Granularity(_)) { "matching.assist_granularity" } else { "matching.assist" };
            return bad(key, e.to_string());
        }
        if let Err(e) = crate::hw::sim::check_object(&self.sim.object) {
            return bad("sim.object", e.to_string());
        }
        if let Err(e) = self.turntable_axis() {
            return bad("cameras.turntable_axis", format!("{e} (expected a turntable.yaml from `spinscan calibrate turntable`, or \"\" for none)"));
        }
        Ok(())
    }

    /// The pipeline settings a config asks for.
    pub fn pipeline_settings(&self) -> PipelineSettings {
        let config = self;
        let mut pipeline = crate::pipeline::PipelineOptions::default();
        let m = &config.matching;
        pipeline.matching = crate::stereo::MatchParams { num_disparities: m.num_disparities, block: m.block, p1: m.p1, p2: m.p2, sgm_paths: m.sgm_paths, sgm_ad_cap: m.sgm_ad_cap, sgm_refine: m.sgm_refine, sgm_refine_block: m.sgm_refine_block, sgm_refine_agree: m.sgm_refine_agree, coarse_to_fine: m.coarse_to_fine.resolve(m.method), ..crate::stereo::MatchParams::for_method(m.method) };
        pipeline.fit_range = m.fit_range;
        // Parallelism comes from the pool: one thread per matcher.
        pipeline.matching.threads = 1;
        // (An unknown colour is refused by `validate`; unvalidated configs find the screen.)
        pipeline.chroma.key = m.key_color.parse().unwrap_or(KeyColour::Auto);
        pipeline.chroma.rim_px = m.rim_px;
        pipeline.follow_surface = m.follow_surface;
        let registration = config.scan.register.then(|| {
            let mut p = crate::register::ring::RegistrationParams::default();
            if config.scan.register_max_points > 0 {
                // Both ends of ICP: the view moved (source) and the view it lands on (target).
                p.max_target_points = config.scan.register_max_points;
                p.icp.max_source_points = p.icp.max_source_points.min(config.scan.register_max_points);
            }
            if !config.scan.texture_tracks {
                p.tracks = None;
            }
            p
        });
        PipelineSettings {
            pipeline,
            segment: config.matching.segment,
            // Checked by `validate`; a file gone since is a warning and no plate.
            plate: config.plate().unwrap_or_else(|e| {
                tracing::warn!("matching.plate: {e}; scans key by the screen's colour alone");
                None
            }),
            // An unknown mode is refused by `validate`; unvalidated configs match full range.
        assist: if registration.is_some() { config.assist().ok().flatten() } else { None },
            registration,
            matcher_threads: config.scan.matcher_threads,
            queue_depth: config.scan.queue_depth,
            record: true,
            pace_hz: (config.backend.kind == BackendKind::Replay && config.backend.replay_paced).then_some(config.cameras.fps as f64),
            register_newest_when_behind: false,
            // Checked by `validate`; a file gone since is a warning and no axis.
            calibrated_axis: config.turntable_axis().unwrap_or_else(|e| {
                tracing::warn!("cameras.turntable_axis: {e}; scans estimate the axis from the views");
                None
            }),
        }
    }

    /// The background plate, when `matching.plate` names one.
    pub fn plate(&self) -> Result<Option<Arc<crate::io::LoadedImage>>, crate::io::ImageIoError> {
        let path = &self.matching.plate;
        if path.as_os_str().is_empty() {
            return Ok(None);
        }
        crate::io::load_image(path).map(|i| Some(Arc::new(i)))
    }

    /// The calibrated turntable axis, when `cameras.turntable_axis` names one.
    pub fn turntable_axis(&self) -> Result<Option<crate::recording::TurntableAxis>, crate::recording::RecordingError> {
        let path = &self.cameras.turntable_axis;
        if path.as_os_str().is_empty() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(path).map_err(|source| crate::recording::RecordingError::Io { path: path.clone(), source })?;
        crate::recording::TurntableAxis::parse(path, &text).map(Some)
    }

    /// The socket's permission bits.
    pub fn socket_mode(&self) -> Option<u32> {
        u32::from_str_radix(self.daemon.socket_mode.trim_start_matches("0o"), 8).ok().filter(|m| *m <= 0o777)
    }

    /// Registration-assisted matching settings (None: full range every frame).
    pub fn assist(&self) -> Result<Option<AssistParams>, AssistModeError> {
        let mode = AssistMode::parse(&self.matching.assist, self.matching.assist_w)?;
        let granularity = Granularity::parse(&self.matching.assist_granularity)?;
        Ok((!matches!(mode, AssistMode::None)).then(|| AssistParams { mode, granularity, ..AssistParams::default() }))
    }
}

#[cfg(test)]
mod tests;
