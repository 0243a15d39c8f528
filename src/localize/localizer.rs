//! The hierarchical localizer: retrieval (VLAD or a global descriptor) → the points of the
//! retrieved images → coarse matching on the deepest selected level → P3P LO-RANSAC → gated
//! matching level by level (the points of the database images nearest the coarse pose,
//! projected, within a radius of each query keypoint) → re-estimation and refinement on all
//! inliers. With a pose prior (a sequence), the gated matching around the prior replaces
//! everything before it, and retrieval runs only when tracking is lost.
//!
//! A [`Localizer`] is built once per map (it indexes the levels, retrieval data, database
//! viewpoints and visibility) and shared by threads; it reads descriptors straight from the
//! mmapped map's f16 blocks, decoding the candidate rows a block at a time inside matching,
//! or (1.1) matches a product-quantised level's codes by table lookups (`adc`): nothing of
//! its own per map point.

use super::coarse::{sure_inliers, CoarseSearch, MAX_SEEDS};
use super::features::{FeatureSet, NonFinite, QueryFeatures};
use super::kernels::sgemm_abt;
use super::level::{index_level, LevelIndex};
use super::matching::MatchOptions;
use super::prior::Viewpoints;
use super::retrieval::{RetrievalFallback, RetrievalIndex, RetrievalMethod};
use crate::format::{Error as FormatError, Map, Retrieval, SectionKind, VisibilityByChunk};
use crate::geometry::{Camera, Pose, PoseCovariance, PoseEstimate};
use crate::vector::{dot, normalise_rows};
use nalgebra::Vector3;
use std::borrow::Cow;
use std::cell::OnceCell;
use std::time::Instant;

/// Localizer settings.
#[derive(Debug, Clone)]
pub struct LocalizeOptions {
    /// Levels to use; empty = all levels of the map. Coarse matching uses the deepest.
    pub levels: Vec<u16>,
    /// Match with the `short` block only.
    pub short: bool,
    /// Retrieved database images (when the map has global descriptors or VLAD).
    pub top_k: usize,
    /// Which stored descriptor ranks the database images.
    pub retrieval: RetrievalMethod,
    /// Lists of the map's image index (format 1.3) a query scores: `None`, the map's own
    /// `probe`; `Some(0)`, no index (every image scored, as maps without one are).
    pub retrieval_probe: Option<usize>,
    /// Descriptor matching: Lowe's ratio, mutual nearest neighbours.
    pub matching: MatchOptions,
    /// Coarse RANSAC threshold (px).
    pub coarse_error_px: f64,
    /// Gate radius of guided matching around projected points (px).
    pub gate_px: f64,
    /// Guided matches must also pass a ratio test among the gated candidates.
    pub gate_ratio: f32,
    /// Final RANSAC threshold (px).
    pub fine_error_px: f64,
    /// Fewer final inliers is a failure.
    pub min_inliers: usize,
    /// Keep each localized query's final inliers ([`Localization::inlier_links`]: their
    /// keypoints and 3D points), to draw them; off, a result holds none (a few kB a query
    /// otherwise, for every query a batch keeps).
    pub keep_inliers: bool,
}

/// The same for every map (Lowe's ratio 0.9); [`LocalizeOptions::for_map`] picks the ratio
/// for a map's descriptors.
impl Default for LocalizeOptions {
    fn default() -> Self {
        LocalizeOptions {
            levels: Vec::new(),
            short: false,
            top_k: crate::format::DEFAULT_RETRIEVAL_TOP_K,
            retrieval: RetrievalMethod::Auto,
            retrieval_probe: None,
            matching: MatchOptions::default(),
            coarse_error_px: 12.0,
            gate_px: 24.0,
            gate_ratio: 0.95,
            fine_error_px: 6.0,
            min_inliers: 12,
            keep_inliers: false,
        }
    }
}

impl LocalizeOptions {
    /// [`Default`], with Lowe's ratio for `map`'s descriptors (`default_ratio`: 0.95 on SFP
    /// maps, 0.9 on SIFT maps). What the CLI, the demo and the C ABI start from.
    pub fn for_map(map: &Map<'_>) -> Self {
        let descriptor = map
            .metadata()
            .levels
            .first()
            .map_or("", |l| l.descriptor.as_str());
        let mut options = Self::default();
        options.matching.ratio = super::default_ratio(descriptor);
        options
    }

    /// The one home of the options' rules: the CLI, the Python package and the C ABI all
    /// reach them through [`Localizer::new`], so a value out of range gets the same message
    /// from each (`ratio 1.5: a ratio in (0, 1]`). Which levels exist is the map's to say.
    pub fn validate(&self) -> Result<(), OptionError> {
        let bad = |option, value: String, expected| {
            Err(OptionError {
                option,
                value,
                expected,
            })
        };
        if !(1..=MAX_TOP_K).contains(&self.top_k) {
            return bad("top_k", self.top_k.to_string(), "1 to 100000 images");
        }
        use crate::ranges::{Range, COSINE, PIXELS, RATIO};
        let m = &self.matching;
        // `text`: the value as given (an f32 widened to f64 prints more digits).
        let check = |option, value: f64, text: &dyn std::fmt::Display, range: Range| {
            range.check(value).map_or_else(
                |expected| bad(option, text.to_string(), expected),
                |_| Ok(()),
            )
        };
        check("ratio", m.ratio.into(), &m.ratio, RATIO)?;
        check(
            "gate_ratio",
            self.gate_ratio.into(),
            &self.gate_ratio,
            RATIO,
        )?;
        let cosine = m.min_similarity;
        check("min_similarity", cosine.into(), &cosine, COSINE)?;
        for (option, value) in [
            ("coarse_error_px", self.coarse_error_px),
            ("gate_px", self.gate_px),
            ("fine_error_px", self.fine_error_px),
        ] {
            check(option, value, &value, PIXELS)?;
        }
        // At least what P3P takes plus one that checks it; at most what keeps the search's
        // multiples of it (`coarse::sure_inliers`, 4 × for a seed) far from overflow.
        if !(4..=MAX_MIN_INLIERS).contains(&self.min_inliers) {
            let value = self.min_inliers.to_string();
            return bad("min_inliers", value, "4 to 1000000 inliers");
        }
        Ok(())
    }
}

/// The most images [`LocalizeOptions::top_k`] may retrieve (retrieval widens a search by
/// multiples of it).
pub const MAX_TOP_K: usize = 100_000;

/// The most inliers [`LocalizeOptions::min_inliers`] may ask for.
const MAX_MIN_INLIERS: usize = 1_000_000;

/// An option of [`LocalizeOptions`] out of its range: `ratio 1.5: a ratio in (0, 1]`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OptionError {
    /// The option's name, as the Python package and the C ABI spell it (the CLI's flag is
    /// the same name with dashes).
    pub option: &'static str,
    /// The value given, as text.
    pub value: String,
    /// What the option takes.
    pub expected: &'static str,
}

impl std::fmt::Display for OptionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} {}: {}", self.option, self.value, self.expected)
    }
}

impl std::error::Error for OptionError {}

/// Milliseconds per stage.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    /// Ranking the database images.
    pub retrieval_ms: f64,
    /// Matching against the retrieved images' points on the coarse level.
    pub coarse_match_ms: f64,
    /// LO-RANSAC on the coarse matches.
    pub coarse_ransac_ms: f64,
    /// Guided matching and refinement on the finer levels.
    pub fine_ms: f64,
    /// The whole query.
    pub total_ms: f64,
}

/// The outcome of one query.
#[derive(Debug, Clone, PartialEq)]
pub struct Localization {
    /// `cam_from_world`, or why the query was not localized.
    pub outcome: Result<Pose, QueryFailure>,
    /// (level, inliers) of the final estimate.
    pub inliers_per_level: Vec<(u16, usize)>,
    /// Matches of the final estimate (2D–3D correspondences tried).
    pub matches: usize,
    /// Inliers of the final estimate.
    pub inliers: usize,
    /// Database images retrieval kept (0 on the tracking path).
    pub retrieved_images: usize,
    /// The retrieved database images, best first (image indices of the map; empty on the
    /// tracking path and without retrieval).
    pub retrieved: Vec<usize>,
    /// The stored descriptor that ranked the retrieved images, if retrieval narrowed them.
    pub retrieval: Option<Retrieval>,
    /// Why the candidates were every point (no retrieval), if they were: the fallback.
    pub retrieval_fallback: Option<RetrievalFallback>,
    /// Which path localized the query (or last tried to).
    pub path: LocalizationPath,
    /// With a pose prior: why tracking did not hold, so that the retrieval path ran.
    pub tracking_lost: Option<TrackingLost>,
    /// Where the query's time went.
    pub times: StageTimes,
    /// How sure the pose is, from the geometry of the final estimate's inliers
    /// ([`crate::geometry::pose_covariance`]); `None` when the query failed, when only the
    /// coarse pose stands (guided matching gave none), or with too few inliers for one.
    pub covariance: Option<PoseCovariance>,
    /// With [`LocalizeOptions::keep_inliers`], the final estimate's inliers; else empty (and
    /// when only the coarse pose stands).
    pub inlier_links: Vec<InlierLink>,
}

/// One inlier of a pose: a query keypoint and the map point it matched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct InlierLink {
    /// The keypoint, in pixels (COLMAP's convention: the first pixel's centre at 0.5).
    pub pixel: [f64; 2],
    /// The map point, in world coordinates.
    pub point: [f64; 3],
    /// The level the match was made on.
    pub level: u16,
}

/// How a query was localized.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LocalizationPath {
    /// Retrieval, coarse matching, then guided matching.
    #[default]
    Retrieval,
    /// Guided matching around a pose prior (a sequence's prediction).
    Tracking,
}

impl LocalizationPath {
    /// `retrieval` or `tracking`, as `--json` prints it.
    pub fn name(self) -> &'static str {
        match self {
            LocalizationPath::Retrieval => "retrieval",
            LocalizationPath::Tracking => "tracking",
        }
    }
}

/// Why a pose prior did not localize a query (the criterion for "tracking lost").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum TrackingLost {
    /// No database image is near the prior looking its way (or the map has no images or
    /// visibility).
    NoImagesNearPrior,
    /// Guided matching around the prior found fewer inliers than `needed`: `min_inliers`, or
    /// 30 % of its `matches` if more.
    TooFewInliers {
        /// Inliers found.
        inliers: usize,
        /// Inliers needed.
        needed: usize,
        /// Matches tried.
        matches: usize,
    },
}

impl std::fmt::Display for TrackingLost {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TrackingLost::NoImagesNearPrior => {
                f.write_str("no database image near the predicted pose")
            }
            TrackingLost::TooFewInliers {
                inliers,
                needed,
                matches,
            } => write!(
                f,
                "{inliers} inliers of {matches} matches around the predicted pose (fewer than {needed})"
            ),
        }
    }
}

impl Localization {
    /// The pose, if the query was localized.
    pub fn pose(&self) -> Option<&Pose> {
        self.outcome.as_ref().ok()
    }

    /// Why the query was not localized, if it was not.
    pub fn failure(&self) -> Option<&QueryFailure> {
        self.outcome.as_ref().err()
    }

    /// Why the query failed, on one line for a report (control characters escaped;
    /// `unknown` for a localized query): what `# failed NAME: …` lines say.
    pub fn failure_line(&self) -> String {
        let reason = self
            .failure()
            .map_or_else(|| "unknown".to_string(), |f| f.to_string());
        crate::escape::escape_control_characters(&reason).into_owned()
    }

    /// A query that was not localized for `failure`, before any matching.
    pub fn failed(failure: QueryFailure) -> Localization {
        Localization {
            outcome: Err(failure),
            inliers_per_level: Vec::new(),
            matches: 0,
            inliers: 0,
            retrieved_images: 0,
            retrieved: Vec::new(),
            retrieval: None,
            retrieval_fallback: None,
            path: LocalizationPath::Retrieval,
            tracking_lost: None,
            times: StageTimes::default(),
            covariance: None,
            inlier_links: Vec::new(),
        }
    }
}

/// Why a query was not localized (the query was usable; the map and it did not agree on a
/// pose). Input that cannot be used at all is a [`LocalizeError`] instead.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum QueryFailure {
    /// No pose from the coarse matches (too few, or no consistent subset).
    NoCoarsePose {
        /// Why pose estimation failed.
        error: crate::geometry::GeometryError,
        /// Coarse matches tried.
        matches: usize,
    },
    /// The best pose has fewer inliers than [`LocalizeOptions::min_inliers`].
    TooFewInliers {
        /// Its inliers.
        inliers: usize,
    },
    /// The caller could not produce the query's features (an unreadable image, a query
    /// missing from the features file); the caller's one-line reason.
    NoFeatures(String),
}

impl std::error::Error for QueryFailure {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            QueryFailure::NoCoarsePose { error, .. } => Some(error),
            _ => None,
        }
    }
}

impl std::fmt::Display for QueryFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            QueryFailure::NoCoarsePose { error, matches } => {
                write!(f, "coarse pose: {error} ({matches} matches)")
            }
            QueryFailure::TooFewInliers { inliers } => write!(f, "only {inliers} inliers"),
            QueryFailure::NoFeatures(reason) => f.write_str(reason),
        }
    }
}

/// What stops a localizer from being built or used (a query that merely fails is not an error).
#[derive(Debug)]
#[non_exhaustive]
pub enum LocalizeError {
    /// Reading the map's sections.
    Format(FormatError),
    /// An option out of its range ([`LocalizeOptions::validate`]).
    Option(OptionError),
    /// The map has no descriptors (geometry only).
    NoDescriptors,
    /// Query features do not fit the map's descriptor space.
    DescriptorMismatch {
        /// The level.
        level: u16,
        /// The dimension the level's descriptors (or projection) take.
        expected: usize,
        /// The query's dimension.
        found: usize,
    },
    /// The query has no features for a level that is to be matched.
    NoFeaturesForLevel {
        /// The level.
        level: u16,
    },
    /// A feature set's descriptors are not `keypoints × dim` values.
    FeatureShape {
        /// Keypoints in the set.
        keypoints: usize,
        /// The set's `dim`.
        dim: usize,
        /// Descriptor values in the set.
        values: usize,
    },
    /// A keypoint, descriptor or global descriptor value is NaN or infinite
    /// ([`QueryFeatures::check_finite`]).
    NonFinite(NonFinite),
    /// A level's sections disagree with its dimensions (the reader's checks should have
    /// caught it; the localizer sizes nothing from a claim it has not checked).
    BadLevel {
        /// The level.
        level: u16,
        /// What disagrees.
        message: String,
    },
    /// Every selected level was skipped (see [`SkippedLevel`]): nothing can be matched.
    NoUsableLevel {
        /// Every selected level, and why it was skipped.
        skipped: Vec<SkippedLevel>,
    },
    /// A query's global descriptor cannot rank the map's images (another size than the map's
    /// global descriptors, or the map stores none): `session::global_mismatch`'s words.
    GlobalDescriptor(String),
}

/// A selected level the localizer does not match, and why (no points, no descriptor
/// dimensions, a projection no query can fit).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SkippedLevel {
    /// The level.
    pub level: u16,
    /// Why it is not matched.
    pub reason: String,
}

impl std::fmt::Display for SkippedLevel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "level {}: {}", self.level, self.reason)
    }
}

/// `skipped` as one line: the first few, then how many more.
pub fn describe_skipped(skipped: &[SkippedLevel]) -> String {
    const SHOWN: usize = 3;
    let mut text = skipped
        .iter()
        .take(SHOWN)
        .map(SkippedLevel::to_string)
        .collect::<Vec<_>>()
        .join("; ");
    if skipped.len() > SHOWN {
        text.push_str(&format!("; and {} more", skipped.len() - SHOWN));
    }
    text
}

impl std::fmt::Display for LocalizeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LocalizeError::Format(e) => e.fmt(f),
            LocalizeError::Option(e) => e.fmt(f),
            LocalizeError::NoDescriptors => f.write_str("the map has no descriptors (geometry only); convert it with --database or --images"),
            LocalizeError::DescriptorMismatch { level, expected, found } => write!(
                f,
                "query descriptors have {found} dimensions but level {level} of the map expects {expected} (another descriptor kind?)"
            ),
            LocalizeError::NoFeaturesForLevel { level } => write!(f, "the query has no features for level {level}"),
            LocalizeError::FeatureShape { keypoints, dim, values } => write!(
                f,
                "query features: {values} descriptor values for {keypoints} keypoints of {dim} dimensions"
            ),
            LocalizeError::BadLevel { level, message } => write!(f, "level {level}: {message}"),
            LocalizeError::NonFinite(e) => e.fmt(f),
            LocalizeError::GlobalDescriptor(why) => write!(f, "global descriptor: {why}"),
            LocalizeError::NoUsableLevel { skipped } => write!(
                f,
                "no selected level can be matched ({})",
                describe_skipped(skipped)
            ),
        }
    }
}

/// Transparent for `Format`: its text is printed as this error's, so its source is the
/// format error's own.
impl std::error::Error for LocalizeError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            LocalizeError::Format(e) => e.source(),
            _ => None,
        }
    }
}

impl From<FormatError> for LocalizeError {
    fn from(e: FormatError) -> Self {
        LocalizeError::Format(e)
    }
}

/// One level's query features and their projection into its basis, made when first needed.
pub(super) struct Query<'q> {
    pub(super) set: &'q FeatureSet,
    pub(super) projected: &'q OnceCell<Vec<f32>>,
}

/// Retrieved images whose points coarse matching tries first, for a map of `images` images:
/// the points of the best few hold enough true matches for a pose at a fraction of the cost
/// of all `top_k`. A large map's retrieval ranks a query's place lower more often (as for
/// [`vlad::default_shape`](crate::vlad::default_shape), from `LARGE_MAP_IMAGES` on). On the
/// 1 M-point street's level-2 short map (7,934 images), the best 3 left 8 of 20 queries to
/// the next tier (median 13.4 ms a query), 4 and 5 left 5 (10.5 and 9.5 ms), 6 and 8 left 4
/// and 3 but cost more in the tier every query runs (11 ms); on the 100 k street (800 images)
/// no query needed the next tier with 3, and 5 cost more (5.3 -> 5.9 ms).
fn coarse_images(images: usize) -> usize {
    if crate::vlad::is_large_map(images) {
        5
    } else {
        3
    }
}

/// What retrieval gave one query.
struct Retrieved {
    /// Candidate points (those the retrieved images see), ascending; `None`: every point.
    candidates: Option<Vec<u32>>,
    /// Those of the best [`coarse_images`] retrieved images, when fewer than `candidates`.
    coarse_candidates: Option<Vec<u32>>,
    /// The retrieved images, best first.
    images: Vec<usize>,
    method: Option<Retrieval>,
    fallback: Option<RetrievalFallback>,
}

/// A map prepared for localization: levels indexed over the map's own descriptor blocks.
pub struct Localizer<'m> {
    pub(super) map: &'m Map<'m>,
    pub(super) options: LocalizeOptions,
    /// The map's point positions as stored (origin-relative f32, read in place when the
    /// section is raw): [`Self::position`] makes a world position of one when it is used. (A
    /// world f64 copy was 24 MB at 1 M points, made at every open, and twice the cache
    /// footprint for guided matching's projections.)
    positions: Cow<'m, [[f32; 3]]>,
    /// Selected levels, deepest first; never empty.
    pub(super) levels: Vec<LevelIndex<'m>>,
    /// Selected levels that are not matched, and why.
    pub(super) skipped: Vec<SkippedLevel>,
    pub(super) retrieval: RetrievalIndex<'m>,
    /// Database camera centres and directions, for images near a pose (`None`: no images).
    pub(super) viewpoints: Option<Viewpoints>,
    /// Image → points, borrowed from the map, or `None` (all points are candidates).
    /// Read where used: a query's images' points are checked when listed (1.2 chunks).
    pub(super) visibility: Option<VisibilityByChunk<'m>>,
}

impl<'m> Localizer<'m> {
    /// Prepares `map` for localization with `options` (checked first,
    /// [`LocalizeOptions::validate`]): the selected levels indexed over the map's own descriptor
    /// blocks, its retrieval data, its images' viewpoints. Reads the sections it needs.
    pub fn new(map: &'m Map<'m>, options: LocalizeOptions) -> Result<Localizer<'m>, LocalizeError> {
        options.validate().map_err(LocalizeError::Option)?;
        if map.metadata().geometry_only || map.level_ids().is_empty() {
            return Err(LocalizeError::NoDescriptors);
        }
        let mut ids = if options.levels.is_empty() {
            map.level_ids()
        } else {
            options.levels.clone()
        };
        ids.sort_unstable_by(|a, b| b.cmp(a));
        ids.dedup();
        // Read by range: what the localizer reads below, fetched in few requests (the
        // selected levels, the VLAD codebook's level, the shared sections it uses).
        map.prefetch(|s| match s.level() {
            Some(_) if s.kind() == SectionKind::LevelDescRest && options.short => false,
            Some(level) => ids.contains(&level) || s.kind() == SectionKind::LevelVladCentroids,
            None => match s.kind() {
                SectionKind::PointColors
                | SectionKind::PointIds
                | SectionKind::VisibilityKeypoints => false,
                SectionKind::ImageIndexCentroids
                | SectionKind::ImageIndexOffsets
                | SectionKind::ImageIndexImages
                | SectionKind::ImageIndexNeighbours => {
                    options.retrieval != RetrievalMethod::Off && options.retrieval_probe != Some(0)
                }
                _ => true,
            },
        })?;
        let mut levels = Vec::new();
        let mut skipped = Vec::new();
        for id in ids {
            let level = map.level(id)?;
            if !level.has_descriptors() {
                return Err(LocalizeError::NoDescriptors);
            }
            match index_level(&level, &options, map.n_points())? {
                Ok(index) => levels.push(index),
                Err(reason) => skipped.push(SkippedLevel { level: id, reason }),
            }
        }
        if levels.is_empty() {
            return Err(LocalizeError::NoUsableLevel { skipped });
        }
        let positions = map.point_positions()?;
        let retrieval = RetrievalIndex::new(map, options.retrieval, options.retrieval_probe)?;
        let viewpoints = map
            .images()?
            .filter(|images| !images.is_empty())
            .map(|images| Viewpoints::new(&images.poses));
        let visibility = map.visibility_by_chunk()?;
        Ok(Localizer {
            map,
            options,
            positions,
            levels,
            skipped,
            retrieval,
            viewpoints,
            visibility,
        })
    }

    /// The options it was built with.
    pub fn options(&self) -> &LocalizeOptions {
        &self.options
    }

    /// The world position of map point `p`.
    pub(super) fn position(&self, p: u32) -> Vector3<f64> {
        Vector3::from(self.map.to_world(self.positions[p as usize]))
    }

    /// How many points the map has (the positions' length).
    pub(super) fn n_points(&self) -> usize {
        self.positions.len()
    }

    /// Level ids in matching order (deepest first).
    pub fn level_order(&self) -> Vec<u16> {
        self.levels.iter().map(|l| l.id).collect()
    }

    /// Selected levels that are not matched (no points, no descriptor dimensions, …), in the
    /// order they were considered; the caller reports them.
    pub fn skipped_levels(&self) -> &[SkippedLevel] {
        &self.skipped
    }

    /// Localizes one query. Errors only for unusable input; a query that cannot be localized
    /// returns a `Localization` whose `outcome` is the [`QueryFailure`].
    pub fn localize(
        &self,
        query: &QueryFeatures,
        camera: &Camera,
    ) -> Result<Localization, LocalizeError> {
        self.localize_with_prior(query, camera, None)
    }

    /// [`Self::localize`] with a pose prior (a sequence's prediction, as a
    /// [`Session`](crate::session::Session) built with `.sequence(true)` makes): the points of the database images nearest the
    /// prior are matched by reprojection around it, with no retrieval and no coarse matching.
    /// If that gives fewer than `min_inliers` (tracking lost, [`TrackingLost`]), the query
    /// goes the retrieval path; [`Localization::path`] says which path localized it.
    pub fn localize_with_prior(
        &self,
        query: &QueryFeatures,
        camera: &Camera,
        prior: Option<&Pose>,
    ) -> Result<Localization, LocalizeError> {
        self.localize_with_prior_then_global(query, camera, prior, &mut || None)
    }

    /// [`Self::localize_with_prior`] for a query extracted without its global descriptor (a
    /// tracked frame needs none, and computing it can cost one more inference,
    /// `extract::GlobalSize`): when tracking is lost and the query goes the retrieval path,
    /// `global` is asked for it once (`None`: the query retrieves without it).
    pub fn localize_with_prior_then_global(
        &self,
        query: &QueryFeatures,
        camera: &Camera,
        prior: Option<&Pose>,
        global: &mut dyn FnMut() -> Option<Vec<f32>>,
    ) -> Result<Localization, LocalizeError> {
        let t0 = Instant::now();
        let mut times = StageTimes::default();
        // The fields are public: a NaN would pass every check of the pose solver's input, an
        // infinity wreck the matching; refused whoever made the features.
        query.check_finite().map_err(LocalizeError::NonFinite)?;
        // The feature set each level matches, checked once; each level projects it into its
        // basis once, when it is first matched, and keeps it for the query (the coarse stage
        // and both fine rounds use it).
        let sets = self
            .levels
            .iter()
            .map(|level| self.feature_set(level, query))
            .collect::<Result<Vec<_>, _>>()?;
        let projected: Vec<OnceCell<Vec<f32>>> =
            self.levels.iter().map(|_| OnceCell::new()).collect();
        let sets: Vec<Query<'_>> = sets
            .into_iter()
            .zip(&projected)
            .map(|(set, projected)| Query { set, projected })
            .collect();

        let mut tracking_lost = None;
        if let Some(prior) = prior {
            match self.track(&sets, prior, camera, &mut times)? {
                Ok(tracked) => {
                    times.total_ms = ms(t0);
                    return Ok(Localization {
                        path: LocalizationPath::Tracking,
                        times,
                        ..tracked
                    });
                }
                Err(lost) => tracking_lost = Some(lost),
            }
        }

        // Retrieval ranks by the global descriptor, so a query without one gets it now. Only
        // retrieval reads it: the feature sets above stay the original query's.
        let with_global;
        let query = match (&query.global, tracking_lost.is_some()) {
            (None, true) => match global() {
                Some(g) => {
                    with_global = QueryFeatures {
                        sets: query.sets.clone(),
                        global: Some(g),
                        model: query.model.clone(),
                    };
                    &with_global
                }
                None => query,
            },
            _ => query,
        };
        let t1 = Instant::now();
        let Retrieved {
            candidates,
            coarse_candidates,
            images: retrieved,
            method: retrieval,
            fallback: retrieval_fallback,
        } = self.candidate_points(query)?;
        times.retrieval_ms = ms(t1);
        let retrieved_images = retrieved.len();
        let ranked = if retrieval.is_some() {
            retrieved.clone()
        } else {
            Vec::new()
        };
        let failed = |failure: QueryFailure, matches, times| Localization {
            outcome: Err(failure),
            inliers_per_level: Vec::new(),
            matches,
            inliers: 0,
            retrieved_images,
            retrieved: ranked.clone(),
            retrieval,
            retrieval_fallback,
            path: LocalizationPath::Retrieval,
            tracking_lost,
            times,
            covariance: None,
            inlier_links: Vec::new(),
        };

        // Fine: guided matching around projections on every selected level, then one final
        // estimate seeded with the coarse pose, against the points of the retrieved images and
        // of the database images nearest the coarse pose (retrieval may have ranked some of
        // them low; either alone lost recall on South Building's SFP level-2 short map, 92 ->
        // 85 %); every point if the coarse pose needed every point. While the result has
        // fewer than `FINE_SURE_FACTOR × min_inliers` inliers, the next coarse tier's pose is
        // refined too (`MAX_SEEDS` in all), and the result with most inliers wins.
        let mut search = CoarseSearch::new(candidates, coarse_candidates.as_deref());
        let sure = sure_inliers(self.options.min_inliers);
        // The coarse pose with most inliers, which stands if no refinement gives a pose.
        let mut best_coarse: Option<PoseEstimate> = None;
        let mut result: Option<Localization> = None;
        let mut fine_ms = 0.0;
        for _ in 0..MAX_SEEDS {
            let Some(seed) =
                self.next_coarse_pose(&mut search, &sets, query, camera, &mut times)?
            else {
                break;
            };
            let t3 = Instant::now();
            let near = match (&self.viewpoints, &self.visibility) {
                (Some(viewpoints), Some(visibility)) if seed.narrowed => {
                    let mut images = viewpoints.near(&seed.estimate.pose, self.options.top_k);
                    images.extend(&retrieved);
                    match images.is_empty() {
                        true => None,
                        false => Some(super::retrieval::points_seen(
                            &images,
                            self.n_points(),
                            |i| visibility.points_of(i),
                        )?),
                    }
                }
                _ => None,
            };
            let fine_candidates = match near {
                Some(points) => points,
                None if seed.narrowed => search.candidates.clone(),
                None => None,
            };
            let refined = self.refine(
                &sets,
                fine_candidates.as_deref(),
                seed.estimate.pose,
                self.options.gate_px,
                camera,
            )?;
            fine_ms += ms(t3);
            if best_coarse
                .as_ref()
                .is_none_or(|b| seed.estimate.num_inliers > b.num_inliers)
            {
                best_coarse = Some(seed.estimate);
            }
            if let Some(refined) =
                refined.filter(|r| result.as_ref().is_none_or(|b| r.inliers > b.inliers))
            {
                result = Some(refined);
            }
            if result.as_ref().is_some_and(|r| r.inliers >= sure) {
                break;
            }
        }
        times.fine_ms = fine_ms;
        times.total_ms = ms(t0);
        let Some(coarse) = best_coarse else {
            let (failure, matches) = search
                .failure
                .expect("a coarse search without a pose left its failure");
            return Ok(failed(failure, matches, times));
        };
        let Some(fine) = result else {
            // The best coarse pose stands if guided matching could not improve it.
            let inliers = coarse.num_inliers;
            // The inlier mask has one entry per coarse match.
            let coarse_matches = coarse.inliers.len();
            if inliers < self.options.min_inliers {
                return Ok(failed(
                    QueryFailure::TooFewInliers { inliers },
                    coarse_matches,
                    times,
                ));
            }
            return Ok(Localization {
                outcome: Ok(coarse.pose),
                inliers_per_level: vec![(self.levels[0].id, inliers)],
                matches: coarse_matches,
                inliers,
                retrieved_images,
                retrieved: ranked,
                retrieval,
                retrieval_fallback,
                path: LocalizationPath::Retrieval,
                tracking_lost,
                times,
                covariance: None,
                inlier_links: Vec::new(),
            });
        };
        Ok(Localization {
            retrieved_images,
            retrieved: ranked,
            retrieval,
            retrieval_fallback,
            path: LocalizationPath::Retrieval,
            tracking_lost,
            times,
            ..fine
        })
    }

    /// The points the retrieved images see (ascending; `None` when that is every point, or
    /// without retrieval data or visibility), how many images were retrieved, the method that
    /// ranked them, and why there was no narrowing if there was none.
    fn candidate_points(&self, query: &QueryFeatures) -> Result<Retrieved, LocalizeError> {
        let n_images = self.map.n_images() as usize;
        let (images, ranked) = self.retrieval.retrieve(query, n_images, self.options.top_k);
        let seen = |images: &[usize]| match (&self.visibility, &ranked) {
            (Some(visibility), Ok(_)) => {
                super::retrieval::points_seen(images, self.n_points(), |i| visibility.points_of(i))
            }
            _ => Ok(None),
        };
        let candidates = seen(&images)?;
        let few = coarse_images(n_images);
        let coarse_candidates = match &candidates {
            Some(_) if images.len() > few => seen(&images[..few])?,
            _ => None,
        };
        let fallback = match ranked {
            Err(why) => Some(why),
            Ok(_) if self.visibility.is_none() => Some(RetrievalFallback::NoVisibility),
            Ok(_) if candidates.is_none() => Some(RetrievalFallback::EveryPointSeen),
            Ok(_) => None,
        };
        Ok(Retrieved {
            candidates,
            coarse_candidates,
            images,
            method: ranked.ok(),
            fallback,
        })
    }

    /// The query's feature set for `level`, checked against the level's descriptor space.
    fn feature_set<'q>(
        &self,
        level: &LevelIndex<'_>,
        query: &'q QueryFeatures,
    ) -> Result<&'q FeatureSet, LocalizeError> {
        let set = query
            .sets
            .iter()
            .find(|s| s.level == Some(level.id))
            .or_else(|| query.sets.iter().find(|s| s.level.is_none()))
            .ok_or(LocalizeError::NoFeaturesForLevel { level: level.id })?;
        let n = set.keypoints.len();
        // The fields are public: a set of the wrong shape is an error, not a panic below.
        if n.checked_mul(set.dim) != Some(set.descriptors.len()) {
            return Err(LocalizeError::FeatureShape {
                keypoints: n,
                dim: set.dim,
                values: set.descriptors.len(),
            });
        }
        if set.dim != level.d_in {
            return Err(LocalizeError::DescriptorMismatch {
                level: level.id,
                expected: level.d_in,
                found: set.dim,
            });
        }
        Ok(set)
    }

    /// The query's descriptors of `set` in `level`'s stored basis, truncated to the matched
    /// dimensions and renormalised: `[keypoints × dim]`, no larger than the set itself
    /// (`dim ≤ d_in`).
    pub(super) fn project(&self, level: &LevelIndex<'_>, set: &FeatureSet) -> Vec<f32> {
        let n = set.keypoints.len();
        let mut out = vec![0.0f32; n * level.dim];
        match &level.projection {
            Some(p) => sgemm_abt(&set.descriptors, p, &mut out, n, level.dim, set.dim),
            None => {
                for (row, src) in out
                    .chunks_exact_mut(level.dim)
                    .zip(set.descriptors.chunks_exact(set.dim))
                {
                    row.copy_from_slice(&src[..level.dim]);
                }
            }
        }
        normalise_rows(&mut out, level.dim);
        out
    }

    /// [`Self::project`] of keypoint `k` alone, into `out`.
    pub(super) fn project_row(
        &self,
        level: &LevelIndex<'_>,
        set: &FeatureSet,
        k: usize,
        out: &mut Vec<f32>,
    ) {
        let src = &set.descriptors[k * set.dim..(k + 1) * set.dim];
        out.clear();
        match &level.projection {
            Some(p) => out.extend(p.chunks_exact(set.dim).map(|row| dot(row, src))),
            None => out.extend_from_slice(&src[..level.dim]),
        }
        normalise_rows(out, level.dim);
    }
}

pub(super) fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::coarse_images;

    #[test]
    fn coarse_matching_starts_from_more_retrieved_images_on_large_maps() {
        assert_eq!(coarse_images(0), 3);
        assert_eq!(coarse_images(crate::vlad::LARGE_MAP_IMAGES - 1), 3);
        assert_eq!(coarse_images(crate::vlad::LARGE_MAP_IMAGES), 5);
        assert_eq!(coarse_images(1_000_000), 5);
    }
}
