//! The exception classes and how library errors become them.
//!
//! Messages are the CLI's: the CLI prints `error: {err:#}` (the error, then each cause after
//! `: `), with the file at fault in front; an exception's text is that line without
//! `error: `.

use pyo3::exceptions::{PyException, PyOverflowError};
use pyo3::prelude::*;
use pyo3::{create_exception, PyErr};
use std::path::Path;

create_exception!(
    sfpmap,
    Error,
    PyException,
    "Base class of every error sfpmap raises."
);
create_exception!(
    sfpmap,
    MapError,
    Error,
    "A map file that is not a valid map, or a section that fails its checks."
);
create_exception!(
    sfpmap,
    FileError,
    Error,
    "A file that cannot be read or written (missing, not a regular file, an existing output)."
);
create_exception!(
    sfpmap,
    NoSuchLevelError,
    MapError,
    "The map has no such level."
);
create_exception!(
    sfpmap,
    ClosedError,
    Error,
    "The map was closed (`Map.close()`)."
);
create_exception!(
    sfpmap,
    ConvertError,
    Error,
    "A COLMAP model (or its database, images, pycolmap object) that cannot be converted."
);
create_exception!(
    sfpmap,
    LocalizeError,
    Error,
    "Query features or a map that cannot be localized against (not a failed query)."
);
create_exception!(
    sfpmap,
    ExtractError,
    Error,
    "The SFP extractor failed: no ONNX Runtime, a bad model, an image that does not decode."
);
create_exception!(
    sfpmap,
    InputError,
    Error,
    "An input that cannot be used: a camera, a query list, a features file, an argument."
);

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("Error", py.get_type::<Error>())?;
    m.add("MapError", py.get_type::<MapError>())?;
    m.add("FileError", py.get_type::<FileError>())?;
    m.add("NoSuchLevelError", py.get_type::<NoSuchLevelError>())?;
    m.add("ClosedError", py.get_type::<ClosedError>())?;
    m.add("ConvertError", py.get_type::<ConvertError>())?;
    m.add("LocalizeError", py.get_type::<LocalizeError>())?;
    m.add("ExtractError", py.get_type::<ExtractError>())?;
    m.add("InputError", py.get_type::<InputError>())?;
    Ok(())
}

/// `e` and its causes, `: `-separated, as anyhow's `{:#}` prints them, on one line: the
/// messages of ONNX Runtime, SQLite or HDF5 may hold line breaks (ORT ends some with one).
pub(crate) fn chain(e: &dyn std::error::Error) -> String {
    let mut text = one_line(&e.to_string());
    let mut source = e.source();
    while let Some(s) = source {
        text.push_str(": ");
        text.push_str(&one_line(&s.to_string()));
        source = s.source();
    }
    text
}

/// `text` with its lines trimmed and joined by `; ` (blank ones dropped); as it is when it
/// holds no line break.
pub(crate) fn one_line(text: &str) -> String {
    if !text.contains(['\n', '\r']) {
        return text.to_string();
    }
    text.split(['\n', '\r'])
        .map(str::trim)
        .filter(|line| !line.is_empty())
        .collect::<Vec<_>>()
        .join("; ")
}

/// `context: chain(e)`.
pub(crate) fn within(context: &str, e: &dyn std::error::Error) -> String {
    format!("{context}: {}", chain(e))
}

/// A format error of the map at `path`, as the CLI's `open_map` reports it: the path in
/// front unless the error (an I/O error) names it already.
pub(crate) fn format_error(path: &Path, e: sfpmap::format::Error) -> PyErr {
    use sfpmap::format::Error as E;
    match &e {
        E::Io { .. } => FileError::new_err(chain(&e)),
        E::NotARegularFile { .. } => FileError::new_err(within(&path.display().to_string(), &e)),
        E::NoSuchLevel { .. } => NoSuchLevelError::new_err(within(&path.display().to_string(), &e)),
        _ => MapError::new_err(within(&path.display().to_string(), &e)),
    }
}

/// A level argument (any Python int): `Ok(id)`, or `Err(its decimal text)` for an int no
/// level id can be (negative, past 65535); not an int is Python's `TypeError`.
pub(crate) fn level_arg(obj: &Bound<'_, PyAny>) -> PyResult<Result<u16, String>> {
    match obj.extract::<i64>() {
        Ok(level) => Ok(u16::try_from(level).map_err(|_| level.to_string())),
        Err(e) if e.is_instance_of::<PyOverflowError>(obj.py()) => Ok(Err(obj.str()?.to_string())),
        Err(e) => Err(e),
    }
}

/// `NoSuchLevelError` for a level no id can be (`level`: its decimal text), in the words of
/// the library's `no_such_level`, the map's path in front.
pub(crate) fn no_such_level(path: &Path, level: &str, available: &[u16]) -> PyErr {
    NoSuchLevelError::new_err(format!(
        "{}: no level {level} in this map (levels: {available:?})",
        path.display()
    ))
}

/// `levels` (Python ints) as level ids; one that cannot be an id is `no_such_level` of the
/// map at `path`, whose levels `available` lists.
pub(crate) fn level_ids(
    path: &Path,
    levels: &[Bound<'_, PyAny>],
    available: impl FnOnce() -> Vec<u16>,
) -> PyResult<Vec<u16>> {
    let ids = levels.iter().map(level_arg).collect::<PyResult<Vec<_>>>()?;
    ids.into_iter()
        .collect::<Result<Vec<u16>, String>>()
        .map_err(|bad| no_such_level(path, &bad, &available()))
}

pub(crate) fn output_error(e: sfpmap::output::OutputError) -> PyErr {
    FileError::new_err(chain(&e))
}
