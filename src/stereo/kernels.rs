//! The matcher's inner loops over a run of disparities.
//!
//! Each kernel walks its slices in fixed chunks of [`LANES`] elements, then a scalar tail.
//! A fixed-size chunk compiles to straight SIMD instructions at whatever level the caller was
//! compiled for (the matcher inlines these into an AVX2 copy and a baseline copy); a plain
//! `for k in 0..len` loop would instead be vectorised with unrolling that only pays off from
//! 64 elements on, leaving the common 16…60-disparity runs to scalar code.

/// Asks for the 64-byte lines of `bytes` bytes from `at` ahead of their use. Any address
/// will do: a prefetch is only a hint, nothing is read (a no-op off x86_64).
#[inline(always)]
pub fn prefetch<T>(at: *const T, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        let at = at as *const i8;
        for line in (0..bytes).step_by(64) {
            // SAFETY: a prefetch of any address is only a hint; nothing is read.
            unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(at.wrapping_add(line)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (at, bytes);
}

/// Elements per chunk: 16 × u16 is one AVX2 register.
pub const LANES: usize = 16;

/// `|a − b|` computed in bytes and widened, so it vectorises as byte max/min/sub.
#[inline(always)]
pub fn absdiff(a: u8, b: u8) -> u16 {
    (a.max(b) - a.min(b)) as u16
}

/// `cs[k] += |l_new − r_new[k]| − |l_old − r_old[k]|`: one row down for a column's window.
#[inline(always)]
pub fn slide_column(cs: &mut [u16], l_new: u8, r_new: &[u8], l_old: u8, r_old: &[u8]) {
    let len = cs.len();
    let (r_new, r_old) = (&r_new[..len], &r_old[..len]);
    let split = len - len % LANES;
    for c in (0..split).step_by(LANES) {
        let dst: &mut [u16; LANES] = (&mut cs[c..c + LANES]).try_into().unwrap();
        let a: &[u8; LANES] = r_new[c..c + LANES].try_into().unwrap();
        let b: &[u8; LANES] = r_old[c..c + LANES].try_into().unwrap();
        for i in 0..LANES {
            dst[i] = dst[i].wrapping_add(absdiff(l_new, a[i])).wrapping_sub(absdiff(l_old, b[i]));
        }
    }
    for k in split..len {
        cs[k] = cs[k].wrapping_add(absdiff(l_new, r_new[k])).wrapping_sub(absdiff(l_old, r_old[k]));
    }
}

/// `dst[k] += |l − r[k]|`.
#[inline(always)]
pub fn add_absdiff(dst: &mut [u16], l: u8, r: &[u8]) {
    let len = dst.len();
    let r = &r[..len];
    let split = len - len % LANES;
    for c in (0..split).step_by(LANES) {
        let d: &mut [u16; LANES] = (&mut dst[c..c + LANES]).try_into().unwrap();
        let a: &[u8; LANES] = r[c..c + LANES].try_into().unwrap();
        for i in 0..LANES {
            d[i] += absdiff(l, a[i]);
        }
    }
    for k in split..len {
        dst[k] += absdiff(l, r[k]);
    }
}

/// `dst[k] = f(dst[k], a[k], b[k])` in fixed chunks, then a scalar tail: the shape of every
/// element-wise kernel below.
#[inline(always)]
fn zip3(dst: &mut [u16], a: &[u16], b: &[u16], f: impl Fn(u16, u16, u16) -> u16) {
    let len = dst.len();
    let (a, b) = (&a[..len], &b[..len]);
    let split = len - len % LANES;
    for c in (0..split).step_by(LANES) {
        let d: &mut [u16; LANES] = (&mut dst[c..c + LANES]).try_into().unwrap();
        let x: &[u16; LANES] = a[c..c + LANES].try_into().unwrap();
        let y: &[u16; LANES] = b[c..c + LANES].try_into().unwrap();
        for i in 0..LANES {
            d[i] = f(d[i], x[i], y[i]);
        }
    }
    for k in split..len {
        dst[k] = f(dst[k], a[k], b[k]);
    }
}

/// `sad[k] = prev[k] + add[k] − sub[k]`: the window slid one pixel right.
#[inline(always)]
pub fn slide_row(sad: &mut [u16], prev: &[u16], add: &[u16], sub: &[u16]) {
    let len = sad.len();
    sad.copy_from_slice(&prev[..len]);
    zip3(sad, add, sub, |p, a, s| p.wrapping_add(a).wrapping_sub(s));
}

/// `dst[k] += src[k]`.
#[inline(always)]
pub fn add_into(dst: &mut [u16], src: &[u16]) {
    zip3(dst, src, src, |d, s, _| d.wrapping_add(s));
}

/// `dst[i] = min(dst[i], src[i])`.
#[inline(always)]
pub fn min_into(dst: &mut [u16], src: &[u16]) {
    zip3(dst, src, src, |d, s, _| d.min(s));
}

/// Index of the first element equal to `target` (`v.len()` if none).
#[inline(always)]
pub fn first_index_of(v: &[u16], target: u16) -> usize {
    let split = v.len() - v.len() % LANES;
    for c in (0..split).step_by(LANES) {
        let s: &[u16; LANES] = v[c..c + LANES].try_into().unwrap();
        // A vector minimum per chunk, then a short scan of the chunk that holds it.
        if s.iter().fold(u16::MAX, |m, &x| m.min(x)) == target {
            return c + s.iter().position(|&x| x == target).unwrap_or(0);
        }
    }
    split + v[split..].iter().position(|&x| x == target).unwrap_or(v.len() - split)
}

/// Smallest value outside `around − 1 ..= around + 1` (`u16::MAX` if none): the direct
/// definition that `rival_from_lanes` must agree with.
///
/// The excluded lanes are masked by index arithmetic in registers; masking the slice in
/// memory instead would stall every vector load on the scalar stores before it.
#[inline(always)]
pub fn min_u16_away_from(v: &[u16], around: usize) -> u16 {
    const IOTA: [u16; LANES] = {
        let mut a = [0u16; LANES];
        let mut i = 0;
        while i < LANES {
            a[i] = i as u16;
            i += 1;
        }
        a
    };
    // `k − (around − 1)` wraps, so "k is within 1 of around" is one unsigned compare.
    let first = (around as u16).wrapping_sub(1);
    let split = v.len() - v.len() % LANES;
    let mut lanes = [u16::MAX; LANES];
    for c in (0..split).step_by(LANES) {
        let s: &[u16; LANES] = v[c..c + LANES].try_into().unwrap();
        for i in 0..LANES {
            let near = (c as u16).wrapping_add(IOTA[i]).wrapping_sub(first) <= 2;
            lanes[i] = lanes[i].min(if near { u16::MAX } else { s[i] });
        }
    }
    let head = lanes.iter().fold(u16::MAX, |m, &x| m.min(x));
    v[split..].iter().enumerate().filter(|(i, _)| (split + i).abs_diff(around) > 1).fold(head, |m, (_, &x)| m.min(x))
}

/// Smallest value of a slice (`u16::MAX` when empty).
#[inline(always)]
pub fn min_u16(v: &[u16]) -> u16 {
    let split = v.len() - v.len() % LANES;
    let mut lanes = [u16::MAX; LANES];
    for c in (0..split).step_by(LANES) {
        let s: &[u16; LANES] = v[c..c + LANES].try_into().unwrap();
        for i in 0..LANES {
            lanes[i] = lanes[i].min(s[i]);
        }
    }
    let head = lanes.iter().fold(u16::MAX, |m, &x| m.min(x));
    v[split..].iter().fold(head, |m, &x| m.min(x))
}

/// Hand-written AVX2 versions of the per-pixel reductions, where the auto-vectoriser falls
/// back to scalar code (index tests, horizontal minima). Callers must have checked that the
/// CPU has AVX2 (the matcher does, once per call).
#[cfg(target_arch = "x86_64")]
pub mod avx2 {
    use std::arch::x86_64::*;


    #[inline(always)]
    unsafe fn load(p: *const u16) -> __m256i {
        _mm256_loadu_si256(p as *const __m256i)
    }

    /// Horizontal minimum of 16 lanes.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    pub unsafe fn hmin(v: __m256i) -> u16 {
        let x = _mm_min_epu16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
        _mm_extract_epi16::<0>(_mm_minpos_epu16(x)) as u16
    }

    /// `right[i] = min(right[i], costs[i])`, and the minimum of `costs`.
    ///
    /// # Safety
    /// AVX2 must be available; `costs.len() >= right.len()`.
    #[inline(always)]
    pub unsafe fn min_into_and_min(right: &mut [u16], costs: &[u16]) -> u16 {
        let len = right.len();
        assert!(costs.len() >= len);
        let (rp, cp) = (right.as_mut_ptr(), costs.as_ptr());
        let mut acc = _mm256_set1_epi16(-1);
        let mut c = 0;
        while c + 16 <= len {
            let v = load(cp.add(c));
            let r = load(rp.add(c));
            _mm256_storeu_si256(rp.add(c) as *mut __m256i, _mm256_min_epu16(r, v));
            acc = _mm256_min_epu16(acc, v);
            c += 16;
        }
        let mut m = hmin(acc);
        for k in c..len {
            right[k] = right[k].min(costs[k]);
            m = m.min(costs[k]);
        }
        m
    }

    /// `row = prev + add − sub`, `right = min(right, row)`, and the minimum of `row`: one
    /// step of the horizontal window, the left–right splat and the winner search fused.
    ///
    /// # Safety
    /// AVX2 must be available; all slices as long as `row`.
    #[inline(always)]
    pub unsafe fn slide_row_min(row: &mut [u16], prev: &[u16], add: &[u16], sub: &[u16], right: &mut [u16]) -> u16 {
        let len = row.len();
        assert!(prev.len() == len && add.len() == len && sub.len() == len && right.len() == len);
        let mut acc = _mm256_set1_epi16(-1);
        let mut c = 0;
        while c + 16 <= len {
            let v = _mm256_sub_epi16(_mm256_add_epi16(load(prev.as_ptr().add(c)), load(add.as_ptr().add(c))), load(sub.as_ptr().add(c)));
            _mm256_storeu_si256(row.as_mut_ptr().add(c) as *mut __m256i, v);
            let r = load(right.as_ptr().add(c));
            _mm256_storeu_si256(right.as_mut_ptr().add(c) as *mut __m256i, _mm256_min_epu16(r, v));
            acc = _mm256_min_epu16(acc, v);
            c += 16;
        }
        let mut m = hmin(acc);
        for k in c..len {
            let v = prev[k].wrapping_add(add[k]).wrapping_sub(sub[k]);
            row[k] = v;
            right[k] = right[k].min(v);
            m = m.min(v);
        }
        m
    }

    /// One computed block of exactly 16 costs whose searched interval is lanes `t0..t1`:
    /// splats the searched costs onto `right` (16 entries; lanes outside the interval leave it
    /// unchanged) and returns the minimum over the interval, its first lane, and the minimum
    /// over the interval away from that lane by more than one — all in registers.
    ///
    /// # Safety
    /// AVX2 must be available; `row` and `right` hold 16 entries; `t0 < t1 <= 16`.
    #[inline(always)]
    pub unsafe fn block16(row: &[u16], t0: usize, t1: usize, right: &mut [u16]) -> (u16, usize, u16) {
        assert!(row.len() == 16 && right.len() == 16 && t0 < t1 && t1 <= 16);
        let iota = _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        // Lanes outside t0..t1 read as u16::MAX: (lane − t0) ≥ (t1 − t0) unsigned.
        let rel = _mm256_sub_epi16(iota, _mm256_set1_epi16(t0 as i16));
        let width = _mm256_set1_epi16((t1 - t0 - 1) as i16);
        let inside = _mm256_cmpeq_epi16(_mm256_min_epu16(rel, width), rel);
        let v = _mm256_or_si256(load(row.as_ptr()), _mm256_andnot_si256(inside, _mm256_set1_epi16(-1)));
        let r = load(right.as_ptr());
        _mm256_storeu_si256(right.as_mut_ptr() as *mut __m256i, _mm256_min_epu16(r, v));
        let min = hmin(v);
        let eq = _mm256_movemask_epi8(_mm256_cmpeq_epi16(v, _mm256_set1_epi16(min as i16))) as u32;
        let best = eq.trailing_zeros() as usize / 2;
        // Mask best − 1 ..= best + 1 as well: (lane − (best − 1)) ≤ 2 unsigned.
        let d = _mm256_sub_epi16(iota, _mm256_set1_epi16(best as i16 - 1));
        let near = _mm256_cmpeq_epi16(_mm256_min_epu16(d, _mm256_set1_epi16(2)), d);
        let rival = hmin(_mm256_or_si256(v, near));
        (min, best, rival)
    }

    /// Minimum of `v`.
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    pub unsafe fn min(v: &[u16]) -> u16 {
        let mut acc = _mm256_set1_epi16(-1);
        let mut c = 0;
        while c + 16 <= v.len() {
            acc = _mm256_min_epu16(acc, load(v.as_ptr().add(c)));
            c += 16;
        }
        v[c..].iter().fold(hmin(acc), |m, &x| m.min(x))
    }

    /// Minimum outside `around − 1 ..= around + 1` (`u16::MAX` if none).
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    pub unsafe fn min_away_from(v: &[u16], around: usize) -> u16 {
        let iota = _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        // `k − (around − 1)` wraps, so "within 1 of around" is `≤ 2` unsigned.
        let first = _mm256_set1_epi16((around as u16).wrapping_sub(1) as i16);
        let two = _mm256_set1_epi16(2);
        let mut acc = _mm256_set1_epi16(-1);
        let mut c = 0;
        while c + 16 <= v.len() {
            // Every chunk is masked (no branch on where `around` lies: it would mispredict).
            let idx = _mm256_add_epi16(_mm256_set1_epi16(c as i16), iota);
            let d = _mm256_sub_epi16(idx, first);
            let near = _mm256_cmpeq_epi16(_mm256_min_epu16(d, two), d);
            acc = _mm256_min_epu16(acc, _mm256_or_si256(load(v.as_ptr().add(c)), near));
            c += 16;
        }
        let mut m = hmin(acc);
        for k in c..v.len() {
            if k.abs_diff(around) > 1 {
                m = m.min(v[k]);
            }
        }
        m
    }

    /// `cs[k] += |l_new − r_new[k]| − |l_old − r_old[k]|`, 32 disparities per step: byte
    /// differences in one register, widened in two halves.
    ///
    /// # Safety
    /// AVX2 must be available; `r_new` and `r_old` at least as long as `cs`.
    #[inline(always)]
    pub unsafe fn slide_column(cs: &mut [u16], l_new: u8, r_new: &[u8], l_old: u8, r_old: &[u8]) {
        let len = cs.len();
        assert!(r_new.len() >= len && r_old.len() >= len);
        let (ln, lo) = (_mm256_set1_epi8(l_new as i8), _mm256_set1_epi8(l_old as i8));
        let cp = cs.as_mut_ptr();
        let mut c = 0;
        while c + 32 <= len {
            let rn = _mm256_loadu_si256(r_new.as_ptr().add(c) as *const __m256i);
            let ro = _mm256_loadu_si256(r_old.as_ptr().add(c) as *const __m256i);
            let dn = _mm256_sub_epi8(_mm256_max_epu8(rn, ln), _mm256_min_epu8(rn, ln));
            let dold = _mm256_sub_epi8(_mm256_max_epu8(ro, lo), _mm256_min_epu8(ro, lo));
            let (n0, n1) = (_mm256_cvtepu8_epi16(_mm256_castsi256_si128(dn)), _mm256_cvtepu8_epi16(_mm256_extracti128_si256::<1>(dn)));
            let (o0, o1) = (_mm256_cvtepu8_epi16(_mm256_castsi256_si128(dold)), _mm256_cvtepu8_epi16(_mm256_extracti128_si256::<1>(dold)));
            let p0 = cp.add(c) as *mut __m256i;
            let p1 = cp.add(c + 16) as *mut __m256i;
            _mm256_storeu_si256(p0, _mm256_sub_epi16(_mm256_add_epi16(_mm256_loadu_si256(p0), n0), o0));
            _mm256_storeu_si256(p1, _mm256_sub_epi16(_mm256_add_epi16(_mm256_loadu_si256(p1), n1), o1));
            c += 32;
        }
        super::slide_column(&mut cs[c..], l_new, &r_new[c..len], l_old, &r_old[c..len]);
    }

    /// Index of the first element equal to `target` (`v.len()` if none). No data-dependent
    /// branch: every chunk is compared and the first hit is kept with a conditional move
    /// (the chunk that holds the winner is unpredictable, so an early exit mispredicts).
    ///
    /// # Safety
    /// AVX2 must be available.
    #[inline(always)]
    pub unsafe fn first_index_of(v: &[u16], target: u16) -> usize {
        let t = _mm256_set1_epi16(target as i16);
        let mut first = usize::MAX;
        let mut c = 0;
        while c + 16 <= v.len() {
            let mask = _mm256_movemask_epi8(_mm256_cmpeq_epi16(load(v.as_ptr().add(c)), t)) as u32;
            let hit = c + mask.trailing_zeros() as usize / 2;
            first = if mask != 0 { first.min(hit) } else { first };
            c += 16;
        }
        for (k, &x) in v.iter().enumerate().skip(c) {
            first = if x == target { first.min(k) } else { first };
        }
        first.min(v.len())
    }

}

/// AVX-512BW versions of the run kernels: 32 costs (64 byte differences) per instruction.
/// Callers must have checked that the CPU has AVX-512F and AVX-512BW.
#[cfg(target_arch = "x86_64")]
pub mod avx512 {
    use std::arch::x86_64::*;

    #[inline(always)]
    unsafe fn load(p: *const u16) -> __m512i {
        _mm512_loadu_si512(p as *const _)
    }

    /// Horizontal minimum of 32 lanes.
    #[inline(always)]
    unsafe fn hmin(v: __m512i) -> u16 {
        let h = _mm256_min_epu16(_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64::<1>(v));
        let x = _mm_min_epu16(_mm256_castsi256_si128(h), _mm256_extracti128_si256::<1>(h));
        _mm_extract_epi16::<0>(_mm_minpos_epu16(x)) as u16
    }

    /// As [`super::avx2::slide_column`], 64 disparities per step.
    ///
    /// # Safety
    /// AVX-512BW must be available; `r_new` and `r_old` at least as long as `cs`.
    #[inline(always)]
    pub unsafe fn slide_column(cs: &mut [u16], l_new: u8, r_new: &[u8], l_old: u8, r_old: &[u8]) {
        let len = cs.len();
        assert!(r_new.len() >= len && r_old.len() >= len);
        let (ln, lo) = (_mm512_set1_epi8(l_new as i8), _mm512_set1_epi8(l_old as i8));
        let cp = cs.as_mut_ptr();
        let mut c = 0;
        while c + 64 <= len {
            let rn = _mm512_loadu_si512(r_new.as_ptr().add(c) as *const _);
            let ro = _mm512_loadu_si512(r_old.as_ptr().add(c) as *const _);
            let dn = _mm512_sub_epi8(_mm512_max_epu8(rn, ln), _mm512_min_epu8(rn, ln));
            let dold = _mm512_sub_epi8(_mm512_max_epu8(ro, lo), _mm512_min_epu8(ro, lo));
            let (n0, n1) = (_mm512_cvtepu8_epi16(_mm512_castsi512_si256(dn)), _mm512_cvtepu8_epi16(_mm512_extracti64x4_epi64::<1>(dn)));
            let (o0, o1) = (_mm512_cvtepu8_epi16(_mm512_castsi512_si256(dold)), _mm512_cvtepu8_epi16(_mm512_extracti64x4_epi64::<1>(dold)));
            let p0 = cp.add(c);
            let p1 = cp.add(c + 32);
            _mm512_storeu_si512(p0 as *mut _, _mm512_sub_epi16(_mm512_add_epi16(load(p0), n0), o0));
            _mm512_storeu_si512(p1 as *mut _, _mm512_sub_epi16(_mm512_add_epi16(load(p1), n1), o1));
            c += 64;
        }
        if c < len {
            super::avx2::slide_column(&mut cs[c..], l_new, &r_new[c..len], l_old, &r_old[c..len]);
        }
    }

    /// As [`super::avx2::slide_row_min`], 32 costs per step.
    ///
    /// # Safety
    /// AVX-512BW must be available; all slices as long as `row`.
    #[inline(always)]
    pub unsafe fn slide_row_min(row: &mut [u16], prev: &[u16], add: &[u16], sub: &[u16], right: &mut [u16]) -> u16 {
        let len = row.len();
        assert!(prev.len() == len && add.len() == len && sub.len() == len && right.len() == len);
        let mut acc = _mm512_set1_epi16(-1);
        let mut c = 0;
        while c + 32 <= len {
            let v = _mm512_sub_epi16(_mm512_add_epi16(load(prev.as_ptr().add(c)), load(add.as_ptr().add(c))), load(sub.as_ptr().add(c)));
            _mm512_storeu_si512(row.as_mut_ptr().add(c) as *mut _, v);
            let r = load(right.as_ptr().add(c));
            _mm512_storeu_si512(right.as_mut_ptr().add(c) as *mut _, _mm512_min_epu16(r, v));
            acc = _mm512_min_epu16(acc, v);
            c += 32;
        }
        let m = hmin(acc);
        if c == len {
            return m;
        }
        m.min(super::avx2::slide_row_min(&mut row[c..], &prev[c..], &add[c..], &sub[c..], &mut right[c..]))
    }

    /// As [`super::avx2::first_index_of`], 32 lanes per step.
    ///
    /// # Safety
    /// AVX-512BW must be available.
    #[inline(always)]
    pub unsafe fn first_index_of(v: &[u16], target: u16) -> usize {
        let t = _mm512_set1_epi16(target as i16);
        let mut c = 0;
        while c + 32 <= v.len() {
            let mask = _mm512_cmpeq_epi16_mask(load(v.as_ptr().add(c)), t);
            if mask != 0 {
                return c + mask.trailing_zeros() as usize;
            }
            c += 32;
        }
        if c == v.len() {
            return c;
        }
        c + super::avx2::first_index_of(&v[c..], target)
    }

    /// As [`super::avx2::min_away_from`], with the excluded lanes as a mask register.
    ///
    /// # Safety
    /// AVX-512BW must be available.
    #[inline(always)]
    pub unsafe fn min_away_from(v: &[u16], around: usize) -> u16 {
        let mut acc = _mm512_set1_epi16(-1);
        let mut c = 0;
        while c + 32 <= v.len() {
            // Bits of around − 1 ..= around + 1 that fall in lanes c .. c + 32.
            let shift = around as i64 + 1 - c as i64; // bit position of around − 1, plus 2
            let near = if (0..34).contains(&shift) { ((0b111u64 << shift) >> 2) as u32 } else { 0 };
            acc = _mm512_mask_min_epu16(acc, !near, acc, load(v.as_ptr().add(c)));
            c += 32;
        }
        let mut m = hmin(acc);
        for k in c..v.len() {
            if k.abs_diff(around) > 1 {
                m = m.min(v[k]);
            }
        }
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunked_kernels_match_scalar_for_every_length() {
        for len in 0..70usize {
            let r: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
            let r2: Vec<u8> = (0..len).map(|i| (i * 91 % 241) as u8).collect();
            let mut cs: Vec<u16> = (0..len).map(|i| 1000 + i as u16).collect();
            let want: Vec<u16> = cs.iter().enumerate().map(|(i, &c)| c + 30u8.abs_diff(r[i]) as u16 - 200u8.abs_diff(r2[i]) as u16).collect();
            slide_column(&mut cs, 30, &r, 200, &r2);
            assert_eq!(cs, want, "slide_column len {len}");

            let costs: Vec<u16> = (0..len).map(|i| ((i * 7919) % 97) as u16).collect();
            let mut right = vec![50u16; len];
            min_into(&mut right, &costs);
            assert!(right.iter().zip(&costs).all(|(&r, &c)| r == c.min(50)));
            if len > 0 {
                let m = *costs.iter().min().unwrap();
                let at = costs.iter().position(|&c| c == m).unwrap();
                assert_eq!(min_u16(&costs), m);
                assert_eq!(first_index_of(&costs, m), at);
                let away = costs.iter().enumerate().filter(|(i, _)| i.abs_diff(at) > 1).map(|(_, &c)| c).min().unwrap_or(u16::MAX);
                assert_eq!(min_u16_away_from(&costs, at), away, "len {len}");
            } else {
                assert_eq!(min_u16(&costs), u16::MAX);
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_kernels_match_portable_ones() {
        if !std::is_x86_feature_detected!("avx2") {
            return; // nothing to compare on this CPU; the portable kernels are tested above
        }
        for len in 1..70usize {
            let costs: Vec<u16> = (0..len).map(|i| ((i * 7919 + len) % 97) as u16).collect();
            let mut r1 = vec![40u16; len];
            let mut r2 = r1.clone();
            // SAFETY: AVX2 is available (checked above).
            unsafe {
                assert_eq!(avx2::min_into_and_min(&mut r1, &costs), min_u16(&costs));
                min_into(&mut r2, &costs);
                assert_eq!(r1, r2);
                assert_eq!(avx2::min(&costs), min_u16(&costs));
                for around in 0..len {
                    assert_eq!(avx2::min_away_from(&costs, around), min_u16_away_from(&costs, around), "len {len} around {around}");
                }
                let m = min_u16(&costs);
                assert_eq!(avx2::first_index_of(&costs, m), first_index_of(&costs, m));
                assert_eq!(avx2::first_index_of(&costs, 1000), len);
                let (add, sub): (Vec<u16>, Vec<u16>) = (costs.iter().map(|c| c * 3).collect(), costs.iter().map(|c| c / 2).collect());
                let mut row = vec![0u16; len];
                let mut right = vec![60u16; len];
                let got = avx2::slide_row_min(&mut row, &costs, &add, &sub, &mut right);
                let want: Vec<u16> = (0..len).map(|i| costs[i] + add[i] - sub[i]).collect();
                assert_eq!(row, want);
                assert_eq!(got, *want.iter().min().unwrap());
                assert!(right.iter().zip(&want).all(|(&r, &v)| r == v.min(60)));
                if len == 16 {
                    for t0 in 0..16 {
                        for t1 in t0 + 1..=16 {
                            let mut r1 = vec![50u16; 16];
                            let mut r2 = r1.clone();
                            let (min, best, rival) = avx2::block16(&costs, t0, t1, &mut r1);
                            let sub = &costs[t0..t1];
                            min_into(&mut r2[t0..t1], sub);
                            assert_eq!(r1, r2);
                            assert_eq!(min, min_u16(sub));
                            assert_eq!(best, t0 + first_index_of(sub, min));
                            assert_eq!(rival, min_u16_away_from(sub, best - t0), "t0 {t0} t1 {t1}");
                        }
                    }
                }
                let rn: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
                let ro: Vec<u8> = (0..len).map(|i| (i * 91 % 241) as u8).collect();
                let mut a: Vec<u16> = (0..len).map(|i| 1000 + i as u16).collect();
                let mut b = a.clone();
                avx2::slide_column(&mut a, 30, &rn, 200, &ro);
                slide_column(&mut b, 30, &rn, 200, &ro);
                assert_eq!(a, b);
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_kernels_match_portable_ones() {
        if !(std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw")) {
            return; // nothing to compare on this CPU; the portable kernels are tested above
        }
        for len in 1..140usize {
            let costs: Vec<u16> = (0..len).map(|i| ((i * 7919 + len) % 97) as u16).collect();
            // SAFETY: AVX-512F/BW are available (checked above).
            unsafe {
                let m = min_u16(&costs);
                assert_eq!(avx512::first_index_of(&costs, m), first_index_of(&costs, m));
                assert_eq!(avx512::first_index_of(&costs, 1000), len);
                for around in 0..len {
                    assert_eq!(avx512::min_away_from(&costs, around), min_u16_away_from(&costs, around), "len {len} around {around}");
                }
                let (add, sub): (Vec<u16>, Vec<u16>) = (costs.iter().map(|c| c * 3).collect(), costs.iter().map(|c| c / 2).collect());
                let mut row = vec![0u16; len];
                let mut right = vec![60u16; len];
                let got = avx512::slide_row_min(&mut row, &costs, &add, &sub, &mut right);
                let want: Vec<u16> = (0..len).map(|i| costs[i] + add[i] - sub[i]).collect();
                assert_eq!(row, want);
                assert_eq!(got, *want.iter().min().unwrap());
                assert!(right.iter().zip(&want).all(|(&r, &v)| r == v.min(60)));
                let rn: Vec<u8> = (0..len).map(|i| (i * 37 % 251) as u8).collect();
                let ro: Vec<u8> = (0..len).map(|i| (i * 91 % 241) as u8).collect();
                let mut a: Vec<u16> = (0..len).map(|i| 1000 + i as u16).collect();
                let mut b = a.clone();
                avx512::slide_column(&mut a, 30, &rn, 200, &ro);
                slide_column(&mut b, 30, &rn, 200, &ro);
                assert_eq!(a, b);
            }
        }
    }
}
