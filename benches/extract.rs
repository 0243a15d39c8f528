//! Extractor speed: one 640×480 image through the network and keypoint/descriptor stages,
//! 2 intra-op threads (the CLI default). The runtime is found or fetched as `sfpmap setup`
//! does. Quoted in README as the median ms per image.
//!
//! `cargo bench --bench extract`; `SFPMAP_BENCH_MODEL=path.onnx` times another model of the
//! same contract (issue 17's candidates), `SFPMAP_BENCH_THREADS=N` another thread count.

use criterion::{criterion_group, criterion_main, Criterion};
use sfpmap::extract::{image, DetectOptions, Extractor, ExtractorOptions};
use std::hint::black_box;
use std::path::PathBuf;

/// A real scene image resized to 640×480: the README quotes this figure, so without the
/// shared data the bench stops instead of timing something else.
fn input(weights: [f32; 3]) -> image::GrayInput {
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
        .resize_exact(640, 480, ::image::imageops::FilterType::Triangle);
    image::from_image(&decoded, weights, None)
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
    let input = input(extractor.contract().gray_weights);
    let options = DetectOptions::default();
    let name = model.as_deref().map_or("sfp-v1 (embedded)".into(), |m| {
        m.file_stem()
            .unwrap_or_default()
            .to_string_lossy()
            .into_owned()
    });
    let mut group = c.benchmark_group(format!("extract {name}, {threads} thread(s)"));
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
