//! hloc's pipeline rebuilt on a window of South Building (`benches/hloc_south_building.py`,
//! torch-free: hloc's `sift` conf, DoG + RootSIFT, mutual NN-ratio matches, triangulated with
//! pycolmap at the `sparse-map` poses), then `convert --features` and `localize --features`
//! from the CLI: every query localized within a tenth of the map's camera spacing and 2° (the
//! comparison with the hloc-style reference, pycolmap on the same matches, is the bench's),
//! the same from its `--budget` slice and from nginx by range, and features files of another
//! feature refused naming both. Built once for all test processes
//! (`tests/support/once.rs`); it needs the CI venv (numpy, h5py, pycolmap 4.2.1) and fails,
//! never skips.
#![cfg(all(feature = "colmap", feature = "onnx"))]

use crate::once::{built_once, Depends};
use serde_json::Value;
use sfpmap::geometry::Pose;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn sfpmap(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(args)
        .env("ORT_DISABLE_TELEMETRY", "1")
        // Remote reads go to the server each time; nothing lands in the user's cache.
        .env("SFPMAP_CACHE_DIR", "off")
        .output()
        .expect("sfpmap runs")
}

fn ok(args: &[&str]) -> String {
    let out = sfpmap(args);
    assert!(
        out.status.success(),
        "sfpmap {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// The scene's files and the reference's numbers (`build_small_scene`'s result).
struct Scene {
    sfm: PathBuf,
    /// Every image's features (map and queries), named as hloc names them.
    features: PathBuf,
    /// The map images' only.
    features_map: PathBuf,
    queries: PathBuf,
    gt: BTreeMap<String, Pose>,
    spacing: f64,
}

fn scene() -> &'static Scene {
    static SCENE: OnceLock<Scene> = OnceLock::new();
    SCENE.get_or_init(|| {
        let root = crate::shared_data::repo_root();
        let script = root.join("benches/hloc_south_building.py");
        let recipe = format!(
            "build_small_scene(12, sift), script xxh3 {:016x}",
            xxhash_rust::xxh3::xxh3_64(&std::fs::read(&script).unwrap())
        );
        let dir = built_once("hloc-south-building", &recipe, Depends::OnRecipe, |dir| {
            let code = r#"
import json, sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
import hloc_south_building as h
r = h.build_small_scene(Path(sys.argv[2]))
keep = ("features", "features_map", "sfm", "queries", "gt_path", "spacing")
Path(sys.argv[2], "scene.json").write_text(json.dumps({k: r[k] for k in keep}, default=str))
"#;
            let out = Command::new(crate::python::python_with("numpy, h5py, pycolmap"))
                .args(["-c", code])
                .arg(root.join("benches"))
                .arg(dir)
                .output()
                .expect("python runs");
            assert!(
                out.status.success(),
                "build_small_scene failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        });
        let r: Value =
            serde_json::from_slice(&std::fs::read(dir.join("scene.json")).unwrap()).unwrap();
        let path = |k: &str| PathBuf::from(r[k].as_str().unwrap());
        let gt = std::fs::read_to_string(path("gt_path"))
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .map(|l| {
                let t: Vec<&str> = l.split_whitespace().collect();
                let v: Vec<f64> = t[1..8].iter().map(|v| v.parse().unwrap()).collect();
                (
                    t[0].to_owned(),
                    Pose::from_colmap_array(v.try_into().unwrap()).unwrap(),
                )
            })
            .collect();
        Scene {
            sfm: path("sfm"),
            features: path("features"),
            features_map: path("features_map"),
            queries: path("queries"),
            gt,
            spacing: r["spacing"].as_f64().unwrap(),
        }
    })
}

/// Poses written by `localize -o` (COLMAP lines), by name.
fn poses(path: &Path) -> BTreeMap<String, Pose> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            let v: Vec<f64> = t[1..8].iter().map(|v| v.parse().unwrap()).collect();
            (
                t[0].to_owned(),
                Pose::from_colmap_array(v.try_into().unwrap()).unwrap(),
            )
        })
        .collect()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `convert --colmap SFM --features FEATS_MAP -o map`: the scene's hloc map.
fn convert_map(map: &Path) {
    let scene = scene();
    ok(&[
        "convert",
        "--colmap",
        s(&scene.sfm),
        "--features",
        s(&scene.features_map),
        "-o",
        s(map),
    ]);
}

#[test]
fn an_hloc_map_converts_and_localizes_every_query_from_its_features_files() {
    let scene = scene();
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("hloc.sfpm");
    let before = std::fs::read(&scene.features_map).unwrap();
    let report: Value = serde_json::from_str(&ok(&[
        "convert",
        "--colmap",
        s(&scene.sfm),
        "--features",
        s(&scene.features_map),
        "-o",
        s(&map),
        "--json",
    ]))
    .unwrap();
    assert_eq!(
        std::fs::read(&scene.features_map).unwrap(),
        before,
        "features file modified"
    );
    assert_eq!(report["points_without_descriptors"], 0, "{report}");
    // hloc's `sift` conf is RootSIFT: named so, never COLMAP's `sift`.
    let info: Value = serde_json::from_str(&ok(&["info", s(&map), "--json"])).unwrap();
    assert_eq!(info["levels"][0]["descriptor"], "rootsift", "{info}");
    // The full map, and its short PQ slice (what a robot would carry): every query
    // localized as precisely.
    let slice = dir.path().join("hloc-short-pq16.sfpm");
    ok(&[
        "slice",
        s(&map),
        "--level",
        "0",
        "--short",
        "--pq",
        "16",
        "-o",
        s(&slice),
    ]);
    assert!(std::fs::metadata(&slice).unwrap().len() < std::fs::metadata(&map).unwrap().len());
    for map in [&map, &slice] {
        localizes_every_query(s(map), dir.path());
    }
}

/// `localize --map MAP` (a path or URL) with the scene's query features: every query within a
/// tenth of the camera spacing and 2° of the ground truth.
fn localizes_every_query(map: &str, dir: &Path) {
    let scene = scene();
    let out = dir.join("poses.txt");
    ok(&[
        "localize",
        "--map",
        map,
        "--query-list",
        s(&scene.queries),
        "--features",
        s(&scene.features),
        "-o",
        s(&out),
        "--force",
    ]);
    let got = poses(&out);
    assert_eq!(
        got.len(),
        scene.gt.len(),
        "{map}: every query localized: {got:?}"
    );
    for (name, gt) in &scene.gt {
        let pose = got[name];
        let (dt, dr) = (pose.center_distance(gt), pose.rotation_error_deg(gt));
        assert!(
            dt <= 0.1 * scene.spacing && dr <= 2.0,
            "{map} {name}: {dt} units (spacing {}), {dr}°",
            scene.spacing
        );
    }
}

/// An hloc map as any other map: `slice --budget` fits it into a quarter of its bytes, and it
/// and its budget slice are read from an HTTP server by range (nginx on loopback) and
/// localize every query as the local file does.
#[test]
fn an_hloc_map_slices_to_a_budget_and_localizes_from_a_server() {
    let nginx = crate::servers::Nginx::start();
    let dir = tempfile::tempdir().unwrap();
    let map = nginx.root.join("hloc.sfpm");
    convert_map(&map);
    let full = std::fs::metadata(&map).unwrap().len();
    let budget = full / 4;
    let slice = nginx.root.join("hloc-budget.sfpm");
    let report: Value = serde_json::from_str(&ok(&[
        "slice",
        s(&map),
        "--budget",
        &budget.to_string(),
        "-o",
        s(&slice),
        "--json",
    ]))
    .unwrap();
    let bytes = std::fs::metadata(&slice).unwrap().len();
    assert!(bytes <= budget, "{bytes} > {budget}: {report}");
    for name in ["hloc.sfpm", "hloc-budget.sfpm"] {
        localizes_every_query(&nginx.url(name), dir.path());
    }
    // Read by range: the server saw partial requests only.
    let requests = nginx.requests();
    assert!(
        !requests.is_empty() && requests.iter().all(|r| r.split(' ').nth(2) == Some("206")),
        "{requests:?}"
    );
}

#[test]
fn query_features_of_another_feature_are_refused_naming_both() {
    let scene = scene();
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("hloc.sfpm");
    convert_map(&map);
    // The same bytes under hloc's name for DISK features.
    let disk = dir.path().join("feats-disk.h5");
    std::fs::copy(&scene.features, &disk).unwrap();
    let out = sfpmap(&[
        "localize",
        "--map",
        s(&map),
        "--query-list",
        s(&scene.queries),
        "--features",
        s(&disk),
        "-o",
        s(&dir.path().join("p.txt")),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8(out.stderr).unwrap();
    assert_eq!(
        err.trim_end(),
        format!(
            "error: {}: features of model \"disk\", but the map {} holds \"rootsift\" \
             descriptors: give query features of \"rootsift\"",
            disk.display(),
            map.display()
        )
    );
}
