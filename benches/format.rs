//! Format benches: open (flat in file size), slice throughput (raw copy vs zstd), and
//! descriptor access (zero-copy raw vs zstd decode). Maps of ~1 MB, ~100 MB and ~1 GB are
//! generated once into `target/bench-maps/` (set SFPMAP_BENCH_MAX_MB=100 to skip the 1 GB one).
//!
//! Run: `cargo bench --bench format --no-default-features`

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use sfpmap::format::{f16, slice, Codec, Descriptors, LevelInfo, Map, MapWriter, SliceOptions};
use sfpmap::progress::Silent;
use std::borrow::Cow;
use std::path::PathBuf;

const DIM: u32 = 128;
const SHORT: u32 = 32;

/// Bytes one point costs: position + index + f16 descriptor, on each of two levels.
const BYTES_PER_POINT: u64 = 12 + 2 * (4 + 2 * DIM as u64);

fn level(id: u16) -> LevelInfo {
    LevelInfo {
        level: id,
        stride: f64::from(4u32 << id),
        descriptor: "bench".into(),
        dim_full: DIM,
        dim_short: SHORT,
        normalization: "l2".into(),
        extra: Default::default(),
    }
}

/// A map of about `mb` megabytes: n points, two levels holding every point.
fn bench_map(mb: u64, codec: Codec) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/bench-maps");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(format!("{mb}mb-{}.sfpm", codec.name()));
    if Map::open(&path).is_ok() {
        return path;
    }
    let n = (mb << 20) / BYTES_PER_POINT;
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state
    };
    let positions: Vec<[f64; 3]> = (0..n)
        .map(|_| {
            [
                (next() % 10_000) as f64 * 0.01,
                (next() % 1000) as f64 * 0.01,
                (next() % 10_000) as f64 * 0.01,
            ]
        })
        .collect();
    let points: Vec<u32> = (0..n as u32).collect();
    // Descriptor-like values: small magnitudes, so zstd sees realistic (poor) redundancy.
    let descriptors: Vec<f16> = (0..n * u64::from(DIM))
        .map(|_| f16::from_f32(((next() % 2001) as f32 - 1000.0) / 11_314.0))
        .collect();
    let mut w = MapWriter::default();
    w.set_codec(codec, 1);
    w.set_points_world(&positions);
    for id in 0..2 {
        w.add_level(
            level(id),
            &points,
            Some(Descriptors::F16(Cow::Borrowed(&descriptors))),
            true,
        )
        .unwrap();
    }
    w.write(&path, &Silent).unwrap();
    path
}

fn sizes() -> Vec<u64> {
    let max: u64 = std::env::var("SFPMAP_BENCH_MAX_MB")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1024);
    [1, 100, 1024].into_iter().filter(|&s| s <= max).collect()
}

fn open(c: &mut Criterion) {
    let mut group = c.benchmark_group("open");
    for mb in sizes() {
        let path = bench_map(mb, Codec::Raw);
        group.bench_with_input(
            BenchmarkId::from_parameter(format!("{mb}MB")),
            &path,
            |b, path| b.iter(|| Map::open(path).unwrap()),
        );
    }
    group.finish();
}

fn slicing(c: &mut Criterion) {
    let path = bench_map(100, Codec::Raw);
    let mut group = c.benchmark_group("slice");
    group.sample_size(10);
    group.throughput(Throughput::Bytes(std::fs::metadata(&path).unwrap().len()));
    for (name, codec) in [("raw-copy", None), ("zstd-1", Some(Codec::Zstd))] {
        let options = SliceOptions {
            levels: vec![1],
            short: true,
            codec,
            zstd_level: 1,
            minimal: false,
        };
        group.bench_function(name, |b| {
            // A fresh open each time: slicing checks every section's checksum first.
            b.iter(|| {
                let map = Map::open(&path).unwrap();
                let (writer, _) = slice(&map, &options).unwrap();
                writer.to_bytes().unwrap().len()
            })
        });
    }
    group.finish();
}

fn descriptors(c: &mut Criterion) {
    let mut group = c.benchmark_group("desc_short");
    for codec in [Codec::Raw, Codec::Zstd] {
        let path = bench_map(100, codec);
        let len = Map::open(&path)
            .unwrap()
            .level(1)
            .unwrap()
            .desc_short()
            .unwrap()
            .len();
        group.throughput(Throughput::Bytes(len as u64 * 2));
        if codec == Codec::Zstd {
            group.sample_size(10);
        }
        // A fresh open each time, so first access (checksum, decode) is what is measured.
        group.bench_function(format!("first-access-{}", codec.name()), |b| {
            b.iter(|| {
                let map = Map::open(&path).unwrap();
                let level = map.level(1).unwrap();
                let d = level.desc_short().unwrap();
                d[d.len() / 2]
            })
        });
    }
    let path = bench_map(100, Codec::Raw);
    let map = Map::open(&path).unwrap();
    map.level(1).unwrap().desc_short().unwrap();
    group.bench_function("cached-raw", |b| {
        b.iter(|| {
            let level = map.level(1).unwrap();
            level.desc_short().unwrap().len()
        })
    });
    group.finish();
}

criterion_group!(benches, open, slicing, descriptors);
criterion_main!(benches);
