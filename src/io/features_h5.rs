//! hloc-style `features.h5` (pure Rust, `hdf5-pure`): one group per image name, readable by
//! hloc, h5py and the HDF5 C library. Layout in `spec/extractor.md`, "features.h5 layout".

use crate::extract::{Features, LevelFeatures};
use crate::format::f16;
use hdf5_pure::{
    AttrValue, Datatype, DatatypeByteOrder, FileBuilder, FinishedGroup, FloatingPointLayout,
    GroupBuilder,
};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
#[cfg(feature = "localize")]
use {
    super::InputError,
    crate::localize::{FeatureSet, NonFiniteValue, QueryFeatures},
    std::collections::HashMap,
};

/// Level ids read as pyramid levels (`level<id>_…` datasets): 0 to 31.
#[cfg(feature = "localize")]
const PYRAMID_LEVELS: u16 = 32;

/// Keypoints in the file are in hloc's convention: the first pixel's centre is (0, 0), so
/// COLMAP's coordinates are these + 0.5 (hloc adds it when it imports into COLMAP).
pub(crate) const KEYPOINT_CONVENTION: &str =
    "pixel centre of the first pixel = (0, 0) (hloc); COLMAP = value + 0.5";

/// What went wrong writing or reading a features file.
#[derive(Debug)]
#[non_exhaustive]
pub enum H5Error {
    /// The HDF5 writer failed.
    Hdf5 {
        /// The file.
        path: PathBuf,
        /// The writer's message.
        reason: String,
    },
    /// Two images map to the same group, or a name cannot be a group path.
    BadName {
        /// The image name.
        name: String,
        /// Why it cannot be a group.
        reason: String,
    },
    /// Writing the file failed.
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// The output cannot be written ([`crate::output`]'s policy or its I/O).
    Output(crate::output::OutputError),
}

impl From<crate::output::OutputError> for H5Error {
    fn from(e: crate::output::OutputError) -> H5Error {
        H5Error::Output(e)
    }
}

impl std::fmt::Display for H5Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            H5Error::Hdf5 { path, reason } => write!(f, "{}: hdf5: {reason}", path.display()),
            H5Error::BadName { name, reason } => write!(f, "image name {name:?}: {reason}"),
            H5Error::Io { path, source } => write!(f, "{}: {source}", path.display()),
            H5Error::Output(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for H5Error {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            // Shown by Display already: the rest of the chain only.
            H5Error::Output(e) => e.source(),
            _ => None,
        }
    }
}

fn f16_type() -> Datatype {
    Datatype::FloatingPoint {
        size: 2,
        byte_order: DatatypeByteOrder::LittleEndian,
        layout: FloatingPointLayout {
            bit_offset: 0,
            bit_precision: 16,
            exponent_location: 10,
            exponent_size: 5,
            mantissa_location: 0,
            mantissa_size: 10,
            exponent_bias: 15,
        },
    }
}

/// `[n × d]` row-major → `[d × n]` little-endian f16 bytes (hloc stores descriptors as
/// `[D × N]`, the layout its networks output).
fn transposed_f16(values: &[f16], n: usize, d: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(n * d * 2);
    for k in 0..d {
        for i in 0..n {
            out.extend_from_slice(&values[i * d + k].to_le_bytes());
        }
    }
    out
}

/// Settings recorded in the file.
#[derive(Debug, Clone)]
pub struct H5Options {
    /// The level whose keypoints/descriptors fill the hloc-standard datasets of each group.
    pub main_level: u16,
    /// Root attributes (model name, hash, contract …), as strings.
    pub attributes: Vec<(String, String)>,
}

/// An image group being assembled: nested groups for names with `/`.
#[derive(Default)]
struct Node<'a> {
    features: Option<&'a Features>,
    children: BTreeMap<String, Node<'a>>,
}

/// Writes `images` (name, features) to `path` ([`crate::output::write_atomic`]).
pub fn write(
    path: &Path,
    images: &[(String, Features)],
    options: &H5Options,
) -> Result<u64, H5Error> {
    let mut root = Node::default();
    for (name, features) in images {
        let parts: Vec<&str> = name.split('/').filter(|p| !p.is_empty()).collect();
        if parts.is_empty() || parts.iter().any(|p| *p == "." || *p == "..") {
            return Err(H5Error::BadName {
                name: name.clone(),
                reason: "not a usable group path".into(),
            });
        }
        let mut node = &mut root;
        for p in parts {
            node = node.children.entry(p.to_string()).or_default();
        }
        if node.features.is_some() {
            return Err(H5Error::BadName {
                name: name.clone(),
                reason: "two images map to the same group".into(),
            });
        }
        // A group that is both an image and a folder is refused in `build_group`.
        node.features = Some(features);
    }
    let mut file = FileBuilder::new();
    file.set_attr(
        "sfp.main_level",
        AttrValue::I64(i64::from(options.main_level)),
    );
    file.set_attr(
        "keypoint_convention",
        AttrValue::String(KEYPOINT_CONVENTION.into()),
    );
    for (k, v) in &options.attributes {
        file.set_attr(k, AttrValue::String(v.clone()));
    }
    for (name, node) in &root.children {
        let group = build_group(file.create_group(name), node, name, options)?;
        file.add_group(group);
    }
    let bytes = file.finish().map_err(|e| H5Error::Hdf5 {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    crate::output::write_atomic(path, |out| {
        std::io::Write::write_all(out, &bytes).map_err(|source| H5Error::Io {
            path: path.to_path_buf(),
            source,
        })
    })?;
    Ok(bytes.len() as u64)
}

/// `node`'s group; `path` is its full group path (the image name), for errors.
fn build_group(
    mut group: GroupBuilder,
    node: &Node<'_>,
    path: &str,
    options: &H5Options,
) -> Result<FinishedGroup, H5Error> {
    if node.features.is_some() && !node.children.is_empty() {
        return Err(H5Error::BadName {
            name: path.to_string(),
            reason: "is both an image and a folder of images".into(),
        });
    }
    if let Some(f) = node.features {
        let main = f
            .level(options.main_level)
            .or_else(|| f.levels.first())
            .ok_or_else(|| H5Error::BadName {
                name: path.to_string(),
                reason: "features with no level".into(),
            })?;
        write_level(&mut group, main, "");
        group
            .create_dataset("image_size")
            .with_i64_data(&[i64::from(f.image_size[0]), i64::from(f.image_size[1])]);
        // Skipped ([`GlobalSize::Skip`](crate::extract::GlobalSize)): no dataset, as hloc's
        // local-feature files have none.
        if !f.global.is_empty() {
            group
                .create_dataset("global_descriptor")
                .with_f32_data(&f.global);
        }
        group.set_attr("level", AttrValue::I64(i64::from(main.level)));
        // Per level as prefixed datasets, not subgroups: hloc's readers load every item of an
        // image group as an array and list every group holding a dataset as an image name.
        for level in &f.levels {
            let prefix = format!("level{}_", level.level);
            write_level(&mut group, level, &prefix);
            let n = level.len();
            group
                .create_dataset(&format!("{prefix}descriptors_short"))
                .with_raw_data(
                    f16_type(),
                    transposed_f16(&level.short, n, level.dim_short),
                    (n * level.dim_short) as u64,
                )
                .with_shape(&[level.dim_short as u64, n as u64]);
            group.set_attr(
                &format!("{prefix}stride"),
                AttrValue::I64(i64::from(level.stride)),
            );
        }
    }
    for (name, child) in &node.children {
        let sub = build_group(
            group.create_group(name),
            child,
            &format!("{path}/{name}"),
            options,
        )?;
        group.add_group(sub);
    }
    Ok(group.finish())
}

/// `{prefix}keypoints` [N×2] f32 (hloc convention), `{prefix}scores` [N] f32,
/// `{prefix}descriptors` [D×N] f16 (full).
fn write_level(group: &mut GroupBuilder, level: &LevelFeatures, prefix: &str) {
    let n = level.len();
    let kps: Vec<f32> = level
        .keypoints
        .iter()
        .flat_map(|k| [k[0] - 0.5, k[1] - 0.5])
        .collect();
    group
        .create_dataset(&format!("{prefix}keypoints"))
        .with_f32_data(&kps)
        .with_shape(&[n as u64, 2]);
    group
        .create_dataset(&format!("{prefix}scores"))
        .with_f32_data(&level.scores)
        .with_shape(&[n as u64]);
    group
        .create_dataset(&format!("{prefix}descriptors"))
        .with_raw_data(
            f16_type(),
            transposed_f16(&level.full, n, level.dim_full),
            (n * level.dim_full) as u64,
        )
        .with_shape(&[level.dim_full as u64, n as u64]);
}

/// Query features from an hloc-style `features.h5` (as `sfpmap extract` writes, or hloc's own
/// extractors): per-level `level<id>_keypoints` / `level<id>_descriptors` when present (SFP),
/// else the image's `keypoints` / `descriptors` for every level. Keypoints are in hloc's
/// convention (first pixel centre at 0) and get +0.5; descriptors are `[D × N]`, f16 or f32.
///
/// The file is read on demand, never whole (hloc's files reach tens of GB): opening reads the
/// superblock, and each query the metadata on its image's path (through a cache of at most
/// [`H5Features::METADATA_CACHE_BYTES`]) and the datasets it uses.
#[cfg(feature = "localize")]
pub struct H5Features {
    file: hdf5_pure::File,
    path: PathBuf,
    /// Bounds every dataset's declared size before it is read (an unwritten dataset of a
    /// declared 2^31 values would otherwise be allocated as its fill value).
    file_len: u64,
}

#[cfg(feature = "localize")]
impl H5Features {
    /// The most bytes of metadata (group indexes, object headers) kept between queries.
    pub const METADATA_CACHE_BYTES: usize = 8 << 20;

    /// Opens a features file and checks its root attributes; groups are read by name as
    /// queries ask for them.
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
        })
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

    fn err(&self, message: String) -> InputError {
        InputError {
            path: self.path.clone(),
            line: None,
            message,
        }
    }

    /// `[rows × cols]` values of the dataset `ds` (`name` in errors): little-endian f16 or
    /// f32, its declared size checked against the file's before anything is read.
    fn matrix(
        &self,
        name: &str,
        ds: &hdf5_pure::Dataset,
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
            return Err(self.err(format!(
                "{name}: values of type {datatype:?} (little-endian f16 or f32 expected)"
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

    /// One feature set from the image's `<prefix>keypoints` and `<prefix>descriptors`
    /// (`datasets`: its group's datasets by name), `None` if either is missing.
    fn set(
        &self,
        name: &str,
        datasets: &HashMap<String, hdf5_pure::Dataset>,
        prefix: &str,
        level: Option<u16>,
    ) -> Result<Option<FeatureSet>, InputError> {
        let (Some(kp), Some(desc)) = (
            datasets.get(&format!("{prefix}keypoints")),
            datasets.get(&format!("{prefix}descriptors")),
        ) else {
            return Ok(None);
        };
        let (kp, n, two) = self.matrix(&format!("{name}/{prefix}keypoints"), kp)?;
        let (desc, dim, n_desc) = self.matrix(&format!("{name}/{prefix}descriptors"), desc)?;
        if two != 2 || n_desc != n {
            return Err(self.err(format!(
                "{name}/{prefix}: {n} keypoints x {two}, descriptors {dim} x {n_desc}"
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
        let mut set = FeatureSet {
            level,
            keypoints,
            descriptors,
            dim,
        };
        // The localizer's rule (`FeatureSet::check_finite`), before normalisation turns an
        // infinity into NaN; named by dataset and keypoint as the file holds them.
        if let Err(e) = set.check_finite() {
            return Err(self.err(match e.what {
                NonFiniteValue::Keypoint { row, axis, value } => {
                    format!("{name}/{prefix}keypoints: keypoint {row}: {axis} is {value}")
                }
                NonFiniteValue::Descriptor { row, value } => {
                    format!("{name}/{prefix}descriptors: keypoint {row}: a value is {value}")
                }
                _ => format!("{name}/{prefix}: {e}"),
            }));
        }
        crate::vector::normalise_rows(&mut set.descriptors, dim);
        Ok(Some(set))
    }

    /// The query's features, `Ok(None)` if the file has no group for it. The image's group
    /// is resolved once and its datasets listed once: a query costs one path lookup, whatever
    /// the number of images or levels.
    pub fn features(&self, name: &str) -> Result<Option<QueryFeatures>, InputError> {
        // No such group (or a dataset of that name): the file has no features for it.
        let Ok(group) = self.file.group(name) else {
            return Ok(None);
        };
        let datasets: HashMap<String, hdf5_pure::Dataset> = group
            .iter_datasets()
            .map_err(|e| self.err(format!("{name}: {e}")))?
            .collect();
        // `level<id>_keypoints`, ids as the writer spells them, ascending; pyramid levels are
        // 0 to 31 (a larger id is another tool's dataset, and the image's plain `keypoints`
        // then serve every level, as before).
        let levels: BTreeMap<u16, &str> = datasets
            .keys()
            .filter_map(|k| {
                let digits = k.strip_prefix("level")?.strip_suffix("_keypoints")?;
                let id: u16 = digits.parse().ok()?;
                (id.to_string() == digits && id < PYRAMID_LEVELS).then_some((id, digits))
            })
            .collect();
        let mut sets = Vec::new();
        for (&id, digits) in &levels {
            if let Some(set) = self.set(name, &datasets, &format!("level{digits}_"), Some(id))? {
                sets.push(set);
            }
        }
        if sets.is_empty() {
            match self.set(name, &datasets, "", None)? {
                Some(set) => sets.push(set),
                None => return Ok(None),
            }
        }
        let global = datasets
            .get("global_descriptor")
            .map(|ds| self.matrix(&format!("{name}/global_descriptor"), ds))
            .transpose()?
            .map(|(v, _, _)| v);
        // A NaN would rank every database image equal, silently.
        if let Err(e) = crate::localize::check_global_finite(global.as_deref()) {
            return Err(self.err(format!("{name}/{e}")));
        }
        Ok(Some(QueryFeatures {
            sets,
            global,
            model: None,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn features(n: usize) -> Features {
        let level = |id: u16, stride: u32, ds: usize, df: usize| LevelFeatures {
            level: id,
            stride,
            keypoints: (0..n)
                .map(|i| [i as f32 + 0.5, 2.0 * i as f32 + 0.5])
                .collect(),
            scores: (0..n).map(|i| 0.5 + i as f32 / 100.0).collect(),
            dim_short: ds,
            dim_full: df,
            short: (0..n * ds).map(|i| f16::from_f32(i as f32 / 8.0)).collect(),
            full: (0..n * df)
                .map(|i| f16::from_f32(i as f32 / 16.0))
                .collect(),
        };
        Features {
            image_size: [64, 48],
            levels: vec![level(0, 2, 2, 5), level(1, 4, 3, 3)],
            global: vec![0.6, 0.8],
        }
    }

    /// `features.h5` in `dir` with a top-level and a nested image, main level 1.
    fn two_images(dir: &Path) -> (PathBuf, Vec<(String, Features)>, H5Options) {
        let path = dir.join("features.h5");
        let images = vec![
            ("a.jpg".to_string(), features(3)),
            ("sub/b.png".to_string(), features(4)),
        ];
        let options = H5Options {
            main_level: 1,
            attributes: vec![("sfp.model".into(), "test".into())],
        };
        write(&path, &images, &options).unwrap();
        (path, images, options)
    }

    #[test]
    fn round_trip_nested_names_and_transposed_descriptors() {
        let dir = tempfile::tempdir().unwrap();
        let (path, _, options) = two_images(dir.path());
        let file = hdf5_pure::File::open(&path).unwrap();
        let kp = file.dataset("sub/b.png/keypoints").unwrap();
        assert_eq!(kp.shape().unwrap(), vec![4, 2]);
        let v = kp.read_f32().unwrap();
        assert_eq!(&v[..4], &[0.0, 0.0, 1.0, 2.0]);
        let d = file.dataset("a.jpg/level0_descriptors").unwrap();
        assert_eq!(d.shape().unwrap(), vec![5, 3]);
        let raw = d.read_raw().unwrap();
        let vals: Vec<f32> = raw
            .chunks_exact(2)
            .map(|b| f16::from_le_bytes([b[0], b[1]]).to_f32())
            .collect();
        // Row k of the file = dimension k over the keypoints: [k, 5 + k, 10 + k] / 16.
        assert_eq!(&vals[..3], &[0.0, 5.0 / 16.0, 10.0 / 16.0]);
        let main = file.dataset("a.jpg/descriptors").unwrap();
        assert_eq!(main.shape().unwrap(), vec![3, 3]);
        let size = file.dataset("a.jpg/image_size").unwrap();
        assert_eq!(size.shape().unwrap(), vec![2]);
        assert!(write(
            &path,
            &[("x".into(), features(1)), ("x".into(), features(1))],
            &options
        )
        .is_err());
    }

    /// The writer and the query reader ([`H5Features`]) agree: every level's
    /// keypoints in sfpmap's pixel convention, its descriptors (normalised, as the reader
    /// hands them out), and the global descriptor.
    #[cfg(feature = "localize")]
    #[test]
    fn the_query_reader_reads_back_what_the_writer_wrote() {
        let dir = tempfile::tempdir().unwrap();
        let (path, images, _) = two_images(dir.path());
        let reader = H5Features::open(&path).unwrap();
        for (name, written) in &images {
            let read = reader.features(name).unwrap().expect("the image is there");
            assert_eq!(read.global.as_deref(), Some(&written.global[..]));
            assert_eq!(read.sets.len(), written.levels.len());
            for (set, level) in read.sets.iter().zip(&written.levels) {
                assert_eq!(set.level, Some(level.level));
                assert_eq!(set.dim, level.dim_full);
                let expected: Vec<[f64; 2]> = level
                    .keypoints
                    .iter()
                    .map(|k| [f64::from(k[0]), f64::from(k[1])])
                    .collect();
                assert_eq!(set.keypoints, expected, "{name} level {}", level.level);
                for (i, row) in set.descriptors.chunks(set.dim).enumerate() {
                    let full: Vec<f32> = level.full[i * set.dim..(i + 1) * set.dim]
                        .iter()
                        .map(|v| v.to_f32())
                        .collect();
                    let norm = full.iter().map(|v| v * v).sum::<f32>().sqrt();
                    for (r, f) in row.iter().zip(&full) {
                        let want = if norm > 0.0 { f / norm } else { 0.0 };
                        assert!(
                            (r - want).abs() < 1e-6,
                            "{name} keypoint {i}: {r} vs {want}"
                        );
                    }
                }
            }
        }
        assert!(reader.features("missing.jpg").unwrap().is_none());
    }

    #[test]
    fn bad_names_are_named_in_full() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.h5");
        let options = H5Options {
            main_level: 0,
            attributes: vec![],
        };
        // Either order: the group "a/b" is an image and holds one.
        for names in [["a/b", "a/b/c.jpg"], ["a/b/c.jpg", "a/b"]] {
            let images: Vec<_> = names.iter().map(|n| (n.to_string(), features(1))).collect();
            let err = write(&path, &images, &options).unwrap_err().to_string();
            assert_eq!(
                err, "image name \"a/b\": is both an image and a folder of images",
                "{names:?}"
            );
        }
        let mut empty = features(1);
        empty.levels.clear();
        let err = write(&path, &[("x/y.jpg".into(), empty)], &options)
            .unwrap_err()
            .to_string();
        assert_eq!(err, "image name \"x/y.jpg\": features with no level");
        assert!(!path.exists());
    }

    #[test]
    fn empty_levels_are_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.h5");
        write(
            &path,
            &[("e.jpg".to_string(), features(0))],
            &H5Options {
                main_level: 0,
                attributes: vec![],
            },
        )
        .unwrap();
        let file = hdf5_pure::File::open(&path).unwrap();
        assert_eq!(
            file.dataset("e.jpg/keypoints").unwrap().shape().unwrap(),
            vec![0, 2]
        );
    }
}
