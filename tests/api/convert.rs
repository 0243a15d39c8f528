//! `convert` on a small model and database the test makes itself, then on the real fixtures.
#![cfg(feature = "colmap")]

use crate::common;
use crate::shared_data;

use rusqlite::{params, Connection};
use sfpmap::build::{convert, Aggregate, ConvertError, ConvertOptions};
use sfpmap::colmap::{bin, Camera, Image, Point2D, Reconstruction, TrackElement};
use sfpmap::format::{Codec, Map};
use sfpmap::geometry::{CameraModel, Pose};
use sfpmap::progress::Silent;
use std::path::{Path, PathBuf};

pub(crate) const POINTS: usize = 9;
pub(crate) const IMAGES: u32 = 3;

/// Point j's observation in image i: a descriptor around a per-point pattern.
fn descriptor(point: usize, image: u32) -> Vec<u8> {
    (0..128)
        .map(|k| ((k * 7 + point * 31) % 97) as u8 + (image as u8) * ((k % 3) as u8) + 10)
        .collect()
}

/// 3 images that each see 9 points (the 10th point2D is not triangulated); point j's
/// keypoints have scale j + 1, so the tertiles put points 0-2, 3-5, 6-8 in levels 0, 1, 2.
pub(crate) fn model() -> Reconstruction {
    let mut b = Reconstruction::builder();
    b.add_camera(Camera {
        id: 1,
        model: CameraModel::SimplePinhole,
        width: 640,
        height: 480,
        params: vec![500.0, 320.0, 240.0],
    });
    for i in 1..=IMAGES {
        let mut points2d: Vec<Point2D> = (0..POINTS)
            .map(|j| Point2D {
                xy: [10.0 * j as f64 + i as f64, 20.0 + j as f64],
                point3d_id: Some(100 + j as u64),
            })
            .collect();
        points2d.push(Point2D {
            xy: [1.0, 1.0],
            point3d_id: None,
        });
        b.add_image(Image {
            id: i,
            name: format!("img{i}.jpg"),
            camera_id: 1,
            cam_from_world: Pose::from_colmap_array([1.0, 0.0, 0.0, 0.0, i as f64, 0.0, 0.0])
                .unwrap(),
            points2d,
        });
    }
    for j in 0..POINTS {
        let track: Vec<TrackElement> = (1..=IMAGES)
            .map(|i| TrackElement {
                image_id: i,
                point2d_idx: j as u32,
            })
            .collect();
        b.add_point3d(
            100 + j as u64,
            [j as f64, 1.0, 5.0],
            [j as u8, 2, 3],
            0.5,
            &track,
        )
        .unwrap();
    }
    b.build().unwrap()
}

pub(crate) fn write_model(dir: &Path, rec: &Reconstruction) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join("cameras.bin"), bin::write_cameras(rec)).unwrap();
    std::fs::write(dir.join("images.bin"), bin::write_images(rec)).unwrap();
    std::fs::write(dir.join("points3D.bin"), bin::write_points3d(rec)).unwrap();
}

/// A current-schema-like database with 4-column keypoints (x, y, scale, orientation).
fn write_database(path: &Path, keypoints_per_image: usize) {
    let db = Connection::open(path).unwrap();
    common::colmap_schema(&db);
    let params: Vec<u8> = [500.0f64, 320.0, 240.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    db.execute(
        "INSERT INTO cameras VALUES (1, 0, 640, 480, ?1, 0)",
        params![params],
    )
    .unwrap();
    for i in 1..=IMAGES {
        db.execute(
            "INSERT INTO images VALUES (?1, ?2, 1)",
            params![i, format!("img{i}.jpg")],
        )
        .unwrap();
        let rows = keypoints_per_image;
        let mut kp = Vec::new();
        let mut desc = Vec::new();
        for j in 0..rows {
            for v in [
                10.0 * j as f32 + i as f32,
                20.0 + j as f32,
                (j % POINTS) as f32 + 1.0,
                0.0,
            ] {
                kp.extend_from_slice(&v.to_le_bytes());
            }
            desc.extend(descriptor(j % POINTS, i));
        }
        db.execute(
            "INSERT INTO keypoints VALUES (?1, ?2, 4, ?3)",
            params![i, rows as i64, kp],
        )
        .unwrap();
        db.execute(
            "INSERT INTO descriptors VALUES (?1, ?2, 128, ?3)",
            params![i, rows as i64, desc],
        )
        .unwrap();
    }
}

struct Fixture {
    _dir: tempfile::TempDir,
    model: PathBuf,
    db: PathBuf,
    out: PathBuf,
}

fn fixture(keypoints_per_image: usize) -> Fixture {
    let dir = tempfile::tempdir().unwrap();
    let model_dir = dir.path().join("sparse");
    write_model(&model_dir, &model());
    let db = dir.path().join("database.db");
    write_database(&db, keypoints_per_image);
    let out = dir.path().join("m.sfpm");
    Fixture {
        model: model_dir,
        db,
        out,
        _dir: dir,
    }
}

fn options(db: &Path) -> ConvertOptions {
    ConvertOptions {
        database: Some(db.to_path_buf()),
        ..ConvertOptions::default()
    }
}

fn normalised(v: impl Iterator<Item = f32>) -> Vec<f32> {
    let v: Vec<f32> = v.collect();
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    v.iter().map(|x| x / n).collect()
}

/// The stored descriptor of every point of `level`, rotated back out of the level's basis.
fn unprojected(map: &Map<'_>, level: u16) -> Vec<Vec<f32>> {
    let l = map.level(level).unwrap();
    let (short, rest) = (l.desc_short().unwrap(), l.desc_rest().unwrap().unwrap());
    let p = l.projection().unwrap().unwrap();
    let (ds, df) = (l.dim_short(), l.dim_full());
    (0..l.len())
        .map(|r| {
            let stored: Vec<f32> = short[r * ds..(r + 1) * ds]
                .iter()
                .chain(&rest[r * (df - ds)..(r + 1) * (df - ds)])
                .map(|x| x.to_f32())
                .collect();
            (0..128)
                .map(|k| (0..df).map(|d| p[d * 128 + k] * stored[d]).sum())
                .collect()
        })
        .collect()
}

#[test]
fn mean_descriptors_levels_basis_and_visibility() {
    let f = fixture(POINTS + 1);
    let before = std::fs::read(&f.db).unwrap();
    let summary = convert(&f.model, &options(&f.db), &f.out, &Silent).unwrap();
    assert_eq!(std::fs::read(&f.db).unwrap(), before, "database modified");
    assert_eq!(
        (summary.points, summary.images, summary.observations),
        (POINTS, 3, 27)
    );
    assert_eq!(
        summary.levels.iter().map(|l| l.points).collect::<Vec<_>>(),
        vec![3, 3, 3]
    );
    let map = Map::open(&f.out).unwrap();
    map.verify().unwrap();
    assert!(!map.metadata().geometry_only);
    for level in 0..3u16 {
        let l = map.level(level).unwrap();
        let base = 3 * level as u32;
        assert_eq!(&*l.points().unwrap(), &[base, base + 1, base + 2]);
        assert_eq!((l.dim_full(), l.dim_short()), (128, 32));
        assert_eq!(l.info().descriptor, "sift");
        let range = l.info().extra["scale_range"].as_array().unwrap();
        assert_eq!(range[0].as_f64().unwrap(), f64::from(base + 1));
        for (r, got) in unprojected(&map, level).iter().enumerate() {
            let point = (base as usize) + r;
            let mut sum = vec![0.0f32; 128];
            for i in 1..=IMAGES {
                for (s, v) in sum.iter_mut().zip(normalised(
                    descriptor(point, i).iter().map(|&b| f32::from(b)),
                )) {
                    *s += v;
                }
            }
            let want = normalised(sum.into_iter());
            let err = got
                .iter()
                .zip(&want)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f32::max);
            assert!(err < 2e-3, "level {level} row {r}: max error {err}");
        }
    }
    let vis = map.visibility().unwrap().unwrap();
    assert_eq!(vis.points_of(1), &(0..9).collect::<Vec<u32>>()[..]);
    assert_eq!(vis.keypoints_of(2).unwrap()[4], [43.0, 24.0]);
    let images = map.images().unwrap().unwrap();
    assert_eq!(images.name(2).unwrap(), "img3.jpg");
    assert_eq!(images.poses[2], [1.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0]);
    assert_eq!(map.point_ids().unwrap().unwrap()[8], 108);
    let w = map.to_world(map.point_positions().unwrap()[8]);
    assert!((w[0] - 8.0).abs() < 1e-6 && (w[2] - 5.0).abs() < 1e-6);
    let sources = &map.metadata().provenance.sources;
    assert_eq!(sources.len(), 4, "3 model files and the database");
    assert!(sources.iter().all(|s| s.bytes > 0 && s.xxh3.len() == 16));
}

#[test]
fn medoid_picks_an_observation_and_short_dims_and_zstd_apply() {
    let f = fixture(POINTS);
    let opts = ConvertOptions {
        aggregate: Aggregate::Medoid,
        short_dims: Some(16),
        codec: Codec::Zstd,
        ..options(&f.db)
    };
    convert(&f.model, &opts, &f.out, &Silent).unwrap();
    let map = Map::open(&f.out).unwrap();
    map.verify().unwrap();
    assert!(map.sections().iter().any(|s| s.codec() == Codec::Zstd));
    for level in 0..3u16 {
        assert_eq!(map.level(level).unwrap().dim_short(), 16);
        for (r, got) in unprojected(&map, level).iter().enumerate() {
            let point = 3 * level as usize + r;
            let candidates: Vec<Vec<f32>> = (1..=IMAGES)
                .map(|i| normalised(descriptor(point, i).iter().map(|&b| f32::from(b))))
                .collect();
            let dist = |c: &Vec<f32>| {
                got.iter()
                    .zip(c)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max)
            };
            assert!(
                candidates.iter().any(|c| dist(c) < 2e-3),
                "level {level} row {r} is no observation"
            );
        }
    }
}

#[test]
fn geometry_only_without_database() {
    let f = fixture(POINTS);
    let summary = convert(&f.model, &ConvertOptions::default(), &f.out, &Silent).unwrap();
    assert!(summary.geometry_only && summary.levels.is_empty());
    let map = Map::open(&f.out).unwrap();
    assert!(map.metadata().geometry_only);
    assert_eq!(map.n_points(), POINTS as u64);
    assert!(map.level_ids().is_empty());
}

#[test]
fn missing_features_warn_or_fail_with_strict() {
    let f = fixture(POINTS + 1);
    Connection::open(&f.db)
        .unwrap()
        .execute("DELETE FROM descriptors WHERE image_id = 2", [])
        .unwrap();
    let summary = convert(&f.model, &options(&f.db), &f.out, &Silent).unwrap();
    assert_eq!(summary.images_without_features, 1);
    let strict = ConvertOptions {
        strict: true,
        ..options(&f.db)
    };
    std::fs::remove_file(&f.out).unwrap();
    let err = convert(&f.model, &strict, &f.out, &Silent).unwrap_err();
    assert!(matches!(err, ConvertError::MissingFeatures { .. }), "{err}");
    assert!(
        err.to_string().contains("img2.jpg") && err.to_string().contains("database.db"),
        "{err}"
    );
    assert!(!f.out.exists(), "nothing written on error");
}

#[test]
fn database_of_another_reconstruction_is_refused() {
    let f = fixture(POINTS + 1);
    Connection::open(&f.db)
        .unwrap()
        .execute(
            "UPDATE images SET name = 'other.jpg' WHERE image_id = 3",
            [],
        )
        .unwrap();
    let err = convert(&f.model, &options(&f.db), &f.out, &Silent).unwrap_err();
    assert!(
        matches!(err, ConvertError::NameMismatch { image_id: 3, .. }),
        "{err}"
    );
    Connection::open(&f.db)
        .unwrap()
        .execute("DELETE FROM images WHERE image_id = 3", [])
        .unwrap();
    let err = convert(&f.model, &options(&f.db), &f.out, &Silent).unwrap_err();
    assert!(err.to_string().contains("database.db"), "{err}");
}

#[test]
fn observation_beyond_the_database_keypoints_is_an_error() {
    let f = fixture(5);
    let err = convert(&f.model, &options(&f.db), &f.out, &Silent).unwrap_err();
    assert!(
        matches!(
            err,
            ConvertError::KeypointOutOfRange {
                keypoints: 5,
                point2d_idx: 5,
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn a_file_that_is_not_a_database_is_refused_with_its_name() {
    let f = fixture(POINTS);
    std::fs::write(
        &f.db,
        b"this is not sqlite at all, not even close; padding padding padding padding",
    )
    .unwrap();
    let err = convert(&f.model, &options(&f.db), &f.out, &Silent).unwrap_err();
    assert!(err.to_string().contains("database.db"), "{err}");
}

fn data() -> Option<PathBuf> {
    shared_data::shared_data("colmap")
}

#[test]
fn real_fixtures_convert_verify_and_slice() {
    let Some(data) = data() else { return };
    let tmp = tempfile::tempdir().unwrap();
    for (model, db, levels) in [
        (
            "bartoszek_test_colmap/sparse/0",
            Some("bartoszek_test_colmap/database.db"),
            3,
        ),
        (
            "kapture_maupertuis/reconstruction",
            Some("kapture_maupertuis/colmap.db"),
            3,
        ),
        ("gtsfm_lund_door/colmap_ground_truth", None, 0),
        ("yding121_video_frames/sparse/0", None, 0),
    ] {
        let db_copy = db.map(|d| {
            let copy = tmp.path().join("copy.db");
            std::fs::copy(data.join(d), &copy).unwrap();
            copy
        });
        let out = tmp.path().join("m.sfpm");
        let opts = ConvertOptions {
            database: db_copy.clone(),
            ..ConvertOptions::default()
        };
        let summary = convert(&data.join(model), &opts, &out, &Silent)
            .unwrap_or_else(|e| panic!("{model}: {e}"));
        assert_eq!(summary.levels.len(), levels, "{model}");
        assert!(summary.output_bytes < summary.input_bytes, "{model}");
        let map = Map::open(&out).unwrap();
        map.verify().unwrap();
        if levels > 0 {
            let (writer, _) = sfpmap::format::slice(
                &map,
                &sfpmap::format::SliceOptions {
                    levels: vec![2],
                    short: true,
                    codec: None,
                    zstd_level: 3,
                    minimal: false,
                },
            )
            .unwrap();
            let bytes = writer.to_bytes().unwrap();
            let sliced = Map::from_bytes(&bytes).unwrap();
            sliced.verify().unwrap();
            assert!(!sliced.level(2).unwrap().has_rest());
            assert!(
                bytes.len() < map.file_len() as usize / 3,
                "{model}: {} vs {}",
                bytes.len(),
                map.file_len()
            );
        }
    }
}

/// (issue 36) `--snap` and `--triangulate` together are refused by the library too (the CLI's
/// parser refuses them first), naming both, before any image is read; nothing is written.
#[test]
fn an_sfp_map_is_not_both_snapped_and_triangulated() {
    let Some(scene) = shared_data::shared_data("scenes/sacre-coeur") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("m.sfpm");
    let mut options = sfpmap::build::SfpMapOptions::new(scene.join("images"));
    options.snap = true;
    options.triangulate = true;
    let e = sfpmap::build::convert_with_images(&scene.join("sparse-map"), &options, &out, &Silent)
        .unwrap_err();
    assert!(matches!(e, ConvertError::Options(_)), "{e:?}");
    let message = e.to_string();
    assert!(
        message.contains("--snap") && message.contains("--triangulate"),
        "{message}"
    );
    assert!(!out.exists());
}

/// (issue 36) A level is a member where the query's detector would find it: sfp-v3's level 2
/// is detected on level 0's score map (`sfp.detect_level`), so its points are scored there and
/// are level 0's points; each level records its threshold, and `score_threshold` holds every
/// level to one.
#[cfg(feature = "onnx")]
#[test]
fn an_sfp_map_scores_each_level_on_the_map_it_is_detected_on() {
    let Some(scene) = shared_data::shared_data("scenes/sacre-coeur") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let convert = |model: &str, threshold: Option<f32>| {
        let out = tmp.path().join("m.sfpm");
        let mut options = sfpmap::build::SfpMapOptions::new(scene.join("images"));
        options.extractor.model = Some(model.into());
        options.score_threshold = threshold;
        let summary =
            sfpmap::build::convert_with_images(&scene.join("sparse-map"), &options, &out, &Silent)
                .unwrap();
        let map = Map::open(&out).unwrap();
        let recorded: Vec<f64> = (map.metadata().levels.iter())
            .map(|l| l.extra["score_threshold"].as_f64().unwrap())
            .collect();
        let points: Vec<usize> = summary.convert.levels.iter().map(|l| l.points).collect();
        (summary.score_thresholds, recorded, points)
    };
    let (own, recorded, points) = convert("sfp-v3", None);
    assert_eq!((own, recorded), (vec![0.5; 4], vec![0.5; 4]));
    assert_eq!(points[2], points[0], "{points:?}");
    // sfp-v2 (same network) scores level 2 on its own, coarser map: other points.
    let (_, _, v2) = convert("sfp-v2", None);
    assert_ne!(v2[2], points[2], "{v2:?} {points:?}");
    assert_eq!((v2[0], v2[1], v2[3]), (points[0], points[1], points[3]));
    let (one, recorded, low) = convert("sfp-v3", Some(0.2));
    assert_eq!((one, recorded), (vec![0.2; 4], vec![f64::from(0.2f32); 4]));
    assert!(low[2] > points[2] && low[2] == low[0], "{low:?} {points:?}");
}
