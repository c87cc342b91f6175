//! `cargo +nightly fuzz run ply`: see `spinscan::fuzz::ply` for the properties checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| spinscan::fuzz::ply(data));
