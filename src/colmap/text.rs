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
use crate::geometry::CameraModel;

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

    /// A NaN or infinite value (Rust's parser, like COLMAP's `stold`, reads `nan`, `inf` and
    /// overflows such as `1e400`), named by line and record.
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

/// Encodes `cameras.txt`.
pub fn write_cameras(model: &Reconstruction) -> String {
    let mut out = String::new();
    out.push_str("# Camera list with one line of data per camera:\n");
    out.push_str("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let _ = writeln!(out, "# Number of cameras: {}", model.cameras().len());
    for c in model.cameras() {
        let _ = write!(out, "{} {} {} {}", c.id, c.model.name(), c.width, c.height);
        for p in &c.params {
            let _ = write!(out, " {p}");
        }
        out.push('\n');
    }
    out
}

/// Encodes `images.txt`.
pub fn write_images(model: &Reconstruction) -> String {
    let mut out = String::new();
    out.push_str("# Image list with two lines of data per image:\n");
    out.push_str("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    out.push_str("#   POINTS2D[] as (X, Y, POINT3D_ID)\n");
    let _ = writeln!(out, "# Number of images: {}", model.images().len());
    for image in model.images() {
        let [qw, qx, qy, qz, tx, ty, tz] = image.cam_from_world.to_colmap();
        let _ = writeln!(
            out,
            "{} {qw} {qx} {qy} {qz} {tx} {ty} {tz} {} {}",
            image.id, image.camera_id, image.name
        );
        for (i, p) in image.points2d.iter().enumerate() {
            if i > 0 {
                out.push(' ');
            }
            let _ = match p.point3d_id {
                Some(id) => write!(out, "{} {} {id}", p.xy[0], p.xy[1]),
                None => write!(out, "{} {} -1", p.xy[0], p.xy[1]),
            };
        }
        out.push('\n');
    }
    out
}

/// Encodes `points3D.txt`.
pub fn write_points3d(model: &Reconstruction) -> String {
    let mut out = String::new();
    out.push_str("# 3D point list with one line of data per point:\n");
    out.push_str("#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n");
    let _ = writeln!(out, "# Number of points: {}", model.points3d().len());
    for p in model.points3d() {
        let [x, y, z] = p.xyz;
        let [r, g, b] = p.rgb;
        let _ = write!(out, "{} {x} {y} {z} {r} {g} {b} {}", p.id, p.error);
        for e in model.track(p) {
            let _ = write!(out, " {} {}", e.image_id, e.point2d_idx);
        }
        out.push('\n');
    }
    out
}
