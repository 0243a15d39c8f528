//! How sure a pose is: the covariance of an absolute pose fitted to pixel correspondences,
//! from the geometry of its inliers (what `sfpmap ros2` publishes as
//! `geometry_msgs/msg/PoseWithCovarianceStamped`).
//!
//! The rule, the textbook one for a least-squares fit (Hartley & Zisserman, 2nd ed., 5.2.3):
//! at the fitted pose, `Σ = σ² (JᵀJ)⁻¹`, where `J` is the Jacobian of the inliers' pixel
//! residuals with respect to the six pose parameters of the refinement ([`super::refine`]:
//! a rotation `ω` and a translation `δt` applied in the camera frame) and `σ²` the residuals'
//! own variance, `Σ|r|² / (2n − 6)` over the `n` inliers. So the covariance grows with the
//! pixel error the fit left and shrinks with more inliers spread wider over the image;
//! outliers do not enter it. It is a first-order figure: it does not know about a wrong
//! match that RANSAC took for an inlier, nor about errors in the map's points; and it is the
//! least-squares fit's, where the refinement's Cauchy loss (1 px) weighs residuals past a
//! pixel less, which spreads its poses a little more when the pixel error is larger.

use nalgebra::{Matrix3, Matrix6, Vector2, Vector3};

use super::camera::Camera;
use super::pose::Pose;
use super::refine::{normal_equations, RobustLoss};

/// Inliers needed: enough residuals (2 each) past the six parameters for `σ²` to mean
/// something (with 4, it has 2 degrees of freedom and is often far too small).
const MIN_INLIERS: usize = 6;

/// `σ` is never taken below this many pixels: keypoints are not placed more precisely than
/// that, and a fit that happens to explain its inliers exactly must not claim certainty.
pub const SIGMA_FLOOR_PX: f64 = 0.25;

/// The smallest eigenvalue of `JᵀJ` over its largest below which a direction counts as
/// unconstrained.
const CONDITION_FLOOR: f64 = 1e-12;

/// The covariance of a `cam_from_world` pose, in the refinement's parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseCovariance {
    /// 6×6 over `[ω; δt]`: the pose moves as `p_cam ← exp(ω)·p_cam + δt`.
    pub camera_frame: Matrix6<f64>,
    /// `σ`, the inliers' pixel residuals' standard deviation the covariance is scaled by.
    pub sigma_px: f64,
    /// The inliers it was computed from.
    pub inliers: usize,
}

impl PoseCovariance {
    /// The covariance of `cam_from_world`'s inverse, the camera's pose in the world, as ROS's
    /// `geometry_msgs/msg/PoseWithCovariance` lays it out: row-major 6×6 over the camera
    /// centre's `x, y, z` in the world frame, then small rotations about the world frame's
    /// `x, y, z` axes (`R_world_from_cam ← exp(θ)·R_world_from_cam`), in map units and
    /// radians.
    ///
    /// To first order the camera centre `c = −Rᵀt` moves by `δc = −Rᵀ·δt` and its
    /// orientation by `θ = −Rᵀ·ω` when the pose moves by `[ω; δt]`, so the covariance is
    /// `A·Σ·Aᵀ` with `A = [[0, −Rᵀ], [−Rᵀ, 0]]`.
    pub fn world_from_camera(&self, cam_from_world: &Pose) -> [f64; 36] {
        let rt: Matrix3<f64> = cam_from_world
            .rotation
            .to_rotation_matrix()
            .matrix()
            .transpose();
        let mut a = Matrix6::<f64>::zeros();
        a.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-rt));
        a.fixed_view_mut::<3, 3>(3, 0).copy_from(&(-rt));
        let world = a * self.camera_frame * a.transpose();
        let mut out = [0.0; 36];
        for r in 0..6 {
            for c in 0..6 {
                // Symmetric by construction; averaged so rounding cannot make it otherwise.
                out[r * 6 + c] = 0.5 * (world[(r, c)] + world[(c, r)]);
            }
        }
        out
    }
}

/// The covariance of `pose` (`cam_from_world`) fitted to the correspondences `indices` of
/// `pixels` and `points` (the inliers; pixels in COLMAP's convention), as the module says;
/// `None` with fewer than four inliers in front of the camera, or a fit that leaves a
/// direction unconstrained (all points on a line through the centre, …).
pub fn pose_covariance(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    indices: &[usize],
    camera: &Camera,
    pose: &Pose,
) -> Option<PoseCovariance> {
    let rotation = pose.rotation.to_rotation_matrix();
    let mut sum_sq = 0.0;
    let mut used = 0usize;
    for &i in indices {
        let p = rotation * points[i] + pose.translation;
        if let Some(pixel) = camera.project(&p) {
            sum_sq += (pixel - pixels[i]).norm_squared();
            used += 1;
        }
    }
    if used < MIN_INLIERS {
        return None;
    }
    let sigma2 = (sum_sq / (2 * used - 6) as f64).max(SIGMA_FLOOR_PX * SIGMA_FLOOR_PX);
    let (hessian, _) =
        normal_equations(pixels, points, indices, camera, pose, &RobustLoss::Trivial);
    // A direction the inliers do not constrain (rounding keeps the matrix invertible).
    let eigen = hessian.symmetric_eigenvalues();
    let (low, high) = (eigen.min(), eigen.max());
    if !(low > high * CONDITION_FLOOR) {
        return None;
    }
    let inverse = hessian.try_inverse()?;
    let camera_frame = inverse * sigma2;
    let finite = camera_frame.iter().all(|v| v.is_finite());
    let positive = (0..6).all(|k| camera_frame[(k, k)] >= 0.0);
    (finite && positive).then_some(PoseCovariance {
        camera_frame,
        sigma_px: sigma2.sqrt(),
        inliers: used,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::{refine_pose, RefineOptions, RobustLoss, SplitMix64};
    use nalgebra::UnitQuaternion;

    /// A camera looking at a box of points 5 to 15 units in front of it.
    fn scene(n: usize, rng: &mut SplitMix64) -> (Camera, Pose, Vec<Vector3<f64>>) {
        let camera = Camera::parse("PINHOLE 640 480 500 500 320 240").unwrap();
        let pose = Pose::new(
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.05),
            Vector3::new(0.3, -0.1, 2.0),
        );
        let inverse = pose.inverse();
        let points = (0..n)
            .map(|_| {
                let z = 5.0 + 10.0 * rng.next_f64();
                let x = (rng.next_f64() - 0.5) * z;
                let y = (rng.next_f64() - 0.5) * 0.75 * z;
                inverse.transform(&Vector3::new(x, y, z))
            })
            .collect();
        (camera, pose, points)
    }

    /// A Gaussian draw (Box–Muller).
    fn gauss(rng: &mut SplitMix64) -> f64 {
        let u = rng.next_f64().max(1e-300);
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * rng.next_f64()).cos()
    }

    fn noisy_pixels(
        camera: &Camera,
        pose: &Pose,
        points: &[Vector3<f64>],
        sigma: f64,
        rng: &mut SplitMix64,
    ) -> Vec<Vector2<f64>> {
        points
            .iter()
            .map(|p| {
                let px = camera.project(&pose.transform(p)).unwrap();
                px + Vector2::new(sigma * gauss(rng), sigma * gauss(rng))
            })
            .collect()
    }

    /// The predicted spread of the camera centre matches the spread of fits to noisy pixels
    /// (Monte Carlo), axis by axis and in the rotation.
    #[test]
    fn the_predicted_covariance_is_the_spread_of_refits_to_noisy_pixels() {
        let mut rng = SplitMix64::new(7);
        let (camera, truth, points) = scene(60, &mut rng);
        let indices: Vec<usize> = (0..points.len()).collect();
        let sigma = 1.5;
        let trials = 400;
        let mut centres = Vec::new();
        let mut angles = Vec::new();
        let mut predicted = [0.0; 36];
        for trial in 0..trials {
            let pixels = noisy_pixels(&camera, &truth, &points, sigma, &mut rng);
            // Least squares: the estimator the covariance describes (the localizer's Cauchy
            // loss is less efficient on residuals past its 1 px scale).
            let options = RefineOptions {
                loss: RobustLoss::Trivial,
                ..RefineOptions::default()
            };
            let fit = refine_pose(&pixels, &points, &camera, &truth, &options)
                .unwrap()
                .pose;
            if trial == 0 {
                let cov = pose_covariance(&pixels, &points, &indices, &camera, &fit).unwrap();
                assert!(
                    (cov.sigma_px - sigma).abs() < 0.3 * sigma,
                    "{}",
                    cov.sigma_px
                );
                predicted = cov.world_from_camera(&fit);
            }
            centres.push(fit.center() - truth.center());
            // The world-frame rotation from the truth to the fit: R_fit_wc · R_truth_wcᵀ.
            let delta = fit.inverse().rotation * truth.inverse().rotation.inverse();
            angles.push(delta.scaled_axis());
        }
        for axis in 0..3 {
            let var_c = centres.iter().map(|d| d[axis] * d[axis]).sum::<f64>() / trials as f64;
            let var_r = angles.iter().map(|d| d[axis] * d[axis]).sum::<f64>() / trials as f64;
            let (pc, pr) = (predicted[axis * 7], predicted[(axis + 3) * 7]);
            assert!(
                (var_c / pc - 1.0).abs() < 0.35,
                "centre axis {axis}: measured {var_c:.3e}, predicted {pc:.3e}"
            );
            assert!(
                (var_r / pr - 1.0).abs() < 0.35,
                "rotation axis {axis}: measured {var_r:.3e}, predicted {pr:.3e}"
            );
        }
        // The correlations too, every pair: a covariance turned the wrong way (R for Rᵀ, the
        // camera's frame for the world's) moves them.
        let samples: Vec<[f64; 6]> = centres
            .iter()
            .zip(&angles)
            .map(|(c, a)| [c.x, c.y, c.z, a.x, a.y, a.z])
            .collect();
        let measured =
            |i: usize, j: usize| samples.iter().map(|v| v[i] * v[j]).sum::<f64>() / trials as f64;
        for i in 0..6 {
            for j in 0..i {
                let rho_m = measured(i, j) / (measured(i, i) * measured(j, j)).sqrt();
                let rho_p = predicted[i * 6 + j] / (predicted[i * 7] * predicted[j * 7]).sqrt();
                assert!(
                    (rho_m - rho_p).abs() < 0.15,
                    "correlation ({i}, {j}): measured {rho_m:.3}, predicted {rho_p:.3}"
                );
            }
        }
    }

    #[test]
    fn a_perfect_fit_is_not_certainty() {
        let mut rng = SplitMix64::new(11);
        let (camera, truth, points) = scene(30, &mut rng);
        let pixels = noisy_pixels(&camera, &truth, &points, 0.0, &mut rng);
        let indices: Vec<usize> = (0..points.len()).collect();
        let c = pose_covariance(&pixels, &points, &indices, &camera, &truth).unwrap();
        assert_eq!(c.sigma_px, SIGMA_FLOOR_PX);
        assert!((0..6).all(|k| c.camera_frame[(k, k)] > 0.0));
    }

    #[test]
    fn more_pixel_error_or_fewer_inliers_is_less_sure() {
        let mut rng = SplitMix64::new(3);
        let (camera, truth, points) = scene(200, &mut rng);
        let trace = |sigma: f64, n: usize, rng: &mut SplitMix64| {
            let pixels = noisy_pixels(&camera, &truth, &points, sigma, rng);
            let indices: Vec<usize> = (0..n).collect();
            let c = pose_covariance(&pixels, &points, &indices, &camera, &truth).unwrap();
            let w = c.world_from_camera(&truth);
            w[0] + w[7] + w[14]
        };
        let base = trace(1.0, 200, &mut rng);
        assert!(trace(4.0, 200, &mut rng) > 8.0 * base);
        assert!(trace(1.0, 20, &mut rng) > 3.0 * base);
    }

    #[test]
    fn too_few_inliers_or_a_degenerate_fit_has_none() {
        let mut rng = SplitMix64::new(5);
        let (camera, truth, points) = scene(10, &mut rng);
        let pixels = noisy_pixels(&camera, &truth, &points, 1.0, &mut rng);
        assert!(pose_covariance(&pixels, &points, &[0, 1, 2, 3, 4], &camera, &truth).is_none());
        // Copies of one correspondence constrain nothing but one ray.
        let same = [0, 0, 0, 0, 0];
        assert!(pose_covariance(&pixels, &points, &same, &camera, &truth).is_none());
    }
}
