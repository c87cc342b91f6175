//! The grid of SGM's blocks of [`LANES`] disparities: where a call's bands start.

use super::super::disparity::{searched_span, DisparityIntervals};
use super::LANES;

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
