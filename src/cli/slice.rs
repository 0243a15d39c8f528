//! `sfpmap slice`: keep some levels, optionally only their short descriptors.

use anyhow::Context;
use serde_json::json;
use sfpmap::format::{slice, Codec, SliceOptions};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum CodecArg {
    Raw,
    Zstd,
}

impl From<CodecArg> for Codec {
    fn from(c: CodecArg) -> Codec {
        match c {
            CodecArg::Raw => Codec::Raw,
            CodecArg::Zstd => Codec::Zstd,
        }
    }
}

/// Cut a map down to some levels; `--short` also drops the `rest` descriptor blocks.
///
/// Points no kept level references are dropped and indices remapped. Sections that do not
/// change are copied byte for byte. Example:
/// `sfpmap slice building.sfpm --level 2 --short -o building-l2s.sfpm`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map to slice.
    pub map: PathBuf,
    /// A level to keep (repeat for several).
    #[arg(long = "level", required = true)]
    pub levels: Vec<u16>,
    /// Keep only the short descriptor block of each level.
    #[arg(long)]
    pub short: bool,
    /// Re-encode every section with this codec (default: keep each section's codec).
    #[arg(long, value_enum)]
    pub codec: Option<CodecArg>,
    /// zstd level when `--codec zstd`.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(i32).range(1..=22))]
    pub zstd_level: i32,
    /// Output map.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Overwrite OUTPUT if it exists.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object with the sizes.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let (input, output) = (&args.map, &args.output);
    super::check_outputs(&[output], &[input], args.force)?;
    let map = super::open_map(input)?;
    let options = SliceOptions {
        levels: args.levels.clone(),
        short: args.short,
        codec: args.codec.map(Codec::from),
        zstd_level: args.zstd_level,
    };
    let (writer, summary) = slice(&map, &options).with_context(|| input.display().to_string())?;
    let bars = super::Bars::new(quiet, args.json);
    let written = writer.write(output, &bars).map_err(super::naming(output))?;
    let before = map.file_len();
    if args.json {
        super::print_json(&json!({
            "input": input.display().to_string(),
            "output": output.display().to_string(),
            "input_bytes": before,
            "output_bytes": written,
            "ratio": before as f64 / written.max(1) as f64,
            "points_before": summary.points_before,
            "points_after": summary.points_after,
            "sections_copied": summary.sections_copied,
            "sections_rebuilt": summary.sections_rebuilt,
            "skipped_sections_dropped": summary.skipped_dropped,
        }))?;
    } else if !quiet {
        println!(
            "{}: {before} bytes -> {}: {written} bytes ({:.2}x smaller), points {} -> {}",
            input.display(),
            output.display(),
            before as f64 / written.max(1) as f64,
            summary.points_before,
            summary.points_after
        );
    }
    Ok(ExitCode::SUCCESS)
}
