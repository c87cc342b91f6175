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
    /// ends, `?` shows the angle stuck and the state `Run`.
    Stall { at_deg: f64 },
    /// On the n-th command line the device disappears (the port closes).
    Vanish { line: u32 },
    /// On the n-th command line the board resets by itself (a power glitch, a brown-out): the
    /// line is lost, motion stops, the position is zeroed, the greeting comes again.
    Reset { line: u32 },
}

/// Firmware settings.
#[derive(Debug, Clone, PartialEq)]
pub struct FirmwareConfig {
    pub greeting: String,
    /// Feed rate after reset, degrees per second (Horus: 200).
    pub feed_deg_s: f64,
    /// Acceleration after reset, degrees per second² (`$120`).
    pub accel_deg_s2: f64,
    /// Steps per degree (`$100`; Horus: 16 microsteps per 1.8° step = 8.889): every target is
    /// rounded to a whole step.
    pub steps_per_deg: f64,
    /// Highest feed rate, degrees per second (`$110`).
    pub max_rate_deg_s: f64,
    /// Which way the table turns for positive X: +1 counterclockwise seen from above
    /// (spinscan's `table_deg` convention), −1 clockwise.
    pub direction: f64,
    /// Simulated seconds per real second (> 1 runs motion faster, for tests).
    pub time_scale: f64,
    /// Real time from a host opening the port (which resets an Arduino-style board through
    /// DTR) to the greeting: the bootloader's wait. About 2 s on a real board.
    pub boot_delay: Duration,
    pub faults: Vec<TurntableFault>,
}

impl Default for FirmwareConfig {
    fn default() -> Self {
        FirmwareConfig {
            greeting: HORUS_GREETING.to_string(),
            feed_deg_s: 200.0,
            accel_deg_s2: 400.0,
            steps_per_deg: 8.889,
            max_rate_deg_s: 500.0,
            direction: 1.0,
            time_scale: 1.0,
            boot_delay: Duration::from_secs(2),
            faults: Vec::new(),
        }
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

/// One trapezoidal move, in machine degrees and simulated seconds.
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

    /// Speed `t` seconds into the move.
    fn speed(&self, t: f64) -> f64 {
        let d = (self.to - self.from).abs();
        let (v, a) = (self.feed, self.accel);
        let total = self.duration_s();
        if t <= 0.0 || t >= total {
            return 0.0;
        }
        let t_acc = (v / a).min((d / a).sqrt());
        (a * t).min(a * t_acc).min(a * (total - t))
    }

    fn position(&self, now_s: f64) -> f64 {
        self.from + (self.to - self.from).signum() * self.covered(now_s - self.start_s)
    }
}

/// What the motor is doing.
#[derive(Debug, Clone, Copy)]
enum Motion {
    /// A move of the queue, rest to rest.
    Move(Move),
    /// A feed hold: decelerating from `speed` to rest; `to` is where the held move was going.
    Hold { from: f64, dir: f64, speed: f64, accel: f64, start_s: f64, to: f64 },
}

impl Motion {
    fn position(&self, now_s: f64) -> f64 {
        match *self {
            Motion::Move(m) => m.position(now_s),
            Motion::Hold { from, dir, speed, accel, start_s, .. } => {
                let t = (now_s - start_s).clamp(0.0, speed / accel);
                from + dir * (speed * t - 0.5 * accel * t * t)
            }
        }
    }

    fn done(&self, now_s: f64) -> bool {
        match *self {
            Motion::Move(m) => now_s - m.start_s >= m.duration_s(),
            Motion::Hold { speed, accel, start_s, .. } => now_s - start_s >= speed / accel,
        }
    }
}

struct Firmware {
    config: FirmwareConfig,
    angle: TableAngle,
    epoch: Instant,
    /// Machine position of the motor when nothing runs, degrees (always a whole step).
    position: f64,
    /// `G50` and reboots: reported and commanded positions are relative to it.
    origin: f64,
    feed: f64,
    accel: f64,
    steps_per_deg: f64,
    max_rate: f64,
    motor_on: bool,
    /// The physical table follows the motor only while it is energised: the machine position
    /// and the table angle (firmware direction) when it last was switched on.
    anchor: (f64, f64),
    current: Option<Motion>,
    /// Targets waiting, machine degrees. After a feed hold the held move's target waits here
    /// (state `Queue`) until `~`.
    queue: VecDeque<f64>,
    held: bool,
    alarm: bool,
    line: Vec<u8>,
    pending: VecDeque<String>,
    lines_seen: u32,
    stalled: bool,
    /// A host has the port open (the master reads without EIO).
    host: bool,
    /// The bootloader runs until then (input is ignored); then the greeting.
    booting_until: Option<Instant>,
}

const QUEUE_SLOTS: usize = 16;

impl Firmware {
    fn new(config: FirmwareConfig, angle: TableAngle) -> Firmware {
        let (feed, accel, spd, max_rate) = (config.feed_deg_s, config.accel_deg_s2, config.steps_per_deg, config.max_rate_deg_s);
        let table_fw = angle.get() * config.direction;
        Firmware {
            config,
            angle,
            epoch: Instant::now(),
            position: 0.0,
            origin: 0.0,
            feed,
            accel,
            steps_per_deg: spd,
            max_rate,
            motor_on: false,
            anchor: (0.0, table_fw),
            current: None,
            queue: VecDeque::new(),
            held: false,
            alarm: false,
            line: Vec::new(),
            pending: VecDeque::new(),
            lines_seen: 0,
            stalled: false,
            host: false,
            booting_until: None,
        }
    }

    fn now_s(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64() * self.config.time_scale
    }

    fn run(&mut self, port: &mut TTYPort, stop: &AtomicBool) {
        let mut buf = [0u8; 256];
        // A real board's power-up greeting is lost when nobody listens; a pty would keep it
        // for the first reader, so the emulator greets only once a host has opened the port
        // (which resets a real board, and the greeting follows the bootloader).
        while !stop.load(Ordering::Acquire) {
            let n = match port.read(&mut buf) {
                Ok(n) => Some(n),
                Err(e) if e.kind() == io::ErrorKind::TimedOut || e.kind() == io::ErrorKind::WouldBlock || e.kind() == io::ErrorKind::Interrupted => Some(0),
                // Nobody has the slave open (EIO on the master): wait for a host.
                Err(_) => None,
            };
            match (n.is_some(), self.host) {
                (true, false) => {
                    // A host opened the port: DTR resets the board; the bootloader runs first.
                    self.host = true;
                    self.reboot();
                    self.booting_until = Some(Instant::now() + self.config.boot_delay);
                }
                (false, true) => self.host = false,
                _ => {}
            }
            let Some(n) = n else {
                std::thread::sleep(Duration::from_millis(5));
                continue;
            };
            if let Some(t) = self.booting_until {
                if Instant::now() < t {
                    continue; // the bootloader ignores what the host sends
                }
                self.booting_until = None;
                if self.send(port, &format!("\r\n{}\r\n", self.config.greeting)).is_err() {
                    return;
                }
            }
            for &b in &buf[..n] {
                match b {
                    0x18 => {
                        let text = self.ctrl_x();
                        if self.send(port, &text).is_err() {
                            return;
                        }
                    }
                    b'?' => {
                        self.advance();
                        let report = self.status();
                        if self.send(port, &report).is_err() {
                            return;
                        }
                    }
                    b'!' => self.feed_hold(),
                    b'~' => self.cycle_start(),
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

    /// Rounds machine degrees to a whole step.
    fn to_step(&self, deg: f64) -> f64 {
        (deg * self.steps_per_deg).round() / self.steps_per_deg
    }

    /// Stops everything where it is and forgets what was queued (reset, alarm, reboot).
    fn stop_all(&mut self) {
        self.advance();
        self.position = self.to_step(self.current_position());
        self.current = None;
        self.queue.clear();
        self.pending.clear();
        self.line.clear();
        self.held = false;
        self.stalled = false;
        self.feed = self.config.feed_deg_s;
        self.publish();
    }

    /// Ctrl-X: a reset. During motion (`Run`, `Hold`) Grbl raises the alarm: the position
    /// may be lost, and every G-code line is refused until `$X`.
    fn ctrl_x(&mut self) -> String {
        self.advance();
        let moving = self.current.is_some();
        self.stop_all();
        if moving {
            self.alarm = true;
            format!("ALARM: Abort during cycle\r\n\r\n{}\r\n['$H'|'$X' to unlock]\r\n", self.config.greeting)
        } else {
            format!("\r\n{}\r\n", self.config.greeting)
        }
    }

    /// Power-on (a host opened the port, or a glitch): the position restarts at zero, the
    /// motor is off, the settings in EEPROM stay.
    fn reboot(&mut self) {
        self.stop_all();
        self.origin = self.position;
        self.alarm = false;
        self.set_motor(false);
    }

    fn set_motor(&mut self, on: bool) {
        // Switching either way re-anchors the table to the motor where both are now.
        if on != self.motor_on {
            self.anchor = (self.current_position(), self.physical());
        }
        self.motor_on = on;
    }

    /// `!`: decelerate to a stop; the rest of the move waits (`Queue`) for `~`.
    fn feed_hold(&mut self) {
        self.advance();
        if self.held {
            return;
        }
        if let (true, Some(Motion::Move(m))) = (self.stalled, self.current) {
            // A stalled motor is already at rest: the hold ends at once, the move waits.
            self.current = None;
            self.stalled = false;
            self.held = true;
            self.queue.push_front(m.to);
            return;
        }
        if let Some(Motion::Move(m)) = self.current {
            let now = self.now_s();
            let from = m.position(now);
            let speed = m.speed(now - m.start_s);
            self.current = Some(Motion::Hold { from, dir: (m.to - m.from).signum(), speed, accel: m.accel, start_s: now, to: m.to });
            self.held = true;
        }
    }

    /// `~`: resume after a hold.
    fn cycle_start(&mut self) {
        self.advance();
        if self.held && self.current.is_none() {
            self.held = false;
        }
    }

    /// Where the motor is now (a stalled move stays where it stalled).
    fn current_position(&self) -> f64 {
        match self.current {
            Some(_) if self.stalled => self.position,
            Some(m) => m.position(self.now_s()),
            None => self.position,
        }
    }

    /// The table's angle in firmware degrees: it follows the motor only while energised.
    fn physical(&self) -> f64 {
        if self.motor_on {
            self.anchor.1 + (self.current_position() - self.anchor.0)
        } else {
            self.anchor.1
        }
    }

    fn publish(&self) {
        self.angle.set(self.config.direction * self.physical());
    }

    /// Moves time forward: finishes moves, starts queued ones, applies a stall.
    fn advance(&mut self) {
        let now = self.now_s();
        if let Some(m) = self.current {
            if let Some(stall) = self.config.faults.iter().find_map(|f| match f {
                TurntableFault::Stall { at_deg } => Some(*at_deg + self.origin),
                _ => None,
            }) {
                if let Motion::Move(mv) = m {
                    let dir = (mv.to - mv.from).signum();
                    let passed = (mv.position(now) - stall) * dir >= 0.0 && (mv.from - stall) * dir <= 0.0;
                    if passed && !self.stalled {
                        // The motor slips and stays: the move never finishes.
                        self.stalled = true;
                        self.position = stall;
                    }
                }
                if self.stalled {
                    self.publish();
                    return;
                }
            }
            if m.done(now) {
                match m {
                    Motion::Move(mv) => self.position = mv.to,
                    Motion::Hold { to, .. } => {
                        // Stopped short: the held move's target waits for `~`.
                        self.position = self.to_step(m.position(now));
                        if (to - self.position).abs() > 0.5 / self.steps_per_deg {
                            self.queue.push_front(to);
                        } else {
                            self.held = false;
                        }
                    }
                }
                self.current = None;
            }
        }
        if self.current.is_none() && !self.held && !self.alarm {
            if let Some(to) = self.queue.pop_front() {
                self.current = Some(Motion::Move(Move { from: self.position, to, start_s: now, feed: self.feed.min(self.max_rate), accel: self.accel }));
            }
        }
        self.publish();
    }

    fn state(&self) -> &'static str {
        if self.alarm {
            "Alarm"
        } else if matches!(self.current, Some(Motion::Hold { .. })) {
            "Hold"
        } else if self.current.is_some() {
            "Run"
        } else if !self.queue.is_empty() {
            "Queue"
        } else {
            "Idle"
        }
    }

    fn status(&self) -> String {
        let x = self.to_step(self.current_position()) - self.origin;
        format!("<{},MPos:{x:.3},0.000,0.000,WPos:{x:.3},0.000,0.000>\r\n", self.state())
    }

    /// Works through received lines; false when the device vanished.
    fn serve(&mut self, port: &mut TTYPort) -> bool {
        loop {
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
            if faults.contains(&TurntableFault::Reset { line: n }) {
                self.reboot();
                if self.send(port, &format!("\r\n{}\r\n", self.config.greeting)).is_err() {
                    return false;
                }
                continue;
            }
            let reply = self.execute(&line);
            let reply = if faults.contains(&TurntableFault::Garbage { line: n }) {
                Some("\u{7f}#\u{1}ok?r%\r\n".to_string())
            } else if faults.contains(&TurntableFault::MissOk { line: n }) {
                None
            } else {
                Some(reply)
            };
            if let Some(r) = reply {
                if self.send(port, &r).is_err() {
                    return false;
                }
            }
        }
    }

    /// Runs one command line and returns its whole reply. What this firmware knows is in
    /// the spec's table; everything else is refused with the firmware's own words.
    fn execute(&mut self, raw: &str) -> String {
        const OK: &str = "ok\r\n";
        let err = |why: &str| format!("error: {why}\r\n");
        let text: String = raw.chars().filter(|c| !c.is_whitespace()).collect::<String>().to_ascii_uppercase();
        if text.is_empty() {
            return OK.into();
        }
        if let Some(setting) = text.strip_prefix('$') {
            return match setting.split_once('=') {
                None if setting == "$" => format!(
                    "$100={:.3} (x, step/deg)\r\n$110={:.3} (x max rate, deg/sec)\r\n$120={:.3} (x accel, deg/sec^2)\r\nok\r\n",
                    self.steps_per_deg, self.max_rate, self.accel
                ),
                None if setting == "X" => {
                    self.alarm = false;
                    "[Caution: Unlocked]\r\nok\r\n".into()
                }
                Some((key, v)) => match (key, v.parse::<f64>()) {
                    (_, Ok(v)) if !(v > 0.0 && v.is_finite()) => err("Bad number format"),
                    (_, Err(_)) => err("Bad number format"),
                    ("100", Ok(v)) => {
                        self.steps_per_deg = v;
                        OK.into()
                    }
                    ("110", Ok(v)) => {
                        self.max_rate = v;
                        OK.into()
                    }
                    ("120", Ok(v)) => {
                        self.accel = v;
                        OK.into()
                    }
                    _ => err("Unsupported command"),
                },
                None => err("Unsupported command"),
            };
        }
        let Some(words) = parse_words(&text) else { return err("Bad number format") };
        if self.alarm {
            return err("Alarm lock");
        }
        let get = |letter: char| words.iter().find(|(l, _)| *l == letter).map(|&(_, v)| v);
        let only = |allowed: &[char]| words.iter().skip(1).all(|(l, _)| allowed.contains(l));
        match words.first() {
            Some(('G', g)) if *g == 1.0 && only(&['X', 'F']) => {
                if let Some(f) = get('F') {
                    if f <= 0.0 {
                        return err("Invalid statement");
                    }
                    self.feed = f;
                }
                if let Some(x) = get('X') {
                    self.queue.push_back(self.to_step(self.origin + x));
                }
                OK.into()
            }
            Some(('G', g)) if *g == 50.0 && only(&[]) => {
                self.origin = self.to_step(self.current_position());
                OK.into()
            }
            Some(('M', m)) if *m == 17.0 && only(&[]) => {
                self.set_motor(true);
                OK.into()
            }
            Some(('M', m)) if *m == 18.0 && only(&[]) => {
                self.set_motor(false);
                OK.into()
            }
            Some(('M', m)) if (*m == 70.0 || *m == 71.0) && only(&['T']) => OK.into(),
            Some(('M', m)) if (*m == 0.0 || *m == 2.0) && only(&[]) => OK.into(),
            Some(('M', m)) if *m == 50.0 && only(&['T']) => "0\r\nok\r\n".into(),
            _ => err("Unsupported command"),
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
    fn a_hold_decelerates_to_rest_at_the_set_acceleration() {
        let m = Move { from: 0.0, to: 100.0, start_s: 0.0, feed: 50.0, accel: 100.0 };
        let speed = m.speed(1.0);
        assert!((speed - 50.0).abs() < 1e-9, "cruising at the feed: {speed}");
        let h = Motion::Hold { from: m.position(1.0), dir: 1.0, speed, accel: 100.0, start_s: 1.0, to: 100.0 };
        assert!(!h.done(1.4) && h.done(1.5));
        assert!((h.position(2.0) - (m.position(1.0) + 50.0 * 50.0 / 200.0)).abs() < 1e-9, "v²/2a to stop");
    }

    #[test]
    fn words_parse_with_or_without_spaces() {
        assert_eq!(parse_words("G1X-10.5F200"), Some(vec![('G', 1.0), ('X', -10.5), ('F', 200.0)]));
        assert_eq!(parse_words("G1X1.2.3"), None);
    }
}
