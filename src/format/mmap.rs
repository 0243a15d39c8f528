//! The one place the crate opens and memory-maps a file.
#![allow(unsafe_code)]

use super::error::Error;
use memmap2::Mmap;
use std::fs::File;
use std::path::Path;

/// Opens `path` for reading if it is a regular file (a symlink to one is fine), else
/// [`Error::NotARegularFile`] saying what it is.
///
/// The path is checked before opening (opening a FIFO waits for a writer, forever if none
/// comes); it is opened with `O_NONBLOCK`, so a path swapped for a FIFO in between cannot
/// block either (the flag means nothing for a regular file); and the opened file is checked
/// again, since that is the one that is read.
pub(crate) fn open_regular(path: &Path) -> Result<File, Error> {
    let metadata = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    check_regular(&metadata)?;
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(rustix::fs::OFlags::NONBLOCK.bits() as i32);
    }
    let file = options.open(path).map_err(|e| Error::io(path, e))?;
    check_regular(&file.metadata().map_err(|e| Error::io(path, e))?)?;
    Ok(file)
}

fn check_regular(metadata: &std::fs::Metadata) -> Result<(), Error> {
    let t = metadata.file_type();
    if t.is_file() {
        return Ok(());
    }
    let what = if t.is_dir() {
        "is a directory"
    } else {
        not_regular(&t)
    };
    Err(Error::NotARegularFile { what })
}

#[cfg(unix)]
fn not_regular(t: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_fifo() {
        "is a FIFO, not a regular file"
    } else if t.is_char_device() {
        "is a character device, not a regular file"
    } else if t.is_block_device() {
        "is a block device, not a regular file"
    } else if t.is_socket() {
        "is a socket, not a regular file"
    } else {
        "is not a regular file"
    }
}

#[cfg(not(unix))]
fn not_regular(_: &std::fs::FileType) -> &'static str {
    "is not a regular file"
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
