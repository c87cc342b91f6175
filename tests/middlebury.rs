//! Accuracy on the Middlebury pairs (`../shared/data/middlebury-stereo`), scored the way
//! `../shared/bench/peer_stereo.py` scores: bad2 counts a missing disparity as wrong, bad2m is
//! over matched pixels only. The bounds are OpenCV 5.0 StereoBM's own figures on the same
//! pairs (block 9, uniqueness 10, speckle 100/2), printed by that script: this test guards
//! "at least as good as BM" on both.

mod support;

use spinscan::io::load_image;
use spinscan::stereo::{DisparityMap, GrayView, MatchParams, Method, StereoMatcher};

struct Case {
    dir: &'static str,
    left: &'static str,
    right: &'static str,
    gt: &'static str,
    gt_scale: f32,
    num_disparities: u32,
    /// OpenCV BM's bad2 % and bad2m % on this pair.
    bm_bad2: f64,
    bm_bad2m: f64,
    /// OpenCV SGBM's bad2 % (3-way, block 5, P1 200, P2 800, uniqueness 10, speckle 100/2).
    sgbm_bad2: f64,
    /// What `--method sgm` must stay below: SGBM's bad2 where it is beaten, else the figure
    /// reached when this bound was set (Tsukuba: 5.88 %, not yet SGBM's 5.11; docs/matcher.md).
    sgm_bound: f64,
}

const CASES: [Case; 3] = [
    Case { dir: "tsukuba", left: "scene1.row3.col3.ppm", right: "scene1.row3.col4.ppm", gt: "truedisp.row3.col3.pgm", gt_scale: 16.0, num_disparities: 16, bm_bad2: 16.23, bm_bad2m: 2.99, sgbm_bad2: 5.11, sgm_bound: 6.0 },
    Case { dir: "teddy", left: "im2.png", right: "im6.png", gt: "disp2.pgm", gt_scale: 4.0, num_disparities: 64, bm_bad2: 35.70, bm_bad2m: 6.13, sgbm_bad2: 23.48, sgm_bound: 23.48 },
    Case { dir: "reindeer", left: "view1.png", right: "view5.png", gt: "disp1.png", gt_scale: 2.0, num_disparities: 128, bm_bad2: 47.61, bm_bad2m: 5.37, sgbm_bad2: 32.55, sgm_bound: 32.55 },
];

/// (bad2 %, bad2m %, density %) over pixels with ground truth.
fn score(disp: &DisparityMap, gt: &[u8], scale: f32) -> (f64, f64, f64) {
    let (mut with_gt, mut bad, mut matched, mut bad_matched) = (0usize, 0usize, 0usize, 0usize);
    for (i, &g) in gt.iter().enumerate() {
        if g == 0 {
            continue;
        }
        with_gt += 1;
        // Scored through the 16-bit PNG the CLI writes (|d| × 256, rounded), as the script does.
        match disp.values()[i] {
            d if d.is_finite() => {
                matched += 1;
                let d = (d.abs() * 256.0).round() / 256.0;
                let wrong = (d - g as f32 / scale).abs() > 2.0;
                bad += wrong as usize;
                bad_matched += wrong as usize;
            }
            _ => bad += 1,
        }
    }
    let pct = |a: usize, b: usize| 100.0 * a as f64 / b.max(1) as f64;
    (pct(bad, with_gt), pct(bad_matched, matched), pct(matched, with_gt))
}

/// The pair's disparity map with `params` (full range), and its ground truth.
fn run(c: &Case, params: MatchParams) -> (DisparityMap, Vec<u8>) {
    let dir = support::shared_data("middlebury-stereo").join(c.dir);
    let (l, r) = (load_image(&dir.join(c.left)).unwrap(), load_image(&dir.join(c.right)).unwrap());
    let gt = load_image(&dir.join(c.gt)).unwrap().gray;
    let mut m = StereoMatcher::new(MatchParams { num_disparities: c.num_disparities, ..params }.validate().unwrap());
    let iv = m.full_intervals(l.width, l.height, None);
    let mut out = DisparityMap::new(l.width, l.height);
    m.compute(GrayView::new(l.width, l.height, &l.gray).unwrap(), GrayView::new(r.width, r.height, &r.gray).unwrap(), &iv, &mut out).unwrap();
    (out, gt)
}

#[test]
fn semi_global_matching_beats_opencv_sgbm_where_it_is_measured_to() {
    for c in &CASES {
        let (out, gt) = run(c, MatchParams::for_method(Method::Sgm));
        let (bad2, bad2m, density) = score(&out, &gt, c.gt_scale);
        println!("{:<9} sgm bad2 {bad2:6.2} % (SGBM {:5.2})  bad2m {bad2m:5.2} %  density {density:5.1} %", c.dir, c.sgbm_bad2);
        assert!(bad2 <= c.sgm_bound, "{}: sgm bad2 {bad2:.2} % is above its bound {} % (SGBM {} %)", c.dir, c.sgm_bound, c.sgbm_bad2);
        assert!(bad2 < c.bm_bad2, "{}: sgm bad2 {bad2:.2} % is not below bm's bound {} %", c.dir, c.bm_bad2);
    }
}

#[test]
fn at_least_as_accurate_as_opencv_bm() {
    for c in &CASES {
        let (out, gt) = run(c, MatchParams::default());
        let (bad2, bad2m, density) = score(&out, &gt, c.gt_scale);
        println!("{:<9} bad2 {bad2:6.2} % (BM {:5.2})  bad2m {bad2m:5.2} % (BM {:5.2})  density {density:5.1} %", c.dir, c.bm_bad2, c.bm_bad2m);
        assert!(bad2 <= c.bm_bad2, "{}: bad2 {bad2:.2} % is worse than OpenCV BM's {} %", c.dir, c.bm_bad2);
        assert!(bad2m <= c.bm_bad2m, "{}: bad2m {bad2m:.2} % is worse than OpenCV BM's {} %", c.dir, c.bm_bad2m);
    }
}
