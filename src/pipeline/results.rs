//! The results folder of a run or a scan (`shared/spec/recording-format.md`): `manifest.json`
//! rewritten after every frame, `views/`, `disparity/`, `poses.jsonl`, `model.ply`,
//! `turntable_estimated.yaml` and `report.json`, with the registration of each view noted in
//! its entry (`super::registered`) and the scores against ground truth where the recording
//! has it. One writer for `spinscan replay` and the daemon's live scans alike.

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::{json, Value};

use super::View;
use crate::assist::AssistParams;
use crate::hw::StereoFrame;
use crate::io;
use crate::register::posestore::ViewPose;
use crate::segment::{edge_share, no_screen, object_on_edge, plain_backdrop, EDGE_WARN_SHARE};
use crate::stereo::gain::NEAR_WHITE;
use crate::stereo::DisparityMap;

/// Share of a view's searched pixels dropped at an end of the disparity range from which a
/// scan warns (once) that the object does not fit the range. Where the object fits, next to
/// none are: 0 on the default lab's simulated recordings, 5 pixels over a faint egg's 20
/// views; 8–17 % a view on a torus whose near side lies 9 px beyond the range.
pub const RANGE_EDGE_WARN_SHARE: f64 = 0.005;

/// Share of a segmented view's searched pixels matched below which a scan warns (once) that
/// the object lies outside the range or shows too little texture. Measured on simulated
/// recordings: 0.9–0.98 on standard textures, 0.71 on a faint egg, 0.09–0.15 where texture
/// is near plain or buried in noise, 0.004–0.018 with the whole object beyond the range.
const FEW_MATCHED_WARN_SHARE: f64 = 0.25;

/// Share of a view's object pixels at or near white (luma ≥ [`NEAR_WHITE`] in the rectified
/// left image) from which a scan warns (once) that the cameras are overexposed: clipped
/// paint has no texture to match. Measured at 640 × 480: 0–0.3 % on the simulated and the
/// independent renderer's recordings, 1.5 % with a strong specular highlight, 80 % with both
/// cameras' gain at 1.8 × (poses 0.53° off against 0.035°, a tenth of the surface missing).
pub const SATURATED_WARN_SHARE: f64 = 0.1;

/// The share (0…1) of `mask`'s object pixels (every pixel without one) of an RGB image whose
/// luma is at least [`NEAR_WHITE`].
pub fn saturated_share(rgb: &[u8], mask: Option<&[u8]>) -> f64 {
    let (mut white, mut n) = (0usize, 0usize);
    for (k, p) in rgb.chunks_exact(3).enumerate() {
        if mask.is_none_or(|m| m.get(k).is_some_and(|&v| v != 0)) {
            n += 1;
            white += (crate::stereo::luma(p[0], p[1], p[2]) >= NEAR_WHITE) as usize;
        }
    }
    white as f64 / n.max(1) as f64
}

/// Why the results folder could not be written (or scored).
#[derive(Debug, thiserror::Error)]
pub enum ResultsError {
    #[error("cannot write {path}: {what}")]
    Output { path: PathBuf, what: String },
    /// A file beside the frames (ground truth) is unusable.
    #[error("{0}")]
    SideFile(String),
    #[error("frame seq {seq}: loop closure: {what}")]
    LoopClosure { seq: u64, what: String },
    #[error("mesh: {0}")]
    Mesh(String),
}

/// Ground-truth comparison of one disparity map (recordings of ideal rigs carry it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GtScore {
    /// Ground-truth pixels.
    pub gt_pixels: usize,
    /// Fraction of them that got a disparity.
    pub coverage: f64,
    /// Fraction of the covered ones off by more than 2 px.
    pub bad2_of_matched: f64,
    /// Mean |error| over covered pixels, px.
    pub mean_abs_err_px: f64,
}

/// Scores `disp` against `gt` (non-finite = no truth) by magnitude.
pub fn score_against_gt(disp: &DisparityMap, gt: &DisparityMap) -> GtScore {
    let (mut n, mut covered, mut bad, mut err) = (0usize, 0usize, 0usize, 0f64);
    for y in 0..gt.height {
        for x in 0..gt.width {
            let Some(t) = gt.get(x, y) else { continue };
            n += 1;
            if let Some(d) = disp.get(x, y) {
                covered += 1;
                let e = (d.abs() - t.abs()).abs();
                err += e as f64;
                bad += (e > 2.0) as usize;
            }
        }
    }
    GtScore {
        gt_pixels: n,
        coverage: covered as f64 / n.max(1) as f64,
        bad2_of_matched: bad as f64 / covered.max(1) as f64,
        mean_abs_err_px: err / covered.max(1) as f64,
    }
}

/// What marks a registration warning as a view's degeneracy (`IcpResult::degeneracy_warning`).
const DEGENERATE: &str = "registration is degenerate";

/// Views whose degeneracy is logged; report.json keeps every one.
const DEGENERATE_LOGGED: usize = 3;

/// `report.json`'s `matching`: the rectification, matcher and search the results were made
/// with, so that a results folder says how to make it again. `assist` is `None` where no
/// frame is assisted (`--assist none`, or no registration to take the motion from); `fit` is
/// what the first frame's probe found, where the range was fitted, and `contrast` the
/// cameras' contrast ratio it measured.
pub fn matching_entry(pipe: &super::Pipeline, assist: Option<&AssistParams>, fit: Option<&super::range::RangeFit>, contrast: Option<&crate::stereo::gain::Contrast>) -> Value {
    let p = pipe.matcher().params();
    let mut m = json!({
        "rectify_alpha": pipe.rect.alpha,
        "rim_px": pipe.chroma.rim_px,
        "follow_surface": pipe.follows_surface(),
        "method": p.method.name(),
        "min_disparity": p.min_disparity,
        "num_disparities": p.num_disparities,
        "block": p.block,
        "prefilter_cap": p.prefilter_cap,
        "uniqueness_ratio": p.uniqueness_ratio,
        "texture_threshold": p.texture_threshold,
        "lr_max_diff": p.lr_max_diff,
        "speckle_window": p.speckle_window,
        "speckle_range_px": p.speckle_range_px,
        "subpixel": p.subpixel,
        "coarse_to_fine": p.coarse_to_fine,
        "assist": assist.map_or("none", |a| a.mode.name()),
    });
    if let Some(a) = assist {
        m["assist_w"] = json!(a.mode.w());
        m["assist_granularity"] = json!(a.granularity.resolve(a.mode).name());
    }
    if p.method == crate::stereo::Method::Sgm {
        for (k, v) in [("p1", json!(p.p1)), ("p2", json!(p.p2)), ("sgm_paths", json!(p.sgm_paths)), ("sgm_ad_cap", json!(p.sgm_ad_cap)), ("sgm_refine", json!(p.sgm_refine)), ("sgm_refine_block", json!(p.sgm_refine_block)), ("sgm_refine_agree", json!(p.sgm_refine_agree))] {
            m[k] = v;
        }
    }
    if let Some(f) = fit {
        m["range_fit"] = f.entry();
    }
    if let Some(c) = contrast {
        m["contrast"] = c.entry();
    }
    m
}

/// The results folder, kept consistent on disk after every frame.
pub struct ResultsWriter {
    pub(super) dir: PathBuf,
    source: String,
    pub(super) frames: Vec<Value>,
    disparity_sign: i32,
    started: Instant,
    /// `report.json`'s `registration` (`registered::finish_registration`).
    pub(super) registration: Option<Value>,
    /// Extra keys of `manifest.json` (the daemon's scan settings and counters).
    pub manifest_extra: serde_json::Map<String, Value>,
    /// Captured pairs that produced no view (dropped before matching, or unmatchable), with why.
    skipped: Vec<Value>,
    /// `report.json`'s `matching` ([`matching_entry`]), once the matcher is set up.
    matching: Option<Value>,
}

impl ResultsWriter {
    pub fn create(dir: &Path, source: &str, disparity_sign: i32) -> Result<ResultsWriter, ResultsError> {
        for sub in ["views", "disparity"] {
            let d = dir.join(sub);
            std::fs::create_dir_all(&d).map_err(|e| ResultsError::Output { path: d, what: e.to_string() })?;
        }
        let w = ResultsWriter { dir: dir.to_path_buf(), source: source.to_string(), frames: Vec::new(), disparity_sign, started: Instant::now(), registration: None, manifest_extra: serde_json::Map::new(), skipped: Vec::new(), matching: None };
        w.write_manifest("running", None)?;
        Ok(w)
    }

    fn write_json(&self, name: &str, value: &Value) -> Result<(), ResultsError> {
        let path = self.dir.join(name);
        io::write_atomic(&path, serde_json::to_string_pretty(value).unwrap().as_bytes()).map_err(|e| ResultsError::Output { path, what: e.to_string() })
    }

    /// `poses.jsonl`: `{"seq", "first_from_view": [[4x4]]}` per registered view.
    pub fn write_poses(&self, poses: &[ViewPose]) -> Result<(), ResultsError> {
        let mut text = String::new();
        for p in poses {
            text.push_str(&json!({"seq": p.seq, "first_from_view": crate::register::to_rows(&p.first_from_view)}).to_string());
            text.push('\n');
        }
        let path = self.dir.join("poses.jsonl");
        io::write_atomic(&path, text.as_bytes()).map_err(|e| ResultsError::Output { path, what: e.to_string() })
    }

    /// Writes a view's cloud and disparity map and returns its `report.json` entry.
    pub fn write_view(&self, frame: &StereoFrame, view: &View, assist: Option<&AssistParams>) -> Result<Value, ResultsError> {
        let seq = frame.seq;
        let view_path = self.dir.join("views").join(format!("{seq:06}.ply"));
        io::ply::write_ply(&view_path, &view.cloud).map_err(|e| ResultsError::Output { path: view_path, what: e.to_string() })?;
        let disp_path = self.dir.join("disparity").join(format!("{seq:06}.png"));
        io::write_disparity_png(&disp_path, &view.disparity).map_err(|e| ResultsError::Output { path: disp_path, what: e.to_string() })?;
        let mut entry = json!({
            "seq": seq,
            "match_ms": view.match_ms,
            "register_ms": null,
            "mean_search_px": view.stats.mean_search_px(),
            "valid_fraction": view.stats.valid_fraction(),
            "searched_px": view.stats.searched,
            // Matches dropped at an end of the disparity range (`StereoMatcher::drop_range_edges`).
            "range_edge_px": view.stats.range_edge,
            "range_edge_share": view.stats.range_edge_share(),
            // Whether this frame searched the full range (no assistance, the first frames,
            // or self-correction); `assist` says why.
            "fallback": view.assist.as_ref().is_none_or(|a| a.searched_full_range()),
            "points": view.cloud.len(),
            // The object's pixels clipped to white: overexposed cameras. Matches dropped where
            // either camera clipped them (`gain::drop_clipped`). The right image's near-white
            // pixels over the left's object pixels (the right image is not segmented).
            "saturated_share": saturated_share(&view.left_rgb, view.mask.as_deref()),
            "clipped_px": view.clipped_px,
            // Points within `matching.rim_px` of the object's silhouette: registered with, not
            // fused, not in `points` or views/.
            "rim_points": view.rim_points(),
            // The surface-following refinement (`matching.follow_surface`): the matched pixels
            // it looked at (half their window matched or more), those it gave a new value, and
            // its time; and of the matched pixels within `stereo::follow::RIM_PROFILE_PX` of the
            // silhouette, those given the rim's profile and those left on the flank the right
            // camera sees compressed (its time is within `ms`).
            "followed_px": {"looked": view.followed.looked, "refined": view.followed.refined, "ms": view.follow_ms,
                "rim": {"looked": view.rim_profile.looked, "profiled": view.rim_profile.profiled, "compressed": view.rim_profile.compressed}},
            "right_saturated_share": view.right_near_white as f64 / view.mask.as_deref().map_or(view.left_rgb.len() / 3, |m| m.iter().filter(|&&v| v != 0).count()).max(1) as f64,
            "table_deg": frame.table_deg,
            "t_left_ns": frame.t_left_ns,
            "skew_ns": frame.t_right_ns as i64 - frame.t_left_ns as i64,
        });
        if let (Some(k), Some(mask)) = (&view.key, &view.mask) {
            entry["segmentation"] = k.report_entry(edge_share(mask, view.disparity.width, view.disparity.height));
        }
        if let Some(a) = &view.assist {
            entry["assist"] = json!({
                "mode": assist.map(|p| p.mode.name()),
                "w": assist.and_then(|p| p.mode.w()),
                "granularity": assist.map(|p| p.granularity.resolve(p.mode).name()),
                "full_range_reason": a.full_range,
                "fallback_reason": a.fallback,
                "interval_ms": a.interval_ms,
                "lag": a.lag,
                "single_px": a.single_px,
                "union_px": a.union_px,
                "filled_px": a.filled_px,
                "uncovered_px": a.uncovered_px,
            });
            if let Some(why) = &a.fallback {
                tracing::warn!("frame seq {seq}: assisted result rejected ({why}); matched again over the full range");
            }
        }
        Ok(entry)
    }

    /// Records the matcher and search the views are made with (`report.json`'s `matching`).
    pub fn set_matching(&mut self, entry: Value) {
        self.matching = Some(entry);
    }

    /// Frames written so far.
    pub fn frame_count(&self) -> usize {
        self.frames.len()
    }

    /// The rig's disparity sign (what `disparity/` PNGs store the magnitude of).
    pub fn disparity_sign(&self) -> i32 {
        self.disparity_sign
    }

    /// Adds a frame's entry and rewrites the manifest (still `running`).
    pub fn push_frame(&mut self, entry: Value) -> Result<(), ResultsError> {
        // Each condition is logged on the first frame that meets it.
        let first = |test: &dyn Fn(&Value) -> bool| test(&entry) && !self.frames.iter().any(test);
        let share = |key: &str| entry["segmentation"][key].as_f64().unwrap_or(0.0) as f32;
        // Registration's warnings and notes (`register_view`); a view's degeneracy — the table's
        // step kept along a motion its surface leaves free, as on nearly every view of a
        // sphere or an egg — only on the first views that have one.
        let degenerate = |f: &Value| f["warnings"].as_array().is_some_and(|w| w.iter().any(|w| w.as_str().is_some_and(|w| w.contains(DEGENERATE))));
        let before = self.frames.iter().filter(|f| degenerate(f)).count();
        for w in entry["warnings"].as_array().into_iter().flatten().filter_map(Value::as_str) {
            match (w.contains(DEGENERATE), before.cmp(&DEGENERATE_LOGGED)) {
                (false, _) | (true, std::cmp::Ordering::Less) => tracing::warn!("{w}"),
                (true, std::cmp::Ordering::Equal) => tracing::warn!("{w}; further views' degeneracy is in report.json only (frames[].warnings)"),
                _ => {}
            }
        }
        for n in entry["notes"].as_array().into_iter().flatten().filter_map(Value::as_str) {
            tracing::info!("{n}");
        }
        if first(&|f| f["segmentation"]["key"] == json!("default")) {
            tracing::warn!("frame seq {}: {}; give the screen's colour (`--key-color R,G,B`, the daemon's `[matching] key_color`) or a background plate (`--plate`), or turn segmentation off", entry["seq"], no_screen());
        }
        if first(&|f| f["segmentation"]["key"] == json!("backdrop")) {
            tracing::info!("frame seq {}: {}", entry["seq"], plain_backdrop(share("texture_threshold")));
        }
        if first(&|f| f["segmentation"]["edge_object_share"].as_f64().is_some_and(|s| s >= EDGE_WARN_SHARE as f64)) {
            tracing::warn!("frame seq {}: {}; cover it in the screen's colour, or give a background plate (`--plate`, the daemon's `[matching] plate`)", entry["seq"], object_on_edge(share("edge_object_share")));
        }
        for (key, camera) in [("saturated_share", "left"), ("right_saturated_share", "right")] {
            if first(&|f| f[key].as_f64().is_some_and(|s| s >= SATURATED_WARN_SHARE)) {
                tracing::warn!(
                    "frame seq {}: {:.0} % of the object's pixels are at or near white (luma {NEAR_WHITE} or more in the {camera} image): the {camera} camera is overexposed and clipped paint has no texture to match; lower its exposure or gain (the daemon's [cameras] exposure_100us, gain)",
                    entry["seq"],
                    100.0 * entry[key].as_f64().unwrap_or(0.0)
                );
            }
        }

        if first(&|f| f["range_edge_share"].as_f64().is_some_and(|s| s >= RANGE_EDGE_WARN_SHARE)) {
            tracing::warn!(
                "frame seq {}: {} of the object's pixels ({:.1} % of those searched) found their best match at an end of the disparity range and were dropped: the object comes closer (or lies farther) than the range covers; widen it (`--num-disparities`, `--min-disparity`; the daemon's `[matching] num_disparities`)",
                entry["seq"],
                entry["range_edge_px"],
                100.0 * entry["range_edge_share"].as_f64().unwrap_or(0.0)
            );
        }
        if first(&|f| f.get("segmentation").is_some() && f["valid_fraction"].as_f64().is_some_and(|v| v < FEW_MATCHED_WARN_SHARE)) {
            tracing::warn!(
                "frame seq {}: only {:.1} % of the object's {} pixels searched got a disparity: the object may lie outside the disparity range (widen it: `--num-disparities`, `--min-disparity`; the daemon's `[matching] num_disparities`), or show too little texture for stereo matching (a plain, dark or shiny surface)",
                entry["seq"],
                100.0 * entry["valid_fraction"].as_f64().unwrap_or(0.0),
                entry["searched_px"]
            );
        }
        self.frames.push(entry);
        self.write_manifest("running", None)
    }

    /// A captured pair that produced no view: listed in `report.json` (`skipped`) and
    /// counted in the manifest.
    pub fn note_skipped(&mut self, seq: u64, why: &str) {
        self.skipped.push(json!({"seq": seq, "why": why}));
    }

    /// `manifest.json`, atomically (temp + rename).
    pub fn write_manifest(&self, status: &str, reason: Option<&str>) -> Result<(), ResultsError> {
        let mut m = json!({
            "format": 1,
            "status": status,
            "frames": self.frames.len(),
            "source": self.source,
            "written_by": format!("spinscan {}", env!("CARGO_PKG_VERSION")),
            "elapsed_s": self.started.elapsed().as_secs_f64(),
        });
        if !self.skipped.is_empty() {
            m["skipped"] = json!(self.skipped.len());
        }
        if let Some(r) = reason {
            m["reason"] = json!(r);
        }
        for (k, v) in &self.manifest_extra {
            m[k] = v.clone();
        }
        self.write_json("manifest.json", &m)
    }

    fn write_report(&self) -> Result<(), ResultsError> {
        let scored: Vec<&Value> = self.frames.iter().filter(|f| f.get("gt_coverage").is_some()).collect();
        let mean = |key: &str, list: &[&Value]| -> Option<f64> {
            let v: Vec<f64> = list.iter().filter_map(|f| f[key].as_f64()).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        let all: Vec<&Value> = self.frames.iter().collect();
        let mut report = json!({
            "disparity_sign": self.disparity_sign,
            "frames": self.frames,
            "summary": {
                "frames": self.frames.len(),
                "mean_match_ms": mean("match_ms", &all),
                "mean_valid_fraction": mean("valid_fraction", &all),
                "gt_frames": scored.len(),
                "mean_gt_coverage": mean("gt_coverage", &scored),
                "mean_gt_bad2_of_matched": mean("gt_bad2_of_matched", &scored),
                "mean_register_ms": mean("register_ms", &all),
                "full_range_frames": self.frames.iter().filter(|f| f["fallback"] == json!(true)).count(),
                "self_corrected_frames": self.frames.iter().filter(|f| f["assist"]["fallback_reason"].is_string()).count(),
            },
            "registration": self.registration,
        });
        if !self.skipped.is_empty() {
            report["skipped"] = json!(self.skipped);
        }
        if let Some(m) = &self.matching {
            report["matching"] = m.clone();
        }
        self.write_json("report.json", &report)
    }

    /// Ends the run: `complete`, or `failed` with the reason.
    pub fn finish(&self, failure: Option<&str>) -> Result<(), ResultsError> {
        match failure {
            None => self.finish_as("complete", None),
            Some(reason) => self.finish_as("failed", Some(reason)),
        }
    }

    /// Ends the run with `status` (`complete`, `interrupted`, `failed`) and why.
    pub fn finish_as(&self, status: &str, reason: Option<&str>) -> Result<(), ResultsError> {
        self.write_report()?;
        self.write_manifest(status, reason)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The share counts the object's pixels whose luma reaches near white — grey, white or
    /// a near-white tint alike, not a saturated colour — and every pixel without a mask.
    #[test]
    fn the_saturated_share_counts_near_white_object_pixels() {
        // White, near-white grey, a pale tint (luma 250), a saturated blue (luma 29), dark.
        let rgb = [[255, 255, 255], [251, 251, 251], [255, 250, 235], [0, 0, 255], [40, 40, 40]].concat();
        assert_eq!(saturated_share(&rgb, None), 3.0 / 5.0);
        assert_eq!(saturated_share(&rgb, Some(&[255, 0, 0, 255, 255])), 1.0 / 3.0);
        assert_eq!(saturated_share(&rgb, Some(&[0; 5])), 0.0);
    }
}

