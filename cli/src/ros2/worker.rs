//! The node's workers: a frame's bytes decoded and its features extracted, then localized
//! and its pose, TF and status published; and what they publish.

use super::dds::{
    self, Covariance, DiagnosticArray, DiagnosticStatus, Header, KeyValue, Participant, PoseMsg,
    PoseWithCovariance, PoseWithCovarianceStamped, Quaternion, TfMessage, Transform,
    TransformStamped, Xyz,
};
use super::frames::{Counts, Mailbox, Stages};
use super::Args;
use crate::Bars;
use ros2_client::{Publisher, QosProfile};
use sfpmap::geometry::{Camera, Pose};
use sfpmap::io::mcap_io::{self, Stamp};
use sfpmap::localize::{Localization, LocalizationPath};
use sfpmap::progress::Reporter;
use sfpmap::session::{image_misfits_camera, Frame, Session};
use std::collections::HashSet;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// An image message as it was taken off the topic.
pub struct Incoming {
    pub bytes: Vec<u8>,
    pub received: Instant,
}

/// A frame decoded and extracted (or why its features could not be made), for the
/// localizing thread.
pub struct Extracted {
    features: Result<Frame, String>,
    camera: Camera,
    stamp: Option<Stamp>,
    frame_id: String,
    received: Instant,
    /// Taken off the mailbox by a worker, and decoded and extracted, this long after `received`.
    queued: Duration,
    extracted: Duration,
}

/// What the receiving thread and the workers share.
pub struct Shared<'a> {
    pub session: Session,
    /// The image topic's message type (`sensor_msgs/msg/CompressedImage` or `Image`).
    pub schema: &'static str,
    /// The model's RGB-to-grey weights.
    pub gray_weights: [f32; 3],
    /// `--camera`, or the newest CameraInfo's.
    pub camera: Mutex<Option<Camera>>,
    pub camera_from_topic: bool,
    pub counts: Counts,
    pub latencies: Mutex<Stages>,
    /// `--frames`.
    pub handled_limit: Option<u64>,
    /// Frames localized or failed.
    pub handled: AtomicU64,
    pub raw: Mailbox<Incoming>,
    pub extracted: Mailbox<Extracted>,
    /// The kinds of warning given once already.
    pub warned: Mutex<HashSet<&'static str>>,
    pub reporter: &'a Bars,
}

impl Shared<'_> {
    /// `--frames` frames were handled.
    pub fn done(&self) -> bool {
        self.handled_limit
            .is_some_and(|n| self.handled.load(Ordering::Relaxed) >= n)
    }

    /// A warning the first time `kind` happens; the counts say how often it did.
    pub fn warn_once(&self, kind: &'static str, message: &str) {
        let first = self
            .warned
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .insert(kind);
        if first {
            self.reporter.warn(message);
        }
    }

    /// A message not published (a subscriber too slow to take it): counted, warned once.
    pub fn unpublished(&self, what: &str, e: &dyn std::fmt::Debug) {
        Counts::add(&self.counts.unpublished);
        self.warn_once(
            "unpublished",
            &format!("{what} could not be published ({e:?}); counted as unpublished"),
        );
    }

    /// `--threads 2`, the first worker: decodes and extracts the newest frame, leaves it for
    /// the localizing one.
    pub fn extract_each(&self) {
        // One frame extracted ahead at most: a newer frame replaces an older one before it
        // is decoded, never after its inference.
        while let Some(incoming) = {
            self.extracted.wait_empty();
            self.raw.take()
        } {
            if let Some(extracted) = self.guarded(|| self.prepare(incoming)).flatten() {
                if self.extracted.put(extracted) {
                    Counts::add(&self.counts.dropped);
                }
            }
        }
        self.extracted.close();
    }

    /// `--threads 2`, the second worker: localizes and publishes.
    pub fn localize_each(&self, outputs: &Outputs) {
        while let Some(extracted) = self.extracted.take() {
            self.guarded(|| self.finish(extracted, outputs));
            if self.done() {
                break;
            }
        }
    }

    /// `--threads 1`: one worker for it all.
    pub fn decode_and_localize_each(&self, outputs: &Outputs) {
        while let Some(incoming) = self.raw.take() {
            if let Some(extracted) = self.guarded(|| self.prepare(incoming)).flatten() {
                self.guarded(|| self.finish(extracted, outputs));
            }
            if self.done() {
                break;
            }
        }
    }

    /// `f`, with a panic counted as a failed frame (a bug) instead of ending the node.
    fn guarded<T>(&self, f: impl FnOnce() -> T) -> Option<T> {
        match catch_unwind(AssertUnwindSafe(f)) {
            Ok(v) => Some(v),
            Err(_) => {
                Counts::add(&self.counts.failed);
                self.handled.fetch_add(1, Ordering::Relaxed);
                self.session.reset_tracking();
                self.warn_once(
                    "panic",
                    "internal error while handling a frame (a bug): the frame is counted as failed",
                );
                None
            }
        }
    }

    /// A message's image decoded and its features extracted; `None` (counted) when its bytes
    /// do not decode or there is no camera of its size.
    fn prepare(&self, incoming: Incoming) -> Option<Extracted> {
        let Incoming { bytes, received } = incoming;
        let queued = received.elapsed();
        let malformed = |e: mcap_io::McapIoError| {
            Counts::add(&self.counts.malformed);
            self.warn_once(
                "malformed",
                &format!(
                    "a {} message was skipped (counted as malformed): {e}",
                    self.schema
                ),
            );
        };
        let camera = self
            .camera
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        let Some(camera) = camera else {
            Counts::add(&self.counts.no_camera);
            self.warn_once(
                "no_camera",
                "frames arrive before any CameraInfo: skipped until one does",
            );
            return None;
        };
        // The size from the header: a frame not of the camera's size is never decoded, so
        // a small message that claims a huge image costs nothing.
        let (w, h) = match mcap_io::image_size(self.schema, "cdr", &bytes) {
            Ok(size) => size,
            Err(e) => {
                malformed(e);
                return None;
            }
        };
        if let Some(reason) = image_misfits_camera(w as usize, h as usize, &camera) {
            Counts::add(&self.counts.camera_mismatch);
            let then = if self.camera_from_topic {
                "skipped until a CameraInfo of that size arrives"
            } else {
                "skipped (--camera is fixed)"
            };
            self.warn_once(
                "camera_mismatch",
                &format!("frames skipped: {reason}; {then}"),
            );
            return None;
        }
        let decoded = match mcap_io::decode_image(self.schema, "cdr", &bytes) {
            Ok(d) => d,
            Err(e) => {
                malformed(e);
                return None;
            }
        };
        drop(bytes);
        let input = sfpmap::extract::image::from_image(&decoded.image, self.gray_weights, None);
        let features = self.session.extract(input).map_err(|e| e.to_string());
        Some(Extracted {
            features,
            camera,
            stamp: decoded.stamp,
            frame_id: decoded.frame_id,
            received,
            queued,
            extracted: received.elapsed(),
        })
    }

    /// A frame localized; its pose (and TF) and status published.
    fn finish(&self, extracted: Extracted, outputs: &Outputs) {
        let Extracted {
            features,
            camera,
            stamp,
            frame_id,
            received,
            queued,
            extracted,
        } = extracted;
        let name = match stamp {
            Some(s) => format!("frame {}.{:09}", s.sec, s.nsec),
            None => "frame".to_owned(),
        };
        let handed = received.elapsed();
        let localizing = Instant::now();
        let found = match features {
            Ok(frame) => self
                .session
                .localize_frame(frame, &camera, &name)
                .map_err(|e| e.to_string()),
            Err(reason) => {
                self.session.reset_tracking();
                Err(reason)
            }
        };
        let localized_in = localizing.elapsed();
        let stamp = stamp.map_or_else(dds::now, |s| dds::ros_time(s.sec, s.nsec));
        let pose = found
            .as_ref()
            .ok()
            .and_then(|l| l.pose().filter(|p| p.is_finite()));
        let localized = pose.is_some();
        if let (Ok(l), Some(pose)) = (&found, pose) {
            outputs.pose(pose, l, stamp, &frame_id, self);
        }
        let latency = received.elapsed();
        Counts::add(if localized {
            &self.counts.localized
        } else {
            &self.counts.failed
        });
        {
            let mut stages = lock(&self.latencies);
            stages.total.record(latency);
            if matches!(&found, Ok(l) if localized && l.path == LocalizationPath::Tracking) {
                stages.tracked.record(latency);
            }
            stages.queued.record(queued);
            stages.extract.record(extracted.saturating_sub(queued));
            stages.handoff.record(handed.saturating_sub(extracted));
            stages.localize.record(localized_in);
            stages
                .publish
                .record(latency.saturating_sub(handed + localized_in));
        }
        self.handled.fetch_add(1, Ordering::Relaxed);
        outputs.status(&found, stamp, latency.as_secs_f64() * 1e3, self);
    }
}

/// The variance published when a pose has no covariance.
pub const UNKNOWN_VARIANCE: f64 = 1e6;

/// A tf2 frame name: letters, digits, `_` and `/`, at most 256, not starting with `/` (tf2
/// refuses those) and not `map_frame` (a TF from the map to itself would loop the tree).
pub fn frame_name<'a>(frame_id: &'a str, map_frame: &str) -> Option<&'a str> {
    let ok = !frame_id.is_empty()
        && frame_id.len() <= 256
        && !frame_id.starts_with('/')
        && frame_id != map_frame
        && frame_id
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '/');
    ok.then_some(frame_id)
}

/// The node's publishers.
pub struct Outputs {
    pose: Mutex<Publisher<PoseWithCovarianceStamped>>,
    tf: Option<Mutex<Publisher<TfMessage>>>,
    status: Mutex<Publisher<DiagnosticArray>>,
    diagnostics: Mutex<Publisher<DiagnosticArray>>,
    map_frame: String,
    camera_frame: Option<String>,
    /// (dropped, received) at the last `/diagnostics` summary.
    last_summary: Mutex<(u64, u64)>,
}

/// The published topics' QoS: reliable, keep last 10 (ROS's default depth); a publish that
/// finds the send window full (a slow subscriber) fails at once and is counted, rather than
/// holding the frame back.
fn output_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(ros2_client::qos::WhenFull::Fail)
        .history(ros2_client::qos::History::KeepLast { depth: 10 })
}

impl Outputs {
    pub fn create(participant: &mut Participant, args: &Args) -> anyhow::Result<Outputs> {
        let qos = output_qos();
        let publisher = |name: &str, package: &str, ty: &str| -> anyhow::Result<_> {
            let topic = participant.topic(name, package, ty, &qos)?;
            Ok(topic)
        };
        let pose_topic = publisher(
            &args.pose_topic,
            "geometry_msgs",
            "PoseWithCovarianceStamped",
        )?;
        let status_topic = publisher(&args.status_topic, "diagnostic_msgs", "DiagnosticArray")?;
        let diagnostics_topic = publisher("/diagnostics", "diagnostic_msgs", "DiagnosticArray")?;
        let tf_topic = match args.tf {
            true => Some(publisher("/tf", "tf2_msgs", "TFMessage")?),
            false => None,
        };
        Ok(Outputs {
            pose: Mutex::new(participant.publisher(&pose_topic, qos.clone())?),
            tf: match tf_topic {
                Some(t) => Some(Mutex::new(participant.publisher(&t, qos.clone())?)),
                None => None,
            },
            status: Mutex::new(participant.publisher(&status_topic, qos.clone())?),
            diagnostics: Mutex::new(participant.publisher(&diagnostics_topic, qos)?),
            map_frame: args.map_frame.clone(),
            camera_frame: args.camera_frame.clone(),
            last_summary: Mutex::new((0, 0)),
        })
    }

    /// The camera's pose in the map (`cam_from_world` inverted) with its covariance, and the
    /// TF to the camera's frame.
    fn pose(
        &self,
        cam_from_world: &Pose,
        l: &Localization,
        stamp: dds::Time,
        frame_id: &str,
        shared: &Shared<'_>,
    ) {
        let world_from_cam = cam_from_world.inverse();
        let t = world_from_cam.translation;
        let q = world_from_cam.rotation;
        let position = Xyz {
            x: t.x,
            y: t.y,
            z: t.z,
        };
        let orientation = Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        };
        // Unknown (only the coarse pose stands): variances no filter trusts; the status says
        // `covariance: unknown`. (geometry_msgs has no mark for unknown; Imu's -1 is read as a
        // variance by filters that do not know it.)
        let covariance = l
            .covariance
            .map(|c| c.world_from_camera(cam_from_world))
            .filter(|c| c.iter().all(|v| v.is_finite()))
            .unwrap_or_else(|| {
                let mut unknown = [0.0; 36];
                for i in 0..6 {
                    unknown[i * 7] = UNKNOWN_VARIANCE;
                }
                unknown
            });
        let header = Header {
            stamp,
            frame_id: self.map_frame.clone(),
        };
        let message = PoseWithCovarianceStamped {
            header: header.clone(),
            pose: PoseWithCovariance {
                pose: PoseMsg {
                    position,
                    orientation,
                },
                covariance: Covariance(covariance),
            },
        };
        if let Err(e) = lock(&self.pose).publish(message) {
            shared.unpublished("a pose", &e);
        }
        if let Some(tf) = &self.tf {
            let child = match (&self.camera_frame, frame_name(frame_id, &self.map_frame)) {
                (Some(c), _) => c.clone(),
                (None, Some(f)) => f.to_owned(),
                (None, None) => {
                    if !frame_id.is_empty() {
                        shared.warn_once("frame_id", "an image's frame_id is not a tf2 frame name of a camera (letters, digits, _ and /, at most 256, no leading /, not the map frame): the TF's child is \"camera\" (--camera-frame names it)");
                    }
                    "camera".to_owned()
                }
            };
            let message = TfMessage {
                transforms: vec![TransformStamped {
                    header,
                    child_frame_id: child,
                    transform: Transform {
                        translation: position,
                        rotation: orientation,
                    },
                }],
            };
            if let Err(e) = lock(tf).publish(message) {
                shared.unpublished("a TF", &e);
            }
        }
    }

    /// The frame's status: localized or why not, inliers, path, timings, latency, counts.
    fn status(
        &self,
        found: &Result<Localization, String>,
        stamp: dds::Time,
        latency_ms: f64,
        shared: &Shared<'_>,
    ) {
        let mut values = Vec::new();
        let mut kv = |k: &str, v: String| {
            values.push(KeyValue {
                key: k.into(),
                value: v,
            })
        };
        let (level, message) = match found {
            Ok(l) => {
                kv("inliers", l.inliers.to_string());
                kv("matches", l.matches.to_string());
                kv("path", l.path.name().to_owned());
                kv("retrieval_ms", format!("{:.3}", l.times.retrieval_ms));
                kv(
                    "coarse_ms",
                    format!("{:.3}", l.times.coarse_match_ms + l.times.coarse_ransac_ms),
                );
                kv("fine_ms", format!("{:.3}", l.times.fine_ms));
                kv("localize_ms", format!("{:.3}", l.times.total_ms));
                match &l.covariance {
                    Some(c) => kv("sigma_px", format!("{:.4}", c.sigma_px)),
                    None => kv("covariance", "unknown".to_owned()),
                }
                match l.pose() {
                    Some(_) => (0u8, "localized".to_owned()),
                    None => (1, l.failure_line()),
                }
            }
            Err(reason) => (1, reason.clone()),
        };
        kv("latency_ms", format!("{latency_ms:.3}"));
        for (name, n) in shared.counts.all() {
            kv(name, n.to_string());
        }
        let message = DiagnosticArray {
            header: Header {
                stamp,
                frame_id: self.map_frame.clone(),
            },
            status: vec![DiagnosticStatus {
                level,
                name: format!("{}: frame", super::dds::NODE_NAME),
                message,
                hardware_id: String::new(),
                values,
            }],
        };
        if let Err(e) = lock(&self.status).publish(message) {
            shared.warn_once(
                "publish_status",
                &format!("a status could not be published: {e:?}"),
            );
        }
    }

    /// The counts and latencies on `/diagnostics`, once a second (what ROS's diagnostic
    /// aggregator reads).
    pub fn summary(&self, shared: &Shared<'_>) {
        let stages = lock(&shared.latencies);
        let latencies = &stages.total;
        let mut values: Vec<KeyValue> = shared
            .counts
            .all()
            .iter()
            .map(|(k, v)| KeyValue {
                key: (*k).into(),
                value: v.to_string(),
            })
            .collect();
        for (key, q) in [("latency_median_ms", 0.5), ("latency_p99_ms", 0.99)] {
            if let Some(ms) = latencies.quantile_ms(q) {
                values.push(KeyValue {
                    key: key.into(),
                    value: format!("{ms:.1}"),
                });
            }
        }
        drop(stages);
        // What changed since the last summary: WARN while frames are being dropped, STALE
        // while none arrive.
        let (dropped, received) = (
            Counts::get(&shared.counts.dropped),
            Counts::get(&shared.counts.received),
        );
        let mut last = lock(&self.last_summary);
        let (level, message) = if received == last.1 {
            (3u8, "no frames since the last summary".to_owned())
        } else if dropped > last.0 {
            (
                1,
                format!(
                    "{} frames dropped: localizing is slower than the camera",
                    dropped - last.0
                ),
            )
        } else {
            (0, "ok".to_owned())
        };
        *last = (dropped, received);
        drop(last);
        let message = DiagnosticArray {
            header: Header {
                stamp: dds::now(),
                frame_id: String::new(),
            },
            status: vec![DiagnosticStatus {
                level,
                name: super::dds::NODE_NAME.to_owned(),
                message,
                hardware_id: String::new(),
                values,
            }],
        };
        if let Err(e) = lock(&self.diagnostics).publish(message) {
            shared.warn_once(
                "publish_diagnostics",
                &format!("diagnostics could not be published: {e:?}"),
            );
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tf_child_is_a_tf2_name_other_than_the_map_frame() {
        assert_eq!(
            frame_name("kitti/camera_left", "map"),
            Some("kitti/camera_left")
        );
        for bad in [
            "",
            "/camera",
            "map",
            "camera left",
            "cam\u{0}",
            &"c".repeat(257),
        ] {
            assert_eq!(frame_name(bad, "map"), None, "{bad:?}");
        }
        assert_eq!(frame_name("map", "world"), Some("map"));
    }
}
