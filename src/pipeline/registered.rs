//! A run's registration into its results folder: each view registered and noted in its
//! `report.json` entry, and at the end the loop closed, the final poses written, the model
//! merged and cleaned, the surface fused into `mesh.ply`, the axis estimated, and all of it
//! scored against ground truth where the recording has it. Shared by `spinscan replay` and
//! the daemon's live scans, around [`ResultsWriter`].

use std::path::Path;
use std::time::Instant;

use nalgebra::Isometry3;
use serde_json::{json, Value};

use super::results::{ResultsError, ResultsWriter};
use super::View;
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

/// Registers one view and notes how into its `report.json` entry; the ICP fitness and RMSE
/// when ICP ran (for the assistant's self-correction). A view that cannot be registered is
/// noted and skipped, not fatal.
pub fn register_view(reg: &mut Registrar, frame: &StereoFrame, view: &View, entry: &mut Value) -> Option<(f64, f64)> {
    let seq = frame.seq;
    match reg.add_view(seq, frame.table_deg, view.registration_cloud()) {
        Ok(r) => {
            let disparity = view.registration_disparity();
            let image = TrackImage { rgb: &view.left_rgb, disparity: disparity.values(), width: disparity.width, height: disparity.height };
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
    // The views come after the last match: the fusion may take every thread of the pool it
    // runs on (the daemon's registration pool, below the matchers' priority).
    if let Some(t) = tsdf.as_mut() {
        t.set_threads(0);
    }
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
            (PointCloud { points: c.points[..n].to_vec(), colors: c.colors[..n].to_vec(), normals: c.normals.as_ref().map(|v| v[..n].to_vec()), rim_px: None }, n, "fused surface")
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
            // The texture tracks' own turn against the table's and the chain's (a fitted axis and tracks).
            "turn_check": f.turn_check.as_ref().map(|c| json!({
                "table_deg": c.table_deg, "registered_deg": c.registered_deg, "tracked_deg": c.tracked_deg, "tracked_sigma_deg": c.tracked_sigma_deg,
                "rms_from_table_deg": c.rms_from_table_deg, "rms_from_registered_deg": c.rms_from_registered_deg,
                "tracks_follow": c.tracks_follow, "sides_with_table": c.sides_with_table, "warning": c.warning, "applied": c.applied,
                "table_scale": c.table_scale, "scaled_rms_deg": c.scaled_rms_deg,
            })),
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
        "pose_source": if reg.turntable_fit().is_some_and(|f| f.applied) { "turntable" } else if reg.tracked_turn().is_some_and(|t| t.applied) || reg.turntable_fit().and_then(|f| f.turn_check.as_ref()).is_some_and(|c| c.applied) { "tracks" } else { "registration" },
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
