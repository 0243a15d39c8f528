//! End to end on real scenes: localization of the shared scenes and KITTI 06 sequences, MCAP
//! logs.
//!
//! One of the three test crates (the guide's Contributing page, "Tests", says which test goes
//! where): each file here is a module, `tests/support/` holds what they share.

#[path = "../../../tests/support/common.rs"]
mod common;
#[path = "../../../tests/support/once.rs"]
mod once;
#[path = "../../../tests/support/python.rs"]
mod python;
#[path = "../../../tests/support/servers.rs"]
mod servers;
#[path = "../../../tests/support/shared_data.rs"]
mod shared_data;

mod hloc_features;
mod localize_cli;
mod mcap_localize;
#[cfg(feature = "ros2")]
mod ros2_node;
mod sequence_kitti;
