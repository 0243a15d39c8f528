//! (1.3) The image index: an inverted file (IVF) over the rows retrieval ranks images with
//! (`image_vlad` or `image_global`). Each image belongs to one list, which has a centroid (the
//! writer's choice: k-means lists, or 1.4 places grown along the neighbours); a query scores
//! the centroids, then only the images of its best lists, exactly. At 40,000
//! images exhaustive ranking was 19 ms of a 26 ms query (issue 35); a few lists of a few
//! hundred images each are a few percent of that.
//!
//! The shapes are checked at open with the rest of the table; the contents (offsets that
//! tile the image list, every image exactly once) where [`Map::image_index`] reads them, so
//! an index that disagrees with its images (count, width, an image missing or twice) is an
//! error. Which list an image is in, and the probe, are the writer's word: they decide how
//! many of a query's best images are found (recall), never an image's score, and
//! `--retrieval-probe 0` ranks without them.
//!
//! (1.4) An index may also store each image's neighbours (`image_index_neighbours`: the
//! images sharing most points with it). A query then widens its search from the best
//! images of the lists it probed along their neighbours, best first, until no neighbour
//! scores among its best: where images lie along a street, the lists cut neighbourhoods
//! apart and no few of them hold a query's best images, but their neighbours do.

use super::error::Error;
use super::layout::{Dtype, SectionKind, NO_LEVEL};
use super::metadata::{ImageIndexInfo, Metadata, Retrieval};
use super::reader::{Map, Section};
use super::writer::{owned_bytes, MapWriter};
use bitvec::vec::BitVec;
use std::borrow::Cow;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

/// A map's image index, read and checked.
#[derive(Debug, Clone)]
pub struct ImageIndex<'m> {
    /// The rows it indexes.
    pub of: Retrieval,
    /// Lists a query scores by default (the metadata's `probe`, 1 to `lists`).
    pub probe: usize,
    /// Values per row (the indexed section's columns).
    pub width: usize,
    /// `[lists × width]`.
    pub centroids: Cow<'m, [f32]>,
    /// `[lists + 1]`: list `l` holds `images[offsets[l]..offsets[l + 1]]`.
    pub offsets: Cow<'m, [u32]>,
    /// Every image index once, grouped by list.
    pub images: Cow<'m, [u32]>,
    /// (1.4) `[images × per_image]`: each image's neighbours, best first, [`NO_NEIGHBOUR`]
    /// past the last; `None` when the map stores none.
    pub neighbours: Option<Neighbours<'m>>,
}

/// Images an indexed ranking scores at least per image asked for: with `top_k` near a list's
/// size, more lists are scored than `probe` says, so the short list is never the whole of
/// what was scored. (The reference reader's rule; `convert` calibrates `probe` by it.)
#[cfg_attr(not(any(feature = "colmap", feature = "localize")), allow(dead_code))]
pub(crate) const MIN_SCORED_PER_K: usize = 8;

/// (1.4) The beam a search along the image neighbours keeps, per image asked for: the
/// second-best images' neighbours are where a best one the lists missed is found.
#[cfg_attr(not(any(feature = "colmap", feature = "localize")), allow(dead_code))]
pub(crate) const BEAM_PER_K: usize = 2;

/// Marks the end of an image's neighbours in `image_index_neighbours`.
pub const NO_NEIGHBOUR: u32 = u32::MAX;

/// The most neighbours an image may list (`image_index_neighbours`' columns).
pub const MAX_NEIGHBOURS: usize = 256;

/// (1.4) Each image's neighbours, as stored in `image_index_neighbours`.
#[derive(Debug, Clone)]
pub struct Neighbours<'m> {
    /// Neighbours each image has room for (the section's columns, 1 to [`MAX_NEIGHBOURS`]).
    pub per_image: usize,
    /// `[images × per_image]`, each below the image count or [`NO_NEIGHBOUR`].
    pub rows: Cow<'m, [u32]>,
}

impl Neighbours<'_> {
    /// Image `i`'s neighbours, best first (none past the images).
    pub fn of(&self, i: usize) -> &[u32] {
        let row = self
            .rows
            .get(i * self.per_image..(i + 1) * self.per_image)
            .unwrap_or(&[]);
        let end = row
            .iter()
            .position(|&n| n == NO_NEIGHBOUR)
            .unwrap_or(row.len());
        &row[..end]
    }

    /// Widens a search along the neighbours: `scored` holds every image scored so far (image,
    /// score); the best `beam` of them are expanded best first, each scoring its neighbours
    /// not scored yet (`score` gives their scores, in order), and a neighbour that comes
    /// among the best `beam` is expanded in turn, until the best image left to expand scores
    /// below the `beam`-th best. The images scored are appended to `scored`. A score that
    /// is not a number is kept but never expanded. Images past `n_images` are not scored.
    pub fn widen(
        &self,
        scored: &mut Vec<(u32, f32)>,
        n_images: usize,
        beam: usize,
        mut score: impl FnMut(&[u32]) -> Vec<f32>,
    ) {
        let beam = beam.max(1);
        let mut seen: BitVec = BitVec::repeat(false, n_images);
        for &(i, _) in scored.iter() {
            if (i as usize) < n_images {
                seen.set(i as usize, true);
            }
        }
        // `best`: the beam, worst on top; `frontier`: the beam's images not expanded yet,
        // best on top. Ties by the lower image, as rankings break them.
        let mut best: BinaryHeap<Reverse<Ranked>> = BinaryHeap::new();
        let mut frontier: BinaryHeap<Ranked> = BinaryHeap::new();
        let admit = |r: Ranked,
                     best: &mut BinaryHeap<Reverse<Ranked>>,
                     frontier: &mut BinaryHeap<Ranked>| {
            if r.0.is_nan() {
                return;
            }
            if best.len() < beam {
                best.push(Reverse(r));
                frontier.push(r);
            } else if best.peek().is_some_and(|w| r > w.0) {
                best.pop();
                best.push(Reverse(r));
                frontier.push(r);
            }
        };
        for &(i, s) in scored.iter() {
            admit(Ranked(s, i), &mut best, &mut frontier);
        }
        let mut fresh = Vec::new();
        while let Some(r) = frontier.pop() {
            // Every frontier entry was in the beam when pushed; if the best left is below
            // the beam's worst now, nothing after it is in the beam either.
            if best.len() >= beam && best.peek().is_some_and(|w| r < w.0) {
                break;
            }
            fresh.clear();
            for &j in self.of(r.1 as usize) {
                if (j as usize) < n_images && !seen.replace(j as usize, true) {
                    fresh.push(j);
                }
            }
            if fresh.is_empty() {
                continue;
            }
            let scores = score(&fresh);
            for (&j, &s) in fresh.iter().zip(&scores) {
                scored.push((j, s));
                admit(Ranked(s, j), &mut best, &mut frontier);
            }
        }
    }
}

/// A scored image, ordered by score, then by the lower image index first (as rankings
/// break ties); scores that are not numbers are never compared (they are not admitted).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Ranked(f32, u32);

impl Eq for Ranked {}

impl PartialOrd for Ranked {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}

impl Ord for Ranked {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.0.total_cmp(&other.0).then(other.1.cmp(&self.1))
    }
}

impl ImageIndex<'_> {
    /// Lists in the index.
    pub fn lists(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    /// The images of list `l` (none past the lists, or where the offsets do not fit the
    /// images: a map's are checked, a hand-made index's may not be).
    pub fn list(&self, l: usize) -> &[u32] {
        let range = |a: &u32, b: &u32| *a as usize..*b as usize;
        match (self.offsets.get(l), self.offsets.get(l + 1)) {
            (Some(a), Some(b)) => self.images.get(range(a, b)).unwrap_or(&[]),
            _ => &[],
        }
    }
}

/// The section the rows of an index `of` are in.
pub(crate) fn indexed_kind(of: Retrieval) -> SectionKind {
    match of {
        Retrieval::Vlad => SectionKind::ImageVlad,
        Retrieval::Global => SectionKind::ImageGlobal,
    }
}

/// The index's parts, when all of them are there: the three sections (not skipped), the
/// metadata, a kind of rows this version knows, and those rows.
struct Parts<'s, 'm> {
    centroids: &'s Section,
    lists: &'s Section,
    images: &'s Section,
    info: &'m ImageIndexInfo,
    of: Retrieval,
    rows: &'s Section,
}

/// The index's [`Parts`], or `None` when any is missing: then the map has no index, which is
/// no error (as the metadata `retrieval` naming rows a map lacks is none). A reader before
/// 1.3 slices a map by dropping sections 39-41, unknown to it, and keeping the metadata key;
/// a later minor may store them in an encoding this version skips.
fn parts<'s, 'm>(
    metadata: &'m Metadata,
    find: impl Fn(SectionKind) -> Option<&'s Section>,
) -> Option<Parts<'s, 'm>> {
    let info = metadata.image_index.as_ref()?;
    let of = info.of()?;
    Some(Parts {
        centroids: find(SectionKind::ImageIndexCentroids)?,
        lists: find(SectionKind::ImageIndexOffsets)?,
        images: find(SectionKind::ImageIndexImages)?,
        info,
        of,
        rows: find(indexed_kind(of))?,
    })
}

/// The rows `map`'s index is over, when all its parts are there (else it has none).
pub(crate) fn indexed_rows(map: &Map<'_>) -> Option<Retrieval> {
    parts(map.metadata(), |kind| map.find(kind, None)).map(|p| p.of)
}

/// Checks from the table and metadata alone that an index whose parts are all there fits the
/// images and the rows it indexes: at least one list and at most one per image, each as wide
/// as the rows (at least one value), and a probe of 1 to the lists.
pub(crate) fn check_shapes<'s>(
    metadata: &Metadata,
    find: impl Fn(SectionKind) -> Option<&'s Section>,
    n_images: u64,
) -> Result<(), Error> {
    // (1.4) Neighbours are checked whenever present (a map without the rest of the index
    // does not use them, but `info` reports them).
    if let Some(n) = find(SectionKind::ImageIndexNeighbours) {
        if n.rows != n_images || n.cols == 0 || n.cols > MAX_NEIGHBOURS as u64 {
            return Err(Error::inconsistent(format!(
                "{} is {} x {}: expected one row per image ({n_images}) of 1 to {MAX_NEIGHBOURS} neighbours",
                n.reference(),
                n.rows,
                n.cols
            )));
        }
    }
    let Some(p) = parts(metadata, &find) else {
        return Ok(());
    };
    let lists = p.centroids.rows;
    if lists == 0 || lists > n_images.max(1) || p.centroids.cols == 0 {
        return Err(Error::inconsistent(format!(
            "{} is {lists} x {}: needs 1 to {} lists (one per image) of at least one value",
            p.centroids.reference(),
            p.centroids.cols,
            n_images.max(1)
        )));
    }
    if u64::from(p.info.probe) == 0 || u64::from(p.info.probe) > lists {
        return Err(Error::inconsistent(format!(
            "the metadata image_index probes {} of the {lists} lists of {}: needs 1 to {lists}",
            p.info.probe,
            p.centroids.reference(),
        )));
    }
    if Some(p.lists.rows) != lists.checked_add(1) {
        return Err(Error::inconsistent(format!(
            "{} has {} rows, expected lists + 1 = {}",
            p.lists.reference(),
            p.lists.rows,
            lists + 1
        )));
    }
    if p.images.rows != n_images {
        return Err(Error::inconsistent(format!(
            "{} has {} rows, expected one per image ({n_images})",
            p.images.reference(),
            p.images.rows
        )));
    }
    if p.rows.cols != p.centroids.cols {
        return Err(Error::inconsistent(format!(
            "{} has {} columns, the {} it indexes {}",
            p.centroids.reference(),
            p.centroids.cols,
            p.rows.kind.name(),
            p.rows.cols
        )));
    }
    Ok(())
}

/// What an index section's contents must satisfy, for a map of `n_images` images (`Err`:
/// what is wrong). The list offsets run from 0 to the image count without decreasing; every
/// image is in exactly one list. (The centroids' finiteness is checked with the other
/// codebooks', in `views::check_contents`.)
pub(crate) fn check_contents(kind: SectionKind, bytes: &[u8], n_images: u64) -> Result<(), String> {
    match kind {
        SectionKind::ImageIndexOffsets => {
            let offsets = super::reader::cast::<u32>(bytes);
            let tiles = offsets.first() == Some(&0)
                && offsets.windows(2).all(|w| w[0] <= w[1])
                && offsets.last().map(|&o| u64::from(o)) == Some(n_images);
            if !tiles {
                return Err(format!(
                    "the list offsets do not run from 0 to the {n_images} images without decreasing"
                ));
            }
        }
        SectionKind::ImageIndexImages => {
            let mut seen: BitVec = BitVec::repeat(false, n_images as usize);
            for &i in super::reader::cast::<u32>(bytes).iter() {
                if u64::from(i) >= n_images || seen.replace(i as usize, true) {
                    return Err(format!(
                        "image {i} is past the {n_images} images or in two lists"
                    ));
                }
            }
        }
        SectionKind::ImageIndexNeighbours => {
            let values = super::reader::cast::<u32>(bytes);
            let bad = values
                .iter()
                .find(|&&i| i != NO_NEIGHBOUR && u64::from(i) >= n_images)
                .copied();
            if let Some(i) = bad {
                return Err(format!("neighbour {i} is past the {n_images} images"));
            }
            // Rows of `rows / n_images` columns (checked at open): end marks only at the end.
            let cols = values
                .len()
                .checked_div(n_images as usize)
                .unwrap_or(0)
                .max(1);
            let gap = values.chunks(cols).position(|row| {
                let end = row
                    .iter()
                    .position(|&n| n == NO_NEIGHBOUR)
                    .unwrap_or(row.len());
                row[end..].iter().any(|&n| n != NO_NEIGHBOUR)
            });
            if let Some(image) = gap {
                return Err(format!(
                    "image {image}'s neighbours go on after their end mark"
                ));
            }
        }
        _ => {}
    }
    Ok(())
}

impl<'a> Map<'a> {
    /// The image index (format 1.3), if the map has one over rows this version knows, its
    /// contents checked ([`check_contents`]).
    pub fn image_index(&self) -> Result<Option<ImageIndex<'_>>, Error> {
        let Some(p) = parts(self.metadata(), |kind| self.find(kind, None)) else {
            return Ok(None);
        };
        let (of, probe) = (p.of, p.info.probe as usize);
        let (centroids_section, lists_section, images_section) = (p.centroids, p.lists, p.images);
        let neighbours = match self.find(SectionKind::ImageIndexNeighbours, None) {
            Some(s) => Some(Neighbours {
                per_image: s.cols as usize,
                rows: self.section_array(s)?,
            }),
            None => None,
        };
        // Their contents are checked on first access ([`check_contents`]).
        Ok(Some(ImageIndex {
            neighbours,
            of,
            probe,
            width: centroids_section.cols as usize,
            centroids: self.section_array(centroids_section)?,
            offsets: self.section_array(lists_section)?,
            images: self.section_array(images_section)?,
        }))
    }
}

impl<'a> MapWriter<'a> {
    /// The rows of a shared (no level) section of `dtype` added as an array, not copied
    /// from another map: its little-endian bytes and column count. What a builder reads back
    /// to index them.
    #[cfg(feature = "colmap")]
    pub(crate) fn pending_rows(&self, kind: SectionKind, dtype: Dtype) -> Option<(&[u8], usize)> {
        let section = self.sections.get(&(kind.code(), NO_LEVEL))?;
        match &section.content {
            super::writer::Content::Array { bytes, .. } if section.dtype == dtype => {
                Some((bytes.as_ref(), section.cols as usize))
            }
            _ => None,
        }
    }

    /// (1.3) Adds the image index over the rows of `info.of` (already set, or set later):
    /// `centroids` `[lists × width]` and each image's list (`list_of[i]` < lists). Images are
    /// grouped by list in index order. The sections are optional: a reader before 1.3 skips
    /// them and ranks every image.
    pub fn set_image_index(
        &mut self,
        info: ImageIndexInfo,
        centroids: Vec<f32>,
        width: usize,
        list_of: &[u32],
    ) -> Result<&mut Self, Error> {
        if width == 0 || centroids.is_empty() || centroids.len() % width != 0 {
            return Err(Error::invalid(
                "image index centroids are not a whole number of rows",
            ));
        }
        if centroids.iter().any(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "an image index centroid value is not finite",
            ));
        }
        let lists = centroids.len() / width;
        if info.probe == 0 || info.probe as usize > lists {
            return Err(Error::invalid(format!(
                "image index probe {} with {lists} lists",
                info.probe
            )));
        }
        let mut offsets = vec![0u32; lists + 1];
        for &l in list_of {
            let slot = offsets
                .get_mut(l as usize + 1)
                .filter(|_| (l as usize) < lists)
                .ok_or_else(|| Error::invalid(format!("image in list {l} of {lists}")))?;
            *slot += 1;
        }
        for l in 0..lists {
            offsets[l + 1] += offsets[l];
        }
        let mut next = offsets.clone();
        let mut images = vec![0u32; list_of.len()];
        for (i, &l) in list_of.iter().enumerate() {
            images[next[l as usize] as usize] = i as u32;
            next[l as usize] += 1;
        }
        for (kind, dtype, rows, cols, bytes) in [
            (
                SectionKind::ImageIndexCentroids,
                Dtype::F32,
                lists,
                width,
                owned_bytes(centroids),
            ),
            (
                SectionKind::ImageIndexOffsets,
                Dtype::U32,
                lists + 1,
                1,
                owned_bytes(offsets),
            ),
            (
                SectionKind::ImageIndexImages,
                Dtype::U32,
                images.len(),
                1,
                owned_bytes(images),
            ),
        ] {
            self.push_array_flagged(kind, NO_LEVEL, dtype, rows, cols, bytes, false);
        }
        self.metadata_mut().image_index = Some(info);
        Ok(self)
    }

    /// (1.4) Adds each image's neighbours to the image index (set with
    /// [`MapWriter::set_image_index`]): `rows` `[images × per_image]`, best first, each below
    /// the image count or [`NO_NEIGHBOUR`] past the last. Optional, as the index is: a 1.3
    /// reader skips it and probes lists alone.
    pub fn set_image_neighbours(
        &mut self,
        rows: Vec<u32>,
        per_image: usize,
    ) -> Result<&mut Self, Error> {
        if per_image == 0 || per_image > MAX_NEIGHBOURS || rows.len() % per_image != 0 {
            return Err(Error::invalid(format!(
                "image neighbours of {} values are not rows of 1 to {MAX_NEIGHBOURS} ({per_image})",
                rows.len()
            )));
        }
        let images = rows.len() / per_image;
        if let Some(&n) = rows
            .iter()
            .find(|&&n| n != NO_NEIGHBOUR && n as usize >= images)
        {
            return Err(Error::invalid(format!(
                "image neighbour {n} of {images} images"
            )));
        }
        self.push_array_flagged(
            SectionKind::ImageIndexNeighbours,
            NO_LEVEL,
            Dtype::U32,
            images,
            per_image,
            owned_bytes(rows),
            false,
        );
        Ok(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `widen` on a path 0-1-2-…-9 scored by closeness to 7, from image 0: it walks to 7 and
    /// its neighbours; a neighbour that does not score as a number is kept, not expanded;
    /// neighbours past the images are skipped.
    #[test]
    fn widening_walks_to_the_best_and_stops() {
        let n = 10u32;
        let mut rows = Vec::new();
        for i in 0..n {
            // 0 lists 1 then the end; 9 lists 8 then 99, past the images.
            match i {
                0 => rows.extend([1, NO_NEIGHBOUR]),
                9 => rows.extend([8, 99]),
                _ => rows.extend([i - 1, i + 1]),
            }
        }
        let graph = Neighbours {
            per_image: 2,
            rows: Cow::Owned(rows),
        };
        let score = |i: u32| -((i as f32) - 7.0).abs();
        let mut scored = vec![(0u32, score(0))];
        let mut calls = Vec::new();
        graph.widen(&mut scored, n as usize, 2, |picks| {
            calls.push(picks.to_vec());
            picks.iter().map(|&i| score(i)).collect()
        });
        let mut images: Vec<u32> = scored.iter().map(|&(i, _)| i).collect();
        images.sort_unstable();
        // Up to 7's neighbours, 6 and 8, each scored once; the beam of two is 7 and 6 (the
        // lower of a tie), so 8 is not expanded and 9 never scored.
        assert_eq!(images, (0..9).collect::<Vec<_>>());
        // One image's fresh neighbours at a time, in walk order: 1, 2, … 8.
        assert_eq!(calls, (1..9).map(|i| vec![i]).collect::<Vec<_>>());
        // Toward 9, whose row lists 99: 9 is expanded, and 99 never scored.
        let mut scored = vec![(0u32, -9.0)];
        calls.clear();
        graph.widen(&mut scored, n as usize, 2, |picks| {
            calls.push(picks.to_vec());
            picks.iter().map(|&i| i as f32 - 9.0).collect()
        });
        assert_eq!(scored.len(), 10);
        assert!(calls.iter().flatten().all(|&i| i < n), "{calls:?}");
        // A NaN at 4 stops the walk there: 5 is never reached.
        let nan = |i: u32| if i == 4 { f32::NAN } else { score(i) };
        let mut scored = vec![(0u32, nan(0))];
        graph.widen(&mut scored, n as usize, 2, |picks| {
            picks.iter().map(|&i| nan(i)).collect()
        });
        let images: Vec<u32> = scored.iter().map(|&(i, _)| i).collect();
        assert_eq!(images, [0, 1, 2, 3, 4]);
    }
}
