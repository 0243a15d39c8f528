//! k-means, the one implementation behind the codebooks a map stores: VLAD's (retrieval,
//! [`crate::vlad`]) and product quantisation's ([`super::pq`]). k-means++ seeding (Arthur &
//! Vassilvitskii, 2007), then Lloyd iterations, on a seeded sample of the rows, so the same
//! rows and seed give the same centroids on every machine.

use crate::geometry::SplitMix64;
use crate::vector::Nearest;

/// How to learn centroids.
#[derive(Debug, Clone, Copy)]
pub(crate) struct KMeans {
    /// Centroids to learn.
    pub clusters: usize,
    /// Rows the iterations see at most (a seeded sample): bounds the time whatever the input.
    pub max_train: usize,
    /// Lloyd iterations at most (fewer once no assignment changes).
    pub iterations: usize,
    pub seed: u64,
}

impl KMeans {
    /// `clusters` centroids `[clusters × dims]` of the non-zero rows of `rows` (`[n × dims]`;
    /// a zero row has no direction: a descriptor that is not there). `None` when there are
    /// fewer such rows than clusters, or no dimension.
    pub(crate) fn train(&self, rows: &[f32], dims: usize) -> Option<Vec<f32>> {
        let clusters = self.clusters;
        if dims == 0 || clusters == 0 {
            return None;
        }
        let mut rng = SplitMix64::new(self.seed);
        let mut sample: Vec<usize> = rows
            .chunks_exact(dims)
            .enumerate()
            .filter(|(_, r)| r.iter().any(|&v| v != 0.0))
            .map(|(i, _)| i)
            .collect();
        if sample.len() < clusters {
            return None;
        }
        // A partial Fisher–Yates shuffle picks the sample; sorted again so memory is read in
        // order.
        let take = sample.len().min(self.max_train);
        for i in 0..take {
            let j = i + (rng.next_u64() % (sample.len() - i) as u64) as usize;
            sample.swap(i, j);
        }
        sample.truncate(take);
        sample.sort_unstable();
        let data: Vec<f32> = sample
            .iter()
            .flat_map(|&i| rows[i * dims..(i + 1) * dims].iter().copied())
            .collect();
        let n = sample.len();
        let row = |i: usize| &data[i * dims..(i + 1) * dims];

        // k-means++: each next centroid is a row drawn with probability ∝ its squared
        // distance to the nearest centroid so far.
        let mut centroids = Vec::with_capacity(clusters * dims);
        centroids.extend_from_slice(row((rng.next_u64() % n as u64) as usize));
        let columns = transpose(&data, dims, n);
        let mut nearest = vec![f64::INFINITY; n];
        for c in 1..clusters {
            let last = &centroids[(c - 1) * dims..c * dims];
            let total = seed_distances(&columns, n, last, &mut nearest);
            let mut target = rng.next_f64() * total;
            let mut pick = n - 1;
            for (i, &d) in nearest.iter().enumerate() {
                if target < d {
                    pick = i;
                    break;
                }
                target -= d;
            }
            centroids.extend_from_slice(row(pick));
        }
        // Only seeding reads the transposed copy.
        drop((columns, nearest));

        let mut assignment = vec![usize::MAX; n];
        for _ in 0..self.iterations {
            let nearest = Nearest::new(&centroids, dims);
            let mut changed = false;
            nearest.find_each(data.chunks_exact(dims), |i, c| {
                changed |= assignment[i] != c;
                assignment[i] = c;
            });
            if !changed {
                break;
            }
            let mut sums = vec![0.0f64; clusters * dims];
            let mut counts = vec![0usize; clusters];
            for (i, &a) in assignment.iter().enumerate() {
                counts[a] += 1;
                for (s, &v) in sums[a * dims..(a + 1) * dims].iter_mut().zip(row(i)) {
                    *s += f64::from(v);
                }
            }
            let old = centroids;
            // Empty clusters restart at the rows farthest from their centroids, a different
            // row each (ties: the lower index), found once per iteration.
            let empty = counts.iter().filter(|&&c| c == 0).count();
            let mut farthest = Vec::new();
            if empty > 0 {
                let mut errors: Vec<(f64, usize)> = (0..n)
                    .map(|i| {
                        let a = assignment[i];
                        (squared_distance(row(i), &old[a * dims..(a + 1) * dims]), i)
                    })
                    .collect();
                let by_error =
                    |a: &(f64, usize), b: &(f64, usize)| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1));
                if empty < n {
                    errors.select_nth_unstable_by(empty - 1, by_error);
                    errors.truncate(empty);
                }
                errors.sort_unstable_by(by_error);
                farthest = errors.into_iter().map(|(_, i)| i).collect();
            }
            let mut restarts = farthest.into_iter();
            centroids = vec![0.0f32; clusters * dims];
            for c in 0..clusters {
                let out = &mut centroids[c * dims..(c + 1) * dims];
                if counts[c] == 0 {
                    out.copy_from_slice(row(restarts.next().unwrap_or(0)));
                    continue;
                }
                for (o, s) in out.iter_mut().zip(&sums[c * dims..(c + 1) * dims]) {
                    *o = (s / counts[c] as f64) as f32;
                }
            }
        }
        Some(centroids)
    }
}

/// `[dims × n]` from `[n × dims]`: one contiguous column per dimension, for [`seed_distances`].
fn transpose(data: &[f32], dims: usize, n: usize) -> Vec<f32> {
    let mut columns = vec![0.0f32; dims * n];
    for (i, r) in data.chunks_exact(dims).enumerate() {
        for (d, &v) in r.iter().enumerate() {
            columns[d * n + i] = v;
        }
    }
    columns
}

/// Rows at a time in [`seed_distances`]: their distances stay in the L1 cache across dimensions.
const SEED_BLOCK: usize = 256;

/// k-means++'s step: `nearest[i] = min(nearest[i], ‖row_i − centroid‖²)` over the transposed
/// rows `columns` (`[dims × n]`); returns the sum of `nearest` in row order. Each distance is
/// [`squared_distance`]'s sum in its order (f64, dimension by dimension), computed for a block
/// of rows at once so it vectorizes; compiled for AVX2 too and chosen at run time.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+avx"))]
fn seed_distances(columns: &[f32], n: usize, centroid: &[f32], nearest: &mut [f64]) -> f64 {
    let mut total = 0.0f64;
    let mut block = [0.0f64; SEED_BLOCK];
    for start in (0..n).step_by(SEED_BLOCK) {
        let len = SEED_BLOCK.min(n - start);
        let acc = &mut block[..len];
        acc.fill(0.0);
        for (d, &c) in centroid.iter().enumerate() {
            let column = &columns[d * n + start..d * n + start + len];
            for (a, &x) in acc.iter_mut().zip(column) {
                let t = f64::from(x - c);
                *a += t * t;
            }
        }
        for (near, &a) in nearest[start..start + len].iter_mut().zip(&*acc) {
            *near = near.min(a);
            total += *near;
        }
    }
    total
}

fn squared_distance(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = f64::from(x - y);
            d * d
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` rows of `dims` around `groups` well-separated directions.
    pub(crate) fn clustered(n: usize, dims: usize, groups: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        let mut rows = Vec::with_capacity(n * dims);
        for i in 0..n {
            let g = i % groups;
            for k in 0..dims {
                let base = if k == g % dims {
                    1.0 + (g / dims) as f32
                } else {
                    0.0
                };
                rows.push(base + 0.05 * (rng.next_f64() as f32 - 0.5));
            }
        }
        rows
    }

    #[test]
    fn finds_separated_groups_deterministically() {
        let rows = clustered(600, 8, 4, 1);
        let kmeans = KMeans {
            clusters: 4,
            max_train: 10_000,
            iterations: 25,
            seed: 7,
        };
        let centroids = kmeans.train(&rows, 8).unwrap();
        assert_eq!(centroids, kmeans.train(&rows, 8).unwrap());
        let nearest = Nearest::new(&centroids, 8);
        let mut owner = [usize::MAX; 4];
        for (i, x) in rows.chunks_exact(8).enumerate() {
            let c = nearest.find(x);
            if owner[i % 4] == usize::MAX {
                owner[i % 4] = c;
            }
            assert_eq!(owner[i % 4], c, "row {i}");
        }
        let mut distinct = owner.to_vec();
        distinct.sort_unstable();
        distinct.dedup();
        assert_eq!(distinct.len(), 4);
        // Too few non-zero rows for the clusters; no dimension.
        let mut few = vec![0.0f32; 8 * 10];
        few[..8].copy_from_slice(&rows[..8]);
        assert!(KMeans {
            clusters: 2,
            ..kmeans
        }
        .train(&few, 8)
        .is_none());
        assert!(kmeans.train(&rows, 0).is_none());
    }

    /// The blocked k-means++ step gives bit for bit what a row-by-row [`squared_distance`]
    /// loop gives (so seeding, and codebooks, do not change with the layout or the CPU).
    #[test]
    fn seed_distances_equal_the_row_by_row_loop() {
        let (n, dims) = (SEED_BLOCK * 2 + 37, 5);
        let data = clustered(n, dims, 7, 3);
        let columns = transpose(&data, dims, n);
        let mut nearest = vec![f64::INFINITY; n];
        let mut want = nearest.clone();
        for c in [3usize, 100, n - 1] {
            let centroid = &data[c * dims..(c + 1) * dims];
            let total = seed_distances(&columns, n, centroid, &mut nearest);
            let mut want_total = 0.0f64;
            for (i, w) in want.iter_mut().enumerate() {
                *w = w.min(squared_distance(&data[i * dims..(i + 1) * dims], centroid));
                want_total += *w;
            }
            assert_eq!(total.to_bits(), want_total.to_bits());
            assert!(nearest
                .iter()
                .zip(&want)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
        }
    }

    #[test]
    fn nearest_is_the_nearest_by_squared_distance() {
        let centroids = [0.0f32, 0.0, 1.0, 0.0, 0.0, 2.0, 1.0, 1.0];
        let nearest = Nearest::new(&centroids, 2);
        for x in [
            [0.1f32, 0.1],
            [0.9, -0.2],
            [0.2, 1.8],
            [0.8, 0.9],
            [5.0, 5.0],
        ] {
            let want = (0..4)
                .min_by(|&a, &b| {
                    let d = |c: usize| squared_distance(&x, &centroids[c * 2..c * 2 + 2]);
                    d(a).total_cmp(&d(b))
                })
                .unwrap();
            assert_eq!(nearest.find(&x), want, "{x:?}");
        }
    }
}
