//! `sfpmap eval`: errors of estimated poses against ground truth.

use serde_json::json;
use sfpmap::io::poses::read_poses;
use sfpmap::localize::eval::{evaluate, map_scale};
use std::path::PathBuf;
use std::process::ExitCode;

/// Compare estimated poses with ground truth: median translation and rotation errors, recall
/// at thresholds, and (with --map) translation errors relative to the median distance between
/// neighbouring map cameras, since SfM scale is arbitrary.
///
/// Example: `sfpmap eval --poses poses.txt --gt gt_poses.txt --map sb.sfpm --json`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Estimated poses (`name qw qx qy qz tx ty tz`).
    #[arg(long)]
    pub poses: PathBuf,
    /// Ground truth in the same format.
    #[arg(long)]
    pub gt: PathBuf,
    /// The map, for relative errors and its size.
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// Recall thresholds `meters,degrees` (repeat): a finite distance over 0 (map units) and
    /// an angle in (0, 180]; default 0.25,2 0.5,5 5,10.
    #[arg(long = "threshold", value_parser = super::args::recall_threshold)]
    pub thresholds: Vec<(f64, f64)>,
    /// Print one JSON object (medians, recall, map_bytes, scale, per_query) instead of text.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, _quiet: bool) -> anyhow::Result<ExitCode> {
    let estimates = read_poses(&args.poses)?;
    let gt = read_poses(&args.gt)?;
    let thresholds = if args.thresholds.is_empty() {
        vec![(0.25, 2.0), (0.5, 5.0), (5.0, 10.0)]
    } else {
        args.thresholds.clone()
    };
    let (scale, map_bytes) = match &args.map {
        Some(path) => {
            let map = super::open_map(path)?;
            (map_scale(&map)?, Some(map.file_len()))
        }
        None => (None, None),
    };
    let e = evaluate(&estimates, &gt, &thresholds, scale);
    if args.json {
        let mut report = e.summary_json();
        report.insert("map_bytes".into(), json!(map_bytes));
        report.insert("scale".into(), json!(e.scale));
        let per_query: Vec<_> = e
            .per_query
            .iter()
            .map(|(n, err)| json!({ "name": n, "translation": err.map(|x| x.0), "rotation_deg": err.map(|x| x.1) }))
            .collect();
        report.insert("per_query".into(), json!(per_query));
        super::print_json(&serde_json::Value::Object(report))?;
        return Ok(ExitCode::SUCCESS);
    }
    let fmt =
        |v: Option<f64>, digits: usize| v.map_or("inf".to_string(), |x| format!("{x:.digits$}"));
    println!(
        "queries {} | localized {} | median {} units, {} deg | relative {} | map {}",
        e.queries,
        e.localized,
        fmt(e.median_translation, 3),
        fmt(e.median_rotation_deg, 2),
        if e.scale.is_some() {
            fmt(e.median_translation_rel, 3)
        } else {
            "- (no --map)".to_string()
        },
        map_bytes.map_or("-".to_string(), |b| format!("{:.2} MB", b as f64 / 1e6))
    );
    for (t, r, v) in &e.recall {
        println!("recall ({t}, {r} deg): {:.1} %", 100.0 * v);
    }
    Ok(ExitCode::SUCCESS)
}
