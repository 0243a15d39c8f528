"""Probe (issue 36): how much of SIFT's lead on an SfM scene is the pseudo ground truth's.

Sacre-Coeur's and South Building's query poses come from SfM on SIFT, queries included
(`../shared/data/README.md`). This probe rebuilds the same scene with another local feature
(the `features.h5` that `sfpmap extract` writes, e.g. with `--model aliked-n16`): the same
images, one camera (so scenes of one camera: South Building, kitchen, lund-street), mutual
nearest-neighbour matching of each image with the 20 images that share most points with it
in the SIFT model (which images overlap, not where they are), COLMAP's geometric verification
and incremental mapping. That reconstruction is aligned to the SIFT one by a similarity
fitted robustly (LO-RANSAC) on the map images' centres (never the queries'); a rebuild that
disagrees with SIFT's by more than a quarter of the camera spacing there is refused as folded.
Then it prints

- how far the two pseudo ground truths place each query (median / max centre distance in
  the scene's units, rotation in degrees): below that, an error measures how closely a
  method agrees with one of the two reconstructions;
- each given localization run's median errors against either ground truth.

A method whose errors are small against the SIFT ground truth and grow against the other one
may be measured on its agreement with SIFT more than on its precision (Brachmann et al., ICCV 2021,
"On the limits of pseudo ground truth in visual camera re-localisation").

South Building, ALIKED-N16 (stop 53): the two ground truths place the 26 queries a median
0.0051 units / 0.11° apart; SIFT's level-2 short map is at 0.00038 against SIFT's and 0.0049
against ALIKED's, sfp-v3's at 0.0021 and 0.0059 (`models/sfp-v3.md`, "Pseudo ground truth").

usage: python3 python/probe_pseudo_gt.py SCENE_DIR FEATURES.h5 WORK_DIR [NAME=POSES ...]
  SCENE_DIR: a scene of make_scene.py (images/, sparse-full/, gt_poses.txt)
  POSES: `sfpmap localize -o` output (`name qw qx qy qz tx ty tz`, cam_from_world)
  WORK_DIR: a new folder (database and reconstruction); nothing in SCENE_DIR is written.
Needs numpy, h5py and pycolmap (the tests' venv). Made for scenes of make_scene.py's size
(up to a few hundred images): it holds every image's descriptors in memory and matches on the
CPU, with no resume.
"""
import os
import sys
import time
from collections import Counter

import h5py
import numpy as np
import pycolmap


# Images each image is matched with. Exhaustive matching of ALIKED on South Building (mutual
# nearest neighbours, no ratio test) registered every image into a folded model: repeated
# windows of facades far apart verified as pairs.
NEIGHBOURS = 20
# Keypoints matched against the other image's per block of rows: bounds the similarity matrix
# at BLOCK × (the other image's keypoints) floats whatever the features file holds.
BLOCK = 2048


def log(*a):
    print(*a, file=sys.stderr, flush=True)


def fail(why):
    sys.exit(f"probe_pseudo_gt.py: {why}")


def read_poses(path):
    """name -> (R cam_from_world, camera centre)."""
    out = {}
    for line in open(path):
        f = line.split()
        if len(f) != 8 or line.startswith("#"):
            continue
        q = np.array([float(v) for v in f[1:5]])
        t = np.array([float(v) for v in f[5:8]])
        R = pycolmap.Rotation3d(np.array([q[1], q[2], q[3], q[0]])).matrix()
        out[f[0]] = (R, -R.T @ t)
    return out


def rec_poses(rec):
    out = {}
    for img in rec.images.values():
        if img.has_pose:
            cfw = img.cam_from_world()
            R = cfw.rotation.matrix()
            out[img.name] = (R, -R.T @ cfw.translation)
    return out


def rot_deg(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def mutual_nn(da, db):
    """Mutual nearest neighbours of two images' unit descriptors, as index pairs."""
    if len(da) == 0 or len(db) == 0:
        return np.zeros((0, 2), np.uint32)
    ab = np.empty(len(da), np.int64)
    best_b = np.full(len(db), -np.inf, np.float32)
    ba = np.zeros(len(db), np.int64)
    for i in range(0, len(da), BLOCK):
        scores = da[i:i + BLOCK] @ db.T
        ab[i:i + BLOCK] = scores.argmax(1)
        rows = scores.argmax(0)
        top = scores[rows, np.arange(len(db))]
        better = top > best_b
        best_b[better] = top[better]
        ba[better] = rows[better] + i
    keep = ba[ab] == np.arange(len(ab))
    return np.stack([np.nonzero(keep)[0], ab[keep]], 1).astype(np.uint32)


def covisible_pairs(rec, n):
    """Each registered image with the `n` images that see most of its points (hloc's
    pairs_from_covisibility): which images overlap, from the SIFT model; not their poses.
    Counted along the tracks, so the cost is the observations', not images squared."""
    observed = {}
    for p in rec.points3D.values():
        ids = {el.image_id for el in p.track.elements}
        for i in ids:
            observed.setdefault(i, Counter()).update(ids - {i})
    pairs = set()
    for i, counts in observed.items():
        pairs.update(tuple(sorted((rec.images[i].name, rec.images[j].name)))
                     for j, _ in counts.most_common(n))
    return sorted(pairs)


def reconstruct(scene, h5, work, pairs):
    images = os.path.join(scene, "images")
    db_path = os.path.join(work, "database.db")
    pycolmap.Database.open(db_path).close()  # creates the file and its tables
    pycolmap.import_images(db_path, images, pycolmap.CameraMode.SINGLE)
    descs = {}
    with pycolmap.Database.open(db_path) as db:
        ids = {im.name: im.image_id for im in db.read_all_images()}
        for name, image_id in ids.items():
            g = h5[name]
            # features.h5 keypoints are in the pixel-index convention; COLMAP's origin is the
            # first pixel's corner.
            db.write_keypoints(image_id, np.asarray(g["keypoints"], np.float32) + 0.5)
            d = np.asarray(g["descriptors"], np.float32).T
            descs[name] = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        shown = time.monotonic()
        for k, (a, b) in enumerate(pairs):
            db.write_matches(ids[a], ids[b], mutual_nn(descs[a], descs[b]))
            if time.monotonic() - shown > 30:
                log(f"matched {k + 1} of {len(pairs)} pairs")
                shown = time.monotonic()
    pairs_path = os.path.join(work, "pairs.txt")
    with open(pairs_path, "w") as f:
        f.write("".join(f"{a} {b}\n" for a, b in pairs))
    log(f"matched {len(pairs)} pairs; verifying")
    pycolmap.verify_matches(db_path, pairs_path)
    out = os.path.join(work, "sparse")
    os.makedirs(out, exist_ok=True)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = 2
    recs = pycolmap.incremental_mapping(db_path, images, out, opts)
    if not recs:
        fail(f"{work}: the mapper registered no model from these features")
    best = max(recs.values(), key=lambda r: r.num_reg_images())
    log(f"reconstruction: {best.num_reg_images()} images, {best.num_points3D()} points, "
        f"reprojection error {best.compute_mean_reprojection_error():.3f} px")
    return best


def main():
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    scene, features, work = sys.argv[1:4]
    # Everything checked before the minutes of matching and mapping.
    runs = []
    for arg in sys.argv[4:]:
        name, _, path = arg.partition("=")
        if not name or not path:
            fail(f"{arg!r}: a run is NAME=POSES")
        if not os.path.isfile(path):
            fail(f"{path}: no such poses file")
        runs.append((name, read_poses(path)))
    full = pycolmap.Reconstruction(os.path.join(scene, "sparse-full"))
    if full.num_cameras() != 1:
        fail(f"{scene}: {full.num_cameras()} cameras; the rebuild models one (a scene of one camera)")
    h5 = h5py.File(features, "r")
    images = sorted(os.listdir(os.path.join(scene, "images")))
    missing = [n for n in images if n not in h5]
    if missing:
        fail(f"{features}: no features for {len(missing)} of the scene's images (first: {missing[0]})")
    sift = rec_poses(full)
    gt = read_poses(os.path.join(scene, "gt_poses.txt"))
    os.makedirs(work, exist_ok=False)
    rebuilt = rec_poses(reconstruct(scene, h5, work, covisible_pairs(full, NEIGHBOURS)))
    map_names = sorted(n for n in rebuilt if n in sift and n not in gt)
    if len(map_names) < 3:
        fail(f"{len(map_names)} map images in both reconstructions: nothing to align on")
    centres = np.array([sift[n][1] for n in map_names])
    spacing = np.median([np.sort(np.linalg.norm(centres - c, axis=1))[1] for c in centres])
    # A video that stands still has centres on top of each other: the spread bounds it below.
    spread = np.median(np.linalg.norm(centres - np.median(centres, axis=0), axis=1))
    spacing = max(spacing, 1e-3 * spread)
    if not spacing > 0:
        fail("the map images' centres coincide: nothing to align on")
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = 0.25 * spacing
    # Robust: a few misregistered images must not pull the similarity.
    found = pycolmap.estimate_sim3d_robust(np.array([rebuilt[n][1] for n in map_names]), centres, ransac)
    if not found:
        fail("no similarity aligns the two reconstructions' map images")
    sim3 = found["tgt_from_src"]
    R_s = sim3.rotation.matrix()
    aligned = {n: (R @ R_s.T, sim3.scale * R_s @ c + sim3.translation) for n, (R, c) in rebuilt.items()}
    resid = np.array([np.linalg.norm(aligned[n][1] - sift[n][1]) for n in map_names])
    queries = sorted(n for n in gt if n in aligned)
    log(f"{len(map_names)} map images aligned: centre residual median {np.median(resid):.5f}, "
        f"max {resid.max():.5f} (camera spacing {spacing:.4f}); {len(queries)} of {len(gt)} queries in both")
    if np.median(resid) > 0.25 * spacing:
        fail(f"the reconstructions disagree by a median {np.median(resid):.4f} on the map images "
             f"(a quarter of the camera spacing is {0.25 * spacing:.4f}): the rebuilt one is folded or broken")
    if not queries:
        fail("no query is in both reconstructions")
    dc = [np.linalg.norm(aligned[n][1] - gt[n][1]) for n in queries]
    dr = [rot_deg(aligned[n][0], gt[n][0]) for n in queries]
    print("| | median transl. | max transl. | median rot. (°) | max rot. (°) |")
    print("|---|---|---|---|---|")
    print(f"| the two ground truths, {len(queries)} queries | {np.median(dc):.5f} | {max(dc):.5f} "
          f"| {np.median(dr):.4f} | {max(dr):.4f} |")
    if runs:
        print()
        print("| run | against SIFT's ground truth: transl. / rot. (°) | against the rebuilt one: transl. / rot. (°) |")
        print("|---|---|---|")
    for name, est in runs:
        both = [n for n in queries if n in est]
        if not both:
            print(f"| {name} (no query localized) | - | - |")
            continue

        def errors(ref):
            return (np.median([np.linalg.norm(est[n][1] - ref[n][1]) for n in both]),
                    np.median([rot_deg(est[n][0], ref[n][0]) for n in both]))

        (ts, rs), (to, ro) = errors(gt), errors(aligned)
        print(f"| {name} ({len(both)} queries) | {ts:.5f} / {rs:.4f} | {to:.5f} / {ro:.4f} |")


if __name__ == "__main__":
    main()
