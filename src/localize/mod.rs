//! The hierarchical localizer, built on [`crate::geometry`] (cameras, P3P, LO-RANSAC,
//! pose refinement).

mod adc;
pub mod catalog;
mod coarse;
pub mod eval;
mod guided;
mod kernels;
mod level;
pub mod localizer;
mod matching;
mod prior;
mod retrieval;
mod scratch;

pub use localizer::{
    describe_skipped, FeatureModel, FeatureSet, Localization, LocalizationPath, LocalizeError,
    LocalizeOptions, Localizer, OptionError, QueryFailure, QueryFeatures, SkippedLevel,
    StageTimes, TrackingLost, MAX_TOP_K,
};
pub use matching::{default_ratio, is_sfp_descriptor, MatchOptions};
pub(crate) use prior::MotionModel;
pub use retrieval::{RetrievalFallback, RetrievalMethod};

/// The matching kernels, for the benches that measure them (feature `fuzzing`, which the
/// crate's tests and benches enable); not part of the API.
#[cfg(feature = "fuzzing")]
pub mod internals {
    pub use super::adc::match_pq_descriptors;
    pub use super::kernels::sgemm_abt;
    pub use super::matching::match_descriptors;
    pub use crate::vector::normalise_rows;
}
