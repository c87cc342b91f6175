//! One view into the field ([`Tsdf::integrate`]), in three steps that split across threads
//! and leave the same field, bit for bit, whatever their count:
//!
//! 1. the view's points placed in the world and sorted by block, then voxel, keeping the
//!    points of one voxel in their order (a radix sort: stable, and one order whatever
//!    the thread count);
//! 2. the points of one voxel merged into one ray, and each ray's updates along it (voxel,
//!    signed distance) listed — on one thread, added to the field at once; on several, in
//!    parts cut between voxels, each listing its updates per owner (a hash of the block's
//!    key picks which thread adds them), with the blocks looked up in the field as it was
//!    before the view; the blocks the view adds are then allocated in the order of the
//!    updates, as one pass allocates them;
//! 3. on several threads, the updates added, each owner's by one thread, part after part in
//!    order: every voxel's sums take their terms in the one order, so the floats come out
//!    the same.

use nalgebra::{Isometry3, Matrix3, Vector3};
use rayon::prelude::*;

use super::{block_key, block_of, grid_index, local, rim_weight, usable, voxel_centre, Block, BlockIndex, Sums, Tsdf};
use crate::cloud::PointCloud;

/// One voxel's update: the block (an index into `Tsdf::blocks`, or [`NEW`] / [`REFUSED`]),
/// the voxel in it, the truncated signed distance, and the ray (its part's index) whose
/// weight and colour it adds.
#[derive(Clone, Copy)]
struct Update {
    block: u32,
    voxel: u16,
    sdf: f32,
    ray: u32,
}

/// A block the field did not hold before the view: allocated after step 2.
const NEW: u32 = u32::MAX - 1;
/// A block the memory budget did not allow: the update is left out (and counted).
const REFUSED: u32 = u32::MAX;

/// The sort key of a point that is not fused (no usable point's key has its top bit set:
/// the block's z takes 18 bits from bit 45).
const UNUSABLE: u64 = u64::MAX;

/// A merged ray's weight and weighted-mean colour.
#[derive(Clone, Copy)]
struct Ray {
    w: f32,
    rgb: [f32; 3],
}

/// What one part of step 2 lists, its buffers kept from view to view.
#[derive(Default)]
pub(super) struct Part {
    rays: Vec<Ray>,
    /// The updates, one list per owner.
    updates: Vec<Vec<Update>>,
    /// `(owner, index into its updates, block key)` of the updates in blocks the field
    /// lacked, in the order listed.
    new: Vec<(u32, u32, [i32; 3])>,
    /// Points weighed down for lying near their view's silhouette.
    rim_weighed: usize,
}

/// Parts of step 2 per thread: the views' voxels differ in how many points they merge.
const PARTS_PER_THREAD: usize = 4;

/// What step 2 reads of the field's settings.
#[derive(Clone, Copy)]
struct Casting {
    voxel: f32,
    trunc: f32,
    depth_ref: f32,
    rim_scale: f32,
    use_rim: bool,
}

/// Where step 2's rays and updates go.
trait Sink {
    /// A merged ray; its index for [`Sink::update`].
    fn ray(&mut self, ray: Ray) -> u32;
    /// One update of voxel `voxel` of block `key` by ray `ray` (the last one handed).
    fn update(&mut self, key: [i32; 3], voxel: u16, sdf: f32, ray: u32);
    /// A point weighed down near its view's silhouette.
    fn rim_weighed(&mut self);
}

impl Tsdf {
    /// Integrates one view: `cloud` in the view's own camera frame (camera centre at the
    /// origin, +Z forward), placed by `world_from_view`. Each point updates the voxels its
    /// viewing ray crosses within the truncation band: signed distance along the ray,
    /// weight (depth_ref / Z)⁴ — times the rim's weight near the silhouette
    /// ([`super::FuseParams::rim_weight_px`]) where the cloud carries its points' distances —,
    /// colour. Split over [`Tsdf::set_threads`] threads (module docs).
    pub fn integrate(&mut self, cloud: &PointCloud, world_from_view: &Isometry3<f64>) {
        // (Only while the field is empty: every voxel has one size.)
        if self.spacing.is_none() && self.blocks.is_empty() {
            self.fit_voxel(cloud);
        }
        let threads = self.threads.max(1);
        let rot = world_from_view.rotation.to_rotation_matrix().into_inner().cast::<f32>();
        let t = world_from_view.translation.vector.cast::<f32>();
        let inv_voxel = 1.0 / self.voxel;
        // 1. The points of the view that land in one voxel are merged (weighted mean
        // position and colour, summed weight) and cast as one ray, as Voxblox's merged
        // integrator does: at the lab's sampling several points fall in each surface voxel,
        // and their rays would update the same voxels alike. Sorted by block, then voxel, the
        // rays come block by block, while the block and its neighbours are in cache.
        let key = |(i, p): (usize, &[f32; 3])| {
            let q = rot * Vector3::new(p[0], p[1], p[2]) + t;
            // The block's coordinates (18 bits each), then the voxel inside the block.
            let g = grid_index(&q, inv_voxel);
            let b = block_key(g).map(|v| ((v as i64 + (1 << 17)) as u64) & ((1 << 18) - 1));
            (b[2] << 45 | b[1] << 27 | b[0] << 9 | local(g) as u64, i as u32)
        };
        let mut order: Vec<(u64, u32)> = if threads > 1 {
            // Every point keyed in parallel (an indexed collect, which splits well), the
            // unusable ones marked and dropped after, in order.
            let mut all: Vec<(u64, u32)> = cloud.points.par_iter().enumerate().map(|(i, p)| if usable(p) { key((i, p)) } else { (UNUSABLE, i as u32) }).collect();
            all.retain(|e| e.0 != UNUSABLE);
            all
        } else {
            cloud.points.iter().enumerate().filter(|(_, p)| usable(p)).map(key).collect()
        };
        compact(&mut order);
        radix_sort(&mut order, &mut self.sort_buffer);
        let rim = cloud.rim_px.as_ref().is_some_and(|r| r.len() == cloud.len()) && self.params.rim_weight_px > 0.0;
        let casting = Casting { voxel: self.voxel, trunc: self.trunc, depth_ref: self.params.depth_ref_mm as f32, rim_scale: 1.0 / (self.params.rim_weight_px as f32 + 1.0), use_rim: rim };
        if threads == 1 {
            let mut sink = Direct { index: &mut self.index, blocks: &mut self.blocks, max_blocks: self.max_blocks, refused: &mut self.refused, rim_weighed: &mut self.rim_weighed, ray: Ray { w: 0.0, rgb: [0.0; 3] }, recent: Recent::default() };
            cast(casting, &order, cloud, &rot, &t, &mut sink);
        } else {
            self.parallel(threads, casting, &order, cloud, &rot, &t);
        }
        self.views += 1;
        self.points += order.len();
    }

    /// Steps 2 and 3 on `threads` threads (module docs).
    fn parallel(&mut self, threads: usize, casting: Casting, order: &[(u64, u32)], cloud: &PointCloud, rot: &Matrix3<f32>, t: &Vector3<f32>) {
        // The parts start on a new voxel.
        let parts_n = threads * PARTS_PER_THREAD;
        let mut cuts = vec![0];
        for p in 1..parts_n {
            let mut c = (order.len() * p / parts_n).max(*cuts.last().expect("starts with 0"));
            while c > 0 && c < order.len() && order[c].0 == order[c - 1].0 {
                c += 1;
            }
            cuts.push(c);
        }
        cuts.push(order.len());
        let mut parts = std::mem::take(&mut self.parts);
        parts.resize_with(parts_n, Part::default);
        let index = &self.index;
        parts.par_iter_mut().zip(cuts.par_windows(2)).for_each(|(part, w)| {
            part.rays.clear();
            part.updates.resize_with(threads, Vec::new);
            part.updates.iter_mut().for_each(Vec::clear);
            part.new.clear();
            part.rim_weighed = 0;
            let mut sink = Listing { index, part, owners: threads as u32, recent: Recent::default() };
            cast(casting, &order[w[0]..w[1]], cloud, rot, t, &mut sink);
        });
        // The blocks the view adds, in the order one pass over the updates meets them.
        for part in &mut parts {
            for &(owner, u, key) in &part.new {
                part.updates[owner as usize][u as usize].block = match block_of(&mut self.index, &mut self.blocks, self.max_blocks, key) {
                    Some(b) => b as u32,
                    None => {
                        self.refused += 1;
                        REFUSED
                    }
                };
            }
            self.rim_weighed += part.rim_weighed;
        }
        // 3. Each owner's updates, on a thread of its own.
        let blocks = Blocks(self.blocks.as_mut_ptr(), self.blocks.len());
        let (blocks, parts_ref) = (&blocks, &parts);
        (0..threads).into_par_iter().for_each(|owner| {
            for part in parts_ref {
                for u in part.updates[owner].iter().filter(|u| u.block != REFUSED) {
                    assert!((u.block as usize) < blocks.1, "an update's block is one the field holds");
                    // SAFETY: in bounds (just checked); an owner's updates are all in blocks
                    // whose keys hash to it, and each key has one block: no other task
                    // touches this one while this task runs.
                    let block = unsafe { &mut *blocks.0.add(u.block as usize) };
                    add(&mut block.voxels[u.voxel as usize], u.sdf, &part.rays[u.ray as usize]);
                }
            }
        });
        self.parts = parts;
    }
}

/// Step 2 over `order` (whole voxels): each voxel's points merged into a ray, and the
/// ray's updates handed to `sink`.
fn cast(c: Casting, order: &[(u64, u32)], cloud: &PointCloud, rot: &Matrix3<f32>, t: &Vector3<f32>, sink: &mut impl Sink) {
    let (voxel, inv_voxel, trunc) = (c.voxel, 1.0 / c.voxel, c.trunc);
    let steps = (trunc * inv_voxel).ceil() as i32;
    let rim = cloud.rim_px.as_deref().filter(|_| c.use_rim);
    let mut k = 0;
    while k < order.len() {
        let run = order[k..].iter().take_while(|e| e.0 == order[k].0).count();
        let (mut w, mut pv, mut rgb) = (0f32, Vector3::zeros(), [0f32; 3]);
        for &(_, i) in &order[k..k + run] {
            let p = &cloud.points[i as usize];
            let wr = rim.map_or(1.0, |r| rim_weight(r[i as usize], c.rim_scale));
            if wr < 1.0 {
                sink.rim_weighed();
            }
            let wi = (c.depth_ref / p[2]).powi(4) * wr;
            w += wi;
            pv += Vector3::new(p[0], p[1], p[2]) * wi;
            let col = cloud.colors.get(i as usize).map_or([200.0; 3], |c| [c[0] as f32, c[1] as f32, c[2] as f32]);
            for j in 0..3 {
                rgb[j] += col[j] * wi;
            }
        }
        k += run;
        let pv = pv / w;
        let ray = sink.ray(Ray { w, rgb: rgb.map(|c| c / w) });
        // The point and its ray in the world.
        let pw = rot * pv + t;
        let dir = rot * (pv / pv.norm());
        for s in -steps..=steps {
            let q = pw + dir * (s as f32 * voxel);
            let g = grid_index(&q, inv_voxel);
            let centre = Vector3::from(voxel_centre(g, voxel));
            // Distance from the voxel to the surface along the ray: positive in front.
            let sdf = (pw - centre).dot(&dir);
            if sdf < -trunc {
                continue;
            }
            sink.update(block_key(g), local(g) as u16, sdf.min(trunc), ray);
        }
    }
}

/// Packs the sort keys of `keys` (`key`'s layout in [`Tsdf::integrate`]: the block's z, y
/// and x in 18 bits each, then the voxel in 9) into the fewest bits that keep their order:
/// each block coordinate less the view's least, in as many bits as its span needs. A view's
/// coordinates straddle zero, where the 18-bit fields differ in every bit.
fn compact(keys: &mut [(u64, u32)]) {
    const FIELD: u64 = (1 << 18) - 1;
    let field = |k: u64, i: u32| (k >> (9 + 18 * i)) & FIELD;
    let (mut lo, mut hi) = ([FIELD; 3], [0u64; 3]);
    for k in keys.iter() {
        for i in 0..3 {
            lo[i] = lo[i].min(field(k.0, i as u32));
            hi[i] = hi[i].max(field(k.0, i as u32));
        }
    }
    // Bits per coordinate (x, y, z) and where each starts.
    let bits = std::array::from_fn::<u32, 3, _>(|i| 64 - hi[i].saturating_sub(lo[i]).leading_zeros());
    let at = [9, 9 + bits[0], 9 + bits[0] + bits[1]];
    for k in keys.iter_mut() {
        let mut c = k.0 & 511;
        for i in 0..3 {
            c |= (field(k.0, i as u32) - lo[i]) << at[i];
        }
        k.0 = c;
    }
}

/// Sorts `keys` by their first field, stably (equal keys keep their order), with `buffer`
/// as scratch: least significant byte first, over the bytes in which the keys differ (a
/// view's blocks span a few dozen per axis, so three or four bytes of the sixty-four).
fn radix_sort(keys: &mut Vec<(u64, u32)>, buffer: &mut Vec<(u64, u32)>) {
    let (any, all) = keys.iter().fold((0u64, !0u64), |(o, a), k| (o | k.0, a & k.0));
    let differ = any ^ all;
    buffer.clear();
    buffer.resize(keys.len(), (0, 0));
    for byte in 0..8 {
        let shift = byte * 8;
        if (differ >> shift) & 0xff == 0 {
            continue;
        }
        let mut start = [0usize; 256];
        for k in keys.iter() {
            start[((k.0 >> shift) & 0xff) as usize] += 1;
        }
        let mut sum = 0;
        for s in start.iter_mut() {
            (*s, sum) = (sum, sum + *s);
        }
        for k in keys.iter() {
            let d = ((k.0 >> shift) & 0xff) as usize;
            buffer[start[d]] = *k;
            start[d] += 1;
        }
        std::mem::swap(keys, buffer);
    }
}

/// One update added to its voxel's sums.
#[inline(always)]
fn add(v: &mut Sums, sdf: f32, ray: &Ray) {
    v.sdf += sdf * ray.w;
    v.weight += ray.w;
    for c in 0..3 {
        v.rgb[c] += ray.rgb[c] * ray.w;
    }
}

/// One thread: each update added to the field as it comes, its block allocated when new.
struct Direct<'a> {
    index: &'a mut BlockIndex,
    blocks: &'a mut Vec<Block>,
    max_blocks: usize,
    refused: &'a mut u64,
    rim_weighed: &'a mut usize,
    /// The ray being cast (one at a time).
    ray: Ray,
    /// The blocks of the last updates: a ray's samples mostly share one or two, and the
    /// next ray (of a neighbouring voxel) the same.
    recent: Recent<u32>,
}

impl Sink for Direct<'_> {
    fn ray(&mut self, ray: Ray) -> u32 {
        self.ray = ray;
        0
    }

    #[inline(always)]
    fn update(&mut self, key: [i32; 3], voxel: u16, sdf: f32, _ray: u32) {
        let b = match self.recent.get(key) {
            Some(b) => b as usize,
            None => match block_of(self.index, self.blocks, self.max_blocks, key) {
                Some(b) => {
                    self.recent.put(key, b as u32);
                    b
                }
                None => {
                    *self.refused += 1;
                    return;
                }
            },
        };
        add(&mut self.blocks[b].voxels[voxel as usize], sdf, &self.ray);
    }

    fn rim_weighed(&mut self) {
        *self.rim_weighed += 1;
    }
}

/// Several threads: the updates listed per owner, their blocks looked up in the field as it
/// was before the view.
struct Listing<'a> {
    index: &'a BlockIndex,
    part: &'a mut Part,
    owners: u32,
    /// The blocks of the last updates, and their owners (see [`Direct`]).
    recent: Recent<(u32, u32)>,
}

impl Sink for Listing<'_> {
    fn ray(&mut self, ray: Ray) -> u32 {
        self.part.rays.push(ray);
        self.part.rays.len() as u32 - 1
    }

    #[inline(always)]
    fn update(&mut self, key: [i32; 3], voxel: u16, sdf: f32, ray: u32) {
        let (block, owner) = match self.recent.get(key) {
            Some(found) => found,
            None => {
                let found = (self.index.get(&key).copied().unwrap_or(NEW), owner(key, self.owners));
                self.recent.put(key, found);
                found
            }
        };
        let list = &mut self.part.updates[owner as usize];
        if block == NEW {
            self.part.new.push((owner, list.len() as u32, key));
        }
        list.push(Update { block, voxel, sdf, ray });
    }

    fn rim_weighed(&mut self) {
        self.part.rim_weighed += 1;
    }
}

/// The last few blocks a sink looked up, by key, with what it found: most updates hit one
/// of them, and need no lookup in the field's index.
struct Recent<T> {
    keys: [[i32; 3]; RECENT],
    found: [T; RECENT],
    /// The slot the next new key takes (round robin).
    next: usize,
}

/// Blocks a [`Recent`] remembers.
const RECENT: usize = 4;

impl<T: Copy + Default> Default for Recent<T> {
    fn default() -> Self {
        // No block has these coordinates: the keys' are far inside i32.
        Recent { keys: [[i32::MIN; 3]; RECENT], found: [T::default(); RECENT], next: 0 }
    }
}

impl<T: Copy> Recent<T> {
    #[inline(always)]
    fn get(&self, key: [i32; 3]) -> Option<T> {
        (0..RECENT).find(|&i| self.keys[i] == key).map(|i| self.found[i])
    }

    #[inline(always)]
    fn put(&mut self, key: [i32; 3], found: T) {
        self.keys[self.next] = key;
        self.found[self.next] = found;
        self.next = (self.next + 1) % RECENT;
    }
}

/// The thread of `owners` that adds block `key`'s updates: neighbouring blocks mostly fall
/// to different ones.
fn owner(key: [i32; 3], owners: u32) -> u32 {
    let h = (key[0] as u32).wrapping_mul(0x9E37_79B1) ^ (key[1] as u32).wrapping_mul(0x85EB_CA77) ^ (key[2] as u32).wrapping_mul(0xC2B2_AE3D);
    (h >> 16) % owners
}

/// The field's blocks, shared by step 3's tasks, each of which writes only its own owner's.
struct Blocks(*mut Block, usize);

// SAFETY: the tasks that share it write disjoint blocks (see `Tsdf::parallel`).
unsafe impl Sync for Blocks {}

#[cfg(test)]
mod tests {
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    use super::*;
    use crate::fuse::{FuseParams, MeshStats};

    /// A bumpy ball (radius 20 mm ± 1.5, 300 mm ahead of the first camera) seen from `n`
    /// cameras turning round it: each view's points in its camera's frame, jittered, with
    /// colours and rim distances that vary from point to point, and the camera's pose.
    fn views(n: usize) -> Vec<(PointCloud, Isometry3<f64>)> {
        let centre = Vector3::new(0.0, 0.0, 300.0);
        let mut seed = 12345u64;
        let mut rand = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 33) as f64 / (1u64 << 31) as f64
        };
        (0..n)
            .map(|k| {
                let angle = k as f64 / n as f64 * std::f64::consts::TAU;
                let world_from_cam = Isometry3::from_parts(Translation3::from(centre), UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle)) * Isometry3::translation(0.0, 0.0, -300.0);
                let cam_from_world = world_from_cam.inverse();
                let mut cloud = PointCloud { rim_px: Some(Vec::new()), ..PointCloud::default() };
                for i in 0..90 {
                    for j in 0..180 {
                        let (th, ph) = ((i as f64 + rand()) / 90.0 * std::f64::consts::PI, (j as f64 + rand()) / 180.0 * std::f64::consts::TAU);
                        let n = Vector3::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin());
                        let r = 20.0 + 1.5 * (3.0 * th).sin() * (4.0 * ph).cos() + 0.05 * rand();
                        let p = cam_from_world * Point3::from(centre + n * r);
                        let facing = (cam_from_world.rotation * n).dot(&-p.coords.normalize());
                        if facing > 0.1 {
                            cloud.points.push([p.x as f32, p.y as f32, p.z as f32]);
                            cloud.colors.push([(rand() * 255.0) as u8, (i * 2) as u8, (j % 256) as u8]);
                            cloud.rim_px.as_mut().unwrap().push(((facing - 0.1) * 25.0) as u8);
                        }
                    }
                }
                (cloud, world_from_cam)
            })
            .collect()
    }

    /// The views fused on a pool of `threads` threads, split as many ways: the mesh, its
    /// figures, and the field's blocks, refused updates and rim-weighed points.
    fn fused(views: &[(PointCloud, Isometry3<f64>)], params: &FuseParams, threads: usize) -> (crate::cloud::Mesh, MeshStats, usize, u64, usize) {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let mut tsdf = Tsdf::new(params.clone()).unwrap();
        tsdf.set_threads(threads);
        for (c, p) in views {
            pool.install(|| tsdf.integrate(c, p));
        }
        let (mesh, stats) = tsdf.mesh();
        (mesh, stats, tsdf.blocks(), tsdf.refused_updates(), tsdf.rim_weighed_points())
    }

    /// Split over threads, the field is the one a single thread makes, bit for bit: every
    /// voxel's sums take their terms in the same order, and new blocks come in the same
    /// order — also when the memory budget refuses some.
    #[test]
    fn the_field_is_the_same_on_any_number_of_threads() {
        let views = views(10);
        for params in [FuseParams::default(), FuseParams { voxel_mm: 0.5, max_field_mib: 1.0, ..FuseParams::default() }] {
            let (one, one_stats, blocks, refused, weighed) = fused(&views, &params, 1);
            assert!(one_stats.triangles > 5000 && weighed > 0, "{one_stats:?}");
            assert_eq!(refused > 0, params.max_field_mib < 1024.0, "{refused} updates refused");
            for threads in [2, 3, 4] {
                let (many, many_stats, b, r, w) = fused(&views, &params, threads);
                assert_eq!((b, r, w), (blocks, refused, weighed), "{threads} threads");
                assert_eq!(many_stats, one_stats, "{threads} threads");
                assert_eq!(many.triangles, one.triangles, "{threads} threads");
                let bits = |m: &crate::cloud::Mesh| (m.cloud.points.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>(), m.cloud.colors.clone());
                assert!(bits(&many) == bits(&one), "{threads} threads: vertices or colours differ");
            }
        }
    }
}
