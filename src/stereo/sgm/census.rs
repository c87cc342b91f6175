//! The census transform and the per-pair matching cost (Hamming distance of census words).
//!
//! Census compares each pixel of a `CENSUS_W × CENSUS_H` window with the window's centre
//! (one bit: neighbour < centre). It depends only on the order of intensities, so a gain or
//! offset between the two cameras — the lab's cameras are not photometrically matched —
//! does not change the cost, and an edge costs no more than texture. The window is clamped
//! at the image border (replicated pixels).

/// Census window width and height (odd). 9 × 7 − 1 = 62 bits, one `u64` per pixel: chosen by
/// measurement against 5 × 5, 7 × 5, 7 × 7 and the centre-symmetric 9 × 7 census (31 bits)
/// on the Middlebury pairs (docs/matcher.md).
pub(super) const CENSUS_W: usize = 9;
pub(super) const CENSUS_H: usize = 7;

/// The census word of every pixel of `img` (`w × h`, row-major) into `out`, each row padded
/// with `pad = (left, right)` copies of its first and last word.
#[inline(always)]
pub(super) fn transform(img: &[u8], w: usize, h: usize, pad: (usize, usize), out: &mut Vec<u64>) {
    let wo = pad.0 + w + pad.1;
    out.clear();
    out.resize(wo * h, 0);
    let (rx, ry) = (CENSUS_W / 2, CENSUS_H / 2);
    // Source rows padded left and right by rx replicated pixels, so the inner loop has no
    // branch.
    let wp = w + 2 * rx;
    let mut padded = vec![0u8; wp * CENSUS_H];
    let mut planes = vec![0u8; 8 * w];
    for y in 0..h {
        for (j, dst) in padded.chunks_mut(wp).enumerate() {
            let sy = (y + j).saturating_sub(ry).min(h - 1);
            let src = &img[sy * w..][..w];
            dst[rx..rx + w].copy_from_slice(src);
            let (first, last) = (src[0], src[w - 1]);
            dst[..rx].fill(first);
            dst[rx + w..].fill(last);
        }
        let centre = &padded[ry * wp + rx..][..w];
        // Comparison t goes to bit t: built as eight byte planes (32 pixels per AVX2
        // instruction), then interleaved into words.
        planes.fill(0);
        let mut t = 0;
        for (j, src) in padded.chunks(wp).enumerate() {
            for i in 0..CENSUS_W {
                if i == rx && j == ry {
                    continue;
                }
                let nb = &src[i..i + w];
                let plane = &mut planes[t / 8 * w..][..w];
                let bit = t % 8;
                for ((o, &c), &n) in plane.iter_mut().zip(centre).zip(nb) {
                    *o |= ((n < c) as u8) << bit;
                }
                t += 1;
            }
        }
        let row = &mut out[y * wo..][..wo];
        let (p0, rest) = planes.split_at(w);
        let (p1, rest) = rest.split_at(w);
        let (p2, rest) = rest.split_at(w);
        let (p3, rest) = rest.split_at(w);
        let (p4, rest) = rest.split_at(w);
        let (p5, rest) = rest.split_at(w);
        let (p6, p7) = rest.split_at(w);
        for (x, o) in row[pad.0..pad.0 + w].iter_mut().enumerate() {
            *o = u64::from_le_bytes([p0[x], p1[x], p2[x], p3[x], p4[x], p5[x], p6[x], p7[x]]);
        }
        let (first, last) = (row[pad.0], row[pad.0 + w - 1]);
        row[..pad.0].fill(first);
        row[pad.0 + w..].fill(last);
    }
}

/// Costs of a left pixel (census `cl`) for consecutive disparities: `out[k]` against
/// `cr_row[start − k]` (the right pixel moves left as the disparity grows).
#[inline(always)]
pub(super) fn costs(cl: u64, cr_row: &[u64], start: usize, out: &mut [u8]) {
    let src = &cr_row[start + 1 - out.len()..=start];
    for (o, &r) in out.iter_mut().zip(src.iter().rev()) {
        *o = (cl ^ r).count_ones() as u8;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn census_bits_order_intensities_and_ignore_gain() {
        let (w, h) = (12, 9);
        let img: Vec<u8> = (0..w * h).map(|i| ((i * 37) % 127) as u8).collect();
        // A strictly increasing change of intensity (gain and offset) keeps every comparison.
        let brighter: Vec<u8> = img.iter().map(|&v| 2 * v + 1).collect();
        let (mut a, mut b) = (Vec::new(), Vec::new());
        transform(&img, w, h, (0, 0), &mut a);
        transform(&brighter, w, h, (0, 0), &mut b);
        assert_eq!(a, b);
        assert!(a.iter().any(|&v| v != 0));
        // Bit by bit at one interior pixel.
        let (x, y) = (6usize, 4usize);
        let (mut expect, mut t) = (0u64, 0);
        for j in 0..CENSUS_H {
            for i in 0..CENSUS_W {
                if i == CENSUS_W / 2 && j == CENSUS_H / 2 {
                    continue;
                }
                let (sx, sy) = (x + i - CENSUS_W / 2, y + j - CENSUS_H / 2);
                expect |= ((img[sy * w + sx] < img[y * w + x]) as u64) << t;
                t += 1;
            }
        }
        assert_eq!(a[y * w + x], expect);
    }

    #[test]
    fn costs_walk_the_right_row_backwards() {
        let cr: Vec<u64> = (0..10u64).map(|i| (1u64 << i) - 1).collect();
        let mut out = [0u8; 4];
        // Right pixels 5, 4, 3, 2.
        costs(0, &cr, 5, &mut out);
        assert_eq!(out, [5, 4, 3, 2]);
    }

    #[test]
    fn padding_replicates_the_border_words() {
        let (w, h) = (10, 3);
        let img: Vec<u8> = (0..w * h).map(|i| ((i * 53) % 200) as u8).collect();
        let (mut plain, mut padded) = (Vec::new(), Vec::new());
        transform(&img, w, h, (0, 0), &mut plain);
        transform(&img, w, h, (3, 2), &mut padded);
        for y in 0..h {
            let row = &padded[y * (w + 5)..][..w + 5];
            assert_eq!(&row[3..3 + w], &plain[y * w..][..w]);
            assert!(row[..3].iter().all(|&v| v == plain[y * w]));
            assert!(row[3 + w..].iter().all(|&v| v == plain[y * w + w - 1]));
        }
    }
}
