//! The winner of each pixel from its complete sums: the minimum inside the pixel's interval,
//! the uniqueness test, the sub-pixel fit, and SGBM's left–right check.

use super::super::disparity::{MatchStats, LR_TIMED_EVERY};
use super::super::params::ValidMatchParams;
use super::{Block, Geo, Sgm, LANES};

/// The smallest sum over disparity indices `lo ..= hi` outside `skip` (absolute indices,
/// none when `skip.0 > skip.1`; `s` covers `a …`), in whole blocks.
#[inline(always)]
fn min_of<const AVX2: bool>(s: &[u16], a: usize, lo: usize, hi: usize, skip: (usize, usize)) -> u16 {
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU.
        return unsafe { super::simd::masked_min(s, a, lo, hi, skip) };
    }
    masked_min(s, a, lo, hi, skip)
}

/// The smallest sum over `lo ..= hi` and the first disparity index holding it.
#[inline(always)]
fn min_and_position<const AVX2: bool>(s: &[u16], a: usize, lo: usize, hi: usize) -> (u16, usize) {
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: as in `min_of`; a searched pixel's interval is not empty.
        return unsafe { super::simd::min_at(s, a, lo, hi) };
    }
    let best = masked_min(s, a, lo, hi, (1, 0));
    (best, first_at(s, a, lo, hi, best))
}

/// The smallest sum over `lo ..= hi`, the first disparity index holding it and, with
/// `rival`, the smallest sum outside that index and its two neighbours (else `u16::MAX`).
/// (Bands of one or two blocks take [`super::simd::select_pixel`] on AVX2.)
#[inline(always)]
fn select<const AVX2: bool>(s: &[u16], a: usize, lo: usize, hi: usize, rival: bool) -> (u16, usize, u16) {
    let (best, bk) = min_and_position::<AVX2>(s, a, lo, hi);
    let second = if rival { min_of::<AVX2>(s, a, lo, hi, (bk.saturating_sub(1), bk + 1)) } else { u16::MAX };
    (best, bk, second)
}

/// Portable [`min_of`].
#[inline(always)]
fn masked_min(s: &[u16], a: usize, lo: usize, hi: usize, skip: (usize, usize)) -> u16 {
    let mut mn: Block = [u16::MAX; LANES];
    for b in (0..s.len()).step_by(LANES) {
        let blk: &Block = s[b..b + LANES].try_into().unwrap();
        for j in 0..LANES {
            let k = a + b + j;
            let inside = k >= lo && k <= hi && !(skip.0 <= k && k <= skip.1);
            mn[j] = mn[j].min(if inside { blk[j] } else { u16::MAX });
        }
    }
    mn.into_iter().fold(u16::MAX, u16::min)
}

/// The first disparity index in `lo ..= hi` whose sum is `best` (the portable half of
/// [`min_and_position`]).
#[inline(always)]
fn first_at(s: &[u16], a: usize, lo: usize, hi: usize, best: u16) -> usize {
    for b in (0..s.len()).step_by(LANES) {
        let blk: &Block = s[b..b + LANES].try_into().unwrap();
        let mut mask = 0u32;
        for j in 0..LANES {
            let k = a + b + j;
            mask |= ((blk[j] == best && k >= lo && k <= hi) as u32) << j;
        }
        if mask != 0 {
            return a + b + mask.trailing_zeros() as usize;
        }
    }
    lo
}

/// Whether left pixel `x` at disparity `di` fails the left–right check against the winning
/// splats of the right row, `right` (`sum << 32 | x`, `u64::MAX`: none): its right pixel's
/// winner lies more than `tol` away. As SGBM: a right pixel outside the image or without a
/// splat says nothing.
#[inline(always)]
fn lr_fails(right: &[u64], x: usize, di: i32, tol: u32) -> bool {
    let xr = x as i32 - di;
    // (A negative `xr` wraps to an index past the row.)
    let Some(&best) = right.get(xr as usize) else {
        return false;
    };
    let d_right = (best as u32) as i32 - xr;
    best != u64::MAX && (d_right - di).unsigned_abs() > tol
}

/// The left–right check of a row's `span` (`out`, its disparities, NaN unmatched) against
/// the winning splats `right`, eight pixels at a time: a match fails, and becomes NaN, when
/// [`lr_fails`] at both the floor and the ceiling of its disparity — the same decisions, the
/// splat's column read by a gather of its low 32 bits (all ones: no splat, as `u64::MAX`).
/// Returns where it stopped (the rest of the span, fewer than eight, is the caller's), the
/// matches looked at and those that passed.
///
/// # Safety
/// The CPU supports AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn lr_check_avx2(right: &[u64], out: &mut [f32], span: std::ops::Range<usize>, tol: u32) -> (usize, usize, usize) {
    use std::arch::x86_64::*;
    assert!(span.end <= out.len() && right.len() <= i32::MAX as usize);
    let (mut candidates, mut passed) = (0usize, 0usize);
    let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    let mut x = span.start;
    while x + 8 <= span.end {
        // SAFETY: eight values of `out` from x (x + 8 ≤ span.end ≤ out.len()).
        let d = unsafe { _mm256_loadu_ps(out.as_ptr().add(x)) };
        let matched = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_ORD_Q>(d, d));
        let xv = _mm256_add_epi32(_mm256_set1_epi32(x as i32), lanes);
        // (Exact: the floor and ceiling of a matched disparity are small integers.)
        let (lo, hi) = (_mm256_cvttps_epi32(_mm256_floor_ps(d)), _mm256_cvttps_epi32(_mm256_ceil_ps(d)));
        // SAFETY: the CPU supports AVX2; the gathers read `right` inside it only.
        let fail = unsafe { _mm256_and_si256(lr_fails8(right, xv, lo, matched, tol), lr_fails8(right, xv, hi, matched, tol)) };
        let kept = _mm256_blendv_ps(d, _mm256_set1_ps(f32::NAN), _mm256_castsi256_ps(fail));
        // SAFETY: as the load above.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr().add(x), kept) };
        candidates += _mm256_movemask_ps(_mm256_castsi256_ps(matched)).count_ones() as usize;
        passed += _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_andnot_si256(fail, matched))).count_ones() as usize;
        x += 8;
    }
    (x, candidates, passed)
}

/// Left pixel `x`'s winning match (disparity `di`, sum `best`) splatted onto its right pixel
/// in `right`: the cheapest splat wins; ties go to the smaller x, i.e. the smaller disparity.
#[inline(always)]
fn splat(right: &mut [u64], x: usize, di: i32, best: u16) {
    let xr = (x as i32 - di) as usize;
    right[xr] = right[xr].min((best as u64) << 32 | x as u64);
}

/// [`lr_fails`] for eight pixels (columns `xv`, disparities `di`, lanes where `matched`):
/// all ones in the lanes that fail.
///
/// # Safety
/// The CPU supports AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn lr_fails8(right: &[u64], xv: std::arch::x86_64::__m256i, di: std::arch::x86_64::__m256i, matched: std::arch::x86_64::__m256i, tol: u32) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    let none = _mm256_set1_epi32(-1);
    let xr = _mm256_sub_epi32(xv, di);
    // The right pixel inside the row, 0 ≤ xr < w: else the check says nothing.
    let inside = _mm256_and_si256(matched, _mm256_and_si256(_mm256_cmpgt_epi32(xr, none), _mm256_cmpgt_epi32(_mm256_set1_epi32(right.len() as i32), xr)));
    // SAFETY: lane by lane, the low half of `right[xr]` where `inside` (0 ≤ xr < right.len());
    // the other lanes are not read.
    let xw = unsafe { _mm256_mask_i32gather_epi32::<8>(none, right.as_ptr() as *const i32, xr, inside) };
    let splat = _mm256_andnot_si256(_mm256_cmpeq_epi32(xw, none), inside);
    let off = _mm256_abs_epi32(_mm256_sub_epi32(_mm256_sub_epi32(xw, xr), di));
    // `off > tol` unsigned: both sides with their top bit flipped, compared signed.
    let flip = _mm256_set1_epi32(i32::MIN);
    let far = _mm256_cmpgt_epi32(_mm256_xor_si256(off, flip), _mm256_xor_si256(_mm256_set1_epi32(tol as i32), flip));
    _mm256_and_si256(splat, far)
}

/// A row's per-pixel records that the fit reads: bands, intervals, offsets of the sums, and
/// each pixel's smallest sum and its disparity index.
#[cfg(target_arch = "x86_64")]
struct FitRows<'a> {
    band_a: &'a [u16],
    band_m: &'a [u16],
    lo: &'a [u16],
    hi: &'a [u16],
    off: &'a [usize],
    best: &'a [u16],
    k: &'a [u16],
}

/// The second loop of [`Sgm::select_row`] without the uniqueness test, with the sub-pixel
/// fit, eight pixels at a time over whole groups of `span`: each searched pixel's disparity
/// index `di`, and the equiangular fit's `num` and `den` from its sums beside the winner
/// (gathered), or `(0, 1)` at its interval's ends; `den` 0 where nothing was searched — the
/// scalar loop's values. Returns where it stopped (the rest, fewer than eight, is the
/// caller's).
///
/// # Safety
/// The CPU supports AVX2; `sum` holds every pixel's band at its offset and one value more.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fit_avx2(r: FitRows, span: std::ops::Range<usize>, dmin: i32, sum: &[u16], (di, num, den): (&mut [i32], &mut [i32], &mut [i32])) -> usize {
    use std::arch::x86_64::*;
    let n = r.band_m.len();
    assert!(span.end <= n && [r.band_a.len(), r.lo.len(), r.hi.len(), r.off.len(), r.best.len(), r.k.len(), di.len(), num.len(), den.len()].iter().all(|&l| l == n));
    let (zero, one) = (_mm256_setzero_si256(), _mm256_set1_epi32(1));
    // Lanes 0, 2, 4 and 6 — the low 32 bits of four u64 — moved to the first four.
    let low = _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6);
    let mut x = span.start;
    while x + 8 <= span.end {
        // SAFETY (loads): eight values of each row from x, x + 8 ≤ n.
        let ld = |v: &[u16]| unsafe { _mm256_cvtepu16_epi32(_mm_loadu_si128(v.as_ptr().add(x) as *const __m128i)) };
        let (m, a, lo, hi, best, k) = (ld(r.band_m), ld(r.band_a), ld(r.lo), ld(r.hi), ld(r.best), ld(r.k));
        let searched = _mm256_cmpgt_epi32(m, zero);
        // The fit where the winner has a neighbour inside the interval on both sides.
        let fit = _mm256_and_si256(searched, _mm256_and_si256(_mm256_cmpgt_epi32(k, lo), _mm256_cmpgt_epi32(hi, k)));
        // Each pixel's offset from the first one's (small: eight bands).
        let base = r.off[x];
        let (o0, o1) = unsafe { (_mm256_loadu_si256(r.off.as_ptr().add(x) as *const __m256i), _mm256_loadu_si256(r.off.as_ptr().add(x + 4) as *const __m256i)) };
        let b = _mm256_set1_epi64x(base as i64);
        let rel = _mm256_blend_epi32::<0b1111_0000>(_mm256_permutevar8x32_epi32(_mm256_sub_epi64(o0, b), low), _mm256_permutevar8x32_epi32(_mm256_sub_epi64(o1, b), low));
        let at = _mm256_sub_epi32(_mm256_add_epi32(rel, k), a);
        // SAFETY: where `fit`, lo < k < hi inside the band (a ≤ lo, hi < a + m), so both
        // reads — 32 bits from the sums at k − 1 and at k + 1 — end at most one value past
        // the pixel's band: inside `sum`, which has values of slack past the last band.
        // The other lanes are not read.
        let p = unsafe { sum.as_ptr().add(base) as *const i32 };
        let (s0, s2) = unsafe { (_mm256_mask_i32gather_epi32::<2>(zero, p, _mm256_sub_epi32(at, one), fit), _mm256_mask_i32gather_epi32::<2>(zero, p, _mm256_add_epi32(at, one), fit)) };
        let mask16 = _mm256_set1_epi32(0xffff);
        let (s0, s2) = (_mm256_and_si256(s0, mask16), _mm256_and_si256(s2, mask16));
        let rise = _mm256_max_epi32(_mm256_sub_epi32(_mm256_max_epi32(s0, s2), best), one);
        let num_v = _mm256_and_si256(fit, _mm256_sub_epi32(s0, s2));
        // 2 · rise where fitted, 1 elsewhere searched, 0 where nothing was.
        let den_v = _mm256_blendv_epi8(_mm256_and_si256(searched, one), _mm256_add_epi32(rise, rise), fit);
        let di_v = _mm256_add_epi32(_mm256_set1_epi32(dmin), k);
        // SAFETY (stores): eight values of each row from x, x + 8 ≤ n.
        unsafe {
            _mm256_storeu_si256(di.as_mut_ptr().add(x) as *mut __m256i, di_v);
            _mm256_storeu_si256(num.as_mut_ptr().add(x) as *mut __m256i, num_v);
            _mm256_storeu_si256(den.as_mut_ptr().add(x) as *mut __m256i, den_v);
        }
        x += 8;
    }
    x
}

impl Sgm {
    /// [`Sgm::select_row`], on AVX2 compiled as a function of its own. Compiled only as part
    /// of the whole matcher, its per-pixel helpers (`min_at`, `masked_min`) stayed calls, one
    /// per pixel; on its own they are inlined into it (and LLVM may then inline it back
    /// whole).
    #[inline(always)]
    pub(super) fn select<const AVX2: bool>(&mut self, p: &ValidMatchParams, g: Geo, y: usize, out: &mut [f32], stats: &mut MatchStats) {
        #[cfg(target_arch = "x86_64")]
        if AVX2 {
            // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU.
            return unsafe { self.select_row_avx2(p, g, y, out, stats) };
        }
        self.select_row::<false>(p, g, y, out, stats)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,popcnt")]
    unsafe fn select_row_avx2(&mut self, p: &ValidMatchParams, g: Geo, y: usize, out: &mut [f32], stats: &mut MatchStats) {
        self.select_row::<true>(p, g, y, out, stats)
    }

    /// Winner, uniqueness, sub-pixel fit and left–right check of row `y`, whose sums are
    /// complete.
    ///
    /// The left–right check is SGBM's: each left pixel that keeps a match splats it onto its
    /// right pixel, where the cheapest splat wins; a match fails when its right pixel's winner
    /// (at both the floor and the ceiling of the sub-pixel disparity) differs by more than
    /// `lr_max_diff`. The classic check — every pair on the right pixel's diagonal competing —
    /// was tried first: it compares aggregated sums of different left pixels, whose levels
    /// differ, and rejected 5–7 % of correct matches on Tsukuba (docs/matcher.md).
    #[inline(always)]
    fn select_row<const AVX2: bool>(&mut self, p: &ValidMatchParams, g: Geo, y: usize, out: &mut [f32], stats: &mut MatchStats) {
        let Geo { w, dmin, .. } = g;
        let uniq = p.uniqueness_ratio;
        self.right_best.fill(u64::MAX);
        // Per pixel the winner and the terms of its fit, `d = di + num / den` (den = 0: no
        // match); the divisions then run over the row in vector lanes, not one per pixel
        // behind the next.
        let (di_row, num_row, den_row) = (&mut self.fit_di[..w], &mut self.fit_num[..w], &mut self.fit_den[..w]);
        // Nothing outside the row's span is searched: those pixels are unmatched (the span's
        // are all written below).
        let span = self.span[y].clone();
        out[..span.start].fill(f32::NAN);
        out[span.end..].fill(f32::NAN);
        den_row[span.clone()].fill(0);
        // The row's per-pixel records sliced once (not indexed through `self` per pixel).
        let row = y * w..(y + 1) * w;
        let (band_a, band_m, lo_row, hi_row, off_row) = (&self.band_a[row.clone()], &self.band_m[row.clone()], &self.lo[row.clone()], &self.hi[row.clone()], &self.off[row]);
        let (sum, right_best) = (&self.sum[..], &mut self.right_best[..w]);
        // Each searched pixel's smallest sum, its disparity index and its rival.
        let (win_best, win_k, win_rival) = (&mut self.win_best[..w], &mut self.win_k[..w], &mut self.win_rival[..w]);
        for x in span.clone() {
            let m = band_m[x] as usize;
            if m == 0 {
                continue;
            }
            let (a, lo, hi) = (band_a[x] as usize, lo_row[x] as usize, hi_row[x] as usize);
            // One or two blocks in registers, a pixel at a time (two blocks read: the sums
            // have `LANES` values of slack past the last band).
            #[cfg(target_arch = "x86_64")]
            if AVX2 && m <= 2 * LANES {
                // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU; the
                // interval lies inside the band, at most two blocks.
                let (best, j, rival) = unsafe { super::simd::select_pixel(&sum[off_row[x]..][..2 * LANES], lo - a, hi - a, uniq > 0) };
                (win_best[x], win_k[x], win_rival[x]) = (best, (a + j) as u16, rival);
                continue;
            }
            let (best, bk, rival) = select::<AVX2>(&sum[off_row[x]..][..m], a, lo, hi, uniq > 0);
            (win_best[x], win_k[x], win_rival[x]) = (best, bk as u16, rival);
        }
        // Without the uniqueness test, the winners' disparities and fits eight at a time,
        // then their splats one by one (two may land on one right pixel); the rest of the
        // span below.
        let mut x = span.start;
        #[cfg(target_arch = "x86_64")]
        if AVX2 && uniq == 0 && p.subpixel {
            let rows = FitRows { band_a, band_m, lo: lo_row, hi: hi_row, off: off_row, best: win_best, k: win_k };
            // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU; `sum` has
            // one value past the last pixel's band.
            x = unsafe { fit_avx2(rows, span.clone(), dmin, sum, (di_row, num_row, den_row)) };
            for x in span.start..x {
                if band_m[x] > 0 {
                    splat(right_best, x, di_row[x], win_best[x]);
                }
            }
        }
        for x in x..span.end {
            let m = band_m[x] as usize;
            if m == 0 {
                continue;
            }
            let (best, bk, rival) = (win_best[x], win_k[x] as usize, win_rival[x]);
            if uniq > 0 && (rival as u32) * (100 - uniq) < best as u32 * 100 {
                continue;
            }
            let (a, lo, hi) = (band_a[x] as usize, lo_row[x] as usize, hi_row[x] as usize);
            let di = dmin + bk as i32;
            splat(right_best, x, di, best);
            di_row[x] = di;
            (num_row[x], den_row[x]) = if p.subpixel && bk > lo && bk < hi {
                // Equiangular (V-shaped) fit: census sums rise about linearly away from the
                // minimum (docs/matcher.md: the parabola and a correlation-cost fit measured).
                let s = &sum[off_row[x]..][..m];
                let (s0, s2) = (s[bk - 1 - a] as i32, s[bk + 1 - a] as i32);
                let rise = (s0.max(s2) - best as i32).max(1);
                (s0 - s2, 2 * rise)
            } else {
                // d + 0 / 1 = d exactly.
                (0, 1)
            };
        }
        for x in span.clone() {
            let d = di_row[x] as f32 + num_row[x] as f32 / den_row[x].max(1) as f32;
            out[x] = if den_row[x] != 0 { d } else { f32::NAN };
        }
        // (Timed on one row in LR_TIMED_EVERY: a clock read costs tens of nanoseconds.)
        let t0 = (y % LR_TIMED_EVERY == 0).then(std::time::Instant::now);
        // Eight at a time on AVX2, the rest below.
        let mut x = span.start;
        #[cfg(target_arch = "x86_64")]
        if let (true, Some(tol)) = (AVX2, p.lr_max_diff) {
            // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU.
            let (done, candidates, passed) = unsafe { lr_check_avx2(&self.right_best[..w], out, span.clone(), tol) };
            x = done;
            stats.lr_candidates += candidates;
            stats.lr_passed += passed;
        }
        for x in x..span.end {
            let d = out[x];
            if d.is_nan() {
                continue;
            }
            stats.lr_candidates += 1;
            if let Some(tol) = p.lr_max_diff {
                let right = &self.right_best[..w];
                if lr_fails(right, x, d.floor() as i32, tol) && lr_fails(right, x, d.ceil() as i32, tol) {
                    out[x] = f32::NAN;
                    continue;
                }
            }
            stats.lr_passed += 1;
        }
        stats.lr_check_ns += t0.map_or(0, |t0| t0.elapsed().as_nanos() as u64 * LR_TIMED_EVERY as u64);
    }
}


#[cfg(test)]
mod tests {
    use super::*;

    /// The selection in registers over any number of blocks (`min_at` and the masked
    /// minimum) is the portable one: bands of one to eight blocks, intervals anywhere
    /// in them, many ties and equal rivals, within and across blocks.
    #[test]
    fn selection_in_registers_is_the_portable_one() {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            let mut next = crate::testing::xorshift(0x9e37_79b9_7f4a_7c15);
            for case in 0..8000 {
                let m = (1 + (next() % 8) as usize) * LANES;
                // Few distinct values, so that ties and equal rivals are common.
                let s: Vec<u16> = (0..m).map(|_| (next() % 6) as u16 * 100 + 40).collect();
                let a = (next() % 4) as usize * LANES;
                let lo = a + (next() % m as u64) as usize;
                let hi = lo + (next() % (a + m - lo) as u64) as usize;
                let best = masked_min(&s, a, lo, hi, (1, 0));
                let bk = first_at(&s, a, lo, hi, best);
                let rival = masked_min(&s, a, lo, hi, (bk.saturating_sub(1), bk + 1));
                let got = select::<true>(&s, a, lo, hi, true);
                assert_eq!(got, (best, bk, rival), "case {case}: {m} disparities from {a}, {lo} ..= {hi}: {s:?}");
                assert_eq!(select::<true>(&s, a, lo, hi, false), (best, bk, u16::MAX));
            }
        }
    }

    /// A pixel of one or two blocks selected in registers (`select_pixel`, which reads two
    /// blocks either way) is the portable selection over its own band: intervals anywhere in
    /// it, many ties and equal rivals, and the next pixel's sums after a one-block band.
    #[test]
    fn a_pixel_in_registers_selects_as_the_portable_selection() {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            let mut next = crate::testing::xorshift(0x2545_f491_4f6c_dd1d);
            for case in 0..4000 {
                let m = (1 + case % 2) * LANES;
                // Few distinct values, so that ties and equal rivals are common; past a
                // one-block band, smaller ones (that must not win).
                let s: Vec<u16> = (0..2 * LANES).map(|i| if i < m { (next() % 5) as u16 * 100 + 40 } else { (next() % 40) as u16 }).collect();
                let a = (next() % 4) as usize * LANES;
                let jlo = (next() % m as u64) as usize;
                let jhi = jlo + (next() % (m - jlo) as u64) as usize;
                for rival in [true, false] {
                    let best = masked_min(&s[..m], a, a + jlo, a + jhi, (1, 0));
                    let bk = first_at(&s[..m], a, a + jlo, a + jhi, best);
                    let second = if rival { masked_min(&s[..m], a, a + jlo, a + jhi, (bk.saturating_sub(1), bk + 1)) } else { u16::MAX };
                    // SAFETY: the CPU has AVX2 (checked above); two blocks, the interval
                    // inside the band.
                    let (got_best, j, got_second) = unsafe { crate::stereo::sgm::simd::select_pixel(&s, jlo, jhi, rival) };
                    assert_eq!((got_best, a + j, got_second), (best, bk, second), "case {case}: {m} disparities from {a}, lanes {jlo} ..= {jhi}, rival {rival}: {s:?}");
                }
            }
        }
    }
}
