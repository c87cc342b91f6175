//! AVX2 copies of the hot loops (the path step and its runs, the masked minimum and its
//! position, the costs): sixteen 16-bit lanes per instruction, the same integer arithmetic
//! as the portable versions, so both give the same map
//! (`the_portable_build_gives_the_same_map`). The costs count bits with AVX-512's
//! `vpopcntd` where the CPU has it (same bytes); wider registers do not pay on the CPUs
//! measured (docs/matcher.md, "Where the narrow SGM call's time goes").

use std::arch::x86_64::*;

use super::census::{CENSUS_H, CENSUS_W};
use super::{From, LANES};

/// [`super::step`] on AVX2, over the band of `sum.len()` disparities. With `FOLDED`
/// ([`super::Geo::folded`]) the first pass stores each sum with its cost above it
/// ([`FOLD_SHIFT`]), and the second pass reads the costs from there (`c` unused) and stores
/// the plain sums.
///
/// # Safety
/// The CPU supports AVX2. Lengths are checked: `sum.len()` a multiple of [`LANES`], every
/// `from[j].around` at least `sum.len() + 2` long, every `out[j]` and (unless it is read
/// from the sums) `c` at least `sum.len()`.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn step<const N: usize, const FOLDED: bool>(c: &[u8], from: [From; N], p1: u16, out: [&mut [u16]; N], sum: &mut [u16], add: bool) -> [u16; N] {
    let m = sum.len();
    assert!(m % LANES == 0 && (FOLDED && add || c.len() >= m));
    for j in 0..N {
        assert!(from[j].around.len() >= m + 2 && out[j].len() >= m);
    }
    let p1v = _mm256_set1_epi16(p1 as i16);
    let jump = from.map(|f| _mm256_set1_epi16(f.jump as i16));
    let base = from.map(|f| _mm256_set1_epi16(f.min as i16));
    let src = from.map(|f| f.around.as_ptr());
    let dst = out.map(|o| o.as_mut_ptr());
    let mut mn = [_mm256_set1_epi16(-1); N];
    // The last path is the horizontal one: its previous pixel's values were stored a moment
    // ago, and a load straddling two of those stores (at ±1 lane) waits for them to reach
    // the cache. It loads whole stored blocks only and shifts lanes in registers: `hp`, `hm`,
    // `hn` the previous, this and the next block of values, the ends from the slot's
    // sentinels.
    let h = from[N - 1].around;
    let mut hp = _mm256_set1_epi16(h[0] as i16);
    // SAFETY: around holds m + 2 ≥ LANES + 2 values.
    let mut hm = unsafe { _mm256_loadu_si256(h.as_ptr().add(1) as *const __m256i) };
    let mut b = 0;
    while b < m {
        // SAFETY: b + LANES ≤ m and the lengths asserted above.
        unsafe {
            let sp = sum.as_mut_ptr().add(b) as *mut __m256i;
            let (cc, mut acc) = cost_and_prior::<FOLDED>(c.as_ptr().wrapping_add(b), sp, add);
            let hn = if b + LANES < m { _mm256_loadu_si256(h.as_ptr().add(1 + b + LANES) as *const __m256i) } else { _mm256_set1_epi16(h[m + 1] as i16) };
            for j in 0..N {
                let (l, mid, r) = if j == N - 1 {
                    // l[i] = hm[i − 1] (hp[15] at i = 0), r[i] = hm[i + 1] (hn[0] at i = 15).
                    let l = _mm256_alignr_epi8::<14>(hm, _mm256_permute2x128_si256::<0x21>(hp, hm));
                    let r = _mm256_alignr_epi8::<2>(_mm256_permute2x128_si256::<0x21>(hm, hn), hm);
                    (l, hm, r)
                } else {
                    let q = src[j].add(b);
                    (_mm256_loadu_si256(q as *const __m256i), _mm256_loadu_si256(q.add(1) as *const __m256i), _mm256_loadu_si256(q.add(2) as *const __m256i))
                };
                let best = best_from(mid, l, r, p1v, jump[j]);
                let v = _mm256_sub_epi16(_mm256_add_epi16(cc, best), base[j]);
                _mm256_storeu_si256(dst[j].add(b) as *mut __m256i, v);
                mn[j] = _mm256_min_epu16(mn[j], v);
                acc = _mm256_add_epi16(acc, v);
            }
            store_sum::<FOLDED>(sp, acc, cc, add);
            (hp, hm) = (hm, hn);
        }
        b += LANES;
    }
    mn.map(|v| hmin(v))
}

/// Where a folded word keeps its cost: the first pass's sum of two paths below, at most
/// 2 · (C_max + P2) < 2⁹ ([`super::Geo::folded`]), the cost (< 2⁷) above.
pub(super) const FOLD_SHIFT: i32 = 9;

/// The first pass's word: its two paths' sum `s` with the cost `cc` above it.
#[target_feature(enable = "avx2")]
#[inline]
fn fold(s: __m256i, cc: __m256i) -> __m256i {
    _mm256_or_si256(s, _mm256_slli_epi16::<FOLD_SHIFT>(cc))
}

/// A folded word's cost and sum.
#[target_feature(enable = "avx2")]
#[inline]
fn unfold(word: __m256i) -> (__m256i, __m256i) {
    (_mm256_srli_epi16::<FOLD_SHIFT>(word), _mm256_and_si256(word, _mm256_set1_epi16((1 << FOLD_SHIFT) - 1)))
}

/// A block's sixteen costs and the sums it adds to, for [`step`] and [`run`]: in pass two
/// (`add`) folded, both from the stored word at `sp`; otherwise the costs from `c` and, in pass
/// two, the stored sums (zero in pass one).
///
/// # Safety
/// `sp` addresses sixteen sums; `c` sixteen costs unless they are read from the folded word.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn cost_and_prior<const FOLDED: bool>(c: *const u8, sp: *const __m256i, add: bool) -> (__m256i, __m256i) {
    // SAFETY: the caller's contract.
    unsafe {
        if FOLDED && add {
            return unfold(_mm256_loadu_si256(sp));
        }
        let cc = _mm256_cvtepu8_epi16(_mm_loadu_si128(c as *const __m128i));
        (cc, if add { _mm256_loadu_si256(sp) } else { _mm256_setzero_si256() })
    }
}

/// Stores a block's sums `s` at `sp`: folded with their costs `cc` in pass one, plain otherwise.
///
/// # Safety
/// `sp` addresses sixteen sums.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn store_sum<const FOLDED: bool>(sp: *mut __m256i, s: __m256i, cc: __m256i, add: bool) {
    // SAFETY: the caller's contract.
    unsafe { _mm256_storeu_si256(sp, if FOLDED && !add { fold(s, cc) } else { s }) }
}

/// A path's term from its previous pixel, per disparity lane: the least of staying
/// (`mid`), a step of one (`l`, `r`: the neighbouring disparities) plus `p1`, and the jump
/// term. `min(l, r) + P1` is `min(l + P1, r + P1)` with one add fewer: no value comes near
/// the top of 16 bits (`UNREACHED` + P1 fits).
#[target_feature(enable = "avx2")]
#[inline]
fn best_from(mid: __m256i, l: __m256i, r: __m256i, p1: __m256i, jump: __m256i) -> __m256i {
    _mm256_min_epu16(_mm256_min_epu16(mid, _mm256_add_epi16(_mm256_min_epu16(l, r), p1)), jump)
}

/// The smallest of sixteen unsigned 16-bit lanes.
#[target_feature(enable = "avx2")]
#[inline]
fn hmin(v: __m256i) -> u16 {
    let half = _mm_min_epu16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    _mm_extract_epi16::<0>(_mm_minpos_epu16(half)) as u16
}

/// Lanes of the block at absolute disparity index `k0` that lie in `lo ..= hi` and outside
/// `skip` (all as i16 lane masks).
#[target_feature(enable = "avx2")]
#[inline]
fn inside(k0: usize, lo: usize, hi: usize, skip: (usize, usize)) -> __m256i {
    let k = _mm256_add_epi16(_mm256_set1_epi16(k0 as i16), _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
    let ge_lo = _mm256_cmpgt_epi16(k, _mm256_set1_epi16(lo as i16 - 1));
    let le_hi = _mm256_cmpgt_epi16(_mm256_set1_epi16(hi as i16 + 1), k);
    let mut m = _mm256_and_si256(ge_lo, le_hi);
    if skip.0 <= skip.1 {
        let in_skip = _mm256_and_si256(_mm256_cmpgt_epi16(k, _mm256_set1_epi16(skip.0 as i16 - 1)), _mm256_cmpgt_epi16(_mm256_set1_epi16(skip.1 as i16 + 1), k));
        m = _mm256_andnot_si256(in_skip, m);
    }
    m
}

/// [`super::costs::band_bits`] on AVX2: bit k set where column k of the sixteen holds the
/// band `(a, m)` (`band_a`, `band_m`) and `other[k]` is non-zero.
///
/// # Safety
/// The CPU supports AVX2.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn band_bits(band_a: &[u16; 16], band_m: &[u16; 16], other: &[u16; 16], (a, m): (u16, u16)) -> u32 {
    // SAFETY: sixteen u16 each.
    let (va, vm, vo) = unsafe { (_mm256_loadu_si256(band_a.as_ptr().cast()), _mm256_loadu_si256(band_m.as_ptr().cast()), _mm256_loadu_si256(other.as_ptr().cast())) };
    let holds = _mm256_and_si256(_mm256_cmpeq_epi16(va, _mm256_set1_epi16(a as i16)), _mm256_cmpeq_epi16(vm, _mm256_set1_epi16(m as i16)));
    lane_bits(_mm256_andnot_si256(_mm256_cmpeq_epi16(vo, _mm256_setzero_si256()), holds))
}

/// Bit k set where slot k of the sixteen (`[a, m]` each) holds another band than `band`.
///
/// # Safety
/// The CPU supports AVX2.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn other_band_bits(slots: &[[u16; 2]; 16], band: [u16; 2]) -> u32 {
    let want = _mm256_set1_epi32((band[0] as u32 | (band[1] as u32) << 16) as i32);
    // SAFETY: sixteen slots of two u16, eight to a register.
    let (lo, hi) = unsafe { (_mm256_loadu_si256(slots.as_ptr().cast()), _mm256_loadu_si256(slots.as_ptr().add(8).cast())) };
    let same = |v| _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(v, want))) as u32;
    !(same(lo) | same(hi) << 8) & 0xffff
}

/// The sixteen 16-bit lane masks of `v` (all ones or zero) as bits 0 … 15.
#[target_feature(enable = "avx2")]
#[inline]
fn lane_bits(v: __m256i) -> u32 {
    // Bytes per 128-bit half: lanes 0–7, 0–7, 8–15, 8–15; the quadwords reordered to 0–7, 8–15.
    let bytes = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packs_epi16(v, v));
    _mm256_movemask_epi8(bytes) as u32 & 0xffff
}

/// [`super::select::masked_min`] on AVX2.
///
/// # Safety
/// The CPU supports AVX2; `s.len()` is a multiple of [`LANES`] and indices fit `i16`.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn masked_min(s: &[u16], a: usize, lo: usize, hi: usize, skip: (usize, usize)) -> u16 {
    assert!(s.len() % LANES == 0);
    let mut mn = _mm256_set1_epi16(-1);
    for (b, blk) in s.chunks_exact(LANES).enumerate() {
        // SAFETY: a block of LANES u16.
        let v = unsafe { _mm256_loadu_si256(blk.as_ptr() as *const __m256i) };
        let keep = inside(a + b * LANES, lo, hi, skip);
        mn = _mm256_min_epu16(mn, _mm256_or_si256(_mm256_and_si256(keep, v), _mm256_andnot_si256(keep, _mm256_set1_epi16(-1))));
    }
    hmin(mn)
}

/// [`super::select::masked_min`] and [`super::select::first_at`] in one pass (no lanes
/// skipped): the smallest sum over `lo ..= hi` and the first disparity index holding it. Each
/// lane keeps its smallest value and the index where it first appeared; the smallest index
/// among the lanes holding the minimum is the first.
///
/// # Safety
/// As [`masked_min`]; the interval is not empty.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn min_at(s: &[u16], a: usize, lo: usize, hi: usize) -> (u16, usize) {
    assert!(s.len() % LANES == 0 && lo <= hi);
    let ones = _mm256_set1_epi16(-1);
    let lanes = _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let (below, above) = (_mm256_set1_epi16(lo as i16 - 1), _mm256_set1_epi16(hi as i16 + 1));
    let (mut mn, mut at) = (ones, ones);
    for (b, blk) in s.chunks_exact(LANES).enumerate() {
        // SAFETY: a block of LANES u16.
        let v = unsafe { _mm256_loadu_si256(blk.as_ptr() as *const __m256i) };
        let k = _mm256_add_epi16(_mm256_set1_epi16((a + b * LANES) as i16), lanes);
        let keep = _mm256_and_si256(_mm256_cmpgt_epi16(k, below), _mm256_cmpgt_epi16(above, k));
        let v = _mm256_or_si256(_mm256_and_si256(keep, v), _mm256_andnot_si256(keep, ones));
        let lower = _mm256_min_epu16(v, mn);
        // Strictly smaller (unsigned): the minimum changed; an equal value keeps the earlier k.
        let changed = _mm256_xor_si256(_mm256_cmpeq_epi16(lower, mn), ones);
        at = _mm256_blendv_epi8(at, k, changed);
        mn = lower;
    }
    let best = hmin(mn);
    let holds = _mm256_cmpeq_epi16(mn, _mm256_set1_epi16(best as i16));
    let first = hmin(_mm256_or_si256(_mm256_and_si256(holds, at), _mm256_andnot_si256(holds, ones)));
    (best, first as usize)
}

/// The selection of a pixel whose band is one block or two, in registers: over `s`, the two
/// blocks from the band's first disparity index, the smallest sum over lanes `jlo ..= jhi`,
/// the first lane holding it, and (with `rival`) the smallest sum outside that lane and its
/// two neighbours (else `u16::MAX`) — what [`min_at`] and [`masked_min`] give, to the bit,
/// without their loops over blocks. Two blocks are read whatever the band: past a one-block
/// band they hold the next pixel's sums or the volume's slack, which the interval leaves out.
///
/// One pixel at a time, its lanes reduced by `phminposuw`: no group of pixels to gather
/// first, so neighbours of different widths take it alike. Sixteen pixels transposed in
/// registers (the minimum and its lane then vertical operations, the selection of the
/// eighth session) took 2.8 ns a pixel against this 1.7 on two-block bands (docs/matcher.md,
/// "The winner a pixel at a time").
///
/// # Safety
/// The CPU supports AVX2; `s` holds `2 · LANES` sums; `jlo ≤ jhi < 2 · LANES`.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn select_pixel(s: &[u16], jlo: usize, jhi: usize, rival: bool) -> (u16, usize, u16) {
    assert!(s.len() == 2 * LANES && jlo <= jhi && jhi < 2 * LANES);
    let ones = _mm256_set1_epi16(-1);
    // SAFETY: block b of the two that `s` holds (asserted above).
    let raw: [__m256i; 2] = std::array::from_fn(|b| unsafe { _mm256_loadu_si256(s.as_ptr().add(b * LANES) as *const __m256i) });
    // Block b's sums, 0xFFFF (above every sum, at most 8 · (134 + 2000)) outside the interval
    // and `skip` (`(1, 0)`: nothing skipped).
    let masked = |b: usize, skip: (usize, usize)| _mm256_or_si256(raw[b], _mm256_andnot_si256(inside(b * LANES, jlo, jhi, skip), ones));
    let v = [masked(0, (1, 0)), masked(1, (1, 0))];
    let best = hmin(_mm256_min_epu16(v[0], v[1]));
    // Two bits per lane, the second block's above the first's: the first lane holding the
    // minimum is the lowest set bit.
    let at = |b: usize| _mm256_movemask_epi8(_mm256_cmpeq_epi16(v[b], _mm256_set1_epi16(best as i16))) as u32 as u64;
    let j = ((at(1) << 32 | at(0)).trailing_zeros() / 2) as usize;
    if !rival {
        return (best, j, u16::MAX);
    }
    let skip = (j.saturating_sub(1), j + 1);
    (best, j, hmin(_mm256_min_epu16(masked(0, skip), masked(1, skip))))
}

/// The census window's neighbours in comparison order (row-major, the centre left out), as
/// (row, column) in the window.
const NEIGHBOURS: [(usize, usize); CENSUS_W * CENSUS_H - 1] = {
    let mut out = [(0, 0); CENSUS_W * CENSUS_H - 1];
    let (mut t, mut j) = (0, 0);
    while j < CENSUS_H {
        let mut i = 0;
        while i < CENSUS_W {
            if !(i == CENSUS_W / 2 && j == CENSUS_H / 2) {
                out[t] = (j, i);
                t += 1;
            }
            i += 1;
        }
        j += 1;
    }
    out
};

/// [`super::census::planes_row`] on AVX2: 32 pixels at a time, each plane's eight
/// comparisons gathered in a register and stored once (written as a loop over memory, the
/// compiler ORs every comparison into the plane in memory, and shifts bytes it cannot shift).
/// Unsigned `neighbour < centre` is a signed compare after flipping the top bits.
///
/// # Safety
/// The CPU supports AVX2; `padded` holds `CENSUS_H` rows of `w + CENSUS_W − 1` bytes and
/// `planes` five planes of `w`.
#[target_feature(enable = "avx2")]
#[inline]
pub(super) unsafe fn planes(padded: &[u8], w: usize, planes: &mut [u8]) {
    let (rx, ry) = (CENSUS_W / 2, CENSUS_H / 2);
    let wp = w + 2 * rx;
    assert!(padded.len() >= wp * CENSUS_H && planes.len() >= 5 * w);
    let flip = _mm256_set1_epi8(i8::MIN);
    let (src, dst) = (padded.as_ptr(), planes.as_mut_ptr());
    let mut x = 0;
    while x < w && w >= 32 {
        // The last columns as the 32 ending at the row's end, again where they overlap the
        // previous 32 (the same comparisons, the same bytes): one by one, the up to 31
        // columns of a crop's width cost as much as the vector part of the row.
        x = x.min(w - 32);
        // SAFETY: every load reads 32 bytes at column x + i ≤ w − 32 + 2 rx of a row of wp
        // bytes, every store 32 bytes at x ≤ w − 32 of a plane of w.
        unsafe {
            let c = _mm256_xor_si256(_mm256_loadu_si256(src.add(ry * wp + rx + x) as *const __m256i), flip);
            // One plane at a time, its comparisons ORed into one register (an array of five
            // accumulators indexed by the comparison was kept in memory by the compiler).
            for k in 0..5 {
                let mut acc = _mm256_setzero_si256();
                for (t, &(j, i)) in NEIGHBOURS.iter().enumerate().skip(8 * k).take(8) {
                    let n = _mm256_xor_si256(_mm256_loadu_si256(src.add(j * wp + i + x) as *const __m256i), flip);
                    acc = _mm256_or_si256(acc, _mm256_and_si256(_mm256_cmpgt_epi8(c, n), _mm256_set1_epi8((1u8 << (t % 8)) as i8)));
                }
                _mm256_storeu_si256(dst.add(k * w + x) as *mut __m256i, acc);
            }
        }
        x += 32;
    }
    // A row narrower than 32 columns one by one, the same comparisons.
    for x in x..w {
        let c = padded[ry * wp + rx + x];
        let mut bytes = [0u8; 5];
        for (t, &(j, i)) in NEIGHBOURS.iter().enumerate() {
            bytes[t / 8] |= ((padded[j * wp + i + x] < c) as u8) << (t % 8);
        }
        for (k, b) in bytes.iter().enumerate() {
            planes[k * w + x] = *b;
        }
    }
}

/// Whether the CPU counts bits in vector lanes (AVX-512 VPOPCNTDQ on 256-bit registers).
#[inline]
pub(super) fn has_vpopcnt() -> bool {
    std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512vl") && std::is_x86_feature_detected!("avx512vpopcntdq")
}

/// [`costs_impl`] with the nibble-table bit counts (AVX2 alone).
///
/// # Safety
/// As [`costs_impl`].
#[target_feature(enable = "avx2")]
pub(super) unsafe fn costs_avx2(run: super::census::Run, start: usize, m: usize, out: &mut [u8]) {
    // SAFETY: the caller's contract.
    unsafe { costs_impl::<false>(run, start, m, out) }
}

/// [`costs_impl`] with one `vpopcntd` per eight words in place of the nibble tables: a third
/// fewer instructions per sixteen costs, the same bytes.
///
/// # Safety
/// As [`costs_impl`], on a CPU with AVX-512 F, VL and VPOPCNTDQ ([`has_vpopcnt`]).
#[target_feature(enable = "avx2,avx512f,avx512vl,avx512vpopcntdq")]
pub(super) unsafe fn costs_vpopcnt(run: super::census::Run, start: usize, m: usize, out: &mut [u8]) {
    // SAFETY: the caller's contract.
    unsafe { costs_impl::<true>(run, start, m, out) }
}

/// [`super::census::costs`] in vector registers for a run of consecutive left pixels of one
/// band (`m` disparities, a whole number of blocks; pixel k's right words end at
/// `start + k`, its costs at `out[k · m ..]`): sixteen Hamming distances per step — the low
/// 32 bits of eight words per register (nibble table popcount, the bytes of each word summed
/// by two multiply-adds; or, with `VPOPCNT`, one `vpopcntd`), the two high bits of all
/// sixteen by one table lookup — plus sixteen capped level differences, written as bytes.
/// The body of [`costs_avx2`] and [`costs_vpopcnt`].
///
/// # Safety
/// The CPU supports AVX2 (and with `VPOPCNT` what [`costs_vpopcnt`] enables); `m` is a
/// multiple of [`LANES`], `out.len()` is `m` times the run's length, and
/// `run.cr_lo[start + 1 − m ..= start + len − 1]`, `run.cr_hi[…]` and `run.ir_row[…]` (the
/// same range) exist.
#[inline(always)]
unsafe fn costs_impl<const VPOPCNT: bool>(run: super::census::Run, start: usize, m: usize, out: &mut [u8]) {
    let len = run.cl.len();
    let (lo_row, hi_row) = (run.cr_lo, run.cr_hi);
    assert!(m % LANES == 0 && m > 0 && run.il.len() == len && out.len() == len * m && start + 1 >= m);
    assert!(len == 0 || (start + len - 1 < lo_row.len() && start + len - 1 < hi_row.len() && start + len - 1 < run.ir_row.len()));
    let cap = _mm_set1_epi8(run.cap as i8);
    let reverse = _mm_setr_epi8(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    let nibble = _mm256_setr_epi8(0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4, 0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4);
    let two_bits = _mm_setr_epi8(0, 1, 1, 2, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0);
    let (low, ones) = (_mm256_set1_epi8(0x0f), _mm256_set1_epi8(1));
    // After the horizontal add, the pack and the permute below, the sixteen counts of words
    // p0 … p15 (p0 the word at `top − 15`) lie in the order p0–p3, p8–p11, p4–p7, p12–p15;
    // disparity k is word p(15 − k).
    let order = _mm_setr_epi8(15, 14, 13, 12, 7, 6, 5, 4, 11, 10, 9, 8, 3, 2, 1, 0);
    for (k, (&cl, &il)) in run.cl.iter().zip(run.il).enumerate() {
        let left_lo = _mm256_set1_epi32(cl as u32 as i32);
        let left_hi = _mm_set1_epi8((cl >> 32) as u8 as i8);
        let level = _mm_set1_epi8(il as i8);
        // Bit counts per byte of eight words, then per 16-bit half (multiply-add with ones).
        let halves = |v: __m256i| -> __m256i {
            let x = _mm256_xor_si256(v, left_lo);
            let lo = _mm256_shuffle_epi8(nibble, _mm256_and_si256(x, low));
            let hi = _mm256_shuffle_epi8(nibble, _mm256_and_si256(_mm256_srli_epi16::<4>(x), low));
            _mm256_maddubs_epi16(_mm256_add_epi8(lo, hi), ones)
        };
        let mut b = 0;
        while b < m {
            // Words top − 15 … top hold disparities b + 15 … b (the right pixel moves left).
            let top = start + k - b;
            // SAFETY: top − 15 ≥ start + 1 − m ≥ 0 and top ≤ start + len − 1, asserted above.
            let (w0, w1, hb, ir) = unsafe {
                let base = lo_row.as_ptr().add(top - 15);
                (
                    _mm256_loadu_si256(base as *const __m256i),
                    _mm256_loadu_si256(base.add(8) as *const __m256i),
                    _mm_loadu_si128(hi_row.as_ptr().add(top - 15) as *const __m128i),
                    _mm_loadu_si128(run.ir_row.as_ptr().add(top - 15) as *const __m128i),
                )
            };
            // Per 128-bit half: the sums of p0–p3 and p8–p11 (low), p4–p7 and p12–p15 (high);
            // with `vpopcntd`, the counts of those words, packed to 16 bits in the same order.
            let sums = if VPOPCNT {
                _mm256_packus_epi32(_mm256_popcnt_epi32(_mm256_xor_si256(w0, left_lo)), _mm256_popcnt_epi32(_mm256_xor_si256(w1, left_lo)))
            } else {
                _mm256_hadd_epi16(halves(w0), halves(w1))
            };
            let packed = _mm256_packus_epi16(sums, sums);
            let joined = _mm256_castsi256_si128(_mm256_permute4x64_epi64::<0b1000>(packed));
            let low_bits = _mm_shuffle_epi8(joined, order);
            let high_bits = _mm_shuffle_epi8(two_bits, _mm_shuffle_epi8(_mm_xor_si128(hb, left_hi), reverse));
            // Levels top − 15 … top, reversed to disparities b … b + 15: |il − ir| capped.
            let ir = _mm_shuffle_epi8(ir, reverse);
            let diff = _mm_or_si128(_mm_subs_epu8(level, ir), _mm_subs_epu8(ir, level));
            let res = _mm_adds_epu8(_mm_add_epi8(low_bits, high_bits), _mm_min_epu8(diff, cap));
            // SAFETY: k · m + b + LANES ≤ len · m = out.len().
            unsafe { _mm_storeu_si128(out.as_mut_ptr().add(k * m + b) as *mut __m128i, res) };
            b += LANES;
        }
    }
}

/// How many pixels ahead of its step a run asks for a pixel's sums and costs (4 and 16 were
/// no faster on a 450 × 384 pair at 128 disparities).
pub(super) const AHEAD: isize = 8;

pub(super) use crate::stereo::kernels::prefetch;

/// One path's previous values of a run's pixels, and where its new values go.
pub(super) struct RunRows {
    /// The previous row's slot of the run's first pixel at disparity index `a − 1` (its
    /// values around the band); the next pixel's slot is `stride` further along `dir`.
    pub(super) prev: *const u16,
    pub(super) prev_min: *const u16,
    /// The current row's slot of the first pixel at index `a` (the band), and its minimum.
    pub(super) cur: *mut u16,
    pub(super) cur_min: *mut u16,
    pub(super) stride: usize,
}

/// [`super::step`] over a run of `len` pixels of one row that share one band of `B` blocks,
/// whose previous pixel along the row searched that same band and whose pixels in the
/// previous row searched (any band): the path along the row (from `h`, its previous values
/// over the band, and their minimum) stays in registers from pixel to pixel, and the path
/// from the previous row reads and writes `v`. Pixel `k`'s costs and sums are at
/// `k · dir · 16B` from `c` and `sum` (packed offsets of equal bands); its vertical slots
/// `k · dir · stride` from the first. Returns the row path's values (in `h`) and minimum at
/// the last pixel. Beside the band the row path's values are `UNREACHED` (equal bands), and
/// a previous-row slot holds `UNREACHED` outside its own band: both read as [`step`] reads
/// them. `FOLDED` as in [`step`] (the second pass does not read `c`).
///
/// # Safety
/// The CPU supports AVX2; every pointer addresses what is described above for all `len`
/// pixels (`prev` reads `16B + 2` values, `cur` writes `16B`).
#[target_feature(enable = "avx2")]
#[inline]
#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn run<const B: usize, const FOLDED: bool>(c: *const u8, sum: *mut u16, dir: isize, len: usize, v: &RunRows, h: &mut [u16], h_min: u16, p1: u16, p2: u16, add: bool) -> u16 {
    assert!(h.len() == B * LANES);
    let m = (B * LANES) as isize;
    let p1v = _mm256_set1_epi16(p1 as i16);
    let p2v = _mm256_set1_epi16(p2 as i16);
    let unreached = _mm256_set1_epi16(super::UNREACHED as i16);
    let mut hv = [_mm256_setzero_si256(); B];
    for (b, r) in hv.iter_mut().enumerate() {
        // SAFETY: h holds B blocks.
        *r = unsafe { _mm256_loadu_si256(h.as_ptr().add(b * LANES) as *const __m256i) };
    }
    let mut hbase = _mm256_set1_epi16(h_min as i16);
    let mut last_min = h_min;
    for k in 0..len as isize {
        // SAFETY: the caller's contract, for pixel k < len.
        unsafe {
            let sp = sum.offset(k * dir * m);
            // At full range both passes stream through volumes larger than the caches, pass
            // two backwards; left to the hardware, the loads wait for memory. The sums (and in
            // pass two the costs, unless they are folded into the sums) of the pixel `AHEAD`
            // steps on are asked for now. (Past the run's end too: a prefetch is only a hint.)
            let ahead = AHEAD * dir * m;
            prefetch(sp.wrapping_offset(ahead), B * LANES * 2);
            if add && !FOLDED {
                prefetch(c.wrapping_offset(k * dir * m + ahead), B * LANES);
            }
            let slot = k * dir * v.stride as isize;
            let (vp, vc) = (v.prev.offset(slot), v.cur.offset(slot));
            let vbase = _mm256_set1_epi16(*v.prev_min.offset(k * dir) as i16);
            let vjump = _mm256_add_epi16(vbase, p2v);
            let hjump = _mm256_add_epi16(hbase, p2v);
            let (mut vmn, mut hmn) = (unreached, unreached);
            let mut nh = [_mm256_setzero_si256(); B];
            for b in 0..B {
                let sb = sp.add(b * LANES) as *mut __m256i;
                let (cc, prior) = cost_and_prior::<FOLDED>(c.wrapping_offset(k * dir * m + (b * LANES) as isize), sb, add);
                let q = vp.add(b * LANES);
                let (l, mid, r) = (_mm256_loadu_si256(q as *const __m256i), _mm256_loadu_si256(q.add(1) as *const __m256i), _mm256_loadu_si256(q.add(2) as *const __m256i));
                let best = best_from(mid, l, r, p1v, vjump);
                let vv = _mm256_sub_epi16(_mm256_add_epi16(cc, best), vbase);
                _mm256_storeu_si256(vc.add(b * LANES) as *mut __m256i, vv);
                vmn = _mm256_min_epu16(vmn, vv);
                // The row path: its values shifted by one lane across the blocks in registers.
                let (hp, hn) = (if b > 0 { hv[b - 1] } else { unreached }, if b + 1 < B { hv[b + 1] } else { unreached });
                let hm = hv[b];
                let l = _mm256_alignr_epi8::<14>(hm, _mm256_permute2x128_si256::<0x21>(hp, hm));
                let r = _mm256_alignr_epi8::<2>(_mm256_permute2x128_si256::<0x21>(hm, hn), hm);
                let best = best_from(hm, l, r, p1v, hjump);
                let hh = _mm256_sub_epi16(_mm256_add_epi16(cc, best), hbase);
                nh[b] = hh;
                hmn = _mm256_min_epu16(hmn, hh);
                let s = _mm256_add_epi16(vv, hh);
                // (Pass one has no earlier sum: no add of a zero.)
                let s = if add { _mm256_add_epi16(s, prior) } else { s };
                store_sum::<FOLDED>(sb, s, cc, add);
            }
            *v.cur_min.offset(k * dir) = hmin(vmn);
            hv = nh;
            // The row minimum, broadcast without leaving the vector registers.
            let half = _mm_min_epu16(_mm256_castsi256_si128(hmn), _mm256_extracti128_si256::<1>(hmn));
            let pos = _mm_minpos_epu16(half);
            hbase = _mm256_broadcastw_epi16(pos);
            last_min = _mm_extract_epi16::<0>(pos) as u16;
        }
    }
    for (b, r) in hv.iter().enumerate() {
        // SAFETY: h holds B blocks.
        unsafe { _mm256_storeu_si256(h.as_mut_ptr().add(b * LANES) as *mut __m256i, *r) };
    }
    last_min
}
