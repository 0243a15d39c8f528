//! SFP maps from a COLMAP model and its images (`sfpmap convert --images`).
//!
//! The network runs once per model image. At every 2D observation of every 3D point, every
//! level's dense features are sampled bilinearly (and L2-normalised) and its score map is
//! sampled too. Per point and level, the track's features are aggregated by normalised mean
//! and the scores by mean. **Level assignment**: a point belongs to level i when its mean
//! level-i score is at least the threshold — by default the model's own keypoint threshold
//! of that level, `sfp.default_threshold` (0.5 for sfp-v1: the score is the probability of
//! the network's sparsity mask keeping that pixel, so ≥ 0.5 is the mask's more likely value),
//! so a map keeps a point on a level where the network would, on average, detect it there.
//! Points no level selects are dropped — the network's learned map compression.
//!
//! Each level stores the contract's `full` descriptor of its points (levels i.. parts, each
//! normalised, concatenated, normalised), so `short` (the first `C_i` dims) is the level's own
//! feature; descriptors stay in the extractor's basis (identity projection, no
//! `level_projection` section), so query descriptors from [`Extractor`] match them directly.
//!
//! A model with a descriptor head (`sfp.descriptor_head = sddh`, ALIKED-N16) describes each
//! image's observations in one run of its head and has one level and no global descriptor:
//! every described point is kept (unless `score_threshold` is given), the level is stored in
//! its uncentred PCA basis (`level_projection`, as SIFT maps; `short` = the leading quarter)
//! and retrieval is the VLAD of those leading dimensions.
//!
//! Two options (issue 36) put a pyramid model's points where a query's keypoints are:
//! `--snap` moves the model's observations onto the network's nearby keypoints
//! ([`super::snap`]); `--triangulate` replaces the model's points by the network's own
//! keypoints matched across the model's images and triangulated with its poses
//! ([`super::network_tracks`]: the network runs once more per image, before the pass above).

use super::basis::Basis;
use super::geometry::{map_index, Geometry};
use super::{read_model_with_sources, ConvertError, ConvertSummary, LevelSummary};
use crate::colmap::Reconstruction;
use crate::extract::contract::DescriptorHead;
use crate::extract::{
    contract, image, ExtractError, Extractor, ExtractorOptions, GlobalSize, ModelInfo,
    GLOBAL_MAX_SIDE,
};
use crate::format::{self, Codec, Descriptors, LevelInfo, Metadata, SourceFile};
use crate::progress::Reporter;
use serde_json::json;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The level rule, as recorded in each level's metadata.
pub(crate) const LEVEL_RULE: &str = "a point is in level i when the mean of score_d (bilinear at its observations; d = sfp.detect_level[i], the level whose map detects level i's keypoints, i itself unless the model says) over its track is >= the level's score_threshold; points in no level are dropped";

/// How [`convert_with_images`](super::convert_with_images) makes an SFP map from a model's images
/// (`sfpmap convert --images`).
#[derive(Debug, Clone)]
pub struct SfpMapOptions {
    /// Folder the model's image names are relative to.
    pub images: PathBuf,
    /// The extractor: its model and runtime.
    pub extractor: ExtractorOptions,
    /// Resize images so the longer side is at most this before the network.
    pub resize_max: Option<u32>,
    /// The longer side of the copy each image's global descriptor is computed on
    /// ([`GLOBAL_MAX_SIDE`] by default; `None`: the network input itself). The map records it
    /// (metadata `global_max_side`) and `localize` computes its queries' the same way.
    pub global_max_side: Option<u32>,
    /// Level assignment threshold on the mean score, for every level (`None` = the model's
    /// `sfp.default_threshold` of each level).
    pub score_threshold: Option<f32>,
    /// Skip model images whose file is missing (default: error).
    pub allow_missing: bool,
    /// (issue 36) Move observations to the network's keypoints near them and, where the moved
    /// observations agree, the point to their triangulation ([`super::snap`]); a pyramid
    /// model only. Holds a second copy of the points' snap-level descriptor sums meanwhile.
    pub snap: bool,
    /// (issue 36) Replace the model's points by the network's own keypoints matched across the
    /// model's covisible images and triangulated with its poses ([`super::network_tracks`]); a
    /// pyramid model only, not with `snap`. Runs the network twice per image.
    pub triangulate: bool,
    /// How the descriptor sections are stored.
    pub codec: Codec,
    /// zstd's level when `codec` is zstd.
    pub zstd_level: i32,
    /// Retrieval data besides the network's global descriptor: a VLAD codebook on level 2.
    pub vlad: super::VladOptions,
    /// Product-quantise every level into this many one-byte codes per point (format 1.1).
    pub pq: Option<usize>,
    /// The caller's record of the job that made the map (a batch job's place, input
    /// fingerprint and options), stored as `provenance.parameters.job`; `None`: no such key.
    pub job: Option<serde_json::Value>,
}

/// The level whose descriptors SFP maps' VLAD aggregates, when the map has it.
const VLAD_LEVEL: u16 = 2;

/// `short` of a descriptor head's level: this fraction of its dimensions (SIFT maps' rule).
const HEAD_SHORT_FRACTION: usize = 4;

/// The level rule of a model with a descriptor head (ALIKED: one level, no levels to choose
/// between), as recorded in the level's metadata.
const ONE_LEVEL_RULE: &str = "one level: every point with an observation whose mean score (bilinear at its observations) is >= score_threshold (0 unless asked)";

impl SfpMapOptions {
    /// The defaults for the images under `images`: the embedded model, the global descriptor
    /// on a copy of at most [`GLOBAL_MAX_SIDE`] pixels, the model's threshold, raw sections.
    pub fn new(images: impl Into<PathBuf>) -> Self {
        SfpMapOptions {
            images: images.into(),
            extractor: ExtractorOptions::default(),
            resize_max: None,
            global_max_side: Some(GLOBAL_MAX_SIDE),
            score_threshold: None,
            allow_missing: false,
            snap: false,
            triangulate: false,
            codec: Codec::Raw,
            zstd_level: 3,
            vlad: super::VladOptions::default(),
            pq: None,
            job: None,
        }
    }
}

/// What an SFP conversion did, beyond the [`ConvertSummary`] every convert reports.
#[derive(Debug, Clone, PartialEq)]
pub struct SfpMapSummary {
    /// `input_bytes` = the COLMAP model files; `levels[..].scale_range` = the level's stride.
    pub convert: ConvertSummary,
    /// 3D points in the model; `convert.points` of them are kept.
    pub model_points: usize,
    /// Model images with no file (skipped with `allow_missing`).
    pub missing_images: Vec<String>,
    /// Bytes of the images read.
    pub image_bytes: u64,
    /// The model that ran.
    pub model: ModelInfo,
    /// What the map's descriptors are: `sfp` for a pyramid model, a descriptor head's model
    /// name otherwise (`aliked-n16`), as the report and provenance record it.
    pub descriptors: String,
    /// Median network + sampling time per image, ms.
    pub ms_per_image: f64,
    /// The threshold of each level used, finest first (the option, or the model's defaults).
    pub score_thresholds: Vec<f32>,
}

/// Each model point's position from its moved observations (`moved`: point, image, pixel in
/// the camera), where they agree ([`super::snap::moved_position`]; `px_per_input[k]`: image
/// k's camera pixels per network input pixel); `None`: it stays.
fn moved_positions(
    model: &Reconstruction,
    px_per_input: &[f64],
    moved: &mut [(u32, u32, [f32; 2])],
) -> Vec<Option<[f64; 3]>> {
    use nalgebra::Vector2;
    let cameras = super::triangulation::image_cameras(model);
    let mut out = vec![None; model.points3d().len()];
    moved.sort_unstable_by_key(|m| (m.0, m.1));
    for group in moved.chunk_by(|a, b| a.0 == b.0) {
        let mut scales = Vec::with_capacity(group.len());
        let observations: Vec<_> = group
            .iter()
            .filter_map(|&(_, k, p)| {
                let camera = cameras[k as usize].as_ref()?;
                let pose = model.images()[k as usize].cam_from_world;
                scales.push(px_per_input[k as usize]);
                Some((camera, pose, Vector2::new(p[0] as f64, p[1] as f64)))
            })
            .collect();
        let was = model.points3d()[group[0].0 as usize].xyz;
        let around = nalgebra::Vector3::new(was[0], was[1], was[2]);
        out[group[0].0 as usize] =
            super::snap::moved_position(&observations, |o| scales[o], around)
                .map(|x| [x.x, x.y, x.z]);
    }
    out
}

/// Moves each kept point that has a position there, with its moved observations as its
/// visibility keypoints (the others keep the model's); returns how many moved. Time: the
/// moved observations sorted, then one pass over the visibility.
fn apply_positions(
    positions: &[Option<[f64; 3]>],
    moved: &[(u32, u32, [f32; 2])],
    map_index: &[u32],
    geometry: &mut Geometry,
) -> usize {
    let mut count = 0;
    for (p, x) in positions.iter().enumerate() {
        if let (Some(x), id) = (x, map_index[p]) {
            if id != u32::MAX {
                geometry.positions[id as usize] = *x;
                count += 1;
            }
        }
    }
    // (image, map point, pixel) of the moved points' observations, in image then point order.
    let mut by_image: Vec<(u32, u32, [f32; 2])> = moved
        .iter()
        .filter(|m| positions[m.0 as usize].is_some() && map_index[m.0 as usize] != u32::MAX)
        .map(|&(p, k, px)| (k, map_index[p as usize], px))
        .collect();
    by_image.sort_unstable_by_key(|m| (m.0, m.1));
    for group in by_image.chunk_by(|a, b| a.0 == b.0) {
        let k = group[0].0 as usize;
        let (a, b) = (
            geometry.vis_offsets[k] as usize,
            geometry.vis_offsets[k + 1] as usize,
        );
        for e in a..b {
            let id = geometry.vis_points[e];
            if let Ok(i) = group.binary_search_by_key(&id, |m| m.1) {
                geometry.vis_keypoints[e] = group[i].2;
            }
        }
    }
    count
}

/// Reads and decodes a model image: its provenance record (hashed from the bytes decoded) and
/// the network's input.
pub(super) fn read_image(
    path: &Path,
    contract: &contract::Contract,
    resize_max: Option<u32>,
) -> Result<(SourceFile, image::GrayInput), ConvertError> {
    let bytes = crate::input::read_regular(path).map_err(|e| ExtractError::Io {
        path: path.to_path_buf(),
        source: e.into(),
    })?;
    let source = SourceFile {
        path: path.display().to_string(),
        bytes: bytes.len() as u64,
        xxh3: format::file_hash(&bytes),
    };
    let input = image::decode(&bytes, path, contract.gray_weights, resize_max)?;
    Ok((source, input))
}

/// Level `level`'s keypoints where a query's would be: the extractor's own detection with the
/// model's defaults, at most `max` (input pixels, pixel-index convention).
pub(super) fn query_keypoints(
    contract: &contract::Contract,
    dense: &crate::extract::Dense,
    level: usize,
    max: usize,
) -> Vec<(f32, f32)> {
    let defaults = crate::extract::DetectOptions::default();
    let peaks = crate::extract::level_peaks(contract, dense, level, max, &defaults);
    crate::extract::placed(contract, dense, level, &peaks, &defaults)
}

/// Input pixel (x, y) of `dense` in the camera's pixels, COLMAP's convention (the model's
/// observations'), `to_file` the file's pixels per camera pixel.
pub(super) fn camera_pixel(
    dense: &crate::extract::Dense,
    (x, y): (f32, f32),
    to_file: [f32; 2],
) -> [f32; 2] {
    let [u, v] = dense.colmap_pixel(x, y);
    [u / to_file[0], v / to_file[1]]
}

/// Camera pixels per network input pixel (the mean of the two axes): pixel bars set in input
/// pixels, where the keypoints' precision is, are this many camera pixels.
pub(super) fn camera_px_per_input(dense: &crate::extract::Dense, to_file: [f32; 2]) -> f64 {
    f64::from(dense.scale[0] / to_file[0] + dense.scale[1] / to_file[1]) / 2.0
}

/// How an image file of `size` pixels scales its camera's pixels: observations are in the
/// camera's pixels, and a file of another size (a downscaled copy) is the same view scaled.
pub(super) fn camera_to_file(
    model: &Reconstruction,
    image: &crate::colmap::Image,
    size: [u32; 2],
) -> [f32; 2] {
    match model.camera(image.camera_id) {
        Some(c) if c.width > 0 && c.height > 0 => [
            size[0] as f32 / c.width as f32,
            size[1] as f32 / c.height as f32,
        ],
        _ => [1.0, 1.0],
    }
}

/// Per-point sums over the track: every level's normalised features, scores, counts.
struct Tracks {
    /// Offsets of each level's features within a point's row.
    offsets: Vec<usize>,
    /// Per level, the level whose score map finds its keypoints (`Contract::detect_levels`):
    /// a level's score at an observation is that map's, as a query's detector would see it.
    score_from: Vec<usize>,
    width: usize,
    levels: usize,
    features: Vec<f32>,
    scores: Vec<f32>,
    counts: Vec<u32>,
}

impl Tracks {
    /// Zero sums for `points` points of the contract's levels.
    fn new(contract: &contract::Contract, points: usize) -> Tracks {
        let dims = &contract.dims;
        let offsets: Vec<usize> = dims
            .iter()
            .scan(0, |at, &d| {
                let start = *at;
                *at += d;
                Some(start)
            })
            .collect();
        let width = dims.iter().sum();
        Tracks {
            offsets,
            score_from: contract.detect_levels.clone(),
            width,
            levels: dims.len(),
            features: vec![0.0; points * width],
            scores: vec![0.0; points * dims.len()],
            counts: vec![0; points],
        }
    }

    /// Adds one observation of `point` at input pixel (x, y): levels `from..` of `dense`, each
    /// level's features (L2-normalised, `buf` as scratch) and score.
    fn add(
        &mut self,
        dense: &crate::extract::Dense,
        point: usize,
        (x, y): (f32, f32),
        from: usize,
        buf: &mut Vec<f32>,
    ) {
        let row = &mut self.features[point * self.width..(point + 1) * self.width];
        for (j, level) in dense.levels.iter().enumerate().skip(from) {
            buf.clear();
            level.descriptor_at(x, y, buf);
            for (s, v) in row[self.offsets[j]..].iter_mut().zip(buf.iter()) {
                *s += v;
            }
            self.scores[point * self.levels + j] += dense.levels[self.score_from[j]].score_at(x, y);
        }
        self.counts[point] += 1;
    }
}

/// Converts the COLMAP model in `model_dir` with the images in `options.images` into an SFP
/// map at `output` (temp file + rename).
pub fn convert_with_images(
    model_dir: &Path,
    options: &SfpMapOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<SfpMapSummary, ConvertError> {
    let (model, sources) = read_model_with_sources(model_dir, reporter)?;
    let colmap = model_dir.display().to_string();
    convert_images_of(&model, sources, &colmap, options, output, reporter)
}

/// [`convert_with_images`] of a model already in memory (the Python package's
/// `from_pycolmap`): the same map, but for provenance, which lists no model files and records
/// `source` as the model.
pub fn convert_model_with_images(
    model: &Reconstruction,
    source: &str,
    options: &SfpMapOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<SfpMapSummary, ConvertError> {
    convert_images_of(model, Vec::new(), source, options, output, reporter)
}

/// The SFP map of `model`; `sources` are its files for provenance, `colmap` what provenance
/// records as the model.
fn convert_images_of(
    model: &Reconstruction,
    mut sources: Vec<SourceFile>,
    colmap: &str,
    options: &SfpMapOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<SfpMapSummary, ConvertError> {
    if options.triangulate && options.snap {
        return Err(ConvertError::Options(
            "--triangulate and --snap: the points are the network's keypoints already, there is \
             nothing to snap"
                .into(),
        ));
    }
    let input_bytes = sources.iter().map(|s| s.bytes).sum();

    // The model (a file) names the images: each stays inside the folder the user named.
    let paths: Vec<PathBuf> = model
        .images()
        .iter()
        .map(|i| {
            crate::input::join_inside(&options.images, &i.name).map_err(|why| {
                ConvertError::Input(crate::io::InputError {
                    path: options.images.clone(),
                    line: None,
                    message: format!("model image {}: {why}", crate::escape::quoted_name(&i.name)),
                })
            })
        })
        .collect::<Result<_, _>>()?;
    // An existing output that is a model image (`../out.sfpm` as a name, a link) would be
    // replaced while it is still to be read: the output policy's same-file rule, per image.
    let image_paths: Vec<&Path> = paths.iter().map(PathBuf::as_path).collect();
    if let Err(e) = crate::output::check_output(output, &image_paths, true) {
        if matches!(e, crate::output::OutputError::IsInput { .. }) {
            return Err(ConvertError::Output(e));
        }
    }
    // Present, not necessarily a file: a FIFO or folder is refused by name when it is read.
    let present: Vec<bool> = paths.iter().map(|p| p.exists()).collect();
    let missing: Vec<String> = model
        .images()
        .iter()
        .zip(&present)
        .filter(|(_, &here)| !here)
        .map(|(i, _)| i.name.clone())
        .collect();
    if !missing.is_empty() {
        if !options.allow_missing {
            return Err(ConvertError::MissingImages {
                images: options.images.clone(),
                missing,
                total: paths.len(),
            });
        }
        reporter.warn(&format!(
            "{}: {} of {} model images missing; their observations get no features",
            crate::escape::path(&options.images),
            missing.len(),
            paths.len()
        ));
    }

    let mut extractor = Extractor::new(&options.extractor, reporter)?;
    let contract = extractor.contract().clone();
    let levels = contract.levels();
    // A descriptor head's model (ALIKED) has one level and a keypoint score that is no map
    // compression rule (its peaks are sharp; a COLMAP point's observations are not its
    // peaks): every described point is kept unless a threshold is asked for.
    let head = contract.descriptor_head == DescriptorHead::Sddh;
    let descriptors = if head {
        contract.model_name.clone()
    } else {
        "sfp".to_string()
    };
    let thresholds: Vec<f32> = match options.score_threshold {
        Some(t) => vec![t; levels],
        None if head => vec![0.0; levels],
        None => contract.default_thresholds.clone(),
    };
    if options.triangulate && head {
        return Err(ConvertError::Options(format!(
            "--triangulate: {} describes one level with its descriptor head; there are no \
             pyramid keypoints to triangulate",
            contract.model_name
        )));
    }
    let triangulated;
    let mut first_pass: Vec<Option<String>> = Vec::new();
    let (model, triangulation) = if options.triangulate {
        let level = super::snap::snap_level(levels);
        let (keypoints, hashes) = super::network_tracks::image_keypoints(
            model,
            &paths,
            &present,
            level,
            &mut extractor,
            options.resize_max,
            reporter,
        )?;
        first_pass = hashes;
        let dims = contract.full_dims[level];
        let found = super::network_tracks::triangulated_model(model, &keypoints, dims, reporter);
        let (points, summary) = found.map_err(|why| {
            use super::network_tracks::NoPoints;
            ConvertError::Input(crate::io::InputError {
                path: PathBuf::from(colmap),
                line: None,
                message: match why {
                    NoPoints::TooManyKeypoints(n) => format!(
                        "--triangulate: {n} keypoints in its images, more than 2^32 - 1 tracks count"
                    ),
                    NoPoints::NoneAgreed(t) => format!(
                        "--triangulate: no keypoints seen in {} or more images agreed ({} image pairs \
                         share points, {} matches); its images share too few points, or its poses \
                         do not fit them",
                        super::network_tracks::MIN_TRACK_VIEWS,
                        t.pairs,
                        t.matches
                    ),
                },
            })
        })?;
        triangulated = points;
        (&triangulated, Some((level, summary)))
    } else {
        (model, None)
    };
    let n_points = model.points3d().len();
    let mut tracks = Tracks::new(&contract, n_points);
    let width = tracks.width;
    let mut global = vec![0.0f32; model.images().len() * contract.global_dim];
    // As the map records it: a `resize_max` input is already no larger than that side.
    let global_size = if contract.global_dim == 0 {
        GlobalSize::Skip
    } else {
        GlobalSize::from_max_side(options.global_max_side).effective(options.resize_max)
    };
    if options.snap && head {
        return Err(ConvertError::Options(format!(
            "--snap: {} describes one level with its descriptor head; there are no pyramid \
             keypoints to move observations to",
            contract.model_name
        )));
    }
    let snapping = options.snap;
    let snap_level = super::snap::snap_level(levels);
    // The level the snap level's keypoints are refined down to (the provenance says).
    let snap_finest = crate::extract::refined_to(&contract, snap_level, true);
    // The snap level's sums over moved observations (none kept without `--snap`).
    let mut snapped = Tracks::new(&contract, if snapping { n_points } else { 0 });
    // (point, image, moved pixel in the camera, COLMAP convention) of every moved observation.
    let mut moved: Vec<(u32, u32, [f32; 2])> = Vec::new();
    let mut ms = Vec::new();
    let mut image_bytes = 0;
    let mut buf = Vec::with_capacity(width);
    let mut scaled = 0usize;
    // Each image's camera pixels per network input pixel (`--snap`'s pixel bars).
    let mut px_per_input = vec![1.0f64; model.images().len()];
    reporter.start("extracting", Some(model.images().len() as u64));
    for (k, (image, path)) in model.images().iter().zip(&paths).enumerate() {
        if !present[k] {
            reporter.advance(1);
            continue;
        }
        // Read once: hashed for provenance and decoded from the same bytes.
        let (source, input) = read_image(path, &contract, options.resize_max)?;
        // `--triangulate` read it before: its keypoints must be this file's.
        if first_pass
            .get(k)
            .is_some_and(|h| h.as_deref() != Some(source.xxh3.as_str()))
        {
            return Err(ConvertError::Input(crate::io::InputError {
                path: path.clone(),
                line: None,
                message: "changed while it was converted (its keypoints were found in another \
                          version of the file)"
                    .into(),
            }));
        }
        image_bytes += source.bytes;
        sources.push(source);
        let t = Instant::now();
        let dense = extractor.run(&input).map_err(|e| e.on_image(path))?;
        let image_global = extractor
            .global(&input, &dense, global_size)
            .map_err(|e| e.on_image(path))?;
        global[k * contract.global_dim..(k + 1) * contract.global_dim]
            .copy_from_slice(&image_global);
        let to_file = camera_to_file(model, image, input.original_size);
        px_per_input[k] = camera_px_per_input(&dense, to_file);
        if to_file != [1.0, 1.0] {
            scaled += 1;
            if scaled == 1 {
                reporter.warn(&format!(
                    "{}: {}x{} px but its camera is {}x{}; observations are scaled to the file (the first of such images)",
                    crate::escape::path(path),
                    input.original_size[0],
                    input.original_size[1],
                    (input.original_size[0] as f32 / to_file[0]).round(),
                    (input.original_size[1] as f32 / to_file[1]).round()
                ));
            }
        }
        let observed: Vec<(usize, [f32; 2])> = image
            .points2d
            .iter()
            .filter_map(|p| {
                let point = p.point3d_id.and_then(|id| model.point3d_index(id))?;
                let xy = [p.xy[0] as f32 * to_file[0], p.xy[1] as f32 * to_file[1]];
                Some((point, dense.input_pixel(xy)))
            })
            .collect();
        if head {
            // The head describes the image's observations in one run of its graph.
            let at: Vec<[f32; 2]> = observed.iter().map(|o| o.1).collect();
            let described = extractor
                .describe(&dense, &at)
                .map_err(|e| e.on_image(path))?;
            let level = &dense.levels[0];
            for (&(point, [x, y]), d) in observed.iter().zip(described.chunks_exact(width)) {
                let row = &mut tracks.features[point * width..(point + 1) * width];
                for (s, v) in row.iter_mut().zip(d) {
                    *s += v;
                }
                tracks.scores[point] += level.score_at(x, y);
                tracks.counts[point] += 1;
            }
        }
        if snapping {
            let max = contract.default_max_keypoints[snap_level];
            let detected = query_keypoints(&contract, &dense, snap_level, max);
            let at: Vec<(f32, f32)> = observed.iter().map(|o| (o.1[0], o.1[1])).collect();
            for (&(point, _), to) in observed.iter().zip(super::snap::assign(&detected, &at)) {
                let Some((x, y)) = to.map(|i| detected[i]) else {
                    continue;
                };
                snapped.add(&dense, point, (x, y), snap_level, &mut buf);
                // Back to the camera's pixels, as the model's are.
                moved.push((
                    point as u32,
                    k as u32,
                    camera_pixel(&dense, (x, y), to_file),
                ));
            }
        }
        for &(point, [x, y]) in observed.iter().filter(|_| !head) {
            tracks.add(&dense, point, (x, y), 0, &mut buf);
        }
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        reporter.advance(1);
    }
    reporter.finish();
    if scaled > 1 {
        reporter.warn(&format!(
            "{scaled} images differ in size from their cameras; their observations were scaled"
        ));
    }

    // Level membership by mean score; points in no level are dropped.
    let positions = if snapping {
        moved_positions(model, &px_per_input, &mut moved)
    } else {
        Vec::new()
    };
    // A moved point's snap level is its moved observations' (features and score).
    let moved_on = |p: usize, j: usize| snapping && j == snap_level && positions[p].is_some();
    let sums = |p: usize, j: usize| if moved_on(p, j) { &snapped } else { &tracks };
    let mean_score =
        |p: usize, j: usize| sums(p, j).scores[p * levels + j] / sums(p, j).counts[p].max(1) as f32;
    let member = |p: usize, j: usize| sums(p, j).counts[p] > 0 && mean_score(p, j) >= thresholds[j];
    let keep: Vec<bool> = (0..n_points)
        .map(|p| (0..levels).any(|j| member(p, j)))
        .collect();
    let mut geometry = Geometry::new(model, Some(&keep));
    let map_index = map_index(&keep);
    let resnapped = if snapping {
        apply_positions(&positions, &moved, &map_index, &mut geometry)
    } else {
        0
    };

    let model_info = extractor.model().clone();
    let mut metadata = Metadata {
        global_max_side: (contract.global_dim > 0)
            .then(|| global_size.max_side())
            .flatten(),
        ..Metadata::default()
    };
    metadata.provenance.model = Some(SourceFile {
        path: model_info.name.clone(),
        bytes: model_info.bytes,
        xxh3: model_info.xxh3.clone(),
    });
    let parameters = json!({
        "operation": "convert",
        "colmap": colmap,
        "images": options.images.display().to_string(),
        "descriptors": descriptors,
        "model": model_info.name,
        "model_xxh3": model_info.xxh3,
        "contract": contract.raw,
        "score_thresholds": thresholds,
        "level_rule": if head { ONE_LEVEL_RULE } else { LEVEL_RULE },
        "aggregate": "mean of L2-normalised features per level, re-normalised",
        "resize_max": options.resize_max,
        "global_max_side": global_size.max_side(),
        "allow_missing": options.allow_missing,
        "missing_images": missing,
        "codec": options.codec.name(),
    });
    let mut parameters = parameters;
    if snapping {
        // Only when asked: a map made without it keeps its bytes.
        parameters["snap"] = json!({
            "level": snap_level,
            "refined_to": snap_finest,
            "radius_px": super::snap::SNAP_RADIUS_PX,
            "max_reprojection_px": super::triangulation::MAX_REPROJECTION_PX,
            "min_triangulation_deg": super::triangulation::MIN_TRIANGULATION_DEG,
            "points_moved": resnapped,
        });
    }
    if let Some((level, t)) = &triangulation {
        parameters["triangulate"] = json!({
            "level": level,
            "refined_to": crate::extract::refined_to(&contract, *level, true),
            "pairs_per_image": super::network_tracks::PAIRS_PER_IMAGE,
            "max_keypoints": contract.default_max_keypoints[*level]
                .min(super::network_tracks::MAX_TRIANGULATED_KEYPOINTS),
            "max_sampson_px": super::network_tracks::MAX_SAMPSON_PX,
            "max_reprojection_px": super::triangulation::MAX_REPROJECTION_PX,
            "min_triangulation_deg": super::triangulation::MIN_TRIANGULATION_DEG,
            "min_track_views": super::network_tracks::MIN_TRACK_VIEWS,
            "pairs": t.pairs,
            "matches": t.matches,
            "points": t.points,
            "observations": t.observations,
        });
    }
    let codec = (options.codec, options.zstd_level);
    let parameters = super::with_job(parameters, options.job.as_ref());
    let mut writer = super::map_writer(metadata, sources, parameters, codec, &geometry)?;
    if contract.global_dim > 0 {
        writer.set_image_global(contract.global_dim, &global)?;
    }

    reporter.start("levels", Some(levels as u64));
    let mut built = Vec::new();
    for (j, &threshold) in thresholds.iter().enumerate() {
        let members: Vec<usize> = (0..n_points).filter(|&p| member(p, j)).collect();
        if members.is_empty() {
            reporter.advance(1);
            continue;
        }
        let (mut dim_short, dim_full) = (contract.dims[j], contract.full_dims[j]);
        let mut descriptors = Vec::with_capacity(members.len() * dim_full);
        let mut energy_short = 0.0f64;
        for &p in &members {
            let source = sums(p, j);
            let row = &source.features[p * tracks.width..(p + 1) * tracks.width];
            let start = descriptors.len();
            for (i, &off) in tracks.offsets.iter().enumerate().skip(j) {
                let part_start = descriptors.len();
                descriptors.extend_from_slice(&row[off..off + contract.dims[i]]);
                crate::vector::l2_normalise(&mut descriptors[part_start..]);
            }
            crate::vector::l2_normalise(&mut descriptors[start..]);
            energy_short += descriptors[start..start + dim_short]
                .iter()
                .map(|v| f64::from(v * v))
                .sum::<f64>();
        }
        let mut variance_short = energy_short / members.len() as f64;
        // A descriptor head has no short head: the level is stored in its uncentred PCA basis
        // (as SIFT maps are, `basis.rs`), so `short` is the leading quarter of the energy-
        // ordered dimensions and a query's descriptors are projected on `level_projection`.
        let basis = head.then(|| {
            let basis = Basis::fit(&descriptors, dim_full);
            let mut projected = vec![0.0; descriptors.len()];
            for (src, dst) in descriptors
                .chunks_exact(dim_full)
                .zip(projected.chunks_exact_mut(dim_full))
            {
                basis.project(src, dst);
            }
            descriptors = projected;
            dim_short = (dim_full / HEAD_SHORT_FRACTION).max(1);
            variance_short = basis.energy_kept(dim_short);
            basis
        });
        let points: Vec<u32> = members.iter().map(|&p| map_index[p]).collect();
        let scores: Vec<f32> = members.iter().map(|&p| mean_score(p, j)).collect();
        let stride = contract.strides[j];
        let mut info = LevelInfo {
            level: contract.level_ids[j],
            stride: f64::from(stride),
            descriptor: contract.model_name.clone(),
            dim_full: dim_full as u32,
            dim_short: dim_short as u32,
            normalization: "l2".into(),
            extra: Default::default(),
        };
        let mean = scores.iter().map(|&s| f64::from(s)).sum::<f64>() / scores.len() as f64;
        let rule = if head { ONE_LEVEL_RULE } else { LEVEL_RULE };
        info.extra.insert("assignment".into(), json!(rule));
        info.extra
            .insert("score_threshold".into(), json!(threshold));
        info.extra.insert("mean_score".into(), json!(mean));
        if head {
            info.extra.insert("basis".into(), json!("uncentred pca"));
            info.extra.insert(
                "full_layout".into(),
                json!("the descriptor head's output (normalised mean over the track), in the level's PCA basis; short = the leading dimensions"),
            );
        } else {
            info.extra.insert(
                "basis".into(),
                json!("identity (the extractor's own; no level_projection)"),
            );
            info.extra.insert(
                "full_layout".into(),
                json!("levels i.. features, each L2-normalised, concatenated, L2-normalised; short = level i's part"),
            );
        }
        info.extra
            .insert("contract".into(), json!(contract.version));
        info.extra
            .insert("variance_short".into(), json!(variance_short));
        built.push((info, points, descriptors, variance_short, basis));
        reporter.advance(1);
    }
    reporter.finish();
    let mut summaries = Vec::new();
    for (info, points, descriptors, variance_short, basis) in &built {
        summaries.push(LevelSummary {
            level: info.level,
            points: points.len(),
            dim_full: info.dim_full,
            dim_short: info.dim_short,
            variance_short: *variance_short,
            scale_range: [info.stride as f32; 2],
        });
        writer.add_level(
            info.clone(),
            points,
            Some(Descriptors::F32(descriptors)),
            true,
        )?;
        if let Some(basis) = basis {
            writer.set_level_projection(info.level, basis.dim, basis.rows.clone())?;
        }
    }
    // Retrieval over level 2's descriptors (the level a `level 2, short` slice keeps), or the
    // deepest level without one; the network's global descriptor stays the default.
    let vlad = built
        .iter()
        .find(|b| b.0.level == VLAD_LEVEL)
        .or(built.last())
        .map(
            |(info, points, descriptors, _, _)| -> Result<Option<super::StoredVlad>, ConvertError> {
                let images = geometry.names.len();
                // A head describes the model's observations, not its own detections.
                let at = if head {
                    crate::vlad::DescribedAt::ModelObservations
                } else {
                    crate::vlad::DescribedAt::OwnKeypoints
                };
                let (clusters, dims) = options.vlad.shape(images, at);
                let dims = dims.min(info.dim_short as usize);
                if clusters == 0 || dims == 0 {
                    return Ok(None);
                }
                let full = info.dim_full as usize;
                let mut rows = vec![0.0f32; geometry.positions.len() * dims];
                for (&p, src) in points.iter().zip(descriptors.chunks_exact(full)) {
                    let dst = &mut rows[p as usize * dims..(p as usize + 1) * dims];
                    dst.copy_from_slice(&src[..dims]);
                    crate::vector::l2_normalise(dst);
                }
                Ok(super::retrieval::add_vlad(
                    &mut writer,
                    info.level,
                    &rows,
                    dims,
                    clusters,
                    "this level's points",
                    (&geometry.vis_offsets, &geometry.vis_points),
                    reporter,
                )?)
            },
        )
        .transpose()?
        .flatten();
    // The extractor's global descriptor, trained for retrieval, stays the default; a model
    // without one (ALIKED) ranks by the VLAD of its level's leading PCA dimensions.
    let retrieval = if contract.global_dim > 0 {
        Some(crate::format::Retrieval::Global)
    } else {
        vlad.map(|_| crate::format::Retrieval::Vlad)
    };
    writer.metadata_mut().retrieval = retrieval.map(|r| r.name().to_string());
    let pq = match options.pq {
        Some(m) => super::pq::quantise_all(&mut writer, m)?,
        None => Vec::new(),
    };
    let neighbours =
        super::retrieval::index_neighbours(&geometry, options.vlad.index_lists, reporter);
    let index = super::retrieval::add_image_index(
        &mut writer,
        options.vlad.index_lists,
        neighbours,
        reporter,
    )?;
    let output_bytes = writer.write(output, reporter)?;
    ms.sort_by(f64::total_cmp);
    Ok(SfpMapSummary {
        convert: ConvertSummary {
            points: geometry.positions.len(),
            images: geometry.names.len(),
            observations: geometry.vis_points.len(),
            input_bytes,
            output_bytes,
            geometry_only: false,
            levels: summaries,
            images_without_features: missing.len(),
            points_without_descriptors: 0,
            vlad,
            index,
            pq,
            // Images through the network are not streamed by a budget (issue 35 is the
            // database and features-file path).
            memory: None,
        },
        model_points: n_points,
        missing_images: missing,
        image_bytes,
        model: model_info,
        descriptors,
        ms_per_image: ms.get(ms.len() / 2).copied().unwrap_or(0.0),
        score_thresholds: thresholds,
    })
}
impl SfpMapSummary {
    /// The `convert --images --json` object of the map written to `out` in `seconds`.
    pub fn report(&self, out: &Path, seconds: f64) -> serde_json::Value {
        let summary = self;
        let c = &summary.convert;
        let levels: Vec<_> = c
            .levels
            .iter()
            .map(|l| {
                serde_json::json!({
                    "level": l.level, "points": l.points, "dim_full": l.dim_full,
                    "dim_short": l.dim_short, "variance_short": l.variance_short,
                    "stride": l.scale_range[0],
                })
            })
            .collect();
        serde_json::json!({
            "output": out.display().to_string(),
            "descriptors": summary.descriptors,
            "points": c.points,
            "model_points": summary.model_points,
            "dropped_points": summary.model_points - c.points,
            "images": c.images,
            "observations": c.observations,
            "input_bytes": c.input_bytes,
            "image_bytes": summary.image_bytes,
            "output_bytes": c.output_bytes,
            "ratio": c.input_bytes as f64 / c.output_bytes.max(1) as f64,
            "seconds": seconds,
            "ms_per_image": summary.ms_per_image,
            "score_thresholds": summary.score_thresholds,
            "model": summary.model.name,
            "model_xxh3": summary.model.xxh3,
            "missing_images": summary.missing_images,
            "levels": levels,
            "vlad": c.vlad.map(|v| serde_json::json!({"level": v.level, "clusters": v.clusters, "dims": v.dims})),
            "image_index": c.index.as_ref().map(|i| serde_json::json!({"of": i.of.name(), "lists": i.lists, "probe": i.probe, "recall": i.recall, "scored": i.scored, "stored": i.stored})),
        })
    }
}
