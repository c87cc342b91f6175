//! The simulated lab (`hw-sim`) behind spinscan's seams: the rig's calibration as spinscan
//! reads it, the simulated cameras as a [`StereoSource`], the turntable firmware emulator on
//! a pty with spinscan's own serial driver talking to it (owned together, as one
//! [`Turntable`]), the daemon's `[sim]` config section, and `spinscan sim render`. This is
//! the only file of `src/` that names `hw_sim`.

use nalgebra::{Matrix3, Vector3};

use crate::calib::{Camera, Distortion, StereoCalib};
use serde::{Deserialize, Serialize};

use super::horus::{DriverConfig, HorusTurntable};
use super::{CaptureError, Picture, StereoFrame, StereoSource, Turntable, TurntableError};
use crate::cloud::Mesh;
use crate::recording::TurntableAxis;

/// The calibration of a simulated rig, exactly (OpenCV's model, 5 coefficients; none for
/// a distortion-free camera).
pub fn calib_of(rig: &hw_sim::Rig) -> StereoCalib {
    let camera = |k: &hw_sim::Intrinsics| Camera {
        k: Matrix3::new(k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0),
        distortion: if k.is_pinhole() { Distortion::none() } else { Distortion::new(&k.distortion).expect("5 coefficients") },
    };
    let p = &rig.right_from_left;
    StereoCalib {
        left: camera(&rig.left),
        right: camera(&rig.right),
        r: Matrix3::from_fn(|i, j| p.r[i][j]),
        t_mm: Vector3::new(p.t[0], p.t[1], p.t[2]),
        image_size: Some((rig.width as u32, rig.height as u32)),
    }
}

/// A small ideal scene for tests and examples: `object` on a `width`×`height` rig with
/// focal length `focal_px` (the default lab scaled down).
pub fn small_scene(object: &str, width: usize, height: usize, focal_px: f64) -> hw_sim::SceneConfig {
    let mut scene = hw_sim::SceneConfig::ideal(hw_sim::Mesh::builtin(object, 20_000).expect("built-in object"));
    scene.rig = hw_sim::Rig::ideal(width, height, focal_px, 60.0);
    scene
}

/// The simulated cameras behind spinscan's camera seam.
pub struct SimCameras {
    camera: hw_sim::SimStereoCamera,
    calib: StereoCalib,
    /// Ground truth of the last delivered frame (for recordings with `gt/`).
    last: Option<hw_sim::RenderedPair>,
    /// A calibration board shown instead of the object ([`StereoSource::show_target`]).
    target: Option<TargetMode>,
    /// Frame rate and pacing of the target's frames (the object's come from `camera`).
    fps: f64,
    paced: bool,
}

impl SimCameras {
    pub fn new(camera: hw_sim::SimStereoCamera) -> SimCameras {
        let calib = calib_of(&camera.renderer().scene().rig);
        SimCameras { camera, calib, last: None, target: None, fps: 15.0, paced: false }
    }

    /// The rate a shown calibration board is delivered at, and whether in real time.
    pub fn with_pace(mut self, fps: f64, paced: bool) -> SimCameras {
        self.fps = fps;
        self.paced = paced;
        self
    }

    /// The rendered pair behind the last frame: its ground-truth pose and disparity.
    pub fn last_truth(&self) -> Option<&hw_sim::RenderedPair> {
        self.last.as_ref()
    }

    pub fn scene(&self) -> &hw_sim::SceneConfig {
        self.camera.renderer().scene()
    }
}

impl StereoSource for SimCameras {
    fn describe(&self) -> String {
        "simulated cameras (hw-sim)".to_string()
    }

    fn calibration(&self) -> &StereoCalib {
        &self.calib
    }

    fn show_target(&mut self, target: Option<super::TargetScene>) -> bool {
        let seed = self.camera.renderer().scene().seed;
        self.target = target.map(|t| TargetMode::new(self.camera.renderer().scene(), &t, self.fps, self.paced, seed));
        true
    }

    fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
        if let Some(t) = &mut self.target {
            return Ok(Some(t.frame(self.camera.angle().get())));
        }
        let f = self.camera.next_frame().map_err(|e| match e {
            hw_sim::SimCameraError::NoFrame { camera, waited_ms } => CaptureError::NoFrame { camera: camera.to_string(), waited_ms },
            hw_sim::SimCameraError::Disconnected { camera } => CaptureError::Disconnected { camera: camera.to_string() },
        })?;
        let (w, h) = (f.pair.width, f.pair.height);
        let raw = |data: &Vec<u8>| Picture::Raw { width: w, height: h, channels: 3, data: data.clone() };
        let frame = StereoFrame {
            seq: f.seq,
            t_left_ns: f.t_left_ns,
            t_right_ns: f.t_right_ns,
            table_deg: Some(f.table_deg),
            left: raw(&f.pair.left_rgb),
            right: raw(&f.pair.right_rgb),
        };
        self.last = Some(f.pair);
        Ok(Some(frame))
    }
}

/// The names of the built-in objects (`egg`, `torus`, …).
pub fn builtin_objects() -> Vec<&'static str> {
    hw_sim::BUILTIN_OBJECTS.iter().map(|o| o.0).collect()
}

/// A built-in object's name is known (`egg`, `torus`, …), else what the choices are.
pub fn check_object(name: &str) -> Result<(), SimError> {
    if hw_sim::BUILTIN_OBJECTS.iter().any(|o| o.0 == name) {
        Ok(())
    } else {
        Err(SimError::UnknownObject { got: name.to_string(), known: builtin_objects().join(", ") })
    }
}

/// The calibration of an ideal (distortion-free, rectified) rig of `width`×`height` pixels,
/// focal length `focal_px` and baseline `baseline_mm`: what unit tests match on.
pub fn ideal_calib(width: usize, height: usize, focal_px: f64, baseline_mm: f64) -> StereoCalib {
    calib_of(&hw_sim::Rig::ideal(width, height, focal_px, baseline_mm))
}

/// The `[sim]` section of the daemon's config: the simulated lab of the `sim` backend.
#[derive(Debug, Clone, PartialEq, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimSection {
    /// Built-in object: egg, torus, vase, sphere.
    pub object: String,
    pub width: usize,
    pub height: usize,
    /// The ideal rectified rig (else distortion and misalignment).
    pub ideal: bool,
    pub seed: u64,
    /// Deliver frames at the cameras' rate (else as fast as they are asked for).
    pub realtime: bool,
    /// Simulated turntable seconds per real second (> 1 turns faster).
    pub time_scale: f64,
}

impl Default for SimSection {
    fn default() -> Self {
        SimSection { object: "egg".into(), width: 640, height: 480, ideal: false, seed: 1, realtime: true, time_scale: 1.0 }
    }
}

/// The firmware emulator on its pty with spinscan's driver connected to it: the sim
/// backend's [`Turntable`]. The emulator lives exactly as long as the driver that talks to it.
pub struct SimTurntable {
    // Field order is drop order: the driver lets go of the pty before the emulator closes it.
    driver: HorusTurntable,
    _emulator: hw_sim::Emulator,
}

impl Turntable for SimTurntable {
    fn move_to(&mut self, table_deg: f64) -> Result<f64, TurntableError> {
        self.driver.move_to(table_deg)
    }
    fn angle(&mut self) -> Result<f64, TurntableError> {
        self.driver.angle()
    }
    fn angle_at(&mut self, t_ns: u64) -> Result<f64, TurntableError> {
        self.driver.angle_at(t_ns)
    }
    fn resolution_deg(&self) -> f64 {
        self.driver.resolution_deg()
    }
    fn release(&mut self) -> Result<(), TurntableError> {
        self.driver.release()
    }
    fn watch_stop(&mut self, stop: std::sync::Arc<std::sync::atomic::AtomicBool>) {
        self.driver.watch_stop(stop)
    }
    fn start_move(&mut self, table_deg: f64, feed_deg_s: f64) -> Result<(), TurntableError> {
        self.driver.start_move(table_deg, feed_deg_s)
    }
    fn halt(&mut self) -> Result<(), TurntableError> {
        self.driver.halt()
    }
    fn describe(&self) -> String {
        self.driver.describe()
    }
}

/// The whole simulated lab for the daemon's `sim` backend: rendered cameras and the
/// turntable firmware on a pseudo-terminal, both seeing one table angle, with spinscan's
/// serial driver connected to the firmware.
pub struct SimLab {
    pub cameras: SimCameras,
    pub turntable: SimTurntable,
}

impl SimLab {
    pub fn open(s: &SimSection, fps: f64, driver: DriverConfig) -> Result<SimLab, SimError> {
        let mesh = hw_sim::Mesh::builtin(&s.object, 30_000)?;
        let mut scene = if s.ideal { hw_sim::SceneConfig::ideal(mesh) } else { hw_sim::SceneConfig::realistic(mesh) };
        let focal = 700.0 * s.width as f64 / 640.0;
        scene.rig = if s.ideal { hw_sim::Rig::ideal(s.width, s.height, focal, 60.0) } else { hw_sim::Rig::realistic(s.width, s.height, focal, 60.0) };
        scene.seed = s.seed;
        let angle = hw_sim::TableAngle::new(0.0);
        // The bootloader's 2 s after the port opens, at the lab's time scale.
        let boot_delay = std::time::Duration::from_secs_f64(2.0 / s.time_scale.max(1.0));
        let fw = hw_sim::FirmwareConfig { time_scale: s.time_scale, boot_delay, ..Default::default() };
        let emulator = hw_sim::Emulator::spawn(fw, angle.clone()).map_err(|e| SimError::Emulator(e.to_string()))?;
        let renderer = hw_sim::Renderer::new(scene)?;
        let timing = hw_sim::Timing { fps, ..Default::default() };
        let camera = hw_sim::SimStereoCamera::new(renderer, timing, angle).realtime(s.realtime);
        let driver = HorusTurntable::open(emulator.port_path(), driver)?;
        Ok(SimLab { cameras: SimCameras::new(camera).with_pace(fps, s.realtime), turntable: SimTurntable { driver, _emulator: emulator } })
    }
}

/// A rendered pair of a scene at `table_deg`: raw left and right RGB images.
pub fn render_pair(scene: &hw_sim::SceneConfig, table_deg: f64) -> Result<(Vec<u8>, Vec<u8>), SimError> {
    let pair = hw_sim::Renderer::new(scene.clone())?.render(table_deg, 0);
    Ok((pair.left_rgb, pair.right_rgb))
}

/// What `spinscan sim render` puts on the turntable.
#[derive(Debug, Clone)]
pub enum SimObject {
    /// A built-in shape (see [`hw_sim::BUILTIN_OBJECTS`]) with about this many triangles.
    Builtin { name: String, triangles: usize },
    /// A triangle mesh in mm, `+y` up, scaled by the factor.
    Mesh(Mesh, f64),
}

/// Settings of a simulated recording.
#[derive(Debug, Clone)]
pub struct RenderOptions {
    pub object: SimObject,
    pub frames: usize,
    pub start_deg: f64,
    pub deg_per_frame: f64,
    /// The ideal rectified rig (with `gt/disparity/`), else a realistic one (distortion,
    /// misalignment).
    pub ideal: bool,
    pub seed: u64,
    pub texture_contrast: f64,
    pub noise_sigma: f64,
    /// Probability that a pair is lost (a gap in `seq`).
    pub drop_probability: f64,
    /// Image size; without [`Lab::focal_px`] the focal length scales with the width (700 px
    /// at 640), so the view is the default lab's at another resolution.
    pub image_size: (usize, usize),
    /// Where the cameras stand and how they see (the default: the lab of every recording so
    /// far).
    pub lab: Lab,
}

/// The rig's optics and the cameras' place around the table: what a different lab, or a
/// different renderer, would change. The object's disparities are about
/// `focal_px · baseline_mm / object_distance_mm` at its middle.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lab {
    /// Focal length, pixels; `None`: 700 px at a width of 640, in proportion at others.
    pub focal_px: Option<f64>,
    /// Distance between the two cameras' centres, mm; negative puts the right camera left of
    /// the left one, so that disparities are negative (as on the XIMEA fixture's rig; such a
    /// rig writes no `gt/disparity/`, whose format is for `T = (−B, 0, 0)` only).
    pub baseline_mm: f64,
    /// Distance from the left camera to the object's middle on the axis, mm.
    pub object_distance_mm: f64,
    /// How far the cameras look down, degrees below the horizontal.
    pub camera_tilt_deg: f64,
    /// Where the object stands off the turntable's axis, (x, z) in the table's plane, mm: it
    /// then swings around the axis as the table turns, as an object placed by hand does.
    pub object_offset_mm: [f64; 2],
    /// How far the right camera is turned towards the left one's line of sight, degrees (a
    /// toed-in rig: `atan(baseline / distance)` aims both cameras at the object; 0: the
    /// cameras look the same way).
    pub toe_in_deg: f64,
}

impl Default for Lab {
    fn default() -> Self {
        Lab { focal_px: None, baseline_mm: 60.0, object_distance_mm: 450.0, camera_tilt_deg: 12.0, object_offset_mm: [0.0, 0.0], toe_in_deg: 0.0 }
    }
}

impl Lab {
    /// The focal length at image width `width`.
    pub fn focal_at(&self, width: usize) -> f64 {
        self.focal_px.unwrap_or(700.0 * width as f64 / 640.0)
    }

    /// The rig of this lab at image size `(w, h)`: the ideal rectified one, or a realistic
    /// one (distortion, misalignment); toed in by `toe_in_deg`.
    pub(super) fn rig(&self, ideal: bool, (w, h): (usize, usize)) -> hw_sim::Rig {
        let (focal, baseline) = (self.focal_at(w), self.baseline_mm);
        let rig = if ideal { hw_sim::Rig::ideal(w, h, focal, baseline) } else { hw_sim::Rig::realistic(w, h, focal, baseline) };
        rig.toed_in(self.toe_in_deg)
    }

    pub(super) fn check(&self) -> Result<(), SimError> {
        let bad = |v: f64| !v.is_finite() || v <= 0.0;
        if self.focal_px.is_some_and(bad) {
            return Err(SimError::Option { what: "--focal-px", expected: "a positive number of pixels", got: format!("{}", self.focal_px.unwrap_or_default()) });
        }
        if !self.baseline_mm.is_finite() || self.baseline_mm == 0.0 {
            return Err(SimError::Option { what: "--baseline-mm", expected: "a non-zero distance in mm (negative: the right camera left of the left one)", got: self.baseline_mm.to_string() });
        }
        if bad(self.object_distance_mm) {
            return Err(SimError::Option { what: "--object-distance-mm", expected: "a positive distance in mm", got: self.object_distance_mm.to_string() });
        }
        if !self.object_offset_mm.iter().all(|v| v.is_finite() && v.abs() <= 1000.0) {
            return Err(SimError::Option { what: "--object-offset-mm", expected: "two distances within ±1000 mm", got: format!("{:?}", self.object_offset_mm) });
        }
        if !(self.camera_tilt_deg.is_finite() && (-80.0..=80.0).contains(&self.camera_tilt_deg)) {
            return Err(SimError::Option { what: "--camera-tilt-deg", expected: "within −80 … 80 degrees", got: self.camera_tilt_deg.to_string() });
        }
        if !(self.toe_in_deg.is_finite() && (-45.0..=45.0).contains(&self.toe_in_deg)) {
            return Err(SimError::Option { what: "--toe-in-deg", expected: "within −45 … 45 degrees", got: self.toe_in_deg.to_string() });
        }
        Ok(())
    }
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            object: SimObject::Builtin { name: "egg".into(), triangles: 100_000 },
            frames: 30,
            start_deg: 0.0,
            deg_per_frame: 2.0,
            ideal: false,
            seed: 1,
            texture_contrast: 0.8,
            noise_sigma: 1.5,
            drop_probability: 0.0,
            image_size: (640, 480),
            lab: Lab::default(),
        }
    }
}

/// Why a simulated recording could not be made.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{0}")]
    Mesh(#[from] hw_sim::MeshError),
    #[error(transparent)]
    Recording(#[from] crate::recording::RecordingError),
    #[error(transparent)]
    Capture(#[from] CaptureError),
    #[error("{what} must be {expected}, got {got}")]
    Option { what: &'static str, expected: &'static str, got: String },
    #[error("must be one of {known}, got {got:?}")]
    UnknownObject { got: String, known: String },
    #[error("cannot start the turntable emulator: {0}")]
    Emulator(String),
    #[error(transparent)]
    Turntable(#[from] TurntableError),
}

/// A simulated recording ready to render: `opts` checked and the scene built, with the
/// object's mesh, once — for its disparity span ([`PreparedRender::object_disparities`]) and
/// then its frames ([`PreparedRender::render`]).
pub struct PreparedRender<'a> {
    opts: &'a RenderOptions,
    scene: hw_sim::SceneConfig,
}

impl<'a> PreparedRender<'a> {
    /// The scene `opts` asks for, after checking every option.
    pub fn new(opts: &'a RenderOptions) -> Result<PreparedRender<'a>, SimError> {
        if opts.frames == 0 {
            return Err(SimError::Option { what: "--frames", expected: "at least 1", got: "0".into() });
        }
        if !(0.0..1.0).contains(&opts.drop_probability) {
            return Err(SimError::Option { what: "drop probability", expected: "within 0 … <1", got: opts.drop_probability.to_string() });
        }
        if !(0.0..=1.0).contains(&opts.texture_contrast) {
            return Err(SimError::Option { what: "--texture-contrast", expected: "within 0 … 1", got: opts.texture_contrast.to_string() });
        }
        let (w, h) = opts.image_size;
        if w < 32 || h < 32 {
            return Err(SimError::Option { what: "image size", expected: "at least 32×32", got: format!("{w}×{h}") });
        }
        opts.lab.check()?;
        let mesh = match &opts.object {
            SimObject::Builtin { name, triangles } => hw_sim::Mesh::builtin(name, *triangles)?,
            SimObject::Mesh(m, scale) => hw_sim::Mesh { vertices: m.cloud.points.clone(), triangles: m.triangles.clone() }.scaled(*scale),
        };
        let (lo, hi) = mesh.bounds();
        let radius = 0.5 * (0..3).map(|i| hi[i] - lo[i]).map(|e| e * e).sum::<f64>().sqrt();
        let swing = opts.lab.object_offset_mm[0].hypot(opts.lab.object_offset_mm[1]);
        if opts.lab.object_distance_mm <= radius + swing + 10.0 {
            return Err(SimError::Option { what: "--object-distance-mm", expected: "more than the object's half-diagonal and its offset plus 10 mm (the camera would sit inside it)", got: format!("{} (half-diagonal {radius:.1} mm, offset {swing:.1} mm)", opts.lab.object_distance_mm) });
        }
        let mut scene = if opts.ideal { hw_sim::SceneConfig::ideal(mesh) } else { hw_sim::SceneConfig::realistic(mesh) };
        scene.rig = opts.lab.rig(opts.ideal, (w, h));
        scene.object_distance_mm = opts.lab.object_distance_mm;
        scene.camera_tilt_deg = opts.lab.camera_tilt_deg;
        scene.object_offset_mm = opts.lab.object_offset_mm;
        scene.seed = opts.seed;
        scene.texture_contrast = opts.texture_contrast;
        scene.noise_sigma = opts.noise_sigma;
        Ok(PreparedRender { opts, scene })
    }

    /// The smallest and largest disparity, pixels, of the object's vertices over the frames
    /// to render (`focal · baseline / Z` in the left camera: about the rectified disparity
    /// on a realistic rig too), so that a user of another lab geometry can pick the range to
    /// search (`--min-disparity`, `--num-disparities`).
    pub fn object_disparities(&self) -> (f64, f64) {
        let opts = self.opts;
        let fb = opts.lab.focal_at(opts.image_size.0) * opts.lab.baseline_mm;
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for k in 0..opts.frames {
            let pose = self.scene.cam_from_obj(opts.start_deg + k as f64 * opts.deg_per_frame);
            for v in &self.scene.object.vertices {
                let z = pose.apply(v.map(f64::from))[2];
                if z > 0.0 {
                    lo = lo.min(fb / z);
                    hi = hi.max(fb / z);
                }
            }
        }
        (lo, hi)
    }

    /// Renders the recording with ground truth into `out`. `progress(done, total)` after
    /// each pair.
    pub fn render(self, out: &std::path::Path, progress: &mut dyn FnMut(usize, usize)) -> Result<crate::recording::Recording, SimError> {
        let PreparedRender { opts, scene } = self;
        let (axis_point, axis_dir) = scene.axis_in_left_camera();
        let mesh = &scene.object;
        let gt_mesh = crate::cloud::Mesh {
            cloud: crate::cloud::PointCloud { points: mesh.vertices.clone(), colors: vec![[200, 180, 150]; mesh.vertices.len()], normals: None, rim_px: None },
            triangles: mesh.triangles.clone(),
        };
        let renderer = hw_sim::Renderer::new(scene)?;
        let timing = hw_sim::Timing { drop_probability: opts.drop_probability, ..Default::default() };
        let camera = hw_sim::SimStereoCamera::new(renderer, timing, hw_sim::TableAngle::new(opts.start_deg)).with_motion(opts.start_deg, opts.deg_per_frame);
        let mut cams = SimCameras::new(camera);
        let mut writer = crate::recording::RecordingWriter::create(out, cams.calibration())?;
        writer.write_gt_mesh(&gt_mesh)?;
        writer.write_turntable(&crate::recording::TurntableAxis { axis_point_mm: axis_point, axis_dir, source: "ground truth".into() }, true)?;
        for done in 1..=opts.frames {
            let frame = cams.next_frame()?.expect("simulated cameras never run out");
            writer.append(&frame)?;
            let truth = cams.last_truth().expect("a frame was delivered");
            writer.append_gt_pose(frame.seq, &truth.cam_from_obj.matrix())?;
            if let Some(gt) = &truth.gt_disparity {
                let map = crate::stereo::DisparityMap::from_values(truth.width, truth.height, gt.clone());
                writer.write_gt_disparity(frame.seq, &map)?;
            }
            progress(done, opts.frames);
        }
        Ok(crate::recording::Recording::open(out)?)
    }
}

/// [`PreparedRender::object_disparities`] of the recording `opts` describes.
pub fn object_disparities(opts: &RenderOptions) -> Result<(f64, f64), SimError> {
    Ok(PreparedRender::new(opts)?.object_disparities())
}

/// Renders a recording with ground truth into `out` ([`PreparedRender::render`]).
pub fn render_recording(opts: &RenderOptions, out: &std::path::Path, progress: &mut dyn FnMut(usize, usize)) -> Result<crate::recording::Recording, SimError> {
    PreparedRender::new(opts)?.render(out, progress)
}

/// The lab's table seen from the rig, and the true axis in the left camera frame: the lab
/// of `object`'s recordings (its cameras aimed at that object's middle), or, without one,
/// aimed at the board's middle; from `lab`'s distance and tilt.
pub(super) fn table_geometry(rig: &hw_sim::Rig, b: &hw_sim::Chessboard, object: Option<&str>, lab: &Lab) -> Result<(hw_sim::Pose, TurntableAxis), SimError> {
    let object = match object {
        Some(name) => hw_sim::Mesh::builtin(name, 2_000)?,
        None => {
            let (_, _, _, y1) = b.extent();
            let height = y1 + 2.0 * b.square_mm;
            // A flat stand-in object as tall as the board: only its bounds aim the cameras.
            hw_sim::Mesh { vertices: vec![[-50.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, height as f32, 0.0]], triangles: vec![[0, 1, 2]] }
        }
    };
    let mut scene = hw_sim::SceneConfig::realistic(object);
    scene.rig = *rig;
    scene.object_distance_mm = lab.object_distance_mm;
    scene.camera_tilt_deg = lab.camera_tilt_deg;
    let (point, dir) = scene.axis_in_left_camera();
    Ok((scene.cam_from_table(), TurntableAxis { axis_point_mm: point, axis_dir: dir, source: "ground truth".into() }))
}

/// The board standing upright on the table, its face towards the cameras at table angle 0,
/// its lower edge on the table surface, off the axis by a little more than a square each way
/// (so the corners' circles differ in radius).
pub(super) fn board_on_table(b: &hw_sim::Chessboard) -> hw_sim::Pose {
    let (_, _, _, y1) = b.extent();
    // Board x along table x, board y down (−table y), board z into the board (−table z).
    let r = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]];
    let width = (b.cols as f64 - 1.0) * b.square_mm;
    hw_sim::Pose { r, t: [-width / 2.0 + 1.3 * b.square_mm, y1, 1.2 * b.square_mm] }
}

/// A board in front of the simulated cameras during a daemon's calibration capture: held
/// up and moved to a new pose about once a second, or standing on the turntable.
pub struct TargetMode {
    renderer: hw_sim::TargetRenderer,
    board: hw_sim::Chessboard,
    /// Held: the poses it is moved through; on the table: the table's pose and the board's on it.
    held: Vec<hw_sim::Pose>,
    table: Option<(hw_sim::Pose, hw_sim::Pose)>,
    frames: u64,
    period: std::time::Duration,
    last: Option<std::time::Instant>,
    seed: u64,
}

impl TargetMode {
    /// The board `target` describes, in front of `scene`'s rig (standing on its table),
    /// delivered at `fps` when `paced`.
    pub fn new(scene: &hw_sim::SceneConfig, target: &super::TargetScene, fps: f64, paced: bool, seed: u64) -> TargetMode {
        let rig = &scene.rig;
        let board = hw_sim::Chessboard { cols: target.cols, rows: target.rows, square_mm: target.square_mm };
        let (held, table) = if target.on_table {
            // The lab's own table, as the scans see it: the axis calibrated is theirs.
            (Vec::new(), Some((scene.cam_from_table(), board_on_table(&board))))
        } else {
            // Far enough that the board fits both images whatever its size.
            let size = (board.cols.max(board.rows) as f64 + 3.0) * board.square_mm;
            let distance = (size * rig.left.fx / (0.4 * rig.width as f64)).max(300.0);
            (hw_sim::target::stereo_poses(rig, &board, 40, distance, seed), None)
        };
        let period = if paced && fps > 0.0 { std::time::Duration::from_secs_f64(1.0 / fps) } else { std::time::Duration::ZERO };
        TargetMode { renderer: hw_sim::TargetRenderer::new(*rig), board, held, table, frames: 0, period, last: None, seed }
    }

    /// The next pair at the table's angle `table_deg`.
    pub fn frame(&mut self, table_deg: f64) -> StereoFrame {
        if let Some(last) = self.last {
            if let Some(wait) = self.period.checked_sub(last.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        self.last = Some(std::time::Instant::now());
        let pose = match (&self.table, self.held.is_empty()) {
            (Some((cam_from_table, table_from_board)), _) => {
                let turn = hw_sim::Pose { r: hw_sim::math::rotation([0.0, 1.0, 0.0], table_deg.to_radians()), t: [0.0; 3] };
                cam_from_table.compose(&turn).compose(table_from_board)
            }
            // A new pose about every second at the cameras' rate (every other frame unpaced).
            (None, false) => self.held[(self.frames / if self.period.is_zero() { 2 } else { 15 }) as usize % self.held.len()],
            // No pose keeps the board in view: it stays out of sight.
            (None, true) => hw_sim::Pose { r: hw_sim::math::IDENTITY, t: [0.0, 0.0, -1000.0] },
        };
        let pair = self.renderer.render(&self.board, &pose, 1.5, self.seed.wrapping_add(self.frames));
        let t = super::frame::monotonic_ns();
        let picture = |data: Vec<u8>| Picture::Raw { width: pair.width, height: pair.height, channels: 1, data };
        let frame = StereoFrame { seq: self.frames, left: picture(pair.left), right: picture(pair.right), t_left_ns: t, t_right_ns: t, table_deg: Some(table_deg) };
        self.frames += 1;
        frame
    }
}
