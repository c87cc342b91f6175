//! Keying a plain backdrop by its lack of texture, where no coloured screen is in view: grey
//! cameras (the recording format's 8-bit grey frames; the lab's XIMEA rig is monochrome), or
//! a colour camera in front of a white, grey or black backdrop.
//!
//! A backdrop is plain: the texture stereo matches is what it lacks. Each pixel's texture is
//! the standard deviation of the luma (smoothed 1-2-1) over a 5 × 5 window; a pixel is smooth
//! below a threshold set over the noise of the image's border. A smooth region that reaches
//! the image's edge (the backdrop, a shaded table reaching the bottom) or is large (a turntable
//! top ringed by its rim, a cast shadow) is background; the rest is object. An opening then
//! removes the thin textured lines such regions' edges leave (a table's rim, a shadow's
//! outline), pieces far smaller than the largest are dropped, and the mask is eroded by the
//! window's half-width, by which the texture measure spreads the object's texture past its
//! silhouette. The same takes a grey floor or turntable out of a colour key's mask where
//! that mask reaches the image's edge ([`key_within`]).

use super::{morph, AUTO_MIN_SHARE};

/// Half-width of the texture window (5 × 5).
const WINDOW: usize = 2;

/// The least texture threshold: a standard deviation of this many grey levels.
pub const MIN_TEXTURE: f32 = 2.0;

/// The texture threshold over the border's noise (its median texture).
pub const NOISE_FACTOR: f32 = 3.0;

/// The most noise a plain backdrop shows: the border's median texture, grey levels of
/// standard deviation after the smoothing (which takes a sensor's noise to about 0.4 of
/// itself). A border noisier than this is textured: no backdrop.
pub const MAX_NOISE: f32 = 4.0;

/// A smooth region covering at least this share of the image is background wherever it lies.
pub const LARGE_SHARE: f32 = 0.002;

/// Radius of the opening that removes the textured lines left by the edges of smooth regions.
const OPEN_RADIUS: usize = 3;

/// Object pieces under this share of the largest piece are dropped.
const PIECE_SHARE: f32 = 0.1;

/// How a frame's backdrop was keyed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Backdrop {
    /// Mean chromaticity `(R, G) / (R + G + B)` of the border's smooth pixels.
    pub chroma: (f32, f32),
    /// Share (0…1) of the border's pixels that are smooth.
    pub border_share: f32,
    /// The texture threshold, grey levels of standard deviation.
    pub threshold: f32,
}

/// The pixels of an RGB image's border ([`border_grid`]) that hold the scene: all but the black
/// ones (0, 0, 0), which a rectified image is wherever it maps outside the camera's (a
/// toed-in rig zoomed out by its alpha shows wide black margins). None where fewer than
/// [`MIN_LIT_BORDER`] are left (and not all of them): too few to say what the border shows.
pub(super) fn lit_border(rgb: &[u8], w: usize, h: usize) -> Option<Vec<usize>> {
    let grid = border_grid(w, h);
    let all = grid.len();
    let at: Vec<usize> = grid.into_iter().filter(|&i| rgb[3 * i..3 * i + 3] != [0, 0, 0]).collect();
    (at.len() >= MIN_LIT_BORDER || (at.len() == all && all > 0)).then_some(at)
}

/// Fewest border pixels ([`lit_border`]) a key is found from, unless the whole border is lit
/// (a tiny image's).
const MIN_LIT_BORDER: usize = 64;

/// The pixels of a `w` × `h` image's border — a ring of a sixteenth of the smaller side — on a
/// grid of an eighth of that (about 7 000 pixels of a 640 × 480 frame), as indices.
fn border_grid(w: usize, h: usize) -> Vec<usize> {
    let ring = (w.min(h) / 16).max(1);
    let step = (ring / 8).max(1);
    let mut at = Vec::new();
    for y in (0..h).step_by(step) {
        let edge_row = y < ring || y + ring >= h;
        at.extend((0..w).step_by(step).filter(|&x| edge_row || x < ring || x + ring >= w).map(|x| y * w + x));
    }
    at
}

/// Each pixel's texture: the variance (grey levels²) of the luma, smoothed 1-2-1 both ways,
/// over the 5 × 5 window around it, clipped to the image. Every pass runs along whole rows
/// (the vertical ones add rows element-wise), so that it vectorises.
fn texture(rgb: &[u8], w: usize, h: usize) -> Vec<f32> {
    // The matcher's grey (BT.601 luma), then 1-2-1 along rows and down columns (the image's
    // edge repeated): ×16, at most 4080.
    let luma: Vec<u16> = rgb.chunks_exact(3).map(|p| crate::stereo::luma(p[0], p[1], p[2]) as u16).collect();
    let mut across = vec![0u16; w * h];
    for (src, dst) in luma.chunks_exact(w).zip(across.chunks_exact_mut(w)) {
        for x in [0, w - 1] {
            dst[x] = src[x.saturating_sub(1)] + 2 * src[x] + src[(x + 1).min(w - 1)];
        }
        for (((d, &l), &m), &r) in dst[1..].iter_mut().zip(src).zip(&src[1..]).zip(src.get(2..).unwrap_or_default()) {
            *d = l + 2 * m + r;
        }
    }
    let mut blurred = vec![0u16; w * h];
    for (y, dst) in blurred.chunks_exact_mut(w).enumerate() {
        let (up, mid, down) = (row(&across, w, y.saturating_sub(1)), row(&across, w, y), row(&across, w, (y + 1).min(h - 1)));
        for x in 0..w {
            dst[x] = up[x] + 2 * mid[x] + down[x];
        }
    }
    // Window sums of the value and its square along rows, then down columns: at most
    // 25 · 4080² < 2³².
    let mut sums = vec![0u32; w * h];
    let mut squares = vec![0u32; w * h];
    for ((src, s), q) in blurred.chunks_exact(w).zip(sums.chunks_exact_mut(w)).zip(squares.chunks_exact_mut(w)) {
        let (mut run_s, mut run_q) = (0u32, 0u32);
        // The running window [x − WINDOW, x + WINDOW], clipped: add what enters, drop what leaves.
        for v in &src[..WINDOW.min(w)] {
            run_s += *v as u32;
            run_q += *v as u32 * *v as u32;
        }
        for x in 0..w {
            if let Some(&v) = src.get(x + WINDOW) {
                run_s += v as u32;
                run_q += v as u32 * v as u32;
            }
            if x > WINDOW {
                let v = src[x - WINDOW - 1] as u32;
                run_s -= v;
                run_q -= v * v;
            }
            s[x] = run_s;
            q[x] = run_q;
        }
    }
    // Down columns as a running sum of rows; the variance is E[v²] − E[v]² (in f32: a few
    // thousandths of a grey level² off, against thresholds of 4 and more), ÷ 16² for grey levels.
    let mut var = vec![0f32; w * h];
    let (mut col_s, mut col_q) = (vec![0u32; w], vec![0u32; w]);
    let add_row = |cs: &mut [u32], cq: &mut [u32], y: usize| {
        for ((a, b), (&s, &q)) in cs.iter_mut().zip(cq.iter_mut()).zip(row(&sums, w, y).iter().zip(row(&squares, w, y))) {
            *a += s;
            *b += q;
        }
    };
    let drop_row = |cs: &mut [u32], cq: &mut [u32], y: usize| {
        for ((a, b), (&s, &q)) in cs.iter_mut().zip(cq.iter_mut()).zip(row(&sums, w, y).iter().zip(row(&squares, w, y))) {
            *a -= s;
            *b -= q;
        }
    };
    for y in 0..WINDOW.min(h) {
        add_row(&mut col_s, &mut col_q, y);
    }
    let inv_cols: Vec<f32> = (0..w).map(|x| 1.0 / ((x + WINDOW + 1).min(w) - x.saturating_sub(WINDOW)) as f32).collect();
    for y in 0..h {
        if y + WINDOW < h {
            add_row(&mut col_s, &mut col_q, y + WINDOW);
        }
        if y > WINDOW {
            drop_row(&mut col_s, &mut col_q, y - WINDOW - 1);
        }
        let inv_rows = 1.0 / ((y + WINDOW + 1).min(h) - y.saturating_sub(WINDOW)) as f32;
        for (((out, &s), &q), &ic) in var[y * w..(y + 1) * w].iter_mut().zip(&col_s).zip(&col_q).zip(&inv_cols) {
            let inv_n = ic * inv_rows;
            let mean = s as f32 * inv_n;
            *out = (q as f32 * inv_n - mean * mean).max(0.0) / 256.0;
        }
    }
    var
}

/// Row `y` of an image `w` wide.
fn row<T>(v: &[T], w: usize, y: usize) -> &[T] {
    &v[y * w..(y + 1) * w]
}

/// Labels of the runs of set pixels of a `w` × `h` mask, connected through 4 or (with `eight`)
/// 8 neighbours: each run `(row, x0, x1)` (pixels `x0..x1`) with its component's number, and
/// the number of components.
fn components(set: &[bool], w: usize, h: usize, eight: bool) -> (Vec<(usize, usize, usize)>, Vec<usize>, usize) {
    let mut runs = Vec::new();
    let mut parent: Vec<usize> = Vec::new();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let reach = eight as usize;
    let mut prev = 0..0;
    for y in 0..h {
        let row = &set[y * w..(y + 1) * w];
        let start = runs.len();
        let mut x = 0;
        while x < w {
            if !row[x] {
                x += 1;
                continue;
            }
            let x0 = x;
            while x < w && row[x] {
                x += 1;
            }
            let me = runs.len();
            runs.push((y, x0, x));
            parent.push(me);
            // Runs of the row above that touch this one (diagonally too with `eight`).
            for k in prev.clone() {
                let (_, a0, a1) = runs[k];
                if a0 < x + reach && x0 < a1 + reach {
                    let (ra, rb) = (root(&mut parent, k), root(&mut parent, me));
                    parent[ra.max(rb)] = ra.min(rb);
                }
            }
        }
        prev = start..runs.len();
    }
    let mut number = vec![usize::MAX; runs.len()];
    let mut count = 0;
    let labels = (0..runs.len())
        .map(|k| {
            let r = root(&mut parent, k);
            if number[r] == usize::MAX {
                number[r] = count;
                count += 1;
            }
            number[r]
        })
        .collect();
    (runs, labels, count)
}

/// The plain backdrop of an interleaved RGB image (module docs): per pixel, whether it lies
/// in a smooth region that reaches the image's edge or covers [`LARGE_SHARE`] of it, and how
/// it was found; None where the border is not plain: its median texture over [`MAX_NOISE`],
/// or under [`AUTO_MIN_SHARE`] of it smooth (a textured background, an object over the
/// border).
fn plain(rgb: &[u8], w: usize, h: usize) -> Option<(Vec<bool>, Backdrop)> {
    if w == 0 || h == 0 || rgb.len() != 3 * w * h {
        return None;
    }
    let border = lit_border(rgb, w, h)?;
    let var = texture(rgb, w, h);
    let mut noise: Vec<f32> = border.iter().map(|&i| var[i]).collect();
    noise.sort_unstable_by(f32::total_cmp);
    let noise = noise[noise.len() / 2].sqrt();
    if noise > MAX_NOISE {
        return None;
    }
    let threshold = MIN_TEXTURE.max(NOISE_FACTOR * noise);
    let smooth: Vec<bool> = var.iter().map(|&v| v < threshold * threshold).collect();
    let plain: Vec<usize> = border.iter().copied().filter(|&i| smooth[i]).collect();
    let border_share = plain.len() as f32 / border.len() as f32;
    if border_share < AUTO_MIN_SHARE {
        return None;
    }
    let (r, g) = plain.iter().fold((0.0, 0.0), |(r, g), &i| {
        let c = super::chromaticity(&rgb[3 * i..3 * i + 3]).unwrap_or((1.0 / 3.0, 1.0 / 3.0));
        (r + c.0, g + c.1)
    });
    let chroma = (r / plain.len() as f32, g / plain.len() as f32);

    // Smooth regions reaching the edge, or large, are background.
    let (runs, labels, count) = components(&smooth, w, h, false);
    let (mut area, mut on_edge) = (vec![0usize; count], vec![false; count]);
    for (&(y, x0, x1), &l) in runs.iter().zip(&labels) {
        area[l] += x1 - x0;
        on_edge[l] |= y == 0 || y + 1 == h || x0 == 0 || x1 == w;
    }
    let large = (LARGE_SHARE * (w * h) as f32).ceil() as usize;
    let mut background = vec![false; w * h];
    for (&(y, x0, x1), &l) in runs.iter().zip(&labels) {
        if on_edge[l] || area[l] >= large {
            background[y * w + x0..y * w + x1].fill(true);
        }
    }
    Some((background, Backdrop { chroma, border_share, threshold }))
}

/// What is left of a mask (255 = object) once plain regions are keyed out: an opening
/// removes the thin textured lines their edges leave, pieces under [`PIECE_SHARE`] of the
/// largest are dropped, and an erosion takes back the texture window's spread.
fn clean(mask: &mut [u8], w: usize, h: usize) {
    morph(mask, w, h, OPEN_RADIUS, false);
    morph(mask, w, h, OPEN_RADIUS, true);
    // Pieces far smaller than the largest: what the opening left of edges and outlines.
    let object: Vec<bool> = mask.iter().map(|&m| m != 0).collect();
    let (runs, labels, count) = components(&object, w, h, true);
    let mut area = vec![0usize; count];
    for (&(_, x0, x1), &l) in runs.iter().zip(&labels) {
        area[l] += x1 - x0;
    }
    let least = (PIECE_SHARE * area.iter().copied().max().unwrap_or(0) as f32).ceil() as usize;
    for (&(y, x0, x1), &l) in runs.iter().zip(&labels) {
        if area[l] < least {
            mask[y * w + x0..y * w + x1].fill(0);
        }
    }
    morph(mask, w, h, WINDOW, false);
}

/// Keys a plain backdrop out of an interleaved RGB image (module docs): the mask (255 =
/// object) and how it was keyed; None where the border is not plain ([`plain`]).
pub fn key(rgb: &[u8], w: usize, h: usize) -> Option<(Vec<u8>, Backdrop)> {
    let (background, b) = plain(rgb, w, h)?;
    let mut mask: Vec<u8> = background.iter().map(|&g| if g { 0 } else { 255 }).collect();
    clean(&mut mask, w, h);
    Some((mask, b))
}

/// Keys the plain regions out of a colour key's `mask` too — a grey floor or turntable that
/// the colour leaves, reaching the image's edge — and cleans it as [`key`] does; None (and
/// `mask` as it was) where the border is not plain.
pub fn key_within(rgb: &[u8], w: usize, h: usize, mask: &mut [u8]) -> Option<Backdrop> {
    let (background, b) = plain(rgb, w, h)?;
    for (m, &g) in mask.iter_mut().zip(&background) {
        if g {
            *m = 0;
        }
    }
    clean(mask, w, h);
    Some(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Run labels against a flood fill written out, on random masks, 4- and 8-connected.
    #[test]
    fn components_are_the_flood_fills() {
        let mut next = crate::testing::xorshift(0xbac_d409);
        for (w, h) in [(1, 1), (1, 9), (9, 1), (17, 13), (40, 31)] {
            for eight in [false, true] {
                let set: Vec<bool> = (0..w * h).map(|_| next() % 5 < 2).collect();
                let (runs, labels, count) = components(&set, w, h, eight);
                let mut label = vec![usize::MAX; w * h];
                for (&(y, x0, x1), &l) in runs.iter().zip(&labels) {
                    label[y * w + x0..y * w + x1].fill(l);
                }
                // Every set pixel labelled, nothing else; neighbours share labels exactly
                // when a flood from one reaches the other.
                let mut seen = vec![false; w * h];
                let mut floods = 0;
                for start in 0..w * h {
                    assert_eq!(set[start], label[start] != usize::MAX);
                    if !set[start] || seen[start] {
                        continue;
                    }
                    floods += 1;
                    let mut stack = vec![start];
                    seen[start] = true;
                    while let Some(i) = stack.pop() {
                        assert_eq!(label[i], label[start], "{w}×{h}, eight {eight}");
                        let (x, y) = ((i % w) as i64, (i / w) as i64);
                        for (dx, dy) in [(-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, -1), (-1, 1), (1, 1)].into_iter().take(if eight { 8 } else { 4 }) {
                            let (nx, ny) = (x + dx, y + dy);
                            if nx < 0 || ny < 0 || nx >= w as i64 || ny >= h as i64 {
                                continue;
                            }
                            let j = ny as usize * w + nx as usize;
                            if set[j] && !seen[j] {
                                seen[j] = true;
                                stack.push(j);
                            }
                        }
                    }
                }
                assert_eq!(count, floods, "{w}×{h}, eight {eight}");
            }
        }
    }

    /// The texture is the windowed variance of the smoothed luma: 0 on a plain image, the
    /// variance written out on a ramp.
    #[test]
    fn texture_is_the_windows_variance() {
        let (w, h) = (12, 9);
        let plain = vec![90u8; 3 * w * h];
        assert!(texture(&plain, w, h).iter().all(|&v| v == 0.0));
        // A ramp of 4 levels a column: smoothing keeps it inside; a full 5-wide window holds
        // 4 · (−2…2), variance 16 · 2 = 32.
        let ramp: Vec<u8> = (0..w * h).flat_map(|i| [(20 + 4 * (i % w)) as u8; 3]).collect();
        let var = texture(&ramp, w, h);
        assert!((var[4 * w + 5] - 32.0).abs() < 1e-3, "{}", var[4 * w + 5]);
    }

    /// A lab in grey: a shaded, noisy backdrop; a plain turntable top ringed by a darker rim,
    /// inside the view; a textured ball above it (on a post the colour of the backdrop: edges
    /// that touch the object stay with it, docs/segmentation.md).
    fn grey_lab(w: usize, h: usize, noise: u64) -> (Vec<u8>, impl Fn(f32, f32) -> f32) {
        let mut next = crate::testing::xorshift(0x9e3_1ab);
        let (cx, cy, radius) = (w as f32 / 2.0, h as f32 * 0.4, h as f32 * 0.2);
        // Signed distance outside the ball (negative inside).
        let ball = move |x: f32, y: f32| ((x - cx).powi(2) + (y - cy).powi(2)).sqrt() - radius;
        let texture: Vec<u8> = (0..(w / 3 + 1) * (h / 3 + 1)).map(|_| 60 + (next() % 140) as u8).collect();
        let mut img = Vec::with_capacity(3 * w * h);
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f32, y as f32);
                let table = ((fx - cx) / (w as f32 * 0.35)).powi(2) + ((fy - h as f32 * 0.78) / (h as f32 * 0.09)).powi(2);
                let rim = ((fx - cx) / (w as f32 * 0.35)).powi(2) + ((fy - h as f32 * 0.78 - 8.0) / (h as f32 * 0.09)).powi(2);
                let v = if ball(fx, fy) < 0.0 {
                    texture[(y / 3) * (w / 3 + 1) + x / 3] as f32
                } else if table <= 1.0 {
                    104.0
                } else if rim <= 1.0 {
                    62.0
                } else {
                    78.0 + 16.0 * fx / w as f32
                };
                let jitter = if noise > 0 { (next() % (2 * noise + 1)) as f32 - noise as f32 } else { 0.0 };
                img.extend([(v + jitter).clamp(0.0, 255.0) as u8; 3]);
            }
        }
        (img, ball)
    }

    /// The ball is kept, and only the ball: the backdrop, the table top and its rim are keyed
    /// out; the silhouette is right to within two pixels; noise on the frame raises the
    /// threshold.
    #[test]
    fn a_plain_backdrop_keys_out_all_but_the_object() {
        let (w, h) = (160, 120);
        for noise in [0, 6] {
            let (img, ball) = grey_lab(w, h, noise);
            let (mask, b) = key(&img, w, h).expect("a plain border");
            assert!(b.border_share > 0.95 && (b.chroma.0 - 1.0 / 3.0).abs() < 1e-3, "{b:?}");
            assert!(if noise == 0 { b.threshold == MIN_TEXTURE } else { b.threshold > MIN_TEXTURE }, "noise {noise}: {b:?}");
            let mut wrong = Vec::new();
            for y in 0..h {
                for x in 0..w {
                    let d = ball(x as f32, y as f32);
                    let object = mask[y * w + x] != 0;
                    if (d < -2.0 && !object) || (d > 2.0 && object) {
                        wrong.push((x, y, d));
                    }
                }
            }
            let inside = wrong.iter().filter(|p| p.2 < 0.0).count();
            let far = wrong.iter().map(|p| p.2.abs()).fold(0.0, f32::max);
            let ys: Vec<usize> = wrong.iter().map(|p| p.1).collect();
            assert!(wrong.is_empty(), "noise {noise}: {} pixels wrong ({inside} inside), farthest {far}, rows {:?}..{:?}", wrong.len(), ys.iter().min(), ys.iter().max());
        }
    }

    /// A textured background (a cluttered room; an object over the whole border) is no
    /// backdrop; a white one behind a colour object is.
    #[test]
    fn only_a_plain_border_is_a_backdrop() {
        let (w, h) = (96, 72);
        let mut next = crate::testing::xorshift(0x7e47);
        let busy: Vec<u8> = (0..w * h).flat_map(|_| [(next() % 256) as u8; 3]).collect();
        assert!(key(&busy, w, h).is_none());
        let mut white = vec![225u8; 3 * w * h];
        for y in 20..50 {
            for x in 30..70 {
                let v = (next() % 120) as u8;
                white[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&[v + 100, v / 2 + 40, v / 3]);
            }
        }
        let (mask, b) = key(&white, w, h).expect("a plain white border");
        assert!(b.border_share > 0.99, "{b:?}");
        let kept: usize = mask.iter().filter(|&&m| m != 0).count();
        // The 40 × 30 block, give or take a pixel around it (the texture window and the
        // smoothing spread it by three, the final erosion takes two back).
        assert!(kept >= 38 * 28 && kept <= 42 * 32, "{kept}");
        assert!(mask[35 * w + 50] != 0 && mask[5 * w + 5] == 0 && mask[60 * w + 50] == 0);
    }
}

