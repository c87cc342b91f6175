//! `spinscand`, the live daemon: owns the cameras and the turntable, scans on command from
//! the control socket, and writes each scan to its own folder.
//!
//! ```text
//!  spinscan CLI / socat / Python ──JSON-RPC lines──> control::server (tokio) ──> Daemon ──spawn_blocking──> pipeline::live::run
//!                                   <── hello, answers, events ──┘                │ devices (taken and given back)
//!                                                                                 └─ state_dir/<name>/manifest.json …
//! ```
//!
//! The daemon knows nothing of JSON-RPC: it takes a [`ScanSpec`] and answers with typed
//! results and [`DaemonError`]s; [`crate::control`] maps requests and errors to the wire.
//! Backends are chosen at run time (`[backend] kind`): `v4l2` + serial (the lab), `sim`
//! (hw-sim cameras, firmware on a pty), `replay` (a recording); everything after
//! [`Devices`] is the same code for all three.

pub mod calibration;
pub mod config;
pub mod throughput;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use crate::hw::sim::SimError;
use crate::hw::{CaptureError, TurntableError};
use crate::pipeline::live::{self as scan, validate_name, Devices, ScanEnd, ScanMode, ScanShared, ScanSpec};
use crate::recording::RecordingError;
use config::{BackendKind, Config};

/// Why the daemon could not do what it was asked.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    /// The request itself is out of bounds (the control layer answers "invalid params").
    #[error(transparent)]
    Spec(#[from] crate::pipeline::live::SpecError),
    #[error("scan {0} is running; stop it first (scan.stop)")]
    Busy(String),
    #[error("a scan named {name} exists already ({dir}); choose another name")]
    Exists { name: String, dir: PathBuf },
    #[error("devices unavailable: {0}")]
    Devices(#[from] DeviceError),
    #[error("cannot create {path}: {source}")]
    Create { path: PathBuf, source: std::io::Error },
    #[error("cannot use the state folder {path}: {source}")]
    StateDir { path: PathBuf, source: std::io::Error },
    #[error("the state folder {path} has {free_mib} MiB free; a scan needs at least {need_mib} MiB to start")]
    NoRoom { path: PathBuf, free_mib: u64, need_mib: u64 },
    #[error("another spinscand uses the state folder {0} (its lock file {0}/.spinscand.lock is held); stop it, or give this one another --state-dir")]
    Locked(PathBuf),
    #[error("no scan is running")]
    NoScan,
    #[error("scan {0} fuses nothing: this daemon's scans are not registered (scan.register = false in its config); its views are in its folder, and `spinscan mesh` meshes a results folder whose views are registered")]
    NotFused(String),
    #[error("no scan named {name} in {state_dir}")]
    NoSuchScan { name: String, state_dir: PathBuf },
    /// A request's parameters are out of bounds (the message names the one and its range).
    #[error("{0}")]
    Params(String),
    #[error("calibration {0} is capturing; stop it first (calib.stop)")]
    Calibrating(String),
    #[error("no calibration is capturing")]
    NoCalibration,
    #[error("a calibration named {name} exists already ({dir}); choose another name")]
    CalibrationExists { name: String, dir: PathBuf },
}

/// Why the configured devices could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error("backend.replay: {0}")]
    Replay(RecordingError),
    #[error("cameras.calibration: {0}")]
    Calibration(crate::calib::CalibError),
    #[error(transparent)]
    Cameras(#[from] CaptureError),
    #[error(transparent)]
    Turntable(#[from] TurntableError),
}

/// A notification for every subscriber (`scan.progress`, `scan.state`, `device.error`).
#[derive(Debug, Clone, PartialEq)]
pub struct Event {
    pub method: String,
    pub params: Value,
}

/// What `scan.start` answers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanStarted {
    pub name: String,
    pub dir: PathBuf,
    pub mode: String,
    pub step_deg: Option<f64>,
    pub total_deg: f64,
    pub views_planned: Option<usize>,
}

/// What `scan.stop` answers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanStopping {
    pub name: String,
    pub stopping: bool,
}

/// What `scan.mesh` answers: the file the running scan's preview mesh will be written to,
/// announced by a `scan.mesh` event when it is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanMeshing {
    pub name: String,
    pub file: String,
}

/// Exit codes of `spinscand` (sysexits.h), named in the unit's `RestartPreventExitStatus=`.
pub mod exit {
    /// The configuration (file or flags) is wrong: restarting will not help.
    pub const CONFIG: u8 = 78;
    /// A device could not be opened at start.
    pub const UNAVAILABLE: u8 = 69;
    /// The socket or the state folder could not be made.
    pub const CANT_CREATE: u8 = 73;
    /// Anything else.
    pub const SOFTWARE: u8 = 70;
}

/// Free space a scan needs to start: a few dozen views with their recording.
const MIN_FREE_BYTES: u64 = 64 << 20;

/// Bytes free for the daemon's user on the file system of `path` (None when it cannot say).
fn free_bytes(path: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let c = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: a valid C string and a statvfs the call fills in.
    (unsafe { libc::statvfs(c.as_ptr(), &mut st) } == 0).then(|| st.f_bavail as u64 * st.f_frsize as u64)
}

/// Takes the state folder's lock (`flock` on `.spinscand.lock`, released when the file
/// closes, so a crashed daemon leaves no stale lock).
fn lock_state_dir(state: &Path) -> Result<std::fs::File, DaemonError> {
    use std::os::fd::AsRawFd;
    let path = state.join(".spinscand.lock");
    let file = std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(&path).map_err(|source| DaemonError::StateDir { path: state.to_path_buf(), source })?;
    // SAFETY: flock on a descriptor this function owns.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } != 0 {
        return Err(DaemonError::Locked(state.to_path_buf()));
    }
    Ok(file)
}

/// A state folder the daemon can write scans into (checked at start, not at the first scan).
fn check_writable(state: &Path) -> std::io::Result<()> {
    let probe = state.join(format!(".spinscand-probe-{}", std::process::id()));
    std::fs::write(&probe, b"ok")?;
    std::fs::remove_file(&probe)
}

/// Marks scans left `running` by a daemon that died (crash, SIGKILL, power loss) as
/// `interrupted`; their recordings replay. Returns their names.
pub fn recover_interrupted(state_dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    for (name, mut m) in list_manifests(state_dir) {
        if m["status"] == "running" {
            m["status"] = json!("interrupted");
            m["reason"] = json!(format!("spinscand stopped while the scan was running (crash, SIGKILL or power loss); its recording replays: spinscan replay {} -o {}", state_dir.join(&name).display(), state_dir.join(&name).join("replayed").display()));
            let path = state_dir.join(&name).join("manifest.json");
            match crate::io::write_atomic(&path, serde_json::to_string_pretty(&m).unwrap().as_bytes()) {
                Ok(()) => {
                    tracing::warn!(scan = %name, "marked interrupted (left running by an earlier daemon)");
                    out.push(name);
                }
                Err(e) => tracing::error!(scan = %name, "cannot mark interrupted: {e}"),
            }
        }
    }
    out
}

/// Every scan folder's manifest, by name (folders without a readable manifest are listed
/// with status "unknown").
pub fn list_manifests(state_dir: &Path) -> Vec<(String, Value)> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(state_dir) else { return out };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().to_string();
        if !e.path().is_dir() || validate_name(&name).is_err() || name == calibration::CALIBRATIONS {
            continue;
        }
        out.push((name.clone(), read_manifest(&e.path())));
    }
    out.sort_by(|a, b| a.0.cmp(&b.0));
    out
}

fn read_manifest(dir: &Path) -> Value {
    let path = dir.join("manifest.json");
    match std::fs::read_to_string(&path).map_err(|e| e.to_string()).and_then(|t| serde_json::from_str::<Value>(&t).map_err(|e| e.to_string())) {
        Ok(v) if v.is_object() => v,
        Ok(_) => json!({"status": "unknown", "reason": format!("{} is not a JSON object", path.display())}),
        Err(e) => json!({"status": "unknown", "reason": format!("{}: {e}", path.display())}),
    }
}

/// Opens the configured backend's devices.
fn open_backend(config: &Config) -> Result<Devices, DeviceError> {
    match config.backend.kind {
        BackendKind::Sim => {
            let lab = crate::hw::sim::SimLab::open(&config.sim, config.cameras.fps as f64, config.turntable.driver())?;
            Ok(Devices { source: Box::new(lab.cameras), turntable: Some(Box::new(lab.turntable)) })
        }
        BackendKind::Replay => {
            let rec = crate::recording::Recording::open(&config.backend.replay).map_err(DeviceError::Replay)?;
            Ok(Devices { source: Box::new(crate::hw::replay::ReplaySource::new(rec)), turntable: None })
        }
        BackendKind::V4l2 => {
            let c = &config.cameras;
            let calib = crate::calib::StereoCalib::load(&c.calibration).map_err(DeviceError::Calibration)?;
            let fourcc = c.fourcc();
            let stream = crate::hw::v4l2::StreamConfig {
                width: c.width,
                height: c.height,
                fps: c.fps,
                fourcc,
                buffers: c.buffers,
                timeout: std::time::Duration::from_millis(c.frame_timeout_ms),
                auto_exposure: c.auto_exposure,
                exposure_100us: c.exposure_100us,
                gain: c.gain,
            };
            let tolerance = (c.pair_tolerance_ms > 0.0).then(|| c.pair_tolerance_ns());
            let cams = crate::hw::v4l2::V4l2Stereo::open(&c.left, &c.right, stream, tolerance, calib)?;
            let table = crate::hw::HorusTurntable::open(&config.turntable.port, config.turntable.driver())?;
            Ok(Devices { source: Box::new(cams), turntable: Some(Box::new(table)) })
        }
    }
}

struct Inner {
    /// None while a scan or a calibration holds them, or after they failed.
    devices: Option<Devices>,
    device_error: Option<String>,
    scan: Option<Arc<ScanShared>>,
    last: Option<(String, ScanEnd)>,
    /// The calibration capturing, if any (`calib.capture`).
    calib: Option<Arc<calibration::CaptureShared>>,
}

/// The daemon's state, shared by every connection.
pub struct Daemon {
    pub config: Config,
    /// The state folder's lock, held for the daemon's life: one daemon per state folder.
    _lock: std::fs::File,
    events: tokio::sync::broadcast::Sender<Event>,
    inner: Mutex<Inner>,
    started: Instant,
    /// Signalled when a scan ends.
    scan_ended: tokio::sync::Notify,
}

impl Daemon {
    /// Opens the devices (an error is fatal at start: the caller exits with
    /// [`exit::UNAVAILABLE`]) and marks scans an earlier daemon left running.
    pub fn start(config: Config) -> Result<Arc<Daemon>, DaemonError> {
        let state = &config.daemon.state_dir;
        std::fs::create_dir_all(state).map_err(|source| DaemonError::StateDir { path: state.clone(), source })?;
        // Before anything in the folder is touched (recovery marks scans left `running`).
        let lock = lock_state_dir(state)?;
        check_writable(state).map_err(|source| DaemonError::StateDir { path: state.clone(), source })?;
        recover_interrupted(state);
        let devices = open_backend(&config)?;
        let (events, _) = tokio::sync::broadcast::channel(256);
        Ok(Arc::new(Daemon {
            config,
            _lock: lock,
            events,
            inner: Mutex::new(Inner { devices: Some(devices), device_error: None, scan: None, last: None, calib: None }),
            started: Instant::now(),
            scan_ended: tokio::sync::Notify::new(),
        }))
    }

    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<Event> {
        self.events.subscribe()
    }

    fn emit(&self, method: &str, params: Value) {
        let _ = self.events.send(Event { method: method.to_string(), params });
    }

    /// The running scan, if any.
    pub fn current_scan(&self) -> Option<Arc<ScanShared>> {
        self.inner.lock().unwrap().scan.clone()
    }

    /// False when a running scan's pipeline has not moved for `daemon.stall_s` (the
    /// watchdog is then not fed).
    pub fn healthy(&self) -> bool {
        self.current_scan().is_none_or(|s| s.idle_s() < self.config.daemon.stall_s)
    }

    /// One line for systemd's STATUS=.
    pub fn status_line(&self) -> String {
        match self.current_scan() {
            Some(s) => {
                let p = s.progress();
                format!("scanning {}: {} views, {} captured, {} drops", s.spec.name, p["views"], p["captured"], p["drops"])
            }
            None => match &self.inner.lock().unwrap().device_error {
                Some(e) => format!("idle; devices failed: {e}"),
                None => "idle".into(),
            },
        }
    }

    pub fn status(&self) -> Value {
        let inner = self.inner.lock().unwrap();
        json!({
            "version": env!("CARGO_PKG_VERSION"),
            "backend": self.config.backend.kind.name(),
            "state": if inner.scan.is_some() { "scanning" } else { "idle" },
            "scan": inner.scan.as_ref().map(|s| s.progress()),
            "calibration": inner.calib.as_ref().map(|c| c.progress()),
            "last_scan": inner.last.as_ref().map(|(name, end)| json!({"name": name, "status": end.status, "reason": end.reason})),
            "devices_ok": inner.device_error.is_none(),
            "device_error": inner.device_error,
            "state_dir": self.config.daemon.state_dir,
            "uptime_s": self.started.elapsed().as_secs_f64(),
            "rss_mib": rss_mib(),
        })
    }

    pub fn devices(&self) -> Value {
        let c = &self.config;
        let mut inner = self.inner.lock().unwrap();
        let scanning = inner.scan.as_ref().map(|s| s.progress()["table_deg"].clone());
        let device_error = inner.device_error.clone();
        let table = match inner.devices.as_mut().and_then(|d| d.turntable.as_mut()) {
            Some(t) => match t.angle() {
                Ok(deg) => json!({"port": t.describe(), "state": "idle", "table_deg": deg}),
                Err(e) => json!({"port": t.describe(), "state": "error", "error": e.to_string()}),
            },
            None if scanning.is_some() => json!({"state": "scanning", "table_deg": scanning}),
            None if c.backend.kind == BackendKind::Replay => json!({"state": "none (replay)"}),
            None => json!({"state": "unavailable", "error": device_error}),
        };
        let source = inner.devices.as_ref().map(|d| d.source.describe());
        drop(inner);
        let mut out = json!({
            "backend": c.backend.kind.name(),
            "source": source,
            "cameras": {
                "left": c.cameras.left, "right": c.cameras.right, "width": c.cameras.width, "height": c.cameras.height,
                "fps": c.cameras.fps, "pixel_format": c.cameras.pixel_format, "pair_tolerance_ms": c.cameras.pair_tolerance_ns() as f64 / 1e6,
            },
            "turntable": table,
        });
        match c.backend.kind {
            BackendKind::V4l2 => {
                let present = crate::hw::v4l2::list_devices();
                let cams = &c.cameras;
                let warnings = crate::hw::v4l2::check_offered(&present, &[&cams.left, &cams.right], cams.fourcc(), cams.width, cams.height, cams.fps);
                out["present"] = present;
                out["warnings"] = json!(warnings);
            }
            BackendKind::Sim => out["sim"] = json!({"object": c.sim.object, "width": c.sim.width, "height": c.sim.height, "ideal": c.sim.ideal}),
            BackendKind::Replay => out["replay"] = json!(c.backend.replay),
        }
        out
    }

    /// Starts a scan in the background. `spec` is checked here ([`ScanSpec::validate`]),
    /// whoever built it.
    pub fn start_scan(self: &Arc<Self>, spec: ScanSpec) -> Result<ScanStarted, DaemonError> {
        spec.validate()?;
        let name = spec.name.clone();
        let mode = spec.mode;
        let dir = self.config.daemon.state_dir.join(&name);
        if name == calibration::CALIBRATIONS {
            return Err(DaemonError::Params(format!("scan.start: `{name}` is the folder of the daemon's calibrations; choose another name")));
        }
        let mut inner = self.inner.lock().unwrap();
        Self::check_idle(&inner)?;
        if dir.exists() {
            return Err(DaemonError::Exists { name, dir });
        }
        self.ensure_devices(&mut inner)?;
        // Room for a scan's first views, and a folder that says what it is from the start:
        // a scan that cannot even begin is refused here, not reported later as "unknown".
        let state = &self.config.daemon.state_dir;
        if let Some(free) = free_bytes(state).filter(|&f| f < MIN_FREE_BYTES) {
            return Err(DaemonError::NoRoom { path: state.clone(), free_mib: free >> 20, need_mib: MIN_FREE_BYTES >> 20 });
        }
        std::fs::create_dir_all(&dir).map_err(|source| DaemonError::Create { path: dir.clone(), source })?;
        if let Err(source) = crate::io::write_atomic(&dir.join("manifest.json"), spec.manifest("running", None).to_string().as_bytes()) {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(DaemonError::Create { path: dir, source });
        }
        let mut devices = inner.devices.take().expect("opened above");
        let events = self.events.clone();
        let shared = Arc::new(ScanShared::new(spec.clone(), dir.clone(), Box::new(move |method, params| {
            let _ = events.send(Event { method: method.to_string(), params });
        })));
        inner.scan = Some(shared.clone());
        drop(inner);
        let views = (mode == ScanMode::Step).then(|| spec.step_views());
        self.emit("scan.state", json!({"name": name, "status": "running", "mode": mode.name(), "views_planned": views}));
        tracing::info!(scan = %name, mode = mode.name(), step_deg = spec.step_deg, total_deg = spec.total_deg, "scan started");
        let daemon = self.clone();
        let settings = self.config.pipeline_settings();
        tokio::task::spawn_blocking(move || {
            let _span = tracing::info_span!("scan", name = %shared.spec.name).entered();
            let end = scan::run(&mut devices, shared.clone(), &settings);
            daemon.scan_finished(devices, &shared, end);
        });
        Ok(ScanStarted { name, dir, mode: mode.name().to_string(), step_deg: (mode == ScanMode::Step).then_some(spec.step_deg), total_deg: spec.total_deg, views_planned: views })
    }

    /// Busy when a scan or a calibration holds the devices.
    fn check_idle(inner: &Inner) -> Result<(), DaemonError> {
        if let Some(s) = &inner.scan {
            return Err(DaemonError::Busy(s.spec.name.clone()));
        }
        if let Some(c) = &inner.calib {
            return Err(DaemonError::Calibrating(c.spec.name.clone()));
        }
        Ok(())
    }

    /// Opens the devices when they are closed (a replay starts from its first frame every
    /// time; failed devices get another try).
    fn ensure_devices(&self, inner: &mut Inner) -> Result<(), DaemonError> {
        if inner.devices.is_none() || self.config.backend.kind == BackendKind::Replay {
            inner.devices = None;
            match open_backend(&self.config) {
                Ok(devices) => {
                    inner.devices = Some(devices);
                    inner.device_error = None;
                }
                Err(e) => {
                    inner.device_error = Some(e.to_string());
                    return Err(DaemonError::Devices(e));
                }
            }
        }
        Ok(())
    }

    /// Gives the devices of a scan or a calibration (`job`: "scan" or "calibration", and its
    /// name) back, or, when one failed (`failure`: why), drops them — they are reopened at
    /// the next start — and says so in a `device.error` event.
    fn return_devices(&self, inner: &mut Inner, devices: Devices, failure: Option<String>, job: (&str, &str)) {
        match failure {
            Some(why) => {
                let mut params = json!({"message": why});
                params[job.0] = json!(job.1);
                self.emit("device.error", params);
                inner.device_error = Some(why);
                drop(devices);
            }
            None => inner.devices = Some(devices),
        }
    }

    fn scan_finished(&self, devices: Devices, shared: &ScanShared, end: ScanEnd) {
        let name = shared.spec.name.clone();
        match end.status {
            "complete" => tracing::info!(scan = %name, "scan complete"),
            s => tracing::warn!(scan = %name, status = s, reason = end.reason.as_deref().unwrap_or(""), "scan ended"),
        }
        let mut inner = self.inner.lock().unwrap();
        let device_failed = end.status == "failed" && end.reason.as_deref().is_some_and(|r| r.contains("camera") || r.contains("turntable"));
        self.return_devices(&mut inner, devices, device_failed.then(|| end.reason.clone().unwrap_or_default()), ("scan", &name));
        inner.scan = None;
        inner.last = Some((name.clone(), end.clone()));
        drop(inner);
        // The scan's buffers are gone; hand glibc's arenas back to the system, so a daemon
        // that runs for months does not grow with every scan.
        #[cfg(target_env = "gnu")]
        // SAFETY: malloc_trim only releases free memory of the allocator.
        unsafe {
            libc::malloc_trim(0);
        }
        let mut state = json!({"name": name, "status": end.status, "reason": end.reason});
        state["progress"] = shared.progress();
        self.emit("scan.state", state);
        self.scan_ended.notify_waiters();
    }

    /// `scan.stop`: the running scan finishes its current view and ends `interrupted`.
    pub fn stop_scan(&self, why: &str) -> Result<ScanStopping, DaemonError> {
        match self.current_scan() {
            Some(s) => {
                s.request_stop(why);
                Ok(ScanStopping { name: s.spec.name.clone(), stopping: true })
            }
            None => Err(DaemonError::NoScan),
        }
    }

    /// `scan.mesh`: the running scan writes a mesh of the views fused so far to
    /// `mesh_live.ply` in its folder and announces it with a `scan.mesh` event.
    pub fn mesh_scan(&self) -> Result<ScanMeshing, DaemonError> {
        match self.current_scan() {
            Some(s) if !self.config.scan.register => Err(DaemonError::NotFused(s.spec.name.clone())),
            Some(s) => {
                s.request_mesh();
                Ok(ScanMeshing { name: s.spec.name.clone(), file: s.dir.join("mesh_live.ply").display().to_string() })
            }
            None => Err(DaemonError::NoScan),
        }
    }

    /// Waits until no scan runs and no calibration captures (graceful shutdown).
    pub async fn wait_idle(&self) {
        loop {
            let ended = self.scan_ended.notified();
            if self.current_scan().is_none() && self.inner.lock().unwrap().calib.is_none() {
                return;
            }
            ended.await;
        }
    }

    /// A scan's manifest (with its live progress while it runs).
    pub fn get_scan(&self, name: &str) -> Result<Value, DaemonError> {
        validate_name(name)?;
        let dir = self.config.daemon.state_dir.join(name);
        if !dir.is_dir() {
            return Err(DaemonError::NoSuchScan { name: name.to_string(), state_dir: self.config.daemon.state_dir.clone() });
        }
        let mut m = read_manifest(&dir);
        m["name"] = json!(name);
        m["dir"] = json!(dir);
        if let Some(s) = self.current_scan().filter(|s| s.spec.name == name) {
            m["progress"] = s.progress();
        }
        Ok(m)
    }

    /// Drops the devices (a simulated turntable's emulator with its driver) at shutdown.
    pub fn close(&self) {
        let mut inner = self.inner.lock().unwrap();
        inner.devices = None;
    }
}

/// Resident set size of this process, MiB (Linux /proc).
pub fn rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: f64 = s.lines().find(|l| l.starts_with("VmRSS:"))?.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// The config file path a daemon was started with, for messages.
pub fn config_source(path: Option<&PathBuf>, sim: bool) -> String {
    match (path, sim) {
        (Some(p), _) => p.display().to_string(),
        (None, true) => "built-in simulated-lab defaults (--sim)".into(),
        (None, false) => "built-in defaults".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn running_scans_of_a_dead_daemon_become_interrupted() {
        let dir = std::env::temp_dir().join(format!("spinscan-recover-{}", std::process::id()));
        for (name, status) in [("a", "running"), ("b", "complete")] {
            std::fs::create_dir_all(dir.join(name)).unwrap();
            std::fs::write(dir.join(name).join("manifest.json"), json!({"format": 1, "status": status, "frames": 3}).to_string()).unwrap();
        }
        std::fs::create_dir_all(dir.join("junk")).unwrap();
        assert_eq!(recover_interrupted(&dir), vec!["a".to_string()]);
        let m = list_manifests(&dir);
        assert_eq!(m.iter().map(|(n, v)| (n.as_str(), v["status"].as_str().unwrap())).collect::<Vec<_>>(), vec![("a", "interrupted"), ("b", "complete"), ("junk", "unknown")]);
        assert!(m[0].1["reason"].as_str().unwrap().contains("spinscan replay"));
        assert_eq!(m[0].1["frames"], 3);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
