//! Cutting a map down to some of its levels, optionally without the `rest` descriptor blocks.

use super::error::Error;
use super::layout::{Codec, Dtype, SectionKind, NO_LEVEL};
use super::metadata::{Metadata, Retrieval};
use super::reader::{Map, Section};
use super::writer::MapWriter;
use std::borrow::Cow;

/// What to keep.
#[derive(Debug, Clone, Default)]
pub struct SliceOptions {
    /// Level ids to keep; must exist in the map.
    pub levels: Vec<u16>,
    /// Drop the `rest` descriptor blocks (keep `short` only).
    pub short: bool,
    /// Re-encode every kept section with this codec; `None` keeps each section's codec
    /// (and its stored bytes, copied without decoding).
    pub codec: Option<Codec>,
    /// zstd's level for sections re-encoded with zstd.
    pub zstd_level: i32,
    /// (1.1) Keep only what localization reads, compactly: drop point ids and colours and the
    /// visibility keypoints, store positions on a grid (`point_positions_q16`, 6 bytes a point)
    /// and each image's visible points sorted, index arrays in codec `delta`; keep only the
    /// retrieval data the map prefers, and none when the map has no more images than retrieval
    /// selects ([`DEFAULT_RETRIEVAL_TOP_K`](super::DEFAULT_RETRIEVAL_TOP_K)).
    pub minimal: bool,
}

/// What a slice kept and dropped.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SliceSummary {
    /// Points in the map.
    pub points_before: u64,
    /// Points in the slice.
    pub points_after: u64,
    /// Sections whose stored bytes were copied without decoding.
    pub sections_copied: usize,
    /// Sections that were rebuilt (remapped indices or a codec change).
    pub sections_rebuilt: usize,
    /// Skipped optional sections (unknown kinds or, 1.1, encodings) that were dropped: their
    /// meaning, so their remapping, is unknown.
    pub skipped_dropped: usize,
    /// The VLAD retrieval data was dropped with the level its codebook belongs to.
    pub vlad_dropped: bool,
    /// (1.3) The image index was dropped with the rows it indexes.
    pub index_dropped: bool,
}

/// Builds a writer holding the slice of `map`. Points no kept level references are dropped
/// and every point index (levels, visibility) is remapped.
pub fn slice<'m>(
    map: &'m Map<'_>,
    options: &SliceOptions,
) -> Result<(MapWriter<'m>, SliceSummary), Error> {
    if options.levels.is_empty() {
        return Err(Error::invalid("slice needs at least one level"));
    }
    let mut keep_levels = options.levels.clone();
    keep_levels.sort_unstable();
    keep_levels.dedup();
    for &l in &keep_levels {
        let level = map.level(l)?;
        if let Some(pq) = level.pq()? {
            if options.short && pq.dims() != level.dim_short() {
                return Err(Error::invalid(format!(
                    "level {l} is product-quantised over all its {} dimensions: --short cannot cut its codes",
                    pq.dims()
                )));
            }
            continue;
        }
        let with_rest = !options.short && level.has_rest();
        if level.has_descriptors() && level.info().matched_dims(with_rest) == 0 {
            // Without `rest` such a level would hold no descriptor dimension (refused at open).
            return Err(Error::invalid(format!(
                "level {l} has no short dimensions (dim_short 0): --short would leave it no descriptors"
            )));
        }
    }
    // VLAD retrieval lives on one level's descriptors: kept with that level, dropped with it.
    let vlad_level = map.vlad_level();
    // --minimal keeps the retrieval data the map prefers when it has both kinds: the
    // localizer reads only that one.
    let preference = map.metadata().retrieval();
    let has_global = map.find(SectionKind::ImageGlobal, None).is_some();
    let vlad_kept = vlad_level.is_some_and(|l| keep_levels.binary_search(&l).is_ok());
    // ... and none when retrieval would select every image anyway.
    let retrieval_useless =
        options.minimal && map.n_images() as usize <= super::metadata::DEFAULT_RETRIEVAL_TOP_K;
    let mut keeps = Keep {
        options,
        levels: &keep_levels,
        vlad: vlad_kept
            && !retrieval_useless
            && !(options.minimal && preference == Some(Retrieval::Global) && has_global),
        global: !(retrieval_useless
            || options.minimal && preference == Some(Retrieval::Vlad) && vlad_kept),
        index: false,
    };
    // (1.3) The image index goes where the rows it indexes go (image indices do not change);
    // an index with a part missing, or over rows this version does not know, is dropped.
    keeps.index = match super::index::indexed_rows(map) {
        Some(Retrieval::Vlad) => keeps.vlad,
        Some(Retrieval::Global) => keeps.global && has_global,
        None => false,
    };
    // Checking everything first means a corrupt section is never copied into the new map.
    // Sections this slice reads are kept decoded and the others streamed, so each is decoded
    // once and a slice fits the map's decode budget.
    // Read by range, only the kept sections are checked, so only they are downloaded.
    let in_memory = map.bytes().is_some();
    map.verify_selected(
        |s| in_memory || keeps.section(s),
        |s| keeps.reads_contents(s),
        |s| keeps.section(s),
    )?;

    // Old point index → new index, u32::MAX for dropped points.
    let n_points = map.n_points() as usize;
    let mut keep: bitvec::vec::BitVec = bitvec::vec::BitVec::repeat(false, n_points);
    for &l in &keep_levels {
        for &p in map.level(l)?.points()?.iter() {
            keep.set(p as usize, true);
        }
    }
    let mut remap = vec![u32::MAX; n_points];
    let mut kept = 0u32;
    for old in keep.iter_ones() {
        remap[old] = kept;
        kept += 1;
    }

    let mut metadata: Metadata = map.metadata().clone();
    metadata
        .levels
        .retain(|l| keep_levels.binary_search(&l.level).is_ok());
    let vlad_dropped = vlad_level.is_some() && !keeps.vlad;
    let index_dropped = map.metadata().image_index.is_some() && !keeps.index;
    if index_dropped {
        metadata.image_index = None;
    }
    let global_kept = keeps.global && has_global;
    match metadata.retrieval() {
        Some(Retrieval::Vlad) if vlad_dropped => {
            metadata.retrieval = global_kept.then(|| Retrieval::Global.name().to_string());
        }
        Some(Retrieval::Global) if has_global && !keeps.global => {
            metadata.retrieval =
                (!vlad_dropped && vlad_level.is_some()).then(|| Retrieval::Vlad.name().to_string());
        }
        _ => {}
    }
    let previous = std::mem::take(&mut metadata.provenance.parameters);
    metadata
        .provenance
        .history
        .push(serde_json::json!({ "tool": metadata.provenance.tool, "parameters": previous }));
    metadata.provenance.tool = Metadata::tool_string();
    metadata.provenance.parameters = serde_json::json!({
        "operation": "slice",
        "levels": keep_levels,
        "short": options.short,
    })
    .as_object()
    .cloned()
    .unwrap_or_default();
    if options.minimal {
        metadata
            .provenance
            .parameters
            .insert("minimal".into(), serde_json::json!(true));
    }

    let mut writer = MapWriter::new(metadata);
    if let Some(codec) = options.codec {
        writer.set_codec(codec, options.zstd_level);
    }
    let mut summary = SliceSummary {
        points_before: map.n_points(),
        points_after: u64::from(kept),
        vlad_dropped,
        index_dropped,
        ..SliceSummary::default()
    };

    for section in map.sections() {
        if section.skipped().is_some() {
            summary.skipped_dropped += 1;
        }
        if !keeps.section(section) {
            continue;
        }
        let rebuilt: Option<Cow<'m, [u8]>> = match section.kind {
            // Quantised below, from the kept positions.
            SectionKind::PointPositions if options.minimal => continue,
            SectionKind::PointPositions
            | SectionKind::PointPositionsQ16
            | SectionKind::PointColors
            | SectionKind::PointIds => {
                Some(gather_rows(map.section_bytes(section)?, section, &keep))
            }
            SectionKind::LevelPoints => {
                let points = map.section_array::<u32>(section)?;
                let v: Vec<u32> = points.iter().map(|&p| remap[p as usize]).collect();
                Some(Cow::Owned(bytemuck::cast_slice(&v).to_vec()))
            }
            // Visibility is rebuilt below as a whole.
            SectionKind::VisibilityOffsets
            | SectionKind::VisibilityPoints
            | SectionKind::VisibilityKeypoints => continue,
            _ => None,
        };
        let rows = match &rebuilt {
            Some(bytes) if section.kind != SectionKind::LevelPoints => {
                bytes.len() as u64 / (section.cols * section.dtype.size())
            }
            _ => section.rows,
        };
        let codec = match section.kind {
            SectionKind::LevelPoints if options.minimal => Some(Codec::Delta),
            _ => options.codec,
        };
        add_section(
            &mut writer,
            map,
            section,
            rows,
            rebuilt,
            codec,
            &mut summary,
        )?;
    }
    if options.minimal {
        let positions = map.point_positions()?;
        let kept: Vec<[f32; 3]> = positions
            .iter()
            .zip(keep.iter().by_vals())
            .filter(|&(_, k)| k)
            .map(|(&p, _)| p)
            .collect();
        writer.set_points_q16(&kept)?;
    }

    if let Some(vis) = map.visibility()? {
        let mut offsets = Vec::with_capacity(vis.offsets.len());
        let mut points = Vec::new();
        let mut keypoints = vis
            .keypoints
            .as_ref()
            .filter(|_| !options.minimal)
            .map(|_| Vec::new());
        offsets.push(0u64);
        for image in 0..vis.offsets.len() - 1 {
            let range = vis.offsets[image] as usize..vis.offsets[image + 1] as usize;
            for i in range {
                let new = remap[vis.points[i] as usize];
                if new != u32::MAX {
                    points.push(new);
                    if let (Some(out), Some(k)) = (keypoints.as_mut(), vis.keypoints.as_ref()) {
                        out.push(k[i]);
                    }
                }
            }
            if options.minimal {
                // Without keypoints the order within an image is free: sorted, it compresses.
                let start = *offsets.last().unwrap_or(&0) as usize;
                points[start..].sort_unstable();
            }
            offsets.push(points.len() as u64);
        }
        let index_codec = if options.minimal {
            Some(Codec::Delta)
        } else {
            options.codec
        };
        let as_bytes = |b: &[u8]| Some(Cow::Owned(b.to_vec()));
        let table = |kind| map.find(kind, None).expect("visibility sections exist");
        add_section(
            &mut writer,
            map,
            table(SectionKind::VisibilityOffsets),
            offsets.len() as u64,
            as_bytes(bytemuck::cast_slice(&offsets)),
            index_codec,
            &mut summary,
        )?;
        add_section(
            &mut writer,
            map,
            table(SectionKind::VisibilityPoints),
            points.len() as u64,
            as_bytes(bytemuck::cast_slice(&points)),
            index_codec,
            &mut summary,
        )?;
        if let Some(k) = keypoints {
            add_section(
                &mut writer,
                map,
                table(SectionKind::VisibilityKeypoints),
                k.len() as u64,
                as_bytes(bytemuck::cast_slice(&k)),
                options.codec,
                &mut summary,
            )?;
        }
    }
    Ok((writer, summary))
}

/// Whether the slice keeps `section` (rebuilt or copied); `keep_levels` is sorted. Unknown
/// kinds are dropped: how to remap indices in them is unknown.
/// Which sections a slice keeps.
struct Keep<'a> {
    options: &'a SliceOptions,
    /// Sorted.
    levels: &'a [u16],
    /// Whether the VLAD codebook's level is kept (and with it `image_vlad`).
    vlad: bool,
    /// Whether `image_global` is kept.
    global: bool,
    /// (1.3) Whether the image index is kept (with the rows it indexes).
    index: bool,
}

impl Keep<'_> {
    fn section(&self, section: &Section) -> bool {
        match section.kind {
            _ if section.skipped().is_some() => false,
            // (1.2) The writer computes the slice's own.
            SectionKind::ChunkChecksums => false,
            SectionKind::LevelDescRest if self.options.short => false,
            SectionKind::PointIds | SectionKind::PointColors | SectionKind::VisibilityKeypoints
                if self.options.minimal =>
            {
                false
            }
            SectionKind::ImageVlad => self.vlad,
            SectionKind::LevelVladCentroids if !self.vlad => false,
            SectionKind::ImageGlobal => self.global,
            SectionKind::ImageIndexCentroids
            | SectionKind::ImageIndexOffsets
            | SectionKind::ImageIndexImages
            | SectionKind::ImageIndexNeighbours => self.index,
            k if k.is_per_level() => self
                .levels
                .binary_search(&section.level.unwrap_or(NO_LEVEL))
                .is_ok(),
            _ => true,
        }
    }

    /// Whether slicing reads `section`'s decoded contents (to rebuild or re-encode it), rather
    /// than dropping it or copying its stored bytes.
    fn reads_contents(&self, section: &Section) -> bool {
        let rebuilt = matches!(
            section.kind,
            SectionKind::PointPositions
                | SectionKind::PointPositionsQ16
                | SectionKind::PointColors
                | SectionKind::PointIds
                | SectionKind::LevelPoints
                | SectionKind::VisibilityOffsets
                | SectionKind::VisibilityPoints
                | SectionKind::VisibilityKeypoints
        );
        self.section(section) && (rebuilt || self.options.codec.is_some_and(|c| c != section.codec))
    }
}

/// Keeps the rows of a per-point section whose point is kept.
fn gather_rows<'m>(
    bytes: &[u8],
    section: &Section,
    keep: &bitvec::slice::BitSlice,
) -> Cow<'m, [u8]> {
    let row_len = (section.cols * section.dtype.size()) as usize;
    let mut out = Vec::with_capacity(bytes.len());
    for (row, k) in bytes
        .chunks_exact(row_len.max(1))
        .zip(keep.iter().by_vals())
    {
        if k {
            out.extend_from_slice(row);
        }
    }
    Cow::Owned(out)
}

/// Adds one kept section: its stored bytes as they are when nothing changes, else the array.
fn add_section<'m>(
    writer: &mut MapWriter<'m>,
    map: &'m Map<'_>,
    section: &Section,
    rows: u64,
    rebuilt: Option<Cow<'m, [u8]>>,
    codec: Option<Codec>,
    summary: &mut SliceSummary,
) -> Result<(), Error> {
    let level = section.level.unwrap_or(NO_LEVEL);
    let dtype: Dtype = section.dtype;
    match rebuilt {
        None if codec.is_none_or(|c| c == section.codec) => {
            // Checked before copying (free: the verify above checked it).
            writer.copy_section(map, section)?;
            summary.sections_copied += 1;
        }
        rebuilt => {
            let bytes = match rebuilt {
                Some(b) => b,
                None => Cow::Borrowed(map.section_bytes(section)?),
            };
            writer.add_raw_section(
                section.kind,
                level,
                dtype,
                rows,
                section.cols,
                section.required,
                bytes,
                codec.or(Some(section.codec)),
            )?;
            summary.sections_rebuilt += 1;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn section(kind: SectionKind, level: Option<u16>) -> Section {
        Section {
            index: 0,
            kind,
            level,
            dtype: kind.expected_layout().unwrap().0,
            codec: Codec::Raw,
            required: false,
            rows: 1,
            cols: 1,
            offset: 0,
            stored_len: 0,
            raw_len: 0,
            checksum: 0,
            skipped: None,
            padding_start: 0,
        }
    }

    #[test]
    fn vlad_sections_follow_the_codebook_level() {
        let codebook = |l| section(SectionKind::LevelVladCentroids, Some(l));
        let image_vlad = section(SectionKind::ImageVlad, None);
        for short in [false, true] {
            let options = SliceOptions {
                levels: vec![2],
                short,
                codec: None,
                zstd_level: 3,
                minimal: false,
            };
            // The codebook's level kept (also short: its dims are within dim_short).
            let keep = Keep {
                options: &options,
                levels: &[2],
                vlad: true,
                global: true,
                index: true,
            };
            assert!(keep.section(&codebook(2)));
            assert!(keep.section(&image_vlad));
            assert!(!keep.reads_contents(&codebook(2)), "copied, not decoded");
            assert!(!keep.reads_contents(&image_vlad), "copied, not decoded");
            // The codebook's level dropped: both go.
            let keep = Keep {
                options: &options,
                levels: &[2],
                vlad: false,
                global: true,
                index: false,
            };
            assert!(!keep.section(&codebook(0)));
            assert!(!keep.section(&image_vlad));
            assert!(!keep.reads_contents(&image_vlad));
        }
        // Re-encoded when the codec changes.
        let options = SliceOptions {
            levels: vec![2],
            short: false,
            codec: Some(Codec::Zstd),
            zstd_level: 3,
            minimal: false,
        };
        let keep = Keep {
            options: &options,
            levels: &[2],
            vlad: true,
            global: true,
            index: true,
        };
        assert!(keep.reads_contents(&codebook(2)));
        assert!(keep.reads_contents(&image_vlad));
    }
}
