//! The Python that tests run reference scripts with: `SFPMAP_PYTHON` (the venv that
//! `bash .ci/test` makes from `python/requirements-ci.txt`), else `python3`. Tests install
//! nothing: a Python that lacks a module fails the test, saying how to get it.
#![allow(dead_code)]

use std::path::PathBuf;
use std::process::Command;

/// The interpreter, after checking that it imports `modules` (e.g. `"numpy, pycolmap"`).
pub fn python_with(modules: &str) -> PathBuf {
    let python =
        std::env::var_os("SFPMAP_PYTHON").map_or_else(|| PathBuf::from("python3"), PathBuf::from);
    let out = Command::new(&python)
        .args(["-c", &format!("import {modules}")])
        .output()
        .unwrap_or_else(|e| panic!("{} does not run: {e}", python.display()));
    assert!(
        out.status.success(),
        "{} cannot import {modules}: run the tests with `bash .ci/test` (it makes a venv from \
         python/requirements-ci.txt and sets SFPMAP_PYTHON), or point SFPMAP_PYTHON at a \
         Python that has them\n{}",
        python.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    python
}
