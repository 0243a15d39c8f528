//! sfpmap: small, fast, level-sliceable visual-localization maps.
//!
//! The crate with `default-features = false` is only the map format ([`format`]): an mmap
//! zero-copy reader and a deterministic writer. Features add the rest of the pipeline:
//! `colmap` (COLMAP models and databases), `localize` (geometry and the localizer), `cli`.
#![deny(unsafe_code)]

pub mod format;
pub mod geometry;
pub mod input;
pub mod io;
pub mod output;
pub mod progress;
#[cfg(any(feature = "colmap", feature = "localize", feature = "onnx"))]
mod vector;

#[cfg(feature = "colmap-model")]
pub mod build;
#[cfg(feature = "colmap-model")]
pub mod colmap;

#[cfg(feature = "localize")]
pub mod localize;

#[cfg(feature = "capi")]
pub mod ffi;

#[cfg(feature = "onnx")]
pub mod extract;

#[cfg(all(feature = "onnx", feature = "colmap", feature = "localize"))]
pub mod demo;
