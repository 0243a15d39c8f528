//! `sfpmap plot`: a top-down PNG of a map, its database cameras and localized / ground-truth
//! poses.

use serde_json::json;
use sfpmap::io::plot::{plot_map, PlotError, PlotOptions};
use sfpmap::io::poses::read_poses;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Draw a map from above: points coloured by level, database cameras, and optionally
/// localized poses (--poses, as written by `sfpmap localize`) and ground truth (--gt), with a
/// line from each localized camera to its ground-truth position. The view is along the
/// world axis in which the database cameras spread least.
///
/// Example: `sfpmap plot building.sfpm --poses poses.txt --gt gt_poses.txt -o building.png`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map file.
    pub map: PathBuf,
    /// Localized poses (`name qw qx qy qz tx ty tz`, cam_from_world).
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Ground-truth poses, same format.
    #[arg(long)]
    pub gt: Option<PathBuf>,
    /// The PNG to write.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Image width in pixels (64 to 16384).
    #[arg(long, default_value_t = 1600, value_parser = clap::value_parser!(u32).range(64..=16384))]
    pub width: u32,
    /// Image height in pixels (64 to 16384).
    #[arg(long, default_value_t = 1200, value_parser = clap::value_parser!(u32).range(64..=16384))]
    pub height: u32,
    /// Draw at most this many points, 1 or more (every k-th point beyond it).
    #[arg(long, default_value_t = 200_000,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub max_points: usize,
    /// Title (default: the map's file name and counts).
    #[arg(long)]
    pub title: Option<String>,
    /// Overwrite OUTPUT if it exists.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object with what was drawn.
    #[arg(long)]
    pub json: bool,
}

fn centres(path: &Path) -> anyhow::Result<Vec<(String, [f64; 3])>> {
    Ok(read_poses(path)?
        .into_iter()
        .map(|(name, pose)| (name, pose.center().into()))
        .collect())
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let inputs: Vec<&Path> = std::iter::once(args.map.as_path())
        .chain(args.poses.as_deref())
        .chain(args.gt.as_deref())
        .collect();
    super::check_outputs(&[&args.output], &inputs, args.force)?;
    let map = super::open_map(&args.map)?;
    let estimated = args
        .poses
        .as_deref()
        .map(centres)
        .transpose()?
        .unwrap_or_default();
    let ground_truth = args
        .gt
        .as_deref()
        .map(centres)
        .transpose()?
        .unwrap_or_default();
    let name = args.map.file_name().map_or_else(
        || sfpmap::escape::path(&args.map).to_string(),
        |n| n.to_string_lossy().into(),
    );
    let title = args.title.clone().unwrap_or_else(|| {
        let images = map.images().ok().flatten().map_or(0, |i| i.len());
        format!(
            "{name}: {} points, {} levels, {images} images (top view)",
            map.n_points(),
            map.metadata().levels.len()
        )
    });
    let options = PlotOptions {
        width: args.width,
        height: args.height,
        max_points: args.max_points,
        title,
        estimated,
        ground_truth,
    };
    let summary = plot_map(&map, &options, &args.output).map_err(|e| match e {
        // Names the output already.
        PlotError::Output(e) => anyhow::Error::new(e),
        // About what the map holds: name the map.
        e @ (PlotError::Empty | PlotError::Unplottable(_)) => {
            anyhow::Error::new(e).context(sfpmap::escape::path(&args.map).to_string())
        }
        PlotError::Format(e) => super::naming(&args.map)(e),
        e => anyhow::Error::new(e).context(sfpmap::escape::path(&args.output).to_string()),
    })?;
    let axes = ["x", "y", "z"];
    if args.json {
        super::print_json(&json!({
            "output": args.output.display().to_string(),
            "axes": [axes[summary.axes.0], axes[summary.axes.1]],
            "points_drawn": summary.points_drawn,
            "cameras": summary.cameras,
            "pairs": summary.pairs,
        }))?;
    } else if !quiet {
        println!(
            "{}: {}–{} view, {} points, {} cameras, {} localized/ground-truth pairs",
            sfpmap::escape::path(&args.output),
            axes[summary.axes.0],
            axes[summary.axes.1],
            summary.points_drawn,
            summary.cameras,
            summary.pairs
        );
    }
    Ok(ExitCode::SUCCESS)
}
