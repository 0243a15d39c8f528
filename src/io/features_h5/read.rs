//! Reading hloc-style `features.h5`: a map's features for `convert --features` and a query's
//! for `localize --features`, from the same datasets by the same rules.

use super::super::InputError;
use hdf5_pure::{Datatype, DatatypeByteOrder};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// One image's local features as the file holds them, in sfpmap's conventions.
#[cfg(any(feature = "colmap", feature = "localize"))]
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LocalFeatures {
    /// Keypoints in COLMAP's convention (the file's + 0.5).
    pub keypoints: Vec<[f64; 2]>,
    /// `[keypoints × dim]`, as stored (not normalised).
    pub descriptors: Vec<f32>,
    /// Dimensions of a descriptor.
    pub dim: usize,
}

/// hloc's feature files are named `feats-<conf>.h5` (`feats-aliked-n16.h5`,
/// `feats-superpoint-n4096-r1024.h5`): the conf names the feature.
const HLOC_PREFIX: &str = "feats-";

/// Features from an hloc-style `features.h5` (as `sfpmap extract` writes, or hloc's own
/// extractors): per-level `level<id>_keypoints` / `level<id>_descriptors` when present (SFP),
/// else the image's `keypoints` / `descriptors` (plus `scales` where the extractor has them,
/// hloc's DoG). Keypoints are in hloc's convention (first pixel centre at 0) and get +0.5;
/// descriptors are `[D × N]`, f16 or f32.
///
/// The file is read on demand, never whole (hloc's files reach tens of GB): opening reads the
/// superblock, and each image the metadata on its path (through a cache of at most
/// [`H5Features::METADATA_CACHE_BYTES`]) and the datasets it uses.
pub struct H5Features {
    file: hdf5_pure::File,
    path: PathBuf,
    /// Bounds every dataset's declared size before it is read (an unwritten dataset of a
    /// declared 2^31 values would otherwise be allocated as its fill value).
    file_len: u64,
    /// Each group walked so far (by path, `""` the root): its child groups by name. Why:
    /// hdf5-pure finds a child by listing its group, so looking up 10,000 images one by one
    /// listed the root 10,000 times (convert was quadratic: 4,000 images 3.8 s); listed once,
    /// every lookup is a hash probe.
    children: Mutex<HashMap<String, Arc<Children>>>,
}

/// A group's child groups by name.
type Children = HashMap<String, hdf5_pure::Group>;

/// An image group's datasets by name.
pub(crate) type Datasets = HashMap<String, hdf5_pure::Dataset>;

/// The most dimensions a descriptor, local or global, may have: the format's limit.
const MAX_DIM: usize = crate::format::MAX_DESCRIPTOR_DIM as usize;

impl H5Features {
    /// The most bytes of metadata (group indexes, object headers) kept between images.
    pub const METADATA_CACHE_BYTES: usize = 8 << 20;

    /// Opens a features file; groups are read by name as they are asked for.
    pub fn open(path: &Path) -> Result<H5Features, InputError> {
        use hdf5_pure::Source;
        let err = |message: String| InputError {
            path: path.into(),
            line: None,
            message,
        };
        let handle = crate::input::open_regular(path).map_err(|e| err(e.to_string()))?;
        let source = hdf5_pure::ReadSeekSource::new(handle)
            .map_err(|e| err(format!("not a readable HDF5 file: {e}")))?;
        let file_len = source.len();
        let properties = hdf5_pure::FileAccessProperties::new().with_metadata_cache(
            hdf5_pure::MetadataCacheConfig::new(Self::METADATA_CACHE_BYTES),
        );
        let file = hdf5_pure::File::from_source_with_options(source, properties)
            .map_err(|e| err(format!("not a readable HDF5 file: {e}")))?;
        Ok(H5Features {
            file,
            path: path.into(),
            file_len,
            children: Mutex::default(),
        })
    }

    /// The file as the user named it.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// A root attribute stored as one string (`sfp.model_name`, …), if the file has it; an
    /// attribute of that name holding anything else is an error, not a missing one.
    pub fn root_string(&self, key: &str) -> Result<Option<String>, InputError> {
        let attrs = self
            .file
            .root()
            .attrs()
            .map_err(|e| self.err(format!("root attributes: {e}")))?;
        match attrs.get(key) {
            None => Ok(None),
            Some(v) => match v.as_str() {
                Some(s) => Ok(Some(s.to_owned())),
                None => Err(self.err(format!("root attribute {key}: not one string"))),
            },
        }
    }

    /// The feature the file holds, as maps record it: its `sfp.model_name` attribute
    /// (`sfpmap extract`), else the conf in hloc's file name (`feats-aliked-n16.h5` →
    /// `aliked-n16`); `None` if neither says. hloc's `sift` conf describes with RootSIFT, not
    /// COLMAP's SIFT bytes: it is `rootsift` here, so neither is taken for the other.
    pub fn feature_name(&self) -> Result<Option<String>, InputError> {
        if let Some(name) = self.root_string("sfp.model_name")? {
            return Ok(Some(name));
        }
        Ok(self
            .path
            .file_stem()
            .and_then(|s| s.to_str())
            .and_then(|s| s.strip_prefix(HLOC_PREFIX))
            .filter(|conf| !conf.is_empty())
            .map(|conf| match conf {
                "sift" => "rootsift".to_owned(),
                conf => conf.to_owned(),
            }))
    }

    /// An error about this file; image and dataset names in `message` are the user's and
    /// may hold anything: control characters are escaped so the error stays one line.
    pub(crate) fn err(&self, message: String) -> InputError {
        InputError {
            path: self.path.clone(),
            line: None,
            message: crate::escape::escape_control_characters(&message).into_owned(),
        }
    }

    /// The datasets of image `name`'s group; `Ok(None)` if the file has no such group. The
    /// group is resolved once and its datasets listed once: an image costs one path lookup,
    /// whatever the number of images or levels.
    pub(crate) fn datasets(&self, name: &str) -> Result<Option<Datasets>, InputError> {
        // No such group (or a dataset of that name): the file has no features for it.
        let Some(group) = self.group(name)? else {
            return Ok(None);
        };
        let datasets = group
            .iter_datasets()
            .map_err(|e| self.err(format!("{name}: {e}")))?
            .collect();
        Ok(Some(datasets))
    }

    /// The group `name` (`a/b/c.jpg`: one component a level), through the index of the
    /// groups walked so far; `None` if a component is not a group. Empty components are
    /// skipped (`d//a.jpg` is `d/a.jpg`, `/b.jpg` is `b.jpg`), as HDF5 paths (h5py's, and
    /// this module's writer) read them.
    fn group(&self, name: &str) -> Result<Option<hdf5_pure::Group>, InputError> {
        let mut group = self.file.root();
        let mut at = String::new();
        for component in name.split('/').filter(|c| !c.is_empty()) {
            let children = self.children_of(&at, &group)?;
            match children.get(component) {
                Some(child) => group = child.clone(),
                None => return Ok(None),
            }
            if !at.is_empty() {
                at.push('/');
            }
            at.push_str(component);
        }
        Ok(Some(group))
    }

    /// The child groups of `group` (at `path`), listed once per file.
    fn children_of(
        &self,
        path: &str,
        group: &hdf5_pure::Group,
    ) -> Result<Arc<Children>, InputError> {
        let mut index = self.children.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(children) = index.get(path) {
            return Ok(Arc::clone(children));
        }
        let children: Arc<Children> = Arc::new(
            group
                .iter_groups()
                .map_err(|e| {
                    self.err(format!("{}: {e}", if path.is_empty() { "/" } else { path }))
                })?
                .collect(),
        );
        index.insert(path.to_owned(), Arc::clone(&children));
        Ok(children)
    }

    /// `[rows × cols]` values of the dataset `ds` (`name` in errors): little-endian f16 or
    /// f32, its declared size checked against the file's before anything is read.
    pub(crate) fn matrix(
        &self,
        name: &str,
        ds: &hdf5_pure::Dataset,
        max_values: usize,
    ) -> Result<(Vec<f32>, usize, usize), InputError> {
        let shape = ds.shape().map_err(|e| self.err(format!("{name}: {e}")))?;
        let (rows, cols) = match shape.as_slice() {
            [r, c] => (*r, *c),
            [n] => (1, *n),
            other => return Err(self.err(format!("{name}: unexpected shape {other:?}"))),
        };
        let datatype = ds
            .datatype()
            .map_err(|e| self.err(format!("{name}: {e}")))?;
        if !matches!(
            datatype,
            Datatype::FloatingPoint {
                size: 2 | 4,
                byte_order: DatatypeByteOrder::LittleEndian,
                ..
            }
        ) {
            let found = match datatype {
                Datatype::FloatingPoint { size, .. } => format!("{}-bit floats", size * 8),
                Datatype::FixedPoint { size, .. } => format!("{}-bit integers", size * 8),
                other => format!("{other:?}"),
            };
            return Err(self.err(format!(
                "{name}: values of {found} (little-endian f16 or f32 expected)"
            )));
        }
        // A dataset many groups link to is counted once in the file but read once per group:
        // what the caller allows of it is checked before anything is read.
        if rows.checked_mul(cols).is_none_or(|n| n > max_values as u64) {
            return Err(self.err(format!(
                "{name}: {rows} x {cols} values, more than the {max_values} it may hold"
            )));
        }
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
        Ok((values, rows, cols))
    }

    /// One feature set from image `name`'s `<prefix>keypoints` and `<prefix>descriptors`,
    /// `None` if either is missing. Refused, naming the image and dataset: keypoints that
    /// are not `N × 2`, descriptors that are not `D × N` (`N × D` is named as a
    /// transposition), NaN or infinite values.
    #[cfg(any(feature = "colmap", feature = "localize"))]
    pub(crate) fn local(
        &self,
        name: &str,
        datasets: &Datasets,
        prefix: &str,
    ) -> Result<Option<LocalFeatures>, InputError> {
        let (Some(kp), Some(desc)) = (
            datasets.get(&format!("{prefix}keypoints")),
            datasets.get(&format!("{prefix}descriptors")),
        ) else {
            return Ok(None);
        };
        let kp_name = format!("{name}/{prefix}keypoints");
        let desc_name = format!("{name}/{prefix}descriptors");
        let (kp, n, two) = self.matrix(&kp_name, kp, usize::MAX)?;
        if two != 2 {
            return Err(self.err(format!("{kp_name}: {n} x {two} (N x 2 expected)")));
        }
        let (desc, dim, n_desc) = self.matrix(&desc_name, desc, usize::MAX)?;
        if n_desc != n {
            return Err(self.err(if dim == n {
                format!(
                    "{desc_name}: {dim} x {n_desc} is keypoints x dimensions; hloc stores \
                     descriptors transposed, dimensions x keypoints ({n_desc} x {n})"
                )
            } else {
                format!("{desc_name}: {dim} x {n_desc} values for {n} keypoints (D x {n} expected)")
            }));
        }
        if let Some(row) = kp
            .chunks_exact(2)
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            let p = &kp[2 * row..2 * row + 2];
            let (axis, value) = if p[0].is_finite() {
                ("y", p[1])
            } else {
                ("x", p[0])
            };
            return Err(self.err(format!("{kp_name}: keypoint {row}: {axis} is {value}")));
        }
        if let Some(i) = desc.iter().position(|v| !v.is_finite()) {
            return Err(self.err(format!(
                "{desc_name}: keypoint {}: a value is {}",
                i % n.max(1),
                desc[i]
            )));
        }
        // Before the loops: `D x 0` holds no values whatever D claims.
        if dim > MAX_DIM {
            return Err(self.err(format!(
                "{desc_name}: {dim} dimensions, more than a map holds ({MAX_DIM})"
            )));
        }
        // [D × N] → [N × D].
        let mut descriptors = vec![0.0f32; n * dim];
        for d in 0..dim {
            for k in 0..n {
                descriptors[k * dim + d] = desc[d * n + k];
            }
        }
        let keypoints = kp
            .chunks_exact(2)
            .map(|p| [f64::from(p[0]) + 0.5, f64::from(p[1]) + 0.5])
            .collect();
        Ok(Some(LocalFeatures {
            keypoints,
            descriptors,
            dim,
        }))
    }

    /// Image `name`'s per-keypoint `scales` (hloc's DoG stores them), if the group has them;
    /// `keypoints` of them, finite and positive, or an error naming the dataset.
    #[cfg(feature = "colmap")]
    pub(crate) fn scales(
        &self,
        name: &str,
        datasets: &Datasets,
        keypoints: usize,
    ) -> Result<Option<Vec<f32>>, InputError> {
        let Some(ds) = datasets.get("scales") else {
            return Ok(None);
        };
        let ds_name = format!("{name}/scales");
        let (scales, rows, cols) = self.matrix(&ds_name, ds, usize::MAX)?;
        if rows * cols != keypoints {
            return Err(self.err(format!(
                "{ds_name}: {} values for {keypoints} keypoints",
                rows * cols
            )));
        }
        if let Some(i) = scales.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(self.err(format!(
                "{ds_name}: keypoint {i}: scale {} (finite and positive expected)",
                scales[i]
            )));
        }
        Ok(Some(scales))
    }

    /// Image `name`'s global descriptor (`global_descriptor`, hloc's retrieval features) if
    /// its group has one; NaN or infinite values are an error (they would rank every
    /// database image equal, silently).
    pub fn global(&self, name: &str) -> Result<Option<Vec<f32>>, InputError> {
        match self.datasets(name)? {
            Some(datasets) => self.global_of(name, &datasets),
            None => Ok(None),
        }
    }

    pub(crate) fn global_of(
        &self,
        name: &str,
        datasets: &Datasets,
    ) -> Result<Option<Vec<f32>>, InputError> {
        let Some(ds) = datasets.get("global_descriptor") else {
            return Ok(None);
        };
        let ds_name = format!("{name}/global_descriptor");
        let (values, _, _) = self.matrix(&ds_name, ds, MAX_DIM)?;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(self.err(format!("{ds_name}: value {i} is {}", values[i])));
        }
        Ok(Some(values))
    }
}

#[cfg(feature = "localize")]
mod query {
    use super::{H5Features, InputError};
    use crate::localize::{FeatureSet, QueryFeatures};
    use std::collections::BTreeMap;

    /// Level ids read as pyramid levels (`level<id>_…` datasets): 0 to 31.
    const PYRAMID_LEVELS: u16 = 32;

    impl H5Features {
        /// The query's features, `Ok(None)` if the file has no group for it; descriptors
        /// L2-normalised, as the localizer takes them.
        pub fn features(&self, name: &str) -> Result<Option<QueryFeatures>, InputError> {
            let Some(datasets) = self.datasets(name)? else {
                return Ok(None);
            };
            // `level<id>_keypoints`, ids as the writer spells them, ascending; pyramid levels
            // are 0 to 31 (a larger id is another tool's dataset, and the image's plain
            // `keypoints` then serve every level, as before).
            let levels: BTreeMap<u16, &str> = datasets
                .keys()
                .filter_map(|k| {
                    let digits = k.strip_prefix("level")?.strip_suffix("_keypoints")?;
                    let id: u16 = digits.parse().ok()?;
                    (id.to_string() == digits && id < PYRAMID_LEVELS).then_some((id, digits))
                })
                .collect();
            let set = |prefix: &str, level: Option<u16>| {
                Ok::<_, InputError>(self.local(name, &datasets, prefix)?.map(|l| {
                    let mut set = FeatureSet {
                        level,
                        keypoints: l.keypoints,
                        descriptors: l.descriptors,
                        dim: l.dim,
                    };
                    crate::vector::normalise_rows(&mut set.descriptors, set.dim);
                    set
                }))
            };
            let mut sets = Vec::new();
            for (&id, digits) in &levels {
                sets.extend(set(&format!("level{digits}_"), Some(id))?);
            }
            if sets.is_empty() {
                match set("", None)? {
                    Some(s) => sets.push(s),
                    None => return Ok(None),
                }
            }
            Ok(Some(QueryFeatures {
                sets,
                global: self.global_of(name, &datasets)?,
                model: None,
            }))
        }
    }
}
