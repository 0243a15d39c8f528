//! The conformance vectors in `spec/vectors/`: generated here (run with
//! `SFPMAP_REGEN_VECTORS=1` to rewrite them), and every committed vector checked against
//! its `.json`. The generator also proves the writer is deterministic: regenerating must
//! reproduce the committed bytes exactly.

use crate::common;

use common::{
    craft, craft_metadata, craft_points, decoded_json, minimal, patch, with_extra_section, Crafted,
    Scene, VladData,
};
use serde_json::{json, Value};
use sfpmap::format::{f16, slice, Codec, Dtype, Map, MapWriter, SectionKind, SliceOptions};
use sfpmap::fuzzing::{
    checksum, Header, RawEntry, ENTRY_LEN, HEADER_LEN, NO_LEVEL, SECTION_REQUIRED,
};
use std::borrow::Cow;
use std::path::{Path, PathBuf};

fn vectors_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("spec/vectors")
}

fn scene() -> Scene {
    Scene::new(
        7,
        24,
        3,
        &[(0, 16.0, 16, 4), (1, 8.0, 8, 4), (2, 4.0, 8, 2)],
    )
}

/// VLAD retrieval (format 1.1) on the scene's level 2 (`dim_short` 2): 2 centroids of 2
/// dimensions, so each image's VLAD has 4 values.
fn scene_vlad(s: &Scene) -> VladData {
    s.vlad(2, 2, vec![0.6, 0.8, -0.8, 0.6])
}

/// The image index of the `image_index` vector: 2 lists over the VLAD's 4 values.
const INDEX_CENTROIDS: [f32; 8] = [0.5, 0.5, 0.5, 0.5, -0.5, 0.5, -0.5, 0.5];

/// The `image_index_neighbours` vector's rows (1.4): 2 an image, image 1 listing one.
const NEIGHBOURS: [u32; 6] = [2, 1, 0, u32::MAX, 1, 0];

/// The vlad vector's map plus an image index (1.3): images 0 and 2 in list 0, 1 in list 1.
fn scene_indexed<'s>(s: &'s Scene, vlad: &VladData) -> MapWriter<'s> {
    let mut w = s.writer_with_vlad(Codec::Raw, vlad);
    let info = sfpmap::format::ImageIndexInfo {
        of: "vlad".into(),
        probe: 1,
        extra: Default::default(),
    };
    w.set_image_index(info, INDEX_CENTROIDS.to_vec(), 4, &[0, 1, 0])
        .unwrap();
    w
}

fn valid_expected(description: &str, bytes: &[u8], content: Value, unknown: Value) -> Value {
    valid_expected_version("1.0", description, bytes, content, unknown)
}

fn valid_expected_version(
    version: &str,
    description: &str,
    bytes: &[u8],
    content: Value,
    unknown: Value,
) -> Value {
    json!({
        "description": description,
        "version": version,
        "file_bytes": bytes.len(),
        "reader_1_0": if opens_under_1_0_rules(bytes) { "opens" } else { "refuses" },
        "content": content,
        "skipped_sections": unknown,
    })
}

/// Whether a reader of 1.0's rules, which refuses unknown dtype, codec and flag codes in any
/// entry and required sections of kinds 1.0 does not define, gets past the table of `bytes`.
fn opens_under_1_0_rules(bytes: &[u8]) -> bool {
    let header = Header::decode(bytes).unwrap();
    let table = &bytes[HEADER_LEN..header.metadata_offset as usize];
    table
        .chunks(header.entry_len as usize)
        .map(|e| RawEntry::decode(&e[..ENTRY_LEN]))
        .all(|e| {
            let kind = SectionKind::from_code(e.kind);
            let known_in_1_0 = kind.expected_layout().is_some() && kind.since_minor() == 0;
            Dtype::from_code(e.dtype).is_some()
                && Codec::from_code(e.codec).is_some()
                && e.flags & !SECTION_REQUIRED == 0
                && (e.flags & SECTION_REQUIRED == 0 || known_in_1_0)
        })
}

fn origin_of(bytes: &[u8]) -> [f64; 3] {
    Map::from_bytes(bytes).unwrap().metadata().origin
}

/// (name, bytes, expected json) of every valid vector.
fn valid_vectors() -> Vec<(&'static str, Vec<u8>, Value)> {
    let mut out = Vec::new();

    let min = minimal();
    let content = json!({
        "points": 2, "positions": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], "colors": null, "point_ids": null,
        "cameras": 0, "images": [], "visibility": null, "levels": [],
    });
    out.push((
        "minimal",
        min.clone(),
        valid_expected("two points, no images, no levels", &min, content, json!([])),
    ));

    let s = scene();
    let levels = s.writer(Codec::Raw).to_bytes().unwrap();
    let content = s.expected_json(origin_of(&levels));
    out.push((
        "levels",
        levels.clone(),
        valid_expected(
            "3 levels with short+rest descriptors, projections, images, visibility",
            &levels,
            content,
            json!([]),
        ),
    ));

    let map = Map::from_bytes(&levels).unwrap();
    let options = SliceOptions {
        levels: vec![2],
        short: true,
        codec: None,
        zstd_level: 3,
        minimal: false,
    };
    let short = slice(&map, &options).unwrap().0.to_bytes().unwrap();
    let content = s.sliced(2).expected_json(origin_of(&levels));
    out.push((
        "short_only",
        short.clone(),
        valid_expected(
            "the levels vector sliced to level 2, short",
            &short,
            content,
            json!([]),
        ),
    ));

    // 1.1: the same slice with --minimal: positions on a 16-bit grid, no colours, ids or
    // keypoints, each image's visibility sorted.
    let minimal = slice(
        &map,
        &SliceOptions {
            minimal: true,
            ..options.clone()
        },
    )
    .unwrap()
    .0
    .to_bytes()
    .unwrap();
    let mut content = s.sliced(2).expected_json(origin_of(&levels));
    content["positions"] = json!(on_grid(&content["positions"]));
    content["colors"] = Value::Null;
    content["point_ids"] = Value::Null;
    let offsets: Vec<usize> =
        serde_json::from_value(content["visibility"]["offsets"].clone()).unwrap();
    let mut points: Vec<u32> =
        serde_json::from_value(content["visibility"]["points"].clone()).unwrap();
    for w in offsets.windows(2) {
        points[w[0]..w[1]].sort_unstable();
    }
    content["visibility"]["points"] = json!(points);
    out.push((
        "minimal_slice",
        minimal.clone(),
        valid_expected_version(
            "1.1",
            "the levels vector sliced to level 2, short, minimal: point_positions_q16",
            &minimal,
            content,
            json!([]),
        ),
    ));

    let zstd = s.writer(Codec::Zstd).to_bytes().unwrap();
    let content = s.expected_json(origin_of(&zstd));
    out.push((
        "zstd",
        zstd.clone(),
        valid_expected(
            "the levels vector with every section zstd",
            &zstd,
            content,
            json!([]),
        ),
    ));

    let unknown = with_extra_section(
        SectionKind::Unknown(0x7F01),
        NO_LEVEL,
        false,
        Some(Codec::Raw),
    );
    let content = json!({
        "points": 2, "positions": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], "colors": null, "point_ids": null,
        "cameras": 0, "images": [], "visibility": null, "levels": [],
    });
    let listed = json!([{ "kind_code": 0x7F01, "skipped": "unknown kind", "dtype": "u16", "rows": 4, "cols": 3 }]);
    out.push((
        "unknown_optional",
        unknown.clone(),
        valid_expected(
            "minimal plus an optional section of an unknown kind (skipped)",
            &unknown,
            content,
            listed,
        ),
    ));

    // Every dtype: u8 colours, u32 indices, u64 ids/offsets, f16 descriptors, f32 positions,
    // f64 poses, plus optional u16 and f64 sections of unknown kinds, zstd and raw mixed.
    let mixed_scene = Scene::new(11, 10, 2, &[(3, 2.0, 6, 3)]);
    let mut w = mixed_scene.writer(Codec::Raw);
    let u16s: Vec<u16> = (0..10).map(|i| i * 1000).collect();
    let f64s: Vec<f64> = vec![0.5, -1.25, 1e100, -0.0];
    w.add_raw_section(
        SectionKind::Unknown(0x7F02),
        NO_LEVEL,
        Dtype::U16,
        10,
        1,
        false,
        Cow::Owned(bytemuck::cast_slice(&u16s).to_vec()),
        Some(Codec::Zstd),
    )
    .unwrap();
    w.add_raw_section(
        SectionKind::Unknown(0x7F03),
        3,
        Dtype::F64,
        2,
        2,
        false,
        Cow::Owned(bytemuck::cast_slice(&f64s).to_vec()),
        None,
    )
    .unwrap();
    let mixed = w.to_bytes().unwrap();
    let content = mixed_scene.expected_json(origin_of(&mixed));
    let listed = json!([
        { "kind_code": 0x7F02, "skipped": "unknown kind", "dtype": "u16", "rows": 10, "cols": 1 },
        { "kind_code": 0x7F03, "skipped": "unknown kind", "dtype": "f64", "rows": 2, "cols": 2 },
    ]);
    out.push((
        "mixed_dtypes",
        mixed.clone(),
        valid_expected(
            "all seven dtypes, raw and zstd sections mixed",
            &mixed,
            content,
            listed,
        ),
    ));

    let vlad = scene_vlad(&s);
    let with_vlad = s.writer_with_vlad(Codec::Raw, &vlad).to_bytes().unwrap();
    let mut content = s.expected_json(origin_of(&with_vlad));
    content["retrieval"] = json!("vlad");
    content["vlad"] = vlad.expected_json();
    out.push((
        "vlad",
        with_vlad.clone(),
        valid_expected_version(
            "1.1",
            "the levels vector plus VLAD retrieval on level 2 (2 centroids x 2 dims)",
            &with_vlad,
            content,
            json!([]),
        ),
    ));

    let indexed = scene_indexed(&s, &vlad).to_bytes().unwrap();
    let mut content = s.expected_json(origin_of(&indexed));
    content["retrieval"] = json!("vlad");
    content["vlad"] = vlad.expected_json();
    content["image_index"] = json!({
        "of": "vlad",
        "probe": 1,
        "centroids": INDEX_CENTROIDS.chunks(4).collect::<Vec<_>>(),
        "lists": [[0, 2], [1]],
    });
    out.push((
        "image_index",
        indexed.clone(),
        valid_expected_version(
            "1.3",
            "the vlad vector plus an image index (1.3) of 2 lists over the 3 images' VLADs",
            &indexed,
            content.clone(),
            json!([]),
        ),
    ));

    // 1.4: the image_index vector plus each image's neighbours (image 1 lists one).
    let mut w = scene_indexed(&s, &vlad);
    w.set_image_neighbours(NEIGHBOURS.to_vec(), 2).unwrap();
    let with_neighbours = w.to_bytes().unwrap();
    // The image_index vector's content, with the neighbours read back.
    content["image_index"]["neighbours"] = json!([[2, 1], [0], [1, 0]]);
    out.push((
        "image_index_neighbours",
        with_neighbours.clone(),
        valid_expected_version(
            "1.4",
            "the image_index vector plus each image's neighbours (1.4), 2 columns, image 1 listing one",
            &with_neighbours,
            content,
            json!([]),
        ),
    ));

    // A later minor's optional sections in encodings 1.1 does not define: a known kind with
    // an unknown codec (colours) and one with an unknown dtype (ids), an unknown kind with an
    // unknown flag bit. A 1.1 reader skips and lists all three and reads the points.
    let mut w = MapWriter::default();
    w.metadata_mut().provenance.tool = "sfpmap test fixture".into();
    w.set_points_world(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    let optional = [
        (
            SectionKind::PointColors,
            Dtype::U8,
            3,
            vec![1u8, 2, 3, 4, 5, 6],
        ),
        (
            SectionKind::PointIds,
            Dtype::U64,
            1,
            bytemuck::cast_slice(&[7u64, 8]).to_vec(),
        ),
        (
            SectionKind::Unknown(0x7F01),
            Dtype::U16,
            1,
            vec![9, 0, 10, 0],
        ),
    ];
    for (kind, dtype, cols, bytes) in optional {
        w.add_raw_section(
            kind,
            NO_LEVEL,
            dtype,
            2,
            cols,
            false,
            Cow::Owned(bytes),
            None,
        )
        .unwrap();
    }
    let later = patch(&w.to_bytes().unwrap(), |h, e| {
        h.minor = 5;
        e[1].codec = 3;
        e[2].dtype = 9;
        e[3].flags = 0x02;
    });
    let content = json!({
        "points": 2, "positions": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], "colors": null, "point_ids": null,
        "cameras": 0, "images": [], "visibility": null, "levels": [],
    });
    let listed = json!([
        { "kind_code": 2, "skipped": "unknown codec code 3", "dtype": null, "rows": 2, "cols": 3 },
        { "kind_code": 3, "skipped": "unknown dtype code 9", "dtype": null, "rows": 2, "cols": 1 },
        { "kind_code": 0x7F01, "skipped": "unknown section flags 0x02", "dtype": null, "rows": 2, "cols": 1 },
    ]);
    out.push((
        "later_minor",
        later.clone(),
        valid_expected_version(
            "1.5",
            "a later minor's optional sections in encodings this version does not know (skipped)",
            &later,
            content,
            listed,
        ),
    ));

    // 1.1: level 1 (dim_full 8, dim_short 4) product-quantised over its short block: 2
    // subspaces of 2 dims, 3 centroids each; point r's codes (r mod 3, r div 3 mod 3).
    let pq = pq_levels(&s);
    let mut content = s.expected_json(origin_of(&pq));
    content["levels"][1] = json!({
        "level": 1, "points": content["levels"][1]["points"], "dim_full": 8, "dim_short": 4,
        "has_rest": false, "short": null, "rest": null,
        "pq": {
            "subspaces": 2, "centroids": 3, "sub_dims": 2,
            "codebook": PQ_CODEBOOK.chunks(2).collect::<Vec<_>>(),
            "codes": pq_codes(&s).chunks(2).collect::<Vec<_>>(),
        },
    });
    out.push((
        "pq",
        pq.clone(),
        valid_expected_version(
            "1.1",
            "the levels vector with level 1 product-quantised (2 subspaces x 3 centroids of 2 dims over its short block)",
            &pq,
            content.clone(),
            json!([]),
        ),
    ));
    // The same codes over the dimensions in the order PQ_ORDER.
    let pq_ordered = pq_levels_ordered(&s, &PQ_ORDER);
    content["levels"][1]["pq"]["order"] = json!(PQ_ORDER);
    out.push((
        "pq_order",
        pq_ordered.clone(),
        valid_expected_version(
            "1.1",
            "the pq vector with level_pq_order: quantised position j is level dimension order[j]",
            &pq_ordered,
            content,
            json!([]),
        ),
    ));

    // (1.2) A section of more than one chunk: the writer adds chunk checksums over every
    // section. The large section is one a reader skips, so the content stays two points.
    let chunked = chunked_map();
    let content = json!({
        "points": 2, "positions": [[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]], "colors": null, "point_ids": null,
        "cameras": 0, "images": [], "visibility": null, "levels": [],
    });
    let listed = json!([{ "kind_code": 0x7F02, "skipped": "unknown kind", "dtype": "u8", "rows": CHUNKED_ROWS, "cols": 1 }]);
    out.push((
        "chunk_checksums",
        chunked.clone(),
        valid_expected_version(
            "1.2",
            "chunk checksums: a 70,000-byte optional section (2 chunks of 64 KiB) and the positions (1), every chunk checked by verify",
            &chunked,
            content,
            listed,
        ),
    ));

    let geo = Scene::new(5, 6, 2, &[]);
    let mut w = geo.writer(Codec::Raw);
    w.metadata_mut().geometry_only = true;
    let geometry = w.to_bytes().unwrap();
    let content = geo.expected_json(origin_of(&geometry));
    out.push((
        "geometry_only",
        geometry.clone(),
        valid_expected(
            "points, images and visibility without descriptors",
            &geometry,
            content,
            json!([]),
        ),
    ));
    out
}

/// Positions (`[[x, y, z]]` JSON) as the spec's grid stores them: 65,535 steps from each
/// axis's smallest to its largest value, each value at its nearest step, read back as f32.
fn on_grid(positions: &Value) -> Vec<[f32; 3]> {
    let p: Vec<[f32; 3]> = serde_json::from_value(positions.clone()).unwrap();
    let axis = |k: usize| p.iter().map(move |v| f64::from(v[k]));
    let min: [f64; 3] = std::array::from_fn(|k| axis(k).fold(f64::INFINITY, f64::min));
    let max: [f64; 3] = std::array::from_fn(|k| axis(k).fold(f64::NEG_INFINITY, f64::max));
    let step: [f64; 3] = std::array::from_fn(|k| (max[k] - min[k]) / 65535.0);
    p.iter()
        .map(|v| {
            std::array::from_fn(|k| {
                let q = ((f64::from(v[k]) - min[k]) / step[k]).round();
                (min[k] + q * step[k]) as f32
            })
        })
        .collect()
}

/// The PQ vector's codebook `[2·3 × 2]`: subspace 0's centroids, then subspace 1's.
const PQ_CODEBOOK: [f32; 12] = [
    0.5, 0.5, -0.5, 0.5, 0.0, -0.7, 0.6, 0.0, -0.6, 0.1, 0.0, 0.25,
];

fn pq_codes(s: &Scene) -> Vec<u8> {
    let n = s.levels[1].points.len();
    (0..n)
        .flat_map(|r| [(r % 3) as u8, (r / 3 % 3) as u8])
        .collect()
}

/// The levels scene with level 1's f16 blocks replaced by PQ codes.
fn pq_levels(s: &Scene) -> Vec<u8> {
    let mut w = s.writer(Codec::Raw);
    w.set_level_pq(1, 2, 3, (PQ_CODEBOOK.to_vec(), pq_codes(s)), None)
        .unwrap();
    w.to_bytes().unwrap()
}

/// `file` with `bytes` written `at` bytes into the first section of `kind`, its checksums
/// recomputed: a value only a check of the section's contents can catch.
fn patched(file: &[u8], kind: SectionKind, at: usize, bytes: &[u8]) -> Vec<u8> {
    let map = Map::from_bytes(file).unwrap();
    let section = map.sections().iter().find(|x| x.kind() == kind).unwrap();
    let start = section.offset() as usize + at;
    let mut b = file.to_vec();
    b[start..start + bytes.len()].copy_from_slice(bytes);
    sfpmap::fuzzing::fix_checksums(&b)
}

/// The scene (with level 1 product-quantised as in the `pq` vector when `pq`) plus one raw
/// section `(kind, dtype, rows, cols)` on level 1 holding `bytes`.
fn pq_plus_raw(
    s: &Scene,
    pq: bool,
    (kind, dtype, rows, cols): (SectionKind, Dtype, u64, u64),
    required: bool,
    bytes: Vec<u8>,
) -> Vec<u8> {
    let mut w = s.writer(Codec::Raw);
    if pq {
        w.set_level_pq(1, 2, 3, (PQ_CODEBOOK.to_vec(), pq_codes(s)), None)
            .unwrap();
    }
    w.add_raw_section(
        kind,
        1,
        dtype,
        rows,
        cols,
        required,
        Cow::Owned(bytes),
        None,
    )
    .unwrap();
    w.to_bytes().unwrap()
}

/// The `pq_order` vector's order of level 1's 4 short dimensions.
const PQ_ORDER: [u16; 4] = [2, 0, 3, 1];

fn pq_levels_ordered(s: &Scene, order: &[u16]) -> Vec<u8> {
    let mut w = s.writer(Codec::Raw);
    w.set_level_pq(
        1,
        2,
        3,
        (PQ_CODEBOOK.to_vec(), pq_codes(s)),
        Some(order.to_vec()),
    )
    .unwrap();
    w.to_bytes().unwrap()
}

/// Bytes of the `chunk_checksums` vector's large section: more than one chunk.
const CHUNKED_ROWS: u64 = 70_000;

/// Two points and an optional section of a kind no version defines, [`CHUNKED_ROWS`] bytes:
/// the writer stores chunk checksums (1.2).
fn chunked_map() -> Vec<u8> {
    let mut w = MapWriter::default();
    w.metadata_mut().provenance.tool = "sfpmap test fixture".into();
    w.set_points_world(&[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    let values: Vec<u8> = (0..CHUNKED_ROWS).map(|i| (i * 7 % 251) as u8).collect();
    w.add_raw_section(
        SectionKind::Unknown(0x7F02),
        NO_LEVEL,
        Dtype::U8,
        CHUNKED_ROWS,
        1,
        false,
        Cow::Owned(values),
        Some(Codec::Raw),
    )
    .unwrap();
    w.to_bytes().unwrap()
}

/// (name, bytes, expected error kind, stage where it must be found).
fn invalid_vectors() -> Vec<(&'static str, Vec<u8>, &'static str, &'static str)> {
    let good = scene().writer(Codec::Raw).to_bytes().unwrap();
    let mut out = Vec::new();

    let mut b = good.clone();
    b[1] = b'X';
    out.push(("bad_magic", b, "bad_magic", "open"));

    let mut b = good.clone();
    b[8] = 2;
    out.push(("unknown_major", b, "version_mismatch", "open"));

    let file_len = good.len() as u64;
    out.push((
        "section_out_of_bounds",
        patch(&good, |_, e| e[2].offset = (file_len + 64) & !63),
        "section_out_of_bounds",
        "open",
    ));

    out.push((
        "overlapping_sections",
        patch(&good, |_, e| e[3].offset = e[2].offset),
        "overlap",
        "open",
    ));

    let mut b = good.clone();
    let last = *b.last().unwrap();
    *b.last_mut().unwrap() = last ^ 0x01;
    out.push(("bad_checksum", b, "checksum_mismatch", "verify"));

    out.push((
        "size_overflow",
        patch(&good, |_, e| {
            e[0].rows = u64::MAX / 2;
            e[0].cols = 4
        }),
        "size_mismatch",
        "open",
    ));

    out.push((
        "truncated",
        good[..good.len() / 2].to_vec(),
        "truncated",
        "open",
    ));

    let mut b = good.clone();
    let first = Map::from_bytes(&good).unwrap().sections()[0].offset() as usize;
    b[first - 1] = 0xFF;
    out.push(("bad_padding", patch(&b, |_, _| {}), "bad_padding", "open"));

    // A NaN position with a correct checksum: found when the section is first read.
    let b = patched(
        &good,
        SectionKind::PointPositions,
        12,
        &f32::NAN.to_le_bytes(),
    );
    out.push(("nonfinite_position", b, "inconsistent", "verify"));

    let b = with_extra_section(
        SectionKind::Unknown(0x7F01),
        NO_LEVEL,
        true,
        Some(Codec::Raw),
    );
    out.push(("unknown_required", b, "unknown_required_section", "open"));

    // 1.1: header flags are required features; none is defined yet.
    // 1.1: quantised positions without the grid that gives them meaning.
    let m = Map::from_bytes(&good).unwrap();
    let (mut w, _) = slice(
        &m,
        &SliceOptions {
            levels: vec![2],
            short: true,
            codec: None,
            zstd_level: 3,
            minimal: true,
        },
    )
    .unwrap();
    let minimal_slice = w.to_bytes().unwrap();
    w.metadata_mut().position_grid = None;
    out.push((
        "q16_without_grid",
        w.to_bytes().unwrap(),
        "bad_metadata",
        "open",
    ));
    // 1.1 defines feature bit 0 (delta); bit 1 is unknown.
    out.push((
        "unknown_feature",
        patch(&minimal_slice, |h, _| h.flags |= 2),
        "unknown_required_feature",
        "open",
    ));
    // 1.1: a required section keeps the encodings its reader knows.
    out.push((
        "required_unknown_codec",
        patch(&minimal_slice, |_, e| e[0].codec = 3),
        "bad_entry",
        "open",
    ));
    // 1.1: codec delta in required sections only behind header feature bit 0 ...
    out.push((
        "delta_without_feature",
        patch(&minimal_slice, |h, _| h.flags = 0),
        "bad_entry",
        "open",
    ));
    // ... and on u32 and u64 arrays only (here the u16 grid positions).
    out.push((
        "delta_on_u16",
        patch(&minimal_slice, |_, e| {
            let q16 = e
                .iter_mut()
                .find(|e| e.kind == SectionKind::PointPositionsQ16.code())
                .unwrap();
            q16.codec = 2;
        }),
        "bad_entry",
        "open",
    ));
    // A delta stream one value short of the 4 values its table declares.
    let short_stream = zstd::bulk::compress(&[2, 2, 2], 3).unwrap();
    let mut delta = Crafted::raw(
        SectionKind::Unknown(0x7F01),
        NO_LEVEL,
        sfpmap::format::Dtype::U32,
        4,
        1,
        short_stream,
    );
    delta.codec = Codec::Delta as u8;
    delta.flags = 0;
    delta.raw_len = 16;
    out.push((
        "delta_short_stream",
        craft(&craft_metadata(vec![]), &[craft_points(2), delta]),
        "decode",
        "verify",
    ));

    // A zstd section whose table claims a huge (but self-consistent) array.
    let z = with_extra_section(
        SectionKind::Unknown(0x7F01),
        NO_LEVEL,
        false,
        Some(Codec::Zstd),
    );
    out.push((
        "decode_bomb",
        patch(&z, |_, e| {
            e[1].rows = 1 << 40;
            e[1].raw_len = (1 << 40) * 3 * 2
        }),
        "decoded_too_large",
        "verify",
    ));

    // 1.1: a VLAD codebook without the image VLADs it belongs with.
    let s = scene();
    let vlad = scene_vlad(&s);
    let mut w = s.writer(Codec::Raw);
    w.add_raw_section(
        SectionKind::LevelVladCentroids,
        2,
        Dtype::F32,
        2,
        2,
        false,
        Cow::Owned(bytemuck::cast_slice(&vlad.centroids).to_vec()),
        None,
    )
    .unwrap();
    out.push((
        "vlad_without_image_vlad",
        w.to_bytes().unwrap(),
        "missing_section",
        "open",
    ));

    // 1.1: image VLADs of 3 values where the 2 x 2 codebook makes 4.
    let mut w = s.writer_with_vlad(Codec::Raw, &vlad);
    let three: Vec<f16> = vlad
        .images
        .chunks(4)
        .flat_map(|r| r[..3].iter().map(|&v| f16::from_f32(v)))
        .collect();
    w.add_raw_section(
        SectionKind::ImageVlad,
        NO_LEVEL,
        Dtype::F16,
        3,
        3,
        false,
        Cow::Owned(bytemuck::cast_slice(&three).to_vec()),
        None,
    )
    .unwrap();
    out.push((
        "vlad_wrong_columns",
        w.to_bytes().unwrap(),
        "inconsistent",
        "open",
    ));

    // 1.3: image 2 in both lists (and image 1 in none), its section checksum recomputed.
    let b = patched(
        &scene_indexed(&s, &vlad).to_bytes().unwrap(),
        SectionKind::ImageIndexImages,
        8,
        &2u32.to_le_bytes(),
    );
    out.push(("image_index_image_twice", b, "inconsistent", "verify"));
    // 1.4: neighbour 3 of the 3 images, its section checksum recomputed.
    let mut w = scene_indexed(&s, &vlad);
    w.set_image_neighbours(NEIGHBOURS.to_vec(), 2).unwrap();
    let b = patched(
        &w.to_bytes().unwrap(),
        SectionKind::ImageIndexNeighbours,
        4,
        &3u32.to_le_bytes(),
    );
    out.push((
        "image_index_neighbour_past_images",
        b,
        "inconsistent",
        "verify",
    ));
    // 1.3: index centroids of 3 values where the VLAD rows have 4.
    let mut w = scene_indexed(&s, &vlad);
    w.add_raw_section(
        SectionKind::ImageIndexCentroids,
        NO_LEVEL,
        Dtype::F32,
        2,
        3,
        false,
        Cow::Owned(bytemuck::cast_slice(&INDEX_CENTROIDS[..6]).to_vec()),
        None,
    )
    .unwrap();
    out.push((
        "image_index_wrong_width",
        w.to_bytes().unwrap(),
        "inconsistent",
        "open",
    ));

    // 1.1: a code past the codebook's 3 centroids, its section checksum recomputed.
    let b = patched(&pq_levels(&s), SectionKind::LevelPqCodes, 1, &[3]);
    out.push(("pq_code_past_codebook", b, "inconsistent", "verify"));
    // 1.1: an order naming dimension 0 twice (and not 3), its section checksum recomputed.
    let ordered = pq_levels_ordered(&s, &PQ_ORDER);
    let b = patched(&ordered, SectionKind::LevelPqOrder, 4, &0u16.to_le_bytes());
    out.push(("pq_order_not_a_permutation", b, "inconsistent", "verify"));
    // 1.1: an order of 3 rows for the 4 quantised dimensions.
    let order3 = bytemuck::cast_slice(&[0u16, 1, 2]).to_vec();
    let b = pq_plus_raw(
        &s,
        true,
        (SectionKind::LevelPqOrder, Dtype::U16, 3, 1),
        true,
        order3,
    );
    out.push(("pq_order_wrong_length", b, "inconsistent", "open"));
    // 1.1: an order on a level stored in f16 (no codes to order).
    let order = bytemuck::cast_slice(&PQ_ORDER).to_vec();
    let b = pq_plus_raw(
        &s,
        false,
        (SectionKind::LevelPqOrder, Dtype::U16, 4, 1),
        true,
        order.clone(),
    );
    out.push(("pq_order_without_pq", b, "inconsistent", "open"));
    // 1.1: the pq_order vector with its order flagged optional (a reader skipping it would
    // read the codes in the wrong dimensions).
    let b = pq_plus_raw(
        &s,
        true,
        (SectionKind::LevelPqOrder, Dtype::U16, 4, 1),
        false,
        order,
    );
    out.push(("pq_order_optional", b, "bad_entry", "open"));
    // 1.1: 2 subspaces x 3 dims = 6, neither dim_short 4 nor dim_full 8 of level 1.
    let codebook = bytemuck::cast_slice(&PQ_CODEBOOK).to_vec();
    let b = pq_plus_raw(
        &s,
        true,
        (SectionKind::LevelPqCodebook, Dtype::F32, 4, 3),
        true,
        codebook,
    );
    out.push(("pq_codebook_wrong_shape", b, "inconsistent", "open"));

    // (1.2) A chunk checksum too few: open refuses the table.
    let chunked = chunked_map();
    let mut b = patch(&chunked, |h, e| {
        let last = e.len() - 1;
        assert_eq!(e[last].kind, SectionKind::ChunkChecksums.code());
        e[last].rows -= 1;
        e[last].raw_len -= 8;
        e[last].stored_len -= 8;
        h.file_len -= 8;
    });
    b.truncate(b.len() - 8);
    out.push(("chunk_count_mismatch", b, "inconsistent", "open"));

    // (1.2) The second chunk of the large section does not match its chunk checksum (the
    // chunk section's own checksum fixed, and the large section's whole checksum intact).
    let map = Map::from_bytes(&chunked).unwrap();
    let sums = *map.sections().last().unwrap();
    assert_eq!(sums.kind(), SectionKind::ChunkChecksums);
    let mut b = chunked.clone();
    let second = sums.offset() as usize + 8 * 2;
    b[second] ^= 0x01;
    let fixed_sum =
        checksum(&b[sums.offset() as usize..(sums.offset() + sums.stored_len()) as usize]);
    let b = patch(&b, |_, e| {
        let last = e.len() - 1;
        e[last].checksum = fixed_sum;
    });
    out.push(("bad_chunk_checksum", b, "checksum_mismatch", "verify"));
    out
}

fn read_file(path: &Path) -> Vec<u8> {
    std::fs::read(path)
        .unwrap_or_else(|e| panic!("{}: {e} (run with SFPMAP_REGEN_VECTORS=1)", path.display()))
}

#[test]
fn committed_vectors_equal_the_generator() {
    let dir = vectors_dir();
    let regen = std::env::var_os("SFPMAP_REGEN_VECTORS").is_some();
    for (name, bytes, expected) in valid_vectors() {
        let (bin, js) = (
            dir.join(format!("valid/{name}.sfpm")),
            dir.join(format!("valid/{name}.json")),
        );
        if regen {
            std::fs::write(&bin, &bytes).unwrap();
            std::fs::write(&js, serde_json::to_string_pretty(&expected).unwrap() + "\n").unwrap();
        }
        assert_eq!(
            read_file(&bin),
            bytes,
            "{name}: writer output differs from the committed vector"
        );
        let committed: Value = serde_json::from_slice(&read_file(&js)).unwrap();
        assert_eq!(committed, expected, "{name}: expected json differs");
    }
    for (name, bytes, error, stage) in invalid_vectors() {
        let (bin, js) = (
            dir.join(format!("invalid/{name}.sfpm")),
            dir.join(format!("invalid/{name}.json")),
        );
        let expected = json!({ "error": error, "stage": stage });
        if regen {
            std::fs::write(&bin, &bytes).unwrap();
            std::fs::write(&js, serde_json::to_string_pretty(&expected).unwrap() + "\n").unwrap();
        }
        assert_eq!(
            read_file(&bin),
            bytes,
            "{name}: generator differs from the committed vector"
        );
        let committed: Value = serde_json::from_slice(&read_file(&js)).unwrap();
        assert_eq!(committed, expected, "{name}: expected json differs");
    }
}

fn committed(kind: &str) -> Vec<(PathBuf, Vec<u8>, Value)> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(vectors_dir().join(kind))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "sfpm"))
        .collect();
    files.sort();
    assert!(files.len() >= 6, "at least 6 {kind} vectors");
    files
        .into_iter()
        .map(|p| {
            let json: Value =
                serde_json::from_slice(&read_file(&p.with_extension("json"))).unwrap();
            let bytes = read_file(&p);
            (p, bytes, json)
        })
        .collect()
}

#[test]
fn valid_vectors_decode_to_their_json() {
    for (path, bytes, expected) in committed("valid") {
        let map = Map::from_bytes(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        map.verify()
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(map.version(), expected["version"], "{}", path.display());
        assert_eq!(map.file_len(), expected["file_bytes"], "{}", path.display());
        assert_eq!(
            decoded_json(&map),
            expected["content"],
            "{}",
            path.display()
        );
        let skipped: Vec<Value> = map
            .skipped_sections()
            .map(|s| {
                let why = s.skipped().unwrap();
                let dtype = (!why.hides_encoding()).then(|| s.dtype().name());
                json!({ "kind_code": s.kind().code(), "skipped": why.to_string(), "dtype": dtype, "rows": s.rows(), "cols": s.cols() })
            })
            .collect();
        assert_eq!(
            json!(skipped),
            expected["skipped_sections"],
            "{}",
            path.display()
        );
        let reader_1_0 = if opens_under_1_0_rules(&bytes) {
            "opens"
        } else {
            "refuses"
        };
        assert_eq!(reader_1_0, expected["reader_1_0"], "{}", path.display());
        // The same through the mmap path.
        let mapped = Map::open(&path).unwrap();
        assert_eq!(decoded_json(&mapped), expected["content"]);
    }
}

#[test]
fn invalid_vectors_fail_with_their_error() {
    for (path, bytes, expected) in committed("invalid") {
        let result = Map::from_bytes(&bytes);
        let (stage, err) = match result {
            Err(e) => ("open", e),
            Ok(map) => (
                "verify",
                map.verify()
                    .expect_err(&format!("{} verifies", path.display())),
            ),
        };
        assert_eq!(
            err.kind_name(),
            expected["error"],
            "{}: {err}",
            path.display()
        );
        assert_eq!(stage, expected["stage"], "{}: {err}", path.display());
    }
}

/// What a 1.0 reader makes of each valid vector, as the spec's vector table states it (by
/// hand, so the generator's `reader_1_0` column is checked against something it did not
/// compute): 1.1 files with a required 1.1 kind or an encoding 1.0 rejects are refused.
#[test]
fn reader_1_0_column_is_the_spec_table() {
    let refused = ["pq", "pq_order", "later_minor", "minimal_slice"];
    for (path, _, expected) in committed("valid") {
        let name = path.file_stem().unwrap().to_str().unwrap();
        let want = if refused.contains(&name) {
            "refuses"
        } else {
            "opens"
        };
        assert_eq!(expected["reader_1_0"], want, "{name}");
    }
}

/// The bytes whose flips `every_byte_flip_of_a_valid_vector_fails_verify` tries: every byte of
/// a small vector; of the `chunk_checksums` vector (70 KB, each flip a whole verify) the
/// index, and of each 64-byte block the first and last byte (so every chunk and both sides of
/// each chunk boundary).
fn flipped_bytes(bytes: &[u8]) -> Vec<usize> {
    if bytes.len() <= 16 << 10 {
        return (0..bytes.len()).collect();
    }
    let header = Header::decode(bytes).unwrap();
    let index_end = (header.metadata_offset + header.metadata_len) as usize;
    (0..bytes.len())
        .filter(|&i| i < index_end || i % 64 == 0 || i % 64 == 63)
        .collect()
}

#[test]
fn every_byte_flip_of_a_valid_vector_fails_verify() {
    for (path, bytes, _) in committed("valid") {
        let mut copy = bytes.clone();
        for i in flipped_bytes(&bytes) {
            for mask in [0x01u8, 0x80] {
                copy[i] ^= mask;
                let outcome = Map::from_bytes(&copy).and_then(|m| m.verify());
                assert!(
                    outcome.is_err(),
                    "{}: flipping bit {mask:#x} of byte {i} passes verify",
                    path.display()
                );
                copy[i] ^= mask;
            }
        }
    }
}

#[test]
fn every_truncation_of_a_valid_vector_fails() {
    for (path, bytes, _) in committed("valid") {
        for len in 0..bytes.len() {
            let outcome = Map::from_bytes(&bytes[..len]).and_then(|m| m.verify());
            assert!(
                outcome.is_err(),
                "{}: truncated to {len} bytes passes",
                path.display()
            );
        }
    }
}
