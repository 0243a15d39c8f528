//! `sfpmap localize --catalog city.sfpc`: each query's candidate places are ranked by
//! retrieval on the catalog's place summaries, optionally only those near `--prior`; the best
//! `--places` localize the query and the pose with the most inliers wins
//! (`sfpmap::session::catalog`). Poses are in the chosen place's frame; `--json` says which
//! place each query went to.

use super::{none_read, warn_skipped, write_poses, Args};
use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::escape::escape_control_characters;
use sfpmap::format::Map;
use sfpmap::io::queries::{read_query_list, Query};
use sfpmap::session::catalog::{CatalogLocalization, CatalogSession, Near};
use sfpmap::session::QuerySource;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

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
    let near = args.prior.map(|position| Near {
        position,
        radius: args.radius,
    });
    let catalog_map = Arc::new(super::super::open_map(catalog_path)?);
    let source = match (&args.database, &args.features) {
        (Some(db), _) => QuerySource::Database(db.clone()),
        #[cfg(feature = "hdf5")]
        (None, Some(h5)) => QuerySource::FeaturesFile(h5.clone()),
        _ => bail!("--catalog needs the queries' features: --database queries.db or --features features.h5"),
    };
    let session = CatalogSession::builder(catalog_map, catalog_path.display().to_string())
        .source(source)
        .places_per_query(args.places)
        .place_options(args.matching.options())
        .remote(super::super::remote_options())
        .build(bars)?;
    // The place maps are inputs too: no output may replace one. Checked before any query
    // is read.
    inputs.extend(session.locations().iter().map(PathBuf::as_path));
    let outputs = super::output_files(args);
    let outputs: Vec<&Path> = outputs.iter().map(PathBuf::as_path).collect();
    super::super::check_outputs(&outputs, &inputs, args.force)?;
    let found = session.localize_all(&queries, near, args.threads, bars)?;
    for (i, place) in session.opened() {
        warn_skipped(&place.skipped_levels(), &session.locations()[i], bars);
    }
    let results: Vec<_> = found.iter().map(|f| f.localization.clone()).collect();
    if !found.iter().any(|f| f.features_read) {
        return Err(none_read(query_list, &queries, &results));
    }
    write_poses(
        &args.output,
        args.format,
        query_list,
        &queries,
        &results,
        &[],
    )?;
    let summary = Summary {
        catalog_path,
        session: &session,
        queries: &queries,
        found: &found,
    };
    if args.json {
        summary.print_json(args, start)?;
    } else if !quiet {
        summary.print(args);
    }
    let unread = found.iter().filter(|f| !f.features_read).count();
    Ok(super::exit_status(&args.output, unread, found.len(), bars))
}

/// A catalog run that wrote its poses, for its summary.
struct Summary<'a> {
    catalog_path: &'a Path,
    session: &'a CatalogSession,
    queries: &'a [Query],
    found: &'a [CatalogLocalization],
}

impl Summary<'_> {
    fn localized(&self) -> usize {
        self.found.iter().filter(|f| f.place.is_some()).count()
    }

    /// How many queries each place localized.
    fn per_place(&self) -> BTreeMap<&str, usize> {
        let places = self.session.places();
        let mut per_place: BTreeMap<&str, usize> = BTreeMap::new();
        for p in self.found.iter().filter_map(|f| f.place) {
            *per_place.entry(places[p].name.as_str()).or_default() += 1;
        }
        per_place
    }

    /// `--json`: counts, each query's place and ranking, what the maps cost.
    fn print_json(&self, args: &Args, start: std::time::Instant) -> anyhow::Result<()> {
        let places = self.session.places();
        let mut transfer = serde_json::Map::new();
        for (i, place) in self.session.opened() {
            transfer.insert(
                places[i].name.clone(),
                super::super::transfer_json(place.map()),
            );
        }
        let chosen: Vec<_> = (self.queries.iter().zip(self.found))
            .map(|(q, f)| {
                let ranked: Vec<_> = f
                    .ranked
                    .iter()
                    .map(|r| json!({"place": places[r.place].name, "score": r.score}))
                    .collect();
                json!({
                    "name": q.name,
                    "place": f.place.map(|p| places[p].name.clone()),
                    "ranked": ranked,
                })
            })
            .collect();
        let catalog: &Map<'static> = self.session.catalog();
        super::super::print_json(&json!({
            "queries": self.queries.len(),
            "localized": self.localized(),
            "places": self.per_place(),
            "chosen": chosen,
            "catalog_transfer": super::super::transfer_json(catalog),
            "transfer": transfer,
            "output": args.output.display().to_string(),
            "seconds": start.elapsed().as_secs_f64(),
        }))
    }

    /// The lines a person reads: the count and each place's share.
    fn print(&self, args: &Args) {
        println!(
            "{}: {}/{} localized with catalog {}",
            sfpmap::escape::path(&args.output),
            self.localized(),
            self.queries.len(),
            sfpmap::escape::path(self.catalog_path)
        );
        for (name, n) in &self.per_place() {
            // The catalog's text: control characters escaped, so it cannot drive the terminal.
            println!("  place {}: {n}", escape_control_characters(name));
        }
    }
}
