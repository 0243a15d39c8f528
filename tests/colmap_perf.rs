//! Measurements, not timed tests (ignored by default). Run in release:
//!
//! ```text
//! SFPMAP_COLMAP_PERF_DIR=/tmp/big cargo test --release --no-default-features \
//!     --features colmap --test colmap_perf -- --ignored --nocapture --test-threads 1
//! ```
//!
//! `generate` writes a synthetic binary model of 1 M points × track length 5 (1000 images of
//! 5000 points2D each) to `$SFPMAP_COLMAP_PERF_DIR` (and as text to its `txt/`); `read` and
//! `read_text` read it back and print the time.
//! Run `read` alone under `/usr/bin/time -v` for its peak memory.
#![cfg(feature = "colmap")]

use std::path::PathBuf;
use std::time::Instant;

use sfpmap::colmap::TrackElement;
use sfpmap::colmap::{
    self, bin, text, Camera, CameraModel, Image, Point2D, Reconstruction, Rigid3,
};

const POINTS: u64 = 1_000_000;
const TRACK: u64 = 5;
const IMAGES: u32 = 1000;

fn perf_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("SFPMAP_COLMAP_PERF_DIR").map(PathBuf::from);
    if dir.is_none() {
        println!("note: set SFPMAP_COLMAP_PERF_DIR to run");
    }
    dir
}

/// Observation `k` of point `p` is in image `(p * TRACK + k) % IMAGES`; each image gets its
/// observations in point order, so `point2D_idx = (p * TRACK + k) / IMAGES`.
fn synthetic() -> Reconstruction {
    let mut b = Reconstruction::builder();
    b.add_camera(Camera {
        id: 1,
        model: CameraModel::SimpleRadial,
        width: 1024,
        height: 768,
        params: vec![800.0, 512.0, 384.0, 0.01],
    });
    let per_image = (POINTS * TRACK / u64::from(IMAGES)) as usize;
    let mut images: Vec<Vec<Point2D>> = vec![Vec::with_capacity(per_image); IMAGES as usize];
    b.reserve_points3d(POINTS as usize, (POINTS * TRACK) as usize);
    let mut track = Vec::with_capacity(TRACK as usize);
    for p in 0..POINTS {
        track.clear();
        for k in 0..TRACK {
            let obs = p * TRACK + k;
            let image = (obs % u64::from(IMAGES)) as usize;
            track.push(TrackElement {
                image_id: image as u32 + 1,
                point2d_idx: images[image].len() as u32,
            });
            let f = obs as f64;
            images[image].push(Point2D {
                xy: [f % 1024.0 + 0.5, (f / 1024.0) % 768.0 + 0.5],
                point3d_id: Some(p + 1),
            });
        }
        let f = p as f64;
        b.add_point3d(p + 1, [f * 1e-3, -f * 2e-3, 5.0], [1, 2, 3], 0.5, &track)
            .unwrap();
    }
    for (i, points2d) in images.into_iter().enumerate() {
        b.add_image(Image {
            id: i as u32 + 1,
            name: format!("images/{i:06}.jpg"),
            camera_id: 1,
            cam_from_world: Rigid3 {
                rotation: [1.0, 0.0, 0.0, 0.0],
                translation: [i as f64, 0.0, 0.0],
            },
            points2d,
        });
    }
    b.build().unwrap()
}

#[test]
#[ignore]
fn generate() {
    let Some(dir) = perf_dir() else { return };
    std::fs::create_dir_all(&dir).unwrap();
    let start = Instant::now();
    let model = synthetic();
    println!(
        "built + validated in {:.2} s",
        start.elapsed().as_secs_f64()
    );
    std::fs::write(dir.join("cameras.bin"), bin::write_cameras(&model)).unwrap();
    std::fs::write(dir.join("images.bin"), bin::write_images(&model)).unwrap();
    std::fs::write(dir.join("points3D.bin"), bin::write_points3d(&model)).unwrap();
    let txt = dir.join("txt");
    std::fs::create_dir_all(&txt).unwrap();
    std::fs::write(txt.join("cameras.txt"), text::write_cameras(&model)).unwrap();
    std::fs::write(txt.join("images.txt"), text::write_images(&model)).unwrap();
    std::fs::write(txt.join("points3D.txt"), text::write_points3d(&model)).unwrap();
}

#[test]
#[ignore]
fn read() {
    let Some(dir) = perf_dir() else { return };
    read_and_report(&dir, "bin");
}

#[test]
#[ignore]
fn read_text() {
    let Some(dir) = perf_dir() else { return };
    read_and_report(&dir.join("txt"), "txt");
}

fn read_and_report(dir: &std::path::Path, ext: &str) {
    let bytes: u64 = ["cameras", "images", "points3D"]
        .iter()
        .map(|f| {
            std::fs::metadata(dir.join(format!("{f}.{ext}")))
                .unwrap()
                .len()
        })
        .sum();
    let start = Instant::now();
    let model = colmap::read_model(dir).unwrap();
    let seconds = start.elapsed().as_secs_f64();
    assert_eq!(model.points3d().len() as u64, POINTS);
    assert_eq!(model.num_observations() as u64, POINTS * TRACK);
    println!(
        "read {} points, {} observations, {:.1} MB in {seconds:.2} s ({:.0} MB/s)",
        model.points3d().len(),
        model.num_observations(),
        bytes as f64 / 1e6,
        bytes as f64 / 1e6 / seconds
    );
}

/// A longer run of the fuzz entry points on mutated real files (`SFPMAP_SOAK_ITERS`, default
/// 200000 per file): byte flips, insertions, deletions and splices. Panics are the failure.
#[test]
#[ignore]
fn mutation_soak() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/colmap");
    if !root.is_dir() {
        println!("note: {} is absent", root.display());
        return;
    }
    let iters: u64 = std::env::var("SFPMAP_SOAK_ITERS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(200_000);
    let mut seed = 0x2545f4914f6cdd1du64;
    let mut next = move || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    let files = [
        "yding121_video_frames/sparse/0/cameras.bin",
        "yding121_video_frames/sparse/0/images.bin",
        "yding121_video_frames/sparse/0/points3D.bin",
        "kapture_maupertuis/reconstruction/cameras.txt",
        "kapture_maupertuis/reconstruction/images.txt",
        "kapture_maupertuis/reconstruction/points3D.txt",
    ];
    let start = Instant::now();
    for file in files {
        let base = std::fs::read(root.join(file)).unwrap();
        // Short inputs keep each try cheap; the headers and first records are where the
        // interesting lengths and counts are.
        let base = &base[..base.len().min(4096)];
        for _ in 0..iters {
            let mut data = base.to_vec();
            for _ in 0..1 + next() % 8 {
                let at = (next() % (data.len() as u64 + 1)) as usize;
                match next() % 4 {
                    0 if at < data.len() => data[at] = next() as u8,
                    1 => data.insert(at, next() as u8),
                    2 if at < data.len() => {
                        data.remove(at);
                    }
                    _ => {
                        let len = (next() % 16) as usize;
                        let from = (next() % base.len() as u64) as usize;
                        let end = (from + len).min(base.len());
                        data.splice(at..at, base[from..end].iter().copied());
                    }
                }
            }
            colmap::fuzz_read_bin(&data);
            colmap::fuzz_read_txt(&data);
        }
    }
    println!(
        "{} mutated inputs in {:.1} s, no panic",
        iters * files.len() as u64,
        start.elapsed().as_secs_f64()
    );
}
