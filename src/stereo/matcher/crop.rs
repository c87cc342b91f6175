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
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Crop {
    pub(super) x0: usize,
    pub(super) y0: usize,
    pub(super) w: usize,
    pub(super) h: usize,
    /// Disparities from the lowest searched to the highest, within the range: no pixel's
    /// interval is wider (what lets a narrow call skip the seed's test, `seed.rs`).
    pub(super) span: usize,
    /// The lowest and the highest disparity searched, clamped into the range: where neither
    /// is an end of the range, no match can lie at one (what lets a call skip
    /// `DisparityMap::drop_range_ends`).
    pub(super) reach: (i32, i32),
    /// The searched pixels' columns and rows in the image (inside the rectangle above):
    /// outside them a call's map holds no disparity.
    pub(super) searched: (Range<usize>, Range<usize>),
}

/// What a call over the whole of its inputs is told of their searched pixels, in its own
/// coordinates: see [`Crop`]'s fields of the same names.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Searched {
    pub(super) span: usize,
    pub(super) reach: (i32, i32),
    pub(super) xs: Range<usize>,
    pub(super) ys: Range<usize>,
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
            let (a_min, b_max) = searched_extremes(&lo[first..=last], &hi[first..=last]);
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
        let (reach, searched) = ((dlo, dhi), (x0..x1 + 1, y0..y1 + 1));
        // Too narrow a crop to hold a window: match the whole image.
        if right - left + 1 < 2 {
            return Some(Crop { x0: 0, y0: 0, w, h, span, reach, searched });
        }
        Some(Crop { x0: left, y0: top, w: right - left + 1, h: bottom - top + 1, span, reach, searched })
    }

    /// The searched pixels as a call sees them whose inputs start at `(x, y)` of the image:
    /// `(0, 0)` for a call over the whole image, the crop's corner for a call over the crop.
    pub(super) fn seen_from(&self, (x, y): (usize, usize)) -> Searched {
        let (xs, ys) = &self.searched;
        Searched { span: self.span, reach: self.reach, xs: xs.start - x..xs.end - x, ys: ys.start - y..ys.end - y }
    }
}

/// The lowest `lo` and the highest `hi` over the searched pixels (`lo <= hi`) of a row's
/// bounds; `(i16::MAX, i16::MIN)` where none is searched.
fn searched_extremes(lo: &[i16], hi: &[i16]) -> (i16, i16) {
    let n = lo.len().min(hi.len());
    let (lo, hi) = (&lo[..n], &hi[..n]);
    #[cfg(target_arch = "x86_64")]
    let (done, (mut a_min, mut b_max)) = {
        use std::arch::x86_64::*;
        // Eight pixels a step in SSE2 (every x86-64 CPU has it), written out: the plain fold
        // below stays scalar, and took 0.017 ms of a call's 0.019 ms crop over a
        // 150 × 210 px object (0.007 ms this way).
        // SAFETY: SSE2 is part of x86-64; each load reads 8 values at k < n − 7 of both slices.
        unsafe {
            let (max, min) = (_mm_set1_epi16(i16::MAX), _mm_set1_epi16(i16::MIN));
            let (mut a, mut b) = (max, min);
            let mut k = 0;
            while k + 8 <= n {
                let l = _mm_loadu_si128(lo.as_ptr().add(k).cast());
                let h = _mm_loadu_si128(hi.as_ptr().add(k).cast());
                // All ones where not searched (lo > hi).
                let off = _mm_cmpgt_epi16(l, h);
                a = _mm_min_epi16(a, _mm_or_si128(_mm_andnot_si128(off, l), _mm_and_si128(off, max)));
                b = _mm_max_epi16(b, _mm_or_si128(_mm_andnot_si128(off, h), _mm_and_si128(off, min)));
                k += 8;
            }
            let (mut la, mut lb) = ([0i16; 8], [0i16; 8]);
            _mm_storeu_si128(la.as_mut_ptr().cast(), a);
            _mm_storeu_si128(lb.as_mut_ptr().cast(), b);
            (k, (la.into_iter().fold(i16::MAX, i16::min), lb.into_iter().fold(i16::MIN, i16::max)))
        }
    };
    #[cfg(not(target_arch = "x86_64"))]
    let (done, (mut a_min, mut b_max)) = (0, (i16::MAX, i16::MIN));
    for (&l, &h) in lo[done..].iter().zip(&hi[done..]) {
        let ok = l <= h;
        a_min = a_min.min(if ok { l } else { i16::MAX });
        b_max = b_max.max(if ok { h } else { i16::MIN });
    }
    (a_min, b_max)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The vector loop against the plain fold it replaces, on rows of every length from 0 to
    /// 40 (whole steps of eight and tails), searched pixels scattered or none, bounds across
    /// the whole `i16` range (`i16::MAX` and `i16::MIN` among them).
    #[test]
    fn the_searched_extremes_are_the_plain_fold_s() {
        let mut rand = crate::testing::xorshift(0xc40b);
        let mut value = |wide: bool| -> i16 {
            let r = rand();
            match r % 11 {
                0 => i16::MAX,
                1 => i16::MIN,
                _ if wide => (r >> 8) as i16,
                _ => ((r >> 8) % 300) as i16 - 150,
            }
        };
        for n in 0..=40 {
            for round in 0..50 {
                let wide = round % 2 == 0;
                let lo: Vec<i16> = (0..n).map(|_| value(wide)).collect();
                let hi: Vec<i16> = lo.iter().map(|&l| if round % 7 == 0 { l.saturating_sub(1) } else { value(wide) }).collect();
                let want = lo.iter().zip(&hi).filter(|(l, h)| l <= h).fold((i16::MAX, i16::MIN), |(a, b), (&l, &h)| (a.min(l), b.max(h)));
                assert_eq!(searched_extremes(&lo, &hi), want, "n {n}, lo {lo:?}, hi {hi:?}");
            }
        }
    }
}
