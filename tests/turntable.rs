//! The turntable: hw-sim's firmware emulator on a pseudo-terminal, checked against the
//! protocol spec by a raw client written here from the spec alone, and spinscan's driver
//! run against it in every fault mode.

use std::io::{Read, Write};
use std::time::{Duration, Instant};

use hw_sim::{Emulator, FirmwareConfig, TableAngle, TurntableFault};
use spinscan::hw::{DriverConfig, HorusTurntable, Turntable, TurntableError};

/// A bare client that speaks the spec: bytes out, lines in.
struct RawClient {
    port: Box<dyn serialport::SerialPort>,
    buf: Vec<u8>,
}

impl RawClient {
    fn open(path: &str) -> RawClient {
        let port = serialport::new(path, 115_200).timeout(Duration::from_millis(10)).open().unwrap();
        RawClient { port, buf: Vec::new() }
    }

    fn send(&mut self, bytes: &[u8]) {
        self.port.write_all(bytes).unwrap();
    }

    /// The next non-empty line within `timeout`, without its `\r\n`.
    fn line(&mut self, timeout: Duration) -> Option<String> {
        let end = Instant::now() + timeout;
        loop {
            while let Some(i) = self.buf.iter().position(|&b| b == b'\n') {
                let raw: Vec<u8> = self.buf.drain(..=i).collect();
                let text = String::from_utf8_lossy(&raw).trim_end_matches(['\r', '\n']).to_string();
                if !text.is_empty() {
                    return Some(text);
                }
            }
            if Instant::now() > end {
                return None;
            }
            let mut b = [0u8; 64];
            if let Ok(n) = self.port.read(&mut b) {
                self.buf.extend_from_slice(&b[..n]);
            }
        }
    }

    fn ask(&mut self, command: &str) -> String {
        self.send(format!("{command}\n").as_bytes());
        self.line(Duration::from_secs(2)).unwrap_or_else(|| panic!("no reply to {command}"))
    }

    /// `(state, first MPos value)` from a `?` report.
    fn status(&mut self) -> (String, f64) {
        self.send(b"?");
        let line = self.line(Duration::from_secs(1)).expect("status report");
        let inner = line.strip_prefix('<').and_then(|l| l.strip_suffix('>')).unwrap_or_else(|| panic!("not a status report: {line}"));
        let (state, rest) = inner.split_once(",MPos:").unwrap();
        (state.to_string(), rest.split(',').next().unwrap().parse().unwrap())
    }
}

/// A board whose bootloader takes `BOOT` after the port opens (a real one: about 2 s).
const BOOT: Duration = Duration::from_millis(300);

fn emulator(faults: Vec<TurntableFault>) -> (Emulator, TableAngle) {
    let angle = TableAngle::new(0.0);
    let cfg = FirmwareConfig { faults, boot_delay: BOOT, ..FirmwareConfig::default() };
    (Emulator::spawn(cfg, angle.clone()).unwrap(), angle)
}

fn quick_driver() -> DriverConfig {
    DriverConfig { reply_timeout: Duration::from_millis(200), feed_deg_s: 200.0, accel_deg_s2: 800.0, settle: Duration::ZERO, boot_wait: Duration::from_secs(3), ..DriverConfig::default() }
}

/// Half a motor step at the Horus default of 8.889 steps per degree.
const HALF_STEP: f64 = 0.5 / 8.889;

impl RawClient {
    /// Polls `?` until the state is one of `states`; the last report.
    fn wait_state(&mut self, states: &[&str]) -> (String, f64) {
        let end = Instant::now() + Duration::from_secs(10);
        loop {
            let s = self.status();
            if states.contains(&s.0.as_str()) || Instant::now() > end {
                return s;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Every line of one reply up to and including its `ok` or `error:`.
    fn ask_all(&mut self, command: &str) -> Vec<String> {
        self.send(format!("{command}\n").as_bytes());
        let mut lines = Vec::new();
        while let Some(l) = self.line(Duration::from_secs(2)) {
            let end = l == "ok" || l.starts_with("error:");
            lines.push(l);
            if end {
                break;
            }
        }
        lines
    }
}

/// The revised spec (`shared/spec/turntable-protocol.md`, read from the Horus 0.2 firmware),
/// line by line, by a client written from the spec alone.
#[test]
fn emulator_conforms_to_the_protocol_spec() {
    let (emu, angle) = emulator(vec![]);
    // Opening the port resets the board: nothing until the bootloader is done, then the
    // greeting on a line of its own.
    let t0 = Instant::now();
    let mut c = RawClient::open(emu.port_path());
    assert_eq!(c.line(Duration::from_secs(3)).as_deref(), Some("Horus 0.2 ['$' for help]"));
    assert!(t0.elapsed() >= BOOT.mul_f64(0.9), "greeting after {:?}, before the boot delay", t0.elapsed());
    // Settings: steps per degree, max rate, acceleration, then ok.
    let settings = c.ask_all("$$");
    assert!(settings[0].starts_with("$100=8.889") && settings[1].starts_with("$110=") && settings[2].starts_with("$120="), "{settings:?}");
    assert_eq!(settings.last().unwrap(), "ok");
    // The firmware accepts a move with the motor off and counts it; the table does not turn.
    assert_eq!(c.ask("G1 X10"), "ok");
    let (state, pos) = c.wait_state(&["Idle"]);
    assert_eq!((state.as_str(), pos), ("Idle", 10.012), "10° rounds to 89 steps");
    assert_eq!(angle.get(), 0.0, "motor off: the table stayed");
    assert_eq!(c.ask("M17"), "ok");
    assert_eq!(c.ask("$120=400"), "ok");
    assert_eq!(c.ask("G1 F200"), "ok");
    // `ok` as soon as the move is queued, before it ends; spaces optional, letters any case.
    let t0 = Instant::now();
    assert_eq!(c.ask("g1x30"), "ok");
    assert!(t0.elapsed() < Duration::from_millis(100));
    std::thread::sleep(Duration::from_millis(60));
    let (state, pos) = c.status();
    assert_eq!(state, "Run");
    assert!(pos > 10.0 && pos < 30.0, "on its way: {pos}");
    let (state, pos) = c.wait_state(&["Idle"]);
    assert_eq!((state.as_str(), pos), ("Idle", 30.037), "a whole step: 267 / 8.889");
    assert!((angle.get() - (30.037 - 10.012)).abs() < 2e-3, "turned with the motor on only: {}", angle.get());
    // Whole steps: `G1 X2` ends at 2.025°.
    assert_eq!(c.ask("G1 X2"), "ok");
    assert_eq!(c.wait_state(&["Idle"]).1, 2.025);
    // No dwell, no rapid, no modes, no other words: refused in the firmware's words.
    for refused in ["G4 P0", "G0 X1", "G90", "G91", "G1 X5 P1", "M999"] {
        assert_eq!(c.ask(refused), "error: Unsupported command", "{refused}");
    }
    assert_eq!(c.ask("G1 X1.2.3"), "error: Bad number format");
    // Absolute moves, negative allowed; feed and move on one line.
    assert_eq!(c.ask("G1 X-5 F400"), "ok");
    assert_eq!(c.wait_state(&["Idle"]).1, -4.950, "−44 steps");
    // G50 makes here the new zero; the physical angle does not change.
    let before = angle.get();
    assert_eq!(c.ask("G50"), "ok");
    assert_eq!(c.status().1, 0.0);
    assert_eq!(angle.get(), before);
    assert_eq!(c.ask("M71 T1"), "ok");
    assert_eq!(c.ask("M70 T1"), "ok");
    let m50 = c.ask_all("M50");
    assert!(m50.len() == 2 && m50[1] == "ok", "M50 prints a value, then ok: {m50:?}");
    // Feed hold: Hold while decelerating, then Queue (the rest waits); `~` resumes.
    assert_eq!(c.ask("G1 X400"), "ok");
    std::thread::sleep(Duration::from_millis(150));
    c.send(b"!");
    let (held, at) = c.wait_state(&["Queue"]);
    assert!(held == "Queue" && at > 0.0 && at < 400.0, "{held} at {at}");
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(c.status(), ("Queue".to_string(), at), "no motion while held");
    c.send(b"~");
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(c.status().0, "Run");
    // Stopped the safe way (hold, wait, reset): no alarm.
    c.send(b"!");
    c.wait_state(&["Queue"]);
    c.send(&[0x18]);
    assert_eq!(c.line(Duration::from_secs(1)).as_deref(), Some("Horus 0.2 ['$' for help]"));
    assert!(c.line(Duration::from_millis(200)).is_none(), "nothing after the greeting");
    assert_eq!(c.status().0, "Idle");
    // A reset during motion raises the alarm; G-code is locked until `$X`.
    assert_eq!(c.ask("M17"), "ok");
    assert_eq!(c.ask("G1 X300"), "ok");
    std::thread::sleep(Duration::from_millis(100));
    c.send(&[0x18]);
    assert_eq!(c.line(Duration::from_secs(1)).as_deref(), Some("ALARM: Abort during cycle"));
    assert_eq!(c.line(Duration::from_secs(1)).as_deref(), Some("Horus 0.2 ['$' for help]"));
    assert_eq!(c.line(Duration::from_secs(1)).as_deref(), Some("['$H'|'$X' to unlock]"));
    assert_eq!(c.status().0, "Alarm");
    assert_eq!(c.ask("G1 X5"), "error: Alarm lock");
    assert_eq!(c.ask_all("$X"), vec!["[Caution: Unlocked]".to_string(), "ok".to_string()]);
    let (state, stopped) = c.status();
    assert_eq!(state, "Idle");
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(c.status().1, stopped, "no motion after the reset");
    assert_eq!(c.ask("G1 X5"), "ok", "unlocked");
    // Reopening the port resets the board again: the position restarts at zero.
    c.wait_state(&["Idle"]);
    drop(c);
    std::thread::sleep(Duration::from_millis(50));
    let mut c = RawClient::open(emu.port_path());
    assert_eq!(c.line(Duration::from_secs(3)).as_deref(), Some("Horus 0.2 ['$' for help]"));
    assert_eq!(c.status(), ("Idle".to_string(), 0.0));
}

/// Defect 1 (`G4 P0` is refused by the real firmware) and 6 (targets round to whole steps):
/// arrival is polled, the angle read back is returned, and a target a step rounds away from is
/// not taken for a stall.
#[test]
fn driver_moves_waits_and_reports_the_angle() {
    let (emu, angle) = emulator(vec![]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    assert_eq!(t.info().steps_per_deg, 8.889);
    assert!((t.resolution_deg() - 1.0 / 8.889).abs() < 1e-12);
    for target in [12.0, 24.5, -3.0, 370.0, 2.0] {
        let arrived = t.move_to(target).unwrap();
        assert!((arrived - target).abs() <= HALF_STEP, "{target}: arrived at {arrived}");
        assert!((t.angle().unwrap() - arrived).abs() < 1e-9, "the angle read back is returned");
        assert!((angle.get() - arrived).abs() < 2e-3, "physical angle {}", angle.get());
    }
    assert_eq!(t.move_to(2.0).unwrap(), 2.025, "`G1 X2` ends at 2.025°");
    assert!(t.describe().contains(emu.port_path()));
}

/// Defect 6: the move's `ok` is lost and the table is found idle at the rounded target —
/// arrived, not stalled.
#[test]
fn an_idle_table_within_half_a_step_has_arrived() {
    // Lines: 1 $$, 2 M17, 3 $120, 4 G1 F, 5 G1 X2.
    let (emu, _) = emulator(vec![TurntableFault::MissOk { line: 5 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    assert_eq!(t.move_to(2.0).unwrap(), 2.025);
}

/// Risk 7: opening the port resets the board; its greeting comes after the bootloader. A
/// driver that sends Ctrl-X into the bootloader and waits briefly reports no greeting.
#[test]
fn driver_waits_for_the_power_on_greeting() {
    let angle = TableAngle::new(0.0);
    let cfg = FirmwareConfig { boot_delay: Duration::from_millis(1500), ..FirmwareConfig::default() };
    let emu = Emulator::spawn(cfg, angle).unwrap();
    let t0 = Instant::now();
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    assert!(t0.elapsed() >= Duration::from_millis(1400), "opened after {:?}", t0.elapsed());
    assert_eq!(t.info().firmware, "Horus 0.2 ['$' for help]");
    assert!(t.move_to(5.0).is_ok());
}

/// Risk 7: a greeting in the middle of a scan means the board reset and lost its position:
/// the driver says so instead of carrying on at a wrong angle.
#[test]
fn a_board_that_resets_mid_scan_is_reported() {
    // Lines: 1 $$, 2 M17, 3 $120, 4 G1 F, 5 G1 X10 (ok), 6 G1 X20: the board resets.
    let (emu, _) = emulator(vec![TurntableFault::Reset { line: 6 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    t.move_to(10.0).unwrap();
    let e = t.move_to(20.0).unwrap_err();
    assert!(matches!(e, TurntableError::BoardReset { .. }), "{e}");
    assert!(e.to_string().contains("position is lost") && e.to_string().contains(emu.port_path()), "{e}");
}

/// Defect 2: a continuous move stopped with Ctrl-X raises the alarm and locks every later
/// line; `halt` stops with a feed hold first, so the next move runs.
#[test]
fn halting_a_moving_table_leaves_no_alarm() {
    let (emu, _) = emulator(vec![]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    t.start_move(300.0, 90.0).unwrap();
    std::thread::sleep(Duration::from_millis(200));
    t.halt().unwrap();
    assert_ne!(t.status().unwrap().0, spinscan::hw::TableState::Alarm);
    let arrived = t.move_to(10.0).unwrap();
    assert!((arrived - 10.0).abs() <= HALF_STEP);
}

/// The driver unlocks an alarm it finds (a reset during motion by someone else).
#[test]
fn driver_unlocks_an_alarm_after_a_reset_in_motion() {
    let (emu, _) = emulator(vec![TurntableFault::Stall { at_deg: 5.0 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    assert!(t.move_to(30.0).is_err());
    // The stalled move still runs in the firmware: Ctrl-X now raises the alarm.
    t.reset().unwrap();
    assert_eq!(t.status().unwrap().0, spinscan::hw::TableState::Idle, "unlocked with $X");
}

/// Risk 11: the motor is switched off at the end of a scan, and on again before a move.
#[test]
fn the_motor_is_released_and_energised_again() {
    let (emu, angle) = emulator(vec![]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    t.move_to(10.0).unwrap();
    t.release().unwrap();
    let arrived = t.move_to(20.0).unwrap();
    assert!((angle.get() - arrived).abs() < 2e-3, "the table turned after M18: M17 was sent again ({} vs {arrived})", angle.get());
}

#[test]
fn driver_turns_continuously_and_halts_where_it_is() {
    let (emu, angle) = emulator(vec![]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    // A slow move returns at once and the angle follows it.
    let t0 = Instant::now();
    t.start_move(90.0, 45.0).unwrap();
    assert!(t0.elapsed() < Duration::from_millis(300), "start_move waits for the queue only");
    std::thread::sleep(Duration::from_millis(400));
    let mid = t.angle().unwrap();
    assert!(mid > 1.0 && mid < 60.0, "on its way: {mid}");
    assert!((angle.get() - mid).abs() < 5.0, "the cameras see the table turning: {} vs {mid}", angle.get());
    // Halt: no motion after, and the step feed is back (a step move runs at 200°/s again).
    t.halt().unwrap();
    let stopped = t.angle().unwrap();
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(t.angle().unwrap(), stopped);
    assert!(stopped < 90.0);
    let t1 = Instant::now();
    t.move_to(stopped + 40.0).unwrap();
    assert!(t1.elapsed() < Duration::from_millis(800), "step feed restored: {:?}", t1.elapsed());
}

#[test]
fn driver_direction_maps_firmware_degrees_to_table_degrees() {
    // A board wired the other way round: positive X turns the table clockwise.
    let angle = TableAngle::new(0.0);
    let emu = Emulator::spawn(FirmwareConfig { direction: -1.0, boot_delay: BOOT, ..FirmwareConfig::default() }, angle.clone()).unwrap();
    let mut t = HorusTurntable::open(emu.port_path(), DriverConfig { direction: -1, ..quick_driver() }).unwrap();
    let arrived = t.move_to(15.0).unwrap();
    assert!((arrived - 15.0).abs() <= HALF_STEP);
    assert!((angle.get() - arrived).abs() < 2e-3, "counterclockwise 15°, got {}", angle.get());
    assert!((t.angle().unwrap() - arrived).abs() < 1e-9);
}

#[test]
fn driver_survives_a_missing_ok_by_resending() {
    // Lines: 1 $$, 2 M17, 3 $120, 4 G1 F, 5 G1 X…. Lose the motor's ok, then the move's.
    for line in [2, 5] {
        let (emu, angle) = emulator(vec![TurntableFault::MissOk { line }]);
        let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
        let arrived = t.move_to(20.0).unwrap();
        assert!((angle.get() - arrived).abs() < 2e-3 && (arrived - 20.0).abs() <= HALF_STEP, "line {line}: at {}", angle.get());
    }
}

#[test]
fn driver_survives_garbage_instead_of_a_reply() {
    for line in [2, 5] {
        let (emu, angle) = emulator(vec![TurntableFault::Garbage { line }]);
        let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
        let arrived = t.move_to(8.0).unwrap();
        assert!((angle.get() - arrived).abs() < 2e-3 && (arrived - 8.0).abs() <= HALF_STEP);
    }
}

#[test]
fn driver_reports_a_stall_with_port_and_angle() {
    let (emu, _) = emulator(vec![TurntableFault::Stall { at_deg: 5.0 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    let e = t.move_to(30.0).unwrap_err();
    assert!(matches!(e, TurntableError::Stalled { .. }), "{e}");
    let msg = e.to_string();
    // The motor slips on a whole step: 5° is 44.4 steps, 44 steps are 4.950°.
    assert!(msg.contains(emu.port_path()) && msg.contains("stalled at 4.950°") && msg.contains("30.037°"), "{msg}");
    // Stopped the safe way, the table stays where it stalled; the driver can start again.
    t.halt().unwrap();
    assert!((t.angle().unwrap() - 5.0).abs() <= HALF_STEP, "after halt: {}", t.angle().unwrap());
}

#[test]
fn driver_reports_a_vanished_device() {
    let (emu, _) = emulator(vec![TurntableFault::Vanish { line: 5 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    let e = t.move_to(10.0).unwrap_err();
    assert!(matches!(e, TurntableError::Vanished { .. } | TurntableError::Unresponsive { .. }), "{e}");
    assert!(e.to_string().contains(emu.port_path()) && e.to_string().contains("G1 X10.012"), "{e}");
}

#[test]
fn driver_gives_up_on_a_silent_device_after_its_retries() {
    // Every reply to the move is lost: three tries, then a clear error.
    let (emu, _) = emulator(vec![TurntableFault::MissOk { line: 5 }, TurntableFault::MissOk { line: 6 }, TurntableFault::MissOk { line: 7 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    let e = t.move_to(10.0).unwrap_err().to_string();
    assert!(e.contains("did not answer `G1 X10.012` within 200 ms (3 tries)") && e.contains(emu.port_path()), "{e}");
}

#[test]
fn driver_refuses_other_firmware_and_missing_ports() {
    let angle = TableAngle::new(0.0);
    let emu = Emulator::spawn(FirmwareConfig { greeting: "Horus 0.1 ['$' for help]".into(), boot_delay: BOOT, ..FirmwareConfig::default() }, angle).unwrap();
    let e = HorusTurntable::open(emu.port_path(), quick_driver()).err().unwrap().to_string();
    assert!(e.contains("unsupported firmware") && e.contains("Horus 0.1"), "{e}");
    let e = HorusTurntable::open("/dev/spinscan-no-such-port", quick_driver()).err().unwrap().to_string();
    assert!(e.contains("cannot open turntable port /dev/spinscan-no-such-port"), "{e}");
}

/// `spinscan turntable`: one JSON object per action, against the emulator on its pty, each
/// waiting for the greeting as a real board needs.
#[test]
fn the_turntable_bench_command_talks_to_the_board() {
    let (emu, angle) = emulator(vec![]);
    let run = |args: &[&str]| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_spinscan")).args(["turntable", "--port", emu.port_path()]).args(args).output().unwrap();
        let text = String::from_utf8_lossy(&o.stdout).into_owned();
        (o.status.code(), serde_json::from_str::<serde_json::Value>(text.trim()).ok(), String::from_utf8_lossy(&o.stderr).into_owned())
    };
    let (code, info, err) = run(&["info"]);
    let info = info.unwrap_or_else(|| panic!("{err}"));
    assert_eq!(code, Some(0));
    assert_eq!((info["state"].as_str(), info["steps_per_deg"].as_f64(), info["firmware"].as_str()), (Some("Idle"), Some(8.889), Some("Horus 0.2 ['$' for help]")), "{info}");
    assert!(info["max_rate_deg_s"].as_f64().unwrap() > 0.0 && info["accel_deg_s2"].as_f64().unwrap() > 0.0);
    let (code, moved, err) = run(&["move", "30", "--speed", "200"]);
    let moved = moved.unwrap_or_else(|| panic!("{err}"));
    assert_eq!((code, moved["state"].as_str(), moved["angle_deg"].as_f64()), (Some(0), Some("Idle"), Some(30.037)), "{moved}");
    assert!((angle.get() - 30.037).abs() < 2e-3);
    // Stopped the safe way mid-move (the port reopened: the position counts from here).
    let (code, stopped, err) = run(&["move", "300", "--speed", "30", "--stop-after", "0.3"]);
    let stopped = stopped.unwrap_or_else(|| panic!("{err}"));
    assert_eq!((code, stopped["stopped"].as_bool()), (Some(0), Some(true)), "{stopped}");
    let a = stopped["angle_deg"].as_f64().unwrap();
    assert!(a > 0.5 && a < 300.0 && stopped["state"] == "Idle", "{stopped}");
    let (code, status, _) = run(&["status"]);
    assert_eq!((code, status.unwrap()["state"].as_str()), (Some(0), Some("Idle")), "no alarm left behind");
    let (code, off, _) = run(&["off"]);
    assert_eq!((code, off.unwrap()["motor"].as_str()), (Some(0), Some("off")));
    // A port that is not a board: a clear error, non-zero.
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_spinscan")).args(["turntable", "--port", "/dev/spinscan-no-such-port", "status"]).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(6));
    assert!(err.contains("cannot open turntable port"), "{err}");
}

/// Risk 11: the udev example covers the boards labs have (Arduino on ttyACM, FTDI on ttyUSB)
/// and identical cameras (by USB port), and says how to read the values.
#[test]
fn the_udev_example_covers_ftdi_boards_and_port_based_names() {
    let rules = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/systemd/99-spinscan.rules")).unwrap();
    for needed in ["ATTRS{idVendor}==\"2341\"", "ATTRS{idVendor}==\"0403\"", "ENV{ID_PATH}", "udevadm info", "SYMLINK+=\"spinscan-table\"", "SYMLINK+=\"spinscan-left\""] {
        assert!(rules.contains(needed), "{needed} missing from the udev example");
    }
}

/// Hardening (issue 17), 6: a table that takes forever is abandoned as soon as a stop is
/// requested, not after minutes.
#[test]
fn a_stop_request_ends_a_wait_for_arrival() {
    let (emu, _) = emulator(vec![]);
    // 0.5°/s to 300°: ten minutes of waiting.
    let mut t = HorusTurntable::open(emu.port_path(), DriverConfig { feed_deg_s: 0.5, ..quick_driver() }).unwrap();
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    t.watch_stop(stop.clone());
    let flag = stop.clone();
    std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(300));
        flag.store(true, std::sync::atomic::Ordering::SeqCst);
    });
    let t0 = Instant::now();
    let e = t.move_to(300.0).unwrap_err();
    assert!(matches!(e, TurntableError::Aborted { .. }), "{e}");
    assert!(t0.elapsed() < Duration::from_secs(2), "ended {:?} after the request", t0.elapsed());
    // And the table is stopped the safe way: no alarm, it can move again.
    t.halt().unwrap();
    stop.store(false, std::sync::atomic::Ordering::SeqCst);
    assert_ne!(t.status().unwrap().0, spinscan::hw::TableState::Alarm);
}
