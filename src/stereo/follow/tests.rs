//! The refinement's tests: synthetic pairs of a textured surface whose disparity is known.

use super::*;

/// A band-limited texture, smooth enough to be sampled between pixels.
fn texture(u: f64, v: f64) -> f64 {
    let waves = [(0.31, 0.07, 0.3, 30.0), (-0.12, 0.27, 1.1, 25.0), (0.19, -0.21, 2.0, 20.0), (0.45, 0.33, 0.7, 12.0), (-0.37, 0.15, 2.9, 12.0)];
    128.0 + waves.iter().map(|&(a, b, p, amp)| amp * (a * u + b * v + p).sin()).sum::<f64>()
}

/// A rectified pair of the texture painted on a surface whose disparity is `disp(x, y)`
/// (NaN: the background, a flat grey on both images), `w × h`.
fn pair(w: usize, h: usize, disp: &dyn Fn(f64, f64) -> f64) -> (Vec<u8>, Vec<u8>) {
    pair_on(w, h, disp, 100)
}

/// [`pair`] with the background a flat `grey`.
fn pair_on(w: usize, h: usize, disp: &dyn Fn(f64, f64) -> f64, grey: u8) -> (Vec<u8>, Vec<u8>) {
    pair_of(w, h, disp, grey, &texture)
}

/// [`pair_on`] with the surface painted by `paint` (grey levels at a surface point).
fn pair_of(w: usize, h: usize, disp: &dyn Fn(f64, f64) -> f64, grey: u8, paint: &dyn Fn(f64, f64) -> f64) -> (Vec<u8>, Vec<u8>) {
    let mut left = vec![grey; w * h];
    let mut right = vec![grey; w * h];
    for y in 0..h {
        for x in 0..w {
            let (xf, yf) = (x as f64, y as f64);
            if !disp(xf, yf).is_nan() {
                left[y * w + x] = paint(xf, yf).round() as u8;
            }
            // The left column this right pixel sees: x_l − d(x_l) = x_r, by fixed point.
            let mut xl = xf + 20.0;
            for _ in 0..30 {
                let d = disp(xl, yf);
                if d.is_nan() {
                    break;
                }
                xl = xf + d;
            }
            if !disp(xl, yf).is_nan() {
                right[y * w + x] = paint(xl, yf).round() as u8;
            }
        }
    }
    (left, right)
}

/// A window's mean of the true map (what a block matcher reports on a curved surface),
/// `side` wide, over the matched pixels.
fn window_mean(truth: &[f32], w: usize, h: usize, side: usize) -> Vec<f32> {
    let r = side as isize / 2;
    (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as isize, (i / w) as isize);
            if truth[i].is_nan() {
                return f32::NAN;
            }
            let (mut s, mut n) = (0.0, 0.0);
            for dy in -r..=r {
                for dx in -r..=r {
                    let (xx, yy) = (x + dx, y + dy);
                    if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        let v = truth[yy as usize * w + xx as usize];
                        if !v.is_nan() {
                            s += v;
                            n += 1.0;
                        }
                    }
                }
            }
            s / n
        })
        .collect()
}

/// A dome towards the camera over the ellipse of centre `c` and semi-axes `r`: `rim` px
/// of disparity at its edge, `rim + rise` at its top; NaN outside.
fn dome(c: (f64, f64), r: (f64, f64), rim: f64, rise: f64) -> impl Fn(f64, f64) -> f64 {
    move |x, y| {
        let q = ((x - c.0) / r.0).powi(2) + ((y - c.1) / r.1).powi(2);
        if q < 1.0 { rim + rise * (1.0 - q).sqrt() } else { f64::NAN }
    }
}

/// `disp` at every pixel of a `w × h` map.
fn sampled(w: usize, h: usize, disp: &dyn Fn(f64, f64) -> f64) -> Vec<f32> {
    (0..w * h).map(|i| disp((i % w) as f64, (i / w) as f64) as f32).collect()
}

/// The map a block matcher gives of `truth`: the window's mean (11 px, the prefilter's
/// Sobel around a 9 px block).
fn as_matched(truth: &[f32], w: usize, h: usize) -> DisparityMap {
    let mut map = DisparityMap::new(w, h);
    map.values_mut().copy_from_slice(&window_mean(truth, w, h, 11));
    map
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

#[test]
fn a_bulge_is_no_longer_flattened_by_the_window() {
    // A dome towards the camera: 16 px of disparity at its rim, 26 at its top.
    let (w, h) = (160, 120);
    let dome = dome((80.0, 60.0), (55.0, 45.0), 16.0, 10.0);
    let (left, right) = pair(w, h, &dome);
    let truth = sampled(w, h, &dome);
    let mut map = as_matched(&truth, w, h);
    let matched = map.values().to_vec();
    let stats = refine_following(&left, &right, None, &mut map);
    // Away from the rim, where the dome is a smooth surface.
    let inner: Vec<usize> = (0..w * h).filter(|&i| dome((i % w) as f64, (i / w) as f64) > 22.0).collect();
    let err = |m: &[f32]| inner.iter().map(|&i| m[i] - truth[i]).collect::<Vec<f32>>();
    let (before, after) = (err(&matched), err(map.values()));
    let mean = |e: &[f32]| e.iter().sum::<f32>() / e.len() as f32;
    let abs_median = |e: &[f32]| median(e.iter().map(|v| v.abs()).collect());
    assert!(mean(&before) < -0.05, "the window's mean falls short on the dome: {}", mean(&before));
    assert!(mean(&after).abs() < 0.25 * mean(&before).abs(), "bias {} → {}", mean(&before), mean(&after));
    assert!(abs_median(&after) < 0.5 * abs_median(&before), "median |error| {} → {}", abs_median(&before), abs_median(&after));
    assert!(stats.refined > inner.len() / 2 && stats.refined <= stats.looked, "{stats:?}");
    // Nothing is matched where nothing was.
    assert!(map.values().iter().zip(&matched).all(|(a, b)| a.is_nan() == b.is_nan()));
}

#[test]
fn the_silhouettes_edge_lends_the_windows_no_samples() {
    // A dome against a dark backdrop: its silhouette is a strong edge in both images,
    // but the right camera sees the surface turn away at another place than the left.
    let (w, h) = (160, 120);
    let dome = dome((80.0, 60.0), (55.0, 45.0), 16.0, 10.0);
    let (left, right) = pair_on(w, h, &dome, 10);
    let truth = sampled(w, h, &dome);
    let matched = as_matched(&truth, w, h);
    let object: Vec<u8> = truth.iter().map(|v| if v.is_nan() { 0 } else { 255 }).collect();
    let inside = crate::segment::inside_rim(&object, w, h, SILHOUETTE_PX);
    // The band between 3 and 8 px inside the silhouette (the refinement's region leaves
    // a margin of 5 px around the dome, all backdrop).
    let far = crate::segment::inside_rim(&object, w, h, 8);
    let band: Vec<usize> = (0..w * h).filter(|&i| inside[i] != 0 && far[i] == 0).collect();
    let err = |m: &DisparityMap| median(band.iter().map(|&i| (m.values()[i] - truth[i]).abs()).collect());
    let (mut with_edge, mut without_edge) = (matched.clone(), matched.clone());
    refine_following(&left, &right, None, &mut with_edge);
    refine_following(&left, &right, Some(&object), &mut without_edge);
    let (before, edge, no_edge) = (err(&matched), err(&with_edge), err(&without_edge));
    // Measured: 0.170 px as matched, 0.130 refined with the edge, 0.076 without it.
    assert!(no_edge < 0.75 * edge, "median |error| near the silhouette: {edge} with its edge, {no_edge} without");
    assert!(no_edge < 0.5 * before, "median |error| near the silhouette: {before} → {no_edge}");
}

#[test]
fn a_mask_without_the_object_leaves_the_map_as_it_was() {
    // No pixel is inside the silhouette: the windows have nothing to compare.
    let (w, h) = (100, 70);
    let dome = dome((50.0, 35.0), (40.0, 30.0), 12.0, 8.0);
    let (left, right) = pair(w, h, &dome);
    let mut map = as_matched(&sampled(w, h, &dome), w, h);
    let matched = map.values().to_vec();
    let stats = refine_following(&left, &right, Some(&vec![0u8; w * h]), &mut map);
    assert_eq!(stats.refined, 0, "{stats:?}");
    assert!(map.values().iter().zip(&matched).all(|(a, b)| a.to_bits() == b.to_bits()));
}

#[test]
fn a_rig_with_negative_disparities_is_refined_alike() {
    // The right camera left of the left one: d = x_left − x_right < 0 (docs: "Disparity
    // sign"). A slanted plane, given to the refinement 0.4 px off.
    let (w, h) = (120, 80);
    let plane = |x: f64, y: f64| -(24.0 + 0.04 * x + 0.02 * y);
    let (left, right) = pair(w, h, &plane);
    let mut map = DisparityMap::new(w, h);
    for y in 10..70 {
        for x in 40..110 {
            map.values_mut()[y * w + x] = plane(x as f64, y as f64) as f32 + 0.4;
        }
    }
    let stats = refine_following(&left, &right, None, &mut map);
    assert!(stats.refined > 3000, "{stats:?}");
    let err: Vec<f32> = (20..60).flat_map(|y| (50..100).map(move |x| (x, y))).map(|(x, y)| (map.values()[y * w + x] - plane(x as f64, y as f64) as f32).abs()).collect();
    assert!(median(err.clone()) < 0.05, "median error {} px after 0.4 px", median(err));
}

/// A cylinder's flank seen by both cameras, its disparity rising along x by 0.3 to 0.5 px a
/// column, painted by `paint`: the right camera sees its texture compressed to 0.5–0.7 of the
/// left's width, and its x-derivative 1.4–2 times larger there than the left's. Given as a
/// block matcher gives it (the window's mean) and refined: the median error and median
/// |error| inside it, px.
fn flank_refined(paint: &dyn Fn(f64, f64) -> f64) -> (f32, f32) {
    let (w, h) = (160, 100);
    let flank = |x: f64, y: f64| if (20.0..140.0).contains(&x) && (10.0..90.0).contains(&y) { 12.0 + 0.3 * (x - 20.0) + 0.00167 * (x - 20.0).powi(2) } else { f64::NAN };
    let (left, right) = pair_of(w, h, &flank, 100, paint);
    let truth = sampled(w, h, &flank);
    let mut map = as_matched(&truth, w, h);
    let stats = refine_following(&left, &right, None, &mut map);
    assert!(stats.refined > 4000, "{stats:?}");
    let inner: Vec<usize> = (0..w * h).filter(|&i| (35..125).contains(&(i % w)) && (25..75).contains(&(i / w))).collect();
    let err: Vec<f32> = inner.iter().map(|&i| map.values()[i] - truth[i]).collect();
    (median(err.clone()), median(err.iter().map(|e| e.abs()).collect()))
}

#[test]
fn a_surface_slanted_away_from_the_right_camera_is_refined_without_bias() {
    // A gentle texture, whose gradients the prefilter does not clip (a clipped one hides
    // the gradients' size from the comparison).
    let (bias, spread) = flank_refined(&|u, v| 128.0 + 0.3 * (texture(u, v) - 128.0));
    // Measured: bias 0.000 px, median |error| 0.019 px; 0.002 and 0.030 px with the right
    // image's prefiltered samples scaled by the stretch alone, 0.013 and 0.148 px with them
    // compared unscaled.
    assert!(bias.abs() < 0.02 && spread < 0.06, "bias {bias} px, median |error| {spread} px");
}

#[test]
fn a_sharp_texture_on_a_slanted_surface_is_compared_as_the_left_camera_sees_it() {
    // Two paints with sharp borders, finer than the texture above: the prefilter's three
    // columns in the compressed right image span more of the texture than in the left, so
    // scaling its derivative by the stretch is not enough; the right image warped first and
    // differentiated after is.
    let (bias, spread) = flank_refined(&|u, v| 128.0 + 40.0 * (3.0 * (texture(1.6 * u, 1.6 * v) - 128.0) / 40.0).tanh());
    // Measured: bias −0.010 px, median |error| 0.025 px; −0.009 and 0.045 px with the
    // prefiltered samples scaled by the stretch alone, −0.015 and 0.067 px unscaled.
    assert!(bias.abs() < 0.02 && spread < 0.035, "bias {bias} px, median |error| {spread} px");
}

#[test]
fn pixels_with_little_of_their_window_matched_keep_their_value() {
    let (w, h) = (96, 64);
    let plane = |x: f64, _y: f64| 20.0 + 0.05 * x;
    let (left, right) = pair(w, h, &plane);
    // A true map, off by 0.3 px everywhere, but matched only on a few lone pixels and a
    // square of 30 × 30.
    let mut map = DisparityMap::new(w, h);
    let lone = [5 * w + 5, 40 * w + 80, 58 * w + 12];
    for i in 0..w * h {
        let (x, y) = (i % w, i / w);
        if lone.contains(&i) || ((20..50).contains(&x) && (15..45).contains(&y)) {
            map.values_mut()[i] = plane(x as f64, y as f64) as f32 + 0.3;
        }
    }
    let before = map.values().to_vec();
    refine_following(&left, &right, None, &mut map);
    for &i in &lone {
        assert_eq!(map.values()[i], before[i], "a lone pixel (seq {i}) keeps its value");
    }
    // The square's middle is pulled back onto the plane.
    let i = 30 * w + 35;
    assert!((map.values()[i] - plane(35.0, 30.0) as f32).abs() < 0.1, "{} against {}", map.values()[i], plane(35.0, 30.0));
}

#[test]
fn the_avx2_copy_gives_the_portable_map() {
    let (w, h) = (100, 70);
    let dome = dome((50.0, 35.0), (40.0, 30.0), 12.0, 8.0);
    let (left, right) = pair(w, h, &dome);
    let truth = sampled(w, h, &dome);
    let mut portable = as_matched(&truth, w, h);
    let mut chosen = portable.clone();
    let a = refine(&left, &right, None, &mut portable, false);
    let b = refine_following(&left, &right, None, &mut chosen);
    assert_eq!(a, b);
    assert!(a.refined > 1000, "{a:?}");
    assert!(portable.values().iter().zip(chosen.values()).all(|(p, c)| p.to_bits() == c.to_bits()), "the two builds' maps differ");
}

#[cfg(target_arch = "x86_64")]
#[test]
fn the_avx2_warp_is_the_portable_one_at_the_span_ends_too() {
    if !std::is_x86_feature_detected!("avx2") {
        return;
    }
    // Rows whose warped positions fall before, inside and past the right span (clamped),
    // with a map never near (NaN), and a length not a multiple of 8.
    let mut seed = 0x2545_f491_4f6c_dd1d_u64;
    let mut rnd = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        (seed >> 40) as f32 / (1u64 << 24) as f32
    };
    for n in [8, 37, 64] {
        let smooth: Vec<f32> = (0..n).map(|i| if i % 11 == 3 { f32::NAN } else { -30.0 + 80.0 * rnd() }).collect();
        let raw: Vec<f32> = (0..24).map(|_| 255.0 * rnd()).collect();
        let warp = WarpRow { x0: 5, smooth: &smooth, right: &raw, first: 3.0, last: 25.0 };
        for &shift in &SHIFTS {
            let (mut p, mut q) = (vec![0f32; n], vec![0f32; n]);
            warp_row(&warp, shift, &mut p, 0);
            // SAFETY: the CPU has AVX2 (checked above); the rows are `n` long.
            let done = unsafe { avx2::warp_row(&warp, shift, &mut q) };
            warp_row(&warp, shift, &mut q, done);
            assert_eq!(done, n / 8 * 8);
            assert!(p.iter().zip(&q).all(|(a, b)| a.to_bits() == b.to_bits()), "warp at {shift}, {n} px: {p:?} against {q:?}");
            assert!(p.iter().zip(&smooth).all(|(v, s)| v.is_nan() == s.is_nan()), "NaN exactly where the map is");
        }
    }
}

#[test]
fn pixels_beside_an_unwarped_one_take_the_stretched_sample() {
    // A 6 × 4 region: the warped right image a ramp (x-Sobel 8 a column of slope 1), one
    // pixel unwarped (unmatched, so not sampled either), and one more not sampled.
    let (w, h) = (6, 4);
    let mut warped: Vec<f32> = (0..w * h).map(|i| 100.0 + (i % w) as f32).collect();
    warped[w + 3] = f32::NAN;
    let left = vec![5.0f32; w * h];
    let mut sampled = vec![1.0f32; w * h];
    (sampled[w + 3], sampled[2 * w + 1]) = (f32::NAN, f32::NAN);
    let mut cost = vec![-1.0f32; w * h];
    derivative_costs(&warped, &left, &sampled, &mut cost, w);
    // The region's edge and the pixels whose kernel reaches the unwarped one (the columns
    // either side of it) are left to the stretched sample; the pixels not sampled cost
    // nothing; the rest compare 5 with the ramp's 8.
    for y in 0..h {
        for x in 0..w {
            let (c, i) = (cost[y * w + x], y * w + x);
            let beside = (x as isize - 3).abs() == 1 && (y as isize - 1).abs() <= 1;
            let edge = x == 0 || y == 0 || x == w - 1 || y == h - 1;
            if i == 2 * w + 1 || i == w + 3 {
                assert_eq!(c, 0.0, "({x}, {y}) is not sampled");
            } else if edge || beside {
                assert!(c.is_nan(), "({x}, {y}): {c}");
            } else {
                assert_eq!(c, 3.0, "({x}, {y})");
            }
        }
    }
    // The stretched sample fills them: a map of 2 + x/2 px (a stretch of 0.5), the right row
    // ten times its column's index.
    let smooth: Vec<f32> = (0..w).map(|x| 2.0 + 0.5 * x as f32).collect();
    let right: Vec<f32> = (0..8).map(|i| 10.0 * i as f32).collect();
    let row = CostRow { x0: 0, smooth: &smooth, left: &left[..w], right: &right, first: 0.0, last: 6.0 };
    let mut out = cost[w..2 * w].to_vec();
    stretched_costs(&row, 0.0, &mut out);
    // At x the right image reads 10 (x/2 − 2) (0 before its first column), scaled by 0.5
    // and clipped to ±62.
    for (x, &c) in out.iter().enumerate() {
        let want = if cost[w + x].is_nan() { (5.0 - (5.0 * (0.5 * x as f32 - 2.0).max(0.0)).min(62.0)).abs() } else { cost[w + x] };
        assert_eq!(c, want, "x = {x}");
    }
}

#[test]
fn an_empty_map_stays_empty() {
    let (w, h) = (40, 30);
    let img = vec![90u8; w * h];
    let mut map = DisparityMap::new(w, h);
    assert_eq!(refine_following(&img, &img, None, &mut map), FollowStats::default());
    assert!(map.values().iter().all(|v| v.is_nan()));
}

#[test]
fn the_box_sum_is_the_sum_over_the_square() {
    let (w, h, r) = (13, 9, 2);
    let a: Vec<f32> = (0..w * h).map(|i| ((i * 37) % 11) as f32).collect();
    let mut b = a.clone();
    let mut tmp = vec![0.0; w * h];
    box_sum(&mut b, &mut tmp, w, h, r);
    for y in 0..h {
        for x in 0..w {
            let mut s = 0.0;
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                    s += a[yy * w + xx];
                }
            }
            assert_eq!(b[y * w + x], s, "at ({x}, {y})");
        }
    }
}
