//! One scan through the live pipeline: capture (with the turntable) → recorder and the
//! bounded matcher channel → matcher pool → registration thread → the scan's folder.
//!
//! ```text
//!  capture task ──every pair──> recorder thread ─> DIR/frames.jsonl, left/, right/
//!   (blocking,      │
//!    turntable)     └─bounded channel (queue_depth)─> matcher-0..N ─views─> register ─> DIR/views/,
//!                     full: step mode waits,              ▲ reads           │   disparity/, poses.jsonl,
//!                     continuous drops the oldest         └── PoseStore <───┘   report.json, model.ply
//! ```
//!
//! Every captured pair is recorded, whatever the matchers manage, so a scan always replays.
//! The registration thread takes views in `seq` order (a reorder buffer; the capture task
//! announces every `seq`, and a dropped or failed pair is skipped explicitly), so poses and
//! the report are the same whatever order the pool finishes in. Each matcher keeps its own
//! [`Assistant`], fed by the frames it matched and the shared [`PoseStore`]; with N
//! matchers it plans from views up to N frames back (the lag the assistant is built for).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TrySendError};
use serde_json::{json, Value};

use crate::assist::{AssistParams, Assistant};
use crate::capture::{StereoFrame, StereoSource};
use crate::pipeline::{Pipeline, PipelineOptions, View};
use crate::recording::RecordingWriter;
use crate::register::posestore::PoseStore;
use crate::register::ring::{Registrar, RegistrationParams};
use crate::replay::{ReplayOptions, ResultsWriter};
use crate::turntable::Turntable;

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

impl ScanSpec {
    /// Views of a step scan: a full turn (or more) does not capture its start twice; a
    /// partial arc includes both ends.
    pub fn step_views(&self) -> usize {
        let n = (self.total_deg / self.step_deg + 1e-9).floor() as usize;
        let n = if self.total_deg < 360.0 - 1e-9 { n + 1 } else { n };
        n.max(1).min(self.max_views.unwrap_or(usize::MAX))
    }
}

/// Pipeline settings of every scan.
#[derive(Debug, Clone)]
pub struct PipelineSettings {
    pub pipeline: PipelineOptions,
    pub segment: bool,
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
    /// Sum and max of registration lag (capture → registered), µs.
    pub lag_sum_us: AtomicU64,
    pub lag_max_us: AtomicU64,
    /// Pairs waiting for the matchers, and for the recorder.
    pub queued: AtomicU64,
    pub recorder_backlog: AtomicU64,
    /// Unpaired frames (free-running cameras).
    pub unpaired: AtomicU64,
    pub max_skew_us: AtomicU64,
}

/// A scan's shared state: its counters, its stop flag and the event sink.
pub struct ScanShared {
    pub spec: ScanSpec,
    pub dir: PathBuf,
    pub started: Instant,
    pub counters: Counters,
    stop: Mutex<Option<String>>,
    stop_flag: AtomicBool,
    events: Box<dyn Fn(&str, Value) + Send + Sync>,
}

impl ScanShared {
    pub fn new(spec: ScanSpec, dir: PathBuf, events: Box<dyn Fn(&str, Value) + Send + Sync>) -> ScanShared {
        ScanShared { spec, dir, started: Instant::now(), counters: Counters::default(), stop: Mutex::new(None), stop_flag: AtomicBool::new(false), events }
    }

    /// Asks the scan to stop after the current view; `why` goes into the manifest.
    pub fn request_stop(&self, why: &str) {
        let mut s = self.stop.lock().unwrap();
        if s.is_none() {
            *s = Some(why.to_string());
        }
        self.stop_flag.store(true, Ordering::SeqCst);
    }

    pub fn stop_requested(&self) -> bool {
        self.stop_flag.load(Ordering::SeqCst)
    }

    fn stop_reason(&self) -> Option<String> {
        self.stop.lock().unwrap().clone()
    }

    fn pulse(&self) {
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

/// The devices a scan uses; handed back when it ends.
pub struct Devices {
    pub source: Box<dyn StereoSource>,
    pub turntable: Option<Box<dyn Turntable>>,
}

/// A pair on its way to a matcher.
struct Job {
    frame: StereoFrame,
    captured: Instant,
}

/// What the registration thread hears, in any order but `Announce`, which comes in `seq`
/// order from the capture task.
enum Note {
    Announce(u64),
    View { frame_meta: StereoFrame, view: Box<View>, captured: Instant },
    Skipped { seq: u64, why: String },
}

/// Runs one scan to its end on the calling thread (a blocking task): spawns the recorder,
/// the matcher pool and the registration thread, captures, and waits for them. The scan's
/// folder always ends with a `manifest.json` that says how it ended, even when the scan
/// failed before its first view.
pub fn run(devices: &mut Devices, shared: Arc<ScanShared>, settings: &PipelineSettings) -> ScanEnd {
    let end = run_scan(devices, shared.clone(), settings);
    let path = shared.dir.join("manifest.json");
    if !path.exists() {
        let spec = &shared.spec;
        let m = json!({
            "format": 1, "status": end.status, "reason": end.reason, "frames": 0,
            "name": spec.name, "mode": spec.mode.name(), "total_deg": spec.total_deg,
            "source": devices.source.describe(), "written_by": format!("spinscan {}", env!("CARGO_PKG_VERSION")),
        });
        if let Err(e) = crate::io::write_atomic(&path, serde_json::to_string_pretty(&m).unwrap().as_bytes()) {
            tracing::error!("cannot write {}: {e}", path.display());
        }
    }
    end
}

fn run_scan(devices: &mut Devices, shared: Arc<ScanShared>, settings: &PipelineSettings) -> ScanEnd {
    let calib = devices.source.calibration().clone();
    let spec = shared.spec.clone();
    let dir = shared.dir.clone();
    // The first pair fixes the image size the pipeline is built for.
    let first = match capture_first(devices, &shared) {
        Ok(Some(f)) => f,
        Ok(None) => return ScanEnd { status: "failed", reason: Some("the source delivered no frame".into()) },
        Err(e) => return ScanEnd { status: "failed", reason: Some(e) },
    };
    let size = match first.left.to_rgb() {
        Ok((w, h, _)) => (w as u32, h as u32),
        Err(e) => return ScanEnd { status: "failed", reason: Some(format!("first frame: {e}")) },
    };

    // Recorder.
    let (rec_tx, rec_rx) = crossbeam_channel::unbounded::<StereoFrame>();
    let recorder = if settings.record {
        let mut writer = match RecordingWriter::create(&dir, &calib) {
            Ok(w) => w,
            Err(e) => return ScanEnd { status: "failed", reason: Some(format!("cannot start the recording: {e}")) },
        };
        let sh = shared.clone();
        Some(
            std::thread::Builder::new()
                .name("recorder".into())
                .spawn(move || -> Result<(), String> {
                    for frame in rec_rx {
                        sh.counters.recorder_backlog.fetch_sub(1, Ordering::Relaxed);
                        writer.append(&frame).map_err(|e| format!("recording seq {}: {e}", frame.seq))?;
                        sh.counters.recorded.fetch_add(1, Ordering::Relaxed);
                    }
                    Ok(())
                })
                .expect("spawn the recorder"),
        )
    } else {
        drop(rec_rx);
        None
    };

    let sign = match Pipeline::new(&calib, size, settings.pipeline.clone()) {
        Ok(p) => p.rect.disparity_sign,
        Err(e) => return ScanEnd { status: "failed", reason: Some(format!("pipeline: {e}")) },
    };
    let results = match ResultsWriter::create(&dir, &devices.source.describe(), sign) {
        Ok(mut r) => {
            r.manifest_extra.insert("name".into(), json!(spec.name));
            r.manifest_extra.insert("mode".into(), json!(spec.mode.name()));
            r.manifest_extra.insert("step_deg".into(), json!((spec.mode == ScanMode::Step).then_some(spec.step_deg)));
            r.manifest_extra.insert("total_deg".into(), json!(spec.total_deg));
            r
        }
        Err(e) => return ScanEnd { status: "failed", reason: Some(e.to_string()) },
    };

    // Matcher pool and registration.
    let threads = if settings.matcher_threads == 0 { std::thread::available_parallelism().map_or(2, |n| n.get()) } else { settings.matcher_threads };
    let (job_tx, job_rx) = crossbeam_channel::bounded::<Job>(settings.queue_depth);
    // Announcements and drops come from the capture task, which must not wait: unbounded
    // (small). Views come from the matchers: bounded, so a registration thread that falls
    // behind holds the matchers back instead of piling views up in memory.
    let (note_tx, note_rx) = crossbeam_channel::unbounded::<Note>();
    let (view_tx, view_rx) = crossbeam_channel::bounded::<Note>(VIEW_BACKLOG);
    let store = Arc::new(PoseStore::new());
    let mut observe_txs = Vec::new();
    let mut matchers = Vec::new();
    for i in 0..threads {
        let pipe = match Pipeline::new(&calib, size, settings.pipeline.clone()) {
            Ok(p) => p,
            Err(e) => return ScanEnd { status: "failed", reason: Some(format!("pipeline: {e}")) },
        };
        let (obs_tx, obs_rx) = crossbeam_channel::unbounded::<(u64, f64, f64)>();
        observe_txs.push(obs_tx);
        let (jobs, notes, store, sh, s) = (job_rx.clone(), view_tx.clone(), store.clone(), shared.clone(), settings.clone());
        matchers.push(std::thread::Builder::new().name(format!("matcher-{i}")).spawn(move || matcher_loop(pipe, jobs, notes, obs_rx, store, sh, s)).expect("spawn a matcher"));
    }
    let registrar = {
        let (sh, s, store) = (shared.clone(), settings.clone(), store.clone());
        std::thread::Builder::new().name("register".into()).spawn(move || register_loop(results, note_rx, view_rx, observe_txs, store, sh, s)).expect("spawn the registration thread")
    };

    // Capture, on this thread.
    let captured = capture(devices, &shared, first, &job_tx, &job_rx, &note_tx, &rec_tx, settings);
    drop((job_tx, job_rx, note_tx, view_tx, rec_tx));
    for m in matchers {
        let _ = m.join();
    }
    let (results, reg_result) = match registrar.join() {
        Ok((r, outcome)) => (Some(r), outcome),
        Err(_) => (None, Err("the registration thread panicked".to_string())),
    };
    let rec_result = recorder.map(|r| r.join().unwrap_or_else(|_| Err("the recorder panicked".into()))).unwrap_or(Ok(()));
    let (status, reason) = match (captured, rec_result, reg_result) {
        (Err(e), _, _) | (_, Err(e), _) | (_, _, Err(e)) => ("failed", Some(e)),
        (Ok(()), Ok(()), Ok(())) => match shared.stop_reason() {
            Some(why) => ("interrupted", Some(why)),
            None => ("complete", None),
        },
    };
    let written = match results {
        Some(r) => r.finish_as(status, reason.as_deref()),
        // Nothing of the results survived: the manifest still tells.
        None => ResultsWriter::create(&dir, &devices.source.describe(), sign).and_then(|r| r.finish_as(status, reason.as_deref())),
    };
    match written {
        Ok(()) => ScanEnd { status, reason },
        Err(e) => ScanEnd { status: "failed", reason: Some(format!("{}{e}", reason.map(|r| format!("{r}; then ")).unwrap_or_default())) },
    }
}

/// Moves to the start (step mode) and takes the first pair.
fn capture_first(devices: &mut Devices, shared: &ScanShared) -> Result<Option<StereoFrame>, String> {
    if shared.spec.mode == ScanMode::Step {
        if let Some(t) = devices.turntable.as_mut() {
            let start = t.angle().map_err(|e| e.to_string())?;
            shared.counters.table_deg_bits.store(start.to_bits(), Ordering::Relaxed);
            let mut f = devices.source.fresh_frame().map_err(|e| e.to_string())?;
            if let Some(f) = f.as_mut() {
                f.table_deg.get_or_insert(start);
            }
            return Ok(f);
        }
    }
    devices.source.next_frame().map_err(|e| e.to_string())
}

#[allow(clippy::too_many_arguments)]
fn capture(
    devices: &mut Devices,
    shared: &ScanShared,
    first: StereoFrame,
    jobs: &Sender<Job>,
    jobs_rx: &Receiver<Job>,
    notes: &Sender<Note>,
    recorder: &Sender<StereoFrame>,
    settings: &PipelineSettings,
) -> Result<(), String> {
    let spec = &shared.spec;
    let c = &shared.counters;
    let t0 = Instant::now();
    let mut sent = 0usize;
    let mut last_seq: Option<u64> = None;
    let mut first_at = Instant::now();
    let mut deliver = |mut frame: StereoFrame, pairing: Option<crate::daemon::v4l2::PairStats>| -> Result<(), String> {
        if last_seq.is_some_and(|p| frame.seq <= p) {
            // A source restarted its numbering: keep seq strictly increasing.
            frame.seq = last_seq.unwrap() + 1;
        }
        last_seq = Some(frame.seq);
        if let Some(deg) = frame.table_deg {
            c.table_deg_bits.store(deg.to_bits(), Ordering::Relaxed);
        }
        if let Some(p) = pairing {
            c.unpaired.store(p.unpaired_left + p.unpaired_right, Ordering::Relaxed);
            c.max_skew_us.store(p.max_abs_skew_ns / 1000, Ordering::Relaxed);
        } else {
            let skew = (frame.t_right_ns as i64 - frame.t_left_ns as i64).unsigned_abs() / 1000;
            c.max_skew_us.fetch_max(skew, Ordering::Relaxed);
        }
        if c.captured.fetch_add(1, Ordering::Relaxed) == 0 {
            first_at = Instant::now();
        }
        c.capture_us.store(first_at.elapsed().as_micros() as u64, Ordering::Relaxed);
        shared.pulse();
        if settings.record {
            c.recorder_backlog.fetch_add(1, Ordering::Relaxed);
            recorder.send(frame.clone()).map_err(|_| "the recorder stopped".to_string())?;
        }
        let seq = frame.seq;
        notes.send(Note::Announce(seq)).map_err(|_| "the registration thread stopped".to_string())?;
        let mut job = Job { frame, captured: Instant::now() };
        match spec.mode {
            ScanMode::Step => {
                c.queued.fetch_add(1, Ordering::Relaxed);
                jobs.send(job).map_err(|_| "the matcher pool stopped".to_string())?;
            }
            ScanMode::Continuous => loop {
                match jobs.try_send(job) {
                    Ok(()) => {
                        c.queued.fetch_add(1, Ordering::Relaxed);
                        break;
                    }
                    Err(TrySendError::Full(j)) => {
                        job = j;
                        // Capture never waits: the oldest waiting pair makes room.
                        if let Ok(old) = jobs_rx.try_recv() {
                            c.queued.fetch_sub(1, Ordering::Relaxed);
                            c.dropped.fetch_add(1, Ordering::Relaxed);
                            let _ = notes.send(Note::Skipped { seq: old.frame.seq, why: "dropped: the matcher pool was behind".into() });
                        }
                    }
                    Err(TrySendError::Disconnected(_)) => return Err("the matcher pool stopped".into()),
                }
            },
        }
        sent += 1;
        if let Some(hz) = settings.pace_hz {
            let due = t0 + Duration::from_secs_f64(sent as f64 / hz);
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        Ok(())
    };

    let start_deg = first.table_deg;
    deliver(first, devices.source.pairing())?;
    let limit = spec.max_views.unwrap_or(usize::MAX);
    match (spec.mode, devices.turntable.is_some()) {
        (ScanMode::Step, true) => {
            let start = start_deg.unwrap_or(0.0);
            for i in 1..spec.step_views() {
                if shared.stop_requested() {
                    break;
                }
                let target = start + i as f64 * spec.step_deg;
                let table = devices.turntable.as_mut().unwrap();
                table.move_to(target).map_err(|e| e.to_string())?;
                let mut frame = match devices.source.fresh_frame().map_err(|e| e.to_string())? {
                    Some(f) => f,
                    None => break,
                };
                frame.table_deg.get_or_insert(target);
                deliver(frame, devices.source.pairing())?;
            }
        }
        (ScanMode::Continuous, true) => {
            let table = devices.turntable.as_mut().unwrap();
            let start = table.angle().map_err(|e| e.to_string())?;
            let end = start + spec.total_deg;
            table.start_move(end, spec.speed_deg_s).map_err(|e| e.to_string())?;
            // A table that stops short (stalled, unplugged mid-move) must not keep a scan
            // capturing forever.
            let allowed = Duration::from_secs_f64(spec.total_deg / spec.speed_deg_s * 1.5 + 10.0);
            let deadline = Instant::now() + allowed;
            let (mut last_t_ns, mut frame_period_s) = (None::<u64>, 1.0 / 15.0);
            let outcome = (|| -> Result<(), String> {
                let mut n = 1;
                while n < limit && !shared.stop_requested() {
                    let Some(mut frame) = devices.source.next_frame().map_err(|e| e.to_string())? else { break };
                    if let Some(prev) = last_t_ns.replace(frame.t_left_ns) {
                        if frame.t_left_ns > prev {
                            frame_period_s = (frame.t_left_ns - prev) as f64 / 1e9;
                        }
                    }
                    let table = devices.turntable.as_mut().unwrap();
                    let deg = match frame.table_deg {
                        Some(d) => d,
                        None => {
                            let d = table.angle().map_err(|e| e.to_string())?;
                            frame.table_deg = Some(d);
                            d
                        }
                    };
                    if Instant::now() > deadline {
                        return Err(format!("turntable did not turn {}° within {:.0} s at {} °/s: it is at {deg:.2}°, started at {start:.2}°", spec.total_deg, allowed.as_secs_f64(), spec.speed_deg_s));
                    }
                    // A full turn's last pair would repeat the first view.
                    // Within half a pair's turn of the end (the cameras' rate from the pairs'
                    // timestamps; 15 fps until two are known).
                    let half_step = 0.5 * spec.speed_deg_s * frame_period_s;
                    let done = deg >= end - 1e-6 || (spec.total_deg >= 360.0 && deg >= end - half_step);
                    if done && spec.total_deg >= 360.0 {
                        break;
                    }
                    deliver(frame, devices.source.pairing())?;
                    n += 1;
                    if done {
                        break;
                    }
                }
                Ok(())
            })();
            // Stop the table whatever happened (it may be mid-move after a stop request).
            let halted = devices.turntable.as_mut().unwrap().halt();
            outcome?;
            halted.map_err(|e| format!("stopping the table: {e}"))?;
        }
        (_, false) => {
            // No turntable (a replay): every pair of the source.
            let mut n = 1;
            while n < limit && !shared.stop_requested() {
                let Some(frame) = devices.source.next_frame().map_err(|e| e.to_string())? else { break };
                deliver(frame, devices.source.pairing())?;
                n += 1;
            }
        }
    }
    Ok(())
}

fn matcher_loop(mut pipe: Pipeline, jobs: Receiver<Job>, notes: Sender<Note>, observed: Receiver<(u64, f64, f64)>, store: Arc<PoseStore>, shared: Arc<ScanShared>, settings: PipelineSettings) {
    let mut assistant = match (&settings.assist, &settings.registration) {
        (Some(a), Some(_)) => {
            let p = pipe.matcher().params();
            Some(Assistant::new(a.clone(), &pipe.rect, (p.min_disparity, p.max_disparity())))
        }
        _ => None,
    };
    let c = &shared.counters;
    for job in jobs {
        c.queued.fetch_sub(1, Ordering::Relaxed);
        let seq = job.frame.seq;
        if let Some(a) = assistant.as_mut() {
            for (s, fitness, rmse) in observed.try_iter() {
                a.observe_registration(s, fitness, rmse);
            }
        }
        let view = (|| -> Result<View, String> {
            let (_, _, left) = job.frame.left.to_rgb().map_err(|e| format!("left image: {e}"))?;
            let (_, _, right) = job.frame.right.to_rgb().map_err(|e| format!("right image: {e}"))?;
            let (w, h) = pipe.rect.size;
            if left.len() != (w * h * 3) as usize || right.len() != left.len() {
                return Err(format!("image size changed during the scan (expected {w}×{h})"));
            }
            match assistant.as_mut() {
                Some(a) => {
                    let prepared = pipe.prepare_rgb(&left, &right, settings.segment, None).map_err(|e| e.to_string())?;
                    let m = pipe.match_assisted(seq, &prepared, a, &store.snapshot()).map_err(|e| e.to_string())?;
                    Ok(pipe.finish_view(prepared, m))
                }
                None => pipe.process_rgb(&left, &right, settings.segment).map_err(|e| e.to_string()),
            }
        })();
        let meta = StereoFrame { left: crate::capture::Picture::Jpeg { bytes: Vec::new() }, right: crate::capture::Picture::Jpeg { bytes: Vec::new() }, ..job.frame };
        let note = match view {
            Ok(view) => {
                c.matched.fetch_add(1, Ordering::Relaxed);
                c.matched_us.fetch_max(shared.started.elapsed().as_micros() as u64, Ordering::Relaxed);
                Note::View { frame_meta: meta, view: Box::new(view), captured: job.captured }
            }
            Err(why) => {
                c.failed.fetch_add(1, Ordering::Relaxed);
                tracing::warn!("frame seq {seq}: not matched: {why} (the pair is recorded)");
                Note::Skipped { seq, why }
            }
        };
        shared.pulse();
        if notes.send(note).is_err() {
            return;
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn register_loop(
    mut results: ResultsWriter,
    notes: Receiver<Note>,
    views: Receiver<Note>,
    observers: Vec<Sender<(u64, f64, f64)>>,
    store: Arc<PoseStore>,
    shared: Arc<ScanShared>,
    settings: PipelineSettings,
) -> (ResultsWriter, Result<(), String>) {
    // Registration yields the cores to the matchers: its thread and its own worker pool run
    // at a lower priority (nice +REGISTER_NICE), so a busy registration delays poses, not
    // views.
    lower_priority();
    let pool = rayon::ThreadPoolBuilder::new().thread_name(|i| format!("register-{i}")).start_handler(|_| lower_priority()).build();
    let outcome = match pool {
        Ok(pool) => pool.install(|| register_all(&mut results, notes, views, observers, store, &shared, &settings)),
        Err(_) => register_all(&mut results, notes, views, observers, store, &shared, &settings),
    };
    (results, outcome)
}

#[allow(clippy::too_many_arguments)]
fn register_all(
    results: &mut ResultsWriter,
    notes: Receiver<Note>,
    views: Receiver<Note>,
    observers: Vec<Sender<(u64, f64, f64)>>,
    store: Arc<PoseStore>,
    shared: &ScanShared,
    settings: &PipelineSettings,
) -> Result<(), String> {
    let mut registrar = settings.registration.clone().map(|p| Registrar::new(p, store));
    let mut expected = std::collections::VecDeque::new();
    let mut done: BTreeMap<u64, Note> = BTreeMap::new();
    let c = &shared.counters;
    let mut last_progress = Instant::now() - Duration::from_secs(1);
    let newest_only = shared.spec.mode == ScanMode::Continuous || settings.register_newest_when_behind;
    let mut process = |note: Note, results: &mut ResultsWriter, behind: bool| -> Result<(), String> {
        match note {
            Note::View { frame_meta, view, captured } => {
                let mut entry = results.write_view(&frame_meta, &view, settings.assist.as_ref()).map_err(|e| e.to_string())?;
                if registrar.is_some() && newest_only && behind {
                    // A continuous scan sees the object at 15 fps: when newer views wait,
                    // this one is kept (views/, disparity/) but only the newest is registered.
                    entry["registered"] = json!(false);
                    entry["register_skipped"] = json!("newer views were waiting (registration is behind; the newest view is registered)");
                    c.register_skipped.fetch_add(1, Ordering::Relaxed);
                } else if let Some(reg) = registrar.as_mut() {
                    if let Some((fitness, rmse)) = crate::replay::register_view(reg, &frame_meta, &view.cloud, &mut entry) {
                        for o in &observers {
                            let _ = o.send((frame_meta.seq, fitness, rmse));
                        }
                    }
                    results.write_poses(reg.poses()).map_err(|e| e.to_string())?;
                    if let Some(p) = reg.poses().last() {
                        c.pose_deg_bits.store(reg.turned_deg().to_bits(), Ordering::Relaxed);
                        c.pose_seq.store(p.seq + 1, Ordering::Relaxed);
                    }
                }
                if entry.get("registered").is_none() {
                    let lag = captured.elapsed().as_micros() as u64;
                    entry["registration_lag_ms"] = json!(lag as f64 / 1e3);
                    c.lag_sum_us.fetch_add(lag, Ordering::Relaxed);
                    c.lag_max_us.fetch_max(lag, Ordering::Relaxed);
                    c.registered.fetch_add(1, Ordering::Relaxed);
                }
                results.push_frame(entry).map_err(|e| e.to_string())?;
            }
            Note::Skipped { seq, why } => results.note_skipped(seq, &why),
            Note::Announce(_) => unreachable!("announcements are not queued"),
        }
        shared.pulse();
        if last_progress.elapsed() >= Duration::from_millis(200) {
            last_progress = Instant::now();
            shared.emit("scan.progress", shared.progress());
        }
        Ok(())
    };
    let (mut notes_open, mut views_open) = (true, true);
    while notes_open || views_open {
        let note = crossbeam_channel::select! {
            recv(if notes_open { Some(&notes) } else { None }.unwrap_or(&crossbeam_channel::never())) -> n => match n {
                Ok(n) => n,
                Err(_) => { notes_open = false; continue; }
            },
            recv(if views_open { Some(&views) } else { None }.unwrap_or(&crossbeam_channel::never())) -> n => match n {
                Ok(n) => n,
                Err(_) => { views_open = false; continue; }
            },
        };
        let seq = match &note {
            Note::Announce(seq) => {
                expected.push_back(*seq);
                continue;
            }
            Note::View { frame_meta, .. } => frame_meta.seq,
            Note::Skipped { seq, .. } => *seq,
        };
        done.insert(seq, note);
        while let Some(next) = expected.front() {
            let Some(note) = done.remove(next) else { break };
            expected.pop_front();
            // Behind: a newer view is finished already, or waits in the channel.
            let behind = done.values().any(|n| matches!(n, Note::View { .. })) || !views.is_empty();
            process(note, results, behind)?;
        }
    }
    // Whatever is left (announced pairs whose matcher never reported: a panic) is skipped.
    for seq in expected {
        match done.remove(&seq) {
            Some(note) => process(note, results, false)?,
            None => results.note_skipped(seq, "never matched"),
        }
    }
    shared.emit("scan.progress", shared.progress());
    if let Some(reg) = registrar.as_mut() {
        let opts = ReplayOptions { registration: settings.registration.clone(), model_voxel_mm: 1.0, denoise: Some(Default::default()), ..Default::default() };
        if reg.poses().len() >= 2 {
            crate::replay::finish_registration(reg, results, &opts, &Default::default()).map_err(|e| format!("model: {e}"))?;
        }
    }
    Ok(())
}

/// Finished views waiting for the registration thread before the matchers wait (a view is
/// about 4 MB at 640×480).
const VIEW_BACKLOG: usize = 4;

/// Nice value of the registration threads (matchers and capture stay at the process's).
const REGISTER_NICE: i32 = 5;

/// Lowers the calling thread's priority (Linux: nice applies per thread).
fn lower_priority() {
    // SAFETY: gettid and setpriority have no memory preconditions.
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        let now = libc::getpriority(libc::PRIO_PROCESS, tid);
        libc::setpriority(libc::PRIO_PROCESS, tid, (now + REGISTER_NICE).min(19));
    }
}

/// The folder of scan `name` in `state_dir`.
pub fn scan_dir(state_dir: &Path, name: &str) -> PathBuf {
    state_dir.join(name)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::StereoCalib;
    use crate::capture::CaptureError;

    /// A camera that never delivers.
    struct Dead(StereoCalib);

    impl StereoSource for Dead {
        fn describe(&self) -> String {
            "dead camera".into()
        }
        fn calibration(&self) -> &StereoCalib {
            &self.0
        }
        fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
            Err(CaptureError::NoFrame { camera: "left".into(), waited_ms: 1000 })
        }
    }

    #[test]
    fn a_scan_that_fails_before_its_first_view_still_leaves_a_manifest() {
        let dir = std::env::temp_dir().join(format!("spinscan-scan-dead-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let calib = crate::sim::calib_of(&hw_sim::Rig::ideal(64, 48, 70.0, 60.0));
        let mut devices = Devices { source: Box::new(Dead(calib)), turntable: None };
        let spec = ScanSpec { name: "dead".into(), mode: ScanMode::Continuous, step_deg: 1.0, total_deg: 360.0, speed_deg_s: 6.0, max_views: None };
        let shared = Arc::new(ScanShared::new(spec, dir.clone(), Box::new(|_, _| {})));
        let config = crate::daemon::config::Config::sim();
        let end = run(&mut devices, shared, &crate::daemon::pipeline_settings(&config));
        assert_eq!(end.status, "failed");
        assert!(end.reason.as_deref().unwrap().contains("left camera delivered no frame"), "{end:?}");
        let m: Value = serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap();
        assert_eq!((m["status"].as_str(), m["frames"].as_u64(), m["name"].as_str()), (Some("failed"), Some(0), Some("dead")));
        assert!(m["reason"].as_str().unwrap().contains("left camera"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn step_views_cover_a_turn_once_and_an_arc_with_both_ends() {
        let spec = |step: f64, total: f64| ScanSpec { name: "x".into(), mode: ScanMode::Step, step_deg: step, total_deg: total, speed_deg_s: 6.0, max_views: None };
        assert_eq!(spec(2.0, 360.0).step_views(), 180);
        assert_eq!(spec(45.0, 360.0).step_views(), 8);
        assert_eq!(spec(30.0, 90.0).step_views(), 4);
        assert_eq!(spec(7.0, 360.0).step_views(), 51);
        assert_eq!(ScanSpec { max_views: Some(5), ..spec(2.0, 360.0) }.step_views(), 5);
    }
}
