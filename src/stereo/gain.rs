//! Where the two cameras see the same surface differently: the right camera's contrast
//! brought to the left's before matching, and matches at pixels a camera clipped to white
//! dropped after it ([`drop_clipped`]).
//!
//! Two cameras rarely deliver the same brightness for the same surface: their gain and
//! exposure are set apart (or automatically), and their sensors differ. The matcher's x-Sobel
//! prefilter removes an offset between them, but not a difference in gain: with the right
//! image's gradients 0.7 × the left's, every window's cost at the true disparity keeps 30 % of
//! its texture as residue, and matches go wrong where texture is faint.
//!
//! So a scan measures the ratio once, on its first pair's matches ([`matched_ratio`]: the
//! same surface points seen by both cameras), and where the cameras differ by more than
//! [`TOLERANCE`] every right image of the scan is scaled about its mean by it
//! ([`scale_contrast`]). Statistics of the whole images would not do: the two views do not
//! show the same scene (a torus seen edge-on shows one camera more of its lit side), and
//! alike cameras measured from 0.94 to 1.20 that way over the simulated lab's recordings
//! (the strongest tenth of each image's gradients).

use super::disparity::{searched_span, DisparityMap, GrayView};

/// Contrast ratios within `1 / TOLERANCE … TOLERANCE` are left as they are: a small difference
/// is not worth scaling for (the independent renderer's cameras, 7 % apart, match as well
/// either way), a large one is.
pub const TOLERANCE: f64 = 1.1;

/// The level (luma) from which a pixel counts as clipped to white: it holds no texture and no
/// longer follows the camera's gain ([`matched_ratio`] leaves it out, [`drop_clipped`] drops
/// its matches, and a scan warns where many of the object's pixels are).
pub const NEAR_WHITE: u8 = 250;

/// Pixels of a grey image at or near white (at least [`NEAR_WHITE`]).
pub fn near_white(gray: &[u8]) -> usize {
    gray.iter().filter(|&&v| v >= NEAR_WHITE).count()
}

/// Fewest corresponding pixels the ratio is measured over.
pub const MIN_PAIRS: usize = 500;

/// The cameras' contrast ratio as a scan measured it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contrast {
    /// The left image's contrast over the right's.
    pub ratio: f64,
    /// Corresponding pixels it was measured over.
    pub matched_px: usize,
}

impl Contrast {
    /// Whether the right images are scaled by the ratio: it lies beyond the tolerance.
    pub fn scales_right(&self) -> bool {
        !(1.0 / TOLERANCE..=TOLERANCE).contains(&self.ratio)
    }

    /// `report.json`'s `matching.contrast` (and `points`' JSON).
    pub fn entry(&self) -> serde_json::Value {
        serde_json::json!({"ratio": self.ratio, "matched_px": self.matched_px, "right_scaled": self.scales_right()})
    }
}

/// The left image's contrast over the right's, measured at corresponding pixels: every pixel
/// of `disparity` with a match, and the right image's level where it matched (interpolated
/// between the two nearest columns). The ratio is the slope of the least-squares line of the
/// left levels on the right ones (a gain with any offset). Pairs that touch a pixel of value
/// 0 (outside a rectified image) or one clipped to white ([`NEAR_WHITE`]) are left out. None
/// under [`MIN_PAIRS`] pairs, or where the right levels do not vary.
///
/// Measured on the pixels both cameras see of the same surface, it is the cameras' own ratio
/// within about 1 %: 0.942 for a right camera at 1.07 × the gain (0.935), 1.000 for alike
/// cameras on a torus whose two views differ most. Gradients instead (the strongest tenth of
/// each side's) came out 5 % high: one camera's image is resampled more than the other's by
/// its rectification, which blurs its edges.
pub fn matched_ratio(left: GrayView, right: GrayView, disparity: &DisparityMap) -> Option<Contrast> {
    let (w, h) = (left.width, left.height);
    let (mut n, mut sl, mut sr, mut srr, mut slr) = (0usize, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for y in 0..h {
        let (lrow, rrow) = (&left.data[y * w..][..w], &right.data[y * w..][..w]);
        for (x, &l) in lrow.iter().enumerate() {
            let Some(d) = disparity.get(x, y) else { continue };
            let xr = x as f32 - d;
            let usable = |v: u8| v != 0 && v < NEAR_WHITE;
            if !(xr >= 0.0 && xr < (w - 1) as f32) || !usable(l) {
                continue;
            }
            let (x0, f) = (xr as usize, (xr - xr.floor()) as f64);
            let (a, b) = (rrow[x0], rrow[x0 + 1]);
            if !usable(a) || !usable(b) {
                continue;
            }
            let (l, r) = (l as f64, a as f64 * (1.0 - f) + b as f64 * f);
            n += 1;
            sl += l;
            sr += r;
            srr += r * r;
            slr += l * r;
        }
    }
    let nf = n as f64;
    let var_r = nf * srr - sr * sr;
    (n >= MIN_PAIRS && var_r > 0.0).then(|| Contrast { ratio: (nf * slr - sl * sr) / var_r, matched_px: n })
}

/// Scales `img`'s contrast by `gain` about its mean (the matcher's prefilter ignores the
/// offset), rounding and clipping to 1…255; a pixel of value 0 (outside the rectified image)
/// stays 0. Returns the level [`NEAR_WHITE`] became: from it up, the scaled image is clipped
/// (clipped as delivered, or pushed to 255 by a gain over 1).
pub fn scale_contrast(img: &mut [u8], gain: f64) -> u8 {
    let (sum, n) = img.iter().filter(|&&v| v != 0).fold((0u64, 0u64), |(s, n), &v| (s + v as u64, n + 1));
    if n == 0 {
        return NEAR_WHITE;
    }
    let mean = sum as f64 / n as f64;
    let lut: Vec<u8> = (0..256).map(|v| if v == 0 { 0 } else { (mean + (v as f64 - mean) * gain).round().clamp(1.0, 255.0) as u8 }).collect();
    for v in img.iter_mut() {
        *v = lut[*v as usize];
    }
    lut[NEAR_WHITE as usize]
}

/// Drops the matches of `disparity` whose left pixel or right match (the nearest column) is
/// clipped to white: the left at [`NEAR_WHITE`] or more, the right at `right_clip` or more
/// (the level [`scale_contrast`] returned, else [`NEAR_WHITE`]). Paint clipped to white holds
/// no texture, and a specular highlight lies where the light and that camera put it, not on
/// the surface: both matchers return a disparity there that is not the surface's (`sgm` fills
/// it from its neighbours along the paths). Returns how many were dropped.
pub fn drop_clipped(disparity: &mut DisparityMap, left: &[u8], right: &[u8], right_clip: u8) -> usize {
    let (w, h) = (disparity.width, disparity.height);
    let mut dropped = 0;
    for y in 0..h {
        // Only from the row's first match to its last (most of a scan's rows are background).
        let row = &disparity.values()[y * w..(y + 1) * w];
        let Some((first, last)) = searched_span(row, row) else { continue };
        for x in first..=last {
            let Some(d) = disparity.get(x, y) else { continue };
            let xr = (x as f32 - d).round();
            let right_white = (0.0..w as f32).contains(&xr) && right[y * w + xr as usize] >= right_clip;
            if left[y * w + x] >= NEAR_WHITE || right_white {
                disparity.set(x, y, None);
                dropped += 1;
            }
        }
    }
    dropped
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured image: a mid-grey ramp with a random texture of amplitude `amp`.
    fn textured(w: usize, h: usize, amp: f64, seed: u64) -> Vec<u8> {
        let mut s = seed;
        (0..w * h)
            .map(|i| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let r = (s >> 33) as f64 / (1u64 << 31) as f64 - 0.5;
                (100.0 + 0.05 * (i % w) as f64 + amp * r).round().clamp(1.0, 255.0) as u8
            })
            .collect()
    }

    /// The right view of `left` at disparity `d` (the left image shifted left by `d`), with a
    /// gain and offset, and the disparity map that says so.
    fn right_view(left: &[u8], w: usize, d: usize, gain: f64, offset: f64) -> (Vec<u8>, DisparityMap) {
        let h = left.len() / w;
        let right: Vec<u8> = (0..w * h).map(|i| (i % w + d).min(w - 1)).zip(0..).map(|(xs, i)| (left[i / w * w + xs] as f64 * gain + offset).round().clamp(0.0, 255.0) as u8).collect();
        let mut map = DisparityMap::new(w, h);
        for y in 0..h {
            for x in d..w {
                map.values_mut()[y * w + x] = d as f32;
            }
        }
        (right, map)
    }

    /// At the pixels that correspond, the ratio recovers a gain put on the right camera,
    /// whatever offset comes with it; alike cameras measure 1. Too few matches measure
    /// nothing.
    #[test]
    fn the_matched_ratio_recovers_the_gain_between_the_cameras() {
        let (w, h) = (200, 100);
        let left = textured(w, h, 60.0, 7);
        fn view(img: &[u8]) -> GrayView<'_> {
            GrayView::new(200, img.len() / 200, img).unwrap()
        }
        for (gain, offset) in [(1.0, 0.0), (0.7, 0.0), (0.7, 20.0), (1.25, -10.0)] {
            let (right, map) = right_view(&left, w, 12, gain, offset);
            let c = matched_ratio(view(&left), view(&right), &map).unwrap();
            assert!((c.ratio * gain - 1.0).abs() < 0.02 && c.matched_px >= (w - 12) * (h - 2) * 99 / 100, "gain {gain}, offset {offset}: {c:?}");
            assert_eq!(c.scales_right(), gain != 1.0, "{c:?}");
        }
        // Read at the wrong pixels (a disparity off by 5), a gain of 0.7 is not recovered.
        let (right, mut map) = right_view(&left, w, 12, 0.7, 0.0);
        map.values_mut().iter_mut().for_each(|d| *d += 5.0);
        assert!(matched_ratio(view(&left), view(&right), &map).is_some_and(|c| (c.ratio * 0.7 - 1.0).abs() > 0.02));
        let few = DisparityMap::new(w, h);
        assert_eq!(matched_ratio(view(&left), view(&right), &few), None);
    }

    /// Matches at a pixel clipped to white in either image are dropped, the right image's
    /// clip level where it was scaled; the rest are kept.
    #[test]
    fn matches_at_clipped_pixels_are_dropped() {
        let (w, h) = (200, 100);
        let mut left = textured(w, h, 60.0, 5);
        left[10 * w + 50] = 255;
        let (mut right, mut map) = right_view(&left, w, 12, 1.0, 0.0);
        right[20 * w + 70 - 12] = 252;
        let before = (0..w * h).filter(|&i| map.get(i % w, i / w).is_some()).count();
        // The left pixel (50, 10), and (70, 20), whose match (58, 20) the right image clipped.
        assert_eq!(drop_clipped(&mut map, &left, &right, NEAR_WHITE), 2);
        assert!(map.get(50, 10).is_none() && map.get(70, 20).is_none() && map.get(51, 10).is_some());
        assert_eq!((0..w * h).filter(|&i| map.get(i % w, i / w).is_some()).count(), before - 2);
        // Scaled by 0.7 about its mean, 250 falls below 250: the level returned finds them.
        let level = scale_contrast(&mut right, 0.7);
        assert!(level < NEAR_WHITE && right[20 * w + 58] >= level && right[20 * w + 57] < level, "{level}");
    }

    /// Scaled, a darker right image gets the left's contrast back, about its mean; pixels
    /// outside the rectified image stay 0.
    #[test]
    fn scaling_brings_the_right_contrast_to_the_left_s() {
        let (w, h) = (200, 100);
        let left = textured(w, h, 60.0, 11);
        let (mut right, map) = right_view(&left, w, 0, 0.7, 0.0);
        right[..w].fill(0);
        scale_contrast(&mut right, 1.0 / 0.7);
        assert!(right[..w].iter().all(|&v| v == 0));
        fn view(img: &[u8]) -> GrayView<'_> {
            GrayView::new(200, img.len() / 200, img).unwrap()
        }
        let after = matched_ratio(view(&left), view(&right), &map).unwrap();
        assert!((after.ratio - 1.0).abs() < 0.02, "after scaling: {after:?}");
    }
}
