"""The extractor from Python: the CLI's features, arrays as images, hostile inputs."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest
import sfpmap

from conftest import assert_releases_the_gil, gil_stall, need_module, rss_kb, run_cli


@pytest.fixture(scope="module")
def extractor():
    return sfpmap.Extractor()


def test_extract_equals_the_cli_features_h5(cli, shared, work, extractor):
    # features.h5 keeps keypoints in hloc's convention (its reader turns them back) and the
    # descriptors before their f16 rounding: the same keypoints, descriptors to f16 precision.
    scene = shared / "scenes/south-building"
    name = sorted(p.name for p in (scene / "images").iterdir())[3]
    h5 = work / "one.h5"
    run_cli(cli, "extract", scene / "images" / name, "-o", h5, "--force")
    from_cli = sfpmap.read_features_h5(h5).features(name)
    mine = extractor.extract(scene / "images" / name)
    assert extractor.descriptor == "sfp-v3"
    assert from_cli.levels == mine.levels == [0, 1, 2, 3]
    for level in mine.levels:
        assert np.array_equal(from_cli.keypoints(level), mine.keypoints(level))
        assert np.allclose(from_cli.descriptors(level), mine.descriptors(level), atol=1e-3, rtol=0)
        assert mine.scores(level).shape == (mine.keypoints(level).shape[0],)
    assert mine.global_descriptor is not None and mine.global_descriptor.ndim == 1


def test_refine_and_global_max_side_are_the_cli_flags(cli, shared, work, extractor):
    # `refine=False` is `--no-refine`, `global_max_side` is `--global-max-side` (512 unless
    # given; 0: the image's own size; under 16 refused).
    scene = shared / "scenes/south-building"
    name = sorted(p.name for p in (scene / "images").iterdir())[3]
    image = scene / "images" / name
    for flags, kwargs in [
        ([], {}),
        (["--no-refine", "--global-max-side", "0"], {"refine": False, "global_max_side": 0}),
    ]:
        h5 = work / "flags.h5"
        run_cli(cli, "extract", image, "-o", h5, "--force", *flags)
        from_cli = sfpmap.read_features_h5(h5).features(name)
        mine = extractor.extract(image, **kwargs)
        for level in mine.levels:
            assert np.array_equal(from_cli.keypoints(level), mine.keypoints(level)), (flags, level)
        assert np.allclose(from_cli.global_descriptor, mine.global_descriptor, atol=1e-6), flags
    own = extractor.extract(image, global_max_side=0).global_descriptor
    small = extractor.extract(image).global_descriptor
    assert float(own @ small) < 0.999
    assert not np.array_equal(
        extractor.extract(image, refine=False).keypoints(2), extractor.extract(image).keypoints(2)
    )
    with pytest.raises(sfpmap.InputError, match="global_max_side 8: 0 .* or at least 16"):
        extractor.extract(image, global_max_side=8)


def write_png(path, gray: np.ndarray) -> None:
    """An 8-bit greyscale PNG, by hand (no imaging package needed)."""
    import struct
    import zlib

    h, w = gray.shape
    raw = b"".join(b"\x00" + gray[y].tobytes() for y in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def test_arrays_are_images(tmp_path, extractor):
    rng = np.random.default_rng(7)
    small = rng.integers(0, 256, (30, 40), dtype=np.uint8)
    gray = np.kron(small, np.ones((16, 16), np.uint8))  # 480 x 640 blocks: corners to detect
    png = tmp_path / "blocks.png"
    write_png(png, gray)
    from_file = extractor.extract(png)
    from_array = extractor.extract(gray)
    from_floats = extractor.extract(gray.astype(np.float32) / 255.0)
    from_rgb = extractor.extract(np.repeat(gray[:, :, None], 3, axis=2))
    assert len(from_file) > 0
    for f in (from_array, from_floats, from_rgb):
        assert f.levels == from_file.levels
        for level in f.levels:
            assert np.array_equal(f.keypoints(level), from_file.keypoints(level))
            assert np.array_equal(f.descriptors(level), from_file.descriptors(level))


def test_hostile_inputs_raise(tmp_path, extractor):
    with pytest.raises(sfpmap.FileError):
        extractor.extract(tmp_path / "missing.jpg")
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"\xff\xd8\xff" + b"\x00" * 100)
    with pytest.raises(sfpmap.ExtractError):
        extractor.extract(junk)
    with pytest.raises(sfpmap.InputError):
        extractor.extract(np.zeros((4, 4, 2), np.uint8))
    with pytest.raises(sfpmap.InputError):
        extractor.extract(np.zeros((4, 4), np.int64))
    with pytest.raises(sfpmap.InputError):
        extractor.extract(np.zeros((0, 4), np.uint8))
    bad_model = tmp_path / "model.onnx"
    bad_model.write_bytes(b"not onnx")
    with pytest.raises(sfpmap.ExtractError):
        sfpmap.Extractor(model=bad_model)
    with pytest.raises(sfpmap.InputError):
        sfpmap.read_features_h5(junk)
    with pytest.raises(sfpmap.InputError):
        sfpmap.QueryDatabase(junk)
    with pytest.raises(sfpmap.InputError):
        sfpmap.read_queries(junk)
    # The CLI's ranges: a radius of 10^6 cells would run for hours.
    image = np.zeros((64, 64), np.uint8)
    for kwargs, words in [
        ({"nms_radius": 10**6}, "nms_radius 1000000: 0 to 64 cells"),
        ({"threshold": float("nan")}, "threshold NaN: a score in [0, 1]"),
        ({"max_keypoints": [0]}, "max_keypoints 0: 1 to 1000000 a level"),
    ]:
        with pytest.raises(sfpmap.InputError, match=re.escape(words)):
            extractor.extract(image, **kwargs)


def test_hloc_features_h5_written_by_h5py(tmp_path):
    """hloc's own layout, as h5py writes it: a group per image name (nested for names with
    folders) holding keypoints (N×2 f32), descriptors (D×N, f16 or f32), scores, image_size;
    no per-level datasets, no global descriptor."""
    h5py = need_module("h5py")
    rng = np.random.default_rng(3)
    images = {}
    path = tmp_path / "feats-superpoint-n4096-r1024.h5"
    with h5py.File(path, "w") as f:
        for name, n, dtype in (("query/day/a.jpg", 7, np.float16), ("b.png", 5, np.float32)):
            keypoints = rng.uniform(0, 500, (n, 2)).astype(np.float32)
            descriptors = rng.normal(size=(256, n)).astype(dtype)
            g = f.create_group(name)
            g.create_dataset("keypoints", data=keypoints)
            g.create_dataset("descriptors", data=descriptors)
            g.create_dataset("scores", data=rng.uniform(0, 1, n).astype(np.float32))
            g.create_dataset("image_size", data=np.array([640, 480]))
            images[name] = (keypoints, descriptors)
    features = sfpmap.read_features_h5(path)
    for name, (keypoints, descriptors) in images.items():
        f = features.features(name)
        assert f.levels == [None] and f.global_descriptor is None
        # hloc's pixel convention (first pixel centre at 0) to COLMAP's: +0.5.
        assert np.array_equal(f.keypoints(), keypoints.astype(np.float64) + 0.5)
        rows = descriptors.T.astype(np.float32)
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
        assert np.allclose(f.descriptors(), rows, atol=1e-6)
    assert features.features("query/day") is None  # a folder, not an image
    assert features.features("query/day/a.jpg/keypoints") is None  # a dataset
    assert features.features("missing.jpg") is None
    # A dataset that is no float array is refused, named.
    with h5py.File(path, "a") as f:
        f["b.png"]["bad"] = np.zeros(3)
        g = f.create_group("ints.jpg")
        g.create_dataset("keypoints", data=np.zeros((2, 2), np.int32))
        g.create_dataset("descriptors", data=np.zeros((4, 2), np.float32))
    features = sfpmap.read_features_h5(path)
    assert features.features("b.png") is not None
    with pytest.raises(sfpmap.InputError, match=r"ints.jpg/keypoints: values of 32-bit integers \(little-endian f16 or f32 expected\)"):
        features.features("ints.jpg")


def test_a_large_features_h5_is_read_on_demand(tmp_path):
    """hloc's files reach tens of GB: opening one and reading an image's features reads the
    metadata on the way and that image's datasets, not the file."""
    h5py = need_module("h5py")
    path = tmp_path / "large.h5"
    with h5py.File(path, "w") as f:
        # 256 MB of other images' data, written in 16 MB slabs.
        other = f.create_dataset("other.jpg/descriptors", shape=(256, 1 << 20), dtype=np.uint8)
        for i in range(0, 256, 16):
            other[i : i + 16] = 1
        g = f.create_group("a.jpg")
        g["keypoints"] = np.array([[1, 2], [3, 4]], np.float32)
        g["descriptors"] = np.ones((8, 2), np.float32)
    before = rss_kb()
    features = sfpmap.read_features_h5(path)
    f = features.features("a.jpg")
    after = rss_kb()
    assert len(f) == 2
    assert after - before < 32 * 1024, (before, after)


def test_extractor_threads_and_the_gil(tmp_path, extractor):
    for threads in (0, -1):
        with pytest.raises(sfpmap.InputError, match=f"threads {threads}: at least 1 thread"):
            sfpmap.Extractor(threads=threads)
    rng = np.random.default_rng(11)
    image = np.kron(rng.integers(0, 256, (60, 80), dtype=np.uint8), np.ones((16, 16), np.uint8))
    assert_releases_the_gil(lambda _: extractor.extract(image))
    # Two threads on one extractor take turns, and the one waiting for its turn (here: a
    # thread starting its next image while the other's runs) waits without the GIL: this
    # thread never stalls for the other's run.
    from concurrent.futures import ThreadPoolExecutor

    t0 = time.perf_counter()
    one = extractor.extract(image)
    single = time.perf_counter() - t0
    got = []

    def four_on_two_threads():
        with ThreadPoolExecutor(2) as pool:
            got.extend(pool.map(extractor.extract, [image] * 4))

    seconds, longest = gil_stall(four_on_two_threads)
    assert longest < single / 2, f"stalled {longest:.3f} s; one image takes {single:.3f} s"
    assert len(got) == 4 and all(np.array_equal(f.keypoints(0), one.keypoints(0)) for f in got)


def test_array_sides_past_u32_are_refused_not_truncated(extractor):
    # Broadcast views: no memory behind them, and the shape is refused before any copy (one
    # would not fit in memory: a copy could only fail).
    tall = np.broadcast_to(np.zeros((1, 1), np.uint8), (2**32 + 16, 1 << 20))
    with pytest.raises(sfpmap.InputError, match=r"image: shape \[4294967312, 1048576\]: a side of 4294967312 pixels"):
        extractor.extract(tall)
    wide = np.broadcast_to(np.zeros((1, 1, 3), np.float32), (1 << 20, 2**32 + 1, 3))
    with pytest.raises(sfpmap.InputError, match="a side of 4294967297 pixels"):
        extractor.extract(wide)


def test_error_messages_are_one_line_and_name_the_file_once(tmp_path, extractor):
    # ONNX Runtime ends this message with a line break: kept to one line.
    model = tmp_path / "no-opset.onnx"
    model.write_bytes(b"\x08\x07\x12\x03abc\x3a\x02\x0a\x00")
    with pytest.raises(sfpmap.ExtractError, match="Missing opset") as e:
        sfpmap.Extractor(model=model)
    assert "\n" not in str(e.value) and str(e.value) == str(e.value).strip()
    # The database's errors name it already: once.
    junk = tmp_path / "junk.db"
    junk.write_bytes(b"not a database" * 100)
    with pytest.raises(sfpmap.InputError) as e:
        sfpmap.QueryDatabase(junk)
    assert str(e.value).count(str(junk)) == 1, str(e.value)


def child_env(tmp_path, **extra):
    """This environment for a child interpreter: no ONNX Runtime but what `extra` says."""
    env = {k: v for k, v in os.environ.items() if k not in ("ORT_DYLIB_PATH", "ORT_DISABLE_TELEMETRY")}
    env.update(HOME=str(tmp_path / "home"), XDG_CACHE_HOME=str(tmp_path / "cache"), **extra)
    return env


def test_telemetry_is_off_from_import(tmp_path):
    # Set once at import (no thread of ours yet), not later in a call that released the GIL,
    # when another thread may read the environment.
    code = (
        "import ctypes, sfpmap\n"
        "libc = ctypes.CDLL(None)\n"
        "libc.getenv.restype = ctypes.c_char_p\n"
        "print(libc.getenv(b'ORT_DISABLE_TELEMETRY'))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], env=child_env(tmp_path), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "b'1'"


def test_fetching_onnx_runtime_is_a_warning(tmp_path, shared):
    """Without a runtime, the extractor (and convert with images) fetches one, as the CLI does,
    and says so: a RuntimeWarning, shown even when the fetch fails (here: the `python3` that
    would run pip is `false`)."""
    scene = shared / "scenes/south-building"
    code = f"""
import warnings, sfpmap
calls = (
    lambda: sfpmap.Extractor(),
    lambda: sfpmap.convert({str(scene / "sparse-map")!r}, images={str(scene / "images")!r},
                           out={str(tmp_path / "x.sfpm")!r}),
)
for call in calls:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            call()
            print("no error")
        except sfpmap.Error as e:
            print(type(e).__name__, e)
    for w in caught:
        print(w.category.__name__, w.message)
"""
    env = child_env(tmp_path, SFPMAP_PYTHON=shutil.which("false"))
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 4, lines
    fetching = re.compile(r"RuntimeWarning ONNX Runtime [0-9.]+ not found; fetching it once")
    assert lines[0].startswith("ExtractError ") and "pip download" in lines[0], lines
    assert fetching.match(lines[1]), lines
    assert lines[2].startswith("ConvertError ") and "pip download" in lines[2], lines
    assert fetching.match(lines[3]), lines
    assert not (tmp_path / "x.sfpm").exists()
