//! Maps of any local feature: a COLMAP model and its features (a `database.db` of SIFT or a
//! learned feature's typed rows, an hloc `features.h5`, a kapture folder: one
//! [`FeatureSource`] each) into an sfpmap map (`sfpmap convert --colmap`, `--kapture`). SIFT
//! maps were the first; the name stayed.
//!
//! Each 3D point's descriptor aggregates its track's descriptors (normalised mean or
//! medoid). Where every keypoint has a scale, points are assigned to 3 levels by the median
//! keypoint scale of their observations (tertiles; level 0 = smallest scale = finest, level 2
//! = largest = deepest, matching the SFP extractor's convention that deeper levels have larger
//! ids); otherwise all go to level 0. Each level stores its descriptors in its own
//! uncentred-PCA basis so a prefix (`short`) is meaningful.

use super::basis::Basis;
#[cfg(feature = "hdf5")]
use super::features::H5Source;
use super::features::{DatabaseSource, FeatureSource, ModelImage, MAX_DESCRIPTOR_DIM};
use super::geometry::Geometry;
use super::{read_geometry_with_sources, source_file, ConvertError, ConvertSummary, LevelSummary};
use crate::colmap::Reconstruction;
use crate::format::{f16, Codec, Descriptors, LevelInfo, Metadata, SourceFile};
use crate::progress::Reporter;
use serde_json::json;
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// How a point's descriptor is made from its observations'.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Aggregate {
    /// Mean of the L2-normalised descriptors, re-normalised.
    #[default]
    Mean,
    /// The observation descriptor with the highest summed similarity to the others.
    Medoid,
}

impl Aggregate {
    /// The name the metadata and `--aggregate` use (`mean`, `medoid`).
    pub fn name(self) -> &'static str {
        match self {
            Aggregate::Mean => "mean",
            Aggregate::Medoid => "medoid",
        }
    }
}

/// How [`convert`](super::convert) makes a map of any local feature from a model and its
/// database, an hloc features file or a kapture folder's features (`sfpmap convert`).
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    /// `database.db` with the model's keypoints and descriptors (SIFT, or a learned feature
    /// by its `type`); `None` and no `features` = geometry only.
    pub database: Option<PathBuf>,
    /// hloc `features.h5` with the model's keypoints and descriptors, by image name (instead
    /// of `database`).
    pub features: Option<PathBuf>,
    /// The feature the map records (`aliked-n16`); `None`: the features file's own name for
    /// it (its `sfp.model_name`, or the conf in hloc's `feats-<conf>.h5`).
    pub feature_name: Option<String>,
    /// hloc `global-feats-*.h5`: every map image's `global_descriptor`, stored as the map's
    /// retrieval descriptors.
    pub global_features: Option<PathBuf>,
    /// Dimensions of the `short` block; `None` = a quarter of the descriptor dimension.
    pub short_dims: Option<u32>,
    /// How the descriptor sections are stored.
    pub codec: Codec,
    /// zstd's level when `codec` is zstd.
    pub zstd_level: i32,
    /// How a point's observation descriptors become its one descriptor.
    pub aggregate: Aggregate,
    /// Fail when an image's features are missing from the database (default: warn, skip).
    pub strict: bool,
    /// Retrieval data: a VLAD codebook on the deepest level's basis.
    pub vlad: super::VladOptions,
    /// Product-quantise every level into this many one-byte codes per point (format 1.1).
    pub pq: Option<usize>,
    /// The caller's record of the job that made the map (a batch job's place, input
    /// fingerprint and options), stored as `provenance.parameters.job`; `None`: no such key.
    pub job: Option<serde_json::Value>,
}

impl Default for ConvertOptions {
    fn default() -> Self {
        ConvertOptions {
            database: None,
            features: None,
            feature_name: None,
            global_features: None,
            short_dims: None,
            codec: Codec::Raw,
            zstd_level: 3,
            aggregate: Aggregate::Mean,
            vlad: super::VladOptions::default(),
            pq: None,
            strict: false,
            job: None,
        }
    }
}

/// Per-observation features gathered from the source, flat and sorted by point.
struct Observations {
    dim: usize,
    /// The feature the map records as its levels' `descriptor`.
    feature: String,
    /// What `feature_source` records: where the descriptors came from.
    source_kind: &'static str,
    /// Whether every image's keypoints had a scale (levels by scale; else one level).
    scaled: bool,
    /// (point index, keypoint scale), one per observation with a descriptor.
    scales: Vec<(u32, f32)>,
    /// Mean: `[points × dim]` sums of normalised descriptors.
    sums: Vec<f32>,
    counts: Vec<u32>,
    /// Medoid: every observation's normalised descriptor, with its point.
    all: Vec<(u32, Vec<f32>)>,
    images_without_features: usize,
}

/// Converts the model in `model_dir` and writes the map to `output` (temp file + rename).
pub fn convert(
    model_dir: &Path,
    options: &ConvertOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<ConvertSummary, ConvertError> {
    let (geometry, sources) = read_geometry_with_sources(model_dir, reporter)?;
    let colmap = model_dir.display().to_string();
    let mut source = open_source(options)?;
    convert_geometry(
        &geometry,
        sources,
        &colmap,
        source
            .as_mut()
            .map(|s| s.as_mut() as &mut dyn FeatureSource),
        options,
        output,
        reporter,
    )
}

/// [`convert`] of a model already in memory (the Python package's `from_pycolmap`): the same
/// map, but for provenance, which lists no model files and records `source` as the model.
pub fn convert_model(
    model: &Reconstruction,
    source: &str,
    options: &ConvertOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<ConvertSummary, ConvertError> {
    let geometry = Geometry::new(model, None);
    let mut features = open_source(options)?;
    convert_geometry(
        &geometry,
        Vec::new(),
        source,
        features
            .as_mut()
            .map(|s| s.as_mut() as &mut dyn FeatureSource),
        options,
        output,
        reporter,
    )
}

/// [`convert_model`] with the features of `source` (a kapture folder, …): `model_desc` is
/// what provenance records as the model; `options.database` and `options.features` are not
/// read.
pub(crate) fn convert_with_source(
    model: &Reconstruction,
    source: &mut dyn FeatureSource,
    model_desc: &str,
    options: &ConvertOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<ConvertSummary, ConvertError> {
    let geometry = Geometry::new(model, None);
    convert_geometry(
        &geometry,
        Vec::new(),
        model_desc,
        Some(source),
        options,
        output,
        reporter,
    )
}

/// The features `options` name: the database or the features file (not both), or none.
fn open_source(options: &ConvertOptions) -> Result<Option<Box<dyn FeatureSource>>, ConvertError> {
    match (&options.database, &options.features) {
        (Some(_), Some(_)) => Err(ConvertError::Options(
            "a database and a features file were both given: the model's features come from one"
                .into(),
        )),
        (Some(db), None) => Ok(Some(Box::new(DatabaseSource::open(db)?))),
        #[cfg(feature = "hdf5")]
        (None, Some(h5)) => Ok(Some(Box::new(H5Source::open(
            h5,
            options.feature_name.clone(),
        )?))),
        #[cfg(not(feature = "hdf5"))]
        (None, Some(h5)) => Err(ConvertError::Options(format!(
            "{}: features files need sfpmap built with the hdf5 feature",
            crate::escape::path(h5)
        ))),
        (None, None) => Ok(None),
    }
}

/// The map of `geometry`; `sources` are its files for provenance, `colmap` what provenance
/// records as the model.
fn convert_geometry(
    geometry: &Geometry,
    mut sources: Vec<SourceFile>,
    colmap: &str,
    source: Option<&mut dyn FeatureSource>,
    options: &ConvertOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<ConvertSummary, ConvertError> {
    let mut observations = match source {
        Some(source) => {
            // A folder (kapture) is recorded by its files' own provenance, not hashed whole.
            if source.path().is_file() {
                sources.push(source_file(source.path(), reporter)?);
            }
            Some(gather(geometry, source, options, reporter)?)
        }
        None => None,
    };
    let global = match &options.global_features {
        Some(path) => {
            sources.push(source_file(path, reporter)?);
            Some(read_global(geometry, path, reporter)?)
        }
        None => None,
    };
    let input_bytes = sources.iter().map(|s| s.bytes).sum();

    let metadata = Metadata {
        geometry_only: observations.is_none(),
        ..Default::default()
    };
    let parameters = json!({
        "operation": "convert",
        "colmap": colmap,
        "database": options.database.as_ref().map(|p| p.display().to_string()),
        "features": options.features.as_ref().map(|p| p.display().to_string()),
        "global_features": options.global_features.as_ref().map(|p| p.display().to_string()),
        "feature": observations.as_ref().map(|o| o.feature.clone()),
        "aggregate": options.aggregate.name(),
        "short_dims": options.short_dims,
        "codec": options.codec.name(),
    });
    let codec = (options.codec, options.zstd_level);
    let parameters = super::with_job(parameters, options.job.as_ref());
    let mut writer = super::map_writer(metadata, sources, parameters, codec, geometry)?;

    let mut summaries = Vec::new();
    let mut points_without_descriptors = 0;
    let mut images_without_features = 0;
    // Retrieval on the deepest level's basis (the level a `level 2, short` slice keeps), over
    // every described point: each point's descriptor projected on the basis' leading rows,
    // made as soon as the levels are, so the full descriptors are dropped before writing.
    let (mut built_levels, vlad_rows) = match observations.as_mut() {
        Some(obs) => {
            images_without_features = obs.images_without_features;
            let n_points = geometry.positions.len();
            reporter.start("aggregating descriptors", Some(n_points as u64));
            let (descriptors, has) = aggregate(obs, n_points, options.aggregate);
            reporter.finish();
            points_without_descriptors = has.iter().filter(|h| !**h).count();
            let levels = build_levels(obs, &descriptors, &has, options.short_dims, reporter)?;
            let (clusters, dims) = options
                .vlad
                .shape(geometry.names.len(), crate::vlad::DescribedAt::OwnKeypoints);
            let rows = levels.last().and_then(|deepest| {
                let dims = dims.min(deepest.info.dim_short as usize);
                (clusters > 0 && dims > 0).then(|| {
                    reporter.start("projecting for retrieval", None);
                    let rows = deepest
                        .basis
                        .project_leading(&descriptors, obs.dim, dims, &has);
                    reporter.finish();
                    (rows, dims, clusters)
                })
            });
            (levels, rows)
        }
        None => (Vec::new(), None),
    };
    // Moved in: the writer splits each level's into its blocks and drops them.
    let level_descriptors: Vec<Vec<f16>> = built_levels
        .iter_mut()
        .map(|l| std::mem::take(&mut l.descriptors))
        .collect();
    for (l, descriptors) in built_levels.iter().zip(level_descriptors) {
        writer.add_level(
            l.info.clone(),
            &l.points,
            Some(Descriptors::F16(Cow::Owned(descriptors))),
            true,
        )?;
        writer.set_level_projection(l.info.level, l.basis.dim, l.basis.rows.clone())?;
        summaries.push(l.summary.clone());
    }
    let mut vlad = None;
    if let (Some((rows, dims, clusters)), Some(deepest)) = (vlad_rows, built_levels.last()) {
        vlad = super::retrieval::add_vlad(
            &mut writer,
            deepest.info.level,
            &rows,
            dims,
            clusters,
            "every point with a descriptor (all levels), projected on this level's basis",
            geometry,
            reporter,
        )?;
    }
    let pq = match options.pq {
        Some(m) => super::pq::quantise_all(&mut writer, m)?,
        None => Vec::new(),
    };
    if let Some((dim, global)) = &global {
        writer.set_image_global(*dim, global)?;
        // Descriptors trained for retrieval (NetVLAD, …) rank better than a VLAD of local ones.
        writer.metadata_mut().retrieval = Some(crate::format::Retrieval::Global.name().to_string());
    }
    let index = super::retrieval::add_image_index(&mut writer, options.vlad.index_lists, reporter)?;
    let output_bytes = writer.write(output, reporter)?;
    Ok(ConvertSummary {
        points: geometry.positions.len(),
        images: geometry.names.len(),
        observations: geometry.vis_points.len(),
        input_bytes,
        output_bytes,
        geometry_only: observations.is_none(),
        levels: summaries,
        images_without_features,
        points_without_descriptors,
        vlad,
        index,
        pq,
    })
}

/// Reads every model image's features from `source` and gathers, per observation of a 3D
/// point, its normalised descriptor and keypoint scale.
fn gather(
    geometry: &Geometry,
    source: &mut dyn FeatureSource,
    options: &ConvertOptions,
    reporter: &dyn Reporter,
) -> Result<Observations, ConvertError> {
    let path = source.path().to_path_buf();
    let n_points = geometry.positions.len();
    let mut obs = Observations {
        dim: 0,
        feature: String::new(),
        source_kind: source.kind(),
        scaled: true,
        scales: Vec::with_capacity(geometry.vis_points.len()),
        sums: Vec::new(),
        counts: vec![0; n_points],
        all: Vec::new(),
        images_without_features: 0,
    };
    let n_images = geometry.names.len();
    reporter.start("reading features", Some(n_images as u64));
    let mut normalised = Vec::new();
    for (i, (&image_id, name)) in geometry.image_ids.iter().zip(&geometry.names).enumerate() {
        let image = ModelImage {
            id: image_id,
            name,
            size: geometry.image_size(i),
        };
        let Some(features) = source.image(image)? else {
            if options.strict {
                return Err(ConvertError::MissingFeatures {
                    features: path,
                    image: name.clone(),
                });
            }
            obs.images_without_features += 1;
            reporter.warn(&format!(
                "{}: image {} has no features; its observations get no descriptor",
                crate::escape::path(&path),
                crate::escape::quoted_name(name)
            ));
            reporter.advance(1);
            continue;
        };
        if features.dim == 0 || features.dim > MAX_DESCRIPTOR_DIM {
            return Err(ConvertError::Input(crate::io::InputError {
                path,
                line: None,
                message: format!(
                    "image {}: descriptors of {} dimensions (1 to {MAX_DESCRIPTOR_DIM} are taken)",
                    crate::escape::quoted_name(name),
                    features.dim
                ),
            }));
        }
        if obs.dim == 0 {
            obs.dim = features.dim;
            if options.aggregate == Aggregate::Mean {
                obs.sums = vec![0.0; n_points * obs.dim];
            }
        } else if features.dim != obs.dim {
            return Err(ConvertError::DescriptorDim {
                features: path,
                image: name.clone(),
                expected: obs.dim,
                found: features.dim,
            });
        }
        obs.scaled &= features.scales.is_some();
        let dim = obs.dim;
        let entries = geometry.vis_offsets[i] as usize..geometry.vis_offsets[i + 1] as usize;
        for (&point, &idx) in geometry.vis_points[entries.clone()]
            .iter()
            .zip(&geometry.vis_point2d[entries])
        {
            let (point, idx) = (point as usize, idx as usize);
            if idx >= features.keypoints || !features.values.row_into(dim, idx, &mut normalised) {
                return Err(ConvertError::KeypointOutOfRange {
                    features: path,
                    image: name.clone(),
                    point2d_idx: idx,
                    keypoints: features.keypoints,
                });
            }
            // Without scales every observation is alike: one level.
            let scale = features.scales.as_ref().map_or(1.0, |s| s[idx]);
            // A NaN scale would drop the point from every level without a word; the level
            // assignment and the metadata's scale ranges need finite scales.
            if !scale.is_finite() {
                return Err(ConvertError::KeypointScaleNotFinite {
                    features: path,
                    image: name.clone(),
                    point2d_idx: idx,
                });
            }
            if let Some(v) = normalised.iter().find(|v| !v.is_finite()) {
                return Err(ConvertError::Input(crate::io::InputError {
                    path,
                    line: None,
                    message: format!(
                        "image {}: keypoint {idx}: a descriptor value is {v}",
                        crate::escape::quoted_name(name)
                    ),
                }));
            }
            crate::vector::l2_normalise(&mut normalised);
            obs.scales.push((point as u32, scale));
            obs.counts[point] += 1;
            match options.aggregate {
                Aggregate::Mean => {
                    for (s, v) in obs.sums[point * dim..(point + 1) * dim]
                        .iter_mut()
                        .zip(&normalised)
                    {
                        *s += v;
                    }
                }
                Aggregate::Medoid => obs.all.push((point as u32, normalised.clone())),
            }
        }
        reporter.advance(1);
    }
    reporter.finish();
    if obs.images_without_features > 0 {
        reporter.warn(&format!(
            "{} of {} images have no features in {}",
            obs.images_without_features,
            n_images,
            crate::escape::path(&path)
        ));
    }
    obs.feature = source
        .feature_name()
        .unwrap_or_else(|| format!("{}{}", crate::format::UNNAMED_FEATURE_PREFIX, obs.dim));
    Ok(obs)
}

/// Every model image's global descriptor from hloc's `global-feats-*.h5`
/// (`global_descriptor`), `[images × dim]`: each image must have one, all of one dimension.
#[cfg(feature = "hdf5")]
fn read_global(
    geometry: &Geometry,
    path: &Path,
    reporter: &dyn Reporter,
) -> Result<(usize, Vec<f32>), ConvertError> {
    let h5 = crate::io::features_h5::H5Features::open(path)?;
    reporter.start(
        "reading global descriptors",
        Some(geometry.names.len() as u64),
    );
    let mut dim = 0;
    let mut out = Vec::new();
    for name in &geometry.names {
        let shown = crate::escape::quoted_name(name);
        let g = h5
            .global(name)?
            .ok_or_else(|| h5.err(format!("image {shown}: no global_descriptor")))?;
        if g.is_empty() {
            return Err(h5
                .err(format!("{name}/global_descriptor: no values"))
                .into());
        }
        if dim == 0 {
            dim = g.len();
            out.reserve(dim * geometry.names.len());
        }
        if g.len() != dim {
            return Err(h5
                .err(format!(
                    "{name}/global_descriptor: {} values, the images before it have {dim}",
                    g.len()
                ))
                .into());
        }
        out.extend_from_slice(&g);
        reporter.advance(1);
    }
    reporter.finish();
    Ok((dim, out))
}

#[cfg(not(feature = "hdf5"))]
fn read_global(
    _: &Geometry,
    path: &Path,
    _: &dyn Reporter,
) -> Result<(usize, Vec<f32>), ConvertError> {
    Err(ConvertError::Options(format!(
        "{}: global features files need sfpmap built with the hdf5 feature",
        crate::escape::path(path)
    )))
}

/// One descriptor per point (`[points × dim]`) and whether the point has one. Takes the
/// observations' sums (or descriptors): a map's worth of f32 not held twice.
fn aggregate(obs: &mut Observations, n_points: usize, how: Aggregate) -> (Vec<f32>, Vec<bool>) {
    let dim = obs.dim;
    let has: Vec<bool> = obs.counts.iter().map(|&c| c > 0).collect();
    match how {
        Aggregate::Mean => {
            let mut out = std::mem::take(&mut obs.sums);
            out.resize(n_points * dim, 0.0);
            for row in out.chunks_exact_mut(dim.max(1)) {
                crate::vector::l2_normalise(row);
            }
            (out, has)
        }
        Aggregate::Medoid => {
            let mut out = vec![0.0; n_points * dim];
            let all = std::mem::take(&mut obs.all);
            let mut by_point: Vec<&(u32, Vec<f32>)> = all.iter().collect();
            by_point.sort_by_key(|(p, _)| *p);
            for group in by_point.chunk_by(|a, b| a.0 == b.0) {
                let best = (0..group.len())
                    .max_by(|&i, &j| {
                        let score = |k: usize| -> f32 {
                            group
                                .iter()
                                .map(|(_, d)| crate::vector::dot(&group[k].1, d))
                                .sum()
                        };
                        score(i).total_cmp(&score(j)).then(j.cmp(&i))
                    })
                    .unwrap_or(0);
                let p = group[0].0 as usize;
                out[p * dim..(p + 1) * dim].copy_from_slice(&group[best].1);
            }
            (out, has)
        }
    }
}

struct BuiltLevel {
    info: LevelInfo,
    points: Vec<u32>,
    /// In the level's basis, rounded to f16 as the writer stores them (half the f32's bytes).
    descriptors: Vec<f16>,
    basis: Basis,
    summary: LevelSummary,
}

/// The rule, as recorded in each level's metadata.
const LEVEL_RULE: &str = "median keypoint scale of the point's observations, split at the map's tertiles; level 0 = smallest scales (finest), level 2 = largest (deepest)";

/// The rule when the keypoints have no scale (hloc's learned features, x/y-only keypoints).
const ONE_LEVEL_RULE: &str = "one level: the features' keypoints have no scale";

fn build_levels(
    obs: &mut Observations,
    descriptors: &[f32],
    has: &[bool],
    short_dims: Option<u32>,
    reporter: &dyn Reporter,
) -> Result<Vec<BuiltLevel>, ConvertError> {
    let dim = obs.dim;
    if dim == 0 {
        return Ok(Vec::new());
    }
    // Median scale per point.
    // Taken: nothing reads them after the levels.
    let mut scales = std::mem::take(&mut obs.scales);
    scales.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut median = vec![f32::NAN; has.len()];
    for group in scales.chunk_by(|a, b| a.0 == b.0) {
        median[group[0].0 as usize] = group[group.len() / 2].1;
    }
    let mut sorted: Vec<f32> = median.iter().copied().filter(|m| m.is_finite()).collect();
    sorted.sort_by(f32::total_cmp);
    // The value below which a share `q` of the points lies (nearest rank).
    let quantile =
        |q: f64| sorted[((sorted.len() as f64 * q).ceil() as usize).clamp(1, sorted.len()) - 1];
    let (t1, t2) = if sorted.is_empty() {
        (0.0, 0.0)
    } else {
        (quantile(1.0 / 3.0), quantile(2.0 / 3.0))
    };
    let level_of = |m: f32| -> u16 {
        if !obs.scaled || m <= t1 {
            0
        } else if m <= t2 {
            1
        } else {
            2
        }
    };
    let short = short_dims
        .map_or(dim as u32 / 4, |s| s.min(dim as u32))
        .max(1);
    let mut levels = Vec::new();
    reporter.start("descriptor bases", Some(3));
    for level in 0..3u16 {
        let points: Vec<u32> = (0..has.len())
            .filter(|&p| has[p] && median[p].is_finite() && level_of(median[p]) == level)
            .map(|p| p as u32)
            .collect();
        if points.is_empty() {
            reporter.advance(1);
            continue;
        }
        // The level's rows read in place, in point order: no f32 copy of the level.
        let rows = || {
            points
                .iter()
                .map(|&p| &descriptors[p as usize * dim..(p as usize + 1) * dim])
        };
        let basis = Basis::fit_rows(rows(), dim);
        // Row by row into f16 (round to nearest even, as the writer converts f32).
        let mut projected = Vec::with_capacity(points.len() * dim);
        let mut row = vec![0.0f32; dim];
        for src in rows() {
            basis.project(src, &mut row);
            projected.extend(row.iter().map(|&v| f16::from_f32(v)));
        }
        let level_scales: Vec<f32> = points.iter().map(|&p| median[p as usize]).collect();
        let lo = level_scales.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = level_scales
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        let mut mid = level_scales.clone();
        mid.sort_by(f32::total_cmp);
        let variance_short = basis.energy_kept(short as usize);
        let mut info = LevelInfo {
            level,
            stride: f64::from(mid[mid.len() / 2]),
            descriptor: obs.feature.clone(),
            dim_full: dim as u32,
            dim_short: short,
            normalization: "l2".into(),
            extra: Default::default(),
        };
        info.extra.insert("scale_range".into(), json!([lo, hi]));
        let rule = if obs.scaled {
            LEVEL_RULE
        } else {
            ONE_LEVEL_RULE
        };
        info.extra.insert("assignment".into(), json!(rule));
        info.extra
            .insert("feature_source".into(), json!(obs.source_kind));
        info.extra.insert("basis".into(), json!("uncentred pca"));
        info.extra
            .insert("variance_short".into(), json!(variance_short));
        levels.push(BuiltLevel {
            summary: LevelSummary {
                level,
                points: points.len(),
                dim_full: dim as u32,
                dim_short: short,
                variance_short,
                scale_range: [lo, hi],
            },
            info,
            points,
            descriptors: projected,
            basis,
        });
        reporter.advance(1);
    }
    reporter.finish();
    Ok(levels)
}
