//! What a camera backend delivers: one picture per camera, paired into a [`StereoFrame`].
//! Plain data; every backend and the recording format share it.

/// One image as the camera delivered it.
#[derive(Debug, Clone, PartialEq)]
pub enum Picture {
    /// Uncompressed 8-bit pixels, `channels` = 1 (grey) or 3 (RGB), row-major, interleaved.
    Raw { width: usize, height: usize, channels: u8, data: Vec<u8> },
    /// A JPEG frame as an MJPEG camera sent it (recorded without re-encoding).
    Jpeg { bytes: Vec<u8> },
}

/// Why a [`Picture`] could not be decoded to RGB.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    #[error("{0}-channel images are not supported (expected 1 or 3)")]
    Channels(u8),
    #[error("{width}×{height}×{channels} image holds {got} bytes (expected {expected})")]
    Size { width: usize, height: usize, channels: u8, got: usize, expected: usize },
    #[error("undecodable JPEG frame: {0}")]
    Jpeg(String),
}

impl Picture {
    /// Decodes to `(width, height, interleaved RGB)`.
    pub fn to_rgb(&self) -> Result<(usize, usize, Vec<u8>), DecodeError> {
        match self {
            Picture::Raw { width, height, channels, data } if matches!(channels, 1 | 3) && data.len() != width * height * *channels as usize => {
                Err(DecodeError::Size { width: *width, height: *height, channels: *channels, got: data.len(), expected: width * height * *channels as usize })
            }
            Picture::Raw { width, height, channels: 3, data } => Ok((*width, *height, data.clone())),
            Picture::Raw { width, height, channels: 1, data } => Ok((*width, *height, data.iter().flat_map(|&g| [g, g, g]).collect())),
            Picture::Raw { channels, .. } => Err(DecodeError::Channels(*channels)),
            Picture::Jpeg { bytes } => {
                let img = image::load_from_memory_with_format(bytes, image::ImageFormat::Jpeg).map_err(|e| DecodeError::Jpeg(e.to_string()))?;
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

impl StereoFrame {
    /// The frame's facts without its pictures (what travels on after matching).
    pub fn meta(&self) -> StereoFrame {
        let empty = || Picture::Raw { width: 0, height: 0, channels: 3, data: Vec::new() };
        StereoFrame { left: empty(), right: empty(), ..*self }
    }
}

/// Now on CLOCK_MONOTONIC, ns: the clock of UVC buffer timestamps, of pairing, and of the
/// turntable's timestamped status replies.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec { tv_sec: 0, tv_nsec: 0 };
    // SAFETY: clock_gettime writes the timespec it is given.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}
