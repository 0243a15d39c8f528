//! End to end on real scenes: localization of the shared scenes and KITTI 06 sequences, MCAP logs,
//! the C example against the built library.
//!
//! One test crate (one binary to link) per kind of test: `tests/api` (the library), `tests/cli`
//! (the binary on small and crafted inputs), `tests/e2e` (real scenes end to end). Each file
//! here is a module; `tests/support/` holds what they share.

#[path = "../support/common.rs"]
mod common;
#[path = "../support/once.rs"]
mod once;
#[path = "../support/python.rs"]
mod python;
#[path = "../support/shared_data.rs"]
mod shared_data;

mod embed_c;
mod localize_cli;
mod mcap_localize;
mod sequence_kitti;
