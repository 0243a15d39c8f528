//! `sfpmap localize --mcap IN.mcap --topic TOPIC -o OUT.mcap`: localize the images of one topic
//! of an MCAP log and write their poses as `foxglove.PoseInFrame` (and optionally TUM). The
//! library runs it ([`sfpmap::session::mcap_log`]); this parses the flags and prints.
//!
//! Damaged logs: each skipped part is a warning naming the file and where, and `unreadable`
//! in `--json`; what was read is localized and written, and the exit status is
//! [`SKIPPED_EXIT`] instead of 0. It is an error when no image message on the topic could be
//! read or decoded at all.

use super::super::Bars;
use super::{Args, SKIPPED_EXIT};
use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::escape::escape_control_characters;
use sfpmap::geometry::Camera;
use sfpmap::localize::eval::{median, PathCounts};
use sfpmap::progress::Reporter;
use sfpmap::session::mcap_log::{ImageLog, LogLocalization, MAX_DAMAGE_WARNINGS};
use sfpmap::session::{QuerySource, Session};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

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

pub fn run(args: &Args, quiet: bool, bars: &Bars) -> anyhow::Result<ExitCode> {
    let start = Instant::now();
    let m = &args.mcap;
    let (Some(input), Some(topic)) = (m.mcap.as_deref(), m.topic.as_deref()) else {
        bail!("--mcap needs --topic");
    };
    super::check_outputs(args, &[input], &[])?;
    // With a summary, a missing topic is found before anything is decoded.
    let log = ImageLog::open(input, topic, bars)?;
    let camera = match (&args.camera, &m.camera_info_topic) {
        (Some(c), _) => Camera::parse(c).context("--camera")?,
        (None, Some(t)) => log.camera_from_info(t)?,
        (None, None) => bail!("--mcap needs the intrinsics: --camera \"MODEL W H params...\" or --camera-info-topic TOPIC"),
    };
    let session = session(args, bars)?;
    let found = log.localize(&session, &camera, args.threads, bars)?;
    found.write_mcap(
        &args.output,
        &m.pose_topic,
        &m.frame_id,
        m.passthrough_images,
    )?;
    if let Some(tum) = &m.tum {
        found.write_tum(tum)?;
    }
    warn_damage(&found, bars);
    if args.json {
        print_json(args, &found, &camera, &session, start)?;
    } else if !quiet {
        print(args, &found);
    }
    Ok(if found.skipped().is_empty() {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(SKIPPED_EXIT)
    })
}

/// The session over `--map`: a log is a sequence, each frame predicted from the last ones
/// and tracked; its images are extracted with the map's model (or `--model`).
fn session(args: &Args, bars: &Bars) -> anyhow::Result<Session> {
    let map = Arc::new(super::super::open_map(args.map_path())?);
    let source = QuerySource::Images {
        folder: None,
        model: args.model.clone(),
    };
    let not_sfp = "MCAP images need an SFP map (their features are extracted with the SFP model)";
    super::session(args, map, source, true, not_sfp, bars)
}

/// One warning summing up the damaged parts skipped, if any: how many, and how many image
/// messages they cost.
fn warn_damage(found: &LogLocalization, bars: &Bars) {
    if found.skipped().is_empty() {
        return;
    }
    // Without a summary (a cut-off log) how many messages were lost is unknown.
    let lost = match found.unreadable_images() {
        Some(n) => format!("{n} lost"),
        None => "how many were lost is unknown (no summary)".to_owned(),
    };
    let parts = match found.skipped_count() {
        1 => "1 damaged part".to_owned(),
        n if n > MAX_DAMAGE_WARNINGS => {
            format!("{n} damaged parts (the first {MAX_DAMAGE_WARNINGS} above)")
        }
        n => format!("{n} damaged parts"),
    };
    bars.warn(&format!(
        "{}: {parts} of the log skipped (exit status {SKIPPED_EXIT}); image messages on {}: {} read, {lost}",
        sfpmap::escape::path(found.path()),
        found.topic(),
        found.images()
    ));
}

/// `--json`, serialized straight from the frames: a `Value` per failed frame would cost far
/// more than the frames themselves.
fn print_json(
    args: &Args,
    found: &LogLocalization,
    camera: &Camera,
    session: &Session,
    start: Instant,
) -> anyhow::Result<()> {
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
    let unreadable = found.skipped().first().map(|e| {
        json!({
            "error": e,
            "messages": found.unreadable_images(),
            "skipped": found.skipped(),
            "skipped_count": found.skipped_count(),
        })
    });
    let paths = PathCounts::of(found.results());
    let m = &args.mcap;
    let report = Report {
        mcap: found.path().display().to_string(),
        topic: found.topic(),
        images: found.images(),
        localized: found.localized(),
        failed: FailedFrames(found),
        unreadable,
        output: args.output.display().to_string(),
        pose_topic: &m.pose_topic,
        tum: m.tum.as_ref().map(|p| p.display().to_string()),
        camera: camera.to_string(),
        seconds: start.elapsed().as_secs_f64(),
        median_ms: super::median_ms(found.results()),
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
    Ok(())
}

/// The lines a person reads: counts, the median time, fallbacks and failed frames.
fn print(args: &Args, found: &LogLocalization) {
    let results = found.results();
    println!(
        "{}: {}/{} images of {} localized, median {:.1} ms per image (after features)",
        sfpmap::escape::path(&args.output),
        found.localized(),
        found.images(),
        escape_control_characters(found.topic()),
        median(results.clone().map(|r| r.times.total_ms).collect()).unwrap_or(f64::NAN)
    );
    super::print_paths(&PathCounts::of(results), found.images());
    for (index, _, reason) in found.failed() {
        // Escaped: the reason may quote the file (a schema name, an encoding).
        println!(
            "failed: image {index} ({})",
            escape_control_characters(&reason)
        );
    }
}

/// The frames that were not localized, serialized as `{index, stamp: {sec, nsec}, reason}`
/// without a copy per frame.
struct FailedFrames<'a>(&'a LogLocalization);

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
        s.collect_seq(self.0.failed().map(|(index, f, reason)| Failed {
            index,
            stamp: StampJson {
                sec: f.stamp.sec,
                nsec: f.stamp.nsec,
            },
            reason,
        }))
    }
}
