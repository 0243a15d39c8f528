//! Reading a kapture folder: the tables into a [`Reconstruction`], features on demand.

use super::{fields, name_problem, KaptureError};
use crate::colmap::{Camera, DescriptorValues, Image, Point2D, Reconstruction, TrackElement};
use crate::geometry::{CameraModel, Pose};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::io::BufRead;
use std::path::{Path, PathBuf};

/// What [`read_kapture`] reads besides the tables every folder has.
#[derive(Debug, Clone, Default)]
pub struct KaptureOptions {
    /// The keypoints type (a folder of `reconstruction/keypoints/`) whose keypoints the
    /// images' 2D points and the observations are; `None`: the only one there (several are
    /// an error naming them).
    pub keypoints_type: Option<String>,
    /// The descriptors type (a folder of `reconstruction/descriptors/`); `None`: the only one
    /// whose `keypoints_type` is the keypoints type chosen.
    pub descriptors_type: Option<String>,
}

/// A value type of a `.kpt` or `.desc` file (`dtype` in `keypoints.txt`, `descriptors.txt`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum KaptureDtype {
    /// `uint8` (SIFT's descriptors).
    U8,
    /// `float32`.
    F32,
    /// `float64` (read as f32).
    F64,
}

impl KaptureDtype {
    /// The numpy name kapture writes.
    pub fn name(self) -> &'static str {
        match self {
            KaptureDtype::U8 => "uint8",
            KaptureDtype::F32 => "float32",
            KaptureDtype::F64 => "float64",
        }
    }

    fn size(self) -> u64 {
        match self {
            KaptureDtype::U8 => 1,
            KaptureDtype::F32 => 4,
            KaptureDtype::F64 => 8,
        }
    }

    fn parse(s: &str) -> Option<Self> {
        // numpy's names, `np.` prefixed or not; Python's `float` is float64.
        match s.strip_prefix("np.").unwrap_or(s) {
            "uint8" => Some(KaptureDtype::U8),
            "float32" => Some(KaptureDtype::F32),
            "float64" | "float" => Some(KaptureDtype::F64),
            _ => None,
        }
    }
}

/// `reconstruction/keypoints/TYPE/keypoints.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct KeypointsInfo {
    /// The type (the folder's name).
    pub name: String,
    /// The value type.
    pub dtype: KaptureDtype,
    /// Values a keypoint: x, y, then what the extractor stores.
    pub dsize: usize,
}

/// `reconstruction/descriptors/TYPE/descriptors.txt`.
#[derive(Debug, Clone, PartialEq)]
pub struct DescriptorsInfo {
    /// The type (the folder's name).
    pub name: String,
    /// The value type.
    pub dtype: KaptureDtype,
    /// Dimensions of a descriptor.
    pub dsize: usize,
    /// The keypoints type they describe.
    pub keypoints_type: String,
    /// The metric kapture records (`L2`, …).
    pub metric_type: String,
}

/// One image's keypoints, `dsize` values each, as f32.
#[derive(Debug, Clone, PartialEq)]
pub struct Keypoints {
    /// Values a keypoint.
    pub dsize: usize,
    /// Row-major values.
    pub values: Vec<f32>,
}

impl Keypoints {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.values.len() / self.dsize.max(1)
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Position of keypoint `i` (kapture's pixels as the extractor wrote them; COLMAP's
    /// convention for keypoints imported from COLMAP).
    pub fn xy(&self, i: usize) -> Option<[f32; 2]> {
        let row = self.values.get(i * self.dsize..(i + 1) * self.dsize)?;
        Some([row[0], row[1]])
    }

    /// Scale of keypoint `i` in pixels, where the layout has one: 3 values (`x, y, scale`,
    /// kapture-localization's R2D2 and D2-Net), 4 (COLMAP's `x, y, scale, orientation`), 6
    /// (COLMAP's affine shape, COLMAP's own scale rule). Other layouts store no scale: `None`.
    pub fn scale(&self, i: usize) -> Option<f32> {
        let row = self.values.get(i * self.dsize..(i + 1) * self.dsize)?;
        match self.dsize {
            3 | 4 => Some(row[2]),
            6 => Some(
                crate::colmap::Keypoint {
                    x: row[0],
                    y: row[1],
                    a11: row[2],
                    a12: row[3],
                    a21: row[4],
                    a22: row[5],
                }
                .scale(),
            ),
            _ => None,
        }
    }
}

/// A kapture folder read: its model and where each image's features are.
#[derive(Debug, Clone)]
pub struct Kapture {
    /// The folder.
    pub root: PathBuf,
    /// Cameras (ids from 1 in `sensors.txt` order), images with a pose (ids from 1 in
    /// `records_camera.txt` order; 2D points = the chosen type's keypoints), points (id =
    /// kapture's `point3d_id`, its row in `points3d.txt`) with their observations as tracks.
    pub reconstruction: Reconstruction,
    /// The keypoints type read, if the folder has keypoints.
    pub keypoints: Option<KeypointsInfo>,
    /// The descriptors type, if the folder has descriptors of those keypoints.
    pub descriptors: Option<DescriptorsInfo>,
    /// Camera records without a pose (neither in `trajectories.txt` nor through a rig): not
    /// registered.
    pub records_without_pose: usize,
    /// Observations of images that are not registered (no record or no pose): left out.
    pub observations_skipped: usize,
    /// The text files read, for provenance.
    pub files: Vec<PathBuf>,
}

/// A kapture pose field set `qw qx qy qz tx ty tz`; `Ok(None)` if it is partial (kapture
/// leaves the rotation or the translation empty where it is unknown).
fn parse_pose(f: &[&str]) -> Result<Option<Pose>, String> {
    if f.iter().any(|v| v.is_empty()) {
        return Ok(None);
    }
    let mut v = [0.0; 7];
    for (v, t) in v.iter_mut().zip(f) {
        *v = parse_number(t)?;
    }
    Pose::from_colmap_array(v)
        .map(Some)
        .map_err(|e| format!("pose: {e}"))
}

fn parse_number(t: &str) -> Result<f64, String> {
    t.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| format!("{} is not a finite number", crate::escape::quoted_name(t)))
}

fn parse_timestamp(t: &str) -> Result<i64, String> {
    t.parse().map_err(|_| {
        format!(
            "timestamp {} is not an integer",
            crate::escape::quoted_name(t)
        )
    })
}

/// Calls `row` with each data line's number and fields; a missing file is `Ok(false)`, or
/// [`KaptureError::Missing`] if `needed_for` says it is needed. Read line by line: an
/// observations file can be larger than memory would like twice.
fn for_each_row(
    path: &Path,
    needed_for: Option<&'static str>,
    mut row: impl FnMut(usize, &[&str]) -> Result<(), KaptureError>,
) -> Result<bool, KaptureError> {
    if std::fs::symlink_metadata(path).is_err() {
        return match needed_for {
            Some(needed_for) => Err(KaptureError::Missing {
                path: path.to_path_buf(),
                needed_for,
            }),
            None => Ok(false),
        };
    }
    let read_error = |reason: String| KaptureError::Read {
        path: path.to_path_buf(),
        reason,
    };
    let file = crate::input::open_regular(path).map_err(|e| read_error(e.to_string()))?;
    let mut reader = std::io::BufReader::new(file);
    let mut buf = Vec::new();
    let mut number = 0;
    loop {
        buf.clear();
        let n = reader
            .read_until(b'\n', &mut buf)
            .map_err(|e| read_error(e.to_string()))?;
        if n == 0 {
            return Ok(true);
        }
        number += 1;
        let line = std::str::from_utf8(&buf).map_err(|_| KaptureError::Line {
            path: path.to_path_buf(),
            line: number,
            message: "not UTF-8 text".into(),
        })?;
        let line = line.trim_end_matches(['\n', '\r']);
        if number == 1 {
            check_version(path, line)?;
        }
        if line.trim().is_empty() || line.starts_with('#') {
            continue;
        }
        row(number, &fields(line))?;
    }
}

/// The `# kapture format: X.Y` first line, if there: 1.0 and 1.1 are read (their tables are
/// the same for what is read here).
fn check_version(path: &Path, first: &str) -> Result<(), KaptureError> {
    let Some(version) = first.strip_prefix("# kapture format:") else {
        return Ok(());
    };
    let version = version.trim();
    if version == "1.0" || version == "1.1" {
        Ok(())
    } else {
        Err(KaptureError::Version {
            path: path.to_path_buf(),
            found: version.to_string(),
        })
    }
}

fn line_error(path: &Path, line: usize) -> impl Fn(String) -> KaptureError + '_ {
    move |message| KaptureError::Line {
        path: path.to_path_buf(),
        line,
        message,
    }
}

/// A camera sensor's intrinsics, or why it has none.
#[derive(Debug)]
struct CameraSensor {
    /// `sensors.txt` line.
    line: usize,
    /// The model's id in the reconstruction (from 1); `None` for `UNKNOWN_CAMERA`.
    camera_id: Option<u32>,
}

/// `sensors.txt`: every sensor id (so trajectories can be checked), and the cameras.
struct Sensors {
    /// Sensor id → its type (`camera`, `gnss`, …).
    types: HashMap<String, String>,
    cameras: HashMap<String, CameraSensor>,
    models: Vec<Camera>,
}

fn read_sensors(path: &Path) -> Result<Sensors, KaptureError> {
    let mut s = Sensors {
        types: HashMap::new(),
        cameras: HashMap::new(),
        models: Vec::new(),
    };
    for_each_row(path, Some("the cameras"), |line, f| {
        let err = line_error(path, line);
        if f.len() < 3 {
            return Err(err(format!(
                "expected `sensor_id, name, sensor_type, [sensor_params]+`, found {} fields",
                f.len()
            )));
        }
        let id = f[0].to_string();
        if s.types.insert(id.clone(), f[2].to_string()).is_some() {
            return Err(err(format!(
                "sensor {} is listed twice",
                crate::escape::quoted_name(&id)
            )));
        }
        if f[2] != "camera" {
            return Ok(());
        }
        let params = &f[3..];
        let Some(&model_name) = params.first() else {
            return Err(err("a camera needs `MODEL, width, height, params…`".into()));
        };
        if model_name == "UNKNOWN_CAMERA" {
            s.cameras.insert(
                id,
                CameraSensor {
                    line,
                    camera_id: None,
                },
            );
            return Ok(());
        }
        let model = CameraModel::from_name(model_name)
            .filter(|m| super::KAPTURE_CAMERA_MODELS.contains(&m.name()))
            .ok_or_else(|| {
                err(format!(
                    "camera model {} is not one kapture 1.1 knows",
                    crate::escape::quoted_name(model_name)
                ))
            })?;
        let values = params[1..]
            .iter()
            .map(|t| parse_number(t))
            .collect::<Result<Vec<f64>, _>>()
            .map_err(&err)?;
        if values.len() != 2 + model.num_params() {
            return Err(err(format!(
                "{model_name} needs width, height and {} parameters ({}), found {} values",
                model.num_params(),
                model.param_names(),
                values.len()
            )));
        }
        let size = |v: f64, what: &str| -> Result<u64, String> {
            (v >= 1.0 && v.fract() == 0.0 && v <= f64::from(u32::MAX))
                .then_some(v as u64)
                .ok_or_else(|| format!("{what} {v} is not a whole number of pixels"))
        };
        let camera_id = s.models.len() as u32 + 1;
        s.models.push(Camera {
            id: camera_id,
            model,
            width: size(values[0], "width").map_err(&err)?,
            height: size(values[1], "height").map_err(&err)?,
            params: values[2..].to_vec(),
        });
        s.cameras.insert(
            id,
            CameraSensor {
                line,
                camera_id: Some(camera_id),
            },
        );
        Ok(())
    })?;
    Ok(s)
}

/// `rigs.txt`: sensor id → rig id → (the row's order, `sensor_from_rig`) for each rig
/// holding it. Looked up by hash, never scanned: a folder may list many rigs.
type Rigs = HashMap<String, HashMap<String, (usize, Pose)>>;

fn read_rigs(path: &Path, sensors: &Sensors) -> Result<(Rigs, HashSet<String>), KaptureError> {
    let mut rigs = Rigs::new();
    let mut rig_ids = HashSet::new();
    for_each_row(path, None, |line, f| {
        let err = line_error(path, line);
        if f.len() != 9 {
            return Err(err(format!(
                "expected `rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz`, found {} fields",
                f.len()
            )));
        }
        if sensors.types.contains_key(f[0]) {
            return Err(err(format!(
                "rig id {} is also a sensor id",
                crate::escape::quoted_name(f[0])
            )));
        }
        if let Some(pose) = parse_pose(&f[2..]).map_err(&err)? {
            let of_sensor = rigs.entry(f[1].to_string()).or_default();
            let order = of_sensor.len();
            // The first row of a rig and sensor counts, as the list this was kept in did.
            of_sensor.entry(f[0].to_string()).or_insert((order, pose));
        }
        rig_ids.insert(f[0].to_string());
        Ok(())
    })?;
    Ok((rigs, rig_ids))
}

/// `trajectories.txt`: `(timestamp, device) → device_from_world`, complete poses only.
fn read_trajectories(
    path: &Path,
    sensors: &Sensors,
    rig_ids: &HashSet<String>,
) -> Result<HashMap<(i64, String), Pose>, KaptureError> {
    let mut poses = HashMap::new();
    for_each_row(path, Some("the image poses"), |line, f| {
        let err = line_error(path, line);
        if f.len() != 9 {
            return Err(err(format!(
                "expected `timestamp, device_id, qw, qx, qy, qz, tx, ty, tz`, found {} fields",
                f.len()
            )));
        }
        let timestamp = parse_timestamp(f[0]).map_err(&err)?;
        if !sensors.types.contains_key(f[1]) && !rig_ids.contains(f[1]) {
            return Err(KaptureError::UnknownDevice {
                path: path.to_path_buf(),
                line,
                device: f[1].to_string(),
            });
        }
        if let Some(pose) = parse_pose(&f[2..]).map_err(&err)? {
            if poses.insert((timestamp, f[1].to_string()), pose).is_some() {
                return Err(err(format!(
                    "a second pose for timestamp {timestamp} and device {}",
                    crate::escape::quoted_name(f[1])
                )));
            }
        }
        Ok(())
    })?;
    Ok(poses)
}

/// The keypoints and descriptors types a folder holds (`keypoints.txt` / `descriptors.txt`
/// beside them), sorted.
fn feature_types(dir: &Path, config: &str) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    let mut types: Vec<String> = entries
        .flatten()
        .filter(|e| e.path().join(config).is_file())
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .collect();
    types.sort();
    types
}

/// The one data line of a `keypoints.txt` or `descriptors.txt`.
fn read_config(
    path: &Path,
    needed_for: &'static str,
) -> Result<(usize, Vec<String>), KaptureError> {
    let mut found = None;
    for_each_row(path, Some(needed_for), |line, f| {
        if found.is_none() {
            found = Some((line, f.iter().map(|s| s.to_string()).collect()));
        }
        Ok(())
    })?;
    found.ok_or_else(|| KaptureError::Line {
        path: path.to_path_buf(),
        line: 1,
        message: "no data line".into(),
    })
}

fn parse_dtype_dsize(
    path: &Path,
    line: usize,
    dtype: &str,
    dsize: &str,
    allowed: &[KaptureDtype],
    min_dsize: usize,
) -> Result<(KaptureDtype, usize), KaptureError> {
    let err = line_error(path, line);
    let dtype = KaptureDtype::parse(dtype)
        .filter(|d| allowed.contains(d))
        .ok_or_else(|| {
            let names: Vec<_> = allowed.iter().map(|d| d.name()).collect();
            err(format!(
                "dtype {} is not one of {}",
                crate::escape::quoted_name(dtype),
                names.join(", ")
            ))
        })?;
    let dsize = dsize
        .parse::<usize>()
        .ok()
        .filter(|&d| d >= min_dsize && d <= 1 << 16)
        .ok_or_else(|| {
            err(format!(
                "dsize {} is not a whole number from {min_dsize} to 65536",
                crate::escape::quoted_name(dsize)
            ))
        })?;
    Ok((dtype, dsize))
}

fn read_keypoints_info(root: &Path, name: &str) -> Result<KeypointsInfo, KaptureError> {
    let path = root
        .join(super::KEYPOINTS_DIR)
        .join(name)
        .join("keypoints.txt");
    let (line, f) = read_config(&path, "the keypoints' type")?;
    if f.len() != 3 {
        return Err(line_error(&path, line)(format!(
            "expected `name, dtype, dsize`, found {} fields",
            f.len()
        )));
    }
    let allowed = [KaptureDtype::F32, KaptureDtype::F64];
    let (dtype, dsize) = parse_dtype_dsize(&path, line, &f[1], &f[2], &allowed, 2)?;
    Ok(KeypointsInfo {
        name: name.to_string(),
        dtype,
        dsize,
    })
}

fn read_descriptors_info(root: &Path, name: &str) -> Result<DescriptorsInfo, KaptureError> {
    let path = root
        .join(super::DESCRIPTORS_DIR)
        .join(name)
        .join("descriptors.txt");
    let (line, f) = read_config(&path, "the descriptors' type")?;
    if f.len() != 5 {
        return Err(line_error(&path, line)(format!(
            "expected `name, dtype, dsize, keypoints_type, metric_type`, found {} fields",
            f.len()
        )));
    }
    let allowed = [KaptureDtype::U8, KaptureDtype::F32, KaptureDtype::F64];
    let (dtype, dsize) = parse_dtype_dsize(&path, line, &f[1], &f[2], &allowed, 1)?;
    Ok(DescriptorsInfo {
        name: name.to_string(),
        dtype,
        dsize,
        keypoints_type: f[3].clone(),
        metric_type: f[4].clone(),
    })
}

/// The keypoints type to read, by `options` or the folder's only one.
fn choose_keypoints(
    root: &Path,
    options: &KaptureOptions,
) -> Result<Option<KeypointsInfo>, KaptureError> {
    let name = match &options.keypoints_type {
        Some(name) => Some(name.clone()),
        None => {
            let dir = root.join(super::KEYPOINTS_DIR);
            let types = feature_types(&dir, "keypoints.txt");
            if types.len() > 1 {
                return Err(KaptureError::Ambiguous {
                    path: dir,
                    what: "keypoints",
                    found: types,
                });
            }
            types.into_iter().next()
        }
    };
    name.map(|name| {
        checked_type_name(root, &name)?;
        read_keypoints_info(root, &name)
    })
    .transpose()
}

fn choose_descriptors(
    root: &Path,
    options: &KaptureOptions,
    keypoints: &KeypointsInfo,
) -> Result<Option<DescriptorsInfo>, KaptureError> {
    if let Some(name) = &options.descriptors_type {
        checked_type_name(root, name)?;
        return read_descriptors_info(root, name).map(Some);
    }
    let dir = root.join(super::DESCRIPTORS_DIR);
    let mut of_keypoints = Vec::new();
    for name in feature_types(&dir, "descriptors.txt") {
        let info = read_descriptors_info(root, &name)?;
        if info.keypoints_type == keypoints.name {
            of_keypoints.push(info);
        }
    }
    if of_keypoints.len() > 1 {
        return Err(KaptureError::Ambiguous {
            path: dir,
            what: "descriptors",
            found: of_keypoints.into_iter().map(|d| d.name).collect(),
        });
    }
    Ok(of_keypoints.pop())
}

/// A feature type name is a folder name: nothing that leaves `reconstruction/…/`.
fn checked_type_name(root: &Path, name: &str) -> Result<(), KaptureError> {
    let problem = name_problem(name).or(name.contains('/').then_some("is not a folder name"));
    match problem {
        Some(problem) => Err(KaptureError::Read {
            path: root.to_path_buf(),
            reason: format!(
                "feature type {} {problem}",
                crate::escape::quoted_name(name)
            ),
        }),
        None => Ok(()),
    }
}

/// Reads the kapture folder `root` (see the [module docs](super) for what is read).
pub fn read_kapture(root: &Path, options: &KaptureOptions) -> Result<Kapture, KaptureError> {
    let sensors_path = root.join(super::SENSORS);
    let rigs_path = root.join(super::RIGS);
    let trajectories_path = root.join(super::TRAJECTORIES);
    let records_path = root.join(super::RECORDS_CAMERA);
    let points_path = root.join(super::POINTS3D);
    let observations_path = root.join(super::OBSERVATIONS);
    let mut files = Vec::new();

    let sensors = read_sensors(&sensors_path)?;
    files.push(sensors_path.clone());
    let (rigs, rig_ids) = read_rigs(&rigs_path, &sensors)?;
    if rigs_path.exists() {
        files.push(rigs_path.clone());
    }
    let trajectories = read_trajectories(&trajectories_path, &sensors, &rig_ids)?;
    files.push(trajectories_path.clone());

    let keypoints = choose_keypoints(root, options)?;
    let descriptors = match &keypoints {
        Some(k) => choose_descriptors(root, options, k)?,
        None => None,
    };
    let kapture = Kapture {
        root: root.to_path_buf(),
        reconstruction: Reconstruction::builder().build()?,
        keypoints,
        descriptors,
        records_without_pose: 0,
        observations_skipped: 0,
        files,
    };
    kapture.read_model(
        &sensors,
        &rigs,
        &trajectories,
        [&records_path, &points_path, &observations_path],
    )
}

impl Kapture {
    /// Images from the camera records with a pose, then the points and their tracks.
    fn read_model(
        mut self,
        sensors: &Sensors,
        rigs: &Rigs,
        trajectories: &HashMap<(i64, String), Pose>,
        [records_path, points_path, observations_path]: [&PathBuf; 3],
    ) -> Result<Kapture, KaptureError> {
        let mut images: Vec<Image> = Vec::new();
        let mut by_name: HashMap<String, usize> = HashMap::new();
        // The devices with a pose at each timestamp: a record of a rig's sensor finds its
        // rig's pose among them (a few), not by trying every rig that holds the sensor.
        let mut posed_at: HashMap<i64, Vec<&str>> = HashMap::new();
        for (timestamp, device) in trajectories.keys() {
            posed_at.entry(*timestamp).or_default().push(device);
        }
        let mut recorded: HashMap<String, usize> = HashMap::new();
        for_each_row(records_path, Some("the images"), |line, f| {
            let err = line_error(records_path, line);
            if f.len() != 3 {
                return Err(err(format!(
                    "expected `timestamp, device_id, image_path`, found {} fields",
                    f.len()
                )));
            }
            let timestamp = parse_timestamp(f[0]).map_err(&err)?;
            let (device, name) = (f[1], f[2]);
            let Some(sensor_type) = sensors.types.get(device) else {
                return Err(KaptureError::UnknownDevice {
                    path: records_path.clone(),
                    line,
                    device: device.to_string(),
                });
            };
            let Some(camera) = sensors.cameras.get(device) else {
                return Err(err(format!(
                    "device {} is a {sensor_type}, not a camera",
                    crate::escape::quoted_name(device)
                )));
            };
            if let Some(problem) = name_problem(name) {
                return Err(err(format!(
                    "image path {} {problem}",
                    crate::escape::quoted_name(name)
                )));
            }
            if let Some(first) = recorded.insert(name.to_string(), line) {
                return Err(err(format!(
                    "image path {} was recorded on line {first} already",
                    crate::escape::quoted_name(name)
                )));
            }
            let pose = trajectories
                .get(&(timestamp, device.to_string()))
                .copied()
                .or_else(|| {
                    let of_sensor = rigs.get(device)?;
                    // Of the sensor's rigs posed then, the first in rigs.txt.
                    let (_, sensor_from_rig, rig) = posed_at
                        .get(&timestamp)?
                        .iter()
                        .filter_map(|rig| of_sensor.get(*rig).map(|(o, p)| (*o, p, *rig)))
                        .min_by_key(|(order, _, _)| *order)?;
                    let rig_from_world = trajectories.get(&(timestamp, rig.to_string()))?;
                    Some(sensor_from_rig.compose(rig_from_world))
                });
            let Some(pose) = pose else {
                self.records_without_pose += 1;
                return Ok(());
            };
            let Some(camera_id) = camera.camera_id else {
                return Err(err(format!(
                    "camera {} (sensors.txt line {}) is UNKNOWN_CAMERA: a map needs its intrinsics",
                    crate::escape::quoted_name(device),
                    camera.line
                )));
            };
            by_name.insert(name.to_string(), images.len());
            images.push(Image {
                id: images.len() as u32 + 1,
                name: name.to_string(),
                camera_id,
                cam_from_world: pose,
                points2d: Vec::new(),
            });
            Ok(())
        })?;
        self.files.push(records_path.clone());

        if self.keypoints.is_some() {
            for image in &mut images {
                if let Some(k) = self.keypoints(&image.name)? {
                    image.points2d = (0..k.len())
                        .map(|i| {
                            let [x, y] = k.xy(i).unwrap_or([0.0; 2]);
                            Point2D {
                                xy: [f64::from(x), f64::from(y)],
                                point3d_id: None,
                            }
                        })
                        .collect();
                }
            }
        }

        let mut points: Vec<([f64; 3], [u8; 3])> = Vec::new();
        if for_each_row(points_path, None, |line, f| {
            let err = line_error(points_path, line);
            if f.len() != 3 && f.len() != 6 {
                return Err(err(format!(
                    "expected `X, Y, Z` or `X, Y, Z, R, G, B`, found {} fields",
                    f.len()
                )));
            }
            let v = f
                .iter()
                .map(|t| parse_number(t))
                .collect::<Result<Vec<f64>, _>>()
                .map_err(&err)?;
            let rgb = if v.len() == 6 {
                [v[3], v[4], v[5]].map(|c| c.round().clamp(0.0, 255.0) as u8)
            } else {
                [128; 3]
            };
            points.push(([v[0], v[1], v[2]], rgb));
            Ok(())
        })? {
            self.files.push(points_path.clone());
        }

        let tracks =
            self.read_observations(observations_path, &mut images, &by_name, points.len())?;

        let mut builder = Reconstruction::builder().paths(
            &self.root.join(super::SENSORS),
            records_path,
            points_path,
        );
        for camera in &sensors.models {
            builder.add_camera(camera.clone());
        }
        for image in images {
            builder.add_image(image);
        }
        builder.reserve_points3d(points.len(), tracks.values().map(Vec::len).sum());
        for (id, (xyz, rgb)) in points.into_iter().enumerate() {
            let track = tracks.get(&(id as u64)).map_or(&[][..], Vec::as_slice);
            builder.add_point3d(id as u64, xyz, rgb, 0.0, track)?;
        }
        self.reconstruction = builder.build()?;
        Ok(self)
    }

    /// `observations.txt` of the chosen keypoints type: each point's track, and each observed
    /// 2D point's `point3d_id` set.
    fn read_observations(
        &mut self,
        path: &Path,
        images: &mut [Image],
        by_name: &HashMap<String, usize>,
        n_points: usize,
    ) -> Result<BTreeMap<u64, Vec<TrackElement>>, KaptureError> {
        let mut tracks: BTreeMap<u64, Vec<TrackElement>> = BTreeMap::new();
        let keypoints_type = self.keypoints.as_ref().map(|k| k.name.clone());
        let kpt_path = |root: &Path, image: &str| {
            keypoints_type
                .as_deref()
                .map(|t| features_path(root, super::KEYPOINTS_DIR, t, image, "kpt"))
        };
        let mut skipped = 0;
        let root = self.root.clone();
        if for_each_row(path, None, |line, f| {
            let err = line_error(path, line);
            if f.len() < 2 || f.len() % 2 != 0 {
                return Err(err(format!(
                    "expected `point3d_id, keypoints_type, [image_path, feature_id]*`, found {} fields",
                    f.len()
                )));
            }
            if Some(f[1]) != keypoints_type.as_deref() {
                return Ok(());
            }
            let point = f[0]
                .parse::<u64>()
                .ok()
                .filter(|&p| p < n_points as u64)
                .ok_or_else(|| {
                    err(format!(
                        "point3d_id {} is not a row of reconstruction/points3d.txt ({n_points} points)",
                        crate::escape::quoted_name(f[0])
                    ))
                })?;
            for pair in f[2..].chunks_exact(2) {
                let Some(&i) = by_name.get(pair[0]) else {
                    skipped += 1;
                    continue;
                };
                let image = &mut images[i];
                let keypoint = pair[1].parse::<u32>().map_err(|_| {
                    err(format!(
                        "feature_id {} is not a keypoint index",
                        crate::escape::quoted_name(pair[1])
                    ))
                })?;
                let n = image.points2d.len();
                let Some(p2d) = image.points2d.get_mut(keypoint as usize) else {
                    let file = kpt_path(&root, &image.name).unwrap_or_default();
                    return Err(err(format!(
                        "keypoint {keypoint} of image {} is not in {} ({n} keypoints)",
                        crate::escape::quoted_name(&image.name),
                        crate::escape::path(&file)
                    )));
                };
                if let Some(other) = p2d.point3d_id {
                    return Err(err(format!(
                        "keypoint {keypoint} of image {} already observes point {other}",
                        crate::escape::quoted_name(&image.name)
                    )));
                }
                p2d.point3d_id = Some(point);
                tracks.entry(point).or_default().push(TrackElement {
                    image_id: image.id,
                    point2d_idx: keypoint,
                });
            }
            Ok(())
        })? {
            self.files.push(path.to_path_buf());
        }
        self.observations_skipped = skipped;
        Ok(tracks)
    }

    /// The `.kpt` file of `image`, `None` without a keypoints type.
    pub fn keypoints_path(&self, image: &str) -> Option<PathBuf> {
        let k = self.keypoints.as_ref()?;
        Some(features_path(
            &self.root,
            super::KEYPOINTS_DIR,
            &k.name,
            image,
            "kpt",
        ))
    }

    /// The `.desc` file of `image`, `None` without a descriptors type.
    pub fn descriptors_path(&self, image: &str) -> Option<PathBuf> {
        let d = self.descriptors.as_ref()?;
        Some(features_path(
            &self.root,
            super::DESCRIPTORS_DIR,
            &d.name,
            image,
            "desc",
        ))
    }

    /// `image`'s keypoints; `Ok(None)` without a keypoints type or a `.kpt` file for it.
    pub fn keypoints(&self, image: &str) -> Result<Option<Keypoints>, KaptureError> {
        let (Some(k), Some(path)) = (&self.keypoints, self.keypoints_path(image)) else {
            return Ok(None);
        };
        let Some(bytes) = read_records(&path, k.dtype, k.dsize)? else {
            return Ok(None);
        };
        Ok(Some(Keypoints {
            dsize: k.dsize,
            values: widen(&bytes, k.dtype),
        }))
    }

    /// `image`'s descriptors (one row per keypoint, [`DescriptorsInfo::dsize`] values each);
    /// `Ok(None)` without a descriptors type or a `.desc` file for it.
    pub fn descriptors(&self, image: &str) -> Result<Option<DescriptorValues>, KaptureError> {
        let (Some(d), Some(path)) = (&self.descriptors, self.descriptors_path(image)) else {
            return Ok(None);
        };
        let Some(bytes) = read_records(&path, d.dtype, d.dsize)? else {
            return Ok(None);
        };
        Ok(Some(match d.dtype {
            KaptureDtype::U8 => DescriptorValues::U8(bytes),
            _ => DescriptorValues::F32(widen(&bytes, d.dtype)),
        }))
    }
}

/// `ROOT/DIR/TYPE/IMAGE.EXT`, the image path's `/` parts as folders.
fn features_path(root: &Path, dir: &str, type_name: &str, image: &str, ext: &str) -> PathBuf {
    root.join(dir)
        .join(type_name)
        .join(format!("{image}.{ext}"))
}

/// A `.kpt` / `.desc` file's bytes, `None` if there is none; its length must be a whole
/// number of `dsize × dtype` records. The allocation is the file's length, never a count
/// from a header (the files have none).
fn read_records(
    path: &Path,
    dtype: KaptureDtype,
    dsize: usize,
) -> Result<Option<Vec<u8>>, KaptureError> {
    if std::fs::symlink_metadata(path).is_err() {
        return Ok(None);
    }
    let bytes = crate::input::read_regular(path).map_err(|e| KaptureError::Read {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    let record = dtype.size() * dsize as u64;
    if bytes.len() as u64 % record != 0 {
        return Err(KaptureError::Truncated {
            path: path.to_path_buf(),
            len: bytes.len() as u64,
            record,
        });
    }
    Ok(Some(bytes))
}

/// Little-endian f32 / f64 values as f32 (what kapture's numpy writes on every platform it
/// runs on).
fn widen(bytes: &[u8], dtype: KaptureDtype) -> Vec<f32> {
    match dtype {
        KaptureDtype::U8 => bytes.iter().map(|&b| f32::from(b)).collect(),
        KaptureDtype::F32 => bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect(),
        KaptureDtype::F64 => bytes
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32)
            .collect(),
    }
}
