//! The images of one topic of an MCAP log, localized in order through a [`Session`] (what
//! `sfpmap localize --mcap` runs, and what a ROS node calls): [`ImageLog::open`] checks the
//! topic against the log's summary before anything is decoded, [`ImageLog::camera_from_info`]
//! reads intrinsics from a `CameraInfo` topic, [`ImageLog::localize`] decodes and extracts the
//! images on `threads` workers while one more thread localizes them in log order (a log is a
//! sequence: build the session with [`SessionBuilder::sequence`] to track it), and the
//! [`LogLocalization`] writes the poses as `foxglove.PoseInFrame` MCAP or TUM.
//!
//! Damaged logs ([`LogReader`]): a chunk that fails its CRC or does not decompress is skipped,
//! and a record whose length cannot be right is skipped up to the next chunk of the chunk index
//! (or, without an intact summary, ends the log). Each skip is a warning through the
//! [`Reporter`] naming the file and where (the first [`MAX_DAMAGE_WARNINGS`]), and listed in
//! [`LogLocalization::skipped`]; what was read is localized. It is an error when no image
//! message on the topic could be read or decoded at all.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use sfpmap::format::Map;
//! use sfpmap::progress::Silent;
//! use sfpmap::session::mcap_log::ImageLog;
//! use sfpmap::session::{QuerySource, Session};
//! use std::path::Path;
//! use std::sync::Arc;
//!
//! let map = Arc::new(Map::open("map.sfpm")?);
//! let session = Session::builder(map, "map.sfpm")
//!     .source(QuerySource::Images { folder: None, model: None })
//!     .sequence(true)
//!     .build(&Silent)?;
//! let log = ImageLog::open(Path::new("run.mcap"), "/camera/image/compressed", &Silent)?;
//! let camera = log.camera_from_info("/camera/camera_info")?;
//! let found = log.localize(&session, &camera, 2, &Silent)?;
//! found.write_mcap(Path::new("poses.mcap"), "/sfpmap/pose", "map", false)?;
//! println!("{} of {} images localized", found.localized(), found.images());
//! # Ok(())
//! # }
//! ```
//!
//! [`SessionBuilder::sequence`]: super::SessionBuilder::sequence

mod pipeline;

use super::{Session, SessionError};
use crate::escape::quoted_name;
use crate::geometry::{Camera, Pose};
use crate::io::mcap_io::{self, LogReader, McapIoError, PoseWriter, Skipped, Stamp};
use crate::io::poses::tum_line;
use crate::localize::Localization;
use crate::output::OutputError;
use crate::progress::Reporter;
use pipeline::{read_topic, Ordered, Scan, Worker};
use std::borrow::Cow;
use std::collections::{BTreeMap, HashSet};
use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Damaged parts named one warning each; the rest are counted.
pub const MAX_DAMAGE_WARNINGS: u64 = 20;
/// Damaged parts [`LogLocalization::skipped`] lists; the rest are counted (a log damaged all
/// over must not cost memory per damaged record).
pub const MAX_DAMAGE_LISTED: usize = 1000;

/// An MCAP log opened for the images of one topic.
pub struct ImageLog {
    path: PathBuf,
    topic: String,
    /// The log, handing out the payload of the image topic only.
    reader: LogReader<File>,
    /// The summary's topics, when the log has an intact summary.
    summary_topics: Option<Topics>,
    /// How many messages the summary's statistics count on the topic.
    expected_on_topic: Option<u64>,
}

impl ImageLog {
    /// Opens the log at `path` for the images of `topic`. With an intact summary, a topic the
    /// log does not have is an error here, before anything is decoded; a summary that cannot
    /// be used is a warning through `reporter` (damage then cannot be skipped by the chunk
    /// index).
    pub fn open(path: &Path, topic: &str, reporter: &dyn Reporter) -> Result<ImageLog, LogError> {
        let reader = open_log(path)?.data_of(topic);
        if let Some(e) = reader.summary_error() {
            reporter.warn(&format!(
                "{}: the summary section is not used ({e}); damage in the log cannot be skipped by its chunk index",
                crate::escape::path(path)
            ));
        }
        let mut log = ImageLog {
            path: path.to_path_buf(),
            topic: topic.to_owned(),
            summary_topics: None,
            expected_on_topic: None,
            reader,
        };
        if let Some(summary) = log.reader.summary() {
            let mut topics = Topics::default();
            for c in summary.channels.values() {
                topics.see(c);
            }
            log.expected_on_topic = summary.message_counts.as_ref().map(|counts| {
                summary
                    .channels
                    .values()
                    .filter(|c| c.topic == topic)
                    .map(|c| counts.get(&c.id).copied().unwrap_or(0))
                    .sum::<u64>()
            });
            log.summary_topics = Some(topics);
        }
        log.check_topic(topic)?;
        Ok(log)
    }

    /// The log's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The image topic.
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// How many messages the summary's statistics count on the image topic (`None` without
    /// an intact summary with statistics).
    pub fn expected_images(&self) -> Option<u64> {
        self.expected_on_topic
    }

    /// With a summary, an error when the log has no `topic`.
    fn check_topic(&self, topic: &str) -> Result<(), LogError> {
        match &self.summary_topics {
            Some(topics) if !topics.contains(topic) => Err(self.no_topic(topic, topics)),
            _ => Ok(()),
        }
    }

    fn no_topic(&self, topic: &str, topics: &Topics) -> LogError {
        LogError::NoTopic {
            path: self.path.clone(),
            topic: topic.to_owned(),
            topics: topic_list(topics),
        }
    }

    /// Intrinsics from the first message on `topic` (`sensor_msgs/msg/CameraInfo`, cdr),
    /// read in a pass of its own. Damage before it is skipped here and reported by
    /// [`ImageLog::localize`], which reads the whole log.
    pub fn camera_from_info(&self, topic: &str) -> Result<Camera, LogError> {
        self.check_topic(topic)?;
        let mut topics = Topics::default();
        for message in open_log(&self.path)?.data_of(topic) {
            let message = match message {
                Ok(m) => m,
                Err(e) if e.skipped == Skipped::Rest => {
                    return Err(LogError::NoCameraInfo {
                        path: self.path.clone(),
                        topic: topic.to_owned(),
                        damage: e.to_string(),
                        topics: topic_list(&topics),
                    })
                }
                Err(_) => continue,
            };
            if message.channel.topic == topic {
                let schema = schema_name(&message.channel);
                let encoding = &message.channel.message_encoding;
                return mcap_io::decode_camera_info(&schema, encoding, &message.data).map_err(
                    |source| LogError::CameraInfo {
                        path: self.path.clone(),
                        topic: topic.to_owned(),
                        source: Box::new(source),
                    },
                );
            }
            topics.see(&message.channel);
        }
        Err(self.no_topic(topic, &topics))
    }

    /// The images of the topic, localized in log order through `session` (which must
    /// extract images: [`QuerySource::Images`](super::QuerySource::Images)) with `camera`.
    /// Decoding and extraction run on `threads` workers; one more thread localizes the frames
    /// as they come, so extraction and matching overlap. Progress (one item per image) and
    /// warnings (each damaged part, up to [`MAX_DAMAGE_WARNINGS`]) go to `reporter`.
    ///
    /// A frame that cannot be decoded or localized is a failed [`LogFrame`], not an error; it
    /// is an error when no message on the topic could be read, or none decoded.
    pub fn localize(
        self,
        session: &Session,
        camera: &Camera,
        threads: usize,
        reporter: &dyn Reporter,
    ) -> Result<LogLocalization, LogError> {
        let Some(gray_weights) = session.gray_weights() else {
            return Err(LogError::Session(SessionError::NoSource(format!(
                "{}: MCAP images need a session that extracts them (QuerySource::Images)",
                session.map_name()
            ))));
        };
        // Bounded as the CLI bounds --threads: the hand-over sizes its queue by it.
        let threads = threads.clamp(1, crate::progress::max_threads());
        reporter.start("localizing", self.expected_on_topic);
        let frames = Mutex::new(Vec::new());
        let (sender, receiver) = std::sync::mpsc::sync_channel::<(usize, mcap::Message)>(threads);
        let receiver = Mutex::new(receiver);
        let pending = Ordered::new(threads);
        let worker = Worker {
            session,
            camera,
            gray_weights,
        };
        let (path, topic) = (&self.path, self.topic.as_str());
        let scan = std::thread::scope(|s| {
            for _ in 0..threads {
                s.spawn(|| worker.extract_each(&receiver, &pending));
            }
            s.spawn(|| worker.localize_in_order(&pending, &frames, reporter));
            // Should the reader panic, the localizing thread must not wait for more frames.
            let _close = pending.close_on_panic();
            let scan = read_topic(self.reader, path, topic, sender, reporter);
            pending.finish(scan.messages_on_topic);
            scan
        });
        reporter.finish();
        let frames = frames.into_inner().unwrap_or_else(|p| p.into_inner());
        check_read(path, topic, &scan, &frames)?;
        Ok(LogLocalization {
            path: self.path,
            topic: self.topic,
            frames,
            messages_on_topic: scan.messages_on_topic,
            expected_on_topic: self.expected_on_topic,
            skipped: scan.skipped,
            skipped_count: scan.skipped_count,
        })
    }
}

/// The images of `topic` in the log at `path` localized through `session` with `camera`:
/// [`ImageLog::open`], then [`ImageLog::localize`].
pub fn localize_log(
    session: &Session,
    path: &Path,
    topic: &str,
    camera: &Camera,
    threads: usize,
    reporter: &dyn Reporter,
) -> Result<LogLocalization, LogError> {
    ImageLog::open(path, topic, reporter)?.localize(session, camera, threads, reporter)
}

/// One image message on the topic and what became of it.
#[derive(Debug)]
pub struct LogFrame {
    /// The message's log time (ns).
    pub log_time: u64,
    /// The message's publish time (ns).
    pub publish_time: u64,
    /// The message's own stamp, else its log time.
    pub stamp: Stamp,
    /// Boxed, and reasons shared between frames: a forged log of 2 M tiny image messages
    /// (64 MiB decompressed from a few KB) keeps one small frame each.
    outcome: Result<Box<Localization>, Arc<str>>,
    /// The image could not be decoded (as opposed to decoded but not localized).
    pub undecodable: bool,
}

impl LogFrame {
    /// The frame of `message`, before anything is known of it (stamped with its log time,
    /// its outcome set by whoever finishes it).
    fn of(message: &mcap::Message<'_>) -> LogFrame {
        LogFrame {
            log_time: message.log_time,
            publish_time: message.publish_time,
            stamp: Stamp::from_nanos(message.log_time),
            outcome: Err(Arc::from("")),
            undecodable: false,
        }
    }

    /// The localizer's result, when the image was decoded and its features extracted.
    pub fn localization(&self) -> Option<&Localization> {
        self.outcome.as_deref().ok()
    }

    /// `cam_from_world`, when the frame was localized.
    pub fn pose(&self) -> Option<&Pose> {
        self.localization().and_then(Localization::pose)
    }

    /// Why the frame was not localized (the decoder's, the extractor's or the localizer's
    /// reason); `None` when it was.
    pub fn failure(&self) -> Option<Cow<'_, str>> {
        match &self.outcome {
            Ok(l) => Some(l.failure()?.to_string().into()),
            Err(e) => Some(Cow::Borrowed(e)),
        }
    }
}

/// The frames of a log's image topic and what the pass over the log skipped.
#[derive(Debug)]
pub struct LogLocalization {
    path: PathBuf,
    topic: String,
    frames: Vec<LogFrame>,
    messages_on_topic: usize,
    expected_on_topic: Option<u64>,
    skipped: Vec<String>,
    skipped_count: u64,
}

impl LogLocalization {
    /// The log's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The image topic.
    pub fn topic(&self) -> &str {
        &self.topic
    }

    /// The frames, in log order (a frame's index is its message's on the topic).
    pub fn frames(&self) -> &[LogFrame] {
        &self.frames
    }

    /// How many image messages on the topic were read.
    pub fn images(&self) -> usize {
        self.messages_on_topic
    }

    /// How many frames were localized.
    pub fn localized(&self) -> usize {
        self.frames.iter().filter(|f| f.pose().is_some()).count()
    }

    /// The frames that were not localized: index, frame and why.
    pub fn failed(&self) -> impl Iterator<Item = (usize, &LogFrame, Cow<'_, str>)> {
        self.frames
            .iter()
            .enumerate()
            .filter_map(|(i, f)| Some((i, f, f.failure()?)))
    }

    /// The localizer's results of the frames that were decoded and extracted.
    pub fn results(&self) -> impl Iterator<Item = &Localization> + Clone {
        self.frames.iter().filter_map(LogFrame::localization)
    }

    /// The first [`MAX_DAMAGE_LISTED`] damaged parts that were skipped, as their warnings
    /// say.
    pub fn skipped(&self) -> &[String] {
        &self.skipped
    }

    /// How many damaged parts were skipped in all.
    pub fn skipped_count(&self) -> u64 {
        self.skipped_count
    }

    /// How many image messages the damaged parts cost, when the summary's statistics say how
    /// many there were; `None` without damage or without them (a cut-off log).
    pub fn unreadable_images(&self) -> Option<u64> {
        self.expected_on_topic
            .map(|n| n.saturating_sub(self.messages_on_topic as u64))
            .filter(|_| !self.skipped.is_empty())
    }

    /// The poses as an MCAP of `foxglove.PoseInFrame` messages on `pose_topic` in frame
    /// `frame_id`, with the image messages' times, written atomically to `out`; with
    /// `passthrough_images`, each image message (same schema and channel) is copied before
    /// its pose, read again from the log.
    pub fn write_mcap(
        &self,
        out: &Path,
        pose_topic: &str,
        frame_id: &str,
        passthrough_images: bool,
    ) -> Result<(), LogError> {
        // Never onto the log itself (its second pass reads it, the rename would replace it).
        crate::output::check_output(out, &[&self.path], true).map_err(LogError::Output)?;
        let writing = |source| LogError::Write {
            path: out.to_path_buf(),
            source,
        };
        crate::output::write_atomic(out, |file| {
            // `&mut AtomicFile` is Write + Seek: the MCAP writer seeks back for the summary.
            let mut writer = PoseWriter::new(file, pose_topic).map_err(writing)?;
            let mut write_pose = |writer: &mut PoseWriter<_>, frame: &LogFrame| match frame.pose() {
                Some(pose) => writer.write_pose(
                    frame.log_time,
                    frame.publish_time,
                    frame.stamp,
                    frame_id,
                    pose,
                ),
                None => Ok(()),
            };
            if passthrough_images {
                self.write_with_images(out, &mut writer, &mut write_pose)?;
            } else {
                for frame in &self.frames {
                    write_pose(&mut writer, frame).map_err(writing)?;
                }
            }
            writer.finish().map_err(writing)?;
            Ok(())
        })
    }

    /// A second pass copies the images in log order, each followed by its pose, to `out`.
    /// The same damaged parts are skipped as in the first pass, so the n-th message on the
    /// topic is the n-th frame.
    fn write_with_images<W: std::io::Write + std::io::Seek>(
        &self,
        out: &Path,
        writer: &mut PoseWriter<W>,
        write_pose: &mut impl FnMut(&mut PoseWriter<W>, &LogFrame) -> Result<(), McapIoError>,
    ) -> Result<(), LogError> {
        let topic = self.topic.as_str();
        let mut frames = self.frames.iter();
        for message in open_log(&self.path)?.data_of(topic).filter(Result::is_ok) {
            let Ok(message) = message else { break };
            if message.channel.topic != topic {
                continue;
            }
            let Some(frame) = frames.next() else { break };
            writer
                .write_message(&message)
                .and_then(|()| write_pose(writer, frame))
                .map_err(|source| LogError::Write {
                    path: out.to_path_buf(),
                    source,
                })?;
        }
        Ok(())
    }

    /// The trajectory as TUM (`timestamp tx ty tz qx qy qz qw`, `world_from_cam`), stamped
    /// with the images' own times in seconds, written atomically to `out`.
    pub fn write_tum(&self, out: &Path) -> Result<(), LogError> {
        use std::io::Write as _;
        crate::output::check_output(out, &[&self.path], true).map_err(LogError::Output)?;
        crate::output::write_atomic(out, |file| {
            let mut write = || -> std::io::Result<()> {
                writeln!(
                    file,
                    "# timestamp tx ty tz qx qy qz qw (TUM: world_from_cam; image stamps)"
                )?;
                for frame in &self.frames {
                    if let Some(pose) = frame.pose() {
                        let stamp = format!("{}.{:09}", frame.stamp.sec, frame.stamp.nsec);
                        writeln!(file, "{}", tum_line(stamp, pose))?;
                    }
                }
                Ok(())
            };
            write().map_err(|e| LogError::Write {
                path: out.to_path_buf(),
                source: McapIoError::Io(e),
            })
        })
    }
}

/// What stops a log's images from being localized (a frame that is not is a failed
/// [`LogFrame`]). Each names the log or the output it is about.
#[derive(Debug)]
#[non_exhaustive]
pub enum LogError {
    /// The log cannot be opened or read as MCAP.
    Open {
        /// The log.
        path: PathBuf,
        /// Why.
        source: McapIoError,
    },
    /// The log has no channel on `topic`.
    NoTopic {
        /// The log.
        path: PathBuf,
        /// The topic asked for.
        topic: String,
        /// The topics the log has, for a one-line message: each with its schema, quoted and
        /// escaped, at most 50 (`"none"` when it has none).
        topics: String,
    },
    /// The log became unreadable before the first message on the camera-info `topic`.
    NoCameraInfo {
        /// The log.
        path: PathBuf,
        /// The camera-info topic.
        topic: String,
        /// The damage that ended the log.
        damage: String,
        /// The topics seen before it, as in [`LogError::NoTopic`].
        topics: String,
    },
    /// The first message on the camera-info `topic` is not intrinsics we read.
    CameraInfo {
        /// The log.
        path: PathBuf,
        /// The camera-info topic.
        topic: String,
        /// Why (boxed: the error's other variants are smaller).
        source: Box<McapIoError>,
    },
    /// No message on `topic` could be read: every one was in a damaged part.
    Unreadable {
        /// The log.
        path: PathBuf,
        /// The image topic.
        topic: String,
        /// How many damaged parts were skipped.
        skipped: u64,
        /// The first of them, as its warning says.
        first: String,
        /// The topics seen, as in [`LogError::NoTopic`].
        topics: String,
    },
    /// The topic has no messages.
    NoMessages {
        /// The log.
        path: PathBuf,
        /// The image topic.
        topic: String,
    },
    /// None of the topic's images could be decoded.
    Undecodable {
        /// The log.
        path: PathBuf,
        /// The image topic.
        topic: String,
        /// How many image messages there were.
        images: usize,
        /// Why the first could not be decoded.
        first: String,
    },
    /// The session cannot localize the log's images (it does not extract them).
    Session(SessionError),
    /// Writing an output (the MCAP of poses, TUM).
    Write {
        /// The output.
        path: PathBuf,
        /// Why.
        source: McapIoError,
    },
    /// An output that may not or could not be written ([`crate::output`]).
    Output(OutputError),
}

impl std::fmt::Display for LogError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LogError::Open { path, source } | LogError::Write { path, source } => {
                write!(f, "{}: {source}", crate::escape::path(path))
            }
            LogError::NoTopic {
                path,
                topic,
                topics,
            } => write!(
                f,
                "{}: no topic {topic:?}; topics present: {topics}",
                crate::escape::path(path)
            ),
            LogError::NoCameraInfo {
                path,
                topic,
                damage,
                topics,
            } => write!(
                f,
                "{}: no message on camera-info topic {topic:?} before the log became unreadable ({damage}); topics seen: {topics}",
                crate::escape::path(path)
            ),
            LogError::CameraInfo {
                path,
                topic,
                source,
            } => write!(f, "{}: topic {topic}: {source}", crate::escape::path(path)),
            LogError::Unreadable {
                path,
                topic,
                skipped,
                first,
                topics,
            } => write!(
                f,
                "{}: no message on topic {topic:?} could be read; {skipped} damaged parts skipped, the first: {first}; topics seen: {topics}",
                crate::escape::path(path)
            ),
            LogError::NoMessages { path, topic } => {
                write!(f, "{}: topic {topic:?} has no messages", crate::escape::path(path))
            }
            LogError::Undecodable {
                path,
                topic,
                images,
                first,
            } => write!(
                f,
                "{}: topic {topic:?}: none of its {images} images could be decoded: {first}",
                crate::escape::path(path)
            ),
            LogError::Session(e) => e.fmt(f),
            LogError::Output(e) => e.fmt(f),
        }
    }
}

/// Each variant prints its cause's text as its own, so its `source()` is the cause's own
/// source (none for [`McapIoError`], whose messages end with their cause).
impl std::error::Error for LogError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            LogError::Session(e) => e.source(),
            LogError::Output(e) => e.source(),
            _ => None,
        }
    }
}

impl From<OutputError> for LogError {
    fn from(e: OutputError) -> Self {
        LogError::Output(e)
    }
}

fn open_log(path: &Path) -> Result<LogReader<File>, LogError> {
    LogReader::open(path).map_err(|source| LogError::Open {
        path: path.to_path_buf(),
        source,
    })
}

/// An error when no message on the topic could be read, or none of its images decoded.
fn check_read(path: &Path, topic: &str, scan: &Scan, frames: &[LogFrame]) -> Result<(), LogError> {
    let (path, topic) = (path.to_path_buf(), topic.to_owned());
    if scan.messages_on_topic == 0 {
        return Err(match scan.skipped.first() {
            Some(first) => LogError::Unreadable {
                path,
                topic,
                skipped: scan.skipped_count,
                first: first.clone(),
                topics: topic_list(&scan.topics),
            },
            None if !scan.topics.contains(&topic) => LogError::NoTopic {
                path,
                topic,
                topics: topic_list(&scan.topics),
            },
            None => LogError::NoMessages { path, topic },
        });
    }
    if frames.iter().all(|f| f.undecodable) {
        let first = frames.first().and_then(|f| f.outcome.as_ref().err());
        return Err(LogError::Undecodable {
            path,
            topic,
            images: frames.len(),
            first: first.map_or("", |s| &**s).to_owned(),
        });
    }
    Ok(())
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

fn schema_name(channel: &mcap::Channel<'_>) -> String {
    channel
        .schema
        .as_ref()
        .map_or_else(|| "no schema".to_owned(), |s| s.name.clone())
}
