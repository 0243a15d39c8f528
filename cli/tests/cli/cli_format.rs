//! The real `sfpmap` binary on temp copies of the conformance vectors.

use crate::run::sfpmap;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Output;

fn vector(kind: &str, name: &str) -> PathBuf {
    crate::shared_data::repo_root().join(format!("spec/vectors/{kind}/{name}.sfpm"))
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn info_json(path: &Path) -> Value {
    let o = sfpmap(&["info", path.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    serde_json::from_slice(&o.stdout).unwrap()
}

/// The kinds of the sections `info --json` lists, in its order.
fn section_kinds(info: &Value) -> Vec<&str> {
    info["sections"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["kind"].as_str().unwrap())
        .collect()
}

#[test]
fn info_json_has_the_documented_keys() {
    let info = info_json(&vector("valid", "levels"));
    assert_eq!(info["version"], "1.0");
    assert_eq!(
        info["file_bytes"],
        std::fs::metadata(vector("valid", "levels")).unwrap().len()
    );
    assert_eq!(info["points"], 24);
    assert_eq!(info["images"], 3);
    let levels = info["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 3);
    for l in levels {
        for key in ["level", "points", "dim_full", "dim_short", "has_rest"] {
            assert!(l.get(key).is_some(), "{key} missing in {l}");
        }
        assert_eq!(l["has_rest"], true);
    }
    let text = sfpmap(&["info", vector("valid", "levels").to_str().unwrap()]);
    assert!(String::from_utf8_lossy(&text.stdout).contains("level 2: 10 points"));
}

#[test]
fn verify_accepts_valid_and_rejects_invalid_with_one_line() {
    for name in [
        "minimal",
        "levels",
        "zstd",
        "short_only",
        "unknown_optional",
        "mixed_dtypes",
        "geometry_only",
    ] {
        let o = sfpmap(&["verify", vector("valid", name).to_str().unwrap()]);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
    }
    for entry in std::fs::read_dir(vector("invalid", "x").parent().unwrap()).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "sfpm") {
            continue;
        }
        let o = sfpmap(&["verify", path.to_str().unwrap()]);
        assert!(!o.status.success(), "{} verifies", path.display());
        let err = stderr(&o);
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert!(
            err.starts_with("error: ") && err.contains(path.to_str().unwrap()),
            "{err}"
        );
    }
}

#[test]
fn slice_keeps_one_short_level_and_is_smaller() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("l2.sfpm");
    let input = vector("valid", "levels");
    let o = sfpmap(&[
        "slice",
        input.to_str().unwrap(),
        "--level",
        "2",
        "--short",
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("bytes ->"));
    let info = info_json(&out);
    let levels = info["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 1);
    assert_eq!(levels[0]["level"], 2);
    assert_eq!(levels[0]["has_rest"], false);
    assert_eq!(info["points"], levels[0]["points"]);
    assert!(info["file_bytes"].as_u64().unwrap() < std::fs::metadata(&input).unwrap().len());
    assert!(sfpmap(&["verify", out.to_str().unwrap()]).status.success());

    // zstd re-encoding, two levels, JSON report.
    let z = dir.path().join("z.sfpm");
    let o = sfpmap(&[
        "slice",
        input.to_str().unwrap(),
        "--level",
        "0",
        "--level",
        "2",
        "--codec",
        "zstd",
        "-o",
        z.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(report["output_bytes"].as_u64().unwrap() > 0);
    assert_eq!(info_json(&z)["levels"].as_array().unwrap().len(), 2);
}

#[test]
fn slice_refuses_to_lose_data() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.sfpm");
    std::fs::copy(vector("valid", "levels"), &input).unwrap();
    let before = std::fs::read(&input).unwrap();
    let i = input.to_str().unwrap();

    let o = sfpmap(&["slice", i, "--level", "2", "-o", i]);
    assert!(
        !o.status.success() && stderr(&o).contains("input"),
        "{}",
        stderr(&o)
    );
    let same_via_dot = dir.path().join(".").join("in.sfpm");
    let o = sfpmap(&[
        "slice",
        i,
        "--level",
        "2",
        "-o",
        same_via_dot.to_str().unwrap(),
        "--force",
    ]);
    assert!(!o.status.success());

    let out = dir.path().join("out.sfpm");
    std::fs::write(&out, b"precious").unwrap();
    let o = sfpmap(&["slice", i, "--level", "2", "-o", out.to_str().unwrap()]);
    assert!(
        !o.status.success() && stderr(&o).contains("--force"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read(&out).unwrap(), b"precious");
    let o = sfpmap(&[
        "slice",
        i,
        "--level",
        "2",
        "-o",
        out.to_str().unwrap(),
        "--force",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));

    let o = sfpmap(&[
        "slice",
        i,
        "--level",
        "7",
        "-o",
        dir.path().join("x.sfpm").to_str().unwrap(),
    ]);
    assert!(
        !o.status.success() && stderr(&o).contains("no level 7"),
        "{}",
        stderr(&o)
    );
    assert!(!dir.path().join("x.sfpm").exists());
    assert_eq!(std::fs::read(&input).unwrap(), before);

    let o = sfpmap(&[
        "slice",
        i,
        "-o",
        dir.path().join("y.sfpm").to_str().unwrap(),
    ]);
    assert!(!o.status.success(), "--level is required");
}

#[test]
fn a_byte_flipped_copy_fails_verify() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(vector("valid", "zstd")).unwrap();
    for at in [0, 9, 70, bytes.len() / 3, bytes.len() / 2, bytes.len() - 1] {
        let mut b = bytes.clone();
        b[at] ^= 0xA5;
        let p = dir.path().join(format!("f{at}.sfpm"));
        std::fs::write(&p, &b).unwrap();
        let o = sfpmap(&["verify", p.to_str().unwrap()]);
        assert!(!o.status.success(), "flip at {at} passes");
        assert!(!stderr(&o).contains("panicked"));
    }
}

/// One line that names the file once, for an I/O error and for a bad file alike.
#[test]
fn errors_name_the_path_once() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.sfpm");
    std::fs::write(
        &bad,
        b"not a map, not even close to one, long enough to read",
    )
    .unwrap();
    let bad = bad.to_str().unwrap();
    for (args, path) in [
        (vec!["info", "/no/such/map.sfpm"], "/no/such/map.sfpm"),
        (vec!["verify", bad], bad),
        (vec!["info", bad], bad),
    ] {
        let o = sfpmap(&args);
        assert!(!o.status.success());
        let err = stderr(&o);
        assert_eq!(err.trim_end().lines().count(), 1, "{err}");
        assert_eq!(err.matches(path).count(), 1, "{err}");
    }
}

/// (1.1) `slice --pq`: the kept levels' f16 blocks become codes; a PQ map is a 1.1 map whose
/// sections `info` lists; requests that cannot be met fail in one line and write nothing.
#[test]
fn slice_pq_replaces_descriptor_blocks_by_codes() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("pq.sfpm");
    let levels = vector("valid", "levels");
    let o = sfpmap(&[
        "slice",
        levels.to_str().unwrap(),
        "--level",
        "0",
        "--pq",
        "4",
        "-o",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["pq"][0]["dims"], 16);
    assert_eq!(report["pq"][0]["subspaces"], 4);
    assert!(sfpmap(&["verify", out.to_str().unwrap()]).status.success());
    let info = info_json(&out);
    assert_eq!(info["version"], "1.1");
    let kinds = section_kinds(&info);
    assert!(kinds.contains(&"level_pq_codes") && kinds.contains(&"level_pq_codebook"));
    assert!(!kinds.contains(&"level_desc_short"), "{kinds:?}");

    // 3 subspaces do not divide 16 dims; a PQ level is not quantised again.
    let bad = dir.path().join("bad.sfpm");
    for (map, level, m, why) in [
        (levels.clone(), "0", "3", "which 3 subspaces do not divide"),
        (vector("valid", "pq"), "1", "2", "already product-quantised"),
    ] {
        let o = sfpmap(&[
            "slice",
            map.to_str().unwrap(),
            "--level",
            level,
            "--pq",
            m,
            "-o",
            bad.to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(1));
        let err = stderr(&o);
        assert!(
            err.contains(why) && err.contains(map.to_str().unwrap()),
            "{err}"
        );
        assert_eq!(err.lines().count(), 1, "{err}");
        assert!(!bad.exists());
    }
}

/// `slice --short --short-dims N`: the kept level's short block in N dims of its own PCA
/// basis, with the projection queries take (`[N × d_in]`, the level's input unchanged); a VLAD
/// on it is learned again and the report says so; a cut that cannot be made fails in one line
/// naming the map and writes nothing.
#[test]
fn slice_short_dims_cuts_the_short_block_to_a_basis_of_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cut.sfpm");
    let cut = |map: &std::path::Path, level: &str, dims: &str, to: &std::path::Path| {
        sfpmap(&[
            "slice",
            map.to_str().unwrap(),
            "--level",
            level,
            "--short",
            "--short-dims",
            dims,
            "-o",
            to.to_str().unwrap(),
            "--json",
        ])
    };
    // Level 0 of `levels`: 4 short dims behind a 16 x 16 projection.
    let levels = vector("valid", "levels");
    let o = cut(&levels, "0", "2", &out);
    assert!(o.status.success(), "{}", stderr(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    let cut_level = &report["short_dims"][0];
    assert_eq!(
        (&cut_level["dims_before"], &cut_level["dims"]),
        (&4.into(), &2.into()),
        "{report}"
    );
    assert!(sfpmap(&["verify", out.to_str().unwrap()]).status.success());
    let info = info_json(&out);
    let level = &info["levels"][0];
    assert_eq!(
        (&level["dim_short"], &level["dim_full"]),
        (&2.into(), &2.into()),
        "{info}"
    );
    let projection = info["sections"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["kind"] == "level_projection")
        .unwrap();
    assert_eq!(
        (&projection["rows"], &projection["cols"]),
        (&2.into(), &16.into()),
        "{projection}"
    );
    // The VLAD on level 2 of `image_index` is learned again over 1 dim; its index of 2 lists
    // over 3 images cannot be (1-dim VLADs of 2 centroids: fewer distinct rows than lists),
    // and goes with its neighbours (1.4).
    for name in ["image_index", "image_index_neighbours"] {
        let out = dir.path().join(format!("cut-{name}.sfpm"));
        let o = cut(&vector("valid", name), "2", "1", &out);
        assert!(o.status.success(), "{}", stderr(&o));
        let report: Value = serde_json::from_slice(&o.stdout).unwrap();
        let cut_level = &report["short_dims"][0];
        assert_eq!(cut_level["vlad_relearned"], true, "{report}");
        assert_eq!(cut_level["index_dropped"], true, "{report}");
        assert!(sfpmap(&["verify", out.to_str().unwrap()]).status.success());
        let info = info_json(&out);
        assert_eq!(info["retrieval"]["preference"], "vlad", "{info}");
        assert_eq!(info["retrieval"]["vlad"]["dims"], 1, "{info}");
        let kinds = section_kinds(&info);
        assert!(
            !kinds.iter().any(|k| k.starts_with("image_index")),
            "{kinds:?}"
        );
    }
    // No level with more short dims than asked for: refused, nothing written.
    let bad = dir.path().join("bad.sfpm");
    let o = cut(&levels, "0", "4", &bad);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(
        err.contains("no kept level has more than 4 short dimensions")
            && err.contains(levels.to_str().unwrap()),
        "{err}"
    );
    assert_eq!(err.lines().count(), 1, "{err}");
    assert!(!bad.exists());
}

/// (1.1) `slice --budget`: the report says what was chosen, the map fits, and a budget below
/// every cut fails in one line naming the map and the smallest cut, writing nothing.
#[test]
fn slice_budget_fits_or_names_the_smallest_cut() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("budget.sfpm");
    let levels = vector("valid", "levels");
    let run = |budget: &str| {
        sfpmap(&[
            "slice",
            levels.to_str().unwrap(),
            "--budget",
            budget,
            "-o",
            out.to_str().unwrap(),
            "--force",
            "--json",
        ])
    };
    let whole = std::fs::metadata(&levels).unwrap().len();
    let o = run("1MiB");
    assert!(o.status.success(), "{}", stderr(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(report["budget"]["budget_bytes"], 1 << 20);
    assert_eq!(report["budget"]["candidates"].as_array().unwrap().len(), 1);
    assert!(report["output_bytes"].as_u64().unwrap() <= whole + 64);

    let o = run("1B");
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(
        err.contains(levels.to_str().unwrap()) && err.contains("the smallest is"),
        "{err}"
    );
    assert_eq!(err.lines().count(), 1, "{err}");
    std::fs::remove_file(&out).unwrap();
    let smallest: u64 = err
        .split("the smallest is ")
        .nth(1)
        .unwrap()
        .trim_start_matches("at least ")
        .split(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let o = run(&(smallest + 256).to_string());
    assert!(o.status.success(), "{}", stderr(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    let written = std::fs::metadata(&out).unwrap().len();
    assert!(
        written <= smallest + 256 && report["output_bytes"] == written,
        "{report}"
    );
    assert!(sfpmap(&["verify", out.to_str().unwrap()]).status.success());

    for (args, why) in [
        (vec!["--budget", "2XB"], "is not a size"),
        (vec!["--budget", "1MB", "--pq", "4"], "cannot be used with"),
        (vec!["--level", "0", "--short-dims", "8"], "--short"),
        (
            vec!["--level", "0", "--short", "--short-dims", "8", "--pq", "4"],
            "cannot be used with",
        ),
    ] {
        let mut all = vec!["slice", levels.to_str().unwrap(), "-o", "never.sfpm"];
        all.extend(args);
        let o = sfpmap(&all);
        assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
        assert!(stderr(&o).contains(why), "{}", stderr(&o));
    }
}
