//! Distance from points to a triangle mesh (accuracy checks against a ground-truth surface).

use nalgebra::{Isometry3, Point3, Vector3};

use super::{KdTree, RegisterError};
use crate::cloud::Mesh;

/// A mesh placed in the query frame, indexed by triangle centroids.
pub struct Surface {
    tris: Vec<[Vector3<f64>; 3]>,
    centroids: KdTree,
    /// Neighbouring centroids examined per query.
    k: usize,
}

impl Surface {
    /// `mesh` moved by `place` (e.g. `cam_from_obj`).
    pub fn new(mesh: &Mesh, place: &Isometry3<f64>) -> Result<Surface, RegisterError> {
        let v: Vec<Vector3<f64>> = mesh.cloud.points.iter().map(|p| (place * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64)).coords).collect();
        let mut tris = Vec::with_capacity(mesh.triangles.len());
        for t in &mesh.triangles {
            let get = |i: u32| v.get(i as usize).copied().ok_or_else(|| RegisterError::Param(format!("triangle refers to vertex {i}, but the mesh has {}", v.len())));
            tris.push([get(t[0])?, get(t[1])?, get(t[2])?]);
        }
        if tris.is_empty() {
            return Err(RegisterError::Empty { what: "mesh (triangles)".into() });
        }
        let cents: Vec<[f32; 3]> = tris.iter().map(|t| ((t[0] + t[1] + t[2]) / 3.0).map(|x| x as f32).into()).collect();
        Ok(Surface { tris, centroids: KdTree::build(cents, "mesh")?, k: 16 })
    }

    /// Distance from `p` to the nearest of the triangles whose centroids are nearest.
    pub fn distance(&self, p: &[f32; 3]) -> f64 {
        let q = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
        self.centroids.knn(p, self.k).into_iter().map(|(i, _)| point_triangle_distance(&q, &self.tris[i])).fold(f64::INFINITY, f64::min)
    }

    /// Distances of many points (in parallel).
    pub fn distances(&self, points: &[[f32; 3]]) -> Vec<f64> {
        use rayon::prelude::*;
        points.par_iter().map(|p| self.distance(p)).collect()
    }
}

/// Euclidean distance from `p` to triangle `t` (Ericson, Real-Time Collision Detection 5.1.5).
pub fn point_triangle_distance(p: &Vector3<f64>, t: &[Vector3<f64>; 3]) -> f64 {
    let (a, b, c) = (t[0], t[1], t[2]);
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(&ap), ac.dot(&ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return (p - a).norm();
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(&bp), ac.dot(&bp));
    if d3 >= 0.0 && d4 <= d3 {
        return (p - b).norm();
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (p - (a + ab * v)).norm();
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(&cp), ac.dot(&cp));
    if d6 >= 0.0 && d5 <= d6 {
        return (p - c).norm();
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (p - (a + ac * w)).norm();
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (p - (b + (c - b) * w)).norm();
    }
    let denom = 1.0 / (va + vb + vc);
    let (v, w) = (vb * denom, vc * denom);
    (p - (a + ab * v + ac * w)).norm()
}

/// The `q`-quantile (0…1) of `values` (sorted copy, nearest rank).
pub fn quantile(values: &[f64], q: f64) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let i = ((v.len() - 1) as f64 * q.clamp(0.0, 1.0)).round() as usize;
    Some(v[i])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cloud::PointCloud;

    #[test]
    fn distances_to_a_unit_square() {
        let mesh = Mesh { cloud: PointCloud { points: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]], colors: vec![], normals: None, rim_px: None }, triangles: vec![[0, 1, 2], [0, 2, 3]] };
        let s = Surface::new(&mesh, &Isometry3::translation(0.0, 0.0, 10.0)).unwrap();
        assert!((s.distance(&[0.5, 0.5, 12.0]) - 2.0).abs() < 1e-9);
        assert!((s.distance(&[2.0, 0.5, 10.0]) - 1.0).abs() < 1e-9);
        assert!((s.distance(&[-3.0, -4.0, 10.0]) - 5.0).abs() < 1e-9);
        assert_eq!(quantile(&[3.0, 1.0, 2.0], 0.5), Some(2.0));
    }
}
