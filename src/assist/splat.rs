//! The Kalman-predicted motion carried into this frame's search intervals: each previous
//! point moved, projected and splatted with its uncertainty into per-pixel `lo`/`hi` (or
//! straight into the tiles). The paper's rule is in paper.rs.

use super::region::{prefetch_row, MaskRows, PREFETCH_ROWS};
use super::tiles::{self, TileBounds};
use super::{Assistant, Plan};

/// One plan's projection of previous points into this frame, in f32: the predicted motion
/// (rotation columns `r0`, translation `t`), the rectified camera, the prediction's
/// covariance terms and the bounds a splat must fall in.
#[derive(Clone, Copy)]
struct Projection {
    r0: [f32; 3],
    t: [f32; 3],
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    dcx: f32,
    tx: f32,
    inv_mtx: f32,
    k_sigma: f32,
    s2: f32,
    min_half: f32,
    /// Var(ω_x), Cov(ω_x, ω_y), Var(ω_y), Cov(ω_x, v_z), Cov(ω_y, v_z), Var(v_z).
    c: [f32; 6],
    /// A splat's `(⌊px⌋, ⌊py⌋)` lies in the region when `x0 ≤ px < x1 − 1` and
    /// `y0 ≤ py < y1 − 1`: `(x0, x1 − 1, y0, y1 − 1)`.
    bounds: [f32; 4],
}

impl Projection {
    /// The previous point of disparity `d` on the ray `(u, v, 1)` (`base = R·(0, v, 1)`, per
    /// row): its predicted pixel `(px, py)`, the bounds `pd ± k·σ` of its predicted disparity,
    /// and whether it lands inside the region (false for NaN, for a point behind the camera
    /// or moved behind it).
    #[inline(always)]
    fn point(&self, base: [f32; 3], u: f32, d: f32) -> (f32, f32, f32, f32, bool) {
        let Projection { r0, t, fx, fy, cx, cy, dcx, tx, inv_mtx, k_sigma, s2, min_half, c: [c00, c01, c11, c05, c15, c55], bounds: [rx0, rx1, ry0, ry1] } = *self;
        // In f32, with 1/Z = (d − dcx)/(−tx): Q·(1/Z) = R·(u, v, 1) + t/Z, so one division
        // gives the projection of the moved point.
        let iz = (d - dcx) * inv_mtx;
        // The moved point times 1/Z.
        let (qx, qy, qz) = (base[0] + r0[0] * u + t[0] * iz, base[1] + r0[1] * u + t[1] * iz, base[2] + r0[2] * u + t[2] * iz);
        let s = 1.0 / qz;
        let (px, py, pd) = (fx * qx * s + cx, fy * qy * s + cy, dcx - tx * iz * s);
        // Var(d) = (∂d/∂Z)²·Var(Z) with the moved point Q = q/iz (mm) and
        // ∂d/∂Z = tx/Q_z² = tx·iz²·s², written without dividing by iz:
        // Var(d) = tx²·s⁴·[iz²·(q_y²c00 − 2q_xq_y c01 + q_x²c11) + 2·iz³·(q_y c05 − q_x c15) + iz⁴·c55].
        let (iz2, s2q) = (iz * iz, s * s);
        let var_d = (tx * tx * s2q * s2q * iz2 * ((qy * qy * c00 - 2.0 * qx * qy * c01 + qx * qx * c11) + 2.0 * iz * (qy * c05 - qx * c15) + iz2 * c55)).max(0.0);
        let half = (k_sigma * (var_d + s2).sqrt()).max(min_half);
        let ok = iz > 0.0 && qz > 0.0;
        let inside = ok & (px >= rx0) & (px < rx1) & (py >= ry0) & (py < ry1);
        (px, py, pd - half, pd + half, inside)
    }
}

impl Assistant {
    /// The Kalman prediction of every previous point into `lo`/`hi`.
    #[inline(always)]
    pub(super) fn splat_predicted(&mut self, gap: u64, lag: u64, mask: Option<&[u8]>, plan: &mut Plan) {
        let w = self.size.0;
        let prev = self.prev.as_ref().expect("planned with a previous frame");
        let Some((m, cov)) = self.filter.predict(gap, lag) else { return };
        let cam = self.cam;
        let rot = m.rotation.to_rotation_matrix().into_inner().cast::<f32>();
        let t = m.translation.vector.cast::<f32>();
        // Var(Z) of a moved point q under a twist perturbation: δZ = δω_x·q_y − δω_y·q_x + δv_z.
        let c = |i: usize, j: usize| cov[(i, j)] as f32;
        let (fx, fy, cx, cy, dcx, tx) = (cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32, cam.dcx as f32, cam.tx as f32);
        let prev_d = prev.disparity.values();
        let (lo, hi, region) = (&mut self.lo, &mut self.hi, self.region);
        let (ifx, ify) = (1.0 / fx, 1.0 / fy);
        let proj = Projection {
            r0: [rot[(0, 0)], rot[(1, 0)], rot[(2, 0)]],
            t: [t.x, t.y, t.z],
            fx,
            fy,
            cx,
            cy,
            dcx,
            tx,
            inv_mtx: -1.0 / tx,
            k_sigma: self.params.predicted_k as f32,
            s2: self.params.predicted_sigma_px.powi(2) as f32,
            min_half: self.params.min_half_width_px as f32,
            c: [c(0, 0), c(0, 1), c(1, 1), c(0, 5), c(1, 5), c(5, 5)],
            // A prediction splats onto the 2 × 2 pixels from (⌊px⌋, ⌊py⌋): they lie inside
            // the region exactly when x0 ≤ px < x1 − 1 and y0 ≤ py < y1 − 1 (NaN fails).
            bounds: [region.x0 as f32, (region.x1 - 1) as f32, region.y0 as f32, (region.y1 - 1) as f32],
        };
        let u_col = region.column_rays(cx, ifx);
        let n = u_col.len();
        assert!(w * self.size.1 <= i32::MAX as usize, "an image of {w}×{} pixels is too large to index in i32", self.size.1);
        // Per row: the projections and bounds of every point, branch-free so that it
        // vectorises (NaN where there is no point or it moves behind the camera), then the
        // splats.
        let (mut xs, mut ys, mut los, mut his) = (vec![0i32; n], vec![-1i32; n], vec![0f32; n], vec![0f32; n]);
        let (mut pxs, mut pys) = (vec![0f32; n], vec![0f32; n]);
        // At tile granularity, each point's tile and the tiles its splat crosses into, found
        // in the vector loop with the projection: the scatter then only widens the hulls.
        let (mut tile_of, mut crosses) = (vec![0u32; n], vec![0u32; n]);
        let cols = self.tiles.cols() as u32;
        let tiled = self.params.granularity.tiled();
        #[cfg(target_arch = "x86_64")]
        let avx2 = tiled && std::is_x86_feature_detected!("avx2");
        let tiles = &mut self.tiles;
        for y in region.ys() {
            prefetch_row(prev_d, w, region.xs(), y + PREFETCH_ROWS, region.y1);
            let v = (y as f32 - cy) * ify;
            let base = rot.column(1) * v + rot.column(2);
            let base = [base.x, base.y, base.z];
            let d_row = &prev_d[y * w + region.x0..y * w + region.x1];
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the CPU has AVX2 (checked above).
                unsafe { tiles_row_avx2(&proj, base, &u_col, d_row, cols, tiles) };
                continue;
            }
            for k in 0..n {
                let (px, py, a, b, inside) = proj.point(base, u_col[k], d_row[k]);
                // Non-negative and inside the image once selected: truncation is the floor,
                // and the plain conversion is exact (it vectorises, unlike `as`).
                let (px, py) = (if inside { px } else { 0.0 }, if inside { py } else { 0.0 });
                // SAFETY: px and py lie in [0, w) and [0, h), far inside i32.
                let (x0, y0) = unsafe { (px.to_int_unchecked::<i32>(), py.to_int_unchecked::<i32>()) };
                (xs[k], ys[k]) = (x0, if inside { y0 } else { -1 });
                (pxs[k], pys[k]) = (px, py);
                (tile_of[k], crosses[k]) = tiles::splat_tile(x0 as u32, y0 as u32, cols);
                los[k] = a;
                his[k] = b;
            }
            for k in 0..n {
                if ys[k] < 0 {
                    continue;
                }
                let (a, b) = (los[k], his[k]);
                if tiled {
                    // Straight into the tiles: no per-pixel map (tiles.rs).
                    tiles.add_splat(tile_of[k] as usize, crosses[k], pxs[k], pys[k], a, b);
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

/// One row of previous points (`d_row`, rays `u_col`) splatted straight into the tiles, as
/// the portable loop of [`Assistant::splat_predicted`] does, eight points at a time in AVX2
/// registers: the same operations in the same order (no fused multiply-add), so the same
/// bounds to the bit. Eight points without a disparity cost one test; eight that land in one
/// tile, or in two neighbouring tiles of a tile row, widen each tile once with their hull
/// (the hull does not depend on the order the bounds arrive in); any other eight go one by
/// one.
///
/// # Safety
/// The CPU supports AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn tiles_row_avx2(p: &Projection, base: [f32; 3], u_col: &[f32], d_row: &[f32], cols: u32, tiles: &mut TileBounds) {
    use std::arch::x86_64::*;
    const TW: u32 = tiles::TW as u32;
    const TH: u32 = tiles::TH as u32;
    const _: () = assert!(TW.is_power_of_two() && TH.is_power_of_two(), "tile sides are shifts here");
    let n = u_col.len().min(d_row.len());
    let s = |v: f32| _mm256_set1_ps(v);
    let [c00, c01, c11, c05, c15, c55] = p.c.map(s);
    let (bx, by, bz) = (s(base[0]), s(base[1]), s(base[2]));
    let (r00, r10, r20) = (s(p.r0[0]), s(p.r0[1]), s(p.r0[2]));
    let (t0, t1, t2) = (s(p.t[0]), s(p.t[1]), s(p.t[2]));
    let (fx, fy, cx, cy, dcx, tx, inv_mtx) = (s(p.fx), s(p.fy), s(p.cx), s(p.cy), s(p.dcx), s(p.tx), s(p.inv_mtx));
    let (k_sigma, s2, min_half, two, one, zero) = (s(p.k_sigma), s(p.s2), s(p.min_half), s(2.0), s(1.0), _mm256_setzero_ps());
    let [rx0, rx1, ry0, ry1] = p.bounds.map(s);
    let (inf, ninf) = (s(f32::INFINITY), s(f32::NEG_INFINITY));
    let (tw_last, th_last, vcols) = (_mm256_set1_epi32(TW as i32 - 1), _mm256_set1_epi32(TH as i32 - 1), _mm256_set1_epi32(cols as i32));
    let mut k = 0;
    while k + 8 <= n {
        // SAFETY: k + 8 ≤ n, within both rows.
        let d = unsafe { _mm256_loadu_ps(d_row.as_ptr().add(k)) };
        if _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_ORD_Q>(d, d)) == 0 {
            k += 8;
            continue;
        }
        // SAFETY: as above.
        let u = unsafe { _mm256_loadu_ps(u_col.as_ptr().add(k)) };
        let (add, sub, mul) = (|a, b| _mm256_add_ps(a, b), |a, b| _mm256_sub_ps(a, b), |a, b| _mm256_mul_ps(a, b));
        let iz = mul(sub(d, dcx), inv_mtx);
        let qx = add(add(bx, mul(r00, u)), mul(t0, iz));
        let qy = add(add(by, mul(r10, u)), mul(t1, iz));
        let qz = add(add(bz, mul(r20, u)), mul(t2, iz));
        let sc = _mm256_div_ps(one, qz);
        let px = add(mul(mul(fx, qx), sc), cx);
        let py = add(mul(mul(fy, qy), sc), cy);
        let pd = sub(dcx, mul(mul(tx, iz), sc));
        let (iz2, s2q) = (mul(iz, iz), mul(sc, sc));
        let quad = add(sub(mul(mul(qy, qy), c00), mul(mul(mul(two, qx), qy), c01)), mul(mul(qx, qx), c11));
        let inner = add(add(quad, mul(mul(two, iz), sub(mul(qy, c05), mul(qx, c15)))), mul(iz2, c55));
        // `max` takes the second operand where the first is NaN, as `f32::max` does.
        let var_d = _mm256_max_ps(mul(mul(mul(mul(mul(tx, tx), s2q), s2q), iz2), inner), zero);
        let half = _mm256_max_ps(mul(k_sigma, _mm256_sqrt_ps(add(var_d, s2))), min_half);
        let ok = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(iz, zero), _mm256_cmp_ps::<_CMP_GT_OQ>(qz, zero));
        let in_x = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(px, rx0), _mm256_cmp_ps::<_CMP_LT_OQ>(px, rx1));
        let in_y = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(py, ry0), _mm256_cmp_ps::<_CMP_LT_OQ>(py, ry1));
        let inside = _mm256_and_ps(ok, _mm256_and_ps(in_x, in_y));
        let m_in = _mm256_movemask_ps(inside);
        if m_in == 0 {
            k += 8;
            continue;
        }
        // Outside lanes read as an empty bound in tile 0 (masked below).
        let inside_i = _mm256_castps_si256(inside);
        let x0 = _mm256_and_si256(_mm256_cvttps_epi32(px), inside_i);
        let y0 = _mm256_and_si256(_mm256_cvttps_epi32(py), inside_i);
        let tile = _mm256_add_epi32(_mm256_mullo_epi32(_mm256_srli_epi32::<{ TH.trailing_zeros() as i32 }>(y0), vcols), _mm256_srli_epi32::<{ TW.trailing_zeros() as i32 }>(x0));
        let right = _mm256_cmpeq_epi32(_mm256_and_si256(x0, tw_last), tw_last);
        let down = _mm256_cmpeq_epi32(_mm256_and_si256(y0, th_last), th_last);
        let (a, b) = (_mm256_blendv_ps(inf, sub(pd, half), inside), _mm256_blendv_ps(ninf, add(pd, half), inside));
        // The first tile of the inside lanes, and which lanes lie in it or the next.
        let t_first = hmin_epu32(_mm256_blendv_epi8(_mm256_set1_epi32(-1), tile, inside_i));
        let in_first = _mm256_and_si256(_mm256_cmpeq_epi32(tile, _mm256_set1_epi32(t_first as i32)), inside_i);
        let in_next = _mm256_and_si256(_mm256_cmpeq_epi32(tile, _mm256_set1_epi32(t_first as i32 + 1)), inside_i);
        let mask = |v: __m256i| _mm256_movemask_ps(_mm256_castsi256_ps(v));
        let m_down = mask(_mm256_and_si256(down, inside_i));
        let two_tiles = mask(_mm256_or_si256(in_first, in_next)) == m_in;
        // A lane of the next tile crossing right would reach a third tile.
        let no_third = mask(_mm256_and_si256(in_next, right)) == 0;
        if two_tiles && no_third && (m_down == 0 || m_down == m_in) {
            let to_next = _mm256_or_si256(in_next, _mm256_and_si256(in_first, right));
            // The lanes' bounds about tile t's plane at their predicted pixels.
            let about = |tiles: &TileBounds, t: usize, lanes: __m256| {
                let [gx, gy, k] = tiles.plane(t);
                let o = add(add(mul(s(gx), px), mul(s(gy), py)), s(k));
                hull_ps(_mm256_blendv_ps(inf, sub(a, o), lanes), _mm256_blendv_ps(ninf, sub(b, o), lanes))
            };
            for (t, lanes) in [(t_first, in_first), (t_first + 1, to_next)] {
                if mask(lanes) == 0 {
                    continue;
                }
                let lanes = _mm256_castsi256_ps(lanes);
                let (lo, hi) = about(tiles, t as usize, lanes);
                tiles.add(t as usize, lo, hi);
                if m_down != 0 {
                    let below = t as usize + cols as usize;
                    let (lo, hi) = about(tiles, below, lanes);
                    tiles.add(below, lo, hi);
                }
            }
        } else {
            let (mut ts, mut rs, mut ds, mut la, mut lb, mut lx, mut ly) = ([0u32; 8], [0u32; 8], [0u32; 8], [0f32; 8], [0f32; 8], [0f32; 8], [0f32; 8]);
            // SAFETY: arrays of eight lanes.
            unsafe {
                _mm256_storeu_si256(ts.as_mut_ptr().cast(), tile);
                _mm256_storeu_si256(rs.as_mut_ptr().cast(), right);
                _mm256_storeu_si256(ds.as_mut_ptr().cast(), down);
                _mm256_storeu_ps(la.as_mut_ptr(), a);
                _mm256_storeu_ps(lb.as_mut_ptr(), b);
                _mm256_storeu_ps(lx.as_mut_ptr(), px);
                _mm256_storeu_ps(ly.as_mut_ptr(), py);
            }
            for j in (0..8).filter(|j| m_in & (1 << j) != 0) {
                let crosses = (rs[j] != 0) as u32 * tiles::RIGHT | (ds[j] != 0) as u32 * tiles::DOWN;
                tiles.add_splat(ts[j] as usize, crosses, lx[j], ly[j], la[j], lb[j]);
            }
        }
        k += 8;
    }
    // The row's last points, one by one.
    for k in k..n {
        splat_point(p, base, u_col[k], d_row[k], cols, tiles);
    }
}

/// One previous point splatted straight into the tiles (what the portable loop of
/// [`Assistant::splat_predicted`] does for each point at tile granularity).
#[inline(always)]
fn splat_point(p: &Projection, base: [f32; 3], u: f32, d: f32, cols: u32, tiles: &mut TileBounds) {
    let (px, py, a, b, inside) = p.point(base, u, d);
    if inside {
        // Non-negative once inside: the conversion is the floor.
        let (t, crosses) = tiles::splat_tile(px as u32, py as u32, cols);
        tiles.add_splat(t as usize, crosses, px, py, a, b);
    }
}

/// The smallest of eight `u32` lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn hmin_epu32(v: std::arch::x86_64::__m256i) -> u32 {
    use std::arch::x86_64::*;
    let m = _mm_min_epu32(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    let m = _mm_min_epu32(m, _mm_shuffle_epi32::<0b01_00_11_10>(m));
    let m = _mm_min_epu32(m, _mm_shuffle_epi32::<0b10_11_00_01>(m));
    _mm_cvtsi128_si32(m) as u32
}

/// The smallest of `lo`'s eight lanes and the largest of `hi`'s (none NaN).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn hull_ps(lo: std::arch::x86_64::__m256, hi: std::arch::x86_64::__m256) -> (f32, f32) {
    use std::arch::x86_64::*;
    let a = _mm_min_ps(_mm256_castps256_ps128(lo), _mm256_extractf128_ps::<1>(lo));
    let b = _mm_max_ps(_mm256_castps256_ps128(hi), _mm256_extractf128_ps::<1>(hi));
    let (a, b) = (_mm_min_ps(a, _mm_movehl_ps(a, a)), _mm_max_ps(b, _mm_movehl_ps(b, b)));
    (_mm_cvtss_f32(_mm_min_ss(a, _mm_shuffle_ps::<0b01>(a, a))), _mm_cvtss_f32(_mm_max_ss(b, _mm_shuffle_ps::<0b01>(b, b))))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AVX2 row splat against the point-by-point one, bit for bit, on flat and sloped tiles:
    /// random small motions
    /// (with roll, so that eight neighbours can land in different tile rows), smooth rows
    /// (eight points of one or two tiles) and scattered ones, runs without disparities, points
    /// landing outside the region.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn the_avx2_tile_splat_is_the_pointwise_one() {
        if !std::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut next = crate::testing::xorshift(0x5b1a_7e11);
        let mut unit = move || (next() % 1_000_003) as f32 / 1_000_003.0;
        let (w, h) = (203usize, 121usize);
        let (fx, fy, cx, cy, tx) = (300.0f32, 310.0f32, 101.5f32, 60.5f32, -300.0f32 * 60.0);
        let (mut fast, mut slow) = (0, 0);
        for case in 0..60 {
            let (rx, ry, rz) = {
                let mut angle = || (unit() - 0.5) * 0.08;
                (angle(), angle(), angle())
            };
            let rot = nalgebra::Rotation3::from_euler_angles(rx, ry, rz).into_inner();
            let region = (7 + case % 5, w - 3 - case % 7, 2 + case % 3, h - 1 - case % 4);
            let p = Projection {
                r0: [rot[(0, 0)], rot[(1, 0)], rot[(2, 0)]],
                t: [(unit() - 0.5) * 40.0, (unit() - 0.5) * 40.0, (unit() - 0.5) * 40.0],
                fx,
                fy,
                cx,
                cy,
                dcx: (unit() - 0.5) * 4.0,
                tx,
                inv_mtx: -1.0 / tx,
                k_sigma: 3.0,
                s2: 0.25,
                min_half: 1.0,
                c: [1e-6 * unit(), -2e-7 * unit(), 1e-6 * unit(), 1e-5 * unit(), -1e-5 * unit(), 0.5 * unit()],
                bounds: [region.0 as f32, (region.1 - 1) as f32, region.2 as f32, (region.3 - 1) as f32],
            };
            let cols = w.div_ceil(tiles::TW) as u32;
            let u_col: Vec<f32> = (region.0..region.1).map(|x| (x as f32 - cx) * (1.0 / fx)).collect();
            let (mut want, mut got) = (TileBounds::default(), TileBounds::default());
            want.reset(w, h);
            got.reset(w, h);
            // Sloped tiles in every other case (each tile its own plane), flat ones between.
            if case % 2 == 1 {
                for t in 0..cols as usize * h.div_ceil(tiles::TH) {
                    let plane = [(unit() - 0.5) * 2.0, (unit() - 0.5) * 2.0, (unit() - 0.5) * 300.0];
                    want.set_plane(t, plane);
                    got.set_plane(t, plane);
                }
            }
            for y in region.2..region.3 {
                let v = (y as f32 - cy) * (1.0 / fy);
                let b = rot.column(1) * v + rot.column(2);
                let base = [b.x, b.y, b.z];
                let smooth = unit() < 0.7;
                let (d0, slope) = (20.0 + 100.0 * unit(), (unit() - 0.5) * 0.6);
                let d_row: Vec<f32> = (0..u_col.len())
                    .map(|k| {
                        let gap = (k / 8 + y) % 5 == 0 || unit() < 0.05;
                        if gap {
                            f32::NAN
                        } else if smooth {
                            d0 + slope * k as f32
                        } else {
                            5.0 + 130.0 * unit()
                        }
                    })
                    .collect();
                for k in 0..u_col.len() {
                    splat_point(&p, base, u_col[k], d_row[k], cols, &mut want);
                }
                // SAFETY: the CPU has AVX2 (checked above).
                unsafe { tiles_row_avx2(&p, base, &u_col, &d_row, cols, &mut got) };
                (fast, slow) = if smooth { (fast + 1, slow) } else { (fast, slow + 1) };
            }
            assert!(got == want, "case {case}: the tiles' hulls differ");
        }
        assert!(fast > 100 && slow > 100, "both kinds of row: {fast} smooth, {slow} scattered");
    }
}
