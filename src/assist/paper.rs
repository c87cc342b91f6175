//! The paper's registration constraint (its two cases, weight w) carried into this frame's
//! search intervals; the rule is in the module docs of `assist`.
//!
//! One pass per row of the region computes every previous point's projected sphere radius
//! ρ, the bounds `d_prev ± ρ` of the pixels of case 1 (the single circle) and — at pixel
//! granularity — their final intervals, clipped and rounded outwards, straight into the
//! plan's map. Pixels of case 2 (the union of the spheres whose left projections hold the
//! pixel) are flagged in that pass and gathered after it; pixels neither case reaches are
//! holes, filled from the bounds around them (`Assistant::fill_holes`).

use std::ops::Range;

use nalgebra::{Matrix3, Vector3};

use super::motion;
use super::region::{ceil, floor, for_each_set, prefetch_row, round_row, MaskRows, Region, PREFETCH_ROWS};
use super::{Assistant, Plan};
use crate::stereo::DisparityIntervals;

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
        let mut union_count = 0;
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
            // The previous frame's map and mask have long left the cache.
            prefetch_row(prev_d, w, region.xs(), y + PREFETCH_ROWS, region.y1);
            prev_masks.prefetch(y + PREFETCH_ROWS, region.y1);
            let (d_row, rho_row) = (&prev_d[row.clone()], &mut rho[row.clone()]);
            let (lo_row, hi_row, un_row) = (&mut lo[row.clone()], &mut hi[row.clone()], &mut union_needed[row.clone()]);
            let (m_row, pm_row) = (masks.row(y), prev_masks.row(y));
            // One branch-free pass, so that it vectorises: ρ (NaN where there is no disparity
            // or the point lies behind the camera), the row's largest ρ as the bits of a
            // positive float (integers reduce in vector lanes; floats would not, for NaN),
            // and case 1 — a single circle around the previous correspondence.
            let (mut singles, mut unions, mut bits_max) = (0u32, 0u32, 0u32);
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
                unions += union as u32;
            }
            let row_max = f32::from_bits(bits_max);
            row_rho_max.push(row_max);
            max_rho = max_rho.max(row_max);
            plan.single_px += singles as usize;
            union_count += unions as usize;
            if let Some(out) = out.as_mut() {
                // Case 1's intervals; the union pixels are written once gathered.
                let (out_lo, out_hi) = out.iv.row_cols_mut(y, region.xs());
                if round_row(m_row, un_row, lo_row, hi_row, out_lo, out_hi, &mut hole_row[..n], range) {
                    for_each_set(&hole_row[..n], |k| out.holes.push((region.x0 + k, y)));
                }
            }
        }
        if union_count == 0 {
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
        let reach = reach_f.ceil() as usize;
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
        let (r0, r1) = (range.0 as f32, range.1 as f32);
        let spheres = Spheres::new(rho, prev_d, w, region, &mut self.rho_blocks, union_count >= BLOCKS_FROM);
        #[cfg(target_arch = "x86_64")]
        let avx2 = std::is_x86_feature_detected!("avx2");
        // Whether any sphere may reach a pixel of each block of the sphere map's grid, found
        // for a block the first time one of its pixels needs the union (0 not yet, 1 no, 2
        // yes): where the foreground holds much that the previous frame did not match (a
        // turntable or a floor the key leaves), most union pixels have no sphere near them.
        let (bx0, nbx) = (region.x0 / BLOCK, region.x1.div_ceil(BLOCK) - region.x0 / BLOCK);
        let mut reached = vec![0u8; nbx];
        let mut found = Vec::new();
        for y in region.ys() {
            if y % BLOCK == 0 || y == region.y0 {
                reached.fill(0);
            }
            pixels.clear();
            for_each_set(&union_needed[y * w + region.x0..y * w + region.x1], |k| pixels.push(region.x0 + k));
            for &x in &pixels {
                let j = y * w + x;
                let flag = &mut reached[x / BLOCK - bx0];
                if *flag == 0 {
                    let (bx, by) = (x / BLOCK, y / BLOCK);
                    let cols = (bx * BLOCK).max(region.x0)..(bx * BLOCK + BLOCK).min(region.x1);
                    *flag = 1 + spheres.may_reach(cols, (by * BLOCK).max(region.y0)..(by * BLOCK + BLOCK).min(region.y1), reach) as u8;
                }
                let (a, b) = if *flag == 2 {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: the CPU has AVX2 (checked above).
                    let (a, b) = if avx2 { unsafe { spheres.gather_avx2(x, y, reach) } } else { spheres.gather(x, y, reach) };
                    #[cfg(not(target_arch = "x86_64"))]
                    let (a, b) = spheres.gather(x, y, reach);
                    (if a < lo[j] { a } else { lo[j] }, if b > hi[j] { b } else { hi[j] })
                } else {
                    (lo[j], hi[j])
                };
                lo[j] = a;
                hi[j] = b;
                union_px += (a <= b) as usize;
                if let Some(out) = out.as_mut() {
                    // Clipped, then rounded outwards, as `round_row` does.
                    let (a, b) = (a.max(r0), b.min(r1));
                    if a <= b {
                        out.iv.set(x, y, Some((floor(a) as i32, ceil(b) as i32)));
                    } else {
                        found.push((x, y));
                    }
                }
            }
        }
        plan.union_px = union_px;
        if let (Some(out), false) = (out, found.is_empty()) {
            // Merged, in order, with the holes of case 1 (in order too).
            let ones = std::mem::take(out.holes);
            let (mut i, mut k) = (0, 0);
            out.holes.reserve(ones.len() + found.len());
            while i < ones.len() || k < found.len() {
                let take_one = k == found.len() || (i < ones.len() && (ones[i].1, ones[i].0) < (found[k].1, found[k].0));
                if take_one {
                    out.holes.push(ones[i]);
                    i += 1;
                } else {
                    out.holes.push(found[k]);
                    k += 1;
                }
            }
        }
    }
}

/// Columns of spheres one union pixel gathers from at a time (eight `f32` lanes).
const GATHER: usize = 8;

/// Side of the square blocks of the sphere map whose largest radius tells the union pixels
/// of a block that no sphere reaches them.
const BLOCK: usize = 8;

/// Union pixels from which the blocks' radii are worth finding. A scan's union pixels are
/// mostly the ≈ 1 000 at the object's edges, next to the spheres, where the blocks only cost
/// (≈ 0.02 ms of a 0.1 ms gather on the simulated 640 × 480 egg); a foreground the key leaves
/// (a grey turntable or floor) gives ≈ 100 000, most far from any sphere. Either way the
/// intervals are the same.
const BLOCKS_FROM: usize = 4096;

/// The distance between two spans of pixels (0 where they meet).
fn gap(a: &Range<usize>, b: &Range<usize>) -> usize {
    if a.end <= b.start {
        b.start + 1 - a.end
    } else {
        a.start.saturating_sub(b.end - 1)
    }
}

/// The previous frame's spheres, for case 2: each point's projected radius ρ (NaN where
/// there is no point) and disparity, full-size maps valid inside `region`; and the largest
/// ρ of each [`BLOCK`] × [`BLOCK`] block of the grid aligned to the map's corner, over the
/// region's pixels, as the bits of the float with the lowest set (at most one float more:
/// non-negative floats order as their bits; 0 where no pixel holds a point), `nbx` blocks a
/// row from block column `region.x0 / BLOCK` and block row `region.y0 / BLOCK`.
#[derive(Clone, Copy)]
struct Spheres<'a> {
    rho: &'a [f32],
    d: &'a [f32],
    w: usize,
    region: Region,
    blocks: &'a [u32],
    nbx: usize,
}

impl<'a> Spheres<'a> {
    /// The spheres of `rho` and `d` inside `region`; with `with_blocks`, their blocks'
    /// largest radii computed into `blocks` (without, none: every block may reach).
    #[inline(always)]
    fn new(rho: &'a [f32], d: &'a [f32], w: usize, region: Region, blocks: &'a mut Vec<u32>, with_blocks: bool) -> Spheres<'a> {
        let (bx0, bx1) = (region.x0 / BLOCK, region.x1.div_ceil(BLOCK));
        let (by0, by1) = (region.y0 / BLOCK, region.y1.div_ceil(BLOCK));
        let nbx = bx1 - bx0;
        blocks.clear();
        if !with_blocks {
            return Spheres { rho, d, w, region, blocks, nbx };
        }
        blocks.resize(nbx * (by1 - by0), 0);
        // NaN fails `r ≥ 0` and counts as 0; a radius of 0 counts as the next float up.
        let bits = |r: &f32| if *r >= 0.0 { r.to_bits() | 1 } else { 0 };
        // The first block column whole inside the region, and the last columns after the
        // whole blocks.
        let first = region.x0.div_ceil(BLOCK) * BLOCK;
        for y in region.ys() {
            let out = &mut blocks[(y / BLOCK - by0) * nbx..][..nbx];
            let row = &rho[y * w..y * w + region.x1];
            if first > region.x0 {
                out[0] = row[region.x0..first.min(region.x1)].iter().map(bits).fold(out[0], u32::max);
            }
            if first < region.x1 {
                let whole = row[first..].chunks_exact(BLOCK);
                let tail = whole.remainder();
                let k0 = first / BLOCK - bx0;
                for (m, c) in out[k0..].iter_mut().zip(whole) {
                    *m = c.iter().map(bits).fold(*m, u32::max);
                }
                if !tail.is_empty() {
                    out[nbx - 1] = tail.iter().map(bits).fold(out[nbx - 1], u32::max);
                }
            }
        }
        Spheres { rho, d, w, region, blocks, nbx }
    }

    /// Whether a block within `reach` of some pixel of the rectangle `cols` × `rows` (inside
    /// the region) may hold a sphere whose left projection holds one of them. A block is
    /// passed over when its largest ρ is short of the rectangle by more than a float's
    /// rounding can hide (ρ² + 1 < the squared distance between the two: then
    /// `ρ² − dy² < dx² − 1` for each of its spheres and each of the pixels, and no chord holds
    /// the pixel). Where it says no, every gather of the rectangle's pixels is empty.
    fn may_reach(&self, cols: Range<usize>, rows: Range<usize>, reach: usize) -> bool {
        let Spheres { region, blocks, nbx, .. } = *self;
        if blocks.is_empty() {
            return true;
        }
        let (sx0, sx1) = (cols.start.saturating_sub(reach).max(region.x0), (cols.end + reach).min(region.x1));
        let (sy0, sy1) = (rows.start.saturating_sub(reach).max(region.y0), (rows.end + reach).min(region.y1));
        if sx0 >= sx1 || sy0 >= sy1 {
            return false;
        }
        let (bx0, by0) = (region.x0 / BLOCK, region.y0 / BLOCK);
        (sy0 / BLOCK..=(sy1 - 1) / BLOCK).any(|by| {
            let gy = gap(&rows, &((by * BLOCK).max(sy0)..(by * BLOCK + BLOCK).min(sy1)));
            let line = &blocks[(by - by0) * nbx..][..nbx];
            (sx0 / BLOCK..=(sx1 - 1) / BLOCK).any(|bx| {
                let m = f32::from_bits(line[bx - bx0]);
                let gx = gap(&cols, &((bx * BLOCK).max(sx0)..(bx * BLOCK + BLOCK).min(sx1)));
                m > 0.0 && m * m + 1.0 >= (gx * gx + gy * gy) as f32
            })
        })
    }

    /// The hull `(lo, hi)` of the chords on row `y` of the spheres within `reach` rows and
    /// columns of left pixel `(x, y)` (inside the region) whose left projections hold it:
    /// `d_s + (x − x_s) ± c`, `c = √(ρ² − (y − y_s)²)`, for the spheres with `|x − x_s| ≤ c`;
    /// `(+∞, −∞)` where none does. Per lane of [`GATHER`] columns, reduced at the end (the
    /// portable version of [`Spheres::gather_avx2`], for other CPUs).
    fn gather(&self, x: usize, y: usize, reach: usize) -> (f32, f32) {
        let Spheres { rho, d, w, region, .. } = *self;
        let (sx0, sx1) = (x.saturating_sub(reach).max(region.x0), (x + reach + 1).min(region.x1));
        let (mut a, mut b) = ([f32::INFINITY; GATHER], [f32::NEG_INFINITY; GATHER]);
        for sy in y.saturating_sub(reach).max(region.y0)..(y + reach + 1).min(region.y1) {
            let dy2 = ((y as i64 - sy as i64) * (y as i64 - sy as i64)) as f32;
            for c0 in (sx0..sx1).step_by(GATHER) {
                let (at, len) = (sy * w + c0, (sx1 - c0).min(GATHER));
                let (mut r_l, mut d_l) = ([f32::NAN; GATHER], [0f32; GATHER]);
                r_l[..len].copy_from_slice(&rho[at..at + len]);
                d_l[..len].copy_from_slice(&d[at..at + len]);
                // Left pixel x lies on the sphere's left chord of row y when |x − x_s| ≤ c; the
                // right chord maps it to d_s + (x − x_s) ± c. NaN (no point, or past the
                // columns) fails the comparison.
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
        let a = a.iter().fold(f32::INFINITY, |m, &v| if v < m { v } else { m });
        let b = b.iter().fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m });
        (a, b)
    }

    /// [`Spheres::gather`] in AVX2 registers: the same operations on the same lanes (no fused
    /// multiply-add), so the same hull to the bit.
    ///
    /// # Safety
    /// The CPU supports AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn gather_avx2(&self, x: usize, y: usize, reach: usize) -> (f32, f32) {
        use std::arch::x86_64::*;
        let Spheres { rho, d, w, region, .. } = *self;
        let (sx0, sx1) = (x.saturating_sub(reach).max(region.x0), (x + reach + 1).min(region.x1));
        let (inf, ninf, nan, zero) = (_mm256_set1_ps(f32::INFINITY), _mm256_set1_ps(f32::NEG_INFINITY), _mm256_set1_ps(f32::NAN), _mm256_setzero_ps());
        let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let (mut a, mut b) = (inf, ninf);
        let mut c0 = sx0;
        while c0 < sx1 {
            let len = (sx1 - c0).min(GATHER);
            // Lanes k < len hold the columns c0 + k; the others read as no point.
            let valid = _mm256_castsi256_ps(_mm256_cmpgt_epi32(_mm256_set1_epi32(len as i32), lane));
            let dx = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_set1_epi32(x as i32 - c0 as i32), lane));
            let adx = _mm256_andnot_ps(_mm256_set1_ps(-0.0), dx);
            for sy in y.saturating_sub(reach).max(region.y0)..(y + reach + 1).min(region.y1) {
                let dy2 = _mm256_set1_ps(((y as i64 - sy as i64) * (y as i64 - sy as i64)) as f32);
                let at = sy * w + c0;
                let (r, dd) = if at + GATHER <= rho.len() && at + GATHER <= d.len() {
                    // SAFETY: at + GATHER is within both maps (checked).
                    unsafe { (_mm256_loadu_ps(rho.as_ptr().add(at)), _mm256_loadu_ps(d.as_ptr().add(at))) }
                } else {
                    // The maps' last columns: a lane-by-lane copy.
                    let (mut r_l, mut d_l) = ([f32::NAN; GATHER], [0f32; GATHER]);
                    r_l[..len].copy_from_slice(&rho[at..at + len]);
                    d_l[..len].copy_from_slice(&d[at..at + len]);
                    // SAFETY: arrays of GATHER = 8 floats.
                    unsafe { (_mm256_loadu_ps(r_l.as_ptr()), _mm256_loadu_ps(d_l.as_ptr())) }
                };
                let r = _mm256_blendv_ps(nan, r, valid);
                let c2 = _mm256_sub_ps(_mm256_mul_ps(r, r), dy2);
                // `max` takes the second operand where c2 is NaN: 0, as `f32::max` does.
                let c = _mm256_sqrt_ps(_mm256_max_ps(c2, zero));
                let inside = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(c2, zero), _mm256_cmp_ps::<_CMP_LE_OQ>(adx, c));
                let base = _mm256_add_ps(dd, dx);
                a = _mm256_min_ps(a, _mm256_blendv_ps(inf, _mm256_sub_ps(base, c), inside));
                b = _mm256_max_ps(b, _mm256_blendv_ps(ninf, _mm256_add_ps(base, c), inside));
            }
            c0 += GATHER;
        }
        let (mut la, mut lb) = ([0f32; GATHER], [0f32; GATHER]);
        // SAFETY: arrays of GATHER = 8 floats.
        unsafe {
            _mm256_storeu_ps(la.as_mut_ptr(), a);
            _mm256_storeu_ps(lb.as_mut_ptr(), b);
        }
        (la.iter().fold(f32::INFINITY, |m, &v| if v < m { v } else { m }), lb.iter().fold(f32::NEG_INFINITY, |m, &v| if v > m { v } else { m }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hull of the rule itself: every sphere within `reach`, one at a time.
    fn gather_every_sphere(s: &Spheres, x: usize, y: usize, reach: usize) -> (f32, f32) {
        let (mut a, mut b) = (f32::INFINITY, f32::NEG_INFINITY);
        let r = s.region;
        for sy in y.saturating_sub(reach).max(r.y0)..(y + reach + 1).min(r.y1) {
            for sx in x.saturating_sub(reach).max(r.x0)..(x + reach + 1).min(r.x1) {
                let (rho, dx, dy) = (s.rho[sy * s.w + sx], x as f32 - sx as f32, y as f32 - sy as f32);
                let c2 = rho * rho - dy * dy;
                if c2 >= 0.0 && dx.abs() <= c2.sqrt() {
                    let base = s.d[sy * s.w + sx] + dx;
                    a = a.min(base - c2.sqrt());
                    b = b.max(base + c2.sqrt());
                }
            }
        }
        (a, b)
    }

    /// Both gathers (portable, and AVX2 where the CPU has it) against the rule sphere by
    /// sphere, bit for bit, and the blocks said out of reach against it, on random spheres:
    /// radii around the reach, points missing, whole blocks empty or of small spheres only,
    /// pixels at the region's and the map's edges, and values outside the region that must
    /// not be read.
    #[test]
    fn the_gathers_give_the_rule_s_hull() {
        #[cfg(target_arch = "x86_64")]
        let avx2 = std::is_x86_feature_detected!("avx2");
        let mut rand = crate::testing::xorshift(777);
        let (w, h) = (53, 29);
        let (mut blocks, mut passed) = (Vec::new(), 0);
        for round in 0..20 {
            // An empty disc of blocks, a ring of blocks of small spheres around it, random
            // spheres elsewhere.
            let centre = ((round * 13) % w, (round * 7) % h);
            let rho: Vec<f32> = (0..w * h)
                .map(|j| {
                    let (bx, by) = ((j % w) / BLOCK * BLOCK + BLOCK / 2, (j / w) / BLOCK * BLOCK + BLOCK / 2);
                    let r2 = bx.abs_diff(centre.0).pow(2) + by.abs_diff(centre.1).pow(2);
                    if r2 <= 14 * 14 {
                        f32::NAN
                    } else if r2 <= 22 * 22 {
                        0.5 + (rand() % 100) as f32 / 100.0
                    } else if rand() % 5 == 0 {
                        f32::NAN
                    } else {
                        0.5 + (rand() % 1000) as f32 / 180.0
                    }
                })
                .collect();
            let d: Vec<f32> = rho.iter().map(|r| if r.is_nan() { f32::NAN } else { (rand() % 12_000) as f32 / 100.0 }).collect();
            let region = if round % 2 == 0 { Region { x0: 0, x1: w, y0: 0, y1: h } } else { Region { x0: 3, x1: w - 5, y0: 2, y1: h - 1 } };
            let s = Spheres::new(&rho, &d, w, region, &mut blocks, true);
            let mut inside = 0;
            for y in region.ys() {
                for x in region.xs() {
                    for reach in [1, 3, 4, 9] {
                        let want = gather_every_sphere(&s, x, y, reach);
                        // The pixel's own block, as the plan asks.
                        let (bx, by) = (x / BLOCK, y / BLOCK);
                        let cols = (bx * BLOCK).max(region.x0)..(bx * BLOCK + BLOCK).min(region.x1);
                        if !s.may_reach(cols, (by * BLOCK).max(region.y0)..(by * BLOCK + BLOCK).min(region.y1), reach) {
                            assert!(want.0 > want.1, "({x}, {y}), reach {reach}, {region:?}: a sphere reaches a pixel of a block said to be out of reach");
                            passed += 1;
                        }
                        let bits = |(a, b): (f32, f32)| (a.to_bits(), b.to_bits());
                        assert_eq!(bits(s.gather(x, y, reach)), bits(want), "portable: ({x}, {y}), reach {reach}, {region:?}");
                        #[cfg(target_arch = "x86_64")]
                        if avx2 {
                            // SAFETY: AVX2 checked above.
                            let got = unsafe { s.gather_avx2(x, y, reach) };
                            assert_eq!(bits(got), bits(want), "AVX2: ({x}, {y}), reach {reach}, {region:?}");
                        }
                        inside += (want.0 <= want.1) as usize;
                    }
                }
            }
            assert!(inside > 1000, "the spheres reach pixels ({inside})");
        }
        assert!(passed > 1000, "blocks are passed over ({passed})");
    }
}
