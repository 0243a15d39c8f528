//! Writing kapture: a map (`sfpmap export --kapture`) and localized queries (`sfpmap
//! localize --format kapture`).
//!
//! What a map export holds: one camera sensor per map camera (`cam_NNNNN`, NNNNN its COLMAP
//! id), a record and a trajectory per database image (the timestamp is the image's id), every
//! point in `points3d.txt` (row = the map's point index; colours where the map has them), and,
//! where the map stores its observations' keypoints, a keypoints type `sfpmap` (`float32`,
//! dsize 2: the observed keypoints of each image, in the map's order) with `observations.txt`.
//! No descriptors: a map keeps one aggregated descriptor per point, not one per image
//! keypoint, so there is nothing kapture's per-image `.desc` files could hold.

use super::{name_problem, KaptureError, KAPTURE_CAMERA_MODELS, KAPTURE_HEADER};
use crate::format::{CameraInfo, Map};
use crate::geometry::Pose;
use crate::output::{check_output, write_atomic, OutputError};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The keypoints type a map export writes.
pub const EXPORT_KEYPOINTS_TYPE: &str = "sfpmap";

/// Counts of what [`export_kapture`] wrote.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct KaptureExportSummary {
    /// Camera sensors.
    pub cameras: usize,
    /// Images (records with a trajectory).
    pub images: usize,
    /// Rows of `points3d.txt`.
    pub points: usize,
    /// Observations (keypoints with a point), 0 if the map stores no keypoints.
    pub observations: usize,
}

/// A sensor id for the map's camera `index`.
fn sensor_id(cameras: &[CameraInfo], index: usize) -> String {
    let id = cameras
        .get(index)
        .and_then(|c| c.id)
        .unwrap_or(index as u32 + 1);
    format!("cam_{id:05}")
}

/// One `sensors.txt` row of a camera, refused if kapture does not know its model.
fn camera_row(
    out: &mut String,
    id: &str,
    model: &str,
    size: [u64; 2],
    params: &[f64],
) -> Result<(), String> {
    if !KAPTURE_CAMERA_MODELS.contains(&model) {
        return Err(format!(
            "model {} is not one kapture 1.1 knows ({})",
            crate::escape::quoted_name(model),
            KAPTURE_CAMERA_MODELS.join(", ")
        ));
    }
    if !params.iter().all(|p| p.is_finite()) {
        return Err("a parameter is not finite".into());
    }
    write!(out, "{id}, , camera, {model}, {}, {}", size[0], size[1]).ok();
    for p in params {
        write!(out, ", {p}").ok();
    }
    out.push('\n');
    Ok(())
}

/// One `trajectories.txt` row.
fn trajectory_row(out: &mut String, timestamp: usize, sensor: &str, pose: &Pose) {
    let [qw, qx, qy, qz, tx, ty, tz] = pose.to_colmap();
    writeln!(
        out,
        "{timestamp}, {sensor}, {qw}, {qx}, {qy}, {qz}, {tx}, {ty}, {tz}"
    )
    .ok();
}

fn unwritable(what: String) -> impl FnOnce(String) -> KaptureError {
    move |reason| KaptureError::Unwritable { what, reason }
}

/// Refuses an image name a kapture table or a `.kpt` path cannot hold.
fn check_name(what: impl FnOnce() -> String, name: &str) -> Result<(), KaptureError> {
    match name_problem(name) {
        Some(problem) => Err(KaptureError::Unwritable {
            what: what(),
            reason: format!(
                "name {} {problem}, which kapture cannot hold",
                crate::escape::quoted_name(name)
            ),
        }),
        None => Ok(()),
    }
}

/// Checks every output against the policy ([`check_output`]) before anything is written, so
/// a refused one leaves the folder as it was.
fn check_outputs(outputs: &[PathBuf], inputs: &[&Path], force: bool) -> Result<(), KaptureError> {
    for out in outputs {
        check_output(out, inputs, force)?;
    }
    Ok(())
}

/// Writes `text` to `path` (its folder created) through the atomic writer.
fn write_text(path: &Path, text: &str) -> Result<(), KaptureError> {
    write_bytes(path, text.as_bytes())
}

fn write_bytes(path: &Path, bytes: &[u8]) -> Result<(), KaptureError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| OutputError::Io {
            path: dir.to_path_buf(),
            action: "cannot create the folder",
            source: e,
        })?;
    }
    write_atomic(path, |out| {
        std::io::Write::write_all(out, bytes).map_err(|e| OutputError::cannot_write(path, e))
    })?;
    Ok(())
}

fn table(header: &str) -> String {
    format!("{KAPTURE_HEADER}\n# {header}\n")
}

/// Whether `map` can be written as kapture at all: images to record, camera models kapture
/// knows, image names its tables and `.kpt` paths can hold, no two images of one name, poses
/// that are rotations. What [`export_kapture`] checks before it writes anything; a caller
/// writing other outputs too (`sfpmap export --ply ... --kapture ...`) asks first, so a
/// refusal leaves none of them behind.
pub fn check_exportable(map: &Map<'_>) -> Result<(), KaptureError> {
    let meta = map.metadata();
    let images = map.images()?.ok_or_else(|| KaptureError::Unwritable {
        what: "the map".into(),
        reason: "has no images; kapture records and trajectories need them".into(),
    })?;
    let mut scratch = String::new();
    for (i, c) in meta.cameras.iter().enumerate() {
        let id = sensor_id(&meta.cameras, i);
        camera_row(&mut scratch, &id, &c.model, [c.width, c.height], &c.params)
            .map_err(unwritable(format!("camera {}", &id[4..])))?;
    }
    // kapture keys an image's files by its path: two images of one name would share a .kpt
    // file (the second written over the first) and its records would not read back.
    let mut seen: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
    for i in 0..images.len() {
        let id = images.ids.as_ref().map_or(i as u32 + 1, |ids| ids[i]) as usize;
        let name = images.name(i)?;
        check_name(|| format!("image {id}"), name)?;
        if let Some(first) = seen.insert(name, id) {
            return Err(unwritable(format!("image {id}"))(format!(
                "its name {} is image {first}'s too, and a kapture folder keys images by name",
                crate::escape::quoted_name(name)
            )));
        }
        Pose::from_colmap_array(images.poses[i])
            .map_err(|e| unwritable(format!("image {id}"))(format!("pose: {e}")))?;
    }
    Ok(())
}

/// Writes `map` as a kapture folder in `dir` (see the [module docs](self) for what is in
/// it). The map is checked first ([`check_exportable`]), every output against `inputs`
/// (never written over) and, unless `force`, refused if it exists; then each file is written
/// through the atomic writer.
pub fn export_kapture(
    map: &Map<'_>,
    dir: &Path,
    inputs: &[&Path],
    force: bool,
) -> Result<KaptureExportSummary, KaptureError> {
    check_exportable(map)?;
    let meta = map.metadata();
    let images = map.images()?.ok_or_else(|| KaptureError::Unwritable {
        what: "the map".into(),
        reason: "has no images; kapture records and trajectories need them".into(),
    })?;
    let visibility = map.visibility()?;
    let positions = map.point_positions()?;
    let colors = map.point_colors()?;

    let mut sensors = table("sensor_id, name, sensor_type, [sensor_params]+");
    for (i, c) in meta.cameras.iter().enumerate() {
        let id = sensor_id(&meta.cameras, i);
        camera_row(&mut sensors, &id, &c.model, [c.width, c.height], &c.params)
            .map_err(unwritable(format!("camera {}", &id[4..])))?;
    }
    let mut records = table("timestamp, device_id, image_path");
    let mut trajectories = table("timestamp, device_id, qw, qx, qy, qz, tx, ty, tz");
    let mut names = Vec::with_capacity(images.len());
    // Names, models and poses were checked above (`check_exportable`).
    for i in 0..images.len() {
        let id = images.ids.as_ref().map_or(i as u32 + 1, |ids| ids[i]) as usize;
        let name = images.name(i)?;
        let sensor = sensor_id(&meta.cameras, images.cameras[i] as usize);
        let pose = Pose::from_colmap_array(images.poses[i])
            .map_err(|e| unwritable(format!("image {id}"))(format!("pose: {e}")))?;
        writeln!(records, "{id}, {sensor}, {name}").ok();
        trajectory_row(&mut trajectories, id, &sensor, &pose);
        names.push(name);
    }
    let mut points = table(if colors.is_some() {
        "X, Y, Z, R, G, B"
    } else {
        "X, Y, Z"
    });
    for (p, &position) in positions.iter().enumerate() {
        let [x, y, z] = map.to_world(position);
        write!(points, "{x}, {y}, {z}").ok();
        if let Some(c) = &colors {
            let [r, g, b] = c[p];
            write!(points, ", {r}, {g}, {b}").ok();
        }
        points.push('\n');
    }

    let root = |relative: &str| dir.join(relative);
    let mut outputs = vec![
        root(super::SENSORS),
        root(super::RECORDS_CAMERA),
        root(super::TRAJECTORIES),
        root(super::POINTS3D),
    ];
    // Keypoints and observations, where the map keeps its observations' keypoints.
    let observed = match &visibility {
        Some(v) => v.keypoints.as_ref().map(|k| (v, k)),
        None => None,
    };
    let keypoints_dir = dir.join(super::KEYPOINTS_DIR).join(EXPORT_KEYPOINTS_TYPE);
    let kpt_path = |name: &str| keypoints_dir.join(format!("{name}.kpt"));
    let mut observations = String::new();
    let mut n_observations = 0;
    if let Some((vis, _)) = observed {
        outputs.push(keypoints_dir.join("keypoints.txt"));
        outputs.extend(names.iter().map(|n| kpt_path(n)));
        outputs.push(root(super::OBSERVATIONS));
        observations = table("point3d_id, keypoints_type, [image_path, feature_id]*");
        let tracks = Tracks::new(positions.len(), images.len(), |i| vis.points_of(i))
            .map_err(unwritable("the map's visibility".into()))?;
        for p in 0..positions.len() {
            let track = tracks.of(p);
            if track.is_empty() {
                continue;
            }
            write!(observations, "{p}, {EXPORT_KEYPOINTS_TYPE}").ok();
            for &(image, k) in track {
                write!(observations, ", {}, {k}", names[image as usize]).ok();
            }
            observations.push('\n');
            n_observations += track.len();
        }
    }
    check_outputs(&outputs, inputs, force)?;

    write_text(&root(super::SENSORS), &sensors)?;
    write_text(&root(super::RECORDS_CAMERA), &records)?;
    write_text(&root(super::TRAJECTORIES), &trajectories)?;
    write_text(&root(super::POINTS3D), &points)?;
    if let Some((vis, keypoints)) = observed {
        write_text(
            &keypoints_dir.join("keypoints.txt"),
            &format!(
                "{}{EXPORT_KEYPOINTS_TYPE}, float32, 2\n",
                table("name, dtype, dsize")
            ),
        )?;
        for (i, name) in names.iter().enumerate() {
            let start = vis.offsets[i] as usize;
            let xys = &keypoints[start..start + vis.points_of(i).len()];
            let bytes: Vec<u8> = xys
                .iter()
                .flat_map(|xy| xy.iter().flat_map(|v| v.to_le_bytes()))
                .collect();
            write_bytes(&kpt_path(name), &bytes)?;
        }
        write_text(&root(super::OBSERVATIONS), &observations)?;
    }
    Ok(KaptureExportSummary {
        cameras: meta.cameras.len(),
        images: images.len(),
        points: positions.len(),
        observations: n_observations,
    })
}

/// Every point's observations, `(image index, index among the image's entries)`, in one flat
/// array (CSR): 8 bytes an observation, no allocation per point.
struct Tracks {
    offsets: Vec<usize>,
    elements: Vec<(u32, u32)>,
}

impl Tracks {
    fn new<'v>(
        n_points: usize,
        n_images: usize,
        points_of: impl Fn(usize) -> &'v [u32],
    ) -> Result<Self, String> {
        let mut offsets = vec![0usize; n_points + 1];
        for i in 0..n_images {
            for &p in points_of(i) {
                let slot = offsets
                    .get_mut(p as usize + 1)
                    .ok_or_else(|| format!("names point {p} of {n_points}"))?;
                *slot += 1;
            }
        }
        for i in 1..offsets.len() {
            offsets[i] += offsets[i - 1];
        }
        let mut next = offsets.clone();
        let mut elements = vec![(0, 0); offsets[n_points]];
        for i in 0..n_images {
            for (k, &p) in points_of(i).iter().enumerate() {
                let at = &mut next[p as usize];
                elements[*at] = (i as u32, k as u32);
                *at += 1;
            }
        }
        Ok(Tracks { offsets, elements })
    }

    fn of(&self, p: usize) -> &[(u32, u32)] {
        &self.elements[self.offsets[p]..self.offsets[p + 1]]
    }
}

/// Writes localized queries as a kapture folder in `dir` (`sfpmap localize --format
/// kapture`): `sensors.txt` with one camera sensor per distinct query camera, a record per
/// query (timestamp = its index in the list), and a trajectory per localized query
/// (`cam_from_world`); a failed query has its record and no trajectory, and a comment
/// `# failed INDEX NAME: reason` in `trajectories.txt`. Outputs are checked as
/// [`export_kapture`] checks them. Returns the number of trajectories written.
#[cfg(feature = "localize")]
pub fn write_query_trajectories(
    dir: &Path,
    queries: &[(&str, &crate::geometry::Camera)],
    results: &[crate::localize::Localization],
    inputs: &[&Path],
    force: bool,
) -> Result<usize, KaptureError> {
    let mut sensors = table("sensor_id, name, sensor_type, [sensor_params]+");
    let mut records = table("timestamp, device_id, image_path");
    let mut trajectories = table("timestamp, device_id, qw, qx, qy, qz, tx, ty, tz");
    // Distinct cameras, by their model, size and parameters' bits.
    let mut distinct: Vec<(&str, [u64; 2], Vec<u64>)> = Vec::new();
    let mut localized = 0;
    for (i, ((name, camera), result)) in queries.iter().zip(results).enumerate() {
        check_name(|| format!("query {}", i + 1), name)?;
        let model = camera.model().name();
        let size = [u64::from(camera.width()), u64::from(camera.height())];
        let bits: Vec<u64> = camera.params().iter().map(|p| p.to_bits()).collect();
        let index = match distinct
            .iter()
            .position(|(m, s, b)| *m == model && *s == size && *b == bits)
        {
            Some(index) => index,
            None => {
                let id = format!("cam_{:05}", distinct.len() + 1);
                camera_row(&mut sensors, &id, model, size, camera.params()).map_err(unwritable(
                    format!(
                        "query {} {}'s camera",
                        i + 1,
                        crate::escape::quoted_name(name)
                    ),
                ))?;
                distinct.push((model, size, bits));
                distinct.len() - 1
            }
        };
        let sensor = format!("cam_{:05}", index + 1);
        writeln!(records, "{i}, {sensor}, {name}").ok();
        match result.pose() {
            Some(pose) => {
                trajectory_row(&mut trajectories, i, &sensor, pose);
                localized += 1;
            }
            None => {
                writeln!(
                    trajectories,
                    "# failed {i} {name}: {}",
                    crate::escape::escape_control_characters(&result.failure_line())
                )
                .ok();
            }
        }
    }
    let outputs = super::QUERY_FILES.map(|f| dir.join(f));
    check_outputs(&outputs, inputs, force)?;
    write_text(&outputs[0], &sensors)?;
    write_text(&outputs[1], &records)?;
    write_text(&outputs[2], &trajectories)?;
    Ok(localized)
}
