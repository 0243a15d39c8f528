//! `sfpmap export-colmap`: a map as a COLMAP text model.

use anyhow::Context;
use serde_json::json;
use sfpmap::io::colmap_export::export_colmap;
use std::path::PathBuf;
use std::process::ExitCode;

/// Write a map's cameras, images (with their observations) and points as a COLMAP text model
/// (cameras.txt, images.txt, points3D.txt) that COLMAP and pycolmap read.
///
/// Example: `sfpmap export-colmap building.sfpm -o building-colmap/`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map file.
    pub map: PathBuf,
    /// Output folder (created if missing).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Overwrite a model already in OUTPUT.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object with the counts.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        super::check_free(&args.output.join(f), args.force)?;
    }
    let map = super::open_map(&args.map)?;
    let summary =
        export_colmap(&map, &args.output).with_context(|| args.map.display().to_string())?;
    if args.json {
        super::print_json(&json!({
            "output": args.output.display().to_string(),
            "cameras": summary.cameras,
            "images": summary.images,
            "points": summary.points,
            "observations": summary.observations,
        }))?;
    } else if !quiet {
        println!(
            "{}: {} cameras, {} images, {} points, {} observations",
            args.output.display(),
            summary.cameras,
            summary.images,
            summary.points,
            summary.observations
        );
    }
    Ok(ExitCode::SUCCESS)
}
