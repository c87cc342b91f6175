//! The matcher's plain data: the grey images it reads, the per-pixel disparity intervals it
//! searches, the disparity map it writes, and what one call did. Shared by the matcher, the
//! speckle filter, triangulation, the assistant and IO.

use std::ops::Range;

/// A borrowed 8-bit grey image, row-major, no padding.
#[derive(Debug, Clone, Copy)]
pub struct GrayView<'a> {
    pub width: usize,
    pub height: usize,
    pub data: &'a [u8],
}

impl<'a> GrayView<'a> {
    /// Wraps a buffer; `None` if it does not hold `width × height` bytes.
    pub fn new(width: usize, height: usize, data: &'a [u8]) -> Option<Self> {
        (data.len() == width * height).then_some(GrayView { width, height, data })
    }
}

/// The disparity interval to search at each left pixel, in disparity units
/// (`d = x_left − x_right`).
#[derive(Debug, Clone)]
pub struct DisparityIntervals {
    pub(in crate::stereo) width: usize,
    pub(in crate::stereo) height: usize,
    // Invariant: a pixel with lo > hi searches nothing.
    pub(in crate::stereo) lo: Vec<i16>,
    pub(in crate::stereo) hi: Vec<i16>,
    /// Columns and rows outside which no pixel searches anything, as far as the writers
    /// kept track (`None`: anywhere). Every method below keeps it true; the matcher reads it
    /// to find its crop without scanning the whole map (`Crop::of`, which checks it against
    /// a whole scan in debug builds). Code inside `stereo` that writes `lo`/`hi` directly
    /// sets it to `None`.
    pub(in crate::stereo) searched: Option<(Range<usize>, Range<usize>)>,
}

/// Equal intervals, whatever each one's record of where they lie.
impl PartialEq for DisparityIntervals {
    fn eq(&self, other: &Self) -> bool {
        (self.width, self.height) == (other.width, other.height) && self.lo == other.lo && self.hi == other.hi
    }
}

impl DisparityIntervals {
    /// Every pixel searches `min_d ..= max_d`.
    pub fn full(width: usize, height: usize, min_d: i32, max_d: i32) -> Self {
        let n = width * height;
        DisparityIntervals { width, height, lo: vec![min_d as i16; n], hi: vec![max_d as i16; n], searched: None }
    }

    /// Pixels where `mask` is non-zero (every pixel without a mask) search `min_d ..= max_d`.
    pub fn within(width: usize, height: usize, mask: Option<&[u8]>, min_d: i32, max_d: i32) -> Self {
        match mask {
            Some(m) => Self::masked(width, height, m, min_d, max_d),
            None => Self::full(width, height, min_d, max_d),
        }
    }

    /// No pixel searches anything.
    pub fn empty(width: usize, height: usize) -> Self {
        let n = width * height;
        DisparityIntervals { width, height, lo: vec![1; n], hi: vec![0; n], searched: Some((0..0, 0..0)) }
    }

    /// Pixels where `mask` is non-zero search `min_d ..= max_d`, the others nothing.
    pub fn masked(width: usize, height: usize, mask: &[u8], min_d: i32, max_d: i32) -> Self {
        let n = width * height;
        // (A short mask leaves the pixels past its end searching the full range.)
        let m = &mask[..mask.len().min(n)];
        // Branch-free, so that it vectorises (it runs for every full-range frame).
        let mut lo: Vec<i16> = m.iter().map(|&m| if m != 0 { min_d as i16 } else { 1 }).collect();
        let mut hi: Vec<i16> = m.iter().map(|&m| if m != 0 { max_d as i16 } else { 0 }).collect();
        lo.resize(n, min_d as i16);
        hi.resize(n, max_d as i16);
        DisparityIntervals { width, height, lo, hi, searched: None }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Sets the interval of one pixel (`None`: do not match it).
    pub fn set(&mut self, x: usize, y: usize, interval: Option<(i32, i32)>) {
        let i = y * self.width + x;
        let (lo, hi) = match interval {
            Some((lo, hi)) if lo <= hi => (lo.clamp(-32768, 32767) as i16, hi.clamp(-32768, 32767) as i16),
            _ => (1, 0),
        };
        self.lo[i] = lo;
        self.hi[i] = hi;
        if lo <= hi {
            self.extend_searched(x..x + 1, y..y + 1);
        }
    }

    /// No pixel of the rectangle `xs × ys` searches anything.
    pub fn clear_rect(&mut self, xs: Range<usize>, ys: Range<usize>) {
        self.clear_rect_but(xs, ys, 0..0, 0..0);
    }

    /// No pixel of `xs × ys` outside `keep_xs × keep_ys` searches anything; the pixels
    /// inside that are left as they are, for a writer about to set every one of them (as
    /// [`DisparityIntervals::clear_rect`] followed by those writes, without clearing the
    /// rectangle that is written anyway). Where the record of the searched pixels lay inside
    /// `xs × ys`, it shrinks to its part inside `keep_xs × keep_ys` (to none, where nothing
    /// is kept).
    pub fn clear_rect_but(&mut self, xs: Range<usize>, ys: Range<usize>, keep_xs: Range<usize>, keep_ys: Range<usize>) {
        let w = self.width;
        for_each_row_outside(xs.clone(), ys.clone(), keep_xs.clone(), keep_ys.clone(), |y, cols| {
            self.lo[y * w + cols.start..y * w + cols.end].fill(1);
            self.hi[y * w + cols.start..y * w + cols.end].fill(0);
        });
        if let Some((sx, sy)) = &self.searched {
            let inside = |a: &Range<usize>, b: &Range<usize>| a.is_empty() || (b.start <= a.start && a.end <= b.end);
            if sx.is_empty() || sy.is_empty() || (inside(sx, &xs) && inside(sy, &ys)) {
                let meet = |a: &Range<usize>, b: &Range<usize>| a.start.max(b.start)..a.end.min(b.end).max(a.start.max(b.start));
                let (mx, my) = (meet(sx, &keep_xs), meet(sy, &keep_ys));
                self.searched = Some(if mx.is_empty() || my.is_empty() { (0..0, 0..0) } else { (mx, my) });
            }
        }
    }

    /// The bounds of row `y`, to fill in place (`lo > hi`: not searched; values are
    /// disparities).
    pub fn row_mut(&mut self, y: usize) -> (&mut [i16], &mut [i16]) {
        self.row_cols_mut(y, 0..self.width)
    }

    /// The bounds of columns `xs` of row `y`, to fill in place: what [`Self::row_mut`] gives,
    /// for a writer that searches no pixel outside `xs` (the matcher then reads fewer columns
    /// to find where the searched pixels lie).
    pub fn row_cols_mut(&mut self, y: usize, xs: Range<usize>) -> (&mut [i16], &mut [i16]) {
        let w = self.width;
        self.extend_searched(xs.clone(), y..y + 1);
        (&mut self.lo[y * w + xs.start..y * w + xs.end], &mut self.hi[y * w + xs.start..y * w + xs.end])
    }

    /// Widens the record of where the searched pixels lie to hold `xs × ys`.
    fn extend_searched(&mut self, xs: Range<usize>, ys: Range<usize>) {
        if let Some((sx, sy)) = self.searched.take() {
            self.searched = Some(if sx.is_empty() || sy.is_empty() {
                (xs, ys)
            } else if xs.is_empty() || ys.is_empty() {
                (sx, sy)
            } else {
                (sx.start.min(xs.start)..sx.end.max(xs.end), sy.start.min(ys.start)..sy.end.max(ys.end))
            });
        }
    }

    /// Columns and rows outside which no pixel searches anything, as the writers recorded
    /// them (`None`: not recorded, anywhere).
    pub fn searched_rect(&self) -> Option<(Range<usize>, Range<usize>)> {
        self.searched.clone()
    }

    /// The interval of one pixel, `None` if it is not searched.
    pub fn get(&self, x: usize, y: usize) -> Option<(i32, i32)> {
        let i = y * self.width + x;
        (self.lo[i] <= self.hi[i]).then(|| (self.lo[i] as i32, self.hi[i] as i32))
    }
}

/// The first and last `x` with `lo[x] <= hi[x]` (a searched pixel), if any. Tested
/// [`SPAN_CHUNK`] at a time from each end, each chunk a fixed-size array tested branch-free
/// (so that it compiles to a few vector compares): rows are mostly background on both sides
/// of the object.
#[inline(always)]
pub(in crate::stereo) fn searched_span<T: PartialOrd + Copy>(lo: &[T], hi: &[T]) -> Option<(usize, usize)> {
    let n = lo.len().min(hi.len());
    let (lo, hi) = (&lo[..n], &hi[..n]);
    let chunk = |a: usize| -> (&[T; SPAN_CHUNK], &[T; SPAN_CHUNK]) { (lo[a..a + SPAN_CHUNK].try_into().unwrap(), hi[a..a + SPAN_CHUNK].try_into().unwrap()) };
    let any = |(l, h): (&[T; SPAN_CHUNK], &[T; SPAN_CHUNK])| l.iter().zip(h).fold(false, |acc, (l, h)| acc | (l <= h));
    let searched = |x: usize| lo[x] <= hi[x];
    // Whole chunks from the left, then the rest one by one.
    let mut start = 0;
    while start + SPAN_CHUNK <= n && !any(chunk(start)) {
        start += SPAN_CHUNK;
    }
    let first = (start..n).find(|&x| searched(x))?;
    // Whole chunks from the right down to `first`, then one by one.
    let mut end = n;
    while end >= first + SPAN_CHUNK && !any(chunk(end - SPAN_CHUNK)) {
        end -= SPAN_CHUNK;
    }
    let last = (first..end).rev().find(|&x| searched(x)).expect("first is searched");
    Some((first, last))
}

/// Pixels [`searched_span`] tests at once.
const SPAN_CHUNK: usize = 32;

/// Whether a search of disparities `lo ..= hi` reaches the ends of the range `first ..=
/// last` at which [`DisparityMap::drop_range_ends`] drops matches: `(the first, the last)`.
/// The last always counts, the first unless it is 0 (nothing lies beyond infinity). Asked of
/// each pixel there, and of a whole call's lowest and highest disparity to skip the pass.
#[inline(always)]
pub(in crate::stereo) fn range_ends_reached(lo: i32, hi: i32, first: i32, last: i32) -> (bool, bool) {
    (first != 0 && lo <= first, last != 0 && hi >= last)
}

/// Each row of the rectangle `xs × ys` with its columns outside `keep_xs × keep_ys` (one
/// or two non-empty pieces a row, none where the kept rectangle covers it): what
/// [`DisparityIntervals::clear_rect_but`] clears and [`DisparityMap::put_rect`] makes NaN.
fn for_each_row_outside(xs: Range<usize>, ys: Range<usize>, keep_xs: Range<usize>, keep_ys: Range<usize>, mut f: impl FnMut(usize, Range<usize>)) {
    // The kept columns inside `xs` (empty where no column is kept: each row of `ys` is then
    // whole).
    let kx = keep_xs.start.clamp(xs.start, xs.end)..keep_xs.end.clamp(xs.start, xs.end);
    for y in ys {
        let pieces = if keep_ys.contains(&y) && !kx.is_empty() { [xs.start..kx.start, kx.end..xs.end] } else { [xs.clone(), 0..0] };
        for cols in pieces.into_iter().filter(|c| !c.is_empty()) {
            f(y, cols);
        }
    }
}

/// A disparity map: `d = x_left − x_right` in rectified pixels, sub-pixel.
#[derive(Debug, Clone)]
pub struct DisparityMap {
    pub width: usize,
    pub height: usize,
    // Invariant: NaN where no disparity was found (the PFM convention); read with `get`.
    data: Vec<f32>,
    /// Columns and rows outside which every value is NaN, as far as the writers kept track
    /// (`None`: unknown). `new` and the matcher's writes of its crop ([`DisparityMap::put_rect`])
    /// keep it; a mutable borrow of the values drops it. The matcher reads it so as not to
    /// write NaN again where the map holds nothing but NaN (a new map, or the same map's
    /// last crop).
    nan_outside: Option<(Range<usize>, Range<usize>)>,
}

/// Equal maps, whatever each one's record of where its values lie.
impl PartialEq for DisparityMap {
    fn eq(&self, other: &Self) -> bool {
        (self.width, self.height) == (other.width, other.height) && self.data == other.data
    }
}

impl DisparityMap {
    pub fn new(width: usize, height: usize) -> Self {
        DisparityMap { width, height, data: vec![f32::NAN; width * height], nan_outside: Some((0..0, 0..0)) }
    }

    /// The rows of `src` (`xs.len()` values each, row-major) written into `xs × ys`, and every
    /// value outside that rectangle NaN: written only where the record says a value might not
    /// be NaN already (everywhere without one). The record becomes the rectangle.
    pub(in crate::stereo) fn put_rect(&mut self, xs: Range<usize>, ys: Range<usize>, src: &[f32]) {
        let w = self.width;
        assert!(xs.end <= w && ys.end <= self.height && src.len() == xs.len() * ys.len(), "a {}×{} rectangle at ({}, {}) in a {w}×{} map", xs.len(), ys.len(), xs.start, ys.start, self.height);
        let (ox, oy) = self.nan_outside.take().unwrap_or((0..w, 0..self.height));
        for_each_row_outside(ox, oy, xs.clone(), ys.clone(), |y, cols| self.data[y * w + cols.start..y * w + cols.end].fill(f32::NAN));
        if !xs.is_empty() {
            for (y, row) in ys.clone().zip(src.chunks_exact(xs.len())) {
                self.data[y * w + xs.start..y * w + xs.end].copy_from_slice(row);
            }
        }
        self.nan_outside = Some((xs, ys));
    }

    /// Every value NaN (written only where the record says one might not be).
    pub(in crate::stereo) fn clear(&mut self) {
        self.put_rect(0..0, 0..0, &[]);
    }

    /// Drops the matches whose best disparity was an end of the range `first ..= last`
    /// where the pixel's interval (`iv`, this map's size) reached that end: the last, and the
    /// first unless it is 0 (nothing lies beyond infinity). The cost was still falling there,
    /// so the true minimum may lie outside the range, where nothing was searched: an object
    /// that comes closer than the range covers would otherwise become a wall of points at
    /// the range's end. A winner's sub-pixel value lies within half a pixel of it, so a value
    /// past the end's half pixel is a winner at the end. Returns how many were dropped.
    pub fn drop_range_ends(&mut self, iv: &DisparityIntervals, first: i32, last: i32) -> usize {
        let (below, above) = (first as f32 + 0.5, last as f32 - 0.5);
        let mut dropped = 0;
        for ((v, &lo), &hi) in self.data.iter_mut().zip(&iv.lo).zip(&iv.hi) {
            let (first_end, last_end) = range_ends_reached(lo as i32, hi as i32, first, last);
            let at_last = last_end && *v > above;
            let at_first = first_end && *v < below;
            if at_last | at_first {
                *v = f32::NAN;
                dropped += 1;
            }
        }
        dropped
    }

    /// Builds a map from values where non-finite means "no disparity".
    pub fn from_values(width: usize, height: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), width * height, "disparity map size");
        DisparityMap { width, height, data, nan_outside: None }
    }

    pub fn get(&self, x: usize, y: usize) -> Option<f32> {
        let v = self.data[y * self.width + x];
        v.is_finite().then_some(v)
    }

    pub fn set(&mut self, x: usize, y: usize, d: Option<f32>) {
        self.data[y * self.width + x] = d.unwrap_or(f32::NAN);
        if let (Some(_), Some((xs, ys))) = (d, self.nan_outside.clone()) {
            // Widened to hold the pixel (or made the pixel, where it held nothing).
            self.nan_outside = Some(if xs.is_empty() || ys.is_empty() { (x..x + 1, y..y + 1) } else { (xs.start.min(x)..xs.end.max(x + 1), ys.start.min(y)..ys.end.max(y + 1)) });
        }
    }

    /// Row-major values, NaN where there is no disparity.
    pub fn values(&self) -> &[f32] {
        &self.data
    }

    /// Row-major values to write in place (the record of where they lie is dropped).
    pub(crate) fn values_mut(&mut self) -> &mut [f32] {
        self.nan_outside = None;
        &mut self.data
    }

    pub fn valid_count(&self) -> usize {
        self.valid_count_within(0..self.width, 0..self.height)
    }

    /// [`DisparityMap::valid_count`] over columns `xs` and rows `ys` alone.
    pub(in crate::stereo) fn valid_count_within(&self, xs: Range<usize>, ys: Range<usize>) -> usize {
        let w = self.width;
        ys.map(|y| self.data[y * w + xs.start..y * w + xs.end].iter().filter(|v| v.is_finite()).count()).sum()
    }
}

/// Rows of a matcher call of which one times its left–right check ([`MatchStats::lr_check_ns`]).
pub(in crate::stereo) const LR_TIMED_EVERY: usize = 8;

/// What one matching call did.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MatchStats {
    /// Pixels with a non-empty search interval.
    pub searched: usize,
    /// Pixels that got a disparity.
    pub matched: usize,
    /// (pixel, disparity) pairs evaluated.
    pub evaluated: u64,
    /// Wall time of the prefilter (a fixed cost per pixel of the image), ns.
    pub prefilter_ns: u64,
    /// Time spent in the left–right check, summed over the worker threads, ns: timed on
    /// every [`LR_TIMED_EVERY`]-th row and scaled by it (two clock reads a row cost ≈ 56 ns:
    /// on every row, about 3 % of a narrow `bm` call).
    pub lr_check_ns: u64,
    /// Pixels that reached the left–right check with a match, and those that passed it.
    pub lr_candidates: usize,
    pub lr_passed: usize,
    /// Wall time of the speckle filter (a fixed cost per matched pixel), ns.
    pub speckle_ns: u64,
    /// Matches dropped because their best disparity was an end of the range searched
    /// (`StereoMatcher::drop_range_edges`): many of them mean the scene comes closer (or lies
    /// farther) than the range covers.
    pub range_edge: usize,
}

impl MatchStats {
    /// `matched / searched` (0 when nothing was searched).
    pub fn valid_fraction(&self) -> f64 {
        if self.searched == 0 {
            0.0
        } else {
            self.matched as f64 / self.searched as f64
        }
    }

    /// `range_edge / searched`: the share of the searched pixels whose match was dropped at an
    /// end of the range (0 when nothing was searched).
    pub fn range_edge_share(&self) -> f64 {
        self.range_edge as f64 / self.searched.max(1) as f64
    }

    /// Percent of the matches that passed the left–right check (100 when it is off).
    pub fn lr_consistency(&self) -> f64 {
        if self.lr_candidates == 0 {
            100.0
        } else {
            100.0 * self.lr_passed as f64 / self.lr_candidates as f64
        }
    }

    /// Mean interval width actually searched, in pixels.
    pub fn mean_search_px(&self) -> f64 {
        if self.searched == 0 {
            0.0
        } else {
            self.evaluated as f64 / self.searched as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random writes through every method that writes: after each, every searched pixel
    /// lies inside the recorded rectangle. (It fails when a writer does not widen it, or when
    /// a clear empties it while a searched pixel is left outside the cleared rectangle.)
    #[test]
    fn the_record_of_where_searched_pixels_lie_holds_them_all() {
        let mut rand = crate::testing::xorshift(0x5EA2_C4ED);
        let mut below = |n: usize| (rand() % n as u64) as usize;
        let (w, h) = (23, 17);
        let mut iv = DisparityIntervals::empty(w, h);
        let mut narrowed = 0;
        for step in 0..4000 {
            let (x, y) = (below(w), below(h));
            let xs = x..x + 1 + below(w - x);
            let ys = y..y + 1 + below(h - y);
            match below(7) {
                0 => iv.set(x, y, Some((3, 9))),
                1 => iv.set(x, y, None),
                2 => iv.clear_rect(xs, ys),
                3 => {
                    let k = below(xs.len());
                    let (lo, hi) = iv.row_cols_mut(y, xs);
                    (lo[k], hi[k]) = (1, 5);
                }
                4 => {
                    let (lo, hi) = iv.row_mut(y);
                    (lo[x], hi[x]) = (2, 2);
                }
                5 => {
                    // Cleared around a kept rectangle (which may reach past the cleared one):
                    // exactly the pixels of `xs × ys` outside it search nothing after.
                    let (kx, ky) = (below(w), below(h));
                    let keep = (kx..kx + below(w - kx + 1), ky..ky + below(h - ky + 1));
                    let before = iv.clone();
                    iv.clear_rect_but(xs.clone(), ys.clone(), keep.0.clone(), keep.1.clone());
                    for yy in 0..h {
                        for xx in 0..w {
                            let cleared = xs.contains(&xx) && ys.contains(&yy) && !(keep.0.contains(&xx) && keep.1.contains(&yy));
                            assert_eq!(iv.get(xx, yy), if cleared { None } else { before.get(xx, yy) }, "step {step}: ({xx}, {yy}) around {keep:?}");
                        }
                    }
                }
                _ => iv.clear_rect(0..w, 0..h),
            }
            let (sx, sy) = iv.searched.clone().expect("the writers keep the record");
            narrowed += (sx.len() < w || sy.len() < h) as usize;
            for yy in 0..h {
                for xx in 0..w {
                    if iv.get(xx, yy).is_some() {
                        assert!(sx.contains(&xx) && sy.contains(&yy), "step {step}: ({xx}, {yy}) searched outside {sx:?} × {sy:?}");
                    }
                }
            }
        }
        assert!(narrowed > 1000, "the record narrows the search ({narrowed})");
        // Equal intervals are equal whatever their records.
        let mut a = DisparityIntervals::empty(4, 3);
        a.row_mut(1).0.fill(0);
        a.clear_rect(0..4, 1..2);
        assert_eq!(a, DisparityIntervals::empty(4, 3));
    }

    /// Random writes through every method that writes a map: each leaves the map a plain
    /// model says it holds (a rectangle put NaN everywhere else, whatever was there), and
    /// where the map keeps a record, every value outside it is NaN. (It fails when
    /// `put_rect` trusts a record that `values_mut` or `set` should have dropped or widened.)
    #[test]
    fn a_map_is_nan_outside_the_rectangle_it_records() {
        let mut rand = crate::testing::xorshift(0x0DD_F00D);
        let mut below = |n: usize| (rand() % n as u64) as usize;
        let (w, h) = (19, 13);
        let mut map = DisparityMap::new(w, h);
        let mut model = vec![f32::NAN; w * h];
        let mut trusted = 0;
        for step in 0..3000 {
            let (x, y) = (below(w), below(h));
            match below(5) {
                0 => {
                    map.set(x, y, Some(step as f32));
                    model[y * w + x] = step as f32;
                }
                1 => {
                    map.set(x, y, None);
                    model[y * w + x] = f32::NAN;
                }
                2 => {
                    map.values_mut()[y * w + x] = -(step as f32);
                    model[y * w + x] = -(step as f32);
                }
                3 => {
                    let (xs, ys) = (x..x + below(w - x + 1), y..y + below(h - y + 1));
                    let src: Vec<f32> = (0..xs.len() * ys.len()).map(|k| if k % 3 == 0 { f32::NAN } else { k as f32 }).collect();
                    trusted += map.nan_outside.is_some() as usize;
                    map.put_rect(xs.clone(), ys.clone(), &src);
                    for yy in 0..h {
                        for xx in 0..w {
                            model[yy * w + xx] = if xs.contains(&xx) && ys.contains(&yy) { src[(yy - ys.start) * xs.len() + xx - xs.start] } else { f32::NAN };
                        }
                    }
                }
                _ => {
                    map.clear();
                    model.fill(f32::NAN);
                }
            }
            assert!(map.values().iter().zip(&model).all(|(a, b)| a.to_bits() == b.to_bits()), "step {step}: the map differs from the model");
            if let Some((xs, ys)) = &map.nan_outside {
                for yy in 0..h {
                    for xx in 0..w {
                        assert!(map.get(xx, yy).is_none() || (xs.contains(&xx) && ys.contains(&yy)), "step {step}: ({xx}, {yy}) holds a value outside {xs:?} × {ys:?}");
                    }
                }
            }
        }
        assert!(trusted > 300, "put_rect read a record ({trusted} times)");
    }
}
