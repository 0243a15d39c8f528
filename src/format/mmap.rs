//! The one place the crate opens and memory-maps a file.
#![allow(unsafe_code)]

use super::error::Error;
use memmap2::Mmap;
use std::fs::File;
use std::path::Path;

/// Opens `path` for reading if it is a regular file (a symlink to one is fine), else
/// [`Error::NotARegularFile`] saying what it is; never blocks ([`crate::input::open_regular`]).
pub(crate) fn open_regular(path: &Path) -> Result<File, Error> {
    crate::input::open_regular(path).map_err(|e| match e {
        crate::input::OpenError::Io(e) => Error::io(path, e),
        crate::input::OpenError::NotRegular(what) => Error::NotARegularFile { what },
    })
}

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
