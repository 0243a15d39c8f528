//! Where tests find the repository's files and `../shared/data` (real COLMAP fixtures and
//! scenes, never committed).
//!
//! A test that needs it fails when it is missing: a check that passes without its data
//! checks nothing. `SFPMAP_SKIP_SHARED_DATA=1` skips such tests, visibly, in a checkout that
//! has no shared data.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// The repository's root (the workspace's, where `Cargo.lock` is), whichever member's test
/// this is: the library's tests run in it, the CLI's in `cli/`. `spec/`, `docs/`, `include/`,
/// `examples/`, `models/` and `tests/*.py` are under it.
pub fn repo_root() -> PathBuf {
    let manifest_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    manifest_dir
        .ancestors()
        .find(|dir| dir.join("Cargo.lock").is_file())
        .unwrap_or_else(|| panic!("no Cargo.lock in {} or above", manifest_dir.display()))
        .to_path_buf()
}

/// `../shared/data/<sub>` if it exists; `None` (skip) only under `SFPMAP_SKIP_SHARED_DATA=1`.
pub fn shared_data(sub: &str) -> Option<PathBuf> {
    let path = repo_root().join("../shared/data").join(sub);
    if path.exists() {
        return Some(path);
    }
    if std::env::var_os("SFPMAP_SKIP_SHARED_DATA").is_some_and(|v| v == "1") {
        eprintln!("SKIPPED: {} is missing", path.display());
        return None;
    }
    panic!(
        "{} is missing: this test needs the shared data (SFPMAP_SKIP_SHARED_DATA=1 skips it)",
        path.display()
    );
}
