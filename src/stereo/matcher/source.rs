//! Where a call's search intervals come from: a map of intervals, or — for SGM's
//! sub-pixel refinement (`refine.rs`) — SGM's own disparities, each matched pixel searching
//! around its value. Its own file, so that the rows that read the intervals (`rows.rs`) and
//! the refinement that asks for them share it without importing each other.

use std::ops::Range;

use super::round_half_away_within;
use crate::stereo::disparity::{searched_span, DisparityIntervals, DisparityMap};

/// Where a call's search intervals come from.
#[derive(Clone, Copy)]
pub(super) enum IntervalSource<'a> {
    /// Each pixel's own, as given (`lo > hi`: not searched).
    Given(&'a DisparityIntervals),
    /// SGM's refinement (`refine.rs`): each matched pixel of the map searches around its
    /// disparity ([`around`]), an unmatched one (NaN) nothing. Read straight from the
    /// map, row by row, rather than written out as a map of intervals first; `spans` are
    /// the map's rows' [`matched_spans`], which the refinement needs itself too.
    Around { map: &'a DisparityMap, spans: &'a [Range<usize>] },
}

/// Per row of `map`, its first to last matched pixel (`0..0` where none) into `spans`.
pub(super) fn matched_spans(map: &DisparityMap, spans: &mut Vec<Range<usize>>) {
    spans.clear();
    // (`d <= d` fails for NaN alone.)
    spans.extend(map.values().chunks_exact(map.width).map(|row| searched_span(row, row).map_or(0..0, |(first, last)| first..last + 1)));
}

/// How far, disparities, the correlation searches either side of SGM's rounded value.
const AROUND: i32 = 2;

/// The correlation's interval around SGM's disparity `d`: its value rounded, ± [`AROUND`],
/// within `dmin ..= dmax`; `(1, 0)`, nothing, where `d` is NaN (unmatched). Branch-free, so
/// that a row of it vectorises: the value is clamped to 3 past the range before it is
/// rounded (NaN to 0, its bounds unused), which changes no bound and lets the rounding skip
/// the cast's checks.
#[inline(always)]
pub(super) fn around(d: f32, dmin: i32, dmax: i32) -> (i32, i32) {
    let matched = !d.is_nan();
    let r = round_half_away_within((if matched { d } else { 0.0 }).clamp(dmin as f32 - 3.0, dmax as f32 + 3.0));
    (if matched { (r - AROUND).max(dmin).min(dmax) } else { 1 }, if matched { (r + AROUND).max(dmin).min(dmax) } else { 0 })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `around` is SGM's value rounded (halves away from zero) ± 2, inside the range, and
    /// nothing for an unmatched pixel: at halves, at and past both ends of the range, far
    /// outside it, with negative disparities.
    #[test]
    fn the_correlation_searches_the_rounded_value_plus_minus_two() {
        let mut next = crate::testing::xorshift(0x0a40_07d);
        for (dmin, dmax) in [(0, 15), (-7, 24), (3, 130)] {
            let mut values = vec![f32::NAN, -1e6, 1e6, dmin as f32 - 0.5, dmax as f32 + 0.5, -2.5, -0.5, 0.5, 2.5, 1.49999];
            values.extend((0..400).map(|_| dmin as f32 - 4.0 + (next() % 1000) as f32 / 1000.0 * (dmax - dmin + 8) as f32));
            values.extend((0..40).map(|i| dmin as f32 - 3.0 + i as f32 * 0.5));
            values.extend((0..40).map(|i| dmax as f32 - 16.0 + i as f32 * 0.5));
            for d in values {
                let want = if d.is_nan() { (1, 0) } else { ((d.round() as i32 - 2).clamp(dmin, dmax), (d.round() as i32 + 2).clamp(dmin, dmax)) };
                assert_eq!(around(d, dmin, dmax), want, "{d} in {dmin} … {dmax}");
            }
        }
    }
}
