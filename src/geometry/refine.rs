//! Levenberg–Marquardt refinement of an absolute pose on pixel reprojection error.
//!
//! Six parameters: a rotation vector `ω` applied on the left (`R ← exp(ω)·R`, so the update
//! lives in the tangent space of SO(3) and never leaves it) and the translation. Residuals are
//! pixel errors through the camera model including distortion, so the threshold a user gives
//! in pixels means the same thing everywhere. Robust losses are handled by iteratively
//! reweighted least squares inside LM; steps are accepted only if the true robust cost falls.

use nalgebra::{Matrix6, UnitQuaternion, Vector2, Vector3, Vector6};

use super::camera::Camera;
use super::error::GeometryError;
use super::pose::Pose;

/// Robust loss `ρ(s)` on the squared pixel residual `s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RobustLoss {
    /// Plain least squares, `ρ(s) = s`.
    Trivial,
    /// Quadratic up to `scale` pixels, linear beyond.
    Huber {
        /// Where the loss turns linear, in pixels.
        scale: f64,
    },
    /// `ρ(s) = c²·ln(1 + s/c²)`: outliers far beyond `scale` pixels barely pull.
    Cauchy {
        /// `c`, in pixels.
        scale: f64,
    },
}

impl RobustLoss {
    #[inline]
    fn rho(&self, s: f64) -> f64 {
        match *self {
            Self::Trivial => s,
            Self::Huber { scale } => {
                if s <= scale * scale {
                    s
                } else {
                    2.0 * scale * s.sqrt() - scale * scale
                }
            }
            Self::Cauchy { scale } => {
                let c2 = scale * scale;
                c2 * (s / c2).ln_1p()
            }
        }
    }

    /// `ρ'(s)`, the IRLS weight of a residual.
    #[inline]
    fn weight(&self, s: f64) -> f64 {
        match *self {
            Self::Trivial => 1.0,
            Self::Huber { scale } => {
                if s <= scale * scale {
                    1.0
                } else {
                    scale / s.sqrt()
                }
            }
            Self::Cauchy { scale } => 1.0 / (1.0 + s / (scale * scale)),
        }
    }

    fn validate(&self) -> Result<(), GeometryError> {
        match *self {
            Self::Trivial => Ok(()),
            Self::Huber { scale } | Self::Cauchy { scale } => {
                if scale.is_finite() && scale > 0.0 {
                    Ok(())
                } else {
                    Err(GeometryError::InvalidOptions {
                        field: "loss.scale",
                        reason: "must be finite and positive",
                    })
                }
            }
        }
    }
}

/// Options of [`refine_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct RefineOptions {
    /// The robust loss on squared pixel residuals.
    pub loss: RobustLoss,
    /// Most Levenberg–Marquardt iterations.
    pub max_iterations: usize,
    /// Stop when the largest gradient component falls below this.
    pub gradient_tolerance: f64,
    /// Stop when the update (rotation in radians, translation relative to its norm) is smaller.
    pub step_tolerance: f64,
    /// Stop when the cost falls by less than this fraction in an accepted step.
    pub cost_tolerance: f64,
    /// Initial Marquardt damping, relative to the diagonal of the normal equations.
    pub initial_damping: f64,
}

impl Default for RefineOptions {
    /// Cauchy at 1 px like pycolmap's refinement default scale; 100 iterations is far more than
    /// a RANSAC start ever needs (typically < 10). The cost tolerance is Ceres' default
    /// function tolerance: robust losses converge linearly under IRLS, and the last digits of
    /// the cost move the pose by far less than the noise does.
    fn default() -> Self {
        Self {
            loss: RobustLoss::Cauchy { scale: 1.0 },
            max_iterations: 100,
            gradient_tolerance: 1e-10,
            step_tolerance: 1e-9,
            cost_tolerance: 1e-6,
            initial_damping: 1e-4,
        }
    }
}

impl RefineOptions {
    pub(crate) fn validate(&self) -> Result<(), GeometryError> {
        self.loss.validate()?;
        let fields = [
            ("gradient_tolerance", self.gradient_tolerance),
            ("step_tolerance", self.step_tolerance),
            ("cost_tolerance", self.cost_tolerance),
            ("initial_damping", self.initial_damping),
        ];
        for (field, value) in fields {
            if !(value.is_finite() && value >= 0.0) {
                return Err(GeometryError::InvalidOptions {
                    field,
                    reason: "must be finite and non-negative",
                });
            }
        }
        Ok(())
    }
}

/// Result of [`refine_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct Refinement {
    /// The refined `cam_from_world`.
    pub pose: Pose,
    /// `½·Σ ρ(|r|²)` at the initial pose.
    pub initial_cost: f64,
    /// `½·Σ ρ(|r|²)` at the refined pose; never larger than `initial_cost`.
    pub final_cost: f64,
    /// Accepted LM steps.
    pub iterations: usize,
}

/// Refinement needs three correspondences (six residuals for six unknowns).
const MIN_CORRESPONDENCES: usize = 3;

/// A point behind the camera has no pixel; it costs as much as a residual of this many pixels
/// so LM cannot lower the cost by pushing a bad point behind the camera.
const BEHIND_CAMERA_RESIDUAL: f64 = 1e6;

/// Refines `initial` (`cam_from_world`) to minimize the robust pixel reprojection error of all
/// correspondences (pixels in COLMAP convention).
pub fn refine_pose(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    camera: &Camera,
    initial: &Pose,
    options: &RefineOptions,
) -> Result<Refinement, GeometryError> {
    validate_correspondences(pixels, points)?;
    let indices: Vec<usize> = (0..pixels.len()).collect();
    refine_checked(pixels, points, &indices, camera, initial, options)
}

/// [`refine_pose`] on the correspondences whose `mask` entry is true (e.g. RANSAC inliers).
pub fn refine_pose_masked(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    mask: &[bool],
    camera: &Camera,
    initial: &Pose,
    options: &RefineOptions,
) -> Result<Refinement, GeometryError> {
    validate_correspondences(pixels, points)?;
    if mask.len() != pixels.len() {
        return Err(GeometryError::LengthMismatch {
            what: "mask",
            expected: pixels.len(),
            found: mask.len(),
        });
    }
    let indices: Vec<usize> = (0..pixels.len()).filter(|&i| mask[i]).collect();
    refine_checked(pixels, points, &indices, camera, initial, options)
}

/// Equal lengths and finite pixels and points; shared with RANSAC's input checks.
pub(super) fn validate_correspondences(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
) -> Result<(), GeometryError> {
    if pixels.len() != points.len() {
        return Err(GeometryError::LengthMismatch {
            what: "points",
            expected: pixels.len(),
            found: points.len(),
        });
    }
    if let Some(index) = pixels
        .iter()
        .position(|p| !(p.x.is_finite() && p.y.is_finite()))
    {
        return Err(GeometryError::NonFinite {
            what: "pixels",
            index,
        });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
        return Err(GeometryError::NonFinite {
            what: "points",
            index,
        });
    }
    Ok(())
}

fn refine_checked(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    indices: &[usize],
    camera: &Camera,
    initial: &Pose,
    options: &RefineOptions,
) -> Result<Refinement, GeometryError> {
    options.validate()?;
    if indices.len() < MIN_CORRESPONDENCES {
        return Err(GeometryError::TooFewCorrespondences {
            found: indices.len(),
            required: MIN_CORRESPONDENCES,
        });
    }
    if !initial.is_finite() {
        return Err(GeometryError::NonFinite {
            what: "initial pose",
            index: 0,
        });
    }
    if !indices
        .iter()
        .any(|&i| initial.transform(&points[i]).z > 0.0)
    {
        return Err(GeometryError::RefinementFailed {
            reason: "no point in front of the camera",
        });
    }
    let refinement = refine_indexed(pixels, points, indices, camera, initial, options);
    if !refinement.pose.is_finite() || !refinement.final_cost.is_finite() {
        return Err(GeometryError::RefinementFailed {
            reason: "non-finite pose",
        });
    }
    Ok(refinement)
}

/// `½·Σ ρ(|r|²)` over the subset.
pub(crate) fn robust_cost(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    indices: &[usize],
    camera: &Camera,
    pose: &Pose,
    loss: &RobustLoss,
) -> f64 {
    let rotation = pose.rotation.to_rotation_matrix();
    let behind = loss.rho(BEHIND_CAMERA_RESIDUAL * BEHIND_CAMERA_RESIDUAL);
    let total: f64 = indices
        .iter()
        .map(|&i| {
            let p_cam = rotation * points[i] + pose.translation;
            match camera.project(&p_cam) {
                Some(pixel) => loss.rho((pixel - pixels[i]).norm_squared()),
                None => behind,
            }
        })
        .sum();
    0.5 * total
}

/// The LM loop without input validation; inputs are finite and indices in range.
pub(crate) fn refine_indexed(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    indices: &[usize],
    camera: &Camera,
    initial: &Pose,
    options: &RefineOptions,
) -> Refinement {
    let loss = &options.loss;
    let mut pose = *initial;
    let initial_cost = robust_cost(pixels, points, indices, camera, &pose, loss);
    let mut cost = initial_cost;
    let mut damping = options.initial_damping;
    let mut iterations = 0;

    'outer: for _ in 0..options.max_iterations {
        let (hessian, gradient) = normal_equations(pixels, points, indices, camera, &pose, loss);
        if !(gradient.amax() > options.gradient_tolerance) {
            break;
        }
        // Retry with more damping until a step lowers the cost or damping explodes.
        loop {
            let mut damped = hessian;
            for k in 0..6 {
                // The absolute floor keeps the system solvable when a direction has no
                // information (e.g. all points at one spot).
                damped[(k, k)] += damping * hessian[(k, k)] + damping * 1e-9;
            }
            let step = damped.cholesky().map(|c| c.solve(&(-gradient)));
            let Some(step) = step.filter(|s| s.iter().all(|v| v.is_finite())) else {
                damping *= 10.0;
                if damping > 1e16 {
                    break 'outer;
                }
                continue;
            };
            let candidate = apply_step(&pose, &step);
            let candidate_cost = robust_cost(pixels, points, indices, camera, &candidate, loss);
            if candidate_cost < cost && candidate.is_finite() {
                let decrease = cost - candidate_cost;
                pose = candidate;
                iterations += 1;
                let relative_step = step.fixed_rows::<3>(0).norm()
                    + step.fixed_rows::<3>(3).norm() / (1.0 + pose.translation.norm());
                let converged = decrease <= options.cost_tolerance * cost
                    || relative_step <= options.step_tolerance;
                cost = candidate_cost;
                damping = (damping * 0.1).max(1e-12);
                if converged {
                    break 'outer;
                }
                break;
            }
            damping *= 10.0;
            if damping > 1e16 {
                break 'outer;
            }
        }
    }
    Refinement {
        pose,
        initial_cost,
        final_cost: cost,
        iterations,
    }
}

/// IRLS normal equations `JᵀWJ` and gradient `JᵀWr` at `pose`, accumulated in scalars (the
/// upper triangle of the symmetric 6×6, mirrored at the end): this runs per point per LM
/// iteration and matrix temporaries cost more than the arithmetic.
pub(super) fn normal_equations(
    pixels: &[Vector2<f64>],
    points: &[Vector3<f64>],
    indices: &[usize],
    camera: &Camera,
    pose: &Pose,
    loss: &RobustLoss,
) -> (Matrix6<f64>, Vector6<f64>) {
    let rotation = pose.rotation.to_rotation_matrix();
    let mut upper = [0.0f64; 21];
    let mut gradient = [0.0f64; 6];
    for &i in indices {
        let p = rotation * points[i] + pose.translation;
        let Some((pixel, d_pixel)) = camera.project_with_jacobian(&p) else {
            continue;
        };
        let residual = pixel - pixels[i];
        let weight = loss.weight(residual.norm_squared());
        // The update is p_cam ← exp(ω)·p_cam + δt (see `apply_step`), so ∂p_cam/∂ω = −[p_cam]×
        // and ∂p_cam/∂δt = I: rotations turn about the camera centre, which decouples them
        // from the translation far better than turning about the world origin. A Jacobian row
        // `a` (∂pixel/∂p_cam) times −[p]× is p × a.
        for row in 0..2 {
            let a = Vector3::new(d_pixel[(row, 0)], d_pixel[(row, 1)], d_pixel[(row, 2)]);
            let rot = p.cross(&a);
            let j = [rot.x, rot.y, rot.z, a.x, a.y, a.z];
            let wr = weight * residual[row];
            let mut k = 0;
            for r in 0..6 {
                let wj = weight * j[r];
                gradient[r] += j[r] * wr;
                for &jc in &j[r..] {
                    upper[k] += wj * jc;
                    k += 1;
                }
            }
        }
    }
    let mut hessian = Matrix6::zeros();
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            hessian[(r, c)] = upper[k];
            hessian[(c, r)] = upper[k];
            k += 1;
        }
    }
    (hessian, Vector6::from_column_slice(&gradient))
}

fn apply_step(pose: &Pose, step: &Vector6<f64>) -> Pose {
    let omega = Vector3::new(step[0], step[1], step[2]);
    let delta = UnitQuaternion::from_scaled_axis(omega);
    let rotation = delta * pose.rotation;
    // The left rotation update also turns the translation's frame; applying it to t keeps the
    // update a proper rigid-motion increment (p_cam' = exp(ω)·p_cam + δt).
    let translation = delta * pose.translation + Vector3::new(step[3], step[4], step[5]);
    Pose::new(
        UnitQuaternion::new_normalize(rotation.into_inner()),
        translation,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn loss_weights_are_derivatives() {
        for loss in [
            RobustLoss::Trivial,
            RobustLoss::Huber { scale: 2.0 },
            RobustLoss::Cauchy { scale: 2.0 },
        ] {
            for s in [0.5, 3.0, 20.0, 400.0] {
                let h = 1e-6 * s;
                let numeric = (loss.rho(s + h) - loss.rho(s - h)) / (2.0 * h);
                assert!((numeric - loss.weight(s)).abs() < 1e-6, "{loss:?} at {s}");
            }
        }
    }
}
