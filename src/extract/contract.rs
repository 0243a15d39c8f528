//! The model contracts `sfp-extractor/1`, `/2` and `/3` (`spec/extractor.md`), read from the model's
//! ONNX `metadata_props`. Every number the extractor uses comes from here, never from constants.

use super::image_refine::{self, ImageRefine};
use super::ExtractError;
use std::collections::BTreeMap;

/// The contracts this extractor implements, oldest first. `/2` is `/1` plus step 5, the image
/// refinement (`sfp.image_refine_sigma`, `sfp.image_refine_radius`): an extractor of `/1`
/// would place such a model's keypoints pixels away from where its maps expect them. `/3` is
/// `/2` plus `sfp.detect_level`: a level may find its keypoints on a finer level's score map,
/// which an extractor of `/2` would not do.
pub const CONTRACTS: [&str; 3] = ["sfp-extractor/1", "sfp-extractor/2", "sfp-extractor/3"];

/// The newest contract this extractor implements.
pub const CONTRACT: &str = CONTRACTS[2];

/// The largest NMS radius, in cells, a model's default or `--nms-radius` may ask for: the
/// suppression (and DKD's window) costs its square per keypoint.
pub const MAX_NMS_RADIUS: u32 = 64;

/// The most keypoints a level may keep, by a model's default or `--max-keypoints`.
pub const MAX_KEYPOINTS: usize = 1_000_000;

/// What a model promises, parsed and checked for consistency.
#[derive(Debug, Clone, PartialEq)]
pub struct Contract {
    /// `sfp.contract`: one of [`CONTRACTS`].
    pub version: &'static str,
    /// `sfp.model_name`: the descriptor kind maps record (`sfp-v2`).
    pub model_name: String,
    /// Level ids as maps and the CLI use them, finest first (`sfp.level_ids`).
    pub level_ids: Vec<u16>,
    /// Stride in pixels per level.
    pub strides: Vec<u32>,
    /// Channels of `feat_i` per level (= short descriptor dims).
    pub dims: Vec<usize>,
    /// Full descriptor dims per level (`dims[i] + … + dims[L−1]`).
    pub full_dims: Vec<usize>,
    /// Dimensions of the global descriptor.
    pub global_dim: usize,
    /// The network's input tensor name.
    pub input_name: String,
    /// RGB → grey weights.
    pub gray_weights: [f32; 3],
    /// Detection threshold per level when the caller gives none (`sfp.default_threshold`:
    /// one score for every level, or, in a `/2` model, one a level).
    pub default_thresholds: Vec<f32>,
    /// NMS radius when the caller gives none, in cells.
    pub default_nms_radius: u32,
    /// Keypoint cap per level when the caller gives none.
    pub default_max_keypoints: Vec<usize>,
    /// How keypoints are found on a score map (`sfp.detector`).
    pub detector: Detector,
    /// Where descriptors come from (`sfp.descriptor_head`).
    pub descriptor_head: DescriptorHead,
    /// The longest side the network is run on (`sfp.max_side`): a larger input is downscaled
    /// first, and keypoints are scaled back. `None`: no cap but the pixel count's.
    pub max_side: Option<u32>,
    /// The shortest side the network takes (`sfp.min_input_side`, default 1).
    pub min_input_side: usize,
    /// The finest level coarse-to-fine refinement walks down to (`sfp.refine_to_level`):
    /// `None`, one level finer than the keypoint's (the SFP rule).
    pub refine_to_level: Option<usize>,
    /// Per level, the image refinement of step 5 (`sfp-extractor/2`); `None` for a level
    /// without it, and for every level of a `/1` model.
    pub image_refine: Vec<Option<ImageRefine>>,
    /// Per level, the index of the level whose score map its keypoints are detected on
    /// (`sfp.detect_level`, `/3`): the level itself, or a finer one. A level detected on
    /// another keeps its own threshold, cap and image refinement, and its own descriptors.
    /// `[0, 1, …]` (each level its own) for `/1` and `/2` models.
    pub detect_levels: Vec<usize>,
    /// Every `sfp.*` key, for provenance.
    pub raw: BTreeMap<String, String>,
}

/// How a model's keypoints are found on its score maps (`sfp.detector`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Detector {
    /// `nms` (the default, SFP's): per level, NMS in a window, threshold, border ring, top-k,
    /// quadratic sub-pixel fit, coarse-to-fine refinement.
    Nms,
    /// `dkd` (ALIKED's differentiable keypoint detection): NMS with two suppression rounds,
    /// a border of the NMS radius, threshold (the map's mean when nothing passes it), cap by
    /// score, soft-argmax sub-pixel position (temperature 0.1) and the score bilinear there.
    Dkd,
}

/// Where a model's descriptors come from (`sfp.descriptor_head`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum DescriptorHead {
    /// `bilinear` (the default, SFP's): `feat_i` sampled at the keypoint, L2-normalised.
    Bilinear,
    /// `sddh` (ALIKED's): the graph's `descriptors` output for the inputs `features` (a
    /// `feat_0`) and `keypoints` (`[N, 2]` input pixels, pixel-index convention); one level.
    Sddh,
}

fn list<T: std::str::FromStr>(value: &str) -> Option<Vec<T>> {
    value.split(',').map(|v| v.trim().parse().ok()).collect()
}

impl Contract {
    /// Parses the metadata of the model file `model` (named in errors). `get` returns a key's
    /// value; `keys` lists the keys present (kept in [`Contract::raw`]).
    pub fn from_metadata(
        model: &str,
        keys: &[String],
        get: impl Fn(&str) -> Option<String>,
    ) -> Result<Contract, ExtractError> {
        let bad = |reason: String| ExtractError::Contract {
            model: model.to_string(),
            reason,
        };
        let req = |key: &str| get(key).ok_or_else(|| bad(format!("metadata key {key:?} missing")));
        let version = match get("sfp.contract") {
            Some(c) => match CONTRACTS.iter().find(|&&k| k == c) {
                Some(&k) => k,
                None => {
                    return Err(bad(format!(
                        "contract {c:?} is not {}; this sfpmap cannot run it",
                        CONTRACTS.map(|k| format!("{k:?}")).join(" or ")
                    )))
                }
            },
            None => {
                return Err(bad(format!(
                    "no sfp.contract in its metadata (not an SFP model for {CONTRACT:?})"
                )))
            }
        };
        fn parse<T: std::str::FromStr>(
            key: &str,
            value: &str,
            bad: &dyn Fn(String) -> ExtractError,
        ) -> Result<Vec<T>, ExtractError> {
            list(value).ok_or_else(|| bad(format!("{key} = {value:?} is not a number list")))
        }
        let levels: usize = req("sfp.levels")?
            .trim()
            .parse()
            .map_err(|_| bad("sfp.levels is not a number".into()))?;
        let level_ids: Vec<u16> = parse("sfp.level_ids", &req("sfp.level_ids")?, &bad)?;
        let strides: Vec<u32> = parse("sfp.strides", &req("sfp.strides")?, &bad)?;
        let dims: Vec<usize> = parse("sfp.dims", &req("sfp.dims")?, &bad)?;
        let short_dims: Vec<usize> = match get("sfp.short_dims") {
            Some(v) => parse("sfp.short_dims", &v, &bad)?,
            None => dims.clone(),
        };
        let full_dims: Vec<usize> = parse("sfp.full_dims", &req("sfp.full_dims")?, &bad)?;
        let max_kp: Vec<usize> = parse(
            "sfp.default_max_keypoints",
            &req("sfp.default_max_keypoints")?,
            &bad,
        )?;
        for (key, n) in [
            ("sfp.level_ids", level_ids.len()),
            ("sfp.strides", strides.len()),
            ("sfp.dims", dims.len()),
            ("sfp.short_dims", short_dims.len()),
            ("sfp.full_dims", full_dims.len()),
            ("sfp.default_max_keypoints", max_kp.len()),
        ] {
            if n != levels {
                return Err(bad(format!(
                    "{key} has {n} values for sfp.levels = {levels}"
                )));
            }
        }
        if levels == 0 {
            return Err(bad("sfp.levels is 0".into()));
        }
        if level_ids.windows(2).any(|w| w[0] >= w[1]) || strides.windows(2).any(|w| w[0] >= w[1]) {
            return Err(bad(
                "sfp.level_ids and sfp.strides must increase (finest level first)".into(),
            ));
        }
        if strides.contains(&0) || dims.contains(&0) {
            return Err(bad("a stride or a dim is 0".into()));
        }
        if short_dims != dims {
            return Err(bad("sfp.short_dims differ from sfp.dims".into()));
        }
        for i in 0..levels {
            let expected: usize = dims[i..].iter().sum();
            if full_dims[i] != expected {
                return Err(bad(format!(
                    "sfp.full_dims[{i}] = {} but the dims of levels {i}.. sum to {expected}",
                    full_dims[i]
                )));
            }
        }
        for (key, want) in [
            ("sfp.padding", "none"),
            ("sfp.size_rule", "ceil"),
            ("sfp.input_channels", "1"),
            ("sfp.descriptor_norm", "l2"),
        ] {
            let v = req(key)?;
            if v.trim() != want {
                return Err(bad(format!("{key} = {v:?}, this extractor needs {want:?}")));
            }
        }
        let weights: Vec<f32> = match get("sfp.input_gray_weights") {
            Some(v) => parse("sfp.input_gray_weights", &v, &bad)?,
            None => vec![0.299, 0.587, 0.114],
        };
        let gray_weights: [f32; 3] = weights
            .try_into()
            .map_err(|_| bad("sfp.input_gray_weights needs 3 values".into()))?;
        let global_dim: usize = req("sfp.global_dim")?
            .trim()
            .parse()
            .map_err(|_| bad("sfp.global_dim is not a number".into()))?;
        let default_thresholds =
            default_thresholds(version, levels, &req("sfp.default_threshold")?, &bad)?;
        let default_nms_radius: u32 = req("sfp.default_nms_radius")?
            .trim()
            .parse()
            .map_err(|_| bad("sfp.default_nms_radius is not a number".into()))?;
        // A model file is an input like any other: its defaults are held to the ranges a
        // user's flags are (a radius of 10^6 cells would run for hours).
        if default_nms_radius > MAX_NMS_RADIUS {
            return Err(bad(format!(
                "sfp.default_nms_radius = {default_nms_radius} is over {MAX_NMS_RADIUS}"
            )));
        }
        if let Some(&n) = max_kp.iter().find(|&&n| !(1..=MAX_KEYPOINTS).contains(&n)) {
            return Err(bad(format!(
                "sfp.default_max_keypoints has {n}: 1 to {MAX_KEYPOINTS} a level"
            )));
        }
        let detector = match get("sfp.detector").as_deref().map(str::trim) {
            None | Some("nms") => Detector::Nms,
            Some("dkd") => Detector::Dkd,
            Some(other) => return Err(bad(format!("sfp.detector = {other:?} is not nms or dkd"))),
        };
        let descriptor_head = match get("sfp.descriptor_head").as_deref().map(str::trim) {
            None | Some("bilinear") => DescriptorHead::Bilinear,
            Some("sddh") => DescriptorHead::Sddh,
            Some(other) => {
                return Err(bad(format!(
                    "sfp.descriptor_head = {other:?} is not bilinear or sddh"
                )))
            }
        };
        if descriptor_head == DescriptorHead::Sddh && levels != 1 {
            return Err(bad(format!(
                "sfp.descriptor_head = sddh describes one level, not sfp.levels = {levels}"
            )));
        }
        let number = |key: &str| -> Result<Option<u32>, ExtractError> {
            get(key)
                .map(|v| {
                    v.trim()
                        .parse()
                        .map_err(|_| bad(format!("{key} = {v:?} is not a number")))
                })
                .transpose()
        };
        let max_side = number("sfp.max_side")?.filter(|&s| s > 0);
        let min_input_side = number("sfp.min_input_side")?.unwrap_or(1).max(1) as usize;
        let refine_to_level = number("sfp.refine_to_level")?.map(|t| t as usize);
        if let Some(t) = refine_to_level.filter(|&t| t >= levels) {
            return Err(bad(format!(
                "sfp.refine_to_level = {t} is no level of sfp.levels = {levels}"
            )));
        }
        let image_refine = image_refine_levels(version, levels, &get, &bad)?;
        if descriptor_head == DescriptorHead::Sddh && image_refine.iter().any(Option::is_some) {
            return Err(bad(
                "sfp.image_refine_sigma refines keypoints that sfp.descriptor_head = sddh \
                 describes where they were detected: a model has one or the other"
                    .into(),
            ));
        }
        let detect_levels = detect_levels(version, levels, &get, &bad)?;
        if descriptor_head == DescriptorHead::Sddh
            && detect_levels.iter().enumerate().any(|(i, &d)| d != i)
        {
            return Err(bad(
                "sfp.detect_level moves a level onto another's score map, and \
                 sfp.descriptor_head = sddh has one level"
                    .into(),
            ));
        }
        let raw = keys
            .iter()
            .filter(|k| k.starts_with("sfp."))
            .filter_map(|k| get(k).map(|v| (k.clone(), v)))
            .collect();
        Ok(Contract {
            version,
            model_name: get("sfp.model_name").unwrap_or_else(|| "unnamed".into()),
            level_ids,
            strides,
            dims,
            full_dims,
            global_dim,
            input_name: get("sfp.input_name").unwrap_or_else(|| "image".into()),
            gray_weights,
            default_thresholds,
            default_nms_radius,
            default_max_keypoints: max_kp,
            detector,
            descriptor_head,
            max_side,
            min_input_side,
            refine_to_level,
            image_refine,
            detect_levels,
            raw,
        })
    }

    /// How many levels the model outputs.
    pub fn levels(&self) -> usize {
        self.level_ids.len()
    }

    /// The position of level id `level` in the contract's lists.
    pub fn level_index(&self, level: u16) -> Option<usize> {
        self.level_ids.iter().position(|&l| l == level)
    }

    /// Side of level `i`'s maps for an image side `n` (`sfp.size_rule = ceil`).
    pub fn level_side(&self, i: usize, n: usize) -> usize {
        n.div_ceil(self.strides[i] as usize)
    }
}

/// `sfp.default_threshold`: one score for every level, or (`/2`) one a level, finest first,
/// each in [0, 1]. A `/1` model has one: its extractors read one number.
fn default_thresholds(
    version: &str,
    levels: usize,
    value: &str,
    bad: &dyn Fn(String) -> ExtractError,
) -> Result<Vec<f32>, ExtractError> {
    let key = "sfp.default_threshold";
    // A model file may hold anything: a message quotes the start of the value.
    let quoted = || format!("{:?}", value.chars().take(80).collect::<String>());
    let values: Vec<f32> =
        list(value).ok_or_else(|| bad(format!("{key} = {} is not a number list", quoted())))?;
    let values = match values.len() {
        1 => vec![values[0]; levels],
        n if n == levels && version != CONTRACTS[0] => values,
        n if version == CONTRACTS[0] => {
            return Err(bad(format!(
                "{key} has {n} values: a {version:?} model has one (one a level needs {:?})",
                CONTRACTS[1]
            )))
        }
        n => {
            return Err(bad(format!(
                "{key} has {n} values: one, or one a level of sfp.levels = {levels}"
            )))
        }
    };
    for &t in &values {
        if let Err(expected) = crate::ranges::SCORE.check(t.into()) {
            return Err(bad(format!("{key} = {}: {t} is not {expected}", quoted())));
        }
    }
    Ok(values)
}

/// Step 5's parameters: `sfp.image_refine_sigma` (per level, input pixels, 0: not refined)
/// and `sfp.image_refine_radius` (per level, input pixels, 0: not refined), both required by
/// `/2` (which refines at least one level) and refused in a `/1` model (whose extractors would
/// ignore them).
fn image_refine_levels(
    version: &str,
    levels: usize,
    get: &impl Fn(&str) -> Option<String>,
    bad: &dyn Fn(String) -> ExtractError,
) -> Result<Vec<Option<ImageRefine>>, ExtractError> {
    const SIGMA: &str = "sfp.image_refine_sigma";
    const RADIUS: &str = "sfp.image_refine_radius";
    let (sigma, radius) = (get(SIGMA), get(RADIUS));
    if version == CONTRACTS[0] {
        return match sigma.and(Some(SIGMA)).or(radius.and(Some(RADIUS))) {
            Some(key) => Err(bad(format!(
                "{key} needs sfp.contract = {:?}, not {version:?}",
                CONTRACTS[1]
            ))),
            None => Ok(vec![None; levels]),
        };
    }
    let need = |key: &str, v: Option<String>| {
        v.ok_or_else(|| bad(format!("metadata key {key:?} missing ({version} needs it)")))
    };
    let sigma = need(SIGMA, sigma)?;
    let radius = need(RADIUS, radius)?;
    let sigmas: Vec<f32> =
        list(&sigma).ok_or_else(|| bad(format!("{SIGMA} = {sigma:?} is not a number list")))?;
    let radii: Vec<u32> =
        list(&radius).ok_or_else(|| bad(format!("{RADIUS} = {radius:?} is not a number list")))?;
    for (key, n) in [(SIGMA, sigmas.len()), (RADIUS, radii.len())] {
        if n != levels {
            return Err(bad(format!(
                "{key} has {n} values for sfp.levels = {levels}"
            )));
        }
    }
    let levels: Vec<Option<ImageRefine>> = sigmas
        .iter()
        .zip(&radii)
        .map(|(&sigma, &radius)| {
            let off = sigma == 0.0;
            if !off && !(image_refine::MIN_SIGMA..=image_refine::MAX_SIGMA).contains(&sigma) {
                return Err(bad(format!(
                    "{SIGMA} has {sigma}: 0 (not refined) or {} to {} pixels",
                    image_refine::MIN_SIGMA,
                    image_refine::MAX_SIGMA
                )));
            }
            if radius > image_refine::MAX_RADIUS {
                return Err(bad(format!(
                    "{RADIUS} has {radius}: 0 to {} pixels",
                    image_refine::MAX_RADIUS
                )));
            }
            Ok((!off && radius > 0).then_some(ImageRefine { sigma, radius }))
        })
        .collect::<Result<_, _>>()?;
    if levels.iter().all(Option::is_none) {
        return Err(bad(format!(
            "{version} refines some level, and {SIGMA} = {sigma:?} with {RADIUS} = {radius:?} \
             refines none"
        )));
    }
    Ok(levels)
}

/// `sfp.detect_level`: per level, finest first, the level index whose score map its keypoints
/// are detected on, that level or a finer one (`/3`, which requires it); refused in a `/1` or
/// `/2` model, whose extractors would ignore it.
fn detect_levels(
    version: &str,
    levels: usize,
    get: &impl Fn(&str) -> Option<String>,
    bad: &dyn Fn(String) -> ExtractError,
) -> Result<Vec<usize>, ExtractError> {
    const KEY: &str = "sfp.detect_level";
    let value = get(KEY);
    if version != CONTRACTS[2] {
        return match value {
            Some(_) => Err(bad(format!(
                "{KEY} needs sfp.contract = {:?}, not {version:?}",
                CONTRACTS[2]
            ))),
            None => Ok((0..levels).collect()),
        };
    }
    let value =
        value.ok_or_else(|| bad(format!("metadata key {KEY:?} missing ({version} needs it)")))?;
    let quoted = || format!("{:?}", value.chars().take(80).collect::<String>());
    let values: Vec<usize> =
        list(&value).ok_or_else(|| bad(format!("{KEY} = {} is not a number list", quoted())))?;
    if values.len() != levels {
        return Err(bad(format!(
            "{KEY} has {} values for sfp.levels = {levels}",
            values.len()
        )));
    }
    if let Some((i, &d)) = values.iter().enumerate().find(|&(i, &d)| d > i) {
        return Err(bad(format!(
            "{KEY} = {}: level {i} is detected on level {d}, which is not it or a finer one",
            quoted()
        )));
    }
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sfp_v1() -> BTreeMap<String, String> {
        [
            ("sfp.contract", "sfp-extractor/1"),
            ("sfp.model_name", "test"),
            ("sfp.levels", "4"),
            ("sfp.level_ids", "0,1,2,3"),
            ("sfp.strides", "2,4,8,16"),
            ("sfp.dims", "16,32,64,128"),
            ("sfp.short_dims", "16,32,64,128"),
            ("sfp.full_dims", "240,224,192,128"),
            ("sfp.global_dim", "128"),
            ("sfp.padding", "none"),
            ("sfp.size_rule", "ceil"),
            ("sfp.input_channels", "1"),
            ("sfp.descriptor_norm", "l2"),
            ("sfp.default_threshold", "0.5"),
            ("sfp.default_nms_radius", "1"),
            ("sfp.default_max_keypoints", "2000,1000,500,250"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v.to_string()))
        .collect()
    }

    fn parse(m: &BTreeMap<String, String>) -> Result<Contract, ExtractError> {
        let keys: Vec<String> = m.keys().cloned().collect();
        Contract::from_metadata("m.onnx", &keys, |k| m.get(k).cloned())
    }

    #[test]
    fn parses_sfp_v1() {
        let c = parse(&sfp_v1()).unwrap();
        assert_eq!(c.level_ids, [0, 1, 2, 3]);
        assert_eq!(c.strides, [2, 4, 8, 16]);
        assert_eq!(c.full_dims, [240, 224, 192, 128]);
        assert_eq!(c.level_side(2, 481), 61);
        assert_eq!(c.level_index(2), Some(2));
        assert_eq!(c.raw.len(), 16);
    }

    #[test]
    fn refuses_other_contracts_and_inconsistent_metadata() {
        let mut m = sfp_v1();
        m.insert("sfp.contract".into(), "sfp-extractor/3".into());
        let e = parse(&m).unwrap_err().to_string();
        assert!(e.contains("m.onnx") && e.contains("sfp-extractor/3"), "{e}");
        let mut m = sfp_v1();
        m.remove("sfp.contract");
        assert!(parse(&m)
            .unwrap_err()
            .to_string()
            .contains("no sfp.contract"));
        let mut m = sfp_v1();
        m.insert("sfp.full_dims".into(), "240,224,190,128".into());
        assert!(parse(&m).unwrap_err().to_string().contains("full_dims[2]"));
        let mut m = sfp_v1();
        m.insert("sfp.strides".into(), "2,4,8".into());
        assert!(parse(&m).unwrap_err().to_string().contains("3 values"));
        let mut m = sfp_v1();
        m.insert("sfp.padding".into(), "multiple".into());
        assert!(parse(&m).is_err());
        let mut m = sfp_v1();
        m.insert("sfp.descriptor_head".into(), "sddh".into());
        assert!(parse(&m).unwrap_err().to_string().contains("one level"));
        let mut m = sfp_v1();
        m.insert("sfp.detector".into(), "sift".into());
        assert!(parse(&m).unwrap_err().to_string().contains("sfp.detector"));
        // Defaults a user's model file gives are held to the flags' ranges.
        for (key, value, words) in [
            ("sfp.default_nms_radius", "1000000", "is over 64"),
            ("sfp.default_max_keypoints", "1000,1000,0,250", "has 0"),
            (
                "sfp.default_max_keypoints",
                "1000,1000,2000000,250",
                "has 2000000",
            ),
            ("sfp.default_threshold", "NaN", "is not a score in [0, 1]"),
            ("sfp.refine_to_level", "4", "is no level"),
            ("sfp.refine_to_level", "-1", "is not a number"),
        ] {
            let mut m = sfp_v1();
            m.insert(key.into(), value.into());
            let e = parse(&m).unwrap_err().to_string();
            assert!(e.contains(key) && e.contains(words), "{key}: {e}");
        }
    }

    #[test]
    fn sfp_models_keep_their_rules_and_aliked_declares_its_own() {
        let c = parse(&sfp_v1()).unwrap();
        assert_eq!(
            (c.detector, c.descriptor_head, c.max_side, c.min_input_side),
            (Detector::Nms, DescriptorHead::Bilinear, None, 1)
        );
        assert_eq!(c.refine_to_level, None);
        let mut m = sfp_v1();
        m.insert("sfp.refine_to_level".into(), "0".into());
        assert_eq!(parse(&m).unwrap().refine_to_level, Some(0));
        let mut m = aliked_like(sfp_v1());
        for (k, v) in [
            ("sfp.global_dim", "0"),
            ("sfp.default_max_keypoints", "20000"),
            ("sfp.detector", "dkd"),
            ("sfp.max_side", "1024"),
            ("sfp.min_input_side", "4"),
        ] {
            m.insert(k.into(), v.into());
        }
        let c = parse(&m).unwrap();
        assert_eq!(
            (c.detector, c.descriptor_head, c.max_side, c.min_input_side),
            (Detector::Dkd, DescriptorHead::Sddh, Some(1024), 4)
        );
        assert_eq!((c.levels(), c.global_dim, c.full_dims[0]), (1, 0, 128));
    }

    #[test]
    fn a_contract_2_model_may_give_each_level_its_threshold() {
        // One value is every level's, in either contract.
        assert_eq!(parse(&sfp_v1()).unwrap().default_thresholds, [0.5; 4]);
        let mut m = sfp_v2_contract("0,2.5,3,4", "0,3,4,5");
        m.insert("sfp.default_threshold".into(), "0.5,0.5,0.1,0.5".into());
        assert_eq!(parse(&m).unwrap().default_thresholds, [0.5, 0.5, 0.1, 0.5]);
        // A /1 extractor reads one number: a list there needs /2.
        let mut v1 = sfp_v1();
        v1.insert("sfp.default_threshold".into(), "0.5,0.5,0.1,0.5".into());
        for (m, threshold, words) in [
            (v1, None, "needs \"sfp-extractor/2\""),
            (m.clone(), Some("0.5,0.1,0.5"), "has 3 values"),
            (
                m.clone(),
                Some("0.5,0.5,1.5,0.5"),
                "1.5 is not a score in [0, 1]",
            ),
            (m, Some("0.5,0.5,,0.5"), "not a number list"),
        ] {
            let mut m = m;
            if let Some(threshold) = threshold {
                m.insert("sfp.default_threshold".into(), threshold.into());
            }
            let e = parse(&m).unwrap_err().to_string();
            assert!(
                e.contains("sfp.default_threshold") && e.contains(words),
                "{words}: {e}"
            );
        }
    }

    /// `m` made a model of one level of 128 dimensions with a descriptor head (ALIKED's shape).
    fn aliked_like(mut m: BTreeMap<String, String>) -> BTreeMap<String, String> {
        for (k, v) in [
            ("sfp.levels", "1"),
            ("sfp.level_ids", "0"),
            ("sfp.strides", "1"),
            ("sfp.dims", "128"),
            ("sfp.short_dims", "128"),
            ("sfp.full_dims", "128"),
            ("sfp.default_max_keypoints", "2000"),
            ("sfp.descriptor_head", "sddh"),
        ] {
            m.insert(k.into(), v.into());
        }
        m
    }

    fn sfp_v2_contract(sigma: &str, radius: &str) -> BTreeMap<String, String> {
        let mut m = sfp_v1();
        m.insert("sfp.contract".into(), "sfp-extractor/2".into());
        m.insert("sfp.image_refine_sigma".into(), sigma.into());
        m.insert("sfp.image_refine_radius".into(), radius.into());
        m
    }

    #[test]
    fn contract_2_reads_the_image_refinement_per_level() {
        let c = parse(&sfp_v2_contract("0,2.5,3,4", "0,3,4,5")).unwrap();
        assert_eq!(c.version, "sfp-extractor/2");
        let r = |sigma, radius| Some(ImageRefine { sigma, radius });
        assert_eq!(c.image_refine, [None, r(2.5, 3), r(3.0, 4), r(4.0, 5)]);
        let c = parse(&sfp_v1()).unwrap();
        assert_eq!(
            (c.version, c.image_refine),
            ("sfp-extractor/1", vec![None; 4])
        );
        for (m, words) in [
            (sfp_v2_contract("0,2.5,3", "0,3,4,5"), "3 values"),
            (sfp_v2_contract("0,2.5,3,40", "0,3,4,5"), "has 40"),
            (sfp_v2_contract("0,2.5,3,0.3", "0,3,4,5"), "has 0.3"),
            (sfp_v2_contract("0,0,0,0", "0,3,4,5"), "refines none"),
            (sfp_v2_contract("0,2.5,3,4", "0,0,0,0"), "refines none"),
            (sfp_v2_contract("0,2.5,3,NaN", "0,3,4,5"), "has NaN"),
            (sfp_v2_contract("0,2.5,3,4", "0,3,4,100"), "has 100"),
            (
                sfp_v2_contract("0,2.5,3,4", "0,3,-4,5"),
                "not a number list",
            ),
        ] {
            let e = parse(&m).unwrap_err().to_string();
            assert!(e.contains("m.onnx") && e.contains(words), "{words}: {e}");
        }
        let mut m = sfp_v2_contract("0,2.5,3,4", "0,3,4,5");
        m.remove("sfp.image_refine_radius");
        let e = parse(&m).unwrap_err().to_string();
        assert!(
            e.contains("sfp.image_refine_radius") && e.contains("missing"),
            "{e}"
        );
        // A level with radius 0 stays; the others refine.
        let c = parse(&sfp_v2_contract("1.5,2.5,3,4", "2,0,4,5")).unwrap();
        assert_eq!(c.image_refine[1], None);
        assert_eq!(c.image_refine[0], r(1.5, 2));
        // A contract value is the exact string.
        let mut m = sfp_v2_contract("0,2.5,3,4", "0,3,4,5");
        m.insert("sfp.contract".into(), "sfp-extractor/2 ".into());
        assert!(parse(&m).is_err());
        // A descriptor head describes where DKD detected: refining moves keypoints it does not see.
        let m = aliked_like(sfp_v2_contract("2", "2"));
        let e = parse(&m).unwrap_err().to_string();
        assert!(e.contains("one or the other"), "{e}");
        // A /1 model with the keys would be refined by this extractor and not by older ones.
        let mut m = sfp_v1();
        m.insert("sfp.image_refine_sigma".into(), "0,2.5,3,4".into());
        let e = parse(&m).unwrap_err().to_string();
        assert!(
            e.contains("needs sfp.contract = \"sfp-extractor/2\""),
            "{e}"
        );
    }

    #[test]
    fn contract_3_detects_a_level_on_a_finer_ones_score_map() {
        let v3 = |detect: Option<&str>| {
            let mut m = sfp_v2_contract("1.5,2.5,1.5,4", "2,3,2,5");
            m.insert("sfp.contract".into(), "sfp-extractor/3".into());
            if let Some(d) = detect {
                m.insert("sfp.detect_level".into(), d.into());
            }
            m
        };
        let c = parse(&v3(Some("0,1,0,3"))).unwrap();
        assert_eq!(
            (c.version, c.detect_levels),
            ("sfp-extractor/3", vec![0, 1, 0, 3])
        );
        // /1 and /2 models detect every level on its own map.
        assert_eq!(parse(&sfp_v1()).unwrap().detect_levels, [0, 1, 2, 3]);
        for (m, words) in [
            (v3(None), "missing"),
            (v3(Some("0,1,0")), "has 3 values"),
            (v3(Some("0,2,2,3")), "level 1 is detected on level 2"),
            (v3(Some("0,1,-1,3")), "not a number list"),
        ] {
            let e = parse(&m).unwrap_err().to_string();
            assert!(
                e.contains("sfp.detect_level") && e.contains(words),
                "{words}: {e}"
            );
        }
        // Older extractors would detect each level on its own map: the key needs /3.
        let mut m = sfp_v2_contract("1.5,2.5,1.5,4", "2,3,2,5");
        m.insert("sfp.detect_level".into(), "0,1,0,3".into());
        let e = parse(&m).unwrap_err().to_string();
        assert!(
            e.contains("needs sfp.contract = \"sfp-extractor/3\""),
            "{e}"
        );
    }
}
