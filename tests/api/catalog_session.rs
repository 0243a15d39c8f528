//! `session::catalog::CatalogSession` over two generated streets: each street's queries go to
//! that street, a prior far from a street keeps its queries out of it, a replaced place map
//! is refused by name, and a catalog without places is not a catalog.
#![cfg(all(feature = "demo", feature = "colmap"))]

use sfpmap::build::catalog::{build_catalog, PlaceMap};
use sfpmap::build::{convert, ConvertOptions};
use sfpmap::demo::street::{write_street, StreetOptions};
use sfpmap::format::Map;
use sfpmap::io::queries::{read_query_list, DatabaseFeatures};
use sfpmap::progress::Silent;
use sfpmap::session::catalog::{CatalogSession, Near};
use sfpmap::session::{QuerySource, SessionError};
use std::path::Path;
use std::sync::Arc;

/// Street `seed` (4,000 points, 4 queries) in `dir`, converted to `dir/map.sfpm`.
fn street(dir: &Path, seed: u64) {
    let options = StreetOptions {
        points: 4_000,
        queries: 4,
        seed,
        ..StreetOptions::default()
    };
    write_street(dir, &options).unwrap();
    let convert_options = ConvertOptions {
        database: Some(dir.join("database.db")),
        ..ConvertOptions::default()
    };
    convert(
        &dir.join("sparse"),
        &convert_options,
        &dir.join("map.sfpm"),
        &Silent,
    )
    .unwrap();
}

/// `root/city.sfpc` over `root/s1/map.sfpm` and `root/s2/map.sfpm`.
fn city(root: &Path) -> Arc<Map<'static>> {
    let maps: Vec<Map<'static>> = ["s1", "s2"]
        .iter()
        .map(|s| Map::open(root.join(s).join("map.sfpm")).unwrap())
        .collect();
    let places: Vec<PlaceMap<'_>> = ["s1", "s2"]
        .iter()
        .zip(&maps)
        .map(|(s, map)| PlaceMap {
            name: s.to_string(),
            location: format!("{s}/map.sfpm"),
            map,
        })
        .collect();
    let path = root.join("city.sfpc");
    build_catalog(&places)
        .unwrap()
        .write(&path, &Silent)
        .unwrap();
    Arc::new(Map::open(&path).unwrap())
}

#[test]
fn each_street_s_queries_go_to_that_street_and_a_prior_keeps_them_out_of_another() {
    let root = tempfile::tempdir().unwrap();
    street(&root.path().join("s1"), 1);
    street(&root.path().join("s2"), 2);
    let catalog = city(root.path());
    let name = root.path().join("city.sfpc").display().to_string();
    for (index, s) in ["s1", "s2"].iter().enumerate() {
        let dir = root.path().join(s);
        let session = CatalogSession::builder(catalog.clone(), &name)
            .source(QuerySource::Database(dir.join("queries.db")))
            .places_per_query(1)
            .build(&Silent)
            .unwrap();
        assert_eq!(
            session.locations()[index],
            root.path().join(s).join("map.sfpm")
        );
        assert_eq!(
            session.opened().len(),
            0,
            "no place is opened before a query"
        );
        let queries = read_query_list(&dir.join("queries.txt"), None).unwrap();
        let found = session.localize_all(&queries, None, 2, &Silent).unwrap();
        // The generator leaves some queries facing nothing (no keypoints): those rank no
        // place; every other one goes to its own street.
        let db = DatabaseFeatures::open(&dir.join("queries.db")).unwrap();
        let mut seen = 0;
        for (q, f) in queries.iter().zip(&found) {
            assert!(f.features_read, "{}", q.name);
            let keypoints: usize = db
                .features(&q.name)
                .unwrap()
                .unwrap()
                .sets
                .iter()
                .map(|s| s.keypoints.len())
                .sum();
            if keypoints == 0 {
                assert!(
                    f.ranked.is_empty() && f.place.is_none(),
                    "{}: {f:?}",
                    q.name
                );
                continue;
            }
            seen += 1;
            let first = f.ranked.first().map(|r| r.place);
            assert_eq!(first, Some(index), "{}: {:?}", q.name, f.ranked);
            assert_eq!(
                f.place,
                Some(index),
                "{}: {:?}",
                q.name,
                f.localization.failure()
            );
        }
        assert!(seen >= 2, "{s}: {seen} queries with features");
        // Only the place that was tried is open.
        assert_eq!(
            session.opened().iter().map(|(i, _)| *i).collect::<Vec<_>>(),
            vec![index]
        );

        // A prior inside the other street's box (and far from this one's): this street is
        // not ranked at all.
        let other = &session.places()[1 - index];
        let position = [
            other.bbox_min[0],
            other.bbox_min[1],
            other.bbox_min[2] - 1_000.0,
        ];
        let far = Near {
            position,
            radius: 0.0,
        };
        let q = queries
            .iter()
            .zip(&found)
            .find_map(|(q, f)| f.place.is_some().then_some(q))
            .unwrap();
        let r = session.localize(&q.name, &q.camera, Some(far)).unwrap();
        assert!(r.ranked.is_empty(), "{:?}", r.ranked);
        assert_eq!(r.place, None);
        assert!(r.localization.pose().is_none());

        // A prior that is not a position, or a negative radius, is refused as options are.
        for bad in [
            Near {
                position: [f64::NAN, 0.0, 0.0],
                radius: 1.0,
            },
            Near {
                position,
                radius: -1.0,
            },
        ] {
            let e = session.localize(&q.name, &q.camera, Some(bad)).unwrap_err();
            assert_eq!(e.kind(), sfpmap::ErrorKind::InvalidArgument, "{e}");
        }

        // A query the source does not hold is a failed query, not an error.
        let missing = session
            .localize("no-such-image.png", &queries[0].camera, None)
            .unwrap();
        assert!(!missing.features_read);
        assert!(missing.localization.pose().is_none());
    }
}

#[test]
fn a_replaced_place_map_is_refused_naming_the_place() {
    let root = tempfile::tempdir().unwrap();
    street(&root.path().join("s1"), 1);
    street(&root.path().join("s2"), 2);
    let catalog = city(root.path());
    // s1's map is replaced by s2's: same format, another index checksum.
    std::fs::copy(
        root.path().join("s2/map.sfpm"),
        root.path().join("s1/map.sfpm"),
    )
    .unwrap();
    let dir = root.path().join("s1");
    let name = root.path().join("city.sfpc").display().to_string();
    let session = CatalogSession::builder(catalog, &name)
        .source(QuerySource::Database(dir.join("queries.db")))
        .build(&Silent)
        .unwrap();
    let queries = read_query_list(&dir.join("queries.txt"), None).unwrap();
    let db = DatabaseFeatures::open(&dir.join("queries.db")).unwrap();
    let q = (queries.iter())
        .find(|q| {
            !db.features(&q.name).unwrap().unwrap().sets[0]
                .keypoints
                .is_empty()
        })
        .unwrap();
    let e = session.localize(&q.name, &q.camera, None).unwrap_err();
    // The failure is kept: the next query that ranks the place gets it again.
    let again = session.localize(&q.name, &q.camera, None).unwrap_err();
    assert_eq!(again.to_string(), e.to_string());
    assert!(
        matches!(e, SessionError::Place { ref place, .. } if place == "s1"),
        "{e:?}"
    );
    let text = e.to_string();
    assert!(
        text.starts_with(&format!("{name}: place \"s1\": "))
            && text.contains("not the map the catalog was built from"),
        "{text}"
    );
}

#[test]
fn a_map_without_places_is_not_a_catalog_and_zero_places_per_query_is_refused() {
    let root = tempfile::tempdir().unwrap();
    street(&root.path().join("s1"), 1);
    let map = Arc::new(Map::open(root.path().join("s1/map.sfpm")).unwrap());
    let e = CatalogSession::builder(map.clone(), "s1/map.sfpm")
        .build(&Silent)
        .err()
        .unwrap();
    assert_eq!(
        e.to_string(),
        "s1/map.sfpm: not a catalog (its metadata lists no places)"
    );
    let e = CatalogSession::builder(map, "s1/map.sfpm")
        .places_per_query(0)
        .build(&Silent)
        .err()
        .unwrap();
    assert_eq!(e.kind(), sfpmap::ErrorKind::InvalidArgument);
    assert_eq!(
        e.to_string(),
        "s1/map.sfpm: places_per_query 0: at least 1 place"
    );
}

#[test]
fn at_most_max_open_places_stay_open() {
    let root = tempfile::tempdir().unwrap();
    street(&root.path().join("s1"), 1);
    street(&root.path().join("s2"), 2);
    let catalog = city(root.path());
    let dir = root.path().join("s1");
    let name = root.path().join("city.sfpc").display().to_string();
    let session = CatalogSession::builder(catalog, name)
        .source(QuerySource::Database(dir.join("queries.db")))
        .places_per_query(2)
        .max_open_places(1)
        .build(&Silent)
        .unwrap();
    let queries = read_query_list(&dir.join("queries.txt"), None).unwrap();
    let found = session.localize_all(&queries, None, 1, &Silent).unwrap();
    // Both places were tried for a query with features, one stays open: the last used.
    assert!(found.iter().any(|f| f.ranked.len() == 2), "{found:?}");
    assert!(found.iter().any(|f| f.place == Some(0)), "{found:?}");
    assert_eq!(session.opened().len(), 1);
}
