//! Geometry every stage shares.
//!
//! Always: the one table of COLMAP camera models ([`CameraModel`]: ids, names, parameter counts
//! and names), read by the COLMAP readers and writers, the localizer's cameras, MCAP camera info
//! and the demo. With the `geometry` feature (nalgebra): cameras that project, P3P, LO-RANSAC and
//! pose refinement, which the localizer (`localize`) builds on.
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
//! use sfpmap::geometry::{estimate_absolute_pose, Camera, Pose, RansacOptions};
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
//! # Ok::<(), sfpmap::geometry::GeometryError>(())
//! ```

// `!(x > limit)` is deliberate throughout: it sends NaN down the rejecting branch, which
// `x <= limit` would not.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

mod camera_model;
pub use camera_model::CameraModel;

#[cfg(feature = "geometry")]
mod camera;
#[cfg(feature = "geometry")]
mod covariance;
#[cfg(feature = "geometry")]
mod error;
#[cfg(feature = "geometry")]
mod p3p;
#[cfg(feature = "geometry")]
mod pose;
#[cfg(feature = "geometry")]
mod prosac;
#[cfg(feature = "geometry")]
mod ransac;
#[cfg(feature = "geometry")]
mod refine;
#[cfg(feature = "geometry")]
pub(crate) mod rng;

#[cfg(feature = "geometry")]
pub use camera::{Camera, SUPPORTED};
#[cfg(feature = "geometry")]
pub use covariance::{pose_covariance, PoseCovariance};
#[cfg(feature = "geometry")]
pub use error::GeometryError;
#[cfg(feature = "geometry")]
pub use p3p::p3p;
#[cfg(feature = "geometry")]
pub use pose::Pose;
#[cfg(feature = "geometry")]
pub use ransac::{
    estimate_absolute_pose, estimate_absolute_pose_with_prior, reprojection_inliers,
    required_iterations, PoseEstimate, RansacOptions,
};

#[cfg(feature = "geometry")]
pub use refine::{refine_pose, refine_pose_masked, RefineOptions, Refinement, RobustLoss};
// The seeded generator of RANSAC's samples, k-means' too; the tests and benches draw from it
// (`crate::fuzzing`).
#[cfg(all(feature = "geometry", any(feature = "colmap-model", test)))]
pub(crate) use rng::SplitMix64;
