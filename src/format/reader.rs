//! `Map`: opens a map from a file (mmap) or from bytes, validates its index once, and hands
//! out sections. Section bytes are checksummed (and decoded, and their contents checked) on
//! first access; `verify` does that for all of them. Every zstd decode is charged to one
//! budget per open map (`decode_budget`), so no file makes a reader decode without bound.

use super::error::{Error, SectionRef};
use super::layout::{
    align_up, checksum, index_checksum, Codec, Dtype, Header, RawEntry, SectionKind, ALIGN,
    ENTRY_LEN, FEATURE_DELTA, HEADER_FEATURES_KNOWN, HEADER_LEN, MAX_DESCRIPTOR_DIM, MAX_ENTRY_LEN,
    MAX_SECTIONS, METADATA_MAX_BYTES, NO_LEVEL, SECTION_FLAGS_KNOWN, SECTION_REQUIRED,
};
use super::metadata::Metadata;
use super::source::{
    fetch, index_end, keep as keep_fetched, read_checked, read_in_pieces, RangeSource, HEAD_READ,
    VERIFY_BATCH, VERIFY_PIECE,
};
use std::borrow::Cow;
use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::OnceLock;

mod verify;

/// A validated section-table entry; fields through its accessors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Section {
    /// Position in the section table.
    pub(crate) index: usize,
    pub(crate) kind: SectionKind,
    /// The level for per-level kinds, `None` otherwise.
    pub(crate) level: Option<u16>,
    pub(crate) dtype: Dtype,
    pub(crate) codec: Codec,
    pub(crate) required: bool,
    pub(crate) rows: u64,
    pub(crate) cols: u64,
    pub(crate) offset: u64,
    pub(crate) stored_len: u64,
    pub(crate) raw_len: u64,
    pub(crate) checksum: u64,
    /// Why this reader skips the section (optional sections only), `None` if it reads it.
    pub(crate) skipped: Option<Skipped>,
    /// Where the zero padding before the section starts (the previous region's end).
    pub(crate) padding_start: u64,
}

/// Why a reader skips an optional section: it does not know its kind, or (1.1) it cannot
/// decode it. A skipped section is not used, `verify` checks only its checksum (and decodes a
/// skipped kind's zstd bytes, within the budget), and `slice` drops it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Skipped {
    /// A kind this reader does not know.
    Kind,
    /// A dtype code this reader does not know.
    Dtype(u8),
    /// A codec code this reader does not know.
    Codec(u8),
    /// Section flag bits this reader does not know (the unknown bits).
    Flags(u8),
}

impl Skipped {
    /// Whether the reader cannot tell what the stored bytes decode to (so it hands none out).
    pub fn hides_encoding(self) -> bool {
        !matches!(self, Skipped::Kind)
    }
}

impl std::fmt::Display for Skipped {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Skipped::Kind => f.write_str("unknown kind"),
            Skipped::Dtype(code) => write!(f, "unknown dtype code {code}"),
            Skipped::Codec(code) => write!(f, "unknown codec code {code}"),
            Skipped::Flags(bits) => write!(f, "unknown section flags 0x{bits:02x}"),
        }
    }
}

/// Read-only: a `Section` comes only from a map's validated table, so the byte ranges and
/// lengths the reader trusts cannot be forged.
impl Section {
    /// Position in the section table.
    pub fn index(&self) -> usize {
        self.index
    }

    /// What the section holds.
    pub fn kind(&self) -> SectionKind {
        self.kind
    }

    /// The level for per-level kinds, `None` otherwise.
    pub fn level(&self) -> Option<u16> {
        self.level
    }

    /// Element type. For a section [skipped](Section::skipped) for its dtype, `U8` (its
    /// bytes; the code is in [`Skipped::Dtype`]).
    pub fn dtype(&self) -> Dtype {
        self.dtype
    }

    /// How the bytes are stored (raw or zstd). For a section [skipped](Section::skipped) for
    /// its codec, `Raw` (the code is in [`Skipped::Codec`]).
    pub fn codec(&self) -> Codec {
        self.codec
    }

    /// Why the reader skips this optional section, `None` when it reads it.
    pub fn skipped(&self) -> Option<Skipped> {
        self.skipped
    }

    /// Whether a reader must understand the section to use the map.
    pub fn required(&self) -> bool {
        self.required
    }

    /// Rows (elements for 1-D sections).
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// Columns (1 for 1-D sections).
    pub fn cols(&self) -> u64 {
        self.cols
    }

    /// Byte offset of the stored bytes in the file.
    pub fn offset(&self) -> u64 {
        self.offset
    }

    /// Stored bytes (compressed for zstd).
    pub fn stored_len(&self) -> u64 {
        self.stored_len
    }

    /// Bytes once decoded.
    pub fn raw_len(&self) -> u64 {
        self.raw_len
    }

    /// XXH3-64 of the stored bytes.
    pub fn checksum(&self) -> u64 {
        self.checksum
    }

    /// How errors name this section.
    pub fn reference(&self) -> SectionRef {
        SectionRef {
            index: self.index,
            kind: self.kind,
            level: self.level,
        }
    }
}

enum Backing<'a> {
    Mmap(memmap2::Mmap),
    Borrowed(&'a [u8]),
    /// Read by range: each section's stored bytes once fetched and checked.
    Source {
        source: Box<dyn RangeSource>,
        fetched: Vec<OnceLock<Decoded>>,
    },
}

/// Decoded bytes of a zstd section (or a fetched section's stored bytes), held in `u64`s so
/// every dtype casts aligned.
pub(super) struct Decoded {
    words: Vec<u64>,
    len: usize,
}

impl Decoded {
    pub(super) fn bytes(&self) -> &[u8] {
        &bytemuck::cast_slice(&self.words)[..self.len]
    }

    /// A copy of `bytes` in `u64`s, so every dtype casts aligned.
    pub(super) fn aligned(bytes: &[u8]) -> Decoded {
        let mut words = vec![0u64; bytes.len().div_ceil(8)];
        bytemuck::cast_slice_mut::<u64, u8>(&mut words)[..bytes.len()].copy_from_slice(bytes);
        Decoded {
            words,
            len: bytes.len(),
        }
    }
}

/// Table positions by (kind, level), built once at open: every lookup is O(1), so nothing
/// that walks the levels is quadratic in them.
#[derive(Debug, Default)]
pub(crate) struct SectionIndex(HashMap<(SectionKind, Option<u16>), usize>);

impl SectionIndex {
    /// Fails on the first (kind, level) pair seen twice.
    pub(crate) fn build(sections: &[Section]) -> Result<SectionIndex, Error> {
        let mut index = HashMap::with_capacity(sections.len());
        for s in sections {
            if index.insert((s.kind, s.level), s.index).is_some() {
                return Err(Error::DuplicateSection {
                    section: s.reference(),
                });
            }
        }
        Ok(SectionIndex(index))
    }

    pub(crate) fn get<'s>(
        &self,
        sections: &'s [Section],
        kind: SectionKind,
        level: Option<u16>,
    ) -> Option<&'s Section> {
        // Every entry counts for duplicates; a skipped one is absent to everything else.
        self.0
            .get(&(kind, level))
            .map(|&i| &sections[i])
            .filter(|s| s.skipped.is_none())
    }
}

/// An open map. Cheap to open whatever its size: only the header, the section table and the
/// metadata are read and checked. `Send + Sync`: share one `Map` between threads.
pub struct Map<'a> {
    backing: Backing<'a>,
    header: Header,
    metadata: Metadata,
    sections: Vec<Section>,
    index: SectionIndex,
    /// Per section: `Ok(None)` once checked (raw), `Ok(Some)` once checked and decoded (zstd).
    ready: Vec<OnceLock<Result<Option<Decoded>, Error>>>,
    /// Per section: checked by `verify` without keeping its decoded bytes.
    checked: Vec<AtomicBool>,
    /// Bytes decoded from zstd sections so far, against `decode_budget(file_len)`.
    decoded: AtomicU64,
    /// (1.2) Chunk checksums, when the map has them: which chunks were checked.
    chunks: Option<super::chunks::ChunkIndex>,
    n_points: u64,
    n_images: u64,
}

impl std::fmt::Debug for Map<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Map")
            .field("version", &self.version())
            .field("file_len", &self.file_len())
            .field("points", &self.n_points)
            .field("images", &self.n_images)
            .field("sections", &self.sections.len())
            .finish()
    }
}

impl Map<'static> {
    /// Memory-maps and validates the map at `path`. Errors name the path.
    pub fn open(path: impl AsRef<Path>) -> Result<Map<'static>, Error> {
        let path = path.as_ref();
        let file = super::mmap::open_regular(path)?;
        let mmap = super::mmap::map_file(&file).map_err(|e| Error::io(path, e))?;
        Map::from_backing(Backing::Mmap(mmap))
    }
}

impl Map<'static> {
    /// Opens a map read by range from `source` (an object in storage): one read of the
    /// first [`HEAD_READ`] bytes holds the header and, usually, the whole index; a second
    /// reads the rest of a longer index. Sections are fetched on first access, or together
    /// by [`Map::prefetch`], and checked against their checksums before use.
    pub fn open_source(source: Box<dyn RangeSource>) -> Result<Map<'static>, Error> {
        let file_len = source.len();
        let mut head = source.read_range(0..file_len.min(HEAD_READ))?;
        let index_end = index_end(&head, file_len)?;
        if index_end > head.len() as u64 {
            head.extend(source.read_range(head.len() as u64..index_end)?);
        }
        let index = validate_index(&head, file_len)?;
        let fetched = (0..index.sections.len()).map(|_| OnceLock::new()).collect();
        Map::from_index(index, Backing::Source { source, fetched })
    }
}

impl<'a> Map<'a> {
    /// Validates a map held in memory, borrowing it (no copy).
    pub fn from_bytes(bytes: &'a [u8]) -> Result<Map<'a>, Error> {
        Map::from_backing(Backing::Borrowed(bytes))
    }

    fn from_backing(backing: Backing<'a>) -> Result<Map<'a>, Error> {
        let bytes: &[u8] = match &backing {
            Backing::Mmap(m) => m,
            Backing::Borrowed(b) => b,
            Backing::Source { .. } => unreachable!("sources open through open_source"),
        };
        let index = validate_index(bytes, bytes.len() as u64)?;
        Map::from_index(index, backing)
    }

    fn from_index(index: Index, backing: Backing<'a>) -> Result<Map<'a>, Error> {
        let n = index.sections.len();
        let chunks = super::chunks::ChunkIndex::new(
            &index.sections,
            index
                .by_kind
                .get(&index.sections, SectionKind::ChunkChecksums, None),
        );
        Ok(Map {
            backing,
            header: index.header,
            metadata: index.metadata,
            sections: index.sections,
            index: index.by_kind,
            ready: (0..n).map(|_| OnceLock::new()).collect(),
            checked: (0..n).map(|_| AtomicBool::new(false)).collect(),
            decoded: AtomicU64::new(0),
            chunks,
            n_points: index.n_points,
            n_images: index.n_images,
        })
    }

    /// The whole file, when it is in memory or mapped (`None` for a map read by range).
    pub fn bytes(&self) -> Option<&[u8]> {
        match &self.backing {
            Backing::Mmap(m) => Some(m),
            Backing::Borrowed(b) => Some(b),
            Backing::Source { .. } => None,
        }
    }

    /// The source of a map opened with [`Map::open_source`].
    pub fn source(&self) -> Option<&dyn RangeSource> {
        match &self.backing {
            Backing::Source { source, .. } => Some(source.as_ref()),
            _ => None,
        }
    }

    /// Fetches, in as few reads as the source allows, the sections `wanted` selects that are
    /// not fetched yet; a no-op for a map in memory. Reading a section fetches it anyway:
    /// this only saves round trips (a command that knows what it reads calls it first).
    /// [Skipped](Section::skipped) sections are never prefetched, whatever `wanted` says:
    /// nothing reads them but [`Map::verify`], which reads them itself, so a map's optional
    /// sections of kinds this reader does not know cost a command that uses the map nothing.
    pub fn prefetch(&self, wanted: impl Fn(&Section) -> bool) -> Result<(), Error> {
        let Backing::Source { source, fetched } = &self.backing else {
            return Ok(());
        };
        let missing: Vec<&Section> = self
            .sections
            .iter()
            .filter(|s| s.skipped.is_none() && fetched[s.index].get().is_none() && wanted(s))
            .collect();
        fetch(
            source.as_ref(),
            fetched,
            self.header.index_checksum,
            &missing,
        )
    }

    /// The raw header (fuzz bodies and tests).
    #[cfg(feature = "fuzzing")]
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// `major.minor` of the file.
    pub fn version(&self) -> String {
        format!("{}.{}", self.header.major, self.header.minor)
    }

    /// The file's length in bytes.
    pub fn file_len(&self) -> u64 {
        self.header.file_len
    }

    /// The header's XXH3-64 over header, table and metadata: identifies the map's content
    /// (every section's checksum is in the table).
    pub fn index_checksum(&self) -> u64 {
        self.header.index_checksum
    }

    /// The metadata block, parsed and checked at open.
    pub fn metadata(&self) -> &Metadata {
        &self.metadata
    }

    /// Every section in the table, in file order, skipped optional ones included.
    pub fn sections(&self) -> &[Section] {
        &self.sections
    }

    /// Optional sections this reader skips: of kinds it does not know, or (1.1) with a dtype,
    /// codec or flag bit it does not know. [`Section::skipped`] says which.
    pub fn skipped_sections(&self) -> impl Iterator<Item = &Section> {
        self.sections.iter().filter(|s| s.skipped.is_some())
    }

    /// Points in the map.
    pub fn n_points(&self) -> u64 {
        self.n_points
    }

    /// Images in the map.
    pub fn n_images(&self) -> u64 {
        self.n_images
    }

    /// The section of `kind` (and `level`), if present. O(1).
    pub fn find(&self, kind: SectionKind, level: Option<u16>) -> Option<&Section> {
        self.index.get(&self.sections, kind, level)
    }

    /// Bytes decoded from zstd sections since open (each decode counts, repeated or not).
    pub fn decoded_bytes(&self) -> u64 {
        self.decoded.load(Ordering::Relaxed)
    }

    /// The most bytes this map may decode from zstd sections: `decode_budget(file_len)`.
    pub fn decode_budget(&self) -> u64 {
        decode_budget(self.file_len())
    }

    /// The stored bytes of one of this map's sections (checked by [`Map::own`]), as they are in
    /// the file (compressed for zstd). Not checksummed: callers that copy them must check or
    /// recompute.
    pub(crate) fn stored_bytes(&self, section: &Section) -> Result<&[u8], Error> {
        match &self.backing {
            Backing::Source { source, fetched } => {
                let slot = &fetched[section.index];
                if slot.get().is_none() {
                    fetch(
                        source.as_ref(),
                        fetched,
                        self.header.index_checksum,
                        &[section],
                    )?;
                }
                Ok(slot.get().expect("fetch kept the section").bytes())
            }
            Backing::Mmap(_) | Backing::Borrowed(_) => {
                let bytes = self.bytes().expect("in memory");
                let start = section.offset as usize;
                Ok(&bytes[start..start + section.stored_len as usize])
            }
        }
    }

    /// (1.2) The map's chunk checksums' state, if it has them.
    pub(crate) fn chunk_index(&self) -> Option<&super::chunks::ChunkIndex> {
        self.chunks.as_ref()
    }

    /// How checking `section` whole (its first access, or `verify`) went, if it was checked.
    pub(crate) fn whole_check(&self, section: &Section) -> Option<Result<(), Error>> {
        if let Some(ready) = self.ready[section.index].get() {
            return Some(ready.as_ref().map(|_| ()).map_err(Error::clone));
        }
        self.checked[section.index]
            .load(Ordering::Acquire)
            .then_some(Ok(()))
    }

    /// [`Map::own`] for the other modules of the reader.
    pub(crate) fn own_section(&self, section: &Section) -> Result<(), Error> {
        self.own(section)
    }

    /// `section` if it is one of this map's, as [`Map::sections`] lists it. A `Section` cannot be
    /// made up outside the reader, but one taken from another map could otherwise index or
    /// slice past what this map holds.
    fn own(&self, section: &Section) -> Result<(), Error> {
        match self.sections.get(section.index) {
            Some(s) if s == section => Ok(()),
            _ => Err(Error::invalid(format!(
                "{} is not a section of this map",
                section.reference()
            ))),
        }
    }

    /// The decoded bytes of a section, checked (checksum, length, contents) on first access.
    pub fn section_bytes(&self, section: &Section) -> Result<&[u8], Error> {
        self.own(section)?;
        if let Some(why) = section.skipped.filter(|s| s.hides_encoding()) {
            return Err(Error::invalid(format!(
                "{} is skipped ({why}): its bytes cannot be decoded",
                section.reference()
            )));
        }
        // Fetched first (read by range), so a failed read is not kept as the section's
        // outcome: the next access reads again.
        if self.ready[section.index].get().is_none() {
            self.stored_bytes(section)?;
        }
        let ready = self.ready[section.index].get_or_init(|| self.prepare(section));
        match ready {
            Ok(None) => self.stored_bytes(section),
            Ok(Some(decoded)) => Ok(decoded.bytes()),
            Err(e) => Err(e.clone()),
        }
    }

    /// A section's array as `T` (which must match its dtype in size), borrowed from the
    /// mapping when aligned, copied when the caller's buffer is not.
    pub fn section_array<T: bytemuck::Pod>(
        &self,
        section: &Section,
    ) -> Result<Cow<'_, [T]>, Error> {
        let bytes = self.section_bytes(section)?;
        Ok(cast(bytes))
    }

    /// Checks one section as its first access would (checksum, decoding, contents) without
    /// keeping the decoded bytes of a zstd section; free once the section was checked.
    pub fn check_section(&self, section: &Section) -> Result<(), Error> {
        self.own(section)?;
        if let Some(ready) = self.ready[section.index].get() {
            return ready.as_ref().map(|_| ()).map_err(Error::clone);
        }
        if self.checked[section.index].load(Ordering::Acquire) {
            return Ok(());
        }
        match section.codec {
            // Skipped for its encoding: only the checksum can be checked.
            _ if section.skipped.is_some_and(|s| s.hides_encoding()) => {
                self.prepare(section)?;
                self.checked[section.index].store(true, Ordering::Release);
                Ok(())
            }
            // Keeping a raw section costs nothing: it is a view of the bytes.
            Codec::Raw => self.section_bytes(section).map(|_| ()),
            Codec::Zstd | Codec::Delta => {
                self.prepare(section)?;
                self.checked[section.index].store(true, Ordering::Release);
                Ok(())
            }
        }
    }

    /// Charges `section`'s decoded length to the budget, before anything is allocated.
    fn charge(&self, section: &Section) -> Result<(), Error> {
        let budget = self.decode_budget();
        self.decoded
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |d| {
                d.checked_add(section.raw_len)
                    .filter(|&total| total <= budget)
            })
            .map(|_| ())
            .map_err(|decoded| Error::DecodeBudgetExceeded {
                section: section.reference(),
                raw_len: section.raw_len,
                decoded,
                budget,
            })
    }

    fn prepare(&self, section: &Section) -> Result<Option<Decoded>, Error> {
        self.prepare_from(section, self.stored_bytes(section)?)
    }

    /// [`Map::prepare`] of `stored`, the section's stored bytes as read (by `verify`, without
    /// keeping them).
    fn prepare_from(&self, section: &Section, stored: &[u8]) -> Result<Option<Decoded>, Error> {
        let found = checksum(stored);
        if found != section.checksum {
            return Err(Error::ChecksumMismatch {
                section: section.reference(),
                expected: section.checksum,
                found,
            });
        }
        if section.skipped.is_some_and(|s| s.hides_encoding()) {
            return Ok(None);
        }
        let decoded = match section.codec {
            Codec::Raw => None,
            codec @ (Codec::Zstd | Codec::Delta) => {
                check_decode_cap(section, self.file_len())?;
                // Read by range, the file length is what the server claims: each section
                // must also keep to the writer's ratio of the bytes actually read, so what
                // is decoded is bounded by what was downloaded.
                if matches!(self.backing, Backing::Source { .. })
                    && !within_decode_ratio(section.raw_len, section.stored_len)
                {
                    return Err(Error::DecodedTooLarge {
                        section: section.reference(),
                        raw_len: section.raw_len,
                        cap: section.stored_len.saturating_mul(DECODE_RATIO),
                    });
                }
                self.charge(section)?;
                Some(match codec {
                    Codec::Delta => decode_delta(section, stored)?,
                    _ => decode_zstd(section, stored)?,
                })
            }
        };
        let bytes = decoded.as_ref().map_or(stored, |d| d.bytes());
        super::views::check_contents(self, section, bytes)?;
        Ok(decoded)
    }
}

/// The cap on a zstd section's declared raw length, derived from the file length, so a
/// forged length cannot make the reader allocate without bound. The writer stores a
/// section raw rather than exceed it.
pub fn decode_cap(file_len: u64) -> u64 {
    file_len.saturating_mul(DECODE_RATIO).max(1 << 20)
}

/// The cap on the bytes one open map decodes from zstd sections, all decodes together:
/// `max(256 × file_len, 64 MiB)`. Many sections each under [`decode_cap`] cannot add up past
/// it, so decoding time and memory are linear in the file length. The writer's per-section
/// rule keeps every map it writes within it (each section decoded once).
pub fn decode_budget(file_len: u64) -> u64 {
    file_len.saturating_mul(DECODE_RATIO).max(64 << 20)
}

/// The decoded : stored ratio both caps allow (see spec/format.md, "Codecs").
pub(crate) const DECODE_RATIO: u64 = 256;

/// Whether a zstd section of `stored_len` bytes decoding to `raw_len` keeps to the ratio the
/// writer keeps every section to, so that the sum over a file's sections stays within
/// [`decode_budget`] (and each within [`decode_cap`]) of the file they are written to.
pub(crate) fn within_decode_ratio(raw_len: u64, stored_len: u64) -> bool {
    raw_len <= stored_len.saturating_mul(DECODE_RATIO)
}

fn check_decode_cap(section: &Section, file_len: u64) -> Result<(), Error> {
    let cap = decode_cap(file_len);
    if section.raw_len > cap {
        return Err(Error::DecodedTooLarge {
            section: section.reference(),
            raw_len: section.raw_len,
            cap,
        });
    }
    Ok(())
}

/// Decodes one frame of exactly `raw_len` bytes; the caller checked the caps.
fn decode_zstd(section: &Section, stored: &[u8]) -> Result<Decoded, Error> {
    let len = section.raw_len as usize;
    let mut words = vec![0u64; len.div_ceil(8)];
    let out: &mut [u8] = &mut bytemuck::cast_slice_mut(&mut words)[..len];
    let decode_err = |message: String| Error::Decode {
        section: section.reference(),
        message,
    };
    // A single frame that fills `out` exactly; `decompress_to_buffer` errors if the frame
    // is larger than `out`, and we check it is not smaller.
    let written =
        zstd::bulk::decompress_to_buffer(stored, out).map_err(|e| decode_err(e.to_string()))?;
    if written != len {
        return Err(decode_err(format!(
            "decoded {written} bytes, the table declares {len}"
        )));
    }
    Ok(Decoded { words, len })
}

/// Decodes a `delta` section (`delta::decompress`) into `raw_len` bytes.
fn decode_delta(section: &Section, stored: &[u8]) -> Result<Decoded, Error> {
    let decode_err = |message: String| Error::Decode {
        section: section.reference(),
        message,
    };
    let len = section.raw_len as usize;
    let mut words = vec![0u64; len.div_ceil(8)];
    let out: &mut [u8] = &mut bytemuck::cast_slice_mut(&mut words)[..len];
    super::delta::decompress(section.dtype, stored, out).map_err(decode_err)?;
    Ok(Decoded { words, len })
}

/// Casts bytes to `T`s without copying when aligned; copies otherwise (never UB).
pub(crate) fn cast<T: bytemuck::Pod>(bytes: &[u8]) -> Cow<'_, [T]> {
    match bytemuck::try_cast_slice(bytes) {
        Ok(slice) => Cow::Borrowed(slice),
        Err(_) => Cow::Owned(bytemuck::pod_collect_to_vec(bytes)),
    }
}

struct Index {
    header: Header,
    metadata: Metadata,
    sections: Vec<Section>,
    by_kind: SectionIndex,
    n_points: u64,
    n_images: u64,
}

/// Everything `open` checks: the header, table bounds, each entry, exact tiling with zero
/// padding, the index checksum, the metadata and the sections' shapes against each other.
/// `bytes` is the file, or (read by range) its first bytes through the padding before the
/// first section; `file_len` the whole file's length.
fn validate_index(bytes: &[u8], file_len: u64) -> Result<Index, Error> {
    let header = Header::decode(bytes)?;
    if file_len < header.file_len {
        return Err(Error::Truncated {
            what: "file",
            needed: header.file_len,
            file_len,
        });
    }
    if file_len > header.file_len {
        return Err(Error::TrailingBytes {
            expected: header.file_len,
            file_len,
        });
    }
    if header.section_count > MAX_SECTIONS {
        return Err(Error::BadIndex {
            what: "section count over the cap of 65536",
        });
    }
    if (header.entry_len as usize) < ENTRY_LEN
        || header.entry_len > MAX_ENTRY_LEN
        || header.entry_len % 8 != 0
    {
        return Err(Error::BadIndex {
            what: "section entry length is not a multiple of 8 between 64 and 1024",
        });
    }
    // Both factors are capped above, so this cannot overflow.
    let table_end =
        HEADER_LEN as u64 + u64::from(header.section_count) * u64::from(header.entry_len);
    if table_end > bytes.len() as u64 {
        return Err(Error::Truncated {
            what: "section table",
            needed: table_end,
            file_len,
        });
    }
    if header.metadata_offset != table_end {
        return Err(Error::BadIndex {
            what: "metadata does not start right after the section table",
        });
    }
    if header.metadata_len > METADATA_MAX_BYTES {
        return Err(Error::MetadataTooLarge {
            len: header.metadata_len,
            max: METADATA_MAX_BYTES,
        });
    }
    let metadata_end = table_end + header.metadata_len;
    if metadata_end > bytes.len() as u64 {
        return Err(Error::Truncated {
            what: "metadata",
            needed: metadata_end,
            file_len,
        });
    }
    let table = &bytes[HEADER_LEN..table_end as usize];
    let metadata_bytes = &bytes[table_end as usize..metadata_end as usize];
    let found = index_checksum(&bytes[..56], table, metadata_bytes);
    if found != header.index_checksum {
        return Err(Error::IndexChecksumMismatch {
            expected: header.index_checksum,
            found,
        });
    }
    // 1.1: header flags are required features (1.0 writers wrote 0, so no 1.0 file has one).
    let unknown_features = header.flags & !HEADER_FEATURES_KNOWN;
    if unknown_features != 0 {
        return Err(Error::UnknownRequiredFeature {
            bits: unknown_features,
        });
    }
    let metadata: Metadata =
        serde_json::from_slice(metadata_bytes).map_err(|e| Error::BadMetadata {
            message: e.to_string(),
        })?;

    let mut sections = Vec::with_capacity(header.section_count as usize);
    for (index, entry_bytes) in table.chunks_exact(header.entry_len as usize).enumerate() {
        let raw = RawEntry::decode(&entry_bytes[..ENTRY_LEN]);
        sections.push(validate_entry(index, &raw, file_len, header.flags)?);
    }
    check_tiling(bytes, file_len, &mut sections, metadata_end)?;
    check_declared_sizes(&sections, file_len)?;

    let (by_kind, n_points, n_images) = super::views::check_shapes(&metadata, &sections)?;
    Ok(Index {
        header,
        metadata,
        sections,
        by_kind,
        n_points,
        n_images,
    })
}

fn validate_entry(
    index: usize,
    raw: &RawEntry,
    file_len: u64,
    features: u64,
) -> Result<Section, Error> {
    let kind = SectionKind::from_code(raw.kind);
    let reference = SectionRef {
        index,
        kind,
        level: (raw.level != NO_LEVEL).then_some(raw.level),
    };
    let bad = |what: String| Error::BadEntry {
        section: reference,
        what,
    };
    if raw.reserved != 0 || raw.reserved2 != 0 {
        return Err(bad("reserved fields are not zero".into()));
    }
    let required = raw.flags & SECTION_REQUIRED != 0;
    // A level_pq_order a reader skipped would silently leave the codes in the wrong
    // dimensions, so the spec makes it required (and a 1.0 reader refuses it).
    if kind == SectionKind::LevelPqOrder && !required {
        return Err(bad("level_pq_order must be flagged required".into()));
    }
    // 1.1: an optional section this reader cannot decode is skipped; a required one keeps the
    // encodings this reader knows (header features aside), so its unknown code is an error.
    let unknown_flags = raw.flags & !SECTION_FLAGS_KNOWN;
    let encoding = match (Dtype::from_code(raw.dtype), Codec::from_code(raw.codec)) {
        (None, _) => Err(Skipped::Dtype(raw.dtype)),
        (_, None) => Err(Skipped::Codec(raw.codec)),
        _ if unknown_flags != 0 => Err(Skipped::Flags(unknown_flags)),
        (Some(dtype), Some(codec)) => Ok((dtype, codec)),
    };
    let (dtype, codec, skipped) = match encoding {
        Ok((dtype, codec)) => (dtype, codec, None),
        Err(why) if required => return Err(bad(why.to_string())),
        Err(why) => (Dtype::U8, Codec::Raw, Some(why)),
    };
    if skipped.is_none() && codec == Codec::Delta {
        if super::delta::width(dtype).is_none() {
            return Err(bad(format!(
                "codec delta applies to u32 and u64 arrays, not {}",
                dtype.name()
            )));
        }
        if required && features & FEATURE_DELTA == 0 {
            return Err(bad(
                "codec delta in a required section without header feature bit 0 (delta)".into(),
            ));
        }
    }
    if skipped.is_none() {
        let expected_raw = raw
            .rows
            .checked_mul(raw.cols)
            .and_then(|n| n.checked_mul(dtype.size()));
        if expected_raw != Some(raw.raw_len) {
            return Err(Error::SizeMismatch {
                section: reference,
                rows: raw.rows,
                cols: raw.cols,
                raw_len: raw.raw_len,
            });
        }
        if codec == Codec::Raw && raw.stored_len != raw.raw_len {
            return Err(bad(format!(
                "raw section stores {} bytes but its array has {}",
                raw.stored_len, raw.raw_len
            )));
        }
    }
    if raw.offset % ALIGN != 0 {
        return Err(Error::Misaligned {
            section: reference,
            offset: raw.offset,
        });
    }
    match raw.offset.checked_add(raw.stored_len) {
        Some(end) if end <= file_len => {}
        _ => {
            return Err(Error::SectionOutOfBounds {
                section: reference,
                offset: raw.offset,
                len: raw.stored_len,
                file_len,
            })
        }
    }
    let layout = if skipped.is_some() {
        None
    } else {
        kind.expected_layout()
    };
    let skipped = match layout {
        None if required => return Err(Error::UnknownRequiredSection { section: reference }),
        None => skipped.or(Some(Skipped::Kind)),
        Some((want_dtype, want_cols)) => {
            if kind.has_descriptor_columns() && raw.cols > MAX_DESCRIPTOR_DIM {
                return Err(Error::WrongLayout {
                    section: reference,
                    expected: format!("{} x at most {MAX_DESCRIPTOR_DIM}", want_dtype.name()),
                    found: format!("{} x {}", dtype.name(), raw.cols),
                });
            }
            if dtype != want_dtype || want_cols.is_some_and(|c| c != raw.cols) {
                let cols = want_cols.map_or("any".to_string(), |c| c.to_string());
                return Err(Error::WrongLayout {
                    section: reference,
                    expected: format!("{} x {cols}", want_dtype.name()),
                    found: format!("{} x {}", dtype.name(), raw.cols),
                });
            }
            if kind.is_per_level() == (raw.level == NO_LEVEL) {
                return Err(bad(format!(
                    "level field {} is wrong for this kind",
                    raw.level
                )));
            }
            None
        }
    };
    Ok(Section {
        index,
        kind,
        level: reference.level,
        dtype,
        codec,
        required,
        rows: raw.rows,
        cols: raw.cols,
        offset: raw.offset,
        stored_len: raw.stored_len,
        raw_len: raw.raw_len,
        checksum: raw.checksum,
        skipped,
        padding_start: 0,
    })
}

/// The zstd sections of known kinds must, together, declare no more than the decode budget:
/// every count a reader takes from them (points, level points, images) is then bounded by the
/// file length before anything is decoded or sized from it. (Skipped sections are not read;
/// only `verify` decodes those of unknown kinds, within the budget as it goes.)
fn check_declared_sizes(sections: &[Section], file_len: u64) -> Result<(), Error> {
    let budget = decode_budget(file_len);
    let mut declared = 0u64;
    for s in sections {
        if s.codec == Codec::Raw || s.skipped.is_some() {
            continue;
        }
        match declared.checked_add(s.raw_len).filter(|&t| t <= budget) {
            Some(total) => declared = total,
            None => {
                return Err(Error::DecodeBudgetExceeded {
                    section: s.reference(),
                    raw_len: s.raw_len,
                    decoded: declared,
                    budget,
                })
            }
        }
    }
    Ok(())
}

/// Sections follow the metadata in table order, each at the next multiple of 64 after the
/// previous region, with zero bytes between; the last one ends the file. So every byte of
/// the file is either index, section data or checked padding. Padding past `bytes` (a map
/// read by range) is checked when its section is fetched ([`Wanted::matches`]).
fn check_tiling(
    bytes: &[u8],
    file_len: u64,
    sections: &mut [Section],
    metadata_end: u64,
) -> Result<(), Error> {
    let mut previous_end = metadata_end;
    for section in sections {
        let expected = align_up(previous_end).ok_or(Error::BadIndex {
            what: "region end overflows",
        })?;
        if section.offset < expected {
            return Err(Error::Overlap {
                section: section.reference(),
                offset: section.offset,
                previous_end,
            });
        }
        if section.offset > expected {
            return Err(Error::BadIndex {
                what: "gap between sections larger than the alignment padding",
            });
        }
        if section.offset <= bytes.len() as u64 {
            check_padding(bytes, previous_end, section.offset)?;
        }
        section.padding_start = previous_end;
        previous_end = section.offset + section.stored_len;
    }
    if previous_end != file_len {
        return Err(Error::TrailingBytes {
            expected: previous_end,
            file_len,
        });
    }
    Ok(())
}

fn check_padding(bytes: &[u8], start: u64, end: u64) -> Result<(), Error> {
    let pad = &bytes[start as usize..end as usize];
    if pad.iter().any(|&b| b != 0) {
        return Err(Error::BadPadding {
            offset: start,
            len: end - start,
        });
    }
    Ok(())
}
