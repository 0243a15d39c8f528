//! The one error of kapture reading and writing.

use crate::output::OutputError;
use std::fmt;
use std::path::PathBuf;

/// What can go wrong reading or writing a kapture folder. Each names the file (and the line,
/// for a text file) in one line of text.
#[derive(Debug)]
#[non_exhaustive]
pub enum KaptureError {
    /// A file the folder needs is not there.
    Missing {
        /// The file.
        path: PathBuf,
        /// Why it is needed, in words.
        needed_for: &'static str,
    },
    /// A file cannot be opened or read (not a regular file, no permission, an I/O error).
    Read {
        /// The file.
        path: PathBuf,
        /// The cause, as text.
        reason: String,
    },
    /// A text line is not what its table holds.
    Line {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// A trajectory or record for a device that neither `sensors.txt` nor `rigs.txt` lists.
    UnknownDevice {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The device id.
        device: String,
    },
    /// A format version other than 1.0 or 1.1 in a file's first line.
    Version {
        /// The file.
        path: PathBuf,
        /// The version it states.
        found: String,
    },
    /// A `.kpt` or `.desc` file whose length is not a whole number of records.
    Truncated {
        /// The file.
        path: PathBuf,
        /// Its length in bytes.
        len: u64,
        /// Bytes of one keypoint or descriptor (`dsize × dtype`'s size).
        record: u64,
    },
    /// An image's keypoints and descriptors differ in count.
    CountMismatch {
        /// The descriptors file.
        path: PathBuf,
        /// Descriptors in it.
        descriptors: u64,
        /// Keypoints of the image.
        keypoints: u64,
    },
    /// The folder holds several keypoints types and none was chosen.
    Ambiguous {
        /// The folder of the types.
        path: PathBuf,
        /// What is ambiguous (`"keypoints"`, `"descriptors"`).
        what: &'static str,
        /// The types found.
        found: Vec<String>,
    },
    /// The model read is not consistent (COLMAP's checks, e.g. an observation twice).
    Model(crate::colmap::Error),
    /// What is written cannot be held by kapture (a name with a comma, a camera model kapture
    /// does not know), or the map lacks what a kapture output needs.
    Unwritable {
        /// What it is about (`image 3`, `camera 1`).
        what: String,
        /// Why.
        reason: String,
    },
    /// A map section read for an export.
    Map(crate::format::Error),
    /// An output that may not or could not be written.
    Output(OutputError),
}

impl fmt::Display for KaptureError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        use KaptureError as E;
        match self {
            E::Missing { path, needed_for } => {
                write!(
                    f,
                    "{}: missing (a kapture folder needs it for {needed_for})",
                    crate::escape::path(path)
                )
            }
            E::Read { path, reason } => write!(f, "{}: {reason}", crate::escape::path(path)),
            E::Line {
                path,
                line,
                message,
            } => write!(f, "{}:{line}: {message}", crate::escape::path(path)),
            E::UnknownDevice { path, line, device } => write!(
                f,
                "{}:{line}: device {} is not in sensors/sensors.txt or sensors/rigs.txt",
                crate::escape::path(path),
                crate::escape::quoted_name(device)
            ),
            E::Version { path, found } => write!(
                f,
                "{}:1: kapture format {} (this reader knows 1.0 and 1.1)",
                crate::escape::path(path),
                crate::escape::quoted_name(found)
            ),
            E::Truncated { path, len, record } => write!(
                f,
                "{}: {len} bytes is not a whole number of {record}-byte records (truncated?)",
                crate::escape::path(path)
            ),
            E::CountMismatch {
                path,
                descriptors,
                keypoints,
            } => write!(
                f,
                "{}: {descriptors} descriptors but the image has {keypoints} keypoints",
                crate::escape::path(path)
            ),
            E::Ambiguous { path, what, found } => write!(
                f,
                "{}: {} {what} types ({}); choose one",
                crate::escape::path(path),
                found.len(),
                found.join(", ")
            ),
            E::Model(e) => e.fmt(f),
            E::Unwritable { what, reason } => write!(f, "{what}: {reason}"),
            E::Map(e) => e.fmt(f),
            E::Output(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for KaptureError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            KaptureError::Model(e) => e.source(),
            KaptureError::Map(e) => e.source(),
            KaptureError::Output(e) => e.source(),
            _ => None,
        }
    }
}

impl From<OutputError> for KaptureError {
    fn from(e: OutputError) -> Self {
        KaptureError::Output(e)
    }
}

impl From<crate::format::Error> for KaptureError {
    fn from(e: crate::format::Error) -> Self {
        KaptureError::Map(e)
    }
}

impl From<crate::colmap::Error> for KaptureError {
    fn from(e: crate::colmap::Error) -> Self {
        KaptureError::Model(e)
    }
}
