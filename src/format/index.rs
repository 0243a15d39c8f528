//! (1.3) The image index: an inverted file (IVF) over the rows retrieval ranks images with
//! (`image_vlad` or `image_global`). Each image belongs to the list of its nearest centroid;
//! a query scores the centroids, then only the images of its best lists, exactly. At 40,000
//! images exhaustive ranking was 19 ms of a 26 ms query (issue 35); a few lists of a few
//! hundred images each are a few percent of that.
//!
//! The shapes are checked at open with the rest of the table; the contents (offsets that
//! tile the image list, every image exactly once) where [`Map::image_index`] reads them, so
//! an index that disagrees with its images is an error, never a wrong ranking.

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
        self.offsets.len() - 1
    }

    /// The images of list `l`.
    pub fn list(&self, l: usize) -> &[u32] {
        &self.images[self.offsets[l] as usize..self.offsets[l + 1] as usize]
    }
}

/// The section the index's rows are in.
fn indexed_kind(of: Retrieval) -> SectionKind {
    match of {
        Retrieval::Vlad => SectionKind::ImageVlad,
        Retrieval::Global => SectionKind::ImageGlobal,
    }
}

/// Checks from the table and metadata alone that the three sections and the metadata come
/// together, and that their shapes fit the images and the rows they index.
pub(crate) fn check_shapes<'s>(
    metadata: &Metadata,
    find: impl Fn(SectionKind) -> Option<&'s Section>,
    n_images: u64,
) -> Result<(), Error> {
    let centroids = find(SectionKind::ImageIndexCentroids);
    let lists = find(SectionKind::ImageIndexLists);
    let images = find(SectionKind::ImageIndexImages);
    let info = metadata.image_index.as_ref();
    let (centroids, lists, images, info) = match (centroids, lists, images, info) {
        (None, None, None, None) => return Ok(()),
        (Some(c), Some(l), Some(i), Some(info)) => (c, l, i, info),
        (c, l, i, info) => {
            let present = [c, l, i]
                .iter()
                .flatten()
                .map(|s| s.kind.name())
                .chain(info.map(|_| "the metadata image_index"))
                .collect::<Vec<_>>();
            return Err(Error::inconsistent(format!(
                "the image index is partly there ({}): sections 39-41 and the metadata image_index come together",
                present.join(", ")
            )));
        }
    };
    if centroids.rows == 0 || u64::from(info.probe) == 0 || u64::from(info.probe) > centroids.rows {
        return Err(Error::inconsistent(format!(
            "{} has {} lists and the metadata image_index probes {}: needs 1 to the lists there are",
            centroids.reference(),
            centroids.rows,
            info.probe
        )));
    }
    if lists.rows != centroids.rows + 1 {
        return Err(Error::inconsistent(format!(
            "{} has {} rows, expected lists + 1 = {}",
            lists.reference(),
            lists.rows,
            centroids.rows + 1
        )));
    }
    if images.rows != n_images {
        return Err(Error::inconsistent(format!(
            "{} has {} rows, expected one per image ({n_images})",
            images.reference(),
            images.rows
        )));
    }
    // An `of` this version does not know leaves the index unused; a known one must be there,
    // row for row as wide as the centroids.
    if let Some(of) = info.of() {
        let Some(rows) = find(indexed_kind(of)) else {
            return Err(Error::inconsistent(format!(
                "the metadata image_index is over {}, which the map does not have",
                indexed_kind(of).name()
            )));
        };
        if rows.cols != centroids.cols {
            return Err(Error::inconsistent(format!(
                "{} has {} columns, the {} it indexes {}",
                centroids.reference(),
                centroids.cols,
                rows.kind.name(),
                rows.cols
            )));
        }
    }
    Ok(())
}

/// What an index section's contents must satisfy, for a map of `n_images` images (`Err`:
/// what is wrong). The list offsets run from 0 to the image count without decreasing; every
/// image is in exactly one list; the centroids are finite (a NaN would rank lists
/// arbitrarily).
pub(crate) fn check_contents(kind: SectionKind, bytes: &[u8], n_images: u64) -> Result<(), String> {
    match kind {
        SectionKind::ImageIndexLists => {
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
            let images = super::reader::cast::<u32>(bytes);
            let mut seen: BitVec = BitVec::repeat(false, images.len());
            for &i in images.iter() {
                if u64::from(i) >= n_images || seen.replace(i as usize, true) {
                    return Err(format!(
                        "image {i} is past the {n_images} images or in two lists"
                    ));
                }
            }
        }
        SectionKind::ImageIndexCentroids
            if super::reader::cast::<f32>(bytes)
                .iter()
                .any(|v| !v.is_finite()) =>
        {
            return Err("a centroid value is not finite".into());
        }
        _ => {}
    }
    Ok(())
}

impl<'a> Map<'a> {
    /// The image index (format 1.3), if the map has one over rows this version knows, its
    /// contents checked ([`check_contents`]).
    pub fn image_index(&self) -> Result<Option<ImageIndex<'_>>, Error> {
        let Some(info) = self.metadata().image_index.as_ref() else {
            return Ok(None);
        };
        let Some(of) = info.of() else {
            return Ok(None);
        };
        let centroids_section = self.required(SectionKind::ImageIndexCentroids)?;
        let lists_section = self.required(SectionKind::ImageIndexLists)?;
        let images_section = self.required(SectionKind::ImageIndexImages)?;
        // Their contents are checked on first access ([`check_contents`]).
        Ok(Some(ImageIndex {
            of,
            probe: info.probe as usize,
            width: centroids_section.cols as usize,
            centroids: self.section_array(centroids_section)?,
            offsets: self.section_array(lists_section)?,
            images: self.section_array(images_section)?,
        }))
    }
}

impl MapWriter<'_> {
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
                SectionKind::ImageIndexLists,
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
            self.push_optional(kind, NO_LEVEL, dtype, rows, cols, bytes);
        }
        self.metadata_mut().image_index = Some(info);
        Ok(self)
    }
}
