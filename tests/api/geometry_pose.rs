//! P3P, LO-RANSAC and LM refinement on synthetic correspondences.
#![cfg(feature = "localize")]

use nalgebra::{UnitQuaternion, Vector2, Vector3};
use proptest::prelude::*;
use sfpmap::fuzzing::SplitMix64;
use sfpmap::geometry::{
    estimate_absolute_pose, estimate_absolute_pose_with_prior, p3p, refine_pose,
    refine_pose_masked, reprojection_inliers, required_iterations, Camera, GeometryError, Pose,
    RansacOptions, RefineOptions, RobustLoss,
};

struct Scene {
    camera: Camera,
    truth: Pose,
    pixels: Vec<Vector2<f64>>,
    points: Vec<Vector3<f64>>,
    is_inlier: Vec<bool>,
}

fn gaussian(rng: &mut SplitMix64) -> f64 {
    // Box–Muller; 1 − u avoids ln(0).
    let (u, v) = (1.0 - rng.next_f64(), rng.next_f64());
    (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
}

fn random_pose(rng: &mut SplitMix64) -> Pose {
    let axis = Vector3::new(gaussian(rng), gaussian(rng), gaussian(rng)).normalize();
    let angle = rng.next_f64() * std::f64::consts::PI;
    let rotation = UnitQuaternion::from_scaled_axis(axis * angle);
    let center = Vector3::new(gaussian(rng), gaussian(rng), gaussian(rng)) * 5.0;
    Pose::new(rotation, -(rotation * center))
}

/// Points seen at random pixels and depths 2–20, pixel noise `noise_px` (σ), and a fraction
/// of outliers whose pixel is replaced by a random one (a wrong match).
fn scene(seed: u64, camera: &str, n: usize, outlier_ratio: f64, noise_px: f64) -> Scene {
    let mut rng = SplitMix64::new(seed);
    let camera = Camera::parse(camera).unwrap();
    let truth = random_pose(&mut rng);
    let world_from_cam = truth.inverse();
    let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
    let num_outliers = (n as f64 * outlier_ratio).round() as usize;
    let mut scene = Scene {
        camera,
        truth,
        pixels: Vec::with_capacity(n),
        points: Vec::with_capacity(n),
        is_inlier: Vec::with_capacity(n),
    };
    for i in 0..n {
        let pixel = Vector2::new(rng.next_f64() * w, rng.next_f64() * h);
        let depth = 2.0 + 18.0 * rng.next_f64();
        let xy = scene.camera.unproject(&pixel);
        let p_cam = Vector3::new(xy.x, xy.y, 1.0) * depth;
        scene.points.push(world_from_cam.transform(&p_cam));
        let inlier = i >= num_outliers;
        let observed = if inlier {
            pixel + Vector2::new(gaussian(&mut rng), gaussian(&mut rng)) * noise_px
        } else {
            Vector2::new(rng.next_f64() * w, rng.next_f64() * h)
        };
        scene.pixels.push(observed);
        scene.is_inlier.push(inlier);
    }
    scene
}

const SIMPLE_RADIAL: &str = "SIMPLE_RADIAL 1024 768 800 512 384 -0.05";
const FISHEYE: &str = "OPENCV_FISHEYE 1024 768 400 405 515 380 0.05 -0.01 0.002 -0.0005";
const OPENCV: &str = "OPENCV 1024 768 800 805 515 380 -0.1 0.02 0.0005 -0.0007";

fn best_error(solutions: &[Pose], truth: &Pose) -> (f64, f64) {
    solutions
        .iter()
        .map(|s| (s.rotation_error_deg(truth), s.center_distance(truth)))
        .min_by(|a, b| (a.0 + a.1).total_cmp(&(b.0 + b.1)))
        .unwrap_or((f64::INFINITY, f64::INFINITY))
}

#[test]
fn p3p_recovers_exact_poses() {
    for seed in 0..200 {
        let s = scene(seed, SIMPLE_RADIAL, 3, 0.0, 0.0);
        let bearings = [0, 1, 2].map(|i| s.camera.bearing(&s.pixels[i]));
        let points = [s.points[0], s.points[1], s.points[2]];
        let solutions = p3p(&bearings, &points);
        assert!(solutions.len() <= 4);
        let (rot, pos) = best_error(&solutions, &s.truth);
        assert!(rot < 1e-6 && pos < 1e-6, "seed {seed}: {rot}° {pos}");
        // Every returned solution explains the three correspondences.
        for pose in &solutions {
            for i in 0..3 {
                let b = pose.transform(&points[i]).normalize();
                assert!((b - bearings[i]).norm() < 1e-6, "seed {seed}");
            }
        }
    }
}

fn check_ransac(
    seed: u64,
    camera: &str,
    n: usize,
    outliers: f64,
    noise: f64,
    options: &RansacOptions,
) {
    let s = scene(seed, camera, n, outliers, noise);
    let estimate = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, options).unwrap();
    let rot = estimate.pose.rotation_error_deg(&s.truth);
    let pos = estimate.pose.center_distance(&s.truth);
    // Points are 2–20 units away; 2 cm at 1 px noise is a few tenths of a pixel of parallax.
    assert!(
        rot < 0.5 && pos < 0.05,
        "seed {seed}, {outliers}: {rot}° {pos} ({} iterations)",
        estimate.iterations
    );
    let true_inliers = s.is_inlier.iter().filter(|&&b| b).count();
    let recovered = estimate
        .inliers
        .iter()
        .zip(&s.is_inlier)
        .filter(|(a, b)| **a && **b)
        .count();
    assert!(
        recovered as f64 >= 0.95 * true_inliers as f64,
        "seed {seed}: {recovered}/{true_inliers}"
    );
    assert_eq!(
        estimate.num_inliers,
        estimate.inliers.iter().filter(|&&b| b).count()
    );
    assert_eq!(estimate.inlier_indices().count(), estimate.num_inliers);
    assert!(estimate.inlier_indices().all(|i| estimate.inliers[i]));
    assert!(estimate.mean_inlier_error_px < 2.0 * noise + 0.5);
    // The adaptive count stopped where the true inlier ratio says it should, with slack for
    // SPRT's rejections of good poses and inliers lost to noise; not at the cap.
    let expected = required_iterations(0.8 * true_inliers as f64 / n as f64, options.confidence)
        .max(options.min_iterations);
    assert!(
        estimate.iterations <= expected,
        "seed {seed}, {outliers}: {} iterations, expected at most {expected}",
        estimate.iterations
    );
}

fn test_options() -> RansacOptions {
    RansacOptions {
        max_error_px: 4.0,
        ..RansacOptions::default()
    }
}

#[test]
fn ransac_50_percent_outliers() {
    for seed in 0..2 {
        check_ransac(seed, SIMPLE_RADIAL, 1000, 0.5, 1.0, &test_options());
    }
    check_ransac(2, FISHEYE, 1000, 0.5, 1.0, &test_options());
}

#[test]
fn ransac_70_percent_outliers() {
    for seed in 10..13 {
        check_ransac(seed, OPENCV, 500, 0.7, 0.5, &test_options());
    }
}

#[test]
fn ransac_90_percent_outliers() {
    check_ransac(20, SIMPLE_RADIAL, 300, 0.9, 0.5, &test_options());
    check_ransac(21, OPENCV, 300, 0.9, 1.0, &test_options());
}

#[test]
fn ransac_is_deterministic_for_a_seed() {
    let s = scene(30, SIMPLE_RADIAL, 300, 0.6, 1.0);
    let options = test_options();
    let a = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    let b = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    assert_eq!(a, b);
}

#[test]
fn adaptive_iterations_stop_early_without_outliers() {
    let s = scene(31, SIMPLE_RADIAL, 200, 0.0, 0.5);
    let options = RansacOptions {
        min_iterations: 10,
        ..test_options()
    };
    let estimate = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    assert!(estimate.iterations <= 20, "{}", estimate.iterations);
    assert!(estimate.num_inliers >= 195);
}

#[test]
fn exactly_four_correspondences_suffice() {
    let s = scene(32, SIMPLE_RADIAL, 4, 0.0, 0.0);
    let options = RansacOptions {
        min_inliers: 4,
        ..test_options()
    };
    let estimate = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    assert!(estimate.pose.rotation_error_deg(&s.truth) < 1e-4);
    assert_eq!(estimate.num_inliers, 4);
}

fn perturb(pose: &Pose, degrees: f64, shift: f64) -> Pose {
    let delta = UnitQuaternion::from_scaled_axis(
        Vector3::new(1.0, -2.0, 0.5).normalize() * degrees.to_radians(),
    );
    Pose::new(
        delta * pose.rotation,
        pose.translation + Vector3::new(shift, -shift, 0.5 * shift),
    )
}

#[test]
fn refinement_improves_a_perturbed_pose() {
    let s = scene(40, OPENCV, 400, 0.0, 0.5);
    let start = perturb(&s.truth, 2.0, 0.2);
    for loss in [
        RobustLoss::Trivial,
        RobustLoss::Huber { scale: 2.0 },
        RobustLoss::Cauchy { scale: 1.0 },
    ] {
        let options = RefineOptions {
            loss,
            ..RefineOptions::default()
        };
        let r = refine_pose(&s.pixels, &s.points, &s.camera, &start, &options).unwrap();
        assert!(r.final_cost < r.initial_cost);
        let rot = r.pose.rotation_error_deg(&s.truth);
        let pos = r.pose.center_distance(&s.truth);
        assert!(rot < 0.05 && pos < 0.01, "{loss:?}: {rot}° {pos}");
        assert!(r.iterations > 0 && r.iterations < 50, "{}", r.iterations);
    }
}

#[test]
fn robust_refinement_resists_outliers() {
    let s = scene(41, SIMPLE_RADIAL, 400, 0.3, 0.5);
    let start = perturb(&s.truth, 0.5, 0.05);
    let options = RefineOptions {
        loss: RobustLoss::Cauchy { scale: 1.0 },
        ..RefineOptions::default()
    };
    let r = refine_pose(&s.pixels, &s.points, &s.camera, &start, &options).unwrap();
    assert!(r.pose.rotation_error_deg(&s.truth) < 0.1);
    // The mask restricts the residuals to the true inliers.
    let trivial = RefineOptions {
        loss: RobustLoss::Trivial,
        ..RefineOptions::default()
    };
    let r = refine_pose_masked(
        &s.pixels,
        &s.points,
        &s.is_inlier,
        &s.camera,
        &start,
        &trivial,
    )
    .unwrap();
    assert!(r.pose.rotation_error_deg(&s.truth) < 0.05);
}

#[test]
fn degenerate_inputs_are_errors() {
    let s = scene(50, SIMPLE_RADIAL, 50, 0.0, 0.5);
    let camera = &s.camera;
    let options = test_options();
    let run = |pixels: &[Vector2<f64>], points: &[Vector3<f64>]| {
        estimate_absolute_pose(pixels, points, camera, &options)
    };

    assert_eq!(
        run(&s.pixels[..3], &s.points[..3]),
        Err(GeometryError::TooFewCorrespondences {
            found: 3,
            required: 4
        })
    );
    assert!(matches!(
        run(&s.pixels[..10], &s.points[..9]),
        Err(GeometryError::LengthMismatch { .. })
    ));
    assert!(matches!(
        run(&[], &[]),
        Err(GeometryError::TooFewCorrespondences { found: 0, .. })
    ));

    let mut pixels = s.pixels.clone();
    pixels[7].x = f64::NAN;
    assert_eq!(
        run(&pixels, &s.points),
        Err(GeometryError::NonFinite {
            what: "pixels",
            index: 7
        })
    );
    let mut points = s.points.clone();
    points[3].z = f64::INFINITY;
    assert_eq!(
        run(&s.pixels, &points),
        Err(GeometryError::NonFinite {
            what: "points",
            index: 3
        })
    );

    let coincident = vec![Vector3::new(1.0, 2.0, 3.0); 50];
    assert!(matches!(
        run(&s.pixels, &coincident),
        Err(GeometryError::Degenerate { .. })
    ));
    let collinear: Vec<Vector3<f64>> = (0..50)
        .map(|i| Vector3::new(1.0, 2.0, 3.0) + Vector3::new(0.3, -0.1, 0.7) * f64::from(i))
        .collect();
    assert!(matches!(
        run(&s.pixels, &collinear),
        Err(GeometryError::Degenerate { .. })
    ));
    let same_pixel = vec![Vector2::new(100.0, 100.0); 50];
    assert!(matches!(
        run(&same_pixel, &s.points),
        Err(GeometryError::Degenerate { .. })
    ));

    // Pure noise: no pose has enough support.
    let mut rng = SplitMix64::new(9);
    let noise: Vec<Vector2<f64>> = (0..50)
        .map(|_| Vector2::new(rng.next_f64() * 1024.0, rng.next_f64() * 768.0))
        .collect();
    let strict = RansacOptions {
        min_inliers: 15,
        max_error_px: 2.0,
        max_iterations: 500,
        ..options.clone()
    };
    assert!(matches!(
        estimate_absolute_pose(&noise, &s.points, camera, &strict),
        Err(GeometryError::TooFewInliers { .. })
    ));

    let bad = RansacOptions {
        confidence: 1.0,
        ..options.clone()
    };
    assert!(matches!(
        run_with(&s, &bad),
        Err(GeometryError::InvalidOptions {
            field: "confidence",
            ..
        })
    ));
    let bad = RansacOptions {
        max_error_px: f64::NAN,
        ..options.clone()
    };
    assert!(matches!(
        run_with(&s, &bad),
        Err(GeometryError::InvalidOptions { .. })
    ));

    // Refinement rejects the same inputs.
    let r = RefineOptions::default();
    assert!(matches!(
        refine_pose(&s.pixels[..2], &s.points[..2], camera, &s.truth, &r),
        Err(GeometryError::TooFewCorrespondences { .. })
    ));
    assert!(matches!(
        refine_pose(&pixels, &s.points, camera, &s.truth, &r),
        Err(GeometryError::NonFinite { .. })
    ));
    let behind = Pose::new(
        s.truth.rotation,
        s.truth.translation - Vector3::new(0.0, 0.0, 1e3),
    );
    assert!(matches!(
        refine_pose(&s.pixels, &s.points, camera, &behind, &r),
        Err(GeometryError::RefinementFailed { .. })
    ));
    let nan_pose = Pose::new(s.truth.rotation, Vector3::new(f64::NAN, 0.0, 0.0));
    assert!(matches!(
        refine_pose(&s.pixels, &s.points, camera, &nan_pose, &r),
        Err(GeometryError::NonFinite { .. })
    ));
    assert!(matches!(
        refine_pose_masked(&s.pixels, &s.points, &[true; 3], camera, &s.truth, &r),
        Err(GeometryError::LengthMismatch { what: "mask", .. })
    ));
}

fn run_with(
    s: &Scene,
    options: &RansacOptions,
) -> Result<sfpmap::geometry::PoseEstimate, GeometryError> {
    estimate_absolute_pose(&s.pixels, &s.points, &s.camera, options)
}

#[test]
fn error_messages_are_lowercase() {
    let errors = [
        GeometryError::TooFewCorrespondences {
            found: 3,
            required: 4,
        },
        GeometryError::Degenerate {
            reason: "all 3d points are collinear",
        },
        GeometryError::NoModel { iterations: 10 },
        GeometryError::NonFinite {
            what: "pixels",
            index: 2,
        },
    ];
    for e in errors {
        let message = e.to_string();
        assert!(message.starts_with(|c: char| c.is_lowercase()), "{message}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// P3P on random poses and triangles finds the true pose among its solutions.
    #[test]
    fn p3p_random_poses(seed in any::<u64>()) {
        let s = scene(seed, OPENCV, 3, 0.0, 0.0);
        let bearings = [0, 1, 2].map(|i| s.camera.bearing(&s.pixels[i]));
        let points = [s.points[0], s.points[1], s.points[2]];
        let solutions = p3p(&bearings, &points);
        let (rot, pos) = best_error(&solutions, &s.truth);
        // Nearly-degenerate triangles (almost collinear in view) may lose digits, not the pose.
        prop_assert!(rot < 1e-4 && pos < 1e-4, "{rot}° {pos}");
        for pose in &solutions {
            prop_assert!(pose.is_finite());
        }
    }

    /// Arbitrary (possibly degenerate) inputs never panic and never give a non-finite pose.
    #[test]
    fn p3p_never_returns_nan(values in proptest::collection::vec(-10.0f64..10.0, 18)) {
        let v = |i: usize| Vector3::new(values[i], values[i + 1], values[i + 2]);
        let solutions = p3p(&[v(0), v(3), v(6)], &[v(9), v(12), v(15)]);
        prop_assert!(solutions.len() <= 4);
        for pose in &solutions {
            prop_assert!(pose.is_finite());
        }
    }

}

proptest! {
    // RANSAC cases are the slow ones in unoptimized test builds.
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// RANSAC with noise and outliers over random poses; small sizes keep the test fast.
    #[test]
    fn ransac_random_poses(seed in any::<u64>(), outliers in 0.0f64..0.6) {
        let s = scene(seed, SIMPLE_RADIAL, 120, outliers, 0.7);
        let options = RansacOptions { seed, ..test_options() };
        let estimate = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
        prop_assert!(estimate.pose.rotation_error_deg(&s.truth) < 0.5);
        prop_assert!(estimate.pose.center_distance(&s.truth) < 0.1);
    }

    /// Refinement from a perturbed pose never increases the cost and stays finite.
    #[test]
    fn refinement_never_worsens(seed in any::<u64>(), degrees in 0.0f64..5.0, shift in 0.0f64..0.5) {
        let s = scene(seed, OPENCV, 60, 0.2, 1.0);
        let start = perturb(&s.truth, degrees, shift);
        let r = refine_pose(&s.pixels, &s.points, &s.camera, &start, &RefineOptions::default()).unwrap();
        prop_assert!(r.final_cost <= r.initial_cost);
        prop_assert!(r.pose.is_finite());
    }
}

fn wild_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        -1e3f64..1e3,
        -1e300f64..1e300,
        Just(0.0),
        Just(f64::MIN_POSITIVE),
        Just(f64::NAN),
        Just(f64::INFINITY),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    /// Whatever the input, estimation returns an error or a finite pose; it never panics.
    #[test]
    fn estimation_never_panics_or_returns_nan(
        pixel_values in proptest::collection::vec(wild_f64(), 0..40),
        point_values in proptest::collection::vec(wild_f64(), 0..60),
    ) {
        let pixels: Vec<Vector2<f64>> =
            pixel_values.chunks_exact(2).map(|c| Vector2::new(c[0], c[1])).collect();
        let points: Vec<Vector3<f64>> =
            point_values.chunks_exact(3).map(|c| Vector3::new(c[0], c[1], c[2])).collect();
        let n = pixels.len().min(points.len());
        let camera = Camera::parse(OPENCV).unwrap();
        let options = RansacOptions { max_iterations: 200, ..test_options() };
        if let Ok(estimate) = estimate_absolute_pose(&pixels[..n], &points[..n], &camera, &options) {
            prop_assert!(estimate.pose.is_finite());
        }
        let start = Pose::identity();
        if let Ok(refined) = refine_pose(&pixels[..n], &points[..n], &camera, &start, &RefineOptions::default()) {
            prop_assert!(refined.pose.is_finite());
        }
    }
}

#[test]
fn huge_coordinates_fail_cleanly() {
    let s = scene(70, SIMPLE_RADIAL, 50, 0.0, 0.5);
    let huge: Vec<Vector3<f64>> = s.points.iter().map(|p| p * 1e307).collect();
    let result = estimate_absolute_pose(&s.pixels, &huge, &s.camera, &test_options());
    assert!(result.is_err() || result.unwrap().pose.is_finite());
    // Far from the origin but well-conditioned: a city-scale map in metres.
    let offset = Vector3::new(4.0e5, 5.4e6, 120.0);
    let shifted: Vec<Vector3<f64>> = s.points.iter().map(|p| p + offset).collect();
    let truth = Pose::new(
        s.truth.rotation,
        s.truth.translation - s.truth.rotation * offset,
    );
    let estimate = estimate_absolute_pose(&s.pixels, &shifted, &s.camera, &test_options()).unwrap();
    assert!(estimate.pose.rotation_error_deg(&truth) < 0.5);
    assert!(estimate.pose.center_distance(&truth) < 0.05);
}

#[test]
fn a_good_prior_shortens_ransac() {
    let s = scene(80, SIMPLE_RADIAL, 300, 0.9, 1.0);
    let options = test_options();
    let prior = perturb(&s.truth, 0.3, 0.02);
    let estimate =
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&prior), &options)
            .unwrap();
    assert!(estimate.pose.rotation_error_deg(&s.truth) < 0.5);
    assert!(estimate.pose.center_distance(&s.truth) < 0.05);
    // The adaptive count for 10 % inliers is ~10^4, far more than the ~10^3 samples it takes
    // to draw a first all-inlier one; a good prior cannot shorten that count below what the
    // inlier ratio demands, but it must not be slower than the same call without it.
    let without = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    assert!(
        estimate.iterations <= without.iterations,
        "{} iterations with the prior, {} without",
        estimate.iterations,
        without.iterations
    );
    let mask = reprojection_inliers(&s.pixels, &s.points, &s.camera, &estimate.pose, 4.0);
    assert_eq!(mask, estimate.inliers);

    // At a low confidence the adaptive count is no longer than the wait for a first all-inlier
    // sample (both ~10^3 at 10 % inliers), so RANSAC without a prior often runs past it; the
    // prior removes that wait. Never slower per scene, fewer in total.
    let loose = RansacOptions {
        confidence: 0.5,
        min_iterations: 1,
        ..test_options()
    };
    let (mut with_prior, mut without_prior) = (0, 0);
    for seed in 200..220 {
        let s = scene(seed, SIMPLE_RADIAL, 300, 0.9, 1.0);
        let options = RansacOptions {
            seed,
            ..loose.clone()
        };
        let prior = perturb(&s.truth, 0.3, 0.02);
        let with = estimate_absolute_pose_with_prior(
            &s.pixels,
            &s.points,
            &s.camera,
            Some(&prior),
            &options,
        )
        .unwrap();
        let without = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
        assert!(with.pose.rotation_error_deg(&s.truth) < 0.5, "seed {seed}");
        assert!(
            with.iterations <= without.iterations,
            "seed {seed}: {} iterations with the prior, {} without",
            with.iterations,
            without.iterations
        );
        with_prior += with.iterations;
        without_prior += without.iterations;
    }
    assert!(
        with_prior < without_prior,
        "{with_prior} iterations with priors, {without_prior} without"
    );

    // With 30 % outliers a prior lets RANSAC stop at the minimum.
    let s = scene(81, SIMPLE_RADIAL, 300, 0.3, 1.0);
    let options = RansacOptions {
        min_iterations: 5,
        ..test_options()
    };
    let prior = perturb(&s.truth, 0.3, 0.02);
    let estimate =
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&prior), &options)
            .unwrap();
    assert!(estimate.iterations <= 30, "{}", estimate.iterations);
    assert!(estimate.pose.rotation_error_deg(&s.truth) < 0.5);
    let without = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    assert!(
        estimate.iterations <= without.iterations,
        "{} iterations with the prior, {} without",
        estimate.iterations,
        without.iterations
    );
    // A non-finite prior is an input error.
    let nan = Pose::new(prior.rotation, Vector3::new(f64::NAN, 0.0, 0.0));
    assert!(matches!(
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&nan), &options),
        Err(GeometryError::NonFinite {
            what: "prior pose",
            ..
        })
    ));
}

/// P3P accuracy over many random configurations, wide and narrow field of view.
#[test]
fn p3p_accuracy_over_random_scenes() {
    for (label, camera) in [
        ("wide", SIMPLE_RADIAL),
        ("narrow", "PINHOLE 1024 768 8000 8000 512 384"),
    ] {
        let trials = 3_000;
        let (mut none, mut bad, mut worst) = (0, 0, 0.0f64);
        let mut counts = [0usize; 5];
        for seed in 0..trials {
            let s = scene(seed, camera, 3, 0.0, 0.0);
            let bearings = [0, 1, 2].map(|i| s.camera.bearing(&s.pixels[i]));
            let solutions = p3p(&bearings, &[s.points[0], s.points[1], s.points[2]]);
            counts[solutions.len()] += 1;
            let (rot, pos) = best_error(&solutions, &s.truth);
            if solutions.is_empty() {
                none += 1;
            } else if rot > 1e-6 || pos > 1e-6 {
                bad += 1;
                worst = worst.max(rot);
            } else {
                worst = worst.max(rot);
            }
        }
        assert_eq!(
            none, 0,
            "{label}: no solution in {none} of {trials} trials (trials by solution count: {counts:?})"
        );
        assert!(
            worst < 1e-4,
            "{label}: worst rotation error {worst:.2e}° ({bad} above 1e-6)"
        );
    }
}

/// Reliability over random scenes (camera models, sizes, noise, outlier ratios up to 70 %).
#[test]
fn ransac_reliability_over_random_scenes() {
    let cameras = [
        SIMPLE_RADIAL,
        OPENCV,
        FISHEYE,
        "PINHOLE 640 480 500 500 320 240",
    ];
    let mut rng = SplitMix64::new(99);
    let (mut failures, mut errors, trials) = (0, 0, 40);
    let mut worst = (0.0f64, 0.0f64);
    let mut total_ms = 0.0;
    for trial in 0..trials {
        let camera = cameras[rng.below(cameras.len())];
        let n = 50 + rng.below(450);
        let outliers = [0.0, 0.3, 0.5, 0.7][rng.below(4)];
        let noise = 2.0 * rng.next_f64();
        let s = scene(1000 + trial, camera, n, outliers, noise);
        let options = RansacOptions {
            max_error_px: 3.0 * noise.max(0.5) + 1.0,
            seed: trial,
            ..RansacOptions::default()
        };
        let start = std::time::Instant::now();
        let result = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options);
        total_ms += start.elapsed().as_secs_f64() * 1e3;
        match result {
            Ok(e) => {
                let (rot, pos) = (
                    e.pose.rotation_error_deg(&s.truth),
                    e.pose.center_distance(&s.truth),
                );
                if rot > 0.5 || pos > 0.1 {
                    failures += 1;
                    println!("trial {trial}: {camera} n={n} outliers={outliers} noise={noise:.2}: {rot:.3}° {pos:.4}");
                }
                worst = (worst.0.max(rot), worst.1.max(pos));
            }
            Err(err) => {
                errors += 1;
                println!(
                    "trial {trial}: {camera} n={n} outliers={outliers} noise={noise:.2}: {err}"
                );
            }
        }
    }
    assert!(
        failures == 0 && errors == 0,
        "{trials} scenes: {failures} wrong poses, {errors} errors, worst {:.3}° {:.4}, mean {:.2} ms",
        worst.0,
        worst.1,
        total_ms / f64::from(trials as u32)
    );
}

/// Reorders a scene by a noisy quality score that favours inliers, as a descriptor ratio does.
fn sorted_by_quality(s: &Scene, seed: u64, inlier_advantage: f64) -> Scene {
    let mut rng = SplitMix64::new(seed);
    let mut keyed: Vec<(f64, usize)> = (0..s.pixels.len())
        .map(|i| {
            let bonus = if s.is_inlier[i] {
                inlier_advantage
            } else {
                0.0
            };
            (rng.next_f64() - bonus, i)
        })
        .collect();
    keyed.sort_by(|a, b| a.0.total_cmp(&b.0));
    Scene {
        camera: s.camera.clone(),
        truth: s.truth,
        pixels: keyed.iter().map(|&(_, i)| s.pixels[i]).collect(),
        points: keyed.iter().map(|&(_, i)| s.points[i]).collect(),
        is_inlier: keyed.iter().map(|&(_, i)| s.is_inlier[i]).collect(),
    }
}

#[test]
fn progressive_sampling_stops_early_on_sorted_matches() {
    let s = sorted_by_quality(&scene(90, SIMPLE_RADIAL, 1000, 0.9, 1.0), 1, 0.7);
    let options = RansacOptions {
        progressive: true,
        min_iterations: 10,
        ..test_options()
    };
    let estimate = estimate_absolute_pose(&s.pixels, &s.points, &s.camera, &options).unwrap();
    assert!(estimate.pose.rotation_error_deg(&s.truth) < 0.5);
    assert!(estimate.pose.center_distance(&s.truth) < 0.05);
    assert!(estimate.iterations < 500, "{}", estimate.iterations);
    let true_inliers = s.is_inlier.iter().filter(|&&b| b).count();
    assert!(estimate.num_inliers as f64 >= 0.95 * true_inliers as f64);

    // An uninformative order still works (PROSAC degrades to plain sampling of the top).
    let s = scene(91, SIMPLE_RADIAL, 500, 0.7, 1.0);
    let shuffled = sorted_by_quality(&s, 2, 0.0);
    let estimate =
        estimate_absolute_pose(&shuffled.pixels, &shuffled.points, &s.camera, &options).unwrap();
    assert!(estimate.pose.rotation_error_deg(&s.truth) < 0.5);
    assert!(estimate.pose.center_distance(&s.truth) < 0.05);
}

/// All points on one plane (a facade): P3P and LM handle coplanar points, only collinear
/// ones are degenerate.
#[test]
fn planar_scene_is_not_degenerate() {
    let mut rng = SplitMix64::new(7);
    let camera = Camera::parse(SIMPLE_RADIAL).unwrap();
    let truth = random_pose(&mut rng);
    let world_from_cam = truth.inverse();
    // A plane through a point 8 units ahead, tilted 30° from the image plane.
    let normal_cam = Vector3::new(0.0, 0.5, -0.866);
    let anchor_cam = Vector3::new(0.0, 0.0, 8.0);
    let (mut pixels, mut points) = (Vec::new(), Vec::new());
    for i in 0..400 {
        let pixel = Vector2::new(rng.next_f64() * 1024.0, rng.next_f64() * 768.0);
        let xy = camera.unproject(&pixel);
        let ray = Vector3::new(xy.x, xy.y, 1.0);
        let depth = anchor_cam.dot(&normal_cam) / ray.dot(&normal_cam);
        points.push(world_from_cam.transform(&(ray * depth)));
        let observed = if i % 2 == 0 {
            Vector2::new(rng.next_f64() * 1024.0, rng.next_f64() * 768.0)
        } else {
            pixel + Vector2::new(gaussian(&mut rng), gaussian(&mut rng)) * 0.7
        };
        pixels.push(observed);
    }
    let estimate = estimate_absolute_pose(&pixels, &points, &camera, &test_options()).unwrap();
    assert!(estimate.pose.rotation_error_deg(&truth) < 0.5);
    assert!(estimate.pose.center_distance(&truth) < 0.05);
    assert!(estimate.num_inliers >= 190);
}

#[test]
fn a_search_without_a_pose_ends_where_min_inliers_would_have_been_found() {
    // 60 correspondences, all wrong: no pose has `min_inliers` of them. A pose that had would
    // have an inlier ratio of at least 8 / 60, so the search ends after the iterations that
    // find such a pose with `confidence` (SPRT's small chance of rejecting it included),
    // far below `max_iterations`.
    let s = scene(41, "PINHOLE 640 480 500 500 320 240", 60, 1.0, 0.5);
    let options = RansacOptions {
        min_inliers: 8,
        max_iterations: 50_000,
        ..RansacOptions::default()
    };
    let iterations = match run_with(&s, &options) {
        Err(GeometryError::TooFewInliers { iterations, .. })
        | Err(GeometryError::NoModel { iterations }) => iterations,
        other => panic!("a pose from outliers only: {other:?}"),
    };
    // SPRT keeps a good pose with probability at least 0.9 (its decision threshold is at
    // least 10), which scales w³ by that.
    let at_floor = required_iterations(8.0 / 60.0, options.confidence);
    let with_sprt = required_iterations(8.0 / 60.0 * 0.9f64.cbrt(), options.confidence);
    assert!(
        (at_floor..=with_sprt).contains(&iterations),
        "{iterations} iterations, {at_floor}-{with_sprt} at the floor ratio"
    );
    // With enough true matches among them the pose is still found.
    let s = scene(42, "PINHOLE 640 480 500 500 320 240", 60, 0.8, 0.5);
    let found = run_with(&s, &options).expect("12 inliers of 60");
    assert!(found.num_inliers >= 12);
}

#[test]
fn a_prior_that_explains_enough_matches_is_accepted_without_sampling() {
    // 300 correspondences, 30 % outliers: a prior near the truth keeps ~210 inliers.
    let s = scene(83, SIMPLE_RADIAL, 300, 0.3, 1.0);
    let prior = perturb(&s.truth, 0.3, 0.02);
    let options = RansacOptions {
        accept_prior: Some(150),
        ..test_options()
    };
    let accepted =
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&prior), &options)
            .unwrap();
    assert_eq!(accepted.iterations, 0);
    assert!(accepted.num_inliers >= 150, "{}", accepted.num_inliers);
    // Refined, not the prior as it came.
    let (prior_rot, prior_shift) = (
        prior.rotation_error_deg(&s.truth),
        prior.center_distance(&s.truth),
    );
    assert!(accepted.pose.rotation_error_deg(&s.truth) < prior_rot / 3.0);
    assert!(accepted.pose.center_distance(&s.truth) < prior_shift / 3.0);
    // The same prior asked to explain more than the matches hold is one hypothesis among
    // the samples: the same search as without the option.
    let sampled = RansacOptions {
        accept_prior: Some(301),
        ..test_options()
    };
    let searched =
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&prior), &sampled)
            .unwrap();
    let without = estimate_absolute_pose_with_prior(
        &s.pixels,
        &s.points,
        &s.camera,
        Some(&prior),
        &test_options(),
    )
    .unwrap();
    assert!(searched.iterations >= sampled.min_iterations);
    assert_eq!(searched.iterations, without.iterations);
    assert_eq!(searched.pose, without.pose);
    // A wrong prior (far from the truth) explains too few and the samples find the pose.
    let wrong = perturb(&s.truth, 30.0, 2.0);
    let recovered =
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&wrong), &options)
            .unwrap();
    assert!(recovered.iterations > 0);
    assert!(recovered.pose.rotation_error_deg(&s.truth) < 0.5);
    // Asked for 0, it still needs what any pose needs (`min_inliers`): the wrong prior is not
    // accepted, the samples find the pose.
    let zero = RansacOptions {
        accept_prior: Some(0),
        ..test_options()
    };
    let floored =
        estimate_absolute_pose_with_prior(&s.pixels, &s.points, &s.camera, Some(&wrong), &zero)
            .unwrap();
    assert!(floored.iterations > 0);
    assert!(floored.pose.rotation_error_deg(&s.truth) < 0.5);
}
