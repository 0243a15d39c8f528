//! `sfpmap extract` and `sfpmap convert --images` end to end on the real sacre-coeur scene
//! (10 images, ~1000 px): the real binary, the real runtime (found, or fetched by the binary
//! itself on first use), the embedded model.
#![cfg(all(feature = "onnx", feature = "colmap"))]

use crate::run::sfpmap;
use serde_json::Value;
use sfpmap::format::Map;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn scene() -> PathBuf {
    crate::shared_data::repo_root().join("../shared/data/scenes/sacre-coeur")
}

fn ok(args: &[&std::ffi::OsStr]) -> Value {
    let out = sfpmap(args);
    assert!(
        out.status.success(),
        "sfpmap {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or(Value::Null)
}

fn os<S: AsRef<std::ffi::OsStr> + ?Sized>(s: &S) -> &std::ffi::OsStr {
    s.as_ref()
}

/// The embedded model's contract (dims, strides, level ids come from its metadata).
fn contract() -> sfpmap::extract::contract::Contract {
    sfpmap::extract::Extractor::new(
        &sfpmap::extract::ExtractorOptions::default(),
        &sfpmap::progress::Silent,
    )
    .expect("runtime and embedded model")
    .contract()
    .clone()
}

fn convert(images: &Path, out: &Path, extra: &[&str]) -> Output {
    let model = scene().join("sparse-map");
    let mut args = vec![
        os("convert"),
        os("--colmap"),
        model.as_os_str(),
        os("--images"),
        images.as_os_str(),
        os("-o"),
        out.as_os_str(),
        os("--json"),
    ];
    args.extend(extra.iter().map(os));
    sfpmap(&args)
}

#[test]
fn convert_images_builds_a_multilevel_map_that_slices_to_level_2_short() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sfp.sfpm");
    let run = convert(&scene().join("images"), &out, &[]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let summary: Value = serde_json::from_slice(&run.stdout).unwrap();
    let model_points = summary["model_points"].as_u64().unwrap();
    let points = summary["points"].as_u64().unwrap();
    assert!(points > 0 && points <= model_points, "{summary}");
    assert_eq!(
        summary["dropped_points"].as_u64().unwrap(),
        model_points - points
    );
    let levels = summary["levels"].as_array().unwrap();
    assert!(
        levels
            .iter()
            .filter(|l| l["points"].as_u64() > Some(0))
            .count()
            >= 3,
        "{summary}"
    );

    ok(&[os("verify"), out.as_os_str()]);
    let map = Map::open(&out).unwrap();
    let meta = map.metadata();
    let model = meta.provenance.model.as_ref().expect("model provenance");
    assert_eq!(model.bytes, sfpmap::extract::DEFAULT_MODEL.len() as u64);
    assert_eq!(
        meta.provenance.parameters["contract"]["sfp.contract"],
        "sfp-extractor/3"
    );
    let c = contract();
    assert!(map.level_ids().iter().all(|l| c.level_ids.contains(l)));
    let (global, dim) = map.image_global().unwrap().expect("global descriptors");
    assert_eq!((global.len() / dim, dim), (8, c.global_dim));
    let i2 = c.level_index(2).expect("the model has a level 2");
    let (short2, full2) = (c.dims[i2], c.full_dims[i2]);
    let level2 = map.level(2).unwrap();
    assert_eq!((level2.dim_short(), level2.dim_full()), (short2, full2));
    assert_eq!(level2.info().stride, f64::from(c.strides[i2]));
    assert!(level2.info().extra["assignment"]
        .as_str()
        .unwrap()
        .contains("mean of score_d"));
    // Every point is in some level; every observation of the map refers to a kept point.
    let mut in_level = vec![false; map.n_points() as usize];
    for level in map.levels() {
        for &p in level.points().unwrap().iter() {
            in_level[p as usize] = true;
        }
    }
    assert!(in_level.iter().all(|&b| b));
    let full_short = level2.desc_short().unwrap().into_owned();
    let full_rest = level2.desc_rest().unwrap().unwrap().into_owned();
    // Full descriptors are unit vectors (f16 rounding aside).
    for i in 0..level2.len() {
        let rest2 = full2 - short2;
        let norm: f32 = full_short[i * short2..(i + 1) * short2]
            .iter()
            .chain(&full_rest[i * rest2..(i + 1) * rest2])
            .map(|v| v.to_f32() * v.to_f32())
            .sum();
        assert!((norm - 1.0).abs() < 5e-3, "point {i}: |full|^2 = {norm}");
    }

    let sliced = dir.path().join("l2.sfpm");
    let s = sfpmap(&[
        os("slice"),
        out.as_os_str(),
        os("--level"),
        os("2"),
        os("--short"),
        os("-o"),
        sliced.as_os_str(),
    ]);
    assert!(s.status.success(), "{}", String::from_utf8_lossy(&s.stderr));
    ok(&[os("verify"), sliced.as_os_str()]);
    let small = Map::open(&sliced).unwrap();
    assert_eq!(small.level_ids(), vec![2]);
    let l = small.level(2).unwrap();
    assert!(!l.has_rest());
    assert_eq!(l.len(), level2.len());
    assert_eq!(l.desc_short().unwrap().into_owned(), full_short);
    assert!(std::fs::metadata(&sliced).unwrap().len() < std::fs::metadata(&out).unwrap().len());

    // Deterministic: the same inputs give the same bytes.
    let again = dir.path().join("again.sfpm");
    assert!(convert(&scene().join("images"), &again, &[])
        .status
        .success());
    assert_eq!(std::fs::read(&out).unwrap(), std::fs::read(&again).unwrap());
}

#[test]
fn missing_images_are_named_unless_allowed() {
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let mut names: Vec<PathBuf> = std::fs::read_dir(scene().join("images"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    // Drop an image the map's model uses (db_images.txt lists them), so its absence matters.
    let listed = scene().join("db_images.txt");
    let db_images =
        std::fs::read_to_string(&listed).unwrap_or_else(|e| panic!("{}: {e}", listed.display()));
    let dropped_name = db_images
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .unwrap_or_else(|| panic!("{}: no image names", listed.display()))
        .to_string();
    let before = names.len();
    names.retain(|p| p.file_name().unwrap().to_string_lossy() != dropped_name.as_str());
    assert_eq!(names.len() + 1, before, "{dropped_name} is in images/");
    for p in &names {
        std::fs::copy(p, images.join(p.file_name().unwrap())).unwrap();
    }
    let out = dir.path().join("m.sfpm");
    let run = convert(&images, &out, &[]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(
        stderr.contains(&dropped_name) && stderr.contains("--allow-missing"),
        "{stderr}"
    );
    assert!(!out.exists());
    let run = convert(&images, &out, &["--allow-missing"]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let summary: Value = serde_json::from_slice(&run.stdout).unwrap();
    assert_eq!(summary["missing_images"], serde_json::json!([dropped_name]));
    ok(&[os("verify"), out.as_os_str()]);
}

/// A failed command prints one error line, `error: …`, that names `path` exactly once (an
/// error chain whose messages contain their sources would repeat it). Warnings before it
/// (the runtime fetched on a fresh machine) are allowed.
fn assert_one_line_naming_once(run: &Output, path: &Path) {
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    let path = path.to_str().unwrap();
    let lines: Vec<&str> = stderr
        .lines()
        .filter(|l| !l.starts_with("warning: "))
        .collect();
    assert!(stderr.ends_with('\n') && lines.len() == 1, "{stderr:?}");
    let stderr = lines[0];
    assert!(stderr.starts_with("error: "), "{stderr}");
    assert_eq!(stderr.matches(path).count(), 1, "{path} in {stderr}");
}

#[test]
fn bad_model_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.onnx");
    std::fs::write(&bad, b"\x08\x07garbage").unwrap();
    let out = dir.path().join("m.sfpm");
    for model in [bad, dir.path().join("absent.onnx")] {
        let run = convert(
            &scene().join("images"),
            &out,
            &["--model", model.to_str().unwrap()],
        );
        assert_one_line_naming_once(&run, &model);
        assert!(!out.exists());
    }
}

#[test]
fn bad_images_are_named_once() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f.h5");
    // No known format; a JPEG header then garbage (a decoder error); a PNG cut after IHDR.
    let unknown = dir.path().join("not-an-image.jpg");
    std::fs::write(&unknown, b"not a JPEG").unwrap();
    let bad_jpeg = dir.path().join("bad.jpg");
    std::fs::write(&bad_jpeg, b"\xff\xd8\xff\xe0\x00\x10JFIF\x00garbage").unwrap();
    let cut_png = dir.path().join("cut.png");
    std::fs::write(&cut_png, b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR").unwrap();
    let absent = dir.path().join("absent.png");
    for image in [&unknown, &bad_jpeg, &cut_png, &absent] {
        let run = sfpmap(&[os("extract"), image.as_os_str(), os("-o"), out.as_os_str()]);
        assert_one_line_naming_once(&run, image);
        assert!(!out.exists());
    }
    // In `convert --images` too (its error wraps the extractor's): every model image is bad.
    let images = dir.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let listed = scene().join("db_images.txt");
    for name in std::fs::read_to_string(&listed)
        .unwrap_or_else(|e| panic!("{}: {e}", listed.display()))
        .lines()
        .filter(|l| !l.trim().is_empty())
    {
        std::fs::write(
            images.join(name.trim()),
            b"\xff\xd8\xff\xe0\x00\x10JFIF\x00garbage",
        )
        .unwrap();
    }
    let map = dir.path().join("m.sfpm");
    let run = convert(&images, &map, &[]);
    assert_one_line_naming_once(&run, &images);
    assert!(!map.exists());
}

#[test]
fn extract_writes_hloc_features_h5() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("features.h5");
    let images = scene().join("images");
    let summary = ok(&[
        os("extract"),
        images.as_os_str(),
        os("-o"),
        out.as_os_str(),
        os("--json"),
    ]);
    assert_eq!(summary["images"], 10);
    assert_eq!(summary["main_level"], 2);
    let c = contract();
    let main_full = c.full_dims[c.level_index(2).unwrap()] as u64;
    assert!(summary["ms_median"].as_f64().unwrap() > 0.0);
    let file = hdf5_pure::File::open(&out).unwrap();
    let mut names: Vec<String> = std::fs::read_dir(&images)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    for name in &names {
        let kp = file.dataset(&format!("{name}/keypoints")).unwrap();
        let shape = kp.shape().unwrap();
        assert_eq!(shape[1], 2);
        let n = shape[0];
        assert!(n > 0, "{name}: no level-2 keypoints");
        let desc = file.dataset(&format!("{name}/descriptors")).unwrap();
        assert_eq!(desc.shape().unwrap(), vec![main_full, n]);
        assert_eq!(
            file.dataset(&format!("{name}/scores"))
                .unwrap()
                .shape()
                .unwrap(),
            vec![n]
        );
        let size = file.dataset(&format!("{name}/image_size")).unwrap();
        assert_eq!(size.shape().unwrap(), vec![2]);
        for (i, level) in c.level_ids.iter().enumerate() {
            let (full, short) = (c.full_dims[i] as u64, c.dims[i] as u64);
            let g = format!("{name}/level{level}_");
            let n = file
                .dataset(&format!("{g}keypoints"))
                .unwrap()
                .shape()
                .unwrap()[0];
            assert_eq!(
                file.dataset(&format!("{g}descriptors"))
                    .unwrap()
                    .shape()
                    .unwrap(),
                vec![full, n]
            );
            assert_eq!(
                file.dataset(&format!("{g}descriptors_short"))
                    .unwrap()
                    .shape()
                    .unwrap(),
                vec![short, n]
            );
        }
    }
    // An existing output is not overwritten without --force.
    let again = sfpmap(&[os("extract"), images.as_os_str(), os("-o"), out.as_os_str()]);
    assert!(!again.status.success());
}

/// `extract --model aliked-n16`: hloc's layout with the built-in ALIKED's 128-dim descriptors
/// and its name; no `global_descriptor` and so no `sfp.global_max_side` (the model has no
/// global head).
#[test]
fn extract_with_aliked_writes_no_global_side() {
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("images");
    std::fs::create_dir(&images).unwrap();
    let name = std::fs::read_dir(scene().join("images"))
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .min()
        .unwrap();
    std::fs::copy(scene().join("images").join(&name), images.join(&name)).unwrap();
    let name = name.to_string_lossy().into_owned();
    let out = dir.path().join("feats-aliked-n16.h5");
    let summary = ok(&[
        os("extract"),
        images.as_os_str(),
        os("--model"),
        os("aliked-n16"),
        os("-o"),
        out.as_os_str(),
        os("--json"),
    ]);
    assert_eq!(summary["images"], 1);
    let file = sfpmap::io::features_h5::H5Features::open(&out).unwrap();
    assert_eq!(file.feature_name().unwrap().as_deref(), Some("aliked-n16"));
    assert_eq!(file.root_string("sfp.global_max_side").unwrap(), None);
    let features = file.features(&name).unwrap().unwrap();
    assert!(features.global.is_none());
    let [set] = &features.sets[..] else {
        panic!("one feature set, not {}", features.sets.len())
    };
    assert_eq!(set.dim, 128);
    let n = set.keypoints.len();
    assert!(n > 100, "{n} keypoints");
    assert_eq!(set.descriptors.len(), n * 128);
}

/// `localize --model` with another model than the map's runs only when it makes the map's
/// levels at the map's dimensions: an ALIKED map (level 0, 128 dims) with SFP, and an SFP map
/// with ALIKED, are refused up front, naming the map, both models and the level, before any
/// query is extracted and without writing the output.
#[test]
fn another_model_of_other_dimensions_is_refused_up_front() {
    let dir = tempfile::tempdir().unwrap();
    let images = scene().join("images");
    let (aliked, sfp) = (dir.path().join("aliked.sfpm"), dir.path().join("sfp.sfpm"));
    for (map, extra, descriptors) in [
        (&aliked, &["--model", "aliked-n16"][..], "aliked-n16"),
        (&sfp, &[][..], "sfp"),
    ] {
        let run = convert(&images, map, extra);
        assert!(
            run.status.success(),
            "{}",
            String::from_utf8_lossy(&run.stderr)
        );
        // The report and the provenance say what the descriptors are, and the level rule
        // the map was made by (ALIKED: one level).
        let report: Value = serde_json::from_slice(&run.stdout).unwrap();
        assert_eq!(report["descriptors"], descriptors, "{report}");
        let provenance = Map::open(map).unwrap().metadata().provenance.clone();
        assert_eq!(provenance.parameters["descriptors"], descriptors);
        let rule = provenance.parameters["level_rule"].as_str().unwrap();
        assert_eq!(
            rule.starts_with("one level"),
            descriptors == "aliked-n16",
            "{rule}"
        );
    }
    // The ALIKED map's descriptors are at the SIFT model's observations: its VLAD codebook
    // has at least 64 centroids (vlad::DescribedAt::ModelObservations).
    let info = ok(&[os("info"), aliked.as_os_str(), os("--json")]);
    assert_eq!(info["retrieval"]["vlad"]["clusters"], 64, "{info}");
    let sfp_v2 = crate::shared_data::repo_root().join("models/sfp-v2.onnx");
    for (map, model, holds, other) in [
        (
            &aliked,
            sfp_v2.as_os_str(),
            "\"aliked-n16\" (level 0: 128 dimensions)",
            "\"sfp-v2\"",
        ),
        (
            &sfp,
            os("aliked-n16"),
            "\"sfp-v3\" (level 0: 240 dimensions)",
            "\"aliked-n16\"",
        ),
    ] {
        let poses = dir.path().join("poses.txt");
        let run = sfpmap(&[
            os("localize"),
            os("--map"),
            map.as_os_str(),
            os("--model"),
            model,
            os("--query-list"),
            scene().join("queries.txt").as_os_str(),
            os("--images"),
            images.as_os_str(),
            os("-o"),
            poses.as_os_str(),
        ]);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{stderr}");
        assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
        assert!(
            stderr.contains(&map.display().to_string())
                && stderr.contains(holds)
                && stderr.contains(&format!("which model {other} does not make")),
            "{stderr}"
        );
        assert!(!poses.exists());
    }
}

/// A fresh machine: no runtime anywhere. The first command that needs it fetches it into the
/// XDG cache (with a warning), `setup` then finds it there; a bad `ORT_DYLIB_PATH` is an error.
#[test]
fn runtime_is_fetched_on_first_use_and_discovery_order_holds() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    let run = |envs: &[(&str, &std::ffi::OsStr)], args: &[&std::ffi::OsStr]| {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_sfpmap"));
        cmd.args(args).env_remove("ORT_DYLIB_PATH");
        for (k, v) in envs {
            cmd.env(k, v);
        }
        cmd.output().expect("sfpmap runs")
    };
    let image = scene().join("images/02928139_3448003521.jpg");
    let h5 = dir.path().join("f.h5");
    let first = run(
        &[("XDG_CACHE_HOME", cache.as_os_str())],
        &[os("extract"), image.as_os_str(), os("-o"), h5.as_os_str()],
    );
    let stderr = String::from_utf8_lossy(&first.stderr);
    assert!(first.status.success(), "{stderr}");
    assert!(stderr.contains("fetching"), "{stderr}");
    let lib = cache.join("sfpmap/onnxruntime-1.31.1/libonnxruntime.so.1.31.1");
    assert!(lib.is_file());

    let setup = run(
        &[("XDG_CACHE_HOME", cache.as_os_str())],
        &[os("setup"), os("--check"), os("--json")],
    );
    assert!(
        setup.status.success(),
        "{}",
        String::from_utf8_lossy(&setup.stderr)
    );
    let report: Value = serde_json::from_slice(&setup.stdout).unwrap();
    assert_eq!(report["fetched"], false);
    assert_eq!(report["version"], "1.31.1");
    assert_eq!(report["active"], lib.to_str().unwrap());

    // ORT_DYLIB_PATH wins, and must name a file.
    let bogus = dir.path().join("nowhere/libonnxruntime.so");
    let bad = run(
        &[
            ("XDG_CACHE_HOME", cache.as_os_str()),
            ("ORT_DYLIB_PATH", bogus.as_os_str()),
        ],
        &[
            os("extract"),
            image.as_os_str(),
            os("-o"),
            dir.path().join("g.h5").as_os_str(),
        ],
    );
    assert!(!bad.status.success());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        stderr.contains("ORT_DYLIB_PATH") && stderr.contains("nowhere"),
        "{stderr}"
    );
    // A library of another release is refused before it is loaded: a fake as large as a real
    // one (the size check passes) that declares VERS_1.30.0, the symbol version it reads.
    let fake = dir.path().join("libonnxruntime.so.1.30.0");
    let mut bytes = b"\x7fELF".to_vec();
    bytes.resize(1 << 20, 0);
    bytes.extend_from_slice(b"GLIBC_2.2.5\0VERS_1.30.0\0");
    std::fs::write(&fake, &bytes).unwrap();
    let bad = run(
        &[
            ("XDG_CACHE_HOME", cache.as_os_str()),
            ("ORT_DYLIB_PATH", fake.as_os_str()),
        ],
        &[os("setup"), os("--check")],
    );
    assert!(!bad.status.success());
    let stderr = String::from_utf8_lossy(&bad.stderr);
    assert!(
        stderr.contains(fake.to_str().unwrap())
            && stderr.contains("is ONNX Runtime 1.30.0; sfpmap needs 1.31.1"),
        "{stderr}"
    );
}

/// Images smaller than their cameras (a downscaled copy of the folder) still give a map: the
/// observations are scaled to the files, with a warning.
#[test]
fn downscaled_images_are_sampled_at_scaled_observations() {
    let dir = tempfile::tempdir().unwrap();
    let images = dir.path().join("half");
    std::fs::create_dir(&images).unwrap();
    for entry in std::fs::read_dir(scene().join("images")).unwrap() {
        let path = entry.unwrap().path();
        let img = image::open(&path).unwrap();
        img.resize_exact(
            img.width() / 2,
            img.height() / 2,
            image::imageops::FilterType::Triangle,
        )
        .save(images.join(path.file_name().unwrap()))
        .unwrap();
    }
    let out = dir.path().join("half.sfpm");
    let run = convert(&images, &out, &[]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(stderr.contains("observations are scaled"), "{stderr}");
    let summary: Value = serde_json::from_slice(&run.stdout).unwrap();
    assert!(summary["points"].as_u64().unwrap() > 0);
    ok(&[os("verify"), out.as_os_str()]);
}

/// `--resize-max` runs the network on a smaller image; keypoints come back in the file's pixels.
#[test]
fn resized_extraction_reports_keypoints_in_original_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let image = scene().join("images/02928139_3448003521.jpg");
    let (w, h) = image::image_dimensions(&image).unwrap();
    let out = dir.path().join("small.h5");
    ok(&[
        os("extract"),
        image.as_os_str(),
        os("-o"),
        out.as_os_str(),
        os("--resize-max"),
        os("320"),
        os("--level"),
        os("1"),
    ]);
    let file = hdf5_pure::File::open(&out).unwrap();
    let name = "02928139_3448003521.jpg";
    let size = file
        .dataset(&format!("{name}/image_size"))
        .unwrap()
        .read_i64()
        .unwrap();
    assert_eq!(size, vec![i64::from(w), i64::from(h)]);
    let kps = file
        .dataset(&format!("{name}/keypoints"))
        .unwrap()
        .read_f32()
        .unwrap();
    assert!(!kps.is_empty());
    let scale = w.max(h) as f32 / 320.0;
    let (mut max_x, mut max_y) = (0.0f32, 0.0f32);
    for k in kps.chunks_exact(2) {
        assert!(k[0] >= -0.5 && k[0] <= w as f32 && k[1] >= -0.5 && k[1] <= h as f32);
        max_x = max_x.max(k[0]);
        max_y = max_y.max(k[1]);
    }
    // Keypoints spread over the whole original image, not only its top-left 320 px.
    assert!(
        max_x > 320.0 || max_y > 320.0,
        "max ({max_x}, {max_y}), scale {scale}"
    );
}

/// The global descriptor is computed on a 512-px copy by default; the map records the side
/// (metadata `global_max_side`), `--global-max-side 0` takes the input's own and records none,
/// `extract` stores its side as `sfp.global_max_side`, and `localize` warns when a file's side
/// is not the map's.
#[test]
fn global_descriptors_follow_the_side_the_map_records() {
    use sfpmap::extract::{image, Extractor, ExtractorOptions, GLOBAL_MAX_SIDE};
    let dir = tempfile::tempdir().unwrap();
    let images = scene().join("images");
    let mut extractor =
        Extractor::new(&ExtractorOptions::default(), &sfpmap::progress::Silent).unwrap();
    let cosine = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();

    let by_default = dir.path().join("default.sfpm");
    assert!(convert(&images, &by_default, &[]).status.success());
    let input_side = dir.path().join("input.sfpm");
    assert!(convert(&images, &input_side, &["--global-max-side", "0"])
        .status
        .success());
    let by_default = Map::open(&by_default).unwrap();
    let input_side = Map::open(&input_side).unwrap();
    assert_eq!(by_default.metadata().global_max_side, Some(GLOBAL_MAX_SIDE));
    assert_eq!(
        by_default.metadata().provenance.parameters["global_max_side"],
        GLOBAL_MAX_SIDE
    );
    assert_eq!(input_side.metadata().global_max_side, None);

    // Image 0's stored descriptors against the network on the file and on its 512-px copy.
    let name = by_default
        .images()
        .unwrap()
        .unwrap()
        .name(0)
        .unwrap()
        .to_string();
    let input = image::load(&images.join(&name), extractor.contract().gray_weights, None).unwrap();
    let own = extractor.run(&input).unwrap().global;
    let copy = input
        .downscaled(GLOBAL_MAX_SIDE)
        .expect("the image is larger");
    let small = extractor.run(&copy).unwrap().global;
    let first = |map: &Map<'_>| -> Vec<f32> {
        let (g, dim) = map.image_global().unwrap().unwrap();
        g[..dim].iter().map(|v| v.to_f32()).collect()
    };
    let (stored, stored_own) = (first(&by_default), first(&input_side));
    assert!(cosine(&stored, &small) > 0.999);
    assert!(cosine(&stored_own, &own) > 0.999);
    assert!(
        cosine(&own, &small) < 0.999,
        "the copy changes the descriptor"
    );

    // Query features of the input's own size, against the 512-px map: a warning, not an error.
    let h5 = dir.path().join("features.h5");
    ok(&[
        os("extract"),
        images.as_os_str(),
        os("-o"),
        h5.as_os_str(),
        os("--global-max-side"),
        os("0"),
        os("--json"),
    ]);
    let file = sfpmap::io::features_h5::H5Features::open(&h5).unwrap();
    assert_eq!(
        file.root_string("sfp.global_max_side").unwrap().as_deref(),
        Some("0")
    );
    let from_file = file.features(&name).unwrap().unwrap().global.unwrap();
    assert!(cosine(&from_file, &own) > 0.9999);
    let localize = |map: &str| {
        sfpmap(&[
            os("localize"),
            os("--map"),
            dir.path().join(map).as_os_str(),
            os("--query-list"),
            scene().join("queries.txt").as_os_str(),
            os("--features"),
            h5.as_os_str(),
            os("-o"),
            dir.path().join("poses.txt").as_os_str(),
            os("--force"),
        ])
    };
    let warned = localize("default.sfpm");
    let stderr = String::from_utf8_lossy(&warned.stderr);
    assert!(warned.status.success(), "{stderr}");
    assert!(
        stderr.contains(&format!(
            "{}: global descriptors computed at max side \"0\"",
            h5.display()
        )) && stderr.contains("--global-max-side 512"),
        "{stderr}"
    );
    // A side that would leave the deepest level a cell or two is refused, by name.
    let tiny = sfpmap(&[
        os("extract"),
        images.as_os_str(),
        os("-o"),
        dir.path().join("tiny.h5").as_os_str(),
        os("--global-max-side"),
        os("8"),
    ]);
    let stderr = String::from_utf8_lossy(&tiny.stderr);
    assert!(
        !tiny.status.success() && stderr.contains("--global-max-side"),
        "{stderr}"
    );
    assert!(stderr.contains("at least 16"), "{stderr}");
    assert!(!dir.path().join("tiny.h5").exists());
    // `localize --images` computes the queries' global descriptors at the map's side: its
    // ranking is the one of features extracted at that side, not at the default 512.
    let ranking = |features: &[&std::ffi::OsStr]| -> Vec<Value> {
        let out = dir.path().join("ranked.json");
        let (map, queries) = (dir.path().join("input.sfpm"), scene().join("queries.txt"));
        let mut args = vec![
            os("localize"),
            os("--map"),
            map.as_os_str(),
            os("--query-list"),
            queries.as_os_str(),
        ];
        args.extend(features);
        args.extend(["--top-k", "10", "--format", "json", "--force", "-q", "-o"].map(os));
        args.push(out.as_os_str());
        ok(&args);
        let list: Value = serde_json::from_slice(&std::fs::read(&out).unwrap()).unwrap();
        list.as_array()
            .unwrap()
            .iter()
            .map(|q| q["retrieved"].clone())
            .collect()
    };
    let h5_default = dir.path().join("features-512.h5");
    ok(&[
        os("extract"),
        images.as_os_str(),
        os("-o"),
        h5_default.as_os_str(),
        os("-q"),
    ]);
    let by_images = ranking(&[os("--images"), images.as_os_str()]);
    assert!(!by_images.is_empty());
    assert!(by_images
        .iter()
        .all(|r| r.as_array().is_some_and(|r| r.len() == 8)));
    assert_eq!(by_images, ranking(&[os("--features"), h5.as_os_str()]));
    assert_ne!(
        by_images,
        ranking(&[os("--features"), h5_default.as_os_str()])
    );
    let matching = localize("input.sfpm");
    let stderr = String::from_utf8_lossy(&matching.stderr);
    assert!(matching.status.success(), "{stderr}");
    assert!(!stderr.contains("global descriptors computed"), "{stderr}");
}
