//! `sfpmap demo`: the whole pipeline on a built-in synthetic scene, nothing downloaded.

use anyhow::Context;
use serde_json::json;
use sfpmap::build::{convert_with_images, SfpMapOptions};
use sfpmap::demo::{write_png, DemoScene, HEIGHT, WIDTH};
use sfpmap::extract::{DetectOptions, Extractor, ExtractorOptions};
use sfpmap::format::{slice, SliceOptions};
use sfpmap::io::plot::{plot_map, PlotOptions};
use sfpmap::io::poses::read_poses;
use sfpmap::io::queries::{read_query_list, sfp_query};
use sfpmap::localize::eval::{evaluate, map_scale, median};
use sfpmap::localize::{LocalizeOptions, Localizer};
use sfpmap::progress::Reporter;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

/// Run the whole pipeline on a built-in scene: render a textured room from known poses, write
/// a COLMAP model of the database images, convert it with the SFP model, slice it to level 2
/// short, localize the query images with both maps and print the evaluation.
///
/// Example: `sfpmap demo --out demo/`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Folder for the scene, maps and poses (default: a `sfpmap-demo` folder in the system
    /// temp folder).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Scene seed.
    #[arg(long, default_value_t = 7)]
    pub seed: u32,
    /// Overwrite the files of an earlier run in OUT (implied without --out: the default folder
    /// is the demo's own).
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object with the results.
    #[arg(long)]
    pub json: bool,
}

struct Variant {
    name: &'static str,
    map: PathBuf,
    short: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let start = Instant::now();
    let out = args
        .out
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join("sfpmap-demo"));
    let images = out.join("images");
    let sparse = out.join("sparse");
    let scene = DemoScene::new(args.seed);
    let outputs: Vec<PathBuf> = scene
        .database
        .iter()
        .chain(&scene.queries)
        .map(|(name, _)| images.join(name))
        .chain(["cameras.txt", "images.txt", "points3D.txt"].map(|f| sparse.join(f)))
        .chain(
            [
                "queries.txt",
                "gt_poses.txt",
                "demo.sfpm",
                "demo-l2-short.sfpm",
                "poses.txt",
                "plot.png",
            ]
            .map(|f| out.join(f)),
        )
        .collect();
    let outputs: Vec<&Path> = outputs.iter().map(|p| p.as_path()).collect();
    super::check_outputs(&outputs, &[], args.force || args.out.is_none())?;
    for dir in [&images, &sparse] {
        std::fs::create_dir_all(dir).with_context(|| sfpmap::escape::path(dir).to_string())?;
    }
    let bars = super::Bars::new(quiet, args.json);
    let say = |line: String| {
        if !quiet && !args.json {
            println!("{line}");
        }
    };

    // 1. The scene: render every image (two threads), write the model and the query files.
    let views: Vec<(&String, _)> = scene
        .database
        .iter()
        .chain(&scene.queries)
        .map(|(n, p)| (n, p))
        .collect();
    bars.start("rendering", Some(views.len() as u64));
    let next = std::sync::atomic::AtomicUsize::new(0);
    let failed = std::sync::Mutex::new(None);
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some((name, pose)) = views.get(i) else {
                    break;
                };
                let pixels = scene.render(pose);
                if let Err(e) = write_png(&images.join(name), WIDTH, HEIGHT, &pixels) {
                    failed
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .get_or_insert(e);
                }
                bars.advance(1);
            });
        }
    });
    bars.finish();
    if let Some(e) = failed.into_inner().unwrap_or_else(|p| p.into_inner()) {
        // Names the image already.
        return Err(e.into());
    }
    let (cameras, images_txt, points) = scene.colmap_text();
    write(&sparse.join("cameras.txt"), &cameras)?;
    write(&sparse.join("images.txt"), &images_txt)?;
    write(&sparse.join("points3D.txt"), &points)?;
    write(&out.join("queries.txt"), &scene.query_list())?;
    write(&out.join("gt_poses.txt"), &scene.gt_poses())?;
    let render_s = start.elapsed().as_secs_f64();
    say(format!(
        "scene: {} database + {} query images rendered, {} surface points ({render_s:.1} s) in {}",
        scene.database.len(),
        scene.queries.len(),
        scene.points.len(),
        sfpmap::escape::path(&out)
    ));

    // 2. Convert with the SFP model, then slice.
    let full = out.join("demo.sfpm");
    let sliced = out.join("demo-l2-short.sfpm");
    let options = SfpMapOptions::new(&images);
    let summary = convert_with_images(&sparse, &options, &full, &bars)?;
    let map = super::open_map(&full)?;
    // The queries' global descriptors are computed as the map's were.
    let detect = DetectOptions {
        global: sfpmap::extract::GlobalSize::of_map(map.metadata()),
        ..Default::default()
    };
    let (writer, _) = slice(
        &map,
        &SliceOptions {
            levels: vec![2],
            short: true,
            codec: None,
            zstd_level: 3,
            minimal: false,
        },
    )?;
    writer.write(&sliced, &bars)?;
    let model_bytes: u64 = ["cameras.txt", "images.txt", "points3D.txt"]
        .iter()
        .map(|f| std::fs::metadata(sparse.join(f)).map_or(0, |m| m.len()))
        .sum();
    say(format!(
        "convert: {} of {} model points kept in {} levels, {:.0} ms per image",
        summary.convert.points,
        summary.model_points,
        summary.convert.levels.len(),
        summary.ms_per_image
    ));

    // 3. Localize the queries with both maps.
    let queries = read_query_list(&out.join("queries.txt"), None)?;
    let gt = read_poses(&out.join("gt_poses.txt"))?;
    let mut extractor = Extractor::new(&ExtractorOptions::default(), &bars)?;
    let mut features = Vec::with_capacity(queries.len());
    for q in &queries {
        let path = images.join(&q.name);
        let input = sfpmap::extract::image::load(&path, extractor.contract().gray_weights, None)?;
        let extracted = extractor
            .extract(&input, &detect)
            .map_err(|e| e.on_image(&path))?;
        features.push(sfp_query(&extracted, &extractor));
    }
    let variants = [
        Variant {
            name: "SFP full",
            map: full.clone(),
            short: false,
        },
        Variant {
            name: "SFP level 2, short",
            map: sliced.clone(),
            short: true,
        },
    ];
    let mut rows = Vec::new();
    // The full map's poses and its plot, for the user to open.
    let (poses_txt, plot_png) = (out.join("poses.txt"), out.join("plot.png"));
    let mut plotted = None;
    say(String::new());
    say(format!(
        "{:<20} {:>9} {:>10} {:>13} {:>11} {:>12} {:>9}",
        "map", "MB", "localized", "median pos.", "median rot.", "pos. / cams", "ms/query"
    ));
    for v in &variants {
        let map = super::open_map(&v.map)?;
        let localizer = Localizer::new(
            &map,
            LocalizeOptions {
                short: v.short,
                ..LocalizeOptions::for_map(&map)
            },
        )?;
        let mut estimates = Vec::new();
        let mut ms = Vec::new();
        let mut results = Vec::with_capacity(queries.len());
        for (q, f) in queries.iter().zip(&features) {
            let r = localizer.localize(f, &q.camera)?;
            ms.push(r.times.total_ms);
            if let Some(p) = r.pose() {
                estimates.push((q.name.clone(), *p));
            }
            results.push(r);
        }
        if plotted.is_none() {
            super::localize::write_poses(
                &poses_txt,
                super::localize::PoseFormat::Colmap,
                &out.join("queries.txt"),
                &queries,
                &results,
                &[],
            )?;
            let centres = |poses: &[(String, sfpmap::geometry::Pose)]| {
                poses
                    .iter()
                    .map(|(n, p)| (n.clone(), p.center().into()))
                    .collect::<Vec<_>>()
            };
            let options = PlotOptions {
                title: format!(
                    "sfpmap demo, {}: localized (estimated) and true query cameras",
                    v.name
                ),
                estimated: centres(&estimates),
                ground_truth: centres(&gt),
                ..PlotOptions::default()
            };
            plotted = Some(
                plot_map(&map, &options, &plot_png)
                    .map_err(|e| anyhow::anyhow!("{}: {e}", sfpmap::escape::path(&plot_png)))?,
            );
        }
        let median_ms = median(ms).unwrap_or(f64::NAN);
        let e = evaluate(
            &estimates,
            &gt,
            &[(0.05, 1.0), (0.25, 2.0), (0.5, 5.0)],
            map_scale(&map)?,
        );
        let fmt = |v: Option<f64>, unit: &str| v.map_or("-".into(), |x| format!("{x:.3}{unit}"));
        say(format!(
            "{:<20} {:>9.3} {:>10} {:>13} {:>11} {:>12} {:>9.1}",
            v.name,
            map.file_len() as f64 / 1e6,
            format!("{}/{}", e.localized, e.queries),
            fmt(e.median_translation, " m"),
            fmt(e.median_rotation_deg, "°"),
            fmt(e.median_translation_rel.map(|r| 100.0 * r), " %"),
            median_ms
        ));
        let mut row = e.summary_json();
        row.insert("map".into(), json!(v.name));
        row.insert("map_bytes".into(), json!(map.file_len()));
        row.insert("median_ms".into(), json!(median_ms));
        rows.push(serde_json::Value::Object(row));
    }
    let seconds = start.elapsed().as_secs_f64();
    say(format!(
        "\nCOLMAP text model {:.2} MB; total {seconds:.1} s",
        model_bytes as f64 / 1e6
    ));
    say(format!(
        "poses of the full map: {}\nplot of the map with localized and true cameras: {}",
        sfpmap::escape::path(&poses_txt),
        sfpmap::escape::path(&plot_png)
    ));
    if args.json {
        super::print_json(&json!({
            "out": out.display().to_string(),
            "images": scene.database.len(),
            "queries": scene.queries.len(),
            "model_bytes": model_bytes,
            "results": rows,
            "poses": poses_txt.display().to_string(),
            "plot": plot_png.display().to_string(),
            "plot_pairs": plotted.as_ref().map(|s| s.pairs),
            "seconds": seconds,
        }))?;
    }
    // The demo is the README's main job and CI's smoke test of the whole pipeline: a run in
    // which a map localizes nothing is a failure, not a table of dashes.
    if let Some(row) = rows.iter().find(|r| r["localized"] == 0) {
        anyhow::bail!(
            "{}: the demo localized none of its {} queries with the {} map",
            sfpmap::escape::path(&out),
            scene.queries.len(),
            row["map"].as_str().unwrap_or("?")
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    super::write_atomic(path, |out| {
        Ok(std::io::Write::write_all(out, text.as_bytes())?)
    })
}
