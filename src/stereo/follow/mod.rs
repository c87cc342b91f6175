//! A view's sub-pixel disparities refined by a window that follows the surface.
//!
//! Block matching reports, at each pixel, the disparity that best shifts its whole window:
//! the mean of the true disparities under it, weighted by where the texture's gradients
//! lie. On a curved surface that mean falls short of the centre's disparity where the
//! surface bulges towards the camera (by σ²/2 × the map's Laplacian, σ² the window's
//! variance), and on a slanted one it moves with the texture. These errors move with the
//! object, so the fusion of many views keeps them (docs/meshing.md, "Where the fused
//! surface's error comes from").
//!
//! Here every matched pixel is correlated once more, with the right window warped by the
//! map itself: each pixel q of the window is compared with the right image at
//! `x_q − S(q) − δ`, `S` the map smoothed, for a few residual shifts δ shared by the window
//! (its matched pixels only: the background and holes are not the surface).
//! The residual's minimum (an equiangular fit through the three samples around it) added to
//! `S` at the centre is the new disparity. The window's mean of the residual is then the
//! mean of `d − S`, small and smooth wherever `S` follows the surface, so neither the
//! curvature nor the texture's weighting biases it (docs/matcher.md, "The window that
//! follows the surface").
//!
//! The windows compare x-derivatives (the matcher's x-Sobel prefilter), and the warp
//! stretches the right image by `1 − ∂S/∂x` along the row: where the surface slants away from
//! the right camera its texture is compressed there, and its derivative larger by that factor
//! and taken over more of the texture. So the right image is warped first and differentiated
//! after, in the left image's columns and rows. Beside an unmatched pixel, whose warp is not
//! known, the right image's own prefiltered value at the warped place is taken, scaled by
//! `1 − ∂S/∂x` (the chain rule of `L(x) = R(x − S(x))`; docs/matcher.md, "The right image's
//! derivative, taken where the left's is").
//!
//! `S` is a plane fitted to the map's matched pixels around each pixel, not their mean: a
//! mean taken near the silhouette or a hole reaches into one side only and lags the surface
//! by its slope times that offset, where the surface turns away fastest. And where the
//! object's silhouette is known, the pixels within [`SILHOUETTE_PX`] of it lend the windows
//! no samples: their prefiltered values hold the edge against the background, which the
//! right camera sees on another part of the surface (docs/matcher.md, "The window near the
//! silhouette").
//!
//! Pixels with less than half their window matched (at the edge of large holes) keep their
//! value, as do those whose residual's minimum lies at an end of the shifts searched,
//! and those the refinement would move by more than [`MAX_MOVE_PX`].

mod plane;
mod rim;

use std::borrow::Cow;

use super::disparity::{searched_span, DisparityMap, GrayView};
use super::matcher::xsobel_rows;
use plane::plane_fit;
pub use rim::{extrapolate_rim, RimStats, RIM_FIT_RADIUS, RIM_PROFILE_PX, RIM_SAMPLE_PX};

/// Side of the warped window, pixels. 11 while the window followed the map's mean; with the
/// fitted plane and the silhouette's edge left out, 13 gave models 1–2 % closer and views
/// 6–7 % closer over 15 recordings (15 and 17 closer views still, but models further on the
/// clean ones; docs/matcher.md, "The window near the silhouette").
pub const FOLLOW_BLOCK: usize = 13;

/// Half-side of the square over which the map is fitted by a plane at each pixel (σ ≈ 3.7 px,
/// the width of the three box passes whose mean it replaced), pixels. Measured over 15
/// recordings (docs/matcher.md, "The window near the silhouette"): 5 and 7 were within 2 %
/// of it on the models, 4 and 10 further.
pub const FOLLOW_FIT_RADIUS: usize = 6;

/// How far inside the object's silhouette a pixel must lie for the windows to compare it,
/// pixels (a square neighbourhood, as [`crate::segment::inside_rim`] erodes): the x-Sobel
/// prefilter, the right image's interpolation and the rendering's or the optics' blur carry
/// the silhouette's edge that far in. Measured (docs/matcher.md): 2 and 4 gave models 1–3 %
/// further than 3.
pub const SILHOUETTE_PX: usize = 3;

/// The least spread of a fitted square's matched pixels along x and along y (their variance,
/// px²) for a plane to be fitted there; where they lie nearly on a line, the plane's tilt
/// across it is not measured and their mean is taken instead.
const MIN_SPREAD_PX2: f64 = 1.0;

/// The least share of a pixel's window that must be matched for it to be refined: where
/// less is, the smoothed map under the window is mostly extrapolated. Measured on realistic
/// recordings (docs/matcher.md, "The window that follows the surface"): the whole window
/// (1) left 45 % of `bm`'s matched pixels as they were, and half of it gained most of what
/// any share down to none did.
const MIN_MATCHED_SHARE: f32 = 0.5;

/// The residual shifts tried, pixels: a smoothed map lies within a pixel of the surface
/// almost everywhere its window is matched.
const SHIFTS: [f32; 5] = [-1.0, -0.5, 0.0, 0.5, 1.0];

/// The most a pixel's value is moved, pixels: further, the smoothed map it was refined
/// around did not follow the surface there.
const MAX_MOVE_PX: f32 = 1.0;

/// The bounds of the warp's stretch `1 − ∂S/∂x` that scales the right image's derivative:
/// beyond them the surface is seen at a grazing angle by one camera (or folds out of its
/// view), where a plane fitted across the fold does not measure the stretch.
const STRETCH_BOUNDS: (f32, f32) = (0.25, 4.0);

/// The x-Sobel prefilter's clip, grey levels (twice the matcher's default cap: the
/// refinement's interpolated samples keep more of the gradients' size). The right image's
/// samples are clipped to it after the warp's stretch has scaled them.
const CAP: u8 = 62;

/// The right image's prefilter's own clip, grey levels (the widest its bytes hold): its
/// samples are clipped to [`CAP`] only once scaled by the warp's stretch, so that a gradient
/// the stretch makes smaller is not one the clip made smaller first.
const RIGHT_CAP: u8 = 127;

/// What the refinement looked at, and what it moved.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FollowStats {
    /// Matched pixels with at least half their window matched (the ones looked at).
    pub looked: usize,
    /// Of those, the ones given a new value.
    pub refined: usize,
}

/// Refines `disp` in place (see the module's documentation). `left`, `right`: the rectified
/// grey images the map was matched on, `disp.width × disp.height` each. `object`: where the
/// object's silhouette is known, its mask of the same size (255 the object, 0 the
/// background, as `segment` gives it): the windows compare only the pixels at least
/// [`SILHOUETTE_PX`] inside it, though every matched pixel is refined. `None`: every matched
/// pixel is compared.
pub fn refine_following(left: &[u8], right: &[u8], object: Option<&[u8]>, disp: &mut DisparityMap) -> FollowStats {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        return unsafe { refine_avx2(left, right, object, disp) };
    }
    refine(left, right, object, disp, false)
}

/// [`refine_following`] compiled for AVX2: its passes over the region in eight lanes instead
/// of the baseline's four, the right rows warped by [`avx2::warp_row`]; the same operations in
/// the same order (no fused multiply-add), so the same disparities.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn refine_avx2(left: &[u8], right: &[u8], object: Option<&[u8]>, disp: &mut DisparityMap) -> FollowStats {
    refine(left, right, object, disp, true)
}

/// The body of [`refine_following`]; `simd`: the CPU has AVX2 (the residual costs in eight
/// lanes).
#[inline(always)]
fn refine(left: &[u8], right: &[u8], object: Option<&[u8]>, disp: &mut DisparityMap, simd: bool) -> FollowStats {
    let (w, h) = (disp.width, disp.height);
    assert!(left.len() == w * h && right.len() == w * h, "images of the map's size");
    assert!(object.is_none_or(|m| m.len() == w * h), "a silhouette of the map's size");
    let half = FOLLOW_BLOCK / 2;
    let Some((x0, x1, y0, y1)) = bounds(disp.values(), w, h) else { return FollowStats::default() };
    // The region worked on: the matched pixels' box and a window's half around it.
    let (rx0, rx1) = (x0.saturating_sub(half), (x1 + half + 1).min(w));
    let (ry0, ry1) = (y0.saturating_sub(half), (y1 + half + 1).min(h));
    let (rw, rh) = (rx1 - rx0, ry1 - ry0);
    if rw < FOLLOW_BLOCK || rh < FOLLOW_BLOCK {
        return FollowStats::default();
    }
    let region = |y: usize| (y + ry0) * w + rx0..(y + ry0) * w + rx1;
    // The map over the region (NaN unmatched), and the plane fitted around each pixel.
    let mut d = Vec::with_capacity(rw * rh);
    for y in 0..rh {
        d.extend_from_slice(&disp.values()[region(y)]);
    }
    let smooth = plane_fit(&d, rw, rh, FOLLOW_FIT_RADIUS, MIN_SPREAD_PX2);
    // A pixel is looked at where at least MIN_MATCHED_SHARE of its window is matched.
    let mut count: Vec<f32> = d.iter().map(|v| if v.is_nan() { 0.0 } else { 1.0 }).collect();
    let mut tmp = vec![0f32; rw * rh];
    box_sum(&mut count, &mut tmp, rw, rh, half);
    // The pixels the windows compare: the matched ones, less the silhouette's edge (the
    // object's mask eroded over the region only; an object that the region's edge cuts keeps
    // its pixels there, as it goes on beyond).
    let sampled: Cow<[f32]> = match object {
        Some(m) => {
            let crop: Vec<u8> = (0..rh).flat_map(|y| &m[region(y)]).copied().collect();
            let inside = crate::segment::inside_rim(&crop, rw, rh, SILHOUETTE_PX);
            Cow::Owned(d.iter().zip(&inside).map(|(&v, &k)| if k != 0 { v } else { f32::NAN }).collect())
        }
        None => Cow::Borrowed(&d),
    };
    let least = (FOLLOW_BLOCK * FOLLOW_BLOCK) as f32 * MIN_MATCHED_SHARE - 0.5;
    // The prefiltered images: the left over the region, the right over the region's rows
    // and the columns its shifted windows reach.
    // (Comparisons with NaN are false: the unmatched pixels leave both as they are.)
    let (dlo, dhi) = d.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| (if v < a { v } else { a }, if v > b { v } else { b }));
    let c0 = ((rx0 as f32 - dhi - 3.0).floor().max(0.0) as usize).min(w - 2);
    let c1 = ((rx1 as f32 - dlo + 3.0).ceil().max(0.0) as usize).clamp(c0 + 2, w);
    let lpf = prefilter(left, (w, h), ry0..ry1, rx0..rx1, CAP);
    let rpf = prefilter(right, (w, h), ry0..ry1, c0..c1, RIGHT_CAP);
    let raw: Vec<f32> = (ry0..ry1).flat_map(|y| right[y * w + c0..y * w + c1].iter().map(|&v| v as f32)).collect();
    let cw = c1 - c0;
    // The columns a shifted sample may fall between: the span's pixels, as offsets into it.
    let (first, last) = (c0 as f32, (c1 - 2) as f32);
    // Per shift, each pixel's absolute difference with the right image at its warped
    // position, then summed over its window. Where the prefilter's kernel around a pixel is
    // on the surface, the right image is warped first and differentiated after, in the left
    // image's columns and rows: the prefilter's own kernel over the same texture as the
    // left's. Beside an unmatched pixel, and on the region's edge, the right image's
    // prefiltered value at the warped place, scaled by the stretch.
    let mut costs = vec![0f32; SHIFTS.len() * rw * rh];
    let mut warped = vec![0f32; rw * rh];
    for (k, &shift) in SHIFTS.iter().enumerate() {
        for y in 0..rh {
            let row = y * rw..(y + 1) * rw;
            let input = WarpRow { x0: rx0, smooth: &smooth[row.clone()], right: &raw[y * cw..(y + 1) * cw], first, last };
            #[cfg(target_arch = "x86_64")]
            let done = if simd {
                // SAFETY: `simd` is only set by `refine_avx2`, on a CPU with AVX2.
                unsafe { avx2::warp_row(&input, shift, &mut warped[row.clone()]) }
            } else {
                0
            };
            #[cfg(not(target_arch = "x86_64"))]
            let done = 0;
            warp_row(&input, shift, &mut warped[row], done);
        }
        let plane = &mut costs[k * rw * rh..(k + 1) * rw * rh];
        derivative_costs(&warped, &lpf, &sampled, plane, rw);
        for y in 0..rh {
            let row = y * rw..(y + 1) * rw;
            let input = CostRow { x0: rx0, smooth: &smooth[row.clone()], left: &lpf[row.clone()], right: &rpf[y * cw..(y + 1) * cw], first, last };
            stretched_costs(&input, shift, &mut plane[row]);
        }
    }
    for cost in costs.chunks_mut(rw * rh) {
        box_sum(cost, &mut tmp, rw, rh, half);
    }
    let mut stats = FollowStats::default();
    let vals = disp.values_mut();
    for y in 0..rh {
        let row = y * rw..(y + 1) * rw;
        let cost: [&[f32]; 5] = std::array::from_fn(|k| &costs[k * rw * rh..][row.clone()]);
        let (looked, refined) = fold_row(cost, &smooth[row.clone()], &d[row.clone()], &count[row.clone()], least, &mut vals[region(y)]);
        stats.looked += looked;
        stats.refined += refined;
    }
    stats
}

/// One row's new values, written to `out` (the map's row over the region; `own` the same
/// values): at each matched pixel with at least `least` of its window matched, the least of
/// its five summed `cost`s, fitted between its neighbours and added to `smooth`, where that
/// least is not at an end of the shifts and moves the pixel by at most [`MAX_MOVE_PX`].
/// Returns the pixels looked at and those given a new value. Branch-free, so that it
/// vectorises.
#[inline(always)]
fn fold_row(cost: [&[f32]; 5], smooth: &[f32], own: &[f32], count: &[f32], least: f32, out: &mut [f32]) -> (usize, usize) {
    let n = out.len();
    let (cost, smooth, own, count) = (cost.map(|c| &c[..n]), &smooth[..n], &own[..n], &count[..n]);
    let step = SHIFTS[1] - SHIFTS[0];
    let (mut looked, mut refined) = (0u32, 0u32);
    for x in 0..n {
        let c: [f32; 5] = std::array::from_fn(|k| cost[k][x]);
        // The first least cost (its shift), and the costs either side of it.
        let (mut shift, mut least_cost, mut before, mut after) = (SHIFTS[0], c[0], c[0], c[1]);
        for k in 1..5 {
            let lower = c[k] < least_cost;
            shift = if lower { SHIFTS[k] } else { shift };
            least_cost = if lower { c[k] } else { least_cost };
            before = if lower { c[k - 1] } else { before };
            after = if lower { c[(k + 1).min(4)] } else { after };
        }
        let inside = shift != SHIFTS[0] && shift != SHIFTS[4];
        let look = !own[x].is_nan() && count[x] >= least;
        let new = smooth[x] + shift + step * equiangular(before, least_cost, after);
        // Across a depth edge the smoothed map lies between the two sides, and the
        // window's residual measures neither: such a pixel keeps its own value.
        let take = look && inside && (new - own[x]).abs() <= MAX_MOVE_PX;
        out[x] = if take { new } else { own[x] };
        looked += look as u32;
        refined += take as u32;
    }
    (looked as usize, refined as usize)
}

/// The equiangular (V-shaped) fit's offset from the middle of three costs whose middle is
/// the least, in steps: within ±0.5.
#[inline(always)]
fn equiangular(c0: f32, c1: f32, c2: f32) -> f32 {
    let rise = (c0 - c1).max(c2 - c1);
    let offset = (0.5 * (c0 - c2) / rise).clamp(-0.5, 0.5);
    if rise > 0.0 {
        offset
    } else {
        0.0
    }
}

/// One row of the region, as the stretched samples read it.
struct CostRow<'a> {
    /// The image column of the row's first pixel.
    x0: usize,
    /// The smoothed map over the region's columns (its slope gives the warp's stretch).
    smooth: &'a [f32],
    /// The left image's prefiltered values over the region's columns.
    left: &'a [f32],
    /// The right image's prefiltered values over the columns the shifted windows reach,
    /// `first` the image column of its first; `last` that of the last a sample may start at
    /// (its second pixel is the one after).
    right: &'a [f32],
    first: f32,
    last: f32,
}

/// The costs [`derivative_costs`] left to it (NaN) in one row of a shift's plane (`out`): the
/// absolute difference of the left image's prefiltered value with the right image's at
/// `x − S − shift`, linearly between its two pixels, clamped to its span, times the warp's
/// stretch (the right image's derivative as the left sees it) and clipped to ±[`CAP`]; 0
/// where `S` is NaN.
#[inline(always)]
fn stretched_costs(row: &CostRow, shift: f32, out: &mut [f32]) {
    for (x, o) in out.iter_mut().enumerate() {
        if !o.is_nan() {
            continue;
        }
        let xr = (row.x0 + x) as f32 - row.smooth[x] - shift;
        let v = (right_at(row.right, row.first, row.last, xr) * stretch_at(row.smooth, x)).max(-(CAP as f32)).min(CAP as f32);
        *o = if !xr.is_nan() { (row.left[x] - v).abs() } else { 0.0 };
    }
}

/// A row of the right image (`right`, its first column `first`, `last` the last a pair of
/// samples may start at) at column `xr`: linearly between its two pixels, `xr` clamped to
/// the span (the first column where `xr` is NaN).
#[inline(always)]
fn right_at(right: &[f32], first: f32, last: f32, xr: f32) -> f32 {
    let xr = if xr.is_nan() { first } else { xr.max(first).min(last + 0.999) };
    // SAFETY: `xr − first` is finite and within 0 … the span's length − 1 (clamped above), so
    // it fits an i32.
    let i = unsafe { (xr - first).to_int_unchecked::<i32>() } as usize;
    let f = xr - first - i as f32;
    let pair = &right[i..i + 2];
    pair[0] + f * (pair[1] - pair[0])
}

/// One row of the region, as the warp reads it: the smoothed map and the right image's
/// grey levels over the columns the shifted windows reach (as in [`CostRow`]).
struct WarpRow<'a> {
    x0: usize,
    smooth: &'a [f32],
    right: &'a [f32],
    first: f32,
    last: f32,
}

/// The right image at `x − S − shift` for each pixel of a row from pixel `from` on,
/// linearly between its two pixels and clamped to its span; NaN where `S` is.
#[inline(always)]
fn warp_row(row: &WarpRow, shift: f32, out: &mut [f32], from: usize) {
    for x in from..row.smooth.len() {
        let xr = (row.x0 + x) as f32 - row.smooth[x] - shift;
        let v = right_at(row.right, row.first, row.last, xr);
        out[x] = if xr.is_nan() { f32::NAN } else { v };
    }
}

/// A shift's costs (`cost`, the region `w` wide): the absolute difference of the left
/// image's prefiltered value with the prefilter of the `warped` right image at every sampled
/// pixel whose kernel's six pixels (the columns either side, three rows) are warped; 0 at the
/// pixels not sampled; NaN, for [`stretched_costs`], at the other sampled pixels (beside an
/// unwarped one, or on the region's edge).
/// The prefilter: the x-Sobel, clipped to ±[`CAP`]. Branch-free inside the region, so that it
/// vectorises.
#[inline(always)]
fn derivative_costs(warped: &[f32], left: &[f32], sampled: &[f32], cost: &mut [f32], w: usize) {
    let h = cost.len() / w;
    let cap = CAP as f32;
    let edge = |s: f32| if s.is_nan() { 0.0 } else { f32::NAN };
    for y in 0..h {
        let (s, c) = (&sampled[y * w..(y + 1) * w], &mut cost[y * w..(y + 1) * w]);
        if y == 0 || y + 1 == h || w < 3 {
            for (c, &s) in c.iter_mut().zip(s) {
                *c = edge(s);
            }
            continue;
        }
        let (up, mid, down) = (&warped[(y - 1) * w..y * w], &warped[y * w..(y + 1) * w], &warped[(y + 1) * w..(y + 2) * w]);
        let l = &left[y * w..(y + 1) * w];
        for x in 1..w - 1 {
            let g = 2.0 * (mid[x + 1] - mid[x - 1]) + (up[x + 1] - up[x - 1]) + (down[x + 1] - down[x - 1]);
            let d = (l[x] - g.max(-cap).min(cap)).abs();
            let d = if g.is_nan() { f32::NAN } else { d };
            c[x] = if s[x].is_nan() { 0.0 } else { d };
        }
        (c[0], c[w - 1]) = (edge(s[0]), edge(s[w - 1]));
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::WarpRow;

    /// [`super::warp_row`] eight pixels at a time; the same operations in the same order, so
    /// the same values. Returns the first pixel it left to the portable loop.
    ///
    /// SAFETY: the CPU has AVX2; `out` is as long as `row.smooth`, and `row.right` holds at
    /// least two values.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn warp_row(row: &WarpRow, shift: f32, out: &mut [f32]) -> usize {
        let n = row.smooth.len();
        assert!(out.len() == n && row.right.len() >= 2);
        let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let first = _mm256_set1_ps(row.first);
        let high = _mm256_set1_ps(row.last + 0.999);
        // The last index a pair of samples may start at: the clamp keeps every index there
        // already; this keeps the loads inside the row whatever the rounding.
        let top = _mm256_set1_epi32(row.right.len() as i32 - 2);
        let nan = _mm256_set1_ps(f32::NAN);
        let shift = _mm256_set1_ps(shift);
        let right = row.right.as_ptr();
        let mut x = 0;
        while x + 8 <= n {
            let s = _mm256_loadu_ps(row.smooth.as_ptr().add(x));
            let at = _mm256_sub_ps(_mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32((row.x0 + x) as i32), lane)), s);
            let (v, near) = right_at(right, (first, high, top), _mm256_sub_ps(at, shift));
            _mm256_storeu_ps(out.as_mut_ptr().add(x), _mm256_blendv_ps(nan, v, near));
            x += 8;
        }
        x
    }

    /// [`super::right_at`] in eight lanes: the right row `right` at the columns `xr`, with
    /// `(first, high, top)` the span's first column, its last + 0.999 and the last index a
    /// pair may start at; and the lanes whose `xr` is not NaN.
    ///
    /// SAFETY: the CPU has AVX2; `right` holds `top + 2` values.
    #[inline(always)]
    unsafe fn right_at(right: *const f32, (first, high, top): (__m256, __m256, __m256i), xr: __m256) -> (__m256, __m256) {
        let near = _mm256_cmp_ps::<_CMP_ORD_Q>(xr, xr);
        let xr = _mm256_blendv_ps(first, _mm256_min_ps(_mm256_max_ps(xr, first), high), near);
        let t = _mm256_sub_ps(xr, first);
        let i = _mm256_cvttps_epi32(t);
        let f = _mm256_sub_ps(t, _mm256_cvtepi32_ps(i));
        let i = _mm256_min_epi32(i, top);
        let (a, b) = pairs(right, i);
        (_mm256_add_ps(a, _mm256_mul_ps(f, _mm256_sub_ps(b, a))), near)
    }

    /// The values at the eight indices `i` of `right` and the ones after them: one 64-bit
    /// load a pixel, put into lanes (as `stereo::remap` does: fewer loads than two gathers,
    /// which are slow on some cores).
    ///
    /// SAFETY: every index and the one after it lie in the slice `right` starts.
    #[inline(always)]
    unsafe fn pairs(right: *const f32, i: __m256i) -> (__m256, __m256) {
        let mut o = [0i32; 8];
        _mm256_storeu_si256(o.as_mut_ptr() as *mut __m256i, i);
        let at = |k: usize| (right.add(o[k] as usize) as *const i64).read_unaligned();
        let lo = _mm256_castsi256_ps(_mm256_setr_epi64x(at(0), at(1), at(2), at(3)));
        let hi = _mm256_castsi256_ps(_mm256_setr_epi64x(at(4), at(5), at(6), at(7)));
        // Lane by lane the shuffles give pixels 0, 1, 4, 5 | 2, 3, 6, 7; the permute puts
        // the 64-bit halves back in order.
        let order = |v: __m256| _mm256_castsi256_ps(_mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_castps_si256(v)));
        (order(_mm256_shuffle_ps::<0b10_00_10_00>(lo, hi)), order(_mm256_shuffle_ps::<0b11_01_11_01>(lo, hi)))
    }
}

/// The warp's stretch `1 − ∂S/∂x` at pixel `x` of a row of the smoothed map `S`: its slope by
/// the central difference, one-sided where a neighbour is NaN (the row's ends included), none
/// where both are; within [`STRETCH_BOUNDS`]; 1 where `S` itself is NaN. Taken only for the
/// pixels [`stretched_costs`] fills, a few beside unmatched ones.
#[inline(always)]
fn stretch_at(s: &[f32], x: usize) -> f32 {
    let c = s[x];
    let before = if x > 0 { s[x - 1] } else { f32::NAN };
    let after = s.get(x + 1).copied().unwrap_or(f32::NAN);
    let slope = match (before.is_nan(), after.is_nan()) {
        (false, false) => 0.5 * (after - before),
        (true, false) => after - c,
        (false, true) => c - before,
        (true, true) => 0.0,
    };
    if c.is_nan() { 1.0 } else { (1.0 - slope).max(STRETCH_BOUNDS.0).min(STRETCH_BOUNDS.1) }
}

/// The box of the matched pixels: first and last column and row.
fn bounds(v: &[f32], w: usize, h: usize) -> Option<(usize, usize, usize, usize)> {
    let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
    for y in 0..h {
        let row = &v[y * w..(y + 1) * w];
        // (`d <= d` fails for NaN alone: the row's first and last matched pixels.)
        let Some((first, last)) = searched_span(row, row) else { continue };
        (x0, x1, y0, y1) = (x0.min(first), x1.max(last), y0.min(y), y);
    }
    (y0 != usize::MAX).then_some((x0, x1, y0, y1))
}

/// The matcher's x-Sobel prefilter of `img` (`w` wide, `h` high; clipped to ±`cap`) over
/// `rows` and `columns`, as signed values.
#[inline(always)]
fn prefilter(img: &[u8], (w, h): (usize, usize), rows: std::ops::Range<usize>, columns: std::ops::Range<usize>, cap: u8) -> Vec<f32> {
    let mut buf = Vec::new();
    let view = GrayView::new(w, h, img).expect("an image of the map's size");
    let filtered = xsobel_rows(view, cap, &mut buf);
    let mut out = Vec::with_capacity(rows.len() * columns.len());
    for y in rows {
        out.extend(filtered[y * w + columns.start..y * w + columns.end].iter().map(|&v| v as f32 - cap as f32));
    }
    out
}

/// Replaces `a` (`w × h`) by its sums over the (2r + 1)² square around each pixel, the part
/// of it inside the image; `tmp` is scratch of the same size.
#[inline(always)]
fn box_sum(a: &mut [f32], tmp: &mut [f32], w: usize, h: usize, r: usize) {
    // Along the rows: the square's 2r + 1 columns added one shifted row at a time, so that
    // it vectorises (a running sum waits on each add); the ends clipped to the row.
    for y in 0..h {
        let (row, out) = (&a[y * w..(y + 1) * w], &mut tmp[y * w..(y + 1) * w]);
        if w <= 2 * r {
            for (x, o) in out.iter_mut().enumerate() {
                *o = row[x.saturating_sub(r)..(x + r + 1).min(w)].iter().sum();
            }
            continue;
        }
        let inner = &mut out[r..w - r];
        inner.copy_from_slice(&row[..w - 2 * r]);
        for k in 1..=2 * r {
            for (o, v) in inner.iter_mut().zip(&row[k..k + w - 2 * r]) {
                *o += v;
            }
        }
        for x in (0..r).chain(w - r..w) {
            out[x] = row[x.saturating_sub(r)..(x + r + 1).min(w)].iter().sum();
        }
    }
    // Down the columns, whole rows at a time (so that it vectorises).
    let mut s = vec![0f32; w];
    for y in 0..(r + 1).min(h) {
        for (acc, v) in s.iter_mut().zip(&tmp[y * w..(y + 1) * w]) {
            *acc += v;
        }
    }
    for y in 0..h {
        a[y * w..(y + 1) * w].copy_from_slice(&s);
        if y + r + 1 < h {
            for (acc, v) in s.iter_mut().zip(&tmp[(y + r + 1) * w..(y + r + 2) * w]) {
                *acc += v;
            }
        }
        if y >= r {
            for (acc, v) in s.iter_mut().zip(&tmp[(y - r) * w..(y - r + 1) * w]) {
                *acc -= v;
            }
        }
    }
}

#[cfg(test)]
mod tests;
