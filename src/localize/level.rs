//! One selected level of a map, indexed for matching over the map's own descriptors as they
//! are stored (views of the mapping for raw sections): f16 blocks, whose rows are decoded and
//! normalised a block or a row at a time where they are compared, never the level at once, or
//! (1.1) PQ codes, compared by asymmetric distance (`adc`) and reconstructed where a row is
//! needed. Nothing is computed per row at open.

use super::{LocalizeError, LocalizeOptions};
use crate::format::{f16, CheckedByChunk, Error as FormatError, Level, Pq};
use std::borrow::Cow;

/// One selected level, ready for matching. Everything here is sized by the level's own
/// points and its sections' actual lengths: a map of many small levels costs what its
/// sections hold, never levels × points.
pub(super) struct LevelIndex<'m> {
    pub(super) id: u16,
    /// The global point of each row, strictly increasing (the map's own array).
    pub(super) points: Cow<'m, [u32]>,
    pub(super) stored: Stored<'m>,
    /// Matched dimensions (`ds`, or `ds + dr` with `rest`; a PQ level's quantised dims), at
    /// least 1.
    pub(super) dim: usize,
    /// `[dim × d_in]`: maps a query descriptor into the stored basis (first `dim` rows).
    pub(super) projection: Option<Vec<f32>>,
    /// The query descriptors' dimension this level takes, at least `dim`.
    pub(super) d_in: usize,
}

/// The shortest `short` block coarse matching compares alone (the measured one: SIFT's 32 of
/// 128): in a few dimensions every similarity is near ±1 and the ratio test keeps nothing.
const COARSE_PREFIX_MIN_DIMS: usize = 32;

/// A level's descriptors as the map stores them.
pub(super) enum Stored<'m> {
    /// The `short` block (`[rows × ds]` f16, a view of the mapping for raw sections), and the
    /// `rest` block (`[rows × dr]`) when it is matched. With chunk checksums (1.2) both are
    /// checked where they are read: [`LevelIndex::rows_of`] checks a query's rows before
    /// matching reads them.
    F16 {
        short: CheckedByChunk<'m, f16>,
        rest: Option<CheckedByChunk<'m, f16>>,
        ds: usize,
        dr: usize,
    },
    /// PQ codes and codebook (1.1).
    Pq(Pq<'m>),
}

impl LevelIndex<'_> {
    /// The leading dimensions coarse matching compares: the `short` block's when the level
    /// also matches its `rest` and the block has at least [`COARSE_PREFIX_MIN_DIMS`],
    /// otherwise all of them. Coarse matching only seeds guided matching, which compares every
    /// dimension; on the 1 M-point street's SIFT map the 32-dimension prefix cut coarse
    /// matching 17 -> 3.3 ms a query, at the same accuracy there and on the shared scenes' 12
    /// variants.
    ///
    /// Only on a level stored in a basis (`level_projection`, SIFT's PCA): its leading
    /// dimensions carry most of the variance. An SFP level's short block is the network's
    /// own, with no such order: on Sacre-Coeur's SFP map (level 2, 64 of 192 dimensions) the
    /// prefix gave coarse RANSAC more outliers, 0.5 -> 6 ms a query.
    pub(super) fn coarse_dim(&self) -> usize {
        match &self.stored {
            Stored::F16 {
                rest: Some(_), ds, ..
            } if *ds >= COARSE_PREFIX_MIN_DIMS && self.projection.is_some() => *ds,
            _ => self.dim,
        }
    }

    /// Row `r` decoded (or, for PQ, reconstructed) and normalised into `out`: its first
    /// `out.len()` values, `dim` or `coarse_dim` of them. For f16 the same values, bit for
    /// bit, as normalising the decoded values with `vector::l2_normalise`.
    pub(super) fn decode_row(&self, r: usize, out: &mut [f32]) {
        match &self.stored {
            Stored::F16 {
                short,
                rest,
                ds,
                dr,
            } => {
                let (to_short, to_rest) = out.split_at_mut(*ds);
                debug_assert!(
                    short.is_checked(r * ds..(r + 1) * ds),
                    "row {r} read unchecked"
                );
                crate::vector::widen_f16(&short.unchecked()[r * ds..(r + 1) * ds], to_short);
                if let Some(block) = rest.as_ref().filter(|_| !to_rest.is_empty()) {
                    debug_assert!(block.is_checked(r * dr..(r + 1) * dr));
                    crate::vector::widen_f16(&block.unchecked()[r * dr..(r + 1) * dr], to_rest);
                }
            }
            Stored::Pq(pq) => pq.decode_row(r, out),
        }
        Self::scale_row(out);
    }

    /// Fills `tile` (`k × dims`, `dims` being `dim` or `coarse_dim`) with the decoded,
    /// normalised rows `rows[..k]`. A run of consecutive f16 rows is converted a block in one
    /// call; `rest_run` is scratch for its `rest` values.
    pub(super) fn fill_rows(
        &self,
        rows: &[usize],
        dims: usize,
        tile: &mut [f32],
        rest_run: &mut Vec<f32>,
    ) {
        debug_assert!(dims == self.dim || dims == self.coarse_dim());
        let dim = dims;
        let n = tile.len() / dim;
        let first = rows[0];
        let Stored::F16 {
            short,
            rest,
            ds,
            dr,
        } = &self.stored
        else {
            for (k, out) in tile.chunks_exact_mut(dim).enumerate() {
                self.decode_row(rows[k], out);
            }
            return;
        };
        if rows[n - 1] != first + n - 1 {
            for (k, out) in tile.chunks_exact_mut(dim).enumerate() {
                self.decode_row(rows[k], out);
            }
            return;
        }
        let (ds, dr) = (*ds, *dr);
        debug_assert!(short.is_checked(first * ds..(first + n) * ds));
        let short = short.unchecked();
        match rest.as_ref().filter(|_| dim > ds) {
            None => crate::vector::widen_f16(&short[first * ds..(first + n) * ds], tile),
            Some(rest) => {
                debug_assert!(rest.is_checked(first * dr..(first + n) * dr));
                rest_run.resize(n * dr, 0.0);
                crate::vector::widen_f16(&rest.unchecked()[first * dr..(first + n) * dr], rest_run);
                let short = &short[first * ds..(first + n) * ds];
                for (k, out) in tile.chunks_exact_mut(dim).enumerate() {
                    crate::vector::widen_f16(&short[k * ds..(k + 1) * ds], &mut out[..ds]);
                    out[ds..].copy_from_slice(&rest_run[k * dr..(k + 1) * dr]);
                }
            }
        }
        for out in tile.chunks_exact_mut(dim) {
            Self::scale_row(out);
        }
    }

    /// The level rows of `points` (ascending global indices), ascending: each found by a
    /// galloping search from where the last one ended, O(c log(n / c)) for c candidates,
    /// never a scan of the level. `None` for `None` (every row). The rows' stored descriptors
    /// are checked (1.2: the chunks holding them, once per map), so matching may read them.
    pub(super) fn rows_of(&self, points: Option<&[u32]>) -> Result<Option<Vec<u32>>, FormatError> {
        let Some(points) = points else {
            // Every row: chunk by chunk (O(chunks), free once checked), not row by row.
            if let Stored::F16 { short, rest, .. } = &self.stored {
                short.check_all()?;
                rest.as_ref().map_or(Ok(()), |rest| rest.check_all())?;
            }
            return Ok(None);
        };
        let level = &self.points[..];
        let mut rows = Vec::with_capacity(points.len().min(level.len()));
        let mut from = 0;
        for &p in points {
            // Gallop: double the step until the level passes p, then search that stretch.
            let mut step = 1;
            while from + step < level.len() && level[from + step] < p {
                step *= 2;
            }
            let end = (from + step + 1).min(level.len());
            match level[from..end].binary_search(&p) {
                Ok(i) => {
                    rows.push((from + i) as u32);
                    from += i + 1;
                }
                Err(i) => from += i,
            }
            if from >= level.len() {
                break;
            }
        }
        self.check_rows(rows.iter().map(|&r| r as usize))?;
        Ok(Some(rows))
    }

    /// Checks the stored descriptors of `rows` (ascending) where the map checks them by chunk.
    fn check_rows(&self, rows: impl Iterator<Item = usize> + Clone) -> Result<(), FormatError> {
        if let Stored::F16 {
            short,
            rest,
            ds,
            dr,
        } = &self.stored
        {
            short.check_rows(rows.clone(), *ds)?;
            if let Some(rest) = rest {
                rest.check_rows(rows, *dr)?;
            }
        }
        Ok(())
    }

    /// Normalises a decoded row: its norm is computed where it is decoded, not stored, so
    /// opening a level costs nothing per row (a 1 M-point level's norms took 0.27 s to
    /// compute at open and 4 MB to keep).
    pub(super) fn scale_row(out: &mut [f32]) {
        crate::vector::l2_normalise(out);
    }
}

/// What the localizer takes of one level, as the map holds it, before any check.
struct LevelParts<'m> {
    id: u16,
    dim_short: usize,
    dim_full: usize,
    /// Whether the map holds the level's `rest` block (`rest` is it when it is matched).
    has_rest: bool,
    points: Cow<'m, [u32]>,
    short: CheckedByChunk<'m, f16>,
    rest: Option<CheckedByChunk<'m, f16>>,
    /// The PQ codes (1.1), instead of `short` and `rest` (then empty and `None`).
    pq: Option<Pq<'m>>,
    /// `[dim_full × d_in]` and `d_in`.
    projection: Option<(Cow<'m, [f32]>, usize)>,
}

/// Reads what [`build_level`] needs of `level` (views of the mapping for raw sections).
pub(super) fn index_level<'m>(
    level: &Level<'m>,
    options: &LocalizeOptions,
    n_points: u64,
) -> Result<Result<LevelIndex<'m>, String>, LocalizeError> {
    let pq = level.pq()?;
    let parts = LevelParts {
        id: level.id(),
        dim_short: level.dim_short(),
        dim_full: level.dim_full(),
        has_rest: level.has_rest(),
        points: level.points()?,
        short: if pq.is_some() {
            CheckedByChunk::from_checked(Cow::Borrowed(&[]))
        } else {
            level.desc_short_by_chunk()?
        },
        // A PQ level's codes cover what they cover: `short` cannot cut them.
        rest: if options.short || pq.is_some() {
            None
        } else {
            level.desc_rest_by_chunk()?
        },
        pq,
        projection: level
            .projection()?
            .map(|p| (p, level.projection_input_dim().unwrap_or(0))),
    };
    build_level(parts, n_points)
}

/// Indexes one level for matching, or says why it is skipped. Every buffer is sized from the
/// sections' actual lengths, checked against the level's dimensions with checked arithmetic:
/// the dims the metadata states size nothing, whatever the reader let through.
fn build_level(
    parts: LevelParts<'_>,
    n_points: u64,
) -> Result<Result<LevelIndex<'_>, String>, LocalizeError> {
    let LevelParts {
        id,
        dim_short: ds,
        dim_full: df,
        has_rest,
        points,
        short,
        rest,
        pq,
        projection,
    } = parts;
    let n = points.len();
    if n == 0 {
        return Ok(Err("no points".into()));
    }
    let bad = |message: String| LocalizeError::BadLevel { level: id, message };
    if points.last().is_some_and(|&p| u64::from(p) >= n_points)
        || points.windows(2).any(|w| w[0] >= w[1])
    {
        return Err(bad(
            "point indices are not increasing indices of the map's points".into(),
        ));
    }
    let (stored, dim) = match pq {
        Some(pq) => {
            // The reader checked the shapes and every code against the codebook; these are
            // the sizes indexing relies on, re-checked on the arrays actually read.
            let dim = pq.dims();
            let codebook = pq
                .subspaces
                .checked_mul(pq.centroids)
                .and_then(|r| r.checked_mul(pq.sub_dims));
            if dim == 0
                || n.checked_mul(pq.subspaces) != Some(pq.codes.len())
                || codebook != Some(pq.codebook.len())
                || pq.order.as_ref().is_some_and(|o| o.len() != dim)
            {
                return Err(bad(format!(
                    "PQ codes ({} bytes) and codebook ({} values) do not fit {n} points x {} subspaces of {} centroids x {} dimensions",
                    pq.codes.len(),
                    pq.codebook.len(),
                    pq.subspaces,
                    pq.centroids,
                    pq.sub_dims
                )));
            }
            (Stored::Pq(pq), dim)
        }
        None => match f16_blocks(ds, df, has_rest, n, short, rest, &bad)? {
            Ok(blocks) => blocks,
            Err(why) => return Ok(Err(why)),
        },
    };
    let (projection, d_in) = match projection {
        Some((p, d_in)) => {
            if d_in == 0 {
                return Ok(Err("the projection takes no input dimensions".into()));
            }
            // A projection to more dimensions than it reads adds nothing to match, and would
            // make a query's projection larger than the query.
            if dim > d_in {
                return Ok(Err(format!(
                    "the projection maps {d_in} input dimensions to {dim}"
                )));
            }
            let used = dim
                .checked_mul(d_in)
                .filter(|&k| k <= p.len())
                .ok_or_else(|| {
                    bad(format!(
                        "projection has {} values, fewer than {dim} x {d_in}",
                        p.len()
                    ))
                })?;
            (Some(p[..used].to_vec()), d_in)
        }
        None => (None, df),
    };
    Ok(Ok(LevelIndex {
        id,
        points,
        stored,
        dim,
        projection,
        d_in,
    }))
}

/// The f16 blocks of a level of `n` points, checked against its dims: the stored form and the
/// matched dims, or why the level is skipped.
#[allow(clippy::type_complexity)]
fn f16_blocks<'m>(
    ds: usize,
    df: usize,
    has_rest: bool,
    n: usize,
    short: CheckedByChunk<'m, f16>,
    rest: Option<CheckedByChunk<'m, f16>>,
    bad: &impl Fn(String) -> LocalizeError,
) -> Result<Result<(Stored<'m>, usize), String>, LocalizeError> {
    // `LevelInfo::matched_dims`, on the blocks actually read.
    let dim = if rest.is_some() { df } else { ds };
    if dim == 0 {
        let why = if has_rest {
            "dim_short 0: nothing to match with the short block only"
        } else {
            "dim_short 0 and no rest block: nothing to match"
        };
        return Ok(Err(why.into()));
    }
    if n.checked_mul(ds) != Some(short.len()) {
        return Err(bad(format!(
            "short block has {} values, not {n} points x {ds} dimensions",
            short.len()
        )));
    }
    let dr = df
        .checked_sub(ds)
        .ok_or_else(|| bad(format!("dim_short {ds} > dim_full {df}")))?;
    if let Some(rest) = &rest {
        if n.checked_mul(dr) != Some(rest.len()) {
            return Err(bad(format!(
                "rest block has {} values, not {n} points x {dr} dimensions",
                rest.len()
            )));
        }
    }
    let dr = if rest.is_some() { dr } else { 0 };
    Ok(Ok((
        Stored::F16 {
            short,
            rest,
            ds,
            dr,
        },
        dim,
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn halves(n: usize) -> CheckedByChunk<'static, f16> {
        CheckedByChunk::from_checked(Cow::Owned(vec![f16::from_f32(0.5); n]))
    }

    fn parts(points: Vec<u32>, ds: usize, df: usize) -> LevelParts<'static> {
        let n = points.len();
        LevelParts {
            id: 3,
            dim_short: ds,
            dim_full: df,
            has_rest: false,
            points: Cow::Owned(points),
            short: halves(n * ds),
            rest: None,
            pq: None,
            projection: None,
        }
    }

    fn skipped(parts: LevelParts<'_>) -> String {
        match build_level(parts, 100) {
            Ok(Err(reason)) => reason,
            Ok(Ok(_)) => panic!("indexed"),
            Err(e) => panic!("error: {e}"),
        }
    }

    fn refused(parts: LevelParts<'_>) -> String {
        match build_level(parts, 100) {
            Err(LocalizeError::BadLevel { level: 3, message }) => message,
            Err(e) => panic!("other error: {e}"),
            Ok(_) => panic!("accepted"),
        }
    }

    #[test]
    fn rows_of_candidates_are_the_level_rows_holding_them() {
        // A level of every third point; candidate lists dense, sparse, past the end, empty.
        let points: Vec<u32> = (0..3000).map(|i| i * 3).collect();
        let index = match build_level(parts(points.clone(), 2, 2), 10_000) {
            Ok(Ok(index)) => index,
            _ => panic!("indexed"),
        };
        let naive = |c: &[u32]| -> Vec<u32> {
            (0..points.len() as u32)
                .filter(|&r| c.binary_search(&points[r as usize]).is_ok())
                .collect()
        };
        let mut rng = 12345u64;
        for density in [1u64, 2, 7, 100, 5000] {
            let mut c: Vec<u32> = Vec::new();
            for p in 0..9_100u32 {
                rng = rng
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                if (rng >> 33) % density == 0 {
                    c.push(p);
                }
            }
            assert_eq!(
                index.rows_of(Some(&c)).unwrap().unwrap(),
                naive(&c),
                "1 in {density}"
            );
        }
        assert_eq!(
            index.rows_of(Some(&[])).unwrap().unwrap(),
            Vec::<u32>::new()
        );
        assert_eq!(
            index.rows_of(Some(&[8_997, 9_000])).unwrap().unwrap(),
            [2_999]
        );
        assert!(index.rows_of(None).unwrap().is_none());
    }

    // The localizer's own checks, whatever the reader's limits let through: degenerate or
    // absurd dims are skipped or refused before anything is sized from them.

    #[test]
    fn dim_short_0_without_rest_is_skipped() {
        assert!(skipped(parts(vec![0, 1, 2], 0, 0)).contains("dim_short 0"));
        assert!(skipped(parts(vec![0, 1, 2], 0, 8)).contains("no rest block"));
    }

    #[test]
    fn an_empty_level_is_skipped_whatever_its_dims() {
        let mut p = parts(vec![], 1, u32::MAX as usize);
        p.has_rest = true;
        p.rest = Some(halves(0));
        assert_eq!(skipped(p), "no points");
    }

    #[test]
    fn dims_the_sections_do_not_hold_are_refused_not_allocated() {
        // One point claiming 2^32 - 1 full dimensions with an empty rest block.
        let mut p = parts(vec![7], 4, u32::MAX as usize);
        p.has_rest = true;
        p.rest = Some(halves(0));
        assert!(refused(p).contains("rest block has 0 values"));
        // A product that overflows usize is refused the same way.
        let mut p = parts(vec![6, 7], 4, 8);
        p.dim_short = usize::MAX / 2 + 1;
        assert!(refused(p).contains("short block"));
        let mut p = parts(vec![0, 1], 2, 2);
        p.short = halves(3);
        assert!(refused(p).contains("short block has 3 values"));
    }

    #[test]
    fn points_out_of_range_or_unsorted_are_refused() {
        assert!(refused(parts(vec![5, 100], 2, 2)).contains("point indices"));
        assert!(refused(parts(vec![5, 5], 2, 2)).contains("point indices"));
    }

    #[test]
    fn projections_no_query_can_fit_are_skipped() {
        let mut p = parts(vec![1], 4, 4);
        p.projection = Some((Cow::Owned(vec![]), 0));
        assert!(skipped(p).contains("no input dimensions"));
        let mut p = parts(vec![1], 4, 4);
        p.projection = Some((Cow::Owned(vec![1.0; 8]), 2));
        assert!(skipped(p).contains("maps 2 input dimensions to 4"));
        let mut p = parts(vec![1], 4, 4);
        p.projection = Some((Cow::Owned(vec![1.0; 7]), 2 + 2));
        assert!(refused(p).contains("projection has 7 values"));
    }

    #[test]
    fn a_sound_level_is_indexed_from_its_sections() {
        let mut p = parts(vec![1, 4], 2, 3);
        p.has_rest = true;
        p.rest = Some(halves(2));
        let level = build_level(p, 100).unwrap().unwrap();
        assert_eq!((level.dim, level.d_in, level.points.len()), (3, 3, 2));
        let mut row = [0.0; 3];
        level.decode_row(1, &mut row);
        let norm: f32 = row.iter().map(|v| v * v).sum();
        assert!((norm - 1.0).abs() < 1e-6);
    }

    #[test]
    fn fill_rows_and_decode_row_take_the_short_prefix_coarse_matching_compares() {
        // 3 points, 32 short + 2 rest dims, every value distinct (and exact in f16).
        let (ds, dr) = (COARSE_PREFIX_MIN_DIMS, 2);
        let mut p = parts(vec![1, 4, 9], ds, ds + dr);
        p.short = CheckedByChunk::from_checked(Cow::Owned(
            (0..3 * ds).map(|v| f16::from_f32(v as f32 + 1.0)).collect(),
        ));
        p.has_rest = true;
        p.rest = Some(CheckedByChunk::from_checked(Cow::Owned(
            (0..3 * dr)
                .map(|v| f16::from_f32(-(v as f32) - 1.0))
                .collect(),
        )));
        p.projection = Some(identity(ds + dr));
        let level = build_level(p, 100).unwrap().unwrap();
        assert_eq!((level.dim, level.coarse_dim()), (ds + dr, ds));
        let unit = |v: &[f32]| {
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            v.iter().map(|x| x / n).collect::<Vec<f32>>()
        };
        let short = |r: usize| (r * ds..(r + 1) * ds).map(|v| v as f32 + 1.0);
        let rest = |r: usize| (r * dr..(r + 1) * dr).map(|v| -(v as f32) - 1.0);
        let mut scratch = Vec::new();
        // A run of consecutive rows (one block) and scattered rows (row by row) agree.
        for rows in [vec![0usize, 1, 2], vec![2, 0]] {
            let mut prefix = vec![0.0; rows.len() * ds];
            level.fill_rows(&rows, ds, &mut prefix, &mut scratch);
            let mut full = vec![0.0; rows.len() * (ds + dr)];
            level.fill_rows(&rows, ds + dr, &mut full, &mut scratch);
            for (k, &r) in rows.iter().enumerate() {
                let want_prefix = unit(&short(r).collect::<Vec<_>>());
                assert_eq!(
                    prefix[k * ds..(k + 1) * ds],
                    want_prefix[..],
                    "rows {rows:?}"
                );
                let all: Vec<f32> = short(r).chain(rest(r)).collect();
                let got = &full[k * (ds + dr)..(k + 1) * (ds + dr)];
                assert_eq!(got, &unit(&all)[..], "rows {rows:?}");
                let mut one = vec![0.0; ds];
                level.decode_row(r, &mut one);
                assert_eq!(one, want_prefix);
            }
        }
        // Without rest, coarse matching compares every dimension.
        let plain = build_level(parts(vec![1], 2, 2), 100).unwrap().unwrap();
        assert_eq!(plain.coarse_dim(), plain.dim);
        // So it does with a short block too small to match alone, and takes one that is not,
        // in a basis; without one (an SFP level: the network's own dimensions), every one.
        for (ds, basis, coarse) in [
            (COARSE_PREFIX_MIN_DIMS - 1, true, 40),
            (COARSE_PREFIX_MIN_DIMS, true, 32),
            (COARSE_PREFIX_MIN_DIMS, false, 40),
        ] {
            let mut p = parts(vec![1], ds, 40);
            p.has_rest = true;
            p.rest = Some(halves(40 - ds));
            p.projection = basis.then(|| identity(40));
            let level = build_level(p, 100).unwrap().unwrap();
            assert_eq!(
                (level.dim, level.coarse_dim()),
                (40, coarse),
                "{ds} short dims, basis {basis}"
            );
        }
    }

    /// The identity basis of `d` dimensions, as `LevelParts::projection` takes it.
    fn identity(d: usize) -> (Cow<'static, [f32]>, usize) {
        let values = (0..d * d)
            .map(|i| if i % (d + 1) == 0 { 1.0 } else { 0.0 })
            .collect();
        (Cow::Owned(values), d)
    }
}
