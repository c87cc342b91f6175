//! Volumetric fusion of the registered views into one surface (Curless & Levoy 1996, as
//! KinectFusion runs it): a truncated signed distance field on sparse 8 × 8 × 8 voxel blocks,
//! so that memory follows the surface, not the volume; each view's points update the voxels
//! along their viewing rays within the truncation band, weighted by their stereo depth
//! uncertainty; colour is averaged per voxel with the same weights. `mesh.rs` extracts the
//! zero level set as a triangle mesh and cleans it up.
//!
//! A view is integrated the moment its pose is known ([`Tsdf::integrate`]); the mesh is
//! extracted whenever it is asked for ([`Tsdf::mesh`]). The field is additive: integrating
//! the views again with refined poses into a fresh field is how a refinement is applied.

mod mesh;

use std::collections::HashMap;

use nalgebra::Isometry3;

use crate::cloud::PointCloud;
use crate::register::voxel::VoxelHasher;
pub use mesh::{MeshStats, SurfaceMesh};

/// Voxels per block side.
const SIDE: i32 = 8;
const VOXELS: usize = (SIDE * SIDE * SIDE) as usize;

/// Knobs of the fusion; see `docs/meshing.md`.
#[derive(Debug, Clone, PartialEq)]
pub struct FuseParams {
    /// Voxel side, mm.
    pub voxel_mm: f64,
    /// Half-width of the band around the surface that a point updates, in voxels.
    pub truncation_voxels: f64,
    /// Close the holes of the mesh (the part never seen, e.g. the bottom on the table) with
    /// caps (`mesh.rs`); reported as filled.
    pub fill: bool,
    /// Connected pieces of the mesh with fewer triangles than this share of the largest are
    /// removed (floating fragments).
    pub min_component_share: f64,
    /// Depth at which a point's weight is 1, mm: weights fall as (depth_ref / Z)⁴, the
    /// inverse variance of a stereo depth (σ_Z ∝ Z²).
    pub depth_ref_mm: f64,
}

impl Default for FuseParams {
    fn default() -> Self {
        FuseParams { voxel_mm: 1.0, truncation_voxels: 4.0, fill: true, min_component_share: 0.05, depth_ref_mm: 500.0 }
    }
}

/// Fusion settings that cannot work.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FuseParamsError {
    #[error("voxel size {0} mm: expected a positive size of at least 0.05 mm")]
    Voxel(f64),
    #[error("truncation {0} voxels: expected at least 1 voxel")]
    Truncation(f64),
    #[error("component share {0}: expected a share between 0 and 1")]
    Share(f64),
    #[error("reference depth {0} mm: expected a positive depth")]
    DepthRef(f64),
}

impl FuseParams {
    pub fn check(&self) -> Result<(), FuseParamsError> {
        if !(self.voxel_mm >= 0.05 && self.voxel_mm.is_finite()) {
            return Err(FuseParamsError::Voxel(self.voxel_mm));
        }
        if !(self.truncation_voxels >= 1.0 && self.truncation_voxels.is_finite()) {
            return Err(FuseParamsError::Truncation(self.truncation_voxels));
        }
        if !(0.0..=1.0).contains(&self.min_component_share) {
            return Err(FuseParamsError::Share(self.min_component_share));
        }
        if !(self.depth_ref_mm > 0.0 && self.depth_ref_mm.is_finite()) {
            return Err(FuseParamsError::DepthRef(self.depth_ref_mm));
        }
        Ok(())
    }
}

/// One block of voxels: the signed distance (mm, positive in front of the surface), the
/// summed weight (0: never seen) and the weighted colour sums, `x` fastest.
#[derive(Clone)]
struct Block {
    sdf: [f32; VOXELS],
    weight: [f32; VOXELS],
    rgb: [[f32; 3]; VOXELS],
}

/// One voxel as the extraction reads it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Voxel {
    pub(crate) sdf: f32,
    pub(crate) rgb: [f32; 3],
}

/// The truncated signed distance field of one scan, in the frame of its poses (the first
/// view's LEFT raw camera frame for spinscan's results).
pub struct Tsdf {
    params: FuseParams,
    voxel: f32,
    trunc: f32,
    index: HashMap<[i32; 3], u32, std::hash::BuildHasherDefault<VoxelHasher>>,
    blocks: Vec<Block>,
    views: usize,
    points: usize,
}

impl Tsdf {
    /// An empty field; `params` must pass [`FuseParams::check`].
    pub fn new(params: FuseParams) -> Result<Tsdf, FuseParamsError> {
        params.check()?;
        let voxel = params.voxel_mm as f32;
        let trunc = (params.truncation_voxels * params.voxel_mm) as f32;
        Ok(Tsdf { params, voxel, trunc, index: HashMap::default(), blocks: Vec::new(), views: 0, points: 0 })
    }

    pub fn params(&self) -> &FuseParams {
        &self.params
    }

    /// Views and points integrated so far.
    pub fn integrated(&self) -> (usize, usize) {
        (self.views, self.points)
    }

    /// Allocated blocks (each 8³ voxels).
    pub fn blocks(&self) -> usize {
        self.blocks.len()
    }

    /// Bytes held by the blocks and their index.
    pub fn memory_bytes(&self) -> usize {
        self.blocks.capacity() * std::mem::size_of::<Block>() + self.index.capacity() * (std::mem::size_of::<[i32; 3]>() + 4 + 8)
    }

    /// Integrates one view: `cloud` in the view's own camera frame (camera centre at the
    /// origin, +Z forward), placed by `world_from_view`. Each point updates the voxels its
    /// viewing ray crosses within the truncation band: signed distance along the ray,
    /// weight (depth_ref / Z)⁴, colour.
    pub fn integrate(&mut self, cloud: &PointCloud, world_from_view: &Isometry3<f64>) {
        let rot = world_from_view.rotation.to_rotation_matrix().into_inner().cast::<f32>();
        let t = world_from_view.translation.vector.cast::<f32>();
        let (voxel, inv_voxel, trunc) = (self.voxel, 1.0 / self.voxel, self.trunc);
        let steps = (trunc * inv_voxel).ceil() as i32;
        let depth_ref = self.params.depth_ref_mm as f32;
        // The block of the last voxel touched: consecutive samples of a ray mostly share it.
        let mut last: Option<([i32; 3], usize)> = None;
        let mut used = 0;
        for (i, p) in cloud.points.iter().enumerate() {
            let z = p[2];
            if !(z > 0.0) || !p.iter().all(|v| v.is_finite()) {
                continue;
            }
            used += 1;
            let w = (depth_ref / z).powi(4);
            let rgb = cloud.colors.get(i).map_or([200.0; 3], |c| [c[0] as f32, c[1] as f32, c[2] as f32]);
            let pv = nalgebra::Vector3::new(p[0], p[1], p[2]);
            let len = pv.norm();
            // The point and its ray in the world.
            let pw = rot * pv + t;
            let dir = rot * (pv / len);
            for s in -steps..=steps {
                let q = pw + dir * (s as f32 * voxel);
                let g = [(q.x * inv_voxel).floor() as i32, (q.y * inv_voxel).floor() as i32, (q.z * inv_voxel).floor() as i32];
                let centre = nalgebra::Vector3::new((g[0] as f32 + 0.5) * voxel, (g[1] as f32 + 0.5) * voxel, (g[2] as f32 + 0.5) * voxel);
                // Distance from the voxel to the surface along the ray: positive in front.
                let sdf = (pw - centre).dot(&dir);
                if sdf < -trunc {
                    continue;
                }
                let sdf = sdf.min(trunc);
                let key = [g[0].div_euclid(SIDE), g[1].div_euclid(SIDE), g[2].div_euclid(SIDE)];
                let b = match last {
                    Some((k, b)) if k == key => b,
                    _ => {
                        let b = self.block_of(key);
                        last = Some((key, b));
                        b
                    }
                };
                let v = local(g);
                let block = &mut self.blocks[b];
                let w0 = block.weight[v];
                let w1 = w0 + w;
                block.sdf[v] = (block.sdf[v] * w0 + sdf * w) / w1;
                block.weight[v] = w1;
                for c in 0..3 {
                    block.rgb[v][c] += rgb[c] * w;
                }
            }
        }
        self.views += 1;
        self.points += used;
    }

    /// The index of block `key`, allocated (unseen) when new.
    fn block_of(&mut self, key: [i32; 3]) -> usize {
        let next = self.blocks.len();
        let b = *self.index.entry(key).or_insert(next as u32) as usize;
        if b == next {
            self.blocks.push(Block { sdf: [0.0; VOXELS], weight: [0.0; VOXELS], rgb: [[0.0; 3]; VOXELS] });
        }
        b
    }

    /// The voxel at grid index `g` (None: never seen).
    pub(crate) fn voxel(&self, g: [i32; 3]) -> Option<Voxel> {
        let key = [g[0].div_euclid(SIDE), g[1].div_euclid(SIDE), g[2].div_euclid(SIDE)];
        let b = &self.blocks[*self.index.get(&key)? as usize];
        let v = local(g);
        (b.weight[v] > 0.0).then(|| Voxel { sdf: b.sdf[v], rgb: b.rgb[v].map(|c| c / b.weight[v]) })
    }

    /// Every allocated block's key, in allocation order.
    pub(crate) fn block_keys(&self) -> Vec<[i32; 3]> {
        let mut keys = vec![[0; 3]; self.blocks.len()];
        for (k, &b) in &self.index {
            keys[b as usize] = *k;
        }
        keys
    }

    pub(crate) fn voxel_mm(&self) -> f32 {
        self.voxel
    }

    /// The zero level set as a cleaned triangle mesh (`mesh.rs`).
    pub fn mesh(&self) -> (SurfaceMesh, MeshStats) {
        mesh::extract(self)
    }
}

/// A voxel's index inside its block.
fn local(g: [i32; 3]) -> usize {
    let (x, y, z) = (g[0].rem_euclid(SIDE), g[1].rem_euclid(SIDE), g[2].rem_euclid(SIDE));
    ((z * SIDE + y) * SIDE + x) as usize
}

/// Voxels per block side, for the extraction.
pub(crate) const BLOCK_SIDE: i32 = SIDE;
