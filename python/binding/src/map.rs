//! `Map`: an open map and numpy views of its sections.
//!
//! Ownership: the mmap lives in the library's map behind an `Arc` (in an [`Opened`], itself
//! behind an `Arc`). A `Map` holds it through one [`Mapping`] Python object, and every numpy
//! view has that `Mapping` as its `base`, so the mapping stays while any view is alive; a
//! `Localizer`'s session holds another `Arc` of the map itself, so it keeps the mapping too.
//! `Map.close()` drops the `Map`'s own reference: the `Map` refuses every later call
//! (`ClosedError`), and the file is unmapped when the last view is garbage-collected. No path
//! leads to a use after unmap.
//!
//! Sections are found through the library's lookup (`Map::find`), so a section this reader
//! skips (a later minor's codec, dtype or flag it does not know) is absent, never a view.
//! Views of raw sections are the mapped bytes themselves: O(1), no copy, no page touched (so
//! no checksum either: `Map.verify()` checks every section, and the localizer checks each it
//! reads, as the library does on first access). A section in any other codec (zstd, delta) is
//! checked and decoded once by the library (`Map::section_bytes`), on its first view; the
//! library keeps the decoded bytes for the map's lifetime and every later view shares them.
//! Views are read-only (the mapping is `PROT_READ`).

use crate::errors::{format_error, level_arg, no_such_level, ClosedError, InputError, MapError};
use numpy::ndarray::{ArrayView, IxDyn};
use numpy::{Element, PyArray, PyArrayMethods};
use pyo3::prelude::*;
use sfpmap::format::{Codec, Dtype, Map as FormatMap, Section, SectionKind};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, OnceLock};

/// An open map and the path it was opened from. The map is shared with the sessions of the
/// `Localizer`s made of it (`sfpmap::session::Session` owns an `Arc` of it): never copied,
/// unmapped when the last of them is dropped.
pub(crate) struct Opened {
    pub(crate) map: Arc<FormatMap<'static>>,
    pub(crate) path: PathBuf,
}

impl Opened {
    /// A format error of this map, as the CLI reports it.
    pub(crate) fn error(&self, e: sfpmap::format::Error) -> PyErr {
        format_error(&self.path, e)
    }
}

/// The owner of a map's memory: the `base` of every numpy view of it. Not made from Python.
#[pyclass(frozen, module = "sfpmap._sfpmap", name = "_Mapping")]
pub(crate) struct Mapping {
    pub(crate) opened: Arc<Opened>,
}

/// An open map (see the module docs for ownership).
#[pyclass(frozen, subclass, module = "sfpmap._sfpmap", name = "_Map")]
pub(crate) struct Map {
    mapping: Mutex<Option<Py<Mapping>>>,
    path: PathBuf,
}

impl Map {
    /// The mapping, or `ClosedError`.
    pub(crate) fn mapping<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, Mapping>> {
        let guard = self.mapping.lock().unwrap_or_else(|p| p.into_inner());
        match guard.as_ref() {
            Some(m) => Ok(m.bind(py).clone()),
            None => Err(ClosedError::new_err(format!(
                "{}: the map is closed",
                self.path.display()
            ))),
        }
    }

    pub(crate) fn opened(&self, py: Python<'_>) -> PyResult<Arc<Opened>> {
        Ok(self.mapping(py)?.get().opened.clone())
    }
}

/// The section kind the spec names `name` (`"level_desc_short"`, ...), `None` for a name
/// this version does not know.
fn kind_named(name: &str) -> Option<SectionKind> {
    static KINDS: OnceLock<HashMap<&'static str, SectionKind>> = OnceLock::new();
    KINDS
        .get_or_init(|| {
            (0..=u16::MAX)
                .map(SectionKind::from_code)
                .filter(|k| !matches!(k, SectionKind::Unknown(_)))
                .map(|k| (k.name(), k))
                .collect()
        })
        .get(name)
        .copied()
}

/// A read-only numpy array of `bytes` as `T` in `shape`, whose base is `owner`; a copy when
/// the bytes are not aligned for `T` (never for a mapped file: sections are 64-byte aligned).
/// `section` names the map and section (`{path}: {section}`) in an error (made only then).
///
/// SAFETY (of the one `unsafe` block): `bytes` lie in memory `owner` keeps alive and
/// unchanged for as long as `owner` lives: the read-only mapping of the map its `Arc<Opened>`
/// holds (by an `Arc` of the map, which sessions may share: the map is dropped, and the file
/// unmapped, only with the last of them, so never while `owner` lives), or decoded bytes the
/// library keeps in that same map until it is dropped. The array holds
/// a reference to `owner` as its base, so the memory outlives the array. It is made
/// read-only before any Python code sees it, so nothing writes to the `PROT_READ` mapping.
#[allow(unsafe_code)]
fn view<'py, T: Element + bytemuck::Pod>(
    owner: &Bound<'py, Mapping>,
    section: &dyn Fn() -> String,
    bytes: &[u8],
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    let py = owner.py();
    let shape_error = |e: &dyn std::fmt::Display| {
        MapError::new_err(format!(
            "{}: {} bytes as shape {shape:?}: {e}",
            section(),
            bytes.len()
        ))
    };
    let array = match bytemuck::try_cast_slice::<u8, T>(bytes) {
        Ok(values) => {
            let view = ArrayView::from_shape(IxDyn(shape), values).map_err(|e| shape_error(&e))?;
            unsafe { PyArray::<T, IxDyn>::borrow_from_array(&view, owner.clone().into_any()) }
        }
        Err(_) => {
            let values: Vec<T> = bytemuck::pod_collect_to_vec(bytes);
            PyArray::from_vec(py, values)
                .reshape(shape.to_vec())
                .map_err(|e| shape_error(&e))?
        }
    };
    array.call_method1("setflags", (false,))?;
    Ok(array.into_any())
}

/// A view of `section` (one the library's lookup gave, so not skipped) of the map `owner`
/// holds: `(rows,)` for the kinds whose column count the spec fixes at 1 (point ids, level
/// points, image cameras and ids, offsets, visibility points), else `(rows, cols)`, even with
/// one column (a 1-dimension descriptor block stays 2-D).
pub(crate) fn section_view<'py>(
    owner: &Bound<'py, Mapping>,
    section: &Section,
) -> PyResult<Bound<'py, PyAny>> {
    let opened = &owner.get().opened;
    let map = &opened.map;
    // `{path}: section 3 (level_desc_short, level 2)`, as the library's errors name it.
    let name = || format!("{}: {}", opened.path.display(), section.reference());
    let bytes: &[u8] = match section.codec() {
        // Validated at open: in bounds, aligned, tiling the file. The package opens files
        // (mmap): the whole file is there. Unchecked, so that a view touches no page.
        Codec::Raw => {
            let start = section.offset() as usize;
            let file = map.bytes().ok_or_else(|| {
                MapError::new_err(format!("{}: the map is not in memory", name()))
            })?;
            &file[start..start + section.stored_len() as usize]
        }
        // Any other codec (zstd, and those a later version adds): checked and decoded once
        // by the library, which keeps the bytes; the GIL is released while it decodes.
        _ => owner
            .py()
            .detach(|| map.section_bytes(section))
            .map_err(|e| opened.error(e))?,
    };
    let (rows, cols) = (section.rows() as usize, section.cols() as usize);
    let one_column = matches!(section.kind().expected_layout(), Some((_, Some(1))));
    let shape: Vec<usize> = if one_column && cols == 1 {
        vec![rows]
    } else {
        vec![rows, cols]
    };
    match section.dtype() {
        Dtype::U8 => view::<u8>(owner, &name, bytes, &shape),
        Dtype::U16 => view::<u16>(owner, &name, bytes, &shape),
        Dtype::U32 => view::<u32>(owner, &name, bytes, &shape),
        Dtype::U64 => view::<u64>(owner, &name, bytes, &shape),
        Dtype::F16 => view::<half::f16>(owner, &name, bytes, &shape),
        Dtype::F32 => view::<f32>(owner, &name, bytes, &shape),
        Dtype::F64 => view::<f64>(owner, &name, bytes, &shape),
        #[allow(unreachable_patterns)]
        other => Err(MapError::new_err(format!(
            "{}: dtype {}: not one this package can view",
            name(),
            other.name()
        ))),
    }
}

#[pymethods]
impl Map {
    /// Opens the map at `path` by mmap; only the header, section table and metadata are read.
    #[new]
    fn new(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let map = py
            .detach(|| FormatMap::open(&path))
            .map_err(|e| format_error(&path, e))?;
        let opened = Arc::new(Opened {
            map: Arc::new(map),
            path: path.clone(),
        });
        let mapping = Py::new(py, Mapping { opened })?;
        Ok(Map {
            mapping: Mutex::new(Some(mapping)),
            path,
        })
    }

    /// Drops this object's hold on the mapping; later calls raise `ClosedError`. Views and
    /// localizers made before keep the mapping alive until they are gone. Closing twice is
    /// fine.
    fn close(&self) {
        let taken = self
            .mapping
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .take();
        drop(taken);
    }

    #[getter]
    fn closed(&self) -> bool {
        self.mapping
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .is_none()
    }

    /// The path the map was opened from.
    #[getter]
    fn path(&self) -> String {
        self.path.display().to_string()
    }

    /// `major.minor` of the file.
    #[getter]
    fn version(&self, py: Python<'_>) -> PyResult<String> {
        Ok(self.opened(py)?.map.version())
    }

    #[getter]
    fn file_bytes(&self, py: Python<'_>) -> PyResult<u64> {
        Ok(self.opened(py)?.map.file_len())
    }

    #[getter]
    fn n_points(&self, py: Python<'_>) -> PyResult<u64> {
        Ok(self.opened(py)?.map.n_points())
    }

    #[getter]
    fn n_images(&self, py: Python<'_>) -> PyResult<u64> {
        Ok(self.opened(py)?.map.n_images())
    }

    /// Level ids, ascending.
    #[getter]
    fn level_ids(&self, py: Python<'_>) -> PyResult<Vec<u16>> {
        Ok(self.opened(py)?.map.level_ids())
    }

    /// The metadata `origin` that point positions are relative to.
    #[getter]
    fn origin(&self, py: Python<'_>) -> PyResult<(f64, f64, f64)> {
        let [x, y, z] = self.opened(py)?.map.metadata().origin;
        Ok((x, y, z))
    }

    /// The metadata block as JSON text.
    fn _metadata_json(&self, py: Python<'_>) -> PyResult<String> {
        let opened = self.opened(py)?;
        serde_json::to_string(opened.map.metadata())
            .map_err(|e| MapError::new_err(format!("{}: metadata: {e}", opened.path.display())))
    }

    /// What `sfpmap info --json` prints, as JSON text.
    fn _info_json(&self, py: Python<'_>) -> PyResult<String> {
        let opened = self.opened(py)?;
        let info = sfpmap::io::info::Info::of(&opened.map, &opened.path);
        serde_json::to_string(&info)
            .map_err(|e| MapError::new_err(format!("{}: info: {e}", opened.path.display())))
    }

    /// A read-only numpy view of the section `kind` (its spec name) of `level`, or `None` if
    /// the map has none or this reader skips it (a later minor's encoding it does not know).
    /// `InputError` for a name that is no section kind.
    #[pyo3(signature = (kind, level=None))]
    fn _section<'py>(
        &self,
        py: Python<'py>,
        kind: &str,
        level: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<Option<Bound<'py, PyAny>>> {
        let owner = self.mapping(py)?;
        let opened = owner.get().opened.clone();
        let kind = kind_named(kind).ok_or_else(|| {
            InputError::new_err(format!("section kind {kind:?}: not a kind of the spec"))
        })?;
        // A level no id can be has no section.
        let level = match level.map(level_arg).transpose()?.transpose() {
            Ok(level) => level,
            Err(_) => return Ok(None),
        };
        match opened.map.find(kind, level) {
            Some(section) => Ok(Some(section_view(&owner, section)?)),
            None => Ok(None),
        }
    }

    /// Point positions relative to `origin` (`world`: false, float32) or in the world
    /// (float64), `(points, 3)`: the stored `point_positions`, or a minimal map's
    /// `point_positions_q16` decoded from its grid, as the library reads them (checked). A
    /// copy.
    #[pyo3(signature = (world=false))]
    fn _point_positions<'py>(&self, py: Python<'py>, world: bool) -> PyResult<Bound<'py, PyAny>> {
        let opened = self.opened(py)?;
        let map = &opened.map;
        let positions = py
            .detach(|| map.point_positions())
            .map_err(|e| opened.error(e))?;
        let n = positions.len();
        let array = if world {
            let flat: Vec<f64> = positions.iter().flat_map(|&p| map.to_world(p)).collect();
            PyArray::from_vec(py, flat).reshape([n, 3])?.into_any()
        } else {
            let flat: Vec<f32> = positions.iter().flatten().copied().collect();
            PyArray::from_vec(py, flat).reshape([n, 3])?.into_any()
        };
        Ok(array)
    }

    /// `(points, dim_short, dim_full, has_rest, has_descriptors, descriptor, stride)` of a
    /// level.
    fn _level_info(
        &self,
        py: Python<'_>,
        level: &Bound<'_, PyAny>,
    ) -> PyResult<(usize, usize, usize, bool, bool, String, f64)> {
        let opened = self.opened(py)?;
        let level = level_arg(level)?
            .map_err(|bad| no_such_level(&opened.path, &bad, &opened.map.level_ids()))?;
        let l = opened.map.level(level).map_err(|e| opened.error(e))?;
        Ok((
            l.len(),
            l.dim_short(),
            l.dim_full(),
            l.has_rest(),
            l.has_descriptors(),
            l.info().descriptor.clone(),
            l.info().stride,
        ))
    }

    /// The database images' names, in map order (checked: UTF-8, offsets in range).
    fn _image_names(&self, py: Python<'_>) -> PyResult<Option<Vec<String>>> {
        let opened = self.opened(py)?;
        let images = opened.map.images().map_err(|e| opened.error(e))?;
        let Some(images) = images else {
            return Ok(None);
        };
        (0..images.len())
            .map(|i| {
                images
                    .name(i)
                    .map(str::to_string)
                    .map_err(|e| opened.error(e))
            })
            .collect::<PyResult<Vec<_>>>()
            .map(Some)
    }

    /// Checks every section (checksums, decoding, contents) as `sfpmap verify` does; raises
    /// `MapError` on the first problem.
    fn verify(&self, py: Python<'_>) -> PyResult<()> {
        let opened = self.opened(py)?;
        py.detach(|| opened.map.verify())
            .map_err(|e| opened.error(e))
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        match self.opened(py) {
            Ok(o) => format!(
                "sfpmap.Map({:?}, version {}, {} points, {} images, levels {:?})",
                self.path.display().to_string(),
                o.map.version(),
                o.map.n_points(),
                o.map.n_images(),
                o.map.level_ids()
            ),
            Err(_) => format!("sfpmap.Map({:?}, closed)", self.path.display().to_string()),
        }
    }
}
