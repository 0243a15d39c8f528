//! Query inputs of the localizer: hloc-style query lists with intrinsics, SIFT features of
//! queries from a COLMAP database (`queries.db`), and the extractor's output as localizer
//! input. hloc's `features.h5` is read beside its writer, in [`super::features_h5`].

use super::InputError;
use crate::geometry::Camera;
#[cfg(any(feature = "colmap", feature = "onnx"))]
use crate::localize::{FeatureSet, QueryFeatures};
use std::path::Path;

/// One query: its image name and camera.
#[derive(Debug, Clone)]
pub struct Query {
    /// The image name, as the list gives it.
    pub name: String,
    /// Its camera.
    pub camera: Camera,
}

/// Reads `name MODEL W H params...` lines (hloc's query list with intrinsics). With
/// `camera`, lines may hold just a name and that camera is used for every query.
pub fn read_query_list(path: &Path, camera: Option<&Camera>) -> Result<Vec<Query>, InputError> {
    let queries = super::parse_lines(path, |line| {
        Ok(match camera {
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
                let (name, camera) = Camera::parse_query_line(line).map_err(|e| e.to_string())?;
                Query { name, camera }
            }
        })
    })?;
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
    /// Opens a COLMAP database of query features (read-only) and indexes its images by name.
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
                    crate::escape::quoted_name(name)
                ),
            });
        }
        let n = keypoints.len().min(descriptors.len());
        let dim = descriptors.dim;
        let mut set = FeatureSet {
            level: None,
            keypoints: Vec::with_capacity(n),
            descriptors: Vec::with_capacity(n * dim),
            dim,
        };
        let mut row = Vec::with_capacity(dim);
        for i in 0..n {
            let Some(xy) = keypoints.xy(i) else {
                continue;
            };
            if !descriptors.row_into(i, &mut row) {
                continue;
            }
            set.keypoints.push([f64::from(xy[0]), f64::from(xy[1])]);
            set.descriptors.extend_from_slice(&row);
        }
        // Typed f32 rows may hold NaN: the localizer's rule, named by image here.
        if let Err(e) = set.check_finite() {
            return Err(crate::colmap::Error::BadRow {
                path: self.db.path().to_path_buf(),
                table: "descriptors",
                id: i64::from(id),
                what: format!("image {}: {e}", crate::escape::quoted_name(name)),
            });
        }
        crate::vector::normalise_rows(&mut set.descriptors, dim);
        Ok(Some(QueryFeatures {
            sets: vec![set],
            global: None,
            // The database says which feature its rows are: a map of another is refused.
            model: Some(crate::localize::FeatureModel {
                name: descriptors.feature(),
                xxh3: None,
            }),
        }))
    }
}

/// Extractor output as localizer input: one feature set per level with the full descriptors
/// (SFP maps keep descriptors in the extractor's basis; the localizer truncates for `short`),
/// and the global descriptor for retrieval.
/// `extractor` made `f`: the features carry its model (a session refuses them for a map of
/// another model).
#[cfg(feature = "onnx")]
pub fn sfp_query(
    f: &crate::extract::Features,
    extractor: &crate::extract::Extractor,
) -> QueryFeatures {
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
        // Empty when the extraction skipped it (`GlobalSize::Skip`).
        global: (!f.global.is_empty()).then(|| f.global.clone()),
        model: Some(crate::localize::FeatureModel {
            name: extractor.contract().model_name.clone(),
            xxh3: Some(extractor.model().xxh3.clone()),
        }),
    }
}
