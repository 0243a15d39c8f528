//! The C ABI on a map from any local feature (issue 31): a map converted from an hloc
//! `features.h5` opened with `sfpm_open`, its queries localized through `sfpm_session_open` +
//! `sfpm_session_localize` (and `sfpm_localize`) with keypoints and descriptors handed in as
//! arrays, as a C caller holding hloc's features gives them.
//!
//! The scene is `benches/hloc_south_building.py`'s torch-free small variant: 12 South Building
//! map images and the 3 queries among them, pycolmap DoG/RootSIFT features in hloc's
//! `features.h5` layout, NN-ratio matches and a pose-verified pycolmap triangulation. It is built
//! by the test venv's Python (numpy, h5py, pycolmap) once per bench script, into this test
//! target's temporary folder (~15 s of CPU the first time).
#![cfg(all(feature = "capi", feature = "colmap", feature = "hdf5"))]
// Every call here passes valid pointers.
#![allow(clippy::undocumented_unsafe_blocks)]

use crate::embed_capi::{last_error, open};
use crate::shared_data::{repo_root, shared_data};

use sfpmap::build::{convert, ConvertOptions};
use sfpmap::ffi::*;
use sfpmap::geometry::Pose;
use sfpmap::progress::Silent;
use std::ffi::CString;
use std::path::{Path, PathBuf};
use std::ptr::null;

/// RootSIFT's dimensions.
const DIM: usize = 128;

/// Builds the scene into `out` and writes `manifest.txt` there: the model and the map images'
/// features file (paths relative to `out`; the file linked as `map/feats-rootsift-dog.h5`),
/// then per query its hloc query line and its ground truth (`gt qw qx qy qz tx ty tz`); and
/// `<name>.xy` (f64 x, y pairs: hloc's keypoints + 0.5, COLMAP's pixel centres) and
/// `<name>.desc` (f32 rows: hloc's `D × N` descriptors transposed), little-endian.
const BUILD: &str = r#"
import sys, os, importlib.util
from pathlib import Path
import numpy as np, h5py
bench, out, scene = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
spec = importlib.util.spec_from_file_location("hloc_south_building", bench)
module = importlib.util.module_from_spec(spec)
spec.loader.exec_module(module)
r = module.build_small_scene(out, features="sift", scene=scene)
# Named by a conf of the test's own: what the library makes of hloc's `sift` is not this test's.
(out / "map").mkdir()
os.link(r["features_map"], out / "map" / "feats-rootsift-dog.h5")
rel = lambda p: os.path.relpath(p, out)
lines = [f"sfm {rel(r['sfm'])}", "features_map map/feats-rootsift-dog.h5"]
with h5py.File(r["features"], "r") as f:
    for line in Path(r["queries"]).read_text().splitlines():
        name = line.split()[0]
        xy = f[name]["keypoints"][()].astype("<f8") + 0.5
        d = np.ascontiguousarray(f[name]["descriptors"][()].T.astype("<f4"))
        assert d.shape == (len(xy), 128), d.shape
        xy.tofile(out / f"{name}.xy")
        d.tofile(out / f"{name}.desc")
        lines.append("query " + line)
        lines.append("gt " + " ".join(repr(float(v)) for v in r["gt"][name]))
# Global descriptors that rank by camera position, as a retrieval network's would rank by view:
# one Gaussian per map camera centre (sigma: twice the median spacing). The map images' go to
# `global-feats-pose.h5` (hloc's layout), each query's (from its ground truth) to `<name>.global`.
import pycolmap
sfm = pycolmap.Reconstruction(str(r["sfm"]))
names = sorted(im.name for im in sfm.images.values())
centres = {im.name: np.asarray(im.projection_center()) for im in sfm.images.values()}
anchors = np.stack([centres[n] for n in names])
gaps = np.linalg.norm(anchors[:, None] - anchors[None], axis=-1)
sigma = 2 * np.median(np.sort(gaps, axis=1)[:, 1])
embed = lambda c: np.exp(-np.sum((anchors - c) ** 2, axis=1) / sigma**2).astype("<f4")
with h5py.File(out / "map" / "global-feats-pose.h5", "w") as g:
    for n in names:
        g.create_group(n).create_dataset("global_descriptor", data=embed(centres[n]))
lines.append("global_map map/global-feats-pose.h5")
def centre(gt):
    w, x, y, z, *t = gt
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return -rot.T @ np.asarray(t)
for line in Path(r["queries"]).read_text().splitlines():
    name = line.split()[0]
    embed(centre(r["gt"][name])).tofile(out / f"{name}.global")
(out / "manifest.txt").write_text("\n".join(lines) + "\n")
"#;

/// One query: its name, hloc camera line, ground truth and features.
pub(crate) struct Query {
    pub(crate) name: String,
    pub(crate) model: CString,
    pub(crate) width: u64,
    pub(crate) height: u64,
    pub(crate) params: Vec<f64>,
    /// `cam_from_world`, COLMAP's qw qx qy qz tx ty tz.
    pub(crate) gt: [f64; 7],
    pub(crate) xy: Vec<f64>,
    pub(crate) desc: Vec<f32>,
    /// Its global descriptor in `Scene::global_map`'s space (near cameras, near descriptors).
    pub(crate) global: Vec<f32>,
}

pub(crate) struct Scene {
    pub(crate) sfm: PathBuf,
    pub(crate) features_map: PathBuf,
    /// The map images' global descriptors, hloc's `global-feats.h5` layout.
    pub(crate) global_map: PathBuf,
    pub(crate) queries: Vec<Query>,
}

/// The scene's folder: built once per bench script (its hash names the folder) and kept in
/// the test target's temporary folder; a build goes to a folder of its own and is renamed
/// into place when finished, so a build killed halfway or one racing another leaves nothing
/// half-made under that name.
pub(crate) fn scene_dir(scene: &Path) -> PathBuf {
    let bench = repo_root().join("benches/hloc_south_building.py");
    let recipe = [std::fs::read(&bench).unwrap(), BUILD.as_bytes().to_vec()].concat();
    let root = Path::new(env!("CARGO_TARGET_TMPDIR"));
    let dir = root.join(format!(
        "hloc-sift-small-{:016x}",
        xxhash_rust::xxh3::xxh3_64(&recipe)
    ));
    if dir.join("manifest.txt").is_file() {
        return dir;
    }
    std::fs::create_dir_all(root).unwrap();
    let building = tempfile::tempdir_in(root).unwrap();
    let out = std::process::Command::new(crate::python::python_with("numpy, h5py, pycolmap"))
        .args(["-c", BUILD])
        .arg(&bench)
        .arg(building.path())
        .arg(scene)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "building the hloc scene failed:\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // Another process may have finished first: its folder is as good as ours.
    let _ = std::fs::rename(building.keep(), &dir);
    assert!(dir.join("manifest.txt").is_file());
    dir
}

pub(crate) fn read_scene(dir: &Path) -> Scene {
    let text = std::fs::read_to_string(dir.join("manifest.txt")).unwrap();
    let (mut sfm, mut features_map, mut global_map, mut queries) = (None, None, None, Vec::new());
    let floats =
        |s: &str| -> Vec<f64> { s.split_whitespace().map(|v| v.parse().unwrap()).collect() };
    for line in text.lines() {
        let (key, rest) = line.split_once(' ').unwrap();
        match key {
            "sfm" => sfm = Some(dir.join(rest)),
            "features_map" => features_map = Some(dir.join(rest)),
            "global_map" => global_map = Some(dir.join(rest)),
            "query" => {
                let mut f = rest.split_whitespace();
                let name = f.next().unwrap().to_string();
                let model = CString::new(f.next().unwrap()).unwrap();
                let width = f.next().unwrap().parse().unwrap();
                let height = f.next().unwrap().parse().unwrap();
                let params = f.map(|v| v.parse().unwrap()).collect();
                let bytes = |ext: &str| std::fs::read(dir.join(format!("{name}.{ext}"))).unwrap();
                let xy = bytes("xy")
                    .chunks_exact(8)
                    .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
                    .collect();
                let floats32 = |ext: &str| -> Vec<f32> {
                    bytes(ext)
                        .chunks_exact(4)
                        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                        .collect()
                };
                let (desc, global) = (floats32("desc"), floats32("global"));
                queries.push(Query {
                    name,
                    model,
                    width,
                    height,
                    params,
                    gt: [0.0; 7],
                    xy,
                    desc,
                    global,
                });
            }
            "gt" => {
                queries.last_mut().unwrap().gt = floats(rest).try_into().unwrap();
            }
            other => panic!("manifest: {other}"),
        }
    }
    Scene {
        sfm: sfm.unwrap(),
        features_map: features_map.unwrap(),
        global_map: global_map.unwrap(),
        queries,
    }
}

impl Query {
    pub(crate) fn camera<R>(&self, f: impl FnOnce(&SfpmCamera) -> R) -> R {
        f(&SfpmCamera {
            model: self.model.as_ptr(),
            width: self.width,
            height: self.height,
            params: self.params.as_ptr(),
            n_params: self.params.len(),
        })
    }

    /// The arrays as the library takes them: one set for every level, as the C ABI makes.
    fn features(&self) -> sfpmap::localize::QueryFeatures {
        let descriptors = self.desc.clone();
        sfpmap::localize::QueryFeatures {
            sets: vec![sfpmap::localize::FeatureSet {
                level: None,
                keypoints: self.xy.chunks_exact(2).map(|p| [p[0], p[1]]).collect(),
                descriptors,
                dim: DIM,
            }],
            global: None,
            model: None,
        }
    }

    fn geo_camera(&self) -> sfpmap::geometry::Camera {
        sfpmap::geometry::Camera::from_model_name(
            self.model.to_str().unwrap(),
            self.width as u32,
            self.height as u32,
            &self.params,
        )
        .unwrap()
    }

    pub(crate) fn n(&self) -> usize {
        assert_eq!(self.xy.len() / 2 * DIM, self.desc.len(), "{}", self.name);
        self.xy.len() / 2
    }
}

/// An hloc `feats-sift.h5` map through the C ABI: every query localized from arrays, by a
/// session and by `sfpm_localize` alike, near the scene's ground truth.
#[test]
fn a_map_from_an_hloc_features_file_localizes_arrays_through_a_session() {
    let Some(south) = shared_data("scenes/south-building") else {
        return;
    };
    let scene = read_scene(&scene_dir(&south));
    assert_eq!(scene.queries.len(), 3);
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("hloc.sfpm");
    let options = ConvertOptions {
        features: Some(scene.features_map.clone()),
        ..ConvertOptions::default()
    };
    let summary = convert(&scene.sfm, &options, &path, &Silent).unwrap();
    assert!(summary.points > 0);
    let levels = sfpmap::format::Map::open(&path)
        .unwrap()
        .metadata()
        .levels
        .clone();
    assert!(
        !levels.is_empty() && levels.iter().all(|l| l.descriptor == "rootsift-dog"),
        "named by the file's conf: {:?}",
        levels.iter().map(|l| &l.descriptor).collect::<Vec<_>>()
    );

    let map = open(&CString::new(path.to_str().unwrap()).unwrap());
    let mut count = 0usize;
    assert_eq!(
        unsafe { sfpm_level_count(map, &mut count) },
        SfpmStatus::SFPM_OK
    );
    assert_eq!(count, levels.len());
    let mut session = 0;
    let status = unsafe { sfpm_session_open(map, null(), &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    for q in &scene.queries {
        let mut out = SfpmLocalization::default();
        let mut tracked = 9u8;
        let status = q.camera(|camera| unsafe {
            sfpm_session_localize(
                session,
                q.xy.as_ptr(),
                q.desc.as_ptr(),
                q.n(),
                DIM,
                camera,
                &mut out,
                &mut tracked,
            )
        });
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}: {}", q.name, last_error());
        assert_eq!(tracked, 0, "not a sequence: retrieval");
        let pose = Pose::from_colmap_array(out.cam_from_world).unwrap();
        let gt = Pose::from_colmap_array(q.gt).unwrap();
        let (centre, degrees) = (pose.center_distance(&gt), pose.rotation_error_deg(&gt));
        // The scene's map cameras are ~0.23 units apart; hloc's own pipeline is within 0.001.
        assert!(
            centre < 0.05 && degrees < 1.0,
            "{}: {centre} units, {degrees} deg from the ground truth ({} inliers)",
            q.name,
            out.inliers
        );
        assert!(out.inliers >= 20, "{}: {} inliers", q.name, out.inliers);

        // `sfpm_localize` (no session): the same pose, to the last bit.
        let mut plain = SfpmLocalization::default();
        let status = q.camera(|camera| unsafe {
            sfpm_localize(
                map,
                q.xy.as_ptr(),
                q.desc.as_ptr(),
                q.n(),
                DIM,
                camera,
                null(),
                &mut plain,
            )
        });
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}: {}", q.name, last_error());
        assert_eq!(plain.cam_from_world, out.cam_from_world, "{}", q.name);
    }
    // Descriptors of another size than the map's: refused, named.
    let q = &scene.queries[0];
    let mut out = SfpmLocalization::default();
    let status = q.camera(|camera| unsafe {
        sfpm_session_localize(
            session,
            q.xy.as_ptr(),
            q.desc.as_ptr(),
            q.n() / 2,
            DIM * 2,
            camera,
            &mut out,
            std::ptr::null_mut(),
        )
    });
    assert_eq!(status, SfpmStatus::SFPM_ERR_LOCALIZE, "{}", last_error());
    assert!(last_error().contains("dimensions"), "{}", last_error());
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}

/// `sfpm_session_localize_global` on a map whose retrieval ranks images by hloc global
/// descriptors (`--global-features`), one image retrieved: each query's own descriptor
/// localizes it near the ground truth; the C call gives, to the last bit, the library
/// session's pose for the same global descriptor, whose retrieval ranked first the image the
/// descriptor points at (the query's nearest camera, or the farthest one's own descriptor);
/// a descriptor of other dimensions or with a NaN is refused.
#[test]
fn query_global_descriptors_rank_a_global_map_through_the_c_abi() {
    let Some(south) = shared_data("scenes/south-building") else {
        return;
    };
    let scene = read_scene(&scene_dir(&south));
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("hloc-global.sfpm");
    let options = ConvertOptions {
        features: Some(scene.features_map.clone()),
        global_features: Some(scene.global_map.clone()),
        ..ConvertOptions::default()
    };
    convert(&scene.sfm, &options, &path, &Silent).unwrap();
    let on_disk = sfpmap::format::Map::open(&path).unwrap();
    assert_eq!(on_disk.metadata().retrieval.as_deref(), Some("global"));
    let (stored, dim) = on_disk.image_global().unwrap().unwrap();
    let globals: Vec<Vec<f32>> = stored
        .chunks_exact(dim)
        .map(|g| g.iter().map(|v| v.to_f32()).collect())
        .collect();

    let map = open(&CString::new(path.to_str().unwrap()).unwrap());
    let mut o = crate::embed_capi_session::default_options(map);
    o.top_k = 1;
    let mut settings = sfpmap::localize::LocalizeOptions::for_map(&on_disk);
    settings.top_k = 1;
    let rust_session = sfpmap::session::Session::builder(std::sync::Arc::new(on_disk), "m.sfpm")
        .options(settings)
        .build(&Silent)
        .unwrap();
    let mut session = 0;
    let status = unsafe { sfpm_session_open(map, &o, &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    let localize = |q: &Query, global: &[f32], out: &mut SfpmLocalization| {
        q.camera(|camera| unsafe {
            sfpm_session_localize_global(
                session,
                q.xy.as_ptr(),
                q.desc.as_ptr(),
                q.n(),
                DIM,
                global.as_ptr(),
                global.len(),
                camera,
                out,
                std::ptr::null_mut(),
            )
        })
    };
    let cosine = |a: &[f32], b: &[f32]| {
        let dot = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
        dot(a, b) / (dot(a, a) * dot(b, b)).sqrt()
    };
    for q in &scene.queries {
        assert_eq!(q.global.len(), dim, "{}", q.name);
        let mut right = SfpmLocalization::default();
        let status = localize(q, &q.global, &mut right);
        assert_eq!(status, SfpmStatus::SFPM_OK, "{}: {}", q.name, last_error());
        let pose = Pose::from_colmap_array(right.cam_from_world).unwrap();
        let gt = Pose::from_colmap_array(q.gt).unwrap();
        let (centre, degrees) = (pose.center_distance(&gt), pose.rotation_error_deg(&gt));
        assert!(
            centre < 0.05 && degrees < 1.0,
            "{}: {centre} units, {degrees} deg ({} inliers)",
            q.name,
            right.inliers
        );
        // The map image farthest from the query, by the descriptors: its own descriptor
        // retrieves it, where the query's retrieves one of the most alike (two neighbours
        // of a query may be alike to the third decimal).
        let likeness = |i: usize, g: &[f32]| cosine(&globals[i], g);
        let far = (0..globals.len())
            .min_by(|&a, &b| likeness(a, &q.global).total_cmp(&likeness(b, &q.global)))
            .unwrap();
        let best = (0..globals.len())
            .map(|i| likeness(i, &q.global))
            .fold(f32::MIN, f32::max);
        for global in [&q.global, &globals[far]] {
            let mut features = q.features();
            features.global = Some(global.clone());
            let library = rust_session
                .localize_features(&features, &q.geo_camera(), &q.name)
                .unwrap();
            let [first] = library.retrieved[..] else {
                panic!("{}: retrieved {:?}", q.name, library.retrieved)
            };
            if std::ptr::eq(global, &q.global) {
                assert!(likeness(first, global) > best - 1e-3, "{}", q.name);
                assert_ne!(first, far, "{}", q.name);
            } else {
                assert_eq!(first, far, "{}", q.name);
            }
            let mut from_c = SfpmLocalization::default();
            let status = localize(q, global, &mut from_c);
            match library.outcome {
                Ok(pose) => {
                    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", q.name);
                    assert_eq!(from_c.cam_from_world, pose.to_colmap());
                }
                Err(_) => assert_eq!(status, SfpmStatus::SFPM_NOT_LOCALIZED, "{}", q.name),
            }
        }
    }
    // Refusals leave `out` as it was.
    let q = &scene.queries[0];
    let untouched = SfpmLocalization {
        cam_from_world: [7.0; 7],
        inliers: 7,
        matches: 7,
    };
    let mut out = untouched;
    let status = localize(q, &q.global[..dim - 1], &mut out);
    assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{}", last_error());
    assert_eq!(out.cam_from_world, untouched.cam_from_world);
    assert_eq!(
        last_error(),
        format!(
            "global: {} values, but the map {} stores global descriptors of {dim}",
            dim - 1,
            path.display()
        )
    );
    let mut nan = q.global.clone();
    nan[1] = f32::NAN;
    let status = localize(q, &nan, &mut out);
    assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{}", last_error());
    assert_eq!(last_error(), "global: value 1 is NaN");
    assert_eq!(out.cam_from_world, untouched.cam_from_world);
    // NULL with a length: named.
    let status = q.camera(|camera| unsafe {
        sfpm_session_localize_global(
            session,
            q.xy.as_ptr(),
            q.desc.as_ptr(),
            q.n(),
            DIM,
            null(),
            dim,
            camera,
            &mut out,
            std::ptr::null_mut(),
        )
    });
    assert_eq!(status, SfpmStatus::SFPM_ERR_NULL, "{}", last_error());
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);

    // A map without global descriptors ranks by VLAD: a global handed in is refused, before
    // a value of it is read.
    let plain = tmp.path().join("hloc.sfpm");
    let options = ConvertOptions {
        features: Some(scene.features_map.clone()),
        ..ConvertOptions::default()
    };
    convert(&scene.sfm, &options, &plain, &Silent).unwrap();
    let map = open(&CString::new(plain.to_str().unwrap()).unwrap());
    let mut session = 0;
    let status = unsafe { sfpm_session_open(map, null(), &mut session) };
    assert_eq!(status, SfpmStatus::SFPM_OK, "{}", last_error());
    let status = q.camera(|camera| unsafe {
        sfpm_session_localize_global(
            session,
            q.xy.as_ptr(),
            q.desc.as_ptr(),
            q.n(),
            DIM,
            q.global.as_ptr(),
            dim,
            camera,
            &mut out,
            std::ptr::null_mut(),
        )
    });
    assert_eq!(status, SfpmStatus::SFPM_ERR_ARGUMENT, "{}", last_error());
    assert!(
        last_error().contains("stores no global descriptors"),
        "{}",
        last_error()
    );
    assert_eq!(sfpm_session_close(session), SfpmStatus::SFPM_OK);
    assert_eq!(sfpm_close(map), SfpmStatus::SFPM_OK);
}
