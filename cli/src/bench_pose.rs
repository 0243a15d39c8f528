//! `sfpmap bench-pose` (hidden): times `estimate_absolute_pose` (LO-RANSAC + final refinement)
//! on correspondences from a file, for `benches/ransac_vs_pycolmap.py`, which runs pycolmap's
//! `estimate_and_refine_absolute_pose` on the same arrays.

use anyhow::{bail, Context};
use nalgebra::{Vector2, Vector3};
use serde::Deserialize;
use serde_json::json;
use sfpmap::geometry::{estimate_absolute_pose, Camera, RansacOptions};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

/// Time absolute-pose LO-RANSAC + refinement on correspondences from a JSON file.
///
/// The file: `{"camera": "MODEL W H params...", "pixels": [[x, y], ...], "points": [[x, y, z],
/// ...], "max_error_px": 4.0, "confidence": 0.9999, "min_iterations": 100, "max_iterations":
/// 10000}` (the last four optional: RansacOptions defaults).
///
/// Example: `sfpmap bench-pose --input corr.json --repeats 20 --json`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Correspondences and options (JSON).
    #[arg(long)]
    pub input: PathBuf,
    /// Timed runs, 1 or more (after one untimed warm-up run).
    #[arg(long, default_value_t = 10,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub repeats: usize,
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Deserialize)]
struct Input {
    camera: String,
    pixels: Vec<[f64; 2]>,
    points: Vec<[f64; 3]>,
    max_error_px: Option<f64>,
    confidence: Option<f64>,
    min_iterations: Option<usize>,
    max_iterations: Option<usize>,
}

pub fn run(args: Args, _quiet: bool) -> anyhow::Result<ExitCode> {
    let text = std::fs::read_to_string(&args.input)
        .with_context(|| format!("reading {}", sfpmap::escape::path(&args.input)))?;
    let input: Input = serde_json::from_str(&text)
        .with_context(|| format!("parsing {}", sfpmap::escape::path(&args.input)))?;
    if input.pixels.len() != input.points.len() {
        bail!(
            "{} pixels but {} points",
            input.pixels.len(),
            input.points.len()
        );
    }
    let camera = Camera::parse(&input.camera).context("camera")?;
    let pixels: Vec<Vector2<f64>> = input.pixels.iter().map(|&p| Vector2::from(p)).collect();
    let points: Vec<Vector3<f64>> = input.points.iter().map(|&p| Vector3::from(p)).collect();
    let defaults = RansacOptions::default();
    let options = RansacOptions {
        max_error_px: input.max_error_px.unwrap_or(defaults.max_error_px),
        confidence: input.confidence.unwrap_or(defaults.confidence),
        min_iterations: input.min_iterations.unwrap_or(defaults.min_iterations),
        max_iterations: input.max_iterations.unwrap_or(defaults.max_iterations),
        ..defaults
    };

    let mut estimate = estimate_absolute_pose(&pixels, &points, &camera, &options)
        .context("estimate_absolute_pose")?;
    let mut times_ms = Vec::with_capacity(args.repeats);
    for _ in 0..args.repeats.max(1) {
        let t = Instant::now();
        estimate = estimate_absolute_pose(&pixels, &points, &camera, &options)
            .context("estimate_absolute_pose")?;
        times_ms.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times_ms.sort_by(f64::total_cmp);
    let median_ms = times_ms[times_ms.len() / 2];
    let pose = estimate.pose.to_colmap();
    if args.json {
        super::print_json(&json!({
            "median_ms": median_ms,
            "times_ms": times_ms,
            "cam_from_world": pose,
            "inliers": estimate.num_inliers,
            "iterations": estimate.iterations,
            "correspondences": pixels.len(),
        }))?;
    } else {
        println!(
            "{} correspondences, {} runs: median {median_ms:.3} ms",
            pixels.len(),
            times_ms.len()
        );
        println!(
            "cam_from_world (qw qx qy qz tx ty tz): {}",
            pose.map(|v| format!("{v:.6}")).join(" ")
        );
        println!(
            "inliers {} of {}, {} iterations",
            estimate.num_inliers,
            pixels.len(),
            estimate.iterations
        );
    }
    Ok(ExitCode::SUCCESS)
}
