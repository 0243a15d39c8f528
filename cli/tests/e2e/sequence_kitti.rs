//! Sequential localization on real frames with metric ground truth: KITTI odometry 06, frames
//! 0–50 (`shared/data/sequences/kitti06`). The scene is built here, once for all test
//! processes (`tests/support/once.rs`), by `shared/data/tools/make_posed_scene.py` (map
//! triangulated with the true poses held fixed, so errors are in metres; every 4th frame a
//! query, 13 in all). It needs Python with pycolmap 4.2.1: the interpreter `SFPMAP_PYTHON`
//! names (`bash .ci/test` sets it), else `python3`. It fails, never skips.
//! `SFPMAP_KITTI06_SCENE` names a scene that script built before, to use instead.
//!
//! `localize --sequence` on the query list (SIFT map and its level-2 short slice) and
//! `localize --mcap` on a log of the query frames (SFP map): every frame localized, within a
//! tenth of the map's camera spacing and 2°, and the frames after the first tracked from the
//! constant-velocity prediction, not retrieved (all 12 of them here; the tests allow one lost
//! on the query list, two in the log).
#![cfg(all(feature = "mcap", feature = "colmap"))]

use crate::common;
use crate::once::{built_once, Depends};

use serde_json::Value;
use sfpmap::geometry::Pose;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn shared() -> PathBuf {
    crate::shared_data::repo_root().join("../shared/data")
}

fn sfpmap(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(args)
        .env("ORT_DISABLE_TELEMETRY", "1")
        .output()
        .expect("sfpmap runs")
}

/// Runs sfpmap, which must succeed; its stdout as JSON (`Null` when it is not JSON).
fn ok(args: &[&str]) -> Value {
    let out = sfpmap(args);
    assert!(
        out.status.success(),
        "sfpmap {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or(Value::Null)
}

pub(crate) fn path_str(p: &Path) -> &str {
    p.to_str().expect("temp paths are UTF-8")
}

pub(crate) struct Query {
    pub(crate) name: String,
    /// `MODEL W H params...`
    pub(crate) camera: String,
    pub(crate) gt_cam_from_world: Pose,
}

pub(crate) struct Scene {
    pub(crate) root: PathBuf,
    /// Median distance between neighbouring map cameras, metres (stats.json).
    pub(crate) spacing_m: f64,
    /// In sequence order.
    pub(crate) queries: Vec<Query>,
}

fn python() -> PathBuf {
    crate::python::python_with("numpy, pycolmap")
}

/// The KITTI 06 scene, built once for all test processes (its folder is named by a hash of
/// the script and the sequence's poses), or the one `SFPMAP_KITTI06_SCENE` names.
pub(crate) fn scene() -> &'static Scene {
    static SCENE: OnceLock<Scene> = OnceLock::new();
    SCENE.get_or_init(|| {
        let root = match std::env::var_os("SFPMAP_KITTI06_SCENE") {
            Some(root) => PathBuf::from(root),
            None => {
                let script = shared().join("tools/make_posed_scene.py");
                let sequence = shared().join("sequences/kitti06");
                let inputs = [script.clone(), sequence.join("poses.txt")]
                    .iter()
                    .map(|p| std::fs::read(p).unwrap())
                    .fold(Vec::new(), |mut all, bytes| {
                        all.extend(bytes);
                        all
                    });
                let recipe = format!(
                    "make_posed_scene.py IMAGES POSES CALIB OUT, inputs xxh3 {:016x}",
                    xxhash_rust::xxh3::xxh3_64(&inputs)
                );
                let dir = built_once("kitti06-scene", &recipe, Depends::OnRecipe, |dir| {
                    let out = Command::new(python())
                        .arg(&script)
                        .arg(sequence.join("images"))
                        .arg(sequence.join("poses.txt"))
                        .arg(sequence.join("calib.txt"))
                        .arg(dir.join("kitti06"))
                        .output()
                        .expect("python3 runs");
                    assert!(
                        out.status.success(),
                        "make_posed_scene.py failed (it needs pycolmap 4.2.1; SFPMAP_PYTHON \
                         names another interpreter): {}",
                        String::from_utf8_lossy(&out.stderr)
                    );
                });
                dir.join("kitti06")
            }
        };
        let stats: Value =
            serde_json::from_slice(&std::fs::read(root.join("stats.json")).unwrap()).unwrap();
        let spacing_m = stats["spacing_m"].as_f64().unwrap();
        let gt: BTreeMap<String, Pose> = std::fs::read_to_string(root.join("gt_poses.txt"))
            .unwrap()
            .lines()
            .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
            .map(|l| {
                let t: Vec<&str> = l.split_whitespace().collect();
                let v: Vec<f64> = t[1..8].iter().map(|v| v.parse().unwrap()).collect();
                let pose = Pose::from_colmap_array(v.try_into().unwrap()).unwrap();
                (t[0].to_owned(), pose)
            })
            .collect();
        let queries: Vec<Query> = std::fs::read_to_string(root.join("queries.txt"))
            .unwrap()
            .lines()
            .filter(|l| !l.trim().is_empty())
            .map(|l| {
                let (name, camera) = l.trim().split_once(' ').unwrap();
                Query {
                    name: name.to_owned(),
                    camera: camera.to_owned(),
                    gt_cam_from_world: gt[name],
                }
            })
            .collect();
        // Frames 0–50, every 4th from frame 2; file names are frame numbers.
        assert_eq!(queries.len(), 13);
        assert!(queries.windows(2).all(|w| w[0].name < w[1].name));
        // About 1.2 m between map frames (a car at ~30 km/h, 10 Hz, 3 of 4 frames mapped).
        assert!((0.5..3.0).contains(&spacing_m), "spacing {spacing_m} m");
        Scene {
            root,
            spacing_m,
            queries,
        }
    })
}

/// Asserts a localized pose is within a tenth of the camera spacing and 2° of the truth.
pub(crate) fn check_pose(scene: &Scene, query: &Query, cam_from_world: &Pose, what: &str) {
    let dist = cam_from_world.center_distance(&query.gt_cam_from_world);
    let rot = cam_from_world.rotation_error_deg(&query.gt_cam_from_world);
    assert!(
        dist < 0.1 * scene.spacing_m && rot < 2.0,
        "{what}: {}: {dist:.3} m, {rot:.2}° from the truth (allowed {:.3} m, 2°)",
        query.name,
        0.1 * scene.spacing_m
    );
}

/// `convert --colmap SCENE/sparse-map SOURCE... -o map --quiet`: SOURCE is the features'
/// (`--database DB` or `--images DIR`).
fn convert_scene(map: &Path, source: &[&str]) {
    let sparse = scene().root.join("sparse-map");
    let mut args = vec!["convert", "--colmap", path_str(&sparse)];
    args.extend(source);
    args.extend(["-o", path_str(map), "--quiet"]);
    ok(&args);
}

/// The SIFT map of the scene (from a copy of its database) and its level-2 short slice, built
/// once for all test processes (`tests/support/once.rs`).
fn sift_map() -> &'static (PathBuf, PathBuf, PathBuf) {
    static MAP: OnceLock<(PathBuf, PathBuf, PathBuf)> = OnceLock::new();
    MAP.get_or_init(|| {
        let s = scene();
        let recipe = format!(
            "convert --database (a copy of) {0}/database.db, slice --level 2 --short",
            s.root.display()
        );
        let dir = built_once("kitti06-sift", &recipe, Depends::OnBinary, |dir| {
            let database = dir.join("database.db");
            std::fs::copy(s.root.join("database.db"), &database).unwrap();
            convert_scene(&dir.join("sift.sfpm"), &["--database", path_str(&database)]);
            // The smallest useful slice: the coarsest level's short descriptors.
            ok(&[
                "slice",
                path_str(&dir.join("sift.sfpm")),
                "--level",
                "2",
                "--short",
                "-o",
                path_str(&dir.join("sift-l2s.sfpm")),
                "--quiet",
            ]);
        });
        (
            dir.clone(),
            dir.join("sift.sfpm"),
            dir.join("sift-l2s.sfpm"),
        )
    })
}

/// `localize` on the query list with the queries' SIFT from a copy of queries.db: the
/// `--json` report and the `--format json` per-query list.
fn localize_list(map: &Path, extra: &[&str]) -> (Value, Vec<Value>) {
    let dir = tempfile::tempdir().unwrap();
    let database = dir.path().join("queries.db");
    std::fs::copy(scene().root.join("queries.db"), &database).unwrap();
    localize_json(map, &["--database", path_str(&database)], extra)
}

/// `localize --map MAP --query-list queries.txt FEATURES... --format json EXTRA...`: the
/// `--json` report and the per-query list.
pub(crate) fn localize_json(map: &Path, features: &[&str], extra: &[&str]) -> (Value, Vec<Value>) {
    let dir = tempfile::tempdir().unwrap();
    let poses = dir.path().join("poses.json");
    let query_list = scene().root.join("queries.txt");
    let mut args = vec![
        "localize",
        "--map",
        path_str(map),
        "--query-list",
        path_str(&query_list),
    ];
    args.extend(features);
    args.extend(["--format", "json", "-o", path_str(&poses), "--json"]);
    args.extend(extra);
    let report = ok(&args);
    let list: Value = serde_json::from_slice(&std::fs::read(&poses).unwrap()).unwrap();
    (report, list.as_array().unwrap().clone())
}

/// Every query localized within the bounds; the per-query paths, tracking-lost reasons and
/// retrieval methods add up to the report's counts. Returns the per-query paths.
fn check_list_run(what: &str, report: &Value, list: &[Value]) -> Vec<String> {
    let s = scene();
    assert_eq!(report["queries"], 13, "{what}: {report}");
    assert_eq!(report["localized"], 13, "{what}: {report}");
    assert_eq!(report["failed"], serde_json::json!([]), "{what}: {report}");
    assert_eq!(list.len(), s.queries.len());
    let mut paths = BTreeMap::<String, u64>::new();
    let mut lost = BTreeMap::<String, u64>::new();
    let mut retrieval = BTreeMap::<String, u64>::new();
    for (q, r) in s.queries.iter().zip(list) {
        assert_eq!(r["name"], q.name.as_str(), "{what}");
        let pose: [f64; 7] = serde_json::from_value(r["cam_from_world"].clone())
            .unwrap_or_else(|_| panic!("{what}: {} not localized: {r}", q.name));
        check_pose(s, q, &Pose::from_colmap_array(pose).unwrap(), what);
        *paths
            .entry(r["path"].as_str().unwrap().to_owned())
            .or_default() += 1;
        if let Some(why) = r["tracking_lost"].as_str() {
            *lost.entry(why.to_owned()).or_default() += 1;
        }
        if let Some(method) = r["retrieval"].as_str() {
            *retrieval.entry(method.to_owned()).or_default() += 1;
        }
    }
    assert_eq!(report["path"], serde_json::json!(paths), "{what}");
    assert_eq!(report["tracking_lost"], serde_json::json!(lost), "{what}");
    assert_eq!(report["retrieval"], serde_json::json!(retrieval), "{what}");
    list.iter()
        .map(|r| r["path"].as_str().unwrap().to_owned())
        .collect()
}

/// A sequence run: the first query has no prediction and is retrieved (with the map's VLAD);
/// at least 11 of the other 12 are tracked; one that is not says why tracking was lost.
fn check_sequence(what: &str, report: &Value, list: &[Value]) {
    let paths = check_list_run(what, report, list);
    assert_eq!(paths[0], "retrieval", "{what}: {}", list[0]);
    assert!(list[0]["tracking_lost"].is_null(), "{what}: {}", list[0]);
    assert_eq!(list[0]["retrieval"], "vlad", "{what}: {}", list[0]);
    let tracked = paths.iter().filter(|p| *p == "tracking").count();
    assert!(tracked >= 11, "{what}: {tracked} of 12 tracked: {report}");
    for r in &list[1..] {
        match r["path"].as_str().unwrap() {
            // Tracking needs no retrieval.
            "tracking" => assert!(r["retrieval"].is_null(), "{what}: {r}"),
            "retrieval" => assert!(r["tracking_lost"].is_string(), "{what}: {r}"),
            other => panic!("{what}: path {other:?}: {r}"),
        }
    }
}

#[test]
fn sift_map_sequence_tracks_every_query_after_the_first() {
    let (_, map, _) = sift_map();
    let (report, list) = localize_list(map, &["--sequence"]);
    check_sequence("SIFT --sequence", &report, &list);
}

#[test]
fn sift_level2_short_slice_sequence_tracks_and_without_it_retrieves() {
    let (_, _, slice) = sift_map();
    let (report, list) = localize_list(slice, &["--short", "--sequence"]);
    check_sequence("SIFT L2 short --sequence", &report, &list);
    // Without --sequence there is no prediction: every query is retrieved. (On the slice
    // only: the path does not depend on the map, and the full map's run takes a minute in a
    // debug build.)
    let (report, list) = localize_list(slice, &["--short"]);
    let paths = check_list_run("SIFT L2 short", &report, &list);
    assert!(paths.iter().all(|p| p == "retrieval"), "{report}");
    assert_eq!(report["retrieval"], serde_json::json!({ "vlad": 13 }));
    assert_eq!(report["tracking_lost"], serde_json::json!({}));
}

/// A `sensor_msgs/msg/CompressedImage` as CDR.
fn compressed_image(stamp_ns: u64, format: &str, data: &[u8]) -> Vec<u8> {
    let stamp = ((stamp_ns / SEC) as i32, (stamp_ns % SEC) as u32);
    common::compressed_image(stamp, "camera_left", format, data)
}

const SEC: u64 = 1_000_000_000;

/// The SFP map of the scene (the built-in model), built once for all test processes.
pub(crate) fn sfp_map() -> &'static (PathBuf, PathBuf) {
    static MAP: OnceLock<(PathBuf, PathBuf)> = OnceLock::new();
    MAP.get_or_init(|| {
        let images = scene().root.join("images");
        let recipe = format!("convert --images {}", images.display());
        let dir = built_once("kitti06-sfp", &recipe, Depends::OnBinary, |dir| {
            convert_scene(&dir.join("sfp.sfpm"), &["--images", path_str(&images)]);
        });
        (dir.clone(), dir.join("sfp.sfpm"))
    })
}

/// `--sequence --images` on the SFP map: every frame localized, the first retrieved by the
/// map's global descriptor (computed on 512-px copies of the 1241x376 frames), the others
/// tracked; a frame with a prior skips the global descriptor's extra inference, a run
/// without `--sequence` skips none.
#[test]
fn sfp_map_sequence_skips_the_global_descriptor_of_tracked_frames() {
    let s = scene();
    let map = &sfp_map().1;
    assert_eq!(
        sfpmap::format::Map::open(map)
            .unwrap()
            .metadata()
            .global_max_side,
        Some(512)
    );
    let images = s.root.join("images");
    let run = |extra: &[&str]| localize_json(map, &["--images", path_str(&images)], extra);
    let (report, list) = run(&["--sequence"]);
    let paths = check_list_run("SFP sequence", &report, &list);
    assert_eq!(paths[0], "retrieval", "{}", list[0]);
    assert_eq!(list[0]["retrieval"], "global", "{}", list[0]);
    let tracked = paths.iter().filter(|p| *p == "tracking").count();
    assert!(tracked >= 11, "{tracked} of 12 tracked: {report}");
    // Every frame after the first had a prior (the first was localized).
    assert_eq!(report["global_skipped"], 12, "{report}");
    let (report, list) = run(&[]);
    check_list_run("SFP list", &report, &list);
    assert_eq!(report["global_skipped"], 0, "{report}");
    assert_eq!(report["retrieval"]["global"], 13, "{report}");
}

#[test]
fn mcap_log_of_the_query_frames_is_tracked() {
    let s = scene();
    let dir = tempfile::tempdir().unwrap();
    let map = &sfp_map().1;

    // The query frames as the camera recorded them: KITTI runs at 10 Hz and the file name is
    // the frame number; the images are the scene's JPEGs, bytes unchanged.
    let topic = "/kitti/camera_left/image_raw/compressed";
    let t0 = 1_317_000_000 * SEC;
    let stamps: Vec<u64> = s
        .queries
        .iter()
        .map(|q| {
            let frame: u64 = q.name.trim_end_matches(".jpg").parse().unwrap();
            t0 + frame * SEC / 10
        })
        .collect();
    let input = dir.path().join("kitti06.mcap");
    {
        let file = std::io::BufWriter::new(std::fs::File::create(&input).unwrap());
        let mut w = mcap::WriteOptions::new().create(file).unwrap();
        let schema = w
            .add_schema("sensor_msgs/msg/CompressedImage", "ros2msg", b"")
            .unwrap();
        let channel = w
            .add_channel(schema, topic, "cdr", &BTreeMap::new())
            .unwrap();
        for (i, (q, &stamp)) in s.queries.iter().zip(&stamps).enumerate() {
            let jpeg = std::fs::read(s.root.join("images").join(&q.name)).unwrap();
            w.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: i as u32,
                    log_time: stamp,
                    publish_time: stamp,
                },
                &compressed_image(stamp, "jpeg", &jpeg),
            )
            .unwrap();
        }
        w.finish().unwrap();
    }

    let output = dir.path().join("poses.mcap");
    let report = ok(&[
        "localize",
        "--map",
        path_str(map),
        "--mcap",
        path_str(&input),
        "--topic",
        topic,
        "--camera",
        &s.queries[0].camera,
        "-o",
        path_str(&output),
        "--json",
    ]);
    assert_eq!(report["images"], 13, "{report}");
    assert_eq!(report["localized"], 13, "{report}");
    assert_eq!(report["failed"], serde_json::json!([]), "{report}");
    let tracked = report["path"]["tracking"].as_u64().unwrap_or(0);
    let retrieved = report["path"]["retrieval"].as_u64().unwrap_or(0);
    assert_eq!(tracked + retrieved, 13, "{report}");
    assert!(tracked >= 10, "{tracked} of 13 tracked: {report}");
    // Only the retrieved frames were ranked (the map's global descriptor); the first frame,
    // with nothing to predict from, is one of them.
    assert!(retrieved >= 1, "{report}");
    let ranked: u64 = report["retrieval"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    assert_eq!(ranked, retrieved, "{report}");
    let lost: u64 = report["tracking_lost"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    assert_eq!(lost, retrieved - 1, "{report}");
    // Frames extracted while the sequence tracked skip the global descriptor's 512-px copy
    // (the frames are 1241x376); the first frames, extracted before any pose, cannot.
    let skipped = report["global_skipped"].as_u64().unwrap();
    assert!((1..=12).contains(&skipped), "{report}");

    // One foxglove.PoseInFrame (world_from_cam, JSON) per frame, at the frame's time.
    let bytes = std::fs::read(&output).unwrap();
    let poses: Vec<(u64, Value)> = mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(|m| m.unwrap())
        .filter(|m| m.channel.topic == "/sfpmap/pose")
        .map(|m| (m.log_time, serde_json::from_slice(&m.data).unwrap()))
        .collect();
    assert_eq!(poses.len(), 13);
    for ((q, &stamp), (log_time, pose)) in s.queries.iter().zip(&stamps).zip(&poses) {
        assert_eq!(*log_time, stamp, "{}", q.name);
        assert_eq!(pose["timestamp"]["sec"], stamp / SEC, "{}", q.name);
        assert_eq!(pose["timestamp"]["nsec"], stamp % SEC, "{}", q.name);
        let p = &pose["pose"]["position"];
        let o = &pose["pose"]["orientation"];
        let [x, y, z, qw, qx, qy, qz] = [
            &p["x"], &p["y"], &p["z"], &o["w"], &o["x"], &o["y"], &o["z"],
        ]
        .map(|v| v.as_f64().unwrap());
        // The same layout as a cam_from_world, read as the transform it is.
        let world_from_cam = Pose::from_colmap(qw, qx, qy, qz, x, y, z).unwrap();
        check_pose(s, q, &world_from_cam.inverse(), "MCAP");
    }
}
