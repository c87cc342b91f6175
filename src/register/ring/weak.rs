//! Motions the surfaces fix only weakly: when a step holds them at its seed and when it
//! solves them, and the line a solved step turned about (docs/registration.md, Known limits,
//! "The first steps held 'no turn'" and "without the table's angles").

use nalgebra::{Isometry3, Vector3};

use crate::register::icp::IcpParams;

/// ICP's settings for a step seeded without the table's angles (`blind`: a view of it has
/// none — a turntable that reports nothing). Its seed then knows nothing of the turn: the
/// identity for a pair, the chain for a block. Holding a weakly constrained rotation at that
/// seed — an egg's about the table's axis, which the probe finds
/// (`IcpParams::degeneracy_probe_ratio`) — keeps "no turn" at every step
/// (docs/registration.md, Known limits, "without the table's angles"), so only truly free
/// motions (below `degeneracy_ratio`) keep the seed there.
pub(super) fn without_angles(params: &IcpParams, blind: bool) -> std::borrow::Cow<'_, IcpParams> {
    if blind {
        std::borrow::Cow::Owned(IcpParams { degeneracy_probe_ratio: 0.0, ..params.clone() })
    } else {
        std::borrow::Cow::Borrowed(params)
    }
}

/// Steps whose free rotation is looked at again with exact pairs (see
/// [`super::Registrar::add_view`]).
pub(super) const MAX_SYMMETRY_TESTS: usize = 2;

/// A step seeded with the identity that held a weak motion there takes the solution that
/// solves it instead when that puts the views onto each other this much closer (its RMSE at
/// most this share of the held one's), with at least [`WEAK_FIT_MIN_FITNESS`] of the held
/// one's fitness (see [`super::Registrar::add_view`]).
pub(super) const WEAK_FIT_GAIN: f64 = 0.97;
pub(super) const WEAK_FIT_MIN_FITNESS: f64 = 0.98;

/// After a step solved the turn, the symmetry test's line is taken for the table's axis only
/// within this many degrees of the line that step turned about (measured: a vase's 0.1–2.0°;
/// an egg's 2.5–25°, its own axis lying up to 22° off the table's; the independent renderer's
/// object 20–25°).
pub(super) const SOLVED_TURN_LINE_DEG: f64 = 6.0;

/// The line a rigid motion turns about (a point on it, its unit direction); None for a turn
/// too small to have one.
pub(super) fn screw_line(t: &Isometry3<f64>) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let dir = t.rotation.axis()?.into_inner();
    if t.rotation.angle() < 1e-4 {
        return None;
    }
    // R c + t = c along the line (the motion's slide along it aside): (I − R) c = t − (t·u) u.
    let r = t.rotation.to_rotation_matrix().into_inner();
    let v = t.translation.vector;
    let point = (nalgebra::Matrix3::identity() - r).svd(true, true).solve(&(v - dir * dir.dot(&v)), 1e-9).ok()?;
    Some((point - dir * dir.dot(&point), dir))
}
