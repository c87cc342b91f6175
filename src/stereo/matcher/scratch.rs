//! The sizes and per-thread buffers every stripe of one matcher call shares.

use std::ops::Range;

use super::source::IntervalSource;
use crate::stereo::params::ValidMatchParams;

/// Below this many disparities a from-scratch window sum runs per entry (scalar) instead of
/// per window line (vectorised).
pub(super) const NARROW: usize = 8;

/// Window sums are computed over whole blocks of this many disparities (clipped to the valid
/// range) around each searched interval: one AVX2 register of costs. Neighbouring pixels
/// whose narrow intervals differ slightly then share a range and slide, instead of
/// recomputing window sums from scratch at every shift.
pub(super) const BLOCK: usize = 16;
// Rounding a disparity index down to its block is a mask.
const _: () = assert!(BLOCK.is_power_of_two());

/// Bytes of slack before and after the prefiltered rows: the tile kernel loads sixteen
/// columns at a time, and the last chunk of a tile (or a tile that runs past the image's
/// right edge) may reach past the rows' ends; those lanes are never used.
pub(super) const PF_SLACK: usize = 64;

/// The prefiltered rows with their slack: the left rows (`wp` apart) and the reversed right
/// rows (`wr` apart), each starting [`PF_SLACK`] bytes into its buffer.
#[derive(Clone, Copy)]
pub(super) struct Slack<'a> {
    pub(super) left: &'a [u8],
    pub(super) right: &'a [u8],
}

/// Tile width, pixels.
pub(super) const TILE_W: usize = 32;
/// Tile height, rows.
pub(super) const TILE_H: usize = 16;

/// Where a tile's window sums stand: its band `lo..=hi` and the row they are valid for.
#[derive(Clone, Copy, PartialEq, Default)]
pub(super) struct TileSums {
    pub(super) lo: i32,
    pub(super) hi: i32,
    /// The row the sums hold (usize::MAX: none).
    pub(super) row: usize,
}

/// Sizes shared by every stripe of one call.
#[derive(Clone, Copy)]
pub(super) struct Geometry {
    pub(super) w: usize,
    pub(super) h: usize,
    pub(super) r: usize,
    /// Padded width of the prefiltered left rows (`w + 2r`).
    pub(super) wp: usize,
    pub(super) n: usize,
    pub(super) dmin: i32,
    /// Replicated padding of the prefiltered right rows on the left and right: wide enough
    /// for every disparity at every column, so that window sums may be computed over whole
    /// blocks even where the right pixel falls outside the image (those pairs are never
    /// searched).
    pub(super) rpad_left: usize,
    pub(super) rpad_right: usize,
}

impl Geometry {
    /// The sizes of matching a `w × h` pair with these parameters.
    pub(super) fn new(p: &ValidMatchParams, w: usize, h: usize) -> Geometry {
        let r = p.radius();
        let (dmin, dmax) = (p.min_disparity, p.max_disparity());
        Geometry {
            w,
            h,
            r,
            wp: w + 2 * r,
            n: p.num_disparities as usize,
            dmin,
            rpad_left: r + dmax.max(0) as usize,
            rpad_right: r + (-dmin).max(0) as usize,
        }
    }

    /// Width of a padded right row.
    pub(super) fn wr(&self) -> usize {
        self.w + self.rpad_left + self.rpad_right
    }
}

/// A `u16` buffer whose contents start on a 64-byte boundary, so that the column and window
/// sums (rows of 16-lane multiples) are read with aligned vector loads: a load that splits
/// a cache line costs extra, and a plain `Vec` gives no alignment guarantee beyond 16 bytes.
#[derive(Default)]
pub(super) struct AlignedBuf {
    pub(super) buf: Vec<u16>,
    pub(super) start: usize,
    pub(super) len: usize,
}

impl AlignedBuf {
    pub(super) const ALIGN: usize = 64;

    /// Makes the buffer `len` long. Contents are not kept: callers overwrite before reading.
    pub(super) fn resize(&mut self, len: usize, value: u16) {
        let slack = Self::ALIGN / std::mem::size_of::<u16>();
        if self.buf.len() < len + slack {
            self.buf = vec![value; len + slack];
        }
        let misalign = self.buf.as_ptr() as usize % Self::ALIGN;
        self.start = if misalign == 0 { 0 } else { (Self::ALIGN - misalign) / std::mem::size_of::<u16>() };
        self.len = len;
    }
}

impl std::ops::Deref for AlignedBuf {
    type Target = [u16];
    fn deref(&self) -> &[u16] {
        &self.buf[self.start..self.start + self.len]
    }
}

impl std::ops::DerefMut for AlignedBuf {
    fn deref_mut(&mut self) -> &mut [u16] {
        &mut self.buf[self.start..self.start + self.len]
    }
}

/// What every stripe of one call reads: parameters, sizes, the prefiltered rows (left
/// padded, right padded and reversed) and the search intervals.
#[derive(Clone, Copy)]
pub(super) struct StripeInput<'a> {
    pub(super) p: &'a ValidMatchParams,
    pub(super) g: Geometry,
    pub(super) lpf: &'a [u8],
    pub(super) rrev: &'a [u8],
    pub(super) intervals: IntervalSource<'a>,
    /// The same rows with the slack around them, for the narrow-band path's chunked loads.
    pub(super) slack: Slack<'a>,
}

impl<'a> StripeInput<'a> {
    /// The input of the prefiltered buffers `left` and `right` (rows with
    /// [`PF_SLACK`] bytes around them, as `prefilter_xsobel` writes them).
    pub(super) fn new(p: &'a ValidMatchParams, g: Geometry, left: &'a [u8], right: &'a [u8], intervals: IntervalSource<'a>) -> Self {
        let (nl, nr) = (g.h * g.wp, g.h * g.wr());
        assert!(left.len() == nl + 2 * PF_SLACK && right.len() == nr + 2 * PF_SLACK, "prefiltered rows of another size");
        StripeInput {
            p,
            g,
            lpf: &left[PF_SLACK..PF_SLACK + nl],
            rrev: &right[PF_SLACK..PF_SLACK + nr],
            intervals,
            slack: Slack { left, right },
        }
    }
}

/// Per-thread buffers, grown to fit and reused across frames.
#[derive(Default)]
pub(super) struct StripeScratch {
    /// Vertical window sums, `wp × n`, column-major in disparity.
    pub(super) cs: AlignedBuf,
    /// Band of valid entries per column (empty when lo > hi).
    pub(super) band_lo: Vec<i32>,
    pub(super) band_hi: Vec<i32>,
    pub(super) need_lo: Vec<i32>,
    pub(super) need_hi: Vec<i32>,
    /// This row's searched intervals, in disparity index `k = d − dmin`.
    pub(super) tlo: Vec<i32>,
    pub(super) thi: Vec<i32>,
    /// The block-aligned ranges the window sums are computed over (⊇ the searched ones).
    pub(super) ilo: Vec<i32>,
    pub(super) ihi: Vec<i32>,
    /// Window sums of the current row, `w × n`.
    pub(super) sad: AlignedBuf,
    /// Cheapest evaluated cost of each right pixel, stored reversed: entry `w − 1 − x + k`
    /// is right pixel `x − dmin − k`, so a left pixel's run of disparities is contiguous.
    pub(super) right_min: Vec<u16>,
    pub(super) best: Vec<Option<(u16, f32)>>,
    /// The narrow-band path's winners of the row, per pixel (whole tiles): disparity index,
    /// cost, whether kept (all ones) before the left–right check, sub-pixel offset.
    pub(super) win_k: Vec<u16>,
    pub(super) win_cost: Vec<u16>,
    pub(super) win_keep: Vec<u16>,
    pub(super) win_frac: Vec<f32>,
    pub(super) tex_col: Vec<u32>,
    /// Window texture of each pixel of the row.
    pub(super) tex_row: Vec<u32>,
    pub(super) band_tmp: Vec<i32>,
    pub(super) prev_ilo: Vec<i32>,
    pub(super) prev_ihi: Vec<i32>,
    /// The bands of the current tile row's tiles.
    pub(super) tile_lo: Vec<i32>,
    pub(super) tile_hi: Vec<i32>,
    /// The clipped intervals of the current tile row's rows, `w` apart, written over each
    /// row's columns in `clip_spans` alone (`rows::clip_row`).
    pub(super) clip_lo: Vec<i32>,
    pub(super) clip_hi: Vec<i32>,
    pub(super) clip_spans: Vec<Range<usize>>,
    /// Searched pixels per tile of the current tile row.
    pub(super) tile_px: Vec<u32>,
    /// Per column of a tile row: the min, max and count of its searched intervals (three
    /// rows of `w`).
    pub(super) tile_cols: Vec<i32>,
    /// The narrow-band path's vertical window sums: per tile and disparity index, its
    /// columns and their halo (`tiles::tile_cols`; only the tile's band is used).
    pub(super) tile_v: AlignedBuf,
    /// The narrow-band path's costs of the current row: per tile and disparity index, one
    /// per pixel of the tile (`tiles::cost_index`).
    pub(super) tile_cost: AlignedBuf,
    pub(super) tile_sums: Vec<TileSums>,
    /// The narrow-band path's copies of the forward right-row minima (see `tiles::tile_row`;
    /// the first holds the merged minima after a row).
    pub(super) tile_right: Vec<u16>,
}


/// The row of the window that sits `dy` rows from `y`, clamped to the image.
#[inline(always)]
pub(super) fn clamp_row(y: isize, h: usize) -> usize {
    y.clamp(0, h as isize - 1) as usize
}
