//! Chunk checksums (1.2): XXH3 of every [`CHUNK_LEN`] bytes of each section's stored bytes, in
//! the optional `chunk_checksums` section, so that a reader checks a large raw section a chunk
//! at a time where it reads it ([`CheckedByChunk`]) instead of whole on first access. Opening a
//! 1 GB map and localizing one query then hashes the chunks that query reads, not the gigabyte
//! (spec, "chunk_checksums").

use super::error::Error;
use super::layout::{checksum, Codec, SectionKind, CHUNK_LEN};
use super::reader::{Map, Section};
use super::views::Level;
use bitvec::vec::BitVec;
use half::f16;
use std::borrow::Cow;
use std::ops::Range;
use std::sync::atomic::AtomicU64;
use std::sync::OnceLock;

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
pub(crate) fn writes_chunk_checksums(mut stored_lens: impl Iterator<Item = u64>) -> bool {
    stored_lens.any(|len| len > CHUNK_LEN)
}

/// Per table position, the row of the section's first chunk in `chunk_checksums` (sections
/// in table order, `chunk_checksums` itself left out: its entry gets the next row and no
/// chunk), and the total, which is the row count `chunk_checksums` must have. `None` on
/// overflow (a table that tiles its file cannot: its stored lengths add up to at most the
/// file's).
pub(crate) fn chunk_rows(sections: &[Section]) -> Option<(Vec<u64>, u64)> {
    let mut first = Vec::with_capacity(sections.len());
    let mut next = 0u64;
    for s in sections {
        first.push(next);
        if s.kind != SectionKind::ChunkChecksums {
            next = next.checked_add(chunk_count(s.stored_len))?;
        }
    }
    Some((first, next))
}

/// Whether the reference reader checks `section` a chunk at a time where it is read: a raw
/// section it reads, of a kind whose contents rules hold value by value (so a chunk's values
/// are checked without the rest), in a map with `chunk_checksums`.
fn reads_by_chunk(map: &Map<'_>, section: &Section) -> bool {
    map.chunk_index().is_some()
        && section.codec == Codec::Raw
        && section.skipped.is_none()
        && super::views::rules_hold_per_value(section.kind)
}

/// Per open map with `chunk_checksums`: where each section's chunks start among its values,
/// and which chunks were checked (set once checked; a failed chunk is checked again).
pub(crate) struct ChunkIndex {
    /// Table position of the `chunk_checksums` section.
    pub(crate) section: usize,
    /// Per table position: the first chunk's row (the chunk section's own entry is unused).
    first: Vec<u64>,
    /// Per table position: a bit per chunk, made when the section's first chunk is checked,
    /// so it is sized by bytes the reader holds (read by range, the file length is only the
    /// server's claim).
    checked: Vec<OnceLock<BitVec<AtomicU64>>>,
}

impl ChunkIndex {
    /// For a validated table whose `chunk_checksums` section (`None`: none, or skipped) has
    /// the rows [`chunk_rows`] gives, as `check_shapes` made sure.
    pub(crate) fn new(sections: &[Section], chunk_section: Option<&Section>) -> Option<ChunkIndex> {
        let chunk_section = chunk_section?;
        let (first, next) = chunk_rows(sections)?;
        debug_assert_eq!(next, chunk_section.rows);
        Some(ChunkIndex {
            section: chunk_section.index,
            first,
            checked: sections.iter().map(|_| OnceLock::new()).collect(),
        })
    }

    /// The row of chunk `k` of `section` in `chunk_checksums`.
    fn row(&self, section: &Section, k: u64) -> Option<usize> {
        usize::try_from(self.first[section.index].checked_add(k)?).ok()
    }

    fn is_checked(&self, section: &Section, k: u64) -> bool {
        self.checked[section.index]
            .get()
            .is_some_and(|bits| usize::try_from(k).is_ok_and(|k| k < bits.len() && bits[k]))
    }

    /// Marks chunk `k` of `section` checked; the caller holds the section's stored bytes, so
    /// the bits are sized by bytes in hand.
    fn mark_checked(&self, section: &Section, k: u64) {
        let bits = self.checked[section.index]
            .get_or_init(|| BitVec::repeat(false, chunk_count(section.stored_len) as usize));
        bits.set_aliased(k as usize, true);
    }
}

/// A section's array read where it is used: with `chunk_checksums`, a view of a raw
/// section's stored values whose chunks are checked (checksum, and the kind's contents rules
/// value by value) the first time a range covering them is asked for; otherwise the array
/// checked whole when the view was made. Made by [`Map::by_chunk`].
#[derive(Debug)]
pub struct CheckedByChunk<'m, T: Clone> {
    values: Cow<'m, [T]>,
    /// The map and section whose chunks are checked where read; `None`: all of it was checked
    /// when the view was made.
    lazy: Option<(&'m Map<'m>, Section)>,
}

impl<'m, T: bytemuck::Pod> CheckedByChunk<'m, T> {
    fn new(map: &'m Map<'m>, section: &Section) -> Result<CheckedByChunk<'m, T>, Error> {
        // A section checked whole already (or refused: its error again) needs no chunk.
        let whole = map.whole_check(section);
        Ok(match whole {
            None if reads_by_chunk(map, section) => CheckedByChunk {
                values: super::reader::cast(map.stored_bytes(section)?),
                lazy: Some((map, *section)),
            },
            Some(Err(e)) => return Err(e),
            _ => CheckedByChunk::from_checked(map.section_array(section)?),
        })
    }

    /// Values checked already (or made by the caller), for code that takes either.
    pub(crate) fn from_checked(values: Cow<'m, [T]>) -> CheckedByChunk<'m, T> {
        CheckedByChunk { values, lazy: None }
    }

    /// Values in the array.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// Whether the array is empty.
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
            let end = r
                .checked_add(1)
                .and_then(|n| n.checked_mul(row_len))
                .filter(|&end| end <= self.values.len())
                .expect("rows within the array");
            let range = end - row_len..end;
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
    /// callers that check ranges ahead of reading them, and tests).
    pub fn is_checked(&self, range: Range<usize>) -> bool {
        assert!(range.start <= range.end && range.end <= self.values.len());
        let (Some((map, section)), Some(chunks)) = (self.lazy, Self::chunks_of(&range)) else {
            return true;
        };
        let index = map
            .chunk_index()
            .expect("lazy views exist only with chunk checksums");
        chunks.into_iter().all(|k| index.is_checked(&section, k))
    }

    /// All values, checked or not: for callers that [`check`](Self::check) each range before
    /// they read it (the localizer checks a query's candidate rows once, then reads them in
    /// its kernels).
    #[cfg(feature = "localize")]
    pub(crate) fn unchecked(&self) -> &[T] {
        &self.values
    }
}

impl Map<'_> {
    /// A view of `section`'s array checked where it is read (see [`CheckedByChunk`]): chunk by chunk
    /// for a raw section of a kind whose contents rules hold value by value (the descriptor
    /// blocks, visibility) in a map with `chunk_checksums` (1.2), otherwise checked whole now.
    /// `T` must have the size of the section's dtype.
    pub fn by_chunk<T: bytemuck::Pod>(
        &self,
        section: &Section,
    ) -> Result<CheckedByChunk<'_, T>, Error> {
        self.own_section(section)?;
        if std::mem::size_of::<T>() as u64 != section.dtype.size() {
            return Err(Error::invalid(format!(
                "{}: {}-byte values asked of a section of {}",
                section.reference(),
                std::mem::size_of::<T>(),
                section.dtype.name()
            )));
        }
        CheckedByChunk::new(self, section)
    }

    /// Checks chunk `k` of `section` against `chunk_checksums`, and its values against the
    /// kind's value-by-value contents rules; free once it passed.
    pub(crate) fn check_chunk(&self, section: &Section, k: u64) -> Result<(), Error> {
        let index = self
            .chunk_index()
            .expect("views checked by chunk exist only with chunk checksums");
        if index.is_checked(section, k) {
            return Ok(());
        }
        let stored = self.stored_bytes(section)?;
        self.check_chunk_in(section, k, 0, stored)
    }

    /// [`Map::check_chunk`] of a chunk in `bytes`, the section's stored bytes from position
    /// `from` on (a piece `verify` read without keeping the section), up to the chunk's end
    /// or the section's.
    pub(crate) fn check_chunk_in(
        &self,
        section: &Section,
        k: u64,
        from: u64,
        bytes: &[u8],
    ) -> Result<(), Error> {
        let index = self
            .chunk_index()
            .expect("views checked by chunk exist only with chunk checksums");
        if index.is_checked(section, k) {
            return Ok(());
        }
        // The chunk section is checked whole (its own checksum) on its first use.
        let sums = self.section_bytes(&self.sections()[index.section])?;
        // Views ask only for chunks of their values, and `verify` for chunks of the stored
        // length; `rows` of `chunk_checksums` was checked against those at open.
        let no_chunk = || Error::invalid(format!("{}: no chunk {k}", section.reference()));
        let start = k * CHUNK_LEN;
        let (Some(row), Some(Ok(local))) = (
            index.row(section, k),
            start.checked_sub(from).map(usize::try_from),
        ) else {
            return Err(no_chunk());
        };
        let end = bytes.len().min(local.saturating_add(CHUNK_LEN as usize));
        let (Some(sum), Some(chunk)) = (sums.get(row * 8..row * 8 + 8), bytes.get(local..end))
        else {
            return Err(no_chunk());
        };
        let expected = u64::from_le_bytes(sum.try_into().expect("8 bytes"));
        let found = checksum(chunk);
        if found != expected {
            return Err(Error::ChunkChecksumMismatch {
                section: section.reference(),
                chunk: k,
                bytes: start..from + end as u64,
                expected,
                found,
            });
        }
        // Another section (`verify` walks every chunk of every section), or one checked whole
        // already, has its contents checked whole.
        if reads_by_chunk(self, section) && self.whole_check(section).is_none() {
            super::views::check_contents(self, section, chunk)?;
        }
        index.mark_checked(section, k);
        Ok(())
    }

    /// Checks the chunks of `section` that lie in `bytes`, its stored bytes from position
    /// `from` (a multiple of [`CHUNK_LEN`]) on (by `verify`, which read them without keeping
    /// the section).
    pub(crate) fn check_chunks_in(
        &self,
        section: &Section,
        from: u64,
        bytes: &[u8],
    ) -> Result<(), Error> {
        if self.chunk_index().is_none() || section.kind == SectionKind::ChunkChecksums {
            return Ok(());
        }
        let first = from / CHUNK_LEN;
        (first..first + chunk_count(bytes.len() as u64))
            .try_for_each(|k| self.check_chunk_in(section, k, from, bytes))
    }

    /// Checks every chunk of `section` (by `verify`, which also checks the section whole).
    pub(crate) fn check_chunks(&self, section: &Section) -> Result<(), Error> {
        if self.chunk_index().is_none() || section.kind == SectionKind::ChunkChecksums {
            return Ok(());
        }
        (0..chunk_count(section.stored_len)).try_for_each(|k| self.check_chunk(section, k))
    }
}

impl<'m> Level<'m> {
    /// [`Level::desc_short`] checked where it is read, a chunk at a time (1.2, see
    /// [`CheckedByChunk`]): what a localizer that reads a few rows per query takes.
    pub fn desc_short_by_chunk(&self) -> Result<CheckedByChunk<'m, f16>, Error> {
        let s = self.short.ok_or(Error::MissingSection {
            kind: SectionKind::LevelDescShort,
            level: Some(self.id()),
        })?;
        self.map.by_chunk(s)
    }

    /// [`Level::desc_rest`] checked where it is read (see [`Level::desc_short_by_chunk`]).
    pub fn desc_rest_by_chunk(&self) -> Result<Option<CheckedByChunk<'m, f16>>, Error> {
        self.rest.map(|s| self.map.by_chunk(s)).transpose()
    }
}

/// Image → point ids, in CSR form, the points checked where they are read (1.2, see
/// [`CheckedByChunk`]): what a localizer that reads a few images' points per query takes.
pub struct VisibilityByChunk<'m> {
    /// `[images + 1]`: image `i`'s points are `points[offsets[i]..offsets[i + 1]]`.
    pub offsets: Cow<'m, [u64]>,
    /// The images' point ids, end to end.
    pub points: CheckedByChunk<'m, u32>,
}

impl VisibilityByChunk<'_> {
    /// The points image `i` sees, their chunks checked.
    pub fn points_of(&self, i: usize) -> Result<&[u32], Error> {
        self.points
            .get(self.offsets[i] as usize..self.offsets[i + 1] as usize)
    }
}

impl Map<'_> {
    /// [`Map::visibility_points`] with the points checked where they are read (1.2, see
    /// [`CheckedByChunk`]).
    pub fn visibility_by_chunk(&self) -> Result<Option<VisibilityByChunk<'_>>, Error> {
        let Some(offsets) = self.find(SectionKind::VisibilityOffsets, None) else {
            return Ok(None);
        };
        Ok(Some(VisibilityByChunk {
            offsets: self.section_array(offsets)?,
            points: self.by_chunk(self.required(SectionKind::VisibilityPoints)?)?,
        }))
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
        assert!(!writes_chunk_checksums([CHUNK_LEN, 3].into_iter()));
        assert!(writes_chunk_checksums([CHUNK_LEN + 1].into_iter()));
    }
}
