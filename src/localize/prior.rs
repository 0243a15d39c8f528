//! Pose priors: where the database cameras are, which of them look where a pose looks, and a
//! constant-velocity motion model that predicts each frame of a sequence from the previous.
//!
//! A prior replaces retrieval: the points of the database images nearest the predicted pose
//! are matched by reprojection around it (guided matching), so a tracked frame needs no
//! global descriptor and no coarse matching at all.

use crate::geometry::Pose;
use crate::vector::top_k_indices;
use nalgebra::Vector3;

/// Each database image's camera centre and viewing direction, in world coordinates.
pub(crate) struct Viewpoints {
    centres: Vec<Vector3<f64>>,
    directions: Vec<Vector3<f64>>,
}

/// Database images looking more than this far away from the query's direction see other
/// things (cos 75°).
const MIN_DIRECTION_COSINE: f64 = 0.26;

impl Viewpoints {
    /// From `cam_from_world` poses (images whose pose is not a rotation are left out: they
    /// are never near anything).
    pub(crate) fn new(poses: &[[f64; 7]]) -> Viewpoints {
        let mut centres = Vec::with_capacity(poses.len());
        let mut directions = Vec::with_capacity(poses.len());
        for &p in poses {
            match Pose::from_colmap_array(p) {
                Ok(pose) => {
                    centres.push(pose.center());
                    directions.push(viewing_direction(&pose));
                }
                Err(_) => {
                    centres.push(Vector3::repeat(f64::NAN));
                    directions.push(Vector3::zeros());
                }
            }
        }
        Viewpoints {
            centres,
            directions,
        }
    }

    /// The `k` database images nearest `pose`'s centre among those looking within 75° of
    /// its direction, nearest first: O(images) and a partial selection, no sort of all.
    pub(crate) fn near(&self, pose: &Pose, k: usize) -> Vec<usize> {
        let (centre, direction) = (pose.center(), viewing_direction(pose));
        let scores: Vec<f32> = self
            .centres
            .iter()
            .zip(&self.directions)
            .map(|(c, d)| {
                let distance = (c - centre).norm();
                if d.dot(&direction) >= MIN_DIRECTION_COSINE && distance.is_finite() {
                    -(distance as f32)
                } else {
                    f32::NEG_INFINITY
                }
            })
            .collect();
        let mut near = top_k_indices(&scores, k);
        near.retain(|&i| scores[i] > f32::NEG_INFINITY);
        near
    }
}

/// The camera's optical axis (+z) in world coordinates.
fn viewing_direction(pose: &Pose) -> Vector3<f64> {
    pose.rotation.inverse() * Vector3::z()
}

/// Constant velocity: the next `cam_from_world` is the last one moved by the motion between
/// the last two frames. A frame that is not localized resets it (the next frame goes through
/// retrieval, then tracking resumes). A [`Session`](crate::session::Session) in sequence mode
/// keeps one.
#[derive(Debug, Clone, Default)]
pub struct MotionModel {
    last: Option<Pose>,
    /// `cam_k_from_cam_{k−1}` of the last two localized frames.
    step: Option<Pose>,
}

impl MotionModel {
    pub fn new() -> MotionModel {
        MotionModel::default()
    }

    /// The predicted pose of the next frame: the last pose moved by the last step, or the
    /// last pose itself after one frame; `None` before any.
    pub fn predict(&self) -> Option<Pose> {
        let last = self.last.as_ref()?;
        Some(match &self.step {
            Some(step) => step.compose(last),
            None => *last,
        })
    }

    /// Records the frame's pose (`None`: not localized, which resets the model).
    pub fn update(&mut self, pose: Option<&Pose>) {
        match pose {
            Some(pose) => {
                self.step = self.last.as_ref().map(|last| pose.compose(&last.inverse()));
                self.last = Some(*pose);
            }
            None => *self = MotionModel::default(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn looking_along_z_at(x: f64) -> Pose {
        // cam_from_world with identity rotation: centre = -t.
        Pose::new(UnitQuaternion::identity(), Vector3::new(-x, 0.0, 0.0))
    }

    #[test]
    fn constant_velocity_predicts_the_next_frame() {
        let mut model = MotionModel::new();
        assert!(model.predict().is_none());
        model.update(Some(&looking_along_z_at(0.0)));
        assert!(
            model
                .predict()
                .unwrap()
                .center_distance(&looking_along_z_at(0.0))
                < 1e-12
        );
        // A turn and a step: the third frame repeats both.
        let turn = UnitQuaternion::from_euler_angles(0.0, 0.1, 0.0);
        let second = Pose::new(turn, turn * Vector3::new(-1.0, 0.0, 0.0));
        model.update(Some(&second));
        let predicted = model.predict().unwrap();
        let step = second.compose(&looking_along_z_at(0.0).inverse());
        let expected = step.compose(&second);
        assert!(predicted.center_distance(&expected) < 1e-12);
        assert!(predicted.rotation_error_deg(&expected) < 1e-9);
        assert!((predicted.rotation_error_deg(&second) - 0.1f64.to_degrees()).abs() < 1e-9);
        // A lost frame resets the model.
        model.update(None);
        assert!(model.predict().is_none());
    }

    #[test]
    fn images_near_a_pose_are_the_nearest_that_look_the_same_way() {
        let ahead = |x: f64| looking_along_z_at(x).to_colmap();
        // Image 3 is nearest but looks backwards (180° about y).
        let back = Pose::new(
            UnitQuaternion::from_euler_angles(0.0, std::f64::consts::PI, 0.0),
            Vector3::zeros(),
        );
        let poses = [
            ahead(5.0),
            ahead(1.0),
            ahead(-2.0),
            back.to_colmap(),
            [0.0; 7],
        ];
        let viewpoints = Viewpoints::new(&poses);
        let query = looking_along_z_at(0.1);
        assert_eq!(viewpoints.near(&query, 2), [1, 2]);
        // Never more than those that qualify; the zero quaternion is never near.
        assert_eq!(viewpoints.near(&query, 10), [1, 2, 0]);
    }
}
