//! The Rust extractor against the Python ONNX Runtime reference (`tests/extract_reference.py`)
//! on a real image: same keypoints, scores, short/full descriptors and global descriptor.
//!
//! Runs the real runtime: `Extractor::new` finds `libonnxruntime.so.1.31.1` or fetches it
//! itself (what `sfpmap setup` does). The reference needs Python with numpy, pillow and
//! onnxruntime==1.31.1: the interpreter `SFPMAP_PYTHON` names (`bash .ci/test` makes that
//! venv), else `python3`. It fails, never skips.
#![cfg(feature = "onnx")]

use serde_json::Value;
use sfpmap::extract::{
    image, DetectOptions, Extractor, ExtractorOptions, Features, GlobalSize, BUILTIN_MODELS,
    GLOBAL_MAX_SIDE,
};
use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn scene_image() -> PathBuf {
    let dir = root().join("../shared/data/scenes/south-building/images");
    let mut images: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .collect();
    images.sort();
    images.pop().expect("south-building has images")
}

/// A Python that can run the reference (see the module docs).
fn python() -> PathBuf {
    static PYTHON: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    PYTHON
        .get_or_init(|| crate::python::python_with("numpy, PIL, onnxruntime"))
        .clone()
}

fn reference(model: &Path, image: &Path, dir: &Path) -> (PathBuf, Value) {
    let png = dir.join("image.png");
    let json = dir.join("reference.json");
    let out = Command::new(python())
        .arg(root().join("tests/extract_reference.py"))
        .arg("--model")
        .arg(model)
        .arg("--image")
        .arg(image)
        .arg("--png")
        .arg(&png)
        .arg("--json")
        .arg(&json)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "the Python reference failed (pip install numpy pillow onnxruntime==1.31.1): {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let value = serde_json::from_slice(&std::fs::read(&json).unwrap()).unwrap();
    (png, value)
}

/// The built-in sfp-v2 (the default before sfp-v3): a model of `sfp-extractor/1`.
fn sfp_v2_bytes() -> &'static [u8] {
    let (_, bytes) = BUILTIN_MODELS
        .iter()
        .find(|(name, _)| *name == "sfp-v2")
        .expect("sfp-v2 is built in");
    bytes
}

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

fn dot(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[test]
fn matches_the_python_onnxruntime_reference_on_a_real_image() {
    let dir = tempfile::tempdir().unwrap();
    // The Python side reads the file the embedded DEFAULT_MODEL is include_bytes! of.
    let model = root().join("models/sfp-v3.onnx");
    let (png, reference) = reference(&model, &scene_image(), dir.path());

    let mut extractor = Extractor::new(
        &ExtractorOptions {
            model: None,
            threads: 2,
        },
        &sfpmap::progress::Silent,
    )
    .expect("runtime found or fetched, model loaded");
    let contract = extractor.contract().clone();
    let input = image::load(&png, contract.gray_weights, None).unwrap();
    let own_size = own_size();
    let features = extractor.extract(&input, &own_size).unwrap();
    // Deterministic: a second run gives the same bytes.
    assert_eq!(features, extractor.extract(&input, &own_size).unwrap());
    // The same bytes whatever the thread count: levels are shared out over the threads
    // (2 here; 1 and 3 share them differently), keypoints stay in score order.
    let dense = extractor.run(&input).unwrap();
    for threads in [1, 3] {
        let other = Extractor::new(
            &ExtractorOptions {
                model: None,
                threads,
            },
            &sfpmap::progress::Silent,
        )
        .unwrap();
        assert_eq!(
            features,
            other
                .features(&dense, input.original_size, &DetectOptions::default())
                .unwrap(),
            "{threads} thread(s)"
        );
    }

    let size: Vec<u32> = reference["image_size"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as u32)
        .collect();
    assert_eq!(features.image_size.to_vec(), size);
    let global = floats(&reference["global"]);
    let worst = global
        .iter()
        .zip(&features.global)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst < 1e-4, "global descriptor differs by {worst}");

    // By default the global descriptor is the `global` of a 512-px copy (the image is larger),
    // the same keypoints and descriptors otherwise: it is not the input's own.
    assert!(input.width.max(input.height) > GLOBAL_MAX_SIDE as usize);
    let by_default = extractor
        .extract(&input, &DetectOptions::default())
        .unwrap();
    assert_eq!(by_default.levels, features.levels);
    let small = input.downscaled(GLOBAL_MAX_SIDE).unwrap();
    assert_eq!(small.width.max(small.height), GLOBAL_MAX_SIDE as usize);
    assert_eq!(by_default.global, extractor.run(&small).unwrap().global);
    let cosine = dot(&by_default.global, &features.global);
    assert!(
        cosine < 0.999,
        "the copy's global is the input's: cosine {cosine}"
    );
    assert!((dot(&by_default.global, &by_default.global) - 1.0).abs() < 1e-4);
    // Skipped: empty, and nothing else changes.
    let skipped = DetectOptions {
        global: GlobalSize::Skip,
        ..Default::default()
    };
    let without = extractor.extract(&input, &skipped).unwrap();
    assert!(without.global.is_empty());
    assert_eq!(without.levels, features.levels);

    assert_levels_match(&reference, &features);
}

/// Every level's keypoints, scores and short/full descriptors against the reference's.
fn assert_levels_match(reference: &Value, features: &Features) {
    let levels = reference["levels"].as_array().unwrap();
    assert_eq!(levels.len(), features.levels.len());
    let mut total = 0;
    for (r, ours) in levels.iter().zip(&features.levels) {
        assert_eq!(r["level"].as_u64().unwrap() as u16, ours.level);
        let kps: Vec<[f32; 2]> = r["keypoints"]
            .as_array()
            .unwrap()
            .iter()
            .map(|k| {
                let k = floats(k);
                [k[0], k[1]]
            })
            .collect();
        let scores = floats(&r["scores"]);
        let shorts: Vec<Vec<f32>> = r["short"].as_array().unwrap().iter().map(floats).collect();
        let fulls: Vec<Vec<f32>> = r["full"].as_array().unwrap().iter().map(floats).collect();
        let n = kps.len();
        // Scores within float noise of the threshold or the cap may flip one keypoint in or out.
        assert!(
            ours.len().abs_diff(n) <= 1 + n / 200,
            "level {}: {} keypoints, reference {n}",
            ours.level,
            ours.len()
        );
        let mut matched = 0;
        for (i, k) in ours.keypoints.iter().enumerate() {
            // Refinement may put two keypoints on one pixel: of the reference keypoints there,
            // the one with the closest score.
            let Some(j) = (0..n)
                .filter(|&j| {
                    (kps[j][0] - k[0]).abs() < 1e-3 * ours.stride as f32
                        && (kps[j][1] - k[1]).abs() < 1e-3 * ours.stride as f32
                })
                .min_by(|&a, &b| {
                    (scores[a] - ours.scores[i])
                        .abs()
                        .total_cmp(&(scores[b] - ours.scores[i]).abs())
                })
            else {
                continue;
            };
            matched += 1;
            assert!(
                (scores[j] - ours.scores[i]).abs() < 1e-4,
                "level {} keypoint {i}: score {} vs {}",
                ours.level,
                ours.scores[i],
                scores[j]
            );
            let short: Vec<f32> = ours.short[i * ours.dim_short..(i + 1) * ours.dim_short]
                .iter()
                .map(|v| v.to_f32())
                .collect();
            let full: Vec<f32> = ours.full[i * ours.dim_full..(i + 1) * ours.dim_full]
                .iter()
                .map(|v| v.to_f32())
                .collect();
            assert!(
                dot(&short, &shorts[j]) > 0.999,
                "level {} short {i}",
                ours.level
            );
            assert!(
                dot(&full, &fulls[j]) > 0.999,
                "level {} full {i}",
                ours.level
            );
            // short is a scaled prefix of full.
            let prefix = &full[..ours.dim_short];
            let norm = dot(prefix, prefix).sqrt();
            assert!(dot(prefix, &short) / norm > 0.999);
        }
        assert!(
            matched * 100 >= ours.len() * 99,
            "level {}: only {matched} of {} keypoints match the reference",
            ours.level,
            ours.len()
        );
        total += matched;
    }
    assert!(total > 100, "too few keypoints to compare: {total}");
}

/// One more `metadata_props` entry (ModelProto field 14: a StringStringEntryProto of key 1 and
/// value 2) to append to a model file: a repeated field takes entries wherever they come in
/// the message, so the file then holds one more key. Lengths are one-byte varints: the entry
/// stays under 128 bytes.
fn metadata_entry(key: &str, value: &str) -> Vec<u8> {
    let mut entry = vec![0x0a, key.len() as u8];
    entry.extend(key.as_bytes());
    entry.extend([0x12, value.len() as u8]);
    entry.extend(value.as_bytes());
    assert!(entry.len() < 128, "{key}: too long for one-byte lengths");
    let mut field = vec![(14 << 3) | 2, entry.len() as u8];
    field.extend(entry);
    field
}

/// A refining model's features of the scene image, checked against the Python reference, the
/// default model's features of the same pixels, and, for each level, how many keypoints the
/// refinement moved (the scores and their order are the default model's). Returns the
/// refining extractor and its input too, for more extractions.
fn refined_against_the_default(
    model: &Path,
    dir: &Path,
) -> (Extractor, image::GrayInput, Vec<(u16, usize, usize)>) {
    let (png, reference) = reference(model, &scene_image(), dir);
    let mut refined = Extractor::new(
        &ExtractorOptions {
            model: Some(model.to_path_buf()),
            threads: 2,
        },
        &sfpmap::progress::Silent,
    )
    .unwrap();
    let input = image::load(&png, refined.contract().gray_weights, None).unwrap();
    let features = refined.extract(&input, &own_size()).unwrap();
    assert_levels_match(&reference, &features);
    let default = sfp_v2_levels_detected_as(refined.contract(), &input, true);
    let moved = (features.levels.iter().zip(&default))
        .map(|(ours, theirs)| {
            assert_eq!(ours.scores, theirs.scores, "level {}", ours.level);
            let moved = (ours.keypoints.iter().zip(&theirs.keypoints))
                .filter(|(a, b)| a != b)
                .count();
            (ours.level, moved, ours.len())
        })
        .collect();
    (refined, input, moved)
}

/// sfp-v2's levels of `input` as `contract` detects them: level i's keypoints found on the
/// score map of level `detect_levels[i]` with level i's threshold and cap, and refined (step 4)
/// or not. What a model of sfp-v2's network with detection rules of its own gives before any
/// refinement on the image; the descriptors are the detecting level's (compare positions and
/// scores only where a level is detected on another).
fn sfp_v2_levels_detected_as(
    contract: &sfpmap::extract::contract::Contract,
    input: &image::GrayInput,
    refine: bool,
) -> Vec<sfpmap::extract::LevelFeatures> {
    let mut sfp_v2 = Extractor::builtin("sfp-v2", 2, &sfpmap::progress::Silent)
        .expect("sfp-v2 is built in")
        .unwrap();
    let dense = sfp_v2.run(input).unwrap();
    (contract.default_thresholds.iter().enumerate())
        .map(|(i, &threshold)| {
            let d = contract.detect_levels[i];
            let mut max_keypoints = contract.default_max_keypoints.clone();
            max_keypoints[d] = contract.default_max_keypoints[i];
            let options = DetectOptions {
                threshold: Some(threshold),
                max_keypoints: Some(max_keypoints),
                refine: Some(refine),
                ..own_size()
            };
            let features = sfp_v2.features(&dense, input.original_size, &options);
            features.unwrap().levels.swap_remove(d)
        })
        .collect()
}

/// How the levels are shared out among threads changes nothing: sfp-v3 (refined on the image,
/// level 2 at a threshold of its own) gives the same features on 1 thread and on 3.
#[test]
fn features_do_not_depend_on_the_threads() {
    let features = |threads| {
        let mut extractor = Extractor::builtin("sfp-v3", threads, &sfpmap::progress::Silent)
            .expect("sfp-v3 is built in")
            .unwrap();
        let weights = extractor.contract().gray_weights;
        let input = image::load(&scene_image(), weights, None).unwrap();
        extractor
            .extract(&input, &DetectOptions::default())
            .unwrap()
    };
    let (one, three) = (features(1), features(3));
    assert!(one.levels.iter().all(|l| l.len() > 10));
    assert_eq!(one.levels, three.levels);
    assert_eq!(one.global, three.global);
}

/// The global descriptor at the input's own size: the reference computes it there.
fn own_size() -> DetectOptions {
    DetectOptions {
        global: GlobalSize::Input,
        ..Default::default()
    }
}

/// A model declaring `sfp.refine_to_level = 0` (sfp-v2 with the key appended) refines levels
/// 2 and 3 on down to level 0's score map, as the Python reference does; levels 0 and 1, and
/// the keypoints' scores and order, are the default model's.
#[test]
fn a_model_refined_down_to_level_0_matches_the_python_reference() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("sfp-v2-refined-to-0.onnx");
    let mut bytes = sfp_v2_bytes().to_vec();
    bytes.extend(metadata_entry("sfp.refine_to_level", "0"));
    std::fs::write(&model, &bytes).unwrap();
    let (refined, _, moved) = refined_against_the_default(&model, dir.path());
    assert_eq!(refined.contract().refine_to_level, Some(0));
    for (level, moved, n) in moved {
        if level < 2 {
            assert_eq!(moved, 0, "level {level} is not refined");
        } else {
            assert!(moved * 4 > n, "level {level}: {moved} of {n} moved");
        }
    }
}

/// The built-in sfp-v3 (`sfp-extractor/3`: sfp-v2's network, level 2 detected on level 0's
/// score map, keypoints refined on the image) gives what the Python reference does
/// (`python/sfp/reference.py`) and moves every level's keypoints onto the image's blobs; every
/// keypoint's score and order stay sfp-v2's detected on the detecting level's map with sfp-v3's
/// per-level thresholds and caps, and `refine: false` gives those keypoints exactly.
#[test]
fn sfp_v3_refined_on_the_image_matches_the_python_reference() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("sfp-v3.onnx");
    let (_, bytes) = BUILTIN_MODELS
        .iter()
        .find(|(name, _)| *name == "sfp-v3")
        .expect("sfp-v3 is built in");
    std::fs::write(&model, bytes).unwrap();
    let (mut refined, input, moved) = refined_against_the_default(&model, dir.path());
    assert_eq!(refined.contract().version, "sfp-extractor/3");
    for (level, moved, n) in moved {
        // Most keypoints have a blob within their radius; an edge or a flat patch has none.
        assert!(moved * 2 > n, "level {level}: {moved} of {n} moved");
    }
    // Its level 2 is found on level 0's score map, at most 4000 keypoints, refined as level
    // 0's: the level-2 maps' points and the queries' matches (models/sfp-v3.md).
    let c = refined.contract().clone();
    assert_eq!(c.detect_levels, [0, 1, 0, 3]);
    assert_eq!(c.default_max_keypoints, [4000, 1000, 4000, 250]);
    assert_eq!(c.image_refine[2], c.image_refine[0]);
    let unrefined = DetectOptions {
        refine: Some(false),
        ..own_size()
    };
    let ours = refined.extract(&input, &unrefined).unwrap().levels;
    let theirs = sfp_v2_levels_detected_as(&c, &input, false);
    for (i, (ours, theirs)) in ours.iter().zip(&theirs).enumerate() {
        if c.detect_levels[i] == i {
            assert_eq!(ours, theirs);
        } else {
            assert_eq!(
                (&ours.keypoints, &ours.scores),
                (&theirs.keypoints, &theirs.scores)
            );
            assert_eq!(
                (usize::from(ours.level), ours.dim_short),
                (i, c.dims[i]),
                "level {i}'s own descriptors"
            );
        }
    }
    // Level 2 and level 0 share the map, the threshold, the cap and the refinement: the same
    // keypoints, described by each level's own features.
    assert_eq!(ours[2].keypoints, ours[0].keypoints);
}

/// sfp-v3's level 2 shares level 0's detection and placement; capped otherwise it is detected
/// and placed on its own (not grouped) and gives the same keypoints, scores and descriptors,
/// up to its cap, and the other levels do not change.
#[test]
fn a_level_placed_alone_matches_the_level_it_shares_a_placement_with() {
    let mut extractor = Extractor::builtin("sfp-v3", 2, &sfpmap::progress::Silent)
        .expect("sfp-v3 is built in")
        .unwrap();
    let input = image::load(&scene_image(), extractor.contract().gray_weights, None).unwrap();
    let grouped = extractor.extract(&input, &own_size()).unwrap();
    let capped = DetectOptions {
        max_keypoints: Some(vec![4000, 1000, 3999, 250]),
        ..own_size()
    };
    let alone = extractor.extract(&input, &capped).unwrap();
    let (g, a) = (&grouped.levels[2], &alone.levels[2]);
    let n = a.len();
    assert!(n > 100 && n == g.len().min(3999), "{n} of {}", g.len());
    assert_eq!(a.keypoints[..], g.keypoints[..n]);
    assert_eq!(a.scores[..], g.scores[..n]);
    assert_eq!(a.short[..], g.short[..n * g.dim_short]);
    assert_eq!(a.full[..], g.full[..n * g.dim_full]);
    for i in [0, 1, 3] {
        assert_eq!(alone.levels[i], grouped.levels[i], "level {i}");
    }
}

/// Every built-in model opens under its own name, with a contract this extractor runs.
#[test]
fn every_built_in_model_opens_under_its_name() {
    for (name, _) in BUILTIN_MODELS {
        let extractor = Extractor::builtin(name, 1, &sfpmap::progress::Silent)
            .expect("a built-in name")
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        let c = extractor.contract();
        assert_eq!(c.model_name, *name);
        assert!(
            sfpmap::extract::contract::CONTRACTS.contains(&c.version),
            "{name}: {}",
            c.version
        );
    }
}

#[test]
fn bad_models_are_refused_with_the_file_named() {
    let dir = tempfile::tempdir().unwrap();
    let corrupt = dir.path().join("corrupt.onnx");
    let mut bytes = sfp_v2_bytes().to_vec();
    bytes.truncate(bytes.len() / 3);
    std::fs::write(&corrupt, &bytes).unwrap();
    let garbage = dir.path().join("garbage.onnx");
    std::fs::write(&garbage, b"not a model at all").unwrap();
    let missing = dir.path().join("missing.onnx");
    // Same length, so the protobuf stays valid: only the contract's value changes.
    let other = dir.path().join("other-contract.onnx");
    let at = sfp_v2_bytes()
        .windows(15)
        .position(|w| w == b"sfp-extractor/1")
        .expect("the model states its contract");
    let mut bytes = sfp_v2_bytes().to_vec();
    bytes[at + 14] = b'9';
    std::fs::write(&other, &bytes).unwrap();
    let err = Extractor::new(
        &ExtractorOptions {
            model: Some(other.clone()),
            threads: 1,
        },
        &sfpmap::progress::Silent,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("other-contract.onnx") && err.contains("sfp-extractor/9"),
        "{err}"
    );
    for path in [&corrupt, &garbage, &missing] {
        let err = Extractor::new(
            &ExtractorOptions {
                model: Some(path.clone()),
                threads: 1,
            },
            &sfpmap::progress::Silent,
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains(&path.display().to_string()),
            "{}: {err}",
            path.display()
        );
    }
}
