//! The Horus turntable over serial: spinscan's driver for the Horus firmware
//! (`shared/spec/turntable-protocol.md`).
//!
//! ```text
//!  move_to(θ) ── "G1 X<θ·direction>" ─> ok ── "G4 P0" ─> ok (arrived) ── settle ─> capture
//!  angle()    ── '?' ─> <Idle,MPos:12.000,0.000,0.000>
//! ```
//!
//! Replies are read line by line with a deadline. A line that is not `ok`, `error: …`, a
//! status report or the greeting is line noise: logged and skipped. A command whose `ok`
//! does not come in time is sent again (every command spinscan sends is absolute, so a
//! repeat is harmless) up to `retries` times, then the device counts as unresponsive. While
//! waiting for arrival the driver polls `?`: a table whose angle stops changing short of the
//! target has stalled. Read or write failures and end-of-file mean the device vanished.
//! Every error names the port and the command.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use serialport::SerialPort;

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
        }
    }
}

/// A reply line, classified.
#[derive(Debug, Clone, PartialEq)]
enum Reply {
    Ok,
    Error(String),
    Status { running: bool, position_deg: f64 },
    Greeting(String),
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
    if line.starts_with("Horus") || line.starts_with("Grbl") {
        return Ok(Reply::Greeting(line.to_string()));
    }
    if let Some(body) = line.strip_prefix('<') {
        let bad = || UnreadableStatus(line.to_string());
        let body = body.strip_suffix('>').ok_or_else(bad)?;
        let (state, rest) = body.split_once(',').ok_or_else(bad)?;
        let mpos = rest.strip_prefix("MPos:").ok_or_else(bad)?;
        let first = mpos.split(',').next().unwrap_or_default();
        let position_deg: f64 = first.parse().map_err(|_| bad())?;
        return Ok(Reply::Status { running: !state.eq_ignore_ascii_case("Idle"), position_deg });
    }
    Ok(Reply::Noise(line.to_string()))
}

/// The Horus serial driver.
pub struct HorusTurntable {
    port: Box<dyn SerialPort>,
    path: String,
    config: DriverConfig,
    pending: Vec<u8>,
}

enum ReadOutcome {
    Line(String),
    TimedOut,
}

impl HorusTurntable {
    /// Opens `path`, resets the board (Ctrl-X), checks its greeting, switches the motor on
    /// and sets feed and acceleration.
    pub fn open(path: &str, config: DriverConfig) -> Result<HorusTurntable, TurntableError> {
        let _span = tracing::info_span!("turntable_open", port = path).entered();
        let port = serialport::new(path, config.baud)
            .timeout(Duration::from_millis(20))
            .open()
            .map_err(|e| TurntableError::Open { port: path.to_string(), what: e.to_string() })?;
        let mut t = HorusTurntable { port, path: path.to_string(), config, pending: Vec::new() };
        t.reset()?;
        t.setup()?;
        tracing::info!(port = path, "turntable ready");
        Ok(t)
    }

    /// Motor on, acceleration and the step feed (after open and after a reset).
    fn setup(&mut self) -> Result<(), TurntableError> {
        self.command("M17")?;
        let (feed, accel) = (self.config.feed_deg_s, self.config.accel_deg_s2);
        self.command(&format!("$120={accel:.3}"))?;
        self.command(&format!("G1 F{feed:.3}"))
    }

    /// Ctrl-X, then waits for the greeting.
    pub fn reset(&mut self) -> Result<(), TurntableError> {
        let command = "Ctrl-X (reset)";
        self.write_bytes(&[0x18], command)?;
        let waited = self.config.reply_timeout * self.config.tries.max(1);
        let deadline = Instant::now() + waited;
        loop {
            match self.read_line(deadline, command)? {
                ReadOutcome::TimedOut => return Err(TurntableError::NoGreeting { port: self.path.clone(), waited_ms: waited.as_millis() as u64 }),
                ReadOutcome::Line(line) => match classify(&line) {
                    Ok(Reply::Greeting(g)) => {
                        let words: Vec<&str> = g.split_whitespace().take(2).collect();
                        if words.join(" ") != SUPPORTED_FIRMWARE {
                            return Err(TurntableError::UnsupportedFirmware { port: self.path.clone(), greeting: g, expected: SUPPORTED_FIRMWARE });
                        }
                        return Ok(());
                    }
                    _ => tracing::debug!(port = %self.path, line, "ignoring a line before the greeting"),
                },
            }
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
        self.command_with_timeout(command, self.config.reply_timeout)
    }

    fn command_with_timeout(&mut self, command: &str, timeout: Duration) -> Result<(), TurntableError> {
        let _span = tracing::debug_span!("turntable_command", port = %self.path, command).entered();
        for attempt in 1..=self.config.tries.max(1) {
            // Drop whatever a previous, abandoned exchange left behind (a late `ok`).
            self.pending.clear();
            let _ = self.port.clear(serialport::ClearBuffer::Input);
            self.write_bytes(format!("{command}\n").as_bytes(), command)?;
            let deadline = Instant::now() + timeout;
            loop {
                match self.read_line(deadline, command)? {
                    ReadOutcome::TimedOut => {
                        tracing::warn!(port = %self.path, command, attempt, "no reply in time");
                        break;
                    }
                    ReadOutcome::Line(line) => match classify(&line) {
                        Ok(Reply::Ok) => return Ok(()),
                        Ok(Reply::Error(reply)) => return Err(TurntableError::Rejected { port: self.path.clone(), command: command.to_string(), reply }),
                        Ok(Reply::Greeting(g)) => {
                            // The board reset under us (power glitch): what was queued is lost.
                            tracing::warn!(port = %self.path, greeting = g, "the board reset during a command");
                        }
                        Ok(other) => tracing::debug!(port = %self.path, ?other, "ignoring"),
                        Err(UnreadableStatus(noise)) => tracing::warn!(port = %self.path, line = noise, "ignoring a malformed status line"),
                    },
                }
            }
        }
        Err(TurntableError::Unresponsive {
            port: self.path.clone(),
            command: command.to_string(),
            timeout_ms: timeout.as_millis() as u64,
            tries: self.config.tries.max(1),
        })
    }

    /// The firmware position (`?`), and whether the table is moving.
    fn status(&mut self) -> Result<(bool, f64), TurntableError> {
        let command = "? (status)";
        for _ in 0..self.config.tries.max(1) {
            self.write_bytes(b"?", command)?;
            let deadline = Instant::now() + self.config.reply_timeout;
            loop {
                match self.read_line(deadline, command)? {
                    ReadOutcome::TimedOut => break,
                    ReadOutcome::Line(line) => match classify(&line) {
                        Ok(Reply::Status { running, position_deg }) => return Ok((running, position_deg)),
                        Err(UnreadableStatus(reply)) => return Err(TurntableError::BadStatus { port: self.path.clone(), reply }),
                        Ok(_) => {} // an `ok` of an earlier line, or noise
                    },
                }
            }
        }
        Err(TurntableError::Unresponsive {
            port: self.path.clone(),
            command: command.into(),
            timeout_ms: self.config.reply_timeout.as_millis() as u64,
            tries: self.config.tries.max(1),
        })
    }

    /// Waits for `G4 P0`'s `ok` (arrival). Its wait is as long as the move; while it is
    /// silent, `?` tells a table still on its way from a stalled one, and a lost `ok` from
    /// a lost table.
    fn wait_arrival(&mut self, target_fw: f64) -> Result<(), TurntableError> {
        let command = "G4 P0";
        self.pending.clear();
        self.write_bytes(b"G4 P0\n", command)?;
        let mut last: Option<f64> = None;
        let mut silent_polls = 0;
        loop {
            let deadline = Instant::now() + self.config.reply_timeout;
            loop {
                match self.read_line(deadline, command)? {
                    ReadOutcome::TimedOut => break,
                    ReadOutcome::Line(line) => match classify(&line) {
                        Ok(Reply::Ok) => return Ok(()),
                        Ok(Reply::Error(reply)) => return Err(TurntableError::Rejected { port: self.path.clone(), command: command.into(), reply }),
                        _ => tracing::warn!(port = %self.path, line, "ignoring an unexpected line while waiting for arrival"),
                    },
                }
            }
            // Silent for a whole reply timeout: look at the table.
            self.write_bytes(b"?", "? (status)")?;
            let deadline = Instant::now() + self.config.reply_timeout;
            let mut status = None;
            loop {
                match self.read_line(deadline, command)? {
                    ReadOutcome::TimedOut => break,
                    ReadOutcome::Line(line) => match classify(&line) {
                        Ok(Reply::Ok) => return Ok(()),
                        Ok(Reply::Status { running, position_deg }) => {
                            status = Some((running, position_deg));
                            break;
                        }
                        Ok(Reply::Error(reply)) => return Err(TurntableError::Rejected { port: self.path.clone(), command: command.into(), reply }),
                        _ => {}
                    },
                }
            }
            match status {
                None => {
                    silent_polls += 1;
                    if silent_polls >= self.config.tries.max(1) {
                        return Err(TurntableError::Unresponsive {
                            port: self.path.clone(),
                            command: command.into(),
                            timeout_ms: self.config.reply_timeout.as_millis() as u64,
                            tries: silent_polls,
                        });
                    }
                }
                Some((false, pos)) if (pos - target_fw).abs() < 1e-3 => {
                    // Idle at the target: the `ok` was lost on the line.
                    tracing::warn!(port = %self.path, "arrival `ok` lost; the table is idle at its target");
                    return Ok(());
                }
                Some((_, pos)) => {
                    // Short of the target (or idle elsewhere): it must still be moving.
                    silent_polls = 0;
                    if let Some(prev) = last {
                        if (pos - prev).abs() < self.config.stall_tolerance_deg {
                            return Err(TurntableError::Stalled { port: self.path.clone(), command: command.into(), target_deg: target_fw, at_deg: pos });
                        }
                    }
                    last = Some(pos);
                }
            }
        }
    }
}

impl Turntable for HorusTurntable {
    fn move_to(&mut self, table_deg: f64) -> Result<(), TurntableError> {
        let _span = tracing::info_span!("turntable_move", port = %self.path, table_deg).entered();
        let target_fw = table_deg * self.config.direction as f64;
        // Three decimals: the precision of the firmware's status report.
        let target_fw = (target_fw * 1000.0).round() / 1000.0;
        self.command(&format!("G1 X{target_fw:.3}"))?;
        self.wait_arrival(target_fw)?;
        std::thread::sleep(self.config.settle);
        Ok(())
    }

    fn angle(&mut self) -> Result<f64, TurntableError> {
        let (_, pos) = self.status()?;
        Ok(pos * self.config.direction as f64)
    }

    fn start_move(&mut self, table_deg: f64, feed_deg_s: f64) -> Result<(), TurntableError> {
        let target_fw = (table_deg * self.config.direction as f64 * 1000.0).round() / 1000.0;
        self.command(&format!("G1 X{target_fw:.3} F{feed_deg_s:.3}"))
    }

    fn halt(&mut self) -> Result<(), TurntableError> {
        self.reset()?;
        self.setup()
    }

    fn describe(&self) -> String {
        format!("Horus turntable on {}", self.path)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replies_are_classified() {
        assert_eq!(classify("ok"), Ok(Reply::Ok));
        assert_eq!(classify("error: Unsupported statement"), Ok(Reply::Error("Unsupported statement".into())));
        assert_eq!(classify("<Run,MPos:-12.500,0.000,0.000>"), Ok(Reply::Status { running: true, position_deg: -12.5 }));
        assert_eq!(classify("<Idle,MPos:3.000,0.000,0.000>"), Ok(Reply::Status { running: false, position_deg: 3.0 }));
        assert_eq!(classify("Horus 0.2 ['$' for help]"), Ok(Reply::Greeting("Horus 0.2 ['$' for help]".into())));
        assert!(classify("<Idle,MPos:abc>").is_err());
        assert!(matches!(classify("\u{7f}#ok?"), Ok(Reply::Noise(_))));
    }
}
