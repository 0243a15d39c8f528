//! Getting maps out to other tools: a COLMAP text model, a PLY point cloud, TUM / images.txt
//! poses, and a top-down PNG plot (feature `plot`).

#[cfg(feature = "colmap-model")]
pub mod colmap_export;
#[cfg(feature = "onnx")]
pub mod features_h5;
#[cfg(feature = "mcap")]
pub mod mcap_io;
#[cfg(feature = "plot")]
pub mod plot;
pub mod ply;
#[cfg(feature = "colmap-model")]
pub mod poses;
#[cfg(feature = "localize")]
pub mod queries;

use std::path::PathBuf;

/// A problem with an input file (query list, features file, poses file), naming the file and,
/// when known, the line.
#[derive(Debug)]
#[non_exhaustive]
pub struct InputError {
    pub path: PathBuf,
    pub line: Option<usize>,
    pub message: String,
}

impl std::fmt::Display for InputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.line {
            Some(line) => write!(f, "{}:{line}: {}", self.path.display(), self.message),
            None => write!(f, "{}: {}", self.path.display(), self.message),
        }
    }
}

impl std::error::Error for InputError {}
