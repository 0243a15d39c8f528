//! Maps read by range from real servers on loopback (`tests/servers`): nginx over HTTP and
//! s3s-fs over S3. Each command that reads a map takes a URL; the tests check the results
//! equal the local file's, count what crossed the wire, and feed the bad cases (404, 403, no
//! server, a server that ignores `Range`, a damaged byte, an object replaced mid-read).
#![cfg(all(feature = "onnx", feature = "localize", feature = "colmap"))]

use crate::once::Depends;
use crate::servers;
use crate::street_cli;

use servers::{Nginx, S3};
use sfpmap::format::{Map, SectionKind};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use street_cli::{failed, json, localize, ok, sfpmap, street};

/// A generated street (`street_cli::street`: model, databases, its SIFT map `map.sfpm`) and
/// the map's level 2 short slice (`l2s.sfpm`), made once for all test processes.
pub(crate) fn scene() -> &'static Path {
    static SCENE: OnceLock<PathBuf> = OnceLock::new();
    SCENE.get_or_init(|| {
        let recipe = "street_cli::street: 6000 points, 4 queries, default seed; l2s.sfpm: \
                      slice --level 2 --short";
        crate::once::built_once("remote-street", recipe, Depends::OnBinary, |dir| {
            let seed = sfpmap::demo::street::StreetOptions::default().seed;
            street(dir, 6000, 4, seed);
            let p = |n: &str| dir.join(n).to_str().unwrap().to_string();
            let slice = [
                "slice",
                &p("map.sfpm"),
                "--level",
                "2",
                "--short",
                "-o",
                &p("l2s.sfpm"),
                "-q",
            ];
            ok(&sfpmap(&slice, &[]));
        })
    })
}

/// `slice MAP --level 2 --short -o OUT --json`, the report.
fn slice_level_2_short(map: &str, out: &Path, env: &[(&str, String)]) -> serde_json::Value {
    let args = [
        "slice",
        map,
        "--level",
        "2",
        "--short",
        "-o",
        out.to_str().unwrap(),
        "--json",
    ];
    json(&sfpmap(&args, env))
}

fn cache(dir: &tempfile::TempDir) -> (&'static str, String) {
    ("SFPMAP_CACHE_DIR", dir.path().display().to_string())
}

/// Bytes of the sections `keep` selects, plus the index (header, table, metadata) and the
/// padding before each.
pub(crate) fn expected_bytes(
    map: &Map<'_>,
    keep: impl Fn(SectionKind, Option<u16>) -> bool,
) -> u64 {
    let first = map
        .sections()
        .first()
        .map_or(map.file_len(), |s| s.offset());
    let mut end_before = 0;
    let mut total = first;
    for s in map.sections() {
        if keep(s.kind(), s.level()) {
            total += s.offset() + s.stored_len() - end_before.max(first);
        }
        end_before = s.offset() + s.stored_len();
    }
    total
}

#[test]
fn http_slice_info_verify_read_only_what_they_use() {
    let nginx = Nginx::start();
    let full = scene().join("map.sfpm");
    std::fs::copy(&full, nginx.root.join("demo.sfpm")).unwrap();
    let url = nginx.url("demo.sfpm");
    let t = tempfile::tempdir().unwrap();
    let no_cache = [("SFPMAP_CACHE_DIR", "off".to_string())];

    // info: the first read holds the whole index: one request.
    let info = json(&sfpmap(&["info", &url, "--json"], &no_cache));
    let local = json(&sfpmap(&["info", full.to_str().unwrap(), "--json"], &[]));
    assert_eq!(info["points"], local["points"]);
    assert_eq!(nginx.requests().len(), 1, "{:?}", nginx.requests());

    // slice --level 2 --short: the kept sections only, byte-identical to the local slice.
    let out = t.path().join("remote-l2s.sfpm");
    let report = slice_level_2_short(&url, &out, &no_cache);
    // The local file's slice, made with the scene.
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(scene().join("l2s.sfpm")).unwrap()
    );
    let map = Map::open(&full).unwrap();
    let kept = expected_bytes(&map, |kind, level| match level {
        Some(l) => l == 2 && kind != SectionKind::LevelDescRest,
        None => true,
    });
    let transfer = &report["transfer"];
    let bytes = transfer["bytes"].as_u64().unwrap();
    assert!(
        bytes <= kept + sfpmap::fuzzing::COALESCE_GAP,
        "{bytes} > {kept}"
    );
    assert!(bytes < map.file_len(), "{bytes} of {}", map.file_len());
    assert!(transfer["requests"].as_u64().unwrap() <= 3, "{transfer}");

    // verify reads everything, once.
    let before = nginx.requests().len();
    ok(&sfpmap(&["verify", &url], &no_cache));
    assert!(
        nginx.requests().len() - before <= 3,
        "{:?}",
        nginx.requests()
    );
}

#[test]
fn http_localize_equals_local_and_runs_from_the_cache_the_second_time() {
    let nginx = Nginx::start();
    let d = scene();
    let full = d.join("map.sfpm");
    std::fs::copy(&full, nginx.root.join("demo.sfpm")).unwrap();
    let url = nginx.url("demo.sfpm");
    let t = tempfile::tempdir().unwrap();
    let cache_dir = tempfile::tempdir().unwrap();
    let env = [cache(&cache_dir)];
    let run = |map: &str, out: &Path, env: &[(&str, String)]| {
        json(&localize(
            ["--map", map],
            d,
            out,
            &["--level", "2", "--short"],
            env,
        ))
    };
    let local = run(full.to_str().unwrap(), &t.path().join("local.txt"), &[]);
    assert!(local["transfer"].is_null());
    let first = run(&url, &t.path().join("remote.txt"), &env);
    assert_eq!(first["localized"], local["localized"]);
    assert_eq!(
        std::fs::read_to_string(t.path().join("local.txt")).unwrap(),
        std::fs::read_to_string(t.path().join("remote.txt")).unwrap()
    );
    // Level 2 only: nothing of the other levels' descriptors, no colours or keypoints.
    let map = Map::open(&full).unwrap();
    let used = expected_bytes(&map, |kind, level| match level {
        // --short: level 2's `rest` block is not read.
        Some(l) => {
            l == 2 && kind != SectionKind::LevelDescRest || kind == SectionKind::LevelVladCentroids
        }
        None => !matches!(
            kind,
            SectionKind::PointColors | SectionKind::PointIds | SectionKind::VisibilityKeypoints
        ),
    });
    let bytes = first["transfer"]["bytes"].as_u64().unwrap();
    assert!(
        bytes <= used + 3 * sfpmap::fuzzing::COALESCE_GAP,
        "{bytes} > {used}"
    );
    assert!(bytes < map.file_len());

    // Second run: the sections come from the cache; only the first read goes out.
    let second = run(&url, &t.path().join("again.txt"), &env);
    assert_eq!(second["transfer"]["requests"], 1, "{}", second["transfer"]);
    assert!(second["transfer"]["cache_hits"].as_u64().unwrap() > 0);
    assert_eq!(
        std::fs::read_to_string(t.path().join("local.txt")).unwrap(),
        std::fs::read_to_string(t.path().join("again.txt")).unwrap()
    );
}

#[test]
fn a_server_that_ignores_range_is_read_whole_and_reported() {
    let nginx = Nginx::start();
    let full = scene().join("l2s.sfpm");
    std::fs::copy(&full, nginx.root.join("m.sfpm")).unwrap();
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("s.sfpm");
    let o = sfpmap(
        &[
            "slice",
            &nginx.url("norange/m.sfpm"),
            "--level",
            "2",
            "-o",
            out.to_str().unwrap(),
        ],
        &[("SFPMAP_CACHE_DIR", "off".into())],
    );
    ok(&o);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("ignores range requests"), "{err}");
    // The refused range, the object's size (HEAD), the whole object.
    assert!(err.contains("in 3 requests"), "{err}");
    Map::open(&out).unwrap().verify().unwrap();
}

#[test]
fn a_damaged_section_is_read_again_once_then_reported_and_never_cached() {
    let nginx = Nginx::start();
    let full = scene().join("l2s.sfpm");
    let mut bytes = std::fs::read(&full).unwrap();
    let map = Map::open(&full).unwrap();
    let section = map
        .sections()
        .iter()
        .find(|s| s.kind() == SectionKind::LevelDescShort)
        .unwrap();
    let at = (section.offset() + section.stored_len() / 2) as usize;
    bytes[at] ^= 0x40;
    std::fs::write(nginx.root.join("bad.sfpm"), &bytes).unwrap();
    let cache_dir = tempfile::tempdir().unwrap();
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("s.sfpm");
    let url = nginx.url("bad.sfpm");
    let o = sfpmap(
        &["slice", &url, "--level", "2", "-o", out.to_str().unwrap()],
        &[cache(&cache_dir)],
    );
    let err = failed(&o);
    assert!(err.contains(&url) && err.contains("checksum"), "{err}");
    assert!(!out.exists());
    // After the first read of everything kept, the damaged section alone (from the end of
    // the section before it) was read once more, and that was all.
    let previous = &map.sections()[section.index() - 1];
    let start = previous.offset() + previous.stored_len();
    let end = section.offset() + section.stored_len() - 1;
    let requests = nginx.requests();
    let again = format!("bytes={start}-{end} ");
    assert_eq!(
        requests.iter().filter(|l| l.contains(&again)).count(),
        1,
        "{requests:?}"
    );
    assert_eq!(requests.len(), 3, "{requests:?}");
    // No cache entry holds the damaged section's bytes.
    for entry in walk(cache_dir.path()) {
        let cached = std::fs::read(&entry).unwrap();
        assert!(
            !cached.windows(16).any(|w| w == &bytes[at - 8..at + 8]),
            "{} holds damaged bytes",
            entry.display()
        );
    }
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        if e.path().is_dir() {
            out.extend(walk(&e.path()));
        } else {
            out.push(e.path());
        }
    }
    out
}

#[test]
fn an_object_replaced_after_its_index_was_read_is_an_error() {
    let nginx = Nginx::start();
    let d = scene();
    let served = nginx.root.join("m.sfpm");
    std::fs::copy(d.join("map.sfpm"), &served).unwrap();
    let mut options = sfpmap::remote::RemoteOptions::default();
    options.cache_dir = None;
    options.cache_max_bytes = 0;
    let map = sfpmap::remote::open(&nginx.url("m.sfpm"), &options).unwrap();
    // Another map at the same URL (another size, so another ETag).
    std::fs::copy(d.join("l2s.sfpm"), nginx.root.join("tmp.sfpm")).unwrap();
    std::fs::rename(nginx.root.join("tmp.sfpm"), &served).unwrap();
    let err = map.verify().unwrap_err().to_string();
    assert!(err.contains("changed since its index was read"), "{err}");
}

#[test]
fn missing_forbidden_and_unreachable_maps_are_one_line_errors() {
    let nginx = Nginx::start();
    std::fs::copy(scene().join("l2s.sfpm"), nginx.root.join("m.sfpm")).unwrap();
    let cache_dir = tempfile::tempdir().unwrap();
    let env = [cache(&cache_dir)];
    let missing = nginx.url("nothing.sfpm");
    let err = failed(&sfpmap(&["info", &missing], &env));
    assert!(err.contains(&missing) && err.contains("404"), "{err}");
    let forbidden = nginx.url("forbidden/m.sfpm");
    let err = failed(&sfpmap(&["info", &forbidden], &env));
    assert!(err.contains(&forbidden) && err.contains("403"), "{err}");
    // Nothing listens on a port just released.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let closed = format!("http://127.0.0.1:{port}/m.sfpm");
    let start = std::time::Instant::now();
    let err = failed(&sfpmap(&["info", &closed], &env));
    assert!(err.contains(&closed), "{err}");
    assert!(start.elapsed() < std::time::Duration::from_secs(60));
    // Not a map at all.
    std::fs::write(nginx.root.join("text.sfpm"), b"hello, not a map").unwrap();
    let err = failed(&sfpmap(&["info", &nginx.url("text.sfpm")], &env));
    assert!(err.contains("magic") || err.contains("truncated"), "{err}");
    assert!(walk(cache_dir.path())
        .iter()
        .all(|p| p.extension().is_none_or(|e| e != "bin")));
}

#[test]
fn a_truncated_response_is_an_error() {
    // A server that announces the whole range and closes half way (nginx never does).
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let map = std::fs::read(scene().join("l2s.sfpm")).unwrap();
    let server = std::thread::spawn(move || {
        use std::io::{Read, Write};
        // Bounded: object_store retries a failed body read a few times.
        for _ in 0..4 {
            let Ok((mut s, _)) = listener.accept() else {
                return;
            };
            let mut request = [0u8; 4096];
            let _ = s.read(&mut request);
            let len = map.len().min(sfpmap::fuzzing::HEAD_READ as usize);
            let head = format!(
                "HTTP/1.1 206 Partial Content\r\nContent-Length: {len}\r\nContent-Range: bytes 0-{}/{}\r\nETag: \"x\"\r\nConnection: close\r\n\r\n",
                len - 1,
                map.len()
            );
            let _ = s.write_all(head.as_bytes());
            let _ = s.write_all(&map[..len / 2]);
        }
    });
    let url = format!("http://127.0.0.1:{port}/m.sfpm");
    let err = failed(&sfpmap(
        &["info", &url],
        &[("SFPMAP_CACHE_DIR", "off".into())],
    ));
    assert!(
        err.contains(&url) && err.contains("truncated response"),
        "{err}"
    );
    drop(server);
}

#[test]
fn s3_slice_and_localize_equal_the_local_map() {
    let s3 = S3::start();
    let d = scene();
    let full = d.join("map.sfpm");
    s3.put("maps", "place/demo.sfpm", &std::fs::read(&full).unwrap());
    let mut env = s3.env();
    env.push(("SFPMAP_CACHE_DIR", "off".into()));
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("s3-l2s.sfpm");
    let report = slice_level_2_short("s3://maps/place/demo.sfpm", &out, &env);
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(d.join("l2s.sfpm")).unwrap()
    );
    assert!(report["transfer"]["bytes"].as_u64().unwrap() < Map::open(&full).unwrap().file_len());

    let poses = t.path().join("poses.txt");
    let r = json(&localize(
        ["--map", "s3://maps/place/demo.sfpm"],
        d,
        &poses,
        &[],
        &env,
    ));
    let local = t.path().join("local-poses.txt");
    let l = json(&localize(
        ["--map", full.to_str().unwrap()],
        d,
        &local,
        &[],
        &[],
    ));
    assert!(r["localized"].as_u64().unwrap() > 0);
    assert_eq!(r["localized"], l["localized"]);
    assert_eq!(
        std::fs::read_to_string(&poses).unwrap(),
        std::fs::read_to_string(&local).unwrap()
    );

    // Wrong credentials: refused by the server, one line.
    let mut bad = s3.env();
    bad.retain(|(k, _)| *k != "AWS_SECRET_ACCESS_KEY");
    bad.push(("AWS_SECRET_ACCESS_KEY", "wrong".into()));
    bad.push(("SFPMAP_CACHE_DIR", "off".into()));
    let err = failed(&sfpmap(&["info", "s3://maps/place/demo.sfpm"], &bad));
    assert!(err.contains("s3://maps/place/demo.sfpm"), "{err}");
}
