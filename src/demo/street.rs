//! A street-sized scene for scale work: a COLMAP model, its `database.db`, and queries with
//! ground truth, generated deterministically from a seed (no images: descriptors are
//! generated, SIFT-like). What `benches/street.sh` and the scale benches run on. The same seed
//! gives the same files on the same platform (the system's `ln`, `cos` and `exp` may differ in
//! their last bits elsewhere).
//!
//! - **Geometry**: a straight street along +z, façades at x = ±6 m, 15 m high (y down, as in
//!   COLMAP's camera frame: the ground is y = 0, a roof y = −15). Points uniform on both
//!   façades; the street is `points / 1000` metres long, so a million points make a
//!   kilometre.
//! - **Database cameras** (PINHOLE 1024 × 768, f = 800) every 0.5 m along the street at eye
//!   height, 4 views each (both façades, across and ahead): about 8 images a metre. Each sees
//!   the façade points in front of it within 45 m and detects at most about 1,400 of them (a
//!   detector's budget): a point is detected along a stretch of the street at its own phase,
//!   so neighbouring images detect mostly the same points, as a real detector does (since
//!   stop 47; before, each image kept a random share); points seen by fewer than 2 images
//!   are dropped, as COLMAP would not have triangulated them.
//! - **Descriptors**: 128-d, per point a base vector with a decaying PCA spectrum in a random
//!   orthonormal basis; each observation adds noise, then SIFT's encoding (clamped at 0, L2 to
//!   512, saturated to `u8`). Keypoint scales follow depth (a point's size over its depth).
//! - **Queries** off the database path (1.5–3 m to the side, other headings): projections of
//!   visible points with 0.7 px noise and about 30 % outlier keypoints that carry the
//!   descriptor of some other point, in `queries.db`; `queries.txt` (hloc list with
//!   intrinsics) and `gt_poses.txt` (`cam_from_world`).

use std::collections::VecDeque;
use std::io::Write;
use std::path::Path;

use bitvec::prelude::{BitSlice, BitVec};
use nalgebra::Vector3;

use super::look_at;
use crate::colmap::{bin, Camera, DatabaseWriter, Error, Image, Point2D, TrackElement};
use crate::format::f16;
use crate::geometry::{Pose, SplitMix64};
use crate::output::AtomicFile;

const WIDTH: u32 = 1024;
const HEIGHT: u32 = 768;
const FOCAL: f64 = 800.0;
const HALF_WIDTH: f64 = 6.0;
const FACADE_HEIGHT: f64 = 15.0;
const EYE: f64 = -1.6;
const MAX_DEPTH: f64 = 45.0;
const MAX_OBSERVATIONS: usize = 1_400;
const DIM: usize = 128;
/// Metres along the street over which a point's detection comes round again (see
/// `Street::detected`): about the stretch a point is in view from.
const DETECTION_CYCLE: f64 = 40.0;

/// What to generate.
#[derive(Debug, Clone)]
pub struct StreetOptions {
    /// Façade points before thinning (those seen by fewer than 2 images are dropped).
    pub points: usize,
    /// Query images (each with its features in `queries.db` and its true pose).
    pub queries: usize,
    /// Seed of every random choice: the same options give the same files.
    pub seed: u64,
    /// Share of a query's keypoints that are outliers (taken as at most 0.9).
    pub outlier_share: f64,
    /// Pixel noise (standard deviation) of the query keypoints.
    pub pixel_noise: f64,
}

impl Default for StreetOptions {
    fn default() -> Self {
        StreetOptions {
            points: 100_000,
            queries: 20,
            seed: 0,
            outlier_share: 0.3,
            pixel_noise: 0.7,
        }
    }
}

/// What was written.
#[derive(Debug, Clone, PartialEq)]
pub struct StreetSummary {
    /// The street's length in metres.
    pub length_m: f64,
    /// 3D points in the model.
    pub points: usize,
    /// Database images.
    pub images: usize,
    /// Observations in the model's tracks.
    pub observations: usize,
    /// Query images.
    pub queries: usize,
}

/// Writes the scene into `dir` (which must exist): `sparse/{cameras,images,points3D}.bin`,
/// `database.db`, `queries.db`, `queries.txt`, `gt_poses.txt`, each through the atomic writer.
///
/// In memory bounded by the points, not the observations: each point's position and size
/// (28 bytes) and a bit (a count of 4 bytes while counting), plus what the cameras within
/// [`MAX_DEPTH`] of the one being written see. Every view is made twice: once to count each point's observations (those
/// seen by fewer than 2 images are dropped), once to write it; the model files and the
/// database are written an image at a time, and a point's track once no later camera can
/// see it.
pub fn write_street(dir: &Path, options: &StreetOptions) -> Result<StreetSummary, Error> {
    let scene = Street::new(options);
    let camera = scene.camera();
    let poses = scene.database_poses();

    let mut track_len = vec![0u32; scene.positions.len()];
    for pose in &poses {
        for (p, _, _) in scene.database_view(pose) {
            track_len[p as usize] += 1;
        }
    }
    let kept: BitVec = track_len.iter().map(|&n| n >= 2).collect();
    drop(track_len);
    let points = kept.count_ones();

    let sparse = dir.join("sparse");
    std::fs::create_dir_all(&sparse)
        .map_err(|e| crate::output::OutputError::cannot_write(&sparse, e))?;
    let mut cameras = 1u64.to_le_bytes().to_vec();
    bin::encode_camera(&camera, &mut cameras);
    crate::output::write_bytes(&sparse.join("cameras.bin"), &cameras)?;
    let mut images_bin = ModelFile::create(&sparse.join("images.bin"), poses.len())?;
    let mut points_bin = ModelFile::create(&sparse.join("points3D.bin"), points)?;
    let mut db = DatabaseWriter::new(&dir.join("database.db"))?;
    db.add_camera(&camera)?;

    let mut rng = SplitMix64::new(options.seed ^ 0x5EED_0001);
    let mut bases = BaseWindow::default();
    let mut tracks = OpenTracks::default();
    let mut observations = 0;
    let mut write_point = |p: usize, track: &[TrackElement], out: &mut Vec<u8>| {
        if kept[p] {
            let xyz = scene.positions[p].into();
            bin::encode_point3d(p as u64 + 1, xyz, scene.color(p), 0.5, track, out);
        }
    };
    for (i, pose) in poses.iter().enumerate() {
        // Cameras go along +z and see points within MAX_DEPTH of them in z: the tracks of
        // points behind that are complete.
        let first_open = scene
            .positions
            .partition_point(|q| q.z < pose.center().z - MAX_DEPTH);
        tracks.close_before(first_open, &mut points_bin, &mut write_point)?;
        bases.forget_before(first_open);

        let id = i as u32 + 1;
        let view = scene.database_view(pose);
        let mut points2d = Vec::with_capacity(view.len());
        let mut keypoints = Vec::with_capacity(view.len());
        let mut descriptors = Vec::with_capacity(view.len() * DIM);
        for (p, xy, depth) in view {
            let point3d_id = kept[p as usize].then_some(u64::from(p) + 1);
            if point3d_id.is_some() {
                let element = TrackElement {
                    image_id: id,
                    point2d_idx: points2d.len() as u32,
                };
                tracks.push(p as usize, element);
                observations += 1;
            }
            points2d.push(Point2D { xy, point3d_id });
            keypoints.push(scene.keypoint(p, xy, depth, &mut rng));
            observe(
                bases.get(&scene, p as usize),
                0.25,
                &mut rng,
                &mut descriptors,
            );
        }
        let name = format!("db_{i:06}.jpg");
        db.add_image(id, &name, camera.id, &keypoints, &descriptors, DIM)?;
        let image = Image {
            id,
            name,
            camera_id: camera.id,
            cam_from_world: *pose,
            points2d,
        };
        images_bin.add(|out| bin::encode_image(&image, out))?;
    }
    tracks.close_before(scene.positions.len(), &mut points_bin, &mut write_point)?;
    db.write()?;
    images_bin.commit()?;
    points_bin.commit()?;

    let queries = scene.write_queries(dir, options, &camera, &kept)?;
    Ok(StreetSummary {
        length_m: scene.length,
        points,
        images: poses.len(),
        observations,
        queries,
    })
}

/// A binary model file written record by record: its count first, then each record as it
/// is made.
struct ModelFile {
    path: std::path::PathBuf,
    file: AtomicFile,
    record: Vec<u8>,
    /// Records the count at the file's start promised, and those added.
    promised: usize,
    added: usize,
}

impl ModelFile {
    fn create(path: &Path, count: usize) -> Result<ModelFile, Error> {
        let mut file = AtomicFile::create(path)?;
        file.write_all(&(count as u64).to_le_bytes())
            .map_err(|e| crate::output::OutputError::cannot_write(path, e))?;
        Ok(ModelFile {
            path: path.to_path_buf(),
            file,
            record: Vec::new(),
            promised: count,
            added: 0,
        })
    }

    /// Appends what `encode` writes.
    fn add(&mut self, encode: impl FnOnce(&mut Vec<u8>)) -> Result<(), Error> {
        self.record.clear();
        encode(&mut self.record);
        self.added += usize::from(!self.record.is_empty());
        self.file
            .write_all(&self.record)
            .map_err(|e| crate::output::OutputError::cannot_write(&self.path, e).into())
    }

    /// Renames the file over its target, if it holds the records its count promised (the
    /// count comes from the first pass over the views, the records from the second).
    fn commit(self) -> Result<(), Error> {
        if self.added != self.promised {
            let why = format!("{} records for a count of {}", self.added, self.promised);
            let e = std::io::Error::new(std::io::ErrorKind::InvalidData, why);
            return Err(crate::output::OutputError::cannot_write(&self.path, e).into());
        }
        Ok(self.file.commit()?)
    }
}

/// The tracks of the points from `first` on, while cameras may still see them.
#[derive(Default)]
struct OpenTracks {
    first: usize,
    tracks: VecDeque<Vec<TrackElement>>,
}

impl OpenTracks {
    fn push(&mut self, p: usize, element: TrackElement) {
        let at = p - self.first;
        if at >= self.tracks.len() {
            self.tracks.resize_with(at + 1, Vec::new);
        }
        self.tracks[at].push(element);
    }

    /// Hands every point before `end` to `write` in point order (its track empty if no image
    /// saw it), and forgets them.
    fn close_before(
        &mut self,
        end: usize,
        file: &mut ModelFile,
        write: &mut impl FnMut(usize, &[TrackElement], &mut Vec<u8>),
    ) -> Result<(), Error> {
        while self.first < end {
            let track = self.tracks.pop_front().unwrap_or_default();
            let p = self.first;
            file.add(|out| write(p, &track, out))?;
            self.first += 1;
        }
        Ok(())
    }
}

/// The base descriptors of a window of consecutive points: those the cameras near the one
/// being written see, made once each.
#[derive(Default)]
struct BaseWindow {
    first: usize,
    rows: VecDeque<[f16; DIM]>,
}

impl BaseWindow {
    fn get(&mut self, scene: &Street, p: usize) -> &[f16; DIM] {
        debug_assert!(p >= self.first, "a point before the window");
        while self.first + self.rows.len() <= p {
            let next = self.first + self.rows.len();
            self.rows.push_back(scene.base(next));
        }
        &self.rows[p - self.first]
    }

    fn forget_before(&mut self, first: usize) {
        while self.first < first {
            if self.rows.pop_front().is_none() {
                self.first = first;
                break;
            }
            self.first += 1;
        }
    }
}

/// Appends one observation of a point whose base descriptor is `base`: plus noise of `noise`
/// times the base's spread, encoded as COLMAP's SIFT (`u8`, L2 norm 512, saturated).
fn observe(base: &[f16], noise: f64, rng: &mut SplitMix64, out: &mut Vec<u8>) {
    let mut v: Vec<f64> = base
        .iter()
        .map(|b| (b.to_f64() + noise * 40.0 * gaussian(rng)).max(0.0))
        .collect();
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-9);
    v.iter_mut().for_each(|x| *x *= 512.0 / n);
    out.extend(v.iter().map(|&x| x.round().min(255.0) as u8));
}

fn gaussian(rng: &mut SplitMix64) -> f64 {
    // Box–Muller; 1 − u keeps the logarithm finite.
    let (u, v) = (1.0 - rng.next_f64(), rng.next_f64());
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// The generated world: façade points sorted along the street, their sizes and base
/// descriptors.
struct Street {
    length: f64,
    seed: u64,
    positions: Vec<Vector3<f64>>,
    /// Physical size (m) of each point's feature: its keypoint scale is size × f / depth.
    sizes: Vec<f32>,
    /// `[DIM × DIM]` an orthonormal basis: the directions of the descriptors' spectrum.
    basis: Vec<f64>,
}

impl Street {
    fn new(options: &StreetOptions) -> Street {
        let length = (options.points as f64 / 1000.0).max(10.0);
        let mut rng = SplitMix64::new(options.seed);
        let mut positions: Vec<Vector3<f64>> = (0..options.points)
            .map(|_| {
                let side = if rng.next_f64() < 0.5 { -1.0 } else { 1.0 };
                // A little relief, so the façades are not exact planes.
                let x = side * (HALF_WIDTH + 0.1 * rng.next_f64());
                Vector3::new(x, -FACADE_HEIGHT * rng.next_f64(), length * rng.next_f64())
            })
            .collect();
        positions.sort_by(|a, b| a.z.total_cmp(&b.z));
        let sizes = (0..options.points)
            .map(|_| (0.02 * 10f64.powf(rng.next_f64())) as f32)
            .collect();
        // A random orthonormal basis (Gram–Schmidt) and a decaying spectrum: a few
        // directions carry most of the variance, as in real SIFT.
        let mut basis = vec![0.0f64; DIM * DIM];
        for k in 0..DIM {
            let mut v: Vec<f64> = (0..DIM).map(|_| gaussian(&mut rng)).collect();
            for j in 0..k {
                let b = &basis[j * DIM..(j + 1) * DIM];
                let d: f64 = v.iter().zip(b).map(|(x, y)| x * y).sum();
                v.iter_mut().zip(b).for_each(|(x, y)| *x -= d * y);
            }
            let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
            basis[k * DIM..(k + 1) * DIM]
                .iter_mut()
                .zip(&v)
                .for_each(|(b, x)| *b = x / n);
        }
        Street {
            length,
            seed: options.seed,
            positions,
            sizes,
            basis,
        }
    }

    /// Point `p`'s base descriptor (before SIFT's encoding): a decaying spectrum on the
    /// basis, from the point's own seed, so any point's is made alone.
    fn base(&self, p: usize) -> [f16; DIM] {
        let mut rng = SplitMix64::new(
            self.seed ^ 0xBA5E_0000 ^ (p as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let mut row = [30.0f64; DIM];
        for k in 0..DIM {
            let c = 40.0 * (-(k as f64) / 24.0).exp() * gaussian(&mut rng);
            row.iter_mut()
                .zip(&self.basis[k * DIM..(k + 1) * DIM])
                .for_each(|(r, b)| *r += c * b);
        }
        // Through f32: `f16::from_f64` rounds once or twice depending on the CPU.
        row.map(|v| f16::from_f32(v as f32))
    }

    fn camera(&self) -> Camera {
        super::pinhole(WIDTH, HEIGHT, FOCAL)
    }

    /// Every 0.5 m along the street: both façades across, both ahead.
    fn database_poses(&self) -> Vec<Pose> {
        let stations = (self.length / 0.5) as usize;
        let mut poses = Vec::with_capacity(stations * 4);
        for s in 0..stations {
            let z = 0.25 + 0.5 * s as f64;
            let x = if s % 2 == 0 { -0.5 } else { 0.5 };
            let centre = Vector3::new(x, EYE, z);
            for (side, ahead) in [(-1.0, 4.0), (1.0, 4.0), (-1.0, 15.0), (1.0, 15.0)] {
                let target = Vector3::new(side * HALF_WIDTH, -3.0, z + ahead);
                poses.push(look_at(centre, target));
            }
        }
        poses
    }

    /// The points `pose` sees: in front, within [`MAX_DEPTH`], inside the frame (1 px
    /// margin); as (point, pixel, depth), in point order.
    fn visible(&self, pose: &Pose) -> Vec<(u32, [f64; 2], f64)> {
        let centre = pose.center();
        let lo = self
            .positions
            .partition_point(|p| p.z < centre.z - MAX_DEPTH);
        let hi = self
            .positions
            .partition_point(|p| p.z <= centre.z + MAX_DEPTH);
        let (w, h) = (f64::from(WIDTH), f64::from(HEIGHT));
        (lo..hi)
            .filter_map(|p| {
                let c = pose.transform(&self.positions[p]);
                if !(c.z > 0.5 && c.z < MAX_DEPTH) {
                    return None;
                }
                let xy = [FOCAL * c.x / c.z + w / 2.0, FOCAL * c.y / c.z + h / 2.0];
                (xy[0] > 1.0 && xy[0] < w - 1.0 && xy[1] > 1.0 && xy[1] < h - 1.0)
                    .then_some((p as u32, xy, c.z))
            })
            .collect()
    }

    /// What a database camera at `pose` detects (both passes over the views call this one).
    fn database_view(&self, pose: &Pose) -> Vec<(u32, [f64; 2], f64)> {
        self.detected(pose, MAX_OBSERVATIONS, |_| true)
    }

    /// What a camera at `pose` detects: of the points it sees for which `wanted` holds, at
    /// most about `budget`, as (point, pixel, depth) in point order. A point is detected
    /// while the camera moves through a stretch of the street `keep × DETECTION_CYCLE`
    /// metres long (at the point's own phase), `keep` the share of the points in view the
    /// budget allows. A real detector finds a feature again from nearby viewpoints and loses
    /// it as the view changes, so a track is a stretch of neighbouring cameras and an image
    /// shares most of its points with its neighbours, as retrieval relies on (thinning
    /// each image on its own would share a random 1 in 15).
    fn detected(
        &self,
        pose: &Pose,
        budget: usize,
        wanted: impl Fn(u32) -> bool,
    ) -> Vec<(u32, [f64; 2], f64)> {
        let mut view = self.visible(pose);
        view.retain(|&(p, _, _)| wanted(p));
        let keep = budget as f64 / view.len().max(1) as f64;
        if keep < 1.0 {
            let z = pose.center().z;
            view.retain(|&(p, _, _)| {
                let phase = SplitMix64::new(
                    self.seed ^ 0xDE7E_C700 ^ u64::from(p).wrapping_mul(0x9E37_79B9_7F4A_7C15),
                )
                .next_f64();
                (phase + z / DETECTION_CYCLE).fract() < keep
            });
        }
        view
    }

    /// `(x, y, scale, orientation)` of point `p` seen at `xy` from `depth`.
    fn keypoint(&self, p: u32, xy: [f64; 2], depth: f64, rng: &mut SplitMix64) -> [f32; 4] {
        let scale = (f64::from(self.sizes[p as usize]) * FOCAL / depth).max(1.0);
        let angle = (rng.next_f64() - 0.5) * std::f64::consts::TAU;
        [xy[0] as f32, xy[1] as f32, scale as f32, angle as f32]
    }

    fn color(&self, p: usize) -> [u8; 3] {
        let h = (p as u64 ^ self.seed).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        [(h >> 40) as u8, (h >> 48) as u8, (h >> 56) as u8]
    }

    /// `queries.db`, `queries.txt`, `gt_poses.txt` (queries anywhere along the street), and
    /// `sequence.db`, `sequence.txt`, `sequence_gt.txt` (as many frames of a camera walking
    /// the pavement, in order, for `localize --sequence`); returns the number of queries.
    fn write_queries(
        &self,
        dir: &Path,
        options: &StreetOptions,
        camera: &Camera,
        kept: &BitSlice,
    ) -> Result<usize, Error> {
        let mut rng = SplitMix64::new(options.seed ^ 0x0051_EE71);
        let random = |_: usize, rng: &mut SplitMix64| {
            let z = self.length * (0.1 + 0.8 * rng.next_f64());
            let side = if rng.next_f64() < 0.5 { -1.0 } else { 1.0 };
            let centre = Vector3::new(
                side * (1.5 + 1.5 * rng.next_f64()),
                EYE + 0.2 * (rng.next_f64() - 0.5),
                z,
            );
            let look = if rng.next_f64() < 0.5 { -side } else { side };
            let height = -1.0 - 4.0 * rng.next_f64();
            // Ahead, but not past the street's end (a short street's queries would look at
            // no façade).
            let target_z = (z + 2.0 + 18.0 * rng.next_f64()).min(self.length);
            let target = Vector3::new(look * HALF_WIDTH, height, target_z);
            look_at(centre, target)
        };
        let files = ("queries", "query", "gt_poses");
        self.write_query_set(dir, files, random, options, camera, kept, &mut rng)?;
        // The walk: 0.5 m a frame along the right pavement from a tenth of the street,
        // looking ahead at the far façade, the view swaying a little (as a hand-held camera).
        let walk = |f: usize, _: &mut SplitMix64| {
            let z = self.length * 0.1 + 0.5 * f as f64;
            let sway = (f as f64 * 0.7).sin();
            let centre = Vector3::new(2.0 + 0.1 * sway, EYE, z);
            let target = Vector3::new(-HALF_WIDTH, -2.0 + 0.3 * sway, z + 10.0 + sway);
            look_at(centre, target)
        };
        let files = ("sequence", "frame", "sequence_gt");
        self.write_query_set(dir, files, walk, options, camera, kept, &mut rng)?;
        Ok(options.queries)
    }

    /// One query set of `options.queries` poses from `pose_of(q, rng)`, `files` = (stem,
    /// image name prefix, ground-truth stem): `{stem}.db` with each pose's keypoints (the points it sees, with noise, and outliers),
    /// `{stem}.txt` and `{gt}.txt`.
    #[allow(clippy::too_many_arguments)]
    fn write_query_set(
        &self,
        dir: &Path,
        (stem, prefix, gt_stem): (&str, &str, &str),
        mut pose_of: impl FnMut(usize, &mut SplitMix64) -> Pose,
        options: &StreetOptions,
        camera: &Camera,
        kept: &BitSlice,
        rng: &mut SplitMix64,
    ) -> Result<(), Error> {
        let mut db = DatabaseWriter::new(&dir.join(format!("{stem}.db")))?;
        db.add_camera(camera)?;
        let (mut list, mut gt) = (String::new(), String::new());
        let (w, h) = (f64::from(WIDTH), f64::from(HEIGHT));
        for q in 0..options.queries {
            let pose = &pose_of(q, rng);
            let visible = self.detected(pose, 1_500, |p| kept[p as usize]);
            // At most 90 % outliers: a share of 1 would ask for infinitely many.
            let share = options.outlier_share.clamp(0.0, 0.9);
            let outliers = (visible.len() as f64 * share / (1.0 - share)) as usize;
            let mut keypoints = Vec::with_capacity(visible.len() + outliers);
            let mut descriptors = Vec::with_capacity((visible.len() + outliers) * DIM);
            for &(p, xy, depth) in &visible {
                let noisy = [
                    xy[0] + options.pixel_noise * gaussian(rng),
                    xy[1] + options.pixel_noise * gaussian(rng),
                ];
                keypoints.push(self.keypoint(p, noisy, depth, rng));
                observe(&self.base(p as usize), 0.25, rng, &mut descriptors);
            }
            for _ in 0..outliers {
                let xy = [
                    1.0 + (w - 2.0) * rng.next_f64(),
                    1.0 + (h - 2.0) * rng.next_f64(),
                ];
                let other = rng.below(self.positions.len()) as u32;
                keypoints.push(self.keypoint(other, xy, 10.0, rng));
                observe(&self.base(other as usize), 0.25, rng, &mut descriptors);
            }
            let name = format!("{prefix}_{q:04}.jpg");
            db.add_image(
                q as u32 + 1,
                &name,
                camera.id,
                &keypoints,
                &descriptors,
                DIM,
            )?;
            let intrinsics =
                crate::geometry::Camera::new(camera.model, WIDTH, HEIGHT, camera.params.clone())
                    .expect("the street camera is valid");
            list.push_str(&format!("{name} {intrinsics}\n"));
            gt.push_str(&crate::io::poses::colmap_pose_line(&name, pose));
            gt.push('\n');
        }
        db.write()?;
        crate::output::write_bytes(&dir.join(format!("{stem}.txt")), list.as_bytes())?;
        crate::output::write_bytes(&dir.join(format!("{gt_stem}.txt")), gt.as_bytes())?;
        Ok(())
    }
}
