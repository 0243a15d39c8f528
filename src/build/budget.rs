//! `sfpmap slice --budget`: the slice of a map expected to localize best within a byte
//! budget — the paper's "adaptive reduction of keypoint map size" as a command.
//!
//! The rule (the guide, `docs/src/maps.md`, "Byte budgets") walks a fixed ladder and keeps the
//! first candidate that fits:
//! 1. level sets: every level (hierarchical, coarse to fine), then level 2 alone (the paper's
//!    choice), then each other level alone, most points first;
//! 2. for each set, descriptors from most to least faithful: full f16 as it is, full f16
//!    `--minimal`, short f16 `--minimal`, then short `--minimal` PQ with 2, 4 and 8 dimensions
//!    per one-byte code (each level its own `M = dim_short / dims per code`).
//!
//! The order comes from the accuracy-per-byte table (`docs/src/benchmarks.md`): `--minimal`
//! costs no accuracy, short costs little, PQ at 2 dims per byte little, at 8 dims per byte up
//! to a third of the recall of SFP maps; so a set is cut down its own ladder before fewer
//! levels are tried.
//! Candidates without PQ are sized exactly (encoded in memory); PQ candidates get a lower
//! bound from their set's short minimal size and are confirmed by encoding when it fits.
//! Empty levels are not tried alone, nor more than 16 single levels.

use super::pq::{centroids_for, quantise_levels, slice_encoded, PqOptions, SlicedMap};
use crate::format::{Error, Map, SliceOptions};

/// One point of the ladder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Candidate {
    /// The levels kept, in the map's numbering.
    pub levels: Vec<u16>,
    /// Only the short descriptor blocks (`slice --short`).
    pub short: bool,
    /// Without what localization does not read (`slice --minimal`).
    pub minimal: bool,
    /// Product-quantised short blocks with this many dimensions per one-byte code: level L
    /// gets `M = dim_short(L) / dims_per_code` codes per point.
    pub dims_per_code: Option<usize>,
}

impl Candidate {
    /// `slice` options for this candidate (each section keeps its codec; `delta` sections
    /// choose their own zstd level).
    pub fn options(&self) -> SliceOptions {
        SliceOptions {
            levels: self.levels.clone(),
            short: self.short,
            codec: None,
            zstd_level: 3,
            minimal: self.minimal,
        }
    }

    /// In words, close to `slice` options, e.g. `--level 2 --short --minimal --pq 16`; with
    /// several levels quantised, each level's `M` (`--pq 8/16/32`), which one `slice --pq`
    /// cannot express (it takes one `M` for every level).
    pub fn describe(&self, map: &Map<'_>) -> String {
        let mut s: Vec<String> = self.levels.iter().map(|l| format!("--level {l}")).collect();
        if self.short {
            s.push("--short".into());
        }
        if self.minimal {
            s.push("--minimal".into());
        }
        if let Some(per) = self.dims_per_code {
            let m: Vec<String> = self
                .levels
                .iter()
                .map(|&l| map.level(l).map_or(0, |v| v.dim_short() / per).to_string())
                .collect();
            s.push(format!("--pq {} ({per} dims per code)", m.join("/")));
        }
        s.join(" ")
    }

    /// The slice, quantised as the candidate says.
    pub fn slice<'m>(&self, map: &'m Map<'_>) -> Result<SlicedMap<'m>, Error> {
        let mut sliced = slice_encoded(map, &self.options(), None, None)?;
        if let Some(per) = self.dims_per_code {
            sliced
                .writer
                .metadata_mut()
                .provenance
                .parameters
                .insert("pq_dims_per_code".into(), serde_json::json!(per));
            for &l in &self.levels {
                let options = PqOptions {
                    subspaces: map.level(l)?.dim_short() / per,
                    short: true,
                };
                let done = quantise_levels(map, &mut sliced.writer, &[l], &options)?;
                sliced.pq.extend(done);
            }
        }
        Ok(sliced)
    }
}

/// A candidate with its size: exact (encoded) or estimated (PQ, before training).
#[derive(Debug, Clone)]
pub struct Sized {
    /// The candidate sized.
    pub candidate: Candidate,
    /// [`Candidate::describe`]'s words for it.
    pub description: String,
    /// Its encoded length, or the lower bound when `estimated`.
    pub bytes: u64,
    /// `bytes` is a lower bound (a PQ candidate not encoded yet).
    pub estimated: bool,
}

/// What [`slice_to_budget`] chose, and every candidate it sized on the way.
pub struct BudgetSlice<'m> {
    /// The first candidate of the ladder that fits the budget.
    pub chosen: Candidate,
    /// Its slice, ready to write.
    pub sliced: SlicedMap<'m>,
    /// The chosen slice's encoded length.
    pub bytes: u64,
    /// Every candidate sized, in ladder order, up to the chosen one.
    pub sized: Vec<Sized>,
}

impl BudgetSlice<'_> {
    /// The `budget` object of `slice --budget --json`.
    pub fn report(&self, budget: u64) -> serde_json::Value {
        let chosen = self.sized.last().map(|s| s.description.clone());
        let c = &self.chosen;
        serde_json::json!({
            "budget_bytes": budget,
            "chosen": chosen,
            "levels": c.levels,
            "short": c.short,
            "minimal": c.minimal,
            "dims_per_code": c.dims_per_code,
            "bytes": self.bytes,
            "rule": RULE,
            "candidates": self.sized.iter().map(|s| serde_json::json!({
                "options": s.description,
                "bytes": s.bytes,
                "estimated": s.estimated,
                "fits": s.bytes <= budget,
            })).collect::<Vec<_>>(),
        })
    }
}

/// Single levels tried at most (most points first).
pub(crate) const MAX_SINGLE_LEVELS: usize = 16;

/// The ladder in one line, for reports.
pub(crate) const RULE: &str = "level sets: all levels, level 2, each other level (most points first); per set: full, full --minimal, --short --minimal, --short --minimal with PQ of 2, 4, 8 dims per one-byte code; the first that fits";

/// The ladder of `map` (`levels`: the only level set to try, if given), most accurate first.
pub fn ladder(map: &Map<'_>, levels: Option<&[u16]>) -> Result<Vec<Candidate>, Error> {
    let mut sets: Vec<Vec<u16>> = Vec::new();
    match levels {
        Some(l) => {
            let mut l = l.to_vec();
            l.sort_unstable();
            l.dedup();
            sets.push(l);
        }
        None => {
            let all = map.level_ids();
            let mut singles: Vec<(u16, usize)> = map
                .levels()
                .map(|l| (l.id(), l.len()))
                .filter(|&(_, n)| n > 0)
                .collect();
            // Level 2 first, then most points first.
            singles.sort_by_key(|&(l, n)| (l != 2, std::cmp::Reverse(n), l));
            singles.truncate(MAX_SINGLE_LEVELS);
            if all.len() > 1 {
                sets.push(all);
            }
            sets.extend(singles.into_iter().map(|(l, _)| vec![l]));
        }
    }
    let mut out = Vec::new();
    for set in sets {
        let mut any_rest = false;
        let mut quantised = false;
        let mut dims = Vec::new();
        for &l in &set {
            let level = map.level(l)?;
            any_rest |= level.has_rest();
            quantised |= level.is_pq() || !level.has_descriptors();
            dims.push(level.dim_short());
        }
        let push = |out: &mut Vec<Candidate>, short, minimal, dims_per_code| {
            out.push(Candidate {
                levels: set.clone(),
                short,
                minimal,
                dims_per_code,
            })
        };
        push(&mut out, false, false, None);
        push(&mut out, false, true, None);
        if any_rest {
            push(&mut out, true, true, None);
        }
        if !quantised {
            for per in [2, 4, 8] {
                if dims.iter().all(|&d| d >= per && d % per == 0) {
                    push(&mut out, true, true, Some(per));
                }
            }
        }
    }
    Ok(out)
}

/// The first candidate of [`ladder`] that fits `budget` bytes, sliced. A budget below every
/// candidate is an error naming the smallest map this one can be cut to.
pub fn slice_to_budget<'m>(
    map: &'m Map<'_>,
    budget: u64,
    levels: Option<&[u16]>,
) -> Result<BudgetSlice<'m>, Error> {
    let mut sized: Vec<Sized> = Vec::new();
    let rungs = ladder(map, levels)?;
    // Each set's short minimal size, for its PQ estimates.
    let mut base: Option<(Vec<u16>, u64)> = None;
    for candidate in rungs {
        let description = candidate.describe(map);
        let (bytes, estimated) = match candidate.dims_per_code {
            None => {
                let sliced = candidate.slice(map)?;
                let bytes = sliced.writer.encoded_len()?;
                if candidate.short && candidate.minimal {
                    base = Some((candidate.levels.clone(), bytes));
                }
                if bytes <= budget {
                    sized.push(Sized {
                        candidate: candidate.clone(),
                        description,
                        bytes,
                        estimated: false,
                    });
                    return Ok(BudgetSlice {
                        chosen: candidate,
                        sliced,
                        bytes,
                        sized,
                    });
                }
                (bytes, false)
            }
            Some(per) => {
                let base_bytes = match &base {
                    Some((set, b)) if *set == candidate.levels => *b,
                    // No rest: the full minimal slice is the short one.
                    _ => sized
                        .iter()
                        .rev()
                        .find(|s| s.candidate.levels == candidate.levels && s.candidate.minimal)
                        .map(|s| s.bytes)
                        .unwrap_or(u64::MAX),
                };
                (estimate_pq(map, &candidate.levels, per, base_bytes)?, true)
            }
        };
        sized.push(Sized {
            candidate: candidate.clone(),
            description,
            bytes,
            estimated,
        });
        if estimated && bytes <= budget {
            let sliced = candidate.slice(map)?;
            let exact = sliced.writer.encoded_len()?;
            let last = sized.last_mut().expect("just pushed");
            last.bytes = exact;
            last.estimated = false;
            if exact <= budget {
                return Ok(BudgetSlice {
                    chosen: candidate,
                    sliced,
                    bytes: exact,
                    sized,
                });
            }
        }
    }
    let smallest = sized
        .iter()
        .min_by_key(|s| s.bytes)
        .ok_or_else(|| Error::invalid("the map has no level to slice"))?;
    Err(Error::invalid(format!(
        "no slice fits in {budget} bytes: the smallest is {}{} bytes ({})",
        if smallest.estimated { "at least " } else { "" },
        smallest.bytes,
        smallest.description
    )))
}

/// A lower bound of a PQ candidate's size from its set's short minimal slice (`base`
/// bytes): each level's f16 short block (at most `n × dim_short × 2` stored) replaced by
/// `dim_short / per` codes per point and a `K × dim_short` f32 codebook; the table entry,
/// alignment, dimension order (`level_pq_order`, 2 bytes a dimension) and `pq` metadata it
/// also adds are left out, so a candidate that fits is never
/// skipped (the chosen one is confirmed by encoding).
fn estimate_pq(map: &Map<'_>, levels: &[u16], per: usize, base: u64) -> Result<u64, Error> {
    let mut bytes = base;
    for &l in levels {
        let level = map.level(l)?;
        let (n, dims) = (level.len() as u64, level.dim_short() as u64);
        let k = centroids_for(n as usize) as u64;
        // Quantised over `dim_short`, a projection keeps its first `dim_short` rows.
        let cut = match (level.has_rest(), level.projection_input_dim()) {
            (true, Some(d_in)) => (level.dim_full() as u64 - dims) * d_in as u64 * 4,
            _ => 0,
        };
        bytes = bytes
            .saturating_sub(n.saturating_mul(dims * 2).saturating_add(cut))
            .saturating_add(
                n.saturating_mul(dims / per as u64)
                    .saturating_add(k * dims * 4),
            );
    }
    Ok(bytes)
}
