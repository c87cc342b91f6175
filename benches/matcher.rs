//! `cargo bench --bench matcher [-- FILTER]`: times the matcher (full range and narrow
//! intervals, per pixel and per tile; both methods, `bm` and `sgm`, each with its defaults)
//! on the Middlebury pairs in `../shared/data` when present, and on a simulated pair always;
//! then the segmentation of the simulated pair (`-- segment`: its blue screen, and the same
//! frame in grey, keyed as a plain backdrop), and a view's other passes: the rectification of
//! a realistic raw pair (`-- rectify`), the window that follows the surface on the simulated
//! object's map (`-- follow`), and a whole view's own work in the matcher thread (`-- view`).
//! Prints min and median milliseconds per case over repeated runs (15, or `RUNS=N` in the
//! environment: more for a profiler); `-- sgm` runs the semi-global cases alone. A filter
//! picks the cases whose name holds it, or, written with a leading `^`, the cases whose name
//! starts with the rest (`-- '^sim-640x480 object tile'`: the `bm` cases without their `sgm`
//! namesakes).
//!
//! For the side-by-side comparison with OpenCV use `../shared/bench/peer_stereo.py` with
//! `--eval-cmd "spinscan disparity … --threads 1 --repeat 5 -o {out}"` (see README).

use std::path::PathBuf;
use std::time::Instant;

use spinscan::io::load_image;
use spinscan::stereo::{DisparityIntervals, DisparityMap, GrayView, MatchParams, Method, StereoMatcher};

#[derive(Clone)]
struct Case {
    name: String,
    width: usize,
    height: usize,
    left: Vec<u8>,
    right: Vec<u8>,
    num_disparities: u32,
    /// The object's pixels (simulated pairs only).
    mask: Option<Vec<u8>>,
}

fn cases() -> Vec<Case> {
    let mut out = Vec::new();
    let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data/middlebury-stereo");
    for (name, l, r, n) in [
        ("tsukuba", "tsukuba/scene1.row3.col3.ppm", "tsukuba/scene1.row3.col4.ppm", 16),
        ("teddy", "teddy/im2.png", "teddy/im6.png", 64),
        ("reindeer", "reindeer/view1.png", "reindeer/view5.png", 128),
    ] {
        if let (Ok(li), Ok(ri)) = (load_image(&data.join(l)), load_image(&data.join(r))) {
            out.push(Case { name: name.into(), width: li.width, height: li.height, left: li.gray, right: ri.gray, num_disparities: n, mask: None });
        }
    }
    let scene = hw_sim::SceneConfig::ideal(hw_sim::Mesh::builtin("egg", 100_000).unwrap());
    let pair = hw_sim::Renderer::new(scene).unwrap().render(30.0, 0);
    out.push(Case {
        name: "sim-640x480".into(),
        width: pair.width,
        height: pair.height,
        left: spinscan::io::rgb_to_gray(&pair.left_rgb),
        right: spinscan::io::rgb_to_gray(&pair.right_rgb),
        num_disparities: 128,
        mask: Some(spinscan::segment::ChromaKey::default().segment(&pair.left_rgb, pair.width, pair.height, None).unwrap()),
    });
    out
}

/// Repeats per case: 15, or `RUNS=N` in the environment.
fn runs() -> usize {
    std::env::var("RUNS").ok().and_then(|s| s.parse().ok()).unwrap_or(15)
}

fn time(runs: usize, mut f: impl FnMut()) -> (f64, f64) {
    f();
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let t0 = Instant::now();
            f();
            t0.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    t.sort_by(f64::total_cmp);
    (t[0], t[t.len() / 2])
}

/// `±half` disparities around each matched pixel of `map`; unmatched pixels are not searched.
fn around(map: &DisparityMap, half: i32) -> DisparityIntervals {
    let mut iv = DisparityIntervals::empty(map.width, map.height);
    for y in 0..map.height {
        for x in 0..map.width {
            iv.set(x, y, map.get(x, y).map(|d| (d.round() as i32 - half, d.round() as i32 + half)));
        }
    }
    iv
}

/// Every pixel of `mask` searches the hull of `iv`'s intervals over its matcher tile
/// (`stereo::BAND_TILE`); the others nothing.
fn per_tile(iv: &DisparityIntervals, mask: &[u8]) -> DisparityIntervals {
    let (w, h) = (iv.width(), iv.height());
    let (tw, th) = spinscan::stereo::BAND_TILE;
    let mut out = DisparityIntervals::empty(w, h);
    for ty in (0..h).step_by(th) {
        for tx in (0..w).step_by(tw) {
            let pixels = || (ty..(ty + th).min(h)).flat_map(move |y| (tx..(tx + tw).min(w)).map(move |x| (x, y)));
            let hull = pixels().filter_map(|(x, y)| iv.get(x, y)).reduce(|(a, b), (c, d)| (a.min(c), b.max(d)));
            for (x, y) in pixels().filter(|&(x, y)| mask[y * w + x] != 0) {
                out.set(x, y, hull);
            }
        }
    }
    out
}

/// Whether the command line's `filter` picks case `name`: it holds the filter, or starts with
/// what follows a leading `^`.
fn picks(filter: &str, name: &str) -> bool {
    match filter.strip_prefix('^') {
        Some(prefix) => name.starts_with(prefix),
        None => name.contains(filter),
    }
}

/// Times the matcher on one set of intervals and prints a line, unless `filter` leaves it out.
fn run(m: &mut StereoMatcher, (lv, rv): (GrayView, GrayView), iv: &DisparityIntervals, name: &str, filter: Option<&str>) {
    if filter.is_some_and(|f| !picks(f, name)) {
        return;
    }
    let mut stats = Default::default();
    let mut out = DisparityMap::new(lv.width, lv.height);
    let (min, med) = time(runs(), || stats = m.compute(lv, rv, iv, &mut out).unwrap());
    println!("{name:<34} {min:>9.2} {med:>9.2} {:>10.1}", stats.mean_search_px());
}

/// The simulated egg's raw pair on the realistic rig (distortion, misalignment), and the
/// rig's calibration.
fn realistic_raw() -> (spinscan::calib::StereoCalib, hw_sim::RenderedPair) {
    let scene = hw_sim::SceneConfig::realistic(hw_sim::Mesh::builtin("egg", 100_000).unwrap());
    let calib = spinscan::hw::sim::calib_of(&scene.rig);
    (calib, hw_sim::Renderer::new(scene).unwrap().render(30.0, 0))
}

/// Times the segmentation of a simulated frame: the chroma key on its blue screen, and the
/// plain backdrop's texture key on the same frame in grey (no coloured screen to find).
fn segmentation(filter: Option<&str>) {
    let scene = hw_sim::SceneConfig::ideal(hw_sim::Mesh::builtin("egg", 100_000).unwrap());
    let pair = hw_sim::Renderer::new(scene).unwrap().render(30.0, 0);
    let grey: Vec<u8> = spinscan::io::rgb_to_gray(&pair.left_rgb).iter().flat_map(|&v| [v; 3]).collect();
    let key = spinscan::segment::ChromaKey::default();
    for (name, rgb) in [("segment blue screen", &pair.left_rgb), ("segment grey backdrop", &grey)] {
        if filter.is_some_and(|f| !picks(f, name)) {
            continue;
        }
        let (min, med) = time(runs(), || drop(key.segment(rgb, pair.width, pair.height, None).unwrap()));
        println!("{name:<34} {min:>9.2} {med:>9.2}");
    }
    // Rectification of a realistic rig's raw pair (its lens distortion and small
    // rotations), as each frame of a scan pays it: the left image in colour and grey, the
    // right in grey.
    let name = "rectify realistic pair";
    if filter.is_none_or(|f| picks(f, name)) {
        let (calib, raw) = realistic_raw();
        let size = (raw.width as u32, raw.height as u32);
        let maps = spinscan::stereo::Rectification::compute_keeping_views(&calib, size).unwrap().maps(&calib);
        let (min, med) = time(runs(), || {
            drop(maps.0.remap_rgb_gray(&raw.left_rgb, size.0, size.1));
            drop(maps.1.remap_gray(&raw.right_rgb, size.0, size.1));
        });
        println!("{name:<34} {min:>9.2} {med:>9.2}");
    }
    // A whole view's own work in the matcher thread (the live pipeline's per-view stages
    // but the assistant's plan): rectify and segment a realistic raw pair, match the object
    // over the full range with `bm`, drop clipped matches, refine the map (the window that
    // follows the surface), triangulate.
    let name = "view realistic pair";
    if filter.is_none_or(|f| picks(f, name)) {
        let (calib, raw) = realistic_raw();
        let opts = spinscan::pipeline::PipelineOptions { matching: MatchParams { num_disparities: 128, ..MatchParams::default() }, ..Default::default() };
        let mut pipe = spinscan::pipeline::Pipeline::new(&calib, (raw.width as u32, raw.height as u32), opts).unwrap();
        let mut points = 0;
        let (min, med) = time(runs(), || points = pipe.process_rgb(&raw.left_rgb, &raw.right_rgb, true).unwrap().cloud.points.len());
        println!("{name:<34} {min:>9.2} {med:>9.2} {:>10}", format!("{points} pt"));
    }
    // The silhouette's rim found (3 px, `--rim-px 3`), as each frame of such a scan pays it
    // after matching.
    let name = "segment rim";
    if filter.is_none_or(|f| picks(f, name)) {
        let mask = key.segment(&pair.left_rgb, pair.width, pair.height, None).unwrap();
        let (min, med) = time(runs(), || drop(spinscan::segment::inside_rim(&mask, pair.width, pair.height, 3)));
        println!("{name:<34} {min:>9.2} {med:>9.2}");
    }
    // How far inside the silhouette each pixel lies (the fusion's rim weights), as each
    // segmented frame pays it after matching.
    let name = "segment rim distance";
    if filter.is_none_or(|f| picks(f, name)) {
        let mask = key.segment(&pair.left_rgb, pair.width, pair.height, None).unwrap();
        let (min, med) = time(runs(), || drop(spinscan::segment::rim_distance(&mask, pair.width, pair.height)));
        println!("{name:<34} {min:>9.2} {med:>9.2}");
    }
    // The right image scaled to the left's contrast (0.7 × the gain), as each frame of a scan
    // whose cameras differ pays it; the ratio is measured once a scan, on the first frame.
    let name = "contrast scale";
    if filter.is_none_or(|f| picks(f, name)) {
        let dark: Vec<u8> = spinscan::io::rgb_to_gray(&pair.right_rgb).iter().map(|&v| (v as f64 * 0.7) as u8).collect();
        let mut r = dark.clone();
        let (min, med) = time(runs(), || {
            r.copy_from_slice(&dark);
            spinscan::stereo::gain::scale_contrast(&mut r, 1.0 / 0.7);
        });
        println!("{name:<34} {min:>9.2} {med:>9.2}");
    }
}

fn main() {
    let filter: Option<String> = std::env::args().skip(1).find(|a| !a.starts_with('-'));
    println!("{:<34} {:>9} {:>9} {:>10}", "case", "min ms", "median ms", "search px");
    segmentation(filter.as_deref());
    for case in cases() {
        for (method, threads) in [(Method::Bm, 1), (Method::Bm, 2), (Method::Sgm, 1), (Method::Sgm, 2)] {
            let params = MatchParams { num_disparities: case.num_disparities, threads, ..MatchParams::for_method(method) }.validate().unwrap();
            let mut m = StereoMatcher::new(params);
            let (w, h) = (case.width, case.height);
            // `bm` cases keep their names; `sgm` ones are prefixed.
            let case_name = if method == Method::Bm { case.name.clone() } else { format!("sgm {}", case.name) };
            let case = Case { name: case_name, ..case.clone() };
            let pair = (GrayView::new(w, h, &case.left).unwrap(), GrayView::new(w, h, &case.right).unwrap());
            let full = m.full_intervals(w, h, None);
            run(&mut m, pair, &full, &format!("{} full t{threads}", case.name), filter.as_deref());
            // Narrow intervals (±2 px) around the full-range result, as the registration
            // constraint gives them: the work must drop in proportion.
            let mut out = DisparityMap::new(w, h);
            m.compute(pair.0, pair.1, &full, &mut out).unwrap();
            run(&mut m, pair, &around(&out, 2), &format!("{} ±2px t{threads}", case.name), filter.as_deref());
            // One disparity everywhere: the matcher's fixed per-pixel cost (the floor row of
            // `bench table1`).
            let mid = case.num_disparities as i32 / 2;
            run(&mut m, pair, &DisparityIntervals::full(w, h, mid, mid), &format!("{} one disparity t{threads}", case.name), filter.as_deref());
            // The object alone (the blue screen segmented away), as a scan matches it: full
            // range, ±3 px around the full-range result, one disparity per pixel.
            if let Some(mask) = &case.mask {
                let fg = DisparityIntervals::within(w, h, Some(mask), 0, case.num_disparities as i32 - 1);
                run(&mut m, pair, &fg, &format!("{} object full t{threads}", case.name), filter.as_deref());
                m.compute(pair.0, pair.1, &fg, &mut out).unwrap();
                run(&mut m, pair, &around(&out, 3), &format!("{} object ±3px t{threads}", case.name), filter.as_deref());
                // The same, one interval per matcher tile (the hull over the tile's object
                // pixels), as the predicted mode gives it.
                run(&mut m, pair, &per_tile(&around(&out, 3), mask), &format!("{} object tile ±3px t{threads}", case.name), filter.as_deref());
                // Tiles of ±7 px: the width `bench table1`'s predicted row gives SGM (about 39
                // disparities a pixel in whole blocks; docs/matcher.md, "Where the narrow SGM
                // call's time goes").
                run(&mut m, pair, &per_tile(&around(&out, 7), mask), &format!("{} object tile ±7px t{threads}", case.name), filter.as_deref());
                let one = DisparityIntervals::within(w, h, Some(mask), mid, mid);
                run(&mut m, pair, &one, &format!("{} object one disparity t{threads}", case.name), filter.as_deref());
                // The window that follows the surface, run on the object's full-range map as
                // each view of a scan pays it after matching, with the object's mask (one
                // thread; each run starts from a copy of the map, about 0.1 ms of it).
                let name = format!("{} follow surface", case.name);
                if threads == 1 && filter.as_deref().is_none_or(|f| name.contains(f)) {
                    m.compute(pair.0, pair.1, &fg, &mut out).unwrap();
                    let mut map = out.clone();
                    let mut stats = Default::default();
                    let (min, med) = time(runs(), || {
                        map = out.clone();
                        stats = spinscan::stereo::follow::refine_following(&case.left, &case.right, Some(mask), &mut map);
                    });
                    println!("{name:<34} {min:>9.2} {med:>9.2} {:>10}", format!("{} px", stats.looked));
                }
                // The rim's profile, on the refined map, as each view pays it after the
                // refinement (each run starts from a copy of the map).
                let name = format!("{} rim profile", case.name);
                if threads == 1 && filter.as_deref().is_none_or(|f| name.contains(f)) {
                    m.compute(pair.0, pair.1, &fg, &mut out).unwrap();
                    spinscan::stereo::follow::refine_following(&case.left, &case.right, Some(mask), &mut out);
                    let rim = spinscan::segment::rim_distance(mask, w, h);
                    let mut map = out.clone();
                    let mut stats = Default::default();
                    let (min, med) = time(runs(), || {
                        map = out.clone();
                        stats = spinscan::stereo::follow::extrapolate_rim(&mut map, &rim, 1);
                    });
                    let spinscan::stereo::follow::RimStats { looked, profiled, .. } = stats;
                    println!("{name:<34} {min:>9.2} {med:>9.2} {:>10}", format!("{profiled}/{looked} px"));
                }
            }
        }
    }
}
