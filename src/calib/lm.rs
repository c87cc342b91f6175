//! Levenberg–Marquardt for calibration's shape of problem: a few parameters every residual
//! depends on (the cameras, the rig) and one small block per view (that view's pose), which
//! only that view's residuals depend on.
//!
//! The Jacobian is taken by central differences: per view, each global parameter and each of
//! the view's own — a few hundred projections of 54 corners per iteration, far cheaper than
//! the solve. The normal equations are assembled densely (global + 6 per view unknowns: 174
//! for 25 stereo pairs) and solved by Cholesky with Marquardt's scaled damping.

use nalgebra::{DMatrix, DVector};

/// A least-squares problem in global parameters and per-view blocks.
pub trait BlockProblem {
    /// Writes view `view`'s residuals for the given parameters into `out` (cleared first).
    fn residuals(&self, global: &[f64], block: &[f64], view: usize, out: &mut Vec<f64>);
    /// A step size for central differences of global parameter `i` at `value`.
    fn global_step(&self, _i: usize, value: f64) -> f64 {
        1e-6 * value.abs().max(1e-2)
    }
    /// Which global parameters are held fixed (default none).
    fn global_fixed(&self, _i: usize) -> bool {
        false
    }
}

/// The outcome of [`solve`].
#[derive(Debug, Clone)]
pub struct Solution {
    pub global: Vec<f64>,
    pub blocks: Vec<Vec<f64>>,
    /// Sum of squared residuals at the solution.
    pub cost: f64,
    pub iterations: usize,
}

/// Minimises the sum of squared residuals from the starting point.
pub fn solve<P: BlockProblem>(problem: &P, mut global: Vec<f64>, mut blocks: Vec<Vec<f64>>, max_iterations: usize) -> Solution {
    let g = global.len();
    let views = blocks.len();
    let bl = blocks.first().map_or(0, Vec::len);
    let n = g + bl * views;
    let cost_of = |global: &[f64], blocks: &[Vec<f64>]| -> f64 {
        let mut r = Vec::new();
        (0..views)
            .map(|v| {
                problem.residuals(global, &blocks[v], v, &mut r);
                r.iter().map(|x| x * x).sum::<f64>()
            })
            .sum()
    };
    let mut cost = cost_of(&global, &blocks);
    let mut lambda = 1e-3;
    let mut iterations = 0;
    let mut r0 = Vec::new();
    let (mut rp, mut rm) = (Vec::new(), Vec::new());
    while iterations < max_iterations {
        iterations += 1;
        let mut normal = DMatrix::<f64>::zeros(n, n);
        let mut grad = DVector::<f64>::zeros(n);
        for v in 0..views {
            problem.residuals(&global, &blocks[v], v, &mut r0);
            let m = r0.len();
            // Columns: the global parameters, then this view's block.
            let cols: Vec<usize> = (0..g).filter(|&i| !problem.global_fixed(i)).chain((0..bl).map(|k| g + v * bl + k)).collect();
            let mut jac = DMatrix::<f64>::zeros(m, cols.len());
            for (c, &p) in cols.iter().enumerate() {
                if p < g {
                    let h = problem.global_step(p, global[p]);
                    let mut x = global.clone();
                    x[p] += h;
                    problem.residuals(&x, &blocks[v], v, &mut rp);
                    x[p] -= 2.0 * h;
                    problem.residuals(&x, &blocks[v], v, &mut rm);
                    for k in 0..m {
                        jac[(k, c)] = (rp[k] - rm[k]) / (2.0 * h);
                    }
                } else {
                    let kk = p - g - v * bl;
                    let h = 1e-7 * blocks[v][kk].abs().max(1.0);
                    let mut b = blocks[v].clone();
                    b[kk] += h;
                    problem.residuals(&global, &b, v, &mut rp);
                    b[kk] -= 2.0 * h;
                    problem.residuals(&global, &b, v, &mut rm);
                    for k in 0..m {
                        jac[(k, c)] = (rp[k] - rm[k]) / (2.0 * h);
                    }
                }
            }
            let jtj = jac.transpose() * &jac;
            let jtr = jac.transpose() * DVector::from_column_slice(&r0);
            for (a, &pa) in cols.iter().enumerate() {
                grad[pa] += jtr[a];
                for (b, &pb) in cols.iter().enumerate() {
                    normal[(pa, pb)] += jtj[(a, b)];
                }
            }
        }
        // Fixed parameters: a unit diagonal and no gradient keep them where they are.
        for i in 0..g {
            if problem.global_fixed(i) {
                normal[(i, i)] = 1.0;
            }
        }
        let mut improved = false;
        for _ in 0..12 {
            let mut damped = normal.clone();
            for i in 0..n {
                damped[(i, i)] += lambda * normal[(i, i)].max(1e-12);
            }
            let Some(chol) = damped.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let step = chol.solve(&(-&grad));
            let new_global: Vec<f64> = global.iter().enumerate().map(|(i, x)| x + step[i]).collect();
            let new_blocks: Vec<Vec<f64>> =
                blocks.iter().enumerate().map(|(v, b)| b.iter().enumerate().map(|(k, x)| x + step[g + v * bl + k]).collect()).collect();
            let new_cost = cost_of(&new_global, &new_blocks);
            if new_cost.is_finite() && new_cost < cost {
                let gain = cost - new_cost;
                global = new_global;
                blocks = new_blocks;
                cost = new_cost;
                lambda = (lambda / 10.0).max(1e-12);
                improved = gain > 1e-14 * cost.max(1e-300);
                break;
            }
            lambda *= 10.0;
        }
        if !improved {
            break;
        }
    }
    Solution { global, blocks, cost, iterations }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Lines y = a·x + b_v sharing a slope a, each view its own offset b_v.
    struct Lines(Vec<Vec<(f64, f64)>>);

    impl BlockProblem for Lines {
        fn residuals(&self, global: &[f64], block: &[f64], view: usize, out: &mut Vec<f64>) {
            out.clear();
            out.extend(self.0[view].iter().map(|&(x, y)| global[0] * x + block[0] - y));
        }
    }

    #[test]
    fn a_shared_slope_and_per_view_offsets_are_recovered() {
        let data: Vec<Vec<(f64, f64)>> = (0..4).map(|v| (0..10).map(|i| (i as f64, 2.5 * i as f64 + v as f64 * 3.0 - 1.0)).collect()).collect();
        let s = solve(&Lines(data), vec![0.0], vec![vec![0.0]; 4], 50);
        assert!((s.global[0] - 2.5).abs() < 1e-8, "{:?}", s.global);
        for (v, b) in s.blocks.iter().enumerate() {
            assert!((b[0] - (v as f64 * 3.0 - 1.0)).abs() < 1e-7);
        }
        assert!(s.cost < 1e-12);
    }
}
