//! Remap tables (OpenCV's `initUndistortRectifyMap`) and bilinear sampling through them:
//! every frame's first stage, on every pixel of both images.
//!
//! A table keeps each rectified pixel's raw coordinates (`map`, the exact float path) and
//! the same in fixed point, as OpenCV's `remap` does: the top-left neighbour's index and the
//! bilinear weights in 1/256 (OpenCV's in 1/32). Pixels whose four neighbours are all inside
//! the source go through the fixed-point path — in AVX2 registers eight at a time, with the
//! same integer operations in the same order as the portable loop, so both give the same
//! bytes — and the few on the border through the exact one.
//!
//! The right image is only ever matched in grey, so [`RemapTable::remap_gray`] samples the
//! colour channels and converts them in one pass ([`luma`] of the rectified colour, the bytes
//! [`RemapTable::remap`] and a conversion after it would give).

use nalgebra::{Matrix3, Vector3};

use crate::calib::Camera;

/// For every rectified pixel, the raw pixel it samples (OpenCV `initUndistortRectifyMap`).
#[derive(Debug, Clone)]
pub struct RemapTable {
    pub width: u32,
    pub height: u32,
    /// Interleaved `(x, y)` raw coordinates, row-major.
    pub map: Vec<[f32; 2]>,
    /// Per output pixel, for a source of the table's own size: the index of the top-left
    /// neighbour, or [`OUTSIDE`] (all four outside: black) or [`BORDER`] (some outside:
    /// sampled by the exact path). Both marks have the top bit set; real indices do not.
    idx: Vec<u32>,
    /// Per output pixel, the bilinear weights of the right and lower neighbours in 1/256:
    /// `fx | fy << 16`.
    weights: Vec<u32>,
    /// The output pixels marked [`BORDER`], in order.
    border: Vec<u32>,
}

const OUTSIDE: u32 = u32::MAX;
const BORDER: u32 = u32::MAX - 1;

/// Grey level of an RGB pixel: ITU-R BT.601 weights in 1/16384, rounded (OpenCV's
/// `COLOR_RGB2GRAY`).
#[inline(always)]
pub fn luma(r: u8, g: u8, b: u8) -> u8 {
    ((r as u32 * 4899 + g as u32 * 9617 + b as u32 * 1868 + (1 << 13)) >> 14) as u8
}

impl RemapTable {
    /// Builds the table for a camera, its rectifying rotation and new camera matrix.
    pub fn new(cam: &Camera, r: &Matrix3<f64>, p: &Matrix3<f64>, size: (u32, u32)) -> RemapTable {
        let ir = (p * r).try_inverse().expect("P·R of a rectification is invertible");
        let (fx, fy, cx, cy) = (cam.k[(0, 0)], cam.k[(1, 1)], cam.k[(0, 2)], cam.k[(1, 2)]);
        let mut map = Vec::with_capacity(size.0 as usize * size.1 as usize);
        for v in 0..size.1 {
            for u in 0..size.0 {
                let ray = ir * Vector3::new(u as f64, v as f64, 1.0);
                let (xd, yd) = cam.distortion.distort(ray.x / ray.z, ray.y / ray.z);
                map.push([(fx * xd + cx) as f32, (fy * yd + cy) as f32]);
            }
        }
        let (sw, sh) = (size.0 as i64, size.1 as i64);
        let (mut idx, mut weights, mut border) = (Vec::with_capacity(map.len()), Vec::with_capacity(map.len()), Vec::new());
        for (i, &[mx, my]) in map.iter().enumerate() {
            let (x0, y0) = (mx.floor() as i64, my.floor() as i64);
            let (fx, fy) = (((mx - mx.floor()) * 256.0).round() as u32, ((my - my.floor()) * 256.0).round() as u32);
            let tap = if x0 < -1 || y0 < -1 || x0 >= sw || y0 >= sh {
                OUTSIDE
            } else if x0 < 0 || y0 < 0 || x0 + 1 >= sw || y0 + 1 >= sh {
                border.push(i as u32);
                BORDER
            } else {
                (y0 * sw + x0) as u32
            };
            idx.push(tap);
            weights.push(fx | fy << 16);
        }
        RemapTable { width: size.0, height: size.1, map, idx, weights, border }
    }

    /// Resamples an image of `C` interleaved 8-bit channels bilinearly; samples outside the
    /// source are black (OpenCV's `BORDER_CONSTANT`).
    pub fn remap<const C: usize>(&self, src: &[u8], src_w: u32, src_h: u32) -> Vec<u8> {
        if !self.fits::<C>(src, src_w, src_h) {
            return self.remap_exact::<C>(src, src_w, src_h);
        }
        let mut out = vec![0u8; self.map.len() * C];
        self.fixed::<C>(src, Some(&mut out), None, true);
        self.border_exact::<C>(src, src_w, src_h, Some(&mut out), None);
        out
    }

    /// The rectified RGB image and its grey levels ([`luma`]), in one pass.
    pub fn remap_rgb_gray(&self, src: &[u8], src_w: u32, src_h: u32) -> (Vec<u8>, Vec<u8>) {
        if !self.fits::<3>(src, src_w, src_h) {
            let rgb = self.remap_exact::<3>(src, src_w, src_h);
            let gray = rgb.chunks_exact(3).map(|p| luma(p[0], p[1], p[2])).collect();
            return (rgb, gray);
        }
        let (mut rgb, mut gray) = (vec![0u8; self.map.len() * 3], vec![0u8; self.map.len()]);
        self.fixed::<3>(src, Some(&mut rgb), Some(&mut gray), true);
        self.border_exact::<3>(src, src_w, src_h, Some(&mut rgb), Some(&mut gray));
        (rgb, gray)
    }

    /// The grey levels ([`luma`]) of the rectified RGB image, without keeping its colour.
    pub fn remap_gray(&self, src: &[u8], src_w: u32, src_h: u32) -> Vec<u8> {
        if !self.fits::<3>(src, src_w, src_h) {
            return self.remap_rgb_gray(src, src_w, src_h).1;
        }
        let mut gray = vec![0u8; self.map.len()];
        self.fixed::<3>(src, None, Some(&mut gray), true);
        self.border_exact::<3>(src, src_w, src_h, None, Some(&mut gray));
        gray
    }

    /// Whether `src` is an image of the table's own size that the fixed-point path can read.
    fn fits<const C: usize>(&self, src: &[u8], src_w: u32, src_h: u32) -> bool {
        (src_w, src_h) == (self.width, self.height) && src.len() >= (src_w * src_h) as usize * C
    }

    /// The fixed-point path over every pixel: `out` gets the `C` channels, `gray` (with
    /// `C == 3`) their [`luma`]; [`OUTSIDE`] and [`BORDER`] pixels get zeros (the border is
    /// overwritten by the caller). `vector`: the AVX2 path may run (where the CPU has it).
    fn fixed<const C: usize>(&self, src: &[u8], mut out: Option<&mut [u8]>, mut gray: Option<&mut [u8]>, vector: bool) {
        let n = self.idx.len();
        assert!(gray.is_none() || C == 3);
        assert!(src.len() >= n * C && out.as_ref().is_none_or(|o| o.len() >= n * C) && gray.as_ref().is_none_or(|g| g.len() >= n));
        let stride = self.width as usize * C;
        let mut start = 0;
        #[cfg(target_arch = "x86_64")]
        if vector && (C == 1 || C == 3) && simd() {
            // SAFETY: the CPU has AVX2 (checked just above), and the sizes asserted above.
            start = unsafe { avx2::fixed::<C>(self, src, out.as_deref_mut(), gray.as_deref_mut()) };
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = vector;
        for i in start..n {
            self.fixed_pixel::<C>(src, stride, i, out.as_deref_mut(), gray.as_deref_mut());
        }
    }

    /// Output pixel `i` by the portable fixed-point path into `out` and `gray` (as
    /// [`RemapTable::fixed`]); [`OUTSIDE`] and [`BORDER`] pixels are left alone.
    #[inline(always)]
    fn fixed_pixel<const C: usize>(&self, src: &[u8], stride: usize, i: usize, out: Option<&mut [u8]>, gray: Option<&mut [u8]>) {
        let t = self.idx[i];
        if t & 1 << 31 != 0 {
            return;
        }
        put(tap::<C>(src, stride, t, self.weights[i]), i, out, gray);
    }

    /// The [`BORDER`] pixels by the exact path into `out` and `gray` (where
    /// [`RemapTable::fixed`] left zeros).
    fn border_exact<const C: usize>(&self, src: &[u8], src_w: u32, src_h: u32, mut out: Option<&mut [u8]>, mut gray: Option<&mut [u8]>) {
        for &i in &self.border {
            let i = i as usize;
            put(self.exact_pixel::<C>(src, src_w, src_h, i), i, out.as_deref_mut(), gray.as_deref_mut());
        }
    }

    /// Float bilinear sampling of output pixel `i`.
    fn exact_pixel<const C: usize>(&self, src: &[u8], src_w: u32, src_h: u32, i: usize) -> [u8; C] {
        let (sw, sh) = (src_w as i64, src_h as i64);
        let [mx, my] = self.map[i];
        let (x0f, y0f) = (mx.floor(), my.floor());
        let (fx, fy) = (mx - x0f, my - y0f);
        let (x0, y0) = (x0f as i64, y0f as i64);
        if x0 < -1 || y0 < -1 || x0 >= sw || y0 >= sh {
            return [0; C];
        }
        let px = |x: i64, y: i64, c: usize| -> f32 {
            if x < 0 || y < 0 || x >= sw || y >= sh {
                0.0
            } else {
                src.get(((y * sw + x) as usize) * C + c).map_or(0.0, |&v| v as f32)
            }
        };
        std::array::from_fn(|c| {
            let top = px(x0, y0, c) * (1.0 - fx) + px(x0 + 1, y0, c) * fx;
            let bottom = px(x0, y0 + 1, c) * (1.0 - fx) + px(x0 + 1, y0 + 1, c) * fx;
            (top * (1.0 - fy) + bottom * fy).round().clamp(0.0, 255.0) as u8
        })
    }

    /// Float bilinear sampling of every pixel, for a source of any size.
    fn remap_exact<const C: usize>(&self, src: &[u8], src_w: u32, src_h: u32) -> Vec<u8> {
        (0..self.map.len()).flat_map(|i| self.exact_pixel::<C>(src, src_w, src_h, i)).collect()
    }
}

/// Output pixel `i`'s sample `p` into `out` (its `C` channels) and `gray` (its [`luma`], with
/// `C == 3`).
#[inline(always)]
fn put<const C: usize>(p: [u8; C], i: usize, out: Option<&mut [u8]>, gray: Option<&mut [u8]>) {
    if let Some(out) = out {
        out[i * C..(i + 1) * C].copy_from_slice(&p);
    }
    if let Some(gray) = gray {
        gray[i] = luma(p[0], p[1 % C], p[2 % C]);
    }
}

fn simd() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::is_x86_feature_detected!("avx2");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// One pixel in fixed point: `idx` its top-left neighbour, `wt` its weights (`fx | fy << 16`).
#[inline(always)]
fn tap<const C: usize>(src: &[u8], stride: usize, idx: u32, wt: u32) -> [u8; C] {
    let o = idx as usize * C;
    let (fx, fy) = (wt & 0xFFFF, wt >> 16);
    let (gx, gy) = (256 - fx, 256 - fy);
    std::array::from_fn(|c| {
        let top = src[o + c] as u32 * gx + src[o + C + c] as u32 * fx;
        let bottom = src[o + stride + c] as u32 * gx + src[o + stride + C + c] as u32 * fx;
        ((top * gy + bottom * fy + 32768) >> 16) as u8
    })
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::RemapTable;

    /// [`RemapTable::fixed`] eight output pixels at a time: the four neighbours' bytes by
    /// plain loads put into lanes (one 64-bit load a row and pixel in colour; with gather
    /// instructions a realistic pair took 1.28 ms instead of 1.10 on this AMD machine, `cargo
    /// bench --bench matcher -- rectify`), each channel's row pair weighted by one `madd`, the
    /// rows blended in 32 bits. Returns the first pixel it left to the portable loop (the last
    /// few, whose stores would run past the end). A group of eight whose loads could read past
    /// `src` goes pixel by pixel.
    ///
    /// SAFETY: the CPU has AVX2; `src` holds `C` bytes per output pixel (the table's
    /// `width × height`); `out` and `gray`, when given, hold `C` and 1 bytes per output pixel.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn fixed<const C: usize>(t: &RemapTable, src: &[u8], mut out: Option<&mut [u8]>, mut gray: Option<&mut [u8]>) -> usize {
        let n = t.idx.len();
        let stride = t.width as usize * C;
        // The last top-left index whose reads stay inside `src`: with C = 3, 64 bits at o
        // and at o + stride ([`taps64`]); with C = 1, 32 bits there ([`taps32`]).
        let reach = if C == 3 { 8 } else { 4 };
        let Some(last_read) = src.len().checked_sub(stride + reach) else { return 0 };
        let limit = _mm256_set1_epi32((last_read / C).min(i32::MAX as usize) as i32);
        // Stores write 16 bytes (C = 3: at 3i and 3i + 12) or 8: stop where they would run
        // past the end.
        let end = n.saturating_sub(8 + 2) / 8 * 8;
        let bytes = src.as_ptr();
        let k256 = _mm256_set1_epi32(256);
        let lo16 = _mm256_set1_epi32(0xFFFF);
        let byte = _mm256_set1_epi32(0xFF);
        let hibyte = _mm256_set1_epi32(0xFF_0000);
        let half = _mm256_set1_epi32(32768);
        let rg = _mm256_set1_epi32(4899 | 9617 << 16);
        let b1 = _mm256_set1_epi32(1868 | (1 << 13) << 16);
        let one_hi = _mm256_set1_epi32(1 << 16);
        let mut i = 0;
        while i < end {
            let iv = _mm256_loadu_si256(t.idx.as_ptr().add(i) as *const __m256i);
            let special = _mm256_srai_epi32(iv, 31);
            let iv = _mm256_andnot_si256(special, iv);
            if _mm256_movemask_epi8(_mm256_cmpgt_epi32(iv, limit)) != 0 {
                for j in i..i + 8 {
                    t.fixed_pixel::<C>(src, stride, j, out.as_deref_mut(), gray.as_deref_mut());
                }
                i += 8;
                continue;
            }
            let wv = _mm256_loadu_si256(t.weights.as_ptr().add(i) as *const __m256i);
            let fx = _mm256_and_si256(wv, lo16);
            let fy = _mm256_srli_epi32(wv, 16);
            let gy = _mm256_sub_epi32(k256, fy);
            // 16-bit pairs (256 − fx, fx): one `madd` weighs a row's two neighbours.
            let hw = _mm256_or_si256(_mm256_sub_epi32(k256, fx), _mm256_slli_epi32(fx, 16));
            let off = if C == 3 { _mm256_add_epi32(iv, _mm256_slli_epi32(iv, 1)) } else { iv };
            let mut o = [0i32; 8];
            _mm256_storeu_si256(o.as_mut_ptr() as *mut __m256i, off);
            let (top0, top1, bot0, bot1) = if C == 3 {
                let (t0, t1) = taps64(bytes, &o);
                let (b0, b1) = taps64(bytes.add(stride), &o);
                (t0, t1, b0, b1)
            } else {
                let top0 = taps32(bytes, &o);
                let bot0 = taps32(bytes.add(stride), &o);
                (top0, _mm256_srli_epi32(top0, 8), bot0, _mm256_srli_epi32(bot0, 8))
            };
            // Channel c of both neighbours of a row as the 16-bit pair (left, right).
            let pair = |a: __m256i, b: __m256i, c: i32| -> __m256i {
                let l = _mm256_and_si256(_mm256_srlv_epi32(a, _mm256_set1_epi32(8 * c)), byte);
                let r = _mm256_and_si256(_mm256_sllv_epi32(b, _mm256_set1_epi32(16 - 8 * c)), hibyte);
                _mm256_or_si256(l, r)
            };
            let channel = |c: i32| -> __m256i {
                let top = _mm256_madd_epi16(pair(top0, top1, c), hw);
                let bottom = _mm256_madd_epi16(pair(bot0, bot1, c), hw);
                let v = _mm256_add_epi32(_mm256_add_epi32(_mm256_mullo_epi32(top, gy), _mm256_mullo_epi32(bottom, fy)), half);
                _mm256_srli_epi32(v, 16)
            };
            if C == 1 {
                let v = channel(0);
                let packed = _mm256_shuffle_epi8(v, _mm256_setr_epi8(0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1));
                let packed = _mm256_permutevar8x32_epi32(packed, _mm256_setr_epi32(0, 4, 1, 1, 1, 1, 1, 1));
                if let Some(out) = out.as_deref_mut() {
                    _mm_storel_epi64(out.as_mut_ptr().add(i) as *mut __m128i, _mm256_castsi256_si128(packed));
                }
            } else {
                let (r, g, b) = (channel(0), channel(1), channel(2));
                if let Some(out) = out.as_deref_mut() {
                    let v = _mm256_or_si256(r, _mm256_or_si256(_mm256_slli_epi32(g, 8), _mm256_slli_epi32(b, 16)));
                    let v = _mm256_shuffle_epi8(v, _mm256_setr_epi8(0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, -1, -1, -1, -1, 0, 1, 2, 4, 5, 6, 8, 9, 10, 12, 13, 14, -1, -1, -1, -1));
                    let p = out.as_mut_ptr().add(3 * i);
                    _mm_storeu_si128(p as *mut __m128i, _mm256_castsi256_si128(v));
                    _mm_storeu_si128(p.add(12) as *mut __m128i, _mm256_extracti128_si256::<1>(v));
                }
                if let Some(gray) = gray.as_deref_mut() {
                    let l = _mm256_add_epi32(_mm256_madd_epi16(_mm256_or_si256(r, _mm256_slli_epi32(g, 16)), rg), _mm256_madd_epi16(_mm256_or_si256(b, one_hi), b1));
                    let l = _mm256_srli_epi32(l, 14);
                    let packed = _mm256_shuffle_epi8(l, _mm256_setr_epi8(0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1));
                    let packed = _mm256_permutevar8x32_epi32(packed, _mm256_setr_epi32(0, 4, 1, 1, 1, 1, 1, 1));
                    _mm_storel_epi64(gray.as_mut_ptr().add(i) as *mut __m128i, _mm256_castsi256_si128(packed));
                }
            }
            // OUTSIDE and BORDER lanes sampled index 0: zero them.
            if special_any(special) {
                for j in i..i + 8 {
                    if t.idx[j] & 1 << 31 != 0 {
                        if let Some(out) = out.as_deref_mut() {
                            out[j * C..(j + 1) * C].fill(0);
                        }
                        if let Some(gray) = gray.as_deref_mut() {
                            gray[j] = 0;
                        }
                    }
                }
            }
            i += 8;
        }
        i
    }

    /// The 32 bits at each of the eight byte offsets `o` from `base`, by plain loads.
    ///
    /// SAFETY: each offset and the 4 bytes from it lie inside the buffer `base` points into.
    #[inline(always)]
    unsafe fn taps32(base: *const u8, o: &[i32; 8]) -> __m256i {
        let at = |k: usize| (base.add(o[k] as usize) as *const i32).read_unaligned();
        _mm256_setr_epi32(at(0), at(1), at(2), at(3), at(4), at(5), at(6), at(7))
    }

    /// The 32 bits at each of the eight byte offsets `o` from `base`, and the 32 bits three
    /// bytes further: one 64-bit load a pixel.
    ///
    /// SAFETY: each offset and the 8 bytes from it lie inside the buffer `base` points into.
    #[inline(always)]
    unsafe fn taps64(base: *const u8, o: &[i32; 8]) -> (__m256i, __m256i) {
        let at = |k: usize| (base.add(o[k] as usize) as *const i64).read_unaligned();
        let a = _mm256_setr_epi64x(at(0), at(1), at(2), at(3));
        let b = _mm256_setr_epi64x(at(4), at(5), at(6), at(7));
        // The low 32 bits of each 64, in pixel order: the shuffle takes them lane by lane
        // (0, 1, 4, 5 | 2, 3, 6, 7), the permute puts the 64-bit halves back in order.
        let low = |a: __m256i, b: __m256i| {
            let v = _mm256_castps_si256(_mm256_shuffle_ps::<0b10_00_10_00>(_mm256_castsi256_ps(a), _mm256_castsi256_ps(b)));
            _mm256_permute4x64_epi64::<0b11_01_10_00>(v)
        };
        (low(a, b), low(_mm256_srli_epi64::<24>(a), _mm256_srli_epi64::<24>(b)))
    }

    #[inline(always)]
    unsafe fn special_any(special: __m256i) -> bool {
        _mm256_testz_si256(special, special) == 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calib::{Distortion, StereoCalib};
    use crate::stereo::Rectification;

    fn table(w: u32, h: u32) -> RemapTable {
        let k = Matrix3::new(0.9 * w as f64, 0.0, w as f64 / 2.0, 0.0, 0.9 * w as f64, h as f64 / 2.0, 0.0, 0.0, 1.0);
        let cam = Camera { k, distortion: Distortion::new(&[-0.2, 0.05, 0.001, -0.001, 0.0]).unwrap() };
        let calib = StereoCalib { left: cam.clone(), right: cam, r: Matrix3::identity(), t_mm: Vector3::new(-60.0, 0.0, 0.0), image_size: None };
        // alpha 1 keeps every source pixel: the table has outside and border pixels.
        let rect = Rectification::compute(&calib, (w, h), 1.0).unwrap();
        rect.maps(&calib).0
    }

    #[test]
    fn fixed_point_remap_is_within_one_level_of_the_exact_one() {
        let map = table(96, 64);
        let src: Vec<u8> = (0..96 * 64 * 3).map(|i| ((i * 7919) % 251) as u8).collect();
        let fast = map.remap::<3>(&src, 96, 64);
        let exact = map.remap_exact::<3>(&src, 96, 64);
        let worst = fast.iter().zip(&exact).map(|(a, b)| (*a as i32 - *b as i32).abs()).max().unwrap();
        assert!(worst <= 1, "largest difference {worst}");
        assert!(fast.iter().zip(&exact).filter(|(a, b)| a != b).count() < fast.len() / 4);
        assert!(!map.border.is_empty() && map.idx.contains(&OUTSIDE), "the test table has border and outside pixels");
    }

    /// The portable fixed-point loop, pixel by pixel, as the reference.
    fn portable<const C: usize>(map: &RemapTable, src: &[u8]) -> (Vec<u8>, Vec<u8>) {
        let n = map.idx.len();
        let (mut out, mut gray) = (vec![0; n * C], vec![0; n]);
        map.fixed::<C>(src, Some(&mut out), (C == 3).then_some(&mut gray[..]), false);
        (out, gray)
    }

    /// The AVX2 path's bytes against the portable loop's on random images through `map`:
    /// colour with grey, grey alone, one channel.
    fn assert_avx2_is_portable(map: &RemapTable, rng: &mut impl FnMut() -> u64) {
        let (w, h) = (map.width, map.height);
        let n = (w * h) as usize;
        let rgb: Vec<u8> = (0..n * 3).map(|_| rng() as u8).collect();
        let (want, want_gray) = portable::<3>(map, &rgb);
        let (mut out, mut gray) = (vec![0; n * 3], vec![0; n]);
        map.fixed::<3>(&rgb, Some(&mut out), Some(&mut gray), true);
        assert_eq!(out, want, "{w}×{h} RGB");
        assert_eq!(gray, want_gray, "{w}×{h} grey");
        let mut only_gray = vec![0; n];
        map.fixed::<3>(&rgb, None, Some(&mut only_gray), true);
        assert_eq!(only_gray, want_gray, "{w}×{h} grey alone");
        let one: Vec<u8> = (0..n).map(|_| rng() as u8).collect();
        let mut out1 = vec![0; n];
        map.fixed::<1>(&one, Some(&mut out1), None, true);
        assert_eq!(out1, portable::<1>(map, &one).0, "{w}×{h} one channel");
    }

    #[test]
    fn the_avx2_remap_gives_the_portable_bytes() {
        if !simd() {
            return;
        }
        let mut rng = crate::testing::xorshift(7);
        // Sizes whose output ends in a partial group of eight (the tail) and a whole one.
        for (w, h) in [(96, 64), (61, 37), (640, 480)] {
            assert_avx2_is_portable(&table(w, h), &mut rng);
        }
    }

    /// A table of random taps over every top-left position the fixed path takes (the last
    /// one included, whose reads end at the source's last byte), with outside and border
    /// marks among them.
    fn random_table(w: u32, h: u32, rng: &mut impl FnMut() -> u64) -> RemapTable {
        let n = (w * h) as usize;
        let (mut idx, mut weights, mut border) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..n {
            let k = match rng() % 16 {
                0 => OUTSIDE,
                1 => {
                    border.push(i as u32);
                    BORDER
                }
                2 => (h - 2) * w + w - 2,
                _ => (rng() % (h as u64 - 1)) as u32 * w + (rng() % (w as u64 - 1)) as u32,
            };
            idx.push(k);
            weights.push((rng() % 257) as u32 | ((rng() % 257) as u32) << 16);
        }
        RemapTable { width: w, height: h, map: vec![[0.0; 2]; n], idx, weights, border }
    }

    #[test]
    fn the_avx2_remap_gives_the_portable_bytes_for_any_taps() {
        if !simd() {
            return;
        }
        let mut rng = crate::testing::xorshift(11);
        for (w, h) in [(16, 9), (33, 20), (640, 480)] {
            let map = random_table(w, h, &mut rng);
            assert_avx2_is_portable(&map, &mut rng);
        }
    }

    #[test]
    fn the_fused_grey_is_the_grey_of_the_rectified_colour() {
        let map = table(61, 37);
        let src: Vec<u8> = (0..61 * 37 * 3).map(|i| ((i * 7919) % 251) as u8).collect();
        let rgb = map.remap::<3>(&src, 61, 37);
        let gray: Vec<u8> = rgb.chunks_exact(3).map(|p| luma(p[0], p[1], p[2])).collect();
        assert_eq!(map.remap_rgb_gray(&src, 61, 37), (rgb.clone(), gray.clone()));
        assert_eq!(map.remap_gray(&src, 61, 37), gray);
        // A source of another size takes the exact path, and the grey follows it.
        let big: Vec<u8> = (0..62 * 37 * 3).map(|i| ((i * 31) % 253) as u8).collect();
        let (rgb, gray) = map.remap_rgb_gray(&big, 62, 37);
        assert_eq!(rgb, map.remap_exact::<3>(&big, 62, 37));
        assert_eq!(gray, rgb.chunks_exact(3).map(|p| luma(p[0], p[1], p[2])).collect::<Vec<_>>());
    }
}
