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
//! to blocks. Runs of pixels and columns sharing one range go through tight AVX2 loops. Tile
//! rows ([`TILE_W`] × [`TILE_H`] tiles) whose bands — the union of a tile's intervals — are
//! narrow take the narrow-band path (`tiles.rs`, the pixels in the vector lanes), which gives
//! the same results: narrow means at most half the range, or at most [`TILE_PATH_BAND`]
//! disparities, where that path is the faster even over the full range.
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
//! uniqueness, sub-pixel) → left–right check → (SGM's refinement) → the drop at the range's
//! ends, where the search reaches one → speckle filter over the searched pixels' rectangle.

use std::ops::Range;

use super::disparity::{range_ends_reached, DisparityIntervals, DisparityMap, GrayView, MatchStats, LR_TIMED_EVERY};
use super::kernels;
use super::params::{Method, ValidMatchParams};
use super::speckle::SpeckleFilter;
use crop::{Crop, Searched};
use rows::{column_bands, left_right_check, row_intervals, select_row, texture_row, tile_bands, update_column_sums, update_texture};
use scratch::{Geometry, StripeInput, StripeScratch, TileSums, PF_SLACK, TILE_H, TILE_W};
use source::IntervalSource;

mod crop;
mod refine;
mod rows;
mod scratch;
mod seed;
mod source;
mod tiles;
#[cfg(test)]
mod tests;

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
    #[error("semi-global matching of {width}×{height} pixels over {disparities} disparities needs {mib} MiB for its aggregated costs, which the system refused; match with `--sgm-paths 5` (`[matching] sgm_paths = 5`: one pass, memory of one row), fewer disparities, smaller images, or `--method bm`")]
    Memory { width: usize, height: usize, disparities: usize, mib: u64 },
}

impl std::convert::From<super::sgm::VolumeRefused> for MatchError {
    fn from(v: super::sgm::VolumeRefused) -> MatchError {
        MatchError::Memory { width: v.width, height: v.height, disparities: v.disparities, mib: v.bytes >> 20 }
    }
}


/// The matcher's tiles, `(width, height)` in pixels, counted from the image's top-left corner
/// (the crop and the threads' stripes start on tile boundaries): a caller that gives every
/// pixel of a tile the same interval gives the narrow-band path one band per tile.
pub const BAND_TILE: (usize, usize) = (TILE_W, TILE_H);

/// Tile rows whose tiles search at most this many disparities on average take the
/// narrow-band path even over the full range: measured with both paths on the Middlebury
/// pairs (one thread, docs/matcher.md), it was the faster up to 64 disparities (Tsukuba's 16:
/// 2.2 against 6.2 ms; Teddy's 64: 7.9 against 14.9 ms), and not reliably so at 128 (once
/// the slower, Reindeer 37.3 against 30.8 ms; once about even).
const TILE_PATH_BAND: usize = 64;

/// Rows each semi-global stripe adds above and below its own: where its vertical paths start.
const SGM_OVERLAP: usize = 32;
/// Fewest rows per semi-global stripe (smaller images run as one).
const SGM_MIN_ROWS: usize = 96;

/// A reusable matcher: holds the validated parameters and every scratch buffer.
pub struct StereoMatcher {
    params: ValidMatchParams,
    left_pf: Vec<u8>,
    right_pf_rev: Vec<u8>,
    stripes: Vec<StripeScratch>,
    speckle: SpeckleFilter,
    /// The semi-global matcher's buffers (`--method sgm`), one per stripe, for each level of
    /// a seeded search (`seed.rs`; 0: the pair as given).
    sgm_levels: Vec<Vec<super::sgm::Sgm>>,
    /// The cropped inputs and output (see [`Crop`]), reused.
    crop_left: Vec<u8>,
    crop_right: Vec<u8>,
    crop_intervals: DisparityIntervals,
    crop_out: DisparityMap,
    /// SGM's refinement pass's buffers (`refine.rs`), reused.
    refine: refine::RefineScratch,
    /// The half-size matches that seed wide searches (`seed.rs`), one per level, reused.
    seeds: Vec<seed::SeedScratch>,
    /// Whether matches at an end of the range are dropped ([`StereoMatcher::drop_range_edges`]).
    drop_range_edges: bool,
}

impl StereoMatcher {
    pub fn new(params: ValidMatchParams) -> Self {
        StereoMatcher {
            params,
            left_pf: Vec::new(),
            right_pf_rev: Vec::new(),
            stripes: Vec::new(),
            speckle: SpeckleFilter::default(),
            sgm_levels: Vec::new(),
            crop_left: Vec::new(),
            crop_right: Vec::new(),
            crop_intervals: DisparityIntervals::empty(0, 0),
            crop_out: DisparityMap::new(0, 0),
            refine: Default::default(),
            seeds: Vec::new(),
            drop_range_edges: false,
        }
    }

    /// Drops the matches at an end of the range searched, before the speckle filter
    /// ([`DisparityMap::drop_range_ends`]; counted in `MatchStats::range_edge`): the true
    /// minimum may lie beyond. The scan pipeline turns this on; off, the default, a whole
    /// pair keeps them, as OpenCV's matchers do (on Tsukuba, whose lamp lies at 14 of
    /// 0 … 15, dropping them cost 0.2 (`bm`) and 0.3 (`sgm`) points of bad2).
    pub fn drop_range_edges(mut self, on: bool) -> Self {
        self.drop_range_edges = on;
        self
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
        // rows and columns of background cost nothing. (With `sgm`, two things see the crop
        // rather than the image: the intensity term's level map where it comes from the
        // images' histograms (a call without priors), and a seeded call's half-size matches
        // within a few pixels of the crop's edge.)
        let Some(crop) = Crop::of(intervals, &self.params) else {
            out.clear();
            return Ok(MatchStats::default());
        };
        if crop.x0 == 0 && crop.y0 == 0 && crop.w == w && crop.h == h {
            return self.compute_whole(left, right, intervals, &crop.seen_from((0, 0)), out);
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
        civ.searched = None;
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
        let stats = self.compute_whole(lv, rv, &civ, &crop.seen_from((crop.x0, crop.y0)), &mut cout);
        if stats.is_ok() {
            // The crop's rows copied in, everything around them unmatched (a new map, or the
            // last crop's, is so already outside that crop: `DisparityMap::put_rect`).
            out.put_rect(crop.x0..crop.x0 + crop.w, crop.y0..crop.y0 + crop.h, cout.values());
        }
        // (The crop's buffers are kept for the next call, whether this one matched or not.)
        (self.crop_left, self.crop_right, self.crop_intervals, self.crop_out) = (lbuf, rbuf, civ, cout);
        stats
    }

    /// [`StereoMatcher::compute`] over the whole of checked inputs, whose searched pixels
    /// `searched` describes in their coordinates: the method's call (seeded from the half-size
    /// pair where wide, `seed.rs`), SGM's refinement, the drop at the range's ends, the speckle
    /// filter.
    fn compute_whole(&mut self, left: GrayView, right: GrayView, intervals: &DisparityIntervals, searched: &Searched, out: &mut DisparityMap) -> Result<MatchStats, MatchError> {
        let params = self.params.clone();
        let mut totals = seed::match_level(self, &params, 0, left, right, intervals, searched.span, out)?;
        if params.method == Method::Sgm && params.subpixel && params.sgm_refine {
            // A mask (the object segmented from the blue screen) marks a scan's view.
            let masked = intervals.lo.iter().zip(&intervals.hi).any(|(a, b)| a > b);
            self.refine_subpixel(left, right, intervals, out, masked, &mut totals);
        }
        // A pass over the map, which only a search that reaches an end of the range needs
        // (the drop's own test, asked of the call's extremes: an assisted call seldom does).
        let (first, last) = (params.min_disparity, params.max_disparity());
        let (first_end, last_end) = range_ends_reached(searched.reach.0, searched.reach.1, first, last);
        if self.drop_range_edges && (first_end || last_end) {
            totals.range_edge = out.drop_range_ends(intervals, first, last);
        }
        self.speckle_filter(out, searched, &mut totals);
        Ok(totals)
    }

    /// The correlation matcher (`bm`) with `params` over the whole of checked inputs, without
    /// the speckle filter.
    fn correlate(&mut self, params: &ValidMatchParams, left: GrayView, right: GrayView, intervals: IntervalSource, out: &mut DisparityMap) -> MatchStats {
        let (w, h) = (left.width, left.height);
        let geo = Geometry::new(params, w, h);

        let t0 = std::time::Instant::now();
        prefilter_xsobel(left, params.prefilter_cap, (geo.r, geo.r), false, &mut self.left_pf);
        prefilter_xsobel(right, params.prefilter_cap, (geo.rpad_left, geo.rpad_right), true, &mut self.right_pf_rev);
        let prefilter_ns = t0.elapsed().as_nanos() as u64;

        let threads = params.thread_count().min(h).max(1);
        self.stripes.resize_with(threads, StripeScratch::default);
        // Stripes start on tile rows (see `BAND_TILE`).
        let rows_per = h.div_ceil(threads).next_multiple_of(TILE_H);
        let input = StripeInput::new(params, geo, &self.left_pf, &self.right_pf_rev, intervals);
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
        totals
    }

    /// The speckle filter over a finished map, and the count of what is left: both over the
    /// rectangle of the call's searched pixels alone, outside which the map holds no
    /// disparity.
    fn speckle_filter(&mut self, out: &mut DisparityMap, searched: &Searched, totals: &mut MatchStats) {
        let params = &self.params;
        let (xs, ys) = (searched.xs.clone(), searched.ys.clone());
        let w = out.width;
        debug_assert!(
            out.values().chunks_exact(w).enumerate().all(|(y, row)| row.iter().enumerate().all(|(x, v)| !v.is_finite() || (xs.contains(&x) && ys.contains(&y)))),
            "a match outside the searched pixels' rectangle {xs:?} × {ys:?}"
        );
        if params.speckle_window > 0 {
            let t0 = std::time::Instant::now();
            self.speckle.apply_within(out, xs.clone(), ys.clone(), params.speckle_window as usize, params.speckle_range_px);
            totals.speckle_ns = t0.elapsed().as_nanos() as u64;
        }
        totals.matched = out.valid_count_within(xs, ys);
    }
}

/// Widest interval that says where a pixel corresponds (for the intensity term's level map):
/// 24 disparities — a seeded band, an assisted interval — and under half the range, so that a
/// narrow full range (Tsukuba's 16) is not taken for one.
fn prior_width(params: &ValidMatchParams) -> i32 {
    PRIOR_MAX_WIDTH.min(params.num_disparities as i32 / 2 - 1)
}

/// See [`prior_width`].
const PRIOR_MAX_WIDTH: i32 = 24;

/// Semi-global matching with `params`, in stripes of rows on its threads, with one of
/// `sgms`' buffers per stripe. Each stripe runs the whole method over its rows and
/// [`SGM_OVERLAP`] more above and below, and keeps its own rows: the vertical paths start that
/// far outside the rows they decide (one thread: no stripes, and exactly the single-stripe
/// map).
fn sgm_stripes(params: &ValidMatchParams, sgms: &mut Vec<super::sgm::Sgm>, left: GrayView, right: GrayView, intervals: &DisparityIntervals, out: &mut DisparityMap) -> Result<MatchStats, MatchError> {
    let (w, h) = (left.width, left.height);
    let stripes = params.thread_count().min(h / SGM_MIN_ROWS).max(1);
    // The intensity term's level map, one for the call (not per stripe): over the pixels
    // that correspond by the intervals where they are priors, else over the whole images.
    let levels = if params.sgm_ad_cap > 0 {
        super::sgm::level_map_from_prior(left, right, intervals, prior_width(params)).unwrap_or_else(|| super::sgm::level_map(left.data, right.data))
    } else {
        std::array::from_fn(|v| v as u8)
    };
    // The blocks' grid, one for the call too: stripes of one map share it.
    let shift = super::sgm::grid::shift(intervals, params.min_disparity, params.max_disparity());
    if stripes == 1 {
        sgms.resize_with(1, Default::default);
        return Ok(sgms[0].compute(params, left, right, &levels, shift, intervals, 0..h, out)?);
    }
    sgms.resize_with(stripes, Default::default);
    let rows_per = h.div_ceil(stripes);
    // Per stripe: its rows, the rows it ran over, its map and what it counted.
    type Stripe = (Range<usize>, Range<usize>, DisparityMap, Result<MatchStats, super::sgm::VolumeRefused>);
    let results: Vec<Stripe> = std::thread::scope(|scope| {
        let handles: Vec<_> = sgms
            .iter_mut()
            .enumerate()
            .map(|(i, sgm)| {
                let rows = i * rows_per..((i + 1) * rows_per).min(h);
                let ext = rows.start.saturating_sub(SGM_OVERLAP)..(rows.end + SGM_OVERLAP).min(h);
                std::thread::Builder::new()
                    .name(format!("sgm-{i}"))
                    .spawn_scoped(scope, move || {
                        let n = ext.len();
                        let (l, r) = (&left.data[ext.start * w..ext.end * w], &right.data[ext.start * w..ext.end * w]);
                        let iv = DisparityIntervals { width: w, height: n, lo: intervals.lo[ext.start * w..ext.end * w].to_vec(), hi: intervals.hi[ext.start * w..ext.end * w].to_vec(), searched: None };
                        let mut part = DisparityMap::new(w, n);
                        let keep = rows.start - ext.start..rows.end - ext.start;
                        let stats = sgm.compute(params, GrayView { width: w, height: n, data: l }, GrayView { width: w, height: n, data: r }, &levels, shift, &iv, keep, &mut part);
                        (rows, ext, part, stats)
                    })
                    .expect("spawning a matcher thread")
            })
            .collect();
        handles.into_iter().map(|h| h.join().expect("matcher thread panicked")).collect()
    });
    let mut totals = MatchStats::default();
    for (rows, ext, part, s) in results {
        let s = s?;
        let src = &part.values()[(rows.start - ext.start) * w..(rows.end - ext.start) * w];
        out.values_mut()[rows.start * w..rows.end * w].copy_from_slice(src);
        totals.searched += s.searched;
        totals.evaluated += s.evaluated;
        totals.prefilter_ns = totals.prefilter_ns.max(s.prefilter_ns);
        totals.lr_check_ns += s.lr_check_ns;
        totals.lr_candidates += s.lr_candidates;
        totals.lr_passed += s.lr_passed;
    }
    Ok(totals)
}

/// `d.round() as i32` (halves away from zero) of a finite `d` with |d| < 2²³: without a
/// libm call (the baseline x86-64 target has no rounding instruction) nor the cast's checks
/// for NaN and overflow, so that a loop of it vectorises.
#[inline(always)]
fn round_half_away_within(d: f32) -> i32 {
    debug_assert!(d.abs() < (1 << 23) as f32, "{d}");
    // SAFETY: d is finite and far inside i32 (the callers clamp it; checked in debug builds).
    let t: i32 = unsafe { d.to_int_unchecked() };
    // d − trunc(d) is exact in f32 for |d| < 2²³.
    let frac = d - t as f32;
    t + (frac >= 0.5) as i32 - (frac <= -0.5) as i32
}

/// [`prefilter_xsobel`] without padding, for the stages after the match
/// (`stereo::follow`): `img`'s rows, clipped to ±cap and offset by cap, one byte a pixel;
/// `buf` holds them.
pub(in crate::stereo) fn xsobel_rows<'a>(img: GrayView, cap: u8, buf: &'a mut Vec<u8>) -> &'a [u8] {
    prefilter_xsobel(img, cap, (0, 0), false, buf);
    &buf[PF_SLACK..PF_SLACK + img.width * img.height]
}

/// OpenCV BM's x-Sobel prefilter, clipped to ±cap and offset by cap, written with
/// `pad = (left, right)` columns of replicated padding; `reversed` stores each padded row back
/// to front so that increasing disparity walks forward in memory. The rows start
/// [`PF_SLACK`] bytes into `out`, which has as many after them.
fn prefilter_xsobel(img: GrayView, cap: u8, pad: (usize, usize), reversed: bool, out: &mut Vec<u8>) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        return unsafe { prefilter_xsobel_avx2(img, cap, pad, reversed, out) };
    }
    prefilter_xsobel_body(img, cap, pad, reversed, out)
}

/// [`prefilter_xsobel`] compiled for AVX2: its interior loop in sixteen `i16` lanes instead
/// of the baseline's eight; the same integer arithmetic, so the same bytes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn prefilter_xsobel_avx2(img: GrayView, cap: u8, pad: (usize, usize), reversed: bool, out: &mut Vec<u8>) {
    prefilter_xsobel_body(img, cap, pad, reversed, out)
}

#[inline(always)]
fn prefilter_xsobel_body(img: GrayView, cap: u8, pad: (usize, usize), reversed: bool, out: &mut Vec<u8>) {
    let (w, h) = (img.width, img.height);
    let (r, wp) = (pad.0, w + pad.0 + pad.1);
    // Slack before and after the rows: the narrow-band path loads whole chunks of columns.
    // Every byte of the rows is written below, so only the slack is cleared (clearing the
    // whole buffer first wrote every byte twice).
    out.resize(wp * h + 2 * PF_SLACK, 0);
    out[..PF_SLACK].fill(0);
    out[PF_SLACK + wp * h..].fill(0);
    let rows = &mut out[PF_SLACK..PF_SLACK + wp * h];
    let cap_i = cap as i16;
    for y in 0..h {
        let up = &img.data[y.saturating_sub(1) * w..][..w];
        let mid = &img.data[y * w..][..w];
        let down = &img.data[(y + 1).min(h - 1) * w..][..w];
        let dst = &mut rows[y * wp..][..wp];
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
    let StripeInput { p, g, lpf, rrev, intervals, slack } = input;
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
    for v in [&mut s.ilo, &mut s.ihi, &mut s.prev_ilo, &mut s.prev_ihi] {
        v.resize(w, 0);
    }
    // A tile's worth past the last pixel, never searched: the narrow-band path reads whole
    // tiles.
    for (v, none) in [(&mut s.tlo, 1), (&mut s.thi, 0)] {
        v.resize(w.next_multiple_of(TILE_W), none);
        v[w..].fill(none);
    }
    // LANES entries of slack: narrow intervals are searched as one 16-lane load.
    s.sad.resize(w * n + kernels::LANES, 0);
    s.right_min.resize(w + n + kernels::LANES, u16::MAX);
    s.best.resize(w, None);
    s.tex_col.resize(wp, 0);
    // Whole tiles: the narrow-band path reads sixteen at a time.
    s.tex_row.resize(w.next_multiple_of(TILE_W), 0);

    // The narrow-band path needs AVX2; a tile row takes it when its tiles' bands are narrow
    // on average — at most half the range, or at most TILE_PATH_BAND (so SGM's ±2
    // refinement always does). A full range over 64 disparities stays on the row path.
    let tile_path_ok = AVX2;
    if tile_path_ok {
        let tiles = w.div_ceil(TILE_W);
        s.tile_v.resize(tiles * n * tiles::tile_cols(g), 0);
        s.tile_cost.resize(tiles * n * TILE_W, 0);
        for v in [&mut s.win_k, &mut s.win_cost, &mut s.win_keep] {
            v.resize(tiles * TILE_W, 0);
        }
        s.win_frac.resize(tiles * TILE_W, 0.0);
        s.tile_sums.clear();
        s.tile_sums.resize(tiles, TileSums { lo: 1, hi: 0, row: usize::MAX });
    }
    let mut narrow = false;

    let mut stats = MatchStats::default();
    let (y0, y_end) = (rows.start, rows.end);
    // Columns whose sums (row path) were brought down to the previous row (all others hold
    // no band), and the previous row with its span; whether the row path's column sums
    // hold that row (not after a row of the narrow-band path).
    let mut live: Range<usize> = 0..0;
    let mut prev_row: Option<(usize, Range<usize>)> = None;
    let mut row_sums_valid = false;
    for y in rows {
        std::mem::swap(&mut s.ilo, &mut s.prev_ilo);
        std::mem::swap(&mut s.ihi, &mut s.prev_ihi);
        let out_row = &mut out[(y - y0) * w..][..w];
        if (y - y0) % TILE_H == 0 {
            let mean_band = tile_bands(g, intervals, y..(y + TILE_H).min(y_end), &mut s.clip_lo, &mut s.clip_hi, &mut s.clip_spans, &mut s.tile_lo, &mut s.tile_hi, &mut s.tile_px, &mut s.tile_cols);
            narrow = tile_path_ok && mean_band <= (n / 2).max(TILE_PATH_BAND) as f64;
        }
        // Only the row's searched span is worked on: rows and columns of background cost
        // (almost) nothing.
        let blocks = (!narrow).then_some((&mut s.ilo[..], &mut s.ihi[..]));
        let i = (y - y0) % TILE_H;
        let Some(span) = row_intervals(g, (&s.clip_lo[i * w..], &s.clip_hi[i * w..]), s.clip_spans[i].clone(), &mut s.tlo, &mut s.thi, blocks, &mut stats) else {
            out_row.fill(f32::NAN);
            continue;
        };
        let first_row = prev_row.as_ref().is_none_or(|(py, _)| py + 1 != y);
        if p.texture_threshold > 0 {
            update_texture(g, lpf, y, first_row, p.prefilter_cap, &mut s.tex_col);
            texture_row(g, s, span.clone());
        }
        if narrow {
            // SAFETY: `narrow` implies AVX2 (checked at dispatch); the stripe's buffers were
            // sized above and this row's intervals and tile bands computed.
            #[cfg(target_arch = "x86_64")]
            unsafe {
                tiles::tile_row(p, g, slack, y, s, span.clone())
            };
            row_sums_valid = false;
        } else {
            let cols = span.start..span.end + 2 * g.r;
            let fresh = first_row || !row_sums_valid;
            // Columns leaving the live set (all of it after a gap) lose their band.
            for xp in live.clone() {
                if fresh || !cols.contains(&xp) {
                    s.band_lo[xp] = 1;
                    s.band_hi[xp] = 0;
                }
            }
            live = cols.clone();
            // A row whose span and ranges repeat the previous row's (always so with the full
            // range) keeps the previous row's column bands.
            let same = !fresh && prev_row.as_ref().is_some_and(|(_, ps)| *ps == span) && s.ilo[span.clone()] == s.prev_ilo[span.clone()] && s.ihi[span.clone()] == s.prev_ihi[span.clone()];
            if !same {
                let sub = Geometry { w: span.len(), wp: span.len() + 2 * g.r, ..g };
                column_bands(sub, &s.ilo[span.clone()], &s.ihi[span.clone()], &mut s.need_lo[cols.clone()], &mut s.need_hi[cols.clone()], &mut s.band_tmp);
            }
            update_column_sums::<AVX2, AVX512>(g, lpf, rrev, y, fresh, cols, s);
            select_row::<AVX2, AVX512>(p, g, s, span.clone());
            row_sums_valid = true;
        }
        // (Timed only where there is a check, and on one row in LR_TIMED_EVERY: a clock read
        // costs tens of nanoseconds, twice a row.)
        let timed = p.lr_max_diff.is_some() && (y - y0) % LR_TIMED_EVERY == 0;
        let t0 = timed.then(std::time::Instant::now);
        out_row[..span.start].fill(f32::NAN);
        out_row[span.end..].fill(f32::NAN);
        let (candidates, passed) = if narrow {
            // SAFETY: as for `tile_row` above, which matched this row.
            #[cfg(target_arch = "x86_64")]
            unsafe {
                tiles::tile_check(p, g, s, out_row, span.clone())
            }
            #[cfg(not(target_arch = "x86_64"))]
            unreachable!("the narrow-band path needs AVX2")
        } else {
            left_right_check(p, g, s, out_row, span.clone())
        };
        stats.lr_candidates += candidates;
        stats.lr_passed += passed;
        prev_row = Some((y, span));
        stats.lr_check_ns += t0.map_or(0, |t0| t0.elapsed().as_nanos() as u64 * LR_TIMED_EVERY as u64);
    }
    stats
}
