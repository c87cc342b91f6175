//! Replayed recordings of rigs other than the default lab's: a search range short of the
//! object, a toed-in rig, cameras of different gain, the silhouette's rim left out of the
//! views, a rig whose right camera sits left of the left one.

mod support;

use std::path::Path;

use spinscan::hw::sim::{RenderOptions, SimObject};
use spinscan::pipeline::replay::{self, ReplayOptions};
use spinscan::recording::Recording;
use support::{read_json, replay, replay_opts, small_recording};

/// A range short of the object (the first 32 disparities; the egg lies beyond them): given
/// leave to (`fit_range`, the CLI's default where no range is given), the first frame's probe
/// widens it to hold the object, and the views come out as over a range that holds it, which
/// the probe leaves as it is. Without leave, the matches at the range's end are dropped.
#[test]
fn a_range_short_of_the_object_is_widened_to_hold_it() {
    let dir = support::temp_dir("rec-range");
    small_recording(&dir.join("sim"), 2, 0.0);
    let run = |n: u32, fit: bool, out: &str| {
        let mut opts = replay_opts();
        opts.pipeline.matching.num_disparities = n;
        opts.pipeline.fit_range = fit;
        replay::run_recording(Recording::open(&dir.join("sim")).unwrap(), &dir.join(out), &opts, &mut |_, _, _| {}).unwrap();
        read_json(&dir.join(out).join("report.json"))
    };
    let points = |r: &serde_json::Value| -> Vec<u64> { r["frames"].as_array().unwrap().iter().map(|f| f["points"].as_u64().unwrap()).collect() };
    let held = run(80, true, "held");
    let fit = &held["matching"]["range_fit"];
    println!("held: {fit}");
    assert_eq!((held["matching"]["min_disparity"].as_i64(), held["matching"]["num_disparities"].as_u64(), fit["widened"].as_bool()), (Some(0), Some(80), Some(false)), "{fit}");
    let (lo, hi) = (fit["object_disparities"][0].as_f64().unwrap(), fit["object_disparities"][1].as_f64().unwrap());
    assert!(lo > 33.0 && hi < 79.0, "{fit}");
    let short = run(32, false, "short");
    assert!(points(&short).iter().all(|&p| p * 10 < points(&held)[0]), "{:?} against {:?}", points(&short), points(&held));
    let widened = run(32, true, "widened");
    let m = &widened["matching"];
    println!("widened: {m}");
    assert_eq!(m["range_fit"]["widened"], true);
    let (min, n) = (m["min_disparity"].as_i64().unwrap(), m["num_disparities"].as_i64().unwrap());
    assert!(min <= lo as i64 - 15 && min + n - 1 >= hi as i64 + 16 && n % 16 == 0, "{m}");
    for (g, w) in points(&widened).iter().zip(points(&held)) {
        assert!(g.abs_diff(w) * 50 <= w, "{:?} points against {:?} over 0 … 79", points(&widened), points(&held));
    }
}

/// A toed-in rig (the right camera turned to aim at the object, 160 mm from the left one,
/// 450 mm away): rectified at alpha 0 the object leaves the right image and nothing matches;
/// by default the rectification keeps the middle of both views (`rectify_alpha` over 0) and
/// the range is fitted to the object, and the views hold as many points as over the rig
/// whose cameras look the same way.
#[test]
fn a_toed_in_rig_keeps_the_object_in_both_rectified_images() {
    let dir = support::temp_dir("rec-toed-in");
    let scan = |toe_in_deg: f64, alpha: Option<f64>, out: &str| -> serde_json::Value {
        let rec = dir.join(format!("rec{toe_in_deg}"));
        if !rec.exists() {
            let lab = spinscan::hw::sim::Lab { baseline_mm: 160.0, camera_tilt_deg: 25.0, toe_in_deg, ..Default::default() };
            let opts = RenderOptions { object: SimObject::Builtin { name: "egg".into(), triangles: 20_000 }, frames: 2, image_size: (320, 240), lab, ..RenderOptions::default() };
            spinscan::hw::sim::render_recording(&opts, &rec, &mut |_, _| {}).unwrap();
        }
        let mut opts = replay_opts();
        opts.pipeline.alpha = alpha;
        opts.pipeline.fit_range = true;
        replay::run_recording(Recording::open(&rec).unwrap(), &dir.join(out), &opts, &mut |_, _, _| {}).unwrap();
        read_json(&dir.join(out).join("report.json"))
    };
    let points = |r: &serde_json::Value| -> Vec<u64> { r["frames"].as_array().unwrap().iter().map(|f| f["points"].as_u64().unwrap()).collect() };
    let toe_in = (160.0f64 / 450.0).atan().to_degrees();
    let parallel = scan(0.0, None, "parallel");
    let cropped = scan(toe_in, Some(0.0), "cropped");
    let kept = scan(toe_in, None, "kept");
    let alpha = |r: &serde_json::Value| r["matching"]["rectify_alpha"].as_f64().unwrap();
    println!("points: parallel {:?} (alpha {}), toed in at alpha 0 {:?}, by default {:?} (alpha {:.3})", points(&parallel), alpha(&parallel), points(&cropped), points(&kept), alpha(&kept));
    assert_eq!(alpha(&parallel), 0.0);
    assert!(alpha(&kept) > 0.0 && alpha(&kept) < 1.0, "{}", alpha(&kept));
    for ((c, k), p) in points(&cropped).iter().zip(points(&kept)).zip(points(&parallel)) {
        assert!(c * 10 < k && k * 10 >= p * 6, "{:?} at alpha 0, {:?} by default, {:?} parallel", points(&cropped), points(&kept), points(&parallel));
    }
}

/// The right camera at 0.6 × the left's gain (the same recording, its right images darkened):
/// the first frame's matches measure the cameras' contrast ratio, every right image is scaled
/// by it, and the scan matches as well as with the cameras alike — against the ground truth,
/// as many pixels matched about as close.
#[test]
fn a_darker_right_camera_is_scaled_to_the_left_s_contrast() {
    let dir = support::temp_dir("rec-gain");
    small_recording(&dir.join("sim"), 2, 0.0);
    let dark = dir.join("dark");
    support::copy_with_right_gain(&dir.join("sim"), &dark, 0.6);
    let report = |rec: &Path, out: &str| -> serde_json::Value {
        replay(rec, &dir.join(out)).unwrap();
        read_json(&dir.join(out).join("report.json"))
    };
    let (alike, darker) = (report(&dir.join("sim"), "out-alike"), report(&dark, "out-dark"));
    let (ca, cd) = (&alike["matching"]["contrast"], &darker["matching"]["contrast"]);
    println!("contrast: alike {ca}, darker {cd}");
    assert!((ca["ratio"].as_f64().unwrap() - 1.0).abs() < 0.02 && ca["right_scaled"] == false, "{ca}");
    assert!((cd["ratio"].as_f64().unwrap() * 0.6 - 1.0).abs() < 0.02 && cd["right_scaled"] == true, "{cd}");
    for (a, d) in alike["frames"].as_array().unwrap().iter().zip(darker["frames"].as_array().unwrap()) {
        let (err, coverage) = (d["gt_mean_abs_err_px"].as_f64().unwrap(), d["gt_coverage"].as_f64().unwrap());
        println!("error {err:.3} px against {:.3}, coverage {coverage:.3} against {:.3}", a["gt_mean_abs_err_px"], a["gt_coverage"]);
        assert!(err <= a["gt_mean_abs_err_px"].as_f64().unwrap() * 1.05 && coverage >= a["gt_coverage"].as_f64().unwrap() - 0.01, "{d}");
    }
}

/// The points within `rim_px` of the object's silhouette are left out of the views' clouds
/// (what is fused): the first frame has exactly that many points fewer than with the rim
/// kept, and every view lies closer to the true surface (its 95th percentile above all: the
/// rim holds a view's worst points). Registration takes them either way: the same poses.
#[test]
fn the_views_leave_out_the_silhouette_s_rim() {
    let dir = support::temp_dir("rec-rim");
    small_recording(&dir.join("sim"), 2, 0.0);
    let run = |rim_px: usize, out: &str| -> serde_json::Value {
        let mut pipeline = replay_opts().pipeline;
        pipeline.chroma.rim_px = rim_px;
        let opts = ReplayOptions::with_registration(pipeline);
        let rec = Recording::open(&dir.join("sim")).unwrap();
        replay::run_recording(rec, &dir.join(out), &opts, &mut |_, _, _| {}).unwrap();
        read_json(&dir.join(out).join("report.json"))
    };
    let (kept, trimmed) = (run(0, "out-kept"), run(3, "out-trimmed"));
    assert_eq!((kept["matching"]["rim_px"].as_u64(), trimmed["matching"]["rim_px"].as_u64()), (Some(0), Some(3)));
    let (k, t) = (kept["frames"].as_array().unwrap(), trimmed["frames"].as_array().unwrap());
    let n = |f: &serde_json::Value, key: &str| f[key].as_u64().unwrap();
    assert_eq!(n(&k[0], "rim_points"), 0);
    assert!(n(&t[0], "rim_points") > 300, "{}", t[0]);
    assert_eq!(n(&k[0], "points") - n(&t[0], "points"), n(&t[0], "rim_points"));
    assert_eq!(kept["registration"]["gt_pose_err_deg"], trimmed["registration"]["gt_pose_err_deg"]);
    for (k, t) in k.iter().zip(t) {
        assert_eq!(k["live_first_from_view"], t["live_first_from_view"]);
        let (dk, dt) = (&k["gt_view_distance_mm"], &t["gt_view_distance_mm"]);
        println!("view {}: {} → {}", k["seq"], dk, dt);
        let at = |d: &serde_json::Value, q: &str| d[q].as_f64().unwrap();
        assert!(at(dt, "median") <= at(dk, "median") && at(dt, "p95") < 0.9 * at(dk, "p95"), "{dk} → {dt}");
    }
    // Each point of a view's PLY carries its pixel's distance inside the silhouette, which
    // the fusion weighs by: none on the background, none inside a trimmed rim, and with the
    // rim kept, some near the silhouette, weighed down.
    for (out, least) in [("out-kept", 1u8), ("out-trimmed", 4)] {
        let cloud = spinscan::io::ply::read_ply(&dir.join(out).join("views").join("000000.ply")).unwrap().cloud;
        let rim = cloud.rim_px.expect("the view's PLY has rim_px");
        assert_eq!(rim.len(), cloud.points.len());
        assert_eq!(rim.iter().min(), Some(&least), "{out}");
    }
    assert!(kept["registration"]["mesh"]["rim_weighed_points"].as_u64().unwrap() > 300, "{}", kept["registration"]["mesh"]);
}

/// A rig whose right camera sits left of the left one (negative disparities, as on the XIMEA
/// fixture's rig) scans as well as its mirror image, the usual rig: the range on its side of
/// zero, the views as dense and as close to the true surface, the poses as good. (Six views,
/// 10° of turn: with four, 6°, the texture tracks cannot fix the axis, the views' points fit it
/// a few degrees off, and the final poses, 0.27–0.54° off, compared two such estimates.)
#[test]
fn a_rig_with_negative_disparities_scans_as_well() {
    let dir = support::temp_dir("rec-negative");
    let scan = |baseline_mm: f64| -> serde_json::Value {
        let rec = dir.join(format!("rec{baseline_mm}"));
        let opts = RenderOptions {
            object: SimObject::Builtin { name: "egg".into(), triangles: 20_000 },
            frames: 6,
            ideal: true,
            image_size: (320, 240),
            lab: spinscan::hw::sim::Lab { baseline_mm, ..Default::default() },
            ..RenderOptions::default()
        };
        let (lo, hi) = spinscan::hw::sim::object_disparities(&opts).unwrap();
        assert!(lo < hi && (lo.abs() > 30.0) && lo * hi > 0.0 && (lo < 0.0) == (baseline_mm < 0.0), "{lo} … {hi}");
        let recording = spinscan::hw::sim::render_recording(&opts, &rec, &mut |_, _| {}).unwrap();
        assert_eq!(rec.join("gt/disparity").exists(), baseline_mm > 0.0, "gt/disparity/ is for T = (−B, 0, 0) only");
        let out = dir.join(format!("out{baseline_mm}"));
        // The whole scan: registration and the predicted search too.
        let opts = ReplayOptions::with_registration(replay_opts().pipeline);
        replay::run_recording(recording, &out, &opts, &mut |_, _, _| {}).unwrap();
        read_json(&out.join("report.json"))
    };
    let (usual, mirrored) = (scan(60.0), scan(-60.0));
    assert_eq!((usual["disparity_sign"].clone(), mirrored["disparity_sign"].clone()), (1.into(), (-1).into()));
    for (u, m) in usual["frames"].as_array().unwrap().iter().zip(mirrored["frames"].as_array().unwrap()) {
        let valid = |f: &serde_json::Value| f["valid_fraction"].as_f64().unwrap();
        let near = |f: &serde_json::Value| f["gt_view_distance_mm"]["median"].as_f64().unwrap();
        assert!(valid(m) > 0.85 && (valid(m) - valid(u)).abs() < 0.05, "{m} against {u}");
        assert!(near(m) < 1.25 * near(u), "view {}: {} mm from the true surface against {}", m["seq"], near(m), near(u));
        assert_eq!(m["range_edge_px"], 0, "{m}");
        // The mirrored rig's truth is rendered from the mesh, signed as its disparities are.
        assert_eq!((m["gt_disparity"].as_str(), u["gt_disparity"].as_str()), (Some("rendered"), Some("recorded")));
        let err = |f: &serde_json::Value| f["gt_mean_abs_err_px"].as_f64().unwrap();
        assert!(m["gt_coverage"].as_f64().unwrap() > 0.85 && err(m) < 1.5 * err(u).max(0.1), "{m} against {u}");
    }
    let err = |r: &serde_json::Value| r["registration"]["gt_pose_err_deg"]["final"]["max"].as_f64().unwrap();
    assert!(err(&mirrored) < 1.0 && err(&mirrored) < 2.0 * err(&usual).max(0.1), "{} against {}", err(&mirrored), err(&usual));
}
