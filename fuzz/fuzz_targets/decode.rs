#![no_main]
//! Body in `sfpmap::format::fuzzing::decode_sections`, so `cargo test` replays the corpus too.
libfuzzer_sys::fuzz_target!(|data: &[u8]| sfpmap::format::fuzzing::decode_sections(data));
