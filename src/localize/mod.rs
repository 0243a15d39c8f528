//! The hierarchical localizer, built on [`crate::geometry`] (cameras, P3P, LO-RANSAC,
//! pose refinement).

pub mod eval;
mod kernels;
pub mod localizer;
pub mod matching;

pub use localizer::{
    describe_skipped, FeatureSet, Localization, LocalizeError, LocalizeOptions, Localizer,
    QueryFailure, QueryFeatures, SkippedLevel, StageTimes,
};
