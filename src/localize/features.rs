//! A query's features as the localizer takes them: per-level keypoints and descriptors, a
//! global descriptor, the model that made them; and the rule that every value is finite
//! (a NaN passes every check of the pose solver's input, an infinity wrecks the matching
//! and a non-finite global descriptor ranks every image equal), which the features.h5
//! reader, the session, Python and C all ask here.

/// Keypoints and descriptors of one query image, for one level or for all.
#[derive(Debug, Clone, Default)]
pub struct FeatureSet {
    /// The map level these features are for; `None`: the same features serve every level
    /// (SIFT queries against a SIFT map, whose levels are scale buckets of one descriptor).
    pub level: Option<u16>,
    /// Pixels, COLMAP convention.
    pub keypoints: Vec<[f64; 2]>,
    /// `[keypoints × dim]`, in the extractor's own space (before the level's projection).
    pub descriptors: Vec<f32>,
    /// Dimensions per descriptor.
    pub dim: usize,
}

/// Everything known about one query image.
#[derive(Debug, Clone, Default)]
pub struct QueryFeatures {
    /// Per-level feature sets (SFP), or one set for every level (SIFT).
    pub sets: Vec<FeatureSet>,
    /// Global descriptor for retrieval, if the extractor gives one.
    pub global: Option<Vec<f32>>,
    /// The model that made these features, when known (the SFP extractor's, a features
    /// file's `sfp.model_name`): a session refuses features of another model than its map's.
    pub model: Option<FeatureModel>,
}

/// The model features came from: its descriptor kind (`sfp-v2`, as maps record it) and, when
/// known, the XXH3 of its ONNX file (a retrained model keeps its name, not its hash).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FeatureModel {
    /// The descriptor kind (`sfp-v2`, `sift`), as maps record it.
    pub name: String,
    /// XXH3-64 of the model's ONNX file (hex), when known.
    pub xxh3: Option<String>,
}

impl FeatureSet {
    /// The first NaN or infinite keypoint coordinate or descriptor value.
    pub fn check_finite(&self) -> Result<(), NonFinite> {
        let at = |what| NonFinite {
            level: Some(self.level),
            what,
        };
        for (row, xy) in self.keypoints.iter().enumerate() {
            if let Some(axis) = xy.iter().position(|v| !v.is_finite()) {
                return Err(at(NonFiniteValue::Keypoint {
                    row,
                    axis: ["x", "y"][axis],
                    value: xy[axis],
                }));
            }
        }
        match self.descriptors.iter().position(|v| !v.is_finite()) {
            Some(i) => Err(at(NonFiniteValue::Descriptor {
                row: i / self.dim.max(1),
                value: self.descriptors[i],
            })),
            None => Ok(()),
        }
    }
}

impl QueryFeatures {
    /// The first NaN or infinite value of the sets or the global descriptor.
    pub fn check_finite(&self) -> Result<(), NonFinite> {
        self.sets.iter().try_for_each(FeatureSet::check_finite)?;
        check_global_finite(self.global.as_deref())
    }
}

/// The first NaN or infinite value of a global descriptor (`None`: none given).
pub fn check_global_finite(global: Option<&[f32]>) -> Result<(), NonFinite> {
    match global.and_then(|g| g.iter().position(|v| !v.is_finite()).map(|i| (i, g[i]))) {
        Some((index, value)) => Err(NonFinite {
            level: None,
            what: NonFiniteValue::Global { index, value },
        }),
        None => Ok(()),
    }
}

/// A NaN or infinite value in query features: where it is and what it is.
#[derive(Debug, Clone, PartialEq)]
pub struct NonFinite {
    /// The feature set's level (`Some(None)`: the set for every level); `None` for the global
    /// descriptor.
    pub level: Option<Option<u16>>,
    /// Which value.
    pub what: NonFiniteValue,
}

/// Which value of query features is not finite.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum NonFiniteValue {
    /// A keypoint's coordinate.
    Keypoint {
        /// The keypoint.
        row: usize,
        /// `"x"` or `"y"`.
        axis: &'static str,
        /// The value.
        value: f64,
    },
    /// A value of a keypoint's descriptor.
    Descriptor {
        /// The keypoint.
        row: usize,
        /// The value.
        value: f32,
    },
    /// A value of the global descriptor.
    Global {
        /// Its index.
        index: usize,
        /// The value.
        value: f32,
    },
}

/// `level 3: keypoints row 2: y is NaN`, `level None (every level): descriptors row 1: a
/// value is -inf`, `global_descriptor: value 0 is inf`.
impl std::fmt::Display for NonFinite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.level {
            Some(Some(level)) => write!(f, "level {level}: ")?,
            Some(None) => f.write_str("level None (every level): ")?,
            None => {}
        }
        match &self.what {
            NonFiniteValue::Keypoint { row, axis, value } => {
                write!(f, "keypoints row {row}: {axis} is {value}")
            }
            NonFiniteValue::Descriptor { row, value } => {
                write!(f, "descriptors row {row}: a value is {value}")
            }
            NonFiniteValue::Global { index, value } => {
                write!(f, "global_descriptor: value {index} is {value}")
            }
        }
    }
}

impl std::error::Error for NonFinite {}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(level: Option<u16>) -> FeatureSet {
        FeatureSet {
            level,
            keypoints: vec![[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]],
            descriptors: vec![0.5; 3 * 4],
            dim: 4,
        }
    }

    #[test]
    fn the_first_non_finite_value_is_named_by_level_row_and_axis() {
        let mut q = QueryFeatures {
            sets: vec![set(Some(0)), set(None)],
            global: Some(vec![0.0; 8]),
            model: None,
        };
        assert_eq!(q.check_finite(), Ok(()));
        q.sets[1].keypoints[2][1] = f64::NAN;
        assert_eq!(
            q.check_finite().unwrap_err().to_string(),
            "level None (every level): keypoints row 2: y is NaN"
        );
        q.sets[0].descriptors[4 + 3] = f32::NEG_INFINITY; // row 1
        assert_eq!(
            q.check_finite().unwrap_err().to_string(),
            "level 0: descriptors row 1: a value is -inf"
        );
        let mut g = QueryFeatures {
            sets: vec![set(Some(3))],
            global: Some(vec![0.0, f32::INFINITY]),
            model: None,
        };
        assert_eq!(
            g.check_finite().unwrap_err().to_string(),
            "global_descriptor: value 1 is inf"
        );
        g.global = None;
        assert_eq!(g.check_finite(), Ok(()));
    }
}
