//! `sfpmap slice`: keep some levels, optionally only their short descriptors.

use anyhow::Context;
use sfpmap::build::budget::slice_to_budget;
use sfpmap::build::pq::slice_encoded;
use sfpmap::format::{Codec, SliceOptions};
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

/// Cut a map down to some levels; `--short` also drops the `rest` descriptor blocks; `--pq M`
/// replaces the kept levels' descriptors by M-byte product-quantisation codes.
///
/// Points no kept level references are dropped and indices remapped. Sections that do not
/// change are copied byte for byte. Examples:
/// `sfpmap slice building.sfpm --level 2 --short -o building-l2s.sfpm`,
/// `sfpmap slice building.sfpm --level 2 --short --pq 8 -o building-l2-pq8.sfpm`,
/// `sfpmap slice building.sfpm --budget 2MB -o building-2mb.sfpm`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map to slice.
    pub map: PathBuf,
    /// A level to keep (repeat for several). With `--budget`, the only level set tried.
    #[arg(long = "level", required_unless_present = "budget")]
    pub levels: Vec<u16>,
    /// Choose levels, short or full, `--minimal` and `--pq` to fit this many bytes with the
    /// best expected accuracy (e.g. 2MB, 500kB, 1.5MiB): the rule is in README, "Byte
    /// budgets", and in `--json`.
    #[arg(long, value_name = "SIZE", value_parser = super::args::byte_size,
          conflicts_with_all = ["short", "short_dims", "minimal", "pq", "codec", "zstd_level"])]
    pub budget: Option<u64>,
    /// Keep only the short descriptor block of each level.
    #[arg(long)]
    pub short: bool,
    /// Keep only what localization reads, compactly (format 1.1): no point ids, colours or
    /// visibility keypoints; positions on a 16-bit grid (the largest error is printed);
    /// sorted, compressed visibility.
    #[arg(long)]
    pub minimal: bool,
    /// With `--short`: keep N dimensions of the short block of each kept level that has more,
    /// the leading ones of an uncentred PCA of the level's own short descriptors (as SIFT maps
    /// store theirs); the level stores the projection a query's descriptors take, and a VLAD on
    /// it (and an image index over that) is learned again. E.g. `--level 2 --short
    /// --short-dims 32` halves an SFP level 2's 64 dimensions.
    #[arg(long, value_name = "N", requires = "short", conflicts_with = "pq",
          value_parser = clap::value_parser!(u16).range(1..=4096))]
    pub short_dims: Option<u16>,
    /// Product-quantise the kept levels' descriptors (all their dims, or with `--short` the
    /// short block's) into M one-byte codes per point, M dividing the dims (format 1.1).
    #[arg(long, value_name = "M", value_parser = clap::value_parser!(u16).range(1..=4096))]
    pub pq: Option<u16>,
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
    let mut budget_report = None;
    let sliced = match args.budget {
        Some(budget) => {
            let levels = (!args.levels.is_empty()).then_some(&args.levels[..]);
            let chosen = slice_to_budget(&map, budget, levels)
                .with_context(|| sfpmap::escape::path(input).to_string())?;
            budget_report = Some(chosen.report(budget));
            if !quiet && !args.json {
                println!(
                    "budget {budget} bytes: {} ({} bytes)",
                    chosen.chosen.describe(&map),
                    chosen.bytes
                );
            }
            chosen.sliced
        }
        None => {
            let options = SliceOptions {
                levels: args.levels.clone(),
                short: args.short,
                codec: args.codec.map(Codec::from),
                zstd_level: args.zstd_level,
                minimal: args.minimal,
            };
            slice_encoded(
                &map,
                &options,
                args.short_dims.map(usize::from),
                args.pq.map(usize::from),
            )
            .with_context(|| sfpmap::escape::path(input).to_string())?
        }
    };
    let bars = super::Bars::new(quiet, args.json);
    let written = sliced
        .writer
        .write(output, &bars)
        .map_err(super::naming(output))?;
    let before = map.file_len();
    let (summary, pq) = (&sliced.summary, &sliced.pq);
    let writer_grid = sliced.writer.metadata().position_grid;
    if args.json {
        let mut report = sliced.report(input, output, before, written);
        report["transfer"] = super::transfer_json(&map);
        if let Some(b) = budget_report {
            report["budget"] = b;
        }
        super::print_json(&report)?;
    } else if !quiet {
        super::report_transfer(&map, quiet);
        println!(
            "{}: {before} bytes -> {}: {written} bytes ({:.2}x smaller), points {} -> {}",
            sfpmap::escape::path(input),
            sfpmap::escape::path(output),
            before as f64 / written.max(1) as f64,
            summary.points_before,
            summary.points_after
        );
        if let Some(g) = writer_grid {
            let e = g.max_error();
            println!(
                "  positions on a 16-bit grid: at most {:.3e}, {:.3e}, {:.3e} {} from where they were (x, y, z)",
                e[0],
                e[1],
                e[2],
                // The file's text: control characters escaped, so a map cannot drive the
                // terminal.
                sfpmap::escape::escape_control_characters(&map.metadata().units)
            );
        }
        for l in &sliced.short_basis {
            println!(
                "  level {}: short {} -> {} dims of its PCA basis ({:.1} % of the energy){}",
                l.level,
                l.dims_before,
                l.dims,
                100.0 * l.energy_kept,
                match (l.vlad_relearned, l.vlad_dropped, l.index_dropped) {
                    (true, _, false) => ", VLAD learned again",
                    (true, _, true) => ", VLAD learned again; its image index could not be built again and was dropped",
                    (_, true, false) => ", VLAD dropped (fewer points than its centroids, or no visibility)",
                    (_, true, true) => ", VLAD and its image index dropped (fewer points than its centroids, or no visibility)",
                    _ => "",
                }
            );
        }
        for l in pq {
            println!(
                "  level {}: {} dims -> {} bytes per point ({} centroids per subspace), descriptors {} -> {} bytes, mean squared error {:.4}",
                l.level, l.dims, l.subspaces, l.centroids, l.bytes_before, l.bytes_after, l.mean_squared_error
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
