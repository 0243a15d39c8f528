"""sfpmap: small, mmap-able visual-localization maps, from Python.

Open a map by mmap and read its sections as numpy views (no copy), convert COLMAP models
(files or a pycolmap ``Reconstruction``) into maps, slice them, extract SFP features and
localize queries. The work runs in Rust with the GIL released.

>>> import sfpmap
>>> with sfpmap.Map("south-building.sfpm") as m:
...     loc = sfpmap.Localizer(m)
...     # the map's own model (a built-in name) and global descriptor size
...     model = m.metadata["levels"][0]["descriptor"]
...     side = m.metadata.get("global_max_side", 0)
...     f = sfpmap.Extractor(model).extract("query.jpg", global_max_side=side)
...     r = loc.localize(f, "SIMPLE_RADIAL 1024 768 850 512 384 0")
...     print(r.cam_from_world)

Threads: ``Map``, ``Localizer``, ``Extractor``, ``FeaturesFile`` and ``QueryDatabase`` may be
shared between threads. ``Localizer.localize`` runs concurrently from several Python threads;
``Localizer.localize_many`` runs a batch on Rust threads (a ``Localizer(map, sequence=True)``
takes its queries one at a time, in order). An ``Extractor`` runs one image at a
time (concurrent calls take turns).

Zero copy: ``Map`` views (``map.points.positions``, ``map.levels[l].short``, ...) are read-only
numpy arrays over the mapping whose ``base`` keeps it alive; ``Map.close()`` makes the
``Map`` refuse further calls, and the file is unmapped when the last view is gone. Views of raw
sections are O(1) and unchecked (``Map.verify()`` checks every checksum); a zstd section is
checked and decoded once, on first access, and shared by later views.

The mmap contract: views are read-only views of the file itself, not copies. sfpmap never
writes onto a file it reads (``convert``, ``slice`` and the rest write a temporary file and
rename it over the output), so a map replaced that way leaves existing views on the old
contents. But a map truncated or rewritten in place by another program while a ``Map``, a
view or a ``Localizer`` of it is alive can crash the process (``SIGBUS`` on reading a page
that is gone) or change what views hold, as with any mmap: replace maps by renaming a new
file over them.

Errors are ``sfpmap.Error`` subclasses whose text is the CLI's one-line message without its
``error: `` prefix.
"""

from __future__ import annotations

import json as _json
import os as _os
from functools import cached_property as _cached_property
from typing import Any, Dict, Iterable, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as _np

from . import _sfpmap
from ._sfpmap import (  # noqa: F401  (re-exported)
    Camera,
    ClosedError,
    ConvertError,
    Error,
    ExtractError,
    Features,
    FeaturesFile,
    FileError,
    InputError,
    LocalizeError,
    MapError,
    NoSuchLevelError,
    QueryDatabase,
    __version__,
    pinhole_intrinsics,
    read_poses,
    read_queries,
)

__all__ = [
    "Camera",
    "ClosedError",
    "ConvertError",
    "Error",
    "ExtractError",
    "Extractor",
    "Features",
    "FeaturesFile",
    "FileError",
    "Images",
    "InputError",
    "Level",
    "Levels",
    "Localization",
    "LocalizeError",
    "Localizer",
    "Map",
    "MapError",
    "NoSuchLevelError",
    "Points",
    "QueryDatabase",
    "Visibility",
    "convert",
    "from_pycolmap",
    "read_features_h5",
    "pinhole_intrinsics",
    "read_poses",
    "read_queries",
    "slice",
]

PathLike = Union[str, "_os.PathLike[str]"]


class Points:
    """The map's 3D points: ``positions`` (N×3 float32, relative to ``origin``; ``None`` in a
    ``minimal`` slice, which stores ``positions_q16``), ``colors`` (N×3 uint8), ``ids`` (N
    uint64, COLMAP ``point3D_id``), each a view or ``None``. ``relative()`` and ``world()``
    decode the positions of every map, a ``minimal`` one's included."""

    def __init__(self, map: "Map") -> None:
        self._map = map

    @property
    def positions(self) -> Optional[_np.ndarray]:
        return self._map._section("point_positions")

    @property
    def positions_q16(self) -> Optional[_np.ndarray]:
        """A ``minimal`` slice's positions (N×3 uint16 on ``metadata["position_grid"]``),
        stored instead of ``positions``."""
        return self._map._section("point_positions_q16")

    @property
    def colors(self) -> Optional[_np.ndarray]:
        return self._map._section("point_colors")

    @property
    def ids(self) -> Optional[_np.ndarray]:
        return self._map._section("point_ids")

    @property
    def origin(self) -> Tuple[float, float, float]:
        return self._map.origin

    def relative(self) -> _np.ndarray:
        """Positions relative to ``origin`` (N×3 float32, a copy), whichever way the map
        stores them: ``positions``, or a ``minimal`` map's ``positions_q16`` decoded from its
        grid. Checked as the library reads them."""
        return self._map._point_positions(False)

    def world(self) -> _np.ndarray:
        """World coordinates (N×3 float64, a copy): ``relative() + origin``, for every map
        (a ``minimal`` one's 16-bit grid decoded)."""
        return self._map._point_positions(True)

    def __len__(self) -> int:
        return int(self._map.n_points)


class Level:
    """One level: ``points`` (global point indices, uint32), ``short`` / ``rest`` descriptor
    blocks (float16, rows × dims; ``rest`` is ``None`` in a short slice), ``projection``
    (float32 dim_full × d_in, or ``None``). Views, no copies."""

    def __init__(self, map: "Map", level: int) -> None:
        self._map = map
        self.id = level
        (
            self.n_points,
            self.dim_short,
            self.dim_full,
            self.has_rest,
            self.has_descriptors,
            self.descriptor,
            self.stride,
        ) = map._level_info(level)

    @property
    def points(self) -> _np.ndarray:
        return self._map._section("level_points", self.id)

    @property
    def short(self) -> Optional[_np.ndarray]:
        return self._map._section("level_desc_short", self.id)

    @property
    def rest(self) -> Optional[_np.ndarray]:
        return self._map._section("level_desc_rest", self.id)

    @property
    def projection(self) -> Optional[_np.ndarray]:
        return self._map._section("level_projection", self.id)

    @property
    def pq_codes(self) -> Optional[_np.ndarray]:
        """A product-quantised level's codes (rows × M uint8), or ``None``."""
        return self._map._section("level_pq_codes", self.id)

    @property
    def pq_codebook(self) -> Optional[_np.ndarray]:
        """A product-quantised level's codebook (float32), or ``None``."""
        return self._map._section("level_pq_codebook", self.id)

    @property
    def pq_order(self) -> Optional[_np.ndarray]:
        """The level dimension at each quantised position (uint16), or ``None`` (the identity,
        or not product-quantised)."""
        order = self._map._section("level_pq_order", self.id)
        if order is None:
            return None
        order = order.reshape(-1)
        # The raw view skips the library's first-access check: a map whose order is not a
        # permutation is refused here as it is when the library reads the level.
        if not _np.array_equal(_np.sort(order), _np.arange(len(order))):
            raise MapError(f"level {self.id}: level_pq_order is not a permutation of 0..{len(order)}")
        return order

    def __len__(self) -> int:
        return int(self.n_points)

    def __repr__(self) -> str:
        return (
            f"sfpmap.Level({self.id}, {self.n_points} points, {self.descriptor!r}, "
            f"dims {self.dim_short}/{self.dim_full}, rest {'present' if self.has_rest else 'absent'})"
        )


class Levels:
    """The map's levels by id: ``levels[2]`` is level 2 (``NoSuchLevelError`` if absent);
    iterating yields ``Level`` objects in ascending id order; ``ids`` lists the ids."""

    def __init__(self, map: "Map") -> None:
        self._map = map

    @property
    def ids(self) -> List[int]:
        return list(self._map.level_ids)

    def __getitem__(self, level: int) -> Level:
        """Level ``level``; ``NoSuchLevelError`` if the map has none (any int, negative or
        past 65535 included)."""
        return Level(self._map, level)

    def __iter__(self) -> Iterator[Level]:
        return (Level(self._map, i) for i in self._map.level_ids)

    def __len__(self) -> int:
        return len(self._map.level_ids)

    def __contains__(self, level: object) -> bool:
        return level in self._map.level_ids


class Images:
    """The map's database images: ``names`` (list of str), ``poses`` (N×7 float64,
    ``cam_from_world`` as qw qx qy qz tx ty tz), ``cameras`` (N uint32, index into
    ``Map.cameras``), ``ids`` (COLMAP ``image_id``), ``global_descriptors`` (N×d float16).
    ``index(name)`` is an image's index. Names are read once (``Map.images`` is one object
    per map)."""

    def __init__(self, map: "Map") -> None:
        self._map = map
        self._names: Optional[List[str]] = None
        self._index: Optional[Dict[str, int]] = None

    @property
    def names(self) -> List[str]:
        if self._names is None:
            self._names = self._map._image_names() or []
        return self._names

    def index(self, name: str) -> int:
        """The index of the image ``name`` (in ``names``, ``poses``, ...); ``ValueError`` if
        the map has no such image, as ``list.index``. O(1) after the first call."""
        if self._index is None:
            index: Dict[str, int] = {}
            for i, n in enumerate(self.names):
                index.setdefault(n, i)
            self._index = index
        try:
            return self._index[name]
        except KeyError:
            raise ValueError(f"{name!r}: no such image in the map") from None

    @property
    def poses(self) -> _np.ndarray:
        return self._map._section("image_poses")

    @property
    def cameras(self) -> _np.ndarray:
        return self._map._section("image_cameras")

    @property
    def ids(self) -> Optional[_np.ndarray]:
        return self._map._section("image_ids")

    @property
    def global_descriptors(self) -> Optional[_np.ndarray]:
        return self._map._section("image_global")

    def __len__(self) -> int:
        return int(self._map.n_images)


class Visibility:
    """Image → points in CSR form: image ``i`` sees ``points[offsets[i]:offsets[i+1]]``
    (uint64 offsets, uint32 point indices), at pixels ``keypoints`` (M×2 float32) if stored."""

    def __init__(self, map: "Map") -> None:
        self._map = map

    @property
    def offsets(self) -> _np.ndarray:
        return self._map._section("visibility_offsets")

    @property
    def points(self) -> _np.ndarray:
        return self._map._section("visibility_points")

    @property
    def keypoints(self) -> Optional[_np.ndarray]:
        return self._map._section("visibility_keypoints")

    def points_of(self, image: int) -> _np.ndarray:
        o = self.offsets
        return self.points[int(o[image]) : int(o[image + 1])]


class Map(_sfpmap._Map):
    """An open map (``Map(path)``): memory-mapped, only its index and metadata read.

    A context manager; ``close()`` ends this object's use of the file (views already made
    keep the mapping alive until they are gone). Section views are read-only numpy arrays
    over the mapping, see the module docs."""

    @_cached_property
    def points(self) -> Points:
        return Points(self)

    @_cached_property
    def levels(self) -> Levels:
        return Levels(self)

    def level(self, level: int) -> Level:
        return Level(self, level)

    @_cached_property
    def images(self) -> Optional[Images]:
        """The database images (one object per map, so names are read once), or ``None``."""
        return Images(self) if self._section("image_poses") is not None else None

    @_cached_property
    def visibility(self) -> Optional[Visibility]:
        return Visibility(self) if self._section("visibility_offsets") is not None else None

    @_cached_property
    def metadata(self) -> Dict[str, Any]:
        """The metadata block (a dict parsed from its JSON once; every access returns that
        same dict, so copy it before changing it)."""
        return _json.loads(self._metadata_json())

    @property
    def cameras(self) -> List[Dict[str, Any]]:
        """The metadata cameras (``model``, ``width``, ``height``, ``params``), from the
        parsed ``metadata``."""
        return self.metadata.get("cameras", [])

    def section(self, kind: str, level: Optional[int] = None) -> Optional[_np.ndarray]:
        """A view of any section by its spec name (``"image_vlad"``, ...), or ``None`` if the
        map has none or this version skips it (a later minor's encoding it does not know).
        ``InputError`` for a name that is no section kind of the spec."""
        return self._section(kind, level)

    def info(self) -> Dict[str, Any]:
        """What ``sfpmap info --json`` prints for this map."""
        return _json.loads(self._info_json())

    def __enter__(self) -> "Map":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Localization:
    """One query's result: ``success``; ``cam_from_world`` (4×4 float64, or ``None``),
    ``quaternion`` (w, x, y, z) and ``translation``; ``colmap`` (qw qx qy qz tx ty tz);
    ``inliers``, ``inliers_per_level`` ({level: n}), ``matches``, ``retrieved`` (image
    indices) and ``retrieved_names``, ``retrieved_images`` (how many retrieval gave),
    ``path``, ``tracking_lost``, ``retrieval``, ``retrieval_fallback``, ``times`` (ms per
    stage) and ``failure`` (why not localized, or ``None``). Names as the CLI's JSON has
    them where it has them."""

    __slots__ = ("_r",)

    def __init__(self, r: Any) -> None:
        self._r = r

    @property
    def success(self) -> bool:
        return bool(self._r.success)

    @property
    def colmap(self) -> Optional[List[float]]:
        c = self._r.colmap
        return list(c) if c is not None else None

    @property
    def cam_from_world(self) -> Optional[_np.ndarray]:
        m = self._r._matrix
        return _np.array(m, dtype=_np.float64) if m is not None else None

    @property
    def quaternion(self) -> Optional[_np.ndarray]:
        """``cam_from_world`` rotation as (w, x, y, z)."""
        c = self._r.colmap
        return _np.array(c[:4]) if c is not None else None

    @property
    def translation(self) -> Optional[_np.ndarray]:
        c = self._r.colmap
        return _np.array(c[4:]) if c is not None else None

    @property
    def failure(self) -> Optional[str]:
        return self._r.failure

    @property
    def inliers(self) -> int:
        return int(self._r.inliers)

    @property
    def inliers_per_level(self) -> Dict[int, int]:
        return dict(self._r.inliers_per_level)

    @property
    def matches(self) -> int:
        return int(self._r.matches)

    @property
    def retrieved(self) -> List[int]:
        return list(self._r.retrieved)

    @property
    def retrieved_names(self) -> List[str]:
        return list(self._r.retrieved_names)

    @property
    def retrieved_images(self) -> int:
        return int(self._r.retrieved_images)

    @property
    def path(self) -> str:
        return self._r.path

    @property
    def tracking_lost(self) -> Optional[str]:
        return self._r.tracking_lost

    @property
    def retrieval(self) -> Optional[str]:
        return self._r.retrieval

    @property
    def retrieval_fallback(self) -> Optional[str]:
        return self._r.retrieval_fallback

    @property
    def times(self) -> Dict[str, float]:
        keys = ("retrieval", "coarse_match", "coarse_ransac", "fine", "total")
        return dict(zip(keys, self._r._times))

    @property
    def covariance(self) -> Optional[_np.ndarray]:
        """How sure the pose is: the 6×6 covariance of the camera's pose in the world (its
        centre's x, y, z, then small rotations about the world's x, y, z axes; map units and
        radians), from the geometry of the final inliers; ``None`` without one."""
        c = self._r._covariance
        return None if c is None else _np.array(c, dtype=_np.float64).reshape(6, 6)

    @property
    def inlier_pixels(self) -> _np.ndarray:
        """N×2 keypoints of the final inliers (``Localizer(keep_inliers=True)``; else 0×2)."""
        return _np.array(self._r._inlier_links[0], dtype=_np.float64).reshape(-1, 2)

    @property
    def inlier_points(self) -> _np.ndarray:
        """N×3 world points the inlier keypoints matched (``keep_inliers=True``)."""
        return _np.array(self._r._inlier_links[1], dtype=_np.float64).reshape(-1, 3)

    @property
    def inlier_levels(self) -> _np.ndarray:
        """N levels the inlier matches were made on (``keep_inliers=True``)."""
        return _np.array(self._r._inlier_links[2], dtype=_np.uint16)

    def to_pycolmap(self) -> Any:
        """``cam_from_world`` as a ``pycolmap.Rigid3d`` (``None`` if not localized)."""
        import pycolmap

        c = self._r.colmap
        if c is None:
            return None
        qw, qx, qy, qz, tx, ty, tz = c
        rotation = pycolmap.Rotation3d(_np.array([qx, qy, qz, qw]))
        return pycolmap.Rigid3d(rotation, _np.array([tx, ty, tz]))

    def __repr__(self) -> str:
        if self.success:
            return f"sfpmap.Localization(colmap={self.colmap}, inliers={self.inliers})"
        return f"sfpmap.Localization(failure={self.failure!r})"


FeaturesLike = Union[Features, Tuple[Any, Any], Dict[Optional[int], Tuple[Any, Any]]]
CameraLike = Union[Camera, str, Dict[str, Any], Any]


class Localizer:
    """A map prepared for localization (built once, shared by threads).

    Options as the CLI's ``localize``: ``levels`` (default all; coarse matching uses the
    deepest), ``short`` (match the short block only), ``top_k``, ``retrieval`` ("auto",
    "vlad", "global", "off"), ``retrieval_probe`` (lists of the map's image index a query
    scores; 0: every image), ``ratio`` (default the map's: 0.95 on SFP maps, 0.9 on SIFT
    maps); and the localizer's ``mutual``, ``min_similarity``,
    ``coarse_error_px``, ``gate_px``, ``gate_ratio``, ``fine_error_px``, ``min_inliers``.
    An option left out (``None``) is the library's default for the map, the one the CLI and
    the C ABI (``sfpm_session_options_default``) start from.
    The library checks them (as for the CLI and the C ABI): one out of range is an
    ``InputError`` in its words (``"top_k 0: 1 to 100000 images"``); a level the map lacks
    is a ``NoSuchLevelError``.

    ``sequence=True``: the queries are an ordered sequence (a camera moving), as the CLI's
    ``localize --sequence``. Each is localized by guided matching around the pose predicted
    from the last ones (``Localization.path == "tracking"``), through retrieval only when
    tracking is lost or before the first pose. ``localize`` calls then take turns, in the
    order they are made; ``localize_many`` runs its queries on one thread, in order.
    ``is_tracking`` says whether the next query has a prediction; ``reset_tracking()``
    forgets the motion (a cut in the sequence).

    ``keep_inliers=True``: each ``Localization`` keeps its final inliers
    (``inlier_pixels``, ``inlier_points``, ``inlier_levels``), e.g. for ``sfpmap.viz``.

    Features that record their model (``Extractor.extract``'s, those of a ``FeaturesFile``
    made by ``sfpmap extract``) must be of the map's model: others raise ``LocalizeError``,
    naming both. Features made from arrays are taken as they are.

    The localizer keeps the map's mapping alive (closing the ``Map`` does not end it)."""

    def __init__(self, map: Map, **options: Any) -> None:
        self._inner = _sfpmap._Localizer(map, **options)

    @property
    def level_order(self) -> List[int]:
        return list(self._inner.level_order)

    @property
    def skipped_levels(self) -> List[Tuple[int, str]]:
        return list(self._inner.skipped_levels)

    @property
    def sequence(self) -> bool:
        """Whether the queries are an ordered sequence (``sequence=True``)."""
        return bool(self._inner.sequence)

    @property
    def is_tracking(self) -> bool:
        """Whether the sequence predicts the next query's pose (it localized the last one);
        always ``False`` outside a sequence."""
        return bool(self._inner.is_tracking)

    def reset_tracking(self) -> None:
        """Forgets the sequence's motion: the next query goes through retrieval. Nothing
        outside a sequence."""
        self._inner.reset_tracking()

    def localize(
        self,
        features: FeaturesLike,
        camera: CameraLike,
        global_descriptor: Optional[Sequence[float]] = None,
        name: str = "query",
    ) -> Localization:
        """Localizes one query. ``features``: ``Features`` (from ``Extractor.extract``,
        ``FeaturesFile``, ``QueryDatabase``), ``(keypoints (n, 2), descriptors (n, d))`` for
        every level, or ``{level: (keypoints, descriptors)}``. ``camera``: ``Camera``,
        ``"MODEL W H params..."``, a dict or a ``pycolmap.Camera``. A query that is not
        localized gives ``success == False``; unusable input raises ``LocalizeError``
        (features of another model than the map's, descriptors of another size) or
        ``InputError`` (arrays or a camera that cannot be read)."""
        g = None if global_descriptor is None else [float(x) for x in global_descriptor]
        return Localization(self._inner.localize(features, camera, g, name))

    def localize_many(
        self, queries: Iterable[Sequence[Any]], threads: Optional[int] = None
    ) -> List[Localization]:
        """Localizes an iterable of ``(features, camera)`` or ``(features, camera, name)`` on
        ``threads`` Rust threads (GIL released); results in input order. ``threads``:
        default the machine's available parallelism; 0 is an ``InputError``; more than 4 per
        core (or 256) is capped, with a ``RuntimeWarning``, as the CLI caps ``--threads``.
        A sequence's queries run on one thread, in order."""
        return [Localization(r) for r in self._inner.localize_many(queries, threads)]


class Extractor:
    """The SFP extractor (``model=None``: the embedded sfp-v3). ONNX Runtime is found or
    fetched as the CLI does (``ORT_DYLIB_PATH``, the cache, ``sfpmap setup``). ``threads``
    as the CLI's ``--threads``: at least 1, capped at 4 per core (at most 256) with a
    ``RuntimeWarning``."""

    def __init__(self, model: Optional[PathLike] = None, threads: int = 2) -> None:
        self._inner = _sfpmap._Extractor(None if model is None else _os.fspath(model), threads)

    @property
    def descriptor(self) -> str:
        return self._inner.descriptor

    def extract(
        self,
        image: Union[PathLike, _np.ndarray],
        resize_max: Optional[int] = None,
        threshold: Optional[float] = None,
        nms_radius: Optional[int] = None,
        max_keypoints: Optional[Sequence[int]] = None,
        refine: bool = True,
        global_max_side: Optional[int] = None,
    ) -> Features:
        """Per-level keypoints and descriptors (and the global descriptor) of an image file
        or a uint8 / [0, 1] float array (H×W grey or H×W×3 RGB). ``refine``: the keypoints'
        refinement, coarse to fine for levels 2+ and on the image for an sfp-extractor/2 model
        (``extract --no-refine`` is ``False``).
        ``global_max_side``: the global descriptor is computed on a copy at most this large
        (``None``: 512; 0: the network input; else at least 16); a map's queries need the
        map's (``Map.metadata.get("global_max_side", 0)``)."""
        if not isinstance(image, _np.ndarray):
            image = _os.fspath(image)
        mk = None if max_keypoints is None else [int(k) for k in max_keypoints]
        return self._inner.extract(
            image,
            resize_max,
            threshold,
            nms_radius,
            mk,
            bool(refine),
            None if global_max_side is None else int(global_max_side),
        )


def read_features_h5(path: PathLike) -> FeaturesFile:
    """hloc's ``features.h5`` (or ``sfpmap extract``'s): ``.features(name)`` per image."""
    return FeaturesFile(_os.fspath(path))


def convert(
    model_dir: Optional[PathLike] = None,
    database: Optional[PathLike] = None,
    images: Optional[PathLike] = None,
    out: Optional[PathLike] = None,
    *,
    kapture: Optional[PathLike] = None,
    **options: Any,
) -> Dict[str, Any]:
    """``sfpmap convert``: a COLMAP model folder into the map ``out`` (a SIFT map with
    ``database``, an SFP map with ``images``, else geometry only), or with ``kapture`` instead
    of ``model_dir`` a kapture folder (``convert --kapture``: its model and its own keypoints
    and descriptors, chosen by ``keypoints_type``/``descriptors_type`` where it has several;
    none: a geometry map). ``options`` are the CLI's flags (``force``, ``codec``,
    ``short_dims``, ``aggregate``, ``vlad_clusters``, ``index_lists``, ``pq``, ``model``, ``resize_max``,
    ``threads``, ``feature_name``, ...), checked as the CLI checks them: ``images`` with
    ``database``, ``short_dims``, ``aggregate`` or ``strict``, both or neither of
    ``model_dir`` and ``kapture``, ``kapture`` with ``database``, ``images`` or ``features``
    are the CLI's ``InputError``; as the CLI, a file already inside the kapture folder is an
    input, refused as ``out`` even with ``force``. ``job`` (a dict; no CLI flag) is kept in
    the map's ``provenance.parameters.job``: ``sfpmap.batch`` records a place's input
    fingerprint there. ``memory`` (bytes, ``--memory``) bounds what a conversion from a
    database or features file uses; the map is the same bytes whatever it is.
    Returns what ``convert --json`` prints."""
    if out is None:
        raise InputError("out: the map to write")
    if options.get("job") is not None:
        options["job"] = _json.dumps(options["job"])
    return _json.loads(
        _sfpmap.convert(
            None if model_dir is None else _os.fspath(model_dir),
            None if database is None else _os.fspath(database),
            None if images is None else _os.fspath(images),
            out=_os.fspath(out),
            kapture=None if kapture is None else _os.fspath(kapture),
            **options,
        )
    )


def slice(
    map_path: PathLike,
    levels: Sequence[int],
    short: bool = False,
    out: Optional[PathLike] = None,
    **options: Any,
) -> Dict[str, Any]:
    """``sfpmap slice``: keep ``levels`` (and with ``short`` only their short blocks) of a
    map, written to ``out``. Options as the CLI's flags: ``minimal`` (only what localization
    reads, positions on a 16-bit grid), ``pq`` (M one-byte codes per point), ``short_dims``
    (with ``short``: N dimensions of each level's own PCA basis), ``codec``,
    ``zstd_level``, ``force``; or ``budget`` (bytes: ``slice --budget``, which chooses the rest;
    ``levels`` may then be empty). Returns what ``slice --json`` prints."""
    if out is None:
        raise InputError("out: the map to write")
    return _json.loads(
        _sfpmap.slice(_os.fspath(map_path), [int(x) for x in levels], short, out=_os.fspath(out), **options)
    )


def from_pycolmap(
    reconstruction: Any,
    database: Optional[PathLike] = None,
    images: Optional[PathLike] = None,
    out: Optional[PathLike] = None,
    **options: Any,
) -> Dict[str, Any]:
    """``convert`` of a ``pycolmap.Reconstruction`` in memory (no temp files). The map equals
    ``sfpmap convert`` of the same model's files except for provenance, which records
    ``source`` (default ``"pycolmap.Reconstruction"``) and lists no model files. An object
    that is not a reconstruction (a missing attribute, a value of the wrong type) is a
    ``ConvertError`` whose ``__cause__`` is Python's error."""
    if out is None:
        raise InputError("out: the map to write")
    return _json.loads(
        _sfpmap.from_pycolmap(
            reconstruction,
            None if database is None else _os.fspath(database),
            None if images is None else _os.fspath(images),
            out=_os.fspath(out),
            **options,
        )
    )
