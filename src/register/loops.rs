//! Loops of views: spreading a loop's disagreement over a chain of poses, and registering a
//! ring of scans (`spinscan register --ring`).

use nalgebra::Isometry3;

use super::icp::{icp, IcpParams, IcpResult, Target};
use super::{scale_transform, RegisterError};

/// Spreads a loop's disagreement over a chain. `chain[k]` = `first_from_view(k)` from
/// sequential registration (`chain[0]` = identity); `measured` = `first_from_last` from
/// registering the last view directly to the first. With N = `chain.len()` edges in the ring
/// (N − 1 in the chain and the loop edge), view k is corrected by k/N of
/// `E = measured · chain[last]⁻¹`.
pub fn distribute_loop_error(chain: &[Isometry3<f64>], measured: &Isometry3<f64>) -> Vec<Isometry3<f64>> {
    distribute_loop_error_weighted(chain, measured, &vec![1.0; chain.len()])
}

/// [`distribute_loop_error`] with an uncertainty per edge (`variances[k]` for the edge into
/// view k, k = 1…N−1, and `variances[0]` for the closing edge): an edge takes a share of the
/// correction in proportion to its variance, so a poor registration absorbs most of it.
pub fn distribute_loop_error_weighted(chain: &[Isometry3<f64>], measured: &Isometry3<f64>, variances: &[f64]) -> Vec<Isometry3<f64>> {
    let n = chain.len();
    if n < 2 || variances.len() != n {
        return chain.to_vec();
    }
    let var: Vec<f64> = variances.iter().map(|v| if v.is_finite() && *v > 0.0 { *v } else { 1.0 }).collect();
    let total: f64 = var.iter().sum();
    let e = measured * chain[n - 1].inverse();
    let mut acc = 0.0;
    chain
        .iter()
        .enumerate()
        .map(|(k, p)| {
            if k > 0 {
                acc += var[k];
            }
            scale_transform(&e, acc / total) * p
        })
        .collect()
}

/// An ICP result's variance for weighting loop closure: RMSE² over the overlap.
pub fn edge_variance(r: &IcpResult) -> f64 {
    r.rmse * r.rmse / r.fitness.max(0.05)
}

/// One registration of a ring: `source` onto `target` (indices of the scans).
#[derive(Debug, Clone)]
pub struct RingEdge {
    pub source: usize,
    pub target: usize,
    pub icp: IcpResult,
}

/// A registered ring of scans.
#[derive(Debug, Clone)]
pub struct RingResult {
    /// Pose of every scan in the frame of the first scan's initial pose.
    pub world_from_scan: Vec<Isometry3<f64>>,
    /// Scan k onto scan k − 1 for every k, then the last onto the first.
    pub edges: Vec<RingEdge>,
    /// Disagreement of the chain and the closing edge before it was spread.
    pub loop_error_deg: f64,
    pub loop_error_translation: f64,
}

/// Registers a ring of scans, each onto the one before it starting from their initial poses'
/// relative motion, then the last onto the first, and spreads the loop's disagreement over
/// the ring in proportion to each edge's [`edge_variance`]
/// ([`distribute_loop_error_weighted`]). The first scan keeps its initial pose.
pub fn register_ring(scans: &[Vec<[f32; 3]>], init_world: &[Isometry3<f64>], params: &IcpParams) -> Result<RingResult, RegisterError> {
    let n = scans.len();
    if n < 3 || init_world.len() != n {
        return Err(RegisterError::Param(format!("a ring needs at least 3 scans with one initial pose each (got {n} scans, {} poses)", init_world.len())));
    }
    let mut targets: Vec<Target> = scans.iter().enumerate().map(|(k, s)| Target::cells(s.clone(), params.cell_size(), params.normals, &format!("scan {k}"))).collect::<Result<_, _>>()?;
    let mut chain = vec![Isometry3::identity()];
    let mut edges = Vec::new();
    for k in 1..n {
        let init = init_world[k - 1].inverse() * init_world[k];
        let r = icp(&scans[k], &mut targets[k - 1], &init, params)?;
        chain.push(chain[k - 1] * r.transform);
        edges.push(RingEdge { source: k, target: k - 1, icp: r });
    }
    let r = icp(&scans[n - 1], &mut targets[0], &chain[n - 1], params)?;
    let e = r.transform * chain[n - 1].inverse();
    let mut variances = vec![edge_variance(&r)];
    variances.extend(edges.iter().map(|e| edge_variance(&e.icp)));
    let closed = distribute_loop_error_weighted(&chain, &r.transform, &variances);
    edges.push(RingEdge { source: n - 1, target: 0, icp: r });
    Ok(RingResult {
        world_from_scan: closed.iter().map(|p| init_world[0] * p).collect(),
        edges,
        loop_error_deg: e.rotation.angle().to_degrees(),
        loop_error_translation: e.translation.vector.norm(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::register::{angle_deg, rotation_about_axis};
    use nalgebra::Vector3;

    #[test]
    fn loop_error_is_spread_evenly() {
        let axis = Vector3::new(0.0, 1.0, 0.0);
        let truth: Vec<Isometry3<f64>> = (0..10).map(|k| rotation_about_axis(&Vector3::zeros(), &axis, 36.0 * k as f64 * 0.97)).collect();
        // A chain that over-rotates by 0.1° per edge.
        let chain: Vec<Isometry3<f64>> = (0..10).map(|k| rotation_about_axis(&Vector3::zeros(), &axis, 36.0 * k as f64 * 0.97 + 0.1 * k as f64)).collect();
        let closed = distribute_loop_error(&chain, &truth[9]);
        assert_eq!(closed[0], Isometry3::identity());
        for k in 0..10 {
            let err = angle_deg(&(closed[k] * truth[k].inverse()));
            // View k keeps 0.1·k − 0.9·k/10 of error: at most 0.09° (at k = 9).
            assert!(err < 0.0901, "view {k}: {err}");
        }
    }
}

