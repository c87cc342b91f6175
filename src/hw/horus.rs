//! The Horus turntable over serial: spinscan's driver for the Horus firmware
//! (`shared/spec/turntable-protocol.md`).
//!
//! ```text
//!  open      ── (port open resets the board) … greeting ≤ boot_wait; else Ctrl-X ── $$ (steps/°, rate, accel) ── M17, $120, G1 F
//!  move_to(θ)── "G1 X<θ·direction, whole steps>" ─> ok ── '?' every 50 ms until <Idle,MPos:θ±½ step> ── settle ─> the angle read back
//!  angle()   ── '?' ─> <Idle,MPos:12.000,0.000,0.000,…>   (each reply timestamped: angle_at(t) interpolates)
//!  halt()    ── '!' (feed hold) ── '?' until Queue/Idle ── Ctrl-X ── greeting ── ($X if an alarm came) ── M17, G1 F
//! ```
//!
//! The firmware has no dwell (`G4` is refused) and acknowledges `G1` when it is queued, not
//! when the move ends, so arrival is found by polling `?`. Every target is rounded to a whole
//! motor step (8.889 steps per degree on a Horus board, read from `$100` at open), and
//! positions are compared to half a step. A reset (Ctrl-X) while the table moves raises
//! Grbl's alarm, so a moving table is first stopped with a feed hold. Replies are read line by
//! line with a deadline; a line that is not `ok`, `error: …`, a status report, an alarm or the
//! greeting is line noise: logged and skipped. A command whose `ok` does not come in time is
//! sent again (every command spinscan sends is absolute, so a repeat is harmless) up to
//! `tries` times, then the device counts as unresponsive. A greeting in the middle of a
//! command means the board reset (power glitch): its position is lost, and the scan is told.
//! Read or write failures and end-of-file mean the device vanished. Every error names the
//! port and the command.

use std::collections::VecDeque;
use std::io::{Read, Write};
use std::time::{Duration, Instant};

use serialport::SerialPort;

use super::frame::monotonic_ns;
use super::{Turntable, TurntableError};

/// The firmware line spinscan supports (the greeting's first words).
pub const SUPPORTED_FIRMWARE: &str = "Horus 0.2";

/// Driver settings (the `[turntable]` section of the daemon's config).
#[derive(Debug, Clone, PartialEq)]
pub struct DriverConfig {
    pub baud: u32,
    /// How long to wait for a reply to one command.
    pub reply_timeout: Duration,
    /// How many times a command is sent before the device counts as unresponsive.
    pub tries: u32,
    /// `+1` when positive firmware X turns the table counterclockwise seen from above, `−1`
    /// when clockwise (the wiring decides).
    pub direction: i8,
    /// Feed rate sent after reset, degrees per second.
    pub feed_deg_s: f64,
    /// Acceleration sent after reset, degrees per second².
    pub accel_deg_s2: f64,
    /// A moving table whose angle changes by less than this between status polls one
    /// `reply_timeout` apart has stalled, degrees.
    pub stall_tolerance_deg: f64,
    /// Wait after arrival before capturing (vibration settles).
    pub settle: Duration,
    /// How long to wait for the power-on greeting after opening the port (opening resets an
    /// Arduino-style board; its bootloader takes about 2 s). Ctrl-X is sent only after it.
    pub boot_wait: Duration,
}

impl Default for DriverConfig {
    fn default() -> Self {
        DriverConfig {
            baud: 115_200,
            reply_timeout: Duration::from_millis(500),
            tries: 3,
            direction: 1,
            feed_deg_s: 30.0,
            accel_deg_s2: 60.0,
            stall_tolerance_deg: 0.001,
            settle: Duration::from_millis(100),
            boot_wait: Duration::from_secs(3),
        }
    }
}

/// The firmware's state word in a status report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TableState {
    Idle,
    /// Moves wait (after a feed hold, or before a cycle start).
    Queue,
    Run,
    Hold,
    Home,
    Alarm,
    Check,
}

impl TableState {
    fn parse(word: &str) -> Option<TableState> {
        Some(match word {
            "Idle" => TableState::Idle,
            "Queue" => TableState::Queue,
            "Run" => TableState::Run,
            "Hold" => TableState::Hold,
            "Home" => TableState::Home,
            "Alarm" => TableState::Alarm,
            "Check" => TableState::Check,
            _ => return None,
        })
    }

    pub fn name(self) -> &'static str {
        match self {
            TableState::Idle => "Idle",
            TableState::Queue => "Queue",
            TableState::Run => "Run",
            TableState::Hold => "Hold",
            TableState::Home => "Home",
            TableState::Alarm => "Alarm",
            TableState::Check => "Check",
        }
    }

    /// The motor is turning (or decelerating).
    fn moving(self) -> bool {
        matches!(self, TableState::Run | TableState::Hold | TableState::Home)
    }
}

/// A reply line, classified.
#[derive(Debug, Clone, PartialEq)]
enum Reply {
    Ok,
    Error(String),
    Status { state: TableState, position_deg: f64 },
    Greeting(String),
    /// `ALARM: …`, or the unlock hint that follows an alarm's greeting.
    Alarm(String),
    /// A settings line of `$$`: `$100=8.889 (x, step/deg)`.
    Setting(u32, f64),
    Noise(String),
}

/// A line that starts like a status report (`<`) but is not one: the line as received.
#[derive(Debug, Clone, PartialEq)]
struct UnreadableStatus(String);

/// Classifies one reply line (without its line end). Written from the protocol spec, apart
/// from hw-sim's emulator.
fn classify(line: &str) -> Result<Reply, UnreadableStatus> {
    let line = line.trim();
    if line.eq_ignore_ascii_case("ok") {
        return Ok(Reply::Ok);
    }
    if let Some(rest) = line.strip_prefix("error:") {
        return Ok(Reply::Error(rest.trim().to_string()));
    }
    if line.starts_with("ALARM") || line.starts_with("['$H'|'$X'") {
        return Ok(Reply::Alarm(line.to_string()));
    }
    if line.starts_with("Horus") || line.starts_with("Grbl") {
        return Ok(Reply::Greeting(line.to_string()));
    }
    if let Some(rest) = line.strip_prefix('$') {
        if let Some((key, value)) = rest.split_once('=') {
            let number = value.split_whitespace().next().unwrap_or_default();
            if let (Ok(k), Ok(v)) = (key.parse(), number.parse()) {
                return Ok(Reply::Setting(k, v));
            }
        }
    }
    if let Some(body) = line.strip_prefix('<') {
        let bad = || UnreadableStatus(line.to_string());
        let body = body.strip_suffix('>').ok_or_else(bad)?;
        let (state, rest) = body.split_once(',').ok_or_else(bad)?;
        let state = TableState::parse(state).ok_or_else(bad)?;
        let mpos = rest.strip_prefix("MPos:").ok_or_else(bad)?;
        let first = mpos.split(',').next().unwrap_or_default();
        let position_deg: f64 = first.parse().map_err(|_| bad())?;
        return Ok(Reply::Status { state, position_deg });
    }
    Ok(Reply::Noise(line.to_string()))
}

/// What the board says of itself at open (`$$` and the greeting).
#[derive(Debug, Clone, PartialEq)]
pub struct BoardInfo {
    pub firmware: String,
    /// `$100`: targets are whole multiples of 1 / this.
    pub steps_per_deg: f64,
    /// `$110`.
    pub max_rate_deg_s: f64,
    /// `$120` as the board had it before spinscan set its own.
    pub accel_deg_s2: f64,
}

/// The Horus serial driver.
pub struct HorusTurntable {
    port: Box<dyn SerialPort>,
    path: String,
    config: DriverConfig,
    pending: Vec<u8>,
    info: BoardInfo,
    /// Status replies with the monotonic time they arrived (ns), newest last, in firmware
    /// degrees: what `angle_at` interpolates.
    samples: VecDeque<(u64, f64)>,
    /// `M17` sent since the last `M18` (the firmware moves its count with the motor off too,
    /// but the table does not turn).
    motor_on: bool,
    /// Set by a scan's stop request: every wait ends.
    stop: Option<std::sync::Arc<std::sync::atomic::AtomicBool>>,
}

enum ReadOutcome {
    Line(String),
    TimedOut,
}

/// How often arrival is polled.
const POLL: Duration = Duration::from_millis(50);

/// Status samples kept for interpolation.
const SAMPLES: usize = 16;

/// Two status replies further apart than this are not interpolated between, ns.
const MAX_SAMPLE_GAP_NS: u64 = 1_000_000_000;


impl HorusTurntable {
    /// Opens `path` (which resets the board), waits for its greeting (Ctrl-X only if none
    /// comes within `boot_wait`), checks it, reads `$$`, switches the motor on and sets feed
    /// and acceleration.
    pub fn open(path: &str, config: DriverConfig) -> Result<HorusTurntable, TurntableError> {
        let _span = tracing::info_span!("turntable_open", port = path).entered();
        let port = serialport::new(path, config.baud)
            .timeout(Duration::from_millis(20))
            .open()
            .map_err(|e| TurntableError::Open { port: path.to_string(), what: e.to_string() })?;
        let info = BoardInfo { firmware: String::new(), steps_per_deg: 0.0, max_rate_deg_s: 0.0, accel_deg_s2: 0.0 };
        let mut t = HorusTurntable { port, path: path.to_string(), config, pending: Vec::new(), info, samples: VecDeque::new(), motor_on: false, stop: None };
        let boot = t.config.boot_wait;
        match t.await_greeting(Instant::now() + boot, "power-on greeting")? {
            Some(greeting) => t.info.firmware = greeting,
            None => {
                tracing::info!(port = path, "no power-on greeting within {} ms; resetting", boot.as_millis());
                t.reset()?;
            }
        }
        t.read_settings()?;
        t.setup()?;
        tracing::info!(port = path, firmware = %t.info.firmware, steps_per_deg = t.info.steps_per_deg, "turntable ready");
        Ok(t)
    }

    /// What the board said of itself at open.
    pub fn info(&self) -> &BoardInfo {
        &self.info
    }

    /// `$$`: steps per degree, maximum rate and acceleration.
    fn read_settings(&mut self) -> Result<(), TurntableError> {
        let lines = self.command_collect("$$")?;
        for line in lines {
            if let Ok(Reply::Setting(k, v)) = classify(&line) {
                match k {
                    100 => self.info.steps_per_deg = v,
                    110 => self.info.max_rate_deg_s = v,
                    120 => self.info.accel_deg_s2 = v,
                    _ => {}
                }
            }
        }
        if !(self.info.steps_per_deg > 0.0 && self.info.steps_per_deg.is_finite()) {
            return Err(TurntableError::Rejected { port: self.path.clone(), command: "$$".into(), reply: "no `$100=<steps/deg>` setting in the answer".into() });
        }
        Ok(())
    }

    /// Motor on, acceleration and the step feed (after open and after a reset).
    fn setup(&mut self) -> Result<(), TurntableError> {
        self.command("M17")?;
        self.motor_on = true;
        let (feed, accel) = (self.config.feed_deg_s, self.config.accel_deg_s2);
        // `$120` lives in EEPROM: not written when the board has it already (rewriting the
        // same value costs no wear either).
        if (self.info.accel_deg_s2 - accel).abs() > 1e-3 {
            self.command(&format!("$120={accel:.3}"))?;
        }
        self.command(&format!("G1 F{feed:.3}"))
    }

    /// Reads lines until the greeting (checked) or `deadline`; None when none came. An alarm
    /// reported around the greeting is unlocked with `$X`.
    fn await_greeting(&mut self, deadline: Instant, command: &str) -> Result<Option<String>, TurntableError> {
        let mut alarm = false;
        let greeting = loop {
            match self.read_line(deadline, command)? {
                ReadOutcome::TimedOut => return Ok(None),
                ReadOutcome::Line(line) => match classify(&line) {
                    Ok(Reply::Greeting(g)) => break g,
                    Ok(Reply::Alarm(a)) => {
                        tracing::warn!(port = %self.path, alarm = a, "the firmware raised an alarm");
                        alarm = true;
                    }
                    _ => tracing::debug!(port = %self.path, line, "ignoring a line before the greeting"),
                },
            }
        };
        let words: Vec<&str> = greeting.split_whitespace().take(2).collect();
        if words.join(" ") != SUPPORTED_FIRMWARE {
            return Err(TurntableError::UnsupportedFirmware { port: self.path.clone(), greeting, expected: SUPPORTED_FIRMWARE });
        }
        // The unlock hint follows the greeting of an alarm.
        let hint_deadline = Instant::now() + Duration::from_millis(100);
        if let ReadOutcome::Line(line) = self.read_line(hint_deadline, command)? {
            match classify(&line) {
                Ok(Reply::Alarm(_)) => alarm = true,
                _ => self.pending.splice(0..0, format!("{line}\n").into_bytes()).for_each(drop),
            }
        }
        if alarm {
            self.unlock()?;
        }
        Ok(Some(greeting))
    }

    /// `$X`: leave the alarm lock.
    fn unlock(&mut self) -> Result<(), TurntableError> {
        tracing::warn!(port = %self.path, "unlocking the firmware after an alarm ($X)");
        self.command("$X")
    }

    /// Ctrl-X, then waits for the greeting (unlocking an alarm with `$X`). Only for a table at
    /// rest: [`Turntable::halt`] stops a moving one first.
    pub fn reset(&mut self) -> Result<(), TurntableError> {
        let command = "Ctrl-X (reset)";
        self.pending.clear();
        self.write_bytes(&[0x18], command)?;
        let waited = self.config.reply_timeout * self.config.tries.max(1);
        match self.await_greeting(Instant::now() + waited, command)? {
            Some(g) => {
                self.info.firmware = g;
                Ok(())
            }
            None => Err(TurntableError::NoGreeting { port: self.path.clone(), waited_ms: waited.as_millis() as u64 }),
        }
    }

    fn write_bytes(&mut self, bytes: &[u8], command: &str) -> Result<(), TurntableError> {
        self.port
            .write_all(bytes)
            .and_then(|_| self.port.flush())
            .map_err(|e| TurntableError::Vanished { port: self.path.clone(), command: command.to_string(), what: format!("write failed: {e}") })
    }

    /// The next complete line before `deadline`.
    fn read_line(&mut self, deadline: Instant, command: &str) -> Result<ReadOutcome, TurntableError> {
        loop {
            if let Some(pos) = self.pending.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.pending.drain(..=pos).collect();
                let text = String::from_utf8_lossy(&line).trim_end_matches(['\r', '\n']).to_string();
                if text.trim().is_empty() {
                    continue;
                }
                return Ok(ReadOutcome::Line(text));
            }
            if Instant::now() >= deadline {
                return Ok(ReadOutcome::TimedOut);
            }
            let mut buf = [0u8; 128];
            match self.port.read(&mut buf) {
                Ok(0) => return Err(TurntableError::Vanished { port: self.path.clone(), command: command.to_string(), what: "end of file on the port".into() }),
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) if matches!(e.kind(), std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock | std::io::ErrorKind::Interrupted) => {}
                Err(e) => return Err(TurntableError::Vanished { port: self.path.clone(), command: command.to_string(), what: format!("read failed: {e}") }),
            }
        }
    }

    /// Sends one line and waits for its `ok`, resending on silence.
    fn command(&mut self, command: &str) -> Result<(), TurntableError> {
        self.command_collect(command).map(drop)
    }

    /// As [`HorusTurntable::command`], returning the lines that came before the `ok` (`$$`).
    fn command_collect(&mut self, command: &str) -> Result<Vec<String>, TurntableError> {
        let _span = tracing::debug_span!("turntable_command", port = %self.path, command).entered();
        let timeout = self.config.reply_timeout;
        for attempt in 1..=self.config.tries.max(1) {
            // Drop whatever a previous, abandoned exchange left behind (a late `ok`).
            self.pending.clear();
            let _ = self.port.clear(serialport::ClearBuffer::Input);
            self.write_bytes(format!("{command}\n").as_bytes(), command)?;
            let deadline = Instant::now() + timeout;
            let mut lines = Vec::new();
            loop {
                match self.read_line(deadline, command)? {
                    ReadOutcome::TimedOut => {
                        tracing::warn!(port = %self.path, command, attempt, "no reply in time");
                        break;
                    }
                    ReadOutcome::Line(line) => match classify(&line) {
                        Ok(Reply::Ok) => return Ok(lines),
                        Ok(Reply::Error(reply)) => return Err(TurntableError::Rejected { port: self.path.clone(), command: command.to_string(), reply }),
                        Ok(Reply::Greeting(g)) => {
                            // The board reset under us (power glitch): its position is lost.
                            tracing::warn!(port = %self.path, greeting = g, "the board reset during a command");
                            return Err(TurntableError::BoardReset { port: self.path.clone(), command: command.to_string() });
                        }
                        Ok(Reply::Noise(noise)) => {
                            tracing::debug!(port = %self.path, line = noise, "line before the ok");
                            lines.push(line);
                        }
                        Ok(_) => lines.push(line),
                        Err(UnreadableStatus(noise)) => tracing::warn!(port = %self.path, line = noise, "ignoring a malformed status line"),
                    },
                }
            }
        }
        Err(TurntableError::Unresponsive { port: self.path.clone(), command: command.to_string(), timeout_ms: timeout.as_millis() as u64, tries: self.config.tries.max(1) })
    }

    /// The firmware's state and position (`?`), timestamped for [`Turntable::angle_at`].
    pub fn status(&mut self) -> Result<(TableState, f64), TurntableError> {
        let command = "? (status)";
        for _ in 0..self.config.tries.max(1) {
            self.write_bytes(b"?", command)?;
            let deadline = Instant::now() + self.config.reply_timeout;
            loop {
                match self.read_line(deadline, command)? {
                    ReadOutcome::TimedOut => break,
                    ReadOutcome::Line(line) => match classify(&line) {
                        Ok(Reply::Status { state, position_deg }) => {
                            if self.samples.len() == SAMPLES {
                                self.samples.pop_front();
                            }
                            self.samples.push_back((monotonic_ns(), position_deg));
                            return Ok((state, position_deg));
                        }
                        Ok(Reply::Greeting(_)) => return Err(TurntableError::BoardReset { port: self.path.clone(), command: command.into() }),
                        Err(UnreadableStatus(reply)) => return Err(TurntableError::BadStatus { port: self.path.clone(), reply }),
                        Ok(_) => {} // an `ok` of an earlier line, or noise
                    },
                }
            }
        }
        Err(TurntableError::Unresponsive { port: self.path.clone(), command: command.into(), timeout_ms: self.config.reply_timeout.as_millis() as u64, tries: self.config.tries.max(1) })
    }

    /// Half a motor step, degrees: how close "at the target" is.
    fn half_step(&self) -> f64 {
        0.5 / self.info.steps_per_deg
    }

    /// `deg` rounded to a whole motor step, as the firmware will.
    fn to_step(&self, deg: f64) -> f64 {
        (deg * self.info.steps_per_deg).round() / self.info.steps_per_deg
    }

    /// Polls `?` until the table is idle within half a step of `target_fw`. A table whose
    /// angle does not change for a whole reply timeout while short of its target has stalled;
    /// one that rests elsewhere for as long lost its move.
    fn wait_arrival(&mut self, target_fw: f64, command: &str) -> Result<f64, TurntableError> {
        let mut last: Option<(f64, Instant)> = None;
        let started = Instant::now();
        let mut allowed: Option<Duration> = None;
        loop {
            if self.stop.as_ref().is_some_and(|s| s.load(std::sync::atomic::Ordering::SeqCst)) {
                return Err(TurntableError::Aborted { port: self.path.clone(), command: command.into() });
            }
            let (state, pos) = self.status()?;
            // An overall deadline: twice the trapezoid's time from here, and 10 s more.
            let (feed, accel) = (self.config.feed_deg_s.max(1e-3), self.config.accel_deg_s2.max(1e-3));
            let allowed = *allowed.get_or_insert_with(|| Duration::from_secs_f64(2.0 * ((target_fw - pos).abs() / feed + feed / accel) + 10.0));
            if started.elapsed() > allowed {
                return Err(TurntableError::TooSlow { port: self.path.clone(), command: command.into(), waited_s: allowed.as_secs_f64(), at_deg: pos });
            }
            if state == TableState::Alarm {
                return Err(TurntableError::Rejected { port: self.path.clone(), command: command.into(), reply: "the firmware is in its alarm state".into() });
            }
            if !state.moving() && (pos - target_fw).abs() <= self.half_step() {
                return Ok(pos);
            }
            match last {
                Some((prev, since)) if (pos - prev).abs() < self.config.stall_tolerance_deg => {
                    if since.elapsed() >= self.config.reply_timeout {
                        return Err(if state.moving() {
                            TurntableError::Stalled { port: self.path.clone(), command: command.into(), target_deg: target_fw, at_deg: pos }
                        } else {
                            TurntableError::StoppedShort { port: self.path.clone(), command: command.into(), target_deg: target_fw, at_deg: pos, state: state.name() }
                        });
                    }
                }
                _ => last = Some((pos, Instant::now())),
            }
            std::thread::sleep(POLL);
        }
    }

    /// `M17` unless the motor is on: the firmware accepts moves with it off, and counts
    /// steps the table never turns.
    fn energise(&mut self) -> Result<(), TurntableError> {
        if !self.motor_on {
            self.command("M17")?;
            self.motor_on = true;
        }
        Ok(())
    }

    /// Firmware degrees for spinscan's `table_deg`, rounded to a whole step.
    fn target_fw(&self, table_deg: f64) -> f64 {
        self.to_step(table_deg * self.config.direction as f64)
    }
}

impl Turntable for HorusTurntable {
    fn move_to(&mut self, table_deg: f64) -> Result<f64, TurntableError> {
        let _span = tracing::info_span!("turntable_move", port = %self.path, table_deg).entered();
        let target_fw = self.target_fw(table_deg);
        let command = format!("G1 X{target_fw:.3}");
        self.energise()?;
        self.command(&command)?;
        let at = self.wait_arrival(target_fw, &command)?;
        std::thread::sleep(self.config.settle);
        Ok(at * self.config.direction as f64)
    }

    fn angle(&mut self) -> Result<f64, TurntableError> {
        let (_, pos) = self.status()?;
        Ok(pos * self.config.direction as f64)
    }

    fn angle_at(&mut self, t_ns: u64) -> Result<f64, TurntableError> {
        let now = self.angle()?;
        Ok(interpolate(&self.samples, t_ns).map_or(now, |fw| fw * self.config.direction as f64))
    }

    fn start_move(&mut self, table_deg: f64, feed_deg_s: f64) -> Result<(), TurntableError> {
        let target_fw = self.target_fw(table_deg);
        self.energise()?;
        self.command(&format!("G1 X{target_fw:.3} F{feed_deg_s:.3}"))
    }

    /// Feed hold, wait for rest, then reset: a reset during motion would raise the alarm.
    fn halt(&mut self) -> Result<(), TurntableError> {
        let command = "! (feed hold)";
        self.write_bytes(b"!", command)?;
        // Deceleration from the feed takes feed / accel; a table that will not come to rest
        // within that and 5 s more is not waited for.
        let bound = Duration::from_secs_f64(self.config.feed_deg_s.max(0.0) / self.config.accel_deg_s2.max(1e-3)).min(Duration::from_secs(60)) + Duration::from_secs(5);
        let deadline = Instant::now() + bound;
        loop {
            let (state, _) = self.status()?;
            if matches!(state, TableState::Queue | TableState::Idle | TableState::Alarm) {
                break;
            }
            if Instant::now() > deadline {
                return Err(TurntableError::Unresponsive { port: self.path.clone(), command: command.into(), timeout_ms: bound.as_millis() as u64, tries: 1 });
            }
            std::thread::sleep(POLL);
        }
        self.reset()?;
        self.setup()
    }

    fn resolution_deg(&self) -> f64 {
        1.0 / self.info.steps_per_deg
    }

    fn release(&mut self) -> Result<(), TurntableError> {
        self.command("M18")?;
        self.motor_on = false;
        Ok(())
    }

    fn watch_stop(&mut self, stop: std::sync::Arc<std::sync::atomic::AtomicBool>) {
        self.stop = Some(stop);
    }

    fn describe(&self) -> String {
        format!("Horus turntable on {}", self.path)
    }
}

/// The position at `t_ns` by linear interpolation between the status samples around it (or
/// the two nearest, within one sample interval beyond them); None with fewer than two.
fn interpolate(samples: &VecDeque<(u64, f64)>, t_ns: u64) -> Option<f64> {
    if samples.len() < 2 {
        return None;
    }
    let pairs = samples.iter().zip(samples.iter().skip(1));
    let (a, b) = pairs.clone().find(|(a, b)| a.0 <= t_ns && t_ns <= b.0).or_else(|| {
        let (first, last) = (samples.front()?, samples.back()?);
        if t_ns < first.0 {
            pairs.clone().next()
        } else if t_ns > last.0 {
            Some((&samples[samples.len() - 2], last))
        } else {
            None
        }
    })?;
    let span = b.0.saturating_sub(a.0);
    if span == 0 {
        return Some(b.1);
    }
    // Replies far apart say nothing of the motion between them: the nearer one.
    if span > MAX_SAMPLE_GAP_NS {
        return Some(if t_ns.abs_diff(a.0) < t_ns.abs_diff(b.0) { a.1 } else { b.1 });
    }
    // Beyond the samples, extrapolate at most one interval.
    let t = (t_ns as f64 - a.0 as f64) / span as f64;
    let t = t.clamp(-1.0, 2.0);
    Some(a.1 + (b.1 - a.1) * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replies_are_classified() {
        assert_eq!(classify("ok"), Ok(Reply::Ok));
        assert_eq!(classify("error: Unsupported statement"), Ok(Reply::Error("Unsupported statement".into())));
        assert_eq!(classify("<Run,MPos:-12.500,0.000,0.000>"), Ok(Reply::Status { state: TableState::Run, position_deg: -12.5 }));
        assert_eq!(classify("<Idle,MPos:3.000,0.000,0.000,WPos:3.000,0.000,0.000>"), Ok(Reply::Status { state: TableState::Idle, position_deg: 3.0 }));
        assert_eq!(classify("<Queue,MPos:1.012,0.000,0.000>"), Ok(Reply::Status { state: TableState::Queue, position_deg: 1.012 }));
        assert_eq!(classify("ALARM: Abort during cycle"), Ok(Reply::Alarm("ALARM: Abort during cycle".into())));
        assert_eq!(classify("$100=8.889 (x, step/deg)"), Ok(Reply::Setting(100, 8.889)));
        assert!(classify("<Dancing,MPos:1.000,0.000,0.000>").is_err());
        assert_eq!(classify("Horus 0.2 ['$' for help]"), Ok(Reply::Greeting("Horus 0.2 ['$' for help]".into())));
        assert!(classify("<Idle,MPos:abc>").is_err());
        assert!(matches!(classify("\u{7f}#ok?"), Ok(Reply::Noise(_))));
    }

    #[test]
    fn angles_are_interpolated_to_the_frame_time() {
        let s: VecDeque<(u64, f64)> = [(1_000, 10.0), (2_000, 12.0), (3_000, 14.0)].into_iter().collect();
        assert_eq!(interpolate(&s, 1_500), Some(11.0));
        assert_eq!(interpolate(&s, 3_000), Some(14.0));
        // Just past the newest reply: extrapolated along the last interval, not frozen.
        assert_eq!(interpolate(&s, 3_500), Some(15.0));
        assert_eq!(interpolate(&s, 500), Some(9.0));
        assert_eq!(interpolate(&VecDeque::from([(1_000, 10.0)]), 1_500), None);
    }
}
