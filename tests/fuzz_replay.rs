//! Replays every input under `fuzz/corpus/<target>/` and `fuzz/regressions/<target>/`
//! through the fuzz targets' bodies, so a crash found once stays fixed without cargo-fuzz.

use std::path::Path;

fn replay(target: &str, body: fn(&[u8])) -> usize {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    let mut n = 0;
    for dir in ["corpus", "regressions"] {
        let Ok(entries) = std::fs::read_dir(root.join(dir).join(target)) else {
            continue;
        };
        for entry in entries {
            let path = entry.unwrap().path();
            if path
                .file_name()
                .is_some_and(|f| f.to_string_lossy().starts_with('.'))
            {
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

#[test]
fn format_targets_survive_their_corpus() {
    use sfpmap::format::fuzzing::*;
    for (target, body) in [
        ("open", open_and_read as fn(&[u8])),
        ("decode", decode_sections),
        ("slice", slice_in_memory),
    ] {
        let n = replay(target, body);
        assert!(
            n >= 13,
            "{target}: only {n} inputs; the seeds come from spec/vectors"
        );
    }
}

#[cfg(feature = "colmap-model")]
#[test]
fn colmap_targets_survive_their_corpus() {
    for (target, body) in [
        ("colmap_bin", sfpmap::colmap::fuzz_read_bin as fn(&[u8])),
        ("colmap_txt", sfpmap::colmap::fuzz_read_txt),
    ] {
        let n = replay(target, body);
        assert!(n >= 3, "{target}: only {n} inputs");
    }
}
