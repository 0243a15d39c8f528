//! Where a map's local features come from: one interface for every source a model's
//! observations can be described from (a COLMAP database, an hloc `features.h5`, a kapture
//! folder), so aggregation, levels and bases are one code path whatever the feature.
//!
//! A source hands out one image's keypoints and descriptors at a time (hloc's files reach
//! tens of GB); [`super::sift`]'s `gather` folds them into per-point descriptors.

use super::ConvertError;
use crate::colmap::{Database, DescriptorValues};
use std::path::{Path, PathBuf};

/// The most descriptor dimensions a map is built from: the per-level PCA basis is `dim²` f64
/// and its eigendecomposition `dim³`, so a small file claiming 20,000 dimensions would cost
/// gigabytes and hours. Local features in use stay far below (SIFT, ALIKED, DISK 128,
/// SuperPoint 256, D2-Net 512).
pub(crate) const MAX_DESCRIPTOR_DIM: usize = 1024;

/// How far outside its image a keypoint may lie and still be taken, as a share of the longer
/// side: real extractors' keypoints overshoot the border by a few pixels (COLMAP's SIFT on
/// the bartoszek fixture: x = 3035.1 in a 3031-pixel-wide image), while keypoints of another
/// resolution, or x and y swapped, miss by far more.
const OUTSIDE_MARGIN: f64 = 0.01;

/// Whether `[x, y]` (COLMAP's convention: the image spans `[0, w] × [0, h]`) lies outside an
/// image of `size`, beyond [`OUTSIDE_MARGIN`]; NaN lies outside.
pub(crate) fn outside_image([x, y]: [f64; 2], size: [u64; 2]) -> bool {
    let [w, h] = size.map(|v| v as f64);
    let margin = OUTSIDE_MARGIN * w.max(h);
    !((-margin..=w + margin).contains(&x) && (-margin..=h + margin).contains(&y))
}

/// One model image, as a source is asked for its features.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ModelImage<'a> {
    /// The model's image id (a database's key).
    pub id: u32,
    /// The image's name in the model (a features file's or kapture's key).
    pub name: &'a str,
    /// The image's camera size in pixels: keypoints must lie in `[0, width] × [0, height]`
    /// (COLMAP's convention).
    pub size: [u64; 2],
}

/// One image's local features.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct SourceFeatures {
    /// Keypoints.
    pub keypoints: usize,
    /// Each keypoint's scale in pixels, where the source has scales; `None` puts every point
    /// of the map on one level.
    pub scales: Option<Vec<f32>>,
    /// Dimensions of a descriptor.
    pub dim: usize,
    /// `keypoints × dim` values, row-major.
    pub values: DescriptorValues,
}

/// A source of per-image local features for `convert`.
pub(crate) trait FeatureSource {
    /// The file or folder the user named: errors and provenance name it.
    fn path(&self) -> &Path;

    /// What kind of source it is, as each level's `feature_source` records it (`colmap
    /// database`, `hloc features.h5`, `kapture`).
    fn kind(&self) -> &'static str;

    /// The feature the map records as its levels' `descriptor` (`sift`, `aliked-n16`, …), or
    /// `None` if the source does not say; asked after every image was read.
    fn feature_name(&self) -> Option<String>;

    /// `image`'s features, `Ok(None)` if the source has none for it (a missing image is the
    /// caller's to warn about or refuse).
    fn image(&mut self, image: ModelImage<'_>) -> Result<Option<SourceFeatures>, ConvertError>;
}

/// A COLMAP `database.db`, by image id: SIFT (u8) or a learned feature's typed f32 rows.
pub(crate) struct DatabaseSource {
    db: Database,
    path: PathBuf,
    /// The descriptor kind of the images read so far (they must all agree).
    feature: Option<String>,
}

impl DatabaseSource {
    pub(crate) fn open(path: &Path) -> Result<DatabaseSource, ConvertError> {
        Ok(DatabaseSource {
            db: Database::open(path)?,
            path: path.to_path_buf(),
            feature: None,
        })
    }
}

impl FeatureSource for DatabaseSource {
    fn path(&self) -> &Path {
        &self.path
    }

    fn kind(&self) -> &'static str {
        "colmap database"
    }

    fn feature_name(&self) -> Option<String> {
        self.feature.clone()
    }

    fn image(&mut self, image: ModelImage<'_>) -> Result<Option<SourceFeatures>, ConvertError> {
        let features = self.db.features(image.id)?;
        if features.image.name != image.name {
            return Err(ConvertError::NameMismatch {
                features: self.path.clone(),
                image_id: image.id,
                model: image.name.to_owned(),
                found: features.image.name,
            });
        }
        let (Some(keypoints), Some(descriptors)) = (features.keypoints, features.descriptors)
        else {
            return Ok(None);
        };
        let feature = descriptors.feature();
        match &self.feature {
            None => self.feature = Some(feature),
            Some(seen) if *seen != feature => {
                return Err(ConvertError::Input(crate::io::InputError {
                    path: self.path.clone(),
                    line: None,
                    message: format!(
                        "image {}: {feature} descriptors, but the images before it hold {seen}",
                        crate::escape::quoted_name(image.name)
                    ),
                }))
            }
            Some(_) => {}
        }
        // Keypoints without a shape (x, y only) have no scale: one level for the map.
        let scales = (0..keypoints.len())
            .map(|i| keypoints.scale(i))
            .collect::<Option<Vec<f32>>>();
        Ok(Some(SourceFeatures {
            keypoints: keypoints.len(),
            scales,
            dim: descriptors.dim,
            values: descriptors.values,
        }))
    }
}

/// An hloc `features.h5`, by image name: `keypoints` (hloc's convention, + 0.5 here),
/// `descriptors` `D × N`, `scales` where the extractor has them.
#[cfg(feature = "hdf5")]
pub(crate) struct H5Source {
    h5: crate::io::features_h5::H5Features,
    /// `--feature-name`, else the file's own ([`H5Features::feature_name`]).
    ///
    /// [`H5Features::feature_name`]: crate::io::features_h5::H5Features::feature_name
    feature: Option<String>,
}

#[cfg(feature = "hdf5")]
impl H5Source {
    /// Opens `path`; `feature` names the feature when the file does not (or overrides it).
    pub(crate) fn open(path: &Path, feature: Option<String>) -> Result<H5Source, ConvertError> {
        let h5 = crate::io::features_h5::H5Features::open(path)?;
        let feature = match feature {
            Some(f) => Some(f),
            None => h5.feature_name()?,
        };
        Ok(H5Source { h5, feature })
    }
}

#[cfg(feature = "hdf5")]
impl FeatureSource for H5Source {
    fn path(&self) -> &Path {
        self.h5.path()
    }

    fn kind(&self) -> &'static str {
        "hloc features.h5"
    }

    fn feature_name(&self) -> Option<String> {
        self.feature.clone()
    }

    fn image(&mut self, image: ModelImage<'_>) -> Result<Option<SourceFeatures>, ConvertError> {
        let Some(datasets) = self.h5.datasets(image.name)? else {
            return Ok(None);
        };
        let Some(local) = self.h5.local(image.name, &datasets, "")? else {
            return Ok(None);
        };
        if let Some(k) = local
            .keypoints
            .iter()
            .position(|&xy| outside_image(xy, image.size))
        {
            // Named as the file holds it (hloc's convention), with its dataset.
            let [x, y] = local.keypoints[k].map(|v| v - 0.5);
            return Err(self
                .h5
                .err(format!(
                    "{}/keypoints: keypoint {k} at ({x}, {y}) lies outside the {} x {} image",
                    image.name, image.size[0], image.size[1]
                ))
                .into());
        }
        let keypoints = local.keypoints.len();
        let scales = self.h5.scales(image.name, &datasets, keypoints)?;
        Ok(Some(SourceFeatures {
            keypoints,
            scales,
            dim: local.dim,
            values: DescriptorValues::F32(local.descriptors),
        }))
    }
}
