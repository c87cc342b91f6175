//! The control socket: a Unix stream socket speaking JSON-RPC 2.0, one object per line.
//! Each connection gets a hello notification, then answers in request order; after
//! `events.subscribe` the daemon's notifications are interleaved with the answers.

use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use serde_json::{json, Value};
use tokio::io::{AsyncBufRead, AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio::net::{UnixListener, UnixStream};

use super::rpc::{self, code, Request, RpcError};
use super::Daemon;

/// Binds the socket: refuses when another daemon answers on it, replaces a stale one,
/// sets the mode and group.
pub fn bind(path: &Path, mode: u32, gid: Option<u32>) -> Result<UnixListener, String> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| format!("cannot create {}: {e}", dir.display()))?;
    }
    if path.exists() {
        if std::os::unix::net::UnixStream::connect(path).is_ok() {
            return Err(format!("{} is in use: another spinscand is running (stop it, or pass --socket)", path.display()));
        }
        std::fs::remove_file(path).map_err(|e| format!("cannot remove the stale socket {}: {e}", path.display()))?;
    }
    let listener = UnixListener::bind(path).map_err(|e| format!("cannot bind {}: {e}", path.display()))?;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).map_err(|e| format!("cannot chmod {}: {e}", path.display()))?;
    if let Some(gid) = gid {
        std::os::unix::fs::chown(path, None, Some(gid)).map_err(|e| format!("cannot give {} to group {gid}: {e} (is spinscand in that group?)", path.display()))?;
    }
    Ok(listener)
}

/// Accepts connections until `shutdown` fires.
pub async fn serve(daemon: Arc<Daemon>, listener: UnixListener, mut shutdown: tokio::sync::watch::Receiver<bool>) {
    let clients = Arc::new(AtomicUsize::new(0));
    loop {
        tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => {
                    let (d, c) = (daemon.clone(), clients.clone());
                    tokio::spawn(async move {
                        if c.fetch_add(1, Ordering::SeqCst) >= d.config.daemon.max_clients {
                            let _ = refuse(stream, d.config.daemon.max_clients).await;
                        } else if let Err(e) = connection(d, stream).await {
                            tracing::debug!("client connection ended: {e}");
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

async fn refuse(mut stream: UnixStream, max: usize) -> std::io::Result<()> {
    let e = RpcError::new(code::BUSY, format!("too many clients (daemon.max_clients = {max}); try again later"));
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

async fn connection(daemon: Arc<Daemon>, stream: UnixStream) -> std::io::Result<()> {
    let cred = stream.peer_cred()?;
    let (uid, gid, pid) = (cred.uid(), cred.gid(), cred.pid());
    let may_control = daemon.auth.may_control(uid, gid);
    tracing::debug!(uid, gid, ?pid, may_control, "client connected");
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
    let hello = rpc::notification("hello", json!({"server": "spinscand", "version": env!("CARGO_PKG_VERSION"), "protocol": rpc::PROTOCOL_VERSION, "may_control": may_control}));
    send(hello).await;
    let max = daemon.config.daemon.max_request_bytes;
    let mut forwarder: Option<tokio::task::JoinHandle<()>> = None;
    loop {
        let line = match read_line(&mut reader, max).await? {
            Line::Eof => break,
            Line::TooLong => {
                let e = RpcError::new(code::INVALID_REQUEST, format!("request line longer than {max} bytes (daemon.max_request_bytes)"));
                send(rpc::error_response(&Value::Null, &e)).await;
                continue;
            }
            Line::NotUtf8 => {
                send(rpc::error_response(&Value::Null, &RpcError::new(code::PARSE_ERROR, "request line is not UTF-8"))).await;
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
        let result = if req.method == "events.subscribe" {
            rpc::Params::new(&req, &[]).map(|_| {
                if forwarder.is_none() {
                    forwarder = Some(forward_events(daemon.subscribe(), tx.clone()));
                }
                json!({"subscribed": ["scan.progress", "scan.state", "device.error"]})
            })
        } else {
            let d = daemon.clone();
            let who = format!("uid {uid}, pid {}", pid.map_or("?".to_string(), |p| p.to_string()));
            // Methods may touch devices (a serial round trip): off the async threads.
            tokio::task::spawn_blocking(move || dispatch(&d, &req, may_control, &who)).await.unwrap_or_else(|_| Err(RpcError::new(code::INTERNAL, "the request handler panicked")))
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
fn forward_events(mut events: tokio::sync::broadcast::Receiver<Value>, tx: tokio::sync::mpsc::Sender<String>) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        loop {
            let line = match events.recv().await {
                Ok(v) => format!("{v}\n"),
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
fn dispatch(daemon: &Arc<Daemon>, req: &Request, may_control: bool, who: &str) -> Result<Value, RpcError> {
    let control = matches!(req.method.as_str(), "scan.start" | "scan.stop");
    if control && !may_control {
        return Err(RpcError::new(code::PERMISSION_DENIED, format!("{}: permission denied for {who}: only root, spinscand's user and members of group `{}` may control scans", req.method, daemon.config.daemon.group)));
    }
    match req.method.as_str() {
        "status" => rpc::Params::new(req, &[]).map(|_| daemon.status()),
        "devices" => rpc::Params::new(req, &[]).map(|_| daemon.devices()),
        "scan.start" => daemon.start_scan(req),
        "scan.stop" => rpc::Params::new(req, &[]).and_then(|_| daemon.stop_scan(&format!("stopped by scan.stop ({who})"))),
        "scan.list" => rpc::Params::new(req, &[]).map(|_| daemon.list_scans()),
        "scan.get" => daemon.get_scan(req),
        other => Err(RpcError::new(code::METHOD_NOT_FOUND, format!("unknown method `{other}` (known: status, devices, scan.start, scan.stop, scan.list, scan.get, events.subscribe)"))),
    }
}
