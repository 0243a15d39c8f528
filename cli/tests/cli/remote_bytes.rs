//! What a server and the cache folder decide (issue 32, cases 6 to 9), on loopback servers
//! only: the bytes a remote read fetches (nothing of a skipped section), the memory `verify
//! URL` holds (a piece, not a section's claim), responses from another version of the object
//! (an error, never cached) and cache folders that are symbolic links (never followed).
#![cfg(all(feature = "onnx", feature = "localize", feature = "colmap"))]

use crate::remote::{expected_bytes, scene};
use crate::servers::Nginx;
use crate::street_cli::{failed, json, ok, sfpmap};

use sfpmap::format::{Codec, Dtype, Map, MapWriter, SectionKind};
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// The kind code of the optional section the tests add: one no reader knows.
const UNKNOWN_KIND: u16 = 0x7F10;

/// The street's map with an optional raw section of an unknown kind holding `len` zero bytes
/// (`vec![0; len]` is untouched zeroed memory: large ones cost address space, not RAM), written
/// to `out`. Unknown kinds without a level go between the shared sections and the levels, so
/// a reader that fetched it would have to skip over it on purpose.
fn with_unknown_section(len: usize, out: &Path) -> u64 {
    let map = Map::open(scene().join("map.sfpm")).unwrap();
    let mut w = MapWriter::new(map.metadata().clone());
    for s in map.sections() {
        if s.kind() != SectionKind::ChunkChecksums {
            w.copy_section(&map, s).unwrap();
        }
    }
    w.add_raw_section(
        SectionKind::Unknown(UNKNOWN_KIND),
        sfpmap::fuzzing::NO_LEVEL,
        Dtype::U8,
        len as u64,
        1,
        false,
        Cow::Owned(vec![0u8; len]),
        Some(Codec::Raw),
    )
    .unwrap();
    w.write(out, &sfpmap::progress::Silent).unwrap()
}

fn no_cache() -> [(&'static str, String); 1] {
    [("SFPMAP_CACHE_DIR", "off".to_string())]
}

/// `SFPMAP_COMPARE_BIN`: another build of `sfpmap` (an older one) that the measuring tests
/// also run, printing its figures beside this build's, never asserting on them: how a
/// change's before and after are measured in one run.
fn compare_bin() -> Option<PathBuf> {
    std::env::var_os("SFPMAP_COMPARE_BIN").map(PathBuf::from)
}

/// `localize --map URL --level 2 --json` of the street's queries by `bin`, its report.
fn localize_level_2(bin: &Path, url: &str, out: &Path) -> serde_json::Value {
    let d = scene();
    let p = |n: &str| d.join(n).to_str().unwrap().to_string();
    let o = std::process::Command::new(bin)
        .args(["localize", "--map", url, "--query-list", &p("queries.txt")])
        .args(["--database", &p("queries.db"), "-o", out.to_str().unwrap()])
        .args(["--level", "2", "--json", "--force"])
        .env("SFPMAP_CACHE_DIR", "off")
        .output()
        .unwrap();
    json(&o)
}

/// Case 7: `localize --map URL --level 2` reads the sections it uses and the index, nothing
/// of a 16 MiB optional section of an unknown kind that sits between them.
#[test]
fn remote_localize_never_downloads_a_skipped_section() {
    let nginx = Nginx::start();
    let served = nginx.root.join("unknown.sfpm");
    let unknown_len = 16 << 20;
    with_unknown_section(unknown_len, &served);
    let url = nginx.url("unknown.sfpm");
    let map = Map::open(&served).unwrap();
    assert_eq!(map.skipped_sections().count(), 1);
    let t = tempfile::tempdir().unwrap();
    let report = localize_level_2(
        Path::new(env!("CARGO_BIN_EXE_sfpmap")),
        &url,
        &t.path().join("poses.txt"),
    );
    if let Some(bin) = compare_bin() {
        let other = localize_level_2(&bin, &url, &t.path().join("other.txt"));
        eprintln!("{}: {}", bin.display(), other["transfer"]);
    }
    assert!(report["localized"].as_u64().unwrap() > 0, "{report}");
    // What the localizer reads: level 2 (both blocks), the VLAD codebook's level, the shared
    // sections but colours, ids and keypoints; never the unknown one.
    let used = expected_bytes(&map, |kind, level| match level {
        Some(l) => l == 2 || kind == SectionKind::LevelVladCentroids,
        None => !matches!(
            kind,
            SectionKind::PointColors
                | SectionKind::PointIds
                | SectionKind::VisibilityKeypoints
                | SectionKind::Unknown(_)
        ),
    });
    let bytes = report["transfer"]["bytes"].as_u64().unwrap();
    eprintln!(
        "localize --level 2 read {bytes} bytes; used sections and index {used}; unknown section {unknown_len}"
    );
    // Neighbours closer than the coalescing gap are read in one request (the bytes between
    // read and dropped): at most one gap per run.
    assert!(
        bytes <= used + 3 * sfpmap::fuzzing::COALESCE_GAP,
        "{bytes} > {used}"
    );
    assert!(bytes < unknown_len as u64, "{bytes}");
}

/// The peak resident memory of `bin args` in bytes (`/usr/bin/time -f %M`, KiB), and its
/// output.
fn peak_rss(bin: &Path, args: &[&str], env: &[(&str, String)]) -> (u64, std::process::Output) {
    let t = tempfile::tempdir().unwrap();
    let report = t.path().join("rss.txt");
    let mut c = std::process::Command::new("/usr/bin/time");
    c.arg("-f")
        .arg("%M")
        .arg("-o")
        .arg(&report)
        .arg(bin)
        .args(args);
    for (k, v) in env {
        c.env(k, v);
    }
    let out = c
        .output()
        .expect("/usr/bin/time runs (apt-get install time)");
    let kib: u64 = std::fs::read_to_string(&report)
        .unwrap()
        .trim()
        .lines()
        .last()
        .unwrap()
        .parse()
        .unwrap();
    (kib * 1024, out)
}

/// Case 8: `verify URL` of a map holding a 1 GiB section stays under 300 MB of resident memory
/// (the target of issue 32): it checks the section a piece at a time. Before, it held the
/// section twice (the download, then its aligned copy). The section is an unknown kind's
/// zeros, so the test costs a 1 GiB file and the transfer, not RAM.
#[test]
fn remote_verify_streams_a_1_gib_section() {
    let nginx = Nginx::start();
    let served = nginx.root.join("big.sfpm");
    let big = 1usize << 30;
    let file_len = with_unknown_section(big, &served);
    let url = nginx.url("big.sfpm");
    if let Some(bin) = compare_bin() {
        let (rss, out) = peak_rss(&bin, &["verify", &url], &no_cache());
        eprintln!("{}: peak RSS {rss} bytes, {}", bin.display(), out.status);
    }
    let (rss, out) = peak_rss(
        Path::new(env!("CARGO_BIN_EXE_sfpmap")),
        &["verify", &url],
        &no_cache(),
    );
    ok(&out);
    eprintln!("verify URL: peak RSS {rss} bytes for a {file_len}-byte map");
    assert!(rss <= 300_000_000, "peak RSS {rss} bytes");
    // It did read the section (every byte is checked), in pieces.
    let read: u64 = nginx
        .requests()
        .iter()
        .filter_map(|l| l.split_whitespace().last()?.parse::<u64>().ok())
        .sum();
    assert!(read >= big as u64, "{read}");
    // Damaged, it is still found: one byte of the section flipped on the server.
    {
        use std::io::{Seek, SeekFrom, Write};
        let map = Map::open(&served).unwrap();
        let s = map.skipped_sections().next().unwrap();
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .open(&served)
            .unwrap();
        f.seek(SeekFrom::Start(s.offset() + s.stored_len() - 3))
            .unwrap();
        f.write_all(&[1]).unwrap();
    }
    let err = failed(&sfpmap(&["verify", &url], &no_cache()));
    assert!(err.contains(&url) && err.contains("checksum"), "{err}");
}

/// How a test server names the version of the object in each response.
#[derive(Clone, Copy)]
enum Version {
    ETag,
    LastModified,
}

/// A request as a test server read it.
struct Request {
    /// A HEAD (no body in the answer).
    head: bool,
    /// `Range: bytes=A-B` (B absent for `A-`).
    range: Option<(u64, Option<u64>)>,
}

/// A loopback HTTP server (one thread, 64 connections at most, one request each): `respond`
/// writes the answer to the `n`th request on its stream. Its URL, `/m.sfpm` on it.
fn loopback_server(
    mut respond: impl FnMut(usize, &Request, &std::net::TcpStream) + Send + 'static,
) -> String {
    use std::io::{BufRead, BufReader};
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for (n, stream) in listener.incoming().enumerate().take(64) {
            let Ok(stream) = stream else { return };
            let mut reader = BufReader::new(&stream);
            let mut request = Request {
                head: false,
                range: None,
            };
            let mut line = String::new();
            while reader.read_line(&mut line).is_ok_and(|r| r > 0) {
                let l = line.trim_end().to_ascii_lowercase();
                if l.is_empty() {
                    break;
                }
                request.head |= l.starts_with("head ");
                if let Some(r) = l.strip_prefix("range: bytes=") {
                    let (a, b) = r.split_once('-').unwrap();
                    request.range = Some((a.parse().unwrap(), b.parse().ok()));
                }
                line.clear();
            }
            respond(n, &request, &stream);
        }
    });
    format!("http://127.0.0.1:{port}/m.sfpm")
}

/// A loopback HTTP server for `bytes` that honours `Range` but answers each response as
/// another version of the object (a new ETag, or a new Last-Modified and no ETag) and
/// ignores `If-Match`: what a careless server does while the object is replaced.
fn changing_server(bytes: Vec<u8>, version: Version) -> String {
    use std::io::Write;
    loopback_server(move |n, request, stream| {
        let range = request.range.map(|(a, b)| {
            let b = b.map_or(bytes.len() - 1, |b| (b as usize).min(bytes.len() - 1));
            a as usize..b + 1
        });
        let stamp = match version {
            Version::ETag => format!("ETag: \"v{n}\""),
            Version::LastModified => {
                format!("Last-Modified: Sun, 06 Dec 2026 01:{:02}:00 GMT", n % 60)
            }
        };
        let (status, body, extra) = match range {
            Some(r) => (
                "206 Partial Content",
                &bytes[r.clone()],
                format!(
                    "Content-Range: bytes {}-{}/{}\r\n",
                    r.start,
                    r.end - 1,
                    bytes.len()
                ),
            ),
            None => ("200 OK", &bytes[..], String::new()),
        };
        let mut s = stream;
        let _ = write!(
            s,
            "HTTP/1.1 {status}\r\nContent-Length: {}\r\n{extra}{stamp}\r\nConnection: close\r\n\r\n",
            body.len()
        );
        if !request.head {
            let _ = s.write_all(body);
        }
    })
}

/// Case 9: every response is compared with the first; another version is an error naming the
/// URL, and nothing read from it is cached.
fn a_changing_object_is_an_error_and_never_cached(version: Version) {
    let url = changing_server(std::fs::read(scene().join("map.sfpm")).unwrap(), version);
    if let Some(bin) = compare_bin() {
        let other = tempfile::tempdir().unwrap();
        let o = std::process::Command::new(&bin)
            .args(["verify", &url])
            .env("SFPMAP_CACHE_DIR", other.path())
            .output()
            .unwrap();
        let cached = walk(other.path())
            .iter()
            .filter(|p| p.extension().is_some_and(|e| e == "bin"))
            .count();
        eprintln!(
            "{}: {}, {cached} entries cached: {}",
            bin.display(),
            o.status,
            String::from_utf8_lossy(&o.stderr).trim()
        );
    }
    let cache_dir = tempfile::tempdir().unwrap();
    let env = [("SFPMAP_CACHE_DIR", cache_dir.path().display().to_string())];
    let err = failed(&sfpmap(&["verify", &url], &env));
    assert!(
        err.contains(&url) && err.contains("the object changed while reading"),
        "{err}"
    );
    let cached: Vec<PathBuf> = walk(cache_dir.path())
        .into_iter()
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    assert!(cached.is_empty(), "{cached:?}");
}

#[test]
fn remote_responses_with_another_etag_are_an_error_even_if_if_match_is_ignored() {
    a_changing_object_is_an_error_and_never_cached(Version::ETag);
}

#[test]
fn remote_responses_with_another_last_modified_are_an_error_without_an_etag() {
    a_changing_object_is_an_error_and_never_cached(Version::LastModified);
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let kind = e.file_type().unwrap();
        if kind.is_dir() {
            out.extend(walk(&e.path()));
        } else {
            out.push(e.path());
        }
    }
    out
}

/// Case 6: a folder of the cache that is a symbolic link to another folder holding files named
/// like cache entries (and an `object.json`): eviction (`SFPMAP_CACHE_MAX_BYTES`) leaves them
/// alone, and the command warns.
#[test]
fn remote_cache_eviction_never_follows_a_symlinked_folder() {
    let nginx = Nginx::start();
    std::fs::copy(scene().join("l2s.sfpm"), nginx.root.join("m.sfpm")).unwrap();
    let url = nginx.url("m.sfpm");
    if let Some(bin) = compare_bin() {
        let left = evict_beside_a_link(&bin, &url).0;
        eprintln!("{}: {left} of 3 files behind the link left", bin.display());
    }
    let (left, o) = evict_beside_a_link(Path::new(env!("CARGO_BIN_EXE_sfpmap")), &url);
    ok(&o);
    assert_eq!(left, 3, "files were removed through the link");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("symbolic link"), "{err}");
}

/// `bin slice URL` with a cache of 1 byte whose folder holds a link `00000000000000aa` to a
/// folder that looks like a URL's (an `object.json`, three entries): how many of the three
/// are left, and the output.
fn evict_beside_a_link(bin: &Path, url: &str) -> (usize, std::process::Output) {
    let cache_dir = tempfile::tempdir().unwrap();
    let victim = tempfile::tempdir().unwrap();
    std::fs::write(victim.path().join("object.json"), b"{}").unwrap();
    let entries: Vec<PathBuf> = (0..3)
        .map(|i| victim.path().join(format!("0123456789abcdef-{i}.bin")))
        .collect();
    for e in &entries {
        std::fs::write(e, vec![1u8; 4096]).unwrap();
    }
    let sections = cache_dir.path().join("remote-sections");
    std::fs::create_dir(&sections).unwrap();
    std::os::unix::fs::symlink(victim.path(), sections.join("00000000000000aa")).unwrap();
    let t = tempfile::tempdir().unwrap();
    let out = t.path().join("s.sfpm");
    let o = std::process::Command::new(bin)
        .args(["slice", url, "--level", "2", "-o", out.to_str().unwrap()])
        .env("SFPMAP_CACHE_DIR", cache_dir.path())
        .env("SFPMAP_CACHE_MAX_BYTES", "1")
        .output()
        .unwrap();
    assert!(std::fs::symlink_metadata(sections.join("00000000000000aa"))
        .unwrap()
        .is_symlink());
    (entries.iter().filter(|e| e.exists()).count(), o)
}

/// What a hostile server streams at most after its headers: enough that a client holding it
/// all is far over the tests' 200 MB, little enough to be quick on loopback.
const FLOOD: usize = 320 << 20;

/// Writes `FLOOD` bytes of `b'z'` to `stream` a MiB at a time, until the client hangs up.
fn flood(mut stream: &std::net::TcpStream) {
    use std::io::Write;
    let chunk = vec![b'z'; 1 << 20];
    for _ in 0..FLOOD >> 20 {
        if stream.write_all(&chunk).is_err() {
            return;
        }
    }
}

/// `verify URL` by this build under GNU time, printing `SFPMAP_COMPARE_BIN`'s figures first
/// when set (each against a server of its own from `server`): exit 1, a one-line error that
/// names the URL and contains `what`, and a peak RSS of at most 200 MB.
fn verify_fails_small(server: impl Fn() -> String, what: &str) {
    if let Some(bin) = compare_bin() {
        let url = server();
        let (rss, out) = peak_rss(&bin, &["verify", &url], &no_cache());
        eprintln!(
            "{}: peak RSS {rss} bytes, {}: {}",
            bin.display(),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let url = server();
    let (rss, out) = peak_rss(
        Path::new(env!("CARGO_BIN_EXE_sfpmap")),
        &["verify", &url],
        &no_cache(),
    );
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    eprintln!("verify URL: peak RSS {rss} bytes: {err}");
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "one line: {err}");
    assert!(err.contains(&url) && err.contains(what), "{err}");
    assert!(rss <= 200_000_000, "peak RSS {rss} bytes");
}

/// A server that answers every range request with `200` and 1000 bytes (it ignores ranges),
/// HEAD with 1000 bytes, and the unranged GET that follows with a Content-Length of `claimed`
/// and up to [`FLOOD`] bytes.
fn ignoring_range_server(claimed: u64) -> String {
    use std::io::Write;
    loopback_server(move |_, request, stream| {
        let stamp =
            "ETag: \"a\"\r\nLast-Modified: Mon, 01 Jan 2024 00:00:00 GMT\r\nConnection: close";
        let mut s = stream;
        if request.head || request.range.is_some() {
            let _ = write!(
                s,
                "HTTP/1.1 200 OK\r\nContent-Length: 1000\r\n{stamp}\r\n\r\n"
            );
            if !request.head {
                let _ = s.write_all(&[b'x'; 1000]);
            }
            return;
        }
        let _ = write!(
            s,
            "HTTP/1.1 200 OK\r\nContent-Length: {claimed}\r\n{stamp}\r\n\r\n"
        );
        flood(stream);
    })
}

/// A server that ignores range requests and whose whole-object answer claims more than its
/// HEAD gave (2^62 bytes: reserved up front, it aborted the process; 4 GiB: held as it came):
/// an error naming the URL before any of the body is held, in little memory.
#[test]
fn remote_whole_object_answer_larger_than_its_head_is_an_error_in_little_memory() {
    for claimed in [1u64 << 62, 4 << 30] {
        verify_fails_small(|| ignoring_range_server(claimed), "its HEAD gave");
    }
}

/// A server that answers each range with `206` and the right Content-Range, but a
/// Content-Length of 100 GB and a flood of bytes: an error naming the URL as soon as more than
/// the range arrives, in little memory.
#[test]
fn remote_ranged_answer_longer_than_the_range_is_an_error_in_little_memory() {
    let server = || {
        loopback_server(|_, request, stream| {
            use std::io::Write;
            let (a, b) = request.range.map_or((0, None), |r| r);
            let b = b.unwrap_or(999_999).min(999_999);
            let mut s = stream;
            let _ = write!(
                s,
                "HTTP/1.1 206 Partial Content\r\nContent-Range: bytes {a}-{b}/1000000\r\nContent-Length: 100000000000\r\nETag: \"a\"\r\nLast-Modified: Mon, 01 Jan 2024 00:00:00 GMT\r\nConnection: close\r\n\r\n"
            );
            flood(stream);
        })
    };
    verify_fails_small(server, "sent more than the 65536 bytes asked for");
}
