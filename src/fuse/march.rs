//! Marching tetrahedra over the fused field (`mesh.rs` cleans what it gives): each cube of
//! eight voxel centres is cut into the six tetrahedra of its Kuhn triangulation (all around
//! the diagonal from its low to its high corner, so that neighbouring cubes cut their shared
//! faces alike), and each tetrahedron whose corners change sign gets one triangle or two. A
//! vertex lies on a grid edge and is shared by every triangle that cuts that edge. Cubes
//! with an unseen corner get no triangles.
//!
//! The blocks are cut into runs, meshed on [`Tsdf`]'s threads and merged in order: the same
//! mesh, bit for bit, as one run of them all.

use super::{cross, dot, near_index, sub, voxel_centre, FastMap, Tsdf, Voxel, SIDE};

/// The seen surface's vertices (positions, colours) and triangles, wound inside to outside.
pub(super) fn surface(tsdf: &Tsdf) -> (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<[u32; 3]>) {
    use rayon::prelude::*;
    let keys = tsdf.block_keys();
    let run = keys.len().div_ceil(tsdf.threads * RUNS_PER_THREAD).max(1);
    let runs: Vec<Builder> = if tsdf.threads > 1 { keys.par_chunks(run).map(|k| build(tsdf, k)).collect() } else { keys.chunks(run).map(|k| build(tsdf, k)).collect() };
    merge(runs)
}

/// Corners of a cube of voxel centres, from its low corner.
const CORNERS: [[i32; 3]; 8] = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]];
/// The six tetrahedra of the Kuhn triangulation: every path from corner 0 to corner 6
/// along the three axes, in each order.
const TETRAS: [[usize; 4]; 6] = [[0, 1, 2, 6], [0, 3, 2, 6], [0, 3, 7, 6], [0, 4, 7, 6], [0, 4, 5, 6], [0, 1, 5, 6]];

/// A grid index packed into one integer (21 bits a coordinate, offset to be positive).
fn pack(g: [i32; 3]) -> u64 {
    const OFF: i64 = 1 << 20;
    let f = |v: i32| ((v as i64 + OFF) as u64) & ((1 << 21) - 1);
    f(g[0]) << 42 | f(g[1]) << 21 | f(g[2])
}

/// The triangles of a run of blocks, with vertices of their own: [`merge`] joins the runs'
/// vertices on the grid edges they share.
#[derive(Default)]
struct Builder {
    points: Vec<[f32; 3]>,
    colors: Vec<[f32; 3]>,
    /// The grid edge of each vertex, by its two packed ends (low, high).
    edges: Vec<(u64, u64)>,
    /// The vertex on each grid edge cut.
    on_edge: FastMap<(u64, u64), u32>,
    triangles: Vec<[u32; 3]>,
    /// The direction each triangle's normal is to take (inside to outside): triangles are
    /// wound once their vertices are the mesh's, in [`merge`].
    outs: Vec<[f32; 3]>,
}

impl Builder {
    /// The vertex where the field crosses zero between two corners.
    fn vertex(&mut self, (ia, pa, va): (u64, [f32; 3], Voxel), (ib, pb, vb): (u64, [f32; 3], Voxel)) -> u32 {
        let key = if ia < ib { (ia, ib) } else { (ib, ia) };
        if let Some(&v) = self.on_edge.get(&key) {
            return v;
        }
        // Kept off the corners, so that no two vertices coincide and no triangle is
        // degenerate (a move of at most 1 % of a voxel).
        let t = (va.sdf / (va.sdf - vb.sdf)).clamp(0.01, 0.99);
        let lerp = |a: [f32; 3], b: [f32; 3]| [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2])];
        let v = self.points.len() as u32;
        self.points.push(lerp(pa, pb));
        self.colors.push(lerp(va.rgb, vb.rgb));
        self.edges.push(key);
        self.on_edge.insert(key, v);
        v
    }

    /// A triangle whose normal is to point along `out` (inside to outside).
    fn triangle(&mut self, v: [u32; 3], out: [f32; 3]) {
        self.triangles.push(v);
        self.outs.push(out);
    }

    /// The triangles of one tetrahedron (corners: packed index, position, voxel).
    fn tetra(&mut self, c: [(u64, [f32; 3], Voxel); 4]) {
        // The corners inside (negative) and outside, each in order, without an allocation.
        let (mut ins, mut outs, mut n_in, mut n_out) = ([0usize; 4], [0usize; 4], 0, 0);
        for (i, corner) in c.iter().enumerate() {
            if corner.2.sdf < 0.0 {
                ins[n_in] = i;
                n_in += 1;
            } else {
                outs[n_out] = i;
                n_out += 1;
            }
        }
        let (inside, outside) = (&ins[..n_in], &outs[..n_out]);
        let mean = |ix: &[usize]| {
            let mut m = [0f32; 3];
            for &i in ix {
                for k in 0..3 {
                    m[k] += c[i].1[k] / ix.len() as f32;
                }
            }
            m
        };
        match inside.len() {
            1 | 3 => {
                // One corner alone on its side: one triangle across its three edges.
                let single = inside.len() == 1;
                let (alone, rest) = if single { (inside[0], outside) } else { (outside[0], inside) };
                let v = [self.vertex(c[alone], c[rest[0]]), self.vertex(c[alone], c[rest[1]]), self.vertex(c[alone], c[rest[2]])];
                let out = if single { sub(mean(rest), c[alone].1) } else { sub(c[alone].1, mean(rest)) };
                self.triangle(v, out);
            }
            2 => {
                // Two and two: a quad round the four cut edges, as two triangles.
                let (a, b, p, q) = (inside[0], inside[1], outside[0], outside[1]);
                let v = [self.vertex(c[a], c[p]), self.vertex(c[a], c[q]), self.vertex(c[b], c[q]), self.vertex(c[b], c[p])];
                let out = sub(mean(outside), mean(inside));
                self.triangle([v[0], v[1], v[2]], out);
                self.triangle([v[0], v[2], v[3]], out);
            }
            _ => {}
        }
    }
}

/// Runs of blocks per thread that [`surface`] meshes apart: the blocks' surfaces differ.
const RUNS_PER_THREAD: usize = 8;

/// The triangles of the blocks `keys`.
fn build(tsdf: &Tsdf, keys: &[[i32; 3]]) -> Builder {
    let voxel = tsdf.voxel_mm();
    let mut b = Builder::default();
    let mut near = Vec::new();
    for &key in keys {
        tsdf.neighbourhood(key, &mut near);
        let origin = [key[0] * SIDE, key[1] * SIDE, key[2] * SIDE];
        for z in 0..SIDE {
            for y in 0..SIDE {
                'cube: for x in 0..SIDE {
                    let mut corners = [(0u64, [0f32; 3], Voxel { sdf: 0.0, rgb: [0.0; 3] }); 8];
                    let (mut neg, mut pos) = (false, false);
                    for (c, off) in CORNERS.iter().enumerate() {
                        let (lx, ly, lz) = (x + off[0], y + off[1], z + off[2]);
                        let Some(v) = near[near_index([lx, ly, lz])] else { continue 'cube };
                        neg |= v.sdf < 0.0;
                        pos |= v.sdf >= 0.0;
                        let g = [origin[0] + lx, origin[1] + ly, origin[2] + lz];
                        corners[c] = (pack(g), voxel_centre(g, voxel), v);
                    }
                    if !(neg && pos) {
                        continue;
                    }
                    for t in TETRAS {
                        b.tetra([corners[t[0]], corners[t[1]], corners[t[2]], corners[t[3]]]);
                    }
                }
            }
        }
    }
    b
}

/// The runs' meshes as one, in order: a grid edge's vertex is the first run's that cut it
/// (made from the same corners in the same order as one run of every block makes it), and
/// each triangle is wound by the mesh's own vertices.
fn merge(runs: Vec<Builder>) -> (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let n = runs.iter().map(|r| r.points.len()).sum::<usize>();
    let (mut points, mut colors, mut triangles) = (Vec::with_capacity(n), Vec::with_capacity(n), Vec::with_capacity(runs.iter().map(|r| r.triangles.len()).sum()));
    let mut on_edge: FastMap<(u64, u64), u32> = FastMap::with_capacity_and_hasher(n, Default::default());
    for run in runs {
        let mine: Vec<u32> = run
            .edges
            .iter()
            .zip(run.points.iter().zip(&run.colors))
            .map(|(edge, (p, c))| {
                *on_edge.entry(*edge).or_insert_with(|| {
                    points.push(*p);
                    colors.push(*c);
                    points.len() as u32 - 1
                })
            })
            .collect();
        for (t, out) in run.triangles.iter().zip(&run.outs) {
            let mut v = t.map(|i| mine[i as usize]);
            let (a, b, c) = (points[v[0] as usize], points[v[1] as usize], points[v[2] as usize]);
            if dot(cross(sub(b, a), sub(c, a)), *out) < 0.0 {
                v.swap(1, 2);
            }
            triangles.push(v);
        }
    }
    (points, colors, triangles)
}
