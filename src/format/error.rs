//! The format's one error type.

use super::layout::SectionKind;
use std::fmt;
use std::path::PathBuf;

/// Names a section in errors: its kind, its level (if any) and its table index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SectionRef {
    /// Its position in the section table (0 = the first entry).
    pub index: usize,
    /// What it holds.
    pub kind: SectionKind,
    /// The level it belongs to; `None` for map-wide sections.
    pub level: Option<u16>,
}

impl fmt::Display for SectionRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "section {} ({}", self.index, self.kind)?;
        if let Some(level) = self.level {
            write!(f, ", level {level}")?;
        }
        f.write_str(")")
    }
}

/// Everything that can be wrong with a map file or a request made of it.
///
/// Variants carry the numbers that explain the problem, so a message can say what was
/// expected and what was found. Offsets and lengths are in bytes, from the start of the file
/// unless a field says otherwise; checksums are XXH3-64.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Error {
    /// Reading or writing the file failed.
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error, as text (so the error stays `Clone + PartialEq`).
        message: String,
    },
    /// The path names a folder, FIFO, device or socket.
    NotARegularFile {
        /// Which (`"a folder"`).
        what: &'static str,
    },
    /// The file does not start with the sfpmap magic.
    BadMagic,
    /// The file's major version is not one this reader understands.
    VersionMismatch {
        /// The major version this reader reads.
        expected: u16,
        /// The file's major version.
        found: u16,
        /// The file's minor version.
        minor: u16,
    },
    /// The endianness check field holds other bytes than expected.
    BadEndianCheck {
        /// The field's value, read little-endian.
        found: u32,
    },
    /// The file ends before something the index says is there.
    Truncated {
        /// What was being read.
        what: &'static str,
        /// The file length it needs.
        needed: u64,
        /// The file's length.
        file_len: u64,
    },
    /// The file is longer than the index accounts for.
    TrailingBytes {
        /// The length the header and table account for.
        expected: u64,
        /// The file's length.
        file_len: u64,
    },
    /// The header's table or metadata description is impossible.
    BadIndex {
        /// Which field, and why.
        what: &'static str,
    },
    /// The checksum over header, table and metadata does not match.
    IndexChecksumMismatch {
        /// The header's checksum.
        expected: u64,
        /// The checksum of the bytes.
        found: u64,
    },
    /// The metadata is larger than the format's limit.
    MetadataTooLarge {
        /// The metadata's length.
        len: u64,
        /// The limit (16 MiB).
        max: u64,
    },
    /// The metadata is not valid JSON of the expected shape.
    BadMetadata {
        /// The JSON parser's or the check's message.
        message: String,
    },
    /// A table entry has nonzero reserved fields, or a required entry an unknown dtype, codec
    /// or flag bit.
    BadEntry {
        /// The entry.
        section: SectionRef,
        /// Which field, and why.
        what: String,
    },
    /// rows × cols × dtype size overflows or disagrees with the raw length.
    SizeMismatch {
        /// The section.
        section: SectionRef,
        /// Its declared rows.
        rows: u64,
        /// Its declared columns.
        cols: u64,
        /// Its declared decoded length.
        raw_len: u64,
    },
    /// A known section kind has another dtype or column count than the spec fixes.
    WrongLayout {
        /// The section.
        section: SectionRef,
        /// The layout the spec fixes (`"f32 x 3"`).
        expected: String,
        /// The layout the table declares.
        found: String,
    },
    /// A section reaches past the end of the file.
    SectionOutOfBounds {
        /// The section.
        section: SectionRef,
        /// Where its stored bytes start.
        offset: u64,
        /// Its stored length.
        len: u64,
        /// The file's length.
        file_len: u64,
    },
    /// A section does not start on the format's 64-byte alignment.
    Misaligned {
        /// The section.
        section: SectionRef,
        /// Where it starts.
        offset: u64,
    },
    /// Two regions of the file overlap (or are not in file order).
    Overlap {
        /// The later section.
        section: SectionRef,
        /// Where it starts.
        offset: u64,
        /// Where the region before it ends.
        previous_end: u64,
    },
    /// Bytes between regions are not the zero padding the layout requires.
    BadPadding {
        /// Where the padding starts.
        offset: u64,
        /// Its length.
        len: u64,
    },
    /// A required section of a kind this reader does not know.
    UnknownRequiredSection {
        /// The section (its kind is `SectionKind::Unknown`).
        section: SectionRef,
    },
    /// The header's `flags` name a required feature this reader does not know (1.1).
    UnknownRequiredFeature {
        /// The header's flags.
        bits: u64,
    },
    /// A section the metadata or another section needs is absent.
    MissingSection {
        /// The kind missing.
        kind: SectionKind,
        /// Its level; `None` for a map-wide section.
        level: Option<u16>,
    },
    /// The same kind (and level) appears twice.
    DuplicateSection {
        /// The second of the two.
        section: SectionRef,
    },
    /// The stored bytes' checksum does not match the table.
    ChecksumMismatch {
        /// The section.
        section: SectionRef,
        /// The table's checksum.
        expected: u64,
        /// The checksum of the stored bytes.
        found: u64,
    },
    /// (1.2) A chunk of a section's stored bytes does not match `chunk_checksums`.
    ChunkChecksumMismatch {
        /// The section.
        section: SectionRef,
        /// The chunk's position in the section.
        chunk: u64,
        /// Its bytes in the section's stored bytes.
        bytes: std::ops::Range<u64>,
        /// The chunk's checksum in `chunk_checksums`.
        expected: u64,
        /// The checksum of the chunk's bytes.
        found: u64,
    },
    /// A compressed section does not decode to its declared raw length.
    Decode {
        /// The section.
        section: SectionRef,
        /// The decoder's message, or the lengths that disagree.
        message: String,
    },
    /// A compressed section declares a raw length beyond the cap derived from the file length.
    DecodedTooLarge {
        /// The section.
        section: SectionRef,
        /// Its declared decoded length.
        raw_len: u64,
        /// The cap: 256 × the file's length, at least 1 MiB (read by range, also 256 × the
        /// section's stored length).
        cap: u64,
    },
    /// Decoding a zstd section would take the bytes decoded from this open map past its
    /// decode budget ([`Map::decode_budget`](super::Map::decode_budget)); at open: the zstd
    /// sections of known kinds declare more than it together.
    DecodeBudgetExceeded {
        /// The section.
        section: SectionRef,
        /// Its declared decoded length.
        raw_len: u64,
        /// What the map decoded before it.
        decoded: u64,
        /// The budget: 256 × the file's length, at least 64 MiB.
        budget: u64,
    },
    /// Section contents or metadata contradict each other.
    Inconsistent {
        /// What disagrees with what.
        what: String,
    },
    /// A level was asked for that the map does not hold.
    NoSuchLevel {
        /// The level asked for.
        level: u16,
        /// The map's levels.
        available: Vec<u16>,
    },
    /// Writer input is invalid (wrong lengths, bad dims, ...).
    InvalidInput {
        /// What, and why.
        what: String,
    },
}

/// Messages quote a file's own text (metadata values, names): the whole text is escaped
/// ([`crate::escape`]), so it stays one line whatever the file holds.
impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let text = Unescaped(self).to_string();
        f.write_str(&crate::escape::escape_control_characters(&text))
    }
}

/// [`Error`]'s text before its control characters are escaped.
struct Unescaped<'a>(&'a Error);

impl fmt::Display for Unescaped<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        use Error::*;
        match self.0 {
            Io { path, message } => write!(f, "{}: {message}", path.display()),
            NotARegularFile { what } => write!(f, "is {what}, not a regular file"),
            BadMagic => f.write_str("not an sfpmap file (bad magic)"),
            VersionMismatch {
                expected,
                found,
                minor,
            } => write!(
                f,
                "unsupported format version {found}.{minor} (this reader handles {expected}.x)"
            ),
            BadEndianCheck { found } => {
                write!(f, "bad endianness check 0x{found:08x} (expected 0x1a2b3c4d)")
            }
            Truncated {
                what,
                needed,
                file_len,
            } => write!(
                f,
                "truncated file: {what} needs {needed} bytes, file has {file_len}"
            ),
            TrailingBytes { expected, file_len } => write!(
                f,
                "file is {file_len} bytes but its index accounts for {expected}"
            ),
            BadIndex { what } => write!(f, "bad index: {what}"),
            IndexChecksumMismatch { expected, found } => write!(
                f,
                "index checksum mismatch (header, table or metadata corrupt): expected {expected:016x}, found {found:016x}"
            ),
            MetadataTooLarge { len, max } => {
                write!(f, "metadata is {len} bytes, more than the cap of {max}")
            }
            BadMetadata { message } => write!(f, "bad metadata: {message}"),
            BadEntry { section, what } => write!(f, "{section}: {what}"),
            SizeMismatch {
                section,
                rows,
                cols,
                raw_len,
            } => write!(
                f,
                "{section}: shape {rows}x{cols} does not match raw length {raw_len} (or overflows)"
            ),
            WrongLayout {
                section,
                expected,
                found,
            } => write!(f, "{section}: expected {expected}, found {found}"),
            SectionOutOfBounds {
                section,
                offset,
                len,
                file_len,
            } => write!(
                f,
                "{section}: bytes {offset}+{len} lie outside the file of {file_len} bytes"
            ),
            Misaligned { section, offset } => {
                write!(f, "{section}: offset {offset} is not a multiple of 64")
            }
            Overlap {
                section,
                offset,
                previous_end,
            } => write!(
                f,
                "{section}: starts at {offset}, overlapping or before the previous region ending at {previous_end}"
            ),
            BadPadding { offset, len } => write!(
                f,
                "{len} bytes at offset {offset} are not the zero padding the layout requires"
            ),
            UnknownRequiredSection { section } => {
                write!(f, "{section}: required section of a kind this reader does not know")
            }
            UnknownRequiredFeature { bits } => write!(
                f,
                "the header requires features this reader does not know (flags 0x{bits:016x})"
            ),
            MissingSection { kind, level } => match level {
                Some(l) => write!(f, "missing section {kind} for level {l}"),
                None => write!(f, "missing section {kind}"),
            },
            DuplicateSection { section } => write!(f, "{section}: appears more than once"),
            ChecksumMismatch {
                section,
                expected,
                found,
            } => write!(
                f,
                "{section}: checksum mismatch, expected {expected:016x}, found {found:016x}"
            ),
            ChunkChecksumMismatch {
                section,
                chunk,
                bytes,
                expected,
                found,
            } => write!(
                f,
                "{section}: checksum mismatch in bytes {} to {} (chunk {chunk}), expected {expected:016x}, found {found:016x}",
                bytes.start, bytes.end
            ),
            Decode { section, message } => write!(f, "{section}: cannot decode: {message}"),
            DecodedTooLarge {
                section,
                raw_len,
                cap,
            } => write!(
                f,
                "{section}: declared raw length {raw_len} exceeds the cap of {cap} bytes"
            ),
            DecodeBudgetExceeded {
                section,
                raw_len,
                decoded,
                budget,
            } => write!(
                f,
                "{section}: its {raw_len} decoded bytes would take the map past its decode budget of {budget} bytes ({decoded} before it)"
            ),
            Inconsistent { what } => write!(f, "inconsistent map: {what}"),
            NoSuchLevel { level, available } => {
                write!(f, "no level {level} in this map (levels: {available:?})")
            }
            InvalidInput { what } => write!(f, "invalid input: {what}"),
        }
    }
}

impl std::error::Error for Error {}

impl Error {
    /// A short stable name for the variant, used by the conformance vectors' `.json` files.
    pub fn kind_name(&self) -> &'static str {
        use Error::*;
        match self {
            Io { .. } => "io",
            NotARegularFile { .. } => "not_a_regular_file",
            BadMagic => "bad_magic",
            VersionMismatch { .. } => "version_mismatch",
            BadEndianCheck { .. } => "bad_endian_check",
            Truncated { .. } => "truncated",
            TrailingBytes { .. } => "trailing_bytes",
            BadIndex { .. } => "bad_index",
            IndexChecksumMismatch { .. } => "index_checksum_mismatch",
            MetadataTooLarge { .. } => "metadata_too_large",
            BadMetadata { .. } => "bad_metadata",
            BadEntry { .. } => "bad_entry",
            SizeMismatch { .. } => "size_mismatch",
            WrongLayout { .. } => "wrong_layout",
            SectionOutOfBounds { .. } => "section_out_of_bounds",
            Misaligned { .. } => "misaligned",
            Overlap { .. } => "overlap",
            BadPadding { .. } => "bad_padding",
            UnknownRequiredSection { .. } => "unknown_required_section",
            UnknownRequiredFeature { .. } => "unknown_required_feature",
            MissingSection { .. } => "missing_section",
            DuplicateSection { .. } => "duplicate_section",
            ChecksumMismatch { .. } | ChunkChecksumMismatch { .. } => "checksum_mismatch",
            Decode { .. } => "decode",
            DecodedTooLarge { .. } => "decoded_too_large",
            DecodeBudgetExceeded { .. } => "decode_budget_exceeded",
            Inconsistent { .. } => "inconsistent",
            NoSuchLevel { .. } => "no_such_level",
            InvalidInput { .. } => "invalid_input",
        }
    }

    pub(crate) fn io(path: &std::path::Path, err: std::io::Error) -> Error {
        Error::Io {
            path: path.to_path_buf(),
            message: err.to_string(),
        }
    }

    pub(crate) fn inconsistent(what: impl Into<String>) -> Error {
        Error::Inconsistent { what: what.into() }
    }

    pub(crate) fn invalid(what: impl Into<String>) -> Error {
        Error::InvalidInput { what: what.into() }
    }
}
