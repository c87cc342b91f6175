//! Speckle filter: removes small connected blobs of disparities (OpenCV `filterSpeckles`).

use super::matcher::DisparityMap;

/// Reusable buffers of the speckle filter.
#[derive(Default)]
pub struct SpeckleFilter {
    labels: Vec<u32>,
    stack: Vec<u32>,
    region: Vec<u32>,
}

impl SpeckleFilter {
    /// Invalidates every 4-connected region (neighbours differing by at most `range_px`) of at
    /// most `max_size` pixels.
    pub fn apply(&mut self, map: &mut DisparityMap, max_size: usize, range_px: f32) {
        let (w, h) = (map.width, map.height);
        debug_assert!(w < 1 << 16 && h < 1 << 16);
        self.labels.clear();
        self.labels.resize(w * h, 0);
        let data = map.values_mut();
        let mut next_label = 0u32;
        for start in 0..w * h {
            if self.labels[start] != 0 || !data[start].is_finite() {
                continue;
            }
            next_label += 1;
            self.labels[start] = next_label;
            self.stack.clear();
            self.region.clear();
            // Stack entries are packed (y << 16) | x, so no division per pixel.
            self.stack.push((((start / w) << 16) | (start % w)) as u32);
            while let Some(packed) = self.stack.pop() {
                let (x, y) = ((packed & 0xffff) as usize, (packed >> 16) as usize);
                let i = y * w + x;
                // Only small regions are ever erased, so only their pixels are kept.
                if self.region.len() <= max_size {
                    self.region.push(i as u32);
                }
                let d = data[i];
                let mut visit = |j: usize, xx: usize, yy: usize| {
                    if self.labels[j] == 0 && (data[j] - d).abs() <= range_px {
                        // NaN fails the comparison, so holes are never joined.
                        self.labels[j] = next_label;
                        self.stack.push(((yy << 16) | xx) as u32);
                    }
                };
                if x > 0 {
                    visit(i - 1, x - 1, y);
                }
                if x + 1 < w {
                    visit(i + 1, x + 1, y);
                }
                if y > 0 {
                    visit(i - w, x, y - 1);
                }
                if y + 1 < h {
                    visit(i + w, x, y + 1);
                }
            }
            if self.region.len() <= max_size {
                for &i in &self.region {
                    data[i as usize] = f32::NAN;
                }
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
}
