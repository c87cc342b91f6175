//! Fuzz entry points: every reader of outside input, fed arbitrary bytes, with the properties
//! each must keep. The `cargo fuzz` targets in `fuzz/` call these (coverage-guided, nightly);
//! `tests/fuzz.rs` runs them on stable over a seeded mutation corpus in every test run. See
//! `docs/fuzzing.md` for the commands and the counts.
//!
//! Each function panics only when a property is broken — a reader that panics, an error
//! without a message, or an accepted input that does not survive its own writer.

use std::path::Path;

use crate::calib::StereoCalib;
use crate::control::protocol::Call;
use crate::control::rpc::{error_response, parse_request};
use crate::daemon::config::Config;

/// A line on the control socket: the JSON-RPC envelope, the call, and what `scan.start` would
/// run. An accepted call survives its own wire form.
pub fn request(data: &[u8]) {
    let Ok(line) = std::str::from_utf8(data) else { return };
    let req = match parse_request(line) {
        Ok(req) => req,
        Err((id, e)) => {
            let answer = error_response(&id, &e);
            assert!(answer["error"]["message"].as_str().is_some_and(|m| !m.is_empty()), "an error without a message: {answer}");
            return;
        }
    };
    let call = match Call::parse(&req) {
        Ok(call) => call,
        Err(e) => {
            assert!(!e.to_string().is_empty());
            return;
        }
    };
    let wire = serde_json::json!({"jsonrpc": "2.0", "id": 1, "method": call.method(), "params": call.params()}).to_string();
    let again = parse_request(&wire).unwrap_or_else(|(_, e)| panic!("{wire} does not parse again: {e}"));
    let call2 = Call::parse(&again).unwrap_or_else(|e| panic!("{wire} is not a call again: {e}"));
    assert_eq!(call2.params(), call.params(), "{wire}");
    if let Call::ScanStart(p) = &call {
        if let Ok(spec) = p.to_spec(&Config::default()) {
            // Refused or accepted, but never a panic, and an accepted scan has a bounded plan.
            if spec.validate().is_ok() && spec.mode == crate::pipeline::live::ScanMode::Step {
                // At most ten turns at the smallest step.
                let most = (3600.0 / crate::pipeline::live::MIN_STEP_DEG).ceil() as usize + 1;
                assert!(spec.step_views() <= most, "{spec:?} plans {} views", spec.step_views());
            }
        }
    }
}

/// A daemon config file: parsed and checked, or refused with the file named.
pub fn config(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let path = Path::new("fuzz.toml");
    match Config::parse(path, text) {
        Ok(c) => {
            // What a parsed config is used for must not panic either.
            let _ = c.pipeline_settings();
            let _ = c.assist();
            let _ = c.socket_mode();
        }
        Err(e) => names_the_file(&e, "fuzz.toml"),
    }
}

/// A `calib.yaml` (OpenCV FileStorage): read, or refused with the file named. An accepted
/// calibration reads back the same from what spinscan writes.
pub fn calibration(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let path = Path::new("calib.yaml");
    match StereoCalib::parse(text, path) {
        Ok(c) => {
            let yaml = c.to_yaml();
            let back = StereoCalib::parse(&yaml, path).unwrap_or_else(|e| panic!("spinscan's own calib.yaml does not read back: {e}\n{yaml}"));
            assert_eq!(back.to_yaml(), yaml);
        }
        Err(e) => names_the_file(&e, "calib.yaml"),
    }
}

/// A recording's `frames.jsonl`.
pub fn frames(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let path = Path::new("frames.jsonl");
    match crate::recording::parse_frames(path, text) {
        Ok((frames, torn)) => {
            let lines = text.split('\n').count();
            assert!(frames.len() <= lines, "{} frames from {lines} lines", frames.len());
            assert!(torn.is_none_or(|l| l == lines), "the torn line {torn:?} is not the last ({lines})");
        }
        Err(e) => names_the_file(&e, "frames.jsonl"),
    }
}

/// A PLY file: read, or refused with the file named. Faces only refer to vertices read, and
/// colours and normals come one per vertex.
pub fn ply(data: &[u8]) {
    let path = Path::new("in.ply");
    match crate::io::ply::read_ply_from(data, path) {
        Ok(mesh) => {
            let n = mesh.cloud.points.len();
            assert!(mesh.cloud.colors.is_empty() || mesh.cloud.colors.len() == n);
            assert!(mesh.cloud.normals.as_ref().is_none_or(|v| v.len() == n));
            assert!(mesh.cloud.rim_px.as_ref().is_none_or(|v| v.len() == n));
            assert!(mesh.triangles.iter().flatten().all(|&i| (i as usize) < n), "a face refers to a vertex outside 0…{n}");
        }
        Err(e) => names_the_file(&e, "in.ply"),
    }
}

/// A refusal says which file it refused.
fn names_the_file(e: &dyn std::fmt::Display, file: &str) {
    let message = e.to_string();
    assert!(message.contains(file), "the error does not name the file {file}: {message}");
}

/// A fuzz entry point: bytes in, a panic when a property breaks.
pub type Target = fn(&[u8]);

/// Every target by name, for the harnesses.
pub const TARGETS: [(&str, Target); 5] = [("request", request), ("config", config), ("calibration", calibration), ("frames", frames), ("ply", ply)];
