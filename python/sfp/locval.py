"""Query localization for model selection (issue 36): the shared scenes' held-out queries
localized with a candidate model as the product localizes them (the scenes' map images are
training images; their queries never are).

Why: held-out homography pairs did not predict localization. At step 25,357 the
ALIKED-distilled student beat sfp-v2 on the pairs' level-2 MMA@1 (0.47 against 0.31, refined
to level 0) and lost 3x on KITTI 06's level-2 short poses (median 7.6 cm against 2.4 cm,
`benches/models_compare.sh`). So a validation here exports the weights to ONNX and runs the
release binary: `convert --images`, `slice --level 2 --short`, `localize` (1 thread), `eval`
at (0.1 x the scene's camera spacing, 2 degrees), for the full map and its level-2 short
slice. The queries are never trained on (`distill_v3.py` asserts it by path and md5).

Needs `target/release/sfpmap` (`cargo build --release`) and the KITTI 06 scene built once
(`python/TRAINING-v3.md`, Install).
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import tempfile

# A variant that localized nothing counts as this many doublings of the reference's errors.
UNLOCALIZED_LOG2 = 6.0
# Each share of the queries lost under the recall bar counts as this many doublings.
RECALL_LOG2 = 4.0


def scene_dirs(names) -> dict[str, str]:
    """Each named scene's folder, as train_v2 finds the scenes whose map images are trained on."""
    import train_v2 as V  # python/train_v2.py: one home for where the scenes are

    known = dict(V.scene_dirs())
    out = {}
    for name in names:
        path = known.get(name)
        if path is None or not os.path.exists(os.path.join(path, "queries.txt")):
            raise SystemExit(f"query localization: no scene {name!r} with queries (known: {', '.join(known)})")
        out[name] = path
    return out


# A step of one scene takes seconds; past this the binary is taken as hung.
STEP_TIMEOUT_S = 600


def _run(cmd: list[str]) -> str:
    # Its own session: a Ctrl-C meant for training does not kill a localization half-way.
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                       timeout=STEP_TIMEOUT_S, start_new_session=True)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)}: exit {p.returncode}: {p.stderr.strip()[-500:]}")
    return p.stdout


def localize_scene(binary: str, model: str, scene: str, work: str) -> dict[str, float]:
    """`full_*` and `l2s_*`: `bytes`, `localized` (share), `recall`, `t`, `r` (medians, None when
    nothing localized) of the scene's queries against the model's map and its level-2 short slice."""
    full, l2s = os.path.join(work, "full.sfpm"), os.path.join(work, "l2s.sfpm")
    _run([binary, "convert", "--colmap", f"{scene}/sparse-map", "--images", f"{scene}/images", "--model", model,
          "-o", full, "--force", "-q"])
    _run([binary, "slice", full, "--level", "2", "--short", "-o", l2s, "--force", "-q"])
    out = {}
    for name, path, extra in (("full", full, []), ("l2s", l2s, ["--short"])):
        poses = path + ".poses"
        _run([binary, "localize", "--map", path, *extra, "--query-list", f"{scene}/queries.txt", "--images",
              f"{scene}/images", "--model", model, "--threads", "1", "-o", poses, "--force", "-q"])
        first = json.loads(_run([binary, "eval", "--poses", poses, "--gt", f"{scene}/gt_poses.txt", "--map", path,
                                 "--json"]))
        bar = f"{0.1 * first['scale']},2"
        d = json.loads(_run([binary, "eval", "--poses", poses, "--gt", f"{scene}/gt_poses.txt", "--map", path,
                             "--threshold", bar, "--json"]))
        if not d["queries"] or not d["recall"]:
            raise RuntimeError(f"{scene}: eval found no queries to score")
        out.update({f"{name}_bytes": os.path.getsize(path), f"{name}_localized": d["localized"] / d["queries"],
                    f"{name}_recall": d["recall"][0]["recall"], f"{name}_t": d["median_translation"],
                    f"{name}_r": d["median_rotation_deg"]})
    return out


def excess(res: dict, ref: list[float], variant: str) -> float:
    """How many doublings of the reference's median errors (`ref` = [translation, rotation], SIFT
    level-2 short's) the variant's are, translation and rotation averaged; plus RECALL_LOG2 for
    each share of queries under the recall bar. 0: the reference's precision; 1: the issue's
    bar (2x). Lower is better."""
    t, r = res[f"{variant}_t"], res[f"{variant}_r"]
    if t is None or r is None:
        return UNLOCALIZED_LOG2 + RECALL_LOG2
    logs = [math.log2(max(t, 1e-12) / ref[0]), math.log2(max(r, 1e-12) / ref[1])]
    return sum(logs) / 2 + RECALL_LOG2 * (1.0 - res[f"{variant}_recall"])


def validate_loc(model_path: str, binary: str, scenes: dict[str, str], refs: dict[str, list[float]]) -> dict:
    """Per scene `loc_<scene>_<key>` (see `localize_scene`) and `loc_<scene>_excess_<variant>`;
    `loc_excess_l2s` / `loc_excess_full`: their means over the scenes."""
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="sfp-locval-") as work:
        for name, path in scenes.items():
            res = localize_scene(binary, model_path, path, work)
            out.update({f"loc_{name}_{k}": v for k, v in res.items()})
            for variant in ("full", "l2s"):
                out[f"loc_{name}_excess_{variant}"] = excess(res, refs[name], variant)
    for variant in ("full", "l2s"):
        out[f"loc_excess_{variant}"] = sum(out[f"loc_{n}_excess_{variant}"] for n in scenes) / len(scenes)
    return out
