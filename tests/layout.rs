//! The layout invariants of ARCHITECTURE.md that a scan of `src/` can check: no import
//! circle between files, no oversized file, no stringly `Result`, hw-sim adapted in one room,
//! IO kept out of the pure modules.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn src() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// Every `.rs` file under `src/`, as paths relative to `src/` with `/` separators.
fn rust_files() -> Vec<String> {
    fn walk(dir: &Path, base: &Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, base, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p.strip_prefix(base).unwrap().to_string_lossy().replace('\\', "/"));
            }
        }
    }
    let mut out = Vec::new();
    walk(&src(), &src(), &mut out);
    out.sort();
    out
}

fn read(rel: &str) -> String {
    std::fs::read_to_string(src().join(rel)).unwrap()
}

/// The library's files: not the binaries (`main.rs`, `bin/`, `cli/`), which are other crates.
fn library_files() -> Vec<String> {
    rust_files().into_iter().filter(|f| f != "main.rs" && !f.starts_with("bin/") && !f.starts_with("cli/")).collect()
}

/// The module path of a library file: `stereo/matcher.rs` → `[stereo, matcher]`.
fn module_of(rel: &str) -> Vec<String> {
    let no_ext = rel.trim_end_matches(".rs");
    let mut parts: Vec<String> = no_ext.split('/').map(str::to_string).collect();
    if parts.last().is_some_and(|p| p == "mod" || p == "lib") {
        parts.pop();
    }
    parts
}

/// The file that holds module `path`, or its deepest ancestor that is a file.
fn file_of(path: &[String], files: &BTreeMap<Vec<String>, String>) -> Option<String> {
    (0..=path.len()).rev().find_map(|n| files.get(&path[..n]).cloned())
}

/// Code without comments and string literals (so doc text naming a path is not an import).
fn code_only(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let mut in_str = false;
        let mut prev = ' ';
        let mut chars = line.chars().peekable();
        while let Some(c) = chars.next() {
            if !in_str && c == '/' && chars.peek() == Some(&'/') {
                break;
            }
            if c == '"' && prev != '\\' && prev != '\'' {
                in_str = !in_str;
            } else if !in_str {
                out.push(c);
            }
            prev = c;
        }
        out.push('\n');
    }
    out
}

/// The paths a file names through `crate::` and `super::`, expanded over `{…}` groups, each
/// as an absolute module path (the items at the end included; `file_of` trims them).
fn referenced_paths(rel: &str, text: &str) -> Vec<Vec<String>> {
    let module = module_of(rel);
    let code = code_only(text);
    let bytes: Vec<char> = code.chars().collect();
    let mut out = Vec::new();
    // Inline `mod x {` blocks (tests) shift `super::` by one; they sit at the end of files.
    let mut inline_depth_at = Vec::new();
    {
        let mut depth = 0usize;
        for line in code.lines() {
            let t = line.trim_start();
            if (t.starts_with("mod ") || t.starts_with("pub mod ")) && t.trim_end().ends_with('{') {
                depth += 1;
            }
            inline_depth_at.push(depth);
        }
    }
    let line_of = |i: usize| bytes[..i].iter().filter(|&&c| c == '\n').count();
    let is_ident = |c: char| c.is_alphanumeric() || c == '_';
    let mut i = 0;
    while i < bytes.len() {
        let starts = |s: &str| bytes[i..].iter().take(s.len()).copied().eq(s.chars());
        let boundary = i == 0 || !is_ident(bytes[i - 1]) && bytes[i - 1] != ':';
        if boundary && (starts("crate::") || starts("super::")) {
            let depth = inline_depth_at[line_of(i).min(inline_depth_at.len() - 1)];
            let mut base: Vec<String> = if starts("crate::") {
                i += "crate::".len();
                Vec::new()
            } else {
                let mut m = module.clone();
                let mut ups = 0usize;
                while bytes[i..].iter().take(7).copied().eq("super::".chars()) {
                    ups += 1;
                    i += 7;
                }
                // Inside an inline module the first `super` only leaves that module.
                let ups = ups.saturating_sub(depth.min(ups));
                for _ in 0..ups {
                    m.pop();
                }
                m
            };
            let mut j = i;
            parse_tree(&bytes, &mut j, &mut base, &mut out);
            i = j.max(i + 1);
        } else {
            i += 1;
        }
    }
    out
}

/// Parses `a::b::{c, d::e}` from `bytes[*i..]`, pushing each full path.
fn parse_tree(bytes: &[char], i: &mut usize, base: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
    let is_ident = |c: char| c.is_alphanumeric() || c == '_';
    let pushed = base.len();
    loop {
        while *i < bytes.len() && bytes[*i].is_whitespace() {
            *i += 1;
        }
        if *i < bytes.len() && bytes[*i] == '{' {
            *i += 1;
            loop {
                let mut b = base.clone();
                parse_tree(bytes, i, &mut b, out);
                while *i < bytes.len() && bytes[*i].is_whitespace() {
                    *i += 1;
                }
                if *i < bytes.len() && bytes[*i] == ',' {
                    *i += 1;
                    continue;
                }
                if *i < bytes.len() && bytes[*i] == '}' {
                    *i += 1;
                }
                break;
            }
            base.truncate(pushed);
            return;
        }
        let start = *i;
        while *i < bytes.len() && is_ident(bytes[*i]) {
            *i += 1;
        }
        if *i == start {
            break;
        }
        let ident: String = bytes[start..*i].iter().collect();
        if ident != "self" {
            base.push(ident);
        }
        if bytes[*i..].iter().take(2).copied().eq("::".chars()) {
            *i += 2;
            continue;
        }
        break;
    }
    out.push(base.clone());
    base.truncate(pushed);
}

/// The CLI binary's files (`main.rs` is its root, `cli/` its modules).
fn cli_files() -> Vec<String> {
    rust_files().into_iter().filter(|f| f == "main.rs" || f.starts_with("cli/")).collect()
}

#[test]
fn no_import_circle_between_files() {
    let mut cycles = cycles_in(library_files());
    cycles.extend(cycles_in(cli_files()));
    assert!(cycles.is_empty(), "import circles between files of src/:\n{}", cycles.join("\n"));
}

/// The import circles among the files of one crate.
fn cycles_in(crate_files: Vec<String>) -> Vec<String> {
    cycles_among(crate_files, &read)
}

/// The import circles among `crate_files`, whose text `text` gives.
fn cycles_among(crate_files: Vec<String>, text: &dyn Fn(&str) -> String) -> Vec<String> {
    let files: BTreeMap<Vec<String>, String> = crate_files.into_iter().map(|f| (if f == "main.rs" { Vec::new() } else { module_of(&f) }, f)).collect();
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in files.values() {
        let targets = edges.entry(f.clone()).or_default();
        for path in referenced_paths(f, &text(f)) {
            if let Some(t) = file_of(&path, &files) {
                // A file naming its own parent's re-exports (`super::Item` in a child of
                // `mod.rs`, `crate::x::Item` re-exported by `x/mod.rs`) is not a cycle by
                // itself; only real file-to-file edges count, so the root is skipped.
                if &t != f && t != "lib.rs" && t != "main.rs" {
                    targets.insert(t);
                }
            }
        }
    }
    // Tarjan-free: a DFS from every node looking for a path back to it.
    let mut cycles = Vec::new();
    for start in edges.keys() {
        let mut stack = vec![(start.clone(), vec![start.clone()])];
        let mut seen = BTreeSet::new();
        while let Some((node, trail)) = stack.pop() {
            for next in edges.get(&node).into_iter().flatten() {
                if next == start {
                    let mut t = trail.clone();
                    t.push(start.clone());
                    cycles.push(t.join(" → "));
                } else if seen.insert(next.clone()) {
                    let mut t = trail.clone();
                    t.push(next.clone());
                    stack.push((next.clone(), t));
                }
            }
        }
    }
    cycles.sort();
    cycles.dedup();
    cycles
}

/// Kernels may be longer when their module doc says why (`// layout: long kernel file`).
const MAX_LINES: usize = 700;

#[test]
fn no_oversized_file() {
    let big: Vec<String> = rust_files()
        .into_iter()
        .filter_map(|f| {
            let text = read(&f);
            let n = text.lines().count();
            (n > MAX_LINES && !text.contains("layout: long kernel file")).then(|| format!("{f}: {n} lines"))
        })
        .collect();
    assert!(big.is_empty(), "files over {MAX_LINES} lines in src/:\n{}", big.join("\n"));
}

#[test]
fn no_stringly_result() {
    let mut hits = Vec::new();
    for f in rust_files() {
        let code = code_only(&read(&f));
        for (n, line) in code.lines().enumerate() {
            let squeezed: String = line.chars().filter(|c| !c.is_whitespace()).collect();
            if squeezed.contains(",String>") && squeezed.contains("Result<") {
                hits.push(format!("{f}:{}: {}", n + 1, line.trim()));
            }
        }
    }
    assert!(hits.is_empty(), "Result<_, String> in src/ (use a thiserror enum):\n{}", hits.join("\n"));
}

#[test]
fn hw_sim_is_named_only_in_hw() {
    let hits: Vec<String> = rust_files()
        .into_iter()
        .filter(|f| !f.starts_with("hw/"))
        .filter(|f| code_only(&read(f)).contains("hw_sim::"))
        .collect();
    assert!(hits.is_empty(), "hw_sim:: named outside src/hw/: {hits:?}");
}

#[test]
fn pure_modules_do_no_io() {
    let pure = ["stereo/", "register/", "assist/", "fuse/", "segment/", "calib/distortion.rs", "calib/filestorage.rs", "calib/board.rs", "calib/grid.rs", "calib/subpix.rs", "calib/lm.rs", "calib/solve.rs", "calib/turntable.rs", "calib/job.rs"];
    let io_calls = ["std::fs", "fs::", "File::", "read_to_string", "OpenOptions"];
    let mut hits = Vec::new();
    for f in library_files().into_iter().filter(|f| pure.iter().any(|p| f.starts_with(p))) {
        let code = code_only(&read(&f));
        // Unit tests may make temporary files.
        let code = code.split("#[cfg(test)]").next().unwrap();
        for call in io_calls {
            if code.contains(call) {
                hits.push(format!("{f}: {call}"));
            }
        }
    }
    assert!(hits.is_empty(), "IO in a pure module:\n{}", hits.join("\n"));
}

#[test]
fn the_cycle_finder_finds_a_circle() {
    // Two files naming each other, as `stereo/matcher.rs` and `stereo/speckle.rs` once did.
    let text = |f: &str| match f {
        "stereo/a.rs" => "use super::b::B;\npub struct A;\n".to_string(),
        _ => "pub struct B(crate::stereo::a::A);\n".to_string(),
    };
    let cycles = cycles_among(vec!["stereo/a.rs".into(), "stereo/b.rs".into(), "io/mod.rs".into()], &text);
    assert_eq!(cycles, vec!["stereo/a.rs → stereo/b.rs → stereo/a.rs", "stereo/b.rs → stereo/a.rs → stereo/b.rs"]);
}

#[test]
fn the_cycle_finder_finds_cycles() {
    // The scanner itself: a child naming its sibling through `super::` and back.
    let a = referenced_paths("stereo/a.rs", "use super::b::Thing;\nfn f() { crate::io::{x, y::z}; }\n#[cfg(test)]\nmod tests {\n use super::*;\n}\n");
    let names: Vec<String> = a.iter().map(|p| p.join("::")).collect();
    assert!(names.contains(&"stereo::b::Thing".to_string()), "{names:?}");
    assert!(names.contains(&"io::x".to_string()) && names.contains(&"io::y::z".to_string()), "{names:?}");
    assert!(names.contains(&"stereo::a::*".to_string()) || names.iter().any(|n| n == "stereo::a"), "{names:?}");
}
