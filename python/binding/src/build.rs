//! `convert`, `slice` and `from_pycolmap`: the CLI's map building, as functions. Each returns
//! the object the CLI's `--json` prints (as JSON text; `sfpmap/__init__.py` parses it).

use crate::errors::{
    chain, format_error, level_arg, no_such_level, output_error, within, ConvertError, FileError,
    InputError,
};
use crate::Warnings;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use sfpmap::build::{Aggregate, ConvertOptions, SfpMapOptions, VladOptions};
use sfpmap::colmap::{Camera as ColmapCamera, Image, Point2D, Reconstruction, TrackElement};
use sfpmap::format::Codec;
use sfpmap::geometry::{CameraModel, Pose};
use sfpmap::progress::Silent;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Every failure of a conversion is a `ConvertError`, its files' and its extractor's included
/// (which `sfpmap::ErrorKind` tells apart): not a classification by kind but what the class
/// has always stood for, "this model cannot be converted".
fn convert_error(e: sfpmap::build::ConvertError) -> PyErr {
    ConvertError::new_err(chain(&e))
}

fn codec(name: &str) -> PyResult<Codec> {
    match name {
        "raw" => Ok(Codec::Raw),
        "zstd" => Ok(Codec::Zstd),
        other => Err(InputError::new_err(format!(
            "codec {other:?}: \"raw\" or \"zstd\""
        ))),
    }
}

/// Options shared by `convert` and `from_pycolmap`, checked as the CLI's parser checks them.
#[derive(Clone)]
struct Options {
    database: Option<PathBuf>,
    /// hloc features.h5 (`--features`), its feature's name (`--feature-name`) and global
    /// descriptors (`--global-features`).
    features: Option<PathBuf>,
    feature_name: Option<String>,
    global_features: Option<PathBuf>,
    images: Option<PathBuf>,
    model: Option<PathBuf>,
    allow_missing: bool,
    threads: usize,
    resize_max: Option<u32>,
    /// `SfpMapOptions::global_max_side` (None: the network input).
    global_max_side: Option<u32>,
    score_threshold: Option<f32>,
    short_dims: Option<u32>,
    codec: Codec,
    zstd_level: i32,
    aggregate: Aggregate,
    strict: bool,
    vlad: VladOptions,
    pq: Option<usize>,
    /// `ConvertOptions::job`: the caller's record, kept in provenance.
    job: Option<serde_json::Value>,
    /// `ConvertOptions::memory`: the budget in bytes (`--memory`).
    memory: Option<u64>,
}

impl Options {
    #[allow(clippy::too_many_arguments)]
    fn new(
        database: Option<PathBuf>,
        images: Option<PathBuf>,
        model: Option<PathBuf>,
        allow_missing: bool,
        threads: usize,
        resize_max: Option<u32>,
        global_max_side: Option<u32>,
        score_threshold: Option<f32>,
        short_dims: Option<u32>,
        codec_name: &str,
        zstd_level: i32,
        aggregate: Option<&str>,
        strict: bool,
        vlad_clusters: Option<usize>,
        vlad_dims: Option<usize>,
        pq: Option<usize>,
        index_lists: Option<usize>,
    ) -> PyResult<Options> {
        let bad = |m: String| Err(InputError::new_err(m));
        // `sfpmap convert`'s parser: `--images` conflicts with `--database`, `--short-dims`,
        // `--aggregate` and `--strict` (cli/convert.rs, `conflicts_with_all`); the first
        // conflict, in the words of its one-line error.
        if images.is_some() {
            let given = [
                (database.is_some(), "--database <DATABASE>"),
                (short_dims.is_some(), "--short-dims <SHORT_DIMS>"),
                (aggregate.is_some(), "--aggregate <AGGREGATE>"),
                (strict, "--strict"),
            ];
            if let Some((_, flag)) = given.iter().find(|(given, _)| *given) {
                return bad(format!(
                    "the argument '--images <IMAGES>' cannot be used with '{flag}'"
                ));
            }
        }
        if images.is_none()
            && (model.is_some()
                || allow_missing
                || resize_max.is_some()
                || global_max_side.is_some())
        {
            return bad("model, allow_missing, resize_max and global_max_side need images".into());
        }
        // As `--global-max-side`: 0 or at least GLOBAL_MIN_SIDE; default GLOBAL_MAX_SIDE.
        let global_max_side = match global_max_side {
            None => Some(sfpmap::extract::GLOBAL_MAX_SIDE),
            Some(side) => sfpmap::extract::GlobalSize::from_flag(side)
                .map_err(|e| InputError::new_err(format!("global_max_side {e}")))?
                .max_side(),
        };
        if images.is_none() && score_threshold.is_some() {
            return bad("score_threshold needs images".into());
        }
        if let Some(t) = score_threshold {
            if let Err(expected) = sfpmap::ranges::SCORE.check(t.into()) {
                return bad(format!("score_threshold {t}: {expected}"));
            }
        }
        if short_dims == Some(0) {
            return bad("short_dims: at least 1".into());
        }
        if resize_max.is_some_and(|r| r < 16) {
            return bad("resize_max: at least 16".into());
        }
        if !(1..=22).contains(&zstd_level) {
            return bad(format!("zstd_level {zstd_level}: 1 to 22"));
        }
        let most = sfpmap::vlad::MAX_CLUSTERS;
        if vlad_clusters.is_some_and(|k| k > most) {
            return bad(format!(
                "vlad_clusters: a number of centroids from 0 (no VLAD) to {most}"
            ));
        }
        if pq.is_some_and(|m| !(1..=4096).contains(&m)) {
            return bad("pq: 1 to 4096 one-byte codes per point".into());
        }
        if vlad_dims.is_some_and(|d| !(1..=256).contains(&d)) {
            return bad("vlad_dims: a number of dimensions from 1 to 256".into());
        }
        let max_lists = sfpmap::build::MAX_INDEX_LISTS;
        if index_lists.is_some_and(|n| n > max_lists) {
            return bad(format!(
                "index_lists: a number of lists from 0 (no index) to {max_lists}"
            ));
        }
        let aggregate = match aggregate.unwrap_or("mean") {
            "mean" => Aggregate::Mean,
            "medoid" => Aggregate::Medoid,
            other => return bad(format!("aggregate {other:?}: \"mean\" or \"medoid\"")),
        };
        Ok(Options {
            database,
            features: None,
            feature_name: None,
            global_features: None,
            images,
            model,
            allow_missing,
            threads,
            resize_max,
            global_max_side,
            score_threshold,
            short_dims,
            codec: codec(codec_name)?,
            zstd_level,
            aggregate,
            strict,
            vlad: VladOptions {
                clusters: vlad_clusters,
                index_lists,
                dims: vlad_dims,
            },
            pq,
            job: None,
            memory: None,
        })
    }

    /// `memory` (`--memory`, bytes): not with `images` (the CLI's parser refuses them
    /// together), not negative.
    fn with_memory(mut self, memory: Option<i64>) -> PyResult<Options> {
        if self.images.is_some() && memory.is_some() {
            return Err(InputError::new_err(
                "the argument '--images <IMAGES>' cannot be used with '--memory <SIZE>'",
            ));
        }
        self.memory = match memory {
            Some(m) => Some(u64::try_from(m).map_err(|_| {
                InputError::new_err(format!("memory: {m} is not a number of bytes"))
            })?),
            None => None,
        };
        Ok(self)
    }

    /// `features`, `feature_name` and `global_features`, refused where the CLI's parser
    /// refuses them (`--features` with `--database` or `--images`, …).
    fn with_features(
        mut self,
        features: Option<PathBuf>,
        feature_name: Option<String>,
        global_features: Option<PathBuf>,
        kapture: bool,
    ) -> PyResult<Options> {
        let bad = |m: &str| Err(InputError::new_err(m.to_string()));
        if features.is_some() && self.database.is_some() {
            return bad(
                "the argument '--features <FEATURES>' cannot be used with '--database <DATABASE>'",
            );
        }
        if self.images.is_some() && (features.is_some() || global_features.is_some()) {
            return bad("images cannot be used with features or global_features");
        }
        if feature_name.is_some() && features.is_none() && !kapture {
            return bad("feature_name needs features or kapture");
        }
        self.features = features;
        self.feature_name = feature_name;
        self.global_features = global_features;
        Ok(self)
    }

    fn sift(&self) -> ConvertOptions {
        ConvertOptions {
            database: self.database.clone(),
            features: self.features.clone(),
            feature_name: self.feature_name.clone(),
            global_features: self.global_features.clone(),
            short_dims: self.short_dims,
            codec: self.codec,
            zstd_level: self.zstd_level,
            aggregate: self.aggregate,
            strict: self.strict,
            vlad: self.vlad,
            pq: self.pq,
            job: self.job.clone(),
            memory: self.memory,
        }
    }

    fn sfp(&self, images: &Path) -> SfpMapOptions {
        SfpMapOptions {
            images: images.to_path_buf(),
            extractor: sfpmap::extract::ExtractorOptions {
                model: self.model.clone(),
                threads: self.threads,
            },
            resize_max: self.resize_max,
            global_max_side: self.global_max_side,
            score_threshold: self.score_threshold,
            allow_missing: self.allow_missing,
            // `convert --images --snap` and `--triangulate` are the CLI's for now (issue 36: off by
            // default while they are measured).
            snap: false,
            triangulate: false,
            codec: self.codec,
            zstd_level: self.zstd_level,
            vlad: self.vlad,
            pq: self.pq,
            job: self.job.clone(),
        }
    }

    /// The CLI's output policy: `out` may not be an input, lie inside an input folder (the
    /// images, `kapture`), or exist without `force`.
    fn check_output(
        &self,
        model_files: &[PathBuf],
        out: &Path,
        force: bool,
        kapture: Option<&Path>,
    ) -> PyResult<()> {
        let mut inputs: Vec<&Path> = model_files.iter().map(|p| p.as_path()).collect();
        inputs.extend(self.database.as_deref());
        inputs.extend(self.features.as_deref());
        inputs.extend(self.global_features.as_deref());
        inputs.extend(self.model.as_deref());
        // A folder input (the model's images, a kapture folder with files its tables do not
        // list) gets nothing new inside it.
        let folders: Vec<&Path> = kapture.into_iter().chain(self.images.as_deref()).collect();
        sfpmap::output::check_outside(out, &folders).map_err(output_error)?;
        sfpmap::output::check_output(out, &inputs, force).map_err(output_error)
    }
}

/// What `convert` reads its model from: a COLMAP model folder (`--colmap`) or a kapture
/// folder (`--kapture`) with the keypoints and descriptors types to read there.
enum Source {
    Colmap(PathBuf),
    Kapture(PathBuf, sfpmap::io::kapture::KaptureOptions),
}

/// `model_dir` or `kapture`, exactly one, refused as `sfpmap convert`'s parser refuses
/// `--colmap` with `--kapture` (or neither), `--kapture` with `--database`, and the kapture
/// types without `--kapture`.
fn source(
    model_dir: Option<PathBuf>,
    kapture: Option<PathBuf>,
    database: bool,
    keypoints_type: Option<String>,
    descriptors_type: Option<String>,
) -> PyResult<Source> {
    let bad = |m: &str| Err(InputError::new_err(m.to_string()));
    match (model_dir, kapture) {
        (Some(_), Some(_)) => {
            bad("the argument '--colmap <COLMAP>' cannot be used with '--kapture <DIR>'")
        }
        (None, None) => {
            bad("the following required arguments were not provided: --colmap <COLMAP>")
        }
        (Some(model_dir), None) => {
            if keypoints_type.is_some() || descriptors_type.is_some() {
                return bad("keypoints_type and descriptors_type need kapture");
            }
            Ok(Source::Colmap(model_dir))
        }
        (None, Some(_)) if database => {
            bad("the argument '--kapture <DIR>' cannot be used with '--database <DATABASE>'")
        }
        (None, Some(dir)) => Ok(Source::Kapture(
            dir,
            sfpmap::io::kapture::KaptureOptions {
                keypoints_type,
                descriptors_type,
            },
        )),
    }
}

/// A `job` argument (JSON text from the package's Python half): an object, kept in a written
/// map's `provenance.parameters.job`.
pub(crate) fn job_record(text: Option<&str>) -> PyResult<Option<serde_json::Value>> {
    text.map(
        |text| match serde_json::from_str::<serde_json::Value>(text) {
            Ok(v) if v.is_object() => Ok(v),
            _ => Err(InputError::new_err("job: a JSON object")),
        },
    )
    .transpose()
}

/// `sfpmap convert`: a COLMAP model folder (+ `database` for a SIFT map, or `images` for an
/// SFP map), or a kapture folder (`kapture`, with its own keypoints and descriptors), into the
/// map `out`. Returns what `convert --json` prints (as JSON text).
#[pyfunction]
#[pyo3(signature = (model_dir=None, database=None, images=None, *, out, force=false, model=None,
                    allow_missing=false, threads=2, resize_max=None, global_max_side=None,
                    score_threshold=None, short_dims=None, codec="raw", zstd_level=3, aggregate=None, strict=false,
                    vlad_clusters=None, vlad_dims=None, pq=None, features=None, feature_name=None,
                    global_features=None, kapture=None, keypoints_type=None, descriptors_type=None,
                    index_lists=None, job=None, memory=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn convert(
    py: Python<'_>,
    model_dir: Option<PathBuf>,
    database: Option<PathBuf>,
    images: Option<PathBuf>,
    out: PathBuf,
    force: bool,
    model: Option<PathBuf>,
    allow_missing: bool,
    threads: i64,
    resize_max: Option<u32>,
    global_max_side: Option<u32>,
    score_threshold: Option<f32>,
    short_dims: Option<u32>,
    codec: &str,
    zstd_level: i32,
    aggregate: Option<&str>,
    strict: bool,
    vlad_clusters: Option<usize>,
    vlad_dims: Option<usize>,
    pq: Option<usize>,
    features: Option<PathBuf>,
    feature_name: Option<String>,
    global_features: Option<PathBuf>,
    kapture: Option<PathBuf>,
    keypoints_type: Option<String>,
    descriptors_type: Option<String>,
    index_lists: Option<usize>,
    job: Option<&str>,
    memory: Option<i64>,
) -> PyResult<String> {
    let start = Instant::now();
    let source = source(
        model_dir,
        kapture,
        database.is_some(),
        keypoints_type,
        descriptors_type,
    )?;
    if matches!(source, Source::Kapture(..)) {
        // `convert --kapture`'s own refusals, in its words (cli/convert.rs).
        if images.is_some() {
            return Err(InputError::new_err(
                "--images builds from a COLMAP model: pass --colmap, not --kapture",
            ));
        }
        if features.is_some() {
            return Err(InputError::new_err(
                "--kapture holds its own features: drop --features",
            ));
        }
    }
    // As the CLI: 0 is refused, the cap (and its warning) applies where threads are used.
    let threads = match (&images, threads) {
        (Some(_), _) | (None, ..=0) => crate::thread_count(py, Some(threads))?,
        (None, n) => n as usize,
    };
    let mut o = Options::new(
        database,
        images,
        model,
        allow_missing,
        threads,
        resize_max,
        global_max_side,
        score_threshold,
        short_dims,
        codec,
        zstd_level,
        aggregate,
        strict,
        vlad_clusters,
        vlad_dims,
        pq,
        index_lists,
    )?
    .with_features(
        features,
        feature_name,
        global_features,
        matches!(source, Source::Kapture(..)),
    )?;
    o.job = job_record(job)?;
    let o = o.with_memory(memory)?;
    let files = match &source {
        Source::Colmap(model_dir) => sfpmap::colmap::model_files(model_dir)
            .map(|f| f.paths)
            .unwrap_or_default(),
        Source::Kapture(dir, _) => sfpmap::io::kapture::tables(dir),
    };
    let kapture = match &source {
        Source::Kapture(dir, _) => Some(dir.as_path()),
        Source::Colmap(_) => None,
    };
    o.check_output(&files, &out, force, kapture)?;
    // The library's warnings (ONNX Runtime fetched, images missing or without features) as
    // `RuntimeWarning`s, as the CLI prints them.
    let warnings = Warnings::default();
    let value = py.detach(|| -> PyResult<serde_json::Value> {
        match (&source, &o.images) {
            (Source::Colmap(model_dir), Some(images)) => {
                let s =
                    sfpmap::build::convert_with_images(model_dir, &o.sfp(images), &out, &warnings)
                        .map_err(convert_error)?;
                Ok(s.report(&out, start.elapsed().as_secs_f64()))
            }
            (Source::Colmap(model_dir), None) => {
                let s = sfpmap::build::convert(model_dir, &o.sift(), &out, &warnings)
                    .map_err(convert_error)?;
                Ok(s.report(&out, start.elapsed().as_secs_f64()))
            }
            // Refused above: `images` with `kapture`.
            (Source::Kapture(dir, kapture_options), _) => {
                let s = sfpmap::build::convert_kapture(
                    dir,
                    kapture_options,
                    &o.sift(),
                    &out,
                    &warnings,
                )
                .map_err(convert_error)?;
                Ok(s.report(&out, start.elapsed().as_secs_f64()))
            }
        }
    });
    Ok(warnings.emit_then(py, value)?.to_string())
}

/// `sfpmap slice`: keep `levels` of the map at `map_path` (and only their short descriptor
/// blocks with `short`; only what localization reads with `minimal`; product-quantised into
/// `pq` codes per point; with `short`, cut to `short_dims` dimensions of each level's own PCA
/// basis), written to `out`; or, with `budget` (bytes), the levels, blocks,
/// `minimal` and `pq` that fit it best (`slice --budget`; `levels`, if any, the only level set
/// tried). Returns what `slice --json` prints.
#[pyfunction]
#[pyo3(signature = (map_path, levels, short=false, *, out, minimal=false, pq=None, codec=None,
                    zstd_level=3, force=false, budget=None, short_dims=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn slice(
    py: Python<'_>,
    map_path: PathBuf,
    levels: Vec<Bound<'_, PyAny>>,
    short: bool,
    out: PathBuf,
    minimal: bool,
    pq: Option<u16>,
    codec: Option<&str>,
    zstd_level: i32,
    force: bool,
    budget: Option<u64>,
    short_dims: Option<u16>,
) -> PyResult<String> {
    use sfpmap::build::pq::slice_encoded;
    if levels.is_empty() && budget.is_none() {
        return Err(InputError::new_err("levels: at least one level to keep"));
    }
    if budget.is_some() && (short || minimal || pq.is_some() || short_dims.is_some()) {
        return Err(InputError::new_err(
            "budget chooses short, minimal and pq itself: pass none of them (nor short_dims)",
        ));
    }
    if short_dims.is_some() && (!short || pq.is_some()) {
        return Err(InputError::new_err(
            "short_dims: needs short=True and no pq",
        ));
    }
    if short_dims == Some(0) {
        return Err(InputError::new_err("short_dims: at least 1 dimension"));
    }
    if !(1..=22).contains(&zstd_level) {
        return Err(InputError::new_err(format!(
            "zstd_level {zstd_level}: 1 to 22"
        )));
    }
    if pq.is_some_and(|m| !(1..=4096).contains(&m)) {
        return Err(InputError::new_err(
            "pq: 1 to 4096 one-byte codes per point",
        ));
    }
    let mut options = sfpmap::format::SliceOptions {
        levels: Vec::new(),
        short,
        codec: codec.map(self::codec).transpose()?,
        zstd_level,
        minimal,
    };
    // Ids, or the text of an int no level can be (refused once the map's levels are known).
    let levels: Vec<Result<u16, String>> = levels.iter().map(level_arg).collect::<PyResult<_>>()?;
    sfpmap::output::check_output(&out, &[&map_path], force).map_err(output_error)?;
    let value = py.detach(|| -> PyResult<serde_json::Value> {
        let map = sfpmap::format::Map::open(&map_path).map_err(|e| format_error(&map_path, e))?;
        options.levels = levels
            .into_iter()
            .collect::<Result<_, String>>()
            .map_err(|bad| no_such_level(&map_path, &bad, &map.level_ids()))?;
        let (sliced, budget_report) = match budget {
            Some(bytes) => {
                let levels = (!options.levels.is_empty()).then_some(&options.levels[..]);
                let chosen = sfpmap::build::budget::slice_to_budget(&map, bytes, levels)
                    .map_err(|e| format_error(&map_path, e))?;
                let report = chosen.report(bytes);
                (chosen.sliced, Some(report))
            }
            None => (
                slice_encoded(
                    &map,
                    &options,
                    short_dims.map(usize::from),
                    pq.map(usize::from),
                )
                .map_err(|e| format_error(&map_path, e))?,
                None,
            ),
        };
        let written = sliced.writer.write(&out, &Silent).map_err(|e| match e {
            sfpmap::format::Error::Io { .. } => FileError::new_err(chain(&e)),
            e => FileError::new_err(within(&out.display().to_string(), &e)),
        })?;
        let mut report = sliced.report(&map_path, &out, map.file_len(), written);
        if let Some(b) = budget_report {
            report["budget"] = b;
        }
        Ok(report)
    })?;
    Ok(value.to_string())
}

/// Why an object could not be read as a reconstruction: Python raised (a missing attribute, a
/// value of the wrong type), or a value is not one a model can hold.
enum Bad {
    Python(PyErr),
    Value(String),
}

impl From<PyErr> for Bad {
    fn from(e: PyErr) -> Bad {
        Bad::Python(e)
    }
}

/// `bad` as a `ConvertError` `pycolmap reconstruction: {item}: ...` (`item`: `camera 1`,
/// `image 3`, `point3D 7`; `None` for the reconstruction itself), Python's exception as its
/// `__cause__`. An exception that is no error of the object (`KeyboardInterrupt`, ...)
/// passes as it is.
fn failure(py: Python<'_>, item: Option<&str>, bad: Bad) -> PyErr {
    let context = match item {
        Some(item) => format!("pycolmap reconstruction: {item}"),
        None => "pycolmap reconstruction".to_string(),
    };
    match bad {
        Bad::Value(what) => ConvertError::new_err(format!("{context}: {what}")),
        Bad::Python(e) if !e.is_instance_of::<PyException>(py) => e,
        Bad::Python(e) => {
            let converted = ConvertError::new_err(format!("{context}: {e}"));
            converted.set_cause(py, Some(e));
            converted
        }
    }
}

/// A key of one of the reconstruction's maps as an error names it: the id, or the `repr` of
/// a key that is no id.
fn key_text(key: &Bound<'_, PyAny>) -> String {
    match key.extract::<u64>() {
        Ok(id) => id.to_string(),
        Err(_) => key
            .repr()
            .map_or_else(|_| "?".to_string(), |r| r.to_string()),
    }
}

/// A list of floats, or an array's (`tolist()`).
fn floats(v: Bound<'_, PyAny>) -> PyResult<Vec<f64>> {
    match v.extract::<Vec<f64>>() {
        Ok(x) => Ok(x),
        Err(_) => v.call_method0("tolist")?.extract(),
    }
}

/// The `(key, value)` pairs of one of the reconstruction's maps (`cameras`, `images`,
/// `points3D`: dicts by id, in pycolmap as in a plain `dict`).
fn items<'py>(rec: &Bound<'py, PyAny>, name: &str) -> Result<Vec<Bound<'py, PyAny>>, Bad> {
    let mut all = Vec::new();
    for item in rec.getattr(name)?.call_method0("items")?.try_iter()? {
        all.push(item?);
    }
    Ok(all)
}

fn read_camera(c: &Bound<'_, PyAny>) -> Result<ColmapCamera, Bad> {
    let id: u32 = c.getattr("camera_id")?.extract()?;
    let model = c.getattr("model")?;
    let name: String = match model.extract::<String>() {
        Ok(s) => s,
        Err(_) => model.getattr("name")?.extract()?,
    };
    let model = CameraModel::from_name(&name)
        .ok_or_else(|| Bad::Value(format!("unknown model {name:?}")))?;
    Ok(ColmapCamera {
        id,
        model,
        width: c.getattr("width")?.extract()?,
        height: c.getattr("height")?.extract()?,
        params: floats(c.getattr("params")?)?,
    })
}

/// A registered image; `None` for one without a pose (pycolmap >= 3.12 keeps unregistered
/// frames; a model file holds registered images only).
fn read_image(im: &Bound<'_, PyAny>) -> Result<Option<Image>, Bad> {
    let id: u32 = im.getattr("image_id")?.extract()?;
    if let Ok(has_pose) = im.getattr("has_pose") {
        if !has_pose.extract::<bool>()? {
            return Ok(None);
        }
    }
    let mut pose = im.getattr("cam_from_world")?;
    if pose.is_callable() {
        pose = pose.call0()?;
    }
    let q = floats(pose.getattr("rotation")?.getattr("quat")?)?;
    let t = floats(pose.getattr("translation")?)?;
    if q.len() != 4 || t.len() != 3 {
        return Err(Bad::Value(format!(
            "a pose of {} + {} values",
            q.len(),
            t.len()
        )));
    }
    // pycolmap's quaternions are [x, y, z, w].
    let cam_from_world = Pose::from_colmap(q[3], q[0], q[1], q[2], t[0], t[1], t[2])
        .map_err(|e| Bad::Value(chain(&e)))?;
    let mut points2d = Vec::new();
    for (i, p) in im.getattr("points2D")?.try_iter()?.enumerate() {
        let p = p?;
        let xy = floats(p.getattr("xy")?)?;
        let point3d: u64 = p.getattr("point3D_id")?.extract()?;
        if xy.len() != 2 {
            return Err(Bad::Value(format!(
                "point2D {i}: {} values for xy",
                xy.len()
            )));
        }
        points2d.push(Point2D {
            xy: [xy[0], xy[1]],
            point3d_id: (point3d != u64::MAX).then_some(point3d),
        });
    }
    Ok(Some(Image {
        id,
        name: im.getattr("name")?.extract()?,
        camera_id: im.getattr("camera_id")?.extract()?,
        cam_from_world,
        points2d,
    }))
}

/// A 3D point: position, colour, error and track (into `track`).
fn read_point(
    p: &Bound<'_, PyAny>,
    track: &mut Vec<TrackElement>,
) -> Result<([f64; 3], [u8; 3], f64), Bad> {
    let xyz = floats(p.getattr("xyz")?)?;
    let color: Vec<u8> = match p.getattr("color")?.extract::<Vec<u8>>() {
        Ok(c) => c,
        Err(_) => p.getattr("color")?.call_method0("tolist")?.extract()?,
    };
    if xyz.len() != 3 || color.len() != 3 {
        return Err(Bad::Value("xyz or color is not 3 values".into()));
    }
    track.clear();
    for e in p.getattr("track")?.getattr("elements")?.try_iter()? {
        let e = e?;
        track.push(TrackElement {
            image_id: e.getattr("image_id")?.extract()?,
            point2d_idx: e.getattr("point2D_idx")?.extract()?,
        });
    }
    Ok((
        [xyz[0], xyz[1], xyz[2]],
        [color[0], color[1], color[2]],
        p.getattr("error")?.extract()?,
    ))
}

/// A pycolmap `Reconstruction` as the library's model, read through its attributes. An object
/// that is not one (a missing attribute, a value of the wrong type) is a `ConvertError` naming
/// the camera, image or point3D at fault and what Python said (`pycolmap reconstruction:
/// point3D 7: AttributeError: ...`), with that exception as its `__cause__`; the model's own
/// checks (ids, tracks) are the library's errors, as for model files.
fn reconstruction_of(rec: &Bound<'_, PyAny>) -> PyResult<Reconstruction> {
    let py = rec.py();
    let whole = |bad: Bad| failure(py, None, bad);
    let mut builder = Reconstruction::builder().paths(
        Path::new("pycolmap cameras"),
        Path::new("pycolmap images"),
        Path::new("pycolmap points3D"),
    );
    for item in items(rec, "cameras").map_err(whole)? {
        let (key, c): (Bound<'_, PyAny>, Bound<'_, PyAny>) =
            item.extract().map_err(|e: PyErr| whole(e.into()))?;
        let camera = read_camera(&c)
            .map_err(|bad| failure(py, Some(&format!("camera {}", key_text(&key))), bad))?;
        builder.add_camera(camera);
    }
    for item in items(rec, "images").map_err(whole)? {
        let (key, im): (Bound<'_, PyAny>, Bound<'_, PyAny>) =
            item.extract().map_err(|e: PyErr| whole(e.into()))?;
        let image = read_image(&im)
            .map_err(|bad| failure(py, Some(&format!("image {}", key_text(&key))), bad))?;
        if let Some(image) = image {
            builder.add_image(image);
        }
    }
    let mut track = Vec::new();
    for item in items(rec, "points3D").map_err(whole)? {
        let (key, p): (Bound<'_, PyAny>, Bound<'_, PyAny>) =
            item.extract().map_err(|e: PyErr| whole(e.into()))?;
        let at = || format!("point3D {}", key_text(&key));
        let id: u64 = key
            .extract()
            .map_err(|e: PyErr| failure(py, Some(&at()), e.into()))?;
        let (xyz, color, error) =
            read_point(&p, &mut track).map_err(|bad| failure(py, Some(&at()), bad))?;
        builder
            .add_point3d(id, xyz, color, error, &track)
            .map_err(|e| ConvertError::new_err(chain(&e)))?;
    }
    builder
        .build()
        .map_err(|e| ConvertError::new_err(chain(&e)))
}

/// `convert` of a pycolmap `Reconstruction` in memory (no temp files): the same map as
/// `sfpmap convert` of the model's files, but for provenance, which records `source` as the
/// model and lists no model files.
#[pyfunction]
#[pyo3(signature = (reconstruction, database=None, images=None, *, out, force=false,
                    source="pycolmap.Reconstruction", model=None, allow_missing=false, threads=2,
                    resize_max=None, global_max_side=None, score_threshold=None,
                    short_dims=None, codec="raw",
                    zstd_level=3, aggregate=None, strict=false,
                    vlad_clusters=None, vlad_dims=None, pq=None, features=None,
                    feature_name=None, global_features=None, index_lists=None, memory=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn from_pycolmap(
    py: Python<'_>,
    reconstruction: &Bound<'_, PyAny>,
    database: Option<PathBuf>,
    images: Option<PathBuf>,
    out: PathBuf,
    force: bool,
    source: &str,
    model: Option<PathBuf>,
    allow_missing: bool,
    threads: i64,
    resize_max: Option<u32>,
    global_max_side: Option<u32>,
    score_threshold: Option<f32>,
    short_dims: Option<u32>,
    codec: &str,
    zstd_level: i32,
    aggregate: Option<&str>,
    strict: bool,
    vlad_clusters: Option<usize>,
    vlad_dims: Option<usize>,
    pq: Option<usize>,
    features: Option<PathBuf>,
    feature_name: Option<String>,
    global_features: Option<PathBuf>,
    index_lists: Option<usize>,
    memory: Option<i64>,
) -> PyResult<String> {
    let start = Instant::now();
    // As the CLI: 0 is refused, the cap (and its warning) applies where threads are used.
    let threads = match (&images, threads) {
        (Some(_), _) | (None, ..=0) => crate::thread_count(py, Some(threads))?,
        (None, n) => n as usize,
    };
    let o = Options::new(
        database,
        images,
        model,
        allow_missing,
        threads,
        resize_max,
        global_max_side,
        score_threshold,
        short_dims,
        codec,
        zstd_level,
        aggregate,
        strict,
        vlad_clusters,
        vlad_dims,
        pq,
        index_lists,
    )?
    .with_features(features, feature_name, global_features, false)?
    .with_memory(memory)?;
    o.check_output(&[], &out, force, None)?;
    let rec = reconstruction_of(reconstruction)?;
    let warnings = Warnings::default();
    let value = py.detach(|| -> PyResult<serde_json::Value> {
        match &o.images {
            Some(images) => {
                let s = sfpmap::build::convert_model_with_images(
                    &rec,
                    source,
                    &o.sfp(images),
                    &out,
                    &warnings,
                )
                .map_err(convert_error)?;
                Ok(s.report(&out, start.elapsed().as_secs_f64()))
            }
            None => {
                let s = sfpmap::build::convert_model(&rec, source, &o.sift(), &out, &warnings)
                    .map_err(convert_error)?;
                Ok(s.report(&out, start.elapsed().as_secs_f64()))
            }
        }
    });
    Ok(warnings.emit_then(py, value)?.to_string())
}

/// A synthetic map of `points` points and one level of `dim_full` f16 dimensions (`dim_short`
/// of them short), for the tests and benchmarks that need a large map quickly (a 1 GB map
/// is 2.2 M points of 240 dims). Not part of the documented API.
///
/// Bounded before anything is allocated: `dim_full` at most the format's
/// `MAX_DESCRIPTOR_DIM`, and `points × (2 × dim_full + 16)` bytes (descriptors, positions,
/// indices) at most [`SYNTHETIC_MAX_BYTES`]; `path` is the CLI's output (no existing file
/// without `force`).
#[pyfunction]
#[pyo3(name = "_write_synthetic_map", signature = (path, points, dim_full, dim_short, force=false))]
pub(crate) fn write_synthetic_map(
    py: Python<'_>,
    path: PathBuf,
    points: u64,
    dim_full: u32,
    dim_short: u32,
    force: bool,
) -> PyResult<u64> {
    use sfpmap::format::{f16, Descriptors, LevelInfo, MapWriter, Metadata, MAX_DESCRIPTOR_DIM};
    if points == 0 || dim_short == 0 || dim_short > dim_full {
        return Err(InputError::new_err(
            "points >= 1, 1 <= dim_short <= dim_full",
        ));
    }
    if u64::from(dim_full) > MAX_DESCRIPTOR_DIM {
        return Err(InputError::new_err(format!(
            "dim_full {dim_full}: at most {MAX_DESCRIPTOR_DIM} (the format's limit)"
        )));
    }
    let bytes = points
        .checked_mul(2 * u64::from(dim_full) + 16)
        .filter(|&b| b <= SYNTHETIC_MAX_BYTES);
    let (Some(_), Ok(n)) = (bytes, usize::try_from(points)) else {
        return Err(InputError::new_err(format!(
            "{points} points of {dim_full} dims: over {} GiB in memory",
            SYNTHETIC_MAX_BYTES >> 30
        )));
    };
    sfpmap::output::check_output(&path, &[], force).map_err(output_error)?;
    py.detach(|| {
        let positions: Vec<[f32; 3]> = (0..n)
            .map(|i| {
                let i = i as f32;
                [i * 1e-3, (i * 0.37).sin(), (i * 0.11).cos()]
            })
            .collect();
        // n <= 4 GiB / 18 < 2^32.
        let indices: Vec<u32> = (0..n as u32).collect();
        let value = f16::from_f32(1.0 / (dim_full as f32).sqrt());
        let descriptors = vec![value; n * dim_full as usize];
        let mut writer = MapWriter::new(Metadata::default());
        writer.set_points(&positions);
        let info = LevelInfo {
            level: 0,
            stride: 8.0,
            descriptor: "synthetic".into(),
            dim_full,
            dim_short,
            normalization: "l2".into(),
            extra: Default::default(),
        };
        writer
            .add_level(
                info,
                &indices,
                Some(Descriptors::F16(std::borrow::Cow::Owned(descriptors))),
                true,
            )
            .and_then(|w| w.write(&path, &Silent))
            .map_err(|e| format_error(&path, e))
    })
}

/// The most memory `_write_synthetic_map` takes for its arrays: 4 GiB.
const SYNTHETIC_MAX_BYTES: u64 = 4 << 30;
