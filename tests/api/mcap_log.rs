//! `session::mcap_log`: the images of an MCAP log written here, localized through a session
//! over a map the built-in sfp-v1's queries fit (random points, so nothing localizes; the
//! frames still run the whole pipeline). A damaged chunk is skipped and reported through the
//! reporter, a missing topic is an error listing the topics, and a session that does not
//! extract is refused.
#![cfg(feature = "mcap")]

use crate::common;
use sfpmap::format::Map;
use sfpmap::geometry::Camera;
use sfpmap::progress::{Reporter, Silent};
use sfpmap::session::mcap_log::{localize_log, ImageLog, LogError};
use sfpmap::session::{QuerySource, Session, SessionError};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

const TOPIC: &str = "/cam/compressed";
const CAMERA: &str = "SIMPLE_PINHOLE 160 120 100 80 60";

/// What a run reported: its stages, progress and warnings.
#[derive(Default)]
struct Recorder {
    stages: Mutex<Vec<(String, Option<u64>)>>,
    advanced: AtomicU64,
    warnings: Mutex<Vec<String>>,
}

impl Reporter for Recorder {
    fn start(&self, stage: &str, total: Option<u64>) {
        self.stages.lock().unwrap().push((stage.to_owned(), total));
    }
    fn advance(&self, n: u64) {
        self.advanced.fetch_add(n, Ordering::Relaxed);
    }
    fn warn(&self, message: &str) {
        self.warnings.lock().unwrap().push(message.to_owned());
    }
}

/// A textured 160×120 PNG, different for each `seed`.
fn png(seed: u64) -> Vec<u8> {
    let mut rng = common::Rng(seed);
    let image = image::RgbImage::from_fn(160, 120, |x, y| {
        let v = ((x / 8 + y / 8) % 2) as f32 * 160.0 + (rng.unit() + 1.0) * 45.0;
        image::Rgb([v as u8; 3])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    image.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// A log of `images` PNGs on [`TOPIC`] stamped 1, 2, ... s, one uncompressed chunk each.
fn write_log(path: &Path, images: u32) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    let options = mcap::WriteOptions::new()
        .compression(None)
        .chunk_size(Some(1024));
    let mut w = options.create(&mut out).unwrap();
    let schema = w
        .add_schema("sensor_msgs/msg/CompressedImage", "ros2msg", b"")
        .unwrap();
    let channel = w
        .add_channel(schema, TOPIC, "cdr", &BTreeMap::new())
        .unwrap();
    for i in 1..=images {
        let time = u64::from(i) * 1_000_000_000;
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: i,
            log_time: time,
            publish_time: time,
        };
        let message = common::compressed_image((i as i32, 0), "cam", "png", &png(i.into()));
        w.write_to_known_channel(&header, &message).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    let bytes = out.into_inner();
    std::fs::write(path, &bytes).unwrap();
    bytes
}

/// The chunk records `(offset, body length)` of a log, in file order.
fn chunks(bytes: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut at = 8;
    while bytes[at] != 0x0f {
        let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().unwrap()) as usize;
        if bytes[at] == 0x06 {
            out.push((at, len));
        }
        at += 9 + len;
    }
    out
}

/// A session over the sfp-v1-shaped map that extracts its queries, in sequence.
fn session(dir: &Path) -> Session {
    let path = dir.join("m.sfpm");
    std::fs::write(&path, common::sfp_level_2_map(&[])).unwrap();
    let map = Arc::new(Map::open(&path).unwrap());
    Session::builder(map, "m.sfpm")
        .source(QuerySource::Images {
            folder: None,
            model: None,
        })
        .sequence(true)
        .build(&Silent)
        .unwrap()
}

#[test]
fn a_damaged_chunk_is_skipped_and_reported_and_the_other_frames_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let clean = dir.path().join("clean.mcap");
    let bytes = write_log(&clean, 3);
    let found = chunks(&bytes);
    assert_eq!(found.len(), 3, "one chunk per image");
    let (at, len) = found[1];
    let mut damaged = bytes.clone();
    // Inside the second chunk's records (the PNG), well past its header.
    damaged[at + 9 + len / 2] ^= 0x10;
    let input = dir.path().join("damaged.mcap");
    std::fs::write(&input, &damaged).unwrap();

    let session = session(dir.path());
    let camera = Camera::parse(CAMERA).unwrap();
    let reporter = Recorder::default();
    let found = localize_log(&session, &input, TOPIC, &camera, 2, &reporter).unwrap();
    assert_eq!(found.images(), 2);
    assert_eq!(found.frames().len(), 2);
    let stamps: Vec<i64> = found.frames().iter().map(|f| f.stamp.sec).collect();
    assert_eq!(stamps, [1, 3]);
    assert!(found.frames().iter().all(|f| !f.undecodable));
    assert_eq!(found.skipped_count(), 1);
    assert_eq!(found.unreadable_images(), Some(1), "the summary counts 3");
    let skipped = &found.skipped()[0];
    assert!(
        skipped.starts_with(&format!("chunk 2 of 3 at byte {at}: chunk CRC mismatch"))
            && skipped.ends_with("chunk skipped"),
        "{skipped}"
    );
    let warnings = reporter.warnings.lock().unwrap().clone();
    assert_eq!(warnings, [format!("{}: {skipped}", input.display())]);
    assert_eq!(
        *reporter.stages.lock().unwrap(),
        [("localizing".to_owned(), Some(3))]
    );
    assert_eq!(reporter.advanced.load(Ordering::Relaxed), 2);
    // Random map points: nothing localizes, each frame says why.
    assert_eq!(found.localized(), 0);
    assert_eq!(found.failed().count(), 2);

    // The output copies the two images read (no pose: none localized), and the TUM file
    // has its header only.
    let out = dir.path().join("out.mcap");
    found.write_mcap(&out, "/pose", "map", true).unwrap();
    let written = std::fs::read(&out).unwrap();
    let topics: Vec<String> = mcap::MessageStream::new(&written)
        .unwrap()
        .map(|m| m.unwrap().channel.topic.clone())
        .collect();
    assert_eq!(topics, [TOPIC, TOPIC]);
    let tum = dir.path().join("out.tum");
    found.write_tum(&tum).unwrap();
    assert_eq!(std::fs::read_to_string(&tum).unwrap().lines().count(), 1);
    // Neither output may be the log it read: refused, the log untouched.
    for e in [
        found.write_mcap(&input, "/pose", "map", true).unwrap_err(),
        found.write_tum(&input).unwrap_err(),
    ] {
        assert!(matches!(e, LogError::Output(_)), "{e:?}");
        assert!(e.to_string().contains("damaged.mcap"), "{e}");
    }
    assert_eq!(std::fs::read(&input).unwrap(), damaged);

    // The clean log: all read, no warning.
    let reporter = Recorder::default();
    let found = localize_log(&session, &clean, TOPIC, &camera, 1, &reporter).unwrap();
    assert_eq!((found.images(), found.skipped_count()), (3, 0));
    assert_eq!(found.unreadable_images(), None);
    assert!(reporter.warnings.lock().unwrap().is_empty());
}

#[test]
fn a_missing_topic_is_an_error_listing_the_topics_before_anything_is_decoded() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("log.mcap");
    write_log(&input, 1);
    let e = ImageLog::open(&input, "/camera/image", &Silent)
        .err()
        .expect("refused");
    assert!(matches!(e, LogError::NoTopic { .. }), "{e:?}");
    assert_eq!(
        e.to_string(),
        format!(
            "{}: no topic \"/camera/image\"; topics present: \"{TOPIC}\" \
             (\"sensor_msgs/msg/CompressedImage\")",
            input.display()
        )
    );
    // The camera-info topic is checked the same way.
    let log = ImageLog::open(&input, TOPIC, &Silent).unwrap();
    assert_eq!(log.expected_images(), Some(1));
    let e = log.camera_from_info("/camera/info").expect_err("refused");
    assert!(
        e.to_string()
            .contains("no topic \"/camera/info\"; topics present: "),
        "{e}"
    );
}

#[test]
fn a_session_that_does_not_extract_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("log.mcap");
    write_log(&input, 1);
    let path = dir.path().join("m.sfpm");
    std::fs::write(&path, common::sfp_level_2_map(&[])).unwrap();
    let map = Arc::new(Map::open(&path).unwrap());
    let session = Session::builder(map, "m.sfpm").build(&Silent).unwrap();
    let camera = Camera::parse(CAMERA).unwrap();
    let e = localize_log(&session, &input, TOPIC, &camera, 1, &Silent).expect_err("refused");
    assert!(
        matches!(e, LogError::Session(SessionError::NoSource(_))),
        "{e:?}"
    );
    assert!(e.to_string().starts_with("m.sfpm: MCAP images need"), "{e}");
    // The crate's error keeps the text.
    let text = e.to_string();
    assert_eq!(sfpmap::Error::from(e).to_string(), text);
}
