//! A model's geometry as a map stores it, from a [`Reconstruction`] or, for `convert`,
//! straight from a binary model's bytes.
//!
//! Why a second way in: a [`Reconstruction`] keeps every 2D point of every image (24 bytes
//! on disk, more in memory), which `convert` never needs beyond the triangulated ones'
//! pixels. Reading `images.bin` in place and keeping only what the map stores makes a
//! million-point model convert several times faster and in a fraction of the memory. It
//! accepts exactly the models [`ReconstructionBuilder::build`](crate::colmap::ReconstructionBuilder)
//! accepts (up to the fingerprint note in [`read_bin`]); anything else sends the caller to
//! the general reader, which reports the problem as COLMAP would.

use std::hash::BuildHasher;
use std::path::Path;

use crate::colmap::bin::{
    image_record_len, point3d_record_len, record_runs, triangulated, ImageRecords, ModelBytes,
    Point3DRecords, Runs, MIN_POINT3D, POINT2D,
};
#[cfg(any(feature = "colmap", test))]
use crate::colmap::{files_with, read_file};
use crate::colmap::{IdIndex, Reconstruction};
use crate::format::CameraInfo;
#[cfg(feature = "colmap")]
use crate::format::{self, MapWriter};

/// Cameras, points (all or a subset, renumbered in model order), images with poses, and
/// visibility with the observing pixels. Shared by the SIFT convert and the SFP convert
/// ([`super::sfp`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Geometry {
    pub cameras: Vec<CameraInfo>,
    pub positions: Vec<[f64; 3]>,
    pub colors: Vec<[u8; 3]>,
    pub ids: Vec<u64>,
    pub names: Vec<String>,
    pub image_cameras: Vec<u32>,
    pub poses: Vec<[f64; 7]>,
    pub image_ids: Vec<u32>,
    pub vis_offsets: Vec<u64>,
    pub vis_points: Vec<u32>,
    pub vis_keypoints: Vec<[f32; 2]>,
    /// Each visibility entry's `point2D_idx` in its image (the keypoint row in `database.db`).
    pub vis_point2d: Vec<u32>,
}

/// Model point index → map point index when only the points with `keep[i]` go into the map
/// (`u32::MAX` = not kept).
pub(crate) fn map_index(keep: &[bool]) -> Vec<u32> {
    let mut next = 0u32;
    keep.iter()
        .map(|&k| {
            if !k {
                return u32::MAX;
            }
            next += 1;
            next - 1
        })
        .collect()
}

impl Geometry {
    /// The bytes its arrays hold (what `convert` plans its memory around).
    #[cfg(feature = "colmap")]
    pub(crate) fn heap_bytes(&self) -> u64 {
        fn bytes<T>(v: &[T]) -> u64 {
            std::mem::size_of_val(v) as u64
        }
        let names: usize = self.names.iter().map(|n| n.len()).sum();
        let cameras: usize = self.cameras.iter().map(|c| c.params.len() * 8 + 64).sum();
        bytes(&self.positions)
            + bytes(&self.colors)
            + bytes(&self.ids)
            + bytes(&self.names)
            + names as u64
            + bytes(&self.image_cameras)
            + bytes(&self.poses)
            + bytes(&self.image_ids)
            + bytes(&self.vis_offsets)
            + bytes(&self.vis_points)
            + bytes(&self.vis_keypoints)
            + bytes(&self.vis_point2d)
            + cameras as u64
    }

    /// Image `i`'s camera size in pixels, `[width, height]` (`[0, 0]` for a camera index out
    /// of range, which the builder's checks exclude).
    #[cfg(feature = "colmap")]
    pub(crate) fn image_size(&self, i: usize) -> [u64; 2] {
        self.image_cameras
            .get(i)
            .and_then(|&c| self.cameras.get(c as usize))
            .map_or([0, 0], |c| [c.width, c.height])
    }

    /// `keep[i]` says whether model point `i` goes into the map (`None`: every point).
    pub(crate) fn new(model: &Reconstruction, keep: Option<&[bool]>) -> Geometry {
        let points = model.points3d();
        let map_index = match keep {
            Some(keep) => map_index(keep),
            None => (0..points.len() as u32).collect(),
        };
        let kept = |i: &usize| map_index[*i] != u32::MAX;
        let positions = (0..points.len())
            .filter(kept)
            .map(|i| points[i].xyz)
            .collect();
        let colors = (0..points.len())
            .filter(kept)
            .map(|i| points[i].rgb)
            .collect();
        let ids = (0..points.len())
            .filter(kept)
            .map(|i| points[i].id)
            .collect();
        // Visibility: image → observed (kept) points, with the observing pixel.
        let mut vis = Visibility::with_capacity(model.images().len(), model.num_observations());
        for image in model.images() {
            for (idx, p) in image.points2d.iter().enumerate() {
                let Some(index) = p.point3d_id.and_then(|id| model.point3d_index(id)) else {
                    continue;
                };
                if map_index[index] != u32::MAX {
                    vis.push(map_index[index], p.xy, idx as u32);
                }
            }
            vis.end_image();
        }
        let cameras: Vec<CameraInfo> = model.cameras().iter().map(camera_info).collect();
        let camera_ids: Vec<u32> = model.cameras().iter().map(|c| c.id).collect();
        let images = model.images().iter().map(|i| ImageHead {
            id: i.id,
            name: i.name.clone(),
            camera_id: i.camera_id,
            pose: i.cam_from_world.to_colmap(),
        });
        let (names, image_cameras, poses, image_ids) = image_columns(&camera_ids, images)
            .expect("the reader checked every image's camera exists");
        Geometry {
            cameras,
            positions,
            colors,
            ids,
            names,
            image_cameras,
            poses,
            image_ids,
            vis_offsets: vis.offsets,
            vis_points: vis.points,
            vis_keypoints: vis.keypoints,
            vis_point2d: vis.point2d,
        }
    }

    /// Adds cameras, points, images and visibility to `writer`.
    #[cfg(feature = "colmap")]
    pub(crate) fn write_into<'a>(
        &'a self,
        writer: &mut MapWriter<'a>,
    ) -> Result<(), format::Error> {
        for c in &self.cameras {
            writer.add_camera(c.clone());
        }
        writer.set_points_world(&self.positions);
        writer.set_point_colors(&self.colors);
        writer.set_point_ids(&self.ids);
        writer.set_images(
            &self.names,
            &self.image_cameras,
            &self.poses,
            Some(&self.image_ids),
        )?;
        writer.set_visibility(
            &self.vis_offsets,
            &self.vis_points,
            Some(&self.vis_keypoints),
        )?;
        Ok(())
    }
}

fn camera_info(c: &crate::colmap::Camera) -> CameraInfo {
    CameraInfo {
        id: Some(c.id),
        model: c.model.name().to_string(),
        width: c.width,
        height: c.height,
        params: c.params.clone(),
    }
}

/// What the map keeps of an image besides its visibility.
struct ImageHead {
    id: u32,
    name: String,
    camera_id: u32,
    pose: [f64; 7],
}

type ImageColumns = (Vec<String>, Vec<u32>, Vec<[f64; 7]>, Vec<u32>);

/// Names, camera indices (into `camera_ids`, sorted), poses and ids; `None` if an image's
/// camera does not exist.
fn image_columns(
    camera_ids: &[u32],
    images: impl ExactSizeIterator<Item = ImageHead>,
) -> Option<ImageColumns> {
    let n = images.len();
    let mut columns = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for image in images {
        let camera = camera_ids.binary_search(&image.camera_id).ok()?;
        columns.0.push(image.name);
        columns.1.push(camera as u32);
        columns.2.push(image.pose);
        columns.3.push(image.id);
    }
    Some(columns)
}

/// The visibility CSR under construction, one image at a time.
struct Visibility {
    offsets: Vec<u64>,
    points: Vec<u32>,
    keypoints: Vec<[f32; 2]>,
    point2d: Vec<u32>,
}

impl Visibility {
    fn with_capacity(images: usize, observations: usize) -> Visibility {
        let mut offsets = Vec::with_capacity(images + 1);
        offsets.push(0);
        Visibility {
            offsets,
            points: Vec::with_capacity(observations),
            keypoints: Vec::with_capacity(observations),
            point2d: Vec::with_capacity(observations),
        }
    }

    #[inline]
    fn push(&mut self, point: u32, xy: [f64; 2], point2d_idx: u32) {
        self.points.push(point);
        self.keypoints.push([xy[0] as f32, xy[1] as f32]);
        self.point2d.push(point2d_idx);
    }

    fn end_image(&mut self) {
        self.offsets.push(self.points.len() as u64);
    }
}

/// Reads the binary model in `dir` straight into a [`Geometry`] of all its points.
///
/// `None` means "take the general path": a file is missing or malformed, the model is
/// inconsistent, or its point ids are too sparse for a lookup table. The general reader
/// then reports the problem (or, for sparse ids, converts the model more slowly).
///
/// Checks, against [`ReconstructionBuilder::build`](crate::colmap::ReconstructionBuilder::build):
/// unique camera, image and point ids, every image's camera exists, every 2D point's
/// `point3D_id` names an existing point, and every 3D point's track is exactly the set of
/// 2D points that carry its id. The last is checked without building the reverse index:
/// the observations `(image_id, point2D_idx, point3D_id)` listed by the tracks and those
/// listed by the 2D points must be the same multiset, and are compared by the wrapping sum
/// of a keyed 64-bit hash of each (one sequential pass over each file, no per-point state).
/// Equal multisets always pass; unequal ones pass with probability about 2⁻⁶⁴ (the key is
/// random per process, so a file cannot be crafted to collide). Either way the map's
/// visibility comes from the 2D points, as in the general path.
#[cfg(any(feature = "colmap", test))]
pub(crate) fn read_bin(dir: &Path) -> Option<Geometry> {
    let [cameras, images, points] = files_with(dir, "bin");
    // cameras.bin is small; the other two are read a block at a time, never held whole.
    let c = read_file(&cameras).ok()?;
    let open = |path: &Path| -> Option<(std::fs::File, u64)> {
        let file = crate::colmap::open_regular(path).ok()?;
        let len = file.metadata().ok()?.len();
        Some((file, len))
    };
    let ((i, i_len), (p, p_len)) = (open(&images)?, open(&points)?);
    from_bytes(
        (&c, &cameras),
        (ModelBytes::File(&i, i_len), &images),
        (ModelBytes::File(&p, p_len), &points),
        Runs::DEFAULT,
    )
}

/// [`read_bin`] on the three files' bytes (each with the path its errors would name): the
/// fuzz body's and the tests' way in.
#[cfg(any(test, feature = "fuzzing"))]
pub(crate) fn from_bin(
    cameras: (&[u8], &Path),
    images: (&[u8], &Path),
    points: (&[u8], &Path),
) -> Option<Geometry> {
    from_bytes(
        cameras,
        (ModelBytes::Memory(images.0), images.1),
        (ModelBytes::Memory(points.0), points.1),
        Runs::DEFAULT,
    )
}

/// An image's record without its 2D points: where they lie in `images.bin`.
struct ImageAt {
    id: u32,
    name: String,
    camera_id: u32,
    pose: [f64; 7],
    /// Offset of the 2D points in the file, and their count.
    points2d: u64,
    count: u64,
}

/// The geometry of the model files' bytes, read as `runs` says.
fn from_bytes(
    cameras: (&[u8], &Path),
    images: (ModelBytes<'_>, &Path),
    points: (ModelBytes<'_>, &Path),
    runs: Runs,
) -> Option<Geometry> {
    let (cameras_data, cameras_path) = cameras;
    let mut cameras = crate::colmap::bin::parse_cameras(cameras_data, cameras_path).ok()?;
    cameras.sort_by_key(|c| c.id);
    if cameras.windows(2).any(|w| w[0].id == w[1].id) {
        return None;
    }
    let camera_ids: Vec<u32> = cameras.iter().map(|c| c.id).collect();

    let (image_bytes, image_path) = images;
    let mut images = Vec::new();
    record_runs(image_bytes, runs, image_record_len, |run, n, at| {
        let mut records = ImageRecords::run(run, n, image_path);
        while let Some(r) = records.next_record().ok()? {
            images.push(ImageAt {
                id: r.id,
                pose: r.cam_from_world.to_colmap(),
                camera_id: r.camera_id,
                count: r.num_points2d() as u64,
                // Where the block lies in the run, as a file offset.
                points2d: at + (r.points2d.as_ptr() as usize - run.as_ptr() as usize) as u64,
                name: r.name,
            });
        }
        Some(())
    })?;
    images.sort_by_key(|i| i.id);
    if images.windows(2).any(|w| w[0].id == w[1].id) {
        return None;
    }

    let random = std::hash::RandomState::new();
    let key = [random.hash_one(1u8), random.hash_one(2u8)];
    let points = Points::read(points.0, points.1, runs, key)?;
    // COLMAP numbers points from 1 and filtering leaves gaps; up to 8 slots a point is a
    // table of at most 32 bytes a point, still far smaller than the points themselves.
    let max_slots = points.ids.len().saturating_mul(8).saturating_add(1 << 20);
    let index = IdIndex::dense(points.ids.iter().copied(), max_slots)?;

    let (visibility, sum) = scan_images(&images, image_bytes, &index, points.observations, key)?;
    if sum != points.track_sum {
        return None;
    }

    let heads = images.into_iter().map(|i| ImageHead {
        id: i.id,
        name: i.name,
        camera_id: i.camera_id,
        pose: i.pose,
    });
    let (names, image_cameras, poses, image_ids) = image_columns(&camera_ids, heads)?;
    Some(Geometry {
        cameras: cameras.iter().map(camera_info).collect(),
        positions: points.positions,
        colors: points.colors,
        ids: points.ids,
        names,
        image_cameras,
        poses,
        image_ids,
        vis_offsets: visibility.offsets,
        vis_points: visibility.points,
        vis_keypoints: visibility.keypoints,
        vis_point2d: visibility.point2d,
    })
}

/// The keyed hash of one observation: murmur3's 64-bit finaliser (a bijection) over the
/// 2D point, then again with the 3D point id folded in.
#[inline]
fn observation_hash(key: [u64; 2], image_id: u32, point2d_idx: u32, point3d_id: u64) -> u64 {
    fn mix(mut x: u64) -> u64 {
        x = (x ^ (x >> 33)).wrapping_mul(0xff51_afd7_ed55_8ccd);
        x = (x ^ (x >> 33)).wrapping_mul(0xc4ce_b9fe_1a85_ec53);
        x ^ (x >> 33)
    }
    let point2d = mix(((u64::from(image_id) << 32) | u64::from(point2d_idx)) ^ key[0]);
    mix(point2d ^ mix(point3d_id ^ key[1]))
}

/// `points3D.bin` as columns sorted by id, with each track's fingerprint.
struct Points {
    ids: Vec<u64>,
    positions: Vec<[f64; 3]>,
    colors: Vec<[u8; 3]>,
    /// Wrapping sum of [`observation_hash`] over every track element.
    track_sum: u64,
    /// Sum of the track lengths.
    observations: usize,
}

impl Points {
    fn read(bytes: ModelBytes<'_>, path: &Path, runs: Runs, key: [u64; 2]) -> Option<Points> {
        // Reserved for the count the file can hold, not the count it claims.
        let mut count = [0u8; 8];
        bytes.read_at(&mut count, 0)?;
        let n = u64::from_le_bytes(count).min(bytes.len() / MIN_POINT3D as u64) as usize;
        let mut points = Points {
            ids: Vec::with_capacity(n),
            positions: Vec::with_capacity(n),
            colors: Vec::with_capacity(n),
            track_sum: 0,
            observations: 0,
        };
        record_runs(bytes, runs, point3d_record_len, |run, n, _| {
            let mut records = Point3DRecords::run(run, n, path);
            while let Some(record) = records.next_record().ok()? {
                for e in record.track() {
                    let hash = observation_hash(key, e.image_id, e.point2d_idx, record.id);
                    points.track_sum = points.track_sum.wrapping_add(hash);
                }
                // u32 is the builder's limit on track lengths.
                let len = u32::try_from(record.track_len()).ok()?;
                points.observations += len as usize;
                points.ids.push(record.id);
                points.positions.push(record.xyz);
                points.colors.push(record.rgb);
            }
            Some(())
        })?;
        if !points.ids.is_sorted() {
            points.sort_by_id();
        }
        if points.ids.windows(2).any(|w| w[0] == w[1]) {
            return None;
        }
        Some(points)
    }

    /// COLMAP writes points in hash-map order; the map wants them by id.
    fn sort_by_id(&mut self) {
        let mut order: Vec<u32> = (0..self.ids.len() as u32).collect();
        order.sort_unstable_by_key(|&i| self.ids[i as usize]);
        fn permute<T: Copy>(v: &mut Vec<T>, order: &[u32]) {
            *v = order.iter().map(|&i| v[i as usize]).collect();
        }
        permute(&mut self.ids, &order);
        permute(&mut self.positions, &order);
        permute(&mut self.colors, &order);
    }
}

/// Visibility from the images' 2D points (in image id order, each image's block read from
/// the file in turn), and the wrapping sum of their observations' hashes. `None` if a 2D
/// point names a missing point or the count differs from the tracks'. One pass, straight
/// into arrays of the tracks' size: nothing of the file is held but one image's block.
fn scan_images(
    images: &[ImageAt],
    bytes: ModelBytes<'_>,
    index: &IdIndex,
    observations: usize,
    key: [u64; 2],
) -> Option<(Visibility, u64)> {
    let mut vis = Visibility::with_capacity(images.len(), observations);
    let mut sum = 0u64;
    let mut block = Vec::new();
    for image in images {
        u32::try_from(image.count).ok()?;
        // Within the file: the record reader checked the block's length.
        block.resize(usize::try_from(image.count).ok()? * POINT2D, 0);
        bytes.read_at(&mut block, image.points2d)?;
        for (idx, xy, id) in triangulated(&block) {
            // Checked again: the first read's checks were on bytes read earlier.
            if !xy.iter().all(|v| v.is_finite()) {
                return None;
            }
            let point = index.position(id)?;
            if vis.points.len() == observations {
                return None;
            }
            vis.push(point as u32, xy, idx);
            sum = sum.wrapping_add(observation_hash(key, image.id, idx, id));
        }
        vis.end_image();
    }
    (vis.points.len() == observations).then_some((vis, sum))
}

/// Fuzz entry point (`crate::fuzzing`): parses `data` as each binary model file, then as a whole model (so
/// validation is fuzzed too) laid out as `u16 BE cameras_len, u16 BE images_len, cameras,
/// images, points3D` (lengths are taken modulo what is left). Never panics (that is the
/// test), and the whole model goes through convert's fast path too, which must accept
/// only what the general reader accepts, with the same geometry.
#[cfg(any(test, feature = "fuzzing"))]
pub fn read_colmap_bin(data: &[u8]) {
    let path = std::path::Path::new("fuzz.bin");
    let _ = crate::colmap::bin::parse_cameras(data, path);
    let _ = crate::colmap::bin::parse_images(data, path);
    let _ = crate::colmap::bin::parse_model((&[0u8; 8], path), (&[0u8; 8], path), (data, path));
    let [c, i, p] = crate::colmap::split3(data);
    let general = crate::colmap::bin::parse_model((c, path), (i, path), (p, path));
    if let Some(fast) = from_bin((c, path), (i, path), (p, path)) {
        let general = match general {
            Ok(model) => Geometry::new(&model, None),
            Err(e) => panic!("the fast path accepted a model the reader rejects: {e}"),
        };
        // Debug, not ==: stricter (-0.0 differs from 0.0). No NaN gets this far: both
        // paths refuse non-finite values in the same record readers.
        assert_eq!(format!("{fast:?}"), format!("{general:?}"));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::colmap::{read_model, Error};
    use std::path::PathBuf;

    /// A point as `points3D.bin` holds it: id, position, colour, track (image id, index).
    type PointRow = (u64, [f64; 3], [u8; 3], Vec<(u32, u32)>);
    /// An image as `images.bin` holds it: id, camera id, name, 2D points (x, y, point id).
    type ImageRow = (u32, u32, &'static str, Vec<(f64, f64, u64)>);

    const NONE: u64 = u64::MAX;

    /// Two cameras; images 7 and 3 (file order not sorted); points 40, 10, 25 (not sorted,
    /// with gaps) with untriangulated 2D points between the triangulated ones.
    fn model() -> (Vec<ImageRow>, Vec<PointRow>) {
        let images = vec![
            (
                7,
                2,
                "b.jpg",
                vec![(1.5, 2.5, 40), (3.0, 4.0, NONE), (5.0, 6.0, 10)],
            ),
            (
                3,
                1,
                "a.jpg",
                vec![
                    (7.0, 8.0, NONE),
                    (9.0, 10.0, 25),
                    (11.0, 12.0, 40),
                    (0.5, 0.5, 10),
                ],
            ),
        ];
        let points = vec![
            (40, [1.0, 2.0, 3.0], [1, 2, 3], vec![(3, 2), (7, 0)]),
            (10, [-1.0, 0.0, 1e6], [4, 5, 6], vec![(7, 2), (3, 3)]),
            (25, [0.25, 0.5, 0.75], [7, 8, 9], vec![(3, 1)]),
        ];
        (images, points)
    }

    fn write(dir: &Path, images: &[ImageRow], points: &[PointRow]) {
        let mut c = 2u64.to_le_bytes().to_vec();
        for (id, model, params) in [
            (1u32, 0i32, vec![500.0, 320.0, 240.0]),
            (2, 1, vec![1.0; 4]),
        ] {
            c.extend(id.to_le_bytes());
            c.extend(model.to_le_bytes());
            c.extend(640u64.to_le_bytes());
            c.extend(480u64.to_le_bytes());
            params.iter().for_each(|p: &f64| c.extend(p.to_le_bytes()));
        }
        let mut i = (images.len() as u64).to_le_bytes().to_vec();
        for (id, camera, name, points2d) in images {
            i.extend(id.to_le_bytes());
            for v in [1.0f64, 0.0, 0.0, 0.0, f64::from(*id), 0.0, 0.0] {
                i.extend(v.to_le_bytes());
            }
            i.extend(camera.to_le_bytes());
            i.extend(name.as_bytes());
            i.push(0);
            i.extend((points2d.len() as u64).to_le_bytes());
            for (x, y, p) in points2d {
                i.extend(x.to_le_bytes());
                i.extend(y.to_le_bytes());
                i.extend(p.to_le_bytes());
            }
        }
        let mut p = (points.len() as u64).to_le_bytes().to_vec();
        for (id, xyz, rgb, track) in points {
            p.extend(id.to_le_bytes());
            xyz.iter().for_each(|v| p.extend(v.to_le_bytes()));
            p.extend(rgb);
            p.extend(0.5f64.to_le_bytes());
            p.extend((track.len() as u64).to_le_bytes());
            for (image, idx) in track {
                p.extend(image.to_le_bytes());
                p.extend(idx.to_le_bytes());
            }
        }
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("cameras.bin"), c).unwrap();
        std::fs::write(dir.join("images.bin"), i).unwrap();
        std::fs::write(dir.join("points3D.bin"), p).unwrap();
    }

    /// The general path's geometry, or its error.
    fn general(dir: &Path) -> Result<Geometry, Error> {
        read_model(dir).map(|m| Geometry::new(&m, None))
    }

    #[test]
    fn fast_path_matches_the_general_path() {
        let tmp = tempfile::tempdir().unwrap();
        let (images, points) = model();
        write(tmp.path(), &images, &points);
        let fast = read_bin(tmp.path()).expect("a consistent model takes the fast path");
        assert_eq!(fast, general(tmp.path()).unwrap());
        // Sorted by id, visibility in image-id order with the 2D points' indices.
        assert_eq!(fast.ids, [10, 25, 40]);
        assert_eq!(fast.colors, [[4, 5, 6], [7, 8, 9], [1, 2, 3]]);
        assert_eq!(fast.image_ids, [3, 7]);
        assert_eq!(fast.image_cameras, [0, 1]);
        assert_eq!(fast.vis_offsets, [0, 3, 5]);
        assert_eq!(fast.vis_points, [1, 2, 0, 2, 0]);
        assert_eq!(fast.vis_point2d, [1, 2, 3, 0, 2]);
        assert_eq!(fast.vis_keypoints[0], [9.0, 10.0]);
    }

    /// Each way a model can be inconsistent: the fast path declines and the general path
    /// names the problem.
    #[test]
    fn inconsistent_models_decline_the_fast_path() {
        type Edit = fn(&mut Vec<ImageRow>, &mut Vec<PointRow>);
        let edits: [(&str, Edit); 9] = [
            ("track names another 2D point", |_, p| p[2].3[0].1 = 0),
            ("track element twice", |_, p| p[2].3.push((3, 1))),
            ("track misses a 2D point", |_, p| {
                p[1].3.pop();
            }),
            ("track names a missing image", |_, p| p[2].3.push((99, 0))),
            ("2D point names a missing point", |i, _| i[0].3[1].2 = 77),
            ("2D point names the wrong point", |i, _| i[0].3[0].2 = 10),
            ("duplicate point id", |_, p| p[2].0 = 10),
            ("duplicate image id", |i, _| i[1].0 = 7),
            ("missing camera", |i, _| i[1].1 = 9),
        ];
        for (what, edit) in edits {
            let tmp = tempfile::tempdir().unwrap();
            let (mut images, mut points) = model();
            edit(&mut images, &mut points);
            write(tmp.path(), &images, &points);
            assert!(read_bin(tmp.path()).is_none(), "{what}");
            assert!(general(tmp.path()).is_err(), "{what}");
        }
    }

    /// Non-finite numbers and names with control characters: the fast path declines and
    /// the general path names the record, so both accept the same files.
    #[test]
    fn non_finite_values_and_bad_names_decline_the_fast_path() {
        type Edit = fn(&mut Vec<ImageRow>, &mut Vec<PointRow>);
        let edits: [(&str, &str, Edit); 5] = [
            ("point3D 25: position", "points3D.bin", |_, p| {
                p[2].1[1] = f64::NAN
            }),
            ("point3D 40: position", "points3D.bin", |_, p| {
                p[0].1[2] = f64::INFINITY
            }),
            ("image 7: point2D 1 position", "images.bin", |i, _| {
                i[0].3[1].0 = f64::NAN
            }),
            ("image 3: point2D 2 position", "images.bin", |i, _| {
                i[1].3[2].1 = f64::NEG_INFINITY
            }),
            ("image 3: name", "images.bin", |i, _| i[1].2 = "a\nb.jpg"),
        ];
        for (what, file, edit) in edits {
            let tmp = tempfile::tempdir().unwrap();
            let (mut images, mut points) = model();
            edit(&mut images, &mut points);
            write(tmp.path(), &images, &points);
            assert!(read_bin(tmp.path()).is_none(), "{what}");
            let err = general(tmp.path()).unwrap_err().to_string();
            assert!(err.contains(file) && err.contains(what), "{what}: {err}");
        }
    }

    /// A point without observations is accepted by both (COLMAP reads it too).
    #[test]
    fn a_point_without_observations_takes_the_fast_path() {
        let tmp = tempfile::tempdir().unwrap();
        let (images, mut points) = model();
        points.push((30, [0.0; 3], [0; 3], Vec::new()));
        write(tmp.path(), &images, &points);
        let fast = read_bin(tmp.path()).expect("fast path");
        assert_eq!(fast, general(tmp.path()).unwrap());
        assert_eq!(fast.ids, [10, 25, 30, 40]);
    }

    #[test]
    fn truncated_files_decline_the_fast_path() {
        let tmp = tempfile::tempdir().unwrap();
        let (images, points) = model();
        write(tmp.path(), &images, &points);
        for name in ["cameras.bin", "images.bin", "points3D.bin"] {
            let path = tmp.path().join(name);
            let bytes = std::fs::read(&path).unwrap();
            for len in [0, bytes.len() / 2, bytes.len() - 1] {
                std::fs::write(&path, &bytes[..len]).unwrap();
                assert!(read_bin(tmp.path()).is_none(), "{name} cut at {len}");
            }
            std::fs::write(&path, &bytes).unwrap();
        }
        assert!(read_bin(tmp.path()).is_some());
    }

    #[test]
    fn sparse_ids_decline_the_fast_path_but_convert_in_general() {
        let tmp = tempfile::tempdir().unwrap();
        let (mut images, mut points) = model();
        // Far past 8 slots a point: no lookup table.
        let far = 1u64 << 40;
        images[0].3[0].2 = far;
        images[1].3[2].2 = far;
        points[0].0 = far;
        write(tmp.path(), &images, &points);
        assert!(read_bin(tmp.path()).is_none());
        assert_eq!(general(tmp.path()).unwrap().ids, [10, 25, far]);
    }

    /// The fuzz seed of a whole model reaches the fast path, so fuzzing compares the two.
    #[test]
    fn the_fuzz_seed_takes_the_fast_path() {
        let seed =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/colmap_bin/consistent-model");
        let data = std::fs::read(seed).unwrap();
        let [c, i, p] = crate::colmap::split3(&data);
        let path = Path::new("seed");
        let fast = from_bin((c, path), (i, path), (p, path)).expect("fast path");
        assert_eq!(fast.ids, [10, 25, 40]);
        read_colmap_bin(&data);
    }

    #[test]
    fn map_index_numbers_the_kept_points() {
        assert_eq!(
            map_index(&[false, true, true, false, true]),
            [u32::MAX, 0, 1, u32::MAX, 2]
        );
    }

    #[test]
    fn hashes_of_distinct_observations_differ() {
        let key = [0x1234_5678_9abc_def0, 0x0fed_cba9_8765_4321];
        let mut seen = std::collections::HashSet::new();
        for image in 0..32 {
            for idx in 0..32 {
                for point in [0, 1, 2, u64::MAX - 1] {
                    assert!(seen.insert(observation_hash(key, image, idx, point)));
                }
            }
        }
        let other = [key[0] ^ 1, key[1]];
        assert_ne!(
            observation_hash(key, 2, 3, 4),
            observation_hash(other, 2, 3, 4)
        );
    }

    /// A record longer than the cap, or a header that does not end within it, makes the
    /// block reader decline (the general reader then judges the file), however it is read.
    #[test]
    fn records_past_the_cap_are_declined() {
        let tmp = tempfile::tempdir().unwrap();
        let (images, points) = model();
        write(tmp.path(), &images, &points);
        let i = std::fs::read(tmp.path().join("images.bin")).unwrap();
        let count = |runs: Runs, bytes: &[u8]| {
            let mut seen = 0;
            record_runs(
                ModelBytes::Memory(bytes),
                runs,
                image_record_len,
                |_, n, _| {
                    seen += n;
                    Some(())
                },
            )
            .map(|total| (total, seen))
        };
        // b.jpg's record: 64 + 6 + 8 + 3 × 24 = 150 bytes; a.jpg's 174.
        for block in [1, 8, 150, 4096] {
            let runs = |max_record| Runs { block, max_record };
            assert_eq!(count(runs(174), &i), Some((2, 2)), "block {block}");
            assert_eq!(count(runs(173), &i), None, "block {block}");
        }
        // A name with no end: declined once the cap is read, not grown into.
        let mut endless = 1u64.to_le_bytes().to_vec();
        endless.extend(std::iter::repeat_n(b'x', 4096));
        let runs = Runs {
            block: 8,
            max_record: 256,
        };
        assert_eq!(count(runs, &endless), None);
        assert_eq!(count(Runs::DEFAULT, &endless), None);
        // The whole model: declined under a cap, read under the default.
        let file = |name: &str| std::fs::read(tmp.path().join(name)).unwrap();
        let (c, p) = (file("cameras.bin"), file("points3D.bin"));
        let read = |runs| {
            let (i, p) = (ModelBytes::Memory(&i), ModelBytes::Memory(&p));
            from_bytes((&c, tmp.path()), (i, tmp.path()), (p, tmp.path()), runs)
        };
        assert!(read(Runs::DEFAULT).is_some());
        assert!(read(Runs {
            block: 8,
            max_record: 100
        })
        .is_none());
    }

    /// Every binary model in the shared data (fixtures, scenes, malformed models): the fast
    /// path gives the general path's geometry, or declines where the general path errors.
    #[test]
    fn shared_models_agree_with_the_general_path() {
        // As tests/shared_data: missing data fails unless skipping is asked for.
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
        if !root.is_dir() {
            let skip = std::env::var_os("SFPMAP_SKIP_SHARED_DATA").is_some_and(|v| v == "1");
            assert!(
                skip,
                "{} is missing (SFPMAP_SKIP_SHARED_DATA=1 skips)",
                root.display()
            );
            eprintln!("SKIPPED: {} is missing", root.display());
            return;
        }
        fn dirs(dir: &Path, out: &mut Vec<PathBuf>) {
            let Ok(entries) = std::fs::read_dir(dir) else {
                return;
            };
            for entry in entries.flatten() {
                let path = entry.path();
                if path.is_dir() {
                    dirs(&path, out);
                } else if path.file_name().is_some_and(|n| n == "points3D.bin") {
                    out.push(dir.to_path_buf());
                }
            }
        }
        let mut found = Vec::new();
        dirs(&root.join("colmap"), &mut found);
        dirs(&root.join("scenes"), &mut found);
        let (mut fast_count, mut declined) = (0, 0);
        for dir in &found {
            let fast = read_bin(dir);
            // A few bytes read at a time: records straddle every block boundary, and the
            // buffer grows past records longer than a block.
            let file = |name: &str| std::fs::read(dir.join(name)).ok();
            if let (Some(c), Some(i), Some(p)) = (
                file("cameras.bin"),
                file("images.bin"),
                file("points3D.bin"),
            ) {
                for block in [1, 13, 4096] {
                    let (images, points) = (ModelBytes::Memory(&i), ModelBytes::Memory(&p));
                    let runs = Runs {
                        block,
                        ..Runs::DEFAULT
                    };
                    let small = from_bytes((&c, dir), (images, dir), (points, dir), runs);
                    assert_eq!(small, fast, "{} in blocks of {block}", dir.display());
                }
            }
            match general(dir) {
                Ok(geometry) => {
                    assert_eq!(fast.as_ref(), Some(&geometry), "{}", dir.display());
                    fast_count += 1;
                }
                Err(_) => {
                    assert!(fast.is_none(), "{}", dir.display());
                    declined += 1;
                }
            }
        }
        eprintln!("{fast_count} models read the fast way, {declined} declined");
        assert!(
            fast_count >= 4,
            "{fast_count} models read, {declined} declined"
        );
    }
}
