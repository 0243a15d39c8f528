//! Fuzz-target bodies, kept in the library so `cargo test` can replay the corpus and the
//! committed crashing inputs without cargo-fuzz.

use super::{slice, Map, SliceOptions};

/// Open + validate, then touch every view. Must never panic.
pub fn open_and_read(data: &[u8]) {
    let Ok(map) = Map::from_bytes(data) else {
        return;
    };
    let _ = map.point_positions();
    let _ = map.point_colors();
    let _ = map.point_ids();
    if let Ok(Some(images)) = map.images() {
        for i in 0..images.len() {
            let _ = images.name(i);
        }
    }
    let _ = map.image_global();
    if let Ok(Some(vis)) = map.visibility() {
        for i in 0..vis.offsets.len().saturating_sub(1) {
            let _ = vis.points_of(i);
            let _ = vis.keypoints_of(i);
        }
    }
    for level in map.levels() {
        let _ = level.points();
        let _ = level.desc_short();
        let _ = level.desc_rest();
        let _ = level.projection();
    }
    let _ = map.verify();
}

/// Decode every section directly (raw and zstd paths), in table order.
pub fn decode_sections(data: &[u8]) {
    let Ok(map) = Map::from_bytes(data) else {
        return;
    };
    for section in map.sections() {
        let _ = map.section_bytes(section);
    }
}

/// Slice in memory to each single level (short and full) and re-open the result.
pub fn slice_in_memory(data: &[u8]) {
    let Ok(map) = Map::from_bytes(data) else {
        return;
    };
    let levels = map.level_ids();
    for (i, &level) in levels.iter().enumerate().take(4) {
        let options = SliceOptions {
            levels: vec![level],
            short: i % 2 == 0,
            codec: None,
            zstd_level: 1,
        };
        if let Ok((writer, _)) = slice(&map, &options) {
            let bytes = writer
                .to_bytes()
                .expect("slicing a verified map gives valid input");
            Map::from_bytes(&bytes)
                .and_then(|m| m.verify())
                .expect("a slice of a readable map must be valid");
        }
    }
}
