//! Matching and localizer benches (issue 6, "Benches"), on generated data of a stated size.
//!
//! - `match/*/{short_64,full_192}`: 2,000 query descriptors × 100,000 map descriptors.
//!   `decoded`: `match_descriptors` (blocked sgemm + mutual NN + ratio test) on the f32 rows the
//!   localizer keeps after `Localizer::new`; `from_f16`: the same, converting the f16 rows as
//!   stored in the map to f32 inside the timed loop; `gemm_only`: the sgemm calls alone, so
//!   `decoded − gemm_only` is the per-score bookkeeping; `adc_pqM`: the same rows
//!   product-quantised into M one-byte codes (256 centroids per subspace), matched by
//!   asymmetric distance as the localizer matches a PQ level (format 1.1). Throughput is in
//!   descriptor pairs.
//! - `localize/per_query/*`: one `Localizer::localize` call (coarse matching on the deepest
//!   level, LO-RANSAC, guided matching on every level, final estimate; query extraction is not
//!   part of it: the ≤ 20 ms target is "after extraction") on a generated 100,000-point map with
//!   4 levels of 25,000 points each (192-d, 64-d `short`, an identity projection). Points fill
//!   a 60 × 12 × 60 street-like volume (~12,000 per level in the query's view); each point's
//!   descriptor is a random unit vector. The query (PINHOLE 1024 × 768, f = 870) has, per
//!   level, 1,500 projections of visible points with 0.7 px noise and descriptor noise of norm
//!   ≈ 0.5, plus 500 random outliers (2,000 keypoints per level).
//!   - `full`: no images, so every point is a coarse candidate (retrieval's worst case);
//!   - `level2_short`: the `--level 2 --short` slice of that map;
//!   - `full_retrieval`: the same map with 100 database images (visibility of ≤ 4,000 points
//!     each, global descriptors that vary smoothly with the camera pose): top-10 retrieval.
//!
//! - `pq/train_and_encode_100k/*`: what `slice --pq M` does per level (codebooks from a
//!   16,384-row sample, then every one of 100,000 rows encoded), one core.
//!
//! Run: `cargo bench --bench localize` (about 4 minutes on 2 loaded cores).

#[cfg(feature = "localize")]
mod localize {
    use std::hint::black_box;
    use std::time::Duration;

    use criterion::{BenchmarkId, Criterion, Throughput};
    use half::f16;
    use nalgebra::{UnitQuaternion, Vector3};
    use sfpmap::build::pq::Quantiser;
    use sfpmap::format::Pq;
    use sfpmap::format::{slice, CameraInfo, Descriptors, LevelInfo, Map, MapWriter, SliceOptions};
    use sfpmap::fuzzing::{
        match_descriptors, match_pq_descriptors, normalise_rows, sgemm_abt, SplitMix64,
    };
    use sfpmap::geometry::{Camera, Pose};
    use sfpmap::localize::{FeatureSet, LocalizeOptions, Localizer, MatchOptions, QueryFeatures};
    use std::borrow::Cow;

    const DIM_FULL: usize = 192;
    const DIM_SHORT: usize = 64;
    const N_POINTS: usize = 100_000;
    const N_LEVELS: usize = 4;
    const N_QUERY: usize = 2_000;
    const INLIERS_PER_LEVEL: usize = 1_500;
    const OUTLIERS_PER_LEVEL: usize = 500;
    const CAMERA: &str = "PINHOLE 1024 768 870 870 512 384";

    fn gaussian(rng: &mut SplitMix64) -> f64 {
        let (u, v) = (1.0 - rng.next_f64(), rng.next_f64());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    fn random_unit_rows(rng: &mut SplitMix64, rows: usize, dim: usize) -> Vec<f32> {
        let mut v: Vec<f32> = (0..rows * dim).map(|_| gaussian(rng) as f32).collect();
        normalise_rows(&mut v, dim);
        v
    }

    /// The first `dim` columns of `[rows × DIM_FULL]`, renormalised (what `short` matching sees).
    fn prefix_rows(v: &[f32], dim: usize) -> Vec<f32> {
        let mut out: Vec<f32> = v
            .chunks_exact(DIM_FULL)
            .flat_map(|row| row[..dim].iter().copied())
            .collect();
        normalise_rows(&mut out, dim);
        out
    }

    fn bench_matching(c: &mut Criterion) {
        let mut rng = SplitMix64::new(11);
        let map = random_unit_rows(&mut rng, N_POINTS, DIM_FULL);
        // Queries: noisy copies of 1,500 map rows plus 500 unrelated ones.
        let mut query = Vec::with_capacity(N_QUERY * DIM_FULL);
        for i in 0..N_QUERY {
            if i < 1_500 {
                let row = (rng.next_f64() * N_POINTS as f64) as usize % N_POINTS;
                query.extend(
                    map[row * DIM_FULL..(row + 1) * DIM_FULL]
                        .iter()
                        .map(|&x| x + 0.036 * gaussian(&mut rng) as f32),
                );
            } else {
                query.extend((0..DIM_FULL).map(|_| gaussian(&mut rng) as f32));
            }
        }
        normalise_rows(&mut query, DIM_FULL);
        let options = MatchOptions::default();

        let mut group = c.benchmark_group("match");
        group.sample_size(10);
        group.warm_up_time(Duration::from_secs(1));
        group.measurement_time(Duration::from_secs(10));
        group.throughput(Throughput::Elements((N_QUERY * N_POINTS) as u64));
        for dim in [DIM_SHORT, DIM_FULL] {
            let label = if dim == DIM_FULL {
                "full_192"
            } else {
                "short_64"
            };
            let (q, m) = if dim == DIM_FULL {
                (query.clone(), map.clone())
            } else {
                (prefix_rows(&query, dim), prefix_rows(&map, dim))
            };
            let stored: Vec<f16> = m.iter().map(|&x| f16::from_f32(x)).collect();
            let found = match_descriptors(&q, &m, dim, &options).len();
            eprintln!("match {label}: {found} matches of {N_QUERY} queries");
            // The GEMM alone, in match_descriptors' blocks of 2,048 map rows: the rest of
            // `decoded` is the per-score best/second/mutual bookkeeping.
            group.bench_with_input(BenchmarkId::new("gemm_only", label), &dim, |b, &dim| {
                let mut scores = vec![0.0f32; N_QUERY * 2048];
                b.iter(|| {
                    for block in m.chunks(2048 * dim) {
                        let rows = block.len() / dim;
                        sgemm_abt(&q, block, &mut scores[..N_QUERY * rows], N_QUERY, rows, dim);
                    }
                    black_box(scores[0])
                })
            });
            group.bench_with_input(BenchmarkId::new("decoded", label), &dim, |b, &dim| {
                b.iter(|| black_box(match_descriptors(&q, &m, dim, &options)))
            });
            group.bench_with_input(BenchmarkId::new("from_f16", label), &dim, |b, &dim| {
                b.iter(|| {
                    let decoded: Vec<f32> = stored.iter().map(|x| x.to_f32()).collect();
                    black_box(match_descriptors(&q, &decoded, dim, &options))
                })
            });
            // The same rows product-quantised (`slice --pq M`: 256 centroids per subspace,
            // learned from 16,384 rows as `slice` samples), matched by asymmetric distance as
            // the localizer matches a PQ level.
            for subspaces in [dim / 8, dim / 4] {
                let sample = &m[..16_384 * dim];
                let quantiser = Quantiser::train(sample, dim, subspaces, 256).unwrap();
                let mut codes = vec![0u8; N_POINTS * subspaces];
                quantiser.encode_rows(&m, &mut codes);
                let pq = Pq {
                    subspaces,
                    centroids: 256,
                    sub_dims: dim / subspaces,
                    codebook: Cow::Borrowed(quantiser.codebook()),
                    codes: Cow::Owned(codes),
                    order: quantiser.order().map(Cow::Borrowed),
                };
                let found = match_pq_descriptors(&q, &pq, &options).len();
                eprintln!("match {label} pq{subspaces}: {found} matches of {N_QUERY} queries");
                let id = BenchmarkId::new(format!("adc_pq{subspaces}"), label);
                group.bench_with_input(id, &dim, |b, _| {
                    b.iter(|| black_box(match_pq_descriptors(&q, &pq, &options)))
                });
            }
        }
        group.finish();

        // What `slice --pq M` does per level: learn the codebooks from a 16,384-row sample,
        // then encode every row (100,000 here), on one core.
        let mut group = c.benchmark_group("pq");
        group.sample_size(10);
        group.warm_up_time(Duration::from_secs(1));
        group.measurement_time(Duration::from_secs(20));
        for (dim, subspaces) in [(DIM_SHORT, 8), (DIM_FULL, 24)] {
            let rows = if dim == DIM_FULL {
                map.clone()
            } else {
                prefix_rows(&map, dim)
            };
            let id = BenchmarkId::new("train_and_encode_100k", format!("{dim}d_pq{subspaces}"));
            group.bench_function(id, |b| {
                b.iter(|| {
                    let q = Quantiser::train(&rows[..16_384 * dim], dim, subspaces, 256).unwrap();
                    let mut codes = vec![0u8; N_POINTS * subspaces];
                    q.encode_rows(&rows, &mut codes);
                    black_box(codes)
                })
            });
        }
        group.finish();
    }

    struct Scene {
        /// World positions.
        points: Vec<[f64; 3]>,
        /// `[N_POINTS × DIM_FULL]`, unit rows.
        descriptors: Vec<f32>,
        camera: Camera,
        truth: Pose,
    }

    fn level_of(point: usize) -> u16 {
        (point % N_LEVELS) as u16
    }

    fn scene() -> Scene {
        let mut rng = SplitMix64::new(5);
        let points = (0..N_POINTS)
            .map(|_| {
                [
                    rng.next_f64() * 60.0 - 30.0,
                    rng.next_f64() * 12.0 - 6.0,
                    rng.next_f64() * 60.0 - 30.0,
                ]
            })
            .collect();
        let descriptors = random_unit_rows(&mut rng, N_POINTS, DIM_FULL);
        let camera = Camera::parse(CAMERA).unwrap();
        // Inside the volume near one end, looking along +z with a slight yaw and pitch.
        let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(0.05, 0.2, 0.02));
        let center = Vector3::new(2.0, 0.5, -27.0);
        let truth = Pose::new(rotation, -(rotation * center));
        Scene {
            points,
            descriptors,
            camera,
            truth,
        }
    }

    const N_IMAGES: usize = 100;
    const OBSERVATIONS_PER_IMAGE: usize = 4_000;
    const GLOBAL_DIM: usize = 128;

    /// A global descriptor that varies smoothly with the camera centre and viewing direction
    /// (random Fourier features), so that retrieval returns spatially close images.
    fn global_descriptor(pose: &Pose) -> Vec<f32> {
        let mut rng = SplitMix64::new(77);
        let c = pose.center();
        let d = pose.rotation.inverse() * Vector3::z();
        let x = [c.x, c.y, c.z, 8.0 * d.x, 8.0 * d.y, 8.0 * d.z];
        let mut g: Vec<f32> = (0..GLOBAL_DIM)
            .map(|_| {
                let w: Vec<f64> = (0..6).map(|_| gaussian(&mut rng) / 8.0).collect();
                let b = rng.next_f64() * std::f64::consts::TAU;
                (w.iter().zip(&x).map(|(w, x)| w * x).sum::<f64>() + b).cos() as f32
            })
            .collect();
        normalise_rows(&mut g, GLOBAL_DIM);
        g
    }

    /// Database images: cameras along the volume looking along ±z with some yaw, each observing
    /// up to `OBSERVATIONS_PER_IMAGE` of the points in its frustum (closer than 25 units).
    struct Images {
        poses: Vec<[f64; 7]>,
        offsets: Vec<u64>,
        points: Vec<u32>,
        global: Vec<f32>,
    }

    fn images(s: &Scene) -> Images {
        let mut rng = SplitMix64::new(21);
        let (w, h) = (f64::from(s.camera.width()), f64::from(s.camera.height()));
        let mut out = Images {
            poses: Vec::new(),
            offsets: vec![0],
            points: Vec::new(),
            global: Vec::new(),
        };
        for i in 0..N_IMAGES {
            let back = if i % 2 == 0 {
                0.0
            } else {
                std::f64::consts::PI
            };
            let yaw = back + (rng.next_f64() - 0.5) * 0.8;
            let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(0.0, yaw, 0.0));
            let center = Vector3::new(
                rng.next_f64() * 20.0 - 10.0,
                rng.next_f64() * 2.0 - 1.0,
                rng.next_f64() * 56.0 - 28.0,
            );
            let pose = Pose::new(rotation, -(rotation * center));
            let mut seen: Vec<u32> = (0..N_POINTS as u32)
                .filter(|&p| {
                    let pc = pose.transform(&Vector3::from(s.points[p as usize]));
                    pc.z > 0.5
                        && pc.z < 25.0
                        && s.camera
                            .project(&pc)
                            .is_some_and(|px| px.x > 0.0 && px.y > 0.0 && px.x < w && px.y < h)
                })
                .collect();
            let keep = OBSERVATIONS_PER_IMAGE as f64 / seen.len().max(1) as f64;
            seen.retain(|_| rng.next_f64() < keep);
            out.points.extend(&seen);
            out.offsets.push(out.points.len() as u64);
            out.poses.push(pose.to_colmap());
            out.global.extend(global_descriptor(&pose));
        }
        out
    }

    fn map_bytes(s: &Scene, images: Option<&Images>) -> Vec<u8> {
        let mut w = MapWriter::default();
        w.add_camera(CameraInfo {
            id: Some(1),
            model: "PINHOLE".into(),
            width: 1024,
            height: 768,
            params: vec![870.0, 870.0, 512.0, 384.0],
        });
        w.set_points_world(&s.points);
        let names: Vec<String> = (0..N_IMAGES).map(|i| format!("db{i:03}.jpg")).collect();
        let cameras = vec![0u32; N_IMAGES];
        if let Some(images) = images {
            w.set_images(&names, &cameras, &images.poses, None).unwrap();
            w.set_visibility(&images.offsets, &images.points, None)
                .unwrap();
            w.set_image_global(GLOBAL_DIM, &images.global).unwrap();
        }
        let levels: Vec<Vec<u32>> = (0..N_LEVELS as u16)
            .map(|l| {
                (0..N_POINTS as u32)
                    .filter(|&p| level_of(p as usize) == l)
                    .collect()
            })
            .collect();
        let identity: Vec<f32> = (0..DIM_FULL * DIM_FULL)
            .map(|i| if i % (DIM_FULL + 1) == 0 { 1.0 } else { 0.0 })
            .collect();
        for (l, points) in levels.iter().enumerate() {
            let desc: Vec<f32> = points
                .iter()
                .flat_map(|&p| {
                    s.descriptors[p as usize * DIM_FULL..(p as usize + 1) * DIM_FULL].to_vec()
                })
                .collect();
            let info = LevelInfo {
                level: l as u16,
                stride: 4.0 * (1 << l) as f64,
                descriptor: "bench".into(),
                dim_full: DIM_FULL as u32,
                dim_short: DIM_SHORT as u32,
                normalization: "l2".into(),
                extra: Default::default(),
            };
            w.add_level(info, points, Some(Descriptors::F32(&desc)), true)
                .unwrap();
            w.set_level_projection(l as u16, DIM_FULL, identity.clone())
                .unwrap();
        }
        w.to_bytes().unwrap()
    }

    /// Per level: projections of visible points of that level (0.7 px noise, descriptor
    /// noise of norm ≈ 0.5) and random outliers.
    fn query(s: &Scene) -> QueryFeatures {
        let mut rng = SplitMix64::new(9);
        let (w, h) = (f64::from(s.camera.width()), f64::from(s.camera.height()));
        let mut sets: Vec<FeatureSet> = (0..N_LEVELS as u16)
            .map(|l| FeatureSet {
                level: Some(l),
                keypoints: Vec::new(),
                descriptors: Vec::new(),
                dim: DIM_FULL,
            })
            .collect();
        let mut visible: Vec<usize> = (0..N_POINTS)
            .filter(|&p| {
                let pc = s.truth.transform(&Vector3::from(s.points[p]));
                pc.z > 0.5
                    && s.camera
                        .project(&pc)
                        .is_some_and(|px| px.x > 0.0 && px.y > 0.0 && px.x < w && px.y < h)
            })
            .collect();
        // A deterministic shuffle so the kept projections spread over the image.
        for i in (1..visible.len()).rev() {
            visible.swap(i, (rng.next_f64() * (i + 1) as f64) as usize % (i + 1));
        }
        for p in visible {
            let set = &mut sets[level_of(p) as usize];
            if set.keypoints.len() >= INLIERS_PER_LEVEL {
                continue;
            }
            let px = s
                .camera
                .project(&s.truth.transform(&Vector3::from(s.points[p])))
                .unwrap();
            set.keypoints.push([
                px.x + 0.7 * gaussian(&mut rng),
                px.y + 0.7 * gaussian(&mut rng),
            ]);
            set.descriptors.extend(
                s.descriptors[p * DIM_FULL..(p + 1) * DIM_FULL]
                    .iter()
                    .map(|&x| x + 0.036 * gaussian(&mut rng) as f32),
            );
        }
        for set in &mut sets {
            for _ in 0..OUTLIERS_PER_LEVEL {
                set.keypoints.push([rng.next_f64() * w, rng.next_f64() * h]);
                set.descriptors
                    .extend((0..DIM_FULL).map(|_| gaussian(&mut rng) as f32));
            }
            normalise_rows(&mut set.descriptors, DIM_FULL);
        }
        QueryFeatures {
            sets,
            global: Some(global_descriptor(&s.truth)),
            model: None,
        }
    }

    /// Points per level in front of the query camera and inside its image: what guided
    /// matching projects and gates.
    fn points_in_view(s: &Scene) -> Vec<usize> {
        let (w, h) = (f64::from(s.camera.width()), f64::from(s.camera.height()));
        let mut counts = vec![0; N_LEVELS];
        for (p, xyz) in s.points.iter().enumerate() {
            let pc = s.truth.transform(&Vector3::from(*xyz));
            if pc.z > 0.0
                && s.camera
                    .project(&pc)
                    .is_some_and(|px| px.x >= 0.0 && px.y >= 0.0 && px.x < w && px.y < h)
            {
                counts[level_of(p) as usize] += 1;
            }
        }
        counts
    }

    fn bench_localize(c: &mut Criterion) {
        let s = scene();
        let bytes = map_bytes(&s, None);
        let map = Map::from_bytes(&bytes).unwrap();
        let images = images(&s);
        let with_images = map_bytes(&s, Some(&images));
        let retrieval_map = Map::from_bytes(&with_images).unwrap();
        let q = query(&s);
        let keypoints: Vec<usize> = q.sets.iter().map(|s| s.keypoints.len()).collect();
        let in_view = points_in_view(&s);
        let sliced = slice(
            &map,
            &SliceOptions {
                levels: vec![2],
                short: true,
                codec: None,
                zstd_level: 3,
                minimal: false,
            },
        )
        .unwrap()
        .0
        .to_bytes()
        .unwrap();
        let small = Map::from_bytes(&sliced).unwrap();

        let mut group = c.benchmark_group("localize");
        group.sample_size(20);
        group.warm_up_time(Duration::from_secs(2));
        group.measurement_time(Duration::from_secs(15));
        for (label, map, short) in [
            ("full", &map, false),
            ("level2_short", &small, true),
            ("full_retrieval", &retrieval_map, false),
        ] {
            let localizer = Localizer::new(
                map,
                LocalizeOptions {
                    short,
                    ..LocalizeOptions::default()
                },
            )
            .unwrap();
            // Check once, outside the timing, that the bench measures successful queries.
            let r = localizer.localize(&q, &s.camera).unwrap();
            let pose = *r
                .pose()
                .unwrap_or_else(|| panic!("{label}: query failed: {:?}", r.failure()));
            eprintln!(
                "localize {label}: keypoints/level {keypoints:?}, points in the query's view/level \
                 {in_view:?}, {} retrieved images, {} matches, inliers/level {:?}, \
                 rotation error {:.4}°, center error {:.4}, stages {:?}",
                r.retrieved_images,
                r.matches,
                r.inliers_per_level,
                pose.rotation_error_deg(&s.truth),
                pose.center_distance(&s.truth),
                r.times,
            );
            group.bench_function(BenchmarkId::new("per_query", label), |b| {
                b.iter(|| black_box(localizer.localize(&q, &s.camera).unwrap()))
            });
        }
        group.finish();
    }

    pub fn benches(c: &mut Criterion) {
        bench_matching(c);
        bench_localize(c);
    }
}

#[cfg(feature = "localize")]
criterion::criterion_group!(benches, localize::benches);
#[cfg(feature = "localize")]
criterion::criterion_main!(benches);

/// Without the `localize` feature there is nothing to measure.
#[cfg(not(feature = "localize"))]
fn main() {}
