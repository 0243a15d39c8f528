//! (issue 36) SFP map points where the network detects: `convert --images --snap`.
//!
//! An SFP map's points are the COLMAP model's, described where SIFT observed them; a query's
//! keypoints are the network's detections, a few pixels from any SIFT keypoint. Matched, the
//! two are not the same image point, and that offset, not the descriptors, was the SFP maps'
//! imprecision: the same sfp-v2 maps described at the queries' own SIFT keypoints localized
//! KITTI 06 at SIFT's precision (`python/probe_sift_keypoint_queries.py`). With `--snap`, each
//! observation moves to the network's keypoint near it (the strongest cell of the snap level's
//! score map within one cell, refined as the extractor refines that level's keypoints), is
//! described there, and the point is triangulated again from its moved observations with the
//! model's poses. A point whose moved observations do not agree (one reprojects further than
//! [`MAX_REPROJECTION_PX`], or fewer than two moved) keeps its place and observations.

use crate::extract::{keypoints, Dense};
use crate::geometry::{Camera, Pose};
use nalgebra::{Matrix4, Vector2, Vector3, Vector4};

/// How far (pixels, in the model's camera) a moved observation may lie from its re-triangulated
/// point's projection: the network's keypoints sit within a pixel or two of one image point
/// (its level-2 MMA@3 on held-out pairs is 0.74).
pub(crate) const MAX_REPROJECTION_PX: f64 = 2.0;

/// The level observations snap to: the one level-2 short maps keep (the stride-8 level), or
/// the deepest of a shallower model.
pub(crate) fn snap_level(levels: usize) -> usize {
    2.min(levels.saturating_sub(1))
}

/// How far (input pixels) an observation may be from the network's keypoint it moves to.
pub(crate) const SNAP_RADIUS_PX: f32 = 4.0;

/// The network's keypoints of level `level` as the extractor detects them with the model's
/// defaults (input pixels), refined down to `finest`.
pub(crate) fn detected(
    dense: &Dense,
    level: usize,
    finest: usize,
    contract: &crate::extract::contract::Contract,
) -> Vec<(f32, f32)> {
    let l = &dense.levels[level];
    let s = l.stride as f32;
    let peaks = keypoints::detect(
        l.score_map(),
        contract.default_nms_radius as usize,
        contract.default_threshold,
        contract.default_max_keypoints[level],
    );
    let mut px: Vec<(f32, f32)> = peaks.iter().map(|p| (p.x * s, p.y * s)).collect();
    let finer: Vec<(f32, keypoints::ScoreMap<'_>)> = (finest..level)
        .rev()
        .map(|j| (dense.levels[j].stride as f32, dense.levels[j].score_map()))
        .collect();
    keypoints::refine_down(&mut px, s, &finer);
    px
}

/// The keypoint of `detected` nearest (x, y) within `radius`, if any.
pub(crate) fn nearest(detected: &[(f32, f32)], x: f32, y: f32, radius: f32) -> Option<(f32, f32)> {
    detected
        .iter()
        .map(|&(a, b)| ((a - x).powi(2) + (b - y).powi(2), (a, b)))
        .filter(|(d, _)| *d <= radius * radius)
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, p)| p)
}

/// The network's keypoint near input pixel (x, y) (pixel-index convention): the strongest cell
/// of level `level`'s score map within one cell, with its sub-pixel fit, then refined on the
/// finer levels down to `finest` as the extractor refines that level's keypoints
/// (`spec/extractor.md` step 4; `finest == level`: not refined).
pub(crate) fn snap(dense: &Dense, level: usize, finest: usize, x: f32, y: f32) -> (f32, f32) {
    let l = &dense.levels[level];
    let stride = l.stride as f32;
    let mut p = [keypoints::refine_on(l.score_map(), stride, 1, x, y)];
    let finer: Vec<(f32, keypoints::ScoreMap<'_>)> = (finest..level)
        .rev()
        .map(|j| (dense.levels[j].stride as f32, dense.levels[j].score_map()))
        .collect();
    keypoints::refine_down(&mut p, stride, &finer);
    p[0]
}

/// The point whose projections are `views` (each a camera's pose and the point's normalised,
/// undistorted image coordinates there): the linear (DLT) solution, `None` when the views do
/// not fix it (fewer than two, parallel rays, at infinity, non-finite).
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
    (h[3].abs() > 1e-12).then(|| Vector3::new(h[0] / h[3], h[1] / h[3], h[2] / h[3]))
}

/// The re-triangulated position of a point from its moved observations (each a camera, its
/// pose, and the moved pixel in COLMAP's convention, in the camera's pixels), when every one
/// reprojects within [`MAX_REPROJECTION_PX`] in front of its camera; `None` otherwise.
pub(crate) fn resnapped_position(
    observations: &[(&Camera, Pose, Vector2<f64>)],
) -> Option<Vector3<f64>> {
    let views: Vec<(Pose, Vector2<f64>)> = observations
        .iter()
        .map(|(camera, pose, px)| (*pose, camera.unproject(px)))
        .collect();
    let x = triangulate(&views)?;
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

    /// Three cameras on a line looking down +z, turned a little each.
    fn poses() -> Vec<Pose> {
        (0..3)
            .map(|i| {
                let angle = 0.05 * i as f64;
                Pose::new(
                    UnitQuaternion::from_euler_angles(0.0, angle, 0.0),
                    Vector3::new(-0.5 * i as f64, 0.1, 0.0),
                )
            })
            .collect()
    }

    #[test]
    fn a_point_seen_exactly_is_found_again() {
        let x = Vector3::new(0.3, -0.2, 5.0);
        let cam = camera();
        let obs: Vec<_> = poses()
            .into_iter()
            .map(|pose| (&cam, pose, cam.project(&pose.transform(&x)).unwrap()))
            .collect();
        let found = resnapped_position(&obs).unwrap();
        assert!((found - x).norm() < 1e-6, "{found} vs {x}");
    }

    #[test]
    fn observations_that_disagree_or_too_few_keep_the_point_where_it_was() {
        let x = Vector3::new(0.3, -0.2, 5.0);
        let cam = camera();
        let mut obs: Vec<_> = poses()
            .into_iter()
            .map(|pose| (&cam, pose, cam.project(&pose.transform(&x)).unwrap()))
            .collect();
        // One observation 10 px off: no point reprojects within 2 px in all three views.
        obs[1].2.x += 10.0;
        assert_eq!(resnapped_position(&obs), None);
        // One view fixes no point.
        assert_eq!(resnapped_position(&obs[..1]), None);
        assert_eq!(triangulate(&[]), None);
    }

    #[test]
    fn the_snap_level_is_level_2_or_the_deepest() {
        assert_eq!(snap_level(4), 2);
        assert_eq!(snap_level(3), 2);
        assert_eq!(snap_level(2), 1);
        assert_eq!(snap_level(1), 0);
    }
}
