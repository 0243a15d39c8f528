//! The built-in demo scene: a textured room rendered by ray casting from known poses, with
//! a COLMAP text model of its database images. Nothing is downloaded; the same seed gives
//! the same scene, images and model. `sfpmap demo` renders it, converts it and localizes its
//! queries.
//!
//! The room is an axis-aligned box with a few boxes inside (pillars and a table) for depth
//! and occlusion. Every surface carries a procedural texture — value-noise at several
//! octaves plus sparse blobs and edges — so a keypoint detector finds corners at all scales.
//! 3D points are sampled on the surfaces; an image observes a point when it projects inside
//! the frame and the ray from the camera reaches that surface point unoccluded.

pub mod street;

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use crate::colmap::{text, Camera, Image, Point2D, Reconstruction, TrackElement};
use crate::geometry::{CameraModel, Pose};

/// Image width of the demo camera, pixels.
pub const WIDTH: u32 = 640;
/// Image height of the demo camera, pixels.
pub const HEIGHT: u32 = 480;
/// PINHOLE f, f, cx, cy (COLMAP pixel convention).
pub(crate) const FOCAL: f64 = 420.0;

type V3 = Vector3<f64>;

/// An axis-aligned box; `inside` boxes are seen from within (the room), others from outside.
#[derive(Debug, Clone, Copy)]
struct Cuboid {
    min: V3,
    max: V3,
    inside: bool,
    texture_seed: u32,
}

/// A camera at `center` looking at `target`, y down (COLMAP: x right, y down, z forward), as
/// `cam_from_world` with `qw >= 0`.
pub(crate) fn look_at(center: V3, target: V3) -> Pose {
    let z = (target - center).normalize();
    let x = z.cross(&V3::new(0.0, -1.0, 0.0)).normalize();
    let y = z.cross(&x);
    // Rows x, y, z: world → camera.
    let rows = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(rows));
    // One sign of the two quaternions of a rotation, so the model's text is canonical.
    let rotation = if rotation.w < 0.0 {
        UnitQuaternion::new_unchecked(-rotation.into_inner())
    } else {
        rotation
    };
    Pose::new(rotation, -(rows * center))
}

/// COLMAP camera 1: PINHOLE with focal `focal` and the principal point at the centre.
fn pinhole(width: u32, height: u32, focal: f64) -> Camera {
    Camera {
        id: 1,
        model: CameraModel::Pinhole,
        width: u64::from(width),
        height: u64::from(height),
        params: vec![
            focal,
            focal,
            f64::from(width) / 2.0,
            f64::from(height) / 2.0,
        ],
    }
}

/// The scene: geometry, cameras and sampled surface points.
#[derive(Debug, Clone)]
pub struct DemoScene {
    boxes: Vec<Cuboid>,
    /// The database images: name and `cam_from_world`.
    pub database: Vec<(String, Pose)>,
    /// The query images: name and true `cam_from_world`.
    pub queries: Vec<(String, Pose)>,
    /// The 3D points sampled on the surfaces, world coordinates.
    pub points: Vec<V3>,
}

fn hash(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^ (x >> 16)
}

fn lattice(ix: i64, iy: i64, seed: u32) -> f64 {
    let h = hash(
        (ix as u32).wrapping_mul(0x9E37_79B1) ^ hash((iy as u32) ^ seed.wrapping_mul(0x85EB_CA77)),
    );
    f64::from(h) / f64::from(u32::MAX)
}

/// Smooth value noise in [0, 1].
fn value_noise(u: f64, v: f64, seed: u32) -> f64 {
    let (x0, y0) = (u.floor(), v.floor());
    let (fx, fy) = (u - x0, v - y0);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (ix, iy) = (x0 as i64, y0 as i64);
    let a = lattice(ix, iy, seed);
    let b = lattice(ix + 1, iy, seed);
    let c = lattice(ix, iy + 1, seed);
    let d = lattice(ix + 1, iy + 1, seed);
    let top = a + (b - a) * sx;
    let bottom = c + (d - c) * sx;
    top + (bottom - top) * sy
}

/// The surface texture at (u, v) metres on a face: octaves of noise, plus dark and bright
/// blobs and crisp rectangles (posters, tiles) on a cell grid, so corners exist at all scales.
fn texture(u: f64, v: f64, seed: u32) -> f64 {
    let mut value = 0.0;
    let mut amplitude = 0.5;
    let mut frequency = 1.5;
    for octave in 0..5 {
        value += amplitude
            * value_noise(
                u * frequency,
                v * frequency,
                seed.wrapping_add(octave * 101),
            );
        amplitude *= 0.5;
        frequency *= 2.3;
    }
    let cell = 0.45;
    let (cx, cy) = ((u / cell).floor(), (v / cell).floor());
    let r = lattice(cx as i64, cy as i64, seed ^ 0xA5A5);
    let (fu, fv) = (u / cell - cx, v / cell - cy);
    if r < 0.25 {
        // A blob.
        let (du, dv) = (fu - 0.5, fv - 0.5);
        let d2 = (du * du + dv * dv) / (0.05 + 0.1 * r);
        value += if r < 0.12 { -0.45 } else { 0.45 } * (-d2).exp();
    } else if r < 0.4 && fu > 0.15 && fu < 0.85 && fv > 0.2 && fv < 0.7 {
        // A rectangle with an inner pattern.
        value = 0.15
            + 0.7
                * lattice(
                    (fu * 4.0) as i64 + cx as i64 * 7,
                    (fv * 3.0) as i64 + cy as i64 * 5,
                    seed ^ 0x5A5A,
                );
    }
    value.clamp(0.0, 1.0)
}

impl Cuboid {
    /// Ray hit: distance and the texture value at the hit, if the ray meets a face.
    fn hit(&self, origin: &V3, dir: &V3) -> Option<(f64, f64)> {
        let mut best: Option<(f64, f64)> = None;
        for axis in 0..3 {
            if dir[axis].abs() < 1e-12 {
                continue;
            }
            for (side, plane) in [(0, self.min[axis]), (1, self.max[axis])] {
                let t = (plane - origin[axis]) / dir[axis];
                if t <= 1e-6 || best.is_some_and(|b| t >= b.0) {
                    continue;
                }
                let p = origin + t * dir;
                let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
                let eps = 1e-9;
                if p[a] < self.min[a] - eps
                    || p[a] > self.max[a] + eps
                    || p[b] < self.min[b] - eps
                    || p[b] > self.max[b] + eps
                {
                    continue;
                }
                // Faces seen from the wrong side are skipped (a room is seen from inside).
                let outward = if side == 0 { -1.0 } else { 1.0 };
                let facing = dir[axis] * outward < 0.0;
                if facing == self.inside {
                    continue;
                }
                let seed = self
                    .texture_seed
                    .wrapping_add((axis * 2 + side) as u32 * 7919);
                best = Some((t, texture(p[a], p[b], seed)));
            }
        }
        best
    }
}

impl DemoScene {
    /// The standard demo scene: a 12 × 4 × 10 m room with two pillars and a table, 36 database
    /// images on a loop around the room looking outwards and across, and 8 queries between them.
    pub fn new(seed: u32) -> DemoScene {
        let boxes = vec![
            Cuboid {
                min: V3::new(-6.0, -3.0, -5.0),
                max: V3::new(6.0, 1.0, 5.0),
                inside: true,
                texture_seed: seed,
            },
            Cuboid {
                min: V3::new(-4.6, -3.0, -3.6),
                max: V3::new(-3.8, 1.0, -2.8),
                inside: false,
                texture_seed: seed ^ 0x1111,
            },
            Cuboid {
                min: V3::new(3.9, -3.0, 2.8),
                max: V3::new(4.7, 1.0, 3.6),
                inside: false,
                texture_seed: seed ^ 0x2222,
            },
            Cuboid {
                min: V3::new(-0.9, 0.2, -0.5),
                max: V3::new(0.9, 0.4, 0.5),
                inside: false,
                texture_seed: seed ^ 0x3333,
            },
        ];
        let ring = |angle: f64, radius: f64, height: f64| {
            V3::new(radius * angle.cos(), height, radius * angle.sin() * 0.8)
        };
        let mut database = Vec::new();
        let n = 36;
        for i in 0..n {
            let a = std::f64::consts::TAU * i as f64 / n as f64;
            let center = ring(a, 3.2, -0.4 + 0.15 * (i % 3) as f64);
            // Alternate: look outwards at the walls, or across the room.
            let target = if i % 2 == 0 {
                ring(a + 0.35, 9.0, -0.6)
            } else {
                ring(a + std::f64::consts::PI + 0.3, 4.0, -0.8)
            };
            database.push((format!("db_{i:03}.png"), look_at(center, target)));
        }
        let mut queries = Vec::new();
        for i in 0..8 {
            let a = std::f64::consts::TAU * (i as f64 + 0.43) / 8.0;
            let center = ring(a, 2.7, -0.55);
            let target = if i % 2 == 0 {
                ring(a + 0.2, 9.0, -0.4)
            } else {
                ring(a + std::f64::consts::PI + 0.5, 4.0, -0.9)
            };
            queries.push((format!("query_{i:02}.png"), look_at(center, target)));
        }
        // Surface points: uniform on every face, density per square metre.
        let mut points = Vec::new();
        let mut state = seed.wrapping_mul(2654435761) | 1;
        let mut rand = move || {
            state = hash(state.wrapping_add(0x9E37_79B9));
            f64::from(state) / f64::from(u32::MAX)
        };
        for b in &boxes {
            for axis in 0..3 {
                let (a, c) = ((axis + 1) % 3, (axis + 2) % 3);
                let area = (b.max[a] - b.min[a]) * (b.max[c] - b.min[c]);
                let count = (area * 120.0) as usize;
                for side in [b.min[axis], b.max[axis]] {
                    for _ in 0..count {
                        let mut p = V3::zeros();
                        p[axis] = side;
                        p[a] = b.min[a] + rand() * (b.max[a] - b.min[a]);
                        p[c] = b.min[c] + rand() * (b.max[c] - b.min[c]);
                        points.push(p);
                    }
                }
            }
        }
        DemoScene {
            boxes,
            database,
            queries,
            points,
        }
    }

    /// The first surface hit along a ray: distance and intensity.
    fn trace(&self, origin: &V3, dir: &V3) -> Option<(f64, f64)> {
        self.boxes
            .iter()
            .filter_map(|b| b.hit(origin, dir))
            .min_by(|a, b| a.0.total_cmp(&b.0))
    }

    /// Renders an 8-bit grayscale image (`WIDTH × HEIGHT`, row-major), 2×2 supersampled,
    /// with distance shading.
    pub fn render(&self, pose: &Pose) -> Vec<u8> {
        let center = pose.center();
        let world_from_cam = pose.rotation.inverse();
        let mut out = Vec::with_capacity((WIDTH * HEIGHT) as usize);
        for y in 0..HEIGHT {
            for x in 0..WIDTH {
                let mut sum = 0.0;
                for (sx, sy) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                    // Pixel (x, y) covers [x, x+1): its centre is x + 0.5 (COLMAP convention).
                    let u = (f64::from(x) + sx - f64::from(WIDTH) / 2.0) / FOCAL;
                    let v = (f64::from(y) + sy - f64::from(HEIGHT) / 2.0) / FOCAL;
                    let d = (world_from_cam * V3::new(u, v, 1.0)).normalize();
                    let value = match self.trace(&center, &d) {
                        Some((t, tex)) => tex * (1.0 / (1.0 + 0.02 * t)),
                        None => 0.0,
                    };
                    sum += value;
                }
                out.push((sum / 4.0 * 255.0).round().clamp(0.0, 255.0) as u8);
            }
        }
        out
    }

    /// Pixel of world point `p` in the image of `pose`, if in front and inside the frame.
    pub fn project(&self, pose: &Pose, p: &V3) -> Option<[f64; 2]> {
        let c = pose.transform(p);
        if c[2] <= 0.1 {
            return None;
        }
        let x = FOCAL * c[0] / c[2] + f64::from(WIDTH) / 2.0;
        let y = FOCAL * c[1] / c[2] + f64::from(HEIGHT) / 2.0;
        (x >= 2.0 && y >= 2.0 && x <= f64::from(WIDTH) - 2.0 && y <= f64::from(HEIGHT) - 2.0)
            .then_some([x, y])
    }

    /// Whether `p` is the first surface the ray from the camera meets.
    fn visible(&self, pose: &Pose, p: &V3) -> bool {
        let center = pose.center();
        let to = p - center;
        let dist = to.norm();
        match self.trace(&center, &to.normalize()) {
            Some((t, _)) => (t - dist).abs() < 1e-3 * dist.max(1.0),
            None => false,
        }
    }

    /// The database images' COLMAP model: one PINHOLE camera, the images with every
    /// visible projected point as a 2D point, and points seen by at least 2 images.
    pub fn colmap_model(&self) -> Reconstruction {
        let mut observations: Vec<Vec<(usize, [f64; 2])>> = vec![Vec::new(); self.database.len()];
        let mut tracks: Vec<Vec<TrackElement>> = vec![Vec::new(); self.points.len()];
        for (i, (_, pose)) in self.database.iter().enumerate() {
            for (p, xyz) in self.points.iter().enumerate() {
                if let Some(px) = self.project(pose, xyz) {
                    if self.visible(pose, xyz) {
                        tracks[p].push(TrackElement {
                            image_id: i as u32 + 1,
                            point2d_idx: observations[i].len() as u32,
                        });
                        observations[i].push((p, px));
                    }
                }
            }
        }
        let kept = |p: usize| tracks[p].len() >= 2;
        let mut model = Reconstruction::builder();
        model.add_camera(pinhole(WIDTH, HEIGHT, FOCAL));
        for (i, (name, pose)) in self.database.iter().enumerate() {
            model.add_image(Image {
                id: i as u32 + 1,
                name: name.clone(),
                camera_id: 1,
                cam_from_world: *pose,
                points2d: observations[i]
                    .iter()
                    .map(|&(p, xy)| Point2D {
                        xy,
                        point3d_id: kept(p).then_some(p as u64 + 1),
                    })
                    .collect(),
            });
        }
        for (p, xyz) in self.points.iter().enumerate() {
            if kept(p) {
                model
                    .add_point3d(p as u64 + 1, (*xyz).into(), [128; 3], 0.0, &tracks[p])
                    .expect("tracks are short");
            }
        }
        model
            .build()
            .expect("the demo model is consistent by construction")
    }

    /// [`colmap_model`](Self::colmap_model) as `cameras.txt`, `images.txt`, `points3D.txt`.
    pub fn colmap_text(&self) -> (String, String, String) {
        let model = self.colmap_model();
        (
            text::write_cameras(&model),
            text::write_images(&model),
            text::write_points3d(&model),
        )
    }

    /// `name PINHOLE W H f f cx cy` lines for the queries (hloc style).
    pub fn query_list(&self) -> String {
        let params = vec![
            FOCAL,
            FOCAL,
            f64::from(WIDTH) / 2.0,
            f64::from(HEIGHT) / 2.0,
        ];
        let camera = crate::geometry::Camera::new(CameraModel::Pinhole, WIDTH, HEIGHT, params)
            .expect("the demo camera is valid");
        let mut s = String::new();
        for (name, _) in &self.queries {
            // `Camera`'s Display is what `Camera::parse_query_line` reads back.
            let _ = writeln!(s, "{name} {camera}");
        }
        s
    }

    /// Ground truth: `name qw qx qy qz tx ty tz` lines.
    pub fn gt_poses(&self) -> String {
        let mut s = String::new();
        for (name, pose) in &self.queries {
            s.push_str(&crate::io::poses::colmap_pose_line(name, pose));
            s.push('\n');
        }
        s
    }
}

/// Writes a grayscale PNG through [`crate::output::AtomicFile`]; errors name `path`.
pub fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    gray: &[u8],
) -> Result<(), crate::output::OutputError> {
    use image::ImageEncoder;
    let mut out = crate::output::AtomicFile::create(path)?;
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(gray, width, height, image::ExtendedColorType::L8)
        .map_err(|e| {
            let source = match e {
                image::ImageError::IoError(e) => e,
                e => std::io::Error::other(e),
            };
            crate::output::OutputError::cannot_write(path, source)
        })?;
    out.commit()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn poses_round_trip_and_points_project_where_rays_land() {
        let scene = DemoScene::new(1);
        let (_, pose) = &scene.database[0];
        let c = pose.center();
        let back = pose.transform(&c);
        assert!(back.iter().all(|v| v.abs() < 1e-9));
        assert!((pose.rotation.quaternion().norm() - 1.0).abs() < 1e-9);
        assert!(pose.rotation.w >= 0.0);
        let seen = scene
            .points
            .iter()
            .filter(|&p| scene.project(pose, p).is_some() && scene.visible(pose, p))
            .count();
        assert!(seen > 200, "{seen}");
    }

    #[test]
    fn the_colmap_text_reads_back_as_the_model() {
        let scene = DemoScene::new(1);
        let model = scene.colmap_model();
        assert_eq!(model.images().len(), scene.database.len());
        assert!(model.points3d().len() > 1000, "{}", model.points3d().len());
        let (c, i, p) = scene.colmap_text();
        let path = Path::new("demo");
        let read = text::parse_model(
            (c.as_bytes(), path),
            (i.as_bytes(), path),
            (p.as_bytes(), path),
        )
        .unwrap();
        assert_eq!(read, model);
    }

    #[test]
    fn texture_has_contrast() {
        let values: Vec<f64> = (0..1000)
            .map(|i| texture(i as f64 * 0.013, (i * 7 % 1000) as f64 * 0.011, 3))
            .collect();
        let mean = values.iter().sum::<f64>() / 1000.0;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 1000.0;
        assert!(var.sqrt() > 0.08, "{}", var.sqrt());
    }
}
