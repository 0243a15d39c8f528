//! Writes a map back out as a COLMAP text model (`cameras.txt`, `images.txt`,
//! `points3D.txt`) that COLMAP and pycolmap read: the independent check of what a map holds.
//!
//! Each image's points2D are the map's visibility entries for it, in order, so a point's
//! track element `(image_id, point2D_idx)` is the entry's index within its image.

use crate::format::{Error, Map};
use std::fmt::Write as _;
use std::path::Path;

/// Counts of what was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExportSummary {
    pub cameras: usize,
    pub images: usize,
    pub points: usize,
    pub observations: usize,
}

/// The three files' contents.
pub struct ColmapText {
    pub cameras: String,
    pub images: String,
    pub points3d: String,
    pub summary: ExportSummary,
}

/// Renders the map as COLMAP text files. Needs images and visibility with keypoints.
pub fn to_colmap_text(map: &Map<'_>) -> Result<ColmapText, Error> {
    let meta = map.metadata();
    let images = map
        .images()?
        .ok_or_else(|| Error::inconsistent("the map has no images; a COLMAP model needs them"))?;
    let vis = map
        .visibility()?
        .ok_or_else(|| Error::inconsistent("the map has no visibility; COLMAP tracks need it"))?;
    let keypoints = vis.keypoints.as_ref().ok_or_else(|| {
        Error::inconsistent("the map has no visibility keypoints; COLMAP points2D need them")
    })?;
    let positions = map.point_positions()?;
    let colors = map.point_colors()?;
    let ids = map.point_ids()?;
    let camera_id = |i: usize| meta.cameras[i].id.unwrap_or(i as u32 + 1);
    let image_id = |i: usize| images.ids.as_ref().map_or(i as u32 + 1, |ids| ids[i]);
    let point_id = |p: usize| ids.as_ref().map_or(p as u64 + 1, |ids| ids[p]);

    let mut cameras = String::from("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    writeln!(cameras, "# Number of cameras: {}", meta.cameras.len()).ok();
    for (i, c) in meta.cameras.iter().enumerate() {
        write!(
            cameras,
            "{} {} {} {}",
            camera_id(i),
            c.model,
            c.width,
            c.height
        )
        .ok();
        for p in &c.params {
            write!(cameras, " {p}").ok();
        }
        cameras.push('\n');
    }

    // Tracks: for each point, (image_id, index within the image), in image order.
    let n_points = positions.len();
    let mut tracks: Vec<Vec<(u32, usize)>> = vec![Vec::new(); n_points];
    let mut text_images = String::from("# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    writeln!(
        text_images,
        "# Number of images: {}, observations: {}",
        images.len(),
        vis.points.len()
    )
    .ok();
    for i in 0..images.len() {
        let q = images.poses[i];
        let cam = images.cameras[i] as usize;
        writeln!(
            text_images,
            "{} {} {} {} {} {} {} {} {} {}",
            image_id(i),
            q[0],
            q[1],
            q[2],
            q[3],
            q[4],
            q[5],
            q[6],
            camera_id(cam),
            images.name(i)?
        )
        .ok();
        let start = vis.offsets[i] as usize;
        let mut line = String::new();
        for (k, &p) in vis.points_of(i).iter().enumerate() {
            let xy = keypoints[start + k];
            if !line.is_empty() {
                line.push(' ');
            }
            write!(line, "{} {} {}", xy[0], xy[1], point_id(p as usize)).ok();
            tracks[p as usize].push((image_id(i), k));
        }
        text_images.push_str(&line);
        text_images.push('\n');
    }

    let mut points3d = String::from("# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    writeln!(points3d, "# Number of points: {n_points}").ok();
    let mut exported = 0;
    for (p, track) in tracks.iter().enumerate() {
        // COLMAP drops points without observations; so do we, to stay readable by it.
        if track.is_empty() {
            continue;
        }
        exported += 1;
        let w = map.to_world(positions[p]);
        let rgb = colors.as_ref().map_or([128, 128, 128], |c| c[p]);
        write!(
            points3d,
            "{} {} {} {} {} {} {} 0",
            point_id(p),
            w[0],
            w[1],
            w[2],
            rgb[0],
            rgb[1],
            rgb[2]
        )
        .ok();
        for (image, idx) in track {
            write!(points3d, " {image} {idx}").ok();
        }
        points3d.push('\n');
    }
    Ok(ColmapText {
        cameras,
        images: text_images,
        points3d,
        summary: ExportSummary {
            cameras: meta.cameras.len(),
            images: images.len(),
            points: exported,
            observations: vis.points.len(),
        },
    })
}

/// Writes the model into `dir` (created if needed), each file through a temp file + rename.
pub fn export_colmap(map: &Map<'_>, dir: &Path) -> Result<ExportSummary, Error> {
    let text = to_colmap_text(map)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    for (name, body) in [
        ("cameras.txt", &text.cameras),
        ("images.txt", &text.images),
        ("points3D.txt", &text.points3d),
    ] {
        let path = dir.join(name);
        let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
        std::fs::write(&tmp, body)
            .and_then(|_| std::fs::rename(&tmp, &path))
            .map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                Error::io(&path, e)
            })?;
    }
    Ok(text.summary)
}
