//! `spinscan disparity`, `rectify` and `points`: one pair through the stereo core.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use serde_json::json;

use super::{input, load_pair, median, output, Failure, KeyArgs, MatchArgs, RawPairArgs, RectArgs};
use spinscan::calib::StereoCalib;
use spinscan::io;
use spinscan::pipeline::{Pipeline, PipelineOptions};
use spinscan::stereo::{DisparityMap, GrayView, StereoMatcher};

#[derive(Args)]
pub struct DisparityArgs {
    /// Left image (PNG, JPEG or PNM; colour is converted to grey).
    #[arg(long)]
    pub left: PathBuf,
    /// Right image, the same size.
    #[arg(long)]
    pub right: PathBuf,
    /// Calibration (file or folder); without it the pair is taken as rectified.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    #[command(flatten)]
    pub rect: RectArgs,
    #[command(flatten)]
    pub matching: MatchArgs,
    /// Times the matcher K times and reports the median as `match_ms`; with K > 1 a warm-up
    /// run comes first (as the peer script does for OpenCV), kept out of the median.
    /// `first_call_ms` is always the matcher's first call, its buffers' first touch included
    /// (the warm-up's, or with K = 1 the one call's).
    #[arg(long, default_value_t = 1)]
    pub repeat: u32,
    /// Disparity as 16-bit PNG (|d| × 256, 0 = none).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Signed disparity as PFM.
    #[arg(long)]
    pub pfm: Option<PathBuf>,
    /// False-colour disparity PNG.
    #[arg(long)]
    pub color: Option<PathBuf>,
}

#[derive(Args)]
pub struct RectifyArgs {
    #[command(flatten)]
    pub pair: RawPairArgs,
    #[command(flatten)]
    pub rect: RectArgs,
    /// Output folder: left.png, right.png, rectification.json.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct PointsArgs {
    #[command(flatten)]
    pub pair: RawPairArgs,
    /// `auto` (blue-screen chroma key) or a mask image in raw left coordinates (non-zero = object).
    #[arg(long)]
    pub mask: Option<String>,
    #[command(flatten)]
    pub key: KeyArgs,
    #[command(flatten)]
    pub rect: RectArgs,
    #[command(flatten)]
    pub matching: MatchArgs,
    /// Output point cloud: binary PLY, x y z float (mm, left raw camera frame), red green blue.
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Also write the disparity (16-bit PNG).
    #[arg(long)]
    pub disparity: Option<PathBuf>,
    /// Also write the rectified mask used (PNG).
    #[arg(long)]
    pub mask_out: Option<PathBuf>,
}

pub fn write_disparity_outputs(disp: &DisparityMap, png: &Path, pfm: Option<&Path>, color: Option<&Path>, range: (f32, f32)) -> Result<(), Failure> {
    io::write_disparity_png(png, disp).map_err(output)?;
    if let Some(p) = pfm {
        io::write_pfm(p, disp).map_err(output)?;
    }
    if let Some(p) = color {
        io::write_rgb_png(p, disp.width, disp.height, &io::disparity_false_color(disp, range)).map_err(output)?;
    }
    Ok(())
}

pub fn cmd_disparity(a: DisparityArgs) -> Result<(), Failure> {
    if a.repeat == 0 {
        return Err(input("--repeat must be at least 1"));
    }
    let (l, r) = load_pair(&a.left, &a.right)?;
    let (w, h) = (l.width, l.height);
    // Rectify first (not timed), then time the matcher alone on grey images.
    let (left_gray, right_gray, params, sign, alpha) = match &a.calib {
        Some(path) => {
            let calib = StereoCalib::load(path).map_err(input)?;
            let opts = PipelineOptions {
                alpha: a.rect.alpha,
                min_disparity: a.matching.min_disparity,
                matching: a.matching.params()?,
                ..Default::default()
            };
            let pipe = Pipeline::new(&calib, (w as u32, h as u32), opts).map_err(input)?;
            let (lr, rr) = pipe.rectify_rgb(&l.rgb, &r.rgb);
            let params = (**pipe.matcher().params()).clone();
            (io::rgb_to_gray(&lr), io::rgb_to_gray(&rr), params, pipe.rect.disparity_sign, Some(pipe.rect.alpha))
        }
        None => {
            let params = a.matching.params()?;
            let sign = if params.min_disparity + params.num_disparities as i32 - 1 <= 0 { -1 } else { 1 };
            (l.gray, r.gray, params, sign, None)
        }
    };
    let valid = params.clone().validate().map_err(input)?;
    let threads = valid.thread_count();
    let mut matcher = StereoMatcher::new(valid);
    let intervals = matcher.full_intervals(w, h, None);
    let (lv, rv) = (GrayView::new(w, h, &left_gray).unwrap(), GrayView::new(w, h, &right_gray).unwrap());
    let mut disp = DisparityMap::new(w, h);
    let mut times = Vec::new();
    let mut stats = Default::default();
    // One warm-up (buffers, caches) before the timed runs when there are several, as the peer
    // script does for OpenCV; its time is reported apart as the first call's.
    let mut first_call_ms = None;
    if a.repeat > 1 {
        let t0 = Instant::now();
        matcher.compute(lv, rv, &intervals, &mut disp).map_err(input)?;
        first_call_ms = Some(t0.elapsed().as_secs_f64() * 1e3);
    }
    for _ in 0..a.repeat {
        let t0 = Instant::now();
        stats = matcher.compute(lv, rv, &intervals, &mut disp).map_err(input)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let first_call_ms = first_call_ms.unwrap_or(times[0]);
    let lo = params.min_disparity as f32;
    let hi = (params.min_disparity + params.num_disparities as i32 - 1) as f32;
    let range = (lo.abs().min(hi.abs()), lo.abs().max(hi.abs()));
    write_disparity_outputs(&disp, &a.out, a.pfm.as_deref(), a.color.as_deref(), range)?;
    let report = json!({
        "match_ms": median(times),
        "first_call_ms": first_call_ms,
        "method": params.method.name(),
        "coarse_to_fine": params.coarse_to_fine,
        "valid_fraction": stats.valid_fraction(),
        "disparity_sign": sign,
        "rectify_alpha": alpha,
        "width": w,
        "height": h,
        "min_disparity": params.min_disparity,
        "num_disparities": params.num_disparities,
        "block": params.block,
        "threads": threads,
        "repeat": a.repeat,
        "matched": stats.matched,
        "searched": stats.searched,
        "mean_search_px": stats.mean_search_px(),
    });
    println!("{report}");
    Ok(())
}

pub fn cmd_rectify(a: RectifyArgs) -> Result<(), Failure> {
    let (l, r) = load_pair(&a.pair.left, &a.pair.right)?;
    let calib = StereoCalib::load(&a.pair.calib).map_err(input)?;
    let opts = PipelineOptions { alpha: a.rect.alpha, ..Default::default() };
    let pipe = Pipeline::new(&calib, (l.width as u32, l.height as u32), opts).map_err(input)?;
    let (lr, rr) = pipe.rectify_rgb(&l.rgb, &r.rgb);
    std::fs::create_dir_all(&a.out).map_err(|e| output(format!("cannot create {}: {e}", a.out.display())))?;
    io::write_rgb_png(&a.out.join("left.png"), l.width, l.height, &lr).map_err(output)?;
    io::write_rgb_png(&a.out.join("right.png"), l.width, l.height, &rr).map_err(output)?;
    let m = |m: nalgebra::DMatrixView<f64>| -> Vec<Vec<f64>> { (0..m.nrows()).map(|i| m.row(i).iter().copied().collect()).collect() };
    let rect = &pipe.rect;
    let doc = json!({
        "alpha": rect.alpha,
        "R1": m(rect.r1.as_view()), "R2": m(rect.r2.as_view()),
        "P1": m(rect.p1.as_view()), "P2": m(rect.p2.as_view()), "Q": m(rect.q.as_view()),
        "disparity_sign": rect.disparity_sign,
    });
    io::write_atomic(&a.out.join("rectification.json"), serde_json::to_string_pretty(&doc).unwrap().as_bytes()).map_err(output)?;
    println!("{}", json!({"left": a.out.join("left.png"), "right": a.out.join("right.png"), "disparity_sign": rect.disparity_sign, "focal_px": rect.p1[(0, 0)], "alpha": rect.alpha}));
    Ok(())
}

pub fn cmd_points(a: PointsArgs) -> Result<(), Failure> {
    let (l, r) = load_pair(&a.pair.left, &a.pair.right)?;
    let calib = StereoCalib::load(&a.pair.calib).map_err(input)?;
    let opts = PipelineOptions {
        alpha: a.rect.alpha,
        min_disparity: a.matching.min_disparity,
        matching: a.matching.params()?,
        chroma: a.key.chroma(),
        follow_surface: !a.matching.no_follow_surface,
        ..Default::default()
    };
    let pipe = Pipeline::new(&calib, (l.width as u32, l.height as u32), opts.clone()).map_err(input)?;
    let plate = a.key.load_plate((l.width, l.height), "the images")?;
    if plate.is_some() && a.mask.as_deref() != Some("auto") {
        return Err(input("--plate is used by the blue-screen segmentation: add --mask auto"));
    }
    let mut prepared = match a.mask.as_deref() {
        None => pipe.prepare_rgb(&l.rgb, &r.rgb, false, None),
        Some("auto") => pipe.prepare_rgb(&l.rgb, &r.rgb, true, plate.map(|p| pipe.rectify_plate(&p)).as_ref()),
        Some(file) => {
            let m = io::load_image(Path::new(file)).map_err(input)?;
            if (m.width, m.height) != (l.width, l.height) {
                return Err(input(format!("mask {file} is {}×{} but the images are {}×{}", m.width, m.height, l.width, l.height)));
            }
            let raw: Vec<u8> = m.gray.iter().map(|&v| if v > 0 { 255 } else { 0 }).collect();
            let mask = pipe.rectify_left_mask(&raw);
            let (lr, rr) = pipe.rectify_rgb(&l.rgb, &r.rgb);
            Ok(spinscan::pipeline::Prepared::from_rectified(lr, &rr, Some(mask)))
        }
    }
    .map_err(input)?;
    // No range given: the pair's own (its object's, with a mask). The right image's contrast
    // brought to the left's where the cameras differ.
    let opts = PipelineOptions { fit_range: a.matching.range_unset(), ..opts };
    let fitted = spinscan::pipeline::range::fit_prepared(pipe, &calib, &prepared, 0, &opts).map_err(input)?;
    let (mut pipe, fit, contrast) = (fitted.pipe, fitted.range, fitted.contrast);
    pipe.balance(&mut prepared);
    let view = pipe.process_prepared(prepared).map_err(input)?;
    match view.key.map(|k| k.source) {
        Some(spinscan::segment::KeySource::NotFound) => eprintln!("points: warning: {}; give the screen's colour (--key-color R,G,B) or a background plate (--plate)", spinscan::segment::no_screen()),
        Some(spinscan::segment::KeySource::Backdrop { threshold, .. }) => eprintln!("points: note: {}", spinscan::segment::plain_backdrop(threshold)),
        _ => {}
    }
    if let (Some(_), Some(mask)) = (view.key, &view.mask) {
        let edge = spinscan::segment::edge_share(mask, view.disparity.width, view.disparity.height);
        if edge >= spinscan::segment::EDGE_WARN_SHARE {
            eprintln!("points: warning: {}; cover it in the screen's colour, or give a background plate (--plate)", spinscan::segment::object_on_edge(edge));
        }
    }
    io::ply::write_ply(&a.out, &view.cloud).map_err(output)?;
    if let Some(p) = &a.disparity {
        io::write_disparity_png(p, &view.disparity).map_err(output)?;
    }
    if let (Some(p), Some(mask)) = (&a.mask_out, &view.mask) {
        io::write_gray_png(p, l.width, l.height, mask).map_err(output)?;
    }
    println!(
        "{}",
        json!({"points": view.cloud.len(), "match_ms": view.match_ms, "valid_fraction": view.stats.valid_fraction(),
               "range_edge_px": view.stats.range_edge, "rim_points": view.rim_points(), "disparity_sign": pipe.rect.disparity_sign, "rectify_alpha": pipe.rect.alpha, "out": a.out,
               "min_disparity": pipe.matcher().params().min_disparity, "num_disparities": pipe.matcher().params().num_disparities,
               "range_fit": fit.map(|f| f.entry()), "contrast": contrast.map(|c| c.entry())})
    );
    if view.stats.range_edge_share() >= spinscan::pipeline::results::RANGE_EDGE_WARN_SHARE {
        eprintln!(
            "points: {} matches at an end of the disparity range were dropped (the scene comes closer, or lies farther, than the range covers): widen it with --num-disparities or --min-disparity",
            view.stats.range_edge
        );
    }
    Ok(())
}
