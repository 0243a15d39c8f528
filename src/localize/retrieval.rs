//! Retrieval: which database images a query is compared with, and which map points they
//! see. A map can rank its images two ways: the extractor's global descriptor
//! (`image_global`, SFP maps) or VLAD of its own local descriptors (`image_vlad`, every map
//! converted by 1.1, see [`crate::vlad`]). The fallback when neither can help (the map has
//! neither, the query lacks what they need, lengths differ) is every image, so every point is
//! a candidate.

use super::features::QueryFeatures;
use crate::format::{Error as FormatError, ImageIndex, Map, Retrieval};
pub(crate) use crate::vector::top_k_indices;
use crate::vector::{dot, normalise_rows, ranked_last_if_not_finite, NearestF16};
use crate::vlad::Codebook;
use bitvec::vec::BitVec;
use half::f16;
use std::borrow::Cow;

/// Which stored global descriptor ranks the map's images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RetrievalMethod {
    /// The map's stated preference (metadata `retrieval`) when the query can use it, else
    /// the other kind the map stores.
    #[default]
    Auto,
    /// Only VLAD.
    Vlad,
    /// Only the extractor's global descriptor.
    Global,
    /// No retrieval: every point is a candidate.
    Off,
}

/// `auto`, `vlad`, `global` or `off`: the names the Python package's `retrieval` takes (and
/// the CLI's `--retrieval` lists, through its own clap value enum for the help text).
impl std::str::FromStr for RetrievalMethod {
    type Err = super::OptionError;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Ok(match name {
            "auto" => RetrievalMethod::Auto,
            "vlad" => RetrievalMethod::Vlad,
            "global" => RetrievalMethod::Global,
            "off" => RetrievalMethod::Off,
            other => {
                return Err(super::OptionError {
                    option: "retrieval",
                    value: format!("{other:?}"),
                    expected: "one of \"auto\", \"vlad\", \"global\", \"off\"",
                })
            }
        })
    }
}

/// Why a query's candidates are every point of the map instead of those of its retrieved
/// images: what `localize` reports per query.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum RetrievalFallback {
    /// The map stores neither global descriptors nor VLAD (SIFT maps written by 1.0), or not
    /// the kind asked for.
    NoMapDescriptors,
    /// The query has no global descriptor (SIFT features, a features.h5 without one).
    NoQueryDescriptor,
    /// The query has no features for the level the map's VLAD aggregates.
    NoQueryFeatures {
        /// The level.
        level: u16,
    },
    /// The query's descriptors have another length than the map's (another model).
    DimensionMismatch {
        /// The map's global descriptor dimension.
        map: usize,
        /// The query's.
        query: usize,
    },
    /// The map has no images, or no visibility to turn images into points.
    NoVisibility,
    /// The retrieved images see every point (`top_k` covers the map).
    EveryPointSeen,
    /// Retrieval was switched off (`--retrieval off`).
    Off,
}

impl std::fmt::Display for RetrievalFallback {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RetrievalFallback::NoMapDescriptors => {
                f.write_str("the map has no retrieval data (global descriptors or VLAD) to use")
            }
            RetrievalFallback::NoQueryDescriptor => {
                f.write_str("the query has no global descriptor")
            }
            RetrievalFallback::NoQueryFeatures { level } => write!(
                f,
                "the query has no features for level {level}, which the map's VLAD aggregates"
            ),
            RetrievalFallback::DimensionMismatch { map, query } => write!(
                f,
                "the query's descriptors for retrieval have {query} dimensions, the map's {map}"
            ),
            RetrievalFallback::NoVisibility => f.write_str("the map has no images or visibility"),
            RetrievalFallback::EveryPointSeen => {
                f.write_str("the retrieved images see every point")
            }
            RetrievalFallback::Off => f.write_str("retrieval is off"),
        }
    }
}

/// A map's VLAD, ready to score queries.
struct VladIndex<'m> {
    level: u16,
    codebook: Codebook,
    /// `[dims × d_in]`: the level basis' leading rows (`None`: the extractor's own basis,
    /// whose leading dimensions are taken as they are).
    projection: Option<Vec<f32>>,
    d_in: usize,
    /// `[images × width]`, the map's f16 rows, read in place (decoded inside the scoring:
    /// at 64 clusters an f32 copy was 64 MB for 8,000 images, and reading it per query took
    /// twice as long).
    images: Cow<'m, [f16]>,
}

/// A map's image index (format 1.3), ready to probe.
struct ProbedIndex<'m> {
    index: ImageIndex<'m>,
    /// Its centroids, in f16: lists rank by distance to them.
    centroids: NearestF16,
    /// Lists a query scores at least (the map's `probe`, or the caller's).
    probe: usize,
}

use crate::format::index::{BEAM_PER_K, MIN_SCORED_PER_K};

impl ProbedIndex<'_> {
    /// The `top_k` images of the lists nearest to `query` (`width` values) by exact score,
    /// best first, ties by image index (as [`rank`]): with every list probed, exactly
    /// [`rank`]'s answer. (1.4) With the map's image neighbours, the search widens from the
    /// best of those lists along them ([`Neighbours::widen`], a beam of
    /// [`BEAM_PER_K`] images per image asked for).
    ///
    /// [`Neighbours::widen`]: crate::format::Neighbours::widen
    fn rank(&self, database: Rows<'_>, query: &[f32], top_k: usize) -> Vec<usize> {
        let index = &self.index;
        let min_scored = top_k.max(1).saturating_mul(MIN_SCORED_PER_K);
        // Asked for half the map or more: scoring every image costs less than probing.
        if min_scored >= index.images.len() / 2 {
            return rank(database, index.width, query, top_k);
        }
        let mut q = query.to_vec();
        normalise_rows(&mut q, index.width);
        // Lists nearest first, as `NearestF16::order` has them; only the first `probe` are
        // sorted unless the query needs more (3,348 lists on the 10 M-point street).
        let mut scores = self.centroids.scores(&q);
        ranked_last_if_not_finite(&mut scores);
        let lists = scores.len();
        let mut order = top_k_indices(&scores, self.probe.max(1).min(lists));
        let mut candidates: Vec<u32> = Vec::new();
        let mut probed = 0;
        while probed < lists && (probed < self.probe || candidates.len() < min_scored) {
            if probed == order.len() {
                order = top_k_indices(&scores, lists);
            }
            candidates.extend_from_slice(index.list(order[probed]));
            probed += 1;
        }
        let scores = database.dots_picked(index.width, &q, &candidates);
        let mut scored: Vec<(u32, f32)> = candidates.into_iter().zip(scores).collect();
        if let Some(neighbours) = &index.neighbours {
            let n_images = index.images.len();
            let beam = top_k.max(1).saturating_mul(BEAM_PER_K);
            neighbours.widen(&mut scored, n_images, beam, |picks| {
                database.dots_picked(index.width, &q, picks)
            });
        }
        // Ascending, so that ties break by image index as the exhaustive ranking's do.
        scored.sort_unstable_by_key(|&(i, _)| i);
        let mut scores: Vec<f32> = scored.iter().map(|&(_, s)| s).collect();
        ranked_last_if_not_finite(&mut scores);
        top_k_indices(&scores, top_k.max(1))
            .into_iter()
            .map(|i| scored[i].0 as usize)
            .collect()
    }
}

/// What a localizer retrieves with: the map's global descriptors (decoded once) and VLAD (read
/// in place), and the image index over one of them.
pub(crate) struct RetrievalIndex<'m> {
    global: Option<(Vec<f32>, usize)>,
    vlad: Option<VladIndex<'m>>,
    indexed: Option<ProbedIndex<'m>>,
    /// The map's preference, else VLAD first (the one every converted map has).
    order: [Retrieval; 2],
    method: RetrievalMethod,
}

impl<'m> RetrievalIndex<'m> {
    /// `probe`: lists of the map's image index a query scores (`None`: the map's `probe`;
    /// `Some(0)`: the index is not used, every image is scored).
    pub(crate) fn new(
        map: &'m Map<'m>,
        method: RetrievalMethod,
        probe: Option<usize>,
    ) -> Result<Self, FormatError> {
        // Only what the method can use is decoded (and checked): `--retrieval off` opens a
        // map whose retrieval sections are damaged, as a 1.0 reader would.
        let (use_global, use_vlad) = match method {
            RetrievalMethod::Auto => (true, true),
            RetrievalMethod::Global => (true, false),
            RetrievalMethod::Vlad => (false, true),
            RetrievalMethod::Off => (false, false),
        };
        let global = if use_global {
            map.image_global()?
        } else {
            None
        };
        let global = global.filter(|(_, dim)| *dim > 0).map(|(g, dim)| {
            let mut v = vec![0.0f32; g.len()];
            crate::vector::widen_f16(&g, &mut v);
            normalise_rows(&mut v, dim);
            (v, dim)
        });
        let vlad = match if use_vlad { map.vlad()? } else { None } {
            None => None,
            Some(v) => {
                let level = map.level(v.level)?;
                let codebook = Codebook::new(v.centroids.to_vec(), v.dims)
                    .ok_or_else(|| FormatError::inconsistent("VLAD codebook of no centroids"))?;
                // Open checked dims ≤ dim_short ≤ dim_full = the projection's rows.
                let (projection, d_in) = match level.projection_input_dim() {
                    Some(d_in) => {
                        let leading = level
                            .projection()?
                            .and_then(|p| p.get(..v.dims * d_in).map(<[f32]>::to_vec))
                            .ok_or_else(|| {
                                FormatError::inconsistent("VLAD dims past the level projection")
                            })?;
                        (Some(leading), d_in)
                    }
                    None => (None, level.info().dim_full as usize),
                };
                Some(VladIndex {
                    level: v.level,
                    codebook,
                    projection,
                    d_in,
                    images: v.images,
                })
            }
        };
        let order = match map.metadata().retrieval() {
            Some(Retrieval::Global) => [Retrieval::Global, Retrieval::Vlad],
            _ => [Retrieval::Vlad, Retrieval::Global],
        };
        // The index is read (and checked) only where it can be used.
        let indexed = |of| match of {
            Retrieval::Global => use_global,
            Retrieval::Vlad => use_vlad,
        };
        let indexed = match map.metadata().image_index.as_ref().and_then(|i| i.of()) {
            Some(of) if indexed(of) && probe != Some(0) => {
                map.image_index()?.map(|index| ProbedIndex {
                    probe: probe.unwrap_or(index.probe),
                    centroids: NearestF16::new(&index.centroids, index.width),
                    index,
                })
            }
            _ => None,
        };
        Ok(RetrievalIndex {
            global,
            vlad,
            indexed,
            order,
            method,
        })
    }

    /// The `top_k` images for `query`, best first, and the method that ranked them; or every
    /// image and why not. Through the map's image index where it has one.
    pub(crate) fn retrieve(
        &self,
        query: &QueryFeatures,
        n_images: usize,
        top_k: usize,
    ) -> (Vec<usize>, Result<Retrieval, RetrievalFallback>) {
        self.retrieve_with(query, n_images, top_k, true)
    }

    /// [`RetrievalIndex::retrieve`] with every image scored, the image index left aside: the
    /// wider nets of a query whose retrieved images gave no pose. How many of a query's best
    /// images the index finds is the writer's word; a query it missed ranks every image (38 ms
    /// at 80,000 images) before it matches every point (14 s on the 10 M-point street).
    pub(crate) fn retrieve_every(
        &self,
        query: &QueryFeatures,
        n_images: usize,
        top_k: usize,
    ) -> (Vec<usize>, Result<Retrieval, RetrievalFallback>) {
        self.retrieve_with(query, n_images, top_k, false)
    }

    fn retrieve_with(
        &self,
        query: &QueryFeatures,
        n_images: usize,
        top_k: usize,
        use_index: bool,
    ) -> (Vec<usize>, Result<Retrieval, RetrievalFallback>) {
        let all = || (0..n_images).collect::<Vec<_>>();
        if n_images == 0 {
            return (all(), Err(RetrievalFallback::NoVisibility));
        }
        let methods: &[Retrieval] = match self.method {
            RetrievalMethod::Off => return (all(), Err(RetrievalFallback::Off)),
            RetrievalMethod::Auto => &self.order,
            RetrievalMethod::Vlad => &[Retrieval::Vlad],
            RetrievalMethod::Global => &[Retrieval::Global],
        };
        // The first usable method ranks; otherwise the first method's reason is reported.
        let mut first_reason = None;
        for &method in methods {
            let vectors = match method {
                Retrieval::Global => self.global_vectors(query),
                Retrieval::Vlad => self.vlad_vectors(query),
            };
            match vectors {
                Ok((database, q, dim)) if database.len() == n_images * dim => {
                    let ranked = match &self.indexed {
                        Some(index)
                            if use_index
                                && index.index.of == method
                                && index.index.width == dim =>
                        {
                            index.rank(database, &q, top_k)
                        }
                        _ => rank(database, dim, &q, top_k),
                    };
                    return (ranked, Ok(method));
                }
                Ok(_) => {
                    first_reason.get_or_insert(RetrievalFallback::NoMapDescriptors);
                }
                Err(why) => {
                    first_reason.get_or_insert(why);
                }
            }
        }
        (
            all(),
            Err(first_reason.unwrap_or(RetrievalFallback::NoMapDescriptors)),
        )
    }

    fn global_vectors(
        &self,
        query: &QueryFeatures,
    ) -> Result<(Rows<'_>, Vec<f32>, usize), RetrievalFallback> {
        let (g, dim) = self
            .global
            .as_ref()
            .ok_or(RetrievalFallback::NoMapDescriptors)?;
        let q = query
            .global
            .as_ref()
            .ok_or(RetrievalFallback::NoQueryDescriptor)?;
        if q.len() != *dim {
            return Err(RetrievalFallback::DimensionMismatch {
                map: *dim,
                query: q.len(),
            });
        }
        Ok((Rows::F32(g), q.clone(), *dim))
    }

    fn vlad_vectors(
        &self,
        query: &QueryFeatures,
    ) -> Result<(Rows<'_>, Vec<f32>, usize), RetrievalFallback> {
        let v = self
            .vlad
            .as_ref()
            .ok_or(RetrievalFallback::NoMapDescriptors)?;
        let set = query
            .sets
            .iter()
            .find(|s| s.level == Some(v.level))
            .or_else(|| query.sets.iter().find(|s| s.level.is_none()))
            .ok_or(RetrievalFallback::NoQueryFeatures { level: v.level })?;
        let n = set.keypoints.len();
        if set.dim != v.d_in || n.checked_mul(set.dim) != Some(set.descriptors.len()) {
            return Err(RetrievalFallback::DimensionMismatch {
                map: v.d_in,
                query: set.dim,
            });
        }
        let dims = v.codebook.dims();
        let mut rows = vec![0.0f32; n * dims];
        match &v.projection {
            Some(p) => super::kernels::sgemm_abt(&set.descriptors, p, &mut rows, n, dims, v.d_in),
            None => {
                for (src, dst) in set
                    .descriptors
                    .chunks_exact(set.dim)
                    .zip(rows.chunks_exact_mut(dims))
                {
                    dst.copy_from_slice(&src[..dims]);
                }
            }
        }
        normalise_rows(&mut rows, dims);
        Ok((
            Rows::F16(&v.images),
            v.codebook.vlad(&rows),
            v.codebook.width(),
        ))
    }
}

/// Database descriptors, `[n_images × dim]` row-major: decoded, or the map's f16.
#[derive(Clone, Copy)]
pub(crate) enum Rows<'a> {
    F32(&'a [f32]),
    F16(&'a [f16]),
}

impl Rows<'_> {
    fn len(&self) -> usize {
        match self {
            Rows::F32(v) => v.len(),
            Rows::F16(v) => v.len(),
        }
    }

    /// [`Rows::dots`] of the rows `picks` names (each below the row count), in that order.
    fn dots_picked(&self, dim: usize, q: &[f32], picks: &[u32]) -> Vec<f32> {
        assert_eq!(q.len(), dim, "Rows::dots_picked: the query is not a row");
        match self {
            Rows::F32(v) => picks
                .iter()
                .map(|&i| dot(&v[i as usize * dim..(i as usize + 1) * dim], q))
                .collect(),
            Rows::F16(v) => crate::vector::dots_f16_picked(v, dim, q, picks),
        }
    }

    /// Each row's dot product with `q` (`dim` values; both kinds refuse any other length).
    pub(crate) fn dots(&self, dim: usize, q: &[f32]) -> Vec<f32> {
        assert_eq!(q.len(), dim, "Rows::dots: the query is not a row");
        if dim == 0 {
            return Vec::new();
        }
        match self {
            Rows::F32(v) => v.chunks_exact(dim).map(|row| dot(row, q)).collect(),
            Rows::F16(v) => crate::vector::dots_f16(v, dim, q),
        }
    }
}

/// The `top_k` database images whose descriptors (`[n_images × dim]`, L2-normalised,
/// row-major) score highest against `query`'s (`dim` values), best first (ties: lower index
/// first); `top_k` 0 is taken as 1.
pub(crate) fn rank(database: Rows<'_>, dim: usize, query: &[f32], top_k: usize) -> Vec<usize> {
    // Scores are cosines, as the map's rows are unit. The ranking would not change without
    // it, but the tie-breaks between scores an ulp apart could.
    let mut q = query.to_vec();
    normalise_rows(&mut q, dim);
    // One query: a dot per image row. (A GEMM of one row packs the whole database first,
    // 16 MB at 8,000 images: most of retrieval's time on the 1 M-point street.)
    let mut scores = database.dots(dim, &q);
    ranked_last_if_not_finite(&mut scores);
    top_k_indices(&scores, top_k.max(1))
}

/// The map points `images` see, ascending and each once (`points_of(i)` lists image `i`'s
/// points; indices past `n_points` are ignored). `None` when that is every point (no
/// narrowing), or when there are no images. A bit per point marks the points already listed:
/// cost O(n_points / 64) to clear plus O(points seen). Fails where `points_of` does (a
/// damaged chunk of the map's visibility).
pub(crate) fn points_seen<'a, E>(
    images: &[usize],
    n_points: usize,
    points_of: impl Fn(usize) -> Result<&'a [u32], E>,
) -> Result<Option<Vec<u32>>, E> {
    if images.is_empty() {
        return Ok(None);
    }
    let mut seen: BitVec = BitVec::repeat(false, n_points);
    let mut list = Vec::new();
    for &i in images {
        for &p in points_of(i)? {
            if (p as usize) < n_points && !seen.replace(p as usize, true) {
                list.push(p);
            }
        }
    }
    if list.len() == n_points {
        return Ok(None);
    }
    list.sort_unstable();
    Ok(Some(list))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::localize::FeatureSet;

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
    fn f16_rows_score_as_their_f32_values() {
        // Widths below, at and past the kernel's 256-value stretch and its 8 lanes.
        let mut rng = crate::geometry::SplitMix64::new(8);
        for dim in [3, 8, 256, 300, 1023, 1024] {
            let rows: Vec<f16> = (0..5 * dim)
                .map(|_| f16::from_f32(rng.next_f64() as f32 - 0.5))
                .collect();
            let q: Vec<f32> = (0..dim).map(|_| rng.next_f64() as f32 - 0.5).collect();
            let wide: Vec<f32> = rows.iter().map(|v| v.to_f32()).collect();
            let want = Rows::F32(&wide).dots(dim, &q);
            let got = Rows::F16(&rows).dots(dim, &q);
            for (g, w) in got.iter().zip(&want) {
                assert!((g - w).abs() <= 1e-4 * (1.0 + w.abs()), "{dim}: {g} vs {w}");
            }
        }
    }

    #[test]
    fn ranking_orders_images_by_cosine() {
        // Four images in 2-D: the query (unnormalised) points along image 2's descriptor.
        let s = std::f32::consts::FRAC_1_SQRT_2;
        let g = [1.0, 0.0, 0.0, 1.0, s, s, -1.0, 0.0];
        assert_eq!(rank(Rows::F32(&g), 2, &[3.0, 2.9], 2), [2, 0]);
        assert_eq!(rank(Rows::F32(&g), 2, &[0.0, -5.0], 1), [0]);
        // top_k 0 is taken as 1; top_k past the images is every image, ranked.
        assert_eq!(rank(Rows::F32(&g), 2, &[3.0, 2.9], 0), [2]);
        assert_eq!(rank(Rows::F32(&g), 2, &[3.0, 2.9], 9), [2, 0, 1, 3]);
        // A stored NaN ranks last, not first.
        let g = [f32::NAN, 0.0, 0.0, 1.0, 1.0, 0.0];
        assert_eq!(rank(Rows::F32(&g), 2, &[1.0, 0.0], 3), [2, 1, 0]);
    }

    fn query(global: Option<Vec<f32>>, sets: Vec<FeatureSet>) -> QueryFeatures {
        QueryFeatures {
            sets,
            global,
            model: None,
        }
    }

    fn set(level: Option<u16>, dim: usize, rows: &[f32]) -> FeatureSet {
        FeatureSet {
            level,
            keypoints: vec![[1.0, 1.0]; rows.len() / dim],
            descriptors: rows.to_vec(),
            dim,
        }
    }

    /// Two images in 2-D: global descriptors along x and y; a VLAD of one centroid on a
    /// level-3 basis that swaps the axes, so the two methods disagree.
    fn index(method: RetrievalMethod, order: [Retrieval; 2]) -> RetrievalIndex<'static> {
        RetrievalIndex {
            global: Some((vec![1.0, 0.0, 0.0, 1.0], 2)),
            vlad: Some(VladIndex {
                level: 3,
                codebook: Codebook::new(vec![0.0, 0.0], 2).unwrap(),
                projection: Some(vec![0.0, 1.0, 1.0, 0.0]),
                d_in: 2,
                images: Cow::Owned([1.0, 0.0, 0.0, 1.0].map(f16::from_f32).to_vec()),
            }),
            indexed: None,
            order,
            method,
        }
    }

    #[test]
    fn the_map_preference_ranks_and_the_other_method_stands_in() {
        use Retrieval::{Global, Vlad};
        let both = query(Some(vec![1.0, 0.0]), vec![set(Some(3), 2, &[1.0, 0.0])]);
        let auto = |order| index(RetrievalMethod::Auto, order);
        // Global says image 0; the swapped VLAD basis says image 1.
        assert_eq!(
            auto([Global, Vlad]).retrieve(&both, 2, 1),
            (vec![0], Ok(Global))
        );
        assert_eq!(
            auto([Vlad, Global]).retrieve(&both, 2, 1),
            (vec![1], Ok(Vlad))
        );
        // Without a global descriptor, VLAD stands in; without level-3 features, global.
        let no_global = query(None, vec![set(Some(3), 2, &[1.0, 0.0])]);
        assert_eq!(
            auto([Global, Vlad]).retrieve(&no_global, 2, 1),
            (vec![1], Ok(Vlad))
        );
        let no_level = query(Some(vec![0.0, 1.0]), vec![set(Some(0), 2, &[1.0, 0.0])]);
        assert_eq!(
            auto([Vlad, Global]).retrieve(&no_level, 2, 1),
            (vec![1], Ok(Global))
        );
        // Features for no particular level (SIFT) serve the VLAD.
        let sift = query(None, vec![set(None, 2, &[0.0, 1.0])]);
        assert_eq!(
            auto([Vlad, Global]).retrieve(&sift, 2, 1),
            (vec![0], Ok(Vlad))
        );
    }

    #[test]
    fn without_usable_retrieval_every_image_is_retrieved_and_why_is_named() {
        use RetrievalFallback::*;
        use RetrievalMethod as M;
        let order = [Retrieval::Vlad, Retrieval::Global];
        let all = vec![0, 1];
        let nothing = query(None, vec![set(Some(0), 2, &[1.0, 0.0])]);
        let wide = query(
            Some(vec![1.0, 0.0, 0.0]),
            vec![set(Some(3), 3, &[1.0, 0.0, 0.0])],
        );
        let cases = [
            (M::Auto, &nothing, NoQueryFeatures { level: 3 }),
            (M::Global, &nothing, NoQueryDescriptor),
            (M::Vlad, &wide, DimensionMismatch { map: 2, query: 3 }),
            (M::Global, &wide, DimensionMismatch { map: 2, query: 3 }),
            (M::Off, &wide, Off),
        ];
        for (method, q, why) in cases {
            assert_eq!(
                index(method, order).retrieve(q, 2, 1),
                (all.clone(), Err(why)),
                "{method:?}"
            );
        }
        let mut bare = index(M::Auto, order);
        bare.global = None;
        bare.vlad = None;
        assert_eq!(
            bare.retrieve(&wide, 2, 1),
            (all.clone(), Err(NoMapDescriptors))
        );
        assert_eq!(bare.retrieve(&wide, 0, 1), (vec![], Err(NoVisibility)));
        assert_eq!(
            DimensionMismatch { map: 2, query: 3 }.to_string(),
            "the query's descriptors for retrieval have 3 dimensions, the map's 2"
        );
    }

    /// `n` unit rows of `dim` and an index of `lists` lists over them, probing `probe`:
    /// each row in the list of the nearest of the first `lists` rows, then each centroid
    /// moved to its members' mean (not unit, so `‖c‖²` differs from list to list).
    fn indexed(
        n: usize,
        dim: usize,
        lists: usize,
        probe: usize,
    ) -> (Vec<f32>, ProbedIndex<'static>) {
        let mut rng = crate::geometry::SplitMix64::new(5);
        let mut rows: Vec<f32> = (0..n * dim).map(|_| rng.next_f64() as f32 - 0.5).collect();
        normalise_rows(&mut rows, dim);
        let seeds = crate::vector::Nearest::new(&rows[..lists * dim], dim);
        let mut members: Vec<Vec<u32>> = vec![Vec::new(); lists];
        for (i, row) in rows.chunks_exact(dim).enumerate() {
            members[seeds.find(row)].push(i as u32);
        }
        let mut centroids = vec![0.0f32; lists * dim];
        for (c, m) in centroids.chunks_exact_mut(dim).zip(&members) {
            for &i in m {
                for (v, r) in c.iter_mut().zip(&rows[i as usize * dim..]) {
                    *v += r / m.len() as f32;
                }
            }
        }
        let mut offsets = vec![0u32];
        for m in &members {
            offsets.push(offsets.last().unwrap() + m.len() as u32);
        }
        let index = ImageIndex {
            of: Retrieval::Global,
            probe,
            width: dim,
            centroids: Cow::Owned(centroids.clone()),
            offsets: Cow::Owned(offsets),
            images: Cow::Owned(members.concat()),
            neighbours: None,
        };
        let probed = ProbedIndex {
            index,
            centroids: NearestF16::new(&centroids, dim),
            probe,
        };
        (rows, probed)
    }

    #[test]
    fn lists_are_probed_nearest_centroid_first() {
        let (rows, probed) = indexed(200, 8, 10, 1);
        let centroids = &probed.index.centroids;
        for q in rows.chunks_exact(8).take(20) {
            // By squared distance, which `x·c − ‖c‖²/2` orders for a unit x.
            let d2 = |l: usize| -> f32 {
                centroids[l * 8..(l + 1) * 8]
                    .iter()
                    .zip(q)
                    .map(|(c, x)| (c - x) * (c - x))
                    .sum()
            };
            let mut by_distance: Vec<usize> = (0..10).collect();
            by_distance.sort_by(|&a, &b| d2(a).total_cmp(&d2(b)));
            assert_eq!(probed.centroids.order(q), by_distance);
        }
    }

    #[test]
    fn every_list_probed_ranks_as_every_image_scored() {
        let (rows, probed) = indexed(400, 8, 20, 20);
        for q in rows.chunks_exact(8).skip(100).take(10) {
            for k in [1, 3, 10, 60, 400] {
                assert_eq!(
                    probed.rank(Rows::F32(&rows), q, k),
                    rank(Rows::F32(&rows), 8, q, k),
                    "k = {k}"
                );
            }
        }
        // f16 rows score the same way through their kernel.
        let half: Vec<f16> = rows.iter().map(|&v| f16::from_f32(v)).collect();
        let q = &rows[800..808];
        assert_eq!(
            probed.rank(Rows::F16(&half), q, 5),
            rank(Rows::F16(&half), 8, q, 5)
        );
    }

    /// The wider nets rank every image: where the index's probe misses a query's best
    /// image, `retrieve_every` still finds it, and `retrieve` goes through the index.
    #[test]
    fn retrieve_every_ranks_past_the_index() {
        let (rows, probed) = indexed(400, 8, 20, 1);
        let index = RetrievalIndex {
            global: Some((rows.clone(), 8)),
            vlad: None,
            indexed: Some(probed),
            order: [Retrieval::Global, Retrieval::Vlad],
            method: RetrievalMethod::Auto,
        };
        let mut missed = 0;
        for q in rows.chunks_exact(8).take(100) {
            let features = query(Some(q.to_vec()), Vec::new());
            let every = rank(Rows::F32(&rows), 8, q, 3);
            let (got, how) = index.retrieve_every(&features, 400, 3);
            assert_eq!((got, how), (every.clone(), Ok(Retrieval::Global)));
            let probed = index.indexed.as_ref().unwrap().rank(Rows::F32(&rows), q, 3);
            assert_eq!(index.retrieve(&features, 400, 3).0, probed);
            missed += usize::from(probed != every);
        }
        // One list of 20 probed does miss some query's best three.
        assert!(missed > 0);
    }

    #[test]
    fn a_probe_ranks_the_images_of_its_lists_only() {
        let (rows, probed) = indexed(400, 8, 20, 2);
        let mut narrower = 0;
        for (n, q) in rows.chunks_exact(8).enumerate().skip(100).take(30) {
            let order = probed.centroids.order(q);
            let lists: Vec<&[u32]> = order.iter().map(|&l| probed.index.list(l)).collect();
            for k in [1, 4] {
                let got = probed.rank(Rows::F32(&rows), q, k);
                // Every image ranked is in a list at least as near as the `probe`-th, or in
                // one the minimum scored count added.
                let first_two: usize = lists[..2].iter().map(|l| l.len()).sum();
                let needed = if first_two >= MIN_SCORED_PER_K * k {
                    2
                } else {
                    (1..=20)
                        .find(|&p| {
                            lists[..p].iter().map(|l| l.len()).sum::<usize>()
                                >= MIN_SCORED_PER_K * k
                        })
                        .unwrap()
                };
                let scored: Vec<u32> = lists[..needed].concat();
                assert!(
                    got.iter().all(|i| scored.contains(&(*i as u32))),
                    "query {n}, k {k}"
                );
                // ... and they are the best of those, as exhaustive ranking orders them.
                let exhaustive = rank(Rows::F32(&rows), 8, q, 400);
                let want: Vec<usize> = exhaustive
                    .into_iter()
                    .filter(|&i| scored.contains(&(i as u32)))
                    .take(k)
                    .collect();
                assert_eq!(got, want, "query {n}, k {k}");
                if scored.len() < 400 && got != rank(Rows::F32(&rows), 8, q, k) {
                    narrower += 1;
                }
            }
        }
        // Probing 2 of 20 lists misses some query's exhaustive best: it did narrow.
        assert!(narrower > 0);
    }

    /// (1.4) Images along a half circle (a street's images, as retrieval sees them), in 20
    /// lists of 20 neighbours each: a query between two lists finds its best two only with
    /// the neighbours; with them, one list probed ranks as every image scored.
    #[test]
    fn neighbours_widen_a_probe_to_the_exhaustive_best() {
        let (n, dim) = (400usize, 4usize);
        let angle = |x: f64| x * std::f64::consts::PI / n as f64;
        let row = |x: f64| [angle(x).cos() as f32, angle(x).sin() as f32, 0.0, 0.0];
        let rows: Vec<f32> = (0..n).flat_map(|i| row(i as f64)).collect();
        let mut centroids = vec![0.0f32; 20 * dim];
        for (l, c) in centroids.chunks_exact_mut(dim).enumerate() {
            for i in l * 20..(l + 1) * 20 {
                for (v, r) in c.iter_mut().zip(&rows[i * dim..(i + 1) * dim]) {
                    *v += r / 20.0;
                }
            }
        }
        // Each image's 4 nearest along the circle, nearest first.
        let mut graph = Vec::new();
        for i in 0..n as i64 {
            let mut near: Vec<i64> = [-2, -1, 1, 2].iter().map(|d| i + d).collect();
            near.sort_by_key(|&j| ((j - i).abs(), j));
            graph.extend(near.iter().map(|&j| {
                if (0..n as i64).contains(&j) {
                    j as u32
                } else {
                    crate::format::NO_NEIGHBOUR
                }
            }));
        }
        let index = |neighbours| ProbedIndex {
            index: ImageIndex {
                of: Retrieval::Global,
                probe: 1,
                width: dim,
                centroids: Cow::Owned(centroids.clone()),
                offsets: Cow::Owned((0..=20).map(|l| l * 20).collect()),
                images: Cow::Owned((0..n as u32).collect()),
                neighbours,
            },
            centroids: NearestF16::new(&centroids, dim),
            probe: 1,
        };
        let bare = index(None);
        let widened = index(Some(crate::format::Neighbours {
            per_image: 4,
            rows: Cow::Owned(graph),
        }));
        let mut missed = 0;
        for l in 1..20 {
            // Just past a list's first image: its best two are in two lists.
            let q = row((l * 20) as f64 - 0.4);
            let every = rank(Rows::F32(&rows), dim, &q, 2);
            assert_eq!(every, [l * 20, l * 20 - 1], "list {l}");
            assert_eq!(widened.rank(Rows::F32(&rows), &q, 2), every, "list {l}");
            missed += usize::from(bare.rank(Rows::F32(&rows), &q, 2) != every);
        }
        // The lists alone miss every one of them.
        assert_eq!(missed, 19);
    }

    fn ok(points: &[u32]) -> Result<&[u32], std::convert::Infallible> {
        Ok(points)
    }

    #[test]
    fn candidates_are_the_points_the_retrieved_images_see() {
        let visibility: [&[u32]; 3] = [&[0, 2], &[2, 3, 99], &[1, 4]];
        let seen = points_seen(&[0, 1], 5, |i| ok(visibility[i]))
            .unwrap()
            .unwrap();
        assert_eq!(seen, [0, 2, 3]);
        // Listed once, ascending, whatever order the images list them in.
        let repeated: [&[u32]; 2] = [&[3, 0, 3], &[2, 0]];
        assert_eq!(
            points_seen(&[1, 0], 5, |i| ok(repeated[i]))
                .unwrap()
                .unwrap(),
            [0, 2, 3]
        );
        // Every point seen: no narrowing; no image: no narrowing either.
        assert!(points_seen(&[0, 1, 2], 5, |i| ok(visibility[i]))
            .unwrap()
            .is_none());
        assert!(points_seen(&[], 5, |i| ok(visibility[i]))
            .unwrap()
            .is_none());
    }
}
