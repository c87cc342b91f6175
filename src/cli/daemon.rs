//! The `spinscan` subcommands that talk to `spinscand`: status, devices, scan, scans — over
//! the typed client of [`spinscan::control`].

use std::io::{IsTerminal, Write};
use std::path::PathBuf;

use clap::{Args, Subcommand};
use serde_json::{json, Value};

use super::exit::DAEMON as EXIT_DAEMON;
use super::Failure;
use spinscan::control::client::{Client, ClientError};
use spinscan::control::ScanStartParams;

#[derive(Args, Clone)]
pub struct SocketArg {
    /// spinscand's control socket.
    #[arg(long, value_name = "PATH", env = "SPINSCAN_SOCKET", default_value = "/run/spinscan/control.sock")]
    pub socket: PathBuf,
    /// Print the daemon's JSON answer instead of text.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args)]
pub struct DevicesArgs {
    /// List this machine's V4L2 devices and serial ports without asking the daemon.
    #[arg(long)]
    pub local: bool,
    /// With --local: check the `[cameras]` of this spinscand config against what the
    /// cameras offer (format, size, rate).
    #[arg(long, requires = "local", value_name = "FILE")]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub socket: SocketArg,
}

#[derive(Subcommand)]
pub enum ScanCommand {
    /// Starts a scan named NAME (its folder in the daemon's state directory).
    Start(ScanStartArgs),
    /// Stops the running scan after its current view (it ends `interrupted`).
    Stop(SocketArg),
    /// Writes a preview mesh of the running scan's views fused so far (`mesh_live.ply` in
    /// its folder); the scan's own `mesh.ply` is written when it ends.
    Mesh(SocketArg),
    /// One scan's manifest (status, frames, why it ended).
    Get {
        name: String,
        #[command(flatten)]
        socket: SocketArg,
    },
}

#[derive(Args)]
pub struct ScanStartArgs {
    /// Scan name: letters, digits, '-', '_', '.'.
    pub name: String,
    /// Step-and-shoot with this step, degrees (default: the daemon's scan.step_deg).
    #[arg(long, conflicts_with = "continuous")]
    pub step_deg: Option<f64>,
    /// Continuous rotation while the cameras run at their frame rate.
    #[arg(long)]
    pub continuous: bool,
    /// How far to turn, degrees (default: the daemon's scan.total_deg, 360).
    #[arg(long)]
    pub total_deg: Option<f64>,
    /// Rotation speed of a continuous scan, degrees per second (default:
    /// turntable.continuous_deg_s).
    #[arg(long)]
    pub speed_deg_s: Option<f64>,
    /// Stop after this many views.
    #[arg(long)]
    pub max_views: Option<u64>,
    /// Follow the scan with a progress bar until it ends (Ctrl-C stops watching, not the
    /// scan).
    #[arg(long)]
    pub watch: bool,
    #[command(flatten)]
    pub socket: SocketArg,
}

pub(super) fn daemon_err(e: ClientError) -> Failure {
    Failure { code: EXIT_DAEMON, message: e.to_string() }
}

pub(super) fn connect(s: &SocketArg) -> Result<Client, Failure> {
    Client::connect(&s.socket).map_err(daemon_err)
}

fn print_json(v: &Value) {
    println!("{}", serde_json::to_string_pretty(v).unwrap());
}

pub fn status(s: SocketArg) -> Result<(), Failure> {
    let mut c = connect(&s)?;
    let v = c.status().map_err(daemon_err)?;
    if s.json {
        print_json(&v);
        return Ok(());
    }
    println!("spinscand {} (protocol {}), backend {}, up {:.0} s, {:.0} MiB", v["version"].as_str().unwrap_or("?"), v["protocol"], v["backend"].as_str().unwrap_or("?"), v["uptime_s"].as_f64().unwrap_or(0.0), v["rss_mib"].as_f64().unwrap_or(0.0));
    match v["scan"].as_object() {
        Some(p) => println!("scanning {}: {} views, {} captured, {:.1} fps, {} drops, table {:.1}°", p["name"].as_str().unwrap_or("?"), p["views"], p["captured"], p["fps"].as_f64().unwrap_or(0.0), p["drops"], p["table_deg"].as_f64().unwrap_or(0.0)),
        None => println!("idle"),
    }
    if let Some(l) = v["last_scan"].as_object() {
        println!("last scan {}: {}{}", l["name"].as_str().unwrap_or("?"), l["status"].as_str().unwrap_or("?"), l["reason"].as_str().map(|r| format!(" ({r})")).unwrap_or_default());
    }
    if let Some(e) = v["device_error"].as_str() {
        println!("devices: {e}");
    }
    Ok(())
}

pub fn devices(a: DevicesArgs) -> Result<(), Failure> {
    let v = if a.local {
        let mut v = spinscan::hw::v4l2::list_devices();
        if let Some(path) = &a.config {
            let config = spinscan::daemon::config::Config::load(path).map_err(|e| Failure { code: super::exit::INPUT, message: e.to_string() })?;
            let c = &config.cameras;
            v["warnings"] = json!(spinscan::hw::v4l2::check_offered(&v, &[&c.left, &c.right], c.fourcc(), c.width, c.height, c.fps));
        }
        v
    } else {
        let mut c = connect(&a.socket)?;
        c.devices().map_err(daemon_err)?
    };
    if a.socket.json {
        print_json(&v);
        return Ok(());
    }
    if !a.local {
        println!("backend {}: {}", v["backend"].as_str().unwrap_or("?"), v["source"].as_str().unwrap_or("(in use by a scan)"));
        println!("configured cameras: left {} right {}, {}x{} {} @ {} fps", v["cameras"]["left"].as_str().unwrap_or("?"), v["cameras"]["right"].as_str().unwrap_or("?"), v["cameras"]["width"], v["cameras"]["height"], v["cameras"]["pixel_format"].as_str().unwrap_or("?"), v["cameras"]["fps"]);
        println!("turntable: {}", v["turntable"]);
    }
    let listing = if a.local { &v } else { &v["present"] };
    if let Some(cams) = listing["cameras"].as_array() {
        println!("V4L2 devices:{}", if cams.is_empty() { " none" } else { "" });
        for cam in cams {
            println!("  {} {}{}", cam["path"].as_str().unwrap_or("?"), cam["card"].as_str().or(cam["name"].as_str()).unwrap_or(""), cam["error"].as_str().map(|e| format!(" ({e})")).unwrap_or_default());
            for f in cam["formats"].as_array().into_iter().flatten() {
                // Each size with the rates it runs at: 640x480@30/15.
                let sizes: Vec<String> = f["sizes"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|s| s.as_str())
                    .map(|s| match f["rates"][s].as_array().filter(|r| !r.is_empty()) {
                        Some(r) => format!("{s}@{}", r.iter().filter_map(|v| v.as_f64()).map(|v| format!("{v}")).collect::<Vec<_>>().join("/")),
                        None => s.to_string(),
                    })
                    .collect();
                println!("    {} {}: {}", f["fourcc"].as_str().unwrap_or("?"), f["description"].as_str().unwrap_or(""), sizes.join(" "));
            }
        }
    }
    for w in v["warnings"].as_array().into_iter().flatten().filter_map(|w| w.as_str()) {
        println!("warning: the configured cameras: {w}");
    }
    if let Some(ports) = listing["serial_ports"].as_array() {
        println!("serial ports:{}", if ports.is_empty() { " none" } else { "" });
        for p in ports {
            println!("  {} {}", p["path"].as_str().or(p["error"].as_str()).unwrap_or("?"), p["kind"].as_str().unwrap_or(""));
        }
    }
    Ok(())
}

pub fn scan(cmd: ScanCommand) -> Result<(), Failure> {
    match cmd {
        ScanCommand::Start(a) => start(a),
        ScanCommand::Stop(s) => {
            let mut c = connect(&s)?;
            let v = c.scan_stop().map_err(daemon_err)?;
            if s.json {
                print_json(&json!(v));
            } else {
                println!("stopping {} after its current view", v.name);
            }
            Ok(())
        }
        ScanCommand::Mesh(s) => {
            let mut c = connect(&s)?;
            let v = c.scan_mesh().map_err(daemon_err)?;
            if s.json {
                print_json(&json!(v));
            } else {
                println!("{}: the mesh of the views fused so far is being written to {} (a scan.mesh event says when)", v.name, v.file);
            }
            Ok(())
        }
        ScanCommand::Get { name, socket } => {
            let mut c = connect(&socket)?;
            let v = c.scan_get(&name).map_err(daemon_err)?;
            print_json(&v);
            Ok(())
        }
    }
}

pub fn scans(s: SocketArg) -> Result<(), Failure> {
    let mut c = connect(&s)?;
    let list = c.scan_list().map_err(daemon_err)?;
    if s.json {
        print_json(&json!(list));
        return Ok(());
    }
    if list.scans.is_empty() {
        println!("no scans");
    }
    for e in list.scans {
        println!(
            "{:<24} {:<11} {:>5} views  {}{}",
            e.name,
            e.status.as_str().unwrap_or("?"),
            e.frames.as_u64().map_or("?".into(), |n| n.to_string()),
            e.mode.as_str().unwrap_or(""),
            e.reason.as_str().map(|r| format!("  ({r})")).unwrap_or_default()
        );
    }
    Ok(())
}

fn start(a: ScanStartArgs) -> Result<(), Failure> {
    let mut c = connect(&a.socket)?;
    if a.watch {
        // Subscribe first so no event of this scan is missed.
        c.subscribe().map_err(daemon_err)?;
    }
    let params = ScanStartParams {
        name: a.name.clone(),
        mode: Some(if a.continuous { "continuous" } else { "step" }.into()),
        step_deg: a.step_deg,
        total_deg: a.total_deg,
        speed_deg_s: a.speed_deg_s,
        max_views: a.max_views,
    };
    let started = c.scan_start(&params).map_err(daemon_err)?;
    if a.socket.json && !a.watch {
        print_json(&json!(started));
        return Ok(());
    }
    eprintln!("scan {} started: {} mode, {} views planned, folder {}", a.name, started.mode, started.views_planned.map_or("(continuous)".into(), |n| n.to_string()), started.dir.display());
    if !a.watch {
        return Ok(());
    }
    c.set_timeout(None).map_err(daemon_err)?;
    let planned = started.views_planned.map(|n| n as u64);
    let total_deg = started.total_deg;
    let tty = std::io::stderr().is_terminal();
    let mut start_deg: Option<f64> = None;
    let mut last_line = String::new();
    loop {
        let n = c.next_notification().map_err(daemon_err)?;
        let p = &n.params;
        if p["name"].as_str() != Some(a.name.as_str()) {
            continue;
        }
        match n.method.as_str() {
            "scan.progress" => {
                let views = p["views"].as_u64().unwrap_or(0);
                let deg = p["table_deg"].as_f64().unwrap_or(0.0);
                let s0 = *start_deg.get_or_insert(deg);
                let fraction = match planned {
                    Some(n) if n > 0 => views as f64 / n as f64,
                    _ => ((deg - s0) / total_deg).clamp(0.0, 1.0),
                };
                let filled = (fraction * 30.0).round() as usize;
                let line = format!(
                    "{} [{}{}] {}{} views  {:.1} fps  {} drops  table {:.1}°",
                    a.name,
                    "#".repeat(filled.min(30)),
                    "-".repeat(30 - filled.min(30)),
                    views,
                    planned.map(|n| format!("/{n}")).unwrap_or_default(),
                    p["fps"].as_f64().unwrap_or(0.0),
                    p["drops"],
                    deg
                );
                if tty {
                    eprint!("\r{line}\x1b[K");
                    let _ = std::io::stderr().flush();
                } else if line != last_line {
                    eprintln!("{line}");
                }
                last_line = line;
            }
            "scan.state" if p["status"] != "running" => {
                if tty {
                    eprintln!();
                }
                let status = p["status"].as_str().unwrap_or("?");
                let reason = p["reason"].as_str().map(|r| format!(": {r}")).unwrap_or_default();
                if a.socket.json {
                    print_json(p);
                } else {
                    println!("scan {} {status}{reason}; {} views, {} drops", a.name, p["progress"]["views"], p["progress"]["drops"]);
                }
                return match status {
                    "complete" => Ok(()),
                    "interrupted" => Err(Failure { code: EXIT_DAEMON, message: format!("scan {} interrupted{reason}", a.name) }),
                    _ => Err(Failure { code: EXIT_DAEMON, message: format!("scan {} {status}{reason}", a.name) }),
                };
            }
            "device.error" => eprintln!("\ndevice error: {}", p["message"].as_str().unwrap_or("?")),
            _ => {}
        }
    }
}
