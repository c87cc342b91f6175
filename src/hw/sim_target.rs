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
use super::sim::{board_on_table, calib_of, table_geometry, SimError};
use crate::recording::RecordingWriter;

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
    /// The board: inner corners along a row, rows, and the square's side in mm.
    pub board: super::TargetScene,
    pub frames: usize,
    pub ideal: bool,
    pub seed: u64,
    pub noise_sigma: f64,
    pub image_size: (usize, usize),
    /// Distance of the held board from the left camera, mm (`Chessboard`).
    pub distance_mm: f64,
    /// Table angles from −sweep to +sweep, degrees (`ChessboardOnTable`).
    pub sweep_deg: f64,
    /// `ChessboardOnTable`: the lab of this built-in object's recordings (`sim render
    /// --object NAME`, cameras aimed at its middle), so the axis calibrated is theirs.
    pub object: Option<String>,
    /// The rig's focal length and baseline; with `ChessboardOnTable`, also the cameras'
    /// distance and tilt around the table (the object's offset plays no part).
    pub lab: super::sim::Lab,
}

impl Default for TargetOptions {
    fn default() -> Self {
        TargetOptions {
            kind: TargetKind::Chessboard,
            board: super::TargetScene { cols: 9, rows: 6, square_mm: 20.0, on_table: false },
            frames: 20,
            ideal: false,
            seed: 1,
            noise_sigma: 1.5,
            image_size: (640, 480),
            distance_mm: 600.0,
            sweep_deg: 50.0,
            object: None,
            lab: super::sim::Lab::default(),
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
    let b = hw_sim::Chessboard { cols: opts.board.cols, rows: opts.board.rows, square_mm: opts.board.square_mm };
    if b.cols < 3 || b.rows < 3 || !(b.square_mm > 0.0 && b.square_mm.is_finite()) {
        return Err(SimError::Option { what: "the board", expected: "at least 3×3 inner corners and a positive square size", got: format!("{}×{}, {} mm", b.cols, b.rows, b.square_mm) });
    }
    opts.lab.check()?;
    let rig = opts.lab.rig(opts.ideal, (w, h));
    let nominal = calib_of(&opts.lab.rig(true, (w, h)));
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
            let (cam_from_table, axis) = table_geometry(&rig, &b, opts.object.as_deref(), &opts.lab)?;
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
