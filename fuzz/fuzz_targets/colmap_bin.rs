#![no_main]
//! Body in `sfpmap::build::fuzz_read_bin`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::build::fuzz_read_bin(data));
