//! The registrar on a synthetic turn, with both kinds of per-view target.

use std::sync::Arc;

use nalgebra::Vector3;

use super::{Registrar, RegistrationParams};
use crate::cloud::PointCloud;
use crate::register::posestore::PoseStore;
use crate::register::rotation_about_axis;

/// A bumpy, asymmetric patch 100 × 80 mm in front of the camera, about 60 mm in front of
/// the table's axis, seen as the table turns `deg`.
fn view(deg: f64, axis: (Vector3<f64>, Vector3<f64>)) -> PointCloud {
    let turn = rotation_about_axis(&axis.0, &axis.1, deg);
    let mut points = Vec::new();
    for i in 0..200 {
        for j in 0..160 {
            let (x, y) = (i as f64 * 0.5 - 50.0, j as f64 * 0.5 - 40.0);
            let z = 390.0 - 15.0 * (x / 9.0).sin() * (y / 11.0 + 0.3).cos() - 10.0 * (-(x - 12.0).powi(2) / 250.0 - (y + 9.0).powi(2) / 180.0).exp() + 0.15 * x;
            let p = turn * nalgebra::Point3::new(x, y, z);
            points.push([p.x as f32, p.y as f32, p.z as f32]);
        }
    }
    PointCloud { colors: vec![[128; 3]; points.len()], points, normals: None }
}

/// Guards the per-view targets: range grids (the default) and exact cell grids both follow a turn
/// of 3° steps, seeded from the identity and then by the table about the estimated axis.
#[test]
fn both_kinds_of_target_follow_the_turn() {
    // An upright axis 60 mm behind the patch, tilted towards the camera like the lab's.
    let axis = (Vector3::new(0.0, 0.0, 450.0), Vector3::new(0.0, -0.978, -0.208).normalize());
    for projective in [true, false] {
        let mut params = RegistrationParams { projective, block: 3, ..Default::default() };
        params.icp.max_distance = 8.0;
        let mut reg = Registrar::new(params, Arc::new(PoseStore::new()));
        for k in 0..8u64 {
            let deg = 3.0 * k as f64;
            let r = reg.add_view(k, Some(deg), &view(deg, axis)).unwrap();
            assert!(r.split.chain_ms >= 0.0 && r.register_ms >= r.publish_ms, "{:?}", r.split);
        }
        for p in reg.poses() {
            // first_from_view undoes the turn since the first view.
            let truth = rotation_about_axis(&axis.0, &axis.1, -p.table_deg.unwrap());
            let err = p.first_from_view.inverse() * truth;
            assert!(err.rotation.angle().to_degrees() < 0.1, "projective {projective}, view {}: {:.3}°", p.seq, err.rotation.angle().to_degrees());
            assert!(err.translation.vector.norm() < 0.5, "projective {projective}, view {}: {:.3} mm", p.seq, err.translation.vector.norm());
        }
    }
}

/// A registrar (with its texture tracker) can be handed to another thread: the daemon builds
/// one per scan on its registration thread, and a caller may build it elsewhere.
#[test]
fn a_registrar_can_move_to_another_thread() {
    fn send<T: Send>(_: &T) {}
    let reg = Registrar::new(RegistrationParams::default(), std::sync::Arc::new(PoseStore::new()));
    send(&reg);
    assert_eq!(std::thread::spawn(move || reg.poses().len()).join().unwrap(), 0);
}
