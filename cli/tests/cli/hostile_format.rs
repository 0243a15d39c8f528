//! Hostile and careless input to the map format (issue 12): maps crafted with correct
//! checksums (`common::craft`) whose layout is valid but whose numbers are absurd, and paths
//! that are not regular files. Each must be refused, or handled, in bounded memory and time.

use crate::common;

use common::{
    craft, craft_level, craft_level_points, craft_metadata, craft_points, run_limited, Crafted,
    Limited,
};
use sfpmap::format::{Dtype, Map, SectionKind};
use sfpmap::fuzzing::NO_LEVEL;
use std::ffi::OsStr;
use std::path::Path;
use std::time::Duration;

/// Generous: the debug binary needs about 100 MB of address space for small maps.
const MEMORY: u64 = 300 << 20;
/// Generous too: each case takes well under a second once fixed, minutes before.
const TIMEOUT: Duration = Duration::from_secs(60);

fn sfpmap(args: &[&OsStr]) -> Limited {
    run_limited(env!("CARGO_BIN_EXE_sfpmap"), args, MEMORY, TIMEOUT)
}

fn os(s: &str) -> &OsStr {
    OsStr::new(s)
}

/// Exit 1, one line `error: <path>: ...` that contains `what`.
fn assert_refused(out: &Limited, path: &Path, what: &str) {
    assert!(!out.timed_out, "ran past {TIMEOUT:?}: {out:?}");
    assert_eq!(out.code, Some(1), "{out:?}");
    let line = out.stderr.trim_end();
    assert!(!line.contains('\n'), "more than one line: {line}");
    let prefix = format!("error: {}: ", path.display());
    assert!(
        line.starts_with(&prefix),
        "{line:?} does not start {prefix:?}"
    );
    assert!(line.contains(what), "{line:?} does not say {what:?}");
}

#[test]
fn crafted_map_opens_and_verifies() {
    let bytes = craft(
        &craft_metadata(vec![craft_level(0, 8, 4)]),
        &[
            craft_points(3),
            craft_level_points(0, &[0, 2]),
            Crafted::raw(
                SectionKind::LevelDescShort,
                0,
                Dtype::F16,
                2,
                4,
                vec![0; 16],
            ),
        ],
    );
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    assert_eq!(map.level(0).unwrap().len(), 2);
}

// ---- Inputs that are not regular files ("No such device (os error 19)", finding 8) ----

#[test]
fn directory_as_map_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let err = Map::open(dir.path()).unwrap_err();
    assert_eq!(err.to_string(), "is a folder, not a regular file");
    for command in ["verify", "info"] {
        let out = sfpmap(&[os(command), dir.path().as_os_str()]);
        assert_refused(&out, dir.path(), "is a folder, not a regular file");
    }
}

#[test]
fn fifo_as_map_is_refused_without_blocking() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("map.sfpm");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    // In a thread: an open that blocks (no writer ever comes) must fail the test, not hang it.
    let (tx, rx) = std::sync::mpsc::channel();
    let path = fifo.clone();
    std::thread::spawn(move || {
        let _ = tx.send(Map::open(&path).map(|_| ()).map_err(|e| e.to_string()));
    });
    let outcome = rx
        .recv_timeout(Duration::from_secs(20))
        .expect("Map::open blocked on a FIFO");
    assert_eq!(outcome, Err("is a FIFO, not a regular file".into()));
    let out = sfpmap(&[os("verify"), fifo.as_os_str()]);
    assert_refused(&out, &fifo, "is a FIFO, not a regular file");
}

#[test]
fn device_as_map_is_refused() {
    let null = Path::new("/dev/null");
    let err = Map::open(null).unwrap_err();
    assert_eq!(err.to_string(), "is a character device, not a regular file");
    let out = sfpmap(&[os("info"), null.as_os_str()]);
    assert_refused(&out, null, "is a character device, not a regular file");
}

#[test]
fn a_symlink_to_a_map_still_opens() {
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("real.sfpm");
    std::fs::write(&map, common::minimal()).unwrap();
    let link = dir.path().join("link.sfpm");
    std::os::unix::fs::symlink(&map, &link).unwrap();
    Map::open(&link).unwrap().verify().unwrap();
}

// ---- Open in O(sections) (finding 6) ----

/// 65,535 empty geometry-only levels (every level id there is) and 65,536 sections, the
/// table's cap: about 11 MB.
fn many_levels() -> Vec<u8> {
    let ids = 0..NO_LEVEL;
    let mut metadata = craft_metadata(ids.clone().map(|l| craft_level(l, 8, 2)).collect());
    metadata["geometry_only"] = true.into();
    let mut sections = vec![craft_points(1)];
    sections.extend(ids.map(|l| craft_level_points(l, &[])));
    craft(&metadata, &sections)
}

#[test]
fn sixty_five_thousand_levels_open_verify_info_and_export_in_linear_time() {
    let bytes = many_levels();
    let map = Map::from_bytes(&bytes).unwrap();
    assert_eq!(map.levels().count(), 65_535);
    assert_eq!(map.level(65_534).unwrap().len(), 0);
    drop(map);

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("levels.sfpm");
    std::fs::write(&path, &bytes).unwrap();
    let ply = dir.path().join("out.ply");
    let sliced = dir.path().join("sliced.sfpm");
    let every_level: Vec<String> = (0..NO_LEVEL).map(|l| l.to_string()).collect();
    let mut slice = vec![os("slice"), path.as_os_str(), os("-o"), sliced.as_os_str()];
    for l in &every_level {
        slice.extend([os("--level"), os(l)]);
    }
    for args in [
        slice,
        vec![os("verify"), sliced.as_os_str()],
        vec![os("verify"), path.as_os_str()],
        vec![os("info"), path.as_os_str()],
        vec![os("info"), os("--json"), path.as_os_str()],
        vec![os("export"), path.as_os_str(), os("--ply"), ply.as_os_str()],
    ] {
        let out = sfpmap(&args);
        assert!(!out.timed_out, "{args:?} ran past {TIMEOUT:?}");
        assert_eq!(out.code, Some(0), "{args:?}: {}", out.stderr);
        eprintln!("{}: {:.2} s", args[0].display(), out.seconds);
    }
}

// ---- One decode budget per open map (finding 5) ----

/// 160 optional zstd sections of unknown kinds, each a ~2 KB frame of 64 MiB of zeros:
/// every one under the per-section cap (256 × the file length), 10 GiB together.
fn decode_budget_bomb() -> Vec<u8> {
    let raw = vec![0u8; 64 << 20];
    let frame = Crafted::zstd(
        SectionKind::Unknown(0x7000),
        NO_LEVEL,
        Dtype::U8,
        raw.len() as u64,
        1,
        &raw,
    );
    let mut metadata = craft_metadata(vec![craft_level(0, 8, 2)]);
    metadata["geometry_only"] = true.into();
    let mut sections = vec![craft_points(1), craft_level_points(0, &[0])];
    for i in 0..160 {
        let mut s = frame.clone().optional();
        s.kind = 0x7000 + i;
        sections.push(s);
    }
    craft(&metadata, &sections)
}

#[test]
fn zstd_sections_share_one_decode_budget() {
    let bytes = decode_budget_bomb();
    assert!(bytes.len() < 400_000, "{} bytes", bytes.len());
    let cap = sfpmap::fuzzing::decode_cap(bytes.len() as u64);
    assert!(
        64 << 20 < cap,
        "each section must be under the per-section cap"
    );

    let map = Map::from_bytes(&bytes).unwrap();
    let err = map.verify().unwrap_err();
    assert_eq!(err.kind_name(), "decode_budget_exceeded", "{err}");
    drop(map);

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bomb.sfpm");
    std::fs::write(&path, &bytes).unwrap();
    let out = sfpmap(&[os("verify"), path.as_os_str()]);
    assert_refused(&out, &path, "decode budget");
    let info = sfpmap(&[os("info"), path.as_os_str()]);
    assert_eq!(info.code, Some(0), "{info:?}");
    let sliced = dir.path().join("sliced.sfpm");
    let slice = sfpmap(&[
        os("slice"),
        path.as_os_str(),
        os("--level"),
        os("0"),
        os("-o"),
        sliced.as_os_str(),
    ]);
    // `slice` checks every section first, streaming, so it meets the same budget as verify.
    assert_refused(&slice, &path, "decode budget");
    assert!(!sliced.exists());
}

// ---- Sizes from the metadata are checked before anything is sized from them (2, 1) ----

/// A one-level map: `points` points, the level holding all of them with `short` and no `rest`.
fn one_level(dim_full: u64, dim_short: u64, points: u32) -> Vec<u8> {
    let held: Vec<u32> = (0..points).collect();
    craft(
        &craft_metadata(vec![craft_level(0, dim_full, dim_short)]),
        &[
            craft_points(u64::from(points)),
            craft_level_points(0, &held),
            Crafted::raw(
                SectionKind::LevelDescShort,
                0,
                Dtype::F16,
                u64::from(points),
                dim_short,
                vec![0; (u64::from(points) * dim_short * 2) as usize],
            ),
        ],
    )
}

fn open_error(bytes: &[u8]) -> String {
    match Map::from_bytes(bytes) {
        Ok(_) => panic!("opens"),
        Err(e) => format!("{}: {e}", e.kind_name()),
    }
}

#[test]
fn absurd_descriptor_dims_are_refused_at_open() {
    // Empty levels claiming 2^32 − 1 and 2^24 dimensions (finding 2).
    for dim_full in [u64::from(u32::MAX), 1 << 24] {
        let err = open_error(&one_level(dim_full, 0, 0));
        assert!(err.starts_with("bad_metadata: "), "{err}");
        assert!(err.contains("at most 4096"), "{err}");
    }
    // No descriptor dimension at all in a map with descriptors (finding 1's map).
    let err = open_error(&one_level(8, 0, 2));
    assert!(err.starts_with("bad_metadata: "), "{err}");
    assert!(err.contains("dim_short"), "{err}");
    // The largest allowed dims open.
    Map::from_bytes(&one_level(4096, 4096, 1))
        .unwrap()
        .verify()
        .unwrap();
}

#[test]
fn absurd_column_counts_are_refused_at_open() {
    // Empty sections whose columns no descriptor has: 0 bytes, so only the cap refuses them.
    for (kind, level) in [
        (SectionKind::ImageGlobal, NO_LEVEL),
        (SectionKind::LevelProjection, 0),
        (SectionKind::Unknown(0x7F01), NO_LEVEL),
    ] {
        let dtype = if kind == SectionKind::LevelProjection {
            Dtype::F32
        } else {
            Dtype::F16
        };
        let mut metadata = craft_metadata(vec![craft_level(0, 0, 0)]);
        metadata["geometry_only"] = true.into();
        let mut sections = vec![craft_points(1), craft_level_points(0, &[])];
        let mut extra = Crafted::raw(kind, level, dtype, 0, 1 << 40, Vec::new());
        if kind == SectionKind::ImageGlobal {
            // image_global needs images; with none it is inconsistent whatever its columns.
            sections.extend(no_images());
        }
        if matches!(kind, SectionKind::Unknown(_)) {
            // Unknown kinds are not the format's to bound: skipped, still opens.
            extra = extra.optional();
            sections.push(extra);
            Map::from_bytes(&craft(&metadata, &sections)).unwrap();
            continue;
        }
        sections.push(extra);
        let err = open_error(&craft(&metadata, &sections));
        assert!(err.starts_with("wrong_layout: "), "{kind}: {err}");
        assert!(err.contains("at most 4096"), "{kind}: {err}");
    }
}

/// The image sections of a map with zero images.
fn no_images() -> Vec<Crafted> {
    vec![
        Crafted::raw(
            SectionKind::ImagePoses,
            NO_LEVEL,
            Dtype::F64,
            0,
            7,
            Vec::new(),
        ),
        Crafted::raw(
            SectionKind::ImageCameras,
            NO_LEVEL,
            Dtype::U32,
            0,
            1,
            Vec::new(),
        ),
        Crafted::raw(
            SectionKind::ImageNameOffsets,
            NO_LEVEL,
            Dtype::U64,
            1,
            1,
            vec![0; 8],
        ),
        Crafted::raw(
            SectionKind::ImageNames,
            NO_LEVEL,
            Dtype::U8,
            0,
            1,
            Vec::new(),
        ),
    ]
}

#[test]
fn absurd_camera_sizes_are_refused_at_open() {
    for (width, height) in [(1u64 << 40, 480u64), (640, u64::MAX), (0, 480)] {
        let mut metadata = craft_metadata(vec![]);
        metadata["cameras"] = serde_json::json!([{
            "model": "PINHOLE", "width": width, "height": height, "params": [500.0, 500.0, 320.0, 240.0],
        }]);
        let err = open_error(&craft(&metadata, &[craft_points(1)]));
        assert!(
            err.starts_with("bad_metadata: ") && err.contains("camera 0: size"),
            "{width}x{height}: {err}"
        );
    }
}

#[test]
fn zero_short_dims_need_a_rest_block() {
    let bytes = craft(
        &craft_metadata(vec![craft_level(0, 4, 0)]),
        &[
            craft_points(2),
            craft_level_points(0, &[0, 1]),
            Crafted::raw(SectionKind::LevelDescShort, 0, Dtype::F16, 2, 0, Vec::new()),
            Crafted::raw(SectionKind::LevelDescRest, 0, Dtype::F16, 2, 4, vec![0; 16]),
        ],
    );
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    // Dropping `rest` would leave the level no dimension at all: refused, not written.
    let options = sfpmap::format::SliceOptions {
        levels: vec![0],
        short: true,
        codec: None,
        zstd_level: 1,
        minimal: false,
    };
    let err = sfpmap::format::slice(&map, &options).unwrap_err();
    assert_eq!(err.kind_name(), "invalid_input", "{err}");
}

/// Writes the crafted maps to `$SFPMAP_HOSTILE_OUT` for measuring by hand (release binary,
/// `/usr/bin/time -v`): `cargo test --release --all-features --test cli
/// hostile_format::write_crafted_maps -- --ignored`.
#[test]
#[ignore]
fn write_crafted_maps() {
    let dir = std::path::PathBuf::from(std::env::var("SFPMAP_HOSTILE_OUT").unwrap());
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("levels-65535.sfpm"), many_levels()).unwrap();
    std::fs::write(dir.join("zstd-160.sfpm"), decode_budget_bomb()).unwrap();
}

/// The writer refuses what open would refuse, instead of writing a map nothing can read (a
/// NaN becomes JSON `null`, finding 16's format side).
#[test]
fn writer_refuses_maps_open_would_refuse() {
    use sfpmap::format::{CameraInfo, Descriptors, MapWriter};
    let camera = |params: Vec<f64>, width: u64| CameraInfo {
        id: None,
        model: "PINHOLE".into(),
        width,
        height: 480,
        params,
    };
    let mut cases: Vec<(&str, MapWriter<'static>)> = Vec::new();
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    w.add_camera(camera(vec![500.0, f64::NAN, 320.0, 240.0], 640));
    cases.push(("a parameter is not finite", w));
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    w.add_camera(camera(vec![500.0, 500.0, 320.0, 240.0], 0));
    cases.push(("size 0x480", w));
    let mut w = MapWriter::default();
    w.set_points_world(&[[f64::NAN, 0.0, 0.0]]);
    cases.push(("origin is not finite", w));
    // Finite in f64, but 1e308 apart: relative to their mean they overflow f32.
    let mut w = MapWriter::default();
    w.set_points_world(&[[1e308, 0.0, 0.0], [-1e308, 0.0, 0.0]]);
    cases.push(("point 0: position is not finite", w));
    let mut w = MapWriter::default();
    static RELATIVE: [[f32; 3]; 2] = [[0.0; 3], [1.0, f32::NAN, 0.0]];
    w.set_points(&RELATIVE);
    cases.push(("point 1: position is not finite", w));
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    w.add_level(common::level_info(0, 8.0, 5000, 4), &[], None, false)
        .unwrap();
    cases.push(("dim_full 5000", w));
    for (what, w) in cases {
        let err = w.to_bytes().unwrap_err();
        assert_eq!(err.kind_name(), "invalid_input", "{what}: {err}");
        assert!(err.to_string().contains(what), "{what}: {err}");
    }
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    let values = [0.5f32; 4];
    let err = w
        .add_level(
            common::level_info(0, 8.0, 4, 0),
            &[0],
            Some(Descriptors::F32(&values)),
            false,
        )
        .unwrap_err();
    assert!(err.to_string().contains("no descriptor dimension"), "{err}");
}

/// Every map the writer writes fits its own decode budget, even one of many sections that
/// each compress past 256:1 but stay under the per-section cap's 1 MiB floor.
#[test]
fn writer_keeps_every_map_within_the_decode_budget() {
    use sfpmap::format::{Codec, MapWriter};
    let zeros = vec![0u8; 1 << 20];
    let mut w = MapWriter::default();
    w.set_points_world(&[[0.0; 3]]);
    for i in 0..65 {
        w.add_raw_section(
            SectionKind::Unknown(0x7000 + i),
            NO_LEVEL,
            Dtype::U8,
            zeros.len() as u64,
            1,
            false,
            std::borrow::Cow::Borrowed(&zeros),
            Some(Codec::Zstd),
        )
        .unwrap();
    }
    let bytes = w.to_bytes().unwrap();
    let map = Map::from_bytes(&bytes).unwrap();
    map.verify().unwrap();
    assert!(map.decoded_bytes() <= map.decode_budget());
}

/// `verify` streams: sections that together decode past the memory cap, each far under it and
/// all within the decode budget, verify in about one section's memory (finding 5's other half:
/// verify kept every decoded section).
#[test]
fn verify_streams_sections() {
    let raw = vec![0u8; 40 << 20];
    let frame = Crafted::zstd(
        SectionKind::Unknown(0x7000),
        NO_LEVEL,
        Dtype::U8,
        raw.len() as u64,
        1,
        &raw,
    );
    drop(raw);
    // 2 MiB of raw padding makes the budget 512 MiB: room for 10 x 40 MiB.
    let padding = Crafted::raw(
        SectionKind::Unknown(0x6FFF),
        NO_LEVEL,
        Dtype::U8,
        2 << 20,
        1,
        vec![0; 2 << 20],
    )
    .optional();
    let mut sections = vec![craft_points(1), padding];
    for i in 0..10 {
        let mut s = frame.clone().optional();
        s.kind = 0x7000 + i;
        sections.push(s);
    }
    let bytes = craft(&craft_metadata(vec![]), &sections);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.sfpm");
    std::fs::write(&path, &bytes).unwrap();
    let out = sfpmap(&[os("verify"), path.as_os_str()]);
    assert_eq!(out.code, Some(0), "{out:?}");
}

/// The fuzz bodies' checksum fix-up makes a damaged map reach the checks behind the checksums.
#[test]
fn fuzz_fixup_reaches_past_the_checksums() {
    use sfpmap::fuzzing::fix_checksums;
    let good = common::minimal();
    let mut bad = good.clone();
    // The low mantissa byte of the last position (a flip in its exponent byte could make it
    // NaN, which the content check refuses).
    let last = bad.len() - 4;
    bad[last] ^= 0x40;
    let err = Map::from_bytes(&bad).unwrap().verify().unwrap_err();
    assert_eq!(err.kind_name(), "checksum_mismatch");
    Map::from_bytes(&fix_checksums(&bad))
        .unwrap()
        .verify()
        .unwrap();
    // A metadata byte: the index checksum first, then the JSON itself.
    let mut bad = good.clone();
    let header = sfpmap::fuzzing::Header::decode(&good).unwrap();
    bad[header.metadata_offset as usize] = b'[';
    assert_eq!(
        Map::from_bytes(&bad).unwrap_err().kind_name(),
        "index_checksum_mismatch"
    );
    assert_eq!(
        Map::from_bytes(&fix_checksums(&bad))
            .unwrap_err()
            .kind_name(),
        "bad_metadata"
    );
    assert_eq!(fix_checksums(&good), good);
}

/// Counts a reader takes from the table before decoding (points, level points) are bounded
/// at open: the zstd sections of known kinds may not declare more than the decode budget
/// together, and a level may not hold more points than the map.
#[test]
fn declared_sizes_are_bounded_at_open() {
    let zeros = vec![0u8; 1 << 20];
    let rows = zeros.len() as u64 / 4;
    let mut metadata = craft_metadata((0..70).map(|l| craft_level(l, 8, 2)).collect());
    metadata["geometry_only"] = true.into();
    let positions = vec![0u8; rows as usize * 12];
    let mut sections = vec![Crafted::zstd(
        SectionKind::PointPositions,
        NO_LEVEL,
        Dtype::F32,
        rows,
        3,
        &positions,
    )];
    for l in 0..70 {
        sections.push(Crafted::zstd(
            SectionKind::LevelPoints,
            l,
            Dtype::U32,
            rows,
            1,
            &zeros,
        ));
    }
    let bytes = craft(&metadata, &sections);
    assert!(bytes.len() < 20_000, "{}", bytes.len());
    let err = open_error(&bytes);
    assert!(err.starts_with("decode_budget_exceeded: "), "{err}");

    // One point, a level claiming two.
    let mut metadata = craft_metadata(vec![craft_level(0, 8, 2)]);
    metadata["geometry_only"] = true.into();
    let bytes = craft(
        &metadata,
        &[craft_points(1), craft_level_points(0, &[0, 1])],
    );
    let err = open_error(&bytes);
    assert!(err.contains("level 0 holds 2 points of 1"), "{err}");
}
