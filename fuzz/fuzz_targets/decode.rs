#![no_main]
//! Body in `sfpmap::fuzzing::decode_sections`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::fuzzing::decode_sections(data));
