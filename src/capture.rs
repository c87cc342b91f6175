//! The camera seam: one trait for every source of synchronized stereo frames — the
//! simulated cameras ([`crate::sim::SimCameras`]), a recording being replayed
//! ([`crate::recording::ReplaySource`]) and, in the daemon, V4L2 devices.

use crate::calib::StereoCalib;

/// One image as the camera delivered it.
#[derive(Debug, Clone, PartialEq)]
pub enum Picture {
    /// Uncompressed 8-bit pixels, `channels` = 1 (grey) or 3 (RGB), row-major, interleaved.
    Raw { width: usize, height: usize, channels: u8, data: Vec<u8> },
    /// A JPEG frame as an MJPEG camera sent it (recorded without re-encoding).
    Jpeg { bytes: Vec<u8> },
}

impl Picture {
    /// Decodes to `(width, height, interleaved RGB)`.
    pub fn to_rgb(&self) -> Result<(usize, usize, Vec<u8>), String> {
        match self {
            Picture::Raw { width, height, channels: 3, data } => Ok((*width, *height, data.clone())),
            Picture::Raw { width, height, channels: 1, data } => Ok((*width, *height, data.iter().flat_map(|&g| [g, g, g]).collect())),
            Picture::Raw { channels, .. } => Err(format!("{channels}-channel images are not supported (expected 1 or 3)")),
            Picture::Jpeg { bytes } => {
                let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Jpeg).map_err(|e| format!("undecodable JPEG frame: {e}"))?;
                let rgb = img.to_rgb8();
                Ok((rgb.width() as usize, rgb.height() as usize, rgb.into_raw()))
            }
        }
    }
}

/// A synchronized stereo pair with its capture facts.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoFrame {
    /// Pair number; strictly increasing, gaps mean dropped pairs.
    pub seq: u64,
    /// Capture time of each image, ns on one monotonic clock.
    pub t_left_ns: u64,
    pub t_right_ns: u64,
    /// Turntable angle at capture, degrees counterclockwise seen from above, if known.
    pub table_deg: Option<f64>,
    pub left: Picture,
    pub right: Picture,
}

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
    fn pairing(&self) -> Option<crate::daemon::v4l2::PairStats> {
        None
    }
}
