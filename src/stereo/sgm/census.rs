//! The census transform and the per-pair matching cost: the Hamming distance of census
//! words plus a capped per-pixel intensity difference.
//!
//! Census compares each pixel of a `CENSUS_W × CENSUS_H` window with the window's centre
//! (one bit: neighbour < centre). It depends only on the order of intensities, so a gain or
//! offset between the two cameras — the lab's cameras are not photometrically matched —
//! does not change it, and an edge costs no more than texture. The window is clamped at the
//! image border (replicated pixels).
//!
//! The intensity term, `min(|I_left − I_right|, cap)`, is what census lacks: the pixel's own
//! level, sharp at depth edges where the census window straddles two surfaces (AD-census,
//! Mei et al. 2011). It is not invariant to the cameras' gain and offset, so the right image
//! is first mapped linearly onto the left's mean and standard deviation: over the pixels the
//! call's intervals say correspond ([`level_map_from_prior`]), else over the whole images
//! ([`level_map`]).

use std::ops::Range;

use crate::stereo::disparity::{searched_span, DisparityIntervals, GrayView};

/// Census window width and height (odd). 7 × 5 − 1 = 34 bits, in a `u64` per pixel: chosen
/// by measurement on the Middlebury pairs (docs/matcher.md) — 9 × 7 was best alone, 7 × 5
/// with the intensity term.
pub(super) const CENSUS_W: usize = 7;
pub(super) const CENSUS_H: usize = 5;
/// Bits of a census word: the most a pair's census cost can be.
pub(super) const MAX_BITS: usize = CENSUS_W * CENSUS_H - 1;

/// The census comparisons of the columns `cols` of `img` (`w × h`, row-major; `cols`
/// non-empty, inside `0..w`), row by row: `emit(y, planes)` receives row `y`'s five byte
/// planes (`cols.len()` bytes each; comparison t at bit t % 8 of plane t / 8), which
/// [`words_row`] or [`split_row`] lay out as the costs read them. The comparisons are those
/// over the whole image: the window reads the pixels beyond `cols` where the image has them,
/// and is clamped at the image's border as there. (Planes, not words: the right census is
/// kept split on AVX2 — its low four planes are its low 32 bits, its fifth the high bits —
/// and words only to be split again were one more pass over memory.)
///
/// `planes_of` makes a row's comparisons: [`planes_row`] or a vector copy of it; `rows` is
/// the caller's buffer for the padded source, reused from call to call.
#[inline(always)]
pub(super) fn transform_cols(img: &[u8], w: usize, h: usize, cols: std::ops::Range<usize>, rows: &mut Vec<u8>, planes_of: impl Fn(&[u8], usize, &mut [u8]), mut emit: impl FnMut(usize, [&[u8]; PLANES])) {
    let (rx, ry) = (CENSUS_W / 2, CENSUS_H / 2);
    let cw = cols.len();
    assert!(cw > 0 && cols.end <= w, "census columns {cols:?} of an image {w} wide");
    // The source rows' columns `cols` with rx more on each side (replicated where they pass
    // the image's edge), so the inner loop has no branch, and above and below by ry
    // replicated rows: each output row's window is `CENSUS_H` consecutive rows of it (the
    // image copied once, not once per window row). Kept in `rows` between calls; every byte
    // is written below, so it is not cleared.
    let wp = cw + 2 * rx;
    let (left_rep, right_rep) = (rx.saturating_sub(cols.start), (cols.end + rx).saturating_sub(w));
    let src = cols.start + left_rep - rx..cols.end + rx - right_rep;
    rows.resize(wp * (h + 2 * ry), 0);
    let padded = &mut rows[..wp * (h + 2 * ry)];
    for (j, dst) in padded.chunks_mut(wp).enumerate() {
        let sy = j.saturating_sub(ry).min(h - 1);
        dst[left_rep..wp - right_rep].copy_from_slice(&img[sy * w..][src.clone()]);
        replicate_ends(dst, (left_rep, right_rep));
    }
    let mut planes = vec![0u8; PLANES * cw];
    for y in 0..h {
        planes_of(&padded[y * wp..][..wp * CENSUS_H], cw, &mut planes);
        emit(y, std::array::from_fn(|k| &planes[k * cw..][..cw]));
    }
}

/// Byte planes of the census: 34 comparisons, five planes (a word's bytes 5–7 stay zero).
pub(super) const PLANES: usize = (CENSUS_W * CENSUS_H - 1).div_ceil(8);

/// A row's planes as census words into `row`, padded by `pad = (left, right)` copies of its
/// first and last word.
#[inline(always)]
pub(super) fn words_row(planes: [&[u8]; PLANES], pad: (usize, usize), row: &mut [u64]) {
    let w = planes[0].len();
    let [p0, p1, p2, p3, p4] = planes;
    // (Shifts and ORs of the planes' bytes over slices of one length, not `from_le_bytes`,
    // so that it vectorises.)
    let (p0, p1, p2, p3, p4, out) = (&p0[..w], &p1[..w], &p2[..w], &p3[..w], &p4[..w], &mut row[pad.0..pad.0 + w]);
    for x in 0..w {
        out[x] = p0[x] as u64 | (p1[x] as u64) << 8 | (p2[x] as u64) << 16 | (p3[x] as u64) << 24 | (p4[x] as u64) << 32;
    }
    replicate_ends(&mut row[..pad.0 + w + pad.1], pad);
}

/// A row's planes as its words' low 32 bits into `lo` and high bits into `hi` (what
/// [`split`] makes of the words), padded as [`words_row`] pads.
#[inline(always)]
pub(super) fn split_row(planes: [&[u8]; PLANES], pad: (usize, usize), lo: &mut [u32], hi: &mut [u8]) {
    let w = planes[0].len();
    let [p0, p1, p2, p3, p4] = planes;
    for (x, o) in lo[pad.0..pad.0 + w].iter_mut().enumerate() {
        *o = u32::from_le_bytes([p0[x], p1[x], p2[x], p3[x]]);
    }
    hi[pad.0..pad.0 + w].copy_from_slice(p4);
    replicate_ends(&mut lo[..pad.0 + w + pad.1], pad);
    replicate_ends(&mut hi[..pad.0 + w + pad.1], pad);
}

/// `row`'s first `pad.0` and last `pad.1` entries set to copies of the first and last entry
/// between them.
#[inline(always)]
fn replicate_ends<T: Copy>(row: &mut [T], pad: (usize, usize)) {
    let end = row.len() - pad.1;
    let (first, last) = (row[pad.0], row[end - 1]);
    row[..pad.0].fill(first);
    row[end..].fill(last);
}

/// One row's comparisons: `padded` holds the window's `CENSUS_H` source rows, each padded by
/// `CENSUS_W / 2` replicated pixels on both sides; comparison t (neighbour < centre, the
/// neighbours in row-major order, the centre left out) goes to bit t % 8 of plane t / 8 of
/// `planes` (five planes of `w` bytes). Byte planes: 32 pixels per AVX2 instruction where
/// the compiler vectorises it, then interleaved into words.
pub(super) fn planes_row(padded: &[u8], w: usize, planes: &mut [u8]) {
    let (rx, ry) = (CENSUS_W / 2, CENSUS_H / 2);
    let wp = w + 2 * rx;
    let centre = &padded[ry * wp + rx..][..w];
    planes.fill(0);
    let mut t = 0;
    for (j, src) in padded.chunks(wp).enumerate() {
        for i in 0..CENSUS_W {
            if i == rx && j == ry {
                continue;
            }
            let nb = &src[i..i + w];
            let plane = &mut planes[t / 8 * w..][..w];
            let bit = t % 8;
            for ((o, &c), &n) in plane.iter_mut().zip(centre).zip(nb) {
                *o |= ((n < c) as u8) << bit;
            }
            t += 1;
        }
    }
}

/// The words of the columns from the first searched pixel to the last (`spans`: each row's
/// searched pixels, none where empty) into `out`'s rows, `w` words each (the other columns
/// are left as they were, nothing where nothing is searched): the left census, which the
/// costs read at searched pixels alone. A crop's columns left of its searched pixels hold
/// the right pixels their disparities reach, and need no left words.
#[inline(always)]
pub(super) fn transform_spans_into(img: &[u8], w: usize, h: usize, spans: &[std::ops::Range<usize>], rows: &mut Vec<u8>, planes_of: impl Fn(&[u8], usize, &mut [u8]), out: &mut Vec<u64>) {
    // Every word a search reads is written below: no clearing unless it grows.
    out.resize(w * h, 0);
    let Some(cols) = spans.iter().filter(|s| !s.is_empty()).cloned().reduce(|a, b| a.start.min(b.start)..a.end.max(b.end)) else { return };
    let start = cols.start;
    transform_cols(img, w, h, cols, rows, planes_of, |y, planes| {
        let cw = planes[0].len();
        words_row(planes, (0, 0), &mut out[y * w + start..][..cw]);
    });
}

/// [`transform_cols`] over the whole image, its words into `out`, `w + pad.0 + pad.1` per
/// row, padded by copies of each row's first and last word: the tests' reference (the
/// matcher writes its rows over the columns its bands reach, [`right_words`], and the left
/// words over the searched columns, [`transform_spans_into`]).
#[cfg(test)]
pub(super) fn transform_into(img: &[u8], w: usize, h: usize, pad: (usize, usize), rows: &mut Vec<u8>, planes_of: impl Fn(&[u8], usize, &mut [u8]), out: &mut Vec<u64>) {
    let wo = pad.0 + w + pad.1;
    // Every word is written below: no clearing (a fill of the whole image) unless it grows.
    out.resize(wo * h, 0);
    transform_cols(img, w, h, 0..w, rows, planes_of, |y, planes| words_row(planes, pad, &mut out[y * wo..][..wo]));
}

/// Where the costs read the right image's rows: image column `c` of row `y` at
/// `y · wr + pad_l + c`, the columns past the image's edges (`pad_l` on the left) holding
/// copies of its edge pixel's entry, so that every disparity of every band has a right
/// pixel. Only the columns a call's bands reach, `reach.0 ..= reach.1` (image columns, past
/// the edges too), are written ([`right_split`], [`right_words`], [`pad_rows`]): an assisted
/// crop's columns hold the left pixels' windows and background the bands never reach, and
/// the padding on the left is a range's width (127 entries a row at 128 disparities) that
/// only a pixel near the image's left edge reads. The rest keeps what earlier calls wrote.
#[derive(Clone, Copy, Debug)]
pub(super) struct RightRows {
    /// The image's width.
    pub(super) w: usize,
    pub(super) pad_l: usize,
    /// A padded row's length.
    pub(super) wr: usize,
    /// The first and the last column read (none where the first is greater).
    pub(super) reach: (i32, i32),
}

impl RightRows {
    /// The image's columns written: those reached, clamped into the image (a reach past an
    /// edge copies that edge's column). `None` where nothing is reached.
    fn cols(&self) -> Option<Range<usize>> {
        let (first, last) = self.reach;
        let edge = |c: i32| c.clamp(0, self.w as i32 - 1) as usize;
        (first <= last).then(|| edge(first)..edge(last) + 1)
    }

    /// Copies of `row`'s edge entries over the padding the reach passes into (`row`: one
    /// padded row, its image columns [`RightRows::cols`] written).
    fn pad<T: Copy>(&self, row: &mut [T]) {
        let (first, last) = self.reach;
        if first < 0 {
            let from = self.pad_l.checked_add_signed(first as isize).expect("a reach inside the left padding");
            let edge = row[self.pad_l];
            row[from..self.pad_l].fill(edge);
        }
        if last >= self.w as i32 {
            let (end, edge) = (self.pad_l + self.w, row[self.pad_l + self.w - 1]);
            row[end..=self.pad_l + last as usize].fill(edge);
        }
    }
}

/// The right image's census as the AVX2 costs read it, its words' low 32 bits into `lo` and
/// their high bits into `hi` (what [`split`] makes of them), over `rows`' reach.
#[inline(always)]
pub(super) fn right_split(img: &[u8], h: usize, rows: RightRows, scratch: &mut Vec<u8>, planes_of: impl Fn(&[u8], usize, &mut [u8]), lo: &mut Vec<u32>, hi: &mut Vec<u8>) {
    let wr = rows.wr;
    lo.resize(wr * h, 0);
    hi.resize(wr * h, 0);
    let Some(cols) = rows.cols() else { return };
    let at = rows.pad_l + cols.start;
    transform_cols(img, rows.w, h, cols, scratch, planes_of, |y, planes| {
        let (lo, hi) = (&mut lo[y * wr..][..wr], &mut hi[y * wr..][..wr]);
        let cw = planes[0].len();
        split_row(planes, (0, 0), &mut lo[at..at + cw], &mut hi[at..at + cw]);
        rows.pad(lo);
        rows.pad(hi);
    });
}

/// The right image's census words as the portable costs read them, over `rows`' reach.
#[inline(always)]
pub(super) fn right_words(img: &[u8], h: usize, rows: RightRows, scratch: &mut Vec<u8>, planes_of: impl Fn(&[u8], usize, &mut [u8]), out: &mut Vec<u64>) {
    let wr = rows.wr;
    out.resize(wr * h, 0);
    let Some(cols) = rows.cols() else { return };
    let at = rows.pad_l + cols.start;
    transform_cols(img, rows.w, h, cols, scratch, planes_of, |y, planes| {
        let row = &mut out[y * wr..][..wr];
        words_row(planes, (0, 0), &mut row[at..at + planes[0].len()]);
        rows.pad(row);
    });
}

/// The map of the right image's grey levels onto the left's mean and standard deviation
/// (both over the whole images): a gain and offset between the cameras removed before the
/// intensity term compares levels. One table for a call, so that every stripe of rows
/// compares the same levels. Two views of different content (more of a dark background on
/// one side) differ in these statistics too; where the call's intervals say what corresponds,
/// [`level_map_from_prior`] compares like with like.
pub(in crate::stereo) fn level_map(left: &[u8], right: &[u8]) -> [u8; 256] {
    // From each image's histogram: one pass of integer counting per image, into four
    // histograms taken in turn (a blue screen repeats one level pixel after pixel, and one
    // counter incremented back to back waits on its own store each time), summed after.
    let stats = |img: &[u8]| {
        let mut hists = [[0u32; 256]; 4];
        let quads = img.chunks_exact(4);
        for &v in quads.remainder() {
            hists[0][v as usize] += 1;
        }
        for q in quads {
            for (hist, &v) in hists.iter_mut().zip(q) {
                hist[v as usize] += 1;
            }
        }
        let hist: [u32; 256] = std::array::from_fn(|v| hists.iter().map(|h| h[v]).sum());
        let n = img.len().max(1) as f64;
        let mean = hist.iter().enumerate().map(|(v, &c)| v as f64 * c as f64).sum::<f64>() / n;
        let var = hist.iter().enumerate().map(|(v, &c)| (v as f64 - mean).powi(2) * c as f64).sum::<f64>() / n;
        (mean, var.sqrt().max(1.0))
    };
    linear_map(stats(left), stats(right))
}

/// Fewest corresponding pairs [`level_map_from_prior`] takes its statistics over.
const MIN_PRIOR_PAIRS: u64 = 512;

/// [`level_map_from_prior`] samples every this many rows.
const PRIOR_ROW_STEP: usize = 4;

/// [`level_map_from_prior`] takes a left pixel only where the pixels this far on either side
/// are searched too: away from the object's silhouette, where a correspondence a few pixels
/// off would sample the background.
const PRIOR_INNER: usize = 8;

/// The map of [`level_map`], with both statistics taken over corresponding pixels: each left
/// pixel whose interval is a prior — searched, at most `max_width` disparities wide — and
/// the right pixel at the interval's middle disparity (inside the image), on every
/// [`PRIOR_ROW_STEP`]-th row and [`PRIOR_INNER`] pixels or more inside the searched pixels.
/// A seeded call's bands and an assisted call's intervals are such priors; the pixels then
/// sample the same surface in both images, within a few pixels, whatever else each view
/// holds. `None` with fewer than [`MIN_PRIOR_PAIRS`] such pairs (a full-range call: then
/// [`level_map`]).
pub(in crate::stereo) fn level_map_from_prior(left: GrayView, right: GrayView, intervals: &DisparityIntervals, max_width: i32) -> Option<[u8; 256]> {
    let w = left.width;
    let (mut n, mut sl, mut sl2, mut sr, mut sr2) = (0u64, 0u64, 0u64, 0u64, 0u64);
    // Every PRIOR_ROW_STEP-th row: thousands of pairs still, at a quarter of the pass.
    for (y, (lo, hi)) in intervals.lo.chunks_exact(w).zip(intervals.hi.chunks_exact(w)).enumerate().step_by(PRIOR_ROW_STEP) {
        let (lrow, rrow) = (&left.data[y * w..][..w], &right.data[y * w..][..w]);
        let (mut rn, mut rl, mut rl2, mut rr, mut rr2) = (0u64, 0u64, 0u64, 0u64, 0u64);
        // Only from the row's first searched pixel to its last: no other pixel is one.
        let Some((first, last)) = searched_span(lo, hi) else { continue };
        for (x, (&a, &b)) in lo.iter().zip(hi).enumerate().take(last + 1).skip(first) {
            let (a, b) = (a as i32, b as i32);
            let xr = x as i32 - ((a + b) >> 1);
            let inner = x >= PRIOR_INNER && x + PRIOR_INNER < w && lo[x - PRIOR_INNER] <= hi[x - PRIOR_INNER] && lo[x + PRIOR_INNER] <= hi[x + PRIOR_INNER];
            if inner && a <= b && b - a <= max_width && xr >= 0 && (xr as usize) < w {
                let (l, r) = (lrow[x] as u64, rrow[xr as usize] as u64);
                rn += 1;
                rl += l;
                rl2 += l * l;
                rr += r;
                rr2 += r * r;
            }
        }
        (n, sl, sl2, sr, sr2) = (n + rn, sl + rl, sl2 + rl2, sr + rr, sr2 + rr2);
    }
    if n < MIN_PRIOR_PAIRS {
        return None;
    }
    let stats = |s: u64, s2: u64| {
        let mean = s as f64 / n as f64;
        let var = (s2 as f64 / n as f64 - mean * mean).max(0.0);
        (mean, var.sqrt().max(1.0))
    };
    Some(linear_map(stats(sl, sl2), stats(sr, sr2)))
}

/// The table taking levels of mean `mr` and deviation `sr` onto `ml` and `sl`, rounded.
fn linear_map((ml, sl): (f64, f64), (mr, sr): (f64, f64)) -> [u8; 256] {
    std::array::from_fn(|v| ((v as f64 - mr) * sl / sr + ml).round().clamp(0.0, 255.0) as u8)
}

/// `img`'s rows (`rows.w` wide, `h` of them) through `map` into `out`, laid out and padded
/// as [`RightRows`] says, over its reach.
pub(super) fn pad_rows(img: &[u8], h: usize, rows: RightRows, map: &[u8; 256], out: &mut Vec<u8>) {
    let (w, wr) = (rows.w, rows.wr);
    out.resize(wr * h, 0);
    let Some(cols) = rows.cols() else { return };
    let at = rows.pad_l + cols.start;
    for (src, dst) in img.chunks_exact(w).zip(out.chunks_exact_mut(wr)).take(h) {
        for (o, &v) in dst[at..at + cols.len()].iter_mut().zip(&src[cols.clone()]) {
            *o = map[v as usize];
        }
        rows.pad(dst);
    }
}

/// One left pixel against a run of right pixels: its census word `cl` and grey level `il`;
/// the right row's census words and (matched, padded) grey levels; the intensity term's cap.
#[derive(Clone, Copy)]
pub(super) struct Pixel<'a> {
    pub cl: u64,
    pub il: u8,
    pub cr_row: &'a [u64],
    pub ir_row: &'a [u8],
    pub cap: u8,
}

/// Consecutive left pixels of one band (their census words and levels) and the right row,
/// its census words split ([`split`]), for the vector costs.
#[derive(Clone, Copy)]
pub(super) struct Run<'a> {
    pub cl: &'a [u64],
    pub il: &'a [u8],
    pub cr_lo: &'a [u32],
    pub cr_hi: &'a [u8],
    pub ir_row: &'a [u8],
    pub cap: u8,
}

/// The census words' low 32 bits and their two high bits (a window of 34 bits), as the
/// vector costs read them (eight words per register instead of four); `lo` and `hi` as long
/// as `words`. The matcher builds them from the planes ([`split_row`]); this is the tests'
/// reference.
#[cfg(test)]
pub(super) fn split(words: &[u64], lo: &mut [u32], hi: &mut [u8]) {
    for ((&w, lo), hi) in words.iter().zip(lo).zip(hi) {
        (*lo, *hi) = (w as u32, (w >> 32) as u8);
    }
}

/// Costs of a left pixel for consecutive disparities: `out[k]` against the right pixel at
/// `start − k` (the right pixel moves left as the disparity grows): census bits plus
/// `min(|il − ir|, cap)`.
#[inline(always)]
pub(super) fn costs(px: Pixel, start: usize, out: &mut [u8]) {
    let from = start + 1 - out.len();
    let (cr, ir) = (&px.cr_row[from..=start], &px.ir_row[from..=start]);
    for ((o, &r), &i) in out.iter_mut().zip(cr.iter().rev()).zip(ir.iter().rev()) {
        *o = (px.cl ^ r).count_ones() as u8 + px.il.abs_diff(i).min(px.cap);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn census_bits_order_intensities_and_ignore_gain() {
        let (w, h) = (12, 9);
        let img: Vec<u8> = (0..w * h).map(|i| ((i * 37) % 127) as u8).collect();
        // A strictly increasing change of intensity (gain and offset) keeps every comparison.
        let brighter: Vec<u8> = img.iter().map(|&v| 2 * v + 1).collect();
        let (mut a, mut b) = (Vec::new(), Vec::new());
        transform_into(&img, w, h, (0, 0), &mut Vec::new(), planes_row, &mut a);
        transform_into(&brighter, w, h, (0, 0), &mut Vec::new(), planes_row, &mut b);
        assert_eq!(a, b);
        assert!(a.iter().any(|&v| v != 0));
        // Bit by bit at one interior pixel.
        let (x, y) = (6usize, 4usize);
        let (mut expect, mut t) = (0u64, 0);
        for j in 0..CENSUS_H {
            for i in 0..CENSUS_W {
                if i == CENSUS_W / 2 && j == CENSUS_H / 2 {
                    continue;
                }
                let (sx, sy) = (x + i - CENSUS_W / 2, y + j - CENSUS_H / 2);
                expect |= ((img[sy * w + sx] < img[y * w + x]) as u64) << t;
                t += 1;
            }
        }
        assert_eq!(a[y * w + x], expect);
    }

    /// The split rows the AVX2 costs read, made from the planes, are the padded words split.
    #[test]
    fn split_rows_are_the_padded_words_split() {
        let (w, h, pad) = (13, 6, (5, 2));
        let mut next = crate::testing::xorshift(7);
        let img: Vec<u8> = (0..w * h).map(|_| next() as u8).collect();
        let wo = pad.0 + w + pad.1;
        let mut words = Vec::new();
        transform_into(&img, w, h, pad, &mut Vec::new(), planes_row, &mut words);
        let (mut lo, mut hi) = (vec![0u32; wo * h], vec![0u8; wo * h]);
        transform_cols(&img, w, h, 0..w, &mut Vec::new(), planes_row, |y, planes| split_row(planes, pad, &mut lo[y * wo..][..wo], &mut hi[y * wo..][..wo]));
        let (mut want_lo, mut want_hi) = (vec![0u32; wo * h], vec![0u8; wo * h]);
        split(&words, &mut want_lo, &mut want_hi);
        assert!(want_hi.iter().any(|&v| v != 0) && want_lo.iter().any(|&v| v != 0));
        assert_eq!((lo, hi), (want_lo, want_hi));
    }

    /// The right rows over a reach are the whole padded rows there — the image's columns,
    /// and copies of its edge pixels where the reach passes an edge — and nothing outside
    /// the reach is written: census words split and whole, and levels.
    #[test]
    fn the_right_rows_over_a_reach_are_the_padded_rows_there() {
        let (w, h, pad) = (23, 6, (9, 4));
        let wr = pad.0 + w + pad.1;
        let mut next = crate::testing::xorshift(11);
        let img: Vec<u8> = (0..w * h).map(|_| next() as u8).collect();
        let map: [u8; 256] = std::array::from_fn(|v| (v as u8).wrapping_mul(3) | 1);
        let mut words = Vec::new();
        transform_into(&img, w, h, pad, &mut Vec::new(), planes_row, &mut words);
        let (mut want_lo, mut want_hi) = (vec![0u32; wr * h], vec![0u8; wr * h]);
        split(&words, &mut want_lo, &mut want_hi);
        let levels: Vec<u8> = img.chunks_exact(w).flat_map(|row| {
            let m = |v: u8| map[v as usize];
            std::iter::repeat_n(m(row[0]), pad.0).chain(row.iter().map(move |&v| m(v))).chain(std::iter::repeat_n(m(row[w - 1]), pad.1))
        }).collect();
        // Inside the image, past the left edge, past the right, past both, one column, none.
        for reach in [(3, 15), (-9, 5), (-4, 0), (17, 26), (12, 22), (-9, 26), (-1, 23), (8, 8), (5, 4)] {
            let rows = RightRows { w, pad_l: pad.0, wr, reach };
            let (mut lo, mut hi, mut whole, mut lv) = (vec![u32::MAX; wr * h], vec![0xee; wr * h], vec![u64::MAX; wr * h], vec![0xee; wr * h]);
            right_split(&img, h, rows, &mut Vec::new(), planes_row, &mut lo, &mut hi);
            right_words(&img, h, rows, &mut Vec::new(), planes_row, &mut whole);
            pad_rows(&img, h, rows, &map, &mut lv);
            for i in 0..wr * h {
                let c = (i % wr) as i32 - pad.0 as i32;
                let reached = (reach.0..=reach.1).contains(&c);
                let at = format!("reach {reach:?}, column {c}, row {}", i / wr);
                assert_eq!(lo[i], if reached { want_lo[i] } else { u32::MAX }, "{at}");
                assert_eq!(hi[i], if reached { want_hi[i] } else { 0xee }, "{at}");
                assert_eq!(whole[i], if reached { words[i] } else { u64::MAX }, "{at}");
                assert_eq!(lv[i], if reached { levels[i] } else { 0xee }, "{at}");
            }
        }
    }

    #[test]
    fn costs_walk_the_right_row_backwards() {
        let cr: Vec<u64> = (0..10u64).map(|i| (1u64 << i) - 1).collect();
        let mut out = [0u8; 4];
        // Right pixels 5, 4, 3, 2.
        let levels = [0u8; 10];
        costs(Pixel { cl: 0, il: 0, cr_row: &cr, ir_row: &levels, cap: 0 }, 5, &mut out);
        assert_eq!(out, [5, 4, 3, 2]);
        // The intensity term, capped: levels 7 · i against a left level of 20.
        let levels: Vec<u8> = (0..10).map(|i| 7 * i).collect();
        costs(Pixel { cl: 0, il: 20, cr_row: &cr, ir_row: &levels, cap: 10 }, 5, &mut out);
        assert_eq!(out, [5 + 10, 4 + 8, 3 + 1, 2 + 6]);
    }

    #[test]
    fn the_right_levels_are_matched_to_the_left_gain_and_offset() {
        let left: Vec<u8> = (0..400).map(|i| (40 + (i * 37) % 150) as u8).collect();
        let right: Vec<u8> = left.iter().map(|&v| (1.2 * v as f64 + 9.0).round() as u8).collect();
        let map = level_map(&left, &right);
        assert!(left.iter().zip(&right).all(|(a, b)| a.abs_diff(map[*b as usize]) <= 1), "{:?}", &map[..10]);
        let mut padded = Vec::new();
        let identity: [u8; 256] = std::array::from_fn(|v| v as u8);
        let rows = RightRows { w: 10, pad_l: 2, wr: 13, reach: (-2, 10) };
        pad_rows(&left[..20], 2, rows, &identity, &mut padded);
        assert_eq!(padded.len(), 26);
        assert_eq!((&padded[..3], padded[12], &padded[13..16]), (&[left[0], left[0], left[0]][..], left[9], &[left[10], left[10], left[10]][..]));
        pad_rows(&right[..20], 2, rows, &map, &mut padded);
        assert!(padded[2..12].iter().zip(&left[..10]).all(|(a, b)| a.abs_diff(*b) <= 1));
    }

    /// A scene whose two views differ in content as well as in gain: the object (a texture
    /// over columns 40 … 159 of the left image, 12 px further left in the right one) and, in
    /// the right image only, a dark strip where the left sees bright background.
    fn gain_and_content(w: usize, h: usize) -> (Vec<u8>, Vec<u8>, DisparityIntervals) {
        let texture = |x: usize, y: usize| (40 + (x * 37 + y * 91 + (x * y) % 23) % 150) as f64;
        let left: Vec<u8> = (0..w * h).map(|i| if (40..160).contains(&(i % w)) { texture(i % w, i / w) as u8 } else { 200 }).collect();
        let right: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let v = if (28..148).contains(&x) { texture(x + 12, y) } else if x >= 150 { 5.0 } else { 200.0 };
                (1.2 * v + 9.0).round().min(255.0) as u8
            })
            .collect();
        // The object's pixels search 12 ± 3 (an assisted call's prior).
        let mut iv = DisparityIntervals::empty(w, h);
        for y in 0..h {
            for x in 40..160 {
                iv.set(x, y, Some((9, 15)));
            }
        }
        (left, right, iv)
    }

    #[test]
    fn the_prior_level_map_compares_the_pixels_that_correspond() {
        let (w, h) = (200, 40);
        let (left, right, iv) = gain_and_content(w, h);
        let (lv, rv) = (GrayView::new(w, h, &left).unwrap(), GrayView::new(w, h, &right).unwrap());
        let off = |map: &[u8; 256]| (0..h).flat_map(|y| (40..160).map(move |x| (x, y))).map(|(x, y)| left[y * w + x].abs_diff(map[right[y * w + x - 12] as usize])).max().unwrap();
        let prior = level_map_from_prior(lv, rv, &iv, 24).expect("the object's pixels are priors");
        assert!(off(&prior) <= 1, "the prior's map is {} levels off", off(&prior));
        // The whole images' statistics see the dark strip and the background as well.
        let whole = level_map(&left, &right);
        assert!(off(&whole) > 10, "the whole images' map is {} levels off", off(&whole));
    }

    #[test]
    fn a_full_range_or_too_few_pixels_is_no_prior() {
        let (w, h) = (200, 40);
        let (left, right, iv) = gain_and_content(w, h);
        let (lv, rv) = (GrayView::new(w, h, &left).unwrap(), GrayView::new(w, h, &right).unwrap());
        // Intervals wider than the prior's width.
        assert!(level_map_from_prior(lv, rv, &iv, 5).is_none());
        assert!(level_map_from_prior(lv, rv, &DisparityIntervals::full(w, h, 0, 63), 24).is_none());
        // Under MIN_PRIOR_PAIRS sampled pairs: one row of the object.
        let mut few = DisparityIntervals::empty(w, h);
        for x in 40..160 {
            few.set(x, 0, Some((9, 15)));
        }
        assert!(level_map_from_prior(lv, rv, &few, 24).is_none());
        // Nothing whose correspondence falls off the image.
        let mut outside = DisparityIntervals::empty(w, h);
        for y in 0..h {
            for x in 0..w {
                outside.set(x, y, Some((x as i32 + 1, x as i32 + 3)));
            }
        }
        assert!(level_map_from_prior(lv, rv, &outside, 24).is_none());
    }

    #[test]
    fn padding_replicates_the_border_words() {
        let (w, h) = (10, 3);
        let img: Vec<u8> = (0..w * h).map(|i| ((i * 53) % 200) as u8).collect();
        let (mut plain, mut padded) = (Vec::new(), Vec::new());
        transform_into(&img, w, h, (0, 0), &mut Vec::new(), planes_row, &mut plain);
        transform_into(&img, w, h, (3, 2), &mut Vec::new(), planes_row, &mut padded);
        for y in 0..h {
            let row = &padded[y * (w + 5)..][..w + 5];
            assert_eq!(&row[3..3 + w], &plain[y * w..][..w]);
            assert!(row[..3].iter().all(|&v| v == plain[y * w]));
            assert!(row[3 + w..].iter().all(|&v| v == plain[y * w + w - 1]));
        }
    }
}
