//! Writes a map back out as a COLMAP text model (`cameras.txt`, `images.txt`,
//! `points3D.txt`) that COLMAP and pycolmap read: the independent check of what a map holds.
//!
//! Each image's points2D are the map's visibility entries for it, in order, so a point's
//! track element `(image_id, point2D_idx)` is the entry's index within its image.

use crate::colmap::text::{self, text_name_problem};
use crate::escape::quoted_name;
use crate::format::{CameraInfo, Error, Images, Map};
use crate::geometry::{CameraModel, Pose};
use std::fmt::Write as _;
use std::path::Path;

/// The files of a COLMAP text model, in the order [`export_colmap`] writes them.
pub const COLMAP_FILES: [&str; 3] = ["cameras.txt", "images.txt", "points3D.txt"];

/// Counts of what was written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ExportSummary {
    /// Cameras written.
    pub cameras: usize,
    /// Images written.
    pub images: usize,
    /// 3D points written.
    pub points: usize,
    /// Observations (2D points with a 3D point) written.
    pub observations: usize,
}

/// Whether `map`'s images can be written as COLMAP text: names `images.txt` can hold and
/// poses that are rotations (what [`export_colmap`] and `--images-txt` check before writing);
/// a caller writing other outputs too asks first, so a refusal leaves none of them behind.
pub fn check_images_exportable(map: &Map<'_>) -> Result<(), Error> {
    if let Some(images) = map.images()? {
        ImageLines::new(map.metadata().cameras.as_slice(), &images)?;
    }
    Ok(())
}

/// Writes the model into `dir` (created if needed), each file through
/// [`crate::output::write_atomic`] (temp file, fsync, rename), streamed: lines go out in
/// chunks, so a million-point map never has its text (or a model) in memory whole. Needs
/// images and visibility with keypoints.
pub fn export_colmap(map: &Map<'_>, dir: &Path) -> Result<ExportSummary, Error> {
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
    let tracks = Tracks::new(
        &images,
        vis.points.as_ref(),
        |i| vis.points_of(i),
        positions.len(),
    )?;
    // Checked before anything is written, so a bad map leaves no partial model behind.
    let lines = ImageLines::new(meta.cameras.as_slice(), &images)?;
    let cameras = cameras_txt(&meta.cameras)?;

    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let path = dir.join(COLMAP_FILES[0]);
    chunked(&path, |buf, _| {
        buf.push_str(&cameras);
        Ok(())
    })?;
    let path = dir.join(COLMAP_FILES[1]);
    chunked(&path, |buf, flush| {
        buf.push_str(text::IMAGES_HEADER);
        writeln!(buf, "# Number of images: {}", images.len()).ok();
        for i in 0..images.len() {
            lines.image_line(buf, i);
            let start = vis.offsets[i] as usize;
            let own = vis.points_of(i);
            let xys = &keypoints[start..start + own.len()];
            let points = xys
                .iter()
                .zip(own)
                .map(|(&xy, &p)| (xy, Some(point_id(p as usize))));
            text::points2d_line(buf, points);
            flush(buf)?;
        }
        Ok(())
    })?;
    let path = dir.join(COLMAP_FILES[2]);
    let mut exported = 0;
    chunked(&path, |buf, flush| {
        buf.push_str(text::POINTS3D_HEADER);
        writeln!(buf, "# Number of points: {}", tracks.observed).ok();
        for p in 0..positions.len() {
            let track = tracks.of(p);
            // COLMAP drops points without observations; so do we, to stay readable by it.
            if track.is_empty() {
                continue;
            }
            exported += 1;
            let rgb = colors.as_ref().map_or([128, 128, 128], |c| c[p]);
            let xyz = map.to_world(positions[p]);
            text::point3d_line(buf, point_id(p), xyz, rgb, 0.0, track.iter().copied());
            flush(buf)?;
        }
        Ok(())
    })?;
    Ok(ExportSummary {
        cameras: meta.cameras.len(),
        images: images.len(),
        points: exported,
        observations: vis.points.len(),
    })
}

/// The map's database images as a COLMAP `images.txt` with empty POINTS2D lines (a valid
/// model file once next to a `cameras.txt`; [`export_colmap`] writes one with observations).
/// A name that line cannot hold (a control character, a space) is an error naming the image.
pub(crate) fn images_txt_without_points(map: &Map<'_>) -> Result<String, Error> {
    let images = map
        .images()?
        .ok_or_else(|| Error::inconsistent("the map has no images"))?;
    let lines = ImageLines::new(&map.metadata().cameras, &images)?;
    let mut out = String::from(text::IMAGES_HEADER);
    writeln!(out, "# Number of images: {}", images.len()).ok();
    for i in 0..images.len() {
        lines.image_line(&mut out, i);
        out.push('\n');
    }
    Ok(out)
}

/// `cameras.txt`; a model name COLMAP does not know is an error naming the camera.
fn cameras_txt(cameras: &[CameraInfo]) -> Result<String, Error> {
    let mut out = String::from(text::CAMERAS_HEADER);
    writeln!(out, "# Number of cameras: {}", cameras.len()).ok();
    for (i, c) in cameras.iter().enumerate() {
        let id = camera_id(cameras, i);
        let model = CameraModel::from_name(&c.model).ok_or_else(|| {
            Error::invalid(format!(
                "camera {id}: model name {} is not a COLMAP camera model, which a COLMAP cameras.txt cannot hold",
                quoted_name(&c.model)
            ))
        })?;
        if c.params.len() != model.num_params() || !c.params.iter().all(|p| p.is_finite()) {
            return Err(Error::invalid(format!(
                "camera {id}: {} parameters ({} expected, all finite)",
                c.params.len(),
                model.num_params()
            )));
        }
        text::camera_line(&mut out, id, model.name(), [c.width, c.height], &c.params);
    }
    Ok(out)
}

/// Every image's first `images.txt` line, checked up front: names COLMAP's text can hold and
/// poses that are rotations.
struct ImageLines<'a> {
    cameras: &'a [CameraInfo],
    images: &'a Images<'a>,
    poses: Vec<Pose>,
}

impl<'a> ImageLines<'a> {
    fn new(cameras: &'a [CameraInfo], images: &'a Images<'a>) -> Result<Self, Error> {
        let mut poses = Vec::with_capacity(images.len());
        for i in 0..images.len() {
            let id = image_id(images, i);
            let name = images.name(i)?;
            if let Some(problem) = text_name_problem(name) {
                return Err(Error::invalid(format!(
                    "image {id}: name {} {problem}, which a COLMAP images.txt cannot hold",
                    quoted_name(name)
                )));
            }
            poses.push(
                Pose::from_colmap_array(images.poses[i])
                    .map_err(|e| Error::inconsistent(format!("image {id}: pose: {e}")))?,
            );
        }
        Ok(ImageLines {
            cameras,
            images,
            poses,
        })
    }

    fn image_line(&self, out: &mut String, i: usize) {
        let camera = camera_id(self.cameras, self.images.cameras[i] as usize);
        // Names were read in `new`; a second read cannot fail.
        let name = self.images.name(i).unwrap_or_default();
        text::image_line(out, image_id(self.images, i), &self.poses[i], camera, name);
    }
}

/// Every point's track, `(image_id, point2D_idx)` in image order, in one flat array (CSR):
/// 8 bytes an observation, no allocation per point.
struct Tracks {
    offsets: Vec<usize>,
    elements: Vec<(u32, u32)>,
    /// Points with at least one observation.
    observed: usize,
}

impl Tracks {
    fn new<'v>(
        images: &Images<'_>,
        all: &[u32],
        points_of: impl Fn(usize) -> &'v [u32],
        n_points: usize,
    ) -> Result<Self, Error> {
        let mut offsets = vec![0usize; n_points + 1];
        for &p in all {
            let slot = offsets.get_mut(p as usize + 1).ok_or_else(|| {
                Error::inconsistent(format!("visibility names point {p} of {n_points}"))
            })?;
            *slot += 1;
        }
        let observed = offsets[1..].iter().filter(|&&n| n > 0).count();
        for i in 1..offsets.len() {
            offsets[i] += offsets[i - 1];
        }
        let mut next = offsets.clone();
        let mut elements = vec![(0, 0); all.len()];
        for i in 0..images.len() {
            let image = image_id(images, i);
            for (k, &p) in points_of(i).iter().enumerate() {
                let at = &mut next[p as usize];
                elements[*at] = (image, k as u32);
                *at += 1;
            }
        }
        Ok(Tracks {
            offsets,
            elements,
            observed,
        })
    }

    fn of(&self, p: usize) -> &[(u32, u32)] {
        &self.elements[self.offsets[p]..self.offsets[p + 1]]
    }
}

/// Writes `path` atomically from text that `fill` appends to a buffer; `fill` calls the
/// flush it is given after each record, which writes the buffer out past 1 MiB.
fn chunked(
    path: &Path,
    fill: impl FnOnce(
        &mut String,
        &mut dyn FnMut(&mut String) -> Result<(), Error>,
    ) -> Result<(), Error>,
) -> Result<(), Error> {
    crate::output::write_atomic(path, |out| {
        let mut write = |buf: &mut String| {
            std::io::Write::write_all(out, buf.as_bytes()).map_err(|e| Error::io(path, e))?;
            buf.clear();
            Ok(())
        };
        let mut flush = |buf: &mut String| {
            if buf.len() >= 1 << 20 {
                write(buf)?;
            }
            Ok(())
        };
        let mut buf = String::new();
        fill(&mut buf, &mut flush)?;
        write(&mut buf)
    })
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
