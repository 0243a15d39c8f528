//! Geometry benches (group `localize`): P3P per solve, LO-RANSAC on 1,000 correspondences at
//! 50 % and 90 % outliers, LM refinement on 500 inliers. Synthetic scenes: SIMPLE_RADIAL
//! 1024×768, points 2–20 units away, 1 px noise, wrong matches as outliers.
//!
//! Run: `cargo bench --bench geometry --no-default-features --features localize`

#[cfg(feature = "localize")]
mod geometry {
    use std::hint::black_box;

    use criterion::{BenchmarkId, Criterion};
    use nalgebra::{UnitQuaternion, Vector2, Vector3};
    use sfpmap::fuzzing::SplitMix64;
    use sfpmap::geometry::{
        estimate_absolute_pose, p3p, refine_pose, Camera, Pose, RansacOptions, RefineOptions,
    };

    struct Scene {
        camera: Camera,
        truth: Pose,
        pixels: Vec<Vector2<f64>>,
        points: Vec<Vector3<f64>>,
    }

    fn gaussian(rng: &mut SplitMix64) -> f64 {
        let (u, v) = (1.0 - rng.next_f64(), rng.next_f64());
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }

    fn scene(seed: u64, n: usize, outlier_ratio: f64) -> Scene {
        let mut rng = SplitMix64::new(seed);
        let camera = Camera::parse("SIMPLE_RADIAL 1024 768 800 512 384 -0.05").unwrap();
        let rotation = UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -1.2, 0.4));
        let truth = Pose::new(rotation, Vector3::new(0.5, -1.0, 2.0));
        let world_from_cam = truth.inverse();
        let num_outliers = (n as f64 * outlier_ratio).round() as usize;
        let (mut pixels, mut points) = (Vec::new(), Vec::new());
        for i in 0..n {
            let pixel = Vector2::new(rng.next_f64() * 1024.0, rng.next_f64() * 768.0);
            let xy = camera.unproject(&pixel);
            let depth = 2.0 + 18.0 * rng.next_f64();
            points.push(world_from_cam.transform(&(Vector3::new(xy.x, xy.y, 1.0) * depth)));
            pixels.push(if i < num_outliers {
                Vector2::new(rng.next_f64() * 1024.0, rng.next_f64() * 768.0)
            } else {
                pixel + Vector2::new(gaussian(&mut rng), gaussian(&mut rng))
            });
        }
        Scene {
            camera,
            truth,
            pixels,
            points,
        }
    }

    pub fn benches(c: &mut Criterion) {
        let mut group = c.benchmark_group("localize");

        let s = scene(1, 1000, 0.0);
        let bearings: Vec<Vector3<f64>> = s.pixels.iter().map(|p| s.camera.bearing(p)).collect();
        let mut j = 0;
        group.bench_function("p3p", |b| {
            b.iter(|| {
                j = (j + 3) % 996;
                black_box(p3p(
                    &[bearings[j], bearings[j + 1], bearings[j + 2]],
                    &[s.points[j], s.points[j + 1], s.points[j + 2]],
                ))
            })
        });

        let options = RansacOptions {
            max_error_px: 4.0,
            ..RansacOptions::default()
        };
        for outliers in [0.5, 0.9] {
            let s = scene(2, 1000, outliers);
            group.bench_with_input(
                BenchmarkId::new("ransac_1000", format!("{}%", outliers * 100.0)),
                &s,
                |b, s| {
                    b.iter(|| {
                        estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap()
                    })
                },
            );
        }

        let s = scene(3, 500, 0.0);
        let start = Pose::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.01, -0.02, 0.005)) * s.truth.rotation,
            s.truth.translation + Vector3::new(0.05, -0.05, 0.02),
        );
        let refine = RefineOptions::default();
        group.bench_function("refine_500", |b| {
            b.iter(|| refine_pose(&s.pixels, &s.points, &s.camera, &start, &refine).unwrap())
        });
        group.finish();
    }
}

#[cfg(feature = "localize")]
criterion::criterion_group!(benches, geometry::benches);
#[cfg(feature = "localize")]
criterion::criterion_main!(benches);

/// Without the `localize` feature there is nothing to measure.
#[cfg(not(feature = "localize"))]
fn main() {}
