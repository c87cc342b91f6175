//! `spinscan calibrate`: the stereo rig from chessboard pairs, the turntable's axis from a
//! board on the table, and capture through the daemon (docs/calibration.md).

use std::path::{Path, PathBuf};

use clap::{Args, Subcommand};

use super::daemon::{connect, daemon_err};
use super::{exit, input, output, progress, Failure};
use spinscan::calib::board::{BoardSize, DetectParams};
use spinscan::calib::job::{self, FoundPair, StereoJob};
use spinscan::calib::solve::{LensModel, SolveError, MIN_VIEWS};
use spinscan::calib::subpix::SubPixParams;
use spinscan::stereo::GrayView;

#[derive(Subcommand)]
pub enum CalibrateCommand {
    /// Both cameras and the rig from pairs of chessboard images: writes calib.yaml.
    Stereo(StereoArgs),
    /// The turntable's axis from a recording of a board standing on the table at several
    /// table angles: writes turntable.yaml (the file replay and the daemon read).
    Turntable(TurntableArgs),
    /// Captures calibration pairs through the daemon and solves them there: keeps a pair
    /// only when the board is found in both images (results under
    /// <state-dir>/calibrations/NAME/).
    Capture(CaptureArgs),
    /// Ends the daemon's calibration capture after its current pair (what it kept is solved).
    Stop(super::daemon::SocketArg),
}

#[derive(Args)]
pub struct CaptureArgs {
    /// Name of this calibration: letters, digits, '-', '_', '.'.
    pub name: String,
    /// `stereo` (the rig: hold the board up at varied poses) or `turntable` (the axis: stand
    /// the board on the table; the daemon turns it through ±--sweep-deg).
    #[arg(long, default_value = "stereo")]
    pub kind: String,
    /// Pairs to keep (default 20 for stereo, 9 for turntable).
    #[arg(long)]
    pub count: Option<u64>,
    /// Inner corners of the board, along a row × rows.
    #[arg(long, default_value = "9x6")]
    pub board: String,
    /// Side of one square as printed, mm.
    #[arg(long)]
    pub square_mm: f64,
    /// The lens model: 5, 8 or 14 coefficients (stereo).
    #[arg(long, default_value_t = 5)]
    pub model: u64,
    /// Turntable: the table turns from −SWEEP to +SWEEP degrees.
    #[arg(long, default_value_t = 45.0)]
    pub sweep_deg: f64,
    /// Follow the capture (pairs kept, why the last was not) until it is solved.
    #[arg(long)]
    pub watch: bool,
    #[command(flatten)]
    pub socket: super::daemon::SocketArg,
}

#[derive(Args)]
pub struct TurntableArgs {
    /// The recording: pairs of the board on the table, each with its `table_deg`.
    #[arg(long)]
    pub recording: PathBuf,
    /// The rig's calibration (from `calibrate stereo`); default: the recording's calib.yaml.
    #[arg(long)]
    pub calib: Option<PathBuf>,
    #[command(flatten)]
    pub board: BoardArgs,
    /// Where to write the axis (turntable.yaml: axis_point_mm, axis_dir, source, rms_px).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Also write the fit's figures (every pair's residual and angle check) as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// The board and how its corners are found (shared by the calibrate commands).
#[derive(Args, Clone)]
pub struct BoardArgs {
    /// Inner corners of the board, along a row × rows (a board of 10 × 7 squares is 9x6).
    #[arg(long, default_value = "9x6")]
    pub board: BoardSize,
    /// Side of one square as printed, mm (measure it: a printer's scaling changes it).
    #[arg(long)]
    pub square_mm: f64,
    /// Half-side of the window each corner is refined in, pixels (OpenCV's cornerSubPix
    /// winSize; shrunk where the squares are smaller).
    #[arg(long, default_value_t = SubPixParams::default().half_window)]
    pub corner_window: usize,
}

impl BoardArgs {
    fn detect(&self) -> Result<DetectParams, Failure> {
        if !(self.square_mm.is_finite() && self.square_mm > 0.0) {
            return Err(input(format!("--square-mm {}: expected the printed side of one square in mm, > 0", self.square_mm)));
        }
        if !(2..=30).contains(&self.corner_window) {
            return Err(input(format!("--corner-window {}: expected 2…30 pixels", self.corner_window)));
        }
        Ok(DetectParams { subpix: SubPixParams { half_window: self.corner_window, ..SubPixParams::default() }, ..DetectParams::default() })
    }
}

#[derive(Args)]
pub struct StereoArgs {
    /// Left images: a file-name pattern with `*` and `?` (quote it), e.g. 'DIR/left*.jpg'.
    #[arg(long, required_unless_present = "recording")]
    pub left: Option<String>,
    /// Right images, paired with the left ones by the part the wildcards match (left07.jpg
    /// with right07.jpg), or in sorted order when the names do not pair up.
    #[arg(long, required_unless_present = "recording")]
    pub right: Option<String>,
    /// A recording folder (frames.jsonl) instead of the two patterns: every pair in it.
    #[arg(long, conflicts_with_all = ["left", "right"])]
    pub recording: Option<PathBuf>,
    #[command(flatten)]
    pub board: BoardArgs,
    /// The lens model: 5 (k1 k2 p1 p2 k3), 8 (rational) or 14 (with thin prism and tilt).
    #[arg(long, default_value_t = 5)]
    pub model: u32,
    /// Where to write the calibration (OpenCV FileStorage YAML).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Also write the full report (every pair, both cameras, warnings) as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// The names of `dir`'s files matching `pattern` (`*`, `?`), each with what its wildcards
/// matched.
fn glob(pattern: &str) -> Result<Vec<(PathBuf, String)>, Failure> {
    let path = Path::new(pattern);
    let (dir, name) = match (path.parent(), path.file_name().and_then(|n| n.to_str())) {
        (Some(d), Some(n)) => (if d.as_os_str().is_empty() { Path::new(".") } else { d }, n),
        _ => return Err(input(format!("`{pattern}`: expected a file-name pattern such as DIR/left*.jpg"))),
    };
    if dir.to_string_lossy().contains(['*', '?']) {
        return Err(input(format!("`{pattern}`: wildcards may only be in the file name, not in the folder")));
    }
    let entries = std::fs::read_dir(dir).map_err(|e| input(format!("cannot list {}: {e}", dir.display())))?;
    let mut out = Vec::new();
    for e in entries.flatten() {
        let Some(n) = e.file_name().to_str().map(str::to_string) else { continue };
        if let Some(matched) = wildcard(name.as_bytes(), n.as_bytes()) {
            if e.path().is_file() {
                out.push((e.path(), String::from_utf8_lossy(&matched).into_owned()));
            }
        }
    }
    out.sort_by(|a, b| natural(&a.0.to_string_lossy(), &b.0.to_string_lossy()));
    Ok(out)
}

/// Matches `name` against `pat`; the bytes the wildcards took, concatenated.
fn wildcard(pat: &[u8], name: &[u8]) -> Option<Vec<u8>> {
    match pat.first() {
        None => name.is_empty().then(Vec::new),
        Some(b'*') => (0..=name.len()).rev().find_map(|k| {
            wildcard(&pat[1..], &name[k..]).map(|mut rest| {
                let mut m = name[..k].to_vec();
                m.append(&mut rest);
                m
            })
        }),
        Some(b'?') => {
            let (&c, rest) = name.split_first()?;
            wildcard(&pat[1..], rest).map(|mut r| {
                r.insert(0, c);
                r
            })
        }
        Some(&c) => (name.first() == Some(&c)).then(|| wildcard(&pat[1..], &name[1..])).flatten(),
    }
}

/// Orders names with their digit runs compared as numbers (img2 before img10).
fn natural(a: &str, b: &str) -> std::cmp::Ordering {
    let key = |s: &str| -> Vec<(String, u64)> {
        let mut out = Vec::new();
        let mut text = String::new();
        let mut num = String::new();
        for ch in s.chars() {
            if ch.is_ascii_digit() {
                num.push(ch);
            } else {
                if !num.is_empty() {
                    out.push((std::mem::take(&mut text), num.parse().unwrap_or(u64::MAX)));
                    num.clear();
                }
                text.push(ch);
            }
        }
        out.push((text, num.parse().unwrap_or(0)));
        out
    };
    key(a).cmp(&key(b)).then_with(|| a.cmp(b))
}

/// Pairs the left and right files: by what the wildcards matched when the names pair up (at
/// least half of them find a partner), else in sorted order when the counts agree.
/// Unpaired files are named in warnings.
fn pair_files(left: Vec<(PathBuf, String)>, right: Vec<(PathBuf, String)>) -> Result<Vec<(PathBuf, PathBuf)>, Failure> {
    let by_key: std::collections::HashMap<&str, &PathBuf> = right.iter().map(|(p, k)| (k.as_str(), p)).collect();
    let matched = left.iter().filter(|(_, k)| by_key.contains_key(k.as_str())).count();
    // Names pair up when most of them find their partner (a few missing is a lab's normal;
    // one accidental match between unrelated names is not a pairing).
    if matched > 0 && 2 * matched >= left.len().min(right.len()) {
        let left_keys: std::collections::HashSet<&str> = left.iter().map(|(_, k)| k.as_str()).collect();
        for (p, k) in &left {
            if !by_key.contains_key(k.as_str()) {
                tracing::warn!("{}: no right image matched `{k}` — left out", p.display());
            }
        }
        for (p, k) in &right {
            if !left_keys.contains(k.as_str()) {
                tracing::warn!("{}: no left image matched `{k}` — left out", p.display());
            }
        }
        return Ok(left.iter().filter_map(|(p, k)| by_key.get(k.as_str()).map(|r| (p.clone(), (*r).clone()))).collect());
    }
    if left.len() != right.len() {
        return Err(input(format!(
            "{} left images but {} right images, and their names do not pair up (what the wildcards match differs): give patterns whose wildcards match the same part, e.g. left*.jpg and right*.jpg",
            left.len(),
            right.len()
        )));
    }
    Ok(left.into_iter().zip(right).map(|(l, r)| (l.0, r.0)).collect())
}

/// The pairs of a recording folder, from its frames.jsonl (its calibration is not needed).
fn recording_pairs(dir: &Path) -> Result<Vec<(PathBuf, PathBuf)>, Failure> {
    Ok(recording_frames(dir)?.into_iter().map(|f| (dir.join(f.left), dir.join(f.right))).collect())
}

/// The lines of a recording's frames.jsonl (its calibration is not needed).
fn recording_frames(dir: &Path) -> Result<Vec<spinscan::recording::FrameEntry>, Failure> {
    let path = dir.join("frames.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|e| input(format!("{}: {e} (expected a recording folder with frames.jsonl)", path.display())))?;
    Ok(spinscan::recording::parse_frames(&path, &text).map_err(input)?.0)
}

fn name_of(p: &Path) -> String {
    p.file_name().map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into_owned())
}

pub fn cmd_stereo(a: StereoArgs) -> Result<(), Failure> {
    let detect = a.board.detect()?;
    let model = LensModel::from_count(a.model).ok_or_else(|| input(format!("--model {}: expected 5, 8 or 14 coefficients", a.model)))?;
    let job = StereoJob { board: a.board.board, square_mm: a.board.square_mm, model, detect };
    let files = match (&a.recording, &a.left, &a.right) {
        (Some(dir), _, _) => recording_pairs(dir)?,
        (None, Some(l), Some(r)) => {
            let (lf, rf) = (glob(l)?, glob(r)?);
            if lf.is_empty() || rf.is_empty() {
                let which = if lf.is_empty() { l } else { r };
                return Err(Failure { code: exit::INPUT, message: format!("no file matches `{which}`") });
            }
            pair_files(lf, rf)?
        }
        _ => return Err(input("give --left and --right patterns, or --recording DIR")),
    };
    let total = files.len();
    let mut size: Option<(u32, u32)> = None;
    let mut found: Vec<FoundPair> = Vec::new();
    let mut rejected: Vec<(String, String, String)> = Vec::new();
    for (k, (lp, rp)) in files.iter().enumerate() {
        progress::show(format!("calibrate: looking for {} boards in pair {}/{total} ({} found so far)", job.board, k + 1, found.len()));
        let (ln, rn) = (name_of(lp), name_of(rp));
        let pair = super::load_pair(lp, rp).and_then(|(l, r)| {
            let this = (l.width as u32, l.height as u32);
            match size {
                Some(s) if s != this => Err(input(format!("{ln} is {}×{} but the first pair was {}×{}: one rig, one image size", this.0, this.1, s.0, s.1))),
                _ => Ok((l, r, this)),
            }
        });
        let (l, r, this) = match pair {
            Ok(v) => v,
            Err(f) => {
                tracing::warn!("{} — left out", f.message);
                rejected.push((ln, rn, f.message));
                continue;
            }
        };
        size = Some(this);
        let lv = GrayView::new(l.width, l.height, &l.gray).expect("decoded size");
        let rv = GrayView::new(r.width, r.height, &r.gray).expect("decoded size");
        match job::find_pair(&job, &ln, &lv, &rn, &rv) {
            Ok(p) => found.push(p),
            Err(why) => {
                tracing::warn!("{why} — pair left out");
                rejected.push((ln, rn, why.to_string()));
            }
        }
    }
    progress::finish();
    println!("boards found in {} of {total} pairs", found.len());
    let Some(size) = size.filter(|_| found.len() >= MIN_VIEWS) else {
        let see = if rejected.is_empty() { "" } else { " (the reasons the others were left out are above)" };
        return Err(input(format!("boards found in {} of {total} pairs; a calibration needs at least {MIN_VIEWS}{see}", found.len())));
    };
    let (sol, report) = job::calibrate(&job, size, &found, &rejected).map_err(|e| match e {
        SolveError::TooFewViews { .. } | SolveError::Degenerate => input(e),
    })?;
    spinscan::io::write_atomic(&a.output, job::calib_yaml(&sol).as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", a.output.display())))?;
    if let Some(path) = &a.json {
        spinscan::io::write_atomic(path, serde_json::to_string_pretty(&report).expect("plain numbers").as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    print_report(&report);
    println!("wrote {}", a.output.display());
    Ok(())
}

pub fn cmd_turntable(a: TurntableArgs) -> Result<(), Failure> {
    use spinscan::calib::solve::{board_points, TargetView};
    use spinscan::calib::turntable::{fit_axis, TablePair};
    let detect = a.board.detect()?;
    let job = StereoJob { board: a.board.board, square_mm: a.board.square_mm, model: LensModel::Five, detect };
    let calib_path = a.calib.clone().unwrap_or_else(|| a.recording.clone());
    let calib = spinscan::calib::StereoCalib::load(&calib_path).map_err(input)?;
    if a.calib.is_none() {
        tracing::warn!("no --calib: using the recording's own calibration ({}); give the one `calibrate stereo` wrote if that is not it", calib_path.display());
    }
    let path = a.recording.join("frames.jsonl");
    let frames = recording_frames(&a.recording)?;
    let object = board_points(job.board.cols, job.board.rows, job.square_mm);
    let mut pairs = Vec::new();
    let mut names = Vec::new();
    let total = frames.len();
    for (k, f) in frames.iter().enumerate() {
        progress::show(format!("calibrate turntable: looking for {} boards in pair {}/{total} ({} found so far)", job.board, k + 1, pairs.len()));
        let Some(deg) = f.table_deg else {
            tracing::warn!("{}:{}: no table_deg — this pair cannot place the axis, left out", path.display(), f.line);
            continue;
        };
        let (lp, rp) = (a.recording.join(&f.left), a.recording.join(&f.right));
        let (l, r) = match super::load_pair(&lp, &rp) {
            Ok(v) => v,
            Err(e) => {
                tracing::warn!("{} — left out", e.message);
                continue;
            }
        };
        if let Some((w, h)) = calib.image_size {
            if (l.width as u32, l.height as u32) != (w, h) {
                return Err(input(format!("{} is {}×{} but the calibration is for {w}×{h} images", lp.display(), l.width, l.height)));
            }
        }
        let lv = GrayView::new(l.width, l.height, &l.gray).expect("decoded size");
        let rv = GrayView::new(r.width, r.height, &r.gray).expect("decoded size");
        match job::find_pair(&job, &f.left, &lv, &f.right, &rv) {
            Ok(p) => {
                names.push((f.seq, deg));
                pairs.push(TablePair {
                    table_deg: deg,
                    left: TargetView { object: object.clone(), image: p.left.points },
                    right: TargetView { object: object.clone(), image: p.right.points },
                });
            }
            Err(why) => tracing::warn!("{why} — pair left out"),
        }
    }
    progress::finish();
    println!("boards found in {} of {total} pairs", pairs.len());
    let fit = fit_axis(&calib, &pairs).map_err(input)?;
    let axis = spinscan::recording::TurntableAxis { axis_point_mm: fit.point_mm.into(), axis_dir: fit.dir.into(), source: "calibrated".into() };
    let yaml = format!("{}rms_px: {:.6}\npairs: {}\n", axis.to_yaml(), fit.rms_px, pairs.len());
    spinscan::io::write_atomic(&a.output, yaml.as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", a.output.display())))?;
    println!("{:>6} {:>9} {:>8} {:>11}", "seq", "table°", "rms px", "angle err°");
    for ((seq, deg), (rms, err)) in names.iter().zip(&fit.pairs) {
        println!("{seq:>6} {deg:>9.2} {rms:>8.3} {err:>11.4}");
    }
    println!(
        "axis point [{:.3}, {:.3}, {:.3}] mm, direction [{:.6}, {:.6}, {:.6}], rms {:.4} px",
        fit.point_mm.x, fit.point_mm.y, fit.point_mm.z, fit.dir.x, fit.dir.y, fit.dir.z, fit.rms_px
    );
    if let Some(path) = &a.json {
        let about = serde_json::json!({
            "axis_point_mm": axis.axis_point_mm, "axis_dir": axis.axis_dir, "rms_px": fit.rms_px, "pairs_used": pairs.len(), "pairs_total": total,
            "pairs": names.iter().zip(&fit.pairs).map(|((seq, deg), (rms, err))| serde_json::json!({"seq": seq, "table_deg": deg, "rms_px": rms, "angle_error_deg": err})).collect::<Vec<_>>(),
        });
        spinscan::io::write_atomic(path, serde_json::to_string_pretty(&about).expect("plain numbers").as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    println!("wrote {}", a.output.display());
    Ok(())
}

fn print_report(r: &job::StereoReport) {
    println!("{:<14} {:<14} {:>8} {:>8} {:>8} {:>8}", "left", "right", "rms L px", "rms R px", "board L%", "board R%");
    for p in &r.pairs {
        match (p.used, &p.reason) {
            (true, _) => println!(
                "{:<14} {:<14} {:>8.3} {:>8.3} {:>8.1} {:>8.1}",
                p.left,
                p.right,
                p.rms_left_px.unwrap_or(f64::NAN),
                p.rms_right_px.unwrap_or(f64::NAN),
                p.board_area_left_pct.unwrap_or(f64::NAN),
                p.board_area_right_pct.unwrap_or(f64::NAN)
            ),
            (false, why) => println!("{:<14} {:<14} left out: {}", p.left, p.right, why.as_deref().unwrap_or("")),
        }
    }
    println!("pairs used: {} of {}", r.pairs_used, r.pairs_total);
    for (side, c) in [("left", &r.left), ("right", &r.right)] {
        println!(
            "{side:<5} fx {:.2} fy {:.2} cx {:.2} cy {:.2}  distortion [{}]  coverage {:.0} %",
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            c.distortion.iter().map(|d| format!("{d:.5}")).collect::<Vec<_>>().join(", "),
            c.coverage_pct
        );
    }
    println!("T [{:.3}, {:.3}, {:.3}] mm, baseline {:.3} mm", r.t_mm[0], r.t_mm[1], r.t_mm[2], r.baseline_mm);
    println!("rms_left {:.4} px  rms_right {:.4} px  rms_stereo {:.4} px", r.rms_left, r.rms_right, r.rms_stereo);
    for w in &r.warnings {
        tracing::warn!("{w}");
    }
}


pub fn cmd_capture(a: CaptureArgs) -> Result<(), Failure> {
    use spinscan::control::protocol::CalibCaptureParams;
    let mut c = connect(&a.socket)?;
    if a.watch {
        // Subscribe first so no event of this capture is missed.
        c.subscribe().map_err(daemon_err)?;
    }
    let params = CalibCaptureParams {
        name: a.name.clone(),
        kind: Some(a.kind.clone()),
        count: a.count,
        board: Some(a.board.clone()),
        square_mm: a.square_mm,
        model: Some(a.model),
        sweep_deg: Some(a.sweep_deg),
        max_pairs: None,
    };
    let started = c.calib_capture(&params).map_err(daemon_err)?;
    eprintln!(
        "calibration {} ({}) started: keeping {} pairs, folder {}",
        a.name,
        a.kind,
        started["count"],
        started["dir"].as_str().unwrap_or("?")
    );
    if a.kind == "stereo" {
        eprintln!("hold the {} board up to both cameras; move it between pairs: near the image's corners and edges, tilted up to 40°", a.board);
    }
    if !a.watch {
        return Ok(());
    }
    c.set_timeout(None).map_err(daemon_err)?;
    loop {
        let n = c.next_notification().map_err(daemon_err)?;
        let p = &n.params;
        if p["name"].as_str() != Some(a.name.as_str()) {
            continue;
        }
        match n.method.as_str() {
            "calib.progress" => {
                let last = p["last_rejection"].as_str().map(|r| format!(" — last pair: {r}")).unwrap_or_default();
                let table = p["table_deg"].as_f64().filter(|_| a.kind == "turntable").map(|d| format!(", table {d:.1}°")).unwrap_or_default();
                let cover = p["coverage_left_pct"].as_f64().filter(|_| a.kind == "stereo").map(|c| format!(", boards cover {c:.0} % of the left image")).unwrap_or_default();
                progress::show(format!("{}: kept {}/{} pairs, {} seen{cover}{table}{last}", a.name, p["kept"], p["count"], p["seen"]));
            }
            "calib.state" if p["status"] != "running" => {
                progress::finish();
                let status = p["status"].as_str().unwrap_or("?");
                let reason = p["reason"].as_str().map(|r| format!(": {r}")).unwrap_or_default();
                if a.socket.json {
                    println!("{}", serde_json::to_string_pretty(p).expect("plain values"));
                } else {
                    let r = &p["result"];
                    println!("calibration {} {status}{reason}", a.name);
                    if let Some(file) = r["file"].as_str() {
                        match a.kind.as_str() {
                            "turntable" => {
                                let v = |key: &str| r[key].as_array().map(|v| v.iter().map(|x| format!("{:.4}", x.as_f64().unwrap_or(f64::NAN))).collect::<Vec<_>>().join(", ")).unwrap_or_default();
                                println!("axis point [{}] mm, direction [{}], rms {:.4} px from {} pairs", v("axis_point_mm"), v("axis_dir"), r["rms_px"].as_f64().unwrap_or(f64::NAN), r["pairs"])
                            }
                            _ => println!(
                                "rms_left {:.4} px  rms_right {:.4} px  rms_stereo {:.4} px, baseline {:.3} mm from {} pairs; coverage {:.0} % / {:.0} %",
                                r["rms_left"].as_f64().unwrap_or(f64::NAN),
                                r["rms_right"].as_f64().unwrap_or(f64::NAN),
                                r["rms_stereo"].as_f64().unwrap_or(f64::NAN),
                                r["baseline_mm"].as_f64().unwrap_or(f64::NAN),
                                r["pairs"],
                                r["coverage_left_pct"].as_f64().unwrap_or(f64::NAN),
                                r["coverage_right_pct"].as_f64().unwrap_or(f64::NAN)
                            ),
                        }
                        for w in r["warnings"].as_array().into_iter().flatten().filter_map(|w| w.as_str()) {
                            tracing::warn!("{w}");
                        }
                        println!("wrote {file}");
                    }
                }
                return match (status, p["result"]["file"].is_string()) {
                    ("complete", _) | ("interrupted", true) => Ok(()),
                    _ => Err(Failure { code: exit::DAEMON, message: format!("calibration {} {status}{reason}", a.name) }),
                };
            }
            "device.error" => tracing::warn!("device error: {}", p["message"].as_str().unwrap_or("?")),
            _ => {}
        }
    }
}

pub fn cmd_stop(s: super::daemon::SocketArg) -> Result<(), Failure> {
    let mut c = connect(&s)?;
    let v = c.calib_stop().map_err(daemon_err)?;
    println!("stopping calibration {} after its current pair; what it kept is solved", v["name"].as_str().unwrap_or("?"));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wildcards_report_what_they_matched() {
        assert_eq!(wildcard(b"left*.jpg", b"left07.jpg"), Some(b"07".to_vec()));
        assert_eq!(wildcard(b"l?ft*.jpg", b"left07.jpg"), Some(b"e07".to_vec()));
        assert_eq!(wildcard(b"left*.jpg", b"right07.jpg"), None);
        assert_eq!(wildcard(b"*", b""), Some(Vec::new()));
    }

    #[test]
    fn names_sort_by_their_numbers() {
        let mut v = vec!["img10.png", "img2.png", "img1.png"];
        v.sort_by(|a, b| natural(a, b));
        assert_eq!(v, ["img1.png", "img2.png", "img10.png"]);
    }
}
