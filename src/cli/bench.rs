//! `spinscan bench table1` and `bench live`: the paper's Table 1, and the live pipeline's
//! throughput.

use std::path::{Path, PathBuf};

use clap::{Args, Subcommand};
use serde_json::json;

use super::{input, output, progress, AssistArgs, Failure, KeyArgs, MatchArgs};
use spinscan::assist::{AssistMode, Granularity};
use spinscan::io;
use spinscan::pipeline::PipelineOptions;

#[derive(Subcommand)]
pub enum BenchCommand {
    /// Throughput of the live pipeline (the daemon's: bounded channel, matcher pool,
    /// registration thread) fed a recording from memory at camera-like paces, and unpaced.
    Live(LiveArgs),
    /// The paper's Table 1 on a recording: matcher time per frame without registration
    /// assistance, with it at each weighting factor w, and with the Kalman-predicted search;
    /// plus accuracy, valid fraction and search width per row, and a Fig. 4-style image.
    Table1(Table1Args),
}

#[derive(Args)]
pub struct Table1Args {
    /// Recording folder (e.g. from `spinscan sim render`).
    pub recording: PathBuf,
    /// Weighting factors of the paper's rows, comma-separated.
    #[arg(long, default_value = "0.6,0.8,1,2", value_delimiter = ',')]
    pub weights: Vec<f64>,
    /// Write the table as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// The Fig. 4-style image (left image, then each row's disparity map).
    #[arg(long, default_value = "table1-fig4.png")]
    pub fig: PathBuf,
    /// Frame shown in the figure (1-based, as in the table) [default: 5, or the last frame of
    /// a shorter run].
    #[arg(long)]
    pub fig_frame: Option<usize>,
    /// Use at most this many frames.
    #[arg(long)]
    pub frames: Option<usize>,
    /// Runs per frame and row (the median is reported).
    #[arg(long, default_value_t = 3)]
    pub repeat: usize,
    /// Let registration run this many views behind the matcher (the daemon's situation).
    #[arg(long, default_value_t = 0)]
    pub lag: u64,
    /// Frame columns printed (all are in the JSON).
    #[arg(long, default_value_t = 10)]
    pub columns: usize,
    /// Leave out the predicted row.
    #[arg(long)]
    pub no_predicted: bool,
    /// How finely the assisted rows set their search ranges: `pixel` (each pixel its own
    /// interval), `tile` (one per 16 × 8 tile), `plane` (one per tile, sloped along the
    /// previous frame's disparities there) or `auto` (planes for predicted, pixels for paper);
    /// a list (e.g. `pixel,tile,plane`) runs the assisted rows once per entry, side by side.
    #[arg(long, default_value = "auto", value_delimiter = ',')]
    pub assist_granularity: Vec<String>,
    #[command(flatten)]
    pub assist: AssistArgs,
    #[command(flatten)]
    pub matching: MatchArgs,
    #[command(flatten)]
    pub key: KeyArgs,
}

/// `spinscan bench live`'s arguments.
#[derive(Args)]
pub struct LiveArgs {
    /// A recording (e.g. `spinscan sim render --frames 90 --deg-per-frame 2 -o REC`).
    pub recording: PathBuf,
    /// Paced runs, pairs per second.
    #[arg(long, default_value = "15,30", value_delimiter = ',')]
    pub pace: Vec<f64>,
    /// Pairs fed per run (the recording is cycled when shorter).
    #[arg(long, default_value_t = 90)]
    pub pairs: usize,
    /// Skip the unpaced run.
    #[arg(long)]
    pub no_unpaced: bool,
    /// Matcher threads (default: one per core).
    #[arg(long, default_value_t = 0)]
    pub matcher_threads: usize,
    /// Pairs waiting for the matchers.
    #[arg(long, default_value_t = 16)]
    pub queue_depth: usize,
    /// Disparities searched (a count; `--max-disparity` is the older name).
    #[arg(long, visible_alias = "max-disparity", default_value_t = 128)]
    pub num_disparities: u32,
    /// Registration keeps at most this many points of a view (0 = all).
    #[arg(long, default_value_t = 20_000)]
    pub register_max_points: usize,
    /// Assistance: predicted, paper or none.
    #[arg(long, default_value = "predicted")]
    pub assist: String,
    /// How finely the assisted search range is set: auto, pixel, tile or plane (as `replay
    /// --assist-granularity`).
    #[arg(long, default_value = "auto")]
    pub assist_granularity: String,
    /// The matcher, as the daemon's `[matching] method`: `bm` or `sgm` (with its default
    /// penalties, paths and refinement).
    #[arg(long, default_value = "bm")]
    pub method: spinscan::stereo::Method,
    /// Leave the views' disparities as the matcher gives them (the daemon's `[matching]
    /// follow_surface = false`; docs/matcher.md, "The window that follows the surface").
    #[arg(long)]
    pub no_follow_surface: bool,
    /// Write the runs as JSON.
    #[arg(long)]
    pub json: Option<PathBuf>,
}

pub fn cmd_bench_live(a: LiveArgs) -> Result<(), Failure> {
    use spinscan::daemon::config::Config;
    let mut config = Config::default();
    config.scan.matcher_threads = a.matcher_threads;
    config.scan.queue_depth = a.queue_depth;
    config.scan.register_max_points = a.register_max_points;
    config.matching.num_disparities = a.num_disparities;
    config.matching.method = a.method;
    config.matching.assist = a.assist.clone();
    config.matching.assist_granularity = a.assist_granularity.clone();
    config.matching.follow_surface = !a.no_follow_surface;
    config.validate(Path::new("bench live flags")).map_err(input)?;
    if a.pairs == 0 || a.pace.iter().any(|p| p.is_nan() || *p <= 0.0) {
        return Err(input("--pairs must be at least 1 and every --pace positive"));
    }
    let opts = spinscan::daemon::throughput::LiveOptions { settings: config.pipeline_settings(), pairs: a.pairs, paces: a.pace.clone(), unpaced: !a.no_unpaced };
    let work = std::env::temp_dir().join(format!("spinscan-bench-live-{}", std::process::id()));
    let runs = spinscan::daemon::throughput::live(&a.recording, &opts, &work, &mut |what| eprintln!("bench live: {what}")).map_err(input);
    let _ = std::fs::remove_dir_all(&work);
    let runs = runs?;
    let threads = if a.matcher_threads == 0 { std::thread::available_parallelism().map_or(2, |n| n.get()) } else { a.matcher_threads };
    // The matcher the pipeline was given (not the flag echoed).
    let method = opts.settings.pipeline.matching.method.name();
    println!("live pipeline: {} matcher threads, queue {}, {} disparities, method {}, assist {} ({}), registration ≤ {} points/view", threads, a.queue_depth, a.num_disparities, method, a.assist, a.assist_granularity, a.register_max_points);
    print!("{}", spinscan::daemon::throughput::render(&runs));
    if let Some(path) = &a.json {
        let v = json!({"matcher_threads": threads, "queue_depth": a.queue_depth, "num_disparities": a.num_disparities, "method": method, "assist": a.assist, "assist_granularity": a.assist_granularity, "runs": runs.iter().map(|r| r.to_json()).collect::<Vec<_>>()});
        io::write_atomic(path, serde_json::to_string_pretty(&v).unwrap().as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    Ok(())
}

pub fn cmd_table1(a: Table1Args) -> Result<(), Failure> {
    if let Some(w) = a.weights.iter().find(|w| !(**w > 0.0 && w.is_finite())) {
        return Err(input(format!("--weights: {w} is not a weighting factor (expected positive numbers, e.g. 0.6,0.8,1,2)")));
    }
    if a.repeat == 0 {
        return Err(input("--repeat must be at least 1"));
    }
    if a.fig_frame == Some(0) {
        return Err(input("--fig-frame counts from 1"));
    }
    let mut methods = Vec::new();
    for m in &a.matching.method {
        if !methods.contains(m) {
            methods.push(*m);
        }
    }
    let matchers = methods
        .iter()
        .map(|&m| {
            let mut p = a.matching.checked_params_for(m, 128)?;
            // One thread unless asked: steadier timings on a shared machine.
            p.threads = a.matching.threads.unwrap_or(1);
            Ok(p)
        })
        .collect::<Result<Vec<_>, Failure>>()?;
    let mut granularities = Vec::new();
    for g in &a.assist_granularity {
        let g = Granularity::parse(g).map_err(|e| input(format!("--assist-granularity: {e}")))?;
        if !granularities.contains(&g) {
            granularities.push(g);
        }
    }
    let plate = match &a.key.plate {
        Some(_) => {
            let (w, h) = spinscan::recording::Recording::open(&a.recording).map_err(input)?.image_size;
            a.key.load_plate((w as usize, h as usize), "the recording's images")?
        }
        None => None,
    };
    let opts = spinscan::bench::Table1Options {
        pipeline: PipelineOptions { min_disparity: a.matching.min_disparity, matching: matchers[0].clone(), chroma: a.key.chroma(), follow_surface: !a.matching.no_follow_surface, ..Default::default() },
        plate,
        matchers,
        weights: a.weights.clone(),
        predicted: !a.no_predicted,
        max_frames: a.frames,
        repeat: a.repeat,
        lag: a.lag,
        assist: a.assist.params(AssistMode::Predicted)?,
        granularities,
        fig_frame: a.fig_frame.map(|k| k - 1),
        ..Default::default()
    };
    let table = spinscan::bench::table1(&a.recording, &opts, &mut |row, done, total| progress::show(format!("bench table1: {row:<10} {done}/{total}")));
    progress::finish();
    let table = table.map_err(input)?;
    print!("{}", table.render(a.columns));
    table.write_figure(&a.fig).map_err(output)?;
    println!("figure: {} (left image of frame {}, then {})", a.fig.display(), table.fig_frame + 1, table.to_json()["fig_tiles"].as_array().map(|t| t[1..].iter().filter_map(|v| v.as_str()).collect::<Vec<_>>().join(", ")).unwrap_or_default());
    if let Some(path) = &a.json {
        io::write_atomic(path, serde_json::to_string_pretty(&table.to_json()).unwrap().as_bytes()).map_err(|e| output(format!("cannot write {}: {e}", path.display())))?;
    }
    Ok(())
}
