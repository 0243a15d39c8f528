//! `sfpmap localize --mcap` end to end on the real sacre-coeur scene: input logs written here
//! with the `mcap` crate (ROS 2 CompressedImage and raw rgb8 Image as CDR, CameraInfo,
//! foxglove.CompressedImage as JSON), the real binary, and the output read back.
#![cfg(feature = "mcap")]

use crate::common;
use crate::once::{built_once, Depends};

use common::Cdr;
use serde_json::Value;
use sfpmap::geometry::Pose;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

fn scene() -> PathBuf {
    crate::shared_data::repo_root().join("../shared/data/scenes/sacre-coeur")
}

fn sfpmap(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(args)
        .env("ORT_DISABLE_TELEMETRY", "1")
        .output()
        .expect("sfpmap runs")
}

fn ok(args: &[&str]) -> (Value, String) {
    let out = sfpmap(args);
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(out.status.success(), "sfpmap {args:?} failed: {stderr}");
    (
        serde_json::from_slice(&out.stdout).unwrap_or(Value::Null),
        stderr,
    )
}

fn fails(args: &[&str]) -> String {
    let out = sfpmap(args);
    assert!(!out.status.success(), "sfpmap {args:?} succeeded");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The SFP map of the scene's map images, built once for all test processes
/// (`tests/support/once.rs`).
fn map() -> &'static str {
    static MAP: OnceLock<String> = OnceLock::new();
    MAP.get_or_init(|| {
        let recipe = "convert --colmap sacre-coeur/sparse-map --images sacre-coeur/images";
        let dir = built_once("sacre-coeur-sfp", recipe, Depends::OnBinary, |dir| {
            let out = dir.join("map.sfpm");
            let s = scene();
            ok(&[
                "convert",
                "--colmap",
                s.join("sparse-map").to_str().unwrap(),
                "--images",
                s.join("images").to_str().unwrap(),
                "-o",
                out.to_str().unwrap(),
                "--quiet",
            ]);
        });
        dir.join("map.sfpm").to_str().unwrap().to_owned()
    })
}

struct Query {
    name: String,
    /// `MODEL W H params...`
    camera: String,
    /// cam_from_world qw qx qy qz tx ty tz (pseudo ground truth).
    gt: [f64; 7],
}

fn queries() -> Vec<Query> {
    let gt: BTreeMap<String, [f64; 7]> = std::fs::read_to_string(scene().join("gt_poses.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let t: Vec<&str> = l.split_whitespace().collect();
            let v: Vec<f64> = t[1..8].iter().map(|v| v.parse().unwrap()).collect();
            (t[0].to_owned(), v.try_into().unwrap())
        })
        .collect();
    std::fs::read_to_string(scene().join("queries.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let (name, camera) = l.trim().split_once(' ').unwrap();
            Query {
                name: name.to_owned(),
                camera: camera.to_owned(),
                gt: gt[name],
            }
        })
        .collect()
}

fn compressed_image(stamp: (i32, u32), jpeg: &[u8]) -> Vec<u8> {
    common::compressed_image(stamp, "camera_a", "jpeg", jpeg)
}

fn raw_image(stamp: (i32, u32), encoding: &str, image: &image::RgbImage) -> Vec<u8> {
    let mut c = Cdr::new();
    c.header(stamp, "camera_b")
        .u32(image.height())
        .u32(image.width())
        .string(encoding)
        .u8(0)
        .u32(image.width() * 3)
        .bytes(image.as_raw());
    c.0
}

/// A ROS CameraInfo for a COLMAP SIMPLE_RADIAL camera `f cx cy k` (ROS puts the first pixel's
/// centre at 0, COLMAP at 0.5).
fn camera_info(stamp: (i32, u32), camera: &str) -> Vec<u8> {
    let t: Vec<&str> = camera.split_whitespace().collect();
    assert_eq!(t[0], "SIMPLE_RADIAL");
    let (w, h): (u32, u32) = (t[1].parse().unwrap(), t[2].parse().unwrap());
    let p: Vec<f64> = t[3..].iter().map(|v| v.parse().unwrap()).collect();
    let mut c = Cdr::new();
    c.header(stamp, "camera_b")
        .u32(h)
        .u32(w)
        .string("plumb_bob")
        .u32(5);
    for d in [p[3], 0.0, 0.0, 0.0, 0.0] {
        c.f64(d);
    }
    for k in [p[0], 0.0, p[1] - 0.5, 0.0, p[0], p[2] - 0.5, 0.0, 0.0, 1.0] {
        c.f64(k);
    }
    for r in [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
        c.f64(r);
    }
    for _ in 0..12 {
        c.f64(0.0);
    }
    c.u32(0).u32(0);
    for _ in 0..4 {
        c.u32(0);
    }
    c.u8(0);
    c.0
}

/// Writes messages `(topic, schema, encoding, log_time, data)` in the given order.
fn write_mcap(path: &Path, chunked: bool, messages: &[(&str, &str, &str, u64, Vec<u8>)]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut w = mcap::WriteOptions::new()
        .use_chunks(chunked)
        .create(file)
        .unwrap();
    let mut channels = BTreeMap::new();
    for (topic, schema, encoding, time, data) in messages {
        let channel = *channels.entry(*topic).or_insert_with(|| {
            let schema_encoding = match *encoding {
                "cdr" => "ros2msg",
                "json" => "jsonschema",
                _ => "",
            };
            let s = w.add_schema(schema, schema_encoding, b"").unwrap();
            w.add_channel(s, topic, encoding, &BTreeMap::new()).unwrap()
        });
        w.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: channel,
                sequence: 0,
                log_time: *time,
                publish_time: *time,
            },
            data,
        )
        .unwrap();
    }
    w.finish().unwrap();
}

struct Out {
    poses: Vec<(u64, Value)>,
    pose_schema: Vec<(String, String, String)>,
    other_messages: usize,
}

fn read_output(path: &Path) -> Out {
    let bytes = std::fs::read(path).unwrap();
    let mut out = Out {
        poses: Vec::new(),
        pose_schema: Vec::new(),
        other_messages: 0,
    };
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic == "/sfpmap/pose" {
            let s = m.channel.schema.as_ref().unwrap();
            out.pose_schema.push((
                s.name.clone(),
                s.encoding.clone(),
                m.channel.message_encoding.clone(),
            ));
            out.poses
                .push((m.log_time, serde_json::from_slice(&m.data).unwrap()));
        } else {
            out.other_messages += 1;
        }
    }
    out
}

const SEC: u64 = 1_000_000_000;

/// Rotation error in degrees of a PoseInFrame (world_from_cam) against a cam_from_world.
fn rotation_error_deg(pose: &Value, cam_from_world: [f64; 7]) -> f64 {
    let o = &pose["pose"]["orientation"];
    let q = [&o["w"], &o["x"], &o["y"], &o["z"]].map(|v| v.as_f64().unwrap());
    // world_from_cam is the conjugate of cam_from_world.
    let g = [
        cam_from_world[0],
        -cam_from_world[1],
        -cam_from_world[2],
        -cam_from_world[3],
    ];
    let n = |v: [f64; 4]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let dot = q.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>() / (n(q) * n(g));
    2.0 * dot.abs().min(1.0).acos().to_degrees()
}

fn check_poses(out: &Out, stamps: &[(i32, u32)], query: &Query) {
    assert_eq!(out.poses.len(), stamps.len());
    for ((log_time, pose), stamp) in out.poses.iter().zip(stamps) {
        assert_eq!(*log_time, stamp.0 as u64 * SEC + u64::from(stamp.1));
        assert_eq!(pose["timestamp"]["sec"], stamp.0);
        assert_eq!(pose["timestamp"]["nsec"], stamp.1);
        assert_eq!(pose["frame_id"], "map");
        let err = rotation_error_deg(pose, query.gt);
        assert!(err < 2.0, "{}: rotation error {err:.2}°", query.name);
        // The position is the camera centre (world_from_cam); the scene spans a few units.
        let [qw, qx, qy, qz, tx, ty, tz] = query.gt;
        let gt = Pose::from_colmap(qw, qx, qy, qz, tx, ty, tz)
            .unwrap()
            .center();
        let p = &pose["pose"]["position"];
        let c = [&p["x"], &p["y"], &p["z"]].map(|v| v.as_f64().unwrap());
        let dist = ((c[0] - gt.x).powi(2) + (c[1] - gt.y).powi(2) + (c[2] - gt.z).powi(2)).sqrt();
        assert!(dist < 0.1, "{}: centre error {dist:.3}", query.name);
    }
    for s in &out.pose_schema {
        assert_eq!(
            s,
            &(
                "foxglove.PoseInFrame".into(),
                "jsonschema".into(),
                "json".into()
            )
        );
    }
}

fn log_time(stamp: (i32, u32)) -> u64 {
    stamp.0 as u64 * SEC + u64::from(stamp.1)
}

#[test]
fn ros_and_foxglove_images_round_trip_to_pose_in_frame() {
    let q = queries();
    let dir = tempfile::tempdir().unwrap();
    let jpeg_a = std::fs::read(scene().join("images").join(&q[0].name)).unwrap();
    let rgb_b = image::open(scene().join("images").join(&q[1].name))
        .unwrap()
        .to_rgb8();
    let stamps_a = [(1_700_000_000, 5_000_000), (1_700_000_001, 0)];
    let stamps_b = [(1_700_000_000, 500_000_000), (1_700_000_002, 250)];
    let fox_stamp = (1_700_000_003, 7);
    let fox = serde_json::json!({
        "timestamp": { "sec": fox_stamp.0, "nsec": fox_stamp.1 },
        "frame_id": "camera_a",
        "format": "jpeg",
        "data": sfpmap::io::mcap_io::base64_encode(&jpeg_a),
    })
    .to_string()
    .into_bytes();
    let input = dir.path().join("in.mcap");
    let ci = "sensor_msgs/msg/CompressedImage";
    let im = "sensor_msgs/msg/Image";
    write_mcap(
        &input,
        true,
        &[
            (
                "/b/camera_info",
                "sensor_msgs/msg/CameraInfo",
                "cdr",
                log_time(stamps_b[0]) - 1,
                camera_info(stamps_b[0], &q[1].camera),
            ),
            (
                "/a/compressed",
                ci,
                "cdr",
                log_time(stamps_a[0]),
                compressed_image(stamps_a[0], &jpeg_a),
            ),
            (
                "/b/image",
                im,
                "cdr",
                log_time(stamps_b[0]),
                raw_image(stamps_b[0], "rgb8", &rgb_b),
            ),
            (
                "/a/compressed",
                ci,
                "cdr",
                log_time(stamps_a[1]),
                compressed_image(stamps_a[1], &jpeg_a),
            ),
            (
                "/b/image",
                im,
                "cdr",
                log_time(stamps_b[1]),
                raw_image(stamps_b[1], "rgb8", &rgb_b),
            ),
            (
                "/a/foxglove",
                "foxglove.CompressedImage",
                "json",
                log_time(fox_stamp),
                fox,
            ),
        ],
    );
    let input = input.to_str().unwrap();

    // CompressedImage, --camera, images passed through, TUM.
    let out_a = dir.path().join("a.mcap");
    let tum = dir.path().join("a.txt");
    let (json, _) = ok(&[
        "localize",
        "--map",
        map(),
        "--mcap",
        input,
        "--topic",
        "/a/compressed",
        "--camera",
        &q[0].camera,
        "--passthrough-images",
        "-o",
        out_a.to_str().unwrap(),
        "--tum",
        tum.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(json["images"], 2, "{json}");
    assert_eq!(json["localized"], 2, "{json}");
    assert!(json["unreadable"].is_null());
    let out = read_output(&out_a);
    check_poses(&out, &stamps_a, &q[0]);
    assert_eq!(out.other_messages, 2, "images passed through");
    let tum = std::fs::read_to_string(&tum).unwrap();
    let rows: Vec<&str> = tum.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(rows.len(), 2);
    assert!(rows[0].starts_with("1700000000.005000000 "), "{tum}");
    let position = &out.poses[0].1["pose"]["position"];
    let tx: f64 = rows[0].split_whitespace().nth(1).unwrap().parse().unwrap();
    assert!((tx - position["x"].as_f64().unwrap()).abs() < 1e-9);

    // Raw rgb8 Image with intrinsics from CameraInfo.
    let out_b = dir.path().join("b.mcap");
    let (json, _) = ok(&[
        "localize",
        "--map",
        map(),
        "--mcap",
        input,
        "--topic",
        "/b/image",
        "--camera-info-topic",
        "/b/camera_info",
        "-o",
        out_b.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(json["localized"], 2, "{json}");
    // The camera as `MODEL W H params...` (what --camera takes): SIMPLE_RADIAL `f cx cy k`
    // comes back from CameraInfo as OPENCV `f f cx cy k 0 0 0`.
    let p: Vec<f64> = q[1].camera.split_whitespace().collect::<Vec<_>>()[3..]
        .iter()
        .map(|v| v.parse().unwrap())
        .collect();
    assert_eq!(
        json["camera"].as_str().unwrap(),
        format!(
            "OPENCV 758 1024 {} {} {} {} {} 0 0 0",
            p[0], p[0], p[1], p[2], p[3]
        ),
        "{json}"
    );
    let out = read_output(&out_b);
    check_poses(&out, &stamps_b, &q[1]);
    assert_eq!(out.other_messages, 0);

    // foxglove.CompressedImage as JSON.
    let out_c = dir.path().join("c.mcap");
    let (json, _) = ok(&[
        "localize",
        "--map",
        map(),
        "--mcap",
        input,
        "--topic",
        "/a/foxglove",
        "--camera",
        &q[0].camera,
        "-o",
        out_c.to_str().unwrap(),
        "--json",
    ]);
    assert_eq!(json["localized"], 1, "{json}");
    check_poses(&read_output(&out_c), &[fox_stamp], &q[0]);
}

#[test]
fn missing_topic_unsupported_encoding_and_truncated_log() {
    let q = queries();
    let dir = tempfile::tempdir().unwrap();
    let jpeg = std::fs::read(scene().join("images").join(&q[0].name)).unwrap();
    let stamps = [(10, 0), (11, 0), (12, 0)];
    let small = image::RgbImage::new(4, 3);
    let mut messages: Vec<(&str, &str, &str, u64, Vec<u8>)> = stamps
        .iter()
        .map(|&s| {
            (
                "/cam/compressed",
                "sensor_msgs/msg/CompressedImage",
                "cdr",
                log_time(s),
                compressed_image(s, &jpeg),
            )
        })
        .collect();
    messages.insert(
        1,
        (
            "/cam/yuv",
            "sensor_msgs/msg/Image",
            "cdr",
            log_time(stamps[0]),
            raw_image(stamps[0], "yuv422", &small),
        ),
    );
    // Unchunked, so a cut inside the last image leaves the ones before it readable.
    let input = dir.path().join("in.mcap");
    write_mcap(&input, false, &messages);
    let input_s = input.to_str().unwrap();
    let out = dir.path().join("out.mcap");
    let out_s = out.to_str().unwrap();
    let run = |input: &str, topic: &str| {
        vec![
            "localize".to_owned(),
            "--map".into(),
            map().into(),
            "--mcap".into(),
            input.into(),
            "--topic".into(),
            topic.into(),
            "--camera".into(),
            q[0].camera.clone(),
            "-o".into(),
            out_s.into(),
            "--json".into(),
        ]
    };
    fn args(v: &[String]) -> Vec<&str> {
        v.iter().map(String::as_str).collect()
    }

    // A topic that is not there: one line naming the topics that are.
    let err = fails(&args(&run(input_s, "/camera/image")));
    assert!(
        err.contains("no topic \"/camera/image\"")
            && err.contains(
                r#""/cam/compressed" ("sensor_msgs/msg/CompressedImage"), "/cam/yuv" ("sensor_msgs/msg/Image")"#
            ),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");

    // An encoding we do not read.
    let err = fails(&args(&run(input_s, "/cam/yuv")));
    assert!(
        err.contains("unsupported image encoding \"yuv422\""),
        "{err}"
    );
    assert!(!out.exists());

    // Cut in the middle of the last image: the first two are localized, the rest reported.
    let bytes = std::fs::read(&input).unwrap();
    let cut = bytes.len() - (jpeg.len() / 2) - 200;
    let truncated = dir.path().join("cut.mcap");
    std::fs::write(&truncated, &bytes[..cut]).unwrap();
    let cut_run = sfpmap(&args(&run(truncated.to_str().unwrap(), "/cam/compressed")));
    let stderr = String::from_utf8_lossy(&cut_run.stderr).into_owned();
    // Part of the log was skipped: exit status 3 (README).
    assert_eq!(cut_run.status.code(), Some(3), "{stderr}");
    let json: Value = serde_json::from_slice(&cut_run.stdout).unwrap();
    assert_eq!(json["images"], 2, "{json}");
    assert_eq!(json["localized"], 2, "{json}");
    assert!(json["unreadable"]["error"].is_string(), "{json}");
    assert!(
        json["unreadable"]["messages"].is_null(),
        "no summary to count from"
    );
    assert!(
        stderr.contains("warning:") && stderr.contains("unreadable"),
        "{stderr}"
    );
    check_poses(&read_output(&out), &stamps[..2], &q[0]);

    // Cut before any image: an error, not an empty output.
    std::fs::remove_file(&out).unwrap();
    std::fs::write(&truncated, &bytes[..bytes.len().min(200)]).unwrap();
    let err = fails(&args(&run(truncated.to_str().unwrap(), "/cam/compressed")));
    assert!(err.contains("no message on topic"), "{err}");
    assert!(!out.exists());
}

#[test]
fn mcap_refuses_query_list_only_flags() {
    // --features and --format describe query-list runs; with --mcap they would be ignored.
    for extra in [["--features", "x.h5"], ["--format", "tum"]] {
        let mut args = vec![
            "localize",
            "--map",
            "m.sfpm",
            "--mcap",
            "in.mcap",
            "--topic",
            "/cam",
            "--camera",
            "PINHOLE 640 480 500 500 320 240",
            "-o",
            "out.mcap",
        ];
        args.extend(extra);
        let err = fails(&args);
        assert!(
            err.contains(&format!(
                "the argument '--mcap <MCAP>' cannot be used with '{} <",
                extra[0]
            )),
            "{err}"
        );
    }
}
