//! Calibration on the real XIMEA chessboard pairs (`../shared/data/stereo-calib-chessboard-ximea`)
//! against OpenCV's corners (`corners.json`).

mod support;

use spinscan::calib::board::{detect, BoardSize, DetectParams};
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
