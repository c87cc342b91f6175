//! The fuzz entry points (`spinscan::fuzz`) on stable, in every test run: each reader of
//! outside input gets its seed files and a few thousand deterministic mutations of them
//! (byte flips, insertions, deletions, splices, and the numbers and tokens that broke readers
//! before). The coverage-guided runs with millions of inputs are `cargo fuzz` in `fuzz/`
//! (`docs/fuzzing.md`); this keeps every target running and its corpus' findings fixed.

use std::path::PathBuf;

use spinscan::calib::StereoCalib;

/// Mutations per seed (ten thousand or so per target: a second in a debug build).
const PER_SEED: usize = 3000;

fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(path)
}

/// The seeds of each target: files the project ships or writes, and hand-made edge cases.
fn seeds(target: &str) -> Vec<Vec<u8>> {
    let calib = spinscan::hw::sim::ideal_calib(640, 480, 70.0, 60.0).to_yaml().into_bytes();
    match target {
        "request" => [
            r#"{"jsonrpc":"2.0","id":1,"method":"status"}"#,
            r#"{"jsonrpc":"2.0","id":2,"method":"scan.start","params":{"name":"bunny-1","mode":"step","step_deg":2.5,"total_deg":360,"max_views":100}}"#,
            r#"{"jsonrpc":"2.0","id":"x","method":"scan.start","params":{"name":"c","mode":"continuous","speed_deg_s":6}}"#,
            r#"{"jsonrpc":"2.0","id":3,"method":"scan.get","params":{"name":"a"}}"#,
            r#"{"jsonrpc":"2.0","method":"events.subscribe"}"#,
            r#"[{"jsonrpc":"2.0","id":1,"method":"status"}]"#,
        ]
        .map(|s| s.as_bytes().to_vec())
        .to_vec(),
        "config" => vec![std::fs::read(repo("config/spinscand.toml")).unwrap(), std::fs::read(repo("config/sim.toml")).unwrap(), b"[scan]\nstep_deg = 1e-300\n".to_vec()],
        "calibration" => vec![calib, b"%YAML:1.0\n---\nM1: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 1., 0., 0., 0., 1., 0., 0., 0., 1. ]\n".to_vec()],
        "frames" => vec![
            concat!(
                r#"{"seq": 0, "left": "left/000000.png", "right": "right/000000.png", "t_left_ns": 1000000000, "t_right_ns": 1000350000, "table_deg": 0.0}"#,
                "\n",
                r#"{"seq": 1, "left": "left/000001.png", "right": "right/000001.png", "t_left_ns": 1066000000, "t_right_ns": 1066300000, "table_deg": 2.0}"#,
                "\n",
                r#"{"seq": 2, "left": "left/000002.png""#
            )
            .as_bytes()
            .to_vec(),
        ],
        "ply" => {
            let ascii = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 255\n3 0 1 2\n".to_vec();
            let mut binary = b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nend_header\n".to_vec();
            for v in [0.0f32, 1.0, 2.0, 0.0, 0.0, 1.0, 3.0, 4.0, 5.0, 1.0, 0.0, 0.0] {
                binary.extend_from_slice(&v.to_le_bytes());
            }
            vec![ascii, binary]
        }
        other => panic!("no seeds for {other}"),
    }
}

/// xorshift64*: the same mutations in every run.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// Tokens that broke readers before, or that sit at the edge of a type.
const TOKENS: &[&str] = &[
    "0", "-1", "1e308", "-1e308", "1e-320", "NaN", "inf", "-inf", "18446744073709551615", "9999999999999999999999", "4294967296", "\"\"", "null", "[]", "{}", "\n", "\r\n", "\"name\":\"a\",\"name\":\"b\"",
    "element vertex 4294967295\n", "element face 99999999999\n", "element vertex 1\nproperty float x\n", "property list uchar int vertex_indices\n", "rows: 100000\n", "!!opencv-matrix", "%YAML:1.0", "\u{feff}", "é", "\\u0000",
];

fn mutate(rng: &mut Rng, seed: &[u8], other: &[u8]) -> Vec<u8> {
    let mut v = seed.to_vec();
    for _ in 0..1 + rng.below(4) {
        let at = rng.below(v.len() + 1);
        match rng.below(6) {
            0 if !v.is_empty() => {
                let i = at.min(v.len() - 1);
                v[i] ^= 1 << rng.below(8);
            }
            1 => {
                let b = (rng.next() & 0xff) as u8;
                v.insert(at, b);
            }
            2 if !v.is_empty() => {
                let end = (at + 1 + rng.below(16)).min(v.len());
                v.drain(at.min(end)..end);
            }
            3 => {
                let t = TOKENS[rng.below(TOKENS.len())];
                v.splice(at..at, t.bytes());
            }
            4 if !other.is_empty() => {
                // Splice a piece of another seed in.
                let from = rng.below(other.len());
                let len = rng.below(64).min(other.len() - from);
                v.splice(at..at, other[from..from + len].iter().copied());
            }
            _ => {
                // Replace a run of digits with an edge number.
                if let Some(start) = (at..v.len()).find(|&i| v[i].is_ascii_digit()) {
                    let end = (start..v.len()).find(|&i| !v[i].is_ascii_digit() && v[i] != b'.').unwrap_or(v.len());
                    let t = TOKENS[rng.below(10)];
                    v.splice(start..end, t.bytes());
                }
            }
        }
    }
    v
}

fn run(target: &str) {
    let (_, f) = spinscan::fuzz::TARGETS.iter().find(|(name, _)| *name == target).expect("a target of that name");
    let seeds = seeds(target);
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15 ^ target.len() as u64);
    let mut inputs = 0;
    for (i, seed) in seeds.iter().enumerate() {
        f(seed);
        let other = &seeds[(i + 1) % seeds.len()];
        for _ in 0..PER_SEED {
            let input = mutate(&mut rng, seed, other);
            let outcome = std::panic::catch_unwind(|| f(&input));
            assert!(outcome.is_ok(), "{target}: input {inputs} broke a property:\n{}", String::from_utf8_lossy(&input));
            inputs += 1;
        }
    }
    assert!(inputs >= PER_SEED);
}

#[test]
fn control_requests_survive_mutation() {
    run("request");
}

#[test]
fn config_files_survive_mutation() {
    run("config");
}

#[test]
fn calibration_files_survive_mutation() {
    run("calibration");
}

#[test]
fn frames_jsonl_survives_mutation() {
    run("frames");
}

#[test]
fn ply_files_survive_mutation() {
    run("ply");
}

/// The seeds themselves are what they claim: accepted by their readers.
#[test]
fn the_seeds_are_valid_inputs() {
    let calib = String::from_utf8(seeds("calibration")[0].clone()).unwrap();
    StereoCalib::parse(&calib, std::path::Path::new("calib.yaml")).unwrap();
    spinscan::io::ply::read_ply_from(&seeds("ply")[0][..], std::path::Path::new("a.ply")).unwrap();
    spinscan::io::ply::read_ply_from(&seeds("ply")[1][..], std::path::Path::new("b.ply")).unwrap();
    let frames = String::from_utf8(seeds("frames")[0].clone()).unwrap();
    let (f, torn) = spinscan::recording::parse_frames(std::path::Path::new("frames.jsonl"), &frames).unwrap();
    assert_eq!((f.len(), torn), (2, Some(3)));
}
