//! Matcher parameters: raw (`MatchParams`, what a user or config gives) and checked
//! (`ValidMatchParams`, the only form the matcher accepts).

/// Matcher settings as given. Defaults follow OpenCV's `StereoBM` where it has an equivalent
/// (prefilter, window, texture), and were tuned on the Middlebury pairs in `../shared/data`
/// where spinscan adds or changes a stage (uniqueness 15 % instead of BM's 10 %, a left–right
/// check, a 0.5 px speckle range): see `docs/matcher.md`.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchParams {
    /// The matcher: correlation (block matching) or semi-global matching.
    pub method: Method,
    /// SGM: penalty for a disparity change of one between neighbours along a path (in the
    /// cost's unit: census bits plus grey levels of the intensity term).
    pub p1: u16,
    /// SGM: penalty for a larger disparity jump between neighbours (> `p1`).
    pub p2: u16,
    /// SGM: aggregation paths, 4 (horizontal and vertical), 8 (and the diagonals), or 5 (from
    /// the left, the right and the three above, in one pass: memory of one row instead of a
    /// volume, less accurate).
    pub sgm_paths: u8,
    /// SGM: the per-pixel intensity term added to the census cost, |left − right| in grey
    /// levels (the right image first matched to the left's mean and spread), capped at this
    /// many levels (0 = census alone; at most 100).
    pub sgm_ad_cap: u8,
    /// SGM: take each match's sub-pixel disparity mostly from the correlation cost (the `bm`
    /// cost over `sgm_refine_block`) around SGM's winner, plus a share of SGM's own deviation
    /// from it, instead of from SGM's own sums alone (sharper on slanted surfaces; about 25 ns
    /// per matched pixel more).
    pub sgm_refine: bool,
    /// Search wide intervals (64 disparities a pixel or more) only around what
    /// the pair matched at half size, per matcher tile (`matcher/seed.rs`): faster the wider
    /// the range, and fewer gross errors; off, every pixel searches its whole interval. On
    /// for sgm, off for bm (whose seeded matches are denser but, in a scan's views, a little
    /// further from the surface: docs/matcher.md, "Seeded from the pair at half size").
    pub coarse_to_fine: bool,
    /// SGM: side of the refinement's square correlation window, odd, 3…31 pixels (`block`
    /// is `bm`'s own window).
    pub sgm_refine_block: u32,
    /// SGM: how close, pixels, the refinement's correlation value must come to SGM's own for
    /// the two to be blended (0.1…2). Where they lie further apart, a scan's view drops the
    /// match and a whole image keeps SGM's value. Lower keeps fewer, closer matches: at 0.5 a
    /// scan's views lose 6–10 % of their pixels (a faint texture's 28 %) and the fused meshes
    /// come out closer to the surface (docs/matcher.md, "How close the two values must
    /// agree"). The default, 1.25, keeps a scan's SGM bad2 under half of `bm`'s on the
    /// realistic rigs' tori, where 1 px missed it ("The agreement limit on realistic rigs").
    pub sgm_refine_agree: f32,
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
    /// Sub-pixel disparities: the equiangular (V) fit through the best cost and its two
    /// neighbours (for sgm, see `sgm_refine`).
    pub subpixel: bool,
    /// Worker threads (row stripes); 0 = all cores.
    pub threads: usize,
}

impl Default for MatchParams {
    fn default() -> Self {
        MatchParams {
            method: Method::Bm,
            p1: 25,
            p2: 100,
            sgm_paths: 4,
            sgm_ad_cap: 25,
            sgm_refine: true,
            coarse_to_fine: false,
            sgm_refine_block: 9,
            sgm_refine_agree: 1.25,
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

impl MatchParams {
    /// The defaults of a matcher. `sgm` differs from `bm` where its sums behave differently,
    /// measured on the Middlebury pairs (docs/matcher.md): no uniqueness test (the aggregated
    /// sums of weak texture are flat, and the test removed more correct matches than wrong
    /// ones), a 2 px speckle range (SGBM's; sub-pixel SGM surfaces are smooth), no texture
    /// threshold (the paths carry texture in from the neighbours).
    pub fn for_method(method: Method) -> MatchParams {
        match method {
            Method::Bm => MatchParams::default(),
            Method::Sgm => MatchParams { method, uniqueness_ratio: 0, speckle_range_px: 2.0, texture_threshold: 0, coarse_to_fine: true, ..MatchParams::default() },
        }
    }
}

/// Which matcher runs (`--method`, `[matching] method`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Correlation along rows: SAD of prefiltered images over a square window (`matcher/`).
    #[default]
    Bm,
    /// Semi-global matching over four or eight paths on census costs (`sgm/`).
    Sgm,
}

impl Method {
    /// The name used on the command line, in configs and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Method::Bm => "bm",
            Method::Sgm => "sgm",
        }
    }
}

/// A matcher name that is neither `bm` nor `sgm`.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("unknown matcher {0:?}: expected bm or sgm")]
pub struct UnknownMethod(pub String);

impl std::str::FromStr for Method {
    type Err = UnknownMethod;
    fn from_str(s: &str) -> Result<Self, UnknownMethod> {
        match s {
            "bm" => Ok(Method::Bm),
            "sgm" => Ok(Method::Sgm),
            _ => Err(UnknownMethod(s.to_string())),
        }
    }
}

impl std::fmt::Display for Method {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
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

    /// Half the side of the widest window any stage reads: `block`'s, or SGM's refinement's
    /// where that is wider.
    pub fn reach(&self) -> usize {
        let refine = if self.method == Method::Sgm && self.sgm_refine && self.subpixel { (self.sgm_refine_block / 2) as usize } else { 0 };
        self.radius().max(refine)
    }

    /// Largest disparity searched.
    pub fn max_disparity(&self) -> i32 {
        self.min_disparity + self.num_disparities as i32 - 1
    }

    /// These parameters for the pair halved in both directions: the disparities whose double
    /// lies in the range, `⌈min / 2⌉ … ⌊max / 2⌋` (half as many: 0 … 127 gives 0 … 63, four
    /// blocks of 16 rather than five), at least one; still within the checked bounds.
    pub(super) fn halved(&self) -> ValidMatchParams {
        let lo = -(-self.min_disparity).div_euclid(2);
        let hi = self.max_disparity().div_euclid(2).max(lo);
        ValidMatchParams(MatchParams { min_disparity: lo, num_disparities: (hi - lo + 1) as u32, ..self.0.clone() })
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
        if self.sgm_refine_block % 2 == 0 || !(3..=31).contains(&self.sgm_refine_block) {
            return err("sgm_refine_block", self.sgm_refine_block.to_string(), "must be odd and within 3…31");
        }
        if !(0.1..=2.0).contains(&self.sgm_refine_agree) {
            // NaN fails too. The refinement correlates over SGM's winner ± 2.
            return err("sgm_refine_agree", self.sgm_refine_agree.to_string(), "must be within 0.1 … 2 pixels");
        }
        if !(1..=63).contains(&self.prefilter_cap) {
            return err("prefilter_cap", self.prefilter_cap.to_string(), "must be within 1…63");
        }
        for (name, block) in [("block", self.block), ("sgm_refine_block", self.sgm_refine_block)] {
            if block * block * 2 * self.prefilter_cap as u32 > u16::MAX as u32 {
                return err(name, block.to_string(), "is too large for this prefilter_cap (block² · 2 · cap must stay below 65536)");
            }
        }
        if self.uniqueness_ratio > 100 {
            return err("uniqueness_ratio", self.uniqueness_ratio.to_string(), "must be a percentage within 0…100");
        }
        if !self.speckle_range_px.is_finite() || self.speckle_range_px < 0.0 {
            return err("speckle_range_px", self.speckle_range_px.to_string(), "must be a finite number ≥ 0");
        }
        if self.p1 == 0 || self.p1 >= self.p2 {
            return err("p1", self.p1.to_string(), "must be at least 1 and below p2");
        }
        if self.p2 > 2000 {
            // Eight path costs of at most 34 + 100 + p2 each must fit the 16-bit sums.
            return err("p2", self.p2.to_string(), "must be within p1 + 1 … 2000");
        }
        if self.sgm_ad_cap > 100 {
            return err("sgm_ad_cap", self.sgm_ad_cap.to_string(), "must be within 0 (census alone) … 100 grey levels");
        }
        if ![4, 5, 8].contains(&self.sgm_paths) {
            return err("sgm_paths", self.sgm_paths.to_string(), "must be 4, 5 or 8");
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
    fn sgm_settings_are_checked_and_have_their_own_defaults() {
        let sgm = MatchParams::for_method(Method::Sgm);
        assert!(sgm.clone().validate().is_ok());
        assert_eq!((sgm.method, sgm.uniqueness_ratio, sgm.speckle_range_px), (Method::Sgm, 0, 2.0));
        assert_eq!(MatchParams::for_method(Method::Bm), MatchParams::default());
        for (bad, name) in [(MatchParams { p1: 0, ..sgm.clone() }, "p1"), (MatchParams { p1: 200, p2: 120, ..sgm.clone() }, "p1"), (MatchParams { p2: 5000, ..sgm.clone() }, "p2"), (MatchParams { sgm_paths: 6, ..sgm.clone() }, "sgm_paths"), (MatchParams { sgm_ad_cap: 101, ..sgm.clone() }, "sgm_ad_cap"), (MatchParams { sgm_refine_agree: 0.05, ..sgm.clone() }, "sgm_refine_agree"), (MatchParams { sgm_refine_agree: 2.5, ..sgm.clone() }, "sgm_refine_agree"), (MatchParams { sgm_refine_agree: f32::NAN, ..sgm }, "sgm_refine_agree")] {
            assert_eq!(bad.validate().unwrap_err().name, name);
        }
        assert_eq!("sgm".parse::<Method>(), Ok(Method::Sgm));
        assert_eq!("census".parse::<Method>().unwrap_err().to_string(), "unknown matcher \"census\": expected bm or sgm");
    }

    #[test]
    fn messages_name_the_parameter() {
        let e = MatchParams { block: 8, ..Default::default() }.validate().unwrap_err();
        assert_eq!(e.to_string(), "block = 8: must be odd and within 3…31");
        let e = MatchParams { num_disparities: 0, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().starts_with("num_disparities = 0"));
    }
}
