//! The C ABI called from Rust as C would, its map readers: zero-copy views against the spec
//! vectors (raw and zstd sections, product-quantised levels), argument errors, optional and
//! NULL out pointers, handles used after close or closed while other threads call with them.
//! `sfpm_localize` is tested in `embed_capi_localize`, sessions in `embed_capi_session`; the
//! helpers all three use (`open`, `last_error`) are here.
#![cfg(feature = "capi")]
// Every call here passes valid pointers (or deliberately NULL ones, which the API reports).
#![allow(clippy::undocumented_unsafe_blocks)]

use serde_json::Value;
use sfpmap::ffi::*;
use std::ffi::{CStr, CString};
use std::path::Path;
use std::ptr::{null, null_mut};

fn vector(name: &str) -> (CString, Value) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("spec/vectors/valid");
    let json = std::fs::read_to_string(root.join(format!("{name}.json"))).unwrap();
    (
        CString::new(root.join(format!("{name}.sfpm")).to_str().unwrap()).unwrap(),
        serde_json::from_str(&json).unwrap(),
    )
}

pub(crate) fn open(path: &CStr) -> SfpmMap {
    let mut map = 0;
    let status = unsafe { sfpm_open(path.as_ptr(), &mut map) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    map
}

pub(crate) fn last_error() -> String {
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

pub(crate) fn vector_path(name: &str) -> CString {
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
