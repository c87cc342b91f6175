//! The rectangle a matcher call works in (`Crop`): the searched pixels with their windows
//! and the right pixels their intervals reach, found inside the rectangle the intervals
//! record (`DisparityIntervals::searched`).

use std::ops::Range;

use super::scratch::{TILE_H, TILE_W};
use crate::stereo::disparity::{searched_span, DisparityIntervals};
use crate::stereo::params::ValidMatchParams;

/// The rectangle of a call that matters: the searched pixels' rows and columns, with the
/// rows of their windows, and the columns of their windows and of every right pixel their
/// intervals reach (plus one column for the prefilter's gradient), clipped to the image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Crop {
    pub(super) x0: usize,
    pub(super) y0: usize,
    pub(super) w: usize,
    pub(super) h: usize,
    /// Disparities from the lowest searched to the highest, within the range: no pixel's
    /// interval is wider (what lets a narrow call skip the seed's test, `seed.rs`).
    pub(super) span: usize,
}

impl Crop {
    /// The crop of `iv`: found inside the rectangle where its writers recorded the searched
    /// pixels to lie (`DisparityIntervals::searched`), the whole map where they did not.
    pub(super) fn of(iv: &DisparityIntervals, p: &ValidMatchParams) -> Option<Crop> {
        let (w, h) = (iv.width, iv.height);
        let Some((xs, ys)) = iv.searched.clone() else { return Self::within(iv, p, 0..w, 0..h) };
        let crop = Self::within(iv, p, xs.start.min(w)..xs.end.min(w), ys.start.min(h)..ys.end.min(h));
        debug_assert_eq!(crop, Self::within(iv, p, 0..w, 0..h), "searched pixels outside the rectangle the intervals recorded ({xs:?} × {ys:?})");
        crop
    }

    /// [`Crop::of`] from the searched pixels of columns `xs` and rows `ys` alone.
    fn within(iv: &DisparityIntervals, p: &ValidMatchParams, xs: Range<usize>, ys: Range<usize>) -> Option<Crop> {
        let (w, h) = (iv.width, iv.height);
        let (dmin, dmax) = (p.min_disparity, p.max_disparity());
        let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0usize, usize::MAX, 0usize);
        let (mut dlo, mut dhi) = (i32::MAX, i32::MIN);
        for y in ys {
            let (lo, hi) = (&iv.lo[y * w..][..w], &iv.hi[y * w..][..w]);
            let Some((first, last)) = searched_span(&lo[xs.clone()], &hi[xs.clone()]) else { continue };
            let (first, last) = (xs.start + first, xs.start + last);
            (x0, x1, y0, y1) = (x0.min(first), x1.max(last), y0.min(y), y1.max(y));
            // Branch-free, so that it vectorises.
            let (mut a_min, mut b_max) = (i16::MAX, i16::MIN);
            for (&a, &b) in lo[first..=last].iter().zip(&hi[first..=last]) {
                let ok = a <= b;
                a_min = a_min.min(if ok { a } else { i16::MAX });
                b_max = b_max.max(if ok { b } else { i16::MIN });
            }
            dlo = dlo.min(a_min as i32);
            dhi = dhi.max(b_max as i32);
        }
        if x0 > x1 {
            return None;
        }
        let (dlo, dhi) = (dlo.clamp(dmin, dmax), dhi.clamp(dmin, dmax));
        let span = (dhi - dlo + 1).max(0) as usize;
        let m = p.reach() as i64 + 1;
        let left = (x0 as i64 - m - dhi.max(0) as i64).max(0) as usize;
        let right = ((x1 as i64 + m - dlo.min(0) as i64) as usize).min(w - 1);
        let top = y0.saturating_sub(m as usize);
        // Started on a tile boundary, so that the narrow-band path's tiles are the image's
        // (a few more columns and rows of prefilter; the results are the same).
        let (left, top) = (left / TILE_W * TILE_W, top / TILE_H * TILE_H);
        let bottom = (y1 + m as usize).min(h - 1);
        // Too narrow a crop to hold a window: match the whole image.
        if right - left + 1 < 2 {
            return Some(Crop { x0: 0, y0: 0, w, h, span });
        }
        Some(Crop { x0: left, y0: top, w: right - left + 1, h: bottom - top + 1, span })
    }
}
