//! The hierarchical localizer: retrieval → candidates → coarse matching on the deepest
//! selected level → P3P LO-RANSAC → gated matching level by level (projected candidates within
//! a radius of each query keypoint) → re-estimation and refinement on all inliers.
//!
//! A [`Localizer`] is built once per map (it indexes the levels and visibility) and shared by
//! threads; it reads descriptors straight from the mmapped map.

use super::geometry::{estimate_absolute_pose_with_prior, Camera, Pose, RansacOptions};
use super::matching::{dot, gemm_abt, match_descriptors, normalise_rows, MatchOptions};
use crate::format::{Error as FormatError, Map, Visibility};
use nalgebra::{Vector2, Vector3};
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
    /// Retrieved database images (when the map has global descriptors).
    pub top_k: usize,
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
    /// `cam_from_world`, or `None` when the query failed.
    pub pose: Option<Pose>,
    /// Why the query failed.
    pub failure: Option<String>,
    /// (level, inliers) of the final estimate.
    pub inliers_per_level: Vec<(u16, usize)>,
    pub matches: usize,
    pub inliers: usize,
    pub retrieved_images: usize,
    pub times: StageTimes,
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
        }
    }
}

impl std::error::Error for LocalizeError {}

impl From<FormatError> for LocalizeError {
    fn from(e: FormatError) -> Self {
        LocalizeError::Format(e)
    }
}

struct LevelIndex {
    id: u16,
    /// Global point → row in the level, `u32::MAX` if the level does not hold it.
    row_of_point: Vec<u32>,
    /// Every row's descriptor as f32, unit norm, in the stored basis: `short` only
    /// (`[rows × dim_short]`) or the full one.
    descriptors: Vec<f32>,
    dim: usize,
    /// `[dim × d_in]`: maps a query descriptor into the stored basis (first `dim` rows).
    projection: Option<Vec<f32>>,
    d_in: usize,
}

/// A map prepared for localization: levels indexed, descriptors decoded to f32 once.
pub struct Localizer<'m> {
    map: &'m Map<'m>,
    options: LocalizeOptions,
    positions: Vec<Vector3<f64>>,
    /// Selected levels, deepest first.
    levels: Vec<LevelIndex>,
    global: Option<(Vec<f32>, usize)>,
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
        let n_points = map.n_points() as usize;
        let mut levels = Vec::new();
        for id in ids {
            let level = map.level(id)?;
            if !level.has_descriptors() {
                return Err(LocalizeError::NoDescriptors);
            }
            let use_full = !options.short && level.has_rest();
            let (ds, df) = (level.dim_short(), level.dim_full());
            let dim = if use_full { df } else { ds };
            let short = level.desc_short()?;
            let rest = if use_full { level.desc_rest()? } else { None };
            let mut descriptors = Vec::with_capacity(level.len() * dim);
            for r in 0..level.len() {
                descriptors.extend(short[r * ds..(r + 1) * ds].iter().map(|x| x.to_f32()));
                if let Some(rest) = &rest {
                    descriptors.extend(
                        rest[r * (df - ds)..(r + 1) * (df - ds)]
                            .iter()
                            .map(|x| x.to_f32()),
                    );
                }
            }
            normalise_rows(&mut descriptors, dim);
            let mut row_of_point = vec![u32::MAX; n_points];
            for (row, &p) in level.points()?.iter().enumerate() {
                row_of_point[p as usize] = row as u32;
            }
            let (projection, d_in) = match level.projection()? {
                Some(p) => {
                    let d_in = level.projection_input_dim().unwrap_or(0);
                    (Some(p[..dim * d_in].to_vec()), d_in)
                }
                None => (None, df),
            };
            levels.push(LevelIndex {
                id,
                row_of_point,
                descriptors,
                dim,
                projection,
                d_in,
            });
        }
        let positions = map
            .point_positions()?
            .iter()
            .map(|&p| Vector3::from(map.to_world(p)))
            .collect();
        let global = map.image_global()?.map(|(g, dim)| {
            let mut v: Vec<f32> = g.iter().map(|x| x.to_f32()).collect();
            normalise_rows(&mut v, dim);
            (v, dim)
        });
        let visibility = map.visibility()?;
        Ok(Localizer {
            map,
            options,
            positions,
            levels,
            global,
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

    /// Localizes one query. Errors only for unusable input; a query that cannot be localized
    /// returns a `Localization` with `pose: None` and the reason.
    pub fn localize(
        &self,
        query: &QueryFeatures,
        camera: &Camera,
    ) -> Result<Localization, LocalizeError> {
        let t0 = Instant::now();
        let mut times = StageTimes::default();
        let candidates = self.candidate_points(query);
        times.retrieval_ms = ms(t0);
        let retrieved_images = candidates.1;
        let candidate_points = candidates.0;

        // Query descriptors in each level's basis.
        let mut projected = Vec::with_capacity(self.levels.len());
        for level in &self.levels {
            let set = query
                .sets
                .iter()
                .find(|s| s.level == Some(level.id))
                .or_else(|| query.sets.iter().find(|s| s.level.is_none()))
                .ok_or(LocalizeError::NoFeaturesForLevel { level: level.id })?;
            projected.push((set, self.project(level, set)?));
        }

        let failed = |reason: String, matches, times| Localization {
            pose: None,
            failure: Some(reason),
            inliers_per_level: Vec::new(),
            matches,
            inliers: 0,
            retrieved_images,
            times,
        };

        // Coarse: the deepest level against its candidates (all levels pooled if too few);
        // if the retrieved images give no pose, once more against every point (retrieval
        // can be wrong where the global descriptor is weak).
        let mut attempt = self.coarse(&projected, &candidate_points, camera, &mut times);
        if attempt.is_err() && candidate_points.len() < self.positions.len() {
            let all: Vec<u32> = (0..self.positions.len() as u32).collect();
            attempt = self.coarse(&projected, &all, camera, &mut times);
        }
        let coarse = match attempt {
            Ok(found) => found,
            Err((reason, matches)) => {
                times.total_ms = ms(t0);
                return Ok(failed(reason, matches, times));
            }
        };

        // Fine: guided matching around projections on every selected level, then one final
        // estimate seeded with the coarse pose.
        let t3 = Instant::now();
        let mut pose = coarse.pose;
        let mut result = None;
        for _round in 0..2 {
            let mut pixels = Vec::new();
            let mut points = Vec::new();
            let mut level_of = Vec::new();
            for (i, level) in self.levels.iter().enumerate() {
                let (set, q) = &projected[i];
                let before = pixels.len();
                self.guided_level(level, set, q, &pose, camera, &mut pixels, &mut points);
                level_of.extend(std::iter::repeat_n(level.id, pixels.len() - before));
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
        times.fine_ms = ms(t3);
        times.total_ms = ms(t0);
        let Some((estimate, level_of, n_matches)) = result else {
            // The coarse pose stands if guided matching could not improve it.
            let inliers = coarse.num_inliers;
            // The inlier mask has one entry per coarse match.
            let coarse_matches = coarse.inliers.len();
            if inliers < self.options.min_inliers {
                return Ok(failed(
                    format!("only {inliers} inliers"),
                    coarse_matches,
                    times,
                ));
            }
            return Ok(Localization {
                pose: Some(coarse.pose),
                failure: None,
                inliers_per_level: vec![(self.levels[0].id, inliers)],
                matches: coarse_matches,
                inliers,
                retrieved_images,
                times,
            });
        };
        let mut per_level: Vec<(u16, usize)> = self.levels.iter().map(|l| (l.id, 0)).collect();
        for (k, &inlier) in estimate.inliers.iter().enumerate() {
            if inlier {
                if let Some(e) = per_level.iter_mut().find(|e| e.0 == level_of[k]) {
                    e.1 += 1;
                }
            }
        }
        Ok(Localization {
            pose: Some(estimate.pose),
            failure: None,
            inliers_per_level: per_level,
            matches: n_matches,
            inliers: estimate.num_inliers,
            retrieved_images,
            times,
        })
    }

    /// Matching against `candidates`, deepest level first, then P3P LO-RANSAC: the pose
    /// estimate (its inlier mask has one entry per match), or the reason and the number of
    /// matches.
    fn coarse(
        &self,
        projected: &[(&FeatureSet, Vec<f32>)],
        candidates: &[u32],
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<super::geometry::PoseEstimate, (String, usize)> {
        let t1 = Instant::now();
        let mut pixels = Vec::new();
        let mut points = Vec::new();
        for (level, (set, q)) in self.levels.iter().zip(projected) {
            self.match_level(level, set, q, candidates, &mut pixels, &mut points);
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
        found.map_err(|e| {
            (
                format!("coarse pose: {e} ({} matches)", pixels.len()),
                pixels.len(),
            )
        })
    }

    /// Candidate points (global indices, sorted, deduplicated) seen by the retrieved images,
    /// and how many images were retrieved. Without global descriptors or visibility: all
    /// points.
    fn candidate_points(&self, query: &QueryFeatures) -> (Vec<u32>, usize) {
        let n_images = self.map.n_images() as usize;
        let images: Vec<usize> = match (&self.global, &query.global) {
            (Some((g, dim)), Some(q)) if q.len() == *dim && n_images > 0 => {
                let mut q = q.clone();
                normalise_rows(&mut q, *dim);
                let mut scores = vec![0.0; n_images];
                gemm_abt(&q, g, &mut scores, 1, n_images, *dim);
                let mut order: Vec<usize> = (0..n_images).collect();
                order.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
                order.truncate(self.options.top_k.max(1));
                order
            }
            _ => (0..n_images).collect(),
        };
        match &self.visibility {
            Some(visibility) if !images.is_empty() => {
                let mut seen = vec![false; self.positions.len()];
                for &i in &images {
                    for &p in visibility.points_of(i) {
                        seen[p as usize] = true;
                    }
                }
                (
                    (0..seen.len() as u32)
                        .filter(|&p| seen[p as usize])
                        .collect(),
                    images.len(),
                )
            }
            _ => ((0..self.positions.len() as u32).collect(), images.len()),
        }
    }

    /// The query's descriptors of `set` in `level`'s stored basis, truncated to the matched
    /// dimensions and renormalised.
    fn project(&self, level: &LevelIndex, set: &FeatureSet) -> Result<Vec<f32>, LocalizeError> {
        let n = set.keypoints.len();
        // The fields are public: a set of the wrong shape is an error, not a panic below.
        if n.checked_mul(set.dim) != Some(set.descriptors.len()) {
            return Err(LocalizeError::FeatureShape {
                keypoints: n,
                dim: set.dim,
                values: set.descriptors.len(),
            });
        }
        let mut out = vec![0.0f32; n * level.dim];
        match &level.projection {
            Some(p) => {
                if set.dim != level.d_in {
                    return Err(LocalizeError::DescriptorMismatch {
                        level: level.id,
                        expected: level.d_in,
                        found: set.dim,
                    });
                }
                gemm_abt(&set.descriptors, p, &mut out, n, level.dim, set.dim);
            }
            None => {
                if set.dim < level.dim || set.dim != level.d_in {
                    return Err(LocalizeError::DescriptorMismatch {
                        level: level.id,
                        expected: level.d_in,
                        found: set.dim,
                    });
                }
                for (row, src) in out
                    .chunks_exact_mut(level.dim)
                    .zip(set.descriptors.chunks_exact(set.dim))
                {
                    row.copy_from_slice(&src[..level.dim]);
                }
            }
        }
        normalise_rows(&mut out, level.dim);
        Ok(out)
    }

    /// Global matching of a level's query descriptors against its candidate points.
    fn match_level(
        &self,
        level: &LevelIndex,
        set: &FeatureSet,
        q: &[f32],
        candidates: &[u32],
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) {
        let rows: Vec<(u32, u32)> = candidates
            .iter()
            .filter_map(|&p| {
                let r = level.row_of_point[p as usize];
                (r != u32::MAX).then_some((p, r))
            })
            .collect();
        let mut block = Vec::with_capacity(rows.len() * level.dim);
        for &(_, r) in &rows {
            block.extend_from_slice(
                &level.descriptors[r as usize * level.dim..(r as usize + 1) * level.dim],
            );
        }
        for m in match_descriptors(q, &block, level.dim, &self.options.matching) {
            let kp = set.keypoints[m.query as usize];
            pixels.push(Vector2::new(kp[0], kp[1]));
            points.push(self.positions[rows[m.map as usize].0 as usize]);
        }
    }

    /// Guided matching: every point of the level that projects into the image is a candidate
    /// for the query keypoints within `gate_px` of its projection.
    #[allow(clippy::too_many_arguments)]
    fn guided_level(
        &self,
        level: &LevelIndex,
        set: &FeatureSet,
        q: &[f32],
        pose: &Pose,
        camera: &Camera,
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) {
        let gate = self.options.gate_px.max(1.0);
        let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
        // Grid cells at least a gate wide (so a 3 × 3 block covers the gate), and at most
        // MAX_GRID_CELLS of them whatever the image size the camera claims.
        let cell_px = gate.max((w * h / MAX_GRID_CELLS).sqrt());
        let cols = (w / cell_px).ceil() as usize + 1;
        let rows_n = (h / cell_px).ceil() as usize + 1;
        let mut grid: Vec<Vec<(u32, [f32; 2])>> = vec![Vec::new(); cols * rows_n];
        for (p, &row) in level.row_of_point.iter().enumerate() {
            if row == u32::MAX {
                continue;
            }
            let pc = pose.transform(&self.positions[p]);
            if pc.z <= 0.0 {
                continue;
            }
            let Some(px) = camera.project(&pc) else {
                continue;
            };
            if !(px.x >= 0.0 && px.y >= 0.0 && px.x < w && px.y < h) {
                continue;
            }
            let cell = (px.y / cell_px) as usize * cols + (px.x / cell_px) as usize;
            grid[cell].push((p as u32, [px.x as f32, px.y as f32]));
        }
        let dim = level.dim;
        // (point, similarity, keypoint); each map point keeps its best keypoint below.
        let mut found: Vec<(u32, f32, usize)> = Vec::new();
        let gate2 = (gate * gate) as f32;
        for (k, kp) in set.keypoints.iter().enumerate() {
            if !(kp[0] >= 0.0 && kp[1] >= 0.0 && kp[0] < w && kp[1] < h) {
                continue;
            }
            let (cx, cy) = ((kp[0] / cell_px) as i64, (kp[1] / cell_px) as i64);
            let qd = &q[k * dim..(k + 1) * dim];
            let (mut best, mut second) = ((f32::NEG_INFINITY, u32::MAX), f32::NEG_INFINITY);
            for gy in cy - 1..=cy + 1 {
                for gx in cx - 1..=cx + 1 {
                    if gx < 0 || gy < 0 || gx as usize >= cols || gy as usize >= rows_n {
                        continue;
                    }
                    for &(p, xy) in &grid[gy as usize * cols + gx as usize] {
                        let (dx, dy) = (xy[0] - kp[0] as f32, xy[1] - kp[1] as f32);
                        if dx * dx + dy * dy > gate2 {
                            continue;
                        }
                        let r = level.row_of_point[p as usize] as usize;
                        let s = dot(qd, &level.descriptors[r * dim..(r + 1) * dim]);
                        if s > best.0 {
                            second = best.0;
                            best = (s, p);
                        } else if s > second {
                            second = s;
                        }
                    }
                }
            }
            if best.1 == u32::MAX || best.0 < self.options.matching.min_similarity {
                continue;
            }
            let d = |s: f32| (2.0 - 2.0 * s).max(0.0).sqrt();
            if second.is_finite() && d(best.0) >= self.options.gate_ratio * d(second) {
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

/// Upper bound on the guided-matching grid (a camera may claim any size up to u32).
const MAX_GRID_CELLS: f64 = (1u32 << 20) as f64;
