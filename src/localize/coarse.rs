//! Coarse matching: the query's keypoints against the points of ever wider sets of
//! candidates (the best retrieved images', all retrieved images', those of 4 and 16 × top_k,
//! then every keypoint, then every point), each followed by P3P LO-RANSAC: the poses guided
//! matching starts from, one tier at a time ([`CoarseSearch`]).

use super::adc::match_pq;
use super::level::{LevelIndex, Stored};
use super::localizer::{ms, Query, QueryFailure, QueryFeatures, StageTimes};
use super::matching::match_rows;
use super::Localizer;
use crate::geometry::{estimate_absolute_pose_with_prior, Camera, PoseEstimate, RansacOptions};
use nalgebra::{Vector2, Vector3};
use std::time::Instant;

/// When coarse matching finds no pose among the points of the `top_k` retrieved images, it
/// tries those of these many times `top_k` before every point (on the 1 M-point street, a
/// query's VLAD ranks its place past 40 images for 2 of 20 queries).
const WIDER_RETRIEVAL: [usize; 2] = [4, 16];

/// Query keypoints a sampled coarse tier uses at least (a stride over them).
const COARSE_KEYPOINTS: usize = 1024;

/// Keypoint × candidate pairs a sampled coarse tier compares at most: more keypoints than
/// [`COARSE_KEYPOINTS`] are used while the pairs stay within this (under 1 ms of f16 GEMM
/// at 64 dims on one core), so a small map's tiers sample little.
const COARSE_PAIRS: usize = 1 << 20;

/// A pose coarse matching found, for guided matching to start from.
pub(super) struct CoarsePose {
    pub(super) estimate: PoseEstimate,
    /// Whether it came from a tier of candidate points (not every point).
    pub(super) narrowed: bool,
}

/// A tier's pose estimate, or why there is none and the number of matches.
type TierResult = Result<PoseEstimate, (QueryFailure, usize)>;

/// The tiers in the order they are tried.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Tier {
    /// The best few retrieved images' points (sampled keypoints).
    Few,
    /// All retrieved images' points (sampled keypoints).
    Retrieved,
    /// The points of `WIDER_RETRIEVAL[i] × top_k` images (sampled keypoints).
    Wider(usize),
    /// The widest candidates so far with every keypoint, if a tier sampled them.
    AllKeypoints,
    /// Every point with every keypoint, if no tier found a pose.
    EveryPoint,
    Done,
}

/// One query's walk through the coarse tiers (see the module text), one pose at a time:
/// guided matching refines each pose [`Localizer::next_coarse_pose`] gives and asks for the
/// next only while its result is weak, so a query whose first pose refines well costs one
/// tier, and one whose first pose settles in a wrong optimum gets more seeds (the demo
/// room's query_04: the best 3 images' 21-inlier pose led guided matching to 78 inliers at
/// 2.05°, every point's 16-inlier pose to 85 at 0.53°).
pub(super) struct CoarseSearch<'c> {
    next: Tier,
    /// The widest narrowed tier's candidate points so far (`None`: every point).
    pub(super) candidates: Option<Vec<u32>>,
    few: Option<&'c [u32]>,
    /// Whether some tier sampled the query keypoints.
    sampled: bool,
    /// Whether every point was matched with every keypoint.
    exhaustive: bool,
    /// Whether some tier gave a pose.
    found: bool,
    /// The last tier's failure, reported when no tier gives a pose.
    pub(super) failure: Option<(QueryFailure, usize)>,
}

impl<'c> CoarseSearch<'c> {
    /// From the retrieved images' points (`candidates`, `None`: every point) and the best
    /// few's (`few`).
    pub(super) fn new(candidates: Option<Vec<u32>>, few: Option<&'c [u32]>) -> Self {
        CoarseSearch {
            next: Tier::Few,
            candidates,
            few,
            sampled: false,
            exhaustive: false,
            found: false,
            failure: None,
        }
    }
}

impl Localizer<'_> {
    /// The next tier's pose (tiers without a pose are passed over), or `None` when the tiers
    /// are spent. Every point is tried last, and only if no tier gave a pose at all (retrieval
    /// can be wrong where the global descriptor is weak, and a busy image's true matches can
    /// be too few in a sample).
    pub(super) fn next_coarse_pose(
        &self,
        search: &mut CoarseSearch<'_>,
        sets: &[Query<'_>],
        query: &QueryFeatures,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Option<CoarsePose> {
        loop {
            let tier = search.next;
            search.next = match tier {
                Tier::Few => Tier::Retrieved,
                Tier::Retrieved => Tier::Wider(0),
                Tier::Wider(i) if i + 1 < WIDER_RETRIEVAL.len() => Tier::Wider(i + 1),
                Tier::Wider(_) => Tier::AllKeypoints,
                Tier::AllKeypoints => Tier::EveryPoint,
                Tier::EveryPoint | Tier::Done => Tier::Done,
            };
            let (candidates, keypoints) = match tier {
                Tier::Done => return None,
                Tier::Few => match search.few {
                    Some(few) => (Some(few.to_vec()), COARSE_KEYPOINTS),
                    None => continue,
                },
                Tier::Retrieved => match &search.candidates {
                    Some(c) => (Some(c.clone()), COARSE_KEYPOINTS),
                    None => continue,
                },
                // A net that would hold every point is the every-point tier (a small map's,
                // where retrieval narrows little and misses most).
                Tier::Wider(i) => {
                    let Some(current) = &search.candidates else {
                        continue;
                    };
                    let k = WIDER_RETRIEVAL[i] * self.options.top_k;
                    match self.retrieved_points(query, k) {
                        Some(wider) if wider.len() > current.len() => {
                            search.candidates = Some(wider.clone());
                            (Some(wider), COARSE_KEYPOINTS)
                        }
                        Some(_) => continue,
                        None => {
                            search.candidates = None;
                            (None, COARSE_KEYPOINTS)
                        }
                    }
                }
                Tier::AllKeypoints if search.sampled => (search.candidates.clone(), usize::MAX),
                Tier::EveryPoint if !search.found && !search.exhaustive => (None, usize::MAX),
                Tier::AllKeypoints | Tier::EveryPoint => continue,
            };
            let mut sampled = false;
            let tried = self.coarse(
                sets,
                candidates.as_deref(),
                keypoints,
                camera,
                times,
                &mut sampled,
            );
            search.sampled |= sampled;
            search.exhaustive |= candidates.is_none() && !sampled;
            match tried {
                Ok(estimate) => {
                    search.found = true;
                    return Some(CoarsePose {
                        estimate,
                        narrowed: candidates.is_some(),
                    });
                }
                Err(failure) => search.failure = Some(failure),
            }
        }
    }

    /// Matching against `candidates` (`None`: every point) with at most `max_keypoints` query
    /// keypoints (a stride), deepest level first, then P3P
    /// LO-RANSAC: the pose estimate (its inlier mask has one entry per match), or the reason
    /// and the number of matches.
    fn coarse(
        &self,
        sets: &[Query<'_>],
        candidates: Option<&[u32]>,
        max_keypoints: usize,
        camera: &Camera,
        times: &mut StageTimes,
        sampled: &mut bool,
    ) -> TierResult {
        let t1 = Instant::now();
        let mut pixels = Vec::new();
        let mut points = Vec::new();
        for (level, set) in self.levels.iter().zip(sets) {
            *sampled |= self.match_level(
                level,
                set,
                candidates,
                max_keypoints,
                &mut pixels,
                &mut points,
            );
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

    /// Global matching of a level's query descriptors against its candidate points; whether
    /// the query keypoints were sampled.
    fn match_level(
        &self,
        level: &LevelIndex<'_>,
        query: &Query<'_>,
        candidates: Option<&[u32]>,
        max_keypoints: usize,
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) -> bool {
        let rows: Vec<usize> = match level.rows_of(candidates) {
            Some(rows) => rows.into_iter().map(|r| r as usize).collect(),
            None => (0..level.points.len()).collect(),
        };
        let set = query.set;
        if rows.is_empty() || set.keypoints.is_empty() {
            return false;
        }
        let q = query.projected.get_or_init(|| self.project(level, set));
        let dim = level.dim;
        // Coarse matching only seeds the pose: every `stride`-th keypoint (COLMAP lists SIFT
        // keypoints by octave, so a stride keeps every scale) usually holds enough true matches.
        let max_keypoints = max_keypoints.max(COARSE_PAIRS / rows.len());
        let stride = set.keypoints.len().div_ceil(max_keypoints).max(1);
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
        let options = &self.options.matching;
        // A PQ level is scored by table lookups (`adc`); f16 candidate rows are decoded from
        // the mapping a block at a time, never all at once.
        let matches = match &level.stored {
            Stored::Pq(pq) => match_pq(q, pq, &rows, options),
            Stored::F16 { .. } => {
                let mut rest_run = Vec::new();
                match_rows(q, rows.len(), dim, options, |start, tile| {
                    level.fill_rows(&rows[start..], tile, &mut rest_run)
                })
            }
        };
        for m in matches {
            let kp = set.keypoints[m.query as usize * stride];
            let p = level.points[rows[m.map as usize]];
            pixels.push(Vector2::new(kp[0], kp[1]));
            points.push(self.positions[p as usize]);
        }
        stride > 1
    }
}
