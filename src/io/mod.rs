//! Getting maps out to other tools: a COLMAP text model, a PLY point cloud, TUM / images.txt
//! poses, and a top-down PNG plot (feature `plot`).

pub mod colmap_export;
#[cfg(all(feature = "onnx", feature = "colmap", feature = "localize"))]
pub mod demo_scene;
#[cfg(feature = "onnx")]
pub mod features_h5;
#[cfg(feature = "mcap")]
pub mod mcap_io;
#[cfg(feature = "plot")]
pub mod plot;
pub mod ply;
pub mod poses;
