//! `cargo +nightly fuzz run frames`: see `spinscan::fuzz::frames` for the properties checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| spinscan::fuzz::frames(data));
