//! The descriptor basis stored with each level: an uncentred PCA, so that a prefix of the
//! projected dimensions (`short`) carries as much of the descriptors' energy as possible.
//!
//! Why uncentred: matching uses dot products. With an orthonormal basis `P`,
//! `(P a) · (P b) = a · b`, so the full projected descriptor matches exactly like the
//! original; centring would change every dot product by the mean.

/// An orthonormal basis, rows sorted by decreasing eigenvalue of the second-moment matrix.
#[derive(Debug, Clone)]
pub struct Basis {
    pub dim: usize,
    /// `[dim × dim]` row-major; row k is the k-th principal direction.
    pub rows: Vec<f32>,
    /// Eigenvalues (energy per direction), descending.
    pub energy: Vec<f64>,
    /// `rows` transposed, for [`project`](Self::project).
    columns: Vec<f32>,
}

impl Basis {
    /// The basis of `descriptors` (`[n × dim]` row-major).
    pub fn fit(descriptors: &[f32], dim: usize) -> Basis {
        Self::fit_rows(descriptors.chunks_exact(dim.max(1)), dim)
    }

    /// The basis of the rows `rows` yields (each `dim` values), in that order: a level's
    /// rows read where they are, not copied together first.
    pub fn fit_rows<'r>(rows: impl Iterator<Item = &'r [f32]>, dim: usize) -> Basis {
        let mut fit = BasisFit::new(dim);
        rows.for_each(|r| fit.add(r));
        fit.finish()
    }

    /// Share of the energy in the first `k` directions.
    pub fn energy_kept(&self, k: usize) -> f64 {
        let total: f64 = self.energy.iter().sum();
        if total <= 0.0 {
            return 0.0;
        }
        self.energy.iter().take(k).sum::<f64>() / total
    }

    /// `out = P · v`.
    pub fn project(&self, v: &[f32], out: &mut [f32]) {
        // Column by column: every out[j] still sums its products in order of k (from -0.0,
        // as `Iterator::sum` does), but the loop over j vectorises.
        out.fill(-0.0);
        for (&vk, column) in v.iter().zip(self.columns.chunks_exact(self.dim)) {
            for (o, &p) in out.iter_mut().zip(column) {
                *o += p * vk;
            }
        }
    }
}

impl Basis {
    /// The first `dst.len()` (at most `dim`) coordinates of `src` in this basis,
    /// renormalised (a map's retrieval rows).
    pub fn project_leading_row(&self, src: &[f32], dst: &mut [f32]) {
        for (o, direction) in dst.iter_mut().zip(self.rows.chunks_exact(self.dim)) {
            *o = crate::vector::dot(direction, src);
        }
        crate::vector::l2_normalise(dst);
    }
}

/// A [`Basis`] fitted one row at a time ([`Basis::fit_rows`], or rows read from a file).
pub struct BasisFit {
    dim: usize,
    /// Upper triangle of Σ r rᵀ.
    m: Vec<f64>,
    row: Vec<f64>,
}

impl BasisFit {
    /// No rows yet, of `dim` values each.
    pub fn new(dim: usize) -> BasisFit {
        BasisFit {
            dim,
            m: vec![0.0; dim * dim],
            row: vec![0.0; dim],
        }
    }

    /// Adds a row (`dim` values). The basis depends on the order rows come in only through
    /// the rounding of the sums: the same rows in the same order give the same bytes on every
    /// machine.
    pub fn add(&mut self, source: &[f32]) {
        // Upper triangle in f64, one row at a time: each element's sum keeps the rows'
        // order, and the loop over j vectorises.
        let (dim, m, row) = (self.dim, &mut self.m, &mut self.row);
        for (r, &x) in row.iter_mut().zip(source) {
            *r = f64::from(x);
        }
        for i in 0..dim {
            let ri = row[i];
            if ri == 0.0 {
                continue;
            }
            for (o, &rj) in m[i * dim + i..(i + 1) * dim].iter_mut().zip(&row[i..]) {
                *o += ri * rj;
            }
        }
    }

    /// The basis of the rows added.
    pub fn finish(self) -> Basis {
        let (dim, mut m) = (self.dim, self.m);
        for i in 0..dim {
            for j in 0..i {
                m[i * dim + j] = m[j * dim + i];
            }
        }
        let (values, vectors) = symmetric_eigen(&m, dim);
        let mut order: Vec<usize> = (0..dim).collect();
        order.sort_by(|&a, &b| values[b].total_cmp(&values[a]).then(a.cmp(&b)));
        let mut rows = Vec::with_capacity(dim * dim);
        for &k in &order {
            // Column k of `vectors`; the sign is fixed so the largest component is positive,
            // which makes the basis deterministic.
            let col: Vec<f64> = (0..dim).map(|i| vectors[i * dim + k]).collect();
            let pivot = col
                .iter()
                .copied()
                .fold(0.0f64, |a, v| if v.abs() > a.abs() { v } else { a });
            let sign = if pivot < 0.0 { -1.0 } else { 1.0 };
            rows.extend(col.iter().map(|v| (v * sign) as f32));
        }
        let columns = (0..dim * dim)
            .map(|t| rows[(t % dim) * dim + t / dim])
            .collect();
        Basis {
            dim,
            rows,
            energy: order.iter().map(|&k| values[k].max(0.0)).collect(),
            columns,
        }
    }
}

/// Eigen-decomposition of a symmetric matrix: returns the eigenvalues and the eigenvectors
/// as columns of a row-major matrix. nalgebra's (Householder tridiagonalisation, then
/// implicit QL), O(n³) once: the cyclic Jacobi sweeps this replaced took 151 s at the
/// 1,024 dimensions a features file may have (issue 31's review).
fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let m = nalgebra::DMatrix::from_row_slice(n, n, a);
    let eigen = nalgebra::SymmetricEigen::new(m);
    let vectors = eigen.eigenvectors;
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        for k in 0..n {
            v[i * n + k] = vectors[(i, k)];
        }
    }
    (eigen.eigenvalues.iter().copied().collect(), v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn basis_is_orthonormal_and_sorted_and_preserves_dots() {
        // Energy concentrated on a known direction mix.
        let dim = 8;
        let mut data = Vec::new();
        let mut s = 1u64;
        for _ in 0..200 {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let a = ((s >> 33) as f32 / (1u64 << 31) as f32) - 0.5;
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            let b = ((s >> 33) as f32 / (1u64 << 31) as f32) - 0.5;
            let row = [3.0 * a, 3.0 * a, b, 0.1 * b, 0.0, 0.01 * a, 0.0, 0.0];
            data.extend_from_slice(&row);
        }
        let basis = Basis::fit(&data, dim);
        for i in 0..dim {
            for j in 0..dim {
                let dot: f32 = (0..dim)
                    .map(|k| basis.rows[i * dim + k] * basis.rows[j * dim + k])
                    .sum();
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((dot - want).abs() < 1e-5, "rows {i},{j}: {dot}");
            }
        }
        assert!(basis.energy.windows(2).all(|w| w[0] >= w[1]));
        assert!(basis.energy_kept(1) > 0.9, "{}", basis.energy_kept(1));
        assert!((basis.energy_kept(dim) - 1.0).abs() < 1e-9);
        let (a, b) = (&data[0..dim], &data[dim..2 * dim]);
        let (mut pa, mut pb) = (vec![0.0; dim], vec![0.0; dim]);
        basis.project(a, &mut pa);
        basis.project(b, &mut pb);
        let dot = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| p * q).sum::<f32>();
        assert!((dot(a, b) - dot(&pa, &pb)).abs() < 1e-5);
    }
}
