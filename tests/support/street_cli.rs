//! What the remote-map and catalog tests share: running the CLI, generated streets converted
//! to SIFT maps, and `localize` of a street's queries (from its query database) against a
//! map, a URL or a catalog.
#![allow(dead_code)]

use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};

/// `sfpmap ARGS` with `env` set.
pub fn sfpmap(args: &[&str], env: &[(&str, String)]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_sfpmap"));
    c.args(args);
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// Its stdout, after asserting success.
pub fn ok(o: &Output) -> String {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8(o.stdout.clone()).unwrap()
}

/// Its stdout as JSON, after asserting success.
pub fn json(o: &Output) -> Value {
    serde_json::from_str(ok(o).trim()).unwrap()
}

/// Its one-line error, after asserting exit code 1.
pub fn failed(o: &Output) -> String {
    assert!(!o.status.success(), "expected a failure");
    assert_eq!(o.status.code(), Some(1));
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    err
}

/// A generated street in `dir` (`sfpmap::demo::street`: COLMAP model, map and query
/// databases, query list), its SIFT map converted to `dir/map.sfpm`.
pub fn street(dir: &Path, points: usize, queries: usize, seed: u64) {
    let _ = std::fs::remove_dir_all(dir);
    let options = sfpmap::demo::street::StreetOptions {
        points,
        queries,
        seed,
        ..Default::default()
    };
    sfpmap::demo::street::write_street(dir, &options).unwrap();
    let p = |n: &str| dir.join(n).to_str().unwrap().to_string();
    ok(&sfpmap(
        &[
            "convert",
            "--colmap",
            &p("sparse"),
            "--database",
            &p("database.db"),
            "-o",
            &p("map.sfpm"),
            "-q",
        ],
        &[],
    ));
}

/// `sfpmap localize --json` of `street`'s queries; `map` is `["--map", M]` or
/// `["--catalog", C]`; `extra` more arguments.
pub fn localize(
    map: [&str; 2],
    street: &Path,
    out: &Path,
    extra: &[&str],
    env: &[(&str, String)],
) -> Output {
    let (list, db) = (street.join("queries.txt"), street.join("queries.db"));
    let mut args = vec![
        "localize",
        map[0],
        map[1],
        "--query-list",
        list.to_str().unwrap(),
        "--database",
        db.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--json",
        "--force",
    ];
    args.extend(extra);
    sfpmap(&args, env)
}
