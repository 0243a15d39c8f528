//! The one error type of the geometry module.

use std::fmt;

use super::{CameraModel, SUPPORTED};

/// Everything that can go wrong in camera parsing, pose estimation and refinement.
///
/// Variants carry the values that caused them so callers (the localizer, the CLI) can report a
/// failed query precisely without parsing messages.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum GeometryError {
    /// A camera model name that is not one of COLMAP's.
    UnknownCameraModel {
        /// The name given.
        name: String,
    },
    /// A COLMAP camera model the localizer does not project (see [`SUPPORTED`]).
    UnsupportedCameraModel {
        /// The model.
        model: CameraModel,
    },
    /// The number of intrinsic parameters does not match the model.
    WrongParamCount {
        /// The model.
        model: CameraModel,
        /// Parameters it takes.
        expected: usize,
        /// Parameters given.
        found: usize,
    },
    /// A camera description string could not be parsed.
    ParseCamera {
        /// The string.
        input: String,
        /// What does not parse.
        reason: String,
    },
    /// Intrinsics that cannot describe a camera (zero size, non-positive focal, NaN).
    InvalidCamera {
        /// Which value, and why.
        reason: &'static str,
    },
    /// The pixel and point slices (or a mask) have different lengths.
    LengthMismatch {
        /// Which slice.
        what: &'static str,
        /// Its length should be this (the correspondences').
        expected: usize,
        /// Its length.
        found: usize,
    },
    /// Fewer correspondences than the estimator needs.
    TooFewCorrespondences {
        /// Correspondences given.
        found: usize,
        /// Correspondences needed.
        required: usize,
    },
    /// A NaN or infinite value in the input.
    NonFinite {
        /// Which input (`"pixels"`, `"points"`, `"initial pose"`).
        what: &'static str,
        /// Its index.
        index: usize,
    },
    /// The input cannot determine a pose (coincident or collinear points, coincident pixels).
    Degenerate {
        /// What is degenerate.
        reason: &'static str,
    },
    /// RANSAC ran its iterations without any minimal sample producing a pose.
    NoModel {
        /// Iterations run.
        iterations: usize,
    },
    /// The best pose is supported by fewer inliers than required.
    TooFewInliers {
        /// Its inliers.
        found: usize,
        /// Inliers required.
        required: usize,
        /// Iterations run.
        iterations: usize,
    },
    /// Options outside their valid range.
    InvalidOptions {
        /// The option.
        field: &'static str,
        /// Its valid range, or why the value is refused.
        reason: &'static str,
    },
    /// The pose refinement produced a non-finite pose or could not start.
    RefinementFailed {
        /// Why.
        reason: &'static str,
    },
}

fn supported_names() -> String {
    SUPPORTED.map(CameraModel::name).join(", ")
}

impl fmt::Display for GeometryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::UnknownCameraModel { name } => write!(
                f,
                "unknown camera model {name:?} (supported: {})",
                supported_names()
            ),
            Self::UnsupportedCameraModel { model } => write!(
                f,
                "camera model {model} is not supported for localization (supported: {})",
                supported_names()
            ),
            Self::WrongParamCount {
                model,
                expected,
                found,
            } => write!(
                f,
                "camera model {} takes {expected} parameters ({}), found {found}",
                model.name(),
                model.param_names()
            ),
            Self::ParseCamera { input, reason } => {
                write!(f, "cannot parse camera {input:?}: {reason}")
            }
            Self::InvalidCamera { reason } => write!(f, "invalid camera: {reason}"),
            Self::LengthMismatch {
                what,
                expected,
                found,
            } => write!(f, "{what}: expected {expected} entries, found {found}"),
            Self::TooFewCorrespondences { found, required } => write!(
                f,
                "too few correspondences: {found}, at least {required} required"
            ),
            Self::NonFinite { what, index } => {
                write!(f, "non-finite value in {what} at index {index}")
            }
            Self::Degenerate { reason } => write!(f, "degenerate input: {reason}"),
            Self::NoModel { iterations } => write!(
                f,
                "no pose hypothesis found in {iterations} ransac iterations"
            ),
            Self::TooFewInliers {
                found,
                required,
                iterations,
            } => write!(
                f,
                "best pose has {found} inliers, at least {required} required \
                 ({iterations} ransac iterations)"
            ),
            Self::InvalidOptions { field, reason } => {
                write!(f, "invalid option {field}: {reason}")
            }
            Self::RefinementFailed { reason } => write!(f, "pose refinement failed: {reason}"),
        }
    }
}

impl std::error::Error for GeometryError {}
