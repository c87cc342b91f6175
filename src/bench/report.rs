//! `bench table1`'s outputs: the JSON of `--json`, the printed table, and Fig. 4.

use std::path::Path;

use serde_json::{json, Value};

use super::{mean, median, BenchError, Row, Table1};
use crate::assist::{AssistMode, Granularity};
use crate::io;
use crate::stereo::Method;

impl Table1 {
    /// The JSON of `--json`.
    pub fn to_json(&self) -> Value {
        json!({
            "recording": self.recording,
            "frames": self.frames,
            "image_size": [self.size.0, self.size.1],
            "disparity_range": [self.range.0, self.range.1],
            "threads": self.threads,
            "repeat": self.repeat,
            "cpu_vector_extensions": crate::stereo::vector_extensions(),
            "lag": self.lag,
            "fig_frame_seq": self.frames[self.fig_frame],
            "floor_ms": self.floor_ms,
            "median_floor_ms": median(&self.floor_ms),
            "floor_ms_by_method": self.floor_ms_by_method.iter().map(|(m, f)| json!({"method": m.name(), "floor_ms": f, "median_floor_ms": median(f)})).collect::<Vec<_>>(),
            "screen_not_found_seqs": self.screen_not_found,
            "backdrop_keyed_seqs": self.backdrop_keyed.iter().map(|b| b.0).collect::<Vec<_>>(),
            "object_on_edge_seqs": self.object_on_edge.iter().map(|e| e.0).collect::<Vec<_>>(),
            "contrast": self.contrast.map(|c| c.entry()),
            "gt_disparity": self.gt_disparity_source(),
            "fig_tiles": std::iter::once("left".to_string()).chain(self.rows.iter().map(row_label)).collect::<Vec<_>>(),
            "rows": self.rows.iter().map(|r| {
                let mut j = r.to_json();
                j["ratio_to_none"] = json!(self.none_ms(r.method).map(|n| r.median_ms() / n));
                let (time, bad2) = self.against_bm_none(r);
                j["ratio_to_bm_none"] = json!(time);
                j["bad2_ratio_to_bm_none"] = json!(bad2);
                j
            }).collect::<Vec<_>>(),
        })
    }

    /// Where bad2's ground truth came from: `recorded` (`gt/disparity/`), `rendered` (from
    /// `gt/mesh.ply` at `gt/poses.jsonl`'s poses), `mixed` where frames differ, `None`
    /// where no frame has any.
    pub fn gt_disparity_source(&self) -> Option<&'static str> {
        crate::pipeline::truth::sources_name(self.gt_disparity.iter().flatten().copied())
    }

    /// A matcher's row without assistance, if the table has one.
    fn none_row(&self, method: Method) -> Option<&Row> {
        self.rows.iter().find(|r| r.mode == AssistMode::None && r.method == method)
    }

    /// The no-assistance row's median of a matcher: what its rows' ratios are taken against.
    fn none_ms(&self, method: Method) -> Option<f64> {
        self.none_row(method).map(Row::median_ms)
    }

    /// A row's median time and bad2 as ratios to the correlation matcher's row without
    /// assistance (a full-range `bm` search: what other methods' rows are measured against),
    /// where the table has that row (and, for bad2, ground truth).
    fn against_bm_none(&self, r: &Row) -> (Option<f64>, Option<f64>) {
        let Some(bm) = self.none_row(Method::Bm) else { return (None, None) };
        let bad2 = match (r.bad2(), bm.bad2()) {
            (Some(a), Some(b)) if b > 0.0 => Some(a / b),
            _ => None,
        };
        (Some(r.median_ms() / bm.median_ms()), bad2)
    }

    /// The paper's table (a column per frame, up to `max_cols` frames) and the accuracy table.
    pub fn render(&self, max_cols: usize) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let cols = self.frames.len().min(max_cols);
        let _ = writeln!(s, "Table 1 — matching time per frame, ms ({}×{}, disparities {}…{}, {} thread(s), median of {} run(s) per frame{}; CPU: {})", self.size.0, self.size.1, self.range.0, self.range.1, self.threads, self.repeat, if self.lag > 0 { format!(", registration {} view(s) behind", self.lag) } else { String::new() }, vectors_label(&crate::stereo::vector_extensions()));
        let _ = write!(s, "{:<16}", "frame");
        for i in 0..cols {
            let _ = write!(s, "{:>7}", i + 1);
        }
        if cols < self.frames.len() {
            let _ = write!(s, "{:>5}", "…");
        }
        let _ = writeln!(s, "{:>9}", "median");
        for r in &self.rows {
            let _ = write!(s, "{:<16}", row_label(r));
            for t in &r.frame_ms[..cols] {
                let _ = write!(s, "{t:>7.2}");
            }
            if cols < self.frames.len() {
                let _ = write!(s, "{:>5}", "");
            }
            let _ = writeln!(s, "{:>9.2}", r.median_ms());
        }
        for (m, floor) in &self.floor_ms_by_method {
            if let Some(f) = median(floor) {
                let label = if self.floor_ms_by_method.len() > 1 { format!("{m} floor") } else { "floor".into() };
                let _ = writeln!(s, "{:<16}{:>width$.2}   (matcher alone, one disparity per foreground pixel: the floor of any interval)", label, f, width = 7 * cols + if cols < self.frames.len() { 5 } else { 0 } + 9);
            }
        }
        let _ = writeln!(s);
        let _ = writeln!(s, "{:<16}{:>8}{:>8}{:>8}{:>9}{:>9}{:>9}{:>10}{:>9}{:>9}{:>9}{:>7}", "mode", "median", "ratio", "bad2 %", "lr %", "err mm", "valid", "search px", "ivl ms", "lr ms", "ns/pair", "full");
        let opt = |v: Option<f64>, p: usize| v.map_or("-".to_string(), |v| format!("{v:.p$}"));
        for r in &self.rows {
            let _ = writeln!(
                s,
                "{:<16}{:>8.2}{:>8}{:>8}{:>9}{:>9}{:>9}{:>10}{:>9}{:>9}{:>9}{:>7}",
                row_label(r),
                r.median_ms(),
                opt(self.none_ms(r.method).map(|n| r.median_ms() / n), 3),
                opt(r.bad2(), 2),
                opt(mean(&r.lr_consistency), 2),
                opt(median(&r.err_mm), 3),
                opt(mean(&r.valid_fraction), 3),
                opt(mean(&r.search_px), 1),
                opt(median(&r.interval_ms), 2),
                opt(median(&r.lr_check_ms), 2),
                opt(median(&r.ns_per_pair), 3),
                r.full_range.len(),
            );
        }
        // Another matcher's rows against the correlation's full range, where both ran.
        let others: Vec<&Row> = self.rows.iter().filter(|r| r.method != Method::Bm).collect();
        if !others.is_empty() && self.none_row(Method::Bm).is_some() {
            let _ = writeln!(s, "\nagainst the row without assistance of bm (time, bad2):");
            for r in others {
                let (time, bad2) = self.against_bm_none(r);
                let _ = writeln!(s, "{:<16}{:>8} ×{:>8} ×", row_label(r), opt(time, 3), opt(bad2, 2));
            }
        }
        match self.gt_disparity_source() {
            Some("rendered") => {
                let _ = writeln!(s, "\nbad2: against disparities rendered from gt/mesh.ply at gt/poses.jsonl's poses (the recording has no gt/disparity/)");
            }
            Some("mixed") => {
                let _ = writeln!(s, "\nbad2: against gt/disparity/ where the recording has it, else disparities rendered from gt/mesh.ply at gt/poses.jsonl's poses");
            }
            _ => {}
        }
        if let Some(&(first, threshold)) = self.backdrop_keyed.first() {
            let _ = writeln!(s, "\nsegmentation: {} of {} frames (the first seq {first}): {}", self.backdrop_keyed.len(), self.frames.len(), crate::segment::plain_backdrop(threshold));
        }
        if let Some(first) = self.screen_not_found.first() {
            let _ = writeln!(s, "\nsegmentation: {} of {} frames (the first seq {first}): {}", self.screen_not_found.len(), self.frames.len(), crate::segment::no_screen());
        }
        if let Some(&(first, share)) = self.object_on_edge.first() {
            let _ = writeln!(s, "\nsegmentation: {} of {} frames (the first seq {first}): {}", self.object_on_edge.len(), self.frames.len(), crate::segment::object_on_edge(share));
        }
        if let Some(c) = self.contrast.filter(crate::stereo::gain::Contrast::scales_right) {
            let _ = writeln!(s, "\ncontrast: the right camera's images have {:.2} × the left's (their gain or exposure differ): every right image was scaled to the left's before matching", 1.0 / c.ratio);
        }
        // The first row that dropped many matches at the range's end (the same frames
        // overflow it in every row).
        let warn = crate::pipeline::results::RANGE_EDGE_WARN_SHARE;
        for r in &self.rows {
            let hit: Vec<usize> = (0..r.range_edge_share.len()).filter(|&i| r.range_edge_share[i] >= warn).collect();
            if let Some(&first) = hit.first() {
                let _ = writeln!(
                    s,
                    "\nrange: {} of {} frames of the row '{}' dropped matches at an end of the disparity range (the first seq {}: {} pixels, {:.1} % of those searched): the object comes closer (or lies farther) than the range covers; widen it (--num-disparities, --min-disparity)",
                    hit.len(),
                    r.range_edge_share.len(),
                    row_label(r).trim(),
                    self.frames[first],
                    r.range_edge_px[first],
                    100.0 * r.range_edge_share[first]
                );
                break;
            }
        }
        s
    }

    /// Fig. 4: the left image of the figure's frame, then each row's disparity map (false
    /// colour, blue far to red near over the object's disparities; black = no disparity), at
    /// half size, four per line.
    pub fn write_figure(&self, path: &Path) -> Result<(), BenchError> {
        let (w, h) = self.size;
        let (tw, th) = (w / 2, h / 2);
        let mut tiles: Vec<Vec<u8>> = vec![self.fig_left.clone()];
        // One colour scale for every map: the object's disparities (2nd to 98th percentile of
        // the first row's), so that differences between rows show.
        let mut all: Vec<f32> = self.rows.first().and_then(|r| r.fig.as_ref()).map(|d| d.values().iter().filter(|v| v.is_finite()).map(|v| v.abs()).collect()).unwrap_or_default();
        all.sort_by(f32::total_cmp);
        let scale = if all.len() > 10 { (all[all.len() / 50], all[all.len() * 49 / 50]) } else { (self.range.0.max(0) as f32, self.range.1.unsigned_abs() as f32) };
        for r in &self.rows {
            let d = r.fig.as_ref().ok_or_else(|| BenchError::Output("no disparity map for the figure".into()))?;
            tiles.push(io::disparity_false_color(d, scale));
        }
        let per_line = 4usize;
        let lines = tiles.len().div_ceil(per_line);
        let (cw, ch) = (per_line * tw + (per_line - 1) * 4, lines * th + (lines - 1) * 4);
        let mut canvas = vec![255u8; cw * ch * 3];
        for (t, tile) in tiles.iter().enumerate() {
            let (ox, oy) = ((t % per_line) * (tw + 4), (t / per_line) * (th + 4));
            for y in 0..th {
                for x in 0..tw {
                    let src = ((2 * y) * w + 2 * x) * 3;
                    let dst = ((oy + y) * cw + ox + x) * 3;
                    canvas[dst..dst + 3].copy_from_slice(&tile[src..src + 3]);
                }
            }
        }
        io::write_rgb_png(path, cw, ch, &canvas).map_err(|e| BenchError::Output(format!("cannot write {}: {e}", path.display())))
    }
}

pub(super) fn row_label(r: &Row) -> String {
    let mode = match r.mode {
        AssistMode::None => "without".into(),
        AssistMode::Paper { w } => format!("w = {w}"),
        AssistMode::Predicted => "predicted".into(),
    };
    // A row at its mode's default granularity keeps the label it always had.
    let mode = match r.granularity {
        Some(g) if g != Granularity::Auto.resolve(r.mode) => format!("{mode} {}", g.name()),
        _ => mode,
    };
    // The default matcher keeps the labels it always had.
    match r.method {
        Method::Bm => mode,
        m => format!("{m} {mode}"),
    }
}

/// The printout's short name of the vector code the matchers run: `AVX-512` where `bm`'s wide
/// searches take it (`avx512f` and `avx512bw`), else `AVX2`, else `no AVX2`.
fn vectors_label(found: &[&str]) -> &'static str {
    match (found.contains(&"avx512f") && found.contains(&"avx512bw"), found.contains(&"avx2")) {
        (true, _) => "AVX-512",
        (false, true) => "AVX2",
        (false, false) => "no AVX2",
    }
}
