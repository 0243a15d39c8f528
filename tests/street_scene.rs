//! The generated street (`sfpmap::demo::street`) at a small size: its files are what COLMAP
//! tools read, it converts, and every query localizes within 0.5 m and 2° (issue 11's bar
//! for generated scenes).
#![cfg(all(feature = "colmap", feature = "localize", feature = "onnx"))]

use sfpmap::build::{convert, ConvertOptions};
use sfpmap::demo::street::{write_street, StreetOptions};
use sfpmap::format::Map;
use sfpmap::io::poses::read_poses;
use sfpmap::io::queries::{read_query_list, DatabaseFeatures};
use sfpmap::localize::{LocalizeOptions, Localizer, RetrievalFallback};

#[test]
fn a_small_street_converts_and_every_query_localizes() {
    let dir = tempfile::tempdir().unwrap();
    let options = StreetOptions {
        points: 12_000,
        queries: 6,
        seed: 7,
        ..StreetOptions::default()
    };
    let summary = write_street(dir.path(), &options).unwrap();
    assert_eq!(summary.queries, 6);
    assert!(summary.images >= 80, "{summary:?}");
    // Thinning and the two-view rule keep most façade points, each seen many times.
    assert!(summary.points > 4_000, "{summary:?}");
    assert!(summary.observations > 10 * summary.points, "{summary:?}");

    // The same seed writes the same files.
    let again = tempfile::tempdir().unwrap();
    write_street(again.path(), &options).unwrap();
    for f in [
        "sparse/images.bin",
        "sparse/points3D.bin",
        "gt_poses.txt",
        "queries.txt",
    ] {
        assert_eq!(
            std::fs::read(dir.path().join(f)).unwrap(),
            std::fs::read(again.path().join(f)).unwrap(),
            "{f}"
        );
    }

    let model = sfpmap::colmap::read_model(&dir.path().join("sparse")).unwrap();
    assert_eq!(model.points3d().len(), summary.points);
    let map_path = dir.path().join("street.sfpm");
    let convert_options = ConvertOptions {
        database: Some(dir.path().join("database.db")),
        ..ConvertOptions::default()
    };
    let converted = convert(
        &dir.path().join("sparse"),
        &convert_options,
        &map_path,
        &sfpmap::progress::Silent,
    )
    .unwrap();
    assert_eq!(converted.images_without_features, 0);
    assert_eq!(converted.points, summary.points);

    let map = Map::open(&map_path).unwrap();
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    let queries = read_query_list(&dir.path().join("queries.txt"), None).unwrap();
    let truth = read_poses(&dir.path().join("gt_poses.txt")).unwrap();
    let features = DatabaseFeatures::open(&dir.path().join("queries.db")).unwrap();
    assert_eq!(queries.len(), 6);
    for (query, (name, gt)) in queries.iter().zip(&truth) {
        assert_eq!(&query.name, name);
        let f = features.features(name).unwrap().unwrap();
        let r = localizer.localize(&f, &query.camera).unwrap();
        let pose = r
            .pose()
            .unwrap_or_else(|| panic!("{name}: {:?}", r.failure()));
        // A SIFT map: no retrieval, and the localizer says so.
        assert_eq!(
            r.retrieval_fallback,
            Some(RetrievalFallback::NoMapDescriptors)
        );
        let (t, deg) = (pose.center_distance(gt), pose.rotation_error_deg(gt));
        assert!(t < 0.5 && deg < 2.0, "{name}: {t} m, {deg}°");
    }
}
