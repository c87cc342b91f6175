//! Recordings on disk (`shared/spec/recording-format.md`, version 1): writing one while
//! scanning, reading one back (strictly, with messages that name the file, line and key),
//! and replaying it as a [`crate::hw::StereoSource`] ([`crate::hw::replay`]).
//!
//! ```text
//!  DIR/calib.yaml  frames.jsonl  left/NNNNNN.png  right/NNNNNN.png  [turntable.yaml]  [gt/…]
//! ```
//!
//! Writers put both images on disk (atomically) before the `frames.jsonl` line that names
//! them, and flush the line, so a crash leaves at worst a torn last line, which readers skip
//! with a warning.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use serde_json::{json, Value};

use crate::calib::{CalibError, StereoCalib};
use crate::hw::frame::{Picture, StereoFrame};

/// Why a recording cannot be read or written.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("{0} is not a recording: it has no frames.jsonl")]
    NoFrames(PathBuf),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Calib(#[from] CalibError),
    #[error("{path}:{line}: not a JSON object ({what}); expected one frame per line like {{\"seq\": 0, \"left\": \"left/000000.png\", …}}")]
    Json { path: PathBuf, line: usize, what: String },
    #[error("{path}:{line}: key `{key}` {what}")]
    Key { path: PathBuf, line: usize, key: &'static str, what: String },
    #[error("{path}:{line}: seq {seq} does not follow seq {previous} (seq must strictly increase)")]
    SeqOrder { path: PathBuf, line: usize, seq: u64, previous: u64 },
    #[error("{path}:{line}: image {image} is missing")]
    MissingImage { path: PathBuf, line: usize, image: PathBuf },
    #[error("{path}:{line}: image {image} cannot be read: {what}")]
    BadImage { path: PathBuf, line: usize, image: PathBuf, what: String },
    #[error("{path}:{line}: image {image} is {got_w}×{got_h} but the recording's images are {want_w}×{want_h} ({why})")]
    ImageSize { path: PathBuf, line: usize, image: PathBuf, got_w: u32, got_h: u32, want_w: u32, want_h: u32, why: &'static str },
    #[error("{path} holds no complete frame")]
    Empty { path: PathBuf },
    #[error("{0} already holds a recording (frames.jsonl); choose an empty folder")]
    Exists(PathBuf),
    #[error("seq {seq} does not follow seq {previous}: a recording's seq must strictly increase")]
    WriteOrder { seq: u64, previous: u64 },
    #[error("cannot write {path}: {what}")]
    Write { path: PathBuf, what: String },
    /// A line of a side file (`turntable.yaml`, `gt/poses.jsonl`); line 0 = the whole file.
    #[error("{path}:{line}: {what}")]
    Invalid { path: PathBuf, line: usize, what: String },
}

/// One line of `frames.jsonl`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameEntry {
    pub seq: u64,
    /// Image paths relative to the recording folder, as written in the line.
    pub left: String,
    pub right: String,
    pub t_left_ns: u64,
    pub t_right_ns: u64,
    pub table_deg: Option<f64>,
    /// 1-based line number in `frames.jsonl`, for messages.
    pub line: usize,
}

/// The turntable axis in the LEFT raw camera frame (`turntable.yaml`).
#[derive(Debug, Clone, PartialEq)]
pub struct TurntableAxis {
    pub axis_point_mm: [f64; 3],
    /// Unit vector pointing up (table surface → object top).
    pub axis_dir: [f64; 3],
    /// "calibrated", "estimated", or "ground truth" (simulator).
    pub source: String,
}

impl TurntableAxis {
    /// Reads the keys [`TurntableAxis::to_yaml`] writes (`axis_point_mm: [x, y, z]`,
    /// `axis_dir: [x, y, z]`, `source: "…"`); `#` comments and unknown keys are ignored.
    pub fn parse(path: &Path, text: &str) -> Result<TurntableAxis, RecordingError> {
        let bad = |line: usize, what: String| RecordingError::Invalid { path: path.to_path_buf(), line, what };
        let (mut point, mut dir, mut source) = (None, None, String::from("calibrated"));
        for (i, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("").trim();
            let Some((key, value)) = line.split_once(':') else { continue };
            let value = value.trim();
            let vec3 = |v: &str| -> Result<[f64; 3], RecordingError> {
                let inner = v.strip_prefix('[').and_then(|v| v.strip_suffix(']')).ok_or_else(|| bad(i + 1, format!("`{}` must be a list [x, y, z]", key.trim())))?;
                let nums: Vec<f64> = inner.split(',').map(|x| x.trim().parse::<f64>()).collect::<Result<_, _>>().map_err(|_| bad(i + 1, format!("`{}` must hold three numbers, found `{v}`", key.trim())))?;
                let arr: [f64; 3] = nums.try_into().map_err(|_| bad(i + 1, format!("`{}` must hold three numbers, found `{v}`", key.trim())))?;
                if arr.iter().all(|x| x.is_finite()) { Ok(arr) } else { Err(bad(i + 1, format!("`{}` has a non-finite number", key.trim()))) }
            };
            match key.trim() {
                "axis_point_mm" => point = Some(vec3(value)?),
                "axis_dir" => {
                    let d = vec3(value)?;
                    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    if n < 1e-9 {
                        return Err(bad(i + 1, "`axis_dir` is the zero vector; expected a direction".into()));
                    }
                    dir = Some([d[0] / n, d[1] / n, d[2] / n]);
                }
                "source" => source = value.trim_matches('"').to_string(),
                _ => {}
            }
        }
        match (point, dir) {
            (Some(axis_point_mm), Some(axis_dir)) => Ok(TurntableAxis { axis_point_mm, axis_dir, source }),
            _ => Err(bad(0, "expected both `axis_point_mm: [x, y, z]` and `axis_dir: [x, y, z]`".into())),
        }
    }

    /// `turntable.yaml` of a recording (a calibrated axis), when it has one.
    pub fn read_calibrated(dir: &Path) -> Result<Option<TurntableAxis>, RecordingError> {
        let path = dir.join("turntable.yaml");
        match std::fs::read_to_string(&path) {
            Ok(text) => TurntableAxis::parse(&path, &text).map(Some),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
            Err(source) => Err(RecordingError::Io { path, source }),
        }
    }

    pub fn to_yaml(&self) -> String {
        let v = |a: [f64; 3]| format!("[{:.9}, {:.9}, {:.9}]", a[0], a[1], a[2]);
        format!("axis_point_mm: {}\naxis_dir: {}\nsource: \"{}\"\n", v(self.axis_point_mm), v(self.axis_dir), self.source)
    }
}

/// An opened, checked recording.
#[derive(Debug, Clone)]
pub struct Recording {
    pub dir: PathBuf,
    pub calib: StereoCalib,
    pub frames: Vec<FrameEntry>,
    /// `(width, height)` of every image.
    pub image_size: (u32, u32),
    /// Line number of a torn last line that was skipped.
    pub torn_line: Option<usize>,
}

fn frames_path(dir: &Path) -> PathBuf {
    dir.join("frames.jsonl")
}

/// Parses `frames.jsonl` text. Unknown keys are ignored; a last line without its newline
/// is a torn write and is skipped (its number is returned).
pub fn parse_frames(path: &Path, text: &str) -> Result<(Vec<FrameEntry>, Option<usize>), RecordingError> {
    let mut frames: Vec<FrameEntry> = Vec::new();
    let mut torn = None;
    let lines: Vec<&str> = text.split('\n').collect();
    for (i, raw) in lines.iter().enumerate() {
        let line = i + 1;
        let is_last = i + 1 == lines.len();
        let content = raw.trim_end_matches('\r');
        if content.trim().is_empty() {
            continue;
        }
        if is_last {
            // No newline after it: the writer died mid-line.
            torn = Some(line);
            break;
        }
        let value: Value = serde_json::from_str(content).map_err(|e| RecordingError::Json { path: path.to_path_buf(), line, what: e.to_string() })?;
        let obj = value.as_object().ok_or_else(|| RecordingError::Json { path: path.to_path_buf(), line, what: format!("found {}", kind(&value)) })?;
        let key_err = |key: &'static str, what: String| RecordingError::Key { path: path.to_path_buf(), line, key, what };
        let uint = |key: &'static str| -> Result<u64, RecordingError> {
            match obj.get(key) {
                None => Err(key_err(key, "is missing (expected a non-negative integer)".into())),
                Some(v) => v.as_u64().ok_or_else(|| key_err(key, format!("is {v} (expected a non-negative integer)"))),
            }
        };
        let string = |key: &'static str| -> Result<String, RecordingError> {
            match obj.get(key) {
                None => Err(key_err(key, "is missing (expected an image path relative to the recording)".into())),
                Some(Value::String(s)) if !s.is_empty() => Ok(s.clone()),
                Some(v) => Err(key_err(key, format!("is {v} (expected an image path relative to the recording)"))),
            }
        };
        let table_deg = match obj.get("table_deg") {
            None | Some(Value::Null) => None,
            Some(v) => Some(v.as_f64().filter(|d| d.is_finite()).ok_or_else(|| key_err("table_deg", format!("is {v} (expected degrees or null)")))?),
        };
        let entry = FrameEntry {
            seq: uint("seq")?,
            left: string("left")?,
            right: string("right")?,
            t_left_ns: uint("t_left_ns")?,
            t_right_ns: uint("t_right_ns")?,
            table_deg,
            line,
        };
        if let Some(prev) = frames.last() {
            if entry.seq <= prev.seq {
                return Err(RecordingError::SeqOrder { path: path.to_path_buf(), line, seq: entry.seq, previous: prev.seq });
            }
        }
        frames.push(entry);
    }
    Ok((frames, torn))
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

impl Recording {
    /// Opens a recording and checks it through: calibration, every line of `frames.jsonl`,
    /// and every image's presence and size (headers only), so a replay fails before it
    /// starts rather than halfway.
    pub fn open(dir: &Path) -> Result<Recording, RecordingError> {
        let path = frames_path(dir);
        if !path.is_file() {
            return Err(RecordingError::NoFrames(dir.to_path_buf()));
        }
        let text = std::fs::read_to_string(&path).map_err(|source| RecordingError::Io { path: path.clone(), source })?;
        let (frames, torn_line) = parse_frames(&path, &text)?;
        if let Some(line) = torn_line {
            tracing::warn!(file = %path.display(), line, "skipping a torn last line (the writer stopped mid-line)");
        }
        if frames.is_empty() {
            return Err(RecordingError::Empty { path });
        }
        let calib = StereoCalib::load(dir)?;
        let mut size = calib.image_size;
        for f in &frames {
            for image in [&f.left, &f.right] {
                let full = dir.join(image);
                if !full.is_file() {
                    return Err(RecordingError::MissingImage { path: path.clone(), line: f.line, image: full });
                }
                let (w, h) = image::image_dimensions(&full).map_err(|e| RecordingError::BadImage { path: path.clone(), line: f.line, image: full.clone(), what: e.to_string() })?;
                match size {
                    None => size = Some((w, h)),
                    Some((want_w, want_h)) if (w, h) != (want_w, want_h) => {
                        let why = if calib.image_size.is_some() { "image_width/image_height in the calibration" } else { "the first image" };
                        return Err(RecordingError::ImageSize { path: path.clone(), line: f.line, image: full, got_w: w, got_h: h, want_w, want_h, why });
                    }
                    Some(_) => {}
                }
            }
        }
        Ok(Recording { dir: dir.to_path_buf(), calib, frames, image_size: size.expect("at least one frame"), torn_line })
    }

    /// Reads the images of frame `index` (as delivered: PNG decoded, JPEG kept encoded).
    pub fn load_frame(&self, index: usize) -> Result<StereoFrame, RecordingError> {
        let f = &self.frames[index];
        let path = frames_path(&self.dir);
        let load = |image: &str| -> Result<Picture, RecordingError> {
            let full = self.dir.join(image);
            let bad = |what: String| RecordingError::BadImage { path: path.clone(), line: f.line, image: full.clone(), what };
            let bytes = std::fs::read(&full).map_err(|e| bad(e.to_string()))?;
            let format = image::guess_format(&bytes).map_err(|e| bad(e.to_string()))?;
            if format == image::ImageFormat::Jpeg {
                return Ok(Picture::Jpeg { bytes });
            }
            let img = image::load_from_memory_with_format(&bytes, format).map_err(|e| bad(e.to_string()))?;
            let (w, h) = (img.width() as usize, img.height() as usize);
            if (w as u32, h as u32) != self.image_size {
                return Err(RecordingError::ImageSize {
                    path: path.clone(),
                    line: f.line,
                    image: full.clone(),
                    got_w: w as u32,
                    got_h: h as u32,
                    want_w: self.image_size.0,
                    want_h: self.image_size.1,
                    why: "the recording's other images",
                });
            }
            Ok(match img {
                image::DynamicImage::ImageLuma8(g) => Picture::Raw { width: w, height: h, channels: 1, data: g.into_raw() },
                other => Picture::Raw { width: w, height: h, channels: 3, data: other.to_rgb8().into_raw() },
            })
        };
        Ok(StereoFrame { seq: f.seq, t_left_ns: f.t_left_ns, t_right_ns: f.t_right_ns, table_deg: f.table_deg, left: load(&f.left)?, right: load(&f.right)? })
    }

    /// The ground-truth disparity of frame `seq`, when the recording has one (ideal rigs).
    pub fn gt_disparity_path(&self, seq: u64) -> Option<PathBuf> {
        gt_disparity_path(&self.dir, seq)
    }
}

/// `DIR/gt/disparity/NNNNNN.png` when it exists.
pub fn gt_disparity_path(dir: &Path, seq: u64) -> Option<PathBuf> {
    Some(dir.join("gt/disparity").join(format!("{seq:06}.png"))).filter(|p| p.is_file())
}

/// `gt/poses.jsonl` of a simulated recording: `(seq, cam_from_obj)` per frame, or `None`
/// when the recording has none.
pub fn read_gt_poses(dir: &Path) -> Result<Option<Vec<(u64, [[f64; 4]; 4])>>, RecordingError> {
    Ok(gt_pose_lines(dir)?.map(|lines| lines.into_iter().map(|(_, seq, rows)| (seq, rows)).collect()))
}

/// [`read_gt_poses`] with each `cam_from_obj` checked as a rigid transform (to 10⁻⁴), as
/// scoring uses them; one that is not is an error naming its line.
pub fn read_gt_cam_from_obj(dir: &Path) -> Result<Option<Vec<(u64, nalgebra::Isometry3<f64>)>>, RecordingError> {
    let Some(lines) = gt_pose_lines(dir)? else { return Ok(None) };
    let path = dir.join("gt/poses.jsonl");
    let rigid = |(line, seq, rows): (usize, u64, [[f64; 4]; 4])| {
        crate::register::from_rows(&rows, 1e-4).map(|t| (seq, t)).map_err(|e| RecordingError::Invalid { path: path.clone(), line, what: format!("seq {seq}: cam_from_obj: {e}") })
    };
    lines.into_iter().map(rigid).collect::<Result<_, _>>().map(Some)
}

/// `gt/poses.jsonl`'s lines as `(line number, seq, cam_from_obj)`, blank lines skipped.
fn gt_pose_lines(dir: &Path) -> Result<Option<Vec<(usize, u64, [[f64; 4]; 4])>>, RecordingError> {
    let path = dir.join("gt/poses.jsonl");
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(RecordingError::Io { path, source }),
    };
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        #[derive(serde::Deserialize)]
        struct GtPose {
            seq: u64,
            cam_from_obj: [[f64; 4]; 4],
        }
        let p: GtPose = serde_json::from_str(line).map_err(|e| RecordingError::Invalid { path: path.clone(), line: i + 1, what: format!("expected {{\"seq\": N, \"cam_from_obj\": [[4x4]]}}: {e}") })?;
        out.push((i + 1, p.seq, p.cam_from_obj));
    }
    Ok(Some(out))
}

/// Writes a recording as frames arrive.
pub struct RecordingWriter {
    dir: PathBuf,
    frames: File,
    last_seq: Option<u64>,
    gt_poses: Option<File>,
}

impl RecordingWriter {
    /// Starts a recording in `dir` (created if needed; must not already hold one).
    pub fn create(dir: &Path, calib: &StereoCalib) -> Result<RecordingWriter, RecordingError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| RecordingError::Io { path, source }
        };
        if frames_path(dir).exists() {
            return Err(RecordingError::Exists(dir.to_path_buf()));
        }
        for sub in ["left", "right"] {
            std::fs::create_dir_all(dir.join(sub)).map_err(io(&dir.join(sub)))?;
        }
        let calib_path = dir.join("calib.yaml");
        crate::io::write_atomic(&calib_path, calib.to_yaml().as_bytes()).map_err(io(&calib_path))?;
        let path = frames_path(dir);
        let frames = File::create(&path).map_err(io(&path))?;
        Ok(RecordingWriter { dir: dir.to_path_buf(), frames, last_seq: None, gt_poses: None })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Stores one pair: both images first, then its line in `frames.jsonl` (flushed).
    pub fn append(&mut self, frame: &StereoFrame) -> Result<(), RecordingError> {
        if let Some(previous) = self.last_seq {
            if frame.seq <= previous {
                return Err(RecordingError::WriteOrder { seq: frame.seq, previous });
            }
        }
        let left = self.write_picture("left", frame.seq, &frame.left)?;
        let right = self.write_picture("right", frame.seq, &frame.right)?;
        let line = json!({
            "seq": frame.seq, "left": left, "right": right,
            "t_left_ns": frame.t_left_ns, "t_right_ns": frame.t_right_ns, "table_deg": frame.table_deg,
        });
        let path = frames_path(&self.dir);
        writeln!(self.frames, "{line}").and_then(|_| self.frames.flush()).map_err(|source| RecordingError::Io { path, source })?;
        self.last_seq = Some(frame.seq);
        Ok(())
    }

    fn write_picture(&self, side: &str, seq: u64, picture: &Picture) -> Result<String, RecordingError> {
        let (rel, bytes) = match picture {
            Picture::Jpeg { bytes } => (format!("{side}/{seq:06}.jpg"), bytes.clone()),
            Picture::Raw { width, height, channels, data } => {
                let color = match channels {
                    1 => image::ExtendedColorType::L8,
                    3 => image::ExtendedColorType::Rgb8,
                    c => return Err(RecordingError::Write { path: self.dir.join(side), what: format!("{c}-channel images are not supported") }),
                };
                let mut png = Vec::new();
                image::ImageEncoder::write_image(image::codecs::png::PngEncoder::new_with_quality(&mut png, image::codecs::png::CompressionType::Fast, image::codecs::png::FilterType::Adaptive), data, *width as u32, *height as u32, color)
                    .map_err(|e| RecordingError::Write { path: self.dir.join(side), what: e.to_string() })?;
                (format!("{side}/{seq:06}.png"), png)
            }
        };
        let full = self.dir.join(&rel);
        crate::io::write_atomic(&full, &bytes).map_err(|source| RecordingError::Io { path: full, source })?;
        Ok(rel)
    }

    /// `turntable.yaml` (a calibrated axis) or, with `gt`, `gt/turntable.yaml`.
    pub fn write_turntable(&self, axis: &TurntableAxis, gt: bool) -> Result<(), RecordingError> {
        let path = if gt { self.dir.join("gt/turntable.yaml") } else { self.dir.join("turntable.yaml") };
        crate::io::write_atomic(&path, axis.to_yaml().as_bytes()).map_err(|source| RecordingError::Io { path, source })
    }

    /// `gt/mesh.ply`: the object's surface in its own frame, mm.
    pub fn write_gt_mesh(&self, mesh: &crate::cloud::Mesh) -> Result<(), RecordingError> {
        let path = self.dir.join("gt/mesh.ply");
        crate::io::ply::write_mesh_ply(&path, mesh).map_err(|e| RecordingError::Write { path, what: e.to_string() })
    }

    /// One line of `gt/poses.jsonl`: `cam_from_obj` maps object points into the LEFT raw
    /// camera frame at frame `seq`, mm.
    pub fn append_gt_pose(&mut self, seq: u64, cam_from_obj: &[[f64; 4]; 4]) -> Result<(), RecordingError> {
        let path = self.dir.join("gt/poses.jsonl");
        if self.gt_poses.is_none() {
            std::fs::create_dir_all(self.dir.join("gt")).map_err(|source| RecordingError::Io { path: path.clone(), source })?;
            self.gt_poses = Some(File::create(&path).map_err(|source| RecordingError::Io { path: path.clone(), source })?);
        }
        let line = json!({"seq": seq, "cam_from_obj": cam_from_obj});
        let file = self.gt_poses.as_mut().unwrap();
        writeln!(file, "{line}").and_then(|_| file.flush()).map_err(|source| RecordingError::Io { path, source })
    }

    /// `gt/disparity/NNNNNN.png` (uint16, disparity × 256, 0 where the object is not seen).
    pub fn write_gt_disparity(&self, seq: u64, disparity: &crate::stereo::DisparityMap) -> Result<(), RecordingError> {
        let path = self.dir.join("gt/disparity").join(format!("{seq:06}.png"));
        crate::io::write_disparity_png(&path, disparity).map_err(|e| RecordingError::Write { path, what: e.to_string() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<(Vec<FrameEntry>, Option<usize>), RecordingError> {
        parse_frames(Path::new("rec/frames.jsonl"), text)
    }

    const LINE0: &str = r#"{"seq": 0, "left": "left/000000.png", "right": "right/000000.png", "t_left_ns": 1000000000, "t_right_ns": 1000350000, "table_deg": 0.0}"#;

    #[test]
    fn gaps_unknown_keys_null_angles_and_crlf_are_fine() {
        let text = format!("{LINE0}\r\n{{\"seq\": 5, \"left\": \"l.png\", \"right\": \"r.png\", \"t_left_ns\": 1, \"t_right_ns\": 2, \"table_deg\": null, \"exposure_us\": 800}}\n");
        let (frames, torn) = parse(&text).unwrap();
        assert_eq!(torn, None);
        assert_eq!(frames.iter().map(|f| f.seq).collect::<Vec<_>>(), [0, 5]);
        assert_eq!(frames[1].table_deg, None);
        assert_eq!(frames[1].line, 2);
    }

    #[test]
    fn a_torn_last_line_is_skipped() {
        let text = format!("{LINE0}\n{{\"seq\": 1, \"left\": \"left/0000");
        let (frames, torn) = parse(&text).unwrap();
        assert_eq!((frames.len(), torn), (1, Some(2)));
    }

    #[test]
    fn bad_lines_are_named() {
        let cases = [
            (format!("{LINE0}\nnot json\n{LINE0}\n"), "frames.jsonl:2: not a JSON object"),
            (format!("{LINE0}\n[1, 2]\n"), "frames.jsonl:2: not a JSON object (found an array)"),
            (format!("{LINE0}\n{LINE0}\n"), "frames.jsonl:2: seq 0 does not follow seq 0"),
            ("{\"seq\": -1}\n".to_string(), "frames.jsonl:1: key `seq` is -1"),
            (LINE0.replace("\"left\": \"left/000000.png\", ", "") + "\n", "frames.jsonl:1: key `left` is missing"),
            (LINE0.replace("0.0}", "\"ten\"}") + "\n", "frames.jsonl:1: key `table_deg` is \"ten\" (expected degrees or null)"),
        ];
        for (text, want) in cases {
            let e = parse(&text).unwrap_err().to_string();
            assert!(e.contains(want), "{e}\n  should contain: {want}");
        }
    }
}
