//! Coarse matching: the query's keypoints against the points of ever wider sets of
//! candidates (the best retrieved images', all retrieved images', those of 4 and 16 × top_k,
//! then every keypoint, then every point), each followed by P3P LO-RANSAC: the poses guided
//! matching starts from, one tier at a time ([`CoarseSearch`]).

use super::adc::match_pq;
use super::features::QueryFeatures;
use super::level::{LevelIndex, Stored};
use super::localizer::{ms, Query, QueryFailure, StageTimes};
use super::matching::match_rows;
use super::{LocalizeError, Localizer};
use crate::geometry::{estimate_absolute_pose_with_prior, Camera, PoseEstimate, RansacOptions};
use crate::vector::normalise_rows;
use nalgebra::{Vector2, Vector3};
use std::time::Instant;

/// When the points of the `top_k` retrieved images give no pose, or only one that refines
/// weakly, coarse matching tries those of these many times `top_k` (on the 1 M-point street,
/// a query's VLAD ranks its place past 40 images for 2 of 20 queries).
const WIDER_RETRIEVAL: [usize; 2] = [4, 16];

/// Query keypoints a sampled coarse tier uses at least (a stride over them).
const COARSE_KEYPOINTS: usize = 1024;

/// Keypoint × candidate pairs a sampled coarse tier compares at most: more keypoints than
/// [`COARSE_KEYPOINTS`] are used while the pairs stay within this (under 1 ms of f16 GEMM
/// at 64 dims on one core), so a small map's tiers sample little.
const COARSE_PAIRS: usize = 1 << 20;

/// A refined pose with at least this many times `min_inliers` inliers ends the coarse
/// search; a weaker one asks for the next tier's pose. Street queries refine to hundreds of
/// inliers; the demo room's query_04, in a wrong optimum, to 78.
pub(super) const FINE_SURE_FACTOR: usize = 8;

/// The inliers that make a pose sure: `FINE_SURE_FACTOR × min_inliers`.
pub(super) fn sure_inliers(min_inliers: usize) -> usize {
    FINE_SURE_FACTOR.saturating_mul(min_inliers)
}

/// Coarse poses guided matching starts from, at most.
pub(super) const MAX_SEEDS: usize = 4;

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
    /// The points of the best `WIDER_RETRIEVAL[i] × top_k` images, every image ranked (not
    /// through the map's image index, which may have missed this query; sampled keypoints).
    Wider(usize),
    /// The widest candidates so far with every keypoint, if a tier sampled them.
    AllKeypoints,
    /// Every point with every keypoint, if no tier found a pose.
    EveryPoint,
    /// The tiers are spent.
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
    /// The wider nets' ranking of every image (the widest net's images, best first), once
    /// the first of them asked: both nets take a prefix of one ranking.
    every_ranked: Option<Vec<usize>>,
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
            every_ranked: None,
        }
    }
}

impl CoarseSearch<'_> {
    /// The next tier's pose (tiers without a pose are passed over), or `None` when the tiers
    /// are spent. Every point is tried last, and only if no tier gave a pose at all (retrieval
    /// can be wrong where the global descriptor is weak, and a busy image's true matches can
    /// be too few in a sample). `wider(k)`: the points of the best `k` retrieved images
    /// (`None`: every point, or no retrieval); `run(candidates, max_keypoints)`: one tier's
    /// matching and RANSAC, and whether it sampled the keypoints. Fails where they fail (a
    /// damaged chunk of the map).
    fn next_pose<E>(
        &mut self,
        top_k: usize,
        mut wider: impl FnMut(usize) -> Result<Option<Vec<u32>>, E>,
        mut run: impl FnMut(Option<&[u32]>, usize) -> Result<(TierResult, bool), E>,
    ) -> Result<Option<CoarsePose>, E> {
        loop {
            let tier = self.next;
            self.next = match tier {
                Tier::Few => Tier::Retrieved,
                Tier::Retrieved => Tier::Wider(0),
                Tier::Wider(i) if i + 1 < WIDER_RETRIEVAL.len() => Tier::Wider(i + 1),
                Tier::Wider(_) => Tier::AllKeypoints,
                Tier::AllKeypoints => Tier::EveryPoint,
                Tier::EveryPoint | Tier::Done => Tier::Done,
            };
            let (candidates, keypoints): (Option<&[u32]>, usize) = match tier {
                Tier::Done => return Ok(None),
                Tier::Few => match self.few {
                    Some(few) => (Some(few), COARSE_KEYPOINTS),
                    None => continue,
                },
                Tier::Retrieved => match &self.candidates {
                    Some(c) => (Some(c), COARSE_KEYPOINTS),
                    None => continue,
                },
                // A net that would hold every point is the every-point tier (a small map's,
                // where retrieval narrows little and misses most).
                Tier::Wider(i) => {
                    let Some(current) = &self.candidates else {
                        continue;
                    };
                    match wider(WIDER_RETRIEVAL[i].saturating_mul(top_k))? {
                        Some(w) if w.len() > current.len() => self.candidates = Some(w),
                        Some(_) => continue,
                        None => self.candidates = None,
                    }
                    (self.candidates.as_deref(), COARSE_KEYPOINTS)
                }
                Tier::AllKeypoints if self.sampled => (self.candidates.as_deref(), usize::MAX),
                Tier::EveryPoint if !self.found && !self.exhaustive => (None, usize::MAX),
                Tier::AllKeypoints | Tier::EveryPoint => continue,
            };
            let (tried, sampled) = run(candidates, keypoints)?;
            let narrowed = candidates.is_some();
            self.sampled |= sampled;
            self.exhaustive |= !narrowed && !sampled;
            match tried {
                Ok(estimate) => {
                    self.found = true;
                    return Ok(Some(CoarsePose { estimate, narrowed }));
                }
                Err(failure) => self.failure = Some(failure),
            }
        }
    }
}

impl Localizer<'_> {
    /// [`CoarseSearch`]'s next pose for this query.
    pub(super) fn next_coarse_pose(
        &self,
        search: &mut CoarseSearch<'_>,
        sets: &[Query<'_>],
        query: &QueryFeatures,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<Option<CoarsePose>, LocalizeError> {
        // Every image is ranked once for both wider nets, up to the widest.
        let widest = WIDER_RETRIEVAL[WIDER_RETRIEVAL.len() - 1].saturating_mul(self.options.top_k);
        let mut ranked = search.every_ranked.take();
        let pose = search.next_pose(
            self.options.top_k,
            |k| self.retrieved_points(query, k, widest, &mut ranked),
            |candidates, keypoints| self.coarse(sets, candidates, keypoints, camera, times),
        );
        search.every_ranked = ranked;
        pose
    }

    /// The points the `k` best images see, every image ranked (the wider nets, after the
    /// retrieved images gave no pose; `None`: no retrieval, or every point). `ranked` holds
    /// the ranking of the `widest` best once made (empty where retrieval cannot rank), so a
    /// query's nets rank every image once.
    fn retrieved_points(
        &self,
        query: &QueryFeatures,
        k: usize,
        widest: usize,
        ranked: &mut Option<Vec<usize>>,
    ) -> Result<Option<Vec<u32>>, LocalizeError> {
        let Some(visibility) = self.visibility.as_ref() else {
            return Ok(None);
        };
        let images = ranked.get_or_insert_with(|| {
            let n_images = self.map.n_images() as usize;
            let (images, how) = self
                .retrieval
                .retrieve_every(query, n_images, widest.max(k));
            if how.is_ok() {
                images
            } else {
                Vec::new()
            }
        });
        if images.is_empty() {
            return Ok(None);
        }
        Ok(super::retrieval::points_seen(
            &images[..k.max(1).min(images.len())],
            self.n_points(),
            |i| visibility.points_of(i),
        )?)
    }

    /// Matching against `candidates` (`None`: every point) with at most `max_keypoints` query
    /// keypoints (a stride), deepest level first, then P3P
    /// LO-RANSAC: the pose estimate (its inlier mask has one entry per match), or the reason
    /// and the number of matches; and whether the query keypoints were sampled.
    fn coarse(
        &self,
        sets: &[Query<'_>],
        candidates: Option<&[u32]>,
        max_keypoints: usize,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<(TierResult, bool), LocalizeError> {
        let t1 = Instant::now();
        let mut pixels = Vec::new();
        let mut points = Vec::new();
        let mut sampled = false;
        for (level, set) in self.levels.iter().zip(sets) {
            sampled |= self.match_level(
                level,
                set,
                candidates,
                max_keypoints,
                &mut pixels,
                &mut points,
            )?;
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
        let found = found.map_err(|error| {
            let matches = pixels.len();
            (QueryFailure::NoCoarsePose { error, matches }, matches)
        });
        Ok((found, sampled))
    }

    /// Global matching of a level's query descriptors (their `coarse_dim` prefix) against its
    /// candidate points; whether the query keypoints were sampled.
    fn match_level(
        &self,
        level: &LevelIndex<'_>,
        query: &Query<'_>,
        candidates: Option<&[u32]>,
        max_keypoints: usize,
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) -> Result<bool, LocalizeError> {
        let rows: Vec<usize> = match level.rows_of(candidates)? {
            Some(rows) => rows.into_iter().map(|r| r as usize).collect(),
            None => (0..level.points.len()).collect(),
        };
        let set = query.set;
        if rows.is_empty() || set.keypoints.is_empty() {
            return Ok(false);
        }
        let q = query.projected.get_or_init(|| self.project(level, set));
        // Coarse matching only seeds the pose: the leading dimensions (`coarse_dim`) of every
        // `stride`-th keypoint (COLMAP lists SIFT keypoints by octave, so a stride keeps every
        // scale) usually hold enough true matches.
        let dim = level.coarse_dim();
        let max_keypoints = max_keypoints.max(COARSE_PAIRS / rows.len());
        let stride = set.keypoints.len().div_ceil(max_keypoints.max(1)).max(1);
        let subset: Vec<f32>;
        let q: &[f32] = if stride > 1 || dim < level.dim {
            // A prefix of a unit row, renormalised: the prefix of the query's projection.
            let mut rows: Vec<f32> = q
                .chunks_exact(level.dim)
                .step_by(stride)
                .flat_map(|row| &row[..dim])
                .copied()
                .collect();
            if dim < level.dim {
                normalise_rows(&mut rows, dim);
            }
            subset = rows;
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
                    level.fill_rows(&rows[start..], dim, tile, &mut rest_run)
                })
            }
        };
        for m in matches {
            let kp = set.keypoints[m.query as usize * stride];
            let p = level.points[rows[m.map as usize]];
            pixels.push(Vector2::new(kp[0], kp[1]));
            points.push(self.position(p));
        }
        Ok(stride > 1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{GeometryError, Pose};

    fn pose(inliers: usize) -> TierResult {
        Ok(PoseEstimate {
            pose: Pose::identity(),
            inliers: vec![true; inliers],
            num_inliers: inliers,
            iterations: 1,
            mean_inlier_error_px: 0.0,
        })
    }

    fn none(matches: usize) -> TierResult {
        let error = GeometryError::Degenerate { reason: "test" };
        Err((QueryFailure::NoCoarsePose { error, matches }, matches))
    }

    /// Runs the search to its end with `results` as the tiers' answers (sampling as given),
    /// `wider` as the wider nets; the tiers run (candidate count, `None` every point; the
    /// keypoint cap), the poses (inliers, narrowed) and the nets asked for.
    #[allow(clippy::type_complexity)]
    fn walk(
        candidates: Option<Vec<u32>>,
        few: Option<&[u32]>,
        mut results: Vec<(TierResult, bool)>,
        wider: impl Fn(usize) -> Option<Vec<u32>>,
    ) -> (
        Vec<(Option<usize>, usize)>,
        Vec<(usize, bool)>,
        Vec<usize>,
        CoarseSearch<'_>,
    ) {
        let mut search = CoarseSearch::new(candidates, few);
        let (mut runs, mut poses, mut asked) = (Vec::new(), Vec::new(), Vec::new());
        results.reverse();
        while let Some(p) = search
            .next_pose(
                10,
                |k| {
                    asked.push(k);
                    Ok::<_, ()>(wider(k))
                },
                |c, k| {
                    runs.push((c.map(<[u32]>::len), k));
                    Ok(results.pop().expect("a tier no test result was given for"))
                },
            )
            .unwrap()
        {
            poses.push((p.estimate.num_inliers, p.narrowed));
        }
        assert!(results.is_empty(), "tiers left unrun: {}", results.len());
        (runs, poses, asked, search)
    }

    #[test]
    fn a_small_map_s_wider_net_is_every_point_and_every_tier_s_pose_is_offered() {
        let few = [1, 2];
        let results = vec![(pose(21), false), (pose(20), false), (pose(16), false)];
        let (runs, poses, asked, search) = walk(Some(vec![1, 2, 3]), Some(&few), results, |_| None);
        let k = COARSE_KEYPOINTS;
        assert_eq!(runs, [(Some(2), k), (Some(3), k), (None, k)]);
        assert_eq!(poses, [(21, true), (20, true), (16, false)]);
        // The every-point net ends the wider tiers; nothing sampled, a pose found: done.
        assert_eq!(asked, [40]);
        assert!(search.candidates.is_none());
    }

    #[test]
    fn without_any_pose_the_nets_widen_then_every_keypoint_then_every_point() {
        let few = [1];
        let results = vec![
            (none(3), true),
            (none(4), true),
            (none(5), true),
            (none(6), true),
            (none(7), false),
            (none(8), false),
        ];
        let (runs, poses, asked, search) = walk(Some(vec![1, 2]), Some(&few), results, |k| {
            Some((0..k as u32).collect())
        });
        let k = COARSE_KEYPOINTS;
        let all = usize::MAX;
        let expected = [
            (Some(1), k),
            (Some(2), k),
            (Some(40), k),
            (Some(160), k),
            (Some(160), all),
            (None, all),
        ];
        assert_eq!(runs, expected);
        assert!(poses.is_empty());
        assert_eq!(asked, [40, 160]);
        assert_eq!(search.failure.map(|f| f.1), Some(8));
    }

    #[test]
    fn a_net_no_wider_than_the_last_is_skipped_and_a_found_pose_spares_every_point() {
        let results = vec![(pose(30), true), (pose(40), false)];
        let (runs, poses, asked, _) =
            walk(Some(vec![1, 2, 3]), None, results, |_| Some(vec![1, 2]));
        let k = COARSE_KEYPOINTS;
        assert_eq!(runs, [(Some(3), k), (Some(3), usize::MAX)]);
        assert_eq!(poses, [(30, true), (40, true)]);
        assert_eq!(asked, [40, 160]);
    }

    #[test]
    fn without_retrieval_only_every_point_is_tried() {
        let (runs, poses, asked, _) = walk(None, None, vec![(pose(50), false)], |_| None);
        assert_eq!(runs, [(None, usize::MAX)]);
        assert_eq!(poses, [(50, false)]);
        assert!(asked.is_empty());
        let (runs, poses, _, search) = walk(None, None, vec![(none(2), false)], |_| None);
        assert_eq!((runs.len(), poses.len()), (1, 0));
        assert!(search.failure.is_some());
    }
}
