//! Every way a control request can fail, and its JSON-RPC error code — in one place.

use crate::daemon::DaemonError;

/// Error codes: JSON-RPC's standard ones and spinscand's own (−32000 …).
pub mod code {
    pub const PARSE_ERROR: i64 = -32700;
    pub const INVALID_REQUEST: i64 = -32600;
    pub const METHOD_NOT_FOUND: i64 = -32601;
    pub const INVALID_PARAMS: i64 = -32602;
    pub const INTERNAL: i64 = -32603;
    /// A scan is already running.
    pub const BUSY: i64 = -32000;
    /// No scan of that name, or no scan running.
    pub const NOT_FOUND: i64 = -32001;
    /// The peer may read but not control (SO_PEERCRED).
    pub const PERMISSION_DENIED: i64 = -32002;
    /// The devices are not usable.
    pub const DEVICE: i64 = -32003;
    /// A scan of that name exists already.
    pub const EXISTS: i64 = -32004;
}

/// Why a request got an error answer.
#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    /// The line is not JSON.
    #[error("{0}")]
    Parse(String),
    /// JSON, but not a JSON-RPC 2.0 request (or too long, or not UTF-8).
    #[error("{0}")]
    InvalidRequest(String),
    #[error("unknown method `{0}` (known: status, devices, scan.start, scan.stop, scan.list, scan.get, events.subscribe)")]
    MethodNotFound(String),
    /// A parameter is unknown, missing, of the wrong type or out of bounds.
    #[error("{0}")]
    Params(String),
    #[error("{method}: permission denied for {who}: only root{} may control scans", if group.is_empty() { " and spinscand's user".to_string() } else { format!(", spinscand's user and members of group `{group}`") })]
    PermissionDenied { method: String, who: String, group: String },
    #[error("too many clients (daemon.max_clients = {0}); try again later")]
    TooManyClients(usize),
    #[error("{0}")]
    Internal(String),
    #[error(transparent)]
    Daemon(#[from] DaemonError),
}

impl ControlError {
    /// The JSON-RPC error code of this error (`docs/protocol.md` lists them).
    pub fn code(&self) -> i64 {
        match self {
            ControlError::Parse(_) => code::PARSE_ERROR,
            ControlError::InvalidRequest(_) => code::INVALID_REQUEST,
            ControlError::MethodNotFound(_) => code::METHOD_NOT_FOUND,
            ControlError::Params(_) => code::INVALID_PARAMS,
            ControlError::PermissionDenied { .. } => code::PERMISSION_DENIED,
            ControlError::TooManyClients(_) => code::BUSY,
            ControlError::Internal(_) => code::INTERNAL,
            ControlError::Daemon(d) => match d {
                DaemonError::Spec(_) => code::INVALID_PARAMS,
                DaemonError::Busy(_) => code::BUSY,
                DaemonError::Exists { .. } => code::EXISTS,
                DaemonError::Devices(_) => code::DEVICE,
                DaemonError::Create { .. } | DaemonError::StateDir { .. } | DaemonError::Locked(_) | DaemonError::NoRoom { .. } => code::INTERNAL,
                DaemonError::NoScan | DaemonError::NoSuchScan { .. } => code::NOT_FOUND,
                DaemonError::NotFused(_) => code::NOT_FOUND,
                DaemonError::Params(_) => code::INVALID_PARAMS,
                DaemonError::Calibrating(_) => code::BUSY,
                DaemonError::NoCalibration => code::NOT_FOUND,
                DaemonError::CalibrationExists { .. } => code::EXISTS,
            },
        }
    }

    /// A daemon error answering `method`: parameter errors name the method, as the
    /// protocol's other parameter errors do.
    pub fn of(method: &str, e: DaemonError) -> ControlError {
        match e {
            DaemonError::Spec(s) => ControlError::Params(format!("{method}: {s}")),
            other => ControlError::Daemon(other),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::live::SpecError;

    #[test]
    fn every_daemon_error_has_its_code() {
        assert_eq!(ControlError::from(DaemonError::Busy("a".into())).code(), code::BUSY);
        assert_eq!(ControlError::from(DaemonError::NoScan).code(), code::NOT_FOUND);
        assert_eq!(ControlError::from(DaemonError::NotFused("a".into())).code(), code::NOT_FOUND);
        assert_eq!(ControlError::from(DaemonError::Exists { name: "a".into(), dir: "/x/a".into() }).code(), code::EXISTS);
        let e = ControlError::of("scan.start", DaemonError::Spec(SpecError::Range { field: "step_deg", expected: "within (0, 360]", got: "0".into() }));
        assert_eq!((e.code(), e.to_string().as_str()), (code::INVALID_PARAMS, "scan.start: `step_deg` must be within (0, 360], got 0"));
        // No group configured: the message names no empty group.
        let e = ControlError::PermissionDenied { method: "scan.start".into(), who: "uid 1000".into(), group: String::new() };
        assert!(e.to_string().ends_with("only root and spinscand's user may control scans"), "{e}");
    }
}
