//! `cargo +nightly fuzz run request`: see `spinscan::fuzz::request` for the properties checked.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| spinscan::fuzz::request(data));
