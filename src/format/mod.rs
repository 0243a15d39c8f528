//! The sfpmap file format (`spec/format.md` is the source of truth).
//!
//! A map is one file: a 64-byte header, a section table, a JSON metadata block, then
//! 64-byte-aligned sections holding arrays (points, per-level descriptors split into
//! `short` and `rest` blocks, images, visibility). [`Map`] opens it with one mmap and
//! validates the index; sections are checked on first access. [`MapWriter`] writes it.
//!
//! ```no_run
//! # fn main() -> Result<(), sfpmap::format::Error> {
//! let map = sfpmap::format::Map::open("building.sfpm")?;
//! let level = map.level(2)?;
//! let short = level.desc_short()?; // &[f16] borrowed from the mapping
//! assert_eq!(short.len(), level.len() * level.dim_short());
//! # Ok(()) }
//! ```

mod catalog;
mod chunks;
mod delta;
mod error;
pub(crate) mod index;
// Fuzz-target bodies and the raw layout they edit: public at `sfpmap::fuzzing`.
#[cfg(feature = "fuzzing")]
pub(crate) mod fuzzing;
mod layout;
mod metadata;
mod mmap;
mod pq;
mod reader;
mod short_basis;
mod slice;
mod source;
mod views;
// Written to by `convert` (`colmap`); the writer reads what it spooled in every build.
#[cfg_attr(not(feature = "colmap"), allow(dead_code, unused_imports))]
mod spool;
mod writer;

pub use catalog::{Catalog, Listing, Place};
pub use chunks::{CheckedByChunk, VisibilityByChunk};
pub use error::{Error, SectionRef};
pub use index::{ImageIndex, Neighbours, MAX_NEIGHBOURS, NO_NEIGHBOUR};
pub use layout::{
    Codec, Dtype, SectionKind, MAGIC, MAX_DESCRIPTOR_DIM, VERSION_MAJOR, VERSION_MINOR,
};
#[cfg(feature = "localize")]
pub(crate) use metadata::descriptor_names_feature;
#[cfg(feature = "colmap")]
pub(crate) use metadata::UNNAMED_FEATURE_PREFIX;
pub use metadata::{
    CameraInfo, ImageIndexInfo, LevelInfo, Metadata, PositionGrid, Provenance, Retrieval,
    SourceFile, DEFAULT_RETRIEVAL_TOP_K,
};
pub use pq::Pq;
pub use reader::{Map, Section, Skipped};
pub use slice::{slice, SliceOptions, SliceSummary};
pub use source::{RangeSource, SourceStats, Wanted};
#[cfg(feature = "colmap")]
pub(crate) use spool::{write_at, Spool, SpoolRegion, SpooledBytes};
// Also convert's fast model reader, which the fuzz body runs without `colmap`.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
#[allow(unused_imports)]
pub(crate) use spool::read_at;
pub use views::{GlobalDescriptors, Images, Level, Visibility, Vlad};
pub use writer::{Descriptors, MapWriter};

/// Re-exported so users need not depend on `half` to name descriptor elements.
pub use half::f16;

// The rest of the crate's view of the format's internals (the fuzzing hooks add the raw
// layout, `sfpmap::fuzzing`).
#[cfg(feature = "colmap")]
pub(crate) use index::indexed_kind;
#[cfg(any(feature = "onnx", feature = "remote"))]
pub(crate) use layout::checksum;
#[cfg(feature = "colmap-model")]
pub(crate) use mmap::map_file;
// Only the PQ trainer in `build` (behind `colmap-model`) checks orders it is handed.
#[cfg(feature = "colmap-model")]
pub(crate) use pq::check_order as pq_check_order;
#[cfg(any(feature = "localize", feature = "colmap-model"))]
pub(crate) use pq::gather as pq_gather;
#[cfg(feature = "remote")]
pub(crate) use source::{coalesce, HEAD_READ};

/// XXH3-64 of a file's bytes, as provenance stores it (hex).
#[cfg(feature = "onnx")]
pub(crate) fn file_hash(bytes: &[u8]) -> String {
    hash_hex(checksum(bytes))
}

/// An XXH3-64 as provenance stores it: 16 hex digits.
#[cfg(any(feature = "colmap", feature = "onnx"))]
pub(crate) fn hash_hex(hash: u64) -> String {
    format!("{hash:016x}")
}
