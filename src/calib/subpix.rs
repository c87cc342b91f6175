//! Sub-pixel chessboard corners, OpenCV's `cornerSubPix` rule, and a measure of blur.
//!
//! At an ideal corner q, every image gradient ∇I(p) in a window around it is orthogonal to
//! p − q (on a flat square the gradient is zero; on an edge through q it is perpendicular to
//! the edge, which runs along p − q). q is the least-squares solution of
//! Σ w(p) ∇I ∇Iᵀ (q − p) = 0, iterated with the window re-sampled (bilinear) around each new q
//! until it moves less than `eps`. The window weights, the bilinear sampling with its border
//! replication and the stopping rule are OpenCV's, so the same window gives OpenCV's corners
//! (within a few hundredths of a pixel where the JPEG decoders agree).

use crate::stereo::GrayView;

/// Stopping rule and window of [`refine`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SubPixParams {
    /// Half the window side: the window is `(2·half + 1)²` pixels (OpenCV's `winSize`).
    pub half_window: usize,
    /// Stop when an iteration moves the corner less than this, pixels.
    pub eps: f64,
    pub max_iterations: usize,
}

impl Default for SubPixParams {
    /// OpenCV's `stereo_calib` sample: an 11-pixel half-window, ε = 0.01, 30 iterations.
    fn default() -> Self {
        SubPixParams { half_window: 11, eps: 0.01, max_iterations: 30 }
    }
}

/// Bilinear sample with the border replicated (OpenCV's `getRectSubPix` outside the image).
fn sample(img: &GrayView, x: f64, y: f64) -> f64 {
    let (w, h) = (img.width as isize, img.height as isize);
    let x0 = x.floor();
    let y0 = y.floor();
    let (fx, fy) = (x - x0, y - y0);
    let at = |xi: isize, yi: isize| -> f64 {
        let xi = xi.clamp(0, w - 1) as usize;
        let yi = yi.clamp(0, h - 1) as usize;
        f64::from(img.data[yi * img.width + xi])
    };
    let (xi, yi) = (x0 as isize, y0 as isize);
    let top = at(xi, yi) * (1.0 - fx) + at(xi + 1, yi) * fx;
    let bottom = at(xi, yi + 1) * (1.0 - fx) + at(xi + 1, yi + 1) * fx;
    top * (1.0 - fy) + bottom * fy
}

/// Refines one corner from its initial estimate `(x, y)` (pixel centres at integers). A
/// corner that wanders further than the window from where it started is returned unmoved,
/// as OpenCV does.
pub fn refine(img: &GrayView, x: f64, y: f64, p: &SubPixParams) -> (f64, f64) {
    let half = p.half_window as isize;
    let side = 2 * half + 1;
    let n = (side + 2) as usize;
    let weight: Vec<f64> = (0..side)
        .map(|i| {
            let t = (i - half) as f64 / half as f64;
            (-t * t).exp()
        })
        .collect();
    let mut patch = vec![0.0f64; n * n];
    let (x0, y0) = (x, y);
    let (mut cx, mut cy) = (x, y);
    for _ in 0..p.max_iterations {
        for (r, row) in patch.chunks_exact_mut(n).enumerate() {
            let sy = cy + (r as f64 - (half + 1) as f64);
            for (c, v) in row.iter_mut().enumerate() {
                *v = sample(img, cx + (c as f64 - (half + 1) as f64), sy);
            }
        }
        let (mut a, mut b, mut c, mut bb1, mut bb2) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for i in 0..side as usize {
            let py = i as f64 - half as f64;
            for j in 0..side as usize {
                let px = j as f64 - half as f64;
                let m = weight[i] * weight[j];
                let gx = patch[(i + 1) * n + j + 2] - patch[(i + 1) * n + j];
                let gy = patch[(i + 2) * n + j + 1] - patch[i * n + j + 1];
                let (gxx, gxy, gyy) = (gx * gx * m, gx * gy * m, gy * gy * m);
                a += gxx;
                b += gxy;
                c += gyy;
                bb1 += gxx * px + gxy * py;
                bb2 += gxy * px + gyy * py;
            }
        }
        let det = a * c - b * b;
        if det.abs() <= f64::EPSILON * f64::EPSILON {
            break;
        }
        let s = 1.0 / det;
        let nx = cx + c * s * bb1 - b * s * bb2;
        let ny = cy - b * s * bb1 + a * s * bb2;
        let moved = (nx - cx).powi(2) + (ny - cy).powi(2);
        cx = nx;
        cy = ny;
        if cx < 0.0 || cx >= img.width as f64 || cy < 0.0 || cy >= img.height as f64 || moved <= p.eps * p.eps {
            break;
        }
    }
    if (cx - x0).abs() > half as f64 || (cy - y0).abs() > half as f64 {
        return (x0, y0);
    }
    (cx, cy)
}

/// The width, in pixels, over which an edge between two squares rises from 10 % to 90 % of
/// its step: sampled across the edge at `(x, y)`, direction `(nx, ny)` (unit), out to `reach`
/// pixels on each side. `None` when there is no step to measure.
pub fn edge_width(img: &GrayView, (x, y): (f64, f64), (nx, ny): (f64, f64), reach: f64) -> Option<f64> {
    let steps = (reach * 4.0).ceil().max(4.0) as usize;
    let profile: Vec<f64> = (0..=2 * steps)
        .map(|k| {
            let t = (k as f64 - steps as f64) / 4.0;
            sample(img, x + nx * t, y + ny * t)
        })
        .collect();
    let lo = profile[..steps / 2].iter().sum::<f64>() / (steps / 2) as f64;
    let hi = profile[profile.len() - steps / 2..].iter().sum::<f64>() / (steps / 2) as f64;
    if (hi - lo).abs() < 10.0 {
        return None;
    }
    // Where the profile crosses 10 % and 90 % of the step, walking out from the middle.
    let level = |f: f64| lo + (hi - lo) * f;
    let crossing = |f: f64| -> Option<f64> {
        let l = level(f);
        let mid = steps;
        let above = |v: f64| if hi > lo { v >= l } else { v <= l };
        // The last position from the start that is still below the level.
        (0..2 * steps).find(|&k| !above(profile[k]) && above(profile[k + 1])).map(|k| {
            let (a, b) = (profile[k], profile[k + 1]);
            let t = if b != a { (l - a) / (b - a) } else { 0.5 };
            (k as f64 + t - mid as f64) / 4.0
        })
    };
    Some((crossing(0.9)? - crossing(0.1)?).abs())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth X-corner at (cx, cy): the product of two soft steps.
    fn corner_image(w: usize, h: usize, cx: f64, cy: f64, angle: f64) -> Vec<u8> {
        let (s, c) = angle.sin_cos();
        let mut img = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as f64 - cx, y as f64 - cy);
                let u = c * dx + s * dy;
                let v = -s * dx + c * dy;
                let v = (u / 1.2).tanh() * (v / 1.2).tanh();
                img[y * w + x] = (128.0 + 100.0 * v).round() as u8;
            }
        }
        img
    }

    #[test]
    fn corners_are_found_to_a_small_fraction_of_a_pixel() {
        for &(cx, cy, angle) in &[(20.3, 19.8, 0.0), (21.71, 18.45, 0.4), (19.5, 20.25, -0.9)] {
            let img = corner_image(40, 40, cx, cy, angle);
            let view = GrayView::new(40, 40, &img).unwrap();
            let (x, y) = refine(&view, cx.round() + 1.0, cy.round() - 1.0, &SubPixParams { half_window: 6, ..Default::default() });
            assert!((x - cx).abs() < 0.03 && (y - cy).abs() < 0.03, "({x}, {y}) vs ({cx}, {cy})");
        }
    }

    #[test]
    fn an_edge_s_width_is_its_blur() {
        let w = 60;
        let make = |sigma: f64| -> Vec<u8> {
            (0..w * w).map(|i| (128.0 + 100.0 * ((i % w) as f64 - 30.0).tanh_scaled(sigma)).round() as u8).collect()
        };
        trait Soft {
            fn tanh_scaled(self, s: f64) -> f64;
        }
        impl Soft for f64 {
            fn tanh_scaled(self, s: f64) -> f64 {
                (self / s).tanh()
            }
        }
        let sharp = make(0.5);
        let soft = make(4.0);
        let ws = edge_width(&GrayView::new(w, w, &sharp).unwrap(), (30.0, 30.0), (1.0, 0.0), 12.0).unwrap();
        let wb = edge_width(&GrayView::new(w, w, &soft).unwrap(), (30.0, 30.0), (1.0, 0.0), 12.0).unwrap();
        // tanh(x/s) rises from 10 % to 90 % of its step over 2·s·atanh(0.8) ≈ 2.2·s.
        assert!(ws < 2.0, "{ws}");
        assert!((wb - 8.79).abs() < 0.6, "{wb}");
    }
}
