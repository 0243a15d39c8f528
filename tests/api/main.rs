//! The library's API: format, COLMAP, geometry, localizer, extractor, the C ABI in process and
//! from C (the example against the built cdylib), vectors, fuzz replays.
//!
//! One of the three test crates (the guide's Contributing page, "Tests", says which test goes
//! where): each file here is a module, `tests/support/` holds what they share.

#[path = "../support/common.rs"]
mod common;
#[path = "../support/python.rs"]
mod python;
#[path = "../support/servers.rs"]
mod servers;
#[path = "../support/shared_data.rs"]
mod shared_data;
#[path = "../support/synthetic_scene.rs"]
mod synthetic_scene;

mod catalog_session;
mod colmap_database;
mod colmap_models;
mod convert;
mod convert_features;
mod embed_c;
mod embed_capi;
mod embed_capi_features;
mod embed_capi_inputs;
mod embed_capi_localize;
mod embed_capi_session;
mod extract_aliked;
mod extract_reference;
mod format_chunks;
mod format_errors;
mod format_index;
mod format_roundtrip;
mod format_source;
mod fuzz_replay;
mod geometry_camera;
mod geometry_pose;
mod geometry_real;
mod localize;
mod mcap_log;
mod remote_objects;
mod session;
mod street_scene;
mod vectors;
