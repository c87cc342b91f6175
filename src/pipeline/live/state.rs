//! What one scan is and shares: its request ([`ScanSpec`], checked once by
//! [`ScanSpec::validate`]), the pipeline settings, the live counters and stop flag every
//! thread of the scan reads, and the messages between the threads.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde_json::{json, Value};

use crate::assist::AssistParams;
use crate::hw::{CaptureError, StereoFrame, StereoSource, Turntable, TurntableError};
use crate::pipeline::results::ResultsError;
use crate::pipeline::{FrameError, PipelineError, PipelineOptions, View};
use crate::recording::RecordingError;
use crate::register::ring::RegistrationParams;

/// How the table turns during a scan.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScanMode {
    /// Step, wait for arrival and settle, capture one pair; repeat.
    Step,
    /// One slow move while the cameras run at their frame rate (the paper's set-up).
    Continuous,
}

impl ScanMode {
    pub fn name(self) -> &'static str {
        match self {
            ScanMode::Step => "step",
            ScanMode::Continuous => "continuous",
        }
    }
}

/// What `scan.start` asked for, resolved against the config.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanSpec {
    pub name: String,
    pub mode: ScanMode,
    pub step_deg: f64,
    pub total_deg: f64,
    /// Rotation speed of a continuous scan, degrees per second.
    pub speed_deg_s: f64,
    /// Stop after this many pairs (None: when the table has turned `total_deg`, or the
    /// source runs out).
    pub max_views: Option<usize>,
}

/// A scan request that cannot run: the field and what it must be.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SpecError {
    #[error("`{field}` must be {expected}, got {got}")]
    Range { field: &'static str, expected: &'static str, got: String },
    #[error("scan name {0:?} is not allowed: use 1–64 letters, digits, '-', '_' or '.', starting with a letter or digit (it names a folder)")]
    Name(String),
}

impl ScanSpec {
    /// The bounds every scan obeys, whoever asked for it (the control socket or the
    /// config's `[scan]` defaults): one place, one set of rules.
    pub fn validate(&self) -> Result<(), SpecError> {
        validate_name(&self.name)?;
        check_step_deg(self.step_deg)?;
        check_total_deg(self.total_deg)?;
        if !(self.speed_deg_s > 0.0 && self.speed_deg_s <= 360.0) {
            return Err(SpecError::Range { field: "speed_deg_s", expected: "within (0, 360]", got: self.speed_deg_s.to_string() });
        }
        if self.max_views == Some(0) {
            return Err(SpecError::Range { field: "max_views", expected: "at least 1", got: "0".into() });
        }
        Ok(())
    }

    /// The manifest of a scan that has no results yet: what it is, how it stands, and why.
    pub fn manifest(&self, status: &str, reason: Option<&str>) -> Value {
        let mut m = json!({
            "format": 1, "status": status, "frames": 0,
            "name": self.name, "mode": self.mode.name(), "total_deg": self.total_deg,
            "written_by": format!("spinscan {}", env!("CARGO_PKG_VERSION")),
        });
        if let Some(r) = reason {
            m["reason"] = json!(r);
        }
        m
    }

    /// Views of a step scan: a full turn (or more) does not capture its start twice; a
    /// partial arc includes both ends.
    pub fn step_views(&self) -> usize {
        let n = (self.total_deg / self.step_deg + 1e-9).floor() as usize;
        let n = if self.total_deg < 360.0 - 1e-9 { n + 1 } else { n };
        n.max(1).min(self.max_views.unwrap_or(usize::MAX))
    }
}

/// Most pairs waiting for the matcher pool (`scan.queue_depth`): each holds a decoded pair.
pub const MAX_QUEUE_DEPTH: usize = 256;

/// Most matcher threads (`scan.matcher_threads`; 0 = one per core, at most this many): each
/// keeps its own scratch buffers.
pub const MAX_MATCHER_THREADS: usize = 32;

/// The smallest step of a step scan, degrees: below it a turn has more views than any lab
/// wants (7200 at 0.05°), and a tiny step would never advance.
pub const MIN_STEP_DEG: f64 = 0.05;

/// Step between views of a step scan: within [0.05, 360] degrees.
pub fn check_step_deg(step_deg: f64) -> Result<(), SpecError> {
    if (MIN_STEP_DEG..=360.0).contains(&step_deg) {
        Ok(())
    } else {
        Err(SpecError::Range { field: "step_deg", expected: "within [0.05, 360]", got: step_deg.to_string() })
    }
}

/// How far a scan turns: within (0, 3600] degrees (ten turns).
pub fn check_total_deg(total_deg: f64) -> Result<(), SpecError> {
    if total_deg > 0.0 && total_deg <= 3600.0 {
        Ok(())
    } else {
        Err(SpecError::Range { field: "total_deg", expected: "within (0, 3600]", got: total_deg.to_string() })
    }
}

/// Scan names: a folder name, never a path.
pub fn validate_name(name: &str) -> Result<(), SpecError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && name.chars().next().is_some_and(|c| c.is_ascii_alphanumeric());
    if ok {
        Ok(())
    } else {
        Err(SpecError::Name(name.to_string()))
    }
}

/// Why a scan stopped short.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error(transparent)]
    Turntable(#[from] TurntableError),
    #[error("stopping the table: {0}")]
    Halt(TurntableError),
    #[error("turntable did not turn {total_deg}° within {allowed_s:.0} s at {speed_deg_s} °/s: it is at {at_deg:.2}°, started at {start_deg:.2}°")]
    TableShort { total_deg: f64, allowed_s: f64, speed_deg_s: f64, at_deg: f64, start_deg: f64 },
    /// A stage of the scan went away before the capture ended.
    #[error("the {0} stopped")]
    Stopped(&'static str),
    #[error("the {0} panicked")]
    Panicked(&'static str),
    #[error("cannot start the recording: {0}")]
    RecordingStart(RecordingError),
    #[error("recording seq {seq}: {source}")]
    Recording { seq: u64, source: RecordingError },
    #[error("first frame: {0}")]
    FirstFrame(FrameError),
    #[error("the background plate is {plate_w}×{plate_h} but the cameras deliver {w}×{h} (expected an image of the empty scene from the left camera at its resolution)")]
    PlateSize { plate_w: usize, plate_h: usize, w: u32, h: u32 },
    #[error("pipeline: {0}")]
    Pipeline(#[from] PipelineError),
    #[error("model: {0}")]
    Model(ResultsError),
    #[error(transparent)]
    Results(#[from] ResultsError),
}

/// Pipeline settings of every scan.
#[derive(Debug, Clone)]
pub struct PipelineSettings {
    pub pipeline: PipelineOptions,
    pub segment: bool,
    /// An image of the empty scene from the left camera (raw, RGB): pixels close to it are
    /// background too (`segment::ChromaKey`); for what the key leaves, such as a turntable
    /// not in the screen's colour.
    pub plate: Option<Arc<crate::io::LoadedImage>>,
    pub registration: Option<RegistrationParams>,
    pub assist: Option<AssistParams>,
    pub matcher_threads: usize,
    pub queue_depth: usize,
    /// Write the captured pairs as a recording (off only when the input already is one:
    /// the throughput benchmark).
    pub record: bool,
    /// Feed pairs no faster than this many per second (replays and the benchmark).
    pub pace_hz: Option<f64>,
    /// When registration is behind, register only the newest view (always so in continuous
    /// scans; step scans register every view unless this is set).
    pub register_newest_when_behind: bool,
    /// The calibrated turntable axis: registration uses it, and the recording keeps it as
    /// its `turntable.yaml` (so a replay does too).
    pub calibrated_axis: Option<crate::recording::TurntableAxis>,
}

impl PipelineSettings {
    /// The assistance the matchers use: `assist`, where registration gives them the motion
    /// (without it every frame is full range).
    pub fn assist_in_use(&self) -> Option<&AssistParams> {
        self.assist.as_ref().filter(|_| self.registration.is_some())
    }
}

/// Live counters of a scan, read by `status` and `scan.progress`.
#[derive(Debug, Default)]
pub struct Counters {
    pub captured: AtomicU64,
    pub recorded: AtomicU64,
    pub matched: AtomicU64,
    pub registered: AtomicU64,
    /// Pairs the matcher pool never saw (continuous mode, pool behind).
    pub dropped: AtomicU64,
    /// Views kept without registration (continuous scans when registration is behind).
    pub register_skipped: AtomicU64,
    /// Pairs whose matching failed (bad frame); recorded all the same.
    pub failed: AtomicU64,
    /// Time of the last capture or view, ms since the scan started (the watchdog's pulse).
    pub pulse_ms: AtomicU64,
    /// Time the last view was matched, µs since the scan started.
    pub matched_us: AtomicU64,
    /// Time of the last capture, µs since the scan started (capture rate = captured / it).
    pub capture_us: AtomicU64,
    /// The newest registered view: its seq + 1 (0: none yet) and its turn from the first
    /// view, degrees (f64 bits).
    pub pose_seq: AtomicU64,
    pub pose_deg_bits: AtomicU64,
    /// Table angle of the last captured pair, f64 bits.
    pub table_deg_bits: AtomicU64,
    /// Sum and max of registration lag (capture → the view's pose published), µs.
    pub lag_sum_us: AtomicU64,
    pub lag_max_us: AtomicU64,
    /// Pairs waiting for the matchers, and for the recorder.
    pub queued: AtomicU64,
    pub recorder_backlog: AtomicU64,
    /// Unpaired frames (free-running cameras).
    pub unpaired: AtomicU64,
    pub max_skew_us: AtomicU64,
    /// Registered views left out of the live preview (its thread was behind).
    pub live_fusion_skipped: AtomicU64,
    /// Per [`Stage`]: the time spent in it so far, µs, and the views that went through it.
    pub stage_us: [AtomicU64; Stage::ALL.len()],
    pub stage_views: [AtomicU64; Stage::ALL.len()],
}

/// Where a view's time goes in the live pipeline (`scan.progress`'s `stage_ms`): the
/// matchers' stages, then the registration thread's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Decoding, rectifying and segmenting the pair.
    Prepare,
    /// The assistant's plan (the search intervals) and its check of the result.
    Assist,
    /// The matcher calls (a full-range redo included).
    Match,
    /// Disparities to points.
    Triangulate,
    /// The view's files and its entry in the scan's folder.
    Write,
    /// Registering the view (views registered only).
    Register,
}

impl Stage {
    pub const ALL: [Stage; 6] = [Stage::Prepare, Stage::Assist, Stage::Match, Stage::Triangulate, Stage::Write, Stage::Register];

    pub fn name(self) -> &'static str {
        match self {
            Stage::Prepare => "prepare",
            Stage::Assist => "assist",
            Stage::Match => "match",
            Stage::Triangulate => "triangulate",
            Stage::Write => "write",
            Stage::Register => "register",
        }
    }
}

/// Milliseconds since `t0`.
pub(super) fn ms_since(t0: Instant) -> f64 {
    t0.elapsed().as_secs_f64() * 1e3
}

impl Counters {
    /// Counts `ms` of one view's time in `stage`.
    pub(super) fn add_stage(&self, stage: Stage, ms: f64) {
        let i = stage as usize;
        self.stage_us[i].fetch_add((ms * 1e3).round() as u64, Ordering::Relaxed);
        self.stage_views[i].fetch_add(1, Ordering::Relaxed);
    }
}

/// A scan's shared state: its counters, its stop flag and the event sink.
pub struct ScanShared {
    pub spec: ScanSpec,
    pub dir: PathBuf,
    pub started: Instant,
    pub counters: Counters,
    stop: Mutex<Option<String>>,
    stop_flag: Arc<AtomicBool>,
    mesh_request: AtomicBool,
    events: Box<dyn Fn(&str, Value) + Send + Sync>,
}

impl ScanShared {
    pub fn new(spec: ScanSpec, dir: PathBuf, events: Box<dyn Fn(&str, Value) + Send + Sync>) -> ScanShared {
        ScanShared { spec, dir, started: Instant::now(), counters: Counters::default(), stop: Mutex::new(None), stop_flag: Arc::new(AtomicBool::new(false)), mesh_request: AtomicBool::new(false), events }
    }

    /// Asks the scan to stop after the current view; `why` goes into the manifest.
    pub fn request_stop(&self, why: &str) {
        let mut s = self.stop.lock().unwrap();
        if s.is_none() {
            *s = Some(why.to_string());
        }
        self.stop_flag.store(true, Ordering::SeqCst);
    }

    /// Asks for a mesh of the views fused so far (`mesh_live.ply`, announced by a
    /// `scan.mesh` event).
    pub fn request_mesh(&self) {
        self.mesh_request.store(true, Ordering::SeqCst);
    }

    /// Whether a mesh was asked for since the last call.
    pub(super) fn take_mesh_request(&self) -> bool {
        self.mesh_request.swap(false, Ordering::SeqCst)
    }

    /// The stop flag itself, for device waits that must end when a stop is asked for.
    pub fn stop_signal(&self) -> Arc<AtomicBool> {
        self.stop_flag.clone()
    }

    pub fn stop_requested(&self) -> bool {
        self.stop_flag.load(Ordering::SeqCst)
    }

    pub(super) fn stop_reason(&self) -> Option<String> {
        self.stop.lock().unwrap().clone()
    }

    pub(super) fn pulse(&self) {
        self.counters.pulse_ms.store(self.started.elapsed().as_millis() as u64, Ordering::Relaxed);
    }

    /// Seconds since the pipeline last moved.
    pub fn idle_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64() - self.counters.pulse_ms.load(Ordering::Relaxed) as f64 / 1e3
    }

    pub fn emit(&self, method: &str, params: Value) {
        (self.events)(method, params)
    }

    /// `scan.progress` / `status` view of the counters.
    pub fn progress(&self) -> Value {
        let c = &self.counters;
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        let elapsed = self.started.elapsed().as_secs_f64();
        let registered = get(&c.registered);
        json!({
            "name": self.spec.name,
            "mode": self.spec.mode.name(),
            "views": get(&c.matched),
            "registered": registered,
            "register_skipped": get(&c.register_skipped),
            "live_fusion_skipped": get(&c.live_fusion_skipped),
            "captured": get(&c.captured),
            "recorded": get(&c.recorded),
            "drops": get(&c.dropped),
            "failed": get(&c.failed),
            "unpaired": get(&c.unpaired),
            "max_skew_ms": get(&c.max_skew_us) as f64 / 1e3,
            "queued": get(&c.queued),
            "recorder_backlog": get(&c.recorder_backlog),
            // Capture rate over the capture so far (pairs after the first per second).
            "fps": match (get(&c.captured), get(&c.capture_us)) {
                (n, us) if n > 1 && us > 0 => (n - 1) as f64 / (us as f64 / 1e6),
                _ => 0.0,
            },
            "table_deg": f64::from_bits(get(&c.table_deg_bits)),
            // The newest registered view and how far the object has turned since the first
            // (by the table's angles where the pairs have them, else the registered steps).
            "pose": match get(&c.pose_seq) {
                0 => Value::Null,
                n => json!({"seq": n - 1, "turned_deg": f64::from_bits(get(&c.pose_deg_bits))}),
            },
            "registration_lag_ms": {"mean": if registered > 0 { get(&c.lag_sum_us) as f64 / registered as f64 / 1e3 } else { 0.0 }, "max": get(&c.lag_max_us) as f64 / 1e3},
            "elapsed_s": elapsed,
            "matched_at_s": get(&c.matched_us) as f64 / 1e6,
            // Mean time per view of each stage, ms (null before a view went through it).
            "stage_ms": Stage::ALL.iter().map(|&st| {
                let (us, n) = (get(&c.stage_us[st as usize]), get(&c.stage_views[st as usize]));
                (st.name().to_string(), if n > 0 { json!(us as f64 / n as f64 / 1e3) } else { Value::Null })
            }).collect::<serde_json::Map<_, _>>(),
        })
    }
}

/// How a scan ended.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanEnd {
    /// `complete`, `interrupted` or `failed`.
    pub status: &'static str,
    pub reason: Option<String>,
}

impl ScanEnd {
    pub fn failed(e: ScanError) -> ScanEnd {
        ScanEnd { status: "failed", reason: Some(e.to_string()) }
    }
}

/// The devices a scan uses; handed back when it ends.
pub struct Devices {
    pub source: Box<dyn StereoSource>,
    pub turntable: Option<Box<dyn Turntable>>,
}

/// A pair on its way to a matcher.
pub(super) struct Job {
    pub(super) frame: StereoFrame,
    pub(super) captured: Instant,
}

/// What the registration thread hears, in any order but `Announce`, which comes in `seq`
/// order from the capture task.
pub(super) enum Note {
    Announce(u64),
    View { frame_meta: StereoFrame, view: Box<View>, captured: Instant },
    Skipped { seq: u64, why: String },
}

/// Sets the calling thread's nice value to `by` above the process's (its main thread's, e.g.
/// systemd's `Nice=`). Linux keeps nice per thread and a new thread inherits its creator's,
/// so this is absolute, not cumulative: a pool started from a lowered thread that lowers its
/// workers again lands at the same value.
pub(super) fn lower_priority(by: i32) {
    // SAFETY: getpid, gettid, getpriority and setpriority have no memory preconditions.
    unsafe {
        let base = libc::getpriority(libc::PRIO_PROCESS, libc::getpid() as libc::id_t);
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, (base + by).min(19));
    }
}

#[cfg(test)]
mod tests {
    /// Nice steps are counted from the process's value, so lowering twice (a pool's worker
    /// started by a lowered thread) lands where lowering once does.
    #[test]
    fn lowering_a_thread_twice_lands_where_once_does() {
        // SAFETY (both): getpriority, getpid and gettid have no memory preconditions.
        let nice_of_this_thread = || unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::syscall(libc::SYS_gettid) as libc::id_t) };
        let base = unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::getpid() as libc::id_t) };
        let got = std::thread::spawn(move || {
            super::lower_priority(3);
            std::thread::spawn(move || {
                super::lower_priority(3);
                nice_of_this_thread()
            })
            .join()
            .unwrap()
        })
        .join()
        .unwrap();
        assert_eq!(got, (base + 3).min(19));
    }

    use super::*;

    #[test]
    fn names_cannot_escape_the_state_folder() {
        for good in ["bunny", "vase-2026.11.22", "a_1"] {
            assert!(validate_name(good).is_ok(), "{good}");
        }
        for bad in ["", "..", ".", "../etc", "a/b", "-rf", ".hidden", "a b", &"x".repeat(65)] {
            assert!(validate_name(bad).is_err(), "{bad:?}");
        }
    }
}
