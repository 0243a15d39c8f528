//! The `sfpmap` binary on small and crafted inputs: each command's output, errors, hostile input,
//! remote maps and catalogs on loopback servers.
//!
//! One of the three test crates (the guide's Contributing page, "Tests", says which test goes
//! where): each file here is a module, `tests/support/` holds what they share.

#[path = "../support/common.rs"]
mod common;
#[path = "../support/once.rs"]
mod once;
#[path = "../support/python.rs"]
mod python;
#[path = "../support/run.rs"]
mod run;
#[path = "../support/servers.rs"]
mod servers;
#[path = "../support/shared_data.rs"]
mod shared_data;
#[path = "../support/street_cli.rs"]
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
mod output_policy;
mod remote;
