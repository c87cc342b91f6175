//! The device seam: everything spinscan knows of cameras and turntables, and nothing else.
//!
//! ```text
//!  V4L2 cameras ─┐                                   ┌─ Horus board on serial (horus.rs)
//!  hw-sim ───────┼─> StereoSource ─> StereoFrame      Turntable <─┼─ hw-sim firmware on a pty (sim.rs)
//!  recording ────┘   (v4l2.rs, sim.rs, replay.rs)                 └─ (none: a replay)
//! ```
//!
//! Two small traits, [`StereoSource`] and [`Turntable`], returned as `Box<dyn …>`; real,
//! simulated and replayed backends are chosen at run time from the config, never by `cfg`.
//! Pairing two free-running cameras by timestamp is a pure struct ([`pairing::Pairer`]) any
//! camera backend can use. `hw-sim` is named only here (`sim.rs`).

pub mod frame;
pub mod horus;
pub mod mjpeg;
pub mod pairing;
pub mod replay;
pub mod sim;
pub mod sim_target;
pub mod v4l2;

pub use frame::{DecodeError, Picture, StereoFrame};
pub use horus::{BoardInfo, DriverConfig, HorusTurntable, TableState};
pub use pairing::PairStats;

use crate::calib::StereoCalib;

/// Why a source could not deliver a frame.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    #[error("{camera} camera delivered no frame within {waited_ms} ms")]
    NoFrame { camera: String, waited_ms: u64 },
    #[error("{camera} camera disconnected")]
    Disconnected { camera: String },
    #[error("{camera} camera: {what}")]
    Device { camera: String, what: String },
    #[error(transparent)]
    Recording(#[from] crate::recording::RecordingError),
}

/// A source of stereo frames. Real, simulated and replayed backends are chosen at run time.
pub trait StereoSource: Send {
    /// What this source is, for logs and reports ("simulated cameras", "recording DIR").
    fn describe(&self) -> String;
    /// The rig's calibration.
    fn calibration(&self) -> &StereoCalib;
    /// The next pair; `Ok(None)` when a finite source (a recording) has no more.
    fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError>;
    /// The next pair captured after this call (step-and-shoot: not one that waited in a
    /// buffer while the table moved). Sources that capture on demand deliver `next_frame`.
    fn fresh_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
        self.next_frame()
    }
    /// Pairing statistics of free-running cameras, when the source pairs frames itself.
    fn pairing(&self) -> Option<PairStats> {
        None
    }
    /// Puts a calibration board in front of a simulated rig (`Some`) or takes it away
    /// (`None`); `true` when this source did. Real cameras answer `false`: in a lab a person
    /// holds the board.
    fn show_target(&mut self, _target: Option<TargetScene>) -> bool {
        false
    }
}

/// A calibration board in front of a simulated rig ([`StereoSource::show_target`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TargetScene {
    /// Inner corners along a row, and rows.
    pub cols: usize,
    pub rows: usize,
    pub square_mm: f64,
    /// Standing on the turntable (it turns with the table), else held up and moved to a new
    /// pose about once a second.
    pub on_table: bool,
}

/// Something that turns the object. Angles are spinscan's `table_deg`: counterclockwise
/// seen from above.
pub trait Turntable: Send {
    /// Moves to `table_deg` and returns once the table has arrived (and settled), with the
    /// angle read back: a stepper rounds the target to a whole step.
    fn move_to(&mut self, table_deg: f64) -> Result<f64, TurntableError>;
    /// The current angle.
    fn angle(&mut self) -> Result<f64, TurntableError>;
    /// The angle at `t_ns` on CLOCK_MONOTONIC (a frame's exposure), interpolated between
    /// timestamped status replies while the table turns. Without history: the angle now.
    fn angle_at(&mut self, _t_ns: u64) -> Result<f64, TurntableError> {
        self.angle()
    }
    /// The smallest move, degrees (one motor step); half of it is the tolerance on angles.
    fn resolution_deg(&self) -> f64 {
        0.0
    }
    /// Switches the motor off (a scan ended): a Horus board keeps it energised otherwise.
    fn release(&mut self) -> Result<(), TurntableError> {
        Ok(())
    }
    /// A flag that, once set, ends any wait of this table with [`TurntableError::Aborted`]
    /// (a scan's stop request: `scan.stop`, SIGTERM).
    fn watch_stop(&mut self, _stop: std::sync::Arc<std::sync::atomic::AtomicBool>) {}
    /// Starts turning towards `table_deg` at `feed_deg_s` and returns at once (continuous
    /// scans); [`Turntable::angle`] follows the motion.
    fn start_move(&mut self, table_deg: f64, feed_deg_s: f64) -> Result<(), TurntableError>;
    /// Stops any motion now and restores the step feed.
    fn halt(&mut self) -> Result<(), TurntableError>;
    /// Where the device is (a port path), for messages.
    fn describe(&self) -> String;
}

/// Why the turntable did not do what it was asked.
#[derive(Debug, thiserror::Error)]
pub enum TurntableError {
    #[error("cannot open turntable port {port}: {what}")]
    Open { port: String, what: String },
    #[error("turntable on {port} sent no greeting within {waited_ms} ms of a reset (Ctrl-X); is it a Horus board and powered?")]
    NoGreeting { port: String, waited_ms: u64 },
    #[error("turntable on {port} greets with `{greeting}`: unsupported firmware (spinscan speaks `{expected}`)")]
    UnsupportedFirmware { port: String, greeting: String, expected: &'static str },
    #[error("turntable on {port} did not answer `{command}` within {timeout_ms} ms ({tries} tries)")]
    Unresponsive { port: String, command: String, timeout_ms: u64, tries: u32 },
    #[error("turntable on {port} refused `{command}`: {reply}")]
    Rejected { port: String, command: String, reply: String },
    #[error("turntable on {port} stalled at {at_deg:.3}° on its way to {target_deg:.3}° (firmware degrees; `{command}` never finished)")]
    Stalled { port: String, command: String, target_deg: f64, at_deg: f64 },
    #[error("turntable on {port} vanished during `{command}`: {what}")]
    Vanished { port: String, command: String, what: String },
    #[error("turntable on {port} sent a status report spinscan cannot read: `{reply}` (expected <State,MPos:x,y,z>)")]
    BadStatus { port: String, reply: String },
    #[error("turntable on {port}: `{command}` abandoned: a stop was requested")]
    Aborted { port: String, command: String },
    #[error("turntable on {port} did not arrive within {waited_s:.0} s of `{command}` (at {at_deg:.3}°, firmware degrees)")]
    TooSlow { port: String, command: String, waited_s: f64, at_deg: f64 },
    #[error("turntable on {port} reset itself during `{command}` (its greeting arrived): the position is lost; check its power supply and USB cable")]
    BoardReset { port: String, command: String },
    #[error("turntable on {port} stopped at {at_deg:.3}° ({state}) short of {target_deg:.3}° (firmware degrees; `{command}` was lost)")]
    StoppedShort { port: String, command: String, target_deg: f64, at_deg: f64, state: &'static str },
}

