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

fn emulator(faults: Vec<TurntableFault>) -> (Emulator, TableAngle) {
    let angle = TableAngle::new(0.0);
    let cfg = FirmwareConfig { faults, ..FirmwareConfig::default() };
    (Emulator::spawn(cfg, angle.clone()).unwrap(), angle)
}

fn quick_driver() -> DriverConfig {
    DriverConfig { reply_timeout: Duration::from_millis(200), feed_deg_s: 200.0, accel_deg_s2: 800.0, settle: Duration::ZERO, ..DriverConfig::default() }
}

#[test]
fn emulator_conforms_to_the_protocol_spec() {
    let (emu, angle) = emulator(vec![]);
    let mut c = RawClient::open(emu.port_path());
    c.send(&[0x18]);
    // The greeting, on a line of its own (a power-up greeting may come first).
    let mut greeting = c.line(Duration::from_secs(2)).unwrap();
    if let Some(again) = c.line(Duration::from_millis(100)) {
        greeting = again;
    }
    assert_eq!(greeting, "Horus 0.2 ['$' for help]");
    assert!(c.ask("G1 X10").starts_with("error:"), "moves are refused with the motor off");
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
    assert!(pos > 0.0 && pos < 30.0, "on its way: {pos}");
    // G4 P0 answers once the move has ended: 30° at 200°/s, 400°/s² takes 2·√(30/400) s.
    assert_eq!(c.ask("G4 P0"), "ok");
    let expected = 2.0 * (30.0f64 / 400.0).sqrt();
    assert!(t0.elapsed().as_secs_f64() >= expected * 0.95, "{:?} < {expected} s", t0.elapsed());
    assert_eq!(c.status(), ("Idle".to_string(), 30.0));
    assert!((angle.get() - 30.0).abs() < 1e-9, "the cameras see the table at 30°");
    // Absolute moves: back to −5 (negative allowed), feed and move on one line.
    assert_eq!(c.ask("G1 X-5 F400"), "ok");
    assert_eq!(c.ask("G4 P0"), "ok");
    assert_eq!(c.status().1, -5.0);
    // G50 makes here the new zero; the physical angle does not change.
    assert_eq!(c.ask("G50"), "ok");
    assert_eq!(c.status().1, 0.0);
    assert!((angle.get() + 5.0).abs() < 1e-9);
    assert_eq!(c.ask("M71 T1"), "ok");
    assert_eq!(c.ask("M70 T1"), "ok");
    assert!(c.ask("M999").starts_with("error:"));
    assert!(c.ask("G1 X1.2.3").starts_with("error:"));
    // Ctrl-X stops motion where it is.
    assert_eq!(c.ask("G1 X400"), "ok");
    std::thread::sleep(Duration::from_millis(100));
    c.send(&[0x18]);
    assert_eq!(c.line(Duration::from_secs(1)).unwrap(), "Horus 0.2 ['$' for help]");
    let (state, stopped) = c.status();
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(state, "Idle");
    assert_eq!(c.status().1, stopped, "no motion after reset");
    assert!(stopped > 0.0 && stopped < 400.0);
}

#[test]
fn driver_moves_waits_and_reports_the_angle() {
    let (emu, angle) = emulator(vec![]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    for target in [12.0, 24.5, -3.0, 370.0] {
        t.move_to(target).unwrap();
        assert!((t.angle().unwrap() - target).abs() < 1e-3);
        assert!((angle.get() - target).abs() < 1e-3, "physical angle {}", angle.get());
    }
    assert!(t.describe().contains(emu.port_path()));
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
    let emu = Emulator::spawn(FirmwareConfig { direction: -1.0, ..FirmwareConfig::default() }, angle.clone()).unwrap();
    let mut t = HorusTurntable::open(emu.port_path(), DriverConfig { direction: -1, ..quick_driver() }).unwrap();
    t.move_to(15.0).unwrap();
    assert!((angle.get() - 15.0).abs() < 1e-3, "counterclockwise 15°, got {}", angle.get());
    assert!((t.angle().unwrap() - 15.0).abs() < 1e-3);
}

#[test]
fn driver_survives_a_missing_ok_by_resending() {
    // Lines: 1 M17, 2 $120, 3 G1 F, 4 G1 X…, 5 G4 P0. Lose the move's ok, then the arrival's.
    for line in [4, 5] {
        let (emu, angle) = emulator(vec![TurntableFault::MissOk { line }]);
        let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
        t.move_to(20.0).unwrap();
        assert!((angle.get() - 20.0).abs() < 1e-3, "line {line}: at {}", angle.get());
    }
}

#[test]
fn driver_survives_garbage_instead_of_a_reply() {
    for line in [1, 4] {
        let (emu, angle) = emulator(vec![TurntableFault::Garbage { line }]);
        let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
        t.move_to(8.0).unwrap();
        assert!((angle.get() - 8.0).abs() < 1e-3);
    }
}

#[test]
fn driver_reports_a_stall_with_port_and_angle() {
    let (emu, _) = emulator(vec![TurntableFault::Stall { at_deg: 5.0 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    let e = t.move_to(30.0).unwrap_err();
    assert!(matches!(e, TurntableError::Stalled { .. }), "{e}");
    let msg = e.to_string();
    assert!(msg.contains(emu.port_path()) && msg.contains("stalled at 5.000°") && msg.contains("30.000°"), "{msg}");
    // A reset clears the stall where the table stopped; the driver can start again.
    t.reset().unwrap();
    assert!((t.angle().unwrap() - 5.0).abs() < 1e-3, "after reset: {}", t.angle().unwrap());
}

#[test]
fn driver_reports_a_vanished_device() {
    let (emu, _) = emulator(vec![TurntableFault::Vanish { line: 4 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    let e = t.move_to(10.0).unwrap_err();
    assert!(matches!(e, TurntableError::Vanished { .. } | TurntableError::Unresponsive { .. }), "{e}");
    assert!(e.to_string().contains(emu.port_path()) && e.to_string().contains("G1 X10.000"), "{e}");
}

#[test]
fn driver_gives_up_on_a_silent_device_after_its_retries() {
    // Every reply to the move is lost: three tries, then a clear error.
    let (emu, _) = emulator(vec![TurntableFault::MissOk { line: 4 }, TurntableFault::MissOk { line: 5 }, TurntableFault::MissOk { line: 6 }]);
    let mut t = HorusTurntable::open(emu.port_path(), quick_driver()).unwrap();
    let e = t.move_to(10.0).unwrap_err().to_string();
    assert!(e.contains("did not answer `G1 X10.000` within 200 ms (3 tries)") && e.contains(emu.port_path()), "{e}");
}

#[test]
fn driver_refuses_other_firmware_and_missing_ports() {
    let angle = TableAngle::new(0.0);
    let emu = Emulator::spawn(FirmwareConfig { greeting: "Horus 0.1 ['$' for help]".into(), ..FirmwareConfig::default() }, angle).unwrap();
    let e = HorusTurntable::open(emu.port_path(), quick_driver()).err().unwrap().to_string();
    assert!(e.contains("unsupported firmware") && e.contains("Horus 0.1"), "{e}");
    let e = HorusTurntable::open("/dev/spinscan-no-such-port", quick_driver()).err().unwrap().to_string();
    assert!(e.contains("cannot open turntable port /dev/spinscan-no-such-port"), "{e}");
}
