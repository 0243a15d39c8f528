//! The format's one error type.

use super::layout::SectionKind;
use std::fmt;
use std::path::PathBuf;

/// Names a section in errors: its kind, its level (if any) and its table index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SectionRef {
    pub index: usize,
    pub kind: SectionKind,
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
/// expected and what was found.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum Error {
    /// Reading or writing the file failed.
    Io { path: PathBuf, message: String },
    /// The path names a folder, FIFO, device or socket; `what` says which (`"a folder"`).
    NotARegularFile { what: &'static str },
    /// The file does not start with the sfpmap magic.
    BadMagic,
    /// The file's major version is not one this reader understands.
    VersionMismatch {
        expected: u16,
        found: u16,
        minor: u16,
    },
    /// The endianness check field holds other bytes than expected.
    BadEndianCheck { found: u32 },
    /// The file ends before something the index says is there.
    Truncated {
        what: &'static str,
        needed: u64,
        file_len: u64,
    },
    /// The file is longer than the index accounts for.
    TrailingBytes { expected: u64, file_len: u64 },
    /// The header's table or metadata description is impossible.
    BadIndex { what: &'static str },
    /// The checksum over header, table and metadata does not match.
    IndexChecksumMismatch { expected: u64, found: u64 },
    /// The metadata is larger than [`super::METADATA_MAX_BYTES`].
    MetadataTooLarge { len: u64, max: u64 },
    /// The metadata is not valid JSON of the expected shape.
    BadMetadata { message: String },
    /// A table entry has nonzero reserved fields, or a required entry an unknown dtype, codec
    /// or flag bit.
    BadEntry { section: SectionRef, what: String },
    /// rows × cols × dtype size overflows or disagrees with the raw length.
    SizeMismatch {
        section: SectionRef,
        rows: u64,
        cols: u64,
        raw_len: u64,
    },
    /// A known section kind has another dtype or column count than the spec fixes.
    WrongLayout {
        section: SectionRef,
        expected: String,
        found: String,
    },
    /// A section reaches past the end of the file.
    SectionOutOfBounds {
        section: SectionRef,
        offset: u64,
        len: u64,
        file_len: u64,
    },
    /// A section does not start on the format's alignment.
    Misaligned { section: SectionRef, offset: u64 },
    /// Two regions of the file overlap (or are not in file order).
    Overlap {
        section: SectionRef,
        offset: u64,
        previous_end: u64,
    },
    /// Bytes between regions are not the zero padding the layout requires.
    BadPadding { offset: u64, len: u64 },
    /// A required section of a kind this reader does not know.
    UnknownRequiredSection { section: SectionRef },
    /// The header's `flags` name a required feature this reader does not know (1.1).
    UnknownRequiredFeature { bits: u64 },
    /// A section the metadata or another section needs is absent.
    MissingSection {
        kind: SectionKind,
        level: Option<u16>,
    },
    /// The same kind (and level) appears twice.
    DuplicateSection { section: SectionRef },
    /// The stored bytes' checksum does not match the table.
    ChecksumMismatch {
        section: SectionRef,
        expected: u64,
        found: u64,
    },
    /// (1.2) A chunk of a section's stored bytes does not match `chunk_checksums`.
    ChunkChecksumMismatch {
        section: SectionRef,
        /// The chunk's position in the section.
        chunk: u64,
        /// Its bytes in the section's stored bytes.
        bytes: std::ops::Range<u64>,
        expected: u64,
        found: u64,
    },
    /// A compressed section does not decode to its declared raw length.
    Decode {
        section: SectionRef,
        message: String,
    },
    /// A compressed section declares a raw length beyond the cap derived from the file length.
    DecodedTooLarge {
        section: SectionRef,
        raw_len: u64,
        cap: u64,
    },
    /// Decoding a zstd section would take the bytes decoded from this open map past its
    /// decode budget ([`super::decode_budget`]); at open: the zstd sections of known kinds
    /// declare more than it together.
    DecodeBudgetExceeded {
        section: SectionRef,
        raw_len: u64,
        decoded: u64,
        budget: u64,
    },
    /// Section contents or metadata contradict each other.
    Inconsistent { what: String },
    /// A level was asked for that the map does not hold.
    NoSuchLevel { level: u16, available: Vec<u16> },
    /// Writer input is invalid (wrong lengths, bad dims, ...).
    InvalidInput { what: String },
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        use Error::*;
        match self {
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
