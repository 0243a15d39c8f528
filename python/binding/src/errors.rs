//! The exception classes and how library errors become them.
//!
//! Messages are the CLI's: the CLI prints `error: {err:#}` (the error, then each cause after
//! `: `), with the file at fault in front; an exception's text is that line without
//! `error: `.

use pyo3::exceptions::{PyException, PyOverflowError};
use pyo3::prelude::*;
use pyo3::{create_exception, PyErr};
use sfpmap::session::SessionError;
use sfpmap::ErrorKind;
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
    "Query features or a map that cannot be localized against (not a failed query): features of another model than the map's, descriptors of another size."
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

/// The exception of a library error of kind `kind` with the text `text`: the one place the
/// classes are made from the library's [`ErrorKind`]s (which the C ABI's status codes are made
/// from too).
pub(crate) fn exception(kind: ErrorKind, text: String) -> PyErr {
    match kind {
        ErrorKind::Io => FileError::new_err(text),
        ErrorKind::Format | ErrorKind::Missing => MapError::new_err(text),
        ErrorKind::NoSuchLevel => NoSuchLevelError::new_err(text),
        ErrorKind::InvalidArgument | ErrorKind::Input => InputError::new_err(text),
        ErrorKind::NoDescriptors | ErrorKind::Mismatch | ErrorKind::Localize => {
            LocalizeError::new_err(text)
        }
        ErrorKind::Extract => ExtractError::new_err(text),
        ErrorKind::Convert => ConvertError::new_err(text),
        // `Other`, and a kind a later library adds.
        _ => Error::new_err(text),
    }
}

/// `e` and its causes, `: `-separated, as anyhow's `{:#}` prints them, on one line: the
/// messages of ONNX Runtime, SQLite or HDF5 may hold line breaks (ORT ends some with one).
pub(crate) fn chain(e: &dyn std::error::Error) -> String {
    causes(one_line(&e.to_string()), e.source())
}

/// `text`, then `source` and its own causes, each after `: `, on one line.
fn causes(mut text: String, mut source: Option<&(dyn std::error::Error + 'static)>) -> String {
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
    let text = match &e {
        sfpmap::format::Error::Io { .. } => chain(&e),
        _ => within(&path.display().to_string(), &e),
    };
    exception(sfpmap::Error::from(e).kind(), text)
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

/// An extractor's error: `FileError` for an image that cannot be read, else `ExtractError`.
pub(crate) fn extract_error(e: sfpmap::extract::ExtractError) -> PyErr {
    let text = chain(&e);
    exception(sfpmap::Error::from(e).kind(), text)
}

/// An option out of its range, in the library's words alone (`top_k 0: 1 to 100000 images`):
/// an `InputError`, as any other argument the package refuses.
pub(crate) fn option_error(e: &sfpmap::localize::OptionError) -> PyErr {
    exception(sfpmap::Error::from(e.clone()).kind(), e.to_string())
}

/// The one place a session's error becomes an exception, by its kind
/// ([`SessionError::kind`]):
///
/// - an option out of range: `InputError`, the library's message alone (no map in front);
/// - the map (a level it lacks, a damaged section), while building the localizer, while a
///   query reads it, or otherwise: `NoSuchLevelError`, `FileError` or `MapError`, as
///   [`format_error`] picks;
/// - query features that do not fit the map (another model's, descriptors of another size,
///   a level they lack), a map that cannot be localized against: `LocalizeError`;
/// - a features file, a query database, a session asked for a query by name that it does
///   not read: `InputError`;
/// - the extractor: `ExtractError` (`FileError` for an image that cannot be read).
///
/// The text is the CLI's line: the session's message (the map or file in front) and its
/// causes.
pub(crate) fn session_error(e: SessionError) -> PyErr {
    let text = match &e {
        SessionError::Localize {
            source: sfpmap::localize::LocalizeError::Option(o),
            ..
        } => o.to_string(),
        _ => session_text(&e),
    };
    exception(e.kind(), text)
}

/// `e`'s text and its causes on one line. A session error's text holds its source's text
/// already (`MAP: query NAME: {source}`): the line goes on from the source's own causes,
/// so that nothing is said twice.
fn session_text(e: &SessionError) -> String {
    use std::error::Error as _;
    let text = one_line(&e.to_string());
    let source = match e.source() {
        Some(s) if text.contains(&one_line(&s.to_string())) => s.source(),
        other => other,
    };
    causes(text, source)
}

pub(crate) fn output_error(e: sfpmap::output::OutputError) -> PyErr {
    let text = chain(&e);
    exception(sfpmap::Error::from(e).kind(), text)
}
