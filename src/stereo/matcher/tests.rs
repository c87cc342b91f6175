//! The matcher on synthetic shifted pairs: known shifts recovered, narrow intervals against
//! the full search, masks, negative disparities, the portable and SIMD paths against each
//! other, cropping against the whole image, a size mismatch named, and the window texture
//! against its definition.

use super::*;
use crate::stereo::MatchParams;

/// A random-texture pair where the right image is the left shifted by `shift(x, y)`.
fn shifted_pair(w: usize, h: usize, shift: impl Fn(usize, usize) -> usize) -> (Vec<u8>, Vec<u8>) {
    let mut state = 12345u32;
    let mut left = vec![0u8; w * h];
    for v in left.iter_mut() {
        state = state.wrapping_mul(1664525).wrapping_add(1013904223);
        *v = (state >> 24) as u8;
    }
    let mut right = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            // right(x) = left(x + d): a left pixel x appears at x − d on the right.
            let d = shift(x, y);
            right[y * w + x] = left[y * w + (x + d).min(w - 1)];
        }
    }
    (left, right)
}

/// Two disparity maps hold the same values (NaN, no match, equal to NaN).
fn same_map(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x == y || (x.is_nan() && y.is_nan()))
}

fn params(n: u32) -> ValidMatchParams {
    MatchParams { num_disparities: n, threads: 2, ..Default::default() }.validate().unwrap()
}

#[test]
fn recovers_a_constant_shift() {
    let (w, h) = (96, 40);
    let (l, r) = shifted_pair(w, h, |_, _| 7);
    let mut m = StereoMatcher::new(params(16));
    let mut out = DisparityMap::new(w, h);
    let iv = m.full_intervals(w, h, None);
    let stats = m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
    let mut good = 0;
    for y in 0..h {
        for x in 20..w - 20 {
            if out.get(x, y).is_some_and(|d| (d - 7.0).abs() < 0.5) {
                good += 1;
            }
        }
    }
    assert!(good as f64 > 0.95 * (h * (w - 40)) as f64, "{good}");
    assert_eq!(stats.searched, w * h);
}

/// A band-limited random texture (a sum of waves, the finest of period 3 px) sampled at x
/// in the left image and at x + `shift` in the right: a sub-pixel shift with no
/// interpolation in it.
fn subpixel_pair(w: usize, h: usize, shift: f64) -> (Vec<u8>, Vec<u8>) {
    let mut state = 777u32;
    let mut rnd = || {
        state = state.wrapping_mul(1664525).wrapping_add(1013904223);
        (state >> 8) as f64 / (1u32 << 24) as f64
    };
    let waves: Vec<[f64; 4]> = (0..40).map(|_| [0.05 + 0.28 * rnd(), 0.3 * (rnd() - 0.5), std::f64::consts::TAU * rnd(), 0.5 + rnd()]).collect();
    let norm = waves.iter().map(|w| w[3]).sum::<f64>();
    let at = |x: f64, y: f64| 128.0 + 110.0 * waves.iter().map(|&[fx, fy, ph, a]| a * (std::f64::consts::TAU * (fx * x + fy * y) + ph).sin()).sum::<f64>() / norm * 2.5;
    let image = |dx: f64| (0..w * h).map(|i| at((i % w) as f64 + dx, (i / w) as f64).round().clamp(0.0, 255.0) as u8).collect();
    (image(0.0), image(shift))
}

/// The sub-pixel fit has no pull towards whole pixels ("pixel locking"): a parabola through
/// the SAD costs pulls a shift of 7.25 to 7.16 here (mean error −0.09 px); the V fit's mean
/// errors stay within ±0.025 px.
#[test]
fn subpixel_shifts_are_not_pulled_to_whole_pixels() {
    let (w, h) = (160, 60);
    for f in [0.125, 0.25, 0.375, 0.625, 0.75] {
        let (l, r) = subpixel_pair(w, h, 7.0 + f);
        let mut m = StereoMatcher::new(params(16));
        let mut out = DisparityMap::new(w, h);
        let iv = m.full_intervals(w, h, None);
        m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
        let ds: Vec<f64> = (5..h - 5).flat_map(|y| (25..w - 25).map(move |x| (x, y))).filter_map(|(x, y)| out.get(x, y)).map(f64::from).collect();
        assert!(ds.len() > (h - 10) * (w - 50) * 9 / 10, "{f}: {} matched", ds.len());
        let bias = ds.iter().map(|d| d - 7.0 - f).sum::<f64>() / ds.len() as f64;
        assert!(bias.abs() < 0.04, "shift 7 + {f}: mean error {bias:+.3} px");
    }
}

#[test]
fn narrow_intervals_match_the_full_search_and_do_less_work() {
    let (w, h) = (120, 48);
    let (l, r) = shifted_pair(w, h, |x, _| 10 + x / 40);
    let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
    let mut m = StereoMatcher::new(params(32));
    let mut full = DisparityMap::new(w, h);
    let iv = m.full_intervals(w, h, None);
    let full_stats = m.compute(lv, rv, &iv, &mut full).unwrap();
    let mut narrow_iv = DisparityIntervals::full(w, h, 0, 31);
    for y in 0..h {
        for x in 0..w {
            let d = 10 + (x / 40) as i32;
            narrow_iv.set(x, y, Some((d - 2, d + 2)));
        }
    }
    let mut narrow = DisparityMap::new(w, h);
    let narrow_stats = m.compute(lv, rv, &narrow_iv, &mut narrow).unwrap();
    assert!(narrow_stats.evaluated * 5 < full_stats.evaluated);
    let mut agree = 0;
    let mut both = 0;
    for y in 0..h {
        for x in 16..w - 16 {
            if let (Some(a), Some(b)) = (full.get(x, y), narrow.get(x, y)) {
                both += 1;
                agree += ((a - b).abs() < 0.01) as usize;
            }
        }
    }
    assert!(both > (h * (w - 32)) * 8 / 10, "{both}");
    assert!(agree * 100 >= both * 99, "{agree} of {both}");
}

#[test]
fn masked_pixels_are_not_matched() {
    let (w, h) = (64, 24);
    let (l, r) = shifted_pair(w, h, |_, _| 3);
    let mask: Vec<u8> = (0..w * h).map(|i| if i % w < 32 { 0 } else { 255 }).collect();
    let mut m = StereoMatcher::new(params(8));
    let iv = m.full_intervals(w, h, Some(&mask));
    let mut out = DisparityMap::new(w, h);
    let stats = m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
    assert_eq!(stats.searched, 32 * h);
    assert!((0..h).all(|y| (0..32).all(|x| out.get(x, y).is_none())));
}

#[test]
fn negative_disparities() {
    let (w, h) = (80, 32);
    // The right image is the left shifted the other way: d = −6.
    let (l, r) = shifted_pair(w, h, |_, _| 6);
    let mut m = StereoMatcher::new(MatchParams { min_disparity: -12, num_disparities: 12, threads: 1, ..Default::default() }.validate().unwrap());
    let iv = m.full_intervals(w, h, None);
    let mut out = DisparityMap::new(w, h);
    // Swap roles: matching right→left sees the shift as negative.
    m.compute(GrayView::new(w, h, &r).unwrap(), GrayView::new(w, h, &l).unwrap(), &iv, &mut out).unwrap();
    let good = (0..h).flat_map(|y| (16..w - 16).map(move |x| (x, y))).filter(|&(x, y)| out.get(x, y).is_some_and(|d| (d + 6.0).abs() < 0.5)).count();
    assert!(good * 10 > h * (w - 32) * 9, "{good}");
}

/// Runs one stripe through the chosen code path, as `compute` does for a single thread.
fn run_path<const AVX2: bool, const AVX512: bool>(m: &mut StereoMatcher, l: GrayView, r: GrayView, iv: &DisparityIntervals) -> Vec<f32> {
    let mut out = DisparityMap::new(l.width, l.height);
    m.compute(l, r, iv, &mut out).unwrap(); // fills the prefiltered rows
    let p = m.params.clone();
    let geo = Geometry::new(&p, l.width, l.height);
    let mut scratch = StripeScratch::default();
    let mut vals = vec![0f32; l.width * l.height];
    let input = StripeInput::new(&p, geo, &m.left_pf, &m.right_pf_rev, IntervalSource::Given(iv));
    match_stripe_impl::<AVX2, AVX512>(input, 0..l.height, &mut vals, &mut scratch);
    vals
}

#[test]
fn portable_and_simd_paths_agree() {
    // Full range and narrow, shifting intervals; 16, 40 and 128 disparities.
    for n in [16u32, 40, 128] {
        let (w, h) = (160, 40);
        let (l, r) = shifted_pair(w, h, |x, y| 3 + (x + y) / 20);
        let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
        let mut m = StereoMatcher::new(MatchParams { num_disparities: n, threads: 1, speckle_window: 0, ..Default::default() }.validate().unwrap());
        let full = m.full_intervals(w, h, None);
        let mut narrow = DisparityIntervals::full(w, h, 0, n as i32 - 1);
        for y in 0..h {
            for x in 0..w {
                let d = 3 + ((x + y) / 20) as i32;
                narrow.set(x, y, (x % 7 != 0).then_some((d - 2 + (x % 3) as i32, d + 2)));
            }
        }
        for iv in [&full, &narrow] {
            let portable = run_path::<false, false>(&mut m, lv, rv, iv);
            #[cfg(target_arch = "x86_64")]
            {
                if std::is_x86_feature_detected!("avx2") {
                    assert!(same_map(&portable, &run_path::<true, false>(&mut m, lv, rv, iv)), "AVX2 differs, n = {n}");
                }
                if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw") {
                    assert!(same_map(&portable, &run_path::<true, true>(&mut m, lv, rv, iv)), "AVX-512 differs, n = {n}");
                }
            }
            assert!(portable.iter().filter(|v| v.is_finite()).count() > w * h / 2, "n = {n}");
        }
    }
}

#[test]
fn narrow_band_tiles_agree_with_the_row_path() {
    // Intervals of random width around a slanted surface, some pixels unsearched, a few
    // with the full range, rows left empty (tile sums must be summed afresh after them),
    // tiles whose band changes from one tile row to the next: the narrow-band path
    // (`tiles.rs`, taken by the AVX2 copy when the tiles' bands are narrow) must give
    // exactly what the row path gives.
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        let mut state = 99u32;
        let mut rand = move |m: u32| {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) % m
        };
        // (The last two without the left–right check, one without the uniqueness test too:
        // the narrow path then keeps the costs for the rival alone, or nothing.)
        let d = MatchParams::default();
        let (lr, uq) = (d.lr_max_diff, d.uniqueness_ratio);
        for (n, min_disparity, block, threads, lr_max_diff, uniqueness_ratio) in [(128u32, 0, 9, 1, lr, uq), (64, 0, 5, 2, lr, uq), (128, -20, 11, 1, lr, uq), (64, 0, 5, 1, None, uq), (128, 0, 9, 1, None, 0)] {
            let (w, h) = (230, 70);
            // The shift grows down the image, so tile bands change between tile rows.
            let (l, r) = shifted_pair(w, h, |_, y| 25 + y / 12);
            let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
            let p = MatchParams { num_disparities: n, min_disparity, block, threads, speckle_window: 0, lr_max_diff, uniqueness_ratio, ..Default::default() }.validate().unwrap();
            let mut m = StereoMatcher::new(p);
            let mut iv = DisparityIntervals::full(w, h, 0, 0);
            for y in 0..h {
                for x in 0..w {
                    let d = 25 + (y / 12) as i32;
                    let searched = !(20..23).contains(&y) && rand(9) != 0 && !(y > 40 && x > 150 && x < 190);
                    let range = match rand(4000) {
                        0 => (min_disparity, min_disparity + n as i32 - 1),
                        _ => (d - 1 - rand(6) as i32, d + 1 + rand(6) as i32),
                    };
                    iv.set(x, y, searched.then_some(range));
                }
            }
            let rows = run_path::<false, false>(&mut m, lv, rv, &iv);
            let tiles = run_path::<true, false>(&mut m, lv, rv, &iv);
            assert!(same_map(&rows, &tiles), "n = {n}, min {min_disparity}, block {block}");
            let good = rows.iter().enumerate().filter(|(i, v)| (*v - (25 + i / w / 12) as f32).abs() < 1.0).count();
            assert!(good > w * h / 2, "n = {n}: {good} pixels right");
            // And through `compute`: stripes (their own tile grids) and the crop change nothing.
            let mut out = DisparityMap::new(w, h);
            m.compute(lv, rv, &iv, &mut out).unwrap();
            assert!(same_map(out.values(), &rows), "compute differs, n = {n}");
        }
    }
}

#[test]
fn narrow_band_tiles_reject_flat_windows_as_the_row_path_does() {
    // Flat patches (no texture) inside a textured pair, narrow intervals: the narrow-band
    // path's texture test (in vector lanes) must reject the pixels the row path rejects.
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        let (w, h) = (160, 64);
        let (mut l, mut r) = shifted_pair(w, h, |_, _| 12);
        for y in 10..40 {
            for x in 30..90 {
                l[y * w + x] = 128;
            }
            for x in 18..78 {
                r[y * w + x] = 128;
            }
        }
        let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
        // (No uniqueness test and no left–right check: a flat window's equal costs would fail
        // them too.)
        let p = MatchParams { num_disparities: 32, threads: 1, speckle_window: 0, uniqueness_ratio: 0, lr_max_diff: None, ..Default::default() }.validate().unwrap();
        let mut m = StereoMatcher::new(p);
        let mut iv = DisparityIntervals::full(w, h, 0, 0);
        for y in 0..h {
            for x in 0..w {
                iv.set(x, y, Some((9, 15)));
            }
        }
        let rows = run_path::<false, false>(&mut m, lv, rv, &iv);
        let tiles = run_path::<true, false>(&mut m, lv, rv, &iv);
        assert!(same_map(&rows, &tiles));
        // The middle of the patch has no texture at all: nothing is matched there.
        assert!((20..30).all(|y| (50..70).all(|x| rows[y * w + x].is_nan())));
        assert!(rows.iter().filter(|v| (*v - 12.0).abs() < 1.0).count() > w * h / 2);
    }
}

#[test]
fn matching_the_crop_gives_what_matching_the_whole_image_gives() {
    let (w, h) = (200, 90);
    let (l, r) = shifted_pair(w, h, |x, y| 20 + (x + 2 * y) / 30);
    let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
    for (min_d, n) in [(0, 64), (-10, 48)] {
        let mut m = StereoMatcher::new(MatchParams { min_disparity: min_d, num_disparities: n, threads: 2, ..Default::default() }.validate().unwrap());
        // An object in the middle, with narrow intervals on part of it, and one pixel at the
        // image's border.
        let mut iv = DisparityIntervals::empty(w, h);
        for y in 30..70 {
            for x in 90..170 {
                let d = 20 + ((x + 2 * y) / 30) as i32;
                iv.set(x, y, Some(if x < 130 { (d - 3, d + 2) } else { (min_d, min_d + n as i32 - 1) }));
            }
        }
        let crop = Crop::of(&iv, &m.params).unwrap();
        assert!(crop.w < w && crop.h < h, "{crop:?}");
        let mut cropped = DisparityMap::new(w, h);
        let stats = m.compute(lv, rv, &iv, &mut cropped).unwrap();
        let mut whole = DisparityMap::new(w, h);
        let whole_stats = m.compute_whole(lv, rv, &iv, &crop.seen_from((0, 0)), &mut whole).unwrap();
        assert_eq!((stats.searched, stats.evaluated, stats.matched), (whole_stats.searched, whole_stats.evaluated, whole_stats.matched));
        assert!(same_map(cropped.values(), whole.values()));
        assert!(stats.matched > 2000, "{}", stats.matched);
        iv.set(0, 0, Some((min_d, min_d + 5)));
        assert_eq!(Crop::of(&iv, &m.params).unwrap().x0, 0);
    }
    // A wide search seeded from the half-size pair. SGM's level map (the intensity term) and
    // the half-size matches near the crop's edge see the crop, not the image, so the two
    // maps may differ at a few pixels; the crop's tiles are the image's, so the seed's are.
    let sgm = MatchParams { num_disparities: 128, threads: 1, ..MatchParams::for_method(crate::stereo::Method::Sgm) }.validate().unwrap();
    let mut m = StereoMatcher::new(sgm.clone());
    let mut iv = DisparityIntervals::empty(w, h);
    for y in 20..80 {
        for x in 40..190 {
            iv.set(x, y, Some((0, 127)));
        }
    }
    let crop = Crop::of(&iv, &m.params).unwrap();
    assert!(crop.w < w && crop.h < h && crop.span == 128, "{crop:?}");
    let (mut cropped, mut whole) = (DisparityMap::new(w, h), DisparityMap::new(w, h));
    let stats = m.compute(lv, rv, &iv, &mut cropped).unwrap();
    let whole_stats = m.compute_whole(lv, rv, &iv, &crop.seen_from((0, 0)), &mut whole).unwrap();
    let both = cropped.values().iter().zip(whole.values()).filter(|(a, b)| !a.is_nan() && !b.is_nan());
    let (n, near) = both.fold((0, 0), |(n, k), (a, b)| (n + 1, k + ((a - b).abs() <= 0.5) as usize));
    assert!(n * 100 >= whole_stats.matched * 99 && near * 100 >= n * 99, "{near} of {n} within 0.5 px, {} and {} matched", stats.matched, whole_stats.matched);
    let unseeded = StereoMatcher::new(MatchParams { coarse_to_fine: false, ..(*sgm).clone() }.validate().unwrap()).compute(lv, rv, &iv, &mut whole).unwrap();
    assert!(stats.evaluated < unseeded.evaluated, "seeded {} against {}", stats.evaluated, unseeded.evaluated);

    let mut m = StereoMatcher::new(params(16));
    let mut out = DisparityMap::new(w, h);
    assert_eq!(m.compute(lv, rv, &DisparityIntervals::empty(w, h), &mut out).unwrap().searched, 0);
    assert_eq!(out.valid_count(), 0);
}

#[test]
fn size_mismatch_is_an_error() {
    let a = vec![0u8; 20 * 10];
    let b = vec![0u8; 20 * 11];
    let mut m = StereoMatcher::new(params(8));
    let iv = m.full_intervals(20, 10, None);
    let err = m
        .compute(GrayView::new(20, 10, &a).unwrap(), GrayView::new(20, 11, &b).unwrap(), &iv, &mut DisparityMap::new(20, 10))
        .unwrap_err();
    assert_eq!(err, MatchError::SizeMismatch(20, 10, 20, 11));
}

/// A long wave along the rows (a period of 40 px), shifted by 7 px between the views.
fn wave_pair(w: usize, h: usize) -> (Vec<u8>, Vec<u8>) {
    let wave = |x: f64| (128.0 + 100.0 * (std::f64::consts::TAU * x / 40.0).sin()).round() as u8;
    let l: Vec<u8> = (0..w * h).map(|i| wave((i % w) as f64)).collect();
    let r: Vec<u8> = (0..w * h).map(|i| wave((i % w) as f64 + 7.0)).collect();
    (l, r)
}

/// SGM's values are refined by the correlation's where the two agree (they end near it);
/// where they disagree a value is dropped in a masked (scan) match and kept on a whole image.
#[test]
fn refinement_keeps_agreeing_values_and_drops_disagreeing_ones_in_a_scan() {
    let (w, h) = (96, 40);
    // The correlation cost falls steadily towards the true shift (7) from 20 px either side,
    // so a search of 3.0 ± 2 ends at its edge, 5.
    let (l, r) = wave_pair(w, h);
    let p = MatchParams { method: crate::stereo::Method::Sgm, num_disparities: 16, threads: 1, ..Default::default() }.validate().unwrap();
    let mut m = StereoMatcher::new(p);
    for masked in [true, false] {
        let mut out = DisparityMap::new(w, h);
        // Near the truth on the left half, 4 px off (beyond the correlation's ± 2) on the right.
        for (i, d) in out.values_mut().iter_mut().enumerate() {
            *d = if i % w < w / 2 { 7.3 } else { 3.0 };
        }
        let mut totals = MatchStats::default();
        let searched = DisparityIntervals::full(w, h, 0, 15);
        m.refine_subpixel(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &searched, &mut out, masked, &mut totals);
        let at = |x: usize, y: usize| out.values()[y * w + x];
        // Agreeing: near the correlation's value (the shift is whole, 7).
        assert!((at(30, 10) - 7.0).abs() < 0.1, "{}", at(30, 10));
        // Disagreeing: dropped in a scan, kept on a whole image.
        assert_eq!(at(70, 10).is_nan(), masked, "{}", at(70, 10));
        if !masked {
            assert_eq!(at(70, 10), 3.0);
        }
    }
}

/// `sgm_refine_agree` sets how close the two values must come: SGM values 0.3 and 0.7 px
/// from the correlation's are both refined at the default 1 px; at 0.5 px a scan drops the
/// second and a whole image keeps SGM's own value there.
#[test]
fn a_closer_agreement_drops_the_further_values_of_a_scan() {
    let (w, h) = (96, 40);
    let (l, r) = wave_pair(w, h);
    for (agree, masked) in [(1.0, true), (0.5, true), (0.5, false)] {
        let p = MatchParams { method: crate::stereo::Method::Sgm, num_disparities: 16, threads: 1, sgm_refine_agree: agree, ..Default::default() }.validate().unwrap();
        let mut m = StereoMatcher::new(p);
        let mut out = DisparityMap::new(w, h);
        // The true shift is whole (7): 0.3 px off on the left half, 0.7 px on the right.
        for (i, d) in out.values_mut().iter_mut().enumerate() {
            *d = if i % w < w / 2 { 7.3 } else { 7.7 };
        }
        let searched = DisparityIntervals::full(w, h, 0, 15);
        m.refine_subpixel(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &searched, &mut out, masked, &mut MatchStats::default());
        let at = |x: usize, y: usize| out.values()[y * w + x];
        // (Columns where the wave's correlation finds the whole shift, as in the test above.)
        assert!((at(30, 10) - 7.0).abs() < 0.1, "agree {agree}: {}", at(30, 10));
        match (agree, masked) {
            (1.0, _) => assert!((at(70, 10) - 7.0).abs() < 0.1, "agree {agree}: {}", at(70, 10)),
            (_, true) => assert!(at(70, 10).is_nan(), "agree {agree}: {}", at(70, 10)),
            (_, false) => assert_eq!(at(70, 10), 7.7),
        }
    }
}

/// The refinement compiled for AVX2 (its search for disagreeing pixels in vector compares)
/// gives the portable build's values to the bit: SGM values near and far from the
/// correlation's, unmatched pixels, on a masked match with a rim and on a whole image.
#[test]
fn the_avx2_refinement_is_the_portable_one() {
    if !std::is_x86_feature_detected!("avx2") {
        return;
    }
    let (w, h) = (83, 37);
    let mut next = crate::testing::xorshift(0x0dd_ba11);
    let l: Vec<u8> = (0..w * h).map(|_| (next() % 256) as u8).collect();
    let r: Vec<u8> = (0..w * h).map(|i| l[(i / w) * w + (i % w + 5).min(w - 1)]).collect();
    let p = MatchParams { method: crate::stereo::Method::Sgm, num_disparities: 16, threads: 1, ..Default::default() }.validate().unwrap();
    let mut searched = DisparityIntervals::full(w, h, 0, 15);
    let mut sgm = DisparityMap::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let d = match next() % 8 {
                0 => None,
                // Beyond the correlation's ± 2, or just inside or outside its agreement.
                1 => Some(1.0 + (next() % 3) as f32),
                2 => Some(5.0 + [-1.25, -0.99, 1.0, 1.01][(next() % 4) as usize]),
                _ => Some(5.0 + ((next() % 100) as f32 - 50.0) / 100.0),
            };
            sgm.set(x, y, d);
            if (20..60).contains(&x) && (5..30).contains(&y) || d.is_none() && next() % 2 == 0 {
                continue;
            }
            searched.set(x, y, None);
        }
    }
    let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
    for masked in [true, false] {
        let mut m = StereoMatcher::new(p.clone());
        let (mut fast, mut portable) = (sgm.clone(), sgm.clone());
        m.refine::<true>(lv, rv, &searched, &mut fast, masked, &mut MatchStats::default());
        m.refine::<false>(lv, rv, &searched, &mut portable, masked, &mut MatchStats::default());
        assert!(fast.values().iter().zip(portable.values()).all(|(a, b)| a.to_bits() == b.to_bits()), "masked {masked}");
        let changed = fast.values().iter().zip(sgm.values()).filter(|(a, b)| a.to_bits() != b.to_bits()).count();
        assert!(changed > w * h / 4, "masked {masked}: {changed} values refined or dropped");
    }
}

/// Where the correlation agrees, the refined value is the correlation's plus a share
/// (`own_weight`) of SGM's deviation from it, around their mean lean over the pixel's square
/// (`OFFSET_TILE`): raising one SGM value raises its refined value by that share of the raise
/// (less its own part of the lean), lowers the rest of its square a little, and leaves
/// the other squares alone; raised further from the correlation's value, SGM's share grows.
#[test]
fn the_blend_takes_sgm_s_deviation_around_its_lean() {
    let (w, h) = (96, 40);
    let (l, r) = shifted_pair(w, h, |_, _| 7);
    // At 1 px the lean is taken over the pixels whose correlation found the shift; a looser
    // limit also takes in a few of this pattern's pixels whose correlation lies 1–1.25 px
    // off, which moves the lean this test reads the blend around.
    let p = MatchParams { method: crate::stereo::Method::Sgm, num_disparities: 16, threads: 1, sgm_refine_agree: 1.0, ..Default::default() }.validate().unwrap();
    let mut m = StereoMatcher::new(p);
    // The raised pixel, in the middle of the first square.
    let (t, c) = (refine::OFFSET_TILE, refine::OFFSET_TILE / 2);
    assert!(3 * t <= w && t <= h);
    let refined = |m: &mut StereoMatcher, raised: Option<f32>| {
        let mut out = DisparityMap::new(w, h);
        out.values_mut().fill(7.1);
        if let Some(v) = raised {
            out.values_mut()[c * w + c] = v;
        }
        let searched = DisparityIntervals::full(w, h, 0, 15);
        m.refine_subpixel(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &searched, &mut out, false, &mut MatchStats::default());
        out
    };
    let before = refined(&mut m, None);
    // Every SGM value of the square equal, its deviation around the lean is about nil: the
    // refined value is about the correlation's own.
    let corr = before.values()[c * w + c];
    assert!((corr - 7.0).abs() < 0.05, "the correlation finds the shift: {corr}");
    let mut shares = vec![];
    for raised in [7.25f32, 7.6, 7.8] {
        let after = refined(&mut m, Some(raised));
        let change = |x: usize, y: usize| after.values()[y * w + x] - before.values()[y * w + x];
        // The lean over the square's 256 agreeing pixels rises by a 256th of the raise.
        // Within a twentieth: the correlation's values differ a little from pixel to pixel, and
        // the pixel's weight before the raise was its own.
        let lift = raised - 7.1;
        let own = refine::own_weight(raised, corr) * lift * (1.0 - 1.0 / (t * t) as f32);
        assert!((change(c, c) - own).abs() < own / 20.0, "{raised}: {} against {own}", change(c, c));
        assert!(change(c + 1, c - 1) < 0.0 && change(c + 1, c - 1) > -own / 100.0, "{}", change(c + 1, c - 1));
        assert_eq!(change(c + t, c), 0.0);
        shares.push(change(c, c) / lift);
    }
    // Near the correlation's value SGM's share is the least; it grows the further apart.
    assert!((shares[0] - refine::OWN_WEIGHT).abs() < 0.01 && shares[1] > shares[0] + 0.05 && shares[2] > shares[1] + 0.05, "SGM's share grows with the disagreement: {shares:?}");
}

/// On a scan's rim the refinement correlates over the object's pixels alone where the whole
/// window disagrees with SGM: a background with stronger texture, matching at a disparity
/// within the refinement's ± 2, pulls a window that straddles the silhouette to its own
/// disparity, and those matches would be dropped.
#[test]
fn the_rim_is_refined_over_the_object_alone() {
    let (w, h, d_object, d_background) = (96, 40, 6usize, 4usize);
    let object = 30..70;
    let mut next = crate::testing::xorshift(7);
    let background: Vec<u8> = (0..w * h).map(|_| (next() % 256) as u8).collect();
    let texture: Vec<u8> = (0..w * h).map(|_| 110 + (next() % 20) as u8).collect();
    let left: Vec<u8> = (0..w * h).map(|i| if object.contains(&(i % w)) { texture[i] } else { background[i] }).collect();
    let right: Vec<u8> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            if object.contains(&(x + d_object)) { texture[y * w + x + d_object] } else { background[y * w + (x + d_background).min(w - 1)] }
        })
        .collect();
    let p = MatchParams { method: crate::stereo::Method::Sgm, num_disparities: 16, threads: 1, ..Default::default() }.validate().unwrap();
    let mut m = StereoMatcher::new(p);
    let mut searched = DisparityIntervals::full(w, h, 0, 15);
    let mut out = DisparityMap::new(w, h);
    for y in 0..h {
        for x in 0..w {
            if object.contains(&x) {
                out.set(x, y, Some(d_object as f32 + 0.1));
            } else {
                searched.set(x, y, None);
            }
        }
    }
    let mut totals = MatchStats::default();
    m.refine_subpixel(GrayView::new(w, h, &left).unwrap(), GrayView::new(w, h, &right).unwrap(), &searched, &mut out, true, &mut totals);
    // Every object pixel kept; away from the image's top and bottom rows (windows cut short)
    // within a pixel of the truth, not at the background's disparity: where the whole window
    // agreed with SGM its value stays (pulled towards the background's at the silhouette), the
    // others are taken over the object alone. Inside, the correlation's own precision.
    for y in 0..h {
        for x in object.clone() {
            let d = out.values()[y * w + x];
            assert!(!d.is_nan(), "pixel ({x}, {y}) dropped");
            let tolerance = if (40..60).contains(&x) { 0.25 } else { 1.0 };
            if (6..h - 6).contains(&y) {
                assert!((d - d_object as f32).abs() < tolerance, "pixel ({x}, {y}): {d}");
            }
        }
    }
}

#[test]
fn rounding_without_libm_is_the_cast_of_round() {
    let mut rand = crate::testing::xorshift(99);
    let mut values: Vec<f32> = (0..100_000).map(|_| ((rand() % 2_000_000) as f32 - 1_000_000.0) / 4096.0).collect();
    values.extend([0.5, -0.5, 1.5, -1.5, 0.49999997, -0.49999997, 2.5000002, 127.5, -127.5, 0.0, -0.0, 8_388_607.5, -8_388_607.5]);
    for d in values {
        assert_eq!(super::round_half_away_within(d), d.round() as i32, "{d}");
    }
}

#[test]
fn full_ranges_up_to_the_tile_band_match_as_the_row_path_does() {
    // Over at most `TILE_PATH_BAND` disparities the full range takes the narrow-band path
    // (faster there): it must give exactly the row path's map, for ranges that are and are
    // not whole blocks of 16, negative ones, and the smallest and largest windows.
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        for (n, min_disparity, block) in [(16u32, 0, 9), (20, 0, 9), (37, -5, 3), (48, -30, 15), (64, 0, 31), (64, 2, 7)] {
            assert!(n as usize <= super::TILE_PATH_BAND);
            let (w, h) = (150, 50);
            let (l, r) = shifted_pair(w, h, |x, _| 8 + x / 40);
            let (lv, rv) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap());
            // (No speckle filter: the stripe runs compared below leave it to `compute`.)
            let p = MatchParams { num_disparities: n, min_disparity, block, threads: 1, speckle_window: 0, ..Default::default() }.validate().unwrap();
            let mut m = StereoMatcher::new(p);
            let iv = m.full_intervals(w, h, None);
            let rows = run_path::<false, false>(&mut m, lv, rv, &iv);
            let tiles = run_path::<true, false>(&mut m, lv, rv, &iv);
            assert!(same_map(&rows, &tiles), "n = {n}, min {min_disparity}, block {block}");
            assert!(rows.iter().filter(|v| !v.is_nan()).count() > w * h / 3, "n = {n}: the pair is matched");
            let mut out = DisparityMap::new(w, h);
            m.compute(lv, rv, &iv, &mut out).unwrap();
            assert!(same_map(out.values(), &rows), "compute differs, n = {n}");
        }
    }
}

#[test]
fn the_searched_span_is_the_first_and_last_searched_pixel() {
    let mut next = crate::testing::xorshift(31);
    for n in [0usize, 1, 5, 31, 32, 33, 64, 95, 200, 640] {
        for _ in 0..50 {
            // Mostly background, a few searched pixels anywhere (none in some rows).
            let searched = (next() % 4) as usize;
            let (mut lo, mut hi) = (vec![1i16; n], vec![0i16; n]);
            for _ in 0..searched.min(n) {
                let x = (next() % n as u64) as usize;
                (lo[x], hi[x]) = (3, 3 + (next() % 5) as i16);
            }
            let want = (0..n).position(|x| lo[x] <= hi[x]).map(|a| (a, (0..n).rposition(|x| lo[x] <= hi[x]).unwrap()));
            assert_eq!(crate::stereo::disparity::searched_span(&lo, &hi), want, "n {n}, lo {lo:?}");
        }
    }
}

#[test]
fn a_pixels_texture_is_the_sum_of_its_windows_column_sums() {
    let mut next = crate::testing::xorshift(0x7e97_0e);
    for block in [3usize, 9, 15] {
        let p = MatchParams { block: block as u32, ..Default::default() }.validate().unwrap();
        let w = 45;
        let g = Geometry::new(&p, w, 20);
        let mut s = StripeScratch { tex_col: (0..g.wp).map(|_| (next() % 2000) as u32).collect(), tex_row: vec![0; w], ..Default::default() };
        for span in [0..w, 3..4, 7..31, w - 1..w] {
            s.tex_row.fill(u32::MAX);
            rows::texture_row(g, &mut s, span.clone());
            for x in 0..w {
                let want = if span.contains(&x) { s.tex_col[x..x + block].iter().sum() } else { u32::MAX };
                assert_eq!(s.tex_row[x], want, "block {block}, span {span:?}, x {x}");
            }
        }
    }
}

/// A pair whose left half lies at disparity 7 and whose right half at `far`, in a smooth
/// texture (a surface's: the cost falls towards the true disparity from afar), matched over
/// `first ..= first + 15` with and without `drop_range_edges` (with `short`, every pixel's
/// interval stops one short of the range's last end). Returns the right half's matches at the
/// range's end (the one `far` lies beyond), all its matches, the left half's good matches,
/// and `range_edge`.
fn range_edge_case(method: Method, first: i32, far: usize, drop: bool, short: bool) -> (usize, usize, usize, usize) {
    let (w, h) = (128, 48);
    let (rough, _) = shifted_pair(w + 32, h, |_, _| 0);
    let rough = &rough;
    // Each pixel the mean of a 17 × 3 window of the random texture.
    let smooth: Vec<u8> = (0..h * (w + 32))
        .map(|i| {
            let (x, y) = (i % (w + 32), i / (w + 32));
            let sum: u32 = (y.saturating_sub(1)..(y + 2).min(h)).flat_map(|yy| (x.saturating_sub(8)..(x + 9).min(w + 32)).map(move |xx| rough[yy * (w + 32) + xx] as u32)).sum();
            (sum / 51) as u8
        })
        .collect();
    let l: Vec<u8> = (0..h).flat_map(|y| smooth[y * (w + 32)..][..w].iter().copied()).collect();
    let r: Vec<u8> = (0..h * w).map(|i| (i % w, i / w)).map(|(x, y)| smooth[y * (w + 32) + x + if x < w / 2 { 7 } else { far }]).collect();
    let p = MatchParams { min_disparity: first, num_disparities: 16, threads: 1, ..MatchParams::for_method(method) }.validate().unwrap();
    let end = if far as i32 > first { p.max_disparity() } else { first } as f32;
    let mut m = StereoMatcher::new(p).drop_range_edges(drop);
    let last = m.params().max_disparity();
    let iv = if short { DisparityIntervals::full(w, h, first, last - 1) } else { m.full_intervals(w, h, None) };
    let mut out = DisparityMap::new(w, h);
    let stats = m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
    let right_half = || (0..h).flat_map(|y| (w / 2 + 24..w - 8).map(move |x| (x, y)));
    let at_end = right_half().filter(|&(x, y)| out.get(x, y).is_some_and(|d| (d - end).abs() < 0.5)).count();
    let matched = right_half().filter(|&(x, y)| out.get(x, y).is_some()).count();
    let good = (0..h).flat_map(|y| (24..w / 2 - 8).map(move |x| (x, y))).filter(|&(x, y)| out.get(x, y).is_some_and(|d| (d - 7.0).abs() < 0.5)).count();
    (at_end, matched, good, stats.range_edge)
}

#[test]
fn matches_at_the_range_s_end_are_dropped_where_asked() {
    for method in [Method::Bm, Method::Sgm] {
        // The right half one disparity beyond the range's end: at 16 with 0 … 15 searched,
        // and at 3 with 4 … 19 (the first disparity is an end too where it is not 0).
        for (first, far) in [(0, 16), (4, 3)] {
            // Kept (what `disparity` gives, as OpenCV does), they pile up at the end:
            // measured 219 and 192 (`bm`), 1519 and 1513 (`sgm`) of the 1536 pixels.
            let (at_end, _, good_kept, edge) = range_edge_case(method, first, far, false, false);
            assert!(at_end > 150, "{method:?} {first}: {at_end} matches at the range's end without dropping");
            assert_eq!(edge, 0);
            let (at_end_dropped, _, good, edge) = range_edge_case(method, first, far, true, false);
            assert_eq!(at_end_dropped, 0, "{method:?} {first}");
            assert!(edge >= at_end, "{method:?} {first}: {edge} dropped, {at_end} at the end in the half's middle alone");
            // What lies inside the range keeps its matches.
            assert!(good == good_kept && good > 1500, "{method:?} {first}: {good} against {good_kept}");
        }
        // A search that reaches the first end but not the last is still checked there (the
        // call skips the drop only when its search reaches neither end).
        let (at_first, _, _, _) = range_edge_case(method, 4, 3, false, true);
        let (dropped_first, _, _, edge) = range_edge_case(method, 4, 3, true, true);
        assert!(at_first > 150 && dropped_first == 0 && edge >= at_first, "{method:?}: {at_first} at the first end, {dropped_first} left, {edge} dropped");
        // Disparity 0 is not an end to drop at: nothing lies beyond infinity.
        let (at_zero, matched, _, edge) = range_edge_case(method, 0, 0, true, false);
        assert!(at_zero > 1500 && at_zero == matched, "{method:?}: {at_zero} of {matched} at 0");
        assert_eq!(edge, 0, "{method:?}");
    }
}
