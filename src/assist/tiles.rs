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

use super::region::{interval, MaskRows, Region};
use super::{AssistMode, AssistModeError, Plan};
use crate::stereo::{DisparityIntervals, BAND_TILE};

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
    /// What measured fastest for the mode: tiles for `predicted` (no per-pixel map to
    /// build), pixels for `paper` (its union of spheres is taken per pixel either way).
    #[default]
    Auto,
    /// Every pixel its own interval (the rule as written).
    Pixel,
    /// One interval per plan tile (16 × 8 pixels, a quarter of the matcher's): the hull of its
    /// pixels' intervals.
    Tile,
}

impl Granularity {
    pub fn name(&self) -> &'static str {
        match self {
            Granularity::Auto => "auto",
            Granularity::Pixel => "pixel",
            Granularity::Tile => "tile",
        }
    }

    pub fn parse(name: &str) -> Result<Granularity, AssistModeError> {
        match name {
            "auto" => Ok(Granularity::Auto),
            "pixel" => Ok(Granularity::Pixel),
            "tile" => Ok(Granularity::Tile),
            other => Err(AssistModeError::Granularity(other.to_string())),
        }
    }

    /// `Pixel` or `Tile`: what `Auto` means for `mode`.
    pub fn resolve(self, mode: AssistMode) -> Granularity {
        match (self, mode) {
            (Granularity::Auto, AssistMode::Predicted) => Granularity::Tile,
            (Granularity::Auto, _) => Granularity::Pixel,
            (g, _) => g,
        }
    }
}

/// Per tile of the image: the hull `lo..=hi` of the bounds splatted into it, and how many
/// of its pixels are foreground.
#[derive(Clone, Default, PartialEq, Debug)]
pub(super) struct TileBounds {
    cols: usize,
    rows: usize,
    lo: Vec<f32>,
    hi: Vec<f32>,
    fg: Vec<u32>,
}

impl TileBounds {
    /// Empties every tile of a `w × h` image.
    pub(super) fn reset(&mut self, w: usize, h: usize) {
        (self.cols, self.rows) = (w.div_ceil(TW), h.div_ceil(TH));
        let n = self.cols * self.rows;
        for (v, fill) in [(&mut self.lo, f32::INFINITY), (&mut self.hi, f32::NEG_INFINITY)] {
            v.clear();
            v.resize(n, fill);
        }
        self.fg.clear();
        self.fg.resize(n, 0);
    }

    pub(super) fn cols(&self) -> usize {
        self.cols
    }

    /// Foreground pixels counted in the tiles over `region`.
    pub(super) fn fg_total(&self, region: &Region) -> usize {
        let (tx, ty) = (region.x0 / TW..region.x1.div_ceil(TW), region.y0 / TH..region.y1.div_ceil(TH));
        ty.flat_map(|y| tx.clone().map(move |x| (x, y))).map(|(x, y)| self.fg[y * self.cols + x] as usize).sum()
    }

    /// Widens tile `t`'s hull to hold `a..=b`.
    #[inline(always)]
    pub(super) fn add(&mut self, t: usize, a: f32, b: f32) {
        self.lo[t] = self.lo[t].min(a);
        self.hi[t] = self.hi[t].max(b);
    }

    /// The tiles of the 2 × 2 pixels from `(x, y)`, given as [`splat_tile`] gives them (the
    /// tile of `(x, y)` and the next tile column and row the pixels cross into): widened to
    /// hold `a..=b`.
    #[inline(always)]
    pub(super) fn add_splat(&mut self, t: usize, crosses: u32, a: f32, b: f32) {
        let (right, down) = (crosses & RIGHT != 0, crosses & DOWN != 0);
        self.add(t, a, b);
        if right {
            self.add(t + 1, a, b);
        }
        if down {
            self.add(t + self.cols, a, b);
            if right {
                self.add(t + self.cols + 1, a, b);
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
                // Branch-free, so that it vectorises.
                let (mut a, mut b, mut count) = (f32::INFINITY, f32::NEG_INFINITY, 0u32);
                for ((&m, &l), &u) in m.iter().zip(&lo[k.clone()]).zip(&hi[k]) {
                    let here = m != 0;
                    a = a.min(if here { l } else { f32::INFINITY });
                    b = b.max(if here { u } else { f32::NEG_INFINITY });
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

    /// The intervals: every foreground pixel of `region` its tile's hull (see the module
    /// docs), written into `iv`; counts filled and full-range pixels into the plan.
    pub(super) fn intervals(&self, iv: &mut DisparityIntervals, masks: &MaskRows, region: &Region, range: (i32, i32), plan: &mut Plan) {
        let n = self.cols * self.rows;
        // Per tile: its clipped hull, or its neighbours' widened, or the full range.
        let mut bands = vec![(1i16, 0i16); n];
        let (ty0, ty1) = (region.y0 / TH, region.y1.div_ceil(TH));
        let (tx0, tx1) = (region.x0 / TW, region.x1.div_ceil(TW));
        for ty in ty0..ty1 {
            for tx in tx0..tx1 {
                let t = ty * self.cols + tx;
                if self.fg[t] == 0 {
                    continue;
                }
                let (a, b) = match interval(range, self.lo[t], self.hi[t]) {
                    Some(own) => own,
                    None => {
                        let (mut a, mut b) = (f32::INFINITY, f32::NEG_INFINITY);
                        for ny in ty.saturating_sub(1)..(ty + 2).min(self.rows) {
                            for nx in tx.saturating_sub(1)..(tx + 2).min(self.cols) {
                                let u = ny * self.cols + nx;
                                if interval(range, self.lo[u], self.hi[u]).is_some() {
                                    (a, b) = (a.min(self.lo[u]), b.max(self.hi[u]));
                                }
                            }
                        }
                        match (a <= b).then(|| interval(range, a - MARGIN, b + MARGIN)).flatten() {
                            Some(filled) => {
                                plan.filled_px += self.fg[t] as usize;
                                filled
                            }
                            None => {
                                plan.uncovered_px += self.fg[t] as usize;
                                range
                            }
                        }
                    }
                };
                bands[t] = (a as i16, b as i16);
            }
        }
        // Per tile row: its tiles' bands spread over the region's columns once, then each of
        // its pixel rows written in one pass (branch-free and element-wise, so that it
        // vectorises).
        let n = region.x1 - region.x0;
        let (mut row_a, mut row_b) = (vec![1i16; n], vec![0i16; n]);
        for (ty, ys) in tile_rows(region) {
            for (xs, t) in segments(region) {
                let (a, b) = bands[ty * self.cols + t];
                row_a[xs.start - region.x0..xs.end - region.x0].fill(a);
                row_b[xs.start - region.x0..xs.end - region.x0].fill(b);
            }
            for y in ys {
                let (out_lo, out_hi) = iv.row_mut(y);
                let pixels = masks.row(y).iter().zip(&mut out_lo[region.xs()]).zip(&mut out_hi[region.xs()]);
                for (((&m, l), u), (&a, &b)) in pixels.zip(row_a.iter().zip(&row_b)) {
                    (*l, *u) = if m != 0 { (a, b) } else { (1, 0) };
                }
            }
        }
    }
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

    #[test]
    fn splats_on_tile_corners_reach_every_tile_they_touch() {
        let mut t = TileBounds::default();
        t.reset(3 * TW, 3 * TH);
        let (tile, crosses) = splat_tile(TW as u32 - 1, TH as u32 - 1, t.cols() as u32);
        assert_eq!((tile, crosses), (0, RIGHT | DOWN));
        t.add_splat(tile as usize, crosses, 10.0, 12.0);
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
