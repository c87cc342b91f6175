//! Disparity → 3D points with `Q`, expressed in the LEFT raw (unrectified) camera frame.

use super::disparity::{searched_span, DisparityMap};
use super::rectify::Rectification;
use crate::cloud::PointCloud;

/// Triangulates every pixel with a disparity. `colors` is the rectified left image as
/// interleaved RGB (same size as the map). Points are in millimetres in the left raw camera
/// frame (`left_from_rectleft = R1ᵀ`); pixels whose point falls behind the camera are skipped.
/// With `rim` — each pixel's distance inside the object's silhouette
/// ([`crate::segment::rim_distance`]) and a width `cut` — every point carries its pixel's
/// distance ([`PointCloud::rim_px`]), and where `cut` is over 0 there is also the cloud of the
/// pixels more than `cut` inside (the view less the silhouette's rim, as
/// [`crate::segment::inside_rim`] leaves it). Both in pixel order.
pub fn triangulate(disp: &DisparityMap, rect: &Rectification, colors: &[u8], rim: Option<(&[u8], usize)>) -> (PointCloud, Option<PointCloud>) {
    let (mut cloud, mut kept) = (PointCloud::default(), rim.filter(|r| r.1 > 0).map(|_| PointCloud::default()));
    if rim.is_some() {
        cloud.rim_px = Some(Vec::new());
        if let Some(k) = kept.as_mut() {
            k.rim_px = Some(Vec::new());
        }
    }
    let left_from_rect: [[f64; 3]; 3] = rect.r1.transpose().into();
    let q: [[f64; 4]; 4] = rect.q.into();
    // One pass to count, so that the clouds grow once.
    let n = disp.values().iter().filter(|d| d.is_finite()).count();
    cloud.points.reserve(n);
    cloud.colors.reserve(n);
    let w = disp.width;
    for y in 0..disp.height {
        let row = &disp.values()[y * w..(y + 1) * w];
        // Only from the row's first match to its last (most of a scan's rows are background).
        let Some((first, last)) = searched_span(row, row) else { continue };
        for x in (first..=last).filter(|&x| row[x].is_finite()) {
            let Some(p) = point_of(&q, &left_from_rect, x as f64, y as f64, row[x] as f64) else { continue };
            let i = y * w + x;
            let (point, color) = ([p[0] as f32, p[1] as f32, p[2] as f32], [colors[3 * i], colors[3 * i + 1], colors[3 * i + 2]]);
            cloud.points.push(point);
            cloud.colors.push(color);
            if let Some((dist, cut)) = rim {
                cloud.rim_px.as_mut().unwrap().push(dist[i]);
                if let Some(kept) = kept.as_mut().filter(|_| dist[i] as usize > cut) {
                    kept.points.push(point);
                    kept.colors.push(color);
                    kept.rim_px.as_mut().unwrap().push(dist[i]);
                }
            }
        }
    }
    (cloud, kept)
}

/// The point of pixel (x, y) at disparity d: `Q · (x, y, d, 1)`, divided by its w, turned
/// into the left raw frame by `left_from_rect`; `None` where w is 0 or the point is not in
/// front of the camera. `q` and `left_from_rect` by columns (nalgebra's order), and the
/// sums in nalgebra's order (column by column), so the same bits as its products.
#[inline(always)]
fn point_of(q: &[[f64; 4]; 4], left_from_rect: &[[f64; 3]; 3], x: f64, y: f64, d: f64) -> Option<[f64; 3]> {
    let h: [f64; 4] = std::array::from_fn(|i| q[0][i] * x + q[1][i] * y + q[2][i] * d + q[3][i]);
    if h[3] == 0.0 {
        return None;
    }
    let r = [h[0] / h[3], h[1] / h[3], h[2] / h[3]];
    if !(r[2] > 0.0) {
        return None;
    }
    let m = left_from_rect;
    Some(std::array::from_fn(|i| m[0][i] * r[0] + m[1][i] * r[1] + m[2][i] * r[2]))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Matrix3, Matrix4, Vector3, Vector4};

    use super::*;

    #[test]
    fn the_points_are_nalgebras_products_bit_for_bit() {
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        for _ in 0..200 {
            // Any Q and rotation-like matrix, every entry non-zero (so that any other order
            // of the sums would round differently somewhere).
            let q = Matrix4::from_fn(|i, j| if i == j { 1.0 } else { 0.0 } + 0.3 * rnd());
            let r = Matrix3::from_fn(|i, j| if i == j { 1.0 } else { 0.0 } + 0.1 * rnd());
            let (x, y, d) = (640.0 * (rnd() + 0.5), 480.0 * (rnd() + 0.5), (128.0 * (rnd() + 0.5)) as f32 as f64);
            let h = q * Vector4::new(x, y, d, 1.0);
            let expected = (h.w != 0.0 && h.z / h.w > 0.0).then(|| r * Vector3::new(h.x / h.w, h.y / h.w, h.z / h.w));
            let got = point_of(&q.into(), &r.into(), x, y, d);
            match (expected, got) {
                (Some(e), Some(g)) => assert!((0..3).all(|i| e[i].to_bits() == g[i].to_bits()), "{e:?} against {g:?}"),
                (None, None) => {}
                (e, g) => panic!("{e:?} against {g:?}"),
            }
        }
    }
}
