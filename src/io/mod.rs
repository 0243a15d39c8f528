//! Getting maps out to other tools: a COLMAP text model.

pub mod colmap_export;
#[cfg(feature = "onnx")]
pub mod features_h5;
