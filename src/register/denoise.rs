//! Isolated-point removal, the paper's two criteria together: a point goes when (i) no other
//! point is within `min_distance` of it AND (ii) the cube of the working volume it lies in
//! holds fewer than `min_cube_points` points. Surface seen from several views accumulates
//! points, so true surface survives; stray matches in empty space do not.

use std::collections::HashMap;

use super::KdTree;

/// Thresholds, in the cloud's units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DenoiseParams {
    /// Criterion (i): a point with no neighbour closer than this is isolated.
    pub min_distance: f64,
    /// Side of the working volume's cubes for criterion (ii).
    pub cube: f64,
    /// Criterion (ii): a cube with fewer points than this is sparse.
    pub min_cube_points: usize,
}

impl Default for DenoiseParams {
    /// For millimetre clouds voxel-merged at 1 mm: isolated beyond 3 mm, in a 10 mm cube with
    /// fewer than 20 points.
    fn default() -> Self {
        DenoiseParams { min_distance: 3.0, cube: 10.0, min_cube_points: 20 }
    }
}

/// Which points to keep (`true`) under both criteria.
pub fn keep_mask(points: &[[f32; 3]], params: &DenoiseParams) -> Vec<bool> {
    if points.len() < 2 {
        return vec![true; points.len()];
    }
    let key = |p: &[f32; 3]| [(p[0] as f64 / params.cube).floor() as i64, (p[1] as f64 / params.cube).floor() as i64, (p[2] as f64 / params.cube).floor() as i64];
    let mut density: HashMap<[i64; 3], usize> = HashMap::new();
    for p in points {
        *density.entry(key(p)).or_default() += 1;
    }
    let sparse: Vec<bool> = points.iter().map(|p| density[&key(p)] < params.min_cube_points).collect();
    if !sparse.iter().any(|&s| s) {
        return vec![true; points.len()];
    }
    let Ok(tree) = KdTree::build(points.to_vec(), "cloud") else {
        return vec![true; points.len()];
    };
    let min2 = (params.min_distance * params.min_distance) as f32;
    use rayon::prelude::*;
    points
        .par_iter()
        .zip(sparse.par_iter())
        .map(|(p, &sparse)| {
            if !sparse {
                return true;
            }
            let nn = tree.knn(p, 2);
            let isolated = nn.get(1).is_none_or(|n| n.1 > min2);
            !isolated
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_points_meeting_both_criteria_go() {
        let mut pts = Vec::new();
        // A dense 1 mm grid patch.
        for i in 0..30 {
            for j in 0..30 {
                pts.push([i as f32, j as f32, 0.0]);
            }
        }
        let dense = pts.len();
        // A stray point far away (isolated and in an empty cube): removed.
        pts.push([200.0, 0.0, 0.0]);
        // A stray pair close together: each has a neighbour, so (i) fails: kept.
        pts.push([300.0, 0.0, 0.0]);
        pts.push([301.0, 0.0, 0.0]);
        // A point 5 mm above the dense patch: isolated, but its cube is dense: kept.
        pts.push([15.0, 15.0, 5.0]);
        let keep = keep_mask(&pts, &DenoiseParams { min_distance: 3.0, cube: 10.0, min_cube_points: 20 });
        assert!(keep[..dense].iter().all(|&k| k));
        assert_eq!(&keep[dense..], &[false, true, true, true]);
    }
}
