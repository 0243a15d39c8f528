//! End to end on real scenes: localization of the shared scenes and KITTI 06 sequences, MCAP logs,
//! the C example against the built library.
//!
//! One of the three test crates (the guide's Contributing page, "Tests", says which test goes
//! where): each file here is a module, `tests/support/` holds what they share.

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
