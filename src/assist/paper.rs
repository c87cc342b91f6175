//! The paper's registration constraint (its two cases, weight w) carried into this frame's
//! search intervals; the rule is in the module docs of `assist`.
//!
//! One pass per row of the region computes every previous point's projected sphere radius
//! ρ, the bounds `d_prev ± ρ` of the pixels of case 1 (the single circle) and — at pixel
//! granularity — their final intervals, clipped and rounded outwards, straight into the
//! plan's map. Pixels of case 2 (the union of the spheres whose left projections hold the
//! pixel) are flagged in that pass and gathered after it; pixels neither case reaches are
//! holes, filled from the bounds around them (`Assistant::fill_holes`).

use nalgebra::{Matrix3, Vector3};

use super::motion;
use super::region::{ceil, floor, for_each_set, round_row, MaskRows};
use super::{Assistant, Plan};
use crate::stereo::DisparityIntervals;

/// Columns of spheres one union pixel gathers from at a time (eight `f32` lanes).
const GATHER: usize = 8;

/// Pixel granularity: the plan's map, written in place, and the holes found in it.
pub(super) struct PixelOut<'a> {
    pub(super) iv: &'a mut DisparityIntervals,
    /// Foreground pixels neither case reached (or whose bounds miss the range), `(x, y)`
    /// sorted by row, then column.
    pub(super) holes: &'a mut Vec<(usize, usize)>,
}

impl Assistant {
    /// The paper's two cases into `lo`/`hi` (every pixel of the region), and with `out` into
    /// the plan's intervals (see the module docs).
    #[inline(always)]
    pub(super) fn splat_paper(&mut self, weight: f64, gap: u64, lag: u64, mask: Option<&[u8]>, plan: &mut Plan, mut out: Option<PixelOut>) {
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
        let (lo, hi, region, range) = (&mut self.lo, &mut self.hi, self.region, self.range);
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
        let mut hole_row = vec![0u8; region.x1 - region.x0];
        // The largest radius of each row of the region.
        let mut row_rho_max = Vec::with_capacity(region.y1 - region.y0);
        for y in region.ys() {
            let v = (y as f32 - cy) * ify;
            // A·(u, v, 1) = A·(0, v, 1) + u·A[:, 0].
            let base = a_m * Vector3::new(0.0, v, 1.0);
            let row = y * w + region.x0..y * w + region.x1;
            let n = row.len();
            let (d_row, rho_row) = (&prev_d[row.clone()], &mut rho[row.clone()]);
            let (lo_row, hi_row, un_row) = (&mut lo[row.clone()], &mut hi[row.clone()], &mut union_needed[row.clone()]);
            let (m_row, pm_row) = (masks.row(y), prev_masks.row(y));
            // One branch-free pass, so that it vectorises: ρ (NaN where there is no disparity
            // or the point lies behind the camera), the row's largest ρ as the bits of a
            // positive float (integers reduce in vector lanes; floats would not, for NaN),
            // and case 1 — a single circle around the previous correspondence.
            let (mut singles, mut unions, mut bits_max) = (0u32, 0u8, 0u32);
            for k in 0..n {
                let d = d_row[k];
                let inv_z = (d - dcx) * inv_mtx;
                let u = u_col[k];
                let (px, py, pz) = (base.x + a00 * u + bx * inv_z, base.y + a10 * u + by * inv_z, base.z + a20 * u + bz * inv_z);
                let r = (scale * (px * px + py * py + pz * pz).sqrt()).min(max_radius).max(min_half);
                let point = inv_z > 0.0;
                let r = if point { r } else { f32::NAN };
                rho_row[k] = r;
                bits_max = bits_max.max(if point { r.to_bits() } else { 0 });
                let here = m_row[k] != 0;
                let single = here & point & (pm_row[k] != 0);
                lo_row[k] = if single { d - r } else { f32::INFINITY };
                hi_row[k] = if single { d + r } else { f32::NEG_INFINITY };
                let union = (here & !single) as u8;
                un_row[k] = union;
                singles += single as u32;
                unions |= union;
            }
            let row_max = f32::from_bits(bits_max);
            row_rho_max.push(row_max);
            max_rho = max_rho.max(row_max);
            plan.single_px += singles as usize;
            any_union |= unions != 0;
            if let Some(out) = out.as_mut() {
                // Case 1's intervals; the union pixels are written once gathered.
                let (out_lo, out_hi) = out.iv.row_mut(y);
                if round_row(m_row, un_row, lo_row, hi_row, &mut out_lo[region.xs()], &mut out_hi[region.xs()], &mut hole_row[..n], range) {
                    for_each_set(&hole_row[..n], |k| out.holes.push((region.x0 + k, y)));
                }
            }
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
        let mut union_holes = false;
        let (r0, r1) = (range.0 as f32, range.1 as f32);
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
                        let (at, len) = (row + c0, (sx1 - c0).min(GATHER));
                        // Whole lanes read in place where the map allows (no copy of a
                        // varying length); the lanes past the region's columns are NaN.
                        let (mut r_l, d_l): ([f32; GATHER], [f32; GATHER]) = match (rho.get(at..at + GATHER), prev_d.get(at..at + GATHER)) {
                            (Some(r), Some(d)) => (r.try_into().expect("GATHER lanes"), d.try_into().expect("GATHER lanes")),
                            _ => {
                                let (mut r_l, mut d_l) = ([f32::NAN; GATHER], [0f32; GATHER]);
                                r_l[..len].copy_from_slice(&rho[at..at + len]);
                                d_l[..len].copy_from_slice(&prev_d[at..at + len]);
                                (r_l, d_l)
                            }
                        };
                        for (k, r) in r_l.iter_mut().enumerate() {
                            *r = if k < len { *r } else { f32::NAN };
                        }
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
                if let Some(out) = out.as_mut() {
                    // Clipped, then rounded outwards, as `round_row` does.
                    let (a, b) = (a.max(r0), b.min(r1));
                    if a <= b {
                        out.iv.set(x, y, Some((floor(a) as i32, ceil(b) as i32)));
                    } else {
                        out.holes.push((x, y));
                        union_holes = true;
                    }
                }
            }
        }
        plan.union_px = union_px;
        if let (Some(out), true) = (out, union_holes) {
            out.holes.sort_unstable_by_key(|&(x, y)| (y, x));
        }
    }
}
