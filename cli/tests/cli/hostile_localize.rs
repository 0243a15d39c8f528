//! Hostile and careless input to `sfpmap localize` (issue 12): crafted maps with correct
//! checksums, damaged query images, a missing images folder, absurd `--threads`. Each test runs
//! the real binary under an address-space cap and a timeout, so a regression to a panic, a
//! huge allocation or a runaway loop fails instead of taking the machine down.
#![cfg(all(feature = "localize", feature = "onnx"))]

use crate::common;

use common::{craft, craft_level, craft_level_points, craft_metadata, craft_points, run_limited};
use common::{level_info, Crafted, Limited, Rng};
use sfpmap::extract::{Features, LevelFeatures};
use sfpmap::format::{f16, Descriptors, Dtype, MapWriter, SectionKind};
use sfpmap::io::features_h5::{self, H5Options};
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::time::Duration;

const GIB: u64 = 1 << 30;

/// The exit status of a run that skipped queries it could not read (README, `localize
/// --help`): as for a log's damaged parts.
const SKIPPED_EXIT: i32 = 3;

fn sfpmap(args: &[&OsStr], max_bytes: u64) -> Limited {
    run_limited(
        env!("CARGO_BIN_EXE_sfpmap"),
        args,
        max_bytes,
        Duration::from_secs(300),
    )
}

/// Arguments as `OsStr`, so paths and flags mix.
macro_rules! args {
    ($($a:expr),* $(,)?) => { [$(AsRef::<OsStr>::as_ref(&$a)),*] };
}

/// An error is one line, `error: <file>: ...`, naming `file`, and nothing panicked.
fn assert_one_line_error(run: &Limited, file: &Path) {
    assert_eq!(run.code, Some(1), "{run:?}");
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(lines.len(), 1, "{run:?}");
    assert!(
        lines[0].starts_with(&format!("error: {}", file.display())),
        "{run:?}"
    );
    assert!(!run.stderr.contains("panicked"), "{run:?}");
}

/// Neither stdout nor stderr holds a control character but the line ends.
fn assert_no_raw_control_characters(run: &Limited) {
    for text in [&run.stdout, &run.stderr] {
        assert!(
            !text.chars().any(|c| c.is_control() && c != '\n'),
            "raw control character: {run:?}"
        );
    }
}

/// A query list of `names`, one pinhole camera for all (640 × 480).
fn query_list(dir: &Path, names: &[&str]) -> PathBuf {
    let path = dir.join("queries.txt");
    let text: String = names
        .iter()
        .map(|n| format!("{n} PINHOLE 640 480 500 500 320 240\n"))
        .collect();
    std::fs::write(&path, text).unwrap();
    path
}

/// A features.h5 with `n` random keypoints of `dim`-dimensional descriptors for the image
/// `name`, as one level whose id no map uses, so the reader serves them to every level.
fn features(dir: &Path, name: &str, n: usize, dim: usize) -> PathBuf {
    let mut rng = Rng(11);
    let full: Vec<f16> = (0..n * dim).map(|_| f16::from_f32(rng.unit())).collect();
    let level = LevelFeatures {
        level: 999,
        stride: 8,
        keypoints: (0..n)
            .map(|_| [(rng.unit() + 1.0) * 320.0, (rng.unit() + 1.0) * 240.0])
            .collect(),
        scores: vec![0.9; n],
        dim_short: dim,
        dim_full: dim,
        short: full.clone(),
        full,
    };
    let f = Features {
        image_size: [640, 480],
        levels: vec![level],
        global: vec![1.0; 4],
    };
    let path = dir.join("features.h5");
    let options = H5Options {
        main_level: 999,
        attributes: Vec::new(),
    };
    features_h5::write(&path, &[(name.to_string(), f)], &options).unwrap();
    path
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

/// `localize --features` of one query against `map`.
fn localize_features(dir: &Path, map: &Path, dim: usize, extra: &[&str]) -> Limited {
    let list = query_list(dir, &["q.jpg"]);
    let h5 = features(dir, "q.jpg", 200, dim);
    let out = dir.join("poses.txt");
    let mut a = args![
        "localize",
        "--map",
        map,
        "--query-list",
        list,
        "--features",
        h5,
        "-o",
        out
    ]
    .to_vec();
    a.extend(extra.iter().map(OsStr::new));
    sfpmap(&a, 2 * GIB)
}

/// A level's descriptor block, crafted: `rows × cols` f16 (zeros).
fn desc(kind: SectionKind, level: u16, rows: u64, cols: u64) -> Crafted {
    let bytes = vec![0u8; (rows * cols * 2) as usize];
    Crafted::raw(kind, level, Dtype::F16, rows, cols, bytes)
}

/// Finding 1: a level with `dim_short` 0 and no `rest` block made `localize` panic
/// ("chunk size must be non-zero"). Now: refused at open, or the level skipped — never a panic.
#[test]
fn finding_1_a_level_with_no_dimensions_to_match_is_not_a_panic() {
    let t = tempfile::tempdir().unwrap();
    // dim_full 8 (the query's), dim_short 0, no rest: nothing to match.
    let metadata = craft_metadata(vec![craft_level(0, 8, 0)]);
    let bytes = craft(
        &metadata,
        &[
            craft_points(4),
            craft_level_points(0, &[0, 1, 2, 3]),
            desc(SectionKind::LevelDescShort, 0, 4, 0),
        ],
    );
    let map = write(t.path(), "dim0.sfpm", &bytes);
    let run = localize_features(t.path(), &map, 8, &[]);
    assert_one_line_error(&run, &map);
    // Refused at open by the format's rule (`LevelInfo::matched_dims`); the localizer's own
    // skip of such a level is unit-tested in `localizer.rs` (`build_level`).
    assert!(run.stderr.contains("no descriptor dimension"), "{run:?}");
}

/// Finding 2: an empty level claiming 2^32 − 1 (or 2^24) descriptor dimensions made
/// `localize` abort allocating ~10^14 bytes. Now a one-line error within a 2 GiB address space.
#[test]
fn finding_2_an_empty_level_of_huge_dimensions_allocates_nothing() {
    let t = tempfile::tempdir().unwrap();
    for dim_full in [u64::from(u32::MAX), 1 << 24] {
        let metadata = craft_metadata(vec![craft_level(0, dim_full, 8)]);
        let bytes = craft(
            &metadata,
            &[
                craft_points(4),
                craft_level_points(0, &[]),
                desc(SectionKind::LevelDescShort, 0, 0, 8),
                desc(SectionKind::LevelDescRest, 0, 0, dim_full - 8),
            ],
        );
        let map = write(t.path(), "huge.sfpm", &bytes);
        let run = localize_features(t.path(), &map, 8, &[]);
        assert_one_line_error(&run, &map);
        // The rest block's columns (dim_full - 8) are refused at open, before any buffer.
        assert!(run.stderr.contains("at most 4096"), "{run:?}");
    }
}

/// Finding 4: 250 k points and 4,000 one-point levels (a 5 MB map) grew past 12 GB: the
/// localizer kept a points-sized table per level. Now it localizes within 1.5 GiB.
#[test]
fn finding_4_many_small_levels_do_not_multiply_memory_by_points() {
    const POINTS: usize = 250_000;
    const LEVELS: usize = 4_000;
    const DIM: usize = 16;
    let t = tempfile::tempdir().unwrap();
    let mut rng = Rng(5);
    let positions: Vec<[f64; 3]> = (0..POINTS)
        .map(|_| {
            [
                f64::from(rng.unit()) * 10.0,
                f64::from(rng.unit()) * 10.0,
                f64::from(rng.unit()) * 10.0 + 20.0,
            ]
        })
        .collect();
    let descriptors: Vec<Vec<f32>> = (0..LEVELS)
        .map(|_| (0..DIM).map(|_| rng.unit()).collect())
        .collect();
    let points: Vec<[u32; 1]> = (0..LEVELS).map(|l| [(l * 61) as u32]).collect();
    let mut w = MapWriter::default();
    w.set_points_world(&positions);
    for l in 0..LEVELS {
        let info = level_info(l as u16, 8.0, DIM as u32, DIM as u32);
        w.add_level(
            info,
            &points[l],
            Some(Descriptors::F32(&descriptors[l])),
            false,
        )
        .unwrap();
    }
    let map = write(t.path(), "levels.sfpm", &w.to_bytes().unwrap());
    assert!(std::fs::metadata(&map).unwrap().len() < 8 << 20);
    let list = query_list(t.path(), &["q.jpg"]);
    let h5 = features(t.path(), "q.jpg", 300, DIM);
    let out = t.path().join("poses.txt");
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--features",
            h5,
            "-o",
            out,
            "--json"
        ],
        3 * GIB / 2,
    );
    assert_eq!(run.code, Some(0), "{run:?}");
    let summary: serde_json::Value = serde_json::from_str(&run.stdout).unwrap();
    assert_eq!(summary["queries"], 1, "{summary}");
    let poses = std::fs::read_to_string(&out).unwrap();
    assert!(poses
        .lines()
        .any(|l| l.starts_with("# failed q.jpg") || l.starts_with("q.jpg ")));
}

/// A textured 640 × 480 JPEG, and where its scan's entropy-coded data starts.
fn query_jpeg() -> (Vec<u8>, usize) {
    let image = image::RgbImage::from_fn(640, 480, |x, y| {
        let v = ((x as f32 * 0.1).sin() * 60.0 + (y as f32 * 0.07).cos() * 60.0 + 128.0) as u8;
        image::Rgb([v, (x * 3 % 256) as u8, ((x ^ y) % 256) as u8])
    });
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    let sos = bytes.windows(2).position(|w| w == [0xFF, 0xDA]).unwrap();
    let start = sos + 2 + usize::from(u16::from_be_bytes([bytes[sos + 2], bytes[sos + 3]]));
    (bytes, start)
}

/// An SFP map the built-in sfp-v1's queries fit: level 2 (stride 8) of sfp-v1, 192 full
/// dimensions of which 64 short, random descriptors.
fn sfp_map(dir: &Path) -> PathBuf {
    write(dir, "sfp.sfpm", &common::sfp_level_2_map(&[]))
}

/// Finding 17: a cut-off or damaged query JPEG was decoded leniently (the lost part grey)
/// and localized, exit 0. Now each is a failed query saying the image does not decode.
#[test]
fn finding_17_a_damaged_query_image_is_a_failed_query_with_the_reason() {
    let t = tempfile::tempdir().unwrap();
    let images = t.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let (jpg, scan) = query_jpeg();
    write(&images, "good.jpg", &jpg);
    // Cut in the middle of the scan, and cut just before the end-of-image marker.
    write(&images, "cut.jpg", &jpg[..(scan + jpg.len()) / 2]);
    write(&images, "cut-end.jpg", &jpg[..jpg.len() - 2]);
    // A burst of set bits in the scan (stuffed 0xFF bytes): no Huffman code reads it.
    let mut burst = jpg.clone();
    let mid = (scan + jpg.len()) / 2;
    for (i, b) in burst[mid..mid + 32].iter_mut().enumerate() {
        *b = if i % 2 == 0 { 0xFF } else { 0x00 };
    }
    write(&images, "burst.jpg", &burst);
    let names = ["good.jpg", "cut.jpg", "cut-end.jpg", "burst.jpg"];
    let list = query_list(t.path(), &names);
    let map = sfp_map(t.path());
    let out = t.path().join("poses.txt");
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--images",
            images,
            "--level",
            "2",
            "-o",
            out,
            "--json"
        ],
        4 * GIB,
    );
    // Some queries were read: the run writes every pose and lists the others as failed,
    // exit status 3 (queries skipped, as for a log's damaged parts).
    assert_eq!(run.code, Some(SKIPPED_EXIT), "{run:?}");
    let poses = std::fs::read_to_string(&out).unwrap();
    for name in &names[1..] {
        let line = poses
            .lines()
            .find(|l| l.starts_with(&format!("# failed {name}:")))
            .unwrap_or_else(|| panic!("{name} not failed: {poses}"));
        assert!(line.contains("the image does not decode"), "{line}");
    }
    assert!(!poses.contains("# failed good.jpg: the image"), "{poses}");
    let summary: serde_json::Value = serde_json::from_str(&run.stdout).unwrap();
    assert!(
        summary["failed"].as_array().unwrap().len() >= 3,
        "{summary}"
    );
}

/// An image of another size than its query's camera: the camera's intrinsics are in pixels
/// of its own size, so the pose would be wrong, not failed. It is a failed query saying both
/// sizes (as a log's frame is); the other queries run.
#[test]
fn an_image_of_another_size_than_its_camera_is_a_failed_query() {
    let t = tempfile::tempdir().unwrap();
    let images = t.path().join("images");
    std::fs::create_dir(&images).unwrap();
    write(&images, "good.jpg", &query_jpeg().0);
    let small =
        image::imageops::thumbnail(&image::load_from_memory(&query_jpeg().0).unwrap(), 320, 240);
    small.save(images.join("small.png")).unwrap();
    let list = query_list(t.path(), &["good.jpg", "small.png"]);
    let map = sfp_map(t.path());
    let out = t.path().join("poses.txt");
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--images",
            images,
            "--level",
            "2",
            "-o",
            out
        ],
        4 * GIB,
    );
    // The other query ran: exit status 3, as for any query that could not be used.
    assert_eq!(run.code, Some(SKIPPED_EXIT), "{run:?}");
    let poses = std::fs::read_to_string(&out).unwrap();
    assert!(
        poses.contains("# failed small.png: the image is 320x240 but the camera is 640x480"),
        "{poses}"
    );
    assert!(
        !poses.contains("# failed good.jpg: the image is"),
        "{poses}"
    );
    assert!(
        poses
            .lines()
            .any(|l| l.starts_with("good.jpg ") || l.starts_with("# failed good.jpg")),
        "good.jpg ran: {poses}"
    );

    // A photo over the network's pixel budget is shrunk before extraction; its camera is
    // compared with the size as decoded, so a matching camera is no failure.
    let big = image::RgbImage::from_fn(4400, 4000, |x, y| {
        image::Rgb([(x % 251) as u8, (y % 241) as u8, ((x ^ y) % 256) as u8])
    });
    big.save(images.join("big.png")).unwrap();
    let list = t.path().join("big.txt");
    std::fs::write(&list, "big.png PINHOLE 4400 4000 3000 3000 2200 2000\n").unwrap();
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--images",
            images,
            "--level",
            "2",
            "-o",
            out,
            "--force"
        ],
        4 * GIB,
    );
    let poses = std::fs::read_to_string(&out).unwrap_or_default();
    assert!(
        poses
            .lines()
            .any(|l| l.starts_with("big.png ") || l.starts_with("# failed big.png"))
            && !poses.contains("the image is"),
        "{run:?} {poses}"
    );
}

/// Finding 17: `--images` naming a missing folder ran every query and exited 0 with all
/// failed. Now it is an error naming the folder, before any work (no model is loaded); so is
/// a folder holding none of the listed images, and a run that could read no query at all.
#[test]
fn finding_17_a_missing_images_folder_is_an_error_before_any_work() {
    let t = tempfile::tempdir().unwrap();
    let map = sfp_map(t.path());
    let list = query_list(t.path(), &["a.jpg", "b.jpg"]);
    let out = t.path().join("poses.txt");
    let missing = t.path().join("no-such-folder");
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--images",
            missing,
            "-o",
            out
        ],
        2 * GIB,
    );
    assert_one_line_error(&run, &missing);
    assert!(run.stderr.contains("no such folder"), "{run:?}");
    assert!(run.seconds < 30.0, "{run:?}");

    let empty = t.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--images",
            empty,
            "-o",
            out
        ],
        2 * GIB,
    );
    assert_one_line_error(&run, &empty);
    assert!(run.stderr.contains("none of the 2 images"), "{run:?}");

    // Features for another image only: no query can be read.
    let h5 = features(t.path(), "other.jpg", 10, 192);
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--features",
            h5,
            "--level",
            "2",
            "-o",
            out
        ],
        2 * GIB,
    );
    assert_one_line_error(&run, &list);
    assert!(
        run.stderr.contains("none of the 2 queries could be read"),
        "{run:?}"
    );
    assert!(!out.exists(), "no output for a run that read nothing");
}

/// `--threads 1000000` spawned a million threads (48 s for 3 queries). Now it is capped
/// with a warning, which `--quiet` silences.
#[test]
fn absurd_threads_are_capped_with_a_warning() {
    let t = tempfile::tempdir().unwrap();
    let metadata = craft_metadata(vec![craft_level(0, 8, 8)]);
    let mut rng = Rng(9);
    let short: Vec<u8> = (0..16 * 8)
        .flat_map(|_| f16::from_f32(rng.unit()).to_le_bytes())
        .collect();
    let bytes = craft(
        &metadata,
        &[
            craft_points(16),
            craft_level_points(0, &(0..16).collect::<Vec<u32>>()),
            Crafted::raw(SectionKind::LevelDescShort, 0, Dtype::F16, 16, 8, short),
        ],
    );
    let map = write(t.path(), "small.sfpm", &bytes);
    let run = localize_features(t.path(), &map, 8, &["--threads", "1000000"]);
    assert_eq!(run.code, Some(0), "{run:?}");
    assert!(
        run.stderr.contains("warning: --threads 1000000: using"),
        "{run:?}"
    );
    assert!(run.seconds < 60.0, "{run:?}");
    let run = localize_features(
        t.path(),
        &map,
        8,
        &["--threads", "1000000", "-q", "--force"],
    );
    assert_eq!(run.code, Some(0), "{run:?}");
    assert!(run.stderr.is_empty(), "{run:?}");
}

/// A crafted map of one level, 16 points with random `dim`-dimensional descriptors.
fn small_map(dir: &Path, dim: u64) -> PathBuf {
    let metadata = craft_metadata(vec![craft_level(0, dim, dim)]);
    let mut rng = Rng(9);
    let short: Vec<u8> = (0..16 * dim)
        .flat_map(|_| f16::from_f32(rng.unit()).to_le_bytes())
        .collect();
    let bytes = craft(
        &metadata,
        &[
            craft_points(16),
            craft_level_points(0, &(0..16).collect::<Vec<u32>>()),
            Crafted::raw(SectionKind::LevelDescShort, 0, Dtype::F16, 16, dim, short),
        ],
    );
    write(dir, "small.sfpm", &bytes)
}

/// Issue 12, finding 18 for `localize -o`: query names went into the pose file as they were,
/// so a control character in a name (ESC, NUL, DEL: the query list's own line and field
/// splitting keeps newlines and spaces out) landed raw in a text format. Now, as the
/// exporters do: the COLMAP format, whose rows start with the name, refuses such a name
/// before any work; TUM, whose rows hold no names, escapes it in its comment; JSON keeps it.
#[test]
fn query_names_with_control_characters_are_refused_or_escaped() {
    let t = tempfile::tempdir().unwrap();
    let map = small_map(t.path(), 8);
    let names = ["q.jpg", "a\u{1b}[2Jb.jpg", "c\u{0}d\u{7f}.jpg"];
    let list = query_list(t.path(), &names);
    let h5 = features(t.path(), "q.jpg", 200, 8);
    let run_format = |format: &str| {
        let out = t.path().join(format!("poses.{format}"));
        let run = sfpmap(
            &args![
                "localize",
                "--map",
                map,
                "--query-list",
                list,
                "--features",
                h5,
                "--format",
                format,
                "-o",
                out
            ],
            2 * GIB,
        );
        (run, out)
    };

    let (run, out) = run_format("colmap");
    assert_one_line_error(&run, &list);
    assert!(
        run.stderr
            .contains(r#"query 2 "a\x1b[2Jb.jpg" holds a control character"#),
        "{run:?}"
    );
    assert!(!out.exists(), "no output for a refused run");

    // The two names the features file lacks fail alone: exit status 3. Nothing printed holds
    // the names' control characters raw (the summary's `failed:` lines, the warning).
    let (run, out) = run_format("tum");
    assert_eq!(run.code, Some(SKIPPED_EXIT), "{run:?}");
    assert_no_raw_control_characters(&run);
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        !text.chars().any(|c| c.is_control() && c != '\n'),
        "raw control character: {text:?}"
    );
    assert!(text.contains("# failed 1 a\\x1b[2Jb.jpg: "), "{text:?}");
    assert!(text.contains("# failed 2 c\\x00d\\x7f.jpg: "), "{text:?}");
    assert_eq!(text.lines().count(), 4, "{text:?}");

    let (run, out) = run_format("json");
    assert_eq!(run.code, Some(SKIPPED_EXIT), "{run:?}");
    assert_no_raw_control_characters(&run);
    let list: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let read: Vec<&str> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|q| q["name"].as_str().unwrap())
        .collect();
    assert_eq!(read, names);
}

/// A COLMAP database with one image, `name`, whose keypoints are `cols` values per row
/// (`keypoints`, row-major) with 128-byte descriptors.
#[cfg(feature = "colmap")]
fn query_database(dir: &Path, name: &str, cols: usize, keypoints: &[f32]) -> PathBuf {
    let path = dir.join(format!("queries-{cols}.db"));
    let conn = rusqlite::Connection::open(&path).unwrap();
    common::colmap_schema(&conn);
    let rows = keypoints.len() / cols;
    let blob: Vec<u8> = keypoints.iter().flat_map(|v| v.to_le_bytes()).collect();
    let mut rng = Rng(21);
    let descriptors: Vec<u8> = (0..rows * 128)
        .map(|_| (rng.unit() * 255.0) as u8)
        .collect();
    conn.execute("INSERT INTO images VALUES (1, ?1, 1)", [name])
        .unwrap();
    conn.execute(
        "INSERT INTO keypoints VALUES (1, ?1, ?2, ?3)",
        rusqlite::params![rows as i64, cols as i64, blob],
    )
    .unwrap();
    conn.execute(
        "INSERT INTO descriptors VALUES (1, ?1, 128, ?2)",
        rusqlite::params![rows as i64, descriptors],
    )
    .unwrap();
    path
}

/// Issue 12 (NaN/inf in COLMAP inputs) for query databases: a keypoint with a NaN or
/// infinite x, y or scale went into matching and pose estimation unchecked. Now it is a
/// failed query naming the database, the image and the keypoint (issue 32: it fails alone);
/// a list of that query alone reads nothing, a one-line error naming the list and the reason.
#[cfg(feature = "colmap")]
#[test]
fn a_non_finite_query_keypoint_is_an_error_naming_database_image_and_keypoint() {
    let t = tempfile::tempdir().unwrap();
    let map = small_map(t.path(), 128);
    let list = query_list(t.path(), &["q.jpg"]);
    let out = t.path().join("poses.txt");
    let cases: [(usize, Vec<f32>, &str); 3] = [
        (
            2,
            vec![10.0, 20.0, f32::NAN, 40.0, 50.0, 60.0],
            "keypoint 1: x is NaN",
        ),
        (
            4,
            vec![10.0, 20.0, 2.0, 0.0, 30.0, f32::NEG_INFINITY, 2.0, 0.0],
            "keypoint 1: y is -inf",
        ),
        (
            4,
            vec![
                10.0,
                20.0,
                2.0,
                0.0,
                30.0,
                40.0,
                2.0,
                0.0,
                1.0,
                2.0,
                f32::INFINITY,
                0.0,
            ],
            "keypoint 2: scale is inf",
        ),
    ];
    for (cols, keypoints, expected) in cases {
        let db = query_database(t.path(), "q.jpg", cols, &keypoints);
        let run = sfpmap(
            &args![
                "localize",
                "--map",
                map,
                "--query-list",
                list,
                "--database",
                db,
                "-o",
                out,
                "--force"
            ],
            2 * GIB,
        );
        assert_one_line_error(&run, &list);
        assert!(
            run.stderr.contains("none of the 1 queries could be read")
                && run.stderr.contains(&db.display().to_string())
                && run.stderr.contains(r#"image "q.jpg""#)
                && run.stderr.contains(expected),
            "{expected}: {run:?}"
        );
        std::fs::remove_file(&db).unwrap();
    }
}

/// The same for a features.h5 query: a keypoint (or descriptor value) that is not finite is
/// an error naming the file, the dataset and the keypoint.
#[test]
fn a_non_finite_features_h5_keypoint_is_an_error_naming_file_and_keypoint() {
    let t = tempfile::tempdir().unwrap();
    for (x, y, expected) in [
        (f32::NAN, 10.0, "keypoint 3: x is NaN"),
        (10.0, f32::INFINITY, "keypoint 3: y is inf"),
    ] {
        let mut rng = Rng(5);
        let full: Vec<f16> = (0..8 * 4).map(|_| f16::from_f32(rng.unit())).collect();
        let mut keypoints: Vec<[f32; 2]> = (0..8).map(|i| [i as f32, 1.0]).collect();
        keypoints[3] = [x, y];
        let level = LevelFeatures {
            level: 0,
            stride: 8,
            keypoints,
            scores: vec![0.9; 8],
            dim_short: 4,
            dim_full: 4,
            short: full.clone(),
            full,
        };
        let f = Features {
            image_size: [64, 48],
            levels: vec![level],
            global: vec![1.0; 4],
        };
        let path = t.path().join("nan.h5");
        let options = H5Options {
            main_level: 0,
            attributes: Vec::new(),
        };
        let _ = std::fs::remove_file(&path);
        features_h5::write(&path, &[("q.jpg".to_string(), f)], &options).unwrap();
        let h5 = sfpmap::io::features_h5::H5Features::open(&path).unwrap();
        let e = h5.features("q.jpg").unwrap_err().to_string();
        assert!(e.starts_with(&path.display().to_string()), "{e}");
        assert!(e.contains(expected), "{e}");
        assert!(!e.contains('\n'), "{e}");
    }
}

/// Issue 11's review: a map's image VLADs are not checked by the format (as descriptors are
/// not), so NaN image VLADs and a query with a NaN descriptor never panic and a NaN image ranks
/// last, not first. Centroids are checked (issue 14): a NaN centroid is a format error.
#[test]
fn hostile_vlad_values_rank_last_and_never_panic() {
    use sfpmap::format::{Codec, Map, Retrieval};
    use sfpmap::geometry::Camera;
    use sfpmap::localize::{FeatureSet, LocalizeOptions, Localizer, QueryFeatures};
    let scene = common::Scene::new(5, 200, 12, &[(2, 4.0, 8, 4)]);
    let mut w = scene.writer(Codec::Raw);
    let (clusters, dims) = (3, 4);
    let mut images = vec![0.1f32; 12 * clusters * dims];
    images[..clusters * dims].fill(f32::NAN);
    let options = LocalizeOptions {
        top_k: 3,
        ..LocalizeOptions::default()
    };

    let mut nan_centroids = vec![0.5f32; clusters * dims];
    nan_centroids[5] = f32::NAN;
    let mut bad = scene.writer(Codec::Raw);
    bad.set_vlad(2, dims, nan_centroids, &images).unwrap();
    let bad_bytes = bad.to_bytes().unwrap();
    let bad_map = Map::from_bytes(&bad_bytes).unwrap();
    let e = Localizer::new(&bad_map, options.clone())
        .err()
        .expect("a NaN centroid is refused")
        .to_string();
    assert!(e.contains("centroid value is not finite"), "{e}");

    w.set_vlad(2, dims, vec![0.5f32; clusters * dims], &images)
        .unwrap();
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    let localizer = Localizer::new(&map, options).unwrap();
    let level = map.level(2).unwrap();
    let d_in = level
        .projection_input_dim()
        .unwrap_or(level.info().dim_full as usize);
    let n = 50;
    let mut descriptors: Vec<f32> = (0..n * d_in)
        .map(|i| ((i * 37 % 101) as f32 / 101.0) - 0.5)
        .collect();
    descriptors[..d_in].fill(f32::NAN);
    let query = QueryFeatures {
        sets: vec![FeatureSet {
            level: None,
            keypoints: (0..n).map(|i| [i as f64 * 10.0 + 5.0, 100.0]).collect(),
            descriptors,
            dim: d_in,
        }],
        global: None,
        model: None,
    };
    let camera = Camera::parse("SIMPLE_RADIAL 640 480 500 320 240 0.01").unwrap();
    // A query row of NaN is refused by the localizer itself, naming it.
    let e = localizer.localize(&query, &camera).unwrap_err().to_string();
    assert!(e.contains("descriptors row 0: a value is NaN"), "{e}");
    let mut query = query;
    query.sets[0].descriptors[..d_in].fill(0.25);
    let r = localizer.localize(&query, &camera).unwrap();
    assert_eq!(r.retrieval, Some(Retrieval::Vlad), "{r:?}");
    assert_eq!(r.retrieved.len(), 3, "{r:?}");
    assert!(
        !r.retrieved.contains(&0),
        "the NaN image ranks last: {:?}",
        r.retrieved
    );
}

/// Issue 32, case 10: a query list naming an absolute path (`/etc/passwd`, `/proc/self/mem`)
/// or a `../` name was read from outside `--images`. Now each such name is a failed query
/// saying why (the decodable image beside the folder is not read), the rest run, exit 3.
#[test]
fn query_names_outside_the_images_folder_fail_naming_why() {
    let t = tempfile::tempdir().unwrap();
    let images = t.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let (jpg, _) = query_jpeg();
    write(&images, "good.jpg", &jpg);
    // A decodable query image beside the folder, by a `..` name and by its absolute path.
    let outside = write(t.path(), "outside.jpg", &jpg);
    let outside = outside.to_str().unwrap();
    let names = [
        "good.jpg",
        "../outside.jpg",
        "./../outside.jpg",
        outside,
        "/etc/passwd",
        "/proc/self/mem",
    ];
    let list = query_list(t.path(), &names);
    let map = sfp_map(t.path());
    let out = t.path().join("poses.txt");
    let run = sfpmap(
        &args![
            "localize",
            "--map",
            map,
            "--query-list",
            list,
            "--images",
            images,
            "--level",
            "2",
            "-o",
            out
        ],
        4 * GIB,
    );
    assert_eq!(run.code, Some(SKIPPED_EXIT), "{run:?}");
    assert!(
        run.stderr.contains("5 of 6 queries could not be read"),
        "{run:?}"
    );
    let poses = std::fs::read_to_string(&out).unwrap();
    for (name, why) in [
        ("../outside.jpg", r#"a name with a ".." component"#),
        ("./../outside.jpg", r#"a name with a ".." component"#),
        (outside, "an absolute path"),
        ("/etc/passwd", "an absolute path"),
        ("/proc/self/mem", "an absolute path"),
    ] {
        let line = poses
            .lines()
            .find(|l| l.starts_with(&format!("# failed {name}: ")))
            .unwrap_or_else(|| panic!("{name} not failed: {poses}"));
        assert!(line.contains(why), "{line}");
    }
    assert!(
        !poses.contains("# failed good.jpg: a name") && !poses.contains("# failed good.jpg: an"),
        "{poses}"
    );
}

/// Writes, with h5py, a features.h5 of `good.jpg` and `bad.jpg` (200 random keypoints of
/// 128-dimensional descriptors each) with `bad.jpg` broken by `mutation`: `nan` (keypoint 3's
/// x), `dim` (64-dimensional descriptors), `count` (150 descriptors for 200 keypoints).
const TWO_QUERIES_H5: &str = r#"
import sys, numpy as np, h5py
path, mutation = sys.argv[1], sys.argv[2]
rng = np.random.default_rng(3)
with h5py.File(path, "w") as f:
    for name in ["good.jpg", "bad.jpg"]:
        xy = (rng.random((200, 2)) * [640, 480]).astype(np.float32)
        d = rng.random((128, 200)).astype(np.float32)
        if name == "bad.jpg":
            if mutation == "nan":
                xy[3, 0] = np.nan
            if mutation == "dim":
                d = d[:64]
            if mutation == "count":
                d = d[:, :150]
        g = f.create_group(name)
        g["keypoints"] = xy
        g["descriptors"] = d.astype(np.float16)
"#;

/// Issue 32, case 11: one malformed query of a features file (a NaN keypoint, descriptors
/// of another dimension than the map's, N keypoints and M descriptors) ended the whole run,
/// no poses written. Now that query fails alone with the reason, the other is localized (here
/// read: the map is random), the poses are written and the exit status is 3.
#[test]
fn a_malformed_query_in_a_features_file_fails_alone() {
    let t = tempfile::tempdir().unwrap();
    let map = small_map(t.path(), 128);
    let list = query_list(t.path(), &["good.jpg", "bad.jpg"]);
    for (mutation, expected) in [
        ("nan", "bad.jpg/keypoints: keypoint 3: x is NaN"),
        (
            "dim",
            "query descriptors have 64 dimensions but level 0 of the map expects 128",
        ),
        (
            "count",
            "bad.jpg/descriptors: 128 x 150 values for 200 keypoints",
        ),
    ] {
        let h5 = t.path().join(format!("{mutation}.h5"));
        let python = crate::python::python_with("numpy, h5py");
        let wrote = std::process::Command::new(python)
            .args(["-c", TWO_QUERIES_H5])
            .arg(&h5)
            .arg(mutation)
            .output()
            .unwrap();
        assert!(wrote.status.success(), "{wrote:?}");
        let out = t.path().join(format!("{mutation}.txt"));
        let run = sfpmap(
            &args![
                "localize",
                "--map",
                map,
                "--query-list",
                list,
                "--features",
                h5,
                "-o",
                out,
                "--json"
            ],
            2 * GIB,
        );
        assert_eq!(run.code, Some(SKIPPED_EXIT), "{mutation}: {run:?}");
        assert!(
            run.stderr.contains("1 of 2 queries could not be read"),
            "{mutation}: {run:?}"
        );
        let poses = std::fs::read_to_string(&out).unwrap();
        let bad = poses
            .lines()
            .find(|l| l.starts_with("# failed bad.jpg: "))
            .unwrap_or_else(|| panic!("{mutation}: bad.jpg not failed: {poses}"));
        assert!(bad.contains(expected), "{mutation}: {bad}");
        // good.jpg was read: localized, or failed by the localizer, not for its features.
        assert!(
            poses.lines().any(|l| l.starts_with("good.jpg "))
                || poses
                    .lines()
                    .any(|l| l.starts_with("# failed good.jpg: ") && !l.contains(".h5")),
            "{mutation}: {poses}"
        );
        let summary: serde_json::Value = serde_json::from_str(&run.stdout).unwrap();
        assert_eq!(summary["queries"], 2, "{summary}");
    }
}
