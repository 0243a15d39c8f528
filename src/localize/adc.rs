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
/// The bytes of query tables held at once (`queries × M × 256 × 4`): queries are matched a
/// chunk of this size at a time, so memory stays bounded whatever the query's keypoints.
const TABLE_BYTES: usize = 8 << 20;

/// The per-query tables of one matching call.
pub(super) struct AdcTables<'p, 'm> {
    pq: &'p Pq<'m>,
    n_q: usize,
    /// `[n_q × M × 256]`: `query_q,s · centroid_s,c` at `(q·M + s)·256 + c`.
    lut: Vec<f32>,
    /// `[M × 256]`: `‖centroid_s,c‖²`.
    norms: Vec<f32>,
}

impl<'p, 'm> AdcTables<'p, 'm> {
    /// Queries per chunk for `pq`: tables of at most 8 MB.
    pub(super) fn chunk(pq: &Pq<'_>) -> usize {
        (TABLE_BYTES / (pq.subspaces.max(1) * SLOTS * 4)).max(1)
    }

    /// Tables for `query` (`[n_q × dims]` unit rows in the level basis; one chunk).
    pub(super) fn new(query: &[f32], pq: &'p Pq<'m>) -> AdcTables<'p, 'm> {
        let (m, k, d) = (pq.subspaces, pq.centroids, pq.sub_dims);
        let dims = pq.dims();
        let n_q = query.len() / dims.max(1);
        let mut lut = vec![0.0f32; n_q * m * SLOTS];
        let mut sub = vec![0.0f32; n_q * d];
        let mut products = vec![0.0f32; n_q * k];
        for s in 0..m {
            for (out, row) in sub.chunks_exact_mut(d).zip(query.chunks_exact(dims)) {
                out.copy_from_slice(&row[s * d..(s + 1) * d]);
            }
            let centroids = &pq.codebook[s * k * d..(s + 1) * k * d];
            sgemm_abt(&sub, centroids, &mut products, n_q, k, d);
            for (q, row) in products.chunks_exact(k).enumerate() {
                let at = (q * m + s) * SLOTS;
                lut[at..at + k].copy_from_slice(row);
            }
        }
        let mut norms = vec![0.0f32; m * SLOTS];
        for (i, c) in pq.codebook.chunks_exact(d).enumerate() {
            norms[(i / k) * SLOTS + i % k] = c.iter().map(|v| v * v).sum();
        }
        AdcTables {
            pq,
            n_q,
            lut,
            norms,
        }
    }

    /// Similarities of every query with the level rows `rows` into `out` (`[n_q × rows]`).
    /// `block_codes` and `inverse_norms` are scratch, reused across calls.
    pub(super) fn scores(
        &self,
        rows: &[usize],
        out: &mut [f32],
        block_codes: &mut Vec<u8>,
        inverse_norms: &mut Vec<f32>,
    ) {
        let m = self.pq.subspaces;
        let count = rows.len();
        // The block's codes, row by row and contiguous, read once per query below.
        block_codes.clear();
        for &r in rows {
            block_codes.extend_from_slice(&self.pq.codes[r * m..(r + 1) * m]);
        }
        inverse_norms.clear();
        for codes in block_codes.chunks_exact(m) {
            let n: f32 = codes
                .iter()
                .enumerate()
                .map(|(s, &c)| slots(&self.norms, s)[usize::from(c)])
                .sum();
            inverse_norms.push(if n > 0.0 { 1.0 / n.sqrt() } else { 0.0 });
        }
        for (q, out) in out.chunks_exact_mut(count).take(self.n_q).enumerate() {
            let tables = &self.lut[q * m * SLOTS..(q + 1) * m * SLOTS];
            let tables: &[[f32; SLOTS]] = bytemuck::cast_slice(tables);
            // The common sizes with the subspace loop unrolled; any other M the same way.
            match m {
                4 => rows_fixed::<4>(tables, block_codes, inverse_norms, out),
                8 => rows_fixed::<8>(tables, block_codes, inverse_norms, out),
                16 => rows_fixed::<16>(tables, block_codes, inverse_norms, out),
                32 => rows_fixed::<32>(tables, block_codes, inverse_norms, out),
                _ => {
                    for ((o, codes), &n) in out
                        .iter_mut()
                        .zip(block_codes.chunks_exact(m))
                        .zip(inverse_norms.iter())
                    {
                        let sum: f32 = tables
                            .iter()
                            .zip(codes)
                            .map(|(t, &c)| t[usize::from(c)])
                            .sum();
                        *o = sum * n;
                    }
                }
            }
        }
    }
}

/// One query's similarities with a block of rows of `M` codes: `M` lookups per row summed in
/// two independent chains (so additions overlap), then scaled by the row's inverse norm.
fn rows_fixed<const M: usize>(
    tables: &[[f32; SLOTS]],
    codes: &[u8],
    inverse_norms: &[f32],
    out: &mut [f32],
) {
    let tables: &[[f32; SLOTS]; M] = tables.try_into().expect("M tables");
    for ((o, codes), &n) in out.iter_mut().zip(codes.chunks_exact(M)).zip(inverse_norms) {
        let codes: &[u8; M] = codes.try_into().expect("M codes");
        let (mut even, mut odd) = (0.0f32, 0.0f32);
        for s in (0..M).step_by(2) {
            even += tables[s][usize::from(codes[s])];
            odd += tables[s + 1][usize::from(codes[s + 1])];
        }
        *o = (even + odd) * n;
    }
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
    let (mut block_codes, mut norms) = (Vec::new(), Vec::new());
    let mut tables: Option<(usize, AdcTables<'_, '_>)> = None;
    super::matching::match_scored(
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
                t.scores(
                    &rows[start..start + count],
                    out,
                    &mut block_codes,
                    &mut norms,
                );
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

/// Table `i` of 256 entries: indexing it with a `u8` cannot go out of bounds.
fn slots(tables: &[f32], i: usize) -> &[f32; SLOTS] {
    tables[i * SLOTS..(i + 1) * SLOTS]
        .try_into()
        .expect("tables are whole multiples of 256 entries")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::SplitMix64;
    use std::borrow::Cow;

    #[test]
    fn adc_scores_are_cosines_with_the_reconstructions() {
        // M = 3 takes the general loop, M = 8 the unrolled one.
        for m in [3usize, 8] {
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
            let mut out = vec![0.0; 4 * rows.len()];
            tables.scores(&rows, &mut out, &mut Vec::new(), &mut Vec::new());
            let mut x = vec![0.0; m * d];
            for (q, qrow) in query.chunks_exact(m * d).enumerate() {
                for (j, &r) in rows.iter().enumerate() {
                    pq.decode_row(r, &mut x);
                    crate::vector::l2_normalise(&mut x);
                    let want: f32 = qrow.iter().zip(&x).map(|(a, b)| a * b).sum();
                    let got = out[q * rows.len() + j];
                    assert!((got - want).abs() < 1e-5, "q {q} row {r}: {got} vs {want}");
                }
            }
            // In chunks of 3 queries, the matches are those of matching the reconstructions.
            let all: Vec<usize> = (0..n).collect();
            let options = crate::localize::MatchOptions::default();
            let chunked = crate::localize::matching::match_scored(
                4,
                n,
                3,
                &options,
                |qs, start, count, out| {
                    let t = AdcTables::new(&query[qs.start * m * d..qs.end * m * d], &pq);
                    t.scores(
                        &all[start..start + count],
                        out,
                        &mut Vec::new(),
                        &mut Vec::new(),
                    );
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
