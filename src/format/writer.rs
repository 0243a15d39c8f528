//! `MapWriter`: collects arrays and metadata, then writes a map deterministically (same
//! input, same bytes) to a temp file in the target folder, fsyncs it and renames it.

use super::error::Error;
use super::layout::{
    align_up, checksum, index_checksum, Codec, Dtype, Header, RawEntry, SectionKind, ENTRY_LEN,
    FEATURE_DELTA, HEADER_LEN, MAX_DESCRIPTOR_DIM, MAX_SECTIONS, METADATA_MAX_BYTES, NO_LEVEL,
    SECTION_REQUIRED, VERSION_MAJOR, VERSION_MINOR,
};
use super::metadata::{CameraInfo, LevelInfo, Metadata, PositionGrid};
use super::reader::{within_decode_ratio, Map, Section, DECODE_RATIO};
use super::spool::Stored;
use crate::progress::{Reporter, Silent};
use half::f16;
use std::borrow::Cow;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

/// Descriptors handed to [`MapWriter::add_level`], row-major `[points × dim_full]`.
#[derive(Debug, Clone)]
pub enum Descriptors<'a> {
    /// Converted to f16 with round-to-nearest-even.
    F32(&'a [f32]),
    /// Stored as they are.
    F16(Cow<'a, [f16]>),
}

/// One section as it will be written.
#[derive(Debug, Clone)]
pub(super) struct PendingSection<'a> {
    kind: SectionKind,
    level: u16,
    pub(super) dtype: Dtype,
    pub(super) rows: u64,
    pub(super) cols: u64,
    required: bool,
    pub(super) content: Content<'a>,
}

#[derive(Debug, Clone)]
pub(super) enum Content<'a> {
    /// The array's little-endian bytes, stored with the writer's codec unless `codec` is set.
    Array {
        bytes: Cow<'a, [u8]>,
        codec: Option<Codec>,
    },
    /// Bytes already encoded with `codec` (copied from another map, byte for byte).
    Stored {
        bytes: Cow<'a, [u8]>,
        codec: Codec,
        raw_len: u64,
    },
    /// The array's little-endian bytes in a scratch file ([`super::spool`]), stored with the
    /// writer's codec.
    Spooled(super::spool::SpooledBytes),
}

/// Builds a map. See the crate docs and `spec/format.md` for what each section means.
#[derive(Debug, Clone)]
pub struct MapWriter<'a> {
    pub(super) metadata: Metadata,
    /// By (kind code, level): one section per pair (a second
    /// push replaces the first) in O(log n), so a map of 65,536 sections builds in linear time.
    pub(super) sections: BTreeMap<(u16, u16), PendingSection<'a>>,
    codec: Codec,
    zstd_level: i32,
}

impl Default for MapWriter<'_> {
    fn default() -> Self {
        MapWriter::new(Metadata::default())
    }
}

fn le_bytes<T: bytemuck::Pod>(values: &[T]) -> Cow<'_, [u8]> {
    // The format is little-endian; every supported target is too (checked at compile time).
    const _: () = assert!(
        cfg!(target_endian = "little"),
        "sfpmap needs a little-endian target"
    );
    Cow::Borrowed(bytemuck::cast_slice(values))
}

pub(super) fn owned_bytes<T: bytemuck::Pod>(values: Vec<T>) -> Cow<'static, [u8]> {
    Cow::Owned(bytemuck::cast_slice(&values).to_vec())
}

impl<'a> MapWriter<'a> {
    /// A writer of a map with `metadata` and no sections yet.
    pub fn new(metadata: Metadata) -> Self {
        MapWriter {
            metadata,
            sections: BTreeMap::new(),
            codec: Codec::Raw,
            zstd_level: 3,
        }
    }

    /// The codec of sections added without one, and the zstd level.
    pub fn codec(&self) -> (Codec, i32) {
        (self.codec, self.zstd_level)
    }

    /// The codec for every section added without one (default raw) and the zstd level.
    pub fn set_codec(&mut self, codec: Codec, zstd_level: i32) -> &mut Self {
        self.codec = codec;
        self.zstd_level = zstd_level;
        self
    }

    /// The metadata the map will hold.
    pub fn metadata(&self) -> &Metadata {
        &self.metadata
    }

    /// The metadata, to change before writing.
    pub fn metadata_mut(&mut self) -> &mut Metadata {
        &mut self.metadata
    }

    /// Adds a camera and returns its index (what `add_images` refers to).
    pub fn add_camera(&mut self, camera: CameraInfo) -> u32 {
        self.metadata.cameras.push(camera);
        (self.metadata.cameras.len() - 1) as u32
    }

    #[allow(clippy::too_many_arguments)] // one per entry-table field
    pub(super) fn push(
        &mut self,
        kind: SectionKind,
        level: u16,
        dtype: Dtype,
        rows: u64,
        cols: u64,
        required: bool,
        content: Content<'a>,
    ) {
        let section = PendingSection {
            kind,
            level,
            dtype,
            rows,
            cols,
            required,
            content,
        };
        self.sections.insert((kind.code(), level), section);
    }

    pub(super) fn push_array(
        &mut self,
        kind: SectionKind,
        level: u16,
        dtype: Dtype,
        rows: usize,
        cols: usize,
        bytes: Cow<'a, [u8]>,
    ) {
        self.push_array_flagged(kind, level, dtype, rows, cols, bytes, true);
    }

    /// [`MapWriter::push_array`], `required` or not (a section a reader may skip).
    #[allow(clippy::too_many_arguments)] // one per entry-table field
    pub(super) fn push_array_flagged(
        &mut self,
        kind: SectionKind,
        level: u16,
        dtype: Dtype,
        rows: usize,
        cols: usize,
        bytes: Cow<'a, [u8]>,
        required: bool,
    ) {
        self.push(
            kind,
            level,
            dtype,
            rows as u64,
            cols as u64,
            required,
            Content::Array { bytes, codec: None },
        );
    }

    /// Point positions in world coordinates: stored as f32 relative to `origin`, the
    /// rounded mean of the points, so large world coordinates keep f32 precision.
    pub fn set_points_world(&mut self, positions: &[[f64; 3]]) -> &mut Self {
        let n = positions.len().max(1) as f64;
        let mut origin = [0.0; 3];
        for p in positions {
            for k in 0..3 {
                origin[k] += p[k] / n;
            }
        }
        // Round so the origin itself is a short, exact number in the metadata.
        let origin = origin.map(|o| (o * 1024.0).round() / 1024.0);
        let relative: Vec<[f32; 3]> = positions
            .iter()
            .map(|p| {
                [
                    (p[0] - origin[0]) as f32,
                    (p[1] - origin[1]) as f32,
                    (p[2] - origin[2]) as f32,
                ]
            })
            .collect();
        self.metadata.origin = origin;
        self.clear_q16();
        self.push_array(
            SectionKind::PointPositions,
            NO_LEVEL,
            Dtype::F32,
            relative.len(),
            3,
            owned_bytes(relative),
        );
        self
    }

    /// Point positions relative to the metadata origin, stored on a grid of 65,536 steps per
    /// axis spanning them (format 1.1, `point_positions_q16`, written required) instead of as
    /// f32: 6 bytes a point instead of 12. Returns the grid (its `max_error` is the most any
    /// position moves).
    pub fn set_points_q16(&mut self, relative: &[[f32; 3]]) -> Result<PositionGrid, Error> {
        if let Some(i) = relative
            .iter()
            .position(|p| p.iter().any(|v| !v.is_finite()))
        {
            return Err(Error::invalid(format!("point {i}: position is not finite")));
        }
        let grid = PositionGrid::spanning(relative);
        let q: Vec<[u16; 3]> = relative.iter().map(|&p| grid.quantise(p)).collect();
        self.sections
            .remove(&(SectionKind::PointPositions.code(), NO_LEVEL));
        self.push_array(
            SectionKind::PointPositionsQ16,
            NO_LEVEL,
            Dtype::U16,
            q.len(),
            3,
            owned_bytes(q),
        );
        self.metadata.position_grid = Some(grid);
        Ok(grid)
    }

    /// Drops quantised positions: a map has f32 positions or (1.1) grid ones.
    fn clear_q16(&mut self) {
        self.sections
            .remove(&(SectionKind::PointPositionsQ16.code(), NO_LEVEL));
        self.metadata.position_grid = None;
    }

    /// Point positions already relative to the metadata origin.
    pub fn set_points(&mut self, relative: &'a [[f32; 3]]) -> &mut Self {
        self.clear_q16();
        self.push_array(
            SectionKind::PointPositions,
            NO_LEVEL,
            Dtype::F32,
            relative.len(),
            3,
            le_bytes(relative),
        );
        self
    }

    /// Each point's 8-bit RGB colour (section `point_colors`).
    pub fn set_point_colors(&mut self, colors: &'a [[u8; 3]]) -> &mut Self {
        self.push_array(
            SectionKind::PointColors,
            NO_LEVEL,
            Dtype::U8,
            colors.len(),
            3,
            le_bytes(colors),
        );
        self
    }

    /// Each point's source id, COLMAP `point3D_id` (section `point_ids`).
    pub fn set_point_ids(&mut self, ids: &'a [u64]) -> &mut Self {
        self.push_array(
            SectionKind::PointIds,
            NO_LEVEL,
            Dtype::U64,
            ids.len(),
            1,
            le_bytes(ids),
        );
        self
    }

    /// Database images: names, camera indices, `cam_from_world` (qw qx qy qz tx ty tz) and
    /// optionally the source's ids.
    pub fn set_images(
        &mut self,
        names: &[impl AsRef<str>],
        cameras: &'a [u32],
        cam_from_world: &'a [[f64; 7]],
        ids: Option<&'a [u32]>,
    ) -> Result<&mut Self, Error> {
        let n = names.len();
        if cameras.len() != n || cam_from_world.len() != n || ids.is_some_and(|i| i.len() != n) {
            return Err(Error::invalid(
                "image names, cameras, poses and ids differ in length",
            ));
        }
        let mut offsets = Vec::with_capacity(n + 1);
        let mut joined = Vec::new();
        offsets.push(0u64);
        for name in names {
            joined.extend_from_slice(name.as_ref().as_bytes());
            offsets.push(joined.len() as u64);
        }
        let joined_len = joined.len();
        self.push_array(
            SectionKind::ImagePoses,
            NO_LEVEL,
            Dtype::F64,
            n,
            7,
            le_bytes(cam_from_world),
        );
        self.push_array(
            SectionKind::ImageCameras,
            NO_LEVEL,
            Dtype::U32,
            n,
            1,
            le_bytes(cameras),
        );
        self.push_array(
            SectionKind::ImageNameOffsets,
            NO_LEVEL,
            Dtype::U64,
            n + 1,
            1,
            owned_bytes(offsets),
        );
        self.push_array(
            SectionKind::ImageNames,
            NO_LEVEL,
            Dtype::U8,
            joined_len,
            1,
            Cow::Owned(joined),
        );
        if let Some(ids) = ids {
            self.push_array(
                SectionKind::ImageIds,
                NO_LEVEL,
                Dtype::U32,
                n,
                1,
                le_bytes(ids),
            );
        }
        Ok(self)
    }

    /// Global descriptors `[images × dim]`, row-major, converted to f16.
    pub fn set_image_global(
        &mut self,
        dim: usize,
        descriptors: &[f32],
    ) -> Result<&mut Self, Error> {
        if dim == 0 || descriptors.len() % dim != 0 {
            return Err(Error::invalid(
                "global descriptors are not a whole number of rows",
            ));
        }
        let values: Vec<f16> = descriptors.iter().map(|&v| f16::from_f32(v)).collect();
        self.push_array(
            SectionKind::ImageGlobal,
            NO_LEVEL,
            Dtype::F16,
            values.len() / dim,
            dim,
            owned_bytes(values),
        );
        Ok(self)
    }

    /// Visibility in CSR form: image i sees `points[offsets[i]..offsets[i + 1]]`, optionally
    /// at the pixels `keypoints[...]` (kept so a map can be exported back to COLMAP).
    pub fn set_visibility(
        &mut self,
        offsets: &'a [u64],
        points: &'a [u32],
        keypoints: Option<&'a [[f32; 2]]>,
    ) -> Result<&mut Self, Error> {
        if offsets.last().copied().unwrap_or(0) != points.len() as u64 {
            return Err(Error::invalid(
                "visibility offsets do not end at the number of entries",
            ));
        }
        if keypoints.is_some_and(|k| k.len() != points.len()) {
            return Err(Error::invalid(
                "visibility keypoints differ in length from points",
            ));
        }
        self.push_array(
            SectionKind::VisibilityOffsets,
            NO_LEVEL,
            Dtype::U64,
            offsets.len(),
            1,
            le_bytes(offsets),
        );
        self.push_array(
            SectionKind::VisibilityPoints,
            NO_LEVEL,
            Dtype::U32,
            points.len(),
            1,
            le_bytes(points),
        );
        if let Some(k) = keypoints {
            self.push_array(
                SectionKind::VisibilityKeypoints,
                NO_LEVEL,
                Dtype::F32,
                k.len(),
                2,
                le_bytes(k),
            );
        }
        Ok(self)
    }

    /// Adds a level: its point indices (strictly increasing) and, unless the map is
    /// geometry-only, its descriptors `[points × dim_full]`, split into `short` and `rest`
    /// at `info.dim_short`. `with_rest = false` stores only `short`.
    pub fn add_level(
        &mut self,
        info: LevelInfo,
        points: &'a [u32],
        descriptors: Option<Descriptors<'_>>,
        with_rest: bool,
    ) -> Result<&mut Self, Error> {
        if points.windows(2).any(|w| w[0] >= w[1]) {
            return Err(Error::invalid(format!(
                "level {}: point indices not strictly increasing",
                info.level
            )));
        }
        if info.dim_short > info.dim_full || info.level == NO_LEVEL {
            return Err(Error::invalid(format!(
                "level {}: bad level id or dim_short > dim_full",
                info.level
            )));
        }
        if descriptors.is_some() && info.matched_dims(with_rest) == 0 {
            return Err(Error::invalid(format!(
                "level {}: dim_short 0 and no rest block: no descriptor dimension",
                info.level
            )));
        }
        let level = info.level;
        let (n, full, short) = (
            points.len(),
            info.dim_full as usize,
            info.dim_short as usize,
        );
        if let Some(descriptors) = descriptors {
            let values: Cow<'_, [f16]> = match descriptors {
                Descriptors::F32(v) => Cow::Owned(v.iter().map(|&x| f16::from_f32(x)).collect()),
                Descriptors::F16(v) => v,
            };
            if values.len() != n * full {
                return Err(Error::invalid(format!(
                    "level {level}: {} descriptor values for {n} points × {full} dims",
                    values.len()
                )));
            }
            // The blocks' little-endian bytes straight from the rows: one copy, and none of
            // `rest` when it is not kept.
            let rest = if with_rest { full - short } else { 0 };
            let mut short_block: Vec<u8> = Vec::with_capacity(n * short * 2);
            let mut rest_block: Vec<u8> = Vec::with_capacity(n * rest * 2);
            for row in values.chunks_exact(full.max(1)).take(n) {
                short_block.extend_from_slice(bytemuck::cast_slice(&row[..short]));
                if with_rest {
                    rest_block.extend_from_slice(bytemuck::cast_slice(&row[short..]));
                }
            }
            self.push_array(
                SectionKind::LevelDescShort,
                level,
                Dtype::F16,
                n,
                short,
                Cow::Owned(short_block),
            );
            if with_rest {
                self.push_array(
                    SectionKind::LevelDescRest,
                    level,
                    Dtype::F16,
                    n,
                    rest,
                    Cow::Owned(rest_block),
                );
            }
        }
        self.push_array(
            SectionKind::LevelPoints,
            level,
            Dtype::U32,
            n,
            1,
            le_bytes(points),
        );
        self.metadata.levels.retain(|l| l.level != level);
        self.metadata.levels.push(info);
        self.metadata.levels.sort_by_key(|l| l.level);
        Ok(self)
    }

    /// The level's descriptor basis: `[dim_full × d_in]` row-major f32.
    pub fn set_level_projection(
        &mut self,
        level: u16,
        d_in: usize,
        matrix: Vec<f32>,
    ) -> Result<&mut Self, Error> {
        if d_in == 0 || matrix.len() % d_in != 0 {
            return Err(Error::invalid("projection is not a whole number of rows"));
        }
        let rows = matrix.len() / d_in;
        self.push_array(
            SectionKind::LevelProjection,
            level,
            Dtype::F32,
            rows,
            d_in,
            owned_bytes(matrix),
        );
        Ok(self)
    }

    /// Retrieval by VLAD (format 1.1): the codebook of `level`, `[clusters × dims]` f32 over
    /// the first `dims` stored dimensions of its descriptors, and each image's VLAD,
    /// `[images × clusters·dims]`, converted to f16. Records `retrieval` in the metadata
    /// unless it is already set. Replaces an earlier call's VLAD (a map has one codebook).
    /// Both sections are written optional: a 1.0 reader skips them and reads the rest of the
    /// map, which they do not change the meaning of.
    pub fn set_vlad(
        &mut self,
        level: u16,
        dims: usize,
        centroids: Vec<f32>,
        images: &[f32],
    ) -> Result<&mut Self, Error> {
        if dims == 0 || centroids.is_empty() || centroids.len() % dims != 0 {
            return Err(Error::invalid(
                "VLAD centroids are not a whole number of rows",
            ));
        }
        let width = centroids.len();
        if images.len() % width != 0 {
            return Err(Error::invalid(
                "image VLADs are not a whole number of clusters x dims rows",
            ));
        }
        let values: Vec<f16> = images.iter().map(|&v| f16::from_f32(v)).collect();
        let codebook = SectionKind::LevelVladCentroids.code();
        self.sections.retain(|&(kind, _), _| kind != codebook);
        self.push(
            SectionKind::LevelVladCentroids,
            level,
            Dtype::F32,
            (width / dims) as u64,
            dims as u64,
            false,
            Content::Array {
                bytes: owned_bytes(centroids),
                codec: None,
            },
        );
        self.push(
            SectionKind::ImageVlad,
            NO_LEVEL,
            Dtype::F16,
            (values.len() / width) as u64,
            width as u64,
            false,
            Content::Array {
                bytes: owned_bytes(values),
                codec: None,
            },
        );
        if self.metadata.retrieval.is_none() {
            self.metadata.retrieval = Some(super::metadata::Retrieval::Vlad.name().to_string());
        }
        Ok(self)
    }

    /// Adds any section from its little-endian array bytes (for kinds a newer minor defines,
    /// and for tests). `codec = None` uses the writer's codec.
    #[allow(clippy::too_many_arguments)]
    pub fn add_raw_section(
        &mut self,
        kind: SectionKind,
        level: u16,
        dtype: Dtype,
        rows: u64,
        cols: u64,
        required: bool,
        bytes: Cow<'a, [u8]>,
        codec: Option<Codec>,
    ) -> Result<&mut Self, Error> {
        if rows
            .checked_mul(cols)
            .and_then(|n| n.checked_mul(dtype.size()))
            != Some(bytes.len() as u64)
        {
            return Err(Error::invalid(format!(
                "{kind}: {rows}x{cols} {} does not match {} bytes",
                dtype.name(),
                bytes.len()
            )));
        }
        self.push(
            kind,
            level,
            dtype,
            rows,
            cols,
            required,
            Content::Array { bytes, codec },
        );
        Ok(self)
    }

    /// Makes the map a catalog (spec "Catalogs"): `listing` in the metadata, place `i`'s
    /// images at rows `place_images[i]..place_images[i + 1]` of `image_vlad`
    /// (`[images × clusters·dims]`), on the codebook `centroids` (`[clusters × dims]`) in the
    /// basis `projection` (`[dims × listing.d_in]`).
    pub fn set_catalog(
        &mut self,
        listing: &super::catalog::Listing,
        place_images: &[u64],
        projection: &[f32],
        centroids: &[f32],
        dims: usize,
        image_vlad: &[f32],
    ) -> Result<&mut Self, Error> {
        let d_in = listing.d_in as usize;
        let clusters = centroids.len() / dims.max(1);
        let width = clusters * dims;
        if dims == 0
            || place_images.len() != listing.places.len() + 1
            || projection.len() != dims * d_in
            || centroids.len() != width
            || width == 0
            || image_vlad.len() % width != 0
            || place_images.last() != Some(&((image_vlad.len() / width) as u64))
        {
            return Err(Error::invalid("catalog arrays of inconsistent shapes"));
        }
        self.metadata.extra.insert(
            super::catalog::CATALOG_KEY.into(),
            serde_json::to_value(listing).map_err(|e| Error::invalid(e.to_string()))?,
        );
        let vlad: Vec<f16> = image_vlad.iter().map(|&v| f16::from_f32(v)).collect();
        let arrays: [(SectionKind, Dtype, usize, usize, Vec<u8>); 4] = [
            (
                SectionKind::PlaceImages,
                Dtype::U64,
                place_images.len(),
                1,
                bytemuck::cast_slice(place_images).to_vec(),
            ),
            (
                SectionKind::CatalogProjection,
                Dtype::F32,
                dims,
                d_in,
                le_bytes(projection).into_owned(),
            ),
            (
                SectionKind::CatalogVladCentroids,
                Dtype::F32,
                clusters,
                dims,
                le_bytes(centroids).into_owned(),
            ),
            (
                SectionKind::CatalogImageVlad,
                Dtype::F16,
                vlad.len() / width,
                width,
                le_bytes(&vlad).into_owned(),
            ),
        ];
        for (kind, dtype, rows, cols, bytes) in arrays {
            self.push_array(kind, NO_LEVEL, dtype, rows, cols, Cow::Owned(bytes));
        }
        Ok(self)
    }

    /// Adds one of `map`'s sections exactly as `map` stores it (copied byte for byte, no
    /// decode), after checking it as its first access would (checksum, decoding, contents), so
    /// a damaged section is never passed on.
    pub fn copy_section(
        &mut self,
        map: &'a Map<'_>,
        section: &Section,
    ) -> Result<&mut Self, Error> {
        map.check_section(section)?;
        let stored = map.stored_bytes(section)?;
        self.push(
            section.kind,
            section.level.unwrap_or(NO_LEVEL),
            section.dtype,
            section.rows,
            section.cols,
            section.required,
            Content::Stored {
                bytes: Cow::Borrowed(stored),
                codec: section.codec,
                raw_len: section.raw_len,
            },
        );
        Ok(self)
    }

    /// Writes the map to `path` through [`crate::output::AtomicFile`] (temp file in the same
    /// folder, fsync, rename): an existing `path` is replaced only once the new file is
    /// complete, and never when it is not a regular file.
    pub fn write(&self, path: &Path, reporter: &dyn Reporter) -> Result<u64, Error> {
        let encoded = self.encode(reporter)?;
        let mut out = crate::output::AtomicFile::create(path)?;
        reporter.start("writing", Some(encoded.file_len));
        encoded.write_to(&mut out, path, reporter)?;
        out.commit()?;
        reporter.finish();
        Ok(encoded.file_len)
    }

    /// The length of the file [`write`](Self::write) would write, without writing it (every
    /// section is encoded, so it costs what encoding does).
    pub fn encoded_len(&self) -> Result<u64, Error> {
        Ok(self.encode(&Silent)?.file_len)
    }

    /// The map's bytes in memory.
    pub fn to_bytes(&self) -> Result<Vec<u8>, Error> {
        let encoded = self.encode(&Silent)?;
        let mut out = Vec::with_capacity(encoded.file_len as usize);
        encoded.write_to(&mut out, Path::new("<memory>"), &Silent)?;
        Ok(out)
    }

    /// The codec an array of `dtype` is stored with: `codec`, else the writer's; `delta`
    /// applies to integer arrays, zstd stands in elsewhere.
    fn array_codec(&self, dtype: Dtype, codec: Option<Codec>) -> Codec {
        match codec.unwrap_or(self.codec) {
            Codec::Delta if super::delta::width(dtype).is_none() => Codec::Zstd,
            codec => codec,
        }
    }

    /// An array's bytes as stored, and the codec they are stored with.
    fn encode_array<'b>(
        &self,
        dtype: Dtype,
        bytes: Cow<'b, [u8]>,
        codec: Option<Codec>,
    ) -> Result<(Cow<'b, [u8]>, Codec), Error> {
        let raw_len = bytes.len() as u64;
        Ok(match self.array_codec(dtype, codec) {
            Codec::Raw => (bytes, Codec::Raw),
            Codec::Delta => {
                let stream = super::delta::encode(dtype, &bytes);
                let z = super::delta::compress(&stream, raw_len, DECODE_RATIO)
                    .map_err(|e| Error::invalid(format!("zstd: {e}")))?;
                // Values that are not nearly sorted gain nothing: stored raw.
                if z.len() as u64 >= raw_len {
                    (bytes, Codec::Raw)
                } else {
                    (Cow::Owned(z), Codec::Delta)
                }
            }
            Codec::Zstd => {
                let z = zstd::bulk::compress(&bytes, self.zstd_level)
                    .map_err(|e| Error::invalid(format!("zstd: {e}")))?;
                // A reader refuses a raw length past decode_cap(file_len) and all of them
                // together past decode_budget(file_len); the file is at least as long as its
                // sections, so keeping each section within 256 x its compressed length keeps
                // every map we write readable.
                if !within_decode_ratio(raw_len, z.len() as u64) {
                    (bytes, Codec::Raw)
                } else {
                    (Cow::Owned(z), Codec::Zstd)
                }
            }
        })
    }

    /// Encodes every section and lays out the file.
    fn encode(&self, reporter: &dyn Reporter) -> Result<Encoded<'_>, Error> {
        // Never write a map that open refuses.
        super::views::check_metadata_values(&self.metadata).map_err(|e| match e {
            Error::BadMetadata { message } => Error::invalid(message),
            e => e,
        })?;
        if let Some(s) = self
            .sections
            .values()
            .find(|s| s.kind.has_descriptor_columns() && s.cols > MAX_DESCRIPTOR_DIM)
        {
            return Err(Error::invalid(format!(
                "{}: {} columns, more than {MAX_DESCRIPTOR_DIM}",
                s.kind, s.cols
            )));
        }
        // A point too far from the origin for f32 (or a NaN the caller passed) would be stored
        // as inf/NaN, which no localizer can use: refuse it, naming the point.
        if let Some(s) = self
            .sections
            .get(&(SectionKind::PointPositions.code(), NO_LEVEL))
        {
            if let Content::Array { bytes, .. } = &s.content {
                let bad = bytes
                    .chunks_exact(4)
                    .position(|b| !f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite());
                if let Some(i) = bad {
                    return Err(Error::invalid(format!(
                        "point {}: position is not finite relative to the origin (too far for f32, or NaN)",
                        i / 3
                    )));
                }
            }
        }
        // Canonical order (`SectionKind::file_order`: shared sections, then level by level),
        // so the bytes do not depend on the order of the calls.
        // `chunk_checksums` is the writer's own (below): one handed in is not copied.
        let mut order: Vec<&PendingSection<'a>> = self
            .sections
            .values()
            .filter(|s| s.kind != SectionKind::ChunkChecksums)
            .collect();
        order.sort_by_key(|s| s.kind.file_order(s.level));
        reporter.start("encoding", Some(order.len() as u64));
        let mut blocks = Vec::with_capacity(order.len());
        for s in order {
            let (bytes, codec, raw_len) = match &s.content {
                // A zstd section copied from another map may compress past the ratio this
                // writer keeps to: it is stored decoded instead.
                Content::Stored {
                    bytes,
                    codec: codec @ (Codec::Zstd | Codec::Delta),
                    raw_len,
                } if !within_decode_ratio(*raw_len, bytes.len() as u64) => {
                    let raw = decode_stored(*codec, s.dtype, bytes, *raw_len)?;
                    (Stored::Memory(Cow::Owned(raw)), Codec::Raw, *raw_len)
                }
                Content::Stored {
                    bytes,
                    codec,
                    raw_len,
                } => (Stored::Memory(Cow::Borrowed(&bytes[..])), *codec, *raw_len),
                Content::Array { bytes, codec } => {
                    let raw_len = bytes.len() as u64;
                    let (bytes, codec) =
                        self.encode_array(s.dtype, Cow::Borrowed(bytes), *codec)?;
                    (Stored::Memory(bytes), codec, raw_len)
                }
                // Stored raw from where it is; another codec compresses it whole, as it
                // would the array in memory.
                Content::Spooled(spooled) => match self.array_codec(s.dtype, None) {
                    Codec::Raw => (Stored::Spooled(spooled), Codec::Raw, spooled.len()),
                    _ => {
                        let bytes = Cow::Owned(spooled.read_all()?);
                        let (bytes, codec) = self.encode_array(s.dtype, bytes, None)?;
                        (Stored::Memory(bytes), codec, spooled.len())
                    }
                },
            };
            blocks.push((s, bytes, codec, raw_len));
            reporter.advance(1);
        }
        reporter.finish();
        // (1.2) Chunk checksums, last, when a section spans more than one chunk, so a reader
        // checks a large section where it reads it (`format/chunks.rs`).
        // Each section's checksum, and its chunks' where the map has them: a spooled
        // section is read once for both.
        let chunked = super::chunks::writes_chunk_checksums(blocks.iter().map(|b| b.1.len()));
        let mut sums = Vec::new();
        let mut checksums = Vec::with_capacity(blocks.len() + 1);
        for (_, bytes, _, _) in &blocks {
            checksums.push(bytes.checksums(chunked.then_some(&mut sums))?);
        }
        let chunk_pending;
        if chunked {
            chunk_pending = PendingSection {
                kind: SectionKind::ChunkChecksums,
                level: NO_LEVEL,
                dtype: Dtype::U64,
                rows: sums.len() as u64,
                cols: 1,
                required: false,
                content: Content::Array {
                    bytes: Cow::Borrowed(&[]),
                    codec: Some(Codec::Raw),
                },
            };
            let bytes = owned_bytes(sums);
            let raw_len = bytes.len() as u64;
            checksums.push(checksum(&bytes));
            blocks.push((&chunk_pending, Stored::Memory(bytes), Codec::Raw, raw_len));
        }
        if blocks.len() > MAX_SECTIONS as usize {
            return Err(Error::invalid(format!(
                "{} sections, more than {MAX_SECTIONS} (with chunk checksums)",
                blocks.len()
            )));
        }

        let mut metadata =
            serde_json::to_vec(&self.metadata).map_err(|e| Error::invalid(e.to_string()))?;
        metadata.shrink_to_fit();
        if metadata.len() as u64 > METADATA_MAX_BYTES {
            return Err(Error::MetadataTooLarge {
                len: metadata.len() as u64,
                max: METADATA_MAX_BYTES,
            });
        }
        let table_end = (HEADER_LEN + blocks.len() * ENTRY_LEN) as u64;
        let metadata_end = table_end + metadata.len() as u64;
        let mut cursor = metadata_end;
        let mut table = Vec::with_capacity(blocks.len() * ENTRY_LEN);
        let mut sections = Vec::with_capacity(blocks.len());
        // Codec `delta` is 1.1 too; in a required section it is also a header feature.
        let minor = blocks
            .iter()
            .map(|(s, _, codec, _)| s.kind.since_minor().max(u16::from(*codec == Codec::Delta)))
            .max()
            .unwrap_or(0);
        let features = if blocks
            .iter()
            .any(|(s, _, codec, _)| s.required && *codec == Codec::Delta)
        {
            FEATURE_DELTA
        } else {
            0
        };
        debug_assert!(minor <= VERSION_MINOR);
        for ((s, bytes, codec, raw_len), checksum) in blocks.into_iter().zip(checksums) {
            let offset = align_up(cursor).ok_or_else(|| Error::invalid("file too large"))?;
            let entry = RawEntry {
                kind: s.kind.code(),
                level: s.level,
                dtype: s.dtype as u8,
                codec: codec as u8,
                flags: if s.required { SECTION_REQUIRED } else { 0 },
                reserved: 0,
                rows: s.rows,
                cols: s.cols,
                offset,
                stored_len: bytes.len(),
                raw_len,
                checksum,
                reserved2: 0,
            };
            table.extend_from_slice(&entry.encode());
            cursor = offset + bytes.len();
            sections.push((offset, bytes));
        }
        let mut header = Header {
            major: VERSION_MAJOR,
            minor,
            flags: features,
            section_count: sections.len() as u32,
            entry_len: ENTRY_LEN as u32,
            metadata_offset: table_end,
            metadata_len: metadata.len() as u64,
            file_len: cursor,
            index_checksum: 0,
        };
        header.index_checksum = index_checksum(&header.encode()[..56], &table, &metadata);
        Ok(Encoded {
            header,
            table,
            metadata,
            sections,
            file_len: cursor,
        })
    }
}

struct Encoded<'w> {
    header: Header,
    table: Vec<u8>,
    metadata: Vec<u8>,
    sections: Vec<(u64, Stored<'w>)>,
    file_len: u64,
}

impl Encoded<'_> {
    /// Writes the file to `out` (`path` names it in errors).
    fn write_to(
        &self,
        out: &mut impl Write,
        path: &Path,
        reporter: &dyn Reporter,
    ) -> Result<(), Error> {
        const ZEROS: [u8; 64] = [0; 64];
        let io = |e| Error::io(path, e);
        out.write_all(&self.header.encode()).map_err(io)?;
        out.write_all(&self.table).map_err(io)?;
        out.write_all(&self.metadata).map_err(io)?;
        let mut pos = self.header.metadata_offset + self.header.metadata_len;
        reporter.advance(pos);
        for (offset, bytes) in &self.sections {
            out.write_all(&ZEROS[..(offset - pos) as usize])
                .map_err(io)?;
            reporter.advance(offset - pos);
            match bytes {
                // Written in chunks so progress moves on large sections.
                Stored::Memory(bytes) => {
                    for chunk in bytes.chunks(8 << 20) {
                        out.write_all(chunk).map_err(io)?;
                        reporter.advance(chunk.len() as u64);
                    }
                }
                Stored::Spooled(spooled) => spooled.copy_to(out, |n| reporter.advance(n))?,
            }
            pos = offset + bytes.len();
        }
        out.flush().map_err(io)
    }
}

/// A copied section's array, decoded (to store it raw when it compresses past the ratio).
fn decode_stored(codec: Codec, dtype: Dtype, bytes: &[u8], raw_len: u64) -> Result<Vec<u8>, Error> {
    let zstd = |e: std::io::Error| Error::invalid(format!("zstd: {e}"));
    match codec {
        Codec::Delta => {
            let mut raw = vec![0u8; raw_len as usize];
            super::delta::decompress(dtype, bytes, &mut raw).map_err(Error::invalid)?;
            Ok(raw)
        }
        _ => zstd::bulk::decompress(bytes, raw_len as usize).map_err(zstd),
    }
}
