//! (issue 36) SFP map points where the network detects: `convert --images --snap`.
//!
//! An SFP map's points are the COLMAP model's, described where SIFT observed them; a query's
//! keypoints are the network's detections, a few pixels from any SIFT keypoint. Matched, the
//! two are not the same image point, and that offset, not the descriptors, is most of the SFP
//! maps' imprecision: the same sfp-v2 maps described at the queries' own SIFT keypoints
//! localized KITTI 06 at SIFT's precision (`python/probe_sift_keypoint_queries.py`).
//!
//! With `--snap`, an observation moves to the snap level's keypoint that the extractor detects
//! within [`SNAP_RADIUS_PX`] of it, if there is one (the model's threshold, NMS and refinement:
//! where a query's keypoint would be). A point with two or more moved observations is
//! triangulated again from them with the model's poses and moves there when every one
//! reprojects within [`MAX_REPROJECTION_PX`] and its rays meet at
//! [`MIN_TRIANGULATION_DEG`] or more; the snap level then describes it at the moved
//! observations, the other levels as before. Points that do not move stay as they were.
//! Measured on sfp-v2 (stop 49, `python/TRAINING-v3.md`): full maps gain on all three shared
//! scenes (KITTI 06 0.0075 → 0.0067 m, South Building 0.0017 → 0.0012, Sacre-Coeur 0.0036 →
//! 0.0031); level-2 short maps on KITTI 06 and South Building (0.0236 → 0.0162 m, 0.0043 →
//! 0.0031) but Sacre-Coeur's localizes one of its two queries instead of both.

use crate::extract::contract::Contract;
use crate::extract::{keypoints, Dense};
use crate::geometry::{Camera, Pose};
use nalgebra::{Matrix4, Vector2, Vector3, Vector4};

/// How far (pixels, in the model's camera) a moved observation may lie from its re-triangulated
/// point's projection: the network's keypoints sit within a pixel or two of one image point
/// (its level-2 MMA@3 on held-out pairs is 0.74).
pub(crate) const MAX_REPROJECTION_PX: f64 = 2.0;

/// How far (network input pixels) an observation may be from the keypoint it moves to: half a
/// stride-8 cell, so it moves to a keypoint of its own cell's neighbourhood, not a neighbour's.
pub(crate) const SNAP_RADIUS_PX: f32 = 4.0;

/// The widest angle (degrees) between a moved point's rays must be at least this: rays
/// meeting at a small angle fix the depth poorly, and a pixel moves the point far along them
/// (Sacre-Coeur's narrow baselines; COLMAP's triangulator asks 1.5).
pub(crate) const MIN_TRIANGULATION_DEG: f64 = 2.0;

/// The level observations snap to: the one level-2 short maps keep (the stride-8 level), or
/// the deepest of a shallower model.
pub(crate) fn snap_level(levels: usize) -> usize {
    2.min(levels.saturating_sub(1))
}

/// Level `level`'s keypoints as the extractor detects them with the model's defaults (NMS
/// radius, threshold, cap), in input pixels, refined down to level `finest` (`finest ==
/// level`: not refined).
pub(crate) fn detected(
    dense: &Dense,
    contract: &Contract,
    level: usize,
    finest: usize,
) -> Vec<(f32, f32)> {
    let l = &dense.levels[level];
    let stride = l.stride as f32;
    let peaks = keypoints::detect(
        l.score_map(),
        contract.default_nms_radius as usize,
        contract.default_threshold,
        contract.default_max_keypoints[level],
    );
    let mut px: Vec<(f32, f32)> = peaks.iter().map(|p| (p.x * stride, p.y * stride)).collect();
    let finer: Vec<(f32, keypoints::ScoreMap<'_>)> = (finest..level)
        .rev()
        .map(|j| (dense.levels[j].stride as f32, dense.levels[j].score_map()))
        .collect();
    keypoints::refine_down(&mut px, stride, &finer);
    px
}

/// The keypoint of `detected` nearest (x, y) within [`SNAP_RADIUS_PX`] (the first of equals).
/// A scan: an image has at most a few thousand keypoints on the snap level and an
/// observation is looked up once.
pub(crate) fn nearest(detected: &[(f32, f32)], x: f32, y: f32) -> Option<(f32, f32)> {
    let mut best: Option<(f32, (f32, f32))> = None;
    for &(a, b) in detected {
        let d = (a - x).powi(2) + (b - y).powi(2);
        if d <= SNAP_RADIUS_PX * SNAP_RADIUS_PX && best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, (a, b)));
        }
    }
    best.map(|(_, p)| p)
}

/// The point whose projections are `views` (each a camera's pose and the point's normalised,
/// undistorted image coordinates there): the linear (DLT) solution, `None` when the views do
/// not fix it (fewer than two, at infinity, non-finite).
pub(crate) fn triangulate(views: &[(Pose, Vector2<f64>)]) -> Option<Vector3<f64>> {
    if views.len() < 2 {
        return None;
    }
    // The sum of each row's outer product: the normal equations of the 2n × 4 system.
    let mut ata = Matrix4::<f64>::zeros();
    for (pose, u) in views {
        let r = pose.rotation_matrix();
        let t = pose.translation;
        let row = |i: usize| Vector4::new(r[(i, 0)], r[(i, 1)], r[(i, 2)], t[i]);
        for a in [row(2) * u.x - row(0), row(2) * u.y - row(1)] {
            ata += a * a.transpose();
        }
    }
    if !ata.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eigen = ata.symmetric_eigen();
    let (smallest, _) = eigen
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let h = eigen.eigenvectors.column(smallest);
    let x = Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]);
    (h[3].abs() > 1e-12 && x.iter().all(|v| v.is_finite())).then_some(x)
}

/// Where a point moves from its moved observations (each a camera, its pose, and the moved
/// pixel in COLMAP's convention, in the camera's pixels): their triangulation, when it is in
/// front of every camera, every one reprojects within [`MAX_REPROJECTION_PX`] and the rays'
/// widest angle is at least [`MIN_TRIANGULATION_DEG`]; `None` otherwise (the point stays).
pub(crate) fn moved_position(
    observations: &[(&Camera, Pose, Vector2<f64>)],
) -> Option<Vector3<f64>> {
    let views: Vec<(Pose, Vector2<f64>)> = observations
        .iter()
        .map(|(camera, pose, px)| (*pose, camera.unproject(px)))
        .collect();
    let x = triangulate(&views)?;
    let rays: Vec<Vector3<f64>> = observations
        .iter()
        .map(|(_, pose, _)| (x - pose.center()).normalize())
        .collect();
    let widest = rays
        .iter()
        .flat_map(|a| rays.iter().map(move |b| a.dot(b).clamp(-1.0, 1.0).acos()))
        .fold(0.0f64, f64::max);
    if widest.to_degrees() < MIN_TRIANGULATION_DEG {
        return None;
    }
    observations
        .iter()
        .all(|(camera, pose, px)| {
            let c = pose.transform(&x);
            c.z > 0.0
                && camera
                    .project(&c)
                    .is_some_and(|p| (p - px).norm() <= MAX_REPROJECTION_PX)
        })
        .then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::CameraModel;
    use nalgebra::UnitQuaternion;

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
        let found = moved_position(&seen(&cam, &x, 0.5)).unwrap();
        assert!((found - x).norm() < 1e-6, "{found} vs {x}");
    }

    #[test]
    fn observations_that_disagree_too_few_or_too_close_leave_the_point() {
        let x = Vector3::new(0.3, -0.2, 5.0);
        let cam = camera();
        let mut obs = seen(&cam, &x, 0.5);
        // One observation 10 px off: no point reprojects within 2 px in all three views.
        obs[1].2.x += 10.0;
        assert_eq!(moved_position(&obs), None);
        // One view fixes no point.
        assert_eq!(moved_position(&obs[..1]), None);
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
        assert_eq!(moved_position(&narrow), None);
    }

    #[test]
    fn an_observation_moves_to_the_nearest_keypoint_within_the_radius() {
        let detected = [(10.0, 10.0), (13.0, 10.0), (30.0, 30.0)];
        assert_eq!(nearest(&detected, 12.0, 10.0), Some((13.0, 10.0)));
        assert_eq!(
            nearest(&detected, 11.5, 10.0),
            Some((10.0, 10.0)),
            "equals: the first"
        );
        assert_eq!(nearest(&detected, 20.0, 20.0), None, "none within 4 px");
        assert_eq!(nearest(&[], 0.0, 0.0), None);
    }

    #[test]
    fn the_snap_level_is_level_2_or_the_deepest() {
        assert_eq!(snap_level(4), 2);
        assert_eq!(snap_level(3), 2);
        assert_eq!(snap_level(2), 1);
        assert_eq!(snap_level(1), 0);
    }
}
