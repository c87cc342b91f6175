//! `cargo bench --bench daemon [-- status|rss|peak] [--clients N] [--scans N]`: the real
//! `spinscand` (release build, simulated lab at 640×480) measured as a service.
//!
//! - `status`: `status` round-trip latency (p50, p99, max) from N clients (default 50), every
//!   one subscribed to events and asking every 20 ms, while a 2° step scan runs.
//! - `rss`: the daemon's resident memory after each of N repeated 45-view step scans
//!   (default 20), idle between scans; prints the series and the last scan's RSS against the
//!   second's (the service must stay flat over months of scans).
//! - `peak`: the daemon's peak resident memory (`VmHWM`) through a 180-view step scan and
//!   through a continuous 360° scan at 6°/s with the cameras at 15 fps in real time (≈ 900
//!   pairs), each on a fresh daemon.
//!
//! Both start their own daemon on a temporary socket and state folder.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use spinscan::control::client::Client;
use spinscan::control::ScanStartParams;

struct Daemon {
    child: Child,
    socket: PathBuf,
}

impl Daemon {
    /// The simulated lab at 640×480 (the shipped `config/sim.toml`), paced in real time or not.
    fn start(dir: &Path, realtime: bool) -> Daemon {
        let _ = std::fs::remove_dir_all(dir);
        std::fs::create_dir_all(dir).unwrap();
        let socket = dir.join("s.sock");
        let text = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("config/sim.toml"))
            .unwrap()
            .replace("socket = \"spinscan.sock\"", &format!("socket = {:?}", socket.display().to_string()))
            .replace("state_dir = \"scans\"", &format!("state_dir = {:?}", dir.join("scans").display().to_string()))
            .replace("max_clients = 32 ", "max_clients = 128 ")
            .replace("realtime = true", &format!("realtime = {realtime}"))
            .replace("settle_ms = 100 ", "settle_ms = 5 ");
        let config = dir.join("spinscand.toml");
        std::fs::write(&config, text).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_spinscand"))
            .arg("--config")
            .arg(&config)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("daemon.log")).unwrap())
            .spawn()
            .expect("start spinscand");
        let t0 = Instant::now();
        while Client::connect(&socket).is_err() {
            assert!(t0.elapsed() < Duration::from_secs(30), "spinscand did not open its socket (see {})", dir.join("daemon.log").display());
            std::thread::sleep(Duration::from_millis(20));
        }
        Daemon { child, socket }
    }

    fn rss_mib(&self) -> f64 {
        self.memory_mib("VmRSS:")
    }

    /// A memory figure of `/proc/PID/status` (`VmRSS:`, `VmHWM:` …), MiB.
    fn memory_mib(&self, key: &str) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        let kb: f64 = status.lines().find_map(|l| l.strip_prefix(key)).and_then(|v| v.split_whitespace().next()).and_then(|v| v.parse().ok()).unwrap();
        kb / 1024.0
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn start_scan(c: &mut Client, name: &str, step_deg: f64) {
    let params = ScanStartParams { name: name.into(), mode: Some("step".into()), step_deg: Some(step_deg), total_deg: Some(360.0), speed_deg_s: None, max_views: None };
    c.scan_start(&params).unwrap_or_else(|e| panic!("scan.start {name}: {e}"));
}

fn start_continuous(c: &mut Client, name: &str, speed_deg_s: f64) {
    let params = ScanStartParams { name: name.into(), mode: Some("continuous".into()), step_deg: None, total_deg: Some(360.0), speed_deg_s: Some(speed_deg_s), max_views: None };
    c.scan_start(&params).unwrap_or_else(|e| panic!("scan.start {name}: {e}"));
}

/// Waits for `name` to end; returns its final status.
fn wait_end(c: &mut Client, name: &str) -> String {
    wait_end_progress(c, name).0
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn status_latency(dir: &Path, clients: usize) {
    let d = Daemon::start(dir, false);
    let mut ctl = Client::connect(&d.socket).unwrap();
    ctl.set_timeout(Some(Duration::from_secs(600))).unwrap();
    ctl.subscribe().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let threads: Vec<_> = (0..clients)
        .map(|_| {
            let (socket, stop) = (d.socket.clone(), stop.clone());
            std::thread::spawn(move || {
                let mut c = Client::connect(&socket).unwrap();
                c.subscribe().unwrap();
                let mut times = Vec::new();
                while !stop.load(Ordering::Relaxed) {
                    let t0 = Instant::now();
                    c.status().expect("status");
                    times.push(t0.elapsed().as_secs_f64() * 1e3);
                    std::thread::sleep(Duration::from_millis(20));
                }
                times
            })
        })
        .collect();
    let t0 = Instant::now();
    start_scan(&mut ctl, "latency", 2.0);
    let end = wait_end(&mut ctl, "latency");
    let scan_s = t0.elapsed().as_secs_f64();
    stop.store(true, Ordering::Relaxed);
    let mut all: Vec<f64> = threads.into_iter().flat_map(|t| t.join().unwrap()).collect();
    all.sort_by(f64::total_cmp);
    println!(
        "status latency, {clients} subscribed clients during a 2° step scan at 640×480 ({end}, {scan_s:.1} s): {} calls, p50 {:.3} ms, p99 {:.3} ms, max {:.3} ms",
        all.len(),
        quantile(&all, 0.5),
        quantile(&all, 0.99),
        all.last().copied().unwrap_or(f64::NAN)
    );
}

fn repeated_scans(dir: &Path, scans: usize) {
    let d = Daemon::start(dir, false);
    let mut c = Client::connect(&d.socket).unwrap();
    c.set_timeout(Some(Duration::from_secs(600))).unwrap();
    c.subscribe().unwrap();
    println!("RSS of an idle daemon: {:.1} MiB", d.rss_mib());
    let mut series = Vec::new();
    for i in 0..scans {
        let name = format!("repeat-{i}");
        let t0 = Instant::now();
        start_scan(&mut c, &name, 8.0);
        let end = wait_end(&mut c, &name);
        // The daemon trims its heap right after the scan ends.
        std::thread::sleep(Duration::from_millis(500));
        let rss = d.rss_mib();
        println!("scan {:>2}: {end}, {:.1} s, RSS after {rss:.1} MiB", i + 1, t0.elapsed().as_secs_f64());
        series.push(rss);
    }
    if series.len() >= 2 {
        let (second, last) = (series[1], series[series.len() - 1]);
        println!("RSS series (MiB): {}", series.iter().map(|v| format!("{v:.1}")).collect::<Vec<_>>().join(", "));
        println!("last / second = {:.3} (flat: within 1.10); highest {:.1} MiB", last / second, series.iter().cloned().fold(f64::MIN, f64::max));
    }
}

/// Waits for `name` to end; returns its final status and progress.
fn wait_end_progress(c: &mut Client, name: &str) -> (String, serde_json::Value) {
    loop {
        let n = c.next_notification().expect("events");
        if n.method == "scan.state" && n.params["name"] == name && n.params["status"] != "running" {
            return (n.params["status"].as_str().unwrap_or("?").to_string(), n.params["progress"].clone());
        }
    }
}

fn peak_memory(dir: &Path) {
    for (name, realtime) in [("step-2deg", false), ("continuous-15fps", true)] {
        let d = Daemon::start(&dir.join(name), realtime);
        let mut c = Client::connect(&d.socket).unwrap();
        c.set_timeout(Some(Duration::from_secs(600))).unwrap();
        c.subscribe().unwrap();
        let t0 = Instant::now();
        if realtime {
            start_continuous(&mut c, name, 6.0);
        } else {
            start_scan(&mut c, name, 2.0);
        }
        let (end, progress) = wait_end_progress(&mut c, name);
        println!(
            "{name}: {end} in {:.0} s, views {}, drops {}; peak RSS {:.1} MiB, RSS after {:.1} MiB",
            t0.elapsed().as_secs_f64(),
            progress["views"],
            progress["drops"],
            d.memory_mib("VmHWM:"),
            d.rss_mib()
        );
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |flag: &str, default: usize| args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).map_or(default, |v| v.parse().expect("a number"));
    let which: Vec<&str> = args.iter().map(String::as_str).filter(|a| ["status", "rss", "peak"].contains(a)).collect();
    let all = which.is_empty();
    let base = std::env::temp_dir().join(format!("spinscan-bench-daemon-{}", std::process::id()));
    if all || which.contains(&"status") {
        status_latency(&base.join("status"), value("--clients", 50));
    }
    if all || which.contains(&"rss") {
        repeated_scans(&base.join("rss"), value("--scans", 20));
    }
    if all || which.contains(&"peak") {
        peak_memory(&base.join("peak"));
    }
    let _ = std::fs::remove_dir_all(&base);
}
