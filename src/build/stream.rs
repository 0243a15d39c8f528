//! Each point's descriptor, made in bounded memory: the source's images are read in model
//! order and a point's observations summed (or kept, for the medoid) only while its track is
//! open, from its first image to its last; a closed point's descriptor goes to a scratch file
//! in point order ([`Spill`]). Where the open tracks would not fit the memory budget, the
//! points are split into ranges of points and the source is read once per range.
//!
//! Each point sees its observations in the order the whole-map aggregation saw them (image
//! order, then the image's visibility order), so the descriptors, and the map made of them,
//! are the same bytes whatever the budget.

use super::features::{FeatureSource, ModelImage, MAX_DESCRIPTOR_DIM};
use super::geometry::Geometry;
use super::sift::{Aggregate, ConvertOptions};
use super::ConvertError;
use crate::format::{read_at, write_at};
use crate::progress::Reporter;
use bitvec::vec::BitVec;
use std::fs::File;
use std::path::{Path, PathBuf};

/// Reads of the features at most (`--memory`): a smaller budget is refused, naming the
/// smallest that works with this many.
pub const MAX_PASSES: usize = 64;

/// Memory the program needs besides what the plan counts (its code, the allocator's
/// slack, one image's features, the scratch files' buffers).
const BASELINE_BYTES: u64 = 160 << 20;

/// A closed point's row waits here until this many bytes of rows are held.
const SPILL_BUFFER_BYTES: usize = 16 << 20;

/// The points' descriptors, aggregated: what [`super::sift`] builds the levels from.
pub(crate) struct Aggregated {
    /// Dimensions of a descriptor (0: no image had features).
    pub dim: usize,
    /// The feature the map records as its levels' `descriptor`.
    pub feature: String,
    /// What `feature_source` records: where the descriptors came from.
    pub source_kind: &'static str,
    /// Whether every image's keypoints had a scale (levels by scale; else one level).
    pub scaled: bool,
    /// Each point's median keypoint scale over its described observations (NaN: none).
    pub median: Vec<f32>,
    /// Points with a descriptor.
    pub has: BitVec,
    /// Each point's descriptor, `dim` f32, in point order (zeros where `has` is unset).
    pub spill: Spill,
    /// Images the source has no features for.
    pub images_without_features: usize,
}

/// How a conversion fits its memory budget (`convert --json`'s `memory`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MemoryPlan {
    /// The budget, in bytes (`--memory`, or half the machine's).
    pub budget: u64,
    /// Reads of the features: the points are made in this many ranges, one read each.
    pub passes: usize,
    /// The most memory the plan expects the conversion to use, in bytes (an estimate from
    /// the model's counts).
    pub peak: u64,
}

/// What a conversion holds besides the open tracks, estimated from the model's counts:
/// `before_reads` (the geometry, and (1.4) the visibility turned point → images
/// to find the image index's neighbours), `during` the reads of the features (the geometry,
/// per-point arrays), and `after` them (the geometry, the retrieval rows and VLADs, the
/// image index's build, sections the writer holds in memory).
#[derive(Debug, Clone, Copy)]
pub(crate) struct FixedCost {
    pub before_reads: u64,
    pub during: u64,
    pub after: u64,
}

impl FixedCost {
    /// The estimate for `geometry` with descriptors of `dim` values (and global descriptors
    /// of `global_width`, 0 without: the image index may be over them).
    pub(crate) fn of(
        geometry: &Geometry,
        options: &ConvertOptions,
        dim: usize,
        global_width: usize,
    ) -> FixedCost {
        let g = geometry;
        let (points, images) = (g.positions.len() as u64, g.names.len() as u64);
        let geometry_bytes = g.heap_bytes();
        // Tracks (last image, length), the open slots' index, medians, the levels' points,
        // the writer's positions: about 36 bytes a point.
        let per_point = points * 36;
        let short = super::sift::short_dims(options.short_dims, dim) as u64;
        let (clusters, dims) = options
            .vlad
            .shape(g.names.len(), crate::vlad::DescribedAt::OwnKeypoints);
        // Retrieval rows (f32 a point), each image's VLAD in f32 and in the writer's f16.
        let vlad = if clusters > 0 && dims > 0 {
            let dims = (dims as u64).min(short);
            points * dims * 4 + images * clusters as u64 * dims * 6
        } else {
            0
        };
        // A codec other than raw compresses each section whole beside its bytes; `--pq`
        // reads the whole map back in memory (`pq::quantise_all`): the levels and the
        // geometry's sections again.
        let levels = points * dim as u64 * 2;
        let held = if options.pq.is_some() {
            2 * (levels + geometry_bytes)
        } else if options.codec != crate::format::Codec::Raw {
            levels + geometry_bytes
        } else {
            0
        };
        // (1.4) The image index's neighbours, found before the reads: the visibility turned
        // point → images (4 bytes an observation, 8 a point), the tracks' 8 bytes a point,
        // a count and a touched slot an image; kept to the write, 4 bytes a neighbour.
        let (neighbour_search_bytes, neighbour_bytes) =
            if super::retrieval::index_wanted(g.names.len(), options.vlad.index_lists) {
                let n = super::retrieval::INDEX_NEIGHBOURS as u64;
                let search = g.vis_points.len() as u64 * 4 + points * 16 + images * (8 + 4 * n);
                (search, images * 4 * n)
            } else {
                (0, 0)
            };
        // The image index, built after the reads from the VLADs or the global descriptors
        // (its rows are counted with them).
        let index = super::retrieval::index_build_bytes(
            g.names.len(),
            (clusters * dims.min(short as usize)).max(global_width),
            options.vlad.index_lists,
        );
        FixedCost {
            before_reads: geometry_bytes + neighbour_search_bytes,
            during: geometry_bytes + per_point + neighbour_bytes,
            after: geometry_bytes + per_point + vlad + held + neighbour_bytes + index,
        }
    }
}

/// Half the memory this process may use: the machine's (`/proc/meminfo`'s `MemTotal`), or
/// less where its cgroup, or one above it, limits it ([`cgroup_limit`]); 8 GB where
/// neither can be read. The budget of a conversion that names none.
pub fn default_memory_budget() -> u64 {
    let read = |path: &str| std::fs::read_to_string(path).ok();
    let total = read("/proc/meminfo").and_then(|text| {
        let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
        let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        kb.checked_mul(1024)
    });
    let limit = read("/proc/self/cgroup").and_then(|own| cgroup_limit(&own, read));
    match (total, limit) {
        (Some(t), Some(l)) => t.min(l) / 2,
        (Some(m), None) | (None, Some(m)) => m / 2,
        (None, None) => 8_000_000_000,
    }
}

/// The tightest memory limit on the cgroup that `own` (`/proc/self/cgroup`'s text) names and
/// on those above it, as `read` gives their files: v2's `memory.max` (`0::/path`), v1's
/// `memory.limit_in_bytes` (`N:memory:/path`). `max` and v1's "no limit" (about 2^63) are no
/// limit. A job limited without a namespace of its own (Slurm, `systemd-run -p MemoryMax`)
/// has its limit on its own cgroup, not the root.
fn cgroup_limit(own: &str, read: impl Fn(&str) -> Option<String>) -> Option<u64> {
    let mut limits = Vec::new();
    for line in own.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(path)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        let (root, file) = match controllers {
            "" => ("/sys/fs/cgroup", "memory.max"),
            c if c.split(',').any(|c| c == "memory") => {
                ("/sys/fs/cgroup/memory", "memory.limit_in_bytes")
            }
            _ => continue,
        };
        // The cgroup and every one above it, up to the root.
        let mut dir = path.trim_end_matches('/').to_string();
        loop {
            let limit = read(&format!("{root}{dir}/{file}"))
                .and_then(|t| t.trim().parse::<u64>().ok())
                .filter(|&l| l < 1 << 62);
            limits.extend(limit);
            match dir.rfind('/') {
                Some(k) => dir.truncate(k),
                None => break,
            }
        }
    }
    limits.into_iter().min()
}

/// The last image (model order) observing each point, and its observations.
struct Tracks {
    last: Vec<u32>,
    lengths: Vec<u32>,
}

impl Tracks {
    fn new(geometry: &Geometry) -> Tracks {
        let n = geometry.positions.len();
        let mut last = vec![u32::MAX; n];
        let mut lengths = vec![0u32; n];
        for i in 0..geometry.names.len() {
            for &p in image_points(geometry, i) {
                last[p as usize] = i as u32;
                lengths[p as usize] = lengths[p as usize].saturating_add(1);
            }
        }
        Tracks { last, lengths }
    }

    /// Bytes an open point holds: its sum (or every observation's row, for the medoid) and
    /// its scales.
    fn weight(&self, p: usize, dim: usize, how: Aggregate) -> u64 {
        let track = u64::from(self.lengths[p]);
        let rows = match how {
            Aggregate::Mean => dim as u64 * 4,
            Aggregate::Medoid => track * dim as u64 * 4,
        };
        rows + track * 4 + 64
    }

    /// The most bytes open at once in each of `ranges` equal ranges of points.
    fn peaks(&self, geometry: &Geometry, ranges: usize, dim: usize, how: Aggregate) -> Vec<u64> {
        let n = self.last.len();
        let mut open: BitVec = BitVec::repeat(false, self.last.len());
        let (mut now, mut peak) = (vec![0u64; ranges], vec![0u64; ranges]);
        for i in 0..geometry.names.len() {
            let points = image_points(geometry, i);
            for &p in points {
                let p = p as usize;
                if !open[p] {
                    open.set(p, true);
                    let r = range_of(p, n, ranges);
                    now[r] += self.weight(p, dim, how);
                    peak[r] = peak[r].max(now[r]);
                }
            }
            for &p in points {
                let p = p as usize;
                if self.last[p] == i as u32 && open[p] {
                    open.set(p, false);
                    now[range_of(p, n, ranges)] -= self.weight(p, dim, how);
                }
            }
        }
        peak
    }
}

/// The range of `point` when `points` are split into `ranges` ranges of consecutive points
/// as even as they go: none is empty while `ranges <= points`.
fn range_of(point: usize, points: usize, ranges: usize) -> usize {
    (point as u64 * ranges as u64 / points.max(1) as u64) as usize
}

/// The points of range `r` of [`range_of`]: `p` with `p × ranges ≥ r × points`, below the
/// next range's.
fn range_bounds(r: usize, points: usize, ranges: usize) -> std::ops::Range<usize> {
    let start = |r: usize| (r as u64 * points as u64).div_ceil(ranges.max(1) as u64) as usize;
    start(r)..start(r + 1).min(points)
}

fn image_points(geometry: &Geometry, i: usize) -> &[u32] {
    let range = geometry.vis_offsets[i] as usize..geometry.vis_offsets[i + 1] as usize;
    &geometry.vis_points[range]
}

/// The fewest reads of the features (1, 2, 4, … [`MAX_PASSES`]) whose open tracks fit
/// `budget` beside `fixed`, or the error naming the smallest budget that works.
fn plan(
    tracks: &Tracks,
    geometry: &Geometry,
    dim: usize,
    how: Aggregate,
    fixed: FixedCost,
    budget: u64,
    model: &Path,
) -> Result<MemoryPlan, ConvertError> {
    let refuse = |needed: u64, passes: usize| ConvertError::MemoryBudget {
        model: model.to_path_buf(),
        budget,
        needed,
        passes,
    };
    let most = MAX_PASSES.min(tracks.last.len().max(1));
    // Ranges at 2n reads do not nest in those at n: the least need over every count tried.
    let mut least = (u64::MAX, 1);
    let mut passes = 1;
    loop {
        let worst = tracks
            .peaks(geometry, passes, dim, how)
            .into_iter()
            .max()
            .unwrap_or(0);
        // The open points' rows and the spill's buffer while reading, the retrieval rows
        // after.
        let reading = fixed.during + worst + SPILL_BUFFER_BYTES as u64;
        let peak = BASELINE_BYTES + reading.max(fixed.after).max(fixed.before_reads);
        if peak <= budget {
            return Ok(MemoryPlan {
                budget,
                passes,
                peak,
            });
        }
        least = least.min((peak, passes));
        if passes >= most {
            return Err(refuse(least.0, least.1));
        }
        passes = (passes * 2).min(most);
    }
}

/// The points' open tracks in one read of the features: slots reused as tracks close.
struct Open {
    dim: usize,
    how: Aggregate,
    /// Each point's slot while its track is open (`u32::MAX`: not open).
    slot_of: Vec<u32>,
    free: Vec<u32>,
    /// Mean: `[slots × dim]` sums.
    sums: Vec<f32>,
    /// Per slot: the keypoint scales of the observations so far.
    scales: Vec<Vec<f32>>,
    /// Medoid: per slot, the observations' normalised rows, in order.
    rows: Vec<Vec<f32>>,
}

impl Open {
    fn new(points: usize, dim: usize, how: Aggregate) -> Open {
        Open {
            dim,
            how,
            slot_of: vec![u32::MAX; points],
            free: Vec::new(),
            sums: Vec::new(),
            scales: Vec::new(),
            rows: Vec::new(),
        }
    }

    fn slot(&mut self, p: usize) -> usize {
        if self.slot_of[p] != u32::MAX {
            return self.slot_of[p] as usize;
        }
        let slot = match self.free.pop() {
            Some(s) => s as usize,
            None => {
                let s = self.scales.len();
                self.scales.push(Vec::new());
                self.rows.push(Vec::new());
                if self.how == Aggregate::Mean {
                    // Grown by an eighth at a time, not doubled: within what the plan counts.
                    if self.sums.len() + self.dim > self.sums.capacity() {
                        let more = (self.sums.len() / 8).max(1024 * self.dim);
                        self.sums.reserve_exact(more);
                    }
                    self.sums.resize((s + 1) * self.dim, 0.0);
                }
                s
            }
        };
        self.slot_of[p] = slot as u32;
        slot
    }

    /// One observation of `p` (of `track` observations in all): its normalised row and
    /// keypoint scale. A slot's lists are reserved for its whole track at once, as the plan
    /// counts them, not grown by doubling.
    fn add(&mut self, p: usize, row: &[f32], scale: f32, track: u32) {
        let s = self.slot(p);
        if self.scales[s].capacity() == 0 {
            self.scales[s].reserve_exact(track as usize);
            if self.how == Aggregate::Medoid {
                self.rows[s].reserve_exact(track as usize * self.dim);
            }
        }
        self.scales[s].push(scale);
        match self.how {
            Aggregate::Mean => {
                for (o, v) in self.sums[s * self.dim..(s + 1) * self.dim]
                    .iter_mut()
                    .zip(row)
                {
                    *o += v;
                }
            }
            Aggregate::Medoid => self.rows[s].extend_from_slice(row),
        }
    }

    /// Closes `p`'s track: its descriptor into `out` and its median scale, or `None` if it
    /// had no described observation.
    fn close(&mut self, p: usize, out: &mut [f32]) -> Option<f32> {
        let s = self.slot_of[p];
        if s == u32::MAX {
            return None;
        }
        let s = s as usize;
        self.slot_of[p] = u32::MAX;
        self.free.push(s as u32);
        let dim = self.dim;
        match self.how {
            Aggregate::Mean => {
                let sum = &mut self.sums[s * dim..(s + 1) * dim];
                out.copy_from_slice(sum);
                sum.fill(0.0);
                crate::vector::l2_normalise(out);
            }
            Aggregate::Medoid => {
                let rows = std::mem::take(&mut self.rows[s]);
                let row = |k: usize| &rows[k * dim..(k + 1) * dim];
                let n = rows.len() / dim.max(1);
                // The highest summed similarity to the others; ties: the earlier observation.
                // Each score once (the same sums, in the same order, as scored per comparison).
                let scores: Vec<f32> = (0..n)
                    .map(|k| (0..n).map(|o| crate::vector::dot(row(k), row(o))).sum())
                    .collect();
                let best = (0..n)
                    .max_by(|&i, &j| scores[i].total_cmp(&scores[j]).then(j.cmp(&i)))
                    .unwrap_or(0);
                out.copy_from_slice(row(best));
            }
        }
        let mut scales = std::mem::take(&mut self.scales[s]);
        scales.sort_by(f32::total_cmp);
        Some(scales[scales.len() / 2])
    }
}

/// A conversion's reads of the features, planned: made before anything long starts, so a
/// budget too small is refused up front.
pub(crate) struct Prepared {
    reader: ImageReader,
    tracks: Tracks,
    /// The plan.
    pub memory: MemoryPlan,
}

#[cfg(test)]
thread_local! {
    /// Tests: the reads of the features every conversion on this thread makes, whatever its
    /// budget (so small maps are made in several).
    pub(super) static FORCED_PASSES: std::cell::Cell<Option<usize>> =
        const { std::cell::Cell::new(None) };
}

#[cfg(test)]
impl Prepared {
    /// The same reads in `passes` ranges of points, whatever the budget.
    fn with_passes(mut self, passes: usize) -> Prepared {
        self.memory.passes = passes;
        self
    }
}

/// Reads the first image's features (the descriptors' dimensions), then plans the reads of
/// the features within `options.memory` bytes (else [`default_memory_budget`]) beside
/// `global_bytes` of global descriptors.
pub(crate) fn prepare(
    geometry: &Geometry,
    source: &mut dyn FeatureSource,
    options: &ConvertOptions,
    global_bytes: u64,
    model: &Path,
) -> Result<Prepared, ConvertError> {
    let mut reader = ImageReader {
        path: source.path().to_path_buf(),
        strict: options.strict,
        dim: 0,
        scaled: true,
        missing: 0,
    };
    for i in 0..geometry.names.len() {
        if let Some(features) = reader.read(geometry, source, i, &crate::progress::Silent)? {
            reader.dim = features.dim;
            break;
        }
    }
    reader.missing = 0;
    let dim = reader.dim;
    let tracks = Tracks::new(geometry);
    let budget = options.memory.unwrap_or_else(default_memory_budget);
    let global_width = (global_bytes / 6)
        .checked_div(geometry.names.len() as u64)
        .unwrap_or(0) as usize;
    let mut fixed = FixedCost::of(geometry, options, dim, global_width);
    // Global descriptors (`--global-features`), held from before the reads to the write.
    fixed.before_reads += global_bytes;
    fixed.during += global_bytes;
    fixed.after += global_bytes;
    let memory = plan(
        &tracks,
        geometry,
        dim,
        options.aggregate,
        fixed,
        budget,
        model,
    )?;
    let prepared = Prepared {
        reader,
        tracks,
        memory,
    };
    #[cfg(test)]
    let prepared = match FORCED_PASSES.get() {
        Some(passes) => prepared.with_passes(passes),
        None => prepared,
    };
    Ok(prepared)
}

/// Reads every model image's features from `source` as `prepared` plans, and makes each
/// point's descriptor and median scale; the descriptors go to a scratch file beside `output`.
pub(crate) fn aggregate(
    geometry: &Geometry,
    source: &mut dyn FeatureSource,
    options: &ConvertOptions,
    prepared: Prepared,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<Aggregated, ConvertError> {
    let Prepared {
        mut reader,
        tracks,
        memory,
    } = prepared;
    let path = reader.path.clone();
    let n_points = geometry.positions.len();
    let dim = reader.dim;
    let mut out = Aggregated {
        dim,
        feature: String::new(),
        source_kind: source.kind(),
        scaled: true, // set once every image was read
        median: vec![f32::NAN; n_points],
        has: BitVec::repeat(false, n_points),
        spill: Spill::create(output, n_points, dim)?,
        images_without_features: 0,
    };
    let mut row = Vec::new();
    let mut closed = vec![0.0f32; dim];
    for pass in 0..memory.passes {
        let points = range_bounds(pass, n_points, memory.passes);
        let in_range = |p: usize| points.contains(&p);
        let stage = match memory.passes {
            1 => "reading features".to_string(),
            n => format!("reading features ({} of {n})", pass + 1),
        };
        let warn: &dyn Reporter = if pass == 0 {
            reporter
        } else {
            &crate::progress::Silent
        };
        reporter.start(&stage, Some(geometry.names.len() as u64));
        let mut open = Open::new(n_points, dim, options.aggregate);
        for i in 0..geometry.names.len() {
            let features = reader.read(geometry, source, i, warn)?;
            let entries = geometry.vis_offsets[i] as usize..geometry.vis_offsets[i + 1] as usize;
            if let Some(features) = features {
                let name = &geometry.names[i];
                for (&point, &idx) in geometry.vis_points[entries.clone()]
                    .iter()
                    .zip(&geometry.vis_point2d[entries.clone()])
                {
                    let (point, idx) = (point as usize, idx as usize);
                    // The first read checks every observation; later ones only their range's.
                    if pass == 0 || in_range(point) {
                        let scale = reader.observation(&features, name, idx, &mut row)?;
                        if in_range(point) {
                            open.add(point, &row, scale, tracks.lengths[point]);
                        }
                    }
                }
            }
            for &p in &geometry.vis_points[entries] {
                let p = p as usize;
                if in_range(p) && tracks.last[p] == i as u32 {
                    if let Some(median) = open.close(p, &mut closed) {
                        out.median[p] = median;
                        out.has.set(p, true);
                        out.spill.put(p, &closed)?;
                    }
                }
            }
            reporter.advance(1);
        }
        reporter.finish();
        if pass == 0 {
            out.images_without_features = reader.missing;
        }
    }
    out.spill.flush()?;
    out.scaled = reader.scaled;
    if out.images_without_features > 0 {
        reporter.warn(&format!(
            "{} of {} images have no features in {}",
            out.images_without_features,
            geometry.names.len(),
            crate::escape::path(&path)
        ));
    }
    out.feature = source
        .feature_name()
        .unwrap_or_else(|| format!("{}{}", crate::format::UNNAMED_FEATURE_PREFIX, dim));
    Ok(out)
}

/// One image's features at a time, checked as the map needs them.
struct ImageReader {
    path: PathBuf,
    strict: bool,
    /// The descriptors' dimensions (0: none read yet).
    dim: usize,
    /// Whether every image read had keypoint scales.
    scaled: bool,
    /// Images without features, counted in the first read (reset after `prepare`'s look).
    missing: usize,
}

impl ImageReader {
    /// Image `i`'s features, `None` (warned of) where the source has none.
    fn read(
        &mut self,
        geometry: &Geometry,
        source: &mut dyn FeatureSource,
        i: usize,
        reporter: &dyn Reporter,
    ) -> Result<Option<super::features::SourceFeatures>, ConvertError> {
        let name = &geometry.names[i];
        let image = ModelImage {
            id: geometry.image_ids[i],
            name,
            size: geometry.image_size(i),
        };
        let Some(features) = source.image(image)? else {
            if self.strict {
                return Err(ConvertError::MissingFeatures {
                    features: self.path.clone(),
                    image: name.clone(),
                });
            }
            self.missing += 1;
            reporter.warn(&format!(
                "{}: image {} has no features; its observations get no descriptor",
                crate::escape::path(&self.path),
                crate::escape::quoted_name(name)
            ));
            return Ok(None);
        };
        if features.dim == 0 || features.dim > MAX_DESCRIPTOR_DIM {
            return Err(ConvertError::Input(crate::io::InputError {
                path: self.path.clone(),
                line: None,
                message: format!(
                    "image {}: descriptors of {} dimensions (1 to {MAX_DESCRIPTOR_DIM} are taken)",
                    crate::escape::quoted_name(name),
                    features.dim
                ),
            }));
        }
        if self.dim != 0 && features.dim != self.dim {
            return Err(ConvertError::DescriptorDim {
                features: self.path.clone(),
                image: name.clone(),
                expected: self.dim,
                found: features.dim,
            });
        }
        self.scaled &= features.scales.is_some();
        Ok(Some(features))
    }

    /// Keypoint `idx`'s descriptor, normalised, into `row`, and its scale (1 without
    /// scales); every observation is checked, whichever range of points is being made.
    fn observation(
        &self,
        features: &super::features::SourceFeatures,
        name: &str,
        idx: usize,
        row: &mut Vec<f32>,
    ) -> Result<f32, ConvertError> {
        if idx >= features.keypoints || !features.values.row_into(self.dim, idx, row) {
            return Err(ConvertError::KeypointOutOfRange {
                features: self.path.clone(),
                image: name.to_string(),
                point2d_idx: idx,
                keypoints: features.keypoints,
            });
        }
        // Without scales every observation is alike: one level.
        let scale = features.scales.as_ref().map_or(1.0, |s| s[idx]);
        // A NaN scale would drop the point from every level without a word; the level
        // assignment and the metadata's scale ranges need finite scales.
        if !scale.is_finite() {
            return Err(ConvertError::KeypointScaleNotFinite {
                features: self.path.clone(),
                image: name.to_string(),
                point2d_idx: idx,
            });
        }
        if let Some(v) = row.iter().find(|v| !v.is_finite()) {
            return Err(ConvertError::Input(crate::io::InputError {
                path: self.path.clone(),
                line: None,
                message: format!(
                    "image {}: keypoint {idx}: a descriptor value is {v}",
                    crate::escape::quoted_name(name)
                ),
            }));
        }
        crate::vector::l2_normalise(row);
        Ok(scale)
    }
}

/// Each point's descriptor (`dim` f32) at its place in a scratch file in the output's
/// folder: closed points arrive in the order their tracks end and are written in runs of
/// consecutive points; read back in point order.
pub(crate) struct Spill {
    file: File,
    output: PathBuf,
    dim: usize,
    points: usize,
    /// Rows waiting, with their points.
    waiting: Vec<(u32, usize)>,
    rows: Vec<f32>,
}

impl Spill {
    fn create(output: &Path, points: usize, dim: usize) -> Result<Spill, ConvertError> {
        // Sparse: the disk fills as points close, `points × dim × 4` bytes at most; a full disk
        // is an error naming the scratch file beside the output.
        let file = crate::output::scratch_file(output).map_err(ConvertError::Output)?;
        let spill = Spill {
            file,
            output: output.to_path_buf(),
            dim,
            points,
            waiting: Vec::new(),
            rows: Vec::new(),
        };
        spill
            .file
            .set_len(points as u64 * dim as u64 * 4)
            .map_err(|e| spill.io(e))?;
        Ok(spill)
    }

    fn io(&self, source: std::io::Error) -> ConvertError {
        ConvertError::Output(crate::output::OutputError::scratch(&self.output, source))
    }

    fn row_bytes(&self) -> u64 {
        self.dim as u64 * 4
    }

    fn put(&mut self, point: usize, row: &[f32]) -> Result<(), ConvertError> {
        self.waiting.push((point as u32, self.rows.len()));
        self.rows.extend_from_slice(row);
        // The rows and their (point, place) entries.
        if self.rows.len() * 4 + self.waiting.len() * 16 >= SPILL_BUFFER_BYTES {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), ConvertError> {
        let mut waiting = std::mem::take(&mut self.waiting);
        waiting.sort_unstable_by_key(|w| w.0);
        let mut bytes: Vec<u8> = Vec::new();
        let mut run_start = None;
        for (k, &(point, at)) in waiting.iter().enumerate() {
            if k > 0 && waiting[k - 1].0 + 1 != point {
                self.write_run(run_start.take(), &mut bytes)?;
            }
            run_start.get_or_insert(point);
            bytes.extend_from_slice(bytemuck::cast_slice(&self.rows[at..at + self.dim]));
        }
        self.write_run(run_start, &mut bytes)?;
        self.rows.clear();
        Ok(())
    }

    fn write_run(&self, start: Option<u32>, bytes: &mut Vec<u8>) -> Result<(), ConvertError> {
        if let Some(start) = start {
            write_at(&self.file, bytes, u64::from(start) * self.row_bytes())
                .map_err(|e| self.io(e))?;
        }
        bytes.clear();
        Ok(())
    }

    /// Calls `f(point, row)` for every point `has` holds, in point order.
    pub(crate) fn for_each(
        &self,
        has: &BitVec,
        mut f: impl FnMut(usize, &[f32]) -> Result<(), ConvertError>,
    ) -> Result<(), ConvertError> {
        let dim = self.dim.max(1);
        let block = (SPILL_BUFFER_BYTES / (dim * 4)).max(1);
        let mut values = vec![0.0f32; block * dim];
        let mut start = 0;
        while start < self.points {
            let n = block.min(self.points - start);
            if has[start..start + n].any() {
                let buf: &mut [u8] = bytemuck::cast_slice_mut(&mut values[..n * dim]);
                read_at(&self.file, buf, start as u64 * self.row_bytes())
                    .map_err(|e| self.io(e))?;
                for k in has[start..start + n].iter_ones() {
                    f(start + k, &values[k * dim..(k + 1) * dim])?;
                }
            }
            start += n;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::features::SourceFeatures;
    use super::*;
    use crate::colmap::DescriptorValues;
    use crate::geometry::rng::SplitMix64;

    const DIM: usize = 6;

    /// A model whose tracks jump between images in no order (most points open at once),
    /// with repeated observations in one image, points seen by no image or only by the image
    /// without features, and a last image that has none.
    fn scene() -> (Geometry, Vec<Option<SourceFeatures>>) {
        let (points, images) = (300, 23);
        let mut rng = SplitMix64::new(35);
        let mut per_image: Vec<Vec<u32>> = vec![Vec::new(); images];
        for p in 0..points - 10 {
            let track = 1 + rng.next_u64() as usize % 6;
            for _ in 0..track {
                per_image[rng.next_u64() as usize % images].push(p as u32);
            }
        }
        per_image[4].push(points as u32 - 3); // only in the image without features
        let mut g = Geometry {
            cameras: Vec::new(),
            positions: vec![[0.0; 3]; points],
            colors: vec![[0; 3]; points],
            ids: (0..points as u64).collect(),
            names: (0..images).map(|i| format!("{i}.jpg")).collect(),
            image_cameras: vec![0; images],
            poses: vec![[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]; images],
            image_ids: (1..=images as u32).collect(),
            vis_offsets: vec![0],
            vis_points: Vec::new(),
            vis_keypoints: Vec::new(),
            vis_point2d: Vec::new(),
        };
        let mut features = Vec::new();
        for (i, seen) in per_image.iter().enumerate() {
            let keypoints = seen.len() + 2;
            for (k, &p) in seen.iter().enumerate() {
                g.vis_points.push(p);
                g.vis_keypoints.push([0.0; 2]);
                g.vis_point2d.push(k as u32 + 1);
            }
            g.vis_offsets.push(g.vis_points.len() as u64);
            let values = (0..keypoints * DIM)
                .map(|_| rng.next_f64() as f32 - 0.3)
                .collect();
            let scales = (0..keypoints)
                .map(|_| 1.0 + rng.next_f64() as f32)
                .collect();
            features.push(((i != 4) && (i != images - 1)).then_some(SourceFeatures {
                keypoints,
                scales: Some(scales),
                dim: DIM,
                values: DescriptorValues::F32(values),
            }));
        }
        (g, features)
    }

    struct Fake(Vec<Option<SourceFeatures>>, PathBuf);

    impl FeatureSource for Fake {
        fn path(&self) -> &Path {
            &self.1
        }
        fn kind(&self) -> &'static str {
            "test"
        }
        fn feature_name(&self) -> Option<String> {
            None
        }
        fn image(&mut self, image: ModelImage<'_>) -> Result<Option<SourceFeatures>, ConvertError> {
            Ok(self.0[image.id as usize - 1].clone())
        }
    }

    /// The whole map at once, as `convert` made it before it streamed: every observation's
    /// normalised row in image order, then each point's mean (or medoid) and median scale.
    fn whole_map(
        g: &Geometry,
        f: &[Option<SourceFeatures>],
        how: Aggregate,
    ) -> Vec<(usize, Vec<f32>, f32)> {
        let mut obs: Vec<Vec<(Vec<f32>, f32)>> = vec![Vec::new(); g.positions.len()];
        for (i, features) in f.iter().enumerate() {
            let Some(features) = features else { continue };
            for k in g.vis_offsets[i] as usize..g.vis_offsets[i + 1] as usize {
                let mut row = Vec::new();
                assert!(features
                    .values
                    .row_into(DIM, g.vis_point2d[k] as usize, &mut row));
                crate::vector::l2_normalise(&mut row);
                let scale = features.scales.as_ref().unwrap()[g.vis_point2d[k] as usize];
                obs[g.vis_points[k] as usize].push((row, scale));
            }
        }
        let mut out = Vec::new();
        for (p, o) in obs.iter().enumerate().filter(|(_, o)| !o.is_empty()) {
            let row = match how {
                Aggregate::Mean => {
                    let mut sum = vec![0.0f32; DIM];
                    for (r, _) in o {
                        sum.iter_mut().zip(r).for_each(|(s, v)| *s += v);
                    }
                    crate::vector::l2_normalise(&mut sum);
                    sum
                }
                Aggregate::Medoid => {
                    let score = |k: usize| -> f32 {
                        o.iter().map(|(r, _)| crate::vector::dot(&o[k].0, r)).sum()
                    };
                    let best = (0..o.len())
                        .max_by(|&i, &j| score(i).total_cmp(&score(j)).then(j.cmp(&i)))
                        .unwrap();
                    o[best].0.clone()
                }
            };
            let mut scales: Vec<f32> = o.iter().map(|x| x.1).collect();
            scales.sort_by(f32::total_cmp);
            out.push((p, row, scales[scales.len() / 2]));
        }
        out
    }

    #[test]
    fn streamed_descriptors_are_the_whole_map_aggregation_whatever_the_passes() {
        let (g, features) = scene();
        let dir = tempfile::tempdir().unwrap();
        let output = dir.path().join("map.sfpm");
        for how in [Aggregate::Mean, Aggregate::Medoid] {
            let expected = whole_map(&g, &features, how);
            assert!(expected.len() > 250, "{}", expected.len());
            let options = ConvertOptions {
                aggregate: how,
                memory: Some(u64::MAX),
                ..Default::default()
            };
            for passes in [1, 3, 7, 300] {
                let mut source = Fake(features.clone(), dir.path().join("db"));
                let prepared = prepare(&g, &mut source, &options, 0, Path::new("model")).unwrap();
                assert_eq!(prepared.memory.passes, 1);
                let prepared = prepared.with_passes(passes);
                let agg = aggregate(
                    &g,
                    &mut source,
                    &options,
                    prepared,
                    &output,
                    &crate::progress::Silent,
                )
                .unwrap();
                assert_eq!(agg.images_without_features, 2);
                assert_eq!(agg.has.count_ones(), expected.len(), "{how:?} {passes}");
                let mut got = Vec::new();
                agg.spill
                    .for_each(&agg.has, |p, row| {
                        got.push((p, row.to_vec(), agg.median[p]));
                        Ok(())
                    })
                    .unwrap();
                let bits = |v: &[(usize, Vec<f32>, f32)]| -> Vec<(usize, Vec<u32>, u32)> {
                    v.iter()
                        .map(|(p, r, m)| (*p, r.iter().map(|x| x.to_bits()).collect(), m.to_bits()))
                        .collect()
                };
                assert_eq!(bits(&got), bits(&expected), "{how:?} in {passes} passes");
                assert!(agg.median[g.positions.len() - 3].is_nan());
            }
        }
        // Nothing is left in the output's folder: the scratch files have no name.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn each_point_is_in_one_non_empty_range_and_its_bounds_hold_it() {
        for points in [1, 5, 100, 301] {
            for ranges in (1..=points.min(64)).chain([points]) {
                let bounds: Vec<_> = (0..ranges)
                    .map(|r| range_bounds(r, points, ranges))
                    .collect();
                assert!(bounds.iter().all(|b| !b.is_empty()), "{points} in {ranges}");
                assert_eq!(bounds.iter().map(|b| b.len()).sum::<usize>(), points);
                for p in 0..points {
                    assert!(
                        bounds[range_of(p, points, ranges)].contains(&p),
                        "{p} of {points}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_tightest_cgroup_limit_up_the_tree_bounds_the_default_budget() {
        fn files(
            files: &'static [(&'static str, &'static str)],
        ) -> impl Fn(&str) -> Option<String> {
            move |path: &str| files.iter().find(|f| f.0 == path).map(|f| f.1.to_string())
        }
        // v2: a job's own cgroup and its parent; the root says `max`.
        let v2 = files(&[
            ("/sys/fs/cgroup/memory.max", "max\n"),
            ("/sys/fs/cgroup/slurm/memory.max", "8000000000\n"),
            ("/sys/fs/cgroup/slurm/job_7/memory.max", "2000000000\n"),
        ]);
        assert_eq!(cgroup_limit("0::/slurm/job_7\n", &v2), Some(2_000_000_000));
        assert_eq!(cgroup_limit("0::/slurm\n", &v2), Some(8_000_000_000));
        assert_eq!(cgroup_limit("0::/\n", &v2), None);
        // v1: the memory controller's line; its "no limit" value is none.
        let v1 = files(&[
            (
                "/sys/fs/cgroup/memory/memory.limit_in_bytes",
                "9223372036854771712",
            ),
            (
                "/sys/fs/cgroup/memory/docker/abc/memory.limit_in_bytes",
                "4294967296",
            ),
        ]);
        let own = "12:cpu,cpuacct:/docker/abc\n4:memory:/docker/abc\n";
        assert_eq!(cgroup_limit(own, &v1), Some(4_294_967_296));
        assert_eq!(cgroup_limit("4:memory:/\n", &v1), None);
        assert_eq!(cgroup_limit("garbage", &v1), None);
    }

    #[test]
    fn a_budget_below_the_smallest_that_works_is_refused_naming_it() {
        let (g, _) = scene();
        let tracks = Tracks::new(&g);
        let fixed = FixedCost {
            before_reads: 500,
            during: 1_000,
            after: 2_000,
        };
        let one = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Mean,
            fixed,
            u64::MAX,
            Path::new("m"),
        )
        .unwrap();
        assert_eq!(one.passes, 1);
        // Just below one read's need: two reads or more, each range's open tracks smaller.
        let unbounded = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Medoid,
            fixed,
            u64::MAX,
            Path::new("m"),
        )
        .unwrap();
        let tighter = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Medoid,
            fixed,
            unbounded.peak - 1,
            Path::new("m"),
        )
        .unwrap();
        assert!(
            tighter.passes > 1 && tighter.peak < unbounded.peak,
            "{tighter:?}"
        );
        // Below every count's need: the least of them, with its reads; that budget plans.
        let err = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Medoid,
            fixed,
            1_000_000,
            Path::new("m"),
        )
        .unwrap_err();
        let ConvertError::MemoryBudget { needed, passes, .. } = err else {
            panic!("{err}");
        };
        let smallest = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Medoid,
            fixed,
            needed,
            Path::new("m"),
        )
        .unwrap();
        assert_eq!((smallest.passes, smallest.peak), (passes, needed));
        assert!(plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Medoid,
            fixed,
            needed - 1,
            Path::new("m")
        )
        .is_err());
        assert!(
            err.to_string()
                .starts_with("m: a memory budget of 1 MB is too small"),
            "{err}"
        ); // What no number of reads lowers (the retrieval rows after the reads): one read.
        let heavy = FixedCost {
            before_reads: 500,
            during: 1_000,
            after: 1 << 40,
        };
        let err = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Medoid,
            heavy,
            1 << 39,
            Path::new("m"),
        )
        .unwrap_err();
        let ConvertError::MemoryBudget { needed, passes, .. } = err else {
            panic!("{err}");
        };
        assert_eq!((needed, passes), (BASELINE_BYTES + (1 << 40), 1));
        // (1.4) What is held before the reads (the neighbours' search) bounds the plan too.
        let searching = FixedCost {
            before_reads: 1 << 41,
            ..fixed
        };
        let err = plan(
            &tracks,
            &g,
            DIM,
            Aggregate::Mean,
            searching,
            1 << 40,
            Path::new("m"),
        )
        .unwrap_err();
        let ConvertError::MemoryBudget { needed, .. } = err else {
            panic!("{err}");
        };
        assert_eq!(needed, BASELINE_BYTES + (1 << 41));
    }
}
