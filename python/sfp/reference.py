"""The SFP extractor's post-processing in numpy (spec/extractor.md): score-map NMS, threshold,
top-k, sub-pixel refinement, bilinear descriptor sampling, short and full descriptors.

The one Python reference of what `sfpmap extract` does after the network; used by
`tests/extract_reference.py` (compared with the Rust extractor) and `python/eval_homography.py`.
Needs only numpy (no torch, no OpenCV).
"""

import numpy as np


def sliding_max(score, r):
    """Max over the (2r+1)^2 window, clipped at the borders."""
    h, w = score.shape
    pad = np.full((h + 2 * r, w + 2 * r), -np.inf, np.float32)
    pad[r:r + h, r:r + w] = score
    out = np.full((h, w), -np.inf, np.float32)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out = np.maximum(out, pad[dy:dy + h, dx:dx + w])
    return out


def quad(m, c, p):
    """Offset of a 1-D quadratic's peak through (-1, m), (0, c), (1, p), within +-0.5."""
    den = m - 2 * c + p
    safe = np.where(np.abs(den) > 1e-9, den, 1.0)
    d = np.where(np.abs(den) > 1e-9, 0.5 * (m - p) / safe, 0.0)
    return np.clip(d, -0.5, 0.5)


def detect(score, radius, thr, k):
    """Cells (x, y) with sub-pixel offsets and scores of the top-k NMS peaks above `thr`."""
    peak = (score >= sliding_max(score, radius)) & (score > thr)
    # the outermost cells have no neighbourhood for the sub-pixel fit
    peak[0, :] = peak[-1, :] = False
    peak[:, 0] = peak[:, -1] = False
    ys, xs = np.nonzero(peak)
    v = score[ys, xs]
    # highest score first, ties by row then column (what the Rust extractor does)
    order = np.lexsort((xs, ys, -v))[:k]
    ys, xs, v = ys[order], xs[order], v[order]
    dx = quad(score[ys, xs - 1], score[ys, xs], score[ys, xs + 1])
    dy = quad(score[ys - 1, xs], score[ys, xs], score[ys + 1, xs])
    return np.stack([xs + dx, ys + dy], 1).astype(np.float32), v


def bilinear(fmap, pts):
    """fmap [C, h, w], pts [K, 2] in cell coordinates (x, y) -> [K, C]."""
    c, h, w = fmap.shape
    x = np.clip(pts[:, 0], 0, w - 1)
    y = np.clip(pts[:, 1], 0, h - 1)
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    ax = (x - x0)[:, None]
    ay = (y - y0)[:, None]
    f = fmap.transpose(1, 2, 0)
    return (f[y0, x0] * (1 - ax) * (1 - ay) + f[y0, x1] * ax * (1 - ay)
            + f[y1, x0] * (1 - ax) * ay + f[y1, x1] * ax * ay)


def l2n(x):
    return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)


def level_features(feats, scores, strides, radius, thr, topk):
    """Per level: (pixels with the pixel-centre origin at 0, short, full, scores).

    `feats[i]` is [C_i, h_i, w_i], `scores[i]` [h_i, w_i]; a level's full descriptor joins the
    normalised samples of it and every deeper level at its keypoints, normalised again.
    """
    out = []
    for i, stride in enumerate(strides):
        cells, v = detect(scores[i], radius, thr, topk[i])
        px = cells * stride
        short = l2n(bilinear(feats[i], cells))
        parts = [l2n(bilinear(feats[j], px / strides[j])) for j in range(i, len(strides))]
        out.append((px, short, l2n(np.concatenate(parts, 1)), v))
    return out
