//! Sections written to a scratch file as they are made, not held in memory until the map is
//! written (`convert` of a district: a level's descriptors are gigabytes). The writer lays
//! the map out as it does any section: the bytes are checksummed and copied from the scratch
//! file into the map at [`MapWriter::write`](super::MapWriter::write), and read back whole
//! only where a codec other than `raw` has to compress them, so a spooled map is byte for
//! byte the map of the same arrays held in memory.

use super::error::Error;
use super::layout::{checksum, Dtype, SectionKind, CHUNK_LEN};
use super::writer::Content;
use super::{LevelInfo, MapWriter};
use std::borrow::Cow;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Bytes read or written through the scratch file at once (a whole number of chunks).
const BLOCK: usize = 128 * CHUNK_LEN as usize;

/// A scratch file that sections are appended to (in the folder of the map it serves, gone
/// when the last section of it is dropped).
#[derive(Debug)]
pub struct Spool {
    file: Arc<File>,
    /// The map the scratch file serves: errors name it.
    output: PathBuf,
    /// Where the next region starts.
    next: u64,
}

/// A region of a [`Spool`] being filled: its bytes go out in [`BLOCK`]s.
#[derive(Debug)]
pub struct SpoolRegion {
    file: Arc<File>,
    output: PathBuf,
    start: u64,
    written: u64,
    len: u64,
    buffer: Vec<u8>,
}

/// A spooled section's bytes: `len` bytes at `offset` of the scratch file.
#[derive(Debug, Clone)]
pub struct SpooledBytes {
    file: Arc<File>,
    output: PathBuf,
    offset: u64,
    len: u64,
}

impl Spool {
    /// A scratch file in the folder of `output` (the map it serves), with no name where the
    /// file system allows it ([`crate::output::scratch_file`]).
    pub fn for_output(output: &Path) -> Result<Spool, Error> {
        let file = crate::output::scratch_file(output)?;
        Ok(Spool {
            file: Arc::new(file),
            output: output.to_path_buf(),
            next: 0,
        })
    }

    /// The next `len` bytes of the scratch file, to be filled in order.
    pub fn region(&mut self, len: u64) -> SpoolRegion {
        let start = self.next;
        self.next += len;
        SpoolRegion {
            file: Arc::clone(&self.file),
            output: self.output.clone(),
            start,
            written: 0,
            len,
            buffer: Vec::with_capacity(BLOCK.min(len as usize)),
        }
    }
}

impl SpoolRegion {
    /// Appends `bytes`; more than the region's length is an error.
    pub fn push(&mut self, bytes: &[u8]) -> Result<(), Error> {
        let total = self.written + self.buffer.len() as u64 + bytes.len() as u64;
        if total > self.len {
            return Err(Error::invalid(format!(
                "spooled section: {total} bytes written to a region of {}",
                self.len
            )));
        }
        self.buffer.extend_from_slice(bytes);
        if self.buffer.len() >= BLOCK {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), Error> {
        write_at(&self.file, &self.buffer, self.start + self.written)
            .map_err(|e| scratch_error(&self.output, e))?;
        self.written += self.buffer.len() as u64;
        self.buffer.clear();
        Ok(())
    }

    /// The region's bytes, once all of them were pushed.
    pub fn finish(mut self) -> Result<SpooledBytes, Error> {
        self.flush()?;
        if self.written != self.len {
            return Err(Error::invalid(format!(
                "spooled section: {} bytes written to a region of {}",
                self.written, self.len
            )));
        }
        Ok(SpooledBytes {
            file: self.file,
            output: self.output,
            offset: self.start,
            len: self.len,
        })
    }
}

/// A failed read or write of the scratch file of `output`'s map.
fn scratch_error(output: &Path, e: std::io::Error) -> Error {
    crate::output::OutputError::scratch(output, e).into()
}

impl<'a> MapWriter<'a> {
    /// [`MapWriter::add_level`] with the level's descriptors already spooled: `short`, the
    /// `[points × dim_short]` f16 little-endian rows, and `rest`, the
    /// `[points × (dim_full − dim_short)]` rest of each row; the map's bytes are those of
    /// `add_level` with the rows in memory.
    pub(crate) fn add_level_spooled(
        &mut self,
        info: LevelInfo,
        points: &'a [u32],
        short: SpooledBytes,
        rest: SpooledBytes,
    ) -> Result<&mut Self, Error> {
        let (level, n) = (info.level, points.len() as u64);
        if info.matched_dims(true) == 0 {
            return Err(Error::invalid(format!(
                "level {level}: no descriptor dimension"
            )));
        }
        let blocks = [
            (
                SectionKind::LevelDescShort,
                short,
                u64::from(info.dim_short),
            ),
            (
                SectionKind::LevelDescRest,
                rest,
                u64::from(info.dim_full.saturating_sub(info.dim_short)),
            ),
        ];
        for (_, bytes, cols) in &blocks {
            if bytes.len() != n * cols * 2 {
                return Err(Error::invalid(format!(
                    "level {level}: {} spooled bytes for {n} points × {cols} dims",
                    bytes.len()
                )));
            }
        }
        // The points, the checks and the metadata.
        self.add_level(info, points, None, false)?;
        for (kind, bytes, cols) in blocks {
            self.push(
                kind,
                level,
                Dtype::F16,
                n,
                cols,
                true,
                Content::Spooled(bytes),
            );
        }
        Ok(self)
    }
}

/// A section's stored bytes as the file will hold them: in memory, or still in the scratch
/// file (stored `raw`).
pub(super) enum Stored<'w> {
    Memory(Cow<'w, [u8]>),
    Spooled(&'w SpooledBytes),
}

impl Stored<'_> {
    pub(super) fn len(&self) -> u64 {
        match self {
            Stored::Memory(b) => b.len() as u64,
            Stored::Spooled(s) => s.len(),
        }
    }

    /// The section's checksum, and its chunks' appended to `chunks` when asked.
    pub(super) fn checksums(&self, chunks: Option<&mut Vec<u64>>) -> Result<u64, Error> {
        match self {
            Stored::Memory(b) => {
                if let Some(out) = chunks {
                    out.extend(super::chunks::chunk_checksums([&b[..]]));
                }
                Ok(checksum(b))
            }
            Stored::Spooled(s) => s.checksums(chunks),
        }
    }
}

impl SpooledBytes {
    /// Its length in bytes.
    pub fn len(&self) -> u64 {
        self.len
    }

    /// Calls `f` on the bytes in order, [`BLOCK`] bytes at a time (whole chunks but the last).
    pub(super) fn for_each_block(
        &self,
        mut f: impl FnMut(&[u8]) -> Result<(), Error>,
    ) -> Result<(), Error> {
        let mut buffer = vec![0u8; BLOCK.min(self.len as usize)];
        let mut done = 0u64;
        while done < self.len {
            let n = BLOCK.min((self.len - done) as usize);
            read_at(&self.file, &mut buffer[..n], self.offset + done)
                .map_err(|e| scratch_error(&self.output, e))?;
            f(&buffer[..n])?;
            done += n as u64;
        }
        Ok(())
    }

    /// The bytes, read back whole (to compress them).
    pub(super) fn read_all(&self) -> Result<Vec<u8>, Error> {
        let mut out = Vec::with_capacity(self.len as usize);
        self.for_each_block(|b| {
            out.extend_from_slice(b);
            Ok(())
        })?;
        Ok(out)
    }

    /// The section's checksum and, when `chunks`, its chunks' ([`super::chunks`]), in one
    /// read.
    pub(super) fn checksums(&self, chunks: Option<&mut Vec<u64>>) -> Result<u64, Error> {
        let mut whole = xxhash_rust::xxh3::Xxh3::new();
        let mut chunks = chunks;
        self.for_each_block(|b| {
            whole.update(b);
            if let Some(out) = chunks.as_deref_mut() {
                out.extend(b.chunks(CHUNK_LEN as usize).map(checksum));
            }
            Ok(())
        })?;
        Ok(whole.digest())
    }

    /// Copies the bytes to `out`, calling `advance` with each block's length.
    pub(super) fn copy_to(
        &self,
        out: &mut impl Write,
        mut advance: impl FnMut(u64),
    ) -> Result<(), Error> {
        self.for_each_block(|b| {
            out.write_all(b).map_err(|e| Error::io(&self.output, e))?;
            advance(b.len() as u64);
            Ok(())
        })
    }
}

/// `bytes` written at `offset` of `file`, whatever the file's position (it has none to
/// share between writers).
#[cfg(unix)]
pub(crate) fn write_at(file: &File, bytes: &[u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::write_all_at(file, bytes, offset)
}

/// `out.len()` bytes read at `offset` of `file`.
#[cfg(unix)]
pub(crate) fn read_at(file: &File, out: &mut [u8], offset: u64) -> std::io::Result<()> {
    std::os::unix::fs::FileExt::read_exact_at(file, out, offset)
}

#[cfg(windows)]
pub(crate) fn write_at(file: &File, mut bytes: &[u8], mut offset: u64) -> std::io::Result<()> {
    while !bytes.is_empty() {
        let n = std::os::windows::fs::FileExt::seek_write(file, bytes, offset)?;
        if n == 0 {
            return Err(std::io::ErrorKind::WriteZero.into());
        }
        bytes = &bytes[n..];
        offset += n as u64;
    }
    Ok(())
}

#[cfg(windows)]
pub(crate) fn read_at(file: &File, mut out: &mut [u8], mut offset: u64) -> std::io::Result<()> {
    while !out.is_empty() {
        let n = std::os::windows::fs::FileExt::seek_read(file, out, offset)?;
        if n == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        out = &mut out[n..];
        offset += n as u64;
    }
    Ok(())
}
