//! A map's points as a binary little-endian PLY that CloudCompare and MeshLab open: world
//! position, colour, and the level each point belongs to.
//!
//! Precision: positions are written as `double`, world = origin + the stored f32 offset
//! computed in f64, so a map in city-scale (UTM-like) coordinates keeps its offsets exact;
//! float32 world coordinates would round them to about a decimetre at 10⁶ m. The origin is
//! also given in a header comment for tools that want to subtract it again.
//!
//! Levels: `level` is the deepest (largest id) level holding the point, or −1 for a point in
//! no level; the deepest is the smallest, most distinctive set (the one coarse matching
//! uses), so colouring by it shows where that support is. `level_mask` has bit `l` set for
//! every level `l < 32` that holds the point, for the full picture.

use crate::format::{Error, Map};
use std::io::Write;

/// What a PLY export wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlySummary {
    /// Points written.
    pub points: usize,
    /// Points in at least one level.
    pub points_in_levels: usize,
}

/// Each point's deepest level (`None`: in no level) and its level bit mask.
pub fn point_levels(map: &Map<'_>) -> Result<(Vec<Option<u16>>, Vec<u32>), Error> {
    let n = map.n_points() as usize;
    let mut deepest = vec![None; n];
    let mut mask = vec![0u32; n];
    // Ascending ids, so the last level written is the deepest.
    for level in map.levels() {
        let id = level.id();
        for &p in level.points()?.iter() {
            let p = p as usize;
            if p < n {
                deepest[p] = Some(id);
                if id < 32 {
                    mask[p] |= 1 << id;
                }
            }
        }
    }
    Ok((deepest, mask))
}

/// Writes the map's points as PLY to `out` (buffer it: one write per field).
pub fn write_ply(map: &Map<'_>, mut out: impl Write, source: &str) -> Result<PlySummary, Error> {
    let positions = map.point_positions()?;
    let colors = map.point_colors()?;
    let (levels, masks) = point_levels(map)?;
    let origin = map.metadata().origin;
    let io = |e: std::io::Error| Error::io(std::path::Path::new(source), e);
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    header += &format!(
        "comment sfpmap export of {}\n",
        source.replace(['\n', '\r'], " ")
    );
    header += &format!(
        "comment origin {:.17} {:.17} {:.17} (positions below are world coordinates)\n",
        origin[0], origin[1], origin[2]
    );
    header += "comment level: deepest level holding the point, -1 for none; level_mask: bit l for level l < 32\n";
    header += &format!("element vertex {}\n", positions.len());
    header += "property double x\nproperty double y\nproperty double z\n";
    header += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
    header += "property int level\nproperty uint level_mask\nend_header\n";
    out.write_all(header.as_bytes()).map_err(io)?;
    let mut record = Vec::with_capacity(35);
    let mut in_levels = 0;
    for (p, &pos) in positions.iter().enumerate() {
        record.clear();
        for c in map.to_world(pos) {
            record.extend_from_slice(&c.to_le_bytes());
        }
        let rgb = colors.as_ref().map_or([200, 200, 200], |c| c[p]);
        record.extend_from_slice(&rgb);
        let level = levels[p].map_or(-1, i32::from);
        in_levels += usize::from(levels[p].is_some());
        record.extend_from_slice(&level.to_le_bytes());
        record.extend_from_slice(&masks[p].to_le_bytes());
        out.write_all(&record).map_err(io)?;
    }
    out.flush().map_err(io)?;
    Ok(PlySummary {
        points: positions.len(),
        points_in_levels: in_levels,
    })
}
