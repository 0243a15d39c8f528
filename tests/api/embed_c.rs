//! The C ABI from C: takes the cdylib this test build made (feature `capi`), compiles
//! `examples/c/sfpm_info.c` with the system C compiler against the committed `include/sfpmap.h`, runs it on the
//! `levels` spec vector and checks its output against the vector's JSON. That the committed
//! header is what cbindgen makes of `src/ffi/` is checked by `.ci/run` (a pinned cbindgen
//! and a diff that fails the run), not here: the test must not depend on a tool's version.

#![cfg(feature = "capi")]

use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The folder of the `libsfpmap.so` that this test run's own build made: the test binary sits
/// in `<target>/<profile>/deps/`, and building the tests builds the library's cdylib into
/// `<target>/<profile>/` with the same features (the test needs `capi`, so the crate's
/// `#![cfg]` asks for it). No nested `cargo build`: that built the dependency tree again.
fn built_cdylib() -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("the test binary sits in <target>/<profile>/deps")
        .to_path_buf();
    assert!(
        dir.join("libsfpmap.so").exists(),
        "no libsfpmap.so in {}: build the library first, with feature `capi` (`cargo build \
         --release --all-features --lib --bins --tests`, as bash .ci/test does)",
        dir.display()
    );
    dir
}

fn compile_example(lib_dir: &Path, out: &Path) {
    let cc = std::env::var_os("CC").unwrap_or_else(|| "cc".into());
    let output = Command::new(&cc)
        .current_dir(root())
        .args(["-std=c11", "-Wall", "-Wextra", "-Werror", "-Iinclude"])
        .arg("examples/c/sfpm_info.c")
        .arg(format!("-L{}", lib_dir.display()))
        .args(["-lsfpmap", "-lm"])
        .arg(format!("-Wl,-rpath,{}", lib_dir.display()))
        .arg("-o")
        .arg(out)
        .output()
        .unwrap_or_else(|e| panic!("run the C compiler {cc:?}: {e}"));
    assert!(
        output.status.success(),
        "C example does not compile:\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-6 * (1.0 + b.abs())
}

#[test]
fn c_example_reads_the_levels_vector() {
    let lib_dir = built_cdylib();
    let tmp = tempfile::tempdir().unwrap();
    let exe = tmp.path().join("sfpm_info");
    compile_example(&lib_dir, &exe);
    let vector = root().join("spec/vectors/valid/levels.sfpm");
    // The test runner may put another folder on LD_LIBRARY_PATH, which outranks the rpath:
    // point it at this build's library.
    let output = Command::new(&exe)
        .arg(&vector)
        .env("LD_LIBRARY_PATH", &lib_dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "sfpm_info failed:\n{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    // "key rest..." lines; "level N key value" lines keyed by "level N key".
    let mut facts: HashMap<String, Vec<String>> = HashMap::new();
    for line in stdout.lines() {
        let t: Vec<&str> = line.split_whitespace().collect();
        let key_len = match t[0] {
            "level" | "image" if t.len() > 2 => 3,
            _ => 1,
        };
        facts.insert(
            t[..key_len.min(t.len())].join(" "),
            t[key_len.min(t.len())..]
                .iter()
                .map(|s| s.to_string())
                .collect(),
        );
    }
    let fact = |k: &str| {
        facts
            .get(k)
            .unwrap_or_else(|| panic!("no {k:?} in:\n{stdout}"))
    };
    let num = |k: &str, i: usize| fact(k)[i].parse::<f64>().unwrap();

    let json: Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("spec/vectors/valid/levels.json")).unwrap(),
    )
    .unwrap();
    let content = &json["content"];
    let levels = content["levels"].as_array().unwrap();
    assert_eq!(fact("levels")[0], levels.len().to_string());
    for level in levels {
        let id = level["level"].as_u64().unwrap();
        let info = fact(&format!("level {id} dim_full"));
        assert_eq!(info[0], level["dim_full"].to_string());
        assert_eq!(info[2], level["dim_short"].to_string());
        assert_eq!(
            info[4],
            level["points"].as_array().unwrap().len().to_string()
        );
        let first_point = level["points"][0].as_f64().unwrap();
        assert_eq!(num(&format!("level {id} first_point"), 0), first_point);
        let short0 = level["short"][0][0].as_f64().unwrap();
        assert!(close(num(&format!("level {id} short_len"), 2), short0));
        let rest0 = level["rest"][0][0].as_f64().unwrap();
        assert!(close(num(&format!("level {id} rest_len"), 2), rest0));
    }
    let positions = content["positions"].as_array().unwrap();
    assert_eq!(fact("points")[0], positions.len().to_string());
    for (k, want) in positions[3].as_array().unwrap().iter().enumerate() {
        assert!(close(num("position3", k), want.as_f64().unwrap()));
    }
    assert_eq!(fact("cameras")[0], content["cameras"].to_string());
    let map = sfpmap::format::Map::open(&vector).unwrap();
    let camera = &map.metadata().cameras[0];
    let line = fact("camera");
    assert_eq!(line[1], camera.model);
    assert_eq!(line[2], camera.width.to_string());
    assert_eq!(line[3], camera.height.to_string());
    assert_eq!(line[5], camera.params.len().to_string());
    assert_eq!(line[7].parse::<f64>().unwrap(), camera.params[0]);
    let images = content["images"].as_array().unwrap();
    assert_eq!(fact("images")[0], images.len().to_string());
    for (i, image) in images.iter().enumerate() {
        let line = fact(&format!("image {i} {}", image["name"].as_str().unwrap()));
        for k in 0..7 {
            let expected = image["cam_from_world"][k].as_f64().unwrap();
            assert!(close(line[3 + k].parse().unwrap(), expected));
        }
    }
    let vis = &content["visibility"];
    let vis_line = fact("visibility");
    assert_eq!(
        vis_line[1],
        vis["offsets"].as_array().unwrap().len().to_string()
    );
    assert_eq!(
        vis_line[3],
        vis["points"].as_array().unwrap().len().to_string()
    );
    // Bad input: NULL out, unknown level, unknown camera model, double close, use after close.
    assert_eq!(fact("null_out")[0], "-1");
    assert_eq!(fact("no_such_level")[0], "-6");
    assert_eq!(fact("bad_camera")[0], "-3");
    assert_eq!(fact("double_close")[0], "-2");
    assert_eq!(fact("use_after_close")[0], "-2");
    // One feature of dimension 4 against level 0 (projection input 16): reported, not a crash.
    assert_eq!(fact("localize")[0], "-8");
    // A camera width above UINT32_MAX (the field is uint64_t): refused, not truncated.
    assert_eq!(fact("too_wide_camera")[0], "-3");
}
