//! The results folder of a run or a scan (`shared/spec/recording-format.md`): `manifest.json`
//! rewritten after every frame, `views/`, `disparity/`, `poses.jsonl`, `model.ply`,
//! `turntable_estimated.yaml` and `report.json`, with the registration of each view noted in
//! its entry and the scores against ground truth where the recording has it. One writer for
//! `spinscan replay` and the daemon's live scans alike.

use std::path::{Path, PathBuf};
use std::time::Instant;

use nalgebra::Isometry3;
use serde_json::{json, Value};

use super::View;
use crate::assist::AssistParams;
use crate::cloud::PointCloud;
use crate::fuse::{FuseParams, MeshStats, Tsdf};
use crate::hw::StereoFrame;
use crate::io;
use crate::recording::TurntableAxis;
use crate::register::denoise::{keep_mask, DenoiseParams};
use crate::register::posestore::ViewPose;
use crate::register::ring::{LoopClosure, Registrar};
use crate::register::surface::{quantile, Surface};
use crate::register::tracks::TrackImage;
use crate::register::voxel::VoxelModel;
use crate::segment::{edge_share, no_screen, object_on_edge, plain_backdrop, KeySource, KeyUsed, EDGE_WARN_SHARE};
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

/// How the final model is merged from the registered views.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelOptions {
    /// Voxel side of `model.ply`, mm (0 is taken as the default, 1 mm).
    pub voxel_mm: f64,
    /// Isolated-point removal on the model (None: keep every voxel).
    pub denoise: Option<DenoiseParams>,
    /// The fused surface, `mesh.ply` (None: no mesh).
    pub mesh: Option<FuseParams>,
}

impl Default for ModelOptions {
    /// A 1 mm model cleaned with the default thresholds.
    fn default() -> Self {
        ModelOptions { voxel_mm: 1.0, denoise: Some(DenoiseParams::default()), mesh: Some(FuseParams::default()) }
    }
}

/// What a run can compare its registration with, and seed it from.
#[derive(Debug, Clone, Default)]
pub struct RegistrationInputs {
    /// The recording's calibrated axis (`turntable.yaml`).
    pub calibrated_axis: Option<TurntableAxis>,
    /// `gt/poses.jsonl`: cam_from_obj per seq.
    pub gt_poses: Option<Vec<(u64, Isometry3<f64>)>>,
    /// `gt/mesh.ply`, the object's surface in its own frame (read once, shared with the
    /// disparities' truth: [`crate::pipeline::truth::GtDisparities::mesh`]).
    pub gt_mesh: Option<std::sync::Arc<crate::cloud::Mesh>>,
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

/// A frame's `segmentation` entry in `report.json`: which key it was keyed by (the colour
/// `given`, one `found` in the frame's border, a plain `backdrop` keyed by texture where no
/// coloured screen was found, or the `default` colour where neither was), its chromaticity,
/// the share of the border it keyed out where it was found, the texture threshold of a
/// backdrop, and the share of the image's edge the mask kept as object
/// (`segment::edge_share`).
fn segmentation_entry(k: &KeyUsed, edge: f32) -> Value {
    let (key, share, threshold) = match k.source {
        KeySource::Given => ("given", None, None),
        KeySource::Found { border_share } => ("found", Some(border_share), None),
        KeySource::Backdrop { border_share, threshold } => ("backdrop", Some(border_share), Some(threshold)),
        KeySource::NotFound => ("default", None, None),
    };
    json!({"key": key, "chromaticity": [k.chroma.0, k.chroma.1], "border_share": share, "texture_threshold": threshold, "edge_object_share": edge})
}

/// `report.json`'s `matching`: the matcher and search the results were made with, so that a
/// results folder says how to make it again. `assist` is `None` where no frame is assisted
/// (`--assist none`, or no registration to take the motion from).
pub fn matching_entry(p: &crate::stereo::MatchParams, assist: Option<&AssistParams>) -> Value {
    let mut m = json!({
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
    m
}

/// The results folder, kept consistent on disk after every frame.
pub struct ResultsWriter {
    dir: PathBuf,
    source: String,
    frames: Vec<Value>,
    disparity_sign: i32,
    started: Instant,
    registration: Option<Value>,
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
            "table_deg": frame.table_deg,
            "t_left_ns": frame.t_left_ns,
            "skew_ns": frame.t_right_ns as i64 - frame.t_left_ns as i64,
        });
        if let (Some(k), Some(mask)) = (&view.key, &view.mask) {
            entry["segmentation"] = segmentation_entry(k, edge_share(mask, view.disparity.width, view.disparity.height));
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
        if first(&|f| f["segmentation"]["key"] == json!("default")) {
            tracing::warn!("frame seq {}: {}; give the screen's colour (`--key-color R,G,B`, the daemon's `[matching] key_color`) or a background plate (`--plate`), or turn segmentation off", entry["seq"], no_screen());
        }
        if first(&|f| f["segmentation"]["key"] == json!("backdrop")) {
            tracing::info!("frame seq {}: {}", entry["seq"], plain_backdrop(share("texture_threshold")));
        }
        if first(&|f| f["segmentation"]["edge_object_share"].as_f64().is_some_and(|s| s >= EDGE_WARN_SHARE as f64)) {
            tracing::warn!("frame seq {}: {}; cover it in the screen's colour, or give a background plate (`--plate`, the daemon's `[matching] plate`)", entry["seq"], object_on_edge(share("edge_object_share")));
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

/// Registers one view and notes how into its `report.json` entry; the ICP fitness and RMSE
/// when ICP ran (for the assistant's self-correction). A view that cannot be registered is
/// noted and skipped, not fatal.
pub fn register_view(reg: &mut Registrar, frame: &StereoFrame, view: &View, entry: &mut Value) -> Option<(f64, f64)> {
    let seq = frame.seq;
    match reg.add_view(seq, frame.table_deg, &view.cloud) {
        Ok(r) => {
            let image = TrackImage { rgb: &view.left_rgb, disparity: view.disparity.values(), width: view.disparity.width, height: view.disparity.height };
            let track_ms = reg.track_view(seq, image);
            entry["register_ms"] = json!(r.register_ms);
            entry["track_ms"] = json!(track_ms);
            entry["publish_ms"] = json!(r.publish_ms);
            entry["register_split_ms"] = json!(r.split);
            // The pose as published when the view was registered (what the matchers read);
            // poses.jsonl has the final one.
            entry["live_first_from_view"] = json!(crate::register::to_rows(&r.first_from_view));
            entry["seed"] = json!(r.seed);
            if let Some(icp) = &r.icp {
                entry["icp_fitness"] = json!(icp.fitness);
                entry["icp_rmse_mm"] = json!(icp.rmse);
                entry["icp_iterations"] = json!(icp.iterations);
                entry["icp_conditioning"] = json!(icp.conditioning);
            }
            if let Some(b) = &r.block {
                entry["block_fitness"] = json!(b.fitness);
                entry["block_correction_deg"] = json!(b.transform.rotation.angle().to_degrees());
            }
            for w in &r.warnings {
                tracing::warn!("{w}");
            }
            for n in &r.notes {
                tracing::info!("{n}");
            }
            if !r.notes.is_empty() {
                entry["notes"] = json!(r.notes);
            }
            if !r.warnings.is_empty() {
                entry["warnings"] = json!(r.warnings);
            }
            r.icp.as_ref().map(|icp| (icp.fitness, icp.rmse))
        }
        Err(e) => {
            tracing::warn!("frame seq {seq}: not registered: {e}");
            entry["register_error"] = json!(e.to_string());
            None
        }
    }
}

/// Closes the loop, writes the final poses, merges and cleans the model from `views/`,
/// writes the estimated axis, and scores against ground truth where the recording has it.
pub fn finish_registration(reg: &mut Registrar, results: &mut ResultsWriter, opts: &ModelOptions, inputs: &RegistrationInputs) -> Result<Value, ResultsError> {
    let closure = reg.finish().map_err(|e| ResultsError::LoopClosure { seq: reg.poses().last().map_or(0, |p| p.seq), what: e.to_string() })?;
    let poses: Vec<ViewPose> = reg.poses().to_vec();
    results.write_poses(&poses)?;

    let voxel = if opts.voxel_mm > 0.0 { opts.voxel_mm } else { 1.0 };
    let mut model = VoxelModel::new(voxel);
    // Scored against the truth as the views are read back for the model (read once).
    let truth = inputs.gt_poses.as_deref().and_then(|gt| Truth::new(gt, &poses, inputs.gt_mesh.as_deref()));
    let mut own = Vec::new();
    // The fused surface, integrated as the views are read (docs/meshing.md).
    let mut tsdf = opts.mesh.clone().map(Tsdf::new).transpose().map_err(|e| ResultsError::Mesh(format!("settings: {e}")))?;
    let fuse_start = Instant::now();
    // The views' points placed by their true poses: samples of the visible true surface.
    let mut seen = Vec::new();
    for p in &poses {
        let path = results.dir.join("views").join(format!("{:06}.ply", p.seq));
        let view = io::ply::read_ply(&path).map_err(|e| ResultsError::Output { path: path.clone(), what: format!("cannot read the view back: {e}") })?;
        model.add(&view.cloud, &p.first_from_view);
        if let Some(t) = tsdf.as_mut() {
            t.integrate(&view.cloud, &p.first_from_view);
        }
        if let Some(t) = &truth {
            let d = t.view_samples(p.seq, &view.cloud.points, &mut own, &mut seen);
            // The view's own distance to the true surface, in its frame's entry: what the
            // stereo gives, whatever the registration.
            if let (false, Some(f)) = (d.is_empty(), results.frames.iter_mut().find(|f| f["seq"] == json!(p.seq))) {
                f["gt_view_distance_mm"] = json!({"median": quantile(&d, 0.5), "p95": quantile(&d, 0.95), "points": d.len()});
            }
        }
    }
    let fuse_ms = fuse_start.elapsed().as_secs_f64() * 1e3;
    let built = tsdf.as_ref().map(|t| {
        let start = Instant::now();
        let (mesh, stats) = t.mesh();
        (mesh, stats, start.elapsed().as_secs_f64() * 1e3)
    });
    // The model: the fused surface's measured vertices where there is a fused surface (each
    // view weighed in, noise averaged out: docs/meshing.md), else the voxel-merged points
    // cleaned by the paper's isolated-point removal.
    let (cloud, voxels, source) = match &built {
        Some((mesh, stats, _)) if stats.measured_vertices > 0 => {
            let n = stats.measured_vertices;
            let c = &mesh.cloud;
            (PointCloud { points: c.points[..n].to_vec(), colors: c.colors[..n].to_vec(), normals: c.normals.as_ref().map(|v| v[..n].to_vec()) }, n, "fused surface")
        }
        _ => {
            let (mut cloud, _) = model.to_cloud();
            let voxels = cloud.len();
            if let Some(d) = &opts.denoise {
                let keep = keep_mask(&cloud.points, d);
                let mut k = keep.iter();
                cloud.points.retain(|_| *k.next().unwrap());
                let mut k = keep.iter();
                cloud.colors.retain(|_| *k.next().unwrap());
            }
            (cloud, voxels, "voxel-merged points")
        }
    };
    let model_path = results.dir.join("model.ply");
    io::ply::write_ply(&model_path, &cloud).map_err(|e| ResultsError::Output { path: model_path, what: e.to_string() })?;
    // (After the model: a mesh that cannot be written loses nothing else.)
    let mesh = match (&tsdf, built) {
        (Some(t), Some((mesh, stats, mesh_ms))) => Some(write_mesh(t, mesh, &stats, mesh_ms, &results.dir.join("mesh.ply"), fuse_ms)?),
        _ => None,
    };

    // The axis fitted to the views' points (also when the texture tracks' axis replaced it).
    let points_fit = reg.points_axis().or(reg.refined_axis().filter(|f| f.tracks.is_none()));
    let mut section = json!({
        "views": poses.len(),
        "model_points": cloud.len(),
        "model_source": source,
        "model_voxels_before_denoise": voxels,
        "model_voxel_mm": voxel,
        "turned_deg": reg.turned_deg(),
        "loop_closure": closure.as_ref().map(loop_json),
        "turntable_fit": reg.turntable_fit().map(|f| json!({
            "steps": f.steps, "rms_deviation_deg": f.rms_deviation_deg, "max_deviation_deg": f.max_deviation_deg, "worst_seq": f.worst_seq,
            "applied": f.applied, "axis_source": f.axis_source, "kept_because": f.kept_because,
            "axis_sigma_deg": f.refined.as_ref().map(|r| r.sigma_dir_deg), "axis_point_sigma_mm": f.refined.as_ref().map(|r| r.sigma_point_mm),
            "axis_fit_rms_mm": points_fit.map(|r| r.rms_mm), "axis_fit_pairs": points_fit.map(|r| r.pairs),
            "axis_fit_tracks": f.refined.as_ref().and_then(|r| r.tracks).map(|t| t.tracks), "axis_fit_rms_px": f.refined.as_ref().and_then(|r| r.tracks).map(|t| t.rms_px),
            "turntable_score_mm": f.scores.map(|s| s.0), "registered_score_mm": f.scores.map(|s| s.1),
        })),
        // A scan without the table's angles: the turn fitted to the texture tracks.
        "tracked_turn": match reg.tracked_turn() {
            Some(t) => json!({
                "applied": t.applied, "kept_because": t.kept_because, "chained_deg": t.chained_deg, "fitted_deg": t.fitted_deg, "max_change_deg": t.max_change_deg,
                "tracks": t.figures.tracks, "observations": t.figures.observations, "fit_rms_px": t.figures.rms_px, "worst_view_px": t.figures.worst_view_px,
            }),
            None if poses.iter().all(|p| p.table_deg.is_none()) => json!({"applied": false, "kept_because": reg.texture_note()}),
            None => Value::Null,
        },
        "pose_source": if reg.turntable_fit().is_some_and(|f| f.applied) { "turntable" } else if reg.tracked_turn().is_some_and(|t| t.applied) { "tracks" } else { "registration" },
    });
    // The axis fitted to every view when there is one, else the one estimated from the poses.
    let axis = match (reg.refined_axis(), reg.estimated_axis()) {
        (Some(f), _) => Some((f.point, f.dir, match &f.tracks {
            Some(t) => {
                let mut about = json!({"method": "tracked", "sigma_deg": f.sigma_dir_deg, "point_sigma_mm": f.sigma_point_mm, "tracks": t.tracks, "observations": t.observations, "fit_rms_px": t.rms_px, "worst_view_px": t.worst_view_px, "views_unconfirmed": t.views_unconfirmed});
                if let Some(p) = points_fit {
                    about["points_fit"] = json!({"dir": p.dir.as_slice(), "point_mm": p.point.as_slice(), "sigma_deg": p.sigma_dir_deg, "fit_rms_mm": p.rms_mm, "pairs": p.pairs, "deg_from_tracked": p.dir.angle(&f.dir).to_degrees()});
                }
                about
            }
            None => json!({"method": "refined", "sigma_deg": f.sigma_dir_deg, "point_sigma_mm": f.sigma_point_mm, "fit_rms_mm": f.rms_mm, "pairs": f.pairs, "texture_note": reg.texture_note()}),
        })),
        (None, Some(a)) => Some((a.point, a.dir, json!({"method": "poses", "rms_axis_deg": a.rms_axis_deg, "rms_offset_mm": a.rms_offset, "views": a.views}))),
        (None, None) => None,
    };
    if let Some((point, dir, mut about)) = axis {
        let est = TurntableAxis { axis_point_mm: point.into(), axis_dir: dir.into(), source: "estimated".into() };
        let path = results.dir.join("turntable_estimated.yaml");
        io::write_atomic(&path, est.to_yaml().as_bytes()).map_err(|e| ResultsError::Output { path, what: e.to_string() })?;
        about["point_mm"] = json!(est.axis_point_mm);
        about["dir"] = json!(est.axis_dir);
        section["axis"] = about;
    }
    if let Some((mesh, about)) = &mesh {
        section["mesh"] = about.clone();
        if let Some(t) = &truth {
            score_mesh(&mut section["mesh"], t, mesh, &own, &seen)?;
        }
    }
    if let Some(t) = &truth {
        score_registration(&mut section, results, &poses, t, &cloud.points, &own)?;
    }
    results.registration = Some(section.clone());
    Ok(section)
}

fn loop_json(c: &LoopClosure) -> Value {
    json!({"views": c.views, "error_deg": c.error_deg, "error_mm": c.error_translation, "fitness": c.icp.fitness, "rmse_mm": c.icp.rmse})
}

/// The ground truth of a recording placed in the first view's frame: the true poses, and
/// the true surface (when `gt/mesh.ply` is there; a mesh whose triangles do not make a
/// surface is an error when the scores are written, after the model).
struct Truth<'a> {
    gt: &'a [(u64, Isometry3<f64>)],
    /// `cam_from_obj` of the first view.
    first: Isometry3<f64>,
    surface: Option<Result<Surface, ResultsError>>,
}

impl<'a> Truth<'a> {
    /// None when the first view has no true pose.
    fn new(gt: &'a [(u64, Isometry3<f64>)], poses: &[ViewPose], mesh: Option<&crate::cloud::Mesh>) -> Option<Truth<'a>> {
        let first = poses.first().and_then(|p| true_pose(gt, p.seq))?;
        let surface = mesh.map(|mesh| Surface::new(mesh, &first).map_err(|e| ResultsError::SideFile(format!("ground truth gt/mesh.ply: {e}"))));
        Some(Truth { gt, first, surface })
    }

    fn cam_from_obj(&self, seq: u64) -> Option<Isometry3<f64>> {
        true_pose(self.gt, seq)
    }

    /// View `seq`'s points placed by its true pose: the distances to the true surface of
    /// every one of them (the view's own error, what the stereo gives whatever the
    /// registration), returned; at most `VIEW_SAMPLE` of those distances into `own`, for the
    /// views' error over the scan; and at most `SEEN_SAMPLE` of the points, as samples of the
    /// visible true surface for the mesh's completeness, into `seen`. (A sample of 5 000
    /// points moved a view's median by up to 0.005 mm with the points it happened to take:
    /// more than some views of two matchers differ by.)
    fn view_samples(&self, seq: u64, points: &[[f32; 3]], own: &mut Vec<f64>, seen: &mut Vec<[f32; 3]>) -> Vec<f64> {
        const VIEW_SAMPLE: usize = 5000;
        const SEEN_SAMPLE: usize = 2000;
        let (Some(Ok(surface)), Some(cam_from_obj)) = (&self.surface, self.cam_from_obj(seq)) else { return Vec::new() };
        let placed = self.first * cam_from_obj.inverse();
        let all: Vec<[f32; 3]> = points.iter().map(|p| crate::register::apply(&placed, p)).collect();
        let d = surface.distances(&all);
        own.extend(crate::register::subsample_indices(d.len(), VIEW_SAMPLE).into_iter().map(|i| d[i]));
        seen.extend(crate::register::subsample_indices(all.len(), SEEN_SAMPLE).into_iter().map(|i| all[i]));
        d
    }
}

/// The fused field's mesh written to `path`; its figures for the report.
fn write_mesh(tsdf: &Tsdf, mesh: crate::cloud::Mesh, stats: &MeshStats, mesh_ms: f64, path: &Path, fuse_ms: f64) -> Result<(crate::cloud::Mesh, Value), ResultsError> {
    io::mesh::write_mesh(path, &mesh).map_err(|e| ResultsError::Output { path: path.to_path_buf(), what: e.to_string() })?;
    let mut about = super::mesh::mesh_json(tsdf, stats, mesh_ms);
    if let Some(w) = about["warning"].as_str() {
        tracing::warn!("mesh.ply: {w}");
    }
    about["file"] = json!("mesh.ply");
    // (Reading the views back, the model's merge and the views' scores included.)
    about["read_and_fuse_ms"] = json!(fuse_ms);
    Ok((mesh, about))
}

/// The mesh against the truth: its vertices' distances to the true surface (and against
/// the views' own), and completeness — the share of the visible true surface (sampled by
/// the views' points placed by their true poses) within 1.5 mm of the mesh.
fn score_mesh(about: &mut Value, truth: &Truth, mesh: &crate::cloud::Mesh, own: &[f64], seen: &[[f32; 3]]) -> Result<(), ResultsError> {
    let Some(Ok(surface)) = &truth.surface else { return Ok(()) };
    let d = surface.distances(&mesh.cloud.points);
    about["gt_distance_mm"] = json!({"median": quantile(&d, 0.5), "p95": quantile(&d, 0.95), "vertices": d.len()});
    if !own.is_empty() {
        about["gt_mesh_to_view_ratio"] = json!({"median": ratio(quantile(&d, 0.5), quantile(own, 0.5)), "p95": ratio(quantile(&d, 0.95), quantile(own, 0.95))});
    }
    if !seen.is_empty() && !mesh.triangles.is_empty() {
        let ours = Surface::new(mesh, &Isometry3::identity()).map_err(|e| ResultsError::Mesh(format!("scoring it: {e}")))?;
        let near = ours.distances(seen).iter().filter(|&&d| d <= 1.5).count();
        about["gt_completeness"] = json!({"within_mm": 1.5, "share": near as f64 / seen.len() as f64, "samples": seen.len()});
    }
    Ok(())
}

/// `m / v` where both are known (a distance against the views' own).
fn ratio(m: Option<f64>, v: Option<f64>) -> Option<f64> {
    m.zip(v).map(|(m, v)| m / v.max(1e-12))
}

/// View `seq`'s `cam_from_obj` in `gt/poses.jsonl`.
fn true_pose(gt: &[(u64, Isometry3<f64>)], seq: u64) -> Option<Isometry3<f64>> {
    gt.iter().find(|g| g.0 == seq).map(|g| g.1)
}

/// Pose error of every view against `gt/poses.jsonl`, and the model's and the views' own
/// (`own`, from [`Truth::view_samples`]) distance to the placed `gt/mesh.ply`, into the
/// report.
fn score_registration(section: &mut Value, results: &mut ResultsWriter, poses: &[ViewPose], truth: &Truth, model: &[[f32; 3]], own: &[f64]) -> Result<(), ResultsError> {
    let mut last = None;
    let (mut live, mut refined) = (Vec::new(), Vec::new());
    let error = |pose: &Isometry3<f64>, true_pose: &Isometry3<f64>| ((pose.inverse() * true_pose).rotation.angle().to_degrees(), (pose.translation.vector - true_pose.translation.vector).norm());
    for p in poses {
        let Some(cam_from_obj) = truth.cam_from_obj(p.seq) else { continue };
        let true_pose = truth.first * cam_from_obj.inverse();
        let (deg, mm) = error(&p.first_from_view, &true_pose);
        refined.push(deg);
        if let Some(f) = results.frames.iter_mut().find(|f| f["seq"] == json!(p.seq)) {
            f["gt_pose_err_deg"] = json!(deg);
            f["gt_pose_err_mm"] = json!(mm);
            let published = serde_json::from_value::<crate::register::Rows4>(f["live_first_from_view"].clone()).ok().and_then(|rows| crate::register::from_rows(&rows, 1e-6).ok());
            if let Some(pose) = published {
                let (deg, mm) = error(&pose, &true_pose);
                f["gt_live_pose_err_deg"] = json!(deg);
                f["gt_live_pose_err_mm"] = json!(mm);
                live.push(deg);
            }
        }
        last = Some((p.seq, deg, mm));
    }
    if let Some((seq, deg, mm)) = last {
        section["gt_last_view"] = json!({"seq": seq, "pose_err_deg": deg, "pose_err_mm": mm});
    }
    // Every view's rotation error: as published while views came (`live`), and final.
    let summary = |v: &[f64]| (!v.is_empty()).then(|| json!({"median": quantile(v, 0.5), "max": v.iter().cloned().fold(0.0, f64::max), "views": v.len()}));
    section["gt_pose_err_deg"] = json!({"live": summary(&live), "final": summary(&refined)});
    match &truth.surface {
        // (SideFile displays its message alone: the same words.)
        Some(Err(e)) => return Err(ResultsError::SideFile(e.to_string())),
        Some(Ok(surface)) => {
            let d = surface.distances(model);
            section["gt_model_distance_mm"] = json!({"median": quantile(&d, 0.5), "p95": quantile(&d, 0.95), "points": d.len()});
            if !own.is_empty() {
                let (median, p95) = (quantile(own, 0.5), quantile(own, 0.95));
                section["gt_view_distance_mm"] = json!({"median": median, "p95": p95, "points": own.len()});
                section["gt_model_to_view_ratio"] = json!({"median": ratio(quantile(&d, 0.5), median), "p95": ratio(quantile(&d, 0.95), p95)});
            }
        }
        None => {}
    }
    Ok(())
}
