#!/usr/bin/env python3
"""sfpmap convert vs. pycolmap read, on a synthetic COLMAP binary model (issue 3, "Speed and size").

Generates (or reuses, under target/bench-colmap/) a COLMAP binary model of N points with tracks
of length 5, a few hundred images with SIMPLE_RADIAL cameras and random valid poses, each
image's points2D holding its observations plus ~25 % untriangulated ones. Then, interleaved,
REPEATS times each (after one warm-up run of each, so both read from the page cache):

- `sfpmap convert --colmap DIR -o OUT --json` (geometry only): wall time, peak RSS;
- `pycolmap.Reconstruction(DIR)` alone in a fresh python process (the import is not timed):
  wall time of the read, peak RSS of the process.

Prints medians side by side and the two ratios of issue 3 with PASS/FAIL against the targets
(pycolmap read / sfpmap convert >= 3x; sfpmap peak RSS / (model + output bytes) <= 2x).
It reports; it does not assert: the exit code is 0 unless something fails to run.

Peak RSS comes from GNU time (`/usr/bin/time -f %M`; Debian package `time`). Why not
os.wait4/getrusage here: Linux carries the parent's RSS high-water mark into a forked child's
ru_maxrss (a /bin/true spawned from a 300 MB python reports 314 MB), so this script, which
holds numpy, would inflate every child's peak. GNU time is a small process in between.

Run (from the repository root, after `cargo build --release`):

    python3 benches/compare_pycolmap.py --points 1000000
    python3 benches/compare_pycolmap.py --points 100000 --repeats 3 --sfpmap target/release/sfpmap

The binary layout follows COLMAP's src/colmap/scene/reconstruction_io_binary.cc (all
little-endian, no header):
  cameras.bin   u64 n; per camera: u32 id, i32 model_id, u64 width, u64 height, f64 params[]
  images.bin    u64 n; per image: u32 id, f64 qw qx qy qz, f64 tx ty tz, u32 camera_id,
                name bytes, '\\0', u64 num_points2D; per point2D: f64 x, f64 y, u64 point3D_id
                (u64 max = untriangulated)
  points3D.bin  u64 n; per point: u64 id, f64 x y z, u8 r g b, f64 error, u64 track_length;
                per track element: u32 image_id, u32 point2D_idx
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

TIME = "/usr/bin/time"
INVALID_POINT3D_ID = np.iinfo(np.uint64).max
SIMPLE_RADIAL = 2
# (width, height) of the synthetic cameras: phone, DSLR-ish, video, action cam.
RESOLUTIONS = [(4032, 3024), (1920, 1080), (1600, 1200), (2704, 1520)]
GENERATOR_VERSION = 1  # bump when the generated content changes, to invalidate caches

POINT2D_DTYPE = np.dtype([("xy", "<f8", (2,)), ("point3d_id", "<u8")])  # 24 bytes, packed


def point3d_dtype(track_length: int) -> np.dtype:
    # Packed (align=False): exactly COLMAP's 43-byte point header + 8 bytes per track element.
    return np.dtype(
        [
            ("id", "<u8"),
            ("xyz", "<f8", (3,)),
            ("rgb", "u1", (3,)),
            ("error", "<f8"),
            ("track_length", "<u8"),
            ("track", "<u4", (track_length, 2)),  # (image_id, point2D_idx)
        ]
    )


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Scalar-first unit quaternions (n, 4) -> rotation matrices (n, 3, 3)."""
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def generate(
    out: Path,
    points: int,
    images: int,
    cameras: int = 4,
    track_length: int = 5,
    untriangulated: float = 0.25,
    seed: int = 0,
) -> dict:
    """Writes cameras.bin, images.bin, points3D.bin into `out`; returns the expected counts."""
    if images < track_length:
        raise ValueError(f"need at least {track_length} images for tracks of {track_length}")
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)

    # Cameras: SIMPLE_RADIAL (f, cx, cy, k), f ~ 0.8-1.2 x the long side, small k.
    sizes = [RESOLUTIONS[i % len(RESOLUTIONS)] for i in range(cameras)]
    with open(out / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", cameras))
        for cam_id, (w, h) in enumerate(sizes, start=1):
            focal = max(w, h) * rng.uniform(0.8, 1.2)
            k = rng.normal(0.0, 0.03)
            f.write(struct.pack("<IiQQ4d", cam_id, SIMPLE_RADIAL, w, h, focal, w / 2, h / 2, k))

    # Images: camera centres scattered over a 200 m x 200 m site at 1-3 m height; random unit
    # quaternions (qw >= 0); cam_from_world translation t = -R C.
    image_cam = np.arange(images) % cameras  # 0-based camera index
    q = rng.normal(size=(images, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    centres = np.column_stack(
        [rng.uniform(-100, 100, images), rng.uniform(1, 3, images), rng.uniform(-100, 100, images)]
    )
    t = -np.einsum("nij,nj->ni", quat_to_rotmat(q), centres)

    # Tracks: `track_length` distinct images per point. Sorting draws from [0, images - L] and
    # adding 0..L-1 makes them strictly increasing, hence distinct, without a per-point loop.
    L = track_length
    track_img = np.sort(rng.integers(0, images - L + 1, size=(points, L)), axis=1)
    track_img += np.arange(L)
    obs_img = track_img.ravel()  # observation o belongs to point o // L
    order = np.argsort(obs_img, kind="stable")
    counts = np.bincount(obs_img, minlength=images)
    starts = np.concatenate([[0], np.cumsum(counts)])
    obs_idx = np.empty(points * L, dtype=np.uint32)  # point2D_idx of each observation

    total_points2d = 0
    with open(out / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", images))
        for i in range(images):
            sel = order[starts[i] : starts[i + 1]]
            n_obs = len(sel)
            n_total = n_obs + int(round(n_obs * untriangulated))
            # Observations take random slots among the image's points2D; the rest stay
            # untriangulated, as after COLMAP's triangulation.
            slots = rng.permutation(n_total)[:n_obs]
            obs_idx[sel] = slots
            w, h = sizes[image_cam[i]]
            p2d = np.empty(n_total, dtype=POINT2D_DTYPE)
            p2d["xy"][:, 0] = rng.uniform(0.5, w - 0.5, n_total)
            p2d["xy"][:, 1] = rng.uniform(0.5, h - 0.5, n_total)
            p2d["point3d_id"] = INVALID_POINT3D_ID
            p2d["point3d_id"][slots] = sel // L + 1  # point ids are 1..N
            name = f"cam{image_cam[i] + 1:02d}/frame_{i + 1:06d}.jpg".encode()
            f.write(struct.pack("<I4d3dI", i + 1, *q[i], *t[i], image_cam[i] + 1))
            f.write(name + b"\0")
            f.write(struct.pack("<Q", n_total))
            f.write(p2d.tobytes())
            total_points2d += n_total

    # Points: a site 200 m x 30 m x 200 m, sorted by id as COLMAP writes them.
    rec = np.empty(points, dtype=point3d_dtype(L))
    rec["id"] = np.arange(1, points + 1, dtype=np.uint64)
    rec["xyz"] = rng.uniform([-100, 0, -100], [100, 30, 100], size=(points, 3))
    rec["rgb"] = rng.integers(0, 256, size=(points, 3), dtype=np.uint8)
    rec["error"] = rng.gamma(2.0, 0.35, size=points)
    rec["track_length"] = L
    rec["track"][:, :, 0] = track_img + 1  # image ids are 1..images
    rec["track"][:, :, 1] = obs_idx.reshape(points, L)
    with open(out / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", points))
        f.write(rec.tobytes())

    return {
        "cameras": cameras,
        "images": images,
        "points3D": points,
        "observations": points * L,
        "points2D": total_points2d,
    }


def model_bytes(model: Path) -> int:
    return sum((model / n).stat().st_size for n in ("cameras.bin", "images.bin", "points3D.bin"))


def cached_model(root: Path, args) -> tuple[Path, dict]:
    """Generates the model once per parameter set; `params.json` is written last as the marker."""
    key = dict(
        version=GENERATOR_VERSION,
        points=args.points,
        images=args.images,
        cameras=args.cameras,
        track_length=args.track_length,
        untriangulated=args.untriangulated,
        seed=args.seed,
    )
    model = root / f"synthetic-{args.points}p-{args.images}i-s{args.seed}"
    marker = model / "params.json"
    if marker.is_file():
        saved = json.loads(marker.read_text())
        if saved.get("key") == key:
            return model, saved["expected"]
    shutil.rmtree(model, ignore_errors=True)
    t0 = time.perf_counter()
    expected = generate(
        model,
        args.points,
        args.images,
        args.cameras,
        args.track_length,
        args.untriangulated,
        args.seed,
    )
    print(f"generated {model} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    marker.write_text(json.dumps({"key": key, "expected": expected}, indent=1))
    return model, expected


def run_measured(cmd: list[str]) -> tuple[float, float, int, str]:
    """Runs `cmd` under GNU time; returns (wall s, CPU s (user + sys), peak RSS bytes, stdout)."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as stats:
        t0 = time.perf_counter()
        proc = subprocess.run(
            [TIME, "-f", "%e %U %S %M", "-o", stats.name, *cmd], capture_output=True, text=True
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}:\n{proc.stderr}")
        # The last line: GNU time prepends "Command exited with non-zero status" on failure.
        _, user, system, max_rss_kib = stats.read().split("\n")[-2].split()
    return wall, float(user) + float(system), int(max_rss_kib) * 1024, proc.stdout


# Runs in a fresh interpreter: import first (not timed), then only the read is timed.
PYCOLMAP_READ = r"""
import json, resource, sys, time
import pycolmap
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t0, c0 = time.perf_counter(), time.process_time()
rec = pycolmap.Reconstruction(sys.argv[1])
seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({
    "seconds": seconds,
    "cpu_seconds": cpu,
    "rss_after_import": before,
    "cameras": rec.num_cameras(),
    "images": rec.num_reg_images(),
    "points3D": rec.num_points3D(),
    "observations": rec.compute_num_observations(),
    "points2D": sum(img.num_points2D() for img in rec.images.values()),
}))
"""


def sfpmap_convert(sfpmap: str, model: Path, output: Path) -> dict:
    wall, cpu, rss, out = run_measured(
        [sfpmap, "convert", "--colmap", str(model), "-o", str(output), "--json", "--quiet"]
    )
    report = json.loads(out)
    output.unlink()
    return {"wall": wall, "cpu": cpu, "rss": rss, "report": report}


def pycolmap_read(model: Path) -> dict:
    wall, cpu, rss, out = run_measured([sys.executable, "-c", PYCOLMAP_READ, str(model)])
    report = json.loads(out)
    return {"wall": wall, "cpu": cpu, "rss": rss, "report": report}


def mb(n: float) -> str:
    return f"{n / 1e6:,.1f} MB"


def main() -> int:
    root = Path(__file__).resolve().parent.parent
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--images", type=int, default=400)
    ap.add_argument("--cameras", type=int, default=4)
    ap.add_argument("--track-length", type=int, default=5)
    ap.add_argument(
        "--untriangulated",
        type=float,
        default=0.25,
        help="untriangulated points2D per image, as a fraction of its observations",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--sfpmap", default=str(root / "target/release/sfpmap"))
    ap.add_argument(
        "--cache",
        default=str(root / "target/bench-colmap"),
        help="where generated models are kept for reuse",
    )
    ap.add_argument("--no-cache", action="store_true", help="generate into a temp dir instead")
    ap.add_argument("--json", metavar="FILE", help="also write the raw measurements here")
    args = ap.parse_args()
    if not os.access(TIME, os.X_OK):
        sys.exit(f"{TIME} not found: install GNU time (Debian: apt-get install time)")

    tmp = tempfile.TemporaryDirectory(prefix="sfpmap-bench-")
    cache = Path(tmp.name) if args.no_cache else Path(args.cache)
    model, expected = cached_model(cache, args)
    in_bytes = model_bytes(model)
    output = Path(tmp.name) / "synthetic.sfpm"

    # Warm-up (page cache, binary and library loading), then interleaved measured runs so
    # that load from other jobs on the machine hits both sides alike.
    sfp_runs, pyc_runs = [], []
    load_before = os.getloadavg()[0]
    first = sfpmap_convert(args.sfpmap, model, output)
    check = pycolmap_read(model)
    for _ in range(args.repeats):
        sfp_runs.append(sfpmap_convert(args.sfpmap, model, output))
        pyc_runs.append(pycolmap_read(model))

    got = {k: check["report"][k] for k in expected}
    counts_ok = got == expected
    sfp_counts_ok = (
        first["report"]["points"] == expected["points3D"]
        and first["report"]["images"] == expected["images"]
    )
    out_bytes = first["report"]["output_bytes"]

    med = statistics.median
    sfp_wall = med(r["wall"] for r in sfp_runs)
    sfp_inner = med(r["report"]["seconds"] for r in sfp_runs)
    sfp_rss = med(r["rss"] for r in sfp_runs)
    sfp_cpu = med(r["cpu"] for r in sfp_runs)
    pyc_cpu = med(r["report"]["cpu_seconds"] for r in pyc_runs)
    pyc_read = med(r["report"]["seconds"] for r in pyc_runs)
    pyc_wall = med(r["wall"] for r in pyc_runs)
    pyc_rss = med(r["rss"] for r in pyc_runs)
    pyc_base = med(r["report"]["rss_after_import"] for r in pyc_runs)
    time_ratio = pyc_read / sfp_wall
    mem_ratio = sfp_rss / (in_bytes + out_bytes)

    n = expected["points3D"]
    print(f"model       {model}")
    print(
        f"            {expected['points3D']:,} points x track {args.track_length}, "
        f"{expected['images']} images, {expected['cameras']} SIMPLE_RADIAL cameras, "
        f"{expected['points2D']:,} points2D ({expected['observations']:,} triangulated)"
    )
    print(f"            model {mb(in_bytes)}, map (geometry only) {mb(out_bytes)}")
    print(
        f"counts      pycolmap reads {got}: {'match' if counts_ok else 'MISMATCH'}; "
        f"sfpmap converted {first['report']['points']:,} points, "
        f"{first['report']['images']} images: {'match' if sfp_counts_ok else 'MISMATCH'}"
    )
    print(
        f"runs        {args.repeats} each after 1 warm-up, interleaved; medians; "
        f"load average {load_before:.1f} -> {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    print()
    w = 44
    print(f"{'':{w}} {'sfpmap convert':>16} {'pycolmap read':>16}")
    print(f"{'wall time, whole process (s)':{w}} {sfp_wall:16.3f} {pyc_wall:16.3f}")
    print(f"{'time of the work (s) [1]':{w}} {sfp_inner:16.3f} {pyc_read:16.3f}")
    print(f"{'CPU time of the work, user + sys (s) [2]':{w}} {sfp_cpu:16.3f} {pyc_cpu:16.3f}")
    print(f"{'peak RSS':{w}} {mb(sfp_rss):>16} {mb(pyc_rss):>16}")
    print(f"{'  of which python + pycolmap import':{w}} {'':>16} {mb(pyc_base):>16}")
    print(f"{'points / s (on the time of the work)':{w}} {n / sfp_inner:16,.0f} {n / pyc_read:16,.0f}")
    print()
    print("[1] sfpmap: the `seconds` its --json reports; pycolmap: Reconstruction(dir) alone.")
    print("[2] sfpmap: the whole process; pycolmap: time.process_time() around the read. Less")
    print("    sensitive than wall time to other jobs competing for the cores.")
    print()
    verdict = lambda ok: "PASS" if ok else "FAIL"  # noqa: E731
    print(
        f"pycolmap read / sfpmap convert (whole process)  {time_ratio:6.2f}x   "
        f"target >= 3x   {verdict(time_ratio >= 3)}"
    )
    if sfp_cpu > 0:  # GNU time counts in 10 ms ticks
        print(f"  the same on CPU time (not the target)         {pyc_cpu / sfp_cpu:6.2f}x")
    print(
        f"sfpmap peak RSS / (model + output bytes)        {mem_ratio:6.2f}x   "
        f"target <= 2x   {verdict(mem_ratio <= 2)}"
    )
    if not (counts_ok and sfp_counts_ok):
        print("WARNING: counts do not match the generated model", file=sys.stderr)

    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "model": str(model),
                    "expected": expected,
                    "pycolmap_counts": got,
                    "model_bytes": in_bytes,
                    "output_bytes": out_bytes,
                    "sfpmap": sfp_runs,
                    "pycolmap": pyc_runs,
                    "time_ratio": time_ratio,
                    "memory_ratio": mem_ratio,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
