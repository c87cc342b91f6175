use super::*;
use crate::stereo::params::{MatchParams, Method};

/// A random texture (left) and the same texture seen with disparity `disp(x, y)` at each
/// right pixel (right): right pixel x shows left pixel x + disp(x).
fn pair(w: usize, h: usize, disp: impl Fn(usize, usize) -> f32) -> (Vec<u8>, Vec<u8>) {
    let mut state = 0x2545F4914F6CDD1Du64;
    let mut noise = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    // Random values on a grid of 3 px, interpolated bilinearly: a texture without plateaus,
    // which a fractional shift changes.
    let (gw, gh) = ((w + 80) / 3 + 2, h / 3 + 2);
    let grid: Vec<f32> = (0..gw * gh).map(|_| noise()).collect();
    let tex = |x: f32, y: usize| -> u8 {
        let (gx, gy) = (x / 3.0, y as f32 / 3.0);
        let (ix, iy) = (gx.floor() as usize, gy.floor() as usize);
        let (fx, fy) = (gx - ix as f32, gy - iy as f32);
        let at = |i: usize, j: usize| grid[j * gw + i];
        let v = at(ix, iy) * (1.0 - fx) * (1.0 - fy) + at(ix + 1, iy) * fx * (1.0 - fy) + at(ix, iy + 1) * (1.0 - fx) * fy + at(ix + 1, iy + 1) * fx * fy;
        (20.0 + 215.0 * v) as u8
    };
    let mut left = vec![0u8; w * h];
    let mut right = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            left[y * w + x] = tex(x as f32 + 40.0, y);
            right[y * w + x] = tex(x as f32 + 40.0 + disp(x, y), y);
        }
    }
    (left, right)
}

fn params(n: u32) -> ValidMatchParams {
    MatchParams { method: Method::Sgm, num_disparities: n, speckle_window: 0, threads: 1, ..MatchParams::default() }.validate().unwrap()
}

fn run(p: &ValidMatchParams, l: &[u8], r: &[u8], w: usize, h: usize, iv: &DisparityIntervals) -> (DisparityMap, MatchStats) {
    let mut out = DisparityMap::new(w, h);
    let shift = grid::shift(iv, p.min_disparity, p.max_disparity());
    let stats = Sgm::default().compute(p, GrayView::new(w, h, l).unwrap(), GrayView::new(w, h, r).unwrap(), &level_map(l, r), shift, iv, 0..h, &mut out).unwrap();
    (out, stats)
}

#[test]
fn recovers_a_slanted_texture() {
    let (w, h) = (120, 60);
    let (l, r) = pair(w, h, |x, _| 6.0 + x as f32 * 0.05);
    // Right pixel x_r shows left pixel x_r + d(x_r): left pixel x has d = (6 + 0.05 x) / 1.05.
    let truth = |x: usize, _y: usize| (6.0 + x as f32 * 0.05) / 1.05;
    let p = params(32);
    let (out, stats) = run(&p, &l, &r, w, h, &DisparityIntervals::full(w, h, 0, 31));
    let (mut good, mut total) = (0, 0);
    for y in 4..h - 4 {
        for x in 30..w - 5 {
            total += 1;
            let d = out.values()[y * w + x];
            good += (!d.is_nan() && (d - truth(x, y)).abs() <= 0.5) as usize;
        }
    }
    assert!(good * 100 >= total * 95, "{good} of {total} within 0.5 px");
    assert_eq!(stats.searched, w * h);
}

/// The intensity term compares levels only after the right image is matched to the left's:
/// a right camera at 0.8 × the gain and 15 levels of offset matches as well as an equal one.
#[test]
fn a_brighter_right_camera_matches_as_well() {
    let (w, h) = (120, 60);
    let (l, r) = pair(w, h, |x, y| 5.0 + ((x / 30 + y / 20) % 3) as f32 * 4.0);
    let bright: Vec<u8> = r.iter().map(|&v| (0.8 * v as f32 + 15.0).round() as u8).collect();
    let p = params(32);
    let iv = DisparityIntervals::full(w, h, 0, 31);
    let correct = |m: &DisparityMap| {
        let (same, _) = run(&p, &l, &r, w, h, &iv);
        m.values().iter().zip(same.values()).filter(|(a, b)| !a.is_nan() && !b.is_nan() && (*a - *b).abs() <= 0.5).count()
    };
    let (equal, _) = run(&p, &l, &r, w, h, &iv);
    let (brighter, _) = run(&p, &l, &bright, w, h, &iv);
    let (a, b) = (correct(&equal), correct(&brighter));
    assert!(b * 100 >= a * 98, "{b} of {a} pixels as with equal cameras");
}

/// The median distance, px, of a matcher's disparities from the truth on a slanted texture
/// (disparity 6 + 0.05 x at the right pixel), over the inner pixels; at least nine in ten of
/// them matched.
fn slant_median_error(p: MatchParams) -> f32 {
    let (w, h) = (160, 60);
    let (l, r) = pair(w, h, |x, _| 6.0 + x as f32 * 0.05);
    let truth = |x: usize| (6.0 + x as f32 * 0.05) / 1.05;
    let mut m = crate::stereo::StereoMatcher::new(p.validate().unwrap());
    let iv = m.full_intervals(w, h, None);
    let mut out = DisparityMap::new(w, h);
    m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
    let mut e: Vec<f32> = (5..h - 5).flat_map(|y| (30..w - 10).map(move |x| (x, y))).filter_map(|(x, y)| out.get(x, y).map(|d| (d - truth(x)).abs())).collect();
    assert!(e.len() > (h - 10) * (w - 40) * 9 / 10, "{} matched", e.len());
    e.sort_by(f32::total_cmp);
    e[e.len() / 2]
}

/// SGM's sums step along a slanted surface; the matcher takes the sub-pixel disparity from
/// the correlation cost around SGM's winner instead (`refine_subpixel`).
#[test]
fn slanted_surfaces_get_the_correlation_s_sub_pixel_precision() {
    let median_error = |sgm_refine: bool| slant_median_error(MatchParams { threads: 1, sgm_refine, ..(*params(32)).clone() });
    let (sgm, refined) = (median_error(false), median_error(true));
    assert!(refined < 0.07 && refined < 0.6 * sgm, "median error {refined:.3} px refined, {sgm:.3} px from SGM's sums");
}

/// SGM's refined disparity blends the correlation's sub-pixel value with SGM's own, and is
/// closer to the truth than the correlation's alone (the `bm` matcher, same window): on
/// this slanted texture, the median error is 0.043 px refined against 0.049 px for `bm`;
/// with the correlation's value alone the two are equal, and the test fails.
#[test]
fn the_blended_sub_pixel_value_beats_the_correlation_alone() {
    let refined = slant_median_error(MatchParams { threads: 1, ..(*params(32)).clone() });
    let bm = slant_median_error(MatchParams { num_disparities: 32, threads: 1, ..MatchParams::default() });
    assert!(refined < bm, "median error {refined:.4} px refined, {bm:.4} px for the correlation alone");
}

/// Intervals in wide patches, 37 × 5 pixels: side by side, patches of one width (so one
/// band width) at other disparities, and a hole about every 41 pixels of a row — runs longer
/// than the sixteen pixels the run and cost loops check at once, ending at band changes,
/// holes and slots that held another band two rows up.
fn wide_patches(w: usize, h: usize) -> DisparityIntervals {
    let mut wide = DisparityIntervals::empty(w, h);
    wide.searched = None;
    for y in 0..h {
        for x in 0..w {
            if (x + 3 * y) % 41 != 0 {
                let lo = ((x / 37 * 17 + y / 5 * 5) % 60) as i16;
                (wide.lo[y * w + x], wide.hi[y * w + x]) = (lo, lo + [3, 20, 40][y / 5 % 3]);
            }
        }
    }
    wide
}

/// Pass one cuts each row into runs of one band for the costs: every pixel gets the costs of
/// its own band, whatever runs it was cut into.
#[test]
fn every_pixel_is_costed_over_its_own_band() {
    let (w, h) = (90, 40);
    let (l, r) = pair(w, h, |x, y| 4.0 + ((x / 20 + y / 10) % 3) as f32 * 5.0);
    let p = params(128);
    let mut sgm = Sgm::default();
    let mut out = DisparityMap::new(w, h);
    sgm.compute_impl::<false>(&p, GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &level_map(&l, &r), 0, &wide_patches(w, h), 0..h, &mut out).unwrap();
    let (n, dmin) = (128, p.min_disparity);
    let pad_l = (dmin + n - 1).max(0) as usize;
    let wr = sgm.census_r.len() / h;
    let mut costed = 0;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (a, m) = (sgm.band_a[i] as usize, sgm.band_m[i] as usize);
            if m == 0 {
                continue;
            }
            let px = census::Pixel { cl: sgm.census_l[i], il: l[i], cr_row: &sgm.census_r[y * wr..][..wr], ir_row: &sgm.levels_r[y * wr..][..wr], cap: p.sgm_ad_cap };
            let mut want = vec![0u8; m];
            census::costs(px, (x as i32 + pad_l as i32 - dmin - a as i32) as usize, &mut want);
            assert_eq!(&sgm.cost[sgm.off[i]..][..m], &want[..], "pixel ({x}, {y}), band {a} + {m}");
            costed += 1;
        }
    }
    assert!(costed > w * h / 2, "{costed}");
}

/// The map of [`run`] (AVX2 where the CPU has it) and of the portable code on `iv`, on the
/// same grid of blocks, bit for bit, with more than a fifth of the pixels matched; `what`
/// names the case.
fn assert_portable_agrees(p: &ValidMatchParams, l: &[u8], r: &[u8], w: usize, h: usize, iv: &DisparityIntervals, what: &str) {
    let (fast, _) = run(p, l, r, w, h, iv);
    let mut portable = DisparityMap::new(w, h);
    Sgm::default().compute_impl::<false>(p, GrayView::new(w, h, l).unwrap(), GrayView::new(w, h, r).unwrap(), &level_map(l, r), grid::shift(iv, p.min_disparity, p.max_disparity()), iv, 0..h, &mut portable).unwrap();
    assert!(fast.values().iter().zip(portable.values()).all(|(a, b)| a.to_bits() == b.to_bits()), "{what}");
    assert!(fast.valid_count() * 5 > w * h, "{what}: {} matched", fast.valid_count());
}

#[test]
fn the_portable_build_gives_the_same_map() {
    let (w, h) = (90, 40);
    let (l, r) = pair(w, h, |x, y| 4.0 + ((x / 20 + y / 10) % 3) as f32 * 5.0);
    // The full range; and patches of 7 × 3 pixels with one interval each — runs of equal
    // bands of one to eight blocks of disparities, band changes and holes between them.
    let full = DisparityIntervals::full(w, h, 0, 39);
    let mut patches = DisparityIntervals::empty(w, h);
    patches.searched = None;
    for y in 0..h {
        for x in 0..w {
            let k = ((x / 7) * 31 + (y / 3) * 17) % 23;
            if k != 5 {
                let (lo, width) = ((k * 13 % 60) as i16, [1, 5, 16, 17, 40, 70, 100, 127][k % 8]);
                (patches.lo[y * w + x], patches.hi[y * w + x]) = (lo, (lo + width).min(127));
            }
        }
    }
    let wide = wide_patches(w, h);
    for (iv, range, what) in [(&full, 40, "full range"), (&patches, 128, "patches"), (&wide, 128, "wide patches")] {
        // (Uniqueness 15 and 0, SGM's default: without the test the fits run in the lanes.)
        for (paths, uniqueness_ratio) in [(4, 15), (5, 15), (8, 15), (4, 0), (5, 0), (8, 0)] {
            let p = MatchParams { sgm_paths: paths, uniqueness_ratio, ..(*params(range)).clone() }.validate().unwrap();
            assert_portable_agrees(&p, &l, &r, w, h, iv, &format!("{what}, {paths} paths, uniqueness {uniqueness_ratio}"));
        }
    }
    // Narrow intervals across 16, on a moved grid of blocks ([`grid::shift`]).
    let truth = |x: usize, y: usize| 14.0 + ((x / 20 + y / 10) % 3) as f32 * 1.5;
    let (l, r) = pair(w, h, truth);
    let mut moved = DisparityIntervals::empty(w, h);
    moved.searched = None;
    for y in 0..h {
        for x in 0..w {
            let t = truth(x, y) as i16;
            (moved.lo[y * w + x], moved.hi[y * w + x]) = (t - 3, t + 3);
        }
    }
    let p = params(40);
    assert_eq!(grid::shift(&moved, p.min_disparity, p.max_disparity()), 5);
    for paths in [4, 5, 8] {
        let p = MatchParams { sgm_paths: paths, ..(*p).clone() }.validate().unwrap();
        assert_portable_agrees(&p, &l, &r, w, h, &moved, &format!("moved grid, {paths} paths"));
    }
}

#[test]
fn narrow_intervals_are_searched_and_nothing_else() {
    let (w, h) = (100, 50);
    // Two bands of rows at different depths: the same disparity for left and right pixels.
    let truth = |_x: usize, y: usize| if y < 25 { 9.0 } else { 27.0 };
    let (l, r) = pair(w, h, truth);
    let p = params(64);
    let mut iv = DisparityIntervals::empty(w, h);
    iv.searched = None;
    for y in 0..h {
        for x in 0..w {
            // A hole in the middle searches nothing; elsewhere ±3 around the truth.
            if !(40..60).contains(&x) {
                let t = truth(x, y) as i16;
                iv.lo[y * w + x] = t - 3;
                iv.hi[y * w + x] = t + 3;
            }
        }
    }
    let (out, stats) = run(&p, &l, &r, w, h, &iv);
    let (full, full_stats) = run(&p, &l, &r, w, h, &DisparityIntervals::full(w, h, 0, 63));
    let (mut good, mut good_full, mut total) = (0, 0, 0);
    for y in 0..h {
        for x in 0..w {
            let d = out.values()[y * w + x];
            let t = truth(x, y);
            if (40..60).contains(&x) {
                assert!(d.is_nan(), "({x}, {y}) searched nothing but got {d}");
                continue;
            }
            if !d.is_nan() {
                assert!((t - 3.5..=t + 3.5).contains(&d), "({x}, {y}): {d} outside its interval around {t}");
            }
            if x >= 30 {
                total += 1;
                good += ((d - t).abs() <= 1.0) as usize;
                good_full += ((full.values()[y * w + x] - t).abs() <= 1.0) as usize;
            }
        }
    }
    // Narrow intervals around the truth match at least as well as the full range.
    assert!(good * 10 >= total * 9 && good >= good_full, "within 1 px: {good} narrow, {good_full} full, of {total}");
    // Work in whole blocks of 16 around each interval: at most two blocks per pixel here,
    // against four at the full range.
    // Searched: outside the hole, where some disparity of the interval has a right pixel.
    let reachable = (0..h).map(|y| (0..w).filter(|&x| !(40..60).contains(&x) && x as f32 >= truth(x, y) - 3.0).count()).sum::<usize>();
    assert_eq!(stats.searched, reachable);
    assert!(stats.evaluated <= (stats.searched * 2 * LANES) as u64);
    assert_eq!(stats.evaluated % LANES as u64, 0);
    assert!(stats.evaluated * 2 <= full_stats.evaluated);
}

/// An assisted frame's intervals gather about the object's disparity. Where that lies on a
/// multiple of 16, the plain grid of blocks gives every pixel two; the call's grid moves so
/// that one block holds each interval ([`grid::shift`]), and the map is as good.
#[test]
fn intervals_across_a_multiple_of_16_take_one_block_on_a_moved_grid() {
    let (w, h) = (100, 40);
    let truth = |_x: usize, y: usize| 31.25 + 0.5 * (y % 2) as f32;
    let (l, r) = pair(w, h, truth);
    let p = params(64);
    let mut iv = DisparityIntervals::empty(w, h);
    iv.searched = None;
    iv.lo.fill(28);
    iv.hi.fill(35);
    assert_eq!(grid::shift(&iv, p.min_disparity, p.max_disparity()), 4);
    let (out, stats) = run(&p, &l, &r, w, h, &iv);
    // One block per searched pixel (every pixel from x = 28 on, where the interval has right
    // pixels).
    assert_eq!(stats.searched, (w - 28) * h);
    assert_eq!(stats.evaluated, (stats.searched * LANES) as u64);
    let (full, _) = run(&p, &l, &r, w, h, &DisparityIntervals::full(w, h, 0, 63));
    let (mut good, mut good_full, mut total) = (0, 0, 0);
    for y in 0..h {
        for x in 40..w {
            let t = truth(x, y);
            total += 1;
            good += ((out.values()[y * w + x] - t).abs() <= 0.5) as usize;
            good_full += ((full.values()[y * w + x] - t).abs() <= 0.5) as usize;
        }
    }
    assert!(good * 10 >= total * 9 && good >= good_full, "within 0.5 px: {good} on the moved grid, {good_full} at full range, of {total}");
}

#[test]
fn stripes_on_threads_give_the_one_thread_map_but_at_their_seams() {
    let (w, h) = (80, 300);
    let (l, r) = pair(w, h, |x, y| 5.0 + (x + y) as f32 * 0.02);
    // (Both the two passes and the single pass of five paths keep only their stripe's rows.)
    for sgm_paths in [4, 5] {
        let run_with = |threads: usize| {
            let p = MatchParams { threads, sgm_paths, ..(*params(32)).clone() }.validate().unwrap();
            let mut m = crate::stereo::StereoMatcher::new(p);
            let iv = m.full_intervals(w, h, None);
            let mut out = DisparityMap::new(w, h);
            let stats = m.compute(GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &iv, &mut out).unwrap();
            (out, stats)
        };
        let (one, s1) = run_with(1);
        let (three, s3) = run_with(3);
        assert_eq!((s1.searched, s1.evaluated), (s3.searched, s3.evaluated), "{sgm_paths} paths");
        let same = one.values().iter().zip(three.values()).filter(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())).count();
        assert!(same * 100 >= w * h * 97, "{sgm_paths} paths: {same} of {} pixels as with one thread", w * h);
        assert!(three.valid_count() * 10 >= w * h * 9, "{sgm_paths} paths");
    }
}

#[test]
fn negative_disparities_are_found_too() {
    // A rig whose right camera ends up left of the left one: left pixel x is right pixel x + 8.
    let (w, h) = (100, 40);
    let (l, r) = pair(w, h, |_, _| -8.0);
    let p = MatchParams { min_disparity: -31, ..(*params(32)).clone() }.validate().unwrap();
    let (out, stats) = run(&p, &l, &r, w, h, &DisparityIntervals::full(w, h, -31, 0));
    let good = (4..h - 4).flat_map(|y| (0..w - 12).map(move |x| (x, y))).filter(|&(x, y)| (out.values()[y * w + x] + 8.0).abs() <= 0.5).count();
    assert!(good * 100 >= (w - 12) * (h - 8) * 95, "{good} within 0.5 px of −8");
    // Every pixel has a right pixel at d = 0; near the right border fewer disparities.
    assert_eq!(stats.searched, w * h);
    assert!(stats.evaluated < (w * h * 32) as u64);
}

/// A matcher reused after a call on another pair reads nothing that call left in its right
/// rows (nor anything else they held), which are written over the columns the bands reach
/// alone ([`census::RightRows`]):
/// its sums and map are a fresh matcher's, for narrow intervals inside the image, near its
/// left edge (bands reaching into the left padding) and, with negative disparities, near its
/// right edge; AVX2 and portable. (It fails when the reach leaves out a band's last or first
/// disparity.)
#[test]
fn a_reused_matcher_reads_only_the_right_columns_its_call_wrote() {
    let (w, h) = (90, 40);
    let (l, r) = pair(w, h, |x, y| 6.0 + ((x / 20 + y / 10) % 3) as f32 * 2.0);
    let (other_l, other_r): (Vec<u8>, Vec<u8>) = (r.iter().map(|v| 255 - v).collect(), l.iter().map(|v| 255 - v).collect());
    let within = |at: &dyn Fn(usize, usize) -> Option<(i32, i32)>| {
        let mut iv = DisparityIntervals::empty(w, h);
        for y in 0..h {
            for x in 0..w {
                iv.set(x, y, at(x, y));
            }
        }
        iv
    };
    let middle = within(&|x, _| (30..80).contains(&x).then_some((5, 13)));
    let left_edge = within(&|x, _| (x < 25).then_some((4, 12)));
    let right_edge = within(&|x, _| (x >= 60).then_some((-14, -6)));
    let (l_neg, r_neg) = pair(w, h, |_, _| -9.0);
    let negative = MatchParams { min_disparity: -40, ..(*params(48)).clone() }.validate().unwrap();
    for (p, (l, r), iv, what) in [(params(48), (&l, &r), &middle, "the middle"), (params(48), (&l, &r), &left_edge, "the left edge"), (negative, (&l_neg, &r_neg), &right_edge, "the right edge")] {
        let full = DisparityIntervals::full(w, h, p.min_disparity, p.max_disparity());
        for avx2 in [false, true] {
            let call = |sgm: &mut Sgm, (l, r): (&[u8], &[u8]), iv: &DisparityIntervals| {
                let mut out = DisparityMap::new(w, h);
                let (lv, rv, levels, shift) = (GrayView::new(w, h, l).unwrap(), GrayView::new(w, h, r).unwrap(), level_map(l, r), grid::shift(iv, p.min_disparity, p.max_disparity()));
                #[cfg(target_arch = "x86_64")]
                if avx2 && std::is_x86_feature_detected!("avx2") {
                    sgm.compute(&p, lv, rv, &levels, shift, iv, 0..h, &mut out).unwrap();
                    return out;
                }
                sgm.compute_impl::<false>(&p, lv, rv, &levels, shift, iv, 0..h, &mut out).unwrap();
                out
            };
            let mut fresh = Sgm::default();
            let want = call(&mut fresh, (l, r), iv);
            let mut reused = Sgm::default();
            call(&mut reused, (&other_l, &other_r), &full);
            // And whatever the rows held before, not what a fresh matcher's zeros would give.
            reused.census_r_lo.fill(0x5a5a_5a5a);
            reused.census_r_hi.fill(0x3);
            reused.census_r.fill(0x2_5a5a_5a5a);
            reused.levels_r.fill(77);
            let got = call(&mut reused, (l, r), iv);
            let sums = fresh.off[w * h];
            assert!(got.valid_count() * 4 > iv.lo.iter().zip(&iv.hi).filter(|(a, b)| a <= b).count(), "{what}: {} matched", got.valid_count());
            assert!(reused.sum[..sums] == fresh.sum[..sums], "{what}, AVX2 {avx2}: the sums differ");
            assert!(got.values().iter().zip(want.values()).all(|(a, b)| a.to_bits() == b.to_bits()), "{what}, AVX2 {avx2}: the maps differ");
        }
    }
}

/// Pixels whose interval is empty once clipped to the image (the first columns when the
/// range starts above zero; intervals entirely past the right image's edge, negative
/// disparities) search nothing and stay unmatched — without overflowing on the way (debug
/// builds check the arithmetic).
#[test]
fn intervals_emptied_by_the_image_border_search_nothing() {
    let (w, h) = (64, 20);
    let (l, r) = pair(w, h, |_, _| 12.0);
    let p = MatchParams { method: Method::Sgm, min_disparity: 20, num_disparities: 32, speckle_window: 0, threads: 1, ..MatchParams::default() }.validate().unwrap();
    let (out, stats) = run(&p, &l, &r, w, h, &DisparityIntervals::full(w, h, 20, 51));
    for y in 0..h {
        for x in 0..20 {
            assert!(out.get(x, y).is_none(), "({x}, {y}) has no right pixel in range");
        }
    }
    assert_eq!(stats.searched, (w - 20) * h);
    // Negative disparities: the interval −40 … −30 leaves the image for x > w − 31.
    let p = MatchParams { method: Method::Sgm, min_disparity: -63, num_disparities: 64, speckle_window: 0, threads: 1, ..MatchParams::default() }.validate().unwrap();
    let (out, stats) = run(&p, &l, &r, w, h, &DisparityIntervals::full(w, h, -40, -30));
    for y in 0..h {
        for x in w - 30..w {
            assert!(out.get(x, y).is_none(), "({x}, {y}) has no right pixel in range");
        }
    }
    assert_eq!(stats.searched, (w - 30) * h);
}

/// The vector costs (the words split into 32 and 2 bits, a run of pixels at once; the bits
/// counted by nibble tables, and by `vpopcntd` where the CPU has it) are the portable ones,
/// over words that use all 34 bits.
#[cfg(target_arch = "x86_64")]
#[test]
fn the_vector_costs_are_the_portable_ones() {
    if !std::is_x86_feature_detected!("avx2") {
        return;
    }
    let mut next = crate::testing::xorshift(0x2545_f491_4f6c_dd1d);
    let bits = (1u64 << (census::CENSUS_W * census::CENSUS_H - 1)) - 1;
    let cr: Vec<u64> = (0..80).map(|_| next() & bits).collect();
    let levels: Vec<u8> = (0..80).map(|_| next() as u8).collect();
    let (mut cr_lo, mut cr_hi) = (vec![0; cr.len()], vec![0; cr.len()]);
    census::split(&cr, &mut cr_lo, &mut cr_hi);
    // (first right word of the run's first pixel, disparities, pixels)
    for (start, m, len) in [(15, 16, 1), (47, 32, 3), (60, 48, 20), (31, 16, 49)] {
        let cl: Vec<u64> = (0..len).map(|_| next() & bits).collect();
        let il: Vec<u8> = (0..len).map(|_| next() as u8).collect();
        let cap = (next() % 101) as u8;
        let mut want = vec![0u8; len * m];
        for (k, out) in want.chunks_exact_mut(m).enumerate() {
            census::costs(census::Pixel { cl: cl[k], il: il[k], cr_row: &cr, ir_row: &levels, cap }, start + k, out);
        }
        let run = || census::Run { cl: &cl, il: &il, cr_lo: &cr_lo, cr_hi: &cr_hi, ir_row: &levels, cap };
        let mut got = vec![0u8; len * m];
        // SAFETY: AVX2 checked above; the words start + 1 − m ..= start + len − 1 exist.
        unsafe { super::simd::costs_avx2(run(), start, m, &mut got) };
        assert_eq!(got, want, "nibble tables: start {start}, {m} disparities, {len} pixels");
        if super::simd::has_vpopcnt() {
            let mut got = vec![0u8; len * m];
            // SAFETY: as above, and the CPU counts bits in vector lanes (checked).
            unsafe { super::simd::costs_vpopcnt(run(), start, m, &mut got) };
            assert_eq!(got, want, "vpopcntd: start {start}, {m} disparities, {len} pixels");
        }
    }
}

#[test]
#[cfg(target_arch = "x86_64")]
fn the_vector_census_planes_are_the_portable_ones() {
    if !std::is_x86_feature_detected!("avx2") {
        return;
    }
    let mut next = crate::testing::xorshift(0x1234_5678_9abc_def1);
    let rows = census::CENSUS_H;
    // Widths below, at and past one register of 32 pixels, with a tail; levels drawn from a
    // few values so that equal neighbours (not below the centre) are common, and from both
    // halves of the byte (the unsigned compare).
    for w in [1, 5, 31, 32, 33, 64, 70, 97] {
        let wp = w + census::CENSUS_W - 1;
        for _ in 0..20 {
            let padded: Vec<u8> = (0..wp * rows).map(|_| [0u8, 1, 127, 128, 129, 254, 255, 64][(next() % 8) as usize]).collect();
            let (mut want, mut got) = (vec![0xaa; 5 * w], vec![0x55; 5 * w]);
            census::planes_row(&padded, w, &mut want);
            // SAFETY: AVX2 checked above; the rows and planes have the documented sizes.
            unsafe { super::simd::planes(&padded, w, &mut got) };
            assert_eq!(got, want, "width {w}");
        }
    }
}

/// Pass one folds each cost into the word above its two paths' sum where the penalties and
/// the cost's cap let them fit (`folds`): at the largest P2 that folds and the first that
/// does not, on a right image unrelated to the left (high costs, so path values near
/// C + P2), the AVX2 build gives the portable map, which keeps the cost volume.
#[test]
#[cfg(target_arch = "x86_64")]
fn folded_sums_hold_the_largest_path_values() {
    let (w, h) = (90, 40);
    let (l, _) = pair(w, h, |_, _| 0.0);
    let r: Vec<u8> = l.iter().rev().copied().collect();
    // 2 · (C_max + P2) < 2⁹ with C_max = 34 census bits + the default cap of 25.
    let largest = 255 - (census::MAX_BITS as u16 + 25);
    for (p2, folded) in [(largest, true), (largest + 1, false)] {
        for iv in [DisparityIntervals::full(w, h, 0, 63), wide_patches(w, h)] {
            let p = MatchParams { p2, ..(*params(64)).clone() }.validate().unwrap();
            assert_eq!(folds(&p), folded, "P2 {p2}");
            let (fast, _) = run(&p, &l, &r, w, h, &iv);
            let mut portable = DisparityMap::new(w, h);
            Sgm::default().compute_impl::<false>(&p, GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), &level_map(&l, &r), grid::shift(&iv, p.min_disparity, p.max_disparity()), &iv, 0..h, &mut portable).unwrap();
            assert!(fast.values().iter().zip(portable.values()).all(|(a, b)| a.to_bits() == b.to_bits()), "P2 {p2}");
        }
    }
}

/// The single pass (`sgm_paths = 5`) keeps one row of sums; after a call they are the last
/// row's. Written out from the recurrence, pair by pair, the five paths from the left, the
/// right, the upper left, above and the upper right sum to them — in the portable build and,
/// where the CPU has it, the AVX2 one. One block of sixteen disparities, so every pixel's band
/// is the same and the recurrence needs no bands.
#[test]
fn one_pass_sums_are_the_five_paths_of_the_recurrence() {
    let (w, h) = (50, 12);
    let (l, r) = pair(w, h, |x, y| 3.0 + ((x / 9 + y / 4) % 3) as f32 * 4.0);
    let p = MatchParams { sgm_paths: 5, ..(*params(16)).clone() }.validate().unwrap();
    let (n, pad_l) = (LANES, LANES - 1);
    let (lv, rv, levels) = (GrayView::new(w, h, &l).unwrap(), GrayView::new(w, h, &r).unwrap(), level_map(&l, &r));
    let mut sgm = Sgm::default();
    let mut out = DisparityMap::new(w, h);
    sgm.compute_impl::<false>(&p, lv, rv, &levels, 0, &DisparityIntervals::full(w, h, 0, 15), 0..h, &mut out).unwrap();
    let wr = sgm.census_r.len() / h;
    let cost = |x: usize, y: usize| {
        let px = census::Pixel { cl: sgm.census_l[y * w + x], il: l[y * w + x], cr_row: &sgm.census_r[y * wr..][..wr], ir_row: &sgm.levels_r[y * wr..][..wr], cap: p.sgm_ad_cap };
        let mut c = vec![0u8; n];
        census::costs(px, x + pad_l, &mut c);
        c.into_iter().map(u32::from).collect::<Vec<u32>>()
    };
    let costs: Vec<Vec<u32>> = (0..w * h).map(|i| cost(i % w, i / w)).collect();
    let (p1, p2) = (p.p1 as u32, p.p2 as u32);
    let mut want = vec![0u32; w * n];
    for (dx, dy) in [(1i32, 0i32), (-1, 0), (1, 1), (0, 1), (-1, 1)] {
        // Pixels in the path's order: rows down, and along each row away from the path's source.
        let mut path = vec![vec![0u32; n]; w * h];
        for y in 0..h {
            let xs: Vec<usize> = if dx < 0 { (0..w).rev().collect() } else { (0..w).collect() };
            for x in xs {
                let (qx, qy) = (x as i32 - dx, y as i32 - dy);
                let c = &costs[y * w + x];
                let v: Vec<u32> = if qx < 0 || qx >= w as i32 || qy < 0 {
                    c.clone()
                } else {
                    let q = &path[qy as usize * w + qx as usize];
                    let mn = *q.iter().min().unwrap();
                    (0..n).map(|k| {
                        let near = [k.checked_sub(1), (k + 1 < n).then_some(k + 1)].into_iter().flatten().map(|j| q[j] + p1).min().unwrap();
                        c[k] + q[k].min(near).min(mn + p2) - mn
                    }).collect()
                };
                path[y * w + x] = v;
            }
        }
        for x in 0..w {
            for k in 0..n {
                want[x * n + k] += path[(h - 1) * w + x][k];
            }
        }
    }
    let got = |sgm: &Sgm| sgm.sum[..w * n].iter().map(|&v| v as u32).collect::<Vec<u32>>();
    assert_eq!(got(&sgm), want, "portable");
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("popcnt") {
        let mut fast = Sgm::default();
        // SAFETY: the CPU has AVX2 and POPCNT, checked just above.
        unsafe { fast.compute_avx2(&p, lv, rv, &levels, 0, &DisparityIntervals::full(w, h, 0, 15), 0..h, &mut out) }.unwrap();
        assert_eq!(got(&fast), want, "AVX2");
    }
}

/// The left words over the rows' searched columns are the whole image's there — their
/// windows read the pixels beyond those columns and are clamped at the image's border
/// as the whole image's are — in the portable comparisons and the AVX2 ones (whose rows
/// narrower than 32 columns go one by one), and nothing is written outside them. (It
/// fails when the columns' window is padded by replication inside the image.)
#[test]
fn the_searched_columns_census_is_the_whole_images_there() {
    let (w, h) = (90, 9);
    let img: Vec<u8> = (0..w * h).map(|i| ((i * 89 + i / w * 37) % 251) as u8).collect();
    let mut whole = Vec::new();
    census::transform_into(&img, w, h, (0, 0), &mut Vec::new(), census::planes_row, &mut whole);
    #[cfg(target_arch = "x86_64")]
    let avx2 = std::is_x86_feature_detected!("avx2");
    #[cfg(not(target_arch = "x86_64"))]
    let avx2 = false;
    for (first, last) in [(0, 89), (0, 0), (1, 5), (2, 40), (30, 70), (50, 89), (86, 89), (45, 45)] {
        // The union of the rows' spans: one row from `first`, another to `last`, one
        // empty.
        let spans: Vec<std::ops::Range<usize>> = (0..h).map(|y| match y % 3 { 0 => first..first + 1, 1 => last..last + 1, _ => 0..0 }).collect();
        for vector in [false, true].into_iter().filter(|&v| !v || avx2) {
            let mut words = vec![u64::MAX; w * h];
            let planes_of = |rows: &[u8], w: usize, planes: &mut [u8]| {
                #[cfg(target_arch = "x86_64")]
                if vector {
                    // SAFETY: the CPU has AVX2 (checked above); `transform_cols` passes
                    // the window's rows and five planes of `w`.
                    return unsafe { simd::planes(rows, w, planes) };
                }
                census::planes_row(rows, w, planes)
            };
            census::transform_spans_into(&img, w, h, &spans, &mut Vec::new(), planes_of, &mut words);
            for (i, (&got, &want)) in words.iter().zip(&whole).enumerate() {
                let x = i % w;
                let expect = if (first..=last).contains(&x) { want } else { u64::MAX };
                assert_eq!(got, expect, "columns {first}…{last}, pixel ({x}, {}), AVX2 {vector}", i / w);
            }
        }
    }
    // Nothing searched: nothing written.
    let mut words = vec![7u64; w * h];
    census::transform_spans_into(&img, w, h, &vec![0..0; h], &mut Vec::new(), census::planes_row, &mut words);
    assert!(words.iter().all(|&v| v == 7));
}
