//! The localizer's one unsafe call: matrixmultiply's sgemm, whose API takes raw pointers.
#![allow(unsafe_code)]

/// `out[n × m] = a[n × k] · b[m × k]ᵀ`, all row-major (`pub` only for `crate::fuzzing`). Panics if a slice is too short, so
/// the unsafe call below never reads or writes outside them.
pub fn sgemm_abt(a: &[f32], b: &[f32], out: &mut [f32], n: usize, m: usize, k: usize) {
    // Checked products: a wrapped one could pass the check with slices far too short.
    let fits = |len: usize, x: usize, y: usize| x.checked_mul(y).is_some_and(|xy| len >= xy);
    assert!(fits(a.len(), n, k) && fits(b.len(), m, k) && fits(out.len(), n, m));
    if n == 0 || m == 0 {
        return;
    }
    // SAFETY: a is n×k with row stride k (checked length n·k), b is read as its transpose
    // k×m with row stride 1 and column stride k (elements b[j·k + t], j < m, t < k: inside
    // m·k), out is n×m with row stride m (inside n·m). The slices do not overlap: `out` is
    // a unique borrow.
    unsafe {
        matrixmultiply::sgemm(
            n,
            k,
            m,
            1.0,
            a.as_ptr(),
            k as isize,
            1,
            b.as_ptr(),
            1,
            k as isize,
            0.0,
            out.as_mut_ptr(),
            m as isize,
            1,
        );
    }
}
