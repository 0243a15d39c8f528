//! Geometry against a real COLMAP reconstruction (the shared South Building scene): COLMAP's
//! own 2D–3D observations, camera and poses must agree with our projection, and RANSAC must
//! recover the stored poses. The model is read by `sfpmap::colmap` (feature `colmap-model`,
//! no dependencies).
#![cfg(all(feature = "localize", feature = "colmap-model"))]

use crate::shared_data;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nalgebra::{Vector2, Vector3};
use sfpmap::geometry::{estimate_absolute_pose, Camera, Pose, RansacOptions};

struct Image {
    name: String,
    camera_id: u32,
    pose: Pose,
    observations: Vec<(Vector2<f64>, u64)>,
}

fn scene_dir(scene: &str) -> Option<PathBuf> {
    shared_data::shared_data(&format!("scenes/{scene}/sparse-full"))
}

type Model = (
    HashMap<u32, Camera>,
    Vec<Image>,
    HashMap<u64, (Vector3<f64>, f64)>,
);

/// The model through the crate's COLMAP reader, in the geometry module's types.
fn read_model(dir: &Path) -> Model {
    let model = sfpmap::colmap::read_model(dir).unwrap();
    let cameras = model
        .cameras()
        .iter()
        .map(|c| {
            // One camera-model type for the COLMAP reader and the localizer.
            let camera = Camera::new(c.model, c.width as u32, c.height as u32, c.params.clone());
            (c.id, camera.unwrap())
        })
        .collect();
    let images = model
        .images()
        .iter()
        .map(|i| {
            Image {
                name: i.name.clone(),
                camera_id: i.camera_id,
                // The reader's pose is the geometry module's: no conversion.
                pose: i.cam_from_world,
                observations: i
                    .points2d
                    .iter()
                    .filter_map(|p| Some((Vector2::new(p.xy[0], p.xy[1]), p.point3d_id?)))
                    .collect(),
            }
        })
        .collect();
    let points = model
        .points3d()
        .iter()
        .map(|p| (p.id, (Vector3::from(p.xyz), p.error)))
        .collect();
    (cameras, images, points)
}

#[test]
fn colmap_observations_reproject_and_poses_are_recovered() {
    for scene in ["south-building", "sacre-coeur"] {
        if let Some(dir) = scene_dir(scene) {
            check_scene(&dir);
        }
    }
}

fn check_scene(dir: &Path) {
    let (cameras, images, points) = read_model(dir);
    let options = RansacOptions {
        max_error_px: 4.0,
        ..RansacOptions::default()
    };
    for image in images.iter().step_by(16) {
        let camera = &cameras[&image.camera_id];
        let (mut pixels, mut xyz) = (Vec::new(), Vec::new());
        let (mut ours, mut colmap) = (0.0, 0.0);
        for &(pixel, id) in &image.observations {
            let (point, error) = points[&id];
            let projected = camera.project(&image.pose.transform(&point)).unwrap();
            ours += (projected - pixel).norm();
            colmap += error;
            pixels.push(pixel);
            xyz.push(point);
        }
        let n = pixels.len() as f64;
        // Our projection of COLMAP's points with COLMAP's pose and camera lands where COLMAP
        // observed them, within COLMAP's own track errors: model, parameter order and pixel
        // convention agree.
        let (ours, colmap) = (ours / n, colmap / n);
        assert!(
            ours < 1.5 && ours < 1.3 * colmap + 0.05,
            "{}: {ours} px vs colmap {colmap} px",
            image.name
        );

        let estimate = estimate_absolute_pose(&pixels, &xyz, camera, &options).unwrap();
        let rot = estimate.pose.rotation_error_deg(&image.pose);
        let pos = estimate.pose.center_distance(&image.pose);
        let shifted: f64 = image
            .observations
            .iter()
            .map(|&(pixel, id)| {
                let projected = camera
                    .project(&image.pose.transform(&points[&id].0))
                    .unwrap();
                (projected - pixel + Vector2::new(0.5, 0.5)).norm()
            })
            .sum::<f64>()
            / n;
        println!(
            "{}: {} obs, mean reprojection {ours:.3} px (colmap track mean {colmap:.3}, with a half-pixel shift {shifted:.3}), ransac {rot:.4}° {pos:.5}, {} inliers, {} iterations",
            image.name,
            pixels.len(),
            estimate.num_inliers,
            estimate.iterations
        );
        // A half-pixel shift of the convention would double the error (0.4 → 0.8 px here).
        assert!(shifted > ours + 0.2, "{}: {shifted} vs {ours}", image.name);
        assert!(rot < 0.1 && pos < 0.01, "{}: {rot}° {pos}", image.name);
        assert!(estimate.num_inliers as f64 > 0.95 * n, "{}", image.name);
    }
}
