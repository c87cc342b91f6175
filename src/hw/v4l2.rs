//! V4L2 cameras: pixel formats as delivered, the capture threads, and the device listing;
//! the two free-running cameras are paired by [`super::pairing`].
//!
//! ```text
//!  left  /dev/videoN ─mmap stream─> capture thread ─(Left, t, seq, Picture)──┐
//!  right /dev/videoM ─mmap stream─> capture thread ─(Right, t, seq, Picture)─┴─> Pairer ─> StereoFrame
//! ```
//!
//! A buffer is sliced to `bytesused` (an MJPEG frame is shorter than its buffer) and copied
//! out before it is queued again. After a dequeue timeout the stream is dropped and made
//! again (its re-queue of the last buffer cannot be trusted then). Timestamps are the
//! kernel's (CLOCK_MONOTONIC on UVC), so both cameras share one clock.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::{json, Value};

use crate::calib::StereoCalib;
use super::mjpeg::{self, MjpegError};
use super::pairing::{CameraFrame, PairStats, Pairer, Side};
use super::frame::monotonic_ns;
use super::{CaptureError, Picture, StereoFrame, StereoSource};


/// Why a buffer is not a frame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FormatError {
    #[error("{fourcc} frame of {got} bytes is too short for {width}×{height} (expected {expected})")]
    Short { fourcc: String, got: usize, expected: usize, width: usize, height: usize },
    #[error(transparent)]
    Mjpeg(#[from] MjpegError),
    #[error("bytesused {used} exceeds the buffer's {len} bytes")]
    Overrun { used: usize, len: usize },
    #[error("pixel format {0} is not supported (expected MJPG, YUYV or GREY)")]
    Unsupported(String),
}

/// The fourcc as text ("MJPG").
pub fn fourcc_name(f: [u8; 4]) -> String {
    f.iter().map(|&b| if b.is_ascii_graphic() || b == b' ' { b as char } else { '?' }).collect()
}

/// One delivered buffer as spinscan keeps it: `buffer[..bytesused]` of a `fourcc` frame of
/// `width`×`height` → a [`Picture`] (MJPEG kept as JPEG bytes; YUYV converted to RGB; GREY
/// kept).
pub fn to_picture(fourcc: [u8; 4], buffer: &[u8], bytesused: usize, width: usize, height: usize) -> Result<Picture, FormatError> {
    if bytesused > buffer.len() {
        return Err(FormatError::Overrun { used: bytesused, len: buffer.len() });
    }
    // Some drivers report 0 for a full buffer.
    let data = if bytesused == 0 { buffer } else { &buffer[..bytesused] };
    let short = |expected: usize| FormatError::Short { fourcc: fourcc_name(fourcc), got: data.len(), expected, width, height };
    match &fourcc {
        b"MJPG" | b"JPEG" => {
            // Whole frames only (through FF D9), with Huffman tables: a standard JPEG.
            let whole = mjpeg::complete(data)?;
            Ok(Picture::Jpeg { bytes: mjpeg::standardize(whole)?.into_owned() })
        }
        b"YUYV" => {
            let expected = width * height * 2;
            if data.len() < expected {
                return Err(short(expected));
            }
            Ok(Picture::Raw { width, height, channels: 3, data: yuyv_to_rgb(&data[..expected], width, height) })
        }
        b"GREY" => {
            let expected = width * height;
            if data.len() < expected {
                return Err(short(expected));
            }
            Ok(Picture::Raw { width, height, channels: 1, data: data[..expected].to_vec() })
        }
        _ => Err(FormatError::Unsupported(fourcc_name(fourcc))),
    }
}

/// YUYV 4:2:2 (Y0 U Y1 V per two pixels, BT.601 limited range) → interleaved RGB.
pub fn yuyv_to_rgb(yuyv: &[u8], width: usize, height: usize) -> Vec<u8> {
    let mut out = vec![0u8; width * height * 3];
    let px = |y: i32, u: i32, v: i32, o: &mut [u8]| {
        let c = 298 * (y - 16);
        let (d, e) = (u - 128, v - 128);
        o[0] = ((c + 409 * e + 128) >> 8).clamp(0, 255) as u8;
        o[1] = ((c - 100 * d - 208 * e + 128) >> 8).clamp(0, 255) as u8;
        o[2] = ((c + 516 * d + 128) >> 8).clamp(0, 255) as u8;
    };
    for (quad, rgb) in yuyv.chunks_exact(4).zip(out.chunks_exact_mut(6)) {
        let (y0, u, y1, v) = (quad[0] as i32, quad[1] as i32, quad[2] as i32, quad[3] as i32);
        px(y0, u, v, &mut rgb[..3]);
        px(y1, u, v, &mut rgb[3..]);
    }
    out
}

/// What is wrong with a camera configuration against a device listing ([`list_devices`]):
/// a camera not present, or one that does not offer the format, size or rate. Empty when
/// each camera offers it (or when a camera's formats could not be read).
pub fn check_offered(listing: &Value, cameras: &[&Path], fourcc: [u8; 4], width: u32, height: u32, fps: u32) -> Vec<String> {
    let (format, size) = (fourcc_name(fourcc), format!("{width}x{height}"));
    let mut out = Vec::new();
    let present = listing["cameras"].as_array().cloned().unwrap_or_default();
    for path in cameras {
        // A udev link (/dev/spinscan-left) names the node it points at.
        let real = std::fs::canonicalize(path).unwrap_or_else(|_| path.to_path_buf());
        let Some(cam) = present.iter().find(|c| c["path"].as_str().is_some_and(|p| Path::new(p) == *path || Path::new(p) == real)) else {
            out.push(format!("{} is not present", path.display()));
            continue;
        };
        let Some(formats) = cam["formats"].as_array() else { continue };
        let Some(f) = formats.iter().find(|f| f["fourcc"] == format) else {
            let have: Vec<&str> = formats.iter().filter_map(|f| f["fourcc"].as_str()).collect();
            out.push(format!("{} does not offer {format} (it offers {})", path.display(), have.join(", ")));
            continue;
        };
        if !f["sizes"].as_array().is_some_and(|s| s.iter().any(|s| s == &json!(size))) {
            out.push(format!("{} does not offer {size} in {format} (sizes: {})", path.display(), f["sizes"]));
            continue;
        }
        if let Some(rates) = f["rates"][&size].as_array().filter(|r| !r.is_empty()) {
            if !rates.iter().filter_map(Value::as_f64).any(|r| !rate_differs(fps, r)) {
                out.push(format!("{} does not run {format} {size} at {fps} fps (rates: {})", path.display(), f["rates"][&size]));
            }
        }
    }
    out
}


/// Settings of one capture stream.
#[derive(Debug, Clone)]
pub struct StreamConfig {
    pub width: u32,
    pub height: u32,
    pub fps: u32,
    pub fourcc: [u8; 4],
    pub buffers: u32,
    pub timeout: Duration,
    pub auto_exposure: Option<bool>,
    pub exposure_100us: Option<i64>,
    pub gain: Option<i64>,
}

// Control ids of the V4L2 ABI (linux/v4l2-controls.h).
const CID_EXPOSURE_AUTO: u32 = 0x009a_0901;
const CID_EXPOSURE_ABSOLUTE: u32 = 0x009a_0902;
const CID_GAIN: u32 = 0x0098_0913;
const EXPOSURE_MANUAL: i64 = 1;
const EXPOSURE_APERTURE_PRIORITY: i64 = 3;

/// Why a camera could not be set up as configured.
#[derive(Debug, thiserror::Error)]
enum SetupError {
    #[error("cannot open {path}: {source}")]
    Open { path: PathBuf, source: std::io::Error },
    #[error("{path}: cannot {what}: {source}")]
    Ioctl { path: PathBuf, what: String, source: std::io::Error },
    #[error("{path} offers {got} instead of the configured {wanted} (see `spinscan devices --local`)")]
    Offers { path: PathBuf, got: String, wanted: String },
}

/// The frame rate of a frame interval (`numerator / denominator` seconds), frames per second.
pub fn frame_rate(interval: v4l::Fraction) -> Option<f64> {
    (interval.numerator > 0 && interval.denominator > 0).then(|| interval.denominator as f64 / interval.numerator as f64)
}

/// Whether the rate a driver chose is not the one asked for (more than 1 % off).
pub fn rate_differs(requested_fps: u32, got_fps: f64) -> bool {
    (got_fps - requested_fps as f64).abs() > 0.01 * requested_fps as f64
}

/// Half a frame period at `fps`, ns: the pairing tolerance unless one is configured.
pub fn half_period_ns(fps: f64) -> u64 {
    (0.5e9 / fps.max(1e-3)) as u64
}

/// A dequeued buffer's capture time, or why it is dropped. Current uvcvideo hands back
/// incomplete frames flagged `V4L2_BUF_FLAG_ERROR` instead of dropping them; and a timestamp
/// is only on CLOCK_MONOTONIC (the clock pairing and the turntable's replies use) when the
/// flags say so — otherwise the time of dequeue (`dequeued_ns`) stands in, and the second
/// value is false.
pub fn buffer_time(flags: v4l::buffer::Flags, timestamp_ns: u64, dequeued_ns: u64) -> Result<(u64, bool), &'static str> {
    use v4l::buffer::Flags;
    if flags.contains(Flags::ERROR) {
        return Err("the driver flagged the buffer as damaged (V4L2_BUF_FLAG_ERROR)");
    }
    let clock = Flags::from_bits_truncate(flags.bits() & Flags::TIMESTAMP_MASK.bits());
    if clock == Flags::TIMESTAMP_MONOTONIC && timestamp_ns > 0 {
        Ok((timestamp_ns, true))
    } else {
        Ok((dequeued_ns, false))
    }
}

/// A streaming error with what a lab can do about it.
pub fn stream_error_advice(e: &std::io::Error) -> String {
    match e.raw_os_error() {
        Some(libc::ENOSPC) => format!(
            "{e} (ENOSPC: the USB controller has no bandwidth left for this camera; use MJPG rather than YUYV, put the two cameras on separate USB controllers, or lower the frame rate or size)"
        ),
        Some(libc::EBUSY) => format!("{e} (EBUSY: another program streams from this camera; stop it)"),
        _ => e.to_string(),
    }
}

fn open_device(path: &Path, cfg: &StreamConfig) -> Result<(v4l::Device, usize, usize, f64), SetupError> {
    use v4l::video::Capture;
    let ioctl = |what: String| move |source: std::io::Error| SetupError::Ioctl { path: path.to_path_buf(), what, source };
    let dev = v4l::Device::with_path(path).map_err(|source| SetupError::Open { path: path.to_path_buf(), source })?;
    let mut fmt = dev.format().map_err(ioctl("read the format".into()))?;
    fmt.width = cfg.width;
    fmt.height = cfg.height;
    fmt.fourcc = v4l::FourCC::new(&cfg.fourcc);
    let wanted = format!("{}×{} {}", cfg.width, cfg.height, fourcc_name(cfg.fourcc));
    let got = dev.set_format(&fmt).map_err(ioctl(format!("set {wanted}")))?;
    if got.fourcc.repr != cfg.fourcc || got.width != cfg.width || got.height != cfg.height {
        return Err(SetupError::Offers { path: path.to_path_buf(), got: format!("{}×{} {}", got.width, got.height, fourcc_name(got.fourcc.repr)), wanted });
    }
    let params = dev.set_params(&v4l::video::capture::Parameters::with_fps(cfg.fps)).map_err(ioctl(format!("set {} fps", cfg.fps)))?;
    // The driver picks the nearest rate it can do at this size and format.
    let fps = frame_rate(params.interval).unwrap_or(cfg.fps as f64);
    let mut controls = Vec::new();
    if let Some(auto) = cfg.auto_exposure {
        controls.push((CID_EXPOSURE_AUTO, if auto { EXPOSURE_APERTURE_PRIORITY } else { EXPOSURE_MANUAL }, "auto_exposure"));
    }
    if let Some(e) = cfg.exposure_100us {
        controls.push((CID_EXPOSURE_ABSOLUTE, e, "exposure_100us"));
    }
    if let Some(g) = cfg.gain {
        controls.push((CID_GAIN, g, "gain"));
    }
    for (id, value, key) in controls {
        dev.set_control(v4l::Control { id, value: v4l::control::Value::Integer(value) }).map_err(ioctl(format!("set cameras.{key} = {value}")))?;
    }
    Ok((dev, got.width as usize, got.height as usize, fps))
}

/// Captures from one camera until `stop` is set or the camera fails; frames go to `tx`.
/// A timeout recreates the stream; `timeouts_to_fail` in a row end the thread with an error.
fn capture_loop(side: Side, path: PathBuf, cfg: StreamConfig, tx: crossbeam_channel::Sender<Result<CameraFrame, CaptureError>>, stop: std::sync::Arc<std::sync::atomic::AtomicBool>) {
    use std::sync::atomic::Ordering;
    use v4l::io::traits::CaptureStream;
    let fail = |e: CaptureError| {
        let _ = tx.send(Err(e));
    };
    let (dev, w, h, _) = match open_device(&path, &cfg) {
        Ok(d) => d,
        Err(e) => return fail(CaptureError::Device { camera: side.name().into(), what: e.to_string() }),
    };
    let mut timeouts = 0;
    let mut warned_clock = false;
    'streams: while !stop.load(Ordering::Relaxed) {
        let mut stream = match v4l::io::mmap::Stream::with_buffers(&dev, v4l::buffer::Type::VideoCapture, cfg.buffers) {
            Ok(s) => s,
            Err(e) => return fail(CaptureError::Device { camera: side.name().into(), what: format!("{}: cannot start streaming: {}", path.display(), stream_error_advice(&e)) }),
        };
        stream.set_timeout(cfg.timeout);
        while !stop.load(Ordering::Relaxed) {
            match stream.next() {
                Ok((buf, meta)) => {
                    timeouts = 0;
                    let stamp = meta.timestamp.sec as u64 * 1_000_000_000 + meta.timestamp.usec as u64 * 1000;
                    let t_ns = match buffer_time(meta.flags, stamp, monotonic_ns()) {
                        Ok((t, trusted)) => {
                            if !trusted && !warned_clock {
                                warned_clock = true;
                                tracing::warn!(camera = side.name(), "the driver's timestamps are not on CLOCK_MONOTONIC; pairing by the time of dequeue");
                            }
                            t
                        }
                        Err(why) => {
                            tracing::warn!(camera = side.name(), sequence = meta.sequence, "dropping a frame: {why}");
                            continue;
                        }
                    };
                    let frame = to_picture(cfg.fourcc, buf, meta.bytesused as usize, w, h).map(|picture| CameraFrame { side, t_ns, sequence: meta.sequence, picture });
                    match frame {
                        Ok(f) => {
                            if tx.send(Ok(f)).is_err() {
                                return;
                            }
                        }
                        // A corrupt buffer is one lost frame, not a lost camera.
                        Err(e) => tracing::warn!(camera = side.name(), "dropping a frame: {e}"),
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {
                    timeouts += 1;
                    tracing::warn!(camera = side.name(), "no frame within {} ms; restarting the stream", cfg.timeout.as_millis());
                    if timeouts >= 3 {
                        return fail(CaptureError::NoFrame { camera: side.name().into(), waited_ms: cfg.timeout.as_millis() as u64 * 3 });
                    }
                    continue 'streams;
                }
                Err(e) => return fail(CaptureError::Device { camera: side.name().into(), what: format!("{}: {e}", path.display()) }),
            }
        }
    }
}

/// Two V4L2 cameras as a [`StereoSource`].
pub struct V4l2Stereo {
    calib: StereoCalib,
    rx: crossbeam_channel::Receiver<Result<CameraFrame, CaptureError>>,
    pairer: Pairer,
    ready: VecDeque<StereoFrame>,
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    threads: Vec<std::thread::JoinHandle<()>>,
    timeout: Duration,
    paths: (PathBuf, PathBuf),
    fps: f64,
}

/// Waits until both cameras delivered a frame (discarded: a scan takes fresh ones), or the
/// first error either reports.
pub fn await_first_frames(rx: &crossbeam_channel::Receiver<Result<CameraFrame, CaptureError>>, within: Duration) -> Result<(), CaptureError> {
    let deadline = std::time::Instant::now() + within;
    let (mut left, mut right) = (false, false);
    while !(left && right) {
        let wait = deadline.saturating_duration_since(std::time::Instant::now());
        match rx.recv_timeout(wait) {
            Ok(Ok(f)) => match f.side {
                Side::Left => left = true,
                Side::Right => right = true,
            },
            Ok(Err(e)) => return Err(e),
            Err(_) => {
                let camera = match (left, right) {
                    (false, false) => "left and right",
                    (false, true) => "left",
                    _ => "right",
                };
                return Err(CaptureError::NoFrame { camera: camera.into(), waited_ms: within.as_millis() as u64 });
            }
        }
    }
    Ok(())
}

impl V4l2Stereo {
    /// Opens both cameras, starts both streams and waits for a first frame from each, so a
    /// daemon never reports ready with cameras that cannot stream (two UVC cameras on one USB
    /// controller may fail STREAMON for bandwidth). `pair_tolerance_ns`: None pairs within
    /// half a frame period at the rate the drivers actually chose.
    pub fn open(left: &Path, right: &Path, cfg: StreamConfig, pair_tolerance_ns: Option<u64>, calib: StereoCalib) -> Result<V4l2Stereo, CaptureError> {
        // Open both once up front so a wrong path or format is reported before a scan.
        let mut slowest = f64::INFINITY;
        for (side, p) in [(Side::Left, left), (Side::Right, right)] {
            let (_, _, _, fps) = open_device(p, &cfg).map_err(|e| CaptureError::Device { camera: side.name().into(), what: e.to_string() })?;
            if rate_differs(cfg.fps, fps) {
                tracing::warn!(camera = side.name(), path = %p.display(), "runs at {fps:.2} fps, not the configured {} (the driver's nearest at {}×{} {}); pairing follows the real rate", cfg.fps, cfg.width, cfg.height, fourcc_name(cfg.fourcc));
            }
            slowest = slowest.min(fps);
        }
        let pair_tolerance_ns = pair_tolerance_ns.unwrap_or_else(|| half_period_ns(slowest));
        let (tx, rx) = crossbeam_channel::bounded(4 * cfg.buffers as usize);
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let mut threads = Vec::new();
        for (side, p) in [(Side::Left, left), (Side::Right, right)] {
            let (tx, stop, p, cfg) = (tx.clone(), stop.clone(), p.to_path_buf(), cfg.clone());
            let t = std::thread::Builder::new()
                .name(format!("capture-{}", side.name()))
                .spawn(move || capture_loop(side, p, cfg, tx, stop))
                .map_err(|e| CaptureError::Device { camera: side.name().into(), what: format!("cannot start its capture thread: {e}") })?;
            threads.push(t);
        }
        let cams = V4l2Stereo { calib, rx, pairer: Pairer::new(pair_tolerance_ns), ready: VecDeque::new(), stop, threads, timeout: cfg.timeout * 2, paths: (left.into(), right.into()), fps: slowest };
        await_first_frames(&cams.rx, cfg.timeout * 3)?;
        Ok(cams)
    }

    /// The frame rate the drivers chose (the slower camera's).
    pub fn fps(&self) -> f64 {
        self.fps
    }

    pub fn pair_stats(&self) -> PairStats {
        self.pairer.stats
    }
}

impl Drop for V4l2Stereo {
    fn drop(&mut self) {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        while self.rx.try_recv().is_ok() {}
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl StereoSource for V4l2Stereo {
    fn describe(&self) -> String {
        format!("V4L2 cameras {} and {}", self.paths.0.display(), self.paths.1.display())
    }

    fn calibration(&self) -> &StereoCalib {
        &self.calib
    }

    fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
        loop {
            if let Some(f) = self.ready.pop_front() {
                return Ok(Some(f));
            }
            match self.rx.recv_timeout(self.timeout) {
                Ok(Ok(frame)) => self.ready.extend(self.pairer.push(frame, None)),
                Ok(Err(e)) => return Err(e),
                Err(_) => return Err(CaptureError::NoFrame { camera: "left or right".into(), waited_ms: self.timeout.as_millis() as u64 }),
            }
        }
    }

    fn fresh_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
        let now = monotonic_ns();
        loop {
            match self.next_frame()? {
                Some(f) if f.t_left_ns.min(f.t_right_ns) < now => continue,
                other => return Ok(other),
            }
        }
    }

    fn pairing(&self) -> Option<PairStats> {
        Some(self.pairer.stats)
    }
}

/// V4L2 devices with their formats and frame sizes, and serial ports: what a lab needs to
/// fill in `[cameras]` and `[turntable]`.
pub fn list_devices() -> Value {
    use v4l::video::Capture;
    let mut cameras = Vec::new();
    let mut nodes = v4l::context::enum_devices();
    nodes.sort_by_key(|n| n.index());
    for node in nodes {
        let path = node.path().to_path_buf();
        let mut entry = json!({"path": path, "name": node.name()});
        match v4l::Device::with_path(&path) {
            Err(e) => entry["error"] = json!(format!("cannot open: {e}")),
            Ok(dev) => {
                if let Ok(caps) = dev.query_caps() {
                    entry["driver"] = json!(caps.driver);
                    entry["card"] = json!(caps.card);
                    entry["bus"] = json!(caps.bus);
                }
                let formats: Vec<Value> = dev
                    .enum_formats()
                    .unwrap_or_default()
                    .into_iter()
                    .map(|f| {
                        let discrete: Vec<(u32, u32)> = dev.enum_framesizes(f.fourcc).unwrap_or_default().into_iter().flat_map(|s| s.size.to_discrete()).map(|d| (d.width, d.height)).collect();
                        let sizes: Vec<String> = discrete.iter().map(|(w, h)| format!("{w}x{h}")).collect();
                        // The rates each size can run at (what `cameras.fps` may be).
                        let mut rates = serde_json::Map::new();
                        for (w, h) in &discrete {
                            let fps: Vec<f64> = dev
                                .enum_frameintervals(f.fourcc, *w, *h)
                                .unwrap_or_default()
                                .into_iter()
                                .filter_map(|i| match i.interval {
                                    v4l::frameinterval::FrameIntervalEnum::Discrete(frac) => frame_rate(frac),
                                    v4l::frameinterval::FrameIntervalEnum::Stepwise(s) => frame_rate(s.min),
                                })
                                .map(|r| (r * 100.0).round() / 100.0)
                                .collect();
                            rates.insert(format!("{w}x{h}"), json!(fps));
                        }
                        json!({"fourcc": fourcc_name(f.fourcc.repr), "description": f.description, "sizes": sizes, "rates": rates})
                    })
                    .collect();
                entry["formats"] = json!(formats);
            }
        }
        cameras.push(entry);
    }
    let ports: Vec<Value> = match serialport::available_ports() {
        Ok(list) => list.into_iter().map(|p| json!({"path": p.port_name, "kind": format!("{:?}", p.port_type)})).collect(),
        Err(e) => vec![json!({"error": e.to_string()})],
    };
    json!({"cameras": cameras, "serial_ports": ports})
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yuyv_is_converted_with_bt601_limited_range() {
        // Black, white, mid grey, and saturated red (Y=82, U=90, V=240).
        let yuyv = [16, 128, 235, 128, 126, 128, 126, 128, 82, 90, 82, 240];
        let rgb = yuyv_to_rgb(&yuyv, 6, 1);
        assert_eq!(&rgb[..6], &[0, 0, 0, 255, 255, 255]);
        assert_eq!(&rgb[6..9], &[128, 128, 128]);
        assert!(rgb[12] > 250 && rgb[13] < 5 && rgb[14] < 5, "{:?}", &rgb[12..15]);
        // The shared chroma of a pair applies to both pixels.
        assert_eq!(&rgb[6..9], &rgb[9..12]);
    }

    #[test]
    fn buffers_are_sliced_to_bytesused() {
        // An MJPEG frame as a UVC driver hands it over: the JPEG, then stale bytes to the
        // end of the buffer.
        let img = image::RgbImage::from_fn(16, 8, |x, y| image::Rgb([x as u8 * 16, y as u8 * 32, 100]));
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90).encode_image(&img).unwrap();
        let mut buffer = jpeg.clone();
        buffer.resize(jpeg.len() + 512, 0xAB);
        let p = to_picture(*b"MJPG", &buffer, jpeg.len(), 16, 8).unwrap();
        assert_eq!(p, Picture::Jpeg { bytes: jpeg.clone() });
        let (w, h, rgb) = p.to_rgb().unwrap();
        assert_eq!((w, h, rgb.len()), (16, 8, 16 * 8 * 3));
        // Garbage, a short YUYV frame, an overrun and an unknown format are named.
        assert_eq!(to_picture(*b"MJPG", &[0u8; 64], 64, 16, 8), Err(FormatError::Mjpeg(MjpegError::NotJpeg(64))));
        // Defect 5: an MJPEG frame cut short passes the FF D8 check but has no FF D9.
        let cut = &jpeg[..jpeg.len() / 2];
        assert_eq!(to_picture(*b"MJPG", cut, cut.len(), 16, 8), Err(FormatError::Mjpeg(MjpegError::Truncated(cut.len()))));
        assert!(matches!(to_picture(*b"YUYV", &[0u8; 100], 100, 16, 8), Err(FormatError::Short { expected: 256, .. })));
        assert!(matches!(to_picture(*b"YUYV", &[0u8; 100], 200, 16, 8), Err(FormatError::Overrun { .. })));
        assert_eq!(to_picture(*b"RGB3", &[0u8; 400], 400, 16, 8).unwrap_err().to_string(), "pixel format RGB3 is not supported (expected MJPG, YUYV or GREY)");
        // Risk 8: a UVC frame without Huffman tables is recorded with the standard ones.
        let no_dht = crate::hw::mjpeg::tests::without_dht(&jpeg);
        let Picture::Jpeg { bytes } = to_picture(*b"MJPG", &no_dht, no_dht.len(), 16, 8).unwrap() else { panic!("kept as JPEG") };
        assert!(bytes.windows(2).any(|w| w == [0xFF, 0xC4]), "a DHT segment was inserted");
        assert_eq!(Picture::Jpeg { bytes }.to_rgb().unwrap().2, rgb, "and it decodes as the original");
        // YUYV with bytesused 0 (the full buffer).
        assert!(matches!(to_picture(*b"YUYV", &[128u8; 256], 0, 16, 8), Ok(Picture::Raw { channels: 3, .. })));
    }

    /// Defect 5: a buffer the driver flags as damaged is dropped; timestamps are trusted
    /// only when they say CLOCK_MONOTONIC.
    #[test]
    fn flagged_buffers_are_dropped_and_only_monotonic_stamps_trusted() {
        use v4l::buffer::Flags;
        assert!(buffer_time(Flags::ERROR | Flags::TIMESTAMP_MONOTONIC, 5, 9).is_err());
        assert_eq!(buffer_time(Flags::DONE | Flags::TIMESTAMP_MONOTONIC, 5, 9), Ok((5, true)));
        assert_eq!(buffer_time(Flags::DONE | Flags::TIMESTAMP_COPY, 5, 9), Ok((9, false)));
        assert_eq!(buffer_time(Flags::DONE, 5, 9), Ok((9, false)), "unknown clock");
    }

    /// Defect 4: the rate the driver chose is read back; the pairing tolerance follows it.
    #[test]
    fn the_real_frame_rate_sets_the_pairing_tolerance() {
        let got = frame_rate(v4l::Fraction::new(1, 10)).unwrap();
        assert_eq!(got, 10.0);
        assert!(rate_differs(15, got) && !rate_differs(15, frame_rate(v4l::Fraction::new(1001, 15015)).unwrap()));
        assert_eq!(half_period_ns(got), 50_000_000, "half of 100 ms, not of the configured 66.7 ms");
        assert_eq!(frame_rate(v4l::Fraction::new(0, 15)), None);
    }

    /// Risk 9: ENOSPC at STREAMON gets advice a lab can act on.
    #[test]
    fn no_bandwidth_is_explained() {
        let e = std::io::Error::from_raw_os_error(libc::ENOSPC);
        let text = stream_error_advice(&e);
        assert!(text.contains("USB controller") && text.contains("MJPG"), "{text}");
    }

    /// Risk 9: opening waits for a first frame from each camera, and names the silent one.
    #[test]
    fn opening_waits_for_both_cameras() {
        let frame = |side| CameraFrame { side, t_ns: 1, sequence: 0, picture: Picture::Raw { width: 1, height: 1, channels: 1, data: vec![0] } };
        let (tx, rx) = crossbeam_channel::unbounded();
        tx.send(Ok(frame(Side::Left))).unwrap();
        tx.send(Ok(frame(Side::Left))).unwrap();
        let e = await_first_frames(&rx, Duration::from_millis(50)).unwrap_err();
        assert!(matches!(&e, CaptureError::NoFrame { camera, .. } if camera == "right"), "{e}");
        tx.send(Ok(frame(Side::Right))).unwrap();
        tx.send(Ok(frame(Side::Left))).unwrap();
        assert!(await_first_frames(&rx, Duration::from_millis(50)).is_ok());
        tx.send(Err(CaptureError::Device { camera: "left".into(), what: "cannot start streaming: ENOSPC".into() })).unwrap();
        assert!(matches!(await_first_frames(&rx, Duration::from_millis(50)), Err(CaptureError::Device { .. })));
    }

    /// `devices` warns when the configured format, size or rate is not offered.
    #[test]
    fn a_configuration_the_cameras_cannot_do_is_named() {
        let listing = json!({"cameras": [
            {"path": "/dev/video0", "formats": [{"fourcc": "MJPG", "sizes": ["640x480", "1280x720"], "rates": {"640x480": [30.0, 15.0], "1280x720": [10.0]}}]},
            {"path": "/dev/video2", "formats": [{"fourcc": "YUYV", "sizes": ["640x480"], "rates": {"640x480": [30.0]}}]},
        ]});
        let (l, r) = (Path::new("/dev/video0"), Path::new("/dev/video2"));
        assert!(check_offered(&listing, &[l], *b"MJPG", 640, 480, 15).is_empty());
        let w = check_offered(&listing, &[l], *b"MJPG", 1280, 720, 15);
        assert!(w.len() == 1 && w[0].contains("at 15 fps") && w[0].contains("10"), "{w:?}");
        let w = check_offered(&listing, &[l, r], *b"MJPG", 640, 480, 15);
        assert!(w.len() == 1 && w[0].contains("/dev/video2 does not offer MJPG (it offers YUYV)"), "{w:?}");
        let w = check_offered(&listing, &[Path::new("/dev/video9")], *b"MJPG", 640, 480, 15);
        assert_eq!(w, vec!["/dev/video9 is not present".to_string()]);
    }
}
