#!/usr/bin/env python3
"""Reference localizer for the real scenes: pycolmap only, no sfpmap code.

Each 3D point of the map model gets the mean of its track's L2-normalised SIFT descriptors
(from the map database); each query's SIFT descriptors (from the queries database) are matched
to all points (mutual nearest neighbour + ratio 0.9, dot products in numpy), and the pose is
pycolmap.estimate_and_refine_absolute_pose (LO-RANSAC + refinement, 12 px). Writes
`name qw qx qy qz tx ty tz` lines like `sfpmap localize` and prints ms per query.

Usage: reference_localize.py SCENE_DIR MAP_DB QUERIES_DB OUT_POSES
"""

import sqlite3
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap


def blobs(db, table, image_id):
    row = db.execute(f"SELECT rows, cols, data FROM {table} WHERE image_id = ?", (image_id,)).fetchone()
    if row is None or row[0] == 0:
        return None
    rows, cols, data = row
    dtype = np.float32 if table == "keypoints" else np.uint8
    return np.frombuffer(data, dtype=dtype).reshape(rows, cols)


def normalise(d):
    d = d.astype(np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)


def main():
    scene, map_db, queries_db, out = Path(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
    rec = pycolmap.Reconstruction(str(scene / "sparse-map"))
    db = sqlite3.connect(f"file:{map_db}?mode=ro&immutable=1", uri=True)
    point_ids = sorted(rec.points3D.keys())
    index = {pid: i for i, pid in enumerate(point_ids)}
    sums = np.zeros((len(point_ids), 128), np.float32)
    for iid, image in rec.images.items():
        desc = blobs(db, "descriptors", iid)
        if desc is None:
            continue
        desc = normalise(desc)
        for idx, p2d in enumerate(image.points2D):
            if p2d.has_point3D():
                sums[index[p2d.point3D_id]] += desc[idx]
    map_desc = normalise(sums)
    xyz = np.array([rec.points3D[p].xyz for p in point_ids])

    qdb = sqlite3.connect(f"file:{queries_db}?mode=ro&immutable=1", uri=True)
    ids = dict(qdb.execute("SELECT name, image_id FROM images").fetchall())
    lines, times = [], []
    for line in (scene / "queries.txt").read_text().splitlines():
        name, model, w, h, *params = line.split()
        camera = pycolmap.Camera(model=model, width=int(w), height=int(h), params=[float(p) for p in params])
        t0 = time.perf_counter()
        kp = blobs(qdb, "keypoints", ids[name])
        qd = normalise(blobs(qdb, "descriptors", ids[name]))
        sim = qd @ map_desc.T
        best = np.argmax(sim, axis=1)
        top2 = np.partition(sim, -2, axis=1)[:, -2:]
        dist = np.sqrt(np.maximum(2 - 2 * top2, 0))
        ratio_ok = dist[:, 1] < 0.9 * dist[:, 0]
        mutual = np.argmax(sim, axis=0)[best] == np.arange(len(best))
        keep = ratio_ok & mutual
        pts2d = kp[keep, :2].astype(np.float64)
        pts3d = xyz[best[keep]]
        opts = pycolmap.AbsolutePoseEstimationOptions()
        opts.ransac.max_error = 12.0
        result = pycolmap.estimate_and_refine_absolute_pose(pts2d, pts3d, camera, opts)
        times.append((time.perf_counter() - t0) * 1e3)
        if result is None:
            lines.append(f"# failed {name}: no pose ({keep.sum()} matches)")
            continue
        pose = result["cam_from_world"]
        x, y, z, w_ = pose.rotation.quat
        t = pose.translation
        lines.append(f"{name} {w_} {x} {y} {z} {t[0]} {t[1]} {t[2]}")
    Path(out).write_text("\n".join(lines) + "\n")
    print(f"reference: {len(times)} queries, median {np.median(times):.1f} ms per query (matching + pose)")


if __name__ == "__main__":
    main()
