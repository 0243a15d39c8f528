//! Maps from kapture folders (`sfpmap convert --kapture`): the folder's model
//! ([`crate::io::kapture::read_kapture`]) with its keypoints and descriptors as the feature
//! source of the SIFT path, so aggregation, levels and bases are the ones every map gets.
//!
//! Levels: keypoints with a scale (kapture dsize 3 or 4: the third value; dsize 6: COLMAP's
//! affine shape) are split by scale as a database's are; keypoints without one (dsize 2, or
//! another layout) put every point on one level.

use super::features::{FeatureSource, ModelImage, SourceFeatures};
use super::{ConvertError, ConvertOptions, ConvertSummary};
use crate::io::kapture::{read_kapture, Kapture, KaptureError, KaptureOptions};
use crate::progress::Reporter;
use std::path::Path;

/// A kapture folder's keypoints and descriptors, one image at a time.
pub(crate) struct KaptureSource<'k> {
    kapture: &'k Kapture,
    /// The name the map's levels record (`--feature-name`, else from the descriptors type).
    feature: Option<String>,
}

impl<'k> KaptureSource<'k> {
    pub(crate) fn new(kapture: &'k Kapture, feature_name: Option<String>) -> Self {
        // kapture names COLMAP's SIFT `SIFT`; the maps (and query databases) call it `sift`.
        let derived = kapture.descriptors.as_ref().map(|d| {
            if d.name.eq_ignore_ascii_case("sift") {
                "sift".to_string()
            } else {
                d.name.clone()
            }
        });
        KaptureSource {
            kapture,
            feature: feature_name.or(derived),
        }
    }
}

impl FeatureSource for KaptureSource<'_> {
    fn path(&self) -> &Path {
        &self.kapture.root
    }

    fn kind(&self) -> &'static str {
        "kapture folder"
    }

    fn feature_name(&self) -> Option<String> {
        self.feature.clone()
    }

    fn image(&mut self, image: ModelImage<'_>) -> Result<Option<SourceFeatures>, ConvertError> {
        let (Some(info), Some(keypoints)) = (
            &self.kapture.descriptors,
            self.kapture.keypoints(image.name)?,
        ) else {
            return Ok(None);
        };
        let Some(values) = self.kapture.descriptors(image.name)? else {
            return Ok(None);
        };
        let count = match &values {
            crate::colmap::DescriptorValues::U8(v) => v.len(),
            crate::colmap::DescriptorValues::F32(v) => v.len(),
        } / info.dsize;
        if count != keypoints.len() {
            return Err(KaptureError::CountMismatch {
                path: self
                    .kapture
                    .descriptors_path(image.name)
                    .unwrap_or_default(),
                descriptors: count as u64,
                keypoints: keypoints.len() as u64,
            }
            .into());
        }
        if let Some(k) = (0..keypoints.len()).find(|&i| {
            keypoints.xy(i).is_some_and(|[x, y]| {
                super::features::outside_image([f64::from(x), f64::from(y)], image.size)
            })
        }) {
            return Err(ConvertError::KeypointOutsideImage {
                features: self.kapture.keypoints_path(image.name).unwrap_or_default(),
                image: image.name.to_owned(),
                keypoint: k,
                xy: keypoints.xy(k).unwrap_or_default(),
                size: image.size,
            });
        }
        let scales = (0..keypoints.len())
            .map(|i| keypoints.scale(i))
            .collect::<Option<Vec<f32>>>();
        Ok(Some(SourceFeatures {
            keypoints: keypoints.len(),
            scales,
            dim: info.dsize,
            values,
        }))
    }
}

/// Converts the kapture folder `dir` into a map at `output`: its model's geometry and, where
/// it has them, its keypoints and descriptors (`options.feature_name` names the feature; a
/// `database` or `features` file is refused: the folder holds its own). Records without a pose
/// and observations of unregistered images are left out, with a warning through `reporter`.
pub fn convert_kapture(
    dir: &Path,
    kapture_options: &KaptureOptions,
    options: &ConvertOptions,
    output: &Path,
    reporter: &dyn Reporter,
) -> Result<ConvertSummary, ConvertError> {
    if options.database.is_some() || options.features.is_some() {
        return Err(ConvertError::Options(format!(
            "{}: a kapture folder holds its own keypoints and descriptors: a database or \
             features file is not read with it",
            dir.display()
        )));
    }
    reporter.start("reading kapture", None);
    let kapture = read_kapture(dir, kapture_options)?;
    reporter.finish();
    if kapture.records_without_pose > 0 {
        reporter.warn(&format!(
            "{}: {} camera records have no pose; their images are not in the map",
            crate::escape::path(dir),
            kapture.records_without_pose
        ));
    }
    if kapture.observations_skipped > 0 {
        reporter.warn(&format!(
            "{}: {} observations of images without a pose left out",
            crate::escape::path(dir),
            kapture.observations_skipped
        ));
    }
    let mut source = KaptureSource::new(&kapture, options.feature_name.clone());
    let desc = dir.display().to_string();
    if kapture.descriptors.is_none() {
        return super::convert_model(
            &kapture.reconstruction,
            &desc,
            &geometry_only(options),
            output,
            reporter,
        );
    }
    let mut summary = super::sift::convert_with_source(
        &kapture.reconstruction,
        &mut source,
        &desc,
        options,
        output,
        reporter,
    )?;
    summary.input_bytes = input_bytes(&kapture);
    Ok(summary)
}

/// The bytes read: the tables, and each registered image's keypoints and descriptors.
fn input_bytes(kapture: &Kapture) -> u64 {
    let size = |p: &Path| std::fs::metadata(p).map_or(0, |m| m.len());
    let tables: u64 = kapture.files.iter().map(|p| size(p)).sum();
    let features: u64 = kapture
        .reconstruction
        .images()
        .iter()
        .flat_map(|i| {
            [
                kapture.keypoints_path(&i.name),
                kapture.descriptors_path(&i.name),
            ]
        })
        .flatten()
        .map(|p| size(&p))
        .sum();
    tables + features
}

/// `options` without any feature input: a folder without descriptors makes a geometry map.
fn geometry_only(options: &ConvertOptions) -> ConvertOptions {
    ConvertOptions {
        database: None,
        features: None,
        global_features: None,
        ..options.clone()
    }
}

impl From<KaptureError> for ConvertError {
    fn from(e: KaptureError) -> Self {
        ConvertError::Kapture(e)
    }
}
