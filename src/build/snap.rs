//! (issue 36) SFP map points where the network detects: `convert --images --snap`.
//!
//! An SFP map's points are the COLMAP model's, described where SIFT observed them; a query's
//! keypoints are the network's detections, a few pixels from any SIFT keypoint. Matched, the
//! two are not the same image point, and that offset, not the descriptors, is most of the SFP
//! maps' imprecision: the same sfp-v2 maps described at the queries' own SIFT keypoints
//! localized KITTI 06 at SIFT's precision (`python/probe_sift_keypoint_queries.py`).
//!
//! With `--snap`, an observation moves to the snap level's keypoint that the extractor detects
//! within [`SNAP_RADIUS_PX`] of it, if there is one and no nearer observation takes it (the
//! model's defaults: where a query's keypoint would be). A point with two or more moved
//! observations is triangulated again from them with the model's poses and moves there when
//! every one reprojects within [`super::triangulation::MAX_REPROJECTION_PX`] and its rays
//! meet at [`super::triangulation::MIN_TRIANGULATION_DEG`] or more; the snap level then describes it at the moved
//! observations, the other levels as before. Points that do not move stay as they were.
//! Measured on sfp-v2 (stop 49, `python/TRAINING-v3.md`): median errors fall on all three
//! shared scenes, full maps (KITTI 06 0.0075 → 0.0070 m, South Building 0.0017 → 0.0013,
//! Sacre-Coeur 0.0036 → 0.0032) and level-2 short maps (0.0236 → 0.0163 m, 0.0043 → 0.0037,
//! 0.045 → 0.036), for 1–8 % more bytes.

use super::triangulation::{accepted, triangulate_about, Observation};
use nalgebra::Vector3;

/// How far (network input pixels) an observation may be from the keypoint it moves to: half a
/// stride-8 cell, so it moves to a keypoint of its own cell's neighbourhood, not a neighbour's.
pub(crate) const SNAP_RADIUS_PX: f32 = 4.0;

/// The level observations snap to: the one level-2 short maps keep (the stride-8 level), or
/// the deepest of a shallower model.
pub(crate) fn snap_level(levels: usize) -> usize {
    2.min(levels.saturating_sub(1))
}

/// Where each observation moves: the index in `detected` of the keypoint nearest it within
/// [`SNAP_RADIUS_PX`], if any, and no keypoint taken by two observations: the nearer keeps it
/// (the first of equals), the other stays. Two points moved onto one keypoint would be one
/// image point twice. Time: linear in both, by a grid of cells the radius wide.
pub(crate) fn assign(detected: &[(f32, f32)], observations: &[(f32, f32)]) -> Vec<Option<usize>> {
    use std::collections::HashMap;
    let cell = |x: f32, y: f32| {
        (
            (x / SNAP_RADIUS_PX).floor() as i64,
            (y / SNAP_RADIUS_PX).floor() as i64,
        )
    };
    let mut grid: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (i, &(x, y)) in detected.iter().enumerate() {
        if x.is_finite() && y.is_finite() {
            grid.entry(cell(x, y)).or_default().push(i);
        }
    }
    let mut nearest: Vec<Option<(usize, f32)>> = observations
        .iter()
        .map(|&(x, y)| {
            if !(x.is_finite() && y.is_finite()) {
                return None;
            }
            let (cx, cy) = cell(x, y);
            let mut best: Option<(usize, f32)> = None;
            for gx in cx - 1..=cx + 1 {
                for gy in cy - 1..=cy + 1 {
                    for &i in grid.get(&(gx, gy)).into_iter().flatten() {
                        let (a, b) = detected[i];
                        let d = (a - x).powi(2) + (b - y).powi(2);
                        let closer = best.is_none_or(|(bi, bd)| d < bd || (d == bd && i < bi));
                        if d <= SNAP_RADIUS_PX * SNAP_RADIUS_PX && closer {
                            best = Some((i, d));
                        }
                    }
                }
            }
            best
        })
        .collect();
    // Each keypoint to its nearest observation (the first of equals).
    let mut taken: HashMap<usize, (usize, f32)> = HashMap::new();
    for (o, n) in nearest.iter().enumerate() {
        if let Some((i, d)) = *n {
            let e = taken.entry(i).or_insert((o, d));
            if d < e.1 {
                *e = (o, d);
            }
        }
    }
    for (o, n) in nearest.iter_mut().enumerate() {
        if let Some((i, _)) = *n {
            if taken[&i].0 != o {
                *n = None;
            }
        }
    }
    nearest.into_iter().map(|n| n.map(|(i, _)| i)).collect()
}

/// Where a point now at `around` moves from its moved observations (camera, pose, moved pixel
/// in COLMAP's convention), `px_per_input(k)` the camera pixels per network input pixel of
/// observation `k`: their triangulation when it is [`accepted`]; `None` otherwise (the point
/// stays).
pub(crate) fn moved_position(
    observations: &[Observation<'_>],
    px_per_input: impl Fn(usize) -> f64,
    around: Vector3<f64>,
) -> Option<Vector3<f64>> {
    let x = triangulate_about(observations, around)?;
    accepted(observations, px_per_input, &x).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::build::triangulation::triangulate;
    use crate::geometry::{Camera, CameraModel, Pose};
    use nalgebra::UnitQuaternion;
    use nalgebra::Vector2;

    fn camera() -> Camera {
        Camera::new(
            CameraModel::SimpleRadial,
            640,
            480,
            vec![500.0, 320.0, 240.0, 0.05],
        )
        .unwrap()
    }

    /// Cameras `step` apart on a line, looking down +z, turned a little each.
    fn poses(step: f64) -> Vec<Pose> {
        (0..3)
            .map(|i| {
                Pose::new(
                    UnitQuaternion::from_euler_angles(0.0, 0.05 * i as f64, 0.0),
                    Vector3::new(-step * i as f64, 0.1, 0.0),
                )
            })
            .collect()
    }

    fn seen<'a>(
        cam: &'a Camera,
        x: &Vector3<f64>,
        step: f64,
    ) -> Vec<(&'a Camera, Pose, Vector2<f64>)> {
        poses(step)
            .into_iter()
            .map(|pose| (cam, pose, cam.project(&pose.transform(x)).unwrap()))
            .collect()
    }

    #[test]
    fn a_point_seen_exactly_is_found_again() {
        let x = Vector3::new(0.3, -0.2, 5.0);
        let cam = camera();
        let found =
            moved_position(&seen(&cam, &x, 0.5), |_| 1.0, Vector3::new(0.2, -0.1, 4.0)).unwrap();
        assert!((found - x).norm() < 1e-6, "{found} vs {x}");
    }

    #[test]
    fn far_from_the_origin_a_point_is_found_to_a_fraction_of_a_pixel() {
        // A georeferenced scene: everything 500 km from the origin.
        let far = Vector3::new(5e5, 4e5, 0.0);
        let x = far + Vector3::new(0.3, -0.2, 5.0);
        let cam = camera();
        let obs: Vec<_> = poses(0.5)
            .into_iter()
            .map(|pose| {
                let pose = Pose::new(pose.rotation, pose.translation - pose.rotation * far);
                (&cam, pose, cam.project(&pose.transform(&x)).unwrap())
            })
            .collect();
        let found = moved_position(&obs, |_| 1.0, far + Vector3::new(0.25, -0.25, 5.1)).unwrap();
        assert!((found - x).norm() < 1e-6, "{found} vs {x}");
    }

    #[test]
    fn observations_that_disagree_too_few_or_too_close_leave_the_point() {
        let x = Vector3::new(0.3, -0.2, 5.0);
        let cam = camera();
        let mut obs = seen(&cam, &x, 0.5);
        // One observation 10 px off: no point reprojects within 2 px in all three views.
        obs[1].2.x += 10.0;
        assert_eq!(moved_position(&obs, |_| 1.0, x), None);
        // One view fixes no point.
        assert_eq!(moved_position(&obs[..1], |_| 1.0, x), None);
        assert_eq!(triangulate(&[]), None);
        // Cameras 5 cm apart see the point at 5 m under about 1 degree: exact, still refused.
        let narrow = seen(&cam, &x, 0.05);
        assert!(triangulate(
            &narrow
                .iter()
                .map(|(c, p, px)| (*p, c.unproject(px)))
                .collect::<Vec<_>>()
        )
        .is_some());
        assert_eq!(moved_position(&narrow, |_| 1.0, x), None);
    }

    #[test]
    fn an_observation_moves_to_the_nearest_keypoint_within_the_radius_and_only_one_takes_it() {
        let detected = [(10.0, 10.0), (13.0, 10.0), (30.0, 30.0), (-3.0, -3.0)];
        // (12, 10): (13, 10) is nearer; (11.5, 10): equally far from both, the first;
        // (20, 20): none within 4 px; (-1, -2): across a cell border, (-3, -3).
        let obs = [(12.0, 10.0), (20.0, 20.0), (-1.0, -2.0), (f32::NAN, 0.0)];
        assert_eq!(assign(&detected, &obs), [Some(1), None, Some(3), None]);
        assert_eq!(assign(&detected, &[(11.5, 10.0)]), [Some(0)]);
        // Two observations nearest to (13, 10): the nearer keeps it, the other stays.
        assert_eq!(
            assign(&detected, &[(14.5, 10.0), (13.5, 10.0)]),
            [None, Some(1)]
        );
        assert_eq!(assign(&[], &obs), [None, None, None, None]);
    }

    #[test]
    fn the_snap_level_is_level_2_or_the_deepest() {
        assert_eq!(snap_level(4), 2);
        assert_eq!(snap_level(3), 2);
        assert_eq!(snap_level(2), 1);
        assert_eq!(snap_level(1), 0);
    }
}
