//! The little linear algebra the simulator needs (it has no dependencies on purpose).

pub type Vec3 = [f64; 3];
/// Row-major 3×3 matrix.
pub type Mat3 = [[f64; 3]; 3];

pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

pub fn normalize(a: Vec3) -> Vec3 {
    let n = norm(a);
    if n > 0.0 {
        scale(a, 1.0 / n)
    } else {
        a
    }
}

pub fn mat_vec(m: &Mat3, v: Vec3) -> Vec3 {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut c = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            c[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    c
}

pub fn transpose(m: &Mat3) -> Mat3 {
    [[m[0][0], m[1][0], m[2][0]], [m[0][1], m[1][1], m[2][1]], [m[0][2], m[1][2], m[2][2]]]
}

pub const IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Right-handed rotation by `angle_rad` about the unit vector `axis` (Rodrigues).
pub fn rotation(axis: Vec3, angle_rad: f64) -> Mat3 {
    let [x, y, z] = normalize(axis);
    let (s, c) = angle_rad.sin_cos();
    let t = 1.0 - c;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

/// A rigid transform `p ↦ r·p + t`. Named `target_from_source` where it is stored.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub r: Mat3,
    pub t: Vec3,
}

impl Pose {
    pub const IDENTITY: Pose = Pose { r: IDENTITY, t: [0.0; 3] };

    pub fn apply(&self, p: Vec3) -> Vec3 {
        add(mat_vec(&self.r, p), self.t)
    }

    /// `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Pose) -> Pose {
        Pose { r: mat_mul(&self.r, &other.r), t: self.apply(other.t) }
    }

    pub fn inverse(&self) -> Pose {
        let rt = transpose(&self.r);
        Pose { r: rt, t: scale(mat_vec(&rt, self.t), -1.0) }
    }

    /// The 4×4 homogeneous matrix, row-major.
    pub fn matrix(&self) -> [[f64; 4]; 4] {
        let r = &self.r;
        [
            [r[0][0], r[0][1], r[0][2], self.t[0]],
            [r[1][0], r[1][1], r[1][2], self.t[1]],
            [r[2][0], r[2][1], r[2][2], self.t[2]],
            [0.0, 0.0, 0.0, 1.0],
        ]
    }
}

/// SplitMix64: a well-mixed hash of one word.
pub fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A small fast generator (wyrand), deterministic for its seed.
#[derive(Debug, Clone)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Rng {
        Rng(mix(seed))
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0xA076_1D64_78BD_642F);
        let t = (self.0 as u128).wrapping_mul((self.0 ^ 0xE703_7ED1_A0B4_28DB) as u128);
        ((t >> 64) as u64) ^ (t as u64)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Approximately standard normal: Irwin–Hall sum of four 16-bit uniforms from one draw
    /// (variance 4/12, rescaled), cheap enough for per-pixel sensor noise.
    pub fn gaussian(&mut self) -> f32 {
        let r = self.next_u64();
        let s = (r & 0xFFFF) + ((r >> 16) & 0xFFFF) + ((r >> 32) & 0xFFFF) + (r >> 48);
        (s as f32 / 65536.0 - 2.0) * 1.732_050_8
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_inverse_and_compose() {
        let p = Pose { r: rotation([0.3, 1.0, -0.2], 0.7), t: [10.0, -4.0, 450.0] };
        let q = p.compose(&p.inverse());
        for i in 0..3 {
            for j in 0..3 {
                assert!((q.r[i][j] - IDENTITY[i][j]).abs() < 1e-12);
            }
            assert!(q.t[i].abs() < 1e-9);
        }
    }

    #[test]
    fn rotation_is_right_handed() {
        // A quarter turn about +y takes +z to +x.
        let r = rotation([0.0, 1.0, 0.0], std::f64::consts::FRAC_PI_2);
        let v = mat_vec(&r, [0.0, 0.0, 1.0]);
        assert!((v[0] - 1.0).abs() < 1e-12 && v[2].abs() < 1e-12);
    }

    #[test]
    fn gaussian_has_unit_variance() {
        let mut rng = Rng::new(7);
        let n = 100_000;
        let (mut s, mut s2) = (0.0f64, 0.0f64);
        for _ in 0..n {
            let g = rng.gaussian() as f64;
            s += g;
            s2 += g * g;
        }
        let mean = s / n as f64;
        let var = s2 / n as f64 - mean * mean;
        assert!(mean.abs() < 0.02 && (var - 1.0).abs() < 0.03, "mean {mean} var {var}");
    }
}
