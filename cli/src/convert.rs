//! `sfpmap convert`: a COLMAP model (+ database.db) into a map.

use super::slice::CodecArg;
use sfpmap::build::{convert, Aggregate, ConvertOptions};
use sfpmap::format::Codec;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum AggregateArg {
    Mean,
    Medoid,
}

/// Convert a COLMAP model (binary or text) or a kapture folder into a map, with descriptors
/// from its database, an hloc features file, the kapture folder's own, or an extractor.
///
/// With --database, each 3D point gets its track's aggregated descriptor of the database's
/// feature (SIFT, or the type COLMAP 4 recorded: ALIKED, LoMa); points with keypoint scales
/// (SIFT's) are split into 3 levels by scale, others make one level; each level's
/// descriptors are stored in a PCA basis so that `short` (the first --short-dims dims) keeps
/// most of the variance. Without descriptors the map is geometry only. Example:
/// `sfpmap convert --colmap sparse/0 --database database.db -o building.sfpm`
///
/// With --features instead of --database, the descriptors are any local feature's from an hloc
/// features.h5 (one level unless the file has keypoint scales), and --global-features stores
/// each image's global descriptor for retrieval. Example:
/// `sfpmap convert --colmap sfm --features feats-aliked-n16.h5 -o aliked.sfpm`
///
/// With --kapture instead of --colmap, the model, keypoints and descriptors are the kapture
/// folder's (--keypoints-type, --descriptors-type choose among several). Example:
/// `sfpmap convert --kapture mapping -o mapping.sfpm`
///
/// With --images instead of --database, an extractor runs on every model image: the built-in
/// SFP model gives each point multi-level descriptors (points it scores low on every level
/// are dropped), `--model aliked-n16` one level of ALIKED's. Example:
/// `sfpmap convert --colmap sparse/0 --images images -o sfp.sfpm`
#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model folder (cameras, images, points3D as .bin or .txt).
    #[arg(long, required_unless_present = "kapture")]
    pub colmap: Option<PathBuf>,
    /// A kapture folder instead of a model and its features: cameras, records and
    /// trajectories, points3d and observations, and its keypoints and descriptors (none: a
    /// geometry map). Example: `sfpmap convert --kapture maupertuis/ -o maupertuis.sfpm`
    #[arg(long, value_name = "DIR", conflicts_with_all = ["colmap", "database"])]
    pub kapture: Option<PathBuf>,
    /// With --kapture: the keypoints type to read (a folder of reconstruction/keypoints;
    /// default: the only one there).
    #[arg(long, value_name = "TYPE", requires = "kapture")]
    pub keypoints_type: Option<String>,
    /// With --kapture: the descriptors type to read (default: the only one of those
    /// keypoints).
    #[arg(long, value_name = "TYPE", requires = "kapture")]
    pub descriptors_type: Option<String>,
    /// The COLMAP database with the model's keypoints and descriptors (opened read-only):
    /// SIFT, or a learned feature by its descriptor type (COLMAP 4's ALIKED).
    #[arg(long)]
    pub database: Option<PathBuf>,
    /// An hloc features.h5 with the model's keypoints and descriptors by image name (hloc's
    /// layout: keypoints N x 2, pixel centres at integers; descriptors D x N, f16 or f32).
    #[cfg(feature = "hdf5")]
    #[arg(long, conflicts_with = "database")]
    pub features: Option<PathBuf>,
    /// With --features or --kapture: the feature's name the map records, which query
    /// features must match (default: the file's sfp.model_name, or the conf of hloc's
    /// feats-CONF.h5, or kapture's descriptors type).
    #[cfg(feature = "hdf5")]
    #[arg(long)]
    pub feature_name: Option<String>,
    /// An hloc global-feats.h5 (global_descriptor per image name): every map image's global
    /// descriptor, stored for retrieval and preferred to VLAD.
    #[cfg(feature = "hdf5")]
    #[arg(long)]
    pub global_features: Option<PathBuf>,
    /// The model's images: build an SFP map with the extractor instead of SIFT descriptors
    /// (levels chosen by the network's scores; see spec/extractor.md).
    #[cfg(feature = "onnx")]
    #[arg(long, conflicts_with_all = ["database", "features", "global_features", "short_dims", "aggregate", "strict", "memory"])]
    pub images: Option<PathBuf>,
    /// With --images: an ONNX model of the sfp-extractor/1, /2 or /3 contract or a built-in
    /// model's name (sfp-v3, sfp-v2, sfp-v1, sfp-v2s, aliked-n16); default: the built-in sfp-v3.
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images")]
    pub model: Option<PathBuf>,
    /// With --images: skip model images whose file is missing (default: error naming them).
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images")]
    pub allow_missing: bool,
    /// With --images: ONNX Runtime intra-op threads (capped at 4 per core, at most 256, with a
    /// warning).
    #[cfg(feature = "onnx")]
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..))]
    pub threads: u32,
    /// With --images: resize images so the longer side is at most this before the network.
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images", value_parser = clap::value_parser!(u32).range(16..))]
    pub resize_max: Option<u32>,
    /// With --images: the longer side of the copy each image's global descriptor (retrieval)
    /// is computed on; 0: the network input itself; else at least 16. The map records it (at
    /// most --resize-max); localize follows it.
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images", default_value_t = sfpmap::extract::GLOBAL_MAX_SIDE,
          value_parser = super::global_max_side)]
    pub global_max_side: u32,
    /// With --images: a point joins level i when its track's mean level-i score is at least
    /// this, on every level (a score in [0, 1]; default: the model's keypoint threshold of
    /// each level, sfp.default_threshold).
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images", value_parser = super::args::score)]
    pub score_threshold: Option<f32>,
    /// With --images (a pyramid model): move observations to the level-2 keypoint the network
    /// detects within 4 px of them (one observation a keypoint), and a point with 2 or more
    /// moved observations that re-triangulate within 2 px (rays at 2 degrees or more) to
    /// there, described there on level 2: the map's points where queries' keypoints are.
    /// Other points stay. Twice the memory of the descriptor sums while converting.
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images")]
    pub snap: bool,
    /// With --images (a pyramid model): the map's points are the network's own level-2
    /// keypoints (the deepest level of a shallower model), matched between each image and the
    /// 20 it shares the most model points with (mutual nearest neighbours, Sampson distance
    /// to the poses' epipolar geometry at most 4 network input px) and triangulated with the
    /// model's poses where 2 or more views agree within 2 px (rays at 2 degrees or more), as hloc
    /// triangulates from a reference model. The model's points only pick the image pairs.
    /// Runs the network twice per image.
    #[cfg(feature = "onnx")]
    #[arg(long, requires = "images", conflicts_with = "snap")]
    pub triangulate: bool,
    /// Output map.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Dimensions of the short descriptor block (default: a quarter of the full dimension).
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub short_dims: Option<u32>,
    /// How sections are stored: raw (read in place, zero-copy) or zstd (smaller, decoded on read).
    #[arg(long, value_enum, default_value = "raw")]
    pub codec: CodecArg,
    /// zstd level when `--codec zstd`.
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(i32).range(1..=22))]
    pub zstd_level: i32,
    /// How a point's descriptor is made from its track's.
    #[arg(long, value_enum, default_value = "mean")]
    pub aggregate: AggregateArg,
    /// Fail if an image's features are missing from the database, features file or kapture
    /// folder (default: warn and go on).
    #[arg(long)]
    pub strict: bool,
    /// Retrieval: centroids of the VLAD codebook stored with the map (0: none). Queries are
    /// ranked against the map's images by their VLAD of the same level's descriptors.
    #[arg(long, value_parser = vlad_clusters, long_help = vlad_help("centroids of the VLAD codebook stored with the map (0: none); queries are ranked against the map's images by their VLAD of the same level's descriptors", |(c, _)| c))]
    pub vlad_clusters: Option<usize>,
    /// Retrieval: lists of the image index stored over the rows the map ranks its images
    /// with (format 1.3; 0: none; at most one per image), with each image's 16 neighbours
    /// (1.4: the images sharing most points) and the lists grown along them as places of
    /// about images / LISTS images. Default: from 2000 images, places of 24 images (at
    /// most 8192 lists; without neighbours, about √images k-means lists), stored only where
    /// a query would then score at most a quarter of the images, centroids included; a query
    /// scores the centroids, a few lists and their best images' neighbours instead of every
    /// image.
    #[arg(long, value_name = "LISTS", value_parser = index_lists)]
    pub index_lists: Option<usize>,
    /// Product-quantise every level into M one-byte codes per point (M dividing each level's
    /// dims; format 1.1). `sfpmap slice --pq` does it for some levels of a map.
    #[arg(long, value_name = "M", value_parser = clap::value_parser!(u16).range(1..=4096))]
    pub pq: Option<u16>,
    /// Retrieval: leading dimensions of the level basis the codebook covers (at most the
    /// level's short dimensions).
    #[arg(long, value_parser = vlad_dims, long_help = vlad_help("leading dimensions of the level basis the codebook covers (at most the level's short dimensions)", |(_, d)| d))]
    pub vlad_dims: Option<usize>,
    /// Memory the conversion may use, such as 4GB (default: half of the machine's or the
    /// container's). Where the points seen at once need more, the features are read once per
    /// range of points (at most 64 times); the map is the same bytes whatever the budget. A
    /// budget too small is refused once the model, one image's features and any global
    /// features are read, before the rest, naming the smallest that works. Scratch files beside OUTPUT take up to
    /// points x dims x 6 bytes of disk meanwhile.
    #[arg(long, value_name = "SIZE", value_parser = super::args::byte_size)]
    pub memory: Option<u64>,
    /// Overwrite OUTPUT if it exists.
    #[arg(long)]
    pub force: bool,
    /// Print one JSON object: points, images, input_bytes, output_bytes, ratio, seconds,
    /// levels, and memory (budget, passes: reads of the features, planned_peak; bytes).
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, quiet: bool) -> anyhow::Result<ExitCode> {
    let start = Instant::now();
    check_output(&args)?;
    #[cfg(feature = "onnx")]
    if let Some(images) = &args.images {
        return run_sfp(&args, images, quiet, start);
    }
    #[allow(unused_mut)] // set below with `hdf5`
    let mut options = ConvertOptions {
        database: args.database.clone(),
        features: None,
        feature_name: None,
        global_features: None,
        short_dims: args.short_dims,
        codec: Codec::from(args.codec),
        zstd_level: args.zstd_level,
        aggregate: match args.aggregate {
            AggregateArg::Mean => Aggregate::Mean,
            AggregateArg::Medoid => Aggregate::Medoid,
        },
        strict: args.strict,
        vlad: vlad_options(&args),
        pq: args.pq.map(usize::from),
        job: None,
        memory: args.memory,
    };
    #[cfg(feature = "hdf5")]
    {
        if args.feature_name.is_some() && args.features.is_none() && args.kapture.is_none() {
            anyhow::bail!("--feature-name names the features of --features or --kapture");
        }
        options.features = args.features.clone();
        options.feature_name = args.feature_name.clone();
        options.global_features = args.global_features.clone();
    }
    let bars = super::Bars::new(quiet, args.json);
    // Errors name the file at fault themselves.
    let summary = match (&args.colmap, &args.kapture) {
        (Some(colmap), _) => convert(colmap, &options, &args.output, &bars)?,
        (None, Some(kapture)) => convert_kapture(&args, kapture, &options, &bars)?,
        (None, None) => anyhow::bail!("pass --colmap or --kapture"),
    };
    let seconds = start.elapsed().as_secs_f64();
    let ratio = summary.input_bytes as f64 / summary.output_bytes.max(1) as f64;
    if args.json {
        super::print_json(&summary.report(&args.output, seconds))?;
    } else if !quiet {
        println!(
            "{}: {} points, {} images, {} observations; {} bytes in -> {} bytes out ({ratio:.2}x) in {seconds:.2} s",
            sfpmap::escape::path(&args.output),
            summary.points,
            summary.images,
            summary.observations,
            summary.input_bytes,
            summary.output_bytes
        );
        for l in &summary.levels {
            println!(
                "level {}: {} points, scales {:.1}-{:.1} px, short {}/{} dims keeps {:.1} % of the variance",
                l.level,
                l.points,
                l.scale_range[0],
                l.scale_range[1],
                l.dim_short,
                l.dim_full,
                100.0 * l.variance_short
            );
        }
        if summary.geometry_only {
            println!("geometry only (no descriptors given or found): no levels");
        }
        if let Some(v) = summary.vlad {
            println!(
                "retrieval: VLAD of {} centroids x {} dims on level {}",
                v.clusters, v.dims, v.level
            );
        }
        if let Some(i) = &summary.index {
            if i.stored {
                println!(
                    "image index: {} lists over {}, {} probed, about {} images scored a query (calibration recall {:.3})",
                    i.lists,
                    i.of.name(),
                    i.probe,
                    i.scored,
                    i.recall
                );
            } else {
                println!(
                    "image index: none (recall {:.3} of ranking every image took {} of {} lists, {} of the {} images: the images' {} rows have no neighbours an index could group)",
                    i.recall,
                    i.probe,
                    i.lists,
                    i.scored,
                    summary.images,
                    i.of.name()
                );
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `--vlad-clusters`/`--vlad-dims` help: `what`, then the default by the map's image count
/// (`pick` takes it from a (clusters, dims) shape), from the library's rule.
fn vlad_help(what: &str, pick: fn((usize, usize)) -> usize) -> String {
    let large = sfpmap::vlad::LARGE_MAP_IMAGES;
    use sfpmap::vlad::{default_shape, DescribedAt};
    let own = |images| pick(default_shape(images, DescribedAt::OwnKeypoints));
    let (small, observed) = (
        own(0),
        pick(default_shape(0, DescribedAt::ModelObservations)),
    );
    let observed = if observed == small {
        String::new()
    } else {
        format!(
            "; at least {observed} for a descriptor head describing the model's observations \
             (--model aliked-n16)"
        )
    };
    format!(
        "Retrieval: {what}. [default: {small}, or {} from {large} images on{observed}]",
        own(large),
    )
}

fn vlad_options(args: &Args) -> sfpmap::build::VladOptions {
    sfpmap::build::VladOptions {
        clusters: args.vlad_clusters,
        dims: args.vlad_dims,
        index_lists: args.index_lists,
    }
}

/// At most as many lists as the index's k-means learns from rows.
fn index_lists(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if n <= sfpmap::build::MAX_INDEX_LISTS => Ok(n),
        _ => Err(format!(
            "a number of lists from 0 (no index) to {}",
            sfpmap::build::MAX_INDEX_LISTS
        )),
    }
}

/// At most [`sfpmap::vlad::MAX_CLUSTERS`] centroids.
fn vlad_clusters(s: &str) -> Result<usize, String> {
    let most = sfpmap::vlad::MAX_CLUSTERS;
    match s.parse::<usize>() {
        Ok(n) if n <= most => Ok(n),
        _ => Err(format!("a number of centroids from 0 (no VLAD) to {most}")),
    }
}

fn vlad_dims(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if (1..=256).contains(&n) => Ok(n),
        _ => Err("a number of dimensions from 1 to 256".into()),
    }
}

/// The output policy, with every file convert reads as an input: the model files, the
/// database, the extractor's model and, with `--images`, an existing output inside the
/// images folder (it may be a model image: refused rather than read the model twice).
fn check_output(args: &Args) -> anyhow::Result<()> {
    let mut model = match &args.colmap {
        Some(colmap) => sfpmap::colmap::model_files(colmap)
            .map(|f| f.paths)
            .unwrap_or_default(),
        None => Vec::new(),
    };
    model.extend(
        args.kapture
            .iter()
            .flat_map(|k| sfpmap::io::kapture::tables(k)),
    );
    let mut inputs: Vec<&std::path::Path> = model.iter().map(|p| p.as_path()).collect();
    inputs.extend(args.database.as_deref());
    #[cfg(feature = "hdf5")]
    inputs.extend(
        args.features
            .iter()
            .chain(&args.global_features)
            .map(|p| p.as_path()),
    );
    #[cfg(feature = "onnx")]
    inputs.extend(args.model.as_deref());
    // A folder input (the model's images, a kapture folder with files its tables do not list)
    // gets nothing new inside it.
    let folders: Vec<&std::path::Path> = args.kapture.iter().map(|p| p.as_path()).collect();
    #[cfg(feature = "onnx")]
    let folders = [folders, args.images.iter().map(|p| p.as_path()).collect()].concat();
    sfpmap::output::check_outside(&args.output, &folders)?;
    super::check_outputs(&[&args.output], &inputs, args.force)
}

#[cfg(feature = "onnx")]
fn run_sfp(
    args: &Args,
    images: &std::path::Path,
    quiet: bool,
    start: Instant,
) -> anyhow::Result<ExitCode> {
    use sfpmap::build::{convert_with_images, SfpMapOptions};
    use sfpmap::extract::{ExtractorOptions, GlobalSize};
    sfpmap::extract::runtime::disable_telemetry();
    let bars = super::Bars::new(quiet, args.json);
    let options = SfpMapOptions {
        images: images.to_path_buf(),
        extractor: ExtractorOptions {
            model: args.model.clone(),
            threads: super::cap_threads(args.threads as usize, &bars),
        },
        resize_max: args.resize_max,
        global_max_side: GlobalSize::from_flag(args.global_max_side)
            .map_err(anyhow::Error::msg)?
            .max_side(),
        score_threshold: args.score_threshold,
        allow_missing: args.allow_missing,
        snap: args.snap,
        triangulate: args.triangulate,
        codec: Codec::from(args.codec),
        zstd_level: args.zstd_level,
        vlad: vlad_options(args),
        pq: args.pq.map(usize::from),
        job: None,
    };
    let colmap = args.colmap.as_deref().ok_or_else(|| {
        anyhow::anyhow!("--images builds from a COLMAP model: pass --colmap, not --kapture")
    })?;
    let summary = convert_with_images(colmap, &options, &args.output, &bars)?;
    let seconds = start.elapsed().as_secs_f64();
    let c = &summary.convert;
    let ratio = c.input_bytes as f64 / c.output_bytes.max(1) as f64;
    if args.json {
        super::print_json(&summary.report(&args.output, seconds))?;
    } else if !quiet {
        println!(
            "{}: {} of {} points kept, {} images, {} observations; model {} bytes -> map {} bytes ({ratio:.2}x) in {seconds:.1} s ({:.0} ms per image)",
            sfpmap::escape::path(&args.output),
            c.points,
            summary.model_points,
            c.images,
            c.observations,
            c.input_bytes,
            c.output_bytes,
            summary.ms_per_image
        );
        for l in &c.levels {
            println!(
                "level {} (stride {}): {} points, short {}/{} dims ({:.1} % of the energy)",
                l.level,
                l.scale_range[0],
                l.points,
                l.dim_short,
                l.dim_full,
                100.0 * l.variance_short
            );
        }
        if !summary.missing_images.is_empty() {
            println!("{} images missing (skipped)", summary.missing_images.len());
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `convert --kapture`: the folder's model and features through the SIFT path.
fn convert_kapture(
    args: &Args,
    dir: &std::path::Path,
    options: &ConvertOptions,
    bars: &super::Bars,
) -> anyhow::Result<sfpmap::build::ConvertSummary> {
    if options.features.is_some() {
        anyhow::bail!("--kapture holds its own features: drop --features");
    }
    let kapture_options = sfpmap::io::kapture::KaptureOptions {
        keypoints_type: args.keypoints_type.clone(),
        descriptors_type: args.descriptors_type.clone(),
    };
    Ok(sfpmap::build::convert_kapture(
        dir,
        &kapture_options,
        options,
        &args.output,
        bars,
    )?)
}
