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
/// Fuzz-target bodies and the raw on-disk structs they edit: for the fuzz crate and the
/// tests, not the reader API.
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
mod layout;
mod metadata;
mod mmap;
mod pq;
mod reader;
mod slice;
mod source;
mod views;
mod writer;

pub use catalog::{Catalog, Listing, Place, CATALOG_KEY};
pub use chunks::{CheckedByChunk, VisibilityByChunk};
pub use error::{Error, SectionRef};
pub use layout::{
    align_up, checksum, Codec, Dtype, SectionKind, ALIGN, CHUNK_LEN, ENDIAN_CHECK, ENTRY_LEN,
    HEADER_LEN, MAGIC, MAX_CAMERA_PARAMS, MAX_DESCRIPTOR_DIM, MAX_ENTRY_LEN, MAX_IMAGE_SIDE,
    MAX_SECTIONS, METADATA_MAX_BYTES, NO_LEVEL, SECTION_REQUIRED, VERSION_MAJOR, VERSION_MINOR,
};
#[cfg(feature = "fuzzing")]
pub use layout::{Header, RawEntry};
pub use metadata::{
    CameraInfo, LevelInfo, Metadata, PositionGrid, Provenance, Retrieval, SourceFile,
    DEFAULT_RETRIEVAL_TOP_K,
};
// Only the PQ trainer in `build` (behind `colmap-model`) checks orders it is handed.
#[cfg(feature = "colmap-model")]
pub(crate) use pq::check_order as pq_check_order;
pub use pq::{gather as pq_gather, Pq, MAX_PQ_CENTROIDS};
pub use reader::{decode_budget, decode_cap, Map, Section, Skipped};
pub use slice::{slice, SliceOptions, SliceSummary};
pub use source::{coalesce, RangeSource, SourceStats, Wanted, COALESCE_GAP, HEAD_READ};
pub use views::{GlobalDescriptors, Images, Level, Visibility, Vlad};
pub use writer::{Descriptors, MapWriter};

/// Memory-maps a file read-only (see the safety note on sfpmap's own files in `mmap.rs`).
#[cfg(feature = "colmap-model")]
pub(crate) use mmap::map_file;

/// Re-exported so users need not depend on `half` to name descriptor elements.
pub use half::f16;

/// XXH3-64 of a file's bytes, as provenance stores it (hex).
pub fn file_hash(bytes: &[u8]) -> String {
    format!("{:016x}", checksum(bytes))
}
