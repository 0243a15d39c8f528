//! Image refinement (`spec/extractor.md` step 5, `sfp-extractor/2` and `/3`): a keypoint moves to the
//! nearest sharp blob of the input image itself, the peak of a difference of Gaussians at the
//! level's scale, fitted to sub-pixel precision.
//!
//! Why: a level's score map has one cell per 2–16 pixels, and its quadratic fit places a
//! keypoint to about a pixel or two; the image's own blobs are as sharp as SIFT's. On 200
//! held-out homography pairs sfp-v2's level-2 viewpoint MMA@1 goes from 0.31 to 0.51.
//!
//! The response is computed only in each keypoint's window (a few hundred pixels), never over
//! the whole image: a 640×480 blur per scale would cost more than the network.

use super::keypoints::{interior_window, subpixel, ScoreMap};

/// The ratio of the two Gaussians' sigmas (SIFT's DoG uses 2^(1/3) to 2; 1.6 approximates the
/// Laplacian of Gaussian best, Marr–Hildreth). python/sfp/reference.py: SIGMA_RATIO.
pub const SIGMA_RATIO: f32 = 1.6;

/// The smallest sigma (input pixels) a refined level may ask for: under half a pixel the
/// Gaussian is hardly a blur and its "blobs" are single noisy pixels.
pub const MIN_SIGMA: f32 = 0.5;

/// The largest sigma (input pixels) a model may ask for. A keypoint's blur costs about
/// (2r + 3 + 10σ)² · 10σ multiply-adds: at 6 and [`MAX_RADIUS`] some 0.3 M, so a level of a
/// million keypoints (the most a model may ask for) stays within minutes, not hours.
/// sfp-v3 uses at most 4. python/sfp/reference.py: MAX_SIGMA.
pub const MAX_SIGMA: f32 = 6.0;

/// The largest search radius (input pixels) a model may ask for. python/sfp/reference.py:
/// MAX_RADIUS.
pub const MAX_RADIUS: u32 = 8;

/// A level's image refinement: the DoG's smaller sigma and the search radius, in input pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImageRefine {
    /// The smaller Gaussian's sigma (the larger's is [`SIGMA_RATIO`] times it).
    pub sigma: f32,
    /// How far a keypoint may move, per axis.
    pub radius: u32,
}

impl ImageRefine {
    /// About how many multiply-adds refining one keypoint takes (both blurs' two passes over
    /// its window): what the extractor's threads share levels by.
    pub fn work_per_keypoint(&self) -> usize {
        let side = 2 * self.radius as usize + 3;
        [self.sigma, self.sigma * SIGMA_RATIO]
            .iter()
            .map(|&s| {
                let taps = 2 * (3.0 * s).ceil() as usize + 1;
                2 * side * (side + taps - 1) * taps
            })
            .sum()
    }
}

/// A grey input plane, row-major, as the network saw it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Plane<'a> {
    /// Pixels per row.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `[height × width]` grey values.
    pub values: &'a [f32],
}

/// A normalised 1-D Gaussian of `sigma`, truncated at ceil(3 sigma): weights from
/// exp(−t²/2σ²) in f64, divided by their sum, then f32 (python/sfp/reference.py's rule).
pub(crate) fn gaussian_kernel(sigma: f32) -> Vec<f32> {
    let s = f64::from(sigma);
    let k = (3.0 * s).ceil() as i64;
    let w: Vec<f64> = (-k..=k)
        .map(|t| (-((t * t) as f64) / (2.0 * s * s)).exp())
        .collect();
    let sum: f64 = w.iter().sum();
    w.iter().map(|v| (v / sum) as f32).collect()
}

/// Reusable buffers and the two kernels of one level's refinement.
pub(crate) struct Refiner {
    refine: ImageRefine,
    small: Vec<f32>,
    large: Vec<f32>,
    block: Vec<f32>,
    columns: Vec<f32>,
    blur: [Vec<f32>; 2],
    response: Vec<f32>,
}

impl Refiner {
    /// A refiner for one level's parameters, which the contract has held to
    /// [`MIN_SIGMA`]…[`MAX_SIGMA`] and [`MAX_RADIUS`].
    pub(crate) fn new(refine: ImageRefine) -> Refiner {
        assert!(
            (MIN_SIGMA..=MAX_SIGMA).contains(&refine.sigma) && refine.radius <= MAX_RADIUS,
            "{refine:?} is outside the contract's ranges"
        );
        Refiner {
            refine,
            small: gaussian_kernel(refine.sigma),
            large: gaussian_kernel(refine.sigma * SIGMA_RATIO),
            block: Vec::new(),
            columns: Vec::new(),
            blur: [Vec::new(), Vec::new()],
            response: Vec::new(),
        }
    }

    /// Keypoint (x, y) (input pixels, pixel-index convention) moved to the strongest pixel of
    /// |G_σ ∗ I − G_1.6σ ∗ I| within `radius` pixels of (floor(x + ½), floor(y + ½)) (the
    /// window clipped to the image's interior; first strongest in row order), when that pixel
    /// is greater than its 8 neighbours, fitted there as score maps are ([`subpixel`]).
    /// Unchanged otherwise (no peak in the window: an edge or a flat patch).
    pub(crate) fn refine(&mut self, image: Plane<'_>, x: f32, y: f32) -> (f32, f32) {
        let (w, h) = (image.width, image.height);
        if w < 3 || h < 3 || !x.is_finite() || !y.is_finite() {
            return (x, y);
        }
        let Some((x0, x1, y0, y1)) = interior_window(x, y, self.refine.radius as usize, w, h)
        else {
            return (x, y);
        };
        // The response on the window and a ring of one pixel (the peak test and the fit).
        let (u0, v0) = (x0 - 1, y0 - 1);
        let (pw, ph) = (x1 + 2 - u0, y1 + 2 - v0);
        self.response_on(image, u0, v0, pw, ph);
        let patch = ScoreMap {
            height: ph,
            width: pw,
            values: &self.response,
        };
        let mut best: Option<(f32, usize, usize)> = None;
        for r in 1..ph - 1 {
            for c in 1..pw - 1 {
                let v = self.response[r * pw + c];
                if best.is_none_or(|(b, _, _)| v > b) && !v.is_nan() {
                    best = Some((v, r, c));
                }
            }
        }
        let Some((v, r, c)) = best else {
            return (x, y);
        };
        // A strict maximum: a flat patch or a ridge has none.
        let peak = (r - 1..=r + 1).all(|rr| {
            (c - 1..=c + 1).all(|cc| (rr, cc) == (r, c) || self.response[rr * pw + cc] < v)
        });
        if !peak {
            return (x, y);
        }
        let (dx, dy) = subpixel(patch, r, c);
        ((u0 + c) as f32 + dx, (v0 + r) as f32 + dy)
    }

    /// `self.response` = the DoG magnitude on the pw × ph pixels from (u0, v0), each Gaussian
    /// separable, along columns first, then along rows, edge pixels repeated beyond the
    /// border; each output sums its taps in order (python/sfp/reference.py adds in the same
    /// order, bit for bit). Both passes run over one flat block per tap, so the loops are long
    /// and vectorise: the row pass also fills the 2k columns past each row's end, which it
    /// reads from the next row and never uses (cheaper than short loops).
    fn response_on(&mut self, image: Plane<'_>, u0: usize, v0: usize, pw: usize, ph: usize) {
        for (which, kernel) in [(0, &self.small), (1, &self.large)] {
            let k = kernel.len() / 2;
            // The image's pixels v0 − k … v0 + ph − 1 + k by u0 − k … u0 + pw − 1 + k.
            let seg = pw + 2 * k;
            let nrows = ph + 2 * k;
            self.block.clear();
            self.block.reserve(nrows * seg);
            for i in 0..nrows {
                let y = clamp(v0 as i64 + i as i64 - k as i64, image.height);
                let row = &image.values[y * image.width..(y + 1) * image.width];
                match u0.checked_sub(k).and_then(|a| row.get(a..a + seg)) {
                    Some(inside) => self.block.extend_from_slice(inside),
                    None => self.block.extend(
                        (0..seg).map(|j| row[clamp(u0 as i64 + j as i64 - k as i64, image.width)]),
                    ),
                }
            }
            // Along columns: ph rows of seg values.
            self.columns.clear();
            self.columns.resize(ph * seg, 0.0);
            for (t, &g) in kernel.iter().enumerate() {
                let src = &self.block[t * seg..(t + ph) * seg];
                for (o, &v) in self.columns.iter_mut().zip(src) {
                    *o += g * v;
                }
            }
            // Along rows: output (i, j) at i·seg + j, j < pw.
            let n = ph * seg - 2 * k;
            let out = &mut self.blur[which];
            out.clear();
            out.resize(n, 0.0);
            for (t, &g) in kernel.iter().enumerate() {
                for (o, &v) in out.iter_mut().zip(&self.columns[t..t + n]) {
                    *o += g * v;
                }
            }
        }
        let (s0, s1) = (self.small.len() / 2 * 2 + pw, self.large.len() / 2 * 2 + pw);
        self.response.clear();
        for i in 0..ph {
            let a = &self.blur[0][i * s0..i * s0 + pw];
            let b = &self.blur[1][i * s1..i * s1 + pw];
            self.response
                .extend(a.iter().zip(b).map(|(a, b)| (a - b).abs()));
        }
    }
}

/// Index `i` clamped to 0 … n − 1 (edge pixels repeat beyond the border).
fn clamp(i: i64, n: usize) -> usize {
    i.clamp(0, n as i64 - 1) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blob(w: usize, h: usize, cx: f32, cy: f32, s: f32) -> Vec<f32> {
        (0..h)
            .flat_map(|r| {
                (0..w).map(move |c| {
                    let d2 = (c as f32 - cx).powi(2) + (r as f32 - cy).powi(2);
                    0.2 + 0.6 * (-d2 / (2.0 * s * s)).exp()
                })
            })
            .collect()
    }

    #[test]
    fn the_kernel_sums_to_one_and_is_symmetric() {
        for s in [0.5, 1.0, 2.5, 4.0] {
            let k = gaussian_kernel(s);
            assert_eq!(k.len(), 2 * (3.0 * s).ceil() as usize + 1);
            assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-5);
            assert!(k.iter().zip(k.iter().rev()).all(|(a, b)| a == b));
        }
    }

    #[test]
    fn a_keypoint_moves_onto_a_blob_within_its_radius_to_a_tenth_of_a_pixel() {
        let (w, h) = (40, 30);
        let img = blob(w, h, 17.3, 12.6, 3.0);
        let plane = Plane {
            width: w,
            height: h,
            values: &img,
        };
        let mut r = Refiner::new(ImageRefine {
            sigma: 3.0,
            radius: 4,
        });
        let (x, y) = r.refine(plane, 15.0, 14.0);
        assert!(
            (x - 17.3).abs() < 0.1 && (y - 12.6).abs() < 0.1,
            "({x}, {y})"
        );
        // Too far: the window holds no peak, the keypoint stays.
        assert_eq!(r.refine(plane, 3.0, 3.0), (3.0, 3.0));
    }

    #[test]
    fn a_flat_image_and_positions_outside_leave_the_keypoint() {
        let img = vec![0.5f32; 20 * 20];
        let plane = Plane {
            width: 20,
            height: 20,
            values: &img,
        };
        let mut r = Refiner::new(ImageRefine {
            sigma: 2.0,
            radius: 3,
        });
        for p in [(7.0, 8.0), (-100.0, 5.0), (1e9, 1e9), (f32::NAN, 2.0)] {
            let q = r.refine(plane, p.0, p.1);
            assert!(q == p || (p.0.is_nan() && q.0.is_nan()), "{p:?} -> {q:?}");
        }
        let tiny = vec![0.5f32; 4];
        let small = Plane {
            width: 2,
            height: 2,
            values: &tiny,
        };
        assert_eq!(r.refine(small, 0.0, 1.0), (0.0, 1.0));
    }

    /// The blocked, vectorised passes against the definition evaluated pixel by pixel (columns,
    /// then rows, edge pixels repeated, taps in order): equal to the bit, at the border too.
    #[test]
    fn the_response_is_the_separable_difference_of_gaussians_pixel_by_pixel() {
        let (w, h) = (23usize, 17usize);
        let img: Vec<f32> = (0..w * h)
            .map(|i| ((i * 7919 % 251) as f32) / 251.0)
            .collect();
        let plane = Plane {
            width: w,
            height: h,
            values: &img,
        };
        let blur_at = |kernel: &[f32], x: usize, y: usize| -> f32 {
            let k = kernel.len() as i64 / 2;
            let column = |xx: usize| {
                let mut acc = 0.0f32;
                for (t, &g) in kernel.iter().enumerate() {
                    acc += g * img[clamp(y as i64 + t as i64 - k, h) * w + xx];
                }
                acc
            };
            let mut acc = 0.0f32;
            for (t, &g) in kernel.iter().enumerate() {
                acc += g * column(clamp(x as i64 + t as i64 - k, w));
            }
            acc
        };
        let mut r = Refiner::new(ImageRefine {
            sigma: 1.5,
            radius: 3,
        });
        for (u0, v0, pw, ph) in [(0, 0, 9, 9), (14, 8, 9, 9), (5, 3, 4, 7)] {
            r.response_on(plane, u0, v0, pw, ph);
            for i in 0..ph {
                for j in 0..pw {
                    let (x, y) = (u0 + j, v0 + i);
                    let want = (blur_at(&r.small, x, y) - blur_at(&r.large, x, y)).abs();
                    assert_eq!(r.response[i * pw + j], want, "({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn the_window_at_the_border_repeats_edge_pixels() {
        // A blob centred on the image's second column: found, and no index leaves the image.
        let (w, h) = (24, 24);
        let img = blob(w, h, 1.2, 11.0, 1.5);
        let plane = Plane {
            width: w,
            height: h,
            values: &img,
        };
        let mut r = Refiner::new(ImageRefine {
            sigma: 1.5,
            radius: 3,
        });
        let (x, y) = r.refine(plane, 2.0, 12.0);
        assert!(
            (x - 1.2).abs() < 0.5 && (y - 11.0).abs() < 0.2,
            "({x}, {y})"
        );
    }
}
