#![no_main]
//! Body in `sfpmap::fuzzing::open_and_read`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::fuzzing::open_and_read(data));
