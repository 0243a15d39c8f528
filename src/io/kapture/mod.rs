//! kapture (NAVER's pivot format for SfM and sensor data, format 1.1) in and out.
//!
//! A kapture folder is text tables and raw binary arrays:
//!
//! | file | rows / contents |
//! |---|---|
//! | `sensors/sensors.txt` | `sensor_id, name, sensor_type, [sensor_params]+`; a camera's params are `MODEL, width, height, COLMAP params…` |
//! | `sensors/rigs.txt` | `rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz` (`sensor_from_rig`), optional |
//! | `sensors/trajectories.txt` | `timestamp, device_id, qw, qx, qy, qz, tx, ty, tz` (`device_from_world`, COLMAP's `cam_from_world` for a camera) |
//! | `sensors/records_camera.txt` | `timestamp, device_id, image_path` |
//! | `reconstruction/points3d.txt` | `X, Y, Z[, R, G, B]`; a point's id is its row (from 0) |
//! | `reconstruction/observations.txt` | `point3d_id, keypoints_type, [image_path, feature_id]*` |
//! | `reconstruction/keypoints/TYPE/keypoints.txt` | `name, dtype, dsize`; `TYPE/IMAGE.kpt` holds `dsize` values of `dtype` a keypoint, little-endian, no header |
//! | `reconstruction/descriptors/TYPE/descriptors.txt` | `name, dtype, dsize, keypoints_type, metric_type`; `TYPE/IMAGE.desc` as `.kpt` |
//!
//! Every text file starts with `# kapture format: 1.1`; lines starting with `#` and blank lines
//! are skipped, fields are split at commas and trimmed. That is kapture's own reader
//! (`kapture.io.csv.table_from_file`), which has no quoting: a CSV crate would read a quote
//! character in a file name as syntax, so the lines are split here, as kapture splits them.
//!
//! [`read_kapture`] reads a folder into a [`Reconstruction`](crate::colmap::Reconstruction)
//! (cameras from camera sensors, images from camera records that have a pose, points with
//! their tracks from `points3d.txt` and `observations.txt`) and hands out each image's
//! keypoints and descriptors on demand ([`Kapture::keypoints`], [`Kapture::descriptors`]), read
//! one file at a time and never sized by more than the file's length.
//!
//! [`export_kapture`] writes a map as kapture; [`write_query_trajectories`] writes localized
//! queries (`sfpmap localize --format kapture`). Every file goes through the one atomic
//! writer ([`crate::output`]).

mod error;
mod read;
mod write;

pub use error::KaptureError;
pub use read::{
    read_kapture, DescriptorsInfo, Kapture, KaptureDtype, KaptureOptions, Keypoints, KeypointsInfo,
};
#[cfg(feature = "localize")]
pub use write::write_query_trajectories;
pub use write::{check_exportable, export_kapture, KaptureExportSummary, EXPORT_KEYPOINTS_TYPE};

/// The first line of every kapture text file this module writes (format 1.1).
pub const KAPTURE_HEADER: &str = "# kapture format: 1.1";

/// `sensors/sensors.txt`, relative to the kapture folder.
pub const SENSORS: &str = "sensors/sensors.txt";
/// `sensors/rigs.txt`.
pub const RIGS: &str = "sensors/rigs.txt";
/// `sensors/trajectories.txt`.
pub const TRAJECTORIES: &str = "sensors/trajectories.txt";
/// `sensors/records_camera.txt`.
pub const RECORDS_CAMERA: &str = "sensors/records_camera.txt";
/// `reconstruction/points3d.txt`.
pub const POINTS3D: &str = "reconstruction/points3d.txt";
/// `reconstruction/observations.txt`.
pub const OBSERVATIONS: &str = "reconstruction/observations.txt";
/// The tables of the kapture folder `dir` that `convert --kapture` reads (the output policy's
/// inputs besides the feature files).
pub fn tables(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    [
        SENSORS,
        RIGS,
        TRAJECTORIES,
        RECORDS_CAMERA,
        POINTS3D,
        OBSERVATIONS,
    ]
    .iter()
    .map(|f| dir.join(f))
    .collect()
}

/// `reconstruction/keypoints` (one folder per keypoints type).
pub const KEYPOINTS_DIR: &str = "reconstruction/keypoints";
/// `reconstruction/descriptors` (one folder per descriptors type).
pub const DESCRIPTORS_DIR: &str = "reconstruction/descriptors";

/// The camera models kapture 1.1 knows (`kapture.CameraType`, less `UNKNOWN_CAMERA`, which
/// has no intrinsics): COLMAP's names and parameters.
pub(crate) const KAPTURE_CAMERA_MODELS: [&str; 11] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
];

/// The fields of a kapture table line: split at commas and trimmed, as kapture does.
fn fields(line: &str) -> Vec<&str> {
    line.split(',').map(str::trim).collect()
}

/// The files [`write_query_trajectories`] writes, relative to its folder.
#[cfg(feature = "localize")]
pub const QUERY_FILES: [&str; 3] = [SENSORS, RECORDS_CAMERA, TRAJECTORIES];

/// Why a name cannot be a kapture field or a relative path under a kapture folder: a comma
/// (the field separator), a control character (a line break ends the row), blanks at either
/// end (kapture trims them away), an absolute path or a `..` part (a `.kpt` path would leave
/// its folder). `None` if it can be.
pub fn name_problem(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("is empty")
    } else if name.contains(',') {
        Some("holds a comma")
    } else if name.chars().any(char::is_control) {
        Some("holds a control character")
    } else if name.trim() != name {
        Some("starts or ends with a blank")
    } else if name.starts_with('/') || name.contains('\\') {
        Some("is not a relative path with / separators")
    } else if name
        .split('/')
        .any(|part| part == ".." || part == "." || part.is_empty())
    {
        Some("has an empty, `.` or `..` path part")
    } else {
        None
    }
}
