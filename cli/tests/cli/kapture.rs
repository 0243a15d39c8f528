//! kapture in and out, checked against NAVER's PyPI package (`kapture==1.1.12`, in the test
//! venv) through `tests/kapture_check.py`: sfpmap reads what kapture's own COLMAP importer
//! writes (the shared `kapture_maupertuis` sample, from naver/kapture's `samples/`), kapture
//! reads what `export --kapture` and `localize --format kapture` write; bad folders are one
//! line naming the file and line; inputs are never written to.

use crate::python::python_with;
use crate::run::sfpmap;
use crate::shared_data::{repo_root, shared_data};
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

const CAMERA: &str = "SIMPLE_PINHOLE 1919 1079 1847.53 959.5 539.5";

fn kapture_check(args: &[&Path]) -> Vec<u8> {
    let python = python_with("kapture, numpy");
    let out = Command::new(python)
        .arg(repo_root().join("tests/kapture_check.py"))
        .args(args)
        .output()
        .expect("run tests/kapture_check.py");
    assert!(
        out.status.success(),
        "kapture_check.py {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out.stdout
}

fn read_with_pypi(dir: &Path) -> Value {
    serde_json::from_slice(&kapture_check(&[Path::new("read"), dir])).unwrap()
}

fn ok(args: &[&std::ffi::OsStr]) -> String {
    let out = sfpmap(args);
    assert!(
        out.status.success(),
        "sfpmap {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn err(args: &[&std::ffi::OsStr]) -> String {
    let out = sfpmap(args);
    assert!(!out.status.success(), "sfpmap {args:?} succeeded");
    String::from_utf8(out.stderr).unwrap()
}

macro_rules! os {
    ($($a:expr),* $(,)?) => { [$(std::ffi::OsStr::new($a)),*] };
}

/// Every file under `dir`, recursively, with its bytes.
fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.clone(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

/// The maupertuis sample (model, database copy, images) and its kapture folder as kapture's
/// importer writes it, in `tmp`.
fn pypi_kapture(tmp: &Path) -> Option<(PathBuf, PathBuf, PathBuf)> {
    let sample = shared_data("colmap/kapture_maupertuis")?;
    let model = sample.join("reconstruction");
    // The database is copied: SQLite may write beside a database it opens.
    let db = tmp.join("colmap.db");
    std::fs::copy(sample.join("colmap.db"), &db).unwrap();
    let kapture = tmp.join("kapture");
    kapture_check(&[
        Path::new("import"),
        &model,
        &db,
        &sample.join("images"),
        &kapture,
    ]);
    Some((model, db, kapture))
}

fn close(a: &Value, b: &Value, tol: f64) -> bool {
    let (a, b) = (a.as_array().unwrap(), b.as_array().unwrap());
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(x, y)| match (x.as_f64(), y.as_f64()) {
                (Some(x), Some(y)) => (x - y).abs() <= tol,
                _ => x == y,
            })
}

#[test]
fn kapture_from_pypi_converts_as_its_colmap_source_and_reads_back_in_pypi() {
    let tmp = tempfile::tempdir().unwrap();
    let Some((model, db, kapture)) = pypi_kapture(tmp.path()) else {
        return;
    };
    let before = tree(&kapture);
    let (from_kapture, from_colmap) = (tmp.path().join("k.sfpm"), tmp.path().join("c.sfpm"));
    let k = ok(&os![
        "convert",
        "--kapture",
        &kapture,
        "-o",
        &from_kapture,
        "--json"
    ]);
    let c = ok(&os![
        "convert",
        "--colmap",
        &model,
        "--database",
        &db,
        "-o",
        &from_colmap,
        "--json"
    ]);
    let (k, c): (Value, Value) = (
        serde_json::from_str(&k).unwrap(),
        serde_json::from_str(&c).unwrap(),
    );
    for key in ["points", "images", "observations", "vlad"] {
        assert_eq!(k[key], c[key], "{key}");
    }
    // The same levels; the share of variance to the last bits only, as the tracks' order
    // (kapture's observations, COLMAP's points3D) changes the order of the sums.
    let (kl, cl) = (
        k["levels"].as_array().unwrap(),
        c["levels"].as_array().unwrap(),
    );
    assert_eq!(kl.len(), 3);
    for (a, b) in kl.iter().zip(cl) {
        for key in ["level", "points", "dim_full", "dim_short", "scale_range"] {
            assert_eq!(a[key], b[key], "{key}");
        }
        let (va, vb) = (a["variance_short"].as_f64(), b["variance_short"].as_f64());
        assert!((va.unwrap() - vb.unwrap()).abs() < 1e-9, "{a} {b}");
    }
    assert_eq!(
        before,
        tree(&kapture),
        "convert --kapture wrote into its input"
    );

    // Both maps exported as kapture: the same tables, byte for byte.
    let (kout, cout) = (tmp.path().join("kout"), tmp.path().join("cout"));
    ok(&os!["export", &from_kapture, "--kapture", &kout]);
    ok(&os!["export", &from_colmap, "--kapture", &cout]);
    for f in [
        "sensors/sensors.txt",
        "sensors/records_camera.txt",
        "sensors/trajectories.txt",
    ] {
        assert_eq!(
            std::fs::read(kout.join(f)).unwrap(),
            std::fs::read(cout.join(f)).unwrap(),
            "{f}"
        );
    }

    // What kapture reads of sfpmap's export is what its importer wrote: poses (quaternions
    // normalised from the model's 6 digits), points (stored as f32), colours, each point's
    // observations by image and keypoint position.
    let source = read_with_pypi(&kapture);
    let exported = read_with_pypi(&kout);
    assert_eq!(source["sensors"], exported["sensors"]);
    let images = source["images"].as_object().unwrap();
    assert_eq!(images.len(), 4);
    for (name, pose) in images {
        assert!(close(pose, &exported["images"][name], 1e-6), "{name}");
    }
    let (sp, ep) = (
        source["points"].as_array().unwrap(),
        exported["points"].as_array().unwrap(),
    );
    assert_eq!(sp.len(), 1039);
    assert_eq!(sp.len(), ep.len());
    for (a, b) in sp.iter().zip(ep) {
        assert!(close(a, b, 1e-5), "{a} {b}");
    }
    assert_eq!(
        exported["keypoints"]["sfpmap"],
        serde_json::json!(["float32", 2])
    );
    assert_eq!(source["observations"], exported["observations"]);

    // And sfpmap reads its own export back to the same map geometry.
    let again = tmp.path().join("again.sfpm");
    let a: Value = serde_json::from_str(&ok(&os![
        "convert",
        "--kapture",
        &kout,
        "-o",
        &again,
        "--json"
    ]))
    .unwrap();
    assert_eq!(a["points"], k["points"]);
    assert_eq!(a["observations"], k["observations"]);
    assert!(a["geometry_only"].as_bool().unwrap());
}

#[test]
fn localize_format_kapture_is_read_by_pypi_kapture() {
    let tmp = tempfile::tempdir().unwrap();
    let Some((_, db, kapture)) = pypi_kapture(tmp.path()) else {
        return;
    };
    let map = tmp.path().join("m.sfpm");
    ok(&os!["convert", "--kapture", &kapture, "-o", &map]);
    let list = tmp.path().join("queries.txt");
    std::fs::write(&list, "00.jpg\n01.jpg\n02.jpg\n03.jpg\n").unwrap();
    let out = tmp.path().join("poses");
    ok(&os![
        "localize",
        "--map",
        &map,
        "--query-list",
        &list,
        "--camera",
        CAMERA,
        "--database",
        &db,
        "-o",
        &out,
        "--format",
        "kapture",
        "--quiet"
    ]);
    let read = read_with_pypi(&out);
    let source = read_with_pypi(&kapture);
    assert_eq!(read["sensors"], source["sensors"]);
    let images = read["images"].as_object().unwrap();
    assert_eq!(images.len(), 4);
    for (name, pose) in images {
        let (p, s) = (
            pose.as_array().unwrap(),
            source["images"][name].as_array().unwrap(),
        );
        // Localized against a map of those very features: within a millimetre-scale of SfM.
        assert!(
            close(&Value::from(&p[1..5]), &Value::from(&s[1..5]), 1e-3),
            "{name}: {pose} vs {s:?}"
        );
        assert!(
            close(&Value::from(&p[5..]), &Value::from(&s[5..]), 1e-2),
            "{name}: {pose} vs {s:?}"
        );
    }
    // A second run without --force refuses the folder's files, naming the first.
    let e = err(&os![
        "localize",
        "--map",
        &map,
        "--query-list",
        &list,
        "--camera",
        CAMERA,
        "--database",
        &db,
        "-o",
        &out,
        "--format",
        "kapture"
    ]);
    assert!(
        e.contains("sensors/sensors.txt: exists; pass --force to overwrite"),
        "{e}"
    );
}

/// A folder of one camera, one image with a pose, one point observed by its keypoint 0.
fn small_kapture(dir: &Path) {
    let write = |f: &str, text: &str| {
        let p = dir.join(f);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    };
    let h = "# kapture format: 1.1\n";
    write(
        "sensors/sensors.txt",
        &format!("{h}cam0, , camera, SIMPLE_PINHOLE, 640, 480, 500, 320, 240\n"),
    );
    write(
        "sensors/trajectories.txt",
        &format!(
            "{h}# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz\n0, cam0, 1, 0, 0, 0, 0, 0, 0\n"
        ),
    );
    write(
        "sensors/records_camera.txt",
        &format!("{h}0, cam0, a.jpg\n"),
    );
    write(
        "reconstruction/points3d.txt",
        &format!("{h}0, 0, 5, 1, 2, 3\n"),
    );
    write(
        "reconstruction/observations.txt",
        &format!("{h}0, kp, a.jpg, 0\n"),
    );
    write(
        "reconstruction/keypoints/kp/keypoints.txt",
        &format!("{h}kp, float32, 2\n"),
    );
    let xy: Vec<u8> = [320f32, 240.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    std::fs::write(dir.join("reconstruction/keypoints/kp/a.jpg.kpt"), xy).unwrap();
}

#[test]
fn bad_kapture_folders_are_one_line_naming_file_and_line() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("k");
    let out = tmp.path().join("m.sfpm");
    small_kapture(&dir);
    let convert = || err(&os!["convert", "--kapture", &dir, "-o", &out]);
    // The folder converts as it is (a geometry map: no descriptors).
    ok(&os!["convert", "--kapture", &dir, "-o", &out]);
    std::fs::remove_file(&out).unwrap();

    let before = tree(&dir);
    let kpt = dir.join("reconstruction/keypoints/kp/a.jpg.kpt");
    std::fs::write(&kpt, [0u8; 10]).unwrap();
    assert_eq!(
        convert(),
        format!(
            "error: {}: 10 bytes is not a whole number of 8-byte records (truncated?)\n",
            kpt.display()
        )
    );
    std::fs::write(&kpt, &before.iter().find(|(p, _)| *p == kpt).unwrap().1).unwrap();

    let trajectories = dir.join("sensors/trajectories.txt");
    std::fs::write(
        &trajectories,
        "# kapture format: 1.1\n# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz\n0, cam0, 1, 0, 0, 0, 0, 0, 0\n1, cam9, 1, 0, 0, 0, 0, 0, 0\n",
    )
    .unwrap();
    assert_eq!(
        convert(),
        format!(
            "error: {}:4: device \"cam9\" is not in sensors/sensors.txt or sensors/rigs.txt\n",
            trajectories.display()
        )
    );

    let sensors = dir.join("sensors/sensors.txt");
    std::fs::remove_file(&sensors).unwrap();
    assert_eq!(
        convert(),
        format!(
            "error: {}: missing (a kapture folder needs it for the cameras)\n",
            sensors.display()
        )
    );
    assert!(!out.exists(), "a refused conversion left an output");
}

/// A kapture folder holds files its tables do not list: `convert --kapture` writes nothing
/// inside it, a new file or one already there, with or without `--force`.
#[test]
fn convert_writes_nothing_inside_its_kapture_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("k");
    small_kapture(&dir);
    let stray = dir.join("reconstruction/stray.sfpm");
    std::fs::write(&stray, b"not a map").unwrap();
    let before = tree(&dir);
    for out in [dir.join("new.sfpm"), dir.join("sensors/new.sfpm"), stray] {
        for force in [false, true] {
            let mut args = os!["convert", "--kapture", &dir, "-o", &out].to_vec();
            if force {
                args.push(std::ffi::OsStr::new("--force"));
            }
            assert_eq!(
                err(&args),
                format!(
                    "error: {}: lies inside the input folder {}; write it outside that folder\n",
                    out.display(),
                    dir.display()
                )
            );
        }
    }
    assert_eq!(tree(&dir), before, "convert --kapture wrote into its input");
}

#[test]
fn export_kapture_overwrites_nothing_without_force_and_leaves_its_map() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("k");
    small_kapture(&dir);
    let map = tmp.path().join("m.sfpm");
    ok(&os!["convert", "--kapture", &dir, "-o", &map]);
    let map_bytes = std::fs::read(&map).unwrap();
    let out = tmp.path().join("out");
    ok(&os!["export", &map, "--kapture", &out]);
    assert_eq!(std::fs::read(&map).unwrap(), map_bytes);
    let obs = std::fs::read_to_string(out.join("reconstruction/observations.txt")).unwrap();
    assert!(obs.ends_with("\n0, sfpmap, a.jpg, 0\n"), "{obs}");
    // Exporting into the folder the map was made from overwrites nothing without --force.
    let e = err(&os!["export", &map, "--kapture", &dir]);
    assert!(
        e.contains("sensors/sensors.txt: exists; pass --force"),
        "{e}"
    );
    // The map itself is never an output.
    let e = err(&os![
        "export",
        &map,
        "--kapture",
        &out,
        "--force",
        "--ply",
        &map
    ]);
    assert!(e.contains("is an input of this command"), "{e}");
    assert_eq!(std::fs::read(&map).unwrap(), map_bytes);
}

/// A COLMAP text model of one camera and the images `names` (identity poses), each seeing
/// the one point at keypoint 0.
fn text_model(dir: &Path, names: &[&str]) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(
        dir.join("cameras.txt"),
        "1 SIMPLE_PINHOLE 640 480 500 320 240\n",
    )
    .unwrap();
    let mut images = String::new();
    let mut track = String::new();
    for (i, name) in names.iter().enumerate() {
        let id = i + 1;
        images.push_str(&format!("{id} 1 0 0 0 0 0 {i} 1 {name}\n320 240 1\n"));
        track.push_str(&format!(" {id} 0"));
    }
    std::fs::write(dir.join("images.txt"), images).unwrap();
    std::fs::write(
        dir.join("points3D.txt"),
        format!("1 0 0 5 1 2 3 0.5{track}\n"),
    )
    .unwrap();
}

/// What a kapture table cannot hold (a comma in a name, two images of one name) is refused
/// before anything is written: by `export --kapture`, whatever other outputs it is asked
/// for, and by `localize --format kapture`, before any query is localized.
#[test]
fn names_kapture_cannot_hold_are_refused_before_anything_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    let ply = tmp.path().join("m.ply");
    let kapture = tmp.path().join("k");
    for (names, words) in [
        (&["a.jpg", "a,b.jpg"][..], r#"image 2: name "a,b.jpg" "#),
        (
            &["a.jpg", "b.jpg", "a.jpg"][..],
            r#"image 3: its name "a.jpg" is image 1's too"#,
        ),
    ] {
        let model = tmp.path().join("model");
        text_model(&model, names);
        let map = tmp.path().join("m.sfpm");
        ok(&os!["convert", "--colmap", &model, "-o", &map, "--force"]);
        let e = err(&os!["export", &map, "--ply", &ply, "--kapture", &kapture]);
        assert!(e.starts_with(&format!("error: {}: ", map.display())), "{e}");
        assert!(e.contains(words), "{e}");
        assert_eq!(e.lines().count(), 1, "{e}");
        assert!(!ply.exists(), "the PLY was written before the refusal");
        assert!(!kapture.exists(), "the kapture folder was made: {e}");
    }
    // A name kapture holds but COLMAP's images.txt does not: the kapture folder is not
    // written either when --colmap refuses.
    let spaced = tmp.path().join("spaced");
    small_kapture(&spaced);
    let h = "# kapture format: 1.1\n";
    std::fs::write(
        spaced.join("sensors/records_camera.txt"),
        format!("{h}0, cam0, IMG 01.jpg\n"),
    )
    .unwrap();
    std::fs::write(
        spaced.join("reconstruction/observations.txt"),
        format!("{h}0, kp, IMG 01.jpg, 0\n"),
    )
    .unwrap();
    let kp = spaced.join("reconstruction/keypoints/kp");
    std::fs::rename(kp.join("a.jpg.kpt"), kp.join("IMG 01.jpg.kpt")).unwrap();
    let map = tmp.path().join("m.sfpm");
    ok(&os!["convert", "--kapture", &spaced, "-o", &map, "--force"]);
    let colmap = tmp.path().join("c");
    let e = err(&os![
        "export",
        &map,
        "--kapture",
        &kapture,
        "--colmap",
        &colmap
    ]);
    assert!(e.contains("which a COLMAP images.txt cannot hold"), "{e}");
    assert!(!kapture.exists() && !colmap.exists(), "{e}");

    // A query list naming "a,b.jpg": refused for kapture output before any query runs.
    let model = tmp.path().join("model");
    text_model(&model, &["a.jpg", "b.jpg"]);
    let map = tmp.path().join("ok.sfpm");
    ok(&os!["convert", "--colmap", &model, "-o", &map]);
    let list = tmp.path().join("queries.txt");
    std::fs::write(&list, "a,b.jpg SIMPLE_PINHOLE 640 480 500 320 240\n").unwrap();
    let poses = tmp.path().join("poses");
    let e = err(&os![
        "localize",
        "--map",
        &map,
        "--query-list",
        &list,
        "--database",
        &tmp.path().join("none.db"),
        "-o",
        &poses,
        "--format",
        "kapture"
    ]);
    assert!(
        e.contains(r#""a,b.jpg""#) && e.contains("--format kapture cannot hold"),
        "{e}"
    );
    assert!(!poses.exists());
}
