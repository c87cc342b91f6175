//! Loop closure of [`Registrar`] (see the module docs of `ring`): the closing views
//! registered directly to the opening ones, the disagreement spread over the ring.

use nalgebra::Isometry3;

use super::{distribute_loop_error_weighted, edge_variance, LoopClosure, Registrar};
use crate::register::icp::{icp, Target};
use crate::register::RegisterError;

/// ICP iterations of loop closure.
const LOOP_ITERATIONS: usize = 60;

impl Registrar {
    pub(super) fn close_loop(&mut self) -> Result<Option<LoopClosure>, RegisterError> {
        let n = self.poses.len();
        if !self.params.close_loop || n < 3 {
            return Ok(None);
        }
        let step = self.turned_deg / (n - 1) as f64;
        if !(step > 0.0 && self.turned_deg + 1.5 * step >= 360.0 && self.turned_deg < 360.0 + 0.5 * step) {
            return Ok(None);
        }
        let Some(last_seq) = self.prev.as_ref().map(|p| p.seq) else { return Ok(None) };
        let chain: Vec<Isometry3<f64>> = self.poses.iter().map(|p| p.first_from_view).collect();
        // The closing views in the last view's frame, the opening ones in the first's; a view
        // on both sides (a short ring) stays on the opening side only.
        let last_from_first = chain[n - 1].inverse();
        let opening: Vec<usize> = self.opening.iter().map(|(k, _)| *k).collect();
        let source: Vec<[f32; 3]> = self.closing.iter().filter(|(k, _)| !opening.contains(k)).flat_map(|(k, pts)| pts.iter().map(|p| crate::register::apply(&(last_from_first * chain[*k]), p)).collect::<Vec<_>>()).collect();
        let target: Vec<[f32; 3]> = self.opening.iter().flat_map(|(k, pts)| pts.iter().map(|p| crate::register::apply(&chain[*k], p)).collect::<Vec<_>>()).collect();
        if source.is_empty() {
            return Err(RegisterError::Empty { what: format!("closing views of the ring (last view {last_seq})") });
        }
        let mut first = Target::cells(target, self.params.icp.cell_size(), self.params.icp.normals, "opening views of the ring")?;
        // Once per scan, from a chain that may have wandered a few degrees: the full
        // iteration budget of a pairwise registration, not the per-view one.
        let mut params = super::without_angles(&self.params.icp, self.poses.iter().any(|p| p.table_deg.is_none())).into_owned();
        params.max_iterations = params.max_iterations.max(LOOP_ITERATIONS);
        let r = icp(&source, &mut first, &chain[n - 1], &params)?;
        if let Some(w) = r.degeneracy_warning() {
            tracing::warn!("loop closure: {w}");
        }
        if r.fitness < self.params.min_fitness {
            tracing::warn!("loop closure: last view {last_seq} overlaps the first too little (fitness {:.2}); poses left as chained", r.fitness);
            return Ok(None);
        }
        let e = r.transform * chain[n - 1].inverse();
        let mut variances = self.step_variance.clone();
        variances[0] = edge_variance(&r);
        let closed = distribute_loop_error_weighted(&chain, &r.transform, &variances);
        for (p, c) in self.poses.iter_mut().zip(closed) {
            p.first_from_view = c;
        }
        self.update_axis();
        Ok(Some(LoopClosure { views: n, error_deg: e.rotation.angle().to_degrees(), error_translation: e.translation.vector.norm(), icp: r }))
    }
}
