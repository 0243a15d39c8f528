//! Localization on the generated street (`sfpmap::demo::street`, issue 11): one
//! `Localizer::localize` call per query (after extraction), on the SIFT map and on its
//! `--level 2 --short` slice, 1 thread: the brute-force path, retrieval, and a tracked frame
//! of the walk. The scene is generated once into `target/street-bench/v2/<points>` and reused.
//!
//! - `street/100000/{sift,level2_short}/…`: always;
//! - `street/1000000/…`: only with `SFPMAP_BENCH_1M=1` (generating it takes ~10 minutes;
//!   converting it ~30 s).
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
    use sfpmap::localize::{LocalizationPath, LocalizeOptions, Localizer, RetrievalMethod};

    /// The scene and its two maps, made once per size.
    fn prepared(points: usize) -> PathBuf {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("target/street-bench/v2")
            .join(points.to_string());
        // v2: maps with VLAD, and the walk (`sequence.*`).
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

    /// Per map: the brute-force path (`RetrievalMethod::Off`, every point a candidate),
    /// retrieval (the map's VLAD), and a tracked frame of the walk (its prior predicted by
    /// the constant-velocity model from the two frames before it, localized first).
    fn bench_size(c: &mut Criterion, points: usize) {
        let dir = prepared(points);
        let queries = read_query_list(&dir.join("queries.txt"), None).unwrap();
        let db = DatabaseFeatures::open(&dir.join("queries.db")).unwrap();
        let query = &queries[0];
        let features = db.features(&query.name).unwrap().unwrap();
        let walk = read_query_list(&dir.join("sequence.txt"), None).unwrap();
        let walk_db = DatabaseFeatures::open(&dir.join("sequence.db")).unwrap();
        let frames: Vec<_> = walk[..3]
            .iter()
            .map(|f| walk_db.features(&f.name).unwrap().unwrap())
            .collect();
        let mut group = c.benchmark_group(format!("street/{points}"));
        group.sample_size(10).warm_up_time(Duration::from_secs(1));
        for (label, file, short) in [
            ("sift", "sift.sfpm", false),
            ("level2_short", "l2.sfpm", true),
        ] {
            let map = Map::open(dir.join(file)).unwrap();
            for (path, retrieval) in [
                ("brute_force", RetrievalMethod::Off),
                ("retrieval", RetrievalMethod::Auto),
            ] {
                let options = LocalizeOptions {
                    short,
                    retrieval,
                    ..LocalizeOptions::default()
                };
                let localizer = Localizer::new(&map, options).unwrap();
                // Once outside the timing: the bench measures a query that localizes.
                let r = localizer.localize(&features, &query.camera).unwrap();
                assert!(r.pose().is_some(), "{label}: {:?}", r.failure());
                group.bench_function(
                    BenchmarkId::new(format!("{label}/{path}"), &query.name),
                    |b| b.iter(|| localizer.localize(&features, &query.camera).unwrap()),
                );
            }
            let options = LocalizeOptions {
                short,
                ..LocalizeOptions::default()
            };
            let localizer = Localizer::new(&map, options).unwrap();
            // The constant-velocity prior of the third frame, as a sequence session makes it:
            // the second pose moved by the step from the first to the second.
            let pose = |i: usize| {
                let r = localizer.localize(&frames[i], &walk[i].camera).unwrap();
                *r.pose().expect("the first two frames localize")
            };
            let (first, second) = (pose(0), pose(1));
            let prior = second.compose(&first.inverse()).compose(&second);
            let (frame, f) = (&walk[2], &frames[2]);
            let r = localizer
                .localize_with_prior(f, &frame.camera, Some(&prior))
                .unwrap();
            assert_eq!(
                r.path,
                LocalizationPath::Tracking,
                "{label}: {:?}",
                r.tracking_lost
            );
            group.bench_function(
                BenchmarkId::new(format!("{label}/tracked"), &frame.name),
                |b| {
                    b.iter(|| {
                        localizer
                            .localize_with_prior(f, &frame.camera, Some(&prior))
                            .unwrap()
                    })
                },
            );
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
