//! Adapters from the simulated lab (`hw-sim`) to spinscan's seams: the rig's calibration
//! as spinscan reads it, and the simulated cameras as a [`StereoSource`].

use nalgebra::{Matrix3, Vector3};

use crate::calib::{Camera, Distortion, StereoCalib};
use crate::capture::{CaptureError, Picture, StereoFrame, StereoSource};

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
}

impl SimCameras {
    pub fn new(camera: hw_sim::SimStereoCamera) -> SimCameras {
        let calib = calib_of(&camera.renderer().scene().rig);
        SimCameras { camera, calib, last: None }
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

    fn next_frame(&mut self) -> Result<Option<StereoFrame>, CaptureError> {
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

/// A built-in object's name is known (`egg`, `torus`, …), else what the choices are.
pub fn check_object(name: &str) -> Result<(), String> {
    if hw_sim::BUILTIN_OBJECTS.iter().any(|o| o.0 == name) {
        Ok(())
    } else {
        Err(format!("must be one of {}, got {name:?}", hw_sim::BUILTIN_OBJECTS.map(|o| o.0).join(", ")))
    }
}

/// The whole simulated lab for the daemon's `sim` backend: rendered cameras and the
/// turntable firmware on a pseudo-terminal, both seeing one table angle, with spinscan's
/// serial driver connected to the firmware.
pub struct SimLab {
    pub cameras: SimCameras,
    pub turntable: crate::turntable::HorusTurntable,
    /// Keeps the pseudo-terminal alive; drop it after the driver.
    pub emulator: hw_sim::Emulator,
}

impl SimLab {
    pub fn open(s: &crate::daemon::config::SimSection, fps: f64, driver: crate::turntable::DriverConfig) -> Result<SimLab, String> {
        let mesh = hw_sim::Mesh::builtin(&s.object, 30_000).map_err(|e| format!("sim.object: {e}"))?;
        let mut scene = if s.ideal { hw_sim::SceneConfig::ideal(mesh) } else { hw_sim::SceneConfig::realistic(mesh) };
        let focal = 700.0 * s.width as f64 / 640.0;
        scene.rig = if s.ideal { hw_sim::Rig::ideal(s.width, s.height, focal, 60.0) } else { hw_sim::Rig::realistic(s.width, s.height, focal, 60.0) };
        scene.seed = s.seed;
        let angle = hw_sim::TableAngle::new(0.0);
        let fw = hw_sim::FirmwareConfig { time_scale: s.time_scale, ..Default::default() };
        let emulator = hw_sim::Emulator::spawn(fw, angle.clone()).map_err(|e| format!("cannot start the turntable emulator: {e}"))?;
        let renderer = hw_sim::Renderer::new(scene).map_err(|e| e.to_string())?;
        let timing = hw_sim::Timing { fps, ..Default::default() };
        let camera = hw_sim::SimStereoCamera::new(renderer, timing, angle).realtime(s.realtime);
        let turntable = crate::turntable::HorusTurntable::open(emulator.port_path(), driver).map_err(|e| e.to_string())?;
        Ok(SimLab { cameras: SimCameras::new(camera), turntable, emulator })
    }
}

/// What `spinscan sim render` puts on the turntable.
#[derive(Debug, Clone)]
pub enum SimObject {
    /// A built-in shape (see [`hw_sim::BUILTIN_OBJECTS`]) with about this many triangles.
    Builtin { name: String, triangles: usize },
    /// A triangle mesh in mm, `+y` up.
    Mesh(hw_sim::Mesh),
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
    /// Image size; the focal length scales with the width (700 px at 640), so the view is
    /// the default lab's at another resolution.
    pub image_size: (usize, usize),
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
}

/// Renders a recording with ground truth into `out`. `progress(done, total)` after each pair.
pub fn render_recording(opts: &RenderOptions, out: &std::path::Path, progress: &mut dyn FnMut(usize, usize)) -> Result<crate::recording::Recording, SimError> {
    if opts.frames == 0 {
        return Err(SimError::Option { what: "--frames", expected: "at least 1", got: "0".into() });
    }
    if !(0.0..1.0).contains(&opts.drop_probability) {
        return Err(SimError::Option { what: "drop probability", expected: "within 0 … <1", got: opts.drop_probability.to_string() });
    }
    if !(0.0..=1.0).contains(&opts.texture_contrast) {
        return Err(SimError::Option { what: "--texture-contrast", expected: "within 0 … 1", got: opts.texture_contrast.to_string() });
    }
    let mesh = match &opts.object {
        SimObject::Builtin { name, triangles } => hw_sim::Mesh::builtin(name, *triangles)?,
        SimObject::Mesh(m) => m.clone(),
    };
    let mut scene = if opts.ideal { hw_sim::SceneConfig::ideal(mesh.clone()) } else { hw_sim::SceneConfig::realistic(mesh.clone()) };
    let (w, h) = opts.image_size;
    if w < 32 || h < 32 {
        return Err(SimError::Option { what: "image size", expected: "at least 32×32", got: format!("{w}×{h}") });
    }
    let focal = 700.0 * w as f64 / 640.0;
    scene.rig = if opts.ideal { hw_sim::Rig::ideal(w, h, focal, 60.0) } else { hw_sim::Rig::realistic(w, h, focal, 60.0) };
    scene.seed = opts.seed;
    scene.texture_contrast = opts.texture_contrast;
    scene.noise_sigma = opts.noise_sigma;
    let (axis_point, axis_dir) = scene.axis_in_left_camera();
    let renderer = hw_sim::Renderer::new(scene)?;
    let timing = hw_sim::Timing { drop_probability: opts.drop_probability, ..Default::default() };
    let camera = hw_sim::SimStereoCamera::new(renderer, timing, hw_sim::TableAngle::new(opts.start_deg)).with_motion(opts.start_deg, opts.deg_per_frame);
    let mut cams = SimCameras::new(camera);
    let mut writer = crate::recording::RecordingWriter::create(out, cams.calibration())?;
    let cloud = crate::cloud::PointCloud { points: mesh.vertices.clone(), colors: vec![[200, 180, 150]; mesh.vertices.len()], normals: None };
    writer.write_gt_mesh(&crate::cloud::Mesh { cloud, triangles: mesh.triangles.clone() })?;
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
