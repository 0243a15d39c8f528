//! The metadata JSON: everything small that describes the arrays (cameras, levels, origin,
//! provenance). Unknown keys are kept in `extra` so a newer minor's keys survive a slice.

use serde::{Deserialize, Serialize};
use serde_json::{Map as JsonMap, Value};

/// The metadata `format` value.
pub const FORMAT_NAME: &str = "sfpmap";
/// The coordinate convention every map uses (see spec, "Metadata").
pub const CONVENTION: &str = "colmap";

/// The map's JSON metadata block (`spec/format.md`, "Metadata"): what the arrays mean,
/// their cameras and levels, and where the map came from. Keys this version does not know
/// are kept in `extra`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metadata {
    /// Always `"sfpmap"`.
    pub format: String,
    /// Length unit of positions and translations (`"model"` for SfM maps of arbitrary scale).
    pub units: String,
    /// `"colmap"`: right-handed world, poses are `cam_from_world`, camera looks along +z,
    /// the top-left pixel's centre is (0.5, 0.5).
    pub convention: String,
    /// Added to every stored f32 point position to get the world position in f64.
    pub origin: [f64; 3],
    /// True when the map holds no descriptors (converted from a model without features).
    #[serde(default)]
    pub geometry_only: bool,
    /// Cameras; `image_cameras` indexes this list.
    #[serde(default)]
    pub cameras: Vec<CameraInfo>,
    /// The levels, sorted by `level`.
    #[serde(default)]
    pub levels: Vec<LevelInfo>,
    /// Where the map came from.
    #[serde(default)]
    pub provenance: Provenance,
    /// 1.1: which stored global descriptor the map retrieves with by default: `"vlad"`
    /// (`image_vlad`) or `"global"` (`image_global`). A value this version does not know is
    /// kept and read as no preference (see [`Metadata::retrieval`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retrieval: Option<String>,
    /// 1.2: the longer side, in pixels, of the image copies `image_global` was computed on
    /// (images larger than that were downscaled for it; spec/extractor.md, "Global
    /// descriptor"); absent: at the extractor's input size. A query's global descriptor is
    /// computed the same way.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub global_max_side: Option<u32>,
    /// 1.3: the image index (sections 39–41): which rows it indexes and how many of its
    /// lists a query scores; present exactly when those sections are.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_index: Option<ImageIndexInfo>,
    /// 1.1: the grid of `point_positions_q16`, present exactly when that section is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position_grid: Option<PositionGrid>,
    /// Keys this version does not know, kept as they are.
    #[serde(flatten)]
    pub extra: JsonMap<String, Value>,
}

/// How many database images retrieval selects by default (the localizer's `top_k`). A map
/// with no more images than this gains nothing from retrieval data: every image is selected,
/// so `slice --minimal` drops it.
pub const DEFAULT_RETRIEVAL_TOP_K: usize = 10;

/// A stored kind of per-image global descriptor that retrieval can rank images with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Retrieval {
    /// `image_vlad`: the map's own local descriptors aggregated over a codebook (any map).
    Vlad,
    /// `image_global`: the extractor's global descriptor (SFP maps).
    Global,
}

impl Retrieval {
    /// The metadata's name for it (`vlad`, `global`).
    pub fn name(self) -> &'static str {
        match self {
            Retrieval::Vlad => "vlad",
            Retrieval::Global => "global",
        }
    }

    /// The retrieval named `name`; `None` for a name this version does not know.
    pub fn from_name(name: &str) -> Option<Retrieval> {
        match name {
            "vlad" => Some(Retrieval::Vlad),
            "global" => Some(Retrieval::Global),
            _ => None,
        }
    }
}

impl Metadata {
    /// The side `image_global` was computed at (`global_max_side`); `None`: the extractor's
    /// input size, which an absent key and 0 both mean.
    pub fn global_side(&self) -> Option<u32> {
        self.global_max_side.filter(|&side| side > 0)
    }

    /// The map's stated retrieval preference, if it states one this version knows.
    pub fn retrieval(&self) -> Option<Retrieval> {
        self.retrieval.as_deref().and_then(Retrieval::from_name)
    }
}

impl Default for Metadata {
    fn default() -> Self {
        Metadata {
            format: FORMAT_NAME.to_string(),
            units: "model".to_string(),
            convention: CONVENTION.to_string(),
            origin: [0.0; 3],
            geometry_only: false,
            cameras: Vec::new(),
            levels: Vec::new(),
            provenance: Provenance::default(),
            retrieval: None,
            global_max_side: None,
            image_index: None,
            position_grid: None,
            extra: JsonMap::new(),
        }
    }
}

/// (1.3) The metadata `image_index`: what the image index (sections 39–41) is over.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageIndexInfo {
    /// The rows it indexes: `"vlad"` (`image_vlad`) or `"global"` (`image_global`). A value
    /// this version does not know leaves the index unused (retrieval scores every image).
    pub of: String,
    /// Lists a query scores by default, 1 to the lists there are: the fewest whose recall
    /// of exhaustive ranking's top images the writer measured at its bar.
    pub probe: u32,
    /// Other keys (how the writer built it and what it measured), kept as they are.
    #[serde(flatten)]
    pub extra: JsonMap<String, Value>,
}

impl ImageIndexInfo {
    /// The rows it indexes, if this version knows the kind.
    pub fn of(&self) -> Option<Retrieval> {
        Retrieval::from_name(&self.of)
    }
}

/// The grid quantised positions lie on (1.1): a stored `q` (u16 per axis) is the position
/// `min + q × step` relative to the metadata `origin`, within `step / 2` of the position it
/// quantised.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PositionGrid {
    /// The grid's corner, relative to the metadata `origin`.
    pub min: [f64; 3],
    /// Step per axis.
    pub step: [f64; 3],
}

impl PositionGrid {
    /// The grid over `positions` (relative to the origin): 65,536 steps from the smallest to
    /// the largest value of each axis (a step of 1 for an axis that does not vary).
    pub fn spanning(positions: &[[f32; 3]]) -> PositionGrid {
        let mut min = [f64::INFINITY; 3];
        let mut max = [f64::NEG_INFINITY; 3];
        for p in positions {
            for k in 0..3 {
                min[k] = min[k].min(f64::from(p[k]));
                max[k] = max[k].max(f64::from(p[k]));
            }
        }
        let mut step = [1.0; 3];
        for k in 0..3 {
            if !min[k].is_finite() {
                min[k] = 0.0;
            } else if max[k] > min[k] {
                step[k] = (max[k] - min[k]) / f64::from(u16::MAX);
            }
        }
        PositionGrid { min, step }
    }

    /// The grid point nearest to `p`.
    pub fn quantise(&self, p: [f32; 3]) -> [u16; 3] {
        std::array::from_fn(|k| {
            ((f64::from(p[k]) - self.min[k]) / self.step[k])
                .round()
                .clamp(0.0, f64::from(u16::MAX)) as u16
        })
    }

    /// The position of grid point `q`, relative to the origin.
    pub fn position(&self, q: [u16; 3]) -> [f32; 3] {
        std::array::from_fn(|k| (self.min[k] + f64::from(q[k]) * self.step[k]) as f32)
    }

    /// Whether every grid point is a finite f32 position: `min` and `step` finite, `step`
    /// above 0, and both corners finite once rounded to f32.
    pub fn is_valid(&self) -> bool {
        let finite = self.min.iter().chain(&self.step).all(|v| v.is_finite());
        finite
            && self.step.iter().all(|&s| s > 0.0)
            && [[0; 3], [u16::MAX; 3]]
                .iter()
                .all(|&q| self.position(q).iter().all(|v| v.is_finite()))
    }

    /// The largest distance, per axis, between a position and its grid point: half a step.
    pub fn max_error(&self) -> [f64; 3] {
        self.step.map(|s| s / 2.0)
    }
}

/// A camera in COLMAP terms.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// The source's camera id (COLMAP `camera_id`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u32>,
    /// COLMAP model name, e.g. `SIMPLE_RADIAL`.
    pub model: String,
    /// Image width in pixels.
    pub width: u64,
    /// Image height in pixels.
    pub height: u64,
    /// COLMAP parameter order for the model.
    pub params: Vec<f64>,
}

/// One level of the pyramid: its keypoint stride and descriptor layout.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LevelInfo {
    /// The level's id (0 = finest).
    pub level: u16,
    /// Feature-map stride in pixels (SFP) or the nominal scale of the level's bucket (SIFT).
    pub stride: f64,
    /// Descriptor kind: `sfp-v1`, `sift`, `aliked-n16`, …; `colmap-<dim>` and
    /// `features-<dim>` for descriptors whose source did not name them.
    pub descriptor: String,
    /// Dimensions of the full descriptor (`short` + `rest`).
    pub dim_full: u32,
    /// Dimensions of the `short` block (a prefix of the full descriptor in the stored basis).
    pub dim_short: u32,
    /// How descriptors are normalised: `l2` (full vector unit length).
    pub normalization: String,
    /// Keys this version does not know (e.g. the rule that assigned points to the level).
    #[serde(flatten)]
    pub extra: JsonMap<String, Value>,
}

/// What a map records as the feature of descriptors whose source does not name it
/// (`features-<dim>`, an hloc file called `feats.h5`): any query features of that dimension
/// are taken for it.
pub(crate) const UNNAMED_FEATURE_PREFIX: &str = "features-";

/// Whether a level's `descriptor` names a feature a query's must be: not geometry only
/// (`""`), not an unnamed `colmap-<dim>` or `features-<dim>`.
pub(crate) fn descriptor_names_feature(d: &str) -> bool {
    !(d.is_empty() || d.starts_with("colmap-") || d.starts_with(UNNAMED_FEATURE_PREFIX))
}

impl LevelInfo {
    /// Whether [`descriptor`](Self::descriptor) names a feature a query's must be: not
    /// geometry only (`""`), not an unnamed `colmap-<dim>` or `features-<dim>`.
    pub fn names_feature(&self) -> bool {
        descriptor_names_feature(&self.descriptor)
    }

    /// Whether the level's descriptors came from a features source (a COLMAP database, an
    /// hloc file, kapture: its `feature_source`, or an older map's SIFT) rather than an
    /// extractor sfpmap runs.
    pub fn from_feature_source(&self) -> bool {
        self.extra.contains_key("feature_source")
            || self.descriptor == "sift"
            || self.descriptor.starts_with("colmap-")
    }

    /// The descriptor dimensions a reader matches this level with: all of them when the `rest`
    /// block is stored and used, else the `short` block's. Zero means nothing to match with:
    /// the one rule behind the writer's and `open`'s refusal, `slice --short`'s and the
    /// localizer's skip.
    pub fn matched_dims(&self, with_rest: bool) -> u32 {
        if with_rest {
            self.dim_full
        } else {
            self.dim_short
        }
    }
}

/// Where the map came from.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// `sfpmap <version>`.
    #[serde(default)]
    pub tool: String,
    /// The input files (model files, database, images folder's images).
    #[serde(default)]
    pub sources: Vec<SourceFile>,
    /// Extractor model, if descriptors came from one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model: Option<SourceFile>,
    /// The parameters of the operation that wrote the map.
    #[serde(default)]
    pub parameters: JsonMap<String, Value>,
    /// Earlier operations (e.g. the convert before a slice), oldest first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub history: Vec<Value>,
}

/// A file that went into the map, with its size and XXH3-64 hash.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SourceFile {
    /// The path as given.
    pub path: String,
    /// Its length.
    pub bytes: u64,
    /// XXH3-64 of its bytes (hex).
    pub xxh3: String,
}

impl Metadata {
    /// The level with id `level`. A binary search: `levels` must be sorted by id, as the spec
    /// requires (open checks it; the writer keeps them sorted).
    pub fn level(&self, level: u16) -> Option<&LevelInfo> {
        self.levels
            .binary_search_by_key(&level, |l| l.level)
            .ok()
            .map(|i| &self.levels[i])
    }

    /// The tool string this crate writes into provenance.
    pub fn tool_string() -> String {
        format!("sfpmap {}", env!("CARGO_PKG_VERSION"))
    }
}
