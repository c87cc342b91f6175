//! Ground-truth disparity of a mesh seen by a rectified rig: what `gt/disparity/` holds for
//! an ideal rig, for any rig whose recording carries `gt/mesh.ply` and `gt/poses.jsonl`.
//!
//! The mesh is z-buffered into the rectified left image (`R1`, `P1`), each pixel centre
//! (integer coordinates, OpenCV's convention) taking the nearest triangle that covers it,
//! and the disparity there is `x_left − x_right` of that surface point (`P1`, `P2`): signed
//! as the matcher's maps are. Both `1/Z` and the disparity are affine in the rectified image
//! over a planar triangle, so interpolating them across it is exact.

use nalgebra::{Isometry3, Matrix3x4, Matrix4, Vector4};

use super::disparity::DisparityMap;
use super::rectify::Rectification;

/// Surface points nearer than this to the rectified camera plane (mm) are not rendered.
const NEAREST_MM: f64 = 1.0;

/// The disparity map of the triangles `triangles` over `vertices` (object frame, mm), placed
/// in the LEFT raw camera frame by `cam_from_obj`, as `rect` rectifies it: NaN where no
/// triangle covers a pixel centre. Triangles with a corner behind [`NEAREST_MM`] are left
/// out (an object on a turntable lies well in front of the cameras).
pub fn render_disparity(vertices: &[[f32; 3]], triangles: &[[u32; 3]], cam_from_obj: &Isometry3<f64>, rect: &Rectification) -> DisparityMap {
    let (w, h) = (rect.size.0 as usize, rect.size.1 as usize);
    let mut rect_from_cam = Matrix4::identity();
    rect_from_cam.fixed_view_mut::<3, 3>(0, 0).copy_from(&rect.r1);
    let rect_from_obj = rect_from_cam * cam_from_obj.to_homogeneous();
    let (p1, p2): (Matrix3x4<f64>, Matrix3x4<f64>) = (rect.p1 * rect_from_obj, rect.p2 * rect_from_obj);
    // Per vertex: rectified left pixel, 1/depth and disparity (NaN depth: not rendered).
    let screen: Vec<[f64; 4]> = vertices
        .iter()
        .map(|v| {
            let x = Vector4::new(v[0] as f64, v[1] as f64, v[2] as f64, 1.0);
            let (l, r) = (p1 * x, p2 * x);
            if !(l.z >= NEAREST_MM && r.z >= NEAREST_MM) {
                return [f64::NAN; 4];
            }
            let (ul, vl, ur) = (l.x / l.z, l.y / l.z, r.x / r.z);
            [ul, vl, 1.0 / l.z, ul - ur]
        })
        .collect();
    let mut inv_depth = vec![0.0f64; w * h];
    let mut disparity = vec![f32::NAN; w * h];
    for tri in triangles {
        let Some([a, b, c]) = corners(&screen, tri) else { continue };
        let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
        if !(area.abs() > 1e-12) {
            continue;
        }
        // Pixel centres inside the triangle's box, clipped to the image.
        let lo = |p: f64| p.ceil().max(0.0);
        let x0 = lo(a[0].min(b[0]).min(c[0]));
        let y0 = lo(a[1].min(b[1]).min(c[1]));
        let x1 = a[0].max(b[0]).max(c[0]).floor().min(w as f64 - 1.0);
        let y1 = a[1].max(b[1]).max(c[1]).floor().min(h as f64 - 1.0);
        if !(x0 <= x1 && y0 <= y1) {
            continue;
        }
        for py in y0 as usize..=y1 as usize {
            let fy = py as f64;
            for px in x0 as usize..=x1 as usize {
                let fx = px as f64;
                let wa = ((c[0] - b[0]) * (fy - b[1]) - (c[1] - b[1]) * (fx - b[0])) / area;
                let wb = ((a[0] - c[0]) * (fy - c[1]) - (a[1] - c[1]) * (fx - c[0])) / area;
                let wc = 1.0 - wa - wb;
                if wa < 0.0 || wb < 0.0 || wc < 0.0 {
                    continue;
                }
                let iz = wa * a[2] + wb * b[2] + wc * c[2];
                let i = py * w + px;
                if iz > inv_depth[i] {
                    inv_depth[i] = iz;
                    disparity[i] = (wa * a[3] + wb * b[3] + wc * c[3]) as f32;
                }
            }
        }
    }
    DisparityMap::from_values(w, h, disparity)
}

/// A triangle's three rendered corners, `None` if one is out of range or not rendered.
fn corners(screen: &[[f64; 4]], tri: &[u32; 3]) -> Option<[[f64; 4]; 3]> {
    let get = |i: u32| screen.get(i as usize).copied().filter(|p| p[2].is_finite());
    Some([get(tri[0])?, get(tri[1])?, get(tri[2])?])
}

#[cfg(test)]
mod tests {
    use nalgebra::{Matrix3, Translation3, UnitQuaternion, Vector3};

    use super::*;
    use crate::calib::{Camera, Distortion, StereoCalib};

    /// A rig whose right camera sits `t.x` from the left one, rotated by `yaw` degrees about
    /// the vertical: rectification turns both cameras.
    fn rect(t: Vector3<f64>, yaw_deg: f64) -> Rectification {
        let k = Matrix3::new(600.0, 0.0, 320.0, 0.0, 600.0, 240.0, 0.0, 0.0, 1.0);
        let calib = StereoCalib {
            left: Camera { k, distortion: Distortion::none() },
            right: Camera { k, distortion: Distortion::none() },
            r: *UnitQuaternion::from_axis_angle(&Vector3::y_axis(), yaw_deg.to_radians()).to_rotation_matrix().matrix(),
            t_mm: t,
            image_size: None,
        };
        Rectification::compute(&calib, (640, 480), 0.0).unwrap()
    }

    /// A square of side `side` facing the camera, centred at `(x, y, z)`.
    fn square(x: f32, y: f32, z: f32, side: f32, first: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
        let h = side / 2.0;
        let v = vec![[x - h, y - h, z], [x + h, y - h, z], [x + h, y + h, z], [x - h, y + h, z]];
        (v, vec![[first, first + 1, first + 2], [first, first + 2, first + 3]])
    }

    #[test]
    fn a_plane_has_f_b_over_z_and_the_nearer_surface_wins() {
        let r = rect(Vector3::new(-60.0, 0.0, 0.0), 0.0);
        // Half a pixel off the centres, so that no edge passes through one.
        let half_px = 0.5 * 500.0 / 600.0;
        let (mut v, mut t) = square(half_px, half_px, 500.0, 400.0, 0);
        // A smaller square in front of the middle, and one behind the camera.
        let (v2, t2) = square(0.0, 0.0, 400.0, 80.0, 4);
        let (v3, t3) = square(0.0, 0.0, -300.0, 400.0, 8);
        v.extend(v2.into_iter().chain(v3));
        t.extend(t2.into_iter().chain(t3));
        let d = render_disparity(&v, &t, &Isometry3::identity(), &r);
        assert_eq!(r.disparity_sign, 1);
        // 600 · 60 / 500 and / 400.
        assert!((d.get(100, 240).unwrap() - 72.0).abs() < 1e-3, "{:?}", d.get(100, 240));
        assert!((d.get(320, 240).unwrap() - 90.0).abs() < 1e-3, "{:?}", d.get(320, 240));
        // The far square spans 320.5 ± 240 px (columns 81 … 560, rows 1 … 479 of the image),
        // the near one 320 ± 60.
        assert_eq!((d.get(80, 240), d.get(561, 240), d.get(300, 0)), (None, None, None));
        assert!(d.get(81, 240).is_some() && d.get(560, 240).is_some() && d.get(300, 1).is_some());
        assert!((d.get(379, 240).unwrap() - 90.0).abs() < 1e-3 && (d.get(381, 240).unwrap() - 72.0).abs() < 1e-3);
        assert_eq!(d.valid_count(), 480 * 479);
    }

    #[test]
    fn the_disparity_is_the_rectified_pair_s_for_a_turned_rig_and_its_sign() {
        // A slanted plane seen by a rig turned 3° between its cameras; every rendered value
        // is the rectified left and right projections' difference of the surface point
        // under that pixel.
        for (t, sign) in [(Vector3::new(-60.0, 2.0, 1.0), 1.0f32), (Vector3::new(60.0, -2.0, 1.0), -1.0)] {
            let r = rect(t, 3.0);
            assert_eq!(r.disparity_sign as f32, sign);
            let (v, tri) = square(0.0, 0.0, 0.0, 300.0, 0);
            let pose = Isometry3::from_parts(Translation3::new(10.0, -5.0, 520.0), UnitQuaternion::from_euler_angles(0.2, 0.5, 0.1));
            let d = render_disparity(&v, &tri, &pose, &r);
            assert!(d.valid_count() > 20_000);
            // The plane in the rectified left frame: n · X = c.
            let m = r.r1 * pose.rotation.to_rotation_matrix().matrix();
            let n = m * Vector3::z();
            let c = n.dot(&(r.r1 * pose.translation.vector));
            let (f, cx, cy) = (r.p1[(0, 0)], r.p1[(0, 2)], r.p1[(1, 2)]);
            let mut checked = 0;
            for y in (0..480).step_by(7) {
                for x in (0..640).step_by(7) {
                    let Some(got) = d.get(x, y) else { continue };
                    let ray = Vector3::new((x as f64 - cx) / f, (y as f64 - cy) / r.p1[(1, 1)], 1.0);
                    let p = ray * (c / n.dot(&ray));
                    let right = r.p2 * p.push(1.0);
                    let want = x as f64 - right.x / right.z;
                    assert!((got as f64 - want).abs() < 1e-3, "({x}, {y}): {got} against {want}");
                    assert_eq!(got.signum(), sign);
                    checked += 1;
                }
            }
            assert!(checked > 400);
        }
    }
}
