//! The surface of a finished results folder, re-meshed (`spinscan mesh`): its views fused
//! with the poses in its `poses.jsonl` (fuse/), the mesh written in the format its name
//! asks for. Scans write `mesh.ply` themselves as they finish (results.rs).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::{json, Value};

use crate::cloud::Mesh;
use crate::fuse::{FuseParams, MeshStats, Tsdf};
use crate::io;

/// Why a results folder could not be meshed.
#[derive(Debug, thiserror::Error)]
pub enum MeshError {
    #[error("{path}: {what}")]
    Input { path: PathBuf, what: String },
    #[error("mesh settings: {0}")]
    Params(#[from] crate::fuse::FuseParamsError),
    #[error("{0}")]
    Write(#[from] io::mesh::MeshWriteError),
    #[error("fusion threads: {0}")]
    Threads(String),
}

/// The views of `poses.jsonl` as `(seq, first_from_view)`, in file order.
pub fn read_poses(path: &Path) -> Result<Vec<(u64, nalgebra::Isometry3<f64>)>, MeshError> {
    let bad = |what: String| MeshError::Input { path: path.to_path_buf(), what };
    let text = std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read it ({e}); is this a results folder of a finished scan?")))?;
    let mut poses = Vec::new();
    for (n, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        #[derive(serde::Deserialize)]
        struct Line {
            seq: u64,
            first_from_view: crate::register::Rows4,
        }
        let l: Line = serde_json::from_str(line).map_err(|e| bad(format!("line {}: {e}; expected {{\"seq\": N, \"first_from_view\": [[4 × 4]]}}", n + 1)))?;
        let pose = crate::register::from_rows(&l.first_from_view, 1e-4).map_err(|e| bad(format!("line {} (seq {}): {e}", n + 1, l.seq)))?;
        poses.push((l.seq, pose));
    }
    if poses.is_empty() {
        return Err(bad("no registered views; expected one line per view".into()));
    }
    Ok(poses)
}

/// The most threads [`mesh_results`] takes (as the matcher's `threads`).
pub const MAX_THREADS: usize = 1024;

/// Fuses the views of results folder `dir` on `threads` threads (0: one per core) and
/// writes the mesh to `out` (.ply, .obj or .stl); `progress(done, total)` after every view.
/// Returns the mesh and its figures.
pub fn mesh_results(dir: &Path, params: FuseParams, threads: usize, out: &Path, mut progress: impl FnMut(usize, usize)) -> Result<(Mesh, Value), MeshError> {
    // Checked before the work: an output name that cannot be written fails now.
    io::mesh::MeshFormat::of(out)?;
    let poses = read_poses(&dir.join("poses.jsonl"))?;
    let mut tsdf = Tsdf::new(params)?;
    if threads > MAX_THREADS {
        return Err(MeshError::Threads(format!("{threads} threads asked for; expected 0 (one per core) … {MAX_THREADS}")));
    }
    let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).thread_name(|i| format!("fuse-{i}")).build().map_err(|e| MeshError::Threads(format!("cannot start them: {e}")))?;
    tsdf.set_threads(pool.current_num_threads());
    let (mut read_ms, mut fuse_ms, mut done) = (0.0, 0.0, 0);
    // The views are read a pool's worth at a time, in parallel (a view's PLY takes about as
    // long to read as to fuse), and fused in order; an unreadable one stops the work at it.
    let read = |seq: &u64| {
        let path = dir.join("views").join(format!("{seq:06}.ply"));
        io::ply::read_ply(&path).map_err(|e| MeshError::Input { path: path.clone(), what: format!("cannot read the view: {e}") })
    };
    for chunk in poses.chunks(pool.current_num_threads()) {
        let t = Instant::now();
        let views: Vec<_> = pool.install(|| {
            use rayon::prelude::*;
            chunk.par_iter().map(|(seq, _)| read(seq)).collect()
        });
        read_ms += t.elapsed().as_secs_f64() * 1e3;
        for (view, (_, pose)) in views.into_iter().zip(chunk) {
            let view = view?;
            let t = Instant::now();
            pool.install(|| tsdf.integrate(&view.cloud, pose));
            fuse_ms += t.elapsed().as_secs_f64() * 1e3;
            done += 1;
            progress(done, poses.len());
        }
    }
    let t = Instant::now();
    let (mesh, stats) = pool.install(|| tsdf.mesh());
    let extract_ms = t.elapsed().as_secs_f64() * 1e3;
    io::mesh::write_mesh(out, &mesh)?;
    let mut about = mesh_json(&tsdf, &stats, extract_ms);
    about["read_ms"] = json!(read_ms);
    about["fuse_ms"] = json!(fuse_ms);
    about["threads"] = json!(pool.current_num_threads());
    about["file"] = json!(out.display().to_string());
    Ok((mesh, about))
}

/// A mesh's figures (`MeshStats`) with the field's: views and points fused, settings,
/// blocks, memory, and the extraction's time.
pub(crate) fn mesh_json(tsdf: &Tsdf, stats: &MeshStats, extract_ms: f64) -> Value {
    let mut about = serde_json::to_value(stats).expect("plain numbers");
    let p = tsdf.params();
    let (views, points) = tsdf.integrated();
    about["views"] = json!(views);
    about["points"] = json!(points);
    // The voxel used (the one asked for, exactly as given, unless it was fitted to the
    // views' sampling), what was asked for, and the sampling.
    let fitted = tsdf.voxel_mm() != p.voxel_mm as f32;
    about["voxel_mm"] = if fitted { json!(tsdf.voxel_mm() as f64) } else { json!(p.voxel_mm) };
    about["voxel_asked_mm"] = json!(p.voxel_mm);
    about["view_spacing_mm"] = json!(tsdf.spacing_mm());
    about["voxel_fitted"] = json!(fitted);
    about["truncation_voxels"] = json!(p.truncation_voxels);
    about["rim_weight_px"] = json!(p.rim_weight_px);
    about["rim_weighed_points"] = json!(tsdf.rim_weighed_points());
    about["filled"] = json!(p.fill);
    about["blocks"] = json!(tsdf.blocks());
    about["field_mib"] = json!(tsdf.memory_bytes() as f64 / (1024.0 * 1024.0));
    about["extract_ms"] = json!(extract_ms);
    about["max_field_mib"] = json!(p.max_field_mib);
    about["refused_updates"] = json!(tsdf.refused_updates());
    if tsdf.refused_updates() > 0 {
        about["warning"] = json!(format!(
            "the field reached its memory budget of {} MiB and {} voxel updates were left out: part of the surface is missing; use a larger voxel (now {} mm) or a larger budget",
            p.max_field_mib,
            tsdf.refused_updates(),
            tsdf.voxel_mm()
        ));
    }
    about
}
