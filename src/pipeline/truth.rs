//! The ground-truth disparities a recording's views are scored against (`replay`'s
//! `gt_*` fields, `bench table1`'s bad2): the simulator's `gt/disparity/` files where it
//! wrote them (ideal rigs only, recording spec), else rendered from `gt/mesh.ply` at the
//! frame's `gt/poses.jsonl` pose through the rig's rectification
//! ([`crate::stereo::truth::render_disparity`]): a realistic rig's recording, or one from
//! another renderer that leaves the files out.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::Isometry3;

use crate::cloud::Mesh;
use crate::io;
use crate::stereo::{DisparityMap, Rectification};

/// Where a frame's ground-truth disparity came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GtSource {
    /// `gt/disparity/NNNNNN.png`.
    Recorded,
    /// Rendered from `gt/mesh.ply` at the frame's `gt/poses.jsonl` pose.
    Rendered,
}

impl GtSource {
    /// The name `report.json` and `bench table1`'s JSON give it.
    pub fn name(self) -> &'static str {
        match self {
            GtSource::Recorded => "recorded",
            GtSource::Rendered => "rendered",
        }
    }
}

/// Where a run's truths came from, by name: the source every frame shares, or `mixed`;
/// `None` for no frame.
pub fn sources_name(sources: impl IntoIterator<Item = GtSource>) -> Option<&'static str> {
    let mut sources = sources.into_iter();
    let first = sources.next()?;
    Some(if sources.all(|s| s == first) { first.name() } else { "mixed" })
}

/// A ground-truth file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    #[error("ground truth: {0}")]
    Recording(#[from] crate::recording::RecordingError),
    #[error("ground truth {path}: {what}")]
    File { path: PathBuf, what: String },
    #[error("ground truth {path} is {got_w}×{got_h}, expected {want_w}×{want_h} (the recording's images)")]
    Size { path: PathBuf, got_w: usize, got_h: usize, want_w: usize, want_h: usize },
}

/// A recording's ground truth for disparities, opened once.
pub struct GtDisparities {
    dir: PathBuf,
    /// `gt/mesh.ply` and `cam_from_obj` per seq, when the recording has both.
    surface: Option<(Arc<Mesh>, HashMap<u64, Isometry3<f64>>)>,
}

impl GtDisparities {
    /// Reads `dir`'s `gt/mesh.ply` and `gt/poses.jsonl` where both exist (a recording with
    /// neither scores nothing, a mesh of points alone is warned about and not used; a
    /// malformed file is an error naming it). The mesh read here is the one a replay
    /// measures its views and model against ([`GtDisparities::mesh`]).
    pub fn open(dir: &Path) -> Result<GtDisparities, TruthError> {
        let mesh_path = dir.join("gt/mesh.ply");
        if !mesh_path.is_file() {
            // Nothing to render; a malformed poses file is still named.
            crate::recording::read_gt_poses(dir)?;
            return Ok(GtDisparities { dir: dir.to_path_buf(), surface: None });
        }
        let surface = match crate::recording::read_gt_cam_from_obj(dir)? {
            Some(list) => {
                let poses: HashMap<u64, Isometry3<f64>> = list.into_iter().collect();
                let mesh = io::ply::read_ply(&mesh_path).map_err(|e| TruthError::File { path: mesh_path.clone(), what: e.to_string() })?;
                if mesh.triangles.is_empty() {
                    // Points alone give no surface to render; the views can still be
                    // scored where `gt/disparity/` exists.
                    tracing::warn!(
                        "{}: no faces, so nothing is measured against it: no ground-truth disparity is rendered from it, nor are views or model scored against the true surface (a surface of triangles is needed)",
                        mesh_path.display()
                    );
                    None
                } else {
                    Some((Arc::new(mesh), poses))
                }
            }
            None => None,
        };
        Ok(GtDisparities { dir: dir.to_path_buf(), surface })
    }

    /// Whether some frame can be scored: `gt/disparity/` or a mesh with poses.
    pub fn any(&self) -> bool {
        self.surface.is_some() || self.dir.join("gt/disparity").is_dir()
    }

    /// `gt/mesh.ply` and `cam_from_obj` per seq, when the recording has both.
    pub fn surface(&self) -> Option<(&Mesh, &HashMap<u64, Isometry3<f64>>)> {
        self.surface.as_ref().map(|(m, p)| (m.as_ref(), p))
    }

    /// `gt/mesh.ply` as read by [`GtDisparities::open`], shared (None: no usable surface).
    pub fn mesh(&self) -> Option<Arc<Mesh>> {
        self.surface.as_ref().map(|(m, _)| Arc::clone(m))
    }

    /// Frame `seq`'s ground truth in `rect`'s rectified left image (signed as the matcher's
    /// maps), with where it came from; `None` where the recording has none for it.
    pub fn get(&self, seq: u64, rect: &Rectification) -> Result<Option<(DisparityMap, GtSource)>, TruthError> {
        let (w, h) = (rect.size.0 as usize, rect.size.1 as usize);
        if let Some(path) = crate::recording::gt_disparity_path(&self.dir, seq) {
            let gt = io::read_disparity_png(&path, rect.disparity_sign as f32).map_err(|e| TruthError::File { path: path.clone(), what: e.to_string() })?;
            if (gt.width, gt.height) != (w, h) {
                return Err(TruthError::Size { path, got_w: gt.width, got_h: gt.height, want_w: w, want_h: h });
            }
            return Ok(Some((gt, GtSource::Recorded)));
        }
        let Some((mesh, poses)) = &self.surface else { return Ok(None) };
        let Some(cam_from_obj) = poses.get(&seq) else { return Ok(None) };
        let gt = crate::stereo::truth::render_disparity(&mesh.cloud.points, &mesh.triangles, cam_from_obj, rect);
        Ok(Some((gt, GtSource::Rendered)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::PointCloud;

    fn recording_with(name: &str, triangles: Vec<[u32; 3]>, poses: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("spinscan-truth-{name}-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("gt")).unwrap();
        let cloud = PointCloud { points: vec![[-50.0, -50.0, 0.0], [50.0, -50.0, 0.0], [0.0, 50.0, 0.0]], colors: vec![[200; 3]; 3], normals: None, rim_px: None };
        io::ply::write_mesh_ply(&dir.join("gt/mesh.ply"), &Mesh { cloud, triangles }).unwrap();
        std::fs::write(dir.join("gt/poses.jsonl"), poses).unwrap();
        dir
    }

    const AHEAD: &str = "{\"seq\": 3, \"cam_from_obj\": [[1,0,0,0],[0,1,0,0],[0,0,1,500],[0,0,0,1]]}\n";

    #[test]
    fn a_frame_is_rendered_from_the_mesh_at_its_pose_and_only_there() {
        let dir = recording_with("ok", vec![[0, 1, 2]], AHEAD);
        let k = nalgebra::Matrix3::new(600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0);
        let cam = crate::calib::Camera { k, distortion: crate::calib::Distortion::none() };
        let calib = crate::calib::StereoCalib { left: cam.clone(), right: cam, r: nalgebra::Matrix3::identity(), t_mm: nalgebra::Vector3::new(-60.0, 0.0, 0.0), image_size: None };
        let rect = Rectification::compute(&calib, (640, 480), 0.0).unwrap();
        let gt = GtDisparities::open(&dir).unwrap();
        assert!(gt.any());
        let (map, source) = gt.get(3, &rect).unwrap().unwrap();
        assert_eq!(source, GtSource::Rendered);
        assert!((map.get(320, 240).unwrap() - 72.0).abs() < 1e-3 && map.valid_count() > 5_000);
        assert!(gt.get(4, &rect).unwrap().is_none(), "no pose, no truth");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn points_alone_render_nothing_and_a_bad_pose_is_named() {
        let dir = recording_with("points", vec![], AHEAD);
        let gt = GtDisparities::open(&dir).unwrap();
        assert!(!gt.any() && gt.surface().is_none());
        std::fs::remove_dir_all(&dir).unwrap();

        let dir = recording_with("bad", vec![[0, 1, 2]], "{\"seq\": 3, \"cam_from_obj\": [[2,0,0,0],[0,1,0,0],[0,0,1,500],[0,0,0,1]]}\n");
        let err = GtDisparities::open(&dir).err().expect("a scaled matrix is no pose").to_string();
        assert!(err.contains("poses.jsonl") && err.contains("seq 3"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
