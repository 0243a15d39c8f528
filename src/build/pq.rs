//! Product quantisation of a map's levels (format 1.1, `slice --pq`, `convert --pq`): each
//! level's descriptors, L2-normalised over the dimensions kept, are cut into `M` subspaces and
//! each subvector replaced by the index of the nearest of `K = 256` centroids learned for its
//! subspace by k-means — one byte per subspace instead of two per dimension. The localizer
//! matches such a level by asymmetric distances (`localize`: the query stays exact, the map
//! side is looked up in per-query tables).

use crate::format::{Error, Map, MapWriter};
use crate::geometry::SplitMix64;
use crate::kmeans::KMeans;
use crate::vector::{l2_normalise, Nearest};

/// Centroids per subspace at most: every value of a one-byte code.
pub(crate) const CENTROIDS: usize = 256;
/// Level points per centroid at least: a small level gets the largest power of two of
/// centroids with this many points each (a level of 345 points 32, one of 2,048 or more 256),
/// so its codebook stays small beside its codes and every centroid is learned from data.
const POINTS_PER_CENTROID: usize = 8;
/// Rows k-means sees per subspace at most (64 per centroid): bounds training time whatever
/// the level's size (≤ 2 s per level on one core).
const MAX_TRAIN: usize = 16_384;
const ITERATIONS: usize = 20;
/// Rows decoded and encoded together by [`quantise_levels`].
const ENCODE_BATCH: usize = 256;
const SEED: u64 = 0x5051_5346_504d_4150;
/// Subspace energies at most this far apart count as balanced ([`dimension_order`]).
const BALANCED: f64 = 4.0;

/// How to quantise.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PqOptions {
    /// Subspaces `M`: bytes per point. Must divide the quantised dimensions.
    pub subspaces: usize,
    /// Quantise only the `short` block (the `rest` is dropped, as `slice --short` does).
    pub short: bool,
}

/// What quantising one level did.
#[derive(Debug, Clone, PartialEq)]
pub struct PqLevelSummary {
    /// The level.
    pub level: u16,
    /// Points coded.
    pub points: usize,
    /// Dimensions quantised (`dim_short`, or `dim_full` with the rest).
    pub dims: usize,
    /// Codes per point (`M`).
    pub subspaces: usize,
    /// Centroids per subspace (`K`, at most 256).
    pub centroids: usize,
    /// Descriptor bytes before quantising (the f16 blocks kept).
    pub bytes_before: u64,
    /// Descriptor bytes after quantising (codes + codebook).
    pub bytes_after: u64,
    /// Mean squared distance between a unit descriptor and its reconstruction.
    pub mean_squared_error: f64,
}

/// How the codes are made, in words (recorded in each level's metadata).
pub(crate) fn rule() -> String {
    format!(
        "descriptors L2-normalised over the quantised dims; where consecutive subspaces' energies (sums of squares over the sample) are more than {BALANCED}x apart, dims sorted by decreasing energy dealt to the subspaces in snake order (level_pq_order), else in place; per subspace, k-means++ then Lloyd ({ITERATIONS} iterations at most, seeded) on a seeded sample of at most {MAX_TRAIN} rows, {CENTROIDS} centroids (fewer for small levels: at least {POINTS_PER_CENTROID} points each); each subvector coded by its nearest centroid"
    )
}

/// A product quantiser of unit rows of `dims = subspaces × sub_dims`.
#[derive(Debug, Clone)]
pub struct Quantiser {
    subspaces: usize,
    centroids: usize,
    sub_dims: usize,
    /// `[M·K × sub_dims]`: subspace m's centroid k is row `m·K + k`.
    codebook: Vec<f32>,
    nearest: Vec<Nearest>,
    /// The row dimension at each position of the quantised vector: subspace s is positions
    /// `s·sub_dims..(s + 1)·sub_dims` ([`dimension_order`]); `None` when it is the identity
    /// (as `level_pq_order` is then not written).
    order: Option<Vec<u16>>,
}

/// The order in which a row's dimensions are quantised: sorted by decreasing energy (sum of
/// squares over `rows`, f64 in row order; ties: the lower dimension), then dealt to the
/// subspaces in snake order (0, 1, …, M−1, M−1, …, 0, 0, 1, …), so every subspace gets a
/// balanced share of the strong and the weak dimensions. Position `i` of subspace `s` is
/// dimension `order[s·(dims/M) + i]`. The identity when consecutive subspaces are already
/// balanced (the largest subspace energy at most [`BALANCED`] times the smallest), or when
/// no order can change a code (one subspace, or one dimension each).
///
/// Why: in a PCA basis (SIFT levels) energy falls steeply with the dimension, so consecutive
/// subspaces give the first one most of the variance and the last ones almost none; the
/// parametric OPQ of Ge et al. (2013) balances it with a permutation. Measured (mean squared
/// error of unit rows, 256 centroids): the level-2 short SIFT maps (32 PCA dims; subspace
/// energies 47–220× apart) of South Building and KITTI 06 lose 16–27 % of it at `M` 4, 8 and
/// 16; Sacre Coeur's raw SIFT descriptors in PCA order (64 dims, `M` 8) 0.083 → 0.051, with
/// recall@1 of the exact nearest neighbour 0.19 → 0.38 (`examples/opq_check.rs` of commit
/// a95c593); OPQ's learned rotation on top changed either by under 1 %. The
/// SFP levels' energies are flat (within 1.9×) and the order changed their error by under
/// 1 %, so they keep the identity.
pub(crate) fn dimension_order(rows: &[f32], dims: usize, subspaces: usize) -> Vec<u16> {
    let identity = |dims: usize| (0..dims as u16).collect::<Vec<u16>>();
    let mut energy = vec![0.0f64; dims];
    for row in rows.chunks_exact(dims.max(1)) {
        for (e, &v) in energy.iter_mut().zip(row) {
            *e += f64::from(v) * f64::from(v);
        }
    }
    // Dimensions fit u16: the format's descriptor dimensions are at most 4,096.
    let mut by_energy: Vec<u16> = (0..dims as u16).collect();
    by_energy.sort_by(|&a, &b| {
        let (ea, eb) = (energy[usize::from(a)], energy[usize::from(b)]);
        eb.total_cmp(&ea).then(a.cmp(&b))
    });
    let m = subspaces.max(1);
    // One subspace, or one dimension each: no order changes a code.
    if m == 1 || m >= dims || dims % m != 0 {
        return identity(dims);
    }
    let in_place: Vec<f64> = energy
        .chunks_exact(dims / m)
        .map(|c| c.iter().sum())
        .collect();
    let most = in_place.iter().copied().fold(0.0f64, f64::max);
    let least = in_place.iter().copied().fold(f64::INFINITY, f64::min);
    if most <= BALANCED * least {
        return identity(dims);
    }
    let mut buckets = vec![Vec::with_capacity(dims / m); m];
    for (rank, &d) in by_energy.iter().enumerate() {
        let (round, i) = (rank / m, rank % m);
        let s = if round % 2 == 0 { i } else { m - 1 - i };
        buckets[s].push(d);
    }
    buckets.concat()
}

impl Quantiser {
    /// Learns `subspaces` codebooks of `centroids` (at most 256) from `rows` (`[n × dims]`,
    /// unit rows; a seeded sample of them is used); fewer training rows than `centroids` give
    /// one centroid per row. Errors say what is wrong with the request.
    pub fn train(
        rows: &[f32],
        dims: usize,
        subspaces: usize,
        centroids: usize,
    ) -> Result<Quantiser, String> {
        // Orders are u16 (the format's dimensions are at most 4,096).
        if dims > usize::from(u16::MAX) + 1 {
            return Err(format!("{dims} dimensions: more than an order can name"));
        }
        let order = (dims > 0).then(|| dimension_order(rows, dims, subspaces.max(1)));
        Quantiser::train_in_order(rows, dims, subspaces, centroids, order)
    }

    /// [`Quantiser::train`] with a given dimension order (`None`: the identity), for
    /// measuring what the order adds. Errors also for an order that is not a permutation of
    /// `0..dims`.
    pub(crate) fn train_in_order(
        rows: &[f32],
        dims: usize,
        subspaces: usize,
        centroids: usize,
        order: Option<Vec<u16>>,
    ) -> Result<Quantiser, String> {
        if subspaces == 0 || dims == 0 || dims % subspaces != 0 {
            return Err(format!(
                "{subspaces} subspaces do not divide {dims} dimensions"
            ));
        }
        let n = rows.len() / dims;
        if n == 0 {
            return Err("no descriptors to learn a codebook from".into());
        }
        let sub_dims = dims / subspaces;
        let centroids = centroids.clamp(1, CENTROIDS).min(n);
        if let Some(o) = &order {
            if o.len() != dims {
                return Err(format!("an order of {} dimensions for {dims}", o.len()));
            }
            crate::format::pq_check_order(o)?;
        }
        let order = order.filter(|o| !o.iter().enumerate().all(|(j, &d)| usize::from(d) == j));
        let mut codebook = Vec::with_capacity(subspaces * centroids * sub_dims);
        // The rows in quantisation order once, so each subspace's columns are contiguous.
        let mut ordered = vec![0.0f32; n * dims];
        for (out, row) in ordered.chunks_exact_mut(dims).zip(rows.chunks_exact(dims)) {
            crate::format::pq_gather(order.as_deref(), row, out);
        }
        let mut sub = vec![0.0f32; n * sub_dims];
        for m in 0..subspaces {
            for (out, row) in sub
                .chunks_exact_mut(sub_dims)
                .zip(ordered.chunks_exact(dims))
            {
                out.copy_from_slice(&row[m * sub_dims..(m + 1) * sub_dims]);
            }
            let kmeans = KMeans {
                clusters: centroids,
                max_train: MAX_TRAIN,
                iterations: ITERATIONS,
                seed: SEED ^ m as u64,
            };
            match kmeans.train(&sub, sub_dims) {
                Some(c) => codebook.extend(c),
                // Fewer non-zero subvectors than centroids: they and zeros are the codebook.
                None => {
                    let mut c: Vec<f32> = sub
                        .chunks_exact(sub_dims)
                        .filter(|r| r.iter().any(|&v| v != 0.0))
                        .take(centroids)
                        .flatten()
                        .copied()
                        .collect();
                    c.resize(centroids * sub_dims, 0.0);
                    codebook.extend(c);
                }
            }
        }
        let nearest = codebook
            .chunks_exact(centroids * sub_dims)
            .map(|c| Nearest::new(c, sub_dims))
            .collect();
        Ok(Quantiser {
            subspaces,
            centroids,
            sub_dims,
            codebook,
            nearest,
            order,
        })
    }

    /// The row dimension at each position of the quantised vector (by subspace energy),
    /// `None` for the identity.
    pub fn order(&self) -> Option<&[u16]> {
        self.order.as_deref()
    }

    /// Codes per vector (`M`).
    pub fn subspaces(&self) -> usize {
        self.subspaces
    }

    /// Centroids per subspace (`K`).
    pub fn centroids(&self) -> usize {
        self.centroids
    }

    /// `[M·K × sub_dims]`.
    pub fn codebook(&self) -> &[f32] {
        &self.codebook
    }

    /// Codes of one unit row (`dims` values) into `codes` (`subspaces` bytes); returns the
    /// squared reconstruction error.
    pub fn encode(&self, row: &[f32], codes: &mut [u8]) -> f64 {
        self.encode_rows(row, codes)
    }

    /// Codes of unit rows (`[n × dims]`) into `codes` (`[n × subspaces]`, as many rows as
    /// both hold); returns the summed squared reconstruction error. Each subspace's rows go
    /// through the nearest-centroid search together.
    pub fn encode_rows(&self, rows: &[f32], codes: &mut [u8]) -> f64 {
        let (d, m) = (self.sub_dims, self.subspaces);
        let dims = d * m;
        let mut error = 0.0f64;
        let n = (rows.len() / dims).min(codes.len() / m);
        // A batch of rows at a time in quantisation order, so each subvector is contiguous
        // and memory stays ENCODE_BATCH rows whatever `rows` holds.
        let mut ordered = vec![0.0f32; n.min(ENCODE_BATCH) * dims];
        let batches = rows[..n * dims]
            .chunks(ENCODE_BATCH * dims)
            .zip(codes[..n * m].chunks_mut(ENCODE_BATCH * m));
        for (batch, batch_codes) in batches {
            let ordered = &mut ordered[..batch.len()];
            for (out, row) in ordered.chunks_exact_mut(dims).zip(batch.chunks_exact(dims)) {
                crate::format::pq_gather(self.order.as_deref(), row, out);
            }
            for (s, nearest) in self.nearest.iter().enumerate() {
                let subvectors = ordered.chunks_exact(dims).map(|r| &r[s * d..(s + 1) * d]);
                nearest.find_each(subvectors, |i, k| {
                    batch_codes[i * m + s] = k as u8;
                    let x = &ordered[i * dims + s * d..i * dims + (s + 1) * d];
                    let at = (s * self.centroids + k) * d;
                    error += x
                        .iter()
                        .zip(&self.codebook[at..at + d])
                        .map(|(&a, &b)| f64::from(a - b).powi(2))
                        .sum::<f64>();
                });
            }
        }
        error
    }
}

/// Replaces the f16 descriptor blocks of `levels` in `writer` (a slice of `map`, see
/// [`crate::format::slice`]) by PQ codes learned from `map`'s descriptors of those levels.
/// Memory: a sample of at most 16,384 rows as f32 plus the codes; rows are decoded one at a
/// time.
pub fn quantise_levels(
    map: &Map<'_>,
    writer: &mut MapWriter<'_>,
    levels: &[u16],
    options: &PqOptions,
) -> Result<Vec<PqLevelSummary>, Error> {
    let mut summaries = Vec::with_capacity(levels.len());
    for &id in levels {
        let level = map.level(id)?;
        let bad =
            |what: String| Error::invalid(format!("--pq {}: level {id} {what}", options.subspaces));
        if level.is_pq() {
            return Err(bad("is already product-quantised".into()));
        }
        if !level.has_descriptors() {
            return Err(bad("has no descriptors".into()));
        }
        let ds = level.dim_short();
        let short = level.desc_short()?;
        let rest = if options.short {
            None
        } else {
            level.desc_rest()?
        };
        let dr = if rest.is_some() {
            level.dim_full() - ds
        } else {
            0
        };
        let dims = ds + dr;
        if dims % options.subspaces.max(1) != 0 || options.subspaces == 0 {
            return Err(bad(format!(
                "has {dims} dimensions, which {} subspaces do not divide",
                options.subspaces
            )));
        }
        let n = level.len();
        let row = |r: usize, out: &mut [f32]| {
            crate::vector::widen_f16(&short[r * ds..(r + 1) * ds], &mut out[..ds]);
            if let Some(rest) = &rest {
                crate::vector::widen_f16(&rest[r * dr..(r + 1) * dr], &mut out[ds..]);
            }
            // The format does not check descriptor values: a non-finite one makes the row a
            // zero row (no direction), never a NaN centroid.
            if out.iter().any(|v| !v.is_finite()) {
                out.fill(0.0);
            }
            l2_normalise(out);
        };
        // The training sample: a seeded partial shuffle of the rows, decoded.
        let mut rng = SplitMix64::new(SEED ^ u64::from(id));
        let take = n.min(MAX_TRAIN);
        let mut picks: Vec<usize> = (0..n).collect();
        for i in 0..take {
            let j = i + rng.below(n - i);
            picks.swap(i, j);
        }
        picks.truncate(take);
        picks.sort_unstable();
        let mut sample = vec![0.0f32; take * dims];
        for (out, &r) in sample.chunks_exact_mut(dims.max(1)).zip(&picks) {
            row(r, out);
        }
        let quantiser =
            Quantiser::train(&sample, dims, options.subspaces, centroids_for(n)).map_err(bad)?;
        let m = options.subspaces;
        let mut codes = vec![0u8; n * m];
        // Rows are decoded a batch at a time, so encoding scores several rows per pass.
        let mut batch = vec![0.0f32; ENCODE_BATCH * dims];
        let mut error = 0.0f64;
        for (b, out) in codes.chunks_mut(ENCODE_BATCH * m).enumerate() {
            let rows = out.len() / m;
            for (i, scratch) in batch.chunks_exact_mut(dims).take(rows).enumerate() {
                row(b * ENCODE_BATCH + i, scratch);
            }
            error += quantiser.encode_rows(&batch[..rows * dims], out);
        }
        let bytes_before = (n * dims * 2) as u64;
        let bytes_after = (codes.len() + quantiser.codebook.len() * 4) as u64;
        summaries.push(PqLevelSummary {
            level: id,
            points: n,
            dims,
            subspaces: m,
            centroids: quantiser.centroids,
            bytes_before,
            bytes_after,
            mean_squared_error: if n == 0 { 0.0 } else { error / n as f64 },
        });
        if let Some(info) = writer
            .metadata_mut()
            .levels
            .iter_mut()
            .find(|l| l.level == id)
        {
            info.extra.insert(
                "pq".into(),
                serde_json::json!({ "subspaces": m, "centroids": quantiser.centroids, "dims": dims, "rule": rule() }),
            );
        }
        let centroids = quantiser.centroids;
        // Quantised over `short` only, a level with a projection has those dims as its
        // descriptor: the metadata says so, and the projection keeps the rows that make them.
        // (Without a projection, `dim_full` is also the query dimension the level takes, so
        // it stays.)
        if let (Some(p), Some(d_in)) = (level.projection()?, level.projection_input_dim()) {
            if dims < level.dim_full() {
                let levels = &mut writer.metadata_mut().levels;
                if let Some(info) = levels.iter_mut().find(|l| l.level == id) {
                    info.dim_full = dims as u32;
                }
                writer.set_level_projection(id, d_in, p[..dims * d_in].to_vec())?;
            }
        }
        // The identity order is not written: such a level reads as before level_pq_order.
        writer.set_level_pq(
            id,
            m,
            centroids,
            (quantiser.codebook, codes),
            quantiser.order,
        )?;
    }
    Ok(summaries)
}

/// Centroids per subspace for a level of `n` points: the largest power of two up to 256 with
/// at least [`POINTS_PER_CENTROID`] points each (at least 1).
pub(crate) fn centroids_for(n: usize) -> usize {
    let most = (n / POINTS_PER_CENTROID).clamp(1, CENTROIDS);
    1 << most.ilog2()
}

/// A slice of a map (`format::slice`) with its kept levels optionally cut to fewer short
/// dimensions or product-quantised: what `sfpmap slice` and the Python package's `slice` write
/// and report.
pub struct SlicedMap<'m> {
    /// The slice, ready to write.
    pub writer: MapWriter<'m>,
    /// What the slice kept.
    pub summary: crate::format::SliceSummary,
    /// Each level cut to fewer short dimensions, empty without `--short-dims` (which needs the
    /// `colmap` feature).
    pub short_basis: Vec<super::short_basis::ShortBasisSummary>,
    /// Each quantised level, empty without `--pq`.
    pub pq: Vec<PqLevelSummary>,
}

/// [`crate::format::slice`], then, with `short_dims = Some(N)` (and `options.short`), every
/// kept level's short block cut to `N` dimensions of its own PCA basis
/// ([`super::short_basis`]), or, with `pq = Some(M)`, every kept level quantised into `M`
/// codes per point over what the slice keeps (`options.short`); recorded in the provenance.
/// The two do not combine (PQ codes are learned from the map's rows, not the cut ones).
pub fn slice_encoded<'m>(
    map: &'m Map<'_>,
    options: &crate::format::SliceOptions,
    short_dims: Option<usize>,
    pq: Option<usize>,
) -> Result<SlicedMap<'m>, Error> {
    if short_dims.is_some() && (pq.is_some() || !options.short) {
        return Err(Error::invalid(
            "--short-dims needs --short and does not combine with --pq",
        ));
    }
    let (mut writer, summary) = crate::format::slice(map, options)?;
    let mut levels = options.levels.clone();
    levels.sort_unstable();
    levels.dedup();
    #[cfg(feature = "colmap")]
    let short_basis = match short_dims {
        Some(dims) => {
            writer
                .metadata_mut()
                .provenance
                .parameters
                .insert("short_dims".into(), serde_json::json!(dims));
            super::short_basis::cut_short(map, &mut writer, &levels, dims)?
        }
        None => Vec::new(),
    };
    #[cfg(not(feature = "colmap"))]
    let short_basis = match short_dims {
        Some(_) => {
            return Err(Error::invalid(
                "--short-dims needs sfpmap built with the colmap feature",
            ))
        }
        None => Vec::new(),
    };
    let pq = match pq {
        Some(m) => {
            writer
                .metadata_mut()
                .provenance
                .parameters
                .insert("pq".into(), serde_json::json!(m));
            let pq_options = PqOptions {
                subspaces: m,
                short: options.short,
            };
            quantise_levels(map, &mut writer, &levels, &pq_options)?
        }
        None => Vec::new(),
    };
    Ok(SlicedMap {
        writer,
        summary,
        short_basis,
        pq,
    })
}

impl SlicedMap<'_> {
    /// The `slice --json` object, once the slice of `input` (`input_bytes`) is written to
    /// `output` (`written` bytes).
    pub fn report(
        &self,
        input: &std::path::Path,
        output: &std::path::Path,
        input_bytes: u64,
        written: u64,
    ) -> serde_json::Value {
        let s = &self.summary;
        serde_json::json!({
            "input": input.display().to_string(),
            "output": output.display().to_string(),
            "input_bytes": input_bytes,
            "output_bytes": written,
            "ratio": input_bytes as f64 / written.max(1) as f64,
            "points_before": s.points_before,
            "points_after": s.points_after,
            "sections_copied": s.sections_copied,
            "sections_rebuilt": s.sections_rebuilt,
            "skipped_sections_dropped": s.skipped_dropped,
            "position_max_error": self.writer.metadata().position_grid.map(|g| g.max_error()),
            "short_dims": self.short_basis.iter().map(|l| serde_json::json!({
                "level": l.level,
                "points": l.points,
                "dims_before": l.dims_before,
                "dims": l.dims,
                "energy_kept": l.energy_kept,
                "vlad_relearned": l.vlad_relearned,
                "vlad_dropped": l.vlad_dropped,
                "index_dropped": l.index_dropped,
            })).collect::<Vec<_>>(),
            "pq": self.pq.iter().map(|l| serde_json::json!({
                "level": l.level,
                "points": l.points,
                "dims": l.dims,
                "subspaces": l.subspaces,
                "centroids": l.centroids,
                "descriptor_bytes_before": l.bytes_before,
                "descriptor_bytes_after": l.bytes_after,
                "mean_squared_error": l.mean_squared_error,
            })).collect::<Vec<_>>(),
        })
    }
}

/// `convert --pq M`: every level with descriptors of the map `writer` holds, quantised over
/// all its dimensions. The map is encoded once in memory to read its levels back.
pub fn quantise_all(
    writer: &mut MapWriter<'_>,
    subspaces: usize,
) -> Result<Vec<PqLevelSummary>, Error> {
    // Raw: the copy is read back once, so compressing it would be wasted work.
    let (codec, level) = writer.codec();
    writer.set_codec(crate::format::Codec::Raw, level);
    let bytes = writer.to_bytes();
    writer.set_codec(codec, level);
    let bytes = bytes?;
    let map = Map::from_bytes(&bytes)?;
    let levels: Vec<u16> = map
        .levels()
        .filter(|l| l.has_descriptors())
        .map(|l| l.id())
        .collect();
    writer
        .metadata_mut()
        .provenance
        .parameters
        .insert("pq".into(), serde_json::json!(subspaces));
    let options = PqOptions {
        subspaces,
        short: false,
    };
    quantise_levels(&map, writer, &levels, &options)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit_rows(n: usize, dims: usize, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        let mut rows: Vec<f32> = (0..n * dims).map(|_| rng.next_f64() as f32 - 0.5).collect();
        rows.chunks_exact_mut(dims).for_each(l2_normalise);
        rows
    }

    #[test]
    fn codes_reconstruct_rows_better_than_chance_and_deterministically() {
        let rows = unit_rows(3000, 16, 1);
        let q = Quantiser::train(&rows, 16, 4, 256).unwrap();
        assert_eq!(q.centroids(), 256);
        assert_eq!(q.codebook().len(), 4 * 256 * 4);
        assert_eq!(
            q.codebook(),
            Quantiser::train(&rows, 16, 4, 256).unwrap().codebook()
        );
        let mut codes = vec![0u8; 4];
        let mut error = 0.0;
        for row in rows.chunks_exact(16) {
            error += q.encode(row, &mut codes);
        }
        // A unit row against a random unit row: 2 on average; 4 × 256 centroids do far better.
        let mean = error / 3000.0;
        assert!(mean < 0.5, "{mean}");
    }

    /// Dimensions by decreasing energy, dealt in snake order (the identity when one
    /// subspace or one dimension per subspace makes the order change nothing); the codes
    /// follow that order: `Pq::decode_row` of the stored codebook, codes and order gives back
    /// the encoder's reconstruction, in the row's own dimension order.
    #[test]
    fn dimensions_are_dealt_by_energy_in_snake_order() {
        // Energy grows with the dimension: 7, 6, …, 0 by decreasing energy; ties by index.
        let rows: Vec<f32> = (0..8).map(|d| d as f32).collect();
        assert_eq!(dimension_order(&rows, 8, 2), [7, 4, 3, 0, 6, 5, 2, 1]);
        assert_eq!(dimension_order(&rows, 8, 4), [7, 0, 6, 1, 5, 2, 4, 3]);
        // Balanced already (equal energies; or within 4×: 1+4 vs 9+16 is 5×, 4+9 vs 1+16 is not).
        assert_eq!(dimension_order(&[1.0; 6], 6, 3), [0, 1, 2, 3, 4, 5]);
        assert_eq!(dimension_order(&[1.0, 2.0, 3.0, 4.0], 4, 2), [3, 0, 2, 1]);
        assert_eq!(dimension_order(&[2.0, 3.0, 1.0, 4.0], 4, 2), [0, 1, 2, 3]);
        // Ties by index: 0 before 1 and 2 before 3.
        assert_eq!(dimension_order(&[3.0, 3.0, 1.0, 1.0], 4, 2), [0, 3, 1, 2]);
        for subspaces in [1, 8] {
            assert_eq!(
                dimension_order(&rows, 8, subspaces),
                [0, 1, 2, 3, 4, 5, 6, 7]
            );
        }
        // A PCA-like spectrum: row values scale down with the dimension.
        let mut rows = unit_rows(2000, 8, 3);
        for row in rows.chunks_exact_mut(8) {
            for (d, v) in row.iter_mut().enumerate() {
                *v /= (d + 1) as f32;
            }
        }
        let q = Quantiser::train(&rows, 8, 2, 16).unwrap();
        assert_eq!(q.order(), Some(&[0u16, 3, 4, 7, 1, 2, 5, 6][..]));
        let mut codes = vec![0u8; 2 * 20];
        let error = q.encode_rows(&rows[..8 * 20], &mut codes);
        let pq = crate::format::Pq {
            subspaces: 2,
            centroids: 16,
            sub_dims: 4,
            codebook: std::borrow::Cow::Borrowed(q.codebook()),
            codes: std::borrow::Cow::Owned(codes),
            order: q.order().map(std::borrow::Cow::Borrowed),
        };
        let mut direct = 0.0f64;
        let mut rebuilt = [0.0f32; 8];
        for (r, row) in rows.chunks_exact(8).take(20).enumerate() {
            pq.decode_row(r, &mut rebuilt);
            direct += row
                .iter()
                .zip(&rebuilt)
                .map(|(&a, &b)| f64::from(a - b).powi(2))
                .sum::<f64>();
        }
        assert!((direct - error).abs() < 1e-9, "{direct} vs {error}");
        assert!(error / 20.0 < 0.05, "{error}");
    }

    #[test]
    fn bad_requests_and_tiny_inputs() {
        let rows = unit_rows(10, 12, 2);
        assert!(Quantiser::train(&rows, 12, 5, 256).is_err());
        assert!(Quantiser::train(&rows, 12, 0, 256).is_err());
        assert!(Quantiser::train(&[], 12, 3, 256).is_err());
        // 10 rows: 10 centroids per subspace, each row its own, so no error.
        let q = Quantiser::train(&rows, 12, 3, 256).unwrap();
        assert_eq!(q.centroids(), 10);
        let mut codes = vec![0u8; 3];
        for row in rows.chunks_exact(12) {
            assert!(q.encode(row, &mut codes) < 1e-10);
        }
        assert_eq!(
            [0, 15, 16, 345, 4095, 4096, 1 << 20].map(centroids_for),
            [1, 1, 2, 32, 256, 256, 256]
        );
    }
}
