//! The target side of ICP, prepared once and reused across runs: its points, an index that
//! pairs a query with a nearby target point, and normals computed on demand (only where
//! correspondences land).

use rayon::prelude::*;

use super::cells::CellIndex;
use super::grid::RangeGrid;
use super::normals::{normal_of, NormalParams};

/// How a target pairs a query point with one of its own.
pub enum Index {
    /// The exact nearest point within a bounded distance (any cloud; see [`super::cells`]).
    Cells(CellIndex),
    /// The nearest point near the query's line of sight (a view's cloud in its own camera
    /// frame; see [`super::grid`]).
    Grid(RangeGrid),
}

/// A point set ICP registers onto.
pub struct Target {
    index: Index,
    normals: Vec<[f32; 3]>,
    /// 0 = not computed, 1 = valid, 2 = too few neighbours.
    state: Vec<u8>,
    params: NormalParams,
}

impl Target {
    /// Exact nearest neighbours on a grid of cubic cells (any cloud); normals from up to
    /// `params.max_nn` neighbours within `params.radius`. `cell` is the cells' side
    /// ([`super::IcpParams::cell_size`] suits ICP).
    pub fn cells(points: Vec<[f32; 3]>, cell: f32, params: NormalParams, what: &str) -> Result<Target, super::RegisterError> {
        Ok(Target::with(Index::Cells(CellIndex::build(points, cell, what)?), params))
    }

    /// Projective pairing on a view's range grid; normals from the grid's 5 × 5 cell
    /// neighbourhood within `params.radius`.
    pub fn grid(grid: RangeGrid, params: NormalParams) -> Target {
        Target::with(Index::Grid(grid), params)
    }

    fn with(index: Index, params: NormalParams) -> Target {
        let n = match &index {
            Index::Cells(c) => c.len(),
            Index::Grid(g) => g.len(),
        };
        Target { index, normals: vec![[0.0; 3]; n], state: vec![0; n], params }
    }

    /// The target's points; pairs and normals index into them.
    pub fn points(&self) -> &[[f32; 3]] {
        match &self.index {
            Index::Cells(c) => &c.points,
            Index::Grid(g) => &g.points,
        }
    }

    /// The point paired with `p` within `max_d2` (squared distance): `(index, squared
    /// distance)`; None when the index has none there (for a range grid, also away from every
    /// point's line of sight).
    #[inline]
    pub fn nearest_within(&self, p: &[f32; 3], max_d2: f32) -> Option<(usize, f32)> {
        match &self.index {
            Index::Cells(c) => c.nearest_within(p, max_d2),
            Index::Grid(g) => g.nearest(p).filter(|&(_, d2)| d2 <= max_d2),
        }
    }

    /// Puts ICP's source points (moved by `init` into the target's frame) in the order that
    /// reads this target's memory best: a cell grid's cell order, so neighbouring queries
    /// read the same cells. A range grid keeps the caller's order (a view's scan order is
    /// already its cells' order).
    pub(super) fn order_queries(&self, src: &mut [[f32; 3]], init: &nalgebra::Isometry3<f64>) {
        if let Index::Cells(cells) = &self.index {
            src.sort_by_cached_key(|p| cells.cell_of(&super::apply(init, p)));
        }
    }

    /// Computes the normals of `indices` not computed yet, in parallel.
    pub(super) fn ensure_normals(&mut self, indices: impl Iterator<Item = usize>) {
        let mut todo: Vec<usize> = indices.filter(|&i| self.state[i] == 0).collect();
        todo.sort_unstable();
        todo.dedup();

        let params = self.params;
        let found: Vec<Option<[f32; 3]>> = match &self.index {
            Index::Cells(cells) => todo
                .par_iter()
                .with_min_len(256)
                .map_init(Vec::new, |scratch, &i| normal_of(cells.knn_within_unordered(&cells.points[i], params.max_nn, params.radius, scratch)).map(|(n, _)| n))
                .collect(),
            Index::Grid(grid) => todo.par_iter().with_min_len(1024).map(|&i| grid.normal_at(i, params.radius)).collect(),
        };
        for (i, n) in todo.into_iter().zip(found) {
            match n {
                Some(n) => {
                    self.normals[i] = n;
                    self.state[i] = 1;
                }
                None => self.state[i] = 2,
            }
        }
    }

    /// The normal of point `i`, when [`Target::ensure_normals`] found one.
    #[inline]
    pub(super) fn normal(&self, i: usize) -> Option<[f32; 3]> {
        (self.state[i] == 1).then(|| self.normals[i])
    }
}
