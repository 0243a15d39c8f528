//! `sfpmap._sfpmap`: the compiled half of the Python package `sfpmap` (the pure-Python half,
//! `sfpmap/__init__.py`, wraps it in the documented API).
//!
//! What lives where: `map.rs` opens maps and hands out numpy views of their sections (the
//! one `unsafe` block is there); `localize.rs` holds cameras, query features, the localizer
//! (a library `Session`) and its results; `build.rs` convert, slice and `from_pycolmap`; `objects.rs` object storage and catalogs for
//! `sfpmap.batch`; `extract.rs`
//! the SFP extractor, hloc's `features.h5` and COLMAP query databases; `errors.rs` the
//! exception classes and the CLI's one-line messages.
//!
//! Every call that does real work (open, verify, convert, slice, extract, localize) runs with
//! the GIL released (`Python::detach`).
//!
//! `unsafe` is denied but for one item, with its `SAFETY` note: `map::view` (a numpy array
//! over the mapping). The localizer and the map it borrows are owned together by the
//! library's `Session` (no lifetime cast here).
#![deny(unsafe_code)]

mod build;
mod errors;
mod extract;
mod localize;
mod map;
mod objects;

use pyo3::prelude::*;
use std::sync::Mutex;

/// Collects the library's warnings, for Python's `warnings` once the work is done.
#[derive(Default)]
pub(crate) struct Warnings(Mutex<Vec<String>>);

impl sfpmap::progress::Reporter for Warnings {
    fn warn(&self, message: &str) {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(message.to_string());
    }
}

impl Warnings {
    /// Each warning as a Python `RuntimeWarning`, attributed to the caller of the package's
    /// function.
    pub(crate) fn emit(self, py: Python<'_>) -> PyResult<()> {
        let category = py.get_type::<pyo3::exceptions::PyRuntimeWarning>();
        for message in self.0.into_inner().unwrap_or_else(|p| p.into_inner()) {
            let text = std::ffi::CString::new(message.replace('\0', " "))
                .expect("no NUL left in the message");
            PyErr::warn(py, &category, &text, 2)?;
        }
        Ok(())
    }

    /// [`Warnings::emit`], then `result`: the warnings of a call that failed are shown too (a
    /// failed ONNX Runtime fetch says it tried). The call's own error wins over one a warning
    /// raises (`-W error`).
    pub(crate) fn emit_then<T>(self, py: Python<'_>, result: PyResult<T>) -> PyResult<T> {
        let emitted = self.emit(py);
        let value = result?;
        emitted?;
        Ok(value)
    }
}

/// A `threads` argument as the CLI takes `--threads`: at least 1 (`InputError`, as the CLI's
/// parser refuses less), capped at 4 per core and at most 256 with a `RuntimeWarning`
/// (`sfpmap::progress::cap_threads`). `None`: the machine's available parallelism.
pub(crate) fn thread_count(py: Python<'_>, requested: Option<i64>) -> PyResult<usize> {
    let requested = match requested {
        Some(n) if n < 1 => {
            return Err(errors::InputError::new_err(format!(
                "threads {n}: at least 1 thread"
            )))
        }
        Some(n) => usize::try_from(n).unwrap_or(usize::MAX),
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    let warnings = Warnings::default();
    let threads = sfpmap::progress::cap_threads("threads", requested, &warnings);
    warnings.emit(py)?;
    Ok(threads)
}

#[pymodule]
fn _sfpmap(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // `ORT_DISABLE_TELEMETRY=1` (`std::env::set_var`) once, here: at import, with the GIL
    // held and before this module has started any thread. Writing the environment while
    // another thread reads it (`getenv`) is undefined behaviour, and later, in a detached
    // call, other Python threads could be doing just that. The library's `runtime()` calls it
    // again before loading ONNX Runtime, a no-op by then (a `OnceLock`); the session builder
    // also turns telemetry off (`with_telemetry(false)`).
    sfpmap::extract::runtime::disable_telemetry();
    errors::register(m)?;
    m.add_class::<map::Map>()?;
    m.add_class::<map::Mapping>()?;
    m.add_class::<localize::Camera>()?;
    m.add_class::<localize::Features>()?;
    m.add_class::<localize::Localizer>()?;
    m.add_class::<localize::Localization>()?;
    m.add_class::<extract::Extractor>()?;
    m.add_class::<extract::FeaturesFile>()?;
    m.add_class::<extract::QueryDatabase>()?;
    m.add_function(wrap_pyfunction!(build::convert, m)?)?;
    m.add_function(wrap_pyfunction!(build::slice, m)?)?;
    m.add_function(wrap_pyfunction!(build::from_pycolmap, m)?)?;
    m.add_function(wrap_pyfunction!(build::write_synthetic_map, m)?)?;
    m.add_function(wrap_pyfunction!(localize::read_queries, m)?)?;
    m.add_function(wrap_pyfunction!(localize::read_poses, m)?)?;
    m.add_function(wrap_pyfunction!(localize::pinhole_intrinsics, m)?)?;
    m.add_function(wrap_pyfunction!(objects::object_list, m)?)?;
    m.add_function(wrap_pyfunction!(objects::object_head, m)?)?;
    m.add_function(wrap_pyfunction!(objects::object_download, m)?)?;
    m.add_function(wrap_pyfunction!(objects::object_upload, m)?)?;
    m.add_function(wrap_pyfunction!(objects::object_delete, m)?)?;
    m.add_function(wrap_pyfunction!(objects::object_list_folders, m)?)?;
    m.add_function(wrap_pyfunction!(objects::is_url, m)?)?;
    m.add_function(wrap_pyfunction!(objects::map_metadata, m)?)?;
    m.add_function(wrap_pyfunction!(objects::build_catalog, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
