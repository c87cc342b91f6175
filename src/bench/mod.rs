//! `spinscan bench table1`: the paper's Table 1 (matching time per frame, without
//! registration and with it at each weighting factor w), plus the predicted mode and what the
//! paper only showed as pictures — accuracy, valid fraction, search width — and a Fig. 4-style
//! image.
//!
//! Every row matches the same prepared frames (rectified, segmented once) with the same
//! matcher parameters; a row differs only in the intervals. A row's time for a frame is
//! interval construction + matching (left–right check included, and a full-range redo when
//! self-correction rejects the assisted result), the median of `repeat` runs of that frame
//! from the same state. The motion comes from spinscan's own registration of the row's own
//! views (seeded by `table_deg`); ground truth is read only to score. As in a scan, the
//! first frame's probe compares the cameras' contrast and every right image is scaled where
//! they differ (`stereo::gain`); the range is not fitted (every row searches the one set).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use nalgebra::{Isometry3, Point3};
use serde_json::{json, Value};

use crate::assist::{AssistMode, AssistParams, Assistant, Granularity};
use crate::pipeline::truth::{GtDisparities, GtSource};
use crate::pipeline::{Assist, Pipeline, PipelineError, PipelineOptions, Prepared};
use crate::recording::{Recording, TurntableAxis};
use crate::register::posestore::{PoseSnapshot, PoseStore};
use crate::register::ring::{Registrar, RegistrationParams};
use crate::register::surface::{quantile, Surface};
use crate::segment::{self, KeySource};
use crate::stereo::{DisparityMap, MatchParams, Method};

mod report;
use report::row_label;

/// What to run.
#[derive(Debug, Clone)]
pub struct Table1Options {
    pub pipeline: PipelineOptions,
    /// The matchers compared: every row runs once per entry (`bench table1 --method
    /// bm,sgm`); empty = `pipeline.matching` alone.
    pub matchers: Vec<MatchParams>,
    /// The paper rows' weighting factors.
    pub weights: Vec<f64>,
    /// Also a row for the predicted mode.
    pub predicted: bool,
    /// Use at most this many frames.
    pub max_frames: Option<usize>,
    /// Runs per frame and row; the median is reported.
    pub repeat: usize,
    /// Hide the newest `lag` registered views from the matcher (as a matcher running ahead
    /// of registration would see the store).
    pub lag: u64,
    /// Knobs of the assisted modes (the mode itself is set per row).
    pub assist: AssistParams,
    /// The assisted rows run once per granularity listed (`--assist-granularity
    /// pixel,tile,plane`); empty = `assist.granularity` alone.
    pub granularities: Vec<Granularity>,
    pub registration: RegistrationParams,
    /// Frame (index) shown in the figure.
    pub fig_frame: Option<usize>,
    /// An image of the empty scene (raw left camera, RGB) that keys out what it shows, as
    /// `replay --plate` does.
    pub plate: Option<Vec<u8>>,
}

impl Default for Table1Options {
    fn default() -> Self {
        Table1Options {
            pipeline: PipelineOptions::default(),
            matchers: Vec::new(),
            weights: vec![0.6, 0.8, 1.0, 2.0],
            predicted: true,
            max_frames: None,
            repeat: 3,
            lag: 0,
            assist: AssistParams::default(),
            granularities: Vec::new(),
            registration: RegistrationParams::default(),
            fig_frame: None,
            plate: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("{0}")]
    Recording(String),
    /// A rig's pipeline cannot be set up (parameters, the calibration against the frames).
    #[error("{0}")]
    Setup(PipelineError),
    #[error("frame seq {seq}: {source}")]
    Pipeline { seq: u64, source: PipelineError },
    #[error("{0}")]
    Output(String),
}

/// One row of the table.
#[derive(Debug, Clone)]
pub struct Row {
    pub method: Method,
    /// Whether the matcher seeds its wide searches from the half-size pair
    /// (`MatchParams::coarse_to_fine`): the row without assistance is then not a search of
    /// every disparity.
    pub coarse_to_fine: bool,
    pub mode: AssistMode,
    /// How finely the assisted rows set their ranges (None: no assistance).
    pub granularity: Option<Granularity>,
    pub frame_ms: Vec<f64>,
    pub interval_ms: Vec<f64>,
    /// The part of `interval_ms` spent checking and keeping the frame for the next.
    pub accept_ms: Vec<f64>,
    pub match_ms: Vec<f64>,
    pub lr_check_ms: Vec<f64>,
    pub prefilter_ms: Vec<f64>,
    /// Matching time less the fixed per-pixel stages (prefilter, speckle) per evaluated
    /// (pixel, disparity) pair, ns; one per frame.
    pub ns_per_pair: Vec<f64>,
    pub bad2: Vec<f64>,
    pub lr_consistency: Vec<f64>,
    pub err_mm: Vec<f64>,
    pub valid_fraction: Vec<f64>,
    pub search_px: Vec<f64>,
    /// Frames searched over the full range, with why (first frames, self-correction).
    pub full_range: Vec<(u64, String)>,
    /// Per frame: pixels given a single circle (or prediction), a union (or filled hole),
    /// and the full range because nothing reached them.
    pub single_px: Vec<usize>,
    pub union_px: Vec<usize>,
    pub filled_px: Vec<usize>,
    pub uncovered_px: Vec<usize>,
    /// Per frame: matches dropped at an end of the disparity range, and their share of the
    /// searched pixels (`MatchStats::range_edge`).
    pub range_edge_px: Vec<usize>,
    pub range_edge_share: Vec<f64>,
    /// The disparity map of the figure's frame.
    pub fig: Option<DisparityMap>,
}

fn median(v: &[f64]) -> Option<f64> {
    let mut v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) })
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

impl Row {
    fn new(matcher: &MatchParams, mode: AssistMode, granularity: Granularity) -> Row {
        Row {
            method: matcher.method,
            coarse_to_fine: matcher.coarse_to_fine,
            mode,
            granularity: (mode != AssistMode::None).then_some(granularity.resolve(mode)),
            frame_ms: vec![],
            interval_ms: vec![],
            accept_ms: vec![],
            match_ms: vec![],
            lr_check_ms: vec![],
            prefilter_ms: vec![],
            ns_per_pair: vec![],
            bad2: vec![],
            lr_consistency: vec![],
            err_mm: vec![],
            valid_fraction: vec![],
            search_px: vec![],
            full_range: vec![],
            single_px: vec![],
            union_px: vec![],
            filled_px: vec![],
            uncovered_px: vec![],
            range_edge_px: vec![],
            range_edge_share: vec![],
            fig: None,
        }
    }

    /// The figures of one matched frame (all but its time, accuracy and figure).
    fn record(&mut self, m: &crate::pipeline::AssistedMatch) {
        let o = &m.outcome;
        self.single_px.push(o.single_px);
        self.union_px.push(o.union_px);
        self.filled_px.push(o.filled_px);
        self.uncovered_px.push(o.uncovered_px);
        self.interval_ms.push(o.interval_ms);
        self.accept_ms.push(o.accept_ms);
        self.match_ms.push(o.match_ms);
        let (mut evaluated, mut searched, mut fixed_ns, mut lr_ns) = (0u64, 0usize, 0u64, 0u64);
        for s in [Some(m.stats), o.rejected].into_iter().flatten() {
            evaluated += s.evaluated;
            searched += s.searched;
            fixed_ns += s.prefilter_ns + s.speckle_ns;
            lr_ns += s.lr_check_ns;
        }
        self.lr_check_ms.push(lr_ns as f64 / 1e6);
        self.prefilter_ms.push(m.stats.prefilter_ns as f64 / 1e6);
        self.ns_per_pair.push(((o.match_ms * 1e6 - fixed_ns as f64) / evaluated.max(1) as f64).max(0.0));
        self.search_px.push(evaluated as f64 / searched.max(1) as f64);
        self.valid_fraction.push(m.stats.valid_fraction());
        self.lr_consistency.push(m.stats.lr_consistency());
        self.range_edge_px.push(m.stats.range_edge);
        self.range_edge_share.push(m.stats.range_edge_share());
        if let Some(why) = o.fallback.clone().or_else(|| o.full_range.clone()) {
            self.full_range.push((m.seq, why));
        }
    }

    pub fn median_ms(&self) -> f64 {
        median(&self.frame_ms).unwrap_or(f64::NAN)
    }

    /// Percent of ground-truth pixels missing or off by more than 2 px, over all frames.
    pub fn bad2(&self) -> Option<f64> {
        mean(&self.bad2)
    }

    pub fn to_json(&self) -> Value {
        json!({
            "method": self.method.name(),
            "coarse_to_fine": self.coarse_to_fine,
            "mode": self.mode.name(),
            "w": self.mode.w(),
            "granularity": self.granularity.map(|g| g.name()),
            "frame_ms": self.frame_ms,
            "median_ms": self.median_ms(),
            "bad2": self.bad2(),
            "lr_consistency": mean(&self.lr_consistency),
            "median_err_mm": median(&self.err_mm),
            "valid_fraction": mean(&self.valid_fraction),
            "mean_search_px": mean(&self.search_px),
            "interval_ms": self.interval_ms,
            "match_ms": self.match_ms,
            "lr_check_ms": self.lr_check_ms,
            "prefilter_ms": self.prefilter_ms,
            "median_interval_ms": median(&self.interval_ms),
            "accept_ms": self.accept_ms,
            "median_accept_ms": median(&self.accept_ms),
            "median_lr_check_ms": median(&self.lr_check_ms),
            "median_prefilter_ms": median(&self.prefilter_ms),
            "median_ns_per_pair": median(&self.ns_per_pair),
            "single_px": self.single_px,
            "union_px": self.union_px,
            "filled_px": self.filled_px,
            "uncovered_px": self.uncovered_px,
            "range_edge_px": self.range_edge_px,
            "frame_bad2": self.bad2,
            "frame_err_mm": self.err_mm,
            "full_range_frames": self.full_range.iter().map(|(s, why)| json!({"seq": s, "why": why})).collect::<Vec<_>>(),
        })
    }
}

/// The whole benchmark.
pub struct Table1 {
    pub recording: PathBuf,
    pub frames: Vec<u64>,
    pub rows: Vec<Row>,
    pub size: (usize, usize),
    pub range: (i32, i32),
    pub threads: usize,
    pub repeat: usize,
    pub lag: u64,
    pub fig_frame: usize,
    pub fig_left: Vec<u8>,
    /// Per frame: the (first) matcher with one disparity at every foreground pixel, ms.
    pub floor_ms: Vec<f64>,
    /// The same per matcher, in the order of `Table1Options::matchers`.
    pub floor_ms_by_method: Vec<(Method, Vec<f64>)>,
    /// Frames (seq) whose border showed no coloured screen, keyed by the default colour
    /// (`segment::KeySource::NotFound`).
    pub screen_not_found: Vec<u64>,
    /// Frames (seq) whose border showed no coloured screen but a plain backdrop, keyed by its
    /// lack of texture (`segment::KeySource::Backdrop`), with the texture threshold.
    pub backdrop_keyed: Vec<(u64, f32)>,
    /// Frames (seq) whose mask keeps at least `segment::EDGE_WARN_SHARE` of the image's edge
    /// as object, with that share.
    pub object_on_edge: Vec<(u64, f32)>,
    /// Per frame, where its ground-truth disparity (bad2's) came from, if it has one.
    pub gt_disparity: Vec<Option<GtSource>>,
    /// The cameras' contrast ratio on the first frame (`stereo::gain`), where measured.
    pub contrast: Option<crate::stereo::gain::Contrast>,
}

struct Truth {
    disparity: Vec<Option<DisparityMap>>,
    /// Per frame, where `disparity` came from.
    disparity_source: Vec<Option<GtSource>>,
    /// obj_from_cam per frame, and the mesh in the object's frame.
    poses: Option<Vec<Option<Isometry3<f64>>>>,
    surface: Option<Surface>,
}

/// Runs the benchmark on a recording. `progress(row, frame)` after each frame.
pub fn table1(dir: &Path, opts: &Table1Options, progress: &mut dyn FnMut(&str, usize, usize)) -> Result<Table1, BenchError> {
    let rec = Recording::open(dir).map_err(|e| BenchError::Recording(e.to_string()))?;
    let n = opts.max_frames.map_or(rec.frames.len(), |m| m.min(rec.frames.len()));
    if n == 0 {
        return Err(BenchError::Recording(format!("{}: no frames to run", dir.display())));
    }
    if let Some(k) = opts.fig_frame.filter(|&k| k >= n) {
        return Err(BenchError::Recording(format!("the figure's frame {} lies past this run's last frame, {n} (ask for 1…{n})", k + 1)));
    }
    let matchers = if opts.matchers.is_empty() { vec![opts.pipeline.matching.clone()] } else { opts.matchers.clone() };
    // One pipeline per matcher (they share the rectification and the prepared frames).
    let mut pipes = Vec::new();
    for m in &matchers {
        let o = PipelineOptions { matching: m.clone(), ..opts.pipeline.clone() };
        pipes.push(Pipeline::new(&rec.calib, rec.image_size, o).map_err(BenchError::Setup)?);
    }
    let size = (rec.image_size.0 as usize, rec.image_size.1 as usize);
    if let Some(p) = opts.plate.as_ref().filter(|p| p.len() != size.0 * size.1 * 3) {
        return Err(BenchError::Recording(format!("the plate holds {} bytes; the recording's {}×{} RGB images take {}", p.len(), size.0, size.1, size.0 * size.1 * 3)));
    }
    let plate = opts.plate.as_deref().map(|p| pipes[0].rectify_plate(p));
    let params = pipes[0].matcher().params().clone();
    // The cameras' contrast, measured on the first frame as a scan measures it (the range is
    // not fitted: every row searches the one set); where they differ, every right image is
    // scaled as a scan scales it.
    let first = rec.load_frame(0).map_err(|e| BenchError::Recording(e.to_string()))?;
    let mut probed = pipes[0].prepare_frame(&first, true, plate.as_ref()).map_err(|e| BenchError::Recording(format!("frame seq {}: {e}", first.seq)))?;
    let contrast = crate::pipeline::range::probe(&pipes[0], &probed).map_err(|source| BenchError::Pipeline { seq: first.seq, source })?.and_then(|(_, c)| c);
    if let Some(c) = contrast.filter(crate::stereo::gain::Contrast::scales_right) {
        pipes.iter_mut().for_each(|p| p.set_right_gain(Some(c.ratio)));
        pipes[0].balance(&mut probed);
    }
    let mut probed = Some((first, probed));
    let range = (params.min_disparity, params.max_disparity());

    // Prepare every frame once: every row matches the same images and masks.
    let mut frames: Vec<(u64, Option<f64>, Prepared)> = Vec::with_capacity(n);
    let (mut screen_not_found, mut backdrop_keyed, mut object_on_edge) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..n {
        let (f, p) = match probed.take() {
            Some(first) => first,
            None => {
                let f = rec.load_frame(i).map_err(|e| BenchError::Recording(e.to_string()))?;
                let p = pipes[0].prepare_frame(&f, true, plate.as_ref()).map_err(|e| BenchError::Recording(format!("frame seq {}: {e}", f.seq)))?;
                (f, p)
            }
        };
        match p.key.map(|k| k.source) {
            Some(KeySource::NotFound) => screen_not_found.push(f.seq),
            Some(KeySource::Backdrop { threshold, .. }) => backdrop_keyed.push((f.seq, threshold)),
            _ => {}
        }
        let edge = p.mask.as_deref().map_or(0.0, |m| segment::edge_share(m, size.0, size.1));
        if edge >= segment::EDGE_WARN_SHARE {
            object_on_edge.push((f.seq, edge));
        }
        frames.push((f.seq, f.table_deg, p));
        progress("prepare", i + 1, n);
    }
    let truth = read_truth(&rec, &frames, &pipes[0].rect)?;

    let mut assisted: Vec<AssistMode> = opts.weights.iter().map(|&w| AssistMode::Paper { w }).collect();
    if opts.predicted {
        assisted.push(AssistMode::Predicted);
    }
    let grains = if opts.granularities.is_empty() { vec![opts.assist.granularity] } else { opts.granularities.clone() };
    let mut modes = vec![(AssistMode::None, opts.assist.granularity)];
    for &g in &grains {
        for &m in &assisted {
            // (`auto` and the granularity it means for the mode are the same row.)
            if !modes.iter().any(|&(m2, g2)| m2 == m && g2.resolve(m2) == g.resolve(m)) {
                modes.push((m, g));
            }
        }
    }
    let rows: Vec<(usize, (AssistMode, Granularity))> = (0..pipes.len()).flat_map(|k| modes.iter().map(move |&m| (k, m))).collect();
    // The default shows frame 5, or the last of a shorter run.
    let fig_frame = opts.fig_frame.unwrap_or(4).min(n - 1);
    let calibrated = TurntableAxis::read_calibrated(dir).map_err(|e| BenchError::Recording(format!("calibrated turntable axis: {e}")))?;
    // Every row keeps its own assistant, pose store and registrar; the rows take turns frame
    // by frame (and run by run), so that a slow phase of a shared machine falls on all of
    // them alike instead of on whichever row it happened to be running.
    struct RowState {
        /// Index of the row's matcher in `pipes`.
        pipe: usize,
        row: Row,
        assistant: Assistant,
        store: Arc<PoseStore>,
        registrar: Option<Registrar>,
    }
    let mut states: Vec<RowState> = rows
        .into_iter()
        .map(|(k, (mode, granularity))| {
            let store = Arc::new(PoseStore::new());
            let registrar = (mode != AssistMode::None).then(|| crate::pipeline::registrar(opts.registration.clone(), calibrated.as_ref(), None, store.clone()));
            let row = Row::new(&matchers[k], mode, granularity);
            RowState { pipe: k, row, assistant: pipes[k].assistant(AssistParams { mode, granularity, ..opts.assist.clone() }), store, registrar }
        })
        .collect();
    let mut floor_ms = vec![Vec::new(); pipes.len()];
    for (i, (seq, table_deg, frame)) in frames.iter().enumerate() {
        let poses: Vec<PoseSnapshot> = states.iter().map(|st| visible_poses(&st.store.snapshot(), *seq, opts.lag)).collect();
        // Time the frame `repeat` times from the same state: planning is repeatable (it moves
        // nothing on) and the matcher is pure, so the extra runs plan and match; the last run
        // also checks and keeps the frame, and is the one kept. Every run is charged the check
        // (and, when the result was rejected, the redo) of that last run.
        // The matcher's floor on this frame, timed in turn with the rows: one disparity at
        // every foreground pixel — what any interval, however narrow, costs before its width
        // counts.
        let mid = (range.0 + range.1) / 2;
        let floor_iv = crate::stereo::DisparityIntervals::within(size.0, size.1, frame.mask.as_deref(), mid, mid);
        let mut floor_runs = vec![Vec::new(); pipes.len()];
        let mut extra = vec![Vec::new(); states.len()];
        for run in 0..opts.repeat.max(1) {
            for (pipe, runs) in pipes.iter_mut().zip(floor_runs.iter_mut()) {
                let (_, _, ms) = pipe.match_gray(&frame.left_gray, &frame.right_gray, &floor_iv).map_err(|source| BenchError::Pipeline { seq: *seq, source })?;
                runs.push(ms);
            }
            if run == 0 {
                continue;
            }
            for (k, st) in states.iter_mut().enumerate() {
                let plan = st.assistant.plan(*seq, frame.mask.as_deref(), &poses[k]);
                let (_, _, ms) = pipes[st.pipe].match_gray(&frame.left_gray, &frame.right_gray, &plan.intervals).map_err(|source| BenchError::Pipeline { seq: *seq, source })?;
                extra[k].push(plan.build_ms + ms);
                st.assistant.recycle(plan);
            }
        }
        // Every row's kept call first, back to back as the extra runs above, and only then
        // each row's view, its scores and its registration: a row timed right after another
        // row's registration (and its scoring's threads) found its caches cold, and the row
        // without assistance, which registers nothing, had no such row before it
        // (docs/assisted-matching.md, "The rows' calls back to back").
        let mut kept = Vec::with_capacity(states.len());
        for (k, st) in states.iter_mut().enumerate() {
            kept.push(pipes[st.pipe].match_frame(*seq, frame, Some(Assist { assistant: &mut st.assistant, poses: &poses[k] })).map_err(|source| BenchError::Pipeline { seq: *seq, source })?);
        }
        for ((k, st), m) in states.iter_mut().enumerate().zip(kept) {
            let label = row_label(&st.row);
            let pipe = &mut pipes[st.pipe];
            let o = &m.outcome;
            let total = o.interval_ms + o.match_ms;
            let first_try = total - o.accept_ms - o.rejected.map_or(0.0, |_| o.match_ms - o.first_match_ms);
            let mut times: Vec<f64> = extra[k].iter().map(|t| t + (total - first_try)).collect();
            times.push(total);
            let row = &mut st.row;
            row.frame_ms.push(median(&times).expect("at least one run"));
            row.record(&m);
            if let Some(Some(gt)) = truth.disparity.get(i) {
                row.bad2.push(bad2_percent(&m.disparity, gt));
            }
            let view = pipe.finish_view(frame.clone(), m);
            if let (Some(poses), Some(surface)) = (&truth.poses, &truth.surface) {
                if let Some(obj_from_cam) = poses[i] {
                    let pts: Vec<[f32; 3]> = view.cloud.points.iter().map(|p| (obj_from_cam * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64)).coords.map(|v| v as f32).into()).collect();
                    if let Some(m) = quantile(&surface.distances(&pts), 0.5) {
                        row.err_mm.push(m);
                    }
                }
            }
            if i == fig_frame {
                row.fig = Some(view.disparity.clone());
            }
            if let Some(reg) = st.registrar.as_mut() {
                match reg.add_view(*seq, *table_deg, view.registration_cloud()) {
                    Ok(r) => {
                        if let Some(icp) = &r.icp {
                            st.assistant.observe_registration(*seq, icp.fitness, icp.rmse);
                        }
                    }
                    Err(e) => tracing::warn!("{label}: frame seq {seq}: not registered: {e}"),
                }
            }
        }
        for (f, runs) in floor_ms.iter_mut().zip(&floor_runs) {
            f.push(median(runs).expect("at least one run"));
        }
        progress("frames", i + 1, n);
    }
    let rows: Vec<Row> = states.into_iter().map(|st| st.row).collect();
    Ok(Table1 {
        recording: dir.to_path_buf(),
        frames: frames.iter().map(|f| f.0).collect(),
        rows,
        size,
        range,
        threads: params.thread_count(),
        repeat: opts.repeat.max(1),
        lag: opts.lag,
        fig_frame,
        fig_left: frames[fig_frame].2.left_rgb.clone(),
        floor_ms: floor_ms[0].clone(),
        floor_ms_by_method: matchers.iter().map(|m| m.method).zip(floor_ms).collect(),
        screen_not_found,
        backdrop_keyed,
        object_on_edge,
        contrast,
        gt_disparity: truth.disparity_source,
    })
}

/// The store as a matcher `lag` views ahead of registration would see it while matching
/// frame `seq`.
fn visible_poses(snap: &PoseSnapshot, seq: u64, lag: u64) -> PoseSnapshot {
    if lag == 0 {
        return snap.clone();
    }
    let keep = snap.views.len().saturating_sub(lag as usize);
    PoseSnapshot { generation: snap.generation, views: snap.views[..keep].iter().filter(|v| v.seq < seq).cloned().collect() }
}

/// Percent of ground-truth pixels whose disparity is missing or off by more than 2 px (as
/// `../shared/bench/peer_stereo.py` counts `bad2`).
pub fn bad2_percent(disp: &DisparityMap, gt: &DisparityMap) -> f64 {
    let (mut n, mut bad) = (0usize, 0usize);
    for (d, t) in disp.values().iter().zip(gt.values()) {
        if !t.is_finite() {
            continue;
        }
        n += 1;
        bad += (!d.is_finite() || (d.abs() - t.abs()).abs() > 2.0) as usize;
    }
    100.0 * bad as f64 / n.max(1) as f64
}

fn read_truth(rec: &Recording, frames: &[(u64, Option<f64>, Prepared)], rect: &crate::stereo::Rectification) -> Result<Truth, BenchError> {
    let gt = GtDisparities::open(&rec.dir).map_err(|e| BenchError::Recording(e.to_string()))?;
    let (mut disparity, mut disparity_source) = (Vec::new(), Vec::new());
    for (seq, _, _) in frames {
        let (map, source) = gt.get(*seq, rect).map_err(|e| BenchError::Recording(format!("frame seq {seq}: {e}")))?.unzip();
        disparity.push(map);
        disparity_source.push(source);
    }
    let (poses, surface) = match gt.surface() {
        Some((mesh, cam_from_obj)) => {
            let poses = frames.iter().map(|f| cam_from_obj.get(&f.0).map(|p| p.inverse())).collect();
            let surface = Surface::new(mesh, &Isometry3::identity()).map_err(|e| BenchError::Recording(format!("ground truth {}: {e}", rec.dir.join("gt/mesh.ply").display())))?;
            (Some(poses), Some(surface))
        }
        None => (None, None),
    };
    Ok(Truth { disparity, disparity_source, poses, surface })
}
