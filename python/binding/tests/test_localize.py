"""Localizing from Python gives the CLI's poses (to 1e-9), on threads too."""

from __future__ import annotations

import json

import numpy as np
import pytest
import sfpmap

from conftest import assert_releases_the_gil, cli_poses, copy_db, need_module, run_cli


def assert_same_poses(python: dict, cli: dict) -> None:
    assert python.keys() == cli.keys()
    for name in cli:
        if cli[name] is None:
            assert python[name] is None, name
        else:
            assert python[name] is not None, f"{name}: the CLI localized it, Python did not"
            assert np.max(np.abs(np.array(python[name]) - np.array(cli[name]))) <= 1e-9, name


def test_sacre_coeur_sift_queries_equal_the_cli(cli, shared, sacre_sift, work):
    scene = shared / "scenes/sacre-coeur"
    db = copy_db(scene / "queries.db", work)
    expected = cli_poses(
        cli, "--map", sacre_sift, "--query-list", scene / "queries.txt", "--database", db,
        out=work / "sacre-poses.json",
    )
    queries = sfpmap.read_queries(scene / "queries.txt")
    features = sfpmap.QueryDatabase(db)
    with sfpmap.Map(sacre_sift) as m:
        loc = sfpmap.Localizer(m)
        got = {}
        for name, camera in queries:
            r = loc.localize(features.features(name), camera)
            got[name] = r.colmap
        assert_same_poses(got, expected)
        assert any(v is not None for v in got.values())


@pytest.fixture(scope="session")
def south_queries(shared):
    scene = shared / "scenes/south-building"
    return scene, sfpmap.read_queries(scene / "queries.txt")


@pytest.fixture(scope="session")
def south_features(south_queries):
    scene, queries = south_queries
    extractor = sfpmap.Extractor()
    return {name: extractor.extract(scene / "images" / name) for name, _ in queries}


def test_south_building_every_query_equals_the_cli(cli, south_sfp, south_queries, south_features, work):
    scene, queries = south_queries
    expected = cli_poses(
        cli, "--map", south_sfp, "--query-list", scene / "queries.txt", "--images", scene / "images",
        out=work / "south-poses.json",
    )
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        got = {name: loc.localize(south_features[name], camera).colmap for name, camera in queries}
    assert_same_poses(got, expected)
    assert sum(v is not None for v in got.values()) == len(queries)


def test_localize_many_equals_localize(south_sfp, south_queries, south_features):
    scene, queries = south_queries
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        one = [loc.localize(south_features[n], c).colmap for n, c in queries]
        batch = [(south_features[n], c, n) for n, c in queries]
        for threads in (1, 2, 4, None):
            many = loc.localize_many(batch, threads=threads)
            assert [r.colmap for r in many] == one
        # Any iterable of tuples or lists.
        assert [r.colmap for r in loc.localize_many(iter(batch))] == one
        assert [r.colmap for r in loc.localize_many(list(q) for q in batch)] == one
        assert loc.localize_many([]) == []
        # Threads as the CLI's --threads: at least 1, capped at 4 per core with a warning.
        for threads in (0, -3):
            with pytest.raises(sfpmap.InputError, match=f"threads {threads}: at least 1 thread"):
                loc.localize_many(batch, threads=threads)
        with pytest.warns(RuntimeWarning, match=r"threads 100000: using \d+ \(4 per core, at most 256\)"):
            capped = loc.localize_many(batch[:2], threads=100_000)
        assert [r.colmap for r in capped] == one[:2]
        with pytest.raises(sfpmap.InputError, match="query 0"):
            loc.localize_many([batch[0][0]])


def test_features_h5_queries_equal_the_cli(cli, south_sfp, south_queries, work):
    scene, queries = south_queries
    names = [n for n, _ in queries][:5]
    h5 = work / "queries.h5"
    run_cli(cli, "extract", *[scene / "images" / n for n in names], "-o", h5, "--force")
    qlist = work / "queries5.txt"
    qlist.write_text("".join(l for l in (scene / "queries.txt").read_text().splitlines(True) if l.split()[0] in names))
    expected = cli_poses(cli, "--map", south_sfp, "--query-list", qlist, "--features", h5, out=work / "h5-poses.json")
    f = sfpmap.read_features_h5(h5)
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        results = {n: loc.localize(f.features(n), c, name=n) for n, c in sfpmap.read_queries(qlist)}
    assert_same_poses({n: r.colmap for n, r in results.items()}, expected)
    assert f.features("not-there.jpg") is None
    # Every field the CLI's JSON has, under its name (its "retrieved" lists names).
    cli_json = {q["name"]: q for q in json.loads((work / "h5-poses.json").read_text())}
    for name, r in results.items():
        q = cli_json[name]
        assert r.failure == q["failure"] and r.inliers == q["inliers"] and r.matches == q["matches"]
        assert r.retrieved_images == q["retrieved_images"] > 0
        assert r.tracking_lost == q["tracking_lost"] is None
        assert r.retrieved_names == q["retrieved"] and r.path == q["path"]
        assert r.retrieval == q["retrieval"] and r.retrieval_fallback == q["retrieval_fallback"]
        assert r.inliers_per_level == {int(l): n for l, n in q["inliers_per_level"]}


def test_result_fields_and_pycolmap(south_sfp, south_queries, south_features):
    pycolmap = need_module("pycolmap")
    scene, queries = south_queries
    name, camera = queries[0]
    with sfpmap.Map(south_sfp) as m:
        r = sfpmap.Localizer(m).localize(south_features[name], camera)
    assert r.success and r.failure is None
    T = r.cam_from_world
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.allclose(T[:3, 3], r.translation)
    w, x, y, z = r.quaternion
    assert abs(w * w + x * x + y * y + z * z - 1) < 1e-12
    rigid = r.to_pycolmap()
    assert isinstance(rigid, pycolmap.Rigid3d)
    assert np.allclose(rigid.matrix(), T[:3, :], atol=1e-12)
    assert sum(r.inliers_per_level.values()) == r.inliers
    assert r.times["total"] > 0 and r.path == "retrieval"
    assert r.retrieved_names and all(isinstance(n, str) for n in r.retrieved_names)
    # A pycolmap.Camera is a camera too.
    cam = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height, params=camera.params)
    with sfpmap.Map(south_sfp) as m:
        assert sfpmap.Localizer(m).localize(south_features[name], cam).colmap == r.colmap


def test_arrays_and_array_images(south_sfp, south_queries, south_features):
    scene, queries = south_queries
    name, camera = queries[0]
    f = south_features[name]
    levels = {l: (f.keypoints(l), f.descriptors(l)) for l in f.levels}
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        a = loc.localize(f, camera)
        b = loc.localize(levels, camera, global_descriptor=f.global_descriptor)
        assert a.colmap == b.colmap
        # A camera as a dict, or as pycolmap would give it.
        cam = {"model": camera.model, "width": camera.width, "height": camera.height, "params": camera.params}
        assert loc.localize(f, cam).colmap == a.colmap


def test_unusable_queries_raise(south_sfp, south_queries, south_features):
    scene, queries = south_queries
    name, camera = queries[0]
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        with pytest.raises(sfpmap.LocalizeError, match="dimensions"):
            loc.localize((np.zeros((10, 2)), np.ones((10, 7))), camera)
        with pytest.raises(sfpmap.InputError):
            loc.localize((np.zeros((10, 2)), np.ones((9, 7))), camera)
        with pytest.raises(sfpmap.InputError):
            loc.localize(south_features[name], "NOT_A_MODEL 1 2 3")
        with pytest.raises(sfpmap.InputError):
            loc.localize("garbage", camera)
        with pytest.raises(sfpmap.InputError):
            sfpmap.Localizer(m, retrieval="nope")
    with pytest.raises(sfpmap.NoSuchLevelError):
        with sfpmap.Map(south_sfp) as m:
            sfpmap.Localizer(m, levels=[9])


def test_localizer_outlives_a_closed_map(south_sfp, south_queries, south_features):
    scene, queries = south_queries
    name, camera = queries[0]
    m = sfpmap.Map(south_sfp)
    loc = sfpmap.Localizer(m)
    before = loc.localize(south_features[name], camera).colmap
    m.close()
    del m
    assert loc.localize(south_features[name], camera).colmap == before


def test_python_threads_share_a_localizer(south_sfp, south_queries, south_features):
    from concurrent.futures import ThreadPoolExecutor

    scene, queries = south_queries
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        one = [loc.localize(south_features[n], c).colmap for n, c in queries]
        with ThreadPoolExecutor(4) as pool:
            threaded = list(pool.map(lambda q: loc.localize(south_features[q[0]], q[1]).colmap, queries))
    assert threaded == one


def test_the_gil_is_released_while_localizing(south_sfp, south_queries, south_features):
    scene, queries = south_queries
    batch = [(south_features[n], c, n) for n, c in queries]
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        assert_releases_the_gil(lambda: loc.localize_many(batch, threads=1))
