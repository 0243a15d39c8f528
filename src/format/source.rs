//! Maps whose bytes are not in memory: a [`RangeSource`] reads byte ranges of the object
//! (an HTTP or S3 object in the `remote` module, anything else a caller implements), and
//! [`Map::open_source`](super::Map::open_source) reads only the header, the index and the
//! sections that are used. The reader needs no network code for it.

use super::error::Error;
use super::layout::{
    align_up, checksum, Header, CHUNK_LEN, HEADER_LEN, MAX_ENTRY_LEN, MAX_SECTIONS,
    METADATA_MAX_BYTES,
};
use super::reader::{Decoded, Section};
use std::ops::Range;
use std::sync::OnceLock;

/// One section a [`Map`](super::Map) wants from its source: the byte range to read (the
/// section's stored bytes, preceded by the zero padding before it) and what the bytes must be.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Wanted {
    /// Position in the section table (a cache key, with the index checksum).
    pub index: usize,
    /// Bytes to read: `padding_start..offset + stored_len`.
    pub range: Range<u64>,
    /// Where the section's stored bytes start (`range.start` up to it is padding).
    pub offset: u64,
    /// XXH3-64 of the stored bytes, from the map's table.
    pub checksum: u64,
}

impl Wanted {
    /// Whether `bytes`, read for this request, are what the table says: the right length,
    /// zero padding, and the checksum. A source uses it to keep damaged bytes out of a cache.
    pub fn matches(&self, bytes: &[u8]) -> bool {
        let Some(pad) = self.offset.checked_sub(self.range.start) else {
            return false;
        };
        let (Some(padding), Some(stored)) = (bytes.get(..pad as usize), bytes.get(pad as usize..))
        else {
            return false;
        };
        Some(bytes.len() as u64) == self.range.end.checked_sub(self.range.start)
            && padding.iter().all(|&b| b == 0)
            && checksum(stored) == self.checksum
    }
}

/// Where the bytes of a map come from when they are read by range. `Send + Sync`: a map
/// opened on a source is shared between threads like any other.
pub trait RangeSource: Send + Sync {
    /// What the user named (a URL), for errors.
    fn name(&self) -> &str;

    /// The object's length in bytes.
    fn len(&self) -> u64;

    /// Whether the object is empty.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes `range` of the object, exactly (`range` lies within [`RangeSource::len`]).
    fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, Error>;

    /// The bytes of each wanted section, in order, each exactly `range` long. A source may
    /// serve them from a cache, merge neighbouring ranges into one request, and keep what it
    /// read (when [`Wanted::matches`] holds). `fresh`: the map found the bytes it had been
    /// given damaged; read from the origin, not a cache. `index_checksum` identifies the
    /// map's content (the header's checksum over header, table and metadata).
    fn read_sections(
        &self,
        index_checksum: u64,
        wanted: &[Wanted],
        fresh: bool,
    ) -> Result<Vec<Vec<u8>>, Error>;

    /// What reading has cost so far.
    fn stats(&self) -> SourceStats {
        SourceStats::default()
    }
}

/// What a [`RangeSource`] has read: from the origin, and from its cache. Non-exhaustive: a
/// source of its own starts from `SourceStats::default()` and sets the fields it counts.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
#[non_exhaustive]
pub struct SourceStats {
    /// Requests sent to the origin.
    pub requests: u64,
    /// Body bytes received from the origin.
    pub bytes: u64,
    /// Sections served from the cache.
    pub cache_hits: u64,
    /// Bytes served from the cache.
    pub cache_bytes: u64,
    /// Sections read again from the origin because the bytes first read were damaged.
    pub refetched: u64,
    /// The origin ignored range requests, so the whole object was read once.
    pub whole_object: bool,
    /// Folders of the on-disk cache found to be symbolic links, not folders, another user's,
    /// or writable by group or others, and left alone, never followed or written in; when
    /// the URL's own folder (or `remote-sections`) is one, its sections are not cached.
    pub cache_links_skipped: u64,
}

/// Ranges closer than this are read as one request (the bytes between are read and dropped):
/// one round trip costs more than this many bytes on any link a map is read over.
#[cfg(any(feature = "remote", feature = "fuzzing", test))]
pub const COALESCE_GAP: u64 = 64 << 10;

/// Groups sorted `wanted` into runs that one ranged read can serve: each run is the range
/// covering it and the positions of its members.
#[cfg(any(feature = "remote", test))]
pub fn coalesce(wanted: &[&Wanted]) -> Vec<(Range<u64>, Vec<usize>)> {
    let mut order: Vec<usize> = (0..wanted.len()).collect();
    order.sort_by_key(|&i| wanted[i].range.start);
    let mut runs: Vec<(Range<u64>, Vec<usize>)> = Vec::new();
    for i in order {
        let r = &wanted[i].range;
        match runs.last_mut() {
            Some((run, members)) if r.start <= run.end.saturating_add(COALESCE_GAP) => {
                run.end = run.end.max(r.end);
                members.push(i);
            }
            _ => runs.push((r.clone(), vec![i])),
        }
    }
    runs
}

/// How much of a map [`Map::open_source`](super::Map::open_source) reads first: the header, a table of ~1,000 sections
/// and the metadata of most maps.
pub const HEAD_READ: u64 = 64 << 10;

/// Where the index of a map whose first bytes are `head` ends, padding to the first section
/// included, capped by the named limits and the file: what `open_source` must have read.
pub(super) fn index_end(head: &[u8], file_len: u64) -> Result<u64, Error> {
    let header = Header::decode(head)?;
    let table = u64::from(header.section_count.min(MAX_SECTIONS))
        * u64::from(header.entry_len.min(MAX_ENTRY_LEN));
    let end = HEADER_LEN as u64 + table + header.metadata_len.min(METADATA_MAX_BYTES);
    Ok(align_up(end).unwrap_or(end).min(file_len))
}

/// Reads `sections` from `source`, checks each (length, padding, checksum), reads the
/// damaged ones once more from the origin, and keeps them.
pub(super) fn fetch(
    source: &dyn RangeSource,
    fetched: &[OnceLock<Decoded>],
    index_checksum: u64,
    sections: &[&Section],
) -> Result<(), Error> {
    let got = read_checked(source, index_checksum, sections)?;
    // Consumed one by one: each read buffer goes once its aligned copy is kept.
    for (section, (want, bytes)) in sections.iter().zip(got) {
        keep(&fetched[section.index], &want, &bytes);
    }
    Ok(())
}

/// The bytes `verify` holds at most of one batch of neighbouring sections it reads from a
/// source (a larger section is read alone): the map is checked a batch at a time, in few
/// requests, never held whole.
pub(super) const VERIFY_BATCH: u64 = 32 << 20;

/// A skipped section longer than this is checked by `verify` without being held: read and
/// hashed in pieces of this many bytes (a multiple of [`CHUNK_LEN`]).
pub(super) const VERIFY_PIECE: u64 = 16 << 20;
const _: () = assert!(VERIFY_PIECE % CHUNK_LEN == 0);

/// Reads `sections` from `source` and checks each (length, padding, checksum), reading the
/// damaged ones once more from the origin: each one's request and bytes as read (the
/// padding first), in order.
pub(super) fn read_checked(
    source: &dyn RangeSource,
    index_checksum: u64,
    sections: &[&Section],
) -> Result<Vec<(Wanted, Vec<u8>)>, Error> {
    if sections.is_empty() {
        return Ok(Vec::new());
    }
    let wanted: Vec<Wanted> = sections
        .iter()
        .map(|s| Wanted {
            index: s.index,
            range: s.padding_start..s.offset + s.stored_len,
            offset: s.offset,
            checksum: s.checksum,
        })
        .collect();
    let got = source.read_sections(index_checksum, &wanted, false)?;
    check_count(source, &got, &wanted)?;
    let mut out: Vec<(Wanted, Vec<u8>)> = wanted.into_iter().zip(got).collect();
    let damaged: Vec<usize> = (0..out.len())
        .filter(|&i| !out[i].0.matches(&out[i].1))
        .collect();
    if damaged.is_empty() {
        return Ok(out);
    }
    let again: Vec<Wanted> = damaged.iter().map(|&i| out[i].0.clone()).collect();
    let got = source.read_sections(index_checksum, &again, true)?;
    check_count(source, &got, &again)?;
    for (&i, bytes) in damaged.iter().zip(got) {
        let (section, want) = (sections[i], &out[i].0);
        if !want.matches(&bytes) {
            return Err(mismatch(source, section, want, &bytes));
        }
        out[i].1 = bytes;
    }
    Ok(out)
}

/// What is wrong with `bytes`, read for `want`, which do not match it.
fn mismatch(source: &dyn RangeSource, section: &Section, want: &Wanted, bytes: &[u8]) -> Error {
    let len = want.range.end - want.range.start;
    if bytes.len() as u64 != len {
        return Error::Io {
            path: source.name().into(),
            message: format!(
                "{}: the source returned {} bytes for a range of {len}",
                section.reference(),
                bytes.len()
            ),
        };
    }
    let pad = (want.offset - want.range.start) as usize;
    if bytes[..pad].iter().any(|&b| b != 0) {
        return Error::BadPadding {
            offset: want.range.start,
            len: pad as u64,
        };
    }
    Error::ChecksumMismatch {
        section: section.reference(),
        expected: section.checksum,
        found: checksum(&bytes[pad..]),
    }
}

/// Reads `section`'s padding and stored bytes from `source` a [`VERIFY_PIECE`] at a time,
/// handing each piece of the stored bytes to `piece` with its position in them; only one
/// piece is held. Non-zero padding is an error.
pub(super) fn read_in_pieces(
    source: &dyn RangeSource,
    section: &Section,
    mut piece: impl FnMut(u64, &[u8]) -> Result<(), Error>,
) -> Result<(), Error> {
    let mut at = 0u64;
    let mut first = true;
    while first || at < section.stored_len {
        let end = section.stored_len.min(at.saturating_add(VERIFY_PIECE));
        let from = if first {
            section.padding_start
        } else {
            section.offset + at
        };
        let bytes = source.read_range(from..section.offset + end)?;
        let expected = section.offset + end - from;
        if bytes.len() as u64 != expected {
            return Err(Error::Io {
                path: source.name().into(),
                message: format!(
                    "{}: the source returned {} bytes for a range of {expected}",
                    section.reference(),
                    bytes.len()
                ),
            });
        }
        // Only the first piece starts at the padding.
        let pad = section.offset.saturating_sub(from) as usize;
        if bytes[..pad].iter().any(|&b| b != 0) {
            return Err(Error::BadPadding {
                offset: from,
                len: pad as u64,
            });
        }
        piece(at, &bytes[pad..])?;
        at = end;
        first = false;
    }
    Ok(())
}

/// A source must answer every wanted section (a short answer would leave one unfetched).
fn check_count(source: &dyn RangeSource, got: &[Vec<u8>], wanted: &[Wanted]) -> Result<(), Error> {
    if got.len() == wanted.len() {
        return Ok(());
    }
    Err(Error::Io {
        path: source.name().into(),
        message: format!(
            "the source answered {} of {} section reads",
            got.len(),
            wanted.len()
        ),
    })
}

/// Keeps a fetched section's stored bytes (the padding before them dropped); a second thread
/// that fetched the same section meanwhile keeps the first copy.
pub(super) fn keep(slot: &OnceLock<Decoded>, want: &Wanted, bytes: &[u8]) {
    let pad = (want.offset - want.range.start) as usize;
    let _ = slot.get_or_init(|| Decoded::aligned(&bytes[pad..]));
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wanted(index: usize, range: Range<u64>) -> Wanted {
        Wanted {
            index,
            offset: range.start,
            range,
            checksum: 0,
        }
    }

    /// Bytes in memory, recording the longest range asked of it in one read.
    struct Recording {
        bytes: Vec<u8>,
        longest: std::sync::Arc<std::sync::atomic::AtomicU64>,
    }

    impl RangeSource for Recording {
        fn name(&self) -> &str {
            "memory"
        }
        fn len(&self) -> u64 {
            self.bytes.len() as u64
        }
        fn read_range(&self, range: Range<u64>) -> Result<Vec<u8>, Error> {
            let len = range.end - range.start;
            self.longest
                .fetch_max(len, std::sync::atomic::Ordering::Relaxed);
            Ok(self.bytes[range.start as usize..range.end as usize].to_vec())
        }
        fn read_sections(&self, _: u64, wanted: &[Wanted], _: bool) -> Result<Vec<Vec<u8>>, Error> {
            wanted
                .iter()
                .map(|w| self.read_range(w.range.clone()))
                .collect()
        }
    }

    #[test]
    fn verify_by_range_reads_a_large_skipped_section_in_pieces() {
        use crate::format::{Codec, Dtype, MapWriter, SectionKind};
        let len = 2 * VERIFY_PIECE as usize + 1000;
        let unknown: Vec<u8> = (0..len).map(|i| (i % 251) as u8).collect();
        let mut w = MapWriter::default();
        w.set_points_world(&[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]);
        w.add_raw_section(
            SectionKind::Unknown(0x7F10),
            crate::format::layout::NO_LEVEL,
            Dtype::U8,
            len as u64,
            1,
            false,
            std::borrow::Cow::Borrowed(&unknown),
            Some(Codec::Raw),
        )
        .unwrap();
        let bytes = w.to_bytes().unwrap();
        let verify = |bytes: Vec<u8>| {
            let longest = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
            let source = Recording {
                bytes,
                longest: longest.clone(),
            };
            let map = crate::format::Map::open_source(Box::new(source)).unwrap();
            let verified = map.verify();
            (verified, longest.load(std::sync::atomic::Ordering::Relaxed))
        };
        let (verified, longest) = verify(bytes.clone());
        verified.unwrap();
        // One piece (and the padding before the first) at a time, never the section.
        assert!(longest <= VERIFY_PIECE + 64, "{longest}");
        // A byte changed in the second piece is found.
        let map = crate::format::Map::from_bytes(&bytes).unwrap();
        let s = *map.skipped_sections().next().unwrap();
        let mut damaged = bytes.clone();
        damaged[(s.offset + VERIFY_PIECE + 5) as usize] ^= 1;
        let (verified, _) = verify(damaged);
        assert!(
            matches!(verified, Err(Error::ChecksumMismatch { .. })),
            "{verified:?}"
        );
    }

    #[test]
    fn neighbours_merge_and_far_ranges_do_not() {
        let a = wanted(0, 0..100);
        let b = wanted(1, 128..200);
        let c = wanted(2, 200 + COALESCE_GAP + 1..300 + COALESCE_GAP);
        let runs = coalesce(&[&c, &a, &b]);
        assert_eq!(runs.len(), 2);
        assert_eq!(runs[0], (0..200, vec![1, 2]));
        assert_eq!(runs[1].1, vec![0]);
    }

    #[test]
    fn matches_checks_length_padding_and_checksum() {
        let data = b"section bytes";
        let mut bytes = vec![0u8; 3];
        bytes.extend_from_slice(data);
        let w = Wanted {
            index: 0,
            range: 10..10 + bytes.len() as u64,
            offset: 13,
            checksum: checksum(data),
        };
        assert!(w.matches(&bytes));
        let mut padded = bytes.clone();
        padded[1] = 1;
        assert!(!w.matches(&padded));
        let mut flipped = bytes.clone();
        flipped[5] ^= 1;
        assert!(!w.matches(&flipped));
        assert!(!w.matches(&bytes[1..]));
    }
}
