//! The C ABI's `sfpm_localize` called from Rust as C would: a known pose found on a synthetic
//! map (f16 and product-quantised levels), from several threads at once and with the map's
//! own camera, and its argument errors. The synthetic map and query are shared with
//! `embed_capi_session`.
#![cfg(feature = "capi")]
// Every call here passes valid pointers (or deliberately NULL ones, which the API reports).
#![allow(clippy::undocumented_unsafe_blocks)]

use crate::embed_capi::{last_error, open};
use crate::synthetic_scene;

use sfpmap::ffi::*;
use sfpmap::format::{CameraInfo, Descriptors, MapWriter};
use sfpmap::geometry::{Camera, Pose};
use std::ffi::CString;
use std::path::Path;
use std::ptr::null;
use synthetic_scene::{level_info, points_and_descriptors, truth, unit, Rng};

// A synthetic map with a known query pose (the localizer tests' scene, smaller).

pub(crate) const DIM: usize = 32;
const N: usize = 1500;

/// Writes the map; returns its points, descriptors and path holder.
pub(crate) fn synthetic_map(dir: &Path) -> (Vec<[f64; 3]>, Vec<f32>, CString) {
    synthetic_map_with(dir, false)
}

/// [`synthetic_map`], with its one image seeing every point when `visibility` (what a
/// sequence's tracking path needs: the points of the images near the predicted pose).
pub(crate) fn synthetic_map_with(
    dir: &Path,
    visibility: bool,
) -> (Vec<[f64; 3]>, Vec<f32>, CString) {
    let (points, descriptors) = points_and_descriptors(N, DIM);
    let all: Vec<u32> = (0..N as u32).collect();
    let mut w = MapWriter::default();
    w.add_camera(CameraInfo {
        id: Some(1),
        model: "PINHOLE".into(),
        width: 640,
        height: 480,
        params: vec![500.0, 500.0, 320.0, 240.0],
    });
    w.set_points_world(&points);
    w.set_images(
        &["db0.jpg"],
        &[0],
        &[[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]],
        None,
    )
    .unwrap();
    let levels: Vec<Vec<u32>> = (0..3usize)
        .map(|l| (l * N / 3..(l + 1) * N / 3).map(|p| p as u32).collect())
        .collect();
    for (l, pts) in levels.iter().enumerate() {
        let desc: Vec<f32> = pts
            .iter()
            .flat_map(|&p| descriptors[p as usize * DIM..(p as usize + 1) * DIM].to_vec())
            .collect();
        let info = level_info(l as u16, DIM);
        w.add_level(info, pts, Some(Descriptors::F32(&desc)), true)
            .unwrap();
    }
    if visibility {
        w.set_visibility(&[0, N as u64], &all, None).unwrap();
    }
    let path = dir.join(if visibility {
        "synthetic-visibility.sfpm"
    } else {
        "synthetic.sfpm"
    });
    std::fs::write(&path, w.to_bytes().unwrap()).unwrap();
    (
        points,
        descriptors,
        CString::new(path.to_str().unwrap()).unwrap(),
    )
}

/// Keypoints (x, y interleaved) and descriptors of the map points the query sees.
pub(crate) fn query(points: &[[f64; 3]], descriptors: &[f32]) -> (Vec<f64>, Vec<f32>) {
    query_at(points, descriptors, &truth())
}

/// [`query`] seen from `pose` (`cam_from_world`).
pub(crate) fn query_at(
    points: &[[f64; 3]],
    descriptors: &[f32],
    pose: &Pose,
) -> (Vec<f64>, Vec<f32>) {
    let camera = Camera::parse("PINHOLE 640 480 500 500 320 240").unwrap();
    let mut rng = Rng(7);
    let (mut xy, mut desc) = (Vec::new(), Vec::new());
    for (p, world) in points.iter().enumerate() {
        let pc = pose.transform(&nalgebra::Vector3::from(*world));
        let Some(px) = camera.project(&pc) else {
            continue;
        };
        if !(px.x > 0.0 && px.y > 0.0 && px.x < 640.0 && px.y < 480.0) {
            continue;
        }
        xy.extend([px.x + 0.3 * rng.normal(), px.y + 0.3 * rng.normal()]);
        let mut d: Vec<f32> = (0..DIM)
            .map(|k| descriptors[p * DIM + k] + 0.05 * rng.normal() as f32)
            .collect();
        unit(&mut d);
        desc.extend(d);
    }
    (xy, desc)
}

pub(crate) fn localize(
    map: SfpmMap,
    xy: &[f64],
    desc: &[f32],
    options: Option<&SfpmLocalizeOptions>,
) -> (SfpmStatus, SfpmLocalization) {
    let model = CString::new("PINHOLE").unwrap();
    let params = [500.0, 500.0, 320.0, 240.0];
    let camera = SfpmCamera {
        model: model.as_ptr(),
        width: 640,
        height: 480,
        params: params.as_ptr(),
        n_params: params.len(),
    };
    let mut out = SfpmLocalization::default();
    let status = unsafe {
        sfpm_localize(
            map,
            xy.as_ptr(),
            desc.as_ptr(),
            xy.len() / 2,
            DIM,
            &camera,
            options.map_or(null(), |o| o as *const _),
            &mut out,
        )
    };
    (status, out)
}

pub(crate) fn assert_near_truth(out: &SfpmLocalization) {
    assert_near(out, &truth());
}

pub(crate) fn assert_near(out: &SfpmLocalization, t: &Pose) {
    let p = out.cam_from_world;
    let pose = Pose::from_colmap(p[0], p[1], p[2], p[3], p[4], p[5], p[6]).unwrap();
    assert!(pose.rotation_error_deg(t) < 0.5, "{p:?}");
    assert!(pose.center_distance(t) < 0.05, "{p:?}");
}

/// (1.1) `sfpm_localize` on the synthetic map with every level product-quantised.
#[test]
fn localizes_a_known_pose_on_a_pq_map() {
    use sfpmap::build::pq::{quantise_all, PqLevelSummary};
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let bytes = std::fs::read(path.to_str().unwrap()).unwrap();
    let source = sfpmap::format::Map::from_bytes(&bytes).unwrap();
    let (mut writer, _) = sfpmap::format::slice(
        &source,
        &sfpmap::format::SliceOptions {
            levels: vec![0, 1, 2],
            ..Default::default()
        },
    )
    .unwrap();
    let summary: Vec<PqLevelSummary> = quantise_all(&mut writer, 8).unwrap();
    assert_eq!(summary.len(), 3);
    let pq_path = tmp.path().join("pq.sfpm");
    std::fs::write(&pq_path, writer.to_bytes().unwrap()).unwrap();
    let map = open(&CString::new(pq_path.to_str().unwrap()).unwrap());
    let (xy, desc) = query(&points, &descriptors);
    let (status, out) = localize(map, &xy, &desc, None);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_near_truth(&out);
    sfpm_close(map);
}

#[test]
fn localizes_a_known_pose_from_several_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let (xy, desc) = query(&points, &descriptors);
    assert!(xy.len() / 2 > 100);
    let map = open(&path);

    let (status, out) = localize(map, &xy, &desc, None);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert!(out.inliers > 50, "{} inliers", out.inliers);
    assert_near_truth(&out);

    // Level 2 only, short block only.
    let level = [2u16];
    let options = SfpmLocalizeOptions {
        levels: level.as_ptr(),
        n_levels: 1,
        short_only: 1,
    };
    let (status, out) = localize(map, &xy, &desc, Some(&options));
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_near_truth(&out);

    // One handle, four threads, the cached localizer shared.
    std::thread::scope(|s| {
        for _ in 0..4 {
            s.spawn(|| {
                let (status, out) = localize(map, &xy, &desc, None);
                assert_eq!(status, SfpmStatus::SFPM_OK);
                assert_near_truth(&out);
            });
        }
    });

    // Too few features: runs, no pose, a reason.
    let (status, out) = localize(map, &xy[..10], &desc[..5 * DIM], None);
    assert_eq!(status, SfpmStatus::SFPM_NOT_LOCALIZED);
    assert_eq!(out.cam_from_world, [0.0; 7]);
    assert!(!last_error().is_empty());

    // No features at all (NULL arrays are allowed for n = 0): an answer, not a crash.
    let (status, _) = localize(map, &[], &[], None);
    assert!(
        [
            SfpmStatus::SFPM_NOT_LOCALIZED,
            SfpmStatus::SFPM_ERR_LOCALIZE
        ]
        .contains(&status),
        "{status:?}"
    );

    // NaN keypoint, wrong descriptor dimension, unknown level, bad camera parameters.
    let mut bad = xy.clone();
    bad[3] = f64::NAN;
    assert_eq!(
        localize(map, &bad, &desc, None).0,
        SfpmStatus::SFPM_ERR_ARGUMENT
    );
    let short_desc: Vec<f32> = desc.chunks(DIM).flat_map(|d| d[..16].to_vec()).collect();
    let model = CString::new("PINHOLE").unwrap();
    let params = [500.0, 500.0, 320.0];
    let camera = SfpmCamera {
        model: model.as_ptr(),
        width: 640,
        height: 480,
        params: params.as_ptr(),
        n_params: params.len(),
    };
    let mut out = SfpmLocalization::default();
    unsafe {
        assert_eq!(
            sfpm_localize(
                map,
                xy.as_ptr(),
                short_desc.as_ptr(),
                xy.len() / 2,
                16,
                &camera,
                null(),
                &mut out
            ),
            SfpmStatus::SFPM_ERR_ARGUMENT,
            "three PINHOLE parameters"
        );
    }
    assert!(last_error().contains("camera"), "{}", last_error());
    let params4 = [500.0, 500.0, 320.0, 240.0];
    let camera = SfpmCamera {
        params: params4.as_ptr(),
        n_params: 4,
        ..camera
    };
    unsafe {
        assert_eq!(
            sfpm_localize(
                map,
                xy.as_ptr(),
                short_desc.as_ptr(),
                xy.len() / 2,
                16,
                &camera,
                null(),
                &mut out
            ),
            SfpmStatus::SFPM_ERR_LOCALIZE,
            "16-dimensional descriptors against a 32-dimensional map"
        );
    }
    let level = [5u16];
    let options = SfpmLocalizeOptions {
        levels: level.as_ptr(),
        n_levels: 1,
        short_only: 0,
    };
    assert_eq!(
        localize(map, &xy, &desc, Some(&options)).0,
        SfpmStatus::SFPM_ERR_NO_SUCH_LEVEL
    );

    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
    assert_eq!(
        localize(map, &xy, &desc, None).0,
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
}

/// `sfpm_camera`'s width and height (`uint64_t`) go straight into an `SfpmCamera`; a size the
/// localizer's 32 bits cannot hold is an argument error, never silently truncated.
#[test]
fn map_camera_localizes_and_oversized_cameras_are_rejected() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let (xy, desc) = query(&points, &descriptors);
    let map = open(&path);
    let mut model = [0 as std::ffi::c_char; 32];
    let (mut width, mut height, mut n_params) = (0u64, 0u64, 0usize);
    let mut params = [0f64; 8];
    let status = unsafe {
        sfpm_camera(
            map,
            0,
            model.as_mut_ptr(),
            model.len(),
            &mut width,
            &mut height,
            params.as_mut_ptr(),
            params.len(),
            &mut n_params,
        )
    };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_eq!((width, height, n_params), (640, 480, 4));
    let camera = SfpmCamera {
        model: model.as_ptr(),
        width,
        height,
        params: params.as_ptr(),
        n_params,
    };
    let run = |camera: &SfpmCamera| {
        let mut out = SfpmLocalization::default();
        let (n, p) = (xy.len() / 2, null());
        let status =
            unsafe { sfpm_localize(map, xy.as_ptr(), desc.as_ptr(), n, DIM, camera, p, &mut out) };
        (status, out)
    };
    let (status, out) = run(&camera);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_near_truth(&out);
    for (width, height, what) in [
        (1u64 << 32, 480, "camera.width"),
        (640, u64::MAX, "camera.height"),
    ] {
        let (status, _) = run(&SfpmCamera {
            width,
            height,
            ..camera
        });
        assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{what}");
        assert!(last_error().contains(what), "{}", last_error());
    }
    let (status, _) = run(&SfpmCamera {
        model: null(),
        ..camera
    });
    assert_eq!(status, SfpmStatus::SFPM_ERR_NULL);
    assert!(
        last_error().contains("camera.model is NULL"),
        "{}",
        last_error()
    );
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}
