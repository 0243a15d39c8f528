#!/usr/bin/env python3
"""Condense a training run's per-step log (python/runs/NAME/log.csv, git-ignored) into a small
committed curve file: means over windows of --every steps -> python/curves/NAME.csv; copies val.csv.

  python3 python/summarize_run.py python/runs/main --name main
"""
import argparse
import csv
import os
import shutil

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--name", required=True)
    ap.add_argument("--every", type=int, default=50)
    args = ap.parse_args()
    here = os.path.dirname(os.path.abspath(__file__))
    out_dir = os.path.join(here, "curves")
    os.makedirs(out_dir, exist_ok=True)
    with open(os.path.join(args.run, "log.csv")) as f:
        rows = list(csv.DictReader(f))
    keys = [k for k in rows[0].keys() if k not in ("step",)]
    out = []
    for i in range(0, len(rows), args.every):
        chunk = rows[i:i + args.every]
        r = {"step": chunk[-1]["step"]}
        for k in keys:
            vals = [float(c[k]) for c in chunk if c.get(k) not in (None, "")]
            r[k] = f"{np.mean(vals):.5g}" if vals else ""
        out.append(r)
    p = os.path.join(out_dir, f"{args.name}.csv")
    with open(p, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["step"] + keys)
        w.writeheader()
        w.writerows(out)
    v = os.path.join(args.run, "val.csv")
    if os.path.exists(v):
        shutil.copy(v, os.path.join(out_dir, f"{args.name}-val.csv"))
    last = out[-1]
    print(f"{p}: {len(out)} rows; last window: " + ", ".join(f"{k}={last[k]}" for k in keys))


if __name__ == "__main__":
    main()
