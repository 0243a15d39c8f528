//! Cameras, query features, the localizer and its results.
//!
//! A [`Localizer`] is built once per map and shared: `localize` can be called from several
//! Python threads at once (the GIL is released while it runs), and `localize_many` runs the
//! queries on Rust threads. It localizes through the library's `Session`, which checks the
//! options and that query features fit the map (their model), and in sequence mode tracks
//! queries in order (calls then take turns).

use crate::errors::{chain, format_error, level_ids, option_error, session_error, InputError};
use crate::map::Map;
use crate::Warnings;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use sfpmap::geometry::Camera as GeoCamera;
use sfpmap::localize::{
    check_global_finite, FeatureSet, Localization as Outcome, LocalizeOptions, MatchOptions,
    OptionError, QueryFeatures, RetrievalMethod,
};
use sfpmap::session::Session;
use std::path::Path;
use std::sync::Arc;

/// A camera: a COLMAP model name, the image size and the model's parameters in COLMAP order.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "Camera")]
#[derive(Clone)]
pub(crate) struct Camera {
    pub(crate) inner: GeoCamera,
}

#[pymethods]
impl Camera {
    #[new]
    fn new(model: &str, width: u32, height: u32, params: Vec<f64>) -> PyResult<Self> {
        GeoCamera::from_model_name(model, width, height, &params)
            .map(|inner| Camera { inner })
            .map_err(|e| InputError::new_err(format!("camera: {}", chain(&e))))
    }

    /// Parses `"MODEL WIDTH HEIGHT p1 p2 ..."` (the CLI's `--camera`, an hloc query line's
    /// tail).
    #[staticmethod]
    fn parse(text: &str) -> PyResult<Self> {
        GeoCamera::parse(text)
            .map(|inner| Camera { inner })
            .map_err(|e| InputError::new_err(format!("camera: {}", chain(&e))))
    }

    #[getter]
    fn model(&self) -> &'static str {
        self.inner.model().name()
    }

    #[getter]
    fn width(&self) -> u32 {
        self.inner.width()
    }

    #[getter]
    fn height(&self) -> u32 {
        self.inner.height()
    }

    #[getter]
    fn params(&self) -> Vec<f64> {
        self.inner.params().to_vec()
    }

    fn __repr__(&self) -> String {
        format!(
            "sfpmap.Camera({:?}, {}, {}, {:?})",
            self.model(),
            self.width(),
            self.height(),
            self.inner.params()
        )
    }
}

/// A camera from a `Camera`, a `"MODEL W H params..."` string, a dict with `model`, `width`,
/// `height`, `params`, or any object with those attributes (a `pycolmap.Camera`, whose
/// `model` is an enum with a `name`).
pub(crate) fn camera_of(obj: &Bound<'_, PyAny>) -> PyResult<GeoCamera> {
    if let Ok(c) = obj.cast::<Camera>() {
        return Ok(c.get().inner.clone());
    }
    if let Ok(text) = obj.extract::<String>() {
        return Ok(Camera::parse(&text)?.inner);
    }
    let field = |name: &str| -> PyResult<Bound<'_, PyAny>> {
        match obj.cast::<PyDict>() {
            Ok(d) => d
                .get_item(name)?
                .ok_or_else(|| InputError::new_err(format!("camera: no {name:?}"))),
            Err(_) => obj.getattr(name).map_err(|_| {
                InputError::new_err(format!(
                    "camera: expected a Camera, a \"MODEL W H params...\" string, a dict or a pycolmap.Camera (no {name:?})"
                ))
            }),
        }
    };
    let model = field("model")?;
    let model: String = match model.extract::<String>() {
        Ok(s) => s,
        Err(_) => model.getattr("name")?.extract()?,
    };
    let width: u32 = field("width")?.extract()?;
    let height: u32 = field("height")?.extract()?;
    let params: Vec<f64> = match field("params")?.extract::<Vec<f64>>() {
        Ok(p) => p,
        Err(_) => field("params")?.call_method0("tolist")?.extract()?,
    };
    Ok(Camera::new(&model, width, height, params)?.inner)
}

/// One query's features: per level (or one set for every level, SIFT), keypoints in pixels
/// (COLMAP convention) and descriptors in the extractor's space; optionally a global
/// descriptor for retrieval.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "Features")]
pub(crate) struct Features {
    pub(crate) inner: Arc<QueryFeatures>,
    /// Per set: the keypoint scores, when the extractor made them.
    pub(crate) scores: Vec<Option<Vec<f32>>>,
}

impl Features {
    pub(crate) fn new(inner: QueryFeatures) -> Features {
        let scores = vec![None; inner.sets.len()];
        Features {
            inner: Arc::new(inner),
            scores,
        }
    }

    /// The set the localizer uses for `level`: the level's own, else the one for every level
    /// (`None`), as the library picks it.
    fn set(&self, level: Option<u16>) -> PyResult<usize> {
        let sets = &self.inner.sets;
        sets.iter()
            .position(|s| s.level == level)
            .or_else(|| sets.iter().position(|s| s.level.is_none()))
            .ok_or_else(|| {
                InputError::new_err(format!(
                    "no features for level {}",
                    level.map_or("None".to_string(), |l| l.to_string())
                ))
            })
    }
}

/// `(n, 2)` keypoints and `(n, dim)` descriptors (any float or integer dtype) as a feature
/// set.
fn feature_set(
    level: Option<u16>,
    keypoints: &Bound<'_, PyAny>,
    descriptors: &Bound<'_, PyAny>,
) -> PyResult<FeatureSet> {
    let np = keypoints.py().import("numpy")?;
    let as_f64 = np.call_method1("ascontiguousarray", (keypoints, "float64"))?;
    let as_f32 = np.call_method1("ascontiguousarray", (descriptors, "float32"))?;
    let k: PyReadonlyArray2<'_, f64> = as_f64.extract().map_err(|_| {
        InputError::new_err("keypoints: expected an array of shape (n, 2) (or (n, >=2))")
    })?;
    let d: PyReadonlyArray2<'_, f32> = as_f32
        .extract()
        .map_err(|_| InputError::new_err("descriptors: expected an array of shape (n, dim)"))?;
    let (n, kcols) = (k.shape()[0], k.shape()[1]);
    if kcols < 2 {
        return Err(InputError::new_err(format!(
            "keypoints: shape ({n}, {kcols}), expected (n, 2)"
        )));
    }
    if d.shape()[0] != n {
        return Err(InputError::new_err(format!(
            "{n} keypoints but {} descriptors",
            d.shape()[0]
        )));
    }
    let k = k.as_array();
    let keypoints: Vec<[f64; 2]> = (0..n).map(|i| [k[[i, 0]], k[[i, 1]]]).collect();
    let dim = d.shape()[1];
    let descriptors: Vec<f32> = d.as_array().iter().copied().collect();
    let set = FeatureSet {
        level,
        keypoints,
        descriptors,
        dim,
    };
    // The library's rule, at once: the error names the array as the caller made it.
    set.check_finite()
        .map_err(|e| InputError::new_err(e.to_string()))?;
    Ok(set)
}

#[pymethods]
impl Features {
    /// Features from arrays: `levels` maps a level id (or `None`: one set for every level, as
    /// for SIFT) to `(keypoints (n, 2), descriptors (n, dim))`.
    #[new]
    #[pyo3(signature = (levels, global_descriptor=None))]
    fn py_new(levels: &Bound<'_, PyDict>, global_descriptor: Option<Vec<f32>>) -> PyResult<Self> {
        check_global(global_descriptor.as_deref())?;
        let mut sets = Vec::new();
        for (level, value) in levels.iter() {
            let level: Option<u16> = level.extract()?;
            let pair = value.cast::<PyTuple>().map_err(|_| {
                InputError::new_err("each level's features are a (keypoints, descriptors) tuple")
            })?;
            if pair.len() != 2 {
                return Err(InputError::new_err(
                    "each level's features are a (keypoints, descriptors) tuple",
                ));
            }
            sets.push(feature_set(level, &pair.get_item(0)?, &pair.get_item(1)?)?);
        }
        Ok(Features::new(QueryFeatures {
            sets,
            global: global_descriptor,
            model: None,
        }))
    }

    /// Level ids with features (`None` for one set serving every level).
    #[getter]
    fn levels(&self) -> Vec<Option<u16>> {
        self.inner.sets.iter().map(|s| s.level).collect()
    }

    /// `(n, 2)` float64 keypoints of `level` (pixels, COLMAP convention).
    #[pyo3(signature = (level=None))]
    fn keypoints<'py>(&self, py: Python<'py>, level: Option<u16>) -> PyResult<Bound<'py, PyAny>> {
        let s = &self.inner.sets[self.set(level)?];
        let flat: Vec<f64> = s.keypoints.iter().flatten().copied().collect();
        let a = Array2::from_shape_vec((s.keypoints.len(), 2), flat)
            .map_err(|e| InputError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py).into_any())
    }

    /// `(n, dim)` float32 descriptors of `level`.
    #[pyo3(signature = (level=None))]
    fn descriptors<'py>(&self, py: Python<'py>, level: Option<u16>) -> PyResult<Bound<'py, PyAny>> {
        let s = &self.inner.sets[self.set(level)?];
        let n = s.keypoints.len();
        let a = Array2::from_shape_vec((n, s.dim), s.descriptors.clone())
            .map_err(|e| InputError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py).into_any())
    }

    /// `(n,)` float32 keypoint scores of `level`, if the extractor made them.
    #[pyo3(signature = (level=None))]
    fn scores<'py>(
        &self,
        py: Python<'py>,
        level: Option<u16>,
    ) -> PyResult<Option<Bound<'py, PyAny>>> {
        let i = self.set(level)?;
        Ok(self.scores[i]
            .as_ref()
            .map(|s| s.clone().into_pyarray(py).into_any()))
    }

    /// The model that made them (`"sfp-v2"`, as maps name their descriptors), when known:
    /// features of `Extractor.extract`, or of a `FeaturesFile` that records its model. A
    /// `Localizer` refuses them for a map of another model; features made from arrays
    /// (`None`) are taken as they are.
    #[getter]
    fn model(&self) -> Option<String> {
        self.inner.model.as_ref().map(|m| m.name.clone())
    }

    /// The global descriptor, if any.
    #[getter]
    fn global_descriptor<'py>(&self, py: Python<'py>) -> Option<Bound<'py, PyAny>> {
        self.inner
            .global
            .as_ref()
            .map(|g| g.clone().into_pyarray(py).into_any())
    }

    fn __len__(&self) -> usize {
        self.inner.sets.iter().map(|s| s.keypoints.len()).sum()
    }

    fn __repr__(&self) -> String {
        let sets: Vec<String> = self
            .inner
            .sets
            .iter()
            .map(|s| {
                format!(
                    "{}: {} x {}",
                    s.level.map_or("all".to_string(), |l| l.to_string()),
                    s.keypoints.len(),
                    s.dim
                )
            })
            .collect();
        format!("sfpmap.Features({})", sets.join(", "))
    }
}

/// A global descriptor holds finite values only (the library's rule, at once).
fn check_global(global: Option<&[f32]>) -> PyResult<()> {
    check_global_finite(global).map_err(|e| InputError::new_err(e.to_string()))
}

/// Query features from a `Features`, a `(keypoints, descriptors)` tuple (one set for every
/// level) or a dict `{level: (keypoints, descriptors)}`; `global_descriptor` replaces theirs.
fn features_of(
    obj: &Bound<'_, PyAny>,
    global_descriptor: Option<Vec<f32>>,
) -> PyResult<Arc<QueryFeatures>> {
    let features = if let Ok(f) = obj.cast::<Features>() {
        f.get().inner.clone()
    } else if let Ok(pair) = obj.cast::<PyTuple>() {
        if pair.len() != 2 {
            return Err(InputError::new_err(
                "features: expected Features, (keypoints, descriptors) or {level: (keypoints, descriptors)}",
            ));
        }
        Arc::new(QueryFeatures {
            sets: vec![feature_set(None, &pair.get_item(0)?, &pair.get_item(1)?)?],
            global: None,
            model: None,
        })
    } else if let Ok(d) = obj.cast::<PyDict>() {
        Features::py_new(d, None)?.inner
    } else {
        return Err(InputError::new_err(
            "features: expected Features, (keypoints, descriptors) or {level: (keypoints, descriptors)}",
        ));
    };
    check_global(global_descriptor.as_deref())?;
    // The library reads the global descriptor from the features: one made here from arrays is
    // this call's own and takes it in place; a shared `Features` object is copied (the
    // library has no call taking the global descriptor beside the features).
    Ok(match global_descriptor {
        Some(g) => {
            let mut f = Arc::try_unwrap(features).unwrap_or_else(|shared| (*shared).clone());
            f.global = Some(g);
            Arc::new(f)
        }
        None => features,
    })
}

/// A map prepared for localization: a library [`Session`] (which owns the map, shared with
/// the `Map` and its views, and the localizer together); see the module docs for threads.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "_Localizer")]
pub(crate) struct Localizer {
    session: Session,
}

/// A count option (`top_k`, `min_inliers`) given as a Python int. The library checks its
/// range ([`LocalizeOptions::validate`], when the session is built); a negative one, which no
/// `usize` holds, is refused here in the library's words: its rule for 0 (which no count
/// option takes), with the value as given (`top_k -1: 1 to 100000 images`).
fn count(
    option: &'static str,
    value: i64,
    set: fn(&mut LocalizeOptions, usize),
) -> PyResult<usize> {
    if let Ok(n) = usize::try_from(value) {
        return Ok(n);
    }
    let mut probe = LocalizeOptions::default();
    set(&mut probe, 0);
    let expected = match probe.validate() {
        Err(e) if e.option == option => e.expected,
        _ => "a count, at least 0",
    };
    Err(option_error(&OptionError {
        option,
        value: value.to_string(),
        expected,
    }))
}

impl Localizer {
    /// One query (GIL released), errors named as the CLI names them (`MAP: query NAME: ...`),
    /// and the names of the images it retrieved, read from the map (checked on first access:
    /// a damaged names section is the map's `MapError`, not an empty list).
    fn run(&self, features: &QueryFeatures, camera: &GeoCamera, name: &str) -> PyResult<Ran> {
        let outcome = self
            .session
            .localize_features(features, camera, name)
            .map_err(session_error)?;
        let names = retrieved_names(self.session.map(), &outcome.retrieved)
            .map_err(|e| format_error(Path::new(self.session.map_name()), e))?;
        Ok((outcome, names))
    }
}

/// One query's outcome and the names of the images it retrieved.
type Ran = (Outcome, Vec<String>);

/// The names of the images `retrieved` (map indices).
fn retrieved_names(
    map: &sfpmap::format::Map<'_>,
    retrieved: &[usize],
) -> Result<Vec<String>, sfpmap::format::Error> {
    if retrieved.is_empty() {
        return Ok(Vec::new());
    }
    let Some(images) = map.images()? else {
        return Ok(Vec::new());
    };
    retrieved
        .iter()
        .map(|&i| images.name(i).map(str::to_string))
        .collect()
}

/// The library's retrieval top-k (`sfpmap.Localizer`'s default).

#[pymethods]
impl Localizer {
    /// Options are checked by the library (`LocalizeOptions::validate`): one out of range is an
    /// `InputError` in its words. `sequence`: queries are an ordered sequence, each tracked
    /// from the last ones (`Session` in sequence mode).
    #[new]
    #[pyo3(signature = (map, levels=None, short=false, top_k=None, retrieval="auto", ratio=None,
                        mutual=None, min_similarity=None, coarse_error_px=None, gate_px=None,
                        gate_ratio=None, fine_error_px=None, min_inliers=None, sequence=false,
                        retrieval_probe=None, keep_inliers=false))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        map: &Bound<'_, Map>,
        levels: Option<Vec<Bound<'_, PyAny>>>,
        short: bool,
        top_k: Option<i64>,
        retrieval: &str,
        ratio: Option<f32>,
        mutual: Option<bool>,
        min_similarity: Option<f32>,
        coarse_error_px: Option<f64>,
        gate_px: Option<f64>,
        gate_ratio: Option<f32>,
        fine_error_px: Option<f64>,
        min_inliers: Option<i64>,
        sequence: bool,
        retrieval_probe: Option<i64>,
        keep_inliers: bool,
    ) -> PyResult<Self> {
        let opened = map.get().opened(py)?;
        // Each option left out (None) is the map's own default (LocalizeOptions::for_map:
        // the library's defaults, with Lowe's ratio 0.95 on SFP maps and 0.9 on SIFT), as
        // the CLI's `localize` without the flag: the defaults have one home, the library.
        let base = LocalizeOptions::for_map(&opened.map);
        let levels = level_ids(&opened.path, &levels.unwrap_or_default(), || {
            opened.map.level_ids()
        })?;
        let top_k = match top_k {
            Some(n) => count("top_k", n, |o, n| o.top_k = n)?,
            None => base.top_k,
        };
        let min_inliers = match min_inliers {
            Some(n) => count("min_inliers", n, |o, n| o.min_inliers = n)?,
            None => base.min_inliers,
        };
        let options = LocalizeOptions {
            levels,
            short,
            top_k,
            retrieval: retrieval
                .parse::<RetrievalMethod>()
                .map_err(|e| InputError::new_err(e.to_string()))?,
            retrieval_probe: retrieval_probe
                .map(|n| count("retrieval_probe", n, |o, n| o.retrieval_probe = Some(n)))
                .transpose()?,
            matching: MatchOptions {
                ratio: ratio.unwrap_or(base.matching.ratio),
                mutual: mutual.unwrap_or(base.matching.mutual),
                min_similarity: min_similarity.unwrap_or(base.matching.min_similarity),
            },
            coarse_error_px: coarse_error_px.unwrap_or(base.coarse_error_px),
            gate_px: gate_px.unwrap_or(base.gate_px),
            gate_ratio: gate_ratio.unwrap_or(base.gate_ratio),
            fine_error_px: fine_error_px.unwrap_or(base.fine_error_px),
            min_inliers,
            keep_inliers,
        };
        let warnings = Warnings::default();
        let session = py.detach(|| {
            Session::builder(opened.map.clone(), opened.path.display().to_string())
                .options(options)
                .sequence(sequence)
                .build(&warnings)
        });
        let session = warnings.emit_then(py, session.map_err(session_error))?;
        Ok(Localizer { session })
    }

    /// Level ids in matching order (deepest first).
    #[getter]
    fn level_order(&self) -> Vec<u16> {
        self.session.level_order()
    }

    /// Selected levels that are not matched, as `(level, reason)`.
    #[getter]
    fn skipped_levels(&self) -> Vec<(u16, String)> {
        self.session
            .skipped_levels()
            .into_iter()
            .map(|s| (s.level, s.reason))
            .collect()
    }

    /// Whether queries are an ordered sequence (`sequence=True`).
    #[getter]
    fn sequence(&self) -> bool {
        self.session.is_sequence()
    }

    /// Whether the sequence predicts the next query's pose (it localized the last one); always
    /// false outside a sequence.
    #[getter]
    fn is_tracking(&self) -> bool {
        self.session.is_tracking()
    }

    /// Forgets the sequence's motion (a cut, a query that could not be had): the next query
    /// goes through retrieval. Nothing outside a sequence.
    fn reset_tracking(&self, py: Python<'_>) {
        // Waits for a query of the sequence that is running: the GIL released meanwhile.
        py.detach(|| self.session.reset_tracking());
    }

    /// Localizes one query (GIL released); a query that is not localized is a result whose
    /// `success` is false, not an exception. In a sequence, calls take turns, each predicted
    /// from the ones before.
    #[pyo3(signature = (features, camera, global_descriptor=None, name="query"))]
    fn localize(
        &self,
        py: Python<'_>,
        features: &Bound<'_, PyAny>,
        camera: &Bound<'_, PyAny>,
        global_descriptor: Option<Vec<f32>>,
        name: &str,
    ) -> PyResult<Localization> {
        let f = features_of(features, global_descriptor)?;
        let c = camera_of(camera)?;
        let (outcome, names) = py.detach(|| self.run(&f, &c, name))?;
        Ok(Localization::new(outcome, names))
    }

    /// Localizes `queries` (any iterable of `(features, camera)` or `(features, camera,
    /// name)`) on `threads` Rust threads sharing this localizer (default: the machine's
    /// parallelism; capped as the CLI caps `--threads`), GIL released; results in order. A
    /// sequence runs on one thread, in order, whatever `threads` says.
    #[pyo3(signature = (queries, threads=None))]
    fn localize_many(
        &self,
        py: Python<'_>,
        queries: &Bound<'_, PyAny>,
        threads: Option<i64>,
    ) -> PyResult<Vec<Localization>> {
        let threads = crate::thread_count(py, threads)?;
        let mut inputs = Vec::new();
        for (i, q) in queries.try_iter()?.enumerate() {
            let q = q?;
            let bad = || {
                InputError::new_err(format!(
                    "query {i}: expected (features, camera) or (features, camera, name)"
                ))
            };
            let items: Vec<Bound<'_, PyAny>> = if let Ok(t) = q.cast::<PyTuple>() {
                t.iter().collect()
            } else if let Ok(l) = q.cast::<PyList>() {
                l.iter().collect()
            } else {
                return Err(bad());
            };
            let (features, camera, name) = match items.as_slice() {
                [f, c] => (f, c, format!("#{i}")),
                [f, c, n] => (f, c, n.extract::<String>()?),
                _ => return Err(bad()),
            };
            inputs.push((features_of(features, None)?, camera_of(camera)?, name));
        }
        let queries: Vec<_> = (inputs.iter())
            .map(|(f, c, name)| (&**f, c, name.as_str()))
            .collect();
        let session = &self.session;
        let outcomes = py.detach(|| {
            let found = session
                .localize_features_all(&queries, threads, &sfpmap::progress::Silent)
                .map_err(session_error)?;
            found
                .into_iter()
                .map(|o| {
                    let names = retrieved_names(session.map(), &o.retrieved)
                        .map_err(|e| format_error(Path::new(session.map_name()), e))?;
                    Ok((o, names))
                })
                .collect::<PyResult<Vec<Ran>>>()
        })?;
        Ok(outcomes
            .into_iter()
            .map(|(o, names)| Localization::new(o, names))
            .collect())
    }
}

/// What `localize` found for one query.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "_Localization")]
pub(crate) struct Localization {
    /// `[qw, qx, qy, qz, tx, ty, tz]`, COLMAP's `cam_from_world`.
    colmap: Option<[f64; 7]>,
    matrix: Option<[[f64; 4]; 4]>,
    failure: Option<String>,
    inliers: usize,
    inliers_per_level: Vec<(u16, usize)>,
    matches: usize,
    retrieved: Vec<usize>,
    retrieved_names: Vec<String>,
    retrieved_images: usize,
    path: &'static str,
    tracking_lost: Option<String>,
    retrieval: Option<&'static str>,
    retrieval_fallback: Option<String>,
    times: [f64; 5],
    /// The pose's covariance, world frame (row-major 6×6: camera centre, then rotations).
    covariance: Option<[f64; 36]>,
    /// With `keep_inliers`: (pixel, point, level) of each final inlier.
    inlier_links: Vec<sfpmap::localize::InlierLink>,
}

impl Localization {
    /// `o`, and the names of its retrieved images (`Localizer::run` reads them).
    fn new(o: Outcome, retrieved_names: Vec<String>) -> Localization {
        let pose = o.pose();
        Localization {
            colmap: pose.map(|p| p.to_colmap()),
            matrix: pose.map(|p| {
                let r = p.rotation.to_rotation_matrix();
                let m = r.matrix();
                let t = &p.translation;
                [
                    [m[(0, 0)], m[(0, 1)], m[(0, 2)], t.x],
                    [m[(1, 0)], m[(1, 1)], m[(1, 2)], t.y],
                    [m[(2, 0)], m[(2, 1)], m[(2, 2)], t.z],
                    [0.0, 0.0, 0.0, 1.0],
                ]
            }),
            failure: o.failure().map(|f| f.to_string()),
            inliers: o.inliers,
            inliers_per_level: o.inliers_per_level.clone(),
            matches: o.matches,
            retrieved: o.retrieved.clone(),
            retrieved_names,
            retrieved_images: o.retrieved_images,
            path: o.path.name(),
            tracking_lost: o.tracking_lost.map(|w| w.to_string()),
            retrieval: o.retrieval.map(|m| m.name()),
            retrieval_fallback: o.retrieval_fallback.map(|w| w.to_string()),
            times: [
                o.times.retrieval_ms,
                o.times.coarse_match_ms,
                o.times.coarse_ransac_ms,
                o.times.fine_ms,
                o.times.total_ms,
            ],
            covariance: match (pose, &o.covariance) {
                (Some(p), Some(c)) => Some(c.world_from_camera(p)),
                _ => None,
            },
            inlier_links: o.inlier_links.clone(),
        }
    }
}

#[pymethods]
impl Localization {
    /// Whether a pose was found.
    #[getter]
    fn success(&self) -> bool {
        self.colmap.is_some()
    }

    /// `cam_from_world` as `[qw, qx, qy, qz, tx, ty, tz]` (COLMAP), or `None`.
    #[getter]
    fn colmap(&self) -> Option<[f64; 7]> {
        self.colmap
    }

    /// `cam_from_world` as a 4×4 matrix (list of rows), or `None`.
    #[getter]
    fn _matrix(&self) -> Option<[[f64; 4]; 4]> {
        self.matrix
    }

    /// Why the query was not localized, or `None`.
    #[getter]
    fn failure(&self) -> Option<String> {
        self.failure.clone()
    }

    #[getter]
    fn inliers(&self) -> usize {
        self.inliers
    }

    /// `{level: inliers}` of the final estimate.
    #[getter]
    fn inliers_per_level(&self) -> Vec<(u16, usize)> {
        self.inliers_per_level.clone()
    }

    #[getter]
    fn matches(&self) -> usize {
        self.matches
    }

    /// Retrieved database images (map indices), best first.
    #[getter]
    fn retrieved(&self) -> Vec<usize> {
        self.retrieved.clone()
    }

    /// Their names.
    #[getter]
    fn retrieved_names(&self) -> Vec<String> {
        self.retrieved_names.clone()
    }

    /// How many database images retrieval gave the coarse stage (the CLI JSON's
    /// `retrieved_images`).
    #[getter]
    fn retrieved_images(&self) -> usize {
        self.retrieved_images
    }

    /// `"retrieval"` or `"tracking"`.
    #[getter]
    fn path(&self) -> &'static str {
        self.path
    }

    /// With a pose prior: why tracking did not hold, so the retrieval path ran (the CLI
    /// JSON's `tracking_lost`); `None` otherwise.
    #[getter]
    fn tracking_lost(&self) -> Option<String> {
        self.tracking_lost.clone()
    }

    /// The stored descriptor that ranked the images (`"vlad"`, `"global"`), if any.
    #[getter]
    fn retrieval(&self) -> Option<&'static str> {
        self.retrieval
    }

    /// Why retrieval did not narrow the candidates, if it did not.
    #[getter]
    fn retrieval_fallback(&self) -> Option<String> {
        self.retrieval_fallback.clone()
    }

    /// Milliseconds per stage: retrieval, coarse_match, coarse_ransac, fine, total.
    #[getter]
    fn _times(&self) -> [f64; 5] {
        self.times
    }

    /// The covariance of the camera's pose in the world, row-major 6×6, or `None`.
    #[getter]
    fn _covariance(&self) -> Option<Vec<f64>> {
        self.covariance.map(|c| c.to_vec())
    }

    /// `(pixels [[x, y]…], points [[x, y, z]…], levels […])` of the final inliers
    /// (`keep_inliers=True`; empty otherwise).
    #[getter]
    #[allow(clippy::type_complexity)]
    fn _inlier_links(&self) -> (Vec<[f64; 2]>, Vec<[f64; 3]>, Vec<u16>) {
        (
            self.inlier_links.iter().map(|l| l.pixel).collect(),
            self.inlier_links.iter().map(|l| l.point).collect(),
            self.inlier_links.iter().map(|l| l.level).collect(),
        )
    }
}

/// `(fx, fy, cx, cy)` of a camera of any COLMAP model (`model` its name, `params` in COLMAP's
/// order), to draw it as a pinhole; `None` for a model without them (EQUIRECTANGULAR).
/// Unlike `Camera`, every model COLMAP knows is read, not only those localization supports.
#[pyfunction]
pub(crate) fn pinhole_intrinsics(model: &str, params: Vec<f64>) -> PyResult<Option<[f64; 4]>> {
    let kind = sfpmap::geometry::CameraModel::from_name_ignore_case(model).ok_or_else(|| {
        InputError::new_err(format!("camera model {model:?}: not a COLMAP model"))
    })?;
    if params.len() != kind.num_params() {
        return Err(InputError::new_err(format!(
            "camera model {kind}: {} parameters ({}), not {}",
            kind.num_params(),
            kind.param_names(),
            params.len()
        )));
    }
    Ok(kind.pinhole_part(&params))
}

/// A poses file (`name qw qx qy qz tx ty tz` lines, COLMAP cam_from_world: `localize -o`,
/// a scene's gt_poses.txt; `#` lines skipped): `[(name, [qw, qx, qy, qz, tx, ty, tz])]`.
#[pyfunction]
pub(crate) fn read_poses(path: std::path::PathBuf) -> PyResult<Vec<(String, [f64; 7])>> {
    let poses = sfpmap::io::poses::read_poses(&path).map_err(|e| InputError::new_err(chain(&e)))?;
    Ok(poses
        .into_iter()
        .map(|(name, pose)| (name, pose.to_colmap()))
        .collect())
}

/// An hloc query list (`name MODEL W H params...` per line), or names only with `camera`:
/// `[(name, Camera)]`.
#[pyfunction]
#[pyo3(signature = (path, camera=None))]
pub(crate) fn read_queries(
    path: std::path::PathBuf,
    camera: Option<&Bound<'_, PyAny>>,
) -> PyResult<Vec<(String, Camera)>> {
    let camera = camera.map(camera_of).transpose()?;
    let queries = sfpmap::io::queries::read_query_list(&path, camera.as_ref())
        .map_err(|e| InputError::new_err(chain(&e)))?;
    Ok(queries
        .into_iter()
        .map(|q| (q.name, Camera { inner: q.camera }))
        .collect())
}
