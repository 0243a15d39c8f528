//! hloc-style `features.h5` (pure Rust, `hdf5-pure`): one group per image name, readable by
//! hloc, h5py and the HDF5 C library. Layout in `spec/extractor.md`, "features.h5 layout".
//! The writer (`sfpmap extract`) is in `write.rs`, the reader ([`H5Features`]: `convert
//! --features`, `localize --features`) in `read.rs`.

mod read;
#[cfg(feature = "onnx")]
mod write;

pub use read::H5Features;
#[cfg(feature = "onnx")]
pub use write::{write, H5Error, H5Options};

#[cfg(all(test, feature = "onnx"))]
mod tests {
    use super::*;
    use crate::extract::{Features, LevelFeatures};
    use crate::format::f16;
    use std::path::{Path, PathBuf};

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

    /// A name with empty components is the group HDF5 reads under it (h5py drops them, as
    /// the writer does): `sub//b.png` and `/a.jpg` find the groups `sub/b.png` and `a.jpg`.
    #[test]
    fn empty_name_components_are_skipped_as_hdf5_skips_them() {
        let dir = tempfile::tempdir().unwrap();
        let (path, _, _) = two_images(dir.path());
        let h5 = H5Features::open(&path).unwrap();
        for (name, same) in [("sub//b.png", "sub/b.png"), ("/a.jpg", "a.jpg")] {
            let (a, b) = (h5.global(name).unwrap(), h5.global(same).unwrap());
            assert!(a.is_some() && a == b, "{name}");
        }
        assert_eq!(h5.global("sub/x.png").unwrap(), None);
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
