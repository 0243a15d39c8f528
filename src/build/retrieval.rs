//! Retrieval for every map: the VLAD codebook and per-image VLADs `convert` stores (format
//! 1.1, [`crate::vlad`]), from the map's own point descriptors in one level's basis.

use super::geometry::Geometry;
use crate::format::MapWriter;
use crate::progress::Reporter;
use crate::vlad::Codebook;
use serde_json::json;

/// How `convert` builds retrieval data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct VladOptions {
    /// Centroids; 0 stores no VLAD; `None`: by the map's images ([`crate::vlad::default_shape`]).
    pub clusters: Option<usize>,
    /// Leading dimensions of the level basis (at most the level's `dim_short`); `None`: by
    /// the map's images.
    pub dims: Option<usize>,
}

impl VladOptions {
    /// (clusters, dims) for a map of `images` images whose descriptors were computed `at`.
    pub fn shape(&self, images: usize, at: crate::vlad::DescribedAt) -> (usize, usize) {
        let (clusters, dims) = crate::vlad::default_shape(images, at);
        (self.clusters.unwrap_or(clusters), self.dims.unwrap_or(dims))
    }
}

/// What a converted map's VLAD is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StoredVlad {
    /// The level whose basis (and codebook section) it is on.
    pub level: u16,
    /// Centroids of its codebook.
    pub clusters: usize,
    /// Leading dimensions of the level basis it aggregates.
    pub dims: usize,
}

/// The seed of the codebook's k-means: fixed, so a map converts to the same bytes.
const SEED: u64 = 0x5f9_1a0;

/// Learns the codebook from `rows` (one per map point: its descriptor's first `dims`
/// dimensions in `level`'s basis, renormalised; a zero row for a point without one; `points`
/// says which points those are, in words) and adds it, each image's VLAD over the points it
/// sees, and the rule to the level's metadata to `writer` (after the level). `None`: a map
/// with fewer described points than centroids, or without images, gets no VLAD.
#[allow(clippy::too_many_arguments)]
pub(crate) fn add_vlad(
    writer: &mut MapWriter<'_>,
    level: u16,
    rows: &[f32],
    dims: usize,
    clusters: usize,
    points: &str,
    geometry: &Geometry,
    reporter: &dyn Reporter,
) -> Result<Option<StoredVlad>, crate::format::Error> {
    if clusters == 0 || dims == 0 || geometry.vis_offsets.len() < 2 {
        return Ok(None);
    }
    reporter.start("retrieval codebook", None);
    let codebook = Codebook::train(rows, dims, clusters, SEED);
    reporter.finish();
    let Some(codebook) = codebook else {
        return Ok(None);
    };
    reporter.start("image VLADs", None);
    let images = codebook.image_vlads(rows, &geometry.vis_offsets, &geometry.vis_points);
    reporter.finish();
    let info = writer
        .metadata_mut()
        .levels
        .iter_mut()
        .find(|l| l.level == level)
        .ok_or_else(|| crate::format::Error::invalid("VLAD for a level the map does not have"))?;
    info.extra.insert(
        "vlad".into(),
        json!({
            "clusters": codebook.clusters(),
            "dims": dims,
            "rule": crate::vlad::rule(),
            "points": points,
        }),
    );
    let clusters = codebook.clusters();
    writer.set_vlad(level, dims, codebook.into_centroids(), &images)?;
    Ok(Some(StoredVlad {
        level,
        clusters,
        dims,
    }))
}

#[cfg(test)]
mod tests {
    use super::VladOptions;

    #[test]
    fn a_stated_shape_wins_over_the_images_rule() {
        let by_images = VladOptions::default();
        let own = crate::vlad::DescribedAt::OwnKeypoints;
        assert_eq!(
            by_images.shape(100, own),
            crate::vlad::default_shape(100, own)
        );
        assert_eq!(
            by_images.shape(10_000, own),
            crate::vlad::default_shape(10_000, own)
        );
        let stated = VladOptions {
            clusters: Some(0),
            dims: None,
        };
        assert_eq!(stated.shape(10_000, own).0, 0);
        assert_eq!(stated.shape(10_000, own).1, crate::vlad::LARGE_DIMS);
    }
}
