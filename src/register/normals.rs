//! Surface normals by principal component analysis of each point's neighbourhood.

use nalgebra::Vector3;

use super::KdTree;

/// How a neighbourhood is chosen: up to `max_nn` nearest points within `radius` (Open3D's
/// "hybrid" search).
#[derive(Debug, Clone, Copy)]
pub struct NormalParams {
    pub radius: f32,
    pub max_nn: usize,
}

/// The normal at `p` from its neighbours in `tree`, and the surface variation
/// λ₀ / (λ₀ + λ₁ + λ₂) (0 on a plane, 1/3 for isotropic scatter). `None` when fewer than
/// three neighbours are in reach. The sign is arbitrary.
pub fn normal_at(tree: &KdTree, p: &[f32; 3], params: NormalParams) -> Option<([f32; 3], f32)> {
    let nn = tree.knn_within(p, params.max_nn, params.radius);
    normal_of(nn.iter().map(|&(i, _)| &tree.points[i]))
}

/// The normal of a neighbourhood and its surface variation (as [`normal_at`]); `None` under
/// three points or when they span no plane.
pub fn normal_of<'a>(points: impl Iterator<Item = &'a [f32; 3]> + Clone) -> Option<([f32; 3], f32)> {
    let v = |q: &[f32; 3]| Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64);
    let n = points.clone().count();
    if n < 3 {
        return None;
    }
    let mean = points.clone().map(v).sum::<Vector3<f64>>() / n as f64;
    let mut cov = [0.0f64; 6];
    for q in points {
        let d = v(q) - mean;
        for (c, x) in cov.iter_mut().zip([d.x * d.x, d.x * d.y, d.x * d.z, d.y * d.y, d.y * d.z, d.z * d.z]) {
            *c += x;
        }
    }
    // Closed form (`grid::smallest_eigenpair`): a tenth of an iterative eigensolver's time,
    // and no normal where the smallest eigenvalue is not separated from the next.
    let (normal, lo) = super::grid::smallest_eigenpair(&cov)?;
    let total = cov[0] + cov[3] + cov[5];
    if total <= 0.0 {
        return None;
    }
    Some(([normal[0] as f32, normal[1] as f32, normal[2] as f32], (lo.max(0.0) / total) as f32))
}

/// Normals of every point of `tree`, oriented towards `viewpoint` (a camera centre) when
/// given; `[0, 0, 0]` where a point has too few neighbours.
pub fn estimate_normals(tree: &KdTree, params: NormalParams, viewpoint: Option<[f32; 3]>) -> Vec<[f32; 3]> {
    use rayon::prelude::*;
    tree.points
        .par_iter()
        .map(|p| match normal_at(tree, p, params) {
            None => [0.0; 3],
            Some((n, _)) => orient(n, p, viewpoint),
        })
        .collect()
}

fn orient(n: [f32; 3], p: &[f32; 3], viewpoint: Option<[f32; 3]>) -> [f32; 3] {
    let Some(v) = viewpoint else { return n };
    let dot = (0..3).map(|i| n[i] * (v[i] - p[i])).sum::<f32>();
    if dot < 0.0 {
        [-n[0], -n[1], -n[2]]
    } else {
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_normals_point_at_the_viewpoint() {
        let mut pts = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                // The plane z = 0.5 x + 100, tilted.
                let (x, y) = (i as f32, j as f32);
                pts.push([x, y, 0.5 * x + 100.0]);
            }
        }
        let tree = KdTree::build(pts, "plane").unwrap();
        let normals = estimate_normals(&tree, NormalParams { radius: 3.0, max_nn: 20 }, Some([0.0; 3]));
        let expect = Vector3::new(0.5f32, 0.0, -1.0).normalize();
        for n in &normals {
            let n = Vector3::new(n[0], n[1], n[2]);
            assert!((n - expect).norm() < 1e-4, "{n:?}");
        }
        let (_, variation) = normal_at(&tree, &[10.0, 10.0, 105.0], NormalParams { radius: 3.0, max_nn: 20 }).unwrap();
        assert!(variation < 1e-6);
    }

    #[test]
    fn isolated_points_get_no_normal() {
        let tree = KdTree::build(vec![[0.0; 3], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]], "sparse").unwrap();
        assert!(normal_at(&tree, &[0.0; 3], NormalParams { radius: 1.0, max_nn: 10 }).is_none());
    }
}
