"""Multi-view supervision from COLMAP models: pairs of map images with their shared tracks, and
co-visibility for the global descriptor.

Coordinates: COLMAP's point2D xy has its origin at the top-left corner of the first pixel
("corner" convention); scaling an image by s maps corner coordinates x -> s * x. The network's
cell <-> pixel rule uses the pixel-index convention (first pixel centre = 0), so a corner
coordinate x is the pixel-index coordinate x - 0.5 (spec/extractor.md, Geometry).

Query images are never loaded: every scene is read with the names of its queries.txt excluded,
and `assert_disjoint` checks image bytes against the query files (names alone are not enough:
train/kitti01 and the KITTI 06 scene share file names such as 000002.jpg).
"""
from __future__ import annotations

import functools
import hashlib
import os

import numpy as np


@functools.cache
def _cv2():
    """OpenCV, imported where an image is read or resized (one thread): the scene readers here
    (`read_queries`, the COLMAP helpers) serve scripts run in CI's venv, which has no OpenCV."""
    import cv2

    cv2.setNumThreads(1)
    return cv2


def read_queries(path: str) -> list[str]:
    out = []
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                if line.strip() and not line.startswith("#"):
                    out.append(line.split()[0])
    return out


def file_md5(path: str) -> str:
    h = hashlib.md5()
    with open(path, "rb") as f:
        h.update(f.read())
    return h.hexdigest()


def imread_gray(path: str) -> np.ndarray:
    cv2 = _cv2()
    im = cv2.imread(path, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION)
    if im is None:
        raise IOError(path)
    return im


def resize_max(im, max_side):
    h, w = im.shape[:2]
    s = max_side / max(h, w)
    if s < 1:
        cv2 = _cv2()
        im = cv2.resize(im, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    return im


class SfMScene:
    """Images of one COLMAP model (queries excluded) with their observations of 3D points.

    images[k]: grey uint8 (max side `max_side`); obs[k]: (pids int64 [M], xy float32 [M,2] in the
    stored image's CORNER convention); covis: [n,n] number of shared 3D points.
    """

    def __init__(self, name, model_dir, images_dir, exclude=(), max_side=1024, min_track=2):
        import pycolmap

        self.name = name
        self.model_dir = model_dir
        self.images_dir = images_dir
        rec = pycolmap.Reconstruction(model_dir)
        exclude = set(exclude)
        self.names, self.paths, self.images, self.obs = [], [], [], []
        for iid in sorted(rec.images.keys()):
            im = rec.images[iid]
            if im.name in exclude:
                continue
            path = os.path.join(images_dir, im.name)
            if not os.path.exists(path):
                continue
            cam = rec.cameras[im.camera_id]
            g = imread_gray(path)
            H0, W0 = g.shape
            g = resize_max(g, max_side)
            h1, w1 = g.shape
            sx = (W0 / cam.width) * (w1 / W0)
            sy = (H0 / cam.height) * (h1 / H0)
            pids, xys = [], []
            for p in im.points2D:
                if p.has_point3D():
                    pids.append(p.point3D_id)
                    xys.append(p.xy)
            if len(pids) < 10:
                continue
            xy = np.asarray(xys, np.float64) * np.array([sx, sy])
            self.names.append(im.name)
            self.paths.append(path)
            self.images.append(g)
            self.obs.append((np.asarray(pids, np.int64), xy.astype(np.float32)))
        n = len(self.names)
        self.covis = np.zeros((n, n), np.int32)
        sets = [set(o[0].tolist()) for o in self.obs]
        for a in range(n):
            for b in range(a + 1, n):
                c = len(sets[a] & sets[b])
                self.covis[a, b] = self.covis[b, a] = c

    def common(self, a, b):
        pa, xa = self.obs[a]
        pb, xb = self.obs[b]
        _, ia, ib = np.intersect1d(pa, pb, assume_unique=False, return_indices=True)
        return xa[ia], xb[ib]

    def __len__(self):
        return len(self.names)


def assert_disjoint(train_paths, query_paths):
    """No training file may be a query image: by path and by content (md5)."""
    qp = {os.path.realpath(p) for p in query_paths}
    for p in train_paths:
        assert os.path.realpath(p) not in qp, f"query image in training data: {p}"
    qh = {file_md5(p): p for p in query_paths}
    for p in train_paths:
        h = file_md5(p)
        assert h not in qh, f"training file {p} has the bytes of query {qh[h]}"


def _scaled(im, s):
    h, w = im.shape
    nw, nh = max(1, round(w * s)), max(1, round(h * s))
    cv2 = _cv2()
    out = cv2.resize(im, (nw, nh), interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    return out, nw / w, nh / h


def _spread(x):
    m = np.median(x, 0)
    return float(np.median(np.linalg.norm(x - m, axis=1))) + 1e-6


class MVPairSampler:
    """Crops A (image a) and B (image b, a co-visible map image) of side S with the pixel-index
    positions of their shared 3D points in both crops.

    pair() -> A, B float32 [S,S] in [0,1]; pa, pb float32 [K,2]; valid bool [K] (K = kmax, padded).
    """

    def __init__(self, scenes, size=192, kmax=192, min_shared=30, min_corr=16, seed=0,
                 side_range=(320, 800), scale_jitter=0.25, photo=1.0, margin=4):
        from . import data as D

        self.D = D
        self.scenes = scenes
        self.S = size
        self.kmax = kmax
        self.min_corr = min_corr
        self.side_range = side_range
        self.jit = scale_jitter
        self.photo = photo
        self.margin = margin
        self.rng = np.random.default_rng(seed)
        self.pairs = []
        for si, sc in enumerate(scenes):
            n = len(sc)
            for a in range(n):
                for b in range(n):
                    if a != b and sc.covis[a, b] >= min_shared:
                        self.pairs.append((si, a, b))
        # weight scenes equally-ish: sqrt of the pair count per scene
        cnt = np.bincount([p[0] for p in self.pairs], minlength=len(scenes)).astype(np.float64)
        w = np.array([1.0 / np.sqrt(cnt[p[0]]) for p in self.pairs])
        self.w = w / w.sum()

    def _try(self, si, a, b):
        rng, S, m = self.rng, self.S, self.margin
        sc = self.scenes[si]
        xa, xb = sc.common(a, b)
        ima, imb = sc.images[a], sc.images[b]
        # scale of image a: random working side, at least big enough for the crop
        ha, wa = ima.shape
        side = np.exp(rng.uniform(np.log(self.side_range[0]), np.log(self.side_range[1])))
        s_a = max(side / max(ha, wa), (S + 2) / min(ha, wa))
        s_a = min(s_a, max(1.5, (S + 2) / min(ha, wa)))
        A_img, sxa, sya = _scaled(ima, s_a)
        Ha, Wa = A_img.shape
        ca = xa * np.array([sxa, sya], np.float32) - 0.5  # pixel-index in scaled a
        k = rng.integers(len(ca))
        oxa = int(np.clip(round(ca[k, 0] - rng.uniform(0.2, 0.8) * S), 0, Wa - S))
        oya = int(np.clip(round(ca[k, 1] - rng.uniform(0.2, 0.8) * S), 0, Ha - S))
        pa = ca - np.array([oxa, oya], np.float32)
        ina = (pa[:, 0] >= m) & (pa[:, 1] >= m) & (pa[:, 0] <= S - 1 - m) & (pa[:, 1] <= S - 1 - m)
        if ina.sum() < self.min_corr:
            return None
        # scale of b: match the spread of the shared points, with jitter
        r = _spread(xb[ina]) / _spread(xa[ina] * np.array([sxa, sya], np.float32)) if ina.sum() >= 3 else 1.0 / s_a
        hb, wb = imb.shape
        s_b = (1.0 / r) * np.exp(rng.uniform(-self.jit, self.jit))
        s_b = float(np.clip(s_b, (S + 2) / min(hb, wb), max(1.5, (S + 2) / min(hb, wb))))
        B_img, sxb, syb = _scaled(imb, s_b)
        Hb, Wb = B_img.shape
        cb = xb * np.array([sxb, syb], np.float32) - 0.5
        cen = np.median(cb[ina], 0) + rng.uniform(-0.15, 0.15, 2) * S
        oxb = int(np.clip(round(cen[0] - S / 2), 0, Wb - S))
        oyb = int(np.clip(round(cen[1] - S / 2), 0, Hb - S))
        pb = cb - np.array([oxb, oyb], np.float32)
        inb = (pb[:, 0] >= m) & (pb[:, 1] >= m) & (pb[:, 0] <= S - 1 - m) & (pb[:, 1] <= S - 1 - m)
        ok = np.nonzero(ina & inb)[0]
        if len(ok) < self.min_corr:
            return None
        if len(ok) > self.kmax:
            ok = rng.choice(ok, self.kmax, replace=False)
        A = A_img[oya:oya + S, oxa:oxa + S].astype(np.float32) / 255.0
        B = B_img[oyb:oyb + S, oxb:oxb + S].astype(np.float32) / 255.0
        if rng.random() < 0.5:
            A, B, pa, pb = B, A, pb, pa
        if rng.random() < 0.5:
            A = self.D.photometric(rng, A, 0.5 * self.photo)
        B = self.D.photometric(rng, B, 0.5 * self.photo)
        K = self.kmax
        PA = np.zeros((K, 2), np.float32)
        PB = np.zeros((K, 2), np.float32)
        V = np.zeros(K, bool)
        PA[:len(ok)] = pa[ok]
        PB[:len(ok)] = pb[ok]
        V[:len(ok)] = True
        return A, B, PA, PB, V

    def pair(self):
        for _ in range(50):
            si, a, b = self.pairs[self.rng.choice(len(self.pairs), p=self.w)]
            out = self._try(si, a, b)
            if out is not None:
                return out
        raise RuntimeError("no multi-view pair with enough correspondences in 50 tries")

    def batch(self, n):
        ps = [self.pair() for _ in range(n)]
        return tuple(np.stack([p[i] for p in ps]) for i in range(5))


class CovisIndex:
    """All map images of all scenes, flat, with co-visibility positives and negatives for the
    global descriptor. Positives of image g: the (up to) `top` most co-visible images of its scene
    sharing >= max(min_pos, frac * best) points; negatives: images of other scenes and images of
    its scene sharing < neg_max points."""

    def __init__(self, scenes, glob_side=288, top=3, min_pos=15, frac=0.3, neg_max=5):
        self.items = []  # (scene index, image index)
        self.images = []
        for si, sc in enumerate(scenes):
            for k in range(len(sc)):
                self.items.append((si, k))
                self.images.append(resize_max(sc.images[k], glob_side).astype(np.float32) / 255.0)
        n = len(self.items)
        self.scene_of = np.array([s for s, _ in self.items])
        C = np.zeros((n, n), np.int32)
        off = 0
        for sc in scenes:
            m = len(sc)
            C[off:off + m, off:off + m] = sc.covis
            off += m
        self.C = C
        self.pos = []
        for g in range(n):
            row = C[g].copy()
            row[g] = 0
            best = row.max()
            order = np.argsort(-row)[:top]
            self.pos.append([int(j) for j in order if row[j] >= max(min_pos, frac * best)])
        same = self.scene_of[:, None] == self.scene_of[None, :]
        self.neg = ~same | (C < neg_max)
        np.fill_diagonal(self.neg, False)
        self.anchors = [g for g in range(n) if self.pos[g]]

    def __len__(self):
        return len(self.items)
