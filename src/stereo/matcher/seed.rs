//! Wide searches seeded from the pair at half size (`MatchParams::coarse_to_fine`).
//!
//! Both matchers cost more the more disparities each pixel searches — SGM's passes most of
//! all. Where a call searches wide intervals (a full-range frame, a Middlebury pair), the pair
//! is first matched at half its size over half the range — a quarter of the pixels, an
//! eighth of the pairs — with the same method, and each matcher tile (`BAND_TILE`) then
//! searches at full size only the band of disparities that the half-size match found over
//! the tile and one half-size pixel around it, doubled and widened by [`SEED_MARGIN`] on each
//! side, within each pixel's own interval. A tile where fewer than a quarter of the searched
//! half-size pixels matched (occlusions, a blank wall, the image's left edge) keeps its own
//! intervals. The half-size call is itself seeded where its intervals are still wide enough,
//! so a range of 256 is narrowed twice. Narrow calls (the assisted rows) are left as they are.
//!
//! The bands are whole tiles' hulls, so a depth edge inside a tile keeps both sides' ranges.
//! What the seed can lose is a structure too thin to match at half size (under two pixels
//! there) whose disparity lies outside its tile's band; docs/matcher.md, "Seeded from the
//! pair at half size", measures what it gains and loses.

use super::*;

/// Calls whose searched pixels search at least this many disparities on average are seeded:
/// four blocks of 16, whose half range is two. On Teddy's 64 disparities the seed is even in
/// time for SGM (7.4–8.2 against 7.4–8.7 ms, alternated) with bad2 13.83 against 14.13 %, and
/// pays for `bm` (3.1 against 4.0 ms).
const SEED_MIN_WIDTH: usize = 64;

/// Disparities added on each side of a tile's seeded band: the half-size match's error,
/// doubled, with room to spare.
const SEED_MARGIN: i32 = 4;

/// One level's buffers: the half-size pair, its intervals and map, and the intervals the
/// level above searches; reused from call to call.
pub(super) struct SeedScratch {
    left: Vec<u8>,
    right: Vec<u8>,
    intervals: DisparityIntervals,
    map: DisparityMap,
    seeded: DisparityIntervals,
}

impl Default for SeedScratch {
    fn default() -> Self {
        SeedScratch { left: Vec::new(), right: Vec::new(), intervals: DisparityIntervals::empty(0, 0), map: DisparityMap::new(0, 0), seeded: DisparityIntervals::empty(0, 0) }
    }
}

/// The matcher's call (`correlate` or semi-global matching in stripes, without SGM's
/// refinement or the speckle filter) with `params` over `intervals` at level `depth` (0 the
/// pair as given, 1 at half size, …), seeded from the level below where
/// `params.coarse_to_fine` is set and the intervals are wide. `span` bounds every interval's
/// width (the disparities from the lowest searched to the highest): under the threshold, the
/// intervals are not even read (an assisted call's 0.02 ms). The levels below count their
/// pairs in `evaluated`.
#[allow(clippy::too_many_arguments)]
pub(super) fn match_level(m: &mut StereoMatcher, params: &ValidMatchParams, depth: usize, left: GrayView, right: GrayView, intervals: &DisparityIntervals, span: usize, out: &mut DisparityMap) -> Result<MatchStats, MatchError> {
    if !params.coarse_to_fine || span < SEED_MIN_WIDTH || !wide(intervals, SEED_MIN_WIDTH) {
        return match_plain(m, params, depth, left, right, intervals, out);
    }
    if m.seeds.len() <= depth {
        m.seeds.resize_with(depth + 1, Default::default);
    }
    // (Taken out for the call, which borrows the matcher; put back whatever it returns.)
    let mut s = std::mem::take(&mut m.seeds[depth]);
    let result = s.seed(m, params, depth, left, right, intervals, span).and_then(|half| {
        let mut stats = match_plain(m, params, depth, left, right, &s.seeded, out)?;
        stats.evaluated += half.evaluated;
        Ok(stats)
    });
    m.seeds[depth] = s;
    result
}

/// The method's own call at level `depth`, each level of SGM with its own buffers.
fn match_plain(m: &mut StereoMatcher, params: &ValidMatchParams, depth: usize, left: GrayView, right: GrayView, intervals: &DisparityIntervals, out: &mut DisparityMap) -> Result<MatchStats, MatchError> {
    match params.method {
        Method::Bm => Ok(m.correlate(params, left, right, IntervalSource::Given(intervals), out)),
        Method::Sgm => {
            if m.sgm_levels.len() <= depth {
                m.sgm_levels.resize_with(depth + 1, Vec::new);
            }
            sgm_stripes(params, &mut m.sgm_levels[depth], left, right, intervals, out)
        }
    }
}

/// Whether `intervals` search at least `min_width` disparities a pixel on average, over an
/// image of at least two tiles each way.
fn wide(intervals: &DisparityIntervals, min_width: usize) -> bool {
    let w = intervals.width;
    if w < 2 * TILE_W || intervals.height < 2 * TILE_H {
        return false;
    }
    // Branch-free, and in 32 bits within a row (a row's pairs fit: 65 536 disparities times
    // the width), so that it vectorises.
    let (mut pixels, mut pairs) = (0u64, 0u64);
    for (lo, hi) in intervals.lo.chunks_exact(w).zip(intervals.hi.chunks_exact(w)) {
        let (mut px, mut pr) = (0u32, 0u32);
        for (&a, &b) in lo.iter().zip(hi) {
            let ok = a <= b;
            px += ok as u32;
            pr += if ok { (b as i32 - a as i32 + 1) as u32 } else { 0 };
        }
        (pixels, pairs) = (pixels + px as u64, pairs + pr as u64);
    }
    pixels > 0 && pairs >= min_width as u64 * pixels
}

/// The mean of each 2 × 2 block of `img`, rounded (the last column and row of an odd size
/// left out); returns the half size.
fn halve(img: GrayView, out: &mut Vec<u8>) -> (usize, usize) {
    let (w, h) = (img.width, img.height);
    let (cw, ch) = (w / 2, h / 2);
    out.clear();
    out.reserve(cw * ch);
    for y in 0..ch {
        let (a, b) = (&img.data[2 * y * w..][..2 * cw], &img.data[(2 * y + 1) * w..][..2 * cw]);
        out.extend(a.chunks_exact(2).zip(b.chunks_exact(2)).map(|(a, b)| ((a[0] as u16 + a[1] as u16 + b[0] as u16 + b[1] as u16 + 2) >> 2) as u8));
    }
    (cw, ch)
}

/// The half-size intervals of `iv` into `out` (`cw × ch`): each half-size pixel searches the
/// hull of its four pixels' searched intervals, halved outwards (`⌊lo / 2⌋ … ⌈hi / 2⌉`),
/// within `range`; nothing where none of the four searches.
fn halve_intervals(iv: &DisparityIntervals, (cw, ch): (usize, usize), range: (i32, i32), out: &mut DisparityIntervals) {
    let w = iv.width;
    (out.width, out.height) = (cw, ch);
    out.searched = None;
    // (Every element is written below.)
    out.lo.resize(cw * ch, 0);
    out.hi.resize(cw * ch, 0);
    let (cmin, cmax) = (range.0, range.1);
    for y in 0..ch {
        let (top, bottom) = (2 * y * w..2 * y * w + 2 * cw, (2 * y + 1) * w..(2 * y + 1) * w + 2 * cw);
        let (lo0, lo1, hi0, hi1) = (&iv.lo[top.clone()], &iv.lo[bottom.clone()], &iv.hi[top], &iv.hi[bottom]);
        let outs = out.lo[y * cw..(y + 1) * cw].iter_mut().zip(&mut out.hi[y * cw..(y + 1) * cw]);
        let ins = lo0.chunks_exact(2).zip(lo1.chunks_exact(2)).zip(hi0.chunks_exact(2).zip(hi1.chunks_exact(2)));
        for ((ol, oh), ((l0, l1), (h0, h1))) in outs.zip(ins) {
            let (mut lo, mut hi) = (i32::MAX, i32::MIN);
            for (l, h) in [(l0[0], h0[0]), (l0[1], h0[1]), (l1[0], h1[0]), (l1[1], h1[1])] {
                let ok = l <= h;
                lo = lo.min(if ok { l as i32 } else { i32::MAX });
                hi = hi.max(if ok { h as i32 } else { i32::MIN });
            }
            // (An arithmetic shift is the floor of a half, negative disparities included.)
            let (a, b) = ((lo >> 1).max(cmin), ((hi + 1) >> 1).min(cmax));
            let ok = lo <= hi && a <= b;
            (*ol, *oh) = (if ok { a as i16 } else { 1 }, if ok { b as i16 } else { 0 });
        }
    }
}

impl SeedScratch {
    /// Matches the pair at half size (level `depth + 1`) and writes `self.seeded`:
    /// `intervals`, each pixel's cut to its tile's band (see the module's text). Returns what
    /// the half-size call counted.
    #[allow(clippy::too_many_arguments)]
    fn seed(&mut self, m: &mut StereoMatcher, params: &ValidMatchParams, depth: usize, left: GrayView, right: GrayView, intervals: &DisparityIntervals, span: usize) -> Result<MatchStats, MatchError> {
        let (cw, ch) = halve(left, &mut self.left);
        halve(right, &mut self.right);
        let half = params.halved();
        halve_intervals(intervals, (cw, ch), (half.min_disparity, half.max_disparity()), &mut self.intervals);
        if (self.map.width, self.map.height) != (cw, ch) {
            self.map = DisparityMap::new(cw, ch);
        }
        let lv = GrayView { width: cw, height: ch, data: &self.left };
        let rv = GrayView { width: cw, height: ch, data: &self.right };
        // (Halved outwards, with one more for the rounding at each end.)
        let stats = match_level(m, &half, depth + 1, lv, rv, &self.intervals, span / 2 + 2, &mut self.map)?;
        cut_to_bands(intervals, &self.intervals, &self.map, &mut self.seeded);
        Ok(stats)
    }
}

/// `intervals` into `out`, each searched pixel's cut to the band of its matcher tile: the
/// hull of the half-size matches (`map`, over `half`'s searched pixels) over the tile and one
/// half-size pixel around it, doubled and widened by [`SEED_MARGIN`]. A tile where fewer
/// than a quarter of those searched pixels matched, and a pixel whose own interval misses
/// its band, keep their intervals.
fn cut_to_bands(intervals: &DisparityIntervals, half: &DisparityIntervals, map: &DisparityMap, out: &mut DisparityIntervals) {
    let (w, h) = (intervals.width, intervals.height);
    let (cw, ch) = (half.width, half.height);
    (out.width, out.height) = (w, h);
    out.searched = None;
    // (Every element is written below.)
    out.lo.resize(w * h, 0);
    out.hi.resize(w * h, 0);
    let map = map.values();
    // Each column's band over the tile row; a tile that keeps its intervals has the widest.
    let (mut band_lo, mut band_hi) = (vec![i16::MIN; w], vec![i16::MAX; w]);
    for ty in (0..h).step_by(TILE_H) {
        let y1 = (ty + TILE_H).min(h);
        for tx in (0..w).step_by(TILE_W) {
            let x1 = (tx + TILE_W).min(w);
            // The half-size pixels over the tile, and one around it; branch-free.
            let xs = (tx / 2).saturating_sub(1)..(x1.div_ceil(2) + 1).min(cw);
            let ys = (ty / 2).saturating_sub(1)..(y1.div_ceil(2) + 1).min(ch);
            let (mut searched, mut matched) = (0u32, 0u32);
            let (mut dlo, mut dhi) = (f32::INFINITY, f32::NEG_INFINITY);
            for y in ys {
                let row = y * cw + xs.start..y * cw + xs.end;
                for ((&d, &a), &b) in map[row.clone()].iter().zip(&half.lo[row.clone()]).zip(&half.hi[row]) {
                    let ok = !d.is_nan();
                    searched += (a <= b) as u32;
                    matched += ok as u32;
                    dlo = dlo.min(if ok { d } else { f32::INFINITY });
                    dhi = dhi.max(if ok { d } else { f32::NEG_INFINITY });
                }
            }
            let (blo, bhi) = if matched == 0 || 4 * matched < searched {
                (i16::MIN, i16::MAX)
            } else {
                let clamp = |v: f32| v.clamp(i16::MIN as f32, i16::MAX as f32) as i16;
                (clamp((2.0 * dlo).floor() - SEED_MARGIN as f32), clamp((2.0 * dhi).ceil() + SEED_MARGIN as f32))
            };
            band_lo[tx..x1].fill(blo);
            band_hi[tx..x1].fill(bhi);
        }
        // Each pixel's interval cut to its column's band, branch-free so that it vectorises.
        // (An unsearched pixel has lo > hi, so a > b: it stays as it was, unsearched; so does
        // a pixel whose own interval misses its band.)
        for y in ty..y1 {
            let row = y * w..(y + 1) * w;
            let ins = intervals.lo[row.clone()].iter().zip(&intervals.hi[row.clone()]).zip(band_lo.iter().zip(&band_hi));
            for ((ol, oh), ((&lo, &hi), (&blo, &bhi))) in out.lo[row.clone()].iter_mut().zip(&mut out.hi[row]).zip(ins) {
                let (a, b) = (lo.max(blo), hi.min(bhi));
                let cut = a <= b;
                (*ol, *oh) = (if cut { a } else { lo }, if cut { b } else { hi });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stereo::MatchParams;

    fn intervals(w: usize, h: usize, v: &[Option<(i16, i16)>]) -> DisparityIntervals {
        let mut iv = DisparityIntervals::empty(w, h);
        iv.searched = None;
        for (i, b) in v.iter().enumerate() {
            if let Some((lo, hi)) = *b {
                (iv.lo[i], iv.hi[i]) = (lo, hi);
            }
        }
        iv
    }

    #[test]
    fn half_size_intervals_are_the_hull_of_four_halved_outwards() {
        // Four half-size pixels (and an odd last column, left out): all searched; one of the
        // four; none; negative disparities, clipped to the half range.
        let full = intervals(
            9,
            2,
            &[
                Some((3, 9)), Some((0, 4)), Some((5, 5)), None, None, None, Some((-7, -3)), Some((-40, -6)), Some((0, 0)),
                Some((2, 2)), Some((1, 11)), None, None, None, None, None, Some((-1, -1)), Some((0, 0)),
            ],
        );
        let mut half = DisparityIntervals::empty(0, 0);
        halve_intervals(&full, (4, 1), (-16, 6), &mut half);
        assert_eq!((half.width, half.height), (4, 1));
        // ⌊0 / 2⌋ … ⌈11 / 2⌉; ⌊5 / 2⌋ … ⌈5 / 2⌉; nothing; ⌊−40 / 2⌋ = −20 → −16 … ⌈−1 / 2⌉ = 0.
        assert_eq!(half.lo, [0, 2, 1, -16]);
        assert_eq!(half.hi, [6, 3, 0, 0]);
    }

    #[test]
    fn the_half_size_range_holds_the_disparities_whose_double_is_in_range() {
        let half = |min_disparity, num_disparities| {
            let p = MatchParams { min_disparity, num_disparities, ..MatchParams::for_method(crate::stereo::Method::Sgm) }.validate().unwrap().halved();
            (p.min_disparity, p.max_disparity())
        };
        assert_eq!(half(0, 128), (0, 63));
        assert_eq!(half(-127, 128), (-63, 0));
        assert_eq!(half(5, 96), (3, 50));
        assert_eq!(half(-3, 1), (-1, -1));
    }

    #[test]
    fn each_tile_searches_around_its_half_size_matches() {
        // Three tiles of 32 × 16 in a row (96 × 16); at half size, matched at 10 … 12; a
        // quarter matched at −3; an eighth matched.
        let (w, h) = (96, 16);
        let full = DisparityIntervals::full(w, h, -40, 60);
        let (cw, ch) = (48, 8);
        let half = DisparityIntervals::full(cw, ch, -20, 30);
        let mut map = DisparityMap::new(cw, ch);
        for y in 0..ch {
            for x in 0..cw {
                let d = match x {
                    // (Columns 16 and 32 are the next tiles' border: 10 … 12 there too.)
                    0..=16 => Some(10.0 + (x % 3) as f32),
                    17..=31 => (x % 2 == 0 && y % 2 == 0).then_some(-3.0),
                    32 => Some(11.0),
                    _ => (x % 8 == 0).then_some(25.0),
                };
                map.values_mut()[y * cw + x] = d.unwrap_or(f32::NAN);
            }
        }
        let mut out = DisparityIntervals::empty(0, 0);
        cut_to_bands(&full, &half, &map, &mut out);
        // Tile 0 (half-size columns 0 … 16): 2 · 10 − 4 … 2 · 12 + 4.
        assert_eq!(out.get(5, 3), Some((16, 28)));
        // Tile 1 (half-size columns 15 … 32, 144 pixels): 15 and 16 at 10 and 11, 32 at 11,
        // seven columns at −3 on four rows: 52 matched, over a quarter: −6 − 4 … 22 + 4.
        assert_eq!(out.get(40, 10), Some((-10, 26)));
        // Tile 2 (columns 31 … 47, 136 pixels): 32 and 40 matched, 16 pixels, fewer than a
        // quarter: its intervals as they were.
        assert_eq!(out.get(80, 15), Some((-40, 60)));

        // A pixel searching nothing stays so; one whose interval misses its band keeps it.
        let mut own = full.clone();
        own.set(1, 1, None);
        own.set(2, 1, Some((40, 50)));
        own.set(3, 1, Some((20, 50)));
        cut_to_bands(&own, &half, &map, &mut out);
        assert_eq!((out.get(1, 1), out.get(2, 1), out.get(3, 1)), (None, Some((40, 50)), Some((20, 28))));
    }

    /// A textured plane at disparity `back` with a textured rectangle at `front` before it.
    fn two_planes(w: usize, h: usize, back: usize, front: usize) -> (Vec<u8>, Vec<u8>, impl Fn(usize, usize) -> usize) {
        let depth = move |x: usize, y: usize| if (70..170).contains(&x) && (30..80).contains(&y) { front } else { back };
        let mut state = 7u32;
        let mut noise = || {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 24) as u8
        };
        // Each plane's texture, by the left pixel that sees it.
        let (tex_back, tex_front): (Vec<u8>, Vec<u8>) = (0..w * h).map(|_| (noise(), noise())).unzip();
        let left: Vec<u8> = (0..w * h).map(|i| if depth(i % w, i / w) == front { tex_front[i] } else { tex_back[i] }).collect();
        // Right pixel xr sees the front plane where left pixel xr + front is on it, the back
        // plane otherwise (left pixel xr + back; the texture past the image is the first row's).
        let mut right = vec![0u8; w * h];
        for y in 0..h {
            for xr in 0..w {
                let xf = xr + front;
                right[y * w + xr] = if xf < w && depth(xf, y) == front { tex_front[y * w + xf] } else { tex_back[(y * w + xr + back) % (w * h)] };
            }
        }
        (left, right, depth)
    }

    fn run(method: Method, seed: bool, min_disparity: i32, l: &[u8], r: &[u8], w: usize, h: usize) -> (DisparityMap, MatchStats) {
        let p = MatchParams { coarse_to_fine: seed, min_disparity, num_disparities: 128, threads: 1, speckle_window: 0, ..MatchParams::for_method(method) };
        let mut m = StereoMatcher::new(p.validate().unwrap());
        let mut out = DisparityMap::new(w, h);
        let iv = m.full_intervals(w, h, None);
        let stats = m.compute(GrayView::new(w, h, l).unwrap(), GrayView::new(w, h, r).unwrap(), &iv, &mut out).unwrap();
        (out, stats)
    }

    #[test]
    fn a_seeded_search_finds_both_sides_of_a_depth_edge_with_less_work_with_either_method() {
        let (w, h) = (256, 112);
        let (l, r, depth) = two_planes(w, h, 20, 100);
        // Right of the range's reach (x ≥ 128), away from the rectangle's occluded strip.
        let good = |map: &DisparityMap, front: bool| {
            let px = (0..h).flat_map(|y| (128..w).map(move |x| (x, y))).filter(|&(x, y)| (depth(x, y) == 100) == front);
            let (n, ok) = px.fold((0, 0), |(n, ok), (x, y)| (n + 1, ok + map.get(x, y).is_some_and(|d| (d - depth(x, y) as f32).abs() <= 1.0) as usize));
            ok as f64 / n as f64
        };
        for method in [Method::Sgm, Method::Bm] {
            let ((seeded, s), (full, f)) = (run(method, true, 0, &l, &r, w, h), run(method, false, 0, &l, &r, w, h));
            for front in [true, false] {
                let (a, b) = (good(&seeded, front), good(&full, front));
                // SGM's bar is the one it had alone; `bm` leaves a few more of the rectangle's
                // edge pixels unmatched whether seeded or not (0.963 of the front at full range).
                let floor = if method == Method::Sgm { 0.97 } else { 0.95 };
                assert!(a >= floor && a >= b - 0.01, "{method}, front {front}: {a} seeded, {b} full");
            }
            // Fewer pairs searched, the half-size call's included, though the tiles along the
            // rectangle's edges search both planes' disparities.
            assert!(s.evaluated * 4 < f.evaluated * 3, "{method}: {} seeded, {} full", s.evaluated, f.evaluated);
        }
    }

    #[test]
    fn negative_ranges_are_seeded_too() {
        // The same scene seen with the images swapped: disparities −20 and −100.
        let (w, h) = (256, 112);
        let (l, r, _) = two_planes(w, h, 20, 100);
        let ((seeded, s), (_, f)) = (run(Method::Sgm, true, -127, &r, &l, w, h), run(Method::Sgm, false, -127, &r, &l, w, h));
        // The rows above and below the rectangle, where both images see the back plane alone.
        let back = (0..h).filter(|y| !(30..80).contains(y)).flat_map(|y| (0..200).map(move |x| (x, y)));
        let (n, ok) = back.fold((0, 0), |(n, ok), (x, y)| (n + 1, ok + seeded.get(x, y).is_some_and(|d| (d + 20.0).abs() <= 1.0) as usize));
        assert!(ok * 100 >= n * 95, "{ok} of {n} at −20");
        assert!(s.evaluated * 4 < f.evaluated * 3, "{} seeded, {} full", s.evaluated, f.evaluated);
    }
}
