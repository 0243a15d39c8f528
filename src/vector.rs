//! The vector kernels every stage shares: L2 normalisation and the dot product. One home, so
//! the descriptors a map is built from and those a query is matched with go through the same
//! arithmetic (the extractor, the SIFT aggregation of `convert`, the localizer).

/// Scales `v` to unit L2 norm; a vector of norm ≤ 1e-12 stays as it is (the extractor's
/// reference, `python/sfp/reference.py`, divides by `max(norm, 1e-12)`; SIFT rows and f16 map
/// rows have norm 0 or far above it).
pub(crate) fn l2_normalise(v: &mut [f32]) {
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if norm > 1e-12 {
        v.iter_mut().for_each(|x| *x /= norm);
    }
}

/// L2 normalisation of each `dim`-row of `v`.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub fn normalise_rows(v: &mut [f32], dim: usize) {
    if dim == 0 {
        return;
    }
    v.chunks_exact_mut(dim).for_each(l2_normalise);
}

/// `rows` (`[n × d_in]`) in the basis `projection` (`[dims × d_in]`, a direction a row), each
/// result row unit length; a zero row (a point without a descriptor) stays zero. A catalog's
/// image VLADs and a query's, ranked against them, go through this one projection.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub(crate) fn project_rows(rows: &[f32], d_in: usize, projection: &[f32], dims: usize) -> Vec<f32> {
    let n = rows.len() / d_in.max(1);
    let mut out = vec![0.0f32; n * dims];
    for (x, o) in rows
        .chunks_exact(d_in.max(1))
        .zip(out.chunks_exact_mut(dims.max(1)))
    {
        if x.iter().any(|&v| v != 0.0) {
            for (k, o) in o.iter_mut().enumerate() {
                *o = dot(&projection[k * d_in..(k + 1) * d_in], x);
            }
        }
    }
    normalise_rows(&mut out, dims);
    out
}

/// f16 → f32, exact, for a whole slice (`to` as long as `from`): the map's descriptor rows
/// and VLADs as matching and retrieval read them. Bit arithmetic and selects only, so the
/// loop vectorizes (compiled for AVX-512 and AVX2 too, chosen at run time); `half`'s slice
/// conversion calls a function per 8 values, which made it a tenth of coarse matching's time
/// and most of ranking 8,000 f16 VLADs. Subnormals go through an integer-to-float conversion,
/// so no arithmetic ever sees a subnormal operand (slow on x86).
#[cfg(any(feature = "colmap-model", feature = "localize"))]
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
pub(crate) fn widen_f16(from: &[half::f16], to: &mut [f32]) {
    assert_eq!(from.len(), to.len(), "widen_f16: lengths differ");
    for (h, out) in from.iter().zip(to.iter_mut()) {
        *out = widen_one(*h);
    }
}

/// One value of [`widen_f16`], inlined into its multiversioned callers.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
#[inline(always)]
fn widen_one(h: half::f16) -> f32 {
    let h = u32::from(h.to_bits());
    let sign = (h & 0x8000) << 16;
    let magnitude = h & 0x7fff;
    // Normal: the exponent rebiased from 15 to 127 (+112 << 23), the mantissa shifted.
    let normal = (magnitude << 13) + (112 << 23);
    // Subnormal: magnitude × 2⁻²⁴, a normal f32.
    let subnormal = (magnitude as f32 * f32::from_bits(0x3380_0000)).to_bits();
    // Infinity and NaN: the exponent all ones, the mantissa (NaN payload) kept.
    let special = (magnitude << 13) | 0x7f80_0000;
    let bits = if magnitude < 0x0400 {
        subnormal
    } else if magnitude >= 0x7c00 {
        special
    } else {
        normal
    };
    f32::from_bits(bits | sign)
}

/// Each `dim`-value row of `rows` (f16) dotted with `q`, the values widened as
/// [`widen_f16`] does: a stretch of a row at a time into a buffer that stays in L1, then its
/// dot product, both inlined here and compiled for AVX-512 and AVX2 too (ranking 8,000 f16
/// VLADs reads 16 MB a query; widening value by value inside the dot product was twice as
/// slow, as it kept the loop from vectorizing).
#[cfg(feature = "localize")]
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
pub(crate) fn dots_f16(rows: &[half::f16], dim: usize, q: &[f32]) -> Vec<f32> {
    assert_eq!(q.len(), dim, "dots_f16: the query is not a row");
    let mut buffer = [0.0f32; STRETCH];
    let mut sums = Vec::with_capacity(rows.len() / dim.max(1));
    // Loops, not iterator closures: a closure is compiled apart, without the target features.
    for row in rows.chunks_exact(dim.max(1)) {
        sums.push(row_dot_f16(row, q, &mut buffer));
    }
    sums
}

/// [`dots_f16`] for the rows `picks` names only (each below `rows.len() / dim`), in that
/// order: what an image index's lists score.
#[cfg(feature = "localize")]
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
pub(crate) fn dots_f16_picked(
    rows: &[half::f16],
    dim: usize,
    q: &[f32],
    picks: &[u32],
) -> Vec<f32> {
    assert_eq!(q.len(), dim, "dots_f16_picked: the query is not a row");
    let mut buffer = [0.0f32; STRETCH];
    let mut sums = Vec::with_capacity(picks.len());
    for &i in picks {
        let start = i as usize * dim;
        sums.push(row_dot_f16(&rows[start..start + dim], q, &mut buffer));
    }
    sums
}

/// Values of an f16 row widened at a time: a buffer that stays in L1.
#[cfg(feature = "localize")]
const STRETCH: usize = 256;

/// One f16 row dotted with `q`, a [`STRETCH`] at a time (inlined into the multiversioned
/// callers, so it gets their target features).
#[cfg(feature = "localize")]
#[inline(always)]
fn row_dot_f16(row: &[half::f16], q: &[f32], buffer: &mut [f32; STRETCH]) -> f32 {
    let mut sum = 0.0;
    for (part, qs) in row.chunks(STRETCH).zip(q.chunks(STRETCH)) {
        let b = &mut buffer[..part.len()];
        for (h, out) in part.iter().zip(b.iter_mut()) {
            *out = widen_one(*h);
        }
        sum += dot(b, qs);
    }
    sum
}

/// Dot product over 8 independent lanes, so it vectorizes (inlined, so that multiversioned
/// callers get their wider vectors).
#[cfg(any(feature = "colmap", feature = "localize"))]
#[inline]
pub(crate) fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut lanes = [0.0f32; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            lanes[k] += x[k] * y[k];
        }
    }
    lanes.iter().sum::<f32>() + tail
}

/// Indices of the `k` highest scores, best first, ties by index: a partial selection
/// (O(n) to find them, O(k log k) to order them), never a sort of all `n`.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub(crate) fn top_k_indices(scores: &[f32], k: usize) -> Vec<usize> {
    let better = |&a: &usize, &b: &usize| scores[b].total_cmp(&scores[a]).then(a.cmp(&b));
    let mut order: Vec<usize> = (0..scores.len()).collect();
    if k < order.len() {
        order.select_nth_unstable_by(k, better);
        order.truncate(k);
        // Callers keep what they are given (a calibration keeps 100 orders of lists).
        order.shrink_to_fit();
    }
    order.sort_unstable_by(better);
    order
}

/// A score that is not a number (a NaN in a stored row, which the format does not check)
/// made the lowest, so it ranks last, not first.
#[cfg(any(feature = "colmap", feature = "localize"))]
pub(crate) fn ranked_last_if_not_finite(scores: &mut [f32]) {
    for s in scores {
        if !s.is_finite() {
            *s = f32::NEG_INFINITY;
        }
    }
}

/// The nearest of a set of centroids, by `x·c − ‖c‖²/2` (the order of the squared distance).
/// The centroids are stored in blocks of [`LANES`] (`[blocks × dims × LANES]`, the last block
/// padded with centroids that never win), so a block's scores stay in one vector register
/// while `x`'s values scale it: the loop vectorizes over centroids without storing scores,
/// which makes 256-centroid codebooks (PQ) cheap to train and encode with. k-means
/// (`kmeans`), VLAD assignments and PQ encoding all go through it.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
#[derive(Debug, Clone, PartialEq)]
pub struct Nearest {
    dims: usize,
    clusters: usize,
    blocks: Vec<f32>,
    /// `−‖c‖²/2` per centroid; `−∞` for the padding.
    minus_half_norms: Vec<f32>,
}

/// Centroids a block: one AVX2 register of f32.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
const LANES: usize = 8;

#[cfg(any(feature = "colmap-model", feature = "localize"))]
impl Nearest {
    /// From centroids `[clusters × dims]` (a partial last row is ignored).
    pub fn new(centroids: &[f32], dims: usize) -> Nearest {
        let clusters = centroids.len().checked_div(dims).unwrap_or(0);
        let padded = clusters.div_ceil(LANES) * LANES;
        let mut blocks = vec![0.0f32; padded * dims];
        let mut minus_half_norms = vec![f32::NEG_INFINITY; padded];
        for (c, centroid) in centroids.chunks_exact(dims.max(1)).enumerate() {
            let (block, lane) = (c / LANES, c % LANES);
            minus_half_norms[c] = 0.0;
            for (d, &v) in centroid.iter().enumerate() {
                blocks[(block * dims + d) * LANES + lane] = v;
                minus_half_norms[c] -= 0.5 * v * v;
            }
        }
        Nearest {
            dims,
            clusters,
            blocks,
            minus_half_norms,
        }
    }

    /// The index of the centroid nearest to `x` (`dims` values, a shorter `x` scores only its
    /// own; ties: the lower index; 0 without centroids, or when no score is a number).
    pub fn find(&self, x: &[f32]) -> usize {
        if self.dims == 0 {
            return 0;
        }
        let used = x.len().min(self.dims);
        #[cfg(target_arch = "x86_64")]
        if let Some(found) =
            avx::nearest_rows(&[x], used, self.dims, &self.blocks, &self.minus_half_norms)
        {
            return self.clamp(found[0]);
        }
        self.clamp(nearest_in_blocks(
            x,
            self.dims,
            &self.blocks,
            &self.minus_half_norms,
        ))
    }

    #[cfg(feature = "colmap")]
    /// Every centroid's `x·c − ‖c‖²/2`, in centroid order (what `find` maximises, summed
    /// block by block: equal to its scores up to rounding).
    pub fn scores(&self, x: &[f32]) -> Vec<f32> {
        let used = x.len().min(self.dims);
        let mut out = Vec::with_capacity(self.minus_half_norms.len());
        if self.dims == 0 {
            out.resize(self.clusters, 0.0);
            return out;
        }
        for (block, halves) in self
            .blocks
            .chunks_exact(self.dims * LANES)
            .zip(self.minus_half_norms.chunks_exact(LANES))
        {
            let mut acc = [0.0f32; LANES];
            for (lanes, &v) in block.chunks_exact(LANES).zip(&x[..used]) {
                for l in 0..LANES {
                    acc[l] += v * lanes[l];
                }
            }
            out.extend(acc.iter().zip(halves).map(|(a, h)| a + h));
        }
        out.truncate(self.clusters);
        out
    }

    #[cfg(feature = "colmap")]
    /// The centroids nearest to `x` first (by [`Nearest::scores`]; ties: the lower index; a
    /// score that is not a number last): the order an image index's lists are probed in, by
    /// the writer's calibration (the localizer's, from f16 centroids, is [`NearestF16`]'s).
    pub fn order(&self, x: &[f32]) -> Vec<usize> {
        let mut scores = self.scores(x);
        ranked_last_if_not_finite(&mut scores);
        top_k_indices(&scores, self.clusters)
    }

    /// [`Nearest::find`] of each row in order, `found(row index, centroid)` for each; rows of
    /// `dims` values go [`ROWS_PER_PASS`] at a time through one pass over the centroids (a block's
    /// loads shared, independent sums in flight), the rest one at a time. Same indices as
    /// `find`, bit for bit. (k-means and PQ encoding, in `build`, use it.)
    #[cfg(feature = "colmap-model")]
    pub fn find_each<'a>(
        &self,
        rows: impl IntoIterator<Item = &'a [f32]>,
        mut found: impl FnMut(usize, usize),
    ) {
        let mut rows = rows.into_iter();
        let mut first = 0;
        loop {
            let mut group: [&[f32]; ROWS_PER_PASS] = [&[]; ROWS_PER_PASS];
            let mut len = 0;
            for (slot, x) in group.iter_mut().zip(rows.by_ref()) {
                *slot = x;
                len += 1;
            }
            if len == 0 {
                return;
            }
            #[cfg(target_arch = "x86_64")]
            if len == ROWS_PER_PASS && self.dims > 0 && group.iter().all(|x| x.len() >= self.dims) {
                let (dims, blocks, norms) = (self.dims, &self.blocks, &self.minus_half_norms);
                if let Some(cs) = avx::nearest_rows(&group, dims, dims, blocks, norms) {
                    for (r, c) in cs.into_iter().enumerate() {
                        found(first + r, self.clamp(c));
                    }
                    first += ROWS_PER_PASS;
                    continue;
                }
            }
            for (r, x) in group[..len].iter().enumerate() {
                found(first + r, self.find(x));
            }
            first += len;
        }
    }

    // The clamp only matters past 2²⁴ blocks, where block indices stop being exact f32.
    fn clamp(&self, found: usize) -> usize {
        found.min(self.clusters.saturating_sub(1))
    }
}

/// [`Nearest::scores`] and [`Nearest::order`] over centroids held in f16 (each rounded once,
/// its `−‖c‖²/2` from the rounded values): half the bytes a query reads. The localizer ranks
/// an image index's lists with it: 3,348 centroids of 1,024 values are 13.7 MB in f32, and
/// reading them was most of a query's retrieval on the 10 M-point street. The order of lists
/// decides which images a query scores (its recall), never a score.
#[cfg(feature = "localize")]
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct NearestF16 {
    dims: usize,
    clusters: usize,
    /// `[blocks × dims × LANES]` f16 bits, the last block padded with zeros.
    blocks: Vec<u16>,
    /// `−‖c‖²/2` per centroid; `−∞` for the padding.
    minus_half_norms: Vec<f32>,
}

#[cfg(feature = "localize")]
impl NearestF16 {
    /// From centroids `[clusters × dims]` (a partial last row is ignored).
    pub(crate) fn new(centroids: &[f32], dims: usize) -> NearestF16 {
        let clusters = centroids.len().checked_div(dims).unwrap_or(0);
        let padded = clusters.div_ceil(LANES) * LANES;
        let mut blocks = vec![0u16; padded * dims];
        let mut minus_half_norms = vec![f32::NEG_INFINITY; padded];
        for (c, centroid) in centroids.chunks_exact(dims.max(1)).enumerate() {
            let (block, lane) = (c / LANES, c % LANES);
            minus_half_norms[c] = 0.0;
            for (d, &v) in centroid.iter().enumerate() {
                let h = half::f16::from_f32(v);
                blocks[(block * dims + d) * LANES + lane] = h.to_bits();
                let v = h.to_f32();
                minus_half_norms[c] -= 0.5 * v * v;
            }
        }
        NearestF16 {
            dims,
            clusters,
            blocks,
            minus_half_norms,
        }
    }

    /// Every centroid's `x·c − ‖c‖²/2`, in centroid order (`x`: `dims` values, a shorter one
    /// scores only its own), summed in four sums over the dimensions (`d mod 4`), each sum
    /// multiplied and added in order (no FMA), added `(s0 + s1) + (s2 + s3)`: the AVX path
    /// and the portable one give the same bits for finite scores (a centroid past f16's range
    /// is infinite, its score not a number on both paths, which ranks last either way).
    pub(crate) fn scores(&self, x: &[f32]) -> Vec<f32> {
        let used = x.len().min(self.dims);
        let mut out = Vec::with_capacity(self.minus_half_norms.len());
        if self.dims == 0 {
            out.resize(self.clusters, 0.0);
            return out;
        }
        #[cfg(target_arch = "x86_64")]
        let done = avx::scores_f16(
            &self.blocks,
            &self.minus_half_norms,
            self.dims,
            &x[..used],
            &mut out,
        );
        #[cfg(not(target_arch = "x86_64"))]
        let done = false;
        if !done {
            scores_f16_portable(
                &self.blocks,
                &self.minus_half_norms,
                self.dims,
                &x[..used],
                &mut out,
            );
        }
        out.truncate(self.clusters);
        out
    }

    /// The centroids nearest to `x` first, as [`Nearest::order`].
    #[cfg(test)]
    pub(crate) fn order(&self, x: &[f32]) -> Vec<usize> {
        let mut scores = self.scores(x);
        ranked_last_if_not_finite(&mut scores);
        top_k_indices(&scores, self.clusters)
    }
}

/// [`NearestF16::scores`] without AVX (and its reference: the same sums in the same order).
#[cfg(feature = "localize")]
fn scores_f16_portable(
    blocks: &[u16],
    minus_half_norms: &[f32],
    dims: usize,
    x: &[f32],
    out: &mut Vec<f32>,
) {
    for (block, halves) in blocks
        .chunks_exact(dims * LANES)
        .zip(minus_half_norms.chunks_exact(LANES))
    {
        let mut acc = [[0.0f32; LANES]; 4];
        for (d, &v) in x.iter().enumerate() {
            let lanes = &block[d * LANES..(d + 1) * LANES];
            for l in 0..LANES {
                acc[d % 4][l] += v * half::f16::from_bits(lanes[l]).to_f32();
            }
        }
        for l in 0..LANES {
            out.push((acc[0][l] + acc[1][l]) + (acc[2][l] + acc[3][l]) + halves[l]);
        }
    }
}

/// Rows [`Nearest::find_each`] scores together: four sums, four running bests and four best
/// blocks stay in 12 of AVX's 16 registers.
#[cfg(feature = "colmap-model")]
const ROWS_PER_PASS: usize = 4;

/// The first maximum over lanes of the per-lane bests, as a centroid index.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
fn first_maximum(best: &[f32; LANES], best_block: &[f32; LANES]) -> usize {
    let max = best.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    (0..LANES)
        .filter(|&k| best[k] == max)
        .map(|k| best_block[k] as usize * LANES + k)
        .min()
        .unwrap_or(0)
}

/// [`Nearest::find`]'s portable loop, for machines without AVX (with it, the `avx` module's
/// kernel runs instead). Each score is `−‖c‖²/2 + x₀c₀ + x₁c₁ + …` summed in that order, so
/// both give the same index.
#[cfg(any(feature = "colmap-model", feature = "localize"))]
fn nearest_in_blocks(x: &[f32], dims: usize, blocks: &[f32], minus_half_norms: &[f32]) -> usize {
    let mut best = [f32::NEG_INFINITY; LANES];
    // Block indices as f32 (exact below 2²⁴ blocks): the update is then one compare and two
    // blends; as u32 the compiler packs and shuffles the compare masks.
    let mut best_block = [0.0f32; LANES];
    for (b, (block, norms)) in blocks
        .chunks_exact(dims * LANES)
        .zip(minus_half_norms.chunks_exact(LANES))
        .enumerate()
    {
        let mut acc = [0.0f32; LANES];
        acc.copy_from_slice(norms);
        for (&v, column) in x.iter().zip(block.chunks_exact(LANES)) {
            for k in 0..LANES {
                acc[k] += v * column[k];
            }
        }
        // Strictly greater: a lane keeps its first (lowest) block on ties; NaN never wins.
        let block_index = b as f32;
        for k in 0..LANES {
            let better = acc[k] > best[k];
            best[k] = if better { acc[k] } else { best[k] };
            best_block[k] = if better { block_index } else { best_block[k] };
        }
    }
    first_maximum(&best, &best_block)
}

/// The same loop written with AVX intrinsics for several rows at once: LLVM does not keep
/// the portable loop's per-lane compare-and-select in registers (it packs the masks), which
/// made it most of PQ training's time. Multiplies and adds stay separate (no FMA), in the
/// portable loop's order, so both give the same index bit for bit.
#[cfg(all(
    target_arch = "x86_64",
    any(feature = "colmap-model", feature = "localize")
))]
#[allow(unsafe_code)]
mod avx {
    use super::LANES;
    use std::arch::x86_64::*;

    /// [`super::NearestF16::scores`] with AVX and F16C (`x` at most `dims` values); false,
    /// with nothing pushed, without them. Panics if the blocks do not hold `dims` columns for
    /// every norm.
    #[cfg(feature = "localize")]
    pub(super) fn scores_f16(
        blocks: &[u16],
        minus_half_norms: &[f32],
        dims: usize,
        x: &[f32],
        out: &mut Vec<f32>,
    ) -> bool {
        if !(std::arch::is_x86_feature_detected!("avx")
            && std::arch::is_x86_feature_detected!("f16c"))
        {
            return false;
        }
        assert!(x.len() <= dims && minus_half_norms.len() % LANES == 0);
        assert!(blocks.len() >= minus_half_norms.len() * dims);
        // SAFETY: AVX and F16C are present (checked above); the asserts are the bounds the
        // function's reads rely on.
        unsafe { scores_f16_avx(blocks, minus_half_norms, dims, x, out) };
        true
    }

    /// # Safety
    /// AVX and F16C must be present; the arguments as [`scores_f16`] asserts.
    #[cfg(feature = "localize")]
    #[target_feature(enable = "avx,f16c")]
    unsafe fn scores_f16_avx(
        blocks: &[u16],
        minus_half_norms: &[f32],
        dims: usize,
        x: &[f32],
        out: &mut Vec<f32>,
    ) {
        for b in 0..minus_half_norms.len() / LANES {
            let mut acc = [_mm256_setzero_ps(); 4];
            for (d, &v) in x.iter().enumerate() {
                // SAFETY: (b·dims + d)·LANES + LANES ≤ blocks.len(), as d < x.len() ≤ dims and
                // b < minus_half_norms.len() / LANES (asserted by the caller).
                let lanes = unsafe {
                    _mm256_cvtph_ps(_mm_loadu_si128(
                        blocks.as_ptr().add((b * dims + d) * LANES) as *const __m128i
                    ))
                };
                acc[d % 4] = _mm256_add_ps(acc[d % 4], _mm256_mul_ps(_mm256_set1_ps(v), lanes));
            }
            let sum = _mm256_add_ps(_mm256_add_ps(acc[0], acc[1]), _mm256_add_ps(acc[2], acc[3]));
            let mut lanes = [0.0f32; LANES];
            // SAFETY: `lanes` holds LANES f32.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), sum) };
            for (l, &h) in lanes
                .iter()
                .zip(&minus_half_norms[b * LANES..(b + 1) * LANES])
            {
                out.push(l + h);
            }
        }
    }

    /// The nearest centroid (before clamping) of each of `xs`, scoring their first `used`
    /// values, or `None` without AVX. Panics if an `x` is shorter than `used`, `used`
    /// exceeds `dims`, or the blocks do not hold `dims` columns for every norm.
    pub(super) fn nearest_rows<const R: usize>(
        xs: &[&[f32]; R],
        used: usize,
        dims: usize,
        blocks: &[f32],
        minus_half_norms: &[f32],
    ) -> Option<[usize; R]> {
        if !std::arch::is_x86_feature_detected!("avx") {
            return None;
        }
        assert!(used <= dims && xs.iter().all(|x| x.len() >= used));
        assert!(minus_half_norms.len() % LANES == 0);
        assert!(blocks.len() >= minus_half_norms.len() * dims);
        // SAFETY: AVX is present (checked above); the asserts are the bounds the function's
        // reads rely on.
        Some(unsafe { nearest_rows_avx(xs, used, dims, blocks, minus_half_norms) })
    }

    /// # Safety
    /// AVX must be present; `xs`, `used`, `dims`, `blocks` and `minus_half_norms` as
    /// [`nearest_rows`] asserts. (An `unsafe fn` so that the crate's Rust 1.85 builds it:
    /// safe `#[target_feature]` functions need 1.86, safe intrinsics in them 1.87.)
    #[target_feature(enable = "avx")]
    unsafe fn nearest_rows_avx<const R: usize>(
        xs: &[&[f32]; R],
        used: usize,
        dims: usize,
        blocks: &[f32],
        minus_half_norms: &[f32],
    ) -> [usize; R] {
        let mut best = [_mm256_set1_ps(f32::NEG_INFINITY); R];
        let mut best_block = [_mm256_setzero_ps(); R];
        for b in 0..minus_half_norms.len() / LANES {
            // SAFETY: b·LANES + LANES ≤ minus_half_norms.len() (the loop's bound); the block's
            // columns d < used ≤ dims lie below (b + 1)·dims·LANES ≤ blocks.len() (asserted by
            // the caller); x[d] with d < used ≤ x.len() (asserted).
            let norms = unsafe { _mm256_loadu_ps(minus_half_norms.as_ptr().add(b * LANES)) };
            let mut acc = [norms; R];
            let block = unsafe { blocks.as_ptr().add(b * dims * LANES) };
            for d in 0..used {
                let column = unsafe { _mm256_loadu_ps(block.add(d * LANES)) };
                for r in 0..R {
                    let v = _mm256_set1_ps(unsafe { *xs[r].get_unchecked(d) });
                    acc[r] = _mm256_add_ps(acc[r], _mm256_mul_ps(v, column));
                }
            }
            // Strictly greater (ordered): a lane keeps its first block on ties; NaN never wins.
            let index = _mm256_set1_ps(b as f32);
            for r in 0..R {
                let better = _mm256_cmp_ps::<_CMP_GT_OQ>(acc[r], best[r]);
                best[r] = _mm256_blendv_ps(best[r], acc[r], better);
                best_block[r] = _mm256_blendv_ps(best_block[r], index, better);
            }
        }
        // SAFETY: AVX is present (this function's contract).
        std::array::from_fn(|r| unsafe { first_maximum_avx(best[r], best_block[r]) })
    }

    /// [`first_maximum`] in registers: the maximum broadcast to every lane, then the lowest
    /// index among the lanes that hold it (indices are exact in f32 below 2²⁴).
    /// # Safety
    /// AVX must be present.
    #[target_feature(enable = "avx")]
    unsafe fn first_maximum_avx(best: __m256, best_block: __m256) -> usize {
        let mut max = _mm256_max_ps(best, _mm256_permute2f128_ps::<0x01>(best, best));
        max = _mm256_max_ps(max, _mm256_permute_ps::<0b0100_1110>(max));
        max = _mm256_max_ps(max, _mm256_permute_ps::<0b1011_0001>(max));
        let lane = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
        let index = _mm256_add_ps(
            _mm256_mul_ps(best_block, _mm256_set1_ps(LANES as f32)),
            lane,
        );
        let is_max = _mm256_cmp_ps::<_CMP_EQ_OQ>(best, max);
        let mut min = _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), index, is_max);
        min = _mm256_min_ps(min, _mm256_permute2f128_ps::<0x01>(min, min));
        min = _mm256_min_ps(min, _mm256_permute_ps::<0b0100_1110>(min));
        min = _mm256_min_ps(min, _mm256_permute_ps::<0b1011_0001>(min));
        let first = _mm256_cvtss_f32(min);
        // Every lane is −∞ or better, so one always equals the maximum; `as` saturates anyway.
        first as usize
    }
}

#[cfg(all(test, feature = "colmap-model"))]
mod tests {
    use super::*;

    /// [`NearestF16::scores`] gives the portable loop's bits on the AVX path (every cluster
    /// count, full and partial blocks, short rows), each within f16 rounding of the f32
    /// scores, and orders as [`Nearest`] does where no two centroids are near a tie.
    #[cfg(all(feature = "localize", feature = "colmap"))]
    #[test]
    fn f16_list_scores_match_the_portable_loop_bit_for_bit() {
        let mut rng = crate::geometry::SplitMix64::new(9);
        for (clusters, dims) in [(3348usize, 64usize), (13, 7), (1, 4), (9, 1)] {
            let centroids: Vec<f32> = (0..clusters * dims)
                .map(|_| rng.next_f64() as f32 - 0.5)
                .collect();
            let half = NearestF16::new(&centroids, dims);
            let exact = Nearest::new(&centroids, dims);
            for used in [dims, dims.div_ceil(2)] {
                let x: Vec<f32> = (0..used).map(|_| rng.next_f64() as f32 - 0.5).collect();
                let got = half.scores(&x);
                let mut portable = Vec::new();
                scores_f16_portable(
                    &half.blocks,
                    &half.minus_half_norms,
                    dims,
                    &x,
                    &mut portable,
                );
                portable.truncate(clusters);
                assert_eq!(
                    got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    portable.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    "{clusters} × {dims}, {used} used"
                );
                let f32_scores = exact.scores(&x);
                for (a, b) in got.iter().zip(&f32_scores) {
                    // Each of the 2 × dims terms within f16's rounding (2⁻¹¹ of values under 0.5).
                    assert!((a - b).abs() < 1e-3 * dims as f32, "{a} vs {b}");
                }
            }
        }
        // Centroids far apart order the same in f16 as in f32.
        let centroids = [1.0f32, 0.0, 0.0, 1.0, -1.0, 0.0, 0.7, 0.7];
        let x = [0.9f32, 0.1];
        assert_eq!(
            NearestF16::new(&centroids, 2).order(&x),
            Nearest::new(&centroids, 2).order(&x)
        );
    }

    /// [`Nearest::find`] is the first maximum of `−‖c‖²/2 + x₀c₀ + x₁c₁ + …` summed in that
    /// order, bit for bit, for cluster counts that do and do not fill the last block, with
    /// ties, and 0 when no score is a number.
    #[test]
    fn nearest_is_the_first_maximum_of_the_scalar_scores() {
        let mut rng = crate::geometry::SplitMix64::new(4);
        for (clusters, dims) in [(256usize, 8usize), (13, 3), (1, 4), (9, 1)] {
            let mut centroids: Vec<f32> = (0..clusters * dims)
                .map(|_| rng.next_f64() as f32 - 0.5)
                .collect();
            // Ties: the same centroid twice, the lower index must win — across lanes (1 and
            // the last), across blocks in one lane (1 and 9), and between lane 7 of block 0
            // and lane 0 of block 1 (7 and 8).
            let copy = |c: &mut Vec<f32>, from: usize, to: usize| {
                let v = c[from * dims..(from + 1) * dims].to_vec();
                c[to * dims..(to + 1) * dims].copy_from_slice(&v);
            };
            if clusters > 2 {
                copy(&mut centroids, 1, clusters - 1);
            }
            if clusters > 9 {
                copy(&mut centroids, 1, 9);
                copy(&mut centroids, 7, 8);
            }
            let nearest = Nearest::new(&centroids, dims);
            let (mut rows, mut wants) = (Vec::new(), Vec::new());
            for t in 0..200 {
                let x: Vec<f32> = if t == 0 && clusters > 2 {
                    centroids[dims..2 * dims].to_vec()
                } else if t == 1 && clusters > 9 {
                    centroids[7 * dims..8 * dims].to_vec()
                } else {
                    (0..dims).map(|_| rng.next_f64() as f32 - 0.5).collect()
                };
                let scores: Vec<f32> = centroids
                    .chunks_exact(dims)
                    .map(|c| {
                        let mut s = 0.0f32;
                        for &v in c {
                            s -= 0.5 * v * v;
                        }
                        for (&xv, &cv) in x.iter().zip(c) {
                            s += xv * cv;
                        }
                        s
                    })
                    .collect();
                let max = scores.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let want = scores.iter().position(|&s| s == max).unwrap();
                assert_eq!(nearest.find(&x), want, "{clusters} clusters, row {t}");
                // The portable loop (the one without AVX) agrees too.
                let portable =
                    nearest_in_blocks(&x, dims, &nearest.blocks, &nearest.minus_half_norms);
                assert_eq!(portable.min(clusters - 1), want);
                rows.extend_from_slice(&x);
                wants.push(want);
            }
            // `find_each`: rows in groups of ROWS_PER_PASS and a partial group (202 = 50·4 + 2).
            rows.extend(vec![f32::NAN; dims]);
            wants.push(0);
            rows.extend_from_slice(&centroids[..dims]);
            wants.push(0);
            let mut got = Vec::new();
            nearest.find_each(rows.chunks_exact(dims), |i, c| got.push((i, c)));
            let want_pairs: Vec<(usize, usize)> = wants.iter().copied().enumerate().collect();
            assert_eq!(got, want_pairs, "{clusters} clusters");
            assert_eq!(nearest.find(&vec![f32::NAN; dims]), 0);
            // An empty `x` scores only `−‖c‖²/2`: the shortest centroid, no panic.
            let norms: Vec<f32> = centroids
                .chunks_exact(dims)
                .map(|c| c.iter().fold(0.0f32, |s, &v| s - 0.5 * v * v))
                .collect();
            let max = norms.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let shortest = norms.iter().position(|&s| s == max).unwrap();
            assert_eq!(nearest.find(&[]), shortest);
        }
        assert_eq!(Nearest::new(&[], 3).find(&[1.0, 2.0, 3.0]), 0);
    }

    #[test]
    fn unit_rows_zero_rows_and_dots() {
        let mut v = vec![3.0, 4.0, 0.0, 0.0, 0.0, 0.0];
        normalise_rows(&mut v, 2);
        assert_eq!(v, [0.6, 0.8, 0.0, 0.0, 0.0, 0.0]);
        normalise_rows(&mut v, 0);
        // 19 values: two full lanes of 8 and a tail of 3.
        let a: Vec<f32> = (0..19).map(|i| i as f32).collect();
        let b: Vec<f32> = (0..19).map(|i| (19 - i) as f32).collect();
        let expected: f32 = (0..19).map(|i| (i * (19 - i)) as f32).sum();
        assert_eq!(dot(&a, &b), expected);
        assert_eq!(dot(&[], &[]), 0.0);
        // Below the threshold a row is left as it is, as the extractor's reference does.
        let mut tiny = vec![1e-20f32, 0.0];
        normalise_rows(&mut tiny, 2);
        assert_eq!(tiny, [1e-20, 0.0]);
    }
}

#[cfg(all(test, any(feature = "colmap-model", feature = "localize")))]
mod widen_tests {
    /// Every one of the 65,536 f16 values widens to `half`'s f32 (NaNs to NaNs of the same
    /// sign), also at an odd length that leaves a tail.
    #[test]
    fn widening_agrees_with_half_on_every_value() {
        let all: Vec<half::f16> = (0..=u16::MAX).map(half::f16::from_bits).collect();
        for len in [all.len(), 13] {
            let mut out = vec![0.0f32; len];
            super::widen_f16(&all[..len], &mut out);
            for (h, &got) in all.iter().zip(&out) {
                let want = h.to_f32();
                if want.is_nan() {
                    assert!(got.is_nan() && got.is_sign_negative() == want.is_sign_negative());
                } else {
                    assert_eq!(got.to_bits(), want.to_bits(), "{:#06x}", h.to_bits());
                }
            }
        }
    }
}
