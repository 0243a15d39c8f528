//! The hierarchical localizer: retrieval → candidates → coarse matching on the deepest
//! selected level → P3P LO-RANSAC → gated matching level by level (projected candidates within
//! a radius of each query keypoint) → re-estimation and refinement on all inliers.
//!
//! A [`Localizer`] is built once per map (it indexes the levels and visibility) and shared by
//! threads; it reads descriptors straight from the mmapped map's f16 blocks, decoding the
//! candidate rows a block at a time inside matching (4 bytes a row of its own: the norm).

use super::kernels::sgemm_abt;
use super::level::{decode, index_level, LevelIndex};
use super::matching::{fails_ratio_test, match_rows, MatchOptions};
use super::prior::Viewpoints;
use super::retrieval::{RetrievalFallback, RetrievalIndex, RetrievalMethod};
use crate::format::{Error as FormatError, Map, Retrieval, Visibility};
use crate::geometry::{estimate_absolute_pose_with_prior, Camera, Pose, RansacOptions};
use crate::vector::{dot, normalise_rows};
use nalgebra::{Vector2, Vector3};
use std::cell::OnceCell;
use std::time::Instant;

/// Keypoints and descriptors of one query image, for one level or for all.
#[derive(Debug, Clone, Default)]
pub struct FeatureSet {
    /// The map level these features are for; `None`: the same features serve every level
    /// (SIFT queries against a SIFT map, whose levels are scale buckets of one descriptor).
    pub level: Option<u16>,
    /// Pixels, COLMAP convention.
    pub keypoints: Vec<[f64; 2]>,
    /// `[keypoints × dim]`, in the extractor's own space (before the level's projection).
    pub descriptors: Vec<f32>,
    pub dim: usize,
}

/// Everything known about one query image.
#[derive(Debug, Clone, Default)]
pub struct QueryFeatures {
    pub sets: Vec<FeatureSet>,
    /// Global descriptor for retrieval, if the extractor gives one.
    pub global: Option<Vec<f32>>,
}

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
}

impl Default for LocalizeOptions {
    fn default() -> Self {
        LocalizeOptions {
            levels: Vec::new(),
            short: false,
            top_k: 10,
            retrieval: RetrievalMethod::Auto,
            matching: MatchOptions::default(),
            coarse_error_px: 12.0,
            gate_px: 24.0,
            gate_ratio: 0.95,
            fine_error_px: 6.0,
            min_inliers: 12,
        }
    }
}

/// Milliseconds per stage.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    pub retrieval_ms: f64,
    pub coarse_match_ms: f64,
    pub coarse_ransac_ms: f64,
    pub fine_ms: f64,
    pub total_ms: f64,
}

/// The outcome of one query.
#[derive(Debug, Clone, PartialEq)]
pub struct Localization {
    /// `cam_from_world`, or why the query was not localized.
    pub outcome: Result<Pose, QueryFailure>,
    /// (level, inliers) of the final estimate.
    pub inliers_per_level: Vec<(u16, usize)>,
    pub matches: usize,
    pub inliers: usize,
    pub retrieved_images: usize,
    /// The stored descriptor that ranked the retrieved images, if retrieval narrowed them.
    pub retrieval: Option<Retrieval>,
    /// Why the candidates were every point (no retrieval), if they were: the fallback.
    pub retrieval_fallback: Option<RetrievalFallback>,
    /// Which path localized the query (or last tried to).
    pub path: LocalizationPath,
    /// With a pose prior: why tracking did not hold, so that the retrieval path ran.
    pub tracking_lost: Option<TrackingLost>,
    pub times: StageTimes,
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
    /// Guided matching around the prior found fewer inliers than `min_inliers`.
    TooFewInliers { inliers: usize, needed: usize },
}

impl std::fmt::Display for TrackingLost {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TrackingLost::NoImagesNearPrior => {
                f.write_str("no database image near the predicted pose")
            }
            TrackingLost::TooFewInliers { inliers, needed } => write!(
                f,
                "{inliers} inliers around the predicted pose (fewer than {needed})"
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

    /// A query that was not localized for `failure`, before any matching.
    pub fn failed(failure: QueryFailure) -> Localization {
        Localization {
            outcome: Err(failure),
            inliers_per_level: Vec::new(),
            matches: 0,
            inliers: 0,
            retrieved_images: 0,
            retrieval: None,
            retrieval_fallback: None,
            path: LocalizationPath::Retrieval,
            tracking_lost: None,
            times: StageTimes::default(),
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
        error: crate::geometry::GeometryError,
        matches: usize,
    },
    /// The best pose has fewer inliers than [`LocalizeOptions::min_inliers`].
    TooFewInliers { inliers: usize },
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
    Format(FormatError),
    /// The map has no descriptors (geometry only).
    NoDescriptors,
    /// Query features do not fit the map's descriptor space.
    DescriptorMismatch {
        level: u16,
        expected: usize,
        found: usize,
    },
    /// The query has no features for a level that is to be matched.
    NoFeaturesForLevel {
        level: u16,
    },
    /// A feature set's descriptors are not `keypoints × dim` values.
    FeatureShape {
        keypoints: usize,
        dim: usize,
        values: usize,
    },
    /// A level's sections disagree with its dimensions (the reader's checks should have
    /// caught it; the localizer sizes nothing from a claim it has not checked).
    BadLevel {
        level: u16,
        message: String,
    },
    /// Every selected level was skipped (see [`SkippedLevel`]): nothing can be matched.
    NoUsableLevel {
        skipped: Vec<SkippedLevel>,
    },
}

/// A selected level the localizer does not match, and why (no points, no descriptor
/// dimensions, a projection no query can fit).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SkippedLevel {
    pub level: u16,
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
struct Query<'q> {
    set: &'q FeatureSet,
    projected: &'q OnceCell<Vec<f32>>,
}

/// Query keypoints coarse matching uses at most (a stride over them).
const COARSE_KEYPOINTS: usize = 1024;

/// A pose prior's gate is this many times `gate_px`: a prediction is further off than a
/// coarse pose fitted to this frame.
const PRIOR_GATE_FACTOR: f64 = 1.0;

/// Decoded values of the rows in view guided matching keeps for a level (16 MB).
const DECODED_IN_VIEW_MAX: usize = 4 << 20;

/// Retrieved images whose points coarse matching tries first: the points of the best few
/// images hold enough true matches for a pose at a fraction of the cost of all `top_k`.
const COARSE_IMAGES: usize = 3;

/// What retrieval gave one query.
struct Retrieved {
    /// Candidate points (those the retrieved images see), ascending; `None`: every point.
    candidates: Option<Vec<u32>>,
    /// Those of the best [`COARSE_IMAGES`] retrieved images, when fewer than `candidates`.
    coarse_candidates: Option<Vec<u32>>,
    /// The retrieved images, best first.
    images: Vec<usize>,
    method: Option<Retrieval>,
    fallback: Option<RetrievalFallback>,
}

/// A map prepared for localization: levels indexed over the map's own descriptor blocks.
pub struct Localizer<'m> {
    map: &'m Map<'m>,
    options: LocalizeOptions,
    positions: Vec<Vector3<f64>>,
    /// Selected levels, deepest first; never empty.
    levels: Vec<LevelIndex<'m>>,
    /// Selected levels that are not matched, and why.
    skipped: Vec<SkippedLevel>,
    retrieval: RetrievalIndex,
    /// Database camera centres and directions, for images near a pose (`None`: no images).
    viewpoints: Option<Viewpoints>,
    /// Image → points, borrowed from the map, or `None` (all points are candidates).
    visibility: Option<Visibility<'m>>,
}

impl<'m> Localizer<'m> {
    pub fn new(map: &'m Map<'m>, options: LocalizeOptions) -> Result<Localizer<'m>, LocalizeError> {
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
        let positions = map
            .point_positions()?
            .iter()
            .map(|&p| Vector3::from(map.to_world(p)))
            .collect();
        let retrieval = RetrievalIndex::new(map, options.retrieval)?;
        let viewpoints = map
            .images()?
            .filter(|images| !images.is_empty())
            .map(|images| Viewpoints::new(&images.poses));
        let visibility = map.visibility()?;
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

    pub fn options(&self) -> &LocalizeOptions {
        &self.options
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

    /// [`Self::localize`] with a pose prior (a sequence's prediction, see
    /// [`MotionModel`](super::MotionModel)): the points of the database images nearest the
    /// prior are matched by reprojection around it, with no retrieval and no coarse matching.
    /// If that gives fewer than `min_inliers` (tracking lost, [`TrackingLost`]), the query
    /// goes the retrieval path; [`Localization::path`] says which path localized it.
    pub fn localize_with_prior(
        &self,
        query: &QueryFeatures,
        camera: &Camera,
        prior: Option<&Pose>,
    ) -> Result<Localization, LocalizeError> {
        let t0 = Instant::now();
        let mut times = StageTimes::default();
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
            match self.track(&sets, prior, camera, &mut times) {
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

        let t1 = Instant::now();
        let Retrieved {
            candidates,
            coarse_candidates,
            images: retrieved,
            method: retrieval,
            fallback: retrieval_fallback,
        } = self.candidate_points(query);
        times.retrieval_ms = ms(t1);
        let retrieved_images = retrieved.len();
        let failed = |failure: QueryFailure, matches, times| Localization {
            outcome: Err(failure),
            inliers_per_level: Vec::new(),
            matches,
            inliers: 0,
            retrieved_images,
            retrieval,
            retrieval_fallback,
            path: LocalizationPath::Retrieval,
            tracking_lost,
            times,
        };

        // Coarse: the deepest level against the points of the best few retrieved images
        // (all levels pooled if too few matches); if they give no pose, against those of all
        // retrieved images; then against every point (retrieval can be wrong where the
        // global descriptor is weak).
        let mut attempt = None;
        if let Some(few) = &coarse_candidates {
            attempt = Some(self.coarse(&sets, Some(few), camera, &mut times));
        }
        if !matches!(attempt, Some(Ok(_))) && candidates.is_some() {
            attempt = Some(self.coarse(&sets, candidates.as_deref(), camera, &mut times));
        }
        let mut narrowed = true;
        let attempt = match attempt {
            Some(Ok(found)) => Ok(found),
            _ => {
                narrowed = false;
                self.coarse(&sets, None, camera, &mut times)
            }
        };
        let coarse = match attempt {
            Ok(found) => found,
            Err((failure, matches)) => {
                times.total_ms = ms(t0);
                return Ok(failed(failure, matches, times));
            }
        };

        // Fine: guided matching around projections on every selected level, then one final
        // estimate seeded with the coarse pose, against the points of the retrieved images
        // and of the database images nearest the coarse pose (which retrieval may have
        // missed); every point if the coarse pose needed every point.
        let t3 = Instant::now();
        let fine_candidates = match (&self.viewpoints, &self.visibility) {
            (Some(viewpoints), Some(visibility)) if narrowed && candidates.is_some() => {
                let images = viewpoints.near(&coarse.pose, self.options.top_k);
                super::retrieval::points_seen(&images, self.positions.len(), |i| {
                    visibility.points_of(i)
                })
            }
            _ if narrowed => candidates,
            _ => None,
        };
        let result = self.refine(
            &sets,
            fine_candidates.as_deref(),
            coarse.pose,
            self.options.gate_px,
            camera,
        );
        times.fine_ms = ms(t3);
        times.total_ms = ms(t0);
        let Some(fine) = result else {
            // The coarse pose stands if guided matching could not improve it.
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
                retrieval,
                retrieval_fallback,
                path: LocalizationPath::Retrieval,
                tracking_lost,
                times,
            });
        };
        Ok(Localization {
            retrieved_images,
            retrieval,
            retrieval_fallback,
            path: LocalizationPath::Retrieval,
            tracking_lost,
            times,
            ..fine
        })
    }

    /// The tracking path: guided matching around `prior` against the points of the database
    /// images nearest it, with a gate widened for the prediction's error.
    fn track(
        &self,
        sets: &[Query<'_>],
        prior: &Pose,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<Localization, TrackingLost> {
        let t = Instant::now();
        let (Some(viewpoints), Some(visibility)) = (&self.viewpoints, &self.visibility) else {
            return Err(TrackingLost::NoImagesNearPrior);
        };
        let images = viewpoints.near(prior, self.options.top_k);
        if images.is_empty() {
            return Err(TrackingLost::NoImagesNearPrior);
        }
        let candidates = super::retrieval::points_seen(&images, self.positions.len(), |i| {
            visibility.points_of(i)
        });
        let gate = self.options.gate_px * PRIOR_GATE_FACTOR;
        let result = self.refine(sets, candidates.as_deref(), *prior, gate, camera);
        times.fine_ms += ms(t);
        match result {
            Some(found) if found.inliers >= self.options.min_inliers => Ok(Localization {
                retrieved_images: images.len(),
                ..found
            }),
            found => Err(TrackingLost::TooFewInliers {
                inliers: found.map_or(0, |f| f.inliers),
                needed: self.options.min_inliers,
            }),
        }
    }

    /// Two rounds of guided matching on every selected level (`candidates`: the points to
    /// consider, `None` every point) around `start`, the first with a gate of `first_gate`
    /// pixels, each followed by a RANSAC estimate seeded with the pose so far: the last
    /// estimate as a localization (the caller fills in retrieval and timing), or `None` if
    /// the first round gives no pose.
    fn refine(
        &self,
        sets: &[Query<'_>],
        candidates: Option<&[u32]>,
        start: Pose,
        first_gate: f64,
        camera: &Camera,
    ) -> Option<Localization> {
        let mut pose = start;
        let mut result = None;
        // Each level's candidate rows, found once for both rounds.
        let rows: Vec<Option<Vec<u32>>> =
            self.levels.iter().map(|l| l.rows_of(candidates)).collect();
        for round in 0..2 {
            // The second round starts from a pose already fitted to fine inliers within
            // `fine_error_px`: a gate of twice that finds them again at a fraction of the
            // comparisons.
            let gate_px = if round == 0 {
                first_gate
            } else {
                first_gate.min(2.0 * self.options.fine_error_px)
            };
            let mut pixels = Vec::new();
            let mut points = Vec::new();
            // The index into `levels` of each match.
            let mut level_of = Vec::new();
            for (i, ((level, set), rows)) in self.levels.iter().zip(sets).zip(&rows).enumerate() {
                let before = pixels.len();
                self.guided_level(
                    level,
                    set,
                    rows.as_deref(),
                    gate_px,
                    &pose,
                    camera,
                    &mut pixels,
                    &mut points,
                );
                level_of.extend(std::iter::repeat_n(i, pixels.len() - before));
            }
            let fine_options = RansacOptions {
                max_error_px: self.options.fine_error_px,
                min_inliers: self.options.min_inliers,
                ..RansacOptions::default()
            };
            match estimate_absolute_pose_with_prior(
                &pixels,
                &points,
                camera,
                Some(&pose),
                &fine_options,
            ) {
                Ok(e) => {
                    pose = e.pose;
                    result = Some((e, level_of, pixels.len()));
                }
                Err(_) => break,
            }
        }
        let (estimate, level_of, matches) = result?;
        let mut per_level: Vec<(u16, usize)> = self.levels.iter().map(|l| (l.id, 0)).collect();
        for (&inlier, &i) in estimate.inliers.iter().zip(&level_of) {
            if inlier {
                per_level[i].1 += 1;
            }
        }
        Some(Localization {
            outcome: Ok(estimate.pose),
            inliers_per_level: per_level,
            matches,
            inliers: estimate.num_inliers,
            retrieved_images: 0,
            retrieval: None,
            retrieval_fallback: None,
            path: LocalizationPath::Retrieval,
            tracking_lost: None,
            times: StageTimes::default(),
        })
    }

    /// Matching against `candidates` (`None`: every point), deepest level first, then P3P
    /// LO-RANSAC: the pose estimate (its inlier mask has one entry per match), or the reason
    /// and the number of matches.
    fn coarse(
        &self,
        sets: &[Query<'_>],
        candidates: Option<&[u32]>,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<crate::geometry::PoseEstimate, (QueryFailure, usize)> {
        let t1 = Instant::now();
        let mut pixels = Vec::new();
        let mut points = Vec::new();
        for (level, set) in self.levels.iter().zip(sets) {
            self.match_level(level, set, candidates, &mut pixels, &mut points);
            if pixels.len() >= 4 * self.options.min_inliers {
                break;
            }
        }
        times.coarse_match_ms += ms(t1);
        let t2 = Instant::now();
        // The coarse pose only seeds guided matching, which must then find `min_inliers`:
        // accept fewer inliers here.
        let coarse_options = RansacOptions {
            max_error_px: self.options.coarse_error_px,
            min_inliers: (self.options.min_inliers * 2 / 3).max(6),
            ..RansacOptions::default()
        };
        let found =
            estimate_absolute_pose_with_prior(&pixels, &points, camera, None, &coarse_options);
        times.coarse_ransac_ms += ms(t2);
        found.map_err(|error| {
            let matches = pixels.len();
            (QueryFailure::NoCoarsePose { error, matches }, matches)
        })
    }

    /// The points the retrieved images see (ascending; `None` when that is every point, or
    /// without retrieval data or visibility), how many images were retrieved, the method that
    /// ranked them, and why there was no narrowing if there was none.
    fn candidate_points(&self, query: &QueryFeatures) -> Retrieved {
        let n_images = self.map.n_images() as usize;
        let (images, ranked) = self.retrieval.retrieve(query, n_images, self.options.top_k);
        let seen = |images: &[usize]| match (&self.visibility, &ranked) {
            (Some(visibility), Ok(_)) => {
                super::retrieval::points_seen(images, self.positions.len(), |i| {
                    visibility.points_of(i)
                })
            }
            _ => None,
        };
        let candidates = seen(&images);
        let coarse_candidates = match &candidates {
            Some(_) if images.len() > COARSE_IMAGES => seen(&images[..COARSE_IMAGES]),
            _ => None,
        };
        let fallback = match ranked {
            Err(why) => Some(why),
            Ok(_) if self.visibility.is_none() => Some(RetrievalFallback::NoVisibility),
            Ok(_) if candidates.is_none() => Some(RetrievalFallback::EveryPointSeen),
            Ok(_) => None,
        };
        Retrieved {
            candidates,
            coarse_candidates,
            images,
            method: ranked.ok(),
            fallback,
        }
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
    fn project(&self, level: &LevelIndex<'_>, set: &FeatureSet) -> Vec<f32> {
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
    fn project_row(&self, level: &LevelIndex<'_>, set: &FeatureSet, k: usize, out: &mut Vec<f32>) {
        let src = &set.descriptors[k * set.dim..(k + 1) * set.dim];
        out.clear();
        match &level.projection {
            Some(p) => out.extend(p.chunks_exact(set.dim).map(|row| dot(row, src))),
            None => out.extend_from_slice(&src[..level.dim]),
        }
        normalise_rows(out, level.dim);
    }

    /// Global matching of a level's query descriptors against its candidate points.
    fn match_level(
        &self,
        level: &LevelIndex<'_>,
        query: &Query<'_>,
        candidates: Option<&[u32]>,
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) {
        let rows: Vec<usize> = match level.rows_of(candidates) {
            Some(rows) => rows.into_iter().map(|r| r as usize).collect(),
            None => (0..level.points.len()).collect(),
        };
        let set = query.set;
        if rows.is_empty() || set.keypoints.is_empty() {
            return;
        }
        let q = query.projected.get_or_init(|| self.project(level, set));
        let dim = level.dim;
        // Coarse matching only seeds the pose: every `stride`-th keypoint (COLMAP lists SIFT
        // keypoints by octave, so a stride keeps every scale) holds enough true matches.
        let stride = set.keypoints.len().div_ceil(COARSE_KEYPOINTS).max(1);
        let subset: Vec<f32>;
        let q: &[f32] = if stride > 1 {
            subset = q
                .chunks_exact(dim)
                .step_by(stride)
                .flatten()
                .copied()
                .collect();
            &subset
        } else {
            q
        };
        // Candidate rows are decoded from the mapping a block at a time, never all at once.
        // Scratch for a run's `rest` values, converted in one call and spread into the rows.
        let mut rest_run = Vec::new();
        let fill = |start: usize, tile: &mut [f32]| {
            let n = tile.len() / dim;
            let first = rows[start];
            if rows[start + n - 1] != first + n - 1 {
                for (k, out) in tile.chunks_exact_mut(dim).enumerate() {
                    level.decode_row(rows[start + k], out);
                }
                return;
            }
            // Consecutive rows (a run of candidates): each block converted in one call.
            let (ds, dr) = (level.ds, level.dr);
            match &level.rest {
                None => decode(&level.short[first * ds..(first + n) * ds], tile),
                Some(rest) => {
                    rest_run.resize(n * dr, 0.0);
                    decode(&rest[first * dr..(first + n) * dr], &mut rest_run);
                    let short = &level.short[first * ds..(first + n) * ds];
                    for (k, out) in tile.chunks_exact_mut(dim).enumerate() {
                        decode(&short[k * ds..(k + 1) * ds], &mut out[..ds]);
                        out[ds..].copy_from_slice(&rest_run[k * dr..(k + 1) * dr]);
                    }
                }
            }
            for (k, out) in tile.chunks_exact_mut(dim).enumerate() {
                level.scale_row(first + k, out);
            }
        };
        for m in match_rows(q, rows.len(), dim, &self.options.matching, fill) {
            let kp = set.keypoints[m.query as usize * stride];
            let p = level.points[rows[m.map as usize]];
            pixels.push(Vector2::new(kp[0], kp[1]));
            points.push(self.positions[p as usize]);
        }
    }

    /// Guided matching: every point of the level (of `rows`, if given) that projects into the
    /// image is a candidate for the query keypoints within `gate_px` of its projection.
    #[allow(clippy::too_many_arguments)]
    fn guided_level(
        &self,
        level: &LevelIndex<'_>,
        query: &Query<'_>,
        rows: Option<&[u32]>,
        gate_px: f64,
        pose: &Pose,
        camera: &Camera,
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) {
        let set = query.set;
        let gate = gate_px.max(1.0);
        let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
        // The projected points keyed by grid cell (a gate wide, so a 3 × 3 block of cells
        // covers the gate) and sorted: memory follows the level's points, whatever image size
        // the camera claims. (cell row, cell column, level row, pixel).
        let mut cells: Vec<(u32, u32, u32, [f32; 2])> = Vec::new();
        let all_rows = || 0..level.points.len() as u32;
        let candidate_rows: &mut dyn Iterator<Item = u32> = match rows {
            Some(rows) => &mut rows.iter().copied(),
            None => &mut all_rows(),
        };
        for row in candidate_rows {
            let p = level.points[row as usize];
            let pc = pose.transform(&self.positions[p as usize]);
            if pc.z <= 0.0 {
                continue;
            }
            let Some(px) = camera.project(&pc) else {
                continue;
            };
            if !(px.x >= 0.0 && px.y >= 0.0 && px.x < w && px.y < h) {
                continue;
            }
            let cell = ((px.y / gate) as u32, (px.x / gate) as u32);
            cells.push((cell.0, cell.1, row, [px.x as f32, px.y as f32]));
        }
        if cells.is_empty() {
            return;
        }
        cells.sort_unstable_by_key(|c| (c.0, c.1, c.2));
        // The rows in view are decoded once, in cell order, when they are few (retrieval's
        // candidates: a gate reaches each row dozens of times, 100 k street fine stage
        // 55 -> 14 ms); a level in view at large (no retrieval, 1 M points) would make that
        // copy hundreds of MB, so then a row is decoded each time a gate reaches it.
        let decoded = (cells.len() * level.dim <= DECODED_IN_VIEW_MAX).then(|| {
            let mut rows = vec![0.0f32; cells.len() * level.dim];
            for (out, c) in rows.chunks_exact_mut(level.dim).zip(&cells) {
                level.decode_row(c.2 as usize, out);
            }
            rows
        });
        let mut map_row = vec![0.0f32; level.dim];
        // (point, similarity, keypoint); each map point keeps its best keypoint below.
        let mut found: Vec<(u32, f32, usize)> = Vec::new();
        let gate2 = (gate * gate) as f32;
        let mut qd = Vec::with_capacity(level.dim);
        // Most keypoints will need their projection when the level has as many points in view
        // as a quarter of the keypoints: then one GEMM for all of them (5x faster than row by
        // row), held only while this level is matched; otherwise each keypoint is projected
        // alone, and only if some point is near it.
        let all = (query.projected.get().is_some() || cells.len() * 4 >= set.keypoints.len())
            .then(|| query.projected.get_or_init(|| self.project(level, set)));
        for (k, kp) in set.keypoints.iter().enumerate() {
            if !(kp[0] >= 0.0 && kp[1] >= 0.0 && kp[0] < w && kp[1] < h) {
                continue;
            }
            let (cy, cx) = ((kp[1] / gate) as u32, (kp[0] / gate) as u32);
            let (x_lo, x_hi) = (cx.saturating_sub(1), cx.saturating_add(1));
            let (mut best, mut second) = ((f32::NEG_INFINITY, u32::MAX), f32::NEG_INFINITY);
            // The keypoint's descriptor is projected once, and only if some point is near.
            let mut projected = false;
            for gy in cy.saturating_sub(1)..=cy.saturating_add(1) {
                let lo = cells.partition_point(|c| (c.0, c.1) < (gy, x_lo));
                let hi = cells.partition_point(|c| (c.0, c.1) <= (gy, x_hi));
                for (ci, &(_, _, row, xy)) in cells[lo..hi].iter().enumerate() {
                    let (dx, dy) = (xy[0] - kp[0] as f32, xy[1] - kp[1] as f32);
                    if dx * dx + dy * dy > gate2 {
                        continue;
                    }
                    let q = match &all {
                        Some(all) => &all[k * level.dim..(k + 1) * level.dim],
                        None => {
                            if !projected {
                                self.project_row(level, set, k, &mut qd);
                                projected = true;
                            }
                            &qd[..]
                        }
                    };
                    let map_row = match &decoded {
                        Some(rows) => &rows[(lo + ci) * level.dim..(lo + ci + 1) * level.dim],
                        None => {
                            level.decode_row(row as usize, &mut map_row);
                            &map_row[..]
                        }
                    };
                    let s = dot(q, map_row);
                    let p = level.points[row as usize];
                    if s > best.0 {
                        second = best.0;
                        best = (s, p);
                    } else if s > second {
                        second = s;
                    }
                }
            }
            if best.1 == u32::MAX || best.0 < self.options.matching.min_similarity {
                continue;
            }
            if fails_ratio_test(best.0, second, self.options.gate_ratio) {
                continue;
            }
            found.push((best.1, best.0, k));
        }
        // Each map point is matched once, to its most similar keypoint.
        found.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)).then(a.2.cmp(&b.2)));
        found.dedup_by_key(|f| f.0);
        for (p, _, k) in found {
            let kp = set.keypoints[k];
            pixels.push(Vector2::new(kp[0], kp[1]));
            points.push(self.positions[p as usize]);
        }
    }
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}
