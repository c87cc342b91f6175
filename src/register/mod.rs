//! Registration of partial views (the paper's section 3): ICP, block registration, isolated
//! point removal, the voxel-merged model, the shared pose store, turntable axis estimation
//! and loop closure.
//!
//! Everything here is pure computation on point sets (and, for the texture tracks of
//! `tracks`, on the views' rectified left images and disparity maps); [`crate::pipeline`] wires it to
//! recordings and results folders, and `spinscan register` to PLY files ([`crate::io::poses`]
//! reads and writes its pose files).
//!
//! Conventions: a pose `b_from_a` is an [`Isometry3`] mapping points of frame `a` into frame
//! `b`; `first_from_view` maps a view's points (its LEFT raw camera frame) into the first
//! view's. Units are the caller's (spinscan's own clouds are millimetres).

pub mod angles;
pub mod axis;
pub mod bundle;
pub mod cells;
pub mod denoise;
pub mod grid;
pub mod icp;
pub mod kdtree;
pub mod loops;
pub mod normals;
pub mod posestore;
pub mod refine;
pub mod ring;
pub mod surface;
pub mod target;
pub mod tracks;
pub mod voxel;

use nalgebra::{Isometry3, Matrix3, Matrix4, Rotation3, Translation3, UnitQuaternion, Vector3};

pub use icp::{icp, IcpMethod, IcpParams, IcpResult, Kernel};
pub use kdtree::KdTree;

/// Why a registration could not run.
#[derive(Debug, thiserror::Error)]
pub enum RegisterError {
    #[error("{what} has no points")]
    Empty { what: String },
    #[error("{what} has a non-finite coordinate at point #{index}")]
    NotFinite { what: String, index: usize },
    #[error("too few {what} ({got}) for {purpose}; at least {need} are needed")]
    TooFew { what: String, got: usize, need: usize, purpose: String },
    #[error("invalid parameter: {0}")]
    Param(String),
    #[error("k-d tree construction failed: {0}")]
    Tree(String),
}

/// A 4×4 row-major matrix as stored in JSON files (`[[…4 rows of 4…]]`).
pub type Rows4 = [[f64; 4]; 4];

/// The rows of a rigid transform.
pub fn to_rows(t: &Isometry3<f64>) -> Rows4 {
    let m = t.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// Why a 4×4 matrix is not a rigid transform.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransformError {
    #[error("a matrix entry is not a finite number")]
    NotFinite,
    #[error("last row is {0:?}, expected [0, 0, 0, 1]")]
    LastRow([f64; 4]),
    #[error("the upper-left 3×3 block is not a rotation (RᵀR differs from I by {err:.2e}, det {det:.4})")]
    NotRotation { err: f64, det: f64 },
}

/// Reads a rigid transform from rows, checking that it is one (orthonormal rotation with
/// determinant +1 to `tol`, last row 0 0 0 1). The rotation is re-orthonormalised.
pub fn from_rows(rows: &Rows4, tol: f64) -> Result<Isometry3<f64>, TransformError> {
    if rows.iter().flatten().any(|v| !v.is_finite()) {
        return Err(TransformError::NotFinite);
    }
    let m = Matrix4::from_fn(|r, c| rows[r][c]);
    let last = [m[(3, 0)], m[(3, 1)], m[(3, 2)], m[(3, 3)]];
    if last[0].abs() > tol || last[1].abs() > tol || last[2].abs() > tol || (last[3] - 1.0).abs() > tol {
        return Err(TransformError::LastRow(last));
    }
    let r: Matrix3<f64> = m.fixed_view::<3, 3>(0, 0).into_owned();
    let err = (r.transpose() * r - Matrix3::identity()).abs().max();
    if err > tol || r.determinant() < 0.0 {
        return Err(TransformError::NotRotation { err, det: r.determinant() });
    }
    // Shepperd's conversion of the (checked) matrix, then normalised. Not
    // `Rotation3::from_matrix`: its iteration starts from the identity and stalls on a
    // half-turn (a view at 180° came back nearly unrotated).
    let rot = UnitQuaternion::new_normalize(*UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r)).quaternion());
    Ok(Isometry3::from_parts(Translation3::new(m[(0, 3)], m[(1, 3)], m[(2, 3)]), rot))
}

/// Rotation angle of a transform, degrees.
pub fn angle_deg(t: &Isometry3<f64>) -> f64 {
    t.rotation.angle().to_degrees()
}

/// `exp(s · log(t))`: the transform `s` of the way along the screw from identity to `t`
/// (rotation and translation interpolated separately, which is what loop closure needs).
pub fn scale_transform(t: &Isometry3<f64>, s: f64) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_scaled_axis(t.rotation.scaled_axis() * s);
    Isometry3::from_parts(Translation3::from(t.translation.vector * s), rot)
}

/// Rotation by `deg` degrees about the line through `point` with direction `dir` (unit).
pub fn rotation_about_axis(point: &Vector3<f64>, dir: &Vector3<f64>, deg: f64) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_scaled_axis(dir.normalize() * deg.to_radians());
    // p' = R (p − c) + c
    let t = point - rot * point;
    Isometry3::from_parts(Translation3::from(t), rot)
}

/// The rigid motion `t` that best maps each `a` onto its `b` (`b ≈ t·a`) in the weighted
/// least-squares sense (Kabsch / Umeyama without scale: the SVD of the weighted
/// cross-covariance, a reflection turned into the nearest rotation). None when the weights sum
/// to zero or the SVD fails.
pub fn rigid_fit(pairs: &[(Vector3<f64>, Vector3<f64>, f64)]) -> Option<Isometry3<f64>> {
    let wsum: f64 = pairs.iter().map(|m| m.2).sum();
    if !(wsum > 0.0) {
        return None;
    }
    let ca = pairs.iter().map(|m| m.0 * m.2).sum::<Vector3<f64>>() / wsum;
    let cb = pairs.iter().map(|m| m.1 * m.2).sum::<Vector3<f64>>() / wsum;
    let mut cov = Matrix3::zeros();
    for (a, b, w) in pairs {
        cov += (b - cb) * (a - ca).transpose() * *w;
    }
    let svd = cov.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let rot = UnitQuaternion::from_matrix(&(u * d * vt));
    Some(Isometry3::from_parts(Translation3::from(cb - rot * ca), rot))
}

/// Checks that a point set is non-empty and finite.
pub fn check_points(points: &[[f32; 3]], what: &str) -> Result<(), RegisterError> {
    if points.is_empty() {
        return Err(RegisterError::Empty { what: what.to_string() });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(RegisterError::NotFinite { what: what.to_string(), index });
    }
    Ok(())
}

/// Squared distance between two points.
#[inline]
pub fn dist2(p: &[f32; 3], q: &[f32; 3]) -> f32 {
    (q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2) + (q[2] - p[2]).powi(2)
}

/// Applies `t` to a point.
#[inline]
pub fn apply(t: &Isometry3<f64>, p: &[f32; 3]) -> [f32; 3] {
    let q = t * nalgebra::Point3::new(p[0] as f64, p[1] as f64, p[2] as f64);
    [q.x as f32, q.y as f32, q.z as f32]
}

/// Every `n`-th point, so that at most `max` remain (deterministic, keeps the scan order's
/// spatial spread). Returns indices.
pub fn subsample_indices(len: usize, max: usize) -> Vec<usize> {
    if max == 0 || len <= max {
        return (0..len).collect();
    }
    let step = len as f64 / max as f64;
    (0..max).map(|i| ((i as f64 + 0.5) * step) as usize).filter(|&i| i < len).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_and_reject_non_rigid() {
        let t = rotation_about_axis(&Vector3::new(1.0, 2.0, 3.0), &Vector3::new(0.0, 1.0, 0.0), 30.0);
        let back = from_rows(&to_rows(&t), 1e-9).unwrap();
        assert!((back.to_homogeneous() - t.to_homogeneous()).abs().max() < 1e-12);
        let mut rows = to_rows(&t);
        rows[0][0] *= 2.0;
        assert!(from_rows(&rows, 1e-6).unwrap_err().to_string().contains("not a rotation"));
        let mut rows = to_rows(&t);
        rows[3][3] = 2.0;
        assert!(from_rows(&rows, 1e-6).unwrap_err().to_string().contains("last row"));
    }

    /// Guards the reading of half-turns: a pose at 180° used to come back nearly unrotated.
    #[test]
    fn a_half_turn_reads_back_as_a_half_turn() {
        for axis in [Vector3::new(0.0, 1.0, 0.0), Vector3::new(0.0, -0.978, -0.208).normalize(), Vector3::new(1.0, 0.0, 0.0)] {
            for deg in [180.0, 179.9, 90.0, -135.0] {
                let t = rotation_about_axis(&Vector3::new(3.0, -4.0, 450.0), &axis, deg);
                let back = from_rows(&to_rows(&t), 1e-6).unwrap();
                let err = back.inverse() * t;
                assert!(err.rotation.angle() < 1e-9 && err.translation.vector.norm() < 1e-9, "{deg}° about {axis:?}: {:.4}°", err.rotation.angle().to_degrees());
            }
        }
        // A simulated recording's camera pose at table angle 180° (gt/poses.jsonl).
        let rows = [[-1.0, 0.0, 1.2246467991473532e-16, 0.0], [-2.5461838666528314e-17, -0.9781476007338057, -0.20791169081775934, 83.14254606237347], [1.1978853283323184e-16, -0.20791169081775934, 0.9781476007338057, 467.67249371950953], [0.0, 0.0, 0.0, 1.0]];
        let t = from_rows(&rows, 1e-6).unwrap();
        let back = to_rows(&t);
        let diff = (0..3).flat_map(|r| (0..4).map(move |c| (r, c))).map(|(r, c)| (back[r][c] - rows[r][c]).abs()).fold(0.0, f64::max);
        assert!(diff < 1e-9, "{back:?}");
    }

    #[test]
    fn rotation_about_axis_fixes_the_axis() {
        let c = Vector3::new(10.0, -5.0, 400.0);
        let t = rotation_about_axis(&c, &Vector3::new(0.0, -1.0, 0.2), 40.0);
        let p = t * nalgebra::Point3::from(c + Vector3::new(0.0, -1.0, 0.2) * 7.0);
        assert!((p.coords - (c + Vector3::new(0.0, -1.0, 0.2) * 7.0)).norm() < 1e-9);
        assert!((angle_deg(&t) - 40.0).abs() < 1e-9);
        assert!((angle_deg(&scale_transform(&t, 0.25)) - 10.0).abs() < 1e-9);
    }

    /// The motion comes back exactly from clean pairs; a pair of weight zero, however far
    /// off, changes nothing; a planar set (one singular value zero) gives it too; no weight
    /// gives None.
    #[test]
    fn rigid_fit_recovers_the_motion_and_ignores_what_weighs_nothing() {
        let truth = rotation_about_axis(&Vector3::new(5.0, 2.0, 300.0), &Vector3::new(0.1, -1.0, 0.3).normalize(), 33.0);
        let moved = |a: Vector3<f64>| (truth * nalgebra::Point3::from(a)).coords;
        let mut pairs: Vec<_> = (0..40).map(|k| {
            let k = k as f64;
            let a = Vector3::new((k * 1.7).sin() * 30.0, (k * 0.9).cos() * 20.0, 400.0 + (k * 2.3).sin() * 15.0);
            (a, moved(a), 1.0 + (k % 3.0))
        }).collect();
        pairs.push((Vector3::new(0.0, 0.0, 0.0), Vector3::new(500.0, -500.0, 9.0), 0.0));
        let planar: Vec<_> = (0..30).map(|k| {
            let a = Vector3::new((k % 6) as f64 * 10.0, (k / 6) as f64 * 10.0, 350.0);
            (a, moved(a), 1.0)
        }).collect();
        for set in [&pairs, &planar] {
            let err = rigid_fit(set).unwrap().inverse() * truth;
            assert!(err.rotation.angle() < 1e-9 && err.translation.vector.norm() < 1e-7, "{err:?}");
        }
        let weightless: Vec<_> = pairs.iter().map(|&(a, b, _)| (a, b, 0.0)).collect();
        assert!(rigid_fit(&weightless).is_none() && rigid_fit(&[]).is_none());
    }

    #[test]
    fn subsample_spreads_evenly() {
        assert_eq!(subsample_indices(5, 10), vec![0, 1, 2, 3, 4]);
        let s = subsample_indices(1000, 10);
        assert_eq!(s.len(), 10);
        assert_eq!(s[0], 50);
        assert_eq!(s[9], 950);
    }
}
