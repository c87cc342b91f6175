//! The real `spinscand` binary in sim mode on a temporary socket, driven through the socket
//! by a bare client written from the protocol doc (and by the `spinscan` CLI): full step and
//! continuous scans, events, errors, signals and crash recovery. Its hardening against
//! hostile values, clients, disks and second daemons: `tests/daemon_hardening.rs`.

mod support;

use std::process::Command;
use std::time::Duration;

use serde_json::{json, Value};
use support::daemon::{jsonl, manifest, Client, Daemon};

#[test]
fn a_full_step_turn_through_the_socket() {
    let dir = support::temp_dir("daemon-step");
    let d = Daemon::start(&dir, "");
    let (mut c, hello) = Client::connect(&d.socket);
    assert_eq!(hello["method"], "hello");
    assert_eq!(hello["params"]["protocol"], 1);
    assert!(hello["params"]["version"].is_string());
    assert_eq!(hello["params"]["may_control"], true);
    let status = c.ok("status", json!({}));
    assert_eq!((status["state"].as_str(), status["backend"].as_str()), (Some("idle"), Some("sim")));
    let devices = c.ok("devices", json!({}));
    assert_eq!(devices["turntable"]["state"], "idle");
    c.ok("events.subscribe", json!({}));

    let started = c.ok("scan.start", json!({"name": "torus-step", "mode": "step", "step_deg": 45}));
    assert_eq!(started["views_planned"], 8);
    // A second scan while one runs is refused.
    let (code, msg) = c.error_code("scan.start", json!({"name": "other"}));
    assert_eq!(code, -32000, "{msg}");
    // A preview mesh of the views fused so far, on request, once a few are registered.
    loop {
        let v = c.line();
        c.events.push(v.clone());
        if v["method"] == "scan.progress" && v["params"]["registered"].as_u64().unwrap() >= 3 {
            break;
        }
    }
    let meshing = c.ok("scan.mesh", json!({}));
    assert_eq!(meshing["name"], "torus-step");
    let end = c.until_end("torus-step");
    assert_eq!(end["status"], "complete", "{end}");
    assert_eq!(end["progress"]["views"], 8);
    assert_eq!(end["progress"]["drops"], 0);
    // Where a view's time went: every stage each view goes through took some.
    let stages = end["progress"]["stage_ms"].as_object().unwrap();
    assert_eq!(stages.keys().collect::<Vec<_>>(), ["assist", "match", "prepare", "register", "triangulate", "write"], "{stages:?}");
    for st in ["prepare", "match", "triangulate", "write", "register"] {
        assert!(stages[st].as_f64().is_some_and(|ms| ms > 0.0), "{st}: {stages:?}");
    }

    // Events: running first, progress with growing view counts and the table's angle.
    let states: Vec<&Value> = c.events.iter().filter(|e| e["method"] == "scan.state").collect();
    assert_eq!(states[0]["params"]["status"], "running");
    let views: Vec<u64> = c.events.iter().filter(|e| e["method"] == "scan.progress").map(|e| e["params"]["views"].as_u64().unwrap()).collect();
    assert!(!views.is_empty() && views.windows(2).all(|w| w[0] <= w[1]), "{views:?}");
    assert!(c.events.iter().any(|e| e["method"] == "scan.progress" && e["params"]["table_deg"].as_f64().unwrap() > 300.0));

    // The folder: recording (8 pairs at 0, 45, … 315°), results, manifest.
    let scan = d.state.join("torus-step");
    let m = manifest(&scan);
    assert_eq!((m["status"].as_str(), m["frames"].as_u64(), m["mode"].as_str()), (Some("complete"), Some(8), Some("step")));
    let frames = jsonl(&scan.join("frames.jsonl"));
    let angles: Vec<f64> = frames.iter().map(|f| f["table_deg"].as_f64().unwrap()).collect();
    for (i, a) in angles.iter().enumerate() {
        assert!((a - 45.0 * i as f64).abs() < 0.01, "{angles:?}");
    }
    assert_eq!(jsonl(&scan.join("poses.jsonl")).len(), 8);
    for f in ["model.ply", "report.json", "calib.yaml", "left/000007.png", "views/000007.ply", "disparity/000007.png"] {
        assert!(scan.join(f).is_file(), "{f} missing");
    }
    let report: Value = serde_json::from_str(&std::fs::read_to_string(scan.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["registration"]["views"], 8);
    // The first pair was probed for the object's disparities; the range set (0 … 31) holds them.
    let m = &report["matching"];
    assert_eq!((m["min_disparity"].as_i64(), m["num_disparities"].as_u64(), m["range_fit"]["widened"].as_bool()), (Some(0), Some(32), Some(false)), "{m}");
    // The preview came as asked (announced, written where the answer said), and the scan's
    // own mesh at its end.
    let preview = c.events.iter().find(|e| e["method"] == "scan.mesh").unwrap_or_else(|| panic!("no scan.mesh event: {:?}", c.events));
    assert!(preview["params"].get("error").is_none() && preview["params"]["views"].as_u64().unwrap() >= 1, "{preview}");
    // A request that reaches the scan after its last view is answered by the scan's own
    // mesh.ply (docs/protocol.md); a loaded machine can make that happen.
    let file = preview["params"]["file"].as_str().unwrap();
    let own = scan.join("mesh.ply").display().to_string();
    assert!(file == meshing["file"] || file == own, "{preview} after {meshing}");
    let live = spinscan::io::ply::read_ply(std::path::Path::new(file)).unwrap();
    assert_eq!(live.triangles.len() as u64, preview["params"]["triangles"].as_u64().unwrap());
    assert!(!live.triangles.is_empty());
    assert!(scan.join("mesh.ply").is_file());
    assert_eq!(report["registration"]["mesh"]["non_manifold_edges"], 0, "{}", report["registration"]["mesh"]);
    // The recording replays.
    let rec = spinscan::recording::Recording::open(&scan).unwrap();
    assert_eq!(rec.frames.len(), 8);

    let got = c.ok("scan.get", json!({"name": "torus-step"}));
    assert_eq!(got["status"], "complete");
    let list = c.ok("scan.list", json!({}));
    assert_eq!(list["scans"][0]["name"], "torus-step");
    // The name is taken now.
    assert_eq!(c.error_code("scan.start", json!({"name": "torus-step"})).0, -32004);
}

/// A range short of the object (the first 16 disparities; the torus lies at about 20–25):
/// the scan widens it from its first pair, says so, and its views hold the object; with
/// `fit_range = false` it searches the 16 as written and its views come out all but empty.
/// Either way the first pair's probe compares the cameras' contrast (the simulated lab's
/// are alike: nothing scaled).
#[test]
fn a_scan_widens_a_range_short_of_the_object() {
    let points = |fit: bool| -> (Value, u64) {
        let dir = support::temp_dir(&format!("daemon-range-{fit}"));
        let config = support::daemon::small_config(&dir, "");
        let text = std::fs::read_to_string(&config).unwrap().replace("num_disparities = 32", &format!("num_disparities = 16\nfit_range = {fit}"));
        std::fs::write(&config, text).unwrap();
        let d = Daemon::start_config(&dir, &config, &[]);
        let (mut c, _) = Client::connect(&d.socket);
        c.ok("events.subscribe", json!({}));
        c.ok("scan.start", json!({"name": "near", "mode": "step", "step_deg": 90}));
        assert_eq!(c.until_end("near")["status"], "complete");
        let report: Value = serde_json::from_str(&std::fs::read_to_string(d.state.join("near/report.json")).unwrap()).unwrap();
        (report["matching"].clone(), report["frames"].as_array().unwrap().iter().map(|f| f["points"].as_u64().unwrap()).sum())
    };
    let (m, widened) = points(true);
    assert_eq!(m["range_fit"]["widened"], true, "{m}");
    let (min, n, far) = (m["min_disparity"].as_i64().unwrap(), m["num_disparities"].as_i64().unwrap(), m["range_fit"]["object_disparities"][1].as_f64().unwrap());
    assert!(min == 0 && (min + n - 1) as f64 >= far + 16.0 && far > 16.0, "{m}");
    let (m2, kept) = points(false);
    assert!(m2.get("range_fit").is_none() && m2["num_disparities"] == 16, "{m2}");
    for c in [&m["contrast"], &m2["contrast"]] {
        assert!(c["ratio"].as_f64().is_some_and(|r| (r - 1.0).abs() < 0.05) && c["right_scaled"] == false && c["matched_px"].as_u64() > Some(500), "{c}");
    }
    assert!(kept * 10 < widened, "{kept} points over 0 … 15 against {widened} widened");
}

#[test]
fn a_continuous_scan_records_every_pair_and_accounts_for_drops() {
    let dir = support::temp_dir("daemon-cont");
    // One matcher and a queue of one: the pool falls behind and drops.
    let d = Daemon::start(&dir, "queue_depth = 1\nmatcher_threads = 1\n");
    let (mut c, _) = Client::connect(&d.socket);
    c.ok("events.subscribe", json!({}));
    // A slow turn (18 s of simulated time, ≈ 0.4 s here), so that even a loaded machine
    // renders well over ten pairs during it.
    let started = c.ok("scan.start", json!({"name": "spin", "mode": "continuous", "total_deg": 90, "speed_deg_s": 5}));
    assert_eq!(started["mode"], "continuous");
    let end = c.until_end("spin");
    assert_eq!(end["status"], "complete", "{end}");
    let p = &end["progress"];
    let (captured, views, drops, failed) = (p["captured"].as_u64().unwrap(), p["views"].as_u64().unwrap(), p["drops"].as_u64().unwrap(), p["failed"].as_u64().unwrap());
    assert!(captured >= 10, "{p}");
    assert_eq!(p["recorded"].as_u64().unwrap(), captured, "every captured pair is recorded");
    assert_eq!(views + drops + failed, captured, "{p}");
    let scan = d.state.join("spin");
    let frames = jsonl(&scan.join("frames.jsonl"));
    assert_eq!(frames.len() as u64, captured);
    // The table turned during capture, within the requested arc.
    let angles: Vec<f64> = frames.iter().map(|f| f["table_deg"].as_f64().unwrap()).collect();
    assert!(angles.windows(2).all(|w| w[1] >= w[0] - 1e-9), "{angles:?}");
    assert!(*angles.last().unwrap() > 45.0 && *angles.last().unwrap() <= 90.0 + 1e-6, "{angles:?}");
    let report: Value = serde_json::from_str(&std::fs::read_to_string(scan.join("report.json")).unwrap()).unwrap();
    assert_eq!(report["frames"].as_array().unwrap().len() as u64, views);
    let skipped = report["skipped"].as_array().map_or(0, |s| s.len()) as u64;
    assert_eq!(skipped, drops + failed);
    assert_eq!(manifest(&scan)["status"], "complete");
    // The table is stopped and idle again.
    let devices = c.ok("devices", json!({}));
    assert_eq!(devices["turntable"]["state"], "idle", "{devices}");
}

#[test]
fn bad_requests_get_json_rpc_errors_and_the_connection_survives() {
    let dir = support::temp_dir("daemon-errors");
    let d = Daemon::start(&dir, "");
    let (mut c, _) = Client::connect(&d.socket);
    c.send_raw("this is not json\n");
    let v = c.line();
    assert_eq!((v["error"]["code"].as_i64(), &v["id"]), (Some(-32700), &Value::Null));
    c.send_raw("{\"jsonrpc\": \"2.0\", \"method\": \"status\", \"id\": {}}\n");
    assert_eq!(c.line()["error"]["code"], -32600);
    assert_eq!(c.error_code("scan.explode", json!({})).0, -32601);
    let (code, msg) = c.error_code("scan.start", json!({"name": "../../etc"}));
    assert_eq!(code, -32602);
    assert!(msg.contains("not allowed"), "{msg}");
    let (code, msg) = c.error_code("scan.start", json!({"name": "ok", "mode": "sideways"}));
    assert!(code == -32602 && msg.contains("continuous"), "{msg}");
    let (code, msg) = c.error_code("scan.start", json!({"name": "ok", "step_deg": -3}));
    assert!(code == -32602 && msg.contains("step_deg"), "{msg}");
    let (code, msg) = c.error_code("scan.start", json!({"name": "ok", "stepdeg": 3}));
    assert!(code == -32602 && msg.contains("stepdeg"), "{msg}");
    assert_eq!(c.error_code("scan.start", json!({})).0, -32602);
    assert_eq!(c.error_code("scan.stop", json!({})).0, -32001);
    assert_eq!(c.error_code("scan.mesh", json!({})).0, -32001);
    assert_eq!(c.error_code("scan.get", json!({"name": "nothing"})).0, -32001);
    // A line over the limit (64 KiB by default) is refused, and the next one is answered.
    let long = format!("{{\"jsonrpc\": \"2.0\", \"id\": 1, \"method\": \"status\", \"params\": {{\"pad\": \"{}\"}}}}\n", "x".repeat(70_000));
    c.send_raw(&long);
    let v = c.line();
    assert_eq!(v["error"]["code"], -32600);
    assert!(v["error"]["message"].as_str().unwrap().contains("longer than"), "{v}");
    assert_eq!(c.ok("status", json!({}))["state"], "idle");
    // A notification (no id) is not answered: the next line is the status answer.
    c.send_raw("{\"jsonrpc\": \"2.0\", \"method\": \"status\"}\n");
    assert_eq!(c.ok("status", json!({}))["state"], "idle");
    // (The state folder holds the daemon's lock file, `.spinscand.lock`.)
    assert!(d.state.is_dir() && std::fs::read_dir(&d.state).unwrap().flatten().all(|e| e.file_name().to_string_lossy().starts_with('.')), "no folder for refused scans");
}

/// Starts a 2° step scan (180 views) and returns once `views` of them are matched.
/// Starts a scan and returns once `views` views are matched and as many pairs are on disk
/// (the recorder runs below the matchers' priority and may lag on a loaded machine).
fn start_and_wait_views(d: &Daemon, name: &str, views: u64) {
    let (mut c, _) = Client::connect(&d.socket);
    c.ok("events.subscribe", json!({}));
    c.ok("scan.start", json!({"name": name, "step_deg": 2}));
    loop {
        let v = c.line();
        let p = &v["params"];
        if v["method"] == "scan.progress" && p["views"].as_u64().unwrap() >= views && p["recorded"].as_u64().unwrap() >= views {
            return;
        }
    }
}

#[test]
fn sigterm_ends_a_scan_interrupted_and_a_killed_daemons_scan_is_recovered() {
    let dir = support::temp_dir("daemon-signals");
    let mut d = Daemon::start(&dir, "");
    // A few views into a long scan, SIGTERM.
    start_and_wait_views(&d, "long", 3);
    d.signal(libc::SIGTERM);
    assert_eq!(d.wait(Duration::from_secs(60)), Some(0), "graceful exit");
    assert!(!d.socket.exists(), "socket removed");
    let scan = d.state.join("long");
    let m = manifest(&scan);
    assert_eq!(m["status"], "interrupted");
    assert!(m["reason"].as_str().unwrap().contains("SIGTERM"), "{m}");
    let frames = jsonl(&scan.join("frames.jsonl"));
    assert!(frames.len() >= 3 && frames.len() < 180);
    assert_eq!(m["frames"].as_u64().unwrap() as usize, frames.len(), "every recorded pair got its view");

    // SIGKILL mid-scan: the next daemon marks the scan interrupted; its recording replays.
    let mut d = Daemon::start(&dir, "");
    start_and_wait_views(&d, "killed", 2);
    d.signal(libc::SIGKILL);
    d.wait(Duration::from_secs(10));
    assert_eq!(manifest(&d.state.join("killed"))["status"], "running");
    let d2 = Daemon::start(&dir, "");
    let m = manifest(&d2.state.join("killed"));
    assert_eq!(m["status"], "interrupted");
    assert!(m["reason"].as_str().unwrap().contains("replay"), "{m}");
    let rec = spinscan::recording::Recording::open(&d2.state.join("killed")).unwrap();
    assert!(rec.frames.len() >= 2);
}

#[test]
fn readiness_is_notified_and_config_errors_exit_78() {
    let dir = support::temp_dir("daemon-notify");
    let notify_path = dir.join("notify.sock");
    let notify = std::os::unix::net::UnixDatagram::bind(&notify_path).unwrap();
    notify.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let _d = Daemon::start_with(&dir, "", &[("NOTIFY_SOCKET", notify_path.to_str().unwrap())]);
    let mut got = String::new();
    let mut buf = [0u8; 4096];
    while !got.contains("READY=1") {
        let n = notify.recv(&mut buf).expect("a notification from spinscand");
        got.push_str(&String::from_utf8_lossy(&buf[..n]));
        got.push('\n');
    }
    assert!(got.contains("STATUS=idle"), "{got}");

    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "[scan]\nstep_deg = -1\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_spinscand")).arg("--config").arg(&bad).output().unwrap();
    assert_eq!(out.status.code(), Some(78));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("scan.step_deg") && err.contains("bad.toml"), "{err}");
    // Matcher parameters are checked by the matcher's own rules when the config is read,
    // not when the first scan starts (a config that passed --check-config once failed then).
    for (key, line) in [("matching.block", "block = 33"), ("matching.block", "block = 4"), ("matching.num_disparities", "num_disparities = 0"), ("matching.num_disparities", "num_disparities = 2000")] {
        std::fs::write(&bad, format!("[matching]\n{line}\n")).unwrap();
        let out = Command::new(env!("CARGO_BIN_EXE_spinscand")).arg("--config").arg(&bad).arg("--check-config").output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(78), "{line}: {err}");
        assert!(err.contains(key) && (err.contains("3…31") || err.contains("1…1024")), "{line}: {err}");
    }
    let out = Command::new(env!("CARGO_BIN_EXE_spinscand")).args(["--sim", "--check-config", "--socket", "/tmp/x.sock"]).output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("kind = \"sim\"") && text.contains("/tmp/x.sock"), "{text}");
}

#[test]
fn the_cli_drives_the_daemon() {
    let dir = support::temp_dir("daemon-cli");
    let d = Daemon::start(&dir, "");
    let cli = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_spinscan")).args(args).arg("--socket").arg(&d.socket).output().unwrap();
        (out.status.code(), String::from_utf8_lossy(&out.stdout).to_string(), String::from_utf8_lossy(&out.stderr).to_string())
    };
    let (code, out, _) = cli(&["status"]);
    assert_eq!(code, Some(0));
    assert!(out.contains("backend sim") && out.contains("idle"), "{out}");
    let (code, out, err) = cli(&["scan", "start", "quarter", "--step-deg", "30", "--total-deg", "90", "--watch"]);
    assert_eq!(code, Some(0), "{out}{err}");
    assert!(out.contains("quarter complete") && out.contains("4 views"), "{out}");
    assert!(err.contains("[##############################] 4/4 views"), "progress bar: {err}");
    let (_, out, _) = cli(&["scans"]);
    assert!(out.contains("quarter") && out.contains("complete"), "{out}");
    let (code, _, err) = cli(&["scan", "stop"]);
    assert_eq!(code, Some(5));
    assert!(err.contains("no scan is running"), "{err}");
    let (code, out, _) = cli(&["devices", "--json"]);
    assert_eq!(code, Some(0));
    assert_eq!(serde_json::from_str::<Value>(&out).unwrap()["backend"], "sim");
    let out = Command::new(env!("CARGO_BIN_EXE_spinscan")).args(["status", "--socket"]).arg(dir.join("nothing.sock")).output().unwrap();
    assert_eq!(out.status.code(), Some(5));
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot connect to spinscand"));
}

/// The lab's calibration workflow on the simulated lab: the rig from a board held up to the
/// cameras, then the axis from the board standing on the table, each kept pair recorded and
/// the results under `calibrations/NAME/`; a second capture, a scan meanwhile and bad
/// parameters are refused with their codes.
#[test]
fn calibration_capture_through_the_socket() {
    let dir = support::temp_dir("daemon-calib");
    let config = support::daemon::small_config(&dir, "");
    let text = std::fs::read_to_string(&config).unwrap().replace("width = 160", "width = 320").replace("height = 120", "height = 240");
    std::fs::write(&config, text).unwrap();
    let d = Daemon::start_config(&dir, &config, &[]);
    let (mut c, _) = Client::connect(&d.socket);
    c.ok("events.subscribe", json!({}));
    let (code, msg) = c.error_code("calib.capture", json!({"name": "rig", "kind": "spiral", "square_mm": 20}));
    assert_eq!(code, -32602, "{msg}");
    assert!(msg.contains("`kind`"), "{msg}");
    let (code, _) = c.error_code("calib.capture", json!({"name": "rig"}));
    assert_eq!(code, -32602, "square_mm is required");

    let started = c.ok("calib.capture", json!({"name": "rig", "count": 6, "square_mm": 20}));
    assert_eq!(started["count"], 6);
    let (code, msg) = c.error_code("scan.start", json!({"name": "during"}));
    assert_eq!(code, -32000, "{msg}");
    assert!(msg.contains("calibration rig is capturing"), "{msg}");
    let (code, _) = c.error_code("calib.capture", json!({"name": "other", "square_mm": 20}));
    assert_eq!(code, -32000);
    let end = until_calibrated(&mut c, "rig");
    assert_eq!(end["status"], "complete", "{end}");
    assert_eq!(end["result"]["pairs"], 6);
    assert!(end["result"]["rms_stereo"].as_f64().unwrap() < 0.2, "{end}");
    let folder = d.state.join("calibrations/rig");
    let calib = spinscan::calib::StereoCalib::load(&folder.join("calib.yaml")).unwrap();
    assert!((calib.t_mm.norm() - 60.0).abs() < 0.5, "{}", calib.t_mm);
    assert_eq!(jsonl(&folder.join("pairs/frames.jsonl")).len(), 6);
    assert!(c.events.iter().any(|e| e["method"] == "calib.progress" && e["params"]["kept"] == 3));
    // Calibrations are not scans.
    assert_eq!(c.ok("scan.list", json!({}))["scans"], json!([]));

    c.ok("calib.capture", json!({"name": "axis", "kind": "turntable", "count": 5, "sweep_deg": 40, "square_mm": 20}));
    let end = until_calibrated(&mut c, "axis");
    assert_eq!(end["status"], "complete", "{end}");
    let dir_up = end["result"]["axis_dir"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect::<Vec<_>>();
    // The simulated cameras look down 12°: up is (0, −cos 12°, −sin 12°) in the camera frame.
    let want = [0.0, -(12f64.to_radians().cos()), -(12f64.to_radians().sin())];
    let cos = dir_up.iter().zip(want).map(|(a, b)| a * b).sum::<f64>();
    assert!(cos.acos().to_degrees() < 0.2, "{dir_up:?}");
    let frames = jsonl(&d.state.join("calibrations/axis/pairs/frames.jsonl"));
    let angles: Vec<f64> = frames.iter().map(|f| f["table_deg"].as_f64().unwrap()).collect();
    assert!((angles[0] + 40.0).abs() < 0.1 && (angles[4] - 40.0).abs() < 0.1, "{angles:?}");
    let (code, _) = c.error_code("calib.capture", json!({"name": "axis", "square_mm": 20}));
    assert_eq!(code, -32004, "the name is taken");
}

fn until_calibrated(c: &mut Client, name: &str) -> Value {
    loop {
        let v = c.line();
        c.events.push(v.clone());
        if v["method"] == "calib.state" && v["params"]["name"] == name && v["params"]["status"] != "running" {
            return v["params"].clone();
        }
    }
}
