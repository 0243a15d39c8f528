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
pub(super) struct AdcTables<'p, 'm> {
    pq: &'p Pq<'m>,
    n_q: usize,
    /// `[M × 256 × n_q]`: `query_q,s · centroid_s,c` at `(s·256 + c)·n_q + q`.
    lut: Vec<f32>,
}

impl<'p, 'm> AdcTables<'p, 'm> {
    /// Queries per chunk for `pq`: tables of at most [`TABLE_BYTES`], a multiple of 8 queries
    /// (whole vectors) from 8 to [`MAX_CHUNK`]. `match_pq` builds them once per chunk:
    /// `match_scored_by_row` takes the chunks in its outer loop.
    pub(super) fn chunk(pq: &Pq<'_>) -> usize {
        let fit = TABLE_BYTES / (pq.subspaces.max(1) * SLOTS * 4);
        (fit / 8 * 8).clamp(8, MAX_CHUNK)
    }

    /// Tables for `query` (`[n_q × dims]` unit rows in the level basis; one chunk).
    pub(super) fn new(query: &[f32], pq: &'p Pq<'m>) -> AdcTables<'p, 'm> {
        let (m, k, d) = (pq.subspaces, pq.centroids, pq.sub_dims);
        let dims = pq.dims();
        let n_q = query.len() / dims.max(1);
        let mut lut = vec![0.0f32; m * SLOTS * n_q];
        let mut sub = vec![0.0f32; n_q * d];
        for s in 0..m {
            for (out, row) in sub.chunks_exact_mut(d).zip(query.chunks_exact(dims)) {
                out.copy_from_slice(&row[s * d..(s + 1) * d]);
            }
            let centroids = &pq.codebook[s * k * d..(s + 1) * k * d];
            // `[k × n_q]`: centroid-major, so each centroid's products with the chunk are a row.
            let at = s * SLOTS * n_q;
            sgemm_abt(centroids, &sub, &mut lut[at..at + k * n_q], k, n_q, d);
        }
        AdcTables { pq, n_q, lut }
    }

    /// Similarities of the level rows `rows` with every query into `out` (`[rows × n_q]`,
    /// map-row-major), `inverse_norms[i]` the inverse norm of row `rows[i]`'s reconstruction.
    pub(super) fn scores(&self, rows: &[usize], inverse_norms: &[f32], out: &mut [f32]) {
        let (pq, n_q) = (self.pq, self.n_q);
        accumulate(
            &self.lut,
            &pq.codes,
            pq.subspaces,
            n_q,
            rows,
            inverse_norms,
            out,
        );
    }
}

/// [`AdcTables::scores`]' loop: for each row, its `M` table rows added across the chunk's
/// queries, then scaled. Compiled for AVX2 too and chosen at run time.
#[multiversion::multiversion(targets("x86_64+avx2+fma", "x86_64+avx"))]
fn accumulate(
    lut: &[f32],
    codes: &[u8],
    m: usize,
    n_q: usize,
    rows: &[usize],
    inverse_norms: &[f32],
    out: &mut [f32],
) {
    let table = |s: usize, c: u8| {
        let at = (s * SLOTS + usize::from(c)) * n_q;
        &lut[at..at + n_q]
    };
    for ((acc, &r), &inv) in out.chunks_exact_mut(n_q).zip(rows).zip(inverse_norms) {
        let Some((&last, middle)) = codes[r * m..(r + 1) * m].split_last() else {
            acc.fill(0.0);
            continue;
        };
        // One pass per subspace: the first writes, the last adds and scales.
        match middle.split_first() {
            Some((&c0, rest)) => {
                acc.copy_from_slice(table(0, c0));
                for (s, &c) in rest.iter().enumerate() {
                    for (a, &v) in acc.iter_mut().zip(table(s + 1, c)) {
                        *a += v;
                    }
                }
                for (a, &v) in acc.iter_mut().zip(table(m - 1, last)) {
                    *a = (*a + v) * inv;
                }
            }
            None => {
                for (a, &v) in acc.iter_mut().zip(table(0, last)) {
                    *a = v * inv;
                }
            }
        }
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
            };
            let mut query: Vec<f32> = (0..4 * m * d)
                .map(|_| rng.next_f64() as f32 - 0.5)
                .collect();
            crate::vector::normalise_rows(&mut query, m * d);
            let tables = AdcTables::new(&query, &pq);
            let rows: Vec<usize> = vec![3, 0, 39, 17, 17];
            let mut out = vec![0.0; rows.len() * 4];
            let norms = inverse_norms(&pq, &rows);
            tables.scores(&rows, &norms, &mut out);
            let mut x = vec![0.0; m * d];
            for (q, qrow) in query.chunks_exact(m * d).enumerate() {
                for (j, &r) in rows.iter().enumerate() {
                    pq.decode_row(r, &mut x);
                    crate::vector::l2_normalise(&mut x);
                    let want: f32 = qrow.iter().zip(&x).map(|(a, b)| a * b).sum();
                    let got = out[j * 4 + q];
                    assert!((got - want).abs() < 1e-5, "q {q} row {r}: {got} vs {want}");
                }
            }
            // In chunks of 3 queries, the matches are those of matching the reconstructions.
            let all: Vec<usize> = (0..n).collect();
            let options = crate::localize::MatchOptions::default();
            let chunked = crate::localize::matching::match_scored_by_row(
                4,
                n,
                3,
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
