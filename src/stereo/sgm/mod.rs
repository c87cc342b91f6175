//! Semi-global matching (Hirschmüller 2008) over per-pixel disparity intervals.
//!
//! # The method
//! The cost of a (pixel, disparity) pair is the Hamming distance of the two pixels' census
//! words (`census.rs`). Along each of four directions r (rows and columns, both ways; eight
//! with the diagonals; five: the row both ways and the three from above, `sgm_paths`) it is
//! aggregated by the recurrence
//!
//! `L_r(p, d) = C(p, d) + min(L_r(q, d), L_r(q, d ± 1) + P1, min_k L_r(q, k) + P2) − min_k L_r(q, k)`
//!
//! with q = p − r the previous pixel of the path: a change of one disparity costs P1, a larger
//! jump P2. The sums `S(p, d) = Σ_r L_r(p, d)` are the aggregated cost; the winner is their
//! minimum within the pixel's interval, with the correlation matcher's uniqueness test and
//! speckle filter, an equiangular sub-pixel fit and SGBM's left–right check (`select.rs`).
//!
//! # Intervals, and the work they save
//! Every pixel aggregates only over its own interval rounded out to whole blocks of
//! [`LANES`] disparities (one SIMD register of 16-bit sums), so the work — a path update
//! per path and pair — is proportional to the pairs searched, up to that rounding; the full
//! range is the special case. The winner is looked for inside the interval itself.
//! `S` is stored packed: pixel p's blocks at `off[p] …`, nothing for the blocks it does not
//! search. Where the previous pixel of a path searched other blocks than p, the path carries
//! across: disparities q did not search count as unreachable except through the jump term,
//! `min_k L_r(q, k) + P2` — a path entering a new band pays P2 at most, as at an edge. A path
//! starts afresh (`L_r = C`) after a pixel that searched nothing (the background).
//! Disparities of a block whose right pixel lies outside the image compare with the image's
//! border column (the census row is padded by replication), and never win.
//!
//! # Passes
//! Pass one goes down the image, left to right, with the paths from the left and above
//! (and the upper left and upper right); pass two goes up, right to left, with the others,
//! and selects each row as soon as its sums are complete. Both walk each row only over its
//! span, from its first to its last searched pixel. With five paths (`single.rs`) there is
//! one pass down the image, and no volume: each row's sums are complete after its own two
//! sweeps.
//!
//! # Runs
//! With four paths, a run of pixels that share one band with the pixel before them on the
//! row, and whose pixels in the previous row searched — the whole row at full range, patches
//! of an assisted map — is stepped by one AVX2 kernel ([`simd::run`]): the row path's values
//! stay in registers from pixel to pixel, and nothing is looked up per pixel (the
//! bookkeeping of the general step cost more than its arithmetic at one or two blocks).
//! The sums are the general step's, to the bit.

use std::ops::Range;

use super::disparity::{DisparityIntervals, DisparityMap, GrayView, MatchStats};
use super::params::ValidMatchParams;

mod census;
mod costs;
pub(in crate::stereo) mod grid;
pub(super) use census::{level_map, level_map_from_prior};
mod select;
mod single;
#[cfg(target_arch = "x86_64")]
mod simd;

#[cfg(test)]
mod tests;

/// Disparities per block: sixteen 16-bit lanes, one AVX2 register.
pub(super) const LANES: usize = 16;
type Block = [u16; LANES];

/// A disparity no path reached: above any reachable path cost (at most 62 + P2 ≤ 2062), and
/// low enough that adding P1 stays inside `u16`.
const UNREACHED: u16 = 0x7000;

/// One row of a path's values: a slot of `n + 2` per pixel (`n` the padded range) —
/// disparity index k at slot offset k + 1, `UNREACHED` at both ends and wherever the slot's
/// pixel did not search — the band each slot holds, and each slot's minimum.
///
/// That holds of every slot at all times, also between passes and calls: a slot keeps the
/// band it last held, and [`PathRow::prepare`] clears what lies outside the next one. So a
/// pass does not clear its rows (which cost a memory fill of the whole row per pass, for the
/// few slots an assisted map searches); only a change of `n` starts them afresh.
#[derive(Default)]
struct PathRow {
    vals: Vec<u16>,
    band: Vec<[u16; 2]>,
    min: Vec<u16>,
    /// The padded range the slots are laid out for.
    n: usize,
}

impl PathRow {
    /// At least `slots` slots of range `n`: all `UNREACHED` where new, or when `n` changed.
    fn fit(&mut self, slots: usize, n: usize) {
        if self.n != n {
            self.vals.clear();
            self.band.clear();
            self.min.clear();
            self.n = n;
        }
        if self.band.len() < slots {
            self.vals.resize(slots * (n + 2), UNREACHED);
            self.band.resize(slots, [0, 0]);
            self.min.resize(slots, 0);
        }
    }

    /// Slot `i` made ready for band `a … a + m`: what an earlier band left outside it becomes
    /// `UNREACHED` again (nothing to do when the bands repeat, as at full range).
    #[inline(always)]
    fn prepare(&mut self, i: usize, n: usize, a: usize, m: usize) {
        let [oa, om] = self.band[i];
        let (oa, om) = (oa as usize, om as usize);
        if (oa, om) != (a, m) && om > 0 {
            let slot = &mut self.vals[i * (n + 2) + 1..][..n];
            let end = (oa + om).min(a);
            if oa < end {
                slot[oa..end].fill(UNREACHED);
            }
            let start = oa.max(a + m);
            if start < oa + om {
                slot[start..oa + om].fill(UNREACHED);
            }
        }
        self.band[i] = [a as u16, m as u16];
    }

    /// Slot `i` over disparity indices `a − 1 … a + m`.
    #[inline(always)]
    fn around(&self, i: usize, n: usize, a: usize, m: usize) -> &[u16] {
        &self.vals[i * (n + 2) + a..][..m + 2]
    }

    /// Slot `i` over disparity indices `a … a + m − 1`.
    #[inline(always)]
    fn band_mut(&mut self, i: usize, n: usize, a: usize, m: usize) -> &mut [u16] {
        &mut self.vals[i * (n + 2) + 1 + a..][..m]
    }
}

/// Where a path comes from at one pixel: the previous pixel's values around the band
/// (`around`), its minimum, and the jump term `min + P2`. A path that starts here reads an
/// `UNREACHED` slot with `min = jump = 0`, which makes `L = C`.
#[derive(Clone, Copy)]
struct From<'a> {
    around: &'a [u16],
    min: u16,
    jump: u16,
}

impl<'a> From<'a> {
    /// A path that starts at this pixel: an `UNREACHED` slot (`fresh`, `n + 2` long) over the
    /// band `a … a + m`.
    #[inline(always)]
    fn start(fresh: &'a [u16], a: usize, m: usize) -> From<'a> {
        From { around: &fresh[a..a + m + 2], min: 0, jump: 0 }
    }

    /// A path that continues from slot `i` of `row` over the band `a … a + m`.
    #[inline(always)]
    fn after(row: &'a PathRow, i: usize, n: usize, a: usize, m: usize, p2: u16) -> From<'a> {
        From { around: row.around(i, n, a, m), min: row.min[i], jump: row.min[i] + p2 }
    }
}

/// The system refused the memory of a call's costs and sums (`bytes`, for `width × height`
/// pixels over `disparities`, the range rounded up to blocks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct VolumeRefused {
    pub(super) width: usize,
    pub(super) height: usize,
    pub(super) disparities: usize,
    pub(super) bytes: u64,
}

/// Reusable buffers of the semi-global matcher.
#[derive(Default)]
pub(super) struct Sgm {
    census_l: Vec<u64>,
    /// The census's padded source image (`census::transform_cols`), reused for both images.
    census_rows: Vec<u8>,
    /// The right census, each row padded by replication so that every disparity of every
    /// block has a right pixel (the portable costs' words).
    census_r: Vec<u64>,
    /// The same split into its low 32 bits and its two high bits, laid out from the census
    /// planes ([`census::split_row`]): the AVX2 costs' words, in place of `census_r`.
    census_r_lo: Vec<u32>,
    census_r_hi: Vec<u8>,
    /// The right image's grey levels matched to the left's, padded as `census_r`.
    levels_r: Vec<u8>,
    /// Per pixel: the aggregated band (first disparity index, on the call's grid of blocks
    /// ([`grid::shift`]) but at the range's ends, and count, a multiple of [`LANES`]; 0 = not
    /// searched), and the interval searched inside it.
    band_a: Vec<u16>,
    band_m: Vec<u16>,
    lo: Vec<u16>,
    hi: Vec<u16>,
    /// Per pixel: offset of its costs and sums in `cost` and `sum`; one more entry at the end.
    off: Vec<usize>,
    /// Per row: the columns from its first to its last searched pixel — where the passes and
    /// the selection walk (an assisted crop's rows are half background).
    span: Vec<Range<usize>>,
    /// Census costs and aggregated costs, packed.
    cost: Vec<u8>,
    sum: Vec<u16>,
    /// The vertical and diagonal paths (from x − 1, x, x + 1 of the previous row): the
    /// previous and the current row.
    vert_prev: [PathRow; 3],
    vert_cur: [PathRow; 3],
    /// The horizontal path at the previous and the current pixel.
    h_prev: PathRow,
    h_cur: PathRow,
    /// An `UNREACHED` slot: where a path starts.
    fresh: Vec<u16>,
    /// Per right pixel of the row: its cheapest winning splat as `sum << 32 | x`.
    right_best: Vec<u64>,
    /// Per pixel of the row being selected: its winning disparity and the numerator and
    /// denominator of its sub-pixel step (`select.rs`).
    fit_di: Vec<i32>,
    fit_num: Vec<i32>,
    fit_den: Vec<i32>,
    /// Per pixel of the row being selected: its smallest sum, the disparity index holding it
    /// and its rival (`select.rs`; sixteen at a time where the bands allow).
    win_best: Vec<u16>,
    win_k: Vec<u16>,
    win_rival: Vec<u16>,
}

/// The geometry of one call: image size, the padded range and the right rows' padding.
#[derive(Clone, Copy)]
struct Geo {
    w: usize,
    h: usize,
    /// Disparity indices `0 … n` (the range rounded up to blocks).
    n: usize,
    dmin: i32,
    /// Columns of replicated padding left of each right census row.
    pad_l: usize,
    /// Padded right row length.
    wr: usize,
    /// Whether pass one stores each sum with its cost above it (`simd::FOLD_SHIFT`), so
    /// that the costs need no volume of their own: `cost` then holds one row's costs, and
    /// pass two reads them from the sums: the volume between the passes a third smaller, and
    /// 6 bytes of memory traffic a pair instead of 8 (the clock shows little of it:
    /// docs/matcher.md). Four paths on AVX2 only, and only where the words hold both
    /// ([`folds`]): the defaults do.
    folded: bool,
}

/// Whether a pixel's sum of pass one's two paths and its cost fit one 16-bit word with `p`'s
/// penalties and cost: a path's value lies in 0 … C + P2 (the jump term bounds it), so the
/// sum is at most 2 · (C_max + P2), which must stay below 2⁹; the cost, at most C_max = 34
/// census bits + the intensity term's cap, takes the 7 bits above.
#[cfg(target_arch = "x86_64")]
fn folds(p: &ValidMatchParams) -> bool {
    let c_max = census::MAX_BITS as u32 + p.sgm_ad_cap as u32;
    p.sgm_paths == 4 && c_max < 1 << (16 - simd::FOLD_SHIFT) && 2 * (c_max + p.p2 as u32) < 1 << simd::FOLD_SHIFT
}

/// Whether the costs count bits with `vpopcntd` (AVX-512, [`simd::has_vpopcnt`]): asked once
/// a pass, not once a run of pixels.
fn has_vpopcnt() -> bool {
    #[cfg(target_arch = "x86_64")]
    return simd::has_vpopcnt();
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The `N` paths of one pass at one pixel (one, two or four): writes each path's values and adds
/// (or, on the first pass, writes) their sum; returns each path's minimum. `folded` as
/// [`Geo::folded`] (pass two does not read `c` then).
#[inline(always)]
fn step<const AVX2: bool, const N: usize>(c: &[u8], from: [From; N], p1: u16, out: [&mut [u16]; N], sum: &mut [u16], add: bool, folded: bool) -> [u16; N] {
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU.
        return unsafe {
            if folded {
                simd::step::<N, true>(c, from, p1, out, sum, add)
            } else {
                simd::step::<N, false>(c, from, p1, out, sum, add)
            }
        };
    }
    debug_assert!(!folded, "the portable build keeps the cost volume");
    step_portable(c, from, p1, out, sum, add)
}

/// Portable [`step`], in whole blocks.
#[inline(always)]
fn step_portable<const N: usize>(c: &[u8], from: [From; N], p1: u16, out: [&mut [u16]; N], sum: &mut [u16], add: bool) -> [u16; N] {
    let m = c.len();
    let mut mn: [Block; N] = [[u16::MAX; LANES]; N];
    for b in (0..m).step_by(LANES) {
        let cc: &[u8; LANES] = c[b..b + LANES].try_into().unwrap();
        let s: &mut Block = (&mut sum[b..b + LANES]).try_into().unwrap();
        let mut acc: Block = if add { *s } else { [0; LANES] };
        for j in 0..N {
            let f = from[j];
            let l: &Block = f.around[b..b + LANES].try_into().unwrap();
            let mid: &Block = f.around[b + 1..b + 1 + LANES].try_into().unwrap();
            let r: &Block = f.around[b + 2..b + 2 + LANES].try_into().unwrap();
            let o: &mut Block = (&mut out[j][b..b + LANES]).try_into().unwrap();
            for k in 0..LANES {
                let v = cc[k] as u16 + mid[k].min(l[k] + p1).min(r[k] + p1).min(f.jump) - f.min;
                o[k] = v;
                mn[j][k] = mn[j][k].min(v);
                acc[k] += v;
            }
        }
        *s = acc;
    }
    mn.map(|v| v.into_iter().fold(u16::MAX, u16::min))
}

impl Sgm {
    /// Matches checked inputs (same size, at least 2 × 1) over `intervals`, and keeps (writes
    /// and counts) the rows `keep` — the others only feed the paths; the speckle filter is the
    /// caller's. `levels` maps `right`'s grey levels onto the left image's for the intensity
    /// term ([`level_map_from_prior`], or [`level_map`] over the whole images).
    pub(super) fn compute(&mut self, p: &ValidMatchParams, left: GrayView, right: GrayView, levels: &[u8; 256], shift: u32, intervals: &DisparityIntervals, keep: Range<usize>, out: &mut DisparityMap) -> Result<MatchStats, VolumeRefused> {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("popcnt") {
            // SAFETY: the CPU supports AVX2 and POPCNT, checked just above.
            return unsafe { self.compute_avx2(p, left, right, levels, shift, intervals, keep, out) };
        }
        self.compute_impl::<false>(p, left, right, levels, shift, intervals, keep, out)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,popcnt")]
    unsafe fn compute_avx2(&mut self, p: &ValidMatchParams, left: GrayView, right: GrayView, levels: &[u8; 256], shift: u32, intervals: &DisparityIntervals, keep: Range<usize>, out: &mut DisparityMap) -> Result<MatchStats, VolumeRefused> {
        self.compute_impl::<true>(p, left, right, levels, shift, intervals, keep, out)
    }

    /// The whole matcher; inlined into each SIMD-level wrapper so the loops vectorise for it.
    #[inline(always)]
    fn compute_impl<const AVX2: bool>(&mut self, p: &ValidMatchParams, left: GrayView, right: GrayView, levels: &[u8; 256], shift: u32, intervals: &DisparityIntervals, keep: Range<usize>, out: &mut DisparityMap) -> Result<MatchStats, VolumeRefused> {
        let (w, h) = (left.width, left.height);
        let n = (p.num_disparities as usize).div_ceil(LANES) * LANES;
        let dmin = p.min_disparity;
        // Right pixels x − d for d in dmin … dmin + n − 1 and x in 0 … w − 1.
        let pad_l = (dmin + n as i32 - 1).max(0) as usize;
        let pad_r = (-dmin).max(0) as usize;
        #[cfg(target_arch = "x86_64")]
        let folded = AVX2 && folds(p);
        #[cfg(not(target_arch = "x86_64"))]
        let folded = false;
        let g = Geo { w, h, n, dmin, pad_l, wr: pad_l + w + pad_r, folded };
        let mut stats = MatchStats::default();
        let single = p.sgm_paths == 5;
        let (row_max, reach) = self.bands(p, g, shift, intervals, keep.clone(), single, &mut stats);
        let t0 = std::time::Instant::now();
        // The census comparisons: the AVX2 copy where the CPU has it.
        let planes_of = |rows: &[u8], w: usize, planes: &mut [u8]| {
            #[cfg(target_arch = "x86_64")]
            if AVX2 {
                // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU; `transform`
                // passes the window's rows and five planes of `w`.
                return unsafe { simd::planes(rows, w, planes) };
            }
            census::planes_row(rows, w, planes)
        };
        // (The left words over the searched columns alone: `census::transform_spans_into`.)
        census::transform_spans_into(left.data, w, h, &self.span, &mut self.census_rows, planes_of, &mut self.census_l);
        // The right words as the costs read them: split on AVX2, whole words otherwise.
        // Over the columns the bands read alone (an assisted crop's rows are half background).
        let rows = census::RightRows { w, pad_l, wr: g.wr, reach };
        if AVX2 {
            census::right_split(right.data, h, rows, &mut self.census_rows, planes_of, &mut self.census_r_lo, &mut self.census_r_hi);
        } else {
            census::right_words(right.data, h, rows, &mut self.census_rows, planes_of, &mut self.census_r);
        }
        census::pad_rows(right.data, h, rows, levels, &mut self.levels_r);
        stats.prefilter_ns = t0.elapsed().as_nanos() as u64;
        let total = self.off[w * h];
        // Pass one writes every cost and sum before anything reads them: no clearing. Folded,
        // the costs of the row being stepped only; in one pass, the costs and sums of one row.
        let (costs, sums) = if single { (row_max, row_max) } else { (if folded { row_max } else { total }, total) };
        // (`LANES` more sums: the selection reads two blocks from a one-block band, and its
        // gathers each sum as the low half of 32 bits.)
        let refused = |_| VolumeRefused { width: w, height: h, disparities: n, bytes: costs as u64 + 2 * (sums + LANES) as u64 };
        super::buffer::resize_for_overwrite(&mut self.cost, costs).map_err(refused)?;
        super::buffer::resize_for_overwrite(&mut self.sum, sums + LANES).map_err(refused)?;
        self.fresh.clear();
        self.fresh.resize(n + 2, UNREACHED);
        self.right_best.resize(w, 0);
        for v in [&mut self.fit_di, &mut self.fit_num, &mut self.fit_den] {
            v.resize(w, 0);
        }
        for v in [&mut self.win_best, &mut self.win_k, &mut self.win_rival] {
            v.resize(w, 0);
        }
        let vals = out.values_mut();
        // Each kept row is written whole by its selection; the other rows stay unmatched.
        vals[..keep.start * w].fill(f32::NAN);
        vals[keep.end * w..].fill(f32::NAN);
        if single {
            self.single_pass::<AVX2>(p, g, left.data, keep, vals, &mut stats);
        } else {
            self.pass::<AVX2>(p, g, left.data, false, keep.clone(), vals, &mut stats);
            self.pass::<AVX2>(p, g, left.data, true, keep, vals, &mut stats);
        }
        Ok(stats)
    }

    /// One pass: down the image left to right (`up = false`: the costs, from the census words
    /// and `left`'s levels, and the sums of four paths), or up right to left (adding the other
    /// four, then selecting each row).
    #[inline(always)]
    fn pass<const AVX2: bool>(&mut self, p: &ValidMatchParams, g: Geo, left: &[u8], up: bool, keep: Range<usize>, out: &mut [f32], stats: &mut MatchStats) {
        let Geo { w, h, n, folded, .. } = g;
        let (p1, p2) = (p.p1, p.p2);
        // Eight paths: all three from the previous row; four: only the one above (below).
        let eight = p.sgm_paths == 8;
        // (Four paths use the rows from straight above alone.)
        let used = if eight { 0..3 } else { 1..2 };
        for r in self.vert_prev[used.clone()].iter_mut().chain(self.vert_cur[used].iter_mut()) {
            r.fit(w, n);
        }
        self.h_prev.fit(1, n);
        self.h_cur.fit(1, n);
        let vpopcnt = AVX2 && !up && has_vpopcnt();
        for step_y in 0..h {
            let y = if up { h - 1 - step_y } else { step_y };
            // Where the row's costs lie in `cost`: at their packed offsets, or (folded) from
            // the start.
            let cbase = if folded { self.off[y * w] } else { 0 };
            if !up {
                self.costs_row::<AVX2>(p, g, left, y, cbase, vpopcnt);
            }
            // The previous row of the vertical paths (none at the first row of the pass).
            let py = if up { y + 1 } else { y.wrapping_sub(1) };
            let has_prev_row = py < h;
            let mut h_live = false;
            // The steps of the row's span, in the pass's direction.
            let span = self.span[y].clone();
            let (mut step_x, end) = if up { (w - span.end, w - span.start) } else { (span.start, span.end) };
            while step_x < end {
                let x = if up { w - 1 - step_x } else { step_x };
                let i = y * w + x;
                let m = self.band_m[i] as usize;
                if m == 0 {
                    h_live = false;
                    step_x += 1;
                    continue;
                }
                let a = self.band_a[i] as usize;
                #[cfg(target_arch = "x86_64")]
                if AVX2 && !eight && h_live && has_prev_row && self.h_prev.band[0] == [a as u16, m as u16] {
                    let len = self.run::<AVX2>(p, g, y, step_x, up, cbase);
                    if len > 0 {
                        step_x += len;
                        continue;
                    }
                }
                let fresh = From::start(&self.fresh, a, m);
                let hf = if h_live { From::after(&self.h_prev, 0, n, a, m, p2) } else { fresh };
                let mut vf = [fresh; 3];
                for (j, f) in vf.iter_mut().enumerate() {
                    let qx = (x + j).wrapping_sub(1);
                    if (eight || j == 1) && has_prev_row && qx < w && self.band_m[py * w + qx] > 0 {
                        *f = From::after(&self.vert_prev[j], qx, n, a, m, p2);
                    }
                }
                self.h_cur.prepare(0, n, a, m);
                #[cfg(target_arch = "x86_64")]
                if AVX2 {
                    // As in the runs (`simd::run`): the volume's lines of a pixel further on the
                    // sweep asked for ahead of their use (folded, pass two's costs are in them).
                    let ahead = if up { i.saturating_sub(simd::AHEAD as usize) } else { (i + simd::AHEAD as usize).min(w * h - 1) };
                    let o = self.off[ahead];
                    simd::prefetch(self.sum[o..].as_ptr(), 2 * m);
                    if up && !folded {
                        simd::prefetch(self.cost[o..].as_ptr(), m);
                    }
                }
                // (Folded, pass two reads the costs from the sums.)
                let c = if folded && up { &[][..] } else { &self.cost[self.off[i] - cbase..][..m] };
                let s = &mut self.sum[self.off[i]..][..m];
                let [v0, v1, v2] = &mut self.vert_cur;
                v1.prepare(x, n, a, m);
                if eight {
                    v0.prepare(x, n, a, m);
                    v2.prepare(x, n, a, m);
                    let outs = [v0.band_mut(x, n, a, m), v1.band_mut(x, n, a, m), v2.band_mut(x, n, a, m), self.h_cur.band_mut(0, n, a, m)];
                    let [m0, m1, m2, mh] = step::<AVX2, 4>(c, [vf[0], vf[1], vf[2], hf], p1, outs, s, up, folded);
                    (v0.min[x], v1.min[x], v2.min[x], self.h_cur.min[0]) = (m0, m1, m2, mh);
                } else {
                    let outs = [v1.band_mut(x, n, a, m), self.h_cur.band_mut(0, n, a, m)];
                    let [m1, mh] = step::<AVX2, 2>(c, [vf[1], hf], p1, outs, s, up, folded);
                    (v1.min[x], self.h_cur.min[0]) = (m1, mh);
                }
                std::mem::swap(&mut self.h_prev, &mut self.h_cur);
                h_live = true;
                step_x += 1;
            }
            std::mem::swap(&mut self.vert_prev, &mut self.vert_cur);
            if up && keep.contains(&y) {
                self.select::<AVX2>(p, g, y, &mut out[y * w..][..w], stats);
            }
        }
    }

    /// Four paths, from the pixel at `step_x` of row `y`'s sweep on (a row with a previous
    /// row in the pass): the run of pixels whose band is the previous pixel's (`h_prev`,
    /// live) and whose previous row's pixel searched (any band), stepped by
    /// [`simd::run`] (no bookkeeping per pixel, the row path kept in registers); returns its
    /// length (0: none, the pixel takes the general step).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn run<const AVX2: bool>(&mut self, p: &ValidMatchParams, g: Geo, y: usize, step_x: usize, up: bool, cbase: usize) -> usize {
        let Geo { w, n, folded, .. } = g;
        let x0 = if up { w - 1 - step_x } else { step_x };
        let band = self.h_prev.band[0];
        let (a, m) = (band[0] as usize, band[1] as usize);
        let blocks = m / LANES;
        if blocks > 8 {
            return 0;
        }
        // The run: the pixels that hold the band and whose previous row's pixels searched
        // (any band: outside its own band the slot holds `UNREACHED`, as the general step
        // reads it) ([`costs::run_length`]).
        let (row, prev_row) = (y * w..(y + 1) * w, if up { (y + 1) * w..(y + 2) * w } else { (y - 1) * w..y * w });
        let (ra, rm, pm) = (&self.band_a[row.clone()], &self.band_m[row], &self.band_m[prev_row]);
        let chunk = |c: usize| c..c + costs::RUN_CHUNK;
        let pair = (band[0], band[1]);
        let len = costs::run_length(x0, w - step_x, up, |c| costs::band_bits::<AVX2>(&ra[chunk(c)], &rm[chunk(c)], &pm[chunk(c)], pair), |x| (ra[x], rm[x]) == pair && pm[x] > 0);
        // Their slots made ready for the band where they hold another one (from two rows
        // back, or earlier).
        let cur = &mut self.vert_cur[1];
        let cols = if up { x0 + 1 - len..x0 + 1 } else { x0..x0 + len };
        for c in cols.clone().step_by(costs::RUN_CHUNK) {
            let mut stale = match cur.band.get(chunk(c)).filter(|_| c + costs::RUN_CHUNK <= cols.end) {
                // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU.
                Some(slots) if AVX2 => unsafe { simd::other_band_bits(slots.try_into().unwrap(), band) },
                _ => cur.band[c..cols.end.min(c + costs::RUN_CHUNK)].iter().enumerate().fold(0u32, |bits, (k, &b)| bits | ((b != band) as u32) << k),
            };
            while stale != 0 {
                cur.prepare(c + stale.trailing_zeros() as usize, n, a, m);
                stale &= stale - 1;
            }
        }
        if len == 0 {
            return 0;
        }
        let dir: isize = if up { -1 } else { 1 };
        let i0 = y * w + x0;
        let off = self.off[i0];
        // The run's packed costs and sums, and its slots, from its first to its last pixel.
        // (Folded, pass two reads the costs from the sums.)
        let span = (len - 1) * m;
        let (first, last) = if up { (off - span, off + m) } else { (off, off + span + m) };
        let costs = if folded && up { &[][..] } else { &self.cost[first - cbase..last - cbase] };
        let sums = &mut self.sum[first..last];
        let stride = n + 2;
        let slots = if up { (x0 + 1 - len) * stride..(x0 + 1) * stride } else { x0 * stride..(x0 + len) * stride };
        let (vp, vc) = (&self.vert_prev[1], &mut self.vert_cur[1]);
        let (prev, cur) = (&vp.vals[slots.clone()], &mut vc.vals[slots]);
        let mins = if up { x0 + 1 - len..x0 + 1 } else { x0..x0 + len };
        let (prev_min, cur_min) = (&vp.min[mins.clone()], &mut vc.min[mins]);
        // Pointers to the run's first pixel inside those slices (the last one when the sweep
        // goes right to left).
        let (k0, s0) = if up { (span, (len - 1) * stride) } else { (0, 0) };
        let mk = if up { len - 1 } else { 0 };
        let rows = simd::RunRows {
            prev: prev[s0 + a..].as_ptr(),
            prev_min: prev_min[mk..].as_ptr(),
            cur: cur[s0 + a + 1..].as_mut_ptr(),
            cur_min: cur_min[mk..].as_mut_ptr(),
            stride,
        };
        let h_min = self.h_prev.min[0];
        let h = self.h_prev.band_mut(0, n, a, m);
        let (c, s) = (costs.get(k0..).map_or(std::ptr::null(), <[u8]>::as_ptr), sums[k0..].as_mut_ptr());
        // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU; the slices above
        // hold every pixel of the run (sums `len · m`, and so do the costs but where pass two
        // reads them from the folded sums, slots `len · stride` with the band inside each,
        // minima `len`), walked along `dir` from the pointers.
        let last_min = unsafe {
            macro_rules! runs {
                ($folded:literal) => {
                    match blocks {
                        1 => simd::run::<1, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        2 => simd::run::<2, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        3 => simd::run::<3, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        4 => simd::run::<4, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        5 => simd::run::<5, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        6 => simd::run::<6, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        7 => simd::run::<7, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                        _ => simd::run::<8, $folded>(c, s, dir, len, &rows, h, h_min, p.p1, p.p2, up),
                    }
                };
            }
            if folded {
                runs!(true)
            } else {
                runs!(false)
            }
        };
        self.h_prev.min[0] = last_min;
        len
    }
}
