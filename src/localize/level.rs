//! One selected level of a map, indexed for matching over the map's own f16 descriptor
//! blocks (views of the mapping for raw sections): rows are decoded and normalised a block or
//! a row at a time where they are compared, never the level at once, and nothing is computed
//! per row at open.

use super::{LocalizeError, LocalizeOptions};
use crate::format::{f16, Level};
use std::borrow::Cow;

/// One selected level, ready for matching. Everything here is sized by the level's own
/// points and its sections' actual lengths: a map of many small levels costs what its
/// sections hold, never levels × points.
pub(super) struct LevelIndex<'m> {
    pub(super) id: u16,
    /// The global point of each row, strictly increasing (the map's own array).
    pub(super) points: Cow<'m, [u32]>,
    /// The level's `short` block as the map stores it (`[rows × ds]` f16, a view of the
    /// mapping for raw sections), and its `rest` block (`[rows × dr]`) when it is matched.
    pub(super) short: Cow<'m, [f16]>,
    pub(super) rest: Option<Cow<'m, [f16]>>,
    pub(super) ds: usize,
    pub(super) dr: usize,
    /// Matched dimensions (`ds`, or `ds + dr` with `rest`), at least 1.
    pub(super) dim: usize,
    /// `[dim × d_in]`: maps a query descriptor into the stored basis (first `dim` rows).
    pub(super) projection: Option<Vec<f32>>,
    /// The query descriptors' dimension this level takes, at least `dim`.
    pub(super) d_in: usize,
}

impl LevelIndex<'_> {
    /// Row `r` decoded and normalised into `out` (`dim` values): the same values, bit for
    /// bit, as normalising the decoded row with `vector::l2_normalise`.
    pub(super) fn decode_row(&self, r: usize, out: &mut [f32]) {
        let (short, rest) = out.split_at_mut(self.ds);
        decode(&self.short[r * self.ds..(r + 1) * self.ds], short);
        if let Some(block) = &self.rest {
            decode(&block[r * self.dr..(r + 1) * self.dr], rest);
        }
        Self::scale_row(out);
    }

    /// The level rows of `points` (ascending global indices), ascending: each found by a
    /// galloping search from where the last one ended, O(c log(n / c)) for c candidates,
    /// never a scan of the level. `None` for `None` (every row).
    pub(super) fn rows_of(&self, points: Option<&[u32]>) -> Option<Vec<u32>> {
        let points = points?;
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
        Some(rows)
    }

    /// Normalises a decoded row: its norm is computed where it is decoded, not stored, so
    /// opening a level costs nothing per row (a 1 M-point level's norms took 0.27 s to
    /// compute at open and 4 MB to keep).
    pub(super) fn scale_row(out: &mut [f32]) {
        crate::vector::l2_normalise(out);
    }
}

/// f16 → f32 (exact), through `half`'s slice conversion (F16C where the CPU has it).
pub(super) fn decode(from: &[f16], to: &mut [f32]) {
    use half::slice::HalfFloatSliceExt;
    from.convert_to_f32_slice(to);
}

/// What the localizer takes of one level, as the map holds it, before any check.
struct LevelParts<'m> {
    id: u16,
    dim_short: usize,
    dim_full: usize,
    /// Whether the map holds the level's `rest` block (`rest` is it when it is matched).
    has_rest: bool,
    points: Cow<'m, [u32]>,
    short: Cow<'m, [f16]>,
    rest: Option<Cow<'m, [f16]>>,
    /// `[dim_full × d_in]` and `d_in`.
    projection: Option<(Cow<'m, [f32]>, usize)>,
}

/// Reads what [`build_level`] needs of `level` (views of the mapping for raw sections).
pub(super) fn index_level<'m>(
    level: &Level<'m>,
    options: &LocalizeOptions,
    n_points: u64,
) -> Result<Result<LevelIndex<'m>, String>, LocalizeError> {
    let parts = LevelParts {
        id: level.id(),
        dim_short: level.dim_short(),
        dim_full: level.dim_full(),
        has_rest: level.has_rest(),
        points: level.points()?,
        short: level.desc_short()?,
        rest: if options.short {
            None
        } else {
            level.desc_rest()?
        },
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
        projection,
    } = parts;
    let n = points.len();
    if n == 0 {
        return Ok(Err("no points".into()));
    }
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
    let bad = |message: String| LocalizeError::BadLevel { level: id, message };
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
    if points.last().is_some_and(|&p| u64::from(p) >= n_points)
        || points.windows(2).any(|w| w[0] >= w[1])
    {
        return Err(bad(
            "point indices are not increasing indices of the map's points".into(),
        ));
    }
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
    let dr = if rest.is_some() { dr } else { 0 };
    Ok(Ok(LevelIndex {
        id,
        points,
        short,
        rest,
        ds,
        dr,
        dim,
        projection,
        d_in,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn halves(n: usize) -> Cow<'static, [f16]> {
        Cow::Owned(vec![f16::from_f32(0.5); n])
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
                index.rows_of(Some(&c)).unwrap(),
                naive(&c),
                "1 in {density}"
            );
        }
        assert_eq!(index.rows_of(Some(&[])).unwrap(), Vec::<u32>::new());
        assert_eq!(index.rows_of(Some(&[8_997, 9_000])).unwrap(), [2_999]);
        assert!(index.rows_of(None).is_none());
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
}
