//! Images in (JPEG/PNG via the `image` crate) → the model's one-channel input.

use super::ExtractError;
use image::{DynamicImage, GrayImage};
use std::path::Path;

/// A grey image with values in [0, 1], row-major, and how it relates to the file.
#[derive(Debug, Clone)]
pub struct GrayInput {
    pub width: usize,
    pub height: usize,
    pub values: Vec<f32>,
    /// Size of the image as stored in the file (before any resize).
    pub original_size: [u32; 2],
}

impl GrayInput {
    /// Factor from this input's pixels to the original's (1 when not resized), per axis.
    pub fn scale(&self) -> [f32; 2] {
        [
            self.original_size[0] as f32 / self.width as f32,
            self.original_size[1] as f32 / self.height as f32,
        ]
    }
}

/// Decodes an image file (format from its content) into the model's input.
pub fn load(
    path: &Path,
    weights: [f32; 3],
    resize_max: Option<u32>,
) -> Result<GrayInput, ExtractError> {
    let bytes = std::fs::read(path).map_err(|source| ExtractError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    decode(&bytes, path, weights, resize_max)
}

/// [`load`] on the bytes of an image file already read; `path` names it in errors.
pub fn decode(
    bytes: &[u8],
    path: &Path,
    weights: [f32; 3],
    resize_max: Option<u32>,
) -> Result<GrayInput, ExtractError> {
    let decoded = image::load_from_memory(bytes).map_err(|source| ExtractError::Image {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(from_image(&decoded, weights, resize_max))
}

/// Grey values as 8-bit, rounded like PIL's `convert("L")` and OpenCV's grey decode: the
/// network was trained on such images, and the Python reference reads them that way.
pub fn to_gray8(image: &DynamicImage, weights: [f32; 3]) -> GrayImage {
    match image {
        DynamicImage::ImageLuma8(g) => g.clone(),
        other => {
            let rgb = other.to_rgb8();
            // Fixed point with 16 fractional bits, as PIL does (0.299 → 19595 / 65536).
            let w = weights.map(|v| (v * 65536.0).round() as u32);
            let (width, height) = rgb.dimensions();
            let data = rgb
                .pixels()
                .map(|p| {
                    let [r, g, b] = p.0.map(u32::from);
                    ((r * w[0] + g * w[1] + b * w[2] + 0x8000) >> 16).min(255) as u8
                })
                .collect();
            GrayImage::from_raw(width, height, data).expect("one byte per pixel")
        }
    }
}

/// [`to_gray8`], resized so its longer side is at most `resize_max` (triangle filter), in [0, 1].
pub fn from_image(image: &DynamicImage, weights: [f32; 3], resize_max: Option<u32>) -> GrayInput {
    let gray = to_gray8(image, weights);
    let original_size = [gray.width(), gray.height()];
    let gray = match resize_max {
        Some(m) if m > 0 && gray.width().max(gray.height()) > m => {
            let s = m as f64 / gray.width().max(gray.height()) as f64;
            let w = ((gray.width() as f64 * s).round() as u32).max(1);
            let h = ((gray.height() as f64 * s).round() as u32).max(1);
            image::imageops::resize(&gray, w, h, image::imageops::FilterType::Triangle)
        }
        _ => gray,
    };
    GrayInput {
        width: gray.width() as usize,
        height: gray.height() as usize,
        values: gray
            .as_raw()
            .iter()
            .map(|&v| f32::from(v) / 255.0)
            .collect(),
        original_size,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::{Rgb, RgbImage};

    #[test]
    fn gray_matches_pil_rounding_and_resize_keeps_aspect() {
        let img = RgbImage::from_fn(40, 20, |x, y| Rgb([(x * 6) as u8, (y * 12) as u8, 200]));
        let g = to_gray8(&DynamicImage::ImageRgb8(img.clone()), [0.299, 0.587, 0.114]);
        for (p, q) in img.pixels().zip(g.pixels()) {
            let [r, gg, b] = p.0.map(u32::from);
            let pil = ((r * 19595 + gg * 38470 + b * 7471 + 0x8000) >> 16) as u8;
            assert_eq!(q.0[0], pil);
        }
        let input = from_image(
            &DynamicImage::ImageRgb8(img),
            [0.299, 0.587, 0.114],
            Some(10),
        );
        assert_eq!((input.width, input.height), (10, 5));
        assert_eq!(input.original_size, [40, 20]);
        assert_eq!(input.scale(), [4.0, 4.0]);
        assert!(input.values.iter().all(|v| (0.0..=1.0).contains(v)));
    }
}
