//! `slice --short --short-dims N`: each kept level's `short` block moved into an uncentred PCA
//! basis of its own rows ([`Basis`], as `convert` stores SIFT's levels) and cut to the leading
//! N dimensions, with the projection that takes a query's descriptor there.
//!
//! Why: a level's short descriptor is whatever its extractor gives — an SFP level's is the
//! network's own (64 dimensions on level 2), with its energy spread evenly, so no prefix of it
//! is a good short descriptor. Fitted to the level's own rows, the basis puts the most energy
//! any N dimensions can hold in the first N, which is what SIFT's maps store (32 of 128).
//!
//! A cut level becomes `dim_short = dim_full = N`, `rest` absent, and `level_projection`
//! `[N × d_in]` = the basis' leading rows composed with what the level took before: its own
//! projection's first `dim_short` rows, or, in the extractor's basis, the first `dim_short`
//! values of the query's descriptor (as the localizer reads such a level). So a query extracted
//! as before matches the cut level with no change anywhere. Levels of N short dimensions or
//! fewer are left as they are. A VLAD on a cut level is learned again in the new basis (its
//! centroids and every image's VLAD), and an image index over it is built again.

#[cfg(feature = "colmap")]
use {
    super::basis::{Basis, BasisFit},
    crate::format::{Error, Map, MapWriter, Retrieval, SectionKind},
    crate::progress::Silent,
    crate::vector::{l2_normalise, widen_f16},
    serde_json::json,
};

/// What cutting one level did.
#[derive(Debug, Clone, PartialEq)]
pub struct ShortBasisSummary {
    /// The level.
    pub level: u16,
    /// Its points.
    pub points: usize,
    /// `dim_short` before.
    pub dims_before: usize,
    /// Dimensions kept.
    pub dims: usize,
    /// Share of the short rows' energy (`Σ‖x‖²`, rows unit) the kept dimensions hold.
    pub energy_kept: f64,
    /// Whether the map's VLAD was on this level and learned again.
    pub vlad_relearned: bool,
    /// Whether the slice's VLAD was on this level and could not be learned again (fewer
    /// described points than its centroids, or no visibility), so it was dropped.
    pub vlad_dropped: bool,
    /// (1.3) Whether the image index over that VLAD was dropped: it could not be built again
    /// from the new rows (k-means found fewer distinct rows than its lists), or the VLAD was.
    pub index_dropped: bool,
}

#[cfg(feature = "colmap")]
/// How the level is stored, in words (recorded in its metadata).
fn rule(dims_before: usize, dims: usize, composed: bool) -> String {
    let from = if composed {
        "the level's stored short block, itself the first rows of its projection"
    } else {
        "the level's short block, the first dim_short values of the extractor's descriptor"
    };
    format!(
        "{from}, each row L2-normalised, in the uncentred PCA basis of those rows (eigenvectors of E[x x^T], decreasing eigenvalue, largest component positive), the leading {dims} of {dims_before} coordinates, L2-normalised; level_projection = those basis rows composed with what the level took before"
    )
}

#[cfg(feature = "colmap")]
/// Moves the `short` block of each level of `levels` in `writer` (a `--short` slice of
/// `map`) with more than `dims` short dimensions into its own PCA basis, cut to `dims`.
/// Memory: a cut level's new rows (`points × dims` f16) and a `dim_short²` moment matrix; with
/// a VLAD on a cut level, its leading dims again (f32) and one index per visibility entry.
pub fn cut_short(
    map: &Map<'_>,
    writer: &mut MapWriter<'_>,
    levels: &[u16],
    dims: usize,
) -> Result<Vec<ShortBasisSummary>, Error> {
    let mut summaries = Vec::with_capacity(levels.len());
    let mut relearn = None;
    if dims == 0 {
        return Err(Error::invalid("--short-dims 0: keep at least 1 dimension"));
    }
    for &id in levels {
        let level = map.level(id)?;
        let bad = |what: String| Error::invalid(format!("--short-dims {dims}: level {id} {what}"));
        if level.is_pq() {
            return Err(bad("is product-quantised".into()));
        }
        if !level.has_descriptors() {
            return Err(bad("has no descriptors".into()));
        }
        let ds = level.dim_short();
        if ds <= dims {
            continue;
        }
        let short = level.desc_short()?;
        let n = level.len();
        if short.len() != n * ds {
            return Err(bad(format!(
                "stores {} short values for {n} points x {ds} dimensions",
                short.len()
            )));
        }
        // The rows as matching sees them: unit, and a non-finite one (the format does not
        // check values) a zero row, never a NaN in the basis.
        let unit_row = |r: usize, out: &mut [f32]| {
            widen_f16(&short[r * ds..(r + 1) * ds], out);
            if out.iter().any(|v| !v.is_finite()) {
                out.fill(0.0);
            }
            l2_normalise(out);
        };
        let mut row = vec![0.0f32; ds];
        let mut fit = BasisFit::new(ds);
        for r in 0..n {
            unit_row(r, &mut row);
            fit.add(&row);
        }
        let basis: Basis = fit.finish();
        // Straight to the stored f16 rows: no f32 copy of the level.
        let mut cut = vec![half::f16::ZERO; n * dims];
        let mut projected = vec![0.0f32; dims];
        for (r, out) in cut.chunks_exact_mut(dims).enumerate() {
            unit_row(r, &mut row);
            basis.project_leading_row(&row, &mut projected);
            for (o, &v) in out.iter_mut().zip(&projected) {
                *o = half::f16::from_f32(v);
            }
        }
        // What the level took from a query's descriptor before: the first `ds` rows of its
        // projection, or the first `ds` values (the extractor's basis).
        let before = level.projection()?;
        let (projection, d_in) = match (&before, level.projection_input_dim()) {
            (Some(p), Some(d_in)) => {
                let rows = p.get(..ds * d_in).ok_or_else(|| {
                    bad(format!(
                        "has a projection of fewer than {ds} x {d_in} values"
                    ))
                })?;
                (
                    compose(&basis.rows[..dims * ds], rows, dims, ds, d_in),
                    d_in,
                )
            }
            _ => {
                let d_in = level.dim_full();
                let mut p = vec![0.0f32; dims * d_in];
                for (out, b) in p.chunks_exact_mut(d_in).zip(basis.rows.chunks_exact(ds)) {
                    out[..ds].copy_from_slice(b);
                }
                (p, d_in)
            }
        };
        let energy_kept = basis.energy_kept(dims);
        let info = writer
            .metadata_mut()
            .levels
            .iter_mut()
            .find(|l| l.level == id)
            .ok_or_else(|| bad("is not in the slice".into()))?;
        info.extra.insert(
            "short_basis".into(),
            json!({
                "dims_before": ds,
                "dims": dims,
                "energy_kept": energy_kept,
                "rule": rule(ds, dims, before.is_some()),
            }),
        );
        info.extra.insert("basis".into(), json!("uncentred pca"));
        // The spec's meaning: the share of the level basis' energy `short` holds, all of it
        // now that `short` is the whole descriptor (`short_basis.energy_kept` says the cut's).
        info.extra.insert("variance_short".into(), json!(1.0));
        info.extra.remove("full_layout");
        // A VLAD on the level is learned again from the rows as stored (f16): their leading
        // dims, as many as the old codebook's (from the section table) and at most `dims`.
        let vlad = map
            .find(SectionKind::LevelVladCentroids, Some(id))
            .filter(|_| writer.has_vlad())
            .map(|s| {
                let vlad_dims = (s.cols() as usize).clamp(1, dims);
                let mut rows = vec![0.0f32; n * vlad_dims];
                for (out, src) in rows.chunks_exact_mut(vlad_dims).zip(cut.chunks_exact(dims)) {
                    widen_f16(&src[..vlad_dims], out);
                    l2_normalise(out);
                }
                (s.rows() as usize, vlad_dims, rows)
            });
        writer.set_level_short(id, dims, cut, d_in, projection)?;
        if let Some(vlad) = vlad {
            relearn = Some((summaries.len(), vlad));
        }
        summaries.push(ShortBasisSummary {
            level: id,
            points: n,
            dims_before: ds,
            dims,
            energy_kept,
            vlad_relearned: false,
            vlad_dropped: false,
            index_dropped: false,
        });
    }
    if summaries.is_empty() {
        return Err(Error::invalid(format!(
            "--short-dims {dims}: no kept level has more than {dims} short dimensions"
        )));
    }
    if let Some((at, vlad)) = relearn {
        let summary = &mut summaries[at];
        let (relearned, index_dropped) = relearn_vlad(map, writer, summary.level, vlad)?;
        summary.vlad_relearned = relearned;
        summary.vlad_dropped = !relearned;
        summary.index_dropped = index_dropped;
    }
    Ok(summaries)
}

#[cfg(feature = "colmap")]
/// `[dims × d_in]` = `b [dims × ds]` · `p [ds × d_in]`.
fn compose(b: &[f32], p: &[f32], dims: usize, ds: usize, d_in: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; dims * d_in];
    for (o, brow) in out.chunks_exact_mut(d_in).zip(b.chunks_exact(ds)) {
        for (&bk, prow) in brow.iter().zip(p.chunks_exact(d_in)) {
            for (x, &pv) in o.iter_mut().zip(prow) {
                *x += bk * pv;
            }
        }
    }
    out
}

#[cfg(feature = "colmap")]
/// The VLAD of level `id` learned again with `clusters` centroids (the old codebook's, at most
/// [`crate::vlad::MAX_CLUSTERS`]) over `rows` (`[points × vlad_dims]`: the cut rows' leading
/// dims, unit), over the map's visibility (a slice keeps every image and the
/// points of every kept level, so each image sees the same described points); then the image
/// index over it, if the slice had one, built again with as many lists. Returns (relearned,
/// index dropped); not relearned, the VLAD is dropped and retrieval falls back to the global
/// descriptors, if any.
fn relearn_vlad(
    map: &Map<'_>,
    writer: &mut MapWriter<'_>,
    id: u16,
    (clusters, vlad_dims, rows): (usize, usize, Vec<f32>),
) -> Result<(bool, bool), Error> {
    // An index over the VLAD in the slice: its lists (from the section table) and each
    // image's neighbours, when they are as wide as the builder makes them (else the index is
    // built again without them, as k-means lists).
    let index_lists = match writer.metadata().image_index.as_ref().and_then(|i| i.of()) {
        Some(Retrieval::Vlad) => {
            let lists = map
                .find(SectionKind::ImageIndexCentroids, None)
                .map_or(0, |s| s.rows() as usize);
            let neighbours = match map.find(SectionKind::ImageIndexNeighbours, None) {
                Some(s) if s.cols() as usize == super::retrieval::INDEX_NEIGHBOURS => {
                    Some(map.section_array::<u32>(s)?.into_owned())
                }
                _ => None,
            };
            // Read as they are stored: one naming no image of the map is not followed.
            let images = map.n_images();
            let neighbours = neighbours.filter(|rows| {
                rows.iter()
                    .all(|&n| n == crate::format::NO_NEIGHBOUR || u64::from(n) < images)
            });
            Some((lists, neighbours))
        }
        _ => None,
    };
    // The old VLAD (and an index over it) goes first; the preference stays if it is relearned.
    let preference = writer.metadata().retrieval.clone();
    writer.drop_vlad();
    let Some(visibility) = map.visibility_points()? else {
        return Ok((false, index_lists.is_some()));
    };
    // Each visibility entry as a row of the level (`u32::MAX`, skipped: a point not on it).
    let points = map.level(id)?.points()?;
    let rows_seen: Vec<u32> = visibility
        .points
        .iter()
        .map(|p| points.binary_search(p).map_or(u32::MAX, |r| r as u32))
        .collect();
    let stored = super::retrieval::add_vlad(
        writer,
        id,
        &rows,
        vlad_dims,
        clusters.min(crate::vlad::MAX_CLUSTERS),
        "the level's points, after slice --short-dims",
        (&visibility.offsets, &rows_seen),
        &Silent,
    )?;
    if stored.is_none() {
        return Ok((false, index_lists.is_some()));
    }
    writer.metadata_mut().retrieval = preference;
    // The index is over what the map retrieves with: built again only where that is the VLAD.
    let index_dropped = match index_lists {
        Some(_) if writer.metadata().retrieval() != Some(Retrieval::Vlad) => true,
        Some((lists, neighbours)) => {
            let index =
                super::retrieval::add_image_index(writer, Some(lists), neighbours, &Silent)?;
            !index.is_some_and(|i| i.stored)
        }
        None => false,
    };
    Ok((true, index_dropped))
}

#[cfg(all(test, feature = "colmap"))]
mod tests {
    use super::*;
    use crate::format::{CameraInfo, Descriptors, LevelInfo, SliceOptions};
    use crate::geometry::SplitMix64;

    const POINTS: usize = 300;
    const IMAGES: usize = 12;

    /// Unit rows of `dims` whose energy grows with the dimension (`rising`) or falls with it,
    /// so a PCA has an order, and a rising one is not a prefix.
    fn rows(n: usize, dims: usize, seed: u64, rising: bool) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        let mut v: Vec<f32> = (0..n * dims)
            .map(|i| {
                let scale = (1 + i % dims) as f32;
                let x = rng.next_f64() as f32 - 0.5;
                if rising {
                    x * scale
                } else {
                    x / scale
                }
            })
            .collect();
        v.chunks_exact_mut(dims).for_each(l2_normalise);
        v
    }

    fn info(level: u16, full: u32, short: u32) -> LevelInfo {
        LevelInfo {
            level,
            stride: 8.0,
            descriptor: "test".into(),
            dim_full: full,
            dim_short: short,
            normalization: "l2".into(),
            extra: Default::default(),
        }
    }

    /// Level 1's projection (16 × 20): row k is ±1 at column `(7 k) mod 20`, orthonormal.
    fn signed_permutation() -> Vec<f32> {
        let mut p = vec![0.0f32; 16 * 20];
        for k in 0..16 {
            p[k * 20 + (7 * k) % 20] = if k % 3 == 0 { -1.0 } else { 1.0 };
        }
        p
    }

    /// The points of level 0 (`p % 3 != 0`) and of level 1 (`p % 5 != 0`); level 2 holds
    /// every point, so a slice of levels 0 and 1 drops those with `p % 15 == 0`.
    fn level_points(level: u32) -> Vec<u32> {
        let modulus = [3, 5, 1][level as usize];
        (0..POINTS as u32)
            .filter(|p| modulus == 1 || p % modulus != 0)
            .collect()
    }

    /// Level 0: 24 dims (8 short) in the extractor's basis, with the VLAD (`clusters` × 8),
    /// with an image index of 3 lists over it (`index`), and global descriptors, retrieval
    /// preferring the VLAD; level 1: 16 dims (8 short) behind [`signed_permutation`]; level
    /// 2: 8 dims (4 short); 12 images, each seeing 200 of the 300 points. Returns the map and
    /// level 0's rows.
    fn map_bytes(clusters: usize, index: bool) -> (Vec<u8>, Vec<f32>) {
        let mut w = MapWriter::default();
        w.add_camera(CameraInfo {
            id: Some(1),
            model: "PINHOLE".into(),
            width: 640,
            height: 480,
            params: vec![500.0, 500.0, 320.0, 240.0],
        });
        let positions: Vec<[f64; 3]> = (0..POINTS).map(|p| [p as f64, 1.0, 5.0]).collect();
        w.set_points_world(&positions);
        let names: Vec<String> = (0..IMAGES).map(|i| format!("{i}.jpg")).collect();
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        let poses = [[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]; IMAGES];
        w.set_images(&names, &[0; IMAGES], &poses, None).unwrap();
        let offsets: Vec<u64> = (0..=IMAGES as u64).map(|i| i * 200).collect();
        let vis: Vec<u32> = (0..IMAGES as u32)
            .flat_map(|i| (0..200).map(move |k| (i * 25 + k) % POINTS as u32))
            .collect();
        w.set_visibility(&offsets, &vis, None).unwrap();
        let points: Vec<Vec<u32>> = (0..3).map(level_points).collect();
        let level0 = rows(points[0].len(), 24, 1, true);
        w.add_level(
            info(0, 24, 8),
            &points[0],
            Some(Descriptors::F32(&level0)),
            true,
        )
        .unwrap();
        let level1 = rows(points[1].len(), 16, 2, false);
        w.add_level(
            info(1, 16, 8),
            &points[1],
            Some(Descriptors::F32(&level1)),
            true,
        )
        .unwrap();
        let level2 = rows(POINTS, 8, 7, false);
        w.add_level(
            info(2, 8, 4),
            &points[2],
            Some(Descriptors::F32(&level2)),
            true,
        )
        .unwrap();
        w.set_level_projection(1, 20, signed_permutation()).unwrap();
        let codebook = rows(clusters, 8, 4, false);
        w.set_vlad(0, 8, codebook, &rows(IMAGES, clusters * 8, 5, false))
            .unwrap();
        w.set_image_global(8, &rows(IMAGES, 8, 6, false)).unwrap();
        w.metadata_mut().retrieval = Some(Retrieval::Vlad.name().to_string());
        if index {
            let built = super::super::retrieval::add_image_index(&mut w, Some(3), None, &Silent)
                .unwrap()
                .unwrap();
            assert!(built.stored);
        }
        (w.to_bytes().unwrap(), level0)
    }

    fn cut(map: &Map<'_>, dims: usize) -> Result<(Vec<u8>, Vec<ShortBasisSummary>), Error> {
        let options = SliceOptions {
            levels: vec![0, 1],
            short: true,
            ..Default::default()
        };
        let (mut writer, _) = crate::format::slice(map, &options)?;
        let summaries = cut_short(map, &mut writer, &[0, 1], dims)?;
        Ok((writer.to_bytes()?, summaries))
    }

    /// The query's descriptor projected as the localizer does (the stored projection's rows,
    /// then unit), `[dims]`.
    fn project(p: &[f32], d_in: usize, query: &[f32]) -> Vec<f32> {
        let mut q: Vec<f32> = p
            .chunks_exact(d_in)
            .map(|row| crate::vector::dot(row, query))
            .collect();
        l2_normalise(&mut q);
        q
    }

    fn stored_row(level: &crate::format::Level<'_>, r: usize) -> Vec<f32> {
        let (short, ds) = (level.desc_short().unwrap(), level.dim_short());
        let mut row = vec![0.0f32; ds];
        widen_f16(&short[r * ds..(r + 1) * ds], &mut row);
        row
    }

    /// On both levels (the extractor's basis, and behind a projection) a query that matched
    /// a map row exactly before lands on it after the cut; the kept dims hold far more energy
    /// than the same number of the old prefix; the VLAD is learned again at the cut's dims,
    /// and its image index with as many lists; the preference stays.
    #[test]
    fn a_query_lands_on_its_row_and_retrieval_follows_the_cut() {
        let (bytes, level0) = map_bytes(4, true);
        let map = Map::from_bytes(&bytes).unwrap();
        let (out, summaries) = cut(&map, 4).unwrap();
        let sliced = Map::from_bytes(&out).unwrap();
        sliced.verify().unwrap();
        // Level 0's energy rises with the dimension: its first 4 short dims hold a small
        // share, the basis' leading 4 most of it.
        let prefix: f64 = level0
            .chunks_exact(24)
            .map(|r| {
                let short = &r[..8];
                let all: f32 = short.iter().map(|v| v * v).sum();
                f64::from(short[..4].iter().map(|v| v * v).sum::<f32>() / all)
            })
            .sum::<f64>()
            / POINTS as f64;
        assert!(
            summaries[0].energy_kept > prefix + 0.3,
            "{prefix} {summaries:?}"
        );
        assert!(summaries.iter().all(|s| (s.dims_before, s.dims) == (8, 4)));
        let (l0, l1) = (sliced.level(0).unwrap(), sliced.level(1).unwrap());
        assert_eq!(
            (l0.dim_short(), l0.dim_full(), l0.has_rest()),
            (4, 4, false)
        );
        assert_eq!(
            (l0.projection_input_dim(), l1.projection_input_dim()),
            (Some(24), Some(20))
        );
        // Level 0: the query is the extractor's descriptor itself.
        let p0 = l0.projection().unwrap().unwrap();
        // Level 1: a query whose projection (a signed permutation) gives the old short row.
        let (old1, p1) = (map.level(1).unwrap(), l1.projection().unwrap().unwrap());
        let before = signed_permutation();
        for r in [0, 7, level_points(0).len() - 1] {
            let mut query1 = [0.0f32; 20];
            for (k, &v) in stored_row(&old1, r).iter().enumerate() {
                let row = &before[k * 20..(k + 1) * 20];
                for (x, &p) in query1.iter_mut().zip(row) {
                    *x += p * v;
                }
            }
            for (p, d_in, query, level) in [
                (&p0, 24, &level0[r * 24..(r + 1) * 24], &l0),
                (&p1, 20, &query1[..], &l1),
            ] {
                let (q, row) = (project(p, d_in, query), stored_row(level, r));
                let worst = q
                    .iter()
                    .zip(&row)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f32::max);
                assert!(worst < 2e-3, "row {r}: {q:?} vs {row:?}");
            }
        }
        assert!(summaries[0].vlad_relearned && !summaries[0].index_dropped);
        let vlad = sliced.vlad().unwrap().unwrap();
        assert_eq!((vlad.level, vlad.clusters, vlad.dims), (0, 4, 4));
        // Each image's VLAD is its own over the slice's remapped points and cut rows (the
        // relearning read the map's: the same described points, by row).
        assert_eq!(sliced.n_points(), POINTS as u64 - POINTS as u64 / 15);
        let mut by_point = vec![0.0f32; sliced.n_points() as usize * 4];
        for (r, &p) in l0.points().unwrap().iter().enumerate() {
            let out = &mut by_point[p as usize * 4..(p as usize + 1) * 4];
            out.copy_from_slice(&stored_row(&l0, r));
            l2_normalise(out);
        }
        let codebook = crate::vlad::Codebook::new(vlad.centroids.to_vec(), 4).unwrap();
        let visibility = sliced.visibility_points().unwrap().unwrap();
        let expected = codebook.image_vlads(&by_point, &visibility.offsets, &visibility.points);
        assert_eq!(expected.len(), vlad.images.len());
        for (a, b) in expected.iter().zip(vlad.images.iter()) {
            assert!((a - b.to_f32()).abs() < 2e-3, "{a} vs {b}");
        }
        assert!(expected.iter().any(|&v| v != 0.0));
        assert_eq!(sliced.metadata().retrieval(), Some(Retrieval::Vlad));
        let index = sliced.image_index().unwrap().unwrap();
        assert_eq!(
            (index.of, index.offsets.len() - 1, index.width),
            (Retrieval::Vlad, 3, 16)
        );
        // The same bytes again (seeded k-means, ordered sums).
        assert_eq!(cut(&map, 4).unwrap().0, out);
    }

    /// A VLAD of more centroids than the cut level has points cannot be learned again: it goes,
    /// with its index, and retrieval falls back to the global descriptors.
    #[test]
    fn a_vlad_that_cannot_be_learned_again_goes_and_global_retrieval_stays() {
        let (bytes, _) = map_bytes(POINTS + 1, true);
        let map = Map::from_bytes(&bytes).unwrap();
        let (out, summaries) = cut(&map, 4).unwrap();
        assert!(
            summaries[0].vlad_dropped && summaries[0].index_dropped,
            "{summaries:?}"
        );
        let sliced = Map::from_bytes(&out).unwrap();
        sliced.verify().unwrap();
        assert!(sliced.vlad().unwrap().is_none());
        assert!(sliced.image_index().unwrap().is_none());
        assert!(sliced
            .metadata()
            .level(0)
            .unwrap()
            .extra
            .get("vlad")
            .is_none());
        assert_eq!(sliced.metadata().retrieval(), Some(Retrieval::Global));
    }

    #[test]
    fn requests_that_cannot_be_met_are_errors() {
        let (bytes, _) = map_bytes(4, false);
        let map = Map::from_bytes(&bytes).unwrap();
        // Levels of `dims` short dims or fewer are left as they are; none left to cut is an error.
        for (dims, why) in [(0, "at least 1"), (8, "no kept level has more than 8")] {
            let err = cut(&map, dims).unwrap_err().to_string();
            assert!(err.contains(why), "{err}");
        }
        let options = SliceOptions {
            levels: vec![0],
            ..Default::default()
        };
        let err = super::super::pq::slice_encoded(&map, &options, Some(4), None)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("needs --short"), "{err}");
    }
}
