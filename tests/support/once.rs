//! Fixtures built once and shared by every test process. The test runner (cargo-nextest)
//! starts a process per test, so a `OnceLock` alone builds once per test, and tests that wrote
//! one fixed folder at the same time raced. Here one process builds while the others wait on
//! a file lock, and each fixture's folder is named by what it was made from: its recipe and,
//! where it runs `sfpmap`, that binary's size and time. A changed recipe or binary gets a new
//! folder; a folder is never removed while another process may read it (only an unfinished
//! one, under the lock). Old folders stay until `cargo clean`.
#![allow(dead_code)]

use std::fs::File;
use std::path::{Path, PathBuf};

/// What a fixture's content depends on besides its recipe.
pub enum Depends {
    /// The `sfpmap` binary under test made it (a rebuilt binary makes it again).
    OnBinary,
    /// Only what the recipe names (e.g. a script and its inputs, hashed into the recipe).
    OnRecipe,
}

/// The folder of fixture `name`, built by `build` (into that folder) unless a finished build
/// of the same recipe is there already. `recipe` says everything the content depends on:
/// change it when the building code changes.
pub fn built_once(
    name: &str,
    recipe: &str,
    depends: Depends,
    build: impl FnOnce(&Path),
) -> PathBuf {
    let mut stamp = recipe.to_owned();
    if let Depends::OnBinary = depends {
        let meta = std::fs::metadata(env!("CARGO_BIN_EXE_sfpmap")).unwrap();
        stamp += &format!("\nsfpmap {} {:?}", meta.len(), meta.modified().unwrap());
    }
    let root = fixtures_root();
    std::fs::create_dir_all(&root).unwrap();
    let dir = root.join(format!(
        "{name}-{:016x}",
        xxhash_rust::xxh3::xxh3_64(stamp.as_bytes())
    ));
    let lock_path = root.join(format!("{name}.lock"));
    let lock = File::create(&lock_path).unwrap();
    rustix::fs::flock(&lock, rustix::fs::FlockOperation::LockExclusive)
        .unwrap_or_else(|e| panic!("lock {}: {e}", lock_path.display()));
    let finished = dir.join(".finished");
    if !finished.exists() {
        // A build that panicked or was killed left no marker: nobody reads its folder.
        if dir.exists() {
            std::fs::remove_dir_all(&dir).unwrap();
        }
        std::fs::create_dir_all(&dir).unwrap();
        build(&dir);
        std::fs::write(&finished, &stamp).unwrap();
    }
    // The lock is released when `lock` is dropped (closed).
    dir
}

/// `<target>/<profile>/test-fixtures`: beside the binary under test, so that builds of other
/// profiles keep their own.
fn fixtures_root() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_sfpmap"))
        .parent()
        .expect("the binary sits in <target>/<profile>")
        .join("test-fixtures")
}
