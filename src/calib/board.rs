//! Chessboard detection: the inner corners of a `cols × rows` board in one grey image, in a
//! fixed order, to sub-pixel precision — or the reason there is none.
//!
//! 1. **Saddle points.** The image is smoothed (Gaussian, σ) and each pixel scored by
//!    `Ixy² − Ixx·Iyy`, positive where the intensity is a saddle, as at the junction of four
//!    squares. Local maxima above a fraction of the strongest are the candidates; each keeps
//!    the direction of its bright diagonal (the Hessian's eigenvector of the larger
//!    eigenvalue).
//! 2. **A grid grown from a seed.** From a candidate, its nearest candidates whose bright
//!    diagonal is turned by ≈ 90° (neighbours along an edge alternate; diagonal neighbours do
//!    not) give the two grid steps; the grid grows one position at a time, each predicted from
//!    the positions already found (straight-line extrapolation, or the parallelogram of three)
//!    and accepted when a candidate of the right parity lies within a third of a step. A
//!    board of inner corners is exactly a full `cols × rows` grid of X-junctions: the board's
//!    border makes L-corners, not saddles.
//! 3. **Order.** Corners are listed row by row (`index = row · cols + col`), with the column
//!    direction × row direction pointing into the image as the x × y axes do (a board is seen
//!    from its front), and, when the board is not symmetric under a half turn (`cols + rows`
//!    odd, as 9 × 6), the square between corners 0, 1, cols, cols+1 dark: the same physical
//!    corner is corner 0 in the left and the right image. Symmetric boards fall back to corner
//!    0 nearest the image's top-left, which two cameras agree on unless the board is turned
//!    near 45°.
//! 4. **Sub-pixel** by [`subpix::refine`] (OpenCV's `cornerSubPix`), each corner's window
//!    shrunk to 0.7 of its nearest neighbour's distance where the squares are small.
//!
//! Failures name what was seen: no grid at all, the largest grid when it is smaller than the
//! board (a wrong `--board`), a grid larger than the board, or edges too wide for the squares
//! (blur).

use std::fmt;

use super::grid::{find_grid, grid_dims, Candidate, Grid, GridMiss, Shape};
use super::subpix::{self, SubPixParams};
use crate::stereo::GrayView;

/// A board's inner-corner count: `cols` along a row, `rows` rows (OpenCV's `patternSize`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BoardSize {
    pub cols: usize,
    pub rows: usize,
}

impl BoardSize {
    /// The number of inner corners.
    pub fn corners(&self) -> usize {
        self.cols * self.rows
    }

    /// `true` when a half turn maps the board's colours onto themselves (the order then rests
    /// on the image's top-left).
    pub fn symmetric(&self) -> bool {
        (self.cols + self.rows) % 2 == 0
    }
}

impl fmt::Display for BoardSize {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}×{}", self.cols, self.rows)
    }
}

/// Why a board size does not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BoardSizeError {
    #[error("`{0}` is not a board size: expected inner corners as COLSxROWS, e.g. 9x6")]
    Syntax(String),
    #[error("`{0}`: a board needs 3…64 inner corners each way")]
    Range(String),
}

impl std::str::FromStr for BoardSize {
    type Err = BoardSizeError;
    /// `9x6` (or `9×6`): inner corners along a row × rows.
    fn from_str(s: &str) -> Result<Self, BoardSizeError> {
        let parts: Vec<&str> = s.split(['x', 'X', '×']).collect();
        let bad = || BoardSizeError::Syntax(s.to_string());
        if parts.len() != 2 {
            return Err(bad());
        }
        let cols: usize = parts[0].trim().parse().map_err(|_| bad())?;
        let rows: usize = parts[1].trim().parse().map_err(|_| bad())?;
        if cols < 3 || rows < 3 || cols > 64 || rows > 64 {
            return Err(BoardSizeError::Range(s.to_string()));
        }
        Ok(BoardSize { cols, rows })
    }
}

/// A board found in an image.
#[derive(Debug, Clone, PartialEq)]
pub struct BoardCorners {
    /// `cols × rows` corners, row by row, pixels (centres at integers, as OpenCV).
    pub points: Vec<[f64; 2]>,
    /// Median distance between neighbouring corners, pixels.
    pub spacing_px: f64,
    /// Median 10–90 % width of the edges between squares, pixels (a blur measure; 0 when
    /// no edge had contrast enough to measure).
    pub edge_px: f64,
}

/// Why no board was found.
#[derive(Debug, Clone, PartialEq)]
pub enum DetectFailure {
    /// Fewer than four corner-like points.
    NoCorners { board: BoardSize },
    /// The largest regular grid of corners is smaller than the board.
    WrongSize { board: BoardSize, found: (usize, usize) },
    /// A regular grid larger than the board: two boards, or a board of another size.
    Ambiguous { board: BoardSize, found: (usize, usize) },
    /// The edges are too wide for the squares to place the corners.
    Blurred { edge_px: f64, spacing_px: f64 },
}

impl fmt::Display for DetectFailure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DetectFailure::NoCorners { board } => {
                write!(f, "no {board} board found (no grid of chessboard corners at all) — is a {board} board in view, lit and in focus?")
            }
            DetectFailure::WrongSize { board, found } => write!(
                f,
                "no {board} board found (largest grid of corners {}×{}) — is the board {board} inner corners, and wholly in view?",
                found.0, found.1
            ),
            DetectFailure::Ambiguous { board, found } => write!(
                f,
                "corners ambiguous: a {}×{} grid of corners, larger than the {board} board (another board in view, or is the board {}×{}?)",
                found.0, found.1, found.0, found.1
            ),
            DetectFailure::Blurred { edge_px, spacing_px } => write!(
                f,
                "board too blurred: its edges are {edge_px:.1} px wide on squares {spacing_px:.1} px apart (at most a third is usable) — focus, or hold still"
            ),
        }
    }
}

/// Knobs of [`detect`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectParams {
    pub subpix: SubPixParams,
    /// Largest edge width, as a fraction of the corner spacing, before a board is too blurred.
    pub max_blur: f64,
}

impl Default for DetectParams {
    fn default() -> Self {
        DetectParams { subpix: SubPixParams::default(), max_blur: 1.0 / 3.0 }
    }
}

/// Finds the board in `img`.
pub fn detect(img: &GrayView, board: BoardSize, params: &DetectParams) -> Result<BoardCorners, DetectFailure> {
    let mut best: Option<DetectFailure> = None;
    // σ 1.5 suits most boards; a noisy or blurred image may need more, tiny squares less.
    for sigma in [1.5, 3.0, 0.8] {
        let candidates = saddles(img, sigma);
        let found = find_grid(&candidates, Shape { cols: board.cols, rows: board.rows }).map_err(|miss| match miss {
            GridMiss::NoCorners => DetectFailure::NoCorners { board },
            GridMiss::Smaller(found) => DetectFailure::WrongSize { board, found },
            GridMiss::Larger(found) => DetectFailure::Ambiguous { board, found },
        });
        match found {
            Ok(grid) => return finish(img, board, &candidates, grid, params),
            Err(e) => {
                best = Some(match (best, e) {
                    (None, e) => e,
                    (Some(DetectFailure::NoCorners { .. }), e) => e,
                    (Some(b @ DetectFailure::Ambiguous { .. }), _) => b,
                    (_, e @ DetectFailure::Ambiguous { .. }) => e,
                    (Some(DetectFailure::WrongSize { board, found: a }), DetectFailure::WrongSize { found: b, .. }) => {
                        DetectFailure::WrongSize { board, found: if b.0 * b.1 > a.0 * a.1 { b } else { a } }
                    }
                    (Some(b), _) => b,
                })
            }
        }
    }
    Err(best.unwrap_or(DetectFailure::NoCorners { board }))
}

fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    let r = (3.0 * sigma).ceil() as isize;
    let k: Vec<f64> = (-r..=r).map(|i| (-((i * i) as f64) / (2.0 * sigma * sigma)).exp()).collect();
    let s: f64 = k.iter().sum();
    k.iter().map(|v| (v / s) as f32).collect()
}

/// Separable blur with the border replicated.
fn blur(img: &GrayView, sigma: f64) -> Vec<f32> {
    let (w, h) = (img.width, img.height);
    let k = gaussian_kernel(sigma);
    let r = (k.len() / 2) as isize;
    let mut tmp = vec![0f32; w * h];
    for y in 0..h {
        let row = &img.data[y * w..(y + 1) * w];
        for x in 0..w {
            let mut s = 0f32;
            for (i, kv) in k.iter().enumerate() {
                let xi = (x as isize + i as isize - r).clamp(0, w as isize - 1) as usize;
                s += kv * f32::from(row[xi]);
            }
            tmp[y * w + x] = s;
        }
    }
    let mut out = vec![0f32; w * h];
    for y in 0..h {
        for (i, kv) in k.iter().enumerate() {
            let yi = (y as isize + i as isize - r).clamp(0, h as isize - 1) as usize;
            let src = &tmp[yi * w..(yi + 1) * w];
            for (o, s) in out[y * w..(y + 1) * w].iter_mut().zip(src) {
                *o += kv * s;
            }
        }
    }
    out
}

/// Saddle points of the smoothed image, strongest first.
fn saddles(img: &GrayView, sigma: f64) -> Vec<Candidate> {
    let (w, h) = (img.width, img.height);
    if w < 8 || h < 8 {
        return Vec::new();
    }
    let s = blur(img, sigma);
    let mut score = vec![0f32; w * h];
    let mut hess = vec![(0f32, 0f32, 0f32); w * h];
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let i = y * w + x;
            let ixx = s[i - 1] - 2.0 * s[i] + s[i + 1];
            let iyy = s[i - w] - 2.0 * s[i] + s[i + w];
            let ixy = (s[i + w + 1] - s[i + w - 1] - s[i - w + 1] + s[i - w - 1]) * 0.25;
            score[i] = (ixy * ixy - ixx * iyy).max(0.0);
            hess[i] = (ixx, ixy, iyy);
        }
    }
    let max = score.iter().copied().fold(0f32, f32::max);
    if max <= 0.0 {
        return Vec::new();
    }
    // Relative to the strongest, and absolute: a saddle of a few grey levels' contrast is
    // the sensor's noise, not a board (a blank image must not grow a "grid").
    let floor = (max * 0.01).max(0.5);
    let r = 3usize;
    let mut out = Vec::new();
    for y in r.max(2)..h - r.max(2) {
        for x in r.max(2)..w - r.max(2) {
            let v = score[y * w + x];
            if v < floor {
                continue;
            }
            let mut peak = true;
            'n: for yy in y - r..=y + r {
                for xx in x - r..=x + r {
                    let u = score[yy * w + xx];
                    // Ties go to the first in scan order.
                    if u > v || (u == v && (yy, xx) < (y, x)) {
                        peak = false;
                        break 'n;
                    }
                }
            }
            if !peak {
                continue;
            }
            // Sub-pixel peak of the score (a parabola each way) for the grid's geometry.
            let at = |xx: usize, yy: usize| f64::from(score[yy * w + xx]);
            let para = |a: f64, b: f64, c: f64| {
                let d = a - 2.0 * b + c;
                if d < 0.0 {
                    (0.5 * (a - c) / d).clamp(-0.5, 0.5)
                } else {
                    0.0
                }
            };
            let dx = para(at(x - 1, y), at(x, y), at(x + 1, y));
            let dy = para(at(x, y - 1), at(x, y), at(x, y + 1));
            if !x_junction(&s, w, h, x as f64 + dx, y as f64 + dy, (3.0 * sigma).max(3.0)) {
                continue;
            }
            let (ixx, ixy, iyy) = hess[y * w + x];
            let theta = (0.5 * f64::from(2.0 * ixy).atan2(f64::from(ixx - iyy))).rem_euclid(std::f64::consts::PI);
            out.push(Candidate { x: x as f64 + dx, y: y as f64 + dy, score: v, theta });
        }
    }
    out.sort_by(|a, b| b.score.total_cmp(&a.score));
    out.truncate(4000);
    out
}

/// `true` when a ring of radius `r` around `(x, y)` crosses four sectors, bright and dark in
/// turn, with opposite sectors alike: the junction of four squares. An L-corner (one square's
/// corner on a plain margin, as all round a board's border) or an edge crosses two.
fn x_junction(s: &[f32], w: usize, h: usize, x: f64, y: f64, r: f64) -> bool {
    const N: usize = 24;
    let mut ring = [0f32; N];
    for (k, v) in ring.iter_mut().enumerate() {
        let a = k as f64 * std::f64::consts::TAU / N as f64;
        let (px, py) = (x + r * a.cos(), y + r * a.sin());
        if px < 0.0 || py < 0.0 || px > (w - 1) as f64 || py > (h - 1) as f64 {
            return false;
        }
        let (x0, y0) = (px.floor() as usize, py.floor() as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let (fx, fy) = ((px - x0 as f64) as f32, (py - y0 as f64) as f32);
        let top = s[y0 * w + x0] * (1.0 - fx) + s[y0 * w + x1] * fx;
        let bottom = s[y1 * w + x0] * (1.0 - fx) + s[y1 * w + x1] * fx;
        *v = top * (1.0 - fy) + bottom * fy;
    }
    let mean = ring.iter().sum::<f32>() / N as f32;
    let bright: Vec<bool> = ring.iter().map(|&v| v > mean).collect();
    let changes = (0..N).filter(|&k| bright[k] != bright[(k + 1) % N]).count();
    let opposite = (0..N).filter(|&k| bright[k] == bright[(k + N / 2) % N]).count();
    changes == 4 && opposite >= N - 4
}

/// Orders the grid, refines its corners and measures its blur.
fn finish(img: &GrayView, board: BoardSize, c: &[Candidate], grid: Grid, params: &DetectParams) -> Result<BoardCorners, DetectFailure> {
    let i0 = grid.keys().map(|k| k.0).min().unwrap_or(0);
    let j0 = grid.keys().map(|k| k.1).min().unwrap_or(0);
    let (ni, nj) = grid_dims(&grid);
    let at = |i: usize, j: usize| {
        let q = grid[&(i as i32 + i0, j as i32 + j0)];
        [c[q].x, c[q].y]
    };
    // Every way of laying the grid on the board: (col, row) → (i, j).
    let (cols, rows) = (board.cols, board.rows);
    let mut layouts: Vec<Box<dyn Fn(usize, usize) -> (usize, usize)>> = Vec::new();
    for swap in [false, true] {
        if (if swap { (nj, ni) } else { (ni, nj) }) != (cols, rows) {
            continue;
        }
        for flip_c in [false, true] {
            for flip_r in [false, true] {
                layouts.push(Box::new(move |col, row| {
                    let col = if flip_c { cols - 1 - col } else { col };
                    let row = if flip_r { rows - 1 - row } else { row };
                    if swap {
                        (row, col)
                    } else {
                        (col, row)
                    }
                }));
            }
        }
    }
    let ordered = |l: &dyn Fn(usize, usize) -> (usize, usize)| -> Vec<[f64; 2]> {
        (0..rows).flat_map(|r| (0..cols).map(move |cc| (cc, r))).map(|(cc, r)| {
            let (i, j) = l(cc, r);
            at(i, j)
        }).collect()
    };
    let smooth = blur(img, 1.0);
    let lum = |x: f64, y: f64| {
        let xi = (x.round() as isize).clamp(0, img.width as isize - 1) as usize;
        let yi = (y.round() as isize).clamp(0, img.height as isize - 1) as usize;
        f64::from(smooth[yi * img.width + xi])
    };
    let mut best: Option<(i32, f64, Vec<[f64; 2]>)> = None;
    for l in &layouts {
        let p = ordered(l.as_ref());
        let ex = (p[cols - 1][0] - p[0][0], p[cols - 1][1] - p[0][1]);
        let ey = (p[(rows - 1) * cols][0] - p[0][0], p[(rows - 1) * cols][1] - p[0][1]);
        if ex.0 * ey.1 - ex.1 * ey.0 <= 0.0 {
            continue;
        }
        // Mean brightness of the squares of corner 0's parity minus the others'.
        let mut contrast = 0.0;
        for r in 0..rows - 1 {
            for cc in 0..cols - 1 {
                let q = [p[r * cols + cc], p[r * cols + cc + 1], p[(r + 1) * cols + cc], p[(r + 1) * cols + cc + 1]];
                let m = lum(q.iter().map(|v| v[0]).sum::<f64>() / 4.0, q.iter().map(|v| v[1]).sum::<f64>() / 4.0);
                contrast += if (r + cc) % 2 == 0 { m } else { -m };
            }
        }
        let dark_first = if board.symmetric() { 0 } else { i32::from(contrast < 0.0) };
        let top_left = -(p[0][0] + p[0][1]);
        if best.as_ref().is_none_or(|b| (dark_first, top_left) > (b.0, b.1)) {
            best = Some((dark_first, top_left, p));
        }
    }
    let Some((_, _, mut points)) = best else {
        return Err(DetectFailure::WrongSize { board, found: (ni, nj) });
    };
    // Spacing: median distance between neighbours along rows and columns.
    let mut steps = Vec::new();
    for r in 0..rows {
        for cc in 0..cols {
            let p = points[r * cols + cc];
            if cc + 1 < cols {
                let q = points[r * cols + cc + 1];
                steps.push(((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt());
            }
            if r + 1 < rows {
                let q = points[(r + 1) * cols + cc];
                steps.push(((q[0] - p[0]).powi(2) + (q[1] - p[1]).powi(2)).sqrt());
            }
        }
    }
    steps.sort_by(f64::total_cmp);
    let spacing = steps[steps.len() / 2];
    // Each corner's window stays clear of the neighbouring junctions and of the grid lines
    // beside it: a junction's edges, and at the board's border the outer squares' edges, do
    // not pass through this corner and pull it (iterated, two corners can merge). The
    // window's half-side is at most `factor` × the nearest of (a) the neighbours' distance
    // (square, as the window is) and (b) the distance to the next grid line each way (a
    // sheared square's height, |u × v| / |u|). Measured on rendered boards (realistic rig,
    // 9 poses × 2 images): 0.8 left a sheared border corner 1.6 px off, 0.7 kept the worst
    // of 972 corners at 0.17 px (median 0.03); on the real XIMEA boards 0.7 still gives
    // OpenCV's 11-pixel window almost everywhere (0.006 px mean from OpenCV's corners).
    let factor = 0.7;
    let initial = points.clone();
    let at = |r: i64, c: i64| (r >= 0 && c >= 0 && r < rows as i64 && c < cols as i64).then(|| initial[r as usize * cols + c as usize]);
    for (k, p) in points.iter_mut().enumerate() {
        let (r, cc) = ((k / cols) as i64, (k % cols) as i64);
        let mut near = f64::INFINITY;
        for (dr, dc) in [(0i64, 1i64), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1)] {
            if let Some(q) = at(r + dr, cc + dc) {
                near = near.min((q[0] - p[0]).abs().max((q[1] - p[1]).abs()));
            }
        }
        let step = |q: Option<[f64; 2]>| q.map(|q| [q[0] - p[0], q[1] - p[1]]);
        let u = step(at(r, cc + 1)).or_else(|| step(at(r, cc - 1)));
        let v = step(at(r + 1, cc)).or_else(|| step(at(r - 1, cc)));
        if let (Some(u), Some(v)) = (u, v) {
            let area = (u[0] * v[1] - u[1] * v[0]).abs();
            let (lu, lv) = (u[0].hypot(u[1]), v[0].hypot(v[1]));
            if lu > 0.0 && lv > 0.0 {
                near = near.min(area / lu).min(area / lv);
            }
        }
        let half = params.subpix.half_window.min(((factor * near).floor() as usize).max(2));
        let (x, y) = subpix::refine(img, p[0], p[1], &SubPixParams { half_window: half, ..params.subpix });
        *p = [x, y];
    }
    // Blur: edges crossed at the middle of each row segment between two corners.
    let mut widths = Vec::new();
    for r in 0..rows {
        for cc in 0..cols - 1 {
            let (p, q) = (points[r * cols + cc], points[r * cols + cc + 1]);
            let (dx, dy) = (q[0] - p[0], q[1] - p[1]);
            let len = (dx * dx + dy * dy).sqrt();
            if len < 1.0 {
                continue;
            }
            let mid = ((p[0] + q[0]) / 2.0, (p[1] + q[1]) / 2.0);
            if let Some(wd) = subpix::edge_width(img, mid, (-dy / len, dx / len), len * 0.45) {
                widths.push(wd);
            }
        }
    }
    widths.sort_by(f64::total_cmp);
    // No edge with a measurable step (a faint board): not judged, reported as 0.
    let edge_px = widths.get(widths.len() / 2).copied().unwrap_or(0.0);
    if edge_px > params.max_blur * spacing {
        return Err(DetectFailure::Blurred { edge_px, spacing_px: spacing });
    }
    Ok(BoardCorners { points, spacing_px: spacing, edge_px })
}
