//! Matcher parameters: raw (`MatchParams`, what a user or config gives) and checked
//! (`ValidMatchParams`, the only form the matcher accepts).

/// Matcher settings as given. Defaults follow OpenCV's `StereoBM` where it has an equivalent
/// (prefilter, window, texture), and were tuned on the Middlebury pairs in `../shared/data`
/// where spinscan adds or changes a stage (uniqueness 15 % instead of BM's 10 %, a left–right
/// check, a 0.5 px speckle range): see `docs/matcher.md`.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchParams {
    /// Smallest disparity searched (OpenCV `minDisparity`); may be negative.
    pub min_disparity: i32,
    /// Number of disparities searched: `min_disparity … min_disparity + num_disparities − 1`.
    /// Any positive count (OpenCV insists on multiples of 16; spinscan does not).
    pub num_disparities: u32,
    /// Side of the square correlation window, odd, 3…31 pixels.
    pub block: u32,
    /// The x-Sobel prefilter clips gradients to ±`prefilter_cap` (1…63).
    pub prefilter_cap: u8,
    /// Reject a match when another disparity (not adjacent) costs within this many percent
    /// of the best (0 disables).
    pub uniqueness_ratio: u32,
    /// Reject pixels whose window holds less gradient than this (sum of |prefiltered|
    /// over the window; 0 disables).
    pub texture_threshold: u32,
    /// Left–right check: the right pixel's own best disparity must agree within this many
    /// pixels (`None` disables).
    pub lr_max_diff: Option<u32>,
    /// Speckle filter: connected regions (neighbours within `speckle_range_px`) of at most
    /// this many pixels are removed (0 disables).
    pub speckle_window: u32,
    /// Largest disparity step, in pixels, between neighbours of one speckle region.
    pub speckle_range_px: f32,
    /// Parabola fit through the best cost and its neighbours.
    pub subpixel: bool,
    /// Worker threads (row stripes); 0 = all cores.
    pub threads: usize,
}

impl Default for MatchParams {
    fn default() -> Self {
        MatchParams {
            min_disparity: 0,
            num_disparities: 64,
            block: 9,
            prefilter_cap: 31,
            uniqueness_ratio: 15,
            texture_threshold: 10,
            lr_max_diff: Some(1),
            speckle_window: 100,
            speckle_range_px: 0.5,
            subpixel: true,
            threads: 0,
        }
    }
}

/// A parameter that cannot be used, with what was expected.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{name} = {value}: {expected}")]
pub struct ParamError {
    pub name: &'static str,
    pub value: String,
    pub expected: &'static str,
}

/// Parameters that passed [`MatchParams::validate`]; the matcher trusts them.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidMatchParams(MatchParams);

impl std::ops::Deref for ValidMatchParams {
    type Target = MatchParams;
    fn deref(&self) -> &MatchParams {
        &self.0
    }
}

impl ValidMatchParams {
    /// Half the window side.
    pub fn radius(&self) -> usize {
        (self.block / 2) as usize
    }

    /// Largest disparity searched.
    pub fn max_disparity(&self) -> i32 {
        self.min_disparity + self.num_disparities as i32 - 1
    }

    /// Worker threads actually used.
    pub fn thread_count(&self) -> usize {
        if self.threads == 0 {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        } else {
            self.threads
        }
    }
}

impl MatchParams {
    /// Checks every parameter once, with a message naming it and the accepted range.
    pub fn validate(self) -> Result<ValidMatchParams, ParamError> {
        let err = |name, value: String, expected| Err(ParamError { name, value, expected });
        if self.num_disparities == 0 || self.num_disparities > 1024 {
            return err("num_disparities", self.num_disparities.to_string(), "must be within 1…1024");
        }
        if !(-4096..=4096).contains(&self.min_disparity) {
            return err("min_disparity", self.min_disparity.to_string(), "must be within −4096…4096");
        }
        if self.block % 2 == 0 || !(3..=31).contains(&self.block) {
            // 31 keeps every window cost (block² · 2·cap) inside 16 bits.
            return err("block", self.block.to_string(), "must be odd and within 3…31");
        }
        if !(1..=63).contains(&self.prefilter_cap) {
            return err("prefilter_cap", self.prefilter_cap.to_string(), "must be within 1…63");
        }
        let max_cost = self.block * self.block * 2 * self.prefilter_cap as u32;
        if max_cost > u16::MAX as u32 {
            return err("block", self.block.to_string(), "is too large for this prefilter_cap (block² · 2 · cap must stay below 65536)");
        }
        if self.uniqueness_ratio > 100 {
            return err("uniqueness_ratio", self.uniqueness_ratio.to_string(), "must be a percentage within 0…100");
        }
        if !self.speckle_range_px.is_finite() || self.speckle_range_px < 0.0 {
            return err("speckle_range_px", self.speckle_range_px.to_string(), "must be a finite number ≥ 0");
        }
        if self.threads > 1024 {
            return err("threads", self.threads.to_string(), "must be within 0 (all cores)…1024");
        }
        Ok(ValidMatchParams(self))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid() {
        assert!(MatchParams::default().validate().is_ok());
    }

    #[test]
    fn messages_name_the_parameter() {
        let e = MatchParams { block: 8, ..Default::default() }.validate().unwrap_err();
        assert_eq!(e.to_string(), "block = 8: must be odd and within 3…31");
        let e = MatchParams { num_disparities: 0, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().starts_with("num_disparities = 0"));
    }
}
