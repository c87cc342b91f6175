//! `spinscan register`: two scans by ICP, or a ring of scans into Stanford `.conf` poses.

use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use serde_json::json;

use super::{input, median, output, Failure};
use spinscan::io;
use spinscan::register::{self, IcpParams};

#[derive(Args)]
pub struct RegisterArgs {
    /// SOURCE.ply TARGET.ply; with --ring, the scans of the ring in order around it.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Register a ring of scans (each to the one before it, then the last to the first, and
    /// close the loop) and write their poses with --conf-out.
    #[arg(long)]
    pub ring: bool,
    /// Initial guess, {"target_from_source": [[4x4 row-major]]}; default identity.
    #[arg(long, conflicts_with = "ring")]
    pub init: Option<PathBuf>,
    /// Initial poses of the ring's scans (Stanford .conf); default identity for all.
    #[arg(long, requires = "ring")]
    pub init_conf: Option<PathBuf>,
    /// Where the ring's registered poses go (Stanford .conf).
    #[arg(long, requires = "ring")]
    pub conf_out: Option<PathBuf>,
    /// point-to-plane (Chen–Medioni) or point-to-point (Besl–McKay, the paper's).
    #[arg(long, default_value = "point-to-plane")]
    pub method: String,
    /// Largest distance between corresponding points, in the files' units. Default: 10 × the
    /// target's median point spacing.
    #[arg(long, allow_hyphen_values = true)]
    pub max_distance: Option<f64>,
    /// Run the registration K times and report the median time.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// At most this many source points take part, evenly spread (0 = all). The target keeps
    /// every point.
    #[arg(long, default_value_t = 2_000)]
    pub max_source_points: usize,
    /// ICP iterations at most.
    #[arg(long, default_value_t = 60)]
    pub max_iterations: usize,
    /// Keep only this fraction of the closest pairs each iteration (1 = no trimming).
    #[arg(long, default_value_t = 1.0)]
    pub trim: f64,
    /// Result JSON: target_from_source, fitness, rmse, iterations, register_ms, …
    #[arg(short = 'o', long = "out")]
    pub out: Option<PathBuf>,
}

pub fn read_scan(path: &Path) -> Result<Vec<[f32; 3]>, Failure> {
    let mesh = io::ply::read_ply(path).map_err(input)?;
    if mesh.cloud.points.is_empty() {
        return Err(input(format!("{}: the PLY file has no vertices", path.display())));
    }
    Ok(mesh.cloud.points)
}

pub fn icp_params_of(a: &RegisterArgs, max_distance: f64) -> Result<IcpParams, Failure> {
    let mut p = IcpParams::new(max_distance);
    p.method = a.method.parse().map_err(input)?;
    p.max_iterations = a.max_iterations;
    p.max_source_points = a.max_source_points;
    p.trim = a.trim;
    p.check().map_err(input)?;
    Ok(p)
}

pub fn cmd_register(a: RegisterArgs) -> Result<(), Failure> {
    if a.repeat == 0 {
        return Err(input("--repeat must be at least 1"));
    }
    if a.ring {
        return cmd_register_ring(a);
    }
    let [source_path, target_path] = a.files.as_slice() else {
        return Err(input(format!("expected SOURCE.ply TARGET.ply, got {} files (use --ring for more than two)", a.files.len())));
    };
    let Some(out) = &a.out else { return Err(input("missing -o OUT.json")) };
    let source = read_scan(source_path)?;
    let target = read_scan(target_path)?;
    let init = match &a.init {
        Some(p) => io::poses::read_transform_json(p).map_err(input)?,
        None => nalgebra::Isometry3::identity(),
    };
    let max_distance = match a.max_distance {
        Some(d) => d,
        None => {
            let tree = register::KdTree::build(target.clone(), &target_path.display().to_string()).map_err(input)?;
            10.0 * tree.median_spacing()
        }
    };
    let params = icp_params_of(&a, max_distance)?;
    let mut times = Vec::new();
    let mut result = None;
    for _ in 0..a.repeat {
        let t0 = Instant::now();
        let mut tgt = register::icp::Target::cells(target.clone(), params.cell_size(), params.normals, &target_path.display().to_string()).map_err(input)?;
        let r = register::icp(&source, &mut tgt, &init, &params).map_err(input)?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        result = Some(r);
    }
    let r = result.unwrap();
    if let Some(w) = r.degeneracy_warning() {
        eprintln!("register: warning: {w}");
    }
    if !r.converged {
        eprintln!("register: warning: ICP did not converge within {} iterations", params.max_iterations);
    }
    let mut j = io::poses::transform_json(&r.transform);
    j["fitness"] = json!(r.fitness);
    j["rmse"] = json!(r.rmse);
    j["iterations"] = json!(r.iterations);
    j["register_ms"] = json!(median(times.clone()));
    j["register_ms_runs"] = json!(times);
    j["converged"] = json!(r.converged);
    j["correspondences"] = json!(r.correspondences);
    j["method"] = json!(a.method);
    j["max_distance"] = json!(max_distance);
    j["source_points"] = json!(source.len());
    j["target_points"] = json!(target.len());
    j["degenerate"] = json!(r.degenerate.iter().map(|d| d.to_string()).collect::<Vec<_>>());
    j["conditioning"] = json!(r.conditioning);
    io::write_atomic(out, serde_json::to_string_pretty(&j).unwrap().as_bytes()).map_err(|e| output(format!("{}: {e}", out.display())))?;
    println!("{}", json!({"out": out, "fitness": r.fitness, "rmse": r.rmse, "iterations": r.iterations, "register_ms": j["register_ms"], "converged": r.converged}));
    Ok(())
}

pub fn cmd_register_ring(a: RegisterArgs) -> Result<(), Failure> {
    let Some(conf_out) = &a.conf_out else { return Err(input("--ring needs --conf-out OUT.conf")) };
    if a.files.len() < 3 {
        return Err(input(format!("a ring needs at least 3 scans, got {}", a.files.len())));
    }
    let names: Vec<String> = a.files.iter().map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()).collect();
    let init_conf = match &a.init_conf {
        Some(p) => Some(io::poses::Conf::read(p).map_err(input)?),
        None => None,
    };
    let init_world: Vec<nalgebra::Isometry3<f64>> = match &init_conf {
        Some(conf) => names
            .iter()
            .map(|n| conf.get(n).map(|p| p.world_from_scan).ok_or_else(|| input(format!("{} has no `bmesh {n}` line", a.init_conf.as_ref().unwrap().display()))))
            .collect::<Result<_, _>>()?,
        None => vec![nalgebra::Isometry3::identity(); names.len()],
    };
    let scans: Vec<Vec<[f32; 3]>> = a.files.iter().map(|p| read_scan(p)).collect::<Result<_, _>>()?;
    let max_distance = match a.max_distance {
        Some(d) => d,
        None => 10.0 * register::KdTree::build(scans[0].clone(), &names[0]).map_err(input)?.median_spacing(),
    };
    let params = icp_params_of(&a, max_distance)?;
    let t0 = Instant::now();
    let ring = register::ring::register_ring(&scans, &init_world, &params).map_err(input)?;
    for (k, e) in ring.edges.iter().enumerate() {
        let (i, j) = (e.source, e.target);
        eprintln!("register: {} → {}: fitness {:.3}, rmse {:.6}, {} iterations{}", names[i], names[j], e.icp.fitness, e.icp.rmse, e.icp.iterations, if e.icp.converged { "" } else { " (not converged)" });
        if let Some(w) = e.icp.degeneracy_warning() {
            eprintln!("register: warning: edge {k}: {w}");
        }
    }
    eprintln!("register: loop closed: {:.4}° and {:.6} apart before spreading", ring.loop_error_deg, ring.loop_error_translation);
    let conf = io::poses::Conf {
        camera: init_conf.and_then(|c| c.camera),
        poses: names.iter().zip(&ring.world_from_scan).map(|(n, w)| io::poses::ConfPose { name: n.clone(), world_from_scan: *w }).collect(),
    };
    io::write_atomic(conf_out, conf.to_text().as_bytes()).map_err(|e| output(format!("{}: {e}", conf_out.display())))?;
    println!("{}", json!({"conf_out": conf_out, "scans": names.len(), "loop_error_deg": ring.loop_error_deg, "loop_error_translation": ring.loop_error_translation, "register_ms": t0.elapsed().as_secs_f64() * 1e3}));
    Ok(())
}
