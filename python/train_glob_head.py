#!/usr/bin/env python3
"""Train SFP's retrieval head (SFP(glob_head=True), python/sfp/model.py) on a frozen network.

The head reads the deepest features detached, so the local descriptors and scores stay exactly
those of the input state; only the `global` output changes. Because the encoder is frozen, its
deepest feature maps are computed once for every map image of the training scenes (queries
excluded and asserted as in train_v2.py), and each step scores *every* image with the current
head: a multi-positive InfoNCE per anchor over its co-visibility positives (multiview.CovisIndex:
the most co-visible images of its scene) against all its negatives (other scenes, or < 5 shared
points), with nothing stale (distill_v2's cached-negative version drifted: a fresh head learned
to move away from the cache, and training recall fell from 0.94 to 0.35 in 500 steps).

  python3 python/train_glob_head.py python/checkpoints/sfp-v2s-state.pt -o python/checkpoints/sfp-v2sg-state.pt
  python3 python/eval_retrieval.py --torch python/checkpoints/sfp-v2sg-state.pt

Caveat: the shared scenes' map images are training images here (their queries are not), so
their retrieval recall measures a head trained on the map it retrieves from; a new map gets a
head trained on others.
"""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import train_v2 as V  # noqa: E402  (scenes, query exclusion)
from sfp import multiview as MV  # noqa: E402
from sfp.model import SFP  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("state", help=".pt with 'model' (a student or v1-shaped state)")
    ap.add_argument("-o", "--out", required=True, help="state written: the input's + glob_head")
    ap.add_argument("--side", type=int, default=512, help="max image side the features are taken at")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--tau", type=float, default=0.05)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--curves", default=os.path.join(HERE, "curves"))
    ap.add_argument("--run-name", default=None)
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    run = args.run_name or time.strftime("glob-head-%Y%m%d-%H%M")

    import pycolmap  # noqa: F401
    scenes = V.load_scenes()
    MV.assert_disjoint([p for sc in scenes for p in sc.paths], V.query_paths())
    cidx = MV.CovisIndex(scenes, glob_side=args.side)
    n = len(cidx)
    print(f"{n} map images, {len(cidx.anchors)} anchors (queries excluded and asserted)", flush=True)

    ck = torch.load(args.state, map_location="cpu", weights_only=False)
    sd = ck["model"]
    base = SFP.for_state_dict(sd)
    net = SFP(stem_mode=base.stem_mode, glob_head=True)
    missing, unexpected = net.load_state_dict(sd, strict=False)
    assert not unexpected and all(k.startswith("glob_head.") for k in missing), (missing, unexpected)
    net.eval()
    for k, p in net.named_parameters():
        p.requires_grad_(k.startswith("glob_head."))

    t0 = time.time()
    with torch.no_grad():
        feats = [net.encode(torch.from_numpy(im)[None, None])[0][-1] for im in cidx.images]
    print(f"deepest features of {n} images in {time.time() - t0:.0f} s", flush=True)

    pos = torch.zeros(n, n, dtype=torch.bool)
    for g in range(n):
        pos[g, cidx.pos[g]] = True
    neg = torch.from_numpy(cidx.neg)
    anchors = torch.tensor(cidx.anchors)

    def describe():
        return torch.cat([net.global_desc(f) for f in feats], 0)

    def recall(G):
        S = G @ G.t()
        S.fill_diagonal_(-2)
        top = S.topk(5, dim=1).indices
        hit1 = pos[anchors, top[anchors, 0]].float().mean().item()
        hit5 = pos[anchors[:, None], top[anchors]].any(1).float().mean().item()
        return hit1, hit5

    opt = torch.optim.AdamW([p for p in net.parameters() if p.requires_grad], lr=args.lr, weight_decay=1e-4)
    os.makedirs(args.curves, exist_ok=True)
    cpath = os.path.join(args.curves, f"{run}.csv")
    with open(cpath, "w", newline="") as cf:
        cw = csv.writer(cf)
        cw.writerow(["step", "loss", "train_r1", "train_r5"])
        with torch.no_grad():
            r1, r5 = recall(describe())
        print(f"step 0: leave-one-out r1={r1:.3f} r5={r5:.3f} (random head)", flush=True)
        cw.writerow([0, "", round(r1, 4), round(r5, 4)])
        for step in range(1, args.steps + 1):
            lr = args.lr * 0.5 * (1 + np.cos(np.pi * step / args.steps))
            for g in opt.param_groups:
                g["lr"] = lr
            G = describe()
            S = (G[anchors] @ G.t()) / args.tau
            P, N = pos[anchors], neg[anchors]
            # multi-positive InfoNCE: log sum over positives vs over positives + negatives
            big = torch.finfo(S.dtype).max / 4
            lp = torch.logsumexp(S.masked_fill(~P, -big), 1)
            la = torch.logsumexp(S.masked_fill(~(P | N), -big), 1)
            loss = (la - lp).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if step % 25 == 0 or step == args.steps:
                with torch.no_grad():
                    r1, r5 = recall(describe())
                cw.writerow([step, round(loss.item(), 5), round(r1, 4), round(r5, 4)])
                cf.flush()
                print(f"step {step}: loss={loss.item():.4f} leave-one-out r1={r1:.3f} r5={r5:.3f}", flush=True)

    out = dict(ck)
    out["model"] = net.state_dict()
    meta = dict(out.get("meta", {}))
    meta["glob_head"] = dict(run=run, from_state=os.path.relpath(args.state, V.REPO), side=args.side,
                             steps=args.steps, lr=args.lr, tau=args.tau, images=n)
    out["meta"] = meta
    if "export_metadata" in out:
        out["export_metadata"] = dict(out["export_metadata"], **{"sfp.global": "glob_head (python/train_glob_head.py)"})
    tmp = args.out + ".tmp"
    torch.save(out, tmp)
    os.replace(tmp, args.out)
    print(f"wrote {args.out}; curves {cpath}", flush=True)


if __name__ == "__main__":
    main()
