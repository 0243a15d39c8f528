//! Writes a map back out as a COLMAP text model (`cameras.txt`, `images.txt`,
//! `points3D.txt`) that COLMAP and pycolmap read: the independent check of what a map holds.
//!
//! Each image's points2D are the map's visibility entries for it, in order, so a point's
//! track element `(image_id, point2D_idx)` is the entry's index within its image.

use crate::format::{CameraInfo, Error, Images, Map};
use std::fmt::Write as _;
use std::path::Path;

/// The files of a COLMAP text model, in the order [`export_colmap`] writes them.
pub const COLMAP_FILES: [&str; 3] = ["cameras.txt", "images.txt", "points3D.txt"];

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
    let point_id = |p: usize| ids.as_ref().map_or(p as u64 + 1, |ids| ids[p]);

    let mut cameras = String::from("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    writeln!(cameras, "# Number of cameras: {}", meta.cameras.len()).ok();
    for (i, c) in meta.cameras.iter().enumerate() {
        if let Some(problem) = text_name_problem(&c.model) {
            return Err(Error::invalid(format!(
                "camera {}: model name {} {problem}, which a COLMAP cameras.txt cannot hold",
                camera_id(&meta.cameras, i),
                quoted_name(&c.model)
            )));
        }
        write!(
            cameras,
            "{} {} {} {}",
            camera_id(&meta.cameras, i),
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
    let mut text_images = images_txt_header(images.len(), vis.points.len());
    for i in 0..images.len() {
        write_image_line(&mut text_images, &meta.cameras, &images, i)?;
        let start = vis.offsets[i] as usize;
        let mut line = String::new();
        for (k, &p) in vis.points_of(i).iter().enumerate() {
            let xy = keypoints[start + k];
            if !line.is_empty() {
                line.push(' ');
            }
            write!(line, "{} {} {}", xy[0], xy[1], point_id(p as usize)).ok();
            tracks[p as usize].push((image_id(&images, i), k));
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

/// Writes the model into `dir` (created if needed), each file through
/// [`crate::output::write_atomic`] (temp file, fsync, rename).
pub fn export_colmap(map: &Map<'_>, dir: &Path) -> Result<ExportSummary, Error> {
    let text = to_colmap_text(map)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    for (name, body) in COLMAP_FILES
        .into_iter()
        .zip([&text.cameras, &text.images, &text.points3d])
    {
        let path = dir.join(name);
        crate::output::write_atomic(&path, |out| {
            std::io::Write::write_all(out, body.as_bytes()).map_err(|e| Error::io(&path, e))
        })?;
    }
    Ok(text.summary)
}

/// The COLMAP `camera_id` of the map's camera `index`: its source id, else `index + 1` (also
/// for an index past the camera list, so a bad index never panics).
fn camera_id(cameras: &[CameraInfo], index: usize) -> u32 {
    cameras
        .get(index)
        .and_then(|c| c.id)
        .unwrap_or(index as u32 + 1)
}

/// The COLMAP `image_id` of image `i`: its source id, else `i + 1`.
fn image_id(images: &Images<'_>, i: usize) -> u32 {
    images.ids.as_ref().map_or(i as u32 + 1, |ids| ids[i])
}

/// The comment header `images.txt` starts with, counts included.
pub(crate) fn images_txt_header(images: usize, observations: usize) -> String {
    format!(
        "# Image list with two lines of data per image:\n\
         #   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n\
         #   POINTS2D[] as (X, Y, POINT3D_ID)\n\
         # Number of images: {images}, observations: {observations}\n"
    )
}

/// Appends image `i`'s first `images.txt` line (`IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID
/// NAME` and the newline); its POINTS2D line is the caller's to write.
pub(crate) fn write_image_line(
    out: &mut String,
    cameras: &[CameraInfo],
    images: &Images<'_>,
    i: usize,
) -> Result<(), Error> {
    let q = images.poses[i];
    let name = images.name(i)?;
    if let Some(problem) = text_name_problem(name) {
        return Err(Error::invalid(format!(
            "image {}: name {} {problem}, which a COLMAP images.txt cannot hold",
            image_id(images, i),
            quoted_name(name)
        )));
    }
    writeln!(
        out,
        "{} {} {} {} {} {} {} {} {} {}",
        image_id(images, i),
        q[0],
        q[1],
        q[2],
        q[3],
        q[4],
        q[5],
        q[6],
        camera_id(cameras, images.cameras[i] as usize),
        name
    )
    .ok();
    Ok(())
}

/// Why `name` cannot be a NAME in `images.txt` (or a MODEL in `cameras.txt`), if it cannot.
/// Refused rather than escaped: COLMAP reads a line up to its newline, trims it and takes
/// each field up to the next space, with no escape syntax, so a control character ends or
/// corrupts the line (a newline injects an image), a space cuts the name short, and an
/// escape would be read back as part of the name.
pub fn text_name_problem(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("is empty")
    } else if name.chars().any(char::is_control) {
        Some("holds a control character")
    } else if name.bytes().any(|b| b.is_ascii_whitespace()) {
        Some("holds a space")
    } else {
        None
    }
}

/// `s` with each control character written as an escape (`\n`, `\r`, `\t`, else
/// `\xNN`; all control characters are below U+00A0), so it stays on one line; borrowed
/// when there is none, which is the usual case.
pub fn escape_control_characters(s: &str) -> std::borrow::Cow<'_, str> {
    if !s.chars().any(char::is_control) {
        return std::borrow::Cow::Borrowed(s);
    }
    let mut out = String::with_capacity(s.len() + 8);
    for c in s.chars() {
        match c {
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c.is_control() => {
                write!(out, "\\x{:02x}", u32::from(c)).ok();
            }
            c => out.push(c),
        }
    }
    std::borrow::Cow::Owned(out)
}

/// At most this many characters of a name go into a message.
const SHOWN_NAME: usize = 60;

/// `name` for a one-line message: quoted, control characters escaped, cut after
/// [`SHOWN_NAME`] characters.
pub fn quoted_name(name: &str) -> String {
    let shown: String = name.chars().take(SHOWN_NAME).collect();
    let cut = if shown.len() < name.len() { "…" } else { "" };
    format!("\"{}{cut}\"", escape_control_characters(&shown))
}
