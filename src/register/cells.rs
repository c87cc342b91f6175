//! Exact nearest-neighbour search within a bounded distance, on a uniform grid of cubic
//! cells: what ICP asks of its target (the nearest point within the correspondence
//! distance, and a normal's neighbours within a radius).
//!
//! The points are sorted by cell, cells in x-fastest order, so a run of cells along x is one
//! run of points. A query visits cells in shells of growing Chebyshev radius around its own
//! cell and stops as soon as no unvisited cell can hold a closer point than what it has — the
//! bound is the distance from the query to the nearest face of the visited block — or when
//! the shells pass the search radius. Far from the cloud a query costs a few empty rows, not
//! a tree descent into everything within reach: a k-d tree's bounded search collects every
//! point inside its radius, which on a dense scan is hundreds of points per query.

use super::{check_points, dist2, RegisterError};

/// Most cells the grid may have; a larger cloud gets larger cells (the search stays exact).
const MAX_CELLS: usize = 1 << 22;

/// Points bucketed by cubic cell; indices in results are into `points` (the caller's order).
pub struct CellIndex {
    pub points: Vec<[f32; 3]>,
    /// The points in cell order, and each one's index in `points`.
    sorted: Vec<[f32; 3]>,
    ids: Vec<u32>,
    /// `starts[c]..starts[c + 1]` are cell `c`'s points in `sorted`.
    starts: Vec<u32>,
    origin: [f32; 3],
    inv_cell: f32,
    cell: f32,
    dims: [usize; 3],
}

/// A query's place in the grid: its cell (possibly outside the grid) and its position inside
/// that cell along each axis, in [0, 1).
struct Located {
    cell: [i64; 3],
    frac: [f32; 3],
    side: f32,
}

impl Located {
    /// Squared distance along axis `a` from the query to the cells `d` steps away on it.
    #[inline]
    fn gap2(&self, a: usize, d: i64) -> f32 {
        let g = match d {
            0 => 0.0,
            d if d > 0 => d as f32 - self.frac[a],
            d => self.frac[a] - (d + 1) as f32,
        } * self.side;
        g * g
    }

    /// Squared distance from the query to any cell outside shells `0..=r`.
    fn beyond2(&self, r: i64) -> f32 {
        (0..3).map(|a| self.gap2(a, r + 1).min(self.gap2(a, -(r + 1)))).fold(f32::INFINITY, f32::min)
    }
}

impl std::fmt::Debug for CellIndex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "CellIndex({} points, {:?} cells of {})", self.points.len(), self.dims, self.cell)
    }
}

impl CellIndex {
    /// Buckets `points` into cells of side `cell` (enlarged when the cloud's box would need more
    /// than `MAX_CELLS`, 4 M). `what` names the point set in errors.
    pub fn build(points: Vec<[f32; 3]>, cell: f32, what: &str) -> Result<CellIndex, RegisterError> {
        check_points(&points, what)?;
        if !(cell.is_finite() && cell > 0.0) {
            return Err(RegisterError::Param(format!("{what}: cell size must be a positive number, got {cell}")));
        }
        if points.len() > u32::MAX as usize {
            return Err(RegisterError::Param(format!("{what}: {} points are more than a cell index holds", points.len())));
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in &points {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let mut cell = cell;
        let dims = loop {
            // In f64: the extent of finite f32 coordinates may overflow f32.
            let dims: [usize; 3] = std::array::from_fn(|a| ((hi[a] as f64 - lo[a] as f64) / cell as f64).min(1e12) as usize + 1);
            if dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d)).is_some_and(|n| n <= MAX_CELLS) {
                break dims;
            }
            cell *= 2.0;
        };
        let mut index = CellIndex { points, sorted: Vec::new(), ids: Vec::new(), starts: Vec::new(), origin: lo, inv_cell: 1.0 / cell, cell, dims };
        let ncells = dims[0] * dims[1] * dims[2];
        let keys: Vec<u32> = index.points.iter().map(|p| index.cell_of(p) as u32).collect();
        let mut starts = vec![0u32; ncells + 1];
        for &k in &keys {
            starts[k as usize + 1] += 1;
        }
        for c in 0..ncells {
            starts[c + 1] += starts[c];
        }
        let mut fill = starts.clone();
        let mut ids = vec![0u32; keys.len()];
        for (i, &k) in keys.iter().enumerate() {
            ids[fill[k as usize] as usize] = i as u32;
            fill[k as usize] += 1;
        }
        index.sorted = ids.iter().map(|&i| index.points[i as usize]).collect();
        index.ids = ids;
        index.starts = starts;
        Ok(index)
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The cell of a point, clamped into the grid's box: queries made in this order read the
    /// points in their memory order.
    pub(super) fn cell_of(&self, p: &[f32; 3]) -> usize {
        let c: [usize; 3] = std::array::from_fn(|a| (((p[a] as f64 - self.origin[a] as f64) * self.inv_cell as f64) as usize).min(self.dims[a] - 1));
        (c[2] * self.dims[1] + c[1]) * self.dims[0] + c[0]
    }

    /// Visits the points of the cells in shell `r` (Chebyshev radius `r` around the query's
    /// cell, clipped to the grid), a run of cells along x at a time, skipping the runs that lie
    /// wholly `bound2` (squared) or farther from the query.
    #[inline]
    fn shell(&self, at: &Located, r: i64, bound2: f32, mut visit: impl FnMut(&[[f32; 3]], &[u32])) {
        let c = at.cell;
        let [nx, ny, nz] = self.dims.map(|d| d as i64);
        let (z0, z1) = ((c[2] - r).max(0), (c[2] + r).min(nz - 1));
        let (y0, y1) = ((c[1] - r).max(0), (c[1] + r).min(ny - 1));
        let (x0, x1) = ((c[0] - r).max(0), (c[0] + r).min(nx - 1));
        if z0 > z1 || y0 > y1 || x0 > x1 {
            return;
        }
        let mut run = |row: i64, a: i64, b: i64| {
            let (s, e) = (self.starts[(row + a) as usize] as usize, self.starts[(row + b + 1) as usize] as usize);
            if s < e {
                visit(&self.sorted[s..e], &self.ids[s..e]);
            }
        };
        for z in z0..=z1 {
            let gz = at.gap2(2, z - c[2]);
            for y in y0..=y1 {
                let gyz = gz + at.gap2(1, y - c[1]);
                if gyz >= bound2 {
                    continue;
                }
                let row = (z * ny + y) * nx;
                if r == 0 || (z - c[2]).abs() == r || (y - c[1]).abs() == r {
                    run(row, x0, x1);
                } else {
                    if c[0] - r >= 0 && gyz + at.gap2(0, -r) < bound2 {
                        run(row, c[0] - r, c[0] - r);
                    }
                    if c[0] + r < nx && gyz + at.gap2(0, r) < bound2 {
                        run(row, c[0] + r, c[0] + r);
                    }
                }
            }
        }
    }

    /// Where a query starts: its cell (possibly outside the grid) and its place inside it.
    fn locate(&self, p: &[f32; 3]) -> Located {
        let mut cell = [0i64; 3];
        let mut frac = [0f32; 3];
        for a in 0..3 {
            // In f64 (differences of f32 coordinates may overflow f32), and clamped: a query
            // far outside the grid only needs to be known as far outside.
            let u = ((p[a] as f64 - self.origin[a] as f64) * self.inv_cell as f64).clamp(-1e9, 1e9);
            let f = u.floor();
            cell[a] = f as i64;
            frac[a] = (u - f) as f32;
        }
        Located { cell, frac, side: self.cell }
    }

    /// The shells a query at `c` must visit at most to reach everything within `radius`, and
    /// whether the grid lies entirely beyond that reach.
    fn reach(&self, c: [i64; 3], radius: f32) -> Option<i64> {
        let r_max = (radius * self.inv_cell).ceil() as i64 + 1;
        // Chebyshev distance in cells from c to the grid's box.
        let gap = (0..3).map(|a| (-c[a]).max(c[a] - (self.dims[a] as i64 - 1)).max(0)).max().unwrap_or(0);
        (gap <= r_max).then_some(r_max)
    }

    /// The nearest point no farther than `sqrt(max_d2)`: `(index, squared distance)`.
    pub fn nearest_within(&self, p: &[f32; 3], max_d2: f32) -> Option<(usize, f32)> {
        let at = self.locate(p);
        let r_max = self.reach(at.cell, max_d2.sqrt())?;
        let mut best: Option<(u32, f32)> = None;
        let mut best_d2 = max_d2;
        for r in 0..=r_max {
            self.shell(&at, r, best_d2.next_up(), |pts, ids| {
                for (q, &id) in pts.iter().zip(ids) {
                    let d2 = dist2(p, q);
                    // Ties go to the lower index, whatever order the cells come in.
                    if d2 < best_d2 || (d2 == best_d2 && best.is_none_or(|(b, _)| id < b)) {
                        best = Some((id, d2));
                        best_d2 = d2;
                    }
                }
            });
            // Every unvisited point is at least this far away.
            if at.beyond2(r) > best_d2 {
                break;
            }
        }
        best.map(|(i, d2)| (i as usize, d2))
    }

    /// Up to `k` nearest points no farther than `radius`, in no particular order (what a
    /// normal needs); `scratch` is reused across calls.
    pub fn knn_within_unordered<'a>(&'a self, p: &[f32; 3], k: usize, radius: f32, scratch: &'a mut Vec<u64>) -> impl Iterator<Item = &'a [f32; 3]> + Clone + 'a {
        self.k_nearest_keys(p, k, radius, scratch);
        scratch.iter().map(|&key| &self.points[(key & 0xffff_ffff) as usize])
    }

    /// The `k` nearest within `radius` as keys `d²'s bits << 32 | index`: a non-negative
    /// float's bits order as the float does, so the keys order by distance, then index.
    fn k_nearest_keys(&self, p: &[f32; 3], k: usize, radius: f32, found: &mut Vec<u64>) {
        found.clear();
        if k == 0 {
            return;
        }
        let at = self.locate(p);
        let Some(r_max) = self.reach(at.cell, radius) else { return };
        // Only points nearer than `cut2` can still be among the k nearest: the radius until k
        // are found, then the k-th nearest so far.
        let mut cut2 = radius * radius;
        for r in 0..=r_max {
            self.shell(&at, r, cut2.next_up(), |pts, ids| {
                for (q, &id) in pts.iter().zip(ids) {
                    let d2 = dist2(p, q);
                    if d2 <= cut2 {
                        found.push((d2.to_bits() as u64) << 32 | id as u64);
                    }
                }
            });
            if found.len() >= k {
                if found.len() > k {
                    found.select_nth_unstable(k - 1);
                    found.truncate(k);
                }
                cut2 = f32::from_bits((found.iter().max().copied().unwrap_or(0) >> 32) as u32);
            }
            if found.len() == k && at.beyond2(r) > cut2 {
                break;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::register::KdTree;
    use crate::testing::xorshift;

    /// A bumpy sheet with a sparse cloud of strays around it: dense where ICP queries land,
    /// empty cells and far points elsewhere.
    fn cloud(rng: &mut impl FnMut() -> f64) -> Vec<[f32; 3]> {
        let mut pts = Vec::new();
        for i in 0..60 {
            for j in 0..50 {
                let (x, y) = (i as f32 * 0.7 + rng() as f32 * 0.3, j as f32 * 0.7 + rng() as f32 * 0.3);
                pts.push([x, y, 2.0 * (x * 0.1).sin() * (y * 0.13).cos()]);
            }
        }
        for _ in 0..200 {
            pts.push([rng() as f32 * 60.0 - 10.0, rng() as f32 * 50.0 - 8.0, rng() as f32 * 30.0 - 15.0]);
        }
        pts
    }

    #[test]
    fn bounded_searches_agree_with_the_k_d_tree() {
        let mut bits = xorshift(7);
        let mut rng = move || (bits() >> 11) as f64 / (1u64 << 53) as f64;
        let pts = cloud(&mut rng);
        let tree = KdTree::build(pts.clone(), "cloud").unwrap();
        for cell in [0.4f32, 1.3, 5.0] {
            let cells = CellIndex::build(pts.clone(), cell, "cloud").unwrap();
            for q in 0..600 {
                // Near the sheet, off it, and outside the cloud's box altogether.
                let p = [rng() as f32 * 70.0 - 15.0, rng() as f32 * 60.0 - 12.0, rng() as f32 * (if q % 3 == 0 { 40.0 } else { 6.0 }) - 3.0];
                for max_d in [0.3f32, 2.0, 7.5] {
                    let got = cells.nearest_within(&p, max_d * max_d);
                    let (i, d2) = tree.nearest(&p);
                    match got {
                        Some((j, e2)) => assert_eq!(e2, d2, "cell {cell}: {p:?} → {j}, tree {i}"),
                        None => assert!(d2 > max_d * max_d, "cell {cell}: {p:?} missed {i} at {d2} within {max_d}"),
                    }
                }
                let (k, radius) = (1 + q % 31, [0.5f32, 2.5, 9.0][q % 3]);
                let mut scratch = Vec::new();
                let mut got: Vec<f32> = cells.knn_within_unordered(&p, k, radius, &mut scratch).map(|q| dist2(&p, q)).collect();
                got.sort_by(f32::total_cmp);
                let want: Vec<f32> = tree.knn_within(&p, k, radius).iter().map(|r| r.1).collect();
                assert_eq!(got, want, "cell {cell}: {k} nearest within {radius} of {p:?}");
            }
        }
    }

    #[test]
    fn a_huge_box_gets_larger_cells_and_bad_sizes_are_refused() {
        let pts = vec![[0.0, 0.0, 0.0], [1e6, 1e6, 1e6], [1.0, 0.0, 0.0]];
        let cells = CellIndex::build(pts, 0.01, "far").unwrap();
        assert!(cells.dims.iter().product::<usize>() <= MAX_CELLS);
        assert_eq!(cells.nearest_within(&[0.9, 0.0, 0.0], 1.0).map(|r| r.0), Some(2));
        assert!(cells.nearest_within(&[5e5, 5e5, 5e5], 1.0).is_none());
        // Extremes of f32: neither the box nor a far query overflows.
        let wide = CellIndex::build(vec![[-3e38, 0.0, 0.0], [3e38, 0.0, 0.0]], 1.0, "wide").unwrap();
        assert_eq!(wide.nearest_within(&[3e38, 0.0, 0.0], 1.0).map(|r| r.0), Some(1));
        assert!(cells.nearest_within(&[-3e38, f32::MAX, 0.0], 1.0).is_none());
        assert!(CellIndex::build(vec![[0.0; 3]], 0.0, "zero").is_err());
        assert!(CellIndex::build(vec![[f32::NAN, 0.0, 0.0]], 1.0, "nan").is_err());
    }
}
