//! `session::Session` on the synthetic map of `localize.rs`: options refused in one place,
//! a sequence that tracks, features of another model refused, handed-in features read by
//! name refused.
#![cfg(feature = "localize")]

use crate::localize::{map_bytes, query, scene, DIM};
use crate::synthetic_scene::truth;
use sfpmap::format::Map;
use sfpmap::localize::{FeatureModel, LocalizationPath, LocalizeOptions, MatchOptions};
use sfpmap::progress::Silent;
use sfpmap::session::{QuerySource, Session, SessionError};
use std::sync::Arc;

/// The synthetic map, written to a file and opened (a session's map is `'static`).
fn map() -> (tempfile::TempDir, Arc<Map<'static>>) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.sfpm");
    std::fs::write(&path, map_bytes(&scene())).unwrap();
    let map = Arc::new(Map::open(&path).unwrap());
    (dir, map)
}

fn build(map: &Arc<Map<'static>>, options: LocalizeOptions) -> Result<Session, SessionError> {
    Session::builder(map.clone(), "m.sfpm")
        .options(options)
        .build(&Silent)
}

#[test]
fn options_out_of_range_are_refused_with_one_message_before_any_file_is_opened() {
    let (_dir, map) = map();
    let base = LocalizeOptions::default();
    let ratio = |ratio| LocalizeOptions {
        matching: MatchOptions {
            ratio,
            ..base.matching
        },
        ..base.clone()
    };
    let cases = [
        (ratio(1.5), "m.sfpm: ratio 1.5: a ratio in (0, 1]"),
        (ratio(0.0), "m.sfpm: ratio 0: a ratio in (0, 1]"),
        (
            LocalizeOptions {
                top_k: 0,
                ..base.clone()
            },
            "m.sfpm: top_k 0: 1 to 100000 images",
        ),
        (
            LocalizeOptions {
                gate_px: f64::NAN,
                ..base.clone()
            },
            "m.sfpm: gate_px NaN: a finite number of pixels > 0",
        ),
        (
            LocalizeOptions {
                min_inliers: usize::MAX,
                ..base.clone()
            },
            "m.sfpm: min_inliers 18446744073709551615: 4 to 1000000 inliers",
        ),
    ];
    for (options, expected) in cases {
        // The database does not exist: the options are refused first.
        let built = Session::builder(map.clone(), "m.sfpm")
            .options(options)
            .source(QuerySource::Database("/nonexistent/queries.db".into()))
            .build(&Silent);
        let Err(e) = built else {
            panic!("{expected}: not refused")
        };
        assert_eq!(e.to_string(), expected);
    }
}

#[test]
fn a_sequence_tracks_from_its_second_query_and_restarts_after_a_reset() {
    let (_dir, map) = map();
    let s = scene();
    let session = Session::builder(map.clone(), "m.sfpm")
        .sequence(true)
        .build(&Silent)
        .unwrap();
    let q = query(&s, &truth(), 50, DIM);
    assert!(session.is_sequence() && !session.is_tracking());
    let first = session.localize_features(&q, &s.camera, "q0").unwrap();
    assert_eq!(first.path, LocalizationPath::Retrieval);
    assert!(first.pose().unwrap().center_distance(&truth()) < 0.05);
    assert!(session.is_tracking());
    let second = session.localize_features(&q, &s.camera, "q1").unwrap();
    assert_eq!(
        second.path,
        LocalizationPath::Tracking,
        "{:?}",
        second.tracking_lost
    );
    assert!(second.pose().unwrap().center_distance(&truth()) < 0.05);
    session.reset_tracking();
    assert!(!session.is_tracking());
    let third = session.localize_features(&q, &s.camera, "q2").unwrap();
    assert_eq!(third.path, LocalizationPath::Retrieval);

    // Outside a sequence nothing is tracked.
    let once = build(&map, LocalizeOptions::default()).unwrap();
    for name in ["a", "b"] {
        let r = once.localize_features(&q, &s.camera, name).unwrap();
        assert_eq!(r.path, LocalizationPath::Retrieval);
    }
    assert!(!once.is_tracking());
}

#[test]
fn features_of_another_model_are_refused_and_unknown_ones_are_taken() {
    let (_dir, map) = map();
    let s = scene();
    let session = build(&map, LocalizeOptions::default()).unwrap();
    let mut q = query(&s, &truth(), 0, DIM);
    // The synthetic map's descriptors are "test"; it records no model hash.
    q.model = Some(FeatureModel {
        name: "sfp-v2".into(),
        xxh3: None,
    });
    let Err(e) = session.localize_features(&q, &s.camera, "q.jpg") else {
        panic!("features of another model taken")
    };
    assert!(matches!(e, SessionError::Mismatch(_)), "{e:?}");
    // A frame handed in is checked the same way.
    let frame = sfpmap::session::Frame::new(q.clone());
    let Err(again) = session.localize_frame(frame, &s.camera, "q.jpg") else {
        panic!("a frame of another model taken")
    };
    assert_eq!(again.to_string(), e.to_string());
    let text = e.to_string();
    assert!(
        text.contains("\"sfp-v2\"") && text.contains("\"test\"") && text.contains("m.sfpm"),
        "{text}"
    );
    q.model = Some(FeatureModel {
        name: "test".into(),
        xxh3: Some("0123456789abcdef".into()),
    });
    assert!(session
        .localize_features(&q, &s.camera, "q.jpg")
        .unwrap()
        .pose()
        .is_some());
    q.model = None;
    assert!(session
        .localize_features(&q, &s.camera, "q.jpg")
        .unwrap()
        .pose()
        .is_some());
}

#[test]
fn a_session_of_handed_in_features_reads_no_query_by_name() {
    let (_dir, map) = map();
    let s = scene();
    let session = build(&map, LocalizeOptions::default()).unwrap();
    let Err(e) = session.localize("q.jpg", &s.camera) else {
        panic!("refused")
    };
    assert!(matches!(e, SessionError::NoSource(_)), "{e:?}");
    assert!(e.to_string().starts_with("m.sfpm: query \"q.jpg\""), "{e}");
}

#[test]
fn a_session_keeps_its_map_alive_and_is_shared_by_threads() {
    let (dir, map) = map();
    let s = scene();
    let session = build(&map, LocalizeOptions::default()).unwrap();
    // The caller's handle and the file may go: the session holds the map.
    drop(map);
    drop(dir);
    let q = query(&s, &truth(), 20, DIM);
    std::thread::scope(|scope| {
        for i in 0..3 {
            let (session, q, camera) = (&session, &q, &s.camera);
            scope.spawn(move || {
                let r = session
                    .localize_features(q, camera, &format!("q{i}"))
                    .unwrap();
                assert!(r.pose().unwrap().center_distance(&truth()) < 0.05);
            });
        }
    });
    assert_eq!(Arc::strong_count(session.map()), 1);
}

/// A map of two points whose one level holds `descriptor` descriptors (none: `None`).
fn map_of(dir: &std::path::Path, descriptor: Option<&str>) -> Arc<Map<'static>> {
    use sfpmap::format::{Descriptors, MapWriter};
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0, 0.0, 1.0], [1.0, 0.0, 1.0]]);
    if let Some(descriptor) = descriptor {
        let mut info = crate::synthetic_scene::level_info(0, DIM);
        info.descriptor = descriptor.into();
        let values = vec![0.25f32; 2 * DIM];
        w.add_level(info, &[0, 1], Some(Descriptors::F32(&values)), true)
            .unwrap();
    }
    let path = dir.join(format!("{}.sfpm", descriptor.unwrap_or("none")));
    std::fs::write(&path, w.to_bytes().unwrap()).unwrap();
    Arc::new(Map::open(&path).unwrap())
}

#[test]
fn only_maps_of_sfp_descriptors_extract_their_queries() {
    let dir = tempfile::tempdir().unwrap();
    for (descriptor, refused) in [
        (None, Some("the map has no descriptors")),
        (Some("sift"), Some("a map of \"sift\" descriptors")),
        (
            Some("colmap-64"),
            Some("a map of \"colmap-64\" descriptors"),
        ),
        (Some("sfp-v2"), None),
    ] {
        let map = map_of(dir.path(), descriptor);
        let checked = sfpmap::session::check_extractable(&map, "m.sfpm");
        match (checked, refused) {
            (Ok(()), None) => {}
            (Err(e), Some(expected)) => {
                assert!(matches!(e, SessionError::NotExtractable { .. }), "{e:?}");
                let text = e.to_string();
                assert!(
                    text.starts_with("m.sfpm: ") && text.contains(expected),
                    "{text}"
                );
            }
            (checked, _) => panic!("{descriptor:?}: {checked:?}"),
        }
    }
    // A session over such a map with images as its source is refused the same way, before
    // any model is loaded.
    let sift = map_of(dir.path(), Some("sift"));
    let built = Session::builder(sift, "m.sfpm")
        .source(QuerySource::Images {
            folder: None,
            model: None,
        })
        .build(&Silent);
    assert!(matches!(built, Err(SessionError::NotExtractable { .. })));
}

#[test]
fn a_query_list_stops_at_its_first_error() {
    use std::sync::atomic::{AtomicU64, Ordering};
    #[derive(Default)]
    struct Count(AtomicU64);
    impl sfpmap::progress::Reporter for Count {
        fn advance(&self, n: u64) {
            self.0.fetch_add(n, Ordering::Relaxed);
        }
    }
    let (_dir, map) = map();
    let s = scene();
    // Handed-in features: every query read by name is an error.
    let session = build(&map, LocalizeOptions::default()).unwrap();
    let queries: Vec<sfpmap::io::queries::Query> = (0..1000)
        .map(|i| sfpmap::io::queries::Query {
            name: format!("q{i}.jpg"),
            camera: s.camera.clone(),
        })
        .collect();
    let count = Count::default();
    let Err(e) = session.localize_all(&queries, 2, &count) else {
        panic!("no error")
    };
    assert!(matches!(e, SessionError::NoSource(_)), "{e:?}");
    // Each of the two workers stops after its first error.
    assert!(
        count.0.load(Ordering::Relaxed) <= 2,
        "{}",
        count.0.load(Ordering::Relaxed)
    );
}

#[test]
fn handed_in_features_with_a_nan_or_infinity_are_refused_naming_the_value() {
    let (_dir, map) = map();
    let s = scene();
    let session = build(&map, LocalizeOptions::default()).unwrap();
    let good = query(&s, &truth(), 20, DIM);
    let mut bad = good.clone();
    bad.sets[0].keypoints[3][0] = f64::NAN;
    let level = bad.sets[0].level;
    let e = session
        .localize_features(&bad, &s.camera, "q.jpg")
        .unwrap_err();
    assert_eq!(e.kind(), sfpmap::ErrorKind::Input);
    let level = level.map_or("None (every level)".to_string(), |l| l.to_string());
    assert_eq!(
        e.to_string(),
        format!("m.sfpm: query \"q.jpg\": level {level}: keypoints row 3: x is NaN")
    );
    let mut global = good.clone();
    global.global = Some(vec![f32::INFINITY; 4]);
    let e = session
        .localize_features(&global, &s.camera, "g")
        .unwrap_err();
    assert!(
        e.to_string().ends_with("global_descriptor: value 0 is inf"),
        "{e}"
    );
    // A frame handed in is checked as well.
    let frame = sfpmap::session::Frame::new(bad.clone());
    let e = session.localize_frame(frame, &s.camera, "f").unwrap_err();
    assert_eq!(e.kind(), sfpmap::ErrorKind::Input);
    assert!(e.to_string().ends_with("keypoints row 3: x is NaN"), "{e}");

    // A batch stops at the bad query; the good ones alone come back in order, each as
    // `localize_features` finds it.
    let e = session
        .localize_features_all(
            &[(&good, &s.camera, "a"), (&bad, &s.camera, "b")],
            2,
            &Silent,
        )
        .unwrap_err();
    assert!(e.to_string().contains("query \"b\""), "{e}");
    let many = query(&s, &truth(), 50, DIM);
    let batch = session
        .localize_features_all(
            &[(&good, &s.camera, "a"), (&many, &s.camera, "b")],
            2,
            &Silent,
        )
        .unwrap();
    for (r, q) in batch.iter().zip([&good, &many]) {
        let one = session.localize_features(q, &s.camera, "x").unwrap();
        assert_eq!(r.pose(), one.pose());
        assert_eq!(r.inliers, one.inliers);
    }
    assert_ne!(
        batch[0].matches, batch[1].matches,
        "results stay in query order"
    );
}
