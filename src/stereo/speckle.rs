//! Speckle filter: removes small connected blobs of disparities (what OpenCV's
//! `filterSpeckles` does), by connected components over row runs.
//!
//! A run is a maximal horizontal stretch of valid pixels whose neighbours differ by at most
//! the range. Runs of adjacent rows are joined (union–find) wherever two vertically adjacent
//! pixels are within the range. Each valid pixel is compared twice (left, above) and written
//! once, invalid pixels are only skipped, and a run's size is counted when it ends — instead
//! of the four neighbour visits and stack traffic of a flood fill.

use super::disparity::DisparityMap;

/// Reusable buffers of the speckle filter.
#[derive(Default)]
pub struct SpeckleFilter {
    /// Run id of each pixel of the previous and current row (valid pixels only).
    run_prev: Vec<u32>,
    run_cur: Vec<u32>,
    /// Per run: union–find parent, pixel count (at the root), row and span.
    parent: Vec<u32>,
    size: Vec<u32>,
    span: Vec<(u32, u32, u32)>,
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
        self.parent.clear();
        self.size.clear();
        self.span.clear();
        self.run_prev.clear();
        self.run_prev.resize(w, u32::MAX);
        self.run_cur.clear();
        self.run_cur.resize(w, u32::MAX);
        let data = map.values_mut();
        for y in 0..h {
            let row = &data[y * w..(y + 1) * w];
            self.run_cur.fill(u32::MAX);
            // Runs of this row (a run's pixels are counted when it ends). A NaN or infinite
            // pixel never continues a run: its difference to the previous one is not ≤ range.
            let first_run = self.parent.len();
            let mut x = 0;
            while x < w {
                if !row[x].is_finite() {
                    x += 1;
                    continue;
                }
                let id = self.parent.len() as u32;
                let start = x;
                self.run_cur[x] = id;
                x += 1;
                while x < w && (row[x] - row[x - 1]).abs() <= range_px {
                    self.run_cur[x] = id;
                    x += 1;
                }
                self.parent.push(id);
                self.size.push((x - start) as u32);
                self.span.push((y as u32, start as u32, (x - 1) as u32));
            }
            // Join with the runs above, visiting this row's runs only.
            if y > 0 {
                let above = &data[(y - 1) * w..y * w];
                let here = &data[y * w..(y + 1) * w];
                for run in first_run..self.parent.len() {
                    let (_, x0, x1) = self.span[run];
                    let mut last = u32::MAX;
                    for x in x0 as usize..=x1 as usize {
                        let b = self.run_prev[x];
                        if b == u32::MAX || b == last {
                            continue;
                        }
                        // NaN never gets here: both pixels belong to runs.
                        if (here[x] - above[x]).abs() <= range_px {
                            self.union(run as u32, b);
                            last = b;
                        }
                    }
                }
            }
            std::mem::swap(&mut self.run_prev, &mut self.run_cur);
        }
        for run in 0..self.parent.len() as u32 {
            let root = self.find(run);
            if self.size[root as usize] as usize <= max_size {
                let (y, x0, x1) = self.span[run as usize];
                data[y as usize * w + x0 as usize..=y as usize * w + x1 as usize].fill(f32::NAN);
            }
        }
    }
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
    fn steps_larger_than_the_range_split_regions() {
        let (w, h) = (12, 4);
        let vals: Vec<f32> = (0..w * h).map(|i| if i % w < 6 { 10.0 } else { 14.0 }).collect();
        let mut map = DisparityMap::from_values(w, h, vals);
        SpeckleFilter::default().apply(&mut map, 24, 1.0);
        assert_eq!(map.valid_count(), 0, "two regions of 24 pixels, both removed");
    }

    #[test]
    fn agrees_with_a_flood_fill_on_random_maps() {
        // Random maps of a few disparity levels, holes and noise: the runs-and-union filter
        // must remove exactly the 4-connected regions (within the range) a flood fill finds
        // of at most the size limit.
        let mut state = 7u32;
        let mut rand = move |m: u32| {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) % m
        };
        for (w, h, max_size, range) in [(23, 17, 6, 0.5f32), (40, 9, 20, 1.0), (1, 30, 3, 0.5), (30, 1, 3, 0.5)] {
            let vals: Vec<f32> = (0..w * h)
                .map(|_| match rand(10) {
                    0 | 1 => f32::NAN,
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
        }
    }
}
