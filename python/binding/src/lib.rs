//! `sfpmap._sfpmap`: the compiled half of the Python package `sfpmap` (the pure-Python half,
//! `sfpmap/__init__.py`, wraps it in the documented API).
//!
//! What lives where: `map.rs` opens maps and hands out numpy views of their sections (the
//! first of its two `unsafe` blocks is there); `localize.rs` holds cameras, query features, the
//! localizer and its results; `build.rs` convert, slice and `from_pycolmap`; `extract.rs`
//! the SFP extractor, hloc's `features.h5` and COLMAP query databases; `errors.rs` the
//! exception classes and the CLI's one-line messages.
//!
//! Every call that does real work (open, verify, convert, slice, extract, localize) runs with
//! the GIL released (`Python::detach`).
//!
//! `unsafe` is denied but for two items, each with its `SAFETY` note: `map::view` (a numpy
//! array over the mapping) and `Localizer::new` (the localizer borrowing the map it owns).
#![deny(unsafe_code)]

mod build;
mod errors;
mod extract;
mod localize;
mod map;

use pyo3::prelude::*;

#[pymodule]
fn _sfpmap(m: &Bound<'_, PyModule>) -> PyResult<()> {
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
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
