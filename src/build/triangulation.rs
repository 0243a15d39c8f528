//! Points from observations with known poses, shared by `convert --images --snap`
//! ([`super::snap`]) and `--triangulate` ([`super::network_tracks`]): the linear
//! triangulation, the reprojection error and the rule a triangulated point passes.

use crate::colmap::Reconstruction;
use crate::geometry::{Camera, Pose};
use nalgebra::{Matrix4, Vector2, Vector3, Vector4};

/// How far (pixels, in the network's input) an observation may lie from its triangulated
/// point's projection: the network's keypoints sit within a pixel or two of one image point
/// (its level-2 MMA@3 on held-out pairs is 0.74).
pub(crate) const MAX_REPROJECTION_PX: f64 = 2.0;

/// The widest angle (degrees) between a point's rays must be at least this: rays meeting at a
/// small angle fix the depth poorly, and a pixel moves the point far along them (Sacre-Coeur's
/// narrow baselines; COLMAP's triangulator asks 1.5).
pub(crate) const MIN_TRIANGULATION_DEG: f64 = 2.0;

/// One observation of a point: the camera, its pose, the pixel (COLMAP's convention, in the
/// camera's pixels).
pub(crate) type Observation<'a> = (&'a Camera, Pose, Vector2<f64>);

/// Each model image's camera as the geometry projects with it (`model.images()` order); `None`
/// for one it cannot build (its observations then stay out).
pub(crate) fn image_cameras(model: &Reconstruction) -> Vec<Option<Camera>> {
    model
        .images()
        .iter()
        .map(|i| {
            let c = model.camera(i.camera_id)?;
            let (w, h) = (u32::try_from(c.width).ok()?, u32::try_from(c.height).ok()?);
            Camera::new(c.model, w, h, c.params.clone()).ok()
        })
        .collect()
}

/// Whether the point `x` passes for `observations`: in front of every camera, each one
/// reprojecting within [`MAX_REPROJECTION_PX`] times its `px_per_input` (camera pixels per
/// network input pixel), the rays' widest angle at least [`MIN_TRIANGULATION_DEG`].
pub(crate) fn accepted(
    observations: &[Observation<'_>],
    px_per_input: impl Fn(usize) -> f64,
    x: &Vector3<f64>,
) -> bool {
    observations
        .iter()
        .enumerate()
        .all(|(k, (camera, pose, px))| {
            reprojection_px(camera, pose, x, px) <= MAX_REPROJECTION_PX * px_per_input(k)
        })
        && rays_meet_widely(
            observations
                .iter()
                .map(|(_, pose, _)| (x - pose.center()).normalize()),
        )
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

/// Whether the widest angle between `rays` (unit) is at least [`MIN_TRIANGULATION_DEG`], in
/// time linear in the rays: every angle is at most twice the widest from the first ray, so
/// the pairs are compared only when that is between half the bar and the bar, and then among
/// the first [`ANGLE_PAIRS_VIEWS`] (a track may have thousands of views).
pub(crate) fn rays_meet_widely(rays: impl Iterator<Item = Vector3<f64>>) -> bool {
    let rays: Vec<Vector3<f64>> = rays.collect();
    let angle = |a: &Vector3<f64>, b: &Vector3<f64>| a.dot(b).clamp(-1.0, 1.0).acos().to_degrees();
    let Some(first) = rays.first() else {
        return false;
    };
    let from_first = rays.iter().map(|r| angle(first, r)).fold(0.0f64, f64::max);
    if from_first >= MIN_TRIANGULATION_DEG {
        return true;
    }
    if from_first < MIN_TRIANGULATION_DEG / 2.0 {
        return false;
    }
    let few = &rays[..rays.len().min(ANGLE_PAIRS_VIEWS)];
    few.iter()
        .flat_map(|a| few.iter().map(move |b| angle(a, b)))
        .any(|d| d >= MIN_TRIANGULATION_DEG)
}

/// The views whose rays are compared pairwise when the first ray does not settle it.
const ANGLE_PAIRS_VIEWS: usize = 64;

/// The DLT triangulation of `observations` (camera, pose, pixel in COLMAP's convention),
/// solved about `around`: georeferenced coordinates (1e5 to 1e6) would leave the linear
/// system too poorly conditioned to place a point to a pixel.
pub(crate) fn triangulate_about(
    observations: &[Observation<'_>],
    around: Vector3<f64>,
) -> Option<Vector3<f64>> {
    let views: Vec<(Pose, Vector2<f64>)> = observations
        .iter()
        .map(|(camera, pose, px)| {
            // The same camera with the world's origin at `around`.
            let shifted = Pose::new(pose.rotation, pose.translation + pose.rotation * around);
            (shifted, camera.unproject(px))
        })
        .collect();
    Some(triangulate(&views)? + around)
}

/// How far (pixels) `x` projects from `px` in the camera at `pose`; infinite when it is behind
/// the camera or does not project.
pub(crate) fn reprojection_px(
    camera: &Camera,
    pose: &Pose,
    x: &Vector3<f64>,
    px: &Vector2<f64>,
) -> f64 {
    let c = pose.transform(x);
    match camera.project(&c) {
        Some(p) if c.z > 0.0 => (p - px).norm(),
        _ => f64::INFINITY,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_meet_widely_at_two_degrees_or_more_however_many() {
        let ray = |deg: f64| Vector3::new(deg.to_radians().sin(), 0.0, deg.to_radians().cos());
        assert!(rays_meet_widely([ray(0.0), ray(2.5)].into_iter()));
        assert!(!rays_meet_widely([ray(0.0), ray(0.5)].into_iter()));
        // The first ray in the middle: 1.5 degrees each way, 3 between the others.
        assert!(rays_meet_widely(
            [ray(0.0), ray(-1.5), ray(1.5)].into_iter()
        ));
        assert!(!rays_meet_widely(std::iter::empty()));
        // Ten thousand views in a narrow cone: decided without the pairs.
        assert!(!rays_meet_widely((0..10_000).map(|i| ray(i as f64 * 1e-5))));
    }
}
