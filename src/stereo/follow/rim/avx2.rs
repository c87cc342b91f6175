//! The rim's window sums in AVX2 registers: the portable loops' operations in the same order
//! (no fused multiply-add), so the same bits.

use super::*;
use std::arch::x86_64::*;

/// Loads a sample array's eight lanes at `o`.
#[inline(always)]
unsafe fn load(v: &[f32], o: usize) -> __m256 {
    let lanes = &v[o..o + LANES];
    // SAFETY: the slice holds eight f32s.
    unsafe { _mm256_loadu_ps(lanes.as_ptr()) }
}

/// [`super::window_lanes`] in AVX2 registers.
///
/// # Safety
/// The CPU must have AVX2.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn window_lanes(smp: &Samples, corner: usize) -> [[f32; LANES]; SUMS] {
    let r = RIM_FIT_RADIUS;
    let (xs, mask) = lane_offsets();
    let xs: [__m256; CHUNKS] = std::array::from_fn(|c| _mm256_loadu_ps(xs[c].as_ptr()));
    let mask: [__m256; CHUNKS] = std::array::from_fn(|c| _mm256_loadu_ps(mask[c].as_ptr()));
    let mut acc = [_mm256_setzero_ps(); SUMS];
    for dy in 0..=2 * r {
        let yv = _mm256_set1_ps(dy as f32 - r as f32);
        let row = corner + dy * smp.rw;
        for c in (0..CHUNKS).filter(|&c| smp.may_hold(row, c)) {
            let o = row + c * LANES;
            let (m, x) = (mask[c], xs[c]);
            let wt = _mm256_mul_ps(load(&smp.weight, o), m);
            let s = _mm256_mul_ps(load(&smp.s, o), m);
            let d = _mm256_mul_ps(load(&smp.d, o), m);
            let t = _mm256_mul_ps(load(&smp.t, o), m);
            let (wx, wy) = (_mm256_mul_ps(wt, x), _mm256_mul_ps(wt, yv));
            acc[0] = _mm256_add_ps(acc[0], wt);
            acc[1] = _mm256_add_ps(acc[1], wx);
            acc[2] = _mm256_add_ps(acc[2], wy);
            acc[3] = _mm256_add_ps(acc[3], _mm256_mul_ps(wx, x));
            acc[4] = _mm256_add_ps(acc[4], _mm256_mul_ps(wx, yv));
            acc[5] = _mm256_add_ps(acc[5], _mm256_mul_ps(wy, yv));
            acc[6] = _mm256_add_ps(acc[6], s);
            acc[7] = _mm256_add_ps(acc[7], _mm256_mul_ps(s, x));
            acc[8] = _mm256_add_ps(acc[8], _mm256_mul_ps(s, yv));
            acc[9] = _mm256_add_ps(acc[9], _mm256_mul_ps(s, s));
            acc[10] = _mm256_add_ps(acc[10], d);
            acc[11] = _mm256_add_ps(acc[11], _mm256_mul_ps(d, x));
            acc[12] = _mm256_add_ps(acc[12], _mm256_mul_ps(d, yv));
            acc[13] = _mm256_add_ps(acc[13], _mm256_mul_ps(s, d));
            acc[14] = _mm256_add_ps(acc[14], t);
            acc[15] = _mm256_add_ps(acc[15], _mm256_mul_ps(t, x));
            acc[16] = _mm256_add_ps(acc[16], _mm256_mul_ps(t, yv));
            acc[17] = _mm256_add_ps(acc[17], _mm256_mul_ps(s, t));
            acc[18] = _mm256_add_ps(acc[18], _mm256_mul_ps(t, t));
            acc[19] = _mm256_add_ps(acc[19], _mm256_mul_ps(d, t));
        }
    }
    std::array::from_fn(|k| {
        let mut out = [0f32; LANES];
        // SAFETY: `out` holds eight f32s.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr(), acc[k]) };
        out
    })
}

/// [`super::residual_lanes`] in AVX2 registers.
///
/// # Safety
/// The CPU must have AVX2.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn residual_lanes(smp: &Samples, corner: usize, p: &Profile) -> [[f32; LANES]; 2] {
    let r = RIM_FIT_RADIUS;
    let (xs, mask) = lane_offsets();
    let xs: [__m256; CHUNKS] = std::array::from_fn(|c| _mm256_loadu_ps(xs[c].as_ptr()));
    let mask: [__m256; CHUNKS] = std::array::from_fn(|c| _mm256_loadu_ps(mask[c].as_ptr()));
    let terms = Terms::of(p);
    let mut acc = [_mm256_setzero_ps(); 2];
    for dy in 0..=2 * r {
        let row = corner + dy * smp.rw;
        for (m, k) in terms.iter().enumerate() {
            let uy = _mm256_set1_ps(k.c0 + k.cy * (dy as f32 - r as f32));
            let (cx, cs, ct) = (_mm256_set1_ps(k.cx), _mm256_set1_ps(k.cs), _mm256_set1_ps(k.ct));
            for c in (0..CHUNKS).filter(|&c| smp.may_hold(row, c)) {
                let o = row + c * LANES;
                let fit = _mm256_mul_ps(load(&smp.weight, o), _mm256_add_ps(uy, _mm256_mul_ps(cx, xs[c])));
                let e = _mm256_sub_ps(_mm256_sub_ps(load(&smp.d, o), fit), _mm256_mul_ps(cs, load(&smp.s, o)));
                let e = _mm256_mul_ps(_mm256_sub_ps(e, _mm256_mul_ps(ct, load(&smp.t, o))), mask[c]);
                acc[m] = _mm256_add_ps(acc[m], _mm256_mul_ps(e, e));
            }
        }
    }
    std::array::from_fn(|k| {
        let mut out = [0f32; LANES];
        // SAFETY: `out` holds eight f32s.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr(), acc[k]) };
        out
    })
}
