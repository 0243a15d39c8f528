//! Maps from any local feature: an hloc `features.h5` (and `global-feats.h5`) and a COLMAP 4
//! database of typed float descriptors, written by h5py and pycolmap 4.2.1 over the small
//! model of `convert.rs`; every malformed file a one-line error naming it, the image and the
//! dataset, and no input ever written to.
#![cfg(all(feature = "colmap", feature = "hdf5", feature = "localize"))]

use crate::convert::{model, write_model, IMAGES, POINTS};
use sfpmap::build::{convert, ConvertError, ConvertOptions};
use sfpmap::format::Map;
use sfpmap::progress::Silent;
use std::path::{Path, PathBuf};

/// The features' dimension: not SIFT's, so nothing can take them for SIFT bytes.
const DIM: usize = 64;

/// Writes, with h5py, hloc's layout for the model's 3 images (10 keypoints each: the model's
/// 2D points minus 0.5; descriptors `DIM × 10` f16 from a per-point pattern) with one
/// `mutation` (see the script), to `path`; `global` also writes `global-feats` to `global`.
const WRITER: &str = r#"
import sys, numpy as np, h5py
path, mutation, dim, images, points = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
def descriptor(j, i):
    k = np.arange(dim)
    return ((k * 7 + j * 31) % 97 + i * (k % 3) + 10).astype(np.float32) / 255.0
with h5py.File(path, "w") as f:
    for i in range(1, images + 1):
        name = f"img{i}.jpg"
        if mutation == "missing" and i == 2:
            continue
        n = points + 1
        xy = np.array([[10.0 * j + i, 20.0 + j] for j in range(points)] + [[1.0, 1.0]], np.float32) - 0.5
        d = np.stack([descriptor(j % points, i) for j in range(n)], 1)  # D x N
        if mutation == "outside" and i == 2:
            xy[3, 0] = 700.0
        if mutation == "edge" and i == 2:
            xy[3, 0] = 643.0  # past the border by less than 1 % of the image: real extractors do
        if mutation == "dim0" and i == 1:
            d = d[:0]
        if mutation == "nan" and i == 2:
            d[5, 4] = np.nan
        if mutation == "dim" and i == 3:
            d = d[:32]
        if mutation == "transposed" and i == 1:
            d = d.T.copy()
        g = f.create_group(name)
        g["keypoints"] = xy
        g["descriptors"] = d.astype(np.float16)
        g["scores"] = np.ones(n, np.float32)
        g["image_size"] = np.array([640, 480])
        if mutation == "scales":
            g["scales"] = np.array([j % points + 1.0 for j in range(n)], np.float32)
        if mutation == "global-linked":
            # One dataset of more values than a map holds, that every image's group links to:
            # counted once in the file, read once per image.
            if i == 1:
                g["global_descriptor"] = np.zeros(5000, np.float16)
            else:
                g["global_descriptor"] = f["img1.jpg/global_descriptor"]
        elif mutation.startswith("global") and not (mutation == "global-missing" and i == 3):
            g["global_descriptor"] = np.full(8 if mutation == "global8" else 16, float(i), np.float32)
"#;

struct Files {
    dir: tempfile::TempDir,
    model: PathBuf,
}

impl Files {
    fn new() -> Files {
        let dir = tempfile::tempdir().unwrap();
        let model_dir = dir.path().join("sparse");
        write_model(&model_dir, &model());
        Files {
            dir,
            model: model_dir,
        }
    }

    /// `name` written with `mutation`.
    fn h5(&self, name: &str, mutation: &str) -> PathBuf {
        let path = self.dir.path().join(name);
        let out = std::process::Command::new(crate::python::python_with("numpy, h5py"))
            .args(["-c", WRITER])
            .arg(&path)
            .args([mutation, &DIM.to_string(), &IMAGES.to_string()])
            .arg(POINTS.to_string())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        path
    }

    fn out(&self) -> PathBuf {
        self.dir.path().join("m.sfpm")
    }
}

fn features(path: &Path) -> ConvertOptions {
    ConvertOptions {
        features: Some(path.to_path_buf()),
        ..ConvertOptions::default()
    }
}

#[test]
fn an_hloc_features_file_makes_a_one_level_map_named_by_its_conf() {
    let f = Files::new();
    let h5 = f.h5("feats-aliked-n16.h5", "plain");
    let before = std::fs::read(&h5).unwrap();
    let summary = convert(&f.model, &features(&h5), &f.out(), &Silent).unwrap();
    assert_eq!(
        std::fs::read(&h5).unwrap(),
        before,
        "features file modified"
    );
    assert_eq!(
        (summary.points, summary.points_without_descriptors),
        (POINTS, 0)
    );
    let map = Map::open(f.out()).unwrap();
    map.verify().unwrap();
    let levels = &map.metadata().levels;
    assert_eq!(levels.len(), 1, "no keypoint scales: one level");
    let info = &levels[0];
    assert_eq!(
        (
            info.level,
            info.descriptor.as_str(),
            info.dim_full,
            info.dim_short
        ),
        (0, "aliked-n16", DIM as u32, DIM as u32 / 4)
    );
    assert_eq!(info.extra["feature_source"], "hloc features.h5");
    assert!(info.names_feature() && info.from_feature_source());
    // Each point's descriptor is the normalised mean of its track's: unprojected, point j
    // of image i is the pattern the script wrote, normalised.
    let level = map.level(0).unwrap();
    let (short, rest) = (
        level.desc_short().unwrap(),
        level.desc_rest().unwrap().unwrap(),
    );
    let p = level.projection().unwrap().unwrap();
    let (ds, df) = (level.dim_short(), level.dim_full());
    for (row, &point) in level.points().unwrap().iter().enumerate() {
        let stored: Vec<f32> = short[row * ds..(row + 1) * ds]
            .iter()
            .chain(&rest[row * (df - ds)..(row + 1) * (df - ds)])
            .map(|x| x.to_f32())
            .collect();
        let got: Vec<f32> = (0..DIM)
            .map(|k| (0..df).map(|d| p[d * DIM + k] * stored[d]).sum())
            .collect();
        let mut want = vec![0.0f32; DIM];
        for i in 1..=IMAGES {
            let d: Vec<f32> = (0..DIM)
                .map(|k| {
                    let v = ((k * 7 + point as usize * 31) % 97) as f32
                        + (i as usize * (k % 3)) as f32
                        + 10.0;
                    // f16 in the file.
                    sfpmap::format::f16::from_f32(v / 255.0).to_f32()
                })
                .collect();
            let n = d.iter().map(|v| v * v).sum::<f32>().sqrt();
            want.iter_mut().zip(&d).for_each(|(w, v)| *w += v / n);
        }
        let n = want.iter().map(|v| v * v).sum::<f32>().sqrt();
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w / n).abs() < 2e-3, "point {point}: {g} vs {}", w / n);
        }
    }
}

#[test]
fn scales_in_the_file_split_the_levels_and_a_stated_name_wins() {
    let f = Files::new();
    let h5 = f.h5("feats.h5", "scales");
    let options = ConvertOptions {
        feature_name: Some("sift-hloc".into()),
        ..features(&h5)
    };
    let summary = convert(&f.model, &options, &f.out(), &Silent).unwrap();
    assert_eq!(
        summary.levels.iter().map(|l| l.points).collect::<Vec<_>>(),
        [3, 3, 3]
    );
    let map = Map::open(f.out()).unwrap();
    assert!(map
        .metadata()
        .levels
        .iter()
        .all(|l| l.descriptor == "sift-hloc"));
    // A file of no name and no stated one: the map records `features-<dim>`, which takes
    // query features of any name.
    convert(&f.model, &features(&h5), &f.out(), &Silent).unwrap();
    let map = Map::open(f.out()).unwrap();
    let info = &map.metadata().levels[0];
    assert_eq!(info.descriptor, format!("features-{DIM}"));
    assert!(!info.names_feature());
}

#[test]
fn global_features_are_stored_for_retrieval_and_every_image_needs_one() {
    let f = Files::new();
    let h5 = f.h5("feats-aliked-n16.h5", "plain");
    let global = f.h5("global-feats-netvlad.h5", "global");
    let options = ConvertOptions {
        global_features: Some(global.clone()),
        ..features(&h5)
    };
    convert(&f.model, &options, &f.out(), &Silent).unwrap();
    let map = Map::open(f.out()).unwrap();
    let (values, dim) = map
        .image_global()
        .unwrap()
        .expect("global descriptors stored");
    assert_eq!((dim, values.len()), (16, 16 * IMAGES as usize));
    // Image i's is all i, in the model's image order.
    for (i, row) in values.chunks(dim).enumerate() {
        assert!(row.iter().all(|v| v.to_f32() == (i + 1) as f32), "{i}");
    }
    assert_eq!(
        map.metadata().retrieval(),
        Some(sfpmap::format::Retrieval::Global)
    );
    let partial = f.h5("global-partial.h5", "global-missing");
    let options = ConvertOptions {
        global_features: Some(partial.clone()),
        ..features(&h5)
    };
    let e = convert(&f.model, &options, &f.dir.path().join("n.sfpm"), &Silent).unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "{}: image \"img3.jpg\": no global_descriptor",
            partial.display()
        )
    );
    // A dataset linked from every group is refused by its shape, before it is read at all.
    let linked = f.h5("global-linked.h5", "global-linked");
    let options = ConvertOptions {
        global_features: Some(linked.clone()),
        ..features(&h5)
    };
    let e = convert(&f.model, &options, &f.dir.path().join("n.sfpm"), &Silent).unwrap_err();
    assert_eq!(
        e.to_string(),
        format!(
            "{}: img1.jpg/global_descriptor: 1 x 5000 values, more than the 4096 it may hold",
            linked.display()
        )
    );
}

/// Every malformed features file: its one-line error, exactly.
#[test]
fn a_malformed_features_file_is_named_with_the_image_and_dataset() {
    let f = Files::new();
    let cases = [
        (
            "missing",
            "image \"img2.jpg\" has no keypoints or descriptors (it would be skipped, not strict)",
        ),
        (
            "dim",
            "image \"img3.jpg\" has 32-dimensional descriptors, others have 64",
        ),
        (
            "outside",
            "img2.jpg/keypoints: keypoint 3 at (700, 22.5) lies outside the 640 x 480 image",
        ),
        (
            "nan",
            "img2.jpg/descriptors: keypoint 4: a value is NaN",
        ),
        (
            "dim0",
            "image \"img1.jpg\": descriptors of 0 dimensions (1 to 1024 are taken)",
        ),
        (
            "transposed",
            "img1.jpg/descriptors: 10 x 64 is keypoints x dimensions; hloc stores descriptors transposed, dimensions x keypoints (64 x 10)",
        ),
    ];
    for (mutation, message) in cases {
        let h5 = f.h5(&format!("feats-{mutation}.h5"), mutation);
        let before = std::fs::read(&h5).unwrap();
        let options = ConvertOptions {
            strict: true,
            ..features(&h5)
        };
        let out = f.dir.path().join(format!("{mutation}.sfpm"));
        let e = convert(&f.model, &options, &out, &Silent).unwrap_err();
        assert_eq!(
            e.to_string(),
            format!("{}: {message}", h5.display()),
            "{mutation}"
        );
        assert!(matches!(
            sfpmap::Error::from(e).kind(),
            sfpmap::ErrorKind::Convert
        ));
        assert_eq!(std::fs::read(&h5).unwrap(), before, "{mutation}: modified");
        assert!(!out.exists(), "{mutation}: a map was written");
    }
    // Past the border by less than 1 % of the image, as real extractors' keypoints are.
    let edge = f.h5("feats-edge.h5", "edge");
    convert(
        &f.model,
        &features(&edge),
        &f.dir.path().join("edge.sfpm"),
        &Silent,
    )
    .unwrap();
    // A database and a features file at once: which one would be a guess.
    let h5 = f.h5("feats-x.h5", "plain");
    let both = ConvertOptions {
        database: Some(h5.clone()),
        ..features(&h5)
    };
    let e = convert(&f.model, &both, &f.out(), &Silent).unwrap_err();
    assert!(matches!(e, ConvertError::Options(_)), "{e:?}");
}

/// Query features files name their feature as maps do: another one is refused naming both,
/// the same one or one of no name is taken.
#[test]
fn a_query_features_file_of_another_feature_is_refused_naming_both() {
    use sfpmap::session::{QuerySource, Session};
    use std::sync::Arc;
    let f = Files::new();
    let h5 = f.h5("feats-aliked-n16.h5", "plain");
    convert(&f.model, &features(&h5), &f.out(), &Silent).unwrap();
    let map = Arc::new(Map::open(f.out()).unwrap());
    let session = |queries: &Path| {
        Session::builder(map.clone(), "m.sfpm")
            .source(QuerySource::FeaturesFile(queries.to_path_buf()))
            .build(&Silent)
    };
    let disk = f.h5("feats-disk.h5", "plain");
    let Err(e) = session(&disk) else {
        panic!("DISK features taken for an ALIKED map")
    };
    assert_eq!(
        e.to_string(),
        format!(
            "{}: features of model \"disk\", but the map m.sfpm holds \"aliked-n16\" \
             descriptors: give query features of \"aliked-n16\"",
            disk.display()
        )
    );
    session(&h5).unwrap();
    session(&f.h5("queries.h5", "plain")).unwrap();
    // Query global descriptors of another size than the map's (here: it stores none) fail the
    // query, naming the file and both, not a retrieval that falls back in silence.
    let global = f.h5("global-feats-8.h5", "global8");
    let with_global = Session::builder(map.clone(), "m.sfpm")
        .source(QuerySource::FeaturesFile(h5.clone()))
        .global_features(Some(global.clone()))
        .build(&Silent)
        .unwrap();
    let camera = sfpmap::geometry::Camera::new(
        sfpmap::geometry::CameraModel::SimplePinhole,
        640,
        480,
        vec![500.0, 320.0, 240.0],
    )
    .unwrap();
    let failed = with_global.localize("img1.jpg", &camera).unwrap();
    assert_eq!(
        failed.outcome,
        Err(sfpmap::localize::QueryFailure::NoFeatures(format!(
            "{}: img1.jpg/global_descriptor: 8 values, but the map m.sfpm stores no global \
             descriptors",
            global.display()
        )))
    );
    // The same rule for a global descriptor handed in (as Python hands them in): refused,
    // never ranked by VLAD in silence.
    let mut features = sfpmap::io::features_h5::H5Features::open(&h5)
        .unwrap()
        .features("img1.jpg")
        .unwrap()
        .unwrap();
    features.global = Some(vec![1.0; 8]);
    let e = with_global
        .localize_features(&features, &camera, "img1.jpg")
        .unwrap_err();
    assert_eq!(
        e.to_string(),
        "m.sfpm: query \"img1.jpg\": global descriptor: 8 values, but the map m.sfpm stores no global \
         descriptors"
    );
    // Where retrieval never ranks by it, it is not refused.
    let vlad = Session::builder(map.clone(), "m.sfpm")
        .options(sfpmap::localize::LocalizeOptions {
            retrieval: sfpmap::localize::RetrievalMethod::Vlad,
            ..Default::default()
        })
        .build(&Silent)
        .unwrap();
    vlad.localize_features(&features, &camera, "img1.jpg")
        .unwrap();
}

/// Writes a COLMAP database of `IMAGES` images with `POINTS + 1` keypoints each, as pycolmap
/// 4.2.1 writes it, the descriptors of type `kind` (`aliked`: type 1, f32; `sift`: type 0,
/// u8), `dim` wide.
fn typed_database(db: &Path, kind: &str, dim: usize) {
    let script = r#"
import sys, numpy as np, pycolmap
db = pycolmap.Database.open(sys.argv[1])
kind, dim, images, points = sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
cid = db.write_camera(pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[500, 320, 240]))
for i in range(1, images + 1):
    iid = db.write_image(pycolmap.Image(name=f"img{i}.jpg", camera_id=cid))
    assert iid == i
    xy = np.array([[10.0 * j + i, 20.0 + j] for j in range(points)] + [[1.0, 1.0]], np.float32)
    d = np.stack([np.roll(np.linspace(0.1, 1.0, dim, dtype=np.float32), j % points) for j in range(points + 1)])
    db.write_keypoints(iid, xy)
    if kind == "aliked":
        rows = pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.ALIKED_N16ROT, d)
    else:
        rows = pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, (d * 255).astype(np.uint8))
    db.write_descriptors(iid, rows.to_bytes() if kind == "aliked" else rows)
db.close()
"#;
    let out = std::process::Command::new(crate::python::python_with("numpy, pycolmap"))
        .args(["-c", script])
        .arg(db)
        .args([
            kind.to_string(),
            dim.to_string(),
            IMAGES.to_string(),
            POINTS.to_string(),
        ])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// COLMAP 4's typed float descriptors, as pycolmap 4.2.1 writes them, make a map of that
/// feature (one level: its keypoints have no scale). A query database of SIFT rows, of the
/// same width, fails each of its queries naming both features (not matched as if alike).
#[test]
fn a_database_of_aliked_descriptors_makes_an_aliked_map() {
    use sfpmap::localize::QueryFailure;
    use sfpmap::session::{QuerySource, Session};
    const WIDE: usize = 128;
    let f = Files::new();
    let db = f.dir.path().join("database.db");
    typed_database(&db, "aliked", WIDE);
    let options = ConvertOptions {
        database: Some(db),
        ..ConvertOptions::default()
    };
    let summary = convert(&f.model, &options, &f.out(), &Silent).unwrap();
    assert_eq!(summary.points_without_descriptors, 0);
    let map = Map::open(f.out()).unwrap();
    let levels = &map.metadata().levels;
    assert_eq!(levels.len(), 1);
    assert_eq!(
        (levels[0].descriptor.as_str(), levels[0].dim_full),
        ("aliked-n16rot", WIDE as u32)
    );
    assert_eq!(levels[0].extra["feature_source"], "colmap database");

    let sift = f.dir.path().join("sift.db");
    typed_database(&sift, "sift", WIDE);
    let session = Session::builder(std::sync::Arc::new(map), "m.sfpm")
        .source(QuerySource::Database(sift.clone()))
        .build(&Silent)
        .unwrap();
    let camera = sfpmap::geometry::Camera::from_model_name(
        "SIMPLE_PINHOLE",
        640,
        480,
        &[500.0, 320.0, 240.0],
    )
    .unwrap();
    let failed = session.localize("img1.jpg", &camera).unwrap();
    assert_eq!(
        failed.outcome,
        Err(QueryFailure::NoFeatures(format!(
            "{}: query \"img1.jpg\": features of model \"sift\", but the map m.sfpm holds \
             \"aliked-n16rot\" descriptors: give query features of \"aliked-n16rot\"",
            sift.display()
        )))
    );
}
