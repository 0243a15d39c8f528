//! Query inputs: hloc-style query lists with intrinsics, and SIFT features of queries read
//! from a COLMAP database (`queries.db`).

#[cfg(any(feature = "colmap", feature = "onnx"))]
use super::localizer::{FeatureSet, QueryFeatures};
use crate::geometry::Camera;
use std::path::{Path, PathBuf};

/// One query: its image name and camera.
#[derive(Debug, Clone)]
pub struct Query {
    pub name: String,
    pub camera: Camera,
}

/// A problem with an input file (query list, features file, poses file), naming the file and,
/// when known, the line.
#[derive(Debug)]
pub struct InputError {
    pub path: PathBuf,
    pub line: Option<usize>,
    pub message: String,
}

impl std::fmt::Display for InputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.line {
            Some(line) => write!(f, "{}:{line}: {}", self.path.display(), self.message),
            None => write!(f, "{}: {}", self.path.display(), self.message),
        }
    }
}

impl std::error::Error for InputError {}

/// Reads `name MODEL W H params...` lines (hloc's query list with intrinsics). With
/// `camera`, lines may hold just a name and that camera is used for every query.
pub fn read_query_list(path: &Path, camera: Option<&Camera>) -> Result<Vec<Query>, InputError> {
    let text = crate::input::read_regular_to_string(path).map_err(|e| InputError {
        path: path.into(),
        line: None,
        message: e.to_string(),
    })?;
    let mut queries = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |message: String| InputError {
            path: path.into(),
            line: Some(i + 1),
            message,
        };
        let query = match camera {
            // One camera for all: the first token is the name, the rest is ignored.
            Some(c) => Query {
                name: line
                    .split_whitespace()
                    .next()
                    .unwrap_or_default()
                    .to_string(),
                camera: c.clone(),
            },
            None => {
                let (name, camera) =
                    Camera::parse_query_line(line).map_err(|e| bad(e.to_string()))?;
                Query { name, camera }
            }
        };
        queries.push(query);
    }
    if queries.is_empty() {
        return Err(InputError {
            path: path.into(),
            line: None,
            message: "no queries".into(),
        });
    }
    Ok(queries)
}

/// SIFT features of query images from a COLMAP database, looked up by image name.
#[cfg(feature = "colmap")]
pub struct DatabaseFeatures {
    db: crate::colmap::Database,
    ids: std::collections::HashMap<String, u32>,
}

#[cfg(feature = "colmap")]
impl DatabaseFeatures {
    pub fn open(path: &Path) -> Result<DatabaseFeatures, crate::colmap::Error> {
        let db = crate::colmap::Database::open(path)?;
        let ids = db.images()?.into_iter().map(|i| (i.name, i.id)).collect();
        Ok(DatabaseFeatures { db, ids })
    }

    /// The query's keypoints and L2-normalised descriptors; `Ok(None)` if the database has no
    /// such image or no features for it; an error naming the image and keypoint if a
    /// keypoint's x, y or scale is not finite.
    pub fn features(&self, name: &str) -> Result<Option<QueryFeatures>, crate::colmap::Error> {
        let Some(&id) = self.ids.get(name) else {
            return Ok(None);
        };
        let f = self.db.features(id)?;
        let (Some(keypoints), Some(descriptors)) = (f.keypoints, f.descriptors) else {
            return Ok(None);
        };
        if let Some((i, field, value)) = keypoints.first_non_finite() {
            return Err(crate::colmap::Error::BadRow {
                path: self.db.path().to_path_buf(),
                table: "keypoints",
                id: i64::from(id),
                what: format!(
                    "image {}, keypoint {i}: {field} is {value}",
                    crate::io::colmap_export::quoted_name(name)
                ),
            });
        }
        let n = keypoints.len().min(descriptors.len());
        let dim = descriptors.cols;
        let mut set = FeatureSet {
            level: None,
            keypoints: Vec::with_capacity(n),
            descriptors: Vec::with_capacity(n * dim),
            dim,
        };
        for i in 0..n {
            let (Some(xy), Some(row)) = (keypoints.xy(i), descriptors.row(i)) else {
                continue;
            };
            set.keypoints.push([f64::from(xy[0]), f64::from(xy[1])]);
            set.descriptors.extend(row.iter().map(|&b| f32::from(b)));
        }
        super::matching::normalise_rows(&mut set.descriptors, dim);
        Ok(Some(QueryFeatures {
            sets: vec![set],
            global: None,
        }))
    }
}

/// Extractor output as localizer input: one feature set per level with the full descriptors
/// (SFP maps keep descriptors in the extractor's basis; the localizer truncates for `short`),
/// and the global descriptor for retrieval.
#[cfg(feature = "onnx")]
pub fn sfp_query(f: &crate::extract::Features) -> QueryFeatures {
    let sets = f
        .levels
        .iter()
        .map(|l| FeatureSet {
            level: Some(l.level),
            keypoints: l
                .keypoints
                .iter()
                .map(|k| [f64::from(k[0]), f64::from(k[1])])
                .collect(),
            descriptors: l.full.iter().map(|x| x.to_f32()).collect(),
            dim: l.dim_full,
        })
        .collect();
    QueryFeatures {
        sets,
        global: Some(f.global.clone()),
    }
}

/// Query features from an hloc-style `features.h5` (as `sfpmap extract` writes, or hloc's own
/// extractors): per-level `level<id>_keypoints` / `level<id>_descriptors` when present (SFP),
/// else the image's `keypoints` / `descriptors` for every level. Keypoints are in hloc's
/// convention (first pixel centre at 0) and get +0.5; descriptors are `[D × N]`, f16 or f32.
#[cfg(feature = "onnx")]
pub struct H5Features {
    file: hdf5_pure::File,
    path: PathBuf,
    /// Bounds every dataset's declared size before it is read (an unwritten dataset of a
    /// declared 2^31 values would otherwise be allocated as its fill value).
    file_len: u64,
}

#[cfg(feature = "onnx")]
impl H5Features {
    pub fn open(path: &Path) -> Result<H5Features, InputError> {
        let err = |message: String| InputError {
            path: path.into(),
            line: None,
            message,
        };
        let bytes = crate::input::read_regular(path).map_err(|e| err(e.to_string()))?;
        let file_len = bytes.len() as u64;
        let file = hdf5_pure::File::from_bytes(bytes)
            .map_err(|e| err(format!("not a readable HDF5 file: {e}")))?;
        Ok(H5Features {
            file,
            path: path.into(),
            file_len,
        })
    }

    fn err(&self, message: String) -> InputError {
        InputError {
            path: self.path.clone(),
            line: None,
            message,
        }
    }

    /// `[rows × cols]` values of a dataset, or `None` if it does not exist.
    fn matrix(&self, name: &str) -> Result<Option<(Vec<f32>, usize, usize)>, InputError> {
        let Ok(ds) = self.file.dataset(name) else {
            return Ok(None);
        };
        let shape = ds.shape().map_err(|e| self.err(format!("{name}: {e}")))?;
        let (rows, cols) = match shape.as_slice() {
            [r, c] => (*r, *c),
            [n] => (1, *n),
            other => return Err(self.err(format!("{name}: unexpected shape {other:?}"))),
        };
        // At least 2 bytes a value (f16): a shape the file cannot hold is refused before
        // hdf5 allocates it.
        if rows
            .checked_mul(cols)
            .and_then(|n| n.checked_mul(2))
            .is_none_or(|b| b > self.file_len)
        {
            return Err(self.err(format!(
                "{name}: {rows} x {cols} values do not fit in a file of {} bytes",
                self.file_len
            )));
        }
        let raw = ds
            .read_raw()
            .map_err(|e| self.err(format!("{name}: {e}")))?;
        // The shape is the file's claim: checked against the bytes actually read, never used
        // to size anything before that.
        let n = rows
            .checked_mul(cols)
            .and_then(|n| usize::try_from(n).ok())
            .filter(|n| n.checked_mul(2).is_some_and(|b| b <= raw.len()))
            .ok_or_else(|| {
                self.err(format!(
                    "{name}: {} bytes for {rows} x {cols} values (f16 or f32 expected)",
                    raw.len()
                ))
            })?;
        let (rows, cols) = (rows as usize, cols as usize);
        let values: Vec<f32> = if raw.len() == n * 4 {
            raw.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect()
        } else if raw.len() == n * 2 {
            raw.chunks_exact(2)
                .map(|b| crate::format::f16::from_le_bytes([b[0], b[1]]).to_f32())
                .collect()
        } else {
            return Err(self.err(format!(
                "{name}: {} bytes for {rows} x {cols} values (f16 or f32 expected)",
                raw.len()
            )));
        };
        Ok(Some((values, rows, cols)))
    }

    /// One feature set from `<prefix>keypoints` and `<prefix>descriptors`.
    fn set(
        &self,
        name: &str,
        prefix: &str,
        level: Option<u16>,
    ) -> Result<Option<FeatureSet>, InputError> {
        let Some((kp, n, two)) = self.matrix(&format!("{name}/{prefix}keypoints"))? else {
            return Ok(None);
        };
        let Some((desc, dim, n_desc)) = self.matrix(&format!("{name}/{prefix}descriptors"))? else {
            return Ok(None);
        };
        if two != 2 || n_desc != n {
            return Err(self.err(format!(
                "{name}/{prefix}: {n} keypoints x {two}, descriptors {dim} x {n_desc}"
            )));
        }
        // As for database keypoints: a NaN would pass every check of the pose solver's input.
        if let Some(i) = kp.iter().position(|v| !v.is_finite()) {
            return Err(self.err(format!(
                "{name}/{prefix}keypoints: keypoint {}: {} is {}",
                i / 2,
                ["x", "y"][i % 2],
                kp[i]
            )));
        }
        if let Some(i) = desc.iter().position(|v| !v.is_finite()) {
            return Err(self.err(format!(
                "{name}/{prefix}descriptors: keypoint {}: a value is {}",
                i % n.max(1),
                desc[i]
            )));
        }
        // [D × N] → [N × D].
        let mut descriptors = vec![0.0f32; n * dim];
        for d in 0..dim {
            for k in 0..n {
                descriptors[k * dim + d] = desc[d * n + k];
            }
        }
        super::matching::normalise_rows(&mut descriptors, dim);
        let keypoints = kp
            .chunks_exact(2)
            .map(|p| [f64::from(p[0]) + 0.5, f64::from(p[1]) + 0.5])
            .collect();
        Ok(Some(FeatureSet {
            level,
            keypoints,
            descriptors,
            dim,
        }))
    }

    /// The query's features, `Ok(None)` if the file has no group for it.
    pub fn features(&self, name: &str) -> Result<Option<QueryFeatures>, InputError> {
        let mut sets = Vec::new();
        for id in 0..32u16 {
            if let Some(set) = self.set(name, &format!("level{id}_"), Some(id))? {
                sets.push(set);
            }
        }
        if sets.is_empty() {
            match self.set(name, "", None)? {
                Some(set) => sets.push(set),
                None => return Ok(None),
            }
        }
        let global = self
            .matrix(&format!("{name}/global_descriptor"))?
            .map(|(v, _, _)| v);
        Ok(Some(QueryFeatures { sets, global }))
    }
}
