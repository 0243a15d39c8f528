//! Extractor speed: one 640×480 image (a JPEG in memory) through decoding, the network, the
//! keypoint/descriptor stage and the global descriptor's 512-px copy, 2 intra-op threads (the
//! CLI default); totals from the JPEG's bytes, for a tracked frame (no global descriptor, as
//! `localize --sequence` extracts one) and with the global descriptor. The runtime is found
//! or fetched as `sfpmap setup` does. Quoted in README as the median ms per image.
//!
//! The built-in `aliked-n16` runs on the same image beside it (its own group: the network,
//! DKD detection with the SDDH head's descriptors, the total; it has no global descriptor).
//!
//! `cargo bench --bench extract`; `SFPMAP_BENCH_MODEL=path.onnx` times another model of the
//! same contract (issue 17's candidates), `SFPMAP_BENCH_THREADS=N` another thread count.

use criterion::{criterion_group, criterion_main, Criterion};
use sfpmap::extract::{image, DetectOptions, Extractor, ExtractorOptions, GlobalSize};
use std::hint::black_box;
use std::path::PathBuf;

/// A real scene image resized to 640×480, as JPEG bytes (quality 90): the README quotes this
/// figure, so without the shared data the bench stops instead of timing something else.
fn jpeg() -> Vec<u8> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/scenes/south-building/images");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e} (the bench needs ../shared/data)", dir.display()))
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    paths.sort();
    let first = paths
        .into_iter()
        .next()
        .unwrap_or_else(|| panic!("{}: no images", dir.display()));
    let decoded = ::image::open(&first)
        .unwrap_or_else(|e| panic!("{}: {e}", first.display()))
        .resize_exact(640, 480, ::image::imageops::FilterType::Triangle)
        .to_rgb8();
    let mut bytes = Vec::new();
    ::image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 90)
        .encode_image(&decoded)
        .expect("JPEG encoding in memory");
    bytes
}

fn bench(c: &mut Criterion) {
    let model = std::env::var_os("SFPMAP_BENCH_MODEL")
        .filter(|m| !m.is_empty())
        .map(PathBuf::from);
    let threads = std::env::var("SFPMAP_BENCH_THREADS").map_or(2, |t| {
        t.parse()
            .unwrap_or_else(|_| panic!("SFPMAP_BENCH_THREADS={t}: not a number"))
    });
    let mut extractor = Extractor::new(
        &ExtractorOptions {
            model: model.clone(),
            threads,
        },
        &sfpmap::progress::Silent,
    )
    .expect("ONNX Runtime found or fetched");
    let weights = extractor.contract().gray_weights;
    let jpeg = jpeg();
    let path = std::path::Path::new("640x480.jpg");
    let decode = |bytes: &[u8]| image::decode(bytes, path, weights, None).unwrap();
    let input = decode(&jpeg);
    assert_eq!((input.width, input.height), (640, 480));
    let tracked = DetectOptions {
        global: GlobalSize::Skip,
        ..Default::default()
    };
    let with_global = DetectOptions::default();
    let name = model.as_deref().map_or("sfp-v3 (embedded)".into(), |m| {
        m.file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned()
    });
    let mut group = c.benchmark_group(format!("extract {name}, {threads} thread(s)"));
    group.sample_size(20);
    group.bench_function("640x480_decode", |b| {
        b.iter(|| black_box(decode(black_box(&jpeg))))
    });
    group.bench_function("640x480_network", |b| {
        b.iter(|| black_box(extractor.run(black_box(&input)).unwrap()))
    });
    let dense = extractor.run(&input).unwrap();
    group.bench_function("640x480_keypoints_descriptors", |b| {
        b.iter(|| {
            black_box(
                extractor
                    .features(black_box(&dense), [640, 480], &tracked)
                    .unwrap(),
            )
        })
    });
    group.bench_function("640x480_global_512", |b| {
        b.iter(|| {
            black_box(
                extractor
                    .global(black_box(&input), &dense, with_global.global)
                    .unwrap(),
            )
        })
    });
    // Decode + network + keypoints and descriptors: a tracked frame.
    group.bench_function("640x480_total", |b| {
        b.iter(|| {
            let input = decode(black_box(&jpeg));
            black_box(extractor.extract(&input, &tracked).unwrap())
        })
    });
    // ... + the global descriptor's 512-px copy: a frame that retrieves.
    group.bench_function("640x480_total_with_global", |b| {
        b.iter(|| {
            let input = decode(black_box(&jpeg));
            black_box(extractor.extract(&input, &with_global).unwrap())
        })
    });
    group.finish();
}

/// ALIKED-N16 (`models/aliked-n16.md`) on the same 640×480 JPEG, at hloc's defaults.
fn aliked(c: &mut Criterion) {
    let threads = std::env::var("SFPMAP_BENCH_THREADS").map_or(2, |t| t.parse().unwrap_or(2));
    let mut extractor = Extractor::builtin("aliked-n16", threads, &sfpmap::progress::Silent)
        .expect("aliked-n16 is built in")
        .expect("ONNX Runtime found or fetched");
    let weights = extractor.contract().gray_weights;
    let jpeg = jpeg();
    let path = std::path::Path::new("640x480.jpg");
    let decode = |bytes: &[u8]| image::decode(bytes, path, weights, None).unwrap();
    let input = decode(&jpeg);
    let options = DetectOptions::default();
    let mut group = c.benchmark_group(format!(
        "extract aliked-n16 (embedded), {threads} thread(s)"
    ));
    group.sample_size(10);
    group.bench_function("640x480_network", |b| {
        b.iter(|| black_box(extractor.run(black_box(&input)).unwrap()))
    });
    let dense = extractor.run(&input).unwrap();
    group.bench_function("640x480_keypoints_descriptors", |b| {
        b.iter(|| {
            black_box(
                extractor
                    .features(black_box(&dense), [640, 480], &options)
                    .unwrap(),
            )
        })
    });
    group.bench_function("640x480_total", |b| {
        b.iter(|| {
            let input = decode(black_box(&jpeg));
            black_box(extractor.extract(&input, &options).unwrap())
        })
    });
    group.finish();
}

criterion_group!(benches, bench, aliked);
criterion_main!(benches);
