//! The global descriptor's image size (`spec/extractor.md`, "Global descriptor"): which copy
//! of an image the `global` output is taken from, and the extractor's methods that take it.

use super::image::GrayInput;
use super::{Dense, ExtractError, Extractor};

/// The longer side, in pixels, of the copy of an image the global descriptor is computed on
/// by default. sfp-v1's GeM global ranks a scene's images better on a small copy: recall@5 of
/// the most co-visible database image on South Building's queries is 0.85 / 0.96 / 0.92 / 0.81
/// at 384 / 512 / 640 / 1024 px, and 0.96 or more on the three shared scenes at 512
/// (`python/eval_retrieval.py --max-side`): level 3's cells then span whole façades.
pub const GLOBAL_MAX_SIDE: u32 = 512;

/// The smallest global descriptor side a flag may ask for (as `--resize-max`'s 16).
pub const GLOBAL_MIN_SIDE: u32 = 16;

/// The image size a global descriptor is computed at (`spec/extractor.md`, "Global
/// descriptor"). Map and query must agree: a map records it (metadata `global_max_side`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GlobalSize {
    /// The network input itself: the `global` output of the one inference every image gets
    /// (maps without `global_max_side`, written before it existed, hold these).
    Input,
    /// A copy downscaled (triangle filter) so its longer side is at most this many pixels;
    /// the input itself when it fits. A larger input costs one more, smaller, inference.
    MaxSide(u32),
    /// No global descriptor (`Features::global` empty): a query localized with a pose prior
    /// does not retrieve, so a sequence skips it.
    Skip,
}

impl Default for GlobalSize {
    fn default() -> Self {
        GlobalSize::MaxSide(GLOBAL_MAX_SIDE)
    }
}

impl GlobalSize {
    /// From a maximum side as a map's metadata and `--global-max-side` state it: `None` or 0
    /// is [`GlobalSize::Input`].
    pub fn from_max_side(max_side: Option<u32>) -> GlobalSize {
        match max_side {
            None | Some(0) => GlobalSize::Input,
            Some(m) => GlobalSize::MaxSide(m),
        }
    }

    /// From `--global-max-side N` (and the Python binding's `global_max_side`): 0 is
    /// [`GlobalSize::Input`]; a side under [`GLOBAL_MIN_SIDE`] is refused, as it would leave
    /// the deepest level a cell or two and retrieval nothing to rank by.
    pub fn from_flag(max_side: u32) -> Result<GlobalSize, String> {
        match max_side {
            0 => Ok(GlobalSize::Input),
            m if m < GLOBAL_MIN_SIDE => Err(format!(
                "{m}: 0 (the image's own size) or at least {GLOBAL_MIN_SIDE}"
            )),
            m => Ok(GlobalSize::MaxSide(m)),
        }
    }

    /// The size the global descriptor ends up computed at when the input was first resized
    /// to at most `resize_max` (`--resize-max`): such an input is no larger than that, and a
    /// query of the full image is downscaled to the same.
    pub fn effective(self, resize_max: Option<u32>) -> GlobalSize {
        match (self, resize_max) {
            (GlobalSize::MaxSide(g), Some(r)) => GlobalSize::MaxSide(g.min(r)),
            (GlobalSize::Input, Some(r)) => GlobalSize::MaxSide(r),
            (size, _) => size,
        }
    }

    /// The side as `--global-max-side` and the features.h5 attribute `sfp.global_max_side`
    /// state it: 0 for the input's own size (and for a skipped one).
    pub fn side(self) -> u32 {
        self.max_side().unwrap_or(0)
    }

    /// What a map records (metadata `global_max_side`): `None` for [`GlobalSize::Input`].
    pub fn max_side(self) -> Option<u32> {
        match self {
            GlobalSize::MaxSide(m) => Some(m),
            GlobalSize::Input | GlobalSize::Skip => None,
        }
    }

    /// Whether an input of `width` x `height` gets its global descriptor from an inference of
    /// its own (on a downscaled copy) at this size.
    pub fn needs_a_copy(self, width: usize, height: usize) -> bool {
        self.max_side()
            .is_some_and(|m| width.max(height) > m as usize)
    }

    /// The size a sequence's frame of `width` x `height` is extracted at: [`GlobalSize::Skip`]
    /// when `tracked` (a frame with a pose prior does not retrieve) and the descriptor would
    /// cost an inference of its own, else `self`. A frame whose size differs from `self` was
    /// skipped, and gets its descriptor from [`Extractor::global_of`] if it loses tracking.
    pub fn for_frame(self, tracked: bool, width: usize, height: usize) -> GlobalSize {
        if tracked && self.needs_a_copy(width, height) {
            GlobalSize::Skip
        } else {
            self
        }
    }

    /// The size a map's global descriptors were computed at, which its queries' must share.
    pub fn of_map(metadata: &crate::format::Metadata) -> GlobalSize {
        GlobalSize::from_max_side(metadata.global_side())
    }
}

impl Extractor {
    /// The global descriptor of `input` at `size`: `dense.global` (`input`'s own inference)
    /// when the input fits, else the `global` of an inference on a downscaled copy; empty for
    /// [`GlobalSize::Skip`].
    pub fn global(
        &mut self,
        input: &GrayInput,
        dense: &Dense,
        size: GlobalSize,
    ) -> Result<Vec<f32>, ExtractError> {
        match size {
            // A model without a global head (`sfp.global_dim = 0`) has none at any size.
            _ if self.contract.global_dim == 0 => Ok(Vec::new()),
            GlobalSize::Skip => Ok(Vec::new()),
            _ if size.needs_a_copy(input.width, input.height) => self.global_of(input, size),
            _ => Ok(dense.global.clone()),
        }
    }

    /// [`Extractor::global`] without the input's inference at hand: one inference, on the
    /// downscaled copy where `size` asks for one, else on `input`.
    pub fn global_of(
        &mut self,
        input: &GrayInput,
        size: GlobalSize,
    ) -> Result<Vec<f32>, ExtractError> {
        self.check_values(input)?;
        if self.contract.global_dim == 0 {
            return Ok(Vec::new());
        }
        match (size, size.max_side().and_then(|m| input.downscaled(m))) {
            (GlobalSize::Skip, _) => Ok(Vec::new()),
            (_, Some(small)) => Ok(self.run(&small)?.global),
            (_, None) => Ok(self.run(input)?.global),
        }
    }

    /// A hand-made input whose values do not fill it is refused before any resize, which
    /// would otherwise take the buffer for one that fits.
    fn check_values(&self, input: &GrayInput) -> Result<(), ExtractError> {
        if input.values.len() == input.width.saturating_mul(input.height) {
            return Ok(());
        }
        Err(ExtractError::Inference {
            model: self.model.name.clone(),
            image: None,
            reason: format!(
                "the input holds {} values for {}x{} pixels",
                input.values.len(),
                input.width,
                input.height
            ),
        })
    }
}
