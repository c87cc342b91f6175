//! A blocking client of the control socket, for the `spinscan` CLI (and anyone's Rust).

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::{json, Value};

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
    pub hello: Value,
    /// Notifications read while waiting for an answer, oldest first.
    pending: std::collections::VecDeque<Value>,
}

impl Client {
    pub fn connect(path: &Path) -> Result<Client, ClientError> {
        let stream = UnixStream::connect(path).map_err(|source| ClientError::Connect { path: path.to_path_buf(), source })?;
        stream.set_read_timeout(Some(Duration::from_secs(30)))?;
        let writer = stream.try_clone()?;
        let mut c = Client { reader: BufReader::new(stream), writer, next_id: 0, hello: Value::Null, pending: Default::default() };
        let hello = c.read()?;
        if hello["method"] == "hello" {
            c.hello = hello["params"].clone();
        } else if let Some(e) = hello.get("error") {
            return Err(ClientError::Rpc { code: e["code"].as_i64().unwrap_or(0), message: e["message"].as_str().unwrap_or("").to_string() });
        } else {
            return Err(ClientError::Protocol(format!("expected a hello notification, got {hello}")));
        }
        Ok(c)
    }

    /// How long a read may wait (a watch waits for events as long as a scan runs).
    pub fn set_timeout(&self, t: Option<Duration>) -> Result<(), ClientError> {
        Ok(self.reader.get_ref().set_read_timeout(t)?)
    }

    fn read(&mut self) -> Result<Value, ClientError> {
        let mut line = String::new();
        if self.reader.read_line(&mut line)? == 0 {
            return Err(ClientError::Io(std::io::Error::new(std::io::ErrorKind::UnexpectedEof, "spinscand closed the connection")));
        }
        serde_json::from_str(&line).map_err(|e| ClientError::Protocol(format!("{e}: {}", line.trim_end())))
    }

    /// Calls `method` and waits for its answer; notifications on the way are kept for
    /// [`Client::next_notification`].
    pub fn call(&mut self, method: &str, params: Value) -> Result<Value, ClientError> {
        self.next_id += 1;
        let id = self.next_id;
        writeln!(self.writer, "{}", json!({"jsonrpc": "2.0", "id": id, "method": method, "params": params}))?;
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

    /// The next notification (`{"method", "params"}`), waiting for it.
    pub fn next_notification(&mut self) -> Result<Value, ClientError> {
        if let Some(v) = self.pending.pop_front() {
            return Ok(v);
        }
        loop {
            let v = self.read()?;
            if v.get("method").is_some() {
                return Ok(v);
            }
        }
    }
}
