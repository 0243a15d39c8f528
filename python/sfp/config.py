"""Training configs: `--set key=json_value` overrides (dotted keys into nested dicts), shared by
train_v2.py, distill_v2.py and distill_v3.py. An unknown key is refused, never added."""
from __future__ import annotations

import json


def apply_sets(cfg: dict, sets: list[str]) -> dict:
    """`cfg` with each `key=json_value` of `sets` applied in place (and returned)."""
    for kv in sets:
        k, v = kv.split("=", 1)
        d = cfg
        ks = k.split(".")
        for kk in ks[:-1]:
            d = d[kk]
        if ks[-1] not in d:
            raise SystemExit(f"--set {kv}: unknown config key {k}")
        d[ks[-1]] = json.loads(v)
    return cfg
