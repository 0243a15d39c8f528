//! External formats in and out, each reader beside its writer: poses (`poses`), hloc's
//! `features.h5`, query inputs (`queries`), MCAP logs (`mcap_io`), the `info --json` object
//! (`info`); and maps out to other tools: a COLMAP text model, a PLY point cloud, TUM /
//! images.txt poses, a PNG plot.

#[cfg(feature = "colmap-model")]
pub mod colmap_export;
#[cfg(feature = "hdf5")]
pub mod features_h5;
/// `info` needs `colmap-model` only to escape text (`colmap::text`).
#[cfg(feature = "colmap-model")]
pub mod info;
/// kapture folders in (`convert --kapture`) and out (`export --kapture`, `localize --format
/// kapture`); reading keeps COLMAP's keypoint-scale rule, so it comes with `colmap`.
#[cfg(feature = "colmap")]
pub mod kapture;
#[cfg(feature = "mcap")]
pub mod mcap_io;
#[cfg(feature = "plot")]
pub mod plot;
pub mod ply;
#[cfg(feature = "colmap-model")]
pub mod poses;
#[cfg(feature = "localize")]
pub mod queries;

use std::path::PathBuf;

/// A problem with an input file (query list, features file, poses file), naming the file and,
/// when known, the line.
#[derive(Debug)]
#[non_exhaustive]
pub struct InputError {
    /// The file.
    pub path: PathBuf,
    /// 1-based line, for line-based files.
    pub line: Option<usize>,
    /// What is wrong.
    pub message: String,
}

impl std::fmt::Display for InputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // The message quotes the file's text (names, values): escaped, so the line stays one.
        let message = crate::escape::escape_control_characters(&self.message);
        match self.line {
            Some(line) => write!(f, "{}:{line}: {message}", crate::escape::path(&self.path)),
            None => write!(f, "{}: {message}", crate::escape::path(&self.path)),
        }
    }
}

impl std::error::Error for InputError {}

/// The data lines of a text input (`#` comments and blank lines skipped, each trimmed), each
/// parsed by `parse`; its error becomes an [`InputError`] naming the file and the line.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
pub(crate) fn parse_lines<T>(
    path: &std::path::Path,
    mut parse: impl FnMut(&str) -> Result<T, String>,
) -> Result<Vec<T>, InputError> {
    let text = crate::input::read_regular_to_string(path).map_err(|e| InputError {
        path: path.into(),
        line: None,
        message: e.to_string(),
    })?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        out.push(parse(line).map_err(|message| InputError {
            path: path.into(),
            line: Some(i + 1),
            message,
        })?);
    }
    Ok(out)
}
