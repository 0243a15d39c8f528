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

use super::basis::{Basis, BasisFit};
#[cfg(feature = "hdf5")]
use super::features::H5Source;
use super::features::{DatabaseSource, FeatureSource};
use super::geometry::Geometry;
use super::stream::Aggregated;
use super::{read_geometry_with_sources, source_file, ConvertError, ConvertSummary, LevelSummary};
use crate::colmap::Reconstruction;
use crate::format::{
    f16, Codec, LevelInfo, Metadata, SourceFile, Spool, SpoolRegion, SpooledBytes,
};
use crate::progress::Reporter;
use serde_json::json;
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
    /// The memory the conversion may use, in bytes (`--memory`); `None`: half the machine's
    /// ([`default_memory_budget`](super::default_memory_budget)). The points' descriptors are
    /// made in as many reads of the features as it takes ([`MAX_PASSES`](super::MAX_PASSES)
    /// at most), and the map is the same bytes whatever the budget; a budget too small is
    /// refused up front, naming the smallest that works.
    pub memory: Option<u64>,
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
            memory: None,
        }
    }
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
    // Global descriptors first (the plan counts them), hashed for provenance after the plan,
    // as the features' source is.
    let global = match &options.global_features {
        Some(path) => Some(read_global(geometry, path, reporter)?),
        None => None,
    };
    // f32 here, f16 in the writer.
    let global_bytes = global.as_ref().map_or(0, |(_, g)| g.len() as u64 * 6);
    let mut memory = None;
    let mut neighbours = None;
    let aggregated = match source {
        Some(source) => {
            // Planned first: a budget too small is refused before anything long runs.
            let model = Path::new(colmap);
            let prepared = super::stream::prepare(geometry, source, options, global_bytes, model)?;
            // A folder (kapture) is recorded by its files' own provenance, not hashed whole.
            if source.path().is_file() {
                sources.push(source_file(source.path(), reporter)?);
            }
            memory = Some(prepared.memory);
            // Before the reads, whose open tracks are the larger part of the peak: its
            // point → images turn of the visibility is gone by then.
            neighbours =
                super::retrieval::index_neighbours(geometry, options.vlad.index_lists, reporter);
            let aggregated =
                super::stream::aggregate(geometry, source, options, prepared, output, reporter)?;
            Some(aggregated)
        }
        None => None,
    };
    // A map without features indexes its global descriptors, if any.
    if neighbours.is_none() && global.is_some() {
        neighbours =
            super::retrieval::index_neighbours(geometry, options.vlad.index_lists, reporter);
    }
    let geometry_only = aggregated.is_none();
    if let Some(path) = &options.global_features {
        sources.push(source_file(path, reporter)?);
    }
    let input_bytes = sources.iter().map(|s| s.bytes).sum();

    let metadata = Metadata {
        geometry_only,
        ..Default::default()
    };
    let parameters = json!({
        "operation": "convert",
        "colmap": colmap,
        "database": options.database.as_ref().map(|p| p.display().to_string()),
        "features": options.features.as_ref().map(|p| p.display().to_string()),
        "global_features": options.global_features.as_ref().map(|p| p.display().to_string()),
        "feature": aggregated.as_ref().map(|o| o.feature.clone()),
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
    // made as the levels are.
    let (built_levels, vlad_rows) = match aggregated {
        Some(agg) => {
            images_without_features = agg.images_without_features;
            points_without_descriptors = geometry.positions.len() - agg.has.count_ones();
            let (clusters, dims) = options
                .vlad
                .shape(geometry.names.len(), crate::vlad::DescribedAt::OwnKeypoints);
            let dims = if clusters > 0 { dims } else { 0 };
            let (levels, rows) = build_levels(&agg, options.short_dims, dims, output, reporter)?;
            // The aggregated descriptors' scratch file goes before the map is written.
            drop(agg);
            (levels, rows.map(|(rows, dims)| (rows, dims, clusters)))
        }
        None => (Vec::new(), None),
    };
    for l in &built_levels {
        writer.add_level_spooled(l.info.clone(), &l.points, l.short.clone(), l.rest.clone())?;
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
            (&geometry.vis_offsets, &geometry.vis_points),
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
    let index = super::retrieval::add_image_index(
        &mut writer,
        options.vlad.index_lists,
        neighbours,
        reporter,
    )?;
    let output_bytes = writer.write(output, reporter)?;
    Ok(ConvertSummary {
        points: geometry.positions.len(),
        images: geometry.names.len(),
        observations: geometry.vis_points.len(),
        input_bytes,
        output_bytes,
        geometry_only,
        levels: summaries,
        images_without_features,
        points_without_descriptors,
        vlad,
        index,
        pq,
        memory,
    })
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

struct BuiltLevel {
    info: LevelInfo,
    points: Vec<u32>,
    /// The `short` and `rest` blocks: in the level's basis, rounded to f16 as the writer
    /// stores them, in the scratch file.
    short: SpooledBytes,
    rest: SpooledBytes,
    basis: Basis,
    summary: LevelSummary,
}

/// The rule, as recorded in each level's metadata.
const LEVEL_RULE: &str = "median keypoint scale of the point's observations, split at the map's tertiles; level 0 = smallest scales (finest), level 2 = largest (deepest)";

/// The rule when the keypoints have no scale (hloc's learned features, x/y-only keypoints).
const ONE_LEVEL_RULE: &str = "one level: the features' keypoints have no scale";

/// Dimensions of each level's `short` block: those asked for (at most `dim`), else a quarter
/// of `dim`; at least 1.
pub(crate) fn short_dims(asked: Option<u32>, dim: usize) -> u32 {
    asked.map_or(dim as u32 / 4, |s| s.min(dim as u32)).max(1)
}

/// Each described point's leading coordinates in the deepest level's basis
/// (`[points × dims]`), and `dims`.
type RetrievalRows = (Vec<f32>, usize);

/// The map's levels from the aggregated descriptors: points split by median scale, each
/// level's basis fitted (one read of the descriptors, in point order) and its rows projected
/// into f16 blocks spooled beside `output` (a second read). With `vlad_dims`, also every
/// described point's first `vlad_dims` coordinates in the deepest level's basis,
/// renormalised (`[points × vlad_dims]`), the rows the retrieval codebook learns from.
fn build_levels(
    agg: &Aggregated,
    short_dims_asked: Option<u32>,
    vlad_dims: usize,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<(Vec<BuiltLevel>, Option<RetrievalRows>), ConvertError> {
    let dim = agg.dim;
    if dim == 0 {
        return Ok((Vec::new(), None));
    }
    let median = &agg.median;
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
    drop(sorted);
    let level_of = |m: f32| -> usize {
        if !agg.scaled || m <= t1 {
            0
        } else if m <= t2 {
            1
        } else {
            2
        }
    };
    let short = short_dims(short_dims_asked, dim);
    let mut points: [Vec<u32>; 3] = Default::default();
    for p in agg.has.iter_ones() {
        if median[p].is_finite() {
            points[level_of(median[p])].push(p as u32);
        }
    }

    reporter.start("descriptor bases", None);
    let mut fits: Vec<Option<BasisFit>> = points
        .iter()
        .map(|p| (!p.is_empty()).then(|| BasisFit::new(dim)))
        .collect();
    agg.spill.for_each(&agg.has, |p, row| {
        if median[p].is_finite() {
            if let Some(fit) = fits[level_of(median[p])].as_mut() {
                fit.add(row);
            }
        }
        Ok(())
    })?;
    let bases: Vec<Option<Basis>> = fits.into_iter().map(|f| f.map(BasisFit::finish)).collect();
    reporter.finish();

    let deepest = (0..3).rev().find(|&l| bases[l].is_some());
    let vlad_dims = vlad_dims.min(short as usize);
    let mut vlad_rows =
        (vlad_dims > 0 && deepest.is_some()).then(|| vec![0.0f32; median.len() * vlad_dims]);
    let mut spool = Spool::for_output(output)?;
    let mut regions: Vec<Option<[SpoolRegion; 2]>> = points
        .iter()
        .map(|p| {
            let n = p.len() as u64;
            (n > 0).then(|| {
                [
                    spool.region(n * u64::from(short) * 2),
                    spool.region(n * u64::from(dim as u32 - short) * 2),
                ]
            })
        })
        .collect();
    reporter.start("projecting descriptors", Some(agg.has.count_ones() as u64));
    let mut row = vec![0.0f32; dim];
    let mut bytes: Vec<u8> = Vec::with_capacity(dim * 2);
    let split = short as usize * 2;
    let mut done = 0u64;
    agg.spill.for_each(&agg.has, |p, src| {
        if median[p].is_finite() {
            let l = level_of(median[p]);
            if let (Some(basis), Some([short_block, rest_block])) = (&bases[l], &mut regions[l]) {
                basis.project(src, &mut row);
                // Rounded to nearest even, as the writer converts f32.
                bytes.clear();
                bytes.extend(row.iter().flat_map(|&v| f16::from_f32(v).to_le_bytes()));
                short_block.push(&bytes[..split])?;
                rest_block.push(&bytes[split..])?;
            }
        }
        if let (Some(rows), Some(d)) = (vlad_rows.as_mut(), deepest) {
            if let Some(basis) = &bases[d] {
                basis.project_leading_row(src, &mut rows[p * vlad_dims..(p + 1) * vlad_dims]);
            }
        }
        done += 1;
        if done % 65_536 == 0 {
            reporter.advance(65_536);
        }
        Ok(())
    })?;
    reporter.finish();

    let mut levels = Vec::new();
    for (((level, points), basis), region) in (0..3u16).zip(points).zip(bases).zip(regions) {
        let (Some(basis), Some([short_block, rest_block])) = (basis, region) else {
            continue;
        };
        let level_scales: Vec<f32> = points.iter().map(|&p| median[p as usize]).collect();
        let lo = level_scales.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = level_scales
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        let mut mid = level_scales;
        mid.sort_by(f32::total_cmp);
        let variance_short = basis.energy_kept(short as usize);
        let mut info = LevelInfo {
            level,
            stride: f64::from(mid[mid.len() / 2]),
            descriptor: agg.feature.clone(),
            dim_full: dim as u32,
            dim_short: short,
            normalization: "l2".into(),
            extra: Default::default(),
        };
        info.extra.insert("scale_range".into(), json!([lo, hi]));
        let rule = if agg.scaled {
            LEVEL_RULE
        } else {
            ONE_LEVEL_RULE
        };
        info.extra.insert("assignment".into(), json!(rule));
        info.extra
            .insert("feature_source".into(), json!(agg.source_kind));
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
            short: short_block.finish()?,
            rest: rest_block.finish()?,
            basis,
        });
    }
    Ok((levels, vlad_rows.map(|rows| (rows, vlad_dims))))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A map made in several reads of the features (ranges of points) is the map made in one,
    /// byte for byte, mean and medoid alike.
    #[test]
    fn a_map_made_in_several_reads_of_the_features_is_the_same_bytes() {
        // As tests/shared_data: missing data fails unless skipping is asked for.
        let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/scenes/sacre-coeur");
        if !scene.is_dir() {
            let skip = std::env::var_os("SFPMAP_SKIP_SHARED_DATA").is_some_and(|v| v == "1");
            assert!(
                skip,
                "{} is missing (SFPMAP_SKIP_SHARED_DATA=1 skips)",
                scene.display()
            );
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let db = dir.path().join("database.db");
        std::fs::copy(scene.join("database.db"), &db).unwrap();
        for aggregate in [Aggregate::Mean, Aggregate::Medoid] {
            let options = ConvertOptions {
                database: Some(db.clone()),
                aggregate,
                ..Default::default()
            };
            let mut maps = Vec::new();
            for passes in [1, 5] {
                super::super::stream::FORCED_PASSES.set(Some(passes));
                let out = dir.path().join(format!("{passes}.sfpm"));
                let made = convert(
                    &scene.join("sparse-map"),
                    &options,
                    &out,
                    &crate::progress::Silent,
                );
                super::super::stream::FORCED_PASSES.set(None);
                assert_eq!(made.unwrap().memory.unwrap().passes, passes);
                maps.push(std::fs::read(&out).unwrap());
            }
            assert!(maps[0] == maps[1], "{aggregate:?}: the maps differ");
        }
    }
}
