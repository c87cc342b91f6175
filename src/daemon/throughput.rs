//! `spinscan bench live`: a recording fed into the live pipeline (the daemon's own
//! [`scan::run`]: bounded channel, matcher pool, registration thread), paced like cameras,
//! and unpaced to find the most pairs per second it sustains.
//!
//! The pairs are decoded into memory first, so the feed costs nothing and what is measured
//! is the pipeline. Paced runs use continuous mode (a full queue drops the oldest pair, as
//! with real cameras; registration takes the newest view when behind). The unpaced runs use
//! step mode (the feed waits for the pool, nothing is dropped): once registering every view
//! (a step scan's policy), once registering the newest view when behind (a continuous
//! scan's), so their rates are what the pipeline sustains without dropping under each.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use serde_json::{json, Value};

use crate::pipeline::live::{self as scan, Devices, PipelineSettings, ScanMode, ScanShared, ScanSpec, Stage};
use crate::calib::StereoCalib;
use crate::hw::{CaptureError, Picture, StereoFrame, StereoSource};

/// Pairs held in memory, delivered in order, `repeat` times over with growing `seq`.
struct MemorySource {
    calib: StereoCalib,
    frames: Vec<StereoFrame>,
    next: usize,
    limit: usize,
}

impl StereoSource for MemorySource {
    fn describe(&self) -> String {
        "recording in memory (bench live)".into()
    }

    fn calibration(&self) -> &StereoCalib {
        &self.calib
    }

    fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
        if self.next >= self.limit {
            return Ok(None);
        }
        let mut f = self.frames[self.next % self.frames.len()].clone();
        f.seq = self.next as u64;
        self.next += 1;
        Ok(Some(f))
    }
}

/// One run's figures.
#[derive(Debug, Clone)]
pub struct LiveRun {
    pub label: String,
    pub pace_hz: Option<f64>,
    pub fed: u64,
    pub matched: u64,
    pub registered: u64,
    pub drops: u64,
    pub wall_s: f64,
    /// From the start to the last view matched (the wall time adds the model at the end).
    pub matching_s: f64,
    pub lag_mean_ms: f64,
    pub lag_max_ms: f64,
    pub max_rss_mib: f64,
    /// Mean time per view of each stage of the pipeline, ms, in [`Stage::ALL`]'s order (None:
    /// no view went through it).
    pub stage_ms: Vec<(Stage, Option<f64>)>,
    pub status: String,
}

impl LiveRun {
    pub fn to_json(&self) -> Value {
        json!({
            "label": self.label, "pace_hz": self.pace_hz, "fed": self.fed, "matched": self.matched,
            "registered": self.registered, "drops": self.drops, "wall_s": self.wall_s,
            "matching_s": self.matching_s,
            "matched_per_s": self.matched as f64 / self.matching_s.max(1e-9),
            "registration_lag_ms": {"mean": self.lag_mean_ms, "max": self.lag_max_ms},
            "max_rss_mib": self.max_rss_mib, "status": self.status,
            "stage_ms": self.stage_ms.iter().map(|(st, ms)| (st.name().to_string(), json!(ms))).collect::<serde_json::Map<_, _>>(),
        })
    }
}

/// Options of `bench live`.
#[derive(Debug, Clone)]
pub struct LiveOptions {
    pub settings: PipelineSettings,
    /// Pairs fed per run (the recording is cycled when shorter).
    pub pairs: usize,
    /// Paced rates to run, pairs per second.
    pub paces: Vec<f64>,
    /// Also run unpaced (step mode, no drops) for the sustained maximum.
    pub unpaced: bool,
}

/// Why `bench live` could not run.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error(transparent)]
    Recording(#[from] crate::recording::RecordingError),
    #[error("frame seq {seq}: {source}")]
    Decode { seq: u64, source: crate::hw::DecodeError },
    #[error("{0} holds no frame")]
    Empty(std::path::PathBuf),
    #[error("cannot create {path}: {source}")]
    Create { path: std::path::PathBuf, source: std::io::Error },
}

/// Runs the recording at each pace and unpaced; results of each run go to a temporary
/// folder under `work` (removed after).
pub fn live(recording: &Path, opts: &LiveOptions, work: &Path, progress: &mut dyn FnMut(&str)) -> Result<Vec<LiveRun>, LiveError> {
    let rec = crate::recording::Recording::open(recording)?;
    progress(&format!("decoding {} pairs", rec.frames.len()));
    let mut frames = Vec::new();
    for i in 0..rec.frames.len() {
        let mut f = rec.load_frame(i)?;
        let seq = f.seq;
        // Decode once: the pipeline then sees raw frames, like YUYV cameras.
        for p in [&mut f.left, &mut f.right] {
            if let Picture::Jpeg { .. } = p {
                let (w, h, rgb) = p.to_rgb().map_err(|source| LiveError::Decode { seq, source })?;
                *p = Picture::Raw { width: w, height: h, channels: 3, data: rgb };
            }
        }
        frames.push(f);
    }
    if frames.is_empty() {
        return Err(LiveError::Empty(recording.to_path_buf()));
    }
    let mut runs = Vec::new();
    let mut plan: Vec<(String, Option<f64>, bool)> = opts.paces.iter().map(|p| (format!("paced {p} pairs/s"), Some(*p), true)).collect();
    if opts.unpaced {
        plan.push(("unpaced, register all".into(), None, false));
        plan.push(("unpaced, reg. newest".into(), None, true));
    }
    for (i, (label, pace, newest)) in plan.into_iter().enumerate() {
        progress(&label);
        let dir = work.join(format!("run-{i}"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).map_err(|source| LiveError::Create { path: dir.clone(), source })?;
        let mut devices = Devices { source: Box::new(MemorySource { calib: rec.calib.clone(), frames: frames.clone(), next: 0, limit: opts.pairs }), turntable: None };
        let spec = ScanSpec { name: format!("bench-{i}"), mode: if pace.is_some() { ScanMode::Continuous } else { ScanMode::Step }, step_deg: 1.0, total_deg: 360.0, speed_deg_s: 1.0, max_views: None };
        let shared = Arc::new(ScanShared::new(spec, dir.clone(), Box::new(|_, _| {})));
        let settings = PipelineSettings { pace_hz: pace, record: false, register_newest_when_behind: newest, ..opts.settings.clone() };
        // Sample RSS while it runs.
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let sampler = {
            let stop = stop.clone();
            std::thread::spawn(move || {
                let mut max = 0f64;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    max = max.max(super::rss_mib().unwrap_or(0.0));
                    std::thread::sleep(std::time::Duration::from_millis(50));
                }
                max
            })
        };
        let t0 = Instant::now();
        let end = scan::run(&mut devices, shared.clone(), &settings);
        let wall_s = t0.elapsed().as_secs_f64();
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        let max_rss_mib = sampler.join().unwrap_or(0.0);
        let p = shared.progress();
        let get = |k: &str| p[k].as_u64().unwrap_or(0);
        runs.push(LiveRun {
            label,
            pace_hz: pace,
            fed: get("captured"),
            matched: get("views"),
            registered: get("registered"),
            drops: get("drops"),
            wall_s,
            matching_s: p["matched_at_s"].as_f64().unwrap_or(wall_s),
            lag_mean_ms: p["registration_lag_ms"]["mean"].as_f64().unwrap_or(0.0),
            lag_max_ms: p["registration_lag_ms"]["max"].as_f64().unwrap_or(0.0),
            max_rss_mib,
            stage_ms: Stage::ALL.iter().map(|&st| (st, p["stage_ms"][st.name()].as_f64())).collect(),
            status: match end.reason {
                Some(r) => format!("{}: {r}", end.status),
                None => end.status.to_string(),
            },
        });
        let _ = std::fs::remove_dir_all(&dir);
    }
    Ok(runs)
}

/// The tables `bench live` prints: the runs, then where a view's time went in each.
pub fn render(runs: &[LiveRun]) -> String {
    let mut s = format!("{:<22} {:>6} {:>8} {:>11} {:>6} {:>8} {:>8} {:>10} {:>14} {:>9}  {}\n", "run", "fed", "matched", "registered", "drops", "match s", "wall s", "matched/s", "reg lag ms", "RSS MiB", "status");
    for r in runs {
        s.push_str(&format!(
            "{:<22} {:>6} {:>8} {:>11} {:>6} {:>8.2} {:>8.2} {:>10.2} {:>6.0} / {:>5.0} {:>9.0}  {}\n",
            r.label,
            r.fed,
            r.matched,
            r.registered,
            r.drops,
            r.matching_s,
            r.wall_s,
            r.matched as f64 / r.matching_s.max(1e-9),
            r.lag_mean_ms,
            r.lag_max_ms,
            r.max_rss_mib,
            r.status
        ));
    }
    s.push_str("\nper view, ms (mean of each stage's views; the matchers' stages, then the registration thread's)\n");
    s.push_str(&format!("{:<22}", "run"));
    for st in Stage::ALL {
        s.push_str(&format!(" {:>11}", st.name()));
    }
    s.push_str("  match share\n");
    for r in runs {
        s.push_str(&format!("{:<22}", r.label));
        for (_, ms) in &r.stage_ms {
            s.push_str(&match ms {
                Some(ms) => format!(" {ms:>11.2}"),
                None => format!(" {:>11}", "–"),
            });
        }
        // The matcher calls' share of the time a view costs: its own stages and writing it
        // (registration runs for some views only, on its own thread).
        let get = |st: Stage| r.stage_ms.iter().find(|(s, _)| *s == st).and_then(|(_, ms)| *ms).unwrap_or(0.0);
        let per_view: f64 = [Stage::Prepare, Stage::Assist, Stage::Match, Stage::Triangulate, Stage::Write].into_iter().map(get).sum();
        s.push_str(&format!("  {:>10.0} %\n", 100.0 * get(Stage::Match) / per_view.max(1e-9)));
    }
    s
}
