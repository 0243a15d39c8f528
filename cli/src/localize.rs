//! `sfpmap localize`: camera poses of query images in a map.

use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::colmap::text::{escape_control_characters, quoted_name, text_name_problem};
use sfpmap::format::Map;
use sfpmap::geometry::Camera;
use sfpmap::io::poses::{colmap_pose_line, tum_line};
use sfpmap::io::queries::{read_query_list, DatabaseFeatures, Query};
use sfpmap::localize::eval::median;
use sfpmap::localize::{
    describe_skipped, Localization, LocalizeOptions, Localizer, MatchOptions, MotionModel,
    QueryFailure, QueryFeatures, RetrievalMethod,
};
use sfpmap::progress::Reporter;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
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
}

/// Localize query images in a map: retrieval, coarse matching on the deepest level, P3P
/// LO-RANSAC, gated matching level by level, refinement.
///
/// Query intrinsics come from the query list (`name MODEL W H params...`, hloc style) or one
/// `--camera` for all. Query features: for SFP maps extracted from the images in --images
/// with the map's model (embedded by default); for SIFT maps from a COLMAP database holding
/// the queries' keypoints and descriptors (`--database queries.db`). Failed queries are written
/// as `# failed NAME: reason` lines. Example:
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
    /// point ("x,y,z").
    #[arg(long, requires = "catalog", value_name = "X,Y,Z")]
    pub prior: Option<String>,
    /// With --prior: how far from a place's bounding box the prior may be (map units).
    #[arg(long, default_value_t = 50.0, requires = "prior")]
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
    /// COLMAP database with the queries' SIFT keypoints and descriptors (SIFT maps).
    #[arg(long)]
    pub database: Option<PathBuf>,
    /// hloc-style features.h5 with the queries' features (e.g. from `sfpmap extract`).
    #[arg(long, conflicts_with = "database")]
    pub features: Option<PathBuf>,
    /// SFP model for query extraction: a file, or a built-in model's name (sfp-v2, sfp-v1, sfp-v2s);
    /// default: the built-in model the map was made with (another model runs as asked, with a
    /// warning).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Levels to use (repeat); default all. Coarse matching uses the deepest.
    #[arg(long = "level")]
    pub levels: Vec<u16>,
    /// Match with the short descriptor block only.
    #[arg(long)]
    pub short: bool,
    /// Database images retrieved per query (maps with global descriptors or VLAD).
    #[arg(long, default_value_t = sfpmap::format::DEFAULT_RETRIEVAL_TOP_K)]
    pub top_k: usize,
    /// What ranks the database images: the map's stated preference (auto), its VLAD of local
    /// descriptors, the extractor's global descriptor, or nothing (every point a candidate).
    #[arg(long, value_enum, default_value = "auto")]
    pub retrieval: RetrievalArg,
    /// Lowe ratio for coarse matching (default: 0.95 on SFP maps, 0.9 on SIFT maps).
    #[arg(long)]
    pub ratio: Option<f32>,
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

/// The descriptor kind of the map's levels (`""` for a map without descriptors).
fn descriptor_kind(map: &Map<'_>) -> String {
    map.metadata()
        .levels
        .first()
        .map(|l| l.descriptor.clone())
        .unwrap_or_default()
}

/// An f32 as the f64 of its shortest decimal form (0.95, not 0.949999988079071).
fn shortest_f64(v: f32) -> f64 {
    v.to_string().parse().unwrap_or(f64::from(v))
}

/// The XXH3 of the model the map's descriptors came from, as its provenance records it.
#[cfg(feature = "onnx")]
fn map_model_xxh3<'a>(map: &'a Map<'_>) -> Option<&'a str> {
    map.metadata()
        .provenance
        .model
        .as_ref()
        .map(|m| m.xxh3.as_str())
        .filter(|h| !h.is_empty())
}

/// Refuses a map whose query features the SFP extractor cannot provide: one without
/// descriptors, or a SIFT map (`sift_hint` says what to do instead).
fn check_extractable(map_path: &Path, descriptor: &str, sift_hint: &str) -> anyhow::Result<()> {
    match descriptor {
        "" => bail!(
            "{}: the map has no descriptors (geometry only)",
            map_path.display()
        ),
        "sift" => bail!("{}: a SIFT map; {sift_hint}", map_path.display()),
        _ => Ok(()),
    }
}

/// Refuses query features of another model than the map's: another `sfp.model_name`, or the
/// same name with another `sfp.model_xxh3` where the file and the map both record one (a
/// re-export). An hloc file without these attributes is taken as it is.
#[cfg(feature = "onnx")]
fn check_h5_model(
    h5: &sfpmap::io::features_h5::H5Features,
    h5_path: &Path,
    map_path: &Path,
    descriptor: &str,
    map_hash: Option<&str>,
) -> anyhow::Result<()> {
    if !sfpmap::localize::is_sfp_descriptor(descriptor) {
        return Ok(());
    }
    if let Some(made) = h5.root_string("sfp.model_name")? {
        if made != descriptor {
            bail!(
                "{}: features of model {made:?}, but the map {} holds {descriptor:?} \
                 descriptors: extract the queries with --model {descriptor}",
                h5_path.display(),
                map_path.display()
            );
        }
    }
    if let (Some(hash), Some(map_hash)) = (h5.root_string("sfp.model_xxh3")?, map_hash) {
        if hash != map_hash {
            bail!(
                "{}: features of a {descriptor:?} model of hash {hash}, but the map {} was \
                 made with one of hash {map_hash}: extract the queries with that model",
                h5_path.display(),
                map_path.display()
            );
        }
    }
    Ok(())
}

/// Warns when the file's global descriptors were computed at another image size than the
/// map's (`sfp.global_max_side` against metadata `global_max_side`): retrieval by them then
/// compares unlike descriptors. An `sfpmap extract` file without the attribute (written before
/// it) computed them at the image's own size; an hloc file (no `sfp.model_name`) is taken as
/// it is, and so is any file for a map without global descriptors.
#[cfg(feature = "onnx")]
fn warn_h5_global_size(
    h5: &sfpmap::io::features_h5::H5Features,
    h5_path: &Path,
    map: &Map<'_>,
    bars: &super::Bars,
) -> anyhow::Result<()> {
    if !matches!(map.image_global(), Ok(Some(_))) {
        return Ok(());
    }
    let map_size = sfpmap::extract::GlobalSize::of_map(map.metadata());
    // Only a warning hangs on it: an attribute that is not one string is named, not fatal.
    let stated = match h5.root_string("sfp.global_max_side") {
        Ok(Some(side)) => side,
        Ok(None) if matches!(h5.root_string("sfp.model_name"), Ok(Some(_))) => "0".to_string(),
        Ok(None) => return Ok(()),
        Err(_) => "(not one string)".to_string(),
    };
    let file_size = stated
        .trim()
        .parse::<u32>()
        .ok()
        .map(|side| sfpmap::extract::GlobalSize::from_max_side(Some(side)));
    if file_size != Some(map_size) {
        let mut shown: String = stated.chars().take(24).collect();
        if shown.len() < stated.len() {
            shown.push('…');
        }
        let map_side = map_size.side();
        bars.warn(&format!(
            "{}: global descriptors computed at max side {shown:?}, the map's at \"{map_side}\" \
             (0: the image's own size): retrieval by them will be poorer; extract with \
             --global-max-side {map_side}",
            h5_path.display()
        ));
    }
    Ok(())
}

/// The size the queries' global descriptors are extracted at: the map's (`global_max_side`),
/// or none where retrieval will not rank by them (the map stores none, or `--retrieval vlad`
/// or `off`).
#[cfg(feature = "onnx")]
fn query_global_size(args: &Args, map: &Map<'_>) -> sfpmap::extract::GlobalSize {
    let ranks_by_global = matches!(args.retrieval, RetrievalArg::Auto | RetrievalArg::Global)
        && matches!(map.image_global(), Ok(Some(_)));
    if ranks_by_global {
        sfpmap::extract::GlobalSize::of_map(map.metadata())
    } else {
        sfpmap::extract::GlobalSize::Skip
    }
}

/// The SFP extractor (`--model`, else the embedded one), checked against the map's descriptors.
#[cfg(feature = "onnx")]
fn sfp_extractor(
    args: &Args,
    descriptor: &str,
    map_model_xxh3: Option<&str>,
    bars: &super::Bars,
) -> anyhow::Result<sfpmap::extract::Extractor> {
    let extractor = match &args.model {
        Some(m) => {
            let options = sfpmap::extract::ExtractorOptions {
                model: Some(m.clone()),
                threads: 2,
            };
            sfpmap::extract::Extractor::new(&options, bars)?
        }
        // Without --model, the built-in model the map was made with (never a file).
        None => match sfpmap::extract::Extractor::builtin(descriptor, 2, bars) {
            Some(extractor) => extractor?,
            None => bail!(
                "{}: the map's descriptors are {descriptor:?}, which no built-in model makes \
                 (built in: {}): pass its model with --model FILE.onnx",
                args.map_path().display(),
                sfpmap::extract::builtin_model_names()
            ),
        },
    };
    // A built-in model (by default, or `--model NAME`) of the map's name but other weights
    // than the map's (a retrained model exported under the same name): the map's descriptors
    // would not match the queries'. An explicit file is the user's choice.
    let builtin = extractor.model().name.ends_with("(embedded)");
    if let (true, Some(made)) = (builtin, map_model_xxh3) {
        if made != extractor.model().xxh3 && extractor.contract().model_name == descriptor {
            bail!(
                "{}: the map was made with a {descriptor:?} model of hash {made}, not the \
                 built-in one ({}): pass that model with --model FILE.onnx",
                args.map_path().display(),
                extractor.model().xxh3
            );
        }
    }
    // Only `--model` can name another model (without it, the map's own runs): that is asked
    // for on purpose (e.g. a faster student of the map's model), so it runs, said once.
    if extractor.contract().model_name != descriptor {
        bars.warn(&format!(
            "{}: the map's descriptors are {descriptor:?} but --model is {:?}: localizing \
             with another model's descriptors, as asked",
            args.map_path().display(),
            extractor.contract().model_name
        ));
    }
    Ok(extractor)
}

/// The localizer with the options of `--level`, `--short`, `--top-k` and `--ratio`.
/// The localizer of `map` (named `name` in errors) with the options `args` give.
fn localizer<'m>(map: &'m Map<'m>, args: &Args, name: &Path) -> anyhow::Result<Localizer<'m>> {
    let base = LocalizeOptions::for_map(map);
    if let Some(r) = args.ratio.filter(|r| !(*r > 0.0 && *r <= 1.0)) {
        bail!("--ratio {r}: a ratio in (0, 1]");
    }
    let options = LocalizeOptions {
        levels: args.levels.clone(),
        short: args.short,
        top_k: args.top_k,
        retrieval: match args.retrieval {
            RetrievalArg::Auto => RetrievalMethod::Auto,
            RetrievalArg::Vlad => RetrievalMethod::Vlad,
            RetrievalArg::Global => RetrievalMethod::Global,
            RetrievalArg::Off => RetrievalMethod::Off,
        },
        matching: MatchOptions {
            ratio: args.ratio.unwrap_or(base.matching.ratio),
            ..base.matching
        },
        ..base
    };
    Localizer::new(map, options).with_context(|| name.display().to_string())
}

/// Warns about the selected levels the localizer does not match (one line for all).
fn warn_skipped(localizer: &Localizer<'_>, map: &Path, reporter: &dyn Reporter) {
    let skipped = localizer.skipped_levels();
    if !skipped.is_empty() {
        reporter.warn(&format!(
            "{}: {} level(s) not matched: {}",
            map.display(),
            skipped.len(),
            describe_skipped(skipped)
        ));
    }
}

/// `--images` must be a folder, checked before any work.
fn check_images_dir(dir: &Path) -> anyhow::Result<()> {
    match std::fs::metadata(dir) {
        Ok(m) if m.is_dir() => Ok(()),
        Ok(_) => bail!("{}: --images is not a folder", dir.display()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            bail!("{}: no such folder (--images)", dir.display())
        }
        Err(e) => bail!("{}: {e}", dir.display()),
    }
}

pub fn run(mut args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
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
    let camera = args
        .camera
        .as_deref()
        .map(Camera::parse)
        .transpose()
        .context("--camera")?;
    let queries = read_query_list(&query_list, camera.as_ref())?;
    check_pose_names(&query_list, args.format, &queries)?;
    let images: Vec<PathBuf> = match &args.images {
        Some(dir) => queries.iter().map(|q| dir.join(&q.name)).collect(),
        None => Vec::new(),
    };
    check_outputs(&args, &[&query_list], &images)?;
    let opening = Instant::now();
    let map = super::open_map(args.map_path())?;
    let open_ms = opening.elapsed().as_secs_f64() * 1e3;
    let descriptor = descriptor_kind(&map);
    #[cfg(feature = "onnx")]
    let from_h5 = match &args.features {
        Some(path) => {
            let h5 = sfpmap::io::features_h5::H5Features::open(path)?;
            check_h5_model(
                &h5,
                path,
                args.map_path(),
                &descriptor,
                map_model_xxh3(&map),
            )?;
            warn_h5_global_size(&h5, path, &map, &bars)?;
            Some(h5)
        }
        None => None,
    };
    #[cfg(not(feature = "onnx"))]
    if let Some(path) = &args.features {
        bail!(
            "{}: reading features.h5 needs the onnx feature",
            path.display()
        );
    }
    let features = match (&args.database, descriptor.as_str()) {
        #[cfg(feature = "onnx")]
        _ if from_h5.is_some() => Source::H5(from_h5.expect("checked")),
        (Some(db), _) => {
            Source::Database(DatabaseFeatures::open(db).with_context(|| db.display().to_string())?)
        }
        #[cfg(feature = "onnx")]
        (None, _) => {
            check_extractable(args.map_path(), &descriptor, SIFT_HINT)?;
            let Some(images) = args.images.clone() else {
                bail!("{}: pass the query images with --images DIR (features are extracted with the SFP model)", query_list.display());
            };
            // A list naming none of the folder's images is a mistake, not N failed queries.
            // `exists`, not `is_file`: a FIFO or folder there is reported as what it is, below.
            if !queries.iter().any(|q| images.join(&q.name).exists()) {
                bail!(
                    "{}: none of the {} images {} names is in this folder (first: {:?})",
                    images.display(),
                    queries.len(),
                    query_list.display(),
                    queries[0].name
                );
            }
            let extractor = sfp_extractor(&args, &descriptor, map_model_xxh3(&map), &bars)?;
            let global = query_global_size(&args, &map);
            Source::Extractor {
                extractor,
                images,
                global,
                skipped_global: 0,
                skipped: None,
            }
        }
        #[cfg(not(feature = "onnx"))]
        (None, other) => {
            check_extractable(args.map_path(), other, SIFT_HINT)?;
            bail!(
                "{}: query features for {other:?} maps need the extractor (feature onnx)",
                args.map_path().display()
            )
        }
    };
    let indexing = Instant::now();
    let localizer = localizer(&map, &args, args.map_path())?;
    // Opening the map and building the localizer: all a remote map's reads (with the
    // first query's time, when its first pose is ready).
    let map_ms = json!({ "open": open_ms, "localizer": indexing.elapsed().as_secs_f64() * 1e3 });
    warn_skipped(&localizer, args.map_path(), &bars);
    bars.start("localizing", Some(queries.len() as u64));
    // Each query's outcome, and whether its features could be read at all.
    let results: Vec<Mutex<Option<(Localization, bool)>>> =
        queries.iter().map(|_| Mutex::new(None)).collect();
    let next = AtomicUsize::new(0);
    let features = Mutex::new(features);
    // A sequence runs in order: one worker, which predicts each query from the last ones.
    let workers = if args.sequence { 1 } else { args.threads };
    let motion = Mutex::new(MotionModel::new());
    let first_error: Mutex<Option<anyhow::Error>> = Mutex::new(None);
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(q) = queries.get(i) else { break };
                // SQLite connections are not shared between threads: reads take turns.
                // Only a sequence (one worker) touches the motion model.
                let sequence = || motion.lock().unwrap_or_else(|p| p.into_inner());
                let tracked = args.sequence && sequence().predict().is_some();
                let f = features
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .features(&q.name, tracked);
                let outcome = match f {
                    Ok(Ok(f)) if args.sequence => sequence()
                        .localize_then_global(&localizer, &f, &q.camera, &mut || {
                            let mut source = features.lock().unwrap_or_else(|p| p.into_inner());
                            source.global_of(&q.name)
                        })
                        .with_context(|| {
                            format!("{}: query {:?}", args.map_path().display(), q.name)
                        })
                        .map(|l| (l, true)),
                    Ok(Ok(f)) => {
                        localize_one(&localizer, args.map_path(), q, &f).map(|l| (l, true))
                    }
                    Ok(Err(reason)) => {
                        if args.sequence {
                            sequence().update(None);
                        }
                        Ok((unread(reason), false))
                    }
                    Err(e) => Err(e),
                };
                match outcome {
                    Ok(l) => *results[i].lock().unwrap_or_else(|p| p.into_inner()) = Some(l),
                    Err(e) => {
                        first_error
                            .lock()
                            .unwrap_or_else(|p| p.into_inner())
                            .get_or_insert(e);
                    }
                }
                bars.advance(1);
            });
        }
    });
    bars.finish();
    if let Some(e) = first_error.into_inner().unwrap_or_else(|p| p.into_inner()) {
        return Err(e);
    }
    let global_skipped = features
        .into_inner()
        .unwrap_or_else(|p| p.into_inner())
        .skipped_global();
    let (results, read): (Vec<Localization>, Vec<bool>) = results
        .into_iter()
        .map(|m| {
            m.into_inner()
                .unwrap_or_else(|p| p.into_inner())
                .expect("every query ran")
        })
        .unzip();
    // Queries that merely fail to localize are listed in the output; a run that could read no
    // query at all is an error.
    if !read.contains(&true) {
        return Err(none_read(&query_list, &queries, &results));
    }
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
    let localized = results.iter().filter(|r| r.pose().is_some()).count();
    let failed: Vec<_> = queries
        .iter()
        .zip(&results)
        .filter_map(|(q, r)| Some(json!({ "name": q.name, "reason": r.failure()?.to_string() })))
        .collect();
    let paths = PathCounts::of(results.iter().filter(|&r| {
        !r.failure()
            .is_some_and(|f| matches!(f, QueryFailure::NoFeatures(_)))
    }));
    if args.json {
        super::print_json(&json!({
            "queries": queries.len(),
            "localized": localized,
            "failed": failed,
            "path": paths.path,
            "tracking_lost": paths.tracking_lost,
            "retrieval": paths.retrieval,
            "retrieval_fallback": paths.retrieval_fallback,
            // Sequence frames with a pose prior, extracted without the global descriptor
            "global_skipped": global_skipped,
            "output": args.output.display().to_string(),
            "seconds": start.elapsed().as_secs_f64(),
            "median_ms": median_ms(&results),
            "median_inliers": median(results.iter().filter(|r| r.pose().is_some()).map(|r| r.inliers as f64).collect()),
            // Lowe's ratio used: --ratio, else the map's (LocalizeOptions::for_map)
            "ratio": shortest_f64(localizer.options().matching.ratio),
            "transfer": super::transfer_json(&map),
            "map_ms": map_ms,
        }))?;
    } else if !quiet {
        super::report_transfer(&map, quiet);
        println!(
            "{}: {localized}/{} localized, median {:.1} ms per query (after features)",
            args.output.display(),
            queries.len(),
            median(results.iter().map(|r| r.times.total_ms).collect()).unwrap_or(f64::NAN)
        );
        paths.print(queries.len());
        for f in &failed {
            // JSON escapes C0 controls but not DEL or C1 ones: escape them all for the terminal.
            println!(
                "failed: {} ({})",
                escape_control_characters(&f["name"].to_string()),
                escape_control_characters(&f["reason"].to_string())
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// How the queries were localized, counted: the path (retrieval or tracking), why tracking
/// was lost, which stored descriptor ranked the images, and retrieval's fallbacks (queries
/// matched against every point), each reason with its count.
#[derive(Default)]
pub(super) struct PathCounts {
    pub path: BTreeMap<&'static str, usize>,
    pub tracking_lost: BTreeMap<String, usize>,
    pub retrieval: BTreeMap<&'static str, usize>,
    pub retrieval_fallback: BTreeMap<String, usize>,
}

impl PathCounts {
    pub(super) fn of<'a>(results: impl Iterator<Item = &'a Localization>) -> PathCounts {
        let mut counts = PathCounts::default();
        for r in results {
            *counts.path.entry(r.path.name()).or_default() += 1;
            if let Some(why) = r.tracking_lost {
                *counts.tracking_lost.entry(why.to_string()).or_default() += 1;
            }
            if let Some(method) = r.retrieval {
                *counts.retrieval.entry(method.name()).or_default() += 1;
            }
            if let Some(why) = r.retrieval_fallback {
                *counts
                    .retrieval_fallback
                    .entry(why.to_string())
                    .or_default() += 1;
            }
        }
        counts
    }

    /// The lines a person reads: fallbacks and lost tracking, with counts of `total`.
    pub(super) fn print(&self, total: usize) {
        for (why, n) in &self.retrieval_fallback {
            println!(
                "retrieval not used for {n} of {total} queries: {why}; every point was a candidate"
            );
        }
        for (why, n) in &self.tracking_lost {
            println!("tracking lost for {n} of {total} queries: {why}; retrieval was used");
        }
    }
}

/// What to do instead when a query-list run meets a SIFT map without `--database`.
const SIFT_HINT: &str = "pass the queries' features with --database queries.db";

/// Where query features come from.
enum Source {
    Database(DatabaseFeatures),
    #[cfg(feature = "onnx")]
    H5(sfpmap::io::features_h5::H5Features),
    #[cfg(feature = "onnx")]
    Extractor {
        extractor: sfpmap::extract::Extractor,
        images: PathBuf,
        /// The map's (`GlobalSize::of_map`).
        global: sfpmap::extract::GlobalSize,
        /// Tracked frames extracted without it (`--json`'s `global_skipped`).
        skipped_global: usize,
        /// The last such frame's name and input, for [`Source::global_of`] if it loses
        /// tracking (no second read and decode).
        skipped: Option<Box<(String, sfpmap::extract::image::GrayInput)>>,
    },
}

impl Source {
    /// The global descriptor of query `name`, a tracked frame extracted without it that
    /// lost tracking (its input is kept until the next query); `None` when this source gives
    /// none, or the inference fails (the query then retrieves without it, which it reports).
    #[cfg_attr(not(feature = "onnx"), allow(unused_variables))]
    fn global_of(&mut self, name: &str) -> Option<Vec<f32>> {
        match self {
            #[cfg(feature = "onnx")]
            Source::Extractor {
                extractor,
                global,
                skipped,
                ..
            } => {
                let (skipped_name, input) = *skipped.take()?;
                if skipped_name != name {
                    return None;
                }
                extractor.global_of(&input, *global).ok()
            }
            _ => None,
        }
    }

    /// How many frames the extractor gave no global descriptor (tracked frames).
    fn skipped_global(&self) -> usize {
        match self {
            #[cfg(feature = "onnx")]
            Source::Extractor { skipped_global, .. } => *skipped_global,
            _ => 0,
        }
    }

    /// The query's features, or why they cannot be had for this query (missing, or an image
    /// that does not decode completely): a failed query, not an error. `tracked`: a sequence's
    /// frame with a pose prior, which does not retrieve, so the extractor skips the global
    /// descriptor's extra inference where it costs one (a frame that then loses tracking gets
    /// it from [`Source::global_of`]).
    #[cfg_attr(not(feature = "onnx"), allow(unused_variables))]
    fn features(
        &mut self,
        name: &str,
        tracked: bool,
    ) -> anyhow::Result<Result<QueryFeatures, String>> {
        let missing = |what: &str| Err(format!("no features for {name:?} ({what})"));
        match self {
            Source::Database(db) => Ok(db
                .features(name)?
                .map_or_else(|| missing("not in the database"), Ok)),
            #[cfg(feature = "onnx")]
            Source::H5(h5) => Ok(h5
                .features(name)?
                .map_or_else(|| missing("not in the features file"), Ok)),
            #[cfg(feature = "onnx")]
            Source::Extractor {
                extractor,
                images,
                global,
                skipped_global,
                skipped,
            } => {
                use sfpmap::extract::ExtractError;
                *skipped = None;
                let path = images.join(name);
                // A FIFO or folder goes on to `load`, whose regular-file rule names it.
                if !path.exists() {
                    return Ok(missing("no such image"));
                }
                let weights = extractor.contract().gray_weights;
                let input = match sfpmap::extract::image::load(&path, weights, None) {
                    Ok(input) => input,
                    Err(ExtractError::Image { source, .. }) => {
                        return Ok(Err(format!("the image does not decode: {source}")))
                    }
                    Err(ExtractError::Io { source, .. }) => {
                        return Ok(Err(format!("the image cannot be read: {source}")))
                    }
                    Err(e) => return Err(e.into()),
                };
                // One oversized query is a failed query, not an aborted run.
                if let Some(reason) =
                    sfpmap::extract::too_large_for_the_network(input.width, input.height)
                {
                    return Ok(Err(reason));
                }
                let size = global.for_frame(tracked, input.width, input.height);
                let skip = size != *global;
                *skipped_global += usize::from(skip);
                let options = sfpmap::extract::DetectOptions {
                    global: size,
                    ..Default::default()
                };
                let f = extractor
                    .extract(&input, &options)
                    .map_err(|e| e.on_image(&path))?;
                if skip {
                    *skipped = Some(Box::new((name.to_string(), input)));
                }
                Ok(Ok(sfpmap::io::queries::sfp_query(&f)))
            }
        }
    }
}

/// Localizes one query; an error (features that do not fit the map) names the map and query.
fn localize_one(
    localizer: &Localizer<'_>,
    map: &Path,
    q: &Query,
    f: &QueryFeatures,
) -> anyhow::Result<Localization> {
    localizer
        .localize(f, &q.camera)
        .with_context(|| format!("{}: query {:?}", map.display(), q.name))
}

/// The error of a run that could read no query's features, naming the first one's reason.
fn none_read(query_list: &Path, queries: &[Query], results: &[Localization]) -> anyhow::Error {
    anyhow::anyhow!(
        "{}: none of the {} queries could be read ({}: {})",
        query_list.display(),
        queries.len(),
        queries[0].name,
        failure(&results[0])
    )
}

/// The failed localization of a query whose features could not be read.
fn unread(reason: String) -> Localization {
    Localization::failed(QueryFailure::NoFeatures(reason))
}

/// The output policy for `-o` (and the MCAP mode's `--tum`): none may be the map, the query
/// list or MCAP log, `--database`, `--features`, `--model` or one of `query_inputs`.
fn check_outputs(args: &Args, query_inputs: &[&Path], images: &[PathBuf]) -> anyhow::Result<()> {
    #[cfg_attr(not(feature = "mcap"), allow(unused_mut))]
    let mut outputs = vec![args.output.as_path()];
    #[cfg(feature = "mcap")]
    outputs.extend(args.mcap.tum.as_deref());
    let mut inputs = vec![args.map_path()];
    inputs.extend(query_inputs);
    inputs.extend(args.database.as_deref());
    inputs.extend(args.features.as_deref());
    inputs.extend(args.model.as_deref());
    inputs.extend(images.iter().map(|p| p.as_path()));
    super::check_outputs(&outputs, &inputs, args.force)
}

/// Refuses, for `--format colmap`, a query name its rows cannot hold, by the rule of the
/// COLMAP exporters ([`text_name_problem`]): rows start with the name and have no escape
/// syntax, so a control character would corrupt or inject a row. Checked before any work.
/// TUM rows hold no names (its comments escape them) and JSON escapes them itself.
fn check_pose_names(
    query_list: &Path,
    format: PoseFormat,
    queries: &[Query],
) -> anyhow::Result<()> {
    if format != PoseFormat::Colmap {
        return Ok(());
    }
    for (i, q) in queries.iter().enumerate() {
        if let Some(problem) = text_name_problem(&q.name) {
            bail!(
                "{}: query {} {} {problem}, which --format colmap cannot hold (--format json keeps any name)",
                query_list.display(),
                i + 1,
                quoted_name(&q.name)
            );
        }
    }
    Ok(())
}

/// Writes all results through [`super::write_atomic`]; `query_list` names refused names.
pub(super) fn write_poses(
    path: &Path,
    format: PoseFormat,
    query_list: &Path,
    queries: &[Query],
    results: &[Localization],
    image_names: &[&str],
) -> anyhow::Result<()> {
    check_pose_names(query_list, format, queries)?;
    super::write_atomic(path, |out| {
        pose_text(out, format, queries, results, image_names)
    })
}

/// Why a query failed, on one line (a comment in the text formats).
fn failure(r: &Localization) -> String {
    let reason = r
        .failure()
        .map_or_else(|| "unknown".to_string(), |f| f.to_string());
    escape_control_characters(&reason).into_owned()
}

/// The results as `--format` says.
fn pose_text(
    out: &mut impl std::io::Write,
    format: PoseFormat,
    queries: &[Query],
    results: &[Localization],
    image_names: &[&str],
) -> anyhow::Result<()> {
    match format {
        PoseFormat::Colmap => {
            writeln!(out, "# name qw qx qy qz tx ty tz (COLMAP cam_from_world)")?;
            for (q, r) in queries.iter().zip(results) {
                match r.pose() {
                    Some(p) => writeln!(out, "{}", colmap_pose_line(&q.name, p))?,
                    None => writeln!(out, "# failed {}: {}", q.name, failure(r))?,
                }
            }
        }
        PoseFormat::Tum => {
            writeln!(out, "# index tx ty tz qx qy qz qw (TUM: world_from_cam); query names in order of the list")?;
            for (i, (q, r)) in queries.iter().zip(results).enumerate() {
                match r.pose() {
                    Some(p) => writeln!(out, "{}", tum_line(i, p))?,
                    None => writeln!(
                        out,
                        "# failed {i} {}: {}",
                        escape_control_characters(&q.name),
                        failure(r)
                    )?,
                }
            }
        }
        PoseFormat::Json => {
            let list: Vec<_> = queries
                .iter()
                .zip(results)
                .map(|(q, r)| {
                    json!({
                        "name": q.name,
                        "cam_from_world": r.pose().map(|p| p.to_colmap()),
                        "failure": r.failure().map(|f| f.to_string()),
                        "inliers": r.inliers,
                        "inliers_per_level": r.inliers_per_level,
                        "matches": r.matches,
                        "retrieved_images": r.retrieved_images,
                        "retrieved": r.retrieved.iter().filter_map(|&i| image_names.get(i)).collect::<Vec<_>>(),
                        "path": r.path.name(),
                        "tracking_lost": r.tracking_lost.map(|w| w.to_string()),
                        "retrieval": r.retrieval.map(|m| m.name()),
                        "retrieval_fallback": r.retrieval_fallback.map(|w| w.to_string()),
                        "ms": r.times.total_ms,
                    })
                })
                .collect();
            serde_json::to_writer_pretty(&mut *out, &list)?;
            writeln!(out)?;
        }
    }
    Ok(())
}
