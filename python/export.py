#!/usr/bin/env python3
"""Export a trained SFP checkpoint to a single-file ONNX model with the extractor contract
(spec/extractor.md) in its metadata_props, then verify it with ONNX Runtime.

Example: python3 python/export.py python/runs/main/best.pt -o models/sfp-v1.onnx
The student of python/distill_v2.py (strided stem, same contract):
  python3 python/export.py python/checkpoints/sfp-v2s-state.pt -o models/sfp-v2s.onnx
The model name (sfp.model_name: a map built with one model is localized only with that model) comes
from --model-name, else the checkpoint's `model_name`, else sfp-v1.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from sfp.model import SFP, SFPExtractor, output_names  # noqa: E402

CONTRACT = "sfp-extractor/1"
OPSET = 17


def contract_metadata(net: SFP, extra: dict | None = None, threshold: float = 0.5,
                      model_name: str = "sfp-v1") -> dict[str, str]:
    dims = list(net.dims)
    full = [sum(dims[i:]) for i in range(len(dims))]
    md = {
        "sfp.contract": CONTRACT,
        "sfp.model_name": model_name,
        "sfp.levels": str(len(dims)),
        "sfp.level_ids": ",".join(str(i) for i in range(len(dims))),
        "sfp.strides": ",".join(str(s) for s in net.strides),
        "sfp.dims": ",".join(str(d) for d in dims),
        "sfp.short_dims": ",".join(str(d) for d in dims),
        "sfp.full_dims": ",".join(str(d) for d in full),
        "sfp.full_layout": "concat of levels i..last, each L2-normalised, then L2-normalised",
        "sfp.global_dim": str(dims[-1]),
        "sfp.global_norm": "l2",
        "sfp.input_name": "image",
        "sfp.input_channels": "1",
        "sfp.input_color": "gray",
        "sfp.input_gray_weights": "0.299,0.587,0.114",
        "sfp.input_range": "0,1",
        "sfp.input_normalisation": "x = pixel / 255 (no mean/std)",
        "sfp.padding": "none",
        "sfp.size_rule": "ceil",
        "sfp.pad_multiple": "1",
        "sfp.cell_to_pixel": "x = stride * col, y = stride * row (pixel-centre origin 0; COLMAP: +0.5)",
        "sfp.score": "sigmoid",
        "sfp.descriptor_norm": "l2",
        "sfp.descriptor_sampling": "bilinear, align_corners=true in cell coordinates (x / stride)",
        "sfp.outputs": ",".join(output_names(len(dims))),
        "sfp.default_threshold": str(threshold),
        "sfp.default_nms_radius": "1",
        "sfp.default_max_keypoints": "2000,1000,500,250",
    }
    if extra:
        md.update({k: str(v) for k, v in extra.items()})
    return md


def load_net(ckpt_path: str) -> tuple[SFP, dict]:
    ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    net = SFP.for_state_dict(ck["model"])  # full or strided stem, from the weight names
    net.eval()
    return net, ck


def export(net: SFP, out: str, metadata: dict[str, str]):
    import onnx

    ext = SFPExtractor(net).eval()
    x = torch.rand(1, 1, 97, 131)
    names = output_names(len(net.dims))
    tmp = out + ".tmp.onnx"
    dyn = {"image": {0: "N", 2: "H", 3: "W"}}
    for i in range(len(net.dims)):
        dyn[f"feat_{i}"] = {0: "N", 2: f"H{i}", 3: f"W{i}"}
        dyn[f"score_{i}"] = {0: "N", 2: f"H{i}", 3: f"W{i}"}
    dyn["global"] = {0: "N"}
    with torch.no_grad():
        torch.onnx.export(ext, (x,), tmp, input_names=["image"], output_names=names,
                          dynamic_axes=dyn, opset_version=OPSET, dynamo=False, do_constant_folding=True)
    m = onnx.load(tmp, load_external_data=True)
    del m.metadata_props[:]
    for k, v in metadata.items():
        e = m.metadata_props.add()
        e.key, e.value = k, v
    m.producer_name = "sfpmap/python/export.py"
    m.doc_string = "Sparse Feature Pyramid extractor; contract in spec/extractor.md"
    onnx.checker.check_model(m)
    onnx.save(m, out)
    os.remove(tmp)
    if os.path.exists(tmp + ".data"):
        os.remove(tmp + ".data")
    return out


def verify(net: SFP, path: str, sizes=((481, 641), (480, 640), (33, 47))):
    import onnxruntime as ort

    s = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    ext = SFPExtractor(net).eval()
    for (h, w) in sizes:
        x = np.random.default_rng(0).random((2, 1, h, w), dtype=np.float32)
        outs = s.run(None, {"image": x})
        with torch.no_grad():
            ref = ext(torch.from_numpy(x))
        for o, r, name in zip(outs, ref, [o.name for o in s.get_outputs()]):
            assert o.shape == tuple(r.shape), (name, o.shape, r.shape)
            err = float(np.abs(o - r.numpy()).max())
            assert err < 1e-3, (name, err)
        for i, st in enumerate(net.strides):
            f = outs[2 * i]
            assert f.shape == (2, net.dims[i], -(-h // st), -(-w // st)), (f.shape, h, w, st)
        print(f"verified {h}x{w}: " + ", ".join(f"{o.name}{list(v.shape)}" for o, v in zip(s.get_outputs(), outs)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("ckpt")
    ap.add_argument("-o", "--out", default=None, help="default models/<model name>.onnx")
    ap.add_argument("--no-verify", action="store_true")
    ap.add_argument("--threshold", type=float, default=0.5, help="default keypoint score threshold (metadata)")
    ap.add_argument("--model-name", default=None, help="sfp.model_name (default: the checkpoint's, else sfp-v1)")
    ap.add_argument("--refine-to-level", default=None,
                    help="sfp.refine_to_level: refine levels 2.. coarse to fine down to this level; "
                         "'none' leaves the key out (default: the checkpoint's, else none: one level)")
    args = ap.parse_args()
    net, ck = load_net(args.ckpt)
    name = args.model_name or ck.get("model_name") or "sfp-v1"
    if net.stem_mode != "full" and name == "sfp-v1":
        raise SystemExit("a strided-stem network is not sfp-v1: give --model-name")
    minutes = ck.get("minutes", ck.get("meta", {}).get("total_minutes", 0))
    extra = {"sfp.train_steps": ck.get("step", ""),
             "sfp.train_minutes": round(float(minutes), 1),
             "sfp.train_loss": ck.get("args", {}).get("loss", "")}
    extra.update(ck.get("export_metadata", {}))  # e.g. the distillation's teacher
    if args.refine_to_level == "none":
        extra.pop("sfp.refine_to_level", None)
    elif args.refine_to_level is not None:
        if not args.refine_to_level.isdigit() or int(args.refine_to_level) >= len(net.dims):
            raise SystemExit(f"--refine-to-level {args.refine_to_level}: a level 0 to {len(net.dims) - 1}, or none")
        extra["sfp.refine_to_level"] = int(args.refine_to_level)
    args.out = args.out or os.path.join("models", f"{name}.onnx")  # never a student over sfp-v1.onnx
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    export(net, args.out, contract_metadata(net, extra, args.threshold, name))
    if not args.no_verify:
        verify(net, args.out)
    h = hashlib.sha256(open(args.out, "rb").read()).hexdigest()
    print(f"wrote {args.out}: {os.path.getsize(args.out)} bytes, sha256 {h}")


if __name__ == "__main__":
    main()
