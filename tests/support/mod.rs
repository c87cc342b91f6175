//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use spinscan::hw::sim::{RenderOptions, SimObject};
use spinscan::pipeline::replay::{self, ReplayOptions};
use spinscan::recording::Recording;
use spinscan::stereo::MatchParams;

pub mod daemon;

/// A data set under `../shared/data` (beside the repository; CI has it).
pub fn shared_data(name: &str) -> PathBuf {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data").join(name);
    assert!(p.is_dir(), "test data {} is missing: these tests need ../shared beside the repository", p.display());
    p
}

/// A copy of recording `src` (every file, ground truth included) whose right camera has
/// `gain` × the left's: its right images scaled and clipped at 255.
pub fn copy_with_right_gain(src: &Path, dst: &Path, gain: f64) {
    fn copy(src: &Path, dst: &Path) {
        std::fs::create_dir_all(dst).unwrap();
        for e in std::fs::read_dir(src).unwrap() {
            let p = e.unwrap().path();
            let to = dst.join(p.file_name().unwrap());
            if p.is_dir() { copy(&p, &to) } else { std::fs::copy(&p, &to).map(drop).unwrap() }
        }
    }
    copy(src, dst);
    for e in std::fs::read_dir(dst.join("right")).unwrap() {
        let p = e.unwrap().path();
        let img = spinscan::io::load_image(&p).unwrap();
        let rgb: Vec<u8> = img.rgb.iter().map(|&v| (v as f64 * gain).round().min(255.0) as u8).collect();
        spinscan::io::write_rgb_png(&p, img.width, img.height, &rgb).unwrap();
    }
}

/// A fresh temporary folder for one test, removed when the test ends — kept (and named on
/// stderr) when it fails, for a look at what it wrote.
pub fn temp_dir(tag: &str) -> TempDir {
    let p = std::env::temp_dir().join(format!("spinscan-test-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&p);
    std::fs::create_dir_all(&p).unwrap();
    TempDir(p)
}

/// See [`temp_dir`]; derefs to its path.
pub struct TempDir(PathBuf);

impl std::ops::Deref for TempDir {
    type Target = PathBuf;
    fn deref(&self) -> &PathBuf {
        &self.0
    }
}

impl AsRef<std::path::Path> for TempDir {
    fn as_ref(&self) -> &std::path::Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("kept {} (the test failed)", self.0.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A small ideal recording of the simulated lab's egg (320×240, f = 350 px: disparities up to
/// ~64).
pub fn small_recording(dir: &Path, frames: usize, drop_probability: f64) -> Recording {
    let opts = RenderOptions {
        object: SimObject::Builtin { name: "egg".into(), triangles: 20_000 },
        frames,
        ideal: true,
        image_size: (320, 240),
        drop_probability,
        ..RenderOptions::default()
    };
    spinscan::hw::sim::render_recording(&opts, dir, &mut |_, _| {}).unwrap()
}

/// Replay options of the recording tests: segmented, 80 disparities.
pub fn replay_opts() -> ReplayOptions {
    let mut opts = ReplayOptions { segment: true, ..Default::default() };
    opts.pipeline.matching = MatchParams { num_disparities: 80, ..Default::default() };
    opts
}

/// Replays recording `dir` into `out` with [`replay_opts`].
pub fn replay(dir: &Path, out: &Path) -> Result<replay::ReplaySummary, String> {
    let rec = Recording::open(dir).map_err(|e| e.to_string())?;
    replay::run_recording(rec, out, &replay_opts(), &mut |_, _, _| {}).map_err(|e| e.to_string())
}

/// A JSON file, parsed.
pub fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}
