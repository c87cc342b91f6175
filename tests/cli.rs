//! The `spinscan` command line as users and acceptance checks call it: output contracts,
//! and one clear line with a non-zero exit for every kind of bad input.

mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn spinscan(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_spinscan")).args(args).output().expect("spinscan runs")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A small simulated pair written as PNG files, with its calibration.
fn sim_pair(dir: &Path) -> (PathBuf, PathBuf) {
    sim_pair_at(dir, 220.0)
}

/// [`sim_pair`] through lenses of focal length `focal_px` (longer: larger disparities).
fn sim_pair_at(dir: &Path, focal_px: f64) -> (PathBuf, PathBuf) {
    let scene = spinscan::hw::sim::small_scene("sphere", 200, 150, focal_px);
    let pair = hw_sim::Renderer::new(scene.clone()).unwrap().render(0.0, 0);
    let (l, r) = (dir.join("left.png"), dir.join("right.png"));
    spinscan::io::write_rgb_png(&l, pair.width, pair.height, &pair.left_rgb).unwrap();
    spinscan::io::write_rgb_png(&r, pair.width, pair.height, &pair.right_rgb).unwrap();
    std::fs::write(dir.join("calib.yaml"), spinscan::hw::sim::calib_of(&scene.rig).to_yaml()).unwrap();
    (l, r)
}

fn json_line(o: &Output) -> serde_json::Value {
    let text = String::from_utf8_lossy(&o.stdout);
    let line = text.lines().last().unwrap_or_default();
    serde_json::from_str(line).unwrap_or_else(|e| panic!("stdout is not one JSON line ({e}): {text}"))
}

#[test]
fn disparity_prints_its_json_contract_and_writes_every_format() {
    let dir = support::temp_dir("cli-disparity");
    let (l, r) = sim_pair(&dir);
    let out = dir.join("d.png");
    let o = spinscan(&[
        "disparity", "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "--max-disparity", "48", "--block", "9",
        "--threads", "1", "--repeat", "3", "-o", out.to_str().unwrap(), "--pfm", dir.join("d.pfm").to_str().unwrap(),
        "--color", dir.join("c.png").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = json_line(&o);
    assert!(j["match_ms"].as_f64().unwrap() > 0.0);
    // The warm-up's time, reported apart.
    assert!(j["first_call_ms"].as_f64().unwrap() > 0.0);
    assert!((0.0..=1.0).contains(&j["valid_fraction"].as_f64().unwrap()));
    assert_eq!(j["disparity_sign"], 1);
    assert_eq!(j["coarse_to_fine"], false, "bm searches every disparity unless asked");
    let png = spinscan::io::read_disparity_png(&out, 1.0).unwrap();
    let pfm = spinscan::io::read_pfm(&dir.join("d.pfm")).unwrap();
    assert_eq!(png.valid_count(), pfm.valid_count());
    assert!(png.valid_count() > 1000);
    assert!(dir.join("c.png").is_file());
    // `--num-disparities` is the name; `--max-disparity` (above) the older alias of the same
    // count, kept so no script breaks.
    let out2 = dir.join("d2.png");
    let o = spinscan(&["disparity", "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "--num-disparities", "48", "--threads", "1", "-o", out2.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!((json_line(&o)["num_disparities"].as_u64(), j["num_disparities"].as_u64()), (Some(48), Some(48)));
    // One call: it is the first call.
    assert_eq!(json_line(&o)["first_call_ms"], json_line(&o)["match_ms"]);
    assert_eq!(std::fs::read(&out2).unwrap(), std::fs::read(&out).unwrap(), "the same count, the same map");
}

#[test]
fn uncalibrated_negative_range_reports_negative_sign() {
    let dir = support::temp_dir("cli-negative");
    let (l, r) = sim_pair(&dir);
    // Swapping the images makes every disparity negative.
    let o = spinscan(&[
        "disparity", "--left", r.to_str().unwrap(), "--right", l.to_str().unwrap(), "--min-disparity", "-47", "--max-disparity",
        "48", "-o", dir.join("d.png").to_str().unwrap(), "--pfm", dir.join("d.pfm").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(json_line(&o)["disparity_sign"], -1);
    let pfm = spinscan::io::read_pfm(&dir.join("d.pfm")).unwrap();
    assert!(pfm.values().iter().filter(|v| v.is_finite()).all(|&v| v <= 0.0));
    assert!(pfm.valid_count() > 1000);
}

/// Runs a command that must fail with the input-error code and one line naming `needle`;
/// returns that line.
fn check_bad_input(args: &[&str], needle: &str) -> String {
    let o = spinscan(args);
    assert_eq!(o.status.code(), Some(3), "expected exit 3 for {args:?}; stderr: {}", stderr(&o));
    let err = stderr(&o);
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(err.contains(needle), "`{needle}` not in: {err}");
    err
}

#[test]
fn bad_inputs_give_one_clear_line() {
    let dir = support::temp_dir("cli-bad");
    let (l, r) = sim_pair(&dir);
    let (l, r) = (l.to_str().unwrap(), r.to_str().unwrap());
    let out = dir.join("o.png");
    let out = out.to_str().unwrap();
    let missing = dir.join("nope.png");
    check_bad_input(&["disparity", "--left", missing.to_str().unwrap(), "--right", r, "-o", out], "nope.png");

    let small = dir.join("small.png");
    spinscan::io::write_gray_png(&small, 20, 10, &[0; 200]).unwrap();
    check_bad_input(&["disparity", "--left", l, "--right", small.to_str().unwrap(), "-o", out], "200×150");

    check_bad_input(&["disparity", "--left", l, "--right", r, "--block", "8", "-o", out], "--block 8: must be odd and within 3…31");
    check_bad_input(&["disparity", "--left", l, "--right", r, "--max-disparity", "0", "-o", out], "--num-disparities 0: must be within 1…1024");

    let text = std::fs::read_to_string(dir.join("calib.yaml")).unwrap();
    let broken = dir.join("broken.yaml");
    std::fs::write(&broken, text.replace("   rows: 3\n   cols: 1", "   rows: 2\n   cols: 1")).unwrap();
    check_bad_input(&["points", "--calib", broken.to_str().unwrap(), "--left", l, "--right", r, "-o", out], "`T`");

    let axis = dir.join("turntable.yaml");
    std::fs::write(&axis, "axis_dir: [0, -1, 0]\n").unwrap();
    check_bad_input(&["replay", dir.to_str().unwrap(), "-o", out, "--turntable", axis.to_str().unwrap()], "axis_point_mm");

    let empty = support::temp_dir("cli-bad-empty");
    check_bad_input(&["points", "--calib", empty.to_str().unwrap(), "--left", l, "--right", r, "-o", out], "holds no calibration");
}

/// A semi-global volume larger than the memory the process may take (`ulimit -v`: 400 MB of
/// address space against ≈ 940 MB of sums for 2000 × 300 pixels at up to 1024 disparities)
/// is one clear line that names the way out, not an abort; the same call with a volume that
/// fits still runs under that limit, and so does the call seeded from the half-size pair (the
/// default), whose tiles aggregate one block of disparities around what it matched.
#[test]
fn sgm_without_the_memory_for_its_volume_says_so_in_one_line() {
    let dir = support::temp_dir("cli-sgm-memory");
    let (w, h) = (2000, 300);
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let noise: Vec<u8> = (0..w * h)
        .map(|_| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 56) as u8
        })
        .collect();
    let (l, r) = (dir.join("l.png"), dir.join("r.png"));
    spinscan::io::write_gray_png(&l, w, h, &noise).unwrap();
    spinscan::io::write_gray_png(&r, w, h, &noise).unwrap();
    let out = dir.join("o.png");
    let run = |disparities: &str, seed: &[&str]| {
        // (One malloc arena: on a machine of many cores, glibc's per-thread arenas reserve
        // address space that `ulimit -v` counts.)
        Command::new("sh")
            .env("MALLOC_ARENA_MAX", "1")
            .args(["-c", "ulimit -v 400000 && exec \"$0\" \"$@\"", env!("CARGO_BIN_EXE_spinscan")])
            .args(["disparity", "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "--method", "sgm", "--threads", "1"])
            .args(["--num-disparities", disparities, "-o", out.to_str().unwrap()])
            .args(seed)
            .output()
            .expect("sh runs")
    };
    let o = run("1024", &["--coarse-to-fine", "off"]);
    assert_eq!(o.status.code(), Some(3), "stderr: {}", stderr(&o));
    let err = stderr(&o);
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(err.contains("2000×300") && err.contains("1024 disparities") && err.contains("--sgm-paths 5"), "{err}");
    // 16 disparities: 19 MB of sums.
    let o = run("16", &["--coarse-to-fine", "off"]);
    assert!(o.status.success(), "stderr: {}", stderr(&o));
    // Seeded: the same pair matched at 1/2 … 1/16 of its size first, then a block a pixel.
    let o = run("1024", &[]);
    assert!(o.status.success(), "stderr: {}", stderr(&o));
    let json = json_line(&o);
    // (The images are equal: every pixel matches, most at disparity 0.)
    assert!(json["valid_fraction"].as_f64().unwrap() > 0.9 && json["mean_search_px"].as_f64().unwrap() < 64.0, "{json}");
}

#[test]
fn points_and_rectify_on_the_real_negative_disparity_rig() {
    let data = support::shared_data("stereo-calib-chessboard-ximea");
    let dir = support::temp_dir("cli-ximea");
    let (l, r) = (data.join("left25.jpg"), data.join("right25.jpg"));
    let ply = dir.join("p.ply");
    let o = spinscan(&[
        "points", "--calib", data.to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(),
        "--max-disparity", "112", "-o", ply.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = json_line(&o);
    assert_eq!(j["disparity_sign"], -1);
    let mesh = spinscan::io::ply::read_ply(&ply).unwrap();
    assert!(mesh.cloud.len() > 5000, "{} points", mesh.cloud.len());
    // The chessboard stands in front of the rig: positive depth in the left camera frame.
    let median_z = {
        let mut z: Vec<f32> = mesh.cloud.points.iter().map(|p| p[2]).collect();
        z.sort_by(f32::total_cmp);
        z[z.len() / 2]
    };
    assert!(median_z > 100.0 && median_z < 3000.0, "median depth {median_z} mm");

    let o = spinscan(&["rectify", "--calib", data.to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "-o", dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(dir.join("left.png").is_file() && dir.join("right.png").is_file() && dir.join("rectification.json").is_file());
}

#[test]
fn demo_records_and_replays_a_scan_on_the_simulated_lab() {
    let dir = support::temp_dir("cli-demo");
    let o = spinscan(&["demo", "-o", dir.to_str().unwrap(), "--frames", "3"]);
    assert!(o.status.success(), "{}", stderr(&o));
    // A newcomer's first run reads clean: the default object's expected condition (a ring
    // ICP cannot turn about its own axis) is no warning, and progress never shares a line
    // with a log line.
    let err = stderr(&o);
    assert!(!err.contains("WARN") && !err.contains("degenerate"), "{err}");
    assert!(err.lines().all(|l| l.matches("demo:").count() <= 1 && !l.contains('\r')), "{err}");
    let j = json_line(&o);
    assert_eq!(j["frames"], 3);
    assert!(j["gt_coverage"].as_f64().unwrap() > 0.8, "{j}");
    assert!(j["gt_bad2_of_matched"].as_f64().unwrap() < 0.05, "{j}");
    assert_eq!(j["gt_disparity"], "recorded", "the demo's ideal rig has gt/disparity/: {j}");
    for f in ["recording/calib.yaml", "recording/frames.jsonl", "recording/gt/poses.jsonl", "recording/gt/mesh.ply", "recording/gt/disparity/000002.png",
              "results/manifest.json", "results/report.json", "results/views/000002.ply", "results/disparity/000002.png",
              "results/poses.jsonl", "results/model.ply", "results/mesh.ply"] {
        assert!(dir.join(f).is_file(), "{f} missing");
    }
    // The fused mesh re-meshed into each format, and each read back by a reader that is not
    // spinscan's writer: every file holds the same triangles — fused on one thread, on three
    // or on one per core as the replay fused it.
    let mesh = spinscan::io::ply::read_ply(&dir.join("results/mesh.ply")).unwrap();
    assert!(mesh.triangles.len() > 1000 && mesh.cloud.normals.is_some(), "{} triangles", mesh.triangles.len());
    for (ext, threads) in [("ply", "1"), ("obj", "3"), ("stl", "0")] {
        let out = dir.join(format!("again.{ext}"));
        let o = spinscan(&["mesh", dir.join("results").to_str().unwrap(), "-o", out.to_str().unwrap(), "--threads", threads]);
        assert!(o.status.success(), "{}", stderr(&o));
        let about = json_line(&o);
        assert!(threads == "0" || about["threads"].as_u64() == threads.parse().ok(), "{about}");
        assert_eq!((about["triangles"].as_u64(), about["boundary_edges"].as_u64(), about["non_manifold_edges"].as_u64()), (Some(mesh.triangles.len() as u64), Some(0), Some(0)), "{about}");
        let bytes = std::fs::read(&out).unwrap();
        match ext {
            "ply" => assert_eq!(spinscan::io::ply::read_ply(&out).unwrap(), mesh),
            "obj" => {
                let text = String::from_utf8(bytes).unwrap();
                let v: Vec<Vec<f32>> = text.lines().filter_map(|l| l.strip_prefix("v ")).map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect()).collect();
                let f: Vec<Vec<usize>> = text.lines().filter_map(|l| l.strip_prefix("f ")).map(|l| l.split_whitespace().map(|x| x.split('/').next().unwrap().parse().unwrap()).collect()).collect();
                assert_eq!((v.len(), f.len()), (mesh.cloud.len(), mesh.triangles.len()));
                assert!(v.iter().all(|v| v.len() == 6 && v[3..].iter().all(|c| (0.0..=1.0).contains(c))));
                assert!(f.iter().all(|f| f.len() == 3 && f.iter().all(|&i| (1..=v.len()).contains(&i))));
                assert_eq!(text.lines().filter(|l| l.starts_with("vn ")).count(), mesh.cloud.len());
            }
            _ => {
                let n = u32::from_le_bytes(bytes[80..84].try_into().unwrap()) as usize;
                assert_eq!((n, bytes.len()), (mesh.triangles.len(), 84 + 50 * n));
                // The first triangle's corners are the mesh's.
                let corner = |k: usize| -> [f32; 3] { std::array::from_fn(|c| f32::from_le_bytes(bytes[84 + 12 + 12 * k + 4 * c..][..4].try_into().unwrap())) };
                assert_eq!([corner(0), corner(1), corner(2)], mesh.triangles[0].map(|v| mesh.cloud.points[v as usize]));
            }
        }
    }
    let o = spinscan(&["mesh", dir.join("results").to_str().unwrap(), "-o", dir.join("again.xyz").to_str().unwrap()]);
    assert!(!o.status.success() && stderr(&o).contains("expected a name ending in .ply, .obj or .stl"), "{}", stderr(&o));
    let o = spinscan(&["mesh", dir.join("results").to_str().unwrap(), "-o", dir.join("again.ply").to_str().unwrap(), "--threads", "5000"]);
    assert!(!o.status.success() && stderr(&o).contains("5000 threads asked for; expected 0 (one per core) … 1024"), "{}", stderr(&o));
    // A view cut short (its views read a pool's worth at a time): the error names it.
    let bad = dir.join("bad");
    std::fs::create_dir_all(bad.join("views")).unwrap();
    std::fs::copy(dir.join("results/poses.jsonl"), bad.join("poses.jsonl")).unwrap();
    for seq in 0..3 {
        let name = format!("views/{seq:06}.ply");
        let bytes = std::fs::read(dir.join("results").join(&name)).unwrap();
        std::fs::write(bad.join(&name), if seq == 1 { &bytes[..bytes.len() / 2] } else { &bytes[..] }).unwrap();
    }
    let o = spinscan(&["mesh", bad.to_str().unwrap(), "-o", dir.join("bad.ply").to_str().unwrap(), "--threads", "3"]);
    assert!(!o.status.success() && stderr(&o).contains("000001.ply") && stderr(&o).contains("cannot read the view"), "{}", stderr(&o));
    // The views are registered: three poses, and a model near the true surface.
    assert_eq!(std::fs::read_to_string(dir.join("results/poses.jsonl")).unwrap().lines().count(), 3);
    assert!(j["registration"]["gt_model_distance_mm"]["median"].as_f64().unwrap() < 2.0, "{j}");
    // Each view's own distance to the true surface, in its frame's entry.
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("results/report.json")).unwrap()).unwrap();
    for f in report["frames"].as_array().unwrap() {
        let d = &f["gt_view_distance_mm"];
        assert!(d["median"].as_f64().is_some_and(|m| m < 1.0) && d["p95"].as_f64() >= d["median"].as_f64() && d["points"].as_u64().is_some_and(|n| n > 100), "{f}");
    }
    let manifest: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("results/manifest.json")).unwrap()).unwrap();
    assert_eq!((manifest["status"].as_str(), manifest["frames"].as_u64(), manifest["format"].as_u64()), (Some("complete"), Some(3), Some(1)));
}

#[test]
fn help_defaults_match_the_library_defaults() {
    // The CLI repeats the chroma key's default as text; keep the two in step.
    let o = spinscan(&["points", "--help"]);
    let k = spinscan::segment::ChromaKey::default().key;
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains(&format!("[default: {k}]")), "{text}");
}

/// Cameras stacked vertically (the baseline along y) cannot be matched along rows: `points`
/// says so and names the way out, instead of matching rows that do not correspond.
#[test]
fn a_vertical_rig_is_refused_naming_why() {
    let dir = support::temp_dir("cli-vertical");
    let (l, r) = sim_pair(&dir);
    let mut calib = spinscan::calib::StereoCalib::load(&dir.join("calib.yaml")).unwrap();
    calib.t_mm = nalgebra::Vector3::new(2.0, -calib.t_mm.norm(), 0.0);
    std::fs::write(dir.join("calib.yaml"), calib.to_yaml()).unwrap();
    let o = points_with_auto_mask(&dir, &l, &r);
    assert!(!o.status.success() && stderr(&o).contains("stacked vertically") && stderr(&o).contains("side by side"), "{}", stderr(&o));
}

/// A sphere leaves ICP free to turn it on nearly every view, and the table's step is kept
/// along those motions: `replay` logs the first three such views and says the rest are in
/// report.json, which keeps every one.
#[test]
fn a_sphere_s_degenerate_views_are_logged_three_times_and_kept_in_the_report() {
    let dir = support::temp_dir("cli-degenerate");
    let (rec, out) = (dir.join("rec"), dir.join("out"));
    let o = spinscan(&["sim", "render", "--object", "sphere", "--triangles", "20000", "--frames", "12", "--size", "320x240", "-o", rec.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = spinscan(&["replay", rec.to_str().unwrap(), "--threads", "1", "-o", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let logged: Vec<String> = stderr(&o).lines().filter(|l| l.contains("registration is degenerate")).map(String::from).collect();
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let kept = report["frames"].as_array().unwrap().iter().filter(|f| f["warnings"].as_array().is_some_and(|w| w.iter().any(|w| w.as_str().unwrap().contains("registration is degenerate")))).count();
    assert!(kept >= 5, "{kept} degenerate views in the report");
    assert_eq!(logged.len(), 4, "{logged:#?}");
    assert!(logged[3].contains("further views' degeneracy is in report.json only"), "{}", logged[3]);
}

/// `points` with no range given fits it to the pair's object: a sphere at disparities beyond
/// the single pair's default (64) is matched over a range that holds it, the JSON says so,
/// and the points outnumber those of the default range given outright many times over.
#[test]
fn points_fit_the_range_to_the_object_where_none_is_given() {
    let dir = support::temp_dir("cli-points-range");
    let (l, r) = sim_pair_at(&dir, 600.0);
    let (calib, out) = (dir.join("calib.yaml"), dir.join("p.ply"));
    let points = |range: &[&str]| {
        let mut args = vec!["points", "--calib", calib.to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "--mask", "auto", "-o", out.to_str().unwrap()];
        args.extend(range);
        let o = spinscan(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        json_line(&o)
    };
    let fitted = points(&[]);
    println!("{fitted}");
    let fit = &fitted["range_fit"];
    assert_eq!(fit["widened"], true, "{fitted}");
    let (lo, hi) = (fit["object_disparities"][0].as_f64().unwrap(), fit["object_disparities"][1].as_f64().unwrap());
    let (min, n) = (fitted["min_disparity"].as_i64().unwrap(), fitted["num_disparities"].as_i64().unwrap());
    assert!(hi > 64.0 && (min as f64) <= lo - 15.0 && ((min + n - 1) as f64) >= hi + 16.0, "{fitted}");
    let given = points(&["--num-disparities", "64"]);
    assert!(given["range_fit"].is_null() && given["num_disparities"] == 64, "{given}");
    assert!(given["points"].as_u64().unwrap() * 5 < fitted["points"].as_u64().unwrap(), "{given} against {fitted}");
}

/// `spinscan points --mask auto` on a pair matched with `dir`'s calibration.
fn points_with_auto_mask(dir: &Path, l: &Path, r: &Path) -> std::process::Output {
    spinscan(&["points", "--calib", dir.join("calib.yaml").to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "--mask", "auto", "--max-disparity", "48", "-o", dir.join("p.ply").to_str().unwrap()])
}

/// `--mask auto` finds the simulated lab's screen without a word. On the same pair in grey,
/// with no colour to find, it keys the screen as a plain backdrop, says so, and keeps about
/// the points the colour key keeps (the default colour's key, before, kept the screen too).
#[test]
fn points_on_grey_images_keys_a_plain_backdrop() {
    let dir = support::temp_dir("cli-grey-screen");
    let (l, r) = sim_pair(&dir);
    let points = |l: &Path, r: &Path| points_with_auto_mask(&dir, l, r);
    let o = points(&l, &r);
    assert!(o.status.success() && !stderr(&o).contains("no coloured screen"), "{}", stderr(&o));
    let colour = json_line(&o)["points"].as_u64().unwrap();
    let grey = |p: &Path| {
        let img = spinscan::io::load_image(p).unwrap();
        let out = dir.join(format!("grey-{}", p.file_name().unwrap().to_str().unwrap()));
        spinscan::io::write_gray_png(&out, img.width, img.height, &img.gray).unwrap();
        out
    };
    let o = points(&grey(&l), &grey(&r));
    assert!(o.status.success() && stderr(&o).contains("keyed as a plain backdrop"), "{}", stderr(&o));
    let got = json_line(&o)["points"].as_u64().unwrap();
    println!("{got} points in grey, {colour} in colour");
    assert!(got.abs_diff(colour) * 10 <= colour, "{got} points in grey, {colour} in colour");
}

/// A floor the key leaves, along the bottom of both images, reaches the image's edge. A
/// plain grey one is keyed out by its lack of texture (no warning, and within 15 % of the
/// points of the scene without it); a patterned one (a carpet) cannot be, and `points` says the mask
/// reaches the edge. The simulated lab's scene (an object in full view) does neither.
#[test]
fn points_says_when_the_mask_reaches_the_image_s_edge() {
    let dir = support::temp_dir("cli-edge");
    let (l, r) = sim_pair(&dir);
    let points = |l: &Path, r: &Path| points_with_auto_mask(&dir, l, r);
    let o = points(&l, &r);
    assert!(o.status.success() && !stderr(&o).contains("edge is kept as object"), "{}", stderr(&o));
    let without = json_line(&o)["points"].as_u64().unwrap();
    let blue = spinscan::segment::ChromaKey { key: spinscan::segment::KeyColour::Rgb(spinscan::segment::DEFAULT_KEY_RGB), ..Default::default() };
    let floor = |p: &Path, name: &str, paint: &dyn Fn(usize) -> [u8; 3]| {
        let img = spinscan::io::load_image(p).unwrap();
        let screen = blue.segment(&img.rgb, img.width, img.height, None).unwrap();
        let mut rgb = img.rgb.clone();
        for (k, (px, &m)) in rgb.chunks_exact_mut(3).zip(&screen).enumerate() {
            if m == 0 && k / img.width >= img.height * 3 / 4 {
                px.copy_from_slice(&paint(k));
            }
        }
        let out = dir.join(format!("{name}-{}", p.file_name().unwrap().to_str().unwrap()));
        spinscan::io::write_rgb_png(&out, img.width, img.height, &rgb).unwrap();
        out
    };
    let grey = |_: usize| [100, 100, 100];
    let o = points(&floor(&l, "grey", &grey), &floor(&r, "grey", &grey));
    assert!(o.status.success() && !stderr(&o).contains("edge is kept as object"), "{}", stderr(&o));
    let kept = json_line(&o)["points"].as_u64().unwrap();
    // (The clean-up after keying by texture — an opening and the window's erosion — takes a
    // few pixels off this small sphere's outline.)
    assert!(kept.abs_diff(without) * 100 <= without * 15, "{kept} points on the grey floor against {without} without it");
    // A carpet of 4-pixel checks, the same in both images (far behind: no disparity to see).
    let carpet = |k: usize| if (k % 200 / 4 + k / 200 / 4) % 2 == 0 { [60, 60, 60] } else { [160, 150, 140] };
    let o = points(&floor(&l, "carpet", &carpet), &floor(&r, "carpet", &carpet));
    assert!(o.status.success() && stderr(&o).contains("of the left image's edge is kept as object"), "{}", stderr(&o));
}

#[test]
fn points_with_auto_mask_and_plate_on_the_simulated_lab() {
    let dir = support::temp_dir("cli-plate");
    let (l, r) = sim_pair(&dir);
    let scene = spinscan::hw::sim::small_scene("sphere", 200, 150, 220.0);
    // A plate of the empty scene: the same view without the object.
    let empty = hw_sim::Renderer::new(scene).unwrap().render_plate(0.0, 0);
    let plate = dir.join("plate.png");
    spinscan::io::write_rgb_png(&plate, empty.width, empty.height, &empty.left_rgb).unwrap();
    let (ply, mask) = (dir.join("p.ply"), dir.join("mask.png"));
    let o = spinscan(&[
        "points", "--calib", dir.join("calib.yaml").to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(),
        "--mask", "auto", "--plate", plate.to_str().unwrap(), "--max-disparity", "48", "-o", ply.to_str().unwrap(),
        "--mask-out", mask.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let m = spinscan::io::load_image(&mask).unwrap();
    let fg = m.gray.iter().filter(|&&v| v > 0).count();
    // The sphere (radius 70 mm at 450 mm, f = 220 px) covers about π·(220·70/450)² ≈ 3.7k px.
    assert!((2500..5000).contains(&fg), "{fg} foreground pixels");
    check_bad_input(
        &["points", "--calib", dir.join("calib.yaml").to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(),
          "--plate", plate.to_str().unwrap(), "-o", ply.to_str().unwrap()],
        "--mask auto",
    );
}

#[test]
fn points_with_a_mask_file_match_only_inside_it() {
    let dir = support::temp_dir("cli-maskfile");
    let (l, r) = sim_pair(&dir);
    let scene = spinscan::hw::sim::small_scene("sphere", 200, 150, 220.0);
    let pair = hw_sim::Renderer::new(scene).unwrap().render(0.0, 0);
    let gt_disparity = pair.gt_disparity.clone().unwrap();
    // The left half of the object only.
    let mask: Vec<u8> = gt_disparity.iter().enumerate().map(|(i, d)| if d.is_finite() && i % 200 < 100 { 255 } else { 0 }).collect();
    let inside = mask.iter().filter(|&&m| m > 0).count();
    let mask_path = dir.join("mask.png");
    spinscan::io::write_gray_png(&mask_path, 200, 150, &mask).unwrap();
    let ply = dir.join("p.ply");
    let o = spinscan(&[
        "points", "--calib", dir.join("calib.yaml").to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(),
        "--mask", mask_path.to_str().unwrap(), "--max-disparity", "48", "-o", ply.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let cloud = spinscan::io::ply::read_ply(&ply).unwrap().cloud;
    assert!(cloud.len() > inside / 2 && cloud.len() <= inside, "{} points for {inside} mask pixels", cloud.len());
    // Left half of the image: x < 0 in the left camera frame.
    assert!(cloud.points.iter().all(|p| p[0] < 5.0), "a point right of the mask");
}

#[test]
fn sim_render_of_a_ply_mesh_replays_from_the_command_line() {
    let dir = support::temp_dir("cli-bunny");
    let mesh = support::shared_data("stanford-bunny-scans").join("bun_zipper.ply");
    let rec = dir.join("rec");
    let o = spinscan(&["sim", "render", "--mesh", mesh.to_str().unwrap(), "--mesh-scale", "1000", "--frames", "2", "--deg-per-frame", "5", "--ideal", "-o", rec.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(json_line(&o)["frames"], 2);
    let poses = std::fs::read_to_string(rec.join("gt/poses.jsonl")).unwrap();
    assert_eq!(poses.lines().count(), 2);
    let frames = std::fs::read_to_string(rec.join("frames.jsonl")).unwrap();
    assert!(frames.lines().nth(1).unwrap().contains("\"table_deg\":5.0"), "{frames}");
    let out = dir.join("out");
    let o = spinscan(&["replay", rec.to_str().unwrap(), "-o", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j = json_line(&o);
    assert!(j["gt_coverage"].as_f64().unwrap() > 0.8 && j["gt_bad2_of_matched"].as_f64().unwrap() < 0.05, "{j}");
    // A second render into the same folder would mix two scans: refused.
    let o = spinscan(&["sim", "render", "--frames", "1", "-o", rec.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(4), "{}", stderr(&o));
    assert!(stderr(&o).contains("already holds a recording"), "{}", stderr(&o));
}

#[test]
fn sim_and_replay_reject_bad_input_in_one_line() {
    let dir = support::temp_dir("cli-sim-bad");
    let out = dir.join("o");
    check_bad_input(&["sim", "render", "--object", "teapot", "-o", out.to_str().unwrap()], "unknown object `teapot`; built-in objects: sphere, egg, vase, torus");
    check_bad_input(&["sim", "render", "--frames", "0", "-o", out.to_str().unwrap()], "--frames must be at least 1");
    check_bad_input(&["replay", dir.join("nothing").to_str().unwrap(), "-o", out.to_str().unwrap()], "is not a recording: it has no frames.jsonl");
}

/// A matcher flag out of its range is named by the flag before any work starts (and so is a
/// figure's frame past the run's last one), and a rig the pipeline cannot be set up for (its
/// cameras stacked vertically) by what is wrong with it. Neither is put on a frame, points to
/// results that were never written, or leaves an output folder behind.
#[test]
fn setup_errors_name_the_flag_or_the_rig_and_write_nothing() {
    let dir = support::temp_dir("cli-setup");
    let rec = dir.join("rec");
    let rec_s = rec.to_str().unwrap();
    let o = spinscan(&["sim", "render", "--object", "sphere", "--triangles", "2000", "--frames", "1", "--size", "160x120", "-o", rec_s]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = dir.join("out");
    let (out_s, json, fig) = (out.to_str().unwrap(), dir.join("t.json"), dir.join("t.png"));
    let table1 = |extra: &[&'static str]| -> Vec<String> {
        let mut a: Vec<String> = ["bench", "table1", rec_s, "--json", json.to_str().unwrap(), "--fig", fig.to_str().unwrap()].map(String::from).to_vec();
        a.extend(extra.iter().map(|s| s.to_string()));
        a
    };
    let cases: Vec<(Vec<String>, &str)> = vec![
        (["replay", rec_s, "--method", "sgm", "--p1", "0", "-o", out_s].map(String::from).to_vec(), "--p1 0: must be at least 1 and below p2"),
        (["replay", rec_s, "--speckle-range=-1", "-o", out_s].map(String::from).to_vec(), "--speckle-range -1: must be a finite number"),
        // (Before the demo renders its recording, or clears an earlier demo's.)
        (["demo", "--method", "sgm", "--p2", "3000", "-o", out_s].map(String::from).to_vec(), "--p2 3000: must be within p1 + 1 … 2000"),
        (table1(&["--method", "bm,sgm", "--p2", "5000"]), "--p2 5000: must be within p1 + 1 … 2000"),
        (table1(&["--uniqueness", "200"]), "--uniqueness 200: must be a percentage"),
        // (Checked before any frame is decoded, as the flags are.)
        (table1(&["--fig-frame", "5"]), "the figure's frame 5 lies past this run's last frame, 1 (ask for 1…1)"),
    ];
    for (args, needle) in &cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert!(!check_bad_input(&args, needle).contains("frame seq"), "{args:?}");
        assert!(!out.exists() && !json.exists() && !fig.exists(), "{args:?} wrote output");
    }
    // The baseline turned from x to y: cameras one above the other.
    let text = std::fs::read_to_string(rec.join("calib.yaml")).unwrap();
    let t = text.find("T: !!opencv-matrix").expect("calib.yaml has T");
    let (start, end) = (t + text[t..].find('[').unwrap() + 1, t + text[t..].find(']').unwrap());
    let v: Vec<&str> = text[start..end].split(',').map(str::trim).collect();
    std::fs::write(rec.join("calib.yaml"), format!("{}{}, {}, {}{}", &text[..start], v[1], v[0], v[2], &text[end..])).unwrap();
    let err = check_bad_input(&["replay", rec_s, "-o", out_s], "stacked vertically");
    assert!(!err.contains("frame seq") && !err.contains("results so far"), "{err}");
    assert!(!out.exists(), "nothing to write, no folder");
}

/// `sim render`'s lab options: the rig and the cameras' place change the object's
/// disparities, which the command prints; a scan whose object comes closer than the range
/// covers drops the matches piled at the range's end, counts them per frame and says so, and
/// one whose object lies wholly outside it says that hardly anything matched.
#[test]
fn another_lab_s_object_beyond_the_range_is_dropped_and_named() {
    let dir = support::temp_dir("cli-lab");
    let rec = dir.join("rec");
    let rec_s = rec.to_str().unwrap();
    // 320 × 240 at f = 350 px: 60 mm at 320 mm from the object's middle puts it at about
    // 66 px, beyond the 0 … 63 searched below.
    let o = spinscan(&["sim", "render", "--object", "egg", "--triangles", "20000", "--frames", "3", "--ideal", "--size", "320x240", "--object-distance-mm", "320", "-o", rec_s]);
    assert!(o.status.success(), "{}", stderr(&o));
    let span = json_line(&o)["object_disparity_px"].clone();
    let (lo, hi) = (span[0].as_f64().unwrap(), span[1].as_f64().unwrap());
    // Within the default 0 … 127: no note about the range.
    assert!(!stderr(&o).contains("--num-disparities"), "{}", stderr(&o));
    // The span printed is the vertices', the hidden ones too: the visible surface's nearest
    // point is its top, and nothing visible lies farther than its bottom.
    let mut truth = (f32::INFINITY, f32::NEG_INFINITY);
    for seq in 0..3 {
        let gt = spinscan::io::read_disparity_png(&rec.join(format!("gt/disparity/{seq:06}.png")), 1.0).unwrap();
        for d in gt.values().iter().filter(|d| d.is_finite()) {
            truth = (truth.0.min(*d), truth.1.max(*d));
        }
    }
    assert!(truth.0 as f64 > lo - 0.5 && (truth.1 as f64 - hi).abs() < 1.0, "printed {lo:.1} … {hi:.1}, ground truth {truth:?}");
    assert!(hi > 70.0, "{lo} … {hi}");

    let report = |out: &Path| -> serde_json::Value { serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap() };
    let short = dir.join("short");
    let o = spinscan(&["replay", rec_s, "--num-disparities", "64", "--no-register", "-o", short.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stderr(&o).matches("end of the disparity range").count(), 1, "one warning: {}", stderr(&o));
    for f in report(&short)["frames"].as_array().unwrap() {
        assert!(f["range_edge_px"].as_u64().unwrap() > 100, "{f}");
        let map = spinscan::io::read_disparity_png(&short.join(format!("disparity/{:06}.png", f["seq"].as_u64().unwrap())), 1.0).unwrap();
        assert!(map.values().iter().all(|d| !(*d > 62.5)), "a match left at the range's end");
    }
    // The whole object beyond 0 … 31: hardly anything matches, and spinscan says why it may be.
    let none = dir.join("none");
    let o = spinscan(&["replay", rec_s, "--num-disparities", "32", "--no-register", "-o", none.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stderr(&o).matches("pixels searched got a disparity: the object may lie outside the disparity range").count(), 1, "{}", stderr(&o));
    let wide = dir.join("wide");
    let o = spinscan(&["replay", rec_s, "--num-disparities", "96", "--no-register", "-o", wide.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stderr(&o).contains("end of the disparity range") && !stderr(&o).contains("got a disparity"), "{}", stderr(&o));
    for f in report(&wide)["frames"].as_array().unwrap() {
        assert_eq!(f["range_edge_px"], 0, "{f}");
    }

    for (args, want) in [
        (&["--size", "320by240"][..], "WIDTHxHEIGHT"),
        (&["--focal-px", "0"][..], "--focal-px must be a positive"),
        (&["--baseline-mm", "0"][..], "--baseline-mm must be a non-zero distance"),
        (&["--object-distance-mm", "40"][..], "--object-distance-mm must be more than the object's half-diagonal"),
        (&["--camera-tilt-deg", "95"][..], "--camera-tilt-deg must be within"),
        (&["--object-offset-mm", "30"][..], "expected X,Z in mm"),
    ] {
        let out = dir.join("bad");
        let o = spinscan(&[&["sim", "render", "--object", "egg", "--frames", "1", "-o", out.to_str().unwrap()][..], args].concat());
        assert!(!o.status.success() && stderr(&o).contains(want), "{args:?}: {}", stderr(&o));
        assert!(!out.join("frames.jsonl").exists(), "{args:?}: a recording was started");
    }
}

/// `points` drops the matches piled at the range's end too, says how many, and warns when
/// they are many: the simulated sphere searched over 0 … 15, short of it, then over 0 … 47.
#[test]
fn points_name_the_matches_dropped_at_the_range_s_end() {
    let dir = support::temp_dir("cli-points-range-end");
    let (l, r) = sim_pair(&dir);
    let calib = dir.join("calib.yaml");
    let run = |n: &str| {
        let out = dir.join(format!("p{n}.ply"));
        let o = spinscan(&["points", "--calib", calib.to_str().unwrap(), "--left", l.to_str().unwrap(), "--right", r.to_str().unwrap(), "--num-disparities", n, "-o", out.to_str().unwrap()]);
        assert!(o.status.success(), "{}", stderr(&o));
        (json_line(&o)["range_edge_px"].as_u64().unwrap(), stderr(&o).contains("at an end of the disparity range were dropped"))
    };
    let (short, warned) = run("16");
    assert!(short > 100 && warned, "{short} dropped, warned: {warned}");
    // The whole pair is matched, screen included: a few of its pixels still end there.
    let (wide, warned) = run("48");
    assert!(wide < short / 20 && !warned, "{wide} dropped, warned: {warned}");
}
