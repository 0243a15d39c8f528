"""Training / evaluation images and random-homography pairs.

Training images: scikit-image's bundled natural images + every image under
../shared/data/scenes/*/images and ../shared/data/colmap/*/ EXCEPT the images named in any scene's
queries.txt (evaluation queries) and the validation hold-out below.
"""
from __future__ import annotations

import glob
import os

import cv2
import numpy as np

cv2.setNumThreads(1)

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.normpath(os.path.join(HERE, "..", ".."))
SHARED = os.environ.get("SFP_SHARED", os.path.normpath(os.path.join(REPO, "..", "shared")))
DATA = os.path.join(SHARED, "data")
IMG_EXT = (".jpg", ".jpeg", ".png")

SKIMAGE_NAMES = ["astronaut", "brick", "camera", "chelsea", "coffee", "coins", "grass", "gravel",
                 "horse", "moon", "motorcycle_left", "motorcycle_right", "page", "rocket", "text",
                 "hubble_deep_field", "immunohistochemistry", "retina", "cell", "clock"]
# Validation hold-out (used to pick the checkpoint): never trained on, never used for the final eval.
VAL_DIRS = ["colmap/kapture_maupertuis/images"]


def query_names() -> set[str]:
    names = set()
    for q in glob.glob(os.path.join(DATA, "scenes", "*", "queries.txt")):
        with open(q) as f:
            for line in f:
                if line.strip() and not line.startswith("#"):
                    names.add(line.split()[0])
    return names


def _list_images(root):
    out = []
    for dp, _, fns in os.walk(root):
        for fn in fns:
            if fn.lower().endswith(IMG_EXT):
                out.append(os.path.join(dp, fn))
    return sorted(out)


def train_files() -> list[str]:
    q = query_names()
    val = {os.path.join(DATA, v) for v in VAL_DIRS}
    files = []
    for root in sorted(glob.glob(os.path.join(DATA, "scenes", "*", "images"))) + \
            sorted(glob.glob(os.path.join(DATA, "colmap", "*"))):
        for p in _list_images(root):
            if os.path.basename(p) in q:
                continue
            if any(p.startswith(v + os.sep) for v in val):
                continue
            files.append(p)
    return files


def val_files() -> list[str]:
    return [p for v in VAL_DIRS for p in _list_images(os.path.join(DATA, v))]


def eval_files() -> list[str]:
    """The scenes' query images: held out from training, used only by eval_homography.py."""
    out = []
    for qf in sorted(glob.glob(os.path.join(DATA, "scenes", "*", "queries.txt"))):
        d = os.path.join(os.path.dirname(qf), "images")
        with open(qf) as f:
            for line in f:
                if line.strip() and not line.startswith("#"):
                    out.append(os.path.join(d, line.split()[0]))
    return out


def load_gray(path, max_side=640) -> np.ndarray:
    im = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
    if im is None:
        raise IOError(path)
    return resize_max(im, max_side)


def resize_max(im, max_side):
    h, w = im.shape[:2]
    s = max_side / max(h, w)
    if s < 1:
        im = cv2.resize(im, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return im


def skimage_images() -> list[np.ndarray]:
    out = []
    try:
        import skimage.data as skd
        from skimage.color import rgb2gray
    except ImportError:
        return out
    for n in SKIMAGE_NAMES:
        try:
            im = getattr(skd, n)()
        except Exception:
            continue
        if im.ndim == 3:
            im = rgb2gray(im[..., :3])
        im = np.asarray(im, dtype=np.float64)
        if im.max() > 1.5:
            im = im / 255.0
        im = (np.clip(im, 0, 1) * 255).astype(np.uint8)
        if min(im.shape) >= 128:
            out.append(resize_max(im, 640))
    return out


# --- random homographies ------------------------------------------------------------------------

def random_homography(rng, size, max_angle=30.0, scale=(0.75, 1.33), persp=0.0008, shift=0.1):
    """H mapping patch-A pixel coords to patch-B pixel coords (square patch of side `size`)."""
    c = (size - 1) / 2.0
    T = np.array([[1, 0, -c], [0, 1, -c], [0, 0, 1]], np.float64)
    Ti = np.array([[1, 0, c], [0, 1, c], [0, 0, 1]], np.float64)
    a = np.deg2rad(rng.uniform(-max_angle, max_angle))
    s = np.exp(rng.uniform(np.log(scale[0]), np.log(scale[1])))
    sx = s * np.exp(rng.uniform(-0.1, 0.1))
    sy = s * np.exp(rng.uniform(-0.1, 0.1))
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    S = np.diag([sx, sy, 1.0])
    sh = rng.uniform(-0.1, 0.1)
    Sh = np.array([[1, sh, 0], [0, 1, 0], [0, 0, 1]], np.float64)
    P = np.array([[1, 0, 0], [0, 1, 0], [rng.uniform(-persp, persp), rng.uniform(-persp, persp), 1]])
    t = rng.uniform(-shift, shift, 2) * size
    Tr = np.array([[1, 0, t[0]], [0, 1, t[1]], [0, 0, 1]], np.float64)
    H = Ti @ Tr @ P @ R @ Sh @ S @ T
    return H / H[2, 2]


def photometric(rng, im, strength=1.0):
    """im float32 in [0,1] -> augmented copy."""
    x = im.astype(np.float32)
    if rng.random() < 0.3 * strength:
        k = rng.choice([3, 5])
        x = cv2.GaussianBlur(x, (k, k), 0)
    g = np.exp(rng.uniform(-0.5, 0.5) * strength)
    x = np.clip(x, 0, 1) ** g
    c = np.exp(rng.uniform(-0.4, 0.4) * strength)
    b = rng.uniform(-0.2, 0.2) * strength
    x = (x - 0.5) * c + 0.5 + b
    if rng.random() < 0.3 * strength:  # smooth illumination gradient
        h, w = x.shape
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        d = rng.normal(size=2)
        ramp = (d[0] * xx / w + d[1] * yy / h) * 0.2 * strength
        x = x + ramp
    sig = rng.uniform(0, 0.03) * strength
    if sig > 0:
        x = x + rng.normal(0, sig, x.shape).astype(np.float32)
    return np.clip(x, 0, 1).astype(np.float32)


class PairSampler:
    """Random crops of size `size` (A) and their random-homography warps (B)."""

    def __init__(self, images, size=192, seed=0, photo=1.0, hom=1.0):
        self.images = images
        self.size = size
        self.rng = np.random.default_rng(seed)
        self.photo = photo
        self.hom = hom

    def pair(self):
        rng, S = self.rng, self.size
        im = self.images[rng.integers(len(self.images))]
        h, w = im.shape
        # random scale of the source, at least big enough for the patch plus margin
        smin = (S * 1.3) / min(h, w)
        s = max(smin, np.exp(rng.uniform(np.log(0.4), np.log(1.0))))
        src = cv2.resize(im, (max(int(w * s), S + 2), max(int(h * s), S + 2)),
                         interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
        src = src.astype(np.float32) / 255.0
        hh, ww = src.shape
        ox = rng.integers(0, ww - S + 1)
        oy = rng.integers(0, hh - S + 1)
        A = src[oy:oy + S, ox:ox + S]
        H = random_homography(rng, S, max_angle=30 * self.hom, persp=0.0008 * self.hom,
                              shift=0.1 * self.hom, scale=(0.75 ** self.hom, 1.33 ** self.hom))
        M = H @ np.array([[1, 0, -ox], [0, 1, -oy], [0, 0, 1]], np.float64)
        B = cv2.warpPerspective(src, M, (S, S), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        valid = cv2.warpPerspective(np.ones_like(src), M, (S, S), flags=cv2.INTER_NEAREST,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if rng.random() < 0.5:
            A = photometric(rng, A, 0.5 * self.photo)
        B = photometric(rng, B, self.photo)
        return A, B, H.astype(np.float32), valid.astype(np.float32)

    def batch(self, n):
        ps = [self.pair() for _ in range(n)]
        A = np.stack([p[0] for p in ps])[:, None]
        B = np.stack([p[1] for p in ps])[:, None]
        H = np.stack([p[2] for p in ps])
        V = np.stack([p[3] for p in ps])[:, None]
        return A, B, H, V
