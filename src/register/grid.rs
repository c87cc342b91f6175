//! A view's points as a range image: projective data association for ICP (KinectFusion's
//! way of pairing points), without a k-d tree.
//!
//! A view's cloud is in its own camera frame, seen from the origin, so its points project to
//! a 2-D grid in the angular coordinates `(x/z, y/z)`: the organised depth image the view came
//! from, at about one point per cell (every point is kept: the points are sorted by cell, so
//! a cell's points lie together). A query point is projected the same way and compared with the points
//! of the few cells around its projection (`WINDOW`); normals are fitted to the points of a
//! 5 × 5 cell neighbourhood. Building costs one pass over the points; a query, a handful of
//! distance computations — where a k-d tree costs a descent and a backtrack per query, and a
//! tree build per view.
//!
//! What it gives up: the pair found is the nearest point *near the query's line of sight*, not
//! the nearest in space. ICP seeded close to the answer (the turntable's step, the previous
//! step) converges to the same point-to-plane optimum; from far off it needs more iterations.
//! A cloud seen from elsewhere (a merged model) must first be moved into a camera frame that
//! sees it (`Registrar`'s block step does).

use super::{check_points, dist2, RegisterError};

/// Half-width, in cells, of the neighbourhood searched around a query's projection.
const WINDOW: isize = 1;
/// Half-width, in cells, of the neighbourhood a normal is fitted to.
const NORMAL_WINDOW: isize = 2;
/// The grid's longest side; a sparser cloud gets coarser cells.
const MAX_SIDE: usize = 2048;

/// The points of one view indexed by their projection; results are indices into `points`.
pub struct RangeGrid {
    /// The points, sorted by cell (row by row).
    pub points: Vec<[f32; 3]>,
    /// Angular coordinates of the grid's corner, and cells per unit of `x/z`.
    u0: f32,
    v0: f32,
    inv_pitch: f32,
    width: usize,
    height: usize,
    /// Cell `c`'s points are `points[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
}

impl std::fmt::Debug for RangeGrid {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "RangeGrid({} points, {} × {} cells)", self.points.len(), self.width, self.height)
    }
}

impl RangeGrid {
    /// Indexes `points` (a cloud in the frame of the camera that saw it: every point in front,
    /// `z > 0`), reordered by cell. The cell size follows the cloud's own sampling. `what`
    /// names the set in errors.
    pub fn build(points: Vec<[f32; 3]>, what: &str) -> Result<RangeGrid, RegisterError> {
        check_points(&points, what)?;
        if points.len() >= u32::MAX as usize {
            return Err(RegisterError::Param(format!("{what}: {} points; a range grid holds fewer than 2³² − 1", points.len())));
        }
        let behind = points.iter().filter(|p| !(p[2] > 0.0)).count();
        if behind > 0 {
            return Err(RegisterError::Param(format!("{what}: {behind} of {} points are not in front of the camera (z ≤ 0); a range grid needs a cloud in the frame of the camera that saw it", points.len())));
        }
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for p in &points {
            let a = [p[0] / p[2], p[1] / p[2]];
            for k in 0..2 {
                lo[k] = lo[k].min(a[k]);
                hi[k] = hi[k].max(a[k]);
            }
        }
        let span = [(hi[0] - lo[0]).max(1e-9), (hi[1] - lo[1]).max(1e-9)];
        // First guess: the points spread evenly over their bounding box. Then the area they
        // really cover (cells hit at that pitch) over their number: about a point per cell.
        let guess = ((span[0] * span[1]) / points.len() as f32).sqrt().max(span[0].max(span[1]) / MAX_SIDE as f32);
        let covered = occupied_cells(&points, lo, guess, span) as f32 * guess * guess;
        let pitch = (covered / points.len() as f32).sqrt().max(span[0].max(span[1]) / (MAX_SIDE - 1) as f32);
        let inv_pitch = 1.0 / pitch;
        let width = ((span[0] * inv_pitch) as usize + 1).min(MAX_SIDE);
        let height = ((span[1] * inv_pitch) as usize + 1).min(MAX_SIDE);
        // A counting sort by cell.
        let cell: Vec<u32> = points.iter().map(|p| cell_of(p, lo, inv_pitch, width, height) as u32).collect();
        let mut starts = vec![0u32; width * height + 1];
        for &c in &cell {
            starts[c as usize + 1] += 1;
        }
        for c in 0..width * height {
            starts[c + 1] += starts[c];
        }
        let mut next = starts.clone();
        let mut sorted = vec![[0f32; 3]; points.len()];
        for (p, &c) in points.iter().zip(&cell) {
            sorted[next[c as usize] as usize] = *p;
            next[c as usize] += 1;
        }
        Ok(RangeGrid { points: sorted, u0: lo[0], v0: lo[1], inv_pitch, width, height, starts })
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Grid coordinates of a point's projection (may lie outside the grid), or None behind
    /// the camera.
    #[inline]
    fn project(&self, p: &[f32; 3]) -> Option<(isize, isize)> {
        if !(p[2] > 0.0) {
            return None;
        }
        let inv_z = 1.0 / p[2];
        let u = (p[0] * inv_z - self.u0) * self.inv_pitch;
        let v = (p[1] * inv_z - self.v0) * self.inv_pitch;
        // Far outside (or not finite): nothing near it.
        let lim = (MAX_SIDE * 4) as f32;
        if !(u > -lim && u < lim && v > -lim && v < lim) {
            return None;
        }
        // floor() without a libm call: truncation, one less below zero.
        let floor = |x: f32| {
            let i = x as isize;
            i - isize::from((i as f32) > x)
        };
        Some((floor(u), floor(v)))
    }

    /// Calls `f` with the index of every point in the cells within `half` cells of `(u, v)`.
    #[inline]
    fn around(&self, (u, v): (isize, isize), half: isize, mut f: impl FnMut(usize)) {
        let (w, h) = (self.width as isize, self.height as isize);
        let (x0, x1) = ((u - half).max(0), (u + half + 1).min(w));
        if x0 >= x1 {
            return;
        }
        for y in (v - half).max(0)..(v + half + 1).min(h) {
            // A row's cells are consecutive, so are their points.
            let row = y as usize * self.width;
            let (a, b) = (self.starts[row + x0 as usize], self.starts[row + x1 as usize]);
            for i in a..b {
                f(i as usize);
            }
        }
    }

    /// The point nearest `p` among those projecting near it: `(index, squared distance)`, or
    /// None when no point does.
    #[inline]
    pub fn nearest(&self, p: &[f32; 3]) -> Option<(usize, f32)> {
        let at = self.project(p)?;
        let mut best: Option<(usize, f32)> = None;
        self.around(at, WINDOW, |i| {
            let q = &self.points[i];
            let d2 = dist2(p, q);
            if best.is_none_or(|(_, b)| d2 < b) {
                best = Some((i, d2));
            }
        });
        best
    }

    /// The normal at point `i` by principal component analysis of the points of the 5 × 5
    /// cells around its projection within `radius` of it (sign arbitrary); None with fewer than
    /// three such points or no clear normal.
    pub fn normal_at(&self, i: usize, radius: f32) -> Option<[f32; 3]> {
        let p = self.points[i];
        let at = self.project(&p)?;
        let r2 = radius * radius;
        let mut n = 0usize;
        let mut s = [0f64; 3];
        let mut ss = [0f64; 6];
        self.around(at, NORMAL_WINDOW, |j| {
            let q = &self.points[j];
            let d = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
            if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= r2 {
                let d = [d[0] as f64, d[1] as f64, d[2] as f64];
                n += 1;
                for k in 0..3 {
                    s[k] += d[k];
                }
                ss[0] += d[0] * d[0];
                ss[1] += d[0] * d[1];
                ss[2] += d[0] * d[2];
                ss[3] += d[1] * d[1];
                ss[4] += d[1] * d[2];
                ss[5] += d[2] * d[2];
            }
        });
        if n < 3 {
            return None;
        }
        let m = [s[0] / n as f64, s[1] / n as f64, s[2] / n as f64];
        let inv = 1.0 / n as f64;
        let cov = [ss[0] * inv - m[0] * m[0], ss[1] * inv - m[0] * m[1], ss[2] * inv - m[0] * m[2], ss[3] * inv - m[1] * m[1], ss[4] * inv - m[1] * m[2], ss[5] * inv - m[2] * m[2]];
        smallest_eigenvector(&cov).map(|v| [v[0] as f32, v[1] as f32, v[2] as f32])
    }
}

/// Cells hit when the points are binned at `pitch` (for the first guess of the cell size).
fn occupied_cells(points: &[[f32; 3]], lo: [f32; 2], pitch: f32, span: [f32; 2]) -> usize {
    let inv = 1.0 / pitch;
    let width = ((span[0] * inv) as usize + 1).min(MAX_SIDE);
    let height = ((span[1] * inv) as usize + 1).min(MAX_SIDE);
    let mut hit = vec![false; width * height];
    for p in points {
        hit[cell_of(p, lo, inv, width, height)] = true;
    }
    hit.iter().filter(|&&h| h).count()
}

#[inline]
fn cell_of(p: &[f32; 3], lo: [f32; 2], inv_pitch: f32, width: usize, height: usize) -> usize {
    let u = (((p[0] / p[2] - lo[0]) * inv_pitch) as usize).min(width - 1);
    let v = (((p[1] / p[2] - lo[1]) * inv_pitch) as usize).min(height - 1);
    v * width + u
}

/// The unit eigenvector of the smallest eigenvalue of a symmetric 3 × 3 matrix given as
/// `[a00, a01, a02, a11, a12, a22]` (closed-form eigenvalues, then the largest cross product
/// of two rows of `A − λI`). None when that eigenvalue is not separated from the next (a
/// line or an isotropic blob has no normal) or the matrix is not finite.
pub fn smallest_eigenvector(a: &[f64; 6]) -> Option<[f64; 3]> {
    smallest_eigenpair(a).map(|(v, _)| v)
}

/// [`smallest_eigenvector`] and its eigenvalue.
pub fn smallest_eigenpair(a: &[f64; 6]) -> Option<([f64; 3], f64)> {
    let [a00, a01, a02, a11, a12, a22] = *a;
    let scale = a.iter().fold(0f64, |m, v| m.max(v.abs()));
    if !(scale > 0.0 && scale.is_finite()) {
        return None;
    }
    // Eigenvalues by the trigonometric method (Smith 1961), on the matrix scaled to O(1).
    let (b00, b01, b02, b11, b12, b22) = (a00 / scale, a01 / scale, a02 / scale, a11 / scale, a12 / scale, a22 / scale);
    let q = (b00 + b11 + b22) / 3.0;
    let p1 = b01 * b01 + b02 * b02 + b12 * b12;
    let p2 = (b00 - q).powi(2) + (b11 - q).powi(2) + (b22 - q).powi(2) + 2.0 * p1;
    let p = (p2 / 6.0).sqrt();
    if !(p > 1e-12) {
        return None;
    }
    let (c00, c11, c22) = ((b00 - q) / p, (b11 - q) / p, (b22 - q) / p);
    let (c01, c02, c12) = (b01 / p, b02 / p, b12 / p);
    let det = c00 * (c11 * c22 - c12 * c12) - c01 * (c01 * c22 - c12 * c02) + c02 * (c01 * c12 - c11 * c02);
    let phi = (det / 2.0).clamp(-1.0, 1.0).acos() / 3.0;
    let largest = q + 2.0 * p * phi.cos();
    let smallest = q + 2.0 * p * (phi + 2.0 * std::f64::consts::FRAC_PI_3).cos();
    let middle = 3.0 * q - largest - smallest;
    if !(middle - smallest > 1e-9 * (largest - smallest).max(1e-300)) {
        return None;
    }
    let rows = [[b00 - smallest, b01, b02], [b01, b11 - smallest, b12], [b02, b12, b22 - smallest]];
    let cross = |a: &[f64; 3], b: &[f64; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let norm2 = |v: &[f64; 3]| v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    let candidates = [cross(&rows[0], &rows[1]), cross(&rows[0], &rows[2]), cross(&rows[1], &rows[2])];
    let best = candidates.iter().max_by(|a, b| norm2(a).total_cmp(&norm2(b)))?;
    let len = norm2(best).sqrt();
    if !(len > 0.0) {
        return None;
    }
    Some(([best[0] / len, best[1] / len, best[2] / len], smallest * scale))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, SymmetricEigen};

    /// A bumpy surface seen from the origin at about 400 mm, `n`² points 0.5 mm apart.
    fn surface(n: usize) -> Vec<[f32; 3]> {
        let mut pts = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (i as f32 * 0.5 - n as f32 * 0.25, j as f32 * 0.5 - n as f32 * 0.25);
                pts.push([x, y, 400.0 + 5.0 * (x / 9.0).sin() + 0.2 * y]);
            }
        }
        pts
    }

    #[test]
    fn nearest_agrees_with_the_exact_search_near_the_surface() {
        let pts = surface(120);
        let grid = RangeGrid::build(pts.clone(), "surface").unwrap();
        let tree = crate::register::KdTree::build(grid.points.clone(), "surface").unwrap();
        let (mut same, mut total) = (0, 0);
        for (k, p) in pts.iter().enumerate().step_by(37) {
            // Off the surface by up to 0.3 mm, the way a nearly registered source point is.
            let q = [p[0] + 0.11 * ((k % 5) as f32 - 2.0), p[1] - 0.07, p[2] + 0.3];
            let (i, d2) = grid.nearest(&q).expect("a point projects near every query over the surface");
            let (j, e2) = tree.nearest(&q);
            total += 1;
            same += usize::from(i == j);
            assert!(d2 <= e2 + 1e-6, "grid pair {d2} against exact {e2}");
        }
        assert_eq!(same, total, "identical pairs");
        // Behind the camera and far outside: nothing.
        assert!(grid.nearest(&[0.0, 0.0, -5.0]).is_none());
        assert!(grid.nearest(&[1e6, 0.0, 400.0]).is_none());
    }

    #[test]
    fn normals_match_the_surface_and_eigenvectors_match_nalgebra() {
        let pts = surface(60);
        let grid = RangeGrid::build(pts.clone(), "surface").unwrap();
        let i = grid.points.iter().position(|p| *p == pts[30 * 60 + 30]).unwrap();
        let n = grid.normal_at(i, 3.0).unwrap();
        let x = grid.points[i][0];
        // z = 400 + 5 sin(x/9) + 0.2 y: normal ∝ (−5/9 cos(x/9), −0.2, 1).
        let expect = nalgebra::Vector3::new(-5.0 / 9.0 * (x / 9.0).cos(), -0.2, 1.0).normalize();
        let got = nalgebra::Vector3::new(n[0], n[1], n[2]);
        assert!(got.dot(&expect).abs() > 0.999, "{got:?} against {expect:?}");
        for a in [[4.0, 1.0, 0.5, 3.0, 0.2, 0.1], [1.0, 0.0, 0.0, 2.0, 0.0, 3.0], [2.0, -0.7, 0.3, 1.0, 0.4, 0.05]] {
            let m: Matrix3<f64> = Matrix3::new(a[0], a[1], a[2], a[1], a[3], a[4], a[2], a[4], a[5]);
            let eig = SymmetricEigen::new(m);
            let k = (0..3usize).min_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j])).unwrap();
            let v = smallest_eigenvector(&a).unwrap();
            let dot = (0..3).map(|r| v[r] * eig.eigenvectors[(r, k)]).sum::<f64>();
            assert!(dot.abs() > 1.0 - 1e-9, "{a:?}: {v:?}");
        }
        // Isotropic: no normal.
        assert!(smallest_eigenvector(&[1.0, 0.0, 0.0, 1.0, 0.0, 1.0]).is_none());
    }

    #[test]
    fn a_cloud_behind_the_camera_is_refused_by_name() {
        let e = RangeGrid::build(vec![[0.0, 0.0, 10.0], [1.0, 0.0, -3.0]], "view 7").unwrap_err().to_string();
        assert!(e.contains("view 7") && e.contains("z ≤ 0"), "{e}");
    }
}
