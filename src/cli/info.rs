//! `sfpmap info`: what a map holds.

use serde_json::{json, Value};
use sfpmap::format::Section;
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

fn section_json(s: &Section) -> Value {
    json!({
        "kind": s.kind.name(),
        "kind_code": s.kind.code(),
        "level": s.level,
        "dtype": s.dtype.name(),
        "rows": s.rows,
        "cols": s.cols,
        "codec": s.codec.name(),
        "stored_bytes": s.stored_len,
        "raw_bytes": s.raw_len,
        "required": s.required,
    })
}

pub fn run(args: Args, _quiet: bool) -> anyhow::Result<ExitCode> {
    let path = &args.map;
    let map = super::open_map(path)?;
    let meta = map.metadata();
    let levels: Vec<Value> = map
        .levels()
        .map(|l| {
            json!({
                "level": l.id(),
                "points": l.len(),
                "dim_full": l.dim_full(),
                "dim_short": l.dim_short(),
                "has_rest": l.has_rest(),
                "has_descriptors": l.has_descriptors(),
                "descriptor": l.info().descriptor,
                "stride": l.info().stride,
                "stored_bytes": l.sections().map(|s| s.stored_len).sum::<u64>(),
                "sections": l.sections().map(section_json).collect::<Vec<_>>(),
            })
        })
        .collect();
    let info = json!({
        "path": path.display().to_string(),
        "version": map.version(),
        "file_bytes": map.file_len(),
        "points": map.n_points(),
        "images": map.n_images(),
        "cameras": meta.cameras.len(),
        "geometry_only": meta.geometry_only,
        "origin": meta.origin,
        "levels": levels,
        "sections": map.sections().iter().map(section_json).collect::<Vec<_>>(),
        "unknown_sections": map.unknown_sections().map(section_json).collect::<Vec<_>>(),
        "provenance": meta.provenance,
    });
    if args.json {
        super::print_json(&info)?;
        return Ok(ExitCode::SUCCESS);
    }
    println!(
        "{}: sfpmap {}, {} bytes, {} points, {} images, {} cameras{}",
        path.display(),
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
    );
    for l in map.levels() {
        println!(
            "level {}: {} points, {} (stride {}), dims {} full / {} short, rest {}",
            l.id(),
            l.len(),
            l.info().descriptor,
            l.info().stride,
            l.dim_full(),
            l.dim_short(),
            if l.has_rest() { "present" } else { "absent" }
        );
    }
    println!("sections:");
    for s in map.sections() {
        let level = s.level.map_or(String::new(), |l| format!(" L{l}"));
        println!(
            "  {:<22}{:<4} {:>4} {:>9}x{:<5} {:<5} {:>12} B stored ({} B raw)",
            s.kind.name(),
            level,
            s.dtype.name(),
            s.rows,
            s.cols,
            s.codec.name(),
            s.stored_len,
            s.raw_len
        );
    }
    Ok(ExitCode::SUCCESS)
}
