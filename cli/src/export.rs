//! `sfpmap export`: a map's points and poses to other tools (PLY, COLMAP text, kapture, TUM).

use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::format::Map;
use sfpmap::io::colmap_export::{export_colmap, ExportSummary, COLMAP_FILES};
use sfpmap::io::{ply, poses};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Export a map's points and database poses to other tools. At least one output is needed.
///
/// --ply writes a binary PLY (x y z as double world coordinates, red green blue, `level` =
/// deepest level holding the point or -1, `level_mask`) that CloudCompare and MeshLab open.
/// --colmap writes a COLMAP text model (same as `export-colmap`). --kapture writes a kapture
/// folder (sensors, records, trajectories, points3d; the observed keypoints and observations
/// where the map stores keypoints; no descriptors: a map keeps one per point, not per image). --tum and --images-txt
/// write the database images' poses as a TUM trajectory (world_from_cam) or a COLMAP
/// images.txt (cam_from_world, no observations). --rerun writes a Rerun recording (points
/// coloured by level, the database cameras as frusta) through the Python package's
/// `sfpmap.viz` (`pip install 'sfpmap[viz]'`; the interpreter is SFPMAP_PYTHON, else python3),
/// which also draws queries, their errors, inliers and trajectories: see the guide.
///
/// Example: `sfpmap export building.sfpm --ply building.ply --tum building-poses.txt`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The map file.
    pub map: PathBuf,
    /// Points as a binary little-endian PLY.
    #[arg(long, value_name = "OUT.ply")]
    pub ply: Option<PathBuf>,
    /// A COLMAP text model (cameras.txt, images.txt, points3D.txt) in this folder.
    #[arg(long, value_name = "DIR")]
    pub colmap: Option<PathBuf>,
    /// A kapture 1.1 folder (sensors, trajectories, records, points3d, keypoints, observations).
    #[arg(long, value_name = "DIR")]
    pub kapture: Option<PathBuf>,
    /// Database image poses as a TUM trajectory (`timestamp tx ty tz qx qy qz qw`).
    #[arg(long, value_name = "OUT.txt")]
    pub tum: Option<PathBuf>,
    /// Database image poses as a COLMAP images.txt without observations.
    #[arg(long, value_name = "OUT.txt")]
    pub images_txt: Option<PathBuf>,
    /// A Rerun recording of the map (rerun-sdk, through `python -m sfpmap.viz`).
    #[arg(long, value_name = "OUT.rrd")]
    pub rerun: Option<PathBuf>,
    /// With --rerun: at most this many points per level (every n-th), for a map too large to
    /// look at whole.
    #[arg(long, requires = "rerun", value_parser = clap::value_parser!(u64).range(1..))]
    pub max_points: Option<u64>,
    /// Overwrite existing outputs.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object with what was written.
    #[arg(long)]
    pub json: bool,
}

use super::{check_outputs, write_atomic};

/// What [`export`] wrote: the `--json` object, one plain-text line per output, and the COLMAP
/// model's counts (`export-colmap` prints those its own way).
pub(super) struct Exported {
    pub report: serde_json::Map<String, serde_json::Value>,
    pub lines: Vec<String>,
    pub colmap: Option<ExportSummary>,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let Exported { report, lines, .. } = export(&args)?;
    if args.json {
        super::print_json(&serde_json::Value::Object(report))?;
    } else if !quiet {
        for line in lines {
            println!("{line}");
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Writes every output `args` asks for (`--json` is the caller's); `export-colmap` runs
/// through here too.
pub(super) fn export(args: &Args) -> anyhow::Result<Exported> {
    if args.ply.is_none()
        && args.colmap.is_none()
        && args.tum.is_none()
        && args.images_txt.is_none()
        && args.kapture.is_none()
        && args.rerun.is_none()
    {
        bail!(
            "nothing to export: pass --ply, --colmap, --kapture, --tum, --images-txt and/or --rerun"
        );
    }
    let colmap_files: Vec<PathBuf> = args
        .colmap
        .iter()
        .flat_map(|dir| COLMAP_FILES.map(|f| dir.join(f)))
        .collect();
    let outputs: Vec<&Path> = [&args.ply, &args.tum, &args.images_txt, &args.rerun]
        .into_iter()
        .flatten()
        .chain(&colmap_files)
        .map(|p| p.as_path())
        .collect();
    check_outputs(&outputs, &[&args.map], args.force)?;
    if let Some(out) = &args.rerun {
        check_rerun(out)?;
    }
    let map = super::open_map(&args.map)?;
    let source = sfpmap::escape::path(&args.map).to_string();
    let mut report = serde_json::Map::new();
    let mut lines = Vec::new();
    let mut colmap = None;

    // What each output can hold (names, camera models, poses) is checked before any is
    // written, and kapture's existing files go first: a refusal leaves no output behind.
    if args.colmap.is_some() || args.images_txt.is_some() {
        sfpmap::io::colmap_export::check_images_exportable(&map)
            .map_err(super::naming(&args.map))?;
    }
    #[cfg(feature = "colmap")]
    if args.kapture.is_some() {
        sfpmap::io::kapture::check_exportable(&map).map_err(|e| kapture_error(&args.map, e))?;
    }
    if let Some(dir) = &args.kapture {
        #[cfg(not(feature = "colmap"))]
        bail!(
            "{}: kapture export needs sfpmap built with the colmap feature",
            sfpmap::escape::path(dir)
        );
        #[cfg(feature = "colmap")]
        {
            let s = sfpmap::io::kapture::export_kapture(&map, dir, &[&args.map], args.force)
                .map_err(|e| kapture_error(&args.map, e))?;
            let counts = [s.cameras, s.images, s.points, s.observations];
            let (entry, line) = model_written(dir, "kapture with ", counts);
            report.insert("kapture".into(), entry);
            lines.push(line);
        }
    }
    if let Some(path) = &args.ply {
        // What the PLY reads is checked first, so a damaged map is reported as the map's
        // error (sections are checked once, so the writer below reads them at no cost).
        map.point_positions().map_err(super::naming(&args.map))?;
        map.point_colors().map_err(super::naming(&args.map))?;
        ply::point_levels(&map).map_err(super::naming(&args.map))?;
        let s = write_atomic(path, |out| {
            ply::write_ply(&map, out, &source).map_err(|e| match e {
                // Writing failed: `write_atomic` names the output; the error's own path is
                // the map (`write_ply` names its errors after its source).
                sfpmap::format::Error::Io { message, .. } => anyhow::anyhow!(message),
                e => super::naming(&args.map)(e),
            })
        })?;
        report.insert(
            "ply".into(),
            json!({"path": path.display().to_string(), "points": s.points, "points_in_levels": s.points_in_levels}),
        );
        lines.push(format!(
            "{}: {} points ({} in levels)",
            sfpmap::escape::path(path),
            s.points,
            s.points_in_levels
        ));
    }
    if let Some(dir) = &args.colmap {
        let s = export_colmap(&map, dir).map_err(super::naming(&args.map))?;
        let counts = [s.cameras, s.images, s.points, s.observations];
        let (entry, line) = model_written(dir, "", counts);
        report.insert("colmap".into(), entry);
        lines.push(line);
        colmap = Some(s);
    }
    for (path, text, key) in [
        (&args.tum, poses::images_tum as fn(&Map<'_>) -> _, "tum"),
        (&args.images_txt, poses::images_txt, "images_txt"),
    ] {
        let Some(path) = path else { continue };
        let n_images = map
            .images()
            .map_err(super::naming(&args.map))?
            .map_or(0, |i| i.len());
        let text = text(&map).with_context(|| source.clone())?;
        write_atomic(path, |out| {
            use std::io::Write;
            out.write_all(text.as_bytes())?;
            Ok(())
        })?;
        report.insert(
            key.into(),
            json!({"path": path.display().to_string(), "images": n_images}),
        );
        lines.push(format!(
            "{}: {n_images} image poses",
            sfpmap::escape::path(path)
        ));
    }
    if let Some(path) = &args.rerun {
        let summary = rerun(&args.map, path, args.max_points)?;
        lines.push(format!(
            "{}: a Rerun recording ({} points, {} cameras)",
            sfpmap::escape::path(path),
            summary["points_per_level"]
                .as_object()
                .map_or(0, |l| l.values().filter_map(|v| v.as_u64()).sum::<u64>()),
            summary["cameras"]
        ));
        report.insert("rerun".into(), summary);
    }
    if map.source().is_some() {
        report.insert("transfer".into(), super::transfer_json(&map));
    }
    Ok(Exported {
        report,
        lines,
        colmap,
    })
}

/// What a `--rerun` that cannot import the package says.
const RERUN_HINT: &str = ": --rerun needs the Python package with its viz extra \
     (pip install 'sfpmap[viz]'), in SFPMAP_PYTHON or python3";

/// The interpreter `--rerun` runs: `SFPMAP_PYTHON`, else `python3`.
fn rerun_python() -> std::ffi::OsString {
    std::env::var_os("SFPMAP_PYTHON").unwrap_or_else(|| "python3".into())
}

/// Before any output is written: the interpreter imports `sfpmap.viz` and rerun-sdk, so a
/// missing one leaves no other output behind.
fn check_rerun(out: &Path) -> anyhow::Result<()> {
    let python = rerun_python();
    let ok = std::process::Command::new(&python)
        .args(["-c", "import sfpmap.viz, rerun"])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if !ok {
        bail!(
            "{}: {} cannot import sfpmap.viz and rerun{RERUN_HINT}",
            sfpmap::escape::path(out),
            Path::new(&python).display()
        );
    }
    Ok(())
}

/// `python -m sfpmap.viz MAP -o OUT --force --json` (the output policy was checked here):
/// the recording is written by the Python package, through rerun-sdk. Rerun's SDK for Rust
/// would add a few hundred crates (Arrow, its own protocol) to every build of the CLI for one
/// export; the Python one is a wheel that users of Rerun already have. Its summary.
fn rerun(map: &Path, out: &Path, max_points: Option<u64>) -> anyhow::Result<serde_json::Value> {
    let python = rerun_python();
    let run = std::process::Command::new(&python)
        .args(["-m", "sfpmap.viz"])
        .arg(map)
        .arg("-o")
        .arg(out)
        .args(["--force", "--json"])
        .args(max_points.map(|n| format!("--max-points={n}")))
        .stdin(std::process::Stdio::null())
        .output()
        .with_context(|| {
            format!(
                "{}: running {} for --rerun (set SFPMAP_PYTHON to a Python with the sfpmap package)",
                sfpmap::escape::path(out),
                Path::new(&python).display()
            )
        })?;
    if !run.status.success() {
        let stderr = String::from_utf8_lossy(&run.stderr);
        let why = stderr
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .unwrap_or("it failed")
            .trim_start_matches("error: ");
        let hint = if stderr.contains("No module named") {
            RERUN_HINT
        } else {
            ""
        };
        bail!("{}: {why}{hint}", sfpmap::escape::path(out));
    }
    serde_json::from_slice(&run.stdout)
        .with_context(|| format!("{}: sfpmap.viz's summary", sfpmap::escape::path(out)))
}

/// A kapture export's error, named with the map where it is about the map.
#[cfg(feature = "colmap")]
fn kapture_error(map: &Path, e: sfpmap::io::kapture::KaptureError) -> anyhow::Error {
    use sfpmap::io::kapture::KaptureError;
    match e {
        KaptureError::Map(e) => super::naming(map)(e),
        // What of the map kapture cannot hold: named with the map it is in.
        e @ KaptureError::Unwritable { .. } => {
            anyhow::anyhow!("{}: {e}", sfpmap::escape::path(map))
        }
        e => anyhow::Error::new(e),
    }
}

/// The `--json` entry and the line of a model written to `dir` (COLMAP text or kapture):
/// its cameras, images, points and observations; `what` leads the counts in the line.
fn model_written(
    dir: &Path,
    what: &str,
    [cameras, images, points, observations]: [usize; 4],
) -> (serde_json::Value, String) {
    let entry = json!({"path": dir.display().to_string(), "cameras": cameras, "images": images, "points": points, "observations": observations});
    let line = format!(
        "{}: {what}{cameras} cameras, {images} images, {points} points, {observations} observations",
        sfpmap::escape::path(dir)
    );
    (entry, line)
}
