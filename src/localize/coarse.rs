//! Coarse matching: the query's keypoints against the points of ever wider sets of
//! candidates (the best retrieved images', all retrieved images', those of 4 and 16 × top_k,
//! every point), each followed by P3P LO-RANSAC, until a pose is sure; the poses guided
//! matching starts from.

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

/// A narrowed coarse tier's pose is taken only with at least this many times `min_inliers`
/// inliers; a weaker one lets the next, wider tier try (the pose with most inliers is kept).
/// On the demo room's query_04 the best 3 images' points gave a 21-inlier pose that guided
/// matching could bring only to 2.05°; all 10 retrieved images' points give 0.5°.
const COARSE_SURE_FACTOR: usize = 2;

/// Unsure coarse poses guided matching starts from, at most (most inliers first).
const MAX_UNSURE_SEEDS: usize = 4;

/// A pose coarse matching found, for guided matching to start from.
pub(super) struct CoarsePose {
    pub(super) estimate: PoseEstimate,
    /// Whether it came from a tier of candidate points (not every point).
    pub(super) narrowed: bool,
}

/// What coarse matching gives one query.
pub(super) struct Coarse {
    /// The sure pose alone, or, when no tier gave a sure one, the poses of the tiers (most
    /// inliers first, at most [`MAX_UNSURE_SEEDS`]): around a weak pose guided matching can
    /// settle in a wrong optimum (the demo room's query_04: the best 3 images' 21-inlier pose
    /// led to 78 inliers at 2.05°, every point's 16-inlier pose to 85 at 0.53°), so each is
    /// refined and the refinement with most inliers wins.
    pub(super) poses: Vec<CoarsePose>,
    /// The widest narrowed tier's candidate points (`None`: every point).
    pub(super) candidates: Option<Vec<u32>>,
}

/// A tier's pose estimate, or why there is none and the number of matches.
type TierResult = Result<PoseEstimate, (QueryFailure, usize)>;

/// The tiers tried so far for one query.
#[derive(Default)]
struct Tiers {
    poses: Vec<CoarsePose>,
    /// The last tier's failure, reported when no tier found a pose.
    failure: Option<(QueryFailure, usize)>,
    /// Whether some tier sampled the query keypoints.
    sampled: bool,
    /// Whether every point was matched with every keypoint.
    exhaustive: bool,
}

impl Tiers {
    fn sure(&self, inliers: usize) -> bool {
        self.poses.iter().any(|p| p.estimate.num_inliers >= inliers)
    }
}

/// The poses guided matching starts from: the one with most inliers alone if it has at
/// least `sure`, else the first [`MAX_UNSURE_SEEDS`] by inliers (ties: the earlier tier,
/// the narrower, first).
fn seeds(mut poses: Vec<CoarsePose>, sure: usize) -> Vec<CoarsePose> {
    poses.sort_by(|a, b| b.estimate.num_inliers.cmp(&a.estimate.num_inliers));
    let keep = match poses.first() {
        Some(best) if best.estimate.num_inliers >= sure => 1,
        _ => MAX_UNSURE_SEEDS,
    };
    poses.truncate(keep);
    poses
}

impl Localizer<'_> {
    /// The coarse tiers (see the module text) from the retrieved images' points
    /// (`candidates`, `None`: every point) and the best few's (`few`); a tier runs only while
    /// no pose so far has `COARSE_SURE_FACTOR × min_inliers` inliers. Every point is tried
    /// last, and only if no tier gave a pose at all (retrieval can be wrong where the global
    /// descriptor is weak, and a busy image's true matches can be too few in a sample).
    pub(super) fn coarse_poses(
        &self,
        sets: &[Query<'_>],
        query: &QueryFeatures,
        mut candidates: Option<Vec<u32>>,
        few: Option<&[u32]>,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<Coarse, (QueryFailure, usize)> {
        let sure = COARSE_SURE_FACTOR * self.options.min_inliers;
        let mut tiers = Tiers::default();
        let mut tier = |tiers: &mut Tiers, candidates: Option<&[u32]>, keypoints| {
            let mut sampled = false;
            let tried = self.coarse(sets, candidates, keypoints, camera, times, &mut sampled);
            tiers.sampled |= sampled;
            tiers.exhaustive |= candidates.is_none() && !sampled;
            match tried {
                Ok(estimate) => tiers.poses.push(CoarsePose {
                    estimate,
                    narrowed: candidates.is_some(),
                }),
                Err(failure) => tiers.failure = Some(failure),
            }
        };
        if let Some(few) = few {
            tier(&mut tiers, Some(few), COARSE_KEYPOINTS);
        }
        if !tiers.sure(sure) && candidates.is_some() {
            tier(&mut tiers, candidates.as_deref(), COARSE_KEYPOINTS);
        }
        // Wider nets before every point (at 1 M points, a fraction of its cost). A net that
        // would hold every point is the every-point tier (a small map's, where retrieval
        // narrows little and misses most).
        for factor in WIDER_RETRIEVAL {
            if tiers.sure(sure) || candidates.is_none() {
                break;
            }
            match self.retrieved_points(query, factor * self.options.top_k) {
                Some(wider) if Some(wider.len()) > candidates.as_ref().map(Vec::len) => {
                    tier(&mut tiers, Some(&wider), COARSE_KEYPOINTS);
                    candidates = Some(wider);
                }
                Some(_) => {}
                None => {
                    tier(&mut tiers, None, COARSE_KEYPOINTS);
                    candidates = None;
                }
            }
        }
        // All keypoints, if a tier sampled them; every point if no tier found a pose.
        if !tiers.sure(sure) && tiers.sampled {
            tier(&mut tiers, candidates.as_deref(), usize::MAX);
        }
        if tiers.poses.is_empty() && !tiers.exhaustive {
            tier(&mut tiers, None, usize::MAX);
        }
        let Tiers { poses, failure, .. } = tiers;
        if poses.is_empty() {
            return Err(failure.expect("a tier without a pose left its failure"));
        }
        Ok(Coarse {
            poses: seeds(poses, sure),
            candidates,
        })
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Pose;

    fn pose(inliers: usize, narrowed: bool) -> CoarsePose {
        CoarsePose {
            estimate: PoseEstimate {
                pose: Pose::identity(),
                inliers: vec![true; inliers],
                num_inliers: inliers,
                iterations: 1,
                mean_inlier_error_px: 0.0,
            },
            narrowed,
        }
    }

    fn inliers(poses: &[CoarsePose]) -> Vec<(usize, bool)> {
        poses
            .iter()
            .map(|p| (p.estimate.num_inliers, p.narrowed))
            .collect()
    }

    #[test]
    fn a_sure_pose_is_refined_alone() {
        let poses = vec![pose(21, true), pose(30, true), pose(16, false)];
        assert_eq!(inliers(&seeds(poses, 24)), [(30, true)]);
    }

    #[test]
    fn unsure_poses_are_all_refined_most_inliers_first_ties_narrower_first() {
        let poses = vec![
            pose(21, true),
            pose(20, true),
            pose(21, false),
            pose(16, false),
            pose(9, true),
        ];
        let got = inliers(&seeds(poses, 24));
        assert_eq!(got, [(21, true), (21, false), (20, true), (16, false)]);
        assert_eq!(got.len(), MAX_UNSURE_SEEDS);
        assert!(seeds(Vec::new(), 24).is_empty());
    }
}
