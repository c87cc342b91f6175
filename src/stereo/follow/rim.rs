//! The disparities of the pixels just inside the silhouette, extrapolated from the band
//! behind them along the rim's own profile.
//!
//! Near an occluding contour the surface turns to meet the view ray, and its depth changes
//! as the square root of the distance from the silhouette: a sphere of radius ρ seen from
//! afar is `√(2ρt)` deep at `t` inside its outline. The pixels near the silhouette are
//! matched, and refined ([`super::refine_following`]), from windows that reach no closer to
//! it than [`super::SILHOUETTE_PX`], and the planes they follow, carried over the last few
//! pixels, lie above the curve: `fr-i30`'s `sgm` maps read +1.03 px at the pixels next to
//! the background on the flank the right camera faces, +0.51 px one further in, +0.24 px two.
//!
//! So each matched pixel within [`RIM_PROFILE_PX`] of the silhouette takes the value at its
//! own distance `t` of `d = c₀ + c₁·u + c₂·√(t − EDGE_PX)`, fitted by least squares to the
//! matched pixels [`RIM_PROFILE_PX`] … [`RIM_SAMPLE_PX`] inside it within [`RIM_FIT_RADIUS`];
//! `u` is the coordinate along the silhouette (across the direction to those samples'
//! centroid). `t` is the chamfer distance from the background ([`Chamfer`]), and `EDGE_PX`
//! where the outline lies on it. A 2 × 2 block of pixels shares one fit, around its top-left
//! pixel.
//!
//! The fit is taken only where the band behind the pixel bends as a surface turning away
//! does: its samples within [`MAX_RMS_PX`] of the curve, its bend [`MIN_BEND_T`] standard
//! errors or more from none and still [`MIN_CURVE_T`] beside a slope along `t`, towards the
//! cameras inwards. A flat face seen up to its edge, a face leaning back to a crease (whose
//! band bends as much by the root alone, but none beside a slope), a faint texture's
//! scattered map keep their matched values.
//!
//! Nor on the flank the right camera sees compressed (the disparity rising along the row,
//! `∂d/∂x` over [`COMPRESSED_SLOPE`]): there the band's values carry the compression's own
//! bias (−0.14 px on `fr-i30`), which the profile would carry to the rim magnified, while the
//! matched values read within 0.17 px there. (docs/matcher.md, "The rim's profile".)

use super::DisparityMap;

/// Pixels closer to the silhouette than this (by the chamfer distance, [`Chamfer`]) take the
/// fitted profile's value; those from it to [`RIM_SAMPLE_PX`] are the fit's samples.
/// Measured over eight recordings of both renderers (views' and models' distances to the
/// true surface, docs/matcher.md, "The rim's profile"): 5 and 6 left some of the bias, 8
/// took too few samples.
pub const RIM_PROFILE_PX: f32 = 6.5;

/// The farthest inside the silhouette a sample of the fit lies, pixels: far enough for the
/// square root's bend to be measured, near enough that the surface's own curvature along it
/// stays small. 12 left the models 1–2 % further, 18 read as 15.
pub const RIM_SAMPLE_PX: f32 = 15.0;

/// Half-side of the square whose samples are fitted, pixels. 6 and 8 left the rim's error
/// further (0.203 and 0.189 px against 0.181 on `fr-i30`'s `sgm` maps, at the first
/// prototype's band), 12 gained 0.001.
pub const RIM_FIT_RADIUS: usize = 10;

/// Where the outline lies, as a chamfer distance: 0.9, just short of the last object pixel's
/// centre (0.955), as the key takes a pixel the object partly covers into the mask. Measured:
/// with 0.9, before the test of [`MIN_CURVE_T`], `fr-i30`'s rim pixels read within 0.05 px of
/// the truth on the faced flank, the top and the bottom, at every distance (docs/matcher.md,
/// "The rim's profile"); 0.5 and 0.7 left the models of eight recordings 0.4–1.8 % further.
const EDGE_PX: f64 = 0.9;

/// The least number of samples for a fit.
const MIN_SAMPLES: f64 = 12.0;

/// The least distance, pixels, from a pixel to its samples' centroid: nearer, the samples
/// surround it (a thin part of the object) and no direction points inwards.
const MIN_CENTROID_PX: f64 = 1.0;

/// The slope of the disparity along the row, px a column, over which the right camera sees
/// the surface compressed (`1 − ∂d/∂x` under 0.95): there the profile is not fitted.
const COMPRESSED_SLOPE: f64 = 0.05;

/// The most a pixel's value is moved, pixels: further, the fit extrapolates something the
/// band does not hold (a fold, a hole's edge).
const MAX_MOVE_PX: f64 = 2.0;

/// The most the samples may scatter about the fitted profile (their RMS residual), pixels:
/// more, and the band is not one surface turning away (a crease, a fold of the outline, a
/// faint texture's noise).
const MAX_RMS_PX: f64 = 0.15;

/// The least bend `c₂`, in its standard errors, for the profile to be taken: a band that
/// barely bends (a large radius, a facet, a crease) is left as matched.
const MIN_BEND_T: f64 = 30.0;

/// The least bend, in its standard errors, of the profile with a slope along `t` beside the
/// root: a flat face leaning back to a crease bends by as much as a surface turning away over
/// the samples' band, but none beside a slope. Measured (docs/matcher.md, "The rim's profile"):
/// 2 left an ideal box's rim within 2 % of its matched values (mean |error|), and kept 70–80 %
/// of the gain on the rims of `fr-i30` and `fr-i13` (median |error|).
const MIN_CURVE_T: f64 = 2.0;

/// The side of the blocks of pixels that share one fit, and where in its block the fit's
/// window is centred (its anchor, that many pixels right of and below the block's corner).
/// Blocks of 4 × 4 (anchored one pixel in) took 40 % less time, but left the models of 26
/// recordings 0.1–0.2 % further (geometric mean; up to 1.5 %) and one more view of `sgm`
/// further than `bm`'s.
const BLOCK: usize = 2;
const ANCHOR: usize = 0;

/// Lanes of a window row's sums: the square's `2·RIM_FIT_RADIUS + 1` columns in chunks of 8.
const LANES: usize = 8;
const CHUNKS: usize = (2 * RIM_FIT_RADIUS + 1).div_ceil(LANES);

/// What the rim's pass looked at and what it moved.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RimStats {
    /// Matched pixels within [`RIM_PROFILE_PX`] of the silhouette.
    pub looked: usize,
    /// Of those, the ones given the profile's value.
    pub profiled: usize,
    /// Of those looked at, the ones left on the compressed flank.
    pub compressed: usize,
}

/// Gives the matched pixels within [`RIM_PROFILE_PX`] of the silhouette the rim's profile
/// (see the module's documentation). `rim`: each pixel's distance inside the silhouette, as
/// [`crate::segment::rim_distance`] gives it (0 on the background, 1 and more on the object),
/// the map's size.
/// `disparity_sign`: +1 where the disparity grows as the surface comes nearer (the rectified
/// right camera right of the left one), −1 where it falls
/// ([`crate::stereo::rectify::Rectification::disparity_sign`]).
pub fn extrapolate_rim(disp: &mut DisparityMap, rim: &[u8], disparity_sign: i32) -> RimStats {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        return unsafe { extrapolate_avx2(disp, rim, disparity_sign) };
    }
    extrapolate(disp, rim, disparity_sign, false)
}

/// [`extrapolate_rim`] compiled for AVX2: the window rows' sums in eight lanes at once.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn extrapolate_avx2(disp: &mut DisparityMap, rim: &[u8], disparity_sign: i32) -> RimStats {
    extrapolate(disp, rim, disparity_sign, true)
}

/// The samples of a region, each array `rw × rh`, zero where a pixel is not a sample.
struct Samples {
    rw: usize,
    /// 1 at a sample.
    weight: Vec<f32>,
    /// `s = √(t − EDGE_PX)`.
    s: Vec<f32>,
    /// The disparity less the region's reference.
    d: Vec<f32>,
    /// The distance `t` itself.
    t: Vec<f32>,
    /// Each region row's columns from its first sample to its last (empty: none). The
    /// windows' passes skip the chunks outside them: a non-sample adds zeros to every sum.
    spans: Vec<std::ops::Range<usize>>,
}

impl Samples {
    /// Whether chunk `c` of the window row starting at region index `row_start` may hold a
    /// sample.
    #[inline(always)]
    fn may_hold(&self, row_start: usize, c: usize) -> bool {
        let (ry, col) = (row_start / self.rw, row_start % self.rw + c * LANES);
        let span = &self.spans[ry];
        col < span.end && col + LANES > span.start
    }
}

/// Each pixel's distance from the background over a box of the image, by the 3 × 3 chamfer
/// of Borgefors (steps of 0.955 along a row or column and 1.369 along a diagonal, OpenCV's
/// `DIST_L2` with a 3 × 3 mask), kept in thousandths of a pixel: within 4 % of the Euclidean
/// distance whatever the silhouette's direction, where the chessboard distance
/// ([`crate::segment::rim_distance`]) counts a diagonal step as 1 and puts a 45° edge's
/// pixels at 0.7 × their distance, two rows of them at each step.
struct Chamfer {
    xs: std::ops::Range<usize>,
    ys: std::ops::Range<usize>,
    d: Vec<u32>,
}

impl Chamfer {
    /// The steps in thousandths of a pixel.
    const STEP: u32 = 955;
    const AXIAL: f32 = Self::STEP as f32 * 1e-3;
    const DIAGONAL_STEP: u32 = 1369;

    /// The distances over `xs × ys` of an image `w` wide whose background is where `rim` is
    /// 0. Beyond the box is taken as the object: the box must hold every background pixel
    /// that is nearest to a pixel whose distance is read.
    fn over(rim: &[u8], w: usize, xs: std::ops::Range<usize>, ys: std::ops::Range<usize>) -> Chamfer {
        let (bw, bh) = (xs.len(), ys.len());
        // A frame of one pixel around the box, beyond the background (u32's top: the sums of
        // steps saturate there).
        let far = u32::MAX;
        let stride = bw + 2;
        let mut d = vec![far; stride * (bh + 2)];
        for (y, src) in ys.clone().map(|y| &rim[y * w + xs.start..y * w + xs.end]).enumerate() {
            for (v, &t) in d[(y + 1) * stride + 1..][..bw].iter_mut().zip(src) {
                *v = if t == 0 { 0 } else { far };
            }
        }
        crate::segment::chamfer_passes(&mut d, bw, bh, Self::STEP, Self::DIAGONAL_STEP);
        Chamfer { xs, ys, d }
    }

    /// The distances of row `y` of the image over `columns`, pixels (inside the box).
    fn row(&self, y: usize, columns: std::ops::Range<usize>) -> impl Iterator<Item = f32> + '_ {
        let from = (y - self.ys.start + 1) * (self.xs.len() + 2) + 1 - self.xs.start;
        self.d[from + columns.start..from + columns.end].iter().map(|&v| v as f32 * 1e-3)
    }

    /// The distance at `(x, y)` of the image (inside the box), pixels.
    fn at(&self, x: usize, y: usize) -> f32 {
        self.d[(y - self.ys.start + 1) * (self.xs.len() + 2) + x - self.xs.start + 1] as f32 * 1e-3
    }
}

/// The sums of a fit over one window: moments of the samples' offsets `x`, `y` from the
/// pixel, of `s` and of the disparity `d`.
#[derive(Default)]
struct Sums {
    n: f64,
    x: f64,
    y: f64,
    xx: f64,
    xy: f64,
    yy: f64,
    s: f64,
    xs: f64,
    ys: f64,
    ss: f64,
    d: f64,
    xd: f64,
    yd: f64,
    sd: f64,
    t: f64,
    xt: f64,
    yt: f64,
    st: f64,
    tt: f64,
    dt: f64,
}

/// The body of [`extrapolate_rim`]; `simd`: the CPU has AVX2 (the windows' sums in
/// [`avx2`]'s registers).
#[inline(always)]
fn extrapolate(disp: &mut DisparityMap, rim: &[u8], disparity_sign: i32, simd: bool) -> RimStats {
    let (w, h) = (disp.width, disp.height);
    assert_eq!(rim.len(), w * h, "a rim distance of the map's size");
    let r = RIM_FIT_RADIUS;
    // The box of the pixels within RIM_PROFILE_PX of the silhouette (matched or not): the
    // chamfer distance is never under 0.955 × the chessboard's.
    let within = (RIM_PROFILE_PX / Chamfer::AXIAL) as u8;
    let near = |t: u8| t.wrapping_sub(1) < within;
    let (mut x0, mut x1, mut y0, mut y1) = (usize::MAX, 0, usize::MAX, 0);
    for (y, row) in rim.chunks_exact(w.max(1)).enumerate() {
        // (A pass without an early exit, which vectorises, before the scalar searches.)
        if row.iter().fold(false, |any, &t| any | near(t)) {
            let first = row.iter().position(|&t| near(t)).unwrap_or(0);
            let last = row.iter().rposition(|&t| near(t)).unwrap_or(0);
            (x0, x1, y0, y1) = (x0.min(first), x1.max(last), y0.min(y), y1.max(y));
        }
    }
    let mut stats = RimStats::default();
    if x0 == usize::MAX {
        return stats;
    }
    // Each BLOCK × BLOCK block of pixels (from columns and rows that are multiples of it) is
    // fitted once, around its anchor, the pixel ANCHOR right of and below its corner. The
    // samples over the anchors' windows: a margin of r rows and columns, and a chunk's more
    // on the right, of non-samples, so that every window is whole chunks inside it.
    let (bx0, by0) = (x0 / BLOCK * BLOCK, y0 / BLOCK * BLOCK);
    let (ox, oy) = ((bx0 + ANCHOR) as isize - r as isize, (by0 + ANCHOR) as isize - r as isize);
    let rw = x1 - bx0 + 1 + 2 * r + LANES;
    let rh = y1 - by0 + 1 + 2 * r;
    // The distances over the samples' box and the background within RIM_SAMPLE_PX of it
    // (a sample's nearest background pixel is within RIM_SAMPLE_PX / 0.955 of it, by the
    // chessboard).
    let pad = r + (RIM_SAMPLE_PX / Chamfer::AXIAL) as usize + 2;
    let dist = Chamfer::over(rim, w, bx0.saturating_sub(pad)..(x1 + pad + 1).min(w), by0.saturating_sub(pad)..(y1 + pad + 1).min(h));
    let values = disp.values();
    // The disparities less a reference, the first sample's (the region's disparities lie
    // within a few tens of it): the sums in f32 keep their precision.
    let mut reference = f32::NAN;
    let mut smp = Samples { rw, weight: vec![0.0; rw * rh], s: vec![0.0; rw * rh], d: vec![0.0; rw * rh], t: vec![0.0; rw * rh], spans: vec![0..0; rh] };
    // The region's columns inside the image (all inside the distances' box), and where they
    // start in the region's rows.
    let columns = ox.max(0) as usize..((ox + rw as isize) as usize).min(w);
    let skip = (columns.start as isize - ox) as usize;
    for ry in 0..rh {
        let y = ry as isize + oy;
        if y < 0 || y >= h as isize {
            continue;
        }
        let y = y as usize;
        let from = ry * rw + skip;
        for (i, (&v, t)) in values[y * w + columns.start..y * w + columns.end].iter().zip(dist.row(y, columns.clone())).enumerate() {
            if (RIM_PROFILE_PX..=RIM_SAMPLE_PX).contains(&t) && !v.is_nan() {
                if reference.is_nan() {
                    reference = v;
                }
                let s = (t - EDGE_PX as f32).sqrt();
                let d = v - reference;
                let k = from + i;
                (smp.weight[k], smp.s[k], smp.d[k], smp.t[k]) = (1.0, s, d, t);
                let (col, span) = (k - ry * rw, &mut smp.spans[ry]);
                *span = if span.start == span.end { col..col + 1 } else { span.start..col + 1 };
            }
        }
    }
    let vals = disp.values_mut();
    let nearer = disparity_sign.signum() as f64;
    for ay in (by0..=y1).step_by(BLOCK) {
        for ax in (bx0..=x1).step_by(BLOCK) {
            // The block's pixels to be given the profile (first by the chessboard distance,
            // which most blocks of the box fail).
            let candidate = |i: usize| {
                let (x, y) = (ax + i % BLOCK, ay + i / BLOCK);
                x < w && y < h && near(rim[y * w + x])
            };
            if !(0..BLOCK * BLOCK).any(candidate) {
                continue;
            }
            let block: [Option<(usize, f32)>; BLOCK * BLOCK] = std::array::from_fn(|i| {
                let (x, y) = (ax + i % BLOCK, ay + i / BLOCK);
                let (k, t) = (y * w + x, if x < w && y < h { dist.at(x, y) } else { 0.0 });
                (t > 0.0 && t < RIM_PROFILE_PX && !vals[k].is_nan()).then_some((k, t))
            });
            let looked = block.iter().flatten().count();
            if looked == 0 {
                continue;
            }
            stats.looked += looked;
            if reference.is_nan() {
                // No samples anywhere.
                continue;
            }
            // The anchor's window's top-left corner in the region.
            let corner = (ay - by0) * rw + (ax - bx0);
            let sums = window_sums(&smp, corner, simd);
            let p = match profile_of(&sums) {
                Fit::Profile(p) => p,
                Fit::Compressed => {
                    stats.compressed += looked;
                    continue;
                }
                Fit::None => continue,
            };
            if !p.holds(residual_sums(&smp, corner, &p, simd), sums.n, nearer) {
                continue;
            }
            for (i, &(k, t)) in block.iter().enumerate().filter_map(|(i, b)| b.as_ref().map(|b| (i, b))) {
                let (dx, dy) = ((i % BLOCK) as f64 - ANCHOR as f64, (i / BLOCK) as f64 - ANCHOR as f64);
                let v = p.at(dx, dy, t) + reference as f64;
                if (v - vals[k] as f64).abs() <= MAX_MOVE_PX {
                    vals[k] = v as f32;
                    stats.profiled += 1;
                }
            }
        }
    }
    stats
}

/// The sums over the window whose top-left corner is at `corner` of the region (the pixel at
/// its centre, `RIM_FIT_RADIUS` right and down). `simd`: the CPU has AVX2.
#[inline(always)]
fn window_sums(smp: &Samples, corner: usize, simd: bool) -> Sums {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: `simd` is only set on a CPU with AVX2; the window's rows lie in the region
    // (its margins, `extrapolate`).
    let acc = if simd { unsafe { avx2::window_lanes(smp, corner) } } else { window_lanes(smp, corner) };
    #[cfg(not(target_arch = "x86_64"))]
    let acc = { let _ = simd; window_lanes(smp, corner) };
    let t: [f64; SUMS] = std::array::from_fn(|k| acc[k].iter().map(|&v| v as f64).sum());
    Sums { n: t[0], x: t[1], y: t[2], xx: t[3], xy: t[4], yy: t[5], s: t[6], xs: t[7], ys: t[8], ss: t[9], d: t[10], xd: t[11], yd: t[12], sd: t[13], t: t[14], xt: t[15], yt: t[16], st: t[17], tt: t[18], dt: t[19] }
}

/// How many sums a window's fit takes.
const SUMS: usize = 20;

/// Each lane's x offset from the window's centre, and whether it lies in the window (1 or 0),
/// chunk by chunk.
fn lane_offsets() -> ([[f32; LANES]; CHUNKS], [[f32; LANES]; CHUNKS]) {
    let r = RIM_FIT_RADIUS;
    let xs = std::array::from_fn(|c| std::array::from_fn(|i| (c * LANES + i) as f32 - r as f32));
    let mask = std::array::from_fn(|c| std::array::from_fn(|i| if c * LANES + i <= 2 * r { 1.0 } else { 0.0 }));
    (xs, mask)
}

/// The window's sums lane by lane, in the order of [`Sums`]' fields: each lane adds its column
/// of each chunk, row after row. [`avx2::window_lanes`] does the same operations in the same
/// order.
fn window_lanes(smp: &Samples, corner: usize) -> [[f32; LANES]; SUMS] {
    let r = RIM_FIT_RADIUS;
    let (xs, mask) = lane_offsets();
    let mut acc = [[0f32; LANES]; SUMS];
    for dy in 0..=2 * r {
        let yv = dy as f32 - r as f32;
        let row = corner + dy * smp.rw;
        for c in (0..CHUNKS).filter(|&c| smp.may_hold(row, c)) {
            let o = row + c * LANES;
            for i in 0..LANES {
                let (m, x) = (mask[c][i], xs[c][i]);
                let (wt, s, d, t) = (smp.weight[o + i] * m, smp.s[o + i] * m, smp.d[o + i] * m, smp.t[o + i] * m);
                let (wx, wy) = (wt * x, wt * yv);
                acc[0][i] += wt;
                acc[1][i] += wx;
                acc[2][i] += wy;
                acc[3][i] += wx * x;
                acc[4][i] += wx * yv;
                acc[5][i] += wy * yv;
                acc[6][i] += s;
                acc[7][i] += s * x;
                acc[8][i] += s * yv;
                acc[9][i] += s * s;
                acc[10][i] += d;
                acc[11][i] += d * x;
                acc[12][i] += d * yv;
                acc[13][i] += s * d;
                acc[14][i] += t;
                acc[15][i] += t * x;
                acc[16][i] += t * yv;
                acc[17][i] += s * t;
                acc[18][i] += t * t;
                acc[19][i] += d * t;
            }
        }
    }
    acc
}

enum Fit {
    Profile(Profile),
    /// The pixel lies on the flank the right camera sees compressed.
    Compressed,
    /// Too few samples, or samples that do not fix the fit.
    None,
}

/// A rim's profile fitted around a pixel: `d = c₀ + c₁·u + c₂·√(t − EDGE_PX)` (less the
/// region's reference), `u = along · (x, y)` the samples' offset along the silhouette; and
/// the same with a slope along `t` too, `k₀ + k₁·u + k₂·√(t − EDGE_PX) + k₃·t`, whose bend
/// tells a surface turning away from a flat face seen up to a crease.
struct Profile {
    c: [f64; 3],
    along: (f64, f64),
    /// The bend's diagonal element (the last) of the fit's inverse normal matrix: the bend's
    /// variance over the residuals' variance.
    bend_var: f64,
    sloped: [f64; 4],
    /// The bend's diagonal element (the third) of the sloped fit's inverse normal matrix: the
    /// bend's variance over the residuals' variance.
    sloped_bend_var: f64,
}

impl Profile {
    /// The profile's value at the pixel `(dx, dy)` from the window's centre, `t` inside the
    /// silhouette.
    fn at(&self, dx: f64, dy: f64, t: f32) -> f64 {
        let [c0, c1, c2] = self.c;
        c0 + c1 * (self.along.0 * dx + self.along.1 * dy) + c2 * (t as f64 - EDGE_PX).sqrt()
    }

    /// Whether the samples follow the profile (`rss` and `sloped_rss`, the sums of their
    /// squared residuals from the profile and from the sloped one, of `n` samples): within
    /// [`MAX_RMS_PX`] of it, with a bend [`MIN_BEND_T`] times its standard error or more, a
    /// bend still [`MIN_CURVE_T`] times its own beside a slope, and both towards the cameras
    /// inwards (an outline's surface comes nearer inside it): `nearer` is the sign of the
    /// disparity's change as it does.
    fn holds(&self, (rss, sloped_rss): (f64, f64), n: f64, nearer: f64) -> bool {
        let var = rss.max(0.0) / n;
        if var > MAX_RMS_PX * MAX_RMS_PX {
            return false;
        }
        let var_c2 = var * self.bend_var;
        let c2 = self.c[2];
        let bent = c2 * c2 >= MIN_BEND_T * MIN_BEND_T * var_c2 && c2 * nearer > 0.0;
        // Beside a slope, on n − 4 degrees of freedom.
        let k2 = self.sloped[2];
        let var_k2 = sloped_rss.max(0.0) / (n - 4.0) * self.sloped_bend_var;
        bent && k2 * k2 >= MIN_CURVE_T * MIN_CURVE_T * var_k2 && k2 * nearer > 0.0
    }
}

/// The sums of the window's samples' squared residuals from `p`'s profile and from its
/// profile with a slope (the window at `corner`, as [`window_sums`] takes it). A second
/// pass, since the residuals are small differences of sums that f32 lanes do not keep.
#[inline(always)]
fn residual_sums(smp: &Samples, corner: usize, p: &Profile, simd: bool) -> (f64, f64) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: as in `window_sums`.
    let acc = if simd { unsafe { avx2::residual_lanes(smp, corner, p) } } else { residual_lanes(smp, corner, p) };
    #[cfg(not(target_arch = "x86_64"))]
    let acc = {
        let _ = simd;
        residual_lanes(smp, corner, p)
    };
    let sum = |a: &[f32; LANES]| a.iter().map(|&v| v as f64).sum();
    (sum(&acc[0]), sum(&acc[1]))
}

/// A model's terms as the residuals' lanes take them: the constant, the slope along x and
/// along y (`c₁·along`), the bend's and the slope's along `t`.
#[derive(Clone, Copy)]
struct Terms {
    c0: f32,
    cx: f32,
    cy: f32,
    cs: f32,
    ct: f32,
}

impl Terms {
    fn of(p: &Profile) -> [Terms; 2] {
        let [c0, c1, c2] = p.c;
        let [k0, k1, k2, k3] = p.sloped;
        let (a, b) = p.along;
        [
            Terms { c0: c0 as f32, cx: (c1 * a) as f32, cy: (c1 * b) as f32, cs: c2 as f32, ct: 0.0 },
            Terms { c0: k0 as f32, cx: (k1 * a) as f32, cy: (k1 * b) as f32, cs: k2 as f32, ct: k3 as f32 },
        ]
    }
}

/// [`residual_sums`]' squared residuals lane by lane, the profile's and the sloped one's
/// ([`avx2::residual_lanes`] in the same order).
fn residual_lanes(smp: &Samples, corner: usize, p: &Profile) -> [[f32; LANES]; 2] {
    let r = RIM_FIT_RADIUS;
    let (xs, mask) = lane_offsets();
    let terms = Terms::of(p);
    let mut acc = [[0f32; LANES]; 2];
    for dy in 0..=2 * r {
        let row = corner + dy * smp.rw;
        for (m, k) in terms.iter().enumerate() {
            let uy = k.c0 + k.cy * (dy as f32 - r as f32);
            for c in (0..CHUNKS).filter(|&c| smp.may_hold(row, c)) {
                let o = row + c * LANES;
                for i in 0..LANES {
                    // Non-samples hold zeros: their residual is 0.
                    let fit = smp.weight[o + i] * (uy + k.cx * xs[c][i]);
                    let e = (smp.d[o + i] - fit - k.cs * smp.s[o + i] - k.ct * smp.t[o + i]) * mask[c][i];
                    acc[m][i] += e * e;
                }
            }
        }
    }
    acc
}

#[cfg(target_arch = "x86_64")]
mod avx2;

/// The rim's profile fitted to a window's sums.
fn profile_of(m: &Sums) -> Fit {
    if m.n < MIN_SAMPLES {
        return Fit::None;
    }
    // Inwards: towards the samples' centroid.
    let (cx, cy) = (m.x / m.n, m.y / m.n);
    let len = cx.hypot(cy);
    if len < MIN_CENTROID_PX {
        return Fit::None;
    }
    // The plane through the samples, for its slope along the row.
    let Some([[_, slope_x, _]]) = solve3([[m.n, m.x, m.y], [m.x, m.xx, m.xy], [m.y, m.xy, m.yy]], [[m.d, m.xd, m.yd]]) else { return Fit::None };
    if slope_x > COMPRESSED_SLOPE {
        return Fit::Compressed;
    }
    // u, along the silhouette.
    let (a, b) = (-cy / len, cx / len);
    let u = a * m.x + b * m.y;
    let uu = a * a * m.xx + 2.0 * a * b * m.xy + b * b * m.yy;
    let us = a * m.xs + b * m.ys;
    let ud = a * m.xd + b * m.yd;
    let h = [[m.n, u, m.s], [u, uu, us], [m.s, us, m.ss]];
    // The fit and, from the right-hand side (0, 0, 1), the bend's diagonal element of the
    // inverse normal matrix: one solve of the two.
    let Some([c, unit3]) = solve3(h, [[m.d, ud, m.sd], [0.0, 0.0, 1.0]]) else { return Fit::None };
    // The same with a slope along t.
    let ut = a * m.xt + b * m.yt;
    let h4 = [[m.n, u, m.s, m.t], [u, uu, us, ut], [m.s, us, m.ss, m.st], [m.t, ut, m.st, m.tt]];
    let Some([sloped, unit]) = solve4(h4, [[m.d, ud, m.sd, m.dt], [0.0, 0.0, 1.0, 0.0]]) else { return Fit::None };
    Fit::Profile(Profile { c, along: (a, b), bend_var: unit3[2], sloped, sloped_bend_var: unit[2] })
}

/// Solves the 4 × 4 system `a·x = b` for each right-hand side `b` by Gaussian elimination with
/// partial pivoting, the matrix eliminated once; `None` where it is nearly singular. (Each
/// right-hand side takes the operations a solve of it alone would: the same bits.)
fn solve4<const R: usize>(mut a: [[f64; 4]; 4], mut b: [[f64; 4]; R]) -> Option<[[f64; 4]; R]> {
    let scale = a.iter().flatten().fold(0f64, |m, v| m.max(v.abs()));
    for col in 0..4 {
        let pivot = (col..4).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if !(a[pivot][col].abs() > 1e-12 * scale) {
            return None;
        }
        a.swap(col, pivot);
        for rhs in &mut b {
            rhs.swap(col, pivot);
        }
        for row in col + 1..4 {
            let f = a[row][col] / a[col][col];
            for k in col..4 {
                a[row][k] -= f * a[col][k];
            }
            for rhs in &mut b {
                rhs[row] -= f * rhs[col];
            }
        }
    }
    Some(b.map(|rhs| {
        let mut x = [0f64; 4];
        for row in (0..4).rev() {
            let rest: f64 = (row + 1..4).map(|k| a[row][k] * x[k]).sum();
            x[row] = (rhs[row] - rest) / a[row][row];
        }
        x
    }))
}

/// Solves the symmetric 3 × 3 system `a·x = b` for each right-hand side `b` by Cramer's rule,
/// the determinant taken once; `None` where it is nearly singular.
fn solve3<const R: usize>(a: [[f64; 3]; 3], b: [[f64; 3]; R]) -> Option<[[f64; 3]; R]> {
    let det = |m: [[f64; 3]; 3]| m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    let d = det(a);
    let scale = a[0][0] * a[1][1] * a[2][2];
    if !(d.abs() > 1e-9 * scale.abs()) {
        return None;
    }
    Some(b.map(|rhs| {
        std::array::from_fn(|k| {
            let mut m = a;
            for (row, &v) in m.iter_mut().zip(&rhs) {
                row[k] = v;
            }
            det(m) / d
        })
    }))
}

#[cfg(test)]
mod tests;
