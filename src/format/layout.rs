//! On-disk structures of the format: the fixed header, the section table entries and the
//! codes they use. These are the raw records of `spec/format.md`; the friendly API lives in
//! `reader`/`views`. All integers are little-endian.

use super::error::Error;

/// The 8 magic bytes every map starts with (PNG-style: a high byte, the name, CR LF, SUB).
pub const MAGIC: [u8; 8] = *b"\x89SFPM\r\n\x1a";
/// The major version this crate reads and writes. A different major is an error.
pub const VERSION_MAJOR: u16 = 1;
/// The highest minor version this crate writes (a file gets the lowest minor that defines all
/// its sections, see [`SectionKind::since_minor`]). Readers accept any minor of their major.
pub const VERSION_MINOR: u16 = 4;
/// Written as a `u32` LE; a reader that sees other bytes has the wrong byte order.
pub const ENDIAN_CHECK: u32 = 0x1A2B_3C4D;
/// Size of the fixed header in bytes.
pub const HEADER_LEN: usize = 64;
/// Size of one section-table entry written by this version. Readers accept larger entries
/// (a later minor may append fields) and read the first `ENTRY_LEN` bytes.
pub const ENTRY_LEN: usize = 64;
/// Cap on the entry length, so the table (hashed at open) stays small whatever the file.
pub const MAX_ENTRY_LEN: u32 = 1024;
/// Every section starts at a multiple of this, so arrays cast zero-copy from the mapping.
pub const ALIGN: u64 = 64;
/// Cap on the metadata JSON; checked before anything is parsed.
pub const METADATA_MAX_BYTES: u64 = 16 << 20;
/// (1.2) Bytes per chunk of a section's stored bytes in `chunk_checksums`: a reader checks a
/// large raw section 64 KiB at a time where it reads it, instead of whole on first access.
pub const CHUNK_LEN: u64 = 1 << 16;
/// Cap on the number of sections, so the table is bounded too.
pub const MAX_SECTIONS: u32 = 1 << 16;
/// `level` value of sections that belong to no level.
pub const NO_LEVEL: u16 = u16::MAX;
/// Cap on descriptor dimensions: a level's `dim_full`, and the columns of the descriptor,
/// projection and global-descriptor sections. Readers size buffers from these before reading
/// a single descriptor, so they are bounded at open.
pub const MAX_DESCRIPTOR_DIM: u64 = 4096;
/// Cap on a camera's width and height in pixels.
pub const MAX_IMAGE_SIDE: u64 = 1 << 20;
/// Cap on a camera's parameter count.
pub const MAX_CAMERA_PARAMS: usize = 64;

/// Section entry flag: a reader that does not know the section's kind must fail.
pub const SECTION_REQUIRED: u8 = 1 << 0;
/// Section flag bits this version knows. An optional section with another bit set is skipped
/// (1.1); a required one is an error.
pub const SECTION_FLAGS_KNOWN: u8 = SECTION_REQUIRED;
/// Header feature bit 0 (1.1): required sections may use codec 2 `delta`.
pub const FEATURE_DELTA: u64 = 1 << 0;
/// Header `flags` bits this version knows: each bit is a *required feature* (1.1), a change
/// to how required sections are encoded that a reader must understand to read the map. A file
/// with another bit set is refused with `unknown_required_feature`.
pub const HEADER_FEATURES_KNOWN: u64 = FEATURE_DELTA;

/// Element type of a section's array.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Dtype {
    /// Unsigned 8-bit integer.
    U8 = 1,
    /// Unsigned 16-bit integer.
    U16 = 2,
    /// Unsigned 32-bit integer.
    U32 = 3,
    /// Unsigned 64-bit integer.
    U64 = 4,
    /// IEEE 754 half-precision float.
    F16 = 5,
    /// IEEE 754 single-precision float.
    F32 = 6,
    /// IEEE 754 double-precision float.
    F64 = 7,
}

impl Dtype {
    /// The dtype of a table entry's `dtype` byte; `None` for a code this version does not know.
    pub fn from_code(code: u8) -> Option<Dtype> {
        Some(match code {
            1 => Dtype::U8,
            2 => Dtype::U16,
            3 => Dtype::U32,
            4 => Dtype::U64,
            5 => Dtype::F16,
            6 => Dtype::F32,
            7 => Dtype::F64,
            _ => return None,
        })
    }

    /// Bytes per element.
    pub fn size(self) -> u64 {
        match self {
            Dtype::U8 => 1,
            Dtype::U16 | Dtype::F16 => 2,
            Dtype::U32 | Dtype::F32 => 4,
            Dtype::U64 | Dtype::F64 => 8,
        }
    }

    /// The spec's name (`f16`), as messages and `info --json` print it.
    pub fn name(self) -> &'static str {
        match self {
            Dtype::U8 => "u8",
            Dtype::U16 => "u16",
            Dtype::U32 => "u32",
            Dtype::U64 => "u64",
            Dtype::F16 => "f16",
            Dtype::F32 => "f32",
            Dtype::F64 => "f64",
        }
    }
}

/// How a section's bytes are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
#[repr(u8)]
pub enum Codec {
    /// The array's bytes as they are: viewable zero-copy.
    #[default]
    Raw = 0,
    /// One zstd frame holding the array's bytes.
    Zstd = 1,
    /// (1.1) u32/u64 arrays: one zstd frame of the LEB128 varints of the zigzag differences
    /// of consecutive values (`format/delta.rs`). In a required section only behind the header
    /// feature bit for it (`FEATURE_DELTA`).
    Delta = 2,
}

impl Codec {
    /// The codec of a table entry's `codec` byte; `None` for a code this version does not know.
    pub fn from_code(code: u8) -> Option<Codec> {
        match code {
            0 => Some(Codec::Raw),
            1 => Some(Codec::Zstd),
            2 => Some(Codec::Delta),
            _ => None,
        }
    }

    /// The spec's name (`raw`, `zstd`, `delta`).
    pub fn name(self) -> &'static str {
        match self {
            Codec::Raw => "raw",
            Codec::Zstd => "zstd",
            Codec::Delta => "delta",
        }
    }
}

/// What a section holds. Codes are stable; a minor version may add new ones.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum SectionKind {
    /// f32 [points × 3]: xyz relative to the metadata `origin`.
    PointPositions,
    /// u16 [points × 3] (1.1): xyz on the metadata `position_grid`, in place of
    /// `PointPositions`.
    PointPositionsQ16,
    /// u8 [points × 3]: RGB.
    PointColors,
    /// u64 [points × 1]: the source's point ids (COLMAP `point3D_id`).
    PointIds,
    /// u32 [n_L × 1]: strictly increasing global point indices held by a level.
    LevelPoints,
    /// f16 [n_L × d_short]: the first `d_short` dimensions of each level point's descriptor.
    LevelDescShort,
    /// f16 [n_L × (d_full − d_short)]: the remaining dimensions.
    LevelDescRest,
    /// f32 [d_full × d_in]: orthonormal rows mapping an extractor descriptor into the stored basis.
    LevelProjection,
    /// f32 [clusters × dims] (1.1): the VLAD codebook of the level whose descriptors (their first
    /// `dims` stored dimensions) retrieval aggregates; at most one level has one.
    LevelVladCentroids,
    /// f32 [M·K × D/M] (1.1): a product-quantised level's codebook, K centroids per subspace,
    /// subspace by subspace.
    LevelPqCodebook,
    /// u8 [n_L × M] (1.1): each level point's centroid in each subspace; replaces the level's
    /// f16 blocks.
    LevelPqCodes,
    /// u16 [D × 1] (1.1): the level dimension at each position of the quantised vector (a
    /// permutation of `0..D`); absent = the identity.
    LevelPqOrder,
    /// f64 [images × 7]: `cam_from_world` as qw qx qy qz tx ty tz (COLMAP).
    ImagePoses,
    /// u32 [images × 1]: index into the metadata `cameras`.
    ImageCameras,
    /// u32 [images × 1]: the source's image ids (COLMAP `image_id`).
    ImageIds,
    /// u64 [images + 1 × 1]: byte offsets into `ImageNames`.
    ImageNameOffsets,
    /// u8 [bytes × 1]: UTF-8 image names, concatenated.
    ImageNames,
    /// f16 [images × d_g]: L2-normalised global descriptors for retrieval.
    ImageGlobal,
    /// f16 [images × clusters·dims] (1.1): each image's VLAD over the level codebook.
    ImageVlad,
    /// f32 [lists × width] (1.3): the image index's list centroids, in the space of the rows
    /// it indexes (`ImageVlad` or `ImageGlobal`, as the metadata `image_index` says).
    ImageIndexCentroids,
    /// u32 [lists + 1 × 1] (1.3): CSR offsets into `ImageIndexImages`, list by list.
    ImageIndexOffsets,
    /// u32 [images × 1] (1.3): every image once, grouped by the list it belongs to.
    ImageIndexImages,
    /// u32 [images × neighbours] (1.4): each image's nearest images in retrieval (the ones
    /// sharing most points), best first, `u32::MAX` past the last; an image index's
    /// searches widen along them from the lists they probed.
    ImageIndexNeighbours,
    /// u64 [images + 1 × 1]: CSR row offsets into `VisibilityPoints`.
    VisibilityOffsets,
    /// u32 [observations × 1]: point indices seen by each image, image by image.
    VisibilityPoints,
    /// f32 [observations × 2]: the pixel (x, y) of each visibility entry.
    VisibilityKeypoints,
    /// u64 [places + 1 × 1] (1.1, catalogs): each place's first row in `CatalogImageVlad`.
    PlaceImages,
    /// f32 [dims × d_in] (1.1, catalogs): the catalog's basis, from the places' common
    /// descriptor space (SIFT's 128 dimensions) to the `dims` its codebook is on.
    CatalogProjection,
    /// f32 [clusters × dims] (1.1, catalogs): the catalog's one VLAD codebook.
    CatalogVladCentroids,
    /// f16 [images × clusters·dims] (1.1, catalogs): every place's images' VLADs on it.
    CatalogImageVlad,
    /// u64 [chunks × 1] (1.2): XXH3 of each [`CHUNK_LEN`] bytes of every other section's stored
    /// bytes, sections in table order.
    ChunkChecksums,
    /// A kind this version does not know.
    Unknown(u16),
}

impl SectionKind {
    const KNOWN: [(u16, SectionKind, &'static str); 31] = [
        (1, SectionKind::PointPositions, "point_positions"),
        (4, SectionKind::PointPositionsQ16, "point_positions_q16"),
        (2, SectionKind::PointColors, "point_colors"),
        (3, SectionKind::PointIds, "point_ids"),
        (16, SectionKind::LevelPoints, "level_points"),
        (17, SectionKind::LevelDescShort, "level_desc_short"),
        (18, SectionKind::LevelDescRest, "level_desc_rest"),
        (19, SectionKind::LevelProjection, "level_projection"),
        (20, SectionKind::LevelVladCentroids, "level_vlad_centroids"),
        (21, SectionKind::LevelPqCodebook, "level_pq_codebook"),
        (22, SectionKind::LevelPqCodes, "level_pq_codes"),
        (23, SectionKind::LevelPqOrder, "level_pq_order"),
        (32, SectionKind::ImagePoses, "image_poses"),
        (33, SectionKind::ImageCameras, "image_cameras"),
        (34, SectionKind::ImageIds, "image_ids"),
        (35, SectionKind::ImageNameOffsets, "image_name_offsets"),
        (36, SectionKind::ImageNames, "image_names"),
        (37, SectionKind::ImageGlobal, "image_global"),
        (38, SectionKind::ImageVlad, "image_vlad"),
        (
            39,
            SectionKind::ImageIndexCentroids,
            "image_index_centroids",
        ),
        (40, SectionKind::ImageIndexOffsets, "image_index_offsets"),
        (41, SectionKind::ImageIndexImages, "image_index_images"),
        (
            42,
            SectionKind::ImageIndexNeighbours,
            "image_index_neighbours",
        ),
        (48, SectionKind::VisibilityOffsets, "visibility_offsets"),
        (49, SectionKind::VisibilityPoints, "visibility_points"),
        (50, SectionKind::VisibilityKeypoints, "visibility_keypoints"),
        (64, SectionKind::PlaceImages, "place_images"),
        (65, SectionKind::CatalogProjection, "catalog_projection"),
        (
            66,
            SectionKind::CatalogVladCentroids,
            "catalog_vlad_centroids",
        ),
        (67, SectionKind::CatalogImageVlad, "catalog_image_vlad"),
        (80, SectionKind::ChunkChecksums, "chunk_checksums"),
    ];

    /// The kind of a table entry's `kind` field; an unknown code is [`SectionKind::Unknown`].
    pub fn from_code(code: u16) -> SectionKind {
        Self::KNOWN
            .iter()
            .find(|(c, _, _)| *c == code)
            .map(|(_, k, _)| *k)
            .unwrap_or(SectionKind::Unknown(code))
    }

    /// The `kind` code written in the table.
    pub fn code(self) -> u16 {
        match self {
            SectionKind::Unknown(c) => c,
            known => Self::KNOWN
                .iter()
                .find(|(_, k, _)| *k == known)
                .map(|(c, _, _)| *c)
                .expect("every known kind is in the table"),
        }
    }

    /// The spec's name of the kind (`unknown` for kinds this version does not know).
    pub fn name(self) -> &'static str {
        Self::KNOWN
            .iter()
            .find(|(_, k, _)| *k == self)
            .map(|(_, _, n)| *n)
            .unwrap_or("unknown")
    }

    /// The dtype and column count the spec fixes for a known kind (`None` = any columns).
    pub fn expected_layout(self) -> Option<(Dtype, Option<u64>)> {
        use SectionKind::*;
        Some(match self {
            PointPositions => (Dtype::F32, Some(3)),
            PointPositionsQ16 => (Dtype::U16, Some(3)),
            PointColors => (Dtype::U8, Some(3)),
            PointIds => (Dtype::U64, Some(1)),
            LevelPoints => (Dtype::U32, Some(1)),
            LevelDescShort | LevelDescRest | ImageGlobal | ImageVlad => (Dtype::F16, None),
            LevelProjection | LevelVladCentroids | LevelPqCodebook | ImageIndexCentroids => {
                (Dtype::F32, None)
            }
            LevelPqCodes => (Dtype::U8, None),
            LevelPqOrder => (Dtype::U16, Some(1)),
            ImagePoses => (Dtype::F64, Some(7)),
            ImageCameras | ImageIds | ImageIndexOffsets | ImageIndexImages => (Dtype::U32, Some(1)),
            ImageIndexNeighbours => (Dtype::U32, None),
            ImageNameOffsets | VisibilityOffsets | PlaceImages | ChunkChecksums => {
                (Dtype::U64, Some(1))
            }
            ImageNames => (Dtype::U8, Some(1)),
            CatalogProjection | CatalogVladCentroids => (Dtype::F32, None),
            CatalogImageVlad => (Dtype::F16, None),
            VisibilityPoints => (Dtype::U32, Some(1)),
            VisibilityKeypoints => (Dtype::F32, Some(2)),
            Unknown(_) => return None,
        })
    }

    /// Whether the kind's columns are a descriptor dimension or a part of one (at most
    /// [`MAX_DESCRIPTOR_DIM`]).
    pub fn has_descriptor_columns(self) -> bool {
        matches!(
            self,
            SectionKind::LevelDescShort
                | SectionKind::LevelDescRest
                | SectionKind::LevelProjection
                | SectionKind::LevelVladCentroids
                | SectionKind::LevelPqCodebook
                | SectionKind::LevelPqCodes
                | SectionKind::ImageGlobal
                | SectionKind::CatalogProjection
                | SectionKind::CatalogVladCentroids
        )
    }

    /// Where the reference writer puts a section of this kind and `level`: the shared
    /// sections (geometry, images, retrieval, visibility) by kind code, then level by level
    /// ascending, each level's `short` block after everything else it needs and its `rest`
    /// block last. So one level's short map is one contiguous byte range, and a reader by
    /// range fetches it in one request (spec, "Section order").
    pub(crate) fn file_order(self, level: u16) -> (u8, u16, u16) {
        // Last: its values cover every section before it.
        if self == SectionKind::ChunkChecksums {
            return (2, 0, 0);
        }
        if level == NO_LEVEL {
            return (0, self.code(), 0);
        }
        let rank = match self {
            SectionKind::LevelPoints => 0,
            SectionKind::LevelProjection => 1,
            SectionKind::LevelVladCentroids => 2,
            SectionKind::LevelPqOrder => 3,
            SectionKind::LevelPqCodebook => 4,
            SectionKind::LevelPqCodes => 5,
            SectionKind::LevelDescShort => 6,
            SectionKind::LevelDescRest => 7,
            other => 16u16.saturating_add(other.code()),
        };
        (1, level, rank)
    }

    /// Whether sections of this kind carry a level id (others use [`NO_LEVEL`]).
    pub fn is_per_level(self) -> bool {
        matches!(
            self,
            SectionKind::LevelPoints
                | SectionKind::LevelDescShort
                | SectionKind::LevelDescRest
                | SectionKind::LevelProjection
                | SectionKind::LevelVladCentroids
                | SectionKind::LevelPqCodebook
                | SectionKind::LevelPqCodes
                | SectionKind::LevelPqOrder
        )
    }

    /// The first minor version that defines the kind (0 for 1.0 kinds and unknown ones): a
    /// writer stamps a file with the highest minor among its sections, so a map without 1.1
    /// sections stays a 1.0 file byte for byte.
    pub fn since_minor(self) -> u16 {
        match self {
            SectionKind::LevelVladCentroids
            | SectionKind::ImageVlad
            | SectionKind::PointPositionsQ16
            | SectionKind::LevelPqCodebook
            | SectionKind::LevelPqCodes
            | SectionKind::LevelPqOrder
            | SectionKind::PlaceImages
            | SectionKind::CatalogProjection
            | SectionKind::CatalogVladCentroids
            | SectionKind::CatalogImageVlad => 1,
            SectionKind::ChunkChecksums => 2,
            SectionKind::ImageIndexCentroids
            | SectionKind::ImageIndexOffsets
            | SectionKind::ImageIndexImages => 3,
            SectionKind::ImageIndexNeighbours => 4,
            _ => 0,
        }
    }
}

impl std::fmt::Display for SectionKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SectionKind::Unknown(c) => write!(f, "unknown kind {c}"),
            k => f.write_str(k.name()),
        }
    }
}

/// The fixed header, decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header {
    /// Major version (offset 8).
    pub major: u16,
    /// Minor version (offset 10).
    pub minor: u16,
    /// Required-feature bits (offset 16; 1.1).
    pub flags: u64,
    /// Entries in the section table (offset 24).
    pub section_count: u32,
    /// Bytes per table entry (offset 28): at least 64, at most 1024.
    pub entry_len: u32,
    /// Where the metadata JSON starts (offset 32).
    pub metadata_offset: u64,
    /// Its length (offset 40).
    pub metadata_len: u64,
    /// The file's length as written (offset 48).
    pub file_len: u64,
    /// XXH3-64 of header (this field zeroed), table and metadata (offset 56).
    pub index_checksum: u64,
}

impl Header {
    /// Decodes the header, checking only what is needed to find the rest of the index.
    pub fn decode(bytes: &[u8]) -> Result<Header, Error> {
        let present = bytes.len().min(MAGIC.len());
        if bytes[..present] != MAGIC[..present] {
            return Err(Error::BadMagic);
        }
        if bytes.len() < HEADER_LEN {
            return Err(Error::Truncated {
                what: "header",
                needed: HEADER_LEN as u64,
                file_len: bytes.len() as u64,
            });
        }
        let major = le_u16(bytes, 8);
        let minor = le_u16(bytes, 10);
        if major != VERSION_MAJOR {
            return Err(Error::VersionMismatch {
                expected: VERSION_MAJOR,
                found: major,
                minor,
            });
        }
        let endian = le_u32(bytes, 12);
        if endian != ENDIAN_CHECK {
            return Err(Error::BadEndianCheck { found: endian });
        }
        Ok(Header {
            major,
            minor,
            flags: le_u64(bytes, 16),
            section_count: le_u32(bytes, 24),
            entry_len: le_u32(bytes, 28),
            metadata_offset: le_u64(bytes, 32),
            metadata_len: le_u64(bytes, 40),
            file_len: le_u64(bytes, 48),
            index_checksum: le_u64(bytes, 56),
        })
    }

    /// The header's 64 bytes.
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[..8].copy_from_slice(&MAGIC);
        b[8..10].copy_from_slice(&self.major.to_le_bytes());
        b[10..12].copy_from_slice(&self.minor.to_le_bytes());
        b[12..16].copy_from_slice(&ENDIAN_CHECK.to_le_bytes());
        b[16..24].copy_from_slice(&self.flags.to_le_bytes());
        b[24..28].copy_from_slice(&self.section_count.to_le_bytes());
        b[28..32].copy_from_slice(&self.entry_len.to_le_bytes());
        b[32..40].copy_from_slice(&self.metadata_offset.to_le_bytes());
        b[40..48].copy_from_slice(&self.metadata_len.to_le_bytes());
        b[48..56].copy_from_slice(&self.file_len.to_le_bytes());
        b[56..64].copy_from_slice(&self.index_checksum.to_le_bytes());
        b
    }
}

/// One section-table entry, decoded but not yet validated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RawEntry {
    /// The section kind's code ([`SectionKind::code`]).
    pub kind: u16,
    /// The level, or `NO_LEVEL` for a map-wide section.
    pub level: u16,
    /// The element type's code ([`Dtype`]).
    pub dtype: u8,
    /// The codec's code ([`Codec`]).
    pub codec: u8,
    /// Section flags (`SECTION_REQUIRED`).
    pub flags: u8,
    /// Zero in this version.
    pub reserved: u8,
    /// Rows of the array.
    pub rows: u64,
    /// Columns of the array.
    pub cols: u64,
    /// Where the stored bytes start in the file (a multiple of 64).
    pub offset: u64,
    /// Stored bytes (after the codec).
    pub stored_len: u64,
    /// Decoded bytes: rows × cols × the dtype's size.
    pub raw_len: u64,
    /// XXH3-64 of the stored bytes.
    pub checksum: u64,
    /// Zero in this version.
    pub reserved2: u64,
}

impl RawEntry {
    /// The first 64 bytes of an entry, decoded without any check.
    pub fn decode(b: &[u8]) -> RawEntry {
        RawEntry {
            kind: le_u16(b, 0),
            level: le_u16(b, 2),
            dtype: b[4],
            codec: b[5],
            flags: b[6],
            reserved: b[7],
            rows: le_u64(b, 8),
            cols: le_u64(b, 16),
            offset: le_u64(b, 24),
            stored_len: le_u64(b, 32),
            raw_len: le_u64(b, 40),
            checksum: le_u64(b, 48),
            reserved2: le_u64(b, 56),
        }
    }

    /// The entry's 64 bytes.
    pub fn encode(&self) -> [u8; ENTRY_LEN] {
        let mut b = [0u8; ENTRY_LEN];
        b[0..2].copy_from_slice(&self.kind.to_le_bytes());
        b[2..4].copy_from_slice(&self.level.to_le_bytes());
        b[4] = self.dtype;
        b[5] = self.codec;
        b[6] = self.flags;
        b[7] = self.reserved;
        b[8..16].copy_from_slice(&self.rows.to_le_bytes());
        b[16..24].copy_from_slice(&self.cols.to_le_bytes());
        b[24..32].copy_from_slice(&self.offset.to_le_bytes());
        b[32..40].copy_from_slice(&self.stored_len.to_le_bytes());
        b[40..48].copy_from_slice(&self.raw_len.to_le_bytes());
        b[48..56].copy_from_slice(&self.checksum.to_le_bytes());
        b[56..64].copy_from_slice(&self.reserved2.to_le_bytes());
        b
    }
}

/// The checksum used everywhere in the format: XXH3-64 with seed 0.
pub fn checksum(bytes: &[u8]) -> u64 {
    xxhash_rust::xxh3::xxh3_64(bytes)
}

/// Checksum of the index: header bytes 0..56, then the section table, then the metadata.
pub fn index_checksum(header_prefix: &[u8], table: &[u8], metadata: &[u8]) -> u64 {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    h.update(header_prefix);
    h.update(table);
    h.update(metadata);
    h.digest()
}

/// Rounds `n` up to the next multiple of the sections' alignment (`ALIGN`, 64), or `None` on
/// overflow.
pub fn align_up(n: u64) -> Option<u64> {
    n.checked_add(ALIGN - 1).map(|v| v & !(ALIGN - 1))
}

fn le_u16(b: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([b[at], b[at + 1]])
}

fn le_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn le_u64(b: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}
