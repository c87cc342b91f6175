//! The grid of SGM's blocks of [`LANES`] disparities: where a call's bands start.

use std::ops::Range;

use super::super::disparity::{searched_span, DisparityIntervals, MatchStats};
use super::super::params::ValidMatchParams;
use super::{Geo, Sgm, LANES};

/// The shift of the blocks' grid, 0 … 15 disparities below the multiples of [`LANES`], that
/// puts the fewest blocks around a call's intervals. An interval of 14 disparities takes one
/// block where it lies inside one and two where it straddles a block's edge; an assisted
/// frame's intervals gather about the object's disparities, so where those lie near a
/// multiple of 16, most straddle one on the plain grid (docs/matcher.md, "The blocks' grid
/// moved to the object"). Counted on every other column of every eighth row (thousands of
/// pixels on an assisted frame; 0.007 ms there, 0.03 ms on a whole 450 × 375 pair) from the
/// residues of the intervals' ends: at shift `s` an end `k` passes to the next block where
/// `k mod 16 ≥ 16 − s`. The plain grid (0) unless a shift saves at least [`SHIFT_SAVES`] of
/// the blocks; a full range keeps it (every shift adds a block there).
pub(in crate::stereo) fn shift(iv: &DisparityIntervals, dmin: i32, dmax: i32) -> u32 {
    let w = iv.width;
    // Four histograms of each end, by sampled column: neighbours mostly share a residue, and
    // one histogram would make each count wait for the one before it.
    let (mut lo_res, mut hi_res) = ([[0u32; LANES]; 4], [[0u32; LANES]; 4]);
    let mut blocks = 0i64;
    for y in (0..iv.height).step_by(8) {
        let (lo, hi) = (&iv.lo[y * w..][..w], &iv.hi[y * w..][..w]);
        let Some((first, last)) = searched_span(lo, hi) else { continue };
        for x in (first..=last).step_by(2) {
            let (a, b) = ((lo[x] as i32).max(dmin), (hi[x] as i32).min(dmax));
            if a > b {
                continue;
            }
            let (ka, kb) = ((a - dmin) as usize, (b - dmin) as usize);
            lo_res[x / 2 % 4][ka % LANES] += 1;
            hi_res[x / 2 % 4][kb % LANES] += 1;
            blocks += (kb / LANES - ka / LANES + 1) as i64;
        }
    }
    let count = |h: &[[u32; LANES]; 4], r: usize| h.iter().map(|c| c[r] as i64).sum::<i64>();
    let (mut change, mut best, mut best_shift) = (0i64, 0i64, 0u32);
    for shift in 1..LANES {
        let r = LANES - shift;
        change += count(&hi_res, r) - count(&lo_res, r);
        if change < best {
            (best, best_shift) = (change, shift as u32);
        }
    }
    if (-best) as f64 >= SHIFT_SAVES * blocks as f64 {
        best_shift
    } else {
        0
    }
}

impl Sgm {
    /// Each pixel's interval clipped to the range and to right pixels inside the image, the
    /// band of whole blocks around it, and the packed offsets: over the whole image, or
    /// (`per_row`) from each row's start. Returns the most values a row packs, and the first
    /// and last right column the costs of those bands read ([`super::census::RightRows`]'s reach).
    #[inline(always)]
    pub(super) fn bands(&mut self, p: &ValidMatchParams, g: Geo, shift: u32, iv: &DisparityIntervals, keep: Range<usize>, per_row: bool, stats: &mut MatchStats) -> (usize, (i32, i32)) {
        let Geo { w, h, dmin, n, .. } = g;
        let dmax = p.max_disparity();
        for v in [&mut self.band_a, &mut self.band_m, &mut self.lo, &mut self.hi] {
            v.resize(w * h, 0);
        }
        self.off.resize(w * h + 1, 0);
        self.span.resize(h, 0..0);
        // The blocks' grid: `shift` disparities below the multiples of 16, one for the call
        // ([`grid::shift`]), so that neighbours with the same interval keep sharing a band.
        let (shift, npad) = (shift as i32, n as i32);
        let (mut total, mut row_max) = (0usize, 0usize);
        // The right columns read: pixel x's band a … a + m − 1 reads x − dmin − a − m + 1 …
        // x − dmin − a.
        let (mut reach_lo, mut reach_hi) = (i32::MAX, i32::MIN);
        for y in 0..h {
            if per_row {
                total = 0;
            }
            let row = y * w..(y + 1) * w;
            let (ilo, ihi) = (&iv.lo[row.clone()], &iv.hi[row.clone()]);
            let (band_a, band_m) = (&mut self.band_a[row.clone()], &mut self.band_m[row.clone()]);
            let (lo_out, hi_out) = (&mut self.lo[row.clone()], &mut self.hi[row.clone()]);
            // Outside the row's searched span nothing is (m = 0); inside it, branch-free so
            // that it vectorises: the clipped interval, its block band (m = 0 where nothing is
            // searched) and its indices.
            let searched_px = searched_span(ilo, ihi).map_or(0..0, |(first, last)| first..last + 1);
            for v in [&mut *band_a, &mut *band_m, &mut *lo_out, &mut *hi_out] {
                v[..searched_px.start].fill(0);
                v[searched_px.end..].fill(0);
            }
            for x in searched_px.clone() {
                let lo = (ilo[x] as i32).max(dmin).max(x as i32 - w as i32 + 1);
                let hi = (ihi[x] as i32).min(dmax).min(x as i32);
                let searched = lo <= hi;
                // (Kept from overflowing where nothing is searched — its values are not
                // used; where something is, lo ≥ dmin and a ≤ khi, so they change nothing.)
                let (klo, khi) = ((lo - dmin).max(0) as u32, (hi - dmin).max(0) as u32);
                // The blocks of the shifted grid that hold klo … khi, clipped to the range's
                // blocks (a band that would pass either end moves inside; at shift 0 none does).
                const B: i32 = LANES as i32;
                let a0 = ((klo as i32 + shift) & !(B - 1)) - shift;
                let e0 = ((khi as i32 + shift) & !(B - 1)) + B - shift;
                let a1 = a0.max(0);
                let m = ((e0 - a1 + B - 1) & !(B - 1)).min(npad);
                let a = a1.min(npad - m);
                let (a, m) = (a as u32, m as u32);
                band_a[x] = if searched { a as u16 } else { 0 };
                band_m[x] = if searched { m as u16 } else { 0 };
                lo_out[x] = if searched { klo as u16 } else { 0 };
                hi_out[x] = if searched { khi as u16 } else { 0 };
                let right = x as i32 - dmin - a as i32;
                reach_lo = reach_lo.min(if searched { right - m as i32 + 1 } else { i32::MAX });
                reach_hi = reach_hi.max(if searched { right } else { i32::MIN });
            }
            let off = &mut self.off[row];
            let (mut row_total, mut row_searched) = (0usize, 0usize);
            off[..searched_px.start].fill(total);
            for (o, &m) in off[searched_px.clone()].iter_mut().zip(&band_m[searched_px.clone()]) {
                *o = total + row_total;
                row_total += m as usize;
                row_searched += (m > 0) as usize;
            }
            off[searched_px.end..].fill(total + row_total);
            let inside = &band_m[searched_px.clone()];
            let first = inside.iter().position(|&m| m > 0);
            let last = inside.iter().rposition(|&m| m > 0);
            self.span[y] = first.zip(last).map_or(0..0, |(a, b)| searched_px.start + a..searched_px.start + b + 1);
            total += row_total;
            row_max = row_max.max(row_total);
            if keep.contains(&y) {
                stats.searched += row_searched;
                stats.evaluated += row_total as u64;
            }
        }
        self.off[w * h] = total;
        (row_max, (reach_lo, reach_hi))
    }
}

/// The share of a call's blocks a shifted grid must save to be taken ([`shift`]).
const SHIFT_SAVES: f64 = 0.05;

#[cfg(test)]
mod tests {
    use super::*;

    fn intervals(w: usize, h: usize, at: impl Fn(usize, usize) -> Option<(i16, i16)>) -> DisparityIntervals {
        let mut iv = DisparityIntervals::empty(w, h);
        iv.searched = None;
        for y in 0..h {
            for x in 0..w {
                if let Some((lo, hi)) = at(x, y) {
                    (iv.lo[y * w + x], iv.hi[y * w + x]) = (lo, hi);
                }
            }
        }
        iv
    }

    /// Intervals across a multiple of 16 move the grid so that one block holds each (the
    /// least shift that does); intervals inside a block, a full range and nothing searched
    /// keep the plain grid.
    #[test]
    fn the_grid_moves_only_where_it_saves_blocks() {
        let (w, h) = (40, 20);
        // 28 … 35 straddles 32: shifts 4 … 12 put it in one block (28 … 43 at 4).
        assert_eq!(shift(&intervals(w, h, |_, _| Some((28, 35))), 0, 127), 4);
        // The same, counted from a negative range's start: 28 … 35 are indices 36 … 43.
        assert_eq!(shift(&intervals(w, h, |_, _| Some((28, 35))), -8, 119), 0);
        assert_eq!(shift(&intervals(w, h, |_, _| Some((20, 27))), -8, 119), 4);
        assert_eq!(shift(&intervals(w, h, |_, _| Some((18, 29))), 0, 127), 0);
        assert_eq!(shift(&DisparityIntervals::full(w, h, 0, 127), 0, 127), 0);
        assert_eq!(shift(&DisparityIntervals::empty(w, h), 0, 127), 0);
        // Half the pixels straddle 32 (29 … 34), half lie inside its block (36 … 44): shift 3
        // puts both in 29 … 44, one block each.
        assert_eq!(shift(&intervals(w, h, |x, _| Some(if x < w / 2 { (29, 34) } else { (36, 44) })), 0, 127), 3);
    }

    /// A shift is taken only where it saves at least [`SHIFT_SAVES`] of the blocks: one
    /// straddling interval in fifty is not worth moving the grid of the other 49.
    #[test]
    fn a_few_straddling_intervals_keep_the_plain_grid() {
        let (w, h) = (50, 8);
        assert_eq!(shift(&intervals(w, h, |x, _| Some(if x == 0 { (29, 34) } else { (36, 44) })), 0, 127), 0);
        assert_eq!(shift(&intervals(w, h, |x, _| Some(if x < 10 { (29, 34) } else { (36, 44) })), 0, 127), 3);
    }
}
