//! `cargo +nightly fuzz run config`: see `spinscan::fuzz::config` for the properties checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| spinscan::fuzz::config(data));
