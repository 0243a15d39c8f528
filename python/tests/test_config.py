"""`--set key=json_value` overrides of the training configs (python/sfp/config.py)."""
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from sfp.config import apply_sets  # noqa: E402


def test_dotted_keys_set_json_values_in_place():
    cfg = {"w": {"desc_proj": 1.0}, "threads": 1}
    out = apply_sets(cfg, ["w.desc_proj=0", "threads=2"])
    assert out is cfg and cfg == {"w": {"desc_proj": 0}, "threads": 2}


def test_an_unknown_key_is_refused_naming_it():
    with pytest.raises(SystemExit) as e:
        apply_sets({"w": {}}, ["w.typo=1"])
    assert "w.typo" in str(e.value)
