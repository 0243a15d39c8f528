//! Keypoints from a level's score map (NMS, threshold, top-k, sub-pixel) and descriptors from
//! its dense features (bilinear, corner-aligned), as `spec/extractor.md` defines them.
//!
//! Positions here are in *cell coordinates* of one level: cell (row r, col c) is at (c, r).

/// A row-major 2-D map (`score_i` of one image).
#[derive(Debug, Clone, Copy)]
pub struct ScoreMap<'a> {
    pub height: usize,
    pub width: usize,
    pub values: &'a [f32],
}

/// A dense feature map `[channels × height × width]` (`feat_i` of one image).
#[derive(Debug, Clone, Copy)]
pub struct FeatureMap<'a> {
    pub channels: usize,
    pub height: usize,
    pub width: usize,
    pub values: &'a [f32],
}

/// A detected cell: refined position in cell coordinates and the score at the cell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Peak {
    pub x: f32,
    pub y: f32,
    pub score: f32,
}

impl ScoreMap<'_> {
    fn at(&self, r: usize, c: usize) -> f32 {
        self.values[r * self.width + c]
    }
}

/// Cells that equal the maximum of their (2·radius+1)² neighbourhood (clipped to the map) and
/// score above `threshold`, without the outermost ring of cells; the `max` best, highest score
/// first (ties: row, then column, so the output is deterministic); each refined to sub-cell
/// precision by [`subpixel`].
pub fn detect(map: ScoreMap<'_>, radius: usize, threshold: f32, max: usize) -> Vec<Peak> {
    let (h, w) = (map.height, map.width);
    debug_assert_eq!(map.values.len(), h * w);
    if h < 3 || w < 3 || max == 0 {
        return Vec::new();
    }
    // A cell is a maximum when no cell of its window is greater (NaN cells never are). Small
    // windows test that directly, most cells above the threshold being beaten within a few
    // reads; larger ones read a row-wise sliding maximum, so that a plateau (a saturated
    // score map) costs O(cells x radius), not O(cells x radius^2).
    let row_max = (radius > 2).then(|| sliding_max_rows(map, radius));
    let mut peaks: Vec<(f32, usize, usize)> = Vec::new();
    for r in 1..h - 1 {
        let (r0, r1) = (
            r.saturating_sub(radius),
            r.saturating_add(radius).min(h - 1),
        );
        let row = &map.values[r * w..(r + 1) * w];
        for (c, &v) in row.iter().enumerate().take(w - 1).skip(1) {
            if v.is_nan() || v <= threshold {
                continue;
            }
            let beaten = match &row_max {
                Some(m) => (r0..=r1).any(|rr| m[rr * w + c] > v),
                None => {
                    let (c0, c1) = (c.saturating_sub(radius), (c + radius).min(w - 1));
                    (r0..=r1).any(|rr| map.values[rr * w + c0..=rr * w + c1].iter().any(|&u| u > v))
                }
            };
            if !beaten {
                peaks.push((v, r, c));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
    peaks.truncate(max);
    peaks
        .into_iter()
        .map(|(score, r, c)| {
            let (dx, dy) = subpixel(map, r, c);
            Peak {
                x: c as f32 + dx,
                y: r as f32 + dy,
                score,
            }
        })
        .collect()
}

/// The finest level a keypoint of level `level` (2 or deeper) is refined down to: the model's
/// `sfp.refine_to_level` where it is finer than `level − 1`, else `level − 1` (at least one
/// level, the SFP rule).
pub(crate) fn finest_refined_level(refine_to: Option<usize>, level: usize) -> usize {
    refine_to.map_or(level - 1, |t| t.min(level - 1))
}

/// Moves keypoints at pixels `px` (pixel-index convention) of a level of stride `stride`
/// coarse to fine (`spec/extractor.md` step 4): onto each of `finer`'s (stride, score map) in
/// turn, the next finer level first, each within half a cell of the level before (at least
/// one cell).
pub(crate) fn refine_down(px: &mut [(f32, f32)], stride: f32, finer: &[(f32, ScoreMap<'_>)]) {
    let mut coarser = stride;
    for &(fs, map) in finer {
        // round half up, as python/sfp/reference.py does
        let radius = ((coarser / fs / 2.0 + 0.5).floor() as usize).max(1);
        for p in px.iter_mut() {
            *p = refine_on(map, fs, radius, p.0, p.1);
        }
        coarser = fs;
    }
}

/// A keypoint of a coarse level at pixel (x, y) (pixel-index convention) moved to the
/// strongest cell of the next finer level's score map `finer` (stride `finer_stride`) within
/// `radius` finer cells of it, refined there like a detection ([`subpixel`]); the first
/// strongest in row order wins, NaN cells never do. Unchanged when no interior cell of
/// `finer` lies in the window. See `spec/extractor.md`, "Coarse-to-fine refinement".
pub(crate) fn refine_on(
    finer: ScoreMap<'_>,
    finer_stride: f32,
    radius: usize,
    x: f32,
    y: f32,
) -> (f32, f32) {
    let (h, w) = (finer.height, finer.width);
    if h < 3 || w < 3 || !x.is_finite() || !y.is_finite() {
        return (x, y);
    }
    let Some((x0, x1, y0, y1)) = interior_window(x / finer_stride, y / finer_stride, radius, w, h)
    else {
        return (x, y);
    };
    let mut best: Option<(f32, usize, usize)> = None;
    for rr in y0..=y1 {
        for (cc, &v) in finer.values[rr * w..(rr + 1) * w]
            .iter()
            .enumerate()
            .take(x1 + 1)
            .skip(x0)
        {
            if best.is_none_or(|(b, _, _)| v > b) && !v.is_nan() {
                best = Some((v, rr, cc));
            }
        }
    }
    let Some((_, rr, cc)) = best else {
        return (x, y);
    };
    let (dx, dy) = subpixel(finer, rr, cc);
    (
        (cc as f32 + dx) * finer_stride,
        (rr as f32 + dy) * finer_stride,
    )
}

/// The cells (x0..=x1, y0..=y1) within `radius` of the cell nearest (x, y) (cell
/// coordinates, `floor(x + 0.5)`) of a w × h map, clipped to its interior (a quadratic fit
/// needs both neighbours); `None` when no interior cell is that near. As floats first, so that
/// a position far outside the map cannot wrap.
pub(crate) fn interior_window(
    x: f32,
    y: f32,
    radius: usize,
    w: usize,
    h: usize,
) -> Option<(usize, usize, usize, usize)> {
    let r = radius as f32;
    let (cx, cy) = ((x + 0.5).floor(), (y + 0.5).floor());
    let x0 = (cx - r).max(1.0);
    let x1 = (cx + r).min(w.saturating_sub(2) as f32);
    let y0 = (cy - r).max(1.0);
    let y1 = (cy + r).min(h.saturating_sub(2) as f32);
    (x0 <= x1 && y0 <= y1).then_some((x0 as usize, x1 as usize, y0 as usize, y1 as usize))
}

/// The maximum over each cell's horizontal window of half-width `radius` (clipped; NaN
/// cells ignored).
fn sliding_max_rows(map: ScoreMap<'_>, radius: usize) -> Vec<f32> {
    let (h, w) = (map.height, map.width);
    let mut out = vec![f32::NEG_INFINITY; h * w];
    for (row, out) in map
        .values
        .chunks_exact(w)
        .zip(out.chunks_exact_mut(w))
        .take(h)
    {
        for (c, o) in out.iter_mut().enumerate() {
            let (c0, c1) = (
                c.saturating_sub(radius),
                c.saturating_add(radius).min(w - 1),
            );
            *o = row[c0..=c1]
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max);
        }
    }
    out
}

/// The 1-D quadratic offset through (−1, m), (0, c), (+1, p), clipped to ±0.5; 0 when the
/// curvature is ~0.
pub(crate) fn quadratic_offset(m: f32, c: f32, p: f32) -> f32 {
    let den = m - 2.0 * c + p;
    // NaN neighbours give a NaN curvature: 0 too, as in python/sfp/reference.py.
    if den.is_nan() || den.abs() <= 1e-9 {
        return 0.0;
    }
    let d = 0.5 * (m - p) / den;
    // An infinite neighbour gives inf / inf: no vertex either (clamp keeps a NaN).
    if d.is_nan() {
        return 0.0;
    }
    d.clamp(-0.5, 0.5)
}

/// Sub-cell offsets (dx, dy) of an interior cell, one quadratic fit per axis.
pub(crate) fn subpixel(map: ScoreMap<'_>, r: usize, c: usize) -> (f32, f32) {
    let v = map.at(r, c);
    let dx = quadratic_offset(map.at(r, c - 1), v, map.at(r, c + 1));
    let dy = quadratic_offset(map.at(r - 1, c), v, map.at(r + 1, c));
    (dx, dy)
}

/// Bilinear sample of every channel at cell coordinates (x, y), clamped to the map
/// (`align_corners = true`: integer coordinates hit cell centres). Appends `channels` values.
#[cfg(test)]
pub(crate) fn sample_bilinear(map: FeatureMap<'_>, x: f32, y: f32, out: &mut Vec<f32>) {
    let start = out.len();
    out.resize(start + map.channels, 0.0);
    sample_into(map, x, y, &mut out[start..]);
}

/// [`sample_bilinear`] into `out[..channels]`.
pub(crate) fn sample_into(map: FeatureMap<'_>, x: f32, y: f32, out: &mut [f32]) {
    let (h, w) = (map.height, map.width);
    let plane = h * w;
    let x = if x.is_nan() {
        0.0
    } else {
        x.clamp(0.0, (w - 1) as f32)
    };
    let y = if y.is_nan() {
        0.0
    } else {
        y.clamp(0.0, (h - 1) as f32)
    };
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (ax, ay) = (x - x0 as f32, y - y0 as f32);
    let (w00, w01, w10, w11) = (
        (1.0 - ax) * (1.0 - ay),
        ax * (1.0 - ay),
        (1.0 - ax) * ay,
        ax * ay,
    );
    let (i00, i01, i10, i11) = (y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1);
    for (ch, o) in out.iter_mut().enumerate().take(map.channels) {
        let p = &map.values[ch * plane..(ch + 1) * plane];
        *o = p[i00] * w00 + p[i01] * w01 + p[i10] * w10 + p[i11] * w11;
    }
}

/// Bilinear sample of a one-channel map at cell coordinates (x, y), clamped like
/// [`sample_bilinear`].
pub(crate) fn bilinear_at(map: ScoreMap<'_>, x: f32, y: f32) -> f32 {
    let mut out = [0.0f32; 1];
    let one = FeatureMap {
        channels: 1,
        height: map.height,
        width: map.width,
        values: map.values,
    };
    sample_into(one, x, y, &mut out);
    out[0]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(h: usize, w: usize, f: impl Fn(usize, usize) -> f32) -> Vec<f32> {
        (0..h * w).map(|i| f(i / w, i % w)).collect()
    }

    #[test]
    fn nms_keeps_local_maxima_above_threshold_inside_the_border() {
        // Two bumps, one on the border ring (dropped), one below the threshold.
        let mut v = vec![0.1f32; 8 * 10];
        v[3 * 10 + 4] = 0.9; // peak
        v[3 * 10 + 5] = 0.8; // neighbour, suppressed
        v[6 * 10 + 8] = 0.7; // second peak
        v[10 + 8] = 0.3; // below threshold
        v[9] = 0.95; // border ring
        let peaks = detect(
            ScoreMap {
                height: 8,
                width: 10,
                values: &v,
            },
            1,
            0.5,
            10,
        );
        assert_eq!(peaks.len(), 2);
        assert_eq!((peaks[0].score, peaks[1].score), (0.9, 0.7));
        assert!((peaks[0].y - 3.0).abs() < 1e-6);
        assert!(peaks[0].x > 4.0 && peaks[0].x <= 4.5, "{:?}", peaks[0]);
        assert_eq!((peaks[1].x, peaks[1].y), (8.0, 6.0));
        // The cap keeps the best.
        let one = detect(
            ScoreMap {
                height: 8,
                width: 10,
                values: &v,
            },
            1,
            0.5,
            1,
        );
        assert_eq!(one.len(), 1);
        assert_eq!(one[0].score, 0.9);
    }

    #[test]
    fn nms_radius_two_suppresses_a_peak_two_cells_away() {
        let mut v = vec![0.0f32; 9 * 9];
        v[4 * 9 + 3] = 0.9;
        v[4 * 9 + 5] = 0.8;
        let s = ScoreMap {
            height: 9,
            width: 9,
            values: &v,
        };
        assert_eq!(detect(s, 1, 0.1, 10).len(), 2);
        assert_eq!(detect(s, 2, 0.1, 10).len(), 1);
    }

    #[test]
    fn ties_are_kept_and_ordered_by_position() {
        let mut v = vec![0.0f32; 7 * 7];
        v[2 * 7 + 2] = 0.6;
        v[2 * 7 + 3] = 0.6;
        let p = detect(
            ScoreMap {
                height: 7,
                width: 7,
                values: &v,
            },
            1,
            0.5,
            10,
        );
        // Both plateau cells are kept; each refines towards the other (to x = 2.5).
        assert_eq!(p.len(), 2);
        assert_eq!((p[0].score, p[1].score), (0.6, 0.6));
        assert_eq!((p[0].x, p[1].x), (2.5, 2.5));
    }

    #[test]
    fn subpixel_recovers_the_vertex_of_a_parabola() {
        // score = 1 - (x - 4.3)^2 / 10 - (y - 2.8)^2 / 10: quadratic, so the fit is exact.
        let v = map(6, 9, |r, c| {
            1.0 - ((c as f32 - 4.3).powi(2) + (r as f32 - 2.8).powi(2)) / 10.0
        });
        let p = detect(
            ScoreMap {
                height: 6,
                width: 9,
                values: &v,
            },
            1,
            0.0,
            1,
        );
        assert!(
            (p[0].x - 4.3).abs() < 1e-4 && (p[0].y - 2.8).abs() < 1e-4,
            "{p:?}"
        );
        assert_eq!(quadratic_offset(1.0, 1.0, 1.0), 0.0);
        assert!((quadratic_offset(0.0, 1.0, 0.5) - 1.0 / 6.0).abs() < 1e-6);
        assert_eq!(quadratic_offset(0.0, 1.0, 0.99), 0.5 * 0.99 / 1.01);
        assert_eq!(quadratic_offset(1.0, 0.0, 1.0), 0.0);
    }

    #[test]
    fn bilinear_is_exact_on_planes_and_clamps() {
        // Channel 0: 2x + 3y + 1; channel 1: constant 5.
        let (h, w) = (4, 5);
        let mut v = map(h, w, |r, c| 2.0 * c as f32 + 3.0 * r as f32 + 1.0);
        v.extend(std::iter::repeat_n(5.0, h * w));
        let f = FeatureMap {
            channels: 2,
            height: h,
            width: w,
            values: &v,
        };
        let mut out = Vec::new();
        sample_bilinear(f, 1.25, 2.5, &mut out);
        assert!(
            (out[0] - (2.5 + 7.5 + 1.0)).abs() < 1e-5 && out[1] == 5.0,
            "{out:?}"
        );
        out.clear();
        sample_bilinear(f, 3.0, 1.0, &mut out); // a cell centre exactly
        assert_eq!(out[0], v[w + 3]);
        out.clear();
        sample_bilinear(f, -3.0, 99.0, &mut out); // clamped to (0, h-1)
        assert_eq!(out[0], 10.0);
        out.clear();
        sample_bilinear(f, 4.0, 3.0, &mut out); // the last cell
        assert_eq!(out[0], 18.0);
        let plane = ScoreMap {
            height: h,
            width: w,
            values: &v[..h * w],
        };
        assert!((bilinear_at(plane, 0.5, 0.5) - (1.0 + 1.0 + 1.5)).abs() < 1e-6);
    }

    #[test]
    fn refinement_moves_to_the_finer_peak_within_half_a_coarse_cell() {
        // A finer level of stride 4 with a parabola peaked at cell (6.25, 5): a coarse
        // keypoint at pixel (24, 20) = cell (6, 5) moves onto it.
        let (h, w) = (12, 14);
        let v = map(h, w, |r, c| {
            10.0 - (c as f32 - 6.25).powi(2) - (r as f32 - 5.0).powi(2)
        });
        let finer = ScoreMap {
            height: h,
            width: w,
            values: &v,
        };
        let (x, y) = refine_on(finer, 4.0, 1, 24.0, 20.0);
        assert!(
            (x - 25.0).abs() < 1e-4 && (y - 20.0).abs() < 1e-4,
            "{x} {y}"
        );
        // From cell 10 the peak is out of the window (cells 9..=11): the window's best cell,
        // 9, wins instead, and its fit (the parabola's vertex, 2.75 cells away) clips to -0.5.
        let (x, y) = refine_on(finer, 4.0, 1, 40.0, 20.0);
        assert!(
            (x - 34.0).abs() < 1e-4 && (y - 20.0).abs() < 1e-4,
            "{x} {y}"
        );
    }

    // Peaks placed by hand: a stride-8 keypoint at pixel (16, 16); the stride-4 map's
    // strongest cell within one cell of (4, 4) is (5, 4), pixel (20, 16); from there the
    // stride-2 map's within one cell of (10, 8) is (11, 9), pixel (22, 18). The stride-2 map's
    // strongest cell near (16, 16) itself, (8, 8), is out of that window: the walk goes one
    // level at a time.
    #[test]
    fn refinement_walks_down_one_level_at_a_time() {
        let level1 = map(16, 16, |r, c| if (r, c) == (4, 5) { 1.0 } else { 0.0 });
        let level0 = map(32, 32, |r, c| match (r, c) {
            (9, 11) => 1.0,
            (8, 8) => 2.0,
            _ => 0.0,
        });
        fn score(values: &[f32], side: usize) -> ScoreMap<'_> {
            ScoreMap {
                height: side,
                width: side,
                values,
            }
        }
        let finer = [(4.0, score(&level1, 16)), (2.0, score(&level0, 32))];
        for (n, expected) in [(0, (16.0, 16.0)), (1, (20.0, 16.0)), (2, (22.0, 18.0))] {
            let mut px = [(16.0, 16.0)];
            refine_down(&mut px, 8.0, &finer[..n]);
            assert_eq!(px, [expected], "{n} finer levels");
        }
    }

    #[test]
    fn non_finite_neighbours_leave_the_cell_centre() {
        for (m, c, p) in [
            (f32::INFINITY, 1.0, 0.0),
            (0.0, 1.0, f32::INFINITY),
            (f32::INFINITY, 1.0, f32::INFINITY),
            (f32::NEG_INFINITY, 1.0, 0.0),
            (f32::NAN, 1.0, 0.0),
        ] {
            assert_eq!(quadratic_offset(m, c, p), 0.0, "{m} {c} {p}");
        }
    }

    #[test]
    fn the_walk_goes_at_least_one_level_down_and_no_further_than_asked() {
        assert_eq!(finest_refined_level(None, 2), 1);
        assert_eq!(finest_refined_level(None, 3), 2);
        assert_eq!(finest_refined_level(Some(0), 3), 0);
        assert_eq!(finest_refined_level(Some(1), 3), 1);
        // A level at or past the keypoint's own still refines one level, as without the key.
        assert_eq!(finest_refined_level(Some(2), 2), 1);
        assert_eq!(finest_refined_level(Some(3), 2), 1);
    }

    #[test]
    fn refinement_leaves_what_it_cannot_refine() {
        let v = vec![0.5f32; 4 * 4];
        let tiny = ScoreMap {
            height: 2,
            width: 8,
            values: &v[..16],
        };
        assert_eq!(refine_on(tiny, 2.0, 1, 3.0, 1.0), (3.0, 1.0));
        let finer = ScoreMap {
            height: 4,
            width: 4,
            values: &v,
        };
        // Far outside the map: no interior cell in the window, and nothing wraps.
        assert_eq!(refine_on(finer, 2.0, 1, 1e30, -1e30), (1e30, -1e30));
        assert_eq!(refine_on(finer, 2.0, 1, f32::NAN, 1.0).1, 1.0);
        // A window of NaN cells only.
        let nan = vec![f32::NAN; 16];
        let nan = ScoreMap {
            height: 4,
            width: 4,
            values: &nan,
        };
        assert_eq!(refine_on(nan, 2.0, 1, 3.0, 3.0), (3.0, 3.0));
        // Ties: the first in row order wins (a flat map: the window's top-left interior cell).
        assert_eq!(refine_on(finer, 2.0, 1, 4.0, 4.0), (2.0, 2.0));
    }

    #[test]
    fn both_nms_paths_agree_with_a_plain_window_test() {
        // A bumpy map with plateaus and a NaN: radius 1-2 test the window directly, 3-5 read
        // the sliding row maximum; each must keep exactly the cells no window cell beats.
        let (h, w) = (23, 31);
        let mut v = map(h, w, |r, c| {
            (((r * 7 + c * 13) % 11) as f32 / 10.0).min(0.8)
        });
        v[5 * w + 9] = f32::NAN;
        let m = ScoreMap {
            height: h,
            width: w,
            values: &v,
        };
        for radius in 1..=5 {
            let got = detect(m, radius, 0.1, usize::MAX);
            let mut want = Vec::new();
            for r in 1..h - 1 {
                for c in 1..w - 1 {
                    let x = v[r * w + c];
                    if x.is_nan() || x <= 0.1 {
                        continue;
                    }
                    let beaten = (r.saturating_sub(radius)..=(r + radius).min(h - 1)).any(|rr| {
                        (c.saturating_sub(radius)..=(c + radius).min(w - 1))
                            .any(|cc| v[rr * w + cc] > x)
                    });
                    if !beaten {
                        want.push((r, c));
                    }
                }
            }
            assert!(
                !want.is_empty(),
                "radius {radius}: the map has no peak to test"
            );
            assert_eq!(got.len(), want.len(), "radius {radius}");
            // Each kept cell is a wanted one (its sub-cell fit moves it by at most half a
            // cell, plateaus by exactly half: compare the score at the cell too).
            for p in &got {
                assert!(
                    want.iter().any(|&(r, c)| (p.x - c as f32).abs() <= 0.5
                        && (p.y - r as f32).abs() <= 0.5
                        && p.score == v[r * w + c]),
                    "radius {radius}: {p:?}"
                );
            }
        }
    }
}
