//! Extractor speed: one 640×480 image through the network and keypoint/descriptor stages,
//! 2 intra-op threads (the CLI default). The runtime is found or fetched as `sfpmap setup`
//! does. Quoted in README as the median ms per image.
//!
//! `cargo bench --bench extract`

use criterion::{criterion_group, criterion_main, Criterion};
use sfpmap::extract::{image, DetectOptions, Extractor, ExtractorOptions};
use std::hint::black_box;
use std::path::PathBuf;

/// A real scene image resized to 640×480 (falls back to a synthetic texture without the data).
fn input(weights: [f32; 3]) -> image::GrayInput {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/scenes/south-building/images");
    let first = std::fs::read_dir(&dir).ok().and_then(|entries| {
        let mut v: Vec<PathBuf> = entries.flatten().map(|e| e.path()).collect();
        v.sort();
        v.into_iter().next()
    });
    let decoded = match first.and_then(|p| ::image::open(p).ok()) {
        Some(img) => img.resize_exact(640, 480, ::image::imageops::FilterType::Triangle),
        None => ::image::DynamicImage::ImageLuma8(::image::GrayImage::from_fn(640, 480, |x, y| {
            ::image::Luma([((x * 7 + y * 13) % 251) as u8 ^ ((x / 16 + y / 16) % 2 * 255) as u8])
        })),
    };
    image::from_image(&decoded, weights, None)
}

fn bench(c: &mut Criterion) {
    let mut extractor = Extractor::new(
        &ExtractorOptions {
            model: None,
            threads: 2,
        },
        &sfpmap::progress::Silent,
    )
    .expect("ONNX Runtime found or fetched");
    let input = input(extractor.contract().gray_weights);
    let options = DetectOptions::default();
    let mut group = c.benchmark_group("extract");
    group.sample_size(20);
    group.bench_function("640x480_network", |b| {
        b.iter(|| black_box(extractor.run(black_box(&input)).unwrap()))
    });
    let dense = extractor.run(&input).unwrap();
    group.bench_function("640x480_keypoints_descriptors", |b| {
        b.iter(|| black_box(extractor.features(black_box(&dense), [640, 480], &options)))
    });
    group.bench_function("640x480_total", |b| {
        b.iter(|| black_box(extractor.extract(black_box(&input), &options).unwrap()))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
