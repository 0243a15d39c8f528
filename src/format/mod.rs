//! The sfpmap file format.
