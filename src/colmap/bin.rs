//! COLMAP binary models: `cameras.bin`, `images.bin`, `points3D.bin`.
//!
//! All little-endian, no header or version (COLMAP's `reconstruction_io`):
//!
//! - `cameras.bin`: `u64 n`, then per camera `u32 id, i32 model_id, u64 width, u64 height,
//!   f64 params[num_params(model)]`.
//! - `images.bin`: `u64 n`, then per image `u32 id, f64 qw qx qy qz, f64 tx ty tz,
//!   u32 camera_id, name bytes, 0u8, u64 num_points2D`, then per 2D point
//!   `f64 x, f64 y, u64 point3D_id` (`u64::MAX` = none).
//! - `points3D.bin`: `u64 n`, then per point `u64 id, f64 x y z, u8 r g b, f64 error,
//!   u64 track_length`, then per element `u32 image_id, u32 point2D_idx`.
//!
//! COLMAP ≥ 3.12 adds `rigs.bin` and `frames.bin`; the three files above keep their layout, so
//! the rig files are not read.

use std::path::Path;

use super::error::{Error, Result};
use super::model::{
    has_control_character, image_pose, non_finite_param, non_finite_point2d, non_finite_point3d,
    BadPose, Camera, Image, Point2D, Reconstruction, ReconstructionBuilder, TrackElement,
};
use crate::geometry::{CameraModel, Pose};

/// COLMAP's invalid `point3D_t`.
const INVALID_POINT3D_ID: u64 = u64::MAX;

/// Smallest encoded size of a record, used to cap preallocation from an untrusted count.
const MIN_CAMERA: usize = 4 + 4 + 8 + 8;
pub(crate) const MIN_IMAGE: usize = 4 + 7 * 8 + 4 + 1 + 8;
pub(crate) const POINT2D: usize = 8 + 8 + 8;
pub(crate) const MIN_POINT3D: usize = 8 + 3 * 8 + 3 + 8 + 8;
const TRACK_ELEMENT: usize = 4 + 4;

/// A bounds-checked little-endian reader over a byte slice.
struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
    path: &'a Path,
}

impl<'a> Reader<'a> {
    fn new(data: &'a [u8], path: &'a Path) -> Self {
        Reader { data, pos: 0, path }
    }

    fn remaining(&self) -> usize {
        self.data.len().saturating_sub(self.pos)
    }

    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8]> {
        let bytes = self
            .pos
            .checked_add(n)
            .and_then(|end| self.data.get(self.pos..end))
            .ok_or_else(|| self.truncated(n as u64, what))?;
        self.pos += n;
        Ok(bytes)
    }

    fn truncated(&self, needed: u64, what: &'static str) -> Error {
        Error::Truncated {
            path: self.path.to_path_buf(),
            offset: self.pos as u64,
            needed,
            len: self.data.len() as u64,
            what,
        }
    }

    fn array<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N]> {
        let bytes = self.take(N, what)?;
        let mut out = [0u8; N];
        out.copy_from_slice(bytes);
        Ok(out)
    }

    fn u32(&mut self, what: &'static str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    fn i32(&mut self, what: &'static str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.array(what)?))
    }

    fn u64(&mut self, what: &'static str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    fn f64(&mut self, what: &'static str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }

    fn f64s<const N: usize>(&mut self, what: &'static str) -> Result<[f64; N]> {
        let mut out = [0f64; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }

    /// A record count; also returns how many records to preallocate: never more than the
    /// remaining bytes could hold, so a forged count cannot make us allocate gigabytes.
    fn count(&mut self, record: usize, what: &'static str) -> Result<(u64, usize)> {
        let n = self.u64(what)?;
        let fits = self.remaining() / record.max(1);
        Ok((n, usize::try_from(n).unwrap_or(usize::MAX).min(fits)))
    }

    /// `n` records of `size` bytes as one slice; a count the file cannot hold is a
    /// truncation (the count itself may be any u64).
    fn block(&mut self, n: u64, size: usize, what: &'static str) -> Result<&'a [u8]> {
        let bytes = usize::try_from(n)
            .ok()
            .and_then(|n| n.checked_mul(size))
            .filter(|&b| b <= self.remaining())
            .ok_or_else(|| self.truncated(n.saturating_mul(size as u64), what))?;
        self.take(bytes, what)
    }

    /// An image's pose that [`image_pose`] refuses.
    fn bad_pose(&self, image_id: u32, bad: BadPose) -> Error {
        match bad {
            BadPose::NotFinite(field) => self.not_finite("image", image_id.into(), field),
            BadPose::ZeroRotation => Error::ZeroRotation {
                path: self.path.to_path_buf(),
                line: None,
                image_id,
            },
        }
    }

    /// A NaN or infinite value of record `kind id` (binary files have no line numbers).
    fn not_finite(&self, kind: &'static str, id: u64, field: impl Into<String>) -> Error {
        Error::NotFinite {
            path: self.path.to_path_buf(),
            line: None,
            kind,
            id,
            field: field.into(),
        }
    }

    fn finish(&self) -> Result<()> {
        if self.pos == self.data.len() {
            Ok(())
        } else {
            Err(Error::TrailingBytes {
                path: self.path.to_path_buf(),
                offset: self.pos as u64,
                len: self.data.len() as u64,
            })
        }
    }
}

// Callers pass slices of exactly the right length (from `chunks_exact`), so the conversions
// cannot fail; the fallback keeps them panic-free anyway.
fn le_u32(b: &[u8]) -> u32 {
    u32::from_le_bytes(b.try_into().unwrap_or_default())
}

fn le_u64(b: &[u8]) -> u64 {
    u64::from_le_bytes(b.try_into().unwrap_or_default())
}

fn le_f64(b: &[u8]) -> f64 {
    f64::from_le_bytes(b.try_into().unwrap_or_default())
}

/// Parses `cameras.bin`; `path` only names the file in errors.
pub fn parse_cameras(data: &[u8], path: &Path) -> Result<Vec<Camera>> {
    let mut r = Reader::new(data, path);
    let (n, cap) = r.count(MIN_CAMERA, "camera count")?;
    let mut cameras = Vec::with_capacity(cap);
    for _ in 0..n {
        let id = r.u32("camera id")?;
        let model_id = r.i32("camera model id")?;
        let model = CameraModel::from_id(model_id).ok_or_else(|| Error::UnknownCameraModelId {
            path: path.to_path_buf(),
            camera_id: id,
            model_id: i64::from(model_id),
        })?;
        let width = r.u64("camera width")?;
        let height = r.u64("camera height")?;
        let mut params = Vec::with_capacity(model.num_params());
        for _ in 0..model.num_params() {
            params.push(r.f64("camera parameters")?);
        }
        if let Some(field) = non_finite_param(&params) {
            return Err(r.not_finite("camera", id.into(), field));
        }
        cameras.push(Camera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    r.finish()?;
    Ok(cameras)
}

/// One record of `images.bin`, its 2D points left as bytes (`num_points2D` × 24).
pub(crate) struct ImageRecord<'a> {
    pub id: u32,
    pub name: String,
    pub camera_id: u32,
    pub cam_from_world: Pose,
    pub points2d: &'a [u8],
}

// The fast path of `build::geometry` reads the points as bytes (maps, and its fuzz body).
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
impl ImageRecord<'_> {
    pub fn num_points2d(&self) -> usize {
        self.points2d.len() / POINT2D
    }
}

/// The triangulated 2D points of an image's `points2D` block (as `images.bin` stores it) as
/// `(point2D_idx, xy, point3D_id)`, in order. Indices stop at `u32::MAX` (a track element
/// cannot name more); check the block's count first.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
pub(crate) fn triangulated(points2d: &[u8]) -> impl Iterator<Item = (u32, [f64; 2], u64)> + '_ {
    (0..=u32::MAX)
        .zip(points2d.chunks_exact(POINT2D))
        .filter_map(|(idx, c)| {
            let id = le_u64(&c[16..24]);
            (id != INVALID_POINT3D_ID).then(|| (idx, [le_f64(&c[0..8]), le_f64(&c[8..16])], id))
        })
}

/// Reads `images.bin` one record at a time: the 2D points stay in the file's bytes, so a
/// caller that only needs some of them (convert) copies nothing else.
pub(crate) struct ImageRecords<'a> {
    r: Reader<'a>,
    left: u64,
    /// How many records to preallocate for (bounded by the file's length).
    pub capacity: usize,
}

impl<'a> ImageRecords<'a> {
    pub fn new(data: &'a [u8], path: &'a Path) -> Result<Self> {
        let mut r = Reader::new(data, path);
        let (left, capacity) = r.count(MIN_IMAGE, "image count")?;
        Ok(ImageRecords { r, left, capacity })
    }

    /// Exactly `n` records that are all of `data` (a run of [`record_runs`]).
    #[cfg(any(feature = "colmap", feature = "fuzzing", test))]
    pub fn run(data: &'a [u8], n: u64, path: &'a Path) -> Self {
        ImageRecords {
            r: Reader::new(data, path),
            left: n,
            capacity: 0,
        }
    }

    /// The next record; `None` once all are read and the file is checked to end there.
    pub fn next_record(&mut self) -> Result<Option<ImageRecord<'a>>> {
        if self.left == 0 {
            self.r.finish()?;
            return Ok(None);
        }
        self.left -= 1;
        let r = &mut self.r;
        let id = r.u32("image id")?;
        let rotation = r.f64s::<4>("image rotation")?;
        let translation = r.f64s::<3>("image translation")?;
        let camera_id = r.u32("image camera id")?;
        let name_start = r.pos;
        let rest = r.data.get(name_start..).unwrap_or(&[]);
        let name_len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or_else(|| r.truncated(rest.len() as u64 + 1, "image name"))?;
        let name_bytes = r.take(name_len + 1, "image name")?;
        let name = std::str::from_utf8(&name_bytes[..name_len])
            .map_err(|_| Error::BadValue {
                path: r.path.to_path_buf(),
                offset: name_start as u64,
                what: format!("image {id}: name is not valid utf-8"),
            })?
            .to_string();
        if has_control_character(&name) {
            return Err(Error::BadImageName {
                path: r.path.to_path_buf(),
                line: None,
                image_id: id,
                name: super::error::shown_name(&name),
            });
        }
        let num_points2d = r.u64("image point2D count")?;
        // One bounds check for the whole block, then fixed-size records.
        let points2d = r.block(num_points2d, POINT2D, "image points2D")?;
        // Checked here, where the general reader and convert's fast path both pass, so they
        // accept the same files.
        let cam_from_world =
            image_pose(rotation, translation).map_err(|bad| r.bad_pose(id, bad))?;
        let xys = points2d
            .chunks_exact(POINT2D)
            .map(|c| [le_f64(&c[0..8]), le_f64(&c[8..16])]);
        if let Some(field) = non_finite_point2d(xys) {
            return Err(r.not_finite("image", id.into(), field));
        }
        Ok(Some(ImageRecord {
            id,
            name,
            camera_id,
            cam_from_world,
            points2d,
        }))
    }
}

/// Parses `images.bin`.
pub fn parse_images(data: &[u8], path: &Path) -> Result<Vec<Image>> {
    let mut records = ImageRecords::new(data, path)?;
    let mut images = Vec::with_capacity(records.capacity);
    while let Some(record) = records.next_record()? {
        let points2d = record
            .points2d
            .chunks_exact(POINT2D)
            .map(|c| {
                let point3d_id = le_u64(&c[16..24]);
                Point2D {
                    xy: [le_f64(&c[0..8]), le_f64(&c[8..16])],
                    point3d_id: (point3d_id != INVALID_POINT3D_ID).then_some(point3d_id),
                }
            })
            .collect();
        images.push(Image {
            id: record.id,
            name: record.name,
            camera_id: record.camera_id,
            cam_from_world: record.cam_from_world,
            points2d,
        });
    }
    Ok(images)
}

/// One record of `points3D.bin`, its track left as bytes (`track_length` × 8).
pub(crate) struct Point3DRecord<'a> {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
    track: &'a [u8],
}

impl Point3DRecord<'_> {
    #[cfg(any(feature = "colmap", feature = "fuzzing", test))]
    pub fn track_len(&self) -> usize {
        self.track.len() / TRACK_ELEMENT
    }

    pub fn track(&self) -> impl Iterator<Item = TrackElement> + '_ {
        self.track
            .chunks_exact(TRACK_ELEMENT)
            .map(|c| TrackElement {
                image_id: le_u32(&c[0..4]),
                point2d_idx: le_u32(&c[4..8]),
            })
    }
}

/// Reads `points3D.bin` one record at a time (see [`ImageRecords`]).
pub(crate) struct Point3DRecords<'a> {
    r: Reader<'a>,
    left: u64,
    /// How many points to preallocate for (bounded by the file's length).
    pub capacity: usize,
    /// How many track elements to preallocate for.
    pub track_capacity: usize,
}

impl<'a> Point3DRecords<'a> {
    /// Exactly `n` records that are all of `data` (a run of [`record_runs`]).
    #[cfg(any(feature = "colmap", feature = "fuzzing", test))]
    pub fn run(data: &'a [u8], n: u64, path: &'a Path) -> Self {
        Point3DRecords {
            r: Reader::new(data, path),
            left: n,
            capacity: 0,
            track_capacity: 0,
        }
    }

    pub fn new(data: &'a [u8], path: &'a Path) -> Result<Self> {
        let mut r = Reader::new(data, path);
        let (left, capacity) = r.count(MIN_POINT3D, "point3D count")?;
        // Typical tracks are a few elements long; reserving up to 8 per point avoids most
        // regrowth without trusting the file's count beyond what its length can hold.
        let track_capacity = (r.remaining().saturating_sub(capacity * MIN_POINT3D) / TRACK_ELEMENT)
            .min(capacity * 8);
        Ok(Point3DRecords {
            r,
            left,
            capacity,
            track_capacity,
        })
    }

    /// The next record; `None` once all are read and the file is checked to end there.
    pub fn next_record(&mut self) -> Result<Option<Point3DRecord<'a>>> {
        if self.left == 0 {
            self.r.finish()?;
            return Ok(None);
        }
        self.left -= 1;
        let r = &mut self.r;
        let id = r.u64("point3D id")?;
        let xyz = r.f64s::<3>("point3D position")?;
        let rgb = r.array::<3>("point3D color")?;
        let error = r.f64("point3D error")?;
        if let Some(field) = non_finite_point3d(&xyz, error) {
            return Err(r.not_finite("point3D", id, field));
        }
        let len = r.u64("point3D track length")?;
        let track = r.block(len, TRACK_ELEMENT, "point3D track")?;
        Ok(Some(Point3DRecord {
            id,
            xyz,
            rgb,
            error,
            track,
        }))
    }
}

/// Parses `points3D.bin` into `builder`.
pub(crate) fn parse_points3d_into(
    data: &[u8],
    path: &Path,
    builder: &mut ReconstructionBuilder,
) -> Result<()> {
    let mut records = Point3DRecords::new(data, path)?;
    builder.reserve_points3d(records.capacity, records.track_capacity);
    while let Some(point) = records.next_record()? {
        let start = builder.begin_point3d();
        for element in point.track() {
            builder.push_track(element);
        }
        builder.end_point3d(start, point.id, point.xyz, point.rgb, point.error)?;
    }
    Ok(())
}

/// Parses and validates the three files of a binary model given as bytes.
pub fn parse_model(
    cameras: (&[u8], &Path),
    images: (&[u8], &Path),
    points3d: (&[u8], &Path),
) -> Result<Reconstruction> {
    super::parse_with(&super::BIN, cameras, images, points3d)
}

/// Encodes `cameras.bin`.
pub fn write_cameras(model: &Reconstruction) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&(model.cameras().len() as u64).to_le_bytes());
    for c in model.cameras() {
        encode_camera(c, &mut out);
    }
    out
}

/// Appends one `cameras.bin` record (the file is a u64 count, then the records).
pub fn encode_camera(c: &super::Camera, out: &mut Vec<u8>) {
    out.extend_from_slice(&c.id.to_le_bytes());
    out.extend_from_slice(&c.model.id().to_le_bytes());
    out.extend_from_slice(&c.width.to_le_bytes());
    out.extend_from_slice(&c.height.to_le_bytes());
    for p in &c.params {
        out.extend_from_slice(&p.to_le_bytes());
    }
}

/// Encodes `images.bin`.
pub fn write_images(model: &Reconstruction) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&(model.images().len() as u64).to_le_bytes());
    for image in model.images() {
        encode_image(image, &mut out);
    }
    out
}

/// Appends one `images.bin` record (the file is a u64 count, then the records): what a
/// writer that streams a model image by image writes.
pub fn encode_image(image: &super::Image, out: &mut Vec<u8>) {
    out.extend_from_slice(&image.id.to_le_bytes());
    for v in image.cam_from_world.to_colmap() {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&image.camera_id.to_le_bytes());
    out.extend_from_slice(image.name.as_bytes());
    out.push(0);
    out.extend_from_slice(&(image.points2d.len() as u64).to_le_bytes());
    for p in &image.points2d {
        out.extend_from_slice(&p.xy[0].to_le_bytes());
        out.extend_from_slice(&p.xy[1].to_le_bytes());
        let id = p.point3d_id.unwrap_or(INVALID_POINT3D_ID);
        out.extend_from_slice(&id.to_le_bytes());
    }
}

/// Encodes `points3D.bin`.
pub fn write_points3d(model: &Reconstruction) -> Vec<u8> {
    let mut out = Vec::with_capacity(
        8 + model.points3d().len() * MIN_POINT3D + model.num_observations() * TRACK_ELEMENT,
    );
    out.extend_from_slice(&(model.points3d().len() as u64).to_le_bytes());
    for p in model.points3d() {
        encode_point3d(p.id, p.xyz, p.rgb, p.error, model.track(p), &mut out);
    }
    out
}

/// Appends one `points3D.bin` record (the file is a u64 count, then the records).
pub fn encode_point3d(
    id: u64,
    xyz: [f64; 3],
    rgb: [u8; 3],
    error: f64,
    track: &[super::TrackElement],
    out: &mut Vec<u8>,
) {
    out.extend_from_slice(&id.to_le_bytes());
    for v in &xyz {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&rgb);
    out.extend_from_slice(&error.to_le_bytes());
    out.extend_from_slice(&(track.len() as u64).to_le_bytes());
    for e in track {
        out.extend_from_slice(&e.image_id.to_le_bytes());
        out.extend_from_slice(&e.point2d_idx.to_le_bytes());
    }
}

/// Bytes of a binary model file: an open file, or bytes in memory (the fuzz body).
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
#[derive(Clone, Copy)]
pub(crate) enum ModelBytes<'a> {
    #[cfg_attr(not(feature = "colmap"), allow(dead_code))]
    File(&'a std::fs::File, u64),
    #[cfg_attr(not(any(test, feature = "fuzzing")), allow(dead_code))]
    Memory(&'a [u8]),
}

#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
impl ModelBytes<'_> {
    pub fn len(&self) -> u64 {
        match self {
            ModelBytes::File(_, len) => *len,
            ModelBytes::Memory(b) => b.len() as u64,
        }
    }

    /// `out.len()` bytes at `offset`; `None` past the end or on a read error.
    pub fn read_at(&self, out: &mut [u8], offset: u64) -> Option<()> {
        match self {
            ModelBytes::File(file, _) => crate::format::read_at(file, out, offset).ok(),
            ModelBytes::Memory(b) => {
                let start = usize::try_from(offset).ok()?;
                out.copy_from_slice(b.get(start..start.checked_add(out.len())?)?);
                Some(())
            }
        }
    }
}

/// How [`record_runs`] reads a file.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
#[derive(Debug, Clone, Copy)]
pub(crate) struct Runs {
    /// Bytes read at once (a record longer than this is read whole).
    pub block: usize,
    /// The longest record taken: past it, or a header not complete within it, the reader
    /// declines, and the general reader judges the file.
    pub max_record: u64,
}

#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
impl Runs {
    /// 16 MiB blocks; records up to 64 MiB (an image of 2.8 M 2D points, a track of 8 M
    /// elements).
    pub const DEFAULT: Runs = Runs {
        block: 16 << 20,
        max_record: 64 << 20,
    };
}

/// The length of the `images.bin` record at the start of `b`, once `b` holds its header.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
pub(crate) fn image_record_len(b: &[u8]) -> Option<u64> {
    const FIXED: usize = 4 + 7 * 8 + 4;
    let name = b.get(FIXED..)?.iter().position(|&c| c == 0)?;
    let count = b.get(FIXED + name + 1..FIXED + name + 9)?;
    let points = le_u64(count).checked_mul(POINT2D as u64)?;
    points.checked_add((FIXED + name + 9) as u64)
}

/// The length of the `points3D.bin` record at the start of `b`, once `b` holds its header.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
pub(crate) fn point3d_record_len(b: &[u8]) -> Option<u64> {
    let count = b.get(MIN_POINT3D - 8..MIN_POINT3D)?;
    let track = le_u64(count).checked_mul(TRACK_ELEMENT as u64)?;
    track.checked_add(MIN_POINT3D as u64)
}

/// Reads a binary model file (a u64 record count, then the records) `runs.block` bytes at a
/// time and
/// calls `f(run, records, offset)` with runs of whole records and where each run starts in
/// the file, so that no more than a block (or one record) of the file is held at once.
/// `record_len` says how long the record at the start of its bytes is, or `None` while
/// they do not hold its header yet. Returns the record count; `None` (a file the general
/// reader must judge) where a record runs past the end, the file is longer than its
/// records, or `f` says `None`.
#[cfg(any(feature = "colmap", feature = "fuzzing", test))]
pub(crate) fn record_runs(
    bytes: ModelBytes<'_>,
    runs: Runs,
    record_len: impl Fn(&[u8]) -> Option<u64>,
    mut f: impl FnMut(&[u8], u64, u64) -> Option<()>,
) -> Option<u64> {
    let (block, max_record) = (runs.block.max(1), runs.max_record);
    let file_len = bytes.len();
    let mut count = [0u8; 8];
    bytes.read_at(&mut count, 0)?;
    let count = le_u64(&count);
    let mut left = count;
    // `buf[..filled]` holds the file from `at`; `next` is where reading goes on.
    let mut buf = vec![0u8; block.max(1).min(file_len as usize)];
    let (mut at, mut filled) = (8u64, 0usize);
    let mut next = 8u64;
    while left > 0 {
        // Whole records from the start of the buffer.
        let (mut pos, mut n) = (0usize, 0u64);
        while n < left {
            let Some(len) = record_len(&buf[pos..filled]) else {
                break;
            };
            if len > file_len - (at + pos as u64) || len > max_record {
                return None;
            }
            if pos as u64 + len > filled as u64 {
                break;
            }
            pos += len as usize;
            n += 1;
        }
        if n > 0 {
            f(&buf[..pos], n, at)?;
            left -= n;
            buf.copy_within(pos..filled, 0);
            filled -= pos;
            // Back to a block once a long record is through.
            if buf.len() > block && filled <= block {
                buf.truncate(block.max(1));
                buf.shrink_to_fit();
            }
            at += pos as u64;
            next = at + filled as u64;
            continue;
        }
        // The next record does not fit what is held: read on, the buffer grown to a record
        // longer than it (bounded by the file's length, checked above).
        if next >= file_len {
            return None;
        }
        if filled == buf.len() {
            if filled as u64 >= max_record {
                return None; // a header that never ends
            }
            let want = record_len(&buf[..filled]).map_or(buf.len() * 2, |l| l as usize);
            buf.resize(want.max(buf.len() * 2).min((file_len - at) as usize), 0);
        }
        let n = (buf.len() - filled).min((file_len - next) as usize);
        bytes.read_at(&mut buf[filled..filled + n], next)?;
        filled += n;
        next += n as u64;
    }
    // Bytes past the last record: the general reader names them.
    (filled == 0 && next == file_len).then_some(count)
}
