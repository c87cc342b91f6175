//! The voxel-merged model: every point that falls in a voxel is averaged into it, so the
//! model's size follows the object's surface, not the number of views.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use nalgebra::Isometry3;

use crate::cloud::PointCloud;

#[derive(Debug, Clone, Copy, Default)]
struct Cell {
    sum: [f64; 3],
    rgb: [u32; 3],
    count: u32,
}

/// A multiplicative hash of voxel keys (FxHash's mixing): the std SipHash is built to resist
/// chosen keys, which voxel coordinates are not, and cost most of a model update.
#[derive(Default)]
pub(crate) struct VoxelHasher(u64);

impl Hasher for VoxelHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }

    fn write_u32(&mut self, v: u32) {
        self.write_u64(v as u64);
    }

    fn write_i32(&mut self, v: i32) {
        self.write_u64(v as u32 as u64);
    }

    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn write_usize(&mut self, v: usize) {
        self.write_u64(v as u64);
    }
}

/// Points averaged per cubic voxel of side `size`.
#[derive(Debug, Clone)]
pub struct VoxelModel {
    size: f64,
    cells: HashMap<[i32; 3], Cell, BuildHasherDefault<VoxelHasher>>,
}

impl VoxelModel {
    /// An empty model; `size` must be positive (checked by callers' parameter parsing).
    pub fn new(size: f64) -> VoxelModel {
        assert!(size > 0.0 && size.is_finite(), "voxel size must be positive");
        VoxelModel { size, cells: HashMap::default() }
    }

    /// Occupied voxels.
    pub fn len(&self) -> usize {
        self.cells.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cells.is_empty()
    }

    /// Adds `cloud`, moved by `t` (e.g. `first_from_view`).
    pub fn add(&mut self, cloud: &PointCloud, t: &Isometry3<f64>) {
        for (i, p) in cloud.points.iter().enumerate() {
            let q = t * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if !(q.x.is_finite() && q.y.is_finite() && q.z.is_finite()) {
                continue;
            }
            let key = [(q.x / self.size).floor() as i32, (q.y / self.size).floor() as i32, (q.z / self.size).floor() as i32];
            let c = self.cells.entry(key).or_default();
            c.sum[0] += q.x;
            c.sum[1] += q.y;
            c.sum[2] += q.z;
            let rgb = cloud.colors.get(i).copied().unwrap_or([200, 200, 200]);
            for k in 0..3 {
                c.rgb[k] += rgb[k] as u32;
            }
            c.count += 1;
        }
    }

    /// One point per voxel (the mean of what fell in it, with its mean colour), and how many
    /// points each one merges.
    pub fn to_cloud(&self) -> (PointCloud, Vec<u32>) {
        let mut keys: Vec<&[i32; 3]> = self.cells.keys().collect();
        keys.sort_unstable();
        let mut cloud = PointCloud::default();
        let mut counts = Vec::with_capacity(keys.len());
        for k in keys {
            let c = &self.cells[k];
            let n = c.count as f64;
            cloud.points.push([(c.sum[0] / n) as f32, (c.sum[1] / n) as f32, (c.sum[2] / n) as f32]);
            cloud.colors.push([(c.rgb[0] / c.count) as u8, (c.rgb[1] / c.count) as u8, (c.rgb[2] / c.count) as u8]);
            counts.push(c.count);
        }
        (cloud, counts)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn repeated_views_do_not_grow_the_model() {
        let cloud = PointCloud { points: (0..1000).map(|i| [(i % 10) as f32 * 2.0, (i / 10 % 10) as f32 * 2.0, (i / 100) as f32 * 2.0]).collect(), colors: vec![[10, 20, 30]; 1000], normals: None, rim_px: None };
        let mut m = VoxelModel::new(1.0);
        m.add(&cloud, &Isometry3::identity());
        let n = m.len();
        assert_eq!(n, 1000);
        for _ in 0..20 {
            m.add(&cloud, &Isometry3::translation(0.1, 0.0, 0.0));
        }
        assert_eq!(m.len(), n);
        let (merged, counts) = m.to_cloud();
        assert_eq!(merged.colors[0], [10, 20, 30]);
        assert_eq!(counts.iter().sum::<u32>(), 21_000);
        // Averages: 1 part at x + 0, 20 parts at x + 0.1.
        let x0 = merged.points.iter().map(|p| p[0]).fold(f32::INFINITY, f32::min);
        assert!((x0 - 2.0 / 21.0).abs() < 1e-5, "{x0}");
    }
}
