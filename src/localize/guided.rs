//! Guided matching: query keypoints matched to the map points that project near them, level
//! by level, around a pose (the coarse pose, or a sequence's prediction), then re-estimated.
//! The fine stage of every query, and the whole of a tracked one.

use super::coarse::sure_inliers;
use super::level::LevelIndex;
use super::localizer::{ms, Query};
use super::matching::fails_ratio_test;
use super::{
    InlierLink, Localization, LocalizationPath, LocalizeError, Localizer, StageTimes, TrackingLost,
};
use crate::geometry::{
    estimate_absolute_pose_with_prior, pose_covariance, Camera, Pose, RansacOptions,
};
use crate::vector::dot;
use nalgebra::{Vector2, Vector3};
use std::time::Instant;

/// A pose prior's first gate is this many times `gate_px`: a prediction is further off than
/// a coarse pose fitted to the frame. Measured on the street's walk (100 k points, level 2
/// short): 1.0 tracked 2 of 20 frames within 0.5 m and 2° (the others drifted), 2.0 all 20.
const PRIOR_GATE_FACTOR: f64 = 2.0;

/// A tracked pose must have at least this share of its guided matches as inliers. The demo
/// room's unordered queries run as a sequence: wrong tracks had 11–13 % (16 of 149, 23 of
/// 175, 30 of 252); the street's walk, level 2 short: right tracks 25–29 % at worst (0.3 lost
/// 4 of its 19 predicted frames, 0.2 none).
const TRACKING_MIN_INLIER_SHARE: f64 = 0.2;

/// The confidence of a prior's wide first round, estimated like a coarse pose (at
/// `coarse_error_px`): it only seeds the second round, which gates again at `gate_px` and
/// estimates at full confidence, and a wrong seed ends in a lost track (retrieval takes the
/// frame). Its matches are a quarter inliers (the street's walk: 36-62 of 205-254 at 6 px),
/// which took 430-2,200 samples at 0.9999 and 6 px; the walk 3.3 -> 2.9 ms a frame, its
/// median errors unchanged (0.023°, 5.3 mm).
const PRIOR_ROUND_CONFIDENCE: f64 = 0.99;

/// Decoded values of the rows in view guided matching keeps for a level (16 MB).
const DECODED_IN_VIEW_MAX: usize = 4 << 20;
// Its buffer is per-thread scratch, which keeps buffers up to this size.
const _: () = assert!(DECODED_IN_VIEW_MAX <= super::scratch::KEEP_MAX_VALUES);

impl Localizer<'_> {
    /// The tracking path: guided matching around `prior` against the points of the database
    /// images nearest it, with a gate widened for the prediction's error.
    pub(super) fn track(
        &self,
        sets: &[Query<'_>],
        prior: &Pose,
        camera: &Camera,
        times: &mut StageTimes,
    ) -> Result<Result<Localization, TrackingLost>, LocalizeError> {
        let t = Instant::now();
        let (Some(viewpoints), Some(visibility)) = (&self.viewpoints, &self.visibility) else {
            return Ok(Err(TrackingLost::NoImagesNearPrior));
        };
        let images = viewpoints.near(prior, self.options.top_k);
        if images.is_empty() {
            return Ok(Err(TrackingLost::NoImagesNearPrior));
        }
        let candidates =
            super::retrieval::points_seen(&images, self.n_points(), |i| visibility.points_of(i))?;
        let gate = self.options.gate_px * PRIOR_GATE_FACTOR;
        let result = self.refine(sets, candidates.as_deref(), *prior, gate, camera)?;
        times.fine_ms += ms(t);
        let (inliers, matches) = result.as_ref().map_or((0, 0), |f| (f.inliers, f.matches));
        // Around a wrong prior, gated matching still finds some matches, and RANSAC a subset
        // of them consistent with a wrong pose: a tracked pose must explain a share of the
        // matches as well as `min_inliers` (`TRACKING_MIN_INLIER_SHARE`).
        let needed = self
            .options
            .min_inliers
            .max((matches as f64 * TRACKING_MIN_INLIER_SHARE).ceil() as usize);
        Ok(match result {
            Some(found) if inliers >= needed => Ok(Localization {
                retrieved_images: images.len(),
                ..found
            }),
            _ => Err(TrackingLost::TooFewInliers {
                inliers,
                needed,
                matches,
            }),
        })
    }

    /// Up to two rounds of guided matching on every selected level (`candidates`: the points
    /// to consider, `None` every point) around `start`, the first with a gate of `first_gate`
    /// pixels (when that is wider than `gate_px`: on every `stride`-th keypoint, again on all
    /// of them if that gives no pose, estimated like a coarse pose only to seed the second),
    /// each followed by a RANSAC estimate seeded with the pose so far; the second is skipped
    /// when the first barely moved the pose at the same gate ([`settled`]). The last estimate
    /// as a localization (the caller fills in retrieval and timing), or `None` if the first
    /// round gives no pose, or a seeding round's second does not. Fails only for a damaged
    /// chunk of the map.
    pub(super) fn refine(
        &self,
        sets: &[Query<'_>],
        candidates: Option<&[u32]>,
        start: Pose,
        first_gate: f64,
        camera: &Camera,
    ) -> Result<Option<Localization>, LocalizeError> {
        let mut pose = start;
        let mut result = None;
        // Each level's candidate rows, found once for all rounds.
        let rows: Vec<Option<Vec<u32>>> = self
            .levels
            .iter()
            .map(|l| l.rows_of(candidates))
            .collect::<Result<_, _>>()?;
        // A first gate wider than `gate_px` (a prior's) looks at every `stride`-th keypoint,
        // so that it compares about as many keypoint × point pairs as a round at `gate_px`
        // (the street's walk, level 2 short: 7 -> 4 ms a frame); if that gives no pose, the
        // round is run again with every keypoint.
        let mut stride = if first_gate > self.options.gate_px {
            ((first_gate / self.options.gate_px).powi(2).round() as usize).max(1)
        } else {
            1
        };
        let mut round = 0;
        while round < 2 {
            // The second round starts from a pose fitted to this frame: a prior's wider first
            // gate is no longer needed. (A narrower one, twice `fine_error_px`, was faster but
            // lost recall on South Building's SFP level-2 short map, 92 -> 88 %.)
            let gate_px = if round == 0 {
                first_gate
            } else {
                first_gate.min(self.options.gate_px)
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
                    if round == 0 { stride } else { 1 },
                    gate_px,
                    &pose,
                    camera,
                    &mut pixels,
                    &mut points,
                );
                level_of.extend(std::iter::repeat_n(i, pixels.len() - before));
            }
            // A pose that already explains `sure` of the gated matches is refined, not searched
            // around (the street's walk: two rounds' RANSAC 1.5 -> 1.1 ms a frame).
            let sure = sure_inliers(self.options.min_inliers);
            let seeding = round == 0 && first_gate > self.options.gate_px;
            let fine_options = RansacOptions {
                max_error_px: if seeding {
                    self.options.coarse_error_px
                } else {
                    self.options.fine_error_px
                },
                confidence: if seeding {
                    PRIOR_ROUND_CONFIDENCE
                } else {
                    RansacOptions::default().confidence
                },
                min_inliers: self.options.min_inliers,
                accept_prior: Some(sure),
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
                    // A strong first round that barely moved the pose ends the refinement.
                    let settled = round == 0
                        && self.options.gate_px >= first_gate
                        && e.num_inliers >= sure
                        && settled(&pose, &e, &points, camera, first_gate / 4.0);
                    pose = e.pose;
                    result = Some((e, level_of, pixels, points));
                    if settled {
                        break;
                    }
                    round += 1;
                }
                Err(_) if round == 0 && stride > 1 => stride = 1,
                // A seeding round's pose (at the coarse threshold) is no answer of its own: the
                // frame goes to retrieval.
                Err(_) if round == 1 && first_gate > self.options.gate_px => return Ok(None),
                Err(_) => break,
            }
        }
        let Some((estimate, level_of, pixels, points)) = result else {
            return Ok(None);
        };
        let matches = pixels.len();
        let inliers: Vec<usize> = estimate.inlier_indices().collect();
        let covariance = pose_covariance(&pixels, &points, &inliers, camera, &estimate.pose);
        let inlier_links = match self.options.keep_inliers {
            true => inliers
                .iter()
                .map(|&i| InlierLink {
                    pixel: [pixels[i].x, pixels[i].y],
                    point: [points[i].x, points[i].y, points[i].z],
                    level: self.levels[level_of[i]].id,
                })
                .collect(),
            false => Vec::new(),
        };
        let mut per_level: Vec<(u16, usize)> = self.levels.iter().map(|l| (l.id, 0)).collect();
        for (&inlier, &i) in estimate.inliers.iter().zip(&level_of) {
            if inlier {
                per_level[i].1 += 1;
            }
        }
        Ok(Some(Localization {
            outcome: Ok(estimate.pose),
            inliers_per_level: per_level,
            matches,
            inliers: estimate.num_inliers,
            retrieved_images: 0,
            retrieved: Vec::new(),
            retrieval: None,
            retrieval_fallback: None,
            path: LocalizationPath::Retrieval,
            tracking_lost: None,
            times: StageTimes::default(),
            covariance,
            inlier_links,
        }))
    }

    /// Guided matching: every point of the level (of `rows`, if given) that projects into the
    /// image is a candidate for the query keypoints (every `stride`-th) within `gate_px` of
    /// its projection.
    #[allow(clippy::too_many_arguments)]
    fn guided_level(
        &self,
        level: &LevelIndex<'_>,
        query: &Query<'_>,
        rows: Option<&[u32]>,
        stride: usize,
        gate_px: f64,
        pose: &Pose,
        camera: &Camera,
        pixels: &mut Vec<Vector2<f64>>,
        points: &mut Vec<Vector3<f64>>,
    ) {
        let set = query.set;
        let gate = gate_px.max(1.0);
        let (w, h) = (f64::from(camera.width()), f64::from(camera.height()));
        // The points in view: (level row, pixel).
        let mut in_view: Vec<(u32, [f32; 2])> = Vec::new();
        let all_rows = || 0..level.points.len() as u32;
        let candidate_rows: &mut dyn Iterator<Item = u32> = match rows {
            Some(rows) => &mut rows.iter().copied(),
            None => &mut all_rows(),
        };
        for row in candidate_rows {
            let p = level.points[row as usize];
            let pc = pose.transform(&self.position(p));
            if pc.z <= 0.0 {
                continue;
            }
            let Some(px) = camera.project(&pc) else {
                continue;
            };
            if !(px.x >= 0.0 && px.y >= 0.0 && px.x < w && px.y < h) {
                continue;
            }
            in_view.push((row, [px.x as f32, px.y as f32]));
        }
        if in_view.is_empty() {
            return;
        }
        let (grid, slots) = Grid::new(&in_view, gate);
        // Most keypoints will need their projection when the level has as many points in view
        // as a quarter of the keypoints: then one GEMM for all of them (5x faster than row by
        // row), held only while this level is matched; otherwise each keypoint is projected
        // alone, and only if some point is near it.
        let all = (query.projected.get().is_some() || in_view.len() * 4 >= set.keypoints.len())
            .then(|| query.projected.get_or_init(|| self.project(level, set)));
        let mut queries = match all {
            Some(all) => QueryRows::Projected(all, level.dim),
            None => QueryRows::OnDemand {
                localizer: self,
                level,
                set,
                row: Vec::with_capacity(level.dim),
                keypoint: usize::MAX,
            },
        };
        // The rows in view are decoded once when they are few (retrieval's candidates: a gate
        // reaches each row dozens of times, 100 k street fine stage 55 -> 14 ms): in ascending
        // row order, which reads the mapping far faster than the grid's order (neighbouring
        // points have neighbouring ids), each into its cell-order slot. A level in view at
        // large (no retrieval, 1 M points) would make that copy hundreds of MB, so then a row
        // is decoded each time a gate reaches it.
        let found = if grid.points.len() * level.dim <= DECODED_IN_VIEW_MAX {
            // Every slot is written: `slots` is a permutation of the rows in view.
            super::scratch::with_f32(grid.points.len() * level.dim, |rows| {
                for (&(row, _), &slot) in in_view.iter().zip(&slots) {
                    let slot = slot as usize;
                    level.decode_row(
                        row as usize,
                        &mut rows[slot * level.dim..(slot + 1) * level.dim],
                    );
                }
                let mut map = MapRows::Decoded(rows, level.dim);
                best_in_gates(set, stride, (w, h), gate, &grid, &mut queries, &mut map)
            })
        } else {
            let mut map = MapRows::OnDemand {
                level,
                row: vec![0.0f32; level.dim],
            };
            best_in_gates(set, stride, (w, h), gate, &grid, &mut queries, &mut map)
        };
        let min_similarity = self.options.matching.min_similarity;
        let mut found: Vec<(u32, f32, usize)> = found
            .into_iter()
            .filter(|g| {
                g.best >= min_similarity
                    && !fails_ratio_test(g.best, g.second, self.options.gate_ratio)
            })
            .map(|g| {
                (
                    level.points[grid.points[g.slot as usize].0 as usize],
                    g.best,
                    g.keypoint,
                )
            })
            .collect();
        // Each map point is matched once, to its most similar keypoint.
        found.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(b.1.total_cmp(&a.1)).then(a.2.cmp(&b.2)));
        found.dedup_by_key(|f| f.0);
        for (p, _, k) in found {
            let kp = set.keypoints[k];
            pixels.push(Vector2::new(kp[0], kp[1]));
            points.push(self.position(p));
        }
    }
}

/// A query keypoint's most similar point within its gate: the point's slot in the grid,
/// the similarity, the runner-up's.
struct Gated {
    keypoint: usize,
    slot: u32,
    best: f32,
    second: f32,
}

/// The query descriptors guided matching compares, in the level's basis.
enum QueryRows<'a, 'm> {
    /// Every keypoint's, projected at once (`[keypoints × dim]`).
    Projected(&'a [f32], usize),
    /// Projected one keypoint at a time, when a gate first holds a point.
    OnDemand {
        localizer: &'a Localizer<'m>,
        level: &'a LevelIndex<'m>,
        set: &'a crate::localize::FeatureSet,
        row: Vec<f32>,
        /// Whose projection `row` holds.
        keypoint: usize,
    },
}

impl QueryRows<'_, '_> {
    #[inline]
    fn row(&mut self, k: usize) -> &[f32] {
        match self {
            QueryRows::Projected(all, dim) => &all[k * *dim..(k + 1) * *dim],
            QueryRows::OnDemand {
                localizer,
                level,
                set,
                row,
                keypoint,
            } => {
                if *keypoint != k {
                    localizer.project_row(level, set, k, row);
                    *keypoint = k;
                }
                row
            }
        }
    }
}

/// The map rows in view, by grid slot.
enum MapRows<'a, 'm> {
    /// Decoded in slot order (`[slots × dim]`).
    Decoded(&'a [f32], usize),
    /// Decoded each time one is compared (`row` is scratch).
    OnDemand {
        level: &'a LevelIndex<'m>,
        row: Vec<f32>,
    },
}

impl MapRows<'_, '_> {
    #[inline]
    fn row(&mut self, slot: usize, level_row: u32) -> &[f32] {
        match self {
            MapRows::Decoded(rows, dim) => &rows[slot * *dim..(slot + 1) * *dim],
            MapRows::OnDemand { level, row } => {
                level.decode_row(level_row as usize, row);
                row
            }
        }
    }
}

/// For every `stride`-th keypoint of `set` inside the image (`size`), the most similar point
/// of `grid` within `gate` pixels, and the runner-up's similarity. Most of guided matching's
/// time (the street's SIFT map: about 200,000 gated pairs of 128 dimensions a level), so it
/// is compiled for AVX-512 and AVX2 too, chosen at run time: the inlined dot product's 8
/// lanes then fill one register with FMA instead of two SSE2 registers without.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
fn best_in_gates<'a, 'b, 'm>(
    set: &crate::localize::FeatureSet,
    stride: usize,
    size: (f64, f64),
    gate: f64,
    grid: &Grid,
    queries: &mut QueryRows<'a, 'm>,
    map: &mut MapRows<'b, 'm>,
) -> Vec<Gated> {
    let (w, h) = size;
    let gate2 = (gate * gate) as f32;
    let mut found = Vec::new();
    for (k, kp) in set.keypoints.iter().enumerate().step_by(stride.max(1)) {
        if !(kp[0] >= 0.0 && kp[1] >= 0.0 && kp[0] < w && kp[1] < h) {
            continue;
        }
        let (x, y) = (kp[0] as f32, kp[1] as f32);
        let mut best = Gated {
            keypoint: k,
            slot: u32::MAX,
            best: f32::NEG_INFINITY,
            second: f32::NEG_INFINITY,
        };
        for (lo, hi) in grid.around(kp[0], kp[1]) {
            for (slot, &(row, xy)) in (lo..hi).zip(&grid.points[lo..hi]) {
                let (dx, dy) = (xy[0] - x, xy[1] - y);
                if dx * dx + dy * dy > gate2 {
                    continue;
                }
                let s = dot(queries.row(k), map.row(slot, row));
                if s > best.best {
                    best.second = best.best;
                    best.best = s;
                    best.slot = slot as u32;
                } else if s > best.second {
                    best.second = s;
                }
            }
        }
        if best.slot != u32::MAX {
            found.push(best);
        }
    }
    found
}

/// The points in view bucketed by a flat grid over their bounding box (counting sort into
/// cell order, offsets per cell): a keypoint finds the points of the 3 × 3 cells around it by
/// six lookups. Cells are at least a gate wide, so those cells cover the gate, and wider when
/// the points spread so far that the grid would outgrow them: memory follows the points in
/// view, and so does the work, whatever image size the camera claims.
struct Grid {
    /// The bounding box's lowest corner.
    origin: [f64; 2],
    cell: f64,
    columns: usize,
    rows: usize,
    /// `offsets[c]..offsets[c + 1]`: cell `c`'s entries of `points` (row-major cells).
    offsets: Vec<u32>,
    /// (level row, pixel), in cell order, in their input order within a cell.
    points: Vec<(u32, [f32; 2])>,
}

impl Grid {
    /// The grid, and the slot in `points` of each entry of `in_view` (whose pixels are
    /// finite).
    fn new(in_view: &[(u32, [f32; 2])], gate: f64) -> (Grid, Vec<u32>) {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for (_, xy) in in_view {
            for k in 0..2 {
                lo[k] = lo[k].min(f64::from(xy[k]));
                hi[k] = hi[k].max(f64::from(xy[k]));
            }
        }
        let (w, h) = ((hi[0] - lo[0]).max(0.0), (hi[1] - lo[1]).max(0.0));
        let max_cells = (4 * in_view.len() + 1024) as f64;
        // Each side has at most `max_cells` cells, and the area at most `max_cells` cells.
        let cell = gate
            .max((w * h / max_cells).sqrt())
            .max(w / max_cells)
            .max(h / max_cells);
        let columns = (w / cell) as usize + 1;
        let rows = (h / cell) as usize + 1;
        let mut grid = Grid {
            origin: if in_view.is_empty() { [0.0; 2] } else { lo },
            cell,
            columns,
            rows,
            offsets: vec![0u32; columns * rows + 1],
            points: vec![(0u32, [0.0f32; 2]); in_view.len()],
        };
        // Counts, their exclusive sums (each cell's start), then each entry placed at its
        // cell's next slot: the starts become the ends, shifted into `offsets[c + 1]`.
        let cells: Vec<usize> = in_view.iter().map(|&(_, xy)| grid.index(xy)).collect();
        for &c in &cells {
            grid.offsets[c] += 1;
        }
        let mut running = 0;
        for o in &mut grid.offsets {
            let count = *o;
            *o = running;
            running += count;
        }
        let slots: Vec<u32> = cells
            .iter()
            .zip(in_view)
            .map(|(&c, &entry)| {
                let slot = grid.offsets[c];
                grid.points[slot as usize] = entry;
                grid.offsets[c] += 1;
                slot
            })
            .collect();
        grid.offsets.rotate_right(1);
        grid.offsets[0] = 0;
        (grid, slots)
    }

    fn index(&self, xy: [f32; 2]) -> usize {
        let cx = (((f64::from(xy[0]) - self.origin[0]) / self.cell) as usize).min(self.columns - 1);
        let cy = (((f64::from(xy[1]) - self.origin[1]) / self.cell) as usize).min(self.rows - 1);
        cy * self.columns + cx
    }

    /// For each of the (up to 3) cell rows around pixel (x, y), the range of `points` in the
    /// (up to 3) cells around it in that row; none when (x, y) is more than a cell outside the
    /// bounding box.
    fn around(&self, x: f64, y: f64) -> impl Iterator<Item = (usize, usize)> + '_ {
        let at = |v: f64, origin: f64| ((v - origin) / self.cell).floor();
        let (fx, fy) = (at(x, self.origin[0]), at(y, self.origin[1]));
        // Cells f − 1 ..= f + 1 within 0..n, as a half-open range (empty when none are).
        let span = |f: f64, n: usize| -> std::ops::Range<usize> {
            if !(f >= -1.0 && f <= n as f64) {
                return 0..0;
            }
            let lo = (f - 1.0).max(0.0) as usize;
            let end = ((f + 2.0) as usize).min(n);
            lo..end.max(lo)
        };
        let columns = span(fx, self.columns);
        let rows = if columns.is_empty() {
            0..0
        } else {
            span(fy, self.rows)
        };
        rows.map(move |gy| {
            let start = gy * self.columns;
            (
                self.offsets[start + columns.start] as usize,
                self.offsets[start + columns.end] as usize,
            )
        })
    }
}

/// Whether the pose barely moved from `before` to `estimate`: 90 % of its inliers reproject
/// within `tolerance_px` of where they did. With a quarter gate, and a first round of at least
/// `sure_inliers(min_inliers)` (the coarse search's "sure"), a second round at the
/// same gate would gate the same candidates and refit the same pose: skipped. (Without the
/// inlier condition South Building's SFP level-2 PQ maps lost accuracy, `l2s-pq8` recall
/// 96 → 85 %: their weak first rounds gain from the second; a 1 px tolerance instead kept
/// them but lost most of the street's gain, SIFT 39 → 49–59 ms.)
fn settled(
    before: &Pose,
    estimate: &crate::geometry::PoseEstimate,
    points: &[Vector3<f64>],
    camera: &Camera,
    tolerance_px: f64,
) -> bool {
    let mut moved: Vec<f64> = estimate
        .inliers
        .iter()
        .zip(points)
        .filter(|(&inlier, _)| inlier)
        .filter_map(|(_, p)| {
            let a = camera.project(&before.transform(p))?;
            let b = camera.project(&estimate.pose.transform(p))?;
            Some((a - b).norm())
        })
        .collect();
    if moved.is_empty() {
        return false;
    }
    let at = (moved.len() * 9 / 10).min(moved.len() - 1);
    let (_, &mut p90, _) = moved.select_nth_unstable_by(at, f64::total_cmp);
    p90 < tolerance_px
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::PoseEstimate;
    use nalgebra::UnitQuaternion;

    /// The points of `points` within `gate` of (x, y), by index, ascending.
    fn within<'a>(
        points: impl Iterator<Item = &'a (u32, [f32; 2])>,
        x: f64,
        y: f64,
        gate: f64,
    ) -> Vec<u32> {
        let mut near: Vec<u32> = points
            .filter(|(_, p)| {
                let (dx, dy) = (f64::from(p[0]) - x, f64::from(p[1]) - y);
                dx * dx + dy * dy <= gate * gate
            })
            .map(|p| p.0)
            .collect();
        near.sort_unstable();
        near
    }

    /// What the grid gives around (x, y), filtered by the gate.
    fn found(grid: &Grid, x: f64, y: f64, gate: f64) -> Vec<u32> {
        let candidates = grid
            .around(x, y)
            .flat_map(|(lo, hi)| grid.points[lo..hi].iter());
        within(candidates, x, y, gate)
    }

    #[test]
    fn the_grid_finds_every_point_within_the_gate_and_stays_small() {
        let mut rng = crate::geometry::SplitMix64::new(3);
        let (w, h, gate) = (200.0, 120.0, 10.0);
        let in_view: Vec<(u32, [f32; 2])> = (0..500)
            .map(|i| {
                let xy = [(rng.next_f64() * w) as f32, (rng.next_f64() * h) as f32];
                (i, xy)
            })
            .collect();
        let (grid, slots) = Grid::new(&in_view, gate);
        assert_eq!(grid.points.len(), in_view.len());
        for (entry, &slot) in in_view.iter().zip(&slots) {
            assert_eq!(grid.points[slot as usize], *entry);
        }
        for _ in 0..200 {
            let (x, y) = (rng.next_f64() * w, rng.next_f64() * h);
            assert_eq!(found(&grid, x, y, gate), within(in_view.iter(), x, y, gate));
        }
        // Points spread over a vast image (or a thin one): the grid stays small, its cells
        // wider than the gate, and still every point within the gate is found.
        for (w, h) in [(4e9, 4e9), (4e9, 1.0), (1.0, 4e9), (1e5, 1e5)] {
            let spread: Vec<(u32, [f32; 2])> = (0..300)
                .map(|i| {
                    let (x, y) = (rng.next_f64() * w, rng.next_f64() * h);
                    (i, [x as f32, y as f32])
                })
                .collect();
            let (grid, _) = Grid::new(&spread, gate);
            assert!(grid.offsets.len() <= 4 * (4 * 300 + 1024), "{w} x {h}");
            for &(_, xy) in spread.iter().take(50) {
                let (x, y) = (f64::from(xy[0]) + 3.0, f64::from(xy[1]) - 3.0);
                let want = within(spread.iter(), x, y, gate);
                assert!(!want.is_empty());
                assert_eq!(found(&grid, x, y, gate), want, "{w} x {h}");
            }
        }
        // A keypoint far outside the points' box finds nothing.
        assert_eq!(grid.around(-1e6, 5.0).count(), 0);
    }

    #[test]
    fn a_pose_that_moved_its_inliers_less_than_the_tolerance_is_settled() {
        let camera = Camera::parse("PINHOLE 640 480 500 500 320 240").unwrap();
        let points: Vec<Vector3<f64>> = (0..50)
            .map(|i| Vector3::new((i % 10) as f64 - 5.0, (i / 10) as f64 - 2.5, 10.0))
            .collect();
        let before = Pose::identity();
        let estimate = |pose: Pose| PoseEstimate {
            pose,
            inliers: vec![true; points.len()],
            num_inliers: points.len(),
            iterations: 1,
            mean_inlier_error_px: 0.0,
        };
        // 1 cm sideways at 10 m: 0.5 px; 20 cm: 10 px.
        let shifted = |dx: f64| Pose::new(UnitQuaternion::identity(), Vector3::new(dx, 0.0, 0.0));
        assert!(settled(
            &before,
            &estimate(shifted(0.01)),
            &points,
            &camera,
            6.0
        ));
        assert!(!settled(
            &before,
            &estimate(shifted(0.2)),
            &points,
            &camera,
            6.0
        ));
        // No inliers: nothing says it settled.
        let mut none = estimate(before);
        none.inliers = vec![false; points.len()];
        assert!(!settled(&before, &none, &points, &camera, 6.0));
    }
}
