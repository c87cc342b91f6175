//! The control socket: a Unix stream socket speaking JSON-RPC 2.0, one object per line.
//! Each connection gets a hello notification, then answers in request order; after
//! `events.subscribe` the daemon's notifications are interleaved with the answers.

use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use serde_json::{json, Value};
use tokio::io::{AsyncBufRead, AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};

use super::auth::Auth;
use super::error::ControlError;
use super::protocol::{Call, Hello, ScanEntry, ScanList, Subscribed, EVENTS, PROTOCOL_VERSION};
use super::rpc;
use crate::daemon::{Daemon, Event};

/// Why the socket could not be made.
#[derive(Debug, thiserror::Error)]
pub enum BindError {
    #[error("cannot create {path}: {source}")]
    Folder { path: PathBuf, source: std::io::Error },
    #[error("{0} is in use: another spinscand is running (stop it, or pass --socket)")]
    InUse(PathBuf),
    #[error("{0} exists and is not a socket; spinscand replaces only a stale socket (choose another --socket, or remove the file yourself)")]
    NotASocket(PathBuf),
    #[error("cannot {what} {path}: {source}")]
    Socket { what: &'static str, path: PathBuf, source: std::io::Error },
    #[error("cannot give {path} to group {gid}: {source} (is spinscand in that group?)")]
    Group { path: PathBuf, gid: u32, source: std::io::Error },
}

/// Binds the socket: refuses when another daemon answers on it, replaces a stale one,
/// sets the mode and group.
pub fn bind(path: &Path, mode: u32, gid: Option<u32>) -> Result<UnixListener, BindError> {
    let socket = |what| move |source| BindError::Socket { what, path: path.to_path_buf(), source };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|source| BindError::Folder { path: dir.to_path_buf(), source })?;
    }
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        // Only a socket nobody answers on is replaced; any other file stays.
        if !std::os::unix::fs::FileTypeExt::is_socket(&meta.file_type()) {
            return Err(BindError::NotASocket(path.to_path_buf()));
        }
        if std::os::unix::net::UnixStream::connect(path).is_ok() {
            return Err(BindError::InUse(path.to_path_buf()));
        }
        std::fs::remove_file(path).map_err(socket("remove the stale socket"))?;
    }
    let listener = UnixListener::bind(path).map_err(socket("bind"))?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).map_err(socket("chmod"))?;
    if let Some(gid) = gid {
        std::os::unix::fs::chown(path, None, Some(gid)).map_err(|source| BindError::Group { path: path.to_path_buf(), gid, source })?;
    }
    Ok(listener)
}

/// Accepts connections until `shutdown` fires. The last [`RESERVED_FOR_CONTROL`] slots of
/// `daemon.max_clients` are kept for peers with control rights, so idle readers can never
/// lock out the people who run scans.
pub async fn serve(daemon: Arc<Daemon>, auth: Arc<Auth>, listener: UnixListener, mut shutdown: tokio::sync::watch::Receiver<bool>) {
    let clients = Arc::new(AtomicUsize::new(0));
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    let (d, a, c) = (daemon.clone(), auth.clone(), clients.clone());
                    tokio::spawn(async move {
                        let peer = Peer::of(&stream, &a);
                        let max = d.config.daemon.max_clients;
                        let limit = if peer.as_ref().is_some_and(|p| p.may_control) { max } else { max - RESERVED_FOR_CONTROL.min(max / 4) };
                        if c.fetch_add(1, Ordering::SeqCst) >= limit {
                            let _ = refuse(stream, max).await;
                        } else if let Some(peer) = peer {
                            if let Err(e) = connection(d, peer, stream).await {
                                tracing::debug!("client connection ended: {e}");
                            }
                        }
                        c.fetch_sub(1, Ordering::SeqCst);
                    });
                }
                Err(e) => {
                    tracing::error!("accept failed: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(100)).await;
                }
            },
            _ = shutdown.changed() => return,
        }
    }
}

/// Connection slots held back for peers with control rights (at most a quarter of them).
pub const RESERVED_FOR_CONTROL: usize = 4;

/// Who is at the other end of a connection.
struct Peer {
    uid: u32,
    pid: Option<i32>,
    may_control: bool,
}

impl Peer {
    /// The peer's credentials at connect time: uid and gid (`SO_PEERCRED`) and its own groups
    /// (`SO_PEERGROUPS`).
    fn of(stream: &UnixStream, auth: &Auth) -> Option<Peer> {
        use std::os::fd::AsRawFd;
        let cred = stream.peer_cred().ok()?;
        let groups = super::auth::peer_groups(stream.as_raw_fd());
        let may_control = auth.may_control(cred.uid(), cred.gid(), groups.as_deref());
        Some(Peer { uid: cred.uid(), pid: cred.pid(), may_control })
    }
}

async fn refuse(mut stream: UnixStream, max: usize) -> std::io::Result<()> {
    let e = ControlError::TooManyClients(max);
    stream.write_all(format!("{}\n", rpc::error_response(&Value::Null, &e)).as_bytes()).await
}

/// What one read produced.
enum Line {
    Text(String),
    TooLong,
    NotUtf8,
    Eof,
}

/// Reads one line of at most `max` bytes; a longer one is consumed and reported.
async fn read_line<R: AsyncBufRead + Unpin>(r: &mut R, max: usize) -> std::io::Result<Line> {
    let mut buf = Vec::new();
    let mut too_long = false;
    loop {
        let chunk = r.fill_buf().await?;
        if chunk.is_empty() {
            return Ok(if buf.is_empty() && !too_long { Line::Eof } else if too_long { Line::TooLong } else { finish(buf) });
        }
        let (take, done) = match chunk.iter().position(|&b| b == b'\n') {
            Some(i) => (i + 1, true),
            None => (chunk.len(), false),
        };
        if !too_long {
            buf.extend_from_slice(&chunk[..take]);
            if buf.len() > max + 1 {
                too_long = true;
                buf = Vec::new();
            }
        }
        r.consume(take);
        if done {
            return Ok(if too_long { Line::TooLong } else { finish(buf) });
        }
    }
}

fn finish(mut buf: Vec<u8>) -> Line {
    while buf.last().is_some_and(|b| *b == b'\n' || *b == b'\r') {
        buf.pop();
    }
    match String::from_utf8(buf) {
        Ok(s) => Line::Text(s),
        Err(_) => Line::NotUtf8,
    }
}

async fn connection(daemon: Arc<Daemon>, peer: Peer, stream: UnixStream) -> std::io::Result<()> {
    let Peer { uid, pid, may_control } = peer;
    tracing::debug!(uid, ?pid, may_control, "client connected");
    let (read, mut write) = stream.into_split();
    let mut reader = BufReader::new(read);
    // Everything written goes through one channel: answers and forwarded events.
    let (tx, mut rx) = tokio::sync::mpsc::channel::<String>(64);
    let writer = tokio::spawn(async move {
        while let Some(line) = rx.recv().await {
            if write.write_all(line.as_bytes()).await.is_err() {
                break;
            }
        }
    });
    let send = |v: Value| {
        let tx = tx.clone();
        async move { tx.send(format!("{v}\n")).await.is_ok() }
    };
    let hello = Hello { server: "spinscand".into(), version: env!("CARGO_PKG_VERSION").into(), protocol: PROTOCOL_VERSION, may_control };
    send(rpc::notification("hello", json!(hello))).await;
    let max = daemon.config.daemon.max_request_bytes;
    let idle = std::time::Duration::from_secs_f64(daemon.config.daemon.idle_timeout_s);
    let mut forwarder: Option<tokio::task::JoinHandle<()>> = None;
    loop {
        // A connection that says nothing for `daemon.idle_timeout_s` is closed, unless it
        // subscribed to events (a `--watch` waits for them as long as a scan runs).
        let read = read_line(&mut reader, max);
        let next = if forwarder.is_some() {
            read.await?
        } else {
            match tokio::time::timeout(idle, read).await {
                Ok(r) => r?,
                Err(_) => {
                    let e = ControlError::InvalidRequest(format!("no request for {} s (daemon.idle_timeout_s); closing", idle.as_secs_f64()));
                    send(rpc::error_response(&Value::Null, &e)).await;
                    break;
                }
            }
        };
        let line = match next {
            Line::Eof => break,
            Line::TooLong => {
                let e = ControlError::InvalidRequest(format!("request line longer than {max} bytes (daemon.max_request_bytes)"));
                send(rpc::error_response(&Value::Null, &e)).await;
                continue;
            }
            Line::NotUtf8 => {
                send(rpc::error_response(&Value::Null, &ControlError::Parse("request line is not UTF-8".into()))).await;
                continue;
            }
            Line::Text(t) if t.trim().is_empty() => continue,
            Line::Text(t) => t,
        };
        let req = match rpc::parse_request(&line) {
            Ok(r) => r,
            Err((id, e)) => {
                send(rpc::error_response(&id, &e)).await;
                continue;
            }
        };
        let id = req.id.clone();
        let result = match Call::parse(&req) {
            Err(e) => Err(e),
            Ok(Call::EventsSubscribe) => {
                if forwarder.is_none() {
                    forwarder = Some(forward_events(daemon.subscribe(), tx.clone()));
                }
                Ok(json!(Subscribed { subscribed: EVENTS.iter().map(|e| e.to_string()).collect() }))
            }
            Ok(call) => {
                let d = daemon.clone();
                let who = format!("uid {uid}, pid {}", pid.map_or("?".to_string(), |p| p.to_string()));
                // Methods may touch devices (a serial round trip): off the async threads.
                tokio::task::spawn_blocking(move || dispatch(&d, call, may_control, &who)).await.unwrap_or_else(|_| Err(ControlError::Internal("the request handler panicked".into())))
            }
        };
        // A notification (no id) gets no answer.
        if let Some(id) = id {
            let out = match result {
                Ok(v) => rpc::response(&id, v),
                Err(e) => rpc::error_response(&id, &e),
            };
            if !send(out).await {
                break;
            }
        }
    }
    if let Some(f) = forwarder {
        f.abort();
    }
    drop(tx);
    let _ = writer.await;
    Ok(())
}

/// Forwards the daemon's notifications to one client until either side goes.
fn forward_events(mut events: tokio::sync::broadcast::Receiver<Event>, tx: tokio::sync::mpsc::Sender<String>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            let line = match events.recv().await {
                Ok(e) => format!("{}\n", rpc::notification(&e.method, e.params)),
                Err(tokio::sync::broadcast::error::RecvError::Lagged(n)) => format!("{}\n", rpc::notification("events.lagged", json!({"missed": n}))),
                Err(tokio::sync::broadcast::error::RecvError::Closed) => break,
            };
            if tx.send(line).await.is_err() {
                break;
            }
        }
    })
}

/// Runs one method (blocking).
fn dispatch(daemon: &Arc<Daemon>, call: Call, may_control: bool, who: &str) -> Result<Value, ControlError> {
    let method = call.method();
    if call.controls() && !may_control {
        return Err(ControlError::PermissionDenied { method: method.into(), who: who.into(), group: daemon.config.daemon.group.clone() });
    }
    let of = |e| ControlError::of(method, e);
    match call {
        Call::Status => {
            let mut s = daemon.status();
            s["protocol"] = json!(PROTOCOL_VERSION);
            Ok(s)
        }
        Call::Devices => Ok(daemon.devices()),
        Call::ScanStart(p) => {
            let spec = p.to_spec(&daemon.config)?;
            daemon.start_scan(spec).map(|s| json!(s)).map_err(of)
        }
        Call::ScanStop => daemon.stop_scan(&format!("stopped by scan.stop ({who})")).map(|s| json!(s)).map_err(of),
        Call::ScanMesh => daemon.mesh_scan().map(|s| json!(s)).map_err(of),
        Call::ScanList => {
            let running = daemon.current_scan().map(|s| s.spec.name.clone());
            let scans = crate::daemon::list_manifests(&daemon.config.daemon.state_dir)
                .into_iter()
                .map(|(name, m)| ScanEntry { running: running.as_deref() == Some(name.as_str()), name, status: m["status"].clone(), frames: m["frames"].clone(), mode: m["mode"].clone(), reason: m["reason"].clone() })
                .collect();
            Ok(json!(ScanList { scans }))
        }
        Call::ScanGet { name } => daemon.get_scan(&name).map_err(of),
        Call::CalibCapture(p) => daemon.start_calibration(p.to_spec()).map_err(of),
        Call::CalibStop => daemon.stop_calibration().map_err(of),
        Call::EventsSubscribe => unreachable!("answered on the connection's own task"),
    }
}
