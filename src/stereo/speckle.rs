//! Speckle filter: removes small connected blobs of disparities (what OpenCV's
//! `filterSpeckles` does), by connected components over row runs.
//!
//! A run is a maximal horizontal stretch of valid pixels whose neighbours differ by at most
//! the range. Runs of adjacent rows are joined (union–find) wherever two vertically adjacent
//! pixels are within the range. Each row's comparisons (valid, joined to the right, joined to
//! the pixel above) are made once, eight pixels at a time, into bit masks; runs are then found
//! by scanning the masks' words, and a run meets each run above it once — at the first pixel
//! that links them, the rest of that run's span skipped — instead of the four neighbour
//! visits and stack traffic of a flood fill, or a branch per pixel.

use std::ops::Range;

use super::disparity::DisparityMap;

/// Reusable buffers of the speckle filter.
#[derive(Default)]
pub struct SpeckleFilter {
    /// Run id of each pixel of the previous and current row (read only where the pixel is
    /// valid: stale elsewhere).
    run_prev: Vec<u32>,
    run_cur: Vec<u32>,
    /// Per run: union–find parent, pixel count (at the root), row and span.
    parent: Vec<u32>,
    size: Vec<u32>,
    span: Vec<(u32, u32, u32)>,
    /// Bit masks of the current row, 64 pixels a word: finite pixels; pixels `x` joined to
    /// `x + 1` (both within the range); pixels joined to the pixel above.
    valid: Vec<u64>,
    joined: Vec<u64>,
    linked: Vec<u64>,
}

impl SpeckleFilter {
    fn find(&mut self, a: u32) -> u32 {
        crate::disjoint::root(&mut self.parent, a)
    }

    fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            let (big, small) = if self.size[ra as usize] >= self.size[rb as usize] { (ra, rb) } else { (rb, ra) };
            self.parent[small as usize] = big;
            self.size[big as usize] += self.size[small as usize];
        }
    }

    /// Invalidates every 4-connected region (neighbours differing by at most `range_px`) of at
    /// most `max_size` pixels.
    pub fn apply(&mut self, map: &mut DisparityMap, max_size: usize, range_px: f32) {
        let (w, h) = (map.width, map.height);
        self.apply_within(map, 0..w, 0..h, max_size, range_px);
    }

    /// [`SpeckleFilter::apply`] over a map with no disparity outside columns `xs` and rows
    /// `ys` (a matcher call's searched pixels): the regions are the same, found without
    /// visiting the rest.
    pub fn apply_within(&mut self, map: &mut DisparityMap, xs: Range<usize>, ys: Range<usize>, max_size: usize, range_px: f32) {
        assert!(xs.end <= map.width && ys.end <= map.height, "columns {xs:?} and rows {ys:?} inside a {}×{} map", map.width, map.height);
        if xs.is_empty() || ys.is_empty() {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { self.apply_avx2(map, xs, ys, max_size, range_px) };
        }
        self.apply_impl::<false>(map, xs, ys, max_size, range_px)
    }

    /// [`SpeckleFilter::apply_within`] with the row masks built in AVX2 registers.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn apply_avx2(&mut self, map: &mut DisparityMap, xs: Range<usize>, ys: Range<usize>, max_size: usize, range_px: f32) {
        self.apply_impl::<true>(map, xs, ys, max_size, range_px)
    }

    /// The filter over columns `xs` and rows `ys` (not empty); `AVX2`: the CPU has AVX2 (and
    /// the caller is compiled for it). Positions in the runs are counted from `xs.start`.
    #[inline(always)]
    fn apply_impl<const AVX2: bool>(&mut self, map: &mut DisparityMap, xs: Range<usize>, ys: Range<usize>, max_size: usize, range_px: f32) {
        let (stride, x0) = (map.width, xs.start);
        let w = xs.len();
        self.parent.clear();
        self.size.clear();
        self.span.clear();
        self.run_prev.clear();
        self.run_prev.resize(w, u32::MAX);
        self.run_cur.clear();
        self.run_cur.resize(w, u32::MAX);
        let words = w.div_ceil(64);
        for v in [&mut self.valid, &mut self.joined, &mut self.linked] {
            v.clear();
            v.resize(words, 0);
        }
        let data = map.values_mut();
        let row_of = |y: usize| y * stride + x0..y * stride + x0 + w;
        for y in ys.clone() {
            let row = &data[row_of(y)];
            // The row's masks, branch-free (they vectorise). A NaN or infinite pixel is not
            // valid and joins nothing: its difference to any pixel is not ≤ range.
            bits::<AVX2>(row, row, &mut self.valid, None);
            bits::<AVX2>(&row[1.min(w)..], &row[..w.saturating_sub(1)], &mut self.joined, Some(range_px));
            // (Bits from w − 1 on stay clear in `joined`: a run ends at the row's end.)
            // Runs of this row: from each valid pixel not joined to its left neighbour to the
            // first pixel not joined to its right one.
            let first_run = self.parent.len();
            let mut x = next_set(&self.valid, 0, w);
            while x < w {
                let end = next_clear(&self.joined, x);
                let id = self.parent.len() as u32;
                self.run_cur[x..=end].fill(id);
                self.parent.push(id);
                self.size.push((end + 1 - x) as u32);
                self.span.push((y as u32, x as u32, end as u32));
                x = next_set(&self.valid, end + 1, w);
            }
            // Join with the runs above, visiting this row's runs only: each run above is
            // joined at the first pixel that links to it, and the rest of its span is skipped.
            if y > ys.start {
                let (above, here) = (&data[row_of(y - 1)], &data[row_of(y)]);
                bits::<AVX2>(here, above, &mut self.linked, Some(range_px));
                for run in first_run..self.parent.len() {
                    let (_, x0, x1) = self.span[run];
                    let mut x = next_set(&self.linked, x0 as usize, w);
                    while x <= x1 as usize {
                        // A linked pixel's neighbour above is valid, so it has a run.
                        let b = self.run_prev[x];
                        self.union(run as u32, b);
                        x = next_set(&self.linked, self.span[b as usize].2 as usize + 1, w);
                    }
                }
            }
            std::mem::swap(&mut self.run_prev, &mut self.run_cur);
        }
        for run in 0..self.parent.len() as u32 {
            let root = self.find(run);
            if self.size[root as usize] as usize <= max_size {
                let (y, a, b) = self.span[run as usize];
                let row = row_of(y as usize);
                data[row.start + a as usize..=row.start + b as usize].fill(f32::NAN);
            }
        }
    }
}

/// Bit `x` of `out` (64 a word, the rest of the words clear): with `within = Some(range)`,
/// whether `|a[x] − b[x]| ≤ range`; with `None`, whether `a[x]` is finite. False for NaN.
/// `AVX2`: eight pixels a compare and a `movemask` (the CPU has AVX2).
#[inline(always)]
fn bits<const AVX2: bool>(a: &[f32], b: &[f32], out: &mut [u64], within: Option<f32>) {
    let test = |x: f32, y: f32| match within {
        Some(range) => (x - y).abs() <= range,
        None => x.is_finite(),
    };
    out.fill(0);
    for (word, (ca, cb)) in out.iter_mut().zip(a.chunks(64).zip(b.chunks(64))) {
        let mut done = 0;
        #[cfg(target_arch = "x86_64")]
        if AVX2 {
            use std::arch::x86_64::*;
            let n = ca.len().min(cb.len()) / 8 * 8;
            // SAFETY: the caller's CPU has AVX2 (the parameter's contract); loads of eight
            // from j < n ≤ both chunks' lengths.
            unsafe {
                let (sign, range) = (_mm256_set1_ps(-0.0), _mm256_set1_ps(within.unwrap_or(0.0)));
                for j in (0..n).step_by(8) {
                    let x = _mm256_loadu_ps(ca.as_ptr().add(j));
                    let ok = match within {
                        Some(_) => _mm256_cmp_ps::<_CMP_LE_OQ>(_mm256_andnot_ps(sign, _mm256_sub_ps(x, _mm256_loadu_ps(cb.as_ptr().add(j)))), range),
                        None => _mm256_cmp_ps::<_CMP_EQ_OQ>(_mm256_sub_ps(x, x), _mm256_setzero_ps()),
                    };
                    *word |= (_mm256_movemask_ps(ok) as u32 as u64) << j;
                }
            }
            done = n;
        }
        for (j, (&x, &y)) in ca.iter().zip(cb).enumerate().skip(done) {
            *word |= (test(x, y) as u64) << j;
        }
    }
}

/// The first set bit at or after `from`, or `n` (the bits' length) when there is none.
fn next_set(m: &[u64], from: usize, n: usize) -> usize {
    let mut i = from / 64;
    if i >= m.len() {
        return n;
    }
    let mut word = m[i] & (u64::MAX << (from % 64));
    loop {
        if word != 0 {
            return (i * 64 + word.trailing_zeros() as usize).min(n);
        }
        i += 1;
        if i == m.len() {
            return n;
        }
        word = m[i];
    }
}

/// The first clear bit at or after `from`; the mask must hold one (a clear bit past the
/// row's last pixel).
fn next_clear(m: &[u64], from: usize) -> usize {
    let mut i = from / 64;
    let mut word = !m[i] & (u64::MAX << (from % 64));
    while word == 0 {
        i += 1;
        word = !m[i];
    }
    i * 64 + word.trailing_zeros() as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn removes_small_blobs_keeps_large_ones() {
        let (w, h) = (20, 10);
        let mut vals = vec![5.0f32; w * h];
        // A 2×2 blob at a different depth, and a hole.
        for (x, y) in [(3, 3), (4, 3), (3, 4), (4, 4)] {
            vals[y * w + x] = 30.0;
        }
        vals[9 * w + 19] = f32::NAN;
        let mut map = DisparityMap::from_values(w, h, vals);
        SpeckleFilter::default().apply(&mut map, 10, 1.0);
        assert!(map.get(3, 3).is_none() && map.get(4, 4).is_none());
        assert_eq!(map.get(0, 0), Some(5.0));
        assert_eq!(map.valid_count(), w * h - 5);
    }

    #[test]
    fn a_u_shaped_region_is_one_region() {
        // Two vertical bars joined only at the bottom: the runs of the top rows belong to
        // different components until the last row joins them.
        let (w, h) = (7, 6);
        let mut vals = vec![f32::NAN; w * h];
        for y in 0..h {
            vals[y * w + 1] = 9.0;
            vals[y * w + 5] = 9.0;
        }
        for x in 1..=5 {
            vals[(h - 1) * w + x] = 9.0;
        }
        let mut map = DisparityMap::from_values(w, h, vals.clone());
        // 6 + 6 + 3 = 15 pixels: kept with a limit of 14, removed with 15.
        SpeckleFilter::default().apply(&mut map, 14, 0.5);
        assert_eq!(map.valid_count(), 15);
        let mut map = DisparityMap::from_values(w, h, vals);
        SpeckleFilter::default().apply(&mut map, 15, 0.5);
        assert_eq!(map.valid_count(), 0);
    }

    #[test]
    fn a_run_above_joins_through_its_first_pixel_alone() {
        // Above: a run of four at 1 and a one-pixel run at 3 right after it; below: one run
        // climbing from 1 to 5 that meets the one-pixel run at its only pixel. The join
        // skips the rest of each run above it has met: the pixel right after must count.
        let n = f32::NAN;
        let vals = vec![1.0, 1.0, 1.0, 1.0, 3.0, n, n, n, 1.0, 1.0, 1.0, 1.8, 2.6, 3.4, 4.2, 5.0];
        let mut map = DisparityMap::from_values(8, 2, vals);
        SpeckleFilter::default().apply(&mut map, 5, 1.0);
        assert_eq!(map.valid_count(), 13, "one region of 13 pixels, kept");
    }

    #[test]
    fn steps_larger_than_the_range_split_regions() {
        let (w, h) = (12, 4);
        let vals: Vec<f32> = (0..w * h).map(|i| if i % w < 6 { 10.0 } else { 14.0 }).collect();
        let mut map = DisparityMap::from_values(w, h, vals);
        SpeckleFilter::default().apply(&mut map, 24, 1.0);
        assert_eq!(map.valid_count(), 0, "two regions of 24 pixels, both removed");
    }

    #[test]
    fn agrees_with_a_flood_fill_on_random_maps() {
        // Random maps of a few disparity levels, holes (NaN and infinite) and noise, rows of
        // one to three mask words: the runs-and-union filter must remove exactly the
        // 4-connected regions (within the range) a flood fill finds of at most the size limit.
        let mut state = 7u32;
        let mut rand = move |m: u32| {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) % m
        };
        for (w, h, max_size, range) in [(23, 17, 6, 0.5f32), (40, 9, 20, 1.0), (1, 30, 3, 0.5), (30, 1, 3, 0.5), (64, 6, 10, 0.5), (65, 5, 10, 0.5), (150, 8, 25, 1.0)] {
            let vals: Vec<f32> = (0..w * h)
                .map(|_| match rand(10) {
                    0 => f32::NAN,
                    1 => if rand(2) == 0 { f32::INFINITY } else { f32::NEG_INFINITY },
                    k => (k / 3) as f32 * 2.0 + rand(3) as f32 * 0.3,
                })
                .collect();
            let mut map = DisparityMap::from_values(w, h, vals.clone());
            SpeckleFilter::default().apply(&mut map, max_size, range);
            // The reference: flood fill from every pixel.
            let mut label = vec![usize::MAX; w * h];
            let mut expected = vals.clone();
            for seed in 0..w * h {
                if !vals[seed].is_finite() || label[seed] != usize::MAX {
                    continue;
                }
                let (mut stack, mut members) = (vec![seed], Vec::new());
                label[seed] = seed;
                while let Some(i) = stack.pop() {
                    members.push(i);
                    let (x, y) = (i % w, i / w);
                    let mut near = Vec::new();
                    if x > 0 { near.push(i - 1) }
                    if x + 1 < w { near.push(i + 1) }
                    if y > 0 { near.push(i - w) }
                    if y + 1 < h { near.push(i + w) }
                    for j in near {
                        if vals[j].is_finite() && label[j] == usize::MAX && (vals[j] - vals[i]).abs() <= range {
                            label[j] = seed;
                            stack.push(j);
                        }
                    }
                }
                if members.len() <= max_size {
                    for i in members {
                        expected[i] = f32::NAN;
                    }
                }
            }
            let got = map.values();
            assert!(got.iter().zip(&expected).all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())), "{w}×{h}");
            // The portable masks (other CPUs) too.
            let mut portable = DisparityMap::from_values(w, h, vals.clone());
            SpeckleFilter::default().apply_impl::<false>(&mut portable, 0..w, 0..h, max_size, range);
            assert!(portable.values().iter().zip(&expected).all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())), "{w}×{h}, portable");
            // Within a rectangle outside which the map holds no disparity (a matcher call's
            // searched pixels), against the filter over the whole of the same map, through
            // the dispatch and the portable masks: the same regions. (It fails when positions
            // inside the rectangle are taken from the map's edge.)
            let (xs, ys) = (w / 5..w - w / 4, h / 4..h - h / 5);
            let cut: Vec<f32> = (0..w * h).map(|i| if xs.contains(&(i % w)) && ys.contains(&(i / w)) { vals[i] } else { f32::NAN }).collect();
            let mut whole = DisparityMap::from_values(w, h, cut.clone());
            SpeckleFilter::default().apply(&mut whole, max_size, range);
            for dispatched in [false, true] {
                let mut within = DisparityMap::from_values(w, h, cut.clone());
                let mut f = SpeckleFilter::default();
                if dispatched {
                    f.apply_within(&mut within, xs.clone(), ys.clone(), max_size, range);
                } else {
                    f.apply_impl::<false>(&mut within, xs.clone(), ys.clone(), max_size, range);
                }
                assert!(within.values().iter().zip(whole.values()).all(|(a, b)| a.to_bits() == b.to_bits()), "{w}×{h} within {xs:?} × {ys:?}, dispatched {dispatched}");
            }
        }
    }
}
