//! SGM's sub-pixel refinement by the correlation cost (`--method sgm`, `sgm_refine`), and its
//! masked correlation on a scan's rim.
//!
//! SGM's aggregated sums are flattened by the smoothness penalties, so its own sub-pixel
//! values step along slanted surfaces; the correlation cost around SGM's winner gives most
//! of the sub-pixel disparity instead, blended with SGM's own. On a scan's rim — where a
//! pixel's window reaches the background that segmentation left unsearched — the window
//! straddles the silhouette and the correlation is pulled off: there it is taken over the
//! window's object pixels alone (docs/matcher.md, "The rim").

use std::ops::Range;

use super::rows::equiangular;
use super::scratch::{Geometry, PF_SLACK};
use super::source::{around, matched_spans, IntervalSource};
use super::{Method, StereoMatcher};
use crate::stereo::disparity::{DisparityIntervals, DisparityMap, GrayView, MatchStats};

/// SGM's share of a refined disparity where its own sub-pixel value `d` and the correlation's
/// `c` lie within [`OWN_WEIGHT_FROM_PX`] of each other. Wherever the two agree, the refined
/// value is `c + w · (d − c − offset)`, with `w` = [`own_weight`]: this share near agreement,
/// more further apart. The two fits err partly independently (their noise differs: the
/// correlation's median error is about half SGM's own), so the blend is closer than either;
/// but SGM's fit through its penalised sums leans one way, by an amount that follows the
/// surface's slant (on the ideal egg −0.11 px on average, −0.01 to −0.18 px by slant), which
/// a fused model would keep: `offset` is the mean of `d − c` over each [`OFFSET_TILE`]-pixel
/// square's agreeing pixels, so the blend takes SGM's deviations around it and not the lean
/// itself (docs/matcher.md, "Two sub-pixel estimates").
pub(super) const OWN_WEIGHT: f32 = 0.2;

/// How far apart, pixels, SGM's value and the correlation's may lie before SGM's share of the
/// blend grows beyond [`OWN_WEIGHT`]; from there it grows evenly, to [`OWN_WEIGHT_MAX`] at
/// [`OWN_WEIGHT_MAX_PX`]. Where the two disagree, the truth lies mostly between them: on the
/// ideal egg, torus, faint egg and bunny, the pixels 0.75–1 px apart had the correlation's
/// value at a median error of 0.42–0.64 px, SGM's own at 0.31–0.48, and their even mean at
/// 0.28–0.34. But between 0.25 and 0.5 px apart, a larger share of SGM's value already
/// blurred the bunny's finer shape (docs/matcher.md, "SGM's share of the blend grows with the
/// disagreement").
pub(super) const OWN_WEIGHT_FROM_PX: f32 = 0.25;

/// SGM's largest share of the blend: an even mean.
pub(super) const OWN_WEIGHT_MAX: f32 = 0.5;

/// How far apart, pixels, the two values lie where the blend becomes an even mean (and stays
/// one up to `sgm_refine_agree`, 1.25 px by default, the furthest apart they are blended).
pub(super) const OWN_WEIGHT_MAX_PX: f32 = 1.0;

/// SGM's share of the blend of its value `d` with the correlation's `c`: [`OWN_WEIGHT`] where
/// they lie within [`OWN_WEIGHT_FROM_PX`], rising evenly to [`OWN_WEIGHT_MAX`] at
/// [`OWN_WEIGHT_MAX_PX`] apart (and no further).
#[inline(always)]
pub(super) fn own_weight(d: f32, c: f32) -> f32 {
    let t = ((d - c).abs() - OWN_WEIGHT_FROM_PX) / (OWN_WEIGHT_MAX_PX - OWN_WEIGHT_FROM_PX);
    OWN_WEIGHT + (OWN_WEIGHT_MAX - OWN_WEIGHT) * t.clamp(0.0, 1.0)
}

/// Side of the squares over which SGM's lean from the correlation ([`OWN_WEIGHT`]) is
/// averaged, pixels. Smaller squares take out more of the lean's slow changes and leave more
/// of SGM's noise: on 120-view realistic rings, squares of 32 gave views with a lower median
/// error but a fused egg 4 % further from the truth than without the blend, squares of 16
/// a fused model within 1 % or closer (docs/matcher.md, "Two sub-pixel estimates").
pub(super) const OFFSET_TILE: usize = 16;

/// How close the rim's correlation over the object must come to SGM's value to stand for the
/// correlation's (elsewhere `sgm_refine_agree`; here that where it is closer still): its
/// window holds fewer pixels, and each rim pixel a view gains is less precise than its median
/// one — at 1 px the realistic egg ring's views' median distance rose above `bm`'s, at 0.5 px
/// it did not (docs/matcher.md, "The rim").
const RIM_AGREE_PX: f32 = 0.5;

/// The refinement's buffers, reused between calls.
pub(super) struct RefineScratch {
    /// The correlation's disparities.
    corr: DisparityMap,
    /// Per row, its first to last matched pixel.
    spans: Vec<Range<usize>>,
    /// The masked pass's rows ([`RimRows`]) and the pixels it looks at.
    rim: RimRows,
    candidates: Vec<u32>,
    /// Per square of [`OFFSET_TILE`] pixels, SGM's mean lean from the correlation, and the
    /// agreeing pixels it is taken over.
    lean: Vec<f32>,
    agreeing: Vec<u32>,
    /// The leans of a row of squares, one per column of the image.
    lean_row: Vec<f32>,
}

impl Default for RefineScratch {
    fn default() -> Self {
        RefineScratch { corr: DisparityMap::new(0, 0), spans: Vec::new(), rim: RimRows::default(), candidates: Vec::new(), lean: Vec::new(), agreeing: Vec::new(), lean_row: Vec::new() }
    }
}

impl StereoMatcher {
    /// SGM's sub-pixel disparities taken from the correlation cost: each matched pixel is
    /// correlated again (the `bm` cost, the `sgm_refine_block` window, no uniqueness,
    /// texture, left–right or speckle test) over its SGM disparity ± 2, and where the
    /// correlation's sub-pixel disparity lies within `sgm_refine_agree` (1.25 px) of SGM's, the
    /// two are blended ([`own_weight`]).
    /// Where they disagree in a `masked` match (a scan's view: the object segmented, the
    /// background unsearched, as `searched` tells), the match is dropped — a view's missing
    /// pixel is seen by its neighbours while a wrong one spoils the fused surface — unless
    /// its window reaches the background and the correlation over the window's searched
    /// pixels alone ([`RimRows`]) lies within [`RIM_AGREE_PX`] (or `sgm_refine_agree` where
    /// closer) of SGM's value, with which it is then blended. On a whole image (a single pair) SGM's value stays where they disagree:
    /// there density matters and there is no rim.
    pub(super) fn refine_subpixel(&mut self, left: GrayView, right: GrayView, searched: &DisparityIntervals, out: &mut DisparityMap, masked: bool, totals: &mut MatchStats) {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { self.refine_avx2(left, right, searched, out, masked, totals) };
        }
        self.refine::<false>(left, right, searched, out, masked, totals)
    }

    /// [`StereoMatcher::refine_subpixel`] compiled for AVX2: its passes over the map are
    /// written branch-free so that they vectorise, in eight lanes here instead of the
    /// baseline's four. The same operations in the same order (no fused multiply-add, the
    /// lean summed in its eight running sums either way), so the same disparities.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn refine_avx2(&mut self, left: GrayView, right: GrayView, searched: &DisparityIntervals, out: &mut DisparityMap, masked: bool, totals: &mut MatchStats) {
        self.refine::<true>(left, right, searched, out, masked, totals)
    }

    /// The body of [`StereoMatcher::refine_subpixel`].
    #[inline(always)]
    pub(super) fn refine<const AVX2: bool>(&mut self, left: GrayView, right: GrayView, searched: &DisparityIntervals, out: &mut DisparityMap, masked: bool, totals: &mut MatchStats) {
        let (w, h) = (left.width, left.height);
        let p = &self.params;
        let (dmin, dmax) = (p.min_disparity, p.max_disparity());
        let agree = p.sgm_refine_agree;
        let bm = crate::stereo::MatchParams { method: Method::Bm, uniqueness_ratio: 0, texture_threshold: 0, lr_max_diff: None, speckle_window: 0, block: p.sgm_refine_block, ..(**p).clone() }.validate().expect("the sgm parameters with the correlation's tests off are valid");
        let mut s = std::mem::take(&mut self.refine);
        // Per row, only from its first match to its last: outside them nothing is searched,
        // and nothing changes below.
        matched_spans(out, &mut s.spans);
        if (s.corr.width, s.corr.height) != (w, h) {
            s.corr = DisparityMap::new(w, h);
        }
        // Each matched pixel's interval read from SGM's map as the rows are matched
        // (`around`), over the spans just found.
        let stats = self.correlate(&bm, left, right, IntervalSource::Around { map: out, spans: &s.spans }, &mut s.corr);
        totals.evaluated += stats.evaluated;
        if masked {
            // The rim's pixels are taken again only where the correlation disagrees: where it
            // agrees, its value is kept as on the rest of the object.
            s.candidates.clear();
            for (y, span) in s.spans.iter().enumerate() {
                let row = y * w + span.start..y * w + span.end;
                let (ds, cs) = (&out.values()[row.clone()], &s.corr.values()[row.clone()]);
                // Eight pixels at a time, as a bit mask: most pixels agree.
                let (dc, cc) = (ds.chunks_exact(8), cs.chunks_exact(8));
                let tail = row.start + dc.len() * 8;
                for (k, (d8, c8)) in dc.clone().zip(cc.clone()).enumerate() {
                    let mut bits = disagree_bits::<AVX2>(d8, c8, agree);
                    while bits != 0 {
                        s.candidates.push((row.start + k * 8 + bits.trailing_zeros() as usize) as u32);
                        bits &= bits - 1;
                    }
                }
                for (j, (&d, &c)) in dc.remainder().iter().zip(cc.remainder()).enumerate() {
                    if disagrees(d, c, agree) {
                        s.candidates.push((tail + j) as u32);
                    }
                }
            }
            if !s.candidates.is_empty() {
                let g = Geometry::new(&bm, w, h);
                s.rim.build(g, &self.left_pf, searched);
                for &i in &s.candidates {
                    let i = i as usize;
                    let (lo, hi) = around(out.values()[i], dmin, dmax);
                    if let Some(costs) = s.rim.costs(g, &self.right_pf_rev, i % w, i / w, lo, hi) {
                        totals.evaluated += (hi - lo + 1) as u64;
                        let c = lo as f32 + fit(&costs[..(hi - lo + 1) as usize]);
                        s.corr.values_mut()[i] = if (c - out.values()[i]).abs() <= RIM_AGREE_PX.min(agree) { c } else { f32::NAN };
                    }
                }
            }
        }
        // SGM's lean from the correlation, per square of OFFSET_TILE pixels: the mean of
        // d − c over its agreeing pixels (a square without any needs none).
        let tiles_x = w.div_ceil(OFFSET_TILE);
        let tiles = tiles_x * h.div_ceil(OFFSET_TILE);
        s.lean.clear();
        s.lean.resize(tiles, 0.0);
        s.agreeing.clear();
        s.agreeing.resize(tiles, 0);
        for (y, span) in s.spans.iter().enumerate() {
            let t0 = y / OFFSET_TILE * tiles_x;
            for (tx, cols) in tile_chunks(span.clone()) {
                let row = y * w + cols.start..y * w + cols.end;
                let (sum, n) = lean_sum(&out.values()[row.clone()], &s.corr.values()[row], agree);
                s.lean[t0 + tx] += sum;
                s.agreeing[t0 + tx] += n;
            }
        }
        for (lean, &n) in s.lean.iter_mut().zip(&s.agreeing) {
            *lean = if n > 0 { *lean / n as f32 } else { 0.0 };
        }
        // The blend, each row's span in one loop: the squares' leans are spread over a row of
        // columns once per row of squares.
        s.lean_row.resize(w, 0.0);
        for (y, span) in s.spans.iter().enumerate() {
            if y % OFFSET_TILE == 0 {
                let t0 = y / OFFSET_TILE * tiles_x;
                for (cols, &lean) in s.lean_row.chunks_mut(OFFSET_TILE).zip(&s.lean[t0..t0 + tiles_x]) {
                    cols.fill(lean);
                }
            }
            let row = y * w + span.start..y * w + span.end;
            let leans = &s.lean_row[span.clone()];
            for ((d, &c), &lean) in out.values_mut()[row.clone()].iter_mut().zip(&s.corr.values()[row]).zip(leans) {
                // Branch-free: an unmatched pixel stays unmatched.
                let agrees = agrees(*d, c, agree);
                let kept = if masked { f32::NAN } else { *d };
                *d = if agrees { c + own_weight(*d, c) * (*d - c - lean) } else { kept };
            }
        }
        self.refine = s;
    }
}

/// Whether SGM's value `d` and the correlation's `c` agree: lie within `agree` pixels
/// (`sgm_refine_agree`). NaN fails every comparison: an unmatched pixel or a missing
/// correlation disagrees.
#[inline(always)]
fn agrees(d: f32, c: f32, agree: f32) -> bool {
    (c - d).abs() <= agree
}

/// Whether SGM's `d` (matched) and the correlation's `c` disagree.
#[inline(always)]
fn disagrees(d: f32, c: f32, agree: f32) -> bool {
    !d.is_nan() && !agrees(d, c, agree)
}

/// Bit j set where `d[j]` and `c[j]` [`disagrees`], for eight pixels (`d` and `c` hold
/// eight values): on AVX2 by one vector compare, else branch-free, so that it vectorises.
#[inline(always)]
fn disagree_bits<const AVX2: bool>(d: &[f32], c: &[f32], agree: f32) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: AVX2 is only set by `refine_avx2`, whose caller checked the CPU.
        return unsafe { disagree_bits_avx2(d, c, agree) };
    }
    (0..8).fold(0u32, |m, j| m | (disagrees(d[j], c[j], agree) as u32) << j)
}

/// [`disagree_bits`] by one compare each.
///
/// # Safety
/// The CPU supports AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn disagree_bits_avx2(d: &[f32], c: &[f32], agree: f32) -> u32 {
    use std::arch::x86_64::*;
    assert!(d.len() == 8 && c.len() == 8);
    // SAFETY: eight values each, asserted above.
    let (d, c) = unsafe { (_mm256_loadu_ps(d.as_ptr()), _mm256_loadu_ps(c.as_ptr())) };
    // |c − d| ≤ agree, false where either is NaN (an ordered compare), as `agrees`.
    let off = _mm256_andnot_ps(_mm256_set1_ps(-0.0), _mm256_sub_ps(c, d));
    let close = _mm256_cmp_ps::<_CMP_LE_OQ>(off, _mm256_set1_ps(agree));
    let matched = _mm256_cmp_ps::<_CMP_ORD_Q>(d, d);
    _mm256_movemask_ps(_mm256_andnot_ps(close, matched)) as u32
}

/// The sum of `d − c` over the pixels where SGM's `d` and the correlation's `c` agree, and
/// their count. Eight running sums, so that it vectorises (one sum waits on each add);
/// inlined, so that it is compiled for the caller's vector width (`refine_avx2`).
#[inline(always)]
fn lean_sum(d: &[f32], c: &[f32], agree: f32) -> (f32, u32) {
    const LANES: usize = 8;
    let (mut sums, mut counts) = ([0.0f32; LANES], [0u32; LANES]);
    let add = |sums: &mut [f32; LANES], counts: &mut [u32; LANES], k: usize, d: f32, c: f32| {
        // Branch-free.
        let agrees = agrees(d, c, agree);
        sums[k] += if agrees { d - c } else { 0.0 };
        counts[k] += agrees as u32;
    };
    let (dc, cc) = (d.chunks_exact(LANES), c.chunks_exact(LANES));
    for (k, (&d, &c)) in dc.remainder().iter().zip(cc.remainder()).enumerate() {
        add(&mut sums, &mut counts, k, d, c);
    }
    for (d8, c8) in dc.zip(cc) {
        for k in 0..LANES {
            add(&mut sums, &mut counts, k, d8[k], c8[k]);
        }
    }
    (sums.iter().sum(), counts.iter().sum())
}

/// The columns of `span` cut at multiples of [`OFFSET_TILE`], each with its square's column.
fn tile_chunks(span: Range<usize>) -> impl Iterator<Item = (usize, Range<usize>)> {
    let mut x = span.start;
    std::iter::from_fn(move || {
        (x < span.end).then(|| {
            let tx = x / OFFSET_TILE;
            let cols = x..((tx + 1) * OFFSET_TILE).min(span.end);
            x = cols.end;
            (tx, cols)
        })
    })
}

/// The winner of `costs` (the first of equal ones) and the equiangular sub-pixel fit through it
/// and its neighbours (none at either end), as an offset from the first cost's disparity: the
/// correlation's own rule (`rows::decide_at`).
fn fit(costs: &[u32]) -> f32 {
    let (best, &min) = costs.iter().enumerate().min_by_key(|&(_, c)| *c).expect("an interval holds a disparity");
    let frac = if best > 0 && best + 1 < costs.len() { equiangular(costs[best - 1] as f32, min as f32, costs[best + 1] as f32) } else { 0.0 };
    best as f32 + frac
}

/// Lanes of one window row: sixteen columns.
const LANES: usize = 16;

/// The left image's object for the rim's masked correlation, in rows laid out as the
/// reversed right rows are (increasing disparity walks forward): per row of the image,
/// `w + 2·LANES` columns stored back to front, columns `−LANES … w + LANES − 1`, one byte
/// each: the prefiltered left value at a searched pixel (below `0x80`: at most twice the
/// prefilter's cap of 63), [`RimRows::BACKGROUND`] at an unsearched pixel of the image and
/// [`RimRows::OUTSIDE`] past its edges. (One array instead of a mask, the object and the
/// background each: a window row is one load for the costs, and one array is built.)
#[derive(Default)]
pub(super) struct RimRows {
    rows: Vec<u8>,
}

impl RimRows {
    /// An unsearched pixel of the image: the window that holds one lies on the rim.
    const BACKGROUND: u8 = 0x80;
    /// A column past the image's edge: neither searched nor background.
    const OUTSIDE: u8 = 0xff;

    /// Position of column `x` (−LANES ≤ x < w + LANES) in a row of `w` columns.
    fn at(w: usize, x: isize) -> usize {
        (w as isize + LANES as isize - 1 - x) as usize
    }

    /// The rows of a call: its searched pixels (`searched`) and the prefiltered left rows the
    /// correlation pass has just left (`left_pf`, padded by `r`; values below `0x80`).
    fn build(&mut self, g: Geometry, left_pf: &[u8], searched: &DisparityIntervals) {
        let Geometry { w, h, r, wp, .. } = g;
        let width = w + 2 * LANES;
        // Every byte is written below.
        self.rows.resize(width * h, 0);
        for (y, row) in self.rows.chunks_exact_mut(width).enumerate() {
            row[..LANES].fill(Self::OUTSIDE);
            row[LANES + w..].fill(Self::OUTSIDE);
            let lrow = &left_pf[PF_SLACK + y * wp + r..][..w];
            let (lo, hi) = (&searched.lo[y * w..][..w], &searched.hi[y * w..][..w]);
            debug_assert!(lrow.iter().all(|&l| l < Self::BACKGROUND), "a prefiltered value at or above 0x80");
            // Columns 0 … w − 1 at positions w + LANES − 1 … LANES: a reversed iterator, so
            // that it vectorises.
            for (o, ((&l, &a), &z)) in row[LANES..LANES + w].iter_mut().rev().zip(lrow.iter().zip(lo).zip(hi)) {
                *o = if a <= z { l } else { Self::BACKGROUND };
            }
        }
    }

    /// The masked SAD of pixel `(x, y)` at disparities `lo ..= hi` (at most five): over its
    /// `block × block` window's searched pixels inside the image — `None` where the window
    /// holds no unsearched pixel (not on the rim).
    fn costs(&self, g: Geometry, right_pf_rev: &[u8], x: usize, y: usize, lo: i32, hi: i32) -> Option<[u32; 5]> {
        debug_assert!(hi - lo < 5 && lo <= hi);
        if 2 * g.r + 1 > LANES {
            return self.costs_scalar(g, right_pf_rev, x, y, lo, hi);
        }
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: SSE2 is part of x86_64; the loads stay inside the buffers (see `costs_sse2`).
            unsafe { self.costs_sse2(g, right_pf_rev, x, y, lo, hi) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        self.costs_scalar(g, right_pf_rev, x, y, lo, hi)
    }

    /// [`RimRows::costs`], one pixel at a time (any window size; the reference of the vector copy).
    fn costs_scalar(&self, g: Geometry, right_pf_rev: &[u8], x: usize, y: usize, lo: i32, hi: i32) -> Option<[u32; 5]> {
        let Geometry { w, h, r, .. } = g;
        let (wr, width) = (g.wr(), w + 2 * LANES);
        let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
        let rows = y.saturating_sub(r)..(y + r + 1).min(h);
        let on_rim = rows.clone().any(|yy| (x0..x1).any(|xx| self.rows[yy * width + Self::at(w, xx as isize)] == Self::BACKGROUND));
        if !on_rim {
            return None;
        }
        let mut costs = [0u32; 5];
        for yy in rows {
            let rrow = &right_pf_rev[PF_SLACK + yy * wr..][..wr];
            for xx in x0..x1 {
                let v = self.rows[yy * width + Self::at(w, xx as isize)];
                if v >= Self::BACKGROUND {
                    continue;
                }
                let lv = v as i32;
                // The right pixel xx − d in the reversed padded row.
                let base = (wr - 1 - g.rpad_left) as i32 - xx as i32;
                for (k, c) in costs[..(hi - lo + 1) as usize].iter_mut().enumerate() {
                    *c += (lv - rrow[(base + lo + k as i32) as usize] as i32).unsigned_abs();
                }
            }
        }
        Some(costs)
    }

    /// [`RimRows::costs`] for windows of at most [`LANES`] columns: per window row, sixteen
    /// columns from the window's last one backwards, the lanes past its first masked off, and
    /// one `psadbw` per disparity.
    ///
    /// # Safety
    /// Loads of 16 bytes: the rim rows from `at(w, x + r)` = `w + LANES − 1 − x − r ≥ 0` (x < w),
    /// ending before `w + 2·LANES` (x + r ≥ 0); the right rows from
    /// `PF_SLACK + wr − rpad_left − 1 − x − r + d ≥ PF_SLACK` past the row's start
    /// (`wr − rpad_left = w + rpad_right`, `rpad_right ≥ r − dmin`) for `d` in `lo ..= lo + 4`
    /// (five read whatever `hi`), ending at most `PF_SLACK + wr + 19 − 2r` past it
    /// (`rpad_left = r + dmax`, `lo ≤ dmax`): inside the buffer, which has `PF_SLACK` (64)
    /// bytes after its last row.
    #[cfg(target_arch = "x86_64")]
    unsafe fn costs_sse2(&self, g: Geometry, right_pf_rev: &[u8], x: usize, y: usize, lo: i32, hi: i32) -> Option<[u32; 5]> {
        use std::arch::x86_64::*;
        let Geometry { w, h, r, .. } = g;
        let (wr, width) = (g.wr(), w + 2 * LANES);
        let b = 2 * r + 1;
        // Lane i holds column x + r − i: the window is the first b lanes. (Made in a register:
        // loaded from a ramp just written on the stack, the load waited on the ramp's stores,
        // a third of this function's time.)
        let window = _mm_cmpgt_epi8(_mm_set1_epi8(b as i8), _mm_setr_epi8(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
        let start = Self::at(w, (x + r) as isize);
        let rows = y.saturating_sub(r)..(y + r + 1).min(h);
        let mut any_bg = _mm_setzero_si128();
        for yy in rows.clone() {
            let v = _mm_loadu_si128(self.rows.as_ptr().add(yy * width + start) as *const __m128i);
            any_bg = _mm_or_si128(any_bg, _mm_and_si128(_mm_cmpeq_epi8(v, _mm_set1_epi8(Self::BACKGROUND as i8)), window));
        }
        if _mm_movemask_epi8(_mm_cmpeq_epi8(any_bg, _mm_setzero_si128())) == 0xffff {
            return None;
        }
        let n = (hi - lo + 1) as usize;
        let mut acc = [_mm_setzero_si128(); 5];
        // Lane i's right pixel at disparity lo: column x + r − i − lo, reversed.
        let first = PF_SLACK as isize + (wr - g.rpad_left) as isize - 1 - (x + r) as isize + lo as isize;
        for yy in rows {
            let p = yy * width + start;
            let v = _mm_loadu_si128(self.rows.as_ptr().add(p) as *const __m128i);
            // Searched: the top bit clear (a signed byte above −1), inside the window.
            let m = _mm_and_si128(_mm_cmpgt_epi8(v, _mm_set1_epi8(-1)), window);
            let lv = _mm_and_si128(v, m);
            let rp = right_pf_rev.as_ptr().offset(first + (yy * wr) as isize);
            // All five disparities, so that the sums stay in registers (over `acc[..n]` they
            // were kept in memory, each row's adds waiting on the last row's stores); the
            // costs past `hi` are dropped below.
            for (k, a) in acc.iter_mut().enumerate() {
                let rv = _mm_and_si128(_mm_loadu_si128(rp.add(k) as *const __m128i), m);
                *a = _mm_add_epi64(*a, _mm_sad_epu8(lv, rv));
            }
        }
        let mut costs = [0u32; 5];
        for (c, a) in costs.iter_mut().zip(&acc).take(n) {
            *c = (_mm_cvtsi128_si64(*a) + _mm_cvtsi128_si64(_mm_unpackhi_epi64(*a, *a))) as u32;
        }
        Some(costs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stereo::MatchParams;

    /// The refinement's correlation reads its intervals straight from SGM's map
    /// (`IntervalSource::Around`): the same map and counts as the same intervals written out
    /// as a map of intervals first, on random images, with SGM values inside, at and past the
    /// range's ends and holes, in the vector copy of the matcher the CPU runs (the
    /// narrow-band path of the AVX2 copy, or of the AVX-512 one over 128 disparities).
    #[test]
    fn intervals_read_from_the_map_are_those_written_out() {
        let mut next = crate::testing::xorshift(0x5eed_a40);
        let (w, h) = (211, 41);
        let mut image = || (0..w * h).map(|_| (next() % 256) as u8).collect::<Vec<u8>>();
        let (l, r) = (image(), image());
        let (l, r) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
        let mut next = crate::testing::xorshift(0xd15_9a);
        for (min_disparity, num_disparities, block) in [(0, 16, 9), (-5, 32, 5), (3, 128, 9)] {
            let p = MatchParams { method: Method::Bm, block, min_disparity, num_disparities, uniqueness_ratio: 0, texture_threshold: 0, lr_max_diff: None, speckle_window: 0, threads: 1, ..Default::default() }.validate().unwrap();
            let (dmin, dmax) = (min_disparity, p.max_disparity());
            let mut map = DisparityMap::new(w, h);
            for v in map.values_mut() {
                *v = match next() % 6 {
                    0 => f32::NAN,
                    1 => dmin as f32 - 3.0 + (next() % 12) as f32 * 0.5,
                    2 => dmax as f32 - 3.0 + (next() % 12) as f32 * 0.5,
                    _ => dmin as f32 + (next() % 1000) as f32 / 1000.0 * (dmax - dmin) as f32,
                };
            }
            // A row and a band of columns with no match.
            map.values_mut()[7 * w..8 * w].fill(f32::NAN);
            for row in map.values_mut().chunks_exact_mut(w) {
                row[..11].fill(f32::NAN);
            }
            let mut iv = DisparityIntervals::empty(w, h);
            for (i, &d) in map.values().iter().enumerate() {
                let (a, b) = around(d, dmin, dmax);
                iv.set(i % w, i / w, (a <= b).then_some((a, b)));
            }
            let mut m = StereoMatcher::new(p.clone());
            let (mut from_map, mut written) = (DisparityMap::new(w, h), DisparityMap::new(w, h));
            let mut spans = Vec::new();
            matched_spans(&map, &mut spans);
            let a = m.correlate(&p, l, r, IntervalSource::Around { map: &map, spans: &spans }, &mut from_map);
            let b = m.correlate(&p, l, r, IntervalSource::Given(&iv), &mut written);
            let bits = |m: &DisparityMap| m.values().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&from_map), bits(&written), "{dmin} … {dmax}");
            assert_eq!((a.searched, a.evaluated), (b.searched, b.evaluated), "{dmin} … {dmax}");
            // (Most pixels: a right pixel must lie inside the image.)
            assert!(from_map.valid_count_within(0..w, 0..h) > w * h / 4, "{dmin} … {dmax}: the correlation matches");
        }
    }

    /// The vector rim costs are the scalar ones: every window side up to sixteen lanes, pixels
    /// at the image's edges and corners, masks with holes, disparities at the range's ends.
    #[test]
    fn the_vector_rim_costs_are_the_scalar_ones() {
        let mut next = crate::testing::xorshift(0x5eed_0f_41);
        for (block, min_disparity, num_disparities) in [(3, 0, 16), (9, 0, 40), (11, -7, 20), (15, 3, 9)] {
            let p = MatchParams { block, min_disparity, num_disparities, ..Default::default() }.validate().unwrap();
            let (w, h) = (37, 23);
            let g = Geometry::new(&p, w, h);
            let left_pf: Vec<u8> = (0..g.wp * h + 2 * PF_SLACK).map(|_| (next() % 63) as u8).collect();
            let right_pf_rev: Vec<u8> = (0..g.wr() * h + 2 * PF_SLACK).map(|_| (next() % 63) as u8).collect();
            let mut searched = DisparityIntervals::full(w, h, min_disparity, p.max_disparity());
            for y in 0..h {
                for x in 0..w {
                    if next() % 4 == 0 {
                        searched.set(x, y, None);
                    }
                }
            }
            let mut rows = RimRows::default();
            rows.build(g, &left_pf, &searched);
            let (dmin, dmax) = (min_disparity, p.max_disparity());
            for y in 0..h {
                for x in 0..w {
                    let lo = dmin + (next() % (dmax - dmin - 3) as u64) as i32;
                    // (At the range's top too: the vector costs read five disparities from
                    // `lo` whatever `hi`.)
                    for (lo, hi) in [(lo, lo + 4), (dmin, dmin + 2), (dmax - 4, dmax), (lo, lo), (dmax - 2, dmax), (dmax, dmax)] {
                        let want = rows.costs_scalar(g, &right_pf_rev, x, y, lo, hi);
                        assert_eq!(rows.costs(g, &right_pf_rev, x, y, lo, hi), want, "block {block}, pixel ({x}, {y}), {lo} … {hi}");
                    }
                }
            }
        }
    }
}
