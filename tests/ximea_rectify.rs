//! Rectification of the real XIMEA rig (`../shared/data/stereo-calib-chessboard-ximea`) against
//! OpenCV 5's own matrices and chessboard corners: guards Bouguet's method, the 14-coefficient
//! lens model and the negative-disparity rig.

mod support;

use nalgebra::DMatrix;
use spinscan::calib::filestorage::Document;
use spinscan::calib::StereoCalib;
use spinscan::stereo::Rectification;

fn dataset() -> std::path::PathBuf {
    support::shared_data("stereo-calib-chessboard-ximea")
}

fn to_dmatrix<const R: usize, const C: usize>(m: &nalgebra::SMatrix<f64, R, C>) -> DMatrix<f64> {
    DMatrix::from_fn(R, C, |r, c| m[(r, c)])
}

/// OpenCV's figure (mean over pairs of mean |y_left − y_right| after rectification), per alpha.
const OPENCV_ROW_ERROR_PX: [(f64, &str, f64); 3] = [(-1.0, "m1", 0.106), (0.0, "0", 0.124), (1.0, "1", 0.094)];

#[test]
fn matrices_equal_opencv5_for_every_alpha() {
    let dir = dataset();
    let calib = StereoCalib::load(&dir).expect("ximea calibration loads");
    assert_eq!(calib.left.distortion.coeffs().len(), 14);
    let text = std::fs::read_to_string(dir.join("opencv_rectify.yaml")).unwrap();
    let doc = Document::parse(&text).unwrap();
    for (alpha, suffix, _) in OPENCV_ROW_ERROR_PX {
        let rect = Rectification::compute(&calib, (640, 512), alpha).unwrap();
        let get = |name: &str| {
            let key = format!("{name}_alpha_{suffix}");
            doc.get(&key).unwrap().as_matrix(&key).unwrap()
        };
        for (name, ours) in [("R1", to_dmatrix(&rect.r1)), ("R2", to_dmatrix(&rect.r2))] {
            let diff = (&ours - get(name)).abs().max();
            println!("alpha {alpha:>4}: {name} max |ours − OpenCV| = {diff:.1e}");
            assert!(diff <= 1e-9, "alpha {alpha}: {name} differs by {diff:e}");
        }
        for (name, ours) in [("P1", to_dmatrix(&rect.p1)), ("P2", to_dmatrix(&rect.p2)), ("Q", to_dmatrix(&rect.q))] {
            let theirs = get(name);
            let rel = (&ours - &theirs).norm() / theirs.norm();
            println!("alpha {alpha:>4}: {name} ‖ours − OpenCV‖ / ‖OpenCV‖ = {rel:.1e}");
            assert!(rel <= 1e-6, "alpha {alpha}: {name} differs by {rel:e} of its norm\nours {ours}\nopencv {theirs}");
        }
        assert_eq!(rect.disparity_sign, -1, "this rig's rectified right camera sits left of the left one");
    }
}

#[test]
fn corners_land_on_the_same_row() {
    let dir = dataset();
    let calib = StereoCalib::load(&dir).unwrap();
    let corners: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("corners.json")).unwrap()).unwrap();
    let corners = corners["corners"].as_object().unwrap();
    let points = |name: &str| -> Vec<(f64, f64)> {
        corners[name].as_array().unwrap().iter().map(|p| (p[0].as_f64().unwrap(), p[1].as_f64().unwrap())).collect()
    };
    for (alpha, _, opencv) in OPENCV_ROW_ERROR_PX {
        let rect = Rectification::compute(&calib, (640, 512), alpha).unwrap();
        let mut per_pair = Vec::new();
        let mut disparities = Vec::new();
        for i in 1..=25 {
            let (l, r) = (points(&format!("left{i:02}.jpg")), points(&format!("right{i:02}.jpg")));
            assert_eq!(l.len(), r.len());
            let mut sum = 0.0;
            for (pl, pr) in l.iter().zip(&r) {
                let a = rect.rectify_left_point(&calib, *pl);
                let b = rect.rectify_right_point(&calib, *pr);
                sum += (a.1 - b.1).abs();
                disparities.push(a.0 - b.0);
            }
            per_pair.push(sum / l.len() as f64);
        }
        let mean = per_pair.iter().sum::<f64>() / per_pair.len() as f64;
        println!("alpha {alpha:>4}: mean |y_left − y_right| = {mean:.4} px (OpenCV {opencv:.3} px)");
        assert!(mean <= opencv + 0.02, "alpha {alpha}: {mean:.4} px > OpenCV's {opencv} + 0.02");
        assert!(disparities.iter().all(|&d| d < 0.0), "every corner has a negative disparity on this rig");
    }
}
