"""Probe (issue 36): a COLMAP model whose points sit at the SFP network's keypoints, from the
SIFT model's tracks and its known poses, so an SFP map made from it (`convert --colmap OUT
--images ...`) has points where the network detects (see probe_sift_keypoint_queries.py for
why that matters).

For each SIFT track, in each image observing it, the nearest level-`LEVEL` (env, default 2)
keypoint of the network within R px (one per image, each keypoint used once); with 2 or more,
the point is triangulated (DLT on the undistorted rays) and kept when every view reprojects
within E px. Writes a text model (cameras, images with only the kept keypoints, points3D).

On KITTI 06 (R 4, E 2): 763 of 9,802 tracks kept; the sfp-v2 level-2 short map localizes at
0.0121 m / 0.039° (the SIFT-track map: 0.0236 m / 0.081°; SIFT level 2 short 0.0066 m /
0.027°), with 8 % of the points; on South Building 2,445 of 37,061 tracks, level 2 short
0.0029 / 0.075° (SIFT-track map 0.0043 / 0.123°). Only tracks that happen to have a network keypoint
nearby survive: matching the network's own keypoints across images and triangulating them
(hloc's way) would keep far more.

usage: python3 python/probe_sfp_tracks.py SPARSE_MODEL EXTRACTED.h5 OUT_DIR [R] [E]
  EXTRACTED.h5: `sfpmap extract MAP_IMAGES -o EXTRACTED.h5`. Needs numpy, scipy, h5py and pycolmap 4.2.1 (python/requirements.txt's).
"""
import os
import sys

import h5py
import numpy as np
import pycolmap
from scipy.spatial import cKDTree

model, h5, out = sys.argv[1:4]
R = float(sys.argv[4]) if len(sys.argv) > 4 else 4.0
E = float(sys.argv[5]) if len(sys.argv) > 5 else 2.0
LEVEL = int(os.environ.get("LEVEL", "2"))
rec = pycolmap.Reconstruction(model)
kp = {}
with h5py.File(h5, "r") as f:
    for im in rec.images.values():
        kp[im.image_id] = f[im.name][f"level{LEVEL}_keypoints"][()].astype(np.float64) + 0.5  # -> COLMAP
trees = {i: cKDTree(k) for i, k in kp.items() if len(k)}
used = {i: {} for i in kp}  # image -> keypoint index -> new point id
points = []  # (xyz, [(image_id, kp idx)])
P = {i: im.cam_from_world().matrix() for i, im in rec.images.items()}
stats = dict(tracks=0, few=0, reproj=0, kept=0)
for pid, p3 in rec.points3D.items():
    stats["tracks"] += 1
    obs = []
    for el in p3.track.elements:
        im = rec.images[el.image_id]
        xy = im.points2D[el.point2D_idx].xy
        if el.image_id not in trees:
            continue
        d, j = trees[el.image_id].query(xy, distance_upper_bound=R)
        if np.isfinite(d) and j not in used[el.image_id] and el.image_id not in {i for i, _ in obs}:
            obs.append((el.image_id, int(j)))
    if len({i for i, _ in obs}) < 2:
        stats["few"] += 1
        continue
    A = []
    for i, j in obs:
        cam = rec.images[i].camera
        u = cam.cam_from_img(kp[i][j][None])[0]
        M = P[i]
        A.append(u[0] * M[2] - M[0])
        A.append(u[1] * M[2] - M[1])
    _, _, vt = np.linalg.svd(np.array(A))
    X = vt[-1][:3] / vt[-1][3]
    ok = True
    for i, j in obs:
        M = P[i]
        c = M[:, :3] @ X + M[:, 3]
        if c[2] <= 0:
            ok = False
            break
        proj = rec.images[i].camera.img_from_cam(c[None, :])[0]
        if np.linalg.norm(proj - kp[i][j]) > E:
            ok = False
            break
    if not ok:
        stats["reproj"] += 1
        continue
    new_id = len(points) + 1
    for i, j in obs:
        used[i][j] = new_id
    points.append((X, obs, p3.color))
    stats["kept"] += 1
print(stats)
os.makedirs(out, exist_ok=True)
rec_cams = rec.cameras
with open(f"{out}/cameras.txt", "w") as f:
    for cid, cam in rec_cams.items():
        f.write(f"{cid} {cam.model_name} {cam.width} {cam.height} {' '.join(repr(float(v)) for v in cam.params)}\n")
pt2d_index = {}
with open(f"{out}/images.txt", "w") as f:
    for iid, im in sorted(rec.images.items()):
        T = im.cam_from_world()
        q = T.rotation.quat  # x, y, z, w
        t = T.translation
        f.write(f"{iid} {q[3]} {q[0]} {q[1]} {q[2]} {t[0]} {t[1]} {t[2]} {im.camera_id} {im.name}\n")
        items = sorted(used[iid].items())
        pt2d_index[iid] = {j: n for n, (j, _) in enumerate(items)}
        f.write(" ".join(f"{kp[iid][j][0]} {kp[iid][j][1]} {pid}" for j, pid in items) + "\n")
with open(f"{out}/points3D.txt", "w") as f:
    for n, (X, obs, color) in enumerate(points):
        track = " ".join(f"{i} {pt2d_index[i][j]}" for i, j in obs)
        f.write(f"{n + 1} {X[0]} {X[1]} {X[2]} {int(color[0])} {int(color[1])} {int(color[2])} 0.5 {track}\n")
