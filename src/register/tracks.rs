//! Texture tracks across the views of a turntable scan: the object's own texture followed
//! from view to view in the rectified left image, for the axis fit of [`super::bundle`].
//!
//! Why: an axis fitted to the views' *points* (`register::refine`) carries a bias of the
//! stereo clouds themselves — neighbouring views see the same texture through nearly the same
//! windows, so their depth errors are correlated, and a surface of revolution hardly fixes
//! the axis's tilt at all (docs/registration.md, Known limits). Where a textured point *is*
//! in each image is known far better than how deep it lies: a tracked point seen over tens
//! of degrees of turn is triangulated by the turn itself, and the line it turns about follows
//! from where it appears, not from its disparity alone.
//!
//! How: each active track's point is placed in the new view by the registered step (its
//! disparity in the previous view, turned by `new_from_prev`, projected), then found by
//! normalised cross-correlation of a window around it over a small search, to sub-pixel by a
//! parabola through the correlation's peak. Tracks that lose their match (low correlation, a
//! peak on the search's border, no disparity at the new place) end; new tracks start in the
//! cells of a grid that hold none, at the pixel whose gradients are strongest in both
//! directions (the smaller eigenvalue of the structure tensor, Shi & Tomasi). Every
//! observation keeps its rectified `(x, y)` and the disparity there.

use nalgebra::{Isometry3, Matrix3, Matrix4, Vector3, Vector4};

/// The rectified left camera: pixels and disparity ↔ points in the LEFT raw camera frame
/// (the frame of a view's points, see `stereo::triangulate`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackCamera {
    /// `rectleft_from_left`.
    r1: Matrix3<f64>,
    q: Matrix4<f64>,
    q_inv: Matrix4<f64>,
}

impl TrackCamera {
    /// From the rectification's `R1` and `Q`; None when `Q` is not invertible.
    pub fn new(r1: Matrix3<f64>, q: Matrix4<f64>) -> Option<TrackCamera> {
        let q_inv = q.try_inverse()?;
        (r1.iter().chain(q.iter()).all(|v| v.is_finite())).then_some(TrackCamera { r1, q, q_inv })
    }

    /// The point (left raw frame) at rectified pixel `(x, y)` with disparity `d`.
    pub fn unproject(&self, x: f64, y: f64, d: f64) -> Option<Vector3<f64>> {
        let h = self.q * Vector4::new(x, y, d, 1.0);
        if h.w == 0.0 {
            return None;
        }
        let p = Vector3::new(h.x / h.w, h.y / h.w, h.z / h.w);
        (p.z > 0.0).then(|| self.r1.transpose() * p)
    }

    /// Rectified pixel and disparity `(x, y, d)` of a point in the left raw frame.
    pub fn project(&self, p: &Vector3<f64>) -> Option<Vector3<f64>> {
        self.project_with_jacobian(p).map(|(v, _)| v)
    }

    /// [`Self::project`] and its derivative with respect to the point.
    pub fn project_with_jacobian(&self, p: &Vector3<f64>) -> Option<(Vector3<f64>, Matrix3<f64>)> {
        let pr = self.r1 * p;
        if !(pr.z > 0.0) {
            return None;
        }
        let h = self.q_inv * Vector4::new(pr.x, pr.y, pr.z, 1.0);
        if h.w.abs() < 1e-12 {
            return None;
        }
        let out = Vector3::new(h.x / h.w, h.y / h.w, h.z / h.w);
        let a = self.q_inv.fixed_view::<3, 3>(0, 0).into_owned();
        let b = self.q_inv.fixed_view::<1, 3>(3, 0).into_owned();
        let d_rect = (a - out * b) / h.w;
        Some((out, d_rect * self.r1))
    }
}

/// Settings of the [`Tracker`].
#[derive(Debug, Clone, PartialEq)]
pub struct TrackParams {
    /// Half the correlation window's side, pixels (5: 11 × 11).
    pub half_window: usize,
    /// How far from the predicted place a track is searched, pixels each way.
    pub search_px: i32,
    /// Side of the grid's cells in which new tracks start, pixels.
    pub cell_px: usize,
    /// A match needs at least this normalised cross-correlation.
    pub min_ncc: f64,
    /// A new track needs at least this smaller eigenvalue of the structure tensor (grey
    /// levels² per pixel, summed over the window).
    pub min_corner: f64,
    /// While fewer tracks than this are active after a view's new ones (a faint texture:
    /// few 5 × 5 windows reach `min_corner`), the cells still empty start tracks where the
    /// structure tensor over the whole correlation window reaches
    /// [`TrackParams::faint_corner`], the strongest first, up to this many active in all.
    pub sparse_tracks: usize,
    /// The smaller eigenvalue, summed over the correlation window (`half_window`), that a
    /// new track needs while tracks are sparse. A faint texture varies slowly: its 5 × 5
    /// gradients sink into the sensor's noise while the 11 × 11 window the tracks are
    /// correlated over still holds it; the correlation (`min_ncc`) then decides.
    pub faint_corner: f64,
}

impl Default for TrackParams {
    /// 11 × 11 windows, ±4 px around the predicted place, one new track per 12 × 12 cell,
    /// correlation ≥ 0.9; corners of 300 over 5 × 5, or of 300 over the window while fewer
    /// than 60 tracks are active.
    fn default() -> Self {
        TrackParams { half_window: 5, search_px: 4, cell_px: 12, min_ncc: 0.9, min_corner: 300.0, sparse_tracks: 60, faint_corner: 300.0 }
    }
}

/// One observation: track `track` seen in view `view` at rectified `(x, y)` with disparity
/// `d`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackObs {
    pub track: u32,
    pub view: u32,
    pub x: f32,
    pub y: f32,
    pub d: f32,
}

/// One view as the tracker reads it: the rectified left image (RGB, interleaved) and its
/// disparity map (NaN where none), both `width × height`.
#[derive(Debug, Clone, Copy)]
pub struct TrackImage<'a> {
    pub rgb: &'a [u8],
    pub disparity: &'a [f32],
    pub width: usize,
    pub height: usize,
}

/// The previous view, kept to track from.
struct Previous {
    gray: Vec<f32>,
    /// Central differences of `gray` along x and y (0 on the border).
    grad: (Vec<f32>, Vec<f32>),
    disparity: Vec<f32>,
    width: usize,
    height: usize,
}

/// One active track.
struct Active {
    id: u32,
    /// Place in the previous view.
    x: f64,
    y: f64,
    /// The window where the track started, normalised: every later view is matched against
    /// it (matching each view against the last one drifts).
    template: std::sync::Arc<Vec<f64>>,
    /// The window's affine shape in the previous view: `[a, b, c, e]` of
    /// `(x + (1 + a)·u + b·v, y + c·u + (1 + e)·v)` for window offsets `(u, v)`.
    warp: [f64; 4],
    /// Started at a faint corner (`faint_corner`, while tracks were sparse): in a noisy image
    /// most such tracks end at their next view, which says nothing of the step, so they
    /// neither call for nor take part in the wide search after a step that lost most tracks.
    faint: bool,
}

/// Follows texture from view to view; see the module docs.
pub struct Tracker {
    camera: TrackCamera,
    params: TrackParams,
    previous: Option<Previous>,
    /// Active tracks: id, place in the previous view, and the window where the track
    /// started (normalised), which every later view is matched against.
    active: Vec<Active>,
    obs: Vec<TrackObs>,
    /// Table angle of each view tracked, by view index.
    table_deg: Vec<f64>,
    next_id: u32,
}

impl Tracker {
    pub fn new(camera: TrackCamera, params: TrackParams) -> Tracker {
        Tracker { camera, params, previous: None, active: Vec::new(), obs: Vec::new(), table_deg: Vec::new(), next_id: 0 }
    }

    pub fn camera(&self) -> &TrackCamera {
        &self.camera
    }

    /// Every observation so far.
    pub fn observations(&self) -> &[TrackObs] {
        &self.obs
    }

    /// The table angle of each view tracked (the `view` of [`TrackObs`] indexes it).
    pub fn table_deg(&self) -> &[f64] {
        &self.table_deg
    }

    /// Tracks the active tracks into a new view and starts new ones. `new_from_prev` maps
    /// the previous view's points into this one's (None: no motion known, the tracks end and
    /// new ones start). `table_deg` NaN: the view's angle is unknown (a reading the turntable
    /// lost); the tracks go on through it, and the fits leave its observations out. An image
    /// whose size or buffers do not agree, or an infinite angle, ends every track and is not
    /// used.
    pub fn add(&mut self, image: TrackImage<'_>, table_deg: f64, new_from_prev: Option<&Isometry3<f64>>) {
        let n = image.width * image.height;
        if image.rgb.len() != 3 * n || image.disparity.len() != n || n == 0 || table_deg.is_infinite() {
            self.previous = None;
            self.active.clear();
            return;
        }
        let gray: Vec<f32> = image.rgb.chunks_exact(3).map(|c| 0.299 * c[0] as f32 + 0.587 * c[1] as f32 + 0.114 * c[2] as f32).collect();
        let view = self.table_deg.len() as u32;
        self.table_deg.push(table_deg);
        let grad = gradients(&gray, image.width, image.height);
        let current = Previous { gray, grad, disparity: image.disparity.to_vec(), width: image.width, height: image.height };
        let mut kept = Vec::new();
        if let (Some(prev), Some(motion)) = (&self.previous, new_from_prev) {
            if prev.width == current.width && prev.height == current.height {
                let guesses: Vec<Option<(f64, f64)>> = self.active.iter().map(|a| self.predict(prev, motion, a)).collect();
                kept = self.follow_all(&current, &guesses, (0.0, 0.0));
                // Most tracks lost: the motion was off by more than the search (a step ICP
                // could not see, before the axis seeds it). Find the image's shift from a
                // sample of tracks searched far, and follow again from there.
                let strong = self.active.iter().filter(|a| !a.faint).count();
                let strong_kept = kept.iter().filter(|(k, _)| !self.active[*k].faint).count();
                if strong_kept * 2 < strong && strong >= 20 {
                    if let Some(shift) = self.coarse_shift(&current, &guesses) {
                        let again = self.follow_all(&current, &guesses, shift);
                        if again.len() > kept.len() {
                            kept = again;
                        }
                    }
                }
            }
        }
        let kept: Vec<Active> = kept
            .into_iter()
            .map(|(k, (x, y, d, warp))| {
                let a = &self.active[k];
                self.obs.push(TrackObs { track: a.id, view, x: x as f32, y: y as f32, d: d as f32 });
                Active { id: a.id, x, y, template: a.template.clone(), warp, faint: a.faint }
            })
            .collect();
        self.active = kept;
        self.start_tracks(&current, view);
        self.previous = Some(current);
    }

    /// Where the previous view's motion puts `track` in the new view.
    fn predict(&self, prev: &Previous, motion: &Isometry3<f64>, track: &Active) -> Option<(f64, f64)> {
        let d = bilinear(&prev.disparity, prev.width, prev.height, track.x, track.y)?;
        let p = self.camera.unproject(track.x, track.y, d)?;
        let guess = self.camera.project(&(motion * nalgebra::Point3::from(p)).coords)?;
        Some((guess.x, guess.y))
    }

    /// Every track found near its guess moved by `shift`: (index into the active tracks,
    /// its place, disparity and window shape).
    fn follow_all(&self, cur: &Previous, guesses: &[Option<(f64, f64)>], shift: (f64, f64)) -> Vec<(usize, (f64, f64, f64, [f64; 4]))> {
        let r = self.params.search_px as i64;
        (self.active.iter().zip(guesses).enumerate())
            .filter_map(|(k, (a, g))| {
                let (gx, gy) = (*g)?;
                let (px, py, _) = self.search(cur, &a.template, (gx + shift.0, gy + shift.1), r)?;
                let (nx, ny, warp) = refine(&a.template, cur, (px, py), a.warp, self.params.half_window as i64)?;
                let nd = bilinear(&cur.disparity, cur.width, cur.height, nx, ny)?;
                Some((k, (nx, ny, nd, warp)))
            })
            .collect()
    }

    /// The median shift between where up to 40 tracks were guessed and where a search of
    /// ±`REACQUIRE_PX` finds them; None when fewer than 5 are found.
    fn coarse_shift(&self, cur: &Previous, guesses: &[Option<(f64, f64)>]) -> Option<(f64, f64)> {
        let stride = (self.active.iter().filter(|a| !a.faint).count() / 40).max(1);
        let mut shifts: Vec<(f64, f64)> = (self.active.iter().zip(guesses).filter(|(a, _)| !a.faint).step_by(stride))
            .filter_map(|(a, g)| {
                let g = (*g)?;
                let (px, py, _) = self.search(cur, &a.template, g, REACQUIRE_PX)?;
                Some((px - g.0, py - g.1))
            })
            .collect();
        if shifts.len() < 5 {
            return None;
        }
        let mid = shifts.len() / 2;
        shifts.sort_by(|a, b| a.0.total_cmp(&b.0));
        let dx = shifts[mid].0;
        shifts.sort_by(|a, b| a.1.total_cmp(&b.1));
        Some((dx, shifts[mid].1))
    }

    /// The best correlation of `template` within ±`r` pixels of `guess`, to sub-pixel by a
    /// parabola: `(x, y, ncc)`; None below `min_ncc`, on the search's border, or too near
    /// the image's.
    fn search(&self, cur: &Previous, template: &[f64], guess: (f64, f64), r: i64) -> Option<(f64, f64, f64)> {
        let hw = self.params.half_window as i64;
        let (cx, cy) = (guess.0.round() as i64, guess.1.round() as i64);
        let (w, h) = (cur.width as i64, cur.height as i64);
        if cx - r - hw - 1 < 0 || cy - r - hw - 1 < 0 || cx + r + hw + 1 >= w || cy + r + hw + 1 >= h {
            return None;
        }
        let side = (2 * r + 1) as usize;
        let mut scores = vec![f64::NEG_INFINITY; side * side];
        let mut best = (f64::NEG_INFINITY, 0usize, 0usize);
        for j in 0..side {
            for i in 0..side {
                let s = ncc_at(template, &cur.gray, cur.width, cx - r + i as i64, cy - r + j as i64, hw);
                scores[j * side + i] = s;
                if s > best.0 {
                    best = (s, i, j);
                }
            }
        }
        let (s, i, j) = best;
        if !(s >= self.params.min_ncc) || i == 0 || j == 0 || i + 1 == side || j + 1 == side {
            return None;
        }
        let at = |i: usize, j: usize| scores[j * side + i];
        let dx = parabola(at(i - 1, j), s, at(i + 1, j));
        let dy = parabola(at(i, j - 1), s, at(i, j + 1));
        Some(((cx - r + i as i64) as f64 + dx, (cy - r + j as i64) as f64 + dy, s))
    }

    /// Starts a track in each cell of the grid that holds none, at its strongest corner: the
    /// structure tensor over 5 × 5 reaching `min_corner`; then, while fewer than
    /// `sparse_tracks` are active, up to that many in all at the strongest corners over the
    /// correlation window that reach `faint_corner`, in the cells still empty.
    fn start_tracks(&mut self, cur: &Previous, view: u32) {
        let cell = self.params.cell_px.max(4);
        let (w, h) = (cur.width, cur.height);
        let (cols, rows) = (w.div_ceil(cell), h.div_ceil(cell));
        let mut taken = vec![false; cols * rows];
        for &Active { x, y, .. } in &self.active {
            let (c, r) = ((x.max(0.0) as usize / cell).min(cols - 1), (y.max(0.0) as usize / cell).min(rows - 1));
            taken[r * cols + c] = true;
        }
        let margin = self.params.half_window + self.params.search_px as usize + 2;
        let half_window = self.params.half_window;
        // Each empty cell's strongest corner over a window of half-side `hw` reaching `least`.
        let corners = |taken: &[bool], hw: usize, least: f64| -> Vec<(f64, usize, usize, usize)> {
            let mut found = Vec::new();
            for r in 0..rows {
                for c in 0..cols {
                    if taken[r * cols + c] {
                        continue;
                    }
                    let (x0, y0) = ((c * cell).max(margin), (r * cell).max(margin));
                    let (x1, y1) = (((c + 1) * cell).min(w.saturating_sub(margin)), ((r + 1) * cell).min(h.saturating_sub(margin)));
                    let mut best: Option<(f64, usize, usize, usize)> = None;
                    for y in (y0..y1).step_by(2) {
                        for x in (x0..x1).step_by(2) {
                            // Only where the whole window has disparities: the object, not its rim.
                            if !cur.disparity[y * w + x].is_finite() || !window_on_object(&cur.disparity, w, x, y, half_window) {
                                continue;
                            }
                            let score = corner_score(&cur.grad, w, x, y, hw);
                            if score >= least && best.is_none_or(|b| score > b.0) {
                                best = Some((score, r * cols + c, x, y));
                            }
                        }
                    }
                    found.extend(best);
                }
            }
            found
        };
        let start = |this: &mut Self, taken: &mut [bool], (_, k, x, y): (f64, usize, usize, usize), faint: bool| {
            if let Some(template) = window(&cur.gray, w, x, y, half_window) {
                let id = this.next_id;
                this.next_id += 1;
                this.obs.push(TrackObs { track: id, view, x: x as f32, y: y as f32, d: cur.disparity[y * w + x] });
                this.active.push(Active { id, x: x as f64, y: y as f64, template: std::sync::Arc::new(template), warp: [0.0; 4], faint });
                taken[k] = true;
            }
        };
        for corner in corners(&taken, 2, self.params.min_corner) {
            start(self, &mut taken, corner, false);
        }
        // Sparse: up to `sparse_tracks` in all, from the faint corners strongest first (in a
        // noisy image most of these die at the next view; so few are tried a view).
        let wanted = self.params.sparse_tracks.saturating_sub(self.active.len());
        if wanted > 0 {
            let mut faint = corners(&taken, self.params.half_window, self.params.faint_corner);
            faint.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            for corner in faint.into_iter().take(wanted) {
                start(self, &mut taken, corner, true);
            }
        }
    }
}

/// How far, pixels each way, a sample of tracks is searched when most were lost.
const REACQUIRE_PX: i64 = 32;

/// The vertex offset of a parabola through three equally spaced values, within ±0.5.
fn parabola(l: f64, c: f64, r: f64) -> f64 {
    let den = l - 2.0 * c + r;
    if den < 0.0 {
        (0.5 * (l - r) / den).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// The window's place and shape refined from `start` and `warp` by Gauss–Newton on the
/// normalised windows' difference (Lucas–Kanade with an affine window, as Shi & Tomasi
/// monitor features, and a linear ramp of brightness across the window): the parabola
/// through the correlation peak is biased towards whole pixels, a turning surface
/// foreshortens the window, and light falling differently across it shifts a plain
/// correlation's peak. None when the place wanders more than a pixel from `start` or the
/// shape degenerates.
fn refine(template: &[f64], image: &Previous, start: (f64, f64), warp: [f64; 4], hw: i64) -> Option<(f64, f64, [f64; 4])> {
    // Unknowns: x, y, the warp's a, b, c, e, and the ramp's slopes along u and v.
    let (mut x, mut y, mut w) = (start.0, start.1, warp);
    let scale = 1.0 / hw.max(1) as f64;
    for _ in 0..8 {
        let (win, gx, gy) = warped_window(image, (x, y), w, hw)?;
        let mut h = nalgebra::SMatrix::<f64, 8, 8>::zeros();
        let mut g = nalgebra::SVector::<f64, 8>::zeros();
        let mut k = 0;
        for v in -hw..=hw {
            for u in -hw..=hw {
                let (uf, vf) = (u as f64 * scale, v as f64 * scale);
                let j = nalgebra::SVector::<f64, 8>::from([gx[k], gy[k], gx[k] * uf, gx[k] * vf, gy[k] * uf, gy[k] * vf, -uf, -vf]);
                let r = win[k] - template[k];
                h += j * j.transpose();
                g += j * r;
                k += 1;
            }
        }
        let step = h.cholesky()?.solve(&(-g));
        x += step[0];
        y += step[1];
        for (wi, si) in w.iter_mut().zip(&step.as_slice()[2..6]) {
            *wi += si * scale;
        }
        if (x - start.0).abs() > 1.0 || (y - start.1).abs() > 1.0 || w.iter().any(|v| v.abs() > 0.5) {
            return None;
        }
        if step[0] * step[0] + step[1] * step[1] < 1e-4 {
            break;
        }
    }
    Some((x, y, w))
}

/// The normalised window centred on `(x, y)` with the affine shape `warp` (see
/// [`Active::warp`]), and its derivatives along the image's x and y.
fn warped_window(image: &Previous, (x, y): (f64, f64), warp: [f64; 4], hw: i64) -> Option<(Vec<f64>, Vec<f64>, Vec<f64>)> {
    let n = ((2 * hw + 1) * (2 * hw + 1)) as usize;
    let (mut win, mut gx, mut gy) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(n));
    let (width, height) = (image.width, image.height);
    for v in -hw..=hw {
        for u in -hw..=hw {
            let (uf, vf) = (u as f64, v as f64);
            let px = x + (1.0 + warp[0]) * uf + warp[1] * vf;
            let py = y + warp[2] * uf + (1.0 + warp[3]) * vf;
            if !(px >= 1.0 && py >= 1.0) {
                return None;
            }
            let (x0, y0) = (px as usize, py as usize);
            if x0 + 2 >= width || y0 + 2 >= height {
                return None;
            }
            let (fx, fy) = (px - x0 as f64, py - y0 as f64);
            let i = y0 * width + x0;
            let taps = [(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy];
            let at = |img: &[f32]| taps[0] * img[i] as f64 + taps[1] * img[i + 1] as f64 + taps[2] * img[i + width] as f64 + taps[3] * img[i + width + 1] as f64;
            win.push(at(&image.gray));
            gx.push(at(&image.grad.0));
            gy.push(at(&image.grad.1));
        }
    }
    let mean = win.iter().sum::<f64>() / n as f64;
    let norm = win.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>().sqrt();
    if !(norm > 1e-3) {
        return None;
    }
    win.iter_mut().for_each(|v| *v = (*v - mean) / norm);
    gx.iter_mut().for_each(|v| *v /= norm);
    gy.iter_mut().for_each(|v| *v /= norm);
    Some((win, gx, gy))
}

/// Central differences along x and y (0 on the image's border).
fn gradients(gray: &[f32], width: usize, height: usize) -> (Vec<f32>, Vec<f32>) {
    let (mut gx, mut gy) = (vec![0.0; gray.len()], vec![0.0; gray.len()]);
    for y in 1..height.saturating_sub(1) {
        for x in 1..width - 1 {
            let i = y * width + x;
            gx[i] = 0.5 * (gray[i + 1] - gray[i - 1]);
            gy[i] = 0.5 * (gray[i + width] - gray[i - width]);
        }
    }
    (gx, gy)
}

/// Bilinear value at `(x, y)`; None when any of the four neighbours is missing (NaN) or
/// they differ by more than a pixel (an edge between surfaces).
fn bilinear(values: &[f32], width: usize, height: usize, x: f64, y: f64) -> Option<f64> {
    if !(x >= 0.0 && y >= 0.0) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    if x0 + 1 >= width || y0 + 1 >= height {
        return None;
    }
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let v = [values[y0 * width + x0], values[y0 * width + x0 + 1], values[(y0 + 1) * width + x0], values[(y0 + 1) * width + x0 + 1]].map(|v| v as f64);
    let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| (l.min(v), h.max(v)));
    if !(lo.is_finite() && hi.is_finite()) || hi - lo > 1.0 {
        return None;
    }
    Some((v[0] * (1.0 - fx) + v[1] * fx) * (1.0 - fy) + (v[2] * (1.0 - fx) + v[3] * fx) * fy)
}

/// The zero-mean, unit-norm window of side `2·hw + 1` centred on the pixel `(x, y)`, which
/// lies at least `hw` pixels inside the image; None on a flat window.
fn window(gray: &[f32], width: usize, x: usize, y: usize, hw: usize) -> Option<Vec<f64>> {
    let mut v: Vec<f64> = (y - hw..=y + hw).flat_map(|yy| gray[yy * width + x - hw..=yy * width + x + hw].iter().map(|&g| g as f64)).collect();
    normalise(&mut v).then_some(v)
}

/// Subtracts the mean and scales to unit norm; false when the values are flat.
fn normalise(v: &mut [f64]) -> bool {
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    let mut ss = 0.0;
    for x in v.iter_mut() {
        *x -= mean;
        ss += *x * *x;
    }
    if !(ss > 1e-6) {
        return false;
    }
    let inv = 1.0 / ss.sqrt();
    v.iter_mut().for_each(|x| *x *= inv);
    true
}

/// Normalised cross-correlation of `template` (normalised) with the window centred on the
/// integer pixel `(x, y)` (inside the image).
fn ncc_at(template: &[f64], gray: &[f32], width: usize, x: i64, y: i64, hw: i64) -> f64 {
    let (mut s, mut s2, mut st) = (0.0, 0.0, 0.0);
    let mut k = 0;
    for j in -hw..=hw {
        let row = ((y + j) as usize) * width;
        for i in -hw..=hw {
            let g = gray[row + (x + i) as usize] as f64;
            s += g;
            s2 += g * g;
            st += g * template[k];
            k += 1;
        }
    }
    let n = k as f64;
    let var = s2 - s * s / n;
    // The template sums to zero, so the window's mean drops out of Σ g·t.
    if var > 1e-6 {
        st / var.sqrt()
    } else {
        f64::NEG_INFINITY
    }
}

/// The smaller eigenvalue of the structure tensor over the window of half-side `hw` at
/// `(x, y)`, from the image's central differences ([`gradients`]).
fn corner_score((grad_x, grad_y): &(Vec<f32>, Vec<f32>), width: usize, x: usize, y: usize, hw: usize) -> f64 {
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for yy in y - hw..=y + hw {
        for xx in x - hw..=x + hw {
            let (gx, gy) = (grad_x[yy * width + xx] as f64, grad_y[yy * width + xx] as f64);
            a += gx * gx;
            b += gx * gy;
            c += gy * gy;
        }
    }
    let t = 0.5 * (a + c);
    t - (0.25 * (a - c) * (a - c) + b * b).sqrt()
}

/// Whether every pixel of the window at `(x, y)` has a disparity.
fn window_on_object(disparity: &[f32], width: usize, x: usize, y: usize, hw: usize) -> bool {
    [(x - hw, y - hw), (x + hw, y - hw), (x - hw, y + hw), (x + hw, y + hw), (x - hw, y), (x + hw, y), (x, y - hw), (x, y + hw)].iter().all(|&(xx, yy)| disparity[yy * width + xx].is_finite())
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// f = 800, principal point (320, 240), baseline 60 mm: OpenCV's `Q` for positive
    /// disparities, no rotation (also `register::bundle`'s tests).
    pub(in crate::register) fn camera() -> TrackCamera {
        let q = Matrix4::new(1.0, 0.0, 0.0, -320.0, 0.0, 1.0, 0.0, -240.0, 0.0, 0.0, 0.0, 800.0, 0.0, 0.0, 1.0 / 60.0, 0.0);
        TrackCamera::new(Matrix3::identity(), q).unwrap()
    }

    #[test]
    fn projection_inverts_unprojection_and_its_jacobian_is_the_derivative() {
        let cam = camera();
        let p = cam.unproject(300.5, 200.25, 96.0).unwrap();
        assert!((p.z - 500.0).abs() < 1e-9, "{p}");
        let (v, j) = cam.project_with_jacobian(&p).unwrap();
        assert!((v - Vector3::new(300.5, 200.25, 96.0)).norm() < 1e-9, "{v}");
        for a in 0..3 {
            let mut e = Vector3::zeros();
            e[a] = 1e-4;
            let numeric = (cam.project(&(p + e)).unwrap() - cam.project(&(p - e)).unwrap()) / 2e-4;
            assert!((numeric - j.column(a)).norm() < 1e-6, "column {a}: {numeric} against {}", j.column(a));
        }
    }

    /// A textured plane at 500 mm, its texture moved by `shift` pixels: random blobs about
    /// 4 px across (value noise, smoothly interpolated), so that no pattern repeats.
    fn textured(width: usize, height: usize, shift: f64) -> (Vec<u8>, Vec<f32>) {
        textured_with(width, height, shift, 160.0)
    }

    /// [`textured`] with the texture's grey levels spanning `contrast` (160 there).
    fn textured_with(width: usize, height: usize, shift: f64, contrast: f64) -> (Vec<u8>, Vec<f32>) {
        let (gw, gh) = (width / 4 + 8, height / 4 + 4);
        let mut seed = 12345u64;
        let grid: Vec<f64> = (0..gw * gh)
            .map(|_| {
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (seed >> 11) as f64 / (1u64 << 53) as f64
            })
            .collect();
        let smooth = |t: f64| t * t * (3.0 - 2.0 * t);
        let mut rgb = vec![0u8; width * height * 3];
        for y in 0..height {
            for x in 0..width {
                let (u, v) = ((x as f64 - shift) / 4.0 + 4.0, y as f64 / 4.0 + 1.0);
                let (i, j) = (u.floor() as usize, v.floor() as usize);
                let (fx, fy) = (smooth(u - i as f64), smooth(v - j as f64));
                let g = |a: usize, b: usize| grid[b * gw + a];
                let n = (g(i, j) * (1.0 - fx) + g(i + 1, j) * fx) * (1.0 - fy) + (g(i, j + 1) * (1.0 - fx) + g(i + 1, j + 1) * fx) * fy;
                rgb[(y * width + x) * 3..][..3].fill((48.0 + contrast * n).round() as u8);
            }
        }
        (rgb, vec![96.0; width * height])
    }

    #[test]
    fn tracks_follow_texture_moved_by_the_step_and_to_sub_pixel() {
        let (w, h) = (320, 240);
        let mut tracker = Tracker::new(camera(), TrackParams::default());
        let (a, da) = textured(w, h, 0.0);
        tracker.add(TrackImage { rgb: &a, disparity: &da, width: w, height: h }, 0.0, None);
        let started = tracker.observations().len();
        assert!(started > 20, "{started} tracks started");
        // The texture moved 2.4 px right; the step predicts 2 px (a 0.4 px error to find).
        // The view's angle is unknown (NaN: a reading the turntable lost): tracked through.
        let (b, db) = textured(w, h, 2.4);
        let step = Isometry3::translation(2.0 * 500.0 / 800.0, 0.0, 0.0);
        tracker.add(TrackImage { rgb: &b, disparity: &db, width: w, height: h }, f64::NAN, Some(&step));
        let first: std::collections::HashMap<u32, TrackObs> = tracker.observations().iter().filter(|o| o.view == 0).map(|o| (o.track, *o)).collect();
        let moved: Vec<f64> = tracker.observations().iter().filter(|o| o.view == 1 && first.contains_key(&o.track)).map(|o| (o.x - first[&o.track].x) as f64).collect();
        assert!(moved.len() * 10 >= started * 8, "{} of {started} tracks followed", moved.len());
        let mut errs: Vec<f64> = moved.iter().map(|m| (m - 2.4).abs()).collect();
        errs.sort_by(f64::total_cmp);
        let worst = errs[errs.len() - 1];
        assert!(worst < 0.15, "shift found to within {worst} px");
        // A step the motion missed by 10 px (beyond the ±4 px search): the tracks are found
        // again from the shift a sample of them shows.
        let (c, dc) = textured(w, h, 12.4);
        tracker.add(TrackImage { rgb: &c, disparity: &dc, width: w, height: h }, 6.0, Some(&step));
        let followed = tracker.observations().iter().filter(|o| o.view == 2 && first.contains_key(&o.track)).count();
        assert!(followed * 10 >= moved.len() * 7, "{followed} of {} tracks found again", moved.len());
        // Without motion the tracks end; new ones start.
        tracker.add(TrackImage { rgb: &c, disparity: &dc, width: w, height: h }, 9.0, None);
        assert!(tracker.observations().iter().filter(|o| o.view == 3).all(|o| !first.contains_key(&o.track)));
        let angles = tracker.table_deg();
        assert!(angles.len() == 4 && angles[1].is_nan() && angles[0] == 0.0 && angles[2] == 6.0 && angles[3] == 9.0, "{angles:?}");
    }

    /// A faint texture, whose 5 × 5 corners all stay under `min_corner`: tracks start at the
    /// correlation window's corners while fewer than `sparse_tracks` are active — the
    /// strongest first, no more than that — and follow the texture as well as strong ones.
    #[test]
    fn a_faint_texture_starts_tracks_at_the_window_s_corners_while_they_are_sparse() {
        let (w, h) = (320, 240);
        let (a, da) = textured_with(w, h, 0.0, 18.0);
        let started = |params: TrackParams| {
            let mut tracker = Tracker::new(camera(), params);
            tracker.add(TrackImage { rgb: &a, disparity: &da, width: w, height: h }, 0.0, None);
            tracker
        };
        assert_eq!(started(TrackParams { sparse_tracks: 0, ..TrackParams::default() }).observations().len(), 0, "a strong corner in the faint texture");
        assert_eq!(started(TrackParams { faint_corner: 1e9, ..TrackParams::default() }).observations().len(), 0);
        assert_eq!(started(TrackParams { sparse_tracks: 25, ..TrackParams::default() }).observations().len(), 25);
        let mut tracker = started(TrackParams::default());
        assert_eq!(tracker.observations().len(), TrackParams::default().sparse_tracks);
        let (b, db) = textured_with(w, h, 2.4, 18.0);
        let step = Isometry3::translation(2.0 * 500.0 / 800.0, 0.0, 0.0);
        tracker.add(TrackImage { rgb: &b, disparity: &db, width: w, height: h }, 3.0, Some(&step));
        let first: std::collections::HashMap<u32, TrackObs> = tracker.observations().iter().filter(|o| o.view == 0).map(|o| (o.track, *o)).collect();
        let moved: Vec<f64> = tracker.observations().iter().filter(|o| o.view == 1 && first.contains_key(&o.track)).map(|o| (o.x - first[&o.track].x) as f64).collect();
        assert!(moved.len() * 10 >= first.len() * 8, "{} of {} faint tracks followed", moved.len(), first.len());
        let worst = moved.iter().map(|m| (m - 2.4).abs()).fold(0.0, f64::max);
        assert!(worst < 0.15, "shift found to within {worst} px");
    }
}
