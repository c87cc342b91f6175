//! Simulated lab hardware for spinscan: a stereo camera pair looking at a textured object in
//! front of a blue screen, rendered by ray casting, deterministic for a seed.
//!
//! This crate knows nothing of spinscan (the dependency points the other way): it produces
//! images and ground truth, spinscan consumes them through its device seam.
//!
//! ```text
//!   scene (object pose, texture, light) --ray cast--> left/right RGB + ground-truth disparity
//! ```
//!
//! The rig is the ideal rectified one: identical pinhole cameras, parallel axes, the right
//! camera `baseline_mm` to the right of the left one, so `X_right = X_left + T` with
//! `T = (−baseline, 0, 0)` and the disparity of a point at depth Z is `f · B / Z`.

/// What sits on the turntable.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// A sphere of this radius (mm).
    Sphere { radius_mm: f64 },
    /// An ellipsoid with these semi-axes (mm): x and z horizontal, y vertical.
    Ellipsoid { semi_axes_mm: [f64; 3] },
}

impl Shape {
    /// The built-in shapes by name, for command lines.
    pub const NAMES: [&'static str; 2] = ["sphere", "egg"];

    /// Looks a built-in shape up by name.
    pub fn by_name(name: &str) -> Option<Shape> {
        match name {
            "sphere" => Some(Shape::Sphere { radius_mm: 70.0 }),
            "egg" => Some(Shape::Ellipsoid { semi_axes_mm: [60.0, 80.0, 55.0] }),
            _ => None,
        }
    }
}

/// Everything that determines a rendered pair.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneConfig {
    pub width: usize,
    pub height: usize,
    /// Focal length of both cameras, pixels.
    pub focal_px: f64,
    pub baseline_mm: f64,
    pub shape: Shape,
    /// Depth of the object's centre in the left camera frame, mm.
    pub object_depth_mm: f64,
    /// Depth of the blue screen, mm.
    pub screen_depth_mm: f64,
    /// Rotation of the object about the vertical axis through its centre, degrees,
    /// counterclockwise seen from above.
    pub table_deg: f64,
    /// Contrast of the procedural surface texture, 0 (plain) … 1.
    pub texture_contrast: f64,
    /// Standard deviation of the sensor noise, grey levels.
    pub noise_sigma: f64,
    pub seed: u64,
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig {
            width: 640,
            height: 480,
            focal_px: 700.0,
            baseline_mm: 60.0,
            shape: Shape::Sphere { radius_mm: 70.0 },
            object_depth_mm: 450.0,
            screen_depth_mm: 700.0,
            table_deg: 0.0,
            texture_contrast: 0.8,
            noise_sigma: 1.5,
            seed: 1,
        }
    }
}

/// One rendered stereo pair with its ground truth.
#[derive(Debug, Clone)]
pub struct StereoPair {
    pub width: usize,
    pub height: usize,
    /// Interleaved RGB.
    pub left_rgb: Vec<u8>,
    pub right_rgb: Vec<u8>,
    /// Left-image disparity `x_left − x_right` where the object is visible, NaN elsewhere.
    pub gt_disparity: Vec<f32>,
}

impl SceneConfig {
    /// Principal point: the image centre (pixel centres at integers).
    pub fn principal_point(&self) -> (f64, f64) {
        ((self.width as f64 - 1.0) / 2.0, (self.height as f64 - 1.0) / 2.0)
    }

    /// Renders the pair.
    pub fn render(&self) -> StereoPair {
        let (w, h) = (self.width, self.height);
        let mut left_rgb = vec![0u8; w * h * 3];
        let mut right_rgb = vec![0u8; w * h * 3];
        let mut gt = vec![f32::NAN; w * h];
        for (cam, img) in [(0usize, &mut left_rgb), (1, &mut right_rgb)] {
            let origin_x = if cam == 0 { 0.0 } else { self.baseline_mm };
            for y in 0..h {
                for x in 0..w {
                    let (colour, depth) = self.shade_pixel(origin_x, x as f64, y as f64);
                    let noise_seed = self.seed ^ ((cam as u64) << 40) ^ ((y * w + x) as u64).wrapping_mul(0x9E37_79B9);
                    for c in 0..3 {
                        let v = colour[c] + self.noise_sigma * gaussian(noise_seed.wrapping_add(c as u64 * 0x51_7CC1));
                        img[(y * w + x) * 3 + c] = v.round().clamp(0.0, 255.0) as u8;
                    }
                    if cam == 0 {
                        if let Some(z) = depth {
                            gt[y * w + x] = (self.focal_px * self.baseline_mm / z) as f32;
                        }
                    }
                }
            }
        }
        StereoPair { width: w, height: h, left_rgb, right_rgb, gt_disparity: gt }
    }

    /// Colour seen through pixel `(u, v)` of the camera at `(origin_x, 0, 0)`, and the depth
    /// of the object point if the ray hits the object.
    fn shade_pixel(&self, origin_x: f64, u: f64, v: f64) -> ([f64; 3], Option<f64>) {
        let (cx, cy) = self.principal_point();
        let dir = [(u - cx) / self.focal_px, (v - cy) / self.focal_px, 1.0];
        let centre = [0.0, 0.0, self.object_depth_mm];
        // The object turns with the table about the vertical axis through its centre: ray
        // and shape meet in the object's own frame.
        let (s, c) = self.table_deg.to_radians().sin_cos();
        let obj_from_cam = |q: [f64; 3]| [c * q[0] + s * q[2], q[1], -s * q[0] + c * q[2]];
        let cam_from_obj = |q: [f64; 3]| [c * q[0] - s * q[2], q[1], s * q[0] + c * q[2]];
        let origin = obj_from_cam([origin_x - centre[0], -centre[1], -centre[2]]);
        if let Some((t, normal_obj)) = self.intersect(origin, obj_from_cam(dir), [0.0; 3]) {
            let normal = cam_from_obj(normal_obj);
            let p = [origin_x + t * dir[0], t * dir[1], t * dir[2]];
            // Texture lives on the object.
            let obj = obj_from_cam([p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]]);
            let tex = 1.0 + self.texture_contrast * (fbm(obj, self.seed) - 0.5) * 1.6;
            // Light from above-left-front; y points down in camera coordinates.
            let l = normalize([-0.4, -0.6, -0.7]);
            let lambert = (normal[0] * l[0] + normal[1] * l[1] + normal[2] * l[2]).max(0.0);
            let shade = 0.25 + 0.75 * lambert;
            let albedo = [190.0, 160.0, 120.0];
            let colour = albedo.map(|a| (a * tex * shade).clamp(0.0, 255.0));
            return (colour, Some(p[2]));
        }
        // The blue screen, lit a little unevenly.
        let t = self.screen_depth_mm;
        let py = t * dir[1];
        let shade = 0.85 + 0.15 * (1.0 - (py / 400.0).abs()).clamp(0.0, 1.0);
        ([40.0 * shade, 70.0 * shade, 190.0 * shade], None)
    }

    /// Ray–object intersection in the object's frame (shape centred at `centre`): the ray
    /// parameter along `dir` and the outward unit normal.
    fn intersect(&self, o: [f64; 3], dir: [f64; 3], centre: [f64; 3]) -> Option<(f64, [f64; 3])> {
        let semi = match self.shape {
            Shape::Sphere { radius_mm } => [radius_mm; 3],
            Shape::Ellipsoid { semi_axes_mm } => semi_axes_mm,
        };
        // Scale space so the ellipsoid becomes the unit sphere.
        let oc = [(o[0] - centre[0]) / semi[0], (o[1] - centre[1]) / semi[1], (o[2] - centre[2]) / semi[2]];
        let d = [dir[0] / semi[0], dir[1] / semi[1], dir[2] / semi[2]];
        let a = dot(d, d);
        let b = 2.0 * dot(oc, d);
        let c = dot(oc, oc) - 1.0;
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return None;
        }
        let t = (-b - disc.sqrt()) / (2.0 * a);
        if t <= 0.0 {
            return None;
        }
        let p = [oc[0] + t * d[0], oc[1] + t * d[1], oc[2] + t * d[2]];
        let n = normalize([p[0] / semi[0], p[1] / semi[1], p[2] / semi[2]]);
        Some((t, n))
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// SplitMix64: a well-mixed hash of one word.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn unit(z: u64) -> f64 {
    (mix(z) >> 11) as f64 / (1u64 << 53) as f64
}

/// An approximately standard normal sample from a hash (Irwin–Hall with 4 terms).
fn gaussian(seed: u64) -> f64 {
    let s: f64 = (0..4).map(|i| unit(seed.wrapping_mul(4).wrapping_add(i))).sum();
    (s - 2.0) * (3.0f64).sqrt()
}

/// Trilinear value noise on a 1-unit lattice, in 0…1.
fn value_noise(p: [f64; 3], seed: u64) -> f64 {
    let f = p.map(f64::floor);
    let t = [p[0] - f[0], p[1] - f[1], p[2] - f[2]].map(|t| t * t * (3.0 - 2.0 * t));
    let corner = |dx: i64, dy: i64, dz: i64| {
        let (x, y, z) = (f[0] as i64 + dx, f[1] as i64 + dy, f[2] as i64 + dz);
        unit(seed ^ (x as u64).wrapping_mul(0x8DA6_B343) ^ (y as u64).wrapping_mul(0xD816_3841) ^ (z as u64).wrapping_mul(0xCB1A_B31F))
    };
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), t[0]);
    let x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), t[0]);
    let x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), t[0]);
    let x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), t[0]);
    lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
}

/// Fractal noise over object coordinates in mm: features from ~2 to ~16 mm, in 0…1.
fn fbm(p: [f64; 3], seed: u64) -> f64 {
    let mut sum = 0.0;
    let mut amp = 0.5;
    let mut scale = 1.0 / 16.0;
    let mut norm = 0.0;
    for octave in 0..4 {
        sum += amp * value_noise(p.map(|v| v * scale), seed.wrapping_add(octave));
        norm += amp;
        amp *= 0.6;
        scale *= 2.0;
    }
    sum / norm
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> SceneConfig {
        SceneConfig { width: 160, height: 120, focal_px: 175.0, ..Default::default() }
    }

    #[test]
    fn deterministic_for_a_seed() {
        let a = small().render();
        let b = small().render();
        assert_eq!(a.left_rgb, b.left_rgb);
        let c = SceneConfig { seed: 2, ..small() }.render();
        assert_ne!(a.left_rgb, c.left_rgb);
    }

    #[test]
    fn ground_truth_disparity_is_f_b_over_z() {
        let cfg = small();
        let pair = cfg.render();
        let (cx, cy) = cfg.principal_point();
        // The centre pixel sees the sphere's nearest point at depth 450 − 70 = 380 mm.
        let d = pair.gt_disparity[cy.round() as usize * cfg.width + cx.round() as usize];
        let expect = cfg.focal_px * cfg.baseline_mm / 380.0;
        assert!((d as f64 - expect).abs() < 0.05, "{d} vs {expect}");
        assert!(pair.gt_disparity[0].is_nan(), "corners see the screen");
    }

    #[test]
    fn the_object_turns_with_the_table() {
        // An egg wider along x than z: a quarter turn shows its narrow side.
        let egg = SceneConfig { shape: Shape::Ellipsoid { semi_axes_mm: [80.0, 60.0, 40.0] }, ..small() };
        let width = |cfg: SceneConfig| cfg.render().gt_disparity[60 * 160..61 * 160].iter().filter(|d| d.is_finite()).count();
        let (front, side) = (width(egg.clone()), width(SceneConfig { table_deg: 90.0, ..egg }));
        assert!(front as f64 > 1.5 * side as f64, "{front} vs {side} pixels across");
    }

    #[test]
    fn right_image_matches_left_shifted_by_ground_truth() {
        // Warping the right image by the true disparity reproduces the left image up to
        // sensor noise, on pixels visible in both.
        let cfg = SceneConfig { noise_sigma: 0.0, ..small() };
        let pair = cfg.render();
        let (w, h) = (pair.width, pair.height);
        let (mut err, mut count) = (0.0, 0);
        for y in 0..h {
            for x in 0..w {
                let d = pair.gt_disparity[y * w + x];
                if !d.is_finite() {
                    continue;
                }
                let xr = x as f64 - d as f64;
                let x0 = xr.floor() as usize;
                let f = xr - x0 as f64;
                if x0 + 1 >= w || pair.gt_disparity.get(y * w + x + 2).is_none_or(|v| v.is_nan()) || x < 2 {
                    continue;
                }
                let l = pair.left_rgb[(y * w + x) * 3 + 1] as f64;
                let r = pair.right_rgb[(y * w + x0) * 3 + 1] as f64 * (1.0 - f) + pair.right_rgb[(y * w + x0 + 1) * 3 + 1] as f64 * f;
                err += (l - r).abs();
                count += 1;
            }
        }
        assert!(count > 1000);
        assert!(err / (count as f64) < 4.0, "mean error {}", err / count as f64);
    }
}
