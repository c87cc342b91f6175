//! The two ways previous points are carried into this frame's search intervals: the paper's
//! registration constraint (its two cases, weight w) and the Kalman-predicted motion. Both
//! splat each previous pixel's sphere (or prediction ± uncertainty) into per-pixel `lo`/`hi`.

use nalgebra::{Matrix3, Vector3};

use super::motion;
use super::region::{ceil, floor, for_each_set, MaskRows};
use super::tiles::{self, Granularity};
use super::{Assistant, Plan};

/// Columns of spheres one union pixel gathers from at a time (eight `f32` lanes).
const GATHER: usize = 8;

impl Assistant {
    /// The paper's two cases into `lo`/`hi` (see the module docs).
    #[inline(always)]
    pub(super) fn splat_paper(&mut self, weight: f64, gap: u64, lag: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        let (w, h) = self.size;
        let prev = self.prev.as_ref().expect("planned with a previous frame");
        let step = self.steps.back().expect("planned with a step").per_frame;
        // Lag: widen by the relative change between the last two steps (at least 10 %).
        let kappa = match (self.steps.len(), self.steps.front()) {
            (2, Some(older)) => {
                let (a, b) = (motion::log(&older.per_frame), motion::log(&step));
                ((b - a).norm() / b.norm().max(1e-12)).max(0.1)
            }
            _ => 0.1,
        };
        let widen = gap as f64 * (1.0 + lag as f64 * kappa);
        // P − M⁻¹·P = A·P + b with A = I − R⁻¹, b = R⁻¹·t.
        let back = step.inverse();
        let a_m = Matrix3::identity() - back.rotation.to_rotation_matrix().into_inner();
        let b_v = -back.translation.vector;
        let cam = self.cam;
        let min_half = self.params.min_half_width_px as f32;
        let (max_radius, scale) = (self.params.max_radius_px as f32, cam.fx * weight * widen);
        let prev_d = prev.disparity.values();
        let (lo, hi, region) = (&mut self.lo, &mut self.hi, self.region);
        // The projected radius (pixels) of every previous point's sphere, once:
        // ρ = fx·w·r/Z = fx·w·|A·(u, v, 1) + b/Z|, at least `min_half`; NaN where no point.
        self.rho.resize(w * h, f32::NAN);
        let rho = &mut self.rho;
        let mut max_rho = 0f32;
        let (a_m, b_v, scale) = (a_m.cast::<f32>(), b_v.cast::<f32>(), scale as f32);
        let (cx, cy, dcx) = (cam.cx as f32, cam.cy as f32, cam.dcx as f32);
        let (ifx, ify, inv_mtx) = (1.0 / cam.fx as f32, 1.0 / cam.fy as f32, -1.0 / cam.tx as f32);
        self.union_needed.resize(w * h, 0);
        let union_needed = &mut self.union_needed;
        let mut any_union = false;
        let (a00, a10, a20) = (a_m[(0, 0)], a_m[(1, 0)], a_m[(2, 0)]);
        let u_col = region.column_rays(cx, ifx);
        let (masks, prev_masks) = (MaskRows::new(mask, w, &region), MaskRows::new(prev.mask.as_deref(), w, &region));
        let (bx, by, bz) = (b_v.x, b_v.y, b_v.z);
        // The largest radius of each row of the region.
        let mut row_rho_max = Vec::with_capacity(region.y1 - region.y0);
        for y in region.ys() {
            let v = (y as f32 - cy) * ify;
            // A·(u, v, 1) = A·(0, v, 1) + u·A[:, 0].
            let base = a_m * Vector3::new(0.0, v, 1.0);
            let row = y * w + region.x0..y * w + region.x1;
            let n = row.len();
            let (d_row, rho_row) = (&prev_d[row.clone()], &mut rho[row.clone()]);
            // Branch-free over the row, so that it vectorises: NaN (no disparity) and points
            // behind the camera give ρ = NaN.
            for k in 0..n {
                let inv_z = (d_row[k] - dcx) * inv_mtx;
                let u = u_col[k];
                let (px, py, pz) = (base.x + a00 * u + bx * inv_z, base.y + a10 * u + by * inv_z, base.z + a20 * u + bz * inv_z);
                let r = (scale * (px * px + py * py + pz * pz).sqrt()).min(max_radius).max(min_half);
                rho_row[k] = if inv_z > 0.0 { r } else { f32::NAN };
            }
            // The row's largest radius, as the bits of a positive float (integers reduce in
            // vector lanes; floats would not, for NaN). NaN fails the comparison.
            let row_max = f32::from_bits(rho_row.iter().fold(0u32, |m, &r| m.max(if r > 0.0 { r.to_bits() } else { 0 })));
            row_rho_max.push(row_max);
            max_rho = max_rho.max(row_max);
            let (lo_row, hi_row, un_row) = (&mut lo[row.clone()], &mut hi[row.clone()], &mut union_needed[row.clone()]);
            let (m_row, pm_row) = (masks.row(y), prev_masks.row(y));
            let (mut singles, mut unions) = (0usize, 0u8);
            for k in 0..n {
                let r = rho_row[k];
                let here = m_row[k] != 0;
                // Case 1: a single circle around the previous correspondence.
                let single = here & !r.is_nan() & (pm_row[k] != 0);
                let d = d_row[k];
                lo_row[k] = if single { d - r } else { f32::INFINITY };
                hi_row[k] = if single { d + r } else { f32::NEG_INFINITY };
                let union = (here & !single) as u8;
                un_row[k] = union;
                singles += single as usize;
                unions |= union;
            }
            plan.single_px += singles;
            any_union |= unions != 0;
        }
        if !any_union {
            return;
        }
        // Case 2: the union of the spheres whose left projections contain the pixel. Most
        // spheres are small: each such pixel gathers from the points within `reach` (the
        // 99th percentile of the radii); the few larger spheres are splatted onto the pixels
        // their discs cover. (The hull of a union does not mind a sphere counted twice.)
        // Which spheres are gathered and which splatted changes nothing in the union, only the
        // time: the radii of every fourth row are enough to choose.
        let mut hist = [0u32; 66];
        let mut count = 0u32;
        for y in region.ys().step_by(4) {
            for &r in &rho[y * w + region.x0..y * w + region.x1] {
                if r.is_finite() {
                    hist[((r * 2.0) as usize).min(65)] += 1;
                    count += 1;
                }
            }
        }
        let (mut acc, mut bin) = (0u32, 0usize);
        while bin < 65 && (acc + hist[bin]) * 100 < count * 99 {
            acc += hist[bin];
            bin += 1;
        }
        let reach_f = ((bin + 1) as f32 * 0.5).min(max_rho);
        let reach = reach_f.ceil() as i64;
        for y in region.ys() {
            if row_rho_max[y - region.y0] <= reach_f {
                continue;
            }
            for x in region.xs() {
                let r = rho[y * w + x];
                if !(r > reach_f) {
                    continue;
                }
                let d = prev_d[y * w + x];
                let (xi, yi, rr) = (x as i64, y as i64, r.ceil() as i64);
                for yy in (yi - rr).max(region.y0 as i64)..=(yi + rr).min(region.y1 as i64 - 1) {
                    let dy = (yy - yi) as f32;
                    let c2 = r * r - dy * dy;
                    if c2 < 0.0 {
                        continue;
                    }
                    let c = c2.sqrt();
                    for xx in (ceil(xi as f32 - c) as i64).max(region.x0 as i64)..=(floor(xi as f32 + c) as i64).min(region.x1 as i64 - 1) {
                        let j = yy as usize * w + xx as usize;
                        if union_needed[j] != 0 {
                            let base = d + (xx - xi) as f32;
                            lo[j] = lo[j].min(base - c);
                            hi[j] = hi[j].max(base + c);
                        }
                    }
                }
            }
        }
        let mut union_px = 0;
        let mut pixels = Vec::new();
        for y in region.ys() {
            pixels.clear();
            for_each_set(&union_needed[y * w + region.x0..y * w + region.x1], |k| pixels.push(region.x0 + k));
            for &x in &pixels {
                let j = y * w + x;
                let (xi, yi) = (x as i64, y as i64);
                let (sx0, sx1) = ((xi - reach).max(region.x0 as i64) as usize, ((xi + reach).min(region.x1 as i64 - 1) + 1) as usize);
                // Per lane of GATHER columns, reduced at the end: fixed-width lanes vectorise
                // (the row of spheres, 2·reach + 1 wide, is taken GATHER at a time).
                let (mut a, mut b) = ([f32::INFINITY; GATHER], [f32::NEG_INFINITY; GATHER]);
                for sy in (yi - reach).max(region.y0 as i64)..=(yi + reach).min(region.y1 as i64 - 1) {
                    let dy2 = ((yi - sy) * (yi - sy)) as f32;
                    let row = sy as usize * w;
                    for c0 in (sx0..sx1).step_by(GATHER) {
                        let len = (sx1 - c0).min(GATHER);
                        let (mut r_l, mut d_l) = ([f32::NAN; GATHER], [0f32; GATHER]);
                        r_l[..len].copy_from_slice(&rho[row + c0..row + c0 + len]);
                        d_l[..len].copy_from_slice(&prev_d[row + c0..row + c0 + len]);
                        // Branch-free: left pixel x lies on the sphere's left chord of row y
                        // when |x − sx| ≤ c = √(r² − dy²); the right chord maps it to
                        // d_prev + (x − sx) ± c. NaN (no point, or past the row) fails the
                        // comparison.
                        // (Differences of small integers in i32, converted in vector lanes.)
                        let dx0 = x as i32 - c0 as i32;
                        for k in 0..GATHER {
                            let (r, dx) = (r_l[k], (dx0 - k as i32) as f32);
                            let c2 = r * r - dy2;
                            let c = c2.max(0.0).sqrt();
                            let inside = c2 >= 0.0 && dx.abs() <= c;
                            let base = d_l[k] + dx;
                            a[k] = if inside && base - c < a[k] { base - c } else { a[k] };
                            b[k] = if inside && base + c > b[k] { base + c } else { b[k] };
                        }
                    }
                }
                let (a, b) = (a.iter().fold(lo[j], |m, &v| if v < m { v } else { m }), b.iter().fold(hi[j], |m, &v| if v > m { v } else { m }));
                lo[j] = a;
                hi[j] = b;
                union_px += (a <= b) as usize;
            }
        }
        plan.union_px = union_px;
    }

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
                los[k] = pd - half;
                his[k] = pd + half;
            }
            for k in 0..n {
                if ys[k] < 0 {
                    continue;
                }
                let (a, b) = (los[k], his[k]);
                let (x0, y0) = (xs[k] as usize, ys[k] as usize);
                if tiled {
                    // Straight into the tiles: no per-pixel map (tiles.rs).
                    let (t, right, down) = tiles::splat_tile(x0, y0, tiles.cols());
                    tiles.add_splat(t, right, down, a, b);
                    continue;
                }
                let i = y0 * w + x0;
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
