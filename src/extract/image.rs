//! Images in (JPEG/PNG via the `image` crate) → the model's one-channel input.

use super::ExtractError;
use image::{DynamicImage, GrayImage};
use std::path::Path;

/// A grey image with values in [0, 1], row-major, and how it relates to the file.
#[derive(Debug, Clone)]
pub struct GrayInput {
    /// Width in pixels (after any resize).
    pub width: usize,
    /// Height in pixels (after any resize).
    pub height: usize,
    /// `[height × width]` grey values, row-major.
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

    /// A copy downscaled (triangle filter, as [`from_image`] resizes) so its longer side is
    /// `max_side`, with the same `original_size`; `None` when it already fits.
    pub fn downscaled(&self, max_side: u32) -> Option<GrayInput> {
        let longer = self.width.max(self.height);
        if max_side == 0 || longer <= max_side as usize {
            return None;
        }
        let s = f64::from(max_side) / longer as f64;
        let side = |v: usize| ((v as f64 * s).round() as u32).max(1);
        let (w, h) = (side(self.width), side(self.height));
        let buffer = image::ImageBuffer::<image::Luma<f32>, &[f32]>::from_raw(
            self.width as u32,
            self.height as u32,
            &self.values[..],
        )?;
        let small = image::imageops::resize(&buffer, w, h, image::imageops::FilterType::Triangle);
        Some(GrayInput {
            width: w as usize,
            height: h as usize,
            values: small.into_raw(),
            original_size: self.original_size,
        })
    }
}

/// Decodes an image file (format from its content) into the model's input.
pub fn load(
    path: &Path,
    weights: [f32; 3],
    resize_max: Option<u32>,
) -> Result<GrayInput, ExtractError> {
    let bytes = crate::input::read_regular(path).map_err(|e| ExtractError::Io {
        path: path.to_path_buf(),
        source: e.into(),
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
    let decoded = decode_complete(bytes).map_err(|source| ExtractError::Image {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(from_image(&decoded, weights, resize_max))
}

/// Most bytes a decoded image may take (the `image` crate's default allocation limit).
pub(crate) const MAX_DECODED_BYTES: u64 = 512 << 20;

/// Decodes an image file's bytes (format from its content), refusing any that does not decode
/// completely. PNG carries CRCs, which the `png` crate checks. JPEG carries no checksum, and the
/// `image` crate decodes it leniently (a cut-off or damaged scan becomes grey and counts as a
/// success), so JPEG goes through zune-jpeg in strict mode, and the scan must end in an
/// end-of-image marker. A flip that leaves a well-formed stream still decodes (to other
/// pixels): no decoder can tell.
pub(crate) fn decode_complete(bytes: &[u8]) -> Result<DynamicImage, image::ImageError> {
    if image::guess_format(bytes).ok() != Some(image::ImageFormat::Jpeg) {
        return image::load_from_memory(bytes);
    }
    decode_jpeg_strict(bytes).map_err(|reason| {
        image::ImageError::Decoding(image::error::DecodingError::new(
            image::ImageFormat::Jpeg.into(),
            reason,
        ))
    })
}

/// A JPEG decoded as the `image` crate would (same colour spaces, same pixels), but failing
/// where that one fills in: zune-jpeg's strict mode, then the end-of-image check.
fn decode_jpeg_strict(bytes: &[u8]) -> Result<DynamicImage, String> {
    use zune_core::colorspace::ColorSpace;
    let options = zune_core::options::DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(usize::MAX)
        .set_max_height(usize::MAX);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(
        zune_core::bytestream::ZCursor::new(bytes),
        options,
    );
    decoder.decode_headers().map_err(|e| e.to_string())?;
    let (width, height) = decoder.dimensions().ok_or("no image dimensions")?;
    // The colour spaces the `image` crate keeps; it converts the others (CMYK, YCCK) to RGB.
    let out = match decoder.input_colorspace() {
        Some(c @ (ColorSpace::RGB | ColorSpace::RGBA | ColorSpace::Luma | ColorSpace::LumaA)) => c,
        _ => ColorSpace::RGB,
    };
    let bytes_needed = (width as u64)
        .checked_mul(height as u64)
        .and_then(|n| n.checked_mul(out.num_components() as u64));
    if bytes_needed.is_none_or(|n| n > MAX_DECODED_BYTES) {
        return Err(format!(
            "{width} x {height} pixels: over the {} MiB decode limit",
            MAX_DECODED_BYTES >> 20
        ));
    }
    decoder.set_options(decoder.options().jpeg_set_out_colorspace(out));
    let pixels = decoder.decode().map_err(|e| e.to_string())?;
    if !ends_with_eoi(bytes) {
        return Err("truncated: the scan does not end in an end-of-image marker".into());
    }
    let (w, h) = (width as u32, height as u32);
    let image = match out {
        ColorSpace::Luma => image::GrayImage::from_raw(w, h, pixels).map(DynamicImage::ImageLuma8),
        ColorSpace::LumaA => {
            image::GrayAlphaImage::from_raw(w, h, pixels).map(DynamicImage::ImageLumaA8)
        }
        ColorSpace::RGBA => image::RgbaImage::from_raw(w, h, pixels).map(DynamicImage::ImageRgba8),
        _ => image::RgbImage::from_raw(w, h, pixels).map(DynamicImage::ImageRgb8),
    };
    image.ok_or_else(|| "decoded pixels do not fill the image".into())
}

/// Whether the JPEG's marker segments, walked from SOI over every scan, reach EOI. A cut-off
/// file does not; an end-of-image marker inside an APP segment (an EXIF thumbnail) is skipped
/// with its segment, so it does not count.
fn ends_with_eoi(bytes: &[u8]) -> bool {
    let byte = |i: usize| bytes.get(i).copied();
    let mut i = 2; // after SOI
    loop {
        // Markers may be preceded by fill bytes (0xFF).
        if byte(i) != Some(0xFF) {
            return false;
        }
        while byte(i + 1) == Some(0xFF) {
            i += 1;
        }
        let Some(marker) = byte(i + 1) else {
            return false;
        };
        i += 2;
        match marker {
            0xD9 => return true,
            // Standalone markers: no length.
            0x01 | 0xD0..=0xD7 => {}
            _ => {
                let (Some(hi), Some(lo)) = (byte(i), byte(i + 1)) else {
                    return false;
                };
                i += usize::from(u16::from_be_bytes([hi, lo]));
                if marker == 0xDA {
                    // Entropy-coded data runs to the next marker that is not a stuffed 0xFF00
                    // or a restart marker.
                    loop {
                        match (byte(i), byte(i + 1)) {
                            (Some(0xFF), Some(m)) if m != 0 && !(0xD0..=0xD7).contains(&m) => break,
                            (Some(_), Some(_)) => i += 1,
                            _ => return false,
                        }
                    }
                }
            }
        }
    }
}

/// Grey values as 8-bit, rounded like PIL's `convert("L")` and OpenCV's grey decode: the
/// network was trained on such images, and the Python reference reads them that way.
pub(crate) fn to_gray8(image: &DynamicImage, weights: [f32; 3]) -> GrayImage {
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

/// The image in grey (the contract's `weights`), resized so its longer side is at most
/// `resize_max` (triangle filter), in [0, 1]; then, if it is still past the network's limit
/// (16 M pixels), downscaled to fit
/// (a 20–24 MP camera photo is an ordinary query). Keypoints come back in the original pixels
/// through `original_size`.
pub fn from_image(image: &DynamicImage, weights: [f32; 3], resize_max: Option<u32>) -> GrayInput {
    let gray = to_gray8(image, weights);
    let original_size = [gray.width(), gray.height()];
    let longer = gray.width().max(gray.height());
    let mut scale = match resize_max {
        Some(m) if m > 0 && longer > m => f64::from(m) / f64::from(longer),
        _ => 1.0,
    };
    let pixels = |s: f64| {
        let w = ((f64::from(gray.width()) * s).round() as u64).max(1);
        let h = ((f64::from(gray.height()) * s).round() as u64).max(1);
        (w, h)
    };
    let (w, h) = pixels(scale);
    if w * h > super::MAX_INPUT_PIXELS {
        scale *= (super::MAX_INPUT_PIXELS as f64 / (w * h) as f64).sqrt();
        // Rounding may land a pixel over: step down until it fits.
        while {
            let (w, h) = pixels(scale);
            w * h > super::MAX_INPUT_PIXELS
        } {
            scale *= 0.999;
        }
    }
    let gray = if scale < 1.0 {
        let (w, h) = pixels(scale);
        image::imageops::resize(
            &gray,
            w as u32,
            h as u32,
            image::imageops::FilterType::Triangle,
        )
    } else {
        gray
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

    fn textured(w: u32, h: u32) -> RgbImage {
        RgbImage::from_fn(w, h, |x, y| {
            let v = ((x as f32 * 0.1).sin() * 60.0 + (y as f32 * 0.07).cos() * 60.0 + 128.0) as u8;
            Rgb([v, (x * 3 % 256) as u8, ((x ^ y) % 256) as u8])
        })
    }

    fn jpeg(image: &DynamicImage) -> Vec<u8> {
        let mut out = Vec::new();
        image
            .write_to(
                &mut std::io::Cursor::new(&mut out),
                image::ImageFormat::Jpeg,
            )
            .unwrap();
        out
    }

    /// Where the (single, baseline) scan's entropy-coded data starts.
    fn scan_start(jpg: &[u8]) -> usize {
        let sos = jpg.windows(2).position(|w| w == [0xFF, 0xDA]).unwrap();
        sos + 2 + usize::from(u16::from_be_bytes([jpg[sos + 2], jpg[sos + 3]]))
    }

    /// The global descriptor's copy: the longer side at the maximum, the aspect kept, the
    /// file's size kept for scaling, the same picture (a 2x2 box of the input, near enough);
    /// an input that fits gets no copy.
    #[test]
    fn a_downscaled_copy_keeps_the_picture_and_the_file_size() {
        let input = from_image(
            &DynamicImage::ImageRgb8(textured(640, 480)),
            [0.299, 0.587, 0.114],
            None,
        );
        assert!(input.downscaled(640).is_none() && input.downscaled(0).is_none());
        let small = input.downscaled(320).unwrap();
        assert_eq!((small.width, small.height), (320, 240));
        assert_eq!(small.original_size, [640, 480]);
        assert_eq!(small.scale(), [2.0, 2.0]);
        // Same mean brightness; and a picture bright on the left, dark on the right, stays so
        // (the triangle filter blurs only the seam's columns).
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        assert!((mean(&small.values) - mean(&input.values)).abs() < 0.005);
        let halves = GrayInput {
            width: 640,
            height: 480,
            values: (0..640 * 480)
                .map(|i| if i % 640 < 320 { 1.0 } else { 0.0 })
                .collect(),
            original_size: [640, 480],
        };
        let small = halves.downscaled(320).unwrap();
        for (x, want) in [
            (0, 1.0),
            (150, 1.0),
            (158, 1.0),
            (161, 0.0),
            (200, 0.0),
            (319, 0.0),
        ] {
            for y in [0, 120, 239] {
                let got = small.values[y * 320 + x];
                assert!((got - want).abs() < 1e-5, "({x}, {y}): {got}");
            }
        }
        let odd = input.downscaled(101).unwrap();
        assert_eq!((odd.width, odd.height), (101, 76));
    }

    #[test]
    fn a_complete_jpeg_decodes_as_the_image_crate_does() {
        for image in [
            DynamicImage::ImageRgb8(textured(97, 61)),
            DynamicImage::ImageLuma8(DynamicImage::ImageRgb8(textured(64, 48)).to_luma8()),
        ] {
            let bytes = jpeg(&image);
            let ours = decode_complete(&bytes).unwrap();
            let theirs = image::load_from_memory(&bytes).unwrap();
            assert_eq!(ours.color(), theirs.color());
            assert_eq!(ours.as_bytes(), theirs.as_bytes());
        }
    }

    #[test]
    fn every_truncation_of_a_jpeg_is_refused() {
        let bytes = jpeg(&DynamicImage::ImageRgb8(textured(64, 48)));
        // The lenient decoder accepts most of these (filled with grey).
        assert!(image::load_from_memory(&bytes[..bytes.len() - 2]).is_ok());
        for cut in scan_start(&bytes)..bytes.len() {
            let e = decode_complete(&bytes[..cut]).unwrap_err();
            assert!(matches!(e, image::ImageError::Decoding(_)), "{cut}: {e}");
        }
    }

    #[test]
    fn damaged_entropy_data_that_breaks_the_code_is_refused() {
        let bytes = jpeg(&DynamicImage::ImageRgb8(textured(160, 120)));
        let mid = (scan_start(&bytes) + bytes.len()) / 2;
        // A burst of set bits (stuffed 0xFF bytes: no code is all ones), and bytes flipped
        // over a stretch of the scan (no 0xFF made, so no stray marker either).
        let mut ones = bytes.clone();
        for (i, b) in ones[mid..mid + 32].iter_mut().enumerate() {
            *b = if i % 2 == 0 { 0xFF } else { 0x00 };
        }
        let mut flipped = bytes.clone();
        for b in flipped[mid..mid + 200]
            .iter_mut()
            .filter(|b| **b != 0xFF && **b != 0x00)
        {
            *b = (*b ^ 0x5A).min(0xFE);
        }
        for (what, damaged) in [("ones", ones), ("flipped", flipped)] {
            assert!(
                image::load_from_memory(&damaged).is_ok(),
                "{what}: lenient fails"
            );
            assert!(decode_complete(&damaged).is_err(), "{what}: accepted");
        }
    }

    #[test]
    fn png_damage_is_refused_by_its_checksums() {
        let mut bytes = Vec::new();
        DynamicImage::ImageRgb8(textured(40, 30))
            .write_to(
                &mut std::io::Cursor::new(&mut bytes),
                image::ImageFormat::Png,
            )
            .unwrap();
        assert!(decode_complete(&bytes).is_ok());
        assert!(decode_complete(&bytes[..bytes.len() - 20]).is_err());
        let mut flipped = bytes.clone();
        let mid = bytes.len() / 2;
        flipped[mid] ^= 0x10;
        assert!(decode_complete(&flipped).is_err());
    }

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

    #[test]
    fn an_input_past_the_network_cap_is_downscaled_to_fit_not_refused() {
        // 16,794,625 pixels, just past 2^24: a grey image, so the test stays cheap.
        let (w, h) = (16_385u32, 1_025u32);
        let img = DynamicImage::ImageLuma8(GrayImage::new(w, h));
        let input = from_image(&img, [0.299, 0.587, 0.114], None);
        let pixels = (input.width * input.height) as u64;
        assert!(pixels <= super::super::MAX_INPUT_PIXELS, "{pixels}");
        assert!(
            pixels > super::super::MAX_INPUT_PIXELS * 99 / 100,
            "{pixels}"
        );
        assert_eq!(input.original_size, [w, h]);
        assert_eq!(
            super::super::too_large_for_the_network(input.width, input.height),
            None
        );
        // Under the cap nothing changes.
        let img = DynamicImage::ImageLuma8(GrayImage::new(4032, 3024));
        let input = from_image(&img, [0.299, 0.587, 0.114], None);
        assert_eq!((input.width, input.height), (4032, 3024));
    }
}
