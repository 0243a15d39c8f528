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
