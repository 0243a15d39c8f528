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
/// The most bytes the query tables of one matching call may take (`n_q × M × 256 × 4`):
/// beyond it the caller reconstructs rows instead.
pub(super) const MAX_TABLE_BYTES: usize = 32 << 20;

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
    /// Tables for `query` (`[n_q × dims]` unit rows in the level basis), or `None` when they
    /// would take more than [`MAX_TABLE_BYTES`].
    pub(super) fn new(query: &[f32], pq: &'p Pq<'m>) -> Option<AdcTables<'p, 'm>> {
        let (m, k, d) = (pq.subspaces, pq.centroids, pq.sub_dims);
        let dims = pq.dims();
        let n_q = query.len() / dims.max(1);
        if n_q.checked_mul(m * SLOTS * 4)? > MAX_TABLE_BYTES {
            return None;
        }
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
        Some(AdcTables {
            pq,
            n_q,
            lut,
            norms,
        })
    }

    /// Similarities of every query with the level rows `rows` into `out` (`[n_q × rows]`).
    /// `codes_t` and `inverse_norms` are scratch, reused across calls.
    pub(super) fn scores(
        &self,
        rows: &[usize],
        out: &mut [f32],
        codes_t: &mut Vec<u8>,
        inverse_norms: &mut Vec<f32>,
    ) {
        let m = self.pq.subspaces;
        let count = rows.len();
        // The block's codes, subspace by subspace, so each lookup pass reads them in order.
        codes_t.resize(m * count, 0);
        for (j, &r) in rows.iter().enumerate() {
            for (s, &c) in self.pq.codes[r * m..(r + 1) * m].iter().enumerate() {
                codes_t[s * count + j] = c;
            }
        }
        inverse_norms.clear();
        inverse_norms.resize(count, 0.0);
        for s in 0..m {
            let norms = slots(&self.norms, s);
            for (n, &c) in inverse_norms
                .iter_mut()
                .zip(&codes_t[s * count..(s + 1) * count])
            {
                *n += norms[usize::from(c)];
            }
        }
        for n in inverse_norms.iter_mut() {
            *n = if *n > 0.0 { 1.0 / n.sqrt() } else { 0.0 };
        }
        for (q, out) in out.chunks_exact_mut(count).take(self.n_q).enumerate() {
            out.fill(0.0);
            for s in 0..m {
                let table = slots(&self.lut, q * m + s);
                for (o, &c) in out.iter_mut().zip(&codes_t[s * count..(s + 1) * count]) {
                    *o += table[usize::from(c)];
                }
            }
            for (o, &n) in out.iter_mut().zip(inverse_norms.iter()) {
                *o *= n;
            }
        }
    }
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
        let (m, k, d, n) = (3, 5, 2, 40);
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
        let tables = AdcTables::new(&query, &pq).unwrap();
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
        // Tables past the cap are refused (the caller reconstructs instead).
        let many = vec![0.0f32; (MAX_TABLE_BYTES / (m * SLOTS * 4) + 1) * m * d];
        assert!(AdcTables::new(&many, &pq).is_none());
    }
}
