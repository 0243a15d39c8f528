//! Hooks for the fuzz crate (`fuzz/`), the tests that craft maps byte by byte and the benches
//! that time internal kernels: feature `fuzzing`, off for library users. Nothing here is part
//! of the API or keeps its shape between versions.
//!
//! - The fuzz-target bodies, kept in the library so `cargo test` replays the corpus and the
//!   committed crashes without cargo-fuzz: [`open_and_read`], [`decode_sections`],
//!   [`slice_in_memory`], [`all_format_bodies`] (the map format), [`read_colmap_bin`] and
//!   [`read_colmap_txt`] (COLMAP models). Each format body runs on its input as it is and
//!   again with every checksum fixed up ([`fix_checksums`]).
//! - The raw layout of a map (`spec/format.md`): [`Header`], [`RawEntry`], the lengths, flags
//!   and caps a crafted map is written with, and [`checksum`].
//! - The matching kernels the localize benches time ([`match_descriptors`] and the others).

pub use crate::format::fuzzing::*;

#[cfg(feature = "colmap-model")]
pub use crate::build::geometry::read_colmap_bin;
#[cfg(feature = "geometry")]
pub use crate::geometry::rng::SplitMix64;
#[cfg(feature = "localize")]
pub use crate::localize::internals::*;
#[cfg(feature = "localize")]
pub use crate::vector::normalise_rows;

/// Fuzz entry point of the COLMAP text readers: `data` parsed as each text model file, then
/// as a whole model (so validation is fuzzed too) laid out as [`read_colmap_bin`] lays out
/// binary ones. Never panics (that is the test).
#[cfg(feature = "colmap-model")]
pub fn read_colmap_txt(data: &[u8]) {
    use crate::colmap::text;
    let path = std::path::Path::new("fuzz.txt");
    let _ = text::parse_cameras(data, path);
    let _ = text::parse_images(data, path);
    let _ = text::parse_model((b"", path), (b"", path), (data, path));
    let [c, i, p] = crate::colmap::split3(data);
    let _ = text::parse_model((c, path), (i, path), (p, path));
}
