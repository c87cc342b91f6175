//! Correlation matching along rectified rows, for a per-pixel disparity interval.
//!
//! # The cost, and why
//! Sum of absolute differences over a `block × block` window of x-Sobel-prefiltered,
//! clipped images (OpenCV `StereoBM`'s cost). The prefilter removes the brightness offset
//! between the cameras, the clipping bounds the influence of edges, and the cost of one
//! (pixel, disparity) pair is one byte difference — eight to thirty-two of them per SIMD
//! instruction, where census needs a 64-bit popcount per pair.
//!
//! # Intervals and the work they save
//! The entry point takes, for every left pixel, the disparity interval to search
//! ([`DisparityIntervals`]; the full range is the special case). Aggregation runs with
//! *banded* running sums, so every (pixel, disparity) pair costs O(1) amortised whatever the
//! interval shape, and no work is done outside the intervals:
//! - per column `x'`, the vertical window sums `CS(x', d)` are kept only over the band of
//!   disparities some pixel whose window covers `x'` needs, and are slid down one row
//!   (add the new row, subtract the old) where the band overlaps the previous row's band,
//!   recomputed from scratch (`block` terms) where it does not;
//! - per pixel, the window cost `SAD(x, d) = Σ CS(x−r … x+r, d)` is slid from pixel `x−1` where
//!   their intervals overlap, summed from scratch elsewhere.
//!
//! Sums are computed over whole blocks of [`BLOCK`] disparities around each searched interval
//! (clipped to the valid range), so that neighbours with slightly different narrow intervals
//! share a range and slide; the work is proportional to the summed interval widths rounded up
//! to blocks. Runs of pixels and columns sharing one range go through tight AVX2 loops.
//!
//! # The left–right check with left intervals only
//! The right image gets no intervals of its own: the candidate set of a right pixel `x_r` is
//! every evaluated pair `(x, d)` with `x − d = x_r` — the left intervals splatted onto the
//! right row. Its best disparity is the cheapest of those; a left match `d` at `x` passes when
//! the best disparity of `x − d` is within `lr_max_diff` of `d`. This costs one `min` per
//! evaluated pair, and with full intervals it is the classic check.
//!
//! # Pipeline
//! prefilter → per row: column sums → window sums + select (winner-take-all, texture,
//! uniqueness, sub-pixel) → left–right check → speckle filter over the whole map.

use std::ops::Range;

use super::kernels::{self, absdiff, add_absdiff, add_into, first_index_of, min_into, min_u16, min_u16_away_from, slide_column, slide_row};
use super::params::ValidMatchParams;
use super::speckle::SpeckleFilter;

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
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityIntervals {
    width: usize,
    height: usize,
    // Invariant: a pixel with lo > hi searches nothing.
    lo: Vec<i16>,
    hi: Vec<i16>,
}

impl DisparityIntervals {
    /// Every pixel searches `min_d ..= max_d`.
    pub fn full(width: usize, height: usize, min_d: i32, max_d: i32) -> Self {
        let n = width * height;
        DisparityIntervals { width, height, lo: vec![min_d as i16; n], hi: vec![max_d as i16; n] }
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
        DisparityIntervals { width, height, lo: vec![1; n], hi: vec![0; n] }
    }

    /// Pixels where `mask` is non-zero search `min_d ..= max_d`, the others nothing.
    pub fn masked(width: usize, height: usize, mask: &[u8], min_d: i32, max_d: i32) -> Self {
        let mut iv = Self::full(width, height, min_d, max_d);
        for (i, &m) in mask.iter().enumerate().take(width * height) {
            if m == 0 {
                iv.lo[i] = 1;
                iv.hi[i] = 0;
            }
        }
        iv
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
    }

    /// No pixel of the rectangle `xs × ys` searches anything.
    pub fn clear_rect(&mut self, xs: Range<usize>, ys: Range<usize>) {
        for y in ys {
            self.lo[y * self.width + xs.start..y * self.width + xs.end].fill(1);
            self.hi[y * self.width + xs.start..y * self.width + xs.end].fill(0);
        }
    }

    /// The bounds of row `y`, to fill in place (`lo > hi`: not searched; values are
    /// disparities).
    pub fn row_mut(&mut self, y: usize) -> (&mut [i16], &mut [i16]) {
        let w = self.width;
        (&mut self.lo[y * w..(y + 1) * w], &mut self.hi[y * w..(y + 1) * w])
    }

    /// The interval of one pixel, `None` if it is not searched.
    pub fn get(&self, x: usize, y: usize) -> Option<(i32, i32)> {
        let i = y * self.width + x;
        (self.lo[i] <= self.hi[i]).then(|| (self.lo[i] as i32, self.hi[i] as i32))
    }
}

/// A disparity map: `d = x_left − x_right` in rectified pixels, sub-pixel.
#[derive(Debug, Clone, PartialEq)]
pub struct DisparityMap {
    pub width: usize,
    pub height: usize,
    // Invariant: NaN where no disparity was found (the PFM convention); read with `get`.
    data: Vec<f32>,
}

impl DisparityMap {
    pub fn new(width: usize, height: usize) -> Self {
        DisparityMap { width, height, data: vec![f32::NAN; width * height] }
    }

    /// Builds a map from values where non-finite means "no disparity".
    pub fn from_values(width: usize, height: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), width * height, "disparity map size");
        DisparityMap { width, height, data }
    }

    pub fn get(&self, x: usize, y: usize) -> Option<f32> {
        let v = self.data[y * self.width + x];
        v.is_finite().then_some(v)
    }

    pub fn set(&mut self, x: usize, y: usize, d: Option<f32>) {
        self.data[y * self.width + x] = d.unwrap_or(f32::NAN);
    }

    /// Row-major values, NaN where there is no disparity.
    pub fn values(&self) -> &[f32] {
        &self.data
    }

    pub(crate) fn values_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }

    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|v| v.is_finite()).count()
    }
}

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
    /// Time spent in the left–right check, summed over the worker threads, ns.
    pub lr_check_ns: u64,
    /// Pixels that reached the left–right check with a match, and those that passed it.
    pub lr_candidates: usize,
    pub lr_passed: usize,
    /// Wall time of the speckle filter (a fixed cost per matched pixel), ns.
    pub speckle_ns: u64,
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

/// Why a pair cannot be matched.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MatchError {
    #[error("left image is {0}×{1} but right image is {2}×{3}; a rectified pair has one size")]
    SizeMismatch(usize, usize, usize, usize),
    #[error("search intervals are {0}×{1} but the images are {2}×{3}")]
    IntervalSize(usize, usize, usize, usize),
    #[error("images of {0}×{1} are too small for a {2}×{2} window")]
    TooSmall(usize, usize, u32),
    #[error("image buffer holds {0} bytes, expected {1} (width × height)")]
    Buffer(usize, usize),
}

/// Below this many disparities a from-scratch window sum runs per entry (scalar) instead of
/// per window line (vectorised).
const NARROW: usize = 8;

/// Window sums are computed over whole blocks of this many disparities (clipped to the valid
/// range) around each searched interval: one AVX2 register of costs. Neighbouring pixels
/// whose narrow intervals differ slightly then share a range and slide, instead of
/// recomputing window sums from scratch at every shift.
const BLOCK: usize = 16;

/// Sizes shared by every stripe of one call.
#[derive(Clone, Copy)]
struct Geometry {
    w: usize,
    h: usize,
    r: usize,
    /// Padded width of the prefiltered left rows (`w + 2r`).
    wp: usize,
    n: usize,
    dmin: i32,
    /// Replicated padding of the prefiltered right rows on the left and right: wide enough
    /// for every disparity at every column, so that window sums may be computed over whole
    /// blocks even where the right pixel falls outside the image (those pairs are never
    /// searched).
    rpad_left: usize,
    rpad_right: usize,
}

impl Geometry {
    /// The sizes of matching a `w × h` pair with these parameters.
    fn new(p: &ValidMatchParams, w: usize, h: usize) -> Geometry {
        let r = p.radius();
        let (dmin, dmax) = (p.min_disparity, p.max_disparity());
        Geometry {
            w,
            h,
            r,
            wp: w + 2 * r,
            n: p.num_disparities as usize,
            dmin,
            rpad_left: r + dmax.max(0) as usize,
            rpad_right: r + (-dmin).max(0) as usize,
        }
    }

    /// Width of a padded right row.
    fn wr(&self) -> usize {
        self.w + self.rpad_left + self.rpad_right
    }
}

/// A `u16` buffer whose contents start on a 64-byte boundary, so that the column and window
/// sums (rows of 16-lane multiples) are read with aligned vector loads: a load that splits
/// a cache line costs extra, and a plain `Vec` gives no alignment guarantee beyond 16 bytes.
#[derive(Default)]
struct AlignedBuf {
    buf: Vec<u16>,
    start: usize,
    len: usize,
}

impl AlignedBuf {
    const ALIGN: usize = 64;

    /// Makes the buffer `len` long. Contents are not kept: callers overwrite before reading.
    fn resize(&mut self, len: usize, value: u16) {
        let slack = Self::ALIGN / std::mem::size_of::<u16>();
        if self.buf.len() < len + slack {
            self.buf = vec![value; len + slack];
        }
        let misalign = self.buf.as_ptr() as usize % Self::ALIGN;
        self.start = if misalign == 0 { 0 } else { (Self::ALIGN - misalign) / std::mem::size_of::<u16>() };
        self.len = len;
    }
}

impl std::ops::Deref for AlignedBuf {
    type Target = [u16];
    fn deref(&self) -> &[u16] {
        &self.buf[self.start..self.start + self.len]
    }
}

impl std::ops::DerefMut for AlignedBuf {
    fn deref_mut(&mut self) -> &mut [u16] {
        &mut self.buf[self.start..self.start + self.len]
    }
}

/// What every stripe of one call reads: parameters, sizes, the prefiltered rows (left
/// padded, right padded and reversed) and the search intervals.
#[derive(Clone, Copy)]
struct StripeInput<'a> {
    p: &'a ValidMatchParams,
    g: Geometry,
    lpf: &'a [u8],
    rrev: &'a [u8],
    intervals: &'a DisparityIntervals,
}

/// Per-thread buffers, grown to fit and reused across frames.
#[derive(Default)]
struct StripeScratch {
    /// Vertical window sums, `wp × n`, column-major in disparity.
    cs: AlignedBuf,
    /// Band of valid entries per column (empty when lo > hi).
    band_lo: Vec<i32>,
    band_hi: Vec<i32>,
    need_lo: Vec<i32>,
    need_hi: Vec<i32>,
    /// This row's searched intervals, in disparity index `k = d − dmin`.
    tlo: Vec<i32>,
    thi: Vec<i32>,
    /// The block-aligned ranges the window sums are computed over (⊇ the searched ones).
    ilo: Vec<i32>,
    ihi: Vec<i32>,
    /// Window sums of the current row, `w × n`.
    sad: AlignedBuf,
    /// Cheapest evaluated cost of each right pixel, stored reversed: entry `w − 1 − x + k`
    /// is right pixel `x − dmin − k`, so a left pixel's run of disparities is contiguous.
    right_min: Vec<u16>,
    best: Vec<Option<(u16, f32)>>,
    tex_col: Vec<u32>,
    /// Window texture of each pixel of the row.
    tex_row: Vec<u32>,
    band_tmp: Vec<i32>,
    prev_ilo: Vec<i32>,
    prev_ihi: Vec<i32>,
}

/// A reusable matcher: holds the validated parameters and every scratch buffer.
pub struct StereoMatcher {
    params: ValidMatchParams,
    left_pf: Vec<u8>,
    right_pf_rev: Vec<u8>,
    stripes: Vec<StripeScratch>,
    speckle: SpeckleFilter,
    /// The cropped inputs and output (see [`Crop`]), reused.
    crop_left: Vec<u8>,
    crop_right: Vec<u8>,
    crop_intervals: DisparityIntervals,
    crop_out: DisparityMap,
}

/// The rectangle of a call that matters: the searched pixels' rows and columns, with the
/// rows of their windows, and the columns of their windows and of every right pixel their
/// intervals reach (plus one column for the prefilter's gradient), clipped to the image.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Crop {
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
}

impl Crop {
    fn of(iv: &DisparityIntervals, p: &ValidMatchParams) -> Option<Crop> {
        let (w, h) = (iv.width, iv.height);
        let (dmin, dmax) = (p.min_disparity, p.max_disparity());
        let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0usize, usize::MAX, 0usize);
        let (mut dlo, mut dhi) = (i32::MAX, i32::MIN);
        for y in 0..h {
            let (lo, hi) = (&iv.lo[y * w..][..w], &iv.hi[y * w..][..w]);
            let Some(first) = lo.iter().zip(hi).position(|(a, b)| a <= b) else { continue };
            let last = w - 1 - lo.iter().zip(hi).rev().position(|(a, b)| a <= b).expect("one exists");
            (x0, x1, y0, y1) = (x0.min(first), x1.max(last), y0.min(y), y1.max(y));
            for (a, b) in lo[first..=last].iter().zip(&hi[first..=last]) {
                if a <= b {
                    dlo = dlo.min(*a as i32);
                    dhi = dhi.max(*b as i32);
                }
            }
        }
        if x0 > x1 {
            return None;
        }
        let (dlo, dhi) = (dlo.clamp(dmin, dmax), dhi.clamp(dmin, dmax));
        let m = p.radius() as i64 + 1;
        let left = (x0 as i64 - m - dhi.max(0) as i64).max(0) as usize;
        let right = ((x1 as i64 + m - dlo.min(0) as i64) as usize).min(w - 1);
        let top = y0.saturating_sub(m as usize);
        let bottom = (y1 + m as usize).min(h - 1);
        // Too narrow a crop to hold a window: match the whole image.
        if right - left + 1 < 2 {
            return Some(Crop { x0: 0, y0: 0, w, h });
        }
        Some(Crop { x0: left, y0: top, w: right - left + 1, h: bottom - top + 1 })
    }
}

impl StereoMatcher {
    pub fn new(params: ValidMatchParams) -> Self {
        StereoMatcher {
            params,
            left_pf: Vec::new(),
            right_pf_rev: Vec::new(),
            stripes: Vec::new(),
            speckle: SpeckleFilter::default(),
            crop_left: Vec::new(),
            crop_right: Vec::new(),
            crop_intervals: DisparityIntervals::empty(0, 0),
            crop_out: DisparityMap::new(0, 0),
        }
    }

    pub fn params(&self) -> &ValidMatchParams {
        &self.params
    }

    /// The full search range of these parameters for every pixel, or only where `mask` is set.
    pub fn full_intervals(&self, width: usize, height: usize, mask: Option<&[u8]>) -> DisparityIntervals {
        DisparityIntervals::within(width, height, mask, self.params.min_disparity, self.params.max_disparity())
    }

    /// Matches a rectified pair. Intervals are clipped to the parameters' disparity range and
    /// to disparities whose right pixel lies inside the image.
    pub fn compute(
        &mut self,
        left: GrayView,
        right: GrayView,
        intervals: &DisparityIntervals,
        out: &mut DisparityMap,
    ) -> Result<MatchStats, MatchError> {
        let (w, h) = (left.width, left.height);
        if (right.width, right.height) != (w, h) {
            return Err(MatchError::SizeMismatch(w, h, right.width, right.height));
        }
        if (intervals.width, intervals.height) != (w, h) {
            return Err(MatchError::IntervalSize(intervals.width, intervals.height, w, h));
        }
        if w < 2 || h < 1 {
            return Err(MatchError::TooSmall(w, h, self.params.block));
        }
        if out.width != w || out.height != h {
            *out = DisparityMap::new(w, h);
        }
        // Only the rectangle the searched pixels' windows and right correspondences need is
        // matched: the results are the same (every window and every right pixel searched lies
        // inside it, and where it meets the image border, the border is the image's), and
        // rows and columns of background cost nothing.
        let Some(crop) = Crop::of(intervals, &self.params) else {
            out.values_mut().fill(f32::NAN);
            return Ok(MatchStats::default());
        };
        if crop.x0 == 0 && crop.y0 == 0 && crop.w == w && crop.h == h {
            return Ok(self.compute_whole(left, right, intervals, out));
        }
        let cut = |img: GrayView, buf: &mut Vec<u8>| {
            buf.clear();
            for y in crop.y0..crop.y0 + crop.h {
                buf.extend_from_slice(&img.data[y * w + crop.x0..][..crop.w]);
            }
        };
        let (mut lbuf, mut rbuf) = (std::mem::take(&mut self.crop_left), std::mem::take(&mut self.crop_right));
        cut(left, &mut lbuf);
        cut(right, &mut rbuf);
        let mut civ = std::mem::replace(&mut self.crop_intervals, DisparityIntervals::empty(0, 0));
        civ.width = crop.w;
        civ.height = crop.h;
        civ.lo.clear();
        civ.hi.clear();
        for y in crop.y0..crop.y0 + crop.h {
            civ.lo.extend_from_slice(&intervals.lo[y * w + crop.x0..][..crop.w]);
            civ.hi.extend_from_slice(&intervals.hi[y * w + crop.x0..][..crop.w]);
        }
        let mut cout = std::mem::replace(&mut self.crop_out, DisparityMap::new(0, 0));
        if (cout.width, cout.height) != (crop.w, crop.h) {
            cout = DisparityMap::new(crop.w, crop.h);
        }
        let lv = GrayView { width: crop.w, height: crop.h, data: &lbuf };
        let rv = GrayView { width: crop.w, height: crop.h, data: &rbuf };
        let stats = self.compute_whole(lv, rv, &civ, &mut cout);
        out.values_mut().fill(f32::NAN);
        for (y, src) in cout.values().chunks(crop.w).enumerate() {
            out.values_mut()[(crop.y0 + y) * w + crop.x0..][..crop.w].copy_from_slice(src);
        }
        (self.crop_left, self.crop_right, self.crop_intervals, self.crop_out) = (lbuf, rbuf, civ, cout);
        Ok(stats)
    }

    /// [`StereoMatcher::compute`] over the whole of checked inputs.
    fn compute_whole(&mut self, left: GrayView, right: GrayView, intervals: &DisparityIntervals, out: &mut DisparityMap) -> MatchStats {
        let (w, h) = (left.width, left.height);
        let geo = Geometry::new(&self.params, w, h);

        let t0 = std::time::Instant::now();
        prefilter_xsobel(left, self.params.prefilter_cap, (geo.r, geo.r), false, &mut self.left_pf);
        prefilter_xsobel(right, self.params.prefilter_cap, (geo.rpad_left, geo.rpad_right), true, &mut self.right_pf_rev);
        let prefilter_ns = t0.elapsed().as_nanos() as u64;

        let threads = self.params.thread_count().min(h).max(1);
        self.stripes.resize_with(threads, StripeScratch::default);
        let rows_per = h.div_ceil(threads);
        let params = &self.params;
        let input = StripeInput { p: params, g: geo, lpf: &self.left_pf, rrev: &self.right_pf_rev, intervals };
        let mut totals = MatchStats { prefilter_ns, ..MatchStats::default() };
        let out_chunks = out.values_mut().chunks_mut(rows_per * w);
        let stats: Vec<MatchStats> = std::thread::scope(|scope| {
            let mut handles = Vec::new();
            let mut first = None;
            for (i, (chunk, scratch)) in out_chunks.zip(self.stripes.iter_mut()).enumerate() {
                let rows = i * rows_per..((i + 1) * rows_per).min(h);
                let job = move || match_stripe(input, rows, chunk, scratch);
                if i == 0 {
                    first = Some(job);
                } else {
                    let handle = std::thread::Builder::new()
                        .name(format!("matcher-{i}"))
                        .spawn_scoped(scope, job)
                        .expect("spawning a matcher thread");
                    handles.push(handle);
                }
            }
            let mut all = vec![first.map(|f| f()).unwrap_or_default()];
            all.extend(handles.into_iter().map(|h| h.join().expect("matcher thread panicked")));
            all
        });
        for s in stats {
            totals.searched += s.searched;
            totals.evaluated += s.evaluated;
            totals.lr_check_ns += s.lr_check_ns;
            totals.lr_candidates += s.lr_candidates;
            totals.lr_passed += s.lr_passed;
        }
        if params.speckle_window > 0 {
            let t0 = std::time::Instant::now();
            self.speckle.apply(out, params.speckle_window as usize, params.speckle_range_px);
            totals.speckle_ns = t0.elapsed().as_nanos() as u64;
        }
        totals.matched = out.valid_count();
        totals
    }
}

/// OpenCV BM's x-Sobel prefilter, clipped to ±cap and offset by cap, written with
/// `pad = (left, right)` columns of replicated padding; `reversed` stores each padded row back
/// to front so that increasing disparity walks forward in memory.
fn prefilter_xsobel(img: GrayView, cap: u8, pad: (usize, usize), reversed: bool, out: &mut Vec<u8>) {
    let (w, h) = (img.width, img.height);
    let (r, wp) = (pad.0, w + pad.0 + pad.1);
    out.clear();
    out.resize(wp * h, 0);
    let cap_i = cap as i16;
    for y in 0..h {
        let up = &img.data[y.saturating_sub(1) * w..][..w];
        let mid = &img.data[y * w..][..w];
        let down = &img.data[(y + 1).min(h - 1) * w..][..w];
        let dst = &mut out[y * wp..][..wp];
        {
            // Interior: written straight into the padded row (vectorises as i16 lanes).
            let row = &mut dst[r..r + w];
            row[0] = cap;
            row[w - 1] = cap;
            for x in 1..w - 1 {
                let g = (mid[x + 1] as i16 - mid[x - 1] as i16) * 2 + (up[x + 1] as i16 - up[x - 1] as i16)
                    + (down[x + 1] as i16 - down[x - 1] as i16);
                row[x] = (g.clamp(-cap_i, cap_i) + cap_i) as u8;
            }
        }
        let (first, last) = (dst[r], dst[r + w - 1]);
        dst[..r].fill(first);
        dst[r + w..].fill(last);
        if reversed {
            dst.reverse();
        }
    }
}

/// The row of the window that sits `dy` rows from `y`, clamped to the image.
#[inline(always)]
fn clamp_row(y: isize, h: usize) -> usize {
    y.clamp(0, h as isize - 1) as usize
}

fn match_stripe(
    input: StripeInput,
    rows: Range<usize>,
    out: &mut [f32],
    s: &mut StripeScratch,
) -> MatchStats {
    #[cfg(target_arch = "x86_64")]
    {
        // 512-bit registers pay off only over long runs of disparities: measured here,
        // AVX-512 was ≈ 5 % faster on Reindeer (128 disparities) but ≈ 10 % slower on Teddy
        // (64) and ≈ 20 % slower on Tsukuba (16) than the AVX2 copy.
        let wide = input.g.n >= 128;
        if wide && std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw") {
            // SAFETY: the CPU supports AVX-512F/BW (and so AVX2), checked just above.
            return unsafe { match_stripe_avx512(input, rows, out, s) };
        }
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            return unsafe { match_stripe_avx2(input, rows, out, s) };
        }
    }
    match_stripe_impl::<false, false>(input, rows, out, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn match_stripe_avx2(
    input: StripeInput,
    rows: Range<usize>,
    out: &mut [f32],
    s: &mut StripeScratch,
) -> MatchStats {
    match_stripe_impl::<true, false>(input, rows, out, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512bw")]
unsafe fn match_stripe_avx512(
    input: StripeInput,
    rows: Range<usize>,
    out: &mut [f32],
    s: &mut StripeScratch,
) -> MatchStats {
    match_stripe_impl::<true, true>(input, rows, out, s)
}

/// The whole per-stripe pipeline; inlined into each SIMD-level wrapper so the compiler
/// vectorises the slice loops for that level.
#[inline(always)]
fn match_stripe_impl<const AVX2: bool, const AVX512: bool>(
    input: StripeInput,
    rows: Range<usize>,
    out: &mut [f32],
    s: &mut StripeScratch,
) -> MatchStats {
    let StripeInput { p, g, lpf, rrev, intervals } = input;
    let Geometry { w, n, wp, .. } = g;
    s.cs.resize(wp * n, 0);
    for v in [&mut s.band_lo, &mut s.need_lo] {
        v.clear();
        v.resize(wp, 1);
    }
    for v in [&mut s.band_hi, &mut s.need_hi] {
        v.clear();
        v.resize(wp, 0);
    }
    for v in [&mut s.ilo, &mut s.ihi, &mut s.prev_ilo, &mut s.prev_ihi, &mut s.tlo, &mut s.thi] {
        v.resize(w, 0);
    }
    // LANES entries of slack: narrow intervals are searched as one 16-lane load.
    s.sad.resize(w * n + kernels::LANES, 0);
    s.right_min.resize(w + n + kernels::LANES, u16::MAX);
    s.best.resize(w, None);
    s.tex_col.resize(wp, 0);
    s.tex_row.resize(w, 0);

    let mut stats = MatchStats::default();
    let y0 = rows.start;
    // Columns whose sums were brought down to the previous row (all others hold no band),
    // and whether that previous row is the one just above.
    let mut live: Range<usize> = 0..0;
    let mut prev_row: Option<(usize, Range<usize>)> = None;
    for y in rows {
        std::mem::swap(&mut s.ilo, &mut s.prev_ilo);
        std::mem::swap(&mut s.ihi, &mut s.prev_ihi);
        let out_row = &mut out[(y - y0) * w..][..w];
        // Only the row's searched span is worked on: rows and columns of background cost
        // (almost) nothing.
        let Some(span) = row_intervals(g, intervals, y, &mut s.tlo, &mut s.thi, &mut s.ilo, &mut s.ihi, &mut stats) else {
            out_row.fill(f32::NAN);
            continue;
        };
        let cols = span.start..span.end + 2 * g.r;
        let first_row = prev_row.as_ref().is_none_or(|(py, _)| py + 1 != y);
        // Columns leaving the live set (all of it after a gap) lose their band.
        for xp in live.clone() {
            if first_row || !cols.contains(&xp) {
                s.band_lo[xp] = 1;
                s.band_hi[xp] = 0;
            }
        }
        live = cols.clone();
        // A row whose span and ranges repeat the previous row's (always so with the full
        // range) keeps the previous row's column bands.
        let same = !first_row && prev_row.as_ref().is_some_and(|(_, ps)| *ps == span) && s.ilo[span.clone()] == s.prev_ilo[span.clone()] && s.ihi[span.clone()] == s.prev_ihi[span.clone()];
        if !same {
            let sub = Geometry { w: span.len(), wp: span.len() + 2 * g.r, ..g };
            column_bands(sub, &s.ilo[span.clone()], &s.ihi[span.clone()], &mut s.need_lo[cols.clone()], &mut s.need_hi[cols.clone()], &mut s.band_tmp);
        }
        update_column_sums::<AVX2, AVX512>(g, lpf, rrev, y, first_row, cols, s);
        if p.texture_threshold > 0 {
            update_texture(g, lpf, y, first_row, p.prefilter_cap, &mut s.tex_col);
        }
        select_row::<AVX2, AVX512>(p, g, s, span.clone());
        let t0 = std::time::Instant::now();
        out_row[..span.start].fill(f32::NAN);
        out_row[span.end..].fill(f32::NAN);
        let (candidates, passed) = left_right_check(p, g, s, out_row, span.clone());
        stats.lr_candidates += candidates;
        stats.lr_passed += passed;
        prev_row = Some((y, span));
        stats.lr_check_ns += t0.elapsed().as_nanos() as u64;
    }
    stats
}

/// This row's intervals as disparity indices, clipped to the search range and to right
/// pixels inside the image (`tlo..=thi`, what is searched), and the block-aligned ranges the
/// sums are computed over (`ilo..=ihi`, see [`BLOCK`]); counts searched pixels and pairs.
/// Returns the span from the first to the last searched pixel (None: nothing searched).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn row_intervals(g: Geometry, iv: &DisparityIntervals, y: usize, tlo: &mut [i32], thi: &mut [i32], ilo: &mut [i32], ihi: &mut [i32], stats: &mut MatchStats) -> Option<Range<usize>> {
    let Geometry { w, n, dmin, .. } = g;
    let (mut first, mut last) = (usize::MAX, 0);
    let (row_lo, row_hi) = (&iv.lo[y * w..][..w], &iv.hi[y * w..][..w]);
    let (mut searched, mut evaluated) = (0usize, 0u64);
    let block = BLOCK as i32;
    for x in 0..w {
        let (mut lo, mut hi, mut clo, mut chi) = (1, 0, 1, 0);
        let (dlo, dhi) = (row_lo[x] as i32, row_hi[x] as i32);
        // The right pixel x − d must lie inside the image: x − w + 1 ≤ d ≤ x.
        let kmin = (x as i32 - w as i32 + 1).max(dmin) - dmin;
        let kmax = (x as i32).min(dmin + n as i32 - 1) - dmin;
        let (a, b) = (dlo - dmin, dhi - dmin);
        if dlo <= dhi && a.max(kmin) <= b.min(kmax) {
            (lo, hi) = (a.max(kmin), b.min(kmax));
            // Whole blocks, so that neighbours with slightly different intervals share one
            // range and slide instead of recomputing; not clipped to the image (the right
            // rows are padded for that), so border pixels share their neighbours' blocks.
            (clo, chi) = (lo - lo.rem_euclid(block), (hi - hi.rem_euclid(block) + block - 1).min(n as i32 - 1));
            searched += 1;
            evaluated += (hi - lo + 1) as u64;
            first = first.min(x);
            last = x;
        }
        tlo[x] = lo;
        thi[x] = hi;
        ilo[x] = clo;
        ihi[x] = chi;
    }
    stats.searched += searched;
    stats.evaluated += evaluated;
    (first <= last).then(|| first..last + 1)
}

/// For each padded column, the union of the intervals of the pixels whose window covers it:
/// a sliding-window min of `ilo` and max of `ihi` (van Herk / Gil–Werman, O(1) per column).
#[inline(always)]
fn column_bands(g: Geometry, ilo: &[i32], ihi: &[i32], need_lo: &mut [i32], need_hi: &mut [i32], tmp: &mut Vec<i32>) {
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
fn sliding_extreme(v: &[i32], b: usize, prefix: &mut [i32], suffix: &mut [i32], pick: fn(i32, i32) -> i32, out: &mut [i32]) {
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
fn right_start(g: Geometry, xp: usize) -> isize {
    // Right sample of (x' = xp − r, d = dmin + k) is padded column x' − d + rpad_left, stored
    // at wr − 1 − (that) in the reversed row.
    g.wr() as isize - 1 - (xp as isize - g.r as isize - g.dmin as isize + g.rpad_left as isize)
}

/// Slides the vertical window sums down to row `y` over each needed band of the columns `cols`.
#[inline(always)]
fn update_column_sums<const AVX2: bool, const AVX512: bool>(g: Geometry, lpf: &[u8], rrev: &[u8], y: usize, first_row: bool, cols: Range<usize>, s: &mut StripeScratch) {
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
unsafe fn slide_columns_avx2<const AVX512: bool>(g: Geometry, cs: &mut [u16], new: (&[u8], &[u8]), old: (&[u8], &[u8]), xps: Range<usize>, k0: usize, k1: usize) {
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
fn fresh_column(g: Geometry, lpf: &[u8], rrev: &[u8], y: usize, xp: usize, j0: isize, a: i32, b: i32, cs: &mut [u16]) {
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
fn update_texture(g: Geometry, lpf: &[u8], y: usize, first_row: bool, cap: u8, tex: &mut [u32]) {
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

/// Window sums, winner-take-all, texture and uniqueness tests, sub-pixel fit, and the
/// right-image minima for the left–right check.
#[inline(always)]
fn select_row<const AVX2: bool, const AVX512: bool>(p: &ValidMatchParams, g: Geometry, s: &mut StripeScratch, span: Range<usize>) {
    let Geometry { w, r, n, .. } = g;
    let b = 2 * r + 1;
    // The right pixels this span's pairs land on: entries w − 1 − x + k.
    s.right_min[w - span.end..w - span.start + n].fill(u16::MAX);
    if p.texture_threshold > 0 {
        // Window texture of every pixel of the span: the column sums slid along the row.
        let mut tex: u32 = s.tex_col[span.start..span.start + b].iter().sum();
        s.tex_row[span.start] = tex;
        for x in span.start + 1..span.end {
            tex = tex + s.tex_col[x + b - 1] - s.tex_col[x - 1];
            s.tex_row[x] = tex;
        }
    }
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
unsafe fn select_run_avx2<const AVX512: bool>(p: &ValidMatchParams, g: Geometry, s: &mut StripeScratch, xs: Range<usize>, k0: usize, k1: usize) {
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
fn decide<const AVX2: bool>(p: &ValidMatchParams, costs: &[u16], min: u16, tex: u32) -> Option<(usize, f32)> {
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
unsafe fn decide_avx512(p: &ValidMatchParams, costs: &[u16], min: u16, tex: u32) -> Option<(usize, f32)> {
    if tex < p.texture_threshold {
        return None;
    }
    let best = kernels::avx512::first_index_of(costs, min);
    let rival = if p.uniqueness_ratio == 0 { u16::MAX } else { kernels::avx512::min_away_from(costs, best) };
    decide_at(p, costs, min, best, rival, tex)
}

/// [`decide`] with the best index and the best non-adjacent rival cost already known.
#[inline(always)]
fn decide_at(p: &ValidMatchParams, costs: &[u16], min: u16, best: usize, rival: u16, tex: u32) -> Option<(usize, f32)> {
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
        let (c0, c1, c2) = (costs[best - 1] as f32, min as f32, costs[best + 1] as f32);
        let denom = c0 + c2 - 2.0 * c1;
        if denom > 0.0 {
            frac = ((c0 - c2) / (2.0 * denom)).clamp(-0.5, 0.5);
        }
    }
    Some((best, frac))
}

/// `SAD(x, k) = Σ CS(x … x + 2r, k)` over pixel `x`'s interval, written to row `x` of `sad`:
/// slid from pixel `x − 1` where their intervals overlap, summed from scratch elsewhere.
#[inline(always)]
fn window_sums(g: Geometry, cs: &[u16], sad: &mut [u16], ilo: &[i32], ihi: &[i32], x: usize) {
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
fn left_right_check(p: &ValidMatchParams, g: Geometry, s: &StripeScratch, out: &mut [f32], span: Range<usize>) -> (usize, usize) {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stereo::MatchParams;

    /// A random-texture pair where the right image is the left shifted by `shift(x, y)`.
    fn shifted_pair(w: usize, h: usize, shift: impl Fn(usize, usize) -> usize) -> (Vec<u8>, Vec<u8>) {
        let mut state = 12345u32;
        let mut left = vec![0u8; w * h];
        for v in left.iter_mut() {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            *v = (state >> 24) as u8;
        }
        let mut right = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                // right(x) = left(x + d): a left pixel x appears at x − d on the right.
                let d = shift(x, y);
                right[y * w + x] = left[y * w + (x + d).min(w - 1)];
            }
        }
        (left, right)
    }

    fn params(n: u32) -> ValidMatchParams {
        MatchParams { num_disparities: n, threads: 2, ..Default::default() }.validate().unwrap()
    }

    #[test]
    fn recovers_a_constant_shift() {
        let (w, h) = (96, 40);
        let (l, r) = shifted_pair(w, h, |_, _| 7);
        let mut m = StereoMatcher::new(params(16));
        let mut out = DisparityMap::new(w, h);
        let iv = m.full_intervals(w, h, None);
        let stats = m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
        let mut good = 0;
        for y in 0..h {
            for x in 20..w - 20 {
                if out.get(x, y).is_some_and(|d| (d - 7.0).abs() < 0.5) {
                    good += 1;
                }
            }
        }
        assert!(good as f64 > 0.95 * (h * (w - 40)) as f64, "{good}");
        assert_eq!(stats.searched, w * h);
    }

    #[test]
    fn narrow_intervals_match_the_full_search_and_do_less_work() {
        let (w, h) = (120, 48);
        let (l, r) = shifted_pair(w, h, |x, _| 10 + x / 40);
        let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
        let mut m = StereoMatcher::new(params(32));
        let mut full = DisparityMap::new(w, h);
        let iv = m.full_intervals(w, h, None);
        let full_stats = m.compute(lv, rv, &iv, &mut full).unwrap();
        let mut narrow_iv = DisparityIntervals::full(w, h, 0, 31);
        for y in 0..h {
            for x in 0..w {
                let d = 10 + (x / 40) as i32;
                narrow_iv.set(x, y, Some((d - 2, d + 2)));
            }
        }
        let mut narrow = DisparityMap::new(w, h);
        let narrow_stats = m.compute(lv, rv, &narrow_iv, &mut narrow).unwrap();
        assert!(narrow_stats.evaluated * 5 < full_stats.evaluated);
        let mut agree = 0;
        let mut both = 0;
        for y in 0..h {
            for x in 16..w - 16 {
                if let (Some(a), Some(b)) = (full.get(x, y), narrow.get(x, y)) {
                    both += 1;
                    agree += ((a - b).abs() < 0.01) as usize;
                }
            }
        }
        assert!(both > (h * (w - 32)) * 8 / 10, "{both}");
        assert!(agree * 100 >= both * 99, "{agree} of {both}");
    }

    #[test]
    fn masked_pixels_are_not_matched() {
        let (w, h) = (64, 24);
        let (l, r) = shifted_pair(w, h, |_, _| 3);
        let mask: Vec<u8> = (0..w * h).map(|i| if i % w < 32 { 0 } else { 255 }).collect();
        let mut m = StereoMatcher::new(params(8));
        let iv = m.full_intervals(w, h, Some(&mask));
        let mut out = DisparityMap::new(w, h);
        let stats = m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
        assert_eq!(stats.searched, 32 * h);
        assert!((0..h).all(|y| (0..32).all(|x| out.get(x, y).is_none())));
    }

    #[test]
    fn negative_disparities() {
        let (w, h) = (80, 32);
        // The right image is the left shifted the other way: d = −6.
        let (l, r) = shifted_pair(w, h, |_, _| 6);
        let mut m = StereoMatcher::new(MatchParams { min_disparity: -12, num_disparities: 12, threads: 1, ..Default::default() }.validate().unwrap());
        let iv = m.full_intervals(w, h, None);
        let mut out = DisparityMap::new(w, h);
        // Swap roles: matching right→left sees the shift as negative.
        m.compute(GrayView::new(w, h, &r).unwrap(), GrayView::new(w, h, &l).unwrap(), &iv, &mut out).unwrap();
        let good = (0..h).flat_map(|y| (16..w - 16).map(move |x| (x, y))).filter(|&(x, y)| out.get(x, y).is_some_and(|d| (d + 6.0).abs() < 0.5)).count();
        assert!(good * 10 > h * (w - 32) * 9, "{good}");
    }

    /// Runs one stripe through the chosen code path, as `compute` does for a single thread.
    fn run_path<const AVX2: bool, const AVX512: bool>(m: &mut StereoMatcher, l: GrayView, r: GrayView, iv: &DisparityIntervals) -> Vec<f32> {
        let mut out = DisparityMap::new(l.width, l.height);
        m.compute(l, r, iv, &mut out).unwrap(); // fills the prefiltered rows
        let p = m.params.clone();
        let geo = Geometry::new(&p, l.width, l.height);
        let mut scratch = StripeScratch::default();
        let mut vals = vec![0f32; l.width * l.height];
        let input = StripeInput { p: &p, g: geo, lpf: &m.left_pf, rrev: &m.right_pf_rev, intervals: iv };
        match_stripe_impl::<AVX2, AVX512>(input, 0..l.height, &mut vals, &mut scratch);
        vals
    }

    #[test]
    fn portable_and_simd_paths_agree() {
        // Full range and narrow, shifting intervals; 16, 40 and 128 disparities.
        for n in [16u32, 40, 128] {
            let (w, h) = (160, 40);
            let (l, r) = shifted_pair(w, h, |x, y| 3 + (x + y) / 20);
            let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
            let mut m = StereoMatcher::new(MatchParams { num_disparities: n, threads: 1, speckle_window: 0, ..Default::default() }.validate().unwrap());
            let full = m.full_intervals(w, h, None);
            let mut narrow = DisparityIntervals::full(w, h, 0, n as i32 - 1);
            for y in 0..h {
                for x in 0..w {
                    let d = 3 + ((x + y) / 20) as i32;
                    narrow.set(x, y, (x % 7 != 0).then_some((d - 2 + (x % 3) as i32, d + 2)));
                }
            }
            for iv in [&full, &narrow] {
                let portable = run_path::<false, false>(&mut m, lv, rv, iv);
                #[cfg(target_arch = "x86_64")]
                {
                    let same = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| x == y || (x.is_nan() && y.is_nan()));
                    if std::is_x86_feature_detected!("avx2") {
                        assert!(same(&portable, &run_path::<true, false>(&mut m, lv, rv, iv)), "AVX2 differs, n = {n}");
                    }
                    if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw") {
                        assert!(same(&portable, &run_path::<true, true>(&mut m, lv, rv, iv)), "AVX-512 differs, n = {n}");
                    }
                }
                assert!(portable.iter().filter(|v| v.is_finite()).count() > w * h / 2, "n = {n}");
            }
        }
    }

    #[test]
    fn matching_the_crop_gives_what_matching_the_whole_image_gives() {
        let (w, h) = (200, 90);
        let (l, r) = shifted_pair(w, h, |x, y| 20 + (x + 2 * y) / 30);
        let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
        for (min_d, n) in [(0, 64), (-10, 48)] {
            let mut m = StereoMatcher::new(MatchParams { min_disparity: min_d, num_disparities: n, threads: 2, ..Default::default() }.validate().unwrap());
            // An object in the middle, with narrow intervals on part of it, and one pixel at the
            // image's border.
            let mut iv = DisparityIntervals::empty(w, h);
            for y in 30..70 {
                for x in 90..170 {
                    let d = 20 + ((x + 2 * y) / 30) as i32;
                    iv.set(x, y, Some(if x < 130 { (d - 3, d + 2) } else { (min_d, min_d + n as i32 - 1) }));
                }
            }
            let crop = Crop::of(&iv, &m.params).unwrap();
            assert!(crop.w < w && crop.h < h, "{crop:?}");
            let mut cropped = DisparityMap::new(w, h);
            let stats = m.compute(lv, rv, &iv, &mut cropped).unwrap();
            let mut whole = DisparityMap::new(w, h);
            let whole_stats = m.compute_whole(lv, rv, &iv, &mut whole);
            assert_eq!((stats.searched, stats.evaluated, stats.matched), (whole_stats.searched, whole_stats.evaluated, whole_stats.matched));
            assert!(cropped.values().iter().zip(whole.values()).all(|(a, b)| a == b || (a.is_nan() && b.is_nan())));
            assert!(stats.matched > 2000, "{}", stats.matched);
            iv.set(0, 0, Some((min_d, min_d + 5)));
            assert_eq!(Crop::of(&iv, &m.params).unwrap().x0, 0);
        }
        let mut m = StereoMatcher::new(params(16));
        let mut out = DisparityMap::new(w, h);
        assert_eq!(m.compute(lv, rv, &DisparityIntervals::empty(w, h), &mut out).unwrap().searched, 0);
        assert_eq!(out.valid_count(), 0);
    }

    #[test]
    fn size_mismatch_is_an_error() {
        let a = vec![0u8; 20 * 10];
        let b = vec![0u8; 20 * 11];
        let mut m = StereoMatcher::new(params(8));
        let iv = m.full_intervals(20, 10, None);
        let err = m
            .compute(GrayView::new(20, 10, &a).unwrap(), GrayView::new(20, 11, &b).unwrap(), &iv, &mut DisparityMap::new(20, 10))
            .unwrap_err();
        assert_eq!(err, MatchError::SizeMismatch(20, 10, 20, 11));
    }
}
