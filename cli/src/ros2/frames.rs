//! Frames from arrival to pose: one-frame mailboxes between the receiving thread and the
//! workers (a new frame replaces one not yet taken, and that is counted: the node drops
//! frames rather than queueing them when localizing is slower than the camera), the counts,
//! and the latency histogram.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Condvar, Mutex};
use std::time::Duration;

/// How long a wait sleeps before it looks again: a notification is never missed (waits and
/// changes hold the lock), this only bounds the cost of a bug elsewhere.
const WAKE: Duration = Duration::from_millis(200);

/// A slot for the newest item: `put` replaces what was not taken yet.
pub struct Mailbox<T> {
    slot: Mutex<(Option<T>, bool)>,
    ready: Condvar,
}

impl<T> Default for Mailbox<T> {
    fn default() -> Self {
        Mailbox {
            slot: Mutex::new((None, false)),
            ready: Condvar::new(),
        }
    }
}

impl<T> Mailbox<T> {
    /// Leaves `item` for the taker; whether it replaced one that was not taken.
    pub fn put(&self, item: T) -> bool {
        let mut slot = self.slot.lock().unwrap_or_else(|p| p.into_inner());
        let replaced = slot.0.replace(item).is_some();
        self.ready.notify_all();
        replaced
    }

    /// Waits until what was put was taken (or the mailbox is closed): the extractor waits
    /// so, and a frame is dropped before it is decoded, not after its inference.
    pub fn wait_empty(&self) {
        let mut slot = self.slot.lock().unwrap_or_else(|p| p.into_inner());
        while slot.0.is_some() && !slot.1 {
            slot = self
                .ready
                .wait_timeout(slot, WAKE)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// The next item, waiting for it; `None` once closed and empty.
    pub fn take(&self) -> Option<T> {
        let mut slot = self.slot.lock().unwrap_or_else(|p| p.into_inner());
        loop {
            if let Some(item) = slot.0.take() {
                // A `wait_empty` may be waiting.
                self.ready.notify_all();
                return Some(item);
            }
            if slot.1 {
                return None;
            }
            slot = self
                .ready
                .wait_timeout(slot, WAKE)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// No more items: a waiting `take` returns what is left, then `None`.
    pub fn close(&self) {
        self.slot.lock().unwrap_or_else(|p| p.into_inner()).1 = true;
        self.ready.notify_all();
    }
}

/// What happened to the frames, counted as it happens (read by the status messages while
/// the workers run).
#[derive(Default)]
pub struct Counts {
    /// Image messages taken from the topic.
    pub received: AtomicU64,
    /// Frames localized (a pose published).
    pub localized: AtomicU64,
    /// Frames extracted and matched that gave no pose.
    pub failed: AtomicU64,
    /// Frames replaced by a newer one before a worker took them (localizing was slower
    /// than the camera).
    pub dropped: AtomicU64,
    /// Messages that did not decode: truncated CDR, another type's bytes, an empty or
    /// undecodable image.
    pub malformed: AtomicU64,
    /// Messages over `--max-message-bytes`, dropped undecoded.
    pub too_large: AtomicU64,
    /// Frames whose size is not the camera's (waiting for a CameraInfo of their size).
    pub camera_mismatch: AtomicU64,
    /// Frames before any camera was known (no `--camera`, no CameraInfo yet).
    pub no_camera: AtomicU64,
    /// Samples a writer sent that never arrived (gaps in its sequence numbers: lost on a
    /// best-effort link, or replaced in the reader's one-sample history).
    pub lost: AtomicU64,
    /// CameraInfo messages that did not decode.
    pub camera_info_malformed: AtomicU64,
    /// Poses, TFs, statuses and summaries not published: a subscriber's window was full.
    pub unpublished: AtomicU64,
}

impl Counts {
    pub fn add(counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    pub fn get(counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }

    /// (name, value) of every count, in the order reports list them.
    pub fn all(&self) -> [(&'static str, u64); 11] {
        let g = Counts::get;
        [
            ("received", g(&self.received)),
            ("localized", g(&self.localized)),
            ("failed", g(&self.failed)),
            ("dropped", g(&self.dropped)),
            ("malformed", g(&self.malformed)),
            ("too_large", g(&self.too_large)),
            ("camera_mismatch", g(&self.camera_mismatch)),
            ("no_camera", g(&self.no_camera)),
            ("lost", g(&self.lost)),
            ("camera_info_malformed", g(&self.camera_info_malformed)),
            ("unpublished", g(&self.unpublished)),
        ]
    }
}

/// Latencies (frame received to pose published) in 0.1 ms bins up to 10 s, and one bin
/// past it: a fixed 400 kB whatever the run's length, so a node that runs for days keeps
/// flat memory.
pub struct Latencies {
    bins: Vec<u32>,
    count: u64,
}

/// Bins per millisecond.
const BINS_PER_MS: f64 = 10.0;
/// The last bin holds every latency of 10 s or more.
const BINS: usize = 100_001;

impl Default for Latencies {
    fn default() -> Self {
        Latencies {
            bins: vec![0; BINS],
            count: 0,
        }
    }
}

impl Latencies {
    pub fn record(&mut self, latency: Duration) {
        let bin = (latency.as_secs_f64() * 1e3 * BINS_PER_MS) as usize;
        let b = &mut self.bins[bin.min(BINS - 1)];
        *b = b.saturating_add(1);
        self.count += 1;
    }

    pub fn count(&self) -> u64 {
        self.count
    }

    /// The `q` quantile (0 to 1) in milliseconds, to the bin's upper edge; `None` before the
    /// first latency.
    pub fn quantile_ms(&self, q: f64) -> Option<f64> {
        if self.count == 0 {
            return None;
        }
        let rank = ((q * self.count as f64).ceil() as u64).clamp(1, self.count);
        let mut seen = 0u64;
        for (i, &n) in self.bins.iter().enumerate() {
            seen += u64::from(n);
            if seen >= rank {
                return Some((i + 1) as f64 / BINS_PER_MS);
            }
        }
        None
    }
}

/// A frame's latencies by stage: the whole (received to pose published), and its parts, which
/// add up to it — waiting for a worker, decoding and extracting, waiting for the localizing
/// worker (`--threads 2`), localizing, publishing — to tell where a slow frame spent its
/// time; and the whole of the frames localized by tracking alone (a sequence's steady state,
/// without the frames that retrieve after tracking was lost).
#[derive(Default)]
pub struct Stages {
    pub total: Latencies,
    pub tracked: Latencies,
    pub queued: Latencies,
    pub extract: Latencies,
    pub handoff: Latencies,
    pub localize: Latencies,
    pub publish: Latencies,
}

impl Stages {
    /// Each stage's name and latencies, in pipeline order.
    pub fn parts(&self) -> [(&'static str, &Latencies); 5] {
        [
            ("queued", &self.queued),
            ("decode_extract", &self.extract),
            ("handoff", &self.handoff),
            ("localize", &self.localize),
            ("publish", &self.publish),
        ]
    }
}

/// Sequence numbers per writer, to count samples that never arrived.
#[derive(Default)]
pub struct Gaps {
    last: std::collections::HashMap<[u8; 16], i64>,
}

/// Writers remembered; past it every view is forgotten and counting starts again (a
/// publisher that comes back is a new writer each time).
const MAX_WRITERS: usize = 64;

/// A jump in a writer's sequence numbers past this is not counted as lost samples: a
/// writer that restarted its numbering, or one that lies about it.
const MAX_GAP: i64 = 1_000_000;

impl Gaps {
    /// The samples between the last one of `writer` and `sequence` (0 for its first).
    pub fn missed(&mut self, writer: [u8; 16], sequence: i64) -> u64 {
        if self.last.len() >= MAX_WRITERS && !self.last.contains_key(&writer) {
            self.last.clear();
        }
        let before = self.last.insert(writer, sequence);
        // In i128: a peer's numbers are anything an i64 holds.
        match before.map(|b| i128::from(sequence) - i128::from(b) - 1) {
            Some(gap) if gap > 0 && gap <= i128::from(MAX_GAP) => gap as u64,
            _ => 0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mailbox_keeps_the_newest_and_says_what_it_replaced() {
        let m = Mailbox::default();
        assert!(!m.put(1));
        assert!(m.put(2));
        assert_eq!(m.take(), Some(2));
        m.put(3);
        m.close();
        assert_eq!(m.take(), Some(3));
        assert_eq!(m.take(), None);
    }

    #[test]
    fn quantiles_are_read_from_the_bins() {
        let mut l = Latencies::default();
        assert_eq!(l.quantile_ms(0.5), None);
        for ms in 1..=100u64 {
            l.record(Duration::from_micros(ms * 1000 + 50));
        }
        assert_eq!(l.quantile_ms(0.5), Some(50.1));
        assert_eq!(l.quantile_ms(0.99), Some(99.1));
        l.record(Duration::from_secs(3600));
        assert_eq!(l.quantile_ms(1.0), Some(10_000.1));
    }

    #[test]
    fn gaps_count_missing_sequence_numbers_per_writer() {
        let mut g = Gaps::default();
        let (a, b) = ([1; 16], [2; 16]);
        assert_eq!(g.missed(a, 1), 0);
        assert_eq!(g.missed(a, 2), 0);
        assert_eq!(g.missed(b, 7), 0);
        assert_eq!(g.missed(a, 5), 2);
        assert_eq!(g.missed(b, 8), 0);
        // A jump no camera makes is not a count of lost frames.
        assert_eq!(g.missed(b, i64::MAX), 0);
        // Numbers at both ends of i64 neither overflow nor count.
        assert_eq!(g.missed(b, i64::MIN), 0);
        assert_eq!(g.missed(b, i64::MAX), 0);
        assert_eq!(g.missed(b, i64::MAX - 1), 0);
    }
}
