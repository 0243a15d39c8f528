//! Object storage and catalogs for batch jobs (`sfpmap.batch`): list, read, write and delete
//! whole objects at `s3://` and `http(s)://` URLs (the library's `remote::objects`, with the
//! CLI's credentials and outbound policy), a map's metadata from a file or a URL (read by
//! range), and `catalog build`. Each call runs with the GIL released.

use crate::errors::{chain, format_error, output_error, FileError, InputError};
use pyo3::prelude::*;
use sfpmap::remote::objects::{self, ObjectInfo};
use sfpmap::remote::RemoteOptions;
use std::path::{Path, PathBuf};

/// `(url, size, etag, last_modified_ms)`: an object as Python sees it.
type Object = (String, u64, Option<String>, i64);

fn object(info: ObjectInfo) -> Object {
    (info.url, info.size, info.e_tag, info.last_modified_ms)
}

/// What batch reads go through: the CLI's remote options but no section cache (a job reads
/// each map's metadata once; thousands of places would only churn the cache).
fn uncached() -> RemoteOptions {
    let mut options = RemoteOptions::from_env();
    options.cache_dir = None;
    options
}

fn failed(e: sfpmap::format::Error) -> PyErr {
    FileError::new_err(chain(&e))
}

/// The objects under the prefix `url`, sorted by URL; more than `max_objects` is an error.
#[pyfunction]
#[pyo3(signature = (url, max_objects=100_000))]
pub(crate) fn object_list(
    py: Python<'_>,
    url: String,
    max_objects: usize,
) -> PyResult<Vec<Object>> {
    py.detach(|| objects::list(&url, max_objects, &RemoteOptions::from_env()))
        .map(|all| all.into_iter().map(object).collect())
        .map_err(failed)
}

/// The object at `url`, or `None` when there is none.
#[pyfunction]
pub(crate) fn object_head(py: Python<'_>, url: String) -> PyResult<Option<Object>> {
    py.detach(|| objects::head(&url, &RemoteOptions::from_env()))
        .map(|found| found.map(object))
        .map_err(failed)
}

/// Reads the object at `url` into the file `dest` (complete or not there); larger than
/// `max_bytes` is an error before anything is written.
#[pyfunction]
pub(crate) fn object_download(
    py: Python<'_>,
    url: String,
    dest: PathBuf,
    max_bytes: u64,
) -> PyResult<Object> {
    py.detach(|| objects::download(&url, &dest, max_bytes, &RemoteOptions::from_env()))
        .map(object)
        .map_err(failed)
}

/// Writes the file `src` as the object at `url` (it appears only complete, its SHA-256 checked
/// by the server).
#[pyfunction]
pub(crate) fn object_upload(py: Python<'_>, src: PathBuf, url: String) -> PyResult<Object> {
    py.detach(|| objects::upload(&src, &url, &RemoteOptions::from_env()))
        .map(object)
        .map_err(failed)
}

/// The folders right under the prefix `url` (one listing request per thousand), sorted.
#[pyfunction]
#[pyo3(signature = (url, max_folders=100_000))]
pub(crate) fn object_list_folders(
    py: Python<'_>,
    url: String,
    max_folders: usize,
) -> PyResult<Vec<String>> {
    py.detach(|| objects::list_folders(&url, max_folders, &RemoteOptions::from_env()))
        .map_err(failed)
}

/// Whether `name` is an `http(s)://` or `s3://` URL, as every command decides.
#[pyfunction]
pub(crate) fn is_url(name: &str) -> bool {
    sfpmap::input::is_url(name)
}

/// Deletes the object at `url` (none there is no error).
#[pyfunction]
pub(crate) fn object_delete(py: Python<'_>, url: String) -> PyResult<()> {
    py.detach(|| objects::delete(&url, &RemoteOptions::from_env()))
        .map_err(failed)
}

/// The metadata (JSON text) of the map at `location`, a file or a URL read by range (the
/// header, index and metadata section only).
#[pyfunction]
pub(crate) fn map_metadata(py: Python<'_>, location: PathBuf) -> PyResult<String> {
    py.detach(|| {
        let map = sfpmap::remote::open_location(&location, &uncached())
            .map_err(|e| format_error(&location, e))?;
        serde_json::to_string(map.metadata()).map_err(|e| FileError::new_err(e.to_string()))
    })
}

/// `sfpmap catalog build`: a catalog of the place maps `maps` (files or URLs) named `names`,
/// written to `out`. The catalog records each map as `locations` says (default: as given; a
/// path relative to the catalog's folder lets the folder move), and `job` (a JSON object) as
/// `provenance.parameters.job`. Returns `{output, bytes, places}` as JSON text.
#[pyfunction]
#[pyo3(signature = (maps, names, *, out, locations=None, job=None, force=false))]
pub(crate) fn build_catalog(
    py: Python<'_>,
    maps: Vec<String>,
    names: Vec<String>,
    out: PathBuf,
    locations: Option<Vec<String>>,
    job: Option<&str>,
    force: bool,
) -> PyResult<String> {
    use sfpmap::build::catalog::{build_catalog, PlaceMap};
    let locations = locations.unwrap_or_else(|| maps.clone());
    if maps.len() != names.len() || maps.len() != locations.len() {
        return Err(InputError::new_err(format!(
            "{} names and {} locations for {} maps: one each",
            names.len(),
            locations.len(),
            maps.len()
        )));
    }
    let job = crate::build::job_record(job)?;
    let mut seen = std::collections::HashSet::new();
    if let Some(twice) = names.iter().find(|n| !seen.insert(n.as_str())) {
        return Err(InputError::new_err(format!(
            "two places are named {twice:?}"
        )));
    }
    let local: Vec<&Path> = maps
        .iter()
        .filter(|m| !sfpmap::input::is_url(m))
        .map(Path::new)
        .collect();
    sfpmap::output::check_output(&out, &local, force).map_err(output_error)?;
    py.detach(|| {
        let options = uncached();
        let opened = maps
            .iter()
            .map(|m| {
                sfpmap::remote::open_location(Path::new(m), &options)
                    .map_err(|e| format_error(Path::new(m), e))
            })
            .collect::<PyResult<Vec<_>>>()?;
        let places: Vec<PlaceMap<'_>> = names
            .iter()
            .zip(&locations)
            .zip(&opened)
            .map(|((name, location), map)| PlaceMap {
                name: name.clone(),
                location: location.clone(),
                map,
            })
            .collect();
        let mut writer = build_catalog(&places).map_err(|e| {
            FileError::new_err(format!("{}: building the catalog: {e}", out.display()))
        })?;
        if let Some(job) = job {
            let parameters = &mut writer.metadata_mut().provenance.parameters;
            parameters.insert("job".into(), job);
        }
        let bytes = writer
            .write(&out, &sfpmap::progress::Silent)
            .map_err(|e| format_error(&out, e))?;
        let report = serde_json::json!({
            "output": out.display().to_string(),
            "bytes": bytes,
            "places": places.iter().map(|p| serde_json::json!({
                "name": p.name,
                "map": p.location,
                "points": p.map.n_points(),
                "images": p.map.n_images(),
            })).collect::<Vec<_>>(),
        });
        Ok(report.to_string())
    })
}
