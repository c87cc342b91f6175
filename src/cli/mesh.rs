//! `spinscan mesh`: re-meshes a results folder (docs/meshing.md).

use std::path::PathBuf;

use clap::Args;

use super::{input, output, progress, Failure};
use spinscan::fuse::FuseParams;
use spinscan::pipeline::mesh::{mesh_results, MeshError};

#[derive(Args)]
pub struct MeshArgs {
    /// Results folder of a finished scan or replay (its `poses.jsonl` and `views/`).
    pub results: PathBuf,
    /// The mesh to write: `.ply` (binary, vertex colours and normals), `.obj` (vertex colours
    /// and normals) or `.stl` (binary, geometry only).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Voxel side of the fused field, mm (smaller: finer detail, more memory and time). The
    /// field uses a coarser voxel, 1.5 × the views' point spacing, where they are sampled
    /// over 1.5 voxels apart (the mesh would be holes); `--exact-voxel` keeps it as given.
    #[arg(long, default_value_t = FuseParams::default().voxel_mm)]
    pub voxel_mm: f64,
    /// Keep `--voxel-mm` even where the views are sampled coarser than it.
    #[arg(long)]
    pub exact_voxel: bool,
    /// Half-width of the band each point updates around the surface, in voxels.
    #[arg(long, default_value_t = FuseParams::default().truncation_voxels)]
    pub truncation_voxels: f64,
    /// Leave the holes open (the part never seen, e.g. the bottom on the table) instead of
    /// capping them.
    #[arg(long)]
    pub no_fill: bool,
    /// Remove connected pieces with fewer triangles than this share of the largest.
    #[arg(long, default_value_t = FuseParams::default().min_component_share)]
    pub min_component_share: f64,
    /// Points within this many pixels of the object's silhouette in their view weigh
    /// (d / (N + 1))² of the others, d their distance (views written before this was
    /// recorded weigh alike): face-on views decide the surface where they see it, and
    /// the mesh comes closer to it (docs/meshing.md, "The rim weighed down"). 0 weighs every
    /// point alike.
    #[arg(long, value_name = "N", default_value_t = FuseParams::default().rim_weight_px)]
    pub rim_weight_px: f64,
    /// Memory the fused field may take, MiB; past it the surface that needs more is left
    /// out and a warning says so.
    #[arg(long, default_value_t = FuseParams::default().max_field_mib)]
    pub max_field_mib: f64,
    /// Threads the fusion runs on (0: one per core). The mesh is the same whatever the
    /// count.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Also write the mesh's figures (counts, holes filled, times) as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn cmd_mesh(a: MeshArgs) -> Result<(), Failure> {
    let params = FuseParams { voxel_mm: a.voxel_mm, truncation_voxels: a.truncation_voxels, fill: !a.no_fill, min_component_share: a.min_component_share, max_field_mib: a.max_field_mib, fit_to_sampling: !a.exact_voxel, rim_weight_px: a.rim_weight_px, ..FuseParams::default() };
    let result = mesh_results(&a.results, params, a.threads, &a.output, |done, total| progress::show(format!("mesh: fused {done}/{total} views")));
    progress::finish();
    let (_, about) = result.map_err(|e| match e {
        MeshError::Write(_) => output(e),
        _ => input(e),
    })?;
    if let Some(w) = about["warning"].as_str() {
        tracing::warn!("{w}");
    }
    if about["voxel_fitted"] == true {
        tracing::info!("the views' points are {:.2} mm apart: the field used {:.2} mm voxels, not {} mm (--exact-voxel keeps the voxel as given)", about["view_spacing_mm"].as_f64().unwrap_or(0.0), about["voxel_mm"].as_f64().unwrap_or(0.0), a.voxel_mm);
    }
    if let Some(path) = &a.json {
        spinscan::io::write_atomic(path, serde_json::to_string_pretty(&about).expect("plain numbers").as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    println!("{about}");
    Ok(())
}
