//! `sfpmap verify`: check every byte of a map.

use anyhow::Context;
use std::path::PathBuf;
use std::process::ExitCode;

/// Check a map completely: index, every section's checksum, decoding and contents.
///
/// Exits 0 when the map is valid; otherwise prints one line naming the problem and exits 1.
/// Example: `sfpmap verify building.sfpm`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map file.
    pub map: PathBuf,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let path = &args.map;
    let map = super::open_map(path)?;
    map.verify()
        .with_context(|| sfpmap::escape::path(path).to_string())?;
    super::report_transfer(&map, quiet);
    if !quiet {
        println!(
            "{}: ok (sfpmap {}, {} sections, {} bytes)",
            sfpmap::escape::path(path),
            map.version(),
            map.sections().len(),
            map.file_len()
        );
    }
    Ok(ExitCode::SUCCESS)
}
