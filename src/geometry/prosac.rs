//! PROSAC: progressive sampling for correspondences sorted best-first (Chum & Matas, CVPR 2005).
//!
//! Samples are drawn from a top-`n` subset that grows on a schedule derived from how often
//! uniform sampling would have drawn each subset; the stopping rule then asks, for every `n`,
//! how many samples from the top `n` would have found its inliers (maximality) provided those
//! inliers are too many to be chance (non-randomness), and stops at the smallest such count.
//! With a useful ordering (ratio-test scores) a good pose is found in a handful of samples and
//! RANSAC stops long before the uniform count `ln(1 − c) / ln(1 − w³)`; with a useless ordering
//! it degrades to ordinary sampling of the top part of the list.

use super::rng::SplitMix64;

/// Correspondences in a minimal sample: P3P needs three.
pub(super) const SAMPLE_SIZE: usize = 3;

/// `T_N` of the paper: the number of samples over which the subset grows to the full list.
const GROWTH_HORIZON: f64 = 200_000.0;

/// One-sided 5 % quantile of the normal distribution, for the non-randomness test.
const NON_RANDOM_QUANTILE: f64 = 1.645;

/// The PROSAC sampling schedule over positions `0..num_points` of a quality-sorted list.
#[derive(Debug, Clone)]
pub(crate) struct ProgressiveSampler {
    num_points: usize,
    /// Size `n` of the current top subset.
    subset: usize,
    /// `T_n`: expected number of uniform samples drawn only from the top `n`.
    t_n: f64,
    /// `T'_n`: the iteration at which the subset grows to `n + 1`.
    t_n_prime: f64,
    iteration: f64,
}

impl ProgressiveSampler {
    /// `num_points` must be at least 3.
    pub fn new(num_points: usize) -> Self {
        let mut t_n = GROWTH_HORIZON;
        for i in 0..SAMPLE_SIZE {
            t_n *= (SAMPLE_SIZE - i) as f64 / (num_points - i) as f64;
        }
        Self {
            num_points,
            subset: SAMPLE_SIZE,
            t_n,
            t_n_prime: 1.0,
            iteration: 0.0,
        }
    }

    /// Positions of the next sample: the newest member of the subset with two others from
    /// before it, or (once the subset is the whole list) three uniform positions.
    pub fn sample(&mut self, rng: &mut SplitMix64) -> [usize; SAMPLE_SIZE] {
        self.iteration += 1.0;
        if self.iteration >= self.t_n_prime && self.subset < self.num_points {
            let n = self.subset as f64 + 1.0;
            let t_next = self.t_n * n / (n - SAMPLE_SIZE as f64);
            self.t_n_prime += (t_next - self.t_n).ceil().max(1.0);
            self.t_n = t_next;
            self.subset += 1;
        }
        if self.t_n_prime < self.iteration {
            distinct(rng, self.subset, None)
        } else {
            distinct(rng, self.subset - 1, Some(self.subset - 1))
        }
    }
}

/// Three distinct positions below `n`, or two below `n` plus `fixed`. With `fixed = None` it
/// is also RANSAC's uniform sampler.
pub(super) fn distinct(
    rng: &mut SplitMix64,
    n: usize,
    fixed: Option<usize>,
) -> [usize; SAMPLE_SIZE] {
    let a = fixed.unwrap_or_else(|| rng.below(n));
    let mut b = rng.below(n);
    while b == a {
        b = rng.below(n);
    }
    let mut c = rng.below(n);
    while c == a || c == b {
        c = rng.below(n);
    }
    [a, b, c]
}

/// PROSAC's stopping rule: the fewest iterations after which, for some top-`n` subset whose
/// inlier count is not explained by chance, a better pose within it would have been found with
/// probability `confidence`. `inlier_in_order[k]` says whether the k-th best correspondence is
/// an inlier of the best pose; `consistent_by_chance` is the probability that a wrong pose
/// explains a point (SPRT's δ); `good_kept` the probability that a good pose survives SPRT.
pub(crate) fn maximality_iterations(
    inlier_in_order: impl Iterator<Item = bool>,
    confidence: f64,
    consistent_by_chance: f64,
    good_kept: f64,
    min_inliers: usize,
) -> usize {
    let beta = consistent_by_chance.clamp(1e-6, 0.5);
    let log_failure = (1.0 - confidence).ln();
    let mut best = usize::MAX;
    let mut inliers = 0usize;
    for (k, inlier) in inlier_in_order.enumerate() {
        inliers += usize::from(inlier);
        let n = k + 1;
        if n <= SAMPLE_SIZE || inliers < min_inliers.max(SAMPLE_SIZE + 1) {
            continue;
        }
        // Binomial tail by its normal approximation: the sample's own three points are inliers
        // by construction, the other n − 3 each by chance with probability β.
        let trials = (n - SAMPLE_SIZE) as f64;
        let by_chance = SAMPLE_SIZE as f64
            + beta * trials
            + NON_RANDOM_QUANTILE * (beta * (1.0 - beta) * trials).sqrt();
        if (inliers as f64) < by_chance {
            continue;
        }
        let good_sample = (inliers as f64 / n as f64).powi(SAMPLE_SIZE as i32) * good_kept;
        if good_sample >= 1.0 {
            return 0;
        }
        let needed = log_failure / (-good_sample).ln_1p();
        if needed.is_finite() && needed >= 0.0 && needed < best as f64 {
            best = needed.ceil() as usize;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_grow_from_the_top() {
        let mut rng = SplitMix64::new(3);
        let mut sampler = ProgressiveSampler::new(1000);
        let mut largest = 0;
        for t in 0..2000 {
            let sample = sampler.sample(&mut rng);
            assert!(sample[0] != sample[1] && sample[1] != sample[2] && sample[0] != sample[2]);
            let top = *sample.iter().max().unwrap();
            assert!(top < 1000);
            // After t samples the subset is about N·(t / T_N)^(1/3), far below N.
            if t < 100 {
                assert!(top < 200, "{t}: {sample:?}");
            }
            largest = largest.max(top);
        }
        assert!(largest > 100 && largest < 400, "{largest}");
    }

    #[test]
    fn a_clean_top_stops_early() {
        // Top 100 all inliers, the rest outliers: a few iterations suffice.
        let order = (0..1000).map(|k| k < 100);
        let n = maximality_iterations(order, 0.9999, 0.01, 0.9, 6);
        assert!(n < 20, "{n}");
        // Inliers spread at 10 %: no subset is better than the whole, ~10^4 iterations.
        let order = (0..1000).map(|k| k % 10 == 0);
        let n = maximality_iterations(order, 0.9999, 0.01, 1.0, 6);
        assert!((5_000..20_000).contains(&n), "{n}");
    }
}
