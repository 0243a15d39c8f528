"""The extractor from Python: the CLI's features, arrays as images, hostile inputs."""

from __future__ import annotations

import numpy as np
import pytest
import sfpmap

from conftest import run_cli


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
    assert extractor.descriptor == "sfp-v1"
    assert from_cli.levels == mine.levels == [0, 1, 2, 3]
    for level in mine.levels:
        assert np.array_equal(from_cli.keypoints(level), mine.keypoints(level))
        assert np.allclose(from_cli.descriptors(level), mine.descriptors(level), atol=1e-3, rtol=0)
        assert mine.scores(level).shape == (mine.keypoints(level).shape[0],)
    assert mine.global_descriptor is not None and mine.global_descriptor.ndim == 1


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
