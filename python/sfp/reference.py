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
            out = np.fmax(out, pad[dy:dy + h, dx:dx + w])  # NaN cells ignored, as in Rust
    return out


def quad(m, c, p):
    """Offset of a 1-D quadratic's peak through (-1, m), (0, c), (1, p), within +-0.5."""
    den = m - 2 * c + p
    safe = np.where(np.abs(den) > 1e-9, den, 1.0)
    with np.errstate(invalid="ignore"):
        d = np.where(np.abs(den) > 1e-9, 0.5 * (m - p) / safe, 0.0)
    d = np.where(np.isnan(d), 0.0, d)  # an infinite neighbour: inf / inf, no vertex (as Rust)
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


REFINE_FROM_LEVEL = 2  # src/extract/mod.rs: REFINE_FROM_LEVEL


def refine_on(finer, finer_stride, radius, px):
    """Coarse-to-fine refinement (spec/extractor.md): each pixel position (pixel-centre origin 0)
    moves to the strongest interior cell of the finer score map within `radius` finer cells of it
    (first in row order on ties; NaN never wins), refined by the quadratic fit there."""
    h, w = finer.shape
    out = px.astype(np.float32).copy()
    if h < 3 or w < 3:
        return out
    for k, (x, y) in enumerate(px):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        cx = np.floor(np.float32(x) / np.float32(finer_stride) + np.float32(0.5))
        cy = np.floor(np.float32(y) / np.float32(finer_stride) + np.float32(0.5))
        x0, x1 = max(cx - radius, 1), min(cx + radius, w - 2)
        y0, y1 = max(cy - radius, 1), min(cy + radius, h - 2)
        if x0 > x1 or y0 > y1:
            continue
        win = finer[int(y0):int(y1) + 1, int(x0):int(x1) + 1]
        flat = win.ravel()  # row order
        ok = np.flatnonzero(~np.isnan(flat))
        if ok.size == 0:
            continue
        a = np.unravel_index(ok[np.argmax(flat[ok])], win.shape)  # first strongest non-NaN
        yy, xx = int(y0) + a[0], int(x0) + a[1]
        dx = quad(finer[yy, xx - 1], finer[yy, xx], finer[yy, xx + 1])
        dy = quad(finer[yy - 1, xx], finer[yy, xx], finer[yy + 1, xx])
        out[k] = [(xx + dx) * finer_stride, (yy + dy) * finer_stride]
    return out


def level_features(feats, scores, strides, radius, thr, topk, refine=True, refine_to=None):
    """Per level: (pixels with the pixel-centre origin at 0, short, full, scores).

    `feats[i]` is [C_i, h_i, w_i], `scores[i]` [h_i, w_i]; a level's full descriptor joins the
    normalised samples of it and every deeper level at its keypoints, normalised again. Levels
    from REFINE_FROM_LEVEL on are refined on the next finer level's score map (`refine`), and
    on from there one level at a time down to level `refine_to` (the model's
    `sfp.refine_to_level`; None: one level only).
    """
    if refine_to is not None and not 0 <= refine_to < len(strides):
        raise ValueError(f"refine_to = {refine_to} is no level of {len(strides)}")
    out = []
    for i, stride in enumerate(strides):
        cells, v = detect(scores[i], radius, thr, topk[i])
        px = cells * stride
        if refine and i >= max(REFINE_FROM_LEVEL, 1):
            finest = i - 1 if refine_to is None else min(refine_to, i - 1)
            for j in range(i - 1, finest - 1, -1):
                r = max(1, int(np.floor(strides[j + 1] / strides[j] / 2 + 0.5)))  # half up, as Rust
                px = refine_on(scores[j], strides[j], r, px)
            cells = px / stride
        short = l2n(bilinear(feats[i], cells))
        parts = [l2n(bilinear(feats[j], px / strides[j])) for j in range(i, len(strides))]
        out.append((px, short, l2n(np.concatenate(parts, 1)), v))
    return out
