//! Convert benches (issue 3, "Speed and size"): `convert` of a synthetic COLMAP binary model,
//! geometry only, at 100k and 1M points × track length 5; the model read alone by the general
//! reader (`read_model_bin`, which convert's fast path for binary models skips); and convert
//! with a synthetic `database.db` (SIFT-like descriptors, affine keypoints) at 100k points.
//! Throughput in points/s.
//!
//! The model (400 images, 4 SIMPLE_RADIAL cameras, random valid poses, each image's points2D
//! holding its observations plus ~25 % untriangulated ones) is built with
//! `ReconstructionBuilder` (so it passes the reader's own checks), written with the crate's
//! `.bin` writers once into `target/bench-colmap/rust-*`, and reused. The database holds every
//! points2D row of every image (COLMAP's keypoint rows): an observation's descriptor is its
//! point's base descriptor plus noise, an untriangulated one is random.
//! `benches/compare_pycolmap.py` generates the same shape of model with numpy and compares
//! the CLI against pycolmap.
//!
//! Run: `cargo bench --bench convert` (SFPMAP_BENCH_MAX_POINTS=100000 skips the 1M model).

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use sfpmap::build::{convert, ConvertOptions};
use sfpmap::colmap::bin::{write_cameras, write_images, write_points3d};
use sfpmap::colmap::{read_model_bin, Camera, Image, Point2D, Reconstruction, TrackElement};
use sfpmap::geometry::{CameraModel, Pose};
use sfpmap::progress::Silent;
use std::path::{Path, PathBuf};

const IMAGES: u32 = 400;
const CAMERAS: u32 = 4;
const TRACK_LENGTH: usize = 5;
/// Untriangulated points2D per image, as a fraction of its observations.
const UNTRIANGULATED: f64 = 0.25;
const RESOLUTIONS: [(u64, u64); 4] = [(4032, 3024), (1920, 1080), (1600, 1200), (2704, 1520)];
/// Bump when the generated content changes, so cached models are rebuilt.
const GENERATOR_VERSION: u32 = 2;

/// xorshift64*: deterministic, dependency-free, plenty for synthetic data.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// Uniform in `[0, 1)`.
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    /// Uniform in `0..n` (n small, the modulo bias is irrelevant here).
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    /// Roughly standard normal (Irwin–Hall of 4), enough for orientations.
    fn normal(&mut self) -> f64 {
        ((0..4).map(|_| self.unit()).sum::<f64>() - 2.0) * 3f64.sqrt()
    }
}

/// `cam_from_world` for a camera at `centre` with a random orientation.
fn random_pose(rng: &mut Rng, centre: [f64; 3]) -> Pose {
    let q = Quaternion::new(rng.normal(), rng.normal(), rng.normal(), rng.normal());
    let rotation = UnitQuaternion::from_quaternion(q);
    // t = -R C, so that the camera centre is C.
    Pose::new(rotation, -(rotation * Vector3::from(centre)))
}

/// A valid reconstruction of `points` points with tracks of `TRACK_LENGTH` distinct images.
fn synthetic_model(points: usize, seed: u64) -> Reconstruction {
    let mut rng = Rng(seed | 1);
    let mut builder = Reconstruction::builder();
    for id in 1..=CAMERAS {
        let (w, h) = RESOLUTIONS[(id as usize - 1) % RESOLUTIONS.len()];
        let focal = w.max(h) as f64 * rng.uniform(0.8, 1.2);
        builder.add_camera(Camera {
            id,
            model: CameraModel::SimpleRadial,
            width: w,
            height: h,
            params: vec![
                focal,
                w as f64 / 2.0,
                h as f64 / 2.0,
                rng.uniform(-0.05, 0.05),
            ],
        });
    }

    // Track images: L draws from [0, IMAGES - L], sorted, plus 0..L: strictly increasing,
    // so distinct (the same construction as the python generator).
    let n_images = IMAGES as usize;
    let mut track_images = vec![0u32; points * TRACK_LENGTH];
    let mut per_image: Vec<Vec<u32>> = vec![Vec::new(); n_images]; // observation indices
    for (p, track) in track_images.chunks_exact_mut(TRACK_LENGTH).enumerate() {
        for slot in track.iter_mut() {
            *slot = rng.below((n_images - TRACK_LENGTH + 1) as u64) as u32;
        }
        track.sort_unstable();
        for (k, slot) in track.iter_mut().enumerate() {
            *slot += k as u32;
            per_image[*slot as usize].push((p * TRACK_LENGTH + k) as u32);
        }
    }

    // Each image: its observations take random slots among its points2D (a Fisher–Yates
    // shuffle of the slots); the other slots stay untriangulated.
    let mut point2d_idx = vec![0u32; points * TRACK_LENGTH];
    for (i, observations) in per_image.iter().enumerate() {
        let camera_id = i as u32 % CAMERAS + 1;
        let (w, h) = RESOLUTIONS[(camera_id as usize - 1) % RESOLUTIONS.len()];
        let n_obs = observations.len();
        let total = n_obs + (n_obs as f64 * UNTRIANGULATED).round() as usize;
        let mut slots: Vec<u32> = (0..total as u32).collect();
        for j in (1..total).rev() {
            slots.swap(j, rng.below(j as u64 + 1) as usize);
        }
        let mut points2d: Vec<Point2D> = (0..total)
            .map(|_| Point2D {
                xy: [
                    rng.uniform(0.5, w as f64 - 0.5),
                    rng.uniform(0.5, h as f64 - 0.5),
                ],
                point3d_id: None,
            })
            .collect();
        for (&o, &slot) in observations.iter().zip(&slots) {
            point2d_idx[o as usize] = slot;
            points2d[slot as usize].point3d_id = Some(o as u64 / TRACK_LENGTH as u64 + 1);
        }
        let centre = [
            rng.uniform(-100.0, 100.0),
            rng.uniform(1.0, 3.0),
            rng.uniform(-100.0, 100.0),
        ];
        builder.add_image(Image {
            id: i as u32 + 1,
            name: format!("cam{camera_id:02}/frame_{:06}.jpg", i + 1),
            camera_id,
            cam_from_world: random_pose(&mut rng, centre),
            points2d,
        });
    }

    builder.reserve_points3d(points, points * TRACK_LENGTH);
    let mut track = Vec::with_capacity(TRACK_LENGTH);
    for p in 0..points {
        track.clear();
        let range = p * TRACK_LENGTH..(p + 1) * TRACK_LENGTH;
        for (&image, &idx) in track_images[range.clone()].iter().zip(&point2d_idx[range]) {
            track.push(TrackElement {
                image_id: image + 1,
                point2d_idx: idx,
            });
        }
        let xyz = [
            rng.uniform(-100.0, 100.0),
            rng.uniform(0.0, 30.0),
            rng.uniform(-100.0, 100.0),
        ];
        let c = rng.next().to_le_bytes();
        let error = 0.1 + 1.4 * rng.unit();
        builder
            .add_point3d(p as u64 + 1, xyz, [c[0], c[1], c[2]], error, &track)
            .unwrap();
    }
    builder.build().expect("the synthetic model is valid")
}

/// The model folder for `points` points, generated on first use.
fn model_dir(points: usize) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(format!(
        "target/bench-colmap/rust-{points}p-{IMAGES}i-v{GENERATOR_VERSION}"
    ));
    // Written last: its presence means the three files are complete.
    let marker = dir.join("complete");
    if marker.is_file() {
        return dir;
    }
    std::fs::create_dir_all(&dir).unwrap();
    let model = synthetic_model(points, 0x5f3d_a11c_e000 + points as u64);
    std::fs::write(dir.join("cameras.bin"), write_cameras(&model)).unwrap();
    std::fs::write(dir.join("images.bin"), write_images(&model)).unwrap();
    std::fs::write(dir.join("points3D.bin"), write_points3d(&model)).unwrap();
    std::fs::write(&marker, b"").unwrap();
    dir
}

/// `database.db` next to the model in `dir`, generated on first use (written to a temp name,
/// then renamed, so a complete file means a complete database).
fn database(dir: &Path) -> PathBuf {
    let path = dir.join("database.db");
    if path.is_file() {
        return path;
    }
    let model = read_model_bin(dir).unwrap();
    let tmp = dir.join("database.db.tmp");
    let _ = std::fs::remove_file(&tmp);
    let mut db = rusqlite::Connection::open(&tmp).unwrap();
    // COLMAP's columns (the reader needs these four tables).
    db.execute_batch(
        "CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY, model INTEGER, width INTEGER,
             height INTEGER, params BLOB, prior_focal_length INTEGER);
         CREATE TABLE images (image_id INTEGER PRIMARY KEY, name TEXT UNIQUE, camera_id INTEGER);
         CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY, rows INTEGER, cols INTEGER, data BLOB);
         CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY, rows INTEGER, cols INTEGER, data BLOB);",
    )
    .unwrap();
    let tx = db.transaction().unwrap();
    for c in model.cameras() {
        let params: Vec<u8> = c.params.iter().flat_map(|v| v.to_le_bytes()).collect();
        tx.execute(
            "INSERT INTO cameras VALUES (?1, ?2, ?3, ?4, ?5, 0)",
            rusqlite::params![c.id, c.model.id(), c.width as i64, c.height as i64, params],
        )
        .unwrap();
    }
    let mut rng = Rng(0x0d15_ea5e);
    for image in model.images() {
        tx.execute(
            "INSERT INTO images VALUES (?1, ?2, ?3)",
            rusqlite::params![image.id, image.name, image.camera_id],
        )
        .unwrap();
        let rows = image.points2d.len();
        let mut keypoints = Vec::with_capacity(rows * 6 * 4);
        let mut descriptors = Vec::with_capacity(rows * 128);
        for p in &image.points2d {
            // SIFT-like scales: log-uniform over 1.5..24 px, a scaled rotation.
            let scale = 1.5 * 16f64.powf(rng.unit()) as f32;
            let angle = rng.uniform(-std::f64::consts::PI, std::f64::consts::PI) as f32;
            let (sin, cos) = angle.sin_cos();
            for v in [
                p.xy[0] as f32,
                p.xy[1] as f32,
                scale * cos,
                -scale * sin,
                scale * sin,
                scale * cos,
            ] {
                keypoints.extend_from_slice(&v.to_le_bytes());
            }
            let mut base = Rng(p
                .point3d_id
                .map_or(rng.next(), |id| id.wrapping_mul(0x9e37_79b9_7f4a_7c15)));
            for _ in 0..128 / 8 {
                let (b, noise) = (base.next().to_le_bytes(), rng.next().to_le_bytes());
                for (b, n) in b.iter().zip(noise) {
                    // Values 0..~140 like SIFT's (0.2-clipped, ×512); ±8 of per-view noise.
                    descriptors.push((b % 128).saturating_add(n % 16).saturating_sub(8));
                }
            }
        }
        tx.execute(
            "INSERT INTO keypoints VALUES (?1, ?2, 6, ?3)",
            rusqlite::params![image.id, rows as i64, keypoints],
        )
        .unwrap();
        tx.execute(
            "INSERT INTO descriptors VALUES (?1, ?2, 128, ?3)",
            rusqlite::params![image.id, rows as i64, descriptors],
        )
        .unwrap();
    }
    tx.commit().unwrap();
    drop(db);
    std::fs::rename(&tmp, &path).unwrap();
    path
}

fn model_bytes(dir: &Path) -> u64 {
    ["cameras.bin", "images.bin", "points3D.bin"]
        .iter()
        .map(|f| std::fs::metadata(dir.join(f)).unwrap().len())
        .sum()
}

fn sizes() -> Vec<usize> {
    let max: usize = std::env::var("SFPMAP_BENCH_MAX_POINTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_000_000);
    [100_000, 1_000_000]
        .into_iter()
        .filter(|&n| n <= max)
        .collect()
}

fn label(points: usize) -> String {
    match points {
        n if n % 1_000_000 == 0 => format!("{}M", n / 1_000_000),
        n if n % 1000 == 0 => format!("{}k", n / 1000),
        n => n.to_string(),
    }
}

fn convert_geometry(c: &mut Criterion) {
    let out_dir = tempfile::tempdir().unwrap();
    let output = out_dir.path().join("synthetic.sfpm");
    let mut group = c.benchmark_group("convert");
    group.sample_size(10);
    for points in sizes() {
        let dir = model_dir(points);
        // Sanity check and sizes, outside the measurement.
        let summary = convert(&dir, &ConvertOptions::default(), &output, &Silent).unwrap();
        assert_eq!(summary.points, points);
        assert_eq!(summary.observations, points * TRACK_LENGTH);
        eprintln!(
            "convert/{}: model {:.1} MB -> map {:.1} MB (geometry only)",
            label(points),
            model_bytes(&dir) as f64 / 1e6,
            summary.output_bytes as f64 / 1e6
        );
        group.throughput(Throughput::Elements(points as u64));
        group.bench_with_input(
            BenchmarkId::new("geometry", label(points)),
            &dir,
            |b, dir| {
                b.iter(|| {
                    convert(dir, &ConvertOptions::default(), &output, &Silent)
                        .unwrap()
                        .output_bytes
                })
            },
        );
        group.bench_with_input(
            BenchmarkId::new("read_model", label(points)),
            &dir,
            |b, dir| b.iter(|| read_model_bin(dir).unwrap().num_observations()),
        );
    }
    group.finish();
}

/// With descriptors: 100k points only (the 1M database would be ~1 GB).
fn convert_with_database(c: &mut Criterion) {
    let out_dir = tempfile::tempdir().unwrap();
    let output = out_dir.path().join("synthetic.sfpm");
    let points = 100_000;
    let dir = model_dir(points);
    let options = ConvertOptions {
        database: Some(database(&dir)),
        ..ConvertOptions::default()
    };
    let summary = convert(&dir, &options, &output, &Silent).unwrap();
    assert_eq!(summary.points, points);
    assert_eq!(summary.points_without_descriptors, 0);
    assert_eq!(summary.levels.len(), 3);
    eprintln!(
        "convert/with_database/{}: model + database {:.1} MB -> map {:.1} MB",
        label(points),
        summary.input_bytes as f64 / 1e6,
        summary.output_bytes as f64 / 1e6
    );
    let mut group = c.benchmark_group("convert");
    group.sample_size(10);
    group.throughput(Throughput::Elements(points as u64));
    group.bench_function(BenchmarkId::new("with_database", label(points)), |b| {
        b.iter(|| {
            convert(&dir, &options, &output, &Silent)
                .unwrap()
                .output_bytes
        })
    });
    group.finish();
}

criterion_group!(benches, convert_geometry, convert_with_database);
criterion_main!(benches);
