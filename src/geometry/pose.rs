//! Rigid camera poses in COLMAP's `cam_from_world` convention.

use nalgebra::{Quaternion, Rotation3, UnitQuaternion, Vector3};

use super::error::GeometryError;

/// A camera pose `cam_from_world`: `p_cam = rotation · p_world + translation`.
///
/// This is what COLMAP stores per image (`images.txt`: `QW QX QY QZ TX TY TZ`) and what
/// `gt_poses.txt` and `sfpmap localize` write.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub rotation: UnitQuaternion<f64>,
    pub translation: Vector3<f64>,
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    pub fn identity() -> Self {
        Self::new(UnitQuaternion::identity(), Vector3::zeros())
    }

    /// From COLMAP's `QW QX QY QZ TX TY TZ`. The quaternion is normalized, since text files
    /// round it; a zero or non-finite quaternion or translation is an error.
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
        let norm = q.norm();
        if !(norm > 1e-12) {
            return Err(GeometryError::Degenerate {
                reason: "zero quaternion",
            });
        }
        Ok(Self::new(
            UnitQuaternion::new_unchecked(q / norm),
            Vector3::new(tx, ty, tz),
        ))
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
    }
}
