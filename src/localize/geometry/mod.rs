//! Camera models, P3P, LO-RANSAC and pose refinement on nalgebra.
//!
//! Conventions follow COLMAP so that poses and intrinsics pass through unchanged:
//! - a [`Pose`] is `cam_from_world`: `p_cam = R · p_world + t`;
//! - the camera looks down +z, x right, y down;
//! - pixel coordinates put the centre of the top-left pixel at (0.5, 0.5) and the principal
//!   point is used as given (COLMAP's `cameras.txt`/`database.db` values, hloc query lists).
//!
//! Nothing here panics on bad input or returns a non-finite pose: every public entry point
//! validates its input once and reports a [`GeometryError`].

// `!(x > limit)` is deliberate throughout: it sends NaN down the rejecting branch, which
// `x <= limit` would not.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod camera;
mod error;
mod p3p;
mod pose;
mod ransac;
mod refine;
mod rng;

pub use camera::{Camera, CameraModel};
pub use error::GeometryError;
pub use p3p::p3p;
pub use pose::Pose;
pub use ransac::{
    estimate_absolute_pose, estimate_absolute_pose_with_prior, reprojection_inliers,
    required_iterations, PoseEstimate, RansacOptions, MIN_CORRESPONDENCES,
};
pub use refine::{refine_pose, refine_pose_masked, RefineOptions, Refinement, RobustLoss};
pub use rng::SplitMix64;
