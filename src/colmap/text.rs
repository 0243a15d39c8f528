//! COLMAP text models: `cameras.txt`, `images.txt`, `points3D.txt`.
//!
//! Lines starting with `#` and blank lines are comments, except that in `images.txt` the line
//! after an image line is always that image's 2D points, even when empty (as COLMAP reads it).
//!
//! - `cameras.txt`: `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]` (`MODEL` is a name).
//! - `images.txt`: `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`, then `(X Y POINT3D_ID)*` with
//!   `POINT3D_ID = -1` for none.
//! - `points3D.txt`: `POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)*`.

use std::fmt::Write as _;
use std::path::Path;
use std::str::FromStr;

use super::error::{Error, Result};
use super::model::{
    has_control_character, image_pose, non_finite_param, non_finite_point2d, non_finite_point3d,
    BadPose, Camera, Image, Point2D, Reconstruction, ReconstructionBuilder, TrackElement,
};
use crate::geometry::{CameraModel, Pose};

/// Lines with their 1-based numbers, `\r\n` tolerated.
struct Lines<'a> {
    rest: &'a [u8],
    number: u64,
}

impl<'a> Lines<'a> {
    fn new(data: &'a [u8]) -> Self {
        Lines {
            rest: data,
            number: 0,
        }
    }

    /// The next raw line (trimmed), comments included.
    fn next_raw(&mut self) -> Option<(u64, &'a [u8])> {
        if self.rest.is_empty() {
            return None;
        }
        let (line, rest) = match self.rest.iter().position(|&b| b == b'\n') {
            Some(i) => (&self.rest[..i], &self.rest[i + 1..]),
            None => (self.rest, &[][..]),
        };
        self.rest = rest;
        self.number += 1;
        Some((self.number, line.trim_ascii()))
    }

    /// The next line that is neither blank nor a comment.
    fn next_data(&mut self) -> Option<(u64, &'a [u8])> {
        while let Some((n, line)) = self.next_raw() {
            if !line.is_empty() && line[0] != b'#' {
                return Some((n, line));
            }
        }
        None
    }
}

/// Whitespace-separated tokens of one line, with errors naming file and line.
struct Tokens<'a> {
    rest: &'a str,
    path: &'a Path,
    line: u64,
}

/// At most this much of a bad token goes into an error message.
const SHOWN: usize = 40;

impl<'a> Tokens<'a> {
    /// Checks the line is UTF-8 once, so tokens need no further checks (a name that is not
    /// UTF-8 could not be stored anyway).
    fn new(line: &'a [u8], path: &'a Path, number: u64) -> Result<Self> {
        let rest = std::str::from_utf8(line).map_err(|e| Error::BadLine {
            path: path.to_path_buf(),
            line: number,
            what: format!("invalid utf-8 at byte {} of the line", e.valid_up_to()),
        })?;
        Ok(Tokens {
            rest,
            path,
            line: number,
        })
    }

    fn error(&self, what: String) -> Error {
        Error::BadLine {
            path: self.path.to_path_buf(),
            line: self.line,
            what,
        }
    }

    fn next_token(&mut self) -> Option<&'a str> {
        let rest = self.rest.trim_ascii_start();
        // ASCII whitespace is one byte, so `end` is a char boundary.
        let end = rest
            .bytes()
            .position(|b| b.is_ascii_whitespace())
            .unwrap_or(rest.len());
        let (token, rest) = rest.split_at(end);
        self.rest = rest;
        (!token.is_empty()).then_some(token)
    }

    /// The rest of the line, trimmed.
    fn rest(&self) -> &'a str {
        self.rest.trim_ascii()
    }

    fn has_more(&self) -> bool {
        !self.rest.trim_ascii_start().is_empty()
    }

    fn count_rest(&self) -> usize {
        self.rest.split_ascii_whitespace().count()
    }

    /// An image's pose that [`image_pose`] refuses.
    fn bad_pose(&self, image_id: u32, bad: BadPose) -> Error {
        match bad {
            BadPose::NotFinite(field) => self.not_finite("image", image_id.into(), field),
            BadPose::ZeroRotation => Error::ZeroRotation {
                path: self.path.to_path_buf(),
                line: Some(self.line),
                image_id,
            },
        }
    }

    /// A NaN or infinite value (Rust's parser, like COLMAP's `stold`, reads `nan`, `inf` and
    /// overflows such as `1e400`), named by line and record.
    fn not_finite(&self, kind: &'static str, id: u64, field: impl Into<String>) -> Error {
        Error::NotFinite {
            path: self.path.to_path_buf(),
            line: Some(self.line),
            kind,
            id,
            field: field.into(),
        }
    }

    fn bad(&self, what: &str, token: &str) -> Error {
        let shown: String = token.chars().take(SHOWN).collect();
        self.error(format!("bad {what} {shown:?}"))
    }

    fn parse<T: FromStr>(&mut self, what: &str) -> Result<T> {
        let token = self
            .next_token()
            .ok_or_else(|| self.error(format!("missing {what}")))?;
        token.parse().map_err(|_| self.bad(what, token))
    }

    fn parse_f64s<const N: usize>(&mut self, what: &str) -> Result<[f64; N]> {
        let mut out = [0f64; N];
        for v in &mut out {
            *v = self.parse(what)?;
        }
        Ok(out)
    }

    /// A `POINT3D_ID` where COLMAP writes `-1` for none.
    fn point3d_id(&mut self) -> Result<Option<u64>> {
        let token = self
            .next_token()
            .ok_or_else(|| self.error("missing point3D id".to_string()))?;
        if token == "-1" {
            return Ok(None);
        }
        let id: u64 = token.parse().map_err(|_| self.bad("point3D id", token))?;
        Ok((id != u64::MAX).then_some(id))
    }
}

/// Parses `cameras.txt`; `path` only names the file in errors.
pub fn parse_cameras(data: &[u8], path: &Path) -> Result<Vec<Camera>> {
    let mut lines = Lines::new(data);
    let mut cameras = Vec::new();
    while let Some((number, line)) = lines.next_data() {
        let mut t = Tokens::new(line, path, number)?;
        let id: u32 = t.parse("camera id")?;
        let name = t
            .next_token()
            .ok_or_else(|| t.error("missing camera model".to_string()))?;
        let model = CameraModel::from_name(name).ok_or_else(|| Error::UnknownCameraModelName {
            path: path.to_path_buf(),
            line: number,
            name: name.chars().take(SHOWN).collect(),
        })?;
        let width: u64 = t.parse("camera width")?;
        let height: u64 = t.parse("camera height")?;
        let found = t.count_rest();
        if found != model.num_params() {
            return Err(t.error(format!(
                "camera {id}: model {model} takes {} parameters, found {found}",
                model.num_params()
            )));
        }
        let mut params = Vec::with_capacity(found);
        for _ in 0..found {
            params.push(t.parse("camera parameter")?);
        }
        if let Some(field) = non_finite_param(&params) {
            return Err(t.not_finite("camera", id.into(), field));
        }
        cameras.push(Camera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    Ok(cameras)
}

/// Parses `images.txt`.
pub fn parse_images(data: &[u8], path: &Path) -> Result<Vec<Image>> {
    let mut lines = Lines::new(data);
    let mut images = Vec::new();
    while let Some((number, line)) = lines.next_data() {
        let mut t = Tokens::new(line, path, number)?;
        let id: u32 = t.parse("image id")?;
        let rotation = t.parse_f64s::<4>("image rotation")?;
        let translation = t.parse_f64s::<3>("image translation")?;
        let camera_id: u32 = t.parse("image camera id")?;
        let cam_from_world =
            image_pose(rotation, translation).map_err(|bad| t.bad_pose(id, bad))?;
        // The name is the rest of the line, so names with spaces survive (COLMAP itself
        // reads up to the first space; `io::colmap_export` refuses to write such names).
        let name = t.rest();
        if name.is_empty() {
            return Err(t.error(format!("image {id}: missing name")));
        }
        if has_control_character(name) {
            return Err(Error::BadImageName {
                path: path.to_path_buf(),
                line: Some(number),
                image_id: id,
                name: super::error::shown_name(name),
            });
        }
        let name = name.to_string();
        // The points line follows unconditionally; a file ending right after the image line
        // means no points.
        let mut points2d = Vec::new();
        if let Some((number, line)) = lines.next_raw() {
            let mut t = Tokens::new(line, path, number)?;
            let n = t.count_rest();
            if n % 3 != 0 {
                return Err(t.error(format!(
                    "image {id}: points2D line has {n} values, not a multiple of 3 (X Y POINT3D_ID)"
                )));
            }
            points2d.reserve_exact(n / 3);
            while t.has_more() {
                let xy = t.parse_f64s::<2>("point2D coordinate")?;
                let point3d_id = t.point3d_id()?;
                points2d.push(Point2D { xy, point3d_id });
            }
            if let Some(field) = non_finite_point2d(points2d.iter().map(|p| p.xy)) {
                return Err(t.not_finite("image", id.into(), field));
            }
        }
        images.push(Image {
            id,
            name,
            camera_id,
            cam_from_world,
            points2d,
        });
    }
    Ok(images)
}

/// Parses `points3D.txt` into `builder`.
pub(crate) fn parse_points3d_into(
    data: &[u8],
    path: &Path,
    builder: &mut ReconstructionBuilder,
) -> Result<()> {
    let mut lines = Lines::new(data);
    while let Some((number, line)) = lines.next_data() {
        let mut t = Tokens::new(line, path, number)?;
        let id: u64 = t.parse("point3D id")?;
        let xyz = t.parse_f64s::<3>("point3D coordinate")?;
        let rgb = [
            t.parse::<u8>("point3D color")?,
            t.parse::<u8>("point3D color")?,
            t.parse::<u8>("point3D color")?,
        ];
        let error: f64 = t.parse("point3D error")?;
        if let Some(field) = non_finite_point3d(&xyz, error) {
            return Err(t.not_finite("point3D", id, field));
        }
        let n = t.count_rest();
        if n % 2 != 0 {
            return Err(t.error(format!(
                "point3D {id}: track has {n} values, not a multiple of 2 (IMAGE_ID POINT2D_IDX)"
            )));
        }
        let start = builder.begin_point3d();
        while t.has_more() {
            let image_id: u32 = t.parse("track image id")?;
            let point2d_idx: u32 = t.parse("track point2D index")?;
            builder.push_track(TrackElement {
                image_id,
                point2d_idx,
            });
        }
        builder.end_point3d(start, id, xyz, rgb, error)?;
    }
    Ok(())
}

/// Parses and validates the three files of a text model given as bytes.
pub fn parse_model(
    cameras: (&[u8], &Path),
    images: (&[u8], &Path),
    points3d: (&[u8], &Path),
) -> Result<Reconstruction> {
    super::parse_with(&super::TEXT, cameras, images, points3d)
}

// Writers. `{}` on f64 prints the shortest text that parses back to the same bits, so a
// text model written here reads back exactly. A `Reconstruction` holds only finite numbers
// and names without control characters (the builder checks), so no value can break a line.
// Names with spaces are written as COLMAP writes them: this crate's reader reads them back,
// COLMAP's reads up to the first space.

/// The comment lines `cameras.txt` starts with (COLMAP's), before the count line.
pub(crate) const CAMERAS_HEADER: &str =
    "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n";
/// The comment lines `images.txt` starts with, before the count line.
pub(crate) const IMAGES_HEADER: &str = "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n";
/// The comment lines `points3D.txt` starts with, before the count line.
pub(crate) const POINTS3D_HEADER: &str = "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n";

// One line of each file, for the writers here and for writers that stream a model they never
// hold whole (`io::colmap_export`). The caller checks names and values (see above).

/// A `cameras.txt` line with its newline.
pub(crate) fn camera_line(out: &mut String, id: u32, model: &str, size: [u64; 2], params: &[f64]) {
    let _ = write!(out, "{id} {model} {} {}", size[0], size[1]);
    for p in params {
        let _ = write!(out, " {p}");
    }
    out.push('\n');
}

/// An image's first `images.txt` line with its newline.
pub(crate) fn image_line(out: &mut String, id: u32, pose: &Pose, camera_id: u32, name: &str) {
    let [qw, qx, qy, qz, tx, ty, tz] = pose.to_colmap();
    let _ = writeln!(
        out,
        "{id} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {camera_id} {name}"
    );
}

/// An image's POINTS2D line with its newline: `X Y POINT3D_ID` per point (`-1`: none).
/// Coordinates print as stored (`f32` from a map prints as the `f32` it is).
pub(crate) fn points2d_line<X: std::fmt::Display>(
    out: &mut String,
    points: impl IntoIterator<Item = ([X; 2], Option<u64>)>,
) {
    for (i, ([x, y], id)) in points.into_iter().enumerate() {
        if i > 0 {
            out.push(' ');
        }
        let _ = match id {
            Some(id) => write!(out, "{x} {y} {id}"),
            None => write!(out, "{x} {y} -1"),
        };
    }
    out.push('\n');
}

/// A `points3D.txt` line with its newline; `track` is `(IMAGE_ID, POINT2D_IDX)` pairs.
pub(crate) fn point3d_line(
    out: &mut String,
    id: u64,
    xyz: [f64; 3],
    rgb: [u8; 3],
    error: f64,
    track: impl IntoIterator<Item = (u32, u32)>,
) {
    let ([x, y, z], [r, g, b]) = (xyz, rgb);
    let _ = write!(out, "{id} {x} {y} {z} {r} {g} {b} {error}");
    for (image_id, point2d_idx) in track {
        let _ = write!(out, " {image_id} {point2d_idx}");
    }
    out.push('\n');
}

/// Encodes `cameras.txt`.
pub fn write_cameras(model: &Reconstruction) -> String {
    let mut out = String::from(CAMERAS_HEADER);
    let _ = writeln!(out, "# Number of cameras: {}", model.cameras().len());
    for c in model.cameras() {
        camera_line(
            &mut out,
            c.id,
            c.model.name(),
            [c.width, c.height],
            &c.params,
        );
    }
    out
}

/// Encodes `images.txt`.
pub fn write_images(model: &Reconstruction) -> String {
    let mut out = String::from(IMAGES_HEADER);
    let _ = writeln!(out, "# Number of images: {}", model.images().len());
    for image in model.images() {
        image_line(
            &mut out,
            image.id,
            &image.cam_from_world,
            image.camera_id,
            &image.name,
        );
        points2d_line(
            &mut out,
            image.points2d.iter().map(|p| (p.xy, p.point3d_id)),
        );
    }
    out
}

/// Encodes `points3D.txt`.
pub fn write_points3d(model: &Reconstruction) -> String {
    let mut out = String::from(POINTS3D_HEADER);
    let _ = writeln!(out, "# Number of points: {}", model.points3d().len());
    for p in model.points3d() {
        let track = model.track(p).iter().map(|e| (e.image_id, e.point2d_idx));
        point3d_line(&mut out, p.id, p.xyz, p.rgb, p.error, track);
    }
    out
}
/// Why `name` cannot be a NAME in `images.txt` (or a MODEL in `cameras.txt`), if it cannot.
/// Refused rather than escaped: COLMAP reads a line up to its newline, trims it and takes
/// each field up to the next space, with no escape syntax, so a control character ends or
/// corrupts the line (a newline injects an image), a space cuts the name short, and an
/// escape would be read back as part of the name.
pub fn text_name_problem(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("is empty")
    } else if has_control_character(name) {
        Some("holds a control character")
    } else if name.bytes().any(|b| b.is_ascii_whitespace()) {
        Some("holds a space")
    } else {
        None
    }
}
