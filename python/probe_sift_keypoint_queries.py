"""Probe (issue 36): an SFP map's queries described by the SFP network at the query's own SIFT
keypoints (from the scene's queries.db) instead of at the network's keypoints.

An SFP map's points are the COLMAP model's SIFT points, described where SIFT observed them
(`convert --images`); a query's keypoints are the network's detections, a few pixels from any
SIFT keypoint. Described at the query's SIFT keypoints instead, the same sfp-v2 maps localize
at SIFT's precision on KITTI 06 and within about 2x of it on South Building (stop 49, medians):

  | map (sfp-v2)                   | network keypoints | SIFT keypoints    | SIFT level 2 short |
  | KITTI 06 level 2 short         | 0.0236 m / 0.081° | 0.0063 m / 0.028° | 0.0066 m / 0.027°  |
  | KITTI 06 full                  | 0.0075 m / 0.028° | 0.0058 m / 0.028° |                    |
  | South Building level 2 short   | 0.0043 / 0.123°   | 0.00074 / 0.017°  | 0.0004 / 0.008°    |
  | South Building full            | 0.0017 / 0.055°   | 0.00042 / 0.011°  |                    |
  (South Building in its model's units.)

So the SFP maps' imprecision is the map's points and the query's keypoints not being the same
image points, not the network's descriptors.

usage: python3 python/probe_sift_keypoint_queries.py MODEL.onnx EXTRACTED.h5 QUERIES.db OUT.h5 IMAGES_DIR
  EXTRACTED.h5: `sfpmap extract IMAGES_DIR -o EXTRACTED.h5` (layout and attributes are copied
  from it); then `sfpmap localize --map MAP [--short] --features OUT.h5 --query-list ...`.
  Needs numpy, h5py, pillow, onnxruntime.
"""
import os
import shutil
import sqlite3
import sys

import h5py
import numpy as np
import onnxruntime as ort
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from sfp.reference import bilinear, l2n  # noqa: E402

model, extracted, qdb, out, images = sys.argv[1:6]
shutil.copy(extracted, out)
s = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
md = s.get_modelmeta().custom_metadata_map
strides = [int(v) for v in md["sfp.strides"].split(",")]
L = len(strides)
con = sqlite3.connect(f"file:{qdb}?mode=ro&immutable=1", uri=True)
names = {iid: name for iid, name in con.execute("select image_id, name from images")}
kps = {}
for iid, rows, cols, data in con.execute("select image_id, rows, cols, data from keypoints"):
    if rows:
        kps[names[iid]] = np.frombuffer(data, np.float32).reshape(rows, cols)[:, :2].copy()
with h5py.File(out, "r+") as f:
    groups = []
    f.visititems(lambda n, o: groups.append(n) if isinstance(o, h5py.Group) and "keypoints" in o else None)
    for g in groups:
        if g not in kps:
            print("no SIFT keypoints for", g)
            continue
        img = Image.open(f"{images}/{g}").convert("L")
        gray = np.asarray(img, np.float32) / 255.0
        outs = dict(zip([o.name for o in s.get_outputs()], s.run(None, {"image": gray[None, None]})))
        feats = [outs[f"feat_{i}"][0] for i in range(L)]
        px = kps[g] - 0.5  # COLMAP (corner 0) -> pixel-index (centre 0)
        grp = f[g]
        for i in range(L):
            short = l2n(bilinear(feats[i], px / strides[i]))
            parts = [l2n(bilinear(feats[j], px / strides[j])) for j in range(i, L)]
            full = l2n(np.concatenate(parts, 1))
            for key, val in ((f"level{i}_keypoints", px.astype(np.float32)),
                             (f"level{i}_scores", np.ones(len(px), np.float32)),
                             (f"level{i}_descriptors", full.T.astype(np.float16)),
                             (f"level{i}_descriptors_short", short.T.astype(np.float16))):
                del grp[key]
                grp.create_dataset(key, data=val)
        main = int(grp.attrs["level"])
        for key, src in (("keypoints", f"level{main}_keypoints"), ("scores", f"level{main}_scores"),
                         ("descriptors", f"level{main}_descriptors")):
            data = grp[src][()]
            del grp[key]
            grp.create_dataset(key, data=data)
        print(g, len(px), "SIFT keypoints")
