//! (1.3) The image index: an inverted file (IVF) over the rows retrieval ranks images with
//! (`image_vlad` or `image_global`). Each image belongs to the list of its nearest centroid;
//! a query scores the centroids, then only the images of its best lists, exactly. At 40,000
//! images exhaustive ranking was 19 ms of a 26 ms query (issue 35); a few lists of a few
//! hundred images each are a few percent of that.
//!
//! The shapes are checked at open with the rest of the table; the contents (offsets that
//! tile the image list, every image exactly once) where [`Map::image_index`] reads them, so
//! an index that disagrees with its images (count, width, an image missing or twice) is an
//! error. Which list an image is in, and the probe, are the writer's word: they decide how
//! many of a query's best images are found (recall), never an image's score, and
//! `--retrieval-probe 0` ranks without them.

use super::error::Error;
use super::layout::{Dtype, SectionKind, NO_LEVEL};
use super::metadata::{ImageIndexInfo, Metadata, Retrieval};
use super::reader::{Map, Section};
use super::writer::{owned_bytes, MapWriter};
use bitvec::vec::BitVec;
use std::borrow::Cow;

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
    let Some(p) = parts(metadata, find) else {
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
        // Their contents are checked on first access ([`check_contents`]).
        Ok(Some(ImageIndex {
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
}
