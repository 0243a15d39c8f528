//! Hostile and careless input to the COLMAP readers, the text exporters and `plot` (issue 12,
//! findings 7, 16 and 18 and the plot / export message rough edges): non-finite numbers in
//! models and databases, image names that would inject lines, maps whose coordinates a plot
//! cannot show, and model files or databases that are not regular files. Each is refused
//! with one line naming the file (and the record), or handled, in bounded time.
#![cfg(feature = "colmap")]

use crate::common;

use common::{run_limited, Limited};
use rusqlite::{params, Connection};
use sfpmap::colmap::{bin, text, Camera, Image, Point2D, Reconstruction, TrackElement};
use sfpmap::format::{CameraInfo, MapWriter};
use sfpmap::geometry::{CameraModel, Pose};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Generous: the debug binary needs well under this for the small inputs here.
const MEMORY: u64 = 1 << 30;
/// Generous too: every case takes well under a second once fixed; a hang is killed here.
const TIMEOUT: Duration = Duration::from_secs(60);

fn sfpmap<S: AsRef<OsStr>>(args: &[S]) -> Limited {
    let args: Vec<&OsStr> = args.iter().map(|a| a.as_ref()).collect();
    run_limited(env!("CARGO_BIN_EXE_sfpmap"), &args, MEMORY, TIMEOUT)
}

/// Exit 1 and one line `error: ...` that contains every string in `says`, and no Debug
/// dump (`{`, `Os {`, quoted struct fields).
fn assert_refused(out: &Limited, says: &[&str]) {
    assert!(!out.timed_out, "ran past {TIMEOUT:?}: {out:?}");
    assert_eq!(out.code, Some(1), "{out:?}");
    let line = out.stderr.trim_end();
    assert!(!line.contains('\n'), "more than one line: {line}");
    assert!(line.starts_with("error: "), "{line}");
    assert!(!line.contains('{'), "a Debug dump: {line}");
    for s in says {
        assert!(line.contains(s), "{line:?} does not say {s:?}");
    }
}

// ---------------------------------------------------------------------------------------
// A small consistent model with distinctive values that tests replace by non-finite ones.

/// Camera 1's focal length.
const FOCAL: f64 = 777.25;
/// Image 2's tx.
const TX: f64 = 4242.5;
/// Point 7's x.
const POINT_X: f64 = 12345.5;
/// Point 7's mean reprojection error.
const POINT_ERROR: f64 = 0.75;

/// Camera 1, images 1 and 2 (names given), points 7 and 8 seen by both.
fn model_named(names: [&str; 2]) -> Reconstruction {
    let mut b = Reconstruction::builder();
    b.add_camera(Camera {
        id: 1,
        model: CameraModel::SimplePinhole,
        width: 640,
        height: 480,
        params: vec![FOCAL, 320.0, 240.0],
    });
    for (i, name) in (1..=2u32).zip(names) {
        b.add_image(Image {
            id: i,
            name: name.to_string(),
            camera_id: 1,
            cam_from_world: Pose::from_colmap_array([
                1.0,
                0.0,
                0.0,
                0.0,
                if i == 2 { TX } else { 0.5 },
                0.0,
                0.0,
            ])
            .unwrap(),
            points2d: vec![
                Point2D {
                    xy: [10.0, 20.0],
                    point3d_id: Some(7),
                },
                Point2D {
                    xy: [30.0, 40.0],
                    point3d_id: Some(8),
                },
            ],
        });
    }
    for (id, idx, x, error) in [(7u64, 0u32, POINT_X, POINT_ERROR), (8, 1, 1.5, 0.5)] {
        let track = [1, 2].map(|image_id| TrackElement {
            image_id,
            point2d_idx: idx,
        });
        b.add_point3d(id, [x, 2.0, 3.0], [1, 2, 3], error, &track)
            .unwrap();
    }
    b.build().unwrap()
}

fn model() -> Reconstruction {
    model_named(["a.jpg", "b.jpg"])
}

/// The model's files, binary or text, in a folder `model` under `tmp`.
fn write_model(tmp: &Path, binary: bool) -> PathBuf {
    let dir = tmp.join("model");
    std::fs::create_dir_all(&dir).unwrap();
    for (name, bytes) in model_files(&model(), binary) {
        std::fs::write(dir.join(name), bytes).unwrap();
    }
    dir
}

/// The model's three files as (name, bytes), binary or text.
fn model_files(model: &Reconstruction, binary: bool) -> [(&'static str, Vec<u8>); 3] {
    if binary {
        [
            ("cameras.bin", bin::write_cameras(model)),
            ("images.bin", bin::write_images(model)),
            ("points3D.bin", bin::write_points3d(model)),
        ]
    } else {
        [
            ("cameras.txt", text::write_cameras(model).into_bytes()),
            ("images.txt", text::write_images(model).into_bytes()),
            ("points3D.txt", text::write_points3d(model).into_bytes()),
        ]
    }
}

/// `bytes` with the one occurrence of `from` replaced by `to`.
fn replace_once(bytes: &[u8], from: &[u8], to: &[u8]) -> Vec<u8> {
    let found: Vec<usize> = (0..=bytes.len().saturating_sub(from.len()))
        .filter(|&i| bytes[i..].starts_with(from))
        .collect();
    assert_eq!(found.len(), 1, "{:?} occurs {} times", from, found.len());
    let at = found[0];
    [&bytes[..at], to, &bytes[at + from.len()..]].concat()
}

/// Writes `files` into `dir/model`, with `file`'s occurrence of `value` replaced by `bad`
/// (f64 bytes for binary files, text for text files).
fn write_with(
    dir: &Path,
    files: [(&str, Vec<u8>); 3],
    file: &str,
    value: f64,
    bad: &str,
) -> PathBuf {
    let model_dir = dir.join("model");
    std::fs::create_dir_all(&model_dir).unwrap();
    for (name, bytes) in files {
        let bytes = if name != file {
            bytes
        } else if name.ends_with(".bin") {
            let bad: f64 = bad.parse().unwrap();
            replace_once(&bytes, &value.to_le_bytes(), &bad.to_le_bytes())
        } else {
            let from = format!(" {value} ");
            replace_once(&bytes, from.as_bytes(), format!(" {bad} ").as_bytes())
        };
        std::fs::write(model_dir.join(name), bytes).unwrap();
    }
    model_dir
}

/// `convert` of the model with `value` in `stem.{bin,txt}` replaced by each non-finite
/// spelling exits 1 with one line naming the file and `record`, and writes no map.
fn assert_convert_refuses(stem: &str, value: f64, record: &str) {
    for binary in [true, false] {
        let ext = if binary { "bin" } else { "txt" };
        // "1e400" is how a text model says inf without saying it: it overflows.
        for bad in ["NaN", "inf", "-inf", "1e400"] {
            let tmp = tempfile::tempdir().unwrap();
            let file = format!("{stem}.{ext}");
            let dir = write_with(tmp.path(), model_files(&model(), binary), &file, value, bad);
            let out_map = tmp.path().join("out.sfpm");
            let out = sfpmap(&[
                OsStr::new("convert"),
                OsStr::new("--colmap"),
                dir.as_os_str(),
                OsStr::new("-o"),
                out_map.as_os_str(),
            ]);
            let path = dir.join(&file);
            assert_refused(&out, &[&path.display().to_string(), record, "not finite"]);
            assert!(!out_map.exists(), "{file} with {bad}: a map was written");
        }
    }
}

/// The unmodified model converts (so the refusals below are about the one value).
#[test]
fn the_model_converts_as_made() {
    for binary in [true, false] {
        let tmp = tempfile::tempdir().unwrap();
        let dir = write_model(tmp.path(), binary);
        let out_map = tmp.path().join("out.sfpm");
        let out = sfpmap(&[
            OsStr::new("convert"),
            OsStr::new("--colmap"),
            dir.as_os_str(),
            OsStr::new("-o"),
            out_map.as_os_str(),
        ]);
        assert_eq!(out.code, Some(0), "{out:?}");
        let verify = sfpmap(&[OsStr::new("verify"), out_map.as_os_str()]);
        assert_eq!(verify.code, Some(0), "{verify:?}");
    }
}

/// Finding 16: NaN or inf in a camera's parameters became JSON `null` in the metadata.
#[test]
fn convert_refuses_non_finite_camera_parameters() {
    assert_convert_refuses("cameras", FOCAL, "camera 1");
}

/// Finding 16: a non-finite point position made the map's origin `null`.
#[test]
fn convert_refuses_non_finite_point_positions() {
    assert_convert_refuses("points3D", POINT_X, "point3D 7");
}

/// Finding 16: a non-finite pose went into the map's poses.
#[test]
fn convert_refuses_non_finite_poses() {
    assert_convert_refuses("images", TX, "image 2");
}

/// Finding 16, through the library: the general reader and convert's fast binary path
/// refuse the same models (the fast path declines, the reader names the problem).
#[test]
fn readers_refuse_non_finite_values_in_every_field() {
    use sfpmap::colmap::read_model;
    let cases: [(&str, f64, &str); 3] = [
        ("cameras", FOCAL, "camera 1"),
        ("images", TX, "image 2"),
        ("points3D", POINT_X, "point3D 7"),
    ];
    for (stem, value, record) in cases {
        for ext in ["bin", "txt"] {
            let tmp = tempfile::tempdir().unwrap();
            let file = format!("{stem}.{ext}");
            let files = model_files(&model(), ext == "bin");
            let dir = write_with(tmp.path(), files, &file, value, "NaN");
            let err = read_model(&dir).expect_err(&file).to_string();
            assert!(
                err.contains(&file) && err.contains(record) && err.contains("not finite"),
                "{file}: {err}"
            );
        }
    }
}

/// A 2D point's pixel coordinates and a point's error are numbers too.
#[test]
fn readers_refuse_non_finite_point2d_coordinates_and_errors() {
    use sfpmap::colmap::read_model;
    for binary in [true, false] {
        let tmp = tempfile::tempdir().unwrap();
        // 30.0 is the x of point2D 1 in both images: change the second image's.
        let files = model_files(&model(), binary);
        let (file, to) = if binary {
            let images = files[1].1.clone();
            let needle = 30.0f64.to_le_bytes();
            let last = images
                .windows(8)
                .rposition(|w| w == needle)
                .expect("x of point2D 1");
            let mut patched = images;
            patched[last..last + 8].copy_from_slice(&f64::NAN.to_le_bytes());
            ("images.bin", patched)
        } else {
            let images = String::from_utf8(files[1].1.clone()).unwrap();
            let at = images.rfind("30 40 8").expect("point2D 1");
            let patched = format!("{}nan 40 8{}", &images[..at], &images[at + 7..]);
            ("images.txt", patched.into_bytes())
        };
        let dir = tmp.path().join("model");
        std::fs::create_dir_all(&dir).unwrap();
        for (name, bytes) in files {
            let bytes = if name == file { to.clone() } else { bytes };
            std::fs::write(dir.join(name), bytes).unwrap();
        }
        let err = read_model(&dir).expect_err(file).to_string();
        assert!(
            err.contains(file) && err.contains("image 2") && err.contains("not finite"),
            "{err}"
        );

        let tmp = tempfile::tempdir().unwrap();
        let points = format!("points3D.{}", if binary { "bin" } else { "txt" });
        let dir = write_with(
            tmp.path(),
            model_files(&model(), binary),
            &points,
            POINT_ERROR,
            "inf",
        );
        let err = read_model(&dir).expect_err(&points).to_string();
        assert!(
            err.contains(&points) && err.contains("point3D") && err.contains("not finite"),
            "{err}"
        );
    }
}

// ---------------------------------------------------------------------------------------
// Databases.

/// A database for [`model`] with 4-column keypoints (x, y, scale, orientation); the scale
/// of image 2's keypoint 1 is `scale`.
fn write_database(path: &Path, scale: f32) {
    let db = Connection::open(path).unwrap();
    common::colmap_schema(&db);
    let params: Vec<u8> = [FOCAL, 320.0, 240.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    db.execute(
        "INSERT INTO cameras VALUES (1, 0, 640, 480, ?1, 0)",
        params![params],
    )
    .unwrap();
    for (i, name) in [(1u32, "a.jpg"), (2, "b.jpg")] {
        db.execute("INSERT INTO images VALUES (?1, ?2, 1)", params![i, name])
            .unwrap();
        let mut kp = Vec::new();
        for (j, [x, y]) in [[10.0f32, 20.0], [30.0, 40.0]].into_iter().enumerate() {
            let s = if i == 2 && j == 1 { scale } else { 2.0 };
            for v in [x, y, s, 0.0] {
                kp.extend_from_slice(&v.to_le_bytes());
            }
        }
        let desc: Vec<u8> = (0..2 * 128).map(|k| (k * 7 % 251) as u8).collect();
        db.execute(
            "INSERT INTO keypoints VALUES (?1, 2, 4, ?2)",
            params![i, kp],
        )
        .unwrap();
        db.execute(
            "INSERT INTO descriptors VALUES (?1, 2, 128, ?2)",
            params![i, desc],
        )
        .unwrap();
    }
}

/// Issue 35: `--memory` below what converting the model needs is refused before the
/// database's descriptors are read through, in one line naming the model and the smallest
/// budget that works; that budget converts, to the same bytes as the default one, and the
/// scratch files are gone after (named ones, `SFPMAP_NO_TMPFILE`: an unnamed one has no name
/// to leave).
#[test]
fn a_memory_budget_too_small_is_refused_naming_the_smallest_that_works() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = write_model(tmp.path(), true);
    let db = tmp.path().join("database.db");
    write_database(&db, 3.0);
    let convert = |out: &Path, memory: Option<&str>| {
        let mut args = vec![
            OsStr::new("SFPMAP_NO_TMPFILE=1"),
            OsStr::new(env!("CARGO_BIN_EXE_sfpmap")),
            OsStr::new("convert"),
            OsStr::new("--colmap"),
            dir.as_os_str(),
            OsStr::new("--database"),
            db.as_os_str(),
            OsStr::new("--json"),
            OsStr::new("-o"),
            out.as_os_str(),
        ];
        if let Some(m) = memory {
            args.extend([OsStr::new("--memory"), OsStr::new(m)]);
        }
        run_limited("env", &args, MEMORY, TIMEOUT)
    };
    let small = tmp.path().join("small.sfpm");
    let out = convert(&small, Some("1MB"));
    let model = dir.display().to_string();
    assert_refused(
        &out,
        &[
            &model,
            "a memory budget of 1 MB is too small",
            "needs at least",
        ],
    );
    assert!(!small.exists());
    let needed: u64 = out
        .stderr
        .split("needs at least ")
        .nth(1)
        .and_then(|rest| rest.split(" MB").next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no smallest budget in {:?}", out.stderr));
    let out = convert(&small, Some(&format!("{needed}MB")));
    assert_eq!(out.code, Some(0), "{out:?}");
    let report: serde_json::Value = serde_json::from_str(&out.stdout).unwrap();
    assert_eq!(report["memory"]["budget"], needed * 1_000_000, "{report}");
    // The smallest that works, to the megabyte shown.
    let planned = report["memory"]["planned_peak"].as_u64().unwrap();
    assert!(
        planned > (needed - 1) * 1_000_000,
        "{planned} planned, {needed} MB needed"
    );
    let default = tmp.path().join("default.sfpm");
    assert_eq!(convert(&default, None).code, Some(0));
    assert_eq!(
        std::fs::read(&small).unwrap(),
        std::fs::read(&default).unwrap()
    );
    // The scratch files are gone with the process: the folder holds the maps, the model, the
    // database.
    let mut names: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["database.db", "default.sfpm", "model", "small.sfpm"]
    );
}

/// Finding 16: a database keypoint's scale feeds the level assignment; a NaN one silently
/// dropped the point from every level.
#[test]
fn convert_refuses_non_finite_keypoint_scales() {
    for scale in [3.0, f32::NAN, f32::INFINITY] {
        let tmp = tempfile::tempdir().unwrap();
        let dir = write_model(tmp.path(), true);
        let db = tmp.path().join("database.db");
        write_database(&db, scale);
        let out_map = tmp.path().join("out.sfpm");
        let out = sfpmap(&[
            OsStr::new("convert"),
            OsStr::new("--colmap"),
            dir.as_os_str(),
            OsStr::new("--database"),
            db.as_os_str(),
            OsStr::new("-o"),
            out_map.as_os_str(),
        ]);
        if scale.is_finite() {
            assert_eq!(out.code, Some(0), "{out:?}");
            continue;
        }
        assert_refused(
            &out,
            &[
                &db.display().to_string(),
                "b.jpg",
                "keypoint 1",
                "not finite",
            ],
        );
        assert!(!out_map.exists());
    }
}

// ---------------------------------------------------------------------------------------
// Not regular files.

#[cfg(unix)]
fn mkfifo(path: &Path) {
    let status = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .unwrap();
    assert!(status.success());
}

/// A FIFO or a folder where a model file should be is refused at once, naming it (a FIFO
/// used to block `open` until a writer came; a folder was reported "missing").
#[cfg(unix)]
#[test]
fn a_model_file_that_is_not_a_regular_file_is_refused() {
    for (binary, stem) in [(true, "cameras"), (true, "points3D"), (false, "images")] {
        for kind in ["FIFO", "folder"] {
            let tmp = tempfile::tempdir().unwrap();
            let dir = tmp.path().join("model");
            std::fs::create_dir_all(&dir).unwrap();
            let ext = if binary { "bin" } else { "txt" };
            let target = dir.join(format!("{stem}.{ext}"));
            for (name, bytes) in model_files(&model(), binary) {
                if dir.join(name) != target {
                    std::fs::write(dir.join(name), bytes).unwrap();
                }
            }
            if kind == "FIFO" {
                mkfifo(&target);
            } else {
                std::fs::create_dir(&target).unwrap();
            }
            let out_map = tmp.path().join("out.sfpm");
            let out = sfpmap(&[
                OsStr::new("convert"),
                OsStr::new("--colmap"),
                dir.as_os_str(),
                OsStr::new("-o"),
                out_map.as_os_str(),
            ]);
            let what = if kind == "FIFO" { "a FIFO" } else { "a folder" };
            assert_refused(
                &out,
                &[&target.display().to_string(), what, "not a regular file"],
            );
            let err = sfpmap::colmap::read_model(&dir).unwrap_err().to_string();
            assert!(err.contains("not a regular file"), "{err}");
        }
    }
}

/// A FIFO or a folder given as --database is refused at once (the FIFO blocked in open).
#[cfg(unix)]
#[test]
fn a_database_that_is_not_a_regular_file_is_refused() {
    for kind in ["FIFO", "folder"] {
        let tmp = tempfile::tempdir().unwrap();
        let dir = write_model(tmp.path(), true);
        let db = tmp.path().join("database.db");
        if kind == "FIFO" {
            mkfifo(&db);
        } else {
            std::fs::create_dir(&db).unwrap();
        }
        let out_map = tmp.path().join("out.sfpm");
        let out = sfpmap(&[
            OsStr::new("convert"),
            OsStr::new("--colmap"),
            dir.as_os_str(),
            OsStr::new("--database"),
            db.as_os_str(),
            OsStr::new("-o"),
            out_map.as_os_str(),
        ]);
        let what = if kind == "FIFO" { "a FIFO" } else { "a folder" };
        assert_refused(
            &out,
            &[&db.display().to_string(), what, "not a regular file"],
        );
        assert!(!out_map.exists());
        let err = sfpmap::colmap::Database::open(&db).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
    }
}

// ---------------------------------------------------------------------------------------
// Image names (finding 18).

/// A binary model whose image name holds a newline (or another control character) is
/// refused at read: no COLMAP text file can hold it, and it would inject lines into every
/// line-based export of the map.
#[test]
fn image_names_with_control_characters_are_refused_at_read() {
    for name in [
        "a\nb.jpg",
        "a\rb.jpg",
        "a\tb.jpg",
        "a\u{1b}[2Jb.jpg",
        "a\u{7f}.jpg",
    ] {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("model");
        std::fs::create_dir_all(&dir).unwrap();
        // The builder refuses such a name too, so write a clean one and patch the bytes.
        let placeholder = "X".repeat(name.len());
        for (file, bytes) in model_files(&model_named([placeholder.as_str(), "b.jpg"]), true) {
            let bytes = if file == "images.bin" {
                replace_once(&bytes, placeholder.as_bytes(), name.as_bytes())
            } else {
                bytes
            };
            std::fs::write(dir.join(file), bytes).unwrap();
        }
        let out_map = tmp.path().join("out.sfpm");
        let out = sfpmap(&[
            OsStr::new("convert"),
            OsStr::new("--colmap"),
            dir.as_os_str(),
            OsStr::new("-o"),
            out_map.as_os_str(),
        ]);
        let images = dir.join("images.bin");
        assert_refused(
            &out,
            &[
                &images.display().to_string(),
                "image 1",
                "control character",
            ],
        );
        assert!(!out_map.exists());
    }
    // Hand-built reconstructions cannot hold one either.
    let mut b = Reconstruction::builder();
    b.add_camera(Camera {
        id: 1,
        model: CameraModel::SimplePinhole,
        width: 1,
        height: 1,
        params: vec![1.0, 0.5, 0.5],
    });
    b.add_image(Image {
        id: 3,
        name: "x\ny".into(),
        camera_id: 1,
        cam_from_world: Pose::from_colmap_array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).unwrap(),
        points2d: Vec::new(),
    });
    let err = b.build().unwrap_err().to_string();
    assert!(
        err.contains("image 3") && err.contains("control character"),
        "{err}"
    );
}

/// A map whose image 2 is named `name` (maps hold any UTF-8 name), with one camera, two
/// points seen by both images, written to `path`.
fn write_map_with_names(path: &Path, names: [&str; 2]) {
    let names: Vec<String> = names.iter().map(|n| n.to_string()).collect();
    let positions = [[0.0, 0.0, 5.0], [1.0, 0.5, 6.0]];
    let poses = [
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0],
    ];
    let mut w = MapWriter::default();
    w.add_camera(CameraInfo {
        id: Some(1),
        model: "SIMPLE_PINHOLE".into(),
        width: 640,
        height: 480,
        params: vec![500.0, 320.0, 240.0],
    });
    w.set_points_world(&positions);
    w.set_images(&names, &[0, 0], &poses, Some(&[1, 2]))
        .unwrap();
    let offsets = [0u64, 2, 4];
    let points = [0u32, 1, 0, 1];
    let keypoints = [[10.0f32, 20.0], [30.0, 40.0], [11.0, 21.0], [31.0, 41.0]];
    w.set_visibility(&offsets, &points, Some(&keypoints))
        .unwrap();
    std::fs::write(path, w.to_bytes().unwrap()).unwrap();
}

/// Finding 18: `images.txt` (export --images-txt, export-colmap) refuses a name it cannot
/// hold, naming the map and the image; nothing is written. COLMAP reads a name up to the
/// first space and a line up to its newline, so whitespace is refused as well.
#[test]
fn images_txt_exports_refuse_names_they_cannot_hold() {
    for name in [
        "x.jpg\n9 1 0 0 0 0 0 0 1 injected.jpg",
        "a\tb.jpg",
        "two words.jpg",
        "\u{1b}]0;t\u{7}",
    ] {
        let tmp = tempfile::tempdir().unwrap();
        let map = tmp.path().join("names.sfpm");
        write_map_with_names(&map, ["a.jpg", name]);
        let map_s = map.display().to_string();
        let txt = tmp.path().join("images.txt");
        let out = sfpmap(&[
            OsStr::new("export"),
            map.as_os_str(),
            OsStr::new("--images-txt"),
            txt.as_os_str(),
        ]);
        assert_refused(&out, &[&map_s, "image 2", "name"]);
        assert!(!txt.exists(), "{name:?}: images.txt written");
        let colmap = tmp.path().join("colmap");
        let out = sfpmap(&[
            OsStr::new("export-colmap"),
            map.as_os_str(),
            OsStr::new("-o"),
            colmap.as_os_str(),
        ]);
        assert_refused(&out, &[&map_s, "image 2", "name"]);
        assert!(!colmap.join("images.txt").exists(), "{name:?}");
    }
    // A clean name still exports, and reads back as a model.
    let tmp = tempfile::tempdir().unwrap();
    let map = tmp.path().join("clean.sfpm");
    write_map_with_names(&map, ["a.jpg", "sub/b-1.jpg"]);
    let colmap = tmp.path().join("colmap");
    let out = sfpmap(&[
        OsStr::new("export-colmap"),
        map.as_os_str(),
        OsStr::new("-o"),
        colmap.as_os_str(),
    ]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let model = sfpmap::colmap::read_model(&colmap).unwrap();
    assert_eq!(model.images()[1].name, "sub/b-1.jpg");
}

/// Finding 18: the TUM export names images only in a comment; a control character there is
/// escaped, so the file keeps one comment line per header and one row per image.
#[test]
fn tum_export_escapes_control_characters_in_names() {
    let tmp = tempfile::tempdir().unwrap();
    let map = tmp.path().join("names.sfpm");
    write_map_with_names(&map, ["a.jpg", "x\n9 1 2 3 0 0 0 1\r"]);
    let tum = tmp.path().join("poses.tum");
    let out = sfpmap(&[
        OsStr::new("export"),
        map.as_os_str(),
        OsStr::new("--tum"),
        tum.as_os_str(),
    ]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let text = std::fs::read_to_string(&tum).unwrap();
    assert!(!text.contains('\r'), "{text:?}");
    let rows: Vec<&str> = text.lines().filter(|l| !l.starts_with('#')).collect();
    assert_eq!(rows.len(), 2, "{text:?}");
    for row in rows {
        assert_eq!(row.split(' ').count(), 8, "{row:?}");
    }
    assert!(text.contains("x\\n9 1 2 3 0 0 0 1\\r"), "{text:?}");
}

// ---------------------------------------------------------------------------------------
// plot (finding 7) and its messages.

/// A map of `relative` positions (f32, relative to `origin`) and, if given, camera poses
/// (cam_from_world), written to `path`. Points only: crafted (so any value can be stored);
/// with poses: through the writer, and `false` if it refuses them (then nothing to test).
fn write_map_at(path: &Path, origin: [f64; 3], relative: &[[f32; 3]], poses: &[[f64; 7]]) -> bool {
    if poses.is_empty() {
        let mut metadata = common::craft_metadata(Vec::new());
        metadata["origin"] = serde_json::json!(origin);
        let bytes: Vec<u8> = relative
            .iter()
            .flatten()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let positions = common::Crafted::raw(
            sfpmap::format::SectionKind::PointPositions,
            sfpmap::fuzzing::NO_LEVEL,
            sfpmap::format::Dtype::F32,
            relative.len() as u64,
            3,
            bytes,
        );
        std::fs::write(path, common::craft(&metadata, &[positions])).unwrap();
        return true;
    }
    let names: Vec<String> = (0..poses.len()).map(|i| format!("{i}.jpg")).collect();
    let cameras = vec![0; poses.len()];
    let mut w = MapWriter::default();
    w.metadata_mut().origin = origin;
    w.set_points(relative);
    w.add_camera(CameraInfo {
        id: Some(1),
        model: "SIMPLE_PINHOLE".into(),
        width: 640,
        height: 480,
        params: vec![500.0, 320.0, 240.0],
    });
    let written = w
        .set_images(&names, &cameras, poses, None)
        .and_then(|w| w.to_bytes());
    match written {
        Ok(bytes) => {
            std::fs::write(path, bytes).unwrap();
            true
        }
        Err(e) => {
            eprintln!("the writer refuses it ({e}): skipped");
            false
        }
    }
}

fn plot(map: &Path, png: &Path) -> Limited {
    sfpmap(&[
        OsStr::new("plot"),
        map.as_os_str(),
        OsStr::new("-o"),
        png.as_os_str(),
        OsStr::new("--width"),
        OsStr::new("320"),
        OsStr::new("--height"),
        OsStr::new("240"),
    ])
}

/// Exit 0 with a PNG, or exit 1 with one line naming the map or the PNG; never hung.
fn assert_plot_bounded(out: &Limited, map: &Path, png: &Path, what: &str) {
    assert!(!out.timed_out, "{what}: ran past {TIMEOUT:?}: {out:?}");
    match out.code {
        Some(0) => assert!(png.is_file(), "{what}: no PNG"),
        Some(1) => {
            let line = out.stderr.trim_end();
            assert!(
                line.starts_with("error: ") && !line.contains('\n') && !line.contains('{'),
                "{what}: {line}"
            );
            let (m, p) = (map.display().to_string(), png.display().to_string());
            assert!(line.contains(&m) || line.contains(&p), "{what}: {line}");
        }
        _ => panic!("{what}: killed or crashed: {out:?}"),
    }
}

/// Finding 7: `plot` never returned on a map whose origin is 1.7e308 (plotters' key-point
/// loop never ends on a range it cannot resolve). Now it plots in map-local coordinates.
#[test]
fn plot_of_a_map_at_1e308_returns() {
    let tmp = tempfile::tempdir().unwrap();
    let map = tmp.path().join("far.sfpm");
    let relative = [[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-1.0, 0.5, 2.0]];
    assert!(write_map_at(&map, [1.7e308; 3], &relative, &[]));
    let png = tmp.path().join("far.png");
    let out = plot(&map, &png);
    assert!(!out.timed_out, "ran past {TIMEOUT:?}: {out:?}");
    assert_eq!(out.code, Some(0), "{out:?}");
    assert!(png.is_file());
}

/// A plot case: what it is, the map's origin, stored positions and camera poses.
type PlotCase = (&'static str, [f64; 3], Vec<[f32; 3]>, Vec<[f64; 7]>);

/// Other maps a plot may choke on: cameras 1e308 away from the points, points all at one
/// spot, no points, NaN positions, coordinates spanning all of f64, tiny extents far out.
#[test]
fn plot_of_degenerate_maps_returns() {
    let identity = |tx: f64| [1.0, 0.0, 0.0, 0.0, tx, 0.0, 0.0];
    let cases: Vec<PlotCase> = vec![
        (
            "cameras far from the points",
            [1.7e308, 0.0, 1.7e308],
            vec![[0.0; 3]; 3],
            vec![identity(0.0), identity(1.0)],
        ),
        (
            "cameras at both ends of f64",
            [0.0; 3],
            vec![[0.0; 3]],
            vec![identity(1.7e308), identity(-1.7e308)],
        ),
        ("one spot", [5.0, 5.0, 5.0], vec![[0.0; 3]; 10], Vec::new()),
        (
            "one spot far out",
            [1e300, -1e300, 1e300],
            vec![[0.0; 3]; 10],
            Vec::new(),
        ),
        ("no points", [0.0; 3], Vec::new(), Vec::new()),
        (
            "no points, one camera",
            [0.0; 3],
            Vec::new(),
            vec![identity(3.0)],
        ),
        (
            "NaN positions",
            [0.0; 3],
            vec![[f32::NAN; 3], [1.0, 2.0, 3.0], [f32::NAN, 0.0, 1.0]],
            Vec::new(),
        ),
        (
            "only NaN positions",
            [0.0; 3],
            vec![[f32::NAN; 3]; 4],
            Vec::new(),
        ),
        (
            "infinite positions",
            [0.0; 3],
            vec![
                [f32::INFINITY, 0.0, 0.0],
                [1.0, 2.0, 3.0],
                [0.0, f32::NEG_INFINITY, 1.0],
            ],
            Vec::new(),
        ),
        (
            "huge extent",
            [0.0; 3],
            vec![
                [f32::MAX, f32::MAX, f32::MAX],
                [-f32::MAX, -f32::MAX, -f32::MAX],
            ],
            Vec::new(),
        ),
        (
            "tiny extent far out",
            [1e15, 1e15, 1e15],
            vec![[0.0; 3], [1e-3, 1e-3, 1e-3]],
            Vec::new(),
        ),
        (
            "NaN pose",
            [0.0; 3],
            vec![[1.0, 2.0, 3.0]; 2],
            vec![[f64::NAN; 7], identity(1.0)],
        ),
        (
            "zero quaternion",
            [0.0; 3],
            vec![[1.0, 2.0, 3.0]; 2],
            vec![[0.0; 7], identity(1.0)],
        ),
    ];
    for (what, origin, relative, poses) in cases {
        let tmp = tempfile::tempdir().unwrap();
        let map = tmp.path().join("map.sfpm");
        if !write_map_at(&map, origin, &relative, &poses) {
            continue;
        }
        let png = tmp.path().join("map.png");
        let out = plot(&map, &png);
        assert_plot_bounded(&out, &map, &png, what);
    }
}

/// `plot` errors are one line naming the file, never plotters' Debug dump.
#[test]
fn plot_errors_are_one_line_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let map = tmp.path().join("map.sfpm");
    assert!(write_map_at(
        &map,
        [0.0; 3],
        &[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]],
        &[]
    ));
    // The PNG's folder does not exist.
    let png = tmp.path().join("missing").join("map.png");
    let out = plot(&map, &png);
    assert_refused(&out, &[&png.display().to_string()]);
    // The map has nothing to plot.
    let empty = tmp.path().join("empty.sfpm");
    assert!(write_map_at(&empty, [0.0; 3], &[], &[]));
    let out = plot(&empty, &tmp.path().join("empty.png"));
    assert_refused(&out, &[&empty.display().to_string(), "nothing to plot"]);
    // Poses that are not poses.
    let poses = tmp.path().join("poses.txt");
    std::fs::write(&poses, "q1 1 0 0\n").unwrap();
    let out = sfpmap(&[
        OsStr::new("plot"),
        map.as_os_str(),
        OsStr::new("--poses"),
        poses.as_os_str(),
        OsStr::new("-o"),
        tmp.path().join("p.png").as_os_str(),
    ]);
    assert_refused(&out, &[&poses.display().to_string()]);
}

// ---------------------------------------------------------------------------------------
// export --ply messages.

/// `export --ply` errors about the map name the map (a damaged section's error said only
/// `point_positions: ...`).
#[test]
fn export_ply_errors_name_the_map() {
    let tmp = tempfile::tempdir().unwrap();
    let map = tmp.path().join("map.sfpm");
    assert!(write_map_at(
        &map,
        [0.0; 3],
        &[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]],
        &[]
    ));
    // Flip a byte of the positions (the last bytes of the file), which open does not hash.
    let mut bytes = std::fs::read(&map).unwrap();
    let map_len = bytes.len();
    let positions = [1.0f32, 2.0, 3.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect::<Vec<u8>>();
    let at = bytes
        .windows(12)
        .position(|w| w == positions.as_slice())
        .expect("positions");
    bytes[at] ^= 1;
    assert_eq!(bytes.len(), map_len);
    std::fs::write(&map, &bytes).unwrap();
    let ply = tmp.path().join("out.ply");
    let out = sfpmap(&[
        OsStr::new("export"),
        map.as_os_str(),
        OsStr::new("--ply"),
        ply.as_os_str(),
    ]);
    assert_refused(&out, &[&map.display().to_string()]);
    assert!(!ply.exists());
}

// ---------------------------------------------------------------------------------------
// Query-side inputs (a review found these bypassed the regular-file rule): a FIFO as the
// query list, the poses or features.h5 blocked for ever, /dev/zero was read without end.

/// Runs `f` on a thread; fails the test if it has not returned within `TIMEOUT`.
fn returns_promptly<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(TIMEOUT)
        .expect("blocked on a file that is not a regular file")
}

#[cfg(unix)]
#[test]
fn query_lists_poses_and_features_must_be_regular_files() {
    let tmp = tempfile::tempdir().unwrap();
    let fifo = tmp.path().join("queries.fifo");
    mkfifo(&fifo);
    for path in [
        fifo.clone(),
        PathBuf::from("/dev/zero"),
        tmp.path().to_path_buf(),
    ] {
        let p = path.clone();
        let err = returns_promptly(move || {
            sfpmap::io::queries::read_query_list(&p, None)
                .unwrap_err()
                .to_string()
        });
        assert!(err.contains("not a regular file"), "{err}");
        let p = path.clone();
        let err =
            returns_promptly(move || sfpmap::io::poses::read_poses(&p).unwrap_err().to_string());
        assert!(err.contains("not a regular file"), "{err}");
        let p = path.clone();
        let err = returns_promptly(
            move || match sfpmap::io::features_h5::H5Features::open(&p) {
                Ok(_) => "opened".to_string(),
                Err(e) => e.to_string(),
            },
        );
        assert!(err.contains("not a regular file"), "{err}");
    }
    // Through the CLI: one line naming the file.
    let out = sfpmap(&[
        OsStr::new("eval"),
        OsStr::new("--poses"),
        fifo.as_os_str(),
        OsStr::new("--gt"),
        fifo.as_os_str(),
    ]);
    assert_refused(&out, &[&fifo.display().to_string(), "a FIFO"]);
}
