//! The `sfpmap` binary on small and crafted inputs: each command's output, errors, hostile input,
//! remote maps and catalogs on loopback servers.
//!
//! One of the three test crates (the guide's Contributing page, "Tests", says which test goes
//! where): each file here is a module, `tests/support/` holds what they share.

#[path = "../../../tests/support/common.rs"]
mod common;
#[path = "../../../tests/support/once.rs"]
mod once;
#[path = "../../../tests/support/python.rs"]
mod python;
#[path = "../../../tests/support/run.rs"]
mod run;
#[path = "../../../tests/support/servers.rs"]
mod servers;
#[path = "../../../tests/support/shared_data.rs"]
mod shared_data;
#[path = "../../../tests/support/street_cli.rs"]
mod street_cli;

mod catalog;
mod cli_format;
mod cli_reference;
mod export_plot;
mod export_ply;
mod extract_cli;
mod hostile_format;
mod hostile_inputs;
mod hostile_localize;
mod hostile_mcap;
mod hostile_names_flags;
mod kapture;
mod outbound_policy;
mod output_policy;
mod remote;
mod remote_bytes;
