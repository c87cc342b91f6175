//! Semi-global matching in one pass down the image (`sgm_paths = 5`): the paths from the
//! left, the upper left, above and the upper right as the pass steps each row left to
//! right, then the path from the right over the same row, right to left — OpenCV SGBM's five
//! directions of its single-pass mode. A row's sums are complete when its two sweeps are done,
//! so it is selected at once, and nothing is kept from row to row but the paths' last row:
//! the costs and sums are one row long. No volume: the call's memory does not grow with the
//! image's area times the range, and its first call pays no page faults for one.

use std::ops::Range;

use super::{has_vpopcnt, step, From, Geo, Sgm};
use crate::stereo::disparity::MatchStats;
use crate::stereo::params::ValidMatchParams;

impl Sgm {
    /// The single pass over rows `0 … h`, keeping (selecting into `out`) the rows `keep`.
    /// `off` holds each pixel's offset from its row's start ([`Sgm::bands`] `per_row`).
    #[inline(always)]
    pub(super) fn single_pass<const AVX2: bool>(&mut self, p: &ValidMatchParams, g: Geo, left: &[u8], keep: Range<usize>, out: &mut [f32], stats: &mut MatchStats) {
        let Geo { w, h, n, .. } = g;
        for r in self.vert_prev.iter_mut().chain(self.vert_cur.iter_mut()) {
            r.fit(w, n);
        }
        self.h_prev.fit(1, n);
        self.h_cur.fit(1, n);
        let vpopcnt = AVX2 && has_vpopcnt();
        for y in 0..h {
            self.costs_row::<AVX2>(p, g, left, y, 0, vpopcnt);
            self.sweep::<AVX2, false>(p, g, y);
            self.sweep::<AVX2, true>(p, g, y);
            std::mem::swap(&mut self.vert_prev, &mut self.vert_cur);
            if keep.contains(&y) {
                self.select::<AVX2>(p, g, y, &mut out[y * w..][..w], stats);
            }
        }
    }

    /// One sweep of row `y` over its span: left to right with the three paths from the row
    /// above and the one from the left, writing the row's sums (`BACK = false`); or right to
    /// left with the path from the right, adding it to them (`BACK = true`).
    #[inline(always)]
    fn sweep<const AVX2: bool, const BACK: bool>(&mut self, p: &ValidMatchParams, g: Geo, y: usize) {
        let Geo { w, n, .. } = g;
        let (p1, p2) = (p.p1, p.p2);
        let span = self.span[y].clone();
        let mut h_live = false;
        for k in 0..span.len() {
            let x = if BACK { span.end - 1 - k } else { span.start + k };
            let i = y * w + x;
            let m = self.band_m[i] as usize;
            if m == 0 {
                h_live = false;
                continue;
            }
            let a = self.band_a[i] as usize;
            let hf = if h_live { From::after(&self.h_prev, 0, n, a, m, p2) } else { From::start(&self.fresh, a, m) };
            self.h_cur.prepare(0, n, a, m);
            let o = self.off[i];
            let (c, s) = (&self.cost[o..][..m], &mut self.sum[o..][..m]);
            let mh = if BACK {
                let [mh] = step::<AVX2, 1>(c, [hf], p1, [self.h_cur.band_mut(0, n, a, m)], s, true, false);
                mh
            } else {
                let mut vf = [From::start(&self.fresh, a, m); 3];
                for (j, f) in vf.iter_mut().enumerate() {
                    // From x − 1, x and x + 1 of the row above, where that pixel searched.
                    let qx = (x + j).wrapping_sub(1);
                    if y > 0 && qx < w && self.band_m[i - w + qx - x] > 0 {
                        *f = From::after(&self.vert_prev[j], qx, n, a, m, p2);
                    }
                }
                let [v0, v1, v2] = &mut self.vert_cur;
                v0.prepare(x, n, a, m);
                v1.prepare(x, n, a, m);
                v2.prepare(x, n, a, m);
                let outs = [v0.band_mut(x, n, a, m), v1.band_mut(x, n, a, m), v2.band_mut(x, n, a, m), self.h_cur.band_mut(0, n, a, m)];
                let [m0, m1, m2, mh] = step::<AVX2, 4>(c, [vf[0], vf[1], vf[2], hf], p1, outs, s, false, false);
                (v0.min[x], v1.min[x], v2.min[x]) = (m0, m1, m2);
                mh
            };
            self.h_cur.min[0] = mh;
            std::mem::swap(&mut self.h_prev, &mut self.h_cur);
            h_live = true;
        }
    }
}
