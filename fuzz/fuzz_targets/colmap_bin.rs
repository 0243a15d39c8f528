#![no_main]
//! Body in `sfpmap::fuzzing::read_colmap_bin`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::fuzzing::read_colmap_bin(data));
