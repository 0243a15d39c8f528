//! The in-memory COLMAP reconstruction and its consistency checks.
//!
//! Layout: cameras, images and 3D points are `Vec`s sorted by id (lookups binary-search them),
//! and all tracks live in one flat array that each [`Point3D`] indexes into. Why: a converted
//! model can have a million points with tracks of ~5, and one `Vec` per track would be a million
//! small allocations; the flat array is one allocation and 8 bytes per observation.

use std::path::{Path, PathBuf};

use super::error::{Error, Result};
use crate::geometry::{CameraModel, Pose};

/// A camera: intrinsics in COLMAP's parameter order for its model.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// `camera_id`.
    pub id: u32,
    /// The camera model, which fixes the parameters' meaning and order.
    pub model: CameraModel,
    /// Image width in pixels.
    pub width: u64,
    /// Image height in pixels.
    pub height: u64,
    /// `model.num_params()` values; the reader checks the count.
    pub params: Vec<f64>,
}

/// A 2D feature observation in an image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point2D {
    /// Pixel coordinates; COLMAP puts the centre of the top-left pixel at (0.5, 0.5).
    pub xy: [f64; 2],
    /// The 3D point this observation belongs to, `None` if it is not triangulated (stored as
    /// `u64::MAX` in `.bin` files and `-1` in `.txt` files).
    pub point3d_id: Option<u64>,
}

/// A registered image.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// `image_id`.
    pub id: u32,
    /// The file name, relative to the images folder.
    pub name: String,
    /// The camera it was taken with.
    pub camera_id: u32,
    /// As stored, up to [`Pose::from_colmap`]'s normalisation of a non-unit quaternion.
    pub cam_from_world: Pose,
    /// Index `i` here is the `point2D_idx` of track elements (and, for COLMAP-written models,
    /// the keypoint row in `database.db`).
    pub points2d: Vec<Point2D>,
}

/// One observation of a 3D point: the `point2d_idx`-th 2D point of image `image_id`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct TrackElement {
    /// The image.
    pub image_id: u32,
    /// The index of the 2D point in the image's `points2d`.
    pub point2d_idx: u32,
}

/// A 3D point. Its track is [`Reconstruction::track`].
///
/// Equality compares the public fields and the track length, not where the track is stored.
#[derive(Debug, Clone, Copy)]
pub struct Point3D {
    /// `point3D_id`.
    pub id: u64,
    /// Position in world coordinates.
    pub xyz: [f64; 3],
    /// Colour, 8-bit RGB.
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels, as COLMAP stored it.
    pub error: f64,
    track_start: usize,
    track_len: u32,
}

impl PartialEq for Point3D {
    fn eq(&self, other: &Self) -> bool {
        self.id == other.id
            && self.xyz == other.xyz
            && self.rgb == other.rgb
            && self.error == other.error
            && self.track_len == other.track_len
    }
}

// Value checks shared by the readers (which report file and line or record) and the
// builder (for models built by hand). Why refuse non-finite numbers at all: a map keeps
// camera parameters and its origin in JSON, which has no NaN or infinity, so such a model
// would convert into a map that does not open.

/// The first camera parameter that is NaN or infinite, as `"parameter {index}"`.
pub(crate) fn non_finite_param(params: &[f64]) -> Option<String> {
    let i = params.iter().position(|p| !p.is_finite())?;
    Some(format!("parameter {i}"))
}

/// What is wrong with an image's stored pose.
pub(crate) enum BadPose {
    /// This part (`"rotation"`, `"translation"`) holds a NaN or infinity.
    NotFinite(&'static str),
    /// The rotation is the zero quaternion, which is no rotation.
    ZeroRotation,
}

/// An image's `cam_from_world` from its stored `qw qx qy qz` and `tx ty tz`.
pub(crate) fn image_pose(rotation: [f64; 4], translation: [f64; 3]) -> Result<Pose, BadPose> {
    if !rotation.iter().all(|v| v.is_finite()) {
        return Err(BadPose::NotFinite("rotation"));
    }
    if !translation.iter().all(|v| v.is_finite()) {
        return Err(BadPose::NotFinite("translation"));
    }
    let [qw, qx, qy, qz] = rotation;
    let [tx, ty, tz] = translation;
    Pose::from_colmap(qw, qx, qy, qz, tx, ty, tz).map_err(|_| BadPose::ZeroRotation)
}

/// The first 2D point of `xys` (in order) with a NaN or infinite coordinate.
pub(crate) fn non_finite_point2d(xys: impl Iterator<Item = [f64; 2]>) -> Option<String> {
    let i = xys
        .into_iter()
        .position(|xy| !(xy[0].is_finite() && xy[1].is_finite()))?;
    Some(format!("point2D {i} position"))
}

/// Which value of a 3D point is NaN or infinite, if any.
pub(crate) fn non_finite_point3d(xyz: &[f64; 3], error: f64) -> Option<&'static str> {
    if !xyz.iter().all(|v| v.is_finite()) {
        Some("position")
    } else if !error.is_finite() {
        Some("error")
    } else {
        None
    }
}

/// Whether an image name holds a control character (U+0000–U+001F, U+007F–U+009F: a
/// newline, a tab, an escape). Such a name is refused: COLMAP's `images.txt` is one image a
/// line, so it cannot hold one, and it would inject lines into every line-based export.
pub(crate) fn has_control_character(name: &str) -> bool {
    name.chars().any(char::is_control)
}

impl Point3D {
    /// Number of observations.
    pub fn track_len(&self) -> usize {
        self.track_len as usize
    }
}

/// A validated COLMAP reconstruction (cameras, registered images, 3D points with tracks).
///
/// Built by the readers or by [`ReconstructionBuilder`]; every instance has passed
/// [`ReconstructionBuilder::build`]'s checks, so tracks and 2D points agree.
///
/// Equality compares content (each point's track, not the flat array's order).
#[derive(Debug, Clone)]
pub struct Reconstruction {
    cameras: Vec<Camera>,
    images: Vec<Image>,
    points3d: Vec<Point3D>,
    tracks: Vec<TrackElement>,
    image_slots: IdIndex,
    point3d_slots: IdIndex,
}

/// Id → position for ids that are dense enough (COLMAP numbers from 1 and leaves few gaps):
/// `slots[id]` is the position or `u32::MAX`. Why: convert looks up an image and a point per
/// observation (millions), and a table read is several times faster than a binary search
/// there. Sparse ids leave the table empty and lookups fall back to binary search.
#[derive(Debug, Clone, Default)]
pub(crate) struct IdIndex {
    slots: Vec<u32>,
}

impl IdIndex {
    const ABSENT: u32 = u32::MAX;

    /// `ids` sorted ascending and unique; an empty (search-only) index if they are sparse.
    fn new(ids: impl ExactSizeIterator<Item = u64> + Clone) -> IdIndex {
        // At most ~2 slots per entry (4 bytes each).
        let max_slots = ids.len().saturating_mul(2).saturating_add(1024);
        IdIndex::dense(ids, max_slots).unwrap_or_default()
    }

    /// A table for `ids` (sorted ascending and unique), or `None` if it would need more than
    /// `max_slots` slots or the positions do not fit u32.
    pub(crate) fn dense(
        ids: impl ExactSizeIterator<Item = u64> + Clone,
        max_slots: usize,
    ) -> Option<IdIndex> {
        let len = ids.len();
        let max = ids.clone().last().unwrap_or(0);
        let fits = u32::try_from(len).is_ok_and(|n| n < IdIndex::ABSENT)
            && usize::try_from(max).is_ok_and(|m| m < max_slots);
        if !fits {
            return None;
        }
        let mut slots = vec![IdIndex::ABSENT; max as usize + 1];
        for (position, id) in ids.enumerate() {
            slots[id as usize] = position as u32;
        }
        Some(IdIndex { slots })
    }

    /// `Some(answer)` if the table decides, `None` to fall back to a search.
    fn get(&self, id: u64) -> Option<Option<usize>> {
        if self.slots.is_empty() {
            return None;
        }
        Some(self.position(id))
    }

    /// The position of `id`, for an index made by [`dense`](Self::dense).
    #[inline]
    pub(crate) fn position(&self, id: u64) -> Option<usize> {
        let slot = usize::try_from(id).ok().and_then(|i| self.slots.get(i))?;
        (*slot != IdIndex::ABSENT).then_some(*slot as usize)
    }
}

impl PartialEq for Reconstruction {
    fn eq(&self, other: &Self) -> bool {
        self.cameras == other.cameras
            && self.images == other.images
            && self.points3d == other.points3d
            && self
                .points3d
                .iter()
                .zip(&other.points3d)
                .all(|(a, b)| self.track(a) == other.track(b))
    }
}

impl Reconstruction {
    /// Cameras sorted by id.
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// Images sorted by id.
    pub fn images(&self) -> &[Image] {
        &self.images
    }

    /// 3D points sorted by id.
    pub fn points3d(&self) -> &[Point3D] {
        &self.points3d
    }

    /// The track of `point` (a point of this reconstruction).
    pub fn track(&self, point: &Point3D) -> &[TrackElement] {
        // The builder checked every range, so this only fails for a point from another
        // reconstruction; an empty track is the harmless answer then.
        let end = point.track_start.saturating_add(point.track_len as usize);
        self.tracks.get(point.track_start..end).unwrap_or(&[])
    }

    /// Total number of observations (sum of track lengths).
    pub fn num_observations(&self) -> usize {
        self.tracks.len()
    }

    /// The camera with id `id`.
    pub fn camera(&self, id: u32) -> Option<&Camera> {
        let i = self.cameras.binary_search_by_key(&id, |c| c.id).ok()?;
        self.cameras.get(i)
    }

    /// The image with id `id`.
    pub fn image(&self, id: u32) -> Option<&Image> {
        self.image_index(id).and_then(|i| self.images.get(i))
    }

    /// Position of image `id` in [`images`](Self::images).
    pub fn image_index(&self, id: u32) -> Option<usize> {
        self.image_slots
            .get(u64::from(id))
            .unwrap_or_else(|| self.images.binary_search_by_key(&id, |c| c.id).ok())
    }

    /// The 3D point with id `id`.
    pub fn point3d(&self, id: u64) -> Option<&Point3D> {
        self.point3d_index(id).and_then(|i| self.points3d.get(i))
    }

    /// Position of 3D point `id` in [`points3d`](Self::points3d).
    pub fn point3d_index(&self, id: u64) -> Option<usize> {
        self.point3d_slots
            .get(id)
            .unwrap_or_else(|| self.points3d.binary_search_by_key(&id, |p| p.id).ok())
    }

    /// An empty builder to assemble a reconstruction by hand (tests, generators, exporters).
    pub fn builder() -> ReconstructionBuilder {
        ReconstructionBuilder::new()
    }
}

/// Collects cameras, images and points in any order, then sorts and validates them.
#[derive(Debug, Clone)]
pub struct ReconstructionBuilder {
    cameras: Vec<Camera>,
    images: Vec<Image>,
    points3d: Vec<Point3D>,
    tracks: Vec<TrackElement>,
    cameras_path: PathBuf,
    images_path: PathBuf,
    points3d_path: PathBuf,
}

impl Default for ReconstructionBuilder {
    fn default() -> Self {
        Self::new()
    }
}

impl ReconstructionBuilder {
    /// An empty builder; errors name the files `cameras`, `images` and `points3D`.
    pub fn new() -> Self {
        ReconstructionBuilder {
            cameras: Vec::new(),
            images: Vec::new(),
            points3d: Vec::new(),
            tracks: Vec::new(),
            cameras_path: PathBuf::from("cameras"),
            images_path: PathBuf::from("images"),
            points3d_path: PathBuf::from("points3D"),
        }
    }

    /// Sets the file names that validation errors report.
    pub fn paths(mut self, cameras: &Path, images: &Path, points3d: &Path) -> Self {
        self.cameras_path = cameras.to_path_buf();
        self.images_path = images.to_path_buf();
        self.points3d_path = points3d.to_path_buf();
        self
    }

    /// Moves the 3D points and tracks of `other` (a builder that parsed only points3D) in.
    pub(crate) fn take_points3d(&mut self, other: ReconstructionBuilder) {
        if self.points3d.is_empty() && self.tracks.is_empty() {
            // The usual case: move, not copy, the (large) arrays.
            self.points3d = other.points3d;
            self.tracks = other.tracks;
            return;
        }
        let offset = self.tracks.len();
        self.tracks.extend(other.tracks);
        self.points3d
            .extend(other.points3d.into_iter().map(|mut p| {
                p.track_start += offset;
                p
            }));
    }

    /// Reserves room for `points` 3D points with `observations` track elements in total.
    pub fn reserve_points3d(&mut self, points: usize, observations: usize) {
        self.points3d.reserve(points);
        self.tracks.reserve(observations);
    }

    /// Adds a camera (ids are checked by [`ReconstructionBuilder::build`]).
    pub fn add_camera(&mut self, camera: Camera) {
        self.cameras.push(camera);
    }

    /// Adds an image (its camera and 2D points are checked by `build`).
    pub fn add_image(&mut self, image: Image) {
        self.images.push(image);
    }

    /// Adds a 3D point with its track.
    pub fn add_point3d(
        &mut self,
        id: u64,
        xyz: [f64; 3],
        rgb: [u8; 3],
        error: f64,
        track: &[TrackElement],
    ) -> Result<()> {
        let start = self.begin_point3d();
        self.tracks.extend_from_slice(track);
        self.end_point3d(start, id, xyz, rgb, error)
    }

    /// Starts a point whose track the caller pushes with [`push_track`](Self::push_track);
    /// returns the track start to give [`end_point3d`](Self::end_point3d). Lets the parsers
    /// append track elements straight into the flat array.
    pub(crate) fn begin_point3d(&self) -> usize {
        self.tracks.len()
    }

    pub(crate) fn push_track(&mut self, element: TrackElement) {
        self.tracks.push(element);
    }

    pub(crate) fn end_point3d(
        &mut self,
        track_start: usize,
        id: u64,
        xyz: [f64; 3],
        rgb: [u8; 3],
        error: f64,
    ) -> Result<()> {
        let len = self.tracks.len().saturating_sub(track_start);
        let track_len = u32::try_from(len).map_err(|_| Error::BadValue {
            path: self.points3d_path.clone(),
            offset: 0,
            what: format!("point3D {id}: track of {len} elements is too long"),
        })?;
        self.points3d.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track_start,
            track_len,
        });
        Ok(())
    }

    /// Sorts by id and checks the model the way COLMAP does when it loads one, plus the
    /// reverse direction: ids are unique; parameter counts match the camera model; images
    /// refer to existing cameras; every track element names an existing image and 2D point
    /// whose `point3D_id` is the point's id, at most once; every 2D point with a `point3D_id`
    /// is in that point's track. Also every number is finite and no image name holds a
    /// control character (the readers check both as they parse, naming the line or record).
    /// The first problem (in input order) is the error.
    pub fn build(mut self) -> Result<Reconstruction> {
        self.check_values()?;
        self.cameras.sort_by_key(|c| c.id);
        if let Some(w) = self.cameras.windows(2).find(|w| w[0].id == w[1].id) {
            return Err(Error::DuplicateId {
                path: self.cameras_path,
                kind: "camera",
                id: u64::from(w[0].id),
            });
        }
        for camera in &self.cameras {
            if camera.params.len() != camera.model.num_params() {
                return Err(Error::ParamCount {
                    path: self.cameras_path,
                    camera_id: camera.id,
                    model: camera.model.name(),
                    expected: camera.model.num_params(),
                    found: camera.params.len(),
                });
            }
        }
        for image in &self.images {
            if self
                .cameras
                .binary_search_by_key(&image.camera_id, |c| c.id)
                .is_err()
            {
                return Err(Error::MissingCamera {
                    path: self.images_path,
                    image_id: image.id,
                    camera_id: image.camera_id,
                });
            }
        }
        self.images.sort_by_key(|i| i.id);
        if let Some(w) = self.images.windows(2).find(|w| w[0].id == w[1].id) {
            return Err(Error::DuplicateId {
                path: self.images_path,
                kind: "image",
                id: u64::from(w[0].id),
            });
        }
        let image_slots = IdIndex::new(self.images.iter().map(|i| u64::from(i.id)));
        self.check_tracks(&image_slots)?;
        self.points3d.sort_unstable_by_key(|p| p.id);
        if let Some(w) = self.points3d.windows(2).find(|w| w[0].id == w[1].id) {
            return Err(Error::DuplicateId {
                path: self.points3d_path,
                kind: "point3D",
                id: w[0].id,
            });
        }
        let point3d_slots = IdIndex::new(self.points3d.iter().map(|p| p.id));
        Ok(Reconstruction {
            cameras: self.cameras,
            images: self.images,
            points3d: self.points3d,
            tracks: self.tracks,
            image_slots,
            point3d_slots,
        })
    }

    /// Finite numbers and names without control characters (see [`non_finite_param`] and
    /// [`has_control_character`] for why).
    fn check_values(&self) -> Result<()> {
        let not_finite = |path: &PathBuf, kind, id, field: String| Error::NotFinite {
            path: path.clone(),
            line: None,
            kind,
            id,
            field,
        };
        for c in &self.cameras {
            if let Some(field) = non_finite_param(&c.params) {
                return Err(not_finite(&self.cameras_path, "camera", c.id.into(), field));
            }
        }
        for image in &self.images {
            let id = u64::from(image.id);
            let [qw, qx, qy, qz, tx, ty, tz] = image.cam_from_world.to_colmap();
            match image_pose([qw, qx, qy, qz], [tx, ty, tz]) {
                Ok(_) => {}
                Err(BadPose::NotFinite(field)) => {
                    return Err(not_finite(&self.images_path, "image", id, field.into()))
                }
                Err(BadPose::ZeroRotation) => {
                    return Err(Error::ZeroRotation {
                        path: self.images_path.clone(),
                        line: None,
                        image_id: image.id,
                    })
                }
            }
            if has_control_character(&image.name) {
                return Err(Error::BadImageName {
                    path: self.images_path.clone(),
                    line: None,
                    image_id: image.id,
                    name: super::error::shown_name(&image.name),
                });
            }
            if let Some(field) = non_finite_point2d(image.points2d.iter().map(|p| p.xy)) {
                return Err(not_finite(&self.images_path, "image", id, field));
            }
        }
        for p in &self.points3d {
            if let Some(field) = non_finite_point3d(&p.xyz, p.error) {
                return Err(not_finite(
                    &self.points3d_path,
                    "point3D",
                    p.id,
                    field.into(),
                ));
            }
        }
        Ok(())
    }

    /// Track → 2D point direction. A fast pass checks image by image (each image's 2D points
    /// stay in cache instead of one random read per observation); only if it finds a problem
    /// does the exact pass run, in input order, so the error reported matches COLMAP's.
    fn check_tracks(&self, image_slots: &IdIndex) -> Result<()> {
        if self.tracks_consistent(image_slots) {
            return Ok(());
        }
        self.check_tracks_in_order(image_slots)
    }

    /// Whether every track element names an existing image and 2D point carrying the point's
    /// id, each 2D point at most once, and every 2D point with an id is in a track.
    fn tracks_consistent(&self, image_slots: &IdIndex) -> bool {
        let n_images = self.images.len();
        let image_of = |id: u32| {
            image_slots
                .get(u64::from(id))
                .unwrap_or_else(|| self.images.binary_search_by_key(&id, |i| i.id).ok())
        };
        // Counting sort of (point2D index, point3D id) by image.
        let mut counts = vec![0usize; n_images + 1];
        for e in &self.tracks {
            match image_of(e.image_id) {
                Some(i) => counts[i + 1] += 1,
                None => return false,
            }
        }
        for i in 0..n_images {
            counts[i + 1] += counts[i];
        }
        let mut next = counts.clone();
        let mut by_image = vec![(0u32, 0u64); self.tracks.len()];
        for point in &self.points3d {
            let end = point.track_start.saturating_add(point.track_len as usize);
            for e in self.tracks.get(point.track_start..end).unwrap_or(&[]) {
                let Some(i) = image_of(e.image_id) else {
                    return false;
                };
                by_image[next[i]] = (e.point2d_idx, point.id);
                next[i] += 1;
            }
        }
        let mut seen = Vec::new();
        for (i, image) in self.images.iter().enumerate() {
            seen.clear();
            seen.resize(image.points2d.len(), false);
            for &(idx, id) in &by_image[counts[i]..counts[i + 1]] {
                match image.points2d.get(idx as usize) {
                    Some(p) if p.point3d_id == Some(id) && !seen[idx as usize] => {
                        seen[idx as usize] = true
                    }
                    _ => return false,
                }
            }
            let referenced = image
                .points2d
                .iter()
                .filter(|p| p.point3d_id.is_some())
                .count();
            if referenced != counts[i + 1] - counts[i] {
                return false;
            }
        }
        true
    }

    /// Track → 2D point direction, in input order so the first error matches COLMAP's.
    fn check_tracks_in_order(&self, image_slots: &IdIndex) -> Result<()> {
        // One bit per 2D point of every image (in sorted image order) marks "seen in a track".
        let mut offsets = Vec::with_capacity(self.images.len());
        let mut total = 0usize;
        for image in &self.images {
            offsets.push(total);
            total = total.saturating_add(image.points2d.len());
        }
        let mut seen = vec![0u64; total.div_ceil(64)];
        for point in &self.points3d {
            let end = point.track_start.saturating_add(point.track_len as usize);
            let track = self.tracks.get(point.track_start..end).unwrap_or(&[]);
            for element in track {
                let found = image_slots
                    .get(u64::from(element.image_id))
                    .unwrap_or_else(|| {
                        self.images
                            .binary_search_by_key(&element.image_id, |i| i.id)
                            .ok()
                    });
                let index = found.ok_or_else(|| Error::TrackImageMissing {
                    path: self.points3d_path.clone(),
                    point3d_id: point.id,
                    image_id: element.image_id,
                })?;
                let image = &self.images[index];
                let idx = element.point2d_idx as usize;
                let Some(point2d) = image.points2d.get(idx) else {
                    return Err(Error::TrackPoint2DOutOfRange {
                        path: self.points3d_path.clone(),
                        point3d_id: point.id,
                        image_id: element.image_id,
                        point2d_idx: element.point2d_idx,
                        num_points2d: image.points2d.len(),
                    });
                };
                if point2d.point3d_id != Some(point.id) {
                    return Err(Error::TrackMismatch {
                        path: self.points3d_path.clone(),
                        point3d_id: point.id,
                        image_id: element.image_id,
                        point2d_idx: element.point2d_idx,
                        found: point2d.point3d_id,
                    });
                }
                let bit = offsets[index] + idx;
                let (word, mask) = (bit / 64, 1u64 << (bit % 64));
                if seen[word] & mask != 0 {
                    return Err(Error::DuplicateTrackElement {
                        path: self.points3d_path.clone(),
                        point3d_id: point.id,
                        image_id: element.image_id,
                        point2d_idx: element.point2d_idx,
                    });
                }
                seen[word] |= mask;
            }
        }
        // Every track element matched a distinct 2D point carrying its id, so the two
        // directions agree exactly when the counts do; only on a mismatch find the culprit.
        let referenced: usize = self
            .images
            .iter()
            .map(|i| i.points2d.iter().filter(|p| p.point3d_id.is_some()).count())
            .sum();
        if referenced == self.tracks.len() {
            return Ok(());
        }
        for (index, image) in self.images.iter().enumerate() {
            for (idx, point2d) in image.points2d.iter().enumerate() {
                let bit = offsets[index] + idx;
                if let Some(id) = point2d.point3d_id {
                    if seen[bit / 64] & (1u64 << (bit % 64)) == 0 {
                        return Err(self.not_in_track(image.id, idx, id));
                    }
                }
            }
        }
        Ok(())
    }

    fn not_in_track(&self, image_id: u32, idx: usize, point3d_id: u64) -> Error {
        Error::Point2DNotInTrack {
            path: self.images_path.clone(),
            image_id,
            point2d_idx: u32::try_from(idx).unwrap_or(u32::MAX),
            point3d_id,
            point3d_exists: self.points3d.iter().any(|p| p.id == point3d_id),
        }
    }
}
