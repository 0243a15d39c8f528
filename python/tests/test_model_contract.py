"""Contract test for a shipped model (spec/extractor.md): `SFP_MODEL`, default models/sfp-v3.onnx
(the embedded default; CI runs it on every file of models/). Needs only onnxruntime, numpy, pillow.

    python3 -m pytest -q python/tests          # or, without pytest:
    python3 python/tests/test_model_contract.py
"""
from __future__ import annotations

import glob
import math
import os
import sys

import numpy as np
import onnxruntime as ort
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(REPO, "python"))
from sfp.reference import CONTRACTS, default_thresholds, detect_levels, image_refine_levels  # noqa: E402  (numpy only)
MODEL = os.environ.get("SFP_MODEL", os.path.join(REPO, "models", "sfp-v3.onnx"))
SHARED = os.environ.get("SFP_SHARED", os.path.normpath(os.path.join(REPO, "..", "shared")))
SCENE_IMAGES = os.path.join(SHARED, "data", "scenes", "south-building", "images")

REQUIRED_KEYS = [
    "sfp.contract", "sfp.levels", "sfp.level_ids", "sfp.strides", "sfp.dims", "sfp.short_dims",
    "sfp.full_dims", "sfp.global_dim", "sfp.global_norm", "sfp.input_name", "sfp.input_channels",
    "sfp.input_range", "sfp.input_normalisation", "sfp.padding", "sfp.size_rule", "sfp.pad_multiple",
    "sfp.cell_to_pixel", "sfp.score", "sfp.descriptor_norm", "sfp.outputs", "sfp.default_threshold",
    "sfp.default_nms_radius", "sfp.default_max_keypoints",
]

_session = None


def session():
    global _session
    if _session is None:
        so = ort.SessionOptions()
        so.intra_op_num_threads = 2
        _session = ort.InferenceSession(MODEL, so, providers=["CPUExecutionProvider"])
    return _session


def meta():
    return session().get_modelmeta().custom_metadata_map


def ints(key):
    return [int(v) for v in meta()[key].split(",")]


def real_image(w=640, h=480):
    files = sorted(f for f in glob.glob(os.path.join(SCENE_IMAGES, "*")) if f.lower().endswith((".jpg", ".jpeg", ".png")))
    assert files, f"no images under {SCENE_IMAGES}"
    im = Image.open(files[-1]).convert("L").resize((w, h), Image.BILINEAR)
    return np.asarray(im, dtype=np.float32)[None, None] / 255.0


def test_model_file_small_and_single():
    assert os.path.getsize(MODEL) < 5 * 1024 * 1024
    assert not glob.glob(MODEL + ".data") and not glob.glob(os.path.join(os.path.dirname(MODEL), "*.onnx.data"))


def test_metadata_contract():
    md = meta()
    missing = [k for k in REQUIRED_KEYS if k not in md]
    assert not missing, f"missing metadata_props: {missing}"
    assert md["sfp.contract"] in CONTRACTS
    n = int(md["sfp.levels"])
    assert n >= 3
    strides, dims, short, full = ints("sfp.strides"), ints("sfp.dims"), ints("sfp.short_dims"), ints("sfp.full_dims")
    assert len(strides) == len(dims) == len(short) == len(full) == n
    assert all(b == 2 * a for a, b in zip(strides, strides[1:]))
    assert all(b > a for a, b in zip(dims, dims[1:])), "channel dims must grow with depth"
    assert short == dims
    assert full == [sum(dims[i:]) for i in range(n)]
    assert md["sfp.input_channels"] == "1" and md["sfp.input_range"] == "0,1"
    assert md["sfp.padding"] == "none" and md["sfp.size_rule"] == "ceil"


def test_image_refinement_only_in_contract_2():
    """sfp-extractor/2 is /1 plus step 5: its two keys, one value a level, in range; a /1 model
    has neither (its older readers would ignore them and place keypoints elsewhere)."""
    md = meta()
    levels = image_refine_levels(md, int(md["sfp.levels"]))  # raises where the extractor refuses
    if md["sfp.contract"] != CONTRACTS[0]:
        assert any(levels), "a /2 or /3 model refines some level"


def test_default_thresholds_one_or_one_a_level_in_contract_2():
    """sfp.default_threshold: one score, or one a level in an sfp-extractor/2 model (a /1 reader
    reads one number); the shipped model's, and the cases src/extract/contract.rs refuses."""
    md = meta()
    n = int(md["sfp.levels"])
    assert len(default_thresholds(md, n)) == n  # raises where the extractor refuses
    v1, v2 = {"sfp.contract": CONTRACTS[0]}, {"sfp.contract": CONTRACTS[1]}
    assert default_thresholds({**v1, "sfp.default_threshold": "0.5"}, 4) == [0.5] * 4
    assert default_thresholds({**v2, "sfp.default_threshold": " 0.5, 0.5,0.1 ,0.5"}, 4)[2] == np.float32(0.1)
    for contract, value in [(v1, "0.5,0.5,0.1,0.5"), (v2, "0.5,0.1,0.5"), (v2, "0.5,0.5,1.5,0.5"),
                            (v2, "0.5,0.5,,0.5"), (v2, "NaN"), (v2, "0.2_5"), (v2, "inf")]:
        try:
            default_thresholds({**contract, "sfp.default_threshold": value}, 4)
        except ValueError:
            continue
        raise AssertionError(f"{contract} {value!r} accepted")


def test_io_names_and_types():
    s = session()
    ins = s.get_inputs()
    assert [i.name for i in ins] == ["image"]
    assert ins[0].type == "tensor(float)"
    assert ins[0].shape[1] == 1 and all(isinstance(d, str) for d in (ins[0].shape[0], ins[0].shape[2], ins[0].shape[3]))
    n = int(meta()["sfp.levels"])
    names = [o.name for o in s.get_outputs()]
    assert set(names) == {f"feat_{i}" for i in range(n)} | {f"score_{i}" for i in range(n)} | {"global"}
    assert meta()["sfp.outputs"].split(",") == names


def test_odd_size_shapes():
    s = session()
    strides, dims = ints("sfp.strides"), ints("sfp.dims")
    G = int(meta()["sfp.global_dim"])
    for (h, w) in [(481, 641), (37, 53)]:
        x = np.random.default_rng(1).random((2, 1, h, w), dtype=np.float32)
        outs = dict(zip([o.name for o in s.get_outputs()], s.run(None, {"image": x})))
        for i, (st, d) in enumerate(zip(strides, dims)):
            hh, ww = math.ceil(h / st), math.ceil(w / st)
            assert outs[f"feat_{i}"].shape == (2, d, hh, ww), (i, outs[f"feat_{i}"].shape)
            assert outs[f"score_{i}"].shape == (2, 1, hh, ww)
            sc = outs[f"score_{i}"]
            assert np.all(np.isfinite(sc)) and sc.min() >= 0 and sc.max() <= 1
            assert np.all(np.isfinite(outs[f"feat_{i}"]))
        g = outs["global"]
        assert g.shape == (2, G)
        assert np.allclose(np.linalg.norm(g, axis=1), 1.0, atol=1e-3)


def test_every_level_alive_on_real_image():
    s = session()
    x = real_image()
    outs = dict(zip([o.name for o in s.get_outputs()], s.run(None, {"image": x})))
    n = int(meta()["sfp.levels"])
    for i in range(n):
        p = outs[f"score_{i}"][0, 0]
        assert float(p.std()) > 0.02 and float(p.max() - p.min()) > 0.2, (i, float(p.std()), float(p.max() - p.min()))
        # keypoints: 3x3 local maxima above the model's default threshold (metadata)
        pad = np.pad(p, 1, constant_values=-1)
        nb = np.max(np.stack([pad[1 + dy:1 + dy + p.shape[0], 1 + dx:1 + dx + p.shape[1]]
                              for dy in (-1, 0, 1) for dx in (-1, 0, 1)]), 0)
        kp = int(((p >= nb) & (p > default_thresholds(meta(), n)[i])).sum())
        assert kp >= 10, f"level {i}: only {kp} keypoints"


def test_detect_level_only_in_contract_3():
    """sfp-extractor/3 is /2 plus `sfp.detect_level` (a level's keypoints found on a finer level's
    score map); an older reader would detect each level on its own map, so /1 and /2 refuse it."""
    md = meta()
    n = int(md["sfp.levels"])
    on = detect_levels(md, n)  # raises where the extractor refuses
    assert all(d <= i for i, d in enumerate(on))
    if md["sfp.model_name"] == "sfp-v3":
        assert md["sfp.contract"] == CONTRACTS[2] and on == [0, 1, 0, 3]
    v2, v3 = {"sfp.contract": CONTRACTS[1]}, {"sfp.contract": CONTRACTS[2]}
    assert detect_levels(v2, 4) == [0, 1, 2, 3]
    assert detect_levels({**v3, "sfp.detect_level": " 0,1, 0,3"}, 4) == [0, 1, 0, 3]
    for contract, value in [(v2, "0,1,0,3"), (v3, None), (v3, "0,1,0"), (v3, "0,2,2,3"), (v3, "0,1,-1,3"),
                            (v3, "0,1,0.5,3")]:
        md = dict(contract) if value is None else {**contract, "sfp.detect_level": value}
        try:
            detect_levels(md, 4)
        except ValueError:
            continue
        raise AssertionError(f"{contract} {value!r} accepted")


if __name__ == "__main__":
    tests = [v for k, v in sorted(globals().items()) if k.startswith("test_") and callable(v)]
    passed = failed = 0
    for t in tests:
        try:
            t()
            passed += 1
            print(f"PASS {t.__name__}")
        except Exception as e:  # noqa: BLE001
            failed += 1
            print(f"FAIL {t.__name__}: {e!r}")
    print(f"{passed} passed, {failed} failed")
    sys.exit(1 if failed else 0)
