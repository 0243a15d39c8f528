//! VLAD (Jégou et al., "Aggregating local descriptors into a compact image representation",
//! 2010): an image's global descriptor made from its local descriptors. Each descriptor is
//! assigned to the nearest of a few centroids and the residuals are summed per centroid; each
//! centroid's sum is normalised on its own ("intra-normalisation", Arandjelović & Zisserman,
//! "All about VLAD", 2013, which damps bursts of similar features) and the whole vector to unit
//! length, so two images compare by a dot product.
//!
//! It gives every map retrieval, also maps without images or a network (SIFT maps from a
//! COLMAP database): `convert` learns the codebook from the map's own descriptors (one level's
//! first `dims` stored dimensions) and stores each database image's VLAD over the points it
//! sees; a query's VLAD comes from its keypoints' descriptors in the same level basis. The
//! codebook is small (16 × 32 by default; 64 × 16 from 2,000 images on; at least 64 centroids
//! for descriptors computed at another detector's keypoints: [`default_shape`])
//! because it only has to rank images of one map.

use crate::vector::{normalise_rows, Nearest};

/// Centroids of the codebook learned by default for a map of up to [`LARGE_MAP_IMAGES`]
/// images.
pub(crate) const DEFAULT_CLUSTERS: usize = 16;
/// Leading dimensions of the level basis the codebook covers by default, up to
/// [`LARGE_MAP_IMAGES`] images.
pub(crate) const DEFAULT_DIMS: usize = 32;
/// From this many images on, the default codebook ([`default_shape`]) is 64 clusters × 16
/// dims, not 16 × 32: it has more images to tell apart. On the 1 M-point street (7,934 images), 16 × 32 ranked the
/// first image that sees half of a query's view past 5th for 5 of 20 queries (up to 18th),
/// and 64 × 16 for none (at most 3rd, as 64 × 32 at twice the bytes); its level-2 short map
/// localized in 16 ms a query instead of 24, the SIFT map in 45 instead of 75. The 100 k
/// street's 800 images gained nothing from it.
pub const LARGE_MAP_IMAGES: usize = 2_000;
/// Centroids of the default codebook from [`LARGE_MAP_IMAGES`] images on.
pub(crate) const LARGE_CLUSTERS: usize = 64;
/// Leading dimensions of the default codebook from [`LARGE_MAP_IMAGES`] images on: 64 × 16
/// values an image, twice the small maps' 16 × 32.
pub(crate) const LARGE_DIMS: usize = 16;

/// Whether a map of `images` images is large: its retrieval has more images to tell apart
/// (a larger default codebook, and coarse matching starts from more retrieved images).
pub(crate) fn is_large_map(images: usize) -> bool {
    images >= LARGE_MAP_IMAGES
}

/// Where a map's descriptors were computed, which decides its default codebook.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DescribedAt {
    /// Where the feature's own detector found them, as the queries' are (SIFT, features
    /// files, SFP's levels).
    OwnKeypoints,
    /// At another detector's keypoints: a descriptor head (the built-in ALIKED) describing a
    /// COLMAP model's SIFT observations, while its queries are described where it detects.
    ModelObservations,
}

/// Centroids of the default codebook, at least, of a map [`DescribedAt::ModelObservations`]
/// (`convert --images --model aliked-n16`). 16 centroids ranked the same four South Building
/// images first for 4 of 26 queries (each then localized 5 scene units off with ~100 inliers,
/// against ~1,400 without retrieval); 64 ranked an image of the query's own view first for
/// all 26, and kept Sacre Coeur and KITTI at 100 %.
pub const MODEL_OBSERVATION_CLUSTERS: usize = 64;

/// Centroids a codebook may have at most (`convert --vlad-clusters`, and a codebook learned
/// again by `slice --short-dims`): more would not rank a map's images better, and k-means time
/// grows with them.
pub const MAX_CLUSTERS: usize = 1024;

/// The default codebook's (clusters, dims) for a map of `images` images whose descriptors
/// were computed `at`.
pub fn default_shape(images: usize, at: DescribedAt) -> (usize, usize) {
    let (clusters, dims) = if is_large_map(images) {
        (LARGE_CLUSTERS, LARGE_DIMS)
    } else {
        (DEFAULT_CLUSTERS, DEFAULT_DIMS)
    };
    match at {
        DescribedAt::OwnKeypoints => (clusters, dims),
        DescribedAt::ModelObservations => (clusters.max(MODEL_OBSERVATION_CLUSTERS), dims),
    }
}

/// Descriptors k-means sees at most (a seeded sample): enough for 16–64 centroids, and it
/// bounds training time whatever the map's size.
#[cfg(feature = "colmap")]
const MAX_TRAIN: usize = 32_768;
#[cfg(feature = "colmap")]
const ITERATIONS: usize = 25;

/// How a codebook is learned and a VLAD made, in words (recorded in the map's metadata).
#[cfg(feature = "colmap")]
pub(crate) fn rule() -> String {
    format!(
        "k-means++ then Lloyd ({ITERATIONS} iterations at most, seeded) on at most {MAX_TRAIN} descriptors (the leading dims of the level basis, renormalised); per image, the residuals of its descriptors to their nearest centroids summed per centroid, each centroid's sum L2-normalised, then the whole"
    )
}

/// A VLAD codebook: `clusters` centroids of `dims` dimensions.
#[derive(Debug, Clone, PartialEq)]
pub struct Codebook {
    clusters: usize,
    dims: usize,
    /// `[clusters × dims]`, row-major.
    centroids: Vec<f32>,
    nearest: Nearest,
}

impl Codebook {
    /// A codebook from stored centroids (`[clusters × dims]`); `None` if the shape is wrong.
    pub fn new(centroids: Vec<f32>, dims: usize) -> Option<Codebook> {
        if dims == 0 || centroids.is_empty() || centroids.len() % dims != 0 {
            return None;
        }
        Some(Codebook {
            clusters: centroids.len() / dims,
            dims,
            nearest: Nearest::new(&centroids, dims),
            centroids,
        })
    }

    /// k-means (`crate::kmeans`: k-means++ seeding, then Lloyd iterations) over the non-zero
    /// rows of `rows` (`[n × dims]`), on a seeded sample of at most 32,768 of them: the same
    /// codebook for the same rows and seed on every machine. `None` when there are fewer
    /// non-zero rows than `clusters`.
    #[cfg(feature = "colmap")]
    pub fn train(rows: &[f32], dims: usize, clusters: usize, seed: u64) -> Option<Codebook> {
        let kmeans = crate::kmeans::KMeans {
            clusters,
            max_train: MAX_TRAIN,
            iterations: ITERATIONS,
            seed,
        };
        Codebook::new(kmeans.train(rows, dims)?, dims)
    }

    /// Centroids.
    pub fn clusters(&self) -> usize {
        self.clusters
    }

    /// Dimensions of each centroid.
    pub fn dims(&self) -> usize {
        self.dims
    }

    /// `[clusters × dims]`, row-major.
    pub fn centroids(&self) -> &[f32] {
        &self.centroids
    }

    /// The centroids, for storing.
    pub fn into_centroids(self) -> Vec<f32> {
        self.centroids
    }

    /// The centroid nearest to `x` (`dims` values; ties: the lower index).
    pub fn nearest(&self, x: &[f32]) -> usize {
        self.nearest.find(x)
    }

    /// Values of one VLAD: `clusters × dims`.
    pub fn width(&self) -> usize {
        self.clusters * self.dims
    }

    /// Adds `x`'s residual to its centroid's block of `sum` (`width()` values).
    fn accumulate(&self, x: &[f32], sum: &mut [f32], cluster: usize) {
        let d = self.dims;
        let centroid = &self.centroids[cluster * d..(cluster + 1) * d];
        for ((s, &v), &c) in sum[cluster * d..(cluster + 1) * d]
            .iter_mut()
            .zip(x)
            .zip(centroid)
        {
            *s += v - c;
        }
    }

    /// The VLAD of `rows` (`[n × dims]`, each already in the codebook's space and unit; zero
    /// rows are skipped): `width()` values, unit length (all zero without rows).
    pub fn vlad(&self, rows: &[f32]) -> Vec<f32> {
        let mut sum = vec![0.0f32; self.width()];
        // Zero rows (descriptors of no direction) are skipped, as the map's are, and so are
        // rows with a non-finite value (one would make the whole VLAD NaN).
        for x in rows
            .chunks_exact(self.dims)
            .filter(|x| x.iter().any(|&v| v != 0.0) && x.iter().all(|v| v.is_finite()))
        {
            self.accumulate(x, &mut sum, self.nearest.find(x));
        }
        self.finish(&mut sum);
        sum
    }

    /// Intra-normalisation, then unit length.
    fn finish(&self, sum: &mut [f32]) {
        normalise_rows(sum, self.dims);
        normalise_rows(sum, sum.len().max(1));
    }

    /// Each image's VLAD over the points it sees: image `i` sees
    /// `points[offsets[i]..offsets[i + 1]]`, rows of `rows` (`[n × dims]`; zero rows are points
    /// without a descriptor and are skipped, as are indices past `n`). `[images × width()]`.
    pub fn image_vlads(&self, rows: &[f32], offsets: &[u64], points: &[u32]) -> Vec<f32> {
        let d = self.dims;
        let n = rows.len() / d;
        // Each point's centroid, once: most points are seen by several images.
        let assignment: Vec<u32> = rows
            .chunks_exact(d)
            .map(|x| {
                if x.iter().all(|&v| v == 0.0) {
                    u32::MAX
                } else {
                    self.nearest.find(x) as u32
                }
            })
            .collect();
        let images = offsets.len().saturating_sub(1);
        let mut out = vec![0.0f32; images * self.width()];
        for (i, sum) in out.chunks_exact_mut(self.width().max(1)).enumerate() {
            let range = offsets[i] as usize..offsets[i + 1] as usize;
            for &p in points.get(range).unwrap_or(&[]) {
                let p = p as usize;
                match assignment.get(p) {
                    Some(&c) if c != u32::MAX && p < n => {
                        self.accumulate(&rows[p * d..(p + 1) * d], sum, c as usize)
                    }
                    _ => {}
                }
            }
            self.finish(sum);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::SplitMix64;
    use crate::vector::dot;

    #[test]
    fn the_default_codebook_grows_with_the_images() {
        let own = |n| default_shape(n, DescribedAt::OwnKeypoints);
        assert_eq!(own(0), (16, 32));
        assert_eq!(own(1_999), (16, 32));
        assert_eq!(own(2_000), (64, 16));
        assert_eq!(own(1_000_000), (64, 16));
        let observed = |n| default_shape(n, DescribedAt::ModelObservations);
        assert_eq!(observed(0), (64, 32));
        assert_eq!(observed(1_999), (64, 32));
        assert_eq!(observed(2_000), (64, 16));
    }

    /// `n` unit rows of `dims` around `groups` well-separated directions.
    fn clustered(n: usize, dims: usize, groups: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        let mut rows = Vec::with_capacity(n * dims);
        for i in 0..n {
            let g = i % groups;
            for k in 0..dims {
                let base = if k == g { 1.0 } else { 0.0 };
                rows.push(base + 0.05 * (rng.next_f64() as f32 - 0.5));
            }
        }
        normalise_rows(&mut rows, dims);
        rows
    }

    #[cfg(feature = "colmap")]
    #[test]
    fn a_vlad_is_unit_and_ranks_images_that_share_points_first() {
        let rows = clustered(400, 8, 4, 2);
        let codebook = Codebook::train(&rows, 8, 4, 3).unwrap();
        // Image 0 sees points 0..100, image 1 points 50..150 (half shared), image 2 200..300,
        // image 3 nothing; the query is points 0..100 again.
        let offsets = [0u64, 100, 200, 300, 300];
        let points: Vec<u32> = (0..100).chain(50..150).chain(200..300).collect();
        let images = codebook.image_vlads(&rows, &offsets, &points);
        assert_eq!(images.len(), 4 * codebook.width());
        let query = codebook.vlad(&rows[..100 * 8]);
        // Rows with a non-finite value, and zero rows, are skipped.
        let mut noisy = rows[..100 * 8].to_vec();
        noisy.extend([f32::NAN; 8]);
        noisy.extend([0.0; 8]);
        assert_eq!(codebook.vlad(&noisy), query);
        let norm = dot(&query, &query).sqrt();
        assert!((norm - 1.0).abs() < 1e-5, "{norm}");
        let scores: Vec<f32> = images
            .chunks_exact(codebook.width())
            .map(|v| dot(&query, v))
            .collect();
        assert!((scores[0] - 1.0).abs() < 1e-5, "{scores:?}");
        assert!(scores[1] > scores[2], "{scores:?}");
        assert_eq!(scores[3], 0.0, "an image without points has a zero VLAD");
        // Indices past the rows are skipped, not a panic.
        let bad = codebook.image_vlads(&rows, &[0, 2], &[0, 9_999]);
        assert_eq!(bad.len(), codebook.width());
    }

    #[test]
    fn stored_centroids_of_the_wrong_shape_are_refused() {
        assert!(Codebook::new(vec![0.0; 6], 4).is_none());
        assert!(Codebook::new(Vec::new(), 4).is_none());
        assert!(Codebook::new(vec![0.0; 8], 0).is_none());
        assert_eq!(Codebook::new(vec![0.0; 8], 4).unwrap().clusters, 2);
    }
}
