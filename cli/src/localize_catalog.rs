//! `sfpmap localize --catalog city.sfpc`: each query's candidate places are ranked by
//! retrieval on the catalog's place summaries (`PlaceRanker`), optionally only those near
//! `--prior`; the best `--places` are opened (files, or URLs read by range: only the sections
//! the localizer reads) and localize the query; the pose with the most inliers wins. Poses
//! are in the chosen place's frame; `--json` says which place each query went to.

use super::{none_read, options, unread, warn_skipped, write_poses, Args};
use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::colmap::text::escape_control_characters;
use sfpmap::format::{Catalog, Map, Place};
use sfpmap::io::queries::{read_query_list, Query};
use sfpmap::localize::catalog::PlaceRanker;
use sfpmap::localize::Localization;
use sfpmap::progress::Reporter;
use sfpmap::session::{QueryReader, QuerySource, Session};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, OnceLock};

/// Where place `location` is: a URL as is; a path from the catalog's folder (absolute ones
/// as they are). A catalog read from a URL names no local file: its other locations are
/// resolved against its URL, so a downloaded catalog cannot make the reader open local files.
fn resolve(catalog: &Path, location: &str) -> anyhow::Result<PathBuf> {
    if sfpmap::remote::is_url(location) {
        return Ok(PathBuf::from(location));
    }
    if let Some(url) = catalog.to_str().filter(|c| sfpmap::remote::is_url(c)) {
        let joined = url::Url::parse(url)
            .and_then(|u| u.join(location))
            .with_context(|| format!("{}: place map {location:?}", catalog.display()))?;
        return Ok(PathBuf::from(joined.as_str()));
    }
    Ok(catalog.parent().unwrap_or(Path::new(".")).join(location))
}

fn parse_prior(text: &str) -> anyhow::Result<[f64; 3]> {
    let v: Vec<f64> = text
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--prior {text:?}: expected x,y,z"))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => bail!("--prior {text:?}: expected three finite numbers x,y,z"),
    }
}

/// A place map at `path` (its resolved location), opened on first use and checked against
/// what the catalog recorded.
fn open_place(catalog: &Path, place: &Place, path: &Path) -> anyhow::Result<Map<'static>> {
    let map = super::super::open_map(path)
        .with_context(|| format!("{}: place {:?}", catalog.display(), place.name))?;
    let found = format!("{:016x}", map.index_checksum());
    if found != place.index_checksum {
        bail!(
            "{}: place {:?}: {} is not the map the catalog was built from (index checksum {found}, catalog says {}); rebuild the catalog",
            catalog.display(),
            place.name,
            path.display(),
            place.index_checksum
        );
    }
    Ok(map)
}

pub(super) fn run(
    args: &Args,
    catalog_path: &Path,
    query_list: &Path,
    quiet: bool,
    bars: &super::super::Bars,
) -> anyhow::Result<ExitCode> {
    let start = std::time::Instant::now();
    let camera = args
        .camera
        .as_deref()
        .map(sfpmap::geometry::Camera::parse)
        .transpose()
        .context("--camera")?;
    let queries = read_query_list(query_list, camera.as_ref())?;
    let mut inputs = vec![catalog_path, query_list];
    inputs.extend(args.database.as_deref());
    inputs.extend(args.features.as_deref());
    let prior = args.prior.as_deref().map(parse_prior).transpose()?;
    let catalog_map = super::super::open_map(catalog_path)?;
    let catalog = Catalog::of(&catalog_map)
        .map_err(super::super::naming(catalog_path))?
        .with_context(|| {
            format!(
                "{}: not a catalog (its metadata lists no places)",
                catalog_path.display()
            )
        })?;
    // The place maps are inputs too: no output may replace one. Checked once, before any
    // query is read.
    let place_paths = catalog
        .places()
        .iter()
        .map(|p| resolve(catalog_path, &p.map))
        .collect::<anyhow::Result<Vec<_>>>()?;
    inputs.extend(place_paths.iter().map(PathBuf::as_path));
    super::super::check_outputs(&[&args.output], &inputs, args.force)?;
    let ranker = PlaceRanker::new(&catalog).map_err(super::super::naming(catalog_path))?;
    let source = match (&args.database, &args.features) {
        (Some(db), _) => QuerySource::Database(db.clone()),
        #[cfg(feature = "onnx")]
        (None, Some(h5)) => QuerySource::FeaturesFile(h5.clone()),
        _ => bail!("--catalog needs the queries' features: --database queries.db or --features features.h5"),
    };
    let catalog_name = catalog_path.display().to_string();
    let mut features =
        QueryReader::for_catalog(source, &catalog_name, &catalog.listing.descriptor, bars)?;
    let places = Places::new(args, catalog_path, catalog.places(), place_paths, bars);
    let near = |i: usize| prior.is_none_or(|p| places.places[i].near(p, args.radius));
    let found = localize_queries(&queries, &mut features, &ranker, &places, near, bars)?;
    if !found.read_any {
        return Err(none_read(query_list, &queries, &found.results));
    }
    write_poses(
        &args.output,
        args.format,
        query_list,
        &queries,
        &found.results,
        &[],
    )?;
    let summary = Summary {
        catalog_path,
        catalog_map: &catalog_map,
        queries: &queries,
        places: &places,
        found: &found,
    };
    if args.json {
        summary.print_json(args, start)?;
    } else if !quiet {
        summary.print(args);
    }
    Ok(ExitCode::SUCCESS)
}

/// The catalog's places and each one's session, made on first use: its map opened (only the
/// sections the localizer reads, for URLs) and checked against what the catalog recorded.
struct Places<'a> {
    args: &'a Args,
    catalog_path: &'a Path,
    places: &'a [Place],
    paths: Vec<PathBuf>,
    sessions: Vec<OnceLock<Result<Session, String>>>,
    bars: &'a super::super::Bars,
}

impl<'a> Places<'a> {
    fn new(
        args: &'a Args,
        catalog_path: &'a Path,
        places: &'a [Place],
        paths: Vec<PathBuf>,
        bars: &'a super::super::Bars,
    ) -> Places<'a> {
        Places {
            args,
            catalog_path,
            places,
            paths,
            sessions: places.iter().map(|_| OnceLock::new()).collect(),
            bars,
        }
    }

    /// Place `i`'s session.
    fn session(&self, i: usize) -> anyhow::Result<&Session> {
        self.sessions[i]
            .get_or_init(|| {
                let map = open_place(self.catalog_path, &self.places[i], &self.paths[i])
                    .map_err(|e| format!("{e:#}"))?;
                let options = options(&map, self.args);
                let path = &self.paths[i];
                let session = Session::builder(Arc::new(map), path.display().to_string())
                    .options(options)
                    .build(self.bars)
                    .map_err(|e| e.to_string())?;
                warn_skipped(&session.skipped_levels(), path, self.bars);
                Ok(session)
            })
            .as_ref()
            .map_err(|e| anyhow::anyhow!("{e}"))
    }
}

/// Each query's result, the place it went to and how the places ranked for it.
struct Found {
    results: Vec<Localization>,
    chosen: Vec<Option<usize>>,
    rankings: Vec<serde_json::Value>,
    /// Whether any query's features could be read.
    read_any: bool,
}

/// Each query localized in the best `--places` of those `near` allows, ranked for it; the
/// pose with the most inliers wins.
fn localize_queries(
    queries: &[Query],
    features: &mut QueryReader,
    ranker: &PlaceRanker,
    places: &Places<'_>,
    near: impl Fn(usize) -> bool,
    bars: &super::super::Bars,
) -> anyhow::Result<Found> {
    bars.start("localizing", Some(queries.len() as u64));
    let mut found = Found {
        results: Vec::with_capacity(queries.len()),
        chosen: Vec::with_capacity(queries.len()),
        rankings: Vec::with_capacity(queries.len()),
        read_any: false,
    };
    for q in queries {
        let f = match features.read(&q.name)? {
            Ok(f) => f,
            Err(reason) => {
                found.results.push(unread(reason));
                found.chosen.push(None);
                found.rankings.push(json!([]));
                bars.advance(1);
                continue;
            }
        };
        found.read_any = true;
        let ranked = ranker.rank(&f, &near);
        found.rankings.push(json!(ranked
            .iter()
            .map(|r| json!({
                "place": places.places[r.place].name,
                "score": r.score,
            }))
            .collect::<Vec<_>>()));
        let mut best: Option<(Localization, usize)> = None;
        for candidate in ranked.iter().take(places.args.places) {
            let l = places
                .session(candidate.place)?
                .localize_features(&f, &q.camera, &q.name)
                .with_context(|| format!("place {:?}", places.places[candidate.place].name))?;
            let better = match &best {
                None => true,
                Some((b, _)) => l.pose().is_some() && (b.pose().is_none() || l.inliers > b.inliers),
            };
            if better {
                best = Some((l, candidate.place));
            }
        }
        match best {
            Some((l, place)) => {
                found.chosen.push(l.pose().is_some().then_some(place));
                found.results.push(l);
            }
            None => {
                found.chosen.push(None);
                found.results.push(unread("no place of the catalog could rank the query (none near --prior, or no retrieval data for its features)".into()));
            }
        }
        bars.advance(1);
    }
    bars.finish();
    Ok(found)
}

/// A catalog run that wrote its poses, for its summary.
struct Summary<'a> {
    catalog_path: &'a Path,
    catalog_map: &'a Map<'static>,
    queries: &'a [Query],
    places: &'a Places<'a>,
    found: &'a Found,
}

impl Summary<'_> {
    fn localized(&self) -> usize {
        self.found
            .results
            .iter()
            .filter(|r| r.pose().is_some())
            .count()
    }

    /// How many queries each place localized.
    fn per_place(&self) -> BTreeMap<&str, usize> {
        let mut per_place: BTreeMap<&str, usize> = BTreeMap::new();
        for p in self.found.chosen.iter().flatten() {
            *per_place
                .entry(self.places.places[*p].name.as_str())
                .or_default() += 1;
        }
        per_place
    }

    /// `--json`: counts, each query's place and ranking, what the maps cost.
    fn print_json(&self, args: &Args, start: std::time::Instant) -> anyhow::Result<()> {
        let places = self.places.places;
        let mut transfer = serde_json::Map::new();
        for (i, s) in self.places.sessions.iter().enumerate() {
            if let Some(Ok(session)) = s.get() {
                let map = session.map();
                transfer.insert(places[i].name.clone(), super::super::transfer_json(map));
            }
        }
        let found = self.found;
        let each = self.queries.iter().zip(&found.chosen).zip(&found.rankings);
        let chosen: Vec<_> = each
            .map(|((q, c), ranked)| {
                json!({
                    "name": q.name,
                    "place": c.map(|p| places[p].name.clone()),
                    "ranked": ranked,
                })
            })
            .collect();
        super::super::print_json(&json!({
            "queries": self.queries.len(),
            "localized": self.localized(),
            "places": self.per_place(),
            "chosen": chosen,
            "catalog_transfer": super::super::transfer_json(self.catalog_map),
            "transfer": transfer,
            "output": args.output.display().to_string(),
            "seconds": start.elapsed().as_secs_f64(),
        }))
    }

    /// The lines a person reads: the count and each place's share.
    fn print(&self, args: &Args) {
        println!(
            "{}: {}/{} localized with catalog {}",
            args.output.display(),
            self.localized(),
            self.queries.len(),
            self.catalog_path.display()
        );
        for (name, n) in &self.per_place() {
            // The catalog's text: control characters escaped, so it cannot drive the terminal.
            println!("  place {}: {n}", escape_control_characters(name));
        }
    }
}
