//! A row's census costs: every searched pixel's band, in runs of pixels that share one.

use super::census::{costs, Pixel};
#[cfg(target_arch = "x86_64")]
use super::{census::Run, simd};
use super::{Geo, Sgm};
use crate::stereo::params::ValidMatchParams;

/// Pixels a run looks at together: sixteen, one bit each of a mask ([`band_bits`]).
pub(super) const RUN_CHUNK: usize = 16;

/// The length of the run of columns from `x0` along a row's sweep (`up`: towards column 0),
/// at most `limit` of them: the columns for which `bits` (the mask of the sixteen columns from
/// its argument on, bit k for column `x_lo + k`) and, past the last whole chunk, `holds` (one
/// column) are true. Sixteen columns a test, each found by the mask's first clear bit, so that
/// neither a run's end nor its length takes a branch per pixel. (Chunks that doubled while
/// they held, each tested whole, then the run's tail one pixel at a time, cost about 4 % of
/// a narrow call on an assisted map, whose bands change every few dozen pixels:
/// docs/assisted-matching.md, "The SGM runs measured by masks".)
#[inline(always)]
pub(super) fn run_length(x0: usize, limit: usize, up: bool, bits: impl Fn(usize) -> u32, holds: impl Fn(usize) -> bool) -> usize {
    let mut len = 0;
    while len + RUN_CHUNK <= limit {
        // Columns x_lo … x_lo + 15, the run's next sixteen: bit 0 is the first in the sweep
        // (`up`: bit 15).
        let mask = bits(if up { x0 - len - (RUN_CHUNK - 1) } else { x0 + len });
        let taken = if up { (!(mask << (32 - RUN_CHUNK))).leading_zeros() } else { (!mask).trailing_zeros() } as usize;
        len += taken.min(RUN_CHUNK);
        if taken < RUN_CHUNK {
            return len;
        }
    }
    while len < limit && holds(if up { x0 - len } else { x0 + len }) {
        len += 1;
    }
    len
}

/// Bit k set where column k of the sixteen holds the band `(a, m)` (`band_a`, `band_m`) and
/// `other[k]` is non-zero (on AVX2 by three compares: [`simd::band_bits`]).
#[inline(always)]
pub(super) fn band_bits<const AVX2: bool>(band_a: &[u16], band_m: &[u16], other: &[u16], band: (u16, u16)) -> u32 {
    let (ba, bm, o): (&[u16; RUN_CHUNK], &[u16; RUN_CHUNK], &[u16; RUN_CHUNK]) = (band_a.try_into().unwrap(), band_m.try_into().unwrap(), other.try_into().unwrap());
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: AVX2 is only set where the CPU was checked (`compute_avx2`, and the test).
        return unsafe { simd::band_bits(ba, bm, o, band) };
    }
    (0..RUN_CHUNK).fold(0u32, |bits, k| bits | (((ba[k] == band.0) & (bm[k] == band.1) & (o[k] > 0)) as u32) << k)
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
            // It and the pixels after it that hold the band ([`run_length`]; the row's own
            // widths stand for `band_bits`' other row: a pixel that holds the band has one).
            let (ra, rm) = (&self.band_a[y * w..][..w], &self.band_m[y * w..][..w]);
            let band = (a, m as u16);
            let len = run_length(x, w - x, false, |c| band_bits::<AVX2>(&ra[c..c + RUN_CHUNK], &rm[c..c + RUN_CHUNK], &rm[c..c + RUN_CHUNK], band), |c| (ra[c], rm[c]) == band);
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A run's length by masks is the plain scan's, both ways along a row, from every column,
    /// with runs that end inside a chunk, on its last column, past the last whole chunk and at
    /// the row's end; and the AVX2 masks are the portable ones.
    #[test]
    fn a_run_measured_by_masks_is_the_plain_scan() {
        let mut next = crate::testing::xorshift(0x5eed_2d);
        let w = 150;
        for trial in 0..60 {
            // Bands that hold for stretches of random length (long ones too), and other
            // columns that mostly hold.
            let mut band_a = vec![0u16; w];
            let mut band_m = vec![0u16; w];
            let mut x = 0;
            while x < w {
                let len = 1 + (next() % if trial % 2 == 0 { 40 } else { 4 }) as usize;
                let band = ((next() % 2) as u16 * 16, 16 + (next() % 2) as u16 * 16);
                for k in x..(x + len).min(w) {
                    (band_a[k], band_m[k]) = band;
                }
                x += len;
            }
            let other: Vec<u16> = (0..w).map(|_| (next() % 50 != 0) as u16).collect();
            let holds = |x: usize, band: (u16, u16)| (band_a[x], band_m[x]) == band && other[x] > 0;
            for x0 in 0..w {
                let band = (band_a[x0], band_m[x0]);
                for up in [false, true] {
                    let limit = if up { x0 + 1 } else { w - x0 };
                    let plain = (0..limit).take_while(|&k| holds(if up { x0 - k } else { x0 + k }, band)).count();
                    let chunk = |c: usize| c..c + RUN_CHUNK;
                    let by = |avx2: bool| {
                        run_length(
                            x0,
                            limit,
                            up,
                            |c| if avx2 { band_bits::<true>(&band_a[chunk(c)], &band_m[chunk(c)], &other[chunk(c)], band) } else { band_bits::<false>(&band_a[chunk(c)], &band_m[chunk(c)], &other[chunk(c)], band) },
                            |x| holds(x, band),
                        )
                    };
                    assert_eq!(by(false), plain, "trial {trial}, from column {x0}, up {up}");
                    #[cfg(target_arch = "x86_64")]
                    if std::is_x86_feature_detected!("avx2") {
                        assert_eq!(by(true), plain, "trial {trial}, from column {x0}, up {up}, AVX2");
                    }
                }
            }
        }
    }
}
