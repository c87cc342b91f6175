//! The control protocol's methods as types: what a client may send ([`Call`]) and the
//! typed answers. The server parses a request into a [`Call`] once, strictly (unknown keys
//! and wrong types are named); the client builds its requests from the same types.

use serde::{Deserialize, Serialize};
use serde_json::{json, Map, Value};

use super::error::ControlError;
use super::rpc::{Params, Request};
use crate::daemon::config::Config;
use crate::pipeline::live::{ScanMode, ScanSpec};

/// Protocol version sent in the hello notification; bumped when a method changes
/// incompatibly (new methods and keys do not bump it).
pub const PROTOCOL_VERSION: u32 = 1;

/// The events `events.subscribe` forwards.
pub const EVENTS: [&str; 6] = ["scan.progress", "scan.state", "scan.mesh", "device.error", "calib.progress", "calib.state"];

/// One method call with its parameters.
#[derive(Debug, Clone, PartialEq)]
pub enum Call {
    Status,
    Devices,
    ScanStart(ScanStartParams),
    ScanStop,
    ScanMesh,
    ScanList,
    ScanGet { name: String },
    EventsSubscribe,
    CalibCapture(CalibCaptureParams),
    CalibStop,
}

/// `calib.capture`'s parameters as sent; what is left out takes the defaults below.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CalibCaptureParams {
    pub name: String,
    /// `stereo` (default) or `turntable`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub kind: Option<String>,
    /// Pairs to keep: default 20 (stereo), 9 (turntable).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub count: Option<u64>,
    /// Inner corners, `9x6` by default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub board: Option<String>,
    pub square_mm: f64,
    /// Lens model: 5 (default), 8 or 14 coefficients.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<u64>,
    /// Turntable: the sweep, ± degrees (default 45).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sweep_deg: Option<f64>,
    /// Stereo: pairs looked at before giving up (default 40 × count).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_pairs: Option<u64>,
}

impl CalibCaptureParams {
    const KEYS: [&'static str; 8] = ["name", "kind", "count", "board", "square_mm", "model", "sweep_deg", "max_pairs"];

    /// The capture these parameters ask for, defaults filled in (checked where it starts).
    pub fn to_spec(&self) -> crate::daemon::calibration::CaptureSpec {
        let kind = self.kind.clone().unwrap_or_else(|| "stereo".into());
        let count = self.count.map_or(if kind == "turntable" { 9 } else { 20 }, |n| usize::try_from(n).unwrap_or(usize::MAX));
        crate::daemon::calibration::CaptureSpec {
            name: self.name.clone(),
            count,
            board: self.board.clone().unwrap_or_else(|| "9x6".into()),
            square_mm: self.square_mm,
            model: self.model.map_or(5, |m| u32::try_from(m).unwrap_or(0)),
            sweep_deg: self.sweep_deg.unwrap_or(45.0),
            max_pairs: self.max_pairs.map_or(count.saturating_mul(40), |n| usize::try_from(n).unwrap_or(usize::MAX)),
            kind,
        }
    }
}

/// `scan.start`'s parameters as sent; what is left out comes from the daemon's config.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ScanStartParams {
    pub name: String,
    /// `step` (default) or `continuous`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mode: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub step_deg: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub total_deg: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub speed_deg_s: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_views: Option<u64>,
}

impl ScanStartParams {
    const KEYS: [&'static str; 6] = ["name", "mode", "step_deg", "total_deg", "speed_deg_s", "max_views"];

    /// The scan these parameters ask for, with the config's defaults for what they leave
    /// out. Bounds are checked by [`ScanSpec::validate`] where the scan starts.
    pub fn to_spec(&self, config: &Config) -> Result<ScanSpec, ControlError> {
        let mode = match self.mode.as_deref() {
            None | Some("step") => ScanMode::Step,
            Some("continuous") => ScanMode::Continuous,
            Some(other) => return Err(ControlError::Params(format!("scan.start: `mode` must be \"step\" or \"continuous\", got {other:?}"))),
        };
        Ok(ScanSpec {
            name: self.name.clone(),
            mode,
            step_deg: self.step_deg.unwrap_or(config.scan.step_deg),
            total_deg: self.total_deg.unwrap_or(config.scan.total_deg),
            speed_deg_s: self.speed_deg_s.unwrap_or(config.turntable.continuous_deg_s),
            max_views: self.max_views.map(|n| usize::try_from(n).unwrap_or(usize::MAX)),
        })
    }
}

impl Call {
    /// Reads a parsed request strictly: its method, and parameters of the right names and
    /// types.
    pub fn parse(req: &Request) -> Result<Call, ControlError> {
        let none = || Params::new(req, &[]);
        Ok(match req.method.as_str() {
            "status" => none().map(|_| Call::Status)?,
            "devices" => none().map(|_| Call::Devices)?,
            "scan.stop" => none().map(|_| Call::ScanStop)?,
            "scan.mesh" => none().map(|_| Call::ScanMesh)?,
            "scan.list" => none().map(|_| Call::ScanList)?,
            "events.subscribe" => none().map(|_| Call::EventsSubscribe)?,
            "scan.get" => {
                let p = Params::new(req, &["name"])?;
                let name = p.str("name")?.ok_or_else(|| ControlError::Params("scan.get: `name` is required".into()))?;
                Call::ScanGet { name: name.to_string() }
            }
            "scan.start" => {
                let p = Params::new(req, &ScanStartParams::KEYS)?;
                let name = p.str("name")?.ok_or_else(|| ControlError::Params("scan.start: `name` is required".into()))?.to_string();
                Call::ScanStart(ScanStartParams {
                    name,
                    mode: p.str("mode")?.map(str::to_string),
                    step_deg: p.f64("step_deg")?,
                    total_deg: p.f64("total_deg")?,
                    speed_deg_s: p.f64("speed_deg_s")?,
                    max_views: p.u64("max_views")?,
                })
            }
            "calib.stop" => none().map(|_| Call::CalibStop)?,
            "calib.capture" => {
                let p = Params::new(req, &CalibCaptureParams::KEYS)?;
                let name = p.str("name")?.ok_or_else(|| ControlError::Params("calib.capture: `name` is required".into()))?.to_string();
                let square_mm = p.f64("square_mm")?.ok_or_else(|| ControlError::Params("calib.capture: `square_mm` (the printed square's side, mm) is required".into()))?;
                Call::CalibCapture(CalibCaptureParams {
                    name,
                    kind: p.str("kind")?.map(str::to_string),
                    count: p.u64("count")?,
                    board: p.str("board")?.map(str::to_string),
                    square_mm,
                    model: p.u64("model")?,
                    sweep_deg: p.f64("sweep_deg")?,
                    max_pairs: p.u64("max_pairs")?,
                })
            }
            other => return Err(ControlError::MethodNotFound(other.to_string())),
        })
    }

    /// The method's name on the wire.
    pub fn method(&self) -> &'static str {
        match self {
            Call::Status => "status",
            Call::Devices => "devices",
            Call::ScanStart(_) => "scan.start",
            Call::ScanStop => "scan.stop",
            Call::ScanMesh => "scan.mesh",
            Call::ScanList => "scan.list",
            Call::ScanGet { .. } => "scan.get",
            Call::EventsSubscribe => "events.subscribe",
            Call::CalibCapture(_) => "calib.capture",
            Call::CalibStop => "calib.stop",
        }
    }

    /// The parameters on the wire (named, an object).
    pub fn params(&self) -> Value {
        match self {
            Call::ScanStart(p) => serde_json::to_value(p).expect("parameters serialise"),
            Call::ScanGet { name } => json!({ "name": name }),
            Call::CalibCapture(p) => serde_json::to_value(p).expect("parameters serialise"),
            _ => Value::Object(Map::new()),
        }
    }

    /// Whether the call changes what the daemon does (only controlling peers may).
    pub fn controls(&self) -> bool {
        matches!(self, Call::ScanStart(_) | Call::ScanStop | Call::ScanMesh | Call::CalibCapture(_) | Call::CalibStop)
    }
}

/// The `hello` notification each connection starts with.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    pub server: String,
    pub version: String,
    pub protocol: u32,
    pub may_control: bool,
}

/// One entry of `scan.list`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanEntry {
    pub name: String,
    pub status: Value,
    pub frames: Value,
    pub mode: Value,
    pub reason: Value,
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub running: bool,
}

/// `scan.list`'s answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScanList {
    pub scans: Vec<ScanEntry>,
}

/// `events.subscribe`'s answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Subscribed {
    pub subscribed: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::rpc::parse_request;

    fn call(line: &str) -> Result<Call, ControlError> {
        Call::parse(&parse_request(line).unwrap())
    }

    #[test]
    fn calls_round_trip_through_the_wire_form() {
        let start = Call::ScanStart(ScanStartParams { name: "vase".into(), mode: Some("continuous".into()), total_deg: Some(90.0), ..Default::default() });
        let calib = Call::CalibCapture(CalibCaptureParams { name: "rig".into(), kind: Some("turntable".into()), square_mm: 24.0, count: Some(9), ..Default::default() });
        for c in [Call::Status, Call::ScanStop, Call::ScanGet { name: "vase".into() }, start, calib, Call::CalibStop] {
            let line = json!({"jsonrpc": "2.0", "id": 1, "method": c.method(), "params": c.params()}).to_string();
            assert_eq!(call(&line).unwrap(), c);
        }
    }

    #[test]
    fn parameters_are_checked_by_name_and_type() {
        let e = call(r#"{"jsonrpc":"2.0","id":1,"method":"scan.start","params":{"name":"a","stepdeg":2}}"#).unwrap_err();
        assert!(e.to_string().contains("`stepdeg`"), "{e}");
        let e = call(r#"{"jsonrpc":"2.0","id":1,"method":"scan.start","params":{"step_deg":2}}"#).unwrap_err();
        assert_eq!(e.to_string(), "scan.start: `name` is required");
        let e = call(r#"{"jsonrpc":"2.0","id":1,"method":"status","params":{"x":1}}"#).unwrap_err();
        assert!(e.to_string().contains("unknown parameter `x`"), "{e}");
        assert!(matches!(call(r#"{"jsonrpc":"2.0","id":1,"method":"scan.explode"}"#), Err(ControlError::MethodNotFound(_))));
        let spec = ScanStartParams { name: "a".into(), mode: Some("spiral".into()), ..Default::default() }.to_spec(&Config::sim());
        assert!(spec.unwrap_err().to_string().contains("\"spiral\""));
    }
}
