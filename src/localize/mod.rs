//! The hierarchical localizer, built on [`crate::geometry`] (cameras, P3P, LO-RANSAC,
//! pose refinement).

mod adc;
pub(crate) mod catalog;
mod coarse;
pub mod eval;
mod features;
mod guided;
mod kernels;
mod level;
mod localizer;
mod matching;
mod prior;
mod retrieval;
mod scratch;

pub use features::{
    check_global_finite, FeatureModel, FeatureSet, NonFinite, NonFiniteValue, QueryFeatures,
};
pub use localizer::{
    describe_skipped, InlierLink, Localization, LocalizationPath, LocalizeError, LocalizeOptions,
    Localizer, OptionError, QueryFailure, SkippedLevel, StageTimes, TrackingLost,
};
pub use matching::MatchOptions;
pub(crate) use matching::{default_ratio, is_sfp_descriptor};
pub(crate) use prior::MotionModel;
pub use retrieval::{RetrievalFallback, RetrievalMethod};

/// The matching kernels, for the benches that time them (public at `crate::fuzzing`).
#[cfg(feature = "fuzzing")]
pub(crate) mod internals {
    pub use super::adc::match_pq_descriptors;
    pub use super::kernels::sgemm_abt;
    pub use super::matching::match_descriptors;
}
