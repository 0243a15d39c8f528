//! The P3P minimal solver, after Lambda Twist (Persson & Nordberg, ECCV 2018).
//!
//! Unknowns are the depths `Λ = (λ1, λ2, λ3)` along the unit bearings `y_i`; congruence of the
//! camera-frame triangle with the world triangle gives three quadrics
//! `λi² + λj² − 2·bij·λi·λj = aij` (`bij = yi·yj`, `aij = |Xi − Xj|²`). Two homogeneous
//! combinations `D1`, `D2` of them vanish on every solution, and so does the degenerate member
//! `D0 = D1 + γ·D2` of their pencil (`det D0 = 0`, a cubic in γ). A degenerate conic with
//! eigenvalues of opposite sign is a pair of planes through the origin; intersecting each plane
//! with `D1` gives at most two rays, and the sum of the three quadrics fixes the scale. The
//! depths are then polished by Gauss–Newton and the pose follows from the two triangles.
//!
//! Differences from the paper, for robustness rather than speed: all real roots of the cubic
//! are tried and the one splitting most clearly into two planes is used; the cubic is solved in
//! `1/γ` when that is better conditioned; the plane is parametrized by an orthonormal basis
//! instead of solving for one depth (no case split on which coefficient is small); and the
//! world triangle is normalized to unit scale so tolerances are absolute.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};

use super::pose::Pose;

/// Up to four solutions without allocating, for the RANSAC inner loop.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Solutions {
    poses: [Pose; 4],
    len: usize,
}

impl Solutions {
    fn new() -> Self {
        Self {
            poses: [Pose::identity(); 4],
            len: 0,
        }
    }

    /// A single pose, so a prior can go through the same scoring path as P3P's solutions.
    pub fn single(pose: Pose) -> Self {
        let mut solutions = Self::new();
        solutions.push(pose);
        solutions
    }

    fn push(&mut self, pose: Pose) {
        if self.len < 4 {
            self.poses[self.len] = pose;
            self.len += 1;
        }
    }

    pub fn as_slice(&self) -> &[Pose] {
        &self.poses[..self.len]
    }
}

/// Solves the perspective-three-point problem: every pose `cam_from_world` with
/// `bearings[i] ∝ R · points[i] + t` at positive depth (at most four).
///
/// Bearings need not be unit length. Degenerate input (collinear or coincident points,
/// parallel bearings, non-finite values) gives no solutions rather than a bad pose.
pub fn p3p(bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3]) -> Vec<Pose> {
    solve(bearings, points).as_slice().to_vec()
}

pub(crate) fn solve(bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3]) -> Solutions {
    let mut out = Solutions::new();
    let finite = |v: &Vector3<f64>| v.iter().all(|c| c.is_finite());
    if !bearings.iter().chain(points.iter()).all(finite) {
        return out;
    }
    let mut y = [Vector3::zeros(); 3];
    for (yi, b) in y.iter_mut().zip(bearings) {
        let n = b.norm();
        if !(n > 0.0) {
            return out;
        }
        *yi = b / n;
    }

    let d12 = points[0] - points[1];
    let d13 = points[0] - points[2];
    let d23 = points[1] - points[2];
    let (a12, a13, a23) = (d12.norm_squared(), d13.norm_squared(), d23.norm_squared());
    let scale2 = (a12 + a13 + a23) / 3.0;
    let normal = d12.cross(&d13);
    // The triangle's area relative to its size: collinear or coincident points fix no pose.
    if !(scale2 > 0.0) || normal.norm_squared() < 1e-16 * scale2 * scale2 {
        return out;
    }
    let Some(world_inv) = Matrix3::from_columns(&[d12, d13, normal]).try_inverse() else {
        return out;
    };
    let scale = scale2.sqrt();
    let (a12, a13, a23) = (a12 / scale2, a13 / scale2, a23 / scale2);
    let (b12, b13, b23) = (y[0].dot(&y[1]), y[0].dot(&y[2]), y[1].dot(&y[2]));

    let m12 = Matrix3::new(1.0, -b12, 0.0, -b12, 1.0, 0.0, 0.0, 0.0, 0.0);
    let m13 = Matrix3::new(1.0, 0.0, -b13, 0.0, 0.0, 0.0, -b13, 0.0, 1.0);
    let m23 = Matrix3::new(0.0, 0.0, 0.0, 0.0, 1.0, -b23, 0.0, -b23, 1.0);
    let d1 = a23 * m12 - a12 * m23;
    let d2 = a23 * m13 - a13 * m23;

    let Some(d0) = degenerate_member(&d1, &d2) else {
        return out;
    };
    let Some((plane_a, plane_b)) = split_into_planes(&d0) else {
        return out;
    };
    // Sum of the three quadrics: |λ1y1−λ2y2|² + |λ1y1−λ3y3|² + |λ2y2−λ3y3|², positive
    // definite unless bearings coincide, so it fixes the scale of any ray.
    let sum = m12 + m13 + m23;
    let sum_a = a12 + a13 + a23;
    let equations = Equations {
        a: [a12, a13, a23],
        b: [b12, b13, b23],
    };

    for plane in [plane_a, plane_b] {
        for ray in rays_in_plane(&plane, &d1, &d2).iter().flatten() {
            let s = ray.dot(&(sum * ray));
            if !(s > 1e-12) {
                continue;
            }
            let mut lambda = ray * (sum_a / s).sqrt();
            if lambda.sum() < 0.0 {
                lambda = -lambda;
            }
            if lambda.iter().any(|&l| !(l > 0.0)) {
                continue;
            }
            equations.refine(&mut lambda);
            if lambda.iter().any(|&l| !(l > 0.0)) {
                continue;
            }
            let lambda = lambda * scale;
            if let Some(pose) = pose_from_depths(&y, &lambda, points, &world_inv) {
                out.push(pose);
            }
        }
    }
    out
}

/// `det(D1 + γ·D2)` is a cubic; returns the member of the pencil (or `D2` itself for γ → ∞)
/// that splits most clearly into two real planes.
fn degenerate_member(d1: &Matrix3<f64>, d2: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let cof1 = cofactors(d1);
    let cof2 = cofactors(d2);
    let c0 = d1.determinant();
    let c1 = cof1.component_mul(d2).sum();
    let c2 = cof2.component_mul(d1).sum();
    let c3 = d2.determinant();
    // Solve in whichever of γ or μ = 1/γ has the larger leading coefficient.
    let (roots, reversed) = if c3.abs() >= c0.abs() {
        (real_cubic_roots(c3, c2, c1, c0), false)
    } else {
        (real_cubic_roots(c0, c1, c2, c3), true)
    };
    let mut best: Option<(f64, Matrix3<f64>)> = None;
    for &root in roots.iter().flatten() {
        let d0 = if reversed {
            root * d1 + d2
        } else {
            d1 + root * d2
        };
        let (trace, minors) = trace_and_minors(&d0);
        // minors = σ1·σ2 of the two non-zero eigenvalues; negative means opposite signs.
        let split = minors / (trace * trace + minors.abs() + 1e-300);
        if split < -1e-12 && best.as_ref().is_none_or(|(s, _)| split < *s) {
            best = Some((split, d0));
        }
    }
    best.map(|(_, d0)| d0)
}

/// Cofactor matrix; for symmetric input it is also the adjugate.
fn cofactors(m: &Matrix3<f64>) -> Matrix3<f64> {
    let (c0, c1, c2) = (m.column(0), m.column(1), m.column(2));
    Matrix3::from_columns(&[c1.cross(&c2), c2.cross(&c0), c0.cross(&c1)])
}

/// Trace and sum of principal 2×2 minors of a symmetric matrix.
fn trace_and_minors(m: &Matrix3<f64>) -> (f64, f64) {
    let trace = m.trace();
    let minors = m[(0, 0)] * m[(1, 1)] - m[(0, 1)] * m[(1, 0)] + m[(0, 0)] * m[(2, 2)]
        - m[(0, 2)] * m[(2, 0)]
        + m[(1, 1)] * m[(2, 2)]
        - m[(1, 2)] * m[(2, 1)];
    (trace, minors)
}

/// A singular symmetric `D0` with eigenvalues `σ+ > 0 > σ−` is
/// `(√σ+·e+ − √−σ−·e−)·Λ · (√σ+·e+ + √−σ−·e−)·Λ`; returns the two plane normals.
fn split_into_planes(d0: &Matrix3<f64>) -> Option<(Vector3<f64>, Vector3<f64>)> {
    let (trace, minors) = trace_and_minors(d0);
    let disc = 0.25 * trace * trace - minors;
    if !(minors < 0.0) || !(disc > 0.0) {
        return None;
    }
    let root = disc.sqrt();
    let (sigma_pos, sigma_neg) = (0.5 * trace + root, 0.5 * trace - root);
    let e_pos = eigenvector(d0, sigma_pos)?;
    let e_neg = eigenvector(d0, sigma_neg)?;
    let (u, v) = (sigma_pos.sqrt() * e_pos, (-sigma_neg).sqrt() * e_neg);
    Some((u - v, u + v))
}

/// Unit eigenvector of a symmetric matrix for a simple eigenvalue: the largest cross product
/// of two rows of `M − σI`, which are all orthogonal to it.
fn eigenvector(m: &Matrix3<f64>, sigma: f64) -> Option<Vector3<f64>> {
    let shifted = m - Matrix3::from_diagonal_element(sigma);
    let rows = [
        shifted.row(0).transpose(),
        shifted.row(1).transpose(),
        shifted.row(2).transpose(),
    ];
    let candidates = [
        rows[0].cross(&rows[1]),
        rows[0].cross(&rows[2]),
        rows[1].cross(&rows[2]),
    ];
    let best = candidates
        .iter()
        .max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))?;
    let n = best.norm();
    (n > 1e-150 && n.is_finite()).then(|| best / n)
}

/// The at most two rays in the plane `normal·Λ = 0` on which `D1` (equivalently `D2`, since
/// `D0` vanishes on the plane) vanishes.
fn rays_in_plane(
    normal: &Vector3<f64>,
    d1: &Matrix3<f64>,
    d2: &Matrix3<f64>,
) -> [Option<Vector3<f64>>; 2] {
    let n_norm = normal.norm();
    if !(n_norm > 0.0) {
        return [None, None];
    }
    let n = normal / n_norm;
    // The axis least aligned with n gives a well-conditioned first basis vector.
    let axis = n.iamin();
    let mut e = Vector3::zeros();
    e[axis] = 1.0;
    let p = n.cross(&e).normalize();
    let q = n.cross(&p);
    let restrict = |d: &Matrix3<f64>| {
        let dp = d * p;
        let dq = d * q;
        (p.dot(&dp), p.dot(&dq), q.dot(&dq))
    };
    let r1 = restrict(d1);
    let r2 = restrict(d2);
    let norm = |r: &(f64, f64, f64)| r.0.abs() + r.1.abs() + r.2.abs();
    let (q00, q01, q11) = if norm(&r1) >= norm(&r2) { r1 } else { r2 };
    if !(q00.abs() + q01.abs() + q11.abs() > 1e-14) {
        return [None, None];
    }
    // q00·α² + 2·q01·αβ + q11·β² = 0, solved for the ratio with the larger leading coefficient.
    let disc = q01 * q01 - q00 * q11;
    if disc < -1e-12 * (q01 * q01 + (q00 * q11).abs()) {
        return [None, None];
    }
    let sqrt_disc = disc.max(0.0).sqrt();
    let ratios = |a: f64, b: f64, c: f64| -> [f64; 2] {
        // Roots of a·r² + 2·b·r + c without cancellation.
        let k = -(b + b.signum() * sqrt_disc);
        if k == 0.0 {
            [0.0, 0.0]
        } else {
            [k / a, c / k]
        }
    };
    let rays: [Vector2<f64>; 2] = if q00.abs() >= q11.abs() {
        let [r0, r1] = ratios(q00, q01, q11);
        [Vector2::new(r0, 1.0), Vector2::new(r1, 1.0)]
    } else {
        let [r0, r1] = ratios(q11, q01, q00);
        [Vector2::new(1.0, r0), Vector2::new(1.0, r1)]
    };
    let to_space = |r: &Vector2<f64>| {
        let v = p * r.x + q * r.y;
        v.iter().all(|c| c.is_finite()).then_some(v)
    };
    let first = to_space(&rays[0]);
    // A double root is one ray, not two identical solutions.
    let second = if sqrt_disc == 0.0 {
        None
    } else {
        to_space(&rays[1])
    };
    [first, second]
}

/// The three congruence equations in normalized units.
struct Equations {
    a: [f64; 3],
    b: [f64; 3],
}

impl Equations {
    fn residual(&self, l: &Vector3<f64>) -> Vector3<f64> {
        let [a12, a13, a23] = self.a;
        let [b12, b13, b23] = self.b;
        Vector3::new(
            l.x * l.x + l.y * l.y - 2.0 * b12 * l.x * l.y - a12,
            l.x * l.x + l.z * l.z - 2.0 * b13 * l.x * l.z - a13,
            l.y * l.y + l.z * l.z - 2.0 * b23 * l.y * l.z - a23,
        )
    }

    /// Newton's method on the depths; the closed form loses digits when the configuration is
    /// nearly degenerate (thin triangles, narrow fields of view), and a few steps recover full
    /// precision. The Jacobian is then nearly singular too, so each step backtracks until the
    /// residual falls; the input is kept if nothing helps.
    fn refine(&self, lambda: &mut Vector3<f64>) {
        let [b12, b13, b23] = self.b;
        let mut residual = self.residual(lambda);
        let mut error = residual.norm_squared();
        for _ in 0..8 {
            if error < 1e-28 {
                break;
            }
            let l = *lambda;
            let jacobian = Matrix3::new(
                2.0 * (l.x - b12 * l.y),
                2.0 * (l.y - b12 * l.x),
                0.0,
                2.0 * (l.x - b13 * l.z),
                0.0,
                2.0 * (l.z - b13 * l.x),
                0.0,
                2.0 * (l.y - b23 * l.z),
                2.0 * (l.z - b23 * l.y),
            );
            let Some(step) = jacobian.try_inverse().map(|inverse| inverse * residual) else {
                break;
            };
            let mut improved = false;
            let mut scale = 1.0;
            for _ in 0..12 {
                let next = l - scale * step;
                let next_residual = self.residual(&next);
                let next_error = next_residual.norm_squared();
                if next_error < error {
                    *lambda = next;
                    residual = next_residual;
                    error = next_error;
                    improved = true;
                    break;
                }
                scale *= 0.5;
            }
            if !improved {
                break;
            }
        }
    }
}

/// `R` maps the world triangle's edges onto the camera triangle's; `t` matches centroids.
fn pose_from_depths(
    y: &[Vector3<f64>; 3],
    lambda: &Vector3<f64>,
    points: &[Vector3<f64>; 3],
    world_inv: &Matrix3<f64>,
) -> Option<Pose> {
    let c = [lambda.x * y[0], lambda.y * y[1], lambda.z * y[2]];
    let v12 = c[0] - c[1];
    let v13 = c[0] - c[2];
    let camera = Matrix3::from_columns(&[v12, v13, v12.cross(&v13)]);
    let r = camera * world_inv;
    // Exact depths make r orthogonal; anything far off is a numerically failed solution.
    let orthogonality = (r.transpose() * r - Matrix3::identity()).abs().max();
    if !(orthogonality < 1e-3) {
        return None;
    }
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let rotation = UnitQuaternion::new_normalize(rotation.into_inner());
    let centroid_cam = (c[0] + c[1] + c[2]) / 3.0;
    let centroid_world = (points[0] + points[1] + points[2]) / 3.0;
    let pose = Pose::new(rotation, centroid_cam - rotation * centroid_world);
    pose.is_finite().then_some(pose)
}

/// Real roots of `c3·x³ + c2·x² + c1·x + c0` (`c3 ≠ 0`), each polished by Newton steps.
fn real_cubic_roots(c3: f64, c2: f64, c1: f64, c0: f64) -> [Option<f64>; 3] {
    let mut out = [None; 3];
    if !(c3.abs() > 0.0) || !c3.is_finite() {
        return out;
    }
    let (a, b, c) = (c2 / c3, c1 / c3, c0 / c3);
    // Depressed cubic t³ + p·t + q with x = t − a/3.
    let shift = a / 3.0;
    let p = b - a * shift;
    let q = 2.0 * shift * shift * shift - b * shift + c;
    let half_q = 0.5 * q;
    let third_p = p / 3.0;
    let disc = half_q * half_q + third_p * third_p * third_p;
    let mut roots = [f64::NAN; 3];
    if disc > 0.0 {
        let s = disc.sqrt();
        roots[0] = (-half_q + s).cbrt() + (-half_q - s).cbrt();
    } else if third_p < 0.0 {
        let r = 2.0 * (-third_p).sqrt();
        let cos_arg = (3.0 * q / (p * r)).clamp(-1.0, 1.0);
        let phi = cos_arg.acos() / 3.0;
        for (k, root) in roots.iter_mut().enumerate() {
            *root = r * (phi - 2.0 * std::f64::consts::PI * k as f64 / 3.0).cos();
        }
    } else {
        roots[0] = 0.0;
    }
    for (slot, t) in out.iter_mut().zip(roots) {
        if !t.is_finite() {
            continue;
        }
        let mut x = t - shift;
        for _ in 0..2 {
            let f = ((x + a) * x + b) * x + c;
            let df = (3.0 * x + 2.0 * a) * x + b;
            if df != 0.0 {
                let next = x - f / df;
                if next.is_finite() {
                    x = next;
                }
            }
        }
        *slot = Some(x);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cubic_roots() {
        // (x − 1)(x + 2)(x − 3) = x³ − 2x² − 5x + 6
        let mut roots: Vec<f64> = real_cubic_roots(1.0, -2.0, -5.0, 6.0)
            .iter()
            .flatten()
            .copied()
            .collect();
        roots.sort_by(f64::total_cmp);
        assert_eq!(roots.len(), 3);
        for (r, e) in roots.iter().zip([-2.0, 1.0, 3.0]) {
            assert!((r - e).abs() < 1e-12, "{roots:?}");
        }
        // x³ + x + 1: one real root near −0.6823.
        let roots: Vec<f64> = real_cubic_roots(2.0, 0.0, 2.0, 2.0)
            .iter()
            .flatten()
            .copied()
            .collect();
        assert_eq!(roots.len(), 1);
        assert!((roots[0] + 0.682_327_803_828_019_3).abs() < 1e-12);
    }

    #[test]
    fn solves_a_simple_configuration() {
        let truth = Pose::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.1, -0.2, 0.3)),
            Vector3::new(0.5, -0.3, 4.0),
        );
        let points = [
            Vector3::new(1.0, 0.0, 0.5),
            Vector3::new(-1.0, 0.5, 0.0),
            Vector3::new(0.2, -1.0, -0.3),
        ];
        let bearings = points.map(|p| truth.transform(&p));
        let solutions = p3p(&bearings, &points);
        assert!(!solutions.is_empty() && solutions.len() <= 4);
        let best = solutions
            .iter()
            .map(|s| s.rotation_error_deg(&truth) + s.center_distance(&truth))
            .fold(f64::INFINITY, f64::min);
        assert!(best < 1e-8, "{best}");
    }

    #[test]
    fn collinear_points_give_no_solution() {
        let points = [
            Vector3::new(0.0, 0.0, 5.0),
            Vector3::new(1.0, 0.0, 5.0),
            Vector3::new(2.0, 0.0, 5.0),
        ];
        assert!(p3p(&points, &points).is_empty());
    }
}
