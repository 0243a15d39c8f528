//! Retrieval for every map: the VLAD codebook and per-image VLADs `convert` stores (format
//! 1.1, [`crate::vlad`]), from the map's own point descriptors in one level's basis; and
//! (1.3) the image index over the rows the map retrieves with, on maps of many images.

use super::geometry::Geometry;
use super::places::{merge_undirected, place_centroids, place_lists, PLACE_IMAGES};
use crate::format::index::{BEAM_PER_K, MIN_SCORED_PER_K};
use crate::format::{Dtype, ImageIndexInfo, MapWriter, Neighbours, Retrieval, NO_NEIGHBOUR};
use crate::geometry::SplitMix64;
use crate::kmeans::KMeans;
use crate::progress::Reporter;
use crate::vector::{dot, top_k_indices, Nearest};
use crate::vlad::Codebook;
use bitvec::vec::BitVec;
use half::f16;
use serde_json::json;
use std::borrow::Cow;

/// How `convert` builds retrieval data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct VladOptions {
    /// Centroids; 0 stores no VLAD; `None`: by the map's images ([`crate::vlad::default_shape`]).
    pub clusters: Option<usize>,
    /// Leading dimensions of the level basis (at most the level's `dim_short`); `None`: by
    /// the map's images.
    pub dims: Option<usize>,
    /// (1.3) Lists of the image index over the rows the map retrieves with (VLAD or global
    /// descriptors), at most [`MAX_INDEX_LISTS`] and one per image; 0 stores none; `None`:
    /// from 2,000 images on, stored only where it pays: places of 24 images with neighbours
    /// (1.4; with them the lists are places of about images / lists images), else about
    /// √images k-means lists.
    pub index_lists: Option<usize>,
}

impl VladOptions {
    /// (clusters, dims) for a map of `images` images whose descriptors were computed `at`.
    pub fn shape(&self, images: usize, at: crate::vlad::DescribedAt) -> (usize, usize) {
        let (clusters, dims) = crate::vlad::default_shape(images, at);
        (self.clusters.unwrap_or(clusters), self.dims.unwrap_or(dims))
    }
}

/// What a converted map's VLAD is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StoredVlad {
    /// The level whose basis (and codebook section) it is on.
    pub level: u16,
    /// Centroids of its codebook.
    pub clusters: usize,
    /// Leading dimensions of the level basis it aggregates.
    pub dims: usize,
}

/// The seed of the codebook's k-means: fixed, so a map converts to the same bytes.
const SEED: u64 = 0x5f9_1a0;

/// Learns the codebook from `rows` (its descriptor's first `dims` dimensions in `level`'s
/// basis, renormalised, a row per map point, a zero row for a point without one; or a row per
/// described point, with `visibility` naming rows; `points` says which points those are, in
/// words) and adds it, each image's VLAD over the rows it sees (`visibility`: offsets per image
/// and row indices; an index past the rows is skipped), and the rule to the level's metadata
/// to `writer` (after the level). `None`: a map with fewer described points than centroids,
/// or without images, gets no VLAD.
#[allow(clippy::too_many_arguments)]
pub(crate) fn add_vlad(
    writer: &mut MapWriter<'_>,
    level: u16,
    rows: &[f32],
    dims: usize,
    clusters: usize,
    points: &str,
    (vis_offsets, vis_points): (&[u64], &[u32]),
    reporter: &dyn Reporter,
) -> Result<Option<StoredVlad>, crate::format::Error> {
    if clusters == 0 || dims == 0 || vis_offsets.len() < 2 {
        return Ok(None);
    }
    reporter.start("retrieval codebook", None);
    let codebook = Codebook::train(rows, dims, clusters, SEED);
    reporter.finish();
    let Some(codebook) = codebook else {
        return Ok(None);
    };
    reporter.start("image VLADs", None);
    let images = codebook.image_vlads(rows, vis_offsets, vis_points);
    reporter.finish();
    let info = writer
        .metadata_mut()
        .levels
        .iter_mut()
        .find(|l| l.level == level)
        .ok_or_else(|| crate::format::Error::invalid("VLAD for a level the map does not have"))?;
    info.extra.insert(
        "vlad".into(),
        json!({
            "clusters": codebook.clusters(),
            "dims": dims,
            "rule": crate::vlad::rule(),
            "points": points,
        }),
    );
    let clusters = codebook.clusters();
    writer.set_vlad(level, dims, codebook.into_centroids(), &images)?;
    Ok(Some(StoredVlad {
        level,
        clusters,
        dims,
    }))
}

/// Lists of the default k-means image index of a map of `images` images (one without
/// neighbours; with them, lists are places, see [`PLACE_IMAGES`]): none below
/// [`crate::vlad::LARGE_MAP_IMAGES`] (ranking every image costs well under a millisecond
/// there), else about √images, so that a list holds about as many images as there are lists
/// and a query scores √images centroids plus `probe` lists of √images images. Whether an
/// index is tried at all goes by it too.
pub(crate) fn default_index_lists(images: usize) -> usize {
    if !crate::vlad::is_large_map(images) {
        0
    } else {
        (images as f64).sqrt().round() as usize
    }
}

/// The most lists an image index may have (`--index-lists`, and the default places): as many
/// as k-means learns from rows, one row a list at least; every query scores every centroid.
pub const MAX_INDEX_LISTS: usize = INDEX_MAX_TRAIN;

/// What a converted map's image index is.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageIndexSummary {
    /// The rows it indexes.
    pub of: Retrieval,
    /// Its lists.
    pub lists: usize,
    /// Lists a query scores by default.
    pub probe: usize,
    /// On the calibration images, the share of each one's exhaustive top
    /// [`DEFAULT_RETRIEVAL_TOP_K`](crate::format::DEFAULT_RETRIEVAL_TOP_K) (itself left out)
    /// found in its first `probe` lists.
    pub recall: f64,
    /// Images the calibration images scored on average with `probe` lists.
    pub scored: usize,
    /// Whether the map stores it. A default index (no `index_lists` asked for) is left out
    /// when `scored` plus the lists (a query scores every centroid) is more than a quarter
    /// of the images: the rows' neighbours are not grouped, or the images share too few
    /// points to make places, and probing would cost about what ranking every image does.
    pub stored: bool,
}

/// A default index whose queries would score more than one image in this many is not
/// stored.
const MAX_SCORED_SHARE: usize = 4;

/// Rows the index's k-means learns from at most (a seeded sample).
const INDEX_MAX_TRAIN: usize = 8_192;
/// Its Lloyd iterations at most.
const INDEX_ITERATIONS: usize = 10;
/// Database images whose own rows calibrate `probe`, at most.
const CALIBRATION_IMAGES: usize = 100;
/// The share of their exhaustive top k that `probe` lists must hold.
const CALIBRATION_RECALL: f64 = 0.99;
/// The seed of the index's sample and k-means.
const INDEX_SEED: u64 = 0x1df_5eed;

/// How the index is built and `probe` chosen, in words (the metadata `image_index.rule`):
/// `places`, the images a place was grown to where the lists are places (1.4, with
/// neighbours), else k-means lists.
fn index_rule(places: Option<usize>) -> String {
    let top = crate::format::DEFAULT_RETRIEVAL_TOP_K;
    match places {
        Some(size) => format!("neighbours: the {INDEX_NEIGHBOURS} images sharing most points with each; lists: places grown breadth first along the neighbours from the first image not placed, up to {size} images, each image of a place under a quarter of that moved to the place of its first neighbour in a larger one, places of zero rows folded into the first other; centroids: each list's mean row, unit length; probe: the fewest lists from {QUERY_MIN_PROBE}, taken nearest centroid first (and on to {MIN_SCORED_PER_K} images per image asked for), from whose best a search along the neighbours (a beam of {BEAM_PER_K} per image asked for) finds {CALIBRATION_RECALL} of the exhaustive top {top} (itself left out) of up to {CALIBRATION_IMAGES} of the map's images"),
        None => format!("k-means++ then Lloyd ({INDEX_ITERATIONS} iterations at most, seeded) on at most {INDEX_MAX_TRAIN} rows; each image in the list of its nearest centroid; probe: the fewest lists, taken nearest centroid first, that hold {CALIBRATION_RECALL} of the exhaustive top {top} (itself left out) of up to {CALIBRATION_IMAGES} of the map's images"),
    }
}

/// One f16 row widened and L2-normalised, as the localizer scores rows; all zeros (no
/// direction: k-means leaves it out) when a value is not finite, a row the localizer ranks
/// last. (Not `vector::widen_f16`: the writer's bytes need not be aligned for an f16 cast.)
fn unit_row(row: &[u8], out: &mut [f32]) {
    for (v, b) in out.iter_mut().zip(row.chunks_exact(2)) {
        *v = f16::from_le_bytes([b[0], b[1]]).to_f32();
    }
    if out.iter().all(|v| v.is_finite()) {
        crate::vector::l2_normalise(out);
    } else {
        out.fill(0.0);
    }
}

/// (1.3) Adds the image index over the rows the map retrieves with (its metadata
/// `retrieval`, already set) to `writer`, read back from the writer: `lists` of them (`None`:
/// [`default_index_lists`], and only if it pays, see [`ImageIndexSummary::stored`]). `None`: no
/// index tried (0 lists, no retrieval rows, fewer images than lists).
pub(crate) fn add_image_index(
    writer: &mut MapWriter<'_>,
    lists: Option<usize>,
    neighbours: Option<Vec<u32>>,
    reporter: &dyn Reporter,
) -> Result<Option<ImageIndexSummary>, crate::format::Error> {
    let Some(of) = writer.metadata().retrieval() else {
        return Ok(None);
    };
    let kind = crate::format::indexed_kind(of);
    let Some((bytes, width)) = writer.pending_rows(kind, Dtype::F16) else {
        return Ok(None);
    };
    let row_bytes = width * 2;
    let images = bytes.len().checked_div(row_bytes).unwrap_or(0);
    let lists_asked = lists;
    // At most one list per image.
    let lists = lists
        .unwrap_or_else(|| default_index_lists(images))
        .min(images);
    if lists == 0 || width == 0 {
        return Ok(None);
    }
    let row = |i: usize| &bytes[i * row_bytes..(i + 1) * row_bytes];
    let neighbours = neighbours.filter(|rows| rows.len() == images * INDEX_NEIGHBOURS);
    // The images a place is grown to: a list's share of the images where lists are asked
    // for; by default PLACE_IMAGES, more where that would make over MAX_INDEX_LISTS lists
    // (every query scores every centroid: 8,192 of 1,024 f16 values are 17 MB a query).
    let place_size = lists_asked.map_or(default_place_size(images), |l| images.div_ceil(l.max(1)));

    // A seeded sample learns the centroids (k-means lists); the calibration images measure,
    // drawn past the sample when the map has the images for both.
    let mut rng = SplitMix64::new(INDEX_SEED);
    let mut order: Vec<usize> = (0..images).collect();
    let take = images.min(INDEX_MAX_TRAIN + CALIBRATION_IMAGES);
    for i in 0..take {
        let j = i + (rng.next_u64() % (images - i) as u64) as usize;
        order.swap(i, j);
    }
    // (1.4) With each image's neighbours, lists are places grown along them, each image's
    // list known before its row is read again; without, k-means lists, each image's found
    // in the pass below.
    let graph = neighbours.as_ref().map(|rows| Neighbours {
        per_image: INDEX_NEIGHBOURS,
        rows: Cow::Borrowed(rows),
    });
    let (centroids, placed, lists) = match &graph {
        Some(graph) => {
            reporter.start("image index places", None);
            let (mut list_of, lists) = place_lists(graph, images, place_size);
            // Images that share too few points for places (a place each, or nearly): every
            // query would score as many centroids as images. A default index is given up
            // before the centroids are made; scoring every list is ranking every image.
            if lists_asked.is_none() && lists * MAX_SCORED_SHARE > images {
                reporter.finish();
                return Ok(Some(ImageIndexSummary {
                    of,
                    lists,
                    probe: lists,
                    recall: 1.0,
                    scored: images,
                    stored: false,
                }));
            }
            let mut centroids =
                place_centroids(&list_of, lists, width, |i, out| unit_row(row(i), out));
            let lists = merge_undirected(&mut list_of, &mut centroids, width);
            reporter.finish();
            (centroids, Some(list_of), lists)
        }
        None => {
            let train = &order[..images.min(INDEX_MAX_TRAIN)];
            let mut sample = vec![0.0f32; train.len() * width];
            for (&i, out) in train.iter().zip(sample.chunks_exact_mut(width)) {
                unit_row(row(i), out);
            }
            reporter.start("image index", None);
            let centroids = KMeans {
                clusters: lists,
                max_train: INDEX_MAX_TRAIN,
                iterations: INDEX_ITERATIONS,
                seed: INDEX_SEED,
            }
            .train(&sample, width);
            reporter.finish();
            drop(sample);
            let Some(centroids) = centroids else {
                return Ok(None);
            };
            (centroids, None, lists)
        }
    };
    let calibration: Vec<usize> = order[take - images.min(CALIBRATION_IMAGES)..take].to_vec();
    let mut queries = vec![0.0f32; calibration.len() * width];
    for (&i, out) in calibration.iter().zip(queries.chunks_exact_mut(width)) {
        unit_row(row(i), out);
    }

    // One pass over the rows: each image's score against each calibration image
    // (`[calibration × images]`), and its k-means list.
    reporter.start("image index lists", Some(images as u64));
    let nearest = Nearest::new(&centroids, width);
    let mut list_of = placed.unwrap_or_else(|| vec![0u32; images]);
    let mut scores = vec![0.0f32; calibration.len() * images];
    let mut buffer = vec![0.0f32; width];
    for (i, list) in list_of.iter_mut().enumerate() {
        unit_row(row(i), &mut buffer);
        if neighbours.is_none() {
            *list = nearest.find(&buffer) as u32;
        }
        for (q, query) in queries.chunks_exact(width).enumerate() {
            scores[q * images + i] = dot(&buffer, query);
        }
        if i % 4096 == 0 {
            reporter.advance(4096.min(images - i) as u64);
        }
    }
    reporter.finish();

    let k = crate::format::DEFAULT_RETRIEVAL_TOP_K.min(images - 1);
    // A calibration image's own row is left out of its neighbours.
    for (q, &i) in calibration.iter().enumerate() {
        scores[q * images + i] = f32::NEG_INFINITY;
    }
    // (1.4) With each image's neighbours, queries widen along them: `probe` is calibrated on
    // that search; without, on the lists alone.
    let set = CalibrationSet {
        scores: &scores,
        calibration: &calibration,
        queries: &queries,
        nearest: &nearest,
        list_of: &list_of,
        lists,
        k,
    };
    let calibrated = match &graph {
        Some(graph) => calibrated_search(&set, graph, lists_asked.is_some(), QUERY_MIN_PROBE),
        None => calibrated_lists(&set),
    };
    drop(scores);
    let Calibrated {
        probe,
        recall,
        scored,
    } = calibrated;
    // A query scores every centroid too (a centroid is as wide as an image's row): a model
    // of images that share no points grows a place per image.
    let stored = lists_asked.is_some() || (scored + lists) * MAX_SCORED_SHARE <= images;
    let outcome = ImageIndexSummary {
        of,
        lists,
        probe,
        recall,
        scored,
        stored,
    };
    if stored {
        let places = neighbours.as_ref().map(|_| place_size);
        let info = index_info(of, probe, calibration.len(), k, recall, scored, places);
        writer.set_image_index(info, centroids, width, &list_of)?;
        if let Some(rows) = neighbours {
            writer.set_image_neighbours(rows, INDEX_NEIGHBOURS)?;
        }
    }
    Ok(Some(outcome))
}

/// The fewest lists that hold [`CALIBRATION_RECALL`] of the calibration images' exhaustive
/// top `k`, taken nearest centroid first, and the images those lists hold on average.
fn calibrated_lists(set: &CalibrationSet<'_>) -> Calibrated {
    let CalibrationSet {
        scores,
        queries,
        nearest,
        list_of,
        lists,
        k,
        ..
    } = *set;
    let images = list_of.len();
    let width = queries.len() / (scores.len() / images.max(1)).max(1);
    // Per calibration image: where its exhaustive top k's lists come in its list order (the
    // order a query probes them in), and the images its lists hold in that order.
    let mut list_sizes = vec![0usize; lists];
    for &l in list_of {
        list_sizes[l as usize] += 1;
    }
    let mut ranks_needed: Vec<usize> = Vec::new();
    let mut images_by_rank: Vec<Vec<usize>> = Vec::new();
    for (q, query) in queries.chunks_exact(width.max(1)).enumerate() {
        let row_scores = &scores[q * images..(q + 1) * images];
        let order = nearest.order(query);
        let mut list_rank = vec![0usize; lists];
        for (r, &l) in order.iter().enumerate() {
            list_rank[l] = r;
        }
        images_by_rank.push(order.iter().map(|&l| list_sizes[l]).collect());
        ranks_needed.extend(
            top_k_indices(row_scores, k)
                .into_iter()
                .map(|i| list_rank[list_of[i] as usize]),
        );
    }
    let (probe, recall) = calibrated_probe(&mut ranks_needed, lists);
    // What a query of them scores with that probe: lists are uneven, so counted in images.
    let scored = images_by_rank
        .iter()
        .map(|sizes| sizes[..probe].iter().sum::<usize>())
        .sum::<usize>()
        .checked_div(images_by_rank.len())
        .unwrap_or(images);
    Calibrated {
        probe,
        recall,
        scored,
    }
}

/// The metadata `image_index`: `probe`, the rule, and what the calibration measured.
fn index_info(
    of: Retrieval,
    probe: usize,
    images: usize,
    k: usize,
    recall: f64,
    scored: usize,
    places: Option<usize>,
) -> ImageIndexInfo {
    let mut extra = serde_json::Map::new();
    extra.insert("rule".into(), json!(index_rule(places)));
    extra.insert(
        "calibration".into(),
        json!({"images": images, "top_k": k, "recall": recall, "scored": scored}),
    );
    ImageIndexInfo {
        of: of.name().to_string(),
        probe: probe as u32,
        extra,
    }
}

/// A map's visibility, image → points (CSR), from which images' neighbours are found.
pub(crate) struct ImageVisibility<'a> {
    /// `[images + 1]`.
    pub offsets: &'a [u64],
    /// Each image's points, each below `n_points`.
    pub points: &'a [u32],
    pub n_points: usize,
}

/// Neighbours each image lists in the index (1.4): the images sharing most points with it.
pub(crate) const INDEX_NEIGHBOURS: usize = 16;

/// Whether `convert` tries an image index for a map of `images` images, `lists` asked for.
pub(crate) fn index_wanted(images: usize, lists: Option<usize>) -> bool {
    lists.unwrap_or_else(|| default_index_lists(images)) > 0
}

/// (1.4) The index's neighbours of `geometry`'s images ([`covisible_neighbours`]), where an
/// index will be tried.
pub(crate) fn index_neighbours(
    geometry: &Geometry,
    lists: Option<usize>,
    reporter: &dyn Reporter,
) -> Option<Vec<u32>> {
    if !index_wanted(geometry.names.len(), lists) {
        return None;
    }
    reporter.start("image neighbours", None);
    let visibility = ImageVisibility {
        offsets: &geometry.vis_offsets,
        points: &geometry.vis_points,
        n_points: geometry.positions.len(),
    };
    let rows = covisible_neighbours(&visibility, INDEX_NEIGHBOURS);
    reporter.finish();
    Some(rows)
}

/// The images a default place is grown to: [`PLACE_IMAGES`], more where that would make over
/// [`MAX_INDEX_LISTS`] places.
fn default_place_size(images: usize) -> usize {
    PLACE_IMAGES.max(images.div_ceil(MAX_INDEX_LISTS))
}

/// The image index's build memory beyond the rows it reads, for the memory plan: each
/// calibration image's score of every image (4 bytes), the images' lists, the order they are
/// drawn in, each list's members and a search's scored images (8 bytes each an image), the
/// centroids twice in f32 (the list and the search's blocks), each calibration image's list
/// order (8 bytes a list) and the calibration rows. Lists as the default makes them: places
/// of [`PLACE_IMAGES`], at most [`MAX_INDEX_LISTS`] (or k-means' √images); more are given up
/// before their centroids are made. 0 where no index is tried.
pub(crate) fn index_build_bytes(images: usize, width: usize, lists: Option<usize>) -> u64 {
    if !index_wanted(images, lists) {
        return 0;
    }
    let lists = lists
        .unwrap_or_else(|| {
            images
                .div_ceil(default_place_size(images))
                .max(default_index_lists(images))
        })
        .min(images) as u64;
    let (images, width, calibration) = (images as u64, width as u64, CALIBRATION_IMAGES as u64);
    // Scores and the calibration's orders (`top_k_indices` keeps no more than it returns);
    // lists, order, members and the search's scored images, 8 bytes each an image; the
    // centroids twice; the calibration rows.
    let per_image = calibration * 4 + 4 * 8;
    let per_list = width.saturating_mul(8).saturating_add(calibration * 8);
    images
        .saturating_mul(per_image)
        .saturating_add(lists.saturating_mul(per_list))
        .saturating_add(calibration.saturating_mul(width).saturating_mul(4))
}

/// Tracks longer than this are left out of the neighbours' counts.
const MAX_NEIGHBOUR_TRACK: usize = 128;

/// Each image's `per_image` neighbours: the other images that share most points with it,
/// most first (ties by the lower image), [`NO_NEIGHBOUR`] past the last; `[images ×
/// per_image]`. Images that share points are what a query near one of them also sees, so
/// their retrieval rows are each other's nearest. Time: the sum over points of their track
/// lengths squared, tracks over [`MAX_NEIGHBOUR_TRACK`] left out (so at most that many
/// steps an observation); memory: the visibility once more, turned point → images (4
/// bytes an observation, 8 a point).
pub(crate) fn covisible_neighbours(v: &ImageVisibility<'_>, per_image: usize) -> Vec<u32> {
    let images = v.offsets.len().saturating_sub(1);
    let entry = |i: usize| v.offsets[i] as usize..v.offsets[i + 1] as usize;
    // Point → images, CSR.
    let mut starts = vec![0u64; v.n_points + 1];
    for &p in v.points {
        starts[p as usize + 1] += 1;
    }
    for p in 0..v.n_points {
        starts[p + 1] += starts[p];
    }
    // Filled from each point's end down, images last to first, so each track ends in image
    // order and `starts` is left as each track's start (no second array of offsets).
    let mut seen_by = vec![0u32; v.points.len()];
    for p in 0..v.n_points {
        starts[p] = starts[p + 1];
    }
    for i in (0..images).rev() {
        for &p in v.points[entry(i)].iter().rev() {
            starts[p as usize] -= 1;
            seen_by[starts[p as usize] as usize] = i as u32;
        }
    }
    let mut rows = vec![NO_NEIGHBOUR; images * per_image];
    let mut shared = vec![0u32; images];
    let mut touched: Vec<u32> = Vec::new();
    for (i, row) in rows.chunks_exact_mut(per_image).enumerate() {
        for &p in &v.points[entry(i)] {
            let track = starts[p as usize] as usize..starts[p as usize + 1] as usize;
            // A point every image sees says little about which are neighbours, and its
            // pairs would cost the square of its track (a hostile model's million).
            if track.len() > MAX_NEIGHBOUR_TRACK {
                continue;
            }
            for &j in &seen_by[track] {
                if j as usize != i {
                    if shared[j as usize] == 0 {
                        touched.push(j);
                    }
                    shared[j as usize] = shared[j as usize].saturating_add(1);
                }
            }
        }
        let most_first =
            |a: &u32, b: &u32| shared[*b as usize].cmp(&shared[*a as usize]).then(a.cmp(b));
        let kept = touched.len().min(per_image);
        if touched.len() > per_image {
            touched.select_nth_unstable_by(per_image - 1, most_first);
        }
        touched[..kept].sort_unstable_by(most_first);
        row[..kept].copy_from_slice(&touched[..kept]);
        // Every count back to 0, not only the kept ones'.
        for &j in &touched {
            shared[j as usize] = 0;
        }
        touched.clear();
    }
    rows
}

/// What the calibration of a search along the neighbours measured at one `probe`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Calibrated {
    probe: usize,
    /// The share of the calibration images' exhaustive top k the search found.
    recall: f64,
    /// Images a search scored, on average.
    scored: usize,
}

/// What a probe is calibrated on: the calibration images (`calibration`, indices of the map's
/// images) with their rows (`queries`, `[calibration × width]`) and their scores against every
/// image (`scores`, `[calibration × images]`, each one's own −∞), the lists (`list_of` each
/// image's, `lists` of them, `nearest` their centroids) and the top `k` a query asks for.
#[derive(Clone, Copy)]
struct CalibrationSet<'a> {
    scores: &'a [f32],
    calibration: &'a [usize],
    queries: &'a [f32],
    nearest: &'a Nearest,
    list_of: &'a [u32],
    lists: usize,
    k: usize,
}

/// The lists a query probes with neighbours at least (all of them where there are fewer): a
/// map's own rows find their neighbours from the one nearest place, but a query's row is of
/// a partial view and features the map does not have, and on the 10 M-point street the
/// queries needed 4 to 8 places of 24 to 48 images to find every image sharing points with
/// them. 8 of 24 is about 200 images scored, a tenth of a millisecond.
const QUERY_MIN_PROBE: usize = 8;

/// The fewest lists, from `least` on (the writer's: [`QUERY_MIN_PROBE`]), a query probes
/// (taken nearest centroid first, then on until it scored [`MIN_SCORED_PER_K`] images per
/// image asked for, as the reference reader does) before it widens along `graph`, for the
/// calibration images to find [`CALIBRATION_RECALL`] of their exhaustive top `k`. Probes are tried 1, 2, 4, … then bisected (about 2 log₂ lists
/// searches per calibration image; the share found grows with the probe, near enough);
/// without `lists_asked`, it stops at a probe that scores more than a quarter of the
/// images, where no index is stored anyway.
fn calibrated_search(
    set: &CalibrationSet<'_>,
    graph: &Neighbours<'_>,
    lists_asked: bool,
    least: usize,
) -> Calibrated {
    let CalibrationSet {
        scores,
        calibration,
        queries,
        nearest,
        list_of,
        lists,
        k,
    } = *set;
    let images = list_of.len();
    let width = queries.len() / calibration.len().max(1);
    let mut members: Vec<Vec<u32>> = vec![Vec::new(); lists];
    for (i, &l) in list_of.iter().enumerate() {
        members[l as usize].push(i as u32);
    }
    let per_query: Vec<(Vec<usize>, Vec<usize>)> = (0..calibration.len())
        .map(|q| {
            let row = &scores[q * images..(q + 1) * images];
            let order = nearest.order(&queries[q * width..(q + 1) * width]);
            (order, top_k_indices(row, k))
        })
        .collect();
    let min_scored = k.max(1) * MIN_SCORED_PER_K;
    let mut truth: BitVec = BitVec::repeat(false, images);
    let mut scored: Vec<(u32, f32)> = Vec::new();
    let mut measure = |probe: usize| -> Calibrated {
        let (mut found, mut scored_total) = (0usize, 0usize);
        for (q, (order, top)) in per_query.iter().enumerate() {
            let row = &scores[q * images..(q + 1) * images];
            scored.clear();
            for (probed, &l) in order.iter().enumerate() {
                if probed >= probe && scored.len() >= min_scored {
                    break;
                }
                scored.extend(members[l].iter().map(|&i| (i, row[i as usize])));
            }
            graph.widen(&mut scored, images, k.max(1) * BEAM_PER_K, |picks| {
                picks.iter().map(|&i| row[i as usize]).collect()
            });
            // Each image is scored once: count the top k among them.
            for &i in top {
                truth.set(i, true);
            }
            found += scored.iter().filter(|&&(i, _)| truth[i as usize]).count();
            for &i in top {
                truth.set(i, false);
            }
            scored_total += scored.len();
        }
        Calibrated {
            probe,
            recall: found as f64 / (per_query.len() * k).max(1) as f64,
            scored: scored_total / per_query.len().max(1),
        }
    };
    let enough = |c: &Calibrated| c.recall >= CALIBRATION_RECALL;
    let too_costly =
        |c: &Calibrated| !lists_asked && (c.scored + lists) * MAX_SCORED_SHARE > images;
    // Doubling from the least probe: the first that holds the bar (or costs too much), and
    // the last below.
    let least = least.min(lists).max(1);
    let mut below = least - 1;
    let mut at = measure(least);
    while !enough(&at) && !too_costly(&at) && at.probe < lists {
        below = at.probe;
        at = measure((at.probe * 2).min(lists));
    }
    if !enough(&at) {
        return at;
    }
    // Bisection between the last probe below the bar and the first at it.
    let mut best = at;
    let (mut lo, mut hi) = (below, best.probe);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        let c = measure(mid);
        if enough(&c) {
            best = c;
            hi = mid;
        } else {
            lo = mid;
        }
    }
    best
}

/// The fewest lists that hold [`CALIBRATION_RECALL`] of the neighbours, from the rank of
/// each neighbour's list in its query's list order (sorted here), and the share they hold.
fn calibrated_probe(ranks_needed: &mut [usize], lists: usize) -> (usize, f64) {
    if ranks_needed.is_empty() {
        return (1, 1.0);
    }
    ranks_needed.sort_unstable();
    let at = ((ranks_needed.len() as f64 * CALIBRATION_RECALL).ceil() as usize)
        .clamp(1, ranks_needed.len());
    debug_assert!(ranks_needed[at - 1] < lists, "a list rank past the lists");
    let probe = ranks_needed[at - 1] + 1;
    let found = ranks_needed.iter().filter(|&&r| r < probe).count();
    (probe, found as f64 / ranks_needed.len() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::SectionKind;
    use crate::progress::Silent;

    /// `n` unit rows of `dims`: `groups` random directions, each row one of them (row `i`,
    /// group `i % groups`) plus noise of `spread` per value; `groups` 0: noise alone.
    fn rows(n: usize, dims: usize, groups: usize, spread: f32, seed: u64) -> Vec<f32> {
        let mut rng = SplitMix64::new(seed);
        let mut centre =
            || -> Vec<f32> { (0..dims).map(|_| rng.next_f64() as f32 - 0.5).collect() };
        let centres: Vec<Vec<f32>> = (0..groups).map(|_| centre()).collect();
        let mut out = Vec::with_capacity(n * dims);
        for i in 0..n {
            let noise = centre();
            let mut row: Vec<f32> = match centres.get(i % groups.max(1)) {
                Some(c) if groups > 0 => {
                    c.iter().zip(&noise).map(|(c, e)| c + spread * e).collect()
                }
                _ => noise,
            };
            crate::vector::l2_normalise(&mut row);
            out.extend(row);
        }
        out
    }

    /// A writer whose map retrieves by `rows` (as global descriptors).
    fn writer_of(rows: &[f32], dims: usize) -> MapWriter<'static> {
        let mut w = MapWriter::default();
        w.set_image_global(dims, rows).unwrap();
        w.metadata_mut().retrieval = Some(Retrieval::Global.name().into());
        w
    }

    #[test]
    fn grouped_rows_get_an_index_that_probes_few_lists() {
        // 3,000 images in 30 groups: an image's 10 nearest are of its group.
        let (n, dims) = (3_000, 32);
        let mut w = writer_of(&rows(n, dims, 30, 0.1, 1), dims);
        let index = add_image_index(&mut w, None, None, &Silent)
            .unwrap()
            .unwrap();
        assert_eq!(index.lists, default_index_lists(n));
        assert!(index.stored, "{index:?}");
        assert!(index.scored * MAX_SCORED_SHARE <= n, "{index:?}");
        assert!(index.scored >= index.probe, "{index:?}");
        let info = w.metadata().image_index.clone().unwrap();
        assert_eq!(
            (info.of.as_str(), info.probe as usize),
            ("global", index.probe)
        );
        // Every image in one list.
        let (images, _) = w
            .pending_rows(SectionKind::ImageIndexImages, Dtype::U32)
            .unwrap();
        let mut all: Vec<u32> = images
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        all.sort_unstable();
        assert_eq!(all, (0..n as u32).collect::<Vec<_>>());
    }

    #[test]
    fn rows_without_neighbours_get_no_index_unless_asked() {
        // Noise: an image's top 10 is anywhere, so 99 % of it takes most lists.
        let (n, dims) = (3_000, 32);
        let noise = rows(n, dims, 0, 1.0, 2);
        let mut w = writer_of(&noise, dims);
        let index = add_image_index(&mut w, None, None, &Silent)
            .unwrap()
            .unwrap();
        assert!(
            !index.stored && index.scored * MAX_SCORED_SHARE > n,
            "{index:?}"
        );
        assert!(w.metadata().image_index.is_none());
        assert!(w.to_bytes().is_ok());
        // Asked for, it is stored with the probe that reaches the recall.
        let mut w = writer_of(&noise, dims);
        let index = add_image_index(&mut w, Some(8), None, &Silent)
            .unwrap()
            .unwrap();
        assert!(index.stored && index.lists == 8, "{index:?}");
        assert_eq!(
            w.metadata().image_index.as_ref().unwrap().probe as usize,
            index.probe
        );
        // None below the default's image count, with 0 lists, or without retrieval rows.
        let mut w = writer_of(&noise[..100 * dims], dims);
        assert!(add_image_index(&mut w, None, None, &Silent)
            .unwrap()
            .is_none());
        let mut w = writer_of(&noise, dims);
        assert!(add_image_index(&mut w, Some(0), None, &Silent)
            .unwrap()
            .is_none());
        w.metadata_mut().retrieval = None;
        assert!(add_image_index(&mut w, Some(8), None, &Silent)
            .unwrap()
            .is_none());
    }

    /// Default places are 24 images until that would make over 8,192 of them.
    #[test]
    fn default_places_stay_under_the_list_cap() {
        assert_eq!(default_place_size(80_000), PLACE_IMAGES);
        for images in [196_608usize, 196_609, 1_000_000, 10_000_000] {
            let lists = images.div_ceil(default_place_size(images));
            assert!(lists <= MAX_INDEX_LISTS, "{images}: {lists}");
        }
        assert!(default_place_size(1_000_000) > PLACE_IMAGES);
    }

    /// (1.4) With neighbours, lists are places; where the images share no points each is
    /// its own place, and a query would score a centroid per image: no index by default.
    #[test]
    fn places_are_stored_where_they_pay_and_not_per_image() {
        let (n, dims) = (3_000, 4);
        // A path: image i's row at angle i·π/n on a half circle, so its best images are
        // its nearest along the path; its neighbours the 16 nearest.
        let angle = |i: usize| i as f32 * std::f32::consts::PI / n as f32;
        let path: Vec<f32> = (0..n)
            .flat_map(|i| [angle(i).cos(), angle(i).sin(), 0.0, 0.0])
            .collect();
        let mut graph = vec![NO_NEIGHBOUR; n * INDEX_NEIGHBOURS];
        for i in 0..n {
            let mut near: Vec<u32> = (1..=8)
                .flat_map(|d| [i.checked_sub(d), Some(i + d)])
                .flatten()
                .filter(|&j| j < n)
                .map(|j| j as u32)
                .collect();
            near.truncate(INDEX_NEIGHBOURS);
            graph[i * INDEX_NEIGHBOURS..i * INDEX_NEIGHBOURS + near.len()].copy_from_slice(&near);
        }
        let mut w = writer_of(&path, dims);
        let index = add_image_index(&mut w, None, Some(graph), &Silent)
            .unwrap()
            .unwrap();
        assert!(index.stored, "{index:?}");
        assert_eq!(index.lists, n.div_ceil(PLACE_IMAGES), "{index:?}");
        assert!(index.probe >= QUERY_MIN_PROBE, "{index:?}");
        let rule = &w.metadata().image_index.as_ref().unwrap().extra["rule"];
        assert!(rule.as_str().unwrap().starts_with("neighbours:"), "{rule}");
        // No image shares a point: 3,000 places of one image, not stored.
        let mut w = writer_of(&path, dims);
        let lone = vec![NO_NEIGHBOUR; n * INDEX_NEIGHBOURS];
        let index = add_image_index(&mut w, None, Some(lone), &Silent)
            .unwrap()
            .unwrap();
        assert!(!index.stored && index.lists == n, "{index:?}");
        assert!(w.metadata().image_index.is_none());
    }

    #[test]
    fn the_probe_is_the_fewest_lists_holding_the_bar() {
        // 100 neighbours: 98 in the first list, one in the 3rd, one in the 7th.
        let mut ranks = vec![0usize; 98];
        ranks.extend([2, 6]);
        let (probe, recall) = calibrated_probe(&mut ranks, 10);
        assert_eq!(probe, 3);
        assert!((recall - 0.99).abs() < 1e-12);
        assert_eq!(calibrated_probe(&mut [], 10), (1, 1.0));
        // The last list, when the bar needs it.
        assert_eq!(calibrated_probe(&mut [9, 9], 10).0, 10);
    }

    #[test]
    fn a_stated_shape_wins_over_the_images_rule() {
        let by_images = VladOptions::default();
        let own = crate::vlad::DescribedAt::OwnKeypoints;
        assert_eq!(
            by_images.shape(100, own),
            crate::vlad::default_shape(100, own)
        );
        assert_eq!(
            by_images.shape(10_000, own),
            crate::vlad::default_shape(10_000, own)
        );
        let stated = VladOptions {
            clusters: Some(0),
            dims: None,
            index_lists: None,
        };
        assert_eq!(stated.shape(10_000, own).0, 0);
        assert_eq!(stated.shape(10_000, own).1, crate::vlad::LARGE_DIMS);
    }

    /// (1.4) Rows along a half circle (images along a street) in 20 lists of 20 in a row:
    /// with each image's 4 nearest as neighbours, one list probed finds every calibration
    /// image's top 10; lists alone need more.
    #[test]
    fn the_search_along_neighbours_is_calibrated_to_one_list() {
        let (n, dim, lists) = (400usize, 4usize, 20usize);
        let angle = |i: usize| i as f32 * std::f32::consts::PI / n as f32;
        let rows: Vec<f32> = (0..n)
            .flat_map(|i| [angle(i).cos(), angle(i).sin(), 0.0, 0.0])
            .collect();
        let list_of: Vec<u32> = (0..n).map(|i| (i / 20) as u32).collect();
        let mut centroids = vec![0.0f32; lists * dim];
        for (i, row) in rows.chunks_exact(dim).enumerate() {
            for (c, r) in centroids[(i / 20) * dim..(i / 20 + 1) * dim]
                .iter_mut()
                .zip(row)
            {
                *c += r / 20.0;
            }
        }
        let nearest = Nearest::new(&centroids, dim);
        let mut graph = Vec::new();
        for i in 0..n as i64 {
            // The ±1 pair then the ±2 pair, those past the ends left out, end marks last.
            let mut near: Vec<u32> = [-1i64, 1, -2, 2]
                .iter()
                .map(|d| i + d)
                .filter(|j| (0..n as i64).contains(j))
                .map(|j| j as u32)
                .collect();
            near.resize(4, NO_NEIGHBOUR);
            graph.extend(near);
        }
        // The calibration images: every fourth, each one's own score −∞.
        let calibration: Vec<usize> = (0..n).step_by(4).collect();
        let queries: Vec<f32> = calibration
            .iter()
            .flat_map(|&i| rows[i * dim..(i + 1) * dim].to_vec())
            .collect();
        let mut scores = vec![0.0f32; calibration.len() * n];
        for (q, &c) in calibration.iter().enumerate() {
            for i in 0..n {
                scores[q * n + i] =
                    dot(&rows[c * dim..(c + 1) * dim], &rows[i * dim..(i + 1) * dim]);
            }
            scores[q * n + c] = f32::NEG_INFINITY;
        }
        let graph = Neighbours {
            per_image: 4,
            rows: Cow::Owned(graph),
        };
        let set = CalibrationSet {
            scores: &scores,
            calibration: &calibration,
            queries: &queries,
            nearest: &nearest,
            list_of: &list_of,
            lists,
            k: 10,
        };
        let search = |least| calibrated_search(&set, &graph, false, least);
        let c = search(1);
        assert_eq!((c.probe, c.recall), (1, 1.0), "{c:?}");
        assert!(c.scored < 200, "{c:?}");
        // From a least probe on, that is the probe where it holds the bar.
        assert_eq!(search(QUERY_MIN_PROBE).probe, QUERY_MIN_PROBE);
        assert_eq!(search(lists + 5).probe, lists, "at most every list");
        // Lists alone: a query near a list's end has its top 10 in two lists, and the
        // second is not always next in its list order.
        let mut ranks = Vec::new();
        for (q, _) in calibration.iter().enumerate() {
            let order = nearest.order(&queries[q * dim..(q + 1) * dim]);
            let mut rank = vec![0usize; lists];
            for (r, &l) in order.iter().enumerate() {
                rank[l] = r;
            }
            ranks.extend(
                top_k_indices(&scores[q * n..(q + 1) * n], 10)
                    .into_iter()
                    .map(|i| rank[list_of[i] as usize]),
            );
        }
        assert!(calibrated_probe(&mut ranks, lists).0 > 1);
    }

    /// Image neighbours are the images sharing most points, most first, ties by the lower
    /// image, never the image itself, cut at `per_image`, padded with `NO_NEIGHBOUR`; the
    /// counts of one image do not leak into the next.
    #[test]
    fn neighbours_are_the_images_sharing_most_points() {
        // Images 0..4 over points 0..6: 0 sees {0,1,2,3}, 1 {0,1,2}, 2 {2,3}, 3 {5}, 4 {0,5}.
        let offsets = [0u64, 4, 7, 9, 10, 12];
        let points = [0u32, 1, 2, 3, 0, 1, 2, 2, 3, 5, 0, 5];
        let v = ImageVisibility {
            offsets: &offsets,
            points: &points,
            n_points: 6,
        };
        let rows = covisible_neighbours(&v, 2);
        let none = NO_NEIGHBOUR;
        assert_eq!(
            rows,
            [
                1, 2, // 0 shares 3 with 1, 2 with 2, 1 with 4
                0, 2, // 1: 3 with 0, then 1 with 2 and 1 with 4: the lower
                0, 1, // 2: 2 with 0, 1 with 1
                4, none, // 3: 1 with 4 only
                0, 1, // 4: 1 with 0, 1, 3: the lower two
            ]
        );
        // A wider row keeps the rest in order.
        assert_eq!(&covisible_neighbours(&v, 3)[..3], &[1, 2, 4]);
    }
}
