//! JSON-RPC 2.0 on the wire: one JSON object per line, both ways (`docs/protocol.md`).
//! Framing only — the methods are typed in [`super::protocol`], the errors in
//! [`super::error`].

use serde_json::{json, Value};

use super::error::ControlError;

/// An error answer as it goes on the wire.
#[derive(Debug, Clone, PartialEq)]
pub struct RpcError {
    pub code: i64,
    pub message: String,
    pub data: Option<Value>,
}

impl From<&ControlError> for RpcError {
    fn from(e: &ControlError) -> RpcError {
        RpcError { code: e.code(), message: e.to_string(), data: None }
    }
}

/// Deserialises any JSON, failing on an object with a key twice (at any depth).
struct NoDuplicateKeys;

impl<'de> serde::Deserialize<'de> for NoDuplicateKeys {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visit;
        impl<'de> serde::de::Visitor<'de> for Visit {
            type Value = NoDuplicateKeys;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("JSON")
            }
            fn visit_map<M: serde::de::MapAccess<'de>>(self, mut map: M) -> Result<NoDuplicateKeys, M::Error> {
                let mut seen = std::collections::HashSet::new();
                while let Some(key) = map.next_key::<String>()? {
                    if !seen.insert(key.clone()) {
                        return Err(serde::de::Error::custom(format!("key `{key}` appears twice")));
                    }
                    map.next_value::<NoDuplicateKeys>()?;
                }
                Ok(NoDuplicateKeys)
            }
            fn visit_seq<S: serde::de::SeqAccess<'de>>(self, mut seq: S) -> Result<NoDuplicateKeys, S::Error> {
                while seq.next_element::<NoDuplicateKeys>()?.is_some() {}
                Ok(NoDuplicateKeys)
            }
            fn visit_bool<E>(self, _: bool) -> Result<NoDuplicateKeys, E> {
                Ok(NoDuplicateKeys)
            }
            fn visit_i64<E>(self, _: i64) -> Result<NoDuplicateKeys, E> {
                Ok(NoDuplicateKeys)
            }
            fn visit_u64<E>(self, _: u64) -> Result<NoDuplicateKeys, E> {
                Ok(NoDuplicateKeys)
            }
            fn visit_f64<E>(self, _: f64) -> Result<NoDuplicateKeys, E> {
                Ok(NoDuplicateKeys)
            }
            fn visit_str<E>(self, _: &str) -> Result<NoDuplicateKeys, E> {
                Ok(NoDuplicateKeys)
            }
            fn visit_unit<E>(self) -> Result<NoDuplicateKeys, E> {
                Ok(NoDuplicateKeys)
            }
        }
        d.deserialize_any(Visit)
    }
}

/// A request as read from a line.
#[derive(Debug, Clone, PartialEq)]
pub struct Request {
    /// None: a notification (no answer is sent).
    pub id: Option<Value>,
    pub method: String,
    pub params: Value,
}

/// Parses one line. On error, the id to answer with (null when unknown) and the error.
#[allow(clippy::result_large_err)] // one per request line; the id must travel with the error
pub fn parse_request(line: &str) -> Result<Request, (Value, ControlError)> {
    let v: Value = serde_json::from_str(line).map_err(|e| (Value::Null, ControlError::Parse(format!("not JSON: {e}; send one JSON-RPC 2.0 object per line"))))?;
    // serde_json keeps the last of duplicate keys; a request that says two things is refused.
    if let Err(e) = serde_json::from_str::<NoDuplicateKeys>(line) {
        return Err((Value::Null, ControlError::InvalidRequest(format!("{e}; every key may appear once"))));
    }
    let Value::Object(obj) = v else {
        return Err((Value::Null, ControlError::InvalidRequest("expected a JSON object like {\"jsonrpc\": \"2.0\", \"id\": 1, \"method\": \"status\"} (batches are not supported)".into())));
    };
    let id = obj.get("id").cloned();
    let id_for_error = id.clone().unwrap_or(Value::Null);
    if let Some(i) = &id {
        if !(i.is_string() || i.is_number() || i.is_null()) {
            return Err((Value::Null, ControlError::InvalidRequest("`id` must be a string, a number or null".into())));
        }
    }
    if obj.get("jsonrpc") != Some(&json!("2.0")) {
        return Err((id_for_error, ControlError::InvalidRequest("`jsonrpc` must be \"2.0\"".into())));
    }
    let method = match obj.get("method") {
        Some(Value::String(m)) => m.clone(),
        _ => return Err((id_for_error, ControlError::InvalidRequest("`method` must be a string".into()))),
    };
    let params = match obj.get("params") {
        None | Some(Value::Null) => json!({}),
        Some(p @ Value::Object(_)) => p.clone(),
        Some(_) => return Err((id_for_error, ControlError::Params("`params` must be an object (named parameters)".into()))),
    };
    Ok(Request { id, method, params })
}

pub fn response(id: &Value, result: Value) -> Value {
    json!({"jsonrpc": "2.0", "id": id, "result": result})
}

pub fn error_response(id: &Value, e: &ControlError) -> Value {
    let e = RpcError::from(e);
    let mut err = json!({"code": e.code, "message": e.message});
    if let Some(d) = &e.data {
        err["data"] = d.clone();
    }
    json!({"jsonrpc": "2.0", "id": id, "error": err})
}

pub fn notification(method: &str, params: Value) -> Value {
    json!({"jsonrpc": "2.0", "method": method, "params": params})
}

/// Reads named parameters strictly: unknown keys and wrong types are named in the error.
pub struct Params<'a> {
    obj: &'a serde_json::Map<String, Value>,
    method: &'a str,
}

impl<'a> Params<'a> {
    /// `allowed`: every key the method knows.
    pub fn new(req: &'a Request, allowed: &[&str]) -> Result<Params<'a>, ControlError> {
        let obj = req.params.as_object().expect("parse_request makes params an object");
        if let Some(k) = obj.keys().find(|k| !allowed.contains(&k.as_str())) {
            let known = if allowed.is_empty() { "none".to_string() } else { allowed.join(", ") };
            return Err(ControlError::Params(format!("{}: unknown parameter `{k}` (known: {known})", req.method)));
        }
        Ok(Params { obj, method: &req.method })
    }

    pub fn str(&self, key: &str) -> Result<Option<&'a str>, ControlError> {
        match self.obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(Value::String(s)) => Ok(Some(s.as_str())),
            Some(other) => Err(ControlError::Params(format!("{}: `{key}` must be a string, got {other}", self.method))),
        }
    }

    pub fn f64(&self, key: &str) -> Result<Option<f64>, ControlError> {
        match self.obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(Value::Number(n)) => Ok(n.as_f64()),
            Some(other) => Err(ControlError::Params(format!("{}: `{key}` must be a number, got {other}", self.method))),
        }
    }

    pub fn u64(&self, key: &str) -> Result<Option<u64>, ControlError> {
        match self.obj.get(key) {
            None | Some(Value::Null) => Ok(None),
            Some(Value::Number(n)) if n.as_u64().is_some() => Ok(n.as_u64()),
            Some(other) => Err(ControlError::Params(format!("{}: `{key}` must be a non-negative integer, got {other}", self.method))),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::error::code;

    #[test]
    fn requests_are_checked() {
        let r = parse_request(r#"{"jsonrpc":"2.0","id":7,"method":"status"}"#).unwrap();
        assert_eq!((r.id, r.method.as_str(), r.params), (Some(json!(7)), "status", json!({})));
        assert_eq!(parse_request("status").unwrap_err().1.code(), code::PARSE_ERROR);
        assert_eq!(parse_request("[1]").unwrap_err().1.code(), code::INVALID_REQUEST);
        let (id, e) = parse_request(r#"{"jsonrpc":"1.0","id":"a","method":"status"}"#).unwrap_err();
        assert_eq!((id, e.code()), (json!("a"), code::INVALID_REQUEST));
        assert_eq!(parse_request(r#"{"jsonrpc":"2.0","id":1,"method":"x","params":[1]}"#).unwrap_err().1.code(), code::INVALID_PARAMS);
        let r = parse_request(r#"{"jsonrpc":"2.0","id":1,"method":"scan.start","params":{"name":"a","stepdeg":2}}"#).unwrap();
        let e = Params::new(&r, &["name", "step_deg"]).err().unwrap();
        assert!(e.to_string().contains("`stepdeg`") && e.to_string().contains("step_deg"), "{e}");
        // Two values for one key: refused, not silently the last.
        let (_, e) = parse_request(r#"{"jsonrpc":"2.0","id":1,"method":"scan.start","params":{"name":"a","name":"b"}}"#).unwrap_err();
        assert_eq!(e.code(), code::INVALID_REQUEST);
        assert!(e.to_string().contains("`name` appears twice"), "{e}");
        let r = parse_request(r#"{"jsonrpc":"2.0","id":1,"method":"scan.start","params":{"name":3}}"#).unwrap();
        assert!(Params::new(&r, &["name"]).unwrap().str("name").unwrap_err().to_string().contains("must be a string"));
    }
}
