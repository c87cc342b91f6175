//! The narrow-band path: rows whose tiles search few disparities, with the pixels in the
//! vector lanes.
//!
//! The image is cut into tiles of [`TILE_W`] × [`TILE_H`] pixels; a tile's band is the
//! exact union of its pixels' searched intervals (`tile_bands`), not widened to blocks. For
//! every disparity of the band, the tile keeps the vertical window sums of its columns and
//! their window's halo in one row of `u16` lanes (one lane per column), slid down row by row
//! where the previous row's band held that disparity and summed afresh elsewhere (the new
//! part of a band at a tile row, or after a gap). A row of the tile then costs, per disparity of the band:
//!
//! - the slide: the new and the old window row's absolute differences, sixteen columns per
//!   instruction (the right row is stored reversed, so its sixteen bytes are reversed once);
//! - the horizontal window sum of each of the 32 pixels from the column sums;
//! - each pixel's own interval as a lane mask (pairs outside it read as `u16::MAX`), the
//!   winner (first lowest: a lane moves only on a strictly lower cost) as a vertical
//!   minimum with its disparity blended in, and the splat onto the right row for the
//!   left–right check;
//!
//! and the rival for the uniqueness test is a second vertical pass over the kept costs. The
//! work is therefore proportional to the pairs of the band, about three instructions per
//! (pixel, disparity) pair, and nothing per pixel but the final decision (texture,
//! uniqueness, sub-pixel fit).
//!
//! The results are those of the row path (`rows.rs`) for the same intervals: the same
//! costs, the same winner, rival, texture, sub-pixel fit and left–right check
//! (`narrow_band_tiles_agree_with_the_row_path`).

use std::ops::Range;

use super::rows::right_start;
use super::scratch::{clamp_row, Geometry, Slack, StripeScratch, TileSums, PF_SLACK, TILE_W};
use crate::stereo::params::ValidMatchParams;

/// Copies of the right row's minima the disparities of a tile take turns at: the next
/// disparity's read-modify-write overlaps this one's by all but one lane, and reading a
/// store still in flight stalls; the copies are merged after the row.
const RIGHT_COPIES: usize = 4;

/// Sixteen-column chunks of a tile's window columns (`TILE_W + 2r`).
pub(super) fn chunks(g: Geometry) -> usize {
    (TILE_W + 2 * g.r).div_ceil(16)
}

/// Entries of one disparity's column sums in a tile (whole chunks).
pub(super) fn tile_cols(g: Geometry) -> usize {
    16 * chunks(g)
}

/// Entries of the forward right-row minima: index `x + n − 1 − k` for left pixel `x` at
/// disparity index `k` (every lane of the last tile included).
pub(super) fn right_len(g: Geometry) -> usize {
    g.w.next_multiple_of(TILE_W) + g.n + 16
}

/// Matches the searched pixels of row `y` inside `span`, tile by tile: fills the winners
/// `s.win_*`, and for the tests that read them the tiles' costs `s.tile_cost` (uniqueness,
/// left–right check) and the forward right-row minima in the first `s.tile_right` copy
/// (left–right check), for [`tile_check`]. Without those tests (SGM's refinement) neither
/// is written: each disparity of a tile then costs a store and a read-modify-write less.
///
/// # Safety
/// AVX2 must be available; `s` must be sized by the stripe set-up, `s.tile_lo/hi` hold this
/// tile row's bands and `s.tlo/thi` this row's intervals (`TILE_W` entries past `w` with
/// nothing searched).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn tile_row(p: &ValidMatchParams, g: Geometry, pf: Slack, y: usize, s: &mut StripeScratch, span: Range<usize>) {
    match (p.lr_max_diff.is_some(), p.uniqueness_ratio > 0) {
        (true, _) => tile_row_with::<true, true>(p, g, pf, y, s, span),
        (false, true) => tile_row_with::<false, true>(p, g, pf, y, s, span),
        (false, false) => tile_row_with::<false, false>(p, g, pf, y, s, span),
    }
}

/// [`tile_row`] writing the right-row minima (`SPLAT`) and the tiles' costs (`COSTS`) or not.
///
/// # Safety
/// As [`tile_row`]; `SPLAT` when the left–right check runs, `COSTS` when it or the
/// uniqueness test does.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn tile_row_with<const SPLAT: bool, const COSTS: bool>(p: &ValidMatchParams, g: Geometry, pf: Slack, y: usize, s: &mut StripeScratch, span: Range<usize>) {
    use std::arch::x86_64::*;
    let Geometry { w, h, r, wp, n, .. } = g;
    let wr = g.wr();
    let (nch, cw) = (chunks(g), tile_cols(g));
    let tiles = w.div_ceil(TILE_W);
    assert!(pf.left.len() >= h * wp + 2 * PF_SLACK && pf.right.len() >= h * wr + 2 * PF_SLACK);
    assert!(s.tile_v.len() >= tiles * n * cw && s.tile_cost.len() >= tiles * n * TILE_W && s.tile_sums.len() >= tiles);
    assert!(s.tlo.len() >= tiles * TILE_W && s.thi.len() >= tiles * TILE_W && s.tex_row.len() >= tiles * TILE_W);
    assert!([s.win_k.len(), s.win_cost.len(), s.win_keep.len(), s.win_frac.len()].iter().all(|&l| l >= tiles * TILE_W));
    let rlen = right_len(g);
    s.tile_right.resize(RIGHT_COPIES * rlen, u16::MAX);
    // Right pixels this row's span reaches: left x in span, k in 0..n.
    let rr = span.start..(span.end.next_multiple_of(TILE_W) + n).min(rlen);
    if SPLAT {
        for c in 0..RIGHT_COPIES {
            s.tile_right[c * rlen + rr.start..c * rlen + rr.end].fill(u16::MAX);
        }
    }
    // Tiles skipped below keep nothing.
    s.win_keep[span.start / TILE_W * TILE_W..span.end.next_multiple_of(TILE_W)].fill(0);
    let (lp, rp) = (pf.left.as_ptr().add(PF_SLACK), pf.right.as_ptr().add(PF_SLACK));
    let y_new = clamp_row(y as isize + r as isize, h);
    let y_old = clamp_row(y as isize - r as isize - 1, h);
    let rev = _mm_setr_epi8(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    // |a − b| of sixteen bytes, widened to sixteen u16 lanes.
    let absdiff = |a: __m128i, b: __m128i| _mm256_cvtepu8_epi16(_mm_or_si128(_mm_subs_epu8(a, b), _mm_subs_epu8(b, a)));
    // The right row's sixteen bytes for columns x0 + 16j … + 15 at disparity index k, in
    // column order: they lie backwards before `pos`.
    let right16 = |row: usize, pos: isize| _mm_shuffle_epi8(_mm_loadu_si128(rp.offset(row as isize * wr as isize + pos - 15) as *const __m128i), rev);
    let right_copies = s.tile_right.as_mut_ptr();
    for t in span.start / TILE_W..=(span.end - 1) / TILE_W {
        let (lo, hi) = (s.tile_lo[t], s.tile_hi[t]);
        if lo > hi {
            continue;
        }
        let x0 = t * TILE_W;
        // The pixels' intervals as i16 lanes (two halves of sixteen).
        let mut ilo = [_mm256_setzero_si256(); 2];
        let mut ihi = [_mm256_setzero_si256(); 2];
        for half in 0..2 {
            let pack = |v: &[i32]| {
                let q = v.as_ptr().add(x0 + 16 * half) as *const __m256i;
                _mm256_permute4x64_epi64::<0xD8>(_mm256_packs_epi32(_mm256_loadu_si256(q), _mm256_loadu_si256(q.add(1))))
            };
            ilo[half] = pack(&s.tlo);
            ihi[half] = pack(&s.thi);
        }
        // Lanes with nothing to search (lo > hi), and whether each half has any other.
        let unsearched = [0, 1].map(|hf| _mm256_cmpgt_epi16(ilo[hf], ihi[hf]));
        let searched = unsearched.map(|u| _mm256_movemask_epi8(u) as u32 != u32::MAX);
        if !searched[0] && !searched[1] {
            // Nothing searched here this row: the sums fall behind and are summed afresh
            // when the tile is needed again.
            continue;
        }
        let vt = s.tile_v.as_mut_ptr().add(t * n * cw);
        // The part of the band whose sums hold the previous row slides down; the rest (all
        // of it after a gap) is summed afresh.
        let state = &mut s.tile_sums[t];
        let (keep_lo, keep_hi) = if state.row.wrapping_add(1) == y { (lo.max(state.lo), hi.min(state.hi)) } else { (1, 0) };
        *state = TileSums { lo, hi, row: y };
        // The left window rows' chunks, shared by every disparity.
        let lchunk = |row: usize, j: usize| _mm_loadu_si128(lp.add(row * wp + x0 + 16 * j) as *const __m128i);
        let pos: [isize; 4] = std::array::from_fn(|j| if j < nch { right_start(g, x0 + 16 * j) } else { 0 });
        // Vertical window sums of the tile's columns, down to row y, for every k of the band.
        if keep_lo <= keep_hi {
            let ln: [__m128i; 4] = std::array::from_fn(|j| if j < nch { lchunk(y_new, j) } else { _mm_setzero_si128() });
            let lo_: [__m128i; 4] = std::array::from_fn(|j| if j < nch { lchunk(y_old, j) } else { _mm_setzero_si128() });
            for k in keep_lo..=keep_hi {
                let col = vt.add(k as usize * cw);
                for j in 0..nch {
                    let dn = absdiff(ln[j], right16(y_new, pos[j] + k as isize));
                    let dold = absdiff(lo_[j], right16(y_old, pos[j] + k as isize));
                    let v = col.add(16 * j) as *mut __m256i;
                    _mm256_storeu_si256(v, _mm256_sub_epi16(_mm256_add_epi16(_mm256_loadu_si256(v), dn), dold));
                }
            }
        }
        for k in (lo..=hi).filter(|k| !(keep_lo..=keep_hi).contains(k)) {
            let col = vt.add(k as usize * cw);
            for j in 0..nch {
                let mut acc = _mm256_setzero_si256();
                for dy in -(r as isize)..=r as isize {
                    let yy = clamp_row(y as isize + dy, h);
                    acc = _mm256_add_epi16(acc, absdiff(lchunk(yy, j), right16(yy, pos[j] + k as isize)));
                }
                _mm256_storeu_si256(col.add(16 * j) as *mut __m256i, acc);
            }
        }
        // Window sums along the row, masked to each pixel's interval: winner, its two
        // neighbours' costs (`u16::MAX` outside the interval) and splat.
        let ones = _mm256_set1_epi16(-1);
        let mut best_c = [ones; 2];
        let mut best_k = [_mm256_setzero_si256(); 2];
        let (mut before, mut after, mut last, mut moved) = ([ones; 2], [ones; 2], [ones; 2], [_mm256_setzero_si256(); 2]);
        let cost = s.tile_cost.as_mut_ptr();
        for k in lo..=hi {
            let col = vt.add(k as usize * cw);
            let kv = _mm256_set1_epi16(k as i16);
            let rm = right_copies.add((k as usize % RIGHT_COPIES) * rlen + x0 + n - 1 - k as usize);
            for half in 0..2 {
                if !searched[half] {
                    continue;
                }
                let c0 = col.add(16 * half);
                let mut sum = _mm256_loadu_si256(c0 as *const __m256i);
                for i in 1..2 * r + 1 {
                    sum = _mm256_add_epi16(sum, _mm256_loadu_si256(c0.add(i) as *const __m256i));
                }
                let out = _mm256_or_si256(_mm256_cmpgt_epi16(ilo[half], kv), _mm256_cmpgt_epi16(kv, ihi[half]));
                let m = _mm256_or_si256(sum, out);
                if COSTS {
                    _mm256_storeu_si256(cost.add(cost_index(n, x0 + 16 * half, k as usize)) as *mut __m256i, m);
                }
                let nb = _mm256_min_epu16(m, best_c[half]);
                // Lanes whose best stays (not strictly lower): the first lowest wins.
                let stay = _mm256_cmpeq_epi16(nb, best_c[half]);
                best_k[half] = _mm256_blendv_epi8(kv, best_k[half], stay);
                best_c[half] = nb;
                // The cost after a winner is this one where the winner moved one step ago;
                // the cost before it, the previous step's.
                after[half] = _mm256_blendv_epi8(after[half], m, moved[half]);
                after[half] = _mm256_blendv_epi8(ones, after[half], stay);
                before[half] = _mm256_blendv_epi8(last[half], before[half], stay);
                moved[half] = _mm256_andnot_si256(stay, ones);
                last[half] = m;
                if SPLAT {
                    let rv = rm.add(16 * half) as *mut __m256i;
                    _mm256_storeu_si256(rv, _mm256_min_epu16(_mm256_loadu_si256(rv), m));
                }
            }
        }
        // The rival: the cheapest pair more than one disparity from the winner.
        let mut rival = [ones; 2];
        if COSTS && p.uniqueness_ratio > 0 {
            let two = _mm256_set1_epi16(2);
            let (below, above) = ([0, 1].map(|hf| _mm256_sub_epi16(best_k[hf], two)), [0, 1].map(|hf| _mm256_add_epi16(best_k[hf], two)));
            for k in lo..=hi {
                let kv = _mm256_set1_epi16(k as i16);
                for half in 0..2 {
                    let c = _mm256_loadu_si256(cost.add(cost_index(n, x0 + 16 * half, k as usize)) as *const __m256i);
                    let near = _mm256_and_si256(_mm256_cmpgt_epi16(kv, below[half]), _mm256_cmpgt_epi16(above[half], kv));
                    rival[half] = _mm256_min_epu16(rival[half], _mm256_or_si256(c, near));
                }
            }
        }
        // Each searched pixel's decision, sixteen lanes at a time (`decide_at`'s rules),
        // kept for the left–right check ([`tile_check`]).
        for half in 0..2 {
            let x = x0 + 16 * half;
            let ok = searched_ok(p, best_c[half], rival[half], s.tex_row.as_ptr().add(x), _mm256_andnot_si256(unsearched[half], ones));
            _mm256_storeu_si256(s.win_keep.as_mut_ptr().add(x) as *mut __m256i, ok);
            _mm256_storeu_si256(s.win_k.as_mut_ptr().add(x) as *mut __m256i, best_k[half]);
            _mm256_storeu_si256(s.win_cost.as_mut_ptr().add(x) as *mut __m256i, best_c[half]);
            let frac = s.win_frac.as_mut_ptr().add(x);
            if p.subpixel {
                subpixel(before[half], best_c[half], after[half], frac);
            } else {
                _mm256_storeu_ps(frac, _mm256_setzero_ps());
                _mm256_storeu_ps(frac.add(8), _mm256_setzero_ps());
            }
        }
    }
    // The copies of the right row merged into the first.
    if !SPLAT {
        return;
    }
    let (first, rest) = s.tile_right.split_at_mut(rlen);
    for c in 0..RIGHT_COPIES - 1 {
        for (m, &v) in first[rr.clone()].iter_mut().zip(&rest[c * rlen + rr.start..c * rlen + rr.end]) {
            *m = (*m).min(v);
        }
    }
}

/// Which of sixteen lanes keep their winner: searched, with enough texture (`tex`, sixteen
/// `u32`), and unique — no pair more than one disparity away (`rival`) within
/// `uniqueness_ratio` percent of the winner's cost `min`: `100 · rival > (100 + ratio) · min`,
/// which is `decide_at`'s `rival > min + min · ratio / 100` in integers.
///
/// # Safety
/// AVX2 must be available; `tex` must point at sixteen readable `u32`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn searched_ok(p: &ValidMatchParams, min: std::arch::x86_64::__m256i, rival: std::arch::x86_64::__m256i, tex: *const u32, searched: std::arch::x86_64::__m256i) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let mut ok = searched;
    // 32-bit halves, packed back to sixteen 16-bit masks.
    let wide = |v: __m256i, i: i32| if i == 0 { _mm256_cvtepu16_epi32(_mm256_castsi256_si128(v)) } else { _mm256_cvtepu16_epi32(_mm256_extracti128_si256::<1>(v)) };
    let pack = |a: __m256i, b: __m256i| _mm256_permute4x64_epi64::<0xD8>(_mm256_packs_epi32(a, b));
    if p.texture_threshold > 0 {
        // tex ≥ threshold ⇔ tex > threshold − 1 (textures are far below 2³¹).
        let thr = _mm256_set1_epi32(p.texture_threshold as i32 - 1);
        let t = |i: usize| _mm256_cmpgt_epi32(_mm256_loadu_si256(tex.add(8 * i) as *const __m256i), thr);
        ok = _mm256_and_si256(ok, pack(t(0), t(1)));
    }
    if p.uniqueness_ratio > 0 {
        let (hundred, scale) = (_mm256_set1_epi32(100), _mm256_set1_epi32(100 + p.uniqueness_ratio as i32));
        let u = |i: i32| _mm256_cmpgt_epi32(_mm256_mullo_epi32(wide(rival, i), hundred), _mm256_mullo_epi32(wide(min, i), scale));
        ok = _mm256_and_si256(ok, pack(u(0), u(1)));
    }
    ok
}

/// The sub-pixel offsets of sixteen winners from their neighbours' costs (`u16::MAX`: the
/// neighbour lies outside the interval, no fit), as `decide_at` computes them, into `out`.
///
/// # Safety
/// AVX2 must be available; `out` must point at sixteen writable `f32`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn subpixel(before: std::arch::x86_64::__m256i, min: std::arch::x86_64::__m256i, after: std::arch::x86_64::__m256i, out: *mut f32) {
    use std::arch::x86_64::*;
    let ones = _mm256_set1_epi16(-1);
    let inside = _mm256_andnot_si256(_mm256_or_si256(_mm256_cmpeq_epi16(before, ones), _mm256_cmpeq_epi16(after, ones)), ones);
    for i in 0..2 {
        let f = |v: __m256i| {
            let h = if i == 0 { _mm256_castsi256_si128(v) } else { _mm256_extracti128_si256::<1>(v) };
            _mm256_cvtepi32_ps(_mm256_cvtepu16_epi32(h))
        };
        let (c0, c1, c2) = (f(before), f(min), f(after));
        let fit = if i == 0 { _mm256_cvtepi16_epi32(_mm256_castsi256_si128(inside)) } else { _mm256_cvtepi16_epi32(_mm256_extracti128_si256::<1>(inside)) };
        let rise = _mm256_sub_ps(_mm256_max_ps(c0, c2), c1);
        let fit = _mm256_and_ps(_mm256_castsi256_ps(fit), _mm256_cmp_ps::<_CMP_GT_OQ>(rise, _mm256_setzero_ps()));
        let q = _mm256_div_ps(_mm256_sub_ps(c0, c2), _mm256_mul_ps(_mm256_set1_ps(2.0), rise));
        let q = _mm256_min_ps(_mm256_max_ps(q, _mm256_set1_ps(-0.5)), _mm256_set1_ps(0.5));
        _mm256_storeu_ps(out.add(8 * i), _mm256_and_ps(q, fit));
    }
}

/// The left–right check of a row matched by [`tile_row`] (the rule of `left_right_check`),
/// writing the disparities of `span` into `out`; returns the matches before and after it.
/// Sixteen pixels at a time: a match passes at once when its own cost reaches its right
/// pixel's minimum (nearly all do); the others look along the right pixel's diagonal.
///
/// # Safety
/// AVX2 must be available; [`tile_row`] must have matched this row with these buffers.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn tile_check(p: &ValidMatchParams, g: Geometry, s: &StripeScratch, out: &mut [f32], span: Range<usize>) -> (usize, usize) {
    use std::arch::x86_64::*;
    let Geometry { w, n, dmin, .. } = g;
    let rlen = right_len(g);
    assert!(out.len() >= w && s.tile_right.len() >= rlen + 2 && span.end <= w);
    let (mut candidates, mut passed) = (0, 0);
    let nan = _mm256_set1_ps(f32::NAN);
    let rmin = s.tile_right.as_ptr();
    let mut x = span.start / 16 * 16;
    while x < span.end {
        let keep = _mm256_loadu_si256(s.win_keep.as_ptr().add(x) as *const __m256i);
        // (Lanes not kept read as disparity index 0: their gather stays inside the row.)
        let k = _mm256_and_si256(keep, _mm256_loadu_si256(s.win_k.as_ptr().add(x) as *const __m256i));
        let own = _mm256_loadu_si256(s.win_cost.as_ptr().add(x) as *const __m256i);
        let mut pass = keep;
        if p.lr_max_diff.is_some() {
            // The right pixel's minimum at x + n − 1 − k, gathered as the low half of a
            // 32-bit read (the copy has two entries of slack).
            let base = _mm256_add_epi32(_mm256_set1_epi32((x + n - 1) as i32), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
            let target = |h: __m128i, lane0: i32| {
                let idx = _mm256_sub_epi32(_mm256_add_epi32(base, _mm256_set1_epi32(lane0)), _mm256_cvtepu16_epi32(h));
                _mm256_and_si256(_mm256_i32gather_epi32::<2>(rmin as *const i32, idx), _mm256_set1_epi32(0xffff))
            };
            let t = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi32(target(_mm256_castsi256_si128(k), 0), target(_mm256_extracti128_si256::<1>(k), 8)));
            let reached = _mm256_cmpeq_epi16(_mm256_min_epu16(own, t), own);
            pass = _mm256_and_si256(keep, reached);
            // Kept matches not passed at once: along the diagonal.
            let mut rest = (_mm256_movemask_epi8(_mm256_andnot_si256(reached, keep)) as u32) & 0x5555_5555;
            let mut extra = 0u32;
            while rest != 0 {
                let lane = rest.trailing_zeros() as usize / 2;
                rest &= rest - 1;
                if diagonal_reaches(p, g, s, x + lane) {
                    extra |= 3 << (2 * lane);
                }
            }
            if extra != 0 {
                let bits = _mm256_setr_epi32(1, 1 << 2, 1 << 4, 1 << 6, 1 << 8, 1 << 10, 1 << 12, 1 << 14);
                let lanes = |e: u32| _mm256_cmpeq_epi32(_mm256_and_si256(_mm256_set1_epi32(e as i32), bits), bits);
                let e = _mm256_permute4x64_epi64::<0xD8>(_mm256_packs_epi32(lanes(extra), lanes(extra >> 16)));
                pass = _mm256_or_si256(pass, e);
            }
        }
        let keep_bits = (_mm256_movemask_epi8(keep) as u32) & 0x5555_5555;
        let pass_bits = (_mm256_movemask_epi8(pass) as u32) & 0x5555_5555;
        // Only the span's pixels count and are written.
        let lo = span.start.saturating_sub(x).min(16);
        let hi = (span.end - x).min(16);
        let inside = (if hi == 16 { u32::MAX } else { (1u32 << (2 * hi)) - 1 }) & !((1u32 << (2 * lo)) - 1);
        candidates += (keep_bits & inside).count_ones() as usize;
        passed += (pass_bits & inside).count_ones() as usize;
        let mut vals = [0f32; 16];
        // Sixteen pixels all inside the span (most) are stored straight into the row; the
        // span's ends go through `vals` (a copy of a length known only here is a call).
        let whole = lo == 0 && hi == 16;
        let dst = if whole { out[x..x + 16].as_mut_ptr() } else { vals.as_mut_ptr() };
        for i in 0..2 {
            let half = |v: __m256i| if i == 0 { _mm256_castsi256_si128(v) } else { _mm256_extracti128_si256::<1>(v) };
            let d = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_cvtepu16_epi32(half(k)), _mm256_set1_epi32(dmin)));
            let v = _mm256_add_ps(d, _mm256_loadu_ps(s.win_frac.as_ptr().add(x + 8 * i)));
            let m = _mm256_castsi256_ps(_mm256_cvtepi16_epi32(half(pass)));
            // SAFETY: `dst` holds sixteen floats (the row's x .. x + 16, checked by the
            // slice above, or `vals`).
            _mm256_storeu_ps(dst.add(8 * i), _mm256_blendv_ps(nan, v, m));
        }
        if !whole {
            out[x + lo..x + hi].copy_from_slice(&vals[lo..hi]);
        }
        x += 16;
    }
    (candidates, passed)
}

/// Where `s.tile_cost` keeps the cost of pixel `x` at disparity index `k` in this row: per
/// tile, per disparity index, one entry per pixel of the tile (sixteen consecutive pixels of
/// a tile are consecutive entries).
#[inline(always)]
fn cost_index(n: usize, x: usize, k: usize) -> usize {
    ((x / TILE_W) * n + k) * TILE_W + x % TILE_W
}

/// Whether a pair on the diagonal of pixel `x`'s right pixel within `lr_max_diff` of its
/// winner reaches that right pixel's minimum (`left_right_check`'s rule, past its first
/// test).
#[inline(always)]
fn diagonal_reaches(p: &ValidMatchParams, g: Geometry, s: &StripeScratch, x: usize) -> bool {
    let Geometry { w, n, .. } = g;
    let k = s.win_k[x] as isize;
    let target = s.tile_right[x + n - 1 - k as usize];
    let m = p.lr_max_diff.unwrap_or(0).min(n as u32) as isize;
    (1..=m).any(|j| {
        [x as isize + j, x as isize - j].into_iter().any(|xj| {
            let kj = k + (xj - x as isize);
            xj >= 0
                && (xj as usize) < w
                && s.tlo[xj as usize] as isize <= kj
                && kj <= s.thi[xj as usize] as isize
                && s.tile_cost[cost_index(n, xj as usize, kj as usize)] <= target
        })
    })
}
