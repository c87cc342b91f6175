//! The disparity range fitted to the object: `replay`, `demo` and `points` where no range is
//! given, the daemon's scans with `[matching] fit_range`.
//!
//! The default range (0 … 127, or its mirror on a rig with negative disparities) holds the
//! simulated lab's objects. Another lab's rig — cameras moved in, a wider baseline, a larger
//! sensor — can put the object beyond it; every match then sits at the range's end and is
//! dropped, and the scan comes out empty or wrong. So the first frame is probed over a wide
//! range (half the image's width) with the correlation matcher, and where the object's
//! disparities do not lie inside the range the scan would search, the range is widened to
//! hold them, with room for the object to come nearer as it turns. Where they do, nothing
//! changes: the range stays the one given or the default.
//!
//! The probe's matches also measure the cameras' contrast ratio ([`crate::stereo::gain`]):
//! where the two cameras' gains differ by more than 10 %, the scan scales every right image
//! by it. That is done whether or not the range is fitted.

use super::{FrameError, Pipeline, PipelineError, PipelineOptions, Prepared, RectifiedPlate};
use crate::calib::StereoCalib;
use crate::hw::StereoFrame;
use crate::stereo::gain::{self, Contrast};
use crate::stereo::{DisparityMap, GrayView, MatchError, MatchParams, Method, StereoMatcher};

/// The most disparities probed (half the image's width, at most this).
const MAX_PROBE: u32 = 512;

/// Matched object pixels needed to tell where the object lies.
pub const MIN_MATCHED: usize = 500;

/// Share of the object's matched pixels left out at each end of its span (outliers).
const TAIL: f64 = 0.01;

/// What the probe of a frame found.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeFit {
    /// The object's disparities (its 1st and 99th percentile, signed as the matcher's).
    pub object: (f32, f32),
    /// Its matched pixels.
    pub matched: usize,
    /// The range to search, `(min_disparity, num_disparities)`, where the pipeline's does
    /// not hold the object; None where it does.
    pub widened: Option<(i32, u32)>,
}

/// The range that holds disparities of magnitude `lo … hi` on a rig of disparity `sign`:
/// from 16 short of `lo` (not past 0: nothing lies beyond infinity) to `hi` plus the span
/// again, at least 16 (a part of the object that turns towards the camera comes nearer than
/// the first view's nearest), in whole blocks of 16, as `(min_disparity, num_disparities)`.
pub fn range_holding(lo: f32, hi: f32, sign: i32) -> (i32, u32) {
    let far = ((lo - 16.0).max(0.0) / 16.0).floor() as i32 * 16;
    let near = (hi + (hi - lo).max(16.0)).ceil() as i32;
    let n = ((near - far + 1 + 15) / 16 * 16) as u32;
    if sign < 0 {
        (-(far + n as i32 - 1), n)
    } else {
        (far, n)
    }
}

/// Probes `frame` (prepared by `pipe`) over a wide range: where its object lies, and the
/// range to search instead of `pipe`'s where that one does not hold it; and the cameras'
/// contrast ratio at the pixels matched. None where too few of the object's pixels match to
/// tell.
pub fn probe(pipe: &Pipeline, frame: &Prepared) -> Result<Option<(RangeFit, Option<Contrast>)>, PipelineError> {
    let (w, h) = pipe.size;
    let sign = pipe.rect.disparity_sign;
    let current = pipe.matcher().params();
    let n = (w as u32 / 2 / 16 * 16).clamp(16, MAX_PROBE);
    let params = MatchParams { num_disparities: n, min_disparity: if sign < 0 { -(n as i32 - 1) } else { 0 }, threads: current.threads, ..MatchParams::for_method(Method::Bm) }.validate()?;
    let mut matcher = StereoMatcher::new(params).drop_range_edges(true);
    let lv = GrayView::new(w, h, &frame.left_gray).ok_or(MatchError::Buffer(frame.left_gray.len(), w * h))?;
    let rv = GrayView::new(w, h, &frame.right_gray).ok_or(MatchError::Buffer(frame.right_gray.len(), w * h))?;
    let mut out = DisparityMap::new(w, h);
    matcher.compute(lv, rv, &matcher.full_intervals(w, h, frame.mask.as_deref()), &mut out)?;
    let contrast = gain::matched_ratio(lv, rv, &out);
    let mut magnitudes: Vec<f32> = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).filter_map(|(x, y)| out.get(x, y)).map(|d| d * sign as f32).collect();
    if magnitudes.len() < MIN_MATCHED {
        return Ok(None);
    }
    magnitudes.sort_unstable_by(f32::total_cmp);
    let at = |q: f64| magnitudes[((magnitudes.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(TAIL), at(1.0 - TAIL));
    // The magnitudes the pipeline searches, and whether they hold the object (a pixel short
    // of each end: a match at the end is dropped).
    let (a, b) = (current.min_disparity * sign, (current.min_disparity + current.num_disparities as i32 - 1) * sign);
    let (first, last) = (a.min(b) as f32, a.max(b) as f32);
    let holds = lo >= first + 1.0 && hi <= last - 1.0;
    let object = if sign < 0 { (-hi, -lo) } else { (lo, hi) };
    Ok(Some((RangeFit { object, matched: magnitudes.len(), widened: (!holds).then(|| range_holding(lo, hi, sign)) }, contrast)))
}

/// A scan's pipeline fitted to its first frame ([`fit`]).
pub struct Fitted {
    /// The pipeline to scan with, and the options it was built from.
    pub pipe: Pipeline,
    pub opts: PipelineOptions,
    /// Where the probe found the object, where the range is fitted (`opts.fit_range`).
    pub range: Option<RangeFit>,
    /// The cameras' contrast ratio, where the probe could measure it.
    pub contrast: Option<Contrast>,
}

/// A scan's pipeline fitted to its first frame: `first` probed with `pipe` (built from
/// `opts`), and the pipeline rebuilt where the probe says to — over a range that holds the
/// object where `pipe`'s does not (with `opts.fit_range`), with the right images scaled to
/// the left's contrast where the cameras' gains differ.
pub fn fit(pipe: Pipeline, calib: &StereoCalib, first: &StereoFrame, segment: bool, plate: Option<&RectifiedPlate>, opts: &PipelineOptions) -> Result<Fitted, FrameError> {
    let prepared = pipe.prepare_frame(first, segment, plate)?;
    Ok(fit_prepared(pipe, calib, &prepared, first.seq, opts)?)
}

/// [`fit`] on a frame already prepared by `pipe` (frame `seq`; a single pair's is 0).
pub fn fit_prepared(pipe: Pipeline, calib: &StereoCalib, prepared: &Prepared, seq: u64, opts: &PipelineOptions) -> Result<Fitted, PipelineError> {
    let Some((found, contrast)) = probe(&pipe, prepared)? else {
        tracing::info!("frame seq {seq}: too few of the object's pixels matched (under {MIN_MATCHED}) over a wide range to fit the disparity range to it or to compare the cameras' contrast; searching the range set");
        return Ok(Fitted { pipe, opts: opts.clone(), range: None, contrast: None });
    };
    let mut fitted = opts.clone();
    if let Some(c) = contrast.filter(Contrast::scales_right) {
        tracing::warn!(
            "frame seq {seq}: the right camera's images have {:.2} × the left's contrast (their gain or exposure differ): each is scaled to the left's before matching, but what one camera clipped or lost in its noise stays lost; set both cameras alike (the daemon's [cameras] exposure_100us, gain)",
            1.0 / c.ratio
        );
        // (On a frame already scaled by a gain the options carried, the two compose.)
        fitted.right_gain = Some(c.ratio * opts.right_gain.unwrap_or(1.0));
    }
    let range = opts.fit_range.then_some(found);
    let mut pipe = match range.as_ref().and_then(|f| refit(&pipe, f, seq, opts)) {
        Some(o) => {
            fitted = PipelineOptions { right_gain: fitted.right_gain, ..o };
            Pipeline::new(calib, (pipe.size.0 as u32, pipe.size.1 as u32), fitted.clone())?
        }
        None => pipe,
    };
    pipe.set_right_gain(fitted.right_gain);
    Ok(Fitted { pipe, opts: fitted, range, contrast })
}

/// Where `pipe`'s range does not hold the object the probe of frame `seq` found, says so and
/// returns `opts` over one that does.
fn refit(pipe: &Pipeline, f: &RangeFit, seq: u64, opts: &PipelineOptions) -> Option<PipelineOptions> {
    let (min, n) = f.widened?;
    let p = pipe.matcher().params();
    tracing::warn!(
        "frame seq {seq}: the object's disparities span {:.1} … {:.1}, outside the range {} … {}: searching {min} … {} instead (`--num-disparities` and `--min-disparity` set it; the daemon's `[matching] num_disparities`, and `fit_range = false` to keep it)",
        f.object.0,
        f.object.1,
        p.min_disparity,
        p.max_disparity(),
        min + n as i32 - 1
    );
    Some(PipelineOptions { min_disparity: Some(min), matching: MatchParams { num_disparities: n, ..opts.matching.clone() }, ..opts.clone() })
}

impl RangeFit {
    /// `report.json`'s `matching.range_fit`.
    pub fn entry(&self) -> serde_json::Value {
        serde_json::json!({"object_disparities": [self.object.0, self.object.1], "matched_px": self.matched, "widened": self.widened.is_some()})
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The range holds the object with room at both ends, in blocks of 16, mirrored on a rig
    /// with negative disparities.
    #[test]
    fn the_range_holds_the_object_with_room() {
        // 140 … 190: from 112 (16 short, down to a block) to 240 (190 + 50): 112 … 255.
        assert_eq!(range_holding(140.0, 190.0, 1), (112, 144));
        assert_eq!(range_holding(140.0, 190.0, -1), (-255, 144));
        // A near object's far end stops at 0; a thin one gets 16 of room on the near side.
        assert_eq!(range_holding(10.0, 20.0, 1), (0, 48));
        for (lo, hi) in [(3.5, 9.0), (94.0, 131.0), (200.0, 410.5)] {
            for sign in [1, -1] {
                let (min, n) = range_holding(lo, hi, sign);
                assert_eq!(n % 16, 0);
                let (a, b) = (min * sign, (min + n as i32 - 1) * sign);
                let (first, last) = (a.min(b) as f32, a.max(b) as f32);
                assert!(first <= (lo - 15.0).max(0.0) && last >= hi + 16.0, "{lo} … {hi}, sign {sign}: {min}, {n}");
            }
        }
    }
}
