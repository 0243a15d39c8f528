//! `sfpmap catalog build` and `localize --catalog` on generated streets (different seeds, so
//! different places): the right place is chosen, a place can be a URL (nginx on loopback),
//! `--prior` filters places, and a catalog naming a missing or replaced map is an error.
#![cfg(all(feature = "localize", feature = "colmap"))]

use crate::once::Depends;
use crate::servers;
use crate::street_cli;

use serde_json::Value;
use sfpmap::format::{Catalog, Map};
use std::path::{Path, PathBuf};
use std::process::Output;
use std::sync::OnceLock;
use street_cli::{failed, json, localize, ok};

/// No cache: each run reads what it reads.
fn sfpmap(args: &[&str]) -> Output {
    street_cli::sfpmap(args, &[("SFPMAP_CACHE_DIR", "off".into())])
}

/// Three generated streets (seeds 1, 2, 3), each with its SIFT map: `streets/sN/`.
pub(crate) fn streets() -> &'static Path {
    static STREETS: OnceLock<PathBuf> = OnceLock::new();
    STREETS.get_or_init(|| {
        let recipe = "street_cli::street s1, s2, s3: 4000 points, 8 queries, seeds 1 to 3";
        crate::once::built_once("catalog-streets", recipe, Depends::OnBinary, |root| {
            for seed in 1..=3u64 {
                street_cli::street(&root.join(format!("s{seed}")), 4000, 8, seed);
            }
        })
    })
}

fn localize_catalog(catalog: &Path, street: &Path, out: &Path, extra: &[&str]) -> Value {
    let no_cache = [("SFPMAP_CACHE_DIR", "off".into())];
    json(&localize(
        ["--catalog", catalog.to_str().unwrap()],
        street,
        out,
        extra,
        &no_cache,
    ))
}

/// How many of `street`'s queries its own map localizes.
fn direct_localized(street: &Path, out: &Path) -> Value {
    let map = street.join("map.sfpm");
    json(&localize(
        ["--map", map.to_str().unwrap()],
        street,
        out,
        &[],
        &[],
    ))["localized"]
        .clone()
}

#[test]
fn each_street_s_queries_go_to_that_street() {
    let root = streets();
    let t = tempfile::tempdir().unwrap();
    let catalog = root.join("city.sfpc");
    let maps: Vec<String> = (1..=3)
        .map(|s| {
            root.join(format!("s{s}/map.sfpm"))
                .to_str()
                .unwrap()
                .to_string()
        })
        .collect();
    let mut args = vec!["catalog", "build"];
    args.extend(maps.iter().map(String::as_str));
    args.extend(["--name", "one", "--name", "two", "--name", "three", "-o"]);
    args.push(catalog.to_str().unwrap());
    args.push("--force");
    ok(&sfpmap(&args));
    // Paths inside the catalog's folder are recorded relative to it.
    let bytes = std::fs::read(&catalog).unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    let c = Catalog::of(&map).unwrap().unwrap();
    assert_eq!(c.places()[1].map, "s2/map.sfpm");
    assert_eq!(
        c.places()[1].points,
        Map::open(&maps[1]).unwrap().n_points()
    );

    for (i, name) in ["one", "two", "three"].iter().enumerate() {
        let street = root.join(format!("s{}", i + 1));
        let out = t.path().join(format!("{name}.txt"));
        let r = localize_catalog(&catalog, &street, &out, &["--places", "1"]);
        // Some generated queries see no point (no features): those rank nothing.
        let ranked: Vec<&Value> = r["chosen"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|q| !q["ranked"].as_array().unwrap().is_empty())
            .collect();
        assert!(!ranked.is_empty(), "{r}");
        for q in &ranked {
            assert_eq!(q["ranked"][0]["place"], *name, "{q}");
        }
        // As many as the street's own map localizes, all in that street.
        let direct = direct_localized(&street, &t.path().join(format!("{name}-direct.txt")));
        assert_eq!(r["localized"], direct, "{r}");
        assert_eq!(r["places"][name], r["localized"], "{r}");
    }

    // --prior far from every street leaves no candidate: queries fail, the run does not.
    let street = root.join("s2");
    let r = localize_catalog(
        &catalog,
        &street,
        &t.path().join("far.txt"),
        &["--prior", "1e6,1e6,1e6"],
    );
    assert_eq!(r["localized"], 0, "{r}");
    // --prior inside street two's box keeps it.
    let c2 = &c.places()[1];
    let centre: Vec<String> = (0..3)
        .map(|k| ((c2.bbox_min[k] + c2.bbox_max[k]) / 2.0).to_string())
        .collect();
    let prior = centre.join(",");
    let r = localize_catalog(
        &catalog,
        &street,
        &t.path().join("near.txt"),
        &[&format!("--prior={prior}"), "--radius", "1"],
    );
    assert_eq!(
        r["localized"],
        direct_localized(&street, &t.path().join("d.txt")),
        "{r}"
    );
    assert!(r["localized"].as_u64().unwrap() > 0, "{r}");
}

#[test]
fn a_place_read_from_a_url_is_fetched_by_range() {
    let root = streets();
    let nginx = servers::Nginx::start();
    std::fs::copy(root.join("s3/map.sfpm"), nginx.root.join("s3.sfpm")).unwrap();
    let t = tempfile::tempdir().unwrap();
    let catalog = t.path().join("city.sfpc");
    let url = nginx.url("s3.sfpm");
    ok(&sfpmap(&[
        "catalog",
        "build",
        root.join("s1/map.sfpm").to_str().unwrap(),
        &url,
        "-o",
        catalog.to_str().unwrap(),
    ]));
    // A catalog file names loopback places only when the user allows it (outbound policy).
    let run = |env: &[(&str, String)]| {
        localize(
            ["--catalog", catalog.to_str().unwrap()],
            &root.join("s3"),
            &t.path().join("p.txt"),
            &["--places", "1"],
            env,
        )
    };
    let no_cache = ("SFPMAP_CACHE_DIR", "off".to_string());
    let err = failed(&run(std::slice::from_ref(&no_cache)));
    assert!(err.contains("SFPMAP_ALLOW_PRIVATE_PLACES=1"), "{err}");
    let r = json(&run(&[
        no_cache,
        ("SFPMAP_ALLOW_PRIVATE_PLACES", "1".to_string()),
    ]));
    let direct = direct_localized(&root.join("s3"), &t.path().join("d.txt"));
    assert!(direct.as_u64().unwrap() > 0);
    assert_eq!(r["localized"], direct, "{r}");
    let transfer = &r["transfer"]["s3"];
    let file_len = Map::open(root.join("s3/map.sfpm")).unwrap().file_len();
    assert!(transfer["bytes"].as_u64().unwrap() < file_len, "{transfer}");
}

#[test]
fn a_missing_or_replaced_place_map_is_a_one_line_error() {
    let root = streets();
    let t = tempfile::tempdir().unwrap();
    let place = t.path().join("p.sfpm");
    std::fs::copy(root.join("s1/map.sfpm"), &place).unwrap();
    let catalog = t.path().join("c.sfpc");
    ok(&sfpmap(&[
        "catalog",
        "build",
        place.to_str().unwrap(),
        "-o",
        catalog.to_str().unwrap(),
    ]));
    // Replaced by another map: the index checksum no longer matches.
    std::fs::copy(root.join("s2/map.sfpm"), &place).unwrap();
    let s1 = root.join("s1");
    let run = |catalog: &Path, out: &str| {
        localize(
            ["--catalog", catalog.to_str().unwrap()],
            &s1,
            &t.path().join(out),
            &[],
            &[],
        )
    };
    let err = failed(&run(&catalog, "a.txt"));
    assert!(err.contains("rebuild the catalog"), "{err}");
    std::fs::remove_file(&place).unwrap();
    let err = failed(&run(&catalog, "b.txt"));
    assert!(err.contains("p.sfpm"), "{err}");
    assert!(!t.path().join("b.txt").exists());
    // An output naming a place map is refused, even with --force, before anything runs.
    std::fs::copy(root.join("s1/map.sfpm"), &place).unwrap();
    let before = std::fs::read(&place).unwrap();
    let o = localize(
        ["--catalog", catalog.to_str().unwrap()],
        &s1,
        &place,
        &[],
        &[],
    );
    let err = failed(&o);
    assert!(err.contains("input"), "{err}");
    assert_eq!(std::fs::read(&place).unwrap(), before);
    // A map that is not a catalog.
    let err = failed(&run(&s1.join("map.sfpm"), "c.txt"));
    assert!(err.contains("not a catalog"), "{err}");
}
