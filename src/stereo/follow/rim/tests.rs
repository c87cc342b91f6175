//! The rim's profile on synthetic maps whose true disparities are known.

use super::*;
use crate::segment::rim_distance;

const W: usize = 200;
const H: usize = 200;

/// A small deterministic noise in ±`amp`, as a matcher's sub-pixel scatter.
fn noise(x: usize, y: usize, amp: f32) -> f32 {
    let h = (x as u32).wrapping_mul(2_654_435_761) ^ (y as u32).wrapping_mul(40_503).rotate_left(13);
    let h = h.wrapping_mul(2_246_822_519) >> 8;
    (h as f32 / (1u32 << 24) as f32 - 0.5) * 2.0 * amp
}

/// A ball's true disparities (`f·B / Z` of a sphere of radius 45 mm whose centre is 410 mm
/// away, 1.6 px a mm, seen orthographically), its silhouette a circle of 72 px around
/// (100, 100); NaN outside. `sign`: the rig's disparity sign.
fn ball(x: f64, y: f64, sign: f64) -> f64 {
    let (rho, zc, px_mm, fb) = (45.0, 410.0, 1.6, 700.0 * 55.0);
    let r = (x - 100.0).hypot(y - 100.0) / px_mm;
    if r >= rho { f64::NAN } else { sign * fb / (zc - (rho * rho - r * r).sqrt()) }
}

/// The map a matcher and the refinement give the ball: the truth with a little noise, and
/// within 6.5 px of the silhouette the straight line through the truth 6.5 and 9.5 px inside
/// (the planes' extrapolation, which the curve bends away from). The mask takes the pixels
/// the ball covers in part too (their centres up to 0.45 px beyond its outline), as a key
/// does; their truth is the outline's. Also the truth and the mask.
fn matched_ball(sign: f64) -> (DisparityMap, Vec<f32>, Vec<u8>) {
    let mut map = DisparityMap::new(W, H);
    let (mut truth, mut mask) = (vec![f32::NAN; W * H], vec![0u8; W * H]);
    let edge = 72.0;
    let along = |t: f64| ball(100.0 + edge - t, 100.0, sign);
    for y in 0..H {
        for x in 0..W {
            let (xf, yf) = (x as f64, y as f64);
            let r = (xf - 100.0).hypot(yf - 100.0);
            if r >= edge + 0.45 {
                continue;
            }
            let inside = edge - r;
            let d = along(inside.max(1e-9));
            let i = y * W + x;
            (truth[i], mask[i]) = (d as f32, 255);
            let v = if inside >= 6.5 {
                d
            } else {
                let (a, b) = (along(6.5), along(9.5));
                a + (a - b) / 3.0 * (6.5 - inside)
            };
            map.set(x, y, Some(v as f32 + noise(x, y, 0.05)));
        }
    }
    (map, truth, mask)
}

/// Whether two maps hold the same values, bit for bit (NaN included).
fn same(a: &DisparityMap, b: &DisparityMap) -> bool {
    a.values().iter().zip(b.values()).all(|(x, y)| x.to_bits() == y.to_bits())
}

/// The median of |map − truth| over the pixels `pick` takes, and their count.
fn median_error(map: &DisparityMap, truth: &[f32], pick: impl Fn(usize, usize) -> bool) -> (f32, usize) {
    let mut e: Vec<f32> = (0..W * H).filter(|&i| pick(i % W, i / W) && !map.values()[i].is_nan()).map(|i| (map.values()[i] - truth[i]).abs()).collect();
    e.sort_by(f32::total_cmp);
    (e.get(e.len() / 2).copied().unwrap_or(f32::NAN), e.len())
}

#[test]
fn the_rim_of_a_ball_takes_the_profile_of_a_surface_turning_away() {
    for sign in [1.0, -1.0] {
        let (mut map, truth, mask) = matched_ball(sign);
        let rim = rim_distance(&mask, W, H);
        let before = map.clone();
        let stats = extrapolate_rim(&mut map, &rim, sign as i32);
        let dist = Chamfer::over(&rim, W, 0..W, 0..H);
        let near = |x: usize, y: usize| rim[y * W + x] > 0 && dist.at(x, y) < RIM_PROFILE_PX;
        // The flank the right camera faces (right of the centre) and the top and bottom: the
        // disparity falls along the row or barely changes. For the swapped rig (sign −1) the
        // compressed flank is the right one.
        let faced = |x: usize, y: usize| near(x, y) && dist.at(x, y) < 2.5 && if sign > 0.0 { x > 110 } else { x < 90 };
        let (was, n) = median_error(&before, &truth, faced);
        let (now, _) = median_error(&map, &truth, faced);
        assert!(n > 80, "{n} rim pixels on the faced flank");
        assert!(was > 0.2, "the extrapolated plane's bias: {was}");
        assert!(now < 0.45 * was, "sign {sign}: median |error| {was} → {now} on the faced flank, within 2.5 px");
        // The compressed flank keeps its matched values.
        let compressed = |x: usize, y: usize| near(x, y) && if sign > 0.0 { x < 80 } else { x > 120 } && (y as isize - 100).abs() < 40;
        let kept = (0..W * H).filter(|&i| compressed(i % W, i / W)).all(|i| before.values()[i].to_bits() == map.values()[i].to_bits());
        assert!(kept, "sign {sign}: the compressed flank changed");
        assert!(stats.compressed > 100 && stats.profiled > 300, "{stats:?}");
        assert_eq!(stats.looked, (0..W * H).filter(|&i| near(i % W, i / W)).count());
        // Beyond the rim nothing moves.
        assert!((0..W * H).filter(|&i| dist.at(i % W, i / W) >= RIM_PROFILE_PX).all(|i| before.values()[i].to_bits() == map.values()[i].to_bits()));
    }
}

#[test]
fn a_flat_face_to_its_edge_keeps_its_matched_values() {
    // A plate facing the cameras, its disparity flat but for the noise, and plates leaning
    // back to the right and left (the disparity falling from the middle, 0.02 … 0.2 px a
    // column: a box's faces turned 10° … 55° from the cameras, ending in a crease). The
    // leaning ones bend as much as a ball's rim over the samples' band by the root alone
    // (without the slope's test, 500–650 of their rim pixels were moved, by a median 0.09 …
    // 0.44 px), but not beside a slope: at most one rim pixel in a hundred takes the profile.
    for lean in [0.0f32, 0.02, 0.05, 0.1, 0.2] {
        let mut map = DisparityMap::new(W, H);
        let mut mask = vec![0u8; W * H];
        for y in 40..160 {
            for x in 40..160 {
                mask[y * W + x] = 255;
                map.set(x, y, Some(80.0 - lean * (x as f32 - 100.0).abs() + noise(x, y, 0.05)));
            }
        }
        let rim = rim_distance(&mask, W, H);
        let before = map.clone();
        let stats = extrapolate_rim(&mut map, &rim, 1);
        assert!(stats.looked > 1000);
        assert!(stats.profiled * 100 <= stats.looked, "lean {lean}: {stats:?}");
        if lean == 0.0 {
            assert!(same(&before, &map));
        }
    }
}

#[test]
fn a_map_without_matches_near_the_rim_is_left_alone() {
    let (map, _, mask) = matched_ball(1.0);
    let rim = rim_distance(&mask, W, H);
    // Only the pixels within the rim are matched: no samples to fit.
    let mut only_rim = DisparityMap::new(W, H);
    let dist = Chamfer::over(&rim, W, 0..W, 0..H);
    for i in (0..W * H).filter(|&i| rim[i] > 0 && dist.at(i % W, i / W) < RIM_PROFILE_PX) {
        only_rim.set(i % W, i / W, Some(map.values()[i]));
    }
    let before = only_rim.clone();
    let stats = extrapolate_rim(&mut only_rim, &rim, 1);
    assert_eq!((stats.profiled, stats.compressed), (0, 0));
    assert!(stats.looked > 0);
    assert!(same(&before, &only_rim));
    // No object at all.
    let mut empty = DisparityMap::new(W, H);
    assert_eq!(extrapolate_rim(&mut empty, &vec![0u8; W * H], 1), RimStats::default());
}

#[cfg(target_arch = "x86_64")]
#[test]
fn the_avx2_window_sums_are_the_portable_ones() {
    if !std::is_x86_feature_detected!("avx2") {
        return;
    }
    // Samples of random values, a third of the pixels, over a region with the margins the
    // windows read.
    let (rw, rh) = (2 * RIM_FIT_RADIUS + 1 + LANES + 5, 2 * RIM_FIT_RADIUS + 1 + 4);
    let n = rw * rh;
    let mut smp = Samples { rw, weight: vec![0.0; n], s: vec![0.0; n], d: vec![0.0; n], t: vec![0.0; n], spans: vec![0..rw; rh] };
    for i in 0..n {
        if noise(i, 7, 1.0) > 0.33 {
            let (s, d) = (2.0 + noise(i, 3, 1.0), 20.0 * noise(i, 5, 1.0));
            (smp.weight[i], smp.s[i], smp.d[i], smp.t[i]) = (1.0, s, d, s * s + EDGE_PX as f32);
        }
    }
    let p = Profile { c: [0.3, -0.07, 1.4], along: (0.6, -0.8), bend_var: 0.0, sloped: [0.2, -0.05, 1.1, 0.03], sloped_bend_var: 0.0 };
    for corner in [0, 1, 5, rw + 3, 3 * rw + 4] {
        // SAFETY: the CPU has AVX2 (checked above); the windows lie in the region.
        let (v, r) = unsafe { (avx2::window_lanes(&smp, corner), avx2::residual_lanes(&smp, corner, &p)) };
        let bits = |a: &[f32]| a.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(v.map(|l| bits(&l)), window_lanes(&smp, corner).map(|l| bits(&l)), "corner {corner}");
        assert_eq!(r.map(|l| bits(&l)), residual_lanes(&smp, corner, &p).map(|l| bits(&l)), "corner {corner}");
        // And the sums are the samples' own.
        let sums = window_sums(&smp, corner, false);
        let count = (0..=2 * RIM_FIT_RADIUS).flat_map(|dy| (0..=2 * RIM_FIT_RADIUS).map(move |dx| corner + dy * rw + dx)).filter(|&i| smp.weight[i] != 0.0).count();
        assert_eq!(sums.n, count as f64);
    }
    // And the whole pass: the same map either way.
    let (map, _, mask) = matched_ball(1.0);
    let rim = rim_distance(&mask, W, H);
    let (mut portable, mut lanes) = (map.clone(), map);
    assert_eq!(extrapolate(&mut portable, &rim, 1, false), extrapolate(&mut lanes, &rim, 1, true));
    assert!(same(&portable, &lanes));
}



#[test]
fn objects_cut_by_the_image_edge_and_small_images_are_refined_in_bounds() {
    // The ball moved so that the image's edges cut it, and images smaller than the fit's
    // window: every pixel read lies inside the image, and what moves stays near the truth.
    for (w, h, cx, cy) in [(200usize, 200usize, 20.0, 180.0), (30, 30, 15.0, 15.0), (9, 40, 4.0, 20.0)] {
        let mut map = DisparityMap::new(w, h);
        let mut mask = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let d = ball(x as f64 - cx + 100.0, y as f64 - cy + 100.0, 1.0);
                if !d.is_nan() {
                    mask[y * w + x] = 255;
                    map.set(x, y, Some(d as f32 + noise(x, y, 0.05)));
                }
            }
        }
        let rim = rim_distance(&mask, w, h);
        let before = map.clone();
        let stats = extrapolate_rim(&mut map, &rim, 1);
        assert!(stats.profiled <= stats.looked);
        for i in 0..w * h {
            let (a, b) = (before.values()[i], map.values()[i]);
            assert_eq!(a.is_nan(), b.is_nan());
            assert!(a.is_nan() || (a - b).abs() <= MAX_MOVE_PX as f32, "{w}×{h}: {a} → {b}");
        }
    }
}
