#!/usr/bin/env python3
"""Export a trained SFP checkpoint to a single-file ONNX model with the extractor contract
(spec/extractor.md) in its metadata_props, then verify it with ONNX Runtime.

Example: python3 python/export.py python/runs/main/best.pt -o models/sfp-v1.onnx
The student of python/distill_v2.py (strided stem, same contract):
  python3 python/export.py python/checkpoints/sfp-v2s-state.pt -o models/sfp-v2s.onnx
The model name (sfp.model_name: a map built with one model is localized only with that model) comes
from --model-name, else the checkpoint's `model_name`, else sfp-v1.

--image-refine SIGMAS/RADII writes a model of sfp-extractor/2 (keypoints refined on the image,
spec/extractor.md step 5); with --detect-level LEVELS, of sfp-extractor/3 (a level's keypoints
detected on a finer level's score map). Given an .onnx file instead of a checkpoint, the network is kept as it
is and only the metadata is rewritten (needs onnx, not torch); sfp-v3 is sfp-v2's network so:
  python3 python/export.py models/sfp-v2.onnx --model-name sfp-v3 -o models/sfp-v3.onnx \
      --image-refine 1.5,2.5,1.5,4/2,3,2,5 --detect-level 0,1,0,3 \
      --threshold 0.5,0.5,0.5,0.5 --max-keypoints 4000,1000,4000,250
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from sfp.reference import (CONTRACTS, default_max_keypoints, default_thresholds,  # noqa: E402  (numpy only)
                           detect_levels, image_refine_levels)

# /2 is /1 plus step 5, the image refinement; /3 is /2 plus a level detected on a finer one's map.
CONTRACT, CONTRACT_IMAGE_REFINE, CONTRACT_DETECT_LEVEL = CONTRACTS

OPSET = 17


def contract_metadata(net, extra: dict | None = None, default_threshold: str = "0.5",
                      model_name: str = "sfp-v1") -> dict[str, str]:
    from sfp.model import output_names

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
        "sfp.default_threshold": str(default_threshold),
        "sfp.default_nms_radius": "1",
        "sfp.default_max_keypoints": "2000,1000,500,250",
    }
    if extra:
        md.update({k: str(v) for k, v in extra.items()})
    return md


def load_net(ckpt_path: str):
    import torch
    from sfp.model import SFP

    ck = torch.load(ckpt_path, map_location="cpu", weights_only=False)
    net = SFP.for_state_dict(ck["model"])  # full or strided stem, from the weight names
    net.eval()
    return net, ck


def export(net, out: str, metadata: dict[str, str]):
    import onnx
    import torch
    from sfp.model import SFPExtractor, output_names

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
    save_with_metadata(m, out)
    os.remove(tmp)
    if os.path.exists(tmp + ".data"):
        os.remove(tmp + ".data")
    return out


def _umask() -> int:
    # Read once, at import, before any thread: os.umask can only be read by setting it.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


UMASK = _umask()


def save_with_metadata(m, out: str):
    import onnx

    import tempfile

    m.producer_name = "sfpmap/python/export.py"
    m.doc_string = "Sparse Feature Pyramid extractor; contract in spec/extractor.md"
    onnx.checker.check_model(m)
    # Atomic: a temporary file in the same folder, flushed to disk, renamed over `out`.
    fd, tmp = tempfile.mkstemp(prefix=".export-", suffix=".onnx", dir=os.path.dirname(os.path.abspath(out)))
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(m.SerializeToString())
            f.flush()
            # mkstemp's file is private (0600); the model gets the mode any new file gets.
            os.fchmod(f.fileno(), 0o666 & ~UMASK)
            os.fsync(f.fileno())
        os.replace(tmp, out)
    except BaseException:
        os.unlink(tmp)
        raise


def image_refine_metadata(spec: str, levels: int) -> dict[str, str]:
    """`--image-refine 1.5,2.5,3,4/2,3,4,5` -> the sfp-extractor/2 keys (sigmas / radii per level)."""
    try:
        sig, rad = spec.split("/")
        sigmas = [float(v) for v in sig.split(",")]
        radii = [int(v) for v in rad.split(",")]
    except ValueError:
        raise SystemExit(f"--image-refine {spec!r}: SIGMAS/RADII, e.g. 1.5,2.5,3,4/2,3,4,5")
    md = {"sfp.contract": CONTRACT_IMAGE_REFINE,
          "sfp.image_refine_sigma": ",".join(f"{s:g}" for s in sigmas),
          "sfp.image_refine_radius": ",".join(str(r) for r in radii)}
    try:
        image_refine_levels(md, levels)  # the extractor's rules
    except ValueError as e:
        raise SystemExit(f"--image-refine {spec!r}: {e}")
    return md


def detect_level_metadata(spec: str, md: dict[str, str]) -> dict[str, str]:
    """`--detect-level 0,1,0,3` -> the sfp-extractor/3 keys (the level whose score map finds each
    level's keypoints); `md` must already be of contract /2 (/3 is /2 plus this key)."""
    if md.get("sfp.contract") != CONTRACT_IMAGE_REFINE:
        raise SystemExit(f"--detect-level {spec!r} needs --image-refine (contract /3 is /2 plus the key)")
    out = {"sfp.contract": CONTRACT_DETECT_LEVEL, "sfp.detect_level": spec}
    try:
        values = detect_levels(out, int(md["sfp.levels"]))  # the extractor's rules
    except ValueError as e:
        raise SystemExit(f"--detect-level {spec!r}: {e}")
    out["sfp.detect_level"] = ",".join(str(v) for v in values)  # as the extractor reads it
    return out


# The detection defaults' metadata keys and the flags that set them (named in refusals).
FLAG_OF = {"sfp.default_threshold": "--threshold", "sfp.default_max_keypoints": "--max-keypoints"}


def product_metadata(net, extra: dict, model_name: str, image_refine: str | None = None,
                     detect_level: str | None = None, threshold: str | None = None,
                     max_keypoints: str | None = None) -> dict[str, str]:
    """A checkpoint's contract metadata with the export options of `main` (`--image-refine`,
    `--detect-level`, `--threshold`, `--max-keypoints`; None: the contract /1 defaults), held to
    the extractor's rules: what `main` writes and what the distillation's validation exports."""
    extra = dict(extra)
    if image_refine:
        extra.update(image_refine_metadata(image_refine, len(net.dims)))
    if detect_level:
        extra.update(detect_level_metadata(detect_level, {**extra, "sfp.levels": str(len(net.dims))}))
    md = contract_metadata(net, extra, "0.5" if threshold is None else str(threshold), model_name)
    if max_keypoints is not None:
        md["sfp.default_max_keypoints"] = str(max_keypoints)
    checked_detection(md, lambda key: FLAG_OF[key])
    return md


def checked_detection(md: dict[str, str], origin) -> None:
    """Holds `md`'s detection defaults to the extractor's rules (python/sfp/reference.py, as
    src/extract/contract.rs), naming `origin(key)` where they fail, and writes them back as the
    extractor reads them (Python's float() and int() take more forms than Rust's parsers)."""
    levels = int(md["sfp.levels"])
    for key, rule in (("sfp.default_max_keypoints", default_max_keypoints),
                      ("sfp.default_threshold", default_thresholds)):
        try:
            values = rule(md, levels)
        except ValueError as e:
            raise SystemExit(f"{origin(key)}: {e}")
        if key == "sfp.default_max_keypoints":
            md[key] = ",".join(str(v) for v in values)
        else:  # one value stays one
            md[key] = ",".join(repr(float(v)) for v in md[key].split(","))


def retag(src: str, out: str, name: str, refine: str | None, detection: dict[str, str],
          detect_level: str | None = None):
    """An exported model's network under new metadata: its name, where the network came from,
    with `refine` contract /2 (and `detect_level` /3), and the detection defaults in `detection`
    (metadata key: value)."""
    import onnx

    data = open(src, "rb").read()
    m = onnx.load_from_string(data)
    md = {p.key: p.value for p in m.metadata_props}
    if not md.get("sfp.contract", "").startswith("sfp-extractor/"):
        raise SystemExit(f"{src}: not an SFP model (no sfp.contract)")
    for k in ("sfp.image_refine_sigma", "sfp.image_refine_radius", "sfp.detect_level"):
        md.pop(k, None)
    md["sfp.contract"] = CONTRACT
    md["sfp.model_name"] = name
    md["sfp.network_from"] = f"{os.path.basename(src)} sha256 {hashlib.sha256(data).hexdigest()}"
    if refine:
        md.update(image_refine_metadata(refine, int(md["sfp.levels"])))
    if detect_level:
        md.update(detect_level_metadata(detect_level, md))
    md.update(detection)
    checked_detection(md, lambda key: FLAG_OF[key] if key in detection else (
        f"{src}'s {key} (one a level needs --image-refine, contract /2)"))
    del m.metadata_props[:]
    for k, v in md.items():
        e = m.metadata_props.add()
        e.key, e.value = k, v
    save_with_metadata(m, out)


def verify(net, path: str, sizes=((481, 641), (480, 640), (33, 47))):
    import onnxruntime as ort

    s = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    import torch
    from sfp.model import SFPExtractor

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
    ap.add_argument("--threshold", default=None,
                    help="default keypoint score threshold (metadata): one, or one a level (sfp-extractor/2 "
                         "only); a checkpoint's default 0.5, an .onnx input's kept")
    ap.add_argument("--max-keypoints", default=None,
                    help="default keypoint cap per level, finest first (metadata); a checkpoint's default "
                         "2000,1000,500,250, an .onnx input's kept")
    ap.add_argument("--model-name", default=None, help="sfp.model_name (default: the checkpoint's, else sfp-v1)")
    ap.add_argument("--refine-to-level", default=None,
                    help="sfp.refine_to_level: refine levels 2.. coarse to fine down to this level; "
                         "'none' leaves the key out (default: the checkpoint's, else none: one level)")
    ap.add_argument("--image-refine", default=None, metavar="SIGMAS/RADII",
                    help="sfp-extractor/2: refine each level's keypoints on the image (step 5), e.g. "
                         "1.5,2.5,3,4/2,3,4,5 (sigma and radius per level, input pixels; 0: not refined)")
    ap.add_argument("--detect-level", default=None, metavar="LEVELS",
                    help="sfp-extractor/3 (with --image-refine): per level, the level whose score map its "
                         "keypoints are detected on, itself or a finer one, e.g. 0,1,0,3")
    args = ap.parse_args()
    if args.ckpt.endswith(".onnx"):
        if not args.model_name or not args.out:
            raise SystemExit("an .onnx input needs --model-name and -o")
        if os.path.exists(args.out) and os.path.samefile(args.out, args.ckpt):
            raise SystemExit(f"-o {args.out}: the input itself (write another file)")
        detection = {k: v for k, v in (("sfp.default_threshold", args.threshold),
                                       ("sfp.default_max_keypoints", args.max_keypoints)) if v is not None}
        retag(args.ckpt, args.out, args.model_name, args.image_refine, detection, args.detect_level)
        h = hashlib.sha256(open(args.out, "rb").read()).hexdigest()
        print(f"wrote {args.out}: {os.path.getsize(args.out)} bytes, sha256 {h}")
        return
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
    md = product_metadata(net, extra, name, args.image_refine, args.detect_level, args.threshold,
                          args.max_keypoints)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    export(net, args.out, md)
    if not args.no_verify:
        verify(net, args.out)
    h = hashlib.sha256(open(args.out, "rb").read()).hexdigest()
    print(f"wrote {args.out}: {os.path.getsize(args.out)} bytes, sha256 {h}")


if __name__ == "__main__":
    main()
