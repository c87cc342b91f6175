//! Triangle meshes out: binary PLY (vertex colours and normals), Wavefront OBJ (vertex
//! colours as the `v x y z r g b` extension that MeshLab, Open3D and CloudCompare read, and
//! `vn` normals) and binary STL (geometry only: STL has no colour). Chosen by extension.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::cloud::Mesh;

/// A mesh file format spinscan writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    Ply,
    Obj,
    Stl,
}

/// Why a mesh could not be written.
#[derive(Debug, thiserror::Error)]
pub enum MeshWriteError {
    #[error("{0}: unknown mesh format; expected a name ending in .ply, .obj or .stl")]
    Format(PathBuf),
    #[error("cannot write {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("cannot write {path}: {what}")]
    Ply { path: PathBuf, what: String },
}

impl MeshFormat {
    /// The format named by a file's extension (case-insensitive).
    pub fn of(path: &Path) -> Result<MeshFormat, MeshWriteError> {
        match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("ply") => Ok(MeshFormat::Ply),
            Some("obj") => Ok(MeshFormat::Obj),
            Some("stl") => Ok(MeshFormat::Stl),
            _ => Err(MeshWriteError::Format(path.to_path_buf())),
        }
    }
}

/// Writes `mesh` in the format its extension names (atomically: a reader never sees half a
/// file).
pub fn write_mesh(path: &Path, mesh: &Mesh) -> Result<(), MeshWriteError> {
    let bytes = match MeshFormat::of(path)? {
        MeshFormat::Ply => return super::ply::write_mesh_ply(path, mesh).map_err(|e| MeshWriteError::Ply { path: path.to_path_buf(), what: e.to_string() }),
        MeshFormat::Obj => obj_bytes(mesh),
        MeshFormat::Stl => stl_bytes(mesh),
    };
    super::write_atomic(path, &bytes).map_err(|source| MeshWriteError::Io { path: path.to_path_buf(), source })
}

fn obj_bytes(mesh: &Mesh) -> Vec<u8> {
    let c = &mesh.cloud;
    let mut out = Vec::with_capacity(c.len() * 80 + mesh.triangles.len() * 40);
    writeln!(out, "# written by spinscan {}: millimetres, vertex colours in 0…1 after x y z", env!("CARGO_PKG_VERSION")).unwrap();
    for (i, p) in c.points.iter().enumerate() {
        let rgb = c.colors.get(i).copied().unwrap_or([200, 200, 200]);
        writeln!(out, "v {} {} {} {:.4} {:.4} {:.4}", p[0], p[1], p[2], rgb[0] as f32 / 255.0, rgb[1] as f32 / 255.0, rgb[2] as f32 / 255.0).unwrap();
    }
    let normals = c.normals.as_ref().filter(|n| n.len() == c.len());
    if let Some(ns) = normals {
        for n in ns {
            writeln!(out, "vn {} {} {}", n[0], n[1], n[2]).unwrap();
        }
    }
    for t in &mesh.triangles {
        let [a, b, d] = t.map(|v| v + 1);
        if normals.is_some() {
            writeln!(out, "f {a}//{a} {b}//{b} {d}//{d}").unwrap();
        } else {
            writeln!(out, "f {a} {b} {d}").unwrap();
        }
    }
    out
}

fn stl_bytes(mesh: &Mesh) -> Vec<u8> {
    let mut out = Vec::with_capacity(84 + mesh.triangles.len() * 50);
    let mut header = [b' '; 80];
    let text = format!("binary STL written by spinscan {}, millimetres", env!("CARGO_PKG_VERSION"));
    header[..text.len().min(80)].copy_from_slice(&text.as_bytes()[..text.len().min(80)]);
    out.extend_from_slice(&header);
    out.extend_from_slice(&(mesh.triangles.len() as u32).to_le_bytes());
    let p = &mesh.cloud.points;
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|v| p[v as usize]);
        let (u, v) = ([b[0] - a[0], b[1] - a[1], b[2] - a[2]], [c[0] - a[0], c[1] - a[1], c[2] - a[2]]);
        let n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
        let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let n = if l > 0.0 { n.map(|x| x / l) } else { [0.0; 3] };
        for v in [n, a, b, c] {
            for x in v {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        out.extend_from_slice(&0u16.to_le_bytes());
    }
    out
}
