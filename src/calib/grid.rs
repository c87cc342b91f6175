//! The grid step of chessboard detection ([`super::board`]): from saddle-point candidates,
//! grids grown from seeds, and the one full board-sized window among them — or what was
//! seen instead (a smaller grid: a wrong board size; a larger one: ambiguous).

use std::collections::HashMap;

/// A saddle point: where, how strong, and which way its bright diagonal runs.
#[derive(Debug, Clone, Copy)]
pub(super) struct Candidate {
    pub(super) x: f64,
    pub(super) y: f64,
    pub(super) score: f32,
    /// Direction of the bright diagonal, radians in [0, π).
    pub(super) theta: f64,
}

/// Inner corners along a row and rows, as the grid step needs them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) struct Shape {
    pub(super) cols: usize,
    pub(super) rows: usize,
}

/// Why no board-sized grid: too few corners, or the largest grid (board-oriented, cols
/// first) when smaller than the board, or a grid larger than the board.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum GridMiss {
    NoCorners,
    Smaller((usize, usize)),
    Larger((usize, usize)),
}

/// Buckets of candidates for nearest-neighbour queries.
struct Buckets {
    cell: f64,
    map: HashMap<(i64, i64), Vec<usize>>,
}

impl Buckets {
    fn new(c: &[Candidate], cell: f64) -> Buckets {
        let mut map: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (i, p) in c.iter().enumerate() {
            map.entry(((p.x / cell).floor() as i64, (p.y / cell).floor() as i64)).or_default().push(i);
        }
        Buckets { cell, map }
    }

    /// Candidates within `radius` of `(x, y)`.
    fn near(&self, c: &[Candidate], x: f64, y: f64, radius: f64) -> impl Iterator<Item = usize> + '_ {
        let (x0, x1) = (((x - radius) / self.cell).floor() as i64, ((x + radius) / self.cell).floor() as i64);
        let (y0, y1) = (((y - radius) / self.cell).floor() as i64, ((y + radius) / self.cell).floor() as i64);
        let r2 = radius * radius;
        let pts: Vec<usize> = (y0..=y1)
            .flat_map(|by| (x0..=x1).map(move |bx| (bx, by)))
            .filter_map(|k| self.map.get(&k))
            .flatten()
            .copied()
            .filter(|&i| (c[i].x - x).powi(2) + (c[i].y - y).powi(2) <= r2)
            .collect();
        pts.into_iter()
    }
}

/// The angle between two bright-diagonal directions, in [0, π/2].
fn turn(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::PI);
    d.min(std::f64::consts::PI - d)
}

/// Grid position → candidate index.
pub(super) type Grid = HashMap<(i32, i32), usize>;

pub(super) fn find_grid(c: &[Candidate], board: Shape) -> Result<Grid, GridMiss> {
    if c.len() < 4 {
        return Err(GridMiss::NoCorners);
    }
    let buckets = Buckets::new(c, 16.0);
    let mut used = vec![false; c.len()];
    let mut largest = (0usize, 0usize);
    let mut too_large: Option<(usize, usize)> = None;
    // The strongest candidates seed grids (a board's corners are high-contrast junctions;
    // a cluttered scene may still put a few hundred saddles ahead of some of them).
    for seed in 0..c.len().min(300) {
        if used[seed] {
            continue;
        }
        let Some(grid) = grow(c, &buckets, seed) else { continue };
        for &i in grid.values() {
            used[i] = true;
        }
        let (placements, full) = placements(&grid, board);
        match placements.as_slice() {
            [one] => return Ok(one.clone()),
            [] => {
                let f = if board.cols >= board.rows { (full.0.max(full.1), full.0.min(full.1)) } else { (full.0.min(full.1), full.0.max(full.1)) };
                if f.0 * f.1 > largest.0 * largest.1 {
                    largest = f;
                }
            }
            _ => too_large = Some(if board.cols >= board.rows { (full.0.max(full.1), full.0.min(full.1)) } else { (full.0.min(full.1), full.0.max(full.1)) }),
        }
    }
    if let Some(found) = too_large {
        return Err(GridMiss::Larger(found));
    }
    if largest.0 * largest.1 < 4 {
        return Err(GridMiss::NoCorners);
    }
    Err(GridMiss::Smaller(largest))
}

pub(super) fn grid_dims(g: &Grid) -> (usize, usize) {
    let (mut i0, mut i1, mut j0, mut j1) = (i32::MAX, i32::MIN, i32::MAX, i32::MIN);
    for &(i, j) in g.keys() {
        i0 = i0.min(i);
        i1 = i1.max(i);
        j0 = j0.min(j);
        j1 = j1.max(j);
    }
    ((i1 - i0 + 1) as usize, (j1 - j0 + 1) as usize)
}

/// The board-sized windows of `grid` in which every position is filled (each as its own
/// grid), and the largest filled rectangle's dimensions.
fn placements(grid: &Grid, board: Shape) -> (Vec<Grid>, (usize, usize)) {
    let i0 = grid.keys().map(|k| k.0).min().unwrap_or(0);
    let j0 = grid.keys().map(|k| k.1).min().unwrap_or(0);
    let (ni, nj) = grid_dims(grid);
    let filled = |i: usize, j: usize| grid.contains_key(&(i as i32 + i0, j as i32 + j0));
    let full_rect = |i: usize, j: usize, w: usize, h: usize| (j..j + h).all(|jj| (i..i + w).all(|ii| filled(ii, jj)));
    let mut out = Vec::new();
    let mut shapes = vec![(board.cols, board.rows)];
    if board.cols != board.rows {
        shapes.push((board.rows, board.cols));
    }
    for &(w, h) in &shapes {
        if w > ni || h > nj {
            continue;
        }
        for j in 0..=nj - h {
            for i in 0..=ni - w {
                if full_rect(i, j, w, h) {
                    let sub: Grid = (j..j + h)
                        .flat_map(|jj| (i..i + w).map(move |ii| (ii, jj)))
                        .map(|(ii, jj)| {
                            let k = (ii as i32 + i0, jj as i32 + j0);
                            (k, grid[&k])
                        })
                        .collect();
                    out.push(sub);
                }
            }
        }
    }
    // The largest filled rectangle (by area), for the failure message: the histogram method,
    // each row's run of filled positions above it as bar heights.
    let mut heights = vec![0usize; ni];
    let mut best = (0, 0);
    for j in 0..nj {
        for (i, hgt) in heights.iter_mut().enumerate() {
            *hgt = if filled(i, j) { *hgt + 1 } else { 0 };
        }
        for i in 0..ni {
            let h = heights[i];
            if h == 0 {
                continue;
            }
            let left = (0..i).rev().take_while(|&k| heights[k] >= h).count();
            let right = (i + 1..ni).take_while(|&k| heights[k] >= h).count();
            let w = left + right + 1;
            if w * h > best.0 * best.1 {
                best = (w, h);
            }
        }
    }
    (out, best)
}

/// Grows a grid from candidate `seed`; `None` when the seed has no two grid neighbours.
fn grow(c: &[Candidate], buckets: &Buckets, seed: usize) -> Option<Grid> {
    let s = c[seed];
    // Nearest neighbours with the other parity (bright diagonal turned by ≈ 90°).
    let mut near: Vec<(f64, usize)> = buckets
        .near(c, s.x, s.y, 160.0)
        .filter(|&i| i != seed && turn(c[i].theta, s.theta) > std::f64::consts::FRAC_PI_4)
        .map(|i| (((c[i].x - s.x).powi(2) + (c[i].y - s.y).powi(2)).sqrt(), i))
        .filter(|&(d, _)| d >= 3.0)
        .collect();
    near.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (d1, n1) = *near.first()?;
    let u = (c[n1].x - s.x, c[n1].y - s.y);
    let n2 = near.iter().skip(1).find(|&&(d, i)| {
        let v = (c[i].x - s.x, c[i].y - s.y);
        let cos = (u.0 * v.0 + u.1 * v.1) / (d1 * d);
        cos.abs() < 0.77 && d / d1 < 2.5
    })?;
    let mut grid: Grid = HashMap::new();
    let mut taken: HashMap<usize, (i32, i32)> = HashMap::new();
    for (k, i) in [((0, 0), seed), ((1, 0), n1), ((0, 1), n2.1)] {
        grid.insert(k, i);
        taken.insert(i, k);
    }
    let pos = |g: &Grid, k: (i32, i32)| g.get(&k).map(|&i| (c[i].x, c[i].y));
    loop {
        let mut added = false;
        let frontier: Vec<(i32, i32)> = {
            let mut f: Vec<(i32, i32)> = grid
                .keys()
                .flat_map(|&(i, j)| [(i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)])
                .filter(|k| !grid.contains_key(k))
                .collect();
            f.sort_unstable();
            f.dedup();
            f
        };
        for k in frontier {
            let (i, j) = k;
            let mut preds: Vec<((f64, f64), f64)> = Vec::new();
            for (di, dj) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                if let (Some(a), Some(b)) = (pos(&grid, (i - di, j - dj)), pos(&grid, (i - 2 * di, j - 2 * dj))) {
                    let step = ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt();
                    preds.push(((2.0 * a.0 - b.0, 2.0 * a.1 - b.1), step));
                }
            }
            for (di, dj) in [(1, 1), (1, -1), (-1, 1), (-1, -1)] {
                if let (Some(a), Some(b), Some(d)) = (pos(&grid, (i - di, j)), pos(&grid, (i, j - dj)), pos(&grid, (i - di, j - dj))) {
                    let step = ((a.0 - d.0).powi(2) + (a.1 - d.1).powi(2)).sqrt().min(((b.0 - d.0).powi(2) + (b.1 - d.1).powi(2)).sqrt());
                    preds.push(((a.0 + b.0 - d.0, a.1 + b.1 - d.1), step));
                }
            }
            if preds.is_empty() {
                continue;
            }
            let n = preds.len() as f64;
            let px = preds.iter().map(|p| p.0 .0).sum::<f64>() / n;
            let py = preds.iter().map(|p| p.0 .1).sum::<f64>() / n;
            let step = preds.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
            let parity_same = (i + j).rem_euclid(2) == 0;
            // A corner of the board scores like the others; clutter beside it mostly does not.
            let mut scores: Vec<f32> = grid.values().map(|&q| c[q].score).collect();
            scores.sort_by(f32::total_cmp);
            let floor = scores[scores.len() / 2] * 0.1;
            let best = buckets
                .near(c, px, py, step / 3.0)
                .filter(|q| !taken.contains_key(q) && c[*q].score >= floor)
                .filter(|&q| (turn(c[q].theta, s.theta) < std::f64::consts::FRAC_PI_4) == parity_same)
                .min_by(|&a, &b| {
                    let da = (c[a].x - px).powi(2) + (c[a].y - py).powi(2);
                    let db = (c[b].x - px).powi(2) + (c[b].y - py).powi(2);
                    da.total_cmp(&db)
                });
            if let Some(q) = best {
                grid.insert(k, q);
                taken.insert(q, k);
                added = true;
            }
        }
        if !added || grid.len() > 64 * 64 {
            break;
        }
    }
    (grid.len() >= 4).then_some(grid)
}
