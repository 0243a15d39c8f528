//! `sfpmap ros2` against a DDS that is not ours: Eclipse Cyclone DDS (PyPI `cyclonedds`, in
//! the venv `bash .ci/test` makes) publishes the KITTI 06 query frames under ROS 2's topic
//! and type names and reads the poses back (`ros2_peer.py` beside this file). Everything
//! stays on loopback: the node joins with `--interface 127.0.0.1`, Cyclone is configured
//! likewise, and each test has a DDS domain of its own (tests run in parallel).

use crate::sequence_kitti::{check_pose, localize_json, path_str, scene, sfp_map};
use serde_json::Value;
use sfpmap::geometry::Pose;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const SEC: u64 = 1_000_000_000;

fn peer_script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/e2e/ros2_peer.py")
}

/// The peer in `mode` (`ros2_peer.py`), to the end; its JSON line.
fn peer(mode: &str, domain: u16, args: &[&str]) -> Value {
    let out = peer_command(mode, domain, args)
        .output()
        .expect("the peer runs");
    assert!(
        out.status.success(),
        "ros2_peer.py {mode} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "ros2_peer.py {mode}: {e}: {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

fn peer_command(mode: &str, domain: u16, args: &[&str]) -> Command {
    let mut c = Command::new(crate::python::python_with("cyclonedds"));
    c.arg(peer_script())
        .arg(mode)
        .args(["--domain", &domain.to_string()])
        .args(args);
    c
}

/// `sfpmap ros2 --map MAP --domain-id D --interface 127.0.0.1 --json ARGS...`, running.
fn node(map: &Path, domain: u16, args: &[&str]) -> Child {
    node_of(&["--map", path_str(map)], domain, args)
}

/// `sfpmap ros2 MAP_ARGS --domain-id D --interface 127.0.0.1 --json ARGS...`, running.
fn node_of(map_args: &[&str], domain: u16, args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .arg("ros2")
        .args(map_args)
        .args(["--domain-id", &domain.to_string()])
        .args(["--interface", "127.0.0.1", "--json"])
        .args(args)
        .env("ORT_DISABLE_TELEMETRY", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("sfpmap ros2 starts")
}

/// Waits for the node (at most `timeout`, then kills it and fails); its `--json` counts.
fn finished(mut node: Child, timeout: Duration) -> Value {
    let end = Instant::now() + timeout;
    while node.try_wait().unwrap().is_none() {
        if Instant::now() > end {
            node.kill().ok();
            let out = node.wait_with_output().unwrap();
            panic!(
                "sfpmap ros2 did not stop in {timeout:?}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = node.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "sfpmap ros2 failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "sfpmap ros2 --json: {e}: {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

/// SIGTERM, as a user's Ctrl-C or a launcher's stop: the node ends its loop and prints its
/// `--json` counts (at most 30 s).
fn terminated(node: Child) -> Value {
    Command::new("kill")
        .args(["-TERM", &node.id().to_string()])
        .status()
        .unwrap();
    finished(node, Duration::from_secs(30))
}

/// The peer in `mode` publishing the frames `names` (in `images`) stamped `stamps` on `topic`;
/// its JSON line.
fn publish(
    mode: &str,
    domain: u16,
    (topic, images): (&str, &Path),
    names: &[&str],
    stamps: &[u64],
    extra: &[&str],
) -> Value {
    let (names, stamps) = (joined(names), joined(stamps));
    let mut args = vec!["--image-topic", topic, "--images", path_str(images)];
    args.extend(["--names", &names, "--stamps", &stamps]);
    args.extend(extra);
    peer(mode, domain, &args)
}

/// The query frames' stamps: KITTI runs at 10 Hz and the file name is the frame number.
fn stamps() -> Vec<u64> {
    scene()
        .queries
        .iter()
        .map(|q| {
            let frame: u64 = q.name.trim_end_matches(".jpg").parse().unwrap();
            1_317_000_000 * SEC + frame * SEC / 10
        })
        .collect()
}

fn joined<T: ToString>(items: impl IntoIterator<Item = T>) -> String {
    items
        .into_iter()
        .map(|v| v.to_string())
        .collect::<Vec<_>>()
        .join(",")
}

/// The node localizes the frames Cyclone publishes as `localize --sequence` localizes the same
/// frames (bit for bit); the publisher leaves after 6 frames and another comes back with the
/// rest, and the node goes on; each pose carries a covariance and the image's stamp.
#[test]
fn frames_a_foreign_dds_publishes_are_localized_as_localize_sequence_does() {
    let s = scene();
    let map = &sfp_map().1;
    let images = s.root.join("images");
    let (_, reference) = localize_json(map, &["--images", path_str(&images)], &["--sequence"]);
    let domain = 41;
    let topic = "/kitti/camera_left/image_raw/compressed";
    let node = node(
        map,
        domain,
        &[
            "--image-topic",
            topic,
            "--camera",
            &s.queries[0].camera,
            "--reliability",
            "reliable",
            "--frames",
            &s.queries.len().to_string(),
            // Warm inference threads change the time, never the poses.
            "--spin",
        ],
    );
    let names: Vec<&str> = s.queries.iter().map(|q| q.name.as_str()).collect();
    let stamps = stamps();
    let run = |range: std::ops::Range<usize>| {
        let (names, stamps) = (&names[range.clone()], &stamps[range]);
        publish("lockstep", domain, (topic, &images), names, stamps, &[])
    };
    // Two publishers, one after the other: the first disappears with its participant.
    let mut frames = run(0..6)["frames"].as_array().unwrap().clone();
    frames.extend(run(6..names.len())["frames"].as_array().unwrap().clone());
    let counts = finished(node, Duration::from_secs(60));
    assert_eq!(counts["received"], 13, "{counts}");
    assert_eq!(counts["localized"], 13, "{counts}");
    for key in ["failed", "dropped", "malformed", "lost", "camera_mismatch"] {
        assert_eq!(counts[key], 0, "{key}: {counts}");
    }
    assert_eq!(counts["latency_ms"]["frames"], 13, "{counts}");
    // The frames tracked are those localize --sequence tracked.
    let tracked = reference.iter().filter(|r| r["path"] == "tracking").count();
    assert_eq!(counts["tracked_latency_ms"]["frames"], tracked, "{counts}");
    // Every stage of every frame was timed; extraction and localization take milliseconds
    // (the histogram's bins are 0.1 ms).
    for stage in ["queued", "decode_extract", "handoff", "localize", "publish"] {
        assert_eq!(
            counts["stages_ms"][stage]["frames"], 13,
            "{stage}: {counts}"
        );
    }
    for stage in ["decode_extract", "localize"] {
        let median = counts["stages_ms"][stage]["median"].as_f64().unwrap();
        assert!(median >= 1.0, "{counts}");
    }

    assert_eq!(frames.len(), reference.len());
    for ((f, r), q) in frames.iter().zip(&reference).zip(&s.queries) {
        assert_eq!(f["name"], r["name"]);
        let pose = &f["pose"];
        assert!(pose.is_object(), "{} has no pose: {f}", q.name);
        assert_eq!(pose["frame_id"], "map");
        let colmap: [f64; 7] = serde_json::from_value(r["cam_from_world"].clone()).unwrap();
        let expected = Pose::from_colmap_array(colmap).unwrap().inverse();
        let position: [f64; 3] = serde_json::from_value(pose["position"].clone()).unwrap();
        let orientation: [f64; 4] = serde_json::from_value(pose["orientation"].clone()).unwrap();
        let t = expected.translation;
        let e = expected.rotation;
        let want = [t.x, t.y, t.z, e.i, e.j, e.k, e.w];
        let got = [position.as_slice(), orientation.as_slice()].concat();
        // Bit for bit: the same computation on the same pose (f64 through CDR and JSON
        // round-trips exactly).
        assert_eq!(got, want, "{}", q.name);
        // As accurate as the reference (it is the reference).
        check_pose(s, q, &Pose::new(e, t).inverse(), "ros2 node");
        // A covariance of the pose: positive definite (Cholesky succeeds), not the unknown
        // one's 10⁶ variances, and a centre's standard deviation under the map's spacing.
        let cov: Vec<f64> = serde_json::from_value(pose["covariance"].clone()).unwrap();
        assert_eq!(cov.len(), 36);
        let m = nalgebra::Matrix6::from_row_slice(&cov);
        assert!(m.cholesky().is_some(), "{}: {cov:?}", q.name);
        for i in 0..3 {
            assert!(cov[i * 7].sqrt() < s.spacing_m, "{}: {cov:?}", q.name);
        }
        // The status says how.
        let status = &f["status"];
        assert_eq!(status["level"], 0, "{status}");
        assert_eq!(status["message"], "localized");
        assert_eq!(status["values"]["path"], r["path"], "{}", q.name);
        assert!(
            status["values"]["inliers"]
                .as_str()
                .unwrap()
                .parse::<u64>()
                .unwrap()
                >= 12
        );
    }
}

/// Malformed messages (a truncated CompressedImage, an empty and an undecodable image,
/// another type under the topic's name, one over the size limit) and a frame of another size
/// are counted and skipped; the camera comes from a CameraInfo topic; the node goes on and
/// localizes the good frames after them.
#[test]
fn malformed_messages_are_counted_and_skipped_and_the_node_goes_on() {
    let s = scene();
    let map = &sfp_map().1;
    let images = s.root.join("images");
    let dir = tempfile::tempdir().unwrap();
    // A frame of half the size: the camera's does not fit it.
    let small = dir.path().join("small.jpg");
    image::open(images.join(&s.queries[0].name))
        .unwrap()
        .resize_exact(620, 188, image::imageops::FilterType::Triangle)
        .save(&small)
        .unwrap();
    std::fs::copy(
        images.join(&s.queries[0].name),
        dir.path().join(&s.queries[0].name),
    )
    .unwrap();
    std::fs::copy(
        images.join(&s.queries[1].name),
        dir.path().join(&s.queries[1].name),
    )
    .unwrap();
    let domain = 42;
    let topic = "/camera/image_raw/compressed";
    let node = node(
        map,
        domain,
        &[
            "--image-topic",
            topic,
            "--camera-info-topic",
            "/camera/camera_info",
            "--reliability",
            "reliable",
            "--max-message-bytes",
            "1MB",
            "--frames",
            "2",
        ],
    );
    let mut info = peer_command(
        "info",
        domain,
        &["--camera", &s.queries[0].camera, "--seconds", "120"],
    )
    .stdout(Stdio::null())
    .spawn()
    .unwrap();
    let stamps = stamps();
    let names = [s.queries[0].name.as_str(), &s.queries[1].name];
    let bad = ["--small", path_str(&small), "--oversize", "2000000"];
    let result = publish(
        "hostile",
        domain,
        (topic, dir.path()),
        &names,
        &stamps[0..2],
        &bad,
    );
    let counts = finished(node, Duration::from_secs(60));
    info.kill().ok();
    info.wait().ok();
    // The good frames after the bad ones were localized.
    for f in result["frames"].as_array().unwrap() {
        assert!(f["pose"].is_object(), "{f}\n{counts}");
    }
    assert_eq!(counts["localized"], 2, "{counts}");
    assert_eq!(counts["too_large"], 1, "{counts}");
    assert_eq!(counts["camera_mismatch"], 1, "{counts}");
    // A truncated message, an empty image and one that does not decode. Another type under
    // the topic's name never reaches the node: DDS matches writers to readers by type name.
    assert_eq!(result["other_type_matched"], false, "{result}");
    assert_eq!(counts["malformed"], 3, "{counts}\n{result}");
    assert_eq!(counts["failed"], 0, "{counts}");
}

/// Frames at KITTI's 10 Hz for 20 s (the 13 query frames looped), best effort as a camera
/// driver publishes: every frame the node took is handled (localized, failed or dropped for
/// a newer one), most are localized, and the node's memory stays flat (the soak, shortened;
/// `benches/ros2_node.sh` runs it for 10 minutes and measures latency).
#[test]
fn a_camera_stream_at_its_frame_rate_keeps_memory_flat() {
    let s = scene();
    let map = &sfp_map().1;
    let images = s.root.join("images");
    let domain = 43;
    let topic = "/camera/image_raw/compressed";
    let node = node(
        map,
        domain,
        &["--image-topic", topic, "--camera", &s.queries[0].camera],
    );
    let pid = node.id();
    let names: Vec<&str> = s.queries.iter().map(|q| q.name.as_str()).collect();
    let mut stream = peer_command(
        "rate",
        domain,
        &[
            "--image-topic",
            topic,
            "--images",
            path_str(&images),
            "--names",
            &joined(&names),
            "--hz",
            "10",
            "--seconds",
            "20",
        ],
    )
    .stdout(Stdio::piped())
    .spawn()
    .unwrap();
    let rss = || rss_kb(pid);
    std::thread::sleep(Duration::from_secs(8));
    let early = rss();
    let out = loop {
        if let Some(status) = stream.try_wait().unwrap() {
            assert!(status.success());
            break stream.wait_with_output().unwrap();
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let late = rss();
    let result: Value = serde_json::from_slice(&out.stdout).unwrap();
    // SIGTERM: the node stops its loop and prints its counts.
    let counts = terminated(node);
    let n = |k: &str| counts[k].as_u64().unwrap();
    assert_eq!(
        n("received"),
        n("localized") + n("failed") + n("dropped") + n("malformed") + n("camera_mismatch"),
        "{counts}"
    );
    assert!(n("received") > 5 + 1, "{counts}");
    assert!(n("localized") >= 100, "{counts}\n{result}");
    assert!(result["poses"].as_u64().unwrap() >= 100, "{result}");
    assert!(
        late <= early + 5 * 1024,
        "RSS grew from {early} kB to {late} kB over 12 s of frames"
    );
}

/// Raw `sensor_msgs/msg/Image` frames (mono8) on one thread with `--tf`: a 0×0 image is
/// counted as malformed; the frames localize (within the bar: Pillow's JPEG decoder gives
/// the grey here, not ours); each pose has its TF `map → ` the image's frame_id at the pose's
/// centre; a burst of frames faster than the node is dropped, not queued; `/diagnostics`
/// carries the counts.
#[test]
fn raw_images_on_one_thread_with_tf_and_a_burst_that_is_dropped() {
    let s = scene();
    let map = &sfp_map().1;
    let images = s.root.join("images");
    let domain = 44;
    let topic = "/camera/image_raw";
    let node = node(
        map,
        domain,
        &[
            "--image-topic",
            topic,
            "--camera",
            &s.queries[0].camera,
            "--reliability",
            "reliable",
            "--threads",
            "1",
            "--tf",
        ],
    );
    let names: Vec<&str> = s.queries.iter().take(5).map(|q| q.name.as_str()).collect();
    let stamps = stamps();
    let result = publish("raw", domain, (topic, &images), &names, &stamps[..5], &[]);
    let counts = terminated(node);
    let n = |k: &str| counts[k].as_u64().unwrap();
    assert_eq!(n("malformed"), 1, "the 0x0 image: {counts}");
    let frames = result["frames"].as_array().unwrap();
    for (f, q) in frames.iter().zip(&s.queries) {
        let pose = &f["pose"];
        let position: [f64; 3] = serde_json::from_value(pose["position"].clone())
            .unwrap_or_else(|_| panic!("{} not localized: {f}", q.name));
        let o: [f64; 4] = serde_json::from_value(pose["orientation"].clone()).unwrap();
        let world_from_cam = Pose::new(
            nalgebra::UnitQuaternion::new_normalize(nalgebra::Quaternion::new(
                o[3], o[0], o[1], o[2],
            )),
            nalgebra::Vector3::from(position),
        );
        check_pose(s, q, &world_from_cam.inverse(), "raw images");
        // Its TF: map -> the image's frame_id, at the pose's centre, with the image's stamp.
        let stamp = f["stamp"].as_u64().unwrap();
        let tf = result["tf"]
            .as_array()
            .unwrap()
            .iter()
            .find(|t| t["stamp"] == serde_json::json!([stamp / SEC, stamp % SEC]))
            .unwrap_or_else(|| panic!("no TF for {}: {}", q.name, result["tf"]));
        assert_eq!(tf["parent"], "map");
        assert_eq!(tf["child"], "kitti/camera_left");
        assert_eq!(tf["translation"], pose["position"]);
    }
    // The burst: more frames than the node can take in the time; the ones replaced while it
    // worked are dropped, and every frame taken is accounted for.
    assert!(n("dropped") >= 1, "{counts}");
    assert_eq!(
        n("received"),
        n("localized") + n("failed") + n("dropped") + n("malformed"),
        "{counts}"
    );
    assert!(
        n("received") + n("lost") >= 5 + 1 + result["burst"].as_u64().unwrap() - 1,
        "{counts}"
    );
    // /diagnostics, once a second: the node's counts.
    let diagnostics = result["diagnostics"].as_array().unwrap();
    let ours = diagnostics
        .iter()
        .filter(|d| d["name"] == "sfpmap_localizer")
        .collect::<Vec<_>>();
    assert!(!ours.is_empty(), "{}", result["diagnostics"]);
    let last = ours.last().unwrap();
    assert!(
        last["values"]["received"]
            .as_str()
            .unwrap()
            .parse::<u64>()
            .unwrap()
            >= 6,
        "{last}"
    );
    assert!(last["values"]["latency_p99_ms"].is_string(), "{last}");
}

/// A process's resident memory, kB (`/proc/PID/status`).
fn rss_kb(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap()
}

/// `--catalog` with `--place`: the node localizes in that place's map, frame by frame with
/// `--no-tracking` (the same poses as `localize` without `--sequence`), its TF child frame
/// from `--camera-frame`; a publisher killed mid-stream (SIGKILL, no goodbye) is followed by
/// another, and the node goes on. A place the catalog does not list, or whose map is not the
/// one the catalog was built from, ends the node at start-up with one line.
#[test]
fn a_catalog_place_untracked_survives_a_publisher_killed_mid_stream() {
    let s = scene();
    let map = &sfp_map().1;
    let images = s.root.join("images");
    let dir = tempfile::tempdir().unwrap();
    let (street, kitti) = (
        dir.path().join("street.sfpm"),
        dir.path().join("kitti.sfpm"),
    );
    // Another place: the map's level 2 alone, whose poses differ from the whole map's.
    let sliced = Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(["slice", path_str(map), "--level", "2", "--short", "--quiet"])
        .args(["-o", path_str(&street)])
        .output()
        .unwrap();
    assert!(
        sliced.status.success(),
        "{}",
        String::from_utf8_lossy(&sliced.stderr)
    );
    std::fs::copy(map, &kitti).unwrap();
    let catalog = dir.path().join("city.sfpc");
    let built = Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(["catalog", "build", path_str(&street), path_str(&kitti)])
        .args(["-o", path_str(&catalog), "--quiet"])
        .output()
        .unwrap();
    assert!(
        built.status.success(),
        "{}",
        String::from_utf8_lossy(&built.stderr)
    );
    let start_fails = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_sfpmap"))
            .args([
                "ros2",
                "--catalog",
                path_str(&catalog),
                "--camera",
                &s.queries[0].camera,
            ])
            .args(["--domain-id", "45", "--interface", "127.0.0.1"])
            .args(args)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(1), "{out:?}");
        let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
        assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
        stderr
    };
    let e = start_fails(&["--place", "nowhere"]);
    assert!(
        e.contains("no place \"nowhere\"") && e.contains("\"kitti\""),
        "{e}"
    );
    let e = start_fails(&[]);
    assert!(e.contains("2 places; choose one with --place"), "{e}");

    let domain = 46;
    let topic = "/camera/image_raw/compressed";
    let (_, reference) = localize_json(map, &["--images", path_str(&images)], &[]);
    let node = node_of(
        &["--catalog", path_str(&catalog), "--place", "kitti"],
        domain,
        &[
            "--image-topic",
            topic,
            "--camera",
            &s.queries[0].camera,
            "--no-tracking",
            "--tf",
            "--camera-frame",
            "cam0",
        ],
    );
    let names: Vec<&str> = s.queries.iter().map(|q| q.name.as_str()).collect();
    let mut killed = peer_command(
        "rate",
        domain,
        &["--image-topic", topic, "--images", path_str(&images)],
    )
    .args(["--names", &joined(&names), "--hz", "10", "--seconds", "60"])
    .stdout(Stdio::null())
    .spawn()
    .unwrap();
    std::thread::sleep(Duration::from_secs(6));
    killed.kill().unwrap(); // SIGKILL: its participant never says goodbye
    killed.wait().unwrap();
    let stamps = stamps();
    let tf = ["--read-tf"];
    let result = publish("lockstep", domain, (topic, &images), &names, &stamps, &tf);
    let counts = terminated(node);
    // Frames of the killed publisher were taken too, and then all 13 of the second.
    assert!(counts["received"].as_u64().unwrap() > 13, "{counts}");
    assert_eq!(counts["failed"], 0, "{counts}");
    // Untracked: every frame retrieves, and its pose is localize's without --sequence.
    assert_eq!(counts["tracked_latency_ms"]["frames"], 0, "{counts}");
    let frames = result["frames"].as_array().unwrap();
    assert_eq!(frames.len(), reference.len());
    let tf = result["tf"].as_array().unwrap();
    for ((f, r), q) in frames.iter().zip(&reference).zip(&s.queries) {
        let pose = &f["pose"];
        assert!(pose.is_object(), "{} has no pose: {f}", q.name);
        assert_eq!(f["status"]["values"]["path"], "retrieval", "{f}");
        let colmap: [f64; 7] = serde_json::from_value(r["cam_from_world"].clone()).unwrap();
        let expected = Pose::from_colmap_array(colmap).unwrap().inverse();
        let position: [f64; 3] = serde_json::from_value(pose["position"].clone()).unwrap();
        let t = expected.translation;
        assert_eq!(position, [t.x, t.y, t.z], "{}", q.name);
        let stamp = f["stamp"].as_u64().unwrap();
        let transform = tf
            .iter()
            .find(|t| t["stamp"] == serde_json::json!([stamp / SEC, stamp % SEC]))
            .unwrap_or_else(|| panic!("no TF for {}: {tf:?}", q.name));
        assert_eq!(transform["parent"], "map");
        assert_eq!(transform["child"], "cam0");
        assert_eq!(transform["translation"], pose["position"]);
    }

    // A place's map replaced since the catalog was built is refused, naming it.
    let sliced = Command::new(env!("CARGO_BIN_EXE_sfpmap"))
        .args(["slice", path_str(map), "--level", "2", "--short", "--force"])
        .args(["-o", path_str(&kitti), "--quiet"])
        .output()
        .unwrap();
    assert!(
        sliced.status.success(),
        "{}",
        String::from_utf8_lossy(&sliced.stderr)
    );
    let e = start_fails(&["--place", "kitti"]);
    assert!(
        e.contains("kitti.sfpm") && e.contains("not the map the catalog was built from"),
        "{e}"
    );
}
