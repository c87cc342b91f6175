//! `spinscan turntable`: the table alone, for checking wiring and firmware before a scan (as
//! Horus's control panel does). Each subcommand opens the port (which resets the board and
//! zeroes its position), waits for the greeting, does one thing, and prints one JSON object.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::{Args, Subcommand};
use serde_json::json;

use super::{exit, input, Failure};
use spinscan::hw::{DriverConfig, HorusTurntable, TableState, Turntable, TurntableError};

#[derive(Args)]
pub struct TurntableArgs {
    /// The board's serial port (e.g. /dev/ttyACM0, /dev/ttyUSB0, /dev/spinscan-table).
    #[arg(long)]
    pub port: PathBuf,
    /// Baud rate (115200; 19200 for the Bluetooth build).
    #[arg(long, default_value_t = DriverConfig::default().baud)]
    pub baud: u32,
    /// +1 when positive firmware X turns the table counterclockwise seen from above, −1
    /// when clockwise (the daemon's `turntable.direction`).
    #[arg(long, default_value_t = 1, allow_hyphen_values = true)]
    pub direction: i8,
    #[command(subcommand)]
    pub action: TableAction,
}

#[derive(Subcommand)]
pub enum TableAction {
    /// Greeting, steps per degree, maximum rate and acceleration as the board reports them.
    Info,
    /// State (Idle, Run, …) and angle.
    Status,
    /// Absolute move to DEG (the position counts from where the table was when the port
    /// opened); waits for arrival, or stops the table the safe way after --stop-after.
    Move {
        #[arg(allow_hyphen_values = true)]
        deg: f64,
        /// Feed rate, degrees per second.
        #[arg(long, default_value_t = DriverConfig::default().feed_deg_s)]
        speed: f64,
        /// Stop after this many seconds (feed hold, then reset), arrived or not.
        #[arg(long)]
        stop_after: Option<f64>,
    },
    /// Motor off (M18): the table turns freely by hand.
    Off,
}

/// A device that did not do what it was asked; the message carries the firmware's words.
fn device(e: TurntableError) -> Failure {
    Failure { code: exit::DEVICE, message: e.to_string() }
}

pub fn cmd_turntable(a: TurntableArgs) -> Result<(), Failure> {
    if a.direction != 1 && a.direction != -1 {
        return Err(input(format!("--direction must be 1 or -1, got {}", a.direction)));
    }
    let mut config = DriverConfig { baud: a.baud, direction: a.direction, ..DriverConfig::default() };
    if let TableAction::Move { speed, stop_after, .. } = &a.action {
        if !(speed.is_finite() && *speed > 0.0) {
            return Err(input(format!("--speed must be a positive number of degrees per second, got {speed}")));
        }
        if stop_after.is_some_and(|s| !(s.is_finite() && s >= 0.0)) {
            return Err(input(format!("--stop-after must be a number of seconds ≥ 0, got {}", stop_after.unwrap())));
        }
        config.feed_deg_s = *speed;
    }
    let port = a.port.to_string_lossy().into_owned();
    eprintln!("turntable: opening {port} (the board resets and greets within a few seconds)…");
    let mut t = HorusTurntable::open(&port, config).map_err(device)?;
    let report = |t: &mut HorusTurntable| -> Result<serde_json::Value, Failure> {
        let (state, fw) = t.status().map_err(device)?;
        Ok(json!({"state": state.name(), "angle_deg": fw * a.direction as f64}))
    };
    let out = match a.action {
        TableAction::Info => {
            let mut v = report(&mut t)?;
            let i = t.info().clone();
            v["firmware"] = json!(i.firmware);
            v["steps_per_deg"] = json!(i.steps_per_deg);
            v["max_rate_deg_s"] = json!(i.max_rate_deg_s);
            v["accel_deg_s2"] = json!(i.accel_deg_s2);
            v
        }
        TableAction::Status => report(&mut t)?,
        TableAction::Move { deg, speed, stop_after: None } => {
            let arrived = t.move_to(deg).map_err(device)?;
            let mut v = report(&mut t)?;
            v["target_deg"] = json!(deg);
            v["arrived_deg"] = json!(arrived);
            v["speed_deg_s"] = json!(speed);
            v
        }
        TableAction::Move { deg, speed, stop_after: Some(seconds) } => {
            t.start_move(deg, speed).map_err(device)?;
            let until = Instant::now() + Duration::from_secs_f64(seconds);
            let mut arrived = false;
            while Instant::now() < until {
                let (state, _) = t.status().map_err(device)?;
                if state == TableState::Idle {
                    arrived = true;
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
            if !arrived {
                t.halt().map_err(device)?;
            }
            let mut v = report(&mut t)?;
            v["target_deg"] = json!(deg);
            v["stopped"] = json!(!arrived);
            v
        }
        TableAction::Off => {
            t.release().map_err(device)?;
            let mut v = report(&mut t)?;
            v["motor"] = json!("off");
            v
        }
    };
    println!("{out}");
    Ok(())
}
