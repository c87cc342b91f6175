//! A reader for the subset of YAML that OpenCV's `FileStorage` writes.
//!
//! OpenCV 3/4 open their files with `%YAML:1.0` (not valid YAML 1.x, so general YAML crates
//! reject it), OpenCV 5 with `%YAML 1.2`; both then write block mappings whose values are
//! scalars, flow sequences (`[ 1., 2.,` wrapped over lines) or tagged mappings
//! (`!!opencv-matrix`, `!!opencv-nd-matrix`). This module parses exactly that shape into a
//! small tree and turns matrix nodes into `nalgebra` matrices. Every error names the line and
//! the key.

use nalgebra::DMatrix;

/// One parsed value.
#[derive(Debug, Clone, PartialEq)]
pub enum Node {
    /// A scalar as written (quotes removed).
    Scalar(String),
    /// A flow or block sequence.
    Seq(Vec<Node>),
    /// A mapping with its optional tag (`opencv-matrix` for `!!opencv-matrix`).
    Map { tag: Option<String>, entries: Vec<(String, Entry)> },
}

/// A mapping value with the 1-based line it starts on, for error messages.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    pub line: usize,
    pub node: Node,
}

/// What went wrong while reading a FileStorage document.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FileStorageError {
    #[error("line {line}: {what}")]
    Syntax { line: usize, what: String },
    #[error("key `{key}` (line {line}): {what}")]
    Value { key: String, line: usize, what: String },
}

/// A parsed FileStorage document: the top-level mapping.
#[derive(Debug, Clone)]
pub struct Document {
    entries: Vec<(String, Entry)>,
}

struct Line<'a> {
    number: usize,
    indent: usize,
    text: &'a str,
}

impl Document {
    /// Parses a whole document.
    pub fn parse(text: &str) -> Result<Document, FileStorageError> {
        let mut lines = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let number = i + 1;
            let raw = raw.trim_end_matches('\r');
            let no_comment = strip_comment(raw);
            let trimmed = no_comment.trim_end();
            if trimmed.trim().is_empty() {
                continue;
            }
            if trimmed.starts_with('%') || trimmed.trim() == "---" || trimmed.trim() == "..." {
                continue;
            }
            let indent = trimmed.len() - trimmed.trim_start().len();
            lines.push(Line { number, indent, text: trimmed.trim_start() });
        }
        if lines.is_empty() {
            return Err(FileStorageError::Syntax {
                line: 1,
                what: "the document is empty (expected `key: value` lines)".into(),
            });
        }
        let mut pos = 0;
        let entries = parse_block_map(&lines, &mut pos, lines[0].indent)?;
        if pos < lines.len() {
            return Err(FileStorageError::Syntax {
                line: lines[pos].number,
                what: format!("unexpected indentation of `{}`", lines[pos].text),
            });
        }
        Ok(Document { entries })
    }

    /// The top-level entry named `key`.
    pub fn get(&self, key: &str) -> Option<&Entry> {
        lookup(&self.entries, key)
    }

    /// All top-level keys, in file order.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.entries.iter().map(|(k, _)| k.as_str())
    }
}

fn lookup<'a>(entries: &'a [(String, Entry)], key: &str) -> Option<&'a Entry> {
    entries.iter().find(|(k, _)| k == key).map(|(_, e)| e)
}

/// Removes a `#` comment that is not inside quotes.
fn strip_comment(s: &str) -> &str {
    let mut in_quote: Option<char> = None;
    for (i, c) in s.char_indices() {
        match (in_quote, c) {
            (None, '"') | (None, '\'') => in_quote = Some(c),
            (Some(q), c) if c == q => in_quote = None,
            (None, '#') if i == 0 || s[..i].ends_with(char::is_whitespace) => return &s[..i],
            _ => {}
        }
    }
    s
}

fn parse_block_map(
    lines: &[Line],
    pos: &mut usize,
    indent: usize,
) -> Result<Vec<(String, Entry)>, FileStorageError> {
    let mut entries = Vec::new();
    while *pos < lines.len() {
        let line = &lines[*pos];
        if line.indent < indent {
            break;
        }
        if line.indent > indent {
            return Err(FileStorageError::Syntax {
                line: line.number,
                what: format!("unexpected indentation of `{}`", line.text),
            });
        }
        let Some((key, rest)) = split_key(line.text) else {
            return Err(FileStorageError::Syntax {
                line: line.number,
                what: format!("expected `key: value`, found `{}`", line.text),
            });
        };
        *pos += 1;
        let number = line.number;
        let (tag, rest) = split_tag(rest.trim());
        let node = if rest.is_empty() {
            // A nested block: a mapping or a `- item` sequence, more indented than the key.
            if *pos < lines.len() && lines[*pos].indent > indent {
                let child_indent = lines[*pos].indent;
                if lines[*pos].text.starts_with("- ") || lines[*pos].text == "-" {
                    parse_block_seq(lines, pos, child_indent)?
                } else {
                    Node::Map { tag, entries: parse_block_map(lines, pos, child_indent)? }
                }
            } else if tag.is_some() {
                Node::Map { tag, entries: Vec::new() }
            } else {
                Node::Scalar(String::new())
            }
        } else {
            let mut node = parse_flow_value(rest, lines, pos, number)?;
            if let (Node::Map { tag: t, .. }, Some(tag)) = (&mut node, tag) {
                *t = Some(tag);
            }
            node
        };
        entries.push((key.to_string(), Entry { line: number, node }));
    }
    Ok(entries)
}

fn parse_block_seq(lines: &[Line], pos: &mut usize, indent: usize) -> Result<Node, FileStorageError> {
    let mut items = Vec::new();
    while *pos < lines.len() && lines[*pos].indent == indent && lines[*pos].text.starts_with('-') {
        let line = &lines[*pos];
        let number = line.number;
        let rest = line.text[1..].trim();
        *pos += 1;
        items.push(parse_flow_value(rest, lines, pos, number)?);
    }
    Ok(Node::Seq(items))
}

/// Splits `key: rest` (the key may be quoted).
fn split_key(text: &str) -> Option<(&str, &str)> {
    if let Some(stripped) = text.strip_prefix('"') {
        let end = stripped.find('"')?;
        let after = stripped[end + 1..].trim_start();
        return Some((&stripped[..end], after.strip_prefix(':')?));
    }
    let idx = text.find(':')?;
    let rest = &text[idx + 1..];
    if !(rest.is_empty() || rest.starts_with(' ') || rest.starts_with('\t')) {
        return None;
    }
    Some((text[..idx].trim(), rest))
}

/// Splits a leading `!!tag` or `!tag` off a value.
fn split_tag(rest: &str) -> (Option<String>, &str) {
    if let Some(t) = rest.strip_prefix('!') {
        let t = t.trim_start_matches('!');
        let end = t.find(char::is_whitespace).unwrap_or(t.len());
        (Some(t[..end].to_string()), t[end..].trim())
    } else {
        (None, rest)
    }
}

/// Parses a flow value that may continue over the following (more indented) lines.
fn parse_flow_value(
    first: &str,
    lines: &[Line],
    pos: &mut usize,
    number: usize,
) -> Result<Node, FileStorageError> {
    if !(first.starts_with('[') || first.starts_with('{')) {
        return Ok(Node::Scalar(unquote(first).to_string()));
    }
    let mut text = first.to_string();
    while !brackets_balanced(&text) {
        if *pos >= lines.len() {
            return Err(FileStorageError::Syntax {
                line: number,
                what: "unterminated `[` or `{` (the file ends before it closes)".into(),
            });
        }
        text.push(' ');
        text.push_str(lines[*pos].text);
        *pos += 1;
    }
    let mut chars = FlowParser { s: text.as_bytes(), i: 0, line: number };
    let node = chars.value()?;
    chars.skip_ws();
    if chars.i != chars.s.len() {
        return Err(FileStorageError::Syntax {
            line: number,
            what: format!("unexpected text after the value: `{}`", &text[chars.i..]),
        });
    }
    Ok(node)
}

fn brackets_balanced(s: &str) -> bool {
    let mut depth = 0i32;
    let mut in_quote = false;
    for c in s.chars() {
        match c {
            '"' => in_quote = !in_quote,
            '[' | '{' if !in_quote => depth += 1,
            ']' | '}' if !in_quote => depth -= 1,
            _ => {}
        }
    }
    depth <= 0
}

fn unquote(s: &str) -> &str {
    let s = s.trim();
    if s.len() >= 2 && ((s.starts_with('"') && s.ends_with('"')) || (s.starts_with('\'') && s.ends_with('\''))) {
        &s[1..s.len() - 1]
    } else {
        s
    }
}

struct FlowParser<'a> {
    s: &'a [u8],
    i: usize,
    line: usize,
}

impl FlowParser<'_> {
    fn skip_ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }

    fn err(&self, what: &str) -> FileStorageError {
        FileStorageError::Syntax { line: self.line, what: what.to_string() }
    }

    fn value(&mut self) -> Result<Node, FileStorageError> {
        self.skip_ws();
        match self.s.get(self.i) {
            Some(b'[') => {
                self.i += 1;
                let mut items = Vec::new();
                loop {
                    self.skip_ws();
                    if self.s.get(self.i) == Some(&b']') {
                        self.i += 1;
                        return Ok(Node::Seq(items));
                    }
                    items.push(self.value()?);
                    self.skip_ws();
                    match self.s.get(self.i) {
                        Some(b',') => self.i += 1,
                        Some(b']') => {}
                        _ => return Err(self.err("expected `,` or `]` in a sequence")),
                    }
                }
            }
            Some(b'{') => {
                self.i += 1;
                let mut entries = Vec::new();
                loop {
                    self.skip_ws();
                    if self.s.get(self.i) == Some(&b'}') {
                        self.i += 1;
                        return Ok(Node::Map { tag: None, entries });
                    }
                    let key = self.scalar(b":")?;
                    if self.s.get(self.i) != Some(&b':') {
                        return Err(self.err("expected `key: value` in a `{ }` mapping"));
                    }
                    self.i += 1;
                    let node = self.value()?;
                    entries.push((key, Entry { line: self.line, node }));
                    self.skip_ws();
                    match self.s.get(self.i) {
                        Some(b',') => self.i += 1,
                        Some(b'}') => {}
                        _ => return Err(self.err("expected `,` or `}` in a mapping")),
                    }
                }
            }
            Some(_) => Ok(Node::Scalar(self.scalar(b",]}")?)),
            None => Err(self.err("expected a value")),
        }
    }

    fn scalar(&mut self, stops: &[u8]) -> Result<String, FileStorageError> {
        self.skip_ws();
        if self.s.get(self.i) == Some(&b'"') {
            let start = self.i + 1;
            let end = self.s[start..]
                .iter()
                .position(|&c| c == b'"')
                .ok_or_else(|| self.err("unterminated string"))?;
            self.i = start + end + 1;
            self.skip_ws();
            return Ok(String::from_utf8_lossy(&self.s[start..start + end]).into_owned());
        }
        let start = self.i;
        while self.i < self.s.len() && !stops.contains(&self.s[self.i]) {
            self.i += 1;
        }
        Ok(String::from_utf8_lossy(&self.s[start..self.i]).trim().to_string())
    }
}

impl Entry {
    fn value_err(&self, key: &str, what: impl Into<String>) -> FileStorageError {
        FileStorageError::Value { key: key.to_string(), line: self.line, what: what.into() }
    }

    /// Reads the entry as a number.
    pub fn as_f64(&self, key: &str) -> Result<f64, FileStorageError> {
        match &self.node {
            Node::Scalar(s) => parse_number(s).ok_or_else(|| self.value_err(key, format!("expected a number, found `{s}`"))),
            _ => Err(self.value_err(key, "expected a number, found a mapping or sequence")),
        }
    }

    /// Reads an `!!opencv-matrix` or `!!opencv-nd-matrix` node (a 1-D nd-matrix becomes a
    /// column).
    pub fn as_matrix(&self, key: &str) -> Result<DMatrix<f64>, FileStorageError> {
        let Node::Map { entries, .. } = &self.node else {
            return Err(self.value_err(key, "expected an !!opencv-matrix (rows, cols, dt, data)"));
        };
        let field = |name: &str| {
            lookup(entries, name).ok_or_else(|| {
                self.value_err(key, format!("matrix has no `{name}` (expected rows, cols, dt, data or sizes, dt, data)"))
            })
        };
        let (rows, cols) = if let Some(sizes) = lookup(entries, "sizes") {
            let Node::Seq(items) = &sizes.node else {
                return Err(self.value_err(key, "`sizes` must be a sequence such as [ 3, 3 ]"));
            };
            let dims = items
                .iter()
                .map(|n| match n {
                    Node::Scalar(s) => s.trim().parse::<usize>().ok(),
                    _ => None,
                })
                .collect::<Option<Vec<_>>>()
                .ok_or_else(|| self.value_err(key, "`sizes` must hold non-negative integers"))?;
            match dims.as_slice() {
                [n] => (*n, 1),
                [r, c] => (*r, *c),
                [r, c, 1] => (*r, *c),
                _ => return Err(self.value_err(key, format!("only 1-D and 2-D matrices are supported, `sizes` is {dims:?}"))),
            }
        } else {
            let int = |name: &str| -> Result<usize, FileStorageError> {
                let e = field(name)?;
                let v = e.as_f64(&format!("{key}.{name}"))?;
                if v < 0.0 || v.fract() != 0.0 {
                    return Err(self.value_err(key, format!("`{name}` must be a non-negative integer, found {v}")));
                }
                Ok(v as usize)
            };
            (int("rows")?, int("cols")?)
        };
        let dt = match &field("dt")?.node {
            Node::Scalar(s) => s.clone(),
            _ => return Err(self.value_err(key, "`dt` must be a type code such as d or f")),
        };
        if dt.len() != 1 || !"ucwsifdh".contains(dt.as_str()) {
            return Err(self.value_err(key, format!("`dt: {dt}` is not a single-channel type (expected one of u c w s i f d h)")));
        }
        let data = match &field("data")?.node {
            Node::Seq(items) => items
                .iter()
                .map(|n| match n {
                    Node::Scalar(s) => parse_number(s),
                    _ => None,
                })
                .collect::<Option<Vec<f64>>>()
                .ok_or_else(|| self.value_err(key, "`data` must be a sequence of numbers"))?,
            _ => return Err(self.value_err(key, "`data` must be a sequence [ … ]")),
        };
        // Calibration matrices are small; a size beyond any of them is a broken file (and
        // an empty matrix of 2⁶⁴ rows would still cost a loop over them).
        if rows > MAX_DIM || cols > MAX_DIM {
            return Err(self.value_err(key, format!("{rows} × {cols} is larger than any calibration matrix (at most {MAX_DIM} rows and columns)")));
        }
        match rows.checked_mul(cols) {
            Some(n) if n == data.len() => {}
            n => {
                let product = n.map_or("more than any file holds".to_string(), |n| n.to_string());
                return Err(self.value_err(key, format!("`data` holds {} numbers but rows × cols = {rows} × {cols} = {product}", data.len())));
            }
        }
        Ok(DMatrix::from_row_slice(rows, cols, &data))
    }
}

/// Most rows or columns of a matrix read.
const MAX_DIM: usize = 4096;

/// Parses a number as OpenCV writes it (`0.`, `1.5e+02`, `.Inf`, `.NaN`).
fn parse_number(s: &str) -> Option<f64> {
    let s = s.trim();
    match s {
        ".Inf" | ".inf" | "+.Inf" => return Some(f64::INFINITY),
        "-.Inf" | "-.inf" => return Some(f64::NEG_INFINITY),
        ".NaN" | ".nan" => return Some(f64::NAN),
        _ => {}
    }
    s.parse::<f64>().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn check_matrix(text: &str, key: &str, rows: usize, cols: usize, first: f64, last: f64) {
        let doc = Document::parse(text).unwrap();
        let m = doc.get(key).unwrap().as_matrix(key).unwrap();
        assert_eq!((m.nrows(), m.ncols()), (rows, cols));
        assert_eq!(m[(0, 0)], first);
        assert_eq!(m[(rows - 1, cols - 1)], last);
    }

    #[test]
    fn reads_opencv4_matrix_wrapped_over_lines() {
        let text = "%YAML:1.0\n---\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 5.18e+02, 0., 3.1e+02, 0.,\n       5.18e+02, 2.4e+02, 0., 0., 1. ]\nimage_width: 640\n";
        check_matrix(text, "M1", 3, 3, 518.0, 1.0);
        let doc = Document::parse(text).unwrap();
        assert_eq!(doc.get("image_width").unwrap().as_f64("image_width").unwrap(), 640.0);
    }

    #[test]
    fn reads_opencv5_header_strings_and_nd_matrix() {
        let text = "%YAML 1.2\n---\nopencv_version: \"5.0.0\"\nD: !!opencv-nd-matrix\n   sizes: [ 5 ]\n   dt: d\n   data: [ -0.1, 0.2, 0., 0., 0.3 ]\nE: !!opencv-nd-matrix\n  sizes: [ 2, 2 ]\n  dt: f\n  data: [ 1, 2, 3, 4 ]\n";
        check_matrix(text, "D", 5, 1, -0.1, 0.3);
        check_matrix(text, "E", 2, 2, 1.0, 4.0);
    }

    #[test]
    fn reads_crlf_and_comments() {
        let text = "%YAML:1.0\r\n---\r\n# calibration\r\nT: !!opencv-matrix # translation\r\n  rows: 3\r\n  cols: 1\r\n  dt: d\r\n  data: [ -60., 0., 0. ]\r\n";
        check_matrix(text, "T", 3, 1, -60.0, 0.0);
    }

    #[test]
    fn names_key_and_line_on_bad_data() {
        let text = "%YAML:1.0\n---\nR: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 0. ]\n";
        let doc = Document::parse(text).unwrap();
        let err = doc.get("R").unwrap().as_matrix("R").unwrap_err().to_string();
        assert!(err.contains("`R`") && err.contains("line 3") && err.contains("3 × 3 = 9"), "{err}");
    }

    #[test]
    fn rejects_unterminated_sequence() {
        let text = "%YAML:1.0\nR: !!opencv-matrix\n   rows: 1\n   cols: 2\n   dt: d\n   data: [ 1., 0.,\n";
        let err = Document::parse(text).unwrap_err().to_string();
        assert!(err.contains("line 6") && err.contains("unterminated"), "{err}");
    }
}
