//! Running the `sfpmap` binary under test (the hostile-input tests run it under limits with
//! `common::run_limited`).
#![allow(dead_code)]

use std::ffi::OsStr;
use std::process::{Command, Output};

/// `sfpmap ARGS`, its output (telemetry off).
pub fn sfpmap<S: AsRef<OsStr>>(args: &[S]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(args)
        .env("ORT_DISABLE_TELEMETRY", "1")
        .output()
        .expect("run sfpmap")
}
