#!/usr/bin/env python3
"""Python ONNX Runtime reference of the SFP extractor (spec/extractor.md), for tests/extract_reference.rs.

Reads an image (optionally re-saving it as an RGB PNG first, so the Rust and Python decoders
see the same pixels), runs the model with onnxruntime (CPU), and writes JSON with, per level,
keypoints (COLMAP convention), scores, short and full descriptors, plus the global descriptor.
Needs numpy, pillow, onnxruntime==1.31.1 (no OpenCV).

  python3 tests/extract_reference.py --model models/sfp-v1.onnx --image in.jpg --png out.png --json ref.json

With --check-h5 FILE (needs h5py) it instead reads an `sfpmap extract` output the way hloc
does and checks the layout of spec/extractor.md ("features.h5 layout"); with --image as well,
it also checks that image's group against this reference (same keypoints, descriptors).
"""

import argparse
import json
import os
import sys

import numpy as np
import onnxruntime as ort
from PIL import Image

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "python"))
from sfp.reference import (CONTRACTS, default_max_keypoints, default_thresholds,  # noqa: E402  (numpy only)
                           detect_levels, image_refine_levels, level_features)


def check_h5(path, reference=None, name=None):
    import h5py
    with h5py.File(path, "r") as f:
        contract = f.attrs["sfp.contract"]
        assert (contract.decode() if isinstance(contract, bytes) else contract) in CONTRACTS, dict(f.attrs)
        main_level = int(f.attrs["sfp.main_level"])
        groups = []
        f.visititems(lambda n, o: groups.append(n) if isinstance(o, h5py.Group) and "keypoints" in o and "image_size" in o else None)
        assert groups, "no image groups"
        for g in groups:
            grp = f[g]
            kp, desc, sc = grp["keypoints"][()], grp["descriptors"][()], grp["scores"][()]
            n = kp.shape[0]
            assert kp.shape == (n, 2) and kp.dtype == np.float32, (g, kp.shape, kp.dtype)
            assert desc.shape[1] == n and desc.dtype == np.float16, (g, desc.shape, desc.dtype)
            assert sc.shape == (n,), (g, sc.shape)
            assert int(grp.attrs["level"]) == main_level
            w, h = grp["image_size"][()]
            assert np.all(kp >= -0.5) and np.all(kp[:, 0] <= w) and np.all(kp[:, 1] <= h), g
            if n:
                norms = np.linalg.norm(desc.astype(np.float32), axis=0)
                assert np.allclose(norms, 1, atol=5e-3), (g, norms.min(), norms.max())
            # hloc's match_features loads every item of the group as an array: no subgroups.
            assert all(isinstance(v, h5py.Dataset) for v in grp.values()), g
            levels = sorted(k[: -len("keypoints")] for k in grp if k.startswith("level") and k.endswith("_keypoints"))
            assert levels, g
            for lv in levels:
                m = grp[lv + "keypoints"].shape[0]
                assert grp[lv + "descriptors"].shape[1] == m and grp[lv + "descriptors_short"].shape[1] == m
                assert grp[lv + "scores"].shape == (m,)
        if reference is not None:
            grp = f[name]
            for lv in reference["levels"]:
                pre = f"level{lv['level']}_"
                ours = grp[pre + "keypoints"][()] + 0.5  # hloc convention -> COLMAP
                ref = np.asarray(lv["keypoints"], np.float32).reshape(-1, 2)
                assert abs(len(ours) - len(ref)) <= 1 + len(ref) // 200, (lv["level"], len(ours), len(ref))
                if len(ref) and len(ours):
                    d = np.abs(ours[:, None, :] - ref[None, :, :]).max(2)
                    j = d.argmin(1)
                    close = d[np.arange(len(ours)), j] < 1e-3 * lv["stride"]
                    assert close.mean() >= 0.99, (lv["level"], close.mean())
                    full = grp[pre + "descriptors"][()].astype(np.float32).T[close]
                    sim = (full * np.asarray(lv["full"], np.float32)[j[close]]).sum(1)
                    assert sim.min() > 0.999, (lv["level"], sim.min())
        print(f"{path}: {len(groups)} image groups, hloc layout ok (h5py {h5py.__version__})")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--check-h5", help="check an sfpmap extract output with h5py")
    ap.add_argument("--name", help="with --check-h5 and --json: the group to compare")
    ap.add_argument("--model")
    ap.add_argument("--image")
    ap.add_argument("--png", help="re-save the image here as RGB PNG and use that")
    ap.add_argument("--json")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    if a.check_h5:
        ref = json.load(open(a.json)) if a.json and a.name else None
        check_h5(a.check_h5, ref, a.name)
        return
    assert a.model and a.image and a.json, "--model, --image and --json are required"

    img = Image.open(a.image).convert("RGB")
    if a.png:
        img.save(a.png)
        img = Image.open(a.png).convert("RGB")
    gray = np.asarray(img.convert("L"), dtype=np.float32) / 255.0

    so = ort.SessionOptions()
    so.intra_op_num_threads = a.threads
    so.inter_op_num_threads = 1
    s = ort.InferenceSession(a.model, so, providers=["CPUExecutionProvider"])
    md = s.get_modelmeta().custom_metadata_map
    assert md["sfp.contract"] in CONTRACTS, md.get("sfp.contract")
    strides = [int(v) for v in md["sfp.strides"].split(",")]
    ids = [int(v) for v in md["sfp.level_ids"].split(",")]
    tops = default_max_keypoints(md, len(strides))
    thr = default_thresholds(md, len(strides))
    radius = int(md["sfp.default_nms_radius"])
    names = [o.name for o in s.get_outputs()]
    outs = dict(zip(names, s.run(None, {md.get("sfp.input_name", "image"): gray[None, None]})))
    feats = [outs[f"feat_{i}"][0] for i in range(len(strides))]
    scores = [outs[f"score_{i}"][0, 0] for i in range(len(strides))]
    levels = []
    refine_to = md.get("sfp.refine_to_level")
    refine_to = None if refine_to is None else int(refine_to)
    image_refines = image_refine_levels(md, len(strides))
    for i, (px, short, full, v) in enumerate(level_features(feats, scores, strides, radius, thr, tops,
                                                             refine_to=refine_to, image=gray,
                                                             image_refines=image_refines,
                                                             detect_on=detect_levels(md, len(strides)))):
        levels.append({
            "level": ids[i],
            "stride": strides[i],
            "keypoints": (px + 0.5).tolist(),
            "scores": v.tolist(),
            "short": short.tolist(),
            "full": full.tolist(),
        })
    json.dump({
        "image_size": [img.width, img.height],
        "ort_version": ort.__version__,
        "levels": levels,
        "global": outs["global"][0].tolist(),
    }, open(a.json, "w"))


if __name__ == "__main__":
    main()
