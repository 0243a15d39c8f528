//! The one error type of the COLMAP reader.

use std::fmt;
use std::path::{Path, PathBuf};

/// Everything that can go wrong reading a COLMAP model or database.
///
/// Every variant names the file it is about (`path`), so the one-line message is enough for a
/// user to find the problem. Messages are lowercase and have no trailing period. The I/O and
/// SQLite causes are not repeated in the message but returned by `source()`, so that a chain
/// printer (`anyhow`'s `{:#}`) shows each once.
#[derive(Debug)]
#[non_exhaustive]
pub enum Error {
    /// Reading a file failed.
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// Writing a model file or database failed (the output policy's error, path included).
    Output(crate::output::OutputError),
    /// A model file or database is not a regular file (a folder, a FIFO, a device): read
    /// only after this check, so a FIFO never blocks the reader.
    NotAFile {
        /// The file.
        path: PathBuf,
        /// What it is instead (`"a folder"`, `"a FIFO"`).
        kind: &'static str,
    },
    /// A number is NaN or infinite (a map, whose metadata is JSON, cannot store it).
    NotFinite {
        /// The file.
        path: PathBuf,
        /// The 1-based line of a text file; `None` in a binary file.
        line: Option<u64>,
        /// `"camera"`, `"image"` or `"point3D"`.
        kind: &'static str,
        /// The record's id.
        id: u64,
        /// Which value (`"parameter 0"`, `"rotation"`, `"point2D 3 position"`).
        field: String,
    },
    /// An image's rotation is the zero quaternion.
    ZeroRotation {
        /// The file.
        path: PathBuf,
        /// As [`Error::NotFinite::line`].
        line: Option<u64>,
        /// The image's id.
        image_id: u32,
    },
    /// An image name holds a control character (a newline, a tab, an escape): no COLMAP text
    /// file can hold it, and it would inject lines into line-based exports.
    BadImageName {
        /// The file.
        path: PathBuf,
        /// As [`Error::NotFinite::line`].
        line: Option<u64>,
        /// The image's id.
        image_id: u32,
        /// The name, quoted, escaped and shortened for the message.
        name: String,
    },
    /// A folder has neither `cameras.bin` … nor `cameras.txt` ….
    NoModel {
        /// The folder.
        dir: PathBuf,
    },
    /// One file of a model is present but another is not (`images.bin` without `points3D.bin`).
    MissingFile {
        /// The file missing.
        path: PathBuf,
    },
    /// A binary file ends inside a record.
    Truncated {
        /// The file.
        path: PathBuf,
        /// Byte offset where the read started.
        offset: u64,
        /// Bytes the read needed.
        needed: u64,
        /// The file's length.
        len: u64,
        /// What was being read (`"point3D track element"`).
        what: &'static str,
    },
    /// A binary file has bytes after its last record.
    TrailingBytes {
        /// The file.
        path: PathBuf,
        /// Where the bytes after the last record start.
        offset: u64,
        /// The file's length.
        len: u64,
    },
    /// A text file has a line that does not parse.
    BadLine {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: u64,
        /// What does not parse.
        what: String,
    },
    /// A binary file has a value that is not valid (not a length problem).
    BadValue {
        /// The file.
        path: PathBuf,
        /// Byte offset in the file.
        offset: u64,
        /// Which value, and why.
        what: String,
    },
    /// A camera has a model id this crate does not know.
    UnknownCameraModelId {
        /// The file.
        path: PathBuf,
        /// The camera's id.
        camera_id: u32,
        /// The model id found.
        model_id: i64,
    },
    /// A camera has a model name this crate does not know.
    UnknownCameraModelName {
        /// The file.
        path: PathBuf,
        /// 1-based line of the text file.
        line: u64,
        /// The model name found.
        name: String,
    },
    /// A camera has the wrong number of parameters for its model.
    ParamCount {
        /// The file.
        path: PathBuf,
        /// The camera's id.
        camera_id: u32,
        /// The camera's model name.
        model: &'static str,
        /// Parameters the model has.
        expected: usize,
        /// Parameters found.
        found: usize,
    },
    /// The same id appears twice (`kind` is `"camera"`, `"image"` or `"point3D"`).
    DuplicateId {
        /// The file.
        path: PathBuf,
        /// `"camera"`, `"image"` or `"point3D"`.
        kind: &'static str,
        /// The duplicated id.
        id: u64,
    },
    /// An image refers to a camera that does not exist.
    MissingCamera {
        /// The file.
        path: PathBuf,
        /// The image's id.
        image_id: u32,
        /// The camera's id.
        camera_id: u32,
    },
    /// A 3D point's track refers to an image that does not exist.
    TrackImageMissing {
        /// The file.
        path: PathBuf,
        /// The 3D point's id.
        point3d_id: u64,
        /// The image's id.
        image_id: u32,
    },
    /// A 3D point's track refers to a 2D point index past the end of the image's points.
    TrackPoint2DOutOfRange {
        /// The file.
        path: PathBuf,
        /// The 3D point's id.
        point3d_id: u64,
        /// The image's id.
        image_id: u32,
        /// The 2D point's index in the image.
        point2d_idx: u32,
        /// How many 2D points the image has.
        num_points2d: usize,
    },
    /// A track element's 2D point does not point back at the 3D point (COLMAP's
    /// `point2D.point3D_id == point3D_id` check).
    TrackMismatch {
        /// The file.
        path: PathBuf,
        /// The 3D point's id.
        point3d_id: u64,
        /// The image's id.
        image_id: u32,
        /// The 2D point's index in the image.
        point2d_idx: u32,
        /// The `point3D_id` stored on the 2D point (`None`: the 2D point has none).
        found: Option<u64>,
    },
    /// The same (image, point2D) appears twice in tracks.
    DuplicateTrackElement {
        /// The file.
        path: PathBuf,
        /// The 3D point's id.
        point3d_id: u64,
        /// The image's id.
        image_id: u32,
        /// The 2D point's index in the image.
        point2d_idx: u32,
    },
    /// A 2D point refers to a 3D point whose track does not contain it (or that does not exist).
    Point2DNotInTrack {
        /// The file.
        path: PathBuf,
        /// The image's id.
        image_id: u32,
        /// The 2D point's index in the image.
        point2d_idx: u32,
        /// The 3D point's id.
        point3d_id: u64,
        /// Whether the 3D point exists at all.
        point3d_exists: bool,
    },
    /// `.bin` and `.txt` models in one folder disagree.
    ModelsDisagree {
        /// The binary files (`DIR/*.bin`).
        bin: PathBuf,
        /// The text files (`DIR/*.txt`).
        txt: PathBuf,
        /// The first difference.
        what: String,
    },
    /// A database has a non-empty `-wal` file next to it: changes an immutable open would not
    /// see (SQLite ignores the write-ahead log then), so reading would silently miss them.
    PendingWal {
        /// The database.
        path: PathBuf,
        /// Its `-wal` file.
        wal: PathBuf,
    },
    /// A file is not an SQLite database.
    NotADatabase {
        /// The file.
        path: PathBuf,
    },
    /// A database lacks a table COLMAP always creates.
    MissingTable {
        /// The database.
        path: PathBuf,
        /// The table.
        table: &'static str,
    },
    /// A database table lacks a column.
    MissingColumn {
        /// The file.
        path: PathBuf,
        /// The table.
        table: &'static str,
        /// The column.
        column: &'static str,
    },
    /// A database row holds a value that does not fit its schema.
    BadRow {
        /// The file.
        path: PathBuf,
        /// The table.
        table: &'static str,
        /// The row's key (`image_id` or `camera_id`).
        id: i64,
        /// Which value, and why.
        what: String,
    },
    /// The database has no row for an image the caller asked for.
    ImageNotInDatabase {
        /// The database.
        path: PathBuf,
        /// The image's id.
        image_id: u32,
    },
    /// An SQLite call failed.
    #[cfg(feature = "colmap")]
    Sqlite {
        /// The database.
        path: PathBuf,
        /// SQLite's error.
        source: rusqlite::Error,
    },
}

/// The `Result` of this module.
pub type Result<T, E = Error> = std::result::Result<T, E>;

fn show(path: &Path) -> impl std::fmt::Display + '_ {
    crate::escape::path(path)
}

/// `path` or `path:line`.
fn at(path: &Path, line: Option<u64>) -> String {
    match line {
        Some(line) => format!("{}:{line}", show(path)),
        None => show(path).to_string(),
    }
}

/// `name` quoted for a message, control characters escaped (the one rule for all messages).
pub(crate) fn shown_name(name: &str) -> String {
    crate::escape::quoted_name(name)
}

fn opt_id(id: Option<u64>) -> String {
    match id {
        Some(id) => id.to_string(),
        None => "none".to_string(),
    }
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::Io { path, .. } => write!(f, "cannot read {}", show(path)),
            Error::Output(e) => e.fmt(f),
            Error::NotAFile { path, kind } => {
                write!(f, "{}: is {kind}, not a regular file", show(path))
            }
            Error::NotFinite { path, line, kind, id, field } => {
                write!(f, "{}: {kind} {id}: {field} is not finite", at(path, *line))
            }
            Error::ZeroRotation { path, line, image_id } => write!(
                f,
                "{}: image {image_id}: rotation is the zero quaternion",
                at(path, *line)
            ),
            Error::BadImageName { path, line, image_id, name } => write!(
                f,
                "{}: image {image_id}: name {name} holds a control character",
                at(path, *line)
            ),
            Error::NoModel { dir } => write!(
                f,
                "{}: no COLMAP model (neither cameras.bin, images.bin, points3D.bin nor the .txt files)",
                show(dir)
            ),
            Error::MissingFile { path } => {
                write!(f, "{}: missing (the other files of the model are present)", show(path))
            }
            Error::Truncated { path, offset, needed, len, what } => write!(
                f,
                "{}: truncated: {what} at byte {offset} needs {needed} bytes, the file ends at byte {len}",
                show(path)
            ),
            Error::TrailingBytes { path, offset, len } => write!(
                f,
                "{}: {} unexpected bytes after the last record at byte {offset}",
                show(path),
                len.saturating_sub(*offset)
            ),
            Error::BadLine { path, line, what } => write!(f, "{}:{line}: {what}", show(path)),
            Error::BadValue { path, offset, what } => {
                write!(f, "{}: at byte {offset}: {what}", show(path))
            }
            Error::UnknownCameraModelId { path, camera_id, model_id } => write!(
                f,
                "{}: camera {camera_id}: unknown camera model id {model_id}",
                show(path)
            ),
            Error::UnknownCameraModelName { path, line, name } => {
                write!(f, "{}:{line}: unknown camera model {name:?}", show(path))
            }
            Error::ParamCount { path, camera_id, model, expected, found } => write!(
                f,
                "{}: camera {camera_id}: model {model} takes {expected} parameters, found {found}",
                show(path)
            ),
            Error::DuplicateId { path, kind, id } => {
                write!(f, "{}: {kind} id {id} appears more than once", show(path))
            }
            Error::MissingCamera { path, image_id, camera_id } => write!(
                f,
                "{}: image {image_id} refers to camera {camera_id}, which does not exist",
                show(path)
            ),
            Error::TrackImageMissing { path, point3d_id, image_id } => write!(
                f,
                "{}: point3D {point3d_id}: track refers to image {image_id}, which does not exist",
                show(path)
            ),
            Error::TrackPoint2DOutOfRange { path, point3d_id, image_id, point2d_idx, num_points2d } => {
                write!(
                    f,
                    "{}: point3D {point3d_id}: track refers to point2D {point2d_idx} of image \
                     {image_id}, which has only {num_points2d} points2D",
                    show(path)
                )
            }
            Error::TrackMismatch { path, point3d_id, image_id, point2d_idx, found } => write!(
                f,
                "{}: inconsistent track: point3D {point3d_id} lists point2D {point2d_idx} of image \
                 {image_id}, but that point2D's point3D_id is {} ({} vs. {point3d_id})",
                show(path),
                opt_id(*found),
                opt_id(*found)
            ),
            Error::DuplicateTrackElement { path, point3d_id, image_id, point2d_idx } => write!(
                f,
                "{}: point3D {point3d_id}: point2D {point2d_idx} of image {image_id} appears twice in tracks",
                show(path)
            ),
            Error::Point2DNotInTrack { path, image_id, point2d_idx, point3d_id, point3d_exists } => {
                if *point3d_exists {
                    write!(
                        f,
                        "{}: inconsistent track: point2D {point2d_idx} of image {image_id} refers \
                         to point3D {point3d_id}, whose track does not list it",
                        show(path)
                    )
                } else {
                    write!(
                        f,
                        "{}: point2D {point2d_idx} of image {image_id} refers to point3D \
                         {point3d_id}, which does not exist",
                        show(path)
                    )
                }
            }
            Error::ModelsDisagree { bin, txt, what } => write!(
                f,
                "{} and {} disagree: {what}",
                show(bin),
                show(txt)
            ),
            Error::PendingWal { path, wal } => write!(
                f,
                "{}: {} holds changes not yet in the database file, which a read-only open \
                 cannot see; let the program writing it finish (or checkpoint it) first",
                show(path),
                show(wal)
            ),
            Error::NotADatabase { path } => {
                write!(f, "{}: not an SQLite database", show(path))
            }
            Error::MissingTable { path, table } => write!(
                f,
                "{}: not a COLMAP database: no table {table:?}",
                show(path)
            ),
            Error::MissingColumn { path, table, column } => write!(
                f,
                "{}: not a COLMAP database: table {table:?} has no column {column:?}",
                show(path)
            ),
            Error::BadRow { path, table, id, what } => {
                write!(f, "{}: table {table}, id {id}: {what}", show(path))
            }
            Error::ImageNotInDatabase { path, image_id } => {
                write!(f, "{}: no image with id {image_id}", show(path))
            }
            #[cfg(feature = "colmap")]
            Error::Sqlite { path, .. } => write!(f, "{}: sqlite query failed", show(path)),
        }
    }
}

impl From<crate::output::OutputError> for Error {
    fn from(e: crate::output::OutputError) -> Self {
        Error::Output(e)
    }
}

impl std::error::Error for Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Error::Io { source, .. } => Some(source),
            // Transparent: its text is printed as this error's.
            Error::Output(e) => e.source(),
            #[cfg(feature = "colmap")]
            Error::Sqlite { source, .. } => Some(source),
            _ => None,
        }
    }
}
