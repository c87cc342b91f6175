//! `spinscand`: the scanning daemon. See `docs/daemon.md` and `docs/protocol.md`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use clap::Parser;

use spinscan::daemon::config::{BackendKind, Config, ConfigError};
use spinscan::control::{server, Auth};
use spinscan::daemon::{exit, Daemon, DaemonError};

#[derive(Parser)]
#[command(name = "spinscand", version, about = "spinscan's daemon: drives the cameras and the turntable, scans on command from a Unix socket")]
struct Args {
    /// Config file (TOML; every key in config/spinscand.toml). Default:
    /// /etc/spinscan/spinscand.toml when it exists, else the built-in defaults.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// The simulated lab (hw-sim cameras, turntable firmware on a pseudo-terminal): with no
    /// --config, the built-in sim defaults (socket ./spinscan.sock, scans in ./scans).
    #[arg(long)]
    sim: bool,
    /// Control socket (overrides daemon.socket).
    #[arg(long, value_name = "PATH")]
    socket: Option<PathBuf>,
    /// Folder of the scans (overrides daemon.state_dir).
    #[arg(long, value_name = "DIR")]
    state_dir: Option<PathBuf>,
    /// Check the configuration, print it as TOML, and exit.
    #[arg(long)]
    check_config: bool,
}

const SYSTEM_CONFIG: &str = "/etc/spinscan/spinscand.toml";

fn load_config(args: &Args) -> Result<Config, ConfigError> {
    let mut config = match (&args.config, args.sim) {
        (Some(p), _) => Config::load(p)?,
        (None, true) => Config::sim(),
        (None, false) if std::path::Path::new(SYSTEM_CONFIG).is_file() => Config::load(std::path::Path::new(SYSTEM_CONFIG))?,
        (None, false) => Config::default(),
    };
    if args.sim {
        config.backend.kind = BackendKind::Sim;
    }
    if let Some(s) = &args.socket {
        config.daemon.socket = s.clone();
    }
    if let Some(d) = &args.state_dir {
        config.daemon.state_dir = d.clone();
    }
    let source = spinscan::daemon::config_source(args.config.as_ref(), args.sim);
    config.validate(std::path::Path::new(&source))?;
    Ok(config)
}

/// Allocations from this size up get pages of their own, returned to the system when freed.
#[cfg(target_env = "gnu")]
const MMAP_THRESHOLD: libc::c_int = 256 * 1024;

fn main() -> ExitCode {
    // Scans run on fresh threads; glibc gives threads arenas of their own and keeps them, so
    // a daemon that runs for months would grow with every scan. Two arenas, a fixed mmap
    // threshold of 256 KiB, and a trim after each scan (see `Daemon::scan_finished`) keep it
    // flat. The fixed threshold matters at camera resolution: left dynamic, glibc raises it
    // to the size of the first freed frame buffer, and from then on every frame-sized buffer
    // lives in the arenas, where fragments of them outlive the scan (RSS after repeated
    // 640×480 scans: 40, 41, 33, 79, 54 MiB; with 256 KiB: 28.0 … 28.8 MiB; docs/daemon.md).
    #[cfg(target_env = "gnu")]
    // SAFETY: mallopt only changes the allocator's tuning; called before any thread starts.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 2);
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
    }
    let args = Args::parse();
    // Under systemd (JOURNAL_STREAM set) journald adds time and colour is noise.
    let journald = std::env::var_os("JOURNAL_STREAM").is_some();
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let fmt = tracing_subscriber::fmt().with_writer(std::io::stderr).with_env_filter(filter).with_thread_names(true).with_ansi(!journald);
    if journald {
        fmt.without_time().init();
    } else {
        fmt.init();
    }
    let config = match load_config(&args) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("spinscand: configuration error: {e}");
            return ExitCode::from(exit::CONFIG);
        }
    };
    if args.check_config {
        print!("{}", toml::to_string(&config).expect("a config serialises"));
        return ExitCode::SUCCESS;
    }
    let auth = match Auth::load(&config.daemon.group) {
        Ok(a) => a,
        Err(e) => {
            eprintln!("spinscand: configuration error: {e}");
            return ExitCode::from(exit::CONFIG);
        }
    };
    let rt = match tokio::runtime::Builder::new_multi_thread().worker_threads(2).thread_name("spinscand-rt").enable_all().build() {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("spinscand: cannot start the async runtime: {e}");
            return ExitCode::from(exit::SOFTWARE);
        }
    };
    let code = rt.block_on(run(config, auth));
    rt.shutdown_timeout(Duration::from_secs(2));
    ExitCode::from(code)
}

fn notify(states: &[sd_notify::NotifyState]) {
    if let Err(e) = sd_notify::notify(states) {
        tracing::debug!("sd_notify: {e}");
    }
}

async fn run(config: Config, auth: Auth) -> u8 {
    let socket = config.daemon.socket.clone();
    let mode = config.socket_mode().expect("validated");
    let gid = auth.group.as_ref().map(|g| g.1);
    tracing::info!(backend = config.backend.kind.name(), socket = %socket.display(), state_dir = %config.daemon.state_dir.display(), "spinscand {} starting", env!("CARGO_PKG_VERSION"));
    let auth = Arc::new(auth);
    let daemon = match tokio::task::spawn_blocking(move || Daemon::start(config)).await {
        Ok(Ok(d)) => d,
        Ok(Err(e)) => {
            tracing::error!("cannot start: {e}");
            eprintln!("spinscand: {e}");
            return match e {
                DaemonError::StateDir { .. } => exit::CANT_CREATE,
                DaemonError::Locked(_) => exit::UNAVAILABLE,
                _ => exit::UNAVAILABLE,
            };
        }
        Err(_) => return exit::SOFTWARE,
    };
    let listener = match server::bind(&socket, mode, gid) {
        Ok(l) => l,
        Err(e) => {
            eprintln!("spinscand: {e}");
            return exit::CANT_CREATE;
        }
    };
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let serving = tokio::spawn(server::serve(daemon.clone(), auth, listener, stop_rx));
    tracing::info!(socket = %socket.display(), "ready");
    notify(&[sd_notify::NotifyState::Ready, sd_notify::NotifyState::Status(&daemon.status_line())]);

    let pulse = tokio::spawn(health(daemon.clone()));
    let why = shutdown_signal().await;
    tracing::info!("{why}: finishing the current view and stopping");
    notify(&[sd_notify::NotifyState::Stopping, sd_notify::NotifyState::Status(&format!("stopping ({why})"))]);
    let _ = daemon.stop_scan(&format!("spinscand stopped ({why})"));
    let _ = daemon.stop_calibration();
    daemon.wait_idle().await;
    let _ = stop_tx.send(true);
    let _ = serving.await;
    pulse.abort();
    // Only our socket is removed (the path may have been replaced meanwhile).
    if std::fs::symlink_metadata(&socket).is_ok_and(|m| std::os::unix::fs::FileTypeExt::is_socket(&m.file_type())) {
        let _ = std::fs::remove_file(&socket);
    }
    let d = daemon.clone();
    let _ = tokio::task::spawn_blocking(move || d.close()).await;
    tracing::info!("stopped");
    0
}

/// Feeds the systemd watchdog while the pipeline is healthy, and keeps STATUS= current.
async fn health(daemon: Arc<Daemon>) {
    let period = sd_notify::watchdog_enabled().map(|w| w / 2).unwrap_or(Duration::from_secs(1)).min(Duration::from_secs(1));
    let mut last_status = String::new();
    loop {
        tokio::time::sleep(period).await;
        let status = daemon.status_line();
        if daemon.healthy() {
            notify(&[sd_notify::NotifyState::Watchdog]);
        } else {
            tracing::error!("pipeline stalled for more than {} s; not feeding the watchdog", daemon.config.daemon.stall_s);
        }
        if status != last_status {
            notify(&[sd_notify::NotifyState::Status(&status)]);
            last_status = status;
        }
    }
}

async fn shutdown_signal() -> &'static str {
    use tokio::signal::unix::{signal, SignalKind};
    let mut term = signal(SignalKind::terminate()).expect("SIGTERM handler");
    let mut int = signal(SignalKind::interrupt()).expect("SIGINT handler");
    tokio::select! {
        _ = term.recv() => "SIGTERM",
        _ = int.recv() => "SIGINT",
    }
}
