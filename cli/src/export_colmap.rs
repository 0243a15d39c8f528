//! `sfpmap export-colmap`: a map as a COLMAP text model.

use anyhow::Context;
use serde_json::json;
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
    // `export --colmap OUTPUT`, with this command's own JSON keys.
    let exported = super::export::export(&super::export::Args {
        map: args.map,
        ply: None,
        colmap: Some(args.output.clone()),
        kapture: None,
        tum: None,
        images_txt: None,
        rerun: None,
        max_points: None,
        force: args.force,
        json: args.json,
    })?;
    let summary = exported.colmap.context("COLMAP export did not run")?;
    if args.json {
        super::print_json(&json!({
            "output": args.output.display().to_string(),
            "cameras": summary.cameras,
            "images": summary.images,
            "points": summary.points,
            "observations": summary.observations,
        }))?;
    } else if !quiet {
        for line in exported.lines {
            println!("{line}");
        }
    }
    Ok(ExitCode::SUCCESS)
}
