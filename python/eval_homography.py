#!/usr/bin/env python3
"""HPatches-style evaluation on held-out images (the scenes' query images, never trained on).

For every image (gray, max side 640) and every split, pairs (A, B = warp(A, H) + photometric change):
  v (viewpoint):    random homography (corner perturbation, rotation, scale) + mild photometric change
  i (illumination): identity geometry + strong photometric change (gamma, contrast, gradient, noise)
Per method (SFP per level, short and full descriptors; OpenCV ORB and SIFT):
  keypoints (SFP: score-map NMS + threshold + top-k, sub-pixel quadratic refinement),
  mutual-nearest-neighbour matching, repeatability@3px, mean matching accuracy (MMA) at 1/3/5 px,
  matches and correct matches@3px per pair.

  python3 python/eval_homography.py --model models/sfp-v1.onnx [--pairs 2] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import cv2
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from sfp import data as D  # noqa: E402
from sfp.reference import detect_levels, image_refine_levels, level_features  # noqa: E402

cv2.setNumThreads(1)


# --- pairs -----------------------------------------------------------------------------------

def viewpoint_h(rng, w, h, strength=1.0):
    c = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], np.float32)
    a = np.deg2rad(rng.uniform(-20, 20) * strength)
    s = np.exp(rng.uniform(np.log(0.75), np.log(1.3)) * strength)
    ctr = np.array([(w - 1) / 2, (h - 1) / 2], np.float32)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]], np.float32) * s
    d = (c - ctr) @ R.T + ctr
    d = d + rng.uniform(-0.12, 0.12, size=(4, 2)).astype(np.float32) * np.array([w, h], np.float32) * strength
    H = cv2.getPerspectiveTransform(c, d.astype(np.float32))
    return H / H[2, 2]


def make_pairs(images, n_per_image, seed=0):
    rng = np.random.default_rng(seed)
    pairs = {"v": [], "i": []}
    for k, im in enumerate(images):
        h, w = im.shape
        a = im.astype(np.float32) / 255.0
        for _ in range(n_per_image):
            H = viewpoint_h(rng, w, h)
            b = cv2.warpPerspective(a, H, (w, h), flags=cv2.INTER_LINEAR, borderValue=0)
            b = D.photometric(rng, b, 0.3)
            pairs["v"].append((k, a, b, H))
            Hi = np.eye(3)
            bi = D.photometric(rng, a.copy(), 1.6)
            pairs["i"].append((k, a, bi, Hi))
    return pairs


def to_u8(x):
    return (np.clip(x, 0, 1) * 255 + 0.5).astype(np.uint8)


# --- SFP ---------------------------------------------------------------------------------------

class SFPRunner:
    def __init__(self, path, threads=1):
        import onnxruntime as ort
        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        self.s = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
        md = self.s.get_modelmeta().custom_metadata_map
        self.strides = [int(v) for v in md["sfp.strides"].split(",")]
        self.dims = [int(v) for v in md["sfp.dims"].split(",")]
        self.names = [o.name for o in self.s.get_outputs()]
        self.input_name = md.get("sfp.input_name", "image")
        self.image_refines = image_refine_levels(md, len(self.strides))  # step 5 (sfp-extractor/2)
        self.detect_on = detect_levels(md, len(self.strides))  # sfp-extractor/3

    def run(self, img01):
        outs = dict(zip(self.names, self.s.run(None, {self.input_name: img01[None, None].astype(np.float32)})))
        feats = [outs[f"feat_{i}"][0] for i in range(len(self.strides))]
        scores = [outs[f"score_{i}"][0, 0] for i in range(len(self.strides))]
        return feats, scores, outs["global"][0]


def sfp_features(runner, img01, topk, thr, refine=True):
    """Per level (pixels, short, full, scores), by the extractor's reference post-processing
    (with its coarse-to-fine refinement of levels 2 and deeper, and an sfp-extractor/2 model's
    refinement on the image, unless `refine` is False)."""
    feats, scores, _ = runner.run(img01)
    return level_features(feats, scores, runner.strides, 1, thr, topk, refine=refine, image=img01,
                          image_refines=runner.image_refines, detect_on=runner.detect_on)


# --- matching / metrics ---------------------------------------------------------------------------

def mutual_nn_float(d1, d2):
    if len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), int)
    sim = d1 @ d2.T
    a = sim.argmax(1)
    b = sim.argmax(0)
    i = np.arange(len(d1))
    keep = b[a] == i
    return np.stack([i[keep], a[keep]], 1)


def mutual_nn_cv(d1, d2, norm):
    if d1 is None or d2 is None or len(d1) == 0 or len(d2) == 0:
        return np.zeros((0, 2), int)
    bf = cv2.BFMatcher(norm, crossCheck=True)
    ms = bf.match(d1, d2)
    return np.array([[m.queryIdx, m.trainIdx] for m in ms], int).reshape(-1, 2)


def warp(H, pts):
    if len(pts) == 0:
        return pts.reshape(0, 2)
    p = cv2.perspectiveTransform(pts.reshape(-1, 1, 2).astype(np.float64), H).reshape(-1, 2)
    return p


def inside(pts, w, h, m=0):
    return (pts[:, 0] >= m) & (pts[:, 1] >= m) & (pts[:, 0] <= w - 1 - m) & (pts[:, 1] <= h - 1 - m)


def pair_metrics(kA, kB, matches, H, w, h, thr=(1, 3, 5), rep_px=3):
    """kA, kB pixel coords; restrict to the common region."""
    Hi = np.linalg.inv(H)
    inA = inside(warp(H, kA), w, h) if len(kA) else np.zeros(0, bool)
    inB = inside(warp(Hi, kB), w, h) if len(kB) else np.zeros(0, bool)
    res = {"nA": int(inA.sum()), "nB": int(inB.sum())}
    # repeatability (SuperPoint style, symmetric)
    a = warp(H, kA[inA]) if inA.any() else np.zeros((0, 2))
    b = kB[inB] if inB.any() else np.zeros((0, 2))
    if len(a) and len(b):
        d = np.linalg.norm(a[:, None] - b[None], axis=2)
        rep = ((d.min(1) <= rep_px).sum() + (d.min(0) <= rep_px).sum()) / (len(a) + len(b))
    else:
        rep = 0.0
    res["rep"] = float(rep)
    if len(matches):
        mm = matches[inA[matches[:, 0]] & inB[matches[:, 1]]] if len(matches) else matches
    else:
        mm = matches
    if len(mm):
        err = np.linalg.norm(warp(H, kA[mm[:, 0]]) - kB[mm[:, 1]], axis=1)
    else:
        err = np.zeros(0)
    res["matches"] = int(len(mm))
    for t in thr:
        res[f"mma{t}"] = float((err <= t).mean()) if len(err) else 0.0
    res["correct3"] = int((err <= 3).sum())
    return res


def aggregate(rs):
    keys = rs[0].keys()
    return {k: float(np.mean([r[k] for r in rs])) for k in keys}


def run_opencv(kind, n):
    if kind == "orb":
        det = cv2.ORB_create(nfeatures=n)
        norm = cv2.NORM_HAMMING
    else:
        det = cv2.SIFT_create(nfeatures=n)
        norm = cv2.NORM_L2

    def f(img01):
        kps, desc = det.detectAndCompute(to_u8(img01), None)
        pts = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        return pts, desc
    return f, norm


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default="models/sfp-v1.onnx")
    ap.add_argument("--pairs", type=int, default=2, help="pairs per image and split")
    ap.add_argument("--max-side", type=int, default=640)
    ap.add_argument("--topk", default="1000,1000,500,250", help="max keypoints per SFP level")
    ap.add_argument("--thr", type=float, default=0.05, help="SFP score threshold after NMS")
    ap.add_argument("--n-classic", type=int, default=1000, help="ORB / SIFT nfeatures")
    ap.add_argument("--no-classic", action="store_true")
    ap.add_argument("--no-refine", action="store_true",
                    help="levels 2+ as detected on their own score map (the extractor before stop 31)")
    ap.add_argument("--json")
    ap.add_argument("--label", default="SFP")
    args = ap.parse_args()

    files = D.eval_files()
    train = set(D.train_files())
    assert not (set(files) & train), "evaluation images overlap the training set"
    images = [D.load_gray(p, args.max_side) for p in files]
    pairs = make_pairs(images, args.pairs)
    runner = SFPRunner(args.model)
    topk = [int(v) for v in args.topk.split(",")]
    results = {}
    for split, ps in pairs.items():
        acc: dict[str, list] = {}
        for (_, a, b, H) in ps:
            h, w = a.shape
            fa = sfp_features(runner, a, topk, args.thr, not args.no_refine)
            fb = sfp_features(runner, b, topk, args.thr, not args.no_refine)
            all_short, all_full = [], []
            for i in range(len(runner.strides)):
                for kind, col in (("short", 1), ("full", 2)):
                    if kind == "full" and i == len(runner.strides) - 1:
                        continue  # the deepest level's full descriptor equals its short one
                    m = mutual_nn_float(fa[i][col], fb[i][col])
                    r = pair_metrics(fa[i][0], fb[i][0], m, H, w, h)
                    acc.setdefault(f"{args.label} L{i} s{runner.strides[i]} {kind}", []).append(r)
            # all levels together (matching within each level, short descriptors)
            kA = np.concatenate([f[0] for f in fa])
            kB = np.concatenate([f[0] for f in fb])
            ms, oa, ob = [], 0, 0
            for i in range(len(runner.strides)):
                m = mutual_nn_float(fa[i][1], fb[i][1])
                if len(m):
                    ms.append(m + np.array([oa, ob]))
                oa += len(fa[i][0])
                ob += len(fb[i][0])
            m = np.concatenate(ms) if ms else np.zeros((0, 2), int)
            acc.setdefault(f"{args.label} all levels short", []).append(pair_metrics(kA, kB, m, H, w, h))
            if not args.no_classic:
                for kind in ("orb", "sift"):
                    f, norm = run_opencv(kind, args.n_classic)
                    pa, da = f(a)
                    pb, db = f(b)
                    m = mutual_nn_cv(da, db, norm)
                    acc.setdefault(f"OpenCV {kind.upper()} {args.n_classic}", []).append(
                        pair_metrics(pa, pb, m, H, w, h))
        results[split] = {k: aggregate(v) for k, v in acc.items()}
    n_pairs = len(pairs["v"])
    print(f"images: {len(images)} held-out query images (max side {args.max_side}), pairs per split: {n_pairs}")
    for split in ("v", "i"):
        name = {"v": "viewpoint (random homography)", "i": "illumination (photometric only)"}[split]
        print(f"\n### {name}\n")
        print("| method | kpts A/B | rep@3 | MMA@1 | MMA@3 | MMA@5 | matches | correct@3 |")
        print("|---|---|---|---|---|---|---|---|")
        for k, r in results[split].items():
            print(f"| {k} | {r['nA']:.0f}/{r['nB']:.0f} | {r['rep']:.3f} | {r['mma1']:.3f} | {r['mma3']:.3f} | "
                  f"{r['mma5']:.3f} | {r['matches']:.0f} | {r['correct3']:.0f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(model=args.model, images=len(images), pairs_per_split=n_pairs, results=results), f,
                      indent=1)


if __name__ == "__main__":
    main()
