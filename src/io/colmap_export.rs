//! Writes a map back out as a COLMAP text model (`cameras.txt`, `images.txt`,
//! `points3D.txt`) that COLMAP and pycolmap read: the independent check of what a map holds.
//!
//! Each image's points2D are the map's visibility entries for it, in order, so a point's
//! track element `(image_id, point2D_idx)` is the entry's index within its image.

use crate::colmap::{
    text, Camera, Image, Point2D, Reconstruction, ReconstructionBuilder, TrackElement,
};
use crate::format::{CameraInfo, Error, Images, Map};
use crate::geometry::{CameraModel, Pose};
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
    let (model, summary) = to_reconstruction(map, true)?;
    Ok(ColmapText {
        cameras: text::write_cameras(&model),
        images: text::write_images(&model),
        points3d: text::write_points3d(&model),
        summary,
    })
}

/// The map as a COLMAP [`Reconstruction`], written by [`crate::colmap::text`], the one COLMAP
/// text writer. With `observations`, each image's points2D are its visibility entries and
/// every observed point is a 3D point (unobserved ones are dropped, as COLMAP drops them);
/// without, the images only (what `export --images-txt` writes).
pub(crate) fn to_reconstruction(
    map: &Map<'_>,
    observations: bool,
) -> Result<(Reconstruction, ExportSummary), Error> {
    let meta = map.metadata();
    let images = map
        .images()?
        .ok_or_else(|| Error::inconsistent("the map has no images; a COLMAP model needs them"))?;
    let mut model = Reconstruction::builder();
    for (i, c) in meta.cameras.iter().enumerate() {
        let id = camera_id(&meta.cameras, i);
        let Some(kind) = CameraModel::from_name(&c.model) else {
            return Err(Error::invalid(format!(
                "camera {id}: model name {} is not a COLMAP camera model, which a COLMAP cameras.txt cannot hold",
                quoted_name(&c.model)
            )));
        };
        model.add_camera(Camera {
            id,
            model: kind,
            width: c.width,
            height: c.height,
            params: c.params.clone(),
        });
    }
    let mut summary = ExportSummary {
        cameras: meta.cameras.len(),
        images: images.len(),
        points: 0,
        observations: 0,
    };
    if !observations {
        for i in 0..images.len() {
            model.add_image(image(&meta.cameras, &images, i, Vec::new())?);
        }
        return Ok((build(model)?, summary));
    }
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

    // Tracks: for each point, (image_id, index within the image), in image order.
    let n_points = positions.len();
    let mut tracks: Vec<Vec<TrackElement>> = vec![Vec::new(); n_points];
    for i in 0..images.len() {
        let start = vis.offsets[i] as usize;
        let mut points2d = Vec::with_capacity(vis.points_of(i).len());
        for (k, &p) in vis.points_of(i).iter().enumerate() {
            let xy = keypoints[start + k];
            points2d.push(Point2D {
                xy: [f64::from(xy[0]), f64::from(xy[1])],
                point3d_id: Some(point_id(p as usize)),
            });
            tracks[p as usize].push(TrackElement {
                image_id: image_id(&images, i),
                point2d_idx: k as u32,
            });
        }
        model.add_image(image(&meta.cameras, &images, i, points2d)?);
    }
    for (p, track) in tracks.iter().enumerate() {
        // COLMAP drops points without observations; so do we, to stay readable by it.
        if track.is_empty() {
            continue;
        }
        summary.points += 1;
        let rgb = colors.as_ref().map_or([128, 128, 128], |c| c[p]);
        model
            .add_point3d(point_id(p), map.to_world(positions[p]), rgb, 0.0, track)
            .map_err(|e| Error::inconsistent(format!("as a COLMAP model: {e}")))?;
    }
    summary.observations = vis.points.len();
    Ok((build(model)?, summary))
}

/// Image `i` with its points2D; a name COLMAP's text files cannot hold is an error.
fn image(
    cameras: &[CameraInfo],
    images: &Images<'_>,
    i: usize,
    points2d: Vec<Point2D>,
) -> Result<Image, Error> {
    let name = images.name(i)?;
    let id = image_id(images, i);
    if let Some(problem) = text_name_problem(name) {
        return Err(Error::invalid(format!(
            "image {id}: name {} {problem}, which a COLMAP images.txt cannot hold",
            quoted_name(name)
        )));
    }
    let cam_from_world = Pose::from_colmap_array(images.poses[i])
        .map_err(|e| Error::inconsistent(format!("image {id}: pose: {e}")))?;
    Ok(Image {
        id,
        name: name.to_string(),
        camera_id: camera_id(cameras, images.cameras[i] as usize),
        cam_from_world,
        points2d,
    })
}

/// The builder's checks (ids unique, tracks and points2D agree, values finite) on what the
/// map holds.
fn build(model: ReconstructionBuilder) -> Result<Reconstruction, Error> {
    model
        .build()
        .map_err(|e| Error::inconsistent(format!("as a COLMAP model: {e}")))
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
