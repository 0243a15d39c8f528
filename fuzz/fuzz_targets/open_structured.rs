#![no_main]
//! Structure-aware: builds a valid map from the input with sfpmap's own writer (points,
//! cameras, images, visibility, levels with short/rest/projection, unknown sections, raw or
//! zstd), then makes absurd but checksum-correct edits to it: numbers in the metadata JSON,
//! table fields, single bytes. Every format body runs on the result
//! (`sfpmap::fuzzing::all_format_bodies`).
//!
//! A crash's input is this target's own encoding; to replay it in `cargo test`, run the
//! target on it with `SFPMAP_FUZZ_SAVE_MAP=path` set, which writes the map it built, and
//! commit that map under `fuzz/regressions/<body>/` for the body the backtrace names (`open`,
//! `decode` or `slice`: each folder is replayed through its own body only).

use libfuzzer_sys::arbitrary::{self, Arbitrary};
use sfpmap::format::{CameraInfo, Codec, Descriptors, Dtype, LevelInfo, MapWriter, SectionKind};
use sfpmap::fuzzing::{
    all_format_bodies, fix_checksums, with_metadata, Header, RawEntry, ENTRY_LEN, HEADER_LEN,
    NO_LEVEL,
};
use std::borrow::Cow;

#[derive(Arbitrary, Debug)]
struct Spec {
    points: u8,
    zstd: bool,
    geometry_only: bool,
    cameras: Vec<Camera>,
    images: u8,
    global_dim: u8,
    levels: Vec<LevelSpec>,
    unknown: Vec<Unknown>,
    number_edits: Vec<NumberEdit>,
    table_edits: Vec<TableEdit>,
    byte_edits: Vec<(u32, u8)>,
}

#[derive(Arbitrary, Debug)]
struct Camera {
    width: u16,
    height: u16,
    params: Vec<f32>,
}

#[derive(Arbitrary, Debug)]
struct LevelSpec {
    id: u16,
    dim_full: u8,
    dim_short: u8,
    /// Bit i of the pattern (cycled): whether point i is in the level.
    membership: u64,
    rest: bool,
    projection: bool,
    values: Vec<u8>,
}

#[derive(Arbitrary, Debug)]
struct Unknown {
    kind: u16,
    dtype: u8,
    cols: u8,
    zstd: bool,
    bytes: Vec<u8>,
}

/// Replaces the `nth` (cycled) number of the metadata JSON.
#[derive(Arbitrary, Debug)]
struct NumberEdit {
    nth: u16,
    value: Number,
}

#[derive(Arbitrary, Debug)]
enum Number {
    U64(u64),
    Small(u8),
    Max32,
    Max16,
    Negative,
    Fraction,
    Huge,
}

#[derive(Arbitrary, Debug)]
struct TableEdit {
    entry: u16,
    field: Field,
    value: u64,
}

#[derive(Arbitrary, Debug)]
enum Field {
    Kind,
    Level,
    Dtype,
    Codec,
    Flags,
    Rows,
    Cols,
    Offset,
    StoredLen,
    RawLen,
}

const MAX_POINTS: usize = 64;
const MAX_DIM: usize = 32;

/// Owned arrays, so the writer can borrow them.
struct Arrays {
    positions: Vec<[f64; 3]>,
    colors: Vec<[u8; 3]>,
    ids: Vec<u64>,
    names: Vec<String>,
    image_cameras: Vec<u32>,
    poses: Vec<[f64; 7]>,
    image_ids: Vec<u32>,
    global: Vec<f32>,
    vis_offsets: Vec<u64>,
    vis_points: Vec<u32>,
    vis_keypoints: Vec<[f32; 2]>,
    levels: Vec<LevelArrays>,
}

struct LevelArrays {
    info: LevelInfo,
    points: Vec<u32>,
    descriptors: Vec<f32>,
    rest: bool,
    projection: Option<Vec<f32>>,
}

fn arrays(spec: &Spec) -> Arrays {
    let n = usize::from(spec.points) % (MAX_POINTS + 1);
    let images = usize::from(spec.images % 5);
    let n_cameras = spec.cameras.len().min(4) as u32;
    let mut vis_offsets = vec![0u64];
    let mut vis_points = Vec::new();
    for i in 0..images {
        vis_points.extend((0..n as u32).filter(|p| (p + i as u32).is_multiple_of(3)));
        vis_offsets.push(vis_points.len() as u64);
    }
    let mut levels = Vec::new();
    for l in spec.levels.iter().take(4) {
        let full = usize::from(l.dim_full) % (MAX_DIM + 1);
        let short = usize::from(l.dim_short) % (full + 1);
        let points: Vec<u32> = (0..n as u32)
            .filter(|&p| l.membership >> (p % 64) & 1 == 1)
            .collect();
        let value = |i: usize| f32::from(*l.values.get(i % l.values.len().max(1)).unwrap_or(&1));
        let descriptors = (0..points.len() * full).map(|i| value(i) / 255.0).collect();
        let projection = l.projection.then(|| {
            (0..full * full)
                .map(|i| if i.is_multiple_of(full + 1) { 1.0 } else { 0.0 })
                .collect()
        });
        let info = LevelInfo {
            level: l.id,
            stride: 8.0,
            descriptor: "sfp-v1".into(),
            dim_full: full as u32,
            dim_short: short as u32,
            normalization: "l2".into(),
            extra: Default::default(),
        };
        levels.push(LevelArrays {
            info,
            points,
            descriptors,
            rest: l.rest,
            projection,
        });
    }
    Arrays {
        positions: (0..n)
            .map(|i| [i as f64, (i * 7 % 5) as f64, -(i as f64)])
            .collect(),
        colors: (0..n).map(|i| [i as u8, 0, 255]).collect(),
        ids: (0..n as u64).map(|i| i * 3 + 1).collect(),
        names: (0..images).map(|i| format!("img{i}.jpg")).collect(),
        image_cameras: (0..images as u32).map(|i| i % n_cameras.max(1)).collect(),
        poses: (0..images)
            .map(|i| [1.0, 0.0, 0.0, 0.0, i as f64, 0.0, 1.0])
            .collect(),
        image_ids: (1..=images as u32).collect(),
        global: vec![0.5; images * usize::from(spec.global_dim % 9)],
        vis_keypoints: vis_points.iter().map(|&p| [p as f32, 1.5]).collect(),
        vis_offsets,
        vis_points,
        levels,
    }
}

/// The writer's map of `spec`, before any edit; `None` when the writer refuses it.
fn build(spec: &Spec, a: &Arrays) -> Option<Vec<u8>> {
    let mut w = MapWriter::default();
    w.set_codec(if spec.zstd { Codec::Zstd } else { Codec::Raw }, 1);
    w.metadata_mut().geometry_only = spec.geometry_only;
    for c in spec.cameras.iter().take(4) {
        w.add_camera(CameraInfo {
            id: None,
            model: "PINHOLE".into(),
            width: u64::from(c.width),
            height: u64::from(c.height),
            params: c.params.iter().take(8).map(|&p| f64::from(p)).collect(),
        });
    }
    w.set_points_world(&a.positions);
    w.set_point_colors(&a.colors);
    w.set_point_ids(&a.ids);
    if !a.names.is_empty() && !spec.cameras.is_empty() {
        w.set_images(&a.names, &a.image_cameras, &a.poses, Some(&a.image_ids))
            .ok()?;
        w.set_visibility(&a.vis_offsets, &a.vis_points, Some(&a.vis_keypoints))
            .ok()?;
        let dim = usize::from(spec.global_dim % 9);
        if dim > 0 {
            w.set_image_global(dim, &a.global).ok()?;
        }
    }
    for l in &a.levels {
        let descriptors = (!spec.geometry_only).then_some(Descriptors::F32(&l.descriptors));
        w.add_level(l.info.clone(), &l.points, descriptors, l.rest)
            .ok()?;
        if let Some(p) = &l.projection {
            w.set_level_projection(l.info.level, l.info.dim_full as usize, p.clone())
                .ok()?;
        }
    }
    for u in spec.unknown.iter().take(4) {
        let dtype = Dtype::from_code(u.dtype % 7 + 1)?;
        let cols = u64::from(u.cols % 4 + 1);
        let row = cols * dtype.size();
        let rows = u.bytes.len() as u64 / row;
        let bytes = u.bytes[..(rows * row) as usize].to_vec();
        let codec = if u.zstd { Codec::Zstd } else { Codec::Raw };
        let kind = SectionKind::Unknown(0x7000 | (u.kind & 0x0fff));
        w.add_raw_section(
            kind,
            NO_LEVEL,
            dtype,
            rows,
            cols,
            false,
            Cow::Owned(bytes),
            Some(codec),
        )
        .ok()?;
    }
    w.to_bytes().ok()
}

/// Replaces numbers in the metadata JSON (relaid out, checksums fixed).
fn edit_numbers(map: Vec<u8>, edits: &[NumberEdit]) -> Vec<u8> {
    if edits.is_empty() {
        return map;
    }
    let Ok(header) = Header::decode(&map) else {
        return map;
    };
    let start = header.metadata_offset as usize;
    let Some(json) = map.get(start..start + header.metadata_len as usize) else {
        return map;
    };
    let mut text = String::from_utf8_lossy(json).into_owned();
    for edit in edits.iter().take(8) {
        let numbers = number_spans(&text);
        if numbers.is_empty() {
            break;
        }
        let (from, to) = numbers[usize::from(edit.nth) % numbers.len()];
        let value = match edit.value {
            Number::U64(v) => v.to_string(),
            Number::Small(v) => v.to_string(),
            Number::Max32 => u32::MAX.to_string(),
            Number::Max16 => u16::MAX.to_string(),
            Number::Negative => "-1".into(),
            Number::Fraction => "0.5".into(),
            Number::Huge => "1e308".into(),
        };
        text.replace_range(from..to, &value);
    }
    with_metadata(&map, text.as_bytes()).unwrap_or(map)
}

/// Byte ranges of the numbers in a JSON text (outside strings).
fn number_spans(text: &str) -> Vec<(usize, usize)> {
    let b = text.as_bytes();
    let (mut spans, mut i, mut in_string) = (Vec::new(), 0, false);
    while i < b.len() {
        match b[i] {
            b'"' if !in_string => in_string = true,
            b'"' if in_string && b[i - 1] != b'\\' => in_string = false,
            c if !in_string && (c == b'-' || c.is_ascii_digit()) => {
                let from = i;
                while i < b.len() && matches!(b[i], b'0'..=b'9' | b'-' | b'+' | b'.' | b'e' | b'E')
                {
                    i += 1;
                }
                spans.push((from, i));
                continue;
            }
            _ => {}
        }
        i += 1;
    }
    spans
}

fn edit_table(mut map: Vec<u8>, spec: &Spec) -> Vec<u8> {
    let Ok(header) = Header::decode(&map) else {
        return map;
    };
    let count = header.section_count as usize;
    for e in spec.table_edits.iter().take(4) {
        if count == 0 {
            break;
        }
        let at = HEADER_LEN + usize::from(e.entry) % count * ENTRY_LEN;
        let Some(bytes) = map.get(at..at + ENTRY_LEN) else {
            break;
        };
        let mut entry = RawEntry::decode(bytes);
        let v = e.value;
        match e.field {
            Field::Kind => entry.kind = v as u16,
            Field::Level => entry.level = v as u16,
            Field::Dtype => entry.dtype = v as u8,
            Field::Codec => entry.codec = v as u8,
            Field::Flags => entry.flags = v as u8,
            Field::Rows => entry.rows = v,
            Field::Cols => entry.cols = v,
            Field::Offset => entry.offset = v,
            Field::StoredLen => entry.stored_len = v,
            Field::RawLen => entry.raw_len = v,
        }
        map[at..at + ENTRY_LEN].copy_from_slice(&entry.encode());
    }
    for &(at, byte) in spec.byte_edits.iter().take(4) {
        if !map.is_empty() {
            let at = at as usize % map.len();
            map[at] = byte;
        }
    }
    fix_checksums(&map)
}

libfuzzer_sys::fuzz_target!(|spec: Spec| {
    let a = arrays(&spec);
    let Some(map) = build(&spec, &a) else { return };
    let map = edit_numbers(map, &spec.number_edits);
    let map = edit_table(map, &spec);
    if let Some(path) = std::env::var_os("SFPMAP_FUZZ_SAVE_MAP") {
        std::fs::write(path, &map).expect("SFPMAP_FUZZ_SAVE_MAP is writable");
    }
    all_format_bodies(&map);
});
