//! The one place the crate memory-maps a file.
#![allow(unsafe_code)]

use memmap2::Mmap;
use std::fs::File;

/// Maps `file` read-only.
///
/// The mapping is only sound while no one truncates or rewrites the file underneath it;
/// sfpmap's own writer never does (it writes a temp file and renames it over the old
/// one, which leaves existing mappings of the old inode intact). A map edited in place by
/// another program while open is outside the contract, as for every mmap reader.
pub fn map_file(file: &File) -> std::io::Result<Mmap> {
    // SAFETY: see above: sfpmap files are replaced by rename, never modified in place, so
    // the mapped bytes do not change for the lifetime of the mapping.
    unsafe { Mmap::map(file) }
}
