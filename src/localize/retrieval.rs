//! Retrieval: which database images a query is compared with, and which map points they
//! see. The fallback when retrieval cannot help (no global descriptors in the map or the
//! query, or descriptors of another length) is every image, so every point is a candidate.

use crate::vector::normalise_rows;
use bitvec::vec::BitVec;

/// Why a query's candidates are every point of the map instead of those of its retrieved
/// images: what `localize` reports per query.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum RetrievalFallback {
    /// The map stores no global descriptors (SIFT maps today).
    NoMapDescriptors,
    /// The query has no global descriptor (SIFT features, a features.h5 without one).
    NoQueryDescriptor,
    /// The query's global descriptor has another length than the map's (another model).
    DimensionMismatch { map: usize, query: usize },
    /// The map has no images, or no visibility to turn images into points.
    NoVisibility,
    /// The retrieved images see every point (`top_k` covers the map).
    EveryPointSeen,
}

impl std::fmt::Display for RetrievalFallback {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RetrievalFallback::NoMapDescriptors => f.write_str("the map has no global descriptors"),
            RetrievalFallback::NoQueryDescriptor => {
                f.write_str("the query has no global descriptor")
            }
            RetrievalFallback::DimensionMismatch { map, query } => write!(
                f,
                "the query's global descriptor has {query} dimensions, the map's {map}"
            ),
            RetrievalFallback::NoVisibility => f.write_str("the map has no images or visibility"),
            RetrievalFallback::EveryPointSeen => {
                f.write_str("the retrieved images see every point")
            }
        }
    }
}

/// The `top_k` database images whose global descriptors (`[n_images × dim]`, L2-normalised,
/// row-major) score highest against the query's, best first (ties: lower index first); or
/// all images in order, with the reason, when the map or the query has no global descriptor
/// of that length.
pub(crate) fn retrieve(
    database: Option<(&[f32], usize)>,
    query: Option<&[f32]>,
    n_images: usize,
    top_k: usize,
) -> (Vec<usize>, Option<RetrievalFallback>) {
    let fallback = match (database, query) {
        _ if n_images == 0 => RetrievalFallback::NoVisibility,
        (None, _) => RetrievalFallback::NoMapDescriptors,
        (_, None) => RetrievalFallback::NoQueryDescriptor,
        (Some((_, map)), Some(q)) if q.len() != map => RetrievalFallback::DimensionMismatch {
            map,
            query: q.len(),
        },
        (Some((g, dim)), Some(q)) => {
            // Scores are cosines, as the map's rows are unit. The ranking would not change
            // without it, but the tie-breaks between scores an ulp apart could.
            let mut q = q.to_vec();
            normalise_rows(&mut q, dim);
            let mut scores = vec![0.0; n_images];
            super::kernels::sgemm_abt(&q, g, &mut scores, 1, n_images, dim);
            return (top_k_indices(&scores, top_k.max(1)), None);
        }
    };
    ((0..n_images).collect(), Some(fallback))
}

/// Indices of the `k` highest scores, best first, ties by index: a partial selection
/// (O(n) to find them, O(k log k) to order them), never a sort of all `n`.
pub(crate) fn top_k_indices(scores: &[f32], k: usize) -> Vec<usize> {
    let better = |&a: &usize, &b: &usize| scores[b].total_cmp(&scores[a]).then(a.cmp(&b));
    let mut order: Vec<usize> = (0..scores.len()).collect();
    if k < order.len() {
        order.select_nth_unstable_by(k, better);
        order.truncate(k);
    }
    order.sort_unstable_by(better);
    order
}

/// One bit per map point: whether one of `images` sees it (`points_of(i)` lists image `i`'s
/// points; indices past `n_points` are ignored). `None` when every point is seen (no
/// narrowing), or when there are no images.
pub(crate) fn points_seen<'a>(
    images: &[usize],
    n_points: usize,
    points_of: impl Fn(usize) -> &'a [u32],
) -> Option<BitVec> {
    if images.is_empty() {
        return None;
    }
    let mut seen = BitVec::repeat(false, n_points);
    for &i in images {
        for &p in points_of(i) {
            if (p as usize) < n_points {
                seen.set(p as usize, true);
            }
        }
    }
    (!seen.all()).then_some(seen)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn top_k_is_the_full_sort_cut_at_k() {
        // Ties, a NaN-free spread, k below, at and above n.
        let scores: [f32; 9] = [0.5, 0.9, 0.1, 0.9, -0.3, 0.5, 0.7, 0.0, 0.9];
        let mut full: Vec<usize> = (0..scores.len()).collect();
        full.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
        assert_eq!(full[..4], [1, 3, 8, 6]);
        for k in 0..=scores.len() + 2 {
            assert_eq!(
                top_k_indices(&scores, k),
                full[..k.min(scores.len())],
                "k = {k}"
            );
        }
        assert!(top_k_indices(&[], 3).is_empty());
    }

    #[test]
    fn retrieval_ranks_images_by_their_global_descriptor() {
        // Four images in 2-D: the query (unnormalised) points along image 2's descriptor.
        let s = std::f32::consts::FRAC_1_SQRT_2;
        let g = [1.0, 0.0, 0.0, 1.0, s, s, -1.0, 0.0];
        assert_eq!(
            retrieve(Some((&g, 2)), Some(&[3.0, 2.9]), 4, 2),
            (vec![2, 0], None)
        );
        assert_eq!(retrieve(Some((&g, 2)), Some(&[0.0, -5.0]), 4, 1).0, [0]);
        // top_k 0 is taken as 1; top_k past the images is every image, ranked.
        assert_eq!(retrieve(Some((&g, 2)), Some(&[3.0, 2.9]), 4, 0).0, [2]);
        assert_eq!(
            retrieve(Some((&g, 2)), Some(&[3.0, 2.9]), 4, 9).0,
            [2, 0, 1, 3]
        );
    }

    #[test]
    fn without_usable_global_descriptors_every_image_is_retrieved_and_why_is_named() {
        use RetrievalFallback::*;
        let g = [1.0, 0.0, 0.0, 1.0];
        let all = vec![0, 1];
        type Case<'a> = (
            Option<(&'a [f32], usize)>,
            Option<&'a [f32]>,
            RetrievalFallback,
        );
        let cases: [Case<'_>; 3] = [
            (None, Some(&[1.0, 0.0]), NoMapDescriptors),
            (Some((&g, 2)), None, NoQueryDescriptor),
            // A query descriptor of another length (another model) cannot be compared.
            (
                Some((&g, 2)),
                Some(&[1.0, 0.0, 0.0]),
                DimensionMismatch { map: 2, query: 3 },
            ),
        ];
        for (database, query, why) in cases {
            assert_eq!(retrieve(database, query, 2, 1), (all.clone(), Some(why)));
        }
        assert_eq!(
            retrieve(Some((&[], 2)), Some(&[1.0, 0.0]), 0, 1),
            (vec![], Some(NoVisibility))
        );
        assert_eq!(
            DimensionMismatch { map: 2, query: 3 }.to_string(),
            "the query's global descriptor has 3 dimensions, the map's 2"
        );
    }

    #[test]
    fn candidates_are_the_points_the_retrieved_images_see() {
        let visibility: [&[u32]; 3] = [&[0, 2], &[2, 3, 99], &[1, 4]];
        let seen = points_seen(&[0, 1], 5, |i| visibility[i]).unwrap();
        assert_eq!(seen.iter_ones().collect::<Vec<_>>(), [0, 2, 3]);
        // Every point seen: no narrowing; no image: no narrowing either.
        assert!(points_seen(&[0, 1, 2], 5, |i| visibility[i]).is_none());
        assert!(points_seen(&[], 5, |i| visibility[i]).is_none());
    }
}
