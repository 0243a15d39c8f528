//! Map building: everything that turns a COLMAP model into a map.
//!
//! - [`convert`] (`colmap`): a map of any local feature from a model and its `database.db`
//!   (SIFT, or a learned feature's typed rows) or hloc `features.h5` (descriptor aggregation
//!   per track, scale levels, a per-level PCA basis) — `sfpmap convert --colmap`;
//!   [`convert_model`] from a model in memory; [`convert_kapture`] from a kapture folder.
//! - [`convert_with_images`] (`colmap` + `onnx`): an SFP map from a model's images through the
//!   extractor — `sfpmap convert --images`; [`convert_model_with_images`] from a model in
//!   memory.
//! - [`pq`]: product quantisation of a map's levels (`slice --pq`, `convert --pq`);
//!   [`budget`]: the largest slice under a byte budget (`slice --budget`); [`catalog`]: a
//!   catalog of place maps (`sfpmap catalog`).
//!
//! The arrays a map stores of a model (cameras, points, images with poses, visibility) come
//! from a [`crate::colmap::Reconstruction`] or straight from a binary model's
//! bytes (a crate-private fast path).
//!
//! [`crate::colmap`] only reads and writes COLMAP files and databases and [`crate::extract`]
//! only runs the network; both are inputs here. Every map is written by
//! [`crate::format::MapWriter`].

#[cfg(feature = "colmap")]
mod basis;
pub mod budget;
#[cfg(feature = "colmap")]
pub mod catalog;
#[cfg(feature = "colmap")]
mod error;
#[cfg(feature = "colmap")]
pub(crate) mod features;
// Maps are built with `colmap`; the fuzz body of binary models (`fuzzing`) compares its fast
// path with the general reader.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
pub(crate) mod geometry;
#[cfg(feature = "colmap")]
mod kapture;
#[cfg(all(feature = "colmap", feature = "onnx"))]
mod network_tracks;
#[cfg(feature = "colmap")]
mod places;
pub mod pq;
#[cfg(feature = "colmap")]
mod retrieval;
#[cfg(all(feature = "colmap", feature = "onnx"))]
mod sfp;
/// `slice --short-dims`: a level's short block cut to fewer dimensions of its own PCA basis.
pub mod short_basis;
#[cfg(feature = "colmap")]
mod sift;
#[cfg(all(feature = "colmap", feature = "onnx"))]
mod snap;
#[cfg(feature = "colmap")]
mod stream;
#[cfg(all(feature = "colmap", feature = "onnx"))]
mod triangulation;

#[cfg(feature = "colmap")]
pub use error::ConvertError;
#[cfg(feature = "colmap")]
pub use kapture::convert_kapture;
#[cfg(feature = "colmap")]
pub use retrieval::{ImageIndexSummary, StoredVlad, VladOptions, MAX_INDEX_LISTS};
#[cfg(all(feature = "colmap", feature = "onnx"))]
pub use sfp::{convert_model_with_images, convert_with_images, SfpMapOptions, SfpMapSummary};
#[cfg(feature = "colmap")]
pub use sift::{convert, convert_model, Aggregate, ConvertOptions};
#[cfg(feature = "colmap")]
pub use stream::{default_memory_budget, MemoryPlan, MAX_PASSES};

#[cfg(feature = "colmap")]
use crate::colmap::{model_files, read_model, ModelFormat, Reconstruction};
#[cfg(feature = "colmap")]
use crate::format::{self, SourceFile};
#[cfg(feature = "colmap")]
use crate::progress::Reporter;
#[cfg(feature = "colmap")]
use geometry::Geometry;
#[cfg(feature = "colmap")]
use std::path::Path;

#[cfg(feature = "colmap")]
/// What one level of the converted map holds.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelSummary {
    /// The level.
    pub level: u16,
    /// Points in it.
    pub points: usize,
    /// Dimensions of its `full` descriptors.
    pub dim_full: u32,
    /// Dimensions of its `short` block (a prefix of `full`).
    pub dim_short: u32,
    /// Share of the descriptors' energy the `short` block keeps.
    pub variance_short: f64,
    /// Smallest and largest median keypoint scale (pixels) of the level's points.
    pub scale_range: [f32; 2],
}

/// What a conversion wrote: counts, sizes and each level (`sfpmap convert --json`).
#[cfg(feature = "colmap")]
#[derive(Debug, Clone, PartialEq)]
pub struct ConvertSummary {
    /// Points in the map (the model's, less those dropped).
    pub points: usize,
    /// Images in the map.
    pub images: usize,
    /// Observations (visibility entries) in the map.
    pub observations: usize,
    /// Model files plus database, in bytes.
    pub input_bytes: u64,
    /// The map's length in bytes.
    pub output_bytes: u64,
    /// No level holds descriptors: the database had none (a map for its geometry).
    pub geometry_only: bool,
    /// Each level, in order.
    pub levels: Vec<LevelSummary>,
    /// Images whose keypoints or descriptors are missing from the database.
    pub images_without_features: usize,
    /// Points none of whose observations has a descriptor (kept, but in no level).
    pub points_without_descriptors: usize,
    /// The VLAD stored for retrieval, if one was.
    pub vlad: Option<StoredVlad>,
    /// (1.3) The image index stored over the retrieval rows, if one was.
    pub index: Option<ImageIndexSummary>,
    /// Each product-quantised level (`--pq`), empty without.
    pub pq: Vec<pq::PqLevelSummary>,
    /// How the descriptors were made within the memory budget; `None`: a geometry-only map,
    /// or one built from images through the network (`--images`), which the budget does not
    /// govern.
    pub memory: Option<MemoryPlan>,
}

/// The writer of a converted map: provenance (the tool, the input files, the `parameters`
/// object), the codec, and the model's geometry already added.
#[cfg(feature = "colmap")]
fn map_writer<'a>(
    mut metadata: format::Metadata,
    sources: Vec<SourceFile>,
    parameters: serde_json::Value,
    codec: (format::Codec, i32),
    geometry: &'a Geometry,
) -> Result<format::MapWriter<'a>, ConvertError> {
    metadata.provenance.tool = format::Metadata::tool_string();
    metadata.provenance.sources = sources;
    metadata.provenance.parameters = parameters.as_object().cloned().unwrap_or_default();
    let mut writer = format::MapWriter::new(metadata);
    writer.set_codec(codec.0, codec.1);
    geometry.write_into(&mut writer)?;
    Ok(writer)
}

/// `parameters` with the caller's `job` record added under `job` (`ConvertOptions::job`).
#[cfg(feature = "colmap")]
fn with_job(
    mut parameters: serde_json::Value,
    job: Option<&serde_json::Value>,
) -> serde_json::Value {
    if let (Some(job), Some(object)) = (job, parameters.as_object_mut()) {
        object.insert("job".into(), job.clone());
    }
    parameters
}

#[cfg(feature = "colmap")]
/// A file's size and XXH3 for `provenance.sources`, read through a fixed buffer (a features
/// file or database may be tens of GB: neither mapped nor held); a file over
/// [`HASH_PROGRESS_BYTES`] reports its bytes to `reporter` as it goes.
pub(crate) fn source_file(
    path: &Path,
    reporter: &dyn Reporter,
) -> Result<SourceFile, ConvertError> {
    use std::io::Read;
    let io = |source| ConvertError::Io {
        path: path.to_path_buf(),
        source,
    };
    // Checked to be a regular file first: opening a FIFO would block.
    let mut file = crate::colmap::open_regular(path)?;
    let len = file.metadata().map_err(io)?.len();
    let shown = len > HASH_PROGRESS_BYTES;
    if shown {
        let name = path.file_name().unwrap_or(path.as_os_str());
        let stage = format!("hashing {}", crate::escape::path(Path::new(name)));
        reporter.start(&stage, Some(len));
    }
    let mut hasher = xxhash_rust::xxh3::Xxh3::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut bytes = 0u64;
    loop {
        let n = match file.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(io(e)),
        };
        hasher.update(&buf[..n]);
        bytes += n as u64;
        if shown {
            reporter.advance(n as u64);
        }
    }
    if shown {
        reporter.finish();
    }
    Ok(SourceFile {
        path: path.display().to_string(),
        bytes,
        xxh3: format::hash_hex(hasher.digest()),
    })
}

/// Source files larger than this show their hashing as a stage of its own.
#[cfg(feature = "colmap")]
const HASH_PROGRESS_BYTES: u64 = 256 << 20;

#[cfg(feature = "colmap")]
/// Reads the model in `model_dir` and describes its files (size, hash) for provenance.
pub(crate) fn read_model_with_sources(
    model_dir: &Path,
    reporter: &dyn Reporter,
) -> Result<(Reconstruction, Vec<SourceFile>), ConvertError> {
    let files = model_files(model_dir)?;
    reporter.start("reading model", None);
    let model = read_model(model_dir)?;
    reporter.finish();
    let sources = files
        .paths
        .iter()
        .map(|p| source_file(p, reporter))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((model, sources))
}

#[cfg(feature = "colmap")]
/// Reads the model in `model_dir` as the map's geometry, with its files' provenance.
///
/// A binary model goes the fast way ([`geometry::read_bin`]) while another thread
/// hashes the files; anything that way declines (errors included) goes the general way.
fn read_geometry_with_sources(
    model_dir: &Path,
    reporter: &dyn Reporter,
) -> Result<(Geometry, Vec<SourceFile>), ConvertError> {
    let files = model_files(model_dir)?;
    if files.format == ModelFormat::Binary {
        reporter.start("reading model", None);
        let (geometry, sources) = std::thread::scope(|s| {
            // Silent: the "reading model" stage is the one shown meanwhile.
            let sources = s.spawn(|| {
                files
                    .paths
                    .iter()
                    .map(|p| source_file(p, &crate::progress::Silent))
                    .collect::<Result<Vec<_>, _>>()
            });
            let geometry = geometry::read_bin(model_dir);
            let sources = sources
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
            (geometry, sources)
        });
        reporter.finish();
        if let Some(geometry) = geometry {
            return Ok((geometry, sources?));
        }
    }
    let (model, sources) = read_model_with_sources(model_dir, reporter)?;
    Ok((Geometry::new(&model, None), sources))
}

#[cfg(feature = "colmap")]
impl ConvertSummary {
    /// The `convert --json` object of a SIFT or geometry-only map written to `out` in
    /// `seconds` (the CLI and the Python package print this).
    pub fn report(&self, out: &Path, seconds: f64) -> serde_json::Value {
        let s = self;
        let levels: Vec<_> = s
            .levels
            .iter()
            .map(|l| {
                serde_json::json!({
                    "level": l.level, "points": l.points, "dim_full": l.dim_full, "dim_short": l.dim_short,
                    "variance_short": l.variance_short, "scale_range": l.scale_range,
                })
            })
            .collect();
        serde_json::json!({
            "output": out.display().to_string(),
            "points": s.points,
            "images": s.images,
            "observations": s.observations,
            "input_bytes": s.input_bytes,
            "output_bytes": s.output_bytes,
            "ratio": s.input_bytes as f64 / s.output_bytes.max(1) as f64,
            "seconds": seconds,
            "geometry_only": s.geometry_only,
            "levels": levels,
            "images_without_features": s.images_without_features,
            "points_without_descriptors": s.points_without_descriptors,
            "vlad": s.vlad.map(|v| serde_json::json!({"level": v.level, "clusters": v.clusters, "dims": v.dims})),
            "image_index": s.index.as_ref().map(|i| serde_json::json!({"of": i.of.name(), "lists": i.lists, "probe": i.probe, "recall": i.recall, "scored": i.scored, "stored": i.stored})),
            "memory": s.memory.map(|m| serde_json::json!({"budget": m.budget, "passes": m.passes, "planned_peak": m.peak})),
        })
    }
}
