//! Descriptor matching: query × map similarity through a blocked GEMM (matrixmultiply's
//! sgemm), keeping per query the best and second-best map rows and per map row its best
//! query, for the ratio test and the mutual-nearest-neighbour check. No O(N·M) scalar loop:
//! the inner products all go through the GEMM kernel.

use super::kernels::sgemm_abt;
/// Options of [`match_descriptors`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatchOptions {
    /// Lowe's ratio on distances between unit vectors: keep a match when
    /// `d(best) < ratio · d(second)`, with `d = sqrt(2 − 2·similarity)`. 1.0 disables it.
    pub ratio: f32,
    /// Keep only mutual nearest neighbours.
    pub mutual: bool,
    /// Keep only matches with at least this similarity (cosine).
    pub min_similarity: f32,
}

impl Default for MatchOptions {
    fn default() -> Self {
        MatchOptions {
            ratio: 0.9,
            mutual: true,
            min_similarity: 0.0,
        }
    }
}

/// Lowe's ratio for a map's descriptors ([`super::LocalizeOptions::for_map`]; `sfpmap
/// localize` without `--ratio`, the demo, the C ABI): [`MatchOptions`]'s 0.9
/// (SIFT's habit), and 0.95 for the SFP network's descriptors (`sfp-*`), whose short blocks
/// separate neighbours less. On the shared scenes (2026-12-04, sfp-v1 and sfp-v2s, full and
/// level-2 short maps) 0.95 localized Sacre-Coeur's level-2 slices 2/2 instead of 1/2 and 0/2
/// (6–7 inliers of the 8 needed at 0.9), and left South Building and KITTI 06 at 100 % with
/// median errors equal or lower. Learned features from files (`aliked-n16`, `rootsift`,
/// `features-<dim>`, …) get 0.95 too: on hloc-style ALIKED South Building
/// (`benches/hloc_south_building.py`) it localized 26/26 at the reference's errors.
pub fn default_ratio(descriptor: &str) -> f32 {
    if is_sfp_descriptor(descriptor) {
        0.95
    } else {
        MatchOptions::default().ratio
    }
}

/// Whether a map's descriptor kind is a learned one (an SFP model's `sfp.model_name`, whatever
/// it is, or a learned feature from a file): not `""` (geometry only), not `sift`, not a COLMAP
/// database's `colmap-<dim>`. Whether an extractor makes it is the session's question
/// (`Fit::check_extractable`, which also asks where the map's descriptors came from).
pub fn is_sfp_descriptor(descriptor: &str) -> bool {
    !(descriptor.is_empty() || descriptor == "sift" || descriptor.starts_with("colmap-"))
}

/// A match: query row, map row, cosine similarity.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    pub query: u32,
    pub map: u32,
    pub similarity: f32,
}

/// Map rows per GEMM block: bounds the score buffer at `queries × BLOCK` floats (2 MB for
/// 1,024 keypoints). With 2,048 rows the 8 MB buffer came in fresh pages at every call: the
/// 100 k street's level-2 short queries 5.1 -> 4.2 ms, the 1 M SIFT map's 23 -> 20.7 ms
/// (256 rows: no faster).
const BLOCK: usize = 512;
/// Map rows per block of [`match_scored_by_row`]: with its chunks of at most 256 queries, a
/// block's scores are at most 256 KB.
const BLOCK_BY_ROW: usize = 256;

/// Matches unit-norm `query` rows (`[n_q × dim]`) against unit-norm `map` rows
/// (`[n_m × dim]`), both row-major f32 (the benches' and tests' entry; the localizer decodes
/// its rows through `match_rows`).
#[cfg(any(test, feature = "fuzzing"))]
pub fn match_descriptors(
    query: &[f32],
    map: &[f32],
    dim: usize,
    options: &MatchOptions,
) -> Vec<Match> {
    if dim == 0 {
        return Vec::new();
    }
    let n_m = map.len() / dim;
    match_rows(query, n_m, dim, options, |start, tile| {
        tile.copy_from_slice(&map[start * dim..start * dim + tile.len()]);
    })
}

/// [`match_descriptors`] against `n_m` map rows that `fill(start, tile)` writes, a block of
/// at most [`BLOCK`] rows at a time, into `tile` (`rows × dim`): the map's rows never need to be
/// in memory as f32 all at once (the localizer decodes them from the mapping's f16). `tile` is
/// per-thread scratch holding an earlier block's or query's values: `fill` writes all of it.
pub(crate) fn match_rows(
    query: &[f32],
    n_m: usize,
    dim: usize,
    options: &MatchOptions,
    mut fill: impl FnMut(usize, &mut [f32]),
) -> Vec<Match> {
    if dim == 0 {
        return Vec::new();
    }
    let n_q = query.len() / dim;
    if n_q == 0 || n_m == 0 {
        return Vec::new();
    }
    super::scratch::with_f32(BLOCK.min(n_m) * dim, |tile| {
        match_scored(n_q, n_m, options, |start, rows, out| {
            let block = &mut tile[..rows * dim];
            fill(start, block);
            sgemm_abt(query, block, out, n_q, rows, dim);
        })
    })
}

/// The matching of [`match_rows`] over similarities that `score(start, rows, out)` writes for
/// every query against map rows `start..start + rows` (at most [`BLOCK`]), query by query, into
/// `out` (`[n_q × rows]`): the GEMM of decoded rows. (A PQ level's asymmetric distances use
/// [`match_scored_by_row`], which takes queries a chunk at a time, scores map-row-major.)
/// `out` is per-thread scratch holding earlier scores: `score` writes every value of it.
pub(crate) fn match_scored(
    n_q: usize,
    n_m: usize,
    options: &MatchOptions,
    mut score: impl FnMut(usize, usize, &mut [f32]),
) -> Vec<Match> {
    if n_q == 0 || n_m == 0 {
        return Vec::new();
    }
    let mut best = vec![(f32::NEG_INFINITY, u32::MAX); n_q];
    let mut second = vec![f32::NEG_INFINITY; n_q];
    // The best similarity of each map row over all queries: query q is map row m's nearest
    // neighbour exactly when S[q][m] reaches it, so no per-score argmax bookkeeping is needed.
    let mut column_max = vec![f32::NEG_INFINITY; n_m];
    super::scratch::with_f32(n_q * BLOCK.min(n_m), |scores| {
        for start in (0..n_m).step_by(BLOCK) {
            let rows = BLOCK.min(n_m - start);
            let out = &mut scores[..n_q * rows];
            score(start, rows, out);
            let columns = &mut column_max[start..start + rows];
            for (q, row) in out.chunks_exact(rows).enumerate() {
                let (s1, j, runner_up) = scan_row(row, columns);
                if s1 > best[q].0 {
                    // The old best is a candidate for second, as is this block's runner-up.
                    second[q] = best[q].0.max(runner_up);
                    best[q] = (s1, (start + j) as u32);
                } else if s1 > second[q] {
                    second[q] = s1;
                }
            }
        }
    });
    select(&best, &second, &column_max, options)
}

/// One pass over a query's scores against a block of map rows (`row` is not empty): its
/// maximum, the maximum's first index and the runner-up (the maximum without that index),
/// while raising `columns` (each row's best score over the queries so far) to `row`. Eight
/// lanes each keep their maximum, its index and their second best, with selects only, so
/// the loop vectorizes (separate passes for the maximum, its index and the columns cost as
/// much as the GEMM at 32 dimensions); compiled for AVX-512 and AVX2 too, chosen at run time.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
fn scan_row(row: &[f32], columns: &mut [f32]) -> (f32, usize, f32) {
    const L: usize = 8;
    let mut top = [f32::NEG_INFINITY; L];
    // Lane k holds indices k, k + 8, …: its first maximum's index, its second best.
    let mut at: [u32; L] = std::array::from_fn(|k| k as u32);
    let mut next = [f32::NEG_INFINITY; L];
    let chunks = row.chunks_exact(L);
    let tail = chunks.remainder();
    for (i, (x, c)) in chunks.zip(columns.chunks_exact_mut(L)).enumerate() {
        for k in 0..L {
            let v = x[k];
            let lower = if v > top[k] { top[k] } else { v };
            next[k] = if lower > next[k] { lower } else { next[k] };
            at[k] = if v > top[k] {
                (i * L + k) as u32
            } else {
                at[k]
            };
            top[k] = if v > top[k] { v } else { top[k] };
            c[k] = if v > c[k] { v } else { c[k] };
        }
    }
    // The lanes and the tail: the overall maximum at its first index; all else (the other
    // lanes' maxima, every lane's second best, the tail) is a candidate for runner-up.
    let base = row.len() - tail.len();
    let lanes = (0..L.min(base)).map(|k| (top[k], at[k] as usize, next[k]));
    // (A NaN never wins a lane's comparison; in the tail it counts as no score.)
    let tail_values = (base..row.len()).map(|i| {
        let v = if row[i].is_nan() {
            f32::NEG_INFINITY
        } else {
            row[i]
        };
        (v, i, f32::NEG_INFINITY)
    });
    let mut best: Option<(f32, usize)> = None;
    let mut runner_up = f32::NEG_INFINITY;
    for (v, index, below) in lanes.chain(tail_values) {
        runner_up = runner_up.max(below);
        match best {
            Some((b, i)) if !(v > b || (v == b && index < i)) => runner_up = runner_up.max(v),
            _ => {
                if let Some((b, _)) = best {
                    runner_up = runner_up.max(b);
                }
                best = Some((v, index));
            }
        }
    }
    let (best, index) = best.unwrap_or((f32::NEG_INFINITY, 0));
    for (c, &v) in columns[base..].iter_mut().zip(tail) {
        *c = if v > *c { v } else { *c };
    }
    (best, index, runner_up)
}

/// [`match_scored`] over similarities written map-row-major: `score(queries, start, rows,
/// out)` writes row `start + r` against query `queries.start + i` at
/// `out[r × queries.len() + i]`, the layout of a PQ level's asymmetric distances, which score
/// one map row against a chunk of queries at once. Same matches as [`match_scored`] on the
/// same similarities (ties go to the first row), with no transposition: per row a maximum
/// across queries, per query a best/second update by minima and maxima that vectorizes.
pub(crate) fn match_scored_by_row(
    n_q: usize,
    n_m: usize,
    query_chunk: usize,
    options: &MatchOptions,
    mut score: impl FnMut(std::ops::Range<usize>, usize, usize, &mut [f32]),
) -> Vec<Match> {
    if n_q == 0 || n_m == 0 {
        return Vec::new();
    }
    let chunk = query_chunk.clamp(1, n_q);
    let mut best = vec![f32::NEG_INFINITY; n_q];
    let mut arg = vec![u32::MAX; n_q];
    let mut second = vec![f32::NEG_INFINITY; n_q];
    let mut column_max = vec![f32::NEG_INFINITY; n_m];
    let mut scores = vec![0.0f32; chunk * BLOCK_BY_ROW.min(n_m)];
    for first in (0..n_q).step_by(chunk) {
        let queries = first..(first + chunk).min(n_q);
        let width = queries.len();
        for start in (0..n_m).step_by(BLOCK_BY_ROW) {
            let rows = BLOCK_BY_ROW.min(n_m - start);
            let out = &mut scores[..rows * width];
            score(queries.clone(), start, rows, out);
            let before = best[queries.clone()].to_vec();
            update_by_row(
                out,
                width,
                &mut column_max[start..start + rows],
                &mut best[queries.clone()],
                &mut second[queries.clone()],
            );
            // A query whose best improved in this block: its first row reaching it.
            for (i, (&b, &was)) in best[queries.clone()].iter().zip(&before).enumerate() {
                if b > was {
                    let r = out[i..].iter().step_by(width).position(|&v| v == b);
                    arg[first + i] = (start + r.unwrap_or(0)) as u32;
                }
            }
        }
    }
    let best: Vec<(f32, u32)> = best.into_iter().zip(arg).collect();
    select(&best, &second, &column_max, options)
}

/// [`match_scored_by_row`]'s bookkeeping of one block (`scores`: rows of `width` queries):
/// each row's maximum, each query's best and second best. Minima and maxima only, so it
/// vectorizes; compiled for AVX2 too and chosen at run time.
#[multiversion::multiversion(targets(
    "x86_64+avx512f+avx512bw+avx512vl+avx2+fma",
    "x86_64+avx2+fma",
    "x86_64+avx"
))]
fn update_by_row(
    scores: &[f32],
    width: usize,
    column_max: &mut [f32],
    best: &mut [f32],
    second: &mut [f32],
) {
    for (row, c) in scores.chunks_exact(width).zip(column_max) {
        let mut lanes = [f32::NEG_INFINITY; 8];
        let chunks = row.chunks_exact(8);
        let tail = chunks.remainder();
        for x in chunks {
            for k in 0..8 {
                lanes[k] = if x[k] > lanes[k] { x[k] } else { lanes[k] };
            }
        }
        let row_max = lanes
            .iter()
            .chain(tail)
            .fold(f32::NEG_INFINITY, |m, &v| m.max(v));
        *c = c.max(row_max);
        for ((&v, b), s) in row.iter().zip(&mut *best).zip(&mut *second) {
            // The loser of (v, best) is a candidate for second.
            let lower = if v > *b { *b } else { v };
            *s = if lower > *s { lower } else { *s };
            *b = if v > *b { v } else { *b };
        }
    }
}

/// The matches the best and second-best row of each query and the best query of each map row
/// allow: similarity, ratio test, mutual check.
fn select(
    best: &[(f32, u32)],
    second: &[f32],
    column_max: &[f32],
    options: &MatchOptions,
) -> Vec<Match> {
    let mut matches = Vec::new();
    for (q, &(s, m)) in best.iter().enumerate() {
        if m == u32::MAX || s < options.min_similarity {
            continue;
        }
        if options.ratio < 1.0 && fails_ratio_test(s, second[q], options.ratio) {
            continue;
        }
        if options.mutual && s < column_max[m as usize] {
            continue;
        }
        matches.push(Match {
            query: q as u32,
            map: m,
            similarity: s,
        });
    }
    matches
}

/// Lowe's ratio test on cosine similarities of unit vectors, as distances: the best match
/// fails when its distance is not below `ratio` times the second best's. No second (`-inf`)
/// passes.
pub(crate) fn fails_ratio_test(best: f32, second: f32, ratio: f32) -> bool {
    let distance = |s: f32| (2.0 - 2.0 * s).max(0.0).sqrt();
    second.is_finite() && distance(best) >= ratio * distance(second)
}

#[cfg(test)]
mod tests {

    #[test]
    fn sfp_maps_get_the_looser_ratio_and_others_sift_s() {
        for sfp in ["sfp-v1", "sfp-v2s", "unnamed", "my-model"] {
            assert!(is_sfp_descriptor(sfp), "{sfp}");
            assert_eq!(default_ratio(sfp), 0.95, "{sfp}");
        }
        for other in ["", "sift", "colmap-64", "colmap-128"] {
            assert!(!is_sfp_descriptor(other), "{other}");
            assert_eq!(
                default_ratio(other),
                MatchOptions::default().ratio,
                "{other}"
            );
        }
    }
    use super::*;
    use crate::vector::normalise_rows;

    fn unit(v: &[f32]) -> Vec<f32> {
        let mut v = v.to_vec();
        let dim = v.len();
        normalise_rows(&mut v, dim);
        v
    }

    #[test]
    fn gemm_matches_naive_product() {
        let (n, m, k) = (5, 7, 3);
        let a: Vec<f32> = (0..n * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.11).cos()).collect();
        let mut out = vec![0.0; n * m];
        sgemm_abt(&a, &b, &mut out, n, m, k);
        for i in 0..n {
            for j in 0..m {
                let want: f32 = (0..k).map(|t| a[i * k + t] * b[j * k + t]).sum();
                assert!((out[i * m + j] - want).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn finds_mutual_ratio_matches_across_blocks() {
        // 3000 map rows (two blocks); queries equal to rows 5 and 2500 plus an ambiguous one.
        let dim = 4;
        let mut map = Vec::new();
        for i in 0..3000 {
            let t = i as f32 * 0.001;
            map.extend(unit(&[t.cos(), t.sin(), 0.2, (i % 7) as f32 * 0.01]));
        }
        let mut query = Vec::new();
        query.extend_from_slice(&map[5 * dim..6 * dim]);
        query.extend_from_slice(&map[2500 * dim..2501 * dim]);
        let opts = MatchOptions {
            ratio: 1.0,
            mutual: true,
            min_similarity: 0.5,
        };
        let found = match_descriptors(&query, &map, dim, &opts);
        assert_eq!(
            found.iter().map(|m| (m.query, m.map)).collect::<Vec<_>>(),
            vec![(0, 5), (1, 2500)]
        );
        // A query halfway between two rows is ambiguous: the ratio test rejects it, while an
        // exact query (distance 0 to its best row) passes any ratio.
        let between: Vec<f32> = (0..dim)
            .map(|k| map[100 * dim + k] + map[101 * dim + k])
            .collect();
        let between = unit(&between);
        let strict = MatchOptions { ratio: 0.8, ..opts };
        assert!(match_descriptors(&between, &map, dim, &strict).is_empty());
        assert_eq!(match_descriptors(&query, &map, dim, &strict).len(), 2);
    }

    #[test]
    fn row_major_scores_give_the_same_matches() {
        // 3 chunks of queries × several blocks of rows; a coarse grid of scores makes ties,
        // and each query has one clear best (query q's row 700·q + 5 scores 0.99) so the
        // ratio test and the mutual check pass for some of them.
        let (n_q, n_m) = (7, 5000);
        let mut rng = crate::geometry::SplitMix64::new(5);
        let mut scores: Vec<f32> = (0..n_q * n_m)
            .map(|_| (rng.next_f64() * 40.0).floor() as f32 / 80.0)
            .collect();
        for q in 0..n_q {
            scores[q * n_m + 700 * q + 5] = 0.99;
        }
        for options in [
            MatchOptions::default(),
            MatchOptions {
                ratio: 1.0,
                mutual: false,
                min_similarity: 0.9,
            },
        ] {
            let by_query = match_scored(n_q, n_m, &options, |start, rows, out| {
                for q in 0..n_q {
                    out[q * rows..(q + 1) * rows]
                        .copy_from_slice(&scores[q * n_m + start..q * n_m + start + rows]);
                }
            });
            let by_row = match_scored_by_row(n_q, n_m, 3, &options, |qs, start, rows, out| {
                let w = qs.len();
                for (i, q) in qs.enumerate() {
                    for r in 0..rows {
                        out[r * w + i] = scores[q * n_m + start + r];
                    }
                }
            });
            assert_eq!(by_query, by_row);
            assert_eq!(by_row.len(), n_q, "{by_row:?}");
            assert!(by_row
                .iter()
                .all(|m| m.map == 700 * m.query + 5 && m.similarity == 0.99));
        }
    }

    #[test]
    fn one_pass_row_scan_agrees_with_separate_passes() {
        // Lengths around the 8 lanes, a coarse grid of values (ties within and across lanes).
        let mut rng = crate::geometry::SplitMix64::new(9);
        for len in [1, 3, 7, 8, 9, 15, 16, 17, 40, 301] {
            for _ in 0..20 {
                // Values in [-1, 1) on a grid of sixths, and now and then -inf (no score).
                let row: Vec<f32> = (0..len)
                    .map(|_| match rng.next_f64() {
                        u if u < 0.05 => f32::NEG_INFINITY,
                        u => ((u * 12.0).floor() as f32 - 6.0) / 6.0,
                    })
                    .collect();
                let mut columns: Vec<f32> =
                    (0..len).map(|_| (rng.next_f64() as f32) - 0.5).collect();
                let want_columns: Vec<f32> =
                    columns.iter().zip(&row).map(|(c, v)| c.max(*v)).collect();
                let max = row.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                let first = row.iter().position(|&v| v == max).unwrap();
                let runner_up = row
                    .iter()
                    .enumerate()
                    .filter(|&(i, _)| i != first)
                    .fold(f32::NEG_INFINITY, |m, (_, &v)| m.max(v));
                assert_eq!(
                    scan_row(&row, &mut columns),
                    (max, first, runner_up),
                    "{row:?}"
                );
                assert_eq!(columns, want_columns);
            }
        }
    }

    #[test]
    fn empty_inputs_give_no_matches() {
        assert!(match_descriptors(&[], &[1.0, 0.0], 2, &MatchOptions::default()).is_empty());
        assert!(match_descriptors(&[1.0, 0.0], &[], 2, &MatchOptions::default()).is_empty());
    }
}
