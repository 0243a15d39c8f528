//! Query features: the SFP extractor, hloc's `features.h5`, COLMAP query databases.

use crate::errors::{chain, extract_error, InputError};
use crate::localize::Features;
use numpy::{IntoPyArray, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use sfpmap::extract::{DetectOptions, Extractor as Inner, ExtractorOptions};
use sfpmap::io::features_h5::H5Features;
use sfpmap::io::queries::DatabaseFeatures;
use sfpmap::localize::FeatureModel;
use std::path::PathBuf;
use std::sync::Mutex;

/// The SFP extractor on ONNX Runtime (found or fetched as the CLI does; see `sfpmap setup`).
/// One network run at a time per extractor (calls from several threads take turns).
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "_Extractor")]
pub(crate) struct Extractor {
    inner: Mutex<Inner>,
    model_name: String,
    /// The model's RGB-to-grey weights, read at construction: preparing an image takes no
    /// lock (and never waits for a network run while holding the GIL).
    gray_weights: [f32; 3],
}

/// An image from a numpy array: `(h, w)` or `(h, w, 1)` grey, `(h, w, 3)` RGB; uint8, or
/// floats in [0, 1]. The shape is checked before anything is copied: each side at least 1 and
/// at most `u32::MAX` pixels (a wider array is refused, not truncated to its low 32 bits).
fn image_of(array: &Bound<'_, PyAny>) -> PyResult<image::DynamicImage> {
    let np = array.py().import("numpy")?;
    let shape: Vec<usize> = array.getattr("shape")?.extract()?;
    let bad = || {
        InputError::new_err(format!(
            "image: shape {shape:?} (expected (h, w), (h, w, 1) or (h, w, 3))"
        ))
    };
    let (h, w) = match shape.as_slice() {
        [h, w] | [h, w, 1] | [h, w, 3] => (*h, *w),
        _ => return Err(bad()),
    };
    if h == 0 || w == 0 {
        return Err(bad());
    }
    let side = |n: usize| {
        u32::try_from(n).map_err(|_| {
            InputError::new_err(format!(
                "image: shape {shape:?}: a side of {n} pixels (at most {})",
                u32::MAX
            ))
        })
    };
    let (h, w) = (side(h)?, side(w)?);
    let dtype = array
        .getattr("dtype")?
        .getattr("kind")?
        .extract::<String>()?;
    let as_u8 = if dtype == "f" {
        let scaled = np
            .call_method1("clip", (array, 0.0, 1.0))?
            .call_method1("__mul__", (255.0,))?
            .call_method1("round", ())?;
        np.call_method1("ascontiguousarray", (scaled, "uint8"))?
    } else if dtype == "u"
        && array
            .getattr("dtype")?
            .getattr("itemsize")?
            .extract::<usize>()?
            == 1
    {
        np.call_method1("ascontiguousarray", (array,))?
    } else {
        return Err(InputError::new_err(format!(
            "image: dtype {} (expected uint8, or floats in [0, 1])",
            array.getattr("dtype")?.str()?
        )));
    };
    let a: PyReadonlyArrayDyn<'_, u8> = as_u8.extract()?;
    if a.shape() != shape.as_slice() {
        return Err(bad());
    }
    let data = a.as_slice()?.to_vec();
    if shape.len() == 3 && shape[2] == 3 {
        let rgb = image::RgbImage::from_raw(w, h, data).ok_or_else(bad)?;
        Ok(image::DynamicImage::ImageRgb8(rgb))
    } else {
        let gray = image::GrayImage::from_raw(w, h, data).ok_or_else(bad)?;
        Ok(image::DynamicImage::ImageLuma8(gray))
    }
}

#[pymethods]
impl Extractor {
    #[new]
    #[pyo3(signature = (model=None, threads=2))]
    fn new(py: Python<'_>, model: Option<PathBuf>, threads: i64) -> PyResult<Self> {
        let threads = crate::thread_count(py, Some(threads))?;
        let options = ExtractorOptions { model, threads };
        // The library's warnings (ONNX Runtime not found, so fetched) as `RuntimeWarning`s.
        let warnings = crate::Warnings::default();
        let inner = py.detach(|| Inner::new(&options, &warnings));
        let inner = warnings.emit_then(py, inner.map_err(extract_error))?;
        let model_name = inner.contract().model_name.clone();
        let gray_weights = inner.contract().gray_weights;
        Ok(Extractor {
            inner: Mutex::new(inner),
            model_name,
            gray_weights,
        })
    }

    /// The descriptor kind the model makes (`"sfp-v2"`, ...), as maps record it.
    #[getter]
    fn descriptor(&self) -> String {
        self.model_name.clone()
    }

    /// Keypoints and descriptors per level, and the global descriptor, of an image file
    /// (`str` / `os.PathLike`) or array. GIL released while the network runs.
    /// `global_max_side`: the global descriptor's image size (`None`: 512; 0: the network
    /// input; else at least 16; a map's metadata `global_max_side`, absent meaning 0, is what
    /// its queries need).
    #[pyo3(signature = (image, resize_max=None, threshold=None, nms_radius=None, max_keypoints=None, refine=true, global_max_side=None))]
    #[allow(clippy::too_many_arguments)]
    fn extract(
        &self,
        py: Python<'_>,
        image: &Bound<'_, PyAny>,
        resize_max: Option<u32>,
        threshold: Option<f32>,
        nms_radius: Option<u32>,
        max_keypoints: Option<Vec<usize>>,
        refine: bool,
        global_max_side: Option<u32>,
    ) -> PyResult<Features> {
        let weights = self.gray_weights;
        let path = image.extract::<PathBuf>().ok();
        let input = if let Some(path) = &path {
            py.detach(|| sfpmap::extract::image::load(path, weights, resize_max))
                .map_err(extract_error)?
        } else {
            let decoded = image_of(image)?;
            py.detach(|| sfpmap::extract::image::from_image(&decoded, weights, resize_max))
        };
        let options = DetectOptions {
            threshold,
            nms_radius,
            max_keypoints,
            refine: Some(refine),
            global: match global_max_side {
                None => sfpmap::extract::GlobalSize::default(),
                Some(side) => sfpmap::extract::GlobalSize::from_flag(side)
                    .map_err(|e| InputError::new_err(format!("global_max_side {e}")))?,
            },
        };
        // The ranges the CLI's flags are held to (a radius of 10^6 cells would run for hours).
        options.check().map_err(InputError::new_err)?;
        let (f, query) = py
            .detach(|| {
                let mut extractor = self.inner.lock().unwrap_or_else(|p| p.into_inner());
                let f = extractor.extract(&input, &options)?;
                // The features carry the model: a session refuses them for another map's.
                let query = sfpmap::io::queries::sfp_query(&f, &extractor);
                Ok::<_, sfpmap::extract::ExtractError>((f, query))
            })
            // Named as the CLI names them: the image in front.
            .map_err(|e| {
                extract_error(match &path {
                    Some(p) => e.on_image(p),
                    None => e,
                })
            })?;
        let mut features = Features::new(query);
        features.scores = f.levels.iter().map(|l| Some(l.scores.clone())).collect();
        Ok(features)
    }
}

/// Query features from an hloc-style `features.h5` (`sfpmap extract`'s, or hloc's own), read
/// on demand (never whole); threads query it concurrently.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "FeaturesFile")]
pub(crate) struct FeaturesFile {
    inner: H5Features,
    /// The feature the file names (`sfp.model_name` and `sfp.model_xxh3`: `sfpmap extract`'s
    /// files; else the conf of hloc's `feats-<conf>.h5` name), which its features carry: a
    /// localizer refuses them for a map of another feature, as `sfpmap localize --features`
    /// refuses the file. `None` for a file that names none.
    model: Option<FeatureModel>,
}

#[pymethods]
impl FeaturesFile {
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let (inner, model) = py
            .detach(|| {
                let inner = H5Features::open(&path)?;
                let model = match inner.feature_name()? {
                    Some(name) => Some(FeatureModel {
                        name,
                        xxh3: inner.root_string("sfp.model_xxh3")?,
                    }),
                    None => None,
                };
                Ok::<_, sfpmap::io::InputError>((inner, model))
            })
            .map_err(|e| InputError::new_err(chain(&e)))?;
        Ok(FeaturesFile { inner, model })
    }

    /// The features of image `name`, or `None` if the file has none.
    fn features(&self, py: Python<'_>, name: &str) -> PyResult<Option<Features>> {
        let f = py
            .detach(|| self.inner.features(name))
            .map_err(|e| InputError::new_err(chain(&e)))?;
        Ok(f.map(|mut f| {
            f.model = self.model.clone();
            Features::new(f)
        }))
    }

    /// The feature the file names (its `sfp.model_name`, else the conf of hloc's
    /// `feats-<conf>.h5` name), or `None`: what its features' `model` is.
    #[getter]
    fn feature(&self) -> Option<String> {
        self.model.as_ref().map(|m| m.name.clone())
    }

    /// Image `name`'s `global_descriptor` (hloc's `global-feats.h5`: NetVLAD's or any
    /// other's), float32, or `None` if the file has none for it; `Localizer.localize`'s
    /// `global_descriptor`, as `sfpmap localize --global-features` reads it.
    fn global_descriptor<'py>(
        &self,
        py: Python<'py>,
        name: &str,
    ) -> PyResult<Option<Bound<'py, PyAny>>> {
        let g = py
            .detach(|| self.inner.global(name))
            .map_err(|e| InputError::new_err(chain(&e)))?;
        Ok(g.map(|g| g.into_pyarray(py).into_any()))
    }
}

/// SIFT features of query images from a COLMAP database (`queries.db`), by image name:
/// L2-normalised descriptors, as `sfpmap localize --database` reads them.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "QueryDatabase")]
pub(crate) struct QueryDatabase {
    inner: Mutex<DatabaseFeatures>,
}

#[pymethods]
impl QueryDatabase {
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = py
            .detach(|| DatabaseFeatures::open(&path))
            // The database's errors name it already.
            .map_err(|e| InputError::new_err(chain(&e)))?;
        Ok(QueryDatabase {
            inner: Mutex::new(inner),
        })
    }

    /// The features of image `name`, or `None` if the database has none.
    fn features(&self, py: Python<'_>, name: &str) -> PyResult<Option<Features>> {
        let f = py
            .detach(|| {
                self.inner
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .features(name)
            })
            .map_err(|e| InputError::new_err(chain(&e)))?;
        Ok(f.map(Features::new))
    }
}
