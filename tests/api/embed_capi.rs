//! The C ABI called from Rust as C would: zero-copy views against the spec vectors (raw and
//! zstd sections), argument errors, a localization through `sfpm_localize` on a synthetic
//! map with a known pose, from several threads at once, and sessions (`sfpm_session_*`):
//! the same pose, options checked, a moving sequence tracked, handles that outlive the map.
#![cfg(feature = "capi")]
// Every call here passes valid pointers (or deliberately NULL ones, which the API reports).
#![allow(clippy::undocumented_unsafe_blocks)]

use crate::synthetic_scene;

use serde_json::Value;
use sfpmap::ffi::*;
use sfpmap::format::{CameraInfo, Descriptors, MapWriter};
use sfpmap::geometry::{Camera, Pose};
use std::ffi::{CStr, CString};
use std::path::Path;
use std::ptr::{null, null_mut};
use synthetic_scene::{level_info, points_and_descriptors, truth, unit, Rng};

fn vector(name: &str) -> (CString, Value) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("spec/vectors/valid");
    let json = std::fs::read_to_string(root.join(format!("{name}.json"))).unwrap();
    (
        CString::new(root.join(format!("{name}.sfpm")).to_str().unwrap()).unwrap(),
        serde_json::from_str(&json).unwrap(),
    )
}

fn open(path: &CStr) -> SfpmMap {
    let mut map = 0;
    let status = unsafe { sfpm_open(path.as_ptr(), &mut map) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    map
}

fn last_error() -> String {
    unsafe { CStr::from_ptr(sfpm_last_error()) }
        .to_string_lossy()
        .into_owned()
}

fn f16(bits: u16) -> f64 {
    f64::from(sfpmap::format::f16::from_bits(bits))
}

/// Short and rest blocks of every level equal the vector's JSON, for raw and zstd maps; the
/// pointers stay the same on a second call (the decoded buffer is owned by the handle).
#[test]
fn descriptor_blocks_match_the_vectors_raw_and_zstd() {
    for name in ["levels", "zstd", "mixed_dtypes"] {
        let (path, json) = vector(name);
        let map = open(&path);
        for level in json["content"]["levels"].as_array().unwrap() {
            let id = level["level"].as_u64().unwrap() as u16;
            for (block, key) in [(0, "short"), (1, "rest")] {
                let Some(rows) = level[key].as_array() else {
                    continue;
                };
                let expected: Vec<f64> = rows
                    .iter()
                    .flat_map(|r| r.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()))
                    .collect();
                let (mut data, mut len) = (null(), 0usize);
                let call = |data: &mut *const u16, len: &mut usize| unsafe {
                    if block == 0 {
                        sfpm_level_desc_short(map, id, data, len)
                    } else {
                        sfpm_level_desc_rest(map, id, data, len)
                    }
                };
                assert_eq!(
                    call(&mut data, &mut len),
                    SfpmStatus::SFPM_OK,
                    "{name} {id} {key}"
                );
                assert_eq!(len, expected.len(), "{name} level {id} {key}");
                let got = unsafe { std::slice::from_raw_parts(data, len) };
                for (g, e) in got.iter().zip(&expected) {
                    assert_eq!(f16(*g), *e, "{name} level {id} {key}");
                }
                let (mut again, mut len2) = (null(), 0usize);
                call(&mut again, &mut len2);
                assert_eq!((again, len2), (data, len), "{name}: pointer moved");
            }
        }
        let (mut positions, mut n, mut origin) = (null(), 0usize, [0f64; 3]);
        assert_eq!(
            unsafe { sfpm_point_positions(map, &mut positions, &mut n, origin.as_mut_ptr()) },
            SfpmStatus::SFPM_OK
        );
        let expected = json["content"]["positions"].as_array().unwrap();
        assert_eq!(n, expected.len());
        let got = unsafe { std::slice::from_raw_parts(positions, 3 * n) };
        for (p, e) in expected.iter().enumerate() {
            for k in 0..3 {
                assert_eq!(f64::from(got[3 * p + k]), e[k].as_f64().unwrap());
            }
        }
        assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
    }
}

#[test]
fn images_visibility_and_argument_errors() {
    let (path, json) = vector("levels");
    let map = open(&path);
    let images = json["content"]["images"].as_array().unwrap();
    unsafe {
        let mut n = 0usize;
        assert_eq!(
            sfpm_level_ids(map, null_mut(), 0, &mut n),
            SfpmStatus::SFPM_OK
        );
        assert_eq!(n, 3);
        let mut one = [0u16; 1];
        assert_eq!(
            sfpm_level_ids(map, one.as_mut_ptr(), 1, &mut n),
            SfpmStatus::SFPM_OK
        );
        assert_eq!((one[0], n), (0, 3), "truncated to capacity, full count");
        assert_eq!(
            sfpm_level_ids(map, null_mut(), 2, &mut n),
            SfpmStatus::SFPM_ERR_NULL
        );
        // A NULL among several out pointers: nothing is written.
        let mut data = null();
        assert_eq!(
            sfpm_level_desc_short(map, 0, &mut data, null_mut()),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert!(data.is_null());
        assert!(last_error().contains("len is NULL"), "{}", last_error());

        assert_eq!(sfpm_image_count(map, &mut n), SfpmStatus::SFPM_OK);
        assert_eq!(n, images.len());
        let mut buf = [0 as std::ffi::c_char; 4];
        let mut needed = 0usize;
        assert_eq!(
            sfpm_image_name(map, 0, buf.as_mut_ptr(), buf.len(), &mut needed),
            SfpmStatus::SFPM_OK
        );
        assert_eq!(CStr::from_ptr(buf.as_ptr()).to_str().unwrap(), "img");
        assert_eq!(needed, images[0]["name"].as_str().unwrap().len());
        let mut pose = [0f64; 7];
        let mut camera = 9u32;
        assert_eq!(
            sfpm_image_pose(map, 2, pose.as_mut_ptr(), &mut camera),
            SfpmStatus::SFPM_OK
        );
        assert_eq!(pose[4], images[2]["cam_from_world"][4].as_f64().unwrap());
        assert_eq!(camera, 0);
        assert_eq!(
            sfpm_image_pose(map, 3, pose.as_mut_ptr(), null_mut()),
            SfpmStatus::SFPM_ERR_ARGUMENT
        );
        assert!(last_error().contains("out of range"), "{}", last_error());

        let (mut offsets, mut n_offsets, mut points, mut n_points) = (null(), 0, null(), 0);
        assert_eq!(
            sfpm_visibility(
                map,
                &mut offsets,
                &mut n_offsets,
                &mut points,
                &mut n_points
            ),
            SfpmStatus::SFPM_OK
        );
        let vis = &json["content"]["visibility"];
        let offsets = std::slice::from_raw_parts(offsets, n_offsets);
        let points = std::slice::from_raw_parts(points, n_points);
        let expected: Vec<u64> = vis["offsets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap())
            .collect();
        assert_eq!(offsets, expected.as_slice());
        assert_eq!(points.len(), vis["points"].as_array().unwrap().len());

        assert_eq!(sfpm_camera_count(map, &mut n), SfpmStatus::SFPM_OK);
        assert_eq!(n, 1);
        let mut model = [0 as std::ffi::c_char; 7];
        let (mut w, mut h, mut n_params) = (0u64, 0u64, 0usize);
        let mut params = [0f64; 1];
        assert_eq!(
            sfpm_camera(
                map,
                0,
                model.as_mut_ptr(),
                model.len(),
                &mut w,
                &mut h,
                params.as_mut_ptr(),
                1,
                &mut n_params
            ),
            SfpmStatus::SFPM_OK
        );
        let map_camera = {
            let m = sfpmap::format::Map::open(path.to_str().unwrap()).unwrap();
            m.metadata().cameras[0].clone()
        };
        let name = CStr::from_ptr(model.as_ptr()).to_str().unwrap();
        assert_eq!(name, &map_camera.model[..map_camera.model.len().min(6)]);
        assert_eq!((w, h), (map_camera.width, map_camera.height));
        assert_eq!(
            (params[0], n_params),
            (map_camera.params[0], map_camera.params.len())
        );
        assert_eq!(
            sfpm_camera(
                map,
                1,
                null_mut(),
                0,
                null_mut(),
                null_mut(),
                null_mut(),
                0,
                null_mut()
            ),
            SfpmStatus::SFPM_ERR_ARGUMENT
        );
        assert_eq!(
            sfpm_camera(
                map,
                0,
                null_mut(),
                8,
                null_mut(),
                null_mut(),
                null_mut(),
                0,
                null_mut()
            ),
            SfpmStatus::SFPM_ERR_NULL
        );

        let mut info = SfpmLevelInfo::default();
        assert_eq!(
            sfpm_level_info(map, 7, &mut info),
            SfpmStatus::SFPM_ERR_NO_SUCH_LEVEL
        );
        assert!(last_error().contains("no level 7"), "{}", last_error());
    }
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);

    // A map without images or rest blocks says so.
    let (path, _) = vector("minimal");
    let map = open(&path);
    unsafe {
        let mut n = 1usize;
        assert_eq!(sfpm_image_count(map, &mut n), SfpmStatus::SFPM_OK);
        assert_eq!(n, 0);
        let mut pose = [0f64; 7];
        assert_eq!(
            sfpm_image_pose(map, 0, pose.as_mut_ptr(), null_mut()),
            SfpmStatus::SFPM_ERR_MISSING
        );
    }
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);

    let missing = CString::new("/nonexistent/map.sfpm").unwrap();
    let mut map = 0;
    assert_eq!(
        unsafe { sfpm_open(missing.as_ptr(), &mut map) },
        SfpmStatus::SFPM_ERR_IO
    );
    assert!(last_error().contains("/nonexistent/map.sfpm"));
    // A folder cannot be read as a file: an I/O error too, saying what it is.
    let folder = tempfile::tempdir().unwrap();
    let folder_path = CString::new(folder.path().to_str().unwrap()).unwrap();
    assert_eq!(
        unsafe { sfpm_open(folder_path.as_ptr(), &mut map) },
        SfpmStatus::SFPM_ERR_IO
    );
    assert!(last_error().contains("is a folder"), "{}", last_error());
    let garbage = tempfile::NamedTempFile::new().unwrap();
    std::fs::write(garbage.path(), b"not a map at all").unwrap();
    let garbage = CString::new(garbage.path().to_str().unwrap()).unwrap();
    assert_eq!(
        unsafe { sfpm_open(garbage.as_ptr(), &mut map) },
        SfpmStatus::SFPM_ERR_FORMAT
    );
}

// A synthetic map with a known query pose (the localizer tests' scene, smaller).

const DIM: usize = 32;
const N: usize = 1500;

/// Writes the map; returns its points, descriptors and path holder.
fn synthetic_map(dir: &Path) -> (Vec<[f64; 3]>, Vec<f32>, CString) {
    synthetic_map_with(dir, false)
}

/// [`synthetic_map`], with its one image seeing every point when `visibility` (what a
/// sequence's tracking path needs: the points of the images near the predicted pose).
fn synthetic_map_with(dir: &Path, visibility: bool) -> (Vec<[f64; 3]>, Vec<f32>, CString) {
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
fn query(points: &[[f64; 3]], descriptors: &[f32]) -> (Vec<f64>, Vec<f32>) {
    query_at(points, descriptors, &truth())
}

/// [`query`] seen from `pose` (`cam_from_world`).
fn query_at(points: &[[f64; 3]], descriptors: &[f32], pose: &Pose) -> (Vec<f64>, Vec<f32>) {
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

fn localize(
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

fn assert_near_truth(out: &SfpmLocalization) {
    assert_near(out, &truth());
}

fn assert_near(out: &SfpmLocalization, t: &Pose) {
    let p = out.cam_from_world;
    let pose = Pose::from_colmap(p[0], p[1], p[2], p[3], p[4], p[5], p[6]).unwrap();
    assert!(pose.rotation_error_deg(t) < 0.5, "{p:?}");
    assert!(pose.center_distance(t) < 0.05, "{p:?}");
}

/// (1.1) A product-quantised level: codes and codebook equal the `pq` vector's, zero-copy
/// (the same pointers again), `SFPM_ERR_MISSING` for an f16 level.
#[test]
fn pq_codes_and_codebook_match_the_vector() {
    let (path, json) = vector("pq");
    let map = open(&path);
    let level = &json["content"]["levels"][1]["pq"];
    let mut out = std::mem::MaybeUninit::<SfpmLevelPq>::zeroed();
    assert_eq!(
        unsafe { sfpm_level_pq(map, 1, out.as_mut_ptr()) },
        SfpmStatus::SFPM_OK
    );
    let pq = unsafe { out.assume_init() };
    assert_eq!((pq.subspaces, pq.centroids, pq.sub_dims), (2, 3, 2));
    let codes = unsafe { std::slice::from_raw_parts(pq.codes, pq.codes_len) };
    let want: Vec<u8> = level["codes"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_u64().unwrap() as u8)
        })
        .collect();
    assert_eq!(codes, want);
    let codebook = unsafe { std::slice::from_raw_parts(pq.codebook, pq.codebook_len) };
    let want: Vec<f32> = level["codebook"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
        })
        .collect();
    assert_eq!(codebook, want);
    let mut again = std::mem::MaybeUninit::<SfpmLevelPq>::zeroed();
    unsafe { sfpm_level_pq(map, 1, again.as_mut_ptr()) };
    let again = unsafe { again.assume_init() };
    assert_eq!((again.codes, again.codebook), (pq.codes, pq.codebook));
    // No order in this vector: the identity, NULL and 0.
    assert_eq!((pq.order, pq.order_len), (std::ptr::null(), 0));
    let (ordered_path, ordered_json) = vector("pq_order");
    let ordered = open(&ordered_path);
    let mut out = std::mem::MaybeUninit::<SfpmLevelPq>::zeroed();
    assert_eq!(
        unsafe { sfpm_level_pq(ordered, 1, out.as_mut_ptr()) },
        SfpmStatus::SFPM_OK
    );
    let with_order = unsafe { out.assume_init() };
    assert!(!with_order.order.is_null());
    assert_eq!(with_order.order_len, 4);
    let order = unsafe { std::slice::from_raw_parts(with_order.order, with_order.order_len) };
    let want: Vec<u16> = ordered_json["content"]["levels"][1]["pq"]["order"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as u16)
        .collect();
    assert_eq!(order, want);
    assert_eq!(sfpm_close(ordered), SfpmStatus::SFPM_OK);
    let mut other = std::mem::MaybeUninit::<SfpmLevelPq>::zeroed();
    assert_eq!(
        unsafe { sfpm_level_pq(map, 0, other.as_mut_ptr()) },
        SfpmStatus::SFPM_ERR_MISSING
    );
    assert!(
        last_error().contains("not product-quantised"),
        "{}",
        last_error()
    );
    assert_eq!(
        unsafe { sfpm_level_pq(map, 1, null_mut()) },
        SfpmStatus::SFPM_ERR_NULL
    );
    sfpm_close(map);
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

/// Optional out pointers may be NULL, names are copied like `snprintf`, and a NULL required
/// pointer is named in the error, the first one in argument order, with nothing written.
#[test]
fn optional_truncated_and_null_outputs() {
    let (path, json) = vector("levels");
    let map = open(&path);
    let name = json["content"]["images"][0]["name"].as_str().unwrap();
    unsafe {
        let mut needed = 0usize;
        assert_eq!(
            sfpm_image_name(map, 0, null_mut(), 0, &mut needed),
            SfpmStatus::SFPM_OK
        );
        assert_eq!(needed, name.len());
        let mut one = [1 as std::ffi::c_char; 1];
        assert_eq!(
            sfpm_image_name(map, 0, one.as_mut_ptr(), 1, null_mut()),
            SfpmStatus::SFPM_OK
        );
        assert_eq!(one[0], 0, "capacity 1 holds just the NUL");
        let mut buf = [1 as std::ffi::c_char; 64];
        assert_eq!(
            sfpm_image_name(map, 0, buf.as_mut_ptr(), buf.len(), null_mut()),
            SfpmStatus::SFPM_OK
        );
        assert_eq!(CStr::from_ptr(buf.as_ptr()).to_str().unwrap(), name);
        assert_eq!(
            sfpm_image_name(map, 0, null_mut(), 8, &mut needed),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert!(last_error().contains("buf is NULL"), "{}", last_error());
        assert_eq!(
            sfpm_image_name(map, 99, null_mut(), 8, null_mut()),
            SfpmStatus::SFPM_ERR_ARGUMENT,
            "the index is checked before the buffer"
        );

        let nulls = sfpm_camera(
            map,
            0,
            null_mut(),
            0,
            null_mut(),
            null_mut(),
            null_mut(),
            0,
            null_mut(),
        );
        assert_eq!(
            nulls,
            SfpmStatus::SFPM_OK,
            "every camera output is optional"
        );
        let mut model = [1 as std::ffi::c_char; 3];
        let mut params = [0f64; 1];
        let mut width = 0u64;
        let status = sfpm_camera(
            map,
            0,
            model.as_mut_ptr(),
            model.len(),
            &mut width,
            null_mut(),
            params.as_mut_ptr(),
            0,
            null_mut(),
        );
        assert_eq!(status, SfpmStatus::SFPM_OK);
        assert_eq!(model[2], 0);
        assert_eq!(params[0], 0.0, "capacity 0: nothing written");
        assert!(width > 0);

        let (mut positions, mut n) = (null(), 0usize);
        assert_eq!(
            sfpm_point_positions(map, &mut positions, &mut n, null_mut()),
            SfpmStatus::SFPM_OK,
            "origin is optional"
        );
        assert_eq!(n, json["content"]["positions"].as_array().unwrap().len());
        assert!(!positions.is_null());

        let mut camera = 9u32;
        assert_eq!(
            sfpm_image_pose(map, 0, null_mut(), &mut camera),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert!(last_error().contains("pose is NULL"), "{}", last_error());
        assert_eq!(camera, 9, "nothing written");

        let (mut offsets, mut n_offsets, mut points) = (null(), 0usize, null());
        assert_eq!(
            sfpm_visibility(map, &mut offsets, &mut n_offsets, &mut points, null_mut()),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert!(
            last_error().contains("n_points is NULL"),
            "{}",
            last_error()
        );
        assert!(offsets.is_null() && points.is_null() && n_offsets == 0);

        let mut other: SfpmMap = 0;
        assert_eq!(sfpm_open(null(), null_mut()), SfpmStatus::SFPM_ERR_NULL);
        assert!(last_error().contains("path is NULL"), "{}", last_error());
        assert_eq!(
            sfpm_open(path.as_ptr(), null_mut()),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert!(last_error().contains("out is NULL"), "{}", last_error());
        let not_utf8 = CString::new(vec![0xffu8, 0xfe]).unwrap();
        assert_eq!(
            sfpm_open(not_utf8.as_ptr(), &mut other),
            SfpmStatus::SFPM_ERR_ARGUMENT
        );
        assert!(last_error().contains("not UTF-8"), "{}", last_error());
        assert_eq!(other, 0);

        let mut count = 7usize;
        assert_eq!(
            sfpm_point_count(0, &mut count),
            SfpmStatus::SFPM_ERR_INVALID_HANDLE
        );
        assert_eq!(count, 7);
        for (f, want) in [
            (sfpm_level_count as unsafe extern "C" fn(_, _) -> _, 3),
            (sfpm_point_count, n),
            (sfpm_camera_count, 1),
            (sfpm_image_count, 3),
        ] {
            assert_eq!(f(map, &mut count), SfpmStatus::SFPM_OK);
            assert_eq!(count, want);
            assert_eq!(f(map, null_mut()), SfpmStatus::SFPM_ERR_NULL);
            assert!(last_error().contains("out is NULL"), "{}", last_error());
        }
    }
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

fn vector_path(name: &str) -> CString {
    CString::new(format!(
        "{}/spec/vectors/valid/{name}.sfpm",
        env!("CARGO_MANIFEST_DIR")
    ))
    .unwrap()
}

#[test]
fn handles_detect_use_after_close() {
    let path = vector_path("levels");
    let mut map: SfpmMap = 0;
    // SAFETY: valid C string and out pointer.
    assert_eq!(
        unsafe { sfpm_open(path.as_ptr(), &mut map) },
        SfpmStatus::SFPM_OK
    );
    let mut n = 0usize;
    // SAFETY: valid out pointer.
    assert_eq!(
        unsafe { sfpm_level_count(map, &mut n) },
        SfpmStatus::SFPM_OK
    );
    assert_eq!(n, 3);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_ERR_INVALID_HANDLE);
    // SAFETY: valid out pointer.
    assert_eq!(
        unsafe { sfpm_level_count(map, &mut n) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    // A new map reusing the slot gets a new generation: the old handle stays dead.
    let mut again: SfpmMap = 0;
    // SAFETY: valid C string and out pointer.
    assert_eq!(
        unsafe { sfpm_open(path.as_ptr(), &mut again) },
        SfpmStatus::SFPM_OK
    );
    assert_ne!(again, map);
    // SAFETY: valid out pointer.
    assert_eq!(
        unsafe { sfpm_level_count(map, &mut n) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(sfpm_close(again), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(0), SfpmStatus::SFPM_ERR_INVALID_HANDLE);
}

#[test]
fn null_pointers_are_errors() {
    let path = vector_path("levels");
    // SAFETY: NULL is allowed and reported.
    assert_eq!(
        unsafe { sfpm_open(std::ptr::null(), std::ptr::null_mut()) },
        SfpmStatus::SFPM_ERR_NULL
    );
    let mut map: SfpmMap = 0;
    // SAFETY: valid C string and out pointer.
    assert_eq!(
        unsafe { sfpm_open(path.as_ptr(), &mut map) },
        SfpmStatus::SFPM_OK
    );
    // SAFETY: NULL out pointers are reported.
    unsafe {
        assert_eq!(
            sfpm_level_count(map, std::ptr::null_mut()),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert_eq!(
            sfpm_level_desc_short(map, 0, std::ptr::null_mut(), std::ptr::null_mut()),
            SfpmStatus::SFPM_ERR_NULL
        );
        assert_eq!(
            sfpm_localize(
                map,
                std::ptr::null(),
                std::ptr::null(),
                0,
                4,
                std::ptr::null(),
                std::ptr::null(),
                std::ptr::null_mut()
            ),
            SfpmStatus::SFPM_ERR_NULL
        );
    }
    // SAFETY: sfpm_last_error returns a NUL-terminated string.
    let msg = unsafe { CStr::from_ptr(sfpm_last_error()) };
    assert!(msg.to_str().unwrap().contains("NULL"), "{msg:?}");
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// Closing a handle while other threads call with it: each call either completes on the map
/// (it holds it until it returns) or sees an invalid handle; nothing crashes.
#[test]
fn close_races_with_calls_on_other_threads() {
    let path = vector_path("zstd");
    for _ in 0..20 {
        let map = open(&path);
        std::thread::scope(|s| {
            for _ in 0..3 {
                s.spawn(|| loop {
                    let (mut data, mut len) = (null(), 0usize);
                    let status = unsafe { sfpm_level_desc_short(map, 0, &mut data, &mut len) };
                    match status {
                        SfpmStatus::SFPM_OK => assert!(len > 0),
                        SfpmStatus::SFPM_ERR_INVALID_HANDLE => break,
                        other => panic!("{other:?}: {}", last_error()),
                    }
                });
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
            assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
        });
    }
}

// Sessions: `sfpm_session_*`.

/// The synthetic query's camera, for `f` to use.
fn with_camera<R>(f: impl FnOnce(&SfpmCamera) -> R) -> R {
    let model = CString::new("PINHOLE").unwrap();
    let params = [500.0, 500.0, 320.0, 240.0];
    f(&SfpmCamera {
        model: model.as_ptr(),
        width: 640,
        height: 480,
        params: params.as_ptr(),
        n_params: params.len(),
    })
}

/// `sfpm_session_localize`: its status, what it found and its path (1: tracking).
fn session_localize(
    session: SfpmSession,
    xy: &[f64],
    desc: &[f32],
) -> (SfpmStatus, SfpmLocalization, u8) {
    let mut out = SfpmLocalization::default();
    let mut tracked = 9u8;
    let status = with_camera(|camera| unsafe {
        sfpm_session_localize(
            session,
            xy.as_ptr(),
            desc.as_ptr(),
            xy.len() / 2,
            DIM,
            camera,
            &mut out,
            &mut tracked,
        )
    });
    (status, out, tracked)
}

fn default_options(map: SfpmMap) -> SfpmSessionOptions {
    let mut out = std::mem::MaybeUninit::<SfpmSessionOptions>::zeroed();
    let status = unsafe { sfpm_session_options_default(map, out.as_mut_ptr()) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    unsafe { out.assume_init() }
}

fn open_session(map: SfpmMap, options: Option<&SfpmSessionOptions>) -> SfpmSession {
    let mut session = 0;
    let options = options.map_or(null(), |o| o as *const _);
    let status = unsafe { sfpm_session_open(map, options, &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_ne!(session, 0);
    session
}

fn is_tracking(session: SfpmSession) -> u8 {
    let mut tracking = 9u8;
    let status = unsafe { sfpm_session_is_tracking(session, &mut tracking) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    tracking
}

/// A session with the map's own settings (NULL options, or `sfpm_session_options_default`'s
/// written out) finds what `sfpm_localize` finds, to the last bit; so does one on level 2's
/// short block, and one shared by four threads.
#[test]
fn a_session_localizes_like_sfpm_localize() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let (xy, desc) = query(&points, &descriptors);
    let map = open(&path);
    let (status, plain) = localize(map, &xy, &desc, None);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());

    // The map's settings: `LocalizeOptions::for_map` (a "test" descriptor, taken for an SFP
    // model's: ratio 0.95).
    let defaults = default_options(map);
    let want = sfpmap::localize::LocalizeOptions::for_map(
        &sfpmap::format::Map::open(path.to_str().unwrap()).unwrap(),
    );
    assert_eq!((defaults.levels, defaults.n_levels), (null(), 0));
    assert_eq!((defaults.short_only, defaults.sequence), (0, 0));
    assert_eq!(defaults.ratio, 0.95);
    assert_eq!(defaults.ratio, want.matching.ratio);
    assert_eq!(defaults.mutual, u8::from(want.matching.mutual));
    assert_eq!(defaults.min_similarity, want.matching.min_similarity);
    assert_eq!(defaults.top_k, want.top_k);
    assert_eq!(defaults.min_inliers, want.min_inliers);
    assert_eq!(
        (
            defaults.coarse_error_px,
            defaults.gate_px,
            defaults.gate_ratio,
            defaults.fine_error_px
        ),
        (
            want.coarse_error_px,
            want.gate_px,
            want.gate_ratio,
            want.fine_error_px
        )
    );

    for options in [None, Some(&defaults)] {
        let session = open_session(map, options);
        let (status, out, tracked) = session_localize(session, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
        assert_eq!(out.cam_from_world, plain.cam_from_world);
        assert_eq!((out.inliers, out.matches), (plain.inliers, plain.matches));
        assert_eq!(tracked, 0, "not a sequence: retrieval");
        assert_eq!(is_tracking(session), 0);
        assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    }

    // Level 2, short block only, both ways.
    let level = [2u16];
    let short = SfpmLocalizeOptions {
        levels: level.as_ptr(),
        n_levels: 1,
        short_only: 1,
    };
    let (status, plain) = localize(map, &xy, &desc, Some(&short));
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    let session = open_session(
        map,
        Some(&SfpmSessionOptions {
            levels: level.as_ptr(),
            n_levels: 1,
            short_only: 1,
            ..defaults
        }),
    );
    let (status, out, _) = session_localize(session, &xy, &desc);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_eq!(out.cam_from_world, plain.cam_from_world);
    assert_eq!(out.inliers, plain.inliers);

    // One session, four threads.
    std::thread::scope(|s| {
        for _ in 0..4 {
            s.spawn(|| {
                let (status, out, _) = session_localize(session, &xy, &desc);
                assert_eq!(status, SfpmStatus::SFPM_OK);
                assert_near_truth(&out);
            });
        }
    });

    // Too few features: runs, no pose, a reason; bad input: the codes of sfpm_localize.
    let (status, out, _) = session_localize(session, &xy[..10], &desc[..5 * DIM]);
    assert_eq!(status, SfpmStatus::SFPM_NOT_LOCALIZED);
    assert_eq!((out.cam_from_world, out.inliers), ([0.0; 7], 0));
    assert!(!last_error().is_empty());
    let mut bad = xy.clone();
    bad[3] = f64::NAN;
    assert_eq!(
        session_localize(session, &bad, &desc).0,
        SfpmStatus::SFPM_ERR_ARGUMENT
    );
    let mut out = SfpmLocalization::default();
    let status = with_camera(|camera| unsafe {
        sfpm_session_localize(
            session,
            xy.as_ptr(),
            desc.as_ptr(),
            1,
            16,
            camera,
            &mut out,
            null_mut(),
        )
    });
    assert_eq!(
        status,
        SfpmStatus::SFPM_ERR_LOCALIZE,
        "16 dimensions against 32"
    );
    assert!(last_error().contains("dimensions"), "{}", last_error());
    unsafe {
        let status = sfpm_session_localize(
            session,
            null(),
            null(),
            0,
            DIM,
            null(),
            &mut out,
            null_mut(),
        );
        assert_eq!(status, SfpmStatus::SFPM_ERR_NULL);
        assert!(last_error().contains("camera is NULL"), "{}", last_error());
        let status = with_camera(|camera| {
            sfpm_session_localize(
                session,
                null(),
                null(),
                0,
                DIM,
                camera,
                null_mut(),
                null_mut(),
            )
        });
        assert_eq!(status, SfpmStatus::SFPM_ERR_NULL);
        assert!(last_error().contains("out is NULL"), "{}", last_error());
    }
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// Options out of range are refused when the session opens, with the library's own message
/// (`LocalizeOptions::validate`, the CLI's and Python's text) and `SFPM_ERR_ARGUMENT`; values
/// are taken as they are, so a zeroed struct is refused too (0 never means "default").
#[test]
fn session_options_out_of_range_are_refused_with_the_library_message() {
    let path = vector_path("levels");
    let map = open(&path);
    let defaults = default_options(map);
    let cases: [(SfpmSessionOptions, &str); 7] = [
        (
            SfpmSessionOptions {
                ratio: 1.5,
                ..defaults
            },
            "ratio 1.5: a ratio in (0, 1]",
        ),
        (
            SfpmSessionOptions {
                ratio: 0.0,
                ..defaults
            },
            "ratio 0: a ratio in (0, 1]",
        ),
        (
            SfpmSessionOptions {
                gate_ratio: -0.5,
                ..defaults
            },
            "gate_ratio -0.5: a ratio in (0, 1]",
        ),
        (
            SfpmSessionOptions {
                top_k: 0,
                ..defaults
            },
            "top_k 0: 1 to 100000 images",
        ),
        (
            SfpmSessionOptions {
                min_similarity: 2.0,
                ..defaults
            },
            "min_similarity 2: a cosine similarity in [-1, 1]",
        ),
        (
            SfpmSessionOptions {
                fine_error_px: f64::NAN,
                ..defaults
            },
            "fine_error_px NaN: a finite number of pixels > 0",
        ),
        (
            SfpmSessionOptions {
                min_inliers: 3,
                ..defaults
            },
            "min_inliers 3: 4 to 1000000 inliers",
        ),
    ];
    for (options, message) in cases {
        let mut session: SfpmSession = 77;
        let status = unsafe { sfpm_session_open(map, &options, &mut session) };
        assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{message}");
        assert_eq!(last_error(), message);
        assert_eq!(session, 77, "nothing written");
    }
    let zeroed = unsafe { std::mem::MaybeUninit::<SfpmSessionOptions>::zeroed().assume_init() };
    let mut session: SfpmSession = 0;
    assert_eq!(
        unsafe { sfpm_session_open(map, &zeroed, &mut session) },
        SfpmStatus::SFPM_ERR_ARGUMENT
    );
    assert_eq!(last_error(), "top_k 0: 1 to 100000 images");
    // A level the map lacks, and NULL pointers.
    let level = [7u16];
    let options = SfpmSessionOptions {
        levels: level.as_ptr(),
        n_levels: 1,
        ..defaults
    };
    assert_eq!(
        unsafe { sfpm_session_open(map, &options, &mut session) },
        SfpmStatus::SFPM_ERR_NO_SUCH_LEVEL
    );
    assert!(last_error().contains("no level 7"), "{}", last_error());
    let options = SfpmSessionOptions {
        levels: null(),
        n_levels: 2,
        ..defaults
    };
    assert_eq!(
        unsafe { sfpm_session_open(map, &options, &mut session) },
        SfpmStatus::SFPM_ERR_NULL
    );
    assert!(
        last_error().contains("options.levels is NULL"),
        "{}",
        last_error()
    );
    assert_eq!(
        unsafe { sfpm_session_open(map, null(), null_mut()) },
        SfpmStatus::SFPM_ERR_NULL
    );
    assert_eq!(
        unsafe { sfpm_session_options_default(map, null_mut()) },
        SfpmStatus::SFPM_ERR_NULL
    );
    assert_eq!(session, 0);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// A sequence session on a map whose image sees every point: the first frame goes through
/// retrieval, the next ones are tracked around the predicted pose, a reset (or a frame that
/// is not localized) sends the next one through retrieval again. A session that is not a
/// sequence never tracks.
#[test]
fn a_sequence_session_tracks_a_moving_camera() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map_with(tmp.path(), true);
    let map = open(&path);
    let options = SfpmSessionOptions {
        sequence: 1,
        ..default_options(map)
    };
    let session = open_session(map, Some(&options));
    // The camera moves 5 cm sideways a frame.
    let t = truth();
    let frame = |k: usize| {
        let pose = Pose::new(
            t.rotation,
            t.translation + nalgebra::Vector3::new(0.05 * k as f64, 0.0, 0.0),
        );
        let (xy, desc) = query_at(&points, &descriptors, &pose);
        (pose, xy, desc)
    };
    assert_eq!(is_tracking(session), 0, "nothing to predict from yet");
    for k in 0..4 {
        let (pose, xy, desc) = frame(k);
        let (status, out, tracked) = session_localize(session, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "frame {k}: {}", last_error());
        assert_near(&out, &pose);
        assert_eq!(
            tracked,
            u8::from(k > 0),
            "frame {k}: the tracking path after the first"
        );
        assert_eq!(is_tracking(session), 1, "frame {k}");
    }
    assert_eq!(sfpm_session_reset_tracking(session), SfpmStatus::SFPM_OK);
    assert_eq!(is_tracking(session), 0);
    for (k, want) in [(4, 0), (5, 1)] {
        let (pose, xy, desc) = frame(k);
        let (status, out, tracked) = session_localize(session, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "frame {k}: {}", last_error());
        assert_near(&out, &pose);
        assert_eq!(tracked, want, "frame {k} after the reset");
    }
    // A frame that is not localized ends the track.
    let (_, xy, desc) = frame(6);
    let (status, _, _) = session_localize(session, &xy[..10], &desc[..5 * DIM]);
    assert_eq!(status, SfpmStatus::SFPM_NOT_LOCALIZED);
    assert_eq!(is_tracking(session), 0);
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);

    let plain = open_session(map, None);
    for k in 0..2 {
        let (pose, xy, desc) = frame(k);
        let (status, out, tracked) = session_localize(plain, &xy, &desc);
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
        assert_near(&out, &pose);
        assert_eq!((tracked, is_tracking(plain)), (0, 0), "not a sequence");
    }
    assert_eq!(sfpm_session_reset_tracking(plain), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_session_close(plain), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// A session holds its map: it keeps localizing after `sfpm_close` of the map handle. Closed
/// sessions and maps, second closes, 0 and handles of the other kind are
/// `SFPM_ERR_INVALID_HANDLE`, never a crash; a map's close does not close a session.
#[test]
fn sessions_outlive_their_map_handle_and_closed_handles_are_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let (points, descriptors, path) = synthetic_map(tmp.path());
    let (xy, desc) = query(&points, &descriptors);
    let map = open(&path);
    let session = open_session(map, None);
    assert_ne!(session, map);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
    let (status, out, _) = session_localize(session, &xy, &desc);
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    assert_near_truth(&out);

    // The closed map opens no session and gives no defaults.
    let mut other: SfpmSession = 0;
    assert_eq!(
        unsafe { sfpm_session_open(map, null(), &mut other) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(other, 0);
    let mut options = std::mem::MaybeUninit::<SfpmSessionOptions>::zeroed();
    assert_eq!(
        unsafe { sfpm_session_options_default(map, options.as_mut_ptr()) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    // A session handle is not a map handle: map calls refuse it, and sfpm_close leaves it.
    let mut n = 0usize;
    assert_eq!(
        unsafe { sfpm_level_count(session, &mut n) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert!(last_error().contains("session handle?"), "{}", last_error());
    assert_eq!(sfpm_close(session), SfpmStatus::SFPM_ERR_INVALID_HANDLE);
    assert_eq!(is_tracking(session), 0, "still open");

    // Nor the reverse.
    let live = open(&path);
    assert_eq!(
        sfpm_session_close(live),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert!(last_error().contains("map handle?"), "{}", last_error());
    assert_eq!(
        session_localize(live, &xy, &desc).0,
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(
        sfpm_session_close(session),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(
        session_localize(session, &xy, &desc).0,
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert!(last_error().contains("closed"), "{}", last_error());
    let mut tracking = 9u8;
    assert_eq!(
        unsafe { sfpm_session_is_tracking(session, &mut tracking) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(tracking, 9);
    assert_eq!(
        sfpm_session_reset_tracking(session),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );
    assert_eq!(sfpm_session_close(0), SfpmStatus::SFPM_ERR_INVALID_HANDLE);
    assert_eq!(
        unsafe { sfpm_session_is_tracking(0, &mut tracking) },
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    // A new session in the freed slot gets a new generation: the old handle stays dead.
    let again = open_session(live, None);
    assert_ne!(again, session);
    assert_eq!(
        sfpm_session_reset_tracking(session),
        SfpmStatus::SFPM_ERR_INVALID_HANDLE
    );

    // Closing a session while other threads localize with it: each call completes or sees
    // an invalid handle.
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                match session_localize(again, &xy, &desc).0 {
                    SfpmStatus::SFPM_OK => {}
                    SfpmStatus::SFPM_ERR_INVALID_HANDLE => break,
                    other => panic!("{other:?}: {}", last_error()),
                }
            });
        }
        std::thread::sleep(std::time::Duration::from_millis(5));
        assert_eq!(sfpm_session_close(again), SfpmStatus::SFPM_OK);
    });
    assert_eq!(sfpm_close(live), SfpmStatus::SFPM_OK);
}
