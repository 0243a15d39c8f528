//! sfpmap: small, fast, level-sliceable visual-localization maps.
//!
//! The crate with `default-features = false` is only the map format ([`format`]): an mmap
//! zero-copy reader and a deterministic writer. Features add the rest of the pipeline, one
//! module per stage: [`colmap`] reads and writes COLMAP models and databases, [`extract`]
//! runs the SFP network, [`build`] turns a model into a map, [`geometry`] holds cameras and
//! the one pose type, [`localize`] localizes queries against a map, [`io`] reads and writes
//! the external formats (poses, features.h5, query inputs, exports, MCAP, plots), [`demo`]
//! is the built-in scene, `ffi` the C ABI. The guide's Architecture page
//! (`docs/src/architecture.md`) says what may use what.
#![deny(unsafe_code)]

pub use error::{Error, Result};

mod error;
pub mod format;
pub mod geometry;
pub mod input;
pub mod io;
#[cfg(feature = "colmap-model")]
pub(crate) mod kmeans;
pub mod output;
pub mod progress;
#[cfg(feature = "remote")]
pub mod remote;
#[cfg(any(feature = "colmap-model", feature = "localize", feature = "onnx"))]
mod vector;
#[cfg(any(feature = "colmap", feature = "localize"))]
pub mod vlad;

#[cfg(feature = "colmap-model")]
pub mod build;
#[cfg(feature = "colmap-model")]
pub mod colmap;

#[cfg(feature = "localize")]
pub mod localize;
#[cfg(feature = "localize")]
pub mod session;

#[cfg(feature = "capi")]
pub mod ffi;

#[cfg(feature = "onnx")]
pub mod extract;

#[cfg(all(feature = "onnx", feature = "colmap", feature = "localize"))]
pub mod demo;

/// The user guide's Rust examples (docs/src/library.md) as doctests: `cargo test --doc`
/// compiles and runs them, so the guide cannot drift from the API.
#[cfg(all(doctest, feature = "colmap", feature = "localize"))]
#[doc = include_str!("../docs/src/library.md")]
pub struct GuideLibrary;
