//! Geometry every stage shares. Today: the one table of COLMAP camera models (ids, names,
//! parameter counts and names), read by the COLMAP readers and writers, the localizer's
//! cameras, the MCAP camera info and the demo. The projection and pose code (nalgebra) is
//! still in `localize::geometry` and moves here next (issue 13).

mod camera_model;

pub use camera_model::CameraModel;
