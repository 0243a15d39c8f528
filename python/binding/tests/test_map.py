"""Reading maps: zero-copy views, ownership across close(), info(), hostile inputs."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import sfpmap

from conftest import run_cli


def rss_kb() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError("no VmRSS")


def test_views_have_the_shapes_info_states(sacre_sift):
    with sfpmap.Map(sacre_sift) as m:
        info = m.info()
        assert m.n_points == info["points"] and len(m.points) == info["points"]
        pos = m.points.positions
        assert pos.shape == (m.n_points, 3) and pos.dtype == np.float32
        assert m.points.colors.shape == (m.n_points, 3) and m.points.colors.dtype == np.uint8
        assert m.levels.ids == [l["level"] for l in info["levels"]]
        for level, li in zip(m.levels, info["levels"]):
            assert len(level) == li["points"]
            assert level.points.dtype == np.uint32 and level.points.shape == (li["points"],)
            assert level.short.dtype == np.float16
            assert level.short.shape == (li["points"], li["dim_short"])
            assert level.rest.shape == (li["points"], li["dim_full"] - li["dim_short"])
            assert level.projection.dtype == np.float32
            assert np.all(np.diff(level.points.astype(np.int64)) > 0)
        images = m.images
        assert len(images.names) == m.n_images == images.poses.shape[0]
        assert images.poses.shape[1] == 7 and images.poses.dtype == np.float64
        assert images.cameras.dtype == np.uint32
        vis = m.visibility
        assert vis.offsets.shape == (m.n_images + 1,) and vis.offsets.dtype == np.uint64
        assert int(vis.offsets[-1]) == vis.points.shape[0]
        assert len(m.cameras) == info["cameras"]


def test_info_is_the_cli_json(cli, sacre_sift):
    with sfpmap.Map(sacre_sift) as m:
        assert m.info() == json.loads(run_cli(cli, "info", sacre_sift, "--json"))


def test_two_views_of_a_section_share_memory_and_the_mapping(sacre_sift):
    m = sfpmap.Map(sacre_sift)
    a, b = m.levels[2].short, m.levels[2].short
    assert a is not b and np.shares_memory(a, b)
    assert a.__array_interface__["data"][0] == b.__array_interface__["data"][0]
    # The view's memory is the file's bytes at the section's offset: no copy.
    section = next(s for s in m.info()["sections"] if s["kind"] == "level_desc_short" and s["level"] == 2)
    raw = np.fromfile(sacre_sift, dtype=np.uint8)
    stored = raw  # the file, read independently
    assert a.nbytes == section["raw_bytes"]
    assert not a.flags.owndata and not a.flags.writeable
    with pytest.raises(ValueError):
        a[0, 0] = 1
    # The same bytes as the file holds somewhere (its section), read without the library.
    assert stored.tobytes().find(a.tobytes()) > 0
    m.close()


def test_zstd_section_is_decoded_once_and_shared(south_zstd):
    with sfpmap.Map(south_zstd) as m:
        codecs = {s["kind"]: s["codec"] for s in m.info()["sections"]}
        assert codecs["level_desc_short"] == "zstd"
        a, b = m.levels[2].short, m.levels[2].short
        assert np.shares_memory(a, b)
        assert not a.flags.writeable


def test_close_keeps_views_valid_and_refuses_the_map(sacre_sift):
    m = sfpmap.Map(sacre_sift)
    view = m.points.positions
    expected = view.copy()
    m.close()
    m.close()  # twice is fine
    assert m.closed
    with pytest.raises(sfpmap.ClosedError, match="the map is closed"):
        m.points.positions
    with pytest.raises(sfpmap.ClosedError):
        m.info()
    gc.collect()
    # The view still reads the mapping it keeps alive.
    assert np.array_equal(view, expected)
    assert isinstance(view.base, object) and view.base is not None
    del view
    gc.collect()


def test_context_manager_closes(sacre_sift):
    with sfpmap.Map(sacre_sift) as m:
        pass
    assert m.closed
    with pytest.raises(sfpmap.Error):
        m.n_points


def test_verify(sacre_sift):
    with sfpmap.Map(sacre_sift) as m:
        m.verify()


def test_no_such_level(sacre_sift):
    with sfpmap.Map(sacre_sift) as m:
        with pytest.raises(sfpmap.NoSuchLevelError, match=r"level 7"):
            m.levels[7]


def test_garbage_inputs_raise(tmp_path, cli, sacre_sift):
    junk = tmp_path / "junk.sfpm"
    junk.write_bytes(b"not a map at all" * 10)
    with pytest.raises(sfpmap.MapError) as e:
        sfpmap.Map(junk)
    # The CLI's message, without "error: ".
    r = subprocess.run([str(cli), "info", str(junk)], capture_output=True, text=True)
    assert r.stderr.strip() == f"error: {e.value}"
    with pytest.raises(sfpmap.FileError) as e:
        sfpmap.Map(tmp_path / "missing.sfpm")
    r = subprocess.run([str(cli), "info", str(tmp_path / "missing.sfpm")], capture_output=True, text=True)
    assert r.stderr.strip() == f"error: {e.value}"
    with pytest.raises(sfpmap.FileError):
        sfpmap.Map(tmp_path)  # a folder
    with pytest.raises(TypeError):
        sfpmap.Map(None)
    # A corrupted section: the map opens (index intact), verify() names the section.
    data = bytearray(sacre_sift.read_bytes())
    with sfpmap.Map(sacre_sift) as m:
        short = m.levels[2].short.tobytes()
    at = bytes(data).find(short)
    assert at > 0
    data[at + 10] ^= 0xFF
    bad = tmp_path / "bad.sfpm"
    bad.write_bytes(bytes(data))
    with sfpmap.Map(bad) as m:
        with pytest.raises(sfpmap.MapError, match="checksum"):
            m.verify()
    # Truncated files never crash.
    for cut in (0, 10, 63, 64, 200, len(data) // 2, len(data) - 1):
        t = tmp_path / f"cut{cut}.sfpm"
        t.write_bytes(bytes(data[:cut]))
        with pytest.raises(sfpmap.Error):
            sfpmap.Map(t)


def test_random_bytes_never_crash(tmp_path):
    # In a child interpreter: a crash there fails this test instead of the run.
    code = f"""
import os, random, sfpmap
random.seed(1)
good = open({str(tmp_path / 'x')!r}, 'wb')
for i in range(300):
    p = {str(tmp_path)!r} + f'/r{{i}}.sfpm'
    n = random.randint(0, 4096)
    open(p, 'wb').write(b'SFPMAP\\x00\\x00' + os.urandom(n))
    try:
        with sfpmap.Map(p) as m:
            m.info(); m.verify()
    except sfpmap.Error:
        pass
print('ok')
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


def test_a_view_of_a_large_map_costs_no_rss_until_touched(tmp_path):
    size_mb = int(os.environ.get("SFPMAP_TEST_BIG_MB", "1024"))
    points = max(1000, size_mb * 1024 * 1024 // (240 * 2 + 12))
    path = tmp_path / "big.sfpm"
    written = sfpmap._sfpmap._write_synthetic_map(str(path), points, 240, 64)
    gc.collect()
    # Drop the file's pages from this process' view: RSS counts mapped pages touched.
    before = rss_kb()
    m = sfpmap.Map(path)
    short = m.levels[0].short
    rest = m.levels[0].rest
    after_views = rss_kb()
    assert short.nbytes + rest.nbytes > 0.9 * written
    # Views touch no page: under 8 MB more than before, for a map of `written` bytes.
    assert after_views - before < 8 * 1024, (before, after_views, written)
    total = float(rest[::4096].astype(np.float32).sum())  # touch a little of it
    assert total > 0
    del short, rest
    m.close()
