//! What the CLI prints and takes (issue 32, cases 5, 11 and 12): paths, URLs and names a user
//! or a file gave are printed with their control characters escaped, so an error line cannot
//! clear the screen or forge another line; a query a database holds but that cannot be used
//! fails alone (exit status 3), the rest localized; numeric flags out of their stated range
//! are refused as clap parses them. The cases of `--images` and features files are in
//! `hostile_localize.rs`.
#![cfg(all(feature = "localize", feature = "colmap"))]

use crate::street_cli;

use std::path::Path;
use std::process::Output;
use street_cli::{json, localize, ok};

/// ESC (clear the screen), BEL and a newline that would start a forged `error:` line.
const HOSTILE: &str = "p\u{1b}[2J\u{7}\nerror: forged";
/// How [`HOSTILE`] reads once escaped.
const ESCAPED: &str = r"p\x1b[2J\x07\nerror: forged";

/// The exit status of a run that skipped queries it could not read (as for a log's damaged
/// parts; README, `localize --help`).
const SKIPPED_EXIT: i32 = 3;

/// No cache: each run reads what it reads.
fn sfpmap(args: &[&str]) -> Output {
    street_cli::sfpmap(args, &[("SFPMAP_CACHE_DIR", "off".into())])
}

/// Its stderr, after asserting it failed with `code` and that stdout and stderr hold no
/// control character but line ends, and stderr one line.
fn one_escaped_line(o: &Output, code: i32) -> String {
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert_eq!(o.status.code(), Some(code), "{err}");
    assert_no_raw_control_characters(o);
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err:?}");
    err
}

fn assert_no_raw_control_characters(o: &Output) {
    for bytes in [&o.stdout, &o.stderr] {
        let text = String::from_utf8_lossy(bytes);
        assert!(
            !text.chars().any(|c| c.is_control() && c != '\n'),
            "raw control character: {text:?}"
        );
    }
}

/// Case 5: a catalog place's path holding ESC, BEL and a newline was printed raw in the error
/// line (the screen cleared, a forged `error:` line). Now it is escaped, in `catalog build`'s
/// lines and in the errors of a replaced and of a missing place map.
#[test]
fn a_catalog_place_path_with_control_characters_is_escaped() {
    let root = crate::catalog::streets();
    let t = tempfile::tempdir().unwrap();
    let place = t.path().join(format!("{HOSTILE}.sfpm"));
    std::fs::copy(root.join("s1/map.sfpm"), &place).unwrap();
    let catalog = t.path().join("c.sfpc");
    let built = sfpmap(&[
        "catalog",
        "build",
        place.to_str().unwrap(),
        "-o",
        catalog.to_str().unwrap(),
        "--name",
        "p",
    ]);
    let printed = ok(&built);
    assert_no_raw_control_characters(&built);
    assert!(printed.contains(ESCAPED), "{printed}");
    let s1 = root.join("s1");
    let run = |out: &str| {
        localize(
            ["--catalog", catalog.to_str().unwrap()],
            &s1,
            &t.path().join(out),
            &[],
            &[],
        )
    };
    // Replaced by another map: the index checksum no longer matches.
    std::fs::copy(root.join("s2/map.sfpm"), &place).unwrap();
    let err = one_escaped_line(&run("a.txt"), 1);
    assert!(
        err.contains(ESCAPED) && err.contains("rebuild the catalog"),
        "{err}"
    );
    // Missing.
    std::fs::remove_file(&place).unwrap();
    let err = one_escaped_line(&run("b.txt"), 1);
    assert!(err.contains(ESCAPED), "{err}");
}

/// Case 5 for a map's own path: `info`, `slice` and `localize --map` name
/// it escaped, whether it is missing or not a map.
#[test]
fn a_map_path_with_control_characters_is_escaped() {
    let t = tempfile::tempdir().unwrap();
    let map = t.path().join(format!("{HOSTILE}.sfpm"));
    let map_text = map.to_str().unwrap();
    let street = crate::catalog::streets().join("s1");
    for exists in [false, true] {
        if exists {
            std::fs::write(&map, b"not a map at all, but long enough to be read").unwrap();
        }
        let err = one_escaped_line(&sfpmap(&["info", map_text]), 1);
        assert!(err.contains(ESCAPED), "{err}");
        let o = sfpmap(&[
            "slice",
            map_text,
            "--level",
            "0",
            "-o",
            t.path().join("s.sfpm").to_str().unwrap(),
        ]);
        let err = one_escaped_line(&o, 1);
        assert!(err.contains(ESCAPED), "{err}");
        let o = localize(
            ["--map", map_text],
            &street,
            &t.path().join("p.txt"),
            &[],
            &[],
        );
        let err = one_escaped_line(&o, 1);
        assert!(err.contains(ESCAPED), "{err}");
    }
}

/// Case 5 for a URL: the error of a map read by range names the URL escaped. The server is
/// a closed port on loopback: nothing leaves the machine.
#[test]
fn a_url_with_control_characters_is_escaped() {
    let url = format!("http://127.0.0.1:1/{HOSTILE}.sfpm");
    let err = one_escaped_line(&sfpmap(&["info", &url]), 1);
    assert!(err.contains("127.0.0.1:1"), "{err}");
}

/// Case 11 for a database: one query whose keypoint is NaN ended the whole run. Now it fails
/// alone, naming the database, the image and the keypoint; the others localize as they do
/// without it (one map, and a catalog of it), the poses are written, exit status 3.
#[test]
fn a_malformed_query_in_a_database_fails_alone() {
    let root = crate::catalog::streets();
    let street = root.join("s1");
    let t = tempfile::tempdir().unwrap();
    let direct = json(&localize(
        ["--map", street.join("map.sfpm").to_str().unwrap()],
        &street,
        &t.path().join("direct.txt"),
        &[],
        &[],
    ));
    // A copy of the street whose first query's first keypoint is NaN.
    let copy = t.path().join("street");
    std::fs::create_dir(&copy).unwrap();
    for f in ["queries.txt", "queries.db"] {
        std::fs::copy(street.join(f), copy.join(f)).unwrap();
    }
    let list = std::fs::read_to_string(copy.join("queries.txt")).unwrap();
    let first = list.split_whitespace().next().unwrap().to_string();
    {
        let db = rusqlite::Connection::open(copy.join("queries.db")).unwrap();
        let (id, mut blob): (i64, Vec<u8>) = db
            .query_row(
                "SELECT k.image_id, k.data FROM keypoints k JOIN images i \
                 ON i.image_id = k.image_id WHERE i.name = ?1",
                [&first],
                |r| Ok((r.get(0)?, r.get(1)?)),
            )
            .unwrap();
        blob[..4].copy_from_slice(&f32::NAN.to_le_bytes());
        db.execute(
            "UPDATE keypoints SET data = ?1 WHERE image_id = ?2",
            rusqlite::params![blob, id],
        )
        .unwrap();
    }
    let catalog = t.path().join("c.sfpc");
    ok(&sfpmap(&[
        "catalog",
        "build",
        street.join("map.sfpm").to_str().unwrap(),
        "-o",
        catalog.to_str().unwrap(),
    ]));
    for map in [
        ["--map", street.join("map.sfpm").to_str().unwrap()],
        ["--catalog", catalog.to_str().unwrap()],
    ] {
        let out = t.path().join("poses.txt");
        let o = localize(map, &copy, &out, &[], &[]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(SKIPPED_EXIT), "{map:?}: {err}");
        assert!(err.contains("1 of 8 queries could not be read"), "{err}");
        let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        // Every other query as without the broken one (the first one may have been among
        // them).
        let (was, now) = (
            direct["localized"].as_u64().unwrap(),
            summary["localized"].as_u64().unwrap(),
        );
        assert!(
            now + 1 >= was && now <= was && was > 1,
            "{map:?}: {was} -> {now}"
        );
        let poses = std::fs::read_to_string(&out).unwrap();
        let line = poses
            .lines()
            .find(|l| l.starts_with(&format!("# failed {first}: ")))
            .unwrap_or_else(|| panic!("{first} not failed: {poses}"));
        assert!(
            line.contains("queries.db") && line.contains("keypoint 0: x is NaN"),
            "{line}"
        );
    }
}

/// Case 12: `--radius NaN`, `eval --threshold nan,nan` and `--threshold=-1,-5` ran and
/// found nothing (0 localized, 0 % recall). Now every numeric flag's value is checked as it
/// is parsed: a usage error (exit status 2) naming the flag and the range, and `--help`
/// states the range.
#[test]
fn numeric_flags_out_of_range_are_refused_naming_the_flag() {
    let t = tempfile::tempdir().unwrap();
    let p = |n: &str| t.path().join(n).to_str().unwrap().to_string();
    let (poses, gt, out) = (p("poses.txt"), p("gt.txt"), p("out.txt"));
    std::fs::write(&poses, "").unwrap();
    std::fs::write(&gt, "").unwrap();
    let localize = |extra: &[&str]| {
        let mut a = vec![
            "localize",
            "--catalog",
            "c.sfpc",
            "--query-list",
            "q.txt",
            "--database",
            "q.db",
            "-o",
            &out,
        ];
        a.extend(extra);
        sfpmap(&a)
    };
    let eval = |threshold: &str| {
        sfpmap(&[
            "eval",
            "--poses",
            &poses,
            "--gt",
            &gt,
            &format!("--threshold={threshold}"),
        ])
    };
    let cases = [
        (
            localize(&["--prior", "0,0,0", "--radius", "NaN"]),
            "--radius",
        ),
        (localize(&["--prior", "0,0,0", "--radius=-1"]), "--radius"),
        (
            localize(&["--prior", "0,0,0", "--radius", "inf"]),
            "--radius",
        ),
        (localize(&["--prior", "0,NaN,0"]), "--prior"),
        (localize(&["--prior", "0,0"]), "--prior"),
        (eval("nan,nan"), "--threshold"),
        (eval("-1,-5"), "--threshold"),
        (eval("0,5"), "--threshold"),
        (eval("1,inf"), "--threshold"),
        (eval("1,200"), "--threshold"),
        (
            sfpmap(&["plot", "m.sfpm", "-o", &p("p.png"), "--width", "0"]),
            "--width",
        ),
        (
            sfpmap(&["plot", "m.sfpm", "-o", &p("p.png"), "--max-points", "0"]),
            "--max-points",
        ),
    ];
    for (o, flag) in &cases {
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{flag}: {err}");
        assert!(
            err.starts_with("error: invalid value") && err.contains(flag),
            "{flag}: {err}"
        );
    }
    // `--help` states each range.
    let help = ok(&sfpmap(&["localize", "--help"]));
    assert!(help.contains("finite, 0 or more"), "{help}");
    assert!(
        help.contains("in (0, 1]") && help.contains("1 to 100000"),
        "{help}"
    );
    let help = ok(&sfpmap(&["eval", "--help"]));
    assert!(help.contains("an angle in (0, 180]"), "{help}");
}

/// Review finding 6: a map's own text and path printed on success were not escaped: `slice`
/// printed the map's `units` raw (ESC[2J cleared the screen), `verify` its path. Now both
/// are escaped, as `info` escapes them.
#[test]
fn a_map_whose_text_and_path_hold_control_characters_is_printed_escaped() {
    use sfpmap::format::Codec;
    let t = tempfile::tempdir().unwrap();
    let scene = crate::common::Scene::new(7, 300, 6, &[(0, 2.0, 8, 4), (1, 4.0, 8, 4)]);
    let mut w = scene.writer(Codec::Raw);
    w.metadata_mut().units = HOSTILE.into();
    let map = t.path().join(format!("{HOSTILE}.sfpm"));
    w.write(&map, &sfpmap::progress::Silent).unwrap();
    let map = map.to_str().unwrap();
    // verify's success line: the path.
    let o = sfpmap(&["verify", map]);
    let printed = ok(&o);
    assert_no_raw_control_characters(&o);
    assert!(
        printed.contains(&format!("{ESCAPED}.sfpm: ok")),
        "{printed}"
    );
    // slice's grid line: the units.
    let out = t.path().join("s.sfpm");
    let o = sfpmap(&[
        "slice",
        map,
        "--level",
        "1",
        "--minimal",
        "-o",
        out.to_str().unwrap(),
    ]);
    let printed = ok(&o);
    assert_no_raw_control_characters(&o);
    assert!(
        printed.contains("positions on a 16-bit grid") && printed.contains(ESCAPED),
        "{printed}"
    );
    // info's lines, as before.
    let o = sfpmap(&["info", map]);
    ok(&o);
    assert_no_raw_control_characters(&o);
}

/// Review finding 7: `extract --nms-radius` and `--max-keypoints` took any whole number;
/// now their ranges are stated in `--help` and a value outside is refused as clap parses it
/// (exit status 2, the flag named), before any model or image is read.
#[cfg(feature = "onnx")]
#[test]
fn extract_whole_number_flags_have_stated_ranges() {
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("f.h5");
    let out = out.to_str().unwrap();
    let extract = |extra: &[&str]| {
        let mut a = vec!["extract", "missing.jpg", "-o", out];
        a.extend(extra);
        sfpmap(&a)
    };
    for (extra, flag) in [
        (&["--nms-radius", "65"][..], "--nms-radius"),
        (&["--nms-radius", "4294967295"][..], "--nms-radius"),
        (&["--max-keypoints", "0"][..], "--max-keypoints"),
        (&["--max-keypoints", "500,0"][..], "--max-keypoints"),
        (&["--max-keypoints", "1000001"][..], "--max-keypoints"),
    ] {
        let o = extract(extra);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {err}");
        assert!(
            err.starts_with("error: invalid value") && err.contains(flag),
            "{extra:?}: {err}"
        );
    }
    assert!(!Path::new(out).exists());
    let help = ok(&sfpmap(&["extract", "--help"]));
    assert!(
        help.contains("0 to 64") && help.contains("1 to 1000000"),
        "{help}"
    );
}
