//! Argument definitions (clap derive) and dispatch; each subcommand runs in its own file.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

#[cfg(feature = "localize")]
mod bench_pose;
#[cfg(feature = "colmap")]
mod convert;
#[cfg(all(feature = "onnx", feature = "colmap", feature = "localize"))]
mod demo;
#[cfg(feature = "localize")]
mod eval;
mod export;
mod export_colmap;
#[cfg(feature = "onnx")]
mod extract;
mod info;
#[cfg(all(feature = "localize", feature = "colmap"))]
mod localize;
#[cfg(feature = "localize")]
mod plot;
mod progress;
#[cfg(feature = "onnx")]
mod setup;
mod slice;
mod verify;

pub use progress::Bars;

/// sfpmap: small, fast, level-sliceable visual-localization maps.
#[derive(Debug, Parser)]
#[command(name = "sfpmap", version, about, propagate_version = true)]
pub struct Cli {
    /// Print nothing but errors (no progress bars, no warnings).
    #[arg(long, short, global = true)]
    pub quiet: bool,
    #[command(subcommand)]
    pub command: Command,
}

// Parsed once per process: the size of the largest variant does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Subcommand)]
pub enum Command {
    #[cfg(feature = "localize")]
    #[command(hide = true)]
    BenchPose(bench_pose::Args),
    #[cfg(feature = "colmap")]
    Convert(convert::Args),
    #[cfg(all(feature = "onnx", feature = "colmap", feature = "localize"))]
    Demo(demo::Args),
    #[cfg(feature = "localize")]
    Eval(eval::Args),
    Export(export::Args),
    ExportColmap(export_colmap::Args),
    #[cfg(feature = "onnx")]
    Extract(extract::Args),
    Info(info::Args),
    #[cfg(all(feature = "localize", feature = "colmap"))]
    Localize(localize::Args),
    #[cfg(feature = "onnx")]
    Setup(setup::Args),
    #[cfg(feature = "localize")]
    Plot(plot::Args),
    Verify(verify::Args),
    Slice(slice::Args),
}

pub fn run() -> anyhow::Result<ExitCode> {
    let cli = Cli::parse();
    match cli.command {
        #[cfg(feature = "localize")]
        Command::BenchPose(args) => bench_pose::run(args, cli.quiet),
        #[cfg(feature = "colmap")]
        Command::Convert(args) => convert::run(args, cli.quiet),
        #[cfg(all(feature = "onnx", feature = "colmap", feature = "localize"))]
        Command::Demo(args) => demo::run(args, cli.quiet),
        #[cfg(feature = "localize")]
        Command::Eval(args) => eval::run(args, cli.quiet),
        Command::Export(args) => export::run(args, cli.quiet),
        Command::ExportColmap(args) => export_colmap::run(args, cli.quiet),
        #[cfg(feature = "onnx")]
        Command::Extract(args) => extract::run(args, cli.quiet),
        Command::Info(args) => info::run(args, cli.quiet),
        #[cfg(all(feature = "localize", feature = "colmap"))]
        Command::Localize(args) => localize::run(args, cli.quiet),
        #[cfg(feature = "onnx")]
        Command::Setup(args) => setup::run(args, cli.quiet),
        #[cfg(feature = "localize")]
        Command::Plot(args) => plot::run(args, cli.quiet),
        Command::Verify(args) => verify::run(args, cli.quiet),
        Command::Slice(args) => slice::run(args, cli.quiet),
    }
}

/// Prints a JSON value on stdout, one line.
pub fn print_json(value: &serde_json::Value) -> anyhow::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    serde_json::to_writer(&mut out, value)?;
    writeln!(out)?;
    Ok(())
}

/// Opens a map; errors name its path once.
pub fn open_map(path: &std::path::Path) -> anyhow::Result<sfpmap::format::Map<'static>> {
    sfpmap::format::Map::open(path).map_err(naming(path))
}

/// A format error with `path` in front, unless it is an I/O error, which already names it.
pub fn naming(path: &std::path::Path) -> impl FnOnce(sfpmap::format::Error) -> anyhow::Error + '_ {
    move |e| match e {
        sfpmap::format::Error::Io { .. } => anyhow::Error::new(e),
        e => anyhow::Error::new(e).context(path.display().to_string()),
    }
}

/// Refuses to replace an existing output unless `--force` was given.
pub fn check_free(path: &std::path::Path, force: bool) -> anyhow::Result<()> {
    if path.exists() && !force {
        anyhow::bail!("{}: exists; pass --force to overwrite", path.display());
    }
    Ok(())
}

/// The same file, even when `b` does not exist yet or is reached by another path.
pub fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    use std::path::{Path, PathBuf};
    let canon = |p: &Path| -> Option<PathBuf> {
        if let Ok(c) = p.canonicalize() {
            return Some(c);
        }
        let parent = p
            .parent()
            .filter(|x| !x.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        Some(parent.canonicalize().ok()?.join(p.file_name()?))
    };
    matches!((canon(a), canon(b)), (Some(x), Some(y)) if x == y)
}

/// Writes `path` through a temp file in the same folder (fsynced), renamed into place once
/// complete; on any error the temp file is removed and `path` is untouched.
pub fn write_atomic(
    path: &std::path::Path,
    write: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    use anyhow::Context;
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty());
    let name = path
        .file_name()
        .with_context(|| format!("{}: output has no file name", path.display()))?;
    let tmp = dir.unwrap_or(std::path::Path::new(".")).join(format!(
        ".{}.tmp{}",
        name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| {
        let file = std::fs::File::create(&tmp).with_context(|| tmp.display().to_string())?;
        let mut out = std::io::BufWriter::new(file);
        write(&mut out)?;
        let file = out.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        std::fs::rename(&tmp, path).with_context(|| path.display().to_string())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}
