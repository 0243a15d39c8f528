//! Catalogs of place maps (`.sfpc`, spec "Catalogs"): a map file of no points whose metadata
//! lists the places (`catalog.places`: where each map is, its origin, bounding box and
//! counts) and whose sections rank them for a query: one VLAD codebook for all places, on a
//! basis of their common descriptor space, and every place's images' VLADs on it. One
//! codebook makes scores comparable across places (each map's own codebook fits its own
//! descriptors, so its scores say little about other places').

use super::error::Error;
use super::layout::SectionKind;
use super::reader::Map;
use half::f16;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;

/// One place of a catalog, as its metadata lists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Place {
    /// A name for reports (the map's file stem unless given).
    pub name: String,
    /// The place map: a URL, or a path (relative to the catalog's folder, or absolute).
    pub map: String,
    /// The map's origin: world = origin + stored position.
    pub origin: [f64; 3],
    /// The smallest corner of the world bounding box of the map's points.
    pub bbox_min: [f64; 3],
    /// The largest corner of that box.
    pub bbox_max: [f64; 3],
    /// Points in the map.
    pub points: u64,
    /// Images in the map.
    pub images: u64,
    /// The map's file length and index checksum (hex) when the catalog was built: a map
    /// replaced since is reported, not silently used.
    pub file_bytes: u64,
    /// See `file_bytes`.
    pub index_checksum: String,
}

impl Place {
    /// Whether `world` lies within `radius` of the place's bounding box: its
    /// [`Place::distance`] is at most `radius`.
    pub fn near(&self, world: [f64; 3], radius: f64) -> bool {
        self.distance(world) <= radius
    }

    /// How far `world` lies outside the place's bounding box, along the axis where it lies
    /// farthest (0 inside); infinite for a coordinate that is not a number.
    pub fn distance(&self, world: [f64; 3]) -> f64 {
        let mut far = 0.0f64;
        for ((w, lo), hi) in world.iter().zip(self.bbox_min).zip(self.bbox_max) {
            let d = (lo - w).max(w - hi);
            if d.is_nan() {
                return f64::INFINITY;
            }
            far = far.max(d);
        }
        far
    }
}

/// The metadata key under which a catalog lists its places.
pub const CATALOG_KEY: &str = "catalog";

/// What a catalog's metadata holds under the key `catalog`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Listing {
    /// The places, in the order of `place_images`.
    pub places: Vec<Place>,
    /// The places' common descriptor (`sift`, an SFP model's name), their dimension `d_in`.
    pub descriptor: String,
    /// Their descriptors' dimension.
    pub d_in: u32,
}

/// A catalog, read from a map that is one; its arrays are checked against each other here.
#[derive(Debug)]
pub struct Catalog<'m> {
    /// The places and their common descriptor.
    pub listing: Listing,
    /// Place `i`'s images are rows `place_images[i]..place_images[i + 1]` of `image_vlad`.
    pub place_images: Cow<'m, [u64]>,
    /// `[dims × d_in]`.
    pub projection: Cow<'m, [f32]>,
    /// `[clusters × dims]`.
    pub centroids: Cow<'m, [f32]>,
    /// Dimensions of the common space.
    pub dims: usize,
    /// `[images × clusters·dims]`, unit rows.
    pub image_vlad: Cow<'m, [f16]>,
}

impl<'m> Catalog<'m> {
    /// The catalog `map` holds, `None` if it is not a catalog.
    pub fn of(map: &'m Map<'_>) -> Result<Option<Catalog<'m>>, Error> {
        let Some(listing) = map.metadata().extra.get(CATALOG_KEY) else {
            return Ok(None);
        };
        let listing: Listing =
            serde_json::from_value(listing.clone()).map_err(|e| Error::BadMetadata {
                message: format!("catalog: {e}"),
            })?;
        let need = |kind| {
            map.find(kind, None)
                .ok_or(Error::MissingSection { kind, level: None })
        };
        let (offsets, projection, centroids, vlad) = (
            need(SectionKind::PlaceImages)?,
            need(SectionKind::CatalogProjection)?,
            need(SectionKind::CatalogVladCentroids)?,
            need(SectionKind::CatalogImageVlad)?,
        );
        let bad = |what: String| Err(Error::inconsistent(format!("catalog: {what}")));
        let dims = centroids.cols() as usize;
        if listing.d_in == 0 || dims == 0 {
            return bad("a descriptor or codebook of no dimension".into());
        }
        if offsets.rows() != listing.places.len() as u64 + 1 {
            return bad(format!(
                "{} place offsets for {} places",
                offsets.rows(),
                listing.places.len()
            ));
        }
        if projection.rows() != centroids.cols() || projection.cols() != u64::from(listing.d_in) {
            return bad(format!(
                "projection is {} x {}, expected {dims} x {}",
                projection.rows(),
                projection.cols(),
                listing.d_in
            ));
        }
        if centroids.rows() == 0 || vlad.cols() != centroids.rows() * centroids.cols() {
            return bad(format!(
                "image VLADs have {} columns for {} x {dims} centroids",
                vlad.cols(),
                centroids.rows()
            ));
        }
        let place_images = map.section_array::<u64>(offsets)?;
        let ordered = place_images.windows(2).all(|w| w[0] <= w[1]);
        if place_images.first() != Some(&0) || !ordered || place_images.last() != Some(&vlad.rows())
        {
            return bad("place offsets do not run from 0 to the image VLADs' rows".into());
        }
        let projection = map.section_array::<f32>(projection)?;
        let centroids = map.section_array::<f32>(centroids)?;
        if !projection
            .iter()
            .chain(centroids.iter())
            .all(|v| v.is_finite())
        {
            return bad("projection or centroids hold a non-finite value".into());
        }
        Ok(Some(Catalog {
            listing,
            place_images,
            projection,
            centroids,
            dims,
            image_vlad: map.section_array::<f16>(vlad)?,
        }))
    }

    /// The places.
    pub fn places(&self) -> &[Place] {
        &self.listing.places
    }
}
