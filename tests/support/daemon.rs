//! The real `spinscand` in sim mode on a temporary socket, and a bare JSON-RPC client for
//! it written from the protocol doc: what `tests/daemon.rs` and `tests/daemon_hardening.rs`
//! drive.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};

/// A small, fast simulated lab: 160×120 torus, turntable 50× faster than real.
pub fn small_config(dir: &Path, extra: &str) -> PathBuf {
    let text = format!(
        r#"
[daemon]
socket = "{sock}"
state_dir = "{state}"
group = ""
[backend]
kind = "sim"
[turntable]
settle_ms = 5
continuous_deg_s = 20.0
[sim]
object = "torus"
width = 160
height = 120
ideal = true
realtime = false
time_scale = 50.0
[matching]
num_disparities = 32
[scan]
step_deg = 45.0
{extra}
"#,
        sock = dir.join("s.sock").display(),
        state = dir.join("scans").display()
    );
    let path = dir.join("spinscand.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// Adds `keys` to the `[daemon]` section of a config written by [`small_config`].
pub fn daemon_keys(config: &Path, keys: &str) {
    let text = std::fs::read_to_string(config).unwrap().replace("group = \"\"", &format!("group = \"\"\n{keys}"));
    std::fs::write(config, text).unwrap();
}

pub struct Daemon {
    pub child: Child,
    pub socket: PathBuf,
    pub state: PathBuf,
}

impl Daemon {
    pub fn start(dir: &Path, extra: &str) -> Daemon {
        Daemon::start_with(dir, extra, &[])
    }

    pub fn start_with(dir: &Path, extra: &str, env: &[(&str, &str)]) -> Daemon {
        Daemon::start_config(dir, &small_config(dir, extra), env)
    }

    /// Starts `spinscand` on `config` (written in `dir` by [`small_config`]) and waits for
    /// its socket.
    pub fn start_config(dir: &Path, config: &Path, env: &[(&str, &str)]) -> Daemon {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_spinscand"));
        cmd.arg("--config").arg(config).stdout(Stdio::null()).stderr(std::fs::File::create(dir.join("daemon.log")).unwrap());
        for (k, v) in env {
            cmd.env(k, v);
        }
        let child = cmd.spawn().expect("start spinscand");
        let d = Daemon { child, socket: dir.join("s.sock"), state: dir.join("scans") };
        let t0 = Instant::now();
        while UnixStream::connect(&d.socket).is_err() {
            assert!(t0.elapsed() < Duration::from_secs(30), "spinscand did not open its socket; log:\n{}", std::fs::read_to_string(dir.join("daemon.log")).unwrap_or_default());
            std::thread::sleep(Duration::from_millis(20));
        }
        d
    }

    pub fn signal(&self, sig: i32) {
        // SAFETY: kill has no memory preconditions.
        assert_eq!(unsafe { libc::kill(self.child.id() as i32, sig) }, 0);
    }

    pub fn wait(&mut self, limit: Duration) -> Option<i32> {
        let t0 = Instant::now();
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                return s.code();
            }
            if t0.elapsed() > limit {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A bare JSON-RPC client: lines out, lines in.
pub struct Client {
    pub r: BufReader<UnixStream>,
    pub w: UnixStream,
    pub id: u64,
    pub events: Vec<Value>,
}

impl Client {
    pub fn connect(socket: &Path) -> (Client, Value) {
        let s = UnixStream::connect(socket).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
        let mut c = Client { r: BufReader::new(s.try_clone().unwrap()), w: s, id: 0, events: Vec::new() };
        let hello = c.line();
        (c, hello)
    }

    pub fn line(&mut self) -> Value {
        let mut l = String::new();
        assert!(self.r.read_line(&mut l).unwrap() > 0, "daemon closed the connection");
        serde_json::from_str(&l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}"))
    }

    pub fn send_raw(&mut self, text: &str) {
        self.w.write_all(text.as_bytes()).unwrap();
    }

    /// The whole answer object (result or error), keeping notifications.
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        self.id += 1;
        let id = self.id;
        self.send_raw(&format!("{}\n", json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params})));
        loop {
            let v = self.line();
            if v["id"] == json!(id) {
                return v;
            }
            assert_eq!(v["jsonrpc"], "2.0");
            assert!(v["method"].is_string(), "neither answer nor notification: {v}");
            self.events.push(v);
        }
    }

    pub fn ok(&mut self, method: &str, params: Value) -> Value {
        let v = self.call(method, params);
        assert!(v.get("error").is_none(), "{method} failed: {v}");
        v["result"].clone()
    }

    pub fn error_code(&mut self, method: &str, params: Value) -> (i64, String) {
        let v = self.call(method, params);
        let e = v.get("error").unwrap_or_else(|| panic!("{method} should fail: {v}"));
        (e["code"].as_i64().unwrap(), e["message"].as_str().unwrap().to_string())
    }

    /// Reads notifications (kept in `events`) until `scan.state` of `name` leaves
    /// `running`; returns that state's params.
    pub fn until_end(&mut self, name: &str) -> Value {
        let is_end = |v: &Value| v["method"] == "scan.state" && v["params"]["name"] == name && v["params"]["status"] != "running";
        if let Some(v) = self.events.iter().find(|v| is_end(v)) {
            return v["params"].clone();
        }
        loop {
            let v = self.line();
            self.events.push(v.clone());
            if is_end(&v) {
                return v["params"].clone();
            }
        }
    }
}

pub fn manifest(dir: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("manifest.json")).unwrap()).unwrap()
}

pub fn jsonl(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}
