//! Small pieces of the interval construction: rounding without libm, clipped intervals, and
//! the rectangle of the image that holds the work.

use crate::stereo::DisparityMap;

/// `x.floor()` without a libm call (the baseline x86-64 target has no rounding instruction);
/// exact for |x| < 2²³, where every value here lies, and ±∞ stays ±∞.
#[inline(always)]
pub(super) fn floor(x: f32) -> f32 {
    if !(x.abs() < 8_388_608.0) {
        return x;
    }
    let t = x as i32 as f32;
    t - (t > x) as i32 as f32
}

/// `x.ceil()`, as [`floor`].
#[inline(always)]
pub(super) fn ceil(x: f32) -> f32 {
    -floor(-x)
}

/// `[lo, hi]` rounded outwards and clipped to `range`; `None` when it misses the range.
#[inline]
pub(super) fn interval(range: (i32, i32), lo: f32, hi: f32) -> Option<(i32, i32)> {
    // floor and ceil without a libm call (the baseline x86-64 target has no rounding
    // instruction); the bounds are far inside i32.
    let (tl, th) = (lo as i32, hi as i32);
    let (a, b) = ((tl - (lo < tl as f32) as i32).max(range.0), (th + (hi > th as f32) as i32).min(range.1));
    (a <= b).then_some((a, b))
}

/// Calls `f(k)` for every non-zero `flags[k]`, in order; eight flags are tested at once, so
/// that sparse flags (the few pixels of a row needing more work) cost little to find.
#[inline(always)]
pub(super) fn for_each_set(flags: &[u8], mut f: impl FnMut(usize)) {
    let mut words = flags.chunks_exact(8);
    let mut base = 0;
    for word in words.by_ref() {
        let mut bits = u64::from_le_bytes(word.try_into().expect("8 bytes"));
        while bits != 0 {
            f(base + bits.trailing_zeros() as usize / 8);
            // Clear the lowest set byte.
            bits &= !(0xff << (bits.trailing_zeros() / 8 * 8));
        }
        base += 8;
    }
    for (k, &v) in words.remainder().iter().enumerate() {
        if v != 0 {
            f(base + k);
        }
    }
}

/// One row of bounds into one row of intervals. A pixel with `want[k] != 0` and
/// `except[k] == 0` searches `lo[k]..=hi[k]` clipped to `range` and rounded outwards; one
/// whose clipped bounds are empty (nothing reached it: `lo = +∞`, `hi = −∞`) searches
/// nothing and is flagged in `hole`; every other pixel searches nothing. Returns whether any
/// hole was flagged.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub(super) fn round_row(want: &[u8], except: &[u8], lo: &[f32], hi: &[f32], out_lo: &mut [i16], out_hi: &mut [i16], hole: &mut [u8], range: (i32, i32)) -> bool {
    let (r0, r1) = (range.0 as f32, range.1 as f32);
    let n = want.len();
    let (except, lo, hi, out_lo, out_hi, hole) = (&except[..n], &lo[..n], &hi[..n], &mut out_lo[..n], &mut out_hi[..n], &mut hole[..n]);
    let mut any = 0u8;
    // Clipped, then rounded outwards (the range's ends are whole, so the order does not
    // matter). Branch-free, so that it vectorises; the rare holes are collected after.
    for k in 0..n {
        let wanted = (want[k] != 0) & (except[k] == 0);
        let (a, b) = (lo[k].max(r0), hi[k].min(r1));
        let ok = wanted & (a <= b);
        // Inside the range once selected, so the plain conversion is exact (and, unlike
        // `as`, needs no saturation checks: it vectorises).
        let (a, b) = (if ok { a } else { r0 }, if ok { b } else { r0 });
        // SAFETY: a and b lie in [r0, r1], whole numbers of i16 range.
        let (ta, tb) = unsafe { (a.to_int_unchecked::<i32>(), b.to_int_unchecked::<i32>()) };
        out_lo[k] = if ok { (ta - (ta as f32 > a) as i32) as i16 } else { 1 };
        out_hi[k] = if ok { (tb + ((tb as f32) < b) as i32) as i16 } else { 0 };
        let missed = wanted & !ok;
        hole[k] = missed as u8;
        any |= missed as u8;
    }
    any != 0
}

/// Pixels nothing reached take the hull of the intervals within this many pixels.
pub(super) const FILL: usize = 6;

/// A rectangle of the image, `x0..x1` × `y0..y1`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub(super) struct Region {
    pub(super) x0: usize,
    pub(super) x1: usize,
    pub(super) y0: usize,
    pub(super) y1: usize,
}

impl Region {
    /// The bounding box of the non-zero pixels of `mask` (the whole image without one).
    pub(super) fn of(mask: Option<&[u8]>, w: usize, h: usize) -> Option<Region> {
        match mask {
            Some(m) => Region::mask_bbox(m, w),
            None => Some(Region { x0: 0, x1: w, y0: 0, y1: h }),
        }
    }

    /// The bounding box of the finite values of a disparity map inside `within` (empty
    /// region if none).
    pub(super) fn of_disparity(d: &DisparityMap, within: Region) -> Region {
        let (w, v) = (d.width, d.values());
        let mut r: Option<Region> = None;
        // Eight values at a time: a value is finite when its exponent bits are not all set, so
        // the OR of `exponent XOR all-ones` over a chunk is non-zero when one of them is
        // (branch-free, it vectorises). The scans from each end stop at the first such chunk.
        const EXP: u32 = 0x7f80_0000;
        let finite_in = |c: &[f32]| c.iter().fold(0u32, |a, d| a | ((d.to_bits() & EXP) ^ EXP)) != 0;
        for y in within.ys() {
            let row = &v[y * w + within.x0..y * w + within.x1];
            let Some(c0) = row.chunks(8).position(finite_in) else { continue };
            let first = c0 * 8 + row[c0 * 8..].iter().position(|d| d.is_finite()).expect("one in the chunk");
            // (Chunks from the end: the last one ends at the row's end.)
            let c1 = row.rchunks(8).position(finite_in).expect("one exists");
            let end = row.len() - c1 * 8;
            let last = row[..end].iter().rposition(|d| d.is_finite()).expect("one in the chunk") + 1;
            r = Some(Region::extended(r, within.x0 + first..within.x0 + last, y));
        }
        r.unwrap_or_default()
    }

    /// The bounding box of the non-zero bytes of a row-major `w`-wide mask
    /// ([`crate::segment::mask_bounds`]).
    fn mask_bbox(mask: &[u8], w: usize) -> Option<Region> {
        crate::segment::mask_bounds(mask, w).map(|(xs, ys)| Region { x0: xs.start, x1: xs.end, y0: ys.start, y1: ys.end })
    }

    /// A bounding box built row by row, top to bottom: `r` grown to hold `xs` of row `y`.
    fn extended(r: Option<Region>, xs: std::ops::Range<usize>, y: usize) -> Region {
        match r {
            None => Region { x0: xs.start, x1: xs.end, y0: y, y1: y + 1 },
            Some(r) => Region { x0: r.x0.min(xs.start), x1: r.x1.max(xs.end), y0: r.y0, y1: y + 1 },
        }
    }

    pub(super) fn union(&self, o: &Region) -> Region {
        if o.x1 == 0 {
            return *self;
        }
        Region { x0: self.x0.min(o.x0), x1: self.x1.max(o.x1), y0: self.y0.min(o.y0), y1: self.y1.max(o.y1) }
    }

    pub(super) fn grow(&self, by: usize, w: usize, h: usize) -> Region {
        Region { x0: self.x0.saturating_sub(by), x1: (self.x1 + by).min(w), y0: self.y0.saturating_sub(by), y1: (self.y1 + by).min(h) }
    }

    /// The columns `(x − cx)/fx` of the rays of this region's pixel columns, in f32 (as the
    /// splats compute them per pixel).
    pub(super) fn column_rays(&self, cx: f32, ifx: f32) -> Vec<f32> {
        self.xs().map(|x| (x as f32 - cx) * ifx).collect()
    }

    pub(super) fn xs(&self) -> std::ops::Range<usize> {
        self.x0..self.x1
    }

    pub(super) fn ys(&self) -> std::ops::Range<usize> {
        self.y0..self.y1
    }
}

/// How many rows ahead a pass over a region asks for the rows of a map it reads.
pub(super) const PREFETCH_ROWS: usize = 4;

/// Asks for row `y` of a `w`-wide map (columns `xs`) to be brought into the cache ahead of
/// its use, where `y < y_end`. A region's rows are short, too short for the hardware to see
/// a stream in them, and the maps of the previous frame have long left the cache by the
/// time the next frame is planned: without it the plan's passes over them wait on memory.
#[inline(always)]
pub(super) fn prefetch_row<T>(map: &[T], w: usize, xs: std::ops::Range<usize>, y: usize, y_end: usize) {
    if y < y_end {
        let row = &map[y * w + xs.start..y * w + xs.end];
        crate::stereo::kernels::prefetch(row.as_ptr(), std::mem::size_of_val(row));
    }
}

/// The rows of a `w`-wide foreground mask inside a region; without a mask every pixel is
/// foreground (a row of ones stands in).
pub(super) struct MaskRows<'a> {
    mask: Option<&'a [u8]>,
    ones: Vec<u8>,
    w: usize,
    xs: std::ops::Range<usize>,
}

impl<'a> MaskRows<'a> {
    pub(super) fn new(mask: Option<&'a [u8]>, w: usize, region: &Region) -> MaskRows<'a> {
        MaskRows { ones: if mask.is_some() { Vec::new() } else { vec![1; region.x1 - region.x0] }, mask, w, xs: region.xs() }
    }

    /// Asks for row `y` of the mask (the region's columns) to be brought into the cache
    /// ([`prefetch_row`]).
    pub(super) fn prefetch(&self, y: usize, y_end: usize) {
        if let Some(m) = self.mask {
            prefetch_row(m, self.w, self.xs.clone(), y, y_end);
        }
    }

    /// Row `y` of the mask, the region's columns only.
    pub(super) fn row(&self, y: usize) -> &[u8] {
        match self.mask {
            Some(m) => &m[y * self.w + self.xs.start..y * self.w + self.xs.end],
            None => &self.ones,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bounding boxes against a plain scan, on sparse random masks and maps of widths
    /// that are and are not multiples of the chunk sizes.
    #[test]
    fn bounding_boxes_agree_with_a_plain_scan() {
        let mut rand = crate::testing::xorshift(12345);
        for (w, h) in [(37, 11), (64, 9), (8, 3), (5, 7), (100, 20)] {
            for density in [0u64, 1, 3, 50] {
                let mask: Vec<u8> = (0..w * h).map(|_| if rand() % 100 < density { 1 + (rand() % 255) as u8 } else { 0 }).collect();
                let vals: Vec<f32> = mask.iter().map(|&m| if m != 0 { m as f32 } else if rand() % 2 == 0 { f32::NAN } else { f32::NEG_INFINITY }).collect();
                let plain = |set: &dyn Fn(usize) -> bool, within: Region| {
                    let mut r: Option<Region> = None;
                    for y in within.ys() {
                        for x in within.xs() {
                            if set(y * w + x) {
                                r = Some(match r {
                                    None => Region { x0: x, x1: x + 1, y0: y, y1: y + 1 },
                                    Some(r) => Region { x0: r.x0.min(x), x1: r.x1.max(x + 1), y0: r.y0, y1: y + 1 },
                                });
                            }
                        }
                    }
                    r
                };
                let full = Region { x0: 0, x1: w, y0: 0, y1: h };
                assert_eq!(Region::mask_bbox(&mask, w), plain(&|i| mask[i] != 0, full), "{w}×{h}, {density} %");
                let map = DisparityMap::from_values(w, h, vals.clone());
                let within = Region { x0: 1.min(w - 1), x1: w - 1, y0: 1, y1: h };
                for win in [full, within] {
                    assert_eq!(Region::of_disparity(&map, win), plain(&|i| vals[i].is_finite(), win).unwrap_or_default(), "{w}×{h}, {density} %, {win:?}");
                }
            }
        }
    }
}
