#!/usr/bin/env python3
"""kapture as NAVER's PyPI package (`kapture==1.1.12`) writes and reads it, for the kapture
round-trip tests (cli/tests/cli/kapture.rs).

    python3 tests/kapture_check.py import MODEL DATABASE IMAGES OUT   # kapture's COLMAP importer
    python3 tests/kapture_check.py read DIR                           # what kapture reads, as JSON

`read` prints one JSON object: `sensors` (id -> [sensor_type, params...]), `images` (image
path -> [sensor, qw, qx, qy, qz, tx, ty, tz] or null without a trajectory), `points`
([x, y, z(, r, g, b)] rows), `observations` (point id -> sorted [image, x, y] of each
observing keypoint, read from its .kpt file) and `keypoints` (type -> [dtype, dsize]).
"""

import json
import sys

import kapture
import kapture.io.csv as kcsv
from kapture.io.features import get_keypoints_fullpath, image_keypoints_from_file


def cmd_import(model, database, images, out):
    from kapture.converter.colmap.import_colmap import import_colmap
    from kapture.io.records import TransferAction

    k = import_colmap(out, database, model, images, force_overwrite_existing=True,
                      images_import_strategy=TransferAction.skip)
    kcsv.kapture_to_dir(out, k)


def cmd_read(root):
    k = kcsv.kapture_from_dir(root)
    sensors = {sid: [s.sensor_type] + list(s.sensor_params) for sid, s in k.sensors.items()}
    images = {}
    for ts, sensor in k.records_camera.key_pairs():
        name = k.records_camera[ts, sensor]
        pose = None
        if k.trajectories is not None and (ts, sensor) in k.trajectories.key_pairs():
            p = k.trajectories[ts, sensor]
            pose = [sensor] + [float(v) for v in p.r_raw] + [float(v) for v in p.t_raw]
        images[name] = pose
    points = [] if k.points3d is None else [[float(v) for v in row] for row in k.points3d]
    keypoints = {}
    observations = {}
    for ktype, kp in (k.keypoints or {}).items():
        keypoints[ktype] = [kp.dtype.__name__, kp.dsize]
        cache = {}
        for point, by_type in (k.observations or {}).items():
            for image, feature in by_type.get(ktype, []):
                if image not in cache:
                    path = get_keypoints_fullpath(ktype, root, image)
                    cache[image] = image_keypoints_from_file(path, kp.dtype, kp.dsize)
                x, y = cache[image][feature][:2]
                observations.setdefault(str(point), []).append([image, float(x), float(y)])
    for obs in observations.values():
        obs.sort()
    json.dump({"sensors": sensors, "images": images, "points": points,
               "observations": observations, "keypoints": keypoints}, sys.stdout)


if __name__ == "__main__":
    if sys.argv[1] == "import":
        cmd_import(*sys.argv[2:6])
    elif sys.argv[1] == "read":
        cmd_read(sys.argv[2])
    else:
        sys.exit(f"unknown command {sys.argv[1]}")
