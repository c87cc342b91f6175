//! Tile granularity (`--assist-granularity tile`): one search interval per plan tile ([`TW`] ×
//! [`TH`] = 16 × 8 pixels, counted from the image's corner: a quarter of the matcher's
//! [`BAND_TILE`]), the hull of the intervals the mode's rule gives the tile's pixels.
//!
//! The matcher's narrow-band path sums costs over its tile's band anyway (the union of its
//! pixels' intervals, for every pixel of the tile in vector lanes); what a per-pixel interval adds is
//! the masking of each pixel inside that band — and a per-pixel map to build. Plan tiles a
//! quarter of the matcher's keep part of that masking at the cost of the tiles alone. At tile
//! resolution the predicted mode needs no per-pixel map at all: every previous point's
//! prediction goes straight into the hull of the tile (or tiles) its 2 × 2 splat lands on,
//! O(points). The paper mode splats its two cases per pixel as before (the union of case 2
//! is taken per pixel, exactly) and reduces them per tile.
//!
//! Every foreground pixel of a tile searches the tile's hull, clipped and rounded outwards
//! (so a pixel no interval reached searches what its tile's other pixels search). A tile with
//! foreground but no interval at all takes the hull of its eight neighbours' hulls widened by
//! 2 px; only where those are empty too, the full range.
//!
//! Plane granularity (`--assist-granularity plane`, the predicted mode's default) sets the
//! same hulls about a plane per tile, fitted to the previous frame's disparities in it
//! ([`TileBounds::fit_planes`]): each bound is taken less the plane where it lands, and each
//! pixel searches the hull plus the plane at that pixel. A flat hull adds the surface's slant
//! across the tile to every pixel (2 disparities on average on a 640 × 480 turntable frame,
//! 0.3–0.5 about a plane); `bm`'s uniqueness test and left–right check then reject more
//! (docs/assisted-matching.md, "Seventeenth pass"). Flat tiles are planes of zero slope.

use super::region::{interval, prefetch_row, MaskRows, Region, PREFETCH_ROWS};
use super::{AssistMode, AssistModeError, Plan};
use crate::stereo::{DisparityIntervals, DisparityMap, BAND_TILE};

/// A plan tile's width and height: a quarter of the matcher's tile ([`BAND_TILE`], 32 × 16),
/// so that each matcher tile is 2 × 2 plan tiles. The matcher sums costs over its tile's
/// band either way; finer plan tiles give each pixel a narrower interval inside that band (the
/// selection's rivals and the left–right check see fewer disparities), and SGM fewer blocks.
/// Measured against plan tiles of the matcher's own size (docs/assisted-matching.md,
/// "Fourteenth pass"): the predicted row's bad2 fell by 0.3–0.4 points on the egg and the vase,
/// and the plan takes no longer with the tiles counted and written per tile row.
pub(super) const TW: usize = 16;
pub(super) const TH: usize = 8;
const _: () = assert!(TW.is_power_of_two() && TH.is_power_of_two() && BAND_TILE.0 % TW == 0 && BAND_TILE.1 % TH == 0, "plan tiles nest in the matcher's tiles");
/// A tile filled from its neighbours takes their hull widened by this much, pixels (as a
/// pixel's hole fill does).
const MARGIN: f32 = 2.0;

/// How finely the assisted search range is set.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Granularity {
    /// What measured best for the mode: sloped tiles (`Plane`) for `predicted` (no per-pixel
    /// map to build, and as few disparities per pixel as its own intervals), pixels for
    /// `paper` (its union of spheres is taken per pixel either way).
    #[default]
    Auto,
    /// Every pixel its own interval (the rule as written).
    Pixel,
    /// One interval per plan tile (16 × 8 pixels, a quarter of the matcher's): the hull of its
    /// pixels' intervals.
    Tile,
    /// One sloped interval per plan tile: a plane through the tile (its slant across the tile
    /// fitted to the previous frame's disparities there) plus the hull of its pixels'
    /// intervals about that plane, so that a slanted surface's tile searches about as few
    /// disparities per pixel as its pixels' own intervals.
    Plane,
}

impl Granularity {
    pub fn name(&self) -> &'static str {
        match self {
            Granularity::Auto => "auto",
            Granularity::Pixel => "pixel",
            Granularity::Tile => "tile",
            Granularity::Plane => "plane",
        }
    }

    pub fn parse(name: &str) -> Result<Granularity, AssistModeError> {
        match name {
            "auto" => Ok(Granularity::Auto),
            "pixel" => Ok(Granularity::Pixel),
            "tile" => Ok(Granularity::Tile),
            "plane" => Ok(Granularity::Plane),
            other => Err(AssistModeError::Granularity(other.to_string())),
        }
    }

    /// Whether the intervals are set per plan tile (`Tile`, `Plane`).
    pub fn tiled(self) -> bool {
        matches!(self, Granularity::Tile | Granularity::Plane)
    }

    /// `Pixel`, `Tile` or `Plane`: what `Auto` means for `mode`.
    pub fn resolve(self, mode: AssistMode) -> Granularity {
        match (self, mode) {
            (Granularity::Auto, AssistMode::Predicted) => Granularity::Plane,
            (Granularity::Auto, _) => Granularity::Pixel,
            (g, _) => g,
        }
    }
}

/// Per tile of the image: its plane `gx·x + gy·y + k` (zero but at [`Granularity::Plane`]),
/// the hull `lo..=hi` of the bounds splatted into it less the plane where each landed, and how
/// many of its pixels are foreground. A pixel `(x, y)` of the tile searches
/// `lo + plane(x, y) ..= hi + plane(x, y)`.
#[derive(Clone, Default, PartialEq, Debug)]
pub(super) struct TileBounds {
    cols: usize,
    rows: usize,
    lo: Vec<f32>,
    hi: Vec<f32>,
    /// `[gx, gy, k]` per tile.
    plane: Vec<[f32; 3]>,
    fg: Vec<u32>,
}

/// The steepest slant a tile's plane takes, disparities per pixel: beyond it a fit spans a
/// depth edge rather than a surface, and a flat hull serves better.
const MAX_SLOPE: f32 = 4.0;
/// The fewest previous disparities a tile's plane is fitted to.
const MIN_FIT_PX: u32 = 12;

impl TileBounds {
    /// Empties every tile of a `w × h` image.
    pub(super) fn reset(&mut self, w: usize, h: usize) {
        (self.cols, self.rows) = (w.div_ceil(TW), h.div_ceil(TH));
        let n = self.cols * self.rows;
        for (v, fill) in [(&mut self.lo, f32::INFINITY), (&mut self.hi, f32::NEG_INFINITY)] {
            v.clear();
            v.resize(n, fill);
        }
        self.plane.clear();
        self.plane.resize(n, [0.0; 3]);
        self.fg.clear();
        self.fg.resize(n, 0);
    }

    /// Each tile's plane, fitted by least squares to the previous frame's disparities in it
    /// (`prev`, inside `region`): the surface's slant across the tile changes little from one
    /// frame to the next. A tile with fewer than [`MIN_FIT_PX`] of them, whose pixels lie on
    /// one line, or whose slant passes [`MAX_SLOPE`] keeps a flat plane.
    #[inline(always)]
    pub(super) fn fit_planes(&mut self, prev: &DisparityMap, region: &Region) {
        let w = prev.width;
        let values = prev.values();
        // Per tile: n, Σx, Σy, Σd, Σxx, Σxy, Σyy, Σxd, Σyd, about the tile's corner. Per
        // tile row, each column's n, Σy, Σd, Σyy, Σyd over its rows first (element-wise along
        // the row, branch-free, so that it vectorises), then the tiles' sums of their columns.
        let mut sums = vec![[0f32; 9]; self.cols * self.rows];
        let n = region.x1 - region.x0;
        // (One array per sum, so that the loop over the row vectorises.)
        let (mut cn, mut cy, mut cd, mut cyy, mut cyd) = (vec![0f32; n], vec![0f32; n], vec![0f32; n], vec![0f32; n], vec![0f32; n]);
        for (ty, ys) in tile_rows(region) {
            for c in [&mut cn, &mut cy, &mut cd, &mut cyy, &mut cyd] {
                c.fill(0.0);
            }
            for y in ys {
                prefetch_row(values, w, region.xs(), y + PREFETCH_ROWS, region.y1);
                let fy = (y - ty * TH) as f32;
                let row = &values[y * w + region.x0..y * w + region.x1];
                let (row, cn, cy, cd, cyy, cyd) = (&row[..n], &mut cn[..n], &mut cy[..n], &mut cd[..n], &mut cyy[..n], &mut cyd[..n]);
                for k in 0..n {
                    let d = row[k];
                    let (v, d) = if d.is_nan() { (0.0, 0.0) } else { (1.0, d) };
                    cn[k] += v;
                    cy[k] += v * fy;
                    cd[k] += d;
                    cyy[k] += v * (fy * fy);
                    cyd[k] += d * fy;
                }
            }
            for (xs, tx) in segments(region) {
                let acc = &mut sums[ty * self.cols + tx];
                let ks = xs.start - region.x0..xs.end - region.x0;
                if ks.len() == TW {
                    // A whole tile's columns: sums and moments in vector lanes.
                    let col = |c: &[f32]| -> [f32; TW] { c[ks.clone()].try_into().expect("a tile's columns") };
                    let (n, sy, sd) = (col(&cn), col(&cy), col(&cd));
                    *acc = [sum_tile(n), dot_tile(n, COL_X), sum_tile(sy), sum_tile(sd), dot_tile(n, COL_XX), dot_tile(sy, COL_X), sum_tile(col(&cyy)), dot_tile(sd, COL_X), sum_tile(col(&cyd))];
                    continue;
                }
                for x in xs {
                    let k = x - region.x0;
                    let (n, sy, sd, syy, syd) = (cn[k], cy[k], cd[k], cyy[k], cyd[k]);
                    let fx = (x - tx * TW) as f32;
                    for (a, v) in acc.iter_mut().zip([n, fx * n, sy, sd, fx * fx * n, fx * sy, syy, fx * sd, syd]) {
                        *a += v;
                    }
                }
            }
        }
        for (t, [n, sx, sy, sd, sxx, sxy, syy, sxd, syd]) in sums.into_iter().enumerate() {
            if n < MIN_FIT_PX as f32 {
                continue;
            }
            // Centred moments, then the 2 × 2 normal equations of the slopes.
            let (mx, my, md) = (sx / n, sy / n, sd / n);
            let (cxx, cxy, cyy, cxd, cyd) = (sxx - sx * mx, sxy - sx * my, syy - sy * my, sxd - sx * md, syd - sy * md);
            let det = cxx * cyy - cxy * cxy;
            if !(det > 1e-3 * n * n) {
                continue;
            }
            let (gx, gy) = ((cxd * cyy - cyd * cxy) / det, (cyd * cxx - cxd * cxy) / det);
            if !(gx.abs() <= MAX_SLOPE && gy.abs() <= MAX_SLOPE) {
                continue;
            }
            // About the image's origin: plane(x, y) = gx·x + gy·y + k, zero at the fit's
            // centroid (the hull about it carries the level).
            let (x0, y0) = (((t % self.cols) * TW) as f32 + mx, ((t / self.cols) * TH) as f32 + my);
            self.plane[t] = [gx, gy, -(gx * x0 + gy * y0)];
        }
    }

    /// Tile `t`'s plane at `(x, y)`.
    #[inline(always)]
    pub(super) fn plane_at(&self, t: usize, x: f32, y: f32) -> f32 {
        let [gx, gy, k] = self.plane[t];
        gx * x + gy * y + k
    }

    /// Sets tile `t`'s plane (tests of the splat against it).
    #[cfg(test)]
    pub(super) fn set_plane(&mut self, t: usize, plane: [f32; 3]) {
        self.plane[t] = plane;
    }

    /// Tile `t`'s plane: `[gx, gy, k]`.
    #[inline(always)]
    pub(super) fn plane(&self, t: usize) -> [f32; 3] {
        self.plane[t]
    }

    /// The least and the most tile `t`'s plane takes over its pixels.
    fn plane_span(&self, t: usize) -> (f32, f32) {
        let [gx, gy, _] = self.plane[t];
        let (x0, y0) = (((t % self.cols) * TW) as f32, ((t / self.cols) * TH) as f32);
        let mid = self.plane_at(t, x0 + (TW - 1) as f32 / 2.0, y0 + (TH - 1) as f32 / 2.0);
        let reach = gx.abs() * (TW - 1) as f32 / 2.0 + gy.abs() * (TH - 1) as f32 / 2.0;
        (mid - reach, mid + reach)
    }

    pub(super) fn cols(&self) -> usize {
        self.cols
    }

    /// Foreground pixels counted in the tiles over `region`.
    pub(super) fn fg_total(&self, region: &Region) -> usize {
        let (tx, ty) = (region.x0 / TW..region.x1.div_ceil(TW), region.y0 / TH..region.y1.div_ceil(TH));
        ty.flat_map(|y| tx.clone().map(move |x| (x, y))).map(|(x, y)| self.fg[y * self.cols + x] as usize).sum()
    }

    /// Widens tile `t`'s hull to hold `a..=b`, already taken about its plane.
    #[inline(always)]
    pub(super) fn add(&mut self, t: usize, a: f32, b: f32) {
        self.lo[t] = self.lo[t].min(a);
        self.hi[t] = self.hi[t].max(b);
    }

    /// Widens tile `t`'s hull to hold `a..=b` at `(x, y)`: about the plane there.
    #[inline(always)]
    pub(super) fn add_at(&mut self, t: usize, x: f32, y: f32, a: f32, b: f32) {
        let o = self.plane_at(t, x, y);
        self.add(t, a - o, b - o);
    }

    /// The tiles of the 2 × 2 pixels from `(⌊x⌋, ⌊y⌋)`, given as [`splat_tile`] gives them (the
    /// tile of `(x, y)` and the next tile column and row the pixels cross into): widened to
    /// hold `a..=b` at `(x, y)`.
    #[inline(always)]
    pub(super) fn add_splat(&mut self, t: usize, crosses: u32, x: f32, y: f32, a: f32, b: f32) {
        let (right, down) = (crosses & RIGHT != 0, crosses & DOWN != 0);
        self.add_at(t, x, y, a, b);
        if right {
            self.add_at(t + 1, x, y, a, b);
        }
        if down {
            self.add_at(t + self.cols, x, y, a, b);
            if right {
                self.add_at(t + self.cols + 1, x, y, a, b);
            }
        }
    }

    /// Widens each tile over `region` to hold the per-pixel bounds `lo`/`hi` (row-major,
    /// `w` wide) of its foreground pixels, and counts them.
    pub(super) fn reduce(&mut self, lo: &[f32], hi: &[f32], masks: &MaskRows, w: usize, region: &Region) {
        for y in region.ys() {
            let m_row = masks.row(y);
            let trow = y / TH * self.cols;
            for (xs, t) in segments(region) {
                let (m, k) = (&m_row[xs.start - region.x0..xs.end - region.x0], y * w + xs.start..y * w + xs.end);
                // About the tile's plane (flat but at `Plane` granularity); branch-free, so
                // that it vectorises.
                let [gx, gy, c] = self.plane[trow + t];
                let row_o = gy * y as f32 + c;
                let (mut a, mut b, mut count) = (f32::INFINITY, f32::NEG_INFINITY, 0u32);
                for (((&m, &l), &u), x) in m.iter().zip(&lo[k.clone()]).zip(&hi[k]).zip(xs) {
                    let here = m != 0;
                    let o = gx * x as f32 + row_o;
                    a = a.min(if here { l - o } else { f32::INFINITY });
                    b = b.max(if here { u - o } else { f32::NEG_INFINITY });
                    count += here as u32;
                }
                self.add(trow + t, a, b);
                self.fg[trow + t] += count;
            }
        }
    }

    /// Counts the foreground pixels of each tile over `region`.
    pub(super) fn count(&mut self, masks: &MaskRows, region: &Region) {
        // Per tile row: each column's foreground count over its rows (element-wise over the
        // row, so that it vectorises), then the tiles' sums of their columns.
        let mut cols = vec![0u16; region.x1 - region.x0];
        for (ty, ys) in tile_rows(region) {
            cols.fill(0);
            for y in ys {
                for (c, &m) in cols.iter_mut().zip(masks.row(y)) {
                    *c += (m != 0) as u16;
                }
            }
            for (xs, t) in segments(region) {
                self.fg[ty * self.cols + t] += cols[xs.start - region.x0..xs.end - region.x0].iter().map(|&c| c as u32).sum::<u32>();
            }
        }
    }

    /// The intervals: every foreground pixel of `region` its tile's hull about the tile's
    /// plane (see the module docs), written into `iv`; counts filled and full-range pixels
    /// into the plan.
    #[inline(always)]
    pub(super) fn intervals(&self, iv: &mut DisparityIntervals, masks: &MaskRows, region: &Region, range: (i32, i32), plan: &mut Plan) {
        let n = self.cols * self.rows;
        // A tile's hull over its pixels (its plane's least and most added), when it has one.
        let extent = |t: usize| {
            let (p0, p1) = self.plane_span(t);
            interval(range, self.lo[t] + p0, self.hi[t] + p1).map(|_| (self.lo[t] + p0, self.hi[t] + p1))
        };
        // Per tile: its own hull about its plane (`[lo, hi, gx, gy, k]`), or its neighbours'
        // widened and flat, or the full range; pixels of a band clipped to the range.
        let mut bands = vec![[1.0f32, 0.0, 0.0, 0.0, 0.0]; n];
        let (ty0, ty1) = (region.y0 / TH, region.y1.div_ceil(TH));
        let (tx0, tx1) = (region.x0 / TW, region.x1.div_ceil(TW));
        for ty in ty0..ty1 {
            for tx in tx0..tx1 {
                let t = ty * self.cols + tx;
                if self.fg[t] == 0 {
                    continue;
                }
                bands[t] = match extent(t) {
                    Some(_) => {
                        let [gx, gy, k] = self.plane[t];
                        [self.lo[t], self.hi[t], gx, gy, k]
                    }
                    None => {
                        let (mut a, mut b) = (f32::INFINITY, f32::NEG_INFINITY);
                        for ny in ty.saturating_sub(1)..(ty + 2).min(self.rows) {
                            for nx in tx.saturating_sub(1)..(tx + 2).min(self.cols) {
                                if let Some((l, u)) = extent(ny * self.cols + nx) {
                                    (a, b) = (a.min(l), b.max(u));
                                }
                            }
                        }
                        let (a, b) = match (a <= b).then(|| interval(range, a - MARGIN, b + MARGIN)).flatten() {
                            Some(filled) => {
                                plan.filled_px += self.fg[t] as usize;
                                filled
                            }
                            None => {
                                plan.uncovered_px += self.fg[t] as usize;
                                range
                            }
                        };
                        [a as f32, b as f32, 0.0, 0.0, 0.0]
                    }
                };
            }
        }
        // Per tile row: its tiles' bands spread over the region's columns once (each
        // column's bounds at row 0, and the rows' slant), then each of its pixel rows written
        // in one pass (branch-free and element-wise, so that it vectorises).
        let n = region.x1 - region.x0;
        let (mut row_a, mut row_b, mut row_gy) = (vec![1f32; n], vec![0f32; n], vec![0f32; n]);
        let (r0, r1) = (range.0 as f32, range.1 as f32);
        for (ty, ys) in tile_rows(region) {
            for (xs, t) in segments(region) {
                let [a, b, gx, gy, k] = bands[ty * self.cols + t];
                for (x, ((ra, rb), rg)) in xs.clone().zip(row_a[xs.start - region.x0..xs.end - region.x0].iter_mut().zip(&mut row_b[xs.start - region.x0..xs.end - region.x0]).zip(&mut row_gy[xs.start - region.x0..xs.end - region.x0])) {
                    let o = gx * x as f32 + k;
                    (*ra, *rb, *rg) = (a + o, b + o, gy);
                }
            }
            for y in ys {
                let (out_lo, out_hi) = iv.row_cols_mut(y, region.xs());
                let fy = y as f32;
                let pixels = masks.row(y).iter().zip(out_lo.iter_mut()).zip(out_hi.iter_mut());
                for (((&m, l), u), ((&a, &b), &gy)) in pixels.zip(row_a.iter().zip(&row_b).zip(&row_gy)) {
                    // Rounded outwards inside the range (a band is never empty there; flat
                    // bands are in whole disparities already).
                    let (a, b) = ((a + gy * fy).clamp(r0, r1), (b + gy * fy).clamp(r0, r1));
                    // SAFETY: clamped into the range, far inside i16.
                    let (ta, tb) = unsafe { (a.to_int_unchecked::<i32>(), b.to_int_unchecked::<i32>()) };
                    let (fa, cb) = (ta - (a < ta as f32) as i32, tb + (b > tb as f32) as i32);
                    (*l, *u) = if m != 0 { (fa as i16, cb as i16) } else { (1, 0) };
                }
            }
        }
    }
}

/// A tile's columns, from its left edge, and their squares.
const COL_X: [f32; TW] = {
    let mut x = [0.0; TW];
    let mut i = 0;
    while i < TW {
        x[i] = i as f32;
        i += 1;
    }
    x
};
const COL_XX: [f32; TW] = {
    let mut x = [0.0; TW];
    let mut i = 0;
    while i < TW {
        x[i] = (i * i) as f32;
        i += 1;
    }
    x
};

/// The sum of a tile's columns, pairwise (element-wise halves, so that it vectorises).
#[inline(always)]
fn sum_tile(mut a: [f32; TW]) -> f32 {
    let mut n = TW;
    while n > 1 {
        n /= 2;
        for i in 0..n {
            a[i] += a[i + n];
        }
    }
    a[0]
}

/// `Σ a·b` over a tile's columns.
#[inline(always)]
fn dot_tile(a: [f32; TW], b: [f32; TW]) -> f32 {
    sum_tile(std::array::from_fn(|i| a[i] * b[i]))
}

/// The region's tile rows: each one's index and its pixel rows inside the region.
fn tile_rows(region: &Region) -> impl Iterator<Item = (usize, std::ops::Range<usize>)> + '_ {
    (region.y0 / TH..region.y1.div_ceil(TH)).map(move |ty| (ty, (ty * TH).max(region.y0)..((ty + 1) * TH).min(region.y1)))
}

/// The columns of `region` cut at tile boundaries, with each piece's tile column.
fn segments(region: &Region) -> impl Iterator<Item = (std::ops::Range<usize>, usize)> + '_ {
    (region.x0 / TW..region.x1.div_ceil(TW)).map(move |t| ((t * TW).max(region.x0)..((t + 1) * TW).min(region.x1), t))
}

/// [`splat_tile`]'s bits: the 2 × 2 pixels cross into the next tile column ([`RIGHT`]), the
/// next tile row ([`DOWN`]).
pub(super) const RIGHT: u32 = 1;
pub(super) const DOWN: u32 = 2;

/// The tile of pixel `(x, y)` in a grid `cols` tiles wide, and whether the 2 × 2 pixels from
/// it cross into the next tile column and row ([`RIGHT`], [`DOWN`]). In `u32` and
/// branch-free, so that it vectorises in the loop that projects the points.
#[inline(always)]
pub(super) fn splat_tile(x: u32, y: u32, cols: u32) -> (u32, u32) {
    let (tw, th) = (TW as u32, TH as u32);
    (y / th * cols + x / tw, (x % tw == tw - 1) as u32 * RIGHT | (y % th == th - 1) as u32 * DOWN)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tile_searches_the_hull_of_its_pixels_and_empty_tiles_take_their_neighbours() {
        let (w, h) = (3 * TW, 3 * TH);
        let region = Region { x0: 0, x1: w, y0: 0, y1: h };
        let mut mask = vec![0u8; w * h];
        // Foreground: from a quarter into tile column 0 to an eighth into column 2, and from a
        // quarter into tile row 0 to halfway into row 2.
        let (fx0, fy0) = (TW / 4, TH / 4);
        for y in fy0..2 * TH + TH / 2 {
            mask[y * w + fx0..y * w + 2 * TW + TW / 8].fill(1);
        }
        let (mut lo, mut hi) = (vec![f32::INFINITY; w * h], vec![f32::NEG_INFINITY; w * h]);
        // Tile (0, 0): two pixels with bounds; one background pixel whose bounds must not count.
        (lo[(fy0 + 1) * w + fx0 + 1], hi[(fy0 + 1) * w + fx0 + 1]) = (20.3, 24.6);
        (lo[(TH / 2) * w + TW - 2], hi[(TH / 2) * w + TW - 2]) = (18.5, 21.0);
        (lo[w + 1], hi[w + 1]) = (0.0, 100.0);
        // Tile (1, 0): one pixel.
        (lo[(fy0 + 1) * w + TW + fx0], hi[(fy0 + 1) * w + TW + fx0]) = (50.0, 52.0);
        let masks = MaskRows::new(Some(&mask), w, &region);
        let mut t = TileBounds::default();
        t.reset(w, h);
        t.reduce(&lo, &hi, &masks, w, &region);
        let mut iv = DisparityIntervals::empty(w, h);
        let mut plan = Plan { intervals: DisparityIntervals::empty(0, 0), full_range: None, single_px: 0, union_px: 0, filled_px: 0, uncovered_px: 0, lag: 0, build_ms: 0.0 };
        t.intervals(&mut iv, &masks, &region, (0, 127), &mut plan);
        // Every foreground pixel of tile (0, 0) searches 18..=25; background nothing.
        assert_eq!(iv.get(fx0 + 1, fy0 + 1), Some((18, 25)));
        assert_eq!(iv.get(TW - 1, TH - 1), Some((18, 25)));
        assert_eq!(iv.get(1, 1), None);
        assert_eq!(iv.get(TW + fx0, fy0 + 1), Some((50, 52)));
        // Tile (2, 0) has foreground and no bounds: its neighbours' hull (tile (1, 0) and
        // tiles (1, 1), (2, 1) — empty) widened by 2.
        assert_eq!(iv.get(2 * TW + 1, fy0 + 1), Some((48, 54)));
        // Tile (0, 1): neighbours (0, 0) and (1, 0): 18.5..52 → 16..=54.
        assert_eq!(iv.get(fx0 + 1, TH + 2), Some((16, 54)));
        // Tile (0, 2): its neighbours are tiles of row 1, all empty: full range.
        assert_eq!(iv.get(fx0 + 1, 2 * TH + 1), Some((0, 127)));
        let fg_tile = |tx: usize, ty: usize| (ty * TH..(ty + 1) * TH).flat_map(|y| (tx * TW..(tx + 1) * TW).map(move |x| (x, y))).filter(|&(x, y)| mask[y * w + x] != 0).count();
        assert_eq!(plan.uncovered_px, fg_tile(0, 2) + fg_tile(1, 2) + fg_tile(2, 2));
        assert_eq!(plan.filled_px, fg_tile(2, 0) + fg_tile(0, 1) + fg_tile(1, 1) + fg_tile(2, 1));
    }

    /// Planes come back from the previous disparities where they can; a tile with too few of
    /// them, with all on one row, or slanting past [`MAX_SLOPE`] stays flat; a pixel of a
    /// sloped tile searches the splat's bounds carried along the plane.
    #[test]
    fn planes_follow_the_previous_disparities_and_stay_flat_where_they_cannot() {
        let (w, h) = (3 * TW, 2 * TH);
        let region = Region { x0: 0, x1: w, y0: 0, y1: h };
        let surface = |x: usize, y: usize| 40.3 + 0.5 * x as f32 - 0.25 * y as f32;
        let mut prev = DisparityMap::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let (tx, ty) = (x / TW, y / TH);
                let d = match (tx, ty) {
                    // Tile (0, 0): every pixel on the plane; tile (0, 1): every other one.
                    (0, 0) => Some(surface(x, y)),
                    (0, 1) => ((x + y) % 2 == 0).then(|| surface(x, y)),
                    // Tile (1, 0): too few; tile (2, 0): one row; tile (1, 1): too steep.
                    (1, 0) => (x % TW < 3 && y % TH < 3).then_some(50.0),
                    (2, 0) => (y == 3).then(|| 60.0 + x as f32),
                    (1, 1) => Some(10.0 + 5.0 * (x % TW) as f32),
                    _ => None,
                };
                prev.set(x, y, d);
            }
        }
        let mut t = TileBounds::default();
        t.reset(w, h);
        t.fit_planes(&prev, &region);
        let cols = t.cols();
        for tile in [0, cols] {
            let [gx, gy, _] = t.plane(tile);
            assert!((gx - 0.5).abs() < 1e-4 && (gy + 0.25).abs() < 1e-4, "tile {tile}: {gx}, {gy}");
        }
        for tile in [1, 2, cols + 1, cols + 2] {
            assert_eq!(t.plane(tile), [0.0; 3], "tile {tile} stays flat");
        }
        // One splat in tile (0, 0) at (3.5, 2.5), its bounds ± 1 around the surface there: every
        // foreground pixel of the tile searches the surface ± 1 at that pixel, rounded outwards.
        let mask: Vec<u8> = (0..w * h).map(|i| (i % w < TW && i / w < TH) as u8).collect();
        let masks = MaskRows::new(Some(&mask), w, &region);
        t.count(&masks, &region);
        let at = 40.3 + 0.5 * 3.5 - 0.25 * 2.5;
        t.add_at(0, 3.5, 2.5, at - 1.0, at + 1.0);
        let mut iv = DisparityIntervals::empty(w, h);
        let mut plan = Plan { intervals: DisparityIntervals::empty(0, 0), full_range: None, single_px: 0, union_px: 0, filled_px: 0, uncovered_px: 0, lag: 0, build_ms: 0.0 };
        t.intervals(&mut iv, &masks, &region, (0, 127), &mut plan);
        for y in 0..TH {
            for x in 0..TW {
                let d = surface(x, y);
                assert_eq!(iv.get(x, y), Some(((d - 1.0).floor() as i32, (d + 1.0).ceil() as i32)), "pixel ({x}, {y})");
            }
        }
        assert_eq!(iv.get(TW, 0), None, "background");
    }

    #[test]
    fn splats_on_tile_corners_reach_every_tile_they_touch() {
        let mut t = TileBounds::default();
        t.reset(3 * TW, 3 * TH);
        let (tile, crosses) = splat_tile(TW as u32 - 1, TH as u32 - 1, t.cols() as u32);
        assert_eq!((tile, crosses), (0, RIGHT | DOWN));
        t.add_splat(tile as usize, crosses, (TW - 1) as f32 + 0.5, (TH - 1) as f32 + 0.5, 10.0, 12.0);
        for u in [0, 1, 3, 4] {
            assert_eq!((t.lo[u], t.hi[u]), (10.0, 12.0), "tile {u}");
        }
        assert_eq!(t.lo[2], f32::INFINITY);
        let (tw, th) = (TW as u32, TH as u32);
        assert_eq!(splat_tile(tw + tw / 4, th + th / 4, 3), (4, 0));
        assert_eq!(splat_tile(2 * tw - 1, th + th / 4, 3), (4, RIGHT));
        assert_eq!(splat_tile(tw + tw / 4, 2 * th - 1, 3), (4, DOWN));
    }
}
