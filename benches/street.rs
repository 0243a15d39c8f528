//! Localization on the generated street (`sfpmap::demo::street`, issue 11): one
//! `Localizer::localize` call per query (after extraction), on the SIFT map and on its
//! `--level 2 --short` slice, 1 thread. The scene is generated once into
//! `target/street-bench/<points>` and reused.
//!
//! - `street/100000/{sift,level2_short}`: always;
//! - `street/1000000/…`: only with `SFPMAP_BENCH_1M=1` (generating it takes ~5 minutes and
//!   ~8 GB; converting it ~15 s).
//!
//! Run: `cargo bench --bench street` (`SFPMAP_BENCH_1M=1 cargo bench --bench street` for both).

#[cfg(all(feature = "colmap", feature = "localize", feature = "onnx"))]
mod street {
    use std::path::{Path, PathBuf};
    use std::time::Duration;

    use criterion::{BenchmarkId, Criterion};
    use sfpmap::build::{convert, ConvertOptions};
    use sfpmap::demo::street::{write_street, StreetOptions};
    use sfpmap::format::{slice, Map, SliceOptions};
    use sfpmap::io::queries::{read_query_list, DatabaseFeatures};
    use sfpmap::localize::{LocalizeOptions, Localizer};

    /// The scene and its two maps, made once per size.
    fn prepared(points: usize) -> PathBuf {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("target/street-bench")
            .join(points.to_string());
        if !dir.join("l2.sfpm").exists() {
            let _ = std::fs::remove_dir_all(&dir);
            std::fs::create_dir_all(&dir).unwrap();
            let options = StreetOptions {
                points,
                queries: 10,
                ..StreetOptions::default()
            };
            write_street(&dir, &options).unwrap();
            let convert_options = ConvertOptions {
                database: Some(dir.join("database.db")),
                ..ConvertOptions::default()
            };
            let progress = &sfpmap::progress::Silent;
            convert(
                &dir.join("sparse"),
                &convert_options,
                &dir.join("sift.sfpm"),
                progress,
            )
            .unwrap();
            let map = Map::open(dir.join("sift.sfpm")).unwrap();
            let options = SliceOptions {
                levels: vec![2],
                short: true,
                ..SliceOptions::default()
            };
            let (writer, _) = slice(&map, &options).unwrap();
            writer.write(&dir.join("l2.sfpm"), progress).unwrap();
        }
        dir
    }

    fn bench_size(c: &mut Criterion, points: usize) {
        let dir = prepared(points);
        let queries = read_query_list(&dir.join("queries.txt"), None).unwrap();
        let db = DatabaseFeatures::open(&dir.join("queries.db")).unwrap();
        let query = &queries[0];
        let features = db.features(&query.name).unwrap().unwrap();
        let mut group = c.benchmark_group(format!("street/{points}"));
        group.sample_size(10).warm_up_time(Duration::from_secs(1));
        for (label, file, short) in [
            ("sift", "sift.sfpm", false),
            ("level2_short", "l2.sfpm", true),
        ] {
            let map = Map::open(dir.join(file)).unwrap();
            let options = LocalizeOptions {
                short,
                ..LocalizeOptions::default()
            };
            let localizer = Localizer::new(&map, options).unwrap();
            // Once outside the timing: the bench measures a query that localizes.
            let r = localizer.localize(&features, &query.camera).unwrap();
            assert!(r.pose().is_some(), "{label}: {:?}", r.failure());
            group.bench_function(BenchmarkId::new(label, &query.name), |b| {
                b.iter(|| localizer.localize(&features, &query.camera).unwrap())
            });
        }
        group.finish();
    }

    pub fn benches(c: &mut Criterion) {
        bench_size(c, 100_000);
        if std::env::var_os("SFPMAP_BENCH_1M").is_some() {
            bench_size(c, 1_000_000);
        }
    }
}

#[cfg(all(feature = "colmap", feature = "localize", feature = "onnx"))]
criterion::criterion_group!(benches, street::benches);
#[cfg(all(feature = "colmap", feature = "localize", feature = "onnx"))]
criterion::criterion_main!(benches);

/// Without the features there is nothing to measure.
#[cfg(not(all(feature = "colmap", feature = "localize", feature = "onnx")))]
fn main() {}
