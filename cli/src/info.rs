//! `sfpmap info`: what a map holds.

use sfpmap::format::{Map, Metadata};
use sfpmap::io::info::{components, Info, Retrieval};
use std::path::PathBuf;
use std::process::ExitCode;

/// Show a map's version, size, points, images and levels.
///
/// Example: `sfpmap info building.sfpm --json`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map file.
    pub map: PathBuf,
    /// Print one JSON object (schema in README.md).
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let path = &args.map;
    let map = super::open_map(path)?;
    let meta = map.metadata();
    super::report_transfer(&map, quiet);
    if args.json {
        print_info_json(&map, path)?;
        return Ok(ExitCode::SUCCESS);
    }
    print_info_text(&map, meta, path)?;
    Ok(ExitCode::SUCCESS)
}

fn print_info_json(map: &Map<'_>, path: &std::path::Path) -> anyhow::Result<()> {
    use std::io::Write;
    let info = Info::of(map, path);
    // As `super::print_json` prints a Value: one line on stdout.
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    serde_json::to_writer(&mut out, &info)?;
    writeln!(out)?;
    out.flush()?;
    Ok(())
}

fn print_info_text(map: &Map<'_>, meta: &Metadata, path: &std::path::Path) -> anyhow::Result<()> {
    use std::io::Write;
    // Buffered: a map may list 65,536 sections.
    let mut out = std::io::BufWriter::new(std::io::stdout().lock());
    writeln!(
        out,
        "{}: sfpmap {}, {} bytes, {} points, {} images, {} cameras{}",
        sfpmap::escape::path(path),
        map.version(),
        map.file_len(),
        map.n_points(),
        map.n_images(),
        meta.cameras.len(),
        if meta.geometry_only {
            ", geometry only"
        } else {
            ""
        }
    )?;
    for l in map.levels() {
        writeln!(
            out,
            "level {}: {} points, {} (stride {}), dims {} full / {} short, rest {}",
            l.id(),
            l.len(),
            // The file's text: control characters escaped, so a map cannot drive the terminal.
            sfpmap::escape::escape_control_characters(&l.info().descriptor),
            l.info().stride,
            l.dim_full(),
            l.dim_short(),
            if l.has_rest() { "present" } else { "absent" }
        )?;
    }
    writeln!(out, "{}", Retrieval::of(map, meta).describe())?;
    let parts: Vec<String> = components(map)
        .iter()
        .map(|(name, b)| format!("{name} {b:.1}"))
        .collect();
    writeln!(out, "bytes per point: {}", parts.join(", "))?;
    writeln!(out, "sections:")?;
    for s in map.sections() {
        let level = s.level().map_or(String::new(), |l| format!(" L{l}"));
        writeln!(
            out,
            "  {:<22}{:<4} {:>4} {:>9}x{:<5} {:<5} {:>12} B stored ({} B raw){}",
            s.kind().name(),
            level,
            s.dtype().name(),
            s.rows(),
            s.cols(),
            s.codec().name(),
            s.stored_len(),
            s.raw_len(),
            s.skipped()
                .map_or(String::new(), |why| format!(", skipped: {why}"))
        )?;
    }
    out.flush()?;
    Ok(())
}
