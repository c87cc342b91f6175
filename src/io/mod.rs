//! Files: images in, disparity maps (16-bit PNG, PFM, false colour), masks, PLY, and the pose
//! files of `spinscan register` (transform JSON, Stanford `.conf`).

pub mod mesh;
pub mod ply;
pub mod poses;

use std::path::{Path, PathBuf};

use image::{ImageBuffer, Luma, Rgb};

use crate::stereo::DisparityMap;

/// Why an image file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    #[error("cannot read image {path}: {what}")]
    Read { path: PathBuf, what: String },
    #[error("cannot write {path}: {what}")]
    Write { path: PathBuf, what: String },
    #[error("{path}: {what}")]
    Format { path: PathBuf, what: String },
}

/// An 8-bit RGB image and its grey version, as loaded from a file.
#[derive(Debug, Clone)]
pub struct LoadedImage {
    pub width: usize,
    pub height: usize,
    /// Interleaved RGB (grey files are replicated to three channels).
    pub rgb: Vec<u8>,
    /// Luma, ITU-R BT.601 like OpenCV's `IMREAD_GRAYSCALE`.
    pub gray: Vec<u8>,
}

/// Loads a PNG, JPEG or PNM image.
pub fn load_image(path: &Path) -> Result<LoadedImage, ImageIoError> {
    // The format from the bytes, not the name: a PNG saved as `.jpg` still loads, and a
    // file that is no image says so.
    let read = |e: String| ImageIoError::Read { path: path.to_path_buf(), what: e };
    let bytes = std::fs::read(path).map_err(|e| read(e.to_string()))?;
    let format = image::guess_format(&bytes).map_err(|_| read("not a PNG, JPEG or PNM image (its first bytes are no image signature)".into()))?;
    let img = image::load_from_memory_with_format(&bytes, format).map_err(|e| read(e.to_string()))?;
    let rgb = img.to_rgb8();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    if w == 0 || h == 0 {
        return Err(ImageIoError::Format { path: path.to_path_buf(), what: "the image is empty".into() });
    }
    let rgb = rgb.into_raw();
    let gray = rgb_to_gray(&rgb);
    Ok(LoadedImage { width: w, height: h, rgb, gray })
}

/// BT.601 luma with OpenCV's fixed-point weights (0.299, 0.587, 0.114).
pub fn rgb_to_gray(rgb: &[u8]) -> Vec<u8> {
    let mut gray = vec![0u8; rgb.len() / 3];
    for (g, p) in gray.iter_mut().zip(rgb.chunks_exact(3)) {
        *g = crate::stereo::luma(p[0], p[1], p[2]);
    }
    gray
}

/// Writes `data` to `path` through a temporary file and a rename, so readers never see a
/// half-written file.
pub fn write_atomic(path: &Path, data: &[u8]) -> std::io::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(format!(".tmp-{}", std::process::id()));
    let tmp = PathBuf::from(tmp);
    let written = std::fs::write(&tmp, data).and_then(|()| std::fs::rename(&tmp, path));
    if written.is_err() {
        // A full disk or a failed rename leaves no half-written temp file behind.
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

fn encode_png<P: image::PixelWithColorType>(path: &Path, img: &ImageBuffer<P, Vec<P::Subpixel>>) -> Result<(), ImageIoError>
where
    [P::Subpixel]: image::EncodableLayout,
{
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, image::ImageFormat::Png)
        .map_err(|e| ImageIoError::Write { path: path.to_path_buf(), what: e.to_string() })?;
    write_atomic(path, buf.get_ref()).map_err(|e| ImageIoError::Write { path: path.to_path_buf(), what: e.to_string() })
}

/// Writes an 8-bit grey PNG (masks, rectified grey images).
pub fn write_gray_png(path: &Path, width: usize, height: usize, data: &[u8]) -> Result<(), ImageIoError> {
    let img = ImageBuffer::<Luma<u8>, _>::from_raw(width as u32, height as u32, data.to_vec())
        .ok_or_else(|| ImageIoError::Write { path: path.to_path_buf(), what: "buffer size does not match the image size".into() })?;
    encode_png(path, &img)
}

/// Writes an 8-bit RGB PNG.
pub fn write_rgb_png(path: &Path, width: usize, height: usize, data: &[u8]) -> Result<(), ImageIoError> {
    let img = ImageBuffer::<Rgb<u8>, _>::from_raw(width as u32, height as u32, data.to_vec())
        .ok_or_else(|| ImageIoError::Write { path: path.to_path_buf(), what: "buffer size does not match the image size".into() })?;
    encode_png(path, &img)
}

/// Writes a disparity map as a 16-bit PNG in the KITTI convention: value = |d| × 256 (rounded,
/// saturated at 65535), 0 = no disparity. The sign is not stored (see `disparity_sign`).
pub fn write_disparity_png(path: &Path, disp: &DisparityMap) -> Result<(), ImageIoError> {
    let data: Vec<u16> = disp
        .values()
        .iter()
        .map(|&d| if d.is_finite() { (d.abs() * 256.0).round().clamp(1.0, 65535.0) as u16 } else { 0 })
        .collect();
    let img = ImageBuffer::<Luma<u16>, _>::from_raw(disp.width as u32, disp.height as u32, data).expect("map size");
    encode_png(path, &img)
}

/// Reads a KITTI-convention 16-bit disparity PNG; `sign` (±1) restores the sign.
pub fn read_disparity_png(path: &Path, sign: f32) -> Result<DisparityMap, ImageIoError> {
    // The format from the bytes, not the name: a PNG saved as `.jpg` still loads, and a
    // file that is no image says so.
    let read = |e: String| ImageIoError::Read { path: path.to_path_buf(), what: e };
    let reader = image::ImageReader::open(path).map_err(|e| read(e.to_string()))?.with_guessed_format().map_err(|e| read(e.to_string()))?;
    if reader.format().is_none() {
        return Err(read("not a PNG, JPEG or PNM image".into()));
    }
    let img = reader.decode().map_err(|e| read(e.to_string()))?;
    if img.color().channel_count() != 1 {
        return Err(ImageIoError::Format { path: path.to_path_buf(), what: format!("a disparity PNG has one channel, this one has {}", img.color().channel_count()) });
    }
    let g = img.to_luma16();
    let (w, h) = (g.width() as usize, g.height() as usize);
    let vals = g.into_raw().into_iter().map(|v| if v == 0 { f32::NAN } else { sign * v as f32 / 256.0 }).collect();
    Ok(DisparityMap::from_values(w, h, vals))
}

/// Writes a signed disparity map as a little-endian grey PFM (non-finite = no disparity).
pub fn write_pfm(path: &Path, disp: &DisparityMap) -> Result<(), ImageIoError> {
    let mut out = format!("Pf\n{} {}\n-1.0\n", disp.width, disp.height).into_bytes();
    // PFM stores rows bottom to top.
    for y in (0..disp.height).rev() {
        for &v in &disp.values()[y * disp.width..(y + 1) * disp.width] {
            let v = if v.is_finite() { v } else { f32::INFINITY };
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    write_atomic(path, &out).map_err(|e| ImageIoError::Write { path: path.to_path_buf(), what: e.to_string() })
}

/// Reads a grey PFM (either byte order).
pub fn read_pfm(path: &Path) -> Result<DisparityMap, ImageIoError> {
    let bytes = std::fs::read(path).map_err(|e| ImageIoError::Read { path: path.to_path_buf(), what: e.to_string() })?;
    let bad = |what: &str| ImageIoError::Format { path: path.to_path_buf(), what: what.to_string() };
    let mut fields = Vec::new();
    let mut pos = 0;
    while fields.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos {
            return Err(bad("the PFM header is incomplete"));
        }
        fields.push(String::from_utf8_lossy(&bytes[start..pos]).into_owned());
    }
    pos += 1; // the single whitespace byte after the scale
    if fields[0] != "Pf" {
        return Err(bad(&format!("expected a grey PFM (`Pf`), found `{}`", fields[0])));
    }
    let w: usize = fields[1].parse().map_err(|_| bad("bad width"))?;
    let h: usize = fields[2].parse().map_err(|_| bad("bad height"))?;
    let scale: f32 = fields[3].parse().map_err(|_| bad("bad scale"))?;
    let data = bytes.get(pos..pos + w * h * 4).ok_or_else(|| bad("the file is shorter than width × height floats"))?;
    let mut vals = vec![0f32; w * h];
    for (i, c) in data.chunks_exact(4).enumerate() {
        let a = [c[0], c[1], c[2], c[3]];
        let v = if scale < 0.0 { f32::from_le_bytes(a) } else { f32::from_be_bytes(a) };
        let (x, y) = (i % w, h - 1 - i / w);
        vals[y * w + x] = if v.is_finite() { v } else { f32::NAN };
    }
    Ok(DisparityMap::from_values(w, h, vals))
}

/// A false-colour rendering for people: near (large |d|) is red, far is blue, no disparity
/// is black. `range` is the |d| range mapped onto the colour scale.
pub fn disparity_false_color(disp: &DisparityMap, range: (f32, f32)) -> Vec<u8> {
    let (lo, hi) = range;
    let span = (hi - lo).max(1e-6);
    let mut out = Vec::with_capacity(disp.values().len() * 3);
    for &d in disp.values() {
        if !d.is_finite() {
            out.extend_from_slice(&[0, 0, 0]);
            continue;
        }
        let t = ((d.abs() - lo) / span).clamp(0.0, 1.0);
        // A "jet"-like ramp: blue → cyan → yellow → red.
        let ch = |c: f32| ((1.5 - (4.0 * t - c).abs()).clamp(0.0, 1.0) * 255.0) as u8;
        out.extend_from_slice(&[ch(3.0), ch(2.0), ch(1.0)]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failed_atomic_write_leaves_no_temp_file() {
        let dir = std::env::temp_dir().join(format!("spinscan-atomic-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        // The target is a non-empty folder: the rename fails after the temp file was written.
        let target = dir.join("manifest.json");
        std::fs::create_dir_all(target.join("inside")).unwrap();
        assert!(write_atomic(&target, b"{}").is_err());
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().map(|e| e.file_name()).collect();
        assert_eq!(left, vec![std::ffi::OsString::from("manifest.json")], "no .tmp file left");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn pfm_and_png_round_trip_signed() {
        let dir = std::env::temp_dir().join(format!("spinscan-io-{}", std::process::id()));
        let map = DisparityMap::from_values(3, 2, vec![-74.5, f32::NAN, -1.25, 3.0, 0.5, -80.0]);
        write_pfm(&dir.join("d.pfm"), &map).unwrap();
        let back = read_pfm(&dir.join("d.pfm")).unwrap();
        assert_eq!(back.get(0, 0), Some(-74.5));
        assert_eq!(back.get(1, 0), None);
        assert_eq!(back.get(2, 1), Some(-80.0));
        write_disparity_png(&dir.join("d.png"), &map).unwrap();
        let png = read_disparity_png(&dir.join("d.png"), -1.0).unwrap();
        assert_eq!(png.get(0, 0), Some(-74.5));
        assert_eq!(png.get(1, 0), None);
        std::fs::remove_dir_all(dir).unwrap();
    }
}
