//! `spinscand`, the live daemon: owns the cameras and the turntable, scans on command from
//! the control socket, and writes each scan to its own folder.
//!
//! ```text
//!  spinscan CLI / socat / Python ──JSON-RPC lines──> server (tokio) ──> Daemon ──spawn_blocking──> scan::run
//!                                   <── hello, answers, events ──┘        │ devices (taken and given back)
//!                                                                         └─ state_dir/<name>/manifest.json …
//! ```
//!
//! Backends are chosen at run time (`[backend] kind`): `v4l2` + serial (the lab), `sim`
//! (hw-sim cameras, firmware on a pty), `replay` (a recording); everything after
//! [`scan::Devices`] is the same code for all three.

pub mod client;
pub mod config;
pub mod rpc;
pub mod server;
pub mod throughput;

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde_json::{json, Value};

use config::{BackendKind, Config};
use rpc::{code, Params, Request, RpcError};
use crate::pipeline::live::{self as scan, Devices, PipelineSettings, ScanEnd, ScanMode, ScanShared, ScanSpec};

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

/// Scan names: a folder name, never a path.
pub fn validate_name(name: &str) -> Result<(), String> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        && name.chars().next().is_some_and(|c| c.is_ascii_alphanumeric());
    if ok {
        Ok(())
    } else {
        Err(format!("scan name {name:?} is not allowed: use 1–64 letters, digits, '-', '_' or '.', starting with a letter or digit (it names a folder)"))
    }
}

/// Marks scans left `running` by a daemon that died (crash, SIGKILL, power loss) as
/// `interrupted`; their recordings replay. Returns their names.
pub fn recover_interrupted(state_dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    for (name, mut m) in list_manifests(state_dir) {
        if m["status"] == "running" {
            m["status"] = json!("interrupted");
            m["reason"] = json!(format!("spinscand stopped while the scan was running (crash, SIGKILL or power loss); its recording replays: spinscan replay {}", state_dir.join(&name).display()));
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
        if !e.path().is_dir() || validate_name(&name).is_err() {
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

/// Who may control the daemon (SO_PEERCRED): root, the daemon's own user, and members of
/// the configured group (primary or supplementary, from /etc/passwd and /etc/group).
#[derive(Debug, Clone)]
pub struct Auth {
    pub daemon_uid: u32,
    /// (name, gid, member user names).
    pub group: Option<(String, u32, Vec<String>)>,
    /// uid → (user name, primary gid), from /etc/passwd.
    pub users: Vec<(u32, String, u32)>,
}

impl Auth {
    /// Reads the group from `/etc/group` (an empty name: no group).
    pub fn load(group: &str) -> Result<Auth, String> {
        Auth::from_files(group, Path::new("/etc/group"), Path::new("/etc/passwd"))
    }

    pub fn from_files(group: &str, group_file: &Path, passwd_file: &Path) -> Result<Auth, String> {
        // SAFETY: geteuid has no preconditions.
        let daemon_uid = unsafe { libc::geteuid() };
        let users = std::fs::read_to_string(passwd_file)
            .unwrap_or_default()
            .lines()
            .filter_map(|l| {
                let f: Vec<&str> = l.split(':').collect();
                Some((f.get(2)?.parse().ok()?, f.first()?.to_string(), f.get(3)?.parse().ok()?))
            })
            .collect();
        if group.is_empty() {
            return Ok(Auth { daemon_uid, group: None, users });
        }
        let text = std::fs::read_to_string(group_file).map_err(|e| format!("cannot read {}: {e}", group_file.display()))?;
        for line in text.lines() {
            let f: Vec<&str> = line.split(':').collect();
            if f.len() >= 4 && f[0] == group {
                let gid = f[2].parse().map_err(|_| format!("{}: group {group} has a bad gid {:?}", group_file.display(), f[2]))?;
                let members = f[3].split(',').filter(|m| !m.is_empty()).map(str::to_string).collect();
                return Ok(Auth { daemon_uid, group: Some((group.to_string(), gid, members)), users });
            }
        }
        Err(format!("group `{group}` (daemon.group) does not exist; create it (groupadd {group}) or set daemon.group = \"\""))
    }

    /// May the peer `uid`/`gid` control scans?
    pub fn may_control(&self, uid: u32, gid: u32) -> bool {
        if uid == 0 || uid == self.daemon_uid {
            return true;
        }
        let Some((_, group_gid, members)) = &self.group else { return false };
        if gid == *group_gid {
            return true;
        }
        self.users.iter().any(|(u, name, primary)| *u == uid && (primary == group_gid || members.contains(name)))
    }
}

/// Opens the configured backend's devices.
fn open_backend(config: &Config) -> Result<Devices, String> {
    match config.backend.kind {
        BackendKind::Sim => {
            let lab = crate::hw::sim::SimLab::open(&config.sim, config.cameras.fps as f64, config.turntable.driver()).map_err(|e| e.to_string())?;
            Ok(Devices { source: Box::new(lab.cameras), turntable: Some(Box::new(lab.turntable)) })
        }
        BackendKind::Replay => {
            let rec = crate::recording::Recording::open(&config.backend.replay).map_err(|e| format!("backend.replay: {e}"))?;
            Ok(Devices { source: Box::new(crate::hw::replay::ReplaySource::new(rec)), turntable: None })
        }
        BackendKind::V4l2 => {
            let c = &config.cameras;
            let calib = crate::calib::StereoCalib::load(&c.calibration).map_err(|e| format!("cameras.calibration: {e}"))?;
            let mut fourcc = [b' '; 4];
            fourcc.copy_from_slice(&c.pixel_format.as_bytes()[..4]);
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
            let cams = crate::hw::v4l2::V4l2Stereo::open(&c.left, &c.right, stream, c.pair_tolerance_ns(), calib).map_err(|e| e.to_string())?;
            let table = crate::hw::HorusTurntable::open(&config.turntable.port, config.turntable.driver()).map_err(|e| e.to_string())?;
            Ok(Devices { source: Box::new(cams), turntable: Some(Box::new(table)) })
        }
    }
}

/// The pipeline settings a config asks for.
pub fn pipeline_settings(config: &Config) -> PipelineSettings {
    let mut pipeline = crate::pipeline::PipelineOptions::default();
    pipeline.matching.num_disparities = config.matching.num_disparities;
    pipeline.matching.block = config.matching.block;
    // Parallelism comes from the pool: one thread per matcher.
    pipeline.matching.threads = 1;
    let registration = config.scan.register.then(|| {
        let mut p = crate::register::ring::RegistrationParams::default();
        if config.scan.register_max_points > 0 {
            // Both ends of ICP: the view moved (source) and the view it lands on (target).
            p.max_target_points = config.scan.register_max_points;
            p.icp.max_source_points = p.icp.max_source_points.min(config.scan.register_max_points);
        }
        p
    });
    PipelineSettings {
        pipeline,
        segment: config.matching.segment,
        assist: if registration.is_some() { config.assist().expect("validated") } else { None },
        registration,
        matcher_threads: config.scan.matcher_threads,
        queue_depth: config.scan.queue_depth,
        record: true,
        pace_hz: (config.backend.kind == BackendKind::Replay && config.backend.replay_paced).then_some(config.cameras.fps as f64),
        register_newest_when_behind: false,
    }
}

struct Inner {
    /// None while a scan holds them or after they failed.
    devices: Option<Devices>,
    device_error: Option<String>,
    scan: Option<Arc<ScanShared>>,
    last: Option<(String, ScanEnd)>,
}

/// The daemon's state, shared by every connection.
pub struct Daemon {
    pub config: Config,
    pub auth: Auth,
    events: tokio::sync::broadcast::Sender<Value>,
    inner: Mutex<Inner>,
    started: Instant,
    /// Signalled when a scan ends.
    scan_ended: tokio::sync::Notify,
}

impl Daemon {
    /// Opens the devices (an error is fatal at start: the caller exits with
    /// [`exit::UNAVAILABLE`]) and marks scans an earlier daemon left running.
    pub fn start(config: Config, auth: Auth) -> Result<Arc<Daemon>, String> {
        std::fs::create_dir_all(&config.daemon.state_dir).map_err(|e| format!("cannot create the state folder {}: {e}", config.daemon.state_dir.display()))?;
        recover_interrupted(&config.daemon.state_dir);
        let devices = open_backend(&config)?;
        let (events, _) = tokio::sync::broadcast::channel(256);
        Ok(Arc::new(Daemon {
            config,
            auth,
            events,
            inner: Mutex::new(Inner { devices: Some(devices), device_error: None, scan: None, last: None }),
            started: Instant::now(),
            scan_ended: tokio::sync::Notify::new(),
        }))
    }

    pub fn subscribe(&self) -> tokio::sync::broadcast::Receiver<Value> {
        self.events.subscribe()
    }

    fn emit(&self, method: &str, params: Value) {
        let _ = self.events.send(rpc::notification(method, params));
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
            "protocol": rpc::PROTOCOL_VERSION,
            "backend": self.config.backend.kind.name(),
            "state": if inner.scan.is_some() { "scanning" } else { "idle" },
            "scan": inner.scan.as_ref().map(|s| s.progress()),
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
            BackendKind::V4l2 => out["present"] = crate::hw::v4l2::list_devices(),
            BackendKind::Sim => out["sim"] = json!({"object": c.sim.object, "width": c.sim.width, "height": c.sim.height, "ideal": c.sim.ideal}),
            BackendKind::Replay => out["replay"] = json!(c.backend.replay),
        }
        out
    }

    /// `scan.start`.
    pub fn start_scan(self: &Arc<Self>, req: &Request) -> Result<Value, RpcError> {
        let p = Params::new(req, &["name", "mode", "step_deg", "total_deg", "speed_deg_s", "max_views"])?;
        let name = p.str("name")?.ok_or_else(|| RpcError::params("scan.start: `name` is required"))?.to_string();
        validate_name(&name).map_err(RpcError::params)?;
        let mode = match p.str("mode")? {
            None | Some("step") => ScanMode::Step,
            Some("continuous") => ScanMode::Continuous,
            Some(other) => return Err(RpcError::params(format!("scan.start: `mode` must be \"step\" or \"continuous\", got {other:?}"))),
        };
        let step_deg = p.f64("step_deg")?.unwrap_or(self.config.scan.step_deg);
        if !(step_deg > 0.0 && step_deg <= 360.0) {
            return Err(RpcError::params(format!("scan.start: `step_deg` must be within (0, 360], got {step_deg}")));
        }
        let total_deg = p.f64("total_deg")?.unwrap_or(self.config.scan.total_deg);
        if !(total_deg > 0.0 && total_deg <= 3600.0) {
            return Err(RpcError::params(format!("scan.start: `total_deg` must be within (0, 3600], got {total_deg}")));
        }
        let speed_deg_s = p.f64("speed_deg_s")?.unwrap_or(self.config.turntable.continuous_deg_s);
        if !(speed_deg_s > 0.0 && speed_deg_s <= 360.0) {
            return Err(RpcError::params(format!("scan.start: `speed_deg_s` must be within (0, 360], got {speed_deg_s}")));
        }
        let max_views = p.u64("max_views")?.map(|n| n as usize);
        if max_views == Some(0) {
            return Err(RpcError::params("scan.start: `max_views` must be at least 1"));
        }
        let dir = self.config.daemon.state_dir.join(&name);
        let spec = ScanSpec { name: name.clone(), mode, step_deg, total_deg, speed_deg_s, max_views };

        let mut inner = self.inner.lock().unwrap();
        if let Some(s) = &inner.scan {
            return Err(RpcError::new(code::BUSY, format!("scan {} is running; stop it first (scan.stop)", s.spec.name)));
        }
        if dir.exists() {
            return Err(RpcError::new(code::EXISTS, format!("a scan named {name} exists already ({}); choose another name", dir.display())));
        }
        // A replay starts from its first frame every time; failed devices get another try.
        if inner.devices.is_none() || self.config.backend.kind == BackendKind::Replay {
            inner.devices = None;
            match open_backend(&self.config) {
                Ok(devices) => {
                    inner.devices = Some(devices);
                    inner.device_error = None;
                }
                Err(e) => {
                    inner.device_error = Some(e.clone());
                    return Err(RpcError::new(code::DEVICE, format!("devices unavailable: {e}")));
                }
            }
        }
        std::fs::create_dir_all(&dir).map_err(|e| RpcError::new(code::INTERNAL, format!("cannot create {}: {e}", dir.display())))?;
        let mut devices = inner.devices.take().expect("opened above");
        let events = self.events.clone();
        let shared = Arc::new(ScanShared::new(spec.clone(), dir.clone(), Box::new(move |m, p| {
            let _ = events.send(rpc::notification(m, p));
        })));
        inner.scan = Some(shared.clone());
        drop(inner);
        let views = (mode == ScanMode::Step).then(|| spec.step_views());
        self.emit("scan.state", json!({"name": name, "status": "running", "mode": mode.name(), "views_planned": views}));
        tracing::info!(scan = %name, mode = mode.name(), step_deg, total_deg, "scan started");
        let daemon = self.clone();
        let settings = pipeline_settings(&self.config);
        tokio::task::spawn_blocking(move || {
            let _span = tracing::info_span!("scan", name = %shared.spec.name).entered();
            let end = scan::run(&mut devices, shared.clone(), &settings);
            daemon.scan_finished(devices, &shared, end);
        });
        Ok(json!({"name": name, "dir": dir, "mode": mode.name(), "step_deg": (mode == ScanMode::Step).then_some(step_deg), "total_deg": total_deg, "views_planned": views}))
    }

    fn scan_finished(&self, devices: Devices, shared: &ScanShared, end: ScanEnd) {
        let name = shared.spec.name.clone();
        match end.status {
            "complete" => tracing::info!(scan = %name, "scan complete"),
            s => tracing::warn!(scan = %name, status = s, reason = end.reason.as_deref().unwrap_or(""), "scan ended"),
        }
        let mut inner = self.inner.lock().unwrap();
        let device_failed = end.status == "failed" && end.reason.as_deref().is_some_and(|r| r.contains("camera") || r.contains("turntable"));
        if device_failed {
            let why = end.reason.clone().unwrap_or_default();
            self.emit("device.error", json!({"message": why, "scan": name}));
            inner.device_error = Some(why);
            // Reopened at the next scan.start.
            drop(devices);
        } else {
            inner.devices = Some(devices);
        }
        inner.scan = None;
        inner.last = Some((name.clone(), end.clone()));
        drop(inner);
        let mut state = json!({"name": name, "status": end.status, "reason": end.reason});
        state["progress"] = shared.progress();
        self.emit("scan.state", state);
        self.scan_ended.notify_waiters();
    }

    /// `scan.stop`: the running scan finishes its current view and ends `interrupted`.
    pub fn stop_scan(&self, why: &str) -> Result<Value, RpcError> {
        match self.current_scan() {
            Some(s) => {
                s.request_stop(why);
                Ok(json!({"name": s.spec.name, "stopping": true}))
            }
            None => Err(RpcError::new(code::NOT_FOUND, "no scan is running")),
        }
    }

    /// Waits until no scan runs (graceful shutdown).
    pub async fn wait_idle(&self) {
        loop {
            let ended = self.scan_ended.notified();
            if self.current_scan().is_none() {
                return;
            }
            ended.await;
        }
    }

    pub fn list_scans(&self) -> Value {
        let running = self.current_scan().map(|s| s.spec.name.clone());
        let list: Vec<Value> = list_manifests(&self.config.daemon.state_dir)
            .into_iter()
            .map(|(name, m)| {
                let mut e = json!({"name": name, "status": m["status"], "frames": m["frames"], "mode": m["mode"], "reason": m["reason"]});
                if running.as_deref() == Some(name.as_str()) {
                    e["running"] = json!(true);
                }
                e
            })
            .collect();
        json!({"scans": list})
    }

    pub fn get_scan(&self, req: &Request) -> Result<Value, RpcError> {
        let p = Params::new(req, &["name"])?;
        let name = p.str("name")?.ok_or_else(|| RpcError::params("scan.get: `name` is required"))?;
        validate_name(name).map_err(RpcError::params)?;
        let dir = self.config.daemon.state_dir.join(name);
        if !dir.is_dir() {
            return Err(RpcError::new(code::NOT_FOUND, format!("no scan named {name} in {}", self.config.daemon.state_dir.display())));
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
    fn names_cannot_escape_the_state_folder() {
        for good in ["bunny", "vase-2026.11.22", "a_1"] {
            assert!(validate_name(good).is_ok(), "{good}");
        }
        for bad in ["", "..", ".", "../etc", "a/b", "-rf", ".hidden", "a b", &"x".repeat(65)] {
            assert!(validate_name(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn control_is_for_root_the_daemon_and_the_group() {
        let dir = std::env::temp_dir().join(format!("spinscan-auth-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("group"), "root:x:0:\nspinscan:x:1500:alice,bob\nother:x:1600:\n").unwrap();
        std::fs::write(dir.join("passwd"), "alice:x:2001:100::/:/bin/sh\ncarol:x:2003:1500::/:/bin/sh\nmallory:x:2004:1600::/:/bin/sh\n").unwrap();
        let auth = Auth::from_files("spinscan", &dir.join("group"), &dir.join("passwd")).unwrap();
        assert!(auth.may_control(0, 0), "root");
        assert!(auth.may_control(auth.daemon_uid, 12345), "the daemon's user");
        assert!(auth.may_control(2001, 100), "a listed member");
        assert!(auth.may_control(2003, 1500), "primary group");
        assert!(auth.may_control(2222, 1500), "peer gid is the group");
        if auth.daemon_uid != 2004 {
            assert!(!auth.may_control(2004, 1600), "not in the group");
        }
        let e = Auth::from_files("nosuch", &dir.join("group"), &dir.join("passwd")).unwrap_err();
        assert!(e.contains("nosuch") && e.contains("groupadd"), "{e}");
        let none = Auth::from_files("", &dir.join("group"), &dir.join("passwd")).unwrap();
        if none.daemon_uid != 2001 {
            assert!(!none.may_control(2001, 1500));
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

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
