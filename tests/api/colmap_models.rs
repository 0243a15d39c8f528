//! COLMAP model reading on the real fixtures in `../shared/data/colmap/` and on synthetic
//! models the tests write themselves.
#![cfg(feature = "colmap")]

use crate::shared_data;

use std::path::{Path, PathBuf};

use sfpmap::colmap::{
    self, bin, text, Camera, Error, Image, ModelFormat, Point2D, Reconstruction, TrackElement,
};
use sfpmap::geometry::{CameraModel, Pose};

fn data_root() -> Option<PathBuf> {
    shared_data::shared_data("colmap")
}

/// (model folder relative to the data root, images, points3D, observations, format).
const FIXTURES: [(&str, usize, usize, usize, ModelFormat); 5] = [
    (
        "bartoszek_test_colmap/sparse/0",
        23,
        1443,
        5931,
        ModelFormat::Binary,
    ),
    (
        "bartoszek_test_colmap/dense/0/sparse",
        23,
        1443,
        5931,
        ModelFormat::Binary,
    ),
    (
        "kapture_maupertuis/reconstruction",
        4,
        1039,
        3355,
        ModelFormat::Text,
    ),
    (
        "gtsfm_lund_door/colmap_ground_truth",
        12,
        11384,
        73327,
        ModelFormat::Text,
    ),
    (
        "yding121_video_frames/sparse/0",
        7,
        699,
        2616,
        ModelFormat::Binary,
    ),
];

#[test]
fn fixtures_load_with_the_documented_counts() {
    let Some(root) = data_root() else { return };
    for (dir, images, points, observations, format) in FIXTURES {
        let dir = root.join(dir);
        assert_eq!(
            colmap::model_files(&dir).unwrap().format,
            format,
            "{}",
            dir.display()
        );
        let model = colmap::read_model(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        assert_eq!(model.images().len(), images, "{}", dir.display());
        assert_eq!(model.points3d().len(), points, "{}", dir.display());
        assert_eq!(model.num_observations(), observations, "{}", dir.display());
        let track_sum: usize = model.points3d().iter().map(|p| model.track(p).len()).sum();
        assert_eq!(track_sum, observations);
        // Sorted by id, lookups agree.
        assert!(model.points3d().windows(2).all(|w| w[0].id < w[1].id));
        for p in model.points3d().iter().step_by(97) {
            assert_eq!(model.point3d(p.id), Some(p));
        }
        for (index, image) in model.images().iter().enumerate() {
            assert_eq!(model.image_index(image.id), Some(index));
        }
        assert_eq!(model.point3d(u64::MAX), None);
    }
}

#[test]
fn fixture_details_match_source_md() {
    let Some(root) = data_root() else { return };
    let model = colmap::read_model(&root.join("kapture_maupertuis/reconstruction")).unwrap();
    let camera = model.camera(1).unwrap();
    assert_eq!(camera.model, CameraModel::SimplePinhole);
    assert_eq!((camera.width, camera.height), (1919, 1079));
    assert_eq!(camera.params, vec![1847.53, 959.5, 539.5]);
    let total2d: usize = model.images().iter().map(|i| i.points2d.len()).sum();
    assert_eq!(total2d, 24010);
    assert_eq!(model.image(4).unwrap().name, "03.jpg");

    let model = colmap::read_model(&root.join("gtsfm_lund_door/colmap_ground_truth")).unwrap();
    let total2d: usize = model.images().iter().map(|i| i.points2d.len()).sum();
    assert_eq!(total2d, 95144);
    assert_eq!(model.cameras()[0].model, CameraModel::SimpleRadial);

    let model = colmap::read_model(&root.join("bartoszek_test_colmap/sparse/0")).unwrap();
    assert_eq!(model.cameras().len(), 23);
    assert!(model
        .cameras()
        .iter()
        .all(|c| c.model == CameraModel::SimpleRadial));
    let total2d: usize = model.images().iter().map(|i| i.points2d.len()).sum();
    assert_eq!(total2d, 16646);
    let dense = colmap::read_model(&root.join("bartoszek_test_colmap/dense/0/sparse")).unwrap();
    assert!(dense
        .cameras()
        .iter()
        .all(|c| c.model == CameraModel::Pinhole));
    assert_eq!(dense.points3d(), model.points3d());

    let model = colmap::read_model(&root.join("yding121_video_frames/sparse/0")).unwrap();
    let total2d: usize = model.images().iter().map(|i| i.points2d.len()).sum();
    assert_eq!(total2d, 34510);
}

#[test]
fn scenes_with_rig_files_load() {
    let Some(root) = data_root() else { return };
    let scenes = root.join("../scenes");
    for scene in ["sacre-coeur", "south-building"] {
        for model in ["sparse-map", "sparse-full"] {
            let dir = scenes.join(scene).join(model);
            if !dir.is_dir() {
                continue;
            }
            assert!(dir.join("rigs.bin").is_file());
            let m = colmap::read_model(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
            assert!(!m.points3d().is_empty());
        }
    }
}

/// pycolmap's message for each malformed model: `(A vs. B)`, A on the 2D point, B the 3D point.
#[test]
fn malformed_models_fail_like_pycolmap() {
    let Some(root) = data_root() else { return };
    let malformed = root.join("malformed");
    let expected = std::fs::read_to_string(malformed.join("pycolmap_errors.txt")).unwrap();
    let mut n = 0;
    for line in expected.lines().filter(|l| !l.trim().is_empty()) {
        let (dir, message) = line.split_once(": ").unwrap();
        let vs = &message[message.rfind('(').unwrap()..];
        let err = colmap::read_model(&malformed.join(dir)).unwrap_err();
        assert!(matches!(err, Error::TrackMismatch { .. }), "{dir}: {err:?}");
        let shown = err.to_string();
        assert!(shown.contains("inconsistent track"), "{shown}");
        assert!(shown.contains("points3D.txt"), "{shown}");
        assert!(shown.ends_with(vs), "{dir}: {shown} should end with {vs}");
        n += 1;
    }
    assert_eq!(n, 17);
}

fn truncations(path: &Path, parse: impl Fn(&[u8]) -> Result<(), Error>) {
    // The whole files parse: `fixtures_load_with_the_documented_counts`.
    let data = std::fs::read(path).unwrap();
    // Every length near the start and the end, a stride in between: the records are
    // small and regular, so this reaches every field kind in many records.
    let step = (data.len() / 300).max(1);
    let lengths = (0..data.len().min(256))
        .chain((256..data.len()).step_by(step))
        .chain(data.len().saturating_sub(256)..data.len());
    for len in lengths {
        match parse(&data[..len]) {
            Err(Error::Truncated { .. }) => {}
            other => panic!("{} cut at {len}: {other:?}", path.display()),
        }
    }
}

#[test]
fn every_truncation_of_a_real_bin_file_errors() {
    let Some(root) = data_root() else { return };
    for dir in [
        "bartoszek_test_colmap/sparse/0",
        "yding121_video_frames/sparse/0",
    ] {
        let dir = root.join(dir);
        let name = Path::new("x.bin");
        truncations(&dir.join("cameras.bin"), |d| {
            bin::parse_cameras(d, name).map(drop)
        });
        truncations(&dir.join("images.bin"), |d| {
            bin::parse_images(d, name).map(drop)
        });
        // Without cameras and images the points parse fully before validation fails, so a
        // cut file must give Truncated; this keeps each try from reparsing images.bin.
        let empty = 0u64.to_le_bytes();
        truncations(&dir.join("points3D.bin"), |d| {
            bin::parse_model((&empty, name), (&empty, name), (d, name)).map(drop)
        });
    }
}

#[test]
fn trailing_bytes_and_unknown_model_id_error() {
    let Some(root) = data_root() else { return };
    let path = root.join("yding121_video_frames/sparse/0/cameras.bin");
    let mut data = std::fs::read(&path).unwrap();
    data.push(0);
    let err = bin::parse_cameras(&data, &path).unwrap_err();
    assert!(matches!(err, Error::TrailingBytes { .. }), "{err}");
    data.pop();
    // The first camera's model id sits after the count (8) and the camera id (4).
    data[12..16].copy_from_slice(&99i32.to_le_bytes());
    let err = bin::parse_cameras(&data, &path).unwrap_err();
    assert!(
        matches!(err, Error::UnknownCameraModelId { model_id: 99, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("unknown camera model id 99"));
    assert!(err.to_string().contains("cameras.bin"));
}

#[test]
fn a_bad_text_line_reports_file_and_line() {
    let path = Path::new("sparse/points3D.txt");
    let data = b"# comment\n\n1 0 0 0 1 2 3 0.5\n2 0 0 zero 1 2 3 0.5\n";
    let err = text::parse_model((b"", path), (b"", path), (data, path)).unwrap_err();
    assert!(matches!(err, Error::BadLine { line: 4, .. }), "{err:?}");
    assert_eq!(
        err.to_string(),
        "sparse/points3D.txt:4: bad point3D coordinate \"zero\""
    );

    let err = text::parse_cameras(b"1 PINHOLE 10 10 1 2 3\n", Path::new("c.txt")).unwrap_err();
    assert_eq!(
        err.to_string(),
        "c.txt:1: camera 1: model PINHOLE takes 4 parameters, found 3"
    );
    let err = text::parse_cameras(b"#\n1 PINHOL 10 10 1 2 3\n", Path::new("c.txt")).unwrap_err();
    assert_eq!(err.to_string(), "c.txt:2: unknown camera model \"PINHOL\"");
    let err =
        text::parse_images(b"1 1 0 0 0 0 0 0 1 a.jpg\n1 2\n", Path::new("i.txt")).unwrap_err();
    assert!(matches!(err, Error::BadLine { line: 2, .. }), "{err}");
    let err =
        text::parse_images(b"1 1 0 0 0 0 0 0 1 a.jpg\n1 2 -2\n", Path::new("i.txt")).unwrap_err();
    assert_eq!(err.to_string(), "i.txt:2: bad point3D id \"-2\"");
}

#[test]
fn missing_files_and_folders() {
    let tmp = tempfile::tempdir().unwrap();
    let err = colmap::read_model(tmp.path()).unwrap_err();
    assert!(matches!(err, Error::NoModel { .. }), "{err}");
    let err = colmap::read_model(&tmp.path().join("absent")).unwrap_err();
    assert!(matches!(err, Error::Io { .. }), "{err}");
    std::fs::write(tmp.path().join("cameras.bin"), 0u64.to_le_bytes()).unwrap();
    std::fs::write(tmp.path().join("images.bin"), 0u64.to_le_bytes()).unwrap();
    let err = colmap::read_model(tmp.path()).unwrap_err();
    match &err {
        Error::MissingFile { path } => assert!(path.ends_with("points3D.bin")),
        _ => panic!("{err}"),
    }
    std::fs::write(tmp.path().join("points3D.bin"), 0u64.to_le_bytes()).unwrap();
    let model = colmap::read_model(tmp.path()).unwrap();
    assert!(model.images().is_empty());
}

fn camera(id: u32) -> Camera {
    Camera {
        id,
        model: CameraModel::SimpleRadial,
        width: 640,
        height: 480,
        params: vec![500.0, 320.0, 240.0, -0.01],
    }
}

/// A small model with awkward values: unsorted ids, id 0, a huge point id, a 2D point
/// without a 3D point, subnormal and negative numbers, a name with a space.
fn synthetic() -> Reconstruction {
    let mut b = Reconstruction::builder();
    b.add_camera(camera(7));
    b.add_camera(Camera {
        id: 0,
        model: CameraModel::RadTanThinPrismFisheye,
        width: 1,
        height: 2,
        params: (0..16).map(|i| f64::from(i) * 0.1 - 0.7).collect(),
    });
    let pose = Pose::from_colmap_array([0.5, -0.5, 0.5, 0.5, 1e-300, -2.5, 3.0]).unwrap();
    let p2 = |x: f64, id: Option<u64>| Point2D {
        xy: [x, x * 0.5 + 0.25],
        point3d_id: id,
    };
    b.add_image(Image {
        id: 3,
        name: "sub dir/image 3.jpg".into(),
        camera_id: 7,
        cam_from_world: pose,
        points2d: vec![p2(1.5, Some(u64::MAX - 1)), p2(2.0, None), p2(3.0, Some(0))],
    });
    b.add_image(Image {
        id: 1,
        name: "a.jpg".into(),
        camera_id: 0,
        cam_from_world: pose,
        points2d: vec![p2(0.1, Some(0))],
    });
    b.add_image(Image {
        id: 2,
        name: "b.jpg".into(),
        camera_id: 0,
        cam_from_world: pose,
        points2d: vec![],
    });
    let el = |image_id, point2d_idx| TrackElement {
        image_id,
        point2d_idx,
    };
    b.add_point3d(u64::MAX - 1, [1.0, 2.0, 3.0], [255, 0, 7], 0.5, &[el(3, 0)])
        .unwrap();
    b.add_point3d(
        0,
        [-1.0, 5e-324, 1e300],
        [1, 2, 3],
        0.0,
        &[el(3, 2), el(1, 0)],
    )
    .unwrap();
    b.add_point3d(5, [0.0; 3], [0; 3], 1.0, &[]).unwrap();
    b.build().unwrap()
}

fn write_model(dir: &Path, model: &Reconstruction) {
    std::fs::write(dir.join("cameras.bin"), bin::write_cameras(model)).unwrap();
    std::fs::write(dir.join("images.bin"), bin::write_images(model)).unwrap();
    std::fs::write(dir.join("points3D.bin"), bin::write_points3d(model)).unwrap();
    std::fs::write(dir.join("cameras.txt"), text::write_cameras(model)).unwrap();
    std::fs::write(dir.join("images.txt"), text::write_images(model)).unwrap();
    std::fs::write(dir.join("points3D.txt"), text::write_points3d(model)).unwrap();
}

#[test]
fn synthetic_model_round_trips_through_bin_and_txt() {
    let model = synthetic();
    assert_eq!(
        model.images().iter().map(|i| i.id).collect::<Vec<_>>(),
        [1, 2, 3]
    );
    assert_eq!(model.point3d(0).map(|p| model.track(p).len()), Some(2));
    // Images have dense ids (table lookups), points sparse ones (binary search).
    assert_eq!(model.image_index(2), Some(1));
    assert_eq!(
        (model.image(0), model.image(4), model.image(u32::MAX)),
        (None, None, None)
    );
    assert_eq!(model.point3d_index(u64::MAX - 1), Some(2));
    assert_eq!((model.point3d(4), model.point3d(u64::MAX)), (None, None));
    let tmp = tempfile::tempdir().unwrap();
    write_model(tmp.path(), &model);
    assert_eq!(
        colmap::model_files(tmp.path()).unwrap().format,
        ModelFormat::Both
    );
    let from_bin = colmap::read_model_bin(tmp.path()).unwrap();
    let from_txt = colmap::read_model_text(tmp.path()).unwrap();
    assert_eq!(from_bin, model);
    assert_eq!(from_txt, model);
    assert_eq!(colmap::read_model(tmp.path()).unwrap(), model);
}

#[test]
fn real_models_round_trip_through_text() {
    let Some(root) = data_root() else { return };
    let model = colmap::read_model(&root.join("yding121_video_frames/sparse/0")).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    write_model(tmp.path(), &model);
    assert_eq!(colmap::read_model_text(tmp.path()).unwrap(), model);
    // Re-encoding reproduces COLMAP's bytes: the layout is the same, nothing is lost.
    let dir = root.join("yding121_video_frames/sparse/0");
    assert_eq!(
        bin::write_cameras(&model),
        std::fs::read(dir.join("cameras.bin")).unwrap()
    );
    assert_eq!(
        bin::write_images(&model),
        std::fs::read(dir.join("images.bin")).unwrap()
    );
}

#[test]
fn bin_and_txt_that_disagree_error() {
    let model = synthetic();
    let tmp = tempfile::tempdir().unwrap();
    write_model(tmp.path(), &model);
    // Drop point 5 (the one with an empty track) from the text model.
    let txt = text::write_points3d(&model);
    let cut: Vec<&str> = txt.lines().filter(|l| !l.starts_with("5 ")).collect();
    std::fs::write(tmp.path().join("points3D.txt"), cut.join("\n")).unwrap();
    let err = colmap::read_model(tmp.path()).unwrap_err();
    assert!(matches!(err, Error::ModelsDisagree { .. }), "{err}");
    assert!(err.to_string().contains("3 vs. 2 point3Ds"), "{err}");
}

fn build_error(edit: impl FnOnce(&mut Vec<Image>, &mut Vec<Camera>)) -> Error {
    let model = synthetic();
    let mut images = model.images().to_vec();
    let mut cameras = model.cameras().to_vec();
    edit(&mut images, &mut cameras);
    let mut b = Reconstruction::builder();
    cameras.into_iter().for_each(|c| b.add_camera(c));
    images.into_iter().for_each(|i| b.add_image(i));
    for p in model.points3d() {
        b.add_point3d(p.id, p.xyz, p.rgb, p.error, model.track(p))
            .unwrap();
    }
    b.build().unwrap_err()
}

#[test]
fn each_consistency_check_fires() {
    let err = build_error(|_, c| c.retain(|c| c.id != 7));
    assert!(
        matches!(
            err,
            Error::MissingCamera {
                image_id: 3,
                camera_id: 7,
                ..
            }
        ),
        "{err}"
    );
    let err = build_error(|_, c| c[0].params.pop().map(drop).unwrap_or(()));
    assert!(
        matches!(
            err,
            Error::ParamCount {
                expected: 16,
                found: 15,
                ..
            }
        ),
        "{err}"
    );
    let err = build_error(|_, c| c.push(camera(7)));
    assert!(
        matches!(
            err,
            Error::DuplicateId {
                kind: "camera",
                id: 7,
                ..
            }
        ),
        "{err}"
    );
    let err = build_error(|i, _| i.retain(|i| i.id != 1));
    assert!(
        matches!(err, Error::TrackImageMissing { image_id: 1, .. }),
        "{err}"
    );
    let err = build_error(|i, _| i[2].points2d.truncate(2));
    assert!(
        matches!(
            err,
            Error::TrackPoint2DOutOfRange {
                num_points2d: 2,
                point2d_idx: 2,
                ..
            }
        ),
        "{err}"
    );
    let err = build_error(|i, _| i[2].points2d[2].point3d_id = None);
    assert!(
        matches!(err, Error::TrackMismatch { found: None, .. }),
        "{err}"
    );
    let err = build_error(|i, _| i[2].points2d[1].point3d_id = Some(5));
    assert!(
        matches!(
            err,
            Error::Point2DNotInTrack {
                point3d_id: 5,
                point3d_exists: true,
                ..
            }
        ),
        "{err}"
    );
    let err = build_error(|i, _| i[2].points2d[1].point3d_id = Some(6));
    assert!(
        matches!(
            err,
            Error::Point2DNotInTrack {
                point3d_exists: false,
                ..
            }
        ),
        "{err}"
    );
    let err = build_error(|i, _| {
        let dup = i[0].clone();
        i.push(dup)
    });
    assert!(
        matches!(err, Error::DuplicateId { kind: "image", .. }),
        "{err}"
    );

    let mut b = Reconstruction::builder();
    b.add_camera(camera(1));
    b.add_image(Image {
        id: 1,
        name: "x".into(),
        camera_id: 1,
        cam_from_world: Pose::from_colmap_array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).unwrap(),
        points2d: vec![Point2D {
            xy: [0.0; 2],
            point3d_id: Some(9),
        }],
    });
    let el = TrackElement {
        image_id: 1,
        point2d_idx: 0,
    };
    b.add_point3d(9, [0.0; 3], [0; 3], 0.0, &[el, el]).unwrap();
    let err = b.build().unwrap_err();
    assert!(matches!(err, Error::DuplicateTrackElement { .. }), "{err}");
}

#[test]
fn camera_models_match_colmap() {
    let expected = [
        ("SIMPLE_PINHOLE", 3),
        ("PINHOLE", 4),
        ("SIMPLE_RADIAL", 4),
        ("RADIAL", 5),
        ("OPENCV", 8),
        ("OPENCV_FISHEYE", 8),
        ("FULL_OPENCV", 12),
        ("FOV", 5),
        ("SIMPLE_RADIAL_FISHEYE", 4),
        ("RADIAL_FISHEYE", 5),
        ("THIN_PRISM_FISHEYE", 12),
        ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
        ("SIMPLE_DIVISION", 4),
        ("DIVISION", 5),
        ("SIMPLE_FISHEYE", 3),
        ("FISHEYE", 4),
        ("EUCM", 6),
        ("EQUIRECTANGULAR", 2),
    ];
    assert_eq!(CameraModel::ALL.len(), expected.len());
    for (id, (name, n)) in expected.into_iter().enumerate() {
        let model = CameraModel::from_id(id as i32).unwrap();
        assert_eq!(
            (model.name(), model.num_params(), model.id()),
            (name, n, id as i32)
        );
        assert_eq!(CameraModel::from_name(name), Some(model));
    }
    assert_eq!(CameraModel::from_id(18), None);
}

#[test]
fn fuzz_entry_points_take_anything() {
    let mut seed = 0x9e3779b97f4a7c15u64;
    let mut next = || {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        seed
    };
    let model = synthetic();
    let bins = [
        bin::write_cameras(&model),
        bin::write_images(&model),
        bin::write_points3d(&model),
    ];
    let txts = [
        text::write_cameras(&model).into_bytes(),
        text::write_images(&model).into_bytes(),
        text::write_points3d(&model).into_bytes(),
    ];
    // Whole models in the layout the entry points split: u16 BE lengths, then the files.
    let whole = |files: &[Vec<u8>; 3]| {
        let mut out = Vec::new();
        out.extend_from_slice(&(files[0].len() as u16).to_be_bytes());
        out.extend_from_slice(&(files[1].len() as u16).to_be_bytes());
        files.iter().for_each(|f| out.extend_from_slice(f));
        out
    };
    let wholes = [whole(&bins), whole(&txts)];
    for base in bins.iter().chain(&txts).chain(&wholes) {
        for _ in 0..300 {
            let mut data = base.clone();
            for _ in 0..1 + next() % 4 {
                if data.is_empty() {
                    break;
                }
                let at = (next() % data.len() as u64) as usize;
                data[at] = next() as u8;
            }
            sfpmap::fuzzing::read_colmap_bin(&data);
            sfpmap::fuzzing::read_colmap_txt(&data);
        }
    }
}

#[test]
fn types_cross_threads() {
    fn send_sync<T: Send + Sync + 'static>() {}
    fn send<T: Send + 'static>() {}
    send_sync::<Error>();
    send_sync::<Reconstruction>();
    // rusqlite connections are Send but not Sync: one database per thread.
    send::<colmap::Database>();
    // The error converts into boxed errors (and so into anyhow in the CLI).
    let boxed: Box<dyn std::error::Error + Send + Sync> = Error::NoModel {
        dir: PathBuf::from("x"),
    }
    .into();
    assert_eq!(
        boxed.to_string(),
        "x: no COLMAP model (neither cameras.bin, images.bin, points3D.bin nor the .txt files)"
    );
}

#[test]
fn text_with_crlf_and_bad_utf8() {
    let Some(root) = data_root() else { return };
    let dir = root.join("kapture_maupertuis/reconstruction");
    let model = colmap::read_model(&dir).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    for name in ["cameras.txt", "images.txt", "points3D.txt"] {
        let text = std::fs::read_to_string(dir.join(name)).unwrap();
        std::fs::write(tmp.path().join(name), text.replace('\n', "\r\n")).unwrap();
    }
    assert_eq!(colmap::read_model(tmp.path()).unwrap(), model);

    let err =
        text::parse_images(b"1 1 0 0 0 0 0 0 1 caf\xe9.jpg\n\n", Path::new("i.txt")).unwrap_err();
    assert_eq!(
        err.to_string(),
        "i.txt:1: invalid utf-8 at byte 21 of the line"
    );
}
