//! One progress line on stderr that log lines never land on: on a terminal the line is
//! redrawn in place, and a log line first clears it, prints itself on a line of its own,
//! then draws the progress again (what `indicatif`'s tracing bridge does, without the
//! dependency). Elsewhere (CI logs, pipes) progress prints as plain lines, at most one a
//! second plus the last one, so logs stay short and readable.

use std::io::{IsTerminal, Write};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use tracing_subscriber::fmt::MakeWriter;

struct State {
    /// The progress line being shown (terminal) or last given (elsewhere).
    line: Option<String>,
    /// Whether `line` has been printed (elsewhere).
    printed: bool,
    last_print: Option<Instant>,
}

static STATE: Mutex<State> = Mutex::new(State { line: None, printed: false, last_print: None });

fn tty() -> bool {
    std::io::stderr().is_terminal()
}

/// How often progress prints when stderr is not a terminal.
const PLAIN_EVERY: Duration = Duration::from_secs(1);

/// Shows `line` as the current progress.
pub fn show(line: impl Into<String>) {
    let line = line.into();
    let mut s = STATE.lock().unwrap_or_else(|e| e.into_inner());
    let mut err = std::io::stderr().lock();
    if tty() {
        let _ = write!(err, "\r{line}\x1b[K");
        let _ = err.flush();
        s.printed = true;
    } else if s.last_print.is_none_or(|t| t.elapsed() >= PLAIN_EVERY) {
        let _ = writeln!(err, "{line}");
        s.last_print = Some(Instant::now());
        s.printed = true;
    } else {
        s.printed = false;
    }
    s.line = Some(line);
}

/// Ends the progress line: on a terminal the cursor moves to the next line; elsewhere the
/// last update is printed if it was not.
pub fn finish() {
    let mut s = STATE.lock().unwrap_or_else(|e| e.into_inner());
    let Some(line) = s.line.take() else { return };
    let mut err = std::io::stderr().lock();
    if tty() {
        let _ = writeln!(err);
    } else if !s.printed {
        let _ = writeln!(err, "{line}");
    }
    s.printed = false;
    s.last_print = None;
}

/// tracing's writer for the CLI: each log line clears the progress line first and draws it
/// again after.
pub struct LogWriter;

impl<'a> MakeWriter<'a> for LogWriter {
    type Writer = LogLine;
    fn make_writer(&'a self) -> LogLine {
        LogLine(Vec::new())
    }
}

/// One log record, written whole when dropped.
pub struct LogLine(Vec<u8>);

impl Write for LogLine {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for LogLine {
    fn drop(&mut self) {
        if self.0.is_empty() {
            return;
        }
        let s = STATE.lock().unwrap_or_else(|e| e.into_inner());
        let mut err = std::io::stderr().lock();
        let shown = s.line.as_deref().filter(|_| tty());
        if shown.is_some() {
            let _ = write!(err, "\r\x1b[K");
        }
        let _ = err.write_all(&self.0);
        if !self.0.ends_with(b"\n") {
            let _ = writeln!(err);
        }
        if let Some(line) = shown {
            let _ = write!(err, "{line}");
        }
        let _ = err.flush();
    }
}
