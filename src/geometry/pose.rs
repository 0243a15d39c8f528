//! Rigid camera poses in COLMAP's `cam_from_world` convention.

use nalgebra::{Quaternion, Rotation3, UnitQuaternion, Vector3};

use super::error::GeometryError;

/// How far `‖q‖²` may be from 1 for a quaternion to count as unit and be kept as given: a few
/// ulps, the error of normalising in f64.
const UNIT_TOLERANCE: f64 = 8.0 * f64::EPSILON;

/// A camera pose `cam_from_world`: `p_cam = rotation · p_world + translation`.
///
/// This is what COLMAP stores per image (`images.txt`: `QW QX QY QZ TX TY TZ`) and what
/// `gt_poses.txt` and `sfpmap localize` write.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// World-to-camera rotation.
    pub rotation: UnitQuaternion<f64>,
    /// World origin in camera coordinates.
    pub translation: Vector3<f64>,
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    /// The pose `p_cam = rotation · p_world + translation`.
    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// The camera at the world origin, looking along +z.
    pub fn identity() -> Self {
        Self::new(UnitQuaternion::identity(), Vector3::zeros())
    }

    /// From COLMAP's `QW QX QY QZ TX TY TZ`; a zero or non-finite quaternion or translation
    /// is an error.
    ///
    /// A quaternion that is not unit (a text file's rounding) is normalised, as COLMAP does
    /// when it reads a model. One that is unit to within a few ulps is kept bit for bit, so
    /// that a model read and written back, or converted into a map, keeps COLMAP's values
    /// exactly, and normalising twice is the same as once.
    pub fn from_colmap(
        qw: f64,
        qx: f64,
        qy: f64,
        qz: f64,
        tx: f64,
        ty: f64,
        tz: f64,
    ) -> Result<Self, GeometryError> {
        let values = [qw, qx, qy, qz, tx, ty, tz];
        if let Some(index) = values.iter().position(|v| !v.is_finite()) {
            return Err(GeometryError::NonFinite {
                what: "colmap pose",
                index,
            });
        }
        let q = Quaternion::new(qw, qx, qy, qz);
        let norm_squared = q.norm_squared();
        if !norm_squared.is_finite() {
            // 1e200 squared: no quaternion of that size can be normalised in f64.
            return Err(GeometryError::NonFinite {
                what: "colmap pose (quaternion norm)",
                index: 0,
            });
        }
        if !(norm_squared > 1e-24) {
            return Err(GeometryError::Degenerate {
                reason: "zero quaternion",
            });
        }
        let q = if (norm_squared - 1.0).abs() <= UNIT_TOLERANCE {
            q
        } else {
            q / norm_squared.sqrt()
        };
        Ok(Self::new(
            UnitQuaternion::new_unchecked(q),
            Vector3::new(tx, ty, tz),
        ))
    }

    /// [`from_colmap`](Self::from_colmap) of `[qw, qx, qy, qz, tx, ty, tz]`, the order of
    /// `images.txt`, `images.bin` and a map's `image_poses`.
    pub fn from_colmap_array(v: [f64; 7]) -> Result<Self, GeometryError> {
        Self::from_colmap(v[0], v[1], v[2], v[3], v[4], v[5], v[6])
    }

    /// `[qw, qx, qy, qz, tx, ty, tz]`, COLMAP's order.
    pub fn to_colmap(&self) -> [f64; 7] {
        let q = self.rotation.quaternion();
        let t = &self.translation;
        [q.w, q.i, q.j, q.k, t.x, t.y, t.z]
    }

    /// Maps a world point into the camera frame.
    #[inline]
    pub fn transform(&self, p_world: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * p_world + self.translation
    }

    /// The camera centre in world coordinates, `-Rᵀ t`.
    pub fn center(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }

    /// `world_from_cam`.
    pub fn inverse(&self) -> Self {
        let rotation = self.rotation.inverse();
        Self::new(rotation, -(rotation * self.translation))
    }

    /// `self ∘ other`: first `other`, then `self` (`a_from_c = a_from_b.compose(&b_from_c)`).
    pub fn compose(&self, other: &Pose) -> Self {
        Self::new(
            self.rotation * other.rotation,
            self.rotation * other.translation + self.translation,
        )
    }

    /// The rotation as a matrix.
    pub fn rotation_matrix(&self) -> Rotation3<f64> {
        self.rotation.to_rotation_matrix()
    }

    /// Angle in degrees of the relative rotation between two poses (0..=180).
    pub fn rotation_error_deg(&self, other: &Pose) -> f64 {
        self.rotation.angle_to(&other.rotation).to_degrees()
    }

    /// Distance between the camera centres, in map units; the translation error of
    /// localization benchmarks.
    pub fn center_distance(&self, other: &Pose) -> f64 {
        (self.center() - other.center()).norm()
    }

    /// Whether every component is finite.
    pub fn is_finite(&self) -> bool {
        self.to_colmap().iter().all(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colmap_round_trip_and_errors() {
        let pose = Pose::from_colmap(2.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0).unwrap();
        assert_eq!(pose.to_colmap(), [1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0]);
        assert_eq!(pose.center(), Vector3::new(-1.0, -2.0, -3.0));
        let turned = Pose::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, 10f64.to_radians())),
            Vector3::zeros(),
        );
        assert!((pose.rotation_error_deg(&turned) - 10.0).abs() < 1e-9);
        assert!(Pose::from_colmap(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).is_err());
        assert!(Pose::from_colmap(f64::NAN, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).is_err());
        // Finite, but its norm overflows: not a rotation (it would normalise to zero).
        assert!(Pose::from_colmap(1e200, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).is_err());
    }

    #[test]
    fn unit_quaternions_are_kept_bit_for_bit_and_normalising_is_idempotent() {
        // Unit to within an ulp but not exactly 1 when squared: kept as given.
        let q = [0.5, 0.5, 0.5, 0.5000000000000002];
        let v = [q[0], q[1], q[2], q[3], 1.0, 2.0, 3.0];
        let squared = Quaternion::new(q[0], q[1], q[2], q[3]).norm_squared();
        assert_ne!(squared, 1.0, "the case normalising would change");
        assert_eq!(Pose::from_colmap_array(v).unwrap().to_colmap(), v);
        // A text file's rounding is normalised, and the result is kept on a second pass.
        let once = Pose::from_colmap(0.6, 0.0, 0.8001, 0.0, 0.0, 0.0, 0.0).unwrap();
        assert!((once.rotation.quaternion().norm() - 1.0).abs() < 1e-15);
        assert_ne!(once.to_colmap()[0], 0.6);
        let twice = Pose::from_colmap_array(once.to_colmap()).unwrap();
        assert_eq!(twice.to_colmap(), once.to_colmap());
    }

    #[test]
    fn compose_and_inverse() {
        let a = Pose::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -0.2, 0.1)),
            Vector3::new(1.0, 2.0, -3.0),
        );
        let b = Pose::new(
            UnitQuaternion::from_scaled_axis(Vector3::new(-0.5, 0.4, 0.9)),
            Vector3::new(-0.5, 0.25, 4.0),
        );
        let p = Vector3::new(0.7, -1.1, 2.5);
        let ab = a.compose(&b);
        assert!((ab.transform(&p) - a.transform(&b.transform(&p))).norm() < 1e-12);
        let identity = a.compose(&a.inverse());
        assert!(identity.transform(&p).metric_distance(&p) < 1e-12);
        assert!(a.inverse().translation.metric_distance(&a.center()) < 1e-12);
    }
}
