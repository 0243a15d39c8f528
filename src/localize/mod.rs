//! Geometry and the hierarchical localizer.
//!
//! [`geometry`] holds the pieces the localizer is built from: COLMAP camera models, the P3P
//! minimal solver, LO-RANSAC for absolute pose and Levenberg–Marquardt pose refinement.

pub mod geometry;

pub use geometry::{
    estimate_absolute_pose, p3p, refine_pose, refine_pose_masked, Camera, CameraModel,
    GeometryError, Pose, PoseEstimate, RansacOptions, RefineOptions, Refinement, RobustLoss,
};

pub mod eval;
mod kernels;
pub mod localizer;
pub mod matching;
pub mod query;

pub use localizer::{
    describe_skipped, FeatureSet, Localization, LocalizeError, LocalizeOptions, Localizer,
    QueryFeatures, SkippedLevel, StageTimes,
};
