#![no_main]
//! Body in `sfpmap::fuzzing::slice_in_memory`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::fuzzing::slice_in_memory(data));
