#!/usr/bin/env python3
"""Retrieval evaluation of the SFP global descriptor (issue 17): for every query of the shared
scenes, is the ground-truth most co-visible database image among the top-k database images
retrieved by cosine similarity of the `global` output?  recall@1/5/10 per scene.

Ground truth "most co-visible":
- south-building, sacre-coeur: the database image sharing the most 3D points with the query in
  `sparse-full/` (the SfM with the queries registered; map and full share image and point ids).
- kitti06 (target/scenes/kitti06, built with make_posed_scene.py; no model with the queries): the
  database frame whose ground-truth camera centre is nearest to the query's (a car driving straight:
  the neighbouring frames; projecting map points without an occlusion test made the frame with the
  most tracks "most co-visible" for every query, so it is not used).

Models: ONNX files (`--onnx`, run with ONNX Runtime as the contract says) and/or training states /
checkpoints with a `model` state dict (`--torch`, e.g. python/checkpoints/sfp-v2-state.pt).
`--localized LABEL:SCENE=FILE` scores instead the ranking `sfpmap localize --format json` reports per
query (`retrieved`, best first; run it with `--top-k 10`), e.g. a map's VLAD (issue 11):

  sfpmap localize --map sift.sfpm --query-list queries.txt --database queries.db --top-k 10 \
      --retrieval vlad --format json -o vlad.json
  python3 python/eval_retrieval.py --localized "SIFT VLAD:south-building=vlad.json"

  python3 python/eval_retrieval.py --onnx models/sfp-v1.onnx --torch python/checkpoints/sfp-v2-state.pt \
      --json python/curves/eval-retrieval.json
"""
from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from sfp import multiview as MV  # noqa: E402

REPO = os.path.normpath(os.path.join(HERE, ".."))
DATA = os.path.normpath(os.path.join(REPO, "..", "shared", "data"))
SCENES = [("south-building", os.path.join(DATA, "scenes", "south-building")),
          ("sacre-coeur", os.path.join(DATA, "scenes", "sacre-coeur")),
          ("kitti06", os.path.join(REPO, "target", "scenes", "kitti06"))]
# Held-out scenes built here with make_scene.py (benches/scenes.sh, models/sfp-v3.md).
_BUILT = os.path.join(REPO, "target", "scenes")
SCENES += [(n, os.path.join(_BUILT, n)) for n in sorted(os.listdir(_BUILT) if os.path.isdir(_BUILT) else [])
           if n not in dict(SCENES) and os.path.isfile(os.path.join(_BUILT, n, "queries.txt"))]


def qvec_to_R(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def ground_truth(name, d):
    """-> db names, query names, {query: most co-visible db name}, {query: covis counts over db}"""
    import pycolmap

    db = [l.strip() for l in open(os.path.join(d, "db_images.txt")) if l.strip()]
    qs = MV.read_queries(os.path.join(d, "queries.txt"))
    rmap = pycolmap.Reconstruction(os.path.join(d, "sparse-map"))
    db_obs = {}
    for im in rmap.images.values():
        db_obs[im.name] = {p.point3D_id for p in im.points2D if p.has_point3D()}
    db = [n for n in db if n in db_obs]
    counts = {}
    if os.path.exists(os.path.join(d, "sparse-full")):
        rf = pycolmap.Reconstruction(os.path.join(d, "sparse-full"))
        by = {im.name: im for im in rf.images.values()}
        for q in qs:
            pq = {p.point3D_id for p in by[q].points2D if p.has_point3D()}
            counts[q] = np.array([len(pq & db_obs[n]) for n in db])
    else:
        gt = {l.split()[0]: list(map(float, l.split()[1:])) for l in open(os.path.join(d, "gt_poses.txt")) if l.strip()}
        by = {im.name: im for im in rmap.images.values()}
        C = np.array([by[n].projection_center() for n in db])
        for q in qs:
            R, t = qvec_to_R(gt[q][:4]), np.array(gt[q][4:7])
            c = -R.T @ t
            counts[q] = -np.linalg.norm(C - c, axis=1)  # nearest camera centre = "most co-visible"
    best = {q: db[int(np.argmax(c))] for q, c in counts.items()}
    return db, qs, best, counts


def load_gray(path, max_side):
    im = Image.open(path).convert("L")
    w, h = im.size
    s = max_side / max(w, h)
    if s < 1:
        im = im.resize((max(1, round(w * s)), max(1, round(h * s))), Image.BILINEAR)
    return np.asarray(im, np.float32)[None, None] / 255.0


class OnnxGlobal:
    def __init__(self, path, threads):
        import onnxruntime as ort

        so = ort.SessionOptions()
        so.intra_op_num_threads = threads
        so.inter_op_num_threads = 1
        self.s = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
        self.label = os.path.relpath(path, REPO)

    def __call__(self, x):
        return self.s.run(["global"], {"image": x})[0][0]


class TorchGlobal:
    def __init__(self, path, threads):
        import torch
        from sfp.model import SFP

        torch.set_num_threads(threads)
        ck = torch.load(path, map_location="cpu", weights_only=False)
        self.net = SFP.for_state_dict(ck["model"])  # also distill_v2.py's strided students
        self.net.eval()
        self.torch = torch
        self.label = f"{os.path.relpath(path, REPO)} (step {ck.get('step')})"

    def __call__(self, x):
        with self.torch.no_grad():
            feats, _ = self.net.encode(self.torch.from_numpy(x))
            return self.net.global_desc(feats[-1])[0].numpy()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--onnx", action="append", default=[])
    ap.add_argument("--torch", action="append", default=[])
    ap.add_argument("--max-side", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    ap.add_argument("--localized", action="append", default=[],
                    help="LABEL:SCENE=FILE, a `sfpmap localize --format json` output")
    args = ap.parse_args()
    models = [OnnxGlobal(p, args.threads) for p in args.onnx] + [TorchGlobal(p, args.threads) for p in args.torch]
    gts = [(n, d) + ground_truth(n, d) for n, d in SCENES if os.path.exists(d)]
    res = {}
    by_scene = {g[0]: g for g in gts}
    for spec in args.localized:
        label, rest = spec.split(":", 1)
        scene, path = rest.split("=", 1)
        name, d, db, qs, best, counts = by_scene[scene]
        ranked = {q["name"]: q.get("retrieved") or [] for q in json.load(open(path))}
        rec = {}
        for k in (1, 5, 10):
            rec[f"r@{k}"] = float(np.mean([best[q] in ranked.get(q, [])[:k] for q in qs]))
        rec["queries"] = len(qs)
        rec["db"] = len(db)
        res.setdefault(label, {})[name] = rec
        print(f"{label:60s} {name:15s} q={len(qs):3d} db={len(db):3d} "
              f"r@1={rec['r@1']:.3f} r@5={rec['r@5']:.3f} r@10={rec['r@10']:.3f}", flush=True)
    for m in models:
        res[m.label] = {}
        for name, d, db, qs, best, counts in gts:
            G = np.stack([m(load_gray(os.path.join(d, "images", n), args.max_side)) for n in db])
            Q = np.stack([m(load_gray(os.path.join(d, "images", q), args.max_side)) for q in qs])
            S = Q @ G.T
            rank = np.argsort(-S, axis=1)
            rec = {}
            for k in (1, 5, 10):
                rec[f"r@{k}"] = float(np.mean([best[q] in [db[j] for j in rank[i, :k]] for i, q in enumerate(qs)]))
            rec["queries"] = len(qs)
            rec["db"] = len(db)
            res[m.label][name] = rec
            print(f"{m.label:60s} {name:15s} q={len(qs):3d} db={len(db):3d} "
                  f"r@1={rec['r@1']:.3f} r@5={rec['r@5']:.3f} r@10={rec['r@10']:.3f}", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(max_side=args.max_side, results=res,
                           ground_truth={n: b for n, _, _, _, b, _ in gts}), f, indent=1)


if __name__ == "__main__":
    main()
