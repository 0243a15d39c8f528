//! Writing hloc-style `features.h5` (`sfpmap extract`).

use crate::extract::{Features, LevelFeatures};
use crate::format::f16;
use hdf5_pure::{
    AttrValue, Datatype, DatatypeByteOrder, FileBuilder, FinishedGroup, FloatingPointLayout,
    GroupBuilder,
};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

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
            H5Error::Hdf5 { path, reason } => {
                write!(f, "{}: hdf5: {reason}", crate::escape::path(path))
            }
            H5Error::BadName { name, reason } => write!(f, "image name {name:?}: {reason}"),
            H5Error::Io { path, source } => write!(f, "{}: {source}", crate::escape::path(path)),
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
