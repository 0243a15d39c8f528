//! `slice --short --short-dims N`: each kept level's `short` block moved into an uncentred PCA
//! basis of its own rows ([`Basis`], as `convert` stores SIFT's levels) and cut to the leading
//! N dimensions, with the projection that takes a query's descriptor there.
//!
//! Why: a level's short descriptor is whatever its extractor gives — an SFP level's is the
//! network's own (64 dimensions on level 2), with its energy spread evenly, so no prefix of it
//! is a good short descriptor. Fitted to the level's own rows, the basis puts the most energy
//! any N dimensions can hold in the first N, which is what SIFT's maps store (32 of 128).
//!
//! The stored level becomes `dim_short = dim_full = N`, `rest` absent, and `level_projection`
//! `[N × d_in]` = the basis' leading rows composed with what the level took before: its own
//! projection's first `dim_short` rows, or, in the extractor's basis, the first `dim_short`
//! values of the query's descriptor (as the localizer reads such a level). So a query extracted
//! as before matches the cut level with no change anywhere. A VLAD on such a level is learned
//! again in the new basis (its centroids and every image's VLAD): the old one would aggregate
//! dimensions the level no longer stores.

use super::basis::{Basis, BasisFit};
use crate::format::{Error, Map, MapWriter};
use crate::vector::{l2_normalise, widen_f16};
use crate::vlad::Codebook;
use serde_json::json;

/// The seed of a re-learned VLAD codebook's k-means: fixed, so a slice is the same bytes.
const VLAD_SEED: u64 = 0x5f9_1a1;

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
    /// Whether the slice's VLAD was on this level and could not be learned again (too few
    /// described points or no visibility), so it was dropped.
    pub vlad_dropped: bool,
    /// (1.3) Whether an image index over the VLAD was dropped with the rows it indexed
    /// (retrieval then ranks every image).
    pub index_dropped: bool,
}

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

/// Moves the `short` block of each level of `levels` in `writer` (a `--short` slice of
/// `map`) into its own PCA basis, cut to `dims` dimensions. Memory: the level's new rows
/// (`points × dims` f32) and a `dim_short²` moment matrix; with a VLAD on a cut level, one
/// row of `dims` per map point and the slice encoded once more in memory, to read its
/// visibility back.
pub fn cut_short(
    map: &Map<'_>,
    writer: &mut MapWriter<'_>,
    levels: &[u16],
    dims: usize,
) -> Result<Vec<ShortBasisSummary>, Error> {
    let mut summaries = Vec::with_capacity(levels.len());
    let mut relearn = None;
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
        if dims == 0 || dims > ds {
            return Err(bad(format!(
                "has {ds} short dimensions: keep 1 to {ds} of them"
            )));
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
        let mut cut = vec![0.0f32; n * dims];
        for (r, out) in cut.chunks_exact_mut(dims).enumerate() {
            unit_row(r, &mut row);
            basis.project_leading_row(&row, out);
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
        let variance_short = info
            .extra
            .get("variance_short")
            .and_then(|v| v.as_f64())
            .map(|v| v * energy_kept);
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
        if let Some(v) = variance_short {
            info.extra.insert("variance_short".into(), json!(v));
        }
        info.extra.remove("full_layout");
        writer.set_level_short(id, dims, &cut, d_in, projection)?;
        if map.vlad_level() == Some(id) && writer.has_vlad() {
            relearn = Some(summaries.len());
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
    if let Some(at) = relearn {
        // The old VLAD goes first: its codebook's dims may exceed the cut level's, and the
        // slice is read back below. The map's retrieval preference stays if it is relearned.
        let summary = &mut summaries[at];
        let preference = writer.metadata().retrieval.clone();
        summary.index_dropped = writer.drop_image_index_of(crate::format::Retrieval::Vlad);
        writer.drop_vlad();
        summary.vlad_relearned = relearn_vlad(map, writer, summary.level)?;
        summary.vlad_dropped = !summary.vlad_relearned;
        if summary.vlad_relearned {
            writer.metadata_mut().retrieval = preference;
        }
    }
    Ok(summaries)
}

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

/// The VLAD of level `id` learned again from the slice's own rows (the cut ones) and
/// visibility, with the old codebook's clusters and as many of its dims as the level keeps.
/// `false`: it could not be (too few described points for the clusters, no visibility).
fn relearn_vlad(map: &Map<'_>, writer: &mut MapWriter<'_>, id: u16) -> Result<bool, Error> {
    let Some(old) = map.vlad()? else {
        return Ok(false);
    };
    let (clusters, old_dims) = (old.clusters, old.dims);
    // The slice read back, in memory and raw: its point indices and visibility are the
    // remapped ones the VLAD must aggregate over.
    let (codec, zstd_level) = writer.codec();
    writer.set_codec(crate::format::Codec::Raw, zstd_level);
    let bytes = writer.to_bytes();
    writer.set_codec(codec, zstd_level);
    let bytes = bytes?;
    let sliced = Map::from_bytes(&bytes)?;
    let level = sliced.level(id)?;
    let dims = old_dims.min(level.dim_short()).max(1);
    let ds = level.dim_short();
    let short = level.desc_short()?;
    let points = level.points()?;
    let mut rows = vec![0.0f32; sliced.n_points() as usize * dims];
    for (r, &p) in points.iter().enumerate() {
        let out = &mut rows[p as usize * dims..(p as usize + 1) * dims];
        widen_f16(&short[r * ds..r * ds + dims], out);
        l2_normalise(out);
    }
    let Some(visibility) = sliced.visibility_points()? else {
        return Ok(false);
    };
    let Some(codebook) = Codebook::train(&rows, dims, clusters, VLAD_SEED) else {
        return Ok(false);
    };
    let images = codebook.image_vlads(&rows, &visibility.offsets, &visibility.points);
    drop(sliced);
    if let Some(info) = writer
        .metadata_mut()
        .levels
        .iter_mut()
        .find(|l| l.level == id)
    {
        info.extra.insert(
            "vlad".into(),
            json!({
                "clusters": codebook.clusters(),
                "dims": dims,
                "rule": crate::vlad::rule(),
                "points": "the level's points, learned again after slice --short-dims",
            }),
        );
    }
    writer.set_vlad(id, dims, codebook.into_centroids(), &images)?;
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::{CameraInfo, Descriptors, LevelInfo, Retrieval, SliceOptions};
    use crate::geometry::SplitMix64;

    const POINTS: usize = 300;
    const IMAGES: usize = 3;

    /// Unit rows of `dims` whose energy falls with the dimension, so a PCA has an order.
    fn rows(n: usize, dims: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        let mut v: Vec<f32> = (0..n * dims)
            .map(|i| (rng.next_f64() as f32 - 0.5) / (1 + i % dims) as f32)
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

    /// Level 0: 24 dims (8 short) in the extractor's basis, with the VLAD (4 × 8) and global
    /// descriptors, retrieval preferring the VLAD; level 1: 16 dims (8 short) behind a
    /// projection from 20 input dims.
    fn map_bytes() -> (Vec<u8>, Vec<f32>, Vec<f32>) {
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
        let poses = [[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]; IMAGES];
        w.set_images(&["a", "b", "c"], &[0; IMAGES], &poses, None)
            .unwrap();
        let offsets: Vec<u64> = (0..=IMAGES as u64).map(|i| i * 200).collect();
        let vis: Vec<u32> = (0..IMAGES as u32)
            .flat_map(|i| (0..200).map(move |k| (i * 50 + k) % POINTS as u32))
            .collect();
        w.set_visibility(&offsets, &vis, None).unwrap();
        let all: Vec<u32> = (0..POINTS as u32).collect();
        let level0 = rows(POINTS, 24, 1);
        w.add_level(info(0, 24, 8), &all, Some(Descriptors::F32(&level0)), true)
            .unwrap();
        let level1 = rows(POINTS, 16, 2);
        w.add_level(info(1, 16, 8), &all, Some(Descriptors::F32(&level1)), true)
            .unwrap();
        let projection = rows(16, 20, 3);
        w.set_level_projection(1, 20, projection.clone()).unwrap();
        let codebook = rows(4, 8, 4);
        w.set_vlad(0, 8, codebook, &rows(IMAGES, 32, 5)).unwrap();
        w.set_image_global(8, &rows(IMAGES, 8, 6)).unwrap();
        w.metadata_mut().retrieval = Some(Retrieval::Vlad.name().to_string());
        (w.to_bytes().unwrap(), level0, projection)
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

    /// A query's descriptor, projected as the localizer does (the stored projection's rows,
    /// then unit), lands on the level's stored row; the kept dims hold more than their share
    /// of the energy; the VLAD is learned again at the cut's dims and the preference stays.
    #[test]
    fn a_query_projected_lands_on_the_stored_row_and_the_vlad_follows() {
        let (bytes, level0, _) = map_bytes();
        let map = Map::from_bytes(&bytes).unwrap();
        let (out, summaries) = cut(&map, 4).unwrap();
        let sliced = Map::from_bytes(&out).unwrap();
        sliced.verify().unwrap();
        for s in &summaries {
            assert_eq!((s.dims_before, s.dims), (8, 4));
            assert!(s.energy_kept > 0.5 && s.energy_kept <= 1.0, "{s:?}");
        }
        assert!(summaries[0].vlad_relearned && !summaries[1].vlad_relearned);
        let l0 = sliced.level(0).unwrap();
        assert_eq!(
            (l0.dim_short(), l0.dim_full(), l0.has_rest()),
            (4, 4, false)
        );
        assert_eq!(l0.projection_input_dim(), Some(24));
        assert_eq!(sliced.level(1).unwrap().projection_input_dim(), Some(20));
        let p = l0.projection().unwrap().unwrap();
        let stored = l0.desc_short().unwrap();
        for r in [0, 7, 299] {
            let query = &level0[r * 24..(r + 1) * 24];
            let mut projected: Vec<f32> = p
                .chunks_exact(24)
                .map(|row| crate::vector::dot(row, query))
                .collect();
            l2_normalise(&mut projected);
            let mut row = [0.0f32; 4];
            widen_f16(&stored[r * 4..(r + 1) * 4], &mut row);
            for (a, b) in projected.iter().zip(&row) {
                assert!((a - b).abs() < 2e-3, "row {r}: {projected:?} vs {row:?}");
            }
        }
        let vlad = sliced.vlad().unwrap().unwrap();
        assert_eq!((vlad.level, vlad.clusters, vlad.dims), (0, 4, 4));
        assert_eq!(sliced.metadata().retrieval(), Some(Retrieval::Vlad));
        // The same bytes again (seeded k-means, ordered sums).
        assert_eq!(cut(&map, 4).unwrap().0, out);
    }

    /// Level 1 sits behind a projection, which the cut composes: with all 8 short dims kept
    /// the new basis is a rotation of the old, so every matching score (the cosine of a
    /// query's projection and a stored row) is what it was.
    #[test]
    fn a_level_behind_a_projection_keeps_its_matching_scores() {
        let (bytes, _, before) = map_bytes();
        let map = Map::from_bytes(&bytes).unwrap();
        let (out, _) = cut(&map, 8).unwrap();
        let sliced = Map::from_bytes(&out).unwrap();
        let (old, new) = (map.level(1).unwrap(), sliced.level(1).unwrap());
        let after = new.projection().unwrap().unwrap();
        assert_eq!(after.len(), 8 * 20);
        let scores = |p: &[f32], stored: &[half::f16], x: &[f32]| -> Vec<f32> {
            let mut q: Vec<f32> = p
                .chunks_exact(20)
                .take(8)
                .map(|r| crate::vector::dot(r, x))
                .collect();
            l2_normalise(&mut q);
            stored
                .chunks_exact(8)
                .map(|s| {
                    let mut row = [0.0f32; 8];
                    widen_f16(s, &mut row);
                    l2_normalise(&mut row);
                    crate::vector::dot(&q, &row)
                })
                .collect()
        };
        let (old_short, new_short) = (old.desc_short().unwrap(), new.desc_short().unwrap());
        for x in rows(5, 20, 9).chunks_exact(20) {
            let a = scores(&before, &old_short, x);
            let b = scores(&after, &new_short, x);
            let worst = a
                .iter()
                .zip(&b)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(worst < 3e-3, "scores moved by {worst}");
        }
    }

    #[test]
    fn requests_that_cannot_be_met_are_errors() {
        let (bytes, _, _) = map_bytes();
        let map = Map::from_bytes(&bytes).unwrap();
        for (dims, why) in [(0, "keep 1 to 8"), (9, "has 8 short dimensions")] {
            let err = cut(&map, dims).unwrap_err().to_string();
            assert!(err.contains(why), "{err}");
        }
        let options = SliceOptions {
            levels: vec![0],
            ..Default::default()
        };
        let err = super::super::pq::slice_quantised(&map, &options, Some(4), None)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("needs --short"), "{err}");
    }
}
