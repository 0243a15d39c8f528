//! Typed views of a map's sections, and the checks that tie sections and metadata together.

use super::error::Error;
use super::layout::{SectionKind, MAX_CAMERA_PARAMS, MAX_DESCRIPTOR_DIM, MAX_IMAGE_SIDE};
use super::metadata::{LevelInfo, Metadata};
use super::pq::Pq;
use super::reader::{cast, Map, Section, SectionIndex};
use half::f16;
use std::borrow::Cow;

/// Checks, from the table and metadata alone, that the sections fit together and that every
/// count and size the metadata states is within the spec's limits, so nothing is sized from
/// an unchecked number. Returns the section index and the point and image counts.
pub(crate) fn check_shapes(
    metadata: &Metadata,
    sections: &[Section],
) -> Result<(SectionIndex, u64, u64), Error> {
    if metadata.format != super::metadata::FORMAT_NAME {
        return Err(Error::BadMetadata {
            message: format!("format is {:?}, expected \"sfpmap\"", metadata.format),
        });
    }
    check_metadata_values(metadata)?;
    let index = SectionIndex::build(sections)?;
    let find = |kind, level| index.get(sections, kind, level);
    let need = |kind, level| find(kind, level).ok_or(Error::MissingSection { kind, level });
    let rows_must = |s: Option<&Section>, rows: u64, what: &str| match s {
        Some(s) if s.rows != rows => Err(Error::inconsistent(format!(
            "{} has {} rows, expected {rows} ({what})",
            s.reference(),
            s.rows
        ))),
        _ => Ok(()),
    };

    let n_points = match (
        find(SectionKind::PointPositions, None),
        find(SectionKind::PointPositionsQ16, None),
    ) {
        (Some(_), None) if metadata.position_grid.is_some() => {
            return Err(Error::BadMetadata {
                message: "position_grid without point_positions_q16".into(),
            })
        }
        (Some(p), None) => p.rows,
        // 1.1: positions on a grid, which the metadata states.
        (None, Some(q)) => {
            let grid = metadata.position_grid.ok_or_else(|| Error::BadMetadata {
                message: "point_positions_q16 without a position_grid".into(),
            })?;
            if !grid.is_valid() {
                return Err(Error::BadMetadata {
                    message: "position_grid: min and step must be finite, step above 0, and every grid point a finite f32".into(),
                });
            }
            q.rows
        }
        (Some(_), Some(q)) => {
            return Err(Error::inconsistent(format!(
                "{} beside point_positions (a map has one of them)",
                q.reference()
            )))
        }
        (None, None) => need(SectionKind::PointPositions, None)?.rows,
    };
    if n_points > u64::from(u32::MAX) {
        return Err(Error::inconsistent(
            "more points than u32 indices can address",
        ));
    }
    rows_must(
        find(SectionKind::PointColors, None),
        n_points,
        "one per point",
    )?;
    rows_must(find(SectionKind::PointIds, None), n_points, "one per point")?;

    let mut previous = None;
    for level in &metadata.levels {
        if previous.is_some_and(|p| p >= level.level) || level.level == super::layout::NO_LEVEL {
            return Err(Error::BadMetadata {
                message: "levels must be sorted by id, unique and below 65535".into(),
            });
        }
        previous = Some(level.level);
        if level.dim_short > level.dim_full {
            return Err(Error::BadMetadata {
                message: format!("level {}: dim_short > dim_full", level.level),
            });
        }
        let l = Some(level.level);
        let n = need(SectionKind::LevelPoints, l)?.rows;
        if n > n_points {
            // Strictly increasing indices below `points` cannot be more than `points`.
            return Err(Error::inconsistent(format!(
                "level {} holds {n} points of {n_points}",
                level.level
            )));
        }
        let short = find(SectionKind::LevelDescShort, l);
        let rest = find(SectionKind::LevelDescRest, l);
        let pq = super::pq::check_shapes(
            level,
            n,
            find(SectionKind::LevelPqCodebook, l),
            find(SectionKind::LevelPqCodes, l),
            find(SectionKind::LevelPqOrder, l),
        )?;
        if pq.is_some() && (metadata.geometry_only || short.is_some() || rest.is_some()) {
            return Err(Error::inconsistent(format!(
                "level {}: PQ codes beside f16 descriptor blocks or in a geometry-only map",
                level.level
            )));
        }
        if pq.is_some() {
            // The codes are the level's descriptors (1.1): no f16 block is required.
        } else if !metadata.geometry_only {
            let short = need(SectionKind::LevelDescShort, l)?;
            rows_must(Some(short), n, "one per level point")?;
            if short.cols != u64::from(level.dim_short) {
                return Err(Error::inconsistent(format!(
                    "{} has {} columns, metadata says dim_short {}",
                    short.reference(),
                    short.cols,
                    level.dim_short
                )));
            }
        } else if short.is_some() || rest.is_some() {
            return Err(Error::inconsistent(format!(
                "geometry-only map has descriptors for level {}",
                level.level
            )));
        }
        if !metadata.geometry_only && pq.is_none() && level.matched_dims(rest.is_some()) == 0 {
            return Err(Error::BadMetadata {
                message: format!(
                    "level {}: dim_short is 0 and there is no rest block: no descriptor dimension",
                    level.level
                ),
            });
        }
        if let Some(rest) = rest {
            rows_must(Some(rest), n, "one per level point")?;
            if rest.cols != u64::from(level.dim_full - level.dim_short) {
                return Err(Error::inconsistent(format!(
                    "{} has {} columns, metadata says dim_full - dim_short = {}",
                    rest.reference(),
                    rest.cols,
                    level.dim_full - level.dim_short
                )));
            }
        }
        rows_must(
            find(SectionKind::LevelProjection, l),
            u64::from(level.dim_full),
            "one per stored dimension",
        )?;
    }
    for s in sections
        .iter()
        .filter(|s| s.kind.is_per_level() && s.skipped.is_none())
    {
        let level = s.level.unwrap_or(super::layout::NO_LEVEL);
        // Sorted above, so this is a binary search.
        if metadata.level(level).is_none() {
            return Err(Error::inconsistent(format!(
                "{} belongs to a level the metadata does not list",
                s.reference()
            )));
        }
    }

    let image_kinds = [
        SectionKind::ImageCameras,
        SectionKind::ImageIds,
        SectionKind::ImageNameOffsets,
        SectionKind::ImageNames,
        SectionKind::ImageGlobal,
        SectionKind::ImageVlad,
        SectionKind::ImageIndexImages,
        SectionKind::ImageIndexNeighbours,
        SectionKind::VisibilityOffsets,
    ];
    let n_images = match find(SectionKind::ImagePoses, None) {
        Some(poses) => poses.rows,
        None => {
            if let Some(s) = image_kinds.iter().find_map(|&k| find(k, None)) {
                return Err(Error::inconsistent(format!(
                    "{} present without image_poses",
                    s.reference()
                )));
            }
            0
        }
    };
    if n_images > 0 || find(SectionKind::ImagePoses, None).is_some() {
        rows_must(
            Some(need(SectionKind::ImageCameras, None)?),
            n_images,
            "one per image",
        )?;
        rows_must(
            Some(need(SectionKind::ImageNameOffsets, None)?),
            n_images + 1,
            "images + 1",
        )?;
        need(SectionKind::ImageNames, None)?;
        rows_must(find(SectionKind::ImageIds, None), n_images, "one per image")?;
        rows_must(
            find(SectionKind::ImageGlobal, None),
            n_images,
            "one per image",
        )?;
        rows_must(
            find(SectionKind::ImageVlad, None),
            n_images,
            "one per image",
        )?;
    }
    check_vlad(metadata, sections, find(SectionKind::ImageVlad, None))?;
    super::index::check_shapes(metadata, |kind| find(kind, None), n_images)?;
    match (
        find(SectionKind::VisibilityOffsets, None),
        find(SectionKind::VisibilityPoints, None),
    ) {
        (Some(offsets), Some(points)) => {
            rows_must(Some(offsets), n_images + 1, "images + 1")?;
            rows_must(
                find(SectionKind::VisibilityKeypoints, None),
                points.rows,
                "one per visibility entry",
            )?;
        }
        (None, None) => {
            if let Some(k) = find(SectionKind::VisibilityKeypoints, None) {
                return Err(Error::inconsistent(format!(
                    "{} present without visibility",
                    k.reference()
                )));
            }
        }
        (Some(_), None) => {
            return Err(Error::MissingSection {
                kind: SectionKind::VisibilityPoints,
                level: None,
            })
        }
        (None, Some(_)) => {
            return Err(Error::MissingSection {
                kind: SectionKind::VisibilityOffsets,
                level: None,
            })
        }
    }
    // (1.2) One checksum per chunk of every other section, so each chunk has one.
    if let Some(chunks) = find(SectionKind::ChunkChecksums, None) {
        match super::chunks::chunk_rows(sections).map(|(_, rows)| rows) {
            Some(rows) if rows == chunks.rows => {}
            expected => {
                return Err(Error::inconsistent(format!(
                    "{} has {} rows, the other sections have {} chunks of {} bytes",
                    chunks.reference(),
                    chunks.rows,
                    expected.map_or("more than 2^64".into(), |n| n.to_string()),
                    super::layout::CHUNK_LEN
                )))
            }
        }
    }
    Ok((index, n_points, n_images))
}

/// 1.1 retrieval: at most one level has a VLAD codebook, over at most its `short`
/// dimensions (so `slice --short` keeps it usable), and `image_vlad` is present with it, one
/// column per codebook value.
fn check_vlad(
    metadata: &Metadata,
    sections: &[Section],
    image_vlad: Option<&Section>,
) -> Result<(), Error> {
    let mut codebooks = sections
        .iter()
        .filter(|s| s.kind == SectionKind::LevelVladCentroids && s.skipped.is_none());
    let codebook = codebooks.next();
    if let Some(second) = codebooks.next() {
        return Err(Error::inconsistent(format!(
            "{} is a second VLAD codebook (a map has at most one)",
            second.reference()
        )));
    }
    let (codebook, vlad) = match (codebook, image_vlad) {
        (None, None) => return Ok(()),
        (Some(c), Some(v)) => (c, v),
        (Some(_), None) => {
            return Err(Error::MissingSection {
                kind: SectionKind::ImageVlad,
                level: None,
            })
        }
        (None, Some(_)) => {
            return Err(Error::MissingSection {
                kind: SectionKind::LevelVladCentroids,
                level: None,
            })
        }
    };
    if metadata.geometry_only {
        return Err(Error::inconsistent(format!(
            "{} in a geometry-only map",
            codebook.reference()
        )));
    }
    let dim_short = codebook
        .level
        .and_then(|l| metadata.level(l))
        .map_or(0, |l| u64::from(l.dim_short));
    if codebook.rows == 0 || codebook.cols == 0 || codebook.cols > dim_short {
        return Err(Error::inconsistent(format!(
            "{} is {} x {}: needs at least one centroid of 1 to dim_short ({dim_short}) dimensions",
            codebook.reference(),
            codebook.rows,
            codebook.cols
        )));
    }
    if codebook.rows.checked_mul(codebook.cols) != Some(vlad.cols) {
        return Err(Error::inconsistent(format!(
            "{} has {} columns, expected clusters x dims = {} x {}",
            vlad.reference(),
            vlad.cols,
            codebook.rows,
            codebook.cols
        )));
    }
    Ok(())
}

/// What the metadata states that anything is sized from, within the spec's limits (camera
/// sizes and parameter counts, `dim_full`), and its floats finite (JSON has no NaN: a writer
/// would write `null`, which no reader parses as a number). Open and the writer both check.
pub(crate) fn check_metadata_values(metadata: &Metadata) -> Result<(), Error> {
    check_cameras(metadata)?;
    for level in &metadata.levels {
        if u64::from(level.dim_full) > MAX_DESCRIPTOR_DIM {
            return Err(Error::BadMetadata {
                message: format!(
                    "level {}: dim_full {} is over the limit: at most {MAX_DESCRIPTOR_DIM}",
                    level.level, level.dim_full
                ),
            });
        }
        if !level.stride.is_finite() {
            return Err(Error::BadMetadata {
                message: format!("level {}: stride is not finite", level.level),
            });
        }
    }
    if metadata.origin.iter().any(|o| !o.is_finite()) {
        return Err(Error::BadMetadata {
            message: "origin is not finite".into(),
        });
    }
    Ok(())
}

/// Camera sizes in `1..=MAX_IMAGE_SIDE` and at most `MAX_CAMERA_PARAMS` parameters.
fn check_cameras(metadata: &Metadata) -> Result<(), Error> {
    for (i, c) in metadata.cameras.iter().enumerate() {
        let side = 1..=MAX_IMAGE_SIDE;
        let message = if !side.contains(&c.width) || !side.contains(&c.height) {
            format!(
                "camera {i}: size {}x{} is outside 1..={MAX_IMAGE_SIDE} pixels",
                c.width, c.height
            )
        } else if c.params.len() > MAX_CAMERA_PARAMS {
            format!(
                "camera {i}: {} parameters, more than {MAX_CAMERA_PARAMS}",
                c.params.len()
            )
        } else if c.params.iter().any(|p| !p.is_finite()) {
            format!("camera {i}: a parameter is not finite")
        } else {
            continue;
        };
        return Err(Error::BadMetadata { message });
    }
    Ok(())
}

/// Whether [`check_contents`]' rules for `kind` hold value by value (none, or each value on
/// its own), so that a part of a section is checked without the rest: what lets a reader
/// check it a chunk at a time (1.2, `chunks.rs`). A kind given a rule across values (order,
/// a total) must leave this list.
pub(crate) fn rules_hold_per_value(kind: SectionKind) -> bool {
    matches!(
        kind,
        SectionKind::LevelDescShort
            | SectionKind::LevelDescRest
            | SectionKind::VisibilityPoints
            | SectionKind::VisibilityKeypoints
    )
}

/// Checks what one section's decoded contents must satisfy (indices in range, offsets
/// monotonic). Runs once per section, on first access (or per chunk, above).
pub(crate) fn check_contents(map: &Map<'_>, section: &Section, bytes: &[u8]) -> Result<(), Error> {
    let bad = |what: String| {
        Err(Error::inconsistent(format!(
            "{}: {what}",
            section.reference()
        )))
    };
    match section.kind {
        SectionKind::LevelPoints => {
            let points = cast::<u32>(bytes);
            if let Some(w) = points.windows(2).find(|w| w[0] >= w[1]) {
                return bad(format!(
                    "indices not strictly increasing ({} then {})",
                    w[0], w[1]
                ));
            }
            if let Some(&last) = points.last() {
                if u64::from(last) >= map.n_points() {
                    return bad(format!(
                        "index {last} out of range for {} points",
                        map.n_points()
                    ));
                }
            }
        }
        SectionKind::VisibilityPoints => {
            let points = cast::<u32>(bytes);
            if let Some(&p) = points.iter().find(|&&p| u64::from(p) >= map.n_points()) {
                return bad(format!(
                    "index {p} out of range for {} points",
                    map.n_points()
                ));
            }
        }
        // The writer never stores one (see `MapWriter`), and a slice or a localizer would carry
        // a NaN or inf position on into poses.
        SectionKind::PointPositions => {
            if let Some(i) = cast::<f32>(bytes).iter().position(|v| !v.is_finite()) {
                return bad(format!("point {}: position is not finite", i / 3));
            }
        }
        SectionKind::ImageCameras => {
            let n = map.metadata().cameras.len() as u64;
            if let Some(&c) = cast::<u32>(bytes).iter().find(|&&c| u64::from(c) >= n) {
                return bad(format!("camera index {c} out of range for {n} cameras"));
            }
        }
        SectionKind::ImageNameOffsets | SectionKind::VisibilityOffsets => {
            let target = if section.kind == SectionKind::ImageNameOffsets {
                SectionKind::ImageNames
            } else {
                SectionKind::VisibilityPoints
            };
            let end = map.find(target, None).map_or(0, |s| s.rows);
            let offsets = cast::<u64>(bytes);
            if offsets.first().is_some_and(|&o| o != 0) {
                return bad("offsets do not start at 0".into());
            }
            if offsets.windows(2).any(|w| w[0] > w[1]) {
                return bad("offsets decrease".into());
            }
            if offsets.last().is_some_and(|&o| o != end) {
                return bad(format!(
                    "offsets end at {}, expected {end}",
                    offsets[offsets.len() - 1]
                ));
            }
        }
        SectionKind::LevelPqCodes => {
            let codebook = map
                .find(SectionKind::LevelPqCodebook, section.level)
                .ok_or(Error::MissingSection {
                    kind: SectionKind::LevelPqCodebook,
                    level: section.level,
                })?;
            if let Err(what) = super::pq::check_codes(bytes, section.cols, codebook) {
                return bad(what);
            }
        }
        SectionKind::LevelPqOrder => {
            if let Err(what) = super::pq::check_order(&cast::<u16>(bytes)) {
                return bad(what);
            }
        }
        SectionKind::ImageIndexOffsets
        | SectionKind::ImageIndexImages
        | SectionKind::ImageIndexNeighbours => {
            if let Err(what) = super::index::check_contents(section.kind, bytes, map.n_images()) {
                return bad(what);
            }
        }
        // A NaN centroid would make every VLAD (or PQ reconstruction) it touches NaN, every
        // ranking (or match) silently arbitrary, and (1.3) an image index's lists.
        SectionKind::LevelPqCodebook
        | SectionKind::LevelVladCentroids
        | SectionKind::ImageIndexCentroids
            if cast::<f32>(bytes).iter().any(|v| !v.is_finite()) =>
        {
            return bad("a centroid value is not finite".into());
        }
        _ => {}
    }
    Ok(())
}

/// Checks that need two sections at once (image names are UTF-8 between their offsets).
/// Reads only those two sections.
pub(crate) fn check_cross_sections(map: &Map<'_>) -> Result<(), Error> {
    let (Some(offsets), Some(names)) = (
        map.find(SectionKind::ImageNameOffsets, None),
        map.find(SectionKind::ImageNames, None),
    ) else {
        return Ok(());
    };
    let offsets = map.section_array::<u64>(offsets)?;
    let names = map.section_bytes(names)?;
    for i in 0..offsets.len().saturating_sub(1) {
        image_name(&offsets, names, i)?;
    }
    Ok(())
}

/// Name `i` between its offsets (checked monotonic and ending at `names.len()` on access).
fn image_name<'m>(offsets: &[u64], names: &'m [u8], i: usize) -> Result<&'m str, Error> {
    let (start, end) = (offsets[i] as usize, offsets[i + 1] as usize);
    std::str::from_utf8(&names[start..end])
        .map_err(|_| Error::inconsistent(format!("image {i}: name is not UTF-8")))
}

/// The map's database images.
#[derive(Debug, Clone)]
pub struct Images<'m> {
    /// `cam_from_world` per image: qw qx qy qz tx ty tz.
    pub poses: Cow<'m, [[f64; 7]]>,
    /// Index into the metadata's cameras per image.
    pub cameras: Cow<'m, [u32]>,
    /// Source ids (COLMAP `image_id`), if stored.
    pub ids: Option<Cow<'m, [u32]>>,
    name_offsets: Cow<'m, [u64]>,
    names: &'m [u8],
}

impl<'m> Images<'m> {
    /// How many images.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// The name of image `i`.
    pub fn name(&self, i: usize) -> Result<&'m str, Error> {
        image_name(&self.name_offsets, self.names, i)
    }
}

/// Image → point ids, in CSR form.
#[derive(Debug, Clone)]
pub struct Visibility<'m> {
    /// `[images + 1]`: image `i`'s points are `points[offsets[i]..offsets[i + 1]]`.
    pub offsets: Cow<'m, [u64]>,
    /// The images' point ids, end to end.
    pub points: Cow<'m, [u32]>,
    /// The pixel of each entry, if stored.
    pub keypoints: Option<Cow<'m, [[f32; 2]]>>,
}

impl Visibility<'_> {
    /// The points image `i` sees.
    pub fn points_of(&self, i: usize) -> &[u32] {
        &self.points[self.offsets[i] as usize..self.offsets[i + 1] as usize]
    }

    /// The pixels at which image `i` sees its points, if stored.
    pub fn keypoints_of(&self, i: usize) -> Option<&[[f32; 2]]> {
        let k = self.keypoints.as_ref()?;
        Some(&k[self.offsets[i] as usize..self.offsets[i + 1] as usize])
    }
}

/// Image global descriptors, row-major `[images × dim]`, and `dim`.
pub type GlobalDescriptors<'m> = (Cow<'m, [f16]>, usize);

/// A map's VLAD retrieval data (format 1.1): a codebook over the first `dims` stored
/// dimensions of `level`'s descriptors, and one VLAD of `clusters × dims` values per image.
#[derive(Debug, Clone)]
pub struct Vlad<'m> {
    /// The level whose basis the codebook is on.
    pub level: u16,
    /// Centroids of the codebook.
    pub clusters: usize,
    /// Leading stored dimensions the codebook covers.
    pub dims: usize,
    /// `[clusters × dims]`.
    pub centroids: Cow<'m, [f32]>,
    /// `[images × clusters·dims]`, L2-normalised rows.
    pub images: Cow<'m, [f16]>,
}

/// One level of a map: its points and descriptor blocks.
#[derive(Debug, Clone, Copy)]
pub struct Level<'m> {
    pub(super) map: &'m Map<'m>,
    info: &'m LevelInfo,
    points: &'m Section,
    pub(super) short: Option<&'m Section>,
    pub(super) rest: Option<&'m Section>,
    projection: Option<&'m Section>,
    pq_codebook: Option<&'m Section>,
    pq_codes: Option<&'m Section>,
    pq_order: Option<&'m Section>,
}

impl<'m> Level<'m> {
    /// The level's id.
    pub fn id(&self) -> u16 {
        self.info.level
    }

    /// Its metadata entry.
    pub fn info(&self) -> &'m LevelInfo {
        self.info
    }

    /// Number of points the level holds.
    pub fn len(&self) -> usize {
        self.points.rows as usize
    }

    /// Whether it holds no points.
    pub fn is_empty(&self) -> bool {
        self.points.rows == 0
    }

    /// Dimensions of the `short` block.
    pub fn dim_short(&self) -> usize {
        self.info.dim_short as usize
    }

    /// Dimensions of the full descriptor (`short` + `rest`).
    pub fn dim_full(&self) -> usize {
        self.info.dim_full as usize
    }

    /// Whether the level stores descriptors: f16 blocks, or (1.1) PQ codes.
    pub fn has_descriptors(&self) -> bool {
        self.short.is_some() || self.pq_codes.is_some()
    }

    /// Whether the level's descriptors are product-quantised (1.1): [`Level::pq`] holds them
    /// and there are no f16 blocks.
    pub fn is_pq(&self) -> bool {
        self.pq_codes.is_some()
    }

    /// The level's PQ codes and codebook (1.1), views of the mapping for raw sections.
    pub fn pq(&self) -> Result<Option<Pq<'m>>, Error> {
        let (Some(codebook), Some(codes)) = (self.pq_codebook, self.pq_codes) else {
            return Ok(None);
        };
        let m = codes.cols as usize;
        Ok(Some(Pq {
            subspaces: m,
            centroids: codebook.rows as usize / m,
            sub_dims: codebook.cols as usize,
            codebook: self.map.section_array(codebook)?,
            codes: self.map.section_array(codes)?,
            order: self
                .pq_order
                .map(|o| self.map.section_array(o))
                .transpose()?,
        }))
    }

    /// Whether the `rest` block is present (a `--short` slice drops it).
    pub fn has_rest(&self) -> bool {
        self.rest.is_some()
    }

    /// Global point indices of the level's rows, strictly increasing.
    pub fn points(&self) -> Result<Cow<'m, [u32]>, Error> {
        self.map.section_array(self.points)
    }

    /// `[len × dim_short]` row-major f16.
    pub fn desc_short(&self) -> Result<Cow<'m, [f16]>, Error> {
        let s = self.short.ok_or(Error::MissingSection {
            kind: SectionKind::LevelDescShort,
            level: Some(self.id()),
        })?;
        self.map.section_array(s)
    }

    /// `[len × (dim_full − dim_short)]` row-major f16, if present.
    pub fn desc_rest(&self) -> Result<Option<Cow<'m, [f16]>>, Error> {
        self.rest.map(|s| self.map.section_array(s)).transpose()
    }

    /// `[dim_full × d_in]` row-major f32: row k maps an extractor descriptor to stored dim k.
    pub fn projection(&self) -> Result<Option<Cow<'m, [f32]>>, Error> {
        self.projection
            .map(|s| self.map.section_array(s))
            .transpose()
    }

    /// Input dimension of the projection (`d_in`), if stored.
    pub fn projection_input_dim(&self) -> Option<usize> {
        self.projection.map(|s| s.cols as usize)
    }

    /// The sections of this level: points, short, rest, projection, PQ codebook and codes.
    pub fn sections(&self) -> impl Iterator<Item = &'m Section> {
        [
            Some(self.points),
            self.short,
            self.rest,
            self.projection,
            self.pq_codebook,
            self.pq_codes,
        ]
        .into_iter()
        .flatten()
    }
}

impl<'a> Map<'a> {
    pub(super) fn required(&self, kind: SectionKind) -> Result<&Section, Error> {
        self.find(kind, None)
            .ok_or(Error::MissingSection { kind, level: None })
    }

    fn optional<T: bytemuck::Pod>(&self, kind: SectionKind) -> Result<Option<Cow<'_, [T]>>, Error> {
        self.find(kind, None)
            .map(|s| self.section_array(s))
            .transpose()
    }

    /// Point positions relative to the metadata origin: a view of the mapping for raw f32
    /// positions, decoded from the grid for (1.1) quantised ones.
    pub fn point_positions(&self) -> Result<Cow<'_, [[f32; 3]]>, Error> {
        if let (Some(q), Some(grid)) = (
            self.find(SectionKind::PointPositionsQ16, None),
            self.metadata().position_grid,
        ) {
            let q = self.section_array::<[u16; 3]>(q)?;
            return Ok(Cow::Owned(q.iter().map(|&q| grid.position(q)).collect()));
        }
        self.section_array(self.required(SectionKind::PointPositions)?)
    }

    /// World position of a stored (origin-relative) position.
    pub fn to_world(&self, p: [f32; 3]) -> [f64; 3] {
        let o = self.metadata().origin;
        [
            o[0] + f64::from(p[0]),
            o[1] + f64::from(p[1]),
            o[2] + f64::from(p[2]),
        ]
    }

    /// Each point's 8-bit RGB colour, if the map stores them (`slice --minimal` drops them).
    pub fn point_colors(&self) -> Result<Option<Cow<'_, [[u8; 3]]>>, Error> {
        self.optional(SectionKind::PointColors)
    }

    /// Each point's source id (COLMAP `point3D_id`), if the map stores them.
    pub fn point_ids(&self) -> Result<Option<Cow<'_, [u64]>>, Error> {
        self.optional(SectionKind::PointIds)
    }

    /// The database images, if the map has any image sections.
    pub fn images(&self) -> Result<Option<Images<'_>>, Error> {
        let Some(poses) = self.find(SectionKind::ImagePoses, None) else {
            return Ok(None);
        };
        Ok(Some(Images {
            poses: self.section_array(poses)?,
            cameras: self.section_array(self.required(SectionKind::ImageCameras)?)?,
            ids: self.optional(SectionKind::ImageIds)?,
            name_offsets: self.section_array(self.required(SectionKind::ImageNameOffsets)?)?,
            names: self.section_bytes(self.required(SectionKind::ImageNames)?)?,
        }))
    }

    /// Global descriptors `[images × dim]` and `dim`, if stored.
    pub fn image_global(&self) -> Result<Option<GlobalDescriptors<'_>>, Error> {
        match self.find(SectionKind::ImageGlobal, None) {
            Some(s) => Ok(Some((self.section_array(s)?, s.cols as usize))),
            None => Ok(None),
        }
    }

    /// The VLAD retrieval data (format 1.1), if stored: the codebook's level, its centroids and
    /// each image's VLAD.
    pub fn vlad(&self) -> Result<Option<Vlad<'_>>, Error> {
        let Some(codebook) = self.vlad_codebook() else {
            return Ok(None);
        };
        let images = self.required(SectionKind::ImageVlad)?;
        Ok(Some(Vlad {
            level: codebook.level.unwrap_or(super::layout::NO_LEVEL),
            clusters: codebook.rows as usize,
            dims: codebook.cols as usize,
            centroids: self.section_array(codebook)?,
            images: self.section_array(images)?,
        }))
    }

    /// The level whose descriptors the VLAD aggregates, from the table alone (nothing read).
    pub fn vlad_level(&self) -> Option<u16> {
        self.vlad_codebook().and_then(|s| s.level)
    }

    /// The VLAD codebook's section (at most one level has one).
    fn vlad_codebook(&self) -> Option<&Section> {
        self.sections()
            .iter()
            .find(|s| s.kind == SectionKind::LevelVladCentroids && s.skipped.is_none())
    }

    /// Which points each image sees, with the keypoints where it sees them, if the map stores
    /// visibility.
    pub fn visibility(&self) -> Result<Option<Visibility<'_>>, Error> {
        self.visibility_with(true)
    }

    /// [`Map::visibility`] without the keypoints (image → points only), so a map read by
    /// range never fetches them for a reader that does not use them.
    pub fn visibility_points(&self) -> Result<Option<Visibility<'_>>, Error> {
        self.visibility_with(false)
    }

    fn visibility_with(&self, keypoints: bool) -> Result<Option<Visibility<'_>>, Error> {
        let Some(offsets) = self.find(SectionKind::VisibilityOffsets, None) else {
            return Ok(None);
        };
        Ok(Some(Visibility {
            offsets: self.section_array(offsets)?,
            points: self.section_array(self.required(SectionKind::VisibilityPoints)?)?,
            keypoints: match keypoints {
                true => self.optional(SectionKind::VisibilityKeypoints)?,
                false => None,
            },
        }))
    }

    /// Level ids in the map, ascending.
    pub fn level_ids(&self) -> Vec<u16> {
        self.metadata().levels.iter().map(|l| l.level).collect()
    }

    /// The levels, ascending by id.
    pub fn levels(&self) -> impl Iterator<Item = Level<'_>> {
        self.metadata()
            .levels
            .iter()
            .map(|info| self.make_level(info))
    }

    /// The level with id `level`.
    pub fn level(&self, level: u16) -> Result<Level<'_>, Error> {
        let info = self
            .metadata()
            .level(level)
            .ok_or_else(|| Error::NoSuchLevel {
                level,
                available: self.level_ids(),
            })?;
        Ok(self.make_level(info))
    }

    fn make_level<'m>(&'m self, info: &'m LevelInfo) -> Level<'m> {
        let l = Some(info.level);
        Level {
            map: self,
            info,
            points: self
                .find(SectionKind::LevelPoints, l)
                .expect("open checked every listed level has level_points"),
            short: self.find(SectionKind::LevelDescShort, l),
            rest: self.find(SectionKind::LevelDescRest, l),
            projection: self.find(SectionKind::LevelProjection, l),
            pq_codebook: self.find(SectionKind::LevelPqCodebook, l),
            pq_codes: self.find(SectionKind::LevelPqCodes, l),
            pq_order: self.find(SectionKind::LevelPqOrder, l),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::layout::{Codec, NO_LEVEL};

    fn section(kind: SectionKind, level: u16, rows: u64, cols: u64) -> Section {
        let dtype = kind.expected_layout().unwrap().0;
        Section {
            index: 0,
            kind,
            level: (level != NO_LEVEL).then_some(level),
            dtype,
            codec: Codec::Raw,
            required: false,
            rows,
            cols,
            offset: 0,
            stored_len: 0,
            raw_len: 0,
            checksum: 0,
            skipped: None,
            padding_start: 0,
        }
    }

    fn metadata(geometry_only: bool) -> Metadata {
        let level = |level, dim_short| LevelInfo {
            level,
            stride: 8.0,
            descriptor: "sfp-v1".into(),
            dim_full: 8,
            dim_short,
            normalization: "l2".into(),
            extra: Default::default(),
        };
        Metadata {
            geometry_only,
            levels: vec![level(0, 4), level(2, 2)],
            ..Metadata::default()
        }
    }

    fn check(metadata: &Metadata, sections: &[Section]) -> Result<(), Error> {
        let vlad = sections.iter().find(|s| s.kind == SectionKind::ImageVlad);
        check_vlad(metadata, sections, vlad)
    }

    fn codebook(level: u16, rows: u64, cols: u64) -> Section {
        section(SectionKind::LevelVladCentroids, level, rows, cols)
    }

    fn image_vlad(cols: u64) -> Section {
        section(SectionKind::ImageVlad, NO_LEVEL, 3, cols)
    }

    #[test]
    fn check_vlad_follows_the_spec() {
        let m = metadata(false);
        assert!(check(&m, &[]).is_ok());
        assert!(check(&m, &[codebook(2, 16, 2), image_vlad(32)]).is_ok());
        assert!(check(&m, &[codebook(0, 1, 4), image_vlad(4)]).is_ok());
        let inconsistent = |sections: &[Section]| {
            assert!(
                matches!(check(&m, sections), Err(Error::Inconsistent { .. })),
                "{sections:?}"
            )
        };
        inconsistent(&[codebook(0, 2, 2), codebook(2, 2, 2), image_vlad(4)]);
        inconsistent(&[codebook(2, 2, 3), image_vlad(6)]);
        inconsistent(&[codebook(0, 2, 5), image_vlad(10)]);
        inconsistent(&[codebook(2, 0, 2), image_vlad(0)]);
        inconsistent(&[codebook(2, 2, 0), image_vlad(0)]);
        inconsistent(&[codebook(2, 2, 2), image_vlad(5)]);
        // A level the metadata does not list has no dim_short: no codebook fits it.
        inconsistent(&[codebook(7, 2, 2), image_vlad(4)]);
        // rows × cols overflowing u64 matches no column count, and does not panic.
        inconsistent(&[codebook(2, u64::MAX, 2), image_vlad(u64::MAX)]);
        assert!(matches!(
            check(&metadata(true), &[codebook(2, 2, 2), image_vlad(4)]),
            Err(Error::Inconsistent { .. })
        ));
        assert!(matches!(
            check(&m, &[codebook(2, 2, 2)]),
            Err(Error::MissingSection {
                kind: SectionKind::ImageVlad,
                level: None
            })
        ));
        assert!(matches!(
            check(&m, &[image_vlad(4)]),
            Err(Error::MissingSection {
                kind: SectionKind::LevelVladCentroids,
                level: None
            })
        ));
    }
}
