#!/usr/bin/env python3
"""Median ONNX Runtime inference time of SFP models at one image size, per intra-op thread count,
with the Rust extractor's session options (src/extract/mod.rs: graph optimisation level 3, one
inter-op thread, spinning off). Issue 17's targets: <= 15 ms on 2 cores, <= 25 ms on 1, 640x480.

  python3 python/bench_onnx.py models/sfp-v1.onnx models/sfp-v2s.onnx [--threads 1,2] [--runs 30]

The models are interleaved round by round so that load from other work on the machine hits all of
them alike; the spread (p10..p90) is printed beside the median.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import onnxruntime as ort


def session(path: str, threads: int) -> ort.InferenceSession:
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("models", nargs="+")
    ap.add_argument("--threads", default="1,2")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--runs", type=int, default=30, help="timed runs per model and thread count")
    ap.add_argument("--warmup", type=int, default=3)
    args = ap.parse_args()
    x = np.random.default_rng(0).random((1, 1, args.height, args.width), dtype=np.float32)
    res, names = {}, {}
    for th in [int(t) for t in args.threads.split(",")]:
        ss = {m: session(m, th) for m in args.models}
        for m, s in ss.items():
            for _ in range(args.warmup):
                s.run(None, {"image": x})
            res[(m, th)] = []
            names[m] = s.get_modelmeta().custom_metadata_map.get("sfp.model_name", "?")
        for _ in range(args.runs):
            for m, s in ss.items():
                t = time.perf_counter()
                s.run(None, {"image": x})
                res[(m, th)].append((time.perf_counter() - t) * 1e3)
    base = args.models[0]
    print(f"{args.width}x{args.height}, {args.runs} runs, median ms (p10..p90), ratio to {base}")
    for (m, th), ts in res.items():
        med = float(np.median(ts))
        ratio = med / float(np.median(res[(base, th)]))
        print(f"  {th} thread(s)  {names[m]:10s} {med:7.2f} ms ({np.percentile(ts, 10):.2f}..{np.percentile(ts, 90):.2f})"
              f"  x{ratio:.2f}  {m}")


if __name__ == "__main__":
    main()
