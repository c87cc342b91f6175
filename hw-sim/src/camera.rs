//! Simulated stereo cameras: rendered images delivered like two free-running V4L2 cameras
//! (per-camera timestamps with jitter, a skew between left and right, dropped pairs), with
//! injectable faults.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::math::Rng;
use crate::render::{RenderedPair, Renderer};

/// The turntable angle the cameras see, degrees (counterclockwise seen from above). Shared
/// between whoever turns the table (the firmware emulator, or a scripted scan) and the
/// cameras.
#[derive(Debug, Clone, Default)]
pub struct TableAngle(Arc<AtomicU64>);

impl TableAngle {
    pub fn new(deg: f64) -> TableAngle {
        TableAngle(Arc::new(AtomicU64::new(deg.to_bits())))
    }

    pub fn get(&self) -> f64 {
        f64::from_bits(self.0.load(Ordering::Acquire))
    }

    pub fn set(&self, deg: f64) {
        self.0.store(deg.to_bits(), Ordering::Release);
    }
}

/// Frame timing of the pair.
#[derive(Debug, Clone, PartialEq)]
pub struct Timing {
    pub fps: f64,
    /// Each timestamp is off its nominal time by up to ± this, ns (uniform).
    pub jitter_ns: u64,
    /// Right camera's mean delay after the left, ns (free-running cameras never agree).
    pub skew_ns: i64,
    /// Probability that a pair is lost (its `seq` is skipped).
    pub drop_probability: f64,
    /// Timestamp of frame 0, ns on the simulated monotonic clock.
    pub start_ns: u64,
}

impl Default for Timing {
    fn default() -> Self {
        Timing { fps: 15.0, jitter_ns: 400_000, skew_ns: 350_000, drop_probability: 0.0, start_ns: 1_000_000_000 }
    }
}

/// Which camera a fault hits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    Left,
    Right,
}

impl Side {
    pub fn name(self) -> &'static str {
        match self {
            Side::Left => "left",
            Side::Right => "right",
        }
    }
}

/// A camera fault, injected from a frame on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CameraFault {
    /// The camera stops delivering frames (the stream stays open).
    Stop { camera: Side, after_frames: u64 },
    /// From then on every frame of this camera arrives `late_ms` late.
    Late { camera: Side, after_frames: u64, late_ms: u64 },
    /// The camera disappears (USB unplugged).
    Disconnect { camera: Side, after_frames: u64 },
}

/// Why no frame came.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SimCameraError {
    #[error("{camera} camera delivered no frame within {waited_ms} ms")]
    NoFrame { camera: &'static str, waited_ms: u64 },
    #[error("{camera} camera disconnected")]
    Disconnected { camera: &'static str },
}

/// One delivered pair.
#[derive(Debug, Clone)]
pub struct SimFrame {
    pub seq: u64,
    pub t_left_ns: u64,
    pub t_right_ns: u64,
    pub table_deg: f64,
    pub pair: RenderedPair,
}

/// Two simulated cameras on one trigger-less clock.
pub struct SimStereoCamera {
    renderer: Renderer,
    timing: Timing,
    faults: Vec<CameraFault>,
    angle: TableAngle,
    /// Next frame number on the nominal clock (counts dropped pairs too).
    next: u64,
    rng: Rng,
    /// Scripted steady rotation `(start_deg, deg_per_frame)`: the table angle follows the
    /// frame number instead of [`TableAngle`] (which is then kept up to date).
    motion: Option<(f64, f64)>,
    /// Pace delivery in real time (live scans); off for tests and offline rendering.
    realtime: bool,
    /// How long a consumer waits for a frame before a stopped camera counts as stopped.
    pub frame_timeout: Duration,
    started: Option<Instant>,
}

impl SimStereoCamera {
    pub fn new(renderer: Renderer, timing: Timing, angle: TableAngle) -> SimStereoCamera {
        let rng = Rng::new(renderer.scene().seed ^ 0x71_3E);
        SimStereoCamera { renderer, timing, faults: Vec::new(), angle, next: 0, rng, motion: None, realtime: false, frame_timeout: Duration::from_millis(500), started: None }
    }

    pub fn with_faults(mut self, faults: Vec<CameraFault>) -> Self {
        self.faults = faults;
        self
    }

    /// Turns the table steadily by `deg_per_frame` per frame period from `start_deg`.
    pub fn with_motion(mut self, start_deg: f64, deg_per_frame: f64) -> Self {
        self.motion = Some((start_deg, deg_per_frame));
        self
    }

    pub fn realtime(mut self, on: bool) -> Self {
        self.realtime = on;
        self
    }

    pub fn renderer(&self) -> &Renderer {
        &self.renderer
    }

    pub fn angle(&self) -> &TableAngle {
        &self.angle
    }

    fn period_ns(&self) -> f64 {
        1e9 / self.timing.fps
    }

    /// The next pair, rendered at the table's current angle.
    pub fn next_frame(&mut self) -> Result<SimFrame, SimCameraError> {
        loop {
            let seq = self.next;
            for fault in &self.faults {
                match *fault {
                    CameraFault::Disconnect { camera, after_frames } if seq >= after_frames => {
                        return Err(SimCameraError::Disconnected { camera: camera.name() });
                    }
                    CameraFault::Stop { camera, after_frames } if seq >= after_frames => {
                        if self.realtime {
                            std::thread::sleep(self.frame_timeout);
                        }
                        return Err(SimCameraError::NoFrame { camera: camera.name(), waited_ms: self.frame_timeout.as_millis() as u64 });
                    }
                    _ => {}
                }
            }
            self.next += 1;
            if self.timing.drop_probability > 0.0 && self.rng.unit() < self.timing.drop_probability {
                continue;
            }
            let nominal = self.timing.start_ns as f64 + seq as f64 * self.period_ns();
            let jitter = |rng: &mut Rng, j: u64| (rng.unit() * 2.0 - 1.0) * j as f64;
            let mut t_left = nominal + jitter(&mut self.rng, self.timing.jitter_ns);
            let mut t_right = nominal + self.timing.skew_ns as f64 + jitter(&mut self.rng, self.timing.jitter_ns);
            for fault in &self.faults {
                if let CameraFault::Late { camera, after_frames, late_ms: ms } = *fault {
                    if seq >= after_frames {
                        match camera {
                            Side::Left => t_left += ms as f64 * 1e6,
                            Side::Right => t_right += ms as f64 * 1e6,
                        }
                    }
                }
            }
            if self.realtime {
                let start = *self.started.get_or_insert_with(Instant::now);
                let due = Duration::from_nanos((t_left.max(t_right) - self.timing.start_ns as f64).max(0.0) as u64);
                if let Some(wait) = due.checked_sub(start.elapsed()) {
                    std::thread::sleep(wait);
                }
            }
            // Both images see the table at one angle: the skew lives in the timestamps only,
            // so the ground-truth disparity stays exact.
            let table_deg = match self.motion {
                Some((start, step)) => {
                    let deg = start + seq as f64 * step;
                    self.angle.set(deg);
                    deg
                }
                None => self.angle.get(),
            };
            let pair = self.renderer.render(table_deg, seq);
            return Ok(SimFrame { seq, t_left_ns: t_left.round() as u64, t_right_ns: t_right.round() as u64, table_deg, pair });
        }
    }
}
