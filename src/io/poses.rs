//! Files of `spinscan register`: transform JSON (`{"target_from_source": [[4x4]]}`) and
//! Stanford `.conf` poses (`bmesh NAME tx ty tz qx qy qz qw`, placing a scan as
//! `p_world = R(q)ᵀ·p + t`, scalar-last quaternion).

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

use crate::register::{from_rows, to_rows, Rows4};

/// Why a transform or conf file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum PoseFileError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: {what}")]
    Invalid { path: PathBuf, what: String },
    #[error("{path} line {line}: {what}")]
    Line { path: PathBuf, line: usize, what: String },
}

/// Reads `{"target_from_source": [[4x4 row-major]]}` (or a bare 4×4 list).
pub fn read_transform_json(path: &Path) -> Result<Isometry3<f64>, PoseFileError> {
    let text = std::fs::read_to_string(path).map_err(|source| PoseFileError::Io { path: path.to_path_buf(), source })?;
    let invalid = |what: String| PoseFileError::Invalid { path: path.to_path_buf(), what };
    let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| invalid(format!("not JSON: {e}")))?;
    let m = value.get("target_from_source").unwrap_or(&value);
    let rows: Rows4 = serde_json::from_value(m.clone()).map_err(|_| invalid("expected {\"target_from_source\": [[4 numbers] × 4 rows]}".into()))?;
    from_rows(&rows, 1e-4).map_err(|e| invalid(format!("target_from_source: {e}")))
}

/// The JSON form of a transform.
pub fn transform_json(t: &Isometry3<f64>) -> serde_json::Value {
    serde_json::json!({ "target_from_source": to_rows(t) })
}

/// One pose line of a `.conf` file.
#[derive(Debug, Clone, PartialEq)]
pub struct ConfPose {
    pub name: String,
    /// Maps the scan's points into the common ("world") frame.
    pub world_from_scan: Isometry3<f64>,
}

/// A parsed `.conf`: its `camera` line (kept verbatim) and its `bmesh` poses.
#[derive(Debug, Clone, Default)]
pub struct Conf {
    pub camera: Option<String>,
    pub poses: Vec<ConfPose>,
}

impl Conf {
    pub fn get(&self, name: &str) -> Option<&ConfPose> {
        self.poses.iter().find(|p| p.name == name)
    }

    /// Reads a `.conf` file; every `bmesh` line must have a name and seven numbers.
    pub fn read(path: &Path) -> Result<Conf, PoseFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| PoseFileError::Io { path: path.to_path_buf(), source })?;
        let mut conf = Conf::default();
        for (i, raw) in text.lines().enumerate() {
            let line = raw.trim();
            let err = |what: String| PoseFileError::Line { path: path.to_path_buf(), line: i + 1, what };
            let words: Vec<&str> = line.split_whitespace().collect();
            match words.first() {
                None => {}
                Some(w) if w.starts_with('#') => {}
                Some(&"camera") => conf.camera = Some(line.to_string()),
                Some(&"bmesh") => {
                    if words.len() != 9 {
                        return Err(err(format!("expected `bmesh NAME tx ty tz qx qy qz qw`, found {} fields", words.len())));
                    }
                    let mut v = [0.0f64; 7];
                    for (k, w) in words[2..].iter().enumerate() {
                        v[k] = w.parse().ok().filter(|x: &f64| x.is_finite()).ok_or_else(|| err(format!("`{w}` is not a number")))?;
                    }
                    let q = Quaternion::new(v[6], v[3], v[4], v[5]);
                    if q.norm() < 1e-9 {
                        return Err(err("the quaternion is zero".into()));
                    }
                    // p_world = R(q)ᵀ p + t: the rotation is q's conjugate.
                    let rot = UnitQuaternion::from_quaternion(q).inverse();
                    conf.poses.push(ConfPose { name: words[1].to_string(), world_from_scan: Isometry3::from_parts(Translation3::new(v[0], v[1], v[2]), rot) });
                }
                Some(other) => return Err(err(format!("unknown record `{other}`; expected `camera` or `bmesh`"))),
            }
        }
        Ok(conf)
    }

    /// The file's text.
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        if let Some(c) = &self.camera {
            out.push_str(c);
            out.push('\n');
        }
        for p in &self.poses {
            let t = p.world_from_scan.translation.vector;
            let q = p.world_from_scan.rotation.inverse();
            out.push_str(&format!("bmesh {} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n", p.name, t.x, t.y, t.z, q.i, q.j, q.k, q.w));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conf_round_trip_and_errors() {
        let dir = std::env::temp_dir().join(format!("spinscan-conf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.conf");

        std::fs::write(&p, "camera 0 0 0 0 0 0 1\nbmesh bun090.ply 2.20761e-05 -3.34606e-05 -7.20881e-05 0.000335889 -0.708202 0.000602459 0.706009\n").unwrap();
        let conf = Conf::read(&p).unwrap();
        let pose = &conf.get("bun090.ply").unwrap().world_from_scan;
        assert!((pose.rotation.angle().to_degrees() - 90.2).abs() < 0.5);
        let back_path = dir.join("b.conf");
        std::fs::write(&back_path, conf.to_text()).unwrap();
        let back = Conf::read(&back_path).unwrap();
        assert!((back.poses[0].world_from_scan.to_homogeneous() - pose.to_homogeneous()).abs().max() < 1e-8);
        assert_eq!(back.camera.as_deref(), Some("camera 0 0 0 0 0 0 1"));
        std::fs::write(&p, "bmesh x.ply 1 2 3 0 0 zero 1\n").unwrap();
        let e = Conf::read(&p).unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("`zero` is not a number"), "{e}");
        std::fs::write(&p, "{\"target_from_source\": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}").unwrap();
        let e = read_transform_json(&p).unwrap_err().to_string();
        assert!(e.contains("expected {\"target_from_source\""), "{e}");
        std::fs::remove_dir_all(dir).unwrap();
    }
}
