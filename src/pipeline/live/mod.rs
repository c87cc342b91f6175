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
//! [`crate::assist::Assistant`], fed by the frames it matched and the shared [`PoseStore`]; with N
//! matchers it plans from views up to N frames back (the lag the assistant is built for).

mod capture;
mod fusion;
mod pool;
mod register;
mod state;

pub use state::{check_step_deg, check_total_deg, validate_name, Counters, Devices, PipelineSettings, ScanEnd, ScanError, ScanMode, ScanShared, ScanSpec, SpecError, Stage, MAX_MATCHER_THREADS, MAX_QUEUE_DEPTH, MIN_STEP_DEG};

use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;

use serde_json::json;

use super::results::ResultsWriter;
use super::Pipeline;
use crate::hw::StereoFrame;
use crate::recording::RecordingWriter;
use crate::register::posestore::PoseStore;
use register::VIEW_BACKLOG;
use state::{Job, Note};

/// Runs one scan to its end on the calling thread (a blocking task): spawns the recorder,
/// the matcher pool and the registration thread, captures, and waits for them. The scan's
/// folder always ends with a `manifest.json` that says how it ended, even when the scan
/// failed before its first view.
pub fn run(devices: &mut Devices, shared: Arc<ScanShared>, settings: &PipelineSettings) -> ScanEnd {
    let end = run_scan(devices, shared.clone(), settings);
    let path = shared.dir.join("manifest.json");
    // Missing, or still saying `running` (the scan failed before its results were set up):
    // the manifest tells how the scan ended.
    let still_running = std::fs::read_to_string(&path).ok().and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok()).is_none_or(|m| m["status"] == "running");
    if still_running {
        let mut m = shared.spec.manifest(end.status, end.reason.as_deref());
        m["source"] = json!(devices.source.describe());
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
    let first = match capture::capture_first(devices, &shared) {
        Ok(Some(f)) => f,
        Ok(None) => return ScanEnd { status: "failed", reason: Some("the source delivered no frame".into()) },
        Err(e) => return ScanEnd::failed(e),
    };
    let size = match first.left.to_rgb() {
        Ok((w, h, _)) => (w as u32, h as u32),
        Err(source) => return ScanEnd::failed(ScanError::FirstFrame(crate::pipeline::FrameError::Decode { side: "left", source })),
    };
    if let Some(p) = settings.plate.as_ref().filter(|p| (p.width as u32, p.height as u32) != size) {
        return ScanEnd::failed(ScanError::PlateSize { plate_w: p.width, plate_h: p.height, w: size.0, h: size.1 });
    }

    // Recorder.
    let (rec_tx, rec_rx) = crossbeam_channel::unbounded::<StereoFrame>();
    let recorder = if settings.record {
        let mut writer = match RecordingWriter::create(&dir, &calib) {
            Ok(w) => w,
            Err(e) => return ScanEnd::failed(ScanError::RecordingStart(e)),
        };
        if let Some(axis) = &settings.calibrated_axis {
            if let Err(e) = writer.write_turntable(axis, false) {
                return ScanEnd::failed(ScanError::RecordingStart(e));
            }
        }
        let sh = shared.clone();
        Some(
            std::thread::Builder::new()
                .name("recorder".into())
                .spawn(move || -> Result<(), ScanError> {
                    // Bulk work that catches up (its queue holds every pair): it yields the
                    // cores to capture and the control socket, as the matchers do.
                    state::lower_priority(pool::MATCHER_NICE);
                    for frame in rec_rx {
                        sh.counters.recorder_backlog.fetch_sub(1, Ordering::Relaxed);
                        writer.append(&frame).map_err(|source| ScanError::Recording { seq: frame.seq, source })?;
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

    let mut settings = settings.clone();
    let (sign, matching) = match fitted_pipeline(&calib, size, &first, &mut settings) {
        Ok(f) => {
            // The registration thread tracks texture in the rectified left images.
            if let Some(r) = settings.registration.as_mut() {
                r.track_camera = crate::pipeline::track_camera(&f.pipe.rect);
            }
            (f.pipe.rect.disparity_sign, super::results::matching_entry(&f.pipe, settings.assist_in_use(), f.range.as_ref(), f.contrast.as_ref()))
        }
        Err(e) => return ScanEnd::failed(e),
    };
    let results = match ResultsWriter::create(&dir, &devices.source.describe(), sign) {
        Ok(mut r) => {
            r.manifest_extra.insert("name".into(), json!(spec.name));
            r.manifest_extra.insert("mode".into(), json!(spec.mode.name()));
            r.manifest_extra.insert("step_deg".into(), json!((spec.mode == ScanMode::Step).then_some(spec.step_deg)));
            r.manifest_extra.insert("total_deg".into(), json!(spec.total_deg));
            r.set_matching(matching);
            r
        }
        Err(e) => return ScanEnd::failed(ScanError::Results(e)),
    };

    // Matcher pool and registration.
    let threads = if settings.matcher_threads == 0 { std::thread::available_parallelism().map_or(2, |n| n.get()) } else { settings.matcher_threads }.min(MAX_MATCHER_THREADS);
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
            Err(e) => return ScanEnd::failed(ScanError::Pipeline(e)),
        };
        let (obs_tx, obs_rx) = crossbeam_channel::unbounded::<(u64, f64, f64)>();
        observe_txs.push(obs_tx);
        let (jobs, notes, store, sh, s) = (job_rx.clone(), view_tx.clone(), store.clone(), shared.clone(), settings.clone());
        matchers.push(std::thread::Builder::new().name(format!("matcher-{i}")).spawn(move || pool::matcher_loop(pipe, jobs, notes, obs_rx, store, sh, s)).expect("spawn a matcher"));
    }
    let registrar = {
        let (sh, s, store) = (shared.clone(), settings.clone(), store.clone());
        std::thread::Builder::new().name("register".into()).spawn(move || register::register_loop(results, note_rx, view_rx, observe_txs, store, sh, s)).expect("spawn the registration thread")
    };

    // Capture, on this thread.
    let captured = capture::capture(devices, &shared, first, &job_tx, &job_rx, &note_tx, &rec_tx, &settings);
    drop((job_tx, job_rx, note_tx, view_tx, rec_tx));
    for m in matchers {
        let _ = m.join();
    }
    let (results, reg_result) = match registrar.join() {
        Ok((r, outcome)) => (Some(r), outcome),
        Err(_) => (None, Err(ScanError::Panicked("registration thread"))),
    };
    let rec_result = recorder.map(|r| r.join().unwrap_or(Err(ScanError::Panicked("recorder")))).unwrap_or(Ok(()));
    let (status, reason) = match first_error(captured, rec_result, reg_result) {
        Some(e) => ("failed", Some(e.to_string())),
        None => match shared.stop_reason() {
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
        Err(e) => {
            let end = ScanEnd { status: "failed", reason: Some(format!("{}{e}", reason.map(|r| format!("{r}; then ")).unwrap_or_default())) };
            // The results could not be finished (a full disk): the manifest must not stay
            // `running`. A small rewrite in place reuses the file's own blocks.
            write_manifest_in_place(&dir.join("manifest.json"), &end);
            end
        }
    }
}

/// A scan's first pipeline, fitted to its first frame (`pipeline::range`): the range to the
/// object where the settings ask, the right images' contrast to the left's where the
/// cameras differ; `settings` then carry what the matchers are built with.
fn fitted_pipeline(calib: &crate::calib::StereoCalib, size: (u32, u32), first: &StereoFrame, settings: &mut PipelineSettings) -> Result<crate::pipeline::range::Fitted, ScanError> {
    let pipe = Pipeline::new(calib, size, settings.pipeline.clone())?;
    let plate = settings.plate.as_ref().map(|p| pipe.rectify_plate(&p.rgb));
    let fitted = crate::pipeline::range::fit(pipe, calib, first, settings.segment, plate.as_ref(), &settings.pipeline).map_err(ScanError::FirstFrame)?;
    settings.pipeline = fitted.opts.clone();
    Ok(fitted)
}

/// The error that caused the others: a stage that stopped because another failed ("the
/// recorder stopped") gives way to that stage's own error (the disk that filled up).
fn first_error(captured: Result<(), ScanError>, recorded: Result<(), ScanError>, registered: Result<(), ScanError>) -> Option<ScanError> {
    let errors: Vec<ScanError> = [captured, recorded, registered].into_iter().filter_map(Result::err).collect();
    let cause = errors.iter().position(|e| !matches!(e, ScanError::Stopped(_))).unwrap_or(0);
    errors.into_iter().nth(cause)
}

/// `{"status": "failed", "reason": …}` merged into the manifest, rewritten in place: no
/// temporary file (there may be no room for one), and not truncated first (a file system
/// may not hand freed blocks back at once), so the new text goes into the blocks the file
/// already holds — a manifest is far smaller than one block.
fn write_manifest_in_place(path: &Path, end: &ScanEnd) {
    use std::io::Write;
    let mut m: serde_json::Value = std::fs::read_to_string(path).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_else(|| json!({"format": 1}));
    m["status"] = json!(end.status);
    m["reason"] = json!(end.reason);
    let text = m.to_string();
    let overwrite = || -> std::io::Result<()> {
        let mut f = std::fs::OpenOptions::new().write(true).open(path)?;
        f.write_all(text.as_bytes())?;
        f.set_len(text.len() as u64)?;
        f.sync_data()
    };
    if let Err(e) = overwrite().or_else(|_| std::fs::write(path, &text)) {
        tracing::error!("cannot mark {} {}: {e}", path.display(), end.status);
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
    use crate::hw::{CaptureError, StereoSource};
    use serde_json::Value;

    /// The settings these tests start from: segmented, recorded, one matcher, nothing else.
    fn test_settings() -> PipelineSettings {
        PipelineSettings {
            pipeline: crate::pipeline::PipelineOptions::default(),
            segment: true,
            plate: None,
            registration: None,
            assist: None,
            matcher_threads: 1,
            queue_depth: 4,
            record: true,
            pace_hz: None,
            register_newest_when_behind: false,
            calibrated_axis: None,
        }
    }

    /// An empty scan folder of this test run.
    fn empty_scan_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("spinscan-scan-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

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
        let dir = empty_scan_dir("dead");
        let calib = crate::hw::sim::ideal_calib(64, 48, 70.0, 60.0);
        let mut devices = Devices { source: Box::new(Dead(calib)), turntable: None };
        let spec = ScanSpec { name: "dead".into(), mode: ScanMode::Continuous, step_deg: 1.0, total_deg: 360.0, speed_deg_s: 6.0, max_views: None };
        let shared = Arc::new(ScanShared::new(spec, dir.clone(), Box::new(|_, _| {})));
        let settings = PipelineSettings { registration: Some(Default::default()), ..test_settings() };
        let end = run(&mut devices, shared, &settings);
        assert_eq!(end.status, "failed");
        assert!(end.reason.as_deref().unwrap().contains("left camera delivered no frame"), "{end:?}");
        let m: Value = serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap();
        assert_eq!((m["status"].as_str(), m["frames"].as_u64(), m["name"].as_str()), (Some("failed"), Some(0), Some("dead")));
        assert!(m["reason"].as_str().unwrap().contains("left camera"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Free-running cameras that have been streaming since the daemon started: frames wait
    /// in their queue until a fresh one is asked for.
    struct Streaming {
        calib: StereoCalib,
        waiting: std::collections::VecDeque<u64>,
        next_seq: u64,
    }

    impl StereoSource for Streaming {
        fn describe(&self) -> String {
            "streaming cameras".into()
        }
        fn calibration(&self) -> &StereoCalib {
            &self.calib
        }
        fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
            let seq = self.waiting.pop_front().unwrap_or_else(|| {
                self.next_seq += 1;
                self.next_seq
            });
            let pic = || crate::hw::Picture::Raw { width: 1, height: 1, channels: 1, data: vec![0] };
            Ok(Some(StereoFrame { seq, t_left_ns: seq, t_right_ns: seq, table_deg: None, left: pic(), right: pic() }))
        }
        fn fresh_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
            self.waiting.clear();
            self.next_frame()
        }
    }

    /// Defect 3: a continuous scan's first view is a pair captured after the scan started,
    /// not one that waited in the cameras' queue since the daemon started.
    #[test]
    fn a_continuous_scan_starts_with_a_fresh_pair() {
        let calib = crate::hw::sim::ideal_calib(64, 48, 70.0, 60.0);
        let mut devices = Devices { source: Box::new(Streaming { calib, waiting: (0..10).collect(), next_seq: 100 }), turntable: None };
        let spec = ScanSpec { name: "fresh".into(), mode: ScanMode::Continuous, step_deg: 1.0, total_deg: 360.0, speed_deg_s: 6.0, max_views: None };
        let shared = ScanShared::new(spec, std::env::temp_dir(), Box::new(|_, _| {}));
        let first = capture::capture_first(&mut devices, &shared).unwrap().unwrap();
        assert_eq!(first.seq, 101, "a pair from after the scan started");
    }

    /// A background plate of another size than the cameras' images stops the scan before
    /// anything is written, naming both sizes.
    #[test]
    fn a_plate_of_another_size_stops_the_scan_and_says_why() {
        let dir = empty_scan_dir("plate");
        let calib = crate::hw::sim::ideal_calib(64, 48, 70.0, 60.0);
        let mut devices = Devices { source: Box::new(Streaming { calib, waiting: Default::default(), next_seq: 0 }), turntable: None };
        let spec = ScanSpec { name: "plate".into(), mode: ScanMode::Continuous, step_deg: 1.0, total_deg: 360.0, speed_deg_s: 6.0, max_views: None };
        let shared = Arc::new(ScanShared::new(spec, dir.clone(), Box::new(|_, _| {})));
        let plate = crate::io::LoadedImage { width: 2, height: 2, rgb: vec![0; 12], gray: vec![0; 4] };
        let settings = PipelineSettings { plate: Some(Arc::new(plate)), ..test_settings() };
        let end = run(&mut devices, shared, &settings);
        assert_eq!(end.status, "failed");
        assert!(end.reason.as_deref().unwrap().contains("background plate is 2×2 but the cameras deliver 1×1"), "{end:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A table turning at 10° per second of the monotonic clock, queried late.
    struct Turning;

    impl crate::hw::Turntable for Turning {
        fn move_to(&mut self, table_deg: f64) -> Result<f64, crate::hw::TurntableError> {
            Ok(table_deg)
        }
        fn angle(&mut self) -> Result<f64, crate::hw::TurntableError> {
            Ok(-1.0) // "now": long after the exposure
        }
        fn angle_at(&mut self, t_ns: u64) -> Result<f64, crate::hw::TurntableError> {
            Ok(t_ns as f64 * 1e-8)
        }
        fn start_move(&mut self, _: f64, _: f64) -> Result<(), crate::hw::TurntableError> {
            Ok(())
        }
        fn halt(&mut self) -> Result<(), crate::hw::TurntableError> {
            Ok(())
        }
        fn describe(&self) -> String {
            "turning".into()
        }
    }

    /// Risk 10: a pair without an angle of its own gets the table's angle at its exposure,
    /// not at the moment it was dequeued.
    #[test]
    fn a_pair_gets_the_angle_at_its_exposure() {
        let calib = crate::hw::sim::ideal_calib(64, 48, 70.0, 60.0);
        let mut devices = Devices { source: Box::new(Streaming { calib, waiting: Default::default(), next_seq: 300_000_000 }), turntable: Some(Box::new(Turning)) };
        let spec = ScanSpec { name: "t".into(), mode: ScanMode::Continuous, step_deg: 1.0, total_deg: 360.0, speed_deg_s: 6.0, max_views: None };
        let shared = ScanShared::new(spec, std::env::temp_dir(), Box::new(|_, _| {}));
        let first = capture::capture_first(&mut devices, &shared).unwrap().unwrap();
        assert_eq!(first.table_deg, Some(first.t_left_ns as f64 * 1e-8));
    }

    /// A stepper that stops on whole steps of 1/8.889° and counts how often its motor was
    /// switched off.
    struct Stepper(Arc<std::sync::atomic::AtomicUsize>);

    impl crate::hw::Turntable for Stepper {
        fn move_to(&mut self, table_deg: f64) -> Result<f64, crate::hw::TurntableError> {
            Ok((table_deg * 8.889).round() / 8.889)
        }
        fn angle(&mut self) -> Result<f64, crate::hw::TurntableError> {
            Ok(0.0)
        }
        fn start_move(&mut self, _: f64, _: f64) -> Result<(), crate::hw::TurntableError> {
            Ok(())
        }
        fn halt(&mut self) -> Result<(), crate::hw::TurntableError> {
            Ok(())
        }
        fn release(&mut self) -> Result<(), crate::hw::TurntableError> {
            self.0.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            Ok(())
        }
        fn describe(&self) -> String {
            "stepper".into()
        }
    }

    /// Defect 6 and risk 11: a step frame records the angle the table arrived at (whole
    /// steps), not the one requested; the motor is switched off when the scan ends.
    #[test]
    fn step_frames_carry_the_angle_read_back_and_the_motor_is_released() {
        let calib = crate::hw::sim::ideal_calib(64, 48, 70.0, 60.0);
        let released = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let mut devices = Devices { source: Box::new(Streaming { calib, waiting: Default::default(), next_seq: 0 }), turntable: Some(Box::new(Stepper(released.clone()))) };
        let spec = ScanSpec { name: "steps".into(), mode: ScanMode::Step, step_deg: 45.0, total_deg: 90.0, speed_deg_s: 6.0, max_views: None };
        let shared = ScanShared::new(spec, std::env::temp_dir(), Box::new(|_, _| {}));
        let first = capture::capture_first(&mut devices, &shared).unwrap().unwrap();
        let (jobs, jobs_rx) = crossbeam_channel::unbounded();
        let (notes, _notes_rx) = crossbeam_channel::unbounded();
        let (recorder, _rec_rx) = crossbeam_channel::unbounded();
        let settings = PipelineSettings { segment: false, queue_depth: 8, record: false, ..test_settings() };
        capture::capture(&mut devices, &shared, first, &jobs, &jobs_rx, &notes, &recorder, &settings).unwrap();
        let angles: Vec<Option<f64>> = jobs_rx.try_iter().map(|j| j.frame.table_deg).collect();
        assert_eq!(angles, vec![Some(0.0), Some(400.0 / 8.889), Some(800.0 / 8.889)]);
        assert_eq!(released.load(std::sync::atomic::Ordering::SeqCst), 1);
    }

    /// Hardening (issue 17), 5: the disk that filled up is the reason, not "the recorder
    /// stopped" that the capture saw as a consequence.
    #[test]
    fn the_cause_is_the_reason_not_its_consequence() {
        let disk = || ScanError::Recording { seq: 7, source: crate::recording::RecordingError::Exists(PathBuf::from("/full/disk")) };
        let e = first_error(Err(ScanError::Stopped("recorder")), Err(disk()), Ok(())).unwrap();
        assert!(matches!(e, ScanError::Recording { seq: 7, .. }), "{e}");
        let e = first_error(Err(ScanError::Stopped("matcher pool")), Ok(()), Ok(())).unwrap();
        assert!(matches!(e, ScanError::Stopped(_)));
        assert!(first_error(Ok(()), Ok(()), Ok(())).is_none());
    }

    /// A scan whose results cannot be finished leaves a manifest that says `failed`.
    #[test]
    fn an_unfinished_manifest_is_marked_failed_in_place() {
        let dir = std::env::temp_dir().join(format!("spinscan-inplace-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("manifest.json");
        std::fs::write(&path, r#"{"format": 1, "status": "running", "frames": 12}"#).unwrap();
        write_manifest_in_place(&path, &ScanEnd { status: "failed", reason: Some("no space left on device".into()) });
        let m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!((m["status"].as_str(), m["frames"].as_u64(), m["reason"].as_str()), (Some("failed"), Some(12), Some("no space left on device")));
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
