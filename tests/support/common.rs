//! Test fixtures shared by the format tests: a small synthetic scene the tests generate
//! themselves, its expected decoded JSON, and a patcher for hand-made corrupt bytes.
#![allow(dead_code)]

use serde_json::{json, Value};
use sfpmap::format::{f16, CameraInfo, Codec, Descriptors, LevelInfo, Map, MapWriter, SectionKind};
use sfpmap::fuzzing::{checksum, Header, RawEntry, ENTRY_LEN, HEADER_LEN};
use std::borrow::Cow;

/// Deterministic pseudo-random numbers (SplitMix64), so fixtures are the same everywhere.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [-1, 1).
    pub fn unit(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 23) as f32 - 1.0
    }
}

pub struct LevelData {
    pub info: LevelInfo,
    pub points: Vec<u32>,
    /// `[points × dim_full]`, L2-normalised rows.
    pub descriptors: Vec<f32>,
    pub projection: Option<(usize, Vec<f32>)>,
}

/// Everything a map can hold, owned, so a writer can borrow it.
pub struct Scene {
    pub positions: Vec<[f64; 3]>,
    pub colors: Vec<[u8; 3]>,
    pub ids: Vec<u64>,
    pub cameras: Vec<CameraInfo>,
    pub image_names: Vec<String>,
    pub image_cameras: Vec<u32>,
    pub image_poses: Vec<[f64; 7]>,
    pub image_ids: Vec<u32>,
    pub global: Option<(usize, Vec<f32>)>,
    pub vis_offsets: Vec<u64>,
    pub vis_points: Vec<u32>,
    pub vis_keypoints: Vec<[f32; 2]>,
    pub levels: Vec<LevelData>,
    pub with_rest: bool,
}

pub fn level_info(level: u16, stride: f64, dim_full: u32, dim_short: u32) -> LevelInfo {
    LevelInfo {
        level,
        stride,
        descriptor: "sfp-v1".into(),
        dim_full,
        dim_short,
        normalization: "l2".into(),
        extra: Default::default(),
    }
}

impl Scene {
    /// `n_points` points, `n_images` images, the given levels as (id, stride, full, short);
    /// each level holds a pseudo-random subset of the points.
    pub fn new(
        seed: u64,
        n_points: usize,
        n_images: usize,
        levels: &[(u16, f64, u32, u32)],
    ) -> Scene {
        let mut rng = Rng(seed);
        let positions: Vec<[f64; 3]> = (0..n_points)
            .map(|_| {
                [
                    f64::from(rng.unit()) * 50.0 + 1000.0,
                    f64::from(rng.unit()) * 5.0,
                    f64::from(rng.unit()) * 20.0,
                ]
            })
            .collect();
        let colors = (0..n_points)
            .map(|i| [i as u8, (i * 7) as u8, (i * 13) as u8])
            .collect();
        let ids = (0..n_points as u64).map(|i| i * 3 + 1).collect();
        let cameras = vec![CameraInfo {
            id: Some(1),
            model: "SIMPLE_RADIAL".into(),
            width: 640,
            height: 480,
            params: vec![500.0, 320.0, 240.0, 0.01],
        }];
        let image_names = (0..n_images).map(|i| format!("img_{i:03}.jpg")).collect();
        let image_cameras = vec![0; n_images];
        let image_poses = (0..n_images)
            .map(|i| [1.0, 0.0, 0.0, 0.0, i as f64, -(i as f64) * 0.5, 2.0])
            .collect();
        let image_ids = (0..n_images as u32).map(|i| i + 1).collect();
        let mut vis_offsets = vec![0u64];
        let mut vis_points = Vec::new();
        let mut vis_keypoints = Vec::new();
        for _ in 0..n_images {
            for p in 0..n_points as u32 {
                if rng.next_u64() % 3 == 0 {
                    vis_points.push(p);
                    vis_keypoints.push([rng.unit() * 300.0 + 320.0, rng.unit() * 200.0 + 240.0]);
                }
            }
            vis_offsets.push(vis_points.len() as u64);
        }
        let levels = levels
            .iter()
            .map(|&(level, stride, full, short)| {
                let points: Vec<u32> = (0..n_points as u32)
                    .filter(|_| rng.next_u64() % 2 == 0)
                    .collect();
                let mut descriptors = Vec::with_capacity(points.len() * full as usize);
                for _ in &points {
                    let row: Vec<f32> = (0..full).map(|_| rng.unit()).collect();
                    let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-6);
                    descriptors.extend(row.iter().map(|v| v / norm));
                }
                let projection = (0..full as usize * full as usize)
                    .map(|i| {
                        if i % (full as usize + 1) == 0 {
                            1.0
                        } else {
                            0.0
                        }
                    })
                    .collect();
                LevelData {
                    info: level_info(level, stride, full, short),
                    points,
                    descriptors,
                    projection: Some((full as usize, projection)),
                }
            })
            .collect();
        Scene {
            positions,
            colors,
            ids,
            cameras,
            image_names,
            image_cameras,
            image_poses,
            image_ids,
            global: (n_images > 0).then(|| {
                (
                    4,
                    (0..n_images * 4)
                        .map(|i| if i % 4 == 0 { 1.0 } else { 0.0 })
                        .collect(),
                )
            }),
            vis_offsets,
            vis_points,
            vis_keypoints,
            levels,
            with_rest: true,
        }
    }

    /// The scene cut to one level, as `slice --level L --short` must produce it.
    pub fn sliced(&self, level: u16) -> Scene {
        let l = self.levels.iter().find(|l| l.info.level == level).unwrap();
        let mut remap = vec![u32::MAX; self.positions.len()];
        for (new, &old) in l.points.iter().enumerate() {
            remap[old as usize] = new as u32;
        }
        let mut vis_offsets = vec![0u64];
        let (mut vis_points, mut vis_keypoints) = (Vec::new(), Vec::new());
        for i in 0..self.image_names.len() {
            for e in self.vis_offsets[i] as usize..self.vis_offsets[i + 1] as usize {
                let new = remap[self.vis_points[e] as usize];
                if new != u32::MAX {
                    vis_points.push(new);
                    vis_keypoints.push(self.vis_keypoints[e]);
                }
            }
            vis_offsets.push(vis_points.len() as u64);
        }
        let pick = |i: &u32| *i as usize;
        Scene {
            positions: l.points.iter().map(|i| self.positions[pick(i)]).collect(),
            colors: l.points.iter().map(|i| self.colors[pick(i)]).collect(),
            ids: l.points.iter().map(|i| self.ids[pick(i)]).collect(),
            cameras: self.cameras.clone(),
            image_names: self.image_names.clone(),
            image_cameras: self.image_cameras.clone(),
            image_poses: self.image_poses.clone(),
            image_ids: self.image_ids.clone(),
            global: self.global.clone(),
            vis_offsets,
            vis_points,
            vis_keypoints,
            levels: vec![LevelData {
                info: l.info.clone(),
                points: (0..l.points.len() as u32).collect(),
                descriptors: l.descriptors.clone(),
                projection: l.projection.clone(),
            }],
            with_rest: false,
        }
    }

    pub fn writer(&self, codec: Codec) -> MapWriter<'_> {
        let mut w = MapWriter::default();
        w.set_codec(codec, 3);
        w.metadata_mut().provenance.tool = "sfpmap test fixture".into();
        for c in &self.cameras {
            w.add_camera(c.clone());
        }
        w.set_points_world(&self.positions);
        w.set_point_colors(&self.colors);
        w.set_point_ids(&self.ids);
        if !self.image_names.is_empty() {
            w.set_images(
                &self.image_names,
                &self.image_cameras,
                &self.image_poses,
                Some(&self.image_ids),
            )
            .unwrap();
            w.set_visibility(
                &self.vis_offsets,
                &self.vis_points,
                Some(&self.vis_keypoints),
            )
            .unwrap();
        }
        if let Some((dim, g)) = &self.global {
            w.set_image_global(*dim, g).unwrap();
        }
        for l in &self.levels {
            w.add_level(
                l.info.clone(),
                &l.points,
                Some(Descriptors::F32(&l.descriptors)),
                self.with_rest,
            )
            .unwrap();
            if let Some((d_in, p)) = &l.projection {
                w.set_level_projection(l.info.level, *d_in, p.clone())
                    .unwrap();
            }
        }
        w
    }

    /// The decoded content a reader must find, computed from the inputs (f16 rounding
    /// applied), in the schema of `decoded_json`.
    pub fn expected_json(&self, origin: [f64; 3]) -> Value {
        let rel =
            |p: &[f64; 3]| -> Vec<f32> { (0..3).map(|k| (p[k] - origin[k]) as f32).collect() };
        let round = |v: &f32| f16::from_f32(*v).to_f32();
        json!({
            "points": self.positions.len(),
            "positions": self.positions.iter().map(rel).collect::<Vec<_>>(),
            "colors": self.colors,
            "point_ids": self.ids,
            "cameras": self.cameras.len(),
            "images": self.image_names.iter().enumerate().map(|(i, n)| json!({
                "name": n, "camera": self.image_cameras[i], "cam_from_world": self.image_poses[i], "id": self.image_ids[i],
            })).collect::<Vec<_>>(),
            "visibility": if self.image_names.is_empty() { Value::Null } else { json!({ "offsets": self.vis_offsets, "points": self.vis_points }) },
            "levels": self.levels.iter().map(|l| {
                let (full, short) = (l.info.dim_full as usize, l.info.dim_short as usize);
                let rows: Vec<&[f32]> = l.descriptors.chunks(full.max(1)).collect();
                json!({
                    "level": l.info.level,
                    "points": l.points,
                    "dim_full": full,
                    "dim_short": short,
                    "has_rest": self.with_rest,
                    "short": rows.iter().map(|r| r[..short].iter().map(round).collect::<Vec<_>>()).collect::<Vec<_>>(),
                    "rest": if self.with_rest { json!(rows.iter().map(|r| r[short..].iter().map(round).collect::<Vec<_>>()).collect::<Vec<_>>()) } else { Value::Null },
                })
            }).collect::<Vec<_>>(),
        })
    }
}

/// A map's VLAD retrieval data (format 1.1) as a writer is given it.
#[derive(Debug, Clone)]
pub struct VladData {
    pub level: u16,
    pub dims: usize,
    /// `[clusters × dims]`.
    pub centroids: Vec<f32>,
    /// `[images × clusters·dims]`, before the f16 rounding of the file.
    pub images: Vec<f32>,
}

impl VladData {
    pub fn clusters(&self) -> usize {
        self.centroids.len() / self.dims
    }

    /// The `vlad` object of the vectors' content (f16 rounding applied).
    pub fn expected_json(&self) -> Value {
        let width = self.centroids.len();
        let round = |v: &f32| f16::from_f32(*v).to_f32();
        json!({
            "level": self.level,
            "clusters": self.clusters(),
            "dims": self.dims,
            "centroids": self.centroids.chunks(self.dims).collect::<Vec<_>>(),
            "images": self.images.chunks(width).map(|r| r.iter().map(round).collect::<Vec<_>>()).collect::<Vec<_>>(),
        })
    }
}

/// L2 normalisation that leaves a zero vector zero.
fn unit(v: &mut [f32]) {
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if norm > 0.0 {
        v.iter_mut().for_each(|x| *x /= norm);
    }
}

/// The VLAD of `rows` (`[n × dims]`, already cut to `dims` and unit) over `centroids`, as
/// spec/format.md states it and independently of `sfpmap::vlad`: each row's residual to its
/// nearest centroid (Euclidean; ties to the lower index) summed per centroid, each centroid's
/// block L2-normalised, then the whole vector.
pub fn reference_vlad(rows: &[&[f32]], centroids: &[f32], dims: usize) -> Vec<f32> {
    let mut sum = vec![0.0f32; centroids.len()];
    for x in rows {
        let distance = |c: &[f32]| -> f32 { x.iter().zip(c).map(|(a, b)| (a - b) * (a - b)).sum() };
        let nearest = centroids
            .chunks(dims)
            .enumerate()
            .min_by(|a, b| distance(a.1).total_cmp(&distance(b.1)).then(a.0.cmp(&b.0)))
            .unwrap()
            .0;
        let block = &mut sum[nearest * dims..(nearest + 1) * dims];
        for ((s, v), c) in block
            .iter_mut()
            .zip(x.iter())
            .zip(&centroids[nearest * dims..])
        {
            *s += v - c;
        }
    }
    sum.chunks_mut(dims).for_each(unit);
    unit(&mut sum);
    sum
}

impl Scene {
    /// The first `dims` dimensions of `level`'s descriptor of each map point, L2-normalised;
    /// `None` for points the level does not hold.
    pub fn vlad_rows(&self, level: u16, dims: usize) -> Vec<Option<Vec<f32>>> {
        let l = self.levels.iter().find(|l| l.info.level == level).unwrap();
        let full = l.info.dim_full as usize;
        let mut rows = vec![None; self.positions.len()];
        for (&p, d) in l.points.iter().zip(l.descriptors.chunks(full)) {
            let mut row = d[..dims].to_vec();
            unit(&mut row);
            rows[p as usize] = Some(row);
        }
        rows
    }

    /// VLAD retrieval over `level` with `centroids` (`[clusters × dims]`): each image's VLAD
    /// over the level's points it sees, by [`reference_vlad`].
    pub fn vlad(&self, level: u16, dims: usize, centroids: Vec<f32>) -> VladData {
        let rows = self.vlad_rows(level, dims);
        let mut images = Vec::new();
        for i in 0..self.image_names.len() {
            let seen: Vec<&[f32]> = self.vis_points
                [self.vis_offsets[i] as usize..self.vis_offsets[i + 1] as usize]
                .iter()
                .filter_map(|&p| rows[p as usize].as_deref())
                .collect();
            images.extend(reference_vlad(&seen, &centroids, dims));
        }
        VladData {
            level,
            dims,
            centroids,
            images,
        }
    }

    /// [`Scene::writer`] plus `vlad` (which also sets `metadata.retrieval` to `"vlad"`).
    pub fn writer_with_vlad(&self, codec: Codec, vlad: &VladData) -> MapWriter<'_> {
        let mut w = self.writer(codec);
        w.set_vlad(vlad.level, vlad.dims, vlad.centroids.clone(), &vlad.images)
            .unwrap();
        w
    }
}

/// What a reader decodes from a map, in the schema of the vectors' `.json` files. The 1.1
/// keys `retrieval` and `vlad`, and 1.3's `image_index`, are there only when the map has
/// them, so 1.0 maps decode as before.
pub fn decoded_json(map: &Map<'_>) -> Value {
    let images = map.images().unwrap();
    let levels: Vec<Value> = map
        .levels()
        .map(|l| {
            if let Some(pq) = l.pq().unwrap() {
                let mut level = json!({
                    "level": l.id(),
                    "points": *l.points().unwrap(),
                    "dim_full": l.dim_full(),
                    "dim_short": l.dim_short(),
                    "has_rest": false,
                    "short": null,
                    "rest": null,
                    "pq": {
                        "subspaces": pq.subspaces,
                        "centroids": pq.centroids,
                        "sub_dims": pq.sub_dims,
                        "codebook": pq.codebook.chunks(pq.sub_dims).collect::<Vec<_>>(),
                        "codes": pq.codes.chunks(pq.subspaces).collect::<Vec<_>>(),
                    },
                });
                if let Some(order) = &pq.order {
                    level["pq"]["order"] = json!(order);
                }
                return level;
            }
            let short = l.desc_short().unwrap();
            let rest = l.desc_rest().unwrap();
            let rows = |v: &[f16], d: usize| -> Vec<Vec<f32>> {
                if d == 0 {
                    return vec![vec![]; l.len()];
                }
                v.chunks(d).map(|r| r.iter().map(|x| x.to_f32()).collect()).collect()
            };
            json!({
                "level": l.id(),
                "points": *l.points().unwrap(),
                "dim_full": l.dim_full(),
                "dim_short": l.dim_short(),
                "has_rest": l.has_rest(),
                "short": rows(&short, l.dim_short()),
                "rest": rest.map(|r| json!(rows(&r, l.dim_full() - l.dim_short()))).unwrap_or(Value::Null),
            })
        })
        .collect();
    let vis = map.visibility().unwrap();
    let mut content = json!({
        "points": map.n_points(),
        "positions": *map.point_positions().unwrap(),
        "colors": map.point_colors().unwrap().map(|c| c.to_vec()),
        "point_ids": map.point_ids().unwrap().map(|c| c.to_vec()),
        "cameras": map.metadata().cameras.len(),
        "images": images.as_ref().map_or(vec![], |im| (0..im.len()).map(|i| json!({
            "name": im.name(i).unwrap(), "camera": im.cameras[i], "cam_from_world": im.poses[i],
            "id": im.ids.as_ref().map(|ids| ids[i]),
        })).collect::<Vec<_>>()),
        "visibility": vis.map(|v| json!({ "offsets": *v.offsets, "points": *v.points })),
        "levels": levels,
    });
    if let Some(retrieval) = &map.metadata().retrieval {
        content["retrieval"] = json!(retrieval);
    }
    if let Some(v) = map.vlad().unwrap() {
        content["vlad"] = json!({
            "level": v.level,
            "clusters": v.clusters,
            "dims": v.dims,
            "centroids": v.centroids.chunks(v.dims).collect::<Vec<_>>(),
            "images": v.images.chunks(v.clusters * v.dims).map(|r| r.iter().map(|x| x.to_f32()).collect::<Vec<_>>()).collect::<Vec<_>>(),
        });
    }
    if let Some(i) = map.image_index().unwrap() {
        content["image_index"] = json!({
            "of": i.of.name(),
            "probe": i.probe,
            "centroids": i.centroids.chunks(i.width).collect::<Vec<_>>(),
            "lists": (0..i.lists()).map(|l| i.list(l)).collect::<Vec<_>>(),
        });
        if let Some(n) = &i.neighbours {
            content["image_index"]["neighbours"] = json!((0..map.n_images())
                .map(|r| n.of(r as usize))
                .collect::<Vec<_>>());
        }
    }
    content
}

/// Re-encodes header and table of `bytes` after `edit`, recomputing the index checksum,
/// so a test can make one precise corruption that the checksum does not catch first.
pub fn patch(bytes: &[u8], edit: impl FnOnce(&mut Header, &mut Vec<RawEntry>)) -> Vec<u8> {
    let mut out = bytes.to_vec();
    let original = Header::decode(bytes).unwrap();
    let mut header = original;
    let table_end = HEADER_LEN + original.section_count as usize * ENTRY_LEN;
    let mut entries: Vec<RawEntry> = bytes[HEADER_LEN..table_end]
        .chunks(ENTRY_LEN)
        .map(RawEntry::decode)
        .collect();
    edit(&mut header, &mut entries);
    for (i, e) in entries.iter().enumerate() {
        out[HEADER_LEN + i * ENTRY_LEN..HEADER_LEN + (i + 1) * ENTRY_LEN]
            .copy_from_slice(&e.encode());
    }
    // Over the original table and metadata ranges: edits of counts and lengths are caught
    // before the checksum is compared anyway.
    let meta = &bytes[original.metadata_offset as usize
        ..(original.metadata_offset + original.metadata_len) as usize];
    header.index_checksum =
        concat_checksum(&header.encode()[..56], &out[HEADER_LEN..table_end], meta);
    out[..HEADER_LEN].copy_from_slice(&header.encode());
    out
}

/// The index checksum (XXH3 of header prefix, table, metadata), computed independently of
/// the reader's streaming hasher: the one-shot hash of the concatenation.
fn concat_checksum(prefix: &[u8], table: &[u8], meta: &[u8]) -> u64 {
    let mut all = Vec::with_capacity(prefix.len() + table.len() + meta.len());
    all.extend_from_slice(prefix);
    all.extend_from_slice(table);
    all.extend_from_slice(meta);
    checksum(&all)
}

/// A minimal valid map: two points, nothing else.
pub fn minimal() -> Vec<u8> {
    let positions = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
    let mut w = MapWriter::default();
    w.metadata_mut().provenance.tool = "sfpmap test fixture".into();
    w.set_points_world(&positions);
    w.to_bytes().unwrap()
}

/// A map with an extra section of `kind` added as raw bytes.
pub fn with_extra_section(
    kind: SectionKind,
    level: u16,
    required: bool,
    codec: Option<Codec>,
) -> Vec<u8> {
    let positions = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]];
    let mut w = MapWriter::default();
    w.metadata_mut().provenance.tool = "sfpmap test fixture".into();
    w.set_points_world(&positions);
    let values: Vec<u16> = (0..12).collect();
    w.add_raw_section(
        kind,
        level,
        sfpmap::format::Dtype::U16,
        4,
        3,
        required,
        Cow::Owned(bytemuck::cast_slice(&values).to_vec()),
        codec,
    )
    .unwrap();
    w.to_bytes().unwrap()
}

/// One section for [`craft`]: the table fields and the stored bytes, taken as given (absurd
/// values welcome); `craft` fills in offset, stored length and checksum.
#[derive(Debug, Clone)]
pub struct Crafted {
    pub kind: u16,
    pub level: u16,
    pub dtype: u8,
    pub codec: u8,
    pub flags: u8,
    pub rows: u64,
    pub cols: u64,
    /// The declared decoded length (a raw section's must equal its stored length).
    pub raw_len: u64,
    /// The bytes as stored: compressed for zstd.
    pub stored: Vec<u8>,
}

impl Crafted {
    /// A raw, required section holding `bytes`.
    pub fn raw(
        kind: SectionKind,
        level: u16,
        dtype: sfpmap::format::Dtype,
        rows: u64,
        cols: u64,
        bytes: Vec<u8>,
    ) -> Crafted {
        Crafted {
            kind: kind.code(),
            level,
            dtype: dtype as u8,
            codec: Codec::Raw as u8,
            flags: sfpmap::fuzzing::SECTION_REQUIRED,
            rows,
            cols,
            raw_len: bytes.len() as u64,
            stored: bytes,
        }
    }

    /// A zstd, required section whose frame decodes to `raw` (level 19: small frames).
    pub fn zstd(
        kind: SectionKind,
        level: u16,
        dtype: sfpmap::format::Dtype,
        rows: u64,
        cols: u64,
        raw: &[u8],
    ) -> Crafted {
        Crafted {
            codec: Codec::Zstd as u8,
            raw_len: raw.len() as u64,
            stored: zstd::bulk::compress(raw, 19).unwrap(),
            ..Crafted::raw(kind, level, dtype, rows, cols, Vec::new())
        }
    }

    /// Clears the required flag (for unknown kinds a reader must skip).
    pub fn optional(mut self) -> Crafted {
        self.flags &= !sfpmap::fuzzing::SECTION_REQUIRED;
        self
    }
}

/// Metadata JSON of a map with the given `levels` (see [`craft_level`]); edit the value for more.
pub fn craft_metadata(levels: Vec<Value>) -> Value {
    json!({
        "format": "sfpmap",
        "units": "model",
        "convention": "colmap",
        "origin": [0.0, 0.0, 0.0],
        "levels": levels,
    })
}

/// One entry of the metadata's `levels`.
pub fn craft_level(level: u16, dim_full: u64, dim_short: u64) -> Value {
    json!({
        "level": level,
        "stride": 8.0,
        "descriptor": "sfp-v1",
        "dim_full": dim_full,
        "dim_short": dim_short,
        "normalization": "l2",
    })
}

/// `point_positions` of `n` points, all at the origin.
pub fn craft_points(n: u64) -> Crafted {
    Crafted::raw(
        SectionKind::PointPositions,
        sfpmap::fuzzing::NO_LEVEL,
        sfpmap::format::Dtype::F32,
        n,
        3,
        vec![0; n as usize * 12],
    )
}

/// `level_points` holding the global indices `points`.
pub fn craft_level_points(level: u16, points: &[u32]) -> Crafted {
    Crafted::raw(
        SectionKind::LevelPoints,
        level,
        sfpmap::format::Dtype::U32,
        points.len() as u64,
        1,
        bytemuck::cast_slice(points).to_vec(),
    )
}

/// Lays out a map from `metadata` and `sections` (in table and file order) the way the spec
/// says (header, table, metadata, 64-byte-aligned sections, zero padding) with every checksum
/// correct, so a test reaches the checks behind them. Nothing else is checked or fixed: the
/// metadata and the table fields may contradict each other as much as the test wants.
pub fn craft(metadata: &Value, sections: &[Crafted]) -> Vec<u8> {
    craft_with_metadata_bytes(&serde_json::to_vec(metadata).unwrap(), sections)
}

/// [`craft`] with the metadata block given as bytes (which need not be JSON at all).
pub fn craft_with_metadata_bytes(metadata: &[u8], sections: &[Crafted]) -> Vec<u8> {
    use sfpmap::format::VERSION_MAJOR;
    use sfpmap::fuzzing::align_up;
    let table_end = (HEADER_LEN + sections.len() * ENTRY_LEN) as u64;
    let mut out = vec![0u8; table_end as usize];
    out.extend_from_slice(metadata);
    let mut table = Vec::with_capacity(sections.len() * ENTRY_LEN);
    for s in sections {
        let offset = align_up(out.len() as u64).unwrap();
        out.resize(offset as usize, 0);
        out.extend_from_slice(&s.stored);
        let entry = RawEntry {
            kind: s.kind,
            level: s.level,
            dtype: s.dtype,
            codec: s.codec,
            flags: s.flags,
            reserved: 0,
            rows: s.rows,
            cols: s.cols,
            offset,
            stored_len: s.stored.len() as u64,
            raw_len: s.raw_len,
            checksum: checksum(&s.stored),
            reserved2: 0,
        };
        table.extend_from_slice(&entry.encode());
    }
    let mut header = Header {
        major: VERSION_MAJOR,
        minor: 0,
        flags: 0,
        section_count: sections.len() as u32,
        entry_len: ENTRY_LEN as u32,
        metadata_offset: table_end,
        metadata_len: metadata.len() as u64,
        file_len: out.len() as u64,
        index_checksum: 0,
    };
    header.index_checksum = concat_checksum(&header.encode()[..56], &table, metadata);
    out[..HEADER_LEN].copy_from_slice(&header.encode());
    out[HEADER_LEN..table_end as usize].copy_from_slice(&table);
    out
}

/// How a child run by [`run_limited`] ended.
#[derive(Debug)]
pub struct Limited {
    /// `None` when it was killed (signal, or past the time limit).
    pub code: Option<i32>,
    pub timed_out: bool,
    pub stdout: String,
    pub stderr: String,
    pub seconds: f64,
}

/// Runs `program args` with its address space capped at `max_bytes` (`ulimit -v`, so a
/// regression to a huge allocation fails instead of swapping) and killed after `timeout`.
/// Pass `env!("CARGO_BIN_EXE_sfpmap")` as `program` for the CLI.
pub fn run_limited(
    program: impl AsRef<std::ffi::OsStr>,
    args: &[&std::ffi::OsStr],
    max_bytes: u64,
    timeout: std::time::Duration,
) -> Limited {
    use std::io::Read;
    use std::process::{Command, Stdio};
    let start = std::time::Instant::now();
    let mut child = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {} && exec \"$@\"", max_bytes / 1024))
        .arg("sh")
        .arg(program.as_ref())
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Drain the pipes on threads so a chatty child cannot block on a full pipe.
    let drain = |mut pipe: Box<dyn Read + Send>| {
        std::thread::spawn(move || {
            let mut s = Vec::new();
            let _ = pipe.read_to_end(&mut s);
            String::from_utf8_lossy(&s).into_owned()
        })
    };
    let out = drain(Box::new(child.stdout.take().unwrap()));
    let err = drain(Box::new(child.stderr.take().unwrap()));
    let mut timed_out = false;
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > timeout {
            timed_out = true;
            let _ = child.kill();
            break child.wait().unwrap();
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    };
    Limited {
        code: status.code(),
        timed_out,
        stdout: out.join().unwrap(),
        stderr: err.join().unwrap(),
        seconds: start.elapsed().as_secs_f64(),
    }
}

/// The four tables of a COLMAP `database.db` that sfpmap reads (the current schema's columns),
/// without rows.
#[cfg(feature = "colmap")]
pub fn colmap_schema(conn: &rusqlite::Connection) {
    conn.execute_batch(
        "CREATE TABLE cameras (camera_id INTEGER PRIMARY KEY, model INTEGER, width INTEGER, \
           height INTEGER, params BLOB, prior_focal_length INTEGER);
         CREATE TABLE images (image_id INTEGER PRIMARY KEY, name TEXT, camera_id INTEGER);
         CREATE TABLE keypoints (image_id INTEGER PRIMARY KEY, rows INTEGER, cols INTEGER, data BLOB);
         CREATE TABLE descriptors (image_id INTEGER PRIMARY KEY, rows INTEGER, cols INTEGER, data BLOB);",
    )
    .unwrap();
}

/// An SFP-like map the built-in sfp-v1's queries fit, built in a moment: 500 random points at
/// depth 10, level 2 (stride 8) of sfp-v1 with 192 full dimensions of which 64 short, random
/// descriptors (so nothing localizes), plus a level with no points for each of `empty_levels`
/// (id, stride).
pub fn sfp_level_2_map(empty_levels: &[(u16, f64)]) -> Vec<u8> {
    let (n, full) = (500, 192);
    let mut rng = Rng(3);
    let positions: Vec<[f64; 3]> = (0..n)
        .map(|_| {
            let x = f64::from(rng.unit()) * 5.0;
            [x, f64::from(rng.unit()) * 4.0, 10.0]
        })
        .collect();
    let descriptors: Vec<f32> = (0..n * full).map(|_| rng.unit()).collect();
    let points: Vec<u32> = (0..n as u32).collect();
    let mut w = MapWriter::default();
    w.set_points_world(&positions);
    w.add_level(
        level_info(2, 8.0, full as u32, 64),
        &points,
        Some(Descriptors::F32(&descriptors)),
        true,
    )
    .unwrap();
    for &(level, stride) in empty_levels {
        w.add_level(
            level_info(level, stride, full as u32, 64),
            &[],
            Some(Descriptors::F32(&[])),
            true,
        )
        .unwrap();
    }
    w.to_bytes().unwrap()
}

/// CDR as ROS 2 writes it: little-endian, aligned relative to the byte after the 4-byte
/// encapsulation header.
pub struct Cdr(pub Vec<u8>);

impl Cdr {
    pub fn new() -> Cdr {
        Cdr(vec![0, 1, 0, 0])
    }
    pub fn align(&mut self, n: usize) {
        while (self.0.len() - 4) % n != 0 {
            self.0.push(0);
        }
    }
    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.align(4);
        self.0.extend(v.to_le_bytes());
        self
    }
    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.align(8);
        self.0.extend(v.to_le_bytes());
        self
    }
    pub fn u8(&mut self, v: u8) -> &mut Self {
        self.0.push(v);
        self
    }
    pub fn string(&mut self, s: &str) -> &mut Self {
        self.u32(s.len() as u32 + 1);
        self.0.extend(s.as_bytes());
        self.0.push(0);
        self
    }
    pub fn bytes(&mut self, b: &[u8]) -> &mut Self {
        self.u32(b.len() as u32);
        self.0.extend(b);
        self
    }
    pub fn header(&mut self, stamp: (i32, u32), frame_id: &str) -> &mut Self {
        self.u32(stamp.0 as u32).u32(stamp.1).string(frame_id)
    }
}

/// A ROS 2 `sensor_msgs/msg/CompressedImage` as CDR: header (stamp `(sec, nanosec)`,
/// `frame_id`), `format` (e.g. "jpeg"), then the encoded image.
pub fn compressed_image(stamp: (i32, u32), frame_id: &str, format: &str, data: &[u8]) -> Vec<u8> {
    let mut c = Cdr::new();
    c.header(stamp, frame_id).string(format).bytes(data);
    c.0
}
