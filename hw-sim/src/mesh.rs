//! Triangle meshes: the built-in procedural objects and meshes handed in by the caller.

use std::f64::consts::PI;

use crate::math::{cross, normalize, sub, Vec3};

/// A triangle mesh in its own frame, millimetres. For objects on the turntable `+y` is up.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// Why a mesh cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    #[error("the mesh has no triangles")]
    Empty,
    #[error("triangle {triangle} uses vertex {vertex} but the mesh has {count} vertices")]
    BadIndex { triangle: usize, vertex: u32, count: usize },
    #[error("vertex {0} is not finite")]
    NotFinite(usize),
    #[error("unknown object `{0}`; built-in objects: sphere, egg, vase, torus")]
    UnknownObject(String),
}

/// The built-in objects: their names and sizes (mm, width × height × depth).
pub const BUILTIN_OBJECTS: [(&str, &str); 4] = [
    ("sphere", "a 140 mm ball"),
    ("egg", "an ellipsoid 120 × 160 × 110 mm"),
    ("vase", "a waisted vase 120 mm across and 160 mm tall"),
    ("torus", "a ring 170 mm across standing on its rim, tube 50 mm thick"),
];

impl Mesh {
    /// Checks indices and coordinates.
    pub fn validate(&self) -> Result<(), MeshError> {
        if self.triangles.is_empty() {
            return Err(MeshError::Empty);
        }
        if let Some(i) = self.vertices.iter().position(|v| v.iter().any(|c| !c.is_finite())) {
            return Err(MeshError::NotFinite(i));
        }
        let count = self.vertices.len();
        for (triangle, t) in self.triangles.iter().enumerate() {
            if let Some(&vertex) = t.iter().find(|&&v| v as usize >= count) {
                return Err(MeshError::BadIndex { triangle, vertex, count });
            }
        }
        Ok(())
    }

    /// A built-in object by name, tessellated to about `triangles` triangles.
    pub fn builtin(name: &str, triangles: usize) -> Result<Mesh, MeshError> {
        // A u × v grid gives 2·u·v triangles; keep cells roughly square (u = 2v).
        let v_steps = ((triangles as f64 / 4.0).sqrt().round() as usize).max(4);
        let u_steps = 2 * v_steps;
        let mesh = match name {
            "sphere" => revolution(u_steps, v_steps, |t| {
                let phi = PI * t;
                (70.0 * phi.sin(), 70.0 * (1.0 - phi.cos()))
            }),
            "egg" => grid(u_steps, v_steps, true, |u, t| {
                let (theta, phi) = (2.0 * PI * u, PI * t);
                [60.0 * phi.sin() * theta.cos(), 80.0 * (1.0 - phi.cos()), 55.0 * phi.sin() * theta.sin()]
            }),
            "vase" => revolution(u_steps, v_steps, |t| {
                // Poles at both ends; a waist two-thirds of the way up.
                let r = (PI * t).sin().sqrt() * (48.0 + 12.0 * (3.0 * PI * t + 0.3).cos());
                (r, 160.0 * (1.0 - (PI * t).cos()) / 2.0)
            }),
            "torus" => {
                let (big, small) = (60.0, 25.0);
                // The last row meets the first; welding closes the tube.
                let mut m = grid(u_steps, v_steps, true, |u, t| {
                    let (a, b) = (2.0 * PI * u, 2.0 * PI * t);
                    let r = big + small * b.cos();
                    // The ring stands on its rim, facing the camera at 0°.
                    [r * a.cos(), big + small + r * a.sin(), small * b.sin()]
                });
                // This parametrisation runs clockwise seen from outside: flip the winding.
                for t in &mut m.triangles {
                    t.swap(1, 2);
                }
                m
            }
            other => return Err(MeshError::UnknownObject(other.to_string())),
        };
        Ok(mesh)
    }

    /// True when every edge is shared by exactly two triangles with opposite directions: a
    /// closed, consistently wound surface, whose back faces can never be seen.
    pub fn is_closed(&self) -> bool {
        let mut edges = std::collections::HashMap::with_capacity(self.triangles.len() * 3);
        for t in &self.triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0u32) += 1;
            }
        }
        edges.iter().all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1))
    }

    /// Per-vertex unit normals: area-weighted sums of the faces around each vertex,
    /// oriented by the triangles' winding (counterclockwise seen from outside).
    pub fn vertex_normals(&self) -> Vec<[f32; 3]> {
        let mut acc = vec![[0.0f64; 3]; self.vertices.len()];
        let p = |i: u32| self.vertices[i as usize].map(f64::from);
        for t in &self.triangles {
            let n = cross(sub(p(t[1]), p(t[0])), sub(p(t[2]), p(t[0])));
            for &i in t {
                let a = &mut acc[i as usize];
                for c in 0..3 {
                    a[c] += n[c];
                }
            }
        }
        acc.into_iter().map(|n| normalize(n).map(|c| c as f32)).collect()
    }

    /// Axis-aligned bounds `(min, max)`.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in &self.vertices {
            for c in 0..3 {
                lo[c] = lo[c].min(v[c] as f64);
                hi[c] = hi[c].max(v[c] as f64);
            }
        }
        (lo, hi)
    }

    /// Multiplies every coordinate by `s` (e.g. 1000 for a mesh in metres).
    pub fn scaled(mut self, s: f64) -> Mesh {
        for v in &mut self.vertices {
            *v = v.map(|c| (c as f64 * s) as f32);
        }
        self
    }
}

/// A grid surface `f(u, t)`, u ∈ [0, 1) around (wrapping), t ∈ [0, 1] from bottom to top.
fn grid(u_steps: usize, v_steps: usize, wrap_u: bool, f: impl Fn(f64, f64) -> Vec3) -> Mesh {
    let cols = if wrap_u { u_steps } else { u_steps + 1 };
    let mut vertices = Vec::with_capacity(cols * (v_steps + 1));
    for j in 0..=v_steps {
        for i in 0..cols {
            vertices.push(f(i as f64 / u_steps as f64, j as f64 / v_steps as f64).map(|c| c as f32));
        }
    }
    let mut triangles: Vec<[u32; 3]> = Vec::with_capacity(2 * u_steps * v_steps);
    for j in 0..v_steps {
        for i in 0..u_steps {
            let i1 = if wrap_u { (i + 1) % cols } else { i + 1 };
            let a = (j * cols + i) as u32;
            let b = (j * cols + i1) as u32;
            let c = ((j + 1) * cols + i) as u32;
            let d = ((j + 1) * cols + i1) as u32;
            // Counterclockwise seen from outside for surfaces whose u runs counterclockwise
            // seen from above and whose t runs upwards.
            triangles.push([a, c, b]);
            triangles.push([b, c, d]);
        }
    }
    weld(Mesh { vertices, triangles })
}

/// Merges vertices at the same place (a grid's poles) and drops the triangles that
/// collapse, so closed shapes come out watertight (every edge shared by two triangles).
fn weld(mesh: Mesh) -> Mesh {
    let key = |v: &[f32; 3]| v.map(|c| (c as f64 * 1e4).round() as i64);
    let mut index = std::collections::HashMap::new();
    let mut vertices = Vec::new();
    let remap: Vec<u32> = mesh
        .vertices
        .iter()
        .map(|v| {
            *index.entry(key(v)).or_insert_with(|| {
                vertices.push(*v);
                vertices.len() as u32 - 1
            })
        })
        .collect();
    let triangles = mesh
        .triangles
        .iter()
        .map(|t| t.map(|i| remap[i as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .collect();
    Mesh { vertices, triangles }
}

/// A surface of revolution about +y: `profile(t) = (radius, height)`.
fn revolution(u_steps: usize, v_steps: usize, profile: impl Fn(f64) -> (f64, f64)) -> Mesh {
    grid(u_steps, v_steps, true, |u, t| {
        let (r, y) = profile(t);
        let a = 2.0 * PI * u;
        [r * a.cos(), y, r * a.sin()]
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::dot;

    #[test]
    fn builtins_have_the_asked_size_and_outward_normals() {
        for (name, _) in BUILTIN_OBJECTS {
            let m = Mesh::builtin(name, 20_000).unwrap();
            m.validate().unwrap();
            assert!(m.is_closed(), "{name} is watertight");
            assert!((16_000..24_000).contains(&m.triangles.len()), "{name}: {}", m.triangles.len());
            let (lo, hi) = m.bounds();
            assert!(lo[1].abs() < 0.5, "{name} stands on y = 0: {}", lo[1]);
            let centre = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0];
            // Outward normals: on convex-ish shapes most normals point away from the centre.
            if name == "torus" {
                // Outward from the tube's centre line (a circle of radius 60 about z at y = 85).
                let normals = m.vertex_normals();
                let outward = m
                    .vertices
                    .iter()
                    .zip(&normals)
                    .filter(|(v, n)| {
                        let (x, y) = (v[0] as f64, v[1] as f64 - 85.0);
                        let r = (x * x + y * y).sqrt();
                        let on_circle = [x * 60.0 / r, 85.0 + y * 60.0 / r, 0.0];
                        dot(sub(v.map(f64::from), on_circle), n.map(f64::from)) > 0.0
                    })
                    .count();
                assert!(outward as f64 > 0.99 * m.vertices.len() as f64, "torus: {outward} of {}", m.vertices.len());
            } else {
                let normals = m.vertex_normals();
                let outward = m
                    .vertices
                    .iter()
                    .zip(&normals)
                    .filter(|(v, n)| dot(sub(v.map(f64::from), centre), n.map(f64::from)) > 0.0)
                    .count();
                assert!(outward as f64 > 0.95 * m.vertices.len() as f64, "{name}: {outward} of {}", m.vertices.len());
            }
        }
    }

    #[test]
    fn bad_meshes_are_named() {
        let m = Mesh { vertices: vec![[0.0; 3]; 2], triangles: vec![[0, 1, 2]] };
        assert!(!m.is_closed());
        assert_eq!(m.validate(), Err(MeshError::BadIndex { triangle: 0, vertex: 2, count: 2 }));
        assert!(matches!(Mesh::builtin("teapot", 100), Err(MeshError::UnknownObject(_))));
    }
}
