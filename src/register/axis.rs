//! The turntable's axis, estimated from registered poses alone (no calibration target).
//!
//! Every `first_from_view` of a turntable scan is a rotation about the same line. Its
//! direction `a` is fixed by every rotation, so it minimises Σ‖(R_k − I) a‖² (the smallest
//! eigenvector of Σ (R_k − I)ᵀ(R_k − I)); a point `c` on it satisfies (I − R_k) c = t_k for
//! every k, solved in least squares with the free component along `a` pinned at a reference
//! point (the object's centre), so `c` is the axis point nearest the object. Views with larger
//! rotations weigh more, as they should: small rotations say little about the axis.
//!
//! "Up" (the spec's sign): the table turns counterclockwise seen from above as `table_deg`
//! grows, so `first_from_view` turns by −(θ_view − θ_first) about up. With no table angles,
//! up is taken as the direction pointing to −y of the camera (image up).

use nalgebra::{Isometry3, Matrix3, SymmetricEigen, Vector3};

use super::icp::Degeneracy;

/// An estimated axis and how well the poses agree with it.
#[derive(Debug, Clone, PartialEq)]
pub struct AxisEstimate {
    pub point: Vector3<f64>,
    /// Unit, pointing up.
    pub dir: Vector3<f64>,
    /// RMS angle between the poses' own rotation axes and `dir`, degrees (views turned > 2°).
    pub rms_axis_deg: f64,
    /// RMS of ‖(I − R_k) c − t_k‖: how far the poses are from pure rotations about the line.
    pub rms_offset: f64,
    /// Views used.
    pub views: usize,
    /// Largest rotation among them, degrees.
    pub span_deg: f64,
}

/// Estimates the axis from `(first_from_view, table_deg − first table_deg)` pairs. Needs a
/// rotation of at least `min_span_deg` among them; `reference` pins the point along the axis.
pub fn estimate_axis(poses: &[(Isometry3<f64>, Option<f64>)], reference: &Vector3<f64>, min_span_deg: f64) -> Option<AxisEstimate> {
    let span_deg = poses.iter().map(|(p, _)| p.rotation.angle().to_degrees()).fold(0.0, f64::max);
    if poses.len() < 2 || span_deg < min_span_deg {
        return None;
    }
    let mut m = Matrix3::zeros();
    for (p, _) in poses {
        let d = p.rotation.to_rotation_matrix().into_inner() - Matrix3::identity();
        m += d.transpose() * d;
    }
    let eig = SymmetricEigen::new(m);
    let k = (0..3).min_by(|&i, &j| eig.eigenvalues[i].total_cmp(&eig.eigenvalues[j]))?;
    let mut dir: Vector3<f64> = eig.eigenvectors.column(k).into_owned().normalize();

    // Sign: from the table angles when there are any, else image up.
    let mut agreement = 0.0;
    let mut have_table = false;
    for (p, dt) in poses {
        if let Some(dt) = dt {
            // Both as angles in (−180°, 180°]: past half a turn a rotation reads as the
            // opposite turn about the opposite axis.
            let signed = p.rotation.scaled_axis().dot(&dir);
            let wrapped = (dt + 180.0).rem_euclid(360.0) - 180.0;
            agreement += signed * wrapped;
            have_table = true;
        }
    }
    if (have_table && agreement > 0.0) || (!have_table && dir.y > 0.0) {
        dir = -dir;
    }

    // The point: Σ AᵀA c = Σ Aᵀ t with A = I − R, plus w·a aᵀ (c − reference) = 0.
    let mut lhs = Matrix3::zeros();
    let mut rhs = Vector3::zeros();
    for (p, _) in poses {
        let a = Matrix3::identity() - p.rotation.to_rotation_matrix().into_inner();
        lhs += a.transpose() * a;
        rhs += a.transpose() * p.translation.vector;
    }
    let w = lhs.norm().max(1e-12);
    lhs += dir * dir.transpose() * w;
    rhs += dir * dir.dot(reference) * w;
    let point = lhs.lu().solve(&rhs)?;

    let (mut axis_sq, mut axis_n, mut off_sq) = (0.0, 0usize, 0.0);
    for (p, _) in poses {
        let a = Matrix3::identity() - p.rotation.to_rotation_matrix().into_inner();
        off_sq += (a * point - p.translation.vector).norm_squared();
        if p.rotation.angle().to_degrees() > 2.0 {
            let own = p.rotation.axis().map(|u| u.into_inner()).unwrap_or(dir);
            axis_sq += own.dot(&dir).abs().min(1.0).acos().to_degrees().powi(2);
            axis_n += 1;
        }
    }
    Some(AxisEstimate {
        point,
        dir,
        rms_axis_deg: if axis_n > 0 { (axis_sq / axis_n as f64).sqrt() } else { 0.0 },
        rms_offset: (off_sq / poses.len() as f64).sqrt(),
        views: poses.len(),
        span_deg,
    })
}

/// Why ICP's free directions are explained by the set-up, so that keeping the guess along
/// them is right — or None, when one is not (a warning then): a rotation about the table's
/// axis when the table's step seeded it (`seeded_by_table`), or a rotation about a line
/// across the table's axis (an object of revolution lying on its side, such as a ring facing
/// the cameras), which the table's motion never turns about. `table_up` is the table's axis
/// when known; before that the image's vertical stands in for it (as for the symmetry-axis
/// seed of [`super::ring::Registrar`]), with a wider margin. A free translation is never
/// expected.
pub fn explained_degeneracy(degenerate: &[Degeneracy], table_up: Option<Vector3<f64>>, seeded_by_table: bool) -> Option<&'static str> {
    let mut why = None;
    for d in degenerate {
        let (_, dir) = d.axis?;
        let dir = Vector3::from(dir);
        let cos = table_up.map_or(dir.y.abs(), |u| dir.dot(&u).abs());
        if cos < if table_up.is_some() { 0.26 } else { 0.5 } {
            why = why.or(Some("an object of revolution about a line across the table's axis; the table never turns about that line"));
        } else if cos > std::f64::consts::FRAC_1_SQRT_2 && seeded_by_table {
            why = why.or(Some("the turntable's step supplies the turn about its axis"));
        } else {
            return None;
        }
    }
    why
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::register::rotation_about_axis;

    #[test]
    fn recovers_axis_point_and_up() {
        // Table axis 450 mm in front, tilted towards the camera; up is image-up (−y).
        let up = Vector3::new(0.0, -0.978, -0.208).normalize();
        let c = Vector3::new(5.0, 40.0, 450.0);
        // A whole turn: past 180° the rotations read as turns about −up.
        let poses: Vec<(Isometry3<f64>, Option<f64>)> = (1..120).map(|k| (rotation_about_axis(&c, &up, -3.0 * k as f64), Some(3.0 * k as f64))).collect();
        let est = estimate_axis(&poses, &Vector3::new(0.0, 0.0, 430.0), 5.0).unwrap();
        assert!((est.dir - up).norm() < 1e-9, "{:?}", est.dir);
        // The estimated point is on the line.
        let off = (est.point - c) - up * up.dot(&(est.point - c));
        assert!(off.norm() < 1e-6, "{off:?}");
        assert!(est.rms_axis_deg < 1e-6 && est.rms_offset < 1e-6);
        // Table angles running the other way flip up.
        let flipped: Vec<_> = poses.iter().map(|(p, d)| (*p, d.map(|d| -d))).collect();
        assert!((estimate_axis(&flipped, &Vector3::zeros(), 5.0).unwrap().dir + up).norm() < 1e-9);
        // Too little rotation: no estimate.
        assert!(estimate_axis(&poses[..1], &Vector3::zeros(), 5.0).is_none());
    }

    #[test]
    fn only_degeneracies_the_set_up_explains_are_expected() {
        let free = |dir: [f64; 3]| Degeneracy { rotation: dir, translation: [0.0; 3], ratio: 0.01, axis: Some(([0.0, 0.0, 400.0], dir)) };
        // A ring facing the cameras: free about the line of sight, across the vertical.
        assert!(explained_degeneracy(&[free([0.0, 0.19, -0.98])], None, false).is_some());
        // A vase about its own (the table's) axis: expected only when the table's step seeded it.
        assert!(explained_degeneracy(&[free([0.0, -1.0, 0.0])], None, false).is_none());
        assert!(explained_degeneracy(&[free([0.0, -1.0, 0.0])], None, true).is_some());
        // A line neither across nor along the axis, or a free translation: a warning.
        assert!(explained_degeneracy(&[free([0.0, 0.6, 0.8])], None, true).is_none());
        let slide = Degeneracy { rotation: [0.0; 3], translation: [1.0, 0.0, 0.0], ratio: 0.01, axis: None };
        assert!(explained_degeneracy(&[slide], None, true).is_none());
        // With the axis known, "across" is measured against it.
        let up = Vector3::new(0.0, -0.98, -0.19);
        assert!(explained_degeneracy(&[free([0.0, 0.19, -0.98])], Some(up), false).is_some());
        assert!(explained_degeneracy(&[free([0.0, 0.5, -0.86])], Some(up), false).is_none());
    }
}
