//! The generated street (`sfpmap::demo::street`) at a small size: its files are what COLMAP
//! tools read, it converts, and every query localizes within 0.5 m and 2° (issue 11's bar
//! for generated scenes).
#![cfg(feature = "demo")]

use sfpmap::build::{convert, ConvertOptions};
use sfpmap::demo::street::{write_street, StreetOptions};
use sfpmap::format::Map;
use sfpmap::format::Retrieval;
use sfpmap::io::poses::read_poses;
use sfpmap::io::queries::{read_query_list, DatabaseFeatures};
use sfpmap::localize::{
    LocalizationPath, LocalizeOptions, Localizer, RetrievalFallback, RetrievalMethod,
};
use sfpmap::session::{QuerySource, Session};

/// The small street both tests use: 12,000 points, 6 queries, seed 7.
fn small_street() -> StreetOptions {
    StreetOptions {
        points: 12_000,
        queries: 6,
        seed: 7,
        ..StreetOptions::default()
    }
}

#[test]
fn a_small_street_converts_and_every_query_localizes() {
    let dir = tempfile::tempdir().unwrap();
    let options = small_street();
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
        "sequence_gt.txt",
        "sequence.txt",
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
    assert_eq!(converted.vlad.map(|v| (v.level, v.dims)), Some((2, 32)));
    assert!(map.vlad().unwrap().is_some());
    let localizer = Localizer::new(&map, LocalizeOptions::default()).unwrap();
    // The brute-force reference: no retrieval, every point a candidate.
    let brute_force = Localizer::new(
        &map,
        LocalizeOptions {
            retrieval: RetrievalMethod::Off,
            ..LocalizeOptions::default()
        },
    )
    .unwrap();
    let queries = read_query_list(&dir.path().join("queries.txt"), None).unwrap();
    let truth = read_poses(&dir.path().join("gt_poses.txt")).unwrap();
    let features = DatabaseFeatures::open(&dir.path().join("queries.db")).unwrap();
    assert_eq!(queries.len(), 6);
    for (query, (name, gt)) in queries.iter().zip(&truth) {
        assert_eq!(&query.name, name);
        let f = features.features(name).unwrap().unwrap();
        for (r, narrowed) in [
            (localizer.localize(&f, &query.camera).unwrap(), true),
            (brute_force.localize(&f, &query.camera).unwrap(), false),
        ] {
            let pose = r
                .pose()
                .unwrap_or_else(|| panic!("{name}: {:?}", r.failure()));
            if narrowed {
                // A SIFT map retrieves with the VLAD convert stored.
                assert_eq!(r.retrieval, Some(Retrieval::Vlad), "{name}");
                assert_eq!(r.retrieval_fallback, None, "{name}");
                assert_eq!(r.retrieved_images, 10, "{name}");
            } else {
                assert_eq!(r.retrieval_fallback, Some(RetrievalFallback::Off));
            }
            assert_eq!(r.path, LocalizationPath::Retrieval);
            let (t, deg) = (pose.center_distance(gt), pose.rotation_error_deg(gt));
            assert!(t < 0.5 && deg < 2.0, "{name}: {t} m, {deg}°");
        }
    }

    // The walk along the pavement, in order: the first frame through retrieval, the others
    // tracked from the constant-velocity prediction, all within the bar.
    let frames = read_query_list(&dir.path().join("sequence.txt"), None).unwrap();
    let truth = read_poses(&dir.path().join("sequence_gt.txt")).unwrap();
    // The session reads each frame from the database and tracks the sequence.
    let sequence = Session::builder(std::sync::Arc::new(Map::open(&map_path).unwrap()), "street")
        .options(LocalizeOptions::default())
        .source(QuerySource::Database(dir.path().join("sequence.db")))
        .sequence(true)
        .build(&sfpmap::progress::Silent)
        .unwrap();
    let mut tracked = 0;
    for (i, (frame, (name, gt))) in frames.iter().zip(&truth).enumerate() {
        assert_eq!(&frame.name, name);
        assert_eq!(sequence.is_tracking(), i > 0, "{name}");
        let r = sequence.localize(name, &frame.camera).unwrap();
        let pose = r
            .pose()
            .unwrap_or_else(|| panic!("{name}: {:?}", r.failure()));
        let (t, deg) = (pose.center_distance(gt), pose.rotation_error_deg(gt));
        assert!(t < 0.5 && deg < 2.0, "{name}: {t} m, {deg}°");
        if i == 0 {
            assert_eq!(r.path, LocalizationPath::Retrieval, "{name}");
        }
        tracked += usize::from(r.path == LocalizationPath::Tracking);
    }
    assert_eq!(frames.len(), 6);
    assert_eq!(tracked, 5, "every frame after the first is tracked");
}

/// (1.3) An image index asked for on a small street (96 images, about 12 lists): with every list
/// probed, each query retrieves what ranking every image retrieves, and with the map's own
/// probe every query still localizes within the bar. (Which images a probe scores is the
/// unit tests' of `localize::retrieval`.)
#[test]
fn an_image_index_probed_whole_ranks_as_every_image_and_its_probe_localizes() {
    let dir = tempfile::tempdir().unwrap();
    write_street(dir.path(), &small_street()).unwrap();
    let map_path = dir.path().join("street.sfpm");
    let mut convert_options = ConvertOptions {
        database: Some(dir.path().join("database.db")),
        ..ConvertOptions::default()
    };
    convert_options.vlad.index_lists = Some(12);
    let converted = convert(
        &dir.path().join("sparse"),
        &convert_options,
        &map_path,
        &sfpmap::progress::Silent,
    )
    .unwrap();
    let index = converted.index.expect("an index asked for");
    // Lists are places grown along the image neighbours to 96 / 12 = 8 images: about 12
    // (a short place left at a street's end joins its neighbour's).
    assert!(
        index.stored && (9..=12).contains(&index.lists) && index.of == Retrieval::Vlad,
        "{index:?}"
    );
    let map = Map::open(&map_path).unwrap();
    let stored = map.image_index().unwrap().unwrap();
    assert_eq!((stored.lists(), stored.probe), (index.lists, index.probe));
    assert!(stored.neighbours.is_some());
    // The lists are places (k-means would also make 12).
    let rule = map.metadata().image_index.as_ref().unwrap().extra["rule"]
        .as_str()
        .unwrap();
    assert!(rule.starts_with("neighbours:"), "{rule}");

    let queries = read_query_list(&dir.path().join("queries.txt"), None).unwrap();
    let truth = read_poses(&dir.path().join("gt_poses.txt")).unwrap();
    let features = DatabaseFeatures::open(&dir.path().join("queries.db")).unwrap();
    // top_k 2: 16 images scored at least, a sixth of the map, so the lists are probed.
    let localizer = |probe| {
        let options = LocalizeOptions {
            top_k: 2,
            retrieval_probe: probe,
            ..LocalizeOptions::default()
        };
        Localizer::new(&map, options).unwrap()
    };
    let (exhaustive, whole, own) = (
        localizer(Some(0)),
        localizer(Some(index.lists)),
        localizer(None),
    );
    for (query, (name, gt)) in queries.iter().zip(&truth) {
        let f = features.features(name).unwrap().unwrap();
        let every = exhaustive.localize(&f, &query.camera).unwrap();
        let probed_whole = whole.localize(&f, &query.camera).unwrap();
        assert_eq!(probed_whole.retrieved, every.retrieved, "{name}");
        let r = own.localize(&f, &query.camera).unwrap();
        assert_eq!(r.retrieved.len(), 2, "{name}");
        let pose = r
            .pose()
            .unwrap_or_else(|| panic!("{name}: {:?}", r.failure()));
        let (t, deg) = (pose.center_distance(gt), pose.rotation_error_deg(gt));
        assert!(t < 0.5 && deg < 2.0, "{name}: {t} m, {deg}°");
    }
}
