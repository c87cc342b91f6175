//! The ground-truth disparities a recording's views are scored against (`replay`'s
//! `gt_*` fields, `bench table1`'s bad2): the simulator's `gt/disparity/` files where it
//! wrote them (ideal rigs only, recording spec), else rendered from `gt/mesh.ply` at the
//! frame's `gt/poses.jsonl` pose through the rig's rectification
//! ([`crate::stereo::truth::render_disparity`]): a realistic rig's recording, or one from
//! another renderer that leaves the files out.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

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
    surface: Option<(Mesh, HashMap<u64, Isometry3<f64>>)>,
}

impl GtDisparities {
    /// Reads `dir`'s `gt/mesh.ply` and `gt/poses.jsonl` where both exist (a recording with
    /// neither scores nothing; a malformed one is an error naming the file).
    pub fn open(dir: &Path) -> Result<GtDisparities, TruthError> {
        let poses_path = dir.join("gt/poses.jsonl");
        let mesh_path = dir.join("gt/mesh.ply");
        let surface = match crate::recording::read_gt_poses(dir)? {
            Some(list) if mesh_path.is_file() => {
                let mut poses = HashMap::new();
                for (seq, rows) in list {
                    let cam_from_obj = crate::register::from_rows(&rows, 1e-4).map_err(|e| TruthError::File { path: poses_path.clone(), what: format!("seq {seq}: cam_from_obj: {e}") })?;
                    poses.insert(seq, cam_from_obj);
                }
                let mesh = io::ply::read_ply(&mesh_path).map_err(|e| TruthError::File { path: mesh_path.clone(), what: e.to_string() })?;
                if let Some(i) = mesh.triangles.iter().flatten().find(|&&i| i as usize >= mesh.cloud.points.len()) {
                    return Err(TruthError::File { path: mesh_path, what: format!("a face refers to vertex {i}, but the mesh has {} vertices", mesh.cloud.points.len()) });
                }
                if mesh.triangles.is_empty() {
                    return Err(TruthError::File { path: mesh_path, what: "holds no faces; a surface (triangles) is needed to score disparities".into() });
                }
                Some((mesh, poses))
            }
            _ => None,
        };
        Ok(GtDisparities { dir: dir.to_path_buf(), surface })
    }

    /// Whether some frame can be scored: `gt/disparity/` or a mesh with poses.
    pub fn any(&self) -> bool {
        self.surface.is_some() || self.dir.join("gt/disparity").is_dir()
    }

    /// `gt/mesh.ply` and `cam_from_obj` per seq, when the recording has both.
    pub fn surface(&self) -> Option<(&Mesh, &HashMap<u64, Isometry3<f64>>)> {
        self.surface.as_ref().map(|(m, p)| (m, p))
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
