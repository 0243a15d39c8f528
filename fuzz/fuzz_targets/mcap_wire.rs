#![no_main]
//! The MCAP message decoders (CDR, protobuf, base64) on any bytes. Their file uses only `std`,
//! so it is compiled here as it is, without the `mcap` feature's ONNX stack; the body is
//! `fuzz_wire` there, which `cargo test` also runs on the corpus.

#[allow(dead_code)]
#[path = "../../src/io/mcap_io/wire.rs"]
mod wire;

libfuzzer_sys::fuzz_target!(|data: &[u8]| wire::fuzz_wire(data));
