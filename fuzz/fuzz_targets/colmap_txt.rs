#![no_main]
//! Body in `sfpmap::colmap::fuzz_read_txt`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::colmap::fuzz_read_txt(data));
