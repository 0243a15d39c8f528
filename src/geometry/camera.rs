//! COLMAP camera models: parameter order, distortion, projection and iterative undistortion.
//!
//! The parameter order and the distortion polynomials are COLMAP's (`sensor/models.h`), so
//! parameters from `cameras.txt`, `database.db` or hloc query lists are used verbatim:
//!
//! | model          | id | parameters                       |
//! |----------------|----|----------------------------------|
//! | SIMPLE_PINHOLE | 0  | f, cx, cy                        |
//! | PINHOLE        | 1  | fx, fy, cx, cy                   |
//! | SIMPLE_RADIAL  | 2  | f, cx, cy, k                     |
//! | RADIAL         | 3  | f, cx, cy, k1, k2                |
//! | OPENCV         | 4  | fx, fy, cx, cy, k1, k2, p1, p2   |
//! | OPENCV_FISHEYE | 5  | fx, fy, cx, cy, k1, k2, k3, k4   |
//! | FULL_OPENCV    | 6  | fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 |
//!
//! The first five are special cases of OPENCV, so validation expands the parameters once into a
//! flat [`Intrinsics`] and they share one code path (zeros switch terms off); the pinhole
//! models skip distortion altogether.

use std::fmt;
use std::str::FromStr;

use nalgebra::{Matrix2, Matrix2x3, Vector2, Vector3};

use super::error::GeometryError;

use super::CameraModel;

/// The models the localizer projects and undistorts (COLMAP ids 0–6); the other COLMAP models
/// are read and written everywhere but refused for a query or map camera here.
pub const SUPPORTED: [CameraModel; 7] = [
    CameraModel::SimplePinhole,
    CameraModel::Pinhole,
    CameraModel::SimpleRadial,
    CameraModel::Radial,
    CameraModel::OpenCv,
    CameraModel::OpenCvFisheye,
    CameraModel::FullOpenCv,
];

/// The model named `name` (any case), if the localizer supports it.
fn supported_model(name: &str) -> Result<CameraModel, GeometryError> {
    let model = CameraModel::from_name_ignore_case(name).ok_or_else(|| {
        GeometryError::UnknownCameraModel {
            name: name.to_owned(),
        }
    })?;
    if SUPPORTED.contains(&model) {
        Ok(model)
    } else {
        Err(GeometryError::UnsupportedCameraModel { model })
    }
}

/// Which distortion function applies to normalized coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Distortion {
    /// The pinhole models, or any model whose coefficients are all zero.
    None,
    /// OPENCV and its special cases: radial `k1·r² + k2·r⁴`, tangential `p1`, `p2`.
    OpenCv,
    /// FULL_OPENCV: the radial factor is rational,
    /// `(1 + k1·r² + k2·r⁴ + k3·r⁶) / (1 + k4·r² + k5·r⁴ + k6·r⁶)`, plus `p1`, `p2`.
    FullOpenCv { k3: f64, k4: f64, k5: f64, k6: f64 },
    /// OPENCV_FISHEYE: equidistant, `θ_d = θ·(1 + k1·θ² + k2·θ⁴ + k3·θ⁶ + k4·θ⁸)` with
    /// `θ = atan(r)`; not the identity even with zero coefficients.
    Fisheye { k3: f64, k4: f64 },
}

/// The parameters of any supported model in one flat, OPENCV-like shape.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub k1: f64,
    pub k2: f64,
    pub p1: f64,
    pub p2: f64,
    pub distortion: Distortion,
}

impl Intrinsics {
    /// `None` for a model outside [`SUPPORTED`]; `p` holds the model's parameter count.
    fn from_params(model: CameraModel, p: &[f64]) -> Option<Self> {
        let opencv = |k1: f64, k2: f64, p1: f64, p2: f64| {
            if k1 == 0.0 && k2 == 0.0 && p1 == 0.0 && p2 == 0.0 {
                Distortion::None
            } else {
                Distortion::OpenCv
            }
        };
        let (fx, fy, cx, cy, k1, k2, p1, p2, distortion) = match model {
            CameraModel::SimplePinhole => {
                (p[0], p[0], p[1], p[2], 0.0, 0.0, 0.0, 0.0, Distortion::None)
            }
            CameraModel::Pinhole => (p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0, 0.0, Distortion::None),
            CameraModel::SimpleRadial => {
                let d = opencv(p[3], 0.0, 0.0, 0.0);
                (p[0], p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0, d)
            }
            CameraModel::Radial => {
                let d = opencv(p[3], p[4], 0.0, 0.0);
                (p[0], p[0], p[1], p[2], p[3], p[4], 0.0, 0.0, d)
            }
            CameraModel::OpenCv => {
                let d = opencv(p[4], p[5], p[6], p[7]);
                (p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], d)
            }
            CameraModel::OpenCvFisheye => {
                let d = Distortion::Fisheye { k3: p[6], k4: p[7] };
                (p[0], p[1], p[2], p[3], p[4], p[5], 0.0, 0.0, d)
            }
            CameraModel::FullOpenCv => {
                let d = if p[4..].iter().all(|&k| k == 0.0) {
                    Distortion::None
                } else {
                    Distortion::FullOpenCv {
                        k3: p[8],
                        k4: p[9],
                        k5: p[10],
                        k6: p[11],
                    }
                };
                (p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], d)
            }
            _ => return None,
        };
        Some(Self {
            fx,
            fy,
            cx,
            cy,
            k1,
            k2,
            p1,
            p2,
            distortion,
        })
    }

    pub fn is_distorted(&self) -> bool {
        self.distortion != Distortion::None
    }

    /// Distorted normalized coordinates (COLMAP's `u + du, v + dv`).
    #[inline]
    pub fn distort(&self, x: f64, y: f64) -> (f64, f64) {
        let (xx, xy, yy) = (x * x, x * y, y * y);
        let r2 = xx + yy;
        let radial = match self.distortion {
            Distortion::None => return (x, y),
            Distortion::OpenCv => 1.0 + self.k1 * r2 + self.k2 * r2 * r2,
            Distortion::FullOpenCv { k3, k4, k5, k6 } => {
                let (r4, r6) = (r2 * r2, r2 * r2 * r2);
                (1.0 + self.k1 * r2 + self.k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
            }
            Distortion::Fisheye { k3, k4 } => {
                let r = r2.sqrt();
                // θ_d / r → 1 at the centre; COLMAP also leaves tiny radii undistorted.
                if r < f64::EPSILON {
                    return (x, y);
                }
                let theta = r.atan();
                let t2 = theta * theta;
                let theta_d = theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (k3 + t2 * k4))));
                let scale = theta_d / r;
                return (x * scale, y * scale);
            }
        };
        (
            x * radial + 2.0 * self.p1 * xy + self.p2 * (r2 + 2.0 * xx),
            y * radial + 2.0 * self.p2 * xy + self.p1 * (r2 + 2.0 * yy),
        )
    }

    /// Pixel of a camera-frame point in plain scalars, `None` behind the camera. This is the
    /// RANSAC inner loop; scalars keep it fast even in unoptimized test builds.
    #[inline(always)]
    pub fn project_scalar(&self, x: f64, y: f64, z: f64) -> Option<(f64, f64)> {
        if !(z > MIN_DEPTH) {
            return None;
        }
        let inv_z = 1.0 / z;
        let (xd, yd) = self.distort(x * inv_z, y * inv_z);
        Some((self.fx * xd + self.cx, self.fy * yd + self.cy))
    }

    /// Jacobian of [`Self::distort`] with respect to the undistorted coordinates: analytic for
    /// the OPENCV family (the common case, and the refinement's inner loop), central
    /// differences for the rarer fisheye and rational models.
    #[inline]
    pub fn distort_jacobian(&self, x: f64, y: f64) -> Matrix2<f64> {
        match self.distortion {
            Distortion::None => Matrix2::identity(),
            Distortion::OpenCv => {
                let r2 = x * x + y * y;
                let radial = self.k1 * r2 + self.k2 * r2 * r2;
                // d(radial)/dx = 2x·(k1 + 2·k2·r2), likewise for y.
                let dradial = 2.0 * (self.k1 + 2.0 * self.k2 * r2);
                let (drx, dry) = (dradial * x, dradial * y);
                Matrix2::new(
                    1.0 + radial + x * drx + 2.0 * self.p1 * y + 6.0 * self.p2 * x,
                    x * dry + 2.0 * self.p1 * x + 2.0 * self.p2 * y,
                    y * drx + 2.0 * self.p2 * y + 2.0 * self.p1 * x,
                    1.0 + radial + y * dry + 2.0 * self.p2 * x + 6.0 * self.p1 * y,
                )
            }
            Distortion::FullOpenCv { .. } | Distortion::Fisheye { .. } => {
                let (hx, hy) = (1e-6 * (1.0 + x.abs()), 1e-6 * (1.0 + y.abs()));
                let (ax, ay) = self.distort(x + hx, y);
                let (bx, by) = self.distort(x - hx, y);
                let (cx, cy) = self.distort(x, y + hy);
                let (dx, dy) = self.distort(x, y - hy);
                Matrix2::new(
                    (ax - bx) / (2.0 * hx),
                    (cx - dx) / (2.0 * hy),
                    (ay - by) / (2.0 * hx),
                    (cy - dy) / (2.0 * hy),
                )
            }
        }
    }
}

/// A camera: a COLMAP model, the image size and the model's parameters in COLMAP order.
///
/// Construction validates once (parameter count, finite values, positive focal lengths and
/// size), so projection never has to check again and never panics.
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    model: CameraModel,
    width: u32,
    height: u32,
    params: Vec<f64>,
    intrinsics: Intrinsics,
}

/// Points closer to the camera plane than this (in camera units along +z) do not project.
pub(crate) const MIN_DEPTH: f64 = 1e-12;

impl Camera {
    /// A camera from a model and its parameters in COLMAP order.
    pub fn new(
        model: CameraModel,
        width: u32,
        height: u32,
        params: Vec<f64>,
    ) -> Result<Self, GeometryError> {
        if !SUPPORTED.contains(&model) {
            return Err(GeometryError::UnsupportedCameraModel { model });
        }
        if params.len() != model.num_params() {
            return Err(GeometryError::WrongParamCount {
                model,
                expected: model.num_params(),
                found: params.len(),
            });
        }
        if width == 0 || height == 0 {
            return Err(GeometryError::InvalidCamera {
                reason: "width and height must be positive",
            });
        }
        if params.iter().any(|p| !p.is_finite()) {
            return Err(GeometryError::InvalidCamera {
                reason: "parameters must be finite",
            });
        }
        let intrinsics = Intrinsics::from_params(model, &params)
            .ok_or(GeometryError::UnsupportedCameraModel { model })?;
        if intrinsics.fx <= 0.0 || intrinsics.fy <= 0.0 {
            return Err(GeometryError::InvalidCamera {
                reason: "focal lengths must be positive",
            });
        }
        Ok(Self {
            model,
            width,
            height,
            params,
            intrinsics,
        })
    }

    /// A camera from a COLMAP model name such as `"SIMPLE_RADIAL"`.
    pub fn from_model_name(
        name: &str,
        width: u32,
        height: u32,
        params: &[f64],
    ) -> Result<Self, GeometryError> {
        Self::new(supported_model(name)?, width, height, params.to_vec())
    }

    /// Parses `MODEL WIDTH HEIGHT p1 p2 ...` (whitespace-separated), the `--camera` syntax and
    /// the tail of an hloc query line.
    pub fn parse(input: &str) -> Result<Self, GeometryError> {
        let parse_err = |reason: String| GeometryError::ParseCamera {
            input: input.to_owned(),
            reason,
        };
        let mut tokens = input.split_whitespace();
        let model = tokens
            .next()
            .ok_or_else(|| parse_err("empty camera description".into()))?;
        let model = supported_model(model)?;
        let mut size = |what: &str| -> Result<u32, GeometryError> {
            let token = tokens
                .next()
                .ok_or_else(|| parse_err(format!("missing {what}")))?;
            token
                .parse::<u32>()
                .map_err(|e| parse_err(format!("{what} {token:?}: {e}")))
        };
        let width = size("width")?;
        let height = size("height")?;
        let params = tokens
            .map(|t| {
                t.parse::<f64>()
                    .map_err(|e| parse_err(format!("parameter {t:?}: {e}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        Self::new(model, width, height, params)
    }

    /// Parses an hloc query-list line `name MODEL WIDTH HEIGHT p1 p2 ...` into the image name
    /// and its camera. Image names must not contain whitespace (as in hloc).
    pub fn parse_query_line(line: &str) -> Result<(String, Self), GeometryError> {
        let line = line.trim();
        let (name, rest) =
            line.split_once(char::is_whitespace)
                .ok_or_else(|| GeometryError::ParseCamera {
                    input: line.to_owned(),
                    reason: "expected `name MODEL WIDTH HEIGHT params...`".into(),
                })?;
        Ok((name.to_owned(), Self::parse(rest)?))
    }

    /// The camera for the same images resized to `new_width × new_height`, as COLMAP's
    /// `Camera::Rescale`: principal point and focal lengths scale per axis (a single focal
    /// length by the mean of both factors); distortion, defined on normalized coordinates,
    /// is unchanged. Feature extractors that downsample need this to keep keypoints and
    /// intrinsics in the same pixels.
    pub fn rescaled(&self, new_width: u32, new_height: u32) -> Result<Self, GeometryError> {
        if new_width == 0 || new_height == 0 {
            return Err(GeometryError::InvalidCamera {
                reason: "width and height must be positive",
            });
        }
        let scale_x = f64::from(new_width) / f64::from(self.width);
        let scale_y = f64::from(new_height) / f64::from(self.height);
        let mut params = self.params.clone();
        if self.has_single_focal() {
            params[0] *= 0.5 * (scale_x + scale_y);
            params[1] *= scale_x;
            params[2] *= scale_y;
        } else {
            params[0] *= scale_x;
            params[1] *= scale_y;
            params[2] *= scale_x;
            params[3] *= scale_y;
        }
        Self::new(self.model, new_width, new_height, params)
    }

    fn has_single_focal(&self) -> bool {
        matches!(
            self.model,
            CameraModel::SimplePinhole | CameraModel::SimpleRadial | CameraModel::Radial
        )
    }

    /// Focal lengths `(fx, fy)` in pixels (equal for the single-focal models).
    pub fn focal_lengths(&self) -> (f64, f64) {
        (self.intrinsics.fx, self.intrinsics.fy)
    }

    /// The COLMAP camera model.
    pub fn model(&self) -> CameraModel {
        self.model
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Parameters in COLMAP order.
    pub fn params(&self) -> &[f64] {
        &self.params
    }

    /// Mean of the x and y focal lengths, to convert pixel thresholds to angles.
    pub fn mean_focal(&self) -> f64 {
        0.5 * (self.intrinsics.fx + self.intrinsics.fy)
    }

    /// Principal point in pixels.
    pub fn principal_point(&self) -> Vector2<f64> {
        Vector2::new(self.intrinsics.cx, self.intrinsics.cy)
    }

    /// Whether a pixel lies inside the image (COLMAP convention: `[0, width) × [0, height)`).
    pub fn contains(&self, pixel: &Vector2<f64>) -> bool {
        pixel.x >= 0.0
            && pixel.y >= 0.0
            && pixel.x < f64::from(self.width)
            && pixel.y < f64::from(self.height)
    }

    pub(crate) fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// Projects a point in camera coordinates to pixels; `None` behind (or on) the camera
    /// plane, where a pixel would be meaningless.
    #[inline]
    pub fn project(&self, p_cam: &Vector3<f64>) -> Option<Vector2<f64>> {
        let (u, v) = self.intrinsics.project_scalar(p_cam.x, p_cam.y, p_cam.z)?;
        (u.is_finite() && v.is_finite()).then_some(Vector2::new(u, v))
    }

    /// Pixel of an undistorted normalized image point `(X/Z, Y/Z)`.
    #[inline]
    pub fn normalized_to_pixel(&self, xy: &Vector2<f64>) -> Vector2<f64> {
        let k = &self.intrinsics;
        let (xd, yd) = k.distort(xy.x, xy.y);
        Vector2::new(k.fx * xd + k.cx, k.fy * yd + k.cy)
    }

    /// Projection and its Jacobian with respect to the camera-frame point, for refinement.
    #[inline]
    pub(crate) fn project_with_jacobian(
        &self,
        p_cam: &Vector3<f64>,
    ) -> Option<(Vector2<f64>, Matrix2x3<f64>)> {
        if !(p_cam.z > MIN_DEPTH) {
            return None;
        }
        let k = &self.intrinsics;
        let inv_z = 1.0 / p_cam.z;
        let (x, y) = (p_cam.x * inv_z, p_cam.y * inv_z);
        let (xd, yd) = k.distort(x, y);
        let pixel = Vector2::new(k.fx * xd + k.cx, k.fy * yd + k.cy);
        let d_norm = Matrix2x3::new(inv_z, 0.0, -x * inv_z, 0.0, inv_z, -y * inv_z);
        let d_dist = k.distort_jacobian(x, y);
        let d_focal = Matrix2::new(k.fx, 0.0, 0.0, k.fy);
        let jacobian = d_focal * d_dist * d_norm;
        (pixel.iter().chain(jacobian.iter()).all(|v| v.is_finite())).then_some((pixel, jacobian))
    }

    /// The undistorted normalized image point `(X/Z, Y/Z)` seen at a pixel.
    ///
    /// Distortion is inverted by Newton's method with the analytic Jacobian, started at the
    /// distorted point, as COLMAP does (it differentiates numerically). Non-convergence (strong
    /// distortion far outside the image) returns the best finite iterate rather than failing,
    /// because callers check reprojection errors anyway; a non-finite pixel gives a
    /// non-finite result.
    pub fn unproject(&self, pixel: &Vector2<f64>) -> Vector2<f64> {
        let k = &self.intrinsics;
        let target = Vector2::new((pixel.x - k.cx) / k.fx, (pixel.y - k.cy) / k.fy);
        if !(k.is_distorted() && target.x.is_finite() && target.y.is_finite()) {
            return target;
        }
        const MAX_ITERATIONS: usize = 100;
        const STEP_TOLERANCE: f64 = 1e-14;
        let mut xy = target;
        for _ in 0..MAX_ITERATIONS {
            let (xd, yd) = k.distort(xy.x, xy.y);
            let residual = Vector2::new(xd - target.x, yd - target.y);
            let Some(inverse) = k.distort_jacobian(xy.x, xy.y).try_inverse() else {
                break;
            };
            let step = inverse * residual;
            let next = xy - step;
            if !(next.x.is_finite() && next.y.is_finite()) {
                break;
            }
            xy = next;
            if step.norm_squared() <= STEP_TOLERANCE * STEP_TOLERANCE * (1.0 + xy.norm_squared()) {
                break;
            }
        }
        xy
    }

    /// Unit bearing vector (camera frame) of the ray through a pixel.
    pub fn bearing(&self, pixel: &Vector2<f64>) -> Vector3<f64> {
        let xy = self.unproject(pixel);
        Vector3::new(xy.x, xy.y, 1.0).normalize()
    }
}

impl FromStr for Camera {
    type Err = GeometryError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::parse(s)
    }
}

impl fmt::Display for Camera {
    /// The `MODEL WIDTH HEIGHT params...` form that [`Camera::parse`] reads back.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} {} {}", self.model, self.width, self.height)?;
        for p in &self.params {
            write!(f, " {p}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_jacobian_matches_finite_differences() {
        let camera =
            Camera::parse("OPENCV 640 480 500 510 320 240 -0.2 0.05 0.001 -0.002").unwrap();
        let k = camera.intrinsics();
        let (x, y) = (0.31, -0.22);
        let h = 1e-7;
        let j = k.distort_jacobian(x, y);
        let (ax, ay) = k.distort(x + h, y);
        let (bx, by) = k.distort(x - h, y);
        let (cx, cy) = k.distort(x, y + h);
        let (dx, dy) = k.distort(x, y - h);
        let numeric = Matrix2::new(
            (ax - bx) / (2.0 * h),
            (cx - dx) / (2.0 * h),
            (ay - by) / (2.0 * h),
            (cy - dy) / (2.0 * h),
        );
        assert!((j - numeric).abs().max() < 1e-7, "{j} vs {numeric}");
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        let camera = Camera::parse("RADIAL 640 480 500 320 240 -0.1 0.02").unwrap();
        let p = Vector3::new(0.3, -0.2, 2.0);
        let (_, j) = camera.project_with_jacobian(&p).unwrap();
        let h = 1e-6;
        for c in 0..3 {
            let mut a = p;
            let mut b = p;
            a[c] += h;
            b[c] -= h;
            let d = (camera.project(&a).unwrap() - camera.project(&b).unwrap()) / (2.0 * h);
            assert!(
                (d - j.column(c)).norm() < 1e-5,
                "column {c}: {d} vs {}",
                j.column(c)
            );
        }
    }

    #[test]
    fn display_round_trips_through_parse() {
        let camera = Camera::parse("simple_radial 1024 768 800.5 512 384 -0.01").unwrap();
        assert_eq!(camera.model(), CameraModel::SimpleRadial);
        assert_eq!(Camera::parse(&camera.to_string()).unwrap(), camera);
    }
}
