//! Building a catalog of place maps (spec "Catalogs"; read by `format::Catalog`): per place,
//! where its map is, its origin, bounding box and counts, and a summary map holding its
//! images and retrieval data, copied byte for byte from the place map.

use crate::format::{Descriptors, Error, Map, MapWriter, Metadata, Place, Provenance, SectionKind};

/// One place for [`build_catalog`].
pub struct PlaceMap<'m> {
    /// A name for reports.
    pub name: String,
    /// Where the catalog says the map is: a URL, or a path relative to the catalog's folder.
    pub location: String,
    pub map: &'m Map<'m>,
}

/// The catalog of `places`, ready to write (`.sfpc`).
pub fn build_catalog(places: &[PlaceMap<'_>]) -> Result<MapWriter<'static>, Error> {
    let mut listed = Vec::with_capacity(places.len());
    let mut summaries = Vec::with_capacity(places.len());
    for p in places {
        listed.push(describe(p)?);
        summaries.push(place_summary(p.map)?);
    }
    let metadata = Metadata {
        geometry_only: true,
        provenance: Provenance {
            tool: format!("sfpmap {} catalog", env!("CARGO_PKG_VERSION")),
            ..Provenance::default()
        },
        ..Metadata::default()
    };
    let mut writer = MapWriter::new(metadata);
    writer.set_points_world(&[]);
    writer.set_catalog(&listed, &summaries)?;
    Ok(writer)
}

/// A place's entry: origin, the world bounding box of its points, counts, and what identifies
/// the map's content.
fn describe(p: &PlaceMap<'_>) -> Result<Place, Error> {
    let map = p.map;
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &q in map.point_positions()?.iter() {
        let w = map.to_world(q);
        for k in 0..3 {
            lo[k] = lo[k].min(w[k]);
            hi[k] = hi[k].max(w[k]);
        }
    }
    if map.n_points() == 0 {
        (lo, hi) = (map.metadata().origin, map.metadata().origin);
    }
    Ok(Place {
        name: p.name.clone(),
        map: p.location.clone(),
        origin: map.metadata().origin,
        bbox_min: lo,
        bbox_max: hi,
        points: map.n_points(),
        images: map.n_images(),
        file_bytes: map.file_len(),
        index_checksum: format!("{:016x}", map.index_checksum()),
    })
}

/// A map of no points holding `map`'s images and what ranks them: the VLAD level's info,
/// projection and codebook (its points and descriptors left out), the images' VLADs and
/// global descriptors. Retrieval on it ranks the images as on the map.
pub fn place_summary(map: &Map<'_>) -> Result<Vec<u8>, Error> {
    let source = map.metadata();
    let vlad_level = map.vlad()?.map(|v| v.level);
    let metadata = Metadata {
        levels: Vec::new(),
        geometry_only: false,
        position_grid: None,
        provenance: Provenance {
            tool: format!("sfpmap {} catalog summary", env!("CARGO_PKG_VERSION")),
            ..Provenance::default()
        },
        extra: Default::default(),
        ..source.clone()
    };
    // No points, the place map's origin kept (`set_points` leaves it as the metadata says).
    let mut writer = MapWriter::new(metadata);
    writer.set_points(&[]);
    let mut copied = vec![
        SectionKind::ImagePoses,
        SectionKind::ImageCameras,
        SectionKind::ImageIds,
        SectionKind::ImageNameOffsets,
        SectionKind::ImageNames,
        SectionKind::ImageGlobal,
        SectionKind::ImageVlad,
    ]
    .into_iter()
    .filter_map(|kind| map.find(kind, None))
    .collect::<Vec<_>>();
    if let Some(level) = vlad_level {
        let info = source
            .level(level)
            .cloned()
            .ok_or_else(|| Error::inconsistent("VLAD level not in the metadata"))?;
        writer.add_level(info, &[], Some(Descriptors::F32(&[])), false)?;
        copied.extend(
            [
                SectionKind::LevelProjection,
                SectionKind::LevelVladCentroids,
            ]
            .into_iter()
            .filter_map(|kind| map.find(kind, Some(level))),
        );
    }
    for section in copied {
        writer.copy_section(map, section)?;
    }
    writer.to_bytes()
}
