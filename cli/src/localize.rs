//! `sfpmap localize`: camera poses of query images in a map.

use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::colmap::text::text_name_problem;
use sfpmap::escape::{escape_control_characters, quoted_name};
use sfpmap::format::Map;
use sfpmap::geometry::Camera;
use sfpmap::io::poses::{write_query_poses, QueryPoseFormat};
use sfpmap::io::queries::{read_query_list, Query};
use sfpmap::localize::eval::{median, PathCounts};
use sfpmap::localize::{
    describe_skipped, Localization, LocalizeOptions, MatchOptions, QueryFailure, RetrievalMethod,
    SkippedLevel,
};
use sfpmap::progress::Reporter;
use sfpmap::session::{QuerySource, Session, SessionError};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum RetrievalArg {
    /// The map's stated preference (metadata `retrieval`), else whichever it has.
    Auto,
    /// The VLAD of the map's own descriptors (every map converted by 1.1).
    Vlad,
    /// The extractor's global descriptor (SFP maps).
    Global,
    /// None: every point is a candidate (the brute-force reference).
    Off,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum PoseFormat {
    /// `name qw qx qy qz tx ty tz` (COLMAP cam_from_world), like gt_poses.txt.
    Colmap,
    /// `index tx ty tz qx qy qz qw` (TUM: the camera's pose in the world).
    Tum,
    /// One JSON object per query, in a list.
    Json,
    /// A kapture 1.1 folder at OUTPUT: sensors.txt (the query cameras), records_camera.txt
    /// (every query) and trajectories.txt (the localized ones).
    Kapture,
}

impl PoseFormat {
    /// The library's layout of a one-file format; `None` for kapture (a folder).
    fn lines(self) -> Option<QueryPoseFormat> {
        match self {
            PoseFormat::Colmap => Some(QueryPoseFormat::Colmap),
            PoseFormat::Tum => Some(QueryPoseFormat::Tum),
            PoseFormat::Json => Some(QueryPoseFormat::Json),
            PoseFormat::Kapture => None,
        }
    }
}

/// The files `-o` names: OUTPUT itself, or the three files of a kapture folder at OUTPUT.
pub(super) fn output_files(args: &Args) -> Vec<PathBuf> {
    match args.format {
        PoseFormat::Kapture => sfpmap::io::kapture::QUERY_FILES
            .iter()
            .map(|f| args.output.join(f))
            .collect(),
        _ => vec![args.output.clone()],
    }
}

/// Localize query images in a map: retrieval, coarse matching on the deepest level, P3P
/// LO-RANSAC, gated matching level by level, refinement.
///
/// Query intrinsics come from the query list (`name MODEL W H params...`, hloc style) or one
/// `--camera` for all. Query features: for SFP maps extracted from the images in --images
/// with the map's model (embedded by default); for SIFT maps from a COLMAP database holding
/// the queries' keypoints and descriptors (`--database queries.db`). Failed queries are written
/// as `# failed NAME: reason` lines; a query whose features cannot be read (missing, an image
/// that does not decode, a name outside --images, a malformed entry of --features or
/// --database) fails alone, and the exit status is then 3. Example:
/// `sfpmap localize --map sb.sfpm --query-list queries.txt --database queries.db -o poses.txt`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map: a file, or an `http(s)://` or `s3://` URL.
    #[arg(long, required_unless_present = "catalog")]
    pub map: Option<PathBuf>,
    /// A catalog of place maps (`sfpmap catalog build`) instead of one map: each query's
    /// candidate places are ranked by retrieval on their summaries, the best `--places` are
    /// opened (only their needed sections, for URLs) and the pose with the most inliers wins.
    /// Query features from `--database` or `--features`.
    #[arg(long, conflicts_with = "map", value_name = "CATALOG")]
    pub catalog: Option<PathBuf>,
    /// With --catalog: candidate places tried per query, best ranked first.
    #[arg(long, default_value_t = 2, requires = "catalog",
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub places: usize,
    /// With --catalog: only places whose bounding box lies within --radius of this world
    /// point ("x,y,z", three finite numbers).
    #[arg(long, requires = "catalog", value_name = "X,Y,Z", value_parser = super::args::point)]
    pub prior: Option<[f64; 3]>,
    /// With --prior: how far from a place's bounding box the prior may be (map units; finite,
    /// 0 or more).
    #[arg(long, default_value_t = 50.0, requires = "prior", value_parser = super::args::distance)]
    pub radius: f64,
    /// Query list: `name MODEL W H params...` per line (or names only with --camera).
    #[cfg_attr(feature = "mcap", arg(long, required_unless_present = "mcap"))]
    #[cfg_attr(not(feature = "mcap"), arg(long, required = true))]
    pub query_list: Option<PathBuf>,
    /// Folder with the query images (needed when features are extracted).
    #[arg(long, conflicts_with = "catalog")]
    pub images: Option<PathBuf>,
    /// One camera for every query: "MODEL W H params...".
    #[arg(long)]
    pub camera: Option<String>,
    /// COLMAP database with the queries' keypoints and descriptors (SIFT, or a learned feature
    /// by its descriptor type), for maps of that feature.
    #[arg(long)]
    pub database: Option<PathBuf>,
    /// hloc-style features.h5 with the queries' features (hloc's, or `sfpmap extract`'s).
    /// A file that names its feature (sfp.model_name, hloc's feats-CONF.h5) must hold the
    /// map's.
    #[arg(long, conflicts_with = "database")]
    pub features: Option<PathBuf>,
    /// hloc global-feats.h5 with the queries' global descriptors, for retrieval in a map
    /// converted with --global-features.
    #[cfg(feature = "hdf5")]
    #[arg(long, conflicts_with = "catalog")]
    pub global_features: Option<PathBuf>,
    /// Model for query extraction: a file, or a built-in model's name (sfp-v3, sfp-v2, sfp-v1, sfp-v2s,
    /// aliked-n16); default: the built-in model the map was made with (another model
    /// runs as asked, with a warning).
    #[arg(long)]
    pub model: Option<PathBuf>,
    #[command(flatten)]
    pub matching: MatchArgs,
    /// Output poses.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Layout of OUTPUT: a line per query (colmap, tum) or a JSON list with each query's details.
    #[arg(long, value_enum, default_value = "colmap")]
    pub format: PoseFormat,
    /// Worker threads (queries run in parallel; the map is shared); capped at 4 per core, at
    /// most 256, with a warning.
    #[arg(long, default_value_t = 2,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub threads: usize,
    /// The query list is an ordered sequence (a camera moving): each query's pose is
    /// predicted from the previous ones (constant velocity) and it is localized by guided
    /// matching around the prediction, through retrieval only when tracking is lost (fewer
    /// than 12 inliers around the prediction, or no database image near it). Queries run in
    /// order, on one thread. Always on for --mcap.
    #[arg(long, conflicts_with = "catalog")]
    pub sequence: bool,
    /// Overwrite the output(s) if they exist.
    #[arg(long)]
    pub force: bool,
    /// Print a JSON summary (counts, per-stage median times).
    #[arg(long)]
    pub json: bool,
    #[cfg(feature = "mcap")]
    #[command(flatten)]
    pub mcap: mcap_input::McapArgs,
}

/// How queries are matched: `--level`, `--short`, `--top-k`, `--retrieval`,
/// `--retrieval-probe` and `--ratio` (`sfpmap localize` and `sfpmap ros2`).
#[derive(Debug, Clone, clap::Args)]
pub struct MatchArgs {
    /// Levels to use (repeat); default all. Coarse matching uses the deepest.
    #[arg(long = "level")]
    pub levels: Vec<u16>,
    /// Match with the short descriptor block only.
    #[arg(long)]
    pub short: bool,
    /// Database images retrieved per query (maps with global descriptors or VLAD; 1 to
    /// 100000).
    #[arg(long, default_value_t = sfpmap::format::DEFAULT_RETRIEVAL_TOP_K)]
    pub top_k: usize,
    /// What ranks the database images: the map's stated preference (auto), its VLAD of local
    /// descriptors, the extractor's global descriptor, or nothing (every point a candidate).
    #[arg(long, value_enum, default_value = "auto")]
    pub retrieval: RetrievalArg,
    /// Lists of the map's image index (format 1.3, maps of many images) a query scores
    /// before it widens along the images' neighbours (1.4) (default: the map's own,
    /// calibrated when it was converted); 0 scores every image, as on maps without an
    /// index.
    #[arg(long, value_name = "LISTS")]
    pub retrieval_probe: Option<usize>,
    /// Lowe ratio for coarse matching, in (0, 1] (default: 0.95 on SFP maps, 0.9 on SIFT
    /// maps).
    #[arg(long)]
    pub ratio: Option<f32>,
}

impl Args {
    /// `--map` (clap requires it unless `--catalog`, whose path does not call this).
    pub fn map_path(&self) -> &Path {
        self.map
            .as_deref()
            .expect("--map is required without --catalog")
    }
}

// Child modules so they share this command's private helpers; the files sit beside this one.
#[path = "localize_catalog.rs"]
mod catalog_input;
#[cfg(feature = "mcap")]
#[path = "localize_mcap.rs"]
mod mcap_input;

/// The `median_ms` object of `--json`: per-stage median times over the results.
fn median_ms<'a, I>(results: I) -> serde_json::Value
where
    I: IntoIterator<Item = &'a Localization>,
    I::IntoIter: Clone,
{
    let results = results.into_iter();
    let stage = |f: fn(&Localization) -> f64| median(results.clone().map(f).collect());
    json!({
        "retrieval": stage(|r| r.times.retrieval_ms),
        "coarse_match": stage(|r| r.times.coarse_match_ms),
        "coarse_ransac": stage(|r| r.times.coarse_ransac_ms),
        "fine": stage(|r| r.times.fine_ms),
        "total": stage(|r| r.times.total_ms),
    })
}

/// An f32 as the f64 of its shortest decimal form (0.95, not 0.949999988079071).
fn shortest_f64(v: f32) -> f64 {
    v.to_string().parse().unwrap_or(f64::from(v))
}

impl MatchArgs {
    /// `base` with these flags.
    fn over(&self, base: LocalizeOptions) -> LocalizeOptions {
        LocalizeOptions {
            levels: self.levels.clone(),
            short: self.short,
            top_k: self.top_k,
            retrieval: match self.retrieval {
                RetrievalArg::Auto => RetrievalMethod::Auto,
                RetrievalArg::Vlad => RetrievalMethod::Vlad,
                RetrievalArg::Global => RetrievalMethod::Global,
                RetrievalArg::Off => RetrievalMethod::Off,
            },
            retrieval_probe: self.retrieval_probe,
            matching: MatchOptions {
                ratio: self.ratio.unwrap_or(base.matching.ratio),
                ..base.matching
            },
            ..base
        }
    }

    /// The localizer's options for a map: its defaults ([`LocalizeOptions::for_map`]) with
    /// these flags. The session checks them; [`MatchArgs::check`] did before any map was
    /// opened.
    pub fn options(&self) -> impl Fn(&Map<'_>) -> LocalizeOptions + Send + Sync + 'static {
        let flags = self.clone();
        move |map| flags.over(LocalizeOptions::for_map(map))
    }

    /// `--ratio` and `--top-k` checked by the library's rules ([`LocalizeOptions::validate`],
    /// the words Python and C get) before any map, catalog place or query is opened: a value
    /// out of range is a usage error naming the flag (exit status 2), as clap's parsers give,
    /// for one map, a catalog (whose places are opened only as queries reach them) and a log
    /// alike. The map's own defaults are in range, so the default options stand in for them.
    pub fn check(&self) -> Result<(), clap::Error> {
        self.over(LocalizeOptions::default())
            .validate()
            .map_err(|e| {
                let flag = format!("--{}", e.option.replace('_', "-"));
                clap::Error::raw(
                    clap::error::ErrorKind::ValueValidation,
                    format!("invalid value '{}' for '{flag}': {}\n", e.value, e.expected),
                )
            })
    }
}

/// The session over `map` (`--map`) with the options `args` give and `source`; a sequence
/// with `--sequence`. `not_extractable` says what to do instead when the map's queries
/// cannot be extracted (a SIFT map).
fn session(
    args: &Args,
    map: Arc<Map<'static>>,
    source: QuerySource,
    sequence: bool,
    not_extractable: &str,
    bars: &super::Bars,
) -> anyhow::Result<Session> {
    let options = args.matching.options()(&map);
    let builder = Session::builder(map, args.map_path().display().to_string())
        .options(options)
        .source(source)
        .sequence(sequence);
    #[cfg(feature = "hdf5")]
    let builder = builder.global_features(args.global_features.clone());
    let session = builder
        .build(bars)
        .map_err(|e| with_hint(e, not_extractable))?;
    warn_skipped(&session.skipped_levels(), args.map_path(), bars);
    Ok(session)
}

/// A session error, with `not_extractable` (what to pass instead) after a map whose queries
/// cannot be extracted.
fn with_hint(e: SessionError, not_extractable: &str) -> anyhow::Error {
    match e {
        SessionError::NotExtractable { .. } => anyhow::anyhow!("{e}; {not_extractable}"),
        e => e.into(),
    }
}

/// Warns about the selected levels the localizer does not match (one line for all).
fn warn_skipped(skipped: &[SkippedLevel], map: &Path, reporter: &dyn Reporter) {
    if !skipped.is_empty() {
        reporter.warn(&format!(
            "{}: {} level(s) not matched: {}",
            sfpmap::escape::path(map),
            skipped.len(),
            describe_skipped(skipped)
        ));
    }
}

/// `--images` must be a folder, checked before any work.
fn check_images_dir(dir: &Path) -> anyhow::Result<()> {
    match std::fs::metadata(dir) {
        Ok(m) if m.is_dir() => Ok(()),
        Ok(_) => bail!("{}: --images is not a folder", sfpmap::escape::path(dir)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!("{}: no such folder (--images)", sfpmap::escape::path(dir))
        }
        Err(e) => bail!("{}: {e}", sfpmap::escape::path(dir)),
    }
}

/// Where the queries' features come from: `--features`, `--database`, else the images of
/// `--images` (extracted with `--model` or the map's own).
fn query_source(args: &Args, queries: &[Query], query_list: &Path) -> anyhow::Result<QuerySource> {
    #[cfg(feature = "hdf5")]
    if let Some(path) = &args.features {
        return Ok(QuerySource::FeaturesFile(path.clone()));
    }
    #[cfg(not(feature = "hdf5"))]
    if let Some(path) = &args.features {
        bail!(
            "{}: reading features.h5 needs the hdf5 feature",
            sfpmap::escape::path(path)
        );
    }
    if let Some(db) = &args.database {
        return Ok(QuerySource::Database(db.clone()));
    }
    #[cfg(feature = "onnx")]
    {
        let Some(images) = args.images.clone() else {
            // A SIFT map's refusal names what to pass instead, before --images is asked for.
            return Ok(QuerySource::Images {
                folder: None,
                model: args.model.clone(),
            });
        };
        // A list naming none of the folder's images is a mistake, not N failed queries.
        // `exists`, not `is_file`: a FIFO or folder there is reported as what it is, later.
        let inside = |q: &Query| sfpmap::input::join_inside(&images, &q.name).ok();
        if !queries.iter().filter_map(inside).any(|p| p.exists()) {
            bail!(
                "{}: none of the {} images {} names is in this folder (first: {:?})",
                sfpmap::escape::path(&images),
                queries.len(),
                sfpmap::escape::path(query_list),
                queries[0].name
            );
        }
        Ok(QuerySource::Images {
            folder: Some(images),
            model: args.model.clone(),
        })
    }
    #[cfg(not(feature = "onnx"))]
    {
        let _ = (queries, query_list);
        bail!("query features from images need the extractor (feature onnx): pass --database")
    }
}

pub fn run(mut args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    // Before any thread starts (a remote map's runtime, the workers): the extractor's runtime
    // reads its settings from the environment.
    #[cfg(feature = "onnx")]
    sfpmap::extract::runtime::disable_telemetry();
    if let Err(e) = args.matching.check() {
        e.print()?;
        return Ok(ExitCode::from(2));
    }
    let bars = super::Bars::new(quiet, args.json);
    args.threads = super::cap_threads(args.threads, &bars);
    #[cfg(feature = "mcap")]
    if args.mcap.mcap.is_some() {
        return mcap_input::run(&args, quiet, &bars);
    }
    let Some(query_list) = args.query_list.clone() else {
        bail!("--query-list is required (or --mcap)");
    };
    if let Some(catalog) = args.catalog.clone() {
        return catalog_input::run(&args, &catalog, &query_list, quiet, &bars);
    }
    if let Some(dir) = &args.images {
        check_images_dir(dir)?;
    }
    let start = Instant::now();
    let queries = read_queries(&args, &query_list)?;
    let source = query_source(&args, &queries, &query_list)?;
    let (session, map_ms) = open_session(&args, source, &query_list, &bars)?;
    let results = session.localize_all(&queries, args.threads, &bars)?;
    // Queries that merely fail to localize are listed in the output; a run that could read no
    // query at all is an error.
    if results.iter().all(unread_query) {
        return Err(none_read(&query_list, &queries, &results));
    }
    let map = session.map();
    // Names of the retrieved images, for `--format json`.
    let image_names: Vec<&str> = match (args.format, map.images()?) {
        (PoseFormat::Json, Some(images)) => (0..images.len())
            .map(|i| images.name(i))
            .collect::<Result<_, _>>()?,
        _ => Vec::new(),
    };
    write_poses(
        &args.output,
        args.format,
        &query_list,
        &queries,
        &results,
        &image_names,
    )?;
    let run = Finished {
        session: &session,
        queries: &queries,
        results: &results,
        start,
        map_ms,
    };
    if args.json {
        run.print_json(&args)?;
    } else if !quiet {
        run.print(&args, quiet);
    }
    let unread = results.iter().filter(|r| unread_query(r)).count();
    Ok(exit_status(&args.output, unread, results.len(), &bars))
}

/// The queries of `query_list` (with `--camera` for all, if given), checked before any work:
/// their names against `--format`, the outputs against the inputs.
fn read_queries(args: &Args, query_list: &Path) -> anyhow::Result<Vec<Query>> {
    let camera = args
        .camera
        .as_deref()
        .map(Camera::parse)
        .transpose()
        .context("--camera")?;
    let queries = read_query_list(query_list, camera.as_ref())?;
    check_pose_names(query_list, args.format, &queries)?;
    let images: Vec<PathBuf> = match &args.images {
        Some(dir) => queries
            .iter()
            .filter_map(|q| sfpmap::input::join_inside(dir, &q.name).ok())
            .collect(),
        None => Vec::new(),
    };
    check_outputs(args, &[query_list], &images)?;
    Ok(queries)
}

/// The map opened and the session over it, with the times they took for `--json`'s
/// `map_ms`: all a remote map's reads (with the first query's time, when its first pose is
/// ready).
fn open_session(
    args: &Args,
    source: QuerySource,
    query_list: &Path,
    bars: &super::Bars,
) -> anyhow::Result<(Session, serde_json::Value)> {
    let opening = Instant::now();
    let map = Arc::new(super::open_map(args.map_path())?);
    let open_ms = opening.elapsed().as_secs_f64() * 1e3;
    let indexing = Instant::now();
    // Without the extractor `query_source` has refused a run without --database already.
    #[cfg(feature = "onnx")]
    let images_missing = matches!(&source, QuerySource::Images { folder: None, .. });
    #[cfg(not(feature = "onnx"))]
    let images_missing = false;
    // Refused before the session is built: that loads the model and reads the map's levels
    // (all of them, for a URL).
    if images_missing {
        let name = args.map_path().display().to_string();
        sfpmap::session::check_extractable(&map, &name).map_err(|e| with_hint(e, SIFT_HINT))?;
        bail!(
            "{}: pass the query images with --images DIR (features are extracted with the SFP model)",
            sfpmap::escape::path(query_list)
        );
    }
    let session = session(args, map, source, args.sequence, SIFT_HINT, bars)?;
    let localizer_ms = indexing.elapsed().as_secs_f64() * 1e3;
    Ok((
        session,
        json!({ "open": open_ms, "localizer": localizer_ms }),
    ))
}

/// A query-list run that wrote its poses, for its summary.
struct Finished<'a> {
    session: &'a Session,
    queries: &'a [Query],
    results: &'a [Localization],
    start: Instant,
    map_ms: serde_json::Value,
}

impl Finished<'_> {
    /// The queries that were not localized, with why.
    fn failed(&self) -> Vec<serde_json::Value> {
        self.queries
            .iter()
            .zip(self.results)
            .filter_map(|(q, r)| {
                Some(json!({ "name": q.name, "reason": r.failure()?.to_string() }))
            })
            .collect()
    }

    fn localized(&self) -> usize {
        self.results.iter().filter(|r| r.pose().is_some()).count()
    }

    fn paths(&self) -> PathCounts {
        PathCounts::of(self.results.iter().filter(|r| !unread_query(r)))
    }

    /// `--json`: counts, paths, per-stage median times, what the map cost.
    fn print_json(&self, args: &Args) -> anyhow::Result<()> {
        let (results, map) = (self.results, self.session.map());
        let paths = self.paths();
        let inliers = results.iter().filter(|r| r.pose().is_some());
        super::print_json(&json!({
            "queries": self.queries.len(),
            "localized": self.localized(),
            "failed": self.failed(),
            "path": paths.path,
            "tracking_lost": paths.tracking_lost,
            "retrieval": paths.retrieval,
            "retrieval_fallback": paths.retrieval_fallback,
            // Sequence frames with a pose prior, extracted without the global descriptor
            "global_skipped": self.session.global_deferred(),
            "output": args.output.display().to_string(),
            "seconds": self.start.elapsed().as_secs_f64(),
            "median_ms": median_ms(results),
            "median_inliers": median(inliers.map(|r| r.inliers as f64).collect()),
            // Lowe's ratio used: --ratio, else the map's (LocalizeOptions::for_map)
            "ratio": shortest_f64(self.session.options().matching.ratio),
            "transfer": super::transfer_json(map),
            "map_ms": self.map_ms,
        }))
    }

    /// The lines a person reads: counts, the median time, fallbacks and failures.
    fn print(&self, args: &Args, quiet: bool) {
        super::report_transfer(self.session.map(), quiet);
        let total = self.queries.len();
        println!(
            "{}: {}/{total} localized, median {:.1} ms per query (after features)",
            sfpmap::escape::path(&args.output),
            self.localized(),
            median(self.results.iter().map(|r| r.times.total_ms).collect()).unwrap_or(f64::NAN)
        );
        print_paths(&self.paths(), total);
        for f in &self.failed() {
            // JSON escapes C0 controls but not DEL or C1 ones: escape them all for the terminal.
            println!(
                "failed: {} ({})",
                escape_control_characters(&f["name"].to_string()),
                escape_control_characters(&f["reason"].to_string())
            );
        }
    }
}

/// The lines a person reads of how queries were localized: fallbacks and lost tracking,
/// with counts of `total`.
fn print_paths(paths: &PathCounts, total: usize) {
    for (why, n) in &paths.retrieval_fallback {
        println!(
            "retrieval not used for {n} of {total} queries: {why}; every point was a candidate"
        );
    }
    for (why, n) in &paths.tracking_lost {
        println!("tracking lost for {n} of {total} queries: {why}; retrieval was used");
    }
}

/// The exit status of a run that skipped what it could not read and did the rest: damaged
/// parts of an MCAP log, queries of a list whose features could not be read (missing, an image
/// that does not decode, a features file's or database's entry that is malformed or does not
/// fit the map). 1 is an error, 2 a usage error.
pub const SKIPPED_EXIT: u8 = 3;

/// The exit status of a query-list run that wrote its poses: [`SKIPPED_EXIT`] when some
/// queries could not be read (each is a `# failed NAME: reason` line of the output), with one
/// warning saying how many.
fn exit_status(output: &Path, unread: usize, total: usize, reporter: &dyn Reporter) -> ExitCode {
    if unread == 0 {
        return ExitCode::SUCCESS;
    }
    reporter.warn(&format!(
        "{}: {unread} of {} queries could not be read (exit status {SKIPPED_EXIT}); each is a \
         \"# failed\" line there",
        sfpmap::escape::path(output),
        total
    ));
    ExitCode::from(SKIPPED_EXIT)
}

/// What to do instead when a query-list run meets a SIFT map without `--database`.
const SIFT_HINT: &str = "pass the queries' features with --database queries.db";

/// Whether `r` is a query whose features could not be read.
fn unread_query(r: &Localization) -> bool {
    matches!(r.failure(), Some(QueryFailure::NoFeatures(_)))
}

/// The error of a run that could read no query's features, naming the first one's reason.
fn none_read(query_list: &Path, queries: &[Query], results: &[Localization]) -> anyhow::Error {
    anyhow::anyhow!(
        "{}: none of the {} queries could be read ({}: {})",
        sfpmap::escape::path(query_list),
        queries.len(),
        // From the list as it is: escaped for the terminal.
        quoted_name(&queries[0].name),
        results[0].failure_line()
    )
}

/// The output policy for `-o` (and the MCAP mode's `--tum`): none may be the map, the query
/// list or MCAP log, `--database`, `--features`, `--model` or one of `query_inputs`.
fn check_outputs(args: &Args, query_inputs: &[&Path], images: &[PathBuf]) -> anyhow::Result<()> {
    let files = output_files(args);
    #[cfg_attr(not(feature = "mcap"), allow(unused_mut))]
    let mut outputs: Vec<&Path> = files.iter().map(PathBuf::as_path).collect();
    #[cfg(feature = "mcap")]
    outputs.extend(args.mcap.tum.as_deref());
    let mut inputs = vec![args.map_path()];
    inputs.extend(query_inputs);
    inputs.extend(args.database.as_deref());
    inputs.extend(args.features.as_deref());
    #[cfg(feature = "hdf5")]
    inputs.extend(args.global_features.as_deref());
    inputs.extend(args.model.as_deref());
    inputs.extend(images.iter().map(|p| p.as_path()));
    // Nothing new among the query images either.
    let folders: Vec<&Path> = args.images.iter().map(PathBuf::as_path).collect();
    for out in &outputs {
        sfpmap::output::check_outside(out, &folders)?;
    }
    super::check_outputs(&outputs, &inputs, args.force)
}

/// Refuses, for `--format colmap` and `--format kapture`, a query name their rows cannot
/// hold, by the rules of the COLMAP exporters ([`text_name_problem`]) and of kapture's tables
/// (`io::kapture::name_problem`): rows start with the name or split at commas and have no
/// escape syntax, so a control character or comma would corrupt or inject a row. Checked
/// before any work. TUM rows hold no names (its comments escape them) and JSON escapes them.
fn check_pose_names(
    query_list: &Path,
    format: PoseFormat,
    queries: &[Query],
) -> anyhow::Result<()> {
    if format == PoseFormat::Kapture {
        for (i, q) in queries.iter().enumerate() {
            if let Some(problem) = sfpmap::io::kapture::name_problem(&q.name) {
                bail!(
                    "{}: query {} {} {problem}, which --format kapture cannot hold (--format json keeps any name)",
                    sfpmap::escape::path(query_list),
                    i + 1,
                    quoted_name(&q.name)
                );
            }
        }
    }
    if format != PoseFormat::Colmap {
        return Ok(());
    }
    for (i, q) in queries.iter().enumerate() {
        if let Some(problem) = text_name_problem(&q.name) {
            bail!(
                "{}: query {} {} {problem}, which --format colmap cannot hold (--format json keeps any name)",
                sfpmap::escape::path(query_list),
                i + 1,
                quoted_name(&q.name)
            );
        }
    }
    Ok(())
}

/// Writes all results through [`super::write_atomic`] ([`write_query_poses`]); `query_list`
/// names refused names.
pub(super) fn write_poses(
    path: &Path,
    format: PoseFormat,
    query_list: &Path,
    queries: &[Query],
    results: &[Localization],
    image_names: &[&str],
) -> anyhow::Result<()> {
    check_pose_names(query_list, format, queries)?;
    let Some(lines) = format.lines() else {
        let named: Vec<_> = queries
            .iter()
            .map(|q| (q.name.as_str(), &q.camera))
            .collect();
        // No inputs and `force`: the caller applied the output policy to the folder's files
        // (`output_files`), with every input, before any query ran.
        sfpmap::io::kapture::write_query_trajectories(path, &named, results, &[], true)?;
        return Ok(());
    };
    let names: Vec<&str> = queries.iter().map(|q| q.name.as_str()).collect();
    super::write_atomic(path, |out| {
        Ok(write_query_poses(out, lines, &names, results, image_names)?)
    })
}
