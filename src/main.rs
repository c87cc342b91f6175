//! `spinscan`, the command line: single pairs, the simulated lab, replays, registration,
//! benchmarks, and the daemon's client. Each subcommand lives in `cli/`.

use std::io::IsTerminal;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod cli;

use cli::bench::BenchCommand;
use cli::calibrate::CalibrateCommand;
use cli::sim::SimCommand;
use cli::{bench, calibrate, daemon, mesh, register, replay, sim, stereo, turntable};

#[derive(Parser)]
#[command(name = "spinscan", version, about = "Registration-assisted stereo scanning for turntable labs")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Disparity map of a stereo pair (rectified, or raw with --calib).
    Disparity(stereo::DisparityArgs),
    /// Writes the rectified pair of a calibrated raw pair.
    Rectify(stereo::RectifyArgs),
    /// Coloured point cloud (PLY, mm, left raw camera frame) of a calibrated raw pair.
    Points(stereo::PointsArgs),
    /// Renders a short scan in the simulated lab, records it, and replays it through the
    /// pipeline, scored against the ground truth. Needs no devices and no files.
    Demo(sim::DemoArgs),
    /// The simulated lab.
    #[command(subcommand)]
    Sim(SimCommand),
    /// Runs the pipeline on a recording and writes the results folder (views, disparity,
    /// report, manifest).
    Replay(replay::ReplayArgs),
    /// Registers two scans by ICP (SOURCE onto TARGET), or, with --ring, a ring of scans into
    /// Stanford .conf poses.
    Register(register::RegisterArgs),
    /// Fuses a results folder's registered views into a closed, coloured triangle mesh
    /// (.ply, .obj or .stl).
    Mesh(mesh::MeshArgs),
    /// Calibration: the stereo rig from chessboard pairs (calib.yaml), the turntable's axis
    /// from a board on the table (turntable.yaml), capture through the daemon.
    #[command(subcommand)]
    Calibrate(CalibrateCommand),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// The daemon's state and the running scan's progress.
    Status(daemon::SocketArg),
    /// Cameras (with formats), serial ports and the turntable, as the daemon sees them
    /// (--local: this machine's V4L2 devices and serial ports, without the daemon).
    Devices(daemon::DevicesArgs),
    /// Starts, stops or shows a scan on the daemon.
    #[command(subcommand)]
    Scan(daemon::ScanCommand),
    /// The daemon's scans with their status.
    Scans(daemon::SocketArg),
    /// The turntable alone, without the daemon: `info`, `status`, `move DEG`, `off`.
    Turntable(turntable::TurntableArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Warnings (and more with RUST_LOG=info|debug) go to stderr. A benchmark registers every
    // row's views: their registration warnings only with RUST_LOG=warn.
    let default_level = if matches!(cli.command, Command::Bench(_)) { "error" } else { "warn" };
    tracing_subscriber::fmt()
        .with_writer(cli::progress::LogWriter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_level)))
        .init();
    let result = match cli.command {
        Command::Disparity(a) => stereo::cmd_disparity(a),
        Command::Rectify(a) => stereo::cmd_rectify(a),
        Command::Points(a) => stereo::cmd_points(a),
        Command::Demo(a) => sim::cmd_demo(a),
        Command::Sim(SimCommand::Render(a)) => sim::cmd_sim_render(a),
        Command::Replay(a) => replay::cmd_replay(a),
        Command::Register(a) => register::cmd_register(a),
        Command::Mesh(a) => mesh::cmd_mesh(a),
        Command::Calibrate(CalibrateCommand::Stereo(a)) => calibrate::cmd_stereo(a),
        Command::Calibrate(CalibrateCommand::Turntable(a)) => calibrate::cmd_turntable(a),
        Command::Calibrate(CalibrateCommand::Capture(a)) => calibrate::cmd_capture(a),
        Command::Calibrate(CalibrateCommand::Stop(a)) => calibrate::cmd_stop(a),
        Command::Bench(BenchCommand::Table1(a)) => bench::cmd_table1(a),
        Command::Bench(BenchCommand::Live(a)) => bench::cmd_bench_live(a),
        Command::Status(a) => daemon::status(a),
        Command::Devices(a) => daemon::devices(a),
        Command::Scan(c) => daemon::scan(c),
        Command::Scans(a) => daemon::scans(a),
        Command::Turntable(a) => turntable::cmd_turntable(a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(f) => {
            eprintln!("spinscan: error: {}", f.message);
            ExitCode::from(f.code)
        }
    }
}
