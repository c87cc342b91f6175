//! One row of a stripe: its intervals, the banded column sums, window sums with
//! winner-take-all, texture, uniqueness and sub-pixel fit, and the left–right check — each
//! stage a function, with its AVX2 / AVX-512 run kernels beside it.

use std::ops::Range;

use super::scratch::{clamp_row, Geometry, StripeScratch, BLOCK, NARROW, TILE_W};
use super::source::{around, IntervalSource};
use crate::stereo::disparity::{searched_span, MatchStats};
use crate::stereo::kernels::{self, absdiff, add_absdiff, add_into, first_index_of, min_into, min_u16, min_u16_away_from, slide_column, slide_row};
use crate::stereo::params::ValidMatchParams;

/// Row `y`'s intervals as disparity indices, clipped to the search range and to right
/// pixels inside the image, into `lo`/`hi` (`lo > hi`: nothing to search), from the row's
/// first to its last searched pixel alone: returns those columns (empty where nothing is
/// searched), outside which `lo`/`hi` are left as they were. (An assisted crop's rows are
/// half columns that only the right image's pixels need.) Branch-free, so it vectorises.
#[inline(always)]
pub(super) fn clip_row(g: Geometry, src: IntervalSource, y: usize, lo: &mut [i32], hi: &mut [i32]) -> Range<usize> {
    let Geometry { w, n, dmin, .. } = g;
    let dmax = dmin + n as i32 - 1;
    let (lo, hi) = (&mut lo[..w], &mut hi[..w]);
    // Pixel x's interval `dlo ..= dhi` (disparities) into `lo[x]`/`hi[x]`.
    let clip = |lo: &mut [i32], hi: &mut [i32], x: usize, dlo: i32, dhi: i32| {
        // The right pixel x − d must lie inside the image: x − w + 1 ≤ d ≤ x.
        let kmin = (x as i32 - w as i32 + 1).max(dmin) - dmin;
        let kmax = (x as i32).min(dmax) - dmin;
        let (a, b) = ((dlo - dmin).max(kmin), (dhi - dmin).min(kmax));
        // Selected with masks, not `if`: LLVM turns an `if` here into masked stores, which
        // are slow on AMD cores.
        let m = -(((dlo <= dhi) & (a <= b)) as i32);
        lo[x] = (a & m) | (1 & !m);
        hi[x] = b & m;
    };
    match src {
        IntervalSource::Given(iv) => {
            let (row_lo, row_hi) = (&iv.lo[y * w..][..w], &iv.hi[y * w..][..w]);
            let Some((first, last)) = searched_span(row_lo, row_hi) else { return 0..0 };
            for x in first..last + 1 {
                clip(lo, hi, x, row_lo[x] as i32, row_hi[x] as i32);
            }
            first..last + 1
        }
        IntervalSource::Around { map, spans } => {
            let row = &map.values()[y * w..][..w];
            let span = spans[y].clone();
            debug_assert_eq!(span, searched_span(row, row).map_or(0..0, |(first, last)| first..last + 1), "row {y}'s span is not the map's");
            for x in span.clone() {
                let (dlo, dhi) = around(row[x], dmin, dmax);
                clip(lo, hi, x, dlo, dhi);
            }
            span
        }
    }
}

/// The clipped intervals of the tile row `rows` (into `clip_lo/hi`, row by row, `w` apart,
/// over each row's columns in `clip_spans` alone: [`clip_row`]) and the band of each of its
/// tiles: the union of its pixels' intervals (empty tiles get `lo > hi`). Returns the mean
/// band width over the searched pixels (0: none).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn tile_bands(g: Geometry, iv: IntervalSource, rows: Range<usize>, clip_lo: &mut Vec<i32>, clip_hi: &mut Vec<i32>, clip_spans: &mut Vec<Range<usize>>, tile_lo: &mut Vec<i32>, tile_hi: &mut Vec<i32>, tile_px: &mut Vec<u32>, cols: &mut Vec<i32>) -> f64 {
    let Geometry { w, .. } = g;
    let tiles = w.div_ceil(TILE_W);
    tile_lo.clear();
    tile_lo.resize(tiles, i32::MAX);
    tile_hi.clear();
    tile_hi.resize(tiles, i32::MIN);
    tile_px.clear();
    tile_px.resize(tiles, 0);
    clip_lo.resize(rows.len() * w, 1);
    clip_hi.resize(rows.len() * w, 0);
    // Per column over the tile row first (element-wise, branch-free: it vectorises), then
    // per tile once: min, max and count of the searched pixels.
    cols.clear();
    cols.resize(3 * w, 0);
    let (col_lo, rest) = cols.split_at_mut(w);
    let (col_hi, col_n) = rest.split_at_mut(w);
    col_lo.fill(i32::MAX);
    col_hi.fill(i32::MIN);
    clip_spans.clear();
    for (i, y) in rows.enumerate() {
        let (lo, hi) = (&mut clip_lo[i * w..][..w], &mut clip_hi[i * w..][..w]);
        let xs = clip_row(g, iv, y, lo, hi);
        clip_spans.push(xs.clone());
        for x in xs {
            let (l, h) = (lo[x], hi[x]);
            // An unsearched pixel (clipped to lo = 1 > hi = 0) takes part as 2³⁰ + 1 and
            // −2³⁰: out of every band. (With `if ok { l } else { i32::MAX }` LLVM stores only
            // where `ok`, as masked stores, which are slow on AMD cores.)
            let out = ((l > h) as i32) << 30;
            col_lo[x] = col_lo[x].min(l | out);
            col_hi[x] = col_hi[x].max(h - out);
            col_n[x] += (l <= h) as i32;
        }
    }
    for (t, ((a, b), c)) in col_lo.chunks(TILE_W).zip(col_hi.chunks(TILE_W)).zip(col_n.chunks(TILE_W)).enumerate() {
        tile_lo[t] = a.iter().fold(tile_lo[t], |m, &v| m.min(v));
        tile_hi[t] = b.iter().fold(tile_hi[t], |m, &v| m.max(v));
        tile_px[t] += c.iter().sum::<i32>() as u32;
    }
    let (mut pairs, mut pixels) = (0u64, 0u64);
    for ((lo, hi), &px) in tile_lo.iter_mut().zip(tile_hi.iter_mut()).zip(tile_px.iter()) {
        if *lo <= *hi {
            pairs += (*hi - *lo + 1) as u64 * px as u64;
            pixels += px as u64;
        } else {
            (*lo, *hi) = (1, 0);
        }
    }
    if pixels == 0 {
        0.0
    } else {
        pairs as f64 / pixels as f64
    }
}

/// This row's clipped intervals (`lo`/`hi` over the columns `clipped_cols`, from
/// [`tile_bands`]) into `tlo..=thi`, what is searched, and — when `blocks` is given (the row
/// path; the narrow-band path has no use for them) — the block-aligned ranges the row path
/// computes sums over (`ilo..=ihi`, see [`BLOCK`]); both hold nothing searched (`1`, `0`)
/// outside the searched pixels' span. Counts searched pixels and pairs. Returns the span from
/// the first to the last searched pixel (None: nothing searched).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn row_intervals(g: Geometry, clipped: (&[i32], &[i32]), clipped_cols: Range<usize>, tlo: &mut [i32], thi: &mut [i32], blocks: Option<(&mut [i32], &mut [i32])>, stats: &mut MatchStats) -> Option<Range<usize>> {
    let Geometry { w, n, .. } = g;
    let (lo, hi) = (&clipped.0[..w], &clipped.1[..w]);
    let (first, last) = searched_span(&lo[clipped_cols.clone()], &hi[clipped_cols.clone()])?;
    let span = clipped_cols.start + first..clipped_cols.start + last + 1;
    // Outside the span, nothing searched (what the clipped rows hold there, unwritten).
    let outside = |v: &mut [i32], none: i32| {
        v[..span.start].fill(none);
        v[span.end..w].fill(none);
    };
    outside(tlo, 1);
    outside(thi, 0);
    tlo[span.clone()].copy_from_slice(&lo[span.clone()]);
    thi[span.clone()].copy_from_slice(&hi[span.clone()]);
    let (mut searched, mut evaluated) = (0u64, 0u64);
    for (&a, &b) in lo[span.clone()].iter().zip(&hi[span.clone()]) {
        let ok = a <= b;
        searched += ok as u64;
        evaluated += if ok { (b - a + 1) as u64 } else { 0 };
    }
    if let Some((ilo, ihi)) = blocks {
        let block = BLOCK as i32;
        outside(ilo, 1);
        outside(ihi, 0);
        for x in span.clone() {
            let (a, b) = (lo[x], hi[x]);
            let ok = a <= b;
            // Whole blocks, so that neighbours with slightly different intervals share one
            // range and slide instead of recomputing; not clipped to the image (the right
            // rows are padded for that), so border pixels share their neighbours' blocks.
            // (Clipped indices are ≥ 0: rounding down to a block is a mask, which
            // vectorises.)
            ilo[x] = if ok { a & !(block - 1) } else { 1 };
            ihi[x] = if ok { ((b & !(block - 1)) + block - 1).min(n as i32 - 1) } else { 0 };
        }
    }
    stats.searched += searched as usize;
    stats.evaluated += evaluated;
    Some(span)
}

/// For each padded column, the union of the intervals of the pixels whose window covers it:
/// a sliding-window min of `ilo` and max of `ihi` (van Herk / Gil–Werman, O(1) per column).
#[inline(always)]
pub(super) fn column_bands(g: Geometry, ilo: &[i32], ihi: &[i32], need_lo: &mut [i32], need_hi: &mut [i32], tmp: &mut Vec<i32>) {
    let Geometry { w, r, wp, .. } = g;
    let b = 2 * r + 1;
    // Column xp is in the windows of pixels xp − 2r ..= xp; with 2r empty pixels padded on
    // each side, that is positions xp ..= xp + 2r of the padded row.
    let blocks = (w + 4 * r).div_ceil(b) * b;
    // Every entry is overwritten below: no need to clear.
    tmp.resize(4 * blocks, 0);
    let (lo_pad, rest) = tmp.split_at_mut(blocks);
    let (hi_pad, rest) = rest.split_at_mut(blocks);
    let (prefix, suffix) = rest.split_at_mut(blocks);
    lo_pad.fill(i32::MAX);
    hi_pad.fill(i32::MIN);
    for x in 0..w {
        if ilo[x] <= ihi[x] {
            lo_pad[x + 2 * r] = ilo[x];
            hi_pad[x + 2 * r] = ihi[x];
        }
    }
    sliding_extreme(lo_pad, b, prefix, suffix, i32::min, &mut need_lo[..wp]);
    sliding_extreme(hi_pad, b, prefix, suffix, i32::max, &mut need_hi[..wp]);
    for xp in 0..wp {
        if need_lo[xp] > need_hi[xp] {
            need_lo[xp] = 1;
            need_hi[xp] = 0;
        }
    }
}

/// `out[i] = pick(v[i ..= i + b − 1])` for every `i < out.len()`; `v.len()` is a multiple of `b`.
#[inline(always)]
pub(super) fn sliding_extreme(v: &[i32], b: usize, prefix: &mut [i32], suffix: &mut [i32], pick: fn(i32, i32) -> i32, out: &mut [i32]) {
    for start in (0..v.len()).step_by(b) {
        let mut acc = v[start];
        prefix[start] = acc;
        for i in start + 1..start + b {
            acc = pick(acc, v[i]);
            prefix[i] = acc;
        }
        let mut acc = v[start + b - 1];
        suffix[start + b - 1] = acc;
        for i in (start..start + b - 1).rev() {
            acc = pick(acc, v[i]);
            suffix[i] = acc;
        }
    }
    for (i, o) in out.iter_mut().enumerate() {
        *o = pick(suffix[i], prefix[i + b - 1]);
    }
}

/// Start, in the reversed right row, of disparity index 0 for padded column `xp`.
#[inline(always)]
pub(super) fn right_start(g: Geometry, xp: usize) -> isize {
    // Right sample of (x' = xp − r, d = dmin + k) is padded column x' − d + rpad_left, stored
    // at wr − 1 − (that) in the reversed row.
    g.wr() as isize - 1 - (xp as isize - g.r as isize - g.dmin as isize + g.rpad_left as isize)
}

/// Slides the vertical window sums down to row `y` over each needed band of the columns `cols`.
#[inline(always)]
pub(super) fn update_column_sums<const AVX2: bool, const AVX512: bool>(g: Geometry, lpf: &[u8], rrev: &[u8], y: usize, first_row: bool, cols: Range<usize>, s: &mut StripeScratch) {
    let Geometry { h, r, wp, n, .. } = g;
    let y_new = clamp_row(y as isize + r as isize, h);
    let y_old = clamp_row(y as isize - r as isize - 1, h);
    let l_new = &lpf[y_new * wp..][..wp];
    let l_old = &lpf[y_old * wp..][..wp];
    let wr = g.wr();
    let r_new = &rrev[y_new * wr..][..wr];
    let r_old = &rrev[y_old * wr..][..wr];
    let mut xp = cols.start;
    let wp = cols.end.min(wp);
    while xp < wp {
        let (a, b) = (s.need_lo[xp], s.need_hi[xp]);
        // The common case — the band is the one the column already holds — runs as one
        // tight loop over the columns that share it.
        #[cfg(target_arch = "x86_64")]
        if AVX2 && !first_row && a <= b && s.band_lo[xp] == a && s.band_hi[xp] == b {
            let mut end = xp + 1;
            while end < wp && s.need_lo[end] == a && s.need_hi[end] == b && s.band_lo[end] == a && s.band_hi[end] == b {
                end += 1;
            }
            // SAFETY: AVX2 is only true in the copy dispatched on CPUs that have it; the
            // bands lie inside the buffers (checked inside).
            unsafe { slide_columns_avx2::<AVX512>(g, &mut s.cs, (l_new, r_new), (l_old, r_old), xp..end, a as usize, b as usize + 1) };
            xp = end;
            continue;
        }
        let cs = &mut s.cs[xp * n..][..n];
        let j0 = right_start(g, xp);
        if a > b {
            s.band_lo[xp] = 1;
            s.band_hi[xp] = 0;
            xp += 1;
            continue;
        }
        let (ov_lo, ov_hi) = if first_row { (1, 0) } else { (a.max(s.band_lo[xp]), b.min(s.band_hi[xp])) };
        let rng = |lo: i32, hi: i32| (lo as usize, (hi + 1) as usize);
        let rs = |lo: i32| (j0 + lo as isize) as usize;
        if ov_lo <= ov_hi {
            let (k0, k1) = rng(ov_lo, ov_hi);
            let len = k1 - k0;
            let (dst, rn, ro) = (&mut cs[k0..k1], &r_new[rs(ov_lo)..][..len], &r_old[rs(ov_lo)..][..len]);
            match AVX2 {
                // SAFETY: AVX2 is only true in the copy dispatched on CPUs that have it.
                #[cfg(target_arch = "x86_64")]
                true => unsafe { kernels::avx2::slide_column(dst, l_new[xp], rn, l_old[xp], ro) },
                _ => slide_column(dst, l_new[xp], rn, l_old[xp], ro),
            }
            if a < ov_lo {
                fresh_column(g, lpf, rrev, y, xp, j0, a, ov_lo - 1, cs);
            }
            if ov_hi < b {
                fresh_column(g, lpf, rrev, y, xp, j0, ov_hi + 1, b, cs);
            }
        } else {
            fresh_column(g, lpf, rrev, y, xp, j0, a, b, cs);
        }
        s.band_lo[xp] = a;
        s.band_hi[xp] = b;
        xp += 1;
    }
}

/// Slides the column sums of the columns `xps`, which all hold and need the band `k0..k1`,
/// down one row.
///
/// # Safety
/// AVX2 must be available.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) unsafe fn slide_columns_avx2<const AVX512: bool>(g: Geometry, cs: &mut [u16], new: (&[u8], &[u8]), old: (&[u8], &[u8]), xps: Range<usize>, k0: usize, k1: usize) {
    let Geometry { wp, n, .. } = g;
    let len = k1 - k0;
    assert!(xps.end <= wp && k1 <= n && cs.len() >= wp * n);
    for xp in xps {
        let start = right_start(g, xp) + k0 as isize;
        assert!(start >= 0 && start as usize + len <= g.wr());
        let dst = std::slice::from_raw_parts_mut(cs.as_mut_ptr().add(xp * n + k0), len);
        let rn = new.1.get_unchecked(start as usize..start as usize + len);
        let ro = old.1.get_unchecked(start as usize..start as usize + len);
        if AVX512 {
            kernels::avx512::slide_column(dst, *new.0.get_unchecked(xp), rn, *old.0.get_unchecked(xp), ro);
        } else {
            kernels::avx2::slide_column(dst, *new.0.get_unchecked(xp), rn, *old.0.get_unchecked(xp), ro);
        }
    }
}

/// Recomputes `cs[k]` for `k in a..=b` as a full vertical window sum.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn fresh_column(g: Geometry, lpf: &[u8], rrev: &[u8], y: usize, xp: usize, j0: isize, a: i32, b: i32, cs: &mut [u16]) {
    let Geometry { h, r, wp, .. } = g;
    let dst = &mut cs[a as usize..=b as usize];
    let start = (j0 + a as isize) as usize;
    if dst.len() < NARROW {
        // Few disparities: one scalar sum per entry beats a vector pass per window row.
        for (i, c) in dst.iter_mut().enumerate() {
            let mut acc = 0u16;
            for dy in -(r as isize)..=r as isize {
                let yy = clamp_row(y as isize + dy, h);
                acc += absdiff(lpf[yy * wp + xp], rrev[yy * g.wr() + start + i]);
            }
            *c = acc;
        }
        return;
    }
    dst.fill(0);
    for dy in -(r as isize)..=r as isize {
        let yy = clamp_row(y as isize + dy, h);
        add_absdiff(dst, lpf[yy * wp + xp], &rrev[yy * g.wr() + start..]);
    }
}

/// Vertical sums of |prefiltered − cap| per column (BM's texture measure).
#[inline(always)]
pub(super) fn update_texture(g: Geometry, lpf: &[u8], y: usize, first_row: bool, cap: u8, tex: &mut [u32]) {
    let Geometry { h, r, wp, .. } = g;
    if first_row {
        tex.fill(0);
        for dy in -(r as isize)..=r as isize {
            let row = &lpf[clamp_row(y as isize + dy, h) * wp..][..wp];
            for (t, &v) in tex.iter_mut().zip(row) {
                *t += v.abs_diff(cap) as u32;
            }
        }
    } else {
        let new = &lpf[clamp_row(y as isize + r as isize, h) * wp..][..wp];
        let old = &lpf[clamp_row(y as isize - r as isize - 1, h) * wp..][..wp];
        for ((t, &a), &b) in tex.iter_mut().zip(new).zip(old) {
            *t = *t + a.abs_diff(cap) as u32 - b.abs_diff(cap) as u32;
        }
    }
}

/// Window texture of every pixel of the span: the sum of the `b` column sums from its
/// window's first column, as `b` element-wise passes over the span (they vectorise; a sum slid
/// along the row waits on itself at every pixel).
#[inline(always)]
pub(super) fn texture_row(g: Geometry, s: &mut StripeScratch, span: Range<usize>) {
    let b = 2 * g.r + 1;
    let out = &mut s.tex_row[span.clone()];
    out.copy_from_slice(&s.tex_col[span.clone()]);
    for k in 1..b {
        for (t, &c) in out.iter_mut().zip(&s.tex_col[span.start + k..span.end + k]) {
            *t += c;
        }
    }
}

/// Window sums, winner-take-all, texture and uniqueness tests, sub-pixel fit, and the
/// right-image minima for the left–right check.
#[inline(always)]
pub(super) fn select_row<const AVX2: bool, const AVX512: bool>(p: &ValidMatchParams, g: Geometry, s: &mut StripeScratch, span: Range<usize>) {
    let Geometry { w, n, .. } = g;
    // The right pixels this span's pairs land on: entries w − 1 − x + k.
    s.right_min[w - span.end..w - span.start + n].fill(u16::MAX);
    let (mut x, xe) = (span.start, span.end);
    while x < xe {
        let (lo, hi) = (s.ilo[x], s.ihi[x]);
        if lo > hi {
            s.best[x] = None;
            x += 1;
            continue;
        }
        // The common case — this range lies inside the previous pixel's, and the next
        // pixels repeat it — runs as one tight loop. (The run splats onto the right row even
        // when the left–right check is off: one vector `min` per 16 pairs, cheaper than
        // leaving the fused loop.)
        let pure_slide = x > 0 && s.ilo[x - 1] <= lo && hi <= s.ihi[x - 1];
        #[cfg(target_arch = "x86_64")]
        if AVX2 && pure_slide {
            let mut end = x + 1;
            while end < xe && s.ilo[end] == lo && s.ihi[end] == hi {
                end += 1;
            }
            // SAFETY: AVX2 is only true in the copy dispatched on CPUs that have it; the run
            // is a pure slide by construction.
            unsafe { select_run_avx2::<AVX512>(p, g, s, x..end, lo as usize, hi as usize + 1) };
            x = end;
            continue;
        }
        window_sums(g, &s.cs, &mut s.sad[..], &s.ilo, &s.ihi, x);
        let (k0, k1) = (s.tlo[x] as usize, s.thi[x] as usize + 1);
        let tex = if p.texture_threshold > 0 { s.tex_row[x] } else { 0 };
        #[cfg(target_arch = "x86_64")]
        if AVX2 && k1 - k0 <= kernels::LANES {
            // A narrow interval, searched as one 16-lane load (the buffers have the slack),
            // from where the window sums were stored when it fits there (see
            // `select_run_avx2`).
            let base = if k1 - (lo as usize) <= kernels::LANES { lo as usize } else { k0 };
            let lanes = &s.sad[x * n + base..x * n + base + kernels::LANES];
            let right = &mut s.right_min[w - 1 - x + base..][..kernels::LANES];
            // SAFETY: AVX2 is only true in the copy dispatched on CPUs that have it.
            let (min, best, rival) = unsafe { kernels::avx2::block16(lanes, k0 - base, k1 - base, right) };
            let costs = &s.sad[x * n + k0..x * n + k1];
            s.best[x] = decide_at(p, costs, min, best - (k0 - base), rival, tex).map(|(best, frac)| ((k0 + best) as u16, frac));
            x += 1;
            continue;
        }
        let costs = &s.sad[x * n + k0..x * n + k1];
        // Splat the searched pairs onto the right row for the left–right check; the same
        // pass finds the cheapest cost.
        let right = &mut s.right_min[w - 1 - x + k0..][..k1 - k0];
        let min = match (AVX2, p.lr_max_diff.is_some()) {
            // SAFETY (all `avx2::` calls here): AVX2 is only true in the copy compiled for,
            // and dispatched on, CPUs that have it.
            #[cfg(target_arch = "x86_64")]
            (true, true) => unsafe { kernels::avx2::min_into_and_min(right, costs) },
            #[cfg(target_arch = "x86_64")]
            (true, false) => unsafe { kernels::avx2::min(costs) },
            (_, true) => {
                min_into(right, costs);
                min_u16(costs)
            }
            (_, false) => min_u16(costs),
        };
        s.best[x] = decide::<AVX2>(p, costs, min, tex).map(|(best, frac)| ((k0 + best) as u16, frac));
        x += 1;
    }
}

/// A run of pixels `xs` that all search `k0..k1`, each sliding from its left neighbour:
/// the window step, the left–right splat and the minimum fused in one AVX2 pass per pixel,
/// with no per-pixel slicing.
///
/// # Safety
/// AVX2 must be available; pixel `xs.start − 1` searched a superset of `k0..k1` and every
/// pixel of `xs` searches exactly `k0..k1` (so all buffers below are in bounds).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) unsafe fn select_run_avx2<const AVX512: bool>(p: &ValidMatchParams, g: Geometry, s: &mut StripeScratch, xs: Range<usize>, k0: usize, k1: usize) {
    let Geometry { w, r, n, .. } = g;
    let b = 2 * r + 1;
    let len = k1 - k0;
    assert!(xs.start >= 1 && xs.end <= w && k1 <= n && len > 0);
    assert!(s.cs.len() >= (xs.end + b - 1) * n && s.sad.len() >= xs.end * n + kernels::LANES && s.right_min.len() >= w + n + kernels::LANES);
    let (cs, sad, right_min) = (s.cs.as_ptr(), s.sad.as_mut_ptr(), s.right_min.as_mut_ptr());
    for x in xs {
        let row = std::slice::from_raw_parts_mut(sad.add(x * n + k0), len);
        let prev = std::slice::from_raw_parts(sad.add((x - 1) * n + k0), len);
        let add = std::slice::from_raw_parts(cs.add((x + b - 1) * n + k0), len);
        let sub = std::slice::from_raw_parts(cs.add((x - 1) * n + k0), len);
        let (t0, t1) = (*s.tlo.get_unchecked(x) as usize, *s.thi.get_unchecked(x) as usize + 1);
        let right = std::slice::from_raw_parts_mut(right_min.add(w - 1 - x + t0), t1 - t0);
        let tex = if p.texture_threshold > 0 { *s.tex_row.get_unchecked(x) } else { 0 };
        let chosen = if (t0, t1) == (k0, k1) && t1 - t0 > kernels::LANES {
            if AVX512 {
                let min = kernels::avx512::slide_row_min(row, prev, add, sub, right);
                decide_avx512(p, row, min, tex)
            } else {
                let min = kernels::avx2::slide_row_min(row, prev, add, sub, right);
                decide::<true>(p, row, min, tex)
            }
        } else if t1 - t0 <= kernels::LANES {
            // At most 16 searched disparities: slide the computed range, then search 16 lanes
            // in registers (lanes outside the interval are masked; the buffers have LANES
            // entries of slack for them). The lanes are read back where a store of the slide
            // put them when the interval fits there: a load that straddles two recent stores
            // cannot be forwarded from them and stalls for the round trip to the cache.
            slide_row(row, prev, add, sub);
            let base = if t1 - k0 <= kernels::LANES { k0 } else { t0 };
            let lanes = std::slice::from_raw_parts(sad.add(x * n + base), kernels::LANES);
            let right = std::slice::from_raw_parts_mut(right_min.add(w - 1 - x + base), kernels::LANES);
            let (min, best, rival) = kernels::avx2::block16(lanes, t0 - base, t1 - base, right);
            decide_at(p, &row[t0 - k0..t1 - k0], min, best - (t0 - base), rival, tex)
        } else {
            slide_row(row, prev, add, sub);
            let min = kernels::avx2::min_into_and_min(right, &row[t0 - k0..t1 - k0]);
            decide::<true>(p, &row[t0 - k0..t1 - k0], min, tex)
        };
        *s.best.get_unchecked_mut(x) = chosen.map(|(best, frac)| ((t0 + best) as u16, frac));
    }
}

/// Texture and uniqueness tests and the sub-pixel fit for one pixel's costs (`min` is their
/// minimum, `tex` the window texture): the best index in `costs` and its sub-pixel offset.
#[inline(always)]
pub(super) fn decide<const AVX2: bool>(p: &ValidMatchParams, costs: &[u16], min: u16, tex: u32) -> Option<(usize, f32)> {
    if tex < p.texture_threshold {
        return None;
    }
    let best = match AVX2 {
        // SAFETY (both `avx2::` calls): AVX2 is only true in the copy dispatched on CPUs
        // that have it.
        #[cfg(target_arch = "x86_64")]
        true => unsafe { kernels::avx2::first_index_of(costs, min) },
        _ => first_index_of(costs, min),
    };
    let rival = if p.uniqueness_ratio == 0 {
        u16::MAX
    } else {
        match AVX2 {
            #[cfg(target_arch = "x86_64")]
            true => unsafe { kernels::avx2::min_away_from(costs, best) },
            _ => min_u16_away_from(costs, best),
        }
    };
    decide_at(p, costs, min, best, rival, tex)
}

/// [`decide`] with the AVX-512 search kernels.
///
/// # Safety
/// AVX-512BW must be available.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(super) unsafe fn decide_avx512(p: &ValidMatchParams, costs: &[u16], min: u16, tex: u32) -> Option<(usize, f32)> {
    if tex < p.texture_threshold {
        return None;
    }
    let best = kernels::avx512::first_index_of(costs, min);
    let rival = if p.uniqueness_ratio == 0 { u16::MAX } else { kernels::avx512::min_away_from(costs, best) };
    decide_at(p, costs, min, best, rival, tex)
}

/// [`decide`] with the best index and the best non-adjacent rival cost already known.
#[inline(always)]
pub(super) fn decide_at(p: &ValidMatchParams, costs: &[u16], min: u16, best: usize, rival: u16, tex: u32) -> Option<(usize, f32)> {
    if tex < p.texture_threshold {
        return None;
    }
    if p.uniqueness_ratio > 0 {
        // Reject when a disparity not adjacent to the best costs nearly as little.
        let thresh = min as u32 + min as u32 * p.uniqueness_ratio / 100;
        if rival as u32 <= thresh {
            return None;
        }
    }
    let mut frac = 0.0f32;
    if p.subpixel && best > 0 && best + 1 < costs.len() {
        frac = equiangular(costs[best - 1] as f32, min as f32, costs[best + 1] as f32);
    }
    Some((best, frac))
}

/// The sub-pixel offset of a minimum `c1` from its neighbours' costs `c0` (one disparity below)
/// and `c2` (one above), within ±0.5: the equiangular (V) fit — SAD rises about linearly away
/// from its minimum; a parabola pulls sub-pixel shifts towards whole pixels (docs/matcher.md).
#[inline(always)]
pub(super) fn equiangular(c0: f32, c1: f32, c2: f32) -> f32 {
    let rise = c0.max(c2) - c1;
    if rise > 0.0 {
        ((c0 - c2) / (2.0 * rise)).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// `SAD(x, k) = Σ CS(x … x + 2r, k)` over pixel `x`'s interval, written to row `x` of `sad`:
/// slid from pixel `x − 1` where their intervals overlap, summed from scratch elsewhere.
#[inline(always)]
pub(super) fn window_sums(g: Geometry, cs: &[u16], sad: &mut [u16], ilo: &[i32], ihi: &[i32], x: usize) {
    let Geometry { r, n, .. } = g;
    let b = 2 * r + 1;
    let (lo, hi) = (ilo[x], ihi[x]);
    let (prev_lo, prev_hi) = if x > 0 { (ilo[x - 1], ihi[x - 1]) } else { (1, 0) };
    let (ov_lo, ov_hi) = (lo.max(prev_lo), hi.min(prev_hi));
    let col = |xp: usize, k0: usize, k1: usize| &cs[xp * n + k0..xp * n + k1];
    let (before, row) = sad.split_at_mut(x * n);
    let row = &mut row[..n];
    let sum_fresh = |k0: usize, k1: usize, row: &mut [u16]| {
        let dst = &mut row[k0..k1];
        if dst.len() < NARROW {
            for (i, d) in dst.iter_mut().enumerate() {
                *d = (x..x + b).map(|xp| cs[xp * n + k0 + i]).sum();
            }
            return;
        }
        dst.copy_from_slice(col(x, k0, k1));
        for xp in x + 1..x + b {
            add_into(dst, col(xp, k0, k1));
        }
    };
    if ov_lo <= ov_hi {
        let (k0, k1) = (ov_lo as usize, ov_hi as usize + 1);
        let prev = &before[(x - 1) * n..][..n];
        slide_row(&mut row[k0..k1], &prev[k0..k1], col(x + b - 1, k0, k1), col(x - 1, k0, k1));
        if lo < ov_lo {
            sum_fresh(lo as usize, ov_lo as usize, row);
        }
        if ov_hi < hi {
            sum_fresh(ov_hi as usize + 1, hi as usize + 1, row);
        }
    } else {
        sum_fresh(lo as usize, hi as usize + 1, row);
    }
}

/// Applies the left–right check and writes the disparities of the pixels in `span`; returns
/// the number of pixels with a match before the check and after it.
///
/// A match `k` at `x` lands on right pixel `x − d`; the cheapest pair anywhere on that right
/// pixel's diagonal is `right_min`. The match passes when a pair on the diagonal within
/// `lr_max_diff` disparities of `k` — pixel `x + j` at index `k + j` — reaches that minimum,
/// i.e. when the right pixel's own best disparity agrees with `k` to `lr_max_diff`.
#[inline(always)]
pub(super) fn left_right_check(p: &ValidMatchParams, g: Geometry, s: &StripeScratch, out: &mut [f32], span: Range<usize>) -> (usize, usize) {
    let Geometry { w, n, dmin, .. } = g;
    let (mut candidates, mut passed) = (0, 0);
    for x in span {
        out[x] = match s.best[x] {
            None => f32::NAN,
            Some((k, frac)) => {
                let ok = match p.lr_max_diff {
                    None => true,
                    Some(max) => {
                        let k = k as isize;
                        let target = s.right_min[w - 1 - x + k as usize];
                        let m = max.min(n as u32) as isize;
                        // The pixel's own pair decides almost always; neighbours on the
                        // diagonal only when another pair is cheaper.
                        let mut ok = s.sad[x * n + k as usize] <= target;
                        let mut j = 1;
                        while !ok && j <= m {
                            for xj in [x as isize + j, x as isize - j] {
                                let kj = k + (xj - x as isize);
                                ok |= xj >= 0
                                    && (xj as usize) < w
                                    && s.tlo[xj as usize] as isize <= kj
                                    && kj <= s.thi[xj as usize] as isize
                                    && s.sad[xj as usize * n + kj as usize] <= target;
                            }
                            j += 1;
                        }
                        ok
                    }
                };
                candidates += 1;
                if ok {
                    passed += 1;
                    (dmin + k as i32) as f32 + frac
                } else {
                    f32::NAN
                }
            }
        };
    }
    (candidates, passed)
}
