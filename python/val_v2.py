#!/usr/bin/env python3
"""train_v2.py's validation (eval mode) on any weights: the 16 fixed homography pairs and 16 fixed
multi-view pairs of the held-out colmap/kapture_maupertuis, same seeds as in training.

  python3 python/val_v2.py models/sfp-v1.onnx python/checkpoints/sfp-v2-state.pt
"""
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import train as T  # noqa: E402
import train_v2 as V  # noqa: E402
from sfp import data as D, multiview as MV  # noqa: E402
from sfp.model import SFP  # noqa: E402

torch.set_num_threads(1)
vs = D.PairSampler([D.load_gray(p, 640) for p in D.val_files()], size=256, seed=1234)
val_h = [tuple(torch.from_numpy(a) for a in vs.batch(4)) for _ in range(4)]
vsc = MV.SfMScene(V.VAL_MODEL[0], os.path.join(V.DATA, V.VAL_MODEL[1]), os.path.join(V.DATA, V.VAL_MODEL[2]))
vmv = MV.MVPairSampler([vsc], size=256, kmax=256, min_shared=30, seed=4321, photo=0.0)
val_mv = [tuple(torch.from_numpy(a) for a in vmv.batch(4)) for _ in range(4)]
for p in sys.argv[1:]:
    if p.endswith(".onnx"):
        net = SFP()
        V.load_v1_encoder(net, p)
        step = "-"
    else:
        ck = torch.load(p, map_location="cpu", weights_only=False)
        net = SFP.for_state_dict(ck["model"])  # also distill_v2.py's strided students
        step = ck.get("step")
    net.eval()
    a, r, s = T.validate(net, val_h)
    m = V.validate_mv(net, val_mv)
    print(f"{p} step {step}: hom_acc {np.round(a, 3)} mv_acc {np.round(m, 3)} rates {np.round(r, 3)} std {np.round(s, 3)}")
