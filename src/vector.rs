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
