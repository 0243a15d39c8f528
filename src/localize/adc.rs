//! Matching against a product-quantised level by asymmetric distance computation (ADC, Jégou
//! et al. 2011): the query stays exact; per query and subspace a table holds its inner product
//! with each of the subspace's centroids, so a map row's similarity is `M` table lookups, never
//! a decoded row. The similarity is the cosine between the query and the row's reconstruction
//! (`Σ lookups / ‖reconstruction‖`, the norm from a query-independent table), the same value
//! the localizer's reconstruct-and-normalise path gives, so the ratio test and the
//! mutual check read it as they read f16 similarities.

use super::kernels::sgemm_abt;
use crate::format::Pq;

/// Table entries per subspace: every value of a code byte, so a lookup needs no bounds check.
const SLOTS: usize = 256;
/// The bytes of query tables held at once (`M × 256 × queries × 4`; more only when `M > 256`,
/// as 8 queries are the least): larger chunks pay the per-row work (codes, norms, the row's
/// maximum) for more queries, which measured faster than tables that fit the L2 cache.
const TABLE_BYTES: usize = 2 << 20;
/// Queries per chunk at most: the width of the vectorised accumulation.
const MAX_CHUNK: usize = 256;

/// The per-query tables of one chunk of queries, laid out query-fastest: a map row's score
/// with every query of the chunk is `M` contiguous rows of the table added together —
/// vector additions across queries instead of one scalar lookup per query and subspace.
/// Entries are i16 (16 queries a 256-bit add, half the bytes of f32: matching is bound by
/// reading the tables), each query's scaled so that no sum of `M` entries can leave i16.
pub(super) struct AdcTables<'p, 'm> {
    pq: &'p Pq<'m>,
    /// `[M × 256 × n_q]`: `round(scale_q · query_q,s · centroid_s,c)` at `(s·256 + c)·n_q + q`.
    lut: Vec<i16>,
    /// `1 / scale_q` per query: a sum of entries times it is the inner product.
    inverse_scales: Vec<f32>,
}

impl<'p, 'm> AdcTables<'p, 'm> {
    /// Queries per chunk for `pq`: tables of at most [`TABLE_BYTES`], a multiple of 16 queries
    /// (whole vectors) from 16 to [`MAX_CHUNK`]. `match_pq` builds them once per chunk:
    /// `match_scored_by_row` takes the chunks in its outer loop.
    pub(super) fn chunk(pq: &Pq<'_>) -> usize {
        let fit = TABLE_BYTES / (pq.subspaces.max(1) * SLOTS * 2);
        (fit / 16 * 16).clamp(16, MAX_CHUNK)
    }

    /// Tables for `query` (`[n_q × dims]` unit rows in the level basis; one chunk).
    pub(super) fn new(query: &[f32], pq: &'p Pq<'m>) -> AdcTables<'p, 'm> {
        let (m, k, d) = (pq.subspaces, pq.centroids, pq.sub_dims);
        let dims = pq.dims();
        let n_q = query.len() / dims.max(1);
        let mut exact = vec![0.0f32; m * SLOTS * n_q];
        let mut sub = vec![0.0f32; n_q * d];
        for s in 0..m {
            for (out, row) in sub.chunks_exact_mut(d).zip(query.chunks_exact(dims)) {
                match &pq.order {
                    None => out.copy_from_slice(&row[s * d..(s + 1) * d]),
                    // Checked a permutation of 0..dims on first access.
                    Some(order) => {
                        for (o, &dim) in out.iter_mut().zip(&order[s * d..(s + 1) * d]) {
                            *o = row[usize::from(dim)];
                        }
                    }
                }
            }
            let centroids = &pq.codebook[s * k * d..(s + 1) * k * d];
            // `[k × n_q]`: centroid-major, so each centroid's products with the chunk are a row.
            let at = s * SLOTS * n_q;
            sgemm_abt(centroids, &sub, &mut exact[at..at + k * n_q], k, n_q, d);
        }
        // A query's largest possible |sum| is the sum over subspaces of its largest |entry|;
        // rounding adds at most 1/2 per subspace, so `scale · bound + M/2 ≤ i16::MAX`.
        let mut bound = vec![0.0f32; n_q];
        for table in exact.chunks_exact(SLOTS * n_q.max(1)) {
            let mut largest = vec![0.0f32; n_q];
            for row in table.chunks_exact(n_q.max(1)) {
                for (l, &v) in largest.iter_mut().zip(row) {
                    *l = l.max(v.abs());
                }
            }
            bound.iter_mut().zip(&largest).for_each(|(b, l)| *b += l);
        }
        let room = (f32::from(i16::MAX) - m as f32 / 2.0 - 1.0).max(0.0);
        let scales: Vec<f32> = bound
            .iter()
            .map(|&b| {
                if b > 0.0 && b.is_finite() {
                    room / b
                } else {
                    0.0
                }
            })
            .collect();
        let mut lut = vec![0i16; exact.len()];
        for (out, v) in lut
            .chunks_exact_mut(n_q.max(1))
            .zip(exact.chunks_exact(n_q.max(1)))
        {
            for ((o, &v), &scale) in out.iter_mut().zip(v).zip(&scales) {
                // `as` saturates and maps NaN to 0: a non-finite query scores 0 everywhere.
                *o = (v * scale).round() as i16;
            }
        }
        let inverse_scales = scales
            .iter()
            .map(|&s| if s > 0.0 { 1.0 / s } else { 0.0 })
            .collect();
        AdcTables {
            pq,
            lut,
            inverse_scales,
        }
    }

    /// Similarities of the level rows `rows` with every query into `out` (`[rows × n_q]`,
    /// map-row-major), `inverse_norms[i]` the inverse norm of row `rows[i]`'s reconstruction.
    pub(super) fn scores(&self, rows: &[usize], inverse_norms: &[f32], out: &mut [f32]) {
        let pq = self.pq;
        accumulate(
            &self.lut,
            &pq.codes,
            pq.subspaces,
            (rows, inverse_norms),
            &self.inverse_scales,
            out,
        );
    }
}

/// [`AdcTables::scores`]' loop: for each row, its `M` table rows added across the chunk's
/// queries (wrapping adds that the scales keep from wrapping), then converted and scaled.
/// Queries go [`TILE`] at a time through all `M` subspaces, so a tile's sums stay in
/// registers. Compiled for AVX-512 and AVX2 too and chosen at run time.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
fn accumulate(
    lut: &[i16],
    codes: &[u8],
    m: usize,
    (rows, inverse_norms): (&[usize], &[f32]),
    inverse_scales: &[f32],
    out: &mut [f32],
) {
    let n_q = inverse_scales.len();
    if n_q == 0 {
        return;
    }
    for ((scores, &r), &inv) in out.chunks_exact_mut(n_q).zip(rows).zip(inverse_norms) {
        let row_codes = &codes[r * m..(r + 1) * m];
        let mut q = 0;
        while q + TILE <= n_q {
            let sums = tile_sums::<TILE>(lut, row_codes, n_q, q);
            scale_tile(
                &sums,
                &inverse_scales[q..q + TILE],
                inv,
                &mut scores[q..q + TILE],
            );
            q += TILE;
        }
        while q + 8 <= n_q {
            let sums = tile_sums::<8>(lut, row_codes, n_q, q);
            scale_tile(&sums, &inverse_scales[q..q + 8], inv, &mut scores[q..q + 8]);
            q += 8;
        }
        for q in q..n_q {
            let sums = tile_sums::<1>(lut, row_codes, n_q, q);
            scale_tile(&sums, &inverse_scales[q..q + 1], inv, &mut scores[q..q + 1]);
        }
    }
}

/// Queries a tile of [`accumulate`]: 32 i16 sums, one AVX-512 or two AVX2 registers.
const TILE: usize = 32;

/// The sums over subspaces of one row's table entries for queries `q..q + T`.
#[inline(always)]
fn tile_sums<const T: usize>(lut: &[i16], codes: &[u8], n_q: usize, q: usize) -> [i16; T] {
    let mut sums = [0i16; T];
    for (s, &c) in codes.iter().enumerate() {
        let at = (s * SLOTS + usize::from(c)) * n_q + q;
        let entries: &[i16; T] = lut[at..at + T].try_into().expect("a tile of T entries");
        for (sum, &e) in sums.iter_mut().zip(entries) {
            *sum = sum.wrapping_add(e);
        }
    }
    sums
}

/// Tile sums to similarities: times the query's inverse scale and the row's inverse norm.
#[inline(always)]
fn scale_tile(sums: &[i16], inverse_scales: &[f32], inverse_norm: f32, out: &mut [f32]) {
    for ((o, &v), &scale) in out.iter_mut().zip(sums).zip(inverse_scales) {
        *o = f32::from(v) * scale * inverse_norm;
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

/// [`match_pq`] against every row of `pq` (the benches' entry).
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
                // Odd m: the identity; even m: the dimensions reversed (level_pq_order).
                order: (m % 2 == 0).then(|| Cow::Owned((0..(m * d) as u16).rev().collect())),
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
}
