//! COLMAP models (binary and text) and `database.db`.
//!
//! - [`read_model`] reads a model folder (`sparse/0`), `.bin` or `.txt`, into a validated
//!   [`Reconstruction`]; [`bin`] and [`text`] parse the same files from bytes and write them.
//! - [`Database`] reads cameras, images, keypoints and descriptors from a COLMAP
//!   `database.db`, opened read-only and immutable so the user's file is never touched.
//!
//! Conventions are COLMAP's: `cam_from_world` poses, scalar-first quaternions, `point3D` ids
//! are `u64` with `u64::MAX` (text: `-1`) meaning none, the top-left pixel's centre is at
//! (0.5, 0.5). The library never prints.
//!
//! ```no_run
//! use std::path::Path;
//! use sfpmap::colmap::{read_model, Database};
//!
//! let model = read_model(Path::new("sparse/0"))?;
//! let db = Database::open(Path::new("database.db"))?;
//! // One image's features in memory at a time.
//! for features in db.iter_features()? {
//!     let features = features?;
//!     let Some(image) = model.image(features.image.id) else { continue };
//!     let (Some(keypoints), Some(descriptors)) = (features.keypoints, features.descriptors)
//!     else {
//!         continue;
//!     };
//!     for (idx, point2d) in image.points2d.iter().enumerate() {
//!         let Some(point) = point2d.point3d_id.and_then(|id| model.point3d(id)) else {
//!             continue;
//!         };
//!         let mut descriptor = Vec::new();
//!         let scale = keypoints.scale(idx);
//!         if descriptors.row_into(idx, &mut descriptor) {
//!             let _ = (point.xyz, scale, &descriptor);
//!         }
//!     }
//! }
//! # Ok::<(), sfpmap::colmap::Error>(())
//! ```

pub mod bin;
#[cfg(feature = "colmap")]
mod database;
#[cfg(feature = "colmap")]
mod database_writer;
mod error;
mod model;
pub mod text;

use std::path::{Path, PathBuf};

#[cfg(feature = "colmap")]
pub use database::{
    Database, DbImage, DescriptorValues, Descriptors, ImageFeatures, ImageFeaturesIter, Keypoint,
    KeypointLayout, Keypoints,
};
#[cfg(feature = "colmap")]
pub use database_writer::DatabaseWriter;
#[cfg(feature = "colmap")]
pub(crate) use error::shown_name;
pub use error::{Error, Result};
// The binary models' fast path in `build` (maps, and its fuzz body).
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
pub(crate) use model::IdIndex;
pub use model::{
    Camera, Image, Point2D, Point3D, Reconstruction, ReconstructionBuilder, TrackElement,
};

/// The file names of a model, in reading order.
const STEMS: [&str; 3] = ["cameras", "images", "points3D"];

/// Which encoding a model folder holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum ModelFormat {
    /// `cameras.bin`, `images.bin`, `points3D.bin`.
    Binary,
    /// `cameras.txt`, `images.txt`, `points3D.txt`.
    Text,
    /// Both sets; [`read_model`] reads both, checks they agree and returns the binary one.
    Both,
}

/// The model files found in a folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelFiles {
    /// Which encoding the folder holds.
    pub format: ModelFormat,
    /// Every model file that [`read_model`] reads (3 or 6), for provenance (sizes, hashes).
    /// `rigs.bin` / `frames.bin` are not listed: they are not read.
    pub paths: Vec<PathBuf>,
}

pub(crate) fn files_with(dir: &Path, ext: &str) -> [PathBuf; 3] {
    STEMS.map(|stem| dir.join(format!("{stem}.{ext}")))
}

/// Finds the model files in `dir`: errors if there are none, if a set is incomplete, or if
/// a model file is not a regular file (a folder or FIFO by that name is not "missing").
pub fn model_files(dir: &Path) -> Result<ModelFiles> {
    let mut found = Vec::new();
    for ext in ["bin", "txt"] {
        let paths = files_with(dir, ext);
        let mut present = [false; 3];
        for (present, path) in present.iter_mut().zip(&paths) {
            *present = is_present(path)?;
        }
        if present.iter().all(|p| !p) {
            continue;
        }
        if let Some((missing, _)) = paths.iter().zip(present).find(|(_, p)| !p) {
            return Err(Error::MissingFile {
                path: missing.clone(),
            });
        }
        found.push((ext, paths));
    }
    let format = match found.as_slice() {
        [] => {
            // A missing folder deserves the I/O error, not "no model".
            if let Err(source) = std::fs::read_dir(dir) {
                return Err(Error::Io {
                    path: dir.to_path_buf(),
                    source,
                });
            }
            return Err(Error::NoModel {
                dir: dir.to_path_buf(),
            });
        }
        [(ext, _)] if *ext == "bin" => ModelFormat::Binary,
        [_] => ModelFormat::Text,
        _ => ModelFormat::Both,
    };
    let paths = found.into_iter().flat_map(|(_, p)| p).collect();
    Ok(ModelFiles { format, paths })
}

/// Whether `path` exists (symlinks followed); an error if it exists but is not a regular file.
fn is_present(path: &Path) -> Result<bool> {
    match crate::input::check_regular_path(path) {
        Ok(_) => Ok(true),
        Err(crate::input::OpenError::Io(_)) => Ok(false),
        Err(e) => Err(input_error(path, e)),
    }
}

/// `input`'s answer as this module's error, naming `path`.
fn input_error(path: &Path, e: crate::input::OpenError) -> Error {
    match e {
        crate::input::OpenError::Io(source) => Error::Io {
            path: path.to_path_buf(),
            source,
        },
        crate::input::OpenError::NotRegular(kind) => Error::NotAFile {
            path: path.to_path_buf(),
            kind,
        },
    }
}

/// Opens `path` for reading if it is a regular file, without blocking on a FIFO
/// ([`crate::input::open_regular`]).
pub(crate) fn open_regular(path: &Path) -> Result<std::fs::File> {
    crate::input::open_regular(path).map_err(|e| input_error(path, e))
}

/// Checks that `path` is a regular file without opening it (for SQLite, which opens the
/// database itself).
#[cfg(feature = "colmap")]
pub(crate) fn check_regular_path(path: &Path) -> Result<()> {
    crate::input::check_regular_path(path)
        .map(drop)
        .map_err(|e| input_error(path, e))
}

/// The file's bytes, memory-mapped: no copy of a model that may be hundreds of MB, and a
/// second look (hashing for provenance) costs no second read.
pub(crate) fn read_file(path: &Path) -> Result<impl std::ops::Deref<Target = [u8]>> {
    let file = open_regular(path)?;
    crate::format::map_file(&file).map_err(|source| Error::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Reads the binary model in `dir` (`cameras.bin`, `images.bin`, `points3D.bin`).
pub fn read_model_bin(dir: &Path) -> Result<Reconstruction> {
    read_with(dir, true)
}

/// Reads the text model in `dir` (`cameras.txt`, `images.txt`, `points3D.txt`).
pub fn read_model_text(dir: &Path) -> Result<Reconstruction> {
    read_with(dir, false)
}

fn read_with(dir: &Path, binary: bool) -> Result<Reconstruction> {
    let [c, i, p] = files_with(dir, if binary { "bin" } else { "txt" });
    let (cameras, images, points3d) = (read_file(&c)?, read_file(&i)?, read_file(&p)?);
    let parsers = if binary { &BIN } else { &TEXT };
    parse_with(parsers, (&cameras, &c), (&images, &i), (&points3d, &p))
}

/// The parsers of one encoding of the three model files.
struct Parsers {
    cameras: fn(&[u8], &Path) -> Result<Vec<Camera>>,
    images: fn(&[u8], &Path) -> Result<Vec<Image>>,
    points3d: fn(&[u8], &Path, &mut ReconstructionBuilder) -> Result<()>,
}

const BIN: Parsers = Parsers {
    cameras: bin::parse_cameras,
    images: bin::parse_images,
    points3d: bin::parse_points3d_into,
};

const TEXT: Parsers = Parsers {
    cameras: text::parse_cameras,
    images: text::parse_images,
    points3d: text::parse_points3d_into,
};

/// Parses and validates a model from its three files' bytes (each with the path errors
/// name). Errors come in file order: cameras, then images, then points3D.
fn parse_with(
    parsers: &Parsers,
    cameras: (&[u8], &Path),
    images: (&[u8], &Path),
    points3d: (&[u8], &Path),
) -> Result<Reconstruction> {
    let mut builder = ReconstructionBuilder::new().paths(cameras.1, images.1, points3d.1);
    for camera in (parsers.cameras)(cameras.0, cameras.1)? {
        builder.add_camera(camera);
    }
    let parse_points = || -> Result<ReconstructionBuilder> {
        let mut points = ReconstructionBuilder::new().paths(cameras.1, images.1, points3d.1);
        (parsers.points3d)(points3d.0, points3d.1, &mut points)?;
        Ok(points)
    };
    // images and points3D are independent until validation: big files are parsed on two
    // threads (for small ones, as in fuzzing, a thread costs more than it saves).
    let (images, points) = if images.0.len() + points3d.0.len() > 1 << 20 {
        std::thread::scope(|s| {
            let images = s.spawn(|| (parsers.images)(images.0, images.1));
            let points = parse_points();
            let images = images
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic));
            (images, points)
        })
    } else {
        ((parsers.images)(images.0, images.1), parse_points())
    };
    images?.into_iter().for_each(|x| builder.add_image(x));
    builder.take_points3d(points?);
    builder.build()
}

/// Reads the model in `dir`, binary or text, whichever is there.
///
/// If both are there, both are read and must agree (camera, image and point ids, and the
/// number of observations); the binary one is returned, having full precision.
pub fn read_model(dir: &Path) -> Result<Reconstruction> {
    match model_files(dir)?.format {
        ModelFormat::Binary => read_model_bin(dir),
        ModelFormat::Text => read_model_text(dir),
        _ => {
            let from_bin = read_model_bin(dir)?;
            let from_txt = read_model_text(dir)?;
            compare(&from_bin, &from_txt).map_err(|what| Error::ModelsDisagree {
                bin: dir.join("*.bin"),
                txt: dir.join("*.txt"),
                what,
            })?;
            Ok(from_bin)
        }
    }
}

/// Whether two models have the same ids and structure; the message says the first difference.
fn compare(a: &Reconstruction, b: &Reconstruction) -> Result<(), String> {
    fn ids<T, K: PartialEq + std::fmt::Display>(
        kind: &str,
        a: &[T],
        b: &[T],
        key: impl Fn(&T) -> K,
    ) -> Result<(), String> {
        if a.len() != b.len() {
            return Err(format!("{} vs. {} {kind}s", a.len(), b.len()));
        }
        match a.iter().zip(b).find(|(x, y)| key(x) != key(y)) {
            Some((x, y)) => Err(format!("{kind} ids differ ({} vs. {})", key(x), key(y))),
            None => Ok(()),
        }
    }
    ids("camera", a.cameras(), b.cameras(), |c| c.id)?;
    ids("image", a.images(), b.images(), |i| i.id)?;
    ids("point3D", a.points3d(), b.points3d(), |p| p.id)?;
    for (x, y) in a.images().iter().zip(b.images()) {
        if x.name != y.name || x.points2d.len() != y.points2d.len() {
            return Err(format!(
                "image {} differs (name or number of points2D)",
                x.id
            ));
        }
    }
    if a.num_observations() != b.num_observations() {
        return Err(format!(
            "{} vs. {} observations",
            a.num_observations(),
            b.num_observations()
        ));
    }
    Ok(())
}

/// Three consecutive parts of `data[4..]`, their lengths from `data[0..4]`.
#[cfg(any(test, feature = "fuzzing"))]
pub(crate) fn split3(data: &[u8]) -> [&[u8]; 3] {
    let (head, rest) = data.split_at(data.len().min(4));
    let mut lens = [0usize; 2];
    for (len, pair) in lens.iter_mut().zip(head.chunks(2)) {
        let n = pair.iter().fold(0usize, |n, &b| n << 8 | usize::from(b));
        *len = n % (rest.len() + 1);
    }
    let (c, rest) = rest.split_at(lens[0].min(rest.len()));
    let (i, p) = rest.split_at(lens[1].min(rest.len()));
    [c, i, p]
}
