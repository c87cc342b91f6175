//! The zero level set of the fused field as a triangle mesh, then its clean-up.
//!
//! Extraction is marching tetrahedra (`march.rs`): each cube of eight voxel centres is cut into the six
//! tetrahedra of its Kuhn triangulation (all around the diagonal from its low to its high
//! corner, so that neighbouring cubes cut their shared faces alike), and each tetrahedron
//! whose corners change sign gets one triangle or two. A vertex lies on a grid edge and is
//! shared by every triangle that cuts that edge, so the mesh is indexed and, where the
//! field is seen, closed; every edge of it lies on a face shared by at most two
//! tetrahedra, so no edge has more than two triangles. Cubes with an unseen corner get no
//! triangles: the mesh has a boundary where the views end.
//!
//! Clean-up, in order: connected pieces with fewer triangles than
//! `min_component_share` × the largest are removed (floating fragments); with `fill`, every
//! boundary loop is closed by a cap — a fan around the loop's centroid (one triangle for a
//! loop of three) — and reported as filled; vertex normals are the area-weighted normals of
//! the triangles around each vertex.

use std::collections::HashMap;

use super::{cross, norm, sub, FastMap, Tsdf};
use crate::cloud::{Mesh, PointCloud};
use crate::disjoint::root;


/// The mesh type the fusion returns: vertices with colours and normals, triangles.
pub type SurfaceMesh = Mesh;

/// What the extraction and clean-up produced and did.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct MeshStats {
    pub vertices: usize,
    pub triangles: usize,
    /// Edges of one triangle after clean-up (0: closed).
    pub boundary_edges: usize,
    /// Edges of more than two triangles (0 by construction; counted, not assumed).
    pub non_manifold_edges: usize,
    /// Connected pieces removed as fragments, and their triangles.
    pub components_removed: usize,
    pub triangles_removed: usize,
    /// Boundary loops closed by caps, their triangles and area (mm²): surface not seen.
    pub holes_filled: usize,
    pub fill_triangles: usize,
    pub fill_area_mm2: f64,
    /// Boundary loops that could not be walked round (left open).
    pub holes_left_open: usize,
    /// Vertices where two parts of the surface touched at a point, split into one vertex
    /// per part (so that every vertex's triangles form one fan).
    pub pinched_vertices_split: usize,
    /// The first this many vertices are on the fused (seen) surface; the rest are the caps'
    /// centres and the copies made by splitting.
    pub measured_vertices: usize,
}

/// The mesh of the field's zero level set, cleaned (module docs).
pub(super) fn extract(tsdf: &Tsdf) -> (Mesh, MeshStats) {
    let (points, colors, triangles) = super::march::surface(tsdf);
    clean(points, colors, triangles, tsdf.params.fill, tsdf.params.min_component_share, tsdf.threads > 1)
}

/// Fragments removed, holes capped, normals computed (module docs).
fn clean(points: Vec<[f32; 3]>, colors: Vec<[f32; 3]>, triangles: Vec<[u32; 3]>, fill: bool, share: f64, parallel: bool) -> (Mesh, MeshStats) {
    let mut stats = MeshStats::default();
    // Connected pieces, by shared vertices.
    let mut parent: Vec<u32> = (0..points.len() as u32).collect();
    for t in &triangles {
        let (a, b, c) = (root(&mut parent, t[0]), root(&mut parent, t[1]), root(&mut parent, t[2]));
        parent[b as usize] = a;
        let c = root(&mut parent, c);
        parent[c as usize] = a;
    }
    let mut size: FastMap<u32, usize> = FastMap::default();
    let roots: Vec<u32> = triangles.iter().map(|t| root(&mut parent, t[0])).collect();
    for &r in &roots {
        *size.entry(r).or_default() += 1;
    }
    let largest = size.values().copied().max().unwrap_or(0);
    let keep_piece = |n: usize| n as f64 >= share * largest as f64;
    stats.components_removed = size.values().filter(|&&n| !keep_piece(n)).count();
    // Kept triangles, their vertices renumbered in order.
    let mut new_index = vec![u32::MAX; points.len()];
    let (mut pts, mut cols, mut tris) = (Vec::new(), Vec::new(), Vec::new());
    for (t, r) in triangles.iter().zip(&roots) {
        if !keep_piece(size[r]) {
            stats.triangles_removed += 1;
            continue;
        }
        let mut nt = [0u32; 3];
        for k in 0..3 {
            let v = t[k] as usize;
            if new_index[v] == u32::MAX {
                new_index[v] = pts.len() as u32;
                pts.push(points[v]);
                cols.push(colors[v]);
            }
            nt[k] = new_index[v];
        }
        tris.push(nt);
    }
    stats.measured_vertices = pts.len();
    if fill {
        fill_holes(&mut pts, &mut cols, &mut tris, &mut stats, parallel);
    }
    stats.pinched_vertices_split = split_pinched(&mut pts, &mut cols, &mut tris);
    let (boundary, non_manifold) = edge_counts(&tris, parallel);
    stats.boundary_edges = boundary.len();
    stats.non_manifold_edges = non_manifold;
    // Area-weighted vertex normals (the cross product's length is twice the area).
    let mut normals = vec![[0f32; 3]; pts.len()];
    for t in &tris {
        let n = cross(sub(pts[t[1] as usize], pts[t[0] as usize]), sub(pts[t[2] as usize], pts[t[0] as usize]));
        for &v in t {
            for k in 0..3 {
                normals[v as usize][k] += n[k];
            }
        }
    }
    for n in &mut normals {
        let l = norm(*n);
        if l > 0.0 {
            *n = n.map(|v| v / l);
        }
    }
    stats.vertices = pts.len();
    stats.triangles = tris.len();
    let colors = cols.iter().map(|c| c.map(|v| v.round().clamp(0.0, 255.0) as u8)).collect();
    (Mesh { cloud: PointCloud { points: pts, colors, normals: Some(normals), rim_px: None }, triangles: tris }, stats)
}

/// Splits every vertex whose triangles form more than one fan (two parts of the surface
/// touching at a point: a pinched boundary, once capped) into one vertex per fan; returns
/// how many vertices were split. Edges keep their triangles: two triangles sharing an edge
/// through the vertex are in the same fan.
fn split_pinched(pts: &mut Vec<[f32; 3]>, cols: &mut Vec<[f32; 3]>, tris: &mut [[u32; 3]]) -> usize {
    let n = pts.len();
    let (start, around) = triangles_round(tris, n);
    let mut split = 0;
    let (mut parent, mut seen): (Vec<u32>, Vec<(u32, u32)>) = (Vec::new(), Vec::new());
    for v in 0..n {
        let ts = &around[start[v]..start[v + 1]];
        if ts.len() < 2 {
            continue;
        }
        // Fans: triangles joined when they share another vertex (an edge through v).
        parent.clear();
        parent.extend(0..ts.len() as u32);
        seen.clear();
        for (j, &k) in ts.iter().enumerate() {
            for &w in &tris[k as usize] {
                if w as usize == v {
                    continue;
                }
                match seen.iter().find(|e| e.0 == w) {
                    Some(&(_, i)) => {
                        let (a, b) = (root(&mut parent, i), root(&mut parent, j as u32));
                        parent[b as usize] = a;
                    }
                    None => seen.push((w, j as u32)),
                }
            }
        }
        let first = root(&mut parent, 0);
        let mut copies: Vec<(u32, u32)> = Vec::new();
        for (j, &k) in ts.iter().enumerate() {
            let r = root(&mut parent, j as u32);
            if r == first {
                continue;
            }
            let copy = match copies.iter().find(|c| c.0 == r) {
                Some(&(_, c)) => c,
                None => {
                    let c = pts.len() as u32;
                    pts.push(pts[v]);
                    cols.push(cols[v]);
                    copies.push((r, c));
                    c
                }
            };
            for u in tris[k as usize].iter_mut() {
                if *u as usize == v {
                    *u = copy;
                }
            }
        }
        split += (!copies.is_empty()) as usize;
    }
    split
}

/// The triangles round each of `n` vertices (every index in `tris` below `n`): vertex v's
/// are `around[start[v]..start[v + 1]]`, in the order of `tris`.
fn triangles_round(tris: &[[u32; 3]], n: usize) -> (Vec<usize>, Vec<u32>) {
    let mut start = vec![0usize; n + 1];
    for &v in tris.iter().flatten() {
        start[v as usize + 1] += 1;
    }
    for v in 0..n {
        start[v + 1] += start[v];
    }
    let mut next = start.clone();
    let mut around = vec![0u32; start[n]];
    for (k, t) in tris.iter().enumerate() {
        for &v in t {
            around[next[v as usize]] = k as u32;
            next[v as usize] += 1;
        }
    }
    (start, around)
}

/// The directed boundary half-edges (each edge of one triangle, as that triangle winds it),
/// sorted, and the number of edges of more than two triangles. Each edge is counted at its
/// lower vertex, among the triangles round it (in runs of vertices on the current rayon
/// pool's threads with `parallel`; the same answer either way).
fn edge_counts(tris: &[[u32; 3]], parallel: bool) -> (Vec<(u32, u32)>, usize) {
    use rayon::prelude::*;
    let n = tris.iter().flatten().max().map_or(0, |&v| v as usize + 1);
    let (start, round) = triangles_round(tris, n);
    // Per run of vertices: its boundary half-edges and its edges of more than two triangles.
    let count = |vs: std::ops::Range<usize>| {
        let (mut boundary, mut over, mut near) = (Vec::new(), 0, Vec::new());
        for v in vs {
            // The half-edges through v to a higher vertex w: (w, as wound).
            near.clear();
            for &i in &round[start[v]..start[v + 1]] {
                let t = tris[i as usize];
                let k = t.iter().position(|&x| x as usize == v).expect("the triangle holds the vertex");
                let (next, prev) = (t[(k + 1) % 3], t[(k + 2) % 3]);
                if next as usize > v {
                    near.push((next, (v as u32, next)));
                }
                if prev as usize > v {
                    near.push((prev, (prev, v as u32)));
                }
            }
            near.sort_unstable_by_key(|e| e.0);
            for group in near.chunk_by(|a, b| a.0 == b.0) {
                match group.len() {
                    1 => boundary.push(group[0].1),
                    2 => {}
                    _ => over += 1,
                }
            }
        }
        (boundary, over)
    };
    const RUN: usize = 4096;
    let runs: Vec<(Vec<(u32, u32)>, usize)> = if parallel {
        (0..n.div_ceil(RUN)).into_par_iter().map(|r| count(r * RUN..((r + 1) * RUN).min(n))).collect()
    } else {
        vec![count(0..n)]
    };
    let over = runs.iter().map(|r| r.1).sum();
    let mut boundary: Vec<(u32, u32)> = runs.into_iter().flat_map(|r| r.0).collect();
    boundary.sort_unstable();
    (boundary, over)
}

/// Closes every boundary loop with a cap (module docs); a loop whose walk cannot close is
/// left open and counted.
fn fill_holes(pts: &mut Vec<[f32; 3]>, cols: &mut Vec<[f32; 3]>, tris: &mut Vec<[u32; 3]>, stats: &mut MeshStats, parallel: bool) {
    let (boundary, _) = edge_counts(tris, parallel);
    // A triangle winds a → b along a boundary edge; the hole runs b → a.
    let mut out: HashMap<u32, Vec<u32>> = HashMap::new();
    for &(a, b) in &boundary {
        out.entry(b).or_default().push(a);
    }
    let mut starts: Vec<u32> = out.keys().copied().collect();
    starts.sort_unstable();
    for s in starts {
        while out.get(&s).is_some_and(|v| !v.is_empty()) {
            // Walk round from s. A vertex met twice pinches the boundary: the part walked
            // since its first visit is a loop of its own, capped alone, so that every cap is
            // bounded by a simple loop (no vertex twice) and no edge gets a third triangle.
            let mut ring = vec![s];
            let mut at: HashMap<u32, usize> = HashMap::from([(s, 0)]);
            let mut cur = out.get_mut(&s).and_then(|v| v.pop()).expect("checked non-empty");
            let mut steps = 0;
            let closed = loop {
                if cur == s {
                    break true;
                }
                if let Some(&i) = at.get(&cur) {
                    let sub: Vec<u32> = ring.drain(i + 1..).collect();
                    let mut simple = vec![cur];
                    simple.extend(sub);
                    for v in &simple[1..] {
                        at.remove(v);
                    }
                    cap(&simple, pts, cols, tris, stats);
                } else {
                    at.insert(cur, ring.len());
                    ring.push(cur);
                }
                steps += 1;
                match out.get_mut(&cur).and_then(|v| v.pop()) {
                    Some(next) if steps <= boundary.len() => cur = next,
                    _ => break false,
                }
            };
            if closed {
                cap(&ring, pts, cols, tris, stats);
            } else {
                stats.holes_left_open += 1;
            }
        }
    }
}

/// Caps one simple boundary loop (module docs); a loop of fewer than three vertices is left
/// open and counted.
fn cap(ring: &[u32], pts: &mut Vec<[f32; 3]>, cols: &mut Vec<[f32; 3]>, tris: &mut Vec<[u32; 3]>, stats: &mut MeshStats) {
    if ring.len() < 3 {
        stats.holes_left_open += 1;
        return;
    }
    let before = tris.len();
    if ring.len() == 3 {
        tris.push([ring[0], ring[1], ring[2]]);
    } else {
        let n = ring.len() as f32;
        let (mut c, mut rgb) = ([0f32; 3], [0f32; 3]);
        for &v in ring {
            for k in 0..3 {
                c[k] += pts[v as usize][k] / n;
                rgb[k] += cols[v as usize][k] / n;
            }
        }
        let m = pts.len() as u32;
        pts.push(c);
        cols.push(rgb);
        for k in 0..ring.len() {
            tris.push([ring[k], ring[(k + 1) % ring.len()], m]);
        }
    }
    stats.holes_filled += 1;
    stats.fill_triangles += tris.len() - before;
    stats.fill_area_mm2 += tris[before..].iter().map(|t| 0.5 * norm(cross(sub(pts[t[1] as usize], pts[t[0] as usize]), sub(pts[t[2] as usize], pts[t[0] as usize]))) as f64).sum::<f64>();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fuse::{FuseParams, Tsdf};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

    /// Views of a sphere (radius 20 mm, centre 300 mm ahead of the first camera) from cameras
    /// turning round it on a horizontal circle, each seeing the hemisphere facing it: the
    /// points, in each camera's own frame, and the camera's pose.
    fn sphere_views(n: usize, top_only: bool) -> Vec<(PointCloud, Isometry3<f64>)> {
        sphere_views_sampled(n, top_only, 120, 240)
    }

    /// [`sphere_views`] with the sphere sampled at `rows` latitudes × `cols` longitudes.
    fn sphere_views_sampled(n: usize, top_only: bool, rows: usize, cols: usize) -> Vec<(PointCloud, Isometry3<f64>)> {
        let centre = Vector3::new(0.0, 0.0, 300.0);
        (0..n)
            .map(|k| {
                let angle = k as f64 / n as f64 * std::f64::consts::TAU;
                // The camera turns round the sphere's vertical axis (y).
                let world_from_cam = Isometry3::from_parts(Translation3::from(centre), UnitQuaternion::from_axis_angle(&Vector3::y_axis(), angle)) * Isometry3::translation(0.0, 0.0, -300.0);
                let cam_from_world = world_from_cam.inverse();
                let mut cloud = PointCloud::default();
                for i in 0..rows {
                    for j in 0..cols {
                        let (th, ph) = (i as f64 / (rows - 1) as f64 * std::f64::consts::PI, j as f64 / cols as f64 * std::f64::consts::TAU);
                        let n = Vector3::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin());
                        // The bottom cap (below −12 mm) is never seen, like an object's base.
                        if top_only && n.y * 20.0 < -12.0 {
                            continue;
                        }
                        let p = cam_from_world * nalgebra::Point3::from(centre + n * 20.0);
                        let seen = (cam_from_world.rotation * n).dot(&-p.coords.normalize()) > 0.1;
                        if seen {
                            cloud.points.push([p.x as f32, p.y as f32, p.z as f32]);
                            cloud.colors.push([200, 100, 50]);
                        }
                    }
                }
                (cloud, world_from_cam)
            })
            .collect()
    }

    fn fused(views: &[(PointCloud, Isometry3<f64>)], fill: bool) -> (Mesh, MeshStats) {
        let mut tsdf = Tsdf::new(FuseParams { voxel_mm: 1.0, fill, ..FuseParams::default() }).unwrap();
        for (c, p) in views {
            tsdf.integrate(c, p);
        }
        tsdf.mesh()
    }

    #[test]
    fn a_sphere_seen_all_round_comes_out_closed_and_on_its_surface() {
        let (mesh, stats) = fused(&sphere_views(24, false), true);
        assert_eq!((stats.boundary_edges, stats.non_manifold_edges), (0, 0), "{stats:?}");
        assert!(stats.triangles > 5000, "{stats:?}");
        let centre = Vector3::new(0.0f32, 0.0, 300.0);
        let mut err: Vec<f32> = mesh.cloud.points.iter().map(|p| ((Vector3::from(*p) - centre).norm() - 20.0).abs()).collect();
        err.sort_by(f32::total_cmp);
        assert!(err[err.len() / 2] < 0.1 && err[err.len() * 95 / 100] < 0.3, "median {} p95 {}", err[err.len() / 2], err[err.len() * 95 / 100]);
        // Normals point out of the sphere; colours are the points'.
        let normals = mesh.cloud.normals.as_ref().unwrap();
        let outward = mesh.cloud.points.iter().zip(normals).filter(|(p, n)| (Vector3::from(**p) - centre).dot(&Vector3::from(**n)) > 0.0).count();
        assert!(outward as f64 > 0.99 * mesh.cloud.points.len() as f64, "{outward} of {} normals outward", mesh.cloud.points.len());
        assert!(mesh.cloud.colors.iter().all(|c| c[0].abs_diff(200) <= 1 && c[2].abs_diff(50) <= 1));
    }

    /// Views sampled ≈ 2.6 mm apart fused at 1 mm voxels: fitted to the sampling, the field
    /// meshes the sphere from what was seen; held at 1 mm, many cubes have a corner no ray
    /// crossed, and the mesh is half caps over holes.
    #[test]
    fn a_coarsely_sampled_scan_gets_a_voxel_fitted_to_its_spacing() {
        let views = sphere_views_sampled(24, false, 24, 48);
        let mesh_of = |fit: bool| {
            let mut tsdf = Tsdf::new(FuseParams { voxel_mm: 1.0, fit_to_sampling: fit, ..FuseParams::default() }).unwrap();
            for (c, p) in &views {
                tsdf.integrate(c, p);
            }
            let (mesh, stats) = tsdf.mesh();
            (tsdf.spacing_mm().unwrap(), tsdf.voxel_mm() as f64, mesh, stats)
        };
        let (spacing, voxel, mesh, fitted) = mesh_of(true);
        assert!((2.0..3.2).contains(&spacing), "spacing {spacing}");
        assert!((voxel - super::super::SAMPLING_VOXELS * spacing).abs() < 1e-3, "voxel {voxel} for spacing {spacing}");
        // The sphere's area is 4π·20² ≈ 5027 mm²: caps cover a small part of it.
        assert_eq!((fitted.boundary_edges, fitted.non_manifold_edges), (0, 0), "{fitted:?}");
        // Only the poles, seen at grazing angles from cameras turning round the y axis, are
        // capped (≈ 680 mm² here); at 1 mm voxels, half the sphere is caps over 48 holes.
        assert!(fitted.holes_filled <= 2 && fitted.fill_area_mm2 < 800.0, "{fitted:?}");
        let centre = Vector3::new(0.0f32, 0.0, 300.0);
        let mut err: Vec<f32> = mesh.cloud.points[..fitted.measured_vertices].iter().map(|p| ((Vector3::from(*p) - centre).norm() - 20.0).abs()).collect();
        err.sort_by(f32::total_cmp);
        assert!(err[err.len() / 2] < 0.3 * voxel as f32, "median {} at voxel {voxel}", err[err.len() / 2]);
        let (_, exact, _, held) = mesh_of(false);
        assert_eq!(exact, 1.0);
        assert!(held.holes_filled > 20 && held.fill_area_mm2 > 3.0 * fitted.fill_area_mm2, "held {held:?} fitted {fitted:?}");
    }

    #[test]
    fn the_unseen_base_is_capped_and_reported_or_left_open() {
        let views = sphere_views(24, true);
        let (_, open) = fused(&views, false);
        assert!(open.boundary_edges > 50 && open.holes_filled == 0, "{open:?}");
        let (mesh, closed) = fused(&views, true);
        assert_eq!((closed.boundary_edges, closed.non_manifold_edges, closed.holes_left_open), (0, 0, 0), "{closed:?}");
        // The cap spans the unseen base: a disc of radius √(20² − 12²) = 16 mm, ≈ 804 mm².
        assert!(closed.holes_filled >= 1 && (600.0..1000.0).contains(&closed.fill_area_mm2), "{closed:?}");
        // Every vertex's triangles form one fan.
        assert_eq!(fans_per_vertex(&mesh).into_iter().max(), Some(1));
        // Every edge has two triangles, wound opposite ways (a closed, oriented surface).
        let mut directed = std::collections::HashSet::new();
        for t in &mesh.triangles {
            for k in 0..3 {
                assert!(directed.insert((t[k], t[(k + 1) % 3])), "edge {:?} wound twice the same way", (t[k], t[(k + 1) % 3]));
            }
        }
    }

    /// How many fans of triangles meet at each vertex (1 where the surface is a disc round it).
    fn fans_per_vertex(mesh: &Mesh) -> Vec<usize> {
        let mut around = vec![Vec::new(); mesh.cloud.len()];
        for (k, t) in mesh.triangles.iter().enumerate() {
            for &v in t {
                around[v as usize].push(k);
            }
        }
        around
            .iter()
            .enumerate()
            .map(|(v, ts)| {
                let mut parent: Vec<u32> = (0..ts.len() as u32).collect();
                for a in 0..ts.len() {
                    for b in a + 1..ts.len() {
                        let shared = mesh.triangles[ts[a]].iter().filter(|&&w| w as usize != v && mesh.triangles[ts[b]].contains(&w)).count();
                        if shared > 0 {
                            let (ra, rb) = (root(&mut parent, a as u32), root(&mut parent, b as u32));
                            parent[rb as usize] = ra;
                        }
                    }
                }
                (0..ts.len() as u32).filter(|&i| root(&mut parent, i) == i).count()
            })
            .collect()
    }

    #[test]
    fn a_vertex_where_two_parts_touch_is_split() {
        // Two squares of two triangles each, touching at one corner (vertex 0), one of them
        // capped nowhere: vertex 0 has two fans before, one each after.
        let pts = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.5], [-1.0, -1.0, 0.5], [0.0, -1.0, 0.5]];
        let tris = vec![[0, 1, 2], [0, 2, 3], [0, 4, 5], [0, 5, 6]];
        let cols = vec![[0.0; 3]; pts.len()];
        let (mesh, stats) = clean(pts, cols, tris, false, 0.0, false);
        assert_eq!(stats.pinched_vertices_split, 1);
        assert_eq!(mesh.cloud.len(), 8);
        assert_eq!(fans_per_vertex(&mesh).into_iter().max(), Some(1));
        assert_eq!(stats.non_manifold_edges, 0);
    }

    #[test]
    fn a_field_over_its_memory_budget_leaves_surface_out_and_counts_it() {
        let views = sphere_views(8, false);
        let mut tsdf = Tsdf::new(FuseParams { voxel_mm: 0.25, max_field_mib: 1.0, fit_to_sampling: false, ..FuseParams::default() }).unwrap();
        for (c, p) in &views {
            tsdf.integrate(c, p);
        }
        assert!(tsdf.refused_updates() > 0);
        assert!(tsdf.memory_bytes() <= 1024 * 1024 + 4096 * 32, "{} bytes", tsdf.memory_bytes());
        // What was fused still meshes (the surface past the budget is missing, not broken).
        let (_, stats) = tsdf.mesh();
        assert_eq!((stats.non_manifold_edges, stats.boundary_edges), (0, 0));
        assert_eq!(Tsdf::new(FuseParams { max_field_mib: 0.5, ..FuseParams::default() }).err(), Some(crate::fuse::FuseParamsError::Budget(0.5)));
    }

    #[test]
    fn fragments_are_removed() {
        let mut views = sphere_views(24, false);
        // A second, tiny sphere's worth of points far off, in one view: a floating fragment.
        let (cloud, pose) = &mut views[0];
        let _ = pose;
        for i in 0..30 {
            for j in 0..30 {
                cloud.points.push([60.0 + i as f32 * 0.3, 60.0 + j as f32 * 0.3, 280.0]);
                cloud.colors.push([0, 0, 0]);
            }
        }
        let (_, stats) = fused(&views, true);
        assert!(stats.components_removed >= 1 && stats.triangles_removed > 0, "{stats:?}");
        assert_eq!(stats.boundary_edges, 0, "{stats:?}");
    }

    /// Each view's points within 6 px of its silhouette (seen at grazing angles: the ray
    /// within ≈ 70° of the surface) placed 1 mm too far out, as matches whose windows reach
    /// across the outline are: weighed down by their distance (`rim_weight_px`), the views
    /// that see that surface face-on decide it, and the mesh comes back onto the sphere;
    /// weighed alike, it keeps the error. The poles, which every camera sees only near its
    /// silhouette, are meshed either way: nothing is left uncovered.
    #[test]
    fn points_near_the_silhouette_weigh_less_and_still_cover_what_only_they_see() {
        let centre = Vector3::new(0.0f32, 0.0, 300.0);
        let views: Vec<(PointCloud, Isometry3<f64>)> = sphere_views(24, false)
            .into_iter()
            .map(|(mut c, pose)| {
                let cam_centre = pose.inverse() * nalgebra::Point3::from(centre.cast::<f64>());
                let mut rim = Vec::new();
                for p in &mut c.points {
                    // How squarely the camera sees the point (1: face-on).
                    let (v, q) = (Vector3::from(*p), cam_centre.coords.cast::<f32>());
                    let n = (v - q).normalize();
                    let facing = n.dot(&-v.normalize());
                    // The image distance to the outline grows with it; 255: far inside.
                    let d = ((facing - 0.1) * 30.0).clamp(1.0, 255.0) as u8;
                    if d <= 6 {
                        *p = (v + n * 1.0).into();
                    }
                    rim.push(if facing > 0.5 { 255 } else { d });
                }
                c.rim_px = Some(rim);
                (c, pose)
            })
            .collect();
        let mesh_of = |width: f64| {
            let mut tsdf = Tsdf::new(FuseParams { voxel_mm: 1.0, rim_weight_px: width, ..FuseParams::default() }).unwrap();
            for (c, p) in &views {
                tsdf.integrate(c, p);
            }
            let weighed = tsdf.rim_weighed_points();
            let (mesh, stats) = tsdf.mesh();
            let measured = &mesh.cloud.points[..stats.measured_vertices];
            let mut err: Vec<f32> = measured.iter().map(|p| ((Vector3::from(*p) - centre).norm() - 20.0).abs()).collect();
            err.sort_by(f32::total_cmp);
            // Measured vertices at the poles (above 60° of latitude), which no camera sees
            // but near its silhouette.
            let poles = measured.iter().filter(|p| (p[1] - centre.y).abs() > 17.3).count();
            (err[err.len() / 2], err[err.len() * 95 / 100], stats, weighed, poles)
        };
        let (median, p95, weighed, n, poles) = mesh_of(10.0);
        let (median_alike, p95_alike, alike, n_alike, poles_alike) = mesh_of(0.0);
        assert!(n > 0 && n_alike == 0, "{n} / {n_alike} points weighed down");
        assert!(median < 0.1 && median_alike > 2.0 * median, "median {median} mm weighed, {median_alike} alike");
        assert!(p95 < p95_alike, "p95 {p95} mm weighed, {p95_alike} alike");
        // The same surface covered: closed, and no more of it capped over.
        assert_eq!((weighed.boundary_edges, weighed.non_manifold_edges), (0, 0), "{weighed:?}");
        assert!(weighed.holes_filled <= alike.holes_filled && weighed.fill_area_mm2 <= alike.fill_area_mm2 + 50.0, "{weighed:?} against {alike:?}");
        assert!(poles > 100 && poles as f64 > 0.8 * poles_alike as f64, "{poles} measured vertices at the poles weighed, {poles_alike} alike");
    }
}
