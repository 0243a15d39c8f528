//! Choosing the places of a catalog (`format::Catalog`) a query may be in, before any place
//! map is opened: each place's summary ranks its images for the query as the place map would
//! (its VLAD or global descriptors), and places are ordered by their best image's cosine.

use super::localizer::LocalizeError;
use super::retrieval::{RetrievalIndex, RetrievalMethod};
use super::QueryFeatures;
use crate::format::{Catalog, Retrieval};

/// The places of a catalog, ready to rank queries.
pub struct PlaceRanker {
    /// Per place, what ranks its images.
    indexes: Vec<RetrievalIndex>,
}

/// One place's score for a query.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlaceScore {
    /// Index into the catalog's places.
    pub place: usize,
    /// The cosine of the query with the place's best image.
    pub score: f32,
    /// What scored it.
    pub method: Retrieval,
}

impl PlaceRanker {
    /// Reads every place's summary (checked as a map is at open).
    pub fn new(
        catalog: &Catalog<'_>,
        method: RetrievalMethod,
    ) -> Result<PlaceRanker, LocalizeError> {
        let mut indexes = Vec::with_capacity(catalog.places().len());
        for i in 0..catalog.places().len() {
            let summary = catalog.summary(i)?;
            indexes.push(RetrievalIndex::new(&summary, method)?);
        }
        Ok(PlaceRanker { indexes })
    }

    /// The places among `allowed` that can score `query`, best first (ties: lower index).
    pub fn rank(&self, query: &QueryFeatures, allowed: impl Fn(usize) -> bool) -> Vec<PlaceScore> {
        let mut scored: Vec<PlaceScore> = self
            .indexes
            .iter()
            .enumerate()
            .filter(|(i, _)| allowed(*i))
            .filter_map(|(place, index)| {
                let (score, method) = index.best_score(query)?;
                Some(PlaceScore {
                    place,
                    score,
                    method,
                })
            })
            .collect();
        scored.sort_by(|a, b| b.score.total_cmp(&a.score).then(a.place.cmp(&b.place)));
        scored
    }
}
