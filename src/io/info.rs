//! The `sfpmap info --json` object: what a map holds, from its index and metadata alone
//! (no section is read). The CLI prints it; the Python package's `Map.info()` returns it.

use crate::format::{Level, Map, Metadata, Provenance, Section, SectionKind};
use serde::Serialize;

/// The `--json` object. Serialised straight from the map (no `serde_json::Value` tree), so
/// a map of 65,535 levels costs a few bytes per section, not a JSON object per value.
#[derive(Serialize)]
pub struct Info<'m> {
    path: String,
    version: String,
    file_bytes: u64,
    points: u64,
    images: u64,
    cameras: usize,
    geometry_only: bool,
    origin: [f64; 3],
    levels: Vec<LevelJson<'m>>,
    sections: Vec<SectionJson>,
    /// Optional sections this reader skips (unknown kinds; 1.1: unknown dtype, codec or flags).
    skipped_sections: Vec<SectionJson>,
    retrieval: Retrieval<'m>,
    /// Stored bytes per point by component ([`components`]), with the file's total.
    bytes_per_point: Vec<(&'static str, f64)>,
    provenance: &'m Provenance,
}

/// What each section is for, as `info` sums stored bytes: the map's size by component.
fn component(kind: SectionKind) -> &'static str {
    use SectionKind::*;
    match kind {
        PointPositions | PointPositionsQ16 => "positions",
        PointColors | PointIds => "colours and ids",
        LevelPoints => "level membership",
        LevelDescShort | LevelDescRest | LevelPqCodes | LevelPqCodebook | LevelPqOrder => {
            "descriptors"
        }
        LevelProjection => "projections",
        LevelVladCentroids | ImageGlobal | ImageVlad | ImageIndexCentroids | ImageIndexOffsets
        | ImageIndexImages | ImageIndexNeighbours => "retrieval",
        ImagePoses | ImageCameras | ImageIds | ImageNameOffsets | ImageNames => "images",
        VisibilityOffsets | VisibilityPoints | VisibilityKeypoints => "visibility",
        PlaceImages | CatalogProjection | CatalogVladCentroids | CatalogImageVlad => "places",
        ChunkChecksums => "chunk checksums",
        Unknown(_) => "skipped",
    }
}

/// Stored bytes per point of each component present, in a fixed order, then the index
/// (header, table, metadata, padding) and the whole file.
pub fn components(map: &Map<'_>) -> Vec<(&'static str, f64)> {
    const ORDER: [&str; 12] = [
        "positions",
        "colours and ids",
        "level membership",
        "descriptors",
        "projections",
        "retrieval",
        "images",
        "visibility",
        "places",
        "chunk checksums",
        "skipped",
        "index and padding",
    ];
    let n = map.n_points().max(1) as f64;
    let mut bytes = [0u64; ORDER.len()];
    let at = |name: &str| {
        ORDER
            .iter()
            .position(|&c| c == name)
            .expect("a listed component")
    };
    for s in map.sections() {
        let name = if s.skipped().is_some() {
            "skipped"
        } else {
            component(s.kind())
        };
        bytes[at(name)] += s.stored_len();
    }
    bytes[at("index and padding")] = map.file_len() - bytes.iter().sum::<u64>();
    let mut out: Vec<(&'static str, f64)> = ORDER
        .iter()
        .zip(bytes)
        .filter(|&(_, b)| b > 0)
        .map(|(&name, b)| (name, b as f64 / n))
        .collect();
    out.push(("total", map.file_len() as f64 / n));
    out
}

/// What the map can retrieve with (format 1.1), from the section table alone.
#[derive(Serialize)]
pub struct Retrieval<'m> {
    /// The metadata `retrieval` as written (`"vlad"`, `"global"`, a later minor's value).
    preference: Option<&'m str>,
    /// `{level, clusters, dims}` of the VLAD codebook.
    vlad: Option<serde_json::Value>,
    /// Dimensions of the stored global descriptors.
    global_dims: Option<u64>,
    /// The image side they were computed at (metadata `global_max_side`).
    global_max_side: Option<u32>,
    /// (1.3) The image index: `{of, lists, probe}` and what its writer measured.
    index: Option<serde_json::Value>,
}

impl<'m> Retrieval<'m> {
    /// What `map` (with metadata `meta`) stores for retrieval.
    pub fn of(map: &'m Map<'_>, meta: &'m Metadata) -> Retrieval<'m> {
        let vlad = map
            .sections()
            .iter()
            .find(|s| s.kind() == SectionKind::LevelVladCentroids && s.skipped().is_none())
            .map(
                |s| serde_json::json!({"level": s.level(), "clusters": s.rows(), "dims": s.cols()}),
            );
        let global_dims = map
            .sections()
            .iter()
            .find(|s| s.kind() == SectionKind::ImageGlobal && s.skipped().is_none())
            .map(|s| s.cols());
        let lists = map
            .sections()
            .iter()
            .find(|s| s.kind() == SectionKind::ImageIndexCentroids && s.skipped().is_none())
            .map(|s| s.rows());
        let neighbours = map
            .sections()
            .iter()
            .find(|s| s.kind() == SectionKind::ImageIndexNeighbours && s.skipped().is_none())
            .map(|s| s.cols());
        // The writer's other keys first, so that none stands in for a known one.
        let index = meta.image_index.as_ref().map(|i| {
            let mut v = serde_json::Value::Object(i.extra.clone());
            v["of"] = serde_json::json!(i.of);
            v["lists"] = serde_json::json!(lists);
            v["probe"] = serde_json::json!(i.probe);
            v["neighbours"] = serde_json::json!(neighbours);
            v
        });
        Retrieval {
            preference: meta.retrieval.as_deref(),
            vlad,
            global_dims,
            global_max_side: meta.global_side(),
            index,
        }
    }

    /// One line for the text output.
    pub fn describe(&self) -> String {
        let mut kinds = Vec::new();
        if let Some(v) = &self.vlad {
            kinds.push(format!(
                "VLAD {} x {} on level {}",
                v["clusters"], v["dims"], v["level"]
            ));
        }
        if let Some(d) = self.global_dims {
            kinds.push(match self.global_max_side {
                Some(side) => format!("global descriptors of {d} dims (images at most {side} px)"),
                None => format!("global descriptors of {d} dims"),
            });
        }
        if kinds.is_empty() {
            return "retrieval: none (every point is a candidate)".into();
        }
        if let Some(i) = &self.index {
            let neighbours = match i["neighbours"].as_u64() {
                Some(n) => format!(", {n} neighbours an image"),
                None => String::new(),
            };
            kinds.push(format!(
                "an index of {} lists over {} ({} probed{neighbours})",
                i["lists"],
                crate::escape::escape_control_characters(i["of"].as_str().unwrap_or("?")),
                i["probe"]
            ));
        }
        let preference = self.preference.map_or(String::new(), |p| {
            format!("; prefers {}", crate::escape::escape_control_characters(p))
        });
        format!("retrieval: {}{preference}", kinds.join(", "))
    }
}

#[derive(Serialize)]
struct LevelJson<'m> {
    level: u16,
    points: usize,
    dim_full: usize,
    dim_short: usize,
    has_rest: bool,
    has_descriptors: bool,
    descriptor: &'m str,
    stride: f64,
    stored_bytes: u64,
    sections: Vec<SectionJson>,
}

#[derive(Serialize)]
struct SectionJson {
    kind: &'static str,
    kind_code: u16,
    level: Option<u16>,
    dtype: &'static str,
    rows: u64,
    cols: u64,
    codec: &'static str,
    /// Where the stored bytes start in the file (a range read fetches from here).
    offset: u64,
    stored_bytes: u64,
    raw_bytes: u64,
    required: bool,
    /// Why the reader skips it (`dtype` and `codec` then say `u8`/`raw`: the bytes as stored).
    #[serde(skip_serializing_if = "Option::is_none")]
    skipped: Option<String>,
}

impl From<&Section> for SectionJson {
    fn from(s: &Section) -> Self {
        SectionJson {
            kind: s.kind().name(),
            kind_code: s.kind().code(),
            level: s.level(),
            dtype: s.dtype().name(),
            rows: s.rows(),
            cols: s.cols(),
            codec: s.codec().name(),
            offset: s.offset(),
            stored_bytes: s.stored_len(),
            raw_bytes: s.raw_len(),
            required: s.required(),
            skipped: s.skipped().map(|why| why.to_string()),
        }
    }
}

impl<'m> From<Level<'m>> for LevelJson<'m> {
    fn from(l: Level<'m>) -> Self {
        LevelJson {
            level: l.id(),
            points: l.len(),
            dim_full: l.dim_full(),
            dim_short: l.dim_short(),
            has_rest: l.has_rest(),
            has_descriptors: l.has_descriptors(),
            descriptor: &l.info().descriptor,
            stride: l.info().stride,
            stored_bytes: l.sections().map(|s| s.stored_len()).sum(),
            sections: l.sections().map(SectionJson::from).collect(),
        }
    }
}

impl<'m> Info<'m> {
    /// The object for `map`, opened from `path`.
    pub fn of(map: &'m Map<'_>, path: &std::path::Path) -> Info<'m> {
        let meta = map.metadata();
        Info {
            path: path.display().to_string(),
            version: map.version(),
            file_bytes: map.file_len(),
            points: map.n_points(),
            images: map.n_images(),
            cameras: meta.cameras.len(),
            geometry_only: meta.geometry_only,
            origin: meta.origin,
            levels: map.levels().map(LevelJson::from).collect(),
            sections: map.sections().iter().map(SectionJson::from).collect(),
            skipped_sections: map.skipped_sections().map(SectionJson::from).collect(),
            retrieval: Retrieval::of(map, meta),
            bytes_per_point: components(map),
            provenance: &meta.provenance,
        }
    }
}
