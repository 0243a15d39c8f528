//! The output policy (src/output.rs) through the real binary on temp trees: no command writes
//! over one of its inputs, over an existing file without `--force`, or over a device or FIFO;
//! a killed or interrupted write leaves the old or the new file and no temp file (or only
//! recognisable ones, which the next write into that folder removes).
//!
//! `SFPMAP_BIN` runs these tests against another build (e.g. an older release) to see them fail.
#![cfg(all(feature = "colmap", unix))]

use crate::common;
use crate::shared_data;

use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

fn bin() -> PathBuf {
    std::env::var_os("SFPMAP_BIN")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_BIN_EXE_sfpmap")))
}

fn sfpmap(args: &[&str]) -> Output {
    Command::new(bin())
        .args(args)
        .arg("--quiet")
        .output()
        .expect("run sfpmap")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Asserts `o` failed with one error line that names `path` and contains `what`.
fn refused(o: &Output, path: &Path, what: &str) {
    let err = stderr(o);
    assert!(!o.status.success(), "accepted; stderr: {err}");
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
    assert!(
        err.contains(s(path)),
        "does not name {}: {err}",
        path.display()
    );
    assert!(err.contains(what), "no {what:?} in: {err}");
    assert!(!err.contains("sfpmap-tmp"), "names a temp file: {err}");
}

/// A copy of the conformance map with points, levels and images.
fn map_in(dir: &Path) -> PathBuf {
    let map = dir.join("map.sfpm");
    std::fs::copy(
        crate::shared_data::repo_root().join("spec/vectors/valid/levels.sfpm"),
        &map,
    )
    .unwrap();
    map
}

/// A COLMAP database with the four tables and no rows: every query is "not found", and
/// `localize` writes its output.
fn empty_database(path: &Path) {
    let db = rusqlite::Connection::open(path).unwrap();
    common::colmap_schema(&db);
}

const CAMERA: &str = "SIMPLE_PINHOLE 640 480 500 320 240";

/// Every file under `dir` with its bytes, to show that nothing changed.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut v: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .map(|p| {
            let bytes = std::fs::read(&p).unwrap();
            (p, bytes)
        })
        .collect();
    v.sort();
    v
}

/// A SIFT map of the shared sacre-coeur scene, its first query and the queries' database, all
/// copied into `dir`: a `localize` run that completes and writes its output.
fn localize_inputs(dir: &Path) -> Option<(PathBuf, PathBuf, PathBuf)> {
    let scene = shared_data::shared_data("scenes/sacre-coeur")?;
    let map = dir.join("map.sfpm");
    let db = dir.join("database.db");
    std::fs::copy(scene.join("database.db"), &db).unwrap();
    let o = sfpmap(&[
        "convert",
        "--colmap",
        s(&scene.join("sparse-map")),
        "--database",
        s(&db),
        "-o",
        s(&map),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    std::fs::remove_file(&db).unwrap();
    let queries = dir.join("queries.txt");
    let list = std::fs::read_to_string(scene.join("queries.txt")).unwrap();
    let first = list.lines().find(|l| !l.starts_with('#')).unwrap();
    std::fs::write(&queries, format!("{first}\n")).unwrap();
    let queries_db = dir.join("queries.db");
    std::fs::copy(scene.join("queries.db"), &queries_db).unwrap();
    Some((map, queries, queries_db))
}

fn localize(map: &Path, queries: &Path, db: &Path, out: &Path, force: bool) -> Output {
    let mut args = vec![
        "localize",
        "--map",
        s(map),
        "--query-list",
        s(queries),
        "--database",
        s(db),
        "-o",
        s(out),
    ];
    if force {
        args.push("--force");
    }
    sfpmap(&args)
}

// Finding 9: `localize -o` overwrote any file without --force, its own inputs included.
#[test]
fn localize_refuses_its_inputs_and_existing_files_as_output() {
    let dir = tempfile::tempdir().unwrap();
    let Some((map, queries, db)) = localize_inputs(dir.path()) else {
        return;
    };
    let before = snapshot(dir.path());
    std::fs::create_dir(dir.path().join("sub")).unwrap();
    for input in [&map, &queries, &db] {
        refused(&localize(&map, &queries, &db, input, false), input, "input");
        // `--force` replaces existing outputs, never inputs, whatever path names them.
        refused(&localize(&map, &queries, &db, input, true), input, "input");
        let other_path = dir.path().join("sub/..").join(input.file_name().unwrap());
        refused(
            &localize(&map, &queries, &db, &other_path, true),
            &other_path,
            "input",
        );
    }
    std::fs::remove_dir(dir.path().join("sub")).unwrap();
    assert_eq!(snapshot(dir.path()), before, "an input changed");

    let out = dir.path().join("poses.txt");
    std::fs::write(&out, "precious").unwrap();
    refused(&localize(&map, &queries, &db, &out, false), &out, "--force");
    assert_eq!(std::fs::read(&out).unwrap(), b"precious");
    let o = localize(&map, &queries, &db, &out, true);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read_to_string(&out).unwrap().starts_with("# name"));

    #[cfg(feature = "mcap")]
    {
        let log = dir.path().join("in.mcap");
        std::fs::write(&log, b"not read: the output is refused first").unwrap();
        let mcap = |out: &Path, tum: Option<&Path>| {
            let mut args = vec![
                "localize",
                "--map",
                s(&map),
                "--mcap",
                s(&log),
                "--topic",
                "/img",
                "--camera",
                CAMERA,
                "-o",
                s(out),
                "--force",
            ];
            if let Some(tum) = tum {
                args.extend(["--tum", s(tum)]);
            }
            sfpmap(&args)
        };
        refused(&mcap(&log, None), &log, "input");
        refused(&mcap(&map, None), &map, "input");
        let fresh = dir.path().join("poses.mcap");
        refused(&mcap(&fresh, Some(&map)), &map, "input");
        assert!(!fresh.exists());
    }
}

// "localize errors name its temp file instead of the output".
#[test]
fn a_failed_write_names_the_output_not_a_temp_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("no-such-folder/poses.txt");
    if let Some((map, queries, db)) = localize_inputs(dir.path()) {
        let o = localize(&map, &queries, &db, &out, false);
        refused(&o, &out, "No such file or directory");
    }
    let map = map_in(dir.path());
    let o = sfpmap(&["slice", s(&map), "--level", "2", "-o", s(&out)]);
    refused(&o, &out, "No such file or directory");
}

// Finding 10: `export --ply MAP --force` replaced the map with a PLY.
#[test]
fn export_never_writes_over_its_map() {
    let dir = tempfile::tempdir().unwrap();
    let map = map_in(dir.path());
    let before = std::fs::read(&map).unwrap();
    for flag in ["--ply", "--tum", "--images-txt"] {
        refused(
            &sfpmap(&["export", s(&map), flag, s(&map), "--force"]),
            &map,
            "input",
        );
        let link = dir.path().join("link.sfpm");
        std::os::unix::fs::symlink(&map, &link).unwrap();
        refused(
            &sfpmap(&["export", s(&map), flag, s(&link), "--force"]),
            &link,
            "input",
        );
        std::fs::remove_file(&link).unwrap();
    }
    // A map named like a COLMAP model file, exported into its own folder.
    let model_dir = dir.path().join("model");
    std::fs::create_dir(&model_dir).unwrap();
    let named = model_dir.join("images.txt");
    std::fs::copy(&map, &named).unwrap();
    let o = sfpmap(&["export-colmap", s(&named), "-o", s(&model_dir), "--force"]);
    refused(&o, &named, "input");
    assert_eq!(std::fs::read(&named).unwrap(), before);
    assert!(
        !model_dir.join("cameras.txt").exists(),
        "wrote part of the model"
    );
    assert_eq!(std::fs::read(&map).unwrap(), before);
}

// Finding 11: `convert -o MODEL_DIR/points3D.bin --force` replaced an input model file.
#[test]
fn convert_never_writes_over_a_model_file_or_the_database() {
    let dir = tempfile::tempdir().unwrap();
    let map = map_in(dir.path());
    let model = dir.path().join("model");
    let o = sfpmap(&["export-colmap", s(&map), "-o", s(&model)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut models = vec![model.clone()];
    // The binary flavour, from the shared data when it is there.
    if let Some(shared) = shared_data::shared_data("scenes/sacre-coeur/sparse-map") {
        let bin_model = dir.path().join("bin-model");
        std::fs::create_dir(&bin_model).unwrap();
        for f in ["cameras.bin", "images.bin", "points3D.bin"] {
            std::fs::copy(shared.join(f), bin_model.join(f)).unwrap();
        }
        models.push(bin_model);
    }
    for model in &models {
        let before = snapshot(model);
        for (input, _) in &before {
            let o = sfpmap(&["convert", "--colmap", s(model), "-o", s(input), "--force"]);
            refused(&o, input, "input");
        }
        assert_eq!(
            snapshot(model),
            before,
            "{}: a model file changed",
            model.display()
        );
        let out = dir.path().join("converted.sfpm");
        let o = sfpmap(&["convert", "--colmap", s(model), "-o", s(&out), "--force"]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let db = dir.path().join("database.db");
    empty_database(&db);
    let before = std::fs::read(&db).unwrap();
    let o = sfpmap(&[
        "convert",
        "--colmap",
        s(&model),
        "--database",
        s(&db),
        "-o",
        s(&db),
        "--force",
    ]);
    refused(&o, &db, "input");
    assert_eq!(std::fs::read(&db).unwrap(), before);
    // With --images, a file in the images folder may be a model image: refused
    // before the extractor runs (no ONNX Runtime needed to get this far).
    let images = dir.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let image = images.join("a.jpg");
    std::fs::write(&image, b"not really a jpeg").unwrap();
    let convert_images_to = |out: &Path| {
        let args = ["convert", "--colmap", s(&model), "--images", s(&images)];
        sfpmap(&[&args[..], &["-o", s(out), "--force"]].concat())
    };
    refused(
        &convert_images_to(&image),
        &image,
        "lies inside the input folder",
    );
    assert_eq!(std::fs::read(&image).unwrap(), b"not really a jpeg");
    // Nor is anything new written among the images, by convert, extract or localize.
    let new = images.join("new.sfpm");
    refused(
        &convert_images_to(&new),
        &images,
        "lies inside the input folder",
    );
    assert!(!new.exists());
    let h5 = images.join("features.h5");
    refused(
        &sfpmap(&["extract", s(&images), "-o", s(&h5)]),
        &images,
        "lies inside the input folder",
    );
    assert!(!h5.exists());
    let list = dir.path().join("queries.txt");
    std::fs::write(&list, "a.jpg SIMPLE_PINHOLE 640 480 500 320 240\n").unwrap();
    let poses = images.join("poses.txt");
    let localize = [
        "localize",
        "--map",
        s(&map),
        "--query-list",
        s(&list),
        "--images",
        s(&images),
        "-o",
        s(&poses),
    ];
    refused(&sfpmap(&localize), &images, "lies inside the input folder");
    assert!(!poses.exists());
    // Outside the folder, through `..` in a model image's name: refused before anything is
    // read or written, naming the image (issue 32: names a file gives stay inside the folder
    // the user named; the same-file rule per image stays behind it).
    let images_txt = std::fs::read_to_string(model.join("images.txt")).unwrap();
    let first = images_txt
        .lines()
        .find(|l| !l.starts_with('#'))
        .unwrap()
        .to_string();
    let renamed = first.rsplit_once(' ').unwrap().0.to_string() + " ../out.sfpm";
    std::fs::write(
        model.join("images.txt"),
        images_txt.replacen(&first, &renamed, 1),
    )
    .unwrap();
    let out = dir.path().join("out.sfpm");
    std::fs::write(&out, b"an image of the model").unwrap();
    refused(
        &convert_images_to(&out),
        &images,
        r#"model image "../out.sfpm""#,
    );
    assert_eq!(std::fs::read(&out).unwrap(), b"an image of the model");
}

// Finding 12: `plot` overwrote without --force, over its own map too, and wrote in place.
#[test]
fn plot_needs_force_refuses_its_map_and_replaces_by_rename() {
    let dir = tempfile::tempdir().unwrap();
    let map = map_in(dir.path());
    let map_bytes = std::fs::read(&map).unwrap();
    let png = dir.path().join("plot.png");
    std::fs::write(&png, b"old png").unwrap();
    refused(&sfpmap(&["plot", s(&map), "-o", s(&png)]), &png, "--force");
    assert_eq!(std::fs::read(&png).unwrap(), b"old png");
    refused(
        &sfpmap(&["plot", s(&map), "-o", s(&map), "--force"]),
        &map,
        "input",
    );
    assert_eq!(std::fs::read(&map).unwrap(), map_bytes);
    let poses = dir.path().join("poses.txt");
    std::fs::write(&poses, "# none\n").unwrap();
    let o = sfpmap(&[
        "plot",
        s(&map),
        "--poses",
        s(&poses),
        "-o",
        s(&poses),
        "--force",
    ]);
    refused(&o, &poses, "input");

    // Replaced by a rename: a second name of the old file still reads the old bytes (a write
    // in place, killed half-way, lost the old PNG).
    let old_link = dir.path().join("old-link.png");
    std::fs::hard_link(&png, &old_link).unwrap();
    let o = sfpmap(&[
        "plot",
        s(&map),
        "-o",
        s(&png),
        "--force",
        "--width",
        "200",
        "--height",
        "150",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(std::fs::read(&old_link).unwrap(), b"old png");
    let new = std::fs::read(&png).unwrap();
    assert!(new.starts_with(b"\x89PNG\r\n\x1a\n"), "not a PNG");
    let decoder = png::Decoder::new(std::io::Cursor::new(new));
    let info = decoder.read_info().unwrap().info().clone();
    assert_eq!((info.width, info.height), (200, 150));
    let mut names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(names, ["map.sfpm", "old-link.png", "plot.png", "poses.txt"]);
}

/// A character device of our own (the same numbers as /dev/null, made with mknod in the temp
/// folder): if a regression renamed over it, no real device would be harmed. Needs root.
fn private_char_device(dir: &Path) -> Option<PathBuf> {
    let node = dir.join("null-device");
    let made = Command::new("mknod")
        .arg(&node)
        .args(["c", "1", "3"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    made.then_some(node)
}

// Finding 13: as root, `-o /dev/full` renamed the temp file over the device node.
#[test]
fn devices_and_fifos_are_never_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let map = map_in(dir.path());
    let queries = dir.path().join("queries.txt");
    std::fs::write(&queries, "q1.jpg\n").unwrap();
    let db = dir.path().join("queries.db");
    empty_database(&db);
    let model = dir.path().join("model");
    let o = sfpmap(&["export-colmap", s(&map), "-o", s(&model)]);
    assert!(o.status.success(), "{}", stderr(&o));

    let fifo = dir.path().join("fifo");
    let made = Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    let mut targets = vec![(fifo, "a FIFO")];
    match private_char_device(dir.path()) {
        Some(node) => targets.push((node, "a character device")),
        None => eprintln!("not root: the device case runs as root only"),
    }
    for (target, kind) in &targets {
        let t = s(target);
        let runs: [Vec<&str>; 6] = [
            vec!["slice", s(&map), "--level", "2", "-o", t, "--force"],
            vec!["export", s(&map), "--ply", t, "--force"],
            vec!["convert", "--colmap", s(&model), "-o", t, "--force"],
            vec!["plot", s(&map), "-o", t, "--force"],
            vec![
                "localize",
                "--map",
                s(&map),
                "--query-list",
                s(&queries),
                "--camera",
                CAMERA,
                "--database",
                s(&db),
                "-o",
                t,
                "--force",
            ],
            vec!["export", s(&map), "--tum", t, "--force"],
        ];
        for args in runs {
            refused(&sfpmap(&args), target, kind);
            let t = std::fs::symlink_metadata(target).unwrap().file_type();
            assert!(
                t.is_fifo() || t.is_char_device(),
                "{args:?} replaced {kind}"
            );
        }
    }
    // A folder as the output: refused too, with what it is.
    let o = sfpmap(&["slice", s(&map), "--level", "2", "-o", s(&model), "--force"]);
    refused(&o, &model, "a folder");
}

/// A map of about `mb` MB (one level, all points, 128 dims), written by the library.
fn big_map(path: &Path, points: usize) {
    use sfpmap::format::{Descriptors, LevelInfo, MapWriter};
    let positions: Vec<[f64; 3]> = (0..points)
        .map(|i| [i as f64 * 1e-3, (i % 97) as f64, (i % 13) as f64])
        .collect();
    let dim = 128;
    let descriptors: Vec<f32> = (0..points * dim)
        .map(|i| ((i * 2_654_435_761) % 1000) as f32 / 1000.0 - 0.5)
        .collect();
    let ids: Vec<u32> = (0..points as u32).collect();
    let mut w = MapWriter::default();
    w.set_points_world(&positions);
    w.add_level(
        LevelInfo {
            level: 0,
            stride: 4.0,
            descriptor: "sfp-v1".into(),
            dim_full: dim as u32,
            dim_short: 32,
            normalization: "l2".into(),
            extra: Default::default(),
        },
        &ids,
        Some(Descriptors::F32(&descriptors)),
        true,
    )
    .unwrap();
    w.write(path, &sfpmap::progress::Silent).unwrap();
}

/// The names in `dir` other than `keep`.
fn others(dir: &Path, keep: &str) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n != keep)
        .collect();
    v.sort();
    v
}

/// Whether `name` is a temp file of the output policy (`.NAME.sfpmap-tmp.PID.RANDOM`).
fn recognisable(name: &str) -> bool {
    name.starts_with(".out.sfpm.sfpmap-tmp.")
}

/// Whether `pid` has a file in `dir` open right now: its temp file (unnamed `O_TMPFILE` ones
/// show as `dir/#INODE (deleted)`), as slice opens nothing else there.
fn writing_into(pid: u32, dir: &Path) -> bool {
    let Ok(fds) = std::fs::read_dir(format!("/proc/{pid}/fd")) else {
        return false;
    };
    fds.flatten()
        .any(|fd| std::fs::read_link(fd.path()).is_ok_and(|target| target.parent() == Some(dir)))
}

/// Starts `slice BIG -o OUT --force`, with the named-temp fallback if `named`.
fn start_slice(input: &Path, out: &Path, named: bool) -> std::process::Child {
    let mut cmd = Command::new(bin());
    cmd.args([
        "slice",
        s(input),
        "--level",
        "0",
        "-o",
        s(out),
        "--force",
        "--quiet",
    ])
    .stdout(Stdio::null())
    .stderr(Stdio::piped());
    if named {
        cmd.env("SFPMAP_NO_TMPFILE", "1");
    }
    cmd.spawn().unwrap()
}

/// Waits until the child writes its temp file (true), or exits first (false).
fn wait_for_write(child: &mut std::process::Child, dir: &Path) -> bool {
    let deadline = Instant::now() + Duration::from_secs(120);
    while Instant::now() < deadline {
        if writing_into(child.id(), dir) {
            return true;
        }
        if child.try_wait().unwrap().is_some() {
            return false;
        }
        std::thread::sleep(Duration::from_micros(200));
    }
    panic!("slice did not start writing in 120 s");
}

fn signal(child: &std::process::Child, sig: rustix::process::Signal) {
    let pid = rustix::process::Pid::from_raw(child.id() as i32).unwrap();
    rustix::process::kill_process(pid, sig).unwrap();
}

/// Delays in `[0, 1)`, different each run (printed, to reproduce a failure).
fn fractions(n: usize) -> Vec<f64> {
    let mut x = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos() as u64
        | 1;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x % 1000) as f64 / 1000.0
        })
        .collect()
}

// Finding 14: kill -9 during a write left a 117 MB temp file behind, never cleaned.
#[test]
fn kill_9_leaves_the_old_or_the_new_file_and_no_stray_temp_file() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("big.sfpm");
    big_map(&input, 120_000);
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let out = out_dir.join("out.sfpm");
    // The new file, from one complete run; the old one, a different valid map.
    let started = Instant::now();
    let o = start_slice(&input, &out, false).wait_with_output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let full_run = started.elapsed();
    let new = std::fs::read(&out).unwrap();
    let old = std::fs::read(map_in(dir.path())).unwrap();
    for named in [false, true] {
        let mut left_behind = 0;
        let mut kills = Vec::new();
        // Mid-write for sure (the temp file is open), then at random times of the whole run.
        for (k, frac) in [None, None]
            .into_iter()
            .chain(fractions(6).into_iter().map(Some))
            .enumerate()
        {
            std::fs::write(&out, &old).unwrap();
            let mut child = start_slice(&input, &out, named);
            match frac {
                None => {
                    if !wait_for_write(&mut child, &out_dir) {
                        eprintln!("run {k}: finished before it could be killed mid-write");
                    }
                }
                Some(f) => std::thread::sleep(full_run.mul_f64(f * 1.2)),
            }
            signal(&child, rustix::process::Signal::KILL);
            let status = child.wait().unwrap();
            kills.push((frac, status.code()));
            let bytes = std::fs::read(&out).unwrap();
            assert!(
                bytes == old || bytes == new,
                "run {k} (named {named}, at {frac:?}): the output is neither the old nor the new file ({} bytes)",
                bytes.len()
            );
            for name in others(&out_dir, "out.sfpm") {
                // Unnamed temps get a recognisable name just before the rename: a kill in
                // that window leaves one in either mode, which the next write removes.
                assert!(
                    recognisable(&name),
                    "run {k} (named {named}, at {frac:?}): {name} left behind"
                );
                left_behind += 1;
            }
        }
        eprintln!(
            "named temps {named}: kills {kills:?}, {left_behind} recognisable temp files left"
        );
        // The next write into the folder removes what killed writers left.
        std::fs::write(&out, &old).unwrap();
        let o = start_slice(&input, &out, named).wait_with_output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(std::fs::read(&out).unwrap(), new);
        assert_eq!(others(&out_dir, "out.sfpm"), Vec::<String>::new());
        if named {
            assert!(
                left_behind > 0,
                "no kill landed mid-write: the cleanup went untested"
            );
        }
    }
}

// SIGINT/SIGTERM while writing: the temp file is removed, the old file kept, exit 130 / 143.
#[test]
fn sigint_and_sigterm_remove_the_temp_file() {
    use rustix::process::Signal;
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("big.sfpm");
    big_map(&input, 120_000);
    let out_dir = dir.path().join("out");
    std::fs::create_dir(&out_dir).unwrap();
    let out = out_dir.join("out.sfpm");
    let old = std::fs::read(map_in(dir.path())).unwrap();
    let mut interrupted = 0;
    for (sig, code) in [(Signal::INT, 130), (Signal::TERM, 143)] {
        for named in [true, false] {
            std::fs::write(&out, &old).unwrap();
            let mut child = start_slice(&input, &out, named);
            let mid_write = wait_for_write(&mut child, &out_dir);
            signal(&child, sig);
            let o = child.wait_with_output().unwrap();
            if mid_write && o.status.code() == Some(code) {
                interrupted += 1;
                assert_eq!(
                    std::fs::read(&out).unwrap(),
                    old,
                    "{sig:?}: the old file is gone"
                );
            } else {
                // The signal came after the rename: the new file is complete.
                assert!(o.status.success(), "{sig:?}: {:?} {}", o.status, stderr(&o));
            }
            assert_eq!(
                others(&out_dir, "out.sfpm"),
                Vec::<String>::new(),
                "{sig:?} (named {named}) left a temp file"
            );
        }
    }
    assert!(
        interrupted >= 2,
        "no signal landed mid-write ({interrupted})"
    );
}

// Review: two outputs of one command naming the same file, the second replaced the first.
#[test]
fn two_outputs_naming_one_file_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let map = map_in(dir.path());
    let a = dir.path().join("a.txt");
    let also_a = dir.path().join(".").join("a.txt");
    let o = sfpmap(&[
        "export",
        s(&map),
        "--tum",
        s(&a),
        "--images-txt",
        s(&also_a),
    ]);
    refused(&o, &also_a, "two outputs");
    assert!(!a.exists(), "an output was written before the refusal");
}
