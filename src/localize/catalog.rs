//! Choosing the places of a catalog (`format::Catalog`) a query may be in, before any place
//! map is opened: the query's VLAD on the catalog's one codebook is scored against every
//! place's images, and places are ordered by their best image's cosine.

use super::retrieval::Rows;
use super::QueryFeatures;
use crate::format::{Catalog, Error as FormatError};
use crate::vector::project_rows;
use crate::vlad::Codebook;

/// A catalog's places, ready to rank queries.
pub(crate) struct PlaceRanker {
    codebook: Codebook,
    /// `[dims × d_in]`.
    projection: Vec<f32>,
    d_in: usize,
    /// `[images × width]`, unit rows.
    images: Vec<f32>,
    /// Place `i`'s images are rows `place_images[i]..place_images[i + 1]`.
    place_images: Vec<u64>,
}

/// One place's score for a query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaceScore {
    /// Index into the catalog's places.
    pub place: usize,
    /// The cosine of the query with the place's best image.
    pub score: f32,
}

impl PlaceRanker {
    /// The ranker of `catalog`'s places: its codebook, projection and image VLADs, widened to f32.
    pub(crate) fn new(catalog: &Catalog<'_>) -> Result<PlaceRanker, FormatError> {
        let codebook = Codebook::new(catalog.centroids.to_vec(), catalog.dims)
            .ok_or_else(|| FormatError::inconsistent("catalog: a codebook of no centroids"))?;
        let mut images = vec![0.0f32; catalog.image_vlad.len()];
        crate::vector::widen_f16(&catalog.image_vlad, &mut images);
        Ok(PlaceRanker {
            codebook,
            projection: catalog.projection.to_vec(),
            d_in: catalog.listing.d_in as usize,
            images,
            place_images: catalog.place_images.to_vec(),
        })
    }

    /// The query's VLAD on the catalog's codebook over all its features of the catalog's
    /// descriptor dimension (a SIFT query's scale levels together), `None` without any.
    fn query_vlad(&self, query: &QueryFeatures) -> Option<Vec<f32>> {
        let sets: Vec<_> = query
            .sets
            .iter()
            .filter(|s| s.dim == self.d_in && s.descriptors.len() == s.keypoints.len() * s.dim)
            .collect();
        if sets.iter().all(|s| s.keypoints.is_empty()) {
            return None;
        }
        let descriptors: Vec<f32> = sets
            .iter()
            .flat_map(|s| s.descriptors.iter().copied())
            .collect();
        let rows = project_rows(
            &descriptors,
            self.d_in,
            &self.projection,
            self.codebook.dims(),
        );
        let vlad = self.codebook.vlad(&rows);
        // No usable feature: nothing to rank by (an all-zero VLAD scores every image 0).
        vlad.iter().any(|&v| v != 0.0).then_some(vlad)
    }

    /// The places among `allowed`, best first (ties: lower index); empty when the query has
    /// no features of the catalog's descriptor.
    pub(crate) fn rank(
        &self,
        query: &QueryFeatures,
        allowed: impl Fn(usize) -> bool,
    ) -> Vec<PlaceScore> {
        let Some(q) = self.query_vlad(query) else {
            return Vec::new();
        };
        let width = self.codebook.width();
        let mut scored: Vec<PlaceScore> = (0..self.place_images.len() - 1)
            .filter(|&p| allowed(p))
            .filter_map(|place| {
                let (start, end) = (
                    self.place_images[place] as usize,
                    self.place_images[place + 1] as usize,
                );
                // The retrieval kernel: a dot per image.
                let cosines = Rows::F32(&self.images[start * width..end * width]).dots(width, &q);
                let score = cosines
                    .into_iter()
                    .filter(|s| s.is_finite())
                    .max_by(f32::total_cmp)?;
                Some(PlaceScore { place, score })
            })
            .collect();
        scored.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.place.cmp(&b.place)));
        scored
    }
}
