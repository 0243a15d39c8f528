//! Replays every input under `fuzz/corpus/<target>/` and `fuzz/regressions/<target>/`
//! through the fuzz targets' bodies, so a crash found once stays fixed without cargo-fuzz.
//! The format targets' seeds are the conformance vectors in `spec/vectors/` themselves.

use std::path::{Path, PathBuf};

fn replay(target: &str, body: fn(&[u8])) -> usize {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut dirs: Vec<PathBuf> = ["corpus", "regressions"]
        .iter()
        .map(|d| root.join("fuzz").join(d).join(target))
        .collect();
    if FORMAT_TARGETS.contains(&target) {
        dirs.extend(VECTOR_DIRS.iter().map(|d| root.join(d)));
    }
    let mut n = 0;
    for dir in dirs {
        let Ok(entries) = std::fs::read_dir(dir) else {
            continue;
        };
        for entry in entries {
            let path = entry.unwrap().path();
            let hidden = path
                .file_name()
                .is_some_and(|f| f.to_string_lossy().starts_with('.'));
            if hidden || path.extension().is_some_and(|e| e == "json") {
                continue;
            }
            let data = std::fs::read(&path).unwrap();
            let outcome = std::panic::catch_unwind(|| body(&data));
            assert!(outcome.is_ok(), "{} panics in {target}", path.display());
            n += 1;
        }
    }
    n
}

const FORMAT_TARGETS: [&str; 3] = ["open", "decode", "slice"];
const VECTOR_DIRS: [&str; 2] = ["spec/vectors/valid", "spec/vectors/invalid"];

#[test]
fn format_targets_survive_their_corpus() {
    use sfpmap::fuzzing::*;
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let vectors = VECTOR_DIRS
        .iter()
        .flat_map(|d| std::fs::read_dir(root.join(d)).unwrap())
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .path()
                .extension()
                .is_some_and(|x| x == "sfpm")
        })
        .count();
    assert!(vectors >= 17, "{vectors} vectors");
    for (target, body) in [
        ("open", open_and_read as fn(&[u8])),
        ("decode", decode_sections),
        ("slice", slice_in_memory),
    ] {
        let n = replay(target, body);
        assert!(n >= vectors, "{target}: {n} inputs for {vectors} vectors");
    }
}

#[cfg(feature = "colmap-model")]
#[test]
fn colmap_targets_survive_their_corpus() {
    for (target, body) in [
        ("colmap_bin", sfpmap::fuzzing::read_colmap_bin as fn(&[u8])),
        ("colmap_txt", sfpmap::fuzzing::read_colmap_txt),
    ] {
        let n = replay(target, body);
        assert!(n >= 3, "{target}: only {n} inputs");
    }
}
