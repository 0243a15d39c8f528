"""Issue 31's other inputs from Python: a kapture folder (`convert(kapture=DIR)`, as
`sfpmap convert --kapture`), a COLMAP database of typed float descriptors (COLMAP 4's ALIKED,
written with pycolmap 4.2.1) and the built-in ALIKED extractor (`model="aliked-n16"`); each
converted and localized from Python.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import sfpmap

from conftest import REPO, _need, copy_db, need_module

# The maupertuis sample's camera (cli/tests/cli/kapture.rs).
MAUPERTUIS_CAMERA = "SIMPLE_PINHOLE 1919 1079 1847.53 959.5 539.5"


def tree(folder: Path) -> dict:
    """Every file under `folder` with its bytes."""
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def kapture_check(*args: object) -> str:
    need_module("kapture")
    r = subprocess.run(
        [sys.executable, str(REPO / "tests/kapture_check.py"), *map(str, args)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, f"kapture_check.py {args}: {r.stderr}"
    return r.stdout


def rotation_deg(q: np.ndarray, r: np.ndarray) -> float:
    """The angle between two unit quaternions (either sign), in degrees."""
    c = abs(float(np.dot(q / np.linalg.norm(q), r / np.linalg.norm(r))))
    return float(np.degrees(2 * np.arccos(min(1.0, c))))


@pytest.fixture(scope="module")
def maupertuis(shared, tmp_path_factory) -> dict:
    """The maupertuis sample (model, a database copy) and its kapture folder as NAVER's PyPI
    `kapture` (1.1.12) imports it from COLMAP, as cli/tests/cli/kapture.rs makes it."""
    sample = _need(shared / "colmap/kapture_maupertuis", "the kapture_maupertuis sample")
    tmp = tmp_path_factory.mktemp("kapture")
    # SQLite may write beside a database it opens: a copy.
    db = tmp / "colmap.db"
    shutil.copyfile(sample / "colmap.db", db)
    kapture = tmp / "kapture"
    kapture_check("import", sample / "reconstruction", db, sample / "images", kapture)
    return {"model": sample / "reconstruction", "db": db, "kapture": kapture, "tmp": tmp}


def test_kapture_converts_as_the_cli_and_its_queries_localize_at_the_ground_truth(cli, maupertuis, tmp_path):
    kapture, db = maupertuis["kapture"], maupertuis["db"]
    before = tree(kapture)
    out = tmp_path / "k.sfpm"
    k = sfpmap.convert(kapture=kapture, out=out)
    # The CLI's summary of the same folder, and the COLMAP source's: the same map.
    cli_out = tmp_path / "cli.sfpm"
    r = subprocess.run(
        [str(cli), "convert", "--kapture", str(kapture), "-o", str(cli_out), "--json"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    c = json.loads(r.stdout)
    colmap = sfpmap.convert(maupertuis["model"], database=db, out=tmp_path / "c.sfpm")
    assert set(k) == set(c)
    for key in ["points", "images", "observations", "vlad", "input_bytes", "output_bytes", "geometry_only"]:
        assert k[key] == c[key], key
    for key in ["points", "images", "observations", "vlad"]:
        assert k[key] == colmap[key], key
    assert len(k["levels"]) == 3 and not k["geometry_only"]
    for a, b in zip(k["levels"], colmap["levels"]):
        for key in ["level", "points", "dim_full", "dim_short", "scale_range"]:
            assert a[key] == b[key], key
    assert out.read_bytes() == cli_out.read_bytes()
    assert tree(kapture) == before, "convert(kapture=...) wrote into its input"

    # Its 4 images as queries, their features from the database (as the CLI test localizes
    # them): within a millimetre-scale of the poses kapture's importer wrote.
    truth = json.loads(kapture_check("read", kapture))["images"]
    assert len(truth) == 4
    features = sfpmap.QueryDatabase(db)
    with sfpmap.Map(out) as m:
        assert m.n_points == k["points"]
        loc = sfpmap.Localizer(m)
        for name in ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]:
            f = features.features(name)
            assert f is not None, name
            got = loc.localize(f, MAUPERTUIS_CAMERA, name=name)
            assert got.success, name
            pose, want = np.array(got.colmap), np.array(truth[name][1:], dtype=float)
            assert np.max(np.abs(pose[:4] - want[:4])) <= 1e-3, (name, pose, want)
            assert np.max(np.abs(pose[4:] - want[4:])) <= 1e-2, (name, pose, want)


@pytest.mark.parametrize(
    "options, words",
    [
        # Both or neither of the folders: the CLI parser's words.
        ({"model_dir": "MODEL"}, "the argument '--colmap <COLMAP>' cannot be used with '--kapture <DIR>'"),
        ({"kapture": None}, "the following required arguments were not provided: --colmap <COLMAP>"),
        ({"database": "DB"}, "the argument '--kapture <DIR>' cannot be used with '--database <DATABASE>'"),
        ({"images": "IMAGES"}, "--images builds from a COLMAP model: pass --colmap, not --kapture"),
        ({"features": "F.h5"}, "--kapture holds its own features: drop --features"),
    ],
)
def test_kapture_conflicts_are_the_cli_s_words(maupertuis, tmp_path, options, words):
    kwargs = {"kapture": maupertuis["kapture"], "out": tmp_path / "x.sfpm", **options}
    with pytest.raises(sfpmap.InputError) as e:
        sfpmap.convert(**kwargs)
    assert str(e.value) == words
    assert not (tmp_path / "x.sfpm").exists()


def test_kapture_types_need_kapture_and_the_output_stays_out_of_the_folder(maupertuis, tmp_path):
    kapture = maupertuis["kapture"]
    with pytest.raises(sfpmap.InputError, match="keypoints_type and descriptors_type need kapture"):
        sfpmap.convert(maupertuis["model"], keypoints_type="sift", out=tmp_path / "x.sfpm")
    # As the CLI: nothing is written inside the kapture folder, a new file or one already
    # there (one its tables do not list too), with or without force.
    stray = kapture / "reconstruction" / "stray.sfpm"
    stray.write_bytes(b"not a map")
    before = tree(kapture)
    table = kapture / "reconstruction" / "points3d.txt"
    for out in (kapture / "new.sfpm", stray, table):
        for force in (False, True):
            with pytest.raises(sfpmap.Error) as e:
                sfpmap.convert(kapture=kapture, out=out, force=force)
            assert str(e.value) == (
                f"{out}: lies inside the input folder {kapture}; write it outside that folder")
    assert tree(kapture) == before
    stray.unlink()
    # An existing output without force is refused as the CLI refuses it; with force, written.
    out = tmp_path / "m.sfpm"
    out.write_bytes(b"x")
    with pytest.raises(sfpmap.Error, match="exists; pass --force to overwrite"):
        sfpmap.convert(kapture=kapture, out=out)
    assert out.read_bytes() == b"x"
    s = sfpmap.convert(kapture=kapture, out=out, force=True, feature_name="my-sift")
    with sfpmap.Map(out) as m:
        assert m.n_points == s["points"]
        assert {lv["descriptor"] for lv in m.metadata["levels"]} == {"my-sift"}


def typed_database(src: Path, dst: Path) -> None:
    """`src`'s cameras, images and keypoints (x, y only: no scale) in a new database `dst`,
    each image's SIFT descriptors as COLMAP 4's typed ALIKED (N16ROT) float32 rows (unit
    length), as pycolmap 4.2.1 writes them (tests/api/convert_features.rs)."""
    pycolmap = need_module("pycolmap")
    tmp = dst.with_suffix(".src.db")
    shutil.copyfile(src, tmp)
    old = pycolmap.Database.open(str(tmp))
    new = pycolmap.Database.open(str(dst))
    # The same camera and image ids: the model's images are the database's by id.
    for cam in old.read_all_cameras():
        camera = pycolmap.Camera(model=cam.model, width=cam.width, height=cam.height, params=cam.params)
        camera.camera_id = cam.camera_id
        assert new.write_camera(camera, use_camera_id=True) == cam.camera_id
    for image in old.read_all_images():
        copy = pycolmap.Image(name=image.name, camera_id=image.camera_id)
        copy.image_id = image.image_id
        iid = new.write_image(copy, use_image_id=True)
        assert iid == image.image_id
        xy = np.ascontiguousarray(old.read_keypoints(image.image_id)[:, :2], dtype=np.float32)
        d = np.asarray(old.read_descriptors(image.image_id).data, dtype=np.float32)
        d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-6)
        new.write_keypoints(iid, xy)
        new.write_descriptors(
            iid,
            pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.ALIKED_N16ROT, d).to_bytes(),
        )
    new.close()
    old.close()
    tmp.unlink()


def test_a_database_of_aliked_descriptors_converts_and_localizes(shared, work, tmp_path):
    scene = shared / "scenes/sacre-coeur"
    db, qdb = tmp_path / "aliked.db", tmp_path / "aliked-queries.db"
    typed_database(scene / "database.db", db)
    typed_database(scene / "queries.db", qdb)
    out = tmp_path / "aliked.sfpm"
    s = sfpmap.convert(scene / "sparse-map", database=db, out=out)
    assert s["points"] > 0
    assert len(s["levels"]) == 1 and s["levels"][0]["dim_full"] == 128
    truth = {}
    for line in (scene / "gt_poses.txt").read_text().splitlines():
        name, *pose = line.split()
        truth[name] = np.array([float(v) for v in pose])
    queries = sfpmap.read_queries(scene / "queries.txt")
    typed, sift = sfpmap.QueryDatabase(qdb), sfpmap.QueryDatabase(copy_db(scene / "queries.db", work))
    with sfpmap.Map(out) as m:
        levels = m.metadata["levels"]
        assert len(levels) == 1
        assert levels[0]["descriptor"] == "aliked-n16rot"
        assert levels[0]["feature_source"] == "colmap database"
        loc = sfpmap.Localizer(m)
        localized = 0
        for name, camera in queries:
            f = typed.features(name)
            assert f is not None and f.model == "aliked-n16rot", name
            r = loc.localize(f, camera, name=name)
            # The same features as arrays (which record no model): the same pose.
            a = loc.localize((f.keypoints(), f.descriptors()), camera)
            assert a.colmap == r.colmap, name
            if r.success:
                localized += 1
                pose = np.array(r.colmap)
                # Measured: 0.08 and 0.03 degrees, 8 and 3 mm (in the scene's units).
                assert rotation_deg(pose[:4], truth[name][:4]) < 0.5, (name, pose, truth[name])
                assert np.linalg.norm(pose[4:] - truth[name][4:]) < 0.05, (name, pose, truth[name])
            # A query of another feature (the scene's SIFT database) is refused, naming both.
            other = sift.features(name)
            assert other is not None and other.model == "sift"
            with pytest.raises(sfpmap.LocalizeError) as e:
                loc.localize(other, camera, name=name)
            message = str(e.value)
            assert 'features of model "sift"' in message, message
            assert '"aliked-n16rot" descriptors' in message, message
        assert localized == len(queries) == 2


def test_a_built_in_aliked_map_localizes_its_queries(shared, tmp_path):
    scene = shared / "scenes/sacre-coeur"
    out = tmp_path / "aliked-n16.sfpm"
    s = sfpmap.convert(scene / "sparse-map", images=scene / "images", out=out, model="aliked-n16")
    assert s["points"] > 0
    truth = {}
    for line in (scene / "gt_poses.txt").read_text().splitlines():
        name, *pose = line.split()
        truth[name] = np.array([float(v) for v in pose])
    queries = sfpmap.read_queries(scene / "queries.txt")
    extractor = sfpmap.Extractor("aliked-n16")
    assert extractor.descriptor == "aliked-n16"
    with sfpmap.Map(out) as m:
        assert [lv["descriptor"] for lv in m.metadata["levels"]] == ["aliked-n16"]
        info = m.info()
        assert [lv["descriptor"] for lv in info["levels"]] == ["aliked-n16"]
        assert info["provenance"]["parameters"]["contract"]["sfp.model_name"] == "aliked-n16"
        loc = sfpmap.Localizer(m)
        results = {}
        for name, camera in queries:
            f = extractor.extract(scene / "images" / name)
            assert f.model == "aliked-n16"
            results[name] = loc.localize(f, camera, name=name)
        assert len(results) == 2
        for name, r in results.items():
            assert r.success, name
            pose = np.array(r.colmap)
            # Measured: 0.41 and 0.40 degrees, 27 and 10 mm (in the scene's units).
            assert rotation_deg(pose[:4], truth[name][:4]) < 2.0, (name, pose, truth[name])
            assert np.linalg.norm(pose[4:] - truth[name][4:]) < 0.1, (name, pose, truth[name])
