//! Calibration targets in the simulated lab: a printed chessboard seen by both cameras
//! through the rig's lens model, held at chosen poses or standing on the turntable.
//!
//! The board frame has its origin at inner corner 0, x along a row of inner corners, y down
//! the rows, z into the board (its printed face looks towards −z). Square (i, j) — between
//! inner corners (i, j) and (i + 1, j + 1), i and j from −1 — is dark when i + j is even,
//! so the square beside corner 0 towards corner `cols + 1` is dark, as spinscan's detector
//! orders boards. A white margin of one square surrounds the squares; the board's edge
//! beyond that meets the lab's dark background.
//!
//! Each pixel averages 4 × 4 samples of the scene (the sensor integrating over its area),
//! through the lens (each sample's ray undistorted exactly), then the optics blur it
//! (Gaussian, σ 0.6 px) and the sensor adds noise.

use crate::math::{self, Pose, Rng, Vec3};
use crate::rig::{Intrinsics, Rig};

/// A printed chessboard.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chessboard {
    /// Inner corners along a row.
    pub cols: usize,
    /// Rows of inner corners.
    pub rows: usize,
    pub square_mm: f64,
}

impl Chessboard {
    /// Inner corner `(col, row)` in the board frame, mm.
    pub fn corner(&self, col: usize, row: usize) -> Vec3 {
        [col as f64 * self.square_mm, row as f64 * self.square_mm, 0.0]
    }

    /// The board's extent in its own frame (x0, y0, x1, y1), mm: squares plus margin.
    pub fn extent(&self) -> (f64, f64, f64, f64) {
        let s = self.square_mm;
        (-2.0 * s, -2.0 * s, (self.cols as f64 + 1.0) * s, (self.rows as f64 + 1.0) * s)
    }

    /// Reflectance at board point (x, y): dark squares 0.08, paper 0.85, `None` off the board.
    fn reflectance(&self, x: f64, y: f64) -> Option<f64> {
        let (x0, y0, x1, y1) = self.extent();
        if x < x0 || y < y0 || x > x1 || y > y1 {
            return None;
        }
        let s = self.square_mm;
        let (i, j) = ((x / s).floor() as i64, (y / s).floor() as i64);
        let squares = i >= -1 && j >= -1 && i < self.cols as i64 && j < self.rows as i64;
        Some(if squares && (i + j).rem_euclid(2) == 0 { 0.08 } else { 0.85 })
    }
}

/// Undistorted rays of every pixel centre of one camera (`z = 1`).
struct RayMap {
    width: usize,
    height: usize,
    rays: Vec<[f64; 2]>,
}

impl RayMap {
    fn new(k: &Intrinsics, width: usize, height: usize) -> RayMap {
        let rays = (0..height).flat_map(|v| (0..width).map(move |u| (u, v))).map(|(u, v)| {
            let (x, y) = k.undistort_pixel(u as f64, v as f64);
            [x, y]
        }).collect();
        RayMap { width, height, rays }
    }

    /// The ray through pixel position (u, v), interpolated between pixel centres.
    fn ray(&self, u: f64, v: f64) -> Vec3 {
        let (w, h) = (self.width as isize, self.height as isize);
        let (u0, v0) = (u.floor(), v.floor());
        let (fu, fv) = (u - u0, v - v0);
        let at = |x: isize, y: isize| self.rays[(y.clamp(0, h - 1) * w + x.clamp(0, w - 1)) as usize];
        let (x0, y0) = (u0 as isize, v0 as isize);
        let (a, b, c, d) = (at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1));
        let lerp = |k: usize| (a[k] * (1.0 - fu) + b[k] * fu) * (1.0 - fv) + (c[k] * (1.0 - fu) + d[k] * fu) * fv;
        [lerp(0), lerp(1), 1.0]
    }
}

/// Renders a chessboard for both cameras of a rig.
pub struct TargetRenderer {
    rig: Rig,
    left: RayMap,
    right: RayMap,
}

/// A rendered pair of target images (8-bit grey, raw camera images) and where the inner
/// corners truly are in each (pixels, row by row; `None` for a corner behind a camera).
#[derive(Debug, Clone)]
pub struct TargetPair {
    pub width: usize,
    pub height: usize,
    pub left: Vec<u8>,
    pub right: Vec<u8>,
    pub left_corners: Vec<Option<(f64, f64)>>,
    pub right_corners: Vec<Option<(f64, f64)>>,
}

impl TargetRenderer {
    pub fn new(rig: Rig) -> TargetRenderer {
        let left = RayMap::new(&rig.left, rig.width, rig.height);
        let right = RayMap::new(&rig.right, rig.width, rig.height);
        TargetRenderer { rig, left, right }
    }

    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// Both images of `board` at `left_from_board` (the board's pose in the LEFT camera
    /// frame), with sensor noise `noise_sigma` grey levels, deterministic for `seed`.
    pub fn render(&self, board: &Chessboard, left_from_board: &Pose, noise_sigma: f64, seed: u64) -> TargetPair {
        let right_from_board = self.rig.right_from_left.compose(left_from_board);
        let corners = |k: &Intrinsics, pose: &Pose| -> Vec<Option<(f64, f64)>> {
            (0..board.rows)
                .flat_map(|r| (0..board.cols).map(move |c| (c, r)))
                .map(|(c, r)| {
                    let p = pose.apply(board.corner(c, r));
                    (p[2] > 0.0).then(|| k.project(p))
                })
                .collect()
        };
        TargetPair {
            width: self.rig.width,
            height: self.rig.height,
            left: self.image(&self.left, board, left_from_board, noise_sigma, math::mix(seed)),
            right: self.image(&self.right, board, &right_from_board, noise_sigma, math::mix(seed ^ 0x5151)),
            left_corners: corners(&self.rig.left, left_from_board),
            right_corners: corners(&self.rig.right, &right_from_board),
        }
    }

    fn image(&self, rays: &RayMap, board: &Chessboard, cam_from_board: &Pose, noise_sigma: f64, seed: u64) -> Vec<u8> {
        let (w, h) = (rays.width, rays.height);
        // The board plane in the camera frame: n · X = d.
        let n = math::mat_vec(&cam_from_board.r, [0.0, 0.0, 1.0]);
        let d = math::dot(n, cam_from_board.t);
        let board_from_cam = cam_from_board.inverse();
        const SUB: usize = 4;
        let mut radiance = vec![0f64; w * h];
        for v in 0..h {
            for u in 0..w {
                let mut sum = 0.0;
                for sv in 0..SUB {
                    for su in 0..SUB {
                        let (pu, pv) = (u as f64 + (su as f64 + 0.5) / SUB as f64 - 0.5, v as f64 + (sv as f64 + 0.5) / SUB as f64 - 0.5);
                        let ray = rays.ray(pu, pv);
                        let denom = math::dot(n, ray);
                        let hit = if denom.abs() > 1e-12 { d / denom } else { -1.0 };
                        let value = if hit > 0.0 {
                            let q = board_from_cam.apply(math::scale(ray, hit));
                            // Light falls off slowly across the board (a lamp above and left).
                            board.reflectance(q[0], q[1]).map(|r| r * (0.9 + 0.1 * (1.0 - (q[0] + q[1]) / (board.square_mm * 20.0)).clamp(0.0, 1.0)))
                        } else {
                            None
                        };
                        // The lab beyond the board: a dim wall.
                        sum += value.unwrap_or(0.12 + 0.03 * (v as f64 / h as f64));
                    }
                }
                radiance[v * w + u] = 255.0 * sum / (SUB * SUB) as f64;
            }
        }
        let blurred = blur(&radiance, w, h, 0.6);
        let mut rng = Rng::new(seed);
        blurred.iter().map(|&x| (x + noise_sigma * f64::from(rng.gaussian())).round().clamp(0.0, 255.0) as u8).collect()
    }
}

fn blur(src: &[f64], w: usize, h: usize, sigma: f64) -> Vec<f64> {
    let r = (3.0 * sigma).ceil() as isize;
    let k: Vec<f64> = (-r..=r).map(|i| (-((i * i) as f64) / (2.0 * sigma * sigma)).exp()).collect();
    let s: f64 = k.iter().sum();
    let k: Vec<f64> = k.iter().map(|v| v / s).collect();
    let mut tmp = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            tmp[y * w + x] = k.iter().enumerate().map(|(i, kv)| kv * src[y * w + (x as isize + i as isize - r).clamp(0, w as isize - 1) as usize]).sum();
        }
    }
    let mut out = vec![0.0; w * h];
    for y in 0..h {
        for x in 0..w {
            out[y * w + x] = k.iter().enumerate().map(|(i, kv)| kv * tmp[(y as isize + i as isize - r).clamp(0, h as isize - 1) as usize * w + x]).sum();
        }
    }
    out
}

/// Poses for a stereo calibration: the board tilted up to ±35° about both of its axes and
/// turned in its plane, its centre placed over a 3 × 3 grid of the left image (so the boards
/// cover the image's edges and corners), `distance_mm` away, every corner seen by both
/// cameras with a margin. Deterministic for `seed`.
pub fn stereo_poses(rig: &Rig, board: &Chessboard, count: usize, distance_mm: f64, seed: u64) -> Vec<Pose> {
    let mut rng = Rng::new(seed);
    let mut out = Vec::new();
    let centre = [(board.cols as f64 - 1.0) * board.square_mm / 2.0, (board.rows as f64 - 1.0) * board.square_mm / 2.0, 0.0];
    let margin = 12.0;
    let inside = |k: &Intrinsics, p: Vec3| {
        if p[2] <= 0.0 {
            return false;
        }
        let (u, v) = k.project(p);
        u > margin && v > margin && u < rig.width as f64 - 1.0 - margin && v < rig.height as f64 - 1.0 - margin
    };
    let mut attempts = 0;
    while out.len() < count && attempts < count * 400 {
        // Slots in turn per attempt: one no pose can fill (the board too large for a corner
        // of both images) is skipped, not retried for ever.
        let slot = attempts % 9;
        attempts += 1;
        let (gx, gy) = ((slot % 3) as f64 - 1.0, (slot / 3) as f64 - 1.0);
        let z = distance_mm * (0.85 + 0.3 * rng.unit());
        // Where the board's centre should be: a third of the way from the centre to the edge
        // of the image per grid step, jittered.
        let u = rig.left.cx + gx * rig.width as f64 * (0.28 + 0.06 * rng.unit());
        let v = rig.left.cy + gy * rig.height as f64 * (0.26 + 0.06 * rng.unit());
        let (x, y) = rig.left.undistort_pixel(u, v);
        let tilt_x = (rng.unit() * 2.0 - 1.0) * 35f64.to_radians();
        let tilt_y = (rng.unit() * 2.0 - 1.0) * 35f64.to_radians();
        let roll = (rng.unit() * 2.0 - 1.0) * 25f64.to_radians();
        let r = math::mat_mul(&math::rotation([0.0, 1.0, 0.0], tilt_y), &math::mat_mul(&math::rotation([1.0, 0.0, 0.0], tilt_x), &math::rotation([0.0, 0.0, 1.0], roll)));
        let c = math::mat_vec(&r, centre);
        let pose = Pose { r, t: math::sub([x * z, y * z, z], c) };
        let right = rig.right_from_left.compose(&pose);
        let seen = (0..board.rows).all(|row| {
            (0..board.cols).all(|col| {
                let p = board.corner(col, row);
                inside(&rig.left, pose.apply(p)) && inside(&rig.right, right.apply(p))
            })
        });
        if seen {
            out.push(pose);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_dark_square_beside_corner_zero_is_dark_in_the_image() {
        let rig = Rig::ideal(320, 240, 350.0, 60.0);
        let board = Chessboard { cols: 7, rows: 5, square_mm: 20.0 };
        let pose = Pose { r: math::IDENTITY, t: [-60.0, -40.0, 400.0] };
        let pair = TargetRenderer::new(rig).render(&board, &pose, 0.0, 1);
        let at = |p: (f64, f64)| pair.left[p.1.round() as usize * 320 + p.0.round() as usize];
        let c0 = pair.left_corners[0].unwrap();
        let c8 = pair.left_corners[board.cols + 1].unwrap();
        let mid = ((c0.0 + c8.0) / 2.0, (c0.1 + c8.1) / 2.0);
        let next = pair.left_corners[2].unwrap();
        let beside = ((pair.left_corners[1].unwrap().0 + next.0) / 2.0, mid.1);
        assert!(at(mid) < 60 && at(beside) > 150, "{} {}", at(mid), at(beside));
    }

    #[test]
    fn stereo_poses_keep_every_corner_in_both_images() {
        let rig = Rig::realistic(640, 480, 700.0, 60.0);
        let board = Chessboard { cols: 9, rows: 6, square_mm: 20.0 };
        let poses = stereo_poses(&rig, &board, 12, 600.0, 3);
        assert_eq!(poses.len(), 12);
    }
}
