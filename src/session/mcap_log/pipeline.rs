//! The threads of [`ImageLog::localize`](super::ImageLog::localize): the reader hands each
//! image message on the topic to `threads` workers that decode and extract it, and one more
//! thread localizes the extracted frames in log order ([`Ordered`]), so extraction and
//! matching overlap.

use super::{schema_name, LogFrame, Topics, MAX_DAMAGE_LISTED, MAX_DAMAGE_WARNINGS};
use crate::geometry::Camera;
use crate::io::mcap_io::{self, Damage, LogReader};
use crate::localize::Localization;
use crate::progress::Reporter;
use crate::session::{Frame, Session, SessionError};
use std::collections::{BTreeMap, HashSet};
use std::fs::File;
use std::path::Path;
use std::sync::mpsc::{Receiver, SyncSender};
use std::sync::{Arc, Mutex};

/// How the pass over the log ended.
#[derive(Default)]
pub(super) struct Scan {
    pub(super) messages_on_topic: usize,
    /// The topics seen, for the "no such topic" error.
    pub(super) topics: Topics,
    /// The first [`MAX_DAMAGE_LISTED`] damaged parts that were skipped, as their warnings say.
    pub(super) skipped: Vec<String>,
    /// How many damaged parts were skipped in all.
    pub(super) skipped_count: u64,
}

/// Reads the log, handing each message on `topic` to the workers with its index on the
/// topic; each damaged part is a warning (the first [`MAX_DAMAGE_WARNINGS`]) and listed.
pub(super) fn read_topic(
    log: LogReader<File>,
    path: &Path,
    topic: &str,
    sender: SyncSender<(usize, mcap::Message<'static>)>,
    reporter: &dyn Reporter,
) -> Scan {
    let mut scan = Scan::default();
    for message in log {
        let message = match message {
            Ok(m) => m,
            // The reader goes on after a skip, or ends after it when the rest is lost.
            Err(damage) => {
                scan.skip(path, &damage, reporter);
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
    scan
}

impl Scan {
    /// A damaged part skipped: a log damaged all over gets a bounded number of lines and
    /// list entries.
    fn skip(&mut self, path: &Path, damage: &Damage, reporter: &dyn Reporter) {
        if self.skipped_count < MAX_DAMAGE_WARNINGS {
            reporter.warn(&format!("{}: {damage}", crate::escape::path(path)));
        }
        if self.skipped.len() < MAX_DAMAGE_LISTED {
            self.skipped.push(damage.to_string());
        }
        self.skipped_count += 1;
    }
}

/// What the threads of [`ImageLog::localize`](super::ImageLog::localize) share.
pub(super) struct Worker<'a> {
    pub(super) session: &'a Session,
    pub(super) camera: &'a Camera,
    pub(super) gray_weights: [f32; 3],
}

/// A frame and its features, or why there are none.
type Extracted = (LogFrame, Result<Frame, String>);

impl Worker<'_> {
    /// A worker: decodes and extracts the messages it receives until the reader is done.
    pub(super) fn extract_each(
        &self,
        receiver: &Mutex<Receiver<(usize, mcap::Message<'static>)>>,
        pending: &Ordered,
    ) {
        loop {
            let next = receiver.lock().unwrap_or_else(|p| p.into_inner()).recv();
            let Ok((index, message)) = next else { break };
            // Every index must reach the localizer, which waits for them in order: a
            // panic becomes the frame's failure instead of a hang.
            let extracted =
                std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.extract(&message)))
                    .unwrap_or_else(|_| {
                        let frame = LogFrame::of(&message);
                        let reason = "internal error while extracting (a bug)".to_string();
                        (frame, Err(reason))
                    });
            drop(message);
            pending.put(index, extracted);
        }
    }

    /// The frame of one image message and its features, or why there are none. While the
    /// sequence tracks, the session defers the global descriptor where it costs an inference.
    fn extract(&self, message: &mcap::Message<'_>) -> Extracted {
        let mut frame = LogFrame::of(message);
        let schema = schema_name(&message.channel);
        let encoding = &message.channel.message_encoding;
        let decoded = match mcap_io::decode_image(&schema, encoding, &message.data) {
            Ok(d) => d,
            Err(e) => {
                frame.undecodable = true;
                return (frame, Err(e.to_string()));
            }
        };
        if let Some(stamp) = decoded.stamp {
            frame.stamp = stamp;
        }
        let size = |n: u32| usize::try_from(n).unwrap_or(usize::MAX);
        let (w, h) = (size(decoded.image.width()), size(decoded.image.height()));
        if let Some(reason) = super::super::source::image_misfits_camera(w, h, self.camera) {
            return (frame, Err(reason));
        }
        let input = crate::extract::image::from_image(&decoded.image, self.gray_weights, None);
        drop(decoded);
        // One ONNX session: extraction takes turns, decoding runs in parallel.
        let features = self.session.extract(input).map_err(|e| e.to_string());
        (frame, features)
    }

    /// The localizing thread: takes the extracted frames in log order and localizes them
    /// (in a session built with `.sequence(true)`, as the CLI builds it, each frame is
    /// predicted from the last ones and tracked; otherwise each is localized on its own).
    pub(super) fn localize_in_order(
        &self,
        pending: &Ordered,
        frames: &Mutex<Vec<LogFrame>>,
        reporter: &dyn Reporter,
    ) {
        // Should this thread panic, the workers and the reader must not wait for it.
        let _close = pending.close_on_panic();
        // Failure reasons, each kept once.
        let mut reasons: HashSet<Arc<str>> = HashSet::new();
        while let Some((index, (mut frame, features))) = pending.take_next() {
            let outcome = match features {
                Ok(query) => self.localize(query, index),
                Err(reason) => {
                    self.session.reset_tracking();
                    Err(reason)
                }
            };
            frame.outcome = match outcome {
                Ok(l) => Ok(Box::new(l)),
                Err(reason) => Err(share(&mut reasons, reason)),
            };
            frames.lock().unwrap_or_else(|p| p.into_inner()).push(frame);
            reporter.advance(1);
        }
    }

    /// Frame `index` localized, or why not. A frame that deferred its global descriptor and
    /// loses tracking gets it from its kept input.
    fn localize(&self, query: Frame, index: usize) -> Result<Localization, String> {
        let session = self.session;
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            session
                .localize_frame(query, self.camera, &format!("image {index}"))
                .map_err(|e| match e {
                    SessionError::Query { source, .. } => source.to_string(),
                    e => e.to_string(),
                })
        }))
        .unwrap_or_else(|_| {
            session.reset_tracking();
            Err("internal error while localizing (a bug)".to_string())
        })
    }
}

/// `reason`, shared with the frames that failed for the same one.
fn share(reasons: &mut HashSet<Arc<str>>, reason: String) -> Arc<str> {
    match reasons.get(reason.as_str()) {
        Some(r) => r.clone(),
        None => {
            let r: Arc<str> = reason.into();
            reasons.insert(r.clone());
            r
        }
    }
}

/// Extracted frames handed from the workers to the localizing thread in log order. Workers
/// wait while `capacity` frames are pending (unless theirs is the one the localizer waits
/// for), so a fast extractor cannot pile up features.
pub(super) struct Ordered {
    state: Mutex<OrderedState>,
    changed: std::sync::Condvar,
    capacity: usize,
}

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
    pub(super) fn new(threads: usize) -> Ordered {
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
    pub(super) fn close_on_panic(&self) -> CloseOnPanic<'_> {
        CloseOnPanic(self)
    }

    /// Every frame has been handed to a worker: `total` of them.
    pub(super) fn finish(&self, total: usize) {
        self.lock().total = Some(total);
        self.changed.notify_all();
    }
}

pub(super) struct CloseOnPanic<'a>(&'a Ordered);

impl Drop for CloseOnPanic<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.lock().closed = true;
            self.0.changed.notify_all();
        }
    }
}
