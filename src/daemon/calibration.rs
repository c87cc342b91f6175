//! Calibration captured by the daemon (`calib.capture`): pairs are taken from the cameras
//! and kept only when the board is found in both images (and, held by hand, has moved since
//! the last pair kept); the turntable kind steps the table through a sweep itself. The pairs
//! are recorded, the rig or the axis solved, and everything written under
//! `<state_dir>/calibrations/<name>/`:
//!
//! ```text
//! pairs/            the kept pairs, a recording (calib.yaml: the calibration in use then)
//! calib.yaml        stereo: the new calibration (OpenCV FileStorage, with rms_*)
//! turntable.yaml    turntable: the axis (replay reads it; [cameras] turntable_axis for scans)
//! report.json       every pair with its figures or the reason it was left out, warnings
//! manifest.json     kind, status (running, complete, failed, interrupted), reason, figures
//! ```

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::calib::board::{BoardSize, DetectParams};
use crate::calib::job::{self, FoundPair, StereoJob};
use crate::calib::solve::{board_points, LensModel, TargetView, MIN_VIEWS};
use crate::calib::turntable::{fit_axis, TablePair};
use crate::hw::{Picture, StereoFrame, TargetScene};
use crate::pipeline::live::Devices;
use crate::recording::{RecordingWriter, TurntableAxis};
use crate::stereo::GrayView;

/// The folder under the state folder that holds calibrations (not a scan name).
pub const CALIBRATIONS: &str = "calibrations";

/// Why a calibration capture could not start, or ended without a result.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    #[error(transparent)]
    Board(#[from] crate::calib::board::BoardSizeError),
    #[error("{0}")]
    Name(#[from] crate::pipeline::live::SpecError),
    #[error("`{key}` must be {expected}, got {got}")]
    Param { key: &'static str, expected: String, got: String },
    #[error("pair {seq}: {source}")]
    Decode { seq: u64, source: crate::hw::DecodeError },
    #[error("pair {seq}: its images differ in size")]
    Size { seq: u64 },
    #[error("cameras: {0}")]
    Cameras(#[from] crate::hw::CaptureError),
    #[error("turntable: {0}")]
    Turntable(#[from] crate::hw::TurntableError),
    #[error("this backend has no turntable to turn the board with")]
    NoTurntable,
    #[error("cannot record the pairs: {0}")]
    Record(#[from] crate::recording::RecordingError),
    #[error("boards found in {found} of {seen} pairs (needs at least {needed}){}", .last.as_ref().map(|r| format!("; the last pair rejected: {r}")).unwrap_or_default())]
    TooFew { found: usize, seen: usize, needed: usize, last: Option<String> },
    #[error(transparent)]
    Solve(#[from] crate::calib::solve::SolveError),
    #[error(transparent)]
    Axis(#[from] crate::calib::turntable::AxisError),
    #[error("cannot write {path}: {source}")]
    Write { path: PathBuf, source: std::io::Error },
}

/// `calib.capture`'s parameters, checked.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaptureSpec {
    pub name: String,
    /// `stereo` or `turntable`.
    pub kind: String,
    pub count: usize,
    pub board: String,
    pub square_mm: f64,
    pub model: u32,
    /// Turntable: the table turns from −sweep to +sweep degrees.
    pub sweep_deg: f64,
    /// Stereo: give up after this many pairs seen without reaching `count`.
    pub max_pairs: usize,
}

impl CaptureSpec {
    /// The board size, parsed.
    pub fn board_size(&self) -> Result<BoardSize, CaptureError> {
        Ok(self.board.parse()?)
    }

    /// Checks every field; the error names it and what it takes.
    pub fn validate(&self) -> Result<(), CaptureError> {
        crate::pipeline::live::validate_name(&self.name)?;
        self.board_size()?;
        let bad = |key: &'static str, expected: String, got: String| Err(CaptureError::Param { key, expected, got });
        if !matches!(self.kind.as_str(), "stereo" | "turntable") {
            return bad("kind", "\"stereo\" or \"turntable\"".into(), format!("{:?}", self.kind));
        }
        if !(self.square_mm.is_finite() && self.square_mm > 0.0 && self.square_mm < 1000.0) {
            return bad("square_mm", "the printed square's side in mm (0 … 1000)".into(), self.square_mm.to_string());
        }
        let least = if self.kind == "stereo" { MIN_VIEWS } else { 3 };
        if !(least..=500).contains(&self.count) {
            return bad("count", format!("{least} … 500 pairs"), self.count.to_string());
        }
        if LensModel::from_count(self.model).is_none() {
            return bad("model", "5, 8 or 14 coefficients".into(), self.model.to_string());
        }
        if !(self.sweep_deg.is_finite() && (10.0..=170.0).contains(&self.sweep_deg)) {
            return bad("sweep_deg", "10 … 170 degrees".into(), self.sweep_deg.to_string());
        }
        if self.max_pairs < self.count {
            return bad("max_pairs", format!("at least `count` ({})", self.count), self.max_pairs.to_string());
        }
        Ok(())
    }
}

/// A running capture: its spec, folder, progress and stop flag.
pub struct CaptureShared {
    pub spec: CaptureSpec,
    pub dir: PathBuf,
    stop: AtomicBool,
    progress: Mutex<Value>,
    emit: Box<dyn Fn(&str, Value) + Send + Sync>,
}

impl CaptureShared {
    pub fn new(spec: CaptureSpec, dir: PathBuf, emit: Box<dyn Fn(&str, Value) + Send + Sync>) -> CaptureShared {
        let progress = json!({"name": spec.name, "kind": spec.kind, "count": spec.count, "kept": 0, "seen": 0});
        CaptureShared { spec, dir, stop: AtomicBool::new(false), progress: Mutex::new(progress), emit }
    }

    pub fn progress(&self) -> Value {
        self.progress.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Ends the capture after the pair it is on; what was kept is still solved.
    pub fn request_stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }

    fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    fn update(&self, kept: usize, seen: usize, last: Option<&str>, extra: Value) {
        let mut p = self.progress.lock().unwrap_or_else(|e| e.into_inner());
        p["kept"] = json!(kept);
        p["seen"] = json!(seen);
        p["last_rejection"] = json!(last);
        if let Value::Object(m) = extra {
            for (k, v) in m {
                p[k] = v;
            }
        }
        let snapshot = p.clone();
        drop(p);
        (self.emit)("calib.progress", snapshot);
    }
}

/// How a capture ended: status, reason, and the figures of what it solved.
#[derive(Debug, Clone)]
pub struct CaptureEnd {
    pub status: &'static str,
    pub reason: Option<String>,
    pub result: Value,
    /// A camera or the turntable failed: the daemon reopens the devices before next use.
    pub device_failed: bool,
}

fn gray(seq: u64, p: &Picture) -> Result<(usize, usize, Vec<u8>), CaptureError> {
    let (w, h, rgb) = p.to_rgb().map_err(|source| CaptureError::Decode { seq, source })?;
    Ok((w, h, crate::io::rgb_to_gray(&rgb)))
}

/// The mean distance the board's corners moved between two sightings, pixels.
fn moved(a: &[[f64; 2]], b: &[[f64; 2]]) -> f64 {
    a.iter().zip(b).map(|(p, q)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()).sum::<f64>() / a.len().max(1) as f64
}

/// Runs the capture on `devices` to its end (the devices are the daemon's for its duration).
pub fn run(devices: &mut Devices, shared: &CaptureShared) -> CaptureEnd {
    let spec = &shared.spec;
    let failed = |e: CaptureError| CaptureEnd {
        device_failed: matches!(e, CaptureError::Cameras(_) | CaptureError::Turntable(_)),
        status: "failed",
        reason: Some(e.to_string()),
        result: Value::Null,
    };
    let board = match spec.board_size() {
        Ok(b) => b,
        Err(e) => return failed(e),
    };
    let model = LensModel::from_count(spec.model).unwrap_or(LensModel::Five);
    let job = StereoJob { board, square_mm: spec.square_mm, model, detect: DetectParams::default() };
    let calib = devices.source.calibration().clone();
    let mut writer = match RecordingWriter::create(&shared.dir.join("pairs"), &calib) {
        Ok(w) => w,
        Err(e) => return failed(e.into()),
    };
    let on_table = spec.kind == "turntable";
    let simulated = devices.source.show_target(Some(TargetScene { cols: board.cols, rows: board.rows, square_mm: spec.square_mm, on_table }));
    if simulated {
        tracing::info!("simulated lab: a {board} board with {} mm squares is shown to the cameras", spec.square_mm);
    }
    let end = capture(devices, shared, &job, &mut writer, on_table);
    devices.source.show_target(None);
    if on_table {
        if let Some(t) = devices.turntable.as_mut() {
            let _ = t.move_to(0.0);
            let _ = t.release();
        }
    }
    let (found, rejected, tables, size) = match end {
        Ok(v) => v,
        Err(e) => return failed(e),
    };
    let interrupted = shared.stopped();
    let status = if interrupted { "interrupted" } else { "complete" };
    let reason = interrupted.then(|| format!("stopped by calib.stop with {} of {} pairs kept", found.len(), spec.count));
    let solved = if on_table { solve_axis(shared, &job, &calib, &found, &tables) } else { solve_rig(shared, &job, size, &found, &rejected) };
    match solved {
        Ok(result) => CaptureEnd { status, reason, result, device_failed: false },
        Err(e) => failed(e),
    }
}

/// The pairs kept, those left out (turntable) with their reasons, the table angles of the
/// kept ones, and the image size.
type Captured = (Vec<FoundPair>, Vec<(String, String, String)>, Vec<f64>, (u32, u32));

fn capture(devices: &mut Devices, shared: &CaptureShared, job: &StereoJob, writer: &mut RecordingWriter, on_table: bool) -> Result<Captured, CaptureError> {
    let spec = &shared.spec;
    let (mut found, mut rejected, mut tables) = (Vec::new(), Vec::new(), Vec::new());
    let mut size = (0u32, 0u32);
    let mut seen = 0usize;
    let mut last_reason: Option<String> = None;
    let angles: Vec<f64> = (0..spec.count).map(|k| -spec.sweep_deg + 2.0 * spec.sweep_deg * k as f64 / (spec.count - 1).max(1) as f64).collect();
    if on_table && devices.turntable.is_none() {
        return Err(CaptureError::NoTurntable);
    }
    while found.len() < spec.count && !shared.stopped() {
        let table_deg = if on_table {
            let Some(&target) = angles.get(seen) else { break };
            let t = devices.turntable.as_mut().expect("checked above");
            Some(t.move_to(target)?)
        } else {
            if seen >= spec.max_pairs {
                break;
            }
            None
        };
        let frame = if on_table { devices.source.fresh_frame() } else { devices.source.next_frame() };
        let mut frame: StereoFrame = match frame? {
            Some(f) => f,
            None => break,
        };
        seen += 1;
        if table_deg.is_some() {
            frame.table_deg = table_deg;
        }
        let (names, pair) = match (gray(frame.seq, &frame.left), gray(frame.seq, &frame.right)) {
            (Ok(l), Ok(r)) if (l.0, l.1) == (r.0, r.1) => ((format!("left {}", frame.seq), format!("right {}", frame.seq)), (l, r)),
            (Ok(_), Ok(_)) => {
                last_reason = Some(CaptureError::Size { seq: frame.seq }.to_string());
                shared.update(found.len(), seen, last_reason.as_deref(), json!({}));
                continue;
            }
            (Err(e), _) | (_, Err(e)) => {
                last_reason = Some(e.to_string());
                shared.update(found.len(), seen, last_reason.as_deref(), json!({}));
                continue;
            }
        };
        let (l, r) = pair;
        let lv = GrayView::new(l.0, l.1, &l.2).expect("decoded to its size");
        let rv = GrayView::new(r.0, r.1, &r.2).expect("decoded to its size");
        match job::find_pair(job, &names.0, &lv, &names.1, &rv) {
            Ok(p) => {
                // Held by hand: keep a pair only once the board has moved (5 % of the image
                // width on average), so twenty pairs are twenty poses.
                let still = !on_table && found.last().is_some_and(|q: &FoundPair| moved(&q.left.points, &p.left.points) < 0.05 * l.0 as f64);
                if still {
                    last_reason = Some("the board has not moved since the last pair kept: hold it at a new pose".into());
                } else {
                    writer.append(&frame)?;
                    size = (l.0 as u32, l.1 as u32);
                    tables.push(frame.table_deg.unwrap_or(0.0));
                    found.push(p);
                    last_reason = None;
                }
            }
            Err(why) => {
                if on_table {
                    rejected.push((names.0, names.1, why.to_string()));
                }
                last_reason = Some(why.to_string());
            }
        }
        let (cl, cr) = job::coverage(&found, job.board, (l.0 as u32, l.1 as u32));
        shared.update(found.len(), seen, last_reason.as_deref(), json!({"table_deg": frame.table_deg, "coverage_left_pct": cl, "coverage_right_pct": cr}));
    }
    if found.len() < spec.count && !shared.stopped() {
        let least = if on_table { 3 } else { MIN_VIEWS };
        if found.len() < least {
            return Err(CaptureError::TooFew { found: found.len(), seen, needed: least, last: last_reason });
        }
        tracing::warn!("only {} of {} pairs kept after {seen} seen; solving with those", found.len(), spec.count);
    }
    Ok((found, rejected, tables, size))
}

fn write(shared: &CaptureShared, file: &str, text: &str) -> Result<(), CaptureError> {
    let path = shared.dir.join(file);
    crate::io::write_atomic(&path, text.as_bytes()).map_err(|source| CaptureError::Write { path, source })
}

fn solve_rig(shared: &CaptureShared, job: &StereoJob, size: (u32, u32), found: &[FoundPair], rejected: &[(String, String, String)]) -> Result<Value, CaptureError> {
    let (sol, report) = job::calibrate(job, size, found, rejected)?;
    write(shared, "calib.yaml", &job::calib_yaml(&sol))?;
    write(shared, "report.json", &serde_json::to_string_pretty(&report).expect("plain numbers"))?;
    Ok(json!({
        "file": shared.dir.join("calib.yaml"), "pairs": found.len(), "rms_left": sol.rms_left, "rms_right": sol.rms_right,
        "rms_stereo": sol.rms_stereo, "baseline_mm": report.baseline_mm, "coverage_left_pct": report.left.coverage_pct,
        "coverage_right_pct": report.right.coverage_pct, "warnings": report.warnings,
    }))
}

fn solve_axis(shared: &CaptureShared, job: &StereoJob, calib: &crate::calib::StereoCalib, found: &[FoundPair], tables: &[f64]) -> Result<Value, CaptureError> {
    let object = board_points(job.board.cols, job.board.rows, job.square_mm);
    let pairs: Vec<TablePair> = found
        .iter()
        .zip(tables)
        .map(|(p, &deg)| TablePair { table_deg: deg, left: TargetView { object: object.clone(), image: p.left.points.clone() }, right: TargetView { object: object.clone(), image: p.right.points.clone() } })
        .collect();
    let fit = fit_axis(calib, &pairs)?;
    let axis = TurntableAxis { axis_point_mm: fit.point_mm.into(), axis_dir: fit.dir.into(), source: "calibrated".into() };
    write(shared, "turntable.yaml", &format!("{}rms_px: {:.6}\npairs: {}\n", axis.to_yaml(), fit.rms_px, pairs.len()))?;
    let report = json!({
        "axis_point_mm": axis.axis_point_mm, "axis_dir": axis.axis_dir, "rms_px": fit.rms_px,
        "pairs": pairs.iter().zip(&fit.pairs).map(|(p, (rms, err))| json!({"table_deg": p.table_deg, "rms_px": rms, "angle_error_deg": err})).collect::<Vec<_>>(),
    });
    write(shared, "report.json", &serde_json::to_string_pretty(&report).expect("plain numbers"))?;
    Ok(json!({"file": shared.dir.join("turntable.yaml"), "pairs": pairs.len(), "rms_px": fit.rms_px, "axis_point_mm": axis.axis_point_mm, "axis_dir": axis.axis_dir}))
}

impl super::Daemon {
    /// `calib.capture`: starts capturing calibration pairs in the background.
    pub fn start_calibration(self: &std::sync::Arc<Self>, spec: CaptureSpec) -> Result<Value, super::DaemonError> {
        use super::DaemonError;
        spec.validate().map_err(|e| DaemonError::Params(format!("calib.capture: {e}")))?;
        let dir = self.config.daemon.state_dir.join(CALIBRATIONS).join(&spec.name);
        let mut inner = self.inner.lock().unwrap();
        Self::check_idle(&inner)?;
        if dir.exists() {
            return Err(DaemonError::CalibrationExists { name: spec.name.clone(), dir });
        }
        self.ensure_devices(&mut inner)?;
        std::fs::create_dir_all(&dir).map_err(|source| DaemonError::Create { path: dir.clone(), source })?;
        let manifest = json!({"format": 1, "kind": spec.kind, "status": "running", "spec": spec});
        if let Err(source) = crate::io::write_atomic(&dir.join("manifest.json"), manifest.to_string().as_bytes()) {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(DaemonError::Create { path: dir, source });
        }
        let mut devices = inner.devices.take().expect("opened above");
        let events = self.events.clone();
        let shared = std::sync::Arc::new(CaptureShared::new(
            spec.clone(),
            dir.clone(),
            Box::new(move |method, params| {
                let _ = events.send(super::Event { method: method.to_string(), params });
            }),
        ));
        inner.calib = Some(shared.clone());
        drop(inner);
        self.emit("calib.state", json!({"name": spec.name, "kind": spec.kind, "status": "running", "count": spec.count}));
        tracing::info!(calibration = %spec.name, kind = %spec.kind, count = spec.count, "calibration capture started");
        let daemon = self.clone();
        tokio::task::spawn_blocking(move || {
            let _span = tracing::info_span!("calibration", name = %shared.spec.name).entered();
            let end = run(&mut devices, &shared);
            daemon.calibration_finished(devices, &shared, end);
        });
        Ok(json!({"name": spec.name, "kind": spec.kind, "dir": dir, "count": spec.count}))
    }

    fn calibration_finished(&self, devices: Devices, shared: &CaptureShared, end: CaptureEnd) {
        let name = shared.spec.name.clone();
        let mut manifest = json!({"format": 1, "kind": shared.spec.kind, "status": end.status, "reason": end.reason, "spec": shared.spec, "result": end.result, "progress": shared.progress()});
        if let Err(e) = crate::io::write_atomic(&shared.dir.join("manifest.json"), serde_json::to_string_pretty(&manifest).expect("plain values").as_bytes()) {
            tracing::error!(calibration = %name, "cannot write its manifest: {e}");
        }
        match end.status {
            "complete" => tracing::info!(calibration = %name, "calibration complete"),
            s => tracing::warn!(calibration = %name, status = s, reason = end.reason.as_deref().unwrap_or(""), "calibration ended"),
        }
        let mut inner = self.inner.lock().unwrap();
        self.return_devices(&mut inner, devices, end.device_failed.then(|| end.reason.clone().unwrap_or_default()), ("calibration", &name));
        inner.calib = None;
        drop(inner);
        manifest["name"] = json!(name);
        manifest["dir"] = json!(shared.dir);
        self.emit("calib.state", manifest);
        self.scan_ended.notify_waiters();
    }

    /// `calib.stop`: the capture ends after its current pair and solves what it kept.
    pub fn stop_calibration(&self) -> Result<Value, super::DaemonError> {
        let current = self.inner.lock().unwrap().calib.clone();
        match current {
            Some(c) => {
                c.request_stop();
                Ok(json!({"name": c.spec.name, "stopping": true}))
            }
            None => Err(super::DaemonError::NoCalibration),
        }
    }
}
