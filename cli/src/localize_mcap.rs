//! `sfpmap localize --mcap IN.mcap --topic TOPIC -o OUT.mcap`: localize the images of one topic
//! of an MCAP log and write their poses as `foxglove.PoseInFrame` (and optionally TUM).
//!
//! Damaged logs ([`LogReader`]): a chunk that fails its CRC or does not decompress is skipped,
//! and a record whose length cannot be right is skipped up to the next chunk of the chunk index
//! (or, without an intact summary, ends the log). Each skip is a warning naming the file and
//! where, and `unreadable` in `--json`; what was read is localized and written, and the exit
//! status is [`SKIPPED_EXIT`] instead of 0. It is an error when no image message on the topic
//! could be read or decoded at all.

use super::super::Bars;
use super::Args;
use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::colmap::text::{escape_control_characters, quoted_name};
use sfpmap::geometry::Camera;
use sfpmap::io::mcap_io::{self, Damage, LogReader, Skipped, Stamp};
use sfpmap::io::poses::tum_line;
use sfpmap::localize::eval::median;
use sfpmap::localize::Localization;
use sfpmap::progress::Reporter;
use sfpmap::session::{self, QuerySource, Session, SessionError};
use std::collections::{BTreeMap, HashSet};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, Mutex};
use std::time::Instant;

/// The exit status of a run that skipped damaged parts of the log (1 is an error, 2 a usage
/// error).
pub const SKIPPED_EXIT: u8 = 3;

/// Damaged parts named one warning each; the rest are counted.
const MAX_DAMAGE_WARNINGS: u64 = 20;
/// Damaged parts `--json` lists; the rest are counted (a log damaged all over must not cost
/// memory per damaged record).
const MAX_DAMAGE_LISTED: usize = 1000;

/// The MCAP flags of `sfpmap localize`.
#[derive(Debug, clap::Args)]
pub struct McapArgs {
    /// Read query images from this MCAP log instead of a query list; -o is then an MCAP with
    /// foxglove.PoseInFrame messages. Example: `sfpmap localize --map m.sfpm --mcap run.mcap
    /// --topic /camera/image_raw/compressed --camera-info-topic /camera/camera_info -o poses.mcap`.
    /// Damaged chunks and records are skipped with a warning; the exit status is then 3.
    #[arg(long, requires = "topic", conflicts_with_all = ["query_list", "images", "database", "features", "format", "catalog"])]
    pub mcap: Option<PathBuf>,
    /// The image topic: sensor_msgs/msg/CompressedImage or sensor_msgs/msg/Image (cdr), or
    /// foxglove.CompressedImage (json, protobuf).
    #[arg(long, requires = "mcap")]
    pub topic: Option<String>,
    /// Intrinsics from the first sensor_msgs/msg/CameraInfo on this topic (instead of --camera).
    #[arg(long, requires = "mcap", conflicts_with = "camera")]
    pub camera_info_topic: Option<String>,
    /// Topic of the poses written to the output MCAP.
    #[arg(long, default_value = "/sfpmap/pose", requires = "mcap")]
    pub pose_topic: String,
    /// frame_id of the poses (the map's frame).
    #[arg(long, default_value = "map", requires = "mcap")]
    pub frame_id: String,
    /// Copy the input image messages (same schema and channel) into the output MCAP.
    #[arg(long, requires = "mcap")]
    pub passthrough_images: bool,
    /// Also write the trajectory as TUM (`timestamp tx ty tz qx qy qz qw`, world_from_cam,
    /// the image stamps in seconds).
    #[arg(long, requires = "mcap")]
    pub tum: Option<PathBuf>,
}

/// One image message on the topic and what became of it.
struct Frame {
    log_time: u64,
    publish_time: u64,
    /// The message's own stamp, else its log time.
    stamp: Stamp,
    /// Boxed, and reasons shared between frames: a forged log of 2 M tiny image messages
    /// (64 MiB decompressed from a few KB) keeps one small frame each.
    outcome: Result<Box<Localization>, Arc<str>>,
    /// The image could not be decoded (as opposed to decoded but not localized).
    undecodable: bool,
}

impl Frame {
    /// The frame of `message`, before anything is known of it (stamped with its log time,
    /// its outcome set by whoever finishes it).
    fn of(message: &mcap::Message<'_>) -> Frame {
        Frame {
            log_time: message.log_time,
            publish_time: message.publish_time,
            stamp: Stamp::from_nanos(message.log_time),
            outcome: Err(Arc::from("")),
            undecodable: false,
        }
    }
}

/// How the pass over the log ended.
#[derive(Default)]
struct Scan {
    messages_on_topic: usize,
    /// The topics seen, for the "no such topic" error.
    topics: Topics,
    /// The first [`MAX_DAMAGE_LISTED`] damaged parts that were skipped, as their warnings say.
    skipped: Vec<String>,
    /// How many damaged parts were skipped in all.
    skipped_count: u64,
}

fn open_log(path: &Path) -> anyhow::Result<LogReader<File>> {
    LogReader::open(path).with_context(|| path.display().to_string())
}

/// The messages again for `--passthrough-images`: the same damaged parts are skipped as in
/// the first pass, so the n-th message on the topic is the n-th frame.
fn open_stream(
    path: &Path,
    topic: &str,
) -> anyhow::Result<impl Iterator<Item = Result<mcap::Message<'static>, Damage>>> {
    Ok(open_log(path)?.data_of(topic).filter(Result::is_ok))
}

/// Topic → schema name of the messages read, recorded once per channel: a forged log can pair
/// a topic of megabytes with a million messages, and copying or comparing it per message would
/// cost their product.
#[derive(Default)]
struct Topics {
    channels: HashSet<u16>,
    names: BTreeMap<String, String>,
}

impl Topics {
    fn see(&mut self, channel: &mcap::Channel<'_>) {
        if self.channels.insert(channel.id) {
            self.names
                .entry(channel.topic.clone())
                .or_insert_with(|| schema_name(channel));
        }
    }

    fn contains(&self, topic: &str) -> bool {
        self.names.contains_key(topic)
    }
}

/// The topics for a one-line message: quoted, escaped and shortened (they come from the file).
fn topic_list(topics: &Topics) -> String {
    if topics.names.is_empty() {
        return "none".into();
    }
    let shown = 50;
    let mut list: Vec<String> = topics
        .names
        .iter()
        .take(shown)
        .map(|(t, s)| format!("{} ({})", quoted_name(t), quoted_name(s)))
        .collect();
    if topics.names.len() > shown {
        list.push(format!("and {} more", topics.names.len() - shown));
    }
    list.join(", ")
}

/// The "no such topic" error, listing the topics there are.
fn no_topic(input: &Path, topic: &str, topics: &Topics) -> anyhow::Error {
    anyhow::anyhow!(
        "{}: no topic {topic:?}; topics present: {}",
        input.display(),
        topic_list(topics)
    )
}

fn schema_name(channel: &mcap::Channel<'_>) -> String {
    channel
        .schema
        .as_ref()
        .map_or_else(|| "no schema".to_owned(), |s| s.name.clone())
}

/// Intrinsics from the first message on the camera-info topic.
fn camera_from_info(path: &Path, topic: &str) -> anyhow::Result<Camera> {
    let mut topics = Topics::default();
    for message in open_log(path)?.data_of(topic) {
        // Damage is reported by the image pass, which reads the whole log.
        let message = match message {
            Ok(m) => m,
            Err(e) if e.skipped == Skipped::Rest => bail!(
                "{}: no message on camera-info topic {topic:?} before the log became unreadable ({e}); topics seen: {}",
                path.display(),
                topic_list(&topics)
            ),
            Err(_) => continue,
        };
        if message.channel.topic == topic {
            let schema = schema_name(&message.channel);
            return mcap_io::decode_camera_info(
                &schema,
                &message.channel.message_encoding,
                &message.data,
            )
            .with_context(|| format!("{}: topic {topic}", path.display()));
        }
        topics.see(&message.channel);
    }
    Err(no_topic(path, topic, &topics))
}

pub fn run(args: &Args, quiet: bool, bars: &Bars) -> anyhow::Result<ExitCode> {
    let start = Instant::now();
    let m = &args.mcap;
    let (Some(input), Some(topic)) = (m.mcap.as_deref(), m.topic.as_deref()) else {
        bail!("--mcap needs --topic");
    };
    super::check_outputs(args, &[input], &[])?;
    let log = open_log(input)?.data_of(topic);
    if let Some(e) = log.summary_error() {
        bars.warn(&format!(
            "{}: the summary section is not used ({e}); damage in the log cannot be skipped by its chunk index",
            input.display()
        ));
    }
    // With a summary, a missing topic is found before anything is decoded.
    let mut expected_on_topic = None;
    if let Some(summary) = log.summary() {
        let mut topics = Topics::default();
        for c in summary.channels.values() {
            topics.see(c);
        }
        for t in std::iter::once(topic).chain(m.camera_info_topic.as_deref()) {
            if !topics.contains(t) {
                return Err(no_topic(input, t, &topics));
            }
        }
        if let Some(counts) = &summary.message_counts {
            expected_on_topic = Some(
                summary
                    .channels
                    .values()
                    .filter(|c| c.topic == topic)
                    .map(|c| counts.get(&c.id).copied().unwrap_or(0))
                    .sum::<u64>(),
            );
        }
    }
    let camera = match (&args.camera, &m.camera_info_topic) {
        (Some(c), _) => Camera::parse(c).context("--camera")?,
        (None, Some(t)) => camera_from_info(input, t)?,
        (None, None) => bail!("--mcap needs the intrinsics: --camera \"MODEL W H params...\" or --camera-info-topic TOPIC"),
    };

    let map = Arc::new(super::super::open_map(args.map_path())?);
    let source = QuerySource::Images {
        folder: None,
        model: args.model.clone(),
    };
    let not_sfp = "MCAP images need an SFP map (their features are extracted with the SFP model)";
    // A log is a sequence: each frame is predicted from the last ones and tracked.
    let session = super::session(args, map, source, true, not_sfp, bars)?;
    let gray_weights = session.gray_weights().expect("a session that extracts");

    bars.start("localizing", expected_on_topic);
    let frames: Mutex<BTreeMap<usize, Frame>> = Mutex::new(BTreeMap::new());
    // Failure reasons, each kept once.
    let reasons: Mutex<HashSet<Arc<str>>> = Mutex::new(HashSet::new());
    let share = |reason: String| -> Arc<str> {
        let mut reasons = reasons.lock().unwrap_or_else(|p| p.into_inner());
        match reasons.get(reason.as_str()) {
            Some(r) => r.clone(),
            None => {
                let r: Arc<str> = reason.into();
                reasons.insert(r.clone());
                r
            }
        }
    };
    let threads = args.threads.max(1);
    let (sender, receiver) = std::sync::mpsc::sync_channel::<(usize, mcap::Message)>(threads);
    let receiver = Mutex::new(receiver);
    // Decoding and extraction run on `threads` workers; one more thread localizes the frames
    // in log order as they come (a log is a sequence: each frame is predicted from the last
    // ones and tracked), so extraction and matching overlap.
    let pending = Ordered::new(threads);
    let scan = std::thread::scope(|s| -> anyhow::Result<Scan> {
        for _ in 0..threads {
            s.spawn(|| loop {
                let next = receiver.lock().unwrap_or_else(|p| p.into_inner()).recv();
                let Ok((index, message)) = next else { break };
                // Every index must reach the localizer, which waits for them in order: a
                // panic becomes the frame's failure instead of a hang.
                let extracted = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    extract_message(&message, &camera, gray_weights, &session)
                }))
                .unwrap_or_else(|_| {
                    let frame = Frame::of(&message);
                    (
                        frame,
                        Err("internal error while extracting (a bug)".to_string()),
                    )
                });
                drop(message);
                pending.put(index, extracted);
            });
        }
        s.spawn(|| {
            // Should this thread panic, the workers and the reader must not wait for it.
            let _close = pending.close_on_panic();
            while let Some((index, (mut frame, features))) = pending.take_next() {
                let outcome = match features {
                    Ok(query) => std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                        // A frame that deferred its global descriptor and loses tracking gets
                        // it from its kept input.
                        session
                            .localize_frame(query, &camera, &format!("image {index}"))
                            .map_err(|e| match e {
                                SessionError::Query { source, .. } => source.to_string(),
                                e => e.to_string(),
                            })
                    }))
                    .unwrap_or_else(|_| {
                        session.reset_tracking();
                        Err("internal error while localizing (a bug)".to_string())
                    }),
                    Err(reason) => {
                        session.reset_tracking();
                        Err(reason)
                    }
                };
                frame.outcome = match outcome {
                    Ok(l) => Ok(Box::new(l)),
                    Err(reason) => Err(share(reason)),
                };
                frames
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .insert(index, frame);
                bars.advance(1);
            }
        });
        // Should the reader panic, the localizing thread must not wait for more frames.
        let _close = pending.close_on_panic();
        let mut scan = Scan::default();
        for message in log {
            let message = match message {
                Ok(m) => m,
                // The reader goes on after a skip, or ends after it when the rest is lost.
                Err(damage) => {
                    // A log damaged all over gets a bounded number of lines and list entries.
                    if scan.skipped_count < MAX_DAMAGE_WARNINGS {
                        bars.warn(&format!("{}: {damage}", input.display()));
                    }
                    if scan.skipped.len() < MAX_DAMAGE_LISTED {
                        scan.skipped.push(damage.to_string());
                    }
                    scan.skipped_count += 1;
                    continue;
                }
            };
            scan.topics.see(&message.channel);
            if message.channel.topic == topic {
                if sender.send((scan.messages_on_topic, message)).is_err() {
                    break;
                }
                scan.messages_on_topic += 1;
            }
        }
        drop(sender);
        pending.finish(scan.messages_on_topic);
        Ok(scan)
    })?;
    bars.finish();

    let frames = frames.into_inner().unwrap_or_else(|p| p.into_inner());
    if scan.messages_on_topic == 0 {
        match scan.skipped.first() {
            Some(e) => bail!(
                "{}: no message on topic {topic:?} could be read; {} damaged parts skipped, the first: {e}; topics seen: {}",
                input.display(),
                scan.skipped_count,
                topic_list(&scan.topics)
            ),
            None if !scan.topics.contains(topic) => {
                return Err(no_topic(input, topic, &scan.topics))
            }
            None => bail!("{}: topic {topic:?} has no messages", input.display()),
        }
    }
    if frames.values().all(|f| f.undecodable) {
        let first = frames
            .values()
            .next()
            .and_then(|f| f.outcome.as_ref().err());
        bail!(
            "{}: topic {topic:?}: none of its {} images could be decoded: {}",
            input.display(),
            frames.len(),
            first.map_or("", |s| &**s)
        );
    }

    write_output(args, input, topic, &frames)?;
    if let Some(tum) = &m.tum {
        write_tum(tum, &frames)?;
    }

    let localized = frames
        .values()
        .filter(|f| matches!(&f.outcome, Ok(l) if l.pose().is_some()))
        .count();
    let failed = FailedFrames(&frames);
    // Without a summary (a cut-off log) how many messages were lost is unknown.
    let unreadable_messages = expected_on_topic
        .map(|n| n.saturating_sub(scan.messages_on_topic as u64))
        .filter(|_| !scan.skipped.is_empty());
    let unreadable = scan.skipped.first().map(|e| {
        json!({
            "error": e,
            "messages": unreadable_messages,
            "skipped": scan.skipped,
            "skipped_count": scan.skipped_count,
        })
    });
    if !scan.skipped.is_empty() {
        let lost = match unreadable_messages {
            Some(n) => format!("{n} lost"),
            None => "how many were lost is unknown (no summary)".to_owned(),
        };
        let parts = match scan.skipped_count {
            1 => "1 damaged part".to_owned(),
            n if n > MAX_DAMAGE_WARNINGS => {
                format!("{n} damaged parts (the first {MAX_DAMAGE_WARNINGS} above)")
            }
            n => format!("{n} damaged parts"),
        };
        bars.warn(&format!(
            "{}: {parts} of the log skipped (exit status {SKIPPED_EXIT}); image messages on {topic}: {} read, {lost}",
            input.display(),
            scan.messages_on_topic
        ));
    }
    let results: Vec<&Localization> = frames
        .values()
        .filter_map(|f| f.outcome.as_deref().ok())
        .collect();
    let paths = super::PathCounts::of(results.iter().copied());
    if args.json {
        // Serialized straight from the frames: a `Value` per failed frame would cost far more
        // than the frames themselves.
        #[derive(serde::Serialize)]
        struct Report<'a> {
            mcap: String,
            topic: &'a str,
            images: usize,
            localized: usize,
            failed: FailedFrames<'a>,
            unreadable: Option<serde_json::Value>,
            output: String,
            pose_topic: &'a str,
            tum: Option<String>,
            camera: String,
            seconds: f64,
            median_ms: serde_json::Value,
            path: BTreeMap<&'static str, usize>,
            tracking_lost: BTreeMap<String, usize>,
            retrieval: BTreeMap<&'static str, usize>,
            retrieval_fallback: BTreeMap<String, usize>,
            /// Frames extracted while tracking, without the global descriptor's copy.
            global_skipped: usize,
        }
        let report = Report {
            mcap: input.display().to_string(),
            topic,
            images: scan.messages_on_topic,
            localized,
            failed,
            unreadable,
            output: args.output.display().to_string(),
            pose_topic: &m.pose_topic,
            tum: m.tum.as_ref().map(|p| p.display().to_string()),
            camera: camera.to_string(),
            seconds: start.elapsed().as_secs_f64(),
            median_ms: super::median_ms(results.iter().copied()),
            path: paths.path,
            tracking_lost: paths.tracking_lost,
            retrieval: paths.retrieval,
            retrieval_fallback: paths.retrieval_fallback,
            global_skipped: session.global_deferred(),
        };
        use std::io::Write as _;
        let mut out = std::io::stdout().lock();
        serde_json::to_writer(&mut out, &report)?;
        writeln!(out)?;
    } else if !quiet {
        println!(
            "{}: {localized}/{} images of {topic} localized, median {:.1} ms per image (after features)",
            args.output.display(),
            scan.messages_on_topic,
            median(results.iter().map(|r| r.times.total_ms).collect()).unwrap_or(f64::NAN)
        );
        paths.print(scan.messages_on_topic);
        for (index, _, reason) in failed.iter() {
            // Escaped: the reason may quote the file (a schema name, an encoding).
            println!(
                "failed: image {index} ({})",
                escape_control_characters(&reason)
            );
        }
    }
    Ok(if scan.skipped.is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(SKIPPED_EXIT)
    })
}

/// The frames that were not localized, serialized (and listed) as
/// `{index, stamp: {sec, nsec}, reason}` without a copy per frame.
struct FailedFrames<'a>(&'a BTreeMap<usize, Frame>);

impl<'a> FailedFrames<'a> {
    fn iter(&self) -> impl Iterator<Item = (usize, &'a Frame, std::borrow::Cow<'a, str>)> {
        self.0.iter().filter_map(|(&i, f)| {
            let reason = match &f.outcome {
                Ok(l) => l.failure()?.to_string().into(),
                Err(e) => std::borrow::Cow::Borrowed(&**e),
            };
            Some((i, f, reason))
        })
    }
}

impl serde::Serialize for FailedFrames<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        #[derive(serde::Serialize)]
        struct Failed<'a> {
            index: usize,
            stamp: StampJson,
            reason: std::borrow::Cow<'a, str>,
        }
        #[derive(serde::Serialize)]
        struct StampJson {
            sec: i64,
            nsec: u32,
        }
        s.collect_seq(self.iter().map(|(index, f, reason)| Failed {
            index,
            stamp: StampJson {
                sec: f.stamp.sec,
                nsec: f.stamp.nsec,
            },
            reason,
        }))
    }
}

/// The frame of one image message and its features, or why there are none. While the
/// sequence tracks, the session defers the global descriptor where it costs an inference.
fn extract_message(
    message: &mcap::Message<'_>,
    camera: &Camera,
    gray_weights: [f32; 3],
    session: &Session,
) -> (Frame, Result<session::Frame, String>) {
    let mut frame = Frame::of(message);
    let schema = schema_name(&message.channel);
    let decoded =
        match mcap_io::decode_image(&schema, &message.channel.message_encoding, &message.data) {
            Ok(d) => d,
            Err(e) => {
                frame.undecodable = true;
                return (frame, Err(e.to_string()));
            }
        };
    if let Some(stamp) = decoded.stamp {
        frame.stamp = stamp;
    }
    let (w, h) = (decoded.image.width(), decoded.image.height());
    if (w, h) != (camera.width(), camera.height()) {
        let reason = format!(
            "the image is {w}x{h} but the camera is {}x{}",
            camera.width(),
            camera.height()
        );
        return (frame, Err(reason));
    }
    let input = sfpmap::extract::image::from_image(&decoded.image, gray_weights, None);
    drop(decoded);
    // One ONNX session: extraction takes turns, decoding runs in parallel.
    let features = session.extract(input).map_err(|e| match e {
        SessionError::Extract(e) => e.to_string(),
        e => e.to_string(),
    });
    (frame, features)
}

/// Extracted frames handed from the workers to the localizing thread in log order. Workers
/// wait while `capacity` frames are pending (unless theirs is the one the localizer waits
/// for), so a fast extractor cannot pile up features.
struct Ordered {
    state: Mutex<OrderedState>,
    changed: std::sync::Condvar,
    capacity: usize,
}

type Extracted = (Frame, Result<session::Frame, String>);

struct OrderedState {
    pending: BTreeMap<usize, Extracted>,
    /// A thread of the hand-over panicked: nobody waits any more, frames are dropped.
    closed: bool,
    /// The index the localizer takes next.
    next: usize,
    /// How many frames there are, once the log is read.
    total: Option<usize>,
}

impl Ordered {
    fn new(threads: usize) -> Ordered {
        Ordered {
            state: Mutex::new(OrderedState {
                pending: BTreeMap::new(),
                closed: false,
                next: 0,
                total: None,
            }),
            changed: std::sync::Condvar::new(),
            // One frame per worker in flight and as many again waiting: extraction takes
            // turns on one ONNX session, so more would only hold features (a few MB each).
            capacity: 2 * threads + 2,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, OrderedState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn put(&self, index: usize, extracted: Extracted) {
        let mut state = self.lock();
        while state.pending.len() >= self.capacity && index != state.next && !state.closed {
            state = self.changed.wait(state).unwrap_or_else(|p| p.into_inner());
        }
        if state.closed {
            return;
        }
        state.pending.insert(index, extracted);
        self.changed.notify_all();
    }

    /// The next frame in order, waiting for it; `None` after the last.
    fn take_next(&self) -> Option<(usize, Extracted)> {
        let mut state = self.lock();
        loop {
            let next = state.next;
            if let Some(extracted) = state.pending.remove(&next) {
                state.next += 1;
                self.changed.notify_all();
                return Some((next, extracted));
            }
            if state.closed || state.total.is_some_and(|total| next >= total) {
                return None;
            }
            state = self.changed.wait(state).unwrap_or_else(|p| p.into_inner());
        }
    }

    /// A guard that closes the hand-over if its thread unwinds.
    fn close_on_panic(&self) -> CloseOnPanic<'_> {
        CloseOnPanic(self)
    }

    /// Every frame has been handed to a worker: `total` of them.
    fn finish(&self, total: usize) {
        self.lock().total = Some(total);
        self.changed.notify_all();
    }
}

struct CloseOnPanic<'a>(&'a Ordered);

impl Drop for CloseOnPanic<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.lock().closed = true;
            self.0.changed.notify_all();
        }
    }
}

/// The output MCAP, through [`write_atomic`](super::super::write_atomic).
fn write_output(
    args: &Args,
    input: &Path,
    topic: &str,
    frames: &BTreeMap<usize, Frame>,
) -> anyhow::Result<()> {
    let m = &args.mcap;
    super::super::write_atomic(&args.output, |out| {
        {
            // `&mut AtomicFile` is Write + Seek: the MCAP writer seeks back for the summary.
            let mut writer = mcap_io::PoseWriter::new(out, &m.pose_topic)?;
            let write_pose =
                |writer: &mut mcap_io::PoseWriter<_>, frame: &Frame| match frame.outcome.as_deref()
                {
                    Ok(Localization {
                        outcome: Ok(pose), ..
                    }) => writer.write_pose(
                        frame.log_time,
                        frame.publish_time,
                        frame.stamp,
                        &m.frame_id,
                        pose,
                    ),
                    _ => Ok(()),
                };
            if m.passthrough_images {
                // A second pass copies the images in log order, each followed by its pose.
                let mut index = 0;
                for message in open_stream(input, topic)? {
                    let Ok(message) = message else { break };
                    if message.channel.topic != topic {
                        continue;
                    }
                    let Some(frame) = frames.get(&index) else {
                        break;
                    };
                    writer.write_message(&message)?;
                    write_pose(&mut writer, frame)?;
                    index += 1;
                }
            } else {
                for frame in frames.values() {
                    write_pose(&mut writer, frame)?;
                }
            }
            writer.finish()?;
            Ok(())
        }
    })
}

/// The trajectory as TUM, stamped with the images' own times in seconds.
fn write_tum(path: &Path, frames: &BTreeMap<usize, Frame>) -> anyhow::Result<()> {
    use std::io::Write as _;
    super::super::write_atomic(path, |out| {
        writeln!(
            out,
            "# timestamp tx ty tz qx qy qz qw (TUM: world_from_cam; image stamps)"
        )?;
        for frame in frames.values() {
            if let Ok(Localization {
                outcome: Ok(pose), ..
            }) = frame.outcome.as_deref()
            {
                let stamp = format!("{}.{:09}", frame.stamp.sec, frame.stamp.nsec);
                writeln!(out, "{}", tum_line(stamp, pose))?;
            }
        }
        Ok(())
    })
}
