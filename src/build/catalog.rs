//! Building a catalog of place maps (spec "Catalogs"; read by `format::Catalog`): per place,
//! where its map is, its origin, bounding box and counts; for all places together, one VLAD
//! codebook on a basis of their common descriptor space, and every place's images' VLADs.
//!
//! Each place's descriptors are taken back to the descriptor space they were extracted in
//! (the transpose of the level's orthonormal projection), so places converted with different
//! bases meet in one space; an uncentred PCA of a sample from every place keeps
//! 32 dimensions, a k-means of 32 centroids is the codebook,
//! and each image's VLAD aggregates the points it sees, as `convert` does for one map.

use super::basis::Basis;
use crate::format::{Error, Listing, Map, MapWriter, Metadata, Place, Provenance};
use crate::vector::{normalise_rows, project_rows};
use crate::vlad::Codebook;

/// Dimensions of the catalog's basis, and centroids of its codebook: an image's VLAD is
/// `32 × 32` f16 values, 2 KiB, so a catalog of 10,000 images is 20 MiB.
pub(crate) const CATALOG_DIMS: usize = 32;
pub(crate) const CATALOG_CLUSTERS: usize = 32;

/// Rows of each place in the basis and codebook sample.
const SAMPLE_PER_PLACE: usize = 20_000;

/// The k-means seed: a catalog builds to the same bytes.
const SEED: u64 = 0xca7a_1065;

/// One place for [`build_catalog`].
pub struct PlaceMap<'m> {
    /// A name for reports.
    pub name: String,
    /// Where the catalog says the map is: a URL, or a path relative to the catalog's folder.
    pub location: String,
    /// The place's map, open.
    pub map: &'m Map<'m>,
}

/// One place's descriptors in the common space, one row per map point (zero rows for points
/// its level does not hold), and its level's descriptor name.
struct PlaceRows {
    rows: Vec<f32>,
    d_in: usize,
    descriptor: String,
}

/// The catalog of `places`, ready to write (`.sfpc`).
pub fn build_catalog(places: &[PlaceMap<'_>]) -> Result<MapWriter<'static>, Error> {
    if places.is_empty() {
        return Err(Error::invalid("a catalog needs at least one place"));
    }
    // Two passes over the places, one place's rows held at a time (a city's would not fit):
    // the first describes each and samples it, the second, once the basis and codebook are
    // fitted, makes its images' VLADs from its rows made again.
    let mut listed = Vec::with_capacity(places.len());
    let mut sample = Vec::new();
    let mut first: Option<(usize, String)> = None;
    for p in places {
        listed.push(describe(p)?);
        let r = place_rows(p)?;
        let (d_in, descriptor) = first.get_or_insert_with(|| (r.d_in, r.descriptor.clone()));
        if r.d_in != *d_in || r.descriptor != *descriptor {
            return Err(Error::invalid(format!(
                "place {:?} has {} descriptors of {} dimensions, place {:?} {descriptor} of {d_in}: a catalog holds places of one descriptor",
                p.name, r.descriptor, r.d_in, places[0].name
            )));
        }
        // The basis and the codebook from a sample of every place (every k-th described
        // point).
        let described: Vec<&[f32]> = r
            .rows
            .chunks_exact(r.d_in)
            .filter(|x| x.iter().any(|&v| v != 0.0))
            .collect();
        let step = described.len().div_ceil(SAMPLE_PER_PLACE).max(1);
        for x in described.iter().step_by(step) {
            sample.extend_from_slice(x);
        }
    }
    let (d_in, descriptor) = first.expect("at least one place");
    let dims = CATALOG_DIMS.min(d_in);
    let basis = Basis::fit(&sample, d_in);
    let projection = basis.rows[..dims * d_in].to_vec();
    let project = |rows: &[f32]| project_rows(rows, d_in, &projection, dims);
    let codebook = Codebook::train(&project(&sample), dims, CATALOG_CLUSTERS, SEED)
        .ok_or_else(|| Error::invalid("too few described points in the places for a codebook"))?;
    let mut place_images = vec![0u64];
    let mut image_vlad = Vec::new();
    for p in places {
        let r = place_rows(p)?;
        let vis = p.map.visibility_points()?.ok_or_else(|| {
            Error::invalid(format!(
                "place {:?} has no visibility (image → points): its images cannot be summarised",
                p.name
            ))
        })?;
        let vlads = codebook.image_vlads(&project(&r.rows), &vis.offsets, &vis.points);
        image_vlad.extend(vlads);
        place_images.push((image_vlad.len() / codebook.width()) as u64);
    }
    let listing = Listing {
        places: listed,
        descriptor,
        d_in: d_in as u32,
    };
    let metadata = Metadata {
        geometry_only: true,
        provenance: Provenance {
            tool: format!("sfpmap {} catalog", env!("CARGO_PKG_VERSION")),
            ..Provenance::default()
        },
        ..Metadata::default()
    };
    let mut writer = MapWriter::new(metadata);
    writer.set_points(&[]);
    writer.set_catalog(
        &listing,
        &place_images,
        &projection,
        codebook.centroids(),
        dims,
        &image_vlad,
    )?;
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

/// The descriptors of the place's retrieval level (its VLAD's, else its level with the most
/// points), back in the space they were extracted in, one row per map point, unit length.
fn place_rows(p: &PlaceMap<'_>) -> Result<PlaceRows, Error> {
    let map = p.map;
    // From the table: reading the VLAD itself would fetch every image's (by range).
    let level_id = match map.vlad_level() {
        Some(level) => level,
        None => map
            .levels()
            .filter(|l| l.has_descriptors())
            .max_by_key(|l| l.len())
            .map(|l| l.id())
            .ok_or_else(|| Error::invalid(format!("place {:?} has no descriptors", p.name)))?,
    };
    let level = map.level(level_id)?;
    if level.pq()?.is_some() {
        return Err(Error::invalid(format!(
            "place {:?}: level {level_id} is product-quantised; a catalog reads f16 descriptors",
            p.name
        )));
    }
    let (full, short) = (level.dim_full(), level.dim_short());
    let short_block = level.desc_short()?;
    let rest_block = level.desc_rest()?;
    let stored = match &rest_block {
        Some(_) => full,
        None => short,
    };
    let projection = level.projection()?;
    let d_in = level.projection_input_dim().unwrap_or(full);
    let n_points = map.n_points() as usize;
    let mut rows = vec![0.0f32; n_points * d_in];
    let mut y = vec![0.0f32; stored];
    for (i, &point) in level.points()?.iter().enumerate() {
        for (k, v) in y[..short].iter_mut().enumerate() {
            *v = short_block[i * short + k].to_f32();
        }
        if let Some(rest) = &rest_block {
            let r = full - short;
            for (k, v) in y[short..].iter_mut().enumerate() {
                *v = rest[i * r + k].to_f32();
            }
        }
        let x = &mut rows[point as usize * d_in..(point as usize + 1) * d_in];
        match &projection {
            // y = P x with orthonormal rows: x ≈ Pᵀ y (exact when all rows are kept).
            Some(p) => {
                for (k, &yk) in y.iter().enumerate() {
                    for (xj, &pkj) in x.iter_mut().zip(&p[k * d_in..(k + 1) * d_in]) {
                        *xj += yk * pkj;
                    }
                }
            }
            None => x[..stored].copy_from_slice(&y),
        }
    }
    normalise_rows(&mut rows, d_in);
    Ok(PlaceRows {
        rows,
        d_in,
        descriptor: level.info().descriptor.clone(),
    })
}
