//! `cargo +nightly fuzz run calibration`: see `spinscan::fuzz::calibration` for the properties checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| spinscan::fuzz::calibration(data));
