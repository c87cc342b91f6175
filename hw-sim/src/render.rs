//! The renderer: a z-buffer rasterizer with deferred Lambertian shading.
//!
//! ```text
//!  mesh (object frame) --cam_from_obj--> screen triangles --z-buffer--> (triangle, 1/Z) per pixel
//!     --shade: perspective-correct barycentrics → object point → texture, normal → Lambert-->
//!  pinhole canvas --lens remap (distorted rigs only)--> raw image --sensor noise--> RGB
//! ```
//!
//! Scene geometry: the turntable frame has `+y` up, its origin on the rotation axis at the
//! table's surface. The object stands on the table with its bounding box centred on the
//! axis; it turns with the table by `Rot(up, table_deg)` (counterclockwise seen from above).
//! The left camera looks down at the object's mid-height on the axis from
//! `object_distance_mm` away, tilted `camera_tilt_deg` below the horizontal. Behind the object
//! is a blue screen; the table top is covered in the same blue, as labs do it.

use crate::math::{self, normalize, rotation, Mat3, Pose, Rng, Vec3};
use crate::mesh::{Mesh, MeshError};
use crate::rig::{Intrinsics, Rig};

/// Everything that fixes what the cameras see.
#[derive(Debug, Clone)]
pub struct SceneConfig {
    pub rig: Rig,
    /// The object, in its own frame (mm, `+y` up).
    pub object: Mesh,
    /// Distance from the left camera to the object's centre, mm.
    pub object_distance_mm: f64,
    /// How far the cameras look down, degrees below the horizontal.
    pub camera_tilt_deg: f64,
    pub table_radius_mm: f64,
    /// Where the object's bounding box stands on the table, off the axis: (x, z) in the
    /// table's frame, mm (0, 0: centred, as a careful user places it).
    pub object_offset_mm: [f64; 2],
    /// Contrast of the procedural surface texture, 0 (plain) … 1.
    pub texture_contrast: f64,
    /// Standard deviation of the sensor noise, grey levels.
    pub noise_sigma: f64,
    pub seed: u64,
}

/// Colour of the blue screen at full light; keyed out by spinscan's default chroma key.
pub const SCREEN_RGB: [f64; 3] = [40.0, 70.0, 190.0];
const TABLE_RGB: [f64; 3] = [36.0, 64.0, 176.0];
const OBJECT_RGB: [f64; 3] = [196.0, 164.0, 124.0];
const TABLE_THICKNESS_MM: f64 = 14.0;
/// Towards the lab's one light, in the left camera's frame (x right, y down, z forward): from
/// the upper left, on the cameras' side of the object (normalised where used).
const LIGHT_LEFT: Vec3 = [-0.4, -0.6, -0.7];

impl SceneConfig {
    /// The default lab (640×480, f = 700 px, 60 mm baseline, object 450 mm away) with this
    /// object, on the ideal rectified rig.
    pub fn ideal(object: Mesh) -> SceneConfig {
        SceneConfig {
            rig: Rig::ideal(640, 480, 700.0, 60.0),
            object,
            object_distance_mm: 450.0,
            camera_tilt_deg: 12.0,
            table_radius_mm: 115.0,
            object_offset_mm: [0.0, 0.0],
            texture_contrast: 0.8,
            noise_sigma: 1.5,
            seed: 1,
        }
    }

    /// The default lab on a realistic rig (distortion, misalignment).
    pub fn realistic(object: Mesh) -> SceneConfig {
        SceneConfig { rig: Rig::realistic(640, 480, 700.0, 60.0), ..SceneConfig::ideal(object) }
    }

    /// Maps table points into the left camera frame (fixed for the scene).
    pub fn cam_from_table(&self) -> Pose {
        let (lo, hi) = self.object.bounds();
        let target = [0.0, (hi[1] - lo[1]) / 2.0, 0.0];
        let t = self.camera_tilt_deg.to_radians();
        // Camera axes in table coordinates: x right, y down, z forward (looking down at the
        // object from the +z side).
        let x = [1.0, 0.0, 0.0];
        let y = [0.0, -t.cos(), t.sin()];
        let z = [0.0, -t.sin(), -t.cos()];
        let r: Mat3 = [x, y, z];
        let centre = math::sub(target, math::scale(z, self.object_distance_mm));
        Pose { r, t: math::scale(math::mat_vec(&r, centre), -1.0) }
    }

    /// Maps object points into the table frame: the bounding box centred on the axis (or
    /// `object_offset_mm` off it), standing on the table surface.
    pub fn table_from_obj(&self) -> Pose {
        let (lo, hi) = self.object.bounds();
        let [dx, dz] = self.object_offset_mm;
        Pose { r: math::IDENTITY, t: [dx - (lo[0] + hi[0]) / 2.0, -lo[1], dz - (lo[2] + hi[2]) / 2.0] }
    }

    /// The turntable axis in the LEFT camera frame: a point on it (the table centre, mm) and
    /// the unit direction pointing up.
    pub fn axis_in_left_camera(&self) -> (Vec3, Vec3) {
        let p = self.cam_from_table();
        (p.t, math::mat_vec(&p.r, [0.0, 1.0, 0.0]))
    }

    /// `cam_from_obj(θ) = cam_from_table · Rot(up, θ) · table_from_obj`, LEFT camera.
    pub fn cam_from_obj(&self, table_deg: f64) -> Pose {
        let turn = Pose { r: rotation([0.0, 1.0, 0.0], table_deg.to_radians()), t: [0.0; 3] };
        self.cam_from_table().compose(&turn).compose(&self.table_from_obj())
    }
}

/// One rendered stereo pair.
#[derive(Debug, Clone)]
pub struct RenderedPair {
    pub width: usize,
    pub height: usize,
    /// Interleaved RGB, raw (distorted) camera images.
    pub left_rgb: Vec<u8>,
    pub right_rgb: Vec<u8>,
    /// Left-image disparity `x_left − x_right` where the object is visible, NaN elsewhere
    /// (the table and the screen are not the object). Only for the ideal rig.
    pub gt_disparity: Option<Vec<f32>>,
    /// Maps object points into the LEFT raw camera frame, mm.
    pub cam_from_obj: Pose,
}

/// Per-camera rendering state: the pinhole canvas and, for a lens with distortion, where
/// each raw pixel samples it.
struct CameraView {
    canvas: Intrinsics,
    canvas_w: usize,
    canvas_h: usize,
    /// For distorted cameras: per raw pixel, the canvas index of the top-left neighbour and
    /// bilinear weights in 1/256.
    remap: Option<Vec<(u32, u8, u8)>>,
    depth: Vec<f32>,
    triangle: Vec<u32>,
    colour: Vec<[f32; 3]>,
    screen: Vec<[f32; 3]>,
}

const NO_TRIANGLE: u32 = u32::MAX;

impl CameraView {
    fn new(k: &Intrinsics, width: usize, height: usize) -> CameraView {
        if k.is_pinhole() {
            return CameraView::with_canvas(*k, width, height, None);
        }
        // The canvas is a pinhole camera with the same focal lengths covering every ray the
        // distorted camera sees, plus a one-pixel margin for bilinear sampling.
        let rays: Vec<(f64, f64)> = (0..height).flat_map(|v| (0..width).map(move |u| (u, v))).map(|(u, v)| k.undistort_pixel(u as f64, v as f64)).collect();
        let (mut xmin, mut xmax, mut ymin, mut ymax) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        for &(x, y) in &rays {
            xmin = xmin.min(x);
            xmax = xmax.max(x);
            ymin = ymin.min(y);
            ymax = ymax.max(y);
        }
        let canvas = Intrinsics { fx: k.fx, fy: k.fy, cx: -xmin * k.fx + 1.0, cy: -ymin * k.fy + 1.0, distortion: [0.0; 5] };
        let cw = ((xmax - xmin) * k.fx).ceil() as usize + 3;
        let ch = ((ymax - ymin) * k.fy).ceil() as usize + 3;
        let remap = rays
            .iter()
            .map(|&(x, y)| {
                let (cu, cv) = (canvas.fx * x + canvas.cx, canvas.fy * y + canvas.cy);
                let (iu, iv) = (cu.floor(), cv.floor());
                let wx = ((cu - iu) * 256.0).round().min(255.0) as u8;
                let wy = ((cv - iv) * 256.0).round().min(255.0) as u8;
                ((iv as usize * cw + iu as usize) as u32, wx, wy)
            })
            .collect();
        CameraView::with_canvas(canvas, cw, ch, Some(remap))
    }

    fn with_canvas(canvas: Intrinsics, canvas_w: usize, canvas_h: usize, remap: Option<Vec<(u32, u8, u8)>>) -> CameraView {
        let n = canvas_w * canvas_h;
        CameraView {
            canvas,
            canvas_w,
            canvas_h,
            remap,
            depth: vec![0.0; n],
            triangle: vec![NO_TRIANGLE; n],
            colour: vec![[0.0; 3]; n],
            screen: Vec::new(),
        }
    }
}

/// Renders stereo pairs of one scene; reuses its buffers from frame to frame.
pub struct Renderer {
    scene: SceneConfig,
    /// Object triangles first, then the table's.
    vertices: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
    object_triangles: usize,
    /// Skip triangles facing away from the camera: the object is closed (and the table is
    /// only ever seen from above), so they are always hidden.
    cull_object: bool,
    views: [CameraView; 2],
    texture: Texture,
    /// Standard normal samples that sensor noise is drawn from (see [`NoiseStream`]).
    gaussians: Vec<f32>,
}

impl Renderer {
    pub fn new(scene: SceneConfig) -> Result<Renderer, MeshError> {
        scene.object.validate()?;
        let mut vertices = scene.object.vertices.clone();
        let mut normals = scene.object.vertex_normals();
        let mut triangles = scene.object.triangles.clone();
        let object_triangles = triangles.len();
        let cull_object = scene.object.is_closed();
        // The table, built in the table frame and carried into the object frame, since
        // both turn together.
        let obj_from_table = scene.table_from_obj().inverse();
        let table = table_mesh(scene.table_radius_mm, 96);
        let table_normals = table.vertex_normals();
        let base = vertices.len() as u32;
        for (v, n) in table.vertices.iter().zip(&table_normals) {
            vertices.push(obj_from_table.apply(v.map(f64::from)).map(|c| c as f32));
            normals.push(math::mat_vec(&obj_from_table.r, n.map(f64::from)).map(|c| c as f32));
        }
        triangles.extend(table.triangles.iter().map(|t| t.map(|i| i + base)));
        let rig = scene.rig;
        let views = [CameraView::new(&rig.left, rig.width, rig.height), CameraView::new(&rig.right, rig.width, rig.height)];
        let texture = Texture::new(scene.seed);
        let mut rng = Rng::new(scene.seed ^ 0x6A05_5E);
        let gaussians = (0..NOISE_TABLE).map(|_| rng.gaussian()).collect();
        Ok(Renderer { scene, vertices, normals, triangles, object_triangles, cull_object, views, texture, gaussians })
    }

    pub fn scene(&self) -> &SceneConfig {
        &self.scene
    }

    /// Renders both cameras with the table at `table_deg`. `frame` seeds the sensor noise.
    pub fn render(&mut self, table_deg: f64, frame: u64) -> RenderedPair {
        let rig = self.scene.rig;
        let cam_from_obj = self.scene.cam_from_obj(table_deg);
        let right_from_obj = rig.right_from_left.compose(&cam_from_obj);
        let mut images = [Vec::new(), Vec::new()];
        let mut gt = None;
        // One light for the lab, fixed with the rig (given in the left camera's frame): each
        // camera sees the same Lambertian shading, whatever the angle between the two.
        let light_left = normalize(LIGHT_LEFT);
        let lights = [light_left, math::mat_vec(&rig.right_from_left.r, light_left)];
        for (cam, pose) in [(0usize, cam_from_obj), (1, right_from_obj)] {
            self.rasterize(cam, &pose);
            self.shade(cam, &pose, lights[cam]);
            if cam == 0 && rig.is_ideal() {
                gt = Some(self.ground_truth_disparity());
            }
            images[cam] = self.develop(cam, frame);
        }
        let [left_rgb, right_rgb] = images;
        RenderedPair { width: rig.width, height: rig.height, left_rgb, right_rgb, gt_disparity: gt, cam_from_obj }
    }

    /// The empty scene (table and screen, no object): a background plate for segmentation.
    pub fn render_plate(&mut self, table_deg: f64, frame: u64) -> RenderedPair {
        let object = std::mem::replace(&mut self.object_triangles, 0);
        let triangles = self.triangles.split_off(object);
        let kept = std::mem::replace(&mut self.triangles, triangles);
        let mut pair = self.render(table_deg, frame);
        let mut tail = std::mem::replace(&mut self.triangles, kept);
        self.triangles.append(&mut tail);
        self.object_triangles = object;
        pair.gt_disparity = pair.gt_disparity.map(|g| vec![f32::NAN; g.len()]);
        pair
    }

    /// Z-buffer pass: the nearest triangle and its 1/Z at every canvas pixel centre.
    fn rasterize(&mut self, cam: usize, pose: &Pose) {
        let view = &mut self.views[cam];
        let k = view.canvas;
        view.depth.fill(0.0);
        view.triangle.fill(NO_TRIANGLE);
        view.screen.clear();
        let r = pose.r.map(|row| row.map(|c| c as f32));
        let t = pose.t.map(|c| c as f32);
        let (fx, fy, cx, cy) = (k.fx as f32, k.fy as f32, k.cx as f32, k.cy as f32);
        view.screen.extend(self.vertices.iter().map(|v| {
            let z = r[2][0] * v[0] + r[2][1] * v[1] + r[2][2] * v[2] + t[2];
            let x = r[0][0] * v[0] + r[0][1] * v[1] + r[0][2] * v[2] + t[0];
            let y = r[1][0] * v[0] + r[1][1] * v[1] + r[1][2] * v[2] + t[1];
            let iz = if z > 1.0 { 1.0 / z } else { f32::NAN };
            [fx * x * iz + cx, fy * y * iz + cy, iz]
        }));
        let (w, h) = (view.canvas_w as i64, view.canvas_h as i64);
        for (id, tri) in self.triangles.iter().enumerate() {
            let [a, b, c] = tri.map(|i| view.screen[i as usize]);
            if !(a[2] > 0.0 && b[2] > 0.0 && c[2] > 0.0) {
                continue; // behind the camera
            }
            let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
            if area.abs() < 1e-9 {
                continue;
            }
            // Image y points down, so a triangle wound counterclockwise seen from outside
            // has negative area when it faces the camera.
            if area > 0.0 && (self.cull_object || id >= self.object_triangles) {
                continue;
            }
            let inv_area = 1.0 / area;
            let x0 = (-fast_floor(-a[0].min(b[0]).min(c[0])) as i64).max(0);
            let x1 = (fast_floor(a[0].max(b[0]).max(c[0])) as i64).min(w - 1);
            let y0 = (-fast_floor(-a[1].min(b[1]).min(c[1])) as i64).max(0);
            let y1 = (fast_floor(a[1].max(b[1]).max(c[1])) as i64).min(h - 1);
            for py in y0..=y1 {
                let fy = py as f32;
                for px in x0..=x1 {
                    let fx = px as f32;
                    let wa = ((c[0] - b[0]) * (fy - b[1]) - (c[1] - b[1]) * (fx - b[0])) * inv_area;
                    let wb = ((a[0] - c[0]) * (fy - c[1]) - (a[1] - c[1]) * (fx - c[0])) * inv_area;
                    let wc = 1.0 - wa - wb;
                    if wa < 0.0 || wb < 0.0 || wc < 0.0 {
                        continue;
                    }
                    let iz = wa * a[2] + wb * b[2] + wc * c[2];
                    let i = (py * w + px) as usize;
                    if iz > view.depth[i] {
                        view.depth[i] = iz;
                        view.triangle[i] = id as u32;
                    }
                }
            }
        }
    }

    /// Shading pass: colour of every canvas pixel, without noise. `light`: the direction
    /// towards the light in this camera's frame.
    fn shade(&mut self, cam: usize, pose: &Pose, light: Vec3) {
        let view = &mut self.views[cam];
        let contrast = self.scene.texture_contrast as f32;
        let r = pose.r;
        let w = view.canvas_w;
        let k = view.canvas;
        // The blue screen, lit a little unevenly from above: one colour per canvas row.
        let screen_rows: Vec<[f32; 3]> = (0..view.canvas_h)
            .map(|v| {
                let ray_y = (v as f64 - k.cy) / k.fy;
                let shade = 0.85 + 0.15 * (1.0 - (ray_y / 0.6).abs()).clamp(0.0, 1.0);
                SCREEN_RGB.map(|c| (c * shade) as f32)
            })
            .collect();
        for i in 0..w * view.canvas_h {
            let id = view.triangle[i];
            if id == NO_TRIANGLE {
                view.colour[i] = screen_rows[i / w];
                continue;
            }
            let tri = self.triangles[id as usize];
            let [a, b, c] = tri.map(|j| view.screen[j as usize]);
            let (fx, fy) = ((i % w) as f32, (i / w) as f32);
            let area = (b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]);
            let wa = ((c[0] - b[0]) * (fy - b[1]) - (c[1] - b[1]) * (fx - b[0])) / area;
            let wb = ((a[0] - c[0]) * (fy - c[1]) - (a[1] - c[1]) * (fx - c[0])) / area;
            let wc = 1.0 - wa - wb;
            // Perspective-correct weights: screen weights scaled by 1/Z, renormalised.
            let iz = view.depth[i];
            let (la, lb, lc) = (wa * a[2] / iz, wb * b[2] / iz, wc * c[2] / iz);
            let lerp = |p: [[f32; 3]; 3]| -> Vec3 { std::array::from_fn(|d| (la * p[0][d] + lb * p[1][d] + lc * p[2][d]) as f64) };
            let n_obj = lerp(tri.map(|j| self.normals[j as usize]));
            let mut n = normalize(math::mat_vec(&r, n_obj));
            let p_obj = lerp(tri.map(|j| self.vertices[j as usize]));
            // Light both faces of open meshes (a scan with holes shows its inside).
            let to_cam = math::scale(pose.apply(p_obj), -1.0);
            if math::dot(n, to_cam) < 0.0 {
                n = math::scale(n, -1.0);
            }
            let lambert = math::dot(n, light).max(0.0);
            let shade = 0.3 + 0.7 * lambert;
            view.colour[i] = if (id as usize) < self.object_triangles {
                let tex = 1.0 + contrast * (self.texture.fbm(p_obj) - 0.5) * 1.6;
                OBJECT_RGB.map(|c| (c * shade) as f32 * tex)
            } else {
                TABLE_RGB.map(|c| (c * shade) as f32)
            };
        }
    }

    fn ground_truth_disparity(&self) -> Vec<f32> {
        let view = &self.views[0];
        let rig = &self.scene.rig;
        let fb = (rig.left.fx * rig.baseline_mm()) as f32;
        view.triangle
            .iter()
            .zip(&view.depth)
            .map(|(&id, &iz)| if (id as usize) < self.object_triangles { fb * iz } else { f32::NAN })
            .collect()
    }

    /// Canvas → raw image (lens remap where the camera has distortion) + sensor noise.
    fn develop(&self, cam: usize, frame: u64) -> Vec<u8> {
        let view = &self.views[cam];
        let (w, h) = (self.scene.rig.width, self.scene.rig.height);
        let sigma = self.scene.noise_sigma as f32;
        let mut noise = NoiseStream::new(self.scene.seed ^ frame.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ ((cam as u64 + 1) << 56), &self.gaussians);
        let mut out = vec![0u8; w * h * 3];
        let mut put = |i: usize, colour: [f32; 3]| {
            for c in 0..3 {
                let v = colour[c] + sigma * noise.next();
                // Round half up and saturate (`as` saturates float → int casts).
                out[i * 3 + c] = (v + 0.5).max(0.0) as u8;
            }
        };
        match &view.remap {
            None => {
                for i in 0..w * h {
                    put(i, view.colour[i]);
                }
            }
            Some(remap) => {
                let cw = view.canvas_w;
                for (i, &(base, wx, wy)) in remap.iter().enumerate() {
                    let base = base as usize;
                    let (fx, fy) = (wx as f32 / 256.0, wy as f32 / 256.0);
                    let p = |j: usize| view.colour[j];
                    let (c00, c01, c10, c11) = (p(base), p(base + 1), p(base + cw), p(base + cw + 1));
                    let colour = std::array::from_fn(|c| {
                        let top = c00[c] + (c01[c] - c00[c]) * fx;
                        let bottom = c10[c] + (c11[c] - c10[c]) * fx;
                        top + (bottom - top) * fy
                    });
                    put(i, colour);
                }
            }
        }
        out
    }
}

/// `floor` without a libm call (the baseline x86-64 target has no rounding instruction).
fn fast_floor(x: f32) -> f32 {
    let t = x as i32 as f32;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

const NOISE_TABLE: usize = 1 << 12;

/// Per-pixel sensor noise: five 12-bit indices into a table of normal samples per random
/// word, about five times cheaper than drawing each sample (noise is a third of a frame's
/// work otherwise). Consecutive pixels get independent indices, so the pattern does not
/// repeat visibly.
struct NoiseStream<'a> {
    rng: Rng,
    word: u64,
    left: u32,
    table: &'a [f32],
}

impl<'a> NoiseStream<'a> {
    fn new(seed: u64, table: &'a [f32]) -> NoiseStream<'a> {
        NoiseStream { rng: Rng::new(seed), word: 0, left: 0, table }
    }

    fn next(&mut self) -> f32 {
        if self.left == 0 {
            self.word = self.rng.next_u64();
            self.left = 5;
        }
        let g = self.table[(self.word & (NOISE_TABLE as u64 - 1)) as usize];
        self.word >>= 12;
        self.left -= 1;
        g
    }
}

/// The turntable: a disc of `radius_mm` with a rim, its top at y = 0 (table frame).
fn table_mesh(radius_mm: f64, segments: usize) -> Mesh {
    let mut vertices = vec![[0.0f32; 3]];
    for ring_y in [0.0, -TABLE_THICKNESS_MM] {
        for s in 0..segments {
            let a = 2.0 * std::f64::consts::PI * s as f64 / segments as f64;
            vertices.push([(radius_mm * a.cos()) as f32, ring_y as f32, (radius_mm * a.sin()) as f32]);
        }
    }
    let mut triangles = Vec::new();
    let n = segments as u32;
    for s in 0..n {
        let (a, b) = (1 + s, 1 + (s + 1) % n);
        // Top face, normal up.
        triangles.push([0, b, a]);
        // Rim, normal outwards.
        triangles.push([a, b, a + n]);
        triangles.push([b, b + n, a + n]);
    }
    Mesh { vertices, triangles }
}

/// Procedural surface texture: fractal value noise on the object's own coordinates (mm),
/// so the pattern sticks to the surface as the table turns.
struct Texture {
    perm: [u8; 512],
}

impl Texture {
    fn new(seed: u64) -> Texture {
        let mut rng = Rng::new(seed ^ 0x7E47_0BE5);
        let mut p: Vec<u8> = (0..=255).collect();
        for i in (1..256).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            p.swap(i, j);
        }
        let mut perm = [0u8; 512];
        for i in 0..512 {
            perm[i] = p[i & 255];
        }
        Texture { perm }
    }

    fn lattice(&self, x: i32, y: i32, z: i32) -> f32 {
        let h = self.perm[(self.perm[(self.perm[(x & 255) as usize] as i32 + (y & 255)) as usize] as i32 + (z & 255)) as usize];
        h as f32 / 255.0
    }

    fn value_noise(&self, p: [f32; 3]) -> f32 {
        let f = p.map(fast_floor);
        let t = [p[0] - f[0], p[1] - f[1], p[2] - f[2]].map(|t| t * t * (3.0 - 2.0 * t));
        let (x, y, z) = (f[0] as i32, f[1] as i32, f[2] as i32);
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let x00 = lerp(self.lattice(x, y, z), self.lattice(x + 1, y, z), t[0]);
        let x10 = lerp(self.lattice(x, y + 1, z), self.lattice(x + 1, y + 1, z), t[0]);
        let x01 = lerp(self.lattice(x, y, z + 1), self.lattice(x + 1, y, z + 1), t[0]);
        let x11 = lerp(self.lattice(x, y + 1, z + 1), self.lattice(x + 1, y + 1, z + 1), t[0]);
        lerp(lerp(x00, x10, t[1]), lerp(x01, x11, t[1]), t[2])
    }

    /// Features from about 2 to 12 mm (3 to 20 pixels at 450 mm), in 0…1.
    fn fbm(&self, p: Vec3) -> f32 {
        let p = p.map(|c| c as f32);
        let mut sum = 0.0;
        let mut amp = 0.5;
        let mut scale = 1.0 / 12.0;
        let mut norm = 0.0;
        for octave in 0..3 {
            let offset = 37.0 * octave as f32;
            sum += amp * self.value_noise([p[0] * scale + offset, p[1] * scale, p[2] * scale - offset]);
            norm += amp;
            amp *= 0.65;
            scale *= 2.2;
        }
        sum / norm
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(object: &str, triangles: usize) -> SceneConfig {
        let mut scene = SceneConfig::ideal(Mesh::builtin(object, triangles).unwrap());
        scene.rig = Rig::ideal(200, 150, 220.0, 60.0);
        scene
    }

    #[test]
    fn back_face_culling_changes_nothing_on_closed_objects() {
        for object in ["egg", "torus"] {
            let mut culled = Renderer::new(small(object, 8_000)).unwrap();
            assert!(culled.cull_object);
            let mut full = Renderer::new(small(object, 8_000)).unwrap();
            full.cull_object = false;
            let (a, b) = (culled.render(40.0, 3), full.render(40.0, 3));
            assert!(a.left_rgb == b.left_rgb && a.right_rgb == b.right_rgb, "{object}: culling changed the image");
        }
    }

    #[test]
    fn ground_truth_depth_matches_ray_traced_sphere() {
        // An independent check of the rasterizer: intersect pixel rays with the true sphere.
        let scene = small("sphere", 60_000);
        let centre_obj = {
            let (lo, hi) = scene.object.bounds();
            [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0]
        };
        let mut r = Renderer::new(scene.clone()).unwrap();
        let pair = r.render(25.0, 0);
        let gt = pair.gt_disparity.unwrap();
        let c = pair.cam_from_obj.apply(centre_obj);
        let k = scene.rig.left;
        let (mut checked, mut worst) = (0, 0.0f64);
        for v in (0..150).step_by(5) {
            for u in (0..200).step_by(5) {
                let d = [(u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0];
                // |t·d − c|² = 70² → a t² − 2 b t + cc = 0, nearest root.
                let (a, b, cc) = (math::dot(d, d), math::dot(d, c), math::dot(c, c) - 70.0 * 70.0);
                let disc = b * b - a * cc;
                let truth = gt[v * 200 + u];
                if disc < 0.0 {
                    continue;
                }
                let z = (b - disc.sqrt()) / a; // depth, since d.z = 1
                let expect = k.fx * 60.0 / z;
                if disc.sqrt() / a < 1.0 {
                    continue; // grazing rays: tessellation decides
                }
                assert!(truth.is_finite(), "pixel ({u}, {v}) sees the sphere");
                worst = worst.max((truth as f64 - expect).abs());
                checked += 1;
            }
        }
        assert!(checked > 100, "{checked}");
        assert!(worst < 0.02, "worst disparity error {worst} px");
    }

    /// The lab has one light: a plain sphere's points that both cameras of a rig toed in by
    /// 15° see face-on have one colour in both images (Lambertian shading does not depend on
    /// the camera). With the light fixed to each camera instead, they differed by up to 27
    /// levels.
    #[test]
    fn both_cameras_of_a_toed_in_rig_see_one_shading() {
        let mut scene = SceneConfig { noise_sigma: 0.0, texture_contrast: 0.0, ..small("sphere", 20_000) };
        scene.rig = scene.rig.toed_in(15.0);
        let rig = scene.rig;
        let mut r = Renderer::new(scene.clone()).unwrap();
        let pair = r.render(0.0, 0);
        let right_from_obj = rig.right_from_left.compose(&pair.cam_from_obj);
        let n = scene.object.vertices.len() as f64;
        let centre: Vec3 = std::array::from_fn(|d| scene.object.vertices.iter().map(|v| v[d] as f64).sum::<f64>() / n);
        let (mut checked, mut worst) = (0, 0u8);
        for v in scene.object.vertices.iter().step_by(7) {
            let p = v.map(|c| c as f64);
            let (normal, top) = (normalize(math::sub(p, centre)), p[1] > centre[1]);
            // Face-on to both cameras (no grazing pixels, which mix in the screen), upper half
            // (clear of the table).
            let facing = |pose: &Pose| {
                let (q, nq) = (pose.apply(p), math::mat_vec(&pose.r, normal));
                math::dot(nq, math::scale(normalize(q), -1.0)) > 0.7
            };
            if !(top && facing(&pair.cam_from_obj) && facing(&right_from_obj)) {
                continue;
            }
            let colour = |rgb: &[u8], k: &Intrinsics, q: Vec3| {
                let (u, v) = k.project(q);
                let (u, v) = (u.round() as usize, v.round() as usize);
                [0, 1, 2].map(|c| rgb[3 * (v * rig.width + u) + c])
            };
            let (a, b) = (colour(&pair.left_rgb, &rig.left, pair.cam_from_obj.apply(p)), colour(&pair.right_rgb, &rig.right, right_from_obj.apply(p)));
            worst = worst.max((0..3).map(|c| a[c].abs_diff(b[c])).max().unwrap());
            checked += 1;
        }
        assert!(checked > 50, "{checked} points checked");
        assert!(worst <= 6, "colours differ by up to {worst} levels between the cameras");
    }

    #[test]
    fn turning_the_table_turns_the_texture_with_the_object() {
        // A point on the object seen at 0° is found at its rotated position at 10°, with the
        // same colour (up to shading): the texture sticks to the surface.
        let scene = SceneConfig { noise_sigma: 0.0, ..small("egg", 20_000) };
        let mut r = Renderer::new(scene.clone()).unwrap();
        let axis = scene.axis_in_left_camera();
        assert!(axis.1[1] < -0.9, "up is −y in the camera frame: {:?}", axis.1);
        let a = r.render(0.0, 0);
        let b = r.render(10.0, 0);
        assert_ne!(a.left_rgb, b.left_rgb);
        let moved = |p: &RenderedPair| p.cam_from_obj.apply([0.0, 80.0, 55.0]);
        let (pa, pb) = (moved(&a), moved(&b));
        // Counterclockwise from above: the front point moves to the camera's right (+x).
        assert!(pb[0] > pa[0] + 5.0, "{pa:?} → {pb:?}");
    }
}
