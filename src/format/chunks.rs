//! Chunk checksums (1.2): XXH3 of every [`CHUNK_LEN`] bytes of each section's stored bytes, in
//! the optional `chunk_checksums` section, so that a reader checks a large raw section a chunk
//! at a time where it reads it ([`Chunked`]) instead of whole on first access. Opening a
//! 1 GB map and localizing one query then hashes the chunks that query reads, not the gigabyte
//! (spec, "chunk_checksums").

use super::error::Error;
use super::layout::{checksum, Codec, SectionKind, CHUNK_LEN};
use super::reader::{Map, Section};
use bitvec::vec::BitVec;
use std::borrow::Cow;
use std::ops::Range;
use std::sync::atomic::AtomicU64;

/// Chunks of a section of `stored_len` bytes (0 for an empty one).
pub(crate) fn chunk_count(stored_len: u64) -> u64 {
    stored_len.div_ceil(CHUNK_LEN)
}

/// The `chunk_checksums` values of sections' stored bytes, sections in table order.
pub(crate) fn chunk_checksums<'b>(stored: impl IntoIterator<Item = &'b [u8]>) -> Vec<u64> {
    stored
        .into_iter()
        .flat_map(|bytes| bytes.chunks(CHUNK_LEN as usize).map(checksum))
        .collect()
}

/// Whether a writer stores `chunk_checksums` for sections of these stored lengths: when one
/// of them spans more than one chunk (a map of small sections gains nothing, and stays the
/// 1.0 or 1.1 file it was, byte for byte).
pub(crate) fn worth_storing(mut stored_lens: impl Iterator<Item = u64>) -> bool {
    stored_lens.any(|len| len > CHUNK_LEN)
}

/// The expected `chunk_checksums` row count for a table: chunks of every other section, in
/// order (the sum of the stored lengths is at most the file's, so this cannot overflow a
/// table that tiles its file; checked anyway).
pub(crate) fn expected_rows(sections: &[Section]) -> Option<u64> {
    sections
        .iter()
        .filter(|s| s.kind != SectionKind::ChunkChecksums)
        .try_fold(0u64, |n, s| n.checked_add(chunk_count(s.stored_len)))
}

/// Per open map with `chunk_checksums`: where each section's chunks start among its values,
/// and which chunks were checked (set once checked; a failed chunk is checked again).
pub(crate) struct ChunkIndex {
    /// Table position of the `chunk_checksums` section.
    pub(crate) section: usize,
    /// Per table position: the first chunk's row (the chunk section's own entry is unused).
    first: Vec<u64>,
    checked: BitVec<AtomicU64>,
}

impl ChunkIndex {
    /// For a validated table whose `chunk_checksums` section (`None`: none, or skipped) has
    /// [`expected_rows`] rows, as `check_shapes` made sure.
    pub(crate) fn new(sections: &[Section], chunk_section: Option<&Section>) -> Option<ChunkIndex> {
        let chunk_section = chunk_section?;
        let mut first = Vec::with_capacity(sections.len());
        let mut next = 0u64;
        for s in sections {
            first.push(next);
            if s.kind != SectionKind::ChunkChecksums {
                next += chunk_count(s.stored_len);
            }
        }
        debug_assert_eq!(next, chunk_section.rows);
        Some(ChunkIndex {
            section: chunk_section.index,
            first,
            checked: BitVec::repeat(false, next as usize),
        })
    }

    /// The row of chunk `k` of `section`.
    pub(crate) fn row(&self, section: &Section, k: u64) -> usize {
        (self.first[section.index] + k) as usize
    }

    pub(crate) fn is_checked(&self, row: usize) -> bool {
        self.checked[row]
    }

    pub(crate) fn mark_checked(&self, row: usize) {
        self.checked.set_aliased(row, true);
    }
}

/// A section's array read where it is used: with `chunk_checksums`, a view of a raw
/// section's stored values whose chunks are checked (checksum, and the kind's contents rules
/// value by value) the first time a range covering them is asked for; otherwise the array
/// checked whole when the view was made. Made by [`Map::chunked`].
pub struct Chunked<'m, T: Clone> {
    values: Cow<'m, [T]>,
    /// The map and section whose chunks are checked where read; `None`: all of it was checked
    /// when the view was made.
    lazy: Option<(&'m Map<'m>, Section)>,
}

impl<'m, T: bytemuck::Pod> Chunked<'m, T> {
    fn new(map: &'m Map<'m>, section: &Section) -> Result<Chunked<'m, T>, Error> {
        let by_chunk = map.chunk_index().is_some()
            && section.codec == Codec::Raw
            && section.skipped.is_none()
            && section.kind.checked_by_chunk()
            && !map.is_checked_whole(section);
        Ok(if by_chunk {
            Chunked {
                values: super::reader::cast(map.stored_bytes(section)?),
                lazy: Some((map, *section)),
            }
        } else {
            Chunked::checked(map.section_array(section)?)
        })
    }

    /// Values checked already (or made by the caller), for code that takes either.
    pub fn checked(values: Cow<'m, [T]>) -> Chunked<'m, T> {
        Chunked { values, lazy: None }
    }

    /// Values in the array.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// The chunks `values[range]` lies in (`None` for an empty range).
    fn chunks_of(range: &Range<usize>) -> Option<std::ops::RangeInclusive<u64>> {
        let size = std::mem::size_of::<T>() as u64;
        (range.end > range.start).then(|| {
            range.start as u64 * size / CHUNK_LEN..=(range.end as u64 * size - 1) / CHUNK_LEN
        })
    }

    /// Checks the chunks holding `values[range]` that are not checked yet.
    ///
    /// # Panics
    /// If `range` is not within the array (a caller's bug, not the file's).
    pub fn check(&self, range: Range<usize>) -> Result<(), Error> {
        assert!(range.start <= range.end && range.end <= self.values.len());
        let (Some((map, section)), Some(chunks)) = (self.lazy, Self::chunks_of(&range)) else {
            return Ok(());
        };
        chunks
            .into_iter()
            .try_for_each(|k| map.check_chunk(&section, k))
    }

    /// Checks the chunks holding rows `rows` (ascending) of `row_len` values: each chunk
    /// asked for once per call, however many rows it holds.
    ///
    /// # Panics
    /// If a row is not within the array.
    pub fn check_rows(
        &self,
        rows: impl IntoIterator<Item = usize>,
        row_len: usize,
    ) -> Result<(), Error> {
        let Some((map, section)) = self.lazy else {
            return Ok(());
        };
        let mut done: Option<u64> = None;
        for r in rows {
            let range = r * row_len..(r + 1) * row_len;
            assert!(range.end <= self.values.len());
            let Some(chunks) = Self::chunks_of(&range) else {
                continue;
            };
            for k in chunks {
                if done.is_none_or(|d| k > d) {
                    map.check_chunk(&section, k)?;
                    done = Some(k);
                }
            }
        }
        Ok(())
    }

    /// Checks every chunk (all of the array).
    pub fn check_all(&self) -> Result<(), Error> {
        self.check(0..self.values.len())
    }

    /// `values[range]`, its chunks checked.
    pub fn get(&self, range: Range<usize>) -> Result<&[T], Error> {
        self.check(range.clone())?;
        Ok(&self.values[range])
    }

    /// Whether every chunk holding `values[range]` was checked (for debug assertions of
    /// callers that check ranges ahead of reading them).
    pub fn is_checked(&self, range: Range<usize>) -> bool {
        let (Some((map, section)), Some(chunks)) = (self.lazy, Self::chunks_of(&range)) else {
            return true;
        };
        let index = map
            .chunk_index()
            .expect("lazy views exist only with chunk checksums");
        chunks
            .into_iter()
            .all(|k| index.is_checked(index.row(&section, k)))
    }

    /// All values, checked or not: for callers that [`check`](Self::check) each range before
    /// they read it (the localizer checks a query's candidate rows once, then reads them in
    /// its kernels).
    pub(crate) fn unchecked(&self) -> &[T] {
        &self.values
    }
}

impl Map<'_> {
    /// A view of `section`'s array checked where it is read (see [`Chunked`]): chunk by chunk
    /// for a raw section of a kind [`SectionKind::checked_by_chunk`] in a map with
    /// `chunk_checksums` (1.2), otherwise checked whole now.
    pub fn chunked<T: bytemuck::Pod>(&self, section: &Section) -> Result<Chunked<'_, T>, Error> {
        self.own_section(section)?;
        Chunked::new(self, section)
    }

    /// Checks chunk `k` of `section` against `chunk_checksums`, and its values against the
    /// kind's value-by-value contents rules; free once it passed.
    pub(crate) fn check_chunk(&self, section: &Section, k: u64) -> Result<(), Error> {
        let index = self
            .chunk_index()
            .expect("chunked views exist only with chunk checksums");
        let row = index.row(section, k);
        if index.is_checked(row) {
            return Ok(());
        }
        // The chunk section is checked whole (its own checksum) on its first use.
        let sums = self.section_bytes(&self.sections()[index.section])?;
        let expected = u64::from_le_bytes(sums[row * 8..row * 8 + 8].try_into().expect("8"));
        let stored = self.stored_bytes(section)?;
        let start = (k * CHUNK_LEN) as usize;
        let end = stored.len().min(start + CHUNK_LEN as usize);
        let bytes = &stored[start..end];
        let found = checksum(bytes);
        if found != expected {
            return Err(Error::ChunkChecksumMismatch {
                section: section.reference(),
                chunk: k,
                bytes: start as u64..end as u64,
                expected,
                found,
            });
        }
        // A kind checked whole (by `verify`, which also walks every chunk) has its contents
        // checked there.
        if section.kind.checked_by_chunk() && section.skipped.is_none() {
            super::views::check_chunk_contents(self, section, bytes)?;
        }
        index.mark_checked(row);
        Ok(())
    }

    /// Checks every chunk of `section` (by `verify`, which also checks the section whole).
    pub(crate) fn check_chunks(&self, section: &Section) -> Result<(), Error> {
        if self.chunk_index().is_none() || section.kind == SectionKind::ChunkChecksums {
            return Ok(());
        }
        (0..chunk_count(section.stored_len)).try_for_each(|k| self.check_chunk(section, k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chunks_cover_every_byte_once() {
        assert_eq!(chunk_count(0), 0);
        assert_eq!(chunk_count(1), 1);
        assert_eq!(chunk_count(CHUNK_LEN), 1);
        assert_eq!(chunk_count(CHUNK_LEN + 1), 2);
        let a = vec![7u8; CHUNK_LEN as usize + 5];
        let b: Vec<u8> = Vec::new();
        let c = vec![1u8; 3];
        let sums = chunk_checksums([&a[..], &b[..], &c[..]]);
        assert_eq!(
            sums,
            [
                checksum(&a[..CHUNK_LEN as usize]),
                checksum(&a[CHUNK_LEN as usize..]),
                checksum(&c)
            ]
        );
        assert!(!worth_storing([CHUNK_LEN, 3].into_iter()));
        assert!(worth_storing([CHUNK_LEN + 1].into_iter()));
    }
}
