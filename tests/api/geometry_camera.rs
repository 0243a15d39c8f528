//! Camera models: parsing, projection, iterative undistortion.
#![cfg(feature = "localize")]

use crate::shared_data;

use nalgebra::{Vector2, Vector3};
use proptest::prelude::*;
use sfpmap::geometry::{Camera, CameraModel, GeometryError};
use sfpmap::io::poses::read_poses;
use sfpmap::io::queries::read_query_list;

/// One camera per model, with distortion strong enough to matter at the image corners.
fn cameras() -> Vec<Camera> {
    [
        "SIMPLE_PINHOLE 1024 768 800 512 384",
        "PINHOLE 1024 768 800 820 510.5 380.2",
        "SIMPLE_RADIAL 1024 768 800 512 384 -0.08",
        "RADIAL 1024 768 800 512 384 -0.1 0.02",
        "OPENCV 1024 768 800 820 510.5 380.2 -0.12 0.03 0.001 -0.0015",
        "OPENCV_FISHEYE 1024 768 400 410 512 384 0.05 -0.01 0.002 -0.0005",
        "FULL_OPENCV 1024 768 800 820 510.5 380.2 -0.12 0.03 0.001 -0.0015 0.01 0.02 0.005 0.001",
    ]
    .iter()
    .map(|s| Camera::parse(s).unwrap())
    .collect()
}

#[test]
fn parses_every_model_with_colmap_parameter_order() {
    let cameras = cameras();
    let models: Vec<CameraModel> = cameras.iter().map(Camera::model).collect();
    assert_eq!(models, sfpmap::geometry::SUPPORTED);
    for camera in &cameras {
        assert_eq!(camera.params().len(), camera.model().num_params());
        assert_eq!((camera.width(), camera.height()), (1024, 768));
        assert_eq!(
            CameraModel::from_id(camera.model().id()),
            Some(camera.model())
        );
    }
    // Principal point is taken as given, no half-pixel shift.
    assert_eq!(cameras[1].principal_point(), Vector2::new(510.5, 380.2));
    let on_axis = cameras[1].project(&Vector3::new(0.0, 0.0, 3.0)).unwrap();
    assert_eq!(on_axis, Vector2::new(510.5, 380.2));
    // PINHOLE is fx, fy, cx, cy.
    let p = cameras[1].project(&Vector3::new(1.0, 1.0, 10.0)).unwrap();
    assert!((p - Vector2::new(510.5 + 80.0, 380.2 + 82.0)).norm() < 1e-12);
}

#[test]
fn distortion_formulas_match_colmap() {
    // SIMPLE_RADIAL: u·(1 + k·r²), r² = u² + v².
    let camera = Camera::parse("SIMPLE_RADIAL 100 100 100 50 50 0.1").unwrap();
    let p = camera.project(&Vector3::new(0.3, 0.4, 1.0)).unwrap();
    let factor = 1.0 + 0.1 * 0.25;
    assert!(
        (p - Vector2::new(50.0 + 100.0 * 0.3 * factor, 50.0 + 100.0 * 0.4 * factor)).norm() < 1e-12
    );
    // OPENCV: radial k1 r² + k2 r⁴, tangential 2·p1·uv + p2·(r² + 2u²), 2·p2·uv + p1·(r² + 2v²).
    let camera = Camera::parse("OPENCV 100 100 100 110 50 60 0.1 0.01 0.002 0.003").unwrap();
    let (u, v) = (0.3, -0.2);
    let r2: f64 = u * u + v * v;
    let radial = 0.1 * r2 + 0.01 * r2 * r2;
    let du = u * radial + 2.0 * 0.002 * u * v + 0.003 * (r2 + 2.0 * u * u);
    let dv = v * radial + 2.0 * 0.003 * u * v + 0.002 * (r2 + 2.0 * v * v);
    let p = camera
        .project(&Vector3::new(u * 2.0, v * 2.0, 2.0))
        .unwrap();
    assert!((p - Vector2::new(50.0 + 100.0 * (u + du), 60.0 + 110.0 * (v + dv))).norm() < 1e-12);
    // FULL_OPENCV: rational radial factor, same tangential terms.
    let camera = Camera::parse(
        "FULL_OPENCV 100 100 100 110 50 60 0.1 0.01 0.002 0.003 0.001 0.05 0.02 0.004",
    )
    .unwrap();
    let (r4, r6) = (r2 * r2, r2 * r2 * r2);
    let radial =
        (1.0 + 0.1 * r2 + 0.01 * r4 + 0.001 * r6) / (1.0 + 0.05 * r2 + 0.02 * r4 + 0.004 * r6);
    let xd = u * radial + 2.0 * 0.002 * u * v + 0.003 * (r2 + 2.0 * u * u);
    let yd = v * radial + 2.0 * 0.003 * u * v + 0.002 * (r2 + 2.0 * v * v);
    let p = camera.project(&Vector3::new(u, v, 1.0)).unwrap();
    assert!((p - Vector2::new(50.0 + 100.0 * xd, 60.0 + 110.0 * yd)).norm() < 1e-12);
    // OPENCV_FISHEYE: θ = atan(r), θ_d = θ·(1 + k1θ² + k2θ⁴ + k3θ⁶ + k4θ⁸), scaled by θ_d / r;
    // with zero coefficients it is the equidistant projection, not a pinhole.
    let camera =
        Camera::parse("OPENCV_FISHEYE 100 100 100 110 50 60 0.1 0.01 0.001 0.0001").unwrap();
    let r = r2.sqrt();
    let theta = r.atan();
    let t2 = theta * theta;
    let theta_d = theta
        * (1.0 + 0.1 * t2 + 0.01 * t2 * t2 + 0.001 * t2 * t2 * t2 + 0.0001 * t2 * t2 * t2 * t2);
    let p = camera.project(&Vector3::new(u, v, 1.0)).unwrap();
    let expected = Vector2::new(
        50.0 + 100.0 * u * theta_d / r,
        60.0 + 110.0 * v * theta_d / r,
    );
    assert!((p - expected).norm() < 1e-12);
    let equidistant = Camera::parse("OPENCV_FISHEYE 100 100 100 100 50 50 0 0 0 0").unwrap();
    let p = equidistant.project(&Vector3::new(1.0, 0.0, 1.0)).unwrap();
    assert!((p.x - (50.0 + 100.0 * std::f64::consts::FRAC_PI_4)).abs() < 1e-12);
}

#[test]
fn unproject_inverts_project_across_the_image() {
    for camera in cameras() {
        for row in 0..=16 {
            for col in 0..=16 {
                let pixel = Vector2::new(
                    f64::from(camera.width()) * f64::from(col) / 16.0,
                    f64::from(camera.height()) * f64::from(row) / 16.0,
                );
                let xy = camera.unproject(&pixel);
                let back = camera.project(&Vector3::new(xy.x, xy.y, 1.0)).unwrap();
                assert!(
                    (back - pixel).norm() < 1e-9,
                    "{} at {pixel}: {back}",
                    camera.model()
                );
                let bearing = camera.bearing(&pixel);
                assert!((bearing.norm() - 1.0).abs() < 1e-12);
                let back = camera.project(&(bearing * 7.5)).unwrap();
                assert!((back - pixel).norm() < 1e-9);
            }
        }
    }
}

#[test]
fn points_behind_the_camera_do_not_project() {
    for camera in cameras() {
        assert_eq!(camera.project(&Vector3::new(0.1, 0.1, -1.0)), None);
        assert_eq!(camera.project(&Vector3::new(0.1, 0.1, 0.0)), None);
        assert_eq!(camera.project(&Vector3::new(f64::NAN, 0.1, 1.0)), None);
    }
}

#[test]
fn parse_errors_are_specific() {
    // A COLMAP model the localizer does not project, by name or built directly; a name that
    // is no COLMAP model.
    let e = Camera::parse("FISHEYE 10 10 1 2 3 4").unwrap_err();
    assert_eq!(
        e,
        GeometryError::UnsupportedCameraModel {
            model: CameraModel::Fisheye
        }
    );
    assert!(e.to_string().contains("FULL_OPENCV"), "{e}");
    assert_eq!(
        Camera::new(CameraModel::Eucm, 10, 10, vec![1.0; 6]).unwrap_err(),
        GeometryError::UnsupportedCameraModel {
            model: CameraModel::Eucm
        }
    );
    assert!(matches!(
        Camera::parse("FISHEYES 10 10 1 2 3"),
        Err(GeometryError::UnknownCameraModel { name }) if name == "FISHEYES"
    ));
    // Names are matched in any case here (hand-written query lists).
    assert_eq!(
        Camera::parse("simple_pinhole 10 10 5 5 5").unwrap().model(),
        CameraModel::SimplePinhole
    );
    assert_eq!(
        Camera::parse("SIMPLE_RADIAL 1024 768 800 512 384"),
        Err(GeometryError::WrongParamCount {
            model: CameraModel::SimpleRadial,
            expected: 4,
            found: 3,
        })
    );
    assert!(matches!(
        Camera::parse(""),
        Err(GeometryError::ParseCamera { .. })
    ));
    assert!(matches!(
        Camera::parse("PINHOLE 10"),
        Err(GeometryError::ParseCamera { .. })
    ));
    assert!(matches!(
        Camera::parse("PINHOLE 10 10 1 1 x 5"),
        Err(GeometryError::ParseCamera { .. })
    ));
    assert!(matches!(
        Camera::parse("PINHOLE 10 10 -1 1 5 5"),
        Err(GeometryError::InvalidCamera { .. })
    ));
    assert!(matches!(
        Camera::parse("PINHOLE 0 10 1 1 5 5"),
        Err(GeometryError::InvalidCamera { .. })
    ));
    assert!(matches!(
        Camera::parse("PINHOLE 10 10 1 NaN 5 5"),
        Err(GeometryError::InvalidCamera { .. })
    ));
    let message = Camera::parse("RADIAL 10 10 1 2 3").unwrap_err().to_string();
    assert_eq!(
        message,
        "camera model RADIAL takes 5 parameters (f, cx, cy, k1, k2), found 3"
    );
}

#[test]
fn rescaling_follows_colmap() {
    let camera = Camera::parse("SIMPLE_RADIAL 1600 1200 1469.2 800 600 -0.0353").unwrap();
    let half = camera.rescaled(800, 600).unwrap();
    assert_eq!(half.params(), &[734.6, 400.0, 300.0, -0.0353]);
    // Anisotropic resize of a single-focal model: focal by the mean factor, as COLMAP.
    let squashed = camera.rescaled(800, 1200).unwrap();
    assert_eq!(squashed.params(), &[1469.2 * 0.75, 400.0, 600.0, -0.0353]);
    let camera = Camera::parse("PINHOLE 1000 500 900 950 500 250").unwrap();
    let resized = camera.rescaled(500, 1000).unwrap();
    assert_eq!(resized.params(), &[450.0, 1900.0, 250.0, 500.0]);
    assert_eq!((resized.width(), resized.height()), (500, 1000));
    // The same ray lands on the scaled pixel (continuous coordinates scale exactly).
    let p = Vector3::new(0.2, -0.1, 1.5);
    let a = camera.project(&p).unwrap();
    let b = resized.project(&p).unwrap();
    assert!((Vector2::new(a.x * 0.5, a.y * 2.0) - b).norm() < 1e-9);
    assert!(camera.rescaled(0, 10).is_err());
}

#[test]
fn parses_hloc_query_lines() {
    let (name, camera) = Camera::parse_query_line(
        "query/night/IMG_001.jpg SIMPLE_RADIAL 1600 1200 1469.2 800 600 -0.0353\n",
    )
    .unwrap();
    assert_eq!(name, "query/night/IMG_001.jpg");
    assert_eq!(camera.model(), CameraModel::SimpleRadial);
    assert_eq!(camera.params(), &[1469.2, 800.0, 600.0, -0.0353]);
    assert!(Camera::parse_query_line("lonely.jpg").is_err());
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn project_unproject_round_trip(
        model in 0usize..7,
        x in -0.6f64..0.6,
        y in -0.45f64..0.45,
        depth in 0.1f64..100.0,
    ) {
        let camera = &cameras()[model];
        let p_cam = Vector3::new(x * depth, y * depth, depth);
        let pixel = camera.project(&p_cam).unwrap();
        let xy = camera.unproject(&pixel);
        prop_assert!((xy - Vector2::new(x, y)).norm() < 1e-10, "{xy} vs ({x}, {y})");
        let bearing = camera.bearing(&pixel);
        prop_assert!((bearing - p_cam.normalize()).norm() < 1e-10);
    }
}

/// The shared scenes' query lists and ground truth parse with the localizer's readers: every
/// query has a usable camera and a ground-truth pose.
#[test]
fn parses_shared_scene_files() {
    let Some(scenes) = shared_data::shared_data("scenes") else {
        return;
    };
    let mut checked = 0;
    for entry in std::fs::read_dir(&scenes).unwrap() {
        let dir = entry.unwrap().path();
        let (queries_path, poses_path) = (dir.join("queries.txt"), dir.join("gt_poses.txt"));
        if !queries_path.exists() && !poses_path.exists() {
            continue;
        }
        let queries = read_query_list(&queries_path, None).unwrap_or_else(|e| panic!("{e}"));
        let poses = read_poses(&poses_path).unwrap_or_else(|e| panic!("{e}"));
        assert!(!queries.is_empty(), "{}", queries_path.display());
        assert!(!poses.is_empty(), "{}", poses_path.display());

        for query in &queries {
            let (name, camera) = (&query.name, &query.camera);
            assert!(!name.is_empty());
            assert_eq!(camera.params().len(), camera.model().num_params(), "{name}");
            assert!(camera.params().iter().all(|p| p.is_finite()), "{name}");
            let (fx, fy) = camera.focal_lengths();
            assert!(fx > 0.0 && fy > 0.0, "{name}: focal lengths {fx}, {fy}");
            let centre = camera.principal_point();
            assert!(
                camera.contains(&centre),
                "{name}: principal point {centre:?}"
            );
            // The principal point looks straight ahead, and the image corners survive an
            // undistort/distort round trip (the distortion does not fold inside the image).
            assert!(
                (camera.bearing(&centre) - Vector3::z()).norm() < 1e-12,
                "{name}"
            );
            let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
            for corner in [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)] {
                let pixel = Vector2::new(corner.0, corner.1);
                let xy = camera.unproject(&pixel);
                let back = camera.project(&Vector3::new(xy.x, xy.y, 1.0)).unwrap();
                assert!(
                    (back - pixel).norm() < 1e-6,
                    "{name}: corner {corner:?} -> {back:?}"
                );
            }
        }

        let mut gt = std::collections::HashMap::new();
        for (name, pose) in &poses {
            assert!(pose.is_finite(), "{name}");
            let norm = pose.rotation.quaternion().norm();
            assert!((norm - 1.0).abs() < 1e-12, "{name}: |q| = {norm}");
            assert!(
                gt.insert(name.as_str(), pose).is_none(),
                "{name}: listed twice"
            );
        }
        let missing: Vec<&str> = queries
            .iter()
            .map(|q| q.name.as_str())
            .filter(|name| !gt.contains_key(name))
            .collect();
        assert!(
            missing.is_empty(),
            "{}: queries without a ground-truth pose: {missing:?}",
            dir.display()
        );
        checked += 1;
    }
    assert!(
        checked > 0,
        "no scene with queries.txt and gt_poses.txt in {}",
        scenes.display()
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Undistortion far outside the image (where polynomial models fold back) must not panic
    /// or produce NaN for finite pixels; it may be inexact there, as in COLMAP.
    #[test]
    fn unproject_is_finite_everywhere(
        model in 0usize..7,
        x in -1e5f64..1e5,
        y in -1e5f64..1e5,
    ) {
        let camera = &cameras()[model];
        let xy = camera.unproject(&Vector2::new(x, y));
        prop_assert!(xy.x.is_finite() && xy.y.is_finite(), "{} at ({x}, {y}): {xy}", camera.model());
        let bearing = camera.bearing(&Vector2::new(x, y));
        prop_assert!(bearing.iter().all(|c| c.is_finite()));
    }
}
