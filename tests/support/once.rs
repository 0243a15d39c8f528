//! Fixtures built once and shared by every test process. The test runner (cargo-nextest)
//! starts a process per test, so a `OnceLock` builds once per test, and tests that wrote
//! one fixed folder at the same time raced. Here one process builds while the others wait
//! on a file lock, and the fixture is rebuilt when the `sfpmap` binary that made it changes.
#![allow(dead_code)]

use std::fs::File;
use std::path::{Path, PathBuf};

/// `dir`, built by `build` unless a complete build by this `sfpmap` binary is there already.
pub fn built_once(dir: &Path, build: impl FnOnce(&Path)) -> PathBuf {
    let parent = dir.parent().expect("a fixture folder has a parent");
    std::fs::create_dir_all(parent).unwrap();
    let lock_path = dir.with_extension("lock");
    let lock = File::create(&lock_path).unwrap();
    rustix::fs::flock(&lock, rustix::fs::FlockOperation::LockExclusive)
        .unwrap_or_else(|e| panic!("lock {}: {e}", lock_path.display()));
    let stamp = binary_stamp();
    let marker = dir.join(".built-by");
    if std::fs::read_to_string(&marker).ok().as_deref() != Some(stamp.as_str()) {
        if dir.exists() {
            std::fs::remove_dir_all(dir).unwrap();
        }
        std::fs::create_dir_all(dir).unwrap();
        build(dir);
        std::fs::write(&marker, &stamp).unwrap();
    }
    // The lock is released when `lock` is dropped (closed).
    dir.to_path_buf()
}

/// What identifies the binary under test: its size and modification time.
fn binary_stamp() -> String {
    let meta = std::fs::metadata(env!("CARGO_BIN_EXE_sfpmap")).unwrap();
    format!("{} {:?}", meta.len(), meta.modified().unwrap())
}
