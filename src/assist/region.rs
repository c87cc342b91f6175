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
        for y in within.ys() {
            let row = &v[y * w + within.x0..y * w + within.x1];
            // Whole-row test first, branch-free (it vectorises); most rows have none or many.
            if !row.iter().fold(false, |any, d| any | d.is_finite()) {
                continue;
            }
            let first = within.x0 + row.iter().position(|d| d.is_finite()).expect("one exists");
            let last = within.x0 + row.len() - row.iter().rev().position(|d| d.is_finite()).expect("one exists");
            r = Some(Region::extended(r, first..last, y));
        }
        r.unwrap_or_default()
    }

    /// The bounding box of the non-zero bytes of a row-major `w`-wide mask.
    fn mask_bbox(mask: &[u8], w: usize) -> Option<Region> {
        let mut r: Option<Region> = None;
        for (y, row) in mask.chunks_exact(w).enumerate() {
            // Whole-row test first, eight bytes at a time: most rows hold none.
            let (words, rest) = row.split_at(w / 8 * 8);
            let any = words.chunks_exact(8).fold(0u64, |a, c| a | u64::from_le_bytes(c.try_into().expect("8 bytes"))) | rest.iter().fold(0u64, |a, &v| a | v as u64);
            if any == 0 {
                continue;
            }
            let first = row.iter().position(|&v| v != 0).expect("one exists");
            let last = w - row.iter().rev().position(|&v| v != 0).expect("one exists");
            r = Some(Region::extended(r, first..last, y));
        }
        r
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

    /// Row `y` of the mask, the region's columns only.
    pub(super) fn row(&self, y: usize) -> &[u8] {
        match self.mask {
            Some(m) => &m[y * self.w + self.xs.start..y * self.w + self.xs.end],
            None => &self.ones,
        }
    }
}
