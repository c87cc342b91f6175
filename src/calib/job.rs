//! A stereo calibration as a lab runs it: boards found in each pair (or the reason not),
//! the rig solved from the pairs kept, and a report of every pair — what `spinscan calibrate
//! stereo` and the daemon's calibration capture both do. No IO: images come in decoded.

use serde::Serialize;

use super::board::{self, BoardCorners, BoardSize, DetectFailure, DetectParams};
use super::solve::{self, board_points, LensModel, SolveError, StereoSolution, TargetView};
use crate::stereo::GrayView;

/// What to calibrate with.
#[derive(Debug, Clone, Copy)]
pub struct StereoJob {
    pub board: BoardSize,
    /// Side of one square, mm.
    pub square_mm: f64,
    pub model: LensModel,
    pub detect: DetectParams,
}

/// The boards found in one pair.
#[derive(Debug, Clone)]
pub struct FoundPair {
    pub left_name: String,
    pub right_name: String,
    pub left: BoardCorners,
    pub right: BoardCorners,
}

/// Why a pair was not kept: the image(s) without a board, and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PairRejected {
    #[error("{name}: {why}")]
    One { name: String, why: DetectFailure },
    #[error("{left} and {right}: {why}")]
    BothAlike { left: String, right: String, why: DetectFailure },
    #[error("{left}: {left_why}; {right}: {right_why}")]
    Both { left: String, left_why: DetectFailure, right: String, right_why: DetectFailure },
}

/// Finds the board in both images of a pair; the error names the image(s) and why.
pub fn find_pair(job: &StereoJob, left_name: &str, left: &GrayView, right_name: &str, right: &GrayView) -> Result<FoundPair, PairRejected> {
    let l = board::detect(left, job.board, &job.detect);
    let r = board::detect(right, job.board, &job.detect);
    match (l, r) {
        (Ok(left), Ok(right)) => Ok(FoundPair { left_name: left_name.to_string(), right_name: right_name.to_string(), left, right }),
        (Err(why), Ok(_)) => Err(PairRejected::One { name: left_name.to_string(), why }),
        (Ok(_), Err(why)) => Err(PairRejected::One { name: right_name.to_string(), why }),
        (Err(a), Err(b)) if a == b => Err(PairRejected::BothAlike { left: left_name.to_string(), right: right_name.to_string(), why: a }),
        (Err(left_why), Err(right_why)) => Err(PairRejected::Both { left: left_name.to_string(), left_why, right: right_name.to_string(), right_why }),
    }
}

/// One row of the report's pair table.
#[derive(Debug, Clone, Serialize)]
pub struct PairRow {
    pub left: String,
    pub right: String,
    pub used: bool,
    /// Why the pair was left out (`used` false).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Reprojection RMS at the joint solution, pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms_left_px: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms_right_px: Option<f64>,
    /// The board's share of each image, percent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub board_area_left_pct: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub board_area_right_pct: Option<f64>,
    /// Median corner spacing and edge width (blur) in the left image, pixels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub spacing_px: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub edge_px: Option<f64>,
}

/// One camera's figures in the report.
#[derive(Debug, Clone, Serialize)]
pub struct CameraRow {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub distortion: Vec<f64>,
    /// Share of the image covered by at least one board, percent (cells of 1/16 of each side).
    pub coverage_pct: f64,
}

/// The whole calibration report (`--json`).
#[derive(Debug, Clone, Serialize)]
pub struct StereoReport {
    pub board: String,
    pub square_mm: f64,
    pub model: usize,
    pub image_width: u32,
    pub image_height: u32,
    pub pairs_total: usize,
    pub pairs_used: usize,
    pub rms_left: f64,
    pub rms_right: f64,
    pub rms_stereo: f64,
    pub baseline_mm: f64,
    pub t_mm: [f64; 3],
    pub left: CameraRow,
    pub right: CameraRow,
    pub pairs: Vec<PairRow>,
    pub warnings: Vec<String>,
}

/// Coverage below this share of an image draws a warning.
pub const MIN_COVERAGE_PCT: f64 = 50.0;

/// The quadrilateral of a board's outer corners.
fn outline(b: &BoardCorners, size: BoardSize) -> [[f64; 2]; 4] {
    let (c, r) = (size.cols, size.rows);
    [b.points[0], b.points[c - 1], b.points[c * r - 1], b.points[c * (r - 1)]]
}

fn inside(q: &[[f64; 2]; 4], x: f64, y: f64) -> bool {
    let mut sign = 0.0;
    for k in 0..4 {
        let (a, b) = (q[k], q[(k + 1) % 4]);
        let cross = (b[0] - a[0]) * (y - a[1]) - (b[1] - a[1]) * (x - a[0]);
        if cross != 0.0 {
            if sign != 0.0 && cross.signum() != sign {
                return false;
            }
            sign = cross.signum();
        }
    }
    true
}

fn area_pct(q: &[[f64; 2]; 4], size: (u32, u32)) -> f64 {
    let a: f64 = (0..4).map(|k| q[k][0] * q[(k + 1) % 4][1] - q[(k + 1) % 4][0] * q[k][1]).sum::<f64>().abs() / 2.0;
    100.0 * a / (size.0 as f64 * size.1 as f64)
}

fn coverage_pct(outlines: &[[[f64; 2]; 4]], size: (u32, u32)) -> f64 {
    const CELLS: usize = 16;
    let mut covered = 0;
    for j in 0..CELLS {
        for i in 0..CELLS {
            let x = (i as f64 + 0.5) * size.0 as f64 / CELLS as f64;
            let y = (j as f64 + 0.5) * size.1 as f64 / CELLS as f64;
            if outlines.iter().any(|q| inside(q, x, y)) {
                covered += 1;
            }
        }
    }
    100.0 * covered as f64 / (CELLS * CELLS) as f64
}

/// The share of each image (left, right) the boards of `found` cover so far, percent.
pub fn coverage(found: &[FoundPair], board: BoardSize, size: (u32, u32)) -> (f64, f64) {
    let lo: Vec<_> = found.iter().map(|p| outline(&p.left, board)).collect();
    let ro: Vec<_> = found.iter().map(|p| outline(&p.right, board)).collect();
    (coverage_pct(&lo, size), coverage_pct(&ro, size))
}

/// Solves the rig from the pairs found and writes the report; `rejected` are the pairs left
/// out, with their reasons, in the order they came (listed after the pairs used).
pub fn calibrate(job: &StereoJob, size: (u32, u32), found: &[FoundPair], rejected: &[(String, String, String)]) -> Result<(StereoSolution, StereoReport), SolveError> {
    let object = board_points(job.board.cols, job.board.rows, job.square_mm);
    let views = |f: fn(&FoundPair) -> &BoardCorners| -> Vec<TargetView> { found.iter().map(|p| TargetView { object: object.clone(), image: f(p).points.clone() }).collect() };
    let (left, right) = (views(|p| &p.left), views(|p| &p.right));
    let sol = solve::calibrate_stereo(&left, &right, size, job.model)?;
    let mut warnings = Vec::new();
    let cam_row = |c: &super::Camera, outlines: &[[[f64; 2]; 4]]| CameraRow {
        fx: c.k[(0, 0)],
        fy: c.k[(1, 1)],
        cx: c.k[(0, 2)],
        cy: c.k[(1, 2)],
        distortion: c.distortion.coeffs().to_vec(),
        coverage_pct: coverage_pct(outlines, size),
    };
    let lo: Vec<_> = found.iter().map(|p| outline(&p.left, job.board)).collect();
    let ro: Vec<_> = found.iter().map(|p| outline(&p.right, job.board)).collect();
    let (lrow, rrow) = (cam_row(&sol.calib.left, &lo), cam_row(&sol.calib.right, &ro));
    for (side, row) in [("left", &lrow), ("right", &rrow)] {
        if row.coverage_pct < MIN_COVERAGE_PCT {
            warnings.push(format!(
                "the boards cover {:.0} % of the {side} image (want ≥ {MIN_COVERAGE_PCT:.0} %): the lens distortion is only measured where boards were — add pairs with the board near the image's edges and corners",
                row.coverage_pct
            ));
        }
    }
    let mut errs: Vec<f64> = sol.pair_rms.iter().map(|p| p.0.max(p.1)).collect();
    errs.sort_by(f64::total_cmp);
    let typical = errs[errs.len() / 2];
    let mut pairs = Vec::new();
    for (k, p) in found.iter().enumerate() {
        let (l, r) = sol.pair_rms[k];
        if l.max(r) > 3.0 * typical && l.max(r) > 0.5 {
            warnings.push(format!(
                "pair {} / {}: reprojection {:.2} px, {:.0}× the typical pair's — a board that moved between the two exposures, or a misdetection? Leave it out if it recurs",
                p.left_name,
                p.right_name,
                l.max(r),
                l.max(r) / typical
            ));
        }
        pairs.push(PairRow {
            left: p.left_name.clone(),
            right: p.right_name.clone(),
            used: true,
            reason: None,
            rms_left_px: Some(l),
            rms_right_px: Some(r),
            board_area_left_pct: Some(area_pct(&lo[k], size)),
            board_area_right_pct: Some(area_pct(&ro[k], size)),
            spacing_px: Some(p.left.spacing_px),
            edge_px: Some(p.left.edge_px),
        });
    }
    for (l, r, why) in rejected {
        pairs.push(PairRow {
            left: l.clone(),
            right: r.clone(),
            used: false,
            reason: Some(why.clone()),
            rms_left_px: None,
            rms_right_px: None,
            board_area_left_pct: None,
            board_area_right_pct: None,
            spacing_px: None,
            edge_px: None,
        });
    }
    let t = sol.calib.t_mm;
    let report = StereoReport {
        board: format!("{}x{}", job.board.cols, job.board.rows),
        square_mm: job.square_mm,
        model: job.model.coefficients(),
        image_width: size.0,
        image_height: size.1,
        pairs_total: found.len() + rejected.len(),
        pairs_used: found.len(),
        rms_left: sol.rms_left,
        rms_right: sol.rms_right,
        rms_stereo: sol.rms_stereo,
        baseline_mm: t.norm(),
        t_mm: [t.x, t.y, t.z],
        left: lrow,
        right: rrow,
        pairs,
        warnings,
    };
    Ok((sol, report))
}

/// `calib.yaml` (OpenCV FileStorage) with the RMS figures beside the matrices.
pub fn calib_yaml(sol: &StereoSolution) -> String {
    let mut s = sol.calib.to_yaml();
    s += &format!("rms_left: {:.9}\nrms_right: {:.9}\nrms_stereo: {:.9}\n", sol.rms_left, sol.rms_right, sol.rms_stereo);
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coverage_counts_the_cells_inside_a_board() {
        let whole = [[0.0, 0.0], [640.0, 0.0], [640.0, 480.0], [0.0, 480.0]];
        let quarter = [[0.0, 0.0], [320.0, 0.0], [320.0, 240.0], [0.0, 240.0]];
        assert_eq!(coverage_pct(&[whole], (640, 480)), 100.0);
        assert_eq!(coverage_pct(&[quarter], (640, 480)), 25.0);
        assert!((area_pct(&quarter, (640, 480)) - 25.0).abs() < 1e-9);
    }
}
