#!/usr/bin/env python3
"""Cross-checks sfpmap's COLMAP reading against pycolmap, an independent implementation.

For every model under DATA/colmap (the malformed ones aside): pycolmap reads the original;
sfpmap converts it (with its database, on a temp copy) and exports the map back as a COLMAP
text model; pycolmap reads that; cameras, images, poses, points, colours and tracks must agree
(positions within f32 precision, since maps store them as f32 relative to an f64 origin). Every
malformed model must be rejected by both, sfpmap without panicking. Databases must be left
byte-identical.

Usage: python3 tests/pycolmap_crosscheck.py target/release/sfpmap ../shared/data
"""

import hashlib
import json
import math
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pycolmap

passed = 0
failed = 0


def check(ok, what):
    global passed, failed
    if ok:
        passed += 1
    else:
        failed += 1
        print(f"FAIL {what}")


def run(sfpmap, *args):
    return subprocess.run([sfpmap, *map(str, args)], capture_output=True, text=True)


def cam_from_world(image):
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose
    x, y, z, w = (float(v) for v in pose.rotation.quat)  # Eigen order: x y z w
    return [w, x, y, z], [float(v) for v in pose.translation]


def same_rotation(a, b):
    # Text models store rounded, not quite unit, quaternions: compare directions.
    norm = math.sqrt(sum(p * p for p in a) * sum(q * q for q in b))
    return abs(sum(p * q for p, q in zip(a, b))) / norm > 1 - 1e-12


def close(a, b, rel=1e-12, abs_=1e-12):
    return all(math.isclose(x, y, rel_tol=rel, abs_tol=abs_) for x, y in zip(a, b))


def tracks_by_xy(rec):
    """point3D id -> sorted [(image_id, x, y)] via each track element's point2D."""
    out = {}
    for pid, p in rec.points3D.items():
        elems = []
        for e in p.track.elements:
            xy = rec.images[e.image_id].points2D[e.point2D_idx].xy
            elems.append((e.image_id, float(xy[0]), float(xy[1])))
        out[pid] = sorted(elems)
    return out


def compare(name, orig, exported):
    check(sorted(orig.cameras) == sorted(exported.cameras), f"{name}: camera ids")
    for cid, c in orig.cameras.items():
        e = exported.cameras[cid] if cid in exported.cameras else None
        ok = e is not None and e.model.name == c.model.name and (e.width, e.height) == (c.width, c.height)
        ok = ok and close(list(c.params), list(e.params), rel=1e-15, abs_=0)
        check(ok, f"{name}: camera {cid}")
    check(sorted(orig.images) == sorted(exported.images), f"{name}: image ids")
    for iid, im in orig.images.items():
        e = exported.images[iid] if iid in exported.images else None
        if e is None:
            continue
        q1, t1 = cam_from_world(im)
        q2, t2 = cam_from_world(e)
        ok = e.name == im.name and e.camera_id == im.camera_id
        ok = ok and same_rotation(q1, q2) and close(t1, t2, rel=1e-12, abs_=1e-12)
        check(ok, f"{name}: image {iid} ({im.name}) name/camera/pose")
        n_obs = sum(1 for p in im.points2D if p.has_point3D())
        check(len(e.points2D) == n_obs, f"{name}: image {iid} observations {len(e.points2D)} vs {n_obs}")
    check(sorted(orig.points3D) == sorted(exported.points3D), f"{name}: point3D ids")
    worst = 0.0
    bad_color = 0
    for pid, p in orig.points3D.items():
        e = exported.points3D[pid] if pid in exported.points3D else None
        if e is None:
            continue
        for a, b in zip(p.xyz, e.xyz):
            worst = max(worst, abs(a - b) / max(1.0, abs(a)))
        bad_color += int(list(p.color) != list(e.color))
    check(worst < 1e-6, f"{name}: positions within f32 precision (worst relative error {worst:.2e})")
    check(bad_color == 0, f"{name}: {bad_color} point colours differ")
    t1, t2 = tracks_by_xy(orig), tracks_by_xy(exported)
    bad_tracks = 0
    for pid, elems in t1.items():
        other = t2.get(pid, [])
        same = len(elems) == len(other) and all(
            a[0] == b[0] and abs(a[1] - b[1]) < 1e-3 and abs(a[2] - b[2]) < 1e-3 for a, b in zip(elems, other)
        )
        bad_tracks += int(not same)
    check(bad_tracks == 0, f"{name}: {bad_tracks} tracks differ")
    print(f"ok   {name}: {len(orig.cameras)} cameras, {len(orig.images)} images, "
          f"{len(orig.points3D)} points, worst position error {worst:.1e}")


def sha(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def main():
    sfpmap, data = sys.argv[1], Path(sys.argv[2])
    fixtures = sorted(p for p in (data / "colmap").iterdir() if p.is_dir() and p.name != "malformed")
    check(len(fixtures) >= 4, "at least 4 fixtures")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for fx in fixtures:
            model = sorted(p.parent for p in fx.rglob("cameras.*") if "dense" not in p.parts)[0]
            dbs = sorted(list(fx.rglob("database.db")) + list(fx.rglob("colmap.db")))
            orig = pycolmap.Reconstruction(str(model))
            out = tmp / f"{fx.name}.sfpm"
            args = ["convert", "--colmap", model, "-o", out, "--json"]
            if dbs:
                db = tmp / f"{fx.name}.db"
                shutil.copy(dbs[0], db)
                before = sha(db)
                args += ["--database", db]
            r = run(sfpmap, *args)
            check(r.returncode == 0, f"{fx.name}: convert: {r.stderr.strip()}")
            if r.returncode != 0:
                continue
            if dbs:
                check(sha(db) == before, f"{fx.name}: database copy modified")
                check(not Path(str(db) + "-wal").exists(), f"{fx.name}: -wal file created")
            r = run(sfpmap, "verify", out)
            check(r.returncode == 0, f"{fx.name}: verify: {r.stderr.strip()}")
            info = json.loads(run(sfpmap, "info", out, "--json").stdout)
            check(info["points"] == orig.num_points3D(), f"{fx.name}: info points {info['points']}")
            check(info["images"] == orig.num_reg_images(), f"{fx.name}: info images {info['images']}")
            check(info["cameras"] == len(orig.cameras), f"{fx.name}: info cameras")
            check((len(info["levels"]) == 3) == bool(dbs), f"{fx.name}: levels {len(info['levels'])}")
            exp = tmp / f"{fx.name}-export"
            r = run(sfpmap, "export-colmap", out, "-o", exp)
            check(r.returncode == 0, f"{fx.name}: export-colmap: {r.stderr.strip()}")
            compare(fx.name, orig, pycolmap.Reconstruction(str(exp)))

        for cams in sorted((data / "colmap" / "malformed").rglob("cameras.txt")):
            model = cams.parent
            rejected_by_pycolmap = False
            try:
                pycolmap.Reconstruction(str(model))
            except Exception:
                rejected_by_pycolmap = True
            r = run(sfpmap, "convert", "--colmap", model, "-o", tmp / "bad.sfpm")
            name = model.relative_to(data / "colmap" / "malformed")
            check(rejected_by_pycolmap, f"malformed {name}: pycolmap accepts it")
            check(r.returncode != 0, f"malformed {name}: sfpmap accepts it")
            check("panicked" not in r.stderr and r.stderr.count("\n") == 1, f"malformed {name}: {r.stderr!r}")
            check(not (tmp / "bad.sfpm").exists(), f"malformed {name}: output written")
        print("malformed models: all rejected by both" if failed == 0 else "")
    print(f"{passed} passed, {failed} failed")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
