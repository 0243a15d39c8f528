"""Rerun recordings (`sfpmap.viz`, `sfpmap export --rerun`), read back with rerun-sdk: the
entities the module doc lists, with the counts the map and the queries give; and the inlier
links and covariance a localization keeps."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sfpmap
import sfpmap.viz
from conftest import cli_poses, copy_db, need_module, run_cli


def read_back(path: Path) -> dict:
    """{entity path: [(rows, timelines, {column: values per row})]} of a recording."""
    rr = need_module("rerun")
    store = rr.chunk.RrdReader(str(path)).stream().collect()
    out: dict = {}
    for chunk in store.stream():
        batch = chunk.to_record_batch()
        columns = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        out.setdefault(chunk.entity_path, []).append((chunk.num_rows, chunk.timeline_names, columns))
    return out


def column(entities: dict, entity: str, name: str) -> list:
    """Every row's value of column `name` of `entity`, over its chunks."""
    rows = []
    for _, _, columns in entities.get(entity, []):
        rows.extend(columns.get(name, []))
    return rows


@pytest.fixture(scope="module")
def scene(cli, shared, sacre_sift, tmp_path_factory):
    """Sacre Coeur: the SIFT map, its localized queries, the ground truth, a TUM trajectory of
    the truth, and one query localized with its inliers kept."""
    work = tmp_path_factory.mktemp("viz")
    s = shared / "scenes/sacre-coeur"
    db = copy_db(s / "queries.db", work)
    poses = work / "poses.txt"
    run_cli(cli, "localize", "--map", sacre_sift, "--query-list", s / "queries.txt", "--database", db, "-o", poses)
    gt = dict(sfpmap.read_poses(str(s / "gt_poses.txt")))
    tum = work / "truth.tum"
    with open(tum, "w") as f:
        for i, (name, p) in enumerate(sorted(gt.items())):
            r, c = sfpmap.viz.world_from_cam(p)
            q = _quaternion_xyzw(r)
            f.write(f"{i * 0.1:.1f} {c[0]} {c[1]} {c[2]} {q[0]} {q[1]} {q[2]} {q[3]}\n")
    queries = sfpmap.read_queries(str(s / "queries.txt"))
    name, camera = queries[0]
    with sfpmap.Map(str(sacre_sift)) as m:
        found = sfpmap.Localizer(m, keep_inliers=True).localize(
            sfpmap.QueryDatabase(str(db)).features(name), camera, name=name
        )
    return {"map": sacre_sift, "scene": s, "db": db, "poses": poses, "gt": gt, "tum": tum,
            "name": name, "camera": camera, "found": found, "work": work}


def _quaternion_xyzw(r: np.ndarray) -> list:
    w = np.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = np.copysign(np.sqrt(max(0.0, 1 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = np.copysign(np.sqrt(max(0.0, 1 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    return [x, y, z, w]


def test_inlier_links_are_the_final_inliers_and_reproject_under_the_pose(scene):
    found, camera = scene["found"], scene["camera"]
    assert found.success
    pixels, points, levels = found.inlier_pixels, found.inlier_points, found.inlier_levels
    assert pixels.shape == (found.inliers, 2) and points.shape == (found.inliers, 3)
    assert levels.shape == (found.inliers,)
    with sfpmap.Map(str(scene["map"])) as m:
        assert set(levels.tolist()) <= set(m.level_ids)
        for level, n in found.inliers_per_level.items():
            assert int((levels == level).sum()) == n
    # Each point projects within the final RANSAC threshold (6 px) of its keypoint: the
    # camera's focal length and principal point, through cam_from_world.
    r, c = sfpmap.viz.world_from_cam(found.colmap)
    cam = (points - c) @ r  # world -> camera: R_cw (p - c), R_cw = r.T
    k, _ = sfpmap.viz._intrinsics(camera)
    projected = (cam @ k.T)[:, :2] / cam[:, 2:3]
    error = np.linalg.norm(projected - pixels, axis=1)
    # Radial distortion left out of the pinhole: a few pixels at the image's edge.
    assert np.median(error) < 6.0, np.median(error)
    # Without keep_inliers, none are kept.
    with sfpmap.Map(str(scene["map"])) as m:
        plain = sfpmap.Localizer(m).localize(
            sfpmap.QueryDatabase(str(scene["db"])).features(scene["name"]), camera
        )
    assert plain.inlier_pixels.shape == (0, 2) and plain.inlier_points.shape == (0, 3)


def test_the_covariance_is_symmetric_with_positive_variances(scene):
    cov = scene["found"].covariance
    assert cov.shape == (6, 6)
    assert np.array_equal(cov, cov.T)
    assert (np.diag(cov) > 0).all()
    # Positive definite: a covariance, not just a symmetric matrix.
    assert np.linalg.eigvalsh(cov).min() > 0


def test_a_recording_holds_the_map_the_queries_their_inliers_and_a_trajectory(scene):
    out = scene["work"] / "sacre.rrd"
    s = scene["scene"]
    r = subprocess.run(
        [sys.executable, "-m", "sfpmap.viz", str(scene["map"]), "-o", str(out),
         "--poses", str(scene["poses"]), "--gt", str(s / "gt_poses.txt"),
         "--trajectory", str(scene["tum"]), "--inliers", scene["name"],
         "--query-list", str(s / "queries.txt"), "--database", str(scene["db"]), "--json"],
        capture_output=True, text=True,
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    entities = read_back(out)
    with sfpmap.Map(str(scene["map"])) as m:
        for level in m.levels:
            positions = column(entities, f"/world/map/level_{level.id}", "Points3D:positions")
            assert len(positions) == 1 and len(positions[0]) == len(level.points)
            assert summary["points_per_level"][str(level.id)] == len(level.points)
        n_images = m.n_images
        image_poses, image_cameras, map_cameras = m.images.poses, m.images.cameras, m.cameras
    cameras = [e for e in entities if e.startswith("/world/map/cameras/")]
    assert len(cameras) == n_images == summary["cameras"]
    # Each frustum is its image's: the camera centre, and the focal lengths and principal
    # point of its camera (a 3x3 stored column-major).
    for i in (0, n_images - 1):
        rotation, centre = sfpmap.viz.world_from_cam(image_poses[i])
        translation = column(entities, f"/world/map/cameras/{i}", "Transform3D:translation")
        assert np.allclose(translation[0], centre, atol=1e-5)
        cam = map_cameras[int(image_cameras[i])]
        fx, fy, cx, cy = sfpmap.pinhole_intrinsics(cam["model"], cam["params"])
        k = np.array(column(entities, f"/world/map/cameras/{i}", "Pinhole:image_from_camera")[0]).reshape(3, 3).T
        assert np.allclose(k, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], rtol=1e-6), k
    estimated = dict(sfpmap.read_poses(str(scene["poses"])))
    assert summary["estimates"] == len(estimated) >= 1
    # The error lines join each estimated centre to its true one.
    errors = column(entities, "/world/errors", "LineStrips3D:strips")
    both = sorted(set(estimated) & set(scene["gt"]))
    assert len(errors) == 1 and len(errors[0]) == len(both) == summary["errors"]
    expected = {(tuple(np.round(sfpmap.viz.world_from_cam(estimated[n])[1], 3)),
                 tuple(np.round(sfpmap.viz.world_from_cam(scene["gt"][n])[1], 3))) for n in both}
    drawn = {(tuple(np.round(a, 3)), tuple(np.round(b, 3))) for a, b in errors[0]}
    assert drawn == expected
    name = sfpmap.viz._entity_part(scene["name"])
    inlier_points = column(entities, f"/world/queries/{name}/inliers/points", "Points3D:positions")
    assert len(inlier_points[0]) == scene["found"].inliers == summary["inliers"]
    keypoints = column(entities, f"/world/queries/{name}/estimate/keypoints", "Points2D:positions")
    assert len(keypoints[0]) == scene["found"].inliers
    links = column(entities, f"/world/queries/{name}/inliers/links", "LineStrips3D:strips")
    assert len(links[0]) == scene["found"].inliers
    # Each query's frusta have its own camera from --query-list.
    queries = dict(sfpmap.read_queries(str(s / "queries.txt")))
    for n in both[:3]:
        fx, fy, cx, cy = sfpmap.pinhole_intrinsics(queries[n].model, queries[n].params)
        for kind in ("estimate", "truth"):
            k = column(entities, f"/world/queries/{sfpmap.viz._entity_part(n)}/{kind}", "Pinhole:image_from_camera")
            assert np.allclose(np.array(k[0]).reshape(3, 3).T, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), (n, kind)
    # The trajectory: one pose per frame on the `frame` timeline, and its whole path.
    frames = sum(n for n, timelines, _ in entities["/world/trajectory/camera"] if "frame" in timelines)
    assert frames == len(scene["gt"]) == summary["trajectory"]
    path = column(entities, "/world/trajectory/path", "LineStrips3D:strips")
    assert len(path[0][0]) == len(scene["gt"])


def test_the_cli_exports_the_same_recording_and_refuses_to_overwrite(cli, scene):
    out = scene["work"] / "cli.rrd"
    env = {**os.environ, "SFPMAP_PYTHON": sys.executable}
    def export(*extra):
        return subprocess.run([str(cli), "export", str(scene["map"]), "--rerun", str(out), *extra],
                              capture_output=True, text=True, env=env)
    r = export("--json")
    assert r.returncode == 0, r.stderr
    entities = read_back(out)
    with sfpmap.Map(str(scene["map"])) as m:
        for level in m.levels:
            assert len(column(entities, f"/world/map/level_{level.id}", "Points3D:positions")[0]) == len(level.points)
    # --max-points thins each level to every n-th point.
    thinned = scene["work"] / "thinned.rrd"
    r = subprocess.run([str(cli), "export", str(scene["map"]), "--rerun", str(thinned), "--max-points", "50"],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    entities = read_back(thinned)
    with sfpmap.Map(str(scene["map"])) as m:
        for level in m.levels:
            drawn = column(entities, f"/world/map/level_{level.id}", "Points3D:positions")[0]
            assert 0 < len(drawn) <= 50 and len(level.points) > 50, level.id
    before = out.stat().st_mtime_ns
    r = export()
    assert r.returncode != 0 and "exists" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert out.stat().st_mtime_ns == before
    # The map is never the output.
    r = subprocess.run([str(cli), "export", str(scene["map"]), "--rerun", str(scene["map"]), "--force"],
                       capture_output=True, text=True, env=env)
    assert r.returncode != 0, r.stderr
    assert not list(scene["work"].glob(".sfpmap-viz-*")), "a temp file was left"


def test_a_python_without_the_package_is_refused_before_any_output(cli, scene, tmp_path):
    ply, rrd = tmp_path / "m.ply", tmp_path / "m.rrd"
    env = {**os.environ, "SFPMAP_PYTHON": "/bin/false"}
    r = subprocess.run([str(cli), "export", str(scene["map"]), "--ply", str(ply), "--rerun", str(rrd)],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 1
    assert r.stderr.count("\n") == 1 and "pip install 'sfpmap[viz]'" in r.stderr, r.stderr
    assert not ply.exists() and not rrd.exists()


def test_record_refuses_its_inputs_and_an_existing_output_and_leaves_no_temp(scene, tmp_path):
    m = str(scene["map"])
    before = scene["map"].stat().st_mtime_ns
    with pytest.raises(sfpmap.InputError, match="is one of the inputs"):
        sfpmap.viz.record(m, m, force=True)
    assert scene["map"].stat().st_mtime_ns == before
    out = tmp_path / "x.rrd"
    out.write_bytes(b"kept")
    with pytest.raises(sfpmap.InputError, match="exists"):
        sfpmap.viz.record(m, str(out))
    assert out.read_bytes() == b"kept"
    # A bad ground-truth line fails the recording part-way: no output, no temp file.
    bad = tmp_path / "bad.txt"
    bad.write_text("q.jpg 0 0 0 0 1 2 3\n")
    fresh = tmp_path / "fresh.rrd"
    with pytest.raises(sfpmap.InputError, match="bad.txt:1: .*zero quaternion"):
        sfpmap.viz.record(m, str(fresh), gt=str(bad))
    assert not fresh.exists()
    assert not list(tmp_path.glob(".sfpmap-viz-*"))


def test_a_pose_line_that_is_not_one_is_named(scene, tmp_path):
    bad = tmp_path / "bad.txt"
    bad.write_text("# a comment\nq.jpg 1 0 0 0 1 2\n")
    with pytest.raises(sfpmap.InputError, match=r"bad.txt.*2.*expected `name qw qx qy qz tx ty tz`, found 7"):
        sfpmap.read_poses(str(bad))
    with pytest.raises(sfpmap.InputError, match="bad.txt"):
        sfpmap.viz.record(str(scene["map"]), str(tmp_path / "x.rrd"), poses=str(bad))
    assert not (tmp_path / "x.rrd").exists()


@pytest.mark.parametrize("text, focal, centre", [
    ("SIMPLE_PINHOLE 640 480 500 320 240", (500, 500), (320, 240)),
    ("SIMPLE_DIVISION 640 480 500 321 241 -0.1", (500, 500), (321, 241)),
    ("SIMPLE_FISHEYE 640 480 300 322 242", (300, 300), (322, 242)),
    ("OPENCV 640 480 510 520 323 243 0.1 0 0 0", (510, 520), (323, 243)),
    ("FULL_OPENCV 640 480 510 520 324 244 0 0 0 0 0 0 0 0", (510, 520), (324, 244)),
])
def test_frusta_read_each_model_s_own_focal_lengths_and_principal_point(text, focal, centre):
    model, w, h, *params = text.split()
    k, resolution = sfpmap.viz._intrinsics({"model": model, "width": w, "height": h, "params": [float(p) for p in params]})
    assert resolution == (640, 480)
    assert np.array_equal(k, [[focal[0], 0, centre[0]], [0, focal[1], centre[1]], [0, 0, 1]])


def test_trajectory_stamps_are_dates_when_unix_times(scene, tmp_path):
    rr = need_module("rerun")
    for t0, kind in ((0.0, "duration"), (1.7e9, "timestamp")):
        tum = tmp_path / f"t{kind}.tum"
        tum.write_text("".join(f"{t0 + i * 0.1} {i} 0 0 0 0 0 1\n" for i in range(3)))
        out = tmp_path / f"t{kind}.rrd"
        sfpmap.viz.record(str(scene["map"]), str(out), trajectory=str(tum), max_points=10)
        store = rr.chunk.RrdReader(str(out)).stream().collect()
        times = [c for c in store.stream() if c.entity_path == "/world/trajectory/camera" and "time" in c.timeline_names]
        assert sum(c.num_rows for c in times) == 3
        column_type = str(times[0].to_record_batch().schema.field("time").type)
        assert ("timestamp" in column_type) == (kind == "timestamp"), column_type


def test_database_frusta_are_spread_over_the_images_past_max_cameras(scene, tmp_path, monkeypatch):
    monkeypatch.setattr(sfpmap.viz, "MAX_CAMERAS", 7)
    out = tmp_path / "few.rrd"
    summary = sfpmap.viz.record(str(scene["map"]), str(out), max_points=10)
    with sfpmap.Map(str(scene["map"])) as m:
        n = m.n_images
    step = -(-n // 7)
    assert summary.cameras == len(range(0, n, step)) <= 7
    drawn = sorted(int(e.rsplit("/", 1)[1]) for e in read_back(out) if e.startswith("/world/map/cameras/"))
    assert drawn == list(range(0, n, step))
    assert all(v <= 10 for v in summary.points_per_level.values())


def test_tum_stamps_not_in_seconds_are_refused_naming_the_line(scene, tmp_path):
    tum = tmp_path / "ms.tum"
    tum.write_text("# t x y z qx qy qz qw\n1700000000123 0 0 0 0 0 0 1\n")
    with pytest.raises(sfpmap.InputError, match=r"ms.tum:2: stamp 1700000000123 is not in seconds"):
        sfpmap.viz.read_tum(str(tum))
    tum.write_text("0.5 0 0 0 0 0 0 0\n")
    with pytest.raises(sfpmap.InputError, match=r"ms.tum:1: quaternion of norm 0"):
        sfpmap.viz.read_tum(str(tum))
    # A good file: rotations of world_from_cam, centres as written.
    tum.write_text("0.1 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n")
    t, r, c = sfpmap.viz.read_tum(str(tum))
    assert t.tolist() == [0.1] and c.tolist() == [[1, 2, 3]]
    assert np.allclose(r[0], [[0, -1, 0], [1, 0, 0], [0, 0, 1]])


def test_query_cameras_come_by_name_or_one_for_all():
    text = "SIMPLE_PINHOLE 640 480 500 320 240"
    cam = sfpmap.Camera.parse(text)
    for given in (cam, text, {"model": "SIMPLE_PINHOLE", "width": 640, "height": 480, "params": [500, 320, 240]}):
        every, by_name = sfpmap.viz._query_cameras(given)
        assert every is not None and every.params == [500, 320, 240] and by_name == {}
    for given in ({"q.jpg": text}, [("q.jpg", cam)]):
        every, by_name = sfpmap.viz._query_cameras(given)
        assert every is None and list(by_name) == ["q.jpg"] and by_name["q.jpg"].width == 640
    with pytest.raises(sfpmap.InputError, match="query_cameras"):
        sfpmap.viz._query_cameras({"q.jpg": 3})
    with pytest.raises(sfpmap.InputError, match="not a rotation"):
        sfpmap.viz._rotations(np.array([[0.0, 0, 0, 0]]))


def test_an_equirectangular_camera_has_no_pinhole_and_a_bad_one_is_named():
    assert sfpmap.pinhole_intrinsics("EQUIRECTANGULAR", [640, 320]) is None
    assert sfpmap.viz._intrinsics({"model": "EQUIRECTANGULAR", "width": 640, "height": 320, "params": [640, 320]}) is None
    with pytest.raises(sfpmap.InputError, match="OPENCV: 8 parameters"):
        sfpmap.pinhole_intrinsics("OPENCV", [1, 2, 3])
    with pytest.raises(sfpmap.InputError, match="not a COLMAP model"):
        sfpmap.pinhole_intrinsics("NOPE", [1])
