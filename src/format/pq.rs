//! Product-quantised levels (1.1): a level's descriptors stored as `M` one-byte codes per
//! point, each naming one of `K ≤ 256` centroids of its subspace (Jégou, Douze & Schmid,
//! "Product quantization for nearest neighbor search", 2011). The shape rules are checked at
//! open, the codes against the codebook on first access; the view hands both out zero-copy.

use super::error::Error;
use super::layout::{Dtype, SectionKind, MAX_DESCRIPTOR_DIM};
use super::metadata::LevelInfo;
use super::reader::Section;
use super::writer::{owned_bytes, MapWriter};
use std::borrow::Cow;

/// Codes are one byte: at most 256 centroids per subspace.
pub const MAX_PQ_CENTROIDS: u64 = 256;

/// A product-quantised level's descriptors: `subspaces` (M) codes per point over `dims`
/// (`dim_short`, or `dim_full` when the quantised vector includes the `rest` dimensions), each
/// subspace `sub_dims` = dims / M wide with `centroids` (K) centroids. The quantised vector is
/// the stored descriptor's first `dims` values, L2-normalised, taken in `order` when there is
/// one (position `j` of the quantised vector is level dimension `order[j]`).
#[derive(Debug, Clone)]
pub struct Pq<'m> {
    /// Codes per point (`M`).
    pub subspaces: usize,
    /// Centroids per subspace (`K`).
    pub centroids: usize,
    /// Dimensions per subspace.
    pub sub_dims: usize,
    /// `[M·K × sub_dims]` f32: subspace m's centroid k is row `m·K + k`.
    pub codebook: Cow<'m, [f32]>,
    /// `[n_L × M]`: point r's centroid in subspace m is `codes[r·M + m]`.
    pub codes: Cow<'m, [u8]>,
    /// `[dims]`, a permutation of `0..dims` (checked on first access); `None` = the identity.
    pub order: Option<Cow<'m, [u16]>>,
}

impl Pq<'_> {
    /// Dimensions the codes quantise: `subspaces × sub_dims`.
    pub fn dims(&self) -> usize {
        self.subspaces * self.sub_dims
    }

    /// Row `r` reconstructed from its codes into `out` (`dims` values, in the level's
    /// dimension order), not renormalised.
    pub fn decode_row(&self, r: usize, out: &mut [f32]) {
        let (m, k, d) = (self.subspaces, self.centroids, self.sub_dims);
        for (s, &code) in self.codes[r * m..(r + 1) * m].iter().enumerate() {
            let row = s * k + usize::from(code);
            let centroid = &self.codebook[row * d..(row + 1) * d];
            match &self.order {
                None => out[s * d..(s + 1) * d].copy_from_slice(centroid),
                Some(order) => {
                    for (&dim, &v) in order[s * d..(s + 1) * d].iter().zip(centroid) {
                        out[usize::from(dim)] = v;
                    }
                }
            }
        }
    }
}

/// `row` (level dimensions) in quantisation order into `out`: `out[j] = row[order[j]]`, a
/// copy without an order. The one gather every PQ user shares (the writer's encoder, the
/// localizer's query tables); [`Pq::decode_row`] is its inverse.
#[cfg(any(feature = "localize", feature = "colmap-model", test))]
pub fn gather(order: Option<&[u16]>, row: &[f32], out: &mut [f32]) {
    match order {
        None => out.copy_from_slice(&row[..out.len()]),
        Some(order) => {
            for (o, &dim) in out.iter_mut().zip(order) {
                *o = row[usize::from(dim)];
            }
        }
    }
}

impl MapWriter<'_> {
    /// Replaces `level`'s f16 descriptor blocks by product-quantisation codes (format 1.1):
    /// `codebook` `[M·K × dims/M]` f32 (subspace m's centroid k is row `m·K + k`) and `codes`
    /// `[points × M]`, over `dims` = `dim_short`, or `dim_full` when the codes include the
    /// `rest` dimensions. `order` (`[dims]`, a permutation of `0..dims`) is the level
    /// dimension at each position of the quantised vector; `None` = the identity. All three
    /// sections are written required: a reader that does not know them cannot match the level,
    /// so a 1.0 reader refuses the map.
    pub fn set_level_pq(
        &mut self,
        level: u16,
        subspaces: usize,
        centroids: usize,
        (codebook, codes): (Vec<f32>, Vec<u8>),
        order: Option<Vec<u16>>,
    ) -> Result<&mut Self, Error> {
        let info = self.metadata.level(level).ok_or_else(|| {
            Error::invalid(format!("level {level}: add the level before its PQ codes"))
        })?;
        let (ds, df) = (info.dim_short as usize, info.dim_full as usize);
        let wrong = |what: String| Err(Error::invalid(format!("level {level}: {what}")));
        if subspaces == 0 || !(1..=MAX_PQ_CENTROIDS as usize).contains(&centroids) {
            return wrong(format!(
                "{subspaces} subspaces of {centroids} centroids: needs at least one subspace and 1 to 256 centroids"
            ));
        }
        if subspaces as u64 > MAX_DESCRIPTOR_DIM {
            return wrong(format!(
                "{subspaces} subspaces: more than {}",
                MAX_DESCRIPTOR_DIM
            ));
        }
        let rows = subspaces * centroids;
        if codebook.iter().any(|v| !v.is_finite()) {
            return wrong("a centroid value is not finite".into());
        }
        if codebook.is_empty() || codebook.len() % rows != 0 {
            return wrong(format!(
                "a codebook of {} values is not {subspaces} x {centroids} centroid rows",
                codebook.len()
            ));
        }
        let sub_dims = codebook.len() / rows;
        let dims = subspaces * sub_dims;
        if dims != ds && dims != df {
            return wrong(format!(
                "{subspaces} subspaces x {sub_dims} dimensions = {dims}, neither dim_short {ds} nor dim_full {df}"
            ));
        }
        let points = self
            .sections
            .get(&(SectionKind::LevelPoints.code(), level))
            .map_or(0, |s| s.rows as usize);
        if codes.len() != points * subspaces {
            return wrong(format!(
                "{} codes for {points} points x {subspaces} subspaces",
                codes.len()
            ));
        }
        if let Some(&c) = codes.iter().find(|&&c| usize::from(c) >= centroids) {
            return wrong(format!(
                "code {c} past the codebook's {centroids} centroids"
            ));
        }
        if let Some(order) = &order {
            if order.len() != dims {
                return wrong(format!(
                    "an order of {} dimensions for {dims} quantised ones",
                    order.len()
                ));
            }
            if let Err(what) = check_order(order) {
                return wrong(format!("PQ order {what}"));
            }
        }
        for kind in [
            SectionKind::LevelDescShort,
            SectionKind::LevelDescRest,
            SectionKind::LevelPqOrder,
        ] {
            self.sections.remove(&(kind.code(), level));
        }
        if let Some(order) = order {
            self.push_array(
                SectionKind::LevelPqOrder,
                level,
                Dtype::U16,
                dims,
                1,
                owned_bytes(order),
            );
        }
        self.push_array(
            SectionKind::LevelPqCodebook,
            level,
            Dtype::F32,
            rows,
            sub_dims,
            owned_bytes(codebook),
        );
        self.push_array(
            SectionKind::LevelPqCodes,
            level,
            Dtype::U8,
            points,
            subspaces,
            Cow::Owned(codes),
        );
        Ok(self)
    }
}

/// Open's rules for a level's PQ sections, from the table alone: both or neither, one code
/// row per level point, `K` in 1..=256 centroids per subspace, and `M × sub_dims` equal to
/// `dim_short` or `dim_full`. Returns the quantised dimensions, `None` without PQ.
pub(crate) fn check_shapes(
    level: &LevelInfo,
    n: u64,
    codebook: Option<&Section>,
    codes: Option<&Section>,
    order: Option<&Section>,
) -> Result<Option<u64>, Error> {
    let l = Some(level.level);
    let (codebook, codes) = match (codebook, codes) {
        (None, None) => {
            return match order {
                Some(o) => Err(Error::inconsistent(format!(
                    "{} on a level without PQ codes",
                    o.reference()
                ))),
                None => Ok(None),
            }
        }
        (Some(b), Some(c)) => (b, c),
        (Some(_), None) => {
            return Err(Error::MissingSection {
                kind: SectionKind::LevelPqCodes,
                level: l,
            })
        }
        (None, Some(_)) => {
            return Err(Error::MissingSection {
                kind: SectionKind::LevelPqCodebook,
                level: l,
            })
        }
    };
    let (m, sub_dims) = (codes.cols, codebook.cols);
    if codes.rows != n {
        return Err(Error::inconsistent(format!(
            "{} has {} rows, expected {n} (one per level point)",
            codes.reference(),
            codes.rows
        )));
    }
    let k = codebook.rows.checked_div(m).unwrap_or(0);
    if m == 0 || sub_dims == 0 || codebook.rows % m != 0 || !(1..=MAX_PQ_CENTROIDS).contains(&k) {
        return Err(Error::inconsistent(format!(
            "{} is {} x {} for {m} subspaces: needs M x K rows (K from 1 to {MAX_PQ_CENTROIDS} centroids per subspace) of at least one dimension",
            codebook.reference(),
            codebook.rows,
            sub_dims
        )));
    }
    // Both are at most MAX_DESCRIPTOR_DIM (checked per entry), so this cannot overflow.
    let dims = m * sub_dims;
    if dims != u64::from(level.dim_short) && dims != u64::from(level.dim_full) {
        return Err(Error::inconsistent(format!(
            "level {}: {m} subspaces x {sub_dims} dimensions = {dims}, neither dim_short {} nor dim_full {}",
            level.level, level.dim_short, level.dim_full
        )));
    }
    if let Some(o) = order.filter(|o| o.rows != dims) {
        return Err(Error::inconsistent(format!(
            "{} has {} rows, expected {dims} (one per quantised dimension)",
            o.reference(),
            o.rows
        )));
    }
    Ok(Some(dims))
}

/// The first-access rule of the order: a permutation of `0..D`, each dimension once.
pub(crate) fn check_order(order: &[u16]) -> Result<(), String> {
    let mut sorted = order.to_vec();
    sorted.sort_unstable();
    // Sorted, the first position j not holding j shows a repeat (it holds j − 1) or a gap.
    match sorted
        .iter()
        .enumerate()
        .find(|&(j, &d)| usize::from(d) != j)
    {
        Some((j, &d)) if usize::from(d) < j => Err(format!(
            "not a permutation of 0..{}: dimension {d} appears twice",
            order.len()
        )),
        Some((j, _)) => Err(format!(
            "not a permutation of 0..{}: dimension {j} is missing",
            order.len()
        )),
        None => Ok(()),
    }
}
/// The first-access rule of the codes: every code names a centroid of the codebook (`< K`).
/// `codebook` is the level's codebook section (for `K`).
pub(crate) fn check_codes(codes: &[u8], m: u64, codebook: &Section) -> Result<(), String> {
    let k = codebook.rows / m.max(1);
    match codes.iter().position(|&c| u64::from(c) >= k) {
        Some(i) => Err(format!(
            "point row {}, subspace {}: code {} past the codebook's {k} centroids",
            i as u64 / m,
            i as u64 % m,
            codes[i]
        )),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_order_is_a_permutation_of_its_positions() {
        assert_eq!(check_order(&[2, 0, 3, 1]), Ok(()));
        assert_eq!(check_order(&[]), Ok(()));
        let err = |o: &[u16]| check_order(o).unwrap_err();
        assert_eq!(
            err(&[0, 0, 1]),
            "not a permutation of 0..3: dimension 0 appears twice"
        );
        assert_eq!(
            err(&[0, 2, 3]),
            "not a permutation of 0..3: dimension 1 is missing"
        );
        assert_eq!(
            err(&[1, 2, 3]),
            "not a permutation of 0..3: dimension 0 is missing"
        );
        assert_eq!(
            err(&[0, 1, 9]),
            "not a permutation of 0..3: dimension 2 is missing"
        );
    }

    #[test]
    fn gather_and_decode_are_inverse() {
        let pq = Pq {
            subspaces: 2,
            centroids: 1,
            sub_dims: 2,
            codebook: Cow::Owned(vec![10.0, 20.0, 30.0, 40.0]),
            codes: Cow::Owned(vec![0, 0]),
            // Not its own inverse: reading it backwards gives another row.
            order: Some(Cow::Owned(vec![1, 2, 3, 0])),
        };
        let mut row = [0.0f32; 4];
        pq.decode_row(0, &mut row);
        assert_eq!(row, [40.0, 10.0, 20.0, 30.0]);
        let mut back = [0.0f32; 4];
        gather(pq.order.as_deref(), &row, &mut back);
        assert_eq!(back, [10.0, 20.0, 30.0, 40.0]);
        gather(None, &row, &mut back);
        assert_eq!(back, row);
    }
}
