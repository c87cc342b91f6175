//! Exact nearest-neighbour search over a fixed point set (kiddo's immutable k-d tree).

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};

use super::{check_points, RegisterError};

/// A k-d tree over `points`; results are indices into `points`.
pub struct KdTree {
    tree: ImmutableKdTree<f32, 3>,
    pub points: Vec<[f32; 3]>,
}

impl std::fmt::Debug for KdTree {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "KdTree({} points)", self.points.len())
    }
}

impl KdTree {
    /// Builds the tree. `what` names the point set in errors.
    pub fn build(points: Vec<[f32; 3]>, what: &str) -> Result<KdTree, RegisterError> {
        check_points(&points, what)?;
        let tree = ImmutableKdTree::new_from_slice(&points).map_err(|e| RegisterError::Tree(format!("{what}: {e}")))?;
        Ok(KdTree { tree, points })
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The nearest point: `(index, squared distance)`.
    #[inline]
    pub fn nearest(&self, p: &[f32; 3]) -> (usize, f32) {
        let r = self.tree.query(p).nearest_one::<SquaredEuclidean<f32>>().execute();
        (r.item as usize, r.distance)
    }

    /// The `k` nearest points, nearest first: `(index, squared distance)`.
    pub fn knn(&self, p: &[f32; 3], k: usize) -> Vec<(usize, f32)> {
        let k = NonZeroUsize::new(k.clamp(1, self.len())).unwrap();
        self.tree.query(p).nearest_n::<SquaredEuclidean<f32>>(k).execute().into_iter().map(|r| (r.item as usize, r.distance)).collect()
    }

    /// Up to `k` nearest points no farther than `radius`, nearest first.
    pub fn knn_within(&self, p: &[f32; 3], k: usize, radius: f32) -> Vec<(usize, f32)> {
        let k = NonZeroUsize::new(k.clamp(1, self.len())).unwrap();
        self.tree.query(p).nearest_n::<SquaredEuclidean<f32>>(k).within(radius * radius).execute().into_iter().map(|r| (r.item as usize, r.distance)).collect()
    }

    /// Median distance from a sample of points to their nearest *other* point: the cloud's
    /// sampling spacing, in its units.
    pub fn median_spacing(&self) -> f64 {
        let idx = super::subsample_indices(self.len(), 2000);
        let mut d: Vec<f32> = idx.iter().filter_map(|&i| self.knn(&self.points[i], 2).get(1).map(|r| r.1.sqrt())).collect();
        if d.is_empty() {
            return 0.0;
        }
        let mid = d.len() / 2;
        d.select_nth_unstable_by(mid, f32::total_cmp);
        d[mid] as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_matches_brute_force() {
        // A small xorshift: uniform points in the unit cube, the same every run.
        let mut next = crate::testing::xorshift(0x9E37_79B9_7F4A_7C15);
        let mut unit = move || (next() >> 11) as f64 / (1u64 << 53) as f64;
        let pts: Vec<[f32; 3]> = (0..2000).map(|_| [unit() as f32, unit() as f32, unit() as f32]).collect();
        let tree = KdTree::build(pts.clone(), "cloud").unwrap();
        for _ in 0..200 {
            let q = [unit() as f32, unit() as f32, unit() as f32];
            let d2 = |p: &[f32; 3]| (0..3).map(|i| (p[i] - q[i]).powi(2)).sum::<f32>();
            let best = pts.iter().map(d2).fold(f32::INFINITY, f32::min);
            let (i, d) = tree.nearest(&q);
            assert!((d - best).abs() < 1e-6 && (d2(&pts[i]) - best).abs() < 1e-6);
            let k = tree.knn(&q, 5);
            assert_eq!(k.len(), 5);
            assert!(k.windows(2).all(|w| w[0].1 <= w[1].1));
        }
    }

    #[test]
    fn empty_and_nan_clouds_are_refused() {
        assert!(KdTree::build(vec![], "target").unwrap_err().to_string().contains("target has no points"));
        let e = KdTree::build(vec![[0.0; 3], [f32::NAN, 0.0, 0.0]], "source").unwrap_err().to_string();
        assert!(e.contains("point #1"), "{e}");
    }
}
