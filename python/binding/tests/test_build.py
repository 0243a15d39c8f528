"""convert, slice and from_pycolmap make the CLI's maps."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import sfpmap

from conftest import assert_releases_the_gil, need_module, run_cli


def without_provenance(path) -> tuple:
    """A map's content but its provenance: metadata (less provenance) and every section's
    decoded bytes, in table order."""
    with sfpmap.Map(path) as m:
        meta = dict(m.metadata)  # the map's own dict: a copy to change
        meta.pop("provenance")
        sections = [
            (s["kind"], s["level"], s["codec"], m.section(s["kind"], s["level"]).tobytes())
            for s in m.info()["sections"]
        ]
    return meta, sections


def test_convert_equals_the_cli(cli, shared, work, sacre_sift):
    scene = shared / "scenes/sacre-coeur"
    out = work / "py-sacre.sfpm"
    summary = sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=out)
    assert summary["points"] > 0 and summary["output"] == str(out)
    # Provenance records the paths as given, so the two maps are byte-identical when the
    # paths are: both were given the same ones.
    assert out.read_bytes() == sacre_sift.read_bytes()


def test_convert_geometry_only_and_options(shared, work):
    scene = shared / "scenes/sacre-coeur"
    out = work / "py-geom.sfpm"
    s = sfpmap.convert(scene / "sparse-map", out=out, codec="zstd")
    assert s["geometry_only"] and s["levels"] == []
    with pytest.raises(sfpmap.FileError, match="exists"):
        sfpmap.convert(scene / "sparse-map", out=out)
    sfpmap.convert(scene / "sparse-map", out=out, force=True)
    with pytest.raises(sfpmap.InputError):
        sfpmap.convert(scene / "sparse-map", out=out, force=True, codec="lzma")
    with pytest.raises(TypeError):
        sfpmap.convert(scene / "sparse-map", out=out, force=True, no_such_option=1)


def test_convert_errors_are_the_cli_messages(cli, tmp_path):
    missing = tmp_path / "no-model"
    with pytest.raises(sfpmap.Error) as e:
        sfpmap.convert(missing, out=tmp_path / "x.sfpm")
    r = subprocess.run([str(cli), "convert", "--colmap", str(missing), "-o", str(tmp_path / "x.sfpm")],
                       capture_output=True, text=True)
    assert r.stderr.strip() == f"error: {e.value}"


def test_slice_equals_the_cli(cli, sacre_sift, work):
    a, b = work / "py-slice.sfpm", work / "cli-slice.sfpm"
    s = sfpmap.slice(sacre_sift, levels=[2], short=True, out=a)
    run_cli(cli, "slice", sacre_sift, "--level", "2", "--short", "-o", b)
    assert a.read_bytes() == b.read_bytes()
    assert s["points_after"] <= s["points_before"]
    with sfpmap.Map(a) as m:
        assert m.levels.ids == [2] and m.levels[2].rest is None
    with pytest.raises(sfpmap.NoSuchLevelError):
        sfpmap.slice(sacre_sift, levels=[9], out=work / "never.sfpm")


@pytest.mark.parametrize(
    "flags, options",
    [
        (["--minimal"], {"minimal": True}),
        (["--short", "--pq", "8"], {"short": True, "pq": 8}),
        (["--short", "--short-dims", "16"], {"short": True, "short_dims": 16}),
    ],
)
def test_slice_options_equal_the_cli(cli, sacre_sift, work, flags, options):
    tag = "-".join(f.strip("-") for f in flags)
    a, b = work / f"py-slice-{tag}.sfpm", work / f"cli-slice-{tag}.sfpm"
    s = sfpmap.slice(sacre_sift, levels=[2], out=a, **options)
    run_cli(cli, "slice", sacre_sift, "--level", "2", *flags, "-o", b)
    assert a.read_bytes() == b.read_bytes()
    with sfpmap.Map(a) as m:
        if options.get("minimal"):
            assert m.points.positions is None and m.points.positions_q16.dtype == np.uint16
            assert s["position_max_error"] is not None
        elif options.get("short_dims"):
            # SIFT's level: 32 short dims of its PCA basis, cut to its leading 16.
            level = m.levels[2]
            assert (level.dim_short, level.dim_full, level.rest) == (16, 16, None)
            assert s["short_dims"][0]["dims_before"] == 32 and s["short_dims"][0]["dims"] == 16
            assert 0.5 < s["short_dims"][0]["energy_kept"] <= 1.0
        else:
            level = m.levels[2]
            assert level.pq_codes.shape == (len(level), 8)
            # SIFT's level basis is PCA: the balanced order is not the identity.
            assert sorted(level.pq_order.tolist()) == list(range(level.dim_short))
            assert level.pq_order.tolist() != list(range(level.dim_short))
            assert s["pq"][0]["subspaces"] == 8


def test_from_pycolmap_equals_convert(shared, work, sacre_sift):
    pycolmap = need_module("pycolmap")
    scene = shared / "scenes/sacre-coeur"
    rec = pycolmap.Reconstruction(str(scene / "sparse-map"))
    out = work / "pycolmap-sacre.sfpm"
    s = sfpmap.from_pycolmap(rec, database=scene / "database.db", out=out)
    assert s["points"] == len(rec.points3D)
    assert without_provenance(out) == without_provenance(sacre_sift)
    with sfpmap.Map(out) as m:
        assert m.metadata["provenance"]["parameters"]["colmap"] == "pycolmap.Reconstruction"


def test_from_pycolmap_south_building_geometry_and_sfp(cli, shared, work, south_sfp):
    pycolmap = need_module("pycolmap")
    scene = shared / "scenes/south-building"
    rec = pycolmap.Reconstruction(str(scene / "sparse-map"))
    geometry_cli = work / "south-geom-cli.sfpm"
    run_cli(cli, "convert", "--colmap", scene / "sparse-map", "-o", geometry_cli)
    geometry_py = work / "south-geom-py.sfpm"
    sfpmap.from_pycolmap(rec, out=geometry_py)
    assert without_provenance(geometry_py) == without_provenance(geometry_cli)
    sfp_py = work / "south-sfp-py.sfpm"
    sfpmap.from_pycolmap(rec, images=scene / "images", out=sfp_py)
    assert without_provenance(sfp_py) == without_provenance(south_sfp)


def test_from_pycolmap_garbage_raises(tmp_path):
    class Fake:
        cameras = {}
        images = {}
        points3D = {1: object()}

    # A point without `xyz`: Python's AttributeError, as a ConvertError caused by it, naming
    # the point.
    with pytest.raises(sfpmap.ConvertError, match="^pycolmap reconstruction: point3D 1: AttributeError") as e:
        sfpmap.from_pycolmap(Fake(), out=tmp_path / "x.sfpm")
    assert isinstance(e.value.__cause__, AttributeError)
    assert not (tmp_path / "x.sfpm").exists()
    with pytest.raises(sfpmap.ConvertError, match="^pycolmap reconstruction: AttributeError: .*cameras"):
        sfpmap.from_pycolmap(object(), out=tmp_path / "y.sfpm")

    class BadId:
        cameras = {}
        images = {}
        points3D = {"one": object()}

    # A point id that is no integer: Python's TypeError, as a ConvertError.
    with pytest.raises(sfpmap.ConvertError, match="^pycolmap reconstruction: point3D 'one': TypeError") as e:
        sfpmap.from_pycolmap(BadId(), out=tmp_path / "z.sfpm")
    assert isinstance(e.value.__cause__, TypeError)
    assert not list(tmp_path.iterdir())


def test_from_pycolmap_errors_name_the_camera_image_or_point(tmp_path):
    from types import SimpleNamespace as NS

    camera = NS(camera_id=1, model="SIMPLE_PINHOLE", width=640, height=480, params=[500.0, 320.0, 240.0])
    pose = NS(rotation=NS(quat=[0.0, 0.0, 0.0, 1.0]), translation=[0.0, 0.0, 0.0])

    def rec(cameras=None, images=None, points3D=None):
        return NS(cameras=cameras or {1: camera}, images=images or {}, points3D=points3D or {})

    cases = [
        # A camera without `width`: Python's error, the camera named.
        (rec(cameras={1: NS(camera_id=1, model="PINHOLE", height=1, params=[])}), AttributeError,
         "pycolmap reconstruction: camera 1: AttributeError"),
        (rec(cameras={3: NS(camera_id=3, model="NO_SUCH_MODEL")}), None,
         'pycolmap reconstruction: camera 3: unknown model "NO_SUCH_MODEL"'),
        # An image without `points2D`, one whose point has no `xy`.
        (rec(images={7: NS(image_id=7, cam_from_world=pose, name="a.jpg", camera_id=1)}), AttributeError,
         "pycolmap reconstruction: image 7: AttributeError"),
        (rec(images={8: NS(image_id=8, cam_from_world=pose, points2D=[NS(point3D_id=1)])}), AttributeError,
         "pycolmap reconstruction: image 8: AttributeError"),
        (rec(images={9: NS(image_id=9, cam_from_world=NS(rotation=NS(quat=[1.0]), translation=[0.0]))}), None,
         "pycolmap reconstruction: image 9: a pose of 1 + 1 values"),
        # A point whose error is no number.
        (rec(points3D={5: NS(xyz=[0.0, 0.0, 0.0], color=[1, 2, 3], track=NS(elements=[]), error="big")}),
         TypeError, "pycolmap reconstruction: point3D 5: TypeError"),
    ]
    for reconstruction, cause, message in cases:
        with pytest.raises(sfpmap.ConvertError) as e:
            sfpmap.from_pycolmap(reconstruction, out=tmp_path / "x.sfpm")
        assert str(e.value).startswith(message), (str(e.value), message)
        if cause is not None:
            assert isinstance(e.value.__cause__, cause)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(
    "flags, options",
    [
        (["--database", "x.db"], {"database": "x.db"}),
        (["--short-dims", "8"], {"short_dims": 8}),
        (["--aggregate", "mean"], {"aggregate": "mean"}),
        (["--strict"], {"strict": True}),
        (["--memory", "4GB"], {"memory": 4_000_000_000}),
    ],
)
def test_convert_refuses_what_the_cli_refuses(cli, tmp_path, flags, options):
    # --images conflicts with each: the same one-line message as the CLI's first line.
    with pytest.raises(sfpmap.InputError) as e:
        sfpmap.convert(tmp_path / "model", images=tmp_path / "images", out=tmp_path / "x.sfpm", **options)
    r = subprocess.run(
        [str(cli), "convert", "--colmap", str(tmp_path / "model"), "--images", str(tmp_path / "images"),
         *flags, "-o", str(tmp_path / "x.sfpm")],
        capture_output=True, text=True,
    )
    assert r.returncode != 0 and r.stderr.splitlines()[0] == f"error: {e.value}"


def test_a_memory_budget_is_the_clis(cli, shared, work, sacre_sift, tmp_path):
    scene = shared / "scenes/sacre-coeur"
    out = work / "py-sacre-memory.sfpm"
    # The same map whatever the budget; the report says how it was kept to.
    s = sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=out, memory=4_000_000_000)
    assert s["memory"]["budget"] == 4_000_000_000 and s["memory"]["passes"] == 1, s["memory"]
    r = subprocess.run(
        [str(cli), "convert", "--colmap", str(scene / "sparse-map"), "--database", str(scene / "database.db"),
         "--memory", "4GB", "--json", "-o", str(tmp_path / "cli.sfpm")],
        capture_output=True, text=True, check=True,
    )
    # The CLI's plan for the same model and budget.
    assert s["memory"] == json.loads(r.stdout)["memory"]
    (tmp_path / "cli.sfpm").unlink()
    assert without_provenance(out) == without_provenance(sacre_sift)
    # Too small: the CLI's one line, naming the model and the smallest that works.
    with pytest.raises(sfpmap.ConvertError) as e:
        sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=tmp_path / "x.sfpm", memory=1_000_000)
    r = subprocess.run(
        [str(cli), "convert", "--colmap", str(scene / "sparse-map"), "--database", str(scene / "database.db"),
         "--memory", "1MB", "-o", str(tmp_path / "x.sfpm")],
        capture_output=True, text=True,
    )
    assert r.returncode != 0 and r.stderr.strip() == f"error: {e.value}"
    assert "a memory budget of 1 MB is too small to convert it: it needs at least" in str(e.value)
    with pytest.raises(sfpmap.InputError, match="memory: -1 is not a number of bytes"):
        sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=tmp_path / "x.sfpm", memory=-1)
    assert not list(tmp_path.iterdir())


def test_threads_are_checked_and_capped_as_the_cli_does(shared, tmp_path):
    # As the CLI's parser: fewer than 1 thread is refused, with or without images.
    scene = shared / "scenes/sacre-coeur"
    for threads in (0, -1):
        with pytest.raises(sfpmap.InputError, match=f"threads {threads}: at least 1 thread"):
            sfpmap.convert(scene / "sparse-map", out=tmp_path / "x.sfpm", threads=threads)
        with pytest.raises(sfpmap.InputError, match=f"threads {threads}: at least 1 thread"):
            sfpmap.convert(scene / "sparse-map", images=tmp_path, out=tmp_path / "x.sfpm", threads=threads)
    assert not list(tmp_path.iterdir())


def test_slice_levels_are_required_and_checked(sacre_sift, work, tmp_path):
    with pytest.raises(TypeError):
        sfpmap.slice(sacre_sift, out=tmp_path / "x.sfpm")  # type: ignore[call-arg]
    for level in (-1, 70000):
        with pytest.raises(sfpmap.NoSuchLevelError, match=f"no level {level} in this map"):
            sfpmap.slice(sacre_sift, levels=[level], out=tmp_path / "x.sfpm")
    for options in ({"short_dims": 16}, {"short": True, "short_dims": 16, "pq": 4}, {"short": True, "short_dims": 0}):
        with pytest.raises(sfpmap.InputError, match="short_dims"):
            sfpmap.slice(sacre_sift, levels=[2], out=tmp_path / "x.sfpm", **options)
    assert not list(tmp_path.iterdir())


def test_convert_releases_the_gil(shared, tmp_path):
    # (slice and verify: test_map.py, on its large map)
    scene = shared / "scenes/sacre-coeur"
    assert_releases_the_gil(
        lambda i: sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=tmp_path / f"a-{i}.sfpm")
        and (tmp_path / f"a-{i}.sfpm").unlink()
    )


def test_an_image_index_is_built_as_the_cli_builds_it_and_probed(cli, shared, work):
    scene = shared / "scenes/sacre-coeur"
    out, by_cli = work / "py-sacre-index.sfpm", work / "cli-sacre-index.sfpm"
    s = sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=out, index_lists=3)
    assert s["image_index"]["lists"] == 3 and s["image_index"]["stored"], s
    run_cli(cli, "convert", "--colmap", scene / "sparse-map", "--database", scene / "database.db",
            "--index-lists", "3", "-o", by_cli)
    assert out.read_bytes() == by_cli.read_bytes()
    with pytest.raises(sfpmap.InputError, match="index_lists"):
        sfpmap.convert(scene / "sparse-map", database=scene / "database.db", out=work / "never.sfpm",
                       index_lists=10**6)
    queries = sfpmap.read_queries(scene / "queries.txt")
    features = sfpmap.QueryDatabase(scene / "queries.db")
    with sfpmap.Map(out) as m:
        retrieved = {}
        for probe in [None, 0, 3]:
            loc = sfpmap.Localizer(m, top_k=2, retrieval_probe=probe)
            for name, camera in queries:
                r = loc.localize(features.features(name), camera, name=name)
                assert r.success, (probe, name)
                retrieved.setdefault(probe, []).append(r.retrieved)
        # The option reaches the library (on 8 images every probe ranks them all; which images
        # a probe scores is the Rust tests' part).
        assert retrieved[3] == retrieved[0]
        with pytest.raises(sfpmap.InputError, match="retrieval_probe"):
            sfpmap.Localizer(m, retrieval_probe=-1)
