//! The vector kernels every stage shares: L2 normalisation and the dot product. One home, so
//! the descriptors a map is built from and those a query is matched with go through the same
//! arithmetic (the extractor, the SIFT aggregation of `convert`, the localizer).

/// Scales `v` to unit L2 norm; a vector of norm ≤ 1e-12 stays as it is (the extractor's
/// reference, `python/sfp/reference.py`, divides by `max(norm, 1e-12)`; SIFT rows and f16 map
/// rows have norm 0 or far above it).
pub(crate) fn l2_normalise(v: &mut [f32]) {
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if norm > 1e-12 {
        v.iter_mut().for_each(|x| *x /= norm);
    }
}

/// L2 normalisation of each `dim`-row of `v`.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub fn normalise_rows(v: &mut [f32], dim: usize) {
    if dim == 0 {
        return;
    }
    v.chunks_exact_mut(dim).for_each(l2_normalise);
}

/// `rows` (`[n × d_in]`) in the basis `projection` (`[dims × d_in]`, a direction a row), each
/// result row unit length; a zero row (a point without a descriptor) stays zero. A catalog's
/// image VLADs and a query's, ranked against them, go through this one projection.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub(crate) fn project_rows(rows: &[f32], d_in: usize, projection: &[f32], dims: usize) -> Vec<f32> {
    let n = rows.len() / d_in.max(1);
    let mut out = vec![0.0f32; n * dims];
    for (x, o) in rows
        .chunks_exact(d_in.max(1))
        .zip(out.chunks_exact_mut(dims.max(1)))
    {
        if x.iter().any(|&v| v != 0.0) {
            for (k, o) in o.iter_mut().enumerate() {
                *o = dot(&projection[k * d_in..(k + 1) * d_in], x);
            }
        }
    }
    normalise_rows(&mut out, dims);
    out
}

/// Dot product over 8 independent lanes, so it vectorizes.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub(crate) fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            lanes[k] += x[k] * y[k];
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// The nearest of a set of centroids, by `x·c − ‖c‖²/2` (the order of the squared distance),
/// with the centroids stored transposed (`[dims × clusters]`) so each of `x`'s values scales
/// one contiguous row into all the scores at once: the loop vectorizes over centroids, which
/// makes 256-centroid codebooks (PQ) cheap to train and encode with. k-means
/// (`kmeans`), VLAD assignments and PQ encoding all go through it.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
#[derive(Debug, Clone, PartialEq)]
pub struct Nearest {
    clusters: usize,
    transposed: Vec<f32>,
    minus_half_norms: Vec<f32>,
}

#[cfg(any(feature = "colmap-model", feature = "localize"))]
impl Nearest {
    /// From centroids `[clusters × dims]` (a partial last row is ignored).
    pub fn new(centroids: &[f32], dims: usize) -> Nearest {
        let clusters = centroids.len().checked_div(dims).unwrap_or(0);
        let mut transposed = vec![0.0f32; dims * clusters];
        let mut minus_half_norms = vec![0.0f32; clusters];
        for (c, centroid) in centroids.chunks_exact(dims.max(1)).enumerate() {
            for (d, &v) in centroid.iter().enumerate() {
                transposed[d * clusters + c] = v;
                minus_half_norms[c] -= 0.5 * v * v;
            }
        }
        Nearest {
            clusters,
            transposed,
            minus_half_norms,
        }
    }

    /// The index of the centroid nearest to `x` (`dims` values; ties: the lower index; 0
    /// without centroids). `scores` is scratch of at least `clusters` values.
    pub fn find(&self, x: &[f32], scores: &mut [f32]) -> usize {
        let scores = &mut scores[..self.clusters];
        nearest_scores(x, &self.transposed, &self.minus_half_norms, scores)
    }
}

/// [`Nearest::find`]'s loop, compiled for AVX2 too and chosen at run time.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+avx"))]
fn nearest_scores(
    x: &[f32],
    transposed: &[f32],
    minus_half_norms: &[f32],
    scores: &mut [f32],
) -> usize {
    let clusters = scores.len();
    scores.copy_from_slice(minus_half_norms);
    for (&v, column) in x.iter().zip(transposed.chunks_exact(clusters.max(1))) {
        for (s, &c) in scores.iter_mut().zip(column) {
            *s += v * c;
        }
    }
    // The maximum in one pass the compiler vectorizes, then its first position.
    let max = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    scores.iter().position(|&s| s == max).unwrap_or(0)
}

#[cfg(all(test, feature = "localize"))]
mod tests {
    use super::*;

    #[test]
    fn unit_rows_zero_rows_and_dots() {
        let mut v = vec![3.0, 4.0, 0.0, 0.0, 0.0, 0.0];
        normalise_rows(&mut v, 2);
        assert_eq!(v, [0.6, 0.8, 0.0, 0.0, 0.0, 0.0]);
        normalise_rows(&mut v, 0);
        // 19 values: two full lanes of 8 and a tail of 3.
        let a: Vec<f32> = (0..19).map(|i| i as f32).collect();
        let b: Vec<f32> = (0..19).map(|i| (19 - i) as f32).collect();
        let expected: f32 = (0..19).map(|i| (i * (19 - i)) as f32).sum();
        assert_eq!(dot(&a, &b), expected);
        assert_eq!(dot(&[], &[]), 0.0);
        // Below the threshold a row is left as it is, as the extractor's reference does.
        let mut tiny = vec![1e-20f32, 0.0];
        normalise_rows(&mut tiny, 2);
        assert_eq!(tiny, [1e-20, 0.0]);
    }
}
