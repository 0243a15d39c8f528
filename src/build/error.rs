//! The one error of map building.

use crate::colmap::Error as ColmapError;
use crate::format;
use std::fmt;
use std::path::PathBuf;

/// What can stop a conversion (`convert` from a database or from images).
#[derive(Debug)]
#[non_exhaustive]
pub enum ConvertError {
    /// Reading the COLMAP model or database.
    Colmap(ColmapError),
    /// Writing the map (or reading the one a conversion starts from).
    Format(format::Error),
    /// The database's image `image_id` has another name than the model's.
    NameMismatch {
        /// The database.
        features: PathBuf,
        /// The image's id in both.
        image_id: u32,
        /// Its name in the model.
        model: String,
        /// Its name in the database.
        found: String,
    },
    /// An observation's keypoint does not exist in the features (database, features file,
    /// kapture folder).
    KeypointOutOfRange {
        /// The features' file or folder.
        features: PathBuf,
        /// The image's name.
        image: String,
        /// The observation's 2D point index.
        point2d_idx: usize,
        /// How many keypoints the database holds for the image.
        keypoints: usize,
    },
    /// An observed keypoint's scale is NaN or infinite.
    KeypointScaleNotFinite {
        /// The features' file or folder.
        features: PathBuf,
        /// The image's name.
        image: String,
        /// The observation's 2D point index.
        point2d_idx: usize,
    },
    /// An image has no features in the database or features file and `strict` is set.
    MissingFeatures {
        /// The features' file or folder.
        features: PathBuf,
        /// The image's name.
        image: String,
    },
    /// Descriptor lengths (or kinds) differ between images.
    DescriptorDim {
        /// The features' file or folder.
        features: PathBuf,
        /// The image whose descriptors differ.
        image: String,
        /// The dimension of the images before it.
        expected: usize,
        /// Its dimension.
        found: usize,
    },
    /// A features file (hloc `features.h5`, kapture) is malformed: its file, and the image
    /// and dataset in the message.
    Input(crate::io::InputError),
    /// An observed keypoint lies outside its image.
    KeypointOutsideImage {
        /// The features' file or folder.
        features: PathBuf,
        /// The image's name.
        image: String,
        /// The keypoint's index.
        keypoint: usize,
        /// Its position (COLMAP's convention: the image spans `[0, width] × [0, height]`).
        xy: [f32; 2],
        /// The image's size.
        size: [u64; 2],
    },
    /// Options that contradict each other (a database and a features file, …).
    Options(String),
    /// A kapture folder (`convert --kapture`): its file and line in the message.
    Kapture(crate::io::kapture::KaptureError),
    /// Reading an input file or the images folder failed.
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// `convert --images`: the network failed on an image.
    #[cfg(feature = "onnx")]
    Extract(crate::extract::ExtractError),
    /// The output is one of the model's images (through `..` in its name, a link, ...).
    Output(crate::output::OutputError),
    /// The memory budget (`--memory`) is smaller than converting the model needs, even
    /// reading its features [`MAX_PASSES`](super::stream::MAX_PASSES) times: `needed` is the
    /// least that works.
    MemoryBudget {
        /// The model (its folder, or what stands for a model in memory).
        model: PathBuf,
        /// The budget asked for, in bytes.
        budget: u64,
        /// The smallest budget that works, in bytes.
        needed: u64,
        /// Reads of the features at that budget.
        passes: usize,
    },
    /// `convert --images`: model images with no file under the images folder.
    MissingImages {
        /// The images folder.
        images: PathBuf,
        /// Every model image without a file, by name.
        missing: Vec<String>,
        /// How many model images there are.
        total: usize,
    },
}

impl fmt::Display for ConvertError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ConvertError::Colmap(e) => e.fmt(f),
            ConvertError::Format(e) => e.fmt(f),
            ConvertError::NameMismatch { features, image_id, model, found } => write!(
                f,
                "{}: image {image_id} is {found:?} in the database but {model:?} in the model (a database of another reconstruction?)",
                crate::escape::path(features)
            ),
            ConvertError::KeypointOutOfRange { features, image, point2d_idx, keypoints } => write!(
                f,
                "{}: image {image:?} has {keypoints} keypoints but the model observes point2D {point2d_idx}",
                crate::escape::path(features)
            ),
            ConvertError::KeypointScaleNotFinite { features, image, point2d_idx } => write!(
                f,
                "{}: image {}: keypoint {point2d_idx}: scale is not finite",
                crate::escape::path(features),
                crate::colmap::shown_name(image)
            ),
            ConvertError::MissingFeatures { features, image } => write!(
                f,
                "{}: image {image:?} has no keypoints or descriptors (it would be skipped, not strict)",
                crate::escape::path(features)
            ),
            ConvertError::DescriptorDim { features, image, expected, found } => write!(
                f,
                "{}: image {image:?} has {found}-dimensional descriptors, others have {expected}",
                crate::escape::path(features)
            ),
            ConvertError::Input(e) => e.fmt(f),
            // Options' messages name paths and names a user gave.
            ConvertError::Options(message) => {
                f.write_str(&crate::escape::escape_control_characters(message))
            }
            ConvertError::KeypointOutsideImage { features, image, keypoint, xy, size } => write!(
                f,
                "{}: image {}: keypoint {keypoint} at ({}, {}) lies outside the {} x {} image",
                crate::escape::path(features),
                crate::colmap::shown_name(image),
                xy[0],
                xy[1],
                size[0],
                size[1]
            ),
            ConvertError::Io { path, source } => write!(f, "{}: {source}", crate::escape::path(path)),
            ConvertError::Kapture(e) => e.fmt(f),
            #[cfg(feature = "onnx")]
            ConvertError::Extract(e) => e.fmt(f),
            ConvertError::Output(e) => e.fmt(f),
            ConvertError::MemoryBudget { model, budget, needed, passes } => write!(
                f,
                "{}: a memory budget of {} MB is too small to convert it: it needs at least {} MB ({} read{} of its features)",
                crate::escape::path(model),
                budget / 1_000_000,
                needed.div_ceil(1_000_000),
                passes,
                if *passes == 1 { "" } else { "s" }
            ),
            ConvertError::MissingImages {
                images,
                missing,
                total,
            } => {
                let shown: Vec<&str> = missing.iter().take(5).map(String::as_str).collect();
                write!(
                    f,
                    "{}: {} of {total} model images missing ({}{}); pass --allow-missing to skip them",
                    crate::escape::path(images),
                    missing.len(),
                    crate::escape::escape_control_characters(&shown.join(", ")),
                    if missing.len() > 5 { ", …" } else { "" }
                )
            }
        }
    }
}

impl std::error::Error for ConvertError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            ConvertError::Colmap(e) => e.source(),
            ConvertError::Format(e) => e.source(),
            ConvertError::Kapture(e) => e.source(),
            #[cfg(feature = "onnx")]
            ConvertError::Extract(e) => e.source(),
            ConvertError::Output(e) => e.source(),
            _ => None,
        }
    }
}

impl From<ColmapError> for ConvertError {
    fn from(e: ColmapError) -> Self {
        ConvertError::Colmap(e)
    }
}

impl From<crate::io::InputError> for ConvertError {
    fn from(e: crate::io::InputError) -> Self {
        ConvertError::Input(e)
    }
}

impl From<format::Error> for ConvertError {
    fn from(e: format::Error) -> Self {
        ConvertError::Format(e)
    }
}

#[cfg(feature = "onnx")]
impl From<crate::extract::ExtractError> for ConvertError {
    fn from(e: crate::extract::ExtractError) -> Self {
        ConvertError::Extract(e)
    }
}
