//! The map fitted by a plane around each pixel: the surface that the refinement's windows
//! are warped by.

/// The products summed for a plane's least-squares fit, per matched pixel: 1, u, v, u², v²,
/// uv, e, ue, ve (u, v its column and row from the map's centre, e its disparity less the
/// map's mean).
const PRODUCTS: usize = 9;

/// The map fitted at each matched pixel by a plane, least squares over the matched pixels
/// of the (2r + 1)² square around it (the part inside the map), and read at the pixel; NaN
/// where unmatched. `d`: `w × h`, NaN unmatched. Where the square's matched pixels do not
/// spread at least `min_spread` (their variance, px²) along x and along y, or lie nearly on
/// a line, their mean.
///
/// Inside the object, where the whole square is matched, the plane's value at the centre is
/// the square's mean; near a silhouette or a hole it is not biased by the slope, as a mean of
/// one side is.
#[inline(always)]
pub(super) fn plane_fit(d: &[f32], w: usize, h: usize, r: usize, min_spread: f64) -> Vec<f32> {
    assert_eq!(d.len(), w * h, "a map of w × h");
    let mut out = vec![f32::NAN; w * h];
    let (n, total) = d.iter().filter(|v| !v.is_nan()).fold((0usize, 0f64), |(n, t), &v| (n + 1, t + v as f64));
    if n == 0 {
        return out;
    }
    // The sums are in f64 from the map's centre and mean: the centred moments a fit takes
    // (a variance of ~14 px² from sums of ~10⁵ px² a pixel) keep 10 digits.
    let reference = total / n as f64;
    let (cx, cy) = ((w / 2) as f64, (h / 2) as f64);
    let u: Vec<f64> = (0..w).map(|x| x as f64 - cx).collect();
    // Per product, its sums down each column over the rows y − r ..= y + r of the row y being
    // fitted; then along the row over the square's columns. One slice a product, so that
    // each pass runs in vector lanes along the row.
    let mut columns = vec![0f64; PRODUCTS * w];
    let mut sums = vec![0f64; PRODUCTS * w];
    // A row's column sums with r zeros either side, and its sums over 2, 4 and 8 columns.
    let mut padded = vec![0f64; w + 2 * r];
    let mut runs = [vec![0f64; w + 2 * r], vec![0f64; w + 2 * r], vec![0f64; w + 2 * r]];
    let (mut m, mut e) = (vec![0f64; w], vec![0f64; w]);
    for y in 0..h + r {
        // The row entering the rows summed, and the one leaving them.
        for (row, sign) in [(y, 1.0), (y.wrapping_sub(2 * r + 1), -1.0)] {
            if row >= h {
                continue;
            }
            let values = &d[row * w..(row + 1) * w];
            if values.iter().all(|v| v.is_nan()) {
                continue;
            }
            for ((m, e), &v) in m.iter_mut().zip(e.iter_mut()).zip(values) {
                (*m, *e) = if v.is_nan() { (0.0, 0.0) } else { (sign, sign * (v as f64 - reference)) };
            }
            let v = row as f64 - cy;
            let mut c = columns.chunks_exact_mut(w);
            let mut next = || c.next().expect("nine products");
            let (c1, cu, cv, cuu, cvv, cuv, ce, cue, cve) = (next(), next(), next(), next(), next(), next(), next(), next(), next());
            for x in 0..w {
                let (m, e, u) = (m[x], e[x], u[x]);
                c1[x] += m;
                cu[x] += m * u;
                cv[x] += m * v;
                cuu[x] += m * u * u;
                cvv[x] += m * v * v;
                cuv[x] += m * u * v;
                ce[x] += e;
                cue[x] += e * u;
                cve[x] += e * v;
            }
        }
        // The row whose squares the columns now hold, over its matched pixels.
        let Some(y) = y.checked_sub(r) else { continue };
        let row = &d[y * w..(y + 1) * w];
        let Some((first, last)) = super::searched_span(row, row) else { continue };
        let (x0, x1) = (first.saturating_sub(r), (last + r + 1).min(w));
        for (s, c) in sums.chunks_exact_mut(w).zip(columns.chunks_exact(w)) {
            // padded[r + x] holds column x (within x0..x1; zeros beyond): the square around
            // x spans padded[x ..= x + 2r].
            padded[r + x0..r + x1].copy_from_slice(&c[x0..x1]);
            padded[first..r + x0].fill(0.0);
            padded[r + x1..(last + 2 * r + 1).max(r + x1)].fill(0.0);
            square_sums(&padded[first..last + 2 * r + 1], &mut runs, r, &mut s[first..=last]);
        }
        // The fits, in vector lanes along the row (every slice as long as the span).
        let v = y as f64 - cy;
        let span = first..last + 1;
        let n = span.len();
        let products: [&[f64]; PRODUCTS] = std::array::from_fn(|k| &sums[k * w + first..k * w + first + n]);
        let (row, o, u) = (&row[span.clone()], &mut out[y * w + first..y * w + first + n], &u[span]);
        for i in 0..n {
            let s: [f64; PRODUCTS] = std::array::from_fn(|k| products[k][i]);
            let fit = (reference + fitted(&s, u[i], v, min_spread)) as f32;
            o[i] = if row[i].is_nan() { f32::NAN } else { fit };
        }
    }
    out
}

/// `out[i]`: the sum of `a[i ..= i + 2r]`, by sums over 2, 4 and 8 (at most 16) columns
/// (`runs`: scratch as long as `a`): a few passes that each run in vector lanes, instead of
/// 2r + 1 of them or a running sum that waits on each add.
#[inline(always)]
fn square_sums(a: &[f64], runs: &mut [Vec<f64>; 3], r: usize, out: &mut [f64]) {
    let side = 2 * r + 1;
    assert!(side <= 16 && a.len() == out.len() + 2 * r, "a square of at most 16 columns");
    let [two, four, eight] = runs;
    let n = a.len();
    for i in 0..n - 1 {
        two[i] = a[i] + a[i + 1];
    }
    for i in 0..n.saturating_sub(3) {
        four[i] = two[i] + two[i + 2];
    }
    for i in 0..n.saturating_sub(7) {
        eight[i] = four[i] + four[i + 4];
    }
    // side = 8·b3 + 4·b2 + 2·b1 + b0: the runs laid end to end.
    for (i, o) in out.iter_mut().enumerate() {
        let mut at = i;
        let mut t = 0.0;
        if side & 8 != 0 {
            t += eight[at];
            at += 8;
        }
        if side & 4 != 0 {
            t += four[at];
            at += 4;
        }
        if side & 2 != 0 {
            t += two[at];
            at += 2;
        }
        if side & 1 != 0 {
            t += a[at];
        }
        *o = t;
    }
}

/// The plane through the summed products `s` read at (pu, pv), relative to the reference; the
/// mean where the pixels do not spread in both directions.
#[inline(always)]
fn fitted(s: &[f64; PRODUCTS], pu: f64, pv: f64, min_spread: f64) -> f64 {
    // (Two divisions a pixel, not seven: the means and the slopes by reciprocals.)
    let per = 1.0 / s[0];
    let (ub, vb, eb) = (s[1] * per, s[2] * per, s[6] * per);
    let (suu, svv, suv) = (s[3] * per - ub * ub, s[4] * per - vb * vb, s[5] * per - ub * vb);
    let (sue, sve) = (s[7] * per - ub * eb, s[8] * per - vb * eb);
    let det = suu * svv - suv * suv;
    // A correlation of x and y under √0.75 leaves the tilt measured both ways.
    let tilted = suu >= min_spread && svv >= min_spread && det >= 0.25 * suu * svv;
    let inv = 1.0 / det;
    let (bx, by) = ((svv * sue - suv * sve) * inv, (suu * sve - suv * sue) * inv);
    // (A select, not a branch: the pixels of a row are fitted in vector lanes.)
    if tilted {
        eb + bx * (pu - ub) + by * (pv - vb)
    } else {
        eb
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w × h` map of `f(x, y)` where `keep(x, y)`, NaN elsewhere.
    fn map(w: usize, h: usize, f: impl Fn(f64, f64) -> f64, keep: impl Fn(usize, usize) -> bool) -> Vec<f32> {
        (0..w * h).map(|i| if keep(i % w, i / w) { f((i % w) as f64, (i / w) as f64) as f32 } else { f32::NAN }).collect()
    }

    #[test]
    fn a_slope_is_followed_up_to_the_edge_and_around_holes() {
        // A plane steep along x (as the surface is where it turns away at the silhouette),
        // matched left of column 30 but for a hole: a mean of the pixels on one side would
        // lag it by 0.8 px a pixel of offset, 2.4 px at the edge.
        let (w, h) = (60, 40);
        let plane = |x: f64, y: f64| 20.0 + 0.8 * x - 0.3 * y;
        let keep = |x: usize, y: usize| x < 30 && (!(10..14).contains(&x) || !(15..19).contains(&y));
        let d = map(w, h, plane, keep);
        let fit = plane_fit(&d, w, h, 6, 1.0);
        for (i, (&f, &v)) in fit.iter().zip(&d).enumerate() {
            assert_eq!(f.is_nan(), v.is_nan(), "fitted exactly where matched, at {i}");
            assert!(v.is_nan() || (f - v).abs() < 1e-3, "at ({}, {}): {f} against the plane's {v}", i % w, i / w);
        }
    }

    #[test]
    fn inside_a_wholly_matched_square_the_fit_is_its_mean() {
        let (w, h) = (40, 30);
        let bumpy = |x: f64, y: f64| 30.0 + (0.3 * x).sin() * 4.0 + 0.01 * x * y;
        let d = map(w, h, bumpy, |_, _| true);
        let fit = plane_fit(&d, w, h, 6, 1.0);
        for (x, y) in [(6, 6), (20, 15), (33, 23)] {
            let d = &d;
            let mean = (y - 6..=y + 6).flat_map(|yy| (x - 6..=x + 6).map(move |xx| d[yy * w + xx] as f64)).sum::<f64>() / 169.0;
            assert!((fit[y * w + x] as f64 - mean).abs() < 1e-4, "at ({x}, {y}): {} against the mean {mean}", fit[y * w + x]);
        }
    }

    #[test]
    fn pixels_on_a_line_take_their_mean() {
        // One column matched: no spread along x, so no tilt across it is fitted.
        let (w, h) = (30, 30);
        let d = map(w, h, |_, y| 10.0 + 0.5 * y, |x, _| x == 12);
        let fit = plane_fit(&d, w, h, 6, 1.0);
        let y = 2;
        let mean = (0..=y + 6).map(|yy| 10.0 + 0.5 * yy as f64).sum::<f64>() / (y + 7) as f64;
        assert!((fit[y * w + 12] as f64 - mean).abs() < 1e-4, "{} against {mean}", fit[y * w + 12]);
        assert!(fit.iter().enumerate().all(|(i, f)| f.is_nan() == (i % w != 12)));
    }

    #[test]
    fn a_map_narrower_than_the_square_is_fitted_over_what_there_is() {
        // 5 × 4 pixels against a 13-pixel square: every sum is clipped to the map.
        let (w, h) = (5, 4);
        let plane = |x: f64, y: f64| 7.0 - 0.5 * x + 0.25 * y;
        let d = map(w, h, plane, |x, y| (x + y) % 3 != 0);
        let fit = plane_fit(&d, w, h, 6, 1.0);
        for (i, (&f, &v)) in fit.iter().zip(&d).enumerate() {
            assert_eq!(f.is_nan(), v.is_nan(), "fitted exactly where matched, at {i}");
            assert!(v.is_nan() || (f - v).abs() < 1e-4, "at {i}: {f} against {v}");
        }
    }

    #[test]
    fn an_unmatched_map_stays_unmatched() {
        assert!(plane_fit(&[f32::NAN; 12], 4, 3, 6, 1.0).iter().all(|v| v.is_nan()));
    }
}
