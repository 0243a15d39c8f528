//! (1.4) The image index's lists as places: where each image's neighbours are known (the
//! images sharing most points with it), lists are grown along them, so a list is a stretch
//! of the map a query near it sees, and its centroid (the mean of its rows) is that
//! stretch's row. k-means lists over VLAD rows group images by what their rows have in
//! common, which on a street of 80,000 images was not where they are: probing 64 of 283
//! such lists found 0.78 of the queries' exhaustive top 10; 8 of 3,348 places of 24 images
//! found every image sharing points with the queries (issue 35).

use crate::format::Neighbours;
use bitvec::vec::BitVec;
use std::collections::VecDeque;

/// Images a place holds by default: small enough that its mean row stands out for a query
/// near it (on the 10 M-point street, places of 48 let one query of 20 rank its place 310th,
/// a stretch of which it saw a sixth), large enough that scoring every place's centroid
/// stays a small part of a query (a centroid costs what one image's row does: 3,348 at
/// 80,000 images).
pub(crate) const PLACE_IMAGES: usize = 24;

/// A place smaller than this share of the size asked for (a leftover of its neighbours'
/// growth) is merged into the places of its images' neighbours, where they have any.
const MIN_PLACE_SHARE: usize = 4;

/// Each image's list: places of about `size` images (at least 1), each grown breadth first
/// from the first image no place holds yet, along `graph`'s neighbours (best first), until
/// it holds `size` images or no neighbour is left; then each image of a place under
/// `size / 4` images moves to the place of its first neighbour in a place that large, if it
/// has one. Lists are numbered in the order they were grown, without gaps. Returns
/// `(list of each image, lists)`. Time and memory: linear in the neighbours.
pub(crate) fn place_lists(graph: &Neighbours<'_>, images: usize, size: usize) -> (Vec<u32>, usize) {
    const NONE: u32 = u32::MAX;
    let size = size.max(1);
    let mut list_of = vec![NONE; images];
    let mut sizes: Vec<usize> = Vec::new();
    let mut queue: VecDeque<u32> = VecDeque::new();
    for seed in 0..images {
        if list_of[seed] != NONE {
            continue;
        }
        let list = sizes.len() as u32;
        let mut held = 0;
        queue.clear();
        queue.push_back(seed as u32);
        while let Some(i) = queue.pop_front() {
            if held == size {
                break;
            }
            if list_of[i as usize] != NONE {
                continue;
            }
            list_of[i as usize] = list;
            held += 1;
            queue.extend(
                graph
                    .of(i as usize)
                    .iter()
                    .filter(|&&j| (j as usize) < images && list_of[j as usize] == NONE),
            );
        }
        sizes.push(held);
    }
    // Leftovers join a neighbour's place; a place that keeps none of its images is gone.
    let small = |l: u32| sizes[l as usize] * MIN_PLACE_SHARE < size;
    let mut moved = list_of.clone();
    for (i, m) in moved.iter_mut().enumerate() {
        if small(list_of[i]) {
            if let Some(&j) = graph
                .of(i)
                .iter()
                .find(|&&j| (j as usize) < images && !small(list_of[j as usize]))
            {
                *m = list_of[j as usize];
            }
        }
    }
    let lists = renumber(&mut moved, sizes.len());
    (moved, lists)
}

/// Numbers the lists `list_of` uses (each below `lists`) from 0 in the order they first
/// come, without gaps; returns how many there are.
fn renumber(list_of: &mut [u32], lists: usize) -> usize {
    const NONE: u32 = u32::MAX;
    let mut number = vec![NONE; lists];
    let mut used = 0u32;
    for l in list_of.iter_mut() {
        let n = &mut number[*l as usize];
        if *n == NONE {
            *n = used;
            used += 1;
        }
        *l = *n;
    }
    used as usize
}

/// Moves the images of lists whose centroid has no direction (every row zero: images that
/// see no described point, and so have no neighbours either) into the first list that has
/// one, and drops those centroids; returns the lists left. A zero centroid is nearer to every
/// unit row than a unit centroid it shares less than half its length with, so a query would
/// probe such lists first, for images it cannot rank. Nothing moves when no list has a
/// direction.
pub(crate) fn merge_undirected(
    list_of: &mut [u32],
    centroids: &mut Vec<f32>,
    width: usize,
) -> usize {
    let lists = centroids.len() / width.max(1);
    let directed = |l: usize| {
        centroids[l * width..(l + 1) * width]
            .iter()
            .any(|&v| v != 0.0)
    };
    let Some(first) = (0..lists).find(|&l| directed(l)) else {
        return lists;
    };
    let keep: BitVec = (0..lists).map(directed).collect();
    for l in list_of.iter_mut() {
        if !keep[*l as usize] {
            *l = first as u32;
        }
    }
    let mut kept = 0;
    for l in 0..lists {
        if keep[l] {
            centroids.copy_within(l * width..(l + 1) * width, kept * width);
            kept += 1;
        }
    }
    centroids.truncate(kept * width);
    // Kept lists are numbered in their order, as their centroids were moved.
    let mut number = vec![0u32; lists];
    let mut next = 0u32;
    for l in 0..lists {
        if keep[l] {
            number[l] = next;
            next += 1;
        }
    }
    for l in list_of.iter_mut() {
        *l = number[*l as usize];
    }
    kept
}

/// Each list's centroid: the mean of its images' rows (`row(i, out)` writes image `i`'s,
/// L2-normalised, or zeros), normalised to unit length (zeros where the mean is, or nearly,
/// see [`MIN_MEAN_NORM`]): with
/// every centroid of one length, the reader's order of lists by distance is their order
/// by cosine. `[lists × width]`.
pub(crate) fn place_centroids(
    list_of: &[u32],
    lists: usize,
    width: usize,
    mut row: impl FnMut(usize, &mut [f32]),
) -> Vec<f32> {
    let mut centroids = vec![0.0f32; lists * width];
    let mut buffer = vec![0.0f32; width];
    for (i, &l) in list_of.iter().enumerate() {
        row(i, &mut buffer);
        let c = &mut centroids[l as usize * width..(l as usize + 1) * width];
        for (c, &v) in c.iter_mut().zip(&buffer) {
            *c += v;
        }
    }
    for c in centroids.chunks_exact_mut(width.max(1)) {
        // A mean that (nearly) cancels has no direction: zero, not a short vector that f16
        // rounds to zero and every query would probe first.
        let norm = c.iter().map(|v| v * v).sum::<f32>().sqrt();
        if norm < MIN_MEAN_NORM {
            c.fill(0.0);
        } else {
            c.iter_mut().for_each(|v| *v /= norm);
        }
    }
    centroids
}

/// The length under which a place's mean row is taken as no direction (a mean of unit rows
/// that agree at all is far longer: 1/√24 for 24 rows at right angles).
const MIN_MEAN_NORM: f32 = 1e-6;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::NO_NEIGHBOUR;
    use std::borrow::Cow;

    /// Images along a path, each with its `per` nearest along it as neighbours, nearest
    /// first (ties: the lower one).
    fn path(images: usize, per: usize) -> Vec<u32> {
        let mut rows = vec![NO_NEIGHBOUR; images * per];
        for i in 0..images {
            let mut near: Vec<u32> = (0..images as u32).filter(|&j| j as usize != i).collect();
            near.sort_by_key(|&j| ((j as i64 - i as i64).abs(), j));
            for (slot, &j) in rows[i * per..(i + 1) * per].iter_mut().zip(&near) {
                *slot = j;
            }
        }
        rows
    }

    fn graph(rows: &[u32], per: usize) -> Neighbours<'_> {
        Neighbours {
            per_image: per,
            rows: Cow::Borrowed(rows),
        }
    }

    #[test]
    fn places_along_a_path_are_its_stretches() {
        let rows = path(100, 4);
        let (list_of, lists) = place_lists(&graph(&rows, 4), 100, 10);
        assert_eq!(lists, 10);
        // Each place is 10 consecutive images: the path cut into stretches.
        for (i, &l) in list_of.iter().enumerate() {
            assert_eq!(l as usize, i / 10, "image {i}");
        }
    }

    #[test]
    fn leftovers_join_a_neighbouring_place_and_lone_images_keep_their_own() {
        // 0..=20 along a path; 21 and 22 share points with no one.
        let mut rows = path(21, 2);
        rows.extend([NO_NEIGHBOUR; 4]);
        // Places of 10: 0..10, 10..20, then image 20 alone (under 10 / 4) joins 19's.
        let (list_of, lists) = place_lists(&graph(&rows, 2), 23, 10);
        assert_eq!(&list_of[..20], &[[0u32; 10], [1; 10]].concat()[..]);
        assert_eq!(list_of[20], 1, "a leftover joins its neighbour's place");
        // The lone images have no neighbour to join: each keeps its own place, and the
        // numbering has no gap where 20's place was.
        assert_eq!(&list_of[21..], &[2, 3]);
        assert_eq!(lists, 4);
    }

    #[test]
    fn neighbours_past_the_images_are_not_followed() {
        let rows = vec![7, NO_NEIGHBOUR, 0, NO_NEIGHBOUR];
        let (list_of, lists) = place_lists(&graph(&rows, 2), 2, 2);
        // Image 0's neighbour 7 is no image; 1 names 0, which is placed already.
        assert_eq!((list_of, lists), (vec![0, 1], 2));
    }

    #[test]
    fn lists_without_a_direction_join_the_first_that_has_one() {
        // Lists 0 and 2 are of zero rows; 1 and 3 have directions.
        let mut centroids = vec![0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        let mut list_of = vec![0, 1, 2, 3, 2];
        assert_eq!(merge_undirected(&mut list_of, &mut centroids, 2), 2);
        assert_eq!(list_of, vec![0, 0, 0, 1, 0]);
        assert_eq!(centroids, vec![1.0, 0.0, 0.0, 1.0]);
        // With no list of a direction, nothing moves.
        let mut zeros = vec![0.0; 4];
        let mut list_of = vec![0, 1];
        assert_eq!(merge_undirected(&mut list_of, &mut zeros, 2), 2);
        assert_eq!(list_of, vec![0, 1]);
    }

    #[test]
    fn a_centroid_is_the_unit_mean_of_its_rows() {
        let rows = [[1.0f32, 0.0], [0.0, 1.0], [0.0, 0.0]];
        let centroids = place_centroids(&[0, 0, 1], 2, 2, |i, out| out.copy_from_slice(&rows[i]));
        let h = std::f32::consts::FRAC_1_SQRT_2;
        assert!((centroids[0] - h).abs() < 1e-6 && (centroids[1] - h).abs() < 1e-6);
        // A place of zero rows has a zero centroid (no direction), not NaN.
        assert_eq!(&centroids[2..], &[0.0, 0.0]);
    }
}
