//! `sfpmap extract`: SFP keypoints and descriptors of images into an hloc-style features.h5.

use anyhow::{bail, Context};
use serde_json::json;
use sfpmap::extract::{image, runtime, DetectOptions, Extractor, ExtractorOptions, GlobalSize};
use sfpmap::io::features_h5::{self, H5Options};
use sfpmap::progress::Reporter;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

/// Extract per-level keypoints, short/full descriptors and a global descriptor from images.
///
/// Writes hloc's `features.h5` layout: one group per image name (relative to the folder given)
/// with `keypoints` [N×2], `descriptors` [D×N] (f16), `scores`, `image_size` of the `--level`
/// level, and `level<id>_…` datasets for every level (spec/extractor.md, "features.h5 layout"). The
/// model is the embedded sfp-v3 unless `--model` is given; ONNX Runtime is fetched on first
/// use (see `sfpmap setup`). Example: `sfpmap extract images/ -o features.h5`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Image folders (searched recursively for .jpg/.jpeg/.png) and/or image files.
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Output features.h5.
    #[arg(short, long)]
    pub output: PathBuf,
    /// An ONNX model of the sfp-extractor/1, /2 or /3 contract or a built-in model's name
    /// (sfp-v3, sfp-v2, sfp-v1, sfp-v2s, aliked-n16); default: the built-in sfp-v3.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// ONNX Runtime intra-op threads (capped at 4 per core, at most 256, with a warning).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..))]
    pub threads: u32,
    /// Resize images so the longer side is at most this (keypoints are scaled back).
    #[arg(long, value_parser = clap::value_parser!(u32).range(16..))]
    pub resize_max: Option<u32>,
    /// Score threshold after NMS, on every level (a score in [0, 1]; default: the model's
    /// sfp.default_threshold of each level).
    #[arg(long, value_parser = super::args::score)]
    pub threshold: Option<f32>,
    /// NMS radius in cells, 0 to 64 (0: no suppression; default: the model's).
    #[arg(long, value_parser = clap::value_parser!(u32).range(0..=i64::from(sfpmap::extract::contract::MAX_NMS_RADIUS)))]
    pub nms_radius: Option<u32>,
    /// Keypoints per level, finest first: one number for all levels, or one per level (each
    /// 1 to 1000000).
    #[arg(long, value_delimiter = ',',
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=sfpmap::extract::contract::MAX_KEYPOINTS as u64))]
    pub max_keypoints: Option<Vec<usize>>,
    /// The level whose features fill each group's hloc datasets (default: 2, else the middle one).
    #[arg(long)]
    pub level: Option<u16>,
    /// Overwrite OUTPUT if it exists.
    #[arg(long)]
    pub force: bool,
    /// The longer side of the copy each image's global descriptor is computed on (images
    /// larger than that are downscaled for it: one more, smaller, inference); 0: the network
    /// input itself. Stored as `sfp.global_max_side`; match the map's (`sfpmap info`).
    #[arg(long, default_value_t = sfpmap::extract::GLOBAL_MAX_SIDE,
          value_parser = super::global_max_side)]
    pub global_max_side: u32,
    /// Keep keypoints where the quadratic fit on their own score map puts them: no
    /// coarse-to-fine refinement of levels 2 and deeper, and no refinement on the image of an
    /// sfp-extractor/2 or /3 model (spec/extractor.md steps 4 and 5).
    #[arg(long)]
    pub no_refine: bool,
    /// Print one JSON object: images, keypoints per level, ms per image, output bytes.
    #[arg(long)]
    pub json: bool,
}

fn is_image(p: &Path) -> bool {
    p.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "jpg" | "jpeg" | "png"))
}

fn walk(dir: &Path, root: &Path, out: &mut Vec<(String, PathBuf)>) -> anyhow::Result<()> {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| sfpmap::escape::path(dir).to_string())?
        .map(|e| e.map(|e| e.path()))
        .collect::<Result<_, _>>()
        .with_context(|| sfpmap::escape::path(dir).to_string())?;
    entries.sort();
    for p in entries {
        if p.is_dir() {
            walk(&p, root, out)?;
        } else if is_image(&p) {
            let name = p
                .strip_prefix(root)
                .unwrap_or(&p)
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect::<Vec<_>>()
                .join("/");
            out.push((name, p));
        }
    }
    Ok(())
}

/// (name in the file, path) for every input image.
pub fn collect_images(inputs: &[PathBuf]) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let mut images = Vec::new();
    for input in inputs {
        if input.is_dir() {
            walk(input, input, &mut images)?;
        } else if input.is_file() {
            let name = input
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            images.push((name, input.clone()));
        } else {
            bail!("{}: no such file or folder", sfpmap::escape::path(input));
        }
    }
    if images.is_empty() {
        bail!("no .jpg/.jpeg/.png images in the inputs given");
    }
    Ok(images)
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    runtime::disable_telemetry();
    let images = collect_images(&args.inputs)?;
    let inputs: Vec<&Path> = images
        .iter()
        .map(|(_, p)| p.as_path())
        .chain(args.model.as_deref())
        .collect();
    // A folder of images gets nothing new inside it (its next walk would find the output).
    let folders: Vec<&Path> = args
        .inputs
        .iter()
        .filter(|p| p.is_dir())
        .map(PathBuf::as_path)
        .collect();
    sfpmap::output::check_outside(&args.output, &folders)?;
    super::check_outputs(&[&args.output], &inputs, args.force)?;
    let bars = super::Bars::new(quiet, args.json);
    let threads = super::cap_threads(args.threads as usize, &bars);
    let mut extractor = Extractor::new(
        &ExtractorOptions {
            model: args.model.clone(),
            threads,
        },
        &bars,
    )?;
    let contract = extractor.contract().clone();
    let main_level = match args.level {
        Some(l) if contract.level_index(l).is_some() => l,
        Some(l) => bail!(
            "--level {l}: the model's levels are {:?}",
            contract.level_ids
        ),
        None if contract.level_index(2).is_some() => 2,
        None => contract.level_ids[contract.levels() / 2],
    };
    let detect = DetectOptions {
        threshold: args.threshold,
        nms_radius: args.nms_radius,
        max_keypoints: args.max_keypoints.clone(),
        refine: Some(!args.no_refine),
        // As convert records it: after `--resize-max`, the effective side.
        global: GlobalSize::from_flag(args.global_max_side)
            .map_err(anyhow::Error::msg)?
            .effective(args.resize_max),
    };
    let mut results = Vec::with_capacity(images.len());
    // Per image: the extraction (network + keypoints and descriptors) and its parts, and the
    // decode before it (file read, decode, grey conversion, resize).
    let mut ms = Vec::with_capacity(images.len());
    let (mut decode_ms, mut network_ms, mut keypoints_ms, mut global_ms) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let since = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
    bars.start("extracting", Some(images.len() as u64));
    for (name, path) in &images {
        let t = Instant::now();
        let input = image::load(path, contract.gray_weights, args.resize_max)?;
        decode_ms.push(since(t));
        let t = Instant::now();
        let dense = extractor.run(&input).map_err(|e| e.on_image(path))?;
        network_ms.push(since(t));
        let t_kp = Instant::now();
        let mut features = extractor
            .features(&dense, input.original_size, &detect)
            .map_err(|e| e.on_image(path))?;
        keypoints_ms.push(since(t_kp));
        let t_global = Instant::now();
        features.global = extractor
            .global(&input, &dense, detect.global)
            .map_err(|e| e.on_image(path))?;
        global_ms.push(since(t_global));
        ms.push(since(t));
        results.push((name.clone(), features));
        bars.advance(1);
    }
    bars.finish();
    let model = extractor.model().clone();
    let mut attributes = vec![
        ("sfp.model".to_string(), model.name.clone()),
        ("sfp.model_xxh3".to_string(), model.xxh3.clone()),
        ("sfp.model_name".to_string(), contract.model_name.clone()),
        ("sfp.contract".to_string(), contract.version.to_string()),
        (
            "sfp.tool".to_string(),
            sfpmap::format::Metadata::tool_string(),
        ),
    ];
    // Whether keypoints were refined (spec/extractor.md steps 4 and 5).
    attributes.push(("sfp.refine".to_string(), (!args.no_refine).to_string()));
    // The size `global_descriptor` was computed at; 0: the network input (metadata
    // `global_max_side` of a map; spec/extractor.md). A model without a global head (ALIKED)
    // writes no `global_descriptor`, so no size either.
    if contract.global_dim > 0 {
        attributes.push((
            "sfp.global_max_side".to_string(),
            detect.global.side().to_string(),
        ));
    }
    attributes.push((
        "sfp.level_ids".to_string(),
        contract
            .level_ids
            .iter()
            .map(|l| l.to_string())
            .collect::<Vec<_>>()
            .join(","),
    ));
    let bytes = features_h5::write(
        &args.output,
        &results,
        &H5Options {
            main_level,
            attributes,
        },
    )?;
    let median_of = |v: &[f64]| {
        let mut sorted = v.to_vec();
        sorted.sort_by(f64::total_cmp);
        sorted[sorted.len() / 2]
    };
    let median = median_of(&ms);
    let per_level: Vec<_> = contract
        .level_ids
        .iter()
        .map(|&l| {
            let n: usize = results
                .iter()
                .map(|(_, f)| f.level(l).map_or(0, |x| x.len()))
                .sum();
            (l, n)
        })
        .collect();
    if args.json {
        super::print_json(&json!({
            "output": args.output.display().to_string(),
            "output_bytes": bytes,
            "images": results.len(),
            "main_level": main_level,
            "keypoints": per_level.iter().map(|(l, n)| json!({"level": l, "keypoints": n})).collect::<Vec<_>>(),
            "ms_per_image": ms,
            "ms_median": median,
            // medians of the parts; ms_per_image = network + keypoints_descriptors + global
            // (the downscaled copy's inference, 0 when the image fits `global_max_side`)
            "ms_median_parts": {
                "decode": median_of(&decode_ms),
                "network": median_of(&network_ms),
                "keypoints_descriptors": median_of(&keypoints_ms),
                "global": median_of(&global_ms),
            },
            "global_max_side": detect.global.side(),
            "threads": threads,
            "model": model.name,
            "model_xxh3": model.xxh3,
        }))?;
    } else if !quiet {
        println!(
            "{}: {} images, {} bytes; median {median:.1} ms per image ({} threads: network {:.1}, \
             keypoints and descriptors {:.1}, global {:.1}; decode before it {:.1})",
            sfpmap::escape::path(&args.output),
            results.len(),
            bytes,
            threads,
            median_of(&network_ms),
            median_of(&keypoints_ms),
            median_of(&global_ms),
            median_of(&decode_ms)
        );
        for (l, n) in per_level {
            println!(
                "level {l}: {n} keypoints ({:.0} per image)",
                n as f64 / results.len() as f64
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
