//! The SFP extractor (feature `onnx`): an ONNX model of the `sfp-extractor/1` or `/2` contract
//! (`spec/extractor.md`) run with ONNX Runtime, turned into per-level keypoints, `short` and
//! `full` descriptors and a global descriptor.
//!
//! ```no_run
//! # fn main() -> Result<(), sfpmap::extract::ExtractError> {
//! use sfpmap::extract::{DetectOptions, Extractor, ExtractorOptions};
//! let mut extractor = Extractor::new(&ExtractorOptions::default(), &sfpmap::progress::Silent)?;
//! let input = sfpmap::extract::image::load(
//!     "query.jpg".as_ref(), extractor.contract().gray_weights, None)?;
//! let features = extractor.extract(&input, &DetectOptions::default())?;
//! println!("{} keypoints on level 2", features.level(2).map_or(0, |l| l.len()));
//! # Ok(()) }
//! ```
//!
//! - [`runtime`]: finding/fetching `libonnxruntime.so.1.31.1`, one process-wide environment.
//! - [`contract`]: the model's metadata, checked.
//! - [`image`]: JPEG/PNG → grey input.
//! - `keypoints.rs`: NMS, sub-pixel refinement, bilinear sampling (crate-private).
//!
//! Turning a model and its images into an SFP map is the `build` module's
//! (`build::convert_with_images`): extraction knows nothing of maps being built.

pub mod contract;
mod dkd;
mod global;
pub mod image;
mod image_refine;
pub(crate) mod keypoints;
pub mod runtime;

pub use self::image_refine::ImageRefine;

use self::contract::{Contract, DescriptorHead, Detector};
pub use self::global::{GlobalSize, GLOBAL_MAX_SIDE, GLOBAL_MIN_SIDE};
use self::image::GrayInput;
use self::keypoints::{FeatureMap, ScoreMap};
use crate::format::f16;
use crate::progress::Reporter;
use half::slice::HalfFloatSliceExt;
use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;
use ort::value::{Tensor, TensorRef};
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard};

/// The default model, embedded so the CLI works from any folder without `--model`: sfp-v3,
/// sfp-v2's network with its keypoints refined on the image and level 2's found on level 0's
/// score map (`models/sfp-v3.md`: more precise than sfp-v2 on every shared and held-out scene
/// at about its bytes, with its recall and retrieval).
pub static DEFAULT_MODEL: &[u8] = include_bytes!("../../models/sfp-v3.onnx");
/// How the embedded model is named in errors and provenance.
pub(crate) const DEFAULT_MODEL_NAME: &str = "models/sfp-v3.onnx (embedded)";
/// How a built-in model's name ends ([`builtin_name`]).
const BUILTIN_SUFFIX: &str = " (embedded)";

/// The models built into the library, by their `sfp.model_name`; the first is
/// [`DEFAULT_MODEL`]. `sfp-v1` was the default until sfp-v2 (`models/sfp-v1.md`), `sfp-v2`
/// until sfp-v3 (`models/sfp-v2.md`: sfp-v1 distilled into a one-convolution stem), `sfp-v2s`
/// is sfp-v1 distilled into a two-convolution strided stem (`models/sfp-v2s.md`), `aliked-n16`
/// is ALIKED-N16 (BSD-3-Clause; `models/aliked-n16.md`: one level of 128-d descriptors from
/// its SDDH head, no global descriptor), `sfp-v3` is sfp-v2's network with its keypoints
/// refined on the image and level 2's found on level 0's score map (`sfp-extractor/3`,
/// `models/sfp-v3.md`). A map records its model's
/// name, so `localize` finds the model a map was made with here; `--model NAME` picks one by
/// name.
pub static BUILTIN_MODELS: &[(&str, &[u8])] = &[
    ("sfp-v3", DEFAULT_MODEL),
    ("sfp-v2", include_bytes!("../../models/sfp-v2.onnx")),
    ("sfp-v1", include_bytes!("../../models/sfp-v1.onnx")),
    ("sfp-v2s", include_bytes!("../../models/sfp-v2s.onnx")),
    ("aliked-n16", include_bytes!("../../models/aliked-n16.onnx")),
];

/// How the built-in model `name` is named in errors and provenance.
fn builtin_name(name: &str) -> String {
    format!("models/{name}.onnx{BUILTIN_SUFFIX}")
}

/// The built-in model named `name` (`sfp.model_name`), if there is one.
pub(crate) fn builtin_model(name: &str) -> Option<&'static [u8]> {
    BUILTIN_MODELS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, bytes)| *bytes)
}

/// The built-in models' names, for messages: "sfp-v3, sfp-v2, sfp-v1, sfp-v2s, aliked-n16".
#[cfg(feature = "localize")]
pub(crate) fn builtin_model_names() -> String {
    BUILTIN_MODELS
        .iter()
        .map(|(n, _)| *n)
        .collect::<Vec<_>>()
        .join(", ")
}

/// What can go wrong while extracting.
#[derive(Debug)]
#[non_exhaustive]
pub enum ExtractError {
    /// Reading a model or image file failed.
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },
    /// ONNX Runtime is not where discovery looked.
    RuntimeNotFound {
        /// The places looked in, in order.
        searched: Vec<PathBuf>,
    },
    /// ONNX Runtime could not be fetched, loaded or started.
    Runtime {
        /// The library, when one was found.
        path: Option<PathBuf>,
        /// ONNX Runtime's or the loader's message.
        reason: String,
    },
    /// The model file is not an ONNX model ORT can load.
    Model {
        /// The model (path or built-in name).
        model: String,
        /// ONNX Runtime's message.
        reason: String,
    },
    /// The model's metadata does not state a contract this extractor implements.
    Contract {
        /// The model (path or built-in name).
        model: String,
        /// What its metadata lacks or breaks.
        reason: String,
    },
    /// An image could not be decoded.
    Image {
        /// The image file.
        path: PathBuf,
        /// The decoder's error.
        source: ::image::ImageError,
    },
    /// Running the model failed, or it returned outputs that break its contract; `image` is
    /// the file the input came from, when the caller says ([`ExtractError::on_image`]).
    Inference {
        /// The model (path or built-in name).
        model: String,
        /// The image file, when known.
        image: Option<PathBuf>,
        /// ONNX Runtime's message, or the broken rule.
        reason: String,
    },
}

impl ExtractError {
    /// Names the image file an [`ExtractError::Inference`] happened on (other errors, and
    /// one that already names an image, are returned as they are).
    pub fn on_image(self, path: &Path) -> Self {
        match self {
            ExtractError::Inference {
                model,
                image: None,
                reason,
            } => ExtractError::Inference {
                model,
                image: Some(path.to_path_buf()),
                reason,
            },
            other => other,
        }
    }
}

/// Paths, model names and the reasons a model file's metadata gives may hold anything:
/// the whole text is escaped ([`crate::escape`]), so it stays one line.
impl fmt::Display for ExtractError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let text = Unescaped(self).to_string();
        f.write_str(&crate::escape::escape_control_characters(&text))
    }
}

/// [`ExtractError`]'s text before its control characters are escaped.
struct Unescaped<'a>(&'a ExtractError);

impl fmt::Display for Unescaped<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            ExtractError::Io { path, source } => write!(f, "{}: {source}", path.display()),
            ExtractError::RuntimeNotFound { searched } => {
                write!(
                    f,
                    "ONNX Runtime {} not found (looked at ORT_DYLIB_PATH",
                    runtime::ORT_VERSION
                )?;
                for p in searched {
                    write!(f, ", {}", p.display())?;
                }
                write!(
                    f,
                    "); run `sfpmap setup` (python3 -m pip download onnxruntime=={}) or set ORT_DYLIB_PATH to a {}",
                    runtime::ORT_VERSION,
                    runtime::LIB_NAME
                )
            }
            ExtractError::Runtime {
                path: Some(path),
                reason,
            } => write!(f, "ONNX Runtime {}: {reason}", path.display()),
            ExtractError::Runtime { path: None, reason } => write!(f, "ONNX Runtime: {reason}"),
            ExtractError::Model { model, reason } => {
                write!(f, "{model}: not a loadable ONNX model: {reason}")
            }
            ExtractError::Contract { model, reason } => write!(f, "{model}: {reason}"),
            // Some decoders end their message with a newline: kept to one line.
            ExtractError::Image { path, source } => write!(
                f,
                "{}: {}",
                path.display(),
                source.to_string().trim_end().replace('\n', "; ")
            ),
            ExtractError::Inference {
                model,
                image: Some(image),
                reason,
            } => write!(f, "{}: {model}: {reason}", image.display()),
            ExtractError::Inference {
                model,
                image: None,
                reason,
            } => write!(f, "{model}: {reason}"),
        }
    }
}

/// No `source()`: every message already contains its cause (`Io` and `Image` print theirs
/// after the path), and a chain printed with `{:#}` would repeat it.
impl std::error::Error for ExtractError {}

/// How the extractor is built.
#[derive(Debug, Clone)]
pub struct ExtractorOptions {
    /// A model file; or, when no file has that path, the name of a built-in model
    /// ([`BUILTIN_MODELS`]: `sfp-v2s`); `None` = the embedded [`DEFAULT_MODEL`].
    pub model: Option<PathBuf>,
    /// ONNX Runtime intra-op threads (spinning is off), and the threads that sample
    /// keypoints and descriptors ([`Extractor::features`]).
    pub threads: usize,
}

impl Default for ExtractorOptions {
    fn default() -> Self {
        ExtractorOptions {
            model: None,
            threads: 2,
        }
    }
}

/// Keypoint selection; `None` fields take the model's defaults (`sfp.default_*`).
#[derive(Debug, Clone, Default)]
pub struct DetectOptions {
    /// Minimum detection score, on every level (`None`: each level's
    /// `sfp.default_threshold`).
    pub threshold: Option<f32>,
    /// Non-maximum suppression radius, in cells of the level's score map.
    pub nms_radius: Option<u32>,
    /// Cap per level, in level order; one value applies to every level.
    pub max_keypoints: Option<Vec<usize>>,
    /// The keypoints' refinement (`spec/extractor.md`): coarse to fine for levels from 2 on
    /// (step 4) and, for a model of `sfp-extractor/2` or `/3`, on the image (step 5); `None` = on.
    pub refine: Option<bool>,
    /// The image size the global descriptor is computed at; the default is
    /// [`GLOBAL_MAX_SIDE`]. A query's must be its map's ([`GlobalSize::of_map`]).
    pub global: GlobalSize,
}

impl DetectOptions {
    /// Why these options cannot run, if they cannot: a threshold that is not a score
    /// ([`crate::ranges::SCORE`]), an NMS radius over [`contract::MAX_NMS_RADIUS`] cells, a
    /// keypoint cap outside 1 to [`contract::MAX_KEYPOINTS`]: the ranges the CLI's flags and a
    /// model's defaults are held to, for callers that build options themselves (Python).
    pub fn check(&self) -> Result<(), String> {
        if let Some(t) = self.threshold {
            crate::ranges::SCORE
                .check(t.into())
                .map_err(|expected| format!("threshold {t}: {expected}"))?;
        }
        if let Some(r) = self.nms_radius.filter(|&r| r > contract::MAX_NMS_RADIUS) {
            return Err(format!(
                "nms_radius {r}: 0 to {} cells",
                contract::MAX_NMS_RADIUS
            ));
        }
        let caps = self.max_keypoints.as_deref().unwrap_or_default();
        if let Some(n) = caps
            .iter()
            .find(|&&n| !(1..=contract::MAX_KEYPOINTS).contains(&n))
        {
            return Err(format!(
                "max_keypoints {n}: 1 to {} a level",
                contract::MAX_KEYPOINTS
            ));
        }
        Ok(())
    }
}

/// The first level (index) whose keypoints are moved to the strongest cell of the next finer
/// level's score map within half a cell (`spec/extractor.md`, "Coarse-to-fine refinement").
/// On the held-out viewpoint pairs of `python/eval_homography.py` (sfp-v1) it raises level
/// 2's MMA@3 from 0.56 to 0.77 and level 3's from 0.22 to 0.53; level 1, refined on level 0,
/// gains at 1 px but loses repeatability, so it is left as detected.
pub(crate) const REFINE_FROM_LEVEL: usize = 2;

/// The finest level level `i`'s keypoints are refined down to (the level they are detected
/// on, `Contract::detect_levels`, itself: not refined): with `refine` (the extractors'
/// option, on by default), keypoints detected on levels from [`REFINE_FROM_LEVEL`] on,
/// walking down to the model's `sfp.refine_to_level`; never a descriptor head's.
pub(crate) fn refined_to(c: &Contract, i: usize, refine: bool) -> usize {
    let d = c.detect_levels[i];
    if refine && c.descriptor_head != DescriptorHead::Sddh && d >= REFINE_FROM_LEVEL.max(1) {
        keypoints::finest_refined_level(c.refine_to_level, d)
    } else {
        d
    }
}

/// A bilinear sample of one full dimension at a keypoint, in the image refinement's
/// multiply-adds: four reads from another channel plane, mostly cache misses, about 100
/// (measured on sfp-v3's four levels at 640×480). [`Extractor::features`] shares levels out
/// among threads by it.
const SAMPLE_WORK: usize = 100;

/// Level `i`'s detector peaks (steps 1–2: NMS, the level's threshold, at most `max`), in
/// cells of the level it is detected on (`Contract::detect_levels`); cheap next to placing
/// and describing them. `convert --images --snap` and
/// `--triangulate` place them too ([`placed`]).
pub(crate) fn level_peaks(
    c: &Contract,
    dense: &Dense,
    i: usize,
    max: usize,
    options: &DetectOptions,
) -> Vec<keypoints::Peak> {
    let threshold = options.threshold.unwrap_or(c.default_thresholds[i]);
    let radius = options.nms_radius.unwrap_or(c.default_nms_radius) as usize;
    // `sfp.detect_level` (`/3`): the score map this level's keypoints are found on.
    let level = &dense.levels[c.detect_levels[i]];
    match c.detector {
        Detector::Nms => keypoints::detect(level.score_map(), radius, threshold, max),
        Detector::Dkd => dkd::detect(level.score_map(), radius, threshold, max),
    }
}

/// Level `i`'s `peaks` in input pixels (pixel-index convention), refined coarse to fine
/// (step 4) and on the image (step 5) where the model and `options` ask for it (not for a
/// descriptor head, whose head takes the detected positions).
pub(crate) fn placed(
    c: &Contract,
    dense: &Dense,
    i: usize,
    peaks: &[keypoints::Peak],
    options: &DetectOptions,
) -> Vec<(f32, f32)> {
    // The peaks are cells of the level they were detected on; coarse-to-fine refinement
    // walks down from there, the image refinement is level `i`'s own.
    let d = c.detect_levels[i];
    let s = dense.levels[d].stride as f32;
    let mut px: Vec<(f32, f32)> = peaks.iter().map(|p| (p.x * s, p.y * s)).collect();
    let finest = refined_to(c, i, options.refine.unwrap_or(true));
    let finer: Vec<(f32, ScoreMap<'_>)> = (finest..d)
        .rev()
        .map(|j| (dense.levels[j].stride as f32, dense.levels[j].score_map()))
        .collect();
    keypoints::refine_down(&mut px, s, &finer);
    if options.refine.unwrap_or(true) {
        let refine = c.image_refine.get(i).copied().flatten();
        debug_assert!(
            refine.is_none() || dense.image().is_some(),
            "Extractor::run keeps the image of a model that refines on it"
        );
        if let (Some(r), Some(image)) = (refine, dense.image()) {
            let mut refiner = image_refine::Refiner::new(r);
            for p in px.iter_mut() {
                *p = refiner.refine(image, p.0, p.1);
            }
        }
    }
    px
}

/// The inputs of a descriptor head's branch (`sfp.descriptor_head = sddh`): a `feat_0` and
/// `[N, 2]` keypoints (input pixels, pixel-index convention).
const SDDH_INPUTS: [&str; 2] = ["features", "keypoints"];
/// The output of a descriptor head's branch: `[N, dims[0]]`, L2-normalised.
const SDDH_OUTPUT: &str = "descriptors";

/// What the describe branch is fed while the dense branch runs: ORT runs every node of the
/// graph each time, so the branch not wanted gets an input that costs nothing (a 4x4 map, one
/// keypoint at its centre).
fn sddh_placeholders(dim: usize) -> Result<(Tensor<f32>, Tensor<f32>), String> {
    let features = Tensor::from_array(([1usize, dim, 4, 4], vec![0.0f32; dim * 16]))
        .map_err(|e| e.to_string())?;
    let keypoints =
        Tensor::from_array(([1usize, 2], vec![1.5f32, 1.5])).map_err(|e| e.to_string())?;
    Ok((features, keypoints))
}

/// The model file an extractor runs, for provenance.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelInfo {
    /// The path given, or `models/NAME.onnx (embedded)` for a built-in model.
    pub name: String,
    /// The file's length.
    pub bytes: u64,
    /// XXH3-64 of the file, hex (as map provenance stores it).
    pub xxh3: String,
}

/// One level's dense outputs for one image.
#[derive(Debug, Clone)]
pub struct DenseLevel {
    /// Input pixels per cell.
    pub stride: u32,
    /// Feature channels.
    pub channels: usize,
    /// Rows of cells.
    pub height: usize,
    /// Columns of cells.
    pub width: usize,
    /// `[channels × height × width]`.
    pub feat: Vec<f32>,
    /// `[height × width]`.
    pub score: Vec<f32>,
}

impl DenseLevel {
    pub(crate) fn feature_map(&self) -> FeatureMap<'_> {
        FeatureMap {
            channels: self.channels,
            height: self.height,
            width: self.width,
            values: &self.feat,
        }
    }

    pub(crate) fn score_map(&self) -> ScoreMap<'_> {
        ScoreMap {
            height: self.height,
            width: self.width,
            values: &self.score,
        }
    }

    /// Appends the L2-normalised features at pixel (x, y) of the model input (pixel-index
    /// convention: the first pixel's centre is 0).
    pub fn descriptor_at(&self, x: f32, y: f32, out: &mut Vec<f32>) {
        let start = out.len();
        out.resize(start + self.channels, 0.0);
        self.descriptor_into(x, y, &mut out[start..]);
    }

    /// [`DenseLevel::descriptor_at`] into `out[..channels]`.
    pub fn descriptor_into(&self, x: f32, y: f32, out: &mut [f32]) {
        let s = self.stride as f32;
        let out = &mut out[..self.channels];
        keypoints::sample_into(self.feature_map(), x / s, y / s, out);
        crate::vector::l2_normalise(out);
    }

    /// The score bilinearly sampled at pixel (x, y) of the model input (pixel-index convention).
    pub fn score_at(&self, x: f32, y: f32) -> f32 {
        let s = self.stride as f32;
        keypoints::bilinear_at(self.score_map(), x / s, y / s)
    }
}

/// The network's outputs for one image.
#[derive(Debug, Clone)]
pub struct Dense {
    /// Size of the model input (after any resize).
    pub input_size: [usize; 2],
    /// Input pixel → original pixel factor per axis.
    pub scale: [f32; 2],
    /// Each level, in the model's order.
    pub levels: Vec<DenseLevel>,
    /// L2-normalised global descriptor.
    pub global: Vec<f32>,
    /// The grey input the network ran on (`input_size`), kept only for a model whose
    /// keypoints are refined on the image (`sfp-extractor/2` and `/3`, step 5); else empty.
    pub(crate) image: Vec<f32>,
}

impl Dense {
    /// The input the network ran on, where it was kept (a model that refines on the image).
    pub(crate) fn image(&self) -> Option<image_refine::Plane<'_>> {
        let [width, height] = self.input_size;
        (!self.image.is_empty() && self.image.len() == width * height).then_some(
            image_refine::Plane {
                width,
                height,
                values: &self.image,
            },
        )
    }

    /// A COLMAP-convention pixel of the original image → pixel-index coordinates of the input.
    pub fn input_pixel(&self, colmap_xy: [f32; 2]) -> [f32; 2] {
        [
            colmap_xy[0] / self.scale[0] - 0.5,
            colmap_xy[1] / self.scale[1] - 0.5,
        ]
    }

    /// Pixel-index coordinates (x, y) of the input → a COLMAP-convention pixel of the original
    /// image: [`Dense::input_pixel`]'s inverse.
    pub fn colmap_pixel(&self, x: f32, y: f32) -> [f32; 2] {
        [(x + 0.5) * self.scale[0], (y + 0.5) * self.scale[1]]
    }

    /// The `full` descriptor of level `i` at input pixel (x, y): levels i.. sampled, each part
    /// L2-normalised, concatenated and normalised again (`spec/extractor.md`).
    pub fn full_descriptor_at(&self, i: usize, x: f32, y: f32, out: &mut Vec<f32>) {
        let start = out.len();
        self.parts_at(i, x, y, out);
        crate::vector::l2_normalise(&mut out[start..]);
    }

    /// [`Dense::full_descriptor_at`] before its last normalisation: levels i.. sampled, each
    /// part L2-normalised, concatenated. The first part (`levels[i].channels` values) is
    /// level i's own descriptor, [`DenseLevel::descriptor_at`].
    pub fn parts_at(&self, i: usize, x: f32, y: f32, out: &mut Vec<f32>) {
        let start = out.len();
        let n: usize = self.levels[i..].iter().map(|l| l.channels).sum();
        out.resize(start + n, 0.0);
        self.parts_into(i, x, y, &mut out[start..]);
    }

    /// [`Dense::parts_at`] into `out[..]` (the sum of levels i..'s channels).
    fn parts_into(&self, i: usize, x: f32, y: f32, out: &mut [f32]) {
        let mut at = 0;
        for level in &self.levels[i..] {
            level.descriptor_into(x, y, &mut out[at..at + level.channels]);
            at += level.channels;
        }
    }
}

/// One level's keypoints and descriptors.
#[derive(Debug, Clone, PartialEq)]
pub struct LevelFeatures {
    /// Level id (`sfp.level_ids`).
    pub level: u16,
    /// Input pixels per cell of the level's maps.
    pub stride: u32,
    /// (x, y) in the original image, COLMAP convention (top-left corner of the first pixel
    /// is 0, its centre 0.5).
    pub keypoints: Vec<[f32; 2]>,
    /// Detection score of each keypoint.
    pub scores: Vec<f32>,
    /// Dimensions of `short`.
    pub dim_short: usize,
    /// Dimensions of `full`.
    pub dim_full: usize,
    /// `[keypoints × dim_short]`, L2-normalised.
    pub short: Vec<f16>,
    /// `[keypoints × dim_full]`, L2-normalised; its first `dim_short` values are `short`
    /// times a constant.
    pub full: Vec<f16>,
}

impl LevelFeatures {
    /// How many keypoints.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }
}

/// Everything extracted from one image.
#[derive(Debug, Clone, PartialEq)]
pub struct Features {
    /// (width, height) of the image file.
    pub image_size: [u32; 2],
    /// Each level's features, in the model's order.
    pub levels: Vec<LevelFeatures>,
    /// L2-normalised. [`Extractor::extract`]'s is at [`DetectOptions::global`]'s size (empty
    /// when skipped); [`Extractor::features`]'s is its inference's own.
    pub global: Vec<f32>,
}

impl Features {
    /// The features of level `level` (`sfp.level_ids`), if the model has it.
    pub fn level(&self, level: u16) -> Option<&LevelFeatures> {
        self.levels.iter().find(|l| l.level == level)
    }

    /// Keypoints over all levels.
    pub fn num_keypoints(&self) -> usize {
        self.levels.iter().map(LevelFeatures::len).sum()
    }
}

/// A loaded model with its session.
pub struct Extractor {
    /// Locked for each inference: [`Extractor::features`] runs a descriptor head's graph from
    /// `&self` (ORT's `run` takes `&mut`).
    session: Mutex<Session>,
    contract: Contract,
    model: ModelInfo,
    /// `ExtractorOptions::threads`: ORT's intra-op threads, and the threads that sample
    /// descriptors in [`Extractor::features`].
    threads: usize,
}

impl fmt::Debug for Extractor {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Extractor")
            .field("model", &self.model)
            .field("contract", &self.contract.model_name)
            .finish_non_exhaustive()
    }
}

fn read_model(
    path: Option<&Path>,
) -> Result<(std::borrow::Cow<'static, [u8]>, String), ExtractError> {
    match path {
        None => Ok((DEFAULT_MODEL.into(), DEFAULT_MODEL_NAME.to_string())),
        Some(p) => {
            // A file wins over a built-in name (a model file may well be called `sfp-v1`); the
            // name applies only where nothing at all is at that path.
            let absent = matches!(std::fs::symlink_metadata(p), Err(e) if e.kind() == std::io::ErrorKind::NotFound);
            if let Some(n) = p.to_str().filter(|_| absent) {
                if let Some(bytes) = builtin_model(n) {
                    return Ok((bytes.into(), builtin_name(n)));
                }
            }
            let bytes = crate::input::read_regular(p).map_err(|e| ExtractError::Io {
                path: p.to_path_buf(),
                source: e.into(),
            })?;
            Ok((bytes.into(), p.display().to_string()))
        }
    }
}

impl Extractor {
    /// Loads the runtime (fetching it on first need), the model, and checks its contract.
    pub fn new(options: &ExtractorOptions, reporter: &dyn Reporter) -> Result<Self, ExtractError> {
        Self::new_spinning(options, false, reporter)
    }

    /// [`Extractor::new`], with the inference threads spinning between images when `spin`
    /// (see [`crate::session::SessionBuilder::extractor_spinning`]).
    pub(crate) fn new_spinning(
        options: &ExtractorOptions,
        spin: bool,
        reporter: &dyn Reporter,
    ) -> Result<Self, ExtractError> {
        let (bytes, name) = read_model(options.model.as_deref())?;
        Self::from_model(bytes, name, options.threads, spin, reporter)
    }

    /// The built-in model `name` ([`BUILTIN_MODELS`]), never a file: what `localize` runs
    /// for a map made with it. `None` when no built-in model has that name.
    pub fn builtin(
        name: &str,
        threads: usize,
        reporter: &dyn Reporter,
    ) -> Option<Result<Self, ExtractError>> {
        Self::builtin_spinning(name, threads, false, reporter)
    }

    /// [`Extractor::builtin`], spinning as [`Extractor::new_spinning`].
    pub(crate) fn builtin_spinning(
        name: &str,
        threads: usize,
        spin: bool,
        reporter: &dyn Reporter,
    ) -> Option<Result<Self, ExtractError>> {
        let bytes = builtin_model(name)?;
        Some(Self::from_model(
            bytes.into(),
            builtin_name(name),
            threads,
            spin,
            reporter,
        ))
    }

    fn from_model(
        bytes: std::borrow::Cow<'static, [u8]>,
        name: String,
        threads: usize,
        spin: bool,
        reporter: &dyn Reporter,
    ) -> Result<Self, ExtractError> {
        // A quick check before ORT: an ONNX ModelProto starts with field 1 (ir_version, varint).
        if bytes.first() != Some(&0x08) {
            return Err(ExtractError::Model {
                model: name,
                reason: "it does not start like an ONNX protobuf (ir_version)".into(),
            });
        }
        let runtime = runtime::runtime(reporter)?;
        let model_err = |e: ort::Error| ExtractError::Model {
            model: name.clone(),
            reason: e.to_string(),
        };
        let option_err =
            |e: ort::Error<ort::session::builder::SessionBuilder>| ExtractError::Runtime {
                path: Some(runtime.location.path.clone()),
                reason: format!("session options: {e}"),
            };
        // Spinning off by default: the threads sleep between images instead of burning the
        // shared cores. On: a frame that comes 100 ms after the last is inferred warm (about
        // 17 instead of 24 ms median on two threads here), for a third of a core.
        let session = Session::builder(runtime.environment())
            .map_err(model_err)?
            .with_optimization_level(GraphOptimizationLevel::Level3)
            .map_err(option_err)?
            .with_intra_threads(threads.max(1))
            .map_err(option_err)?
            .with_inter_threads(1)
            .map_err(option_err)?
            .with_intra_op_spinning(spin)
            .map_err(option_err)?
            .with_inter_op_spinning(false)
            .map_err(option_err)?
            .commit_from_memory(&bytes)
            .map_err(model_err)?;
        let meta = session.metadata().map_err(model_err)?;
        let keys = meta.custom_keys().map_err(model_err)?;
        let contract = Contract::from_metadata(&name, &keys, |k| meta.custom(k))?;
        drop(meta);
        let output_names: Vec<String> = session
            .outputs()
            .iter()
            .map(|o| o.name().to_string())
            .collect();
        // An input with a default (an initializer of its name: aliked-n16's describe branch, so
        // the model runs on an image alone) is listed apart by ONNX Runtime; it is fed alike.
        let input_names: Vec<String> = session
            .inputs()
            .iter()
            .map(|i| i.name().to_string())
            .chain(
                session
                    .overridable_initializers()
                    .iter()
                    .map(|i| i.name().to_string()),
            )
            .collect();
        let mut outputs: Vec<String> = (0..contract.levels())
            .flat_map(|i| [format!("feat_{i}"), format!("score_{i}")])
            .collect();
        if contract.global_dim > 0 {
            outputs.push("global".into());
        }
        let mut inputs = vec![contract.input_name.clone()];
        if contract.descriptor_head == DescriptorHead::Sddh {
            outputs.push(SDDH_OUTPUT.into());
            inputs.extend(SDDH_INPUTS.iter().map(|s| s.to_string()));
        }
        for out in outputs {
            if !output_names.contains(&out) {
                return Err(ExtractError::Contract {
                    model: name,
                    reason: format!("the model has no output {out:?}"),
                });
            }
        }
        for input in inputs {
            if !input_names.contains(&input) {
                return Err(ExtractError::Contract {
                    model: name,
                    reason: format!("the model has no input {input:?}"),
                });
            }
        }
        let model = ModelInfo {
            name,
            bytes: bytes.len() as u64,
            xxh3: crate::format::file_hash(&bytes),
        };
        Ok(Extractor {
            session: Mutex::new(session),
            contract,
            model,
            threads: threads.max(1),
        })
    }

    /// Whether the model is one of [`BUILTIN_MODELS`] (loaded by [`Extractor::builtin`], or
    /// the default), not a file the caller named.
    pub fn is_builtin(&self) -> bool {
        self.model.name.ends_with(BUILTIN_SUFFIX)
    }

    /// The model's contract metadata, checked.
    pub fn contract(&self) -> &Contract {
        &self.contract
    }

    /// The model file it runs.
    pub fn model(&self) -> &ModelInfo {
        &self.model
    }

    fn session(&self) -> MutexGuard<'_, Session> {
        // A panic during an inference leaves nothing half-written that a later one reads.
        self.session.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn inference_error(&self, reason: String) -> ExtractError {
        ExtractError::Inference {
            model: self.model.name.clone(),
            image: None,
            reason,
        }
    }

    /// Runs the network on one grey input; an input longer than the model's `sfp.max_side`
    /// is downscaled to it first (`Dense::scale` maps back to the input's file).
    pub fn run(&mut self, input: &GrayInput) -> Result<Dense, ExtractError> {
        let (w, h) = (input.width, input.height);
        if let Some(small) = self.contract.max_side.and_then(|m| input.downscaled(m)) {
            return self.run(&small);
        }
        let infer = |reason: String| self.inference_error(reason);
        if w == 0 || h == 0 {
            return Err(infer("empty image".into()));
        }
        let min = self.contract.min_input_side;
        if w < min || h < min {
            return Err(infer(format!(
                "the image is {w}x{h} pixels; the model takes at least {min} a side"
            )));
        }
        if let Some(reason) = too_large_for_the_network(w, h) {
            return Err(infer(reason));
        }
        // A view, not a copy: a 12-megapixel input is 48 MB.
        let tensor = TensorRef::from_array_view(([1usize, 1, h, w], &input.values[..]))
            .map_err(|e| infer(e.to_string()))?;
        let input_name = self.contract.input_name.clone();
        let c = &self.contract;
        let mut session = self.session();
        let outputs = if c.descriptor_head == DescriptorHead::Sddh {
            // The describe branch runs on every run: a 4x4 map and one keypoint cost nothing.
            let (features, keypoints) = sddh_placeholders(c.dims[0]).map_err(&infer)?;
            session.run(ort::inputs![
                input_name.as_str() => tensor,
                SDDH_INPUTS[0] => features,
                SDDH_INPUTS[1] => keypoints,
            ])
        } else {
            session.run(ort::inputs![input_name.as_str() => tensor])
        }
        .map_err(|e| infer(e.to_string()))?;
        let mut levels = Vec::with_capacity(c.levels());
        for i in 0..c.levels() {
            let (lh, lw) = (c.level_side(i, h), c.level_side(i, w));
            let channels = c.dims[i];
            let take = |out: &str, channels: usize| -> Result<Vec<f32>, ExtractError> {
                let value = outputs
                    .get(out)
                    .ok_or_else(|| infer(format!("no output {out:?}")))?;
                let (shape, data) = value
                    .try_extract_tensor::<f32>()
                    .map_err(|e| infer(format!("{out}: {e}")))?;
                let want = [1, channels as i64, lh as i64, lw as i64];
                if **shape != want {
                    return Err(infer(format!(
                        "{out} has shape {:?}, the contract says {want:?} for a {w}x{h} input",
                        &**shape
                    )));
                }
                Ok(data.to_vec())
            };
            let feat = take(&format!("feat_{i}"), channels)?;
            let score = take(&format!("score_{i}"), 1)?;
            levels.push(DenseLevel {
                stride: c.strides[i],
                channels,
                height: lh,
                width: lw,
                feat,
                score,
            });
        }
        let global = if c.global_dim == 0 {
            Vec::new()
        } else {
            let value = outputs
                .get("global")
                .ok_or_else(|| infer("no output \"global\"".into()))?;
            let (shape, data) = value
                .try_extract_tensor::<f32>()
                .map_err(|e| infer(format!("global: {e}")))?;
            if **shape != [1, c.global_dim as i64] {
                return Err(infer(format!("global has shape {:?}", &**shape)));
            }
            data.to_vec()
        };
        let image = if c.image_refine.iter().any(Option::is_some) {
            input.values.clone()
        } else {
            Vec::new()
        };
        Ok(Dense {
            input_size: [w, h],
            scale: input.scale(),
            levels,
            global,
            image,
        })
    }

    /// Each point's `full` descriptor on the model's first level, `[points × full_dims[0]]`
    /// L2-normalised; points are pixels of the network input (pixel-index convention, as
    /// [`Dense::input_pixel`] gives them). A descriptor head (`sfp.descriptor_head = sddh`)
    /// runs its graph once for all points; other models sample `dense` as
    /// [`Dense::full_descriptor_at`] does.
    pub fn describe(&self, dense: &Dense, points: &[[f32; 2]]) -> Result<Vec<f32>, ExtractError> {
        let Some(level) = dense.levels.first() else {
            return Ok(Vec::new());
        };
        if self.contract.descriptor_head == DescriptorHead::Bilinear {
            let mut out = Vec::new();
            for &[x, y] in points {
                dense.full_descriptor_at(0, x, y, &mut out);
            }
            return Ok(out);
        }
        let dim = level.channels;
        if points.is_empty() {
            return Ok(Vec::new());
        }
        let infer = |reason: String| self.inference_error(reason);
        let features =
            TensorRef::from_array_view(([1, dim, level.height, level.width], &level.feat[..]))
                .map_err(|e| infer(e.to_string()))?;
        let flat: Vec<f32> = points.iter().flatten().copied().collect();
        let keypoints =
            Tensor::from_array(([points.len(), 2], flat)).map_err(|e| infer(e.to_string()))?;
        let side = self.contract.min_input_side.max(32);
        let image = Tensor::from_array(([1usize, 1, side, side], vec![0.0f32; side * side]))
            .map_err(|e| infer(e.to_string()))?;
        let input_name = self.contract.input_name.clone();
        let mut session = self.session();
        let outputs = session
            .run(ort::inputs![
                input_name.as_str() => image,
                SDDH_INPUTS[0] => features,
                SDDH_INPUTS[1] => keypoints,
            ])
            .map_err(|e| infer(e.to_string()))?;
        let value = outputs
            .get(SDDH_OUTPUT)
            .ok_or_else(|| infer(format!("no output {SDDH_OUTPUT:?}")))?;
        let (shape, data) = value
            .try_extract_tensor::<f32>()
            .map_err(|e| infer(format!("{SDDH_OUTPUT}: {e}")))?;
        let want = [points.len() as i64, dim as i64];
        if **shape != want {
            return Err(infer(format!(
                "{SDDH_OUTPUT} has shape {:?}, the contract says {want:?}",
                &**shape
            )));
        }
        Ok(data.to_vec())
    }

    /// Keypoints and descriptors of every level from the network's outputs, and the global
    /// descriptor of this inference (`dense.global`, [`GlobalSize::Input`]; [`Extractor::extract`]
    /// takes it at [`DetectOptions::global`]'s size). Levels detected alike share one
    /// detection and placement. With more than one thread every placement's peaks are found
    /// first, and the placements then shared out by their work (peaks × (the refinement on
    /// the image + the full descriptors' sampling)); the result does not depend on it.
    pub fn features(
        &self,
        dense: &Dense,
        original_size: [u32; 2],
        options: &DetectOptions,
    ) -> Result<Features, ExtractError> {
        let c = &self.contract;
        // Another model's outputs (a `Dense` is public): every per-level rule below is this
        // contract's.
        if dense.levels.len() != c.levels() {
            return Err(self.inference_error(format!(
                "{} levels of outputs for a model of {}",
                dense.levels.len(),
                c.levels()
            )));
        }
        let max_of = |i: usize| match options.max_keypoints.as_deref() {
            Some([one]) => *one,
            Some(list) => list.get(i).copied().unwrap_or(c.default_max_keypoints[i]),
            None => c.default_max_keypoints[i],
        };
        let n = dense.levels.len();
        // Levels detected alike (the same score map, threshold, cap and image refinement:
        // sfp-v3's levels 0 and 2) share one detection and placement; each is described by
        // its own features. `groups[g]` = the levels of one placement, its first the lead.
        // `alike` must cover every per-level input of `level_peaks` and `placed` (the rest,
        // radius, detector and refinement switches, is one for all levels), or a grouped
        // level would be placed as another is; tests/api/extract_reference.rs checks a level
        // placed alone against its group.
        let threshold_of = |i: usize| options.threshold.unwrap_or(c.default_thresholds[i]);
        let alike = |i: usize, j: usize| {
            c.detect_levels[i] == c.detect_levels[j]
                && threshold_of(i).to_bits() == threshold_of(j).to_bits()
                && max_of(i) == max_of(j)
                && c.image_refine[i] == c.image_refine[j]
        };
        let mut groups: Vec<Vec<usize>> = Vec::new();
        for i in 0..n {
            match groups.iter_mut().find(|g| alike(g[0], i)) {
                Some(g) => g.push(i),
                None => groups.push(vec![i]),
            }
        }
        let threads = self.threads.min(groups.len()).max(1);
        let mut levels: Vec<Option<LevelFeatures>> = vec![None; n];
        let mut peaks: Vec<Vec<keypoints::Peak>> = (groups.iter())
            .map(|g| level_peaks(c, dense, g[0], max_of(g[0]), options))
            .collect();
        if threads == 1 {
            for (g, peaks) in groups.iter().zip(peaks) {
                for (i, f) in self.group_features(dense, g, peaks, options) {
                    levels[i] = Some(f?);
                }
            }
        } else {
            // The peaks first (cheap), then the groups shared out by their work: longest job
            // first onto the least loaded thread. Work a keypoint, in the image refinement's
            // multiply-adds: the blurs once, a bilinear sample per full dimension of the lead
            // (its group's levels share the samples: `group_features`).
            let cost: Vec<usize> = (groups.iter().zip(&peaks))
                .map(|(g, p)| {
                    let refine = c.image_refine[g[0]].map_or(0, |r| r.work_per_keypoint());
                    let sample = SAMPLE_WORK * c.full_dims[g[0]];
                    p.len().saturating_mul(refine + sample)
                })
                .collect();
            let mut jobs: Vec<usize> = (0..groups.len()).collect();
            jobs.sort_by_key(|&g| std::cmp::Reverse(cost[g]));
            let mut load = vec![0usize; threads];
            let mut share: Vec<Vec<(usize, Vec<keypoints::Peak>)>> = vec![Vec::new(); threads];
            for g in jobs {
                let t = (0..threads).min_by_key(|&t| load[t]).unwrap_or(0);
                load[t] = load[t].saturating_add(cost[g]);
                share[t].push((g, std::mem::take(&mut peaks[g])));
            }
            let groups = &groups;
            let done: Vec<Vec<(usize, Result<LevelFeatures, ExtractError>)>> =
                std::thread::scope(|s| {
                    let work = |mine: Vec<(usize, Vec<keypoints::Peak>)>| {
                        mine.into_iter()
                            .flat_map(|(g, peaks)| {
                                self.group_features(dense, &groups[g], peaks, options)
                            })
                            .collect::<Vec<_>>()
                    };
                    let mut share = share.into_iter();
                    let first = share.next().expect("threads >= 1");
                    let handles: Vec<_> = share.map(|m| s.spawn(move || work(m))).collect();
                    let mut done = vec![work(first)];
                    for h in handles {
                        // A panic in a worker is a bug here; re-raise it on the caller's thread.
                        done.push(h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)));
                    }
                    done
                });
            for (i, f) in done.into_iter().flatten() {
                levels[i] = Some(f?);
            }
        }
        Ok(Features {
            image_size: original_size,
            levels: levels.into_iter().flatten().collect(),
            global: dense.global.clone(),
        })
    }

    /// The levels of `group` (detected alike, the first the lead and the finest): the lead's
    /// `peaks` placed once, then each level's short and full descriptors there. A level's
    /// descriptor is its own part and every deeper level's, so the lead's parts hold every
    /// level's of the group: sampled once (sfp-v3's levels 0 and 2: 240 samples a keypoint
    /// instead of 240 + 192), the same values as a level sampled alone.
    fn group_features(
        &self,
        dense: &Dense,
        group: &[usize],
        peaks: Vec<keypoints::Peak>,
        options: &DetectOptions,
    ) -> Vec<(usize, Result<LevelFeatures, ExtractError>)> {
        let px = placed(&self.contract, dense, group[0], &peaks, options);
        if self.contract.descriptor_head == DescriptorHead::Sddh {
            return (group.iter())
                .map(|&i| (i, self.described_level(dense, i, &peaks, &px)))
                .collect();
        }
        // Groups are built in level order: the lead is the finest, its parts hold the others'.
        debug_assert!(group.windows(2).all(|w| w[0] < w[1]), "{group:?}");
        let lead = group[0];
        // The levels' own channel counts (`run` checks them against the contract; a `Dense`
        // built by hand may differ, and then gets descriptors of its own sizes, as long as each
        // level's maps hold channels × h × w values).
        let width: usize = dense.levels[lead..].iter().map(|l| l.channels).sum();
        let n = peaks.len();
        let mut parts = vec![0.0f32; n * width];
        // Sampled in raster order, not score order: consecutive keypoints then read the same
        // rows of every channel plane, from cache (score order missed it at every channel:
        // a quarter of this stage's time).
        let mut order: Vec<usize> = (0..n).collect();
        order.sort_unstable_by(|&a, &b| {
            (px[a].1.total_cmp(&px[b].1)).then(px[a].0.total_cmp(&px[b].0))
        });
        for k in order {
            dense.parts_into(
                lead,
                px[k].0,
                px[k].1,
                &mut parts[k * width..(k + 1) * width],
            );
        }
        (group.iter())
            .map(|&i| {
                let skip: usize = dense.levels[lead..i].iter().map(|l| l.channels).sum();
                (
                    i,
                    Ok(self.level_features(dense, i, &peaks, &px, &parts, width, skip)),
                )
            })
            .collect()
    }

    /// Level `i`'s keypoints (its detector's `peaks`, placed at `px`) and their short and
    /// full descriptors from `parts` (`[keypoints × width]`, each keypoint's normalised
    /// parts of the group's lead level and deeper; level `i`'s start `skip` values in).
    #[allow(clippy::too_many_arguments)]
    fn level_features(
        &self,
        dense: &Dense,
        i: usize,
        peaks: &[keypoints::Peak],
        px: &[(f32, f32)],
        parts: &[f32],
        width: usize,
        skip: usize,
    ) -> LevelFeatures {
        let c = &self.contract;
        let ds = dense.levels[i].channels;
        let df = width - skip;
        let n = peaks.len();
        let mut short = vec![f16::ZERO; n * ds];
        let mut full = vec![f16::ZERO; n * df];
        // One keypoint's full descriptor at a time: no second copy of the group's samples.
        let mut full32 = vec![0.0f32; df];
        for (k, row) in parts.chunks_exact(width.max(1)).take(n).enumerate() {
            let row = &row[skip..];
            // Level i's own part is `short`; normalised with the rest it is `full`.
            short[k * ds..(k + 1) * ds].convert_from_f32_slice(&row[..ds]);
            full32.copy_from_slice(row);
            crate::vector::l2_normalise(&mut full32);
            full[k * df..(k + 1) * df].convert_from_f32_slice(&full32);
        }
        LevelFeatures {
            level: c.level_ids[i],
            stride: c.strides[i],
            keypoints: px.iter().map(|&(x, y)| dense.colmap_pixel(x, y)).collect(),
            scores: peaks.iter().map(|p| p.score).collect(),
            dim_short: ds,
            dim_full: df,
            short,
            full,
        }
    }

    /// Level `i` of a model with a descriptor head: its descriptors at the keypoints `px`
    /// (input pixels), both `short` and `full` (one level: the same vectors).
    fn described_level(
        &self,
        dense: &Dense,
        i: usize,
        peaks: &[keypoints::Peak],
        px: &[(f32, f32)],
    ) -> Result<LevelFeatures, ExtractError> {
        let c = &self.contract;
        let points: Vec<[f32; 2]> = px.iter().map(|&(x, y)| [x, y]).collect();
        let described = self.describe(dense, &points)?;
        let mut full = vec![f16::ZERO; described.len()];
        full.convert_from_f32_slice(&described);
        let dim = dense.levels[i].channels;
        Ok(LevelFeatures {
            level: c.level_ids[i],
            stride: c.strides[i],
            keypoints: px.iter().map(|&(x, y)| dense.colmap_pixel(x, y)).collect(),
            scores: peaks.iter().map(|p| p.score).collect(),
            dim_short: dim,
            dim_full: dim,
            short: full.clone(),
            full,
        })
    }

    /// [`Extractor::run`], [`Extractor::features`] and [`Extractor::global`] at
    /// `options.global`.
    pub fn extract(
        &mut self,
        input: &GrayInput,
        options: &DetectOptions,
    ) -> Result<Features, ExtractError> {
        let dense = self.run(input)?;
        let mut features = self.features(&dense, input.original_size, options)?;
        features.global = self.global(input, &dense, options.global)?;
        Ok(features)
    }
}

/// The most pixels the network is run on: its activations take about 70 bytes a pixel
/// (a 120 MP PNG of 117 KB took 8.7 GB), so 16 MP keeps one inference near 1.2 GB. A 12 MP
/// phone photo fits; larger decoded images are downscaled to fit ([`image::from_image`]).
pub(crate) const MAX_INPUT_PIXELS: u64 = 1 << 24;

/// Why an input of `w x h` pixels is refused, if it is.
pub(crate) fn too_large_for_the_network(w: usize, h: usize) -> Option<String> {
    let pixels = (w as u64).saturating_mul(h as u64);
    (pixels > MAX_INPUT_PIXELS).then(|| {
        format!(
            "the image is {w}x{h} pixels, more than the {MAX_INPUT_PIXELS} the extractor runs on; \
             downscale it (--resize-max)"
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn level(stride: u32, channels: usize, side: usize, seed: u32) -> DenseLevel {
        let mut state = seed;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1 << 24) as f32 - 0.5
        };
        DenseLevel {
            stride,
            channels,
            height: side,
            width: side,
            feat: (0..channels * side * side).map(|_| next()).collect(),
            score: (0..side * side).map(|_| next()).collect(),
        }
    }

    /// Level `l`'s feature vector at cell (cx, cy), read straight from the CHW array.
    fn cell(l: &DenseLevel, cx: usize, cy: usize) -> Vec<f32> {
        (0..l.channels)
            .map(|c| l.feat[(c * l.height + cy) * l.width + cx])
            .collect()
    }

    fn unit(v: &[f32]) -> Vec<f32> {
        let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter().map(|x| x / n).collect()
    }

    fn assert_close(a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() < 1e-6, "{a:?}\n{b:?}");
        }
    }

    // The expected values come from the feature arrays by hand (cell lookups, a mean of two
    // cells, explicit norms), not from the sampling or normalising code under test.
    #[test]
    fn descriptors_are_sampled_per_level_normalised_and_concatenated() {
        let dense = Dense {
            input_size: [32, 32],
            scale: [1.0, 1.0],
            levels: vec![level(2, 4, 16, 1), level(4, 6, 8, 2), level(8, 8, 4, 3)],
            global: vec![1.0],
            image: Vec::new(),
        };
        let l = &dense.levels;
        // Pixel (8, 16) is a cell centre on every level: cells (4, 8), (2, 4), (1, 2).
        let own = [cell(&l[0], 4, 8), cell(&l[1], 2, 4), cell(&l[2], 1, 2)];
        for i in 0..3 {
            let mut got = Vec::new();
            l[i].descriptor_at(8.0, 16.0, &mut got);
            assert_close(&got, &unit(&own[i]));
            // full = the unit parts of levels i.. concatenated, over sqrt(number of parts).
            let k = (3 - i) as f32;
            let expected: Vec<f32> = own[i..]
                .iter()
                .flat_map(|p| unit(p))
                .map(|x| x / k.sqrt())
                .collect();
            let mut full = vec![9.0];
            dense.full_descriptor_at(i, 8.0, 16.0, &mut full);
            assert_eq!(full[0], 9.0, "appends, keeps what was there");
            assert_close(&full[1..], &expected);
            let mut parts = Vec::new();
            dense.parts_at(i, 8.0, 16.0, &mut parts);
            let unnormalised: Vec<f32> = own[i..].iter().flat_map(|p| unit(p)).collect();
            assert_close(&parts, &unnormalised);
        }
        // Half-way between cells 4 and 5 of level 0 (pixel x = 9): the mean of the two cells.
        let mean: Vec<f32> = cell(&l[0], 4, 8)
            .iter()
            .zip(cell(&l[0], 5, 8))
            .map(|(a, b)| (a + b) / 2.0)
            .collect();
        let mut got = Vec::new();
        l[0].descriptor_at(9.0, 16.0, &mut got);
        assert_close(&got, &unit(&mean));
    }

    #[test]
    fn inputs_past_sixteen_megapixels_are_refused_before_inference() {
        assert_eq!(too_large_for_the_network(4096, 4096), None);
        assert_eq!(too_large_for_the_network(4032, 3024), None);
        let reason = too_large_for_the_network(12000, 10000).unwrap();
        assert!(reason.contains("12000x10000") && reason.contains("--resize-max"));
        assert!(too_large_for_the_network(4097, 4096).is_some());
        assert!(too_large_for_the_network(usize::MAX, usize::MAX).is_some());
    }

    #[test]
    fn inference_errors_name_the_image_once() {
        let e = ExtractError::Inference {
            model: "m.onnx".into(),
            image: None,
            reason: "empty image".into(),
        };
        assert_eq!(e.to_string(), "m.onnx: empty image");
        let e = e.on_image(Path::new("a.jpg")).on_image(Path::new("b.jpg"));
        assert_eq!(e.to_string(), "a.jpg: m.onnx: empty image");
        let io = ExtractError::Io {
            path: "x.png".into(),
            source: std::io::Error::from(std::io::ErrorKind::NotFound),
        };
        assert!(std::error::Error::source(&io).is_none());
        assert!(io
            .on_image(Path::new("y.png"))
            .to_string()
            .starts_with("x.png: "));
    }
}
