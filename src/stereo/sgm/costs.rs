//! A row's census costs: every searched pixel's band, in runs of pixels that share one.

use std::ops::Range;

use super::census::{costs, Pixel};
#[cfg(target_arch = "x86_64")]
use super::{census::Run, simd};
use super::{all_eq, Geo, Sgm, LANES};
use crate::stereo::params::ValidMatchParams;

/// A run of `len` pixels grown by chunks while `holds(k, c)` (the `c` pixels from the run's
/// `k`-th on continue it): chunks of [`LANES`], each twice the last while they hold, back to
/// `LANES` at the first that does not, as long as `LANES` more fit in `end`. The caller goes
/// on one by one. (Asking the whole rest of the span first, as the runs did, fails at every
/// run of an assisted map and scanned the rest of its row each time:
/// docs/assisted-matching.md, "The SGM runs found without rescanning the row".)
pub(super) fn grow_run(mut len: usize, end: usize, holds: impl Fn(usize, usize) -> bool) -> usize {
    let mut chunk = LANES;
    while len + LANES <= end {
        let c = chunk.min(end - len);
        let ok = holds(len, c);
        if !ok && c == LANES {
            break;
        }
        (len, chunk) = if ok { (len + c, 2 * c) } else { (len, LANES) };
    }
    len
}

impl Sgm {
    /// Row `y`'s census costs, every searched pixel's band, into `cost` from `off[y·w] − cbase`
    /// on (`vpopcnt`: count bits with `vpopcntd`, [`super::has_vpopcnt`]).
    #[inline(always)]
    pub(super) fn costs_row<const AVX2: bool>(&mut self, p: &ValidMatchParams, g: Geo, left: &[u8], y: usize, cbase: usize, vpopcnt: bool) {
        let w = g.w;
        // (Only the AVX2 costs can count with `vpopcntd`.)
        #[cfg(not(target_arch = "x86_64"))]
        let _ = vpopcnt;
        let cl = &self.census_l[y * w..][..w];
        let il = &left[y * w..][..w];
        let ir_row = &self.levels_r[y * g.wr..][..g.wr];
        // Runs of pixels of one band at once (their costs are packed one after the
        // other; the right pixel of each moves one column on).
        let end = self.span[y].end;
        let mut x = self.span[y].start;
        while x < end {
            let i = y * w + x;
            let (a, m) = (self.band_a[i], self.band_m[i] as usize);
            if m == 0 {
                x += 1;
                continue;
            }
            // The pixels after it that hold the band ([`grow_run`]: the full range's rest of
            // the span in a few checks, each without a branch per pixel), then one by one.
            let holds = |px: Range<usize>| all_eq(&self.band_a[px.clone()], a) && all_eq(&self.band_m[px], m as u16);
            let mut len = grow_run(1, w - x, |k, c| holds(i + k..i + k + c));
            while x + len < w && self.band_m[i + len] as usize == m && self.band_a[i + len] == a {
                len += 1;
            }
            // Right pixel of disparity index k: x − dmin − k, at x − dmin − k + pad_l in
            // the padded row.
            let start = (x as i32 + g.pad_l as i32 - g.dmin - a as i32) as usize;
            let out = &mut self.cost[self.off[i] - cbase..][..len * m];
            #[cfg(target_arch = "x86_64")]
            if AVX2 {
                let (cr_lo, cr_hi) = (&self.census_r_lo[y * g.wr..][..g.wr], &self.census_r_hi[y * g.wr..][..g.wr]);
                let run = Run { cl: &cl[x..x + len], il: &il[x..x + len], cr_lo, cr_hi, ir_row, cap: p.sgm_ad_cap };
                // SAFETY: AVX2 is only set by `compute_avx2`, which checked the CPU, and
                // `vpopcnt` only where it has `costs_vpopcnt`'s features; the padded
                // right rows hold every disparity of every band.
                unsafe {
                    if vpopcnt {
                        simd::costs_vpopcnt(run, start, m, out)
                    } else {
                        simd::costs_avx2(run, start, m, out)
                    }
                };
                x += len;
                continue;
            }
            let cr_row = &self.census_r[y * g.wr..][..g.wr];
            for (k, out) in out.chunks_exact_mut(m).enumerate() {
                let px = Pixel { cl: cl[x + k], il: il[x + k], cr_row, ir_row, cap: p.sgm_ad_cap };
                costs(px, start + k, out);
            }
            x += len;
        }
    }
}
