//! `sfpmap ros2`: a ROS 2 localization node. It subscribes to a camera's image topic,
//! localizes each frame in the map through a [`Session`] (a camera stream is a sequence:
//! each frame is predicted from the last ones and tracked), and publishes
//! `geometry_msgs/msg/PoseWithCovarianceStamped`, optionally a TF `map → camera`, and a
//! status per frame (`diagnostic_msgs/msg/DiagnosticArray`). DDS is RustDDS through
//! `ros2-client`: nothing of ROS is installed to build, test or run it.
//!
//! Threads: this one takes messages off the topics and leaves the newest frame in a
//! one-frame mailbox ([`frames::Mailbox`]); with `--threads 1` one worker decodes,
//! extracts, localizes and publishes; with 2, one decodes and extracts while the other
//! localizes and publishes the frame before. A frame that waits while a newer one arrives is
//! replaced and counted as dropped: the pose is always of a recent frame, never of a queue.

mod dds;
mod frames;
mod worker;

use crate::localize::MatchArgs;
use crate::Bars;
use anyhow::{bail, Context as _};
use dds::{Participant, RawReader};
use frames::{Counts, Gaps, Mailbox, Stages};
use ros2_client::dds::rustdds;
use ros2_client::QosProfile;
use sfpmap::format::Place;
use sfpmap::geometry::Camera;
use sfpmap::io::mcap_io::{self, ROS_CAMERA_INFO};
use sfpmap::session::catalog::CatalogSession;
use sfpmap::session::{QuerySource, Session};
use std::net::IpAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::Ordering;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use worker::{Incoming, Outputs, Shared};

/// Run a ROS 2 localization node: camera frames in, poses out.
///
/// Subscribes to --image-topic (sensor_msgs/msg/CompressedImage or Image) with the QoS camera
/// drivers publish with (best effort, keep last 1: a reliable publisher matches too), takes
/// the intrinsics from --camera or a sensor_msgs/msg/CameraInfo topic, and publishes each
/// localized frame's pose as geometry_msgs/msg/PoseWithCovarianceStamped (stamped with the
/// image's stamp, in --map-frame; the covariance comes from the inliers' geometry: the
/// refinement's Gauss-Newton covariance, σ²(JᵀJ)⁻¹, σ² the inliers' pixel residual variance,
/// as the camera centre in the map frame and small rotations about the map frame's axes),
/// a TF map → camera with --tf, and a status per frame (diagnostic_msgs/msg/DiagnosticArray:
/// inliers, path, timings, counts) on --status-topic. Frames are tracked as a sequence.
/// When localizing is slower than the camera, frames are dropped, not queued, and counted.
/// Malformed messages (truncated CDR, another type, an empty image) are counted and skipped.
/// Stops on SIGINT/SIGTERM (or after --frames) and prints the counts and latencies. Example:
/// `sfpmap ros2 --map kitti.sfpm --image-topic /camera/image/compressed --camera-info-topic
/// /camera/camera_info --tf`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map: a file, or an `http(s)://` or `s3://` URL. An SFP map (frames are extracted
    /// with its model).
    #[arg(long, required_unless_present = "catalog")]
    pub map: Option<PathBuf>,
    /// A catalog of place maps (`sfpmap catalog build`) instead of --map: the node localizes
    /// in one of its places, --place by name or the one nearest --prior (a place's map is
    /// refused when it is not the one the catalog was built from).
    #[arg(long, conflicts_with = "map", value_name = "CATALOG")]
    pub catalog: Option<PathBuf>,
    /// With --catalog: the place's name (default: the catalog's only place).
    #[arg(long, requires = "catalog", conflicts_with = "prior")]
    pub place: Option<String>,
    /// With --catalog: the place whose bounding box is nearest this world point ("x,y,z",
    /// e.g. from GNSS), within --radius.
    #[arg(long, requires = "catalog", value_name = "X,Y,Z", value_parser = crate::args::point)]
    pub prior: Option<[f64; 3]>,
    /// With --prior: how far outside a place's bounding box the prior may be (map units).
    #[arg(long, default_value_t = 50.0, requires = "prior", value_parser = crate::args::distance)]
    pub radius: f64,
    /// The camera's image topic.
    #[arg(long, default_value = "/camera/image_raw/compressed")]
    pub image_topic: String,
    /// The image topic's type; default: compressed when the topic's name ends in
    /// `/compressed`, else raw.
    #[arg(long, value_enum)]
    pub image_type: Option<ImageType>,
    /// The camera's intrinsics: "MODEL W H params..." (instead of --camera-info-topic).
    #[arg(long, conflicts_with = "camera_info_topic")]
    pub camera: Option<String>,
    /// Intrinsics from the newest sensor_msgs/msg/CameraInfo on this topic; frames of another
    /// size are skipped (counted) until a CameraInfo of their size arrives.
    #[arg(long)]
    pub camera_info_topic: Option<String>,
    /// Topic of the poses (geometry_msgs/msg/PoseWithCovarianceStamped).
    #[arg(long, default_value = "/sfpmap/pose")]
    pub pose_topic: String,
    /// Topic of the per-frame status (diagnostic_msgs/msg/DiagnosticArray).
    #[arg(long, default_value = "/sfpmap/status")]
    pub status_topic: String,
    /// The map's frame: the poses' frame_id and the TF's parent.
    #[arg(long, default_value = "map")]
    pub map_frame: String,
    /// Also publish each pose on /tf as map-frame → camera frame.
    #[arg(long)]
    pub tf: bool,
    /// The TF child frame; default: the image's frame_id (or "camera" when it has none).
    #[arg(long, requires = "tf")]
    pub camera_frame: Option<String>,
    /// The image subscription's reliability: best effort (what camera drivers publish; a
    /// reliable publisher matches it too) or reliable (a best-effort publisher does not match).
    #[arg(long, value_enum, default_value = "best-effort")]
    pub reliability: ReliabilityArg,
    /// 1: one thread decodes, extracts (one inference thread), localizes and publishes;
    /// 2: extraction of the next frame (two inference threads) overlaps localizing this one.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u8).range(1..=2))]
    pub threads: u8,
    /// Keep the inference threads spinning a while after each frame: a frame that comes at
    /// the camera's rate is inferred on warm threads (about a third faster at 10 Hz here),
    /// for about a third of a core more.
    #[arg(long)]
    pub spin: bool,
    /// Localize each frame on its own (no pose prior from the frames before).
    #[arg(long)]
    pub no_tracking: bool,
    /// Image and CameraInfo messages larger than this are dropped undecoded and counted.
    #[arg(long, default_value = "64MiB", value_parser = crate::args::byte_size)]
    pub max_message_bytes: u64,
    /// The DDS domain; default: ROS_DOMAIN_ID, else 0.
    #[arg(long, value_parser = clap::value_parser!(u16).range(0..=232))]
    pub domain_id: Option<u16>,
    /// Only these local addresses carry DDS discovery and multicast (repeat; e.g. 127.0.0.1
    /// to stay on this machine); default: every interface.
    #[arg(long = "interface", value_name = "ADDRESS")]
    pub interfaces: Vec<IpAddr>,
    /// Stop after this many frames were handled (localized or not).
    #[arg(long)]
    pub frames: Option<u64>,
    /// Model for extraction: a file, or a built-in model's name; default: the map's.
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[command(flatten)]
    pub matching: MatchArgs,
    /// At the end, print the counts and latencies as one JSON line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ImageType {
    /// sensor_msgs/msg/CompressedImage (JPEG or PNG).
    Compressed,
    /// sensor_msgs/msg/Image (mono8, rgb8, bgr8, rgba8, bgra8, mono16).
    Raw,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ReliabilityArg {
    BestEffort,
    Reliable,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    sfpmap::extract::runtime::disable_telemetry();
    if let Err(e) = args.matching.check() {
        e.print()?;
        return Ok(ExitCode::from(2));
    }
    let bars = Bars::new(quiet, args.json);
    if worker::frame_name(&args.map_frame, "").is_none() {
        bail!(
            "--map-frame {:?}: not a tf2 frame name (letters, digits, _ and /, at most 256, no leading /)",
            args.map_frame
        );
    }
    if args.tf && args.camera_frame.is_none() && args.map_frame == "camera" {
        bail!("--map-frame camera: \"camera\" is the TF child of a frame without a frame_id; name the camera's frame with --camera-frame");
    }
    if let Some(c) = &args.camera_frame {
        if worker::frame_name(c, &args.map_frame).is_none() {
            bail!(
                "--camera-frame {c:?}: not a tf2 frame name (letters, digits, _ and /, at most 256, no leading /) other than --map-frame"
            );
        }
    }
    let image_type = args.image_type.unwrap_or(
        if args
            .image_topic
            .trim_end_matches('/')
            .ends_with("/compressed")
        {
            ImageType::Compressed
        } else {
            ImageType::Raw
        },
    );
    let fixed_camera = match (&args.camera, &args.camera_info_topic) {
        (Some(c), _) => Some(Camera::parse(c).context("--camera")?),
        (None, Some(_)) => None,
        (None, None) => bail!(
            "the node needs the intrinsics: --camera \"MODEL W H params...\" or --camera-info-topic TOPIC"
        ),
    };
    let session = session(&args, &bars)?;
    crate::report_transfer(session.map(), quiet);
    let domain = match args.domain_id {
        Some(d) => d,
        None => domain_from_env()?,
    };
    crate::stop_on_signal();

    let mut participant = Participant::join(domain, &args.interfaces)?;
    let camera_qos = camera_qos(args.reliability);
    let (package, ty) = match image_type {
        ImageType::Compressed => ("sensor_msgs", "CompressedImage"),
        ImageType::Raw => ("sensor_msgs", "Image"),
    };
    let image_topic = participant.topic(&args.image_topic, package, ty, &camera_qos)?;
    let mut images = participant.raw_reader(&image_topic, &camera_qos)?;
    let mut camera_info = match &args.camera_info_topic {
        Some(t) => {
            let topic = participant.topic(t, "sensor_msgs", "CameraInfo", &camera_qos)?;
            Some(participant.raw_reader(&topic, &camera_qos)?)
        }
        None => None,
    };
    let outputs = Outputs::create(&mut participant, &args)?;

    let schema = match image_type {
        ImageType::Compressed => mcap_io::ROS_COMPRESSED_IMAGE,
        ImageType::Raw => mcap_io::ROS_IMAGE,
    };
    let Some(gray_weights) = session.gray_weights() else {
        bail!(
            "{}: the node extracts its frames' features, and this map's session does not",
            sfpmap::escape::escape_control_characters(session.map_name())
        );
    };
    let shared = Shared {
        session,
        schema,
        gray_weights,
        camera: Mutex::new(fixed_camera),
        camera_from_topic: args.camera_info_topic.is_some(),
        counts: Counts::default(),
        latencies: Mutex::new(Stages::default()),
        handled_limit: args.frames,
        handled: Default::default(),
        raw: Mailbox::default(),
        extracted: Mailbox::default(),
        warned: Default::default(),
        reporter: &bars,
    };
    if !quiet {
        eprintln!(
            "sfpmap ros2: node /{} on DDS domain {domain}: {} ({}) → {}{}",
            dds::NODE_NAME,
            args.image_topic,
            schema,
            args.pose_topic,
            if args.tf { " and /tf" } else { "" }
        );
    }
    let started = Instant::now();
    std::thread::scope(|s| -> anyhow::Result<()> {
        // However the receiving loop ends (a panic too), the workers are told to finish,
        // so the scope's join cannot wait on them for ever.
        let _close = CloseOnDrop(&shared);
        let workers: Vec<_> = if args.threads >= 2 {
            vec![
                s.spawn(|| shared.extract_each()),
                s.spawn(|| shared.localize_each(&outputs)),
            ]
        } else {
            vec![s.spawn(|| shared.decode_and_localize_each(&outputs))]
        };
        let running = || workers.iter().all(|w| !w.is_finished());
        receive(
            &shared,
            &mut images,
            camera_info.as_mut(),
            &args,
            &outputs,
            &running,
        )
    })?;
    report(&args, &shared, started.elapsed(), quiet)?;
    Ok(ExitCode::SUCCESS)
}

/// Closes both mailboxes when dropped: the workers then take what is left and end.
struct CloseOnDrop<'a, 'b>(&'a Shared<'b>);

impl Drop for CloseOnDrop<'_, '_> {
    fn drop(&mut self) {
        self.0.raw.close();
        self.0.extracted.close();
    }
}

/// The session over `--map`: frames are extracted with the map's model (or `--model`) and,
/// unless `--no-tracking`, tracked as a sequence.
fn session(args: &Args, bars: &Bars) -> anyhow::Result<Session> {
    let (map, name) = match (&args.map, &args.catalog) {
        (Some(path), _) => (crate::open_map(path)?, path.display().to_string()),
        (None, Some(catalog)) => place_map(args, catalog, bars)?,
        (None, None) => bail!("the node needs --map MAP or --catalog CATALOG"),
    };
    let map = Arc::new(map);
    let options = args.matching.options()(&map);
    let source = QuerySource::Images {
        folder: None,
        model: args.model.clone(),
    };
    Session::builder(map, name)
        .options(options)
        .source(source)
        .sequence(!args.no_tracking)
        .extractor_threads(args.threads.into())
        .extractor_spinning(args.spin)
        .build(bars)
        .map_err(|e| match e {
            sfpmap::session::SessionError::NotExtractable { .. } => anyhow::anyhow!(
                "{e}; the node extracts its frames' features, so it needs an SFP map (or one \
                 made with a built-in model)"
            ),
            e => e.into(),
        })
}

/// `--catalog`: the place `--place` names, the one nearest `--prior`, or the only one; its
/// map opened and checked as the catalog session opens places, and its location.
fn place_map(
    args: &Args,
    catalog: &std::path::Path,
    bars: &Bars,
) -> anyhow::Result<(sfpmap::format::Map<'static>, String)> {
    use sfpmap::escape::path;
    let session = CatalogSession::builder(
        Arc::new(crate::open_map(catalog)?),
        catalog.display().to_string(),
    )
    .remote(crate::remote_options())
    .build(bars)?;
    let chosen = choose_place(
        session.places(),
        args.place.as_deref(),
        args.prior,
        args.radius,
    )
    .map_err(|e| anyhow::anyhow!("{}: {e}", path(catalog)))?;
    let map = session.open_place_map(chosen)?;
    Ok((map, session.locations()[chosen].display().to_string()))
}

/// The place `place` names; else the one whose bounding box is nearest `prior` within
/// `radius` (of several that hold it, the one whose centre is nearest); else the only one.
fn choose_place(
    places: &[Place],
    place: Option<&str>,
    prior: Option<[f64; 3]>,
    radius: f64,
) -> Result<usize, String> {
    use sfpmap::escape::quoted_name;
    if places.is_empty() {
        return Err("lists no places".into());
    }
    let names = || {
        let mut listed: Vec<String> = places
            .iter()
            .take(10)
            .map(|p| quoted_name(&p.name))
            .collect();
        if places.len() > 10 {
            listed.push(format!("and {} more", places.len() - 10));
        }
        listed.join(", ")
    };
    let centre_distance = |p: &Place, w: [f64; 3]| {
        (0..3)
            .map(|k| (w[k] - 0.5 * (p.bbox_min[k] + p.bbox_max[k])).powi(2))
            .sum::<f64>()
    };
    match (place, prior) {
        (Some(name), _) => places
            .iter()
            .position(|p| p.name == name)
            .ok_or_else(|| format!("no place {} (places: {})", quoted_name(name), names())),
        (None, Some(w)) => places
            .iter()
            .enumerate()
            .filter(|(_, p)| p.near(w, radius))
            .min_by(|(_, a), (_, b)| {
                (a.distance(w).total_cmp(&b.distance(w)))
                    .then(centre_distance(a, w).total_cmp(&centre_distance(b, w)))
            })
            .map(|(i, _)| i)
            .ok_or_else(|| format!("no place within {radius} of {w:?} (places: {})", names())),
        (None, None) if places.len() == 1 => Ok(0),
        (None, None) => Err(format!(
            "{} places; choose one with --place NAME or --prior X,Y,Z (places: {})",
            places.len(),
            names()
        )),
    }
}

/// `ROS_DOMAIN_ID` as ROS reads it: unset or empty is domain 0.
fn domain_from_env() -> anyhow::Result<u16> {
    match std::env::var("ROS_DOMAIN_ID") {
        Ok(v) if !v.trim().is_empty() => v
            .trim()
            .parse::<u16>()
            .ok()
            .filter(|d| *d <= 232)
            .with_context(|| format!("ROS_DOMAIN_ID={v:?}: not a DDS domain (0 to 232)")),
        _ => Ok(0),
    }
}

/// The camera topics' QoS: keep last 1 (older frames are of no use once a newer one came).
fn camera_qos(reliability: ReliabilityArg) -> QosProfile {
    let base = QosProfile::subscription_default();
    match reliability {
        ReliabilityArg::BestEffort => base.reliability_best_effort(),
        ReliabilityArg::Reliable => base.reliability_reliable(ros2_client::qos::WhenFull::DEFAULT),
    }
}

/// Poll interval of the receiving loop: how soon a stop is seen and the 1 Hz summary sent.
const POLL: Duration = Duration::from_millis(100);

/// Samples taken off a topic per round of the receiving loop: a flood of them cannot keep it
/// from seeing a stop or sending the summary (the next round then does not wait).
const TAKE_PER_ROUND: usize = 64;

/// Takes messages off the image (and CameraInfo) topics until a signal, `--frames` or a
/// worker's end (a bug: a worker ends only when told); sends the 1 Hz summary to
/// `/diagnostics`.
fn receive(
    shared: &Shared<'_>,
    images: &mut RawReader,
    mut camera_info: Option<&mut RawReader>,
    args: &Args,
    outputs: &Outputs,
    workers_running: &dyn Fn() -> bool,
) -> anyhow::Result<()> {
    use rustdds::mio1::{Events, Interest, Poll, Token};
    let mut poll = Poll::new().context("creating the event poll")?;
    poll.registry()
        .register(images, Token(0), Interest::READABLE)
        .context("watching the image topic")?;
    if let Some(info) = camera_info.as_deref_mut() {
        poll.registry()
            .register(info, Token(1), Interest::READABLE)
            .context("watching the CameraInfo topic")?;
    }
    let mut events = Events::with_capacity(8);
    let mut gaps = Gaps::default();
    let mut last_summary = Instant::now();
    let limit = args.max_message_bytes;
    let mut more = false;
    loop {
        if crate::stop_requested() || shared.done() {
            return Ok(());
        }
        if !workers_running() {
            bail!("a worker thread of the node ended (a bug)");
        }
        let wait = if more { Duration::ZERO } else { POLL };
        more = false;
        if let Err(e) = poll.poll(&mut events, Some(wait)) {
            if e.kind() != std::io::ErrorKind::Interrupted {
                return Err(e).context("waiting for messages");
            }
        }
        // Each sample leaves a wake-up byte behind; unread, they would fill the socket and
        // the poll would wake only at its timeout.
        images.drain_read_notifications();
        if let Some(info) = camera_info.as_deref() {
            info.drain_read_notifications();
            let mut taken = 0;
            loop {
                if taken == TAKE_PER_ROUND {
                    more = true;
                    break;
                }
                taken += 1;
                match info.try_take_one() {
                    Ok(Some(sample)) => shared.camera_info(&sample.sample.bytes, limit),
                    Ok(None) => break,
                    Err(_) => Counts::add(&shared.counts.camera_info_malformed),
                }
            }
        }
        let mut taken = 0;
        loop {
            if taken == TAKE_PER_ROUND {
                more = true;
                break;
            }
            taken += 1;
            let sample = match images.try_take_one() {
                Ok(Some(s)) => s,
                Ok(None) => break,
                Err(e) => {
                    // RustDDS's own reading failed (not the message's bytes): counted.
                    Counts::add(&shared.counts.malformed);
                    shared.warn_once(
                        "dds",
                        &format!("{}: a sample could not be read ({e:?})", args.image_topic),
                    );
                    continue;
                }
            };
            let received = Instant::now();
            Counts::add(&shared.counts.received);
            let writer = sample.writer_guid.to_bytes();
            let missed = gaps.missed(writer, i64::from(sample.sequence_number));
            shared.counts.lost.fetch_add(missed, Ordering::Relaxed);
            let bytes = sample.sample.bytes;
            if bytes.len() as u64 > limit {
                Counts::add(&shared.counts.too_large);
                shared.warn_once(
                    "too_large",
                    &format!(
                        "{}: a message of {} bytes is over --max-message-bytes ({limit}): dropped (counted as too_large)",
                        args.image_topic,
                        bytes.len()
                    ),
                );
                continue;
            }
            if shared.raw.put(Incoming { bytes, received }) {
                Counts::add(&shared.counts.dropped);
            }
        }
        if last_summary.elapsed() >= Duration::from_secs(1) {
            last_summary = Instant::now();
            outputs.summary(shared);
        }
    }
}

/// The counts and latencies at the end: a line each, or one JSON line with `--json`.
fn report(args: &Args, shared: &Shared<'_>, elapsed: Duration, quiet: bool) -> anyhow::Result<()> {
    let counts = shared.counts.all();
    let stages = shared.latencies.lock().unwrap_or_else(|p| p.into_inner());
    let latencies = &stages.total;
    let (p50, p99) = (latencies.quantile_ms(0.5), latencies.quantile_ms(0.99));
    if args.json {
        let mut value = serde_json::Map::new();
        for (name, n) in counts {
            value.insert(name.into(), n.into());
        }
        value.insert("seconds".into(), elapsed.as_secs_f64().into());
        value.insert(
            "latency_ms".into(),
            serde_json::json!({"median": p50, "p99": p99, "frames": latencies.count()}),
        );
        let parts: serde_json::Map<_, _> = stages
            .parts()
            .iter()
            .map(|(name, l)| {
                let q = |q| l.quantile_ms(q);
                (
                    (*name).into(),
                    serde_json::json!({"median": q(0.5), "p99": q(0.99), "frames": l.count()}),
                )
            })
            .collect();
        value.insert("stages_ms".into(), parts.into());
        let tracked = &stages.tracked;
        value.insert(
            "tracked_latency_ms".into(),
            serde_json::json!({"median": tracked.quantile_ms(0.5), "p99": tracked.quantile_ms(0.99), "frames": tracked.count()}),
        );
        value.insert("threads".into(), args.threads.into());
        crate::print_json(&serde_json::Value::Object(value))?;
    } else if !quiet {
        let line: Vec<String> = counts
            .iter()
            .filter(|(name, n)| *n > 0 || matches!(*name, "received" | "localized"))
            .map(|(name, n)| format!("{n} {}", name.replace('_', " ")))
            .collect();
        eprintln!(
            "sfpmap ros2: {} in {:.1} s",
            line.join(", "),
            elapsed.as_secs_f64()
        );
        if let (Some(a), Some(b)) = (p50, p99) {
            eprintln!(
                "sfpmap ros2: frame received → pose published: median {a:.1} ms, p99 {b:.1} ms"
            );
        }
    }
    Ok(())
}

impl Shared<'_> {
    /// A CameraInfo message: the camera frames are localized with from now on.
    fn camera_info(&self, bytes: &[u8], limit: u64) {
        if bytes.len() as u64 > limit {
            Counts::add(&self.counts.too_large);
            return;
        }
        match mcap_io::decode_camera_info(ROS_CAMERA_INFO, "cdr", bytes) {
            Ok(camera) => {
                let mut current = self.camera.lock().unwrap_or_else(|p| p.into_inner());
                if current.as_ref() != Some(&camera) {
                    *current = Some(camera);
                }
            }
            Err(e) => {
                Counts::add(&self.counts.camera_info_malformed);
                self.warn_once(
                    "camera_info",
                    &format!("a CameraInfo message was skipped: {e}"),
                );
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn place(name: &str, min: [f64; 3], max: [f64; 3]) -> Place {
        Place {
            name: name.into(),
            map: format!("{name}.sfpm"),
            origin: [0.0; 3],
            bbox_min: min,
            bbox_max: max,
            points: 1,
            images: 1,
            file_bytes: 0,
            index_checksum: String::new(),
        }
    }

    #[test]
    fn a_place_is_chosen_by_name_by_the_nearest_box_or_as_the_only_one() {
        let city = place("city", [0.0; 3], [100.0; 3]);
        let library = place("library", [10.0; 3], [20.0; 3]);
        let harbour = place("harbour", [200.0, 0.0, 0.0], [220.0, 10.0, 10.0]);
        let places = [city, library, harbour];
        assert_eq!(choose_place(&places, Some("harbour"), None, 50.0), Ok(2));
        let e = choose_place(&places, Some("park"), None, 50.0).unwrap_err();
        assert!(
            e.contains("no place \"park\"") && e.contains("\"library\""),
            "{e}"
        );
        // Inside two boxes: the one whose centre is nearer (the library, not the city).
        assert_eq!(choose_place(&places, None, Some([15.0; 3]), 50.0), Ok(1));
        // Outside every box: the nearest within the radius.
        assert_eq!(
            choose_place(&places, None, Some([150.0, 5.0, 5.0]), 60.0),
            Ok(2)
        );
        assert_eq!(
            choose_place(&places, None, Some([130.0, 5.0, 5.0]), 60.0),
            Ok(0)
        );
        let e = choose_place(&places, None, Some([500.0, 0.0, 0.0]), 60.0).unwrap_err();
        assert!(e.starts_with("no place within 60"), "{e}");
        let e = choose_place(&places, None, None, 50.0).unwrap_err();
        assert!(e.starts_with("3 places; choose one"), "{e}");
        assert_eq!(choose_place(&places[..1], None, None, 50.0), Ok(0));
        assert_eq!(
            choose_place(&[], Some("city"), None, 50.0),
            Err("lists no places".to_owned())
        );
    }

    #[test]
    fn near_is_a_distance_within_the_radius() {
        let p = place("p", [0.0, 0.0, 1e16], [1.0, 1.0, 1e16]);
        for (w, r) in [
            ([0.5, 0.5, 1e16], 0.0),
            ([2.0, 0.5, 1e16], 1.0),
            ([2.0, 0.5, 1e16], 0.999),
            ([0.5, 0.5, 1.5], 1e16 - 2.0),
            ([f64::NAN, 0.5, 1e16], 1e300),
        ] {
            assert_eq!(p.near(w, r), p.distance(w) <= r, "{w:?} {r}");
        }
        assert_eq!(p.distance([2.0, -3.0, 1e16]), 3.0);
        assert_eq!(p.distance([f64::NAN, 0.0, 0.0]), f64::INFINITY);
    }
}
