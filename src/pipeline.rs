//! One view through the stereo core: rectify → segment → match → triangulate.

use std::time::Instant;

use crate::calib::StereoCalib;
use crate::cloud::PointCloud;
use crate::io::rgb_to_gray;
use crate::segment::{ChromaKey, SegmentError};
use crate::stereo::{
    triangulate::triangulate, DisparityIntervals, DisparityMap, GrayView, MatchError, MatchParams, MatchStats, ParamError,
    Rectification, RectifyError, RemapTable, StereoMatcher,
};

/// How a view is processed.
#[derive(Debug, Clone)]
pub struct PipelineOptions {
    /// Rectification scaling: 0 keeps only valid pixels (default), 1 keeps all, −1 unscaled.
    pub alpha: f64,
    /// First disparity searched. `None` picks it from the rig: 0 when rectified disparities
    /// are positive, `−(N − 1)` when they are negative, so the N disparities cover the
    /// rig's side of zero.
    pub min_disparity: Option<i32>,
    /// Matcher settings; its `min_disparity` is replaced by the one resolved above.
    pub matching: MatchParams,
    /// Foreground segmentation (used when a view asks for it).
    pub chroma: ChromaKey,
}

impl Default for PipelineOptions {
    fn default() -> Self {
        PipelineOptions { alpha: 0.0, min_disparity: None, matching: MatchParams::default(), chroma: ChromaKey::default() }
    }
}

/// Why a view could not be processed.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("rectification: {0}")]
    Rectify(#[from] RectifyError),
    #[error("matcher parameter {0}")]
    Param(#[from] ParamError),
    #[error("matching: {0}")]
    Match(#[from] MatchError),
    #[error("segmentation: {0}")]
    Segment(#[from] SegmentError),
    #[error("image is {0}×{1} but the calibration is for {2}×{3}")]
    ImageSize(usize, usize, u32, u32),
}

/// Everything one view produced.
#[derive(Debug, Clone)]
pub struct View {
    pub disparity: DisparityMap,
    /// Rectified left image, RGB.
    pub left_rgb: Vec<u8>,
    /// Foreground mask in rectified left coordinates (255 = object), when segmentation ran.
    pub mask: Option<Vec<u8>>,
    pub cloud: PointCloud,
    pub stats: MatchStats,
    /// Time of the matcher alone, milliseconds.
    pub match_ms: f64,
}

/// The stereo core set up for one rig: rectification, remap tables and a matcher whose
/// buffers are reused from view to view.
pub struct Pipeline {
    pub rect: Rectification,
    maps: (RemapTable, RemapTable),
    matcher: StereoMatcher,
    chroma: ChromaKey,
    size: (usize, usize),
}

impl Pipeline {
    pub fn new(calib: &StereoCalib, size: (u32, u32), opts: PipelineOptions) -> Result<Pipeline, PipelineError> {
        if let Some((w, h)) = calib.image_size {
            if (w, h) != size {
                return Err(PipelineError::ImageSize(size.0 as usize, size.1 as usize, w, h));
            }
        }
        let rect = Rectification::compute(calib, size, opts.alpha)?;
        let n = opts.matching.num_disparities as i32;
        let min_disparity = opts.min_disparity.unwrap_or(if rect.disparity_sign < 0 { -(n - 1) } else { 0 });
        let params = MatchParams { min_disparity, ..opts.matching }.validate()?;
        let maps = rect.maps(calib);
        Ok(Pipeline { rect, maps, matcher: StereoMatcher::new(params), chroma: opts.chroma, size: (size.0 as usize, size.1 as usize) })
    }

    pub fn matcher(&self) -> &StereoMatcher {
        &self.matcher
    }

    /// Rectifies a raw RGB pair.
    pub fn rectify_rgb(&self, left: &[u8], right: &[u8]) -> (Vec<u8>, Vec<u8>) {
        let (w, h) = (self.size.0 as u32, self.size.1 as u32);
        (self.maps.0.remap::<3>(left, w, h), self.maps.1.remap::<3>(right, w, h))
    }

    /// Rectifies a mask given in raw left coordinates.
    pub fn rectify_left_mask(&self, mask: &[u8]) -> Vec<u8> {
        let m = self.maps.0.remap::<1>(mask, self.size.0 as u32, self.size.1 as u32);
        m.into_iter().map(|v| if v >= 128 { 255 } else { 0 }).collect()
    }

    /// Processes a raw RGB pair. `segment`: match only the chroma-keyed foreground.
    pub fn process_rgb(&mut self, left: &[u8], right: &[u8], segment: bool) -> Result<View, PipelineError> {
        self.process_rgb_with_plate(left, right, segment, None)
    }

    /// As [`Pipeline::process_rgb`], with an optional background plate (raw left image of the
    /// empty scene, RGB) that the segmentation also keys against.
    pub fn process_rgb_with_plate(&mut self, left: &[u8], right: &[u8], segment: bool, plate: Option<&[u8]>) -> Result<View, PipelineError> {
        let (w, h) = self.size;
        let (lr, rr) = self.rectify_rgb(left, right);
        let mask = if segment {
            let plate = plate.map(|p| self.maps.0.remap::<3>(p, w as u32, h as u32));
            Some(self.chroma.segment(&lr, w, h, plate.as_deref())?)
        } else {
            None
        };
        self.process_rectified(lr, &rr, mask)
    }

    /// Matches and triangulates an already rectified RGB pair, with an optional rectified mask.
    pub fn process_rectified(&mut self, left_rgb: Vec<u8>, right_rgb: &[u8], mask: Option<Vec<u8>>) -> Result<View, PipelineError> {
        let (w, h) = self.size;
        let (lg, rg) = (rgb_to_gray(&left_rgb), rgb_to_gray(right_rgb));
        let intervals = self.matcher.full_intervals(w, h, mask.as_deref());
        let (disparity, stats, match_ms) = self.match_gray(&lg, &rg, &intervals)?;
        let cloud = triangulate(&disparity, &self.rect, &left_rgb);
        Ok(View { disparity, left_rgb, mask, cloud, stats, match_ms })
    }

    /// Runs the matcher alone on rectified grey images and times it.
    pub fn match_gray(&mut self, left: &[u8], right: &[u8], intervals: &DisparityIntervals) -> Result<(DisparityMap, MatchStats, f64), PipelineError> {
        let (w, h) = self.size;
        let mut out = DisparityMap::new(w, h);
        let lv = GrayView::new(w, h, left).ok_or(MatchError::Buffer(left.len(), w * h))?;
        let rv = GrayView::new(w, h, right).ok_or(MatchError::Buffer(right.len(), w * h))?;
        let t0 = Instant::now();
        let stats = self.matcher.compute(lv, rv, intervals, &mut out)?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok((out, stats, ms))
    }
}
