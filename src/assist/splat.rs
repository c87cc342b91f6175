//! The Kalman-predicted motion carried into this frame's search intervals: each previous
//! point moved, projected and splatted with its uncertainty into per-pixel `lo`/`hi` (or
//! straight into the tiles). The paper's rule is in paper.rs.

use super::region::MaskRows;
use super::tiles::{self, Granularity};
use super::{Assistant, Plan};

impl Assistant {
    /// The Kalman prediction of every previous point into `lo`/`hi`.
    #[inline(always)]
    pub(super) fn splat_predicted(&mut self, gap: u64, lag: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        let w = self.size.0;
        let prev = self.prev.as_ref().expect("planned with a previous frame");
        let Some((m, cov)) = self.filter.predict(gap, lag) else { return };
        let cam = self.cam;
        let (k_sigma, s2) = (self.params.predicted_k as f32, self.params.predicted_sigma_px.powi(2) as f32);
        let min_half = self.params.min_half_width_px as f32;
        // In f32, per previous point with ray (u, v, 1) and 1/Z = (d − dcx)/(−tx):
        // Q·(1/Z) = R·(u, v, 1) + t/Z, so one division gives the projection of the moved point.
        let rot = m.rotation.to_rotation_matrix().into_inner().cast::<f32>();
        let t = m.translation.vector.cast::<f32>();
        // Var(Z) of a moved point q under a twist perturbation: δZ = δω_x·q_y − δω_y·q_x + δv_z.
        let c = |i: usize, j: usize| cov[(i, j)] as f32;
        let (c00, c01, c11, c05, c15, c55) = (c(0, 0), c(0, 1), c(1, 1), c(0, 5), c(1, 5), c(5, 5));
        let (fx, fy, cx, cy, dcx, tx) = (cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32, cam.dcx as f32, cam.tx as f32);
        let prev_d = prev.disparity.values();
        let (lo, hi, region) = (&mut self.lo, &mut self.hi, self.region);
        let (ifx, ify, inv_mtx) = (1.0 / fx, 1.0 / fy, -1.0 / tx);
        let u_col = region.column_rays(cx, ifx);
        let n = u_col.len();
        assert!(w * self.size.1 <= i32::MAX as usize, "an image of {w}×{} pixels is too large to index in i32", self.size.1);
        // Per row: the projections and bounds of every point, branch-free so that it
        // vectorises (NaN where there is no point or it moves behind the camera), then the
        // splats.
        let (mut xs, mut ys, mut los, mut his) = (vec![0i32; n], vec![-1i32; n], vec![0f32; n], vec![0f32; n]);
        // At tile granularity, each point's tile and the tiles its splat crosses into, found
        // in the vector loop with the projection: the scatter then only widens the hulls.
        let (mut tile_of, mut crosses) = (vec![0u32; n], vec![0u32; n]);
        let cols = self.tiles.cols() as u32;
        let tiled = self.params.granularity == Granularity::Tile;
        let tiles = &mut self.tiles;
        // A prediction splats onto the 2 × 2 pixels from (⌊px⌋, ⌊py⌋): they lie inside the
        // region exactly when x0 ≤ px < x1 − 1 and y0 ≤ py < y1 − 1 (NaN fails).
        let (rx0, rx1, ry0, ry1) = (region.x0 as f32, (region.x1 - 1) as f32, region.y0 as f32, (region.y1 - 1) as f32);
        let (r00, r10, r20) = (rot[(0, 0)], rot[(1, 0)], rot[(2, 0)]);
        for y in region.ys() {
            let v = (y as f32 - cy) * ify;
            let base = rot.column(1) * v + rot.column(2);
            let d_row = &prev_d[y * w + region.x0..y * w + region.x1];
            for k in 0..n {
                let d = d_row[k];
                let iz = (d - dcx) * inv_mtx;
                let u = u_col[k];
                // The moved point times 1/Z.
                let (qx, qy, qz) = (base.x + r00 * u + t.x * iz, base.y + r10 * u + t.y * iz, base.z + r20 * u + t.z * iz);
                let s = 1.0 / qz;
                let (px, py, pd) = (fx * qx * s + cx, fy * qy * s + cy, dcx - tx * iz * s);
                // Var(d) = (∂d/∂Z)²·Var(Z) with the moved point Q = q/iz (mm) and
                // ∂d/∂Z = tx/Q_z² = tx·iz²·s², written without dividing by iz:
                // Var(d) = tx²·s⁴·[iz²·(q_y²c00 − 2q_xq_y c01 + q_x²c11) + 2·iz³·(q_y c05 − q_x c15) + iz⁴·c55].
                let (iz2, s2q) = (iz * iz, s * s);
                let var_d = (tx * tx * s2q * s2q * iz2 * ((qy * qy * c00 - 2.0 * qx * qy * c01 + qx * qx * c11) + 2.0 * iz * (qy * c05 - qx * c15) + iz2 * c55)).max(0.0);
                let half = (k_sigma * (var_d + s2).sqrt()).max(min_half);
                // NaN (no disparity), points behind the camera and points moved behind it fail.
                let ok = iz > 0.0 && qz > 0.0;
                let inside = ok & (px >= rx0) & (px < rx1) & (py >= ry0) & (py < ry1);
                // Non-negative and inside the image once selected: truncation is the floor,
                // and the plain conversion is exact (it vectorises, unlike `as`).
                let (px, py) = (if inside { px } else { 0.0 }, if inside { py } else { 0.0 });
                // SAFETY: px and py lie in [0, w) and [0, h), far inside i32.
                let (x0, y0) = unsafe { (px.to_int_unchecked::<i32>(), py.to_int_unchecked::<i32>()) };
                (xs[k], ys[k]) = (x0, if inside { y0 } else { -1 });
                (tile_of[k], crosses[k]) = tiles::splat_tile(x0 as u32, y0 as u32, cols);
                los[k] = pd - half;
                his[k] = pd + half;
            }
            for k in 0..n {
                if ys[k] < 0 {
                    continue;
                }
                let (a, b) = (los[k], his[k]);
                if tiled {
                    // Straight into the tiles: no per-pixel map (tiles.rs).
                    tiles.add_splat(tile_of[k] as usize, crosses[k], a, b);
                    continue;
                }
                let i = ys[k] as usize * w + xs[k] as usize;
                for j in [i, i + 1, i + w, i + w + 1] {
                    lo[j] = lo[j].min(a);
                    hi[j] = hi[j].max(b);
                }
            }
        }
        if tiled {
            // Counted per tile (tiles.rs).
            return;
        }
        let masks = MaskRows::new(mask, w, &region);
        let mut singles = 0;
        for y in region.ys() {
            let row = y * w + region.x0..y * w + region.x1;
            singles += masks.row(y).iter().zip(&lo[row.clone()]).zip(&hi[row]).filter(|((&m, &a), &b)| m != 0 && a <= b).count();
        }
        plan.single_px = singles;

    }
}
