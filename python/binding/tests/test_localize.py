"""Localizing from Python gives the CLI's poses (to 1e-9), on threads too."""

from __future__ import annotations

import json
import re

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
        assert_releases_the_gil(lambda _: loc.localize_many(batch, threads=1))


def test_features_prefer_the_level_s_own_set():
    # As the localizer picks: a level's own set first, else the one for every level.
    every = (np.zeros((2, 2)), np.ones((2, 4)))
    own = (np.ones((3, 2)), np.full((3, 4), 2.0))
    f = sfpmap.Features({None: every, 2: own})
    assert f.keypoints(2).shape == (3, 2)
    assert np.array_equal(f.descriptors(2), own[1].astype(np.float32))
    assert f.keypoints(1).shape == (2, 2) and f.keypoints().shape == (2, 2)
    with pytest.raises(sfpmap.InputError, match="no features for level 1"):
        sfpmap.Features({2: own}).keypoints(1)


def test_non_finite_features_are_refused(south_sfp, south_queries):
    # As the features.h5 and database readers refuse them: the level and the row named.
    scene, queries = south_queries
    camera = queries[0][1]
    keypoints, descriptors = np.zeros((4, 2)), np.ones((4, 8), np.float32)
    bad_keypoints = keypoints.copy()
    bad_keypoints[2, 1] = np.nan
    bad_descriptors = descriptors.copy()
    bad_descriptors[1, 5] = -np.inf
    with pytest.raises(sfpmap.InputError, match=re.escape("level 3: keypoints row 2: y is NaN")):
        sfpmap.Features({3: (bad_keypoints, descriptors)})
    with pytest.raises(sfpmap.InputError, match=re.escape("level 0: descriptors row 1: a value is -inf")):
        sfpmap.Features({0: (keypoints, bad_descriptors)})
    with pytest.raises(sfpmap.InputError, match=re.escape("global_descriptor: value 1 is NaN")):
        sfpmap.Features({0: (keypoints, descriptors)}, global_descriptor=[0.0, float("nan")])
    with sfpmap.Map(south_sfp) as m:
        loc = sfpmap.Localizer(m)
        with pytest.raises(sfpmap.InputError, match=re.escape("level None (every level): keypoints row 2: y is NaN")):
            loc.localize((bad_keypoints, descriptors), camera)
        with pytest.raises(sfpmap.InputError, match="descriptors row 1"):
            loc.localize({0: (keypoints, bad_descriptors)}, camera)
        with pytest.raises(sfpmap.InputError, match="global_descriptor: value 0 is inf"):
            loc.localize((keypoints, descriptors), camera, global_descriptor=[float("inf")])
        with pytest.raises(sfpmap.InputError, match="descriptors row 1"):
            loc.localize_many([((keypoints, bad_descriptors), camera)])


def test_localizer_options_are_checked(south_sfp):
    nan, inf = float("nan"), float("inf")
    refused = [
        ({"top_k": 0}, "top_k 0: 1 to 100000 images"),
        ({"top_k": -1}, "top_k -1: 1 to 100000 images"),
        ({"top_k": 100_001}, "top_k 100001: 1 to 100000 images"),
        ({"ratio": 0.0}, "ratio 0: a ratio in (0, 1]"),
        ({"ratio": 1.5}, "ratio 1.5: a ratio in (0, 1]"),
        ({"ratio": nan}, "ratio NaN: a ratio in (0, 1]"),
        ({"gate_ratio": -0.5}, "gate_ratio -0.5: a ratio in (0, 1]"),
        ({"min_similarity": nan}, "min_similarity NaN: a cosine similarity in [-1, 1]"),
        ({"min_similarity": 2.0}, "min_similarity 2: a cosine similarity in [-1, 1]"),
        ({"coarse_error_px": inf}, "coarse_error_px inf: a finite number of pixels > 0"),
        ({"gate_px": 0.0}, "gate_px 0: a finite number of pixels > 0"),
        ({"fine_error_px": nan}, "fine_error_px NaN: a finite number of pixels > 0"),
    ]
    with sfpmap.Map(south_sfp) as m:
        for options, message in refused:
            with pytest.raises(sfpmap.InputError) as e:
                sfpmap.Localizer(m, **options)
            assert str(e.value) == message, options
        # The bounds themselves are fine.
        sfpmap.Localizer(m, top_k=1, ratio=1.0, gate_ratio=1.0, min_similarity=-1.0)
        sfpmap.Localizer(m, top_k=100_000)


def test_damaged_image_names_are_an_error_not_an_empty_list(south_sfp, south_queries, south_features, tmp_path):
    # Retrieved images are named from the map's image sections, checked on first access: a
    # damaged names section is the map's error (here the localizer, which reads the image
    # sections as it starts, meets it first), never a result whose names are silently empty.
    scene, queries = south_queries
    name, camera = queries[0]
    with sfpmap.Map(south_sfp) as m:
        r = sfpmap.Localizer(m).localize(south_features[name], camera)
        assert r.retrieved and r.retrieved_names == [m.images.names[i] for i in r.retrieved]
        names = next(s for s in m.info()["sections"] if s["kind"] == "image_names")
    assert names["codec"] == "raw"
    data = bytearray(south_sfp.read_bytes())
    data[names["offset"] + 3] ^= 0x01
    bad = tmp_path / "bad-names.sfpm"
    bad.write_bytes(bytes(data))
    with sfpmap.Map(bad) as m:
        with pytest.raises(sfpmap.MapError, match=r"bad-names\.sfpm: section \d+ \(image_names\): checksum"):
            sfpmap.Localizer(m)


def test_min_inliers_is_checked_by_the_library(south_sfp):
    # The library's rule (LocalizeOptions::validate), in its words; a negative Python int too.
    with sfpmap.Map(south_sfp) as m:
        for value in (3, 0, -1, 1_000_001):
            with pytest.raises(sfpmap.InputError) as e:
                sfpmap.Localizer(m, min_inliers=value)
            assert str(e.value) == f"min_inliers {value}: 4 to 1000000 inliers"
        sfpmap.Localizer(m, min_inliers=4)
        sfpmap.Localizer(m, min_inliers=1_000_000)


def test_a_sequence_tracks_its_queries_in_order(south_sfp, south_queries, south_features):
    scene, queries = south_queries
    batch = [(south_features[n], c, n) for n, c in queries[:4]]
    with sfpmap.Map(south_sfp) as m:
        plain = sfpmap.Localizer(m)
        assert not plain.sequence and not plain.is_tracking
        alone = [plain.localize(f, c, name=n) for f, c, n in batch]
        assert all(r.success and r.path == "retrieval" and r.tracking_lost is None for r in alone)
        assert not plain.is_tracking
        plain.reset_tracking()  # nothing outside a sequence

        # A camera standing still: the first query has no prediction (retrieval), the next
        # are tracked around the pose predicted from the ones before.
        loc = sfpmap.Localizer(m, sequence=True)
        assert loc.sequence and not loc.is_tracking
        f, c, n = batch[0]
        still = [loc.localize(f, c, name=n) for _ in range(3)]
        assert [r.path for r in still] == ["retrieval", "tracking", "tracking"]
        assert all(r.success and r.tracking_lost is None for r in still)
        assert still[0].colmap == alone[0].colmap
        for r in still[1:]:
            assert np.allclose(r.cam_from_world, alone[0].cam_from_world, atol=1e-3)
        assert loc.is_tracking

        # Forgotten: the next query goes through retrieval again.
        loc.reset_tracking()
        assert not loc.is_tracking
        again = loc.localize(f, c, name=n)
        assert again.path == "retrieval" and again.colmap == alone[0].colmap

        # The scene's queries in order (every 5th photo): each after the first is tried
        # around its prediction, which holds or falls back to retrieval saying why.
        loc.reset_tracking()
        walk = [loc.localize(f, c, name=n) for f, c, n in batch]
        assert walk[0].path == "retrieval" and walk[0].tracking_lost is None
        assert all(r.success for r in walk)
        assert all(r.path == "tracking" or r.tracking_lost for r in walk[1:])
        for w, a in zip(walk, alone):
            assert np.allclose(w.cam_from_world, a.cam_from_world, atol=0.05)

        # localize_many runs a sequence on one thread, in order, whatever `threads` says.
        loc.reset_tracking()
        many = loc.localize_many(batch, threads=4)
        assert [(r.path, r.tracking_lost, r.colmap) for r in many] == [
            (r.path, r.tracking_lost, r.colmap) for r in walk
        ]
        loc.reset_tracking()
        many = loc.localize_many([batch[0]] * 3, threads=4)
        assert [r.path for r in many] == ["retrieval", "tracking", "tracking"]


def test_features_of_another_model_are_refused(cli, south_sfp, south_queries, south_features, work):
    scene, queries = south_queries
    name, camera = queries[0]
    ours = south_features[name]
    other = sfpmap.Extractor("sfp-v1").extract(scene / "images" / name)
    with sfpmap.Map(south_sfp) as m:
        descriptor = m.metadata["levels"][0]["descriptor"]
        assert ours.model == descriptor == "sfp-v3" and other.model == "sfp-v1"
        loc = sfpmap.Localizer(m)
        with pytest.raises(sfpmap.LocalizeError) as e:
            loc.localize(other, camera, name=name)
        message = str(e.value)
        assert f'query "{name}": features of model "sfp-v1"' in message, message
        assert f'the map {south_sfp} holds "sfp-v3" descriptors' in message, message
        with pytest.raises(sfpmap.LocalizeError, match='features of model "sfp-v1"'):
            loc.localize_many([(other, camera, name)])
        # A sequence refuses them too, and goes on.
        seq = sfpmap.Localizer(m, sequence=True)
        with pytest.raises(sfpmap.LocalizeError, match='features of model "sfp-v1"'):
            seq.localize(other, camera)
        assert seq.localize(ours, camera).success

        # Arrays record no model: they are taken as they are.
        arrays = {l: (ours.keypoints(l), ours.descriptors(l)) for l in ours.levels}
        as_arrays = sfpmap.Features(arrays, global_descriptor=ours.global_descriptor)
        assert as_arrays.model is None
        assert loc.localize(as_arrays, camera).colmap == loc.localize(ours, camera).colmap
        # The other model's features as arrays: no model to refuse, so they are matched (sfp-v1
        # and sfp-v3 share their dimensions; these localize, as v1's student's would).
        foreign = {l: (other.keypoints(l), other.descriptors(l)) for l in other.levels}
        assert loc.localize(foreign, camera).success

    # A features file that records its model (`sfpmap extract`'s) gives features that carry it.
    h5 = work / "queries-sfp-v1.h5"
    run_cli(cli, "extract", scene / "images" / name, "--model", "sfp-v1", "-o", h5, "--force")
    from_file = sfpmap.read_features_h5(h5).features(name)
    assert from_file is not None and from_file.model == "sfp-v1"
    with sfpmap.Map(south_sfp) as m:
        with pytest.raises(sfpmap.LocalizeError, match='features of model "sfp-v1"'):
            sfpmap.Localizer(m).localize(from_file, camera, name=name)
