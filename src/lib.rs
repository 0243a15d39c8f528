//! Small, fast, level-sliceable visual-localization maps (SFP: Sparse Feature Pyramid).
//!
//! A map (`.sfpm`, specified in `spec/format.md`) holds a scene's 3D points, its database
//! images with their poses and which points each sees, and the points' descriptors in levels
//! of a feature pyramid, each split into a `short` prefix and the `rest`. One mmap opens it
//! zero-copy; a slice keeps the levels and blocks a device needs. This crate builds maps from
//! COLMAP models, extracts SFP features with ONNX Runtime, and localizes query images
//! (`cam_from_world` poses) against a map. The `sfpmap` command-line tool (package
//! `sfpmap-cli`), the Python package and the C ABI are clients of this API.
//!
//! # Quick start
//!
//! Open a map and localize a query whose features you have (here: the projections of the
//! map's own points, made by the hidden lines, which also write the small map):
//!
//! ```
//! # #[cfg(feature = "localize")]
//! # fn main() -> sfpmap::Result<()> {
//! use sfpmap::format::Map;
//! use sfpmap::geometry::Camera;
//! use sfpmap::localize::{FeatureSet, QueryFeatures};
//! use sfpmap::progress::Silent;
//! use sfpmap::session::Session;
//! use std::sync::Arc;
//! # use sfpmap::format::{CameraInfo, Descriptors, LevelInfo, MapWriter};
//! # // 600 points 10 to 16 m ahead of two database images, one level of 32-dim descriptors.
//! # let (n, dim) = (600usize, 32usize);
//! # let points: Vec<[f64; 3]> = (0..n)
//! #     .map(|i| [(i % 30) as f64 * 0.6 - 9.0, (i / 30) as f64 * 0.6 - 6.0, 10.0 + (i * 7 % 13) as f64 * 0.5])
//! #     .collect();
//! # let mut state = 7u64;
//! # let mut next = move || {
//! #     state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
//! #     (state >> 11) as f32 / (1u64 << 53) as f32 - 0.5
//! # };
//! # let mut descriptors = vec![0f32; n * dim];
//! # for row in descriptors.chunks_mut(dim) {
//! #     row.iter_mut().for_each(|v| *v = next());
//! #     let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt();
//! #     row.iter_mut().for_each(|v| *v /= norm);
//! # }
//! # let mut writer = MapWriter::default();
//! # writer.add_camera(CameraInfo {
//! #     id: Some(1),
//! #     model: "PINHOLE".into(),
//! #     width: 640,
//! #     height: 480,
//! #     params: vec![500.0, 500.0, 320.0, 240.0],
//! # });
//! # writer.set_points_world(&points);
//! # let poses = [[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]];
//! # writer.set_images(&["db0.jpg", "db1.jpg"], &[0, 0], &poses, None)?;
//! # let ids: Vec<u32> = (0..n as u32).collect();
//! # let level = LevelInfo {
//! #     level: 0,
//! #     stride: 4.0,
//! #     descriptor: "example".into(),
//! #     dim_full: dim as u32,
//! #     dim_short: 16,
//! #     normalization: "l2".into(),
//! #     extra: Default::default(),
//! # };
//! # writer.add_level(level, &ids, Some(Descriptors::F32(&descriptors)), true)?;
//! # let seen: Vec<u32> = ids.iter().chain(&ids).copied().collect();
//! # let offsets = [0, n as u64, 2 * n as u64];
//! # writer.set_visibility(&offsets, &seen, None)?;
//! # let path = std::env::temp_dir().join(format!("sfpmap-quick-start-{}.sfpm", std::process::id()));
//! # writer.write(&path, &Silent)?;
//! // One mmap; the index is checked here, each section where it is first read.
//! let map = Arc::new(Map::open(&path)?);
//! assert_eq!((map.n_points(), map.n_images()), (600, 2));
//!
//! // A session owns what a query needs: the map (shared), its localizer and where query
//! // features come from. Built with `.source(QuerySource::Images(..))` it extracts them
//! // from image files with the map's own model; here they are handed in.
//! let session = Session::builder(map, "example.sfpm").build(&Silent)?;
//! let camera = Camera::parse("PINHOLE 640 480 500 500 320 240")?;
//! # let (tx, ty, tz) = (0.4, -0.2, 1.5);
//! # let mut set = FeatureSet { level: None, keypoints: Vec::new(), descriptors: Vec::new(), dim };
//! # for (p, [x, y, z]) in points.iter().enumerate() {
//! #     if let Some(px) = camera.project(&nalgebra::Vector3::new(x + tx, y + ty, z + tz)) {
//! #         set.keypoints.push([px.x, px.y]);
//! #         set.descriptors.extend_from_slice(&descriptors[p * dim..(p + 1) * dim]);
//! #     }
//! # }
//! let features = QueryFeatures { sets: vec![set], ..Default::default() };
//! let result = session.localize_features(&features, &camera, "query.jpg")?;
//! match result.pose() {
//!     // `cam_from_world`, as COLMAP's images.txt writes it: qw qx qy qz tx ty tz.
//!     Some(pose) => println!("query.jpg {:?}", pose.to_colmap()),
//!     None => println!("query.jpg not localized: {:?}", result.failure()),
//! }
//! # let pose = result.pose().expect("the quick start localizes its query").to_colmap();
//! # assert!((pose[4] - tx).abs() < 1e-3 && (pose[6] - tz).abs() < 1e-3, "{pose:?}");
//! # std::fs::remove_file(&path).ok();
//! # Ok(())
//! # }
//! # #[cfg(not(feature = "localize"))]
//! # fn main() {}
//! ```
//!
//! A map is built from a COLMAP model with [`build::convert`] (SIFT, from the model's
//! `database.db`) or [`build::convert_with_images`] (SFP, from its images), and sliced with
//! [`format::slice`]. The guide (`docs/`, "Using the Rust library") walks through each.
//!
//! # Modules
//!
//! | module | what it holds | feature |
//! |---|---|---|
//! | [`format`](mod@format) | the `.sfpm` reader ([`format::Map`], zero copy, or by range from a [`format::RangeSource`]), writer ([`format::MapWriter`]) and [`format::slice`] | always |
//! | [`geometry`] | the COLMAP camera-model table; cameras that project, the one pose type [`geometry::Pose`], P3P, LO-RANSAC, pose refinement | `geometry` for all but the table |
//! | [`colmap`] | COLMAP binary and text models; `database.db` | `colmap-model`; the database `colmap` |
//! | [`build`] | a model into a map: SIFT and SFP maps, product quantisation, byte budgets, catalogs | `colmap`, `onnx` for SFP maps |
//! | [`extract`] | the SFP extractor on ONNX Runtime (loaded at run time) | `onnx` |
//! | [`localize`] | the hierarchical localizer over a borrowed map | `localize` |
//! | [`session`] | a query end to end: a shared map, its localizer, the query source, sequence tracking | `localize` |
//! | [`io`] | external formats beside each other: poses, query lists, features.h5, COLMAP text export, PLY, plots, MCAP | per format |
//! | [`vlad`] | the VLAD codebook of a map's retrieval data | `colmap` or `localize` |
//! | [`remote`] | maps read by range from `http(s)://` and `s3://` URLs, with an on-disk cache | `remote` |
//! | [`input`], [`output`], [`progress`] | the input policy's error, the output policy and atomic writer, the [`progress::Reporter`] the library reports through (it never prints) | always |
//! | [`ffi`] | the C ABI (`include/sfpmap.h`) | `capi` |
//! | [`demo`] | the built-in scenes of `sfpmap demo` and the scale tests; not part of the map API | `demo` |
//! | [`fuzzing`] | hooks for the fuzz crate and the tests; not API | `fuzzing` |
//!
//! Every item is at one path. The public API is listed in `docs/public-api.txt`, which CI
//! keeps equal to what rustdoc documents (`.ci/public_api.py`).
//!
//! # Feature flags
//!
//! With `default-features = false` the crate is only the map format (memmap2, half, zstd,
//! XXH3): a reader to embed. The default features are what the CLI builds, but `demo`.
//!
//! | feature | adds | default |
//! |---|---|---|
//! | `colmap-model` | COLMAP model readers and writers (and `geometry`) | |
//! | `colmap` | `database.db` (SQLite, bundled) and map building | yes |
//! | `geometry` | cameras, pose estimation and refinement (nalgebra) | |
//! | `localize` | the localizer and sessions (and `geometry`) | yes |
//! | `onnx` | the SFP extractor, image decoding, features.h5 | yes |
//! | `mcap` | MCAP logs: images in, poses out | yes |
//! | `plot` | PNG plots of a map and poses | yes |
//! | `remote` | maps by URL (object_store, tokio on one thread) | yes |
//! | `capi` | the C ABI (`libsfpmap.so`) | |
//! | `demo` | the built-in scenes | |
//! | `fuzzing` | the fuzz bodies, the raw format structs, internal kernels: for `fuzz/`, the tests and benches | |
//!
//! # Errors
//!
//! Each module has one error type with the details a caller may inspect
//! ([`format::Error`], [`colmap::Error`], ...); every one converts into [`Error`], so `?`
//! into [`Result`] works across modules. A query that is not localized is not an error but a
//! [`localize::QueryFailure`] in the [`localize::Localization`].
#![deny(unsafe_code)]
#![warn(missing_docs)]

pub use error::{Error, ErrorKind, Result};

mod error;
pub mod escape;
pub mod format;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
pub mod geometry;
pub mod input;
pub mod io;
#[cfg(feature = "colmap-model")]
pub(crate) mod kmeans;
pub mod output;
pub mod progress;
pub mod ranges;
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

#[cfg(feature = "demo")]
pub mod demo;

/// The user guide's Rust examples (docs/src/library.md) as doctests: `cargo test --doc`
/// compiles and runs them, so the guide cannot drift from the API.
#[cfg(all(doctest, feature = "colmap", feature = "localize"))]
#[doc = include_str!("../docs/src/library.md")]
pub struct GuideLibrary;
