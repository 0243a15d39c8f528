//! The `sfpmap` command-line tool, a client of the `sfpmap` library: all logic is in the
//! library; this only parses arguments, draws progress and prints results. Argument
//! definitions (clap derive) and dispatch are here; each subcommand runs in its own file.

use clap::{Parser, Subcommand};
use std::process::ExitCode;

mod args;
#[cfg(feature = "localize")]
mod bench_pose;
#[cfg(feature = "colmap")]
mod catalog;
mod completions;
#[cfg(feature = "colmap")]
mod convert;
#[cfg(feature = "demo")]
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
mod reference;
#[cfg(feature = "ros2")]
mod ros2;
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
    /// Follow HTTP redirects of map and catalog URLs to another scheme, host or port (also
    /// SFPMAP_ALLOW_REDIRECTS=1).
    ///
    /// Without it a server may redirect only to itself. Either way a redirect never goes from
    /// https to http, and the rest of the outbound policy holds for its target: no link-local
    /// address (cloud metadata services), loopback or private ones only from a URL you named.
    /// The whole policy (catalogs, S3 credentials) is in the guide's "Remote maps" page.
    #[arg(long, global = true)]
    pub allow_redirects: bool,
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
    Catalog(catalog::Args),
    Completions(completions::Args),
    #[cfg(feature = "colmap")]
    Convert(convert::Args),
    #[cfg(feature = "demo")]
    Demo(demo::Args),
    #[cfg(feature = "localize")]
    Eval(eval::Args),
    Export(export::Args),
    ExportColmap(export_colmap::Args),
    #[cfg(feature = "onnx")]
    Extract(extract::Args),
    #[command(hide = true)]
    GenerateReference(reference::Args),
    Info(info::Args),
    #[cfg(all(feature = "localize", feature = "colmap"))]
    Localize(localize::Args),
    #[cfg(feature = "onnx")]
    Setup(setup::Args),
    #[cfg(feature = "localize")]
    Plot(plot::Args),
    #[cfg(feature = "ros2")]
    Ros2(ros2::Args),
    Verify(verify::Args),
    Slice(slice::Args),
}

fn main() -> ExitCode {
    // Before any work: a Ctrl-C while writing must not leave a temp file behind.
    remove_temps_on_signal();
    match run() {
        Ok(code) => code,
        Err(err) => {
            // `sfpmap info m.sfpm | head` closes the pipe early: that is not an error.
            if err
                .chain()
                .filter_map(|e| e.downcast_ref::<std::io::Error>())
                .any(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
            {
                return ExitCode::SUCCESS;
            }
            // Every path and name in it is escaped where it is shown; this holds the line to
            // one, whatever a dependency's message quotes.
            let text = format!("{err:#}");
            eprintln!(
                "error: {}",
                sfpmap::escape::escape_control_characters(&text)
            );
            ExitCode::from(1)
        }
    }
}

/// `--allow-redirects`, for [`remote_options`].
static ALLOW_REDIRECTS: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

fn run() -> anyhow::Result<ExitCode> {
    let cli = Cli::parse();
    ALLOW_REDIRECTS.store(cli.allow_redirects, std::sync::atomic::Ordering::Relaxed);
    match cli.command {
        #[cfg(feature = "localize")]
        Command::BenchPose(args) => bench_pose::run(args, cli.quiet),
        #[cfg(feature = "colmap")]
        Command::Catalog(args) => catalog::run(args, cli.quiet),
        Command::Completions(args) => completions::run(args, cli.quiet),
        #[cfg(feature = "colmap")]
        Command::Convert(args) => convert::run(args, cli.quiet),
        #[cfg(feature = "demo")]
        Command::Demo(args) => demo::run(args, cli.quiet),
        #[cfg(feature = "localize")]
        Command::Eval(args) => eval::run(args, cli.quiet),
        Command::Export(args) => export::run(args, cli.quiet),
        Command::ExportColmap(args) => export_colmap::run(args, cli.quiet),
        #[cfg(feature = "onnx")]
        Command::Extract(args) => extract::run(args, cli.quiet),
        Command::GenerateReference(args) => reference::run(args, cli.quiet),
        Command::Info(args) => info::run(args, cli.quiet),
        #[cfg(all(feature = "localize", feature = "colmap"))]
        Command::Localize(args) => localize::run(args, cli.quiet),
        #[cfg(feature = "onnx")]
        Command::Setup(args) => setup::run(args, cli.quiet),
        #[cfg(feature = "localize")]
        Command::Plot(args) => plot::run(args, cli.quiet),
        #[cfg(feature = "ros2")]
        Command::Ros2(args) => ros2::run(args, cli.quiet),
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

/// How maps by URL are read: cache, S3 settings and the outbound policy's opt-ins from the
/// environment (`sfpmap::remote::RemoteOptions::from_env`), and `--allow-redirects`.
pub fn remote_options() -> sfpmap::remote::RemoteOptions {
    let mut options = sfpmap::remote::RemoteOptions::from_env();
    options.allow_redirects |= ALLOW_REDIRECTS.load(std::sync::atomic::Ordering::Relaxed);
    options
}

/// Opens a map, a file or an `http(s)://` / `s3://` URL read by range ([`remote_options`]);
/// errors name it once.
pub fn open_map(path: &std::path::Path) -> anyhow::Result<sfpmap::format::Map<'static>> {
    sfpmap::remote::open_location(path, &remote_options()).map_err(naming(path))
}

/// What reading a map by range cost (`None` for a local map), for `--json`.
pub fn transfer_json(map: &sfpmap::format::Map<'_>) -> serde_json::Value {
    map.source()
        .map_or(serde_json::Value::Null, |s| serde_json::json!(s.stats()))
}

/// One line on stderr saying what reading a map by range cost (nothing for a local map, or
/// with `--quiet`), and a warning when the server ignored range requests.
pub fn report_transfer(map: &sfpmap::format::Map<'_>, quiet: bool) {
    let Some(source) = map.source() else {
        return;
    };
    if quiet {
        return;
    }
    warn_whole_object(map, quiet);
    let links = source.stats().cache_links_skipped;
    if links > 0 {
        eprintln!(
            "warning: {}: {links} folder(s) in the cache (SFPMAP_CACHE_DIR) are symbolic links, not folders, another user's or writable by others: left alone, never followed",
            sfpmap::escape::escape_control_characters(source.name())
        );
    }
    eprintln!("{}", transfer_line(source.name(), &source.stats()));
}

/// A warning on stderr when the server of a map read by range ignored range requests.
fn warn_whole_object(map: &sfpmap::format::Map<'_>, quiet: bool) {
    if let Some(source) = map.source().filter(|s| !quiet && s.stats().whole_object) {
        eprintln!(
            "warning: {}: the server ignores range requests; the whole object ({} bytes) was read",
            sfpmap::escape::escape_control_characters(source.name()),
            source.len()
        );
    }
}

/// `URL: read N bytes in K requests (C sections, B bytes from the cache)`.
pub fn transfer_line(name: &str, s: &sfpmap::format::SourceStats) -> String {
    let name = sfpmap::escape::escape_control_characters(name);
    let mut line = format!(
        "{name}: read {} bytes in {} request{}",
        s.bytes,
        s.requests,
        if s.requests == 1 { "" } else { "s" }
    );
    if s.cache_hits > 0 {
        line.push_str(&format!(
            " ({} sections, {} bytes from the cache)",
            s.cache_hits, s.cache_bytes
        ));
    }
    if s.refetched > 0 {
        line.push_str(&format!("; {} damaged section(s) read again", s.refetched));
    }
    line
}

/// A format error with `path` in front, unless it is an I/O error, which already names it.
pub fn naming(path: &std::path::Path) -> impl FnOnce(sfpmap::format::Error) -> anyhow::Error + '_ {
    move |e| match e {
        sfpmap::format::Error::Io { .. } => anyhow::Error::new(e),
        e => anyhow::Error::new(e).context(sfpmap::escape::path(path).to_string()),
    }
}

/// The output policy ([`sfpmap::output::check_output`]) for each of `outputs`: none may be one
/// of `inputs`, a device, FIFO or folder, or an existing file without `--force`; and no two
/// outputs may name the same file (the second would silently replace the first).
pub fn check_outputs(
    outputs: &[&std::path::Path],
    inputs: &[&std::path::Path],
    force: bool,
) -> anyhow::Result<()> {
    for out in outputs {
        sfpmap::output::check_output(out, inputs, force)?;
    }
    // The file an output names, whether or not it exists yet: its folder resolved, its name.
    let place = |p: &std::path::Path| {
        let dir = p.parent().filter(|d| !d.as_os_str().is_empty());
        let dir = dir.unwrap_or(std::path::Path::new("."));
        Some((dir.canonicalize().ok()?, p.file_name()?.to_os_string()))
    };
    let places: Vec<_> = outputs.iter().map(|p| place(p)).collect();
    for (i, a) in places.iter().enumerate() {
        if let Some(j) = places[..i].iter().position(|b| a.is_some() && b == a) {
            anyhow::bail!(
                "{}: named as two outputs (also as {}); give each output its own file",
                sfpmap::escape::path(outputs[i]),
                sfpmap::escape::path(outputs[j])
            );
        }
    }
    Ok(())
}

/// Writes `path` through [`sfpmap::output::AtomicFile`] (temp file in the same folder, fsync,
/// rename; nothing changed and nothing left on error); errors of `write` get `path` in front.
pub fn write_atomic<T>(
    path: &std::path::Path,
    write: impl FnOnce(&mut sfpmap::output::AtomicFile) -> anyhow::Result<T>,
) -> anyhow::Result<T> {
    use anyhow::Context;
    sfpmap::output::write_atomic(path, |out| {
        write(out).with_context(|| sfpmap::escape::path(path).to_string())
    })
}

/// Set by [`stop_on_signal`]: a SIGINT or SIGTERM asks the command to stop, not the process
/// to exit.
static STOP_ON_SIGNAL: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
/// A SIGINT or SIGTERM arrived while [`STOP_ON_SIGNAL`] was set.
static STOP_REQUESTED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// On SIGINT or SIGTERM: removes the temp files of unfinished writes and exits 130 (SIGINT)
/// or 143 (SIGTERM), as a shell reports a process killed by them; after [`stop_on_signal`],
/// the first one only asks the command to stop ([`stop_requested`]) and a second exits.
pub fn remove_temps_on_signal() {
    use signal_hook::consts::{SIGINT, SIGTERM};
    use std::sync::atomic::Ordering;
    // Without a handler the default action still ends the process: only temp files stay.
    let Ok(mut signals) = signal_hook::iterator::Signals::new([SIGINT, SIGTERM]) else {
        return;
    };
    std::thread::spawn(move || {
        for signal in signals.forever() {
            if STOP_ON_SIGNAL.load(Ordering::SeqCst) && !STOP_REQUESTED.swap(true, Ordering::SeqCst)
            {
                continue;
            }
            sfpmap::output::remove_pending_temps();
            std::process::exit(128 + signal);
        }
    });
}

/// From now on a SIGINT or SIGTERM asks the running command to stop (`sfpmap ros2` ends its
/// loop and prints its counts); a second one exits at once.
#[cfg(feature = "ros2")]
pub fn stop_on_signal() {
    STOP_ON_SIGNAL.store(true, std::sync::atomic::Ordering::SeqCst);
}

/// Whether a signal asked the command to stop.
#[cfg(feature = "ros2")]
pub fn stop_requested() -> bool {
    STOP_REQUESTED.load(std::sync::atomic::Ordering::SeqCst)
}

/// `--global-max-side N`: 0, or a side of at least `GLOBAL_MIN_SIDE` (`GlobalSize::from_flag`).
#[cfg(feature = "onnx")]
pub fn global_max_side(value: &str) -> Result<u32, String> {
    let side: u32 = value
        .parse()
        .map_err(|_| format!("{value:?}: not a whole number of pixels"))?;
    sfpmap::extract::GlobalSize::from_flag(side)?;
    Ok(side)
}

/// `--threads` capped at [`sfpmap::progress::max_threads`] (4 per core, at most 256), with a
/// warning (silent under `--quiet`) when it is cut; the Python package caps the same way.
#[cfg(any(feature = "colmap", feature = "onnx"))]
pub fn cap_threads(requested: usize, reporter: &dyn sfpmap::progress::Reporter) -> usize {
    sfpmap::progress::cap_threads("--threads", requested, reporter)
}
