//! The narrow-band path: rows whose tiles search few disparities.
//!
//! The image is cut into tiles of [`TILE_W`] × [`TILE_H`] pixels; a tile's band is the union
//! of its pixels' searched intervals, widened to whole 16-lane blocks (`tile_bands`). Each
//! tile keeps its own vertical window sums over its band for its columns and their window's
//! halo, slid down row by row while the band stays, summed afresh where it changes (a new
//! tile row with another band, or a gap). Along a row the window sums slide from pixel to
//! pixel inside the tile. Every pixel then searches only its own interval, masked inside the
//! band's lanes: winner, rival for the uniqueness test and the splat onto the right row for
//! the left–right check are a few vector instructions per block of 16 disparities — no
//! per-pixel branching on ranges, and the tile's sums stay in the first-level cache.
//!
//! The results are those of the row path (`rows.rs`) for the same intervals: the same
//! costs, the same winner (first lowest), rival, texture, sub-pixel fit and left–right check.

use std::ops::Range;

use super::rows::{decide_at, right_start};
use super::scratch::{clamp_row, Geometry, StripeScratch, TileSums, TILE_W};
use crate::stereo::params::ValidMatchParams;

/// Copies of the right row's minima the pixels of a row take turns at.
const RIGHT_COPIES: usize = 4;

/// Whether the tile path can run with these sizes: whole blocks of 16 disparities, at most
/// [`MAX_BLOCKS`] of them.
pub(super) fn supported(g: Geometry) -> bool {
    g.n % 16 == 0 && g.n / 16 <= MAX_BLOCKS
}

/// Most blocks of 16 disparities a tile band may have (256 disparities).
pub(super) const MAX_BLOCKS: usize = 16;

/// Matches the searched pixels of row `y` inside `span`, tile by tile: fills `s.best`,
/// the window sums `s.sad` of every searched pixel over its tile's band, and the right-row
/// minima `s.right_min` of the searched pairs (as `select_row` does).
///
/// # Safety
/// AVX2 must be available; [`supported`] must hold; `s` must be sized by the stripe set-up
/// and `s.tile_lo/hi` hold this tile row's bands, `s.tlo/thi` this row's intervals.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn tile_row(p: &ValidMatchParams, g: Geometry, lpf: &[u8], rrev: &[u8], y: usize, s: &mut StripeScratch, span: Range<usize>) {
    use std::arch::x86_64::*;
    let Geometry { w, h, r, wp, n, .. } = g;
    let wr = g.wr();
    let cols = TILE_W + 2 * r;
    let y_new = clamp_row(y as isize + r as isize, h);
    let y_old = clamp_row(y as isize - r as isize - 1, h);
    assert!(lpf.len() >= h * wp && rrev.len() >= h * wr && s.sad.len() >= w * n && s.right_min.len() >= w + n);
    assert!(s.tile_cs.len() >= w.div_ceil(TILE_W) * cols * n && s.tile_sums.len() >= w.div_ceil(TILE_W));
    let (lp, rp) = (lpf.as_ptr(), rrev.as_ptr());
    let sad = s.sad.as_mut_ptr();
    // Pixel x splats onto copy x mod RIGHT_COPIES of the right row: the next pixel's
    // read-modify-write overlaps this one's by all but one lane, and reading a store still in
    // flight stalls; the copies are merged after the row.
    let stride = w + n + 16;
    s.tile_right.resize(RIGHT_COPIES * stride, u16::MAX);
    let right_range = w - span.end..w - span.start + n;
    for c in 0..RIGHT_COPIES {
        s.tile_right[c * stride + right_range.start..c * stride + right_range.end].fill(u16::MAX);
    }
    let right_copies = s.tile_right.as_mut_ptr();
    s.best[span.clone()].fill(None);
    for t in span.start / TILE_W..=(span.end - 1) / TILE_W {
        let (lo, hi) = (s.tile_lo[t], s.tile_hi[t]);
        if lo > hi {
            continue;
        }
        let x0 = t * TILE_W;
        let x1 = ((t + 1) * TILE_W).min(w);
        // The searched pixels of this tile in this row.
        let Some(xa) = (x0.max(span.start)..x1.min(span.end)).find(|&x| s.tlo[x] <= s.thi[x]) else {
            // Nothing searched here this row: the sums fall behind and are summed afresh
            // when the tile is needed again.
            continue;
        };
        let xb = (xa..x1.min(span.end)).rev().find(|&x| s.tlo[x] <= s.thi[x]).expect("xa is searched");
        let k0 = lo as usize;
        let nb = (hi - lo + 1) as usize / 16;
        debug_assert!((hi - lo + 1) % 16 == 0 && nb <= MAX_BLOCKS);
        let ncols = (x1 + 2 * r).min(wp) - x0;
        let cs = s.tile_cs.as_mut_ptr().add(t * cols * n);
        let state = &mut s.tile_sums[t];
        let slide = state.lo == lo && state.hi == hi && state.row.wrapping_add(1) == y;
        *state = TileSums { lo, hi, row: y };
        // Vertical window sums of the tile's columns, down to row y.
        for c in 0..ncols {
            let xp = x0 + c;
            let rs = (right_start(g, xp) + k0 as isize) as usize;
            let col = cs.add(c * n + k0);
            if slide {
                let ln = _mm_set1_epi8(*lp.add(y_new * wp + xp) as i8);
                let lo_ = _mm_set1_epi8(*lp.add(y_old * wp + xp) as i8);
                let (rn, ro) = (rp.add(y_new * wr + rs), rp.add(y_old * wr + rs));
                for j in 0..nb {
                    let a = _mm_loadu_si128(rn.add(16 * j) as *const __m128i);
                    let o = _mm_loadu_si128(ro.add(16 * j) as *const __m128i);
                    let da = _mm_or_si128(_mm_subs_epu8(a, ln), _mm_subs_epu8(ln, a));
                    let dold = _mm_or_si128(_mm_subs_epu8(o, lo_), _mm_subs_epu8(lo_, o));
                    let v = _mm256_load_si256(col.add(16 * j) as *const __m256i);
                    let v = _mm256_sub_epi16(_mm256_add_epi16(v, _mm256_cvtepu8_epi16(da)), _mm256_cvtepu8_epi16(dold));
                    _mm256_store_si256(col.add(16 * j) as *mut __m256i, v);
                }
            } else {
                for j in 0..nb {
                    let mut acc = _mm256_setzero_si256();
                    for dy in -(r as isize)..=r as isize {
                        let yy = clamp_row(y as isize + dy, h);
                        let l = _mm_set1_epi8(*lp.add(yy * wp + xp) as i8);
                        let a = _mm_loadu_si128(rp.add(yy * wr + rs + 16 * j) as *const __m128i);
                        let d = _mm_or_si128(_mm_subs_epu8(a, l), _mm_subs_epu8(l, a));
                        acc = _mm256_add_epi16(acc, _mm256_cvtepu8_epi16(d));
                    }
                    _mm256_store_si256(col.add(16 * j) as *mut __m256i, acc);
                }
            }
        }
        // Window sums along the row, then each searched pixel's own interval: the band's
        // lanes in registers where it has at most four blocks (nearly always when this path
        // is taken), through memory otherwise.
        let px = TilePixels { p, g, cs, sad, right_copies, stride, lo, k0, xs: (xa, xb), x0 };
        match nb {
            1 => tile_pixels::<1>(px, s, 1),
            2 => tile_pixels::<2>(px, s, 2),
            3 => tile_pixels::<3>(px, s, 3),
            4 => tile_pixels::<4>(px, s, 4),
            _ => tile_pixels::<MAX_BLOCKS>(px, s, nb),
        }
    }
    let (copies, merged) = (&s.tile_right, &mut s.right_min[right_range.clone()]);
    merged.copy_from_slice(&copies[right_range.clone()]);
    for c in 1..RIGHT_COPIES {
        for (m, &v) in merged.iter_mut().zip(&copies[c * stride + right_range.start..c * stride + right_range.end]) {
            *m = (*m).min(v);
        }
    }

}

/// What [`tile_pixels`] needs of its tile: the column sums `cs` (band from `k0`), the
/// row's window sums `sad`, the right-row copies, the band's first disparity index `lo` and
/// the tile's first and last searched pixel `xs`, the tile's first column `x0`.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
struct TilePixels<'a> {
    p: &'a ValidMatchParams,
    g: Geometry,
    cs: *const u16,
    sad: *mut u16,
    right_copies: *mut u16,
    stride: usize,
    lo: i32,
    k0: usize,
    xs: (usize, usize),
    x0: usize,
}

/// The pixels `xs` of one tile in one row: window sums slid along the row over the band's
/// `nb` blocks (`NB` of them in registers; `NB` = [`MAX_BLOCKS`] runs through the first `nb`),
/// each pixel's own interval masked inside them, its winner, rival and decision, and its
/// pairs splatted onto the right row.
///
/// # Safety
/// AVX2 must be available; `px` must describe a tile of [`tile_row`] with `nb ≤ NB` blocks
/// in its band.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn tile_pixels<const NB: usize>(px: TilePixels, s: &mut StripeScratch, nb: usize) {
    use crate::stereo::kernels::avx2::hmin;
    use std::arch::x86_64::*;
    let TilePixels { p, g, cs, sad, right_copies, stride, lo, k0, xs: (xa, xb), x0 } = px;
    let (w, n, b) = (g.w, g.n, 2 * g.r + 1);
    let nb = if NB <= 4 { NB } else { nb };
    let ones = _mm256_set1_epi16(-1);
    let mut kv = [_mm256_setzero_si256(); NB];
    for (j, k) in kv.iter_mut().enumerate().take(nb) {
        *k = _mm256_add_epi16(_mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15), _mm256_set1_epi16(16 * j as i16));
    }
    let mut lanes = [_mm256_setzero_si256(); NB];
    let mut masked = [ones; NB];
    let check_texture = p.texture_threshold > 0;
    for x in xa..=xb {
        let c = x - x0;
        let row = sad.add(x * n + k0);
        if x == xa {
            for (j, lane) in lanes.iter_mut().enumerate().take(nb) {
                let mut acc = _mm256_load_si256(cs.add(c * n + k0 + 16 * j) as *const __m256i);
                for cc in c + 1..c + b {
                    acc = _mm256_add_epi16(acc, _mm256_load_si256(cs.add(cc * n + k0 + 16 * j) as *const __m256i));
                }
                *lane = acc;
            }
        } else {
            let (add, sub) = (cs.add((c + b - 1) * n + k0), cs.add((c - 1) * n + k0));
            for (j, lane) in lanes.iter_mut().enumerate().take(nb) {
                let a = _mm256_load_si256(add.add(16 * j) as *const __m256i);
                let o = _mm256_load_si256(sub.add(16 * j) as *const __m256i);
                *lane = _mm256_sub_epi16(_mm256_add_epi16(*lane, a), o);
            }
        }
        for (j, lane) in lanes.iter().enumerate().take(nb) {
            _mm256_store_si256(row.add(16 * j) as *mut __m256i, *lane);
        }
        let (t0, t1) = (*s.tlo.get_unchecked(x), *s.thi.get_unchecked(x));
        if t0 > t1 {
            continue;
        }
        let tex = if check_texture { *s.tex_row.get_unchecked(x) } else { 0 };
        // Lanes outside the pixel's interval read as u16::MAX (whole blocks outside it too:
        // their splat leaves the right row as it is).
        let (a, bb) = (_mm256_set1_epi16((t0 - lo) as i16), _mm256_set1_epi16((t1 - lo) as i16));
        let mut minv = ones;
        let rm = right_copies.add((x % RIGHT_COPIES) * stride + w - 1 - x + k0);
        for j in 0..nb {
            let out = _mm256_or_si256(_mm256_cmpgt_epi16(a, kv[j]), _mm256_cmpgt_epi16(kv[j], bb));
            let m = _mm256_or_si256(lanes[j], out);
            masked[j] = m;
            minv = _mm256_min_epu16(minv, m);
            let rmj = rm.add(16 * j) as *mut __m256i;
            _mm256_storeu_si256(rmj, _mm256_min_epu16(_mm256_loadu_si256(rmj), m));
        }
        let min = hmin(minv);
        let target = _mm256_set1_epi16(min as i16);
        let mut best = 0;
        for (j, m) in masked.iter().enumerate().take(nb) {
            let bits = _mm256_movemask_epi8(_mm256_cmpeq_epi16(*m, target)) as u32;
            if bits != 0 {
                best = 16 * j + bits.trailing_zeros() as usize / 2;
                break;
            }
        }
        let rival = if p.uniqueness_ratio == 0 {
            u16::MAX
        } else {
            let (below, above) = (_mm256_set1_epi16(best as i16 - 2), _mm256_set1_epi16(best as i16 + 2));
            let mut rv = ones;
            for j in 0..nb {
                let near = _mm256_and_si256(_mm256_cmpgt_epi16(kv[j], below), _mm256_cmpgt_epi16(above, kv[j]));
                rv = _mm256_min_epu16(rv, _mm256_or_si256(masked[j], near));
            }
            hmin(rv)
        };
        let i0 = (t0 - lo) as usize;
        let costs = std::slice::from_raw_parts(row.add(i0), (t1 - t0 + 1) as usize);
        // A `match`, not `Option::map`: the closure was not inlined into this AVX2 function.
        #[allow(clippy::manual_map)]
        let chosen = match decide_at(p, costs, min, best - i0, rival, tex) {
            Some((bi, frac)) => Some(((t0 as usize + bi) as u16, frac)),
            None => None,
        };
        *s.best.get_unchecked_mut(x) = chosen;
    }
}

