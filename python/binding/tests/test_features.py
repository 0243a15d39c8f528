"""Maps from any local feature (issue 31) from Python: `convert(model, features=features.h5)`
on a real hloc-style scene, and localizing with that map from the same file's features.

The scene is benches/hloc_south_building.py's torch-free small variant (12 South Building map
images + the 3 queries among them: pycolmap DoG/RootSIFT features in hloc's `features.h5`
layout, NN-ratio matches, a pose-verified pycolmap triangulation), built once per session into
a temp folder (~15 s of CPU, ~25 s on a loaded machine).
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess

import numpy as np
import pytest
import sfpmap

from conftest import REPO, cli_poses, need_module, run_cli


# The feature's name, as the files below are named: hloc's `feats-<conf>.h5` with a conf of
# this test's (what the library makes of hloc's own `sift` conf is its business, not this
# test's).
NAME = "rootsift-dog"
FILE = f"feats-{NAME}.h5"


@pytest.fixture(scope="session")
def hloc(shared, tmp_path_factory) -> dict:
    """The bench's `build_small_scene`: paths (`features` for every image, `features_map` for
    the map images, both linked as `FILE`; `sfm`, `queries`) and the ground truth `gt`
    {name: qw qx qy qz tx ty tz}."""
    need_module("h5py")
    need_module("pycolmap")
    spec = importlib.util.spec_from_file_location("hloc_south_building", REPO / "benches/hloc_south_building.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    scene = shared / "scenes/south-building"
    r = bench.build_small_scene(tmp_path_factory.mktemp("hloc"), features="sift", scene=scene)
    for key, folder in (("features", "all"), ("features_map", "map")):
        link = r["work"] / "named" / folder / FILE
        link.parent.mkdir(parents=True)
        os.link(r[key], link)
        r[key] = link
    return r


@pytest.fixture(scope="session")
def hloc_map(hloc, tmp_path_factory):
    """The map of the scene's model and map images' features (`FILE`), made by Python."""
    out = tmp_path_factory.mktemp("hloc-map") / "hloc.sfpm"
    summary = sfpmap.convert(hloc["sfm"], features=hloc["features_map"], out=out)
    return out, summary


def copy_h5(src, dst, keep=None, mutate=None) -> None:
    """`src`'s image groups to `dst` (h5py): the datasets `keep` only (default all), then
    `mutate(name, {dataset: array})` may change them."""
    import h5py

    with h5py.File(src, "r") as f, h5py.File(dst, "w") as g:
        for name in f:
            data = {k: f[name][k][()] for k in f[name] if keep is None or k in keep}
            if mutate is not None:
                mutate(name, data)
            group = g.create_group(name)
            for k, v in data.items():
                group[k] = v


def arrays(features_h5, name: str):
    """hloc's `keypoints` (+0.5: COLMAP's pixel centres) and `descriptors` (D×N, transposed to
    N×D), read with h5py: what a caller with hloc's features hands `Localizer.localize`."""
    import h5py

    with h5py.File(features_h5, "r") as f:
        return f[name]["keypoints"][()].astype(np.float64) + 0.5, f[name]["descriptors"][()].T


def pose_error(a, b) -> tuple:
    """(camera centre distance, rotation angle in degrees) between two cam_from_world poses
    (qw qx qy qz tx ty tz)."""

    def rotation_and_centre(p):
        w, x, y, z, *t = np.asarray(p, float) / [*([np.linalg.norm(p[:4])] * 4), 1, 1, 1]
        r = np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ])
        return r, -r.T @ np.array(t)

    (ra, ca), (rb, cb) = rotation_and_centre(a), rotation_and_centre(b)
    cos = np.clip((np.trace(ra @ rb.T) - 1) / 2, -1.0, 1.0)
    return float(np.linalg.norm(ca - cb)), float(np.degrees(np.arccos(cos)))


def test_convert_features_names_the_map_by_the_file_as_the_cli_does(cli, hloc, hloc_map, tmp_path):
    out, summary = hloc_map
    assert summary["points"] > 0 and summary["images"] == 12
    assert summary["points_without_descriptors"] == summary["images_without_features"] == 0
    with sfpmap.Map(out) as m:
        levels = m.metadata["levels"]
        # hloc's DoG keypoints carry `scales`: the levels split by scale, every one named by
        # the file's conf, 128 dimensions.
        assert [lv["descriptor"] for lv in levels] == [NAME] * 3
        assert all(lv["dim_full"] == 128 and lv["feature_source"] == "hloc features.h5" for lv in levels)
        assert m.info()["provenance"]["parameters"]["feature"] == NAME
        assert m.images.global_descriptors is None
    # The CLI's map, byte for byte (the same paths given: provenance records them as given).
    cli_out = tmp_path / "cli.sfpm"
    run_cli(cli, "convert", "--colmap", hloc["sfm"], "--features", hloc["features_map"], "-o", cli_out)
    assert cli_out.read_bytes() == out.read_bytes()

    # `feature_name` names it instead.
    named = tmp_path / "named.sfpm"
    sfpmap.convert(hloc["sfm"], features=hloc["features_map"], feature_name="rootsift-hloc", out=named)
    with sfpmap.Map(named) as m:
        assert {lv["descriptor"] for lv in m.metadata["levels"]} == {"rootsift-hloc"}

    # Keypoints without scales (hloc's learned features): one level, named by the file.
    plain = tmp_path / "feats-dog-n2k.h5"
    copy_h5(hloc["features_map"], plain, keep={"keypoints", "descriptors", "image_size"})
    one = tmp_path / "one.sfpm"
    s = sfpmap.convert(hloc["sfm"], features=plain, out=one)
    assert [lv["level"] for lv in s["levels"]] == [0]
    with sfpmap.Map(one) as m:
        assert [(lv["level"], lv["descriptor"]) for lv in m.metadata["levels"]] == [(0, "dog-n2k")]
        assert len(m.levels[0]) == summary["points"]


def test_from_pycolmap_with_features_equals_convert(hloc, hloc_map, tmp_path):
    """The same map from the reconstruction in memory, provenance aside."""
    pycolmap = need_module("pycolmap")
    from test_build import without_provenance

    out = tmp_path / "mem.sfpm"
    rec = pycolmap.Reconstruction(hloc["sfm"])
    sfpmap.from_pycolmap(rec, features=hloc["features_map"], out=out)
    assert without_provenance(out) == without_provenance(hloc_map[0])


def test_global_features_are_stored_and_serve_retrieval(hloc, tmp_path):
    """`global_features=`: a `global-feats.h5` (here each image's mean RootSIFT, normalised:
    any global descriptor will do) stored per map image, shown by `info`; queries' own, read
    from the same file (`FeaturesFile.global_descriptor`, as `localize --global-features`),
    rank the map images."""
    import h5py

    g = tmp_path / "global-feats-mean.h5"
    with h5py.File(hloc["features"], "r") as f, h5py.File(g, "w") as out:
        for name in f:
            d = f[name]["descriptors"][()].astype(np.float32).mean(axis=1)
            out.create_group(name)["global_descriptor"] = d / np.linalg.norm(d)
    m_path = tmp_path / "global.sfpm"
    sfpmap.convert(hloc["sfm"], features=hloc["features_map"], global_features=g, out=m_path)
    with sfpmap.Map(m_path) as m:
        stored = m.images.global_descriptors
        assert stored is not None and stored.shape == (len(m.images), 128)
        info = m.info()
        assert info["retrieval"]["global_dims"] == 128, info["retrieval"]
        assert info["provenance"]["parameters"]["global_features"] == str(g)
        with h5py.File(g, "r") as f:
            want = np.stack([f[n]["global_descriptor"][()] for n in m.images.names])
        assert np.allclose(stored.astype(np.float32), want, atol=1e-3)

        globals_ = sfpmap.FeaturesFile(g)
        assert globals_.feature is None  # "global-feats-…" names no local feature
        assert globals_.global_descriptor("no-such.jpg") is None
        loc = sfpmap.Localizer(m, retrieval="global", top_k=4)
        for name, camera in sfpmap.read_queries(hloc["queries"]):
            gd = globals_.global_descriptor(name)
            assert gd.dtype == np.float32 and gd.shape == (128,)
            r = loc.localize(arrays(hloc["features"], name), camera, global_descriptor=gd, name=name)
            assert r.success, (name, r.failure)
            assert r.retrieval == "global" and len(r.retrieved) == 4, (name, r.retrieval, r.retrieved)
            assert pose_error(r.colmap, hloc["gt"][name])[0] < 0.05


@pytest.mark.parametrize(
    "options, words",
    [
        ({"database": "x.db"}, ["features", "database"]),
        ({"images": "images"}, ["images", "features"]),
        ({"images": "images", "features": None, "global_features": "g.h5"}, ["images", "global_features"]),
        ({"features": None, "feature_name": "x"}, ["feature_name", "features"]),
    ],
)
def test_convert_feature_conflicts_are_one_line_input_errors(hloc, tmp_path, options, words):
    kwargs = {"features": hloc["features_map"], **options}
    kwargs = {k: v for k, v in kwargs.items() if v is not None}
    with pytest.raises(sfpmap.InputError) as e:
        sfpmap.convert(hloc["sfm"], out=tmp_path / "x.sfpm", **kwargs)
    text = str(e.value)
    assert "\n" not in text and all(w in text for w in words), text
    assert not (tmp_path / "x.sfpm").exists()


def test_convert_features_conflict_is_the_cli_message(cli, hloc, tmp_path):
    with pytest.raises(sfpmap.InputError) as e:
        sfpmap.convert(hloc["sfm"], database="x.db", features=hloc["features_map"], out=tmp_path / "x.sfpm")
    r = subprocess.run(
        [str(cli), "convert", "--colmap", str(hloc["sfm"]), "--features", str(hloc["features_map"]),
         "--database", "x.db", "-o", str(tmp_path / "x.sfpm")],
        capture_output=True, text=True,
    )
    assert r.returncode != 0 and r.stderr.splitlines()[0] == f"error: {e.value}"


def test_a_malformed_features_file_is_a_convert_error_naming_file_image_and_dataset(cli, hloc, tmp_path):
    import h5py

    with h5py.File(hloc["features_map"], "r") as f:
        victim = sorted(f)[1]

    def nan(name, data):
        if name == victim:
            d = data["descriptors"].copy()
            d[7, 3] = np.nan
            data["descriptors"] = d

    def transposed(name, data):
        if name == victim:
            data["descriptors"] = data["descriptors"].T.copy()

    for label, mutate, message in (
        ("nan", nan, f"{victim}/descriptors: keypoint 3: a value is NaN"),
        ("transposed", transposed, f"{victim}/descriptors: "),
    ):
        h5 = tmp_path / f"feats-{label}.h5"
        copy_h5(hloc["features_map"], h5, mutate=mutate)
        before = h5.read_bytes()
        out = tmp_path / f"{label}.sfpm"
        with pytest.raises(sfpmap.ConvertError) as e:
            sfpmap.convert(hloc["sfm"], features=h5, out=out)
        text = str(e.value)
        assert "\n" not in text and text.startswith(f"{h5}: {message}"), text
        if label == "transposed":
            assert "hloc stores descriptors transposed" in text, text
        # The CLI's words, and nothing written or changed.
        r = subprocess.run(
            [str(cli), "convert", "--colmap", str(hloc["sfm"]), "--features", str(h5), "-o", str(out)],
            capture_output=True, text=True,
        )
        assert r.returncode != 0 and r.stderr.splitlines()[0] == f"error: {text}"
        assert not out.exists() and h5.read_bytes() == before


def test_localize_with_features_from_the_file_as_arrays_and_as_the_cli(cli, hloc, hloc_map, tmp_path):
    out, _ = hloc_map
    queries = sfpmap.read_queries(hloc["queries"])
    assert len(queries) == 3
    with sfpmap.Map(out) as m:
        loc = sfpmap.Localizer(m)
        file = sfpmap.FeaturesFile(hloc["features"])
        assert file.feature == NAME
        from_arrays, from_file = [], []
        for name, camera in queries:
            kp, desc = arrays(hloc["features"], name)
            assert desc.shape == (len(kp), 128)
            r = loc.localize((kp, desc), camera, name=name)
            assert r.success, (name, r.failure)
            centre, degrees = pose_error(r.colmap, hloc["gt"][name])
            assert centre < 0.05 and degrees < 1.0, (name, centre, degrees)
            from_arrays.append(r)
            # The file's features (the same rows, normalised, keypoints +0.5), which name
            # their feature: the map's, taken.
            f = file.features(name)
            assert f.model == NAME and np.array_equal(f.keypoints(), kp)
            r2 = loc.localize(f, camera, name=name)
            assert r2.success and pose_error(r2.colmap, r.colmap)[0] < 0.01
            from_file.append(r2)
        # A batch on Rust threads finds the same poses.
        many = loc.localize_many([(arrays(hloc["features"], n), c, n) for n, c in queries], threads=2)
        assert [r.colmap for r in many] == [r.colmap for r in from_arrays]
        # The CLI's `localize --features` on the same file: the file's poses, to the last bit.
        poses = cli_poses(cli, "--map", out, "--query-list", hloc["queries"], "--features", hloc["features"],
                          out=tmp_path / "cli.json")
        for (name, _), r in zip(queries, from_file):
            assert poses[name] is not None, name
            assert np.max(np.abs(np.array(r.colmap) - np.array(poses[name]))) <= 1e-9, name

        # A features file of another feature (hloc's name says "disk") is refused naming both,
        # as the CLI refuses it.
        disk = tmp_path / "feats-disk.h5"
        shutil.copyfile(hloc["features"], disk)
        name, camera = queries[0]
        f = sfpmap.FeaturesFile(disk).features(name)
        assert f.model == "disk"
        with pytest.raises(sfpmap.LocalizeError) as e:
            loc.localize(f, camera, name=name)
        refusal = (f'features of model "disk", but the map {out} holds "{NAME}" descriptors: '
                   f'give query features of "{NAME}"')
        assert str(e.value) == f'{out}: query "{name}": {refusal}'
        r = subprocess.run(
            [str(cli), "localize", "--map", str(out), "--query-list", str(hloc["queries"]), "--features", str(disk),
             "-o", str(tmp_path / "disk.txt")],
            capture_output=True, text=True,
        )
        assert r.returncode != 0 and r.stderr.splitlines()[0] == f"error: {disk}: {refusal}", r.stderr
