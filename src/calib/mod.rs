//! Stereo calibration as OpenCV writes it.
//!
//! Two layouts are accepted (`--calib PATH` takes a file or a folder holding either):
//! - one `calib.yaml` with `M1 D1 M2 D2 R T` (+ optional `image_width`, `image_height`);
//! - the pair `intrinsics.yml` (`M1 D1 M2 D2`) + `extrinsics.yml` (`R T`, the rest ignored)
//!   from OpenCV's `stereo_calib` sample.
//!
//! Convention: `X_right = R · X_left + T`, T in millimetres (the units of the calibration
//! target, which labs measure in mm).

pub mod board;
pub mod distortion;
pub mod filestorage;
mod grid;
pub mod job;
pub mod lm;
pub mod solve;
pub mod subpix;
pub mod turntable;

use std::path::{Path, PathBuf};

use nalgebra::{DMatrix, Matrix3, Vector3};

pub use distortion::Distortion;
use filestorage::{Document, FileStorageError};

/// A pinhole camera: intrinsic matrix and lens distortion.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// `[fx 0 cx; 0 fy cy; 0 0 1]`, pixels, pixel centres at integers (OpenCV).
    pub k: Matrix3<f64>,
    pub distortion: Distortion,
}

/// A calibrated stereo rig.
#[derive(Debug, Clone, PartialEq)]
pub struct StereoCalib {
    pub left: Camera,
    pub right: Camera,
    /// Rotation of `right_from_left`: `X_right = r · X_left + t_mm`.
    pub r: Matrix3<f64>,
    /// Translation of `right_from_left`, millimetres.
    pub t_mm: Vector3<f64>,
    /// `(width, height)` in pixels when the file records it.
    pub image_size: Option<(u32, u32)>,
}

/// Why a calibration could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum CalibError {
    #[error("cannot read calibration {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {source}")]
    Format { path: PathBuf, source: FileStorageError },
    #[error("{path}: key `{key}` is missing (expected {expected})")]
    Missing { path: PathBuf, key: String, expected: String },
    #[error("{path}: key `{key}` {what}")]
    Invalid { path: PathBuf, key: String, what: String },
    #[error("{path} holds no calibration: expected calib.yaml (or .yml/.xml-free YAML with M1 D1 M2 D2 R T) or intrinsics.yml + extrinsics.yml")]
    NotFound { path: PathBuf },
}

impl StereoCalib {
    /// Loads a calibration from a file or a folder (see the module docs for the layouts).
    pub fn load(path: &Path) -> Result<StereoCalib, CalibError> {
        if path.is_dir() {
            for name in ["calib.yaml", "calib.yml"] {
                let p = path.join(name);
                if p.is_file() {
                    return Self::load_file(&p);
                }
            }
            let intr = ["intrinsics.yml", "intrinsics.yaml"].map(|n| path.join(n)).into_iter().find(|p| p.is_file());
            let extr = ["extrinsics.yml", "extrinsics.yaml"].map(|n| path.join(n)).into_iter().find(|p| p.is_file());
            return match (intr, extr) {
                (Some(i), Some(e)) => Self::load_pair(&i, &e),
                _ => Err(CalibError::NotFound { path: path.to_path_buf() }),
            };
        }
        Self::load_file(path)
    }

    /// Loads a single `calib.yaml`. If it is an `intrinsics.yml` with an `extrinsics.yml`
    /// beside it, the pair is read.
    pub fn load_file(path: &Path) -> Result<StereoCalib, CalibError> {
        let doc = read_doc(path)?;
        if doc.get("R").is_none() && doc.get("M1").is_some() {
            if let Some(dir) = path.parent() {
                for name in ["extrinsics.yml", "extrinsics.yaml"] {
                    let e = dir.join(name);
                    if e.is_file() {
                        return Self::load_pair(path, &e);
                    }
                }
            }
        }
        Self::from_docs((&doc, path), (&doc, path))
    }

    /// A calibration from the text of one `calib.yaml` (OpenCV FileStorage); `path` names
    /// the source in errors.
    pub fn parse(text: &str, path: &Path) -> Result<StereoCalib, CalibError> {
        let doc = Document::parse(text).map_err(|source| CalibError::Format { path: path.to_path_buf(), source })?;
        Self::from_docs((&doc, path), (&doc, path))
    }

    /// Loads `intrinsics.yml` + `extrinsics.yml`.
    pub fn load_pair(intrinsics: &Path, extrinsics: &Path) -> Result<StereoCalib, CalibError> {
        let i = read_doc(intrinsics)?;
        let e = read_doc(extrinsics)?;
        Self::from_docs((&i, intrinsics), (&e, extrinsics))
    }

    fn from_docs(intr: (&Document, &Path), extr: (&Document, &Path)) -> Result<StereoCalib, CalibError> {
        let left = read_camera(intr, "M1", "D1")?;
        let right = read_camera(intr, "M2", "D2")?;
        let r = read_fixed::<3, 3>(extr, "R", "a 3×3 rotation matrix")?;
        let det = r.determinant();
        let orth = (r.transpose() * r - Matrix3::identity()).norm();
        if (det - 1.0).abs() > 1e-6 || orth > 1e-6 {
            return Err(invalid(extr.1, "R", format!("is not a rotation (det {det:.6}, ‖RᵀR − I‖ {orth:.2e})")));
        }
        let t = read_matrix(extr, "T", "a 3-vector translation in mm")?;
        if t.len() != 3 {
            return Err(invalid(extr.1, "T", format!("must have 3 elements, has {}", t.len())));
        }
        let t_mm = Vector3::new(t[0], t[1], t[2]);
        if t_mm.norm() == 0.0 {
            return Err(invalid(extr.1, "T", "is zero: the two cameras cannot share a centre".into()));
        }
        let dim = |key: &str| -> Result<Option<u32>, CalibError> {
            match intr.0.get(key).or_else(|| extr.0.get(key)) {
                None => Ok(None),
                Some(e) => {
                    let v = e.as_f64(key).map_err(|source| CalibError::Format { path: intr.1.to_path_buf(), source })?;
                    if v < 1.0 || v.fract() != 0.0 || v > 65535.0 {
                        return Err(invalid(intr.1, key, format!("must be a positive whole number of pixels, found {v}")));
                    }
                    Ok(Some(v as u32))
                }
            }
        };
        let image_size = match (dim("image_width")?, dim("image_height")?) {
            (Some(w), Some(h)) => Some((w, h)),
            _ => None,
        };
        Ok(StereoCalib { left, right, r, t_mm, image_size })
    }

    /// Writes the calibration as an OpenCV 4-style `calib.yaml` that this module (and OpenCV)
    /// read back.
    pub fn to_yaml(&self) -> String {
        let mut s = String::from("%YAML:1.0\n---\n");
        if let Some((w, h)) = self.image_size {
            s += &format!("image_width: {w}\nimage_height: {h}\n");
        }
        let mat = |name: &str, rows: usize, cols: usize, data: Vec<f64>| {
            let data: Vec<String> = data.iter().map(|v| format!("{v:.17e}")).collect();
            format!("{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n   data: [ {} ]\n", data.join(", "))
        };
        let m3 = |m: &Matrix3<f64>| (0..3).flat_map(|r| (0..3).map(move |c| m[(r, c)])).collect::<Vec<_>>();
        s += &mat("M1", 3, 3, m3(&self.left.k));
        let d1 = self.left.distortion.coeffs().to_vec();
        s += &mat("D1", 1, d1.len(), d1);
        s += &mat("M2", 3, 3, m3(&self.right.k));
        let d2 = self.right.distortion.coeffs().to_vec();
        s += &mat("D2", 1, d2.len(), d2);
        s += &mat("R", 3, 3, m3(&self.r));
        s += &mat("T", 3, 1, self.t_mm.iter().copied().collect());
        s
    }
}

fn read_doc(path: &Path) -> Result<Document, CalibError> {
    let text = std::fs::read_to_string(path).map_err(|source| CalibError::Io { path: path.to_path_buf(), source })?;
    Document::parse(&text).map_err(|source| CalibError::Format { path: path.to_path_buf(), source })
}

fn invalid(path: &Path, key: &str, what: String) -> CalibError {
    CalibError::Invalid { path: path.to_path_buf(), key: key.to_string(), what }
}

fn read_matrix((doc, path): (&Document, &Path), key: &str, expected: &str) -> Result<DMatrix<f64>, CalibError> {
    let entry = doc.get(key).ok_or_else(|| CalibError::Missing {
        path: path.to_path_buf(),
        key: key.to_string(),
        expected: format!("{expected}, as an !!opencv-matrix"),
    })?;
    let m = entry.as_matrix(key).map_err(|source| CalibError::Format { path: path.to_path_buf(), source })?;
    if m.iter().any(|v| !v.is_finite()) {
        return Err(invalid(path, key, "holds a non-finite number".into()));
    }
    Ok(m)
}

fn read_fixed<const R: usize, const C: usize>(
    src: (&Document, &Path),
    key: &str,
    expected: &str,
) -> Result<nalgebra::SMatrix<f64, R, C>, CalibError> {
    let m = read_matrix(src, key, expected)?;
    if m.nrows() != R || m.ncols() != C {
        return Err(invalid(src.1, key, format!("must be {R}×{C} ({expected}), found {}×{}", m.nrows(), m.ncols())));
    }
    Ok(nalgebra::SMatrix::<f64, R, C>::from_fn(|r, c| m[(r, c)]))
}

fn read_camera(src: (&Document, &Path), m_key: &str, d_key: &str) -> Result<Camera, CalibError> {
    let k = read_fixed::<3, 3>(src, m_key, "a 3×3 camera matrix")?;
    if k[(0, 0)] <= 0.0 || k[(1, 1)] <= 0.0 || k[(2, 2)] != 1.0 || k[(1, 0)] != 0.0 || k[(2, 0)] != 0.0 || k[(2, 1)] != 0.0 {
        return Err(invalid(src.1, m_key, "must be [fx 0 cx; 0 fy cy; 0 0 1] with fx, fy > 0".into()));
    }
    let d = read_matrix(src, d_key, "a distortion vector of 4, 5, 8, 12 or 14 coefficients")?;
    if d.nrows() != 1 && d.ncols() != 1 {
        return Err(invalid(src.1, d_key, format!("must be 1×N or N×1, found {}×{}", d.nrows(), d.ncols())));
    }
    let coeffs: Vec<f64> = d.iter().copied().collect();
    let distortion = Distortion::new(&coeffs).ok_or_else(|| {
        invalid(src.1, d_key, format!("has {} coefficients; expected 4, 5, 8, 12 or 14", coeffs.len()))
    })?;
    Ok(Camera { k, distortion })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ideal() -> StereoCalib {
        StereoCalib {
            left: Camera { k: Matrix3::new(700.0, 0.0, 319.5, 0.0, 700.0, 239.5, 0.0, 0.0, 1.0), distortion: Distortion::none() },
            right: Camera {
                k: Matrix3::new(700.0, 0.0, 319.5, 0.0, 700.0, 239.5, 0.0, 0.0, 1.0),
                distortion: Distortion::new(&[-0.1, 0.01, 0.0, 0.0, 0.001]).unwrap(),
            },
            r: Matrix3::identity(),
            t_mm: Vector3::new(-60.0, 0.0, 0.0),
            image_size: Some((640, 480)),
        }
    }

    #[test]
    fn yaml_round_trip() {
        let dir = std::env::temp_dir().join(format!("spinscan-calib-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let calib = ideal();
        std::fs::write(dir.join("calib.yaml"), calib.to_yaml()).unwrap();
        let back = StereoCalib::load(&dir).unwrap();
        assert_eq!(back, calib);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn missing_key_is_named() {
        let dir = std::env::temp_dir().join(format!("spinscan-calib-missing-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let text = ideal().to_yaml().replace("T: !!opencv", "X: !!opencv");
        std::fs::write(dir.join("calib.yaml"), text).unwrap();
        let err = StereoCalib::load(&dir).unwrap_err().to_string();
        assert!(err.contains("`T` is missing") && err.contains("calib.yaml"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
