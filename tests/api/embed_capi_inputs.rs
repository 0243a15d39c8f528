//! The C ABI on maps from every input issue 31 adds besides hloc's files (those are
//! `embed_capi_features`): a COLMAP 4 database of typed float descriptors, a kapture folder
//! written by NAVER's PyPI `kapture`, and the built-in ALIKED-N16 describing the model's images.
//! Each map is opened with `sfpm_open` and every query of `embed_capi_features`' South Building
//! scene is localized through `sfpm_session_localize` from arrays, as a C caller holding those
//! features hands them in, near the scene's ground truth.
//!
//! The typed database and the kapture folder hold the scene's own features (pycolmap's
//! DoG/RootSIFT, the model's observations index them): the database stores them as type 1
//! (`ALIKED_N16ROT`, 128 f32 a row, the layout that type has), so what is tested is that the
//! typed layout is read as floats, not which network made the values. The ALIKED map's and its
//! queries' features come from the built-in model itself (`Extractor::builtin`).
// Every call here passes valid pointers.
#![allow(clippy::undocumented_unsafe_blocks)]

use crate::embed_capi::{last_error, open};
use crate::embed_capi_features::{read_scene, scene_dir, Query, Scene};
use crate::shared_data::shared_data;

use sfpmap::build::{convert, convert_kapture, convert_with_images, ConvertOptions, SfpMapOptions};
use sfpmap::extract::{image, DetectOptions, Extractor, ExtractorOptions};
use sfpmap::ffi::*;
use sfpmap::geometry::Pose;
use sfpmap::io::kapture::KaptureOptions;
use sfpmap::progress::Silent;
use std::ffi::CString;
use std::path::{Path, PathBuf};

/// The longer side the ALIKED map's images and its queries are run at (the scene's images are
/// 1024 × 768: the network sees them whole).
const RESIZE_MAX: u32 = 1024;

/// Writes, from the scene's model (`argv[1]`), its database of keypoints (`argv[2]`) and its
/// features file (`argv[3]`), into `argv[4]`: `typed.db` (the database with each image's
/// descriptors as pycolmap 4.2.1 writes type 1) and `kapture/` (cameras, poses, records,
/// keypoints, descriptors, points and observations through the `kapture` package's own
/// writers; keypoints in COLMAP's pixel convention, as kapture's COLMAP importer keeps them).
const INPUTS: &str = r#"
import sys, shutil
from pathlib import Path
import numpy as np, h5py, pycolmap, kapture
import kapture.io.csv as kcsv
from kapture.io.features import (get_descriptors_fullpath, get_keypoints_fullpath,
                                 image_descriptors_to_file, image_keypoints_to_file)
sfm, keypoints_db, feats, out = sys.argv[1], sys.argv[2], sys.argv[3], Path(sys.argv[4])
rec = pycolmap.Reconstruction(sfm)
with h5py.File(feats, "r") as f:
    desc = {im.name: np.ascontiguousarray(f[im.name]["descriptors"][()].T.astype(np.float32))
            for im in rec.images.values()}
    xy = {im.name: f[im.name]["keypoints"][()].astype(np.float32) + 0.5
          for im in rec.images.values()}

shutil.copy(keypoints_db, out / "typed.db")
with pycolmap.Database.open(str(out / "typed.db")) as db:
    for image_id, im in rec.images.items():
        assert db.read_keypoints(image_id).shape[0] == len(xy[im.name]), im.name
        db.write_descriptors(image_id, pycolmap.FeatureDescriptorsFloat(
            pycolmap.FeatureExtractorType.ALIKED_N16ROT, desc[im.name]).to_bytes())

root = str(out / "kapture")
sensors, trajectories, records = kapture.Sensors(), kapture.Trajectories(), kapture.RecordsCamera()
for cam_id, cam in rec.cameras.items():
    sensors[f"cam{cam_id}"] = kapture.Camera(cam.model.name, [cam.width, cam.height, *cam.params])
keypoints = kapture.Keypoints("rootsift", np.float32, 2)
descriptors = kapture.Descriptors("rootsift", np.float32, 128, "rootsift", "L2")
for ts, (image_id, im) in enumerate(sorted(rec.images.items())):
    sensor = f"cam{im.camera_id}"
    records[ts, sensor] = im.name
    pose = im.cam_from_world()
    x, y, z, w = pose.rotation.quat
    trajectories[ts, sensor] = kapture.PoseTransform(r=[w, x, y, z], t=list(pose.translation))
    image_keypoints_to_file(get_keypoints_fullpath("rootsift", root, im.name), xy[im.name])
    image_descriptors_to_file(get_descriptors_fullpath("rootsift", root, im.name), desc[im.name])
    keypoints.add(im.name)
    descriptors.add(im.name)
ids = sorted(rec.points3D)
points = kapture.Points3d(np.array([[*rec.points3D[i].xyz, *rec.points3D[i].color] for i in ids]))
observations = kapture.Observations()
for row, point_id in enumerate(ids):
    for el in rec.points3D[point_id].track.elements:
        observations.add(row, "rootsift", rec.images[el.image_id].name, int(el.point2D_idx))
kcsv.kapture_to_dir(root, kapture.Kapture(
    sensors=sensors, records_camera=records, trajectories=trajectories,
    keypoints={"rootsift": keypoints}, descriptors={"rootsift": descriptors},
    points3d=points, observations=observations))
"#;

/// `typed.db` and `kapture/` of the scene, in `out`.
fn write_inputs(scene: &Scene, out: &Path) -> (PathBuf, PathBuf) {
    let keypoints_db = scene.sfm.parent().unwrap().join("sfm-database.db");
    let run =
        std::process::Command::new(crate::python::python_with("numpy, h5py, pycolmap, kapture"))
            .args(["-c", INPUTS])
            .arg(&scene.sfm)
            .arg(&keypoints_db)
            .arg(&scene.features_map)
            .arg(out)
            .output()
            .unwrap();
    assert!(
        run.status.success(),
        "writing the typed database and kapture folder failed:\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    (out.join("typed.db"), out.join("kapture"))
}

/// A query's arrays as a C caller hands them in.
struct Arrays {
    xy: Vec<f64>,
    desc: Vec<f32>,
    dim: usize,
}

/// Localizes every query through a session on the map at `path` (`features` gives each its
/// arrays) and checks the pose against the ground truth; `within` is the centre distance
/// allowed, in scene units (the map cameras are ~0.23 apart).
fn localizes_every_query(
    path: &Path,
    queries: &[Query],
    within: f64,
    features: impl Fn(&Query) -> Arrays,
) {
    let map = open(&CString::new(path.to_str().unwrap()).unwrap());
    let mut session = 0;
    let status = unsafe { sfpm_session_open(map, std::ptr::null(), &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    for q in queries {
        let a = features(q);
        assert_eq!(a.xy.len() / 2 * a.dim, a.desc.len(), "{}", q.name);
        let mut out = SfpmLocalization::default();
        let status = q.camera(|camera| unsafe {
            sfpm_session_localize(
                session,
                a.xy.as_ptr(),
                a.desc.as_ptr(),
                a.xy.len() / 2,
                a.dim,
                camera,
                &mut out,
                std::ptr::null_mut(),
            )
        });
        let name = path.file_name().unwrap().to_string_lossy();
        assert_eq!(
            status,
            SfpmStatus::SFPM_OK,
            "{name} {}: {}",
            q.name,
            last_error()
        );
        let pose = Pose::from_colmap_array(out.cam_from_world).unwrap();
        let gt = Pose::from_colmap_array(q.gt).unwrap();
        let (centre, degrees) = (pose.center_distance(&gt), pose.rotation_error_deg(&gt));
        assert!(
            centre < within && degrees < 2.0,
            "{name} {}: {centre} units, {degrees} deg from the ground truth ({} inliers)",
            q.name,
            out.inliers
        );
        assert!(
            out.inliers >= 20,
            "{name} {}: {} inliers",
            q.name,
            out.inliers
        );
    }
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

fn descriptor_names(path: &Path) -> Vec<String> {
    let map = sfpmap::format::Map::open(path).unwrap();
    map.metadata()
        .levels
        .iter()
        .map(|l| l.descriptor.clone())
        .collect()
}

/// A COLMAP 4 database of typed float descriptors and a kapture folder of the same features:
/// each makes a map of that feature whose queries localize through the C ABI as the hloc map's
/// do (within 0.05 units, hloc's own pipeline being within 0.001).
#[test]
fn maps_from_a_typed_database_and_a_kapture_folder_localize_arrays_through_the_c_abi() {
    let Some(south) = shared_data("scenes/south-building") else {
        return;
    };
    let scene = read_scene(&scene_dir(&south));
    let tmp = tempfile::tempdir().unwrap();
    let (typed_db, kapture) = write_inputs(&scene, tmp.path());
    let own = |q: &Query| Arrays {
        xy: q.xy.clone(),
        desc: q.desc.clone(),
        dim: 128,
    };

    let from_db = tmp.path().join("typed.sfpm");
    let options = ConvertOptions {
        database: Some(typed_db),
        ..ConvertOptions::default()
    };
    let summary = convert(&scene.sfm, &options, &from_db, &Silent).unwrap();
    assert_eq!(summary.points_without_descriptors, 0);
    assert_eq!(descriptor_names(&from_db), ["aliked-n16rot"]);
    localizes_every_query(&from_db, &scene.queries, 0.05, own);

    let from_kapture = tmp.path().join("kapture.sfpm");
    let summary = convert_kapture(
        &kapture,
        &KaptureOptions::default(),
        &ConvertOptions::default(),
        &from_kapture,
        &Silent,
    )
    .unwrap();
    assert_eq!(summary.points_without_descriptors, 0);
    assert_eq!(descriptor_names(&from_kapture), ["rootsift"]);
    // The folder holds its own features: a database beside it is refused, not ignored.
    let with_db = ConvertOptions {
        database: Some(scene.features_map.clone()),
        ..ConvertOptions::default()
    };
    let other = tmp.path().join("other.sfpm");
    let e = convert_kapture(
        &kapture,
        &KaptureOptions::default(),
        &with_db,
        &other,
        &Silent,
    )
    .unwrap_err();
    assert!(e.to_string().contains("holds its own keypoints"), "{e}");
    assert!(!other.exists());
    localizes_every_query(&from_kapture, &scene.queries, 0.05, own);
}

/// The built-in ALIKED-N16 describing the model's images makes a one-level map; its queries,
/// extracted by the same built-in model in the library, localize through the C ABI.
#[test]
fn a_builtin_aliked_map_localizes_aliked_arrays_through_the_c_abi() {
    let Some(south) = shared_data("scenes/south-building") else {
        return;
    };
    let scene = read_scene(&scene_dir(&south));
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("aliked.sfpm");
    let mut options = SfpMapOptions::new(south.join("images"));
    options.extractor = ExtractorOptions {
        model: Some("aliked-n16".into()),
        ..ExtractorOptions::default()
    };
    options.resize_max = Some(RESIZE_MAX);
    let summary = convert_with_images(&scene.sfm, &options, &path, &Silent).unwrap();
    assert!(summary.convert.points > 300, "{}", summary.convert.points);
    assert_eq!(descriptor_names(&path), ["aliked-n16"]);

    let mut extractor = Extractor::builtin("aliked-n16", 2, &Silent)
        .expect("aliked-n16 is built in")
        .unwrap();
    let weights = extractor.contract().gray_weights;
    let arrays: Vec<(String, Arrays)> = scene
        .queries
        .iter()
        .map(|q| {
            let input = image::load(
                &south.join("images").join(&q.name),
                weights,
                Some(RESIZE_MAX),
            )
            .unwrap();
            let features = extractor
                .extract(&input, &DetectOptions::default())
                .unwrap();
            let level = &features.levels[0];
            let arrays = Arrays {
                xy: level
                    .keypoints
                    .iter()
                    .flat_map(|p| [f64::from(p[0]), f64::from(p[1])])
                    .collect(),
                desc: level.full.iter().map(|v| v.to_f32()).collect(),
                dim: level.dim_full,
            };
            (q.name.clone(), arrays)
        })
        .collect();
    // ALIKED's keypoints are not the model's (its points are SIFT's, described where SIFT
    // found them): stage-4 recall's bar on South Building is 0.1 of the camera spacing.
    localizes_every_query(&path, &scene.queries, 0.1, |q| {
        let (_, a) = arrays.iter().find(|(n, _)| *n == q.name).unwrap();
        Arrays {
            xy: a.xy.clone(),
            desc: a.desc.clone(),
            dim: a.dim,
        }
    });
}
