//! The control layer: the daemon's socket protocol, typed.
//!
//! ```text
//!  line ─rpc::parse_request─> Request ─protocol::Call::parse─> Call ─server::dispatch─> Daemon (typed)
//!  line <─rpc::response / error_response <─ result or ControlError (error.rs: the codes) ─┘
//! ```
//!
//! The daemon's scan logic knows nothing of JSON-RPC; this module maps calls to it and its
//! [`crate::daemon::DaemonError`]s to error codes, in one place. The server and the blocking
//! [`client::Client`] share the request and answer types of [`protocol`].

pub mod auth;
pub mod client;
pub mod error;
pub mod protocol;
pub mod rpc;
pub mod server;

pub use auth::Auth;
pub use error::ControlError;
pub use protocol::{Call, ScanStartParams};
