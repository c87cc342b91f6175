//! A blocking client of the control socket, for the `spinscan` CLI (and anyone's Rust):
//! requests are [`Call`]s, answers the protocol's types.

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::de::DeserializeOwned;
use serde_json::{json, Value};

use super::protocol::{Call, Hello, ScanList, ScanStartParams, Subscribed};
use crate::daemon::{ScanMeshing, ScanStarted, ScanStopping};

/// Why a call did not get a result.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    #[error("cannot connect to spinscand at {path}: {source} (is it running? `systemctl status spinscand`, or pass --socket)")]
    Connect { path: PathBuf, source: std::io::Error },
    #[error("connection to spinscand lost: {0}")]
    Io(#[from] std::io::Error),
    #[error("spinscand sent a line that is not JSON-RPC: {0}")]
    Protocol(String),
    #[error("{message} (error {code})")]
    Rpc { code: i64, message: String },
}

pub struct Client {
    reader: BufReader<UnixStream>,
    writer: UnixStream,
    next_id: u64,
    /// The hello notification's params.
    pub hello: Hello,
    /// Notifications read while waiting for an answer, oldest first.
    pending: std::collections::VecDeque<Value>,
}

impl Client {
    pub fn connect(path: &Path) -> Result<Client, ClientError> {
        let stream = UnixStream::connect(path).map_err(|source| ClientError::Connect { path: path.to_path_buf(), source })?;
        stream.set_read_timeout(Some(Duration::from_secs(30)))?;
        let writer = stream.try_clone()?;
        let mut reader = BufReader::new(stream);
        let hello = read(&mut reader)?;
        if hello["method"] == "hello" {
            let hello = serde_json::from_value(hello["params"].clone()).map_err(|e| ClientError::Protocol(format!("hello: {e}")))?;
            Ok(Client { reader, writer, next_id: 0, hello, pending: Default::default() })
        } else if let Some(e) = hello.get("error") {
            Err(ClientError::Rpc { code: e["code"].as_i64().unwrap_or(0), message: e["message"].as_str().unwrap_or("").to_string() })
        } else {
            Err(ClientError::Protocol(format!("expected a hello notification, got {hello}")))
        }
    }

    /// How long a read may wait (a watch waits for events as long as a scan runs).
    pub fn set_timeout(&self, t: Option<Duration>) -> Result<(), ClientError> {
        Ok(self.reader.get_ref().set_read_timeout(t)?)
    }

    fn read(&mut self) -> Result<Value, ClientError> {
        read(&mut self.reader)
    }

    /// Sends `call` and waits for its answer; notifications on the way are kept for
    /// [`Client::next_notification`].
    pub fn call(&mut self, call: &Call) -> Result<Value, ClientError> {
        self.next_id += 1;
        let id = self.next_id;
        writeln!(self.writer, "{}", json!({"jsonrpc": "2.0", "id": id, "method": call.method(), "params": call.params()}))?;
        loop {
            let v = self.read()?;
            if v.get("id") == Some(&json!(id)) {
                if let Some(e) = v.get("error") {
                    return Err(ClientError::Rpc { code: e["code"].as_i64().unwrap_or(0), message: e["message"].as_str().unwrap_or("").to_string() });
                }
                return Ok(v["result"].clone());
            }
            if v.get("method").is_some() {
                self.pending.push_back(v);
            } else {
                return Err(ClientError::Protocol(format!("an answer to another request: {v}")));
            }
        }
    }

    /// `call`'s answer, read as `T`.
    fn typed<T: DeserializeOwned>(&mut self, call: &Call) -> Result<T, ClientError> {
        let v = self.call(call)?;
        serde_json::from_value(v.clone()).map_err(|e| ClientError::Protocol(format!("{} answered {v}: {e}", call.method())))
    }

    /// `status`: the daemon, its scan and its devices.
    pub fn status(&mut self) -> Result<Value, ClientError> {
        self.call(&Call::Status)
    }

    /// `devices`: the configured devices and what is present.
    pub fn devices(&mut self) -> Result<Value, ClientError> {
        self.call(&Call::Devices)
    }

    pub fn scan_start(&mut self, params: &ScanStartParams) -> Result<ScanStarted, ClientError> {
        self.typed(&Call::ScanStart(params.clone()))
    }

    pub fn scan_stop(&mut self) -> Result<ScanStopping, ClientError> {
        self.typed(&Call::ScanStop)
    }

    /// `scan.mesh`: asks the running scan for a preview mesh (announced by a `scan.mesh`
    /// event).
    pub fn scan_mesh(&mut self) -> Result<ScanMeshing, ClientError> {
        self.typed(&Call::ScanMesh)
    }

    pub fn scan_list(&mut self) -> Result<ScanList, ClientError> {
        self.typed(&Call::ScanList)
    }

    /// `scan.get`: a scan's manifest.
    pub fn scan_get(&mut self, name: &str) -> Result<Value, ClientError> {
        self.call(&Call::ScanGet { name: name.to_string() })
    }

    /// `calib.capture`: starts capturing calibration pairs (announced by `calib.*` events).
    pub fn calib_capture(&mut self, params: &super::protocol::CalibCaptureParams) -> Result<Value, ClientError> {
        self.call(&Call::CalibCapture(params.clone()))
    }

    /// `calib.stop`: ends the capture after its current pair; what was kept is solved.
    pub fn calib_stop(&mut self) -> Result<Value, ClientError> {
        self.call(&Call::CalibStop)
    }

    pub fn subscribe(&mut self) -> Result<Subscribed, ClientError> {
        self.typed(&Call::EventsSubscribe)
    }

    /// The next notification, waiting for it.
    pub fn next_notification(&mut self) -> Result<Notification, ClientError> {
        let v = match self.pending.pop_front() {
            Some(v) => v,
            None => loop {
                let v = self.read()?;
                if v.get("method").is_some() {
                    break v;
                }
            },
        };
        match v["method"].as_str() {
            Some(m) => Ok(Notification { method: m.to_string(), params: v["params"].clone() }),
            None => Err(ClientError::Protocol(format!("a notification without a method: {v}"))),
        }
    }
}

/// A notification from the daemon (`scan.progress`, `scan.state`, `device.error`,
/// `events.lagged`).
#[derive(Debug, Clone, PartialEq)]
pub struct Notification {
    pub method: String,
    pub params: Value,
}

fn read(reader: &mut BufReader<UnixStream>) -> Result<Value, ClientError> {
    let mut line = String::new();
    if reader.read_line(&mut line)? == 0 {
        return Err(ClientError::Io(std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "spinscand closed the connection")));
    }
    serde_json::from_str(&line).map_err(|e| ClientError::Protocol(format!("{e}: {}", line.trim_end())))
}
