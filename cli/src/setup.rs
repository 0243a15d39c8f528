//! `sfpmap setup`: fetch the ONNX Runtime the extractor needs.

use serde_json::json;
use sfpmap::extract::runtime::{self, RuntimeSource, ORT_VERSION};
use sfpmap::progress::Reporter;
use std::process::ExitCode;

/// Fetch ONNX Runtime 1.31.1 for `extract` and `convert --images` (once per machine).
///
/// Runs `python3 -m pip download --no-deps onnxruntime==1.31.1` into a temporary folder and
/// extracts `libonnxruntime.so.1.31.1` from the wheel into
/// `$XDG_CACHE_HOME/sfpmap/onnxruntime-1.31.1/` (default `~/.cache`). The commands that need
/// the runtime do this by themselves on first use; `ORT_DYLIB_PATH` or a `libonnxruntime.so*`
/// beside the executable take precedence. Example: `sfpmap setup`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Fetch again even if the cache already holds the library.
    #[arg(long)]
    pub force: bool,
    /// Also load the library and check the version it reports.
    #[arg(long)]
    pub check: bool,
    /// Print one JSON object: path, bytes, fetched, version.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    runtime::disable_telemetry();
    let bars = super::Bars::new(quiet, args.json);
    let report = runtime::setup(args.force, &bars)?;
    let mut version = None;
    let mut active = None;
    if args.check {
        let rt = runtime::runtime(&bars)?;
        version = Some(rt.version.clone());
        active = Some(rt.location.path.display().to_string());
        if rt.location.source != RuntimeSource::Cache
            && rt.location.source != RuntimeSource::Fetched
        {
            bars.warn(&format!(
                "the runtime in use is {} (ORT_DYLIB_PATH or beside the executable), not the cached one",
                sfpmap::escape::path(&rt.location.path)
            ));
        }
    }
    if args.json {
        super::print_json(&json!({
            "path": report.path.display().to_string(),
            "bytes": report.bytes,
            "fetched": report.fetched,
            "version": version,
            "active": active,
        }))?;
    } else if !quiet {
        println!(
            "{}: ONNX Runtime {ORT_VERSION}, {} bytes ({})",
            sfpmap::escape::path(&report.path),
            report.bytes,
            if report.fetched {
                "fetched"
            } else {
                "already there"
            }
        );
        if let Some(v) = version {
            println!("loaded: reports version {v}");
        }
    }
    Ok(ExitCode::SUCCESS)
}
