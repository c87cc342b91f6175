//! Calibration on the real XIMEA chessboard pairs (`../shared/data/stereo-calib-chessboard-ximea`)
//! against OpenCV's corners (`corners.json`).

mod support;

use spinscan::calib::board::{detect, BoardSize, DetectParams};
use spinscan::calib::solve::{board_points, calibrate_stereo, LensModel, TargetView};
use spinscan::stereo::Rectification;
use spinscan::stereo::GrayView;

fn opencv_corners() -> serde_json::Value {
    let p = support::shared_data("stereo-calib-chessboard-ximea").join("corners.json");
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

#[test]
fn boards_are_found_in_every_image_within_a_tenth_of_a_pixel_of_opencv_s_corners() {
    let dir = support::shared_data("stereo-calib-chessboard-ximea");
    let reference = opencv_corners();
    let board = BoardSize { cols: 9, rows: 6 };
    let mut all = Vec::new();
    for side in ["left", "right"] {
        for i in 1..=25 {
            let name = format!("{side}{i:02}.jpg");
            let img = spinscan::io::load_image(&dir.join(&name)).unwrap();
            let view = GrayView::new(img.width, img.height, &img.gray).unwrap();
            let found = detect(&view, board, &DetectParams::default()).unwrap_or_else(|e| panic!("{name}: {e}"));
            let theirs: Vec<[f64; 2]> = reference["corners"][&name].as_array().unwrap().iter().map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()]).collect();
            assert_eq!(found.points.len(), 54);
            let mut sum = 0.0;
            for p in &found.points {
                let d = theirs.iter().map(|q| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()).fold(f64::INFINITY, f64::min);
                sum += d;
            }
            let mean = sum / 54.0;
            eprintln!("{name}: mean {mean:.4} px, spacing {:.1}, edges {:.2} px", found.spacing_px, found.edge_px);
            all.push(mean);
        }
    }
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    eprintln!("mean over 50 images {mean:.4} px");
    assert!(mean < 0.1, "{mean}");
}

fn detected_views() -> (Vec<TargetView>, Vec<TargetView>) {
    let dir = support::shared_data("stereo-calib-chessboard-ximea");
    let board = BoardSize { cols: 9, rows: 6 };
    let object = board_points(9, 6, 24.0);
    let view = |name: String| {
        let img = spinscan::io::load_image(&dir.join(&name)).unwrap();
        let found = detect(&GrayView::new(img.width, img.height, &img.gray).unwrap(), board, &DetectParams::default()).unwrap();
        TargetView { object: object.clone(), image: found.points }
    };
    ((1..=25).map(|i| view(format!("left{i:02}.jpg"))).collect(), (1..=25).map(|i| view(format!("right{i:02}.jpg"))).collect())
}

/// OpenCV 5.0 on the same 25 pairs (its corners, `calibrateCamera` then `stereoCalibrate`
/// with the intrinsics refined, 5 coefficients; `bench/peer_calib.py`).
const OPENCV_RMS: (f64, f64, f64) = (0.1488, 0.1604, 0.1739);
const OPENCV_T_NORM: f64 = 92.028;
const OPENCV_ROWS_PX: f64 = 0.1031;

#[test]
fn the_rig_is_calibrated_as_well_as_opencv_does_it() {
    let (left, right) = detected_views();
    let sol = calibrate_stereo(&left, &right, (640, 512), LensModel::Five).unwrap();
    let t = sol.calib.t_mm.norm();
    eprintln!("rms left {:.4} right {:.4} stereo {:.4} (OpenCV {:?}); |T| {t:.3} (OpenCV {OPENCV_T_NORM})", sol.rms_left, sol.rms_right, sol.rms_stereo, OPENCV_RMS);
    assert!(sol.rms_stereo <= OPENCV_RMS.2 + 0.02, "stereo rms {}", sol.rms_stereo);
    assert!(sol.rms_left <= OPENCV_RMS.0 + 0.02 && sol.rms_right <= OPENCV_RMS.1 + 0.02);
    assert!((t / OPENCV_T_NORM - 1.0).abs() < 0.002, "|T| {t}");

    // OpenCV's corners rectified with this calibration land on the same rows.
    let reference = opencv_corners();
    let rect = Rectification::compute(&sol.calib, (640, 512), -1.0).unwrap();
    let pts = |name: &str| -> Vec<(f64, f64)> { reference["corners"][name].as_array().unwrap().iter().map(|p| (p[0].as_f64().unwrap(), p[1].as_f64().unwrap())).collect() };
    let mut per_pair = Vec::new();
    for i in 1..=25 {
        let (l, r) = (pts(&format!("left{i:02}.jpg")), pts(&format!("right{i:02}.jpg")));
        let sum: f64 = l.iter().zip(&r).map(|(a, b)| (rect.rectify_left_point(&sol.calib, *a).1 - rect.rectify_right_point(&sol.calib, *b).1).abs()).sum();
        per_pair.push(sum / l.len() as f64);
    }
    let rows = per_pair.iter().sum::<f64>() / 25.0;
    eprintln!("row mismatch after rectification {rows:.4} px (OpenCV's calibration {OPENCV_ROWS_PX})");
    assert!(rows <= OPENCV_ROWS_PX + 0.02, "{rows}");
}

fn spinscan(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_spinscan")).args(args).output().expect("spinscan runs")
}

/// Eight good pairs, a non-image, a pair without a board and a left image without its right
/// one: each bad input named in one line, the rest calibrated; then a wrong `--board` and too
/// few pairs, exit 3 with the count.
#[test]
fn calibrate_stereo_names_every_bad_input_and_uses_the_rest() {
    let src = support::shared_data("stereo-calib-chessboard-ximea");
    let dir = support::temp_dir("calibrate-stereo");
    for i in [1, 3, 5, 9, 12, 17, 21, 25] {
        for side in ["left", "right"] {
            std::fs::copy(src.join(format!("{side}{i:02}.jpg")), dir.join(format!("{side}{i:02}.jpg"))).unwrap();
        }
    }
    std::fs::write(dir.join("left30.jpg"), b"not a picture").unwrap();
    std::fs::copy(src.join("right02.jpg"), dir.join("right30.jpg")).unwrap();
    // A pair with no board: a flat grey picture.
    let grey = vec![128u8; 640 * 512 * 3];
    spinscan::io::write_rgb_png(&dir.join("left31.jpg"), 640, 512, &grey).unwrap();
    spinscan::io::write_rgb_png(&dir.join("right31.jpg"), 640, 512, &grey).unwrap();
    std::fs::copy(src.join("left04.jpg"), dir.join("left32.jpg")).unwrap();

    let (l, r) = (format!("{}/left*.jpg", dir.display()), format!("{}/right*.jpg", dir.display()));
    let yaml = dir.join("calib.yaml");
    let json = dir.join("report.json");
    let o = spinscan(&["calibrate", "stereo", "--left", &l, "--right", &r, "--board", "9x6", "--square-mm", "24", "-o", yaml.to_str().unwrap(), "--json", json.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{err}\n{out}");
    assert!(err.lines().any(|l| l.contains("left30.jpg") && l.contains("left out")), "the non-image is named: {err}");
    assert!(err.lines().any(|l| l.contains("left31.jpg") && l.contains("no 9×6 board found")), "the empty pair is named: {err}");
    assert!(err.lines().any(|l| l.contains("left32.jpg") && l.contains("no right image")), "the unpaired image is named: {err}");
    assert!(out.contains("pairs used: 8 of 10"), "{out}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(report["pairs_used"], 8);
    assert!(report["rms_stereo"].as_f64().unwrap() < 0.3, "{report}");
    // What it wrote loads as a calibration, and its RMS figures are in it.
    let calib = spinscan::calib::StereoCalib::load(&yaml).unwrap();
    assert!((calib.t_mm.norm() - 92.0).abs() < 1.0, "{}", calib.t_mm);
    assert!(std::fs::read_to_string(&yaml).unwrap().contains("rms_stereo: "));

    // A wrong board size: every pair says what it saw, and the run fails with the count.
    let o = spinscan(&["calibrate", "stereo", "--left", &l, "--right", &r, "--board", "8x6", "--square-mm", "24", "-o", yaml.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(err.contains("a 9×6 grid of corners, larger than the 8×6 board"), "{err}");
    assert!(err.contains("boards found in 0 of 10 pairs; a calibration needs at least 4"), "{err}");

    // Counts that differ and names that do not pair up.
    let o = spinscan(&["calibrate", "stereo", "--left", &format!("{}/left0*.jpg", dir.display()), "--right", &format!("{}/right*1.jpg", dir.display()), "--square-mm", "24", "-o", yaml.to_str().unwrap()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(err.contains("left images but") && err.contains("do not pair up"), "{err}");
}

/// Corners found on rendered boards (realistic rig: distortion, blur, noise) lie where the
/// renderer put them, and in the same order.
#[test]
fn rendered_boards_are_found_where_they_are() {
    let rig = hw_sim::Rig::realistic(640, 480, 700.0, 60.0);
    let board = hw_sim::Chessboard { cols: 9, rows: 6, square_mm: 20.0 };
    let renderer = hw_sim::TargetRenderer::new(rig);
    let mut errs = Vec::new();
    for (k, pose) in hw_sim::target::stereo_poses(&rig, &board, 9, 600.0, 7).iter().enumerate() {
        let pair = renderer.render(&board, pose, 1.5, k as u64);
        for (img, truth) in [(&pair.left, &pair.left_corners), (&pair.right, &pair.right_corners)] {
            let found = detect(&GrayView::new(640, 480, img).unwrap(), BoardSize { cols: 9, rows: 6 }, &DetectParams::default()).unwrap_or_else(|e| panic!("pose {k}: {e}"));
            for (i, (p, t)) in found.points.iter().zip(truth).enumerate() {
                let t = t.unwrap();
                let e = ((p[0] - t.0).powi(2) + (p[1] - t.1).powi(2)).sqrt();
                if e > 0.3 {
                    eprintln!("pose {k} corner {i}: found ({:.2}, {:.2}), truth ({:.2}, {:.2})", p[0], p[1], t.0, t.1);
                }
                errs.push(e);
            }
        }
    }
    errs.sort_by(f64::total_cmp);
    let (median, worst) = (errs[errs.len() / 2], errs[errs.len() - 1]);
    eprintln!("corner error vs truth: median {median:.4} px, worst {worst:.4} px");
    assert!(median < 0.05 && worst < 0.3, "median {median}, worst {worst}");
}

fn angle_deg(a: nalgebra::Vector3<f64>, b: nalgebra::Vector3<f64>) -> f64 {
    a.normalize().dot(&b.normalize()).clamp(-1.0, 1.0).acos().to_degrees()
}

/// The simulated lab's chessboard recordings (realistic rig): the rig and then the turntable
/// axis recovered through the CLI, each within the bounds of the truth in gt/.
#[test]
fn the_simulated_rig_and_turntable_are_recovered() {
    let dir = support::temp_dir("calibrate-sim");
    let run = |args: &[&str]| {
        let o = spinscan(args);
        assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
    };
    let (st, tt) = (dir.join("stereo"), dir.join("table"));
    run(&["sim", "render", "--target", "chessboard", "--frames", "16", "--seed", "3", "-o", st.to_str().unwrap()]);
    run(&["sim", "render", "--target", "chessboard-on-table", "--frames", "9", "--seed", "3", "-o", tt.to_str().unwrap()]);
    let calib_path = dir.join("calib.yaml");
    run(&["calibrate", "stereo", "--recording", st.to_str().unwrap(), "--square-mm", "20", "-o", calib_path.to_str().unwrap()]);
    let got = spinscan::calib::StereoCalib::load(&calib_path).unwrap();
    let truth = spinscan::calib::StereoCalib::load(&st.join("gt/calib.yaml")).unwrap();
    for (side, g, t) in [("left", &got.left, &truth.left), ("right", &got.right, &truth.right)] {
        let (fx, fy) = (g.k[(0, 0)] / t.k[(0, 0)] - 1.0, g.k[(1, 1)] / t.k[(1, 1)] - 1.0);
        let (cx, cy) = (g.k[(0, 2)] - t.k[(0, 2)], g.k[(1, 2)] - t.k[(1, 2)]);
        eprintln!("{side}: fx {:+.3} %, fy {:+.3} %, cx {cx:+.3} px, cy {cy:+.3} px", 100.0 * fx, 100.0 * fy);
        assert!(fx.abs() < 0.003 && fy.abs() < 0.003 && cx.abs() < 1.0 && cy.abs() < 1.0);
    }
    let baseline = got.t_mm.norm() - truth.t_mm.norm();
    let r_err = nalgebra::Rotation3::from_matrix_unchecked(got.r * truth.r.transpose()).angle().to_degrees();
    eprintln!("baseline {baseline:+.4} mm, R {r_err:.4}°");
    assert!(baseline.abs() < 0.3 && r_err < 0.05);

    let axis_path = dir.join("turntable.yaml");
    run(&["calibrate", "turntable", "--recording", tt.to_str().unwrap(), "--calib", calib_path.to_str().unwrap(), "--square-mm", "20", "-o", axis_path.to_str().unwrap()]);
    let read = |p: &std::path::Path| spinscan::recording::TurntableAxis::parse(p, &std::fs::read_to_string(p).unwrap()).unwrap();
    let (got, truth) = (read(&axis_path), read(&tt.join("gt/turntable.yaml")));
    let (gd, td) = (nalgebra::Vector3::from(got.axis_dir), nalgebra::Vector3::from(truth.axis_dir));
    let (gp, tp) = (nalgebra::Vector3::from(got.axis_point_mm), nalgebra::Vector3::from(truth.axis_point_mm));
    // The true point's distance from the fitted line.
    let off = (tp - gp) - gd * gd.dot(&(tp - gp));
    eprintln!("axis direction {:.4}°, point {:.3} mm from the fitted axis", angle_deg(gd, td), off.norm());
    assert!(angle_deg(gd, td) < 0.1 && off.norm() < 0.5);
}

/// A board out of focus is named as such, not as a wrong board size.
#[test]
fn a_blurred_board_is_named_blurred() {
    let rig = hw_sim::Rig::ideal(640, 480, 700.0, 60.0);
    let board = hw_sim::Chessboard { cols: 9, rows: 6, square_mm: 20.0 };
    let pose = hw_sim::Pose { r: hw_sim::math::IDENTITY, t: [-80.0, -50.0, 450.0] };
    let pair = hw_sim::TargetRenderer::new(rig).render(&board, &pose, 0.5, 1);
    let size = BoardSize { cols: 9, rows: 6 };
    let sharp = detect(&GrayView::new(640, 480, &pair.left).unwrap(), size, &DetectParams::default()).unwrap();
    // Defocus: three passes of a 9-pixel box filter each way (σ ≈ 4.5 px).
    let mut img: Vec<f32> = pair.left.iter().map(|&v| f32::from(v)).collect();
    for _ in 0..3 {
        for (w, h, stride, step) in [(640usize, 480usize, 640usize, 1usize), (480, 640, 1, 640)] {
            let src = img.clone();
            for line in 0..h {
                for i in 0..w {
                    let (lo, hi) = (i.saturating_sub(4), (i + 4).min(w - 1));
                    let sum: f32 = (lo..=hi).map(|k| src[line * stride + k * step]).sum();
                    img[line * stride + i * step] = sum / (hi - lo + 1) as f32;
                }
            }
        }
    }
    let blurred: Vec<u8> = img.iter().map(|v| v.round() as u8).collect();
    let err = detect(&GrayView::new(640, 480, &blurred).unwrap(), size, &DetectParams::default()).unwrap_err();
    eprintln!("sharp edges {:.2} px on {:.1} px squares; blurred: {err}", sharp.edge_px, sharp.spacing_px);
    assert!(matches!(err, spinscan::calib::board::DetectFailure::Blurred { .. }), "{err}");
    assert!(err.to_string().starts_with("board too blurred"), "{err}");
}

/// A board held in front of a cluttered scene (Middlebury's Teddy: toys, text, a
/// chequered cloth's worth of saddles) is still found where it is.
#[test]
fn a_board_is_found_in_a_cluttered_scene() {
    let teddy = spinscan::io::load_image(&support::shared_data("middlebury-stereo").join("teddy/im2.png")).unwrap();
    let (w, h) = (teddy.width, teddy.height);
    let rig = hw_sim::Rig::ideal(w, h, 450.0, 60.0);
    let board = hw_sim::Chessboard { cols: 9, rows: 6, square_mm: 12.0 };
    let pose = hw_sim::Pose { r: hw_sim::math::rotation([0.3, 1.0, 0.1], 0.5), t: [-40.0, -20.0, 400.0] };
    let pair = hw_sim::TargetRenderer::new(rig).render(&board, &pose, 1.0, 3);
    // The board (inside its outline, projected) where the renderer drew it, Teddy elsewhere.
    let (x0, y0, x1, y1) = board.extent();
    let outline: Vec<(f64, f64)> = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)].iter().map(|&(x, y)| rig.left.project(pose.apply([x, y, 0.0]))).collect();
    let inside = |x: f64, y: f64| {
        let side = |k: usize| {
            let (a, b) = (outline[k], outline[(k + 1) % 4]);
            (b.0 - a.0) * (y - a.1) - (b.1 - a.1) * (x - a.0)
        };
        let s: Vec<f64> = (0..4).map(side).collect();
        s.iter().all(|&v| v >= 0.0) || s.iter().all(|&v| v <= 0.0)
    };
    let img: Vec<u8> = (0..w * h).map(|i| if inside((i % w) as f64, (i / w) as f64) { pair.left[i] } else { teddy.gray[i] }).collect();
    let found = detect(&GrayView::new(w, h, &img).unwrap(), BoardSize { cols: 9, rows: 6 }, &DetectParams::default()).unwrap();
    let worst = found.points.iter().zip(&pair.left_corners).map(|(p, t)| {
        let t = t.unwrap();
        ((p[0] - t.0).powi(2) + (p[1] - t.1).powi(2)).sqrt()
    }).fold(0.0, f64::max);
    assert!(worst < 0.3, "worst corner {worst} px off");
}

/// A board standing on the table of another lab (`sim render --target chessboard-on-table
/// --object NAME` with that lab's rig and distances) has the axis of that lab's recordings of
/// the object, and rectifies with that rig's focal length and baseline.
#[test]
fn a_board_on_another_lab_s_table_has_that_lab_s_axis() {
    let dir = support::temp_dir("calibrate-lab");
    let lab = ["--focal-px", "900", "--baseline-mm", "40", "--object-distance-mm", "400", "--camera-tilt-deg", "20"];
    let (board, object) = (dir.join("board"), dir.join("object"));
    let run = |args: &[&str]| {
        let o = spinscan(args);
        assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
    };
    run(&[&["sim", "render", "--target", "chessboard-on-table", "--object", "egg", "--frames", "2", "-o", board.to_str().unwrap()][..], &lab].concat());
    run(&[&["sim", "render", "--object", "egg", "--triangles", "2000", "--frames", "1", "-o", object.to_str().unwrap()][..], &lab].concat());
    let read = |p: &std::path::Path| std::fs::read_to_string(p).unwrap();
    assert_eq!(read(&board.join("gt/turntable.yaml")), read(&object.join("gt/turntable.yaml")));
    let (b, o) = (spinscan::calib::StereoCalib::load(&board.join("gt/calib.yaml")).unwrap(), spinscan::calib::StereoCalib::load(&object.join("calib.yaml")).unwrap());
    assert!((b.left.k[(0, 0)] / 900.0 - 1.0).abs() < 0.01 && (b.t_mm.norm() - 40.0).abs() < 1.5, "{:?} {:?}", b.left.k, b.t_mm);
    assert_eq!((b.left.k, b.t_mm), (o.left.k, o.t_mm));
    // A held board has no table: the lab's place around the table is refused with it.
    let o = spinscan(&["sim", "render", "--target", "chessboard", "--frames", "2", "--object-distance-mm", "400", "-o", dir.join("held").to_str().unwrap()]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("go with --target chessboard-on-table"));
}
