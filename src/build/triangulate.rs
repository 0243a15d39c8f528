//! (issue 36) Map points from the network's own keypoints: `convert --images --triangulate`.
//!
//! `--snap` moves the model's SIFT observations onto nearby network keypoints; most SIFT points
//! have none near, and a query's keypoints still meet the map's points only where the two
//! happen to coincide. Here the model gives only its poses, as hloc's triangulation from a
//! reference model does: every image's keypoints of the snap level (the extractor's own
//! detection, where a query's keypoints are) are matched to those of the images it shares the
//! most points with ([`PAIRS_PER_IMAGE`], the model's covisibility), by mutual nearest
//! neighbour on the descriptors, kept where the pair's epipolar geometry agrees within
//! [`MAX_EPIPOLAR_PX`]; matches join into tracks (connected components), and a track is a
//! point where its triangulation reprojects within [`snap::MAX_REPROJECTION_PX`] in every
//! view it keeps and its rays meet at [`snap::MIN_TRIANGULATION_DEG`] or more. The result is a
//! reconstruction with the model's cameras and poses whose points are those tracks; the SFP
//! conversion then describes and assigns levels to them as to any model's points.

use super::snap;
use crate::colmap::{Image, Point2D, Reconstruction, TrackElement};
use crate::geometry::{Camera, Pose};
use nalgebra::{Matrix3, Vector2, Vector3};

/// Each image is matched to at most this many others, those it shares the most model points
/// with (hloc's `pairs_from_covisibility` for triangulation takes 20).
pub(crate) const PAIRS_PER_IMAGE: usize = 20;

/// A match is kept when its Sampson distance to the pair's epipolar geometry is at most this
/// (pixels, by the pair's mean focal length): the keypoints sit within a pixel or two of one
/// image point and the poses are the model's, so a wrong match is far more often far off.
pub(crate) const MAX_EPIPOLAR_PX: f64 = 4.0;

/// Views a track needs to become a point (after the views that disagree are dropped). Two views
/// are fixed only along the epipolar line, which a wrong match also satisfies.
pub(crate) const MIN_TRACK_VIEWS: usize = 3;

/// One model image's keypoints, as matched: pixels in the model's camera (COLMAP's convention)
/// and their descriptors (`dims` each, unit length).
#[derive(Debug, Default)]
pub(crate) struct ImageKeypoints {
    pub xy: Vec<[f64; 2]>,
    pub descriptors: Vec<f32>,
}

/// What the triangulation did (provenance `parameters.triangulate`).
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct TriangulationSummary {
    pub pairs: usize,
    pub matches: usize,
    pub points: usize,
    pub observations: usize,
}

/// The image pairs `(i, j)`, `i < j`, by position in `model.images()`: each image with the
/// [`PAIRS_PER_IMAGE`] images it shares the most points with (ties by position). Time: the sum
/// over points of their track length squared.
pub(crate) fn covisible_pairs(model: &Reconstruction) -> Vec<(usize, usize)> {
    let n = model.images().len();
    let mut shared = vec![0u32; n];
    let mut touched: Vec<usize> = Vec::new();
    let mut pairs = Vec::new();
    for (i, image) in model.images().iter().enumerate() {
        for p in &image.points2d {
            let Some(point) = p.point3d_id.and_then(|id| model.point3d(id)) else {
                continue;
            };
            for e in model.track(point) {
                match model.image_index(e.image_id) {
                    Some(j) if j != i => {
                        if shared[j] == 0 {
                            touched.push(j);
                        }
                        shared[j] += 1;
                    }
                    _ => {}
                }
            }
        }
        touched.sort_unstable_by_key(|&j| (std::cmp::Reverse(shared[j]), j));
        pairs.extend(
            touched
                .iter()
                .take(PAIRS_PER_IMAGE)
                .map(|&j| (i.min(j), i.max(j))),
        );
        for &j in &touched {
            shared[j] = 0;
        }
        touched.clear();
    }
    pairs.sort_unstable();
    pairs.dedup();
    pairs
}

/// Mutual nearest neighbours of `a`'s and `b`'s descriptors (`dims` each) by dot product:
/// `(index in a, index in b)`. Time: |a| · |b| · dims.
pub(crate) fn mutual_nearest(a: &[f32], b: &[f32], dims: usize) -> Vec<(u32, u32)> {
    if dims == 0 {
        return Vec::new();
    }
    let (na, nb) = (a.len() / dims, b.len() / dims);
    let mut best_of_b = vec![(f32::NEG_INFINITY, u32::MAX); nb];
    let mut best_of_a = vec![(f32::NEG_INFINITY, u32::MAX); na];
    for (i, x) in a.chunks_exact(dims).enumerate() {
        for (j, y) in b.chunks_exact(dims).enumerate() {
            let s = crate::vector::dot(x, y);
            if s > best_of_a[i].0 {
                best_of_a[i] = (s, j as u32);
            }
            if s > best_of_b[j].0 {
                best_of_b[j] = (s, i as u32);
            }
        }
    }
    best_of_a
        .iter()
        .enumerate()
        .filter(|(i, (_, j))| *j != u32::MAX && best_of_b[*j as usize].1 == *i as u32)
        .map(|(i, &(_, j))| (i as u32, j))
        .collect()
}

/// A pair's epipolar geometry from the model's poses: `b_from_a`'s essential matrix.
fn essential(a: &Pose, b: &Pose) -> Option<Matrix3<f64>> {
    let b_from_a = b.compose(&a.inverse());
    let t = b_from_a.translation;
    // No baseline: no epipolar geometry, and no point to triangulate either.
    if t.norm() <= 1e-12 * (1.0 + a.translation.norm()) || !t.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(t.normalize().cross_matrix() * b_from_a.rotation_matrix().matrix())
}

/// The Sampson distance of normalised image points `xa`, `xb` to `e` (normalised units).
fn sampson(e: &Matrix3<f64>, xa: &Vector2<f64>, xb: &Vector2<f64>) -> f64 {
    let (ha, hb) = (Vector3::new(xa.x, xa.y, 1.0), Vector3::new(xb.x, xb.y, 1.0));
    let (ea, eb) = (e * ha, e.transpose() * hb);
    let r = hb.dot(&ea);
    let d = ea.x * ea.x + ea.y * ea.y + eb.x * eb.x + eb.y * eb.y;
    if d > 0.0 {
        (r * r / d).sqrt()
    } else {
        f64::INFINITY
    }
}

/// Union–find over every image's keypoints (hand-written: fifteen lines, and no crate in the
/// tree has one).
struct Components {
    parent: Vec<u32>,
}

impl Components {
    fn new(n: usize) -> Components {
        Components {
            parent: (0..n as u32).collect(),
        }
    }

    fn root(&mut self, mut x: u32) -> u32 {
        while self.parent[x as usize] != x {
            let up = self.parent[self.parent[x as usize] as usize];
            self.parent[x as usize] = up;
            x = up;
        }
        x
    }

    fn join(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.root(a), self.root(b));
        if ra != rb {
            self.parent[ra.max(rb) as usize] = ra.min(rb);
        }
    }
}

/// Where a track's views put its point: the triangulation of the views left after dropping,
/// one at a time, the one that reprojects worst while any is beyond
/// [`snap::MAX_REPROJECTION_PX`] (or behind its camera); `None` when fewer than
/// [`MIN_TRACK_VIEWS`] are left or their rays meet too narrowly. `views` keeps those used.
fn track_position(views: &mut Vec<(&Camera, Pose, Vector2<f64>, usize)>) -> Option<Vector3<f64>> {
    loop {
        if views.len() < MIN_TRACK_VIEWS {
            return None;
        }
        // About the cameras' mean centre: georeferenced coordinates would leave the linear
        // system too poorly conditioned to place a point to a pixel.
        let around = views.iter().map(|v| v.1.center()).sum::<Vector3<f64>>() / views.len() as f64;
        let observations: Vec<(&Camera, Pose, Vector2<f64>)> =
            views.iter().map(|v| (v.0, v.1, v.2)).collect();
        let x = snap::triangulate_about(&observations, around)?;
        let worst = views
            .iter()
            .enumerate()
            .map(|(k, v)| (k, snap::reprojection_px(v.0, &v.1, &x, &v.2)))
            .max_by(|a, b| a.1.total_cmp(&b.1))?;
        if worst.1 <= snap::MAX_REPROJECTION_PX {
            return snap::rays_meet_widely(views.iter().map(|v| (x - v.1.center()).normalize()))
                .then_some(x);
        }
        views.swap_remove(worst.0);
    }
}

/// The reconstruction whose points are `keypoints` matched across `model`'s covisible images
/// and triangulated with its poses (the module's rule); `keypoints[k]` is image `k`'s
/// (`model.images()` order), `dims` its descriptors' length. The images keep their ids, names,
/// cameras and poses; their 2D points are their keypoints.
pub(crate) fn network_points(
    model: &Reconstruction,
    keypoints: &[ImageKeypoints],
    dims: usize,
    reporter: &dyn crate::progress::Reporter,
) -> crate::colmap::Result<(Reconstruction, TriangulationSummary)> {
    let cameras: Vec<Option<Camera>> = model
        .images()
        .iter()
        .map(|i| {
            model
                .camera(i.camera_id)
                .and_then(super::sfp::geometry_camera)
        })
        .collect();
    // Each keypoint's normalised image coordinates, once.
    let normalised: Vec<Vec<Vector2<f64>>> = keypoints
        .iter()
        .zip(&cameras)
        .map(|(k, c)| match c {
            Some(c) => {
                k.xy.iter()
                    .map(|p| c.unproject(&Vector2::new(p[0], p[1])))
                    .collect()
            }
            None => Vec::new(),
        })
        .collect();
    let offsets: Vec<u32> = keypoints
        .iter()
        .scan(0u32, |at, k| {
            let start = *at;
            *at += k.xy.len() as u32;
            Some(start)
        })
        .collect();
    let total: usize = keypoints.iter().map(|k| k.xy.len()).sum();
    let mut components = Components::new(total);
    let pairs = covisible_pairs(model);
    let mut summary = TriangulationSummary {
        pairs: pairs.len(),
        ..Default::default()
    };
    reporter.start("matching keypoints", Some(pairs.len() as u64));
    for &(i, j) in &pairs {
        reporter.advance(1);
        let (Some(ci), Some(cj)) = (&cameras[i], &cameras[j]) else {
            continue;
        };
        let (pi, pj) = (
            &model.images()[i].cam_from_world,
            &model.images()[j].cam_from_world,
        );
        let Some(e) = essential(pi, pj) else {
            continue;
        };
        let focal = 0.5 * (ci.mean_focal() + cj.mean_focal());
        for (a, b) in mutual_nearest(&keypoints[i].descriptors, &keypoints[j].descriptors, dims) {
            let (xa, xb) = (&normalised[i][a as usize], &normalised[j][b as usize]);
            if sampson(&e, xa, xb) * focal <= MAX_EPIPOLAR_PX {
                components.join(offsets[i] + a, offsets[j] + b);
                summary.matches += 1;
            }
        }
    }
    reporter.finish();

    // Tracks: keypoints grouped by component, in image order within each.
    let mut image_of = Vec::with_capacity(total);
    for (k, kp) in keypoints.iter().enumerate() {
        image_of.extend(std::iter::repeat_n(k as u32, kp.xy.len()));
    }
    let mut order: Vec<(u32, u32)> = (0..total as u32).map(|g| (components.root(g), g)).collect();
    order.sort_unstable();
    // point3d_id per keypoint (0: none).
    let mut assigned = vec![0u64; total];
    let mut builder = Reconstruction::builder();
    for c in model.cameras() {
        builder.add_camera(c.clone());
    }
    let mut next_id = 1u64;
    let mut track: Vec<TrackElement> = Vec::new();
    for group in order.chunk_by(|a, b| a.0 == b.0) {
        if group.len() < MIN_TRACK_VIEWS {
            continue;
        }
        // An image seen twice in one track is a chain of matches gone astray: its views go.
        let mut views: Vec<(&Camera, Pose, Vector2<f64>, usize)> = Vec::new();
        let images: Vec<u32> = group.iter().map(|g| image_of[g.1 as usize]).collect();
        for (g, &k) in group.iter().zip(&images) {
            if images.iter().filter(|&&m| m == k).count() > 1 {
                continue;
            }
            let Some(camera) = cameras[k as usize].as_ref() else {
                continue;
            };
            let local = (g.1 - offsets[k as usize]) as usize;
            let px = keypoints[k as usize].xy[local];
            let pose = model.images()[k as usize].cam_from_world;
            views.push((camera, pose, Vector2::new(px[0], px[1]), g.1 as usize));
        }
        let Some(x) = track_position(&mut views) else {
            continue;
        };

        track.clear();
        let mut error = 0.0;
        for v in &views {
            let k = image_of[v.3] as usize;
            assigned[v.3] = next_id;
            error += snap::reprojection_px(v.0, &v.1, &x, &v.2);
            track.push(TrackElement {
                image_id: model.images()[k].id,
                point2d_idx: v.3 as u32 - offsets[k],
            });
        }
        builder.add_point3d(
            next_id,
            [x.x, x.y, x.z],
            [128, 128, 128],
            error / views.len() as f64,
            &track,
        )?;
        summary.points += 1;
        summary.observations += views.len();
        next_id += 1;
    }
    for (k, image) in model.images().iter().enumerate() {
        let points2d = keypoints[k]
            .xy
            .iter()
            .enumerate()
            .map(|(local, &xy)| {
                let id = assigned[offsets[k] as usize + local];
                Point2D {
                    xy,
                    point3d_id: (id != 0).then_some(id),
                }
            })
            .collect();
        builder.add_image(Image {
            id: image.id,
            name: image.name.clone(),
            camera_id: image.camera_id,
            cam_from_world: image.cam_from_world,
            points2d,
        });
    }
    Ok((builder.build()?, summary))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mutual_nearest_keeps_only_pairs_that_choose_each_other() {
        // a0 → b0 and b0 → a0; a1 → b0 too but b0 prefers a0; b1 → a1 but a1 prefers b0.
        let a = [1.0, 0.0, 0.8, 0.6];
        let b = [1.0, 0.0, 0.6, 0.8];
        assert_eq!(mutual_nearest(&a, &b, 2), vec![(0, 0)]);
        assert!(mutual_nearest(&a, &[], 2).is_empty());
    }

    #[test]
    fn sampson_distance_is_zero_on_the_epipolar_line_and_grows_off_it() {
        let a = Pose::identity();
        let b = Pose::new(
            nalgebra::UnitQuaternion::identity(),
            Vector3::new(-1.0, 0.0, 0.0),
        );
        let e = essential(&a, &b).unwrap();
        let x = Vector3::new(0.3, -0.2, 4.0);
        let (pa, pb) = (a.transform(&x), b.transform(&x));
        let (xa, xb) = (pa.xy() / pa.z, pb.xy() / pb.z);
        assert!(sampson(&e, &xa, &xb) < 1e-12);
        let off = xb + Vector2::new(0.0, 0.01);
        assert!((sampson(&e, &xa, &off) - 0.01).abs() < 1e-3);
        assert!(essential(&a, &a).is_none());
    }

    #[test]
    fn components_join_transitively() {
        let mut c = Components::new(5);
        c.join(0, 3);
        c.join(3, 4);
        assert_eq!(c.root(4), c.root(0));
        assert_ne!(c.root(1), c.root(0));
    }
}
