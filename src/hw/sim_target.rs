//! The simulated lab's calibration recordings (`spinscan sim render --target …`): a printed
//! chessboard held at varied poses in front of the rig (for `calibrate stereo`), or standing
//! on the turntable while it steps (for `calibrate turntable`).
//!
//! A target recording is an ordinary recording whose `calib.yaml` is the rig's *nominal*
//! calibration (its design values: no distortion, principal point at the centre, the ideal
//! baseline) — what a lab has before calibrating. The truth is under `gt/`: `gt/calib.yaml`
//! (the rig), `gt/turntable.yaml` (the axis), `gt/corners.jsonl` (every inner corner's true
//! pixel position in each image, per pair) and `gt/board.json` (the board).

use std::path::Path;

use serde_json::json;

use super::frame::{Picture, StereoFrame};
use super::sim::{calib_of, SimError};
use crate::recording::{RecordingWriter, TurntableAxis};

/// Which target recording.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TargetKind {
    /// The board held at varied poses, covering the image (stereo calibration).
    Chessboard,
    /// The board standing upright on the turntable, turned through ±`sweep` degrees.
    ChessboardOnTable,
}

/// Settings of a target recording.
#[derive(Debug, Clone)]
pub struct TargetOptions {
    pub kind: TargetKind,
    pub board: hw_sim::Chessboard,
    pub frames: usize,
    pub ideal: bool,
    pub seed: u64,
    pub noise_sigma: f64,
    pub image_size: (usize, usize),
    /// Distance of the held board from the left camera, mm (`Chessboard`).
    pub distance_mm: f64,
    /// Table angles from −sweep to +sweep, degrees (`ChessboardOnTable`).
    pub sweep_deg: f64,
}

impl Default for TargetOptions {
    fn default() -> Self {
        TargetOptions {
            kind: TargetKind::Chessboard,
            board: hw_sim::Chessboard { cols: 9, rows: 6, square_mm: 20.0 },
            frames: 20,
            ideal: false,
            seed: 1,
            noise_sigma: 1.5,
            image_size: (640, 480),
            distance_mm: 600.0,
            sweep_deg: 50.0,
        }
    }
}

/// Renders a target recording into `out`; `progress(done, total)` after each pair.
pub fn render_target_recording(opts: &TargetOptions, out: &Path, progress: &mut dyn FnMut(usize, usize)) -> Result<(), SimError> {
    if opts.frames < 2 {
        return Err(SimError::Option { what: "--frames", expected: "at least 2 for a target", got: opts.frames.to_string() });
    }
    let (w, h) = opts.image_size;
    if w < 160 || h < 120 {
        return Err(SimError::Option { what: "image size", expected: "at least 160×120 for a target", got: format!("{w}×{h}") });
    }
    let b = opts.board;
    if b.cols < 3 || b.rows < 3 || !(b.square_mm > 0.0 && b.square_mm.is_finite()) {
        return Err(SimError::Option { what: "the board", expected: "at least 3×3 inner corners and a positive square size", got: format!("{}×{}, {} mm", b.cols, b.rows, b.square_mm) });
    }
    let focal = 700.0 * w as f64 / 640.0;
    let rig = if opts.ideal { hw_sim::Rig::ideal(w, h, focal, 60.0) } else { hw_sim::Rig::realistic(w, h, focal, 60.0) };
    let nominal = calib_of(&hw_sim::Rig::ideal(w, h, focal, 60.0));
    let mut writer = RecordingWriter::create(out, &nominal)?;
    let gt = out.join("gt");
    let io = |path: &Path, e: std::io::Error| SimError::Recording(crate::recording::RecordingError::Io { path: path.to_path_buf(), source: e });
    std::fs::create_dir_all(&gt).map_err(|e| io(&gt, e))?;
    let calib_path = gt.join("calib.yaml");
    crate::io::write_atomic(&calib_path, calib_of(&rig).to_yaml().as_bytes()).map_err(|e| io(&calib_path, e))?;
    let board_path = gt.join("board.json");
    let about = json!({"cols": b.cols, "rows": b.rows, "square_mm": b.square_mm, "kind": match opts.kind { TargetKind::Chessboard => "chessboard", TargetKind::ChessboardOnTable => "chessboard-on-table" }});
    crate::io::write_atomic(&board_path, about.to_string().as_bytes()).map_err(|e| io(&board_path, e))?;

    // Poses in the left camera frame, and the table angle of each (on the table only).
    let (poses, angles): (Vec<hw_sim::Pose>, Vec<Option<f64>>) = match opts.kind {
        TargetKind::Chessboard => {
            let p = hw_sim::target::stereo_poses(&rig, &b, opts.frames, opts.distance_mm, opts.seed);
            if p.len() < opts.frames {
                return Err(SimError::Option { what: "the board and distance", expected: "a board small enough to be seen whole by both cameras at the distance", got: format!("{}×{} × {} mm at {} mm", b.cols, b.rows, b.square_mm, opts.distance_mm) });
            }
            let n = p.len();
            (p, vec![None; n])
        }
        TargetKind::ChessboardOnTable => {
            let (cam_from_table, axis) = table_geometry(&rig, &b);
            writer.write_turntable(&axis, true)?;
            let table_from_board = board_on_table(&b);
            let angles: Vec<f64> = (0..opts.frames).map(|k| -opts.sweep_deg + 2.0 * opts.sweep_deg * k as f64 / (opts.frames - 1) as f64).collect();
            let poses = angles
                .iter()
                .map(|&deg| {
                    let turn = hw_sim::Pose { r: hw_sim::math::rotation([0.0, 1.0, 0.0], deg.to_radians()), t: [0.0; 3] };
                    cam_from_table.compose(&turn).compose(&table_from_board)
                })
                .collect();
            (poses, angles.into_iter().map(Some).collect())
        }
    };
    let renderer = hw_sim::TargetRenderer::new(rig);
    let corners_path = gt.join("corners.jsonl");
    let mut corners = String::new();
    let period_ns = 1_000_000_000 / 15;
    for (k, (pose, angle)) in poses.iter().zip(&angles).enumerate() {
        let pair = renderer.render(&b, pose, opts.noise_sigma, opts.seed.wrapping_mul(1000).wrapping_add(k as u64));
        let picture = |data: &Vec<u8>| Picture::Raw { width: pair.width, height: pair.height, channels: 1, data: data.clone() };
        let t = 1_000_000_000 + k as u64 * period_ns;
        writer.append(&StereoFrame { seq: k as u64, left: picture(&pair.left), right: picture(&pair.right), t_left_ns: t, t_right_ns: t, table_deg: *angle })?;
        let pts = |v: &[Option<(f64, f64)>]| v.iter().map(|p| p.map(|(x, y)| [x, y])).collect::<Vec<_>>();
        corners += &json!({"seq": k, "left": pts(&pair.left_corners), "right": pts(&pair.right_corners), "left_from_board": pose.matrix()}).to_string();
        corners.push('\n');
        progress(k + 1, poses.len());
    }
    crate::io::write_atomic(&corners_path, corners.as_bytes()).map_err(|e| io(&corners_path, e))?;
    Ok(())
}

/// The lab's table seen from the rig (as the scan recordings' lab, aimed at the board's
/// middle), and the true axis in the left camera frame.
fn table_geometry(rig: &hw_sim::Rig, b: &hw_sim::Chessboard) -> (hw_sim::Pose, TurntableAxis) {
    let (_, _, _, y1) = b.extent();
    let height = y1 + 2.0 * b.square_mm;
    // A flat stand-in object as tall as the board: only its bounds aim the cameras.
    let object = hw_sim::Mesh { vertices: vec![[-50.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, height as f32, 0.0]], triangles: vec![[0, 1, 2]] };
    let mut scene = hw_sim::SceneConfig::realistic(object);
    scene.rig = *rig;
    let (point, dir) = scene.axis_in_left_camera();
    (scene.cam_from_table(), TurntableAxis { axis_point_mm: point, axis_dir: dir, source: "ground truth".into() })
}

/// The board standing upright on the table, its face towards the cameras at table angle 0,
/// its lower edge on the table surface, off the axis by a little more than a square each way
/// (so the corners' circles differ in radius).
fn board_on_table(b: &hw_sim::Chessboard) -> hw_sim::Pose {
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
    /// The board `scene` describes, for `rig`, delivered at `fps` when `paced`.
    pub fn new(rig: &hw_sim::Rig, scene: &super::TargetScene, fps: f64, paced: bool, seed: u64) -> TargetMode {
        let board = hw_sim::Chessboard { cols: scene.cols, rows: scene.rows, square_mm: scene.square_mm };
        let (held, table) = if scene.on_table {
            let (cam_from_table, _) = table_geometry(rig, &board);
            (Vec::new(), Some((cam_from_table, board_on_table(&board))))
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
