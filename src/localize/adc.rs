//! Matching against a product-quantised level by asymmetric distance computation (ADC, Jégou
//! et al. 2011): the query stays exact; per query and subspace a table holds its inner product
//! with each of the subspace's centroids, so a map row's similarity is `M` table lookups, never
//! a decoded row. The similarity is the cosine between the query and the row's reconstruction
//! (`Σ lookups / ‖reconstruction‖`, the norm from a query-independent table): the value the
//! localizer's reconstruct-and-normalise path gives, up to the i16 tables' rounding (see
//! [`I16_MAX_SUBSPACES`]), so the ratio test and the mutual check read it as they read f16
//! similarities.

use super::kernels::sgemm_abt;
use crate::format::Pq;

/// Table entries per subspace: every value of a code byte, so a lookup needs no bounds check.
const SLOTS: usize = 256;
/// The bytes of query tables held at once (`M × 256 × queries × 2` for i16 tables; more only
/// when `M > 128`, as one tile of queries is the least): larger chunks pay the per-row work
/// (codes, norms, the row's maximum) for more queries, which measured faster than tables that
/// fit the L2 cache.
const TABLE_BYTES: usize = 2 << 20;
/// Queries per chunk at most: the width of the vectorised accumulation.
const MAX_CHUNK: usize = 256;
/// Subspaces up to which the tables are i16. A score's rounding error is at most `M/2` units
/// of `Σ_s max_c |q_s·c_s,c| / 32,767`, typically `√(M/12)` units: at `M = 64` about 1.4e-4
/// (worst 2e-3), far below PQ's own error and the ratio test's margins. Beyond it (`M` near
/// the dimension, 1- or 2-dimensional subspaces, where PQ itself is nearly exact) the tables
/// stay f32.
const I16_MAX_SUBSPACES: usize = 64;

/// One chunk's table entries: i16 with a per-query scale, or f32 (see [`I16_MAX_SUBSPACES`]).
enum Entries {
    I16(Vec<i16>),
    F32(Vec<f32>),
}

/// The per-query tables of one chunk of queries, laid out query-fastest: a map row's score
/// with every query of the chunk is `M` contiguous rows of the table added together —
/// vector additions across queries instead of one scalar lookup per query and subspace.
/// Entries are i16 when `M` allows (16 queries a 256-bit add, half the bytes of f32: matching
/// is bound by reading the tables), each query's scaled so that no sum of `M` entries can
/// leave i16. Rows are padded to a multiple of 8 queries (zero entries) so every tile is
/// vector-wide.
pub(super) struct AdcTables<'p, 'm> {
    pq: &'p Pq<'m>,
    /// `[M × 256 × stride]`: `round(scale_q · query_q,s · centroid_s,c)` (i16) or the product
    /// itself (f32) at `(s·256 + c)·stride + q`.
    entries: Entries,
    /// Queries a table row holds: the chunk's, rounded up to a multiple of 8.
    stride: usize,
    /// `1 / scale_q` per query (`stride` of them): a sum of entries times it is the inner
    /// product; 1 for f32 tables; NaN for a query with a non-finite product, so it matches
    /// nothing, as on f16 levels.
    inverse_scales: Vec<f32>,
}

impl<'p, 'm> AdcTables<'p, 'm> {
    /// Queries per chunk for `pq`: tables of at most [`TABLE_BYTES`], whole tiles of [`TILE`]
    /// queries from one to [`MAX_CHUNK`]. `match_pq` builds them once per chunk:
    /// `match_scored_by_row` takes the chunks in its outer loop.
    pub(super) fn chunk(pq: &Pq<'_>) -> usize {
        let fit = TABLE_BYTES / (pq.subspaces.max(1) * SLOTS * 2);
        (fit / TILE * TILE).clamp(TILE, MAX_CHUNK)
    }

    /// Tables for `query` (`[n_q × dims]` unit rows in the level basis; one chunk).
    pub(super) fn new(query: &[f32], pq: &'p Pq<'m>) -> AdcTables<'p, 'm> {
        let (m, k, d) = (pq.subspaces, pq.centroids, pq.sub_dims);
        let dims = pq.dims().max(1);
        let n_q = query.len() / dims;
        let stride = n_q.div_ceil(8) * 8;
        let mut products = vec![0.0f32; m * SLOTS * stride];
        // The queries in the codes' dimension order (level_pq_order), so subvectors are
        // contiguous; padding queries are zero.
        let mut ordered = vec![0.0f32; stride * dims];
        for (out, row) in ordered.chunks_exact_mut(dims).zip(query.chunks_exact(dims)) {
            crate::format::pq_gather(pq.order.as_deref(), row, out);
        }
        let mut sub = vec![0.0f32; stride * d];
        for s in 0..m {
            for (out, row) in sub.chunks_exact_mut(d).zip(ordered.chunks_exact(dims)) {
                out.copy_from_slice(&row[s * d..(s + 1) * d]);
            }
            let centroids = &pq.codebook[s * k * d..(s + 1) * k * d];
            // `[k × stride]`: centroid-major, so each centroid's products with the chunk are a
            // row; slots past `k` stay zero (codes are checked `< k` on first access).
            let at = s * SLOTS * stride;
            sgemm_abt(
                centroids,
                &sub,
                &mut products[at..at + k * stride],
                k,
                stride,
                d,
            );
        }
        // A query's largest possible |sum| is the sum over subspaces of its largest |entry|
        // (f64, so the bound is not below the true sum); rounding adds at most 1/2 per
        // subspace, so `scale · bound + M/2 ≤ i16::MAX`.
        let mut bound = vec![0.0f64; stride];
        let mut finite = vec![true; stride];
        let mut largest = vec![0.0f32; stride];
        for table in products.chunks_exact(SLOTS * stride) {
            largest.fill(0.0);
            for row in table[..k * stride].chunks_exact(stride) {
                for ((l, f), &v) in largest.iter_mut().zip(&mut finite).zip(row) {
                    *l = l.max(v.abs());
                    *f &= v.is_finite();
                }
            }
            bound
                .iter_mut()
                .zip(&largest)
                .for_each(|(b, &l)| *b += f64::from(l));
        }
        if m > I16_MAX_SUBSPACES {
            let inverse_scales = finite
                .iter()
                .map(|&f| if f { 1.0 } else { f32::NAN })
                .collect();
            return AdcTables {
                pq,
                entries: Entries::F32(products),
                stride,
                inverse_scales,
            };
        }
        let room = f64::from(i16::MAX) - m as f64 / 2.0 - 1.0;
        let scales: Vec<f32> = bound
            .iter()
            .zip(&finite)
            .map(|(&b, &f)| if f && b > 0.0 { (room / b) as f32 } else { 0.0 })
            .collect();
        let mut lut = vec![0i16; products.len()];
        for (out, v) in lut
            .chunks_exact_mut(stride)
            .zip(products.chunks_exact(stride))
        {
            for ((o, &v), &scale) in out.iter_mut().zip(v).zip(&scales) {
                // Every |v · scale| ≤ room here; a non-finite query's scale is 0.
                *o = (v * scale).round() as i16;
            }
        }
        let inverse_scales = scales
            .iter()
            .zip(&finite)
            .map(|(&s, &f)| match (f, s > 0.0) {
                (false, _) => f32::NAN,
                (true, true) => 1.0 / s,
                // A zero query: every entry 0, every score 0.
                (true, false) => 0.0,
            })
            .collect();
        AdcTables {
            pq,
            entries: Entries::I16(lut),
            stride,
            inverse_scales,
        }
    }

    /// Similarities of the level rows `rows` with every query into `out` (`[rows × n_q]`,
    /// map-row-major), `inverse_norms[i]` the inverse norm of row `rows[i]`'s reconstruction.
    pub(super) fn scores(&self, rows: &[usize], inverse_norms: &[f32], out: &mut [f32]) {
        let pq = self.pq;
        let n_q = out.len().checked_div(rows.len()).unwrap_or(0);
        let shape = Shape {
            m: pq.subspaces,
            stride: self.stride,
            n_q,
        };
        let rows = (rows, inverse_norms);
        match &self.entries {
            Entries::I16(lut) => accumulate(lut, &pq.codes, shape, rows, &self.inverse_scales, out),
            Entries::F32(lut) => accumulate(lut, &pq.codes, shape, rows, &self.inverse_scales, out),
        }
    }
}

/// The table layout [`accumulate`] reads: `m` subspaces, `stride` queries a table row, `n_q`
/// of them written per map row.
#[derive(Clone, Copy)]
struct Shape {
    m: usize,
    stride: usize,
    n_q: usize,
}

/// A table entry: summed across subspaces, then widened to f32.
trait Entry: Copy + Default {
    fn add(self, other: Self) -> Self;
    fn widen(self) -> f32;
}

impl Entry for i16 {
    /// Wrapping: the scales keep the sums from wrapping, and it vectorises.
    #[inline(always)]
    fn add(self, other: i16) -> i16 {
        self.wrapping_add(other)
    }
    #[inline(always)]
    fn widen(self) -> f32 {
        f32::from(self)
    }
}

impl Entry for f32 {
    #[inline(always)]
    fn add(self, other: f32) -> f32 {
        self + other
    }
    #[inline(always)]
    fn widen(self) -> f32 {
        self
    }
}

/// For each row, its `M` table rows added across the chunk's queries, then converted and
/// scaled by the query's inverse scale and the row's inverse norm. Queries go [`TILE`] (then
/// 8) at a time through all `M` subspaces, so a tile's sums stay in registers; the table rows
/// are padded to whole tiles of 8, and only the chunk's `n_q` scores are written. Compiled for
/// AVX-512 and AVX2 too and chosen at run time.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
fn accumulate<E: Entry>(
    lut: &[E],
    codes: &[u8],
    Shape { m, stride, n_q }: Shape,
    (rows, inverse_norms): (&[usize], &[f32]),
    inverse_scales: &[f32],
    out: &mut [f32],
) {
    if n_q == 0 {
        return;
    }
    for ((scores, &r), &inv) in out.chunks_exact_mut(n_q).zip(rows).zip(inverse_norms) {
        let row_codes = &codes[r * m..(r + 1) * m];
        let mut q = 0;
        while q + TILE <= n_q {
            let sums = tile_sums::<E, TILE>(lut, row_codes, stride, q);
            scale_tile(&sums, &inverse_scales[q..], inv, &mut scores[q..q + TILE]);
            q += TILE;
        }
        while q < n_q {
            let sums = tile_sums::<E, 8>(lut, row_codes, stride, q);
            let end = (q + 8).min(n_q);
            scale_tile(&sums, &inverse_scales[q..], inv, &mut scores[q..end]);
            q += 8;
        }
    }
}

/// Queries a tile of [`accumulate`]: 32 i16 sums, one AVX-512 or two AVX2 registers.
const TILE: usize = 32;

/// The sums over subspaces of one row's table entries for queries `q..q + T`.
#[inline(always)]
fn tile_sums<E: Entry, const T: usize>(lut: &[E], codes: &[u8], stride: usize, q: usize) -> [E; T] {
    let mut sums = [E::default(); T];
    for (s, &c) in codes.iter().enumerate() {
        let at = (s * SLOTS + usize::from(c)) * stride + q;
        let entries: &[E; T] = lut[at..at + T].try_into().expect("a tile of T entries");
        for (sum, &e) in sums.iter_mut().zip(entries) {
            *sum = sum.add(e);
        }
    }
    sums
}

/// Tile sums to similarities (as many as `out` holds): times the query's inverse scale and
/// the row's inverse norm.
#[inline(always)]
fn scale_tile<E: Entry>(sums: &[E], inverse_scales: &[f32], inverse_norm: f32, out: &mut [f32]) {
    for ((o, &v), &scale) in out.iter_mut().zip(sums).zip(inverse_scales) {
        *o = v.widen() * scale * inverse_norm;
    }
}

/// The inverse norm of each row's reconstruction (`1 / ‖Σ_s centroid_s,code‖`, 0 for a zero
/// reconstruction): query-independent, computed once per matching call.
fn inverse_norms(pq: &Pq<'_>, rows: &[usize]) -> Vec<f32> {
    let (m, k, d) = (pq.subspaces, pq.centroids, pq.sub_dims);
    let mut norms = vec![0.0f32; m * SLOTS];
    for (i, c) in pq.codebook.chunks_exact(d).enumerate() {
        norms[(i / k) * SLOTS + i % k] = c.iter().map(|v| v * v).sum();
    }
    rows.iter()
        .map(|&r| {
            let n: f32 = pq.codes[r * m..(r + 1) * m]
                .iter()
                .enumerate()
                .map(|(s, &c)| norms[s * SLOTS + usize::from(c)])
                .sum();
            if n > 0.0 {
                1.0 / n.sqrt()
            } else {
                0.0
            }
        })
        .collect()
}

/// Matches unit `query` rows (`[n_q × dims]`) against the level rows `rows` of `pq` by
/// asymmetric distance, a chunk of queries at a time (match indices are positions in `rows`).
pub(super) fn match_pq(
    query: &[f32],
    pq: &Pq<'_>,
    rows: &[usize],
    options: &super::MatchOptions,
) -> Vec<super::matching::Match> {
    let dims = pq.dims().max(1);
    let norms = inverse_norms(pq, rows);
    let mut tables: Option<(usize, AdcTables<'_, '_>)> = None;
    super::matching::match_scored_by_row(
        query.len() / dims,
        rows.len(),
        AdcTables::chunk(pq),
        options,
        |queries, start, count, out| {
            if tables
                .as_ref()
                .is_none_or(|(first, _)| *first != queries.start)
            {
                let chunk = &query[queries.start * dims..queries.end * dims];
                tables = Some((queries.start, AdcTables::new(chunk, pq)));
            }
            if let Some((_, t)) = &tables {
                let range = start..start + count;
                t.scores(&rows[range.clone()], &norms[range], out);
            }
        },
    )
}

/// `match_pq` against every row of `pq` (the benches' entry).
#[cfg(any(test, feature = "fuzzing"))]
pub fn match_pq_descriptors(
    query: &[f32],
    pq: &Pq<'_>,
    options: &super::MatchOptions,
) -> Vec<super::matching::Match> {
    let rows: Vec<usize> = (0..pq.codes.len() / pq.subspaces.max(1)).collect();
    match_pq(query, pq, &rows, options)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::SplitMix64;
    use std::borrow::Cow;

    /// Queries of the test: whole tiles of 32 and of 8, and single queries.
    const QUERIES: usize = 45;

    #[test]
    fn adc_scores_are_cosines_with_the_reconstructions() {
        for m in [1usize, 2, 3, 8] {
            let (k, d, n) = (5, 2, 40);
            let mut rng = SplitMix64::new(9);
            let codebook: Vec<f32> = (0..m * k * d)
                .map(|_| rng.next_f64() as f32 - 0.5)
                .collect();
            let codes: Vec<u8> = (0..n * m).map(|_| rng.below(k) as u8).collect();
            let pq = Pq {
                subspaces: m,
                centroids: k,
                sub_dims: d,
                codebook: Cow::Owned(codebook),
                codes: Cow::Owned(codes),
                // Odd m: the identity; even m: a rotation of the dimensions (level_pq_order;
                // not its own inverse, so reading it backwards fails).
                order: (m % 2 == 0).then(|| {
                    let dims = (m * d) as u16;
                    Cow::Owned((0..dims).map(|j| (j + 1) % dims).collect())
                }),
            };
            let mut query: Vec<f32> = (0..QUERIES * m * d)
                .map(|_| rng.next_f64() as f32 - 0.5)
                .collect();
            crate::vector::normalise_rows(&mut query, m * d);
            let tables = AdcTables::new(&query, &pq);
            let rows: Vec<usize> = vec![3, 0, 39, 17, 17];
            let mut out = vec![0.0; rows.len() * QUERIES];
            let norms = inverse_norms(&pq, &rows);
            tables.scores(&rows, &norms, &mut out);
            let mut x = vec![0.0; m * d];
            for (q, qrow) in query.chunks_exact(m * d).enumerate() {
                for (j, &r) in rows.iter().enumerate() {
                    pq.decode_row(r, &mut x);
                    crate::vector::l2_normalise(&mut x);
                    let want: f32 = qrow.iter().zip(&x).map(|(a, b)| a * b).sum();
                    let got = out[j * QUERIES + q];
                    // i16 tables: each of the M entries is off by at most half a unit of
                    // 1/scale, before the row's inverse norm.
                    let unit = tables.inverse_scales[q];
                    assert!(unit > 0.0 && unit < 1e-3, "{unit}");
                    let tolerance = (m as f32 * 0.5 * unit) * norms[j] * 1.001 + 1e-6;
                    assert!(
                        (got - want).abs() < tolerance,
                        "q {q} row {r}: {got} vs {want}"
                    );
                }
            }
            // In chunks of 41 queries (a tile of 32, one of 8, one query), the matches are
            // those of matching the reconstructions.
            let all: Vec<usize> = (0..n).collect();
            let options = crate::localize::MatchOptions::default();
            let chunked = crate::localize::matching::match_scored_by_row(
                QUERIES,
                n,
                41,
                &options,
                |qs, start, count, out| {
                    let t = AdcTables::new(&query[qs.start * m * d..qs.end * m * d], &pq);
                    let rows = &all[start..start + count];
                    t.scores(rows, &inverse_norms(&pq, rows), out);
                },
            );
            let mut rebuilt = vec![0.0; n * m * d];
            for (r, out) in rebuilt.chunks_exact_mut(m * d).enumerate() {
                pq.decode_row(r, out);
                crate::vector::l2_normalise(out);
            }
            let exact =
                crate::localize::matching::match_descriptors(&query, &rebuilt, m * d, &options);
            assert_eq!(chunked.len(), exact.len());
            for (a, b) in chunked.iter().zip(&exact) {
                assert_eq!((a.query, a.map), (b.query, b.map));
            }
            assert_eq!(
                match_pq_descriptors(&query, &pq, &options).len(),
                exact.len()
            );
        }
    }

    /// Rows whose sum reaches a query's bound exactly (every subspace at its largest entry)
    /// keep their sign and value, on i16 tables up to [`I16_MAX_SUBSPACES`] and f32 beyond;
    /// a query with a NaN value matches nothing (NaN scores), as on f16 levels.
    #[test]
    fn extreme_sums_do_not_wrap_and_nan_queries_score_nan() {
        for m in [1usize, 2, I16_MAX_SUBSPACES, I16_MAX_SUBSPACES + 1] {
            // One dimension per subspace, centroids +1 and −1; rows all +1 and all −1.
            let codebook: Vec<f32> = (0..m).flat_map(|_| [1.0f32, -1.0]).collect();
            let codes: Vec<u8> = [0u8, 1].iter().flat_map(|&c| vec![c; m]).collect();
            let pq = Pq {
                subspaces: m,
                centroids: 2,
                sub_dims: 1,
                codebook: Cow::Owned(codebook),
                codes: Cow::Owned(codes),
                order: None,
            };
            let unit = 1.0 / (m as f32).sqrt();
            let mut query = vec![unit; m];
            query.extend(vec![0.0; m]);
            query.extend((0..m).map(|s| if s == 0 { f32::NAN } else { unit }));
            let tables = AdcTables::new(&query, &pq);
            let rows = [0usize, 1];
            let mut out = vec![0.0; 2 * 3];
            tables.scores(&rows, &inverse_norms(&pq, &rows), &mut out);
            assert!((out[0] - 1.0).abs() < 1e-3, "m {m}: {}", out[0]);
            assert!((out[3] + 1.0).abs() < 1e-3, "m {m}: {}", out[3]);
            assert_eq!((out[1], out[4]), (0.0, 0.0), "m {m}: a zero query");
            assert!(out[2].is_nan() && out[5].is_nan(), "m {m}: {out:?}");
        }
    }
}
