//! Catalogs of place maps (`.sfpc`, spec "Catalogs"): a map file of no points whose metadata
//! lists the places (`catalog.places`: where each map is, its origin, bounding box and
//! counts) and whose sections hold each place's summary, itself a map: its images and what
//! ranks them (the VLAD level's projection and codebook, the images' VLADs or global
//! descriptors), no points. A localizer ranks the places for a query from the summaries
//! before it opens any place map.

use super::error::Error;
use super::layout::{SectionKind, ALIGN};
use super::reader::{cast, Map};
use serde::{Deserialize, Serialize};

/// One place of a catalog, as its metadata lists it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Place {
    /// A name for reports (the map's file stem unless given).
    pub name: String,
    /// The place map: a URL, or a path (relative to the catalog's folder, or absolute).
    pub map: String,
    /// The map's origin: world = origin + stored position.
    pub origin: [f64; 3],
    /// The world bounding box of the map's points.
    pub bbox_min: [f64; 3],
    pub bbox_max: [f64; 3],
    pub points: u64,
    pub images: u64,
    /// The map's file length and index checksum (hex) when the catalog was built: a map
    /// replaced since is reported, not silently used.
    pub file_bytes: u64,
    pub index_checksum: String,
}

impl Place {
    /// Whether `world` lies within `radius` of the place's bounding box.
    pub fn near(&self, world: [f64; 3], radius: f64) -> bool {
        (0..3)
            .all(|k| world[k] >= self.bbox_min[k] - radius && world[k] <= self.bbox_max[k] + radius)
    }
}

/// The metadata key under which a catalog lists its places.
pub const CATALOG_KEY: &str = "catalog";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Listing {
    places: Vec<Place>,
}

/// A catalog, read from a map that is one. Place summaries are checked (opened as maps) on
/// access.
#[derive(Debug)]
pub struct Catalog<'m> {
    places: Vec<Place>,
    offsets: Vec<u64>,
    summaries: &'m [u8],
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
        let offsets: Vec<u64> =
            cast::<u64>(map.section_bytes(need(SectionKind::PlaceOffsets)?)?).into_owned();
        let summaries = map.section_bytes(need(SectionKind::PlaceSummaries)?)?;
        if offsets.len() != listing.places.len() + 1 {
            return Err(Error::inconsistent(format!(
                "catalog: {} place offsets for {} places",
                offsets.len(),
                listing.places.len()
            )));
        }
        let ordered = offsets.windows(2).all(|w| w[0] <= w[1]);
        let aligned = offsets.iter().all(|&o| o % ALIGN == 0);
        if offsets.first() != Some(&0)
            || !ordered
            || !aligned
            || offsets.last() != Some(&(summaries.len() as u64))
        {
            return Err(Error::inconsistent(
                "catalog: place offsets are not increasing multiples of 64 from 0 to the summaries' length",
            ));
        }
        Ok(Some(Catalog {
            places: listing.places,
            offsets,
            summaries,
        }))
    }

    pub fn places(&self) -> &[Place] {
        &self.places
    }

    /// Place `i`'s summary map (images and retrieval data), checked as any map is at open.
    pub fn summary(&self, i: usize) -> Result<Map<'m>, Error> {
        let (start, end) = (self.offsets[i] as usize, self.offsets[i + 1] as usize);
        // A summary is zero-padded to 64 bytes; the map inside ends where its header says.
        let bytes = &self.summaries[start..end];
        let len = bytes
            .get(48..56) // the header's file_len field
            .map_or(0, |b| {
                u64::from_le_bytes(b.try_into().expect("8 bytes")) as usize
            });
        Map::from_bytes(&bytes[..len.min(bytes.len())]).map_err(|e| {
            Error::inconsistent(format!(
                "catalog place {i} ({}): summary: {e}",
                self.places[i].name
            ))
        })
    }

    /// The metadata value a catalog of `places` stores under [`CATALOG_KEY`].
    pub fn listing(places: &[Place]) -> serde_json::Value {
        serde_json::to_value(Listing {
            places: places.to_vec(),
        })
        .expect("places serialise")
    }
}
