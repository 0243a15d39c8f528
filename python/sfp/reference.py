"""The SFP extractor's post-processing in numpy (spec/extractor.md): score-map NMS, threshold,
top-k, sub-pixel refinement, bilinear descriptor sampling, short and full descriptors.

The one Python reference of what `sfpmap extract` does after the network; used by
`tests/extract_reference.py` (compared with the Rust extractor) and `python/eval_homography.py`.
Needs only numpy (no torch, no OpenCV).
"""

import re

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


# The contracts (spec/extractor.md; src/extract/contract.rs: CONTRACTS): /2 is /1 plus step 5, /3 is
# /2 plus sfp.detect_level.
CONTRACTS = ("sfp-extractor/1", "sfp-extractor/2", "sfp-extractor/3")
# Step 5's ranges and ratio (src/extract/image_refine.rs: MIN_SIGMA, MAX_SIGMA, MAX_RADIUS, SIGMA_RATIO).
MIN_SIGMA, MAX_SIGMA, MAX_RADIUS = 0.5, 6.0, 8
SIGMA_RATIO = 1.6


def gaussian_kernel(sigma):
    """Normalised 1-D Gaussian truncated at ceil(3 sigma): weights in float64 summed in order (as
    Rust's iter().sum(); numpy's sum is pairwise), then divided and cast to float32."""
    s = np.float64(np.float32(sigma))
    k = int(np.ceil(3.0 * s))
    t = np.arange(-k, k + 1, dtype=np.float64)
    w = np.exp(-(t * t) / (2.0 * s * s))
    total = 0.0
    for v in w:
        total += float(v)
    return (w / total).astype(np.float32)


def _blur_patch(img, u0, v0, pw, ph, kernel):
    """Gaussian blur of img on the pw x ph pixels from (u0, v0): along columns first, then along
    rows, edge pixels repeated, summed tap by tap in float32 (the Rust extractor's order)."""
    h, w = img.shape
    k = len(kernel) // 2
    rows = np.clip(np.arange(v0 - k, v0 + ph + k), 0, h - 1)
    cols = np.clip(np.arange(u0 - k, u0 + pw + k), 0, w - 1)
    block = img[rows][:, cols]
    vert = np.zeros((ph, pw + 2 * k), np.float32)
    for t, g in enumerate(kernel):
        vert += g * block[t:t + ph]
    out = np.zeros((ph, pw), np.float32)
    for t, g in enumerate(kernel):
        out += g * vert[:, t:t + pw]
    return out


def image_refine(img, px, sigma, radius):
    """Step 5 (sfp-extractor/2): each pixel position moves to the strongest pixel of
    |G_sigma * I - G_1.6sigma * I| within `radius` pixels of its rounded position (clipped to the
    image interior, first strongest in row order) when that pixel is greater than its 8
    neighbours, refined there by the quadratic fit; else it stays."""
    img = np.asarray(img, np.float32)
    h, w = img.shape
    out = px.astype(np.float32).copy()
    if h < 3 or w < 3:
        return out
    small, large = gaussian_kernel(sigma), gaussian_kernel(np.float32(sigma) * np.float32(SIGMA_RATIO))
    r = np.float32(radius)
    for n, (x, y) in enumerate(out.copy()):
        if not (np.isfinite(x) and np.isfinite(y)):
            continue
        cx, cy = np.floor(x + np.float32(0.5)), np.floor(y + np.float32(0.5))
        x0, x1 = max(cx - r, 1), min(cx + r, w - 2)
        y0, y1 = max(cy - r, 1), min(cy + r, h - 2)
        if x0 > x1 or y0 > y1:
            continue
        u0, v0 = int(x0) - 1, int(y0) - 1
        pw, ph = int(x1) + 2 - u0, int(y1) + 2 - v0
        resp = np.abs(_blur_patch(img, u0, v0, pw, ph, small) - _blur_patch(img, u0, v0, pw, ph, large))
        inner = resp[1:ph - 1, 1:pw - 1]
        a = np.unravel_index(np.argmax(inner), inner.shape)  # first strongest in row order
        rr, cc = a[0] + 1, a[1] + 1
        v = resp[rr, cc]
        nb = resp[rr - 1:rr + 2, cc - 1:cc + 2].copy()
        nb[1, 1] = -np.inf
        if not (nb < v).all():
            continue
        dx = quad(resp[rr, cc - 1], v, resp[rr, cc + 1])
        dy = quad(resp[rr - 1, cc], v, resp[rr + 1, cc])
        out[n] = [np.float32(u0 + cc) + np.float32(dx), np.float32(v0 + rr) + np.float32(dy)]
    return out


def image_refine_levels(metadata, levels):
    """Per level (sigma, radius) or None, from a model's metadata as src/extract/contract.rs reads
    it (a ValueError where it refuses the model)."""
    keys = ("sfp.image_refine_sigma", "sfp.image_refine_radius")
    contract = metadata.get("sfp.contract")
    if contract not in CONTRACTS:
        raise ValueError(f"contract {contract!r} is not one of {CONTRACTS}")
    if contract == CONTRACTS[0]:
        if any(k in metadata for k in keys):
            raise ValueError(f"{keys} need sfp.contract = {CONTRACTS[1]}")
        return [None] * levels
    sig = [np.float32(v) for v in metadata[keys[0]].split(",")]
    rad = [int(v) for v in metadata[keys[1]].split(",")]
    if len(sig) != levels or len(rad) != levels or min(rad) < 0:
        raise ValueError(f"{keys}: one value a level, radii from 0")
    out = []
    for s, r in zip(sig, rad):
        if s != 0 and not MIN_SIGMA <= s <= MAX_SIGMA or r > MAX_RADIUS:
            raise ValueError(f"sigma {s}, radius {r}: out of range")
        out.append((s, r) if s != 0 and r > 0 else None)
    if all(v is None for v in out):
        raise ValueError("an sfp-extractor/2 model refines some level")
    return out


def detect_levels(metadata, levels):
    """Per level, the level index whose score map its keypoints are detected on
    (`sfp.detect_level`, sfp-extractor/3, which requires it; each level itself before), as
    src/extract/contract.rs reads it (a ValueError where it refuses the model)."""
    key = "sfp.detect_level"
    contract = metadata.get("sfp.contract")
    if contract != CONTRACTS[2]:
        if key in metadata:
            raise ValueError(f"{key} needs sfp.contract = {CONTRACTS[2]}")
        return list(range(levels))
    if key not in metadata:
        raise ValueError(f"{key} missing ({contract} needs it)")
    items = [v.strip() for v in metadata[key].split(",")]
    if len(items) != levels or not all(re.fullmatch(r"[+]?[0-9]+", v) for v in items):
        raise ValueError(f"{key} = {metadata[key][:80]!r}: one level index a level")
    values = [int(v) for v in items]
    if any(d > i for i, d in enumerate(values)):
        raise ValueError(f"{key} = {metadata[key][:80]!r}: a level is detected on itself or a finer level")
    return values


# The most keypoints a level may keep (src/extract/contract.rs: MAX_KEYPOINTS).
MAX_KEYPOINTS = 1_000_000

# A number as Rust's `str::parse::<f32>` reads one (ASCII digits, no `_`): what a model may hold.
NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(inf|infinity|nan)", re.IGNORECASE)


def default_max_keypoints(metadata, levels):
    """Per level, the model's `sfp.default_max_keypoints` as src/extract/contract.rs reads it: one
    cap a level, each 1 to MAX_KEYPOINTS (a ValueError where it refuses the model)."""
    items = [v.strip() for v in metadata["sfp.default_max_keypoints"].split(",")]
    if len(items) != levels or not all(re.fullmatch(r"[+]?[0-9]+", v) for v in items):
        raise ValueError(f"sfp.default_max_keypoints = {metadata['sfp.default_max_keypoints'][:80]!r}: "
                         f"one whole number a level")
    caps = [int(v) for v in items]
    if not all(1 <= c <= MAX_KEYPOINTS for c in caps):
        raise ValueError(f"sfp.default_max_keypoints: {caps}: 1 to {MAX_KEYPOINTS} a level")
    return caps


def default_thresholds(metadata, levels):
    """Per level, the model's `sfp.default_threshold` as src/extract/contract.rs reads it: one
    score for every level or, in an sfp-extractor/2 model, one a level, each in [0, 1] once
    read as float32 (a ValueError where it refuses the model)."""
    items = [v.strip() for v in metadata["sfp.default_threshold"].split(",")]
    if not all(NUMBER.fullmatch(v) for v in items):
        raise ValueError(f"sfp.default_threshold = {metadata['sfp.default_threshold'][:80]!r} is not a number list")
    values = [float(np.float32(float(v))) for v in items]
    if len(values) == 1:
        values = values * levels
    elif len(values) != levels or metadata.get("sfp.contract") == CONTRACTS[0]:
        raise ValueError(f"sfp.default_threshold: one value, or one a level in {CONTRACTS[1]}")
    if not all(0.0 <= v <= 1.0 for v in values):
        raise ValueError(f"sfp.default_threshold: {values} not scores in [0, 1]")
    return values


def level_features(feats, scores, strides, radius, thr, topk, refine=True, refine_to=None,
                   image=None, image_refines=None, detect_on=None):
    """Per level: (pixels with the pixel-centre origin at 0, short, full, scores).

    `feats[i]` is [C_i, h_i, w_i], `scores[i]` [h_i, w_i]; `thr` is one threshold or one a
    level. A level's full descriptor joins the normalised samples of it and every deeper level
    at its keypoints, normalised again. Levels from REFINE_FROM_LEVEL on are refined on the
    next finer level's score map (`refine`), and on from there one level at a time down to
    level `refine_to` (the model's
    `sfp.refine_to_level`; None: one level only). With `refine`, a level whose entry of
    `image_refines` is (sigma, radius) then moves onto the grey input `image` (step 5).
    `detect_on[i]` (sfp-extractor/3's `sfp.detect_level`; None: each level itself) is the level
    whose score map level i's keypoints are detected on, and refined down from.
    """
    if refine_to is not None and not 0 <= refine_to < len(strides):
        raise ValueError(f"refine_to = {refine_to} is no level of {len(strides)}")
    thresholds = list(thr) if np.ndim(thr) else [thr] * len(strides)
    out = []
    on = list(range(len(strides))) if detect_on is None else list(detect_on)
    for i, stride in enumerate(strides):
        d = on[i]
        cells, v = detect(scores[d], radius, thresholds[i], topk[i])
        px = cells * strides[d]
        if refine and d >= max(REFINE_FROM_LEVEL, 1):
            finest = d - 1 if refine_to is None else min(refine_to, d - 1)
            for j in range(d - 1, finest - 1, -1):
                r = max(1, int(np.floor(strides[j + 1] / strides[j] / 2 + 0.5)))  # half up, as Rust
                px = refine_on(scores[j], strides[j], r, px)
        cells = px / stride
        if refine and image is not None and image_refines is not None and image_refines[i] is not None:
            px = image_refine(image, px, *image_refines[i])
            cells = px / stride
        short = l2n(bilinear(feats[i], cells))
        parts = [l2n(bilinear(feats[j], px / strides[j])) for j in range(i, len(strides))]
        out.append((px, short, l2n(np.concatenate(parts, 1)), v))
    return out
