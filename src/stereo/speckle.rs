//! Speckle filter: removes small connected blobs of disparities (what OpenCV's
//! `filterSpeckles` does), by connected components over row runs.
//!
//! A run is a maximal horizontal stretch of valid pixels whose neighbours differ by at most
//! the range. Runs of adjacent rows are joined (union–find) wherever two vertically adjacent
//! pixels are within the range. Each pixel is compared twice (left, above) and written once,
//! instead of the four neighbour visits and stack traffic of a flood fill.

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
    fn find(&mut self, mut a: u32) -> u32 {
        while self.parent[a as usize] != a {
            let up = self.parent[self.parent[a as usize] as usize];
            self.parent[a as usize] = up;
            a = up;
        }
        a
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
            // Runs of this row.
            let mut current = u32::MAX;
            for x in 0..w {
                let d = row[x];
                if !d.is_finite() {
                    self.run_cur[x] = u32::MAX;
                    current = u32::MAX;
                    continue;
                }
                if current == u32::MAX || (d - row[x - 1]).abs() > range_px {
                    current = self.parent.len() as u32;
                    self.parent.push(current);
                    self.size.push(0);
                    self.span.push((y as u32, x as u32, x as u32));
                }
                self.size[current as usize] += 1;
                self.span[current as usize].2 = x as u32;
                self.run_cur[x] = current;
            }
            // Join with the runs above.
            if y > 0 {
                let above = &data[(y - 1) * w..y * w];
                let mut last = (u32::MAX, u32::MAX);
                for x in 0..w {
                    let (a, b) = (self.run_cur[x], self.run_prev[x]);
                    if a == u32::MAX || b == u32::MAX || (a, b) == last {
                        continue;
                    }
                    // NaN never gets here: both pixels belong to runs.
                    if (data[y * w + x] - above[x]).abs() <= range_px {
                        self.union(a, b);
                        last = (a, b);
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
}
