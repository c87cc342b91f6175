//! Turntable firmware emulator: the Horus dialect of `shared/spec/turntable-protocol.md`
//! (a Grbl 0.9 fork) spoken on a pseudo-terminal, so spinscan's real serial driver runs
//! against it unchanged.
//!
//! ```text
//!  driver --/dev/pts/N (slave)--> pty --master--> emulator thread: line parser, motion queue,
//!                                                 trapezoidal motion, `?` status, faults
//! ```
//!
//! This parser is written from the spec independently of spinscan's driver (which has its
//! own encoder and reply parser), so a misreading on one side fails a test instead of
//! cancelling out.

use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use serialport::{SerialPort, TTYPort};

use crate::camera::TableAngle;

/// The greeting of the firmware spinscan supports.
pub const HORUS_GREETING: &str = "Horus 0.2 ['$' for help]";

/// A device fault, chosen by config.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TurntableFault {
    /// The `ok` of the n-th command line (1-based, counting every line received) is never sent.
    MissOk { line: u32 },
    /// The n-th command line is answered with line noise instead of its reply.
    Garbage { line: u32 },
    /// The motor stalls when the angle reaches `at_deg` (firmware degrees): the move never
    /// ends, `G4 P0` never answers, `?` shows the angle stuck.
    Stall { at_deg: f64 },
    /// On the n-th command line the device disappears (the port closes).
    Vanish { line: u32 },
}

/// Firmware settings.
#[derive(Debug, Clone, PartialEq)]
pub struct FirmwareConfig {
    pub greeting: String,
    /// Feed rate after reset, degrees per second (Horus: 200).
    pub feed_deg_s: f64,
    /// Acceleration after reset, degrees per second².
    pub accel_deg_s2: f64,
    /// Which way the table turns for positive X: +1 counterclockwise seen from above
    /// (spinscan's `table_deg` convention), −1 clockwise.
    pub direction: f64,
    /// Simulated seconds per real second (> 1 runs motion faster, for tests).
    pub time_scale: f64,
    pub faults: Vec<TurntableFault>,
}

impl Default for FirmwareConfig {
    fn default() -> Self {
        FirmwareConfig { greeting: HORUS_GREETING.to_string(), feed_deg_s: 200.0, accel_deg_s2: 400.0, direction: 1.0, time_scale: 1.0, faults: Vec::new() }
    }
}

/// A running emulator; the device path is [`Emulator::port_path`]. Stops when dropped.
pub struct Emulator {
    path: String,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Emulator {
    /// Starts the firmware on a new pseudo-terminal. `angle` receives the table's physical
    /// angle (spinscan's convention) as it moves, for the simulated cameras.
    pub fn spawn(config: FirmwareConfig, angle: TableAngle) -> io::Result<Emulator> {
        let (mut master, slave) = TTYPort::pair().map_err(io::Error::other)?;
        let path = slave.name().ok_or_else(|| io::Error::other("pseudo-terminal has no name"))?;
        // The slave handle holds the port's lock; the driver opens the slave by path. The pty
        // lives as long as the master.
        drop(slave);
        master.set_timeout(Duration::from_millis(2)).map_err(io::Error::other)?;
        let stop = Arc::new(AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::Builder::new().name("turntable-emulator".into()).spawn(move || {
            let mut fw = Firmware::new(config, angle);
            fw.run(&mut master, &flag);
        })?;
        Ok(Emulator { path, stop, thread: Some(thread) })
    }

    pub fn port_path(&self) -> &str {
        &self.path
    }
}

impl Drop for Emulator {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// One trapezoidal move, in firmware degrees and simulated seconds.
#[derive(Debug, Clone, Copy)]
struct Move {
    from: f64,
    to: f64,
    start_s: f64,
    feed: f64,
    accel: f64,
}

impl Move {
    fn duration_s(&self) -> f64 {
        let d = (self.to - self.from).abs();
        let (v, a) = (self.feed, self.accel);
        if d >= v * v / a {
            2.0 * v / a + (d - v * v / a) / v
        } else {
            2.0 * (d / a).sqrt()
        }
    }

    /// Distance covered `t` seconds into the move.
    fn covered(&self, t: f64) -> f64 {
        let d = (self.to - self.from).abs();
        let (v, a) = (self.feed, self.accel);
        let total = self.duration_s();
        if t >= total {
            return d;
        }
        let t_acc = (v / a).min((d / a).sqrt());
        let v_peak = a * t_acc;
        if t < t_acc {
            0.5 * a * t * t
        } else if t > total - t_acc {
            let r = total - t;
            d - 0.5 * a * r * r
        } else {
            0.5 * a * t_acc * t_acc + v_peak * (t - t_acc)
        }
    }

    fn position(&self, now_s: f64) -> f64 {
        self.from + (self.to - self.from).signum() * self.covered(now_s - self.start_s)
    }
}

enum Step {
    /// Line handled; reply sent (or withheld by a fault).
    Done,
    /// `G4`: the reply waits until the queue drains and the dwell ends.
    Dwell(f64),
}

struct Firmware {
    config: FirmwareConfig,
    angle: TableAngle,
    epoch: Instant,
    /// Machine position of the motor when no move is running, firmware degrees.
    position: f64,
    /// `G50` origin: reported and commanded positions are relative to it.
    origin: f64,
    feed: f64,
    accel: f64,
    motor_on: bool,
    current: Option<Move>,
    queue: VecDeque<f64>,
    line: Vec<u8>,
    pending: VecDeque<String>,
    /// A `G4` waiting: when the queue drains, its dwell runs until this many seconds later.
    dwell: Option<(f64, Option<f64>)>,
    lines_seen: u32,
    stalled: bool,
}

const QUEUE_SLOTS: usize = 16;

impl Firmware {
    fn new(config: FirmwareConfig, angle: TableAngle) -> Firmware {
        let (feed, accel) = (config.feed_deg_s, config.accel_deg_s2);
        Firmware {
            config,
            angle,
            epoch: Instant::now(),
            position: 0.0,
            origin: 0.0,
            feed,
            accel,
            motor_on: false,
            current: None,
            queue: VecDeque::new(),
            line: Vec::new(),
            pending: VecDeque::new(),
            dwell: None,
            lines_seen: 0,
            stalled: false,
        }
    }

    fn now_s(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64() * self.config.time_scale
    }

    fn run(&mut self, port: &mut TTYPort, stop: &AtomicBool) {
        let mut buf = [0u8; 256];
        // A real board prints its greeting at power-up (lost if nobody listens yet).
        let _ = self.send(port, &format!("\r\n{}\r\n", self.config.greeting));
        while !stop.load(Ordering::Acquire) {
            let n = match port.read(&mut buf) {
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::TimedOut || e.kind() == io::ErrorKind::WouldBlock || e.kind() == io::ErrorKind::Interrupted => 0,
                // Nobody has the slave open yet (or it was closed): wait for a host.
                Err(_) => {
                    std::thread::sleep(Duration::from_millis(5));
                    0
                }
            };
            for &b in &buf[..n] {
                match b {
                    0x18 => {
                        self.reset();
                        if self.send(port, &format!("\r\n{}\r\n", self.config.greeting)).is_err() {
                            return;
                        }
                    }
                    b'?' => {
                        let report = self.status();
                        if self.send(port, &report).is_err() {
                            return;
                        }
                    }
                    b'\n' | b'\r' => {
                        if !self.line.is_empty() {
                            let text = String::from_utf8_lossy(&self.line).into_owned();
                            self.pending.push_back(text);
                            self.line.clear();
                        }
                    }
                    _ => self.line.push(b),
                }
            }
            self.advance();
            if !self.serve(port) {
                return;
            }
        }
    }

    fn send(&self, port: &mut TTYPort, s: &str) -> io::Result<()> {
        port.write_all(s.as_bytes())?;
        port.flush()
    }

    fn reset(&mut self) {
        // Ctrl-X stops motion where it is and clears everything queued.
        self.advance();
        self.position = self.current_position();
        self.current = None;
        self.queue.clear();
        self.pending.clear();
        self.line.clear();
        self.dwell = None;
        self.feed = self.config.feed_deg_s;
        self.accel = self.config.accel_deg_s2;
        self.motor_on = false;
        self.stalled = false;
        self.publish();
    }

    /// Where the motor is now (a stalled move stays where it stalled).
    fn current_position(&self) -> f64 {
        match self.current {
            Some(m) if self.stalled => m.from,
            Some(m) => m.position(self.now_s()),
            None => self.position,
        }
    }

    fn publish(&self) {
        self.angle.set(self.config.direction * self.current_position());
    }

    /// Moves time forward: finishes moves, starts queued ones, applies a stall.
    fn advance(&mut self) {
        let now = self.now_s();
        if let Some(m) = self.current {
            let pos = m.position(now);
            if let Some(stall) = self.config.faults.iter().find_map(|f| match f {
                TurntableFault::Stall { at_deg } => Some(*at_deg),
                _ => None,
            }) {
                let passed = (pos - stall) * (m.to - m.from).signum() >= 0.0 && (m.from - stall) * (m.to - m.from).signum() <= 0.0;
                if passed || self.stalled {
                    // The motor slips and stays: the move never finishes.
                    self.stalled = true;
                    self.current = Some(Move { from: stall, to: m.to, start_s: f64::INFINITY, ..m });
                    self.angle.set(self.config.direction * stall);
                    return;
                }
            }
            if now - m.start_s >= m.duration_s() {
                self.position = m.to;
                self.current = None;
            }
        }
        if self.current.is_none() {
            if let Some(to) = self.queue.pop_front() {
                self.current = Some(Move { from: self.position, to, start_s: now, feed: self.feed, accel: self.accel });
            }
        }
        self.publish();
    }

    fn status(&self) -> String {
        let state = if self.current.is_some() || !self.queue.is_empty() { "Run" } else { "Idle" };
        format!("<{state},MPos:{:.3},0.000,0.000>\r\n", self.current_position() - self.origin)
    }

    /// Works through received lines; false when the device vanished.
    fn serve(&mut self, port: &mut TTYPort) -> bool {
        loop {
            if let Some((_, until)) = self.dwell {
                let idle = self.current.is_none() && self.queue.is_empty();
                match until {
                    None if idle => {
                        let seconds = self.dwell.unwrap().0;
                        self.dwell = Some((seconds, Some(self.now_s() + seconds)));
                        continue;
                    }
                    Some(t) if self.now_s() >= t => {
                        self.dwell = None;
                        if self.send(port, "ok\r\n").is_err() {
                            return false;
                        }
                    }
                    _ => return true,
                }
            }
            let Some(line) = self.pending.pop_front() else { return true };
            if self.queue.len() >= QUEUE_SLOTS && line.to_ascii_uppercase().trim_start().starts_with("G1") {
                // Planner full: the line waits, as Grbl blocks the stream.
                self.pending.push_front(line);
                return true;
            }
            self.lines_seen += 1;
            let n = self.lines_seen;
            let faults = self.config.faults.clone();
            if faults.contains(&TurntableFault::Vanish { line: n }) {
                return false;
            }
            let (step, reply) = self.execute(&line);
            let reply = if faults.contains(&TurntableFault::Garbage { line: n }) {
                Some("\u{7f}#\u{1}ok?r%\r\n".to_string())
            } else if faults.contains(&TurntableFault::MissOk { line: n }) {
                None
            } else {
                reply
            };
            match step {
                Step::Dwell(seconds) => {
                    self.dwell = Some((seconds, None));
                    if reply.is_none() {
                        // The fault eats this dwell's ok: finish the wait silently.
                        self.dwell = None;
                    }
                }
                Step::Done => {
                    if let Some(r) = reply {
                        if self.send(port, &r).is_err() {
                            return false;
                        }
                    }
                }
            }
        }
    }

    /// Runs one command line: what happens and the reply (a `G4`'s comes later).
    fn execute(&mut self, raw: &str) -> (Step, Option<String>) {
        let ok = || Some("ok\r\n".to_string());
        let err = |why: &str| (Step::Done, Some(format!("error: {why}\r\n")));
        let text: String = raw.chars().filter(|c| !c.is_whitespace()).collect::<String>().to_ascii_uppercase();
        if text.is_empty() {
            return (Step::Done, ok());
        }
        if let Some(setting) = text.strip_prefix('$') {
            return match setting.split_once('=') {
                Some(("120", v)) => match v.parse::<f64>() {
                    Ok(a) if a > 0.0 && a.is_finite() => {
                        self.accel = a;
                        (Step::Done, ok())
                    }
                    _ => err("Bad number format"),
                },
                Some(_) => err("Unsupported setting"),
                None => (Step::Done, Some(format!("$120={:.3}\r\nok\r\n", self.accel))),
            };
        }
        let words = match parse_words(&text) {
            Some(w) => w,
            None => return err("Bad number format"),
        };
        let get = |letter: char| words.iter().find(|(l, _)| *l == letter).map(|&(_, v)| v);
        match words.first() {
            Some(('G', g)) if *g == 1.0 => {
                if let Some(f) = get('F') {
                    if f <= 0.0 {
                        return err("Invalid feed rate");
                    }
                    self.feed = f;
                }
                if let Some(x) = get('X') {
                    if !self.motor_on {
                        return err("motor disabled");
                    }
                    self.queue.push_back(self.origin + x);
                }
                (Step::Done, ok())
            }
            Some(('G', g)) if *g == 4.0 => match get('P') {
                Some(p) if p >= 0.0 => (Step::Dwell(p), ok()),
                _ => err("Expected P with dwell seconds"),
            },
            Some(('G', g)) if *g == 50.0 => {
                self.origin = self.current_position();
                (Step::Done, ok())
            }
            Some(('M', m)) if *m == 17.0 => {
                self.motor_on = true;
                (Step::Done, ok())
            }
            Some(('M', m)) if *m == 18.0 => {
                self.motor_on = false;
                (Step::Done, ok())
            }
            Some(('M', m)) if *m == 70.0 || *m == 71.0 => (Step::Done, ok()),
            _ => err("Unsupported statement"),
        }
    }
}

/// `G1X10.5F200` → `[('G', 1), ('X', 10.5), ('F', 200)]`; None on a malformed number.
fn parse_words(text: &str) -> Option<Vec<(char, f64)>> {
    let mut words = Vec::new();
    let mut chars = text.char_indices().peekable();
    while let Some((i, c)) = chars.next() {
        if !c.is_ascii_alphabetic() {
            return None;
        }
        let start = i + 1;
        let mut end = start;
        while let Some(&(j, d)) = chars.peek() {
            if d.is_ascii_digit() || d == '.' || d == '-' || d == '+' {
                end = j + 1;
                chars.next();
            } else {
                break;
            }
        }
        words.push((c, text[start..end].parse().ok()?));
    }
    Some(words)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trapezoid_reaches_its_target_at_its_duration() {
        for (d, v, a) in [(90.0, 200.0, 400.0), (5.0, 200.0, 400.0), (30.0, 10.0, 50.0)] {
            let m = Move { from: 10.0, to: 10.0 - d, start_s: 0.0, feed: v, accel: a };
            let t = m.duration_s();
            assert!((m.position(t) - m.to).abs() < 1e-9);
            assert!((m.position(t / 2.0) - (10.0 - d / 2.0)).abs() < 1e-9, "symmetric profile");
            // Never faster than the feed.
            let mut last = m.position(0.0);
            for k in 1..=1000 {
                let p = m.position(t * k as f64 / 1000.0);
                assert!((p - last).abs() <= v * t / 1000.0 + 1e-9);
                last = p;
            }
        }
    }

    #[test]
    fn words_parse_with_or_without_spaces() {
        assert_eq!(parse_words("G1X-10.5F200"), Some(vec![('G', 1.0), ('X', -10.5), ('F', 200.0)]));
        assert_eq!(parse_words("G1X1.2.3"), None);
    }
}
