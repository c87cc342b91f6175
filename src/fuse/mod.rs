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

mod integrate;
mod march;
mod mesh;

use std::collections::HashMap;

use crate::cloud::PointCloud;
use crate::register::voxel::VoxelHasher;
pub use mesh::{MeshStats, SurfaceMesh};

/// Valid points a view needs for its spacing to be measured (and the voxel fitted to it).
const MIN_FIT_POINTS: usize = 16;

/// Whether a view's point can be fused: finite, in front of the camera.
#[inline(always)]
fn usable(p: &[f32; 3]) -> bool {
    p[2] > 0.0 && p.iter().all(|v| v.is_finite())
}

/// A point's share of weight at `d` pixels inside the silhouette: `(d · scale)²` up to 1,
/// `scale` = 1 / (`rim_weight_px` + 1). A point on the silhouette itself (0: a mask that let
/// a background pixel's match through) weighs as one at half a pixel, never nothing.
#[inline]
fn rim_weight(d: u8, scale: f32) -> f32 {
    let s = (d as f32).max(0.5) * scale;
    (s * s).min(1.0)
}

/// Voxels per block side.
pub(crate) const SIDE: i32 = 8;
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
    /// Memory the field may take, MiB: past it no new block is allocated, and the
    /// surface that would have needed one is left out (counted, and reported) rather than
    /// the process running out of memory (a tiny voxel on a large object).
    pub max_field_mib: f64,
    /// Let the voxel grow to [`SAMPLING_VOXELS`] × the first view's point spacing where the
    /// spacing is over [`FIT_ABOVE_VOXELS`] × `voxel_mm`: each point updates one column of
    /// voxels, so at a voxel much finer than the sampling most cubes have a corner no ray
    /// crossed, and the mesh is holes, or from a few views nothing (a low camera
    /// resolution, a large object). False keeps `voxel_mm` exactly.
    pub fit_to_sampling: bool,
    /// Points whose pixel lay within this many pixels of the object's silhouette in their
    /// view ([`crate::cloud::PointCloud::rim_px`]) weigh `(d / (rim_weight_px + 1))²` of the
    /// others, `d` their distance: matched by windows that reach across the outline, and
    /// seen at grazing angles, they are a view's least accurate, and where another view sees
    /// the same surface face-on it decides it. Where no view sees a part but near its
    /// silhouette, those points still make it (only the weights' ratios count). 0 weighs
    /// every point alike, as clouds without the distances are (docs/meshing.md, "The rim
    /// weighed down").
    pub rim_weight_px: f64,
}

/// The voxel, in point spacings (median nearest-neighbour distance of the first view), that
/// the field grows to when the views are sampled much coarser than the voxel asked for
/// ([`FuseParams::fit_to_sampling`], [`FIT_ABOVE_VOXELS`]). 1 is the least at which every
/// voxel column of a surface facing the camera holds a point, on a lattice aligned with the
/// grid; the nearest neighbour is a lattice's shorter side, and the lattice is turned: a
/// sphere sampled 2.6 mm apart meshes with 6 caps over 5400 mm² at 1 spacing, 2 over the
/// grazing poles' 680 mm² at 1.5 (`fuse/mesh.rs` tests).
pub const SAMPLING_VOXELS: f64 = 1.5;

/// The first view's point spacing, in voxels asked for, past which the voxel is fitted to
/// it. Up to it, the overlap of the views (a turn of tens of them) covers the columns one
/// view leaves empty, and the voxel asked for keeps its detail: 45 views of the torus at
/// 320 × 240 (1.23 mm apart, 1 mm voxels) keep 92 % completeness against 89 % fitted to
/// 1.85 mm. Past it, a few views mesh to little or nothing (the daemon's 160 × 120 lab,
/// 2.5 mm apart: its live preview of the first views was empty).
pub const FIT_ABOVE_VOXELS: f64 = 1.5;

impl Default for FuseParams {
    fn default() -> Self {
        FuseParams { voxel_mm: 1.0, truncation_voxels: 4.0, fill: true, min_component_share: 0.05, depth_ref_mm: 500.0, max_field_mib: 1024.0, fit_to_sampling: true, rim_weight_px: 10.0 }
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
    #[error("field memory budget {0} MiB: expected at least 1 MiB")]
    Budget(f64),
    #[error("rim weight width {0} px: expected 0 (off) to 254 pixels")]
    RimWeight(f64),
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
        if !(self.max_field_mib >= 1.0) {
            return Err(FuseParamsError::Budget(self.max_field_mib));
        }
        if !(0.0..=254.0).contains(&self.rim_weight_px) {
            return Err(FuseParamsError::RimWeight(self.rim_weight_px));
        }
        Ok(())
    }
}

/// One voxel's sums: the weighted signed distance (mm, positive in front of the surface),
/// the weight (0: never seen) and the weighted colour. Sums, not averages, so that an update
/// needs no division; the five live together, so that it touches one cache line.
#[derive(Clone, Copy, Default)]
struct Sums {
    sdf: f32,
    weight: f32,
    rgb: [f32; 3],
}

/// One block of voxels, `x` fastest.
#[derive(Clone)]
struct Block {
    voxels: [Sums; VOXELS],
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
    index: BlockIndex,
    blocks: Vec<Block>,
    /// Blocks the memory budget allows.
    max_blocks: usize,
    views: usize,
    points: usize,
    /// Voxel updates refused because the budget was spent.
    refused: u64,
    /// Points weighed down for lying near their view's silhouette
    /// ([`FuseParams::rim_weight_px`]).
    rim_weighed: usize,
    /// The first view's point spacing, mm, once a view with points came (the voxel is
    /// fitted to it then, [`FuseParams::fit_to_sampling`]).
    spacing: Option<f64>,
    /// Parts a view's integration is split into, run on the current rayon pool (1: all on
    /// the calling thread); the field is the same for any count (`integrate.rs`).
    threads: usize,
    /// The parts' buffers, kept from view to view.
    parts: Vec<integrate::Part>,
    /// The sort's scratch, kept from view to view.
    sort_buffer: Vec<(u64, u32)>,
}

impl Tsdf {
    /// An empty field; `params` must pass [`FuseParams::check`].
    pub fn new(params: FuseParams) -> Result<Tsdf, FuseParamsError> {
        params.check()?;
        let voxel = params.voxel_mm as f32;
        let trunc = (params.truncation_voxels * params.voxel_mm) as f32;
        let max_blocks = (params.max_field_mib * 1024.0 * 1024.0 / std::mem::size_of::<Block>() as f64) as usize;
        Ok(Tsdf { params, voxel, trunc, index: HashMap::default(), blocks: Vec::new(), max_blocks, views: 0, points: 0, refused: 0, rim_weighed: 0, spacing: None, threads: 1, parts: Vec::new(), sort_buffer: Vec::new() })
    }

    /// Splits each view's integration into `threads` parts run on the current rayon pool
    /// (0: as many as the pool has threads; 1, the default: the calling thread alone). The
    /// field, and so the mesh, is the same bit for bit whatever the count.
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = if threads == 0 { rayon::current_num_threads() } else { threads };
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

    /// Voxel updates left out because the field had spent its memory budget (0: none).
    pub fn refused_updates(&self) -> u64 {
        self.refused
    }

    /// Points integrated so far with less than full weight for lying within
    /// [`FuseParams::rim_weight_px`] of their view's silhouette.
    pub fn rim_weighed_points(&self) -> usize {
        self.rim_weighed
    }

    /// Bytes held by the blocks and their index.
    pub fn memory_bytes(&self) -> usize {
        self.blocks.capacity() * std::mem::size_of::<Block>() + self.index.capacity() * (std::mem::size_of::<[i32; 3]>() + 4 + 8)
    }

    /// Measures the first view's point spacing (it needs [`MIN_FIT_POINTS`] valid points;
    /// with fewer, the next view's, as long as nothing was fused yet) and, with
    /// `fit_to_sampling`, grows the voxel and the truncation band to [`SAMPLING_VOXELS`]
    /// spacings where the spacing is over [`FIT_ABOVE_VOXELS`] voxels. Called only while the
    /// field is empty, so that every voxel has one size.
    fn fit_voxel(&mut self, cloud: &PointCloud) {
        let points: Vec<[f32; 3]> = cloud.points.iter().filter(|p| usable(p)).copied().collect();
        if points.len() < MIN_FIT_POINTS {
            return;
        }
        let Ok(tree) = crate::register::KdTree::build(points, "view") else { return };
        let spacing = tree.median_spacing();
        self.spacing = Some(spacing);
        let fitted = SAMPLING_VOXELS * spacing;
        if self.params.fit_to_sampling && spacing > FIT_ABOVE_VOXELS * self.params.voxel_mm {
            self.voxel = fitted as f32;
            self.trunc = (self.params.truncation_voxels * fitted) as f32;
        }
    }

    /// The first view's point spacing, mm (None before a view with points came).
    pub fn spacing_mm(&self) -> Option<f64> {
        self.spacing
    }

    /// The averages of block `key`'s voxels, and of the first layer of voxels past its high
    /// faces (from the neighbouring blocks): a 9 × 9 × 9 neighbourhood, `x` fastest, None
    /// where never seen — every cube whose low corner lies in the block.
    pub(crate) fn neighbourhood(&self, key: [i32; 3], out: &mut Vec<Option<Voxel>>) {
        out.clear();
        out.resize(near_index([SIDE; 3]) + 1, None);
        for dz in 0..2 {
            for dy in 0..2 {
                for dx in 0..2 {
                    let Some(&b) = self.index.get(&[key[0] + dx, key[1] + dy, key[2] + dz]) else { continue };
                    let block = &self.blocks[b as usize];
                    // The part of this block inside the neighbourhood.
                    let span = |d: i32| if d == 0 { 0..SIDE } else { 0..1 };
                    for z in span(dz) {
                        for y in span(dy) {
                            for x in span(dx) {
                                let v = block.voxels[local([x, y, z])];
                                if v.weight > 0.0 {
                                    let inv = 1.0 / v.weight;
                                    out[near_index([x + dx * SIDE, y + dy * SIDE, z + dz * SIDE])] = Some(Voxel { sdf: v.sdf * inv, rgb: v.rgb.map(|c| c * inv) });
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    /// Every allocated block's key, in allocation order.
    pub(crate) fn block_keys(&self) -> Vec<[i32; 3]> {
        let mut keys = vec![[0; 3]; self.blocks.len()];
        for (k, &b) in &self.index {
            keys[b as usize] = *k;
        }
        keys
    }

    /// The voxel side the field uses, mm: `voxel_mm`, or coarser where it was fitted to the
    /// views' sampling ([`FuseParams::fit_to_sampling`]).
    pub fn voxel_mm(&self) -> f32 {
        self.voxel
    }

    /// The zero level set as a cleaned triangle mesh (`mesh.rs`).
    pub fn mesh(&self) -> (SurfaceMesh, MeshStats) {
        mesh::extract(self)
    }
}

/// The blocks' index.
type BlockIndex = FastMap<[i32; 3], u32>;

/// The index of block `key` in `blocks`, allocated (unseen) when new; None when it is new
/// and the memory budget (`max_blocks`) is spent.
fn block_of(index: &mut BlockIndex, blocks: &mut Vec<Block>, max_blocks: usize, key: [i32; 3]) -> Option<usize> {
    if let Some(&b) = index.get(&key) {
        return Some(b as usize);
    }
    if blocks.len() >= max_blocks {
        return None;
    }
    if blocks.len() == blocks.capacity() {
        // Doubling, but never past the budget.
        let extra = blocks.capacity().max(16).min(max_blocks - blocks.len());
        blocks.reserve_exact(extra);
    }
    index.insert(key, blocks.len() as u32);
    blocks.push(Block { voxels: [Sums::default(); VOXELS] });
    Some(blocks.len() - 1)
}

/// A hash map with a fast multiplicative hash (keys are grid and vertex indices, not chosen
/// by anyone).
type FastMap<K, V> = HashMap<K, V, std::hash::BuildHasherDefault<VoxelHasher>>;

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn norm(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}

/// `x.floor() as i32` without a libm call (the baseline x86-64 target has no rounding
/// instruction) nor the cast's checks for NaN and overflow: `x` is first held within
/// ±[`GRID_LIMIT`] (NaN goes to its low end), where the truncating conversion is exact and
/// defined. Exact for the grid indices here, far inside that.
#[inline(always)]
fn floor_i32(x: f32) -> i32 {
    let x = x.max(-GRID_LIMIT).min(GRID_LIMIT);
    // SAFETY: x is finite and within ±2³⁰, inside i32 (just clamped; NaN fails `max`).
    let t: i32 = unsafe { x.to_int_unchecked() };
    t - ((t as f32) > x) as i32
}

/// Voxels from the origin past which a grid index is held (2³⁰; a key keeps 2²⁰ anyway).
const GRID_LIMIT: f32 = (1u32 << 30) as f32;

/// The grid index of the voxel holding world point `q`.
#[inline(always)]
fn grid_index(q: &nalgebra::Vector3<f32>, inv_voxel: f32) -> [i32; 3] {
    [floor_i32(q.x * inv_voxel), floor_i32(q.y * inv_voxel), floor_i32(q.z * inv_voxel)]
}

/// The key of the block holding voxel `g`.
#[inline(always)]
fn block_key(g: [i32; 3]) -> [i32; 3] {
    g.map(|v| v.div_euclid(SIDE))
}

/// The centre of voxel `g`, in the world.
#[inline(always)]
pub(crate) fn voxel_centre(g: [i32; 3], voxel: f32) -> [f32; 3] {
    g.map(|v| (v as f32 + 0.5) * voxel)
}

/// The index of `l` (each coordinate 0…8, from the block's low corner) in a block's 9³
/// neighbourhood ([`Tsdf::neighbourhood`]).
#[inline(always)]
pub(crate) fn near_index(l: [i32; 3]) -> usize {
    const N: i32 = SIDE + 1;
    ((l[2] * N + l[1]) * N + l[0]) as usize
}

/// A voxel's index inside its block.
fn local(g: [i32; 3]) -> usize {
    let (x, y, z) = (g[0].rem_euclid(SIDE), g[1].rem_euclid(SIDE), g[2].rem_euclid(SIDE));
    ((z * SIDE + y) * SIDE + x) as usize
}
