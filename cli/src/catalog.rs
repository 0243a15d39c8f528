//! `sfpmap catalog build`: a catalog of place maps (`.sfpc`) for `localize --catalog`.

use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::build::catalog::{build_catalog, PlaceMap};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Catalogs of place maps: many maps (files or URLs) listed in one small file, with each
/// place's bounding box and retrieval summary, so `localize --catalog` opens only the places
/// a query may be in.
#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(subcommand)]
    pub command: CatalogCommand,
}

#[derive(Debug, clap::Subcommand)]
pub enum CatalogCommand {
    Build(BuildArgs),
}

/// Write a catalog of place maps. A map given as a path is recorded relative to the
/// catalog's folder when it lies inside it (the folder can move), else absolute; a URL as is.
/// Example: `sfpmap catalog build https://maps.example/a.sfpm b.sfpm -o city.sfpc`
#[derive(Debug, clap::Args)]
pub struct BuildArgs {
    /// The place maps: files or `http(s)://` / `s3://` URLs (read by range: only their
    /// positions, images and retrieval data).
    #[arg(required = true)]
    pub maps: Vec<PathBuf>,
    /// A name per map, in order (default: the file name without extension).
    #[arg(long = "name")]
    pub names: Vec<String>,
    /// Output catalog.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Overwrite OUTPUT if it exists.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    match args.command {
        CatalogCommand::Build(args) => build(args, quiet),
    }
}

/// What the catalog records for `map`: a URL as given; a path relative to `dir` when inside
/// it, else absolute.
fn location(map: &Path, dir: &Path) -> anyhow::Result<String> {
    let text = map
        .to_str()
        .with_context(|| format!("{}: not UTF-8", sfpmap::escape::path(map)))?;
    if sfpmap::input::is_url(text) {
        return Ok(text.to_string());
    }
    let absolute = map
        .canonicalize()
        .with_context(|| sfpmap::escape::path(map).to_string())?;
    let relative = dir
        .canonicalize()
        .ok()
        .and_then(|d| absolute.strip_prefix(d).ok().map(Path::to_path_buf));
    let chosen = relative.unwrap_or(absolute);
    Ok(chosen
        .to_str()
        .with_context(|| format!("{}: not UTF-8", sfpmap::escape::path(map)))?
        .to_string())
}

fn build(args: BuildArgs, quiet: bool) -> anyhow::Result<ExitCode> {
    if !args.names.is_empty() && args.names.len() != args.maps.len() {
        bail!(
            "--name given {} times for {} maps: name every map or none",
            args.names.len(),
            args.maps.len()
        );
    }
    let inputs: Vec<&Path> = args.maps.iter().map(PathBuf::as_path).collect();
    super::check_outputs(&[&args.output], &inputs, args.force)?;
    let dir = args
        .output
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let maps = args
        .maps
        .iter()
        .map(|m| super::open_map(m))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let mut places = Vec::with_capacity(maps.len());
    for (i, (path, map)) in args.maps.iter().zip(&maps).enumerate() {
        let name = match args.names.get(i) {
            Some(n) => n.clone(),
            None => path
                .file_stem()
                .map_or_else(|| format!("place{i}"), |s| s.to_string_lossy().into_owned()),
        };
        places.push(PlaceMap {
            name,
            location: location(path, dir)?,
            map,
        });
    }
    if let Some(twice) = places.iter().enumerate().find_map(|(i, p)| {
        places[..i]
            .iter()
            .any(|q| q.name == p.name)
            .then_some(&p.name)
    }) {
        bail!("two places are named {twice:?}: give each a --name");
    }
    let writer = build_catalog(&places).map_err(|e| {
        anyhow::anyhow!("{e}").context(format!(
            "{}: building the catalog",
            sfpmap::escape::path(&args.output)
        ))
    })?;
    let bars = super::Bars::new(quiet, args.json);
    let written = writer
        .write(&args.output, &bars)
        .map_err(super::naming(&args.output))?;
    if args.json {
        super::print_json(&json!({
            "output": args.output.display().to_string(),
            "bytes": written,
            "places": places.iter().zip(&maps).map(|(p, m)| json!({
                "name": p.name,
                "map": p.location,
                "points": m.n_points(),
                "images": m.n_images(),
                "transfer": super::transfer_json(m),
            })).collect::<Vec<_>>(),
        }))?;
    } else if !quiet {
        println!(
            "{}: {} places, {written} bytes",
            sfpmap::escape::path(&args.output),
            places.len()
        );
        for (p, m) in places.iter().zip(&maps) {
            println!(
                "  {}: {} ({} points, {} images)",
                sfpmap::escape::escape_control_characters(&p.name),
                sfpmap::escape::escape_control_characters(&p.location),
                m.n_points(),
                m.n_images()
            );
            super::report_transfer(m, quiet);
        }
    }
    Ok(ExitCode::SUCCESS)
}
