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
//!
//! ```
//! use nalgebra::{UnitQuaternion, Vector2, Vector3};
//! use sfpmap::localize::geometry::{estimate_absolute_pose, Camera, Pose, RansacOptions};
//!
//! let camera = Camera::parse("SIMPLE_RADIAL 1024 768 800 512 384 -0.05")?;
//! let truth = Pose::new(
//!     UnitQuaternion::from_scaled_axis(Vector3::new(0.1, -0.4, 0.05)),
//!     Vector3::new(0.3, -0.2, 1.0),
//! );
//! // Points on a grid in front of the camera, seen through the model.
//! let (mut pixels, mut points) = (Vec::new(), Vec::new());
//! for i in 0..50 {
//!     let pixel = Vector2::new(20.0 + 19.7 * f64::from(i % 50), 30.0 + 14.1 * f64::from(i % 7 * 7));
//!     let xy = camera.unproject(&pixel);
//!     let depth = 4.0 + f64::from(i % 5);
//!     points.push(truth.inverse().transform(&(Vector3::new(xy.x, xy.y, 1.0) * depth)));
//!     pixels.push(pixel);
//! }
//! let estimate = estimate_absolute_pose(&pixels, &points, &camera, &RansacOptions::default())?;
//! assert!(estimate.pose.rotation_error_deg(&truth) < 1e-3);
//! assert!(estimate.pose.center_distance(&truth) < 1e-3);
//! assert_eq!(estimate.num_inliers, 50);
//! # Ok::<(), sfpmap::localize::geometry::GeometryError>(())
//! ```

// `!(x > limit)` is deliberate throughout: it sends NaN down the rejecting branch, which
// `x <= limit` would not.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod camera;
mod error;
mod p3p;
mod pose;
mod prosac;
mod ransac;
mod refine;
mod rng;

pub use camera::{Camera, CameraModel, SUPPORTED};
pub use error::GeometryError;
pub use p3p::p3p;
pub use pose::Pose;
pub use ransac::{
    estimate_absolute_pose, estimate_absolute_pose_with_prior, reprojection_inliers,
    required_iterations, PoseEstimate, RansacOptions, MIN_CORRESPONDENCES,
};
pub use refine::{refine_pose, refine_pose_masked, RefineOptions, Refinement, RobustLoss};
pub use rng::SplitMix64;
