"""Rerun recordings of a map and its queries (extra ``sfpmap[viz]``: ``rerun-sdk``).

    python -m sfpmap.viz MAP -o OUT.rrd [--poses POSES] [--gt GT] [--trajectory TUM]
                         [--inliers NAME --query-list LIST (--images DIR | --database DB)]

``sfpmap export MAP --rerun OUT.rrd`` runs this module. What the recording holds, under
``world/`` (COLMAP's world frame, the map's):

- ``map/level_<L>``: the map's points of level L (a point on several levels is drawn in each),
  one colour per level (``LEVEL_COLORS``);
- ``map/cameras/<i>``: database image i's camera as a frustum (its pose, and the focal lengths
  and principal point of its camera model; distortion left out); at most ``MAX_CAMERAS`` of
  them, spread evenly over the images;
- ``queries/<name>/estimate`` and ``queries/<name>/truth``: a query's localized pose
  (``--poses``: ``localize -o`` lines, COLMAP's ``name qw qx qy qz tx ty tz``) and its ground
  truth (``--gt``, the same lines) as frusta, with the query's camera (``--query-list`` or
  ``--camera``; else the map's first camera); at most ``MAX_CAMERAS`` of each, spread;
- ``errors``: a line from each estimated camera centre to its true one;
- ``queries/<name>/inliers``: for the query ``--inliers`` names, localized here, the 3D points
  of its final inliers, a line from each to the camera centre, and their keypoints in the
  camera's image plane (``.../estimate/keypoints``); its features are extracted with the map's
  own model (``--images``, or ``--model FILE``) or read from ``--database``, and it is localized
  with the library's default options;
- ``trajectory``: a sequence's poses over time (``--trajectory``: TUM lines, world_from_cam, as
  ``localize --sequence --format tum``, ``localize --mcap --tum`` or ``export --tum`` write them)
  on the timeline ``frame`` (and ``time``: the TUM stamps, as dates where they are Unix times,
  else as seconds from zero), and its whole path.

A recording is written whole to a temp file beside OUT and renamed into place: OUT is never
half-written, and nothing else is written.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np

import sfpmap

__all__ = [
    "LEVEL_COLORS", "MAX_CAMERAS", "Summary", "main", "read_tum", "record",
    "rotation_matrix", "world_from_cam",
]

#: RGB per level id: level 0 (finest) to 3 (coarsest), then around again.
LEVEL_COLORS = [(230, 159, 0), (86, 180, 233), (0, 158, 115), (204, 121, 167)]
#: Colours of a query's estimated pose, its ground truth, and the error between them.
ESTIMATE_COLOR, TRUTH_COLOR, ERROR_COLOR = (255, 64, 64), (64, 200, 64), (255, 255, 0)
#: Frusta are drawn for at most this many database images (every one below it, else every
#: n-th).
MAX_CAMERAS = 5000
#: TUM stamps from this on (2001-09-09) are read as Unix times.
UNIX_STAMPS_FROM = 1e9


@dataclass
class Summary:
    """What a recording holds: counts per entity kind, for tests and ``--json``."""

    points_per_level: Dict[int, int] = field(default_factory=dict)
    cameras: int = 0
    estimates: int = 0
    truths: int = 0
    errors: int = 0
    inliers: int = 0
    trajectory: int = 0

    def as_dict(self) -> Dict[str, Any]:
        return {
            "points_per_level": {str(k): v for k, v in self.points_per_level.items()},
            "cameras": self.cameras,
            "estimates": self.estimates,
            "truths": self.truths,
            "errors": self.errors,
            "inliers": self.inliers,
            "trajectory": self.trajectory,
        }


def _rerun() -> Any:
    try:
        import rerun
    except ImportError as e:  # pragma: no cover - the message is the point
        raise sfpmap.InputError(
            "Rerun recordings need the rerun-sdk package: pip install 'sfpmap[viz]'"
        ) from e
    return rerun


def rotation_matrix(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """The rotation of a unit quaternion (w, x, y, z)."""
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if not (n > 0 and math.isfinite(n)):
        raise sfpmap.InputError(f"quaternion ({qw}, {qx}, {qy}, {qz}) is not a rotation")
    w, x, y, z = qw / n, qx / n, qy / n, qz / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def world_from_cam(colmap: Sequence[float]) -> Tuple[np.ndarray, np.ndarray]:
    """(rotation, camera centre) of the camera in the world, from COLMAP's cam_from_world
    ``[qw, qx, qy, qz, tx, ty, tz]``."""
    r = rotation_matrix(*colmap[:4])
    t = np.asarray(colmap[4:7], dtype=np.float64)
    return r.T, -r.T @ t


def _rotations(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of quaternions, rows ``(w, x, y, z)``, normalised here (a norm of 0,
    or one that overflows, is an ``InputError``): ``[n, 3, 3]``."""
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    if not (np.isfinite(norm) & (norm > 0)).all():
        raise sfpmap.InputError("a quaternion of norm 0 or too large to normalise is not a rotation")
    q = q / norm
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def _worlds_from_cams(colmap: Any) -> Tuple[np.ndarray, np.ndarray]:
    """:func:`world_from_cam` of many poses at once (rows ``qw qx qy qz tx ty tz``, from the
    map or the library's readers, so quaternions of norm > 0): rotations ``[n, 3, 3]`` and
    centres ``[n, 3]``."""
    colmap = np.asarray(colmap, dtype=np.float64).reshape(-1, 7)
    r = _rotations(colmap[:, :4])
    rt = np.transpose(r, (0, 2, 1))
    return rt, -np.einsum("nij,nj->ni", rt, colmap[:, 4:7])


#: The largest TUM stamp read, in seconds (year 2262, where nanoseconds leave an i64): a
#: larger one is in milliseconds or nanoseconds, which the format does not use.
MAX_STAMP = 9.2e9


def read_tum(path: str) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TUM lines ``t tx ty tz qx qy qz qw`` (world_from_cam): stamps ``[n]``, rotations
    ``[n, 3, 3]`` and centres ``[n, 3]``. A line that is not one is an error naming the file
    and line."""
    rows: List[List[float]] = []
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            fields = line.split()
            if not fields or fields[0].startswith("#"):
                continue
            try:
                v = [float(x) for x in fields]
                if len(v) != 8 or not all(math.isfinite(x) for x in v):
                    raise ValueError
            except ValueError:
                raise sfpmap.InputError(
                    f"{path}:{number}: expected 'timestamp tx ty tz qx qy qz qw'"
                ) from None
            if abs(v[0]) > MAX_STAMP:
                raise sfpmap.InputError(
                    f"{path}:{number}: stamp {fields[0]} is not in seconds (milliseconds or nanoseconds?)"
                )
            if not math.hypot(*v[4:8]) > 0:
                raise sfpmap.InputError(f"{path}:{number}: quaternion of norm 0 is not a rotation")
            rows.append(v)
    a = np.array(rows, dtype=np.float64).reshape(-1, 8)
    wxyz = a[:, [7, 4, 5, 6]]
    return a[:, 0], _rotations(wxyz), a[:, 1:4]


def _intrinsics(camera: Any) -> Optional[Tuple[np.ndarray, Tuple[int, int]]]:
    """A pinhole matrix of a ``sfpmap.Camera`` or a map's camera dict (any COLMAP model's
    focal lengths and principal point, distortion left out: a frustum, not a rectification)
    and the resolution; ``None`` for a model without them (EQUIRECTANGULAR)."""
    if isinstance(camera, sfpmap.Camera):
        model, params, size = camera.model, camera.params, (camera.width, camera.height)
    else:
        model, params, size = camera["model"], camera["params"], (int(camera["width"]), int(camera["height"]))
    pinhole = sfpmap.pinhole_intrinsics(model, params)
    if pinhole is None:
        return None
    fx, fy, cx, cy = pinhole
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), size


def _map_intrinsics(cameras: List[Dict[str, Any]]) -> List[Optional[Tuple[np.ndarray, Tuple[int, int]]]]:
    """Each map camera's :func:`_intrinsics`, once; a camera the library cannot read (a
    model or parameter count the map's writer did not check) is drawn as its pose alone."""
    out: List[Optional[Tuple[np.ndarray, Tuple[int, int]]]] = []
    for c in cameras:
        try:
            out.append(_intrinsics(c))
        except sfpmap.InputError:
            out.append(None)
    return out


def _frustum(rr: Any, rec: Any, path: str, rotation: np.ndarray, centre: np.ndarray,
             intrinsics: Optional[Tuple[np.ndarray, Tuple[int, int]]], depth: float,
             color: Optional[Tuple[int, int, int]] = None) -> None:
    rec.log(path, rr.Transform3D(translation=centre, mat3x3=rotation), static=True)
    if intrinsics is not None:  # else the pose alone
        k, resolution = intrinsics
        rec.log(path, rr.Pinhole(image_from_camera=k, resolution=resolution, image_plane_distance=depth,
                                 camera_xyz=rr.ViewCoordinates.RDF, color=color), static=True)


def _entity_part(name: str) -> str:
    """A query's name as one part of an entity path (``/`` and other specials escaped)."""
    return str(_rerun().escape_entity_path_part(name))


def _scene_scale(centres: np.ndarray) -> float:
    """A frustum depth that suits the scene: half the median distance between consecutive
    cameras."""
    if len(centres) < 2:
        return 0.1
    d = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    d = d[d > 0]
    return float(np.median(d)) * 0.5 if len(d) else 0.1


def _query_cameras(given: Any) -> Tuple[Optional[sfpmap.Camera], Dict[str, sfpmap.Camera]]:
    """``record``'s ``query_cameras``: one camera for every query (a ``Camera``, a
    ``"MODEL W H params..."`` string or a camera dict), or cameras by name (a dict of them, or
    ``read_queries``'s list of pairs); ``(every, by_name)``."""
    def camera(c: Any) -> sfpmap.Camera:
        if isinstance(c, sfpmap.Camera):
            return c
        if isinstance(c, str):
            return sfpmap.Camera.parse(c)
        if isinstance(c, dict) and "model" in c:
            return sfpmap.Camera(c["model"], int(c["width"]), int(c["height"]), list(c["params"]))
        raise sfpmap.InputError(f"query_cameras: {c!r} is not a camera")
    if given is None:
        return None, {}
    if isinstance(given, (sfpmap.Camera, str)) or (isinstance(given, dict) and "model" in given):
        return camera(given), {}
    pairs = given.items() if isinstance(given, dict) else given
    try:
        return None, {str(name): camera(c) for name, c in pairs}
    except (TypeError, ValueError):
        raise sfpmap.InputError("query_cameras: a camera, or cameras by query name") from None


def _spread(n: int, most: int) -> range:
    """Indices of at most ``most`` of ``n`` items, evenly spread (all of them below it)."""
    return range(0, n, max(1, math.ceil(n / most)))


def record(
    map_path: str,
    out: str,
    *,
    poses: Optional[str] = None,
    gt: Optional[str] = None,
    trajectory: Optional[str] = None,
    inliers: Optional[Tuple[str, "sfpmap.Localization", sfpmap.Camera]] = None,
    query_cameras: Any = None,
    max_points: Optional[int] = None,
    force: bool = False,
) -> Summary:
    """Writes the recording of the map at ``map_path`` (and whatever else is given, as the
    module says) to ``out``. ``inliers``: (query name, its localization made with
    ``Localizer(keep_inliers=True)``, its camera). ``query_cameras``: the queries' cameras by
    name (a dict, or ``read_queries``'s pairs), or one camera for every query (a ``Camera``, a
    ``"MODEL W H params..."`` string or a camera dict), for their frusta (default: the map's
    first camera). ``max_points``: at most this
    many points per level (every n-th), for maps too large to look at whole. Frusta are drawn
    for at most ``MAX_CAMERAS`` database images and as many queries, spread over them; the
    error lines for every query. An existing ``out`` is refused unless ``force``; one of the
    inputs, always."""
    rr = _rerun()
    if max_points is not None and max_points < 1:
        raise sfpmap.InputError(f"max_points {max_points}: at least 1")
    if os.path.lexists(out):
        inputs = [p for p in (map_path, poses, gt, trajectory) if p and os.path.exists(p)]
        if any(os.path.samefile(p, out) for p in inputs):
            raise sfpmap.InputError(f"{out}: is one of the inputs")
        if not force:
            raise sfpmap.InputError(f"{out}: exists (force=True, --force, overwrites it)")
    summary = Summary()
    folder = os.path.dirname(os.path.abspath(out))
    fd, temp = tempfile.mkstemp(prefix=".sfpmap-viz-", suffix=".rrd", dir=folder)
    os.close(fd)
    try:
        rec = rr.RecordingStream("sfpmap")
        rec.save(temp)
        with sfpmap.Map(map_path) as m:
            # A float64 copy of every point (24 bytes each): max_points thins what is drawn,
            # not this.
            world = m.points.world()
            for level in m.levels:
                rows = level.points
                if max_points is not None and len(rows) > max_points:
                    rows = rows[:: math.ceil(len(rows) / max_points)]
                color = LEVEL_COLORS[level.id % len(LEVEL_COLORS)]
                rec.log(f"world/map/level_{level.id}", rr.Points3D(world[rows], colors=color, radii=rr.Radius.ui_points(1.5)), static=True)
                summary.points_per_level[level.id] = int(len(rows))
            del world
            map_cameras = m.cameras
            intrinsics = _map_intrinsics(map_cameras)
            images = m.images
            depth = 0.1
            if images is not None and len(images):
                image_cameras = images.cameras
                rotations, centres = _worlds_from_cams(images.poses)
                depth = _scene_scale(centres)
                for i in _spread(len(centres), MAX_CAMERAS):
                    c = int(image_cameras[i])
                    _frustum(rr, rec, f"world/map/cameras/{i}", rotations[i], centres[i],
                             intrinsics[c] if c < len(intrinsics) else None, depth)
                    summary.cameras += 1
            default = intrinsics[0] if intrinsics else None
            every, by_name = _query_cameras(query_cameras)
            if inliers is not None:
                by_name.setdefault(inliers[0], inliers[2])

            def query_intrinsics(name: str) -> Any:
                camera = by_name.get(name, every)
                return _intrinsics(camera) if camera is not None else default

            drawn: set = set()
            thinned = False
            for kind, path, colour in (("estimate", poses, ESTIMATE_COLOR), ("truth", gt, TRUTH_COLOR)):
                if not path:
                    continue
                read = sfpmap.read_poses(path)
                if kind == "estimate":
                    estimated = dict(read)
                else:
                    truth = dict(read)
                names = [n for n, _ in read]
                rotations, centres = _worlds_from_cams([p for _, p in read])
                # Thinned by name: past MAX_CAMERAS estimates, the truths drawn are those of
                # the estimates drawn.
                if kind == "estimate" or not thinned:
                    drawn = {names[i] for i in _spread(len(names), MAX_CAMERAS)}
                    thinned = len(drawn) < len(names)
                for i, name in enumerate(names):
                    if name in drawn:
                        _frustum(rr, rec, f"world/queries/{_entity_part(name)}/{kind}",
                                 rotations[i], centres[i], query_intrinsics(name), depth, colour)
                setattr(summary, "estimates" if kind == "estimate" else "truths", len(names))
            if poses and gt:
                both = [n for n in estimated if n in truth]
                if both:
                    _, a = _worlds_from_cams([estimated[n] for n in both])
                    _, b = _worlds_from_cams([truth[n] for n in both])
                    rec.log("world/errors", rr.LineStrips3D(np.stack([a, b], axis=1), colors=ERROR_COLOR), static=True)
                    summary.errors = len(both)
            if inliers is not None:
                summary.inliers = _inliers(rr, rec, inliers, depth)
            if trajectory:
                summary.trajectory = _trajectory(rr, rec, read_tum(trajectory))
        rec.flush()
        rec.disconnect()
        # As every file sfpmap writes: the umask's mode, not mkstemp's 0600.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(temp, 0o666 & ~umask)
        os.replace(temp, out)
    except BaseException:
        try:
            os.unlink(temp)
        except FileNotFoundError:
            pass
        raise
    return summary


def _inliers(rr: Any, rec: Any, inliers: Tuple[str, Any, Any], depth: float) -> int:
    name, found, camera = inliers
    if not found.success:
        raise sfpmap.LocalizeError(f"query {name!r} was not localized: {found.failure}")
    pixels, points = found.inlier_pixels, found.inlier_points
    rotation, centre = world_from_cam(found.colmap)
    base = f"world/queries/{_entity_part(name)}"
    _frustum(rr, rec, f"{base}/estimate", rotation, centre, _intrinsics(camera), depth, ESTIMATE_COLOR)
    rec.log(f"{base}/inliers/points", rr.Points3D(points, colors=ESTIMATE_COLOR), static=True)
    rec.log(f"{base}/inliers/links", rr.LineStrips3D([[p, centre] for p in points], colors=(255, 160, 160)), static=True)
    rec.log(f"{base}/estimate/keypoints", rr.Points2D(pixels, colors=ESTIMATE_COLOR), static=True)
    return int(len(points))


def _trajectory(rr: Any, rec: Any, frames: Tuple[np.ndarray, np.ndarray, np.ndarray]) -> int:
    stamps, rotations, centres = frames
    if not len(stamps):
        return 0
    # Stamps from a ROS log or a clock are Unix times (shown as dates); a sequence's own
    # (KITTI's, from 0) are seconds from its start. Sent as columns: one chunk, however long.
    if stamps.min() >= UNIX_STAMPS_FROM:
        time = rr.TimeColumn("time", timestamp=stamps)
    else:
        time = rr.TimeColumn("time", duration=stamps)
    rec.send_columns(
        "world/trajectory/camera",
        indexes=[rr.TimeColumn("frame", sequence=np.arange(len(stamps))), time],
        columns=rr.Transform3D.columns(translation=centres, mat3x3=rotations),
    )
    rec.log("world/trajectory/camera", rr.TransformAxes3D(_scene_scale(centres)), static=True)
    rec.log("world/trajectory/path", rr.LineStrips3D([centres], colors=(255, 255, 255)), static=True)
    return int(len(stamps))


def _query_features(args: argparse.Namespace, m: sfpmap.Map, name: str) -> Any:
    if args.database:
        found = sfpmap.QueryDatabase(args.database).features(name)
        if found is None:
            raise sfpmap.InputError(f"{args.database}: no features for query {name!r}")
        return found
    if not args.images:
        raise sfpmap.InputError("--inliers needs the query's features: --images DIR or --database DB")
    # As `localize --images` extracts: the map's own built-in model (or the file named), the
    # global descriptor at the side the map's were computed at (absent: the network input).
    if not m.levels:
        raise sfpmap.InputError(f"{args.map}: a map without levels has no features to match")
    model = args.model or m.levels[0].descriptor
    side = m.metadata.get("global_max_side") or 0
    return sfpmap.Extractor(model).extract(os.path.join(args.images, name), global_max_side=side)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sfpmap.viz", description=__doc__.splitlines()[0])
    parser.add_argument("map", help="the map: a file or an http(s):// or s3:// URL")
    parser.add_argument("-o", "--out", required=True, help="the recording (.rrd)")
    parser.add_argument("--poses", help="localized poses: 'name qw qx qy qz tx ty tz' lines")
    parser.add_argument("--gt", help="ground-truth poses, the same lines")
    parser.add_argument("--trajectory", help="a sequence's poses as TUM lines")
    parser.add_argument("--inliers", metavar="NAME", help="draw this query's inlier links (localized here)")
    parser.add_argument("--query-list", help="queries with their cameras ('name MODEL W H params...'): their frusta, and --inliers")
    parser.add_argument("--camera", help="one camera for every query ('MODEL W H params...')")
    parser.add_argument("--images", help="query images (SFP maps: features extracted here)")
    parser.add_argument("--database", help="a COLMAP database with the queries' features (SIFT maps)")
    parser.add_argument("--model", help="with --images: the model file the map was made with (default: its built-in model)")
    parser.add_argument("--max-points", type=int, help="at most this many points per level (1 or more)")
    parser.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    parser.add_argument("--json", action="store_true", help="print what was recorded as JSON")
    args = parser.parse_args(argv)
    try:
        named = [p for p in (args.query_list, args.database, args.images) if p]
        if os.path.lexists(args.out) and any(os.path.exists(p) and os.path.samefile(p, args.out) for p in named):
            raise sfpmap.InputError(f"{args.out}: is one of the inputs")
        links = None
        if args.inliers:
            links = _localize_one(args)
        cameras: Any = None
        if args.query_list:
            cameras = dict(sfpmap.read_queries(args.query_list, args.camera))
        elif args.camera:
            cameras = sfpmap.Camera.parse(args.camera)
        summary = record(args.map, args.out, poses=args.poses, gt=args.gt, trajectory=args.trajectory,
                         inliers=links, query_cameras=cameras, max_points=args.max_points, force=args.force)
    except KeyboardInterrupt:
        return 130
    except Exception as e:  # one line, whatever failed (the CLI shows it after OUT's name)
        print(f"error: {e}", file=sys.stderr)
        return 1
    if args.json:
        import json

        print(json.dumps({"out": args.out, **summary.as_dict()}))
    return 0


def _localize_one(args: argparse.Namespace) -> Tuple[str, Any, Any]:
    name = args.inliers
    camera = None
    if args.query_list:
        cameras = dict(sfpmap.read_queries(args.query_list, args.camera))
        if name not in cameras:
            raise sfpmap.InputError(f"{args.query_list}: no query {name!r}")
        camera = cameras[name]
    elif args.camera:
        camera = sfpmap.Camera.parse(args.camera)
    else:
        raise sfpmap.InputError("--inliers needs the query's camera: --query-list or --camera")
    with sfpmap.Map(args.map) as m:
        found = sfpmap.Localizer(m, keep_inliers=True).localize(_query_features(args, m, name), camera, name=name)
    return name, found, camera


if __name__ == "__main__":
    sys.exit(main())
