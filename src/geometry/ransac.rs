//! LO-RANSAC for absolute pose from 2D–3D correspondences.
//!
//! Hypotheses come from P3P on random minimal samples of bearings; each is scored by MSAC
//! (`Σ min(e², τ²)` over pixel reprojection errors `e` through the camera model, so distortion
//! is honoured and the threshold `τ` means pixels everywhere). Whenever a hypothesis beats the
//! best score, local optimisation refits it on its inliers with Levenberg–Marquardt and keeps
//! the refit while it improves the score (Chum, Matas & Kittler 2003; Lebeda et al. 2012). The
//! iteration count adapts to the best inlier ratio `w`: `N = ln(1 − confidence) / ln(1 − w³)`,
//! clamped to `[min_iterations, max_iterations]`, with `w` never below `min_inliers / n`
//! (a weaker pose is a failure anyway), so a search without a pose ends too.
//!
//! Most hypotheses are wrong, so scoring stops early: as soon as the MSAC score exceeds the
//! best one, and (by default) when Wald's SPRT decides the pose is bad after a few dozen
//! points (Matas & Chum 2008). Points are scored in a shuffled order so that early decisions
//! do not depend on how the caller sorted its matches. With SPRT, `w³` above is multiplied by
//! the probability that a good pose survives the test.
//!
//! Sampling and shuffling use a seeded SplitMix64, so a given input and seed always gives the
//! same pose.

use nalgebra::{Matrix2, Vector2, Vector3};

use super::camera::{Camera, Intrinsics};
use super::error::GeometryError;
use super::p3p;
use super::pose::Pose;
use super::prosac::{distinct, maximality_iterations, ProgressiveSampler, SAMPLE_SIZE};
use super::refine::{refine_indexed, validate_correspondences, RefineOptions};
use super::rng::SplitMix64;

/// Options of [`estimate_absolute_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct RansacOptions {
    /// Inlier threshold on the reprojection error, in pixels.
    pub max_error_px: f64,
    /// Probability of having drawn at least one all-inlier sample when stopping.
    pub confidence: f64,
    /// Iterations always run, so a lucky early sample cannot end the search before LO and the
    /// inlier-ratio estimate have settled.
    pub min_iterations: usize,
    /// Upper bound on iterations. At 90 % outliers the adaptive count needs ~9,200 at
    /// confidence 0.9999 (~10,300 with SPRT's occasional rejection of a good pose); the
    /// default leaves room for that.
    pub max_iterations: usize,
    /// Fewer inliers than this is a failure, not a pose.
    pub min_inliers: usize,
    /// Seed of the sampling PRNG; the same input and seed give the same result.
    pub seed: u64,
    /// Refit each new best hypothesis on its inliers (the LO in LO-RANSAC).
    pub local_optimization: bool,
    /// Abandon hypotheses early with Wald's sequential probability ratio test (Matas & Chum
    /// 2008): a bad pose is typically rejected after a few dozen points instead of scoring all
    /// of them, several times faster at high outlier ratios. The iteration count accounts for
    /// the small chance of rejecting a good pose.
    pub sprt: bool,
    /// The correspondences are sorted best-first (e.g. by descriptor ratio): sample them with
    /// PROSAC and stop by its maximality rule, which ends after a few dozen iterations when the
    /// top of the list is clean even if the whole list is mostly outliers.
    pub progressive: bool,
    /// LM options of the local refits; few iterations suffice because the sample is refit
    /// again whenever it improves.
    pub local_refine: RefineOptions,
    /// A final LM refinement on all inliers of the best pose; `None` returns the LO-RANSAC pose.
    pub final_refine: Option<RefineOptions>,
    /// A prior ([`estimate_absolute_pose_with_prior`]) whose local optimization keeps at
    /// least this many inliers ends the search without sampling: guided matches gathered
    /// around a pose that already explains this many of them need no search for another
    /// (the localizer's fine stage: 100+ samples a round on the street's walk otherwise).
    /// Never fewer than `min_inliers` nor a sample's points, whatever is set here. `None`: the
    /// prior is one hypothesis among the samples.
    pub accept_prior: Option<usize>,
}

impl Default for RansacOptions {
    /// 12 px is pycolmap's `estimate_absolute_pose` default threshold; six inliers is the
    /// least that over-determines a pose (six unknowns) with some margin against a chance fit.
    fn default() -> Self {
        Self {
            max_error_px: 12.0,
            confidence: 0.9999,
            min_iterations: 100,
            max_iterations: 20_000,
            min_inliers: 6,
            seed: 0x5EED_5F9A_0000_0001,
            local_optimization: true,
            sprt: true,
            progressive: false,
            local_refine: RefineOptions {
                max_iterations: 10,
                ..RefineOptions::default()
            },
            final_refine: Some(RefineOptions::default()),
            accept_prior: None,
        }
    }
}

impl RansacOptions {
    fn validate(&self) -> Result<(), GeometryError> {
        let invalid = |field, reason| Err(GeometryError::InvalidOptions { field, reason });
        if !(self.max_error_px.is_finite() && self.max_error_px > 0.0) {
            return invalid("max_error_px", "must be finite and positive");
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return invalid("confidence", "must be in (0, 1)");
        }
        if self.max_iterations == 0 {
            return invalid("max_iterations", "must be at least 1");
        }
        if self.min_iterations > self.max_iterations {
            return invalid("min_iterations", "must not exceed max_iterations");
        }
        if self.min_inliers < SAMPLE_SIZE {
            return invalid("min_inliers", "must be at least 3");
        }
        self.local_refine.validate()?;
        if let Some(final_refine) = &self.final_refine {
            final_refine.validate()?;
        }
        Ok(())
    }
}

/// The result of [`estimate_absolute_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct PoseEstimate {
    /// `cam_from_world`.
    pub pose: Pose,
    /// One entry per correspondence: reprojection error below the threshold.
    pub inliers: Vec<bool>,
    /// How many `inliers` are true.
    pub num_inliers: usize,
    /// RANSAC iterations (minimal samples drawn).
    pub iterations: usize,
    /// Mean reprojection error of the inliers, in pixels.
    pub mean_inlier_error_px: f64,
}

impl PoseEstimate {
    /// Indices of the inlier correspondences, ascending.
    pub fn inlier_indices(&self) -> impl Iterator<Item = usize> + '_ {
        self.inliers
            .iter()
            .enumerate()
            .filter_map(|(i, &inlier)| inlier.then_some(i))
    }
}

/// Fewer correspondences than this cannot tell P3P's up to four solutions apart.
pub const MIN_CORRESPONDENCES: usize = 4;

/// Estimates `cam_from_world` from pixels (COLMAP convention) and their 3D points with
/// LO-RANSAC over P3P, then (by default) refines it on all inliers.
///
/// Errors rather than a bad pose: mismatched lengths, fewer than four correspondences, NaN or
/// infinite input, all points coincident or collinear, all pixels coincident, no hypothesis, or
/// fewer than `min_inliers` inliers.
pub fn estimate_absolute_pose(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    camera: &Camera,
    options: &RansacOptions,
) -> Result<PoseEstimate, GeometryError> {
    estimate_absolute_pose_with_prior(pixels, points, camera, None, options)
}

/// [`estimate_absolute_pose`] that first scores a prior pose (e.g. from a coarser level) as if
/// a sample had produced it. A good prior sets a high inlier ratio at once, so the adaptive
/// count stops after `min_iterations` (or at once, see [`RansacOptions::accept_prior`]); a
/// bad one costs one scoring pass.
pub fn estimate_absolute_pose_with_prior(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    camera: &Camera,
    prior: Option<&Pose>,
    options: &RansacOptions,
) -> Result<PoseEstimate, GeometryError> {
    options.validate()?;
    validate_input(pixels, points)?;
    if prior.is_some_and(|p| !p.is_finite()) {
        return Err(GeometryError::NonFinite {
            what: "prior pose",
            index: 0,
        });
    }

    // Bearings are only needed for sampling; scoring projects the 3D points instead, so a
    // pixel whose undistortion fails is merely never sampled.
    let bearings: Vec<Vector3<f64>> = pixels.iter().map(|p| camera.bearing(p)).collect();
    let usable: Vec<usize> = (0..pixels.len())
        .filter(|&i| bearings[i].iter().all(|c| c.is_finite()))
        .collect();
    if usable.len() < MIN_CORRESPONDENCES {
        return Err(GeometryError::Degenerate {
            reason: "too few pixels can be undistorted",
        });
    }

    let mut rng = SplitMix64::new(options.seed);
    let scorer = Scorer::new(pixels, points, camera, options.max_error_px, &mut rng);
    let mut sprt = options
        .sprt
        .then(|| Sprt::new(pixels.len(), options.min_inliers));
    let mut best: Option<(Pose, f64)> = None;
    let mut inlier_indices = Vec::with_capacity(pixels.len());
    // A pose with fewer than `min_inliers` is a failure, so the inlier ratio of any pose worth
    // finding is at least this: the iterations that find such a pose with `confidence` bound
    // the search also while no (or only a weaker) pose is known. Without it a search that
    // fails ran to `max_iterations` (coarse matching on the 1 M-point street: 10-19 ms for
    // 60 matches that held no pose). The count assumes uniform samples: PROSAC's reach the
    // bottom of the list only late, so it keeps its own stopping rules.
    let floor_ratio = if options.progressive {
        0.0
    } else {
        options.min_inliers.max(SAMPLE_SIZE) as f64 / pixels.len() as f64
    };
    let kept = |sprt: Option<&Sprt>| sprt.map_or(1.0, Sprt::acceptance_probability);
    let mut required =
        required_iterations(floor_ratio * kept(sprt.as_ref()).cbrt(), options.confidence);
    let mut iterations = 0;

    let mut progressive = options
        .progressive
        .then(|| ProgressiveSampler::new(usable.len()));
    let mut pending_prior = prior.copied();
    // Set when the prior alone is accepted (`accept_prior`).
    let mut accepted = false;
    while !accepted
        && iterations
            < options
                .max_iterations
                .min(required.max(options.min_iterations))
    {
        let hypotheses = match pending_prior.take() {
            Some(prior) => p3p::Solutions::single(prior),
            None => {
                iterations += 1;
                let sample = match progressive.as_mut() {
                    Some(sampler) => sampler.sample(&mut rng).map(|k| usable[k]),
                    None => distinct(&mut rng, usable.len(), None).map(|k| usable[k]),
                };
                p3p::solve(&sample.map(|i| bearings[i]), &sample.map(|i| points[i]))
            }
        };
        for hypothesis in hypotheses.as_slice() {
            let bound = best.as_ref().map_or(f64::INFINITY, |(_, score)| *score);
            let score = match scorer.evaluate(hypothesis, bound, sprt.as_ref()) {
                Evaluation::Score(score) => score,
                Evaluation::Bounded => continue,
                Evaluation::Rejected { consistent, tested } => {
                    if let Some(sprt) = sprt.as_mut() {
                        sprt.record_rejection(consistent, tested);
                    }
                    continue;
                }
            };
            let mut candidate = (*hypothesis, score);
            if options.local_optimization {
                candidate = local_optimization(
                    &scorer,
                    candidate,
                    &options.local_refine,
                    &mut inlier_indices,
                );
            }
            best = Some(candidate);
            let inlier_ratio =
                scorer.inliers_into(&candidate.0, &mut inlier_indices) as f64 / pixels.len() as f64;
            if let Some(sprt) = sprt.as_mut() {
                sprt.set_inlier_ratio(inlier_ratio);
            }
            // Only the prior is scored before the first sample.
            if iterations == 0
                && options
                    .accept_prior
                    // Never below what a pose needs at all (`min_inliers`, a sample).
                    .map(|needed| needed.max(options.min_inliers).max(SAMPLE_SIZE))
                    .is_some_and(|needed| inlier_indices.len() >= needed)
            {
                accepted = true;
            }
            let good_sample_kept = kept(sprt.as_ref());
            required = required_iterations(
                inlier_ratio.max(floor_ratio) * good_sample_kept.cbrt(),
                options.confidence,
            );
            if progressive.is_some() {
                let unrolled = Unrolled::new(&candidate.0);
                let in_order = usable.iter().map(|&i| {
                    unrolled.squared_error(camera.intrinsics(), &pixels[i], &points[i])
                        < scorer.threshold2
                });
                let chance = sprt.as_ref().map_or(0.01, |sprt| sprt.delta);
                required = required.min(maximality_iterations(
                    in_order,
                    options.confidence,
                    chance,
                    good_sample_kept,
                    options.min_inliers,
                ));
            }
        }
    }

    let Some((mut pose, score)) = best else {
        return Err(GeometryError::NoModel { iterations });
    };
    if let Some(final_refine) = &options.final_refine {
        scorer.inliers_into(&pose, &mut inlier_indices);
        if inlier_indices.len() >= SAMPLE_SIZE {
            let refined = refine_indexed(
                &scorer.pixels,
                &scorer.points,
                &inlier_indices,
                camera,
                &pose,
                final_refine,
            );
            // The refinement minimizes a robust cost, not MSAC; keep it unless it clearly
            // lost support (which would mean it slid to a different minimum).
            if refined.pose.is_finite()
                && scorer
                    .score(&refined.pose, f64::INFINITY)
                    .is_some_and(|s| s <= score * 1.05 + 1e-9)
            {
                pose = refined.pose;
            }
        }
    }

    let mut inliers = vec![false; pixels.len()];
    let mut num_inliers = 0;
    let mut error_sum = 0.0;
    let unrolled = Unrolled::new(&pose);
    for (i, inlier) in inliers.iter_mut().enumerate() {
        let e2 = unrolled.squared_error(camera.intrinsics(), &pixels[i], &points[i]);
        if e2 < scorer.threshold2 {
            *inlier = true;
            num_inliers += 1;
            error_sum += e2.sqrt();
        }
    }
    if num_inliers < options.min_inliers.max(SAMPLE_SIZE) || !pose.is_finite() {
        return Err(GeometryError::TooFewInliers {
            found: num_inliers,
            required: options.min_inliers,
            iterations,
        });
    }
    Ok(PoseEstimate {
        pose,
        inliers,
        num_inliers,
        iterations,
        mean_inlier_error_px: error_sum / num_inliers as f64,
    })
}

/// Which correspondences reproject within `max_error_px` pixels under `pose` (false behind the
/// camera or for non-finite input).
pub fn reprojection_inliers(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    camera: &Camera,
    pose: &Pose,
    max_error_px: f64,
) -> Vec<bool> {
    let unrolled = Unrolled::new(pose);
    let threshold2 = max_error_px * max_error_px;
    pixels
        .iter()
        .zip(points)
        .map(|(pixel, point)| {
            unrolled.squared_error(camera.intrinsics(), pixel, point) < threshold2
        })
        .collect()
}

/// Iterations needed so that with probability `confidence` one sample was all inliers.
pub fn required_iterations(inlier_ratio: f64, confidence: f64) -> usize {
    let all_inliers = inlier_ratio.clamp(0.0, 1.0).powi(SAMPLE_SIZE as i32);
    if all_inliers >= 1.0 - f64::EPSILON {
        return 0;
    }
    if !(all_inliers > 0.0) {
        return usize::MAX;
    }
    // ln_1p keeps precision when w³ is tiny (high outlier ratios).
    let n = (1.0 - confidence).ln() / (-all_inliers).ln_1p();
    if n.is_finite() && n < usize::MAX as f64 {
        n.ceil().max(0.0) as usize
    } else {
        usize::MAX
    }
}

/// Refits on inliers while the MSAC score improves.
fn local_optimization(
    scorer: &Scorer<'_>,
    start: (Pose, f64),
    refine: &RefineOptions,
    inlier_indices: &mut Vec<usize>,
) -> (Pose, f64) {
    const MAX_ROUNDS: usize = 4;
    let mut best = start;
    for _ in 0..MAX_ROUNDS {
        if scorer.inliers_into(&best.0, inlier_indices) < SAMPLE_SIZE {
            break;
        }
        let refined = refine_indexed(
            &scorer.pixels,
            &scorer.points,
            inlier_indices,
            scorer.camera,
            &best.0,
            refine,
        );
        match scorer.score(&refined.pose, best.1) {
            Some(score) if score < best.1 && refined.pose.is_finite() => {
                let gain = best.1 - score;
                best = (refined.pose, score);
                if gain <= 1e-6 * score {
                    break;
                }
            }
            _ => break,
        }
    }
    best
}

/// Pixel-space scoring of hypotheses, on the correspondences in a random order: early
/// termination (the score bound and SPRT) judges a hypothesis by the points it sees first, so
/// these must not be, say, all the outliers of a sorted match list.
struct Scorer<'a> {
    pixels: Vec<Vector2<f64>>,
    points: Vec<Vector3<f64>>,
    camera: &'a Camera,
    threshold2: f64,
}

/// Outcome of scoring one hypothesis.
enum Evaluation {
    /// MSAC score over all points.
    Score(f64),
    /// Stopped because the score cannot beat the best.
    Bounded,
    /// Stopped by SPRT after `tested` points of which `consistent` were inliers.
    Rejected { consistent: usize, tested: usize },
}

/// A pose unrolled into scalars for the scoring loops.
struct Unrolled {
    r: [f64; 9],
    t: [f64; 3],
}

impl Unrolled {
    fn new(pose: &Pose) -> Self {
        let m = pose.rotation.to_rotation_matrix().into_inner();
        Self {
            r: [
                m[(0, 0)],
                m[(0, 1)],
                m[(0, 2)],
                m[(1, 0)],
                m[(1, 1)],
                m[(1, 2)],
                m[(2, 0)],
                m[(2, 1)],
                m[(2, 2)],
            ],
            t: [pose.translation.x, pose.translation.y, pose.translation.z],
        }
    }

    /// Squared pixel error of one correspondence, infinite behind the camera or if NaN.
    #[inline(always)]
    fn squared_error(&self, k: &Intrinsics, pixel: &Vector2<f64>, point: &Vector3<f64>) -> f64 {
        let (r, t) = (&self.r, &self.t);
        let (px, py, pz) = (point.x, point.y, point.z);
        let x = r[0] * px + r[1] * py + r[2] * pz + t[0];
        let y = r[3] * px + r[4] * py + r[5] * pz + t[1];
        let z = r[6] * px + r[7] * py + r[8] * pz + t[2];
        match k.project_scalar(x, y, z) {
            Some((u, v)) => {
                let (du, dv) = (u - pixel.x, v - pixel.y);
                let e2 = du * du + dv * dv;
                if e2.is_nan() {
                    f64::INFINITY
                } else {
                    e2
                }
            }
            None => f64::INFINITY,
        }
    }
}

impl<'a> Scorer<'a> {
    fn new(
        pixels: &[Vector2<f64>],
        points: &[Vector3<f64>],
        camera: &'a Camera,
        max_error_px: f64,
        rng: &mut SplitMix64,
    ) -> Self {
        let mut order: Vec<usize> = (0..pixels.len()).collect();
        for i in (1..order.len()).rev() {
            order.swap(i, rng.below(i + 1));
        }
        Self {
            pixels: order.iter().map(|&i| pixels[i]).collect(),
            points: order.iter().map(|&i| points[i]).collect(),
            camera,
            threshold2: max_error_px * max_error_px,
        }
    }

    /// MSAC score, or `None` as soon as it cannot beat `bound` (most hypotheses are bad, and
    /// stopping early saves most of their cost).
    fn score(&self, pose: &Pose, bound: f64) -> Option<f64> {
        match self.evaluate(pose, bound, None) {
            Evaluation::Score(score) => Some(score),
            _ => None,
        }
    }

    fn evaluate(&self, pose: &Pose, bound: f64, sprt: Option<&Sprt>) -> Evaluation {
        let unrolled = Unrolled::new(pose);
        let k = self.camera.intrinsics();
        let (consistent_step, inconsistent_step, decision) = match sprt {
            Some(sprt) => sprt.steps(),
            None => (1.0, 1.0, f64::INFINITY),
        };
        let mut score = 0.0;
        let mut likelihood_ratio = 1.0;
        let mut consistent = 0;
        for (j, (pixel, point)) in self.pixels.iter().zip(&self.points).enumerate() {
            let e2 = unrolled.squared_error(k, pixel, point);
            if e2 < self.threshold2 {
                score += e2;
                consistent += 1;
                likelihood_ratio *= consistent_step;
            } else {
                score += self.threshold2;
                likelihood_ratio *= inconsistent_step;
            }
            if score >= bound {
                return Evaluation::Bounded;
            }
            if likelihood_ratio > decision {
                return Evaluation::Rejected {
                    consistent,
                    tested: j + 1,
                };
            }
        }
        if score.is_finite() {
            Evaluation::Score(score)
        } else {
            Evaluation::Bounded
        }
    }

    /// Collects inlier indices (into the shuffled arrays); returns their number.
    fn inliers_into(&self, pose: &Pose, out: &mut Vec<usize>) -> usize {
        out.clear();
        let unrolled = Unrolled::new(pose);
        let k = self.camera.intrinsics();
        for (i, (pixel, point)) in self.pixels.iter().zip(&self.points).enumerate() {
            if unrolled.squared_error(k, pixel, point) < self.threshold2 {
                out.push(i);
            }
        }
        out.len()
    }
}

/// State of Wald's SPRT: `ε` the inlier ratio of a good pose (the best so far), `δ` the
/// fraction of points a bad pose happens to explain (estimated from rejected poses), and the
/// decision threshold `A` on the likelihood ratio.
struct Sprt {
    epsilon: f64,
    delta: f64,
    decision: f64,
    /// Points consistent with / tested against rejected poses, with a prior of δ = 1 % over
    /// 200 points so the first few rejections cannot swing δ wildly.
    delta_consistent: f64,
    delta_tested: f64,
}

impl Sprt {
    /// Time to compute P3P's poses in units of scoring one point (~0.8 µs vs ~8 ns), and the
    /// mean number of poses per sample: the cost model behind the decision threshold.
    const MODEL_COST: f64 = 100.0;
    const MODELS_PER_SAMPLE: f64 = 1.8;

    fn new(num_points: usize, min_inliers: usize) -> Self {
        // Before any pose is found, assume the lowest useful inlier ratio: a too-low ε only
        // makes the test slower to reject, a too-high one rejects good poses.
        let epsilon = (min_inliers as f64 / num_points as f64).clamp(0.02, 0.1);
        let mut sprt = Self {
            epsilon,
            delta: 0.01,
            decision: f64::INFINITY,
            delta_consistent: 2.0,
            delta_tested: 200.0,
        };
        sprt.update_decision();
        sprt
    }

    /// Likelihood-ratio factors for a consistent and an inconsistent point, and `A`.
    fn steps(&self) -> (f64, f64, f64) {
        (
            self.delta / self.epsilon,
            (1.0 - self.delta) / (1.0 - self.epsilon),
            self.decision,
        )
    }

    fn set_inlier_ratio(&mut self, inlier_ratio: f64) {
        self.epsilon = inlier_ratio.clamp(0.02, 0.95);
        self.update_decision();
    }

    fn record_rejection(&mut self, consistent: usize, tested: usize) {
        self.delta_consistent += consistent as f64;
        self.delta_tested += tested as f64;
        let delta = (self.delta_consistent / self.delta_tested).clamp(1e-4, 0.5);
        // Re-derive A only on a real change; the fixed point below is not free.
        if (delta / self.delta - 1.0).abs() > 0.1 {
            self.delta = delta;
            self.update_decision();
        }
    }

    /// `A = K + 1 + ln A` with `K = t_M · C / m_S` (Matas & Chum 2008, eq. 11), where `C` is
    /// the expected log-likelihood gain per point of a bad pose. A test that cannot tell good
    /// from bad (δ close to ε) is switched off.
    fn update_decision(&mut self) {
        let (delta, epsilon) = (self.delta, self.epsilon);
        if delta >= 0.5 * epsilon {
            self.decision = f64::INFINITY;
            return;
        }
        let c =
            (1.0 - delta) * ((1.0 - delta) / (1.0 - epsilon)).ln() + delta * (delta / epsilon).ln();
        let k = Self::MODEL_COST * c / Self::MODELS_PER_SAMPLE;
        let mut a = k + 1.0;
        for _ in 0..10 {
            a = k + 1.0 + a.ln();
        }
        // Below 10 the test rejects good poses too often for little gain.
        self.decision = if a.is_finite() {
            a.max(10.0)
        } else {
            f64::INFINITY
        };
    }

    /// Probability that a good pose survives the test, `1 − 1/A`.
    fn acceptance_probability(&self) -> f64 {
        if self.decision.is_finite() {
            1.0 - 1.0 / self.decision
        } else {
            1.0
        }
    }
}

fn validate_input(pixels: &[Vector2<f64>], points: &[Vector3<f64>]) -> Result<(), GeometryError> {
    // Errors in this order: length mismatch, too few correspondences, non-finite values (the
    // first and last from `validate_correspondences`).
    if pixels.len() == points.len() && pixels.len() < MIN_CORRESPONDENCES {
        return Err(GeometryError::TooFewCorrespondences {
            found: pixels.len(),
            required: MIN_CORRESPONDENCES,
        });
    }
    validate_correspondences(pixels, points)?;
    check_point_spread(points)?;
    check_pixel_spread(pixels)
}

/// Coincident or collinear 3D points leave the rotation about their line undetermined.
///
/// Closed form rather than an eigen-decomposition: nalgebra's iterative solver has no iteration
/// cap by default, and overflowing coordinates must fail fast, not spin.
fn check_point_spread(points: &[Vector3<f64>]) -> Result<(), GeometryError> {
    let n = points.len() as f64;
    let centroid = points.iter().sum::<Vector3<f64>>() / n;
    let (mut far, mut far_distance2) = (centroid, 0.0);
    for p in points {
        let d2 = (p - centroid).norm_squared();
        if d2 > far_distance2 {
            (far, far_distance2) = (*p, d2);
        }
    }
    if !(centroid.iter().all(|c| c.is_finite()) && far_distance2.is_finite()) {
        return Err(GeometryError::Degenerate {
            reason: "3d coordinates overflow",
        });
    }
    // Relative to the centroid's magnitude: far from the origin, f64 rounding alone spreads
    // coincident points by ~1e-16 of their coordinates.
    if !(far_distance2 > 1e-24 * (1.0 + centroid.norm_squared())) {
        return Err(GeometryError::Degenerate {
            reason: "all 3d points coincide",
        });
    }
    let axis = (far - centroid) / far_distance2.sqrt();
    let off_axis2 = points
        .iter()
        .map(|p| {
            let d = p - centroid;
            (d - axis * d.dot(&axis)).norm_squared()
        })
        .fold(0.0, f64::max);
    if !(off_axis2 > 1e-16 * far_distance2) {
        return Err(GeometryError::Degenerate {
            reason: "all 3d points are collinear",
        });
    }
    Ok(())
}

fn check_pixel_spread(pixels: &[Vector2<f64>]) -> Result<(), GeometryError> {
    let n = pixels.len() as f64;
    let centroid = pixels.iter().sum::<Vector2<f64>>() / n;
    let covariance = pixels
        .iter()
        .map(|p| {
            let d = p - centroid;
            d * d.transpose()
        })
        .sum::<Matrix2<f64>>()
        / n;
    if !(covariance.trace() > 1e-12) {
        return Err(GeometryError::Degenerate {
            reason: "all pixels coincide",
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iteration_count_follows_the_formula() {
        assert_eq!(required_iterations(1.0, 0.99), 0);
        assert_eq!(required_iterations(0.0, 0.99), usize::MAX);
        // w = 0.5: ln(0.01) / ln(0.875) = 34.5
        assert_eq!(required_iterations(0.5, 0.99), 35);
        // w = 0.1 at 0.9999: ~9,206, below the default cap of 20,000.
        let n = required_iterations(0.1, 0.9999);
        assert!((9_190..9_220).contains(&n), "{n}");
        assert!(n <= RansacOptions::default().max_iterations);
    }
}
