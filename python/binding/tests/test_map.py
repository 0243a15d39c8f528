"""Reading maps: zero-copy views, ownership across close(), info(), hostile inputs."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import sfpmap

from conftest import assert_releases_the_gil, rss_kb, run_cli


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
    assert section["codec"] == "raw" and a.nbytes == section["raw_bytes"] == section["stored_bytes"]
    assert not a.flags.owndata and not a.flags.writeable
    with pytest.raises(ValueError):
        a[0, 0] = 1
    # The file's bytes at the section's offset, read with Python's own I/O, not the library.
    with open(sacre_sift, "rb") as f:
        f.seek(section["offset"])
        stored = np.frombuffer(f.read(section["stored_bytes"]), dtype=np.float16)
    assert a.shape == (section["rows"], section["cols"])
    assert np.array_equal(a.reshape(-1).view(np.uint16), stored.view(np.uint16))
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
    # The view still reads the mapping it keeps alive: its base is the map's owner of it.
    assert np.array_equal(view, expected)
    assert type(view.base) is sfpmap._sfpmap._Mapping
    del view
    gc.collect()


def test_a_closed_map_makes_no_localizer_and_a_localizer_outlives_its_close(sacre_sift, shared):
    scene = shared / "scenes/sacre-coeur"
    database = sfpmap.QueryDatabase(str(scene / "queries.db"))
    name, camera = sfpmap.read_queries(str(scene / "queries.txt"))[0]
    m = sfpmap.Map(sacre_sift)
    localizer = sfpmap.Localizer(m)
    order = localizer.level_order
    before = localizer.localize(database.features(name), camera)
    m.close()
    # A session over a closed map cannot be made; one made before holds the map it needs.
    with pytest.raises(sfpmap.ClosedError, match="the map is closed"):
        sfpmap.Localizer(m)
    gc.collect()
    assert localizer.level_order == order and order
    # It still localizes from the mapping it keeps, as it did before the close.
    after = localizer.localize(database.features(name), camera)
    assert (after.success, after.colmap, after.inliers) == (before.success, before.colmap, before.inliers)


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
        # Ids no level can have are no such level either, not an OverflowError.
        for level in (-1, 70000, 2**70):
            with pytest.raises(sfpmap.NoSuchLevelError, match=rf"no level {level} in this map"):
                m.levels[level]
            with pytest.raises(sfpmap.NoSuchLevelError):
                m.level(level)
            assert m.section("level_points", level) is None


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
    if size_mb >= 1024:
        # Checking a GB (a fresh map each time: a checked section is not checked again) and
        # slicing it let other Python threads run.
        assert_releases_the_gil(lambda _: sfpmap.Map(path).verify(), min_seconds=0.1)
        def slice_once(i: int) -> None:
            out = tmp_path / f"short-{i}.sfpm"  # a new name each call; removed after
            sfpmap.slice(path, levels=[0], short=True, out=out)
            out.unlink()

        assert_releases_the_gil(slice_once)


VECTORS = Path(__file__).resolve().parents[3] / "spec/vectors/valid"


@pytest.mark.parametrize("name", sorted(p.stem for p in VECTORS.glob("*.sfpm")))
def test_views_are_the_spec_vectors_content(name):
    """Every valid vector read through the package equals its .json: a section this version
    skips (later_minor: a later minor's codec, dtype or flag) is absent (None), never a view
    of bytes it cannot decode."""
    expected = json.loads((VECTORS / f"{name}.json").read_text())
    content = expected["content"]
    with sfpmap.Map(VECTORS / f"{name}.sfpm") as m:
        assert m.version == expected["version"] and m.n_points == content["points"]
        points = m.points
        for view, key in ((points.colors, "colors"), (points.ids, "point_ids")):
            if content[key] is None:
                assert view is None, key
            else:
                assert view.tolist() == content[key], key
        # Positions relative to the origin, raw or (minimal) decoded from the 16-bit grid.
        relative = points.relative()
        assert relative.dtype == np.float32 and relative.shape == (content["points"], 3)
        assert np.array_equal(relative, np.array(content["positions"], np.float32).reshape(-1, 3))
        world = points.world()
        assert np.array_equal(world, relative.astype(np.float64) + np.array(m.origin))
        if points.positions is None:
            assert points.positions_q16 is not None  # a minimal map: world() works all the same
        images = m.images
        if content["images"]:
            assert images.names == [i["name"] for i in content["images"]]
            assert images.cameras.tolist() == [i["camera"] for i in content["images"]]
            assert images.poses.tolist() == [i["cam_from_world"] for i in content["images"]]
            for i, image in enumerate(content["images"]):
                assert images.index(image["name"]) == i
        if content["visibility"] is not None:
            assert m.visibility.offsets.tolist() == content["visibility"]["offsets"]
            assert m.visibility.points.tolist() == content["visibility"]["points"]
        assert m.levels.ids == [l["level"] for l in content["levels"]]
        for level in content["levels"]:
            assert m.levels[level["level"]].points.tolist() == level["points"]
        # What info() lists as skipped is absent to every lookup.
        skipped = [s for s in m.info()["sections"] if s.get("skipped")]
        assert len(skipped) == len(expected["skipped_sections"])
        for s in skipped:
            if s["kind"] != "unknown":
                assert m.section(s["kind"], s["level"]) is None, s


def test_one_column_kinds_are_1d_and_descriptor_blocks_stay_2d(tmp_path, sacre_sift):
    # A level of 2 dimensions, 1 short: its blocks have one column and stay (rows, 1).
    path = tmp_path / "thin.sfpm"
    sfpmap._sfpmap._write_synthetic_map(str(path), 50, 2, 1)
    with sfpmap.Map(path) as m:
        level = m.levels[0]
        assert level.short.shape == (50, 1) and level.rest.shape == (50, 1)
        assert level.points.shape == (50,)
    # The kinds whose column count the spec fixes at 1 are 1-D.
    with sfpmap.Map(sacre_sift) as m:
        assert m.points.ids.shape == (m.n_points,)
        assert m.images.cameras.shape == (m.n_images,)
        assert m.visibility.points.ndim == 1 and m.visibility.offsets.ndim == 1
        assert m.section("image_name_offsets").shape == (m.n_images + 1,)
        assert m.images.poses.shape == (m.n_images, 7)


def test_images_metadata_and_cameras_are_read_once(sacre_sift):
    with sfpmap.Map(sacre_sift) as m:
        images = m.images
        assert images is m.images
        names = images.names
        assert names is m.images.names
        assert images.index(names[3]) == 3 and images.index(names[-1]) == len(names) - 1
        with pytest.raises(ValueError, match="no such image"):
            images.index("not-an-image.jpg")
        assert m.metadata is m.metadata and m.cameras is m.cameras
        assert m.origin == tuple(m.metadata["origin"]) and isinstance(m.origin, tuple)
        with pytest.raises(sfpmap.InputError, match="not a kind of the spec"):
            m.section("level_short")


def test_synthetic_maps_are_bounded_and_never_overwrite(tmp_path):
    write = sfpmap._sfpmap._write_synthetic_map
    path = tmp_path / "s.sfpm"
    with pytest.raises(sfpmap.InputError, match="dim_full 4097: at most 4096"):
        write(str(path), 10, 4097, 1)
    assert not path.exists()
    written = write(str(path), 10, 8, 4)
    # The CLI's output policy: an existing file only with force.
    with pytest.raises(sfpmap.FileError, match="exists"):
        write(str(path), 20, 8, 4)
    assert path.stat().st_size == written
    assert write(str(path), 20, 8, 4, force=True) > written
    with sfpmap.Map(path) as m:
        assert m.n_points == 20
    # Sizes past memory are refused before anything is allocated. In a child interpreter: an
    # allocation that fails aborts the process, which then fails this test, not the run.
    huge = tmp_path / "huge.sfpm"
    code = f"""
import sfpmap
for points, dims in ((2**32 - 1, 4096), (1 << 27, 4096), (1 << 20, 1 << 31)):
    try:
        sfpmap._sfpmap._write_synthetic_map({str(huge)!r}, points, dims, 1)
    except sfpmap.InputError as e:
        print(e)
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == [
        "4294967295 points of 4096 dims: over 4 GiB in memory",
        "134217728 points of 4096 dims: over 4 GiB in memory",
        "dim_full 2147483648: at most 4096 (the format's limit)",
    ]
    assert not huge.exists()
