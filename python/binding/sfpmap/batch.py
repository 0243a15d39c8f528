"""``python -m sfpmap.batch MANIFEST --out PREFIX``: many places' COLMAP models into sfpmap maps
and a catalog, on a Ray cluster (``pip install 'sfpmap[ray]'``). The guide's page "Building a
city on Ray" says what it does for a user; this is how.

MANIFEST is JSON lines, one place each (a local file or an ``s3://``/``http(s)://`` URL)::

    {"place": "hall-a", "colmap": "s3://in/hall-a/sparse", "database": "s3://in/hall-a/database.db",
     "variants": ["l2s", "pq8"], "budget": "2MB"}

or an ``s3://`` prefix ending in ``/``, whose folders are the places (``<place>/sparse/`` and
``<place>/database.db`` or ``<place>/images/``).

The driver reads the manifest (a bad line is a failed row, never the end of the job), then keeps
at most a few tasks per CPU of the cluster in flight. Each task (:func:`run_place`) lists its
place's inputs, fingerprints them with its options, and skips the place when every output already
carries that fingerprint (``provenance.parameters.job``, or ``provenance.history`` for a slice);
else it fetches remote inputs into a work folder, converts, slices and stores each output whole
(an S3 PUT or completed multipart upload; in a folder, a rename from ``PREFIX/.sfpmap-batch-tmp``).
Ray retries a task whose worker or node is lost; a place's own error is its row's one line. Last,
``PREFIX/catalog.sfpc`` is rewritten when its places or their fingerprints changed.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import importlib
import json
import logging
import math
import os
import posixpath
import re
import resource
import shutil
import sys
import tempfile
import time
from typing import Any, Callable, Dict, List, Optional, Tuple

from . import Error as _SfpmapError
from . import MapError as _MapError
from . import __version__
from . import convert as _convert
from . import slice as _slice

# The compiled half (object storage, map metadata by URL, catalogs), untyped here.
_sfpmap: Any = importlib.import_module("sfpmap._sfpmap")

__all__ = ["main", "run", "run_place", "read_manifest", "parse_variant", "parse_size", "job_of"]

MANIFEST_KEYS = ("place", "colmap", "database", "images", "variants", "budget")
# The model files the library reads (src/colmap: cameras, images, points3D, .bin or .txt).
MODEL_FILES = tuple(f"{stem}.{ext}" for ext in ("bin", "txt") for stem in ("cameras", "images", "points3D"))
PLACE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}\Z")
RESERVED_NAMES = ("catalog.sfpc",)
VARIANT = re.compile(r"(?:l(?P<level>\d{1,5})(?P<short>s?)(?:-pq(?P<lpq>\d{1,4}))?|pq(?P<pq>\d{1,4}))(?P<min>-min)?\Z")
SIZE = re.compile(r"(?P<number>\d{1,19}(?:\.\d{1,9})?) ?(?P<unit>[kKMGT]?i?B?)\Z")
UNITS = {"": 1, "B": 1, "kB": 10**3, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
         "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}
MAP_NAME = "map.sfpm"
CATALOG_NAME = "catalog.sfpc"
# A local PREFIX's work folder: outputs are renamed from it into place (same file system).
TMP_NAME = ".sfpmap-batch-tmp"
# One input object at most (the work folder holds it; memory holds a piece at a time).
MAX_OBJECT_BYTES = 1 << 40
MAX_FILES = 100_000
MAX_MANIFEST_BYTES = 256 << 20
MAX_ERROR_CHARS = 2000
STAGES = ("list", "fetch", "convert", "slice", "store")
PLACES_PER_WORKER = 16
FETCHES_IN_FLIGHT = 8
# Variables a task gets from the driver: configuration always, secrets on request.
SECRET = re.compile(r"KEY|SECRET|TOKEN|PASSWORD|CREDENTIAL")


def is_url(location: str) -> bool:
    return bool(_sfpmap.is_url(location))


def _scheme(location: str) -> str:
    return location.split("://", 1)[0].lower() if is_url(location) else ""


def _normal_url(url: str) -> str:
    """``url`` with its scheme in lower case and its path without ``.``, ``..`` or empty
    segments (listed keys come back that way); ``..`` above the bucket is refused."""
    scheme, rest = url.split("://", 1)
    origin, _, path = rest.partition("/")
    parts: List[str] = []
    for part in path.split("/"):
        if part in ("", "."):
            continue
        if part == "..":
            if not parts:
                raise ValueError(f"{url[:300]}: .. above {scheme.lower()}://{origin}")
            parts.pop()
        else:
            parts.append(part)
    return f"{scheme.lower()}://{origin}/" + "/".join(parts) + ("/" if path.endswith("/") and parts else "")


def one_line(e: BaseException) -> str:
    text = (str(e) or type(e).__name__)[: MAX_ERROR_CHARS * 2]
    text = " ".join(text.split())
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS] + "..."


def parse_size(value: Any) -> int:
    """A byte count: an int, or text such as ``2MB``, ``500kB``, ``1.5MiB`` (1 to 2**63 - 1)."""
    if isinstance(value, int) and not isinstance(value, bool):
        n = value
    else:
        m = SIZE.match(value) if isinstance(value, str) else None
        if m is None or m["unit"] not in UNITS:
            raise ValueError(f"{value!r} is not a size such as 2MB, 500kB or 1.5MiB")
        x = float(m["number"]) * UNITS[m["unit"]]
        n = int(x) if math.isfinite(x) and x < 2**63 else -1
    if not 1 <= n < 2**63:
        raise ValueError(f"{value!r}: a budget is 1 to 2**63 - 1 bytes")
    return n


def parse_variant(name: Any) -> Dict[str, Any]:
    """What a variant name asks ``slice`` for: ``levels`` (None: every level), ``short``, ``pq``
    (1 to 4096), ``minimal``. Names: ``l<level>[s][-pq<M>][-min]`` or ``pq<M>[-min]``."""
    m = VARIANT.match(name) if isinstance(name, str) else None
    pq = None if m is None else (m["lpq"] or m["pq"])
    if m is None or (pq is not None and not 1 <= int(pq) <= 4096) or \
            (m["level"] is not None and int(m["level"]) > 65534):
        raise ValueError(f"variant {name!r}: l<level>[s][-pq<M>][-min] or pq<M>[-min] "
                         "(e.g. l2s, l2, pq8, l2s-pq8-min; M 1 to 4096)")
    return {
        "levels": None if m["level"] is None else [int(m["level"])],
        "short": bool(m["short"]),
        "pq": None if pq is None else int(pq),
        "minimal": m["min"] is not None,
    }


# ---------------------------------------------------------------------------------------------
# The manifest


def _resolve(value: Any, key: str, manifest_base: str) -> str:
    """A location of the manifest: a relative one against its folder. A manifest read from a URL
    may name only objects on its own server or bucket (as a catalog read from a URL may)."""
    if not isinstance(value, str) or not value or "\0" in value:
        raise ValueError(f"{key}: a path or URL")
    if is_url(manifest_base):
        origin = _normal_url(manifest_base).split("/", 3)[:3]
        if not is_url(value):
            if os.path.isabs(value):
                raise ValueError(f"{key} {value[:300]!r}: a manifest read from a URL names no local file")
            value = manifest_base.rstrip("/") + "/" + value
        value = _normal_url(value)
        if value.split("/", 3)[:3] != origin:
            raise ValueError(f"{key} {value[:300]!r}: a manifest read from a URL names only objects beside it "
                             f"({'/'.join(origin)})")
        return value
    if is_url(value):
        return _normal_url(value)
    if os.path.isabs(value):
        return value
    return os.path.normpath(os.path.join(manifest_base, value))


def _parse_line(obj: Any, line: int, base: str) -> Dict[str, Any]:
    if not isinstance(obj, dict):
        raise ValueError("not a JSON object")
    unknown = sorted(set(obj) - set(MANIFEST_KEYS))
    if unknown:
        raise ValueError(f"unknown key {unknown[0][:100]!r} (known: {', '.join(MANIFEST_KEYS)})")
    name = obj.get("place")
    if not isinstance(name, str) or not PLACE_NAME.match(name) or name in RESERVED_NAMES:
        raise ValueError("place: 1 to 128 of A-Z a-z 0-9 . _ -, starting with a letter or digit, "
                         f"not {', '.join(RESERVED_NAMES)}")
    if "colmap" not in obj:
        raise ValueError("no colmap: the place's COLMAP model folder")
    if ("database" in obj) == ("images" in obj):
        raise ValueError("give database (a feature map) or images (an SFP map), one of them")
    variants = obj.get("variants", [])
    if not isinstance(variants, list):
        raise ValueError("variants: a list such as [\"l2s\", \"pq8\"]")
    for v in variants:
        parse_variant(v)
    if len(set(variants)) != len(variants):
        raise ValueError("variants: a variant listed twice")
    return {
        "line": line,
        "place": name,
        "colmap": _resolve(obj["colmap"], "colmap", base),
        "database": _resolve(obj["database"], "database", base) if "database" in obj else None,
        "images": _resolve(obj["images"], "images", base) if "images" in obj else None,
        "variants": list(variants),
        "budget": None if obj.get("budget") is None else parse_size(obj["budget"]),
    }


def _row(place: str, line: Optional[int] = None) -> Dict[str, Any]:
    """A report row, failed until the place is done or skipped."""
    return {"place": place, "line": line, "status": "failed", "error": None, "bytes_in": 0,
            "bytes_out": 0, "seconds": {}, "outputs": []}


def _failed(place: str, error: str, line: Optional[int] = None) -> Dict[str, Any]:
    row = _row(place, line)
    row["error"] = error
    return row


def read_manifest(manifest: str) -> Tuple[List[Dict[str, Any]], List[Dict[str, Any]]]:
    """The places of ``manifest`` (a JSON lines file or URL, or an ``s3://`` prefix ending in
    ``/``) and a failed row for each line (or folder) that is not one. Raises ``sfpmap.Error``,
    ``OSError`` or ``ValueError`` when the manifest itself cannot be read."""
    if _scheme(manifest) == "s3" and manifest.endswith("/"):
        return _list_places(_normal_url(manifest))
    if is_url(manifest):
        with tempfile.TemporaryDirectory(prefix="sfpmap-manifest-") as tmp:
            path = os.path.join(tmp, "manifest.jsonl")
            _sfpmap.object_download(manifest, path, MAX_MANIFEST_BYTES)
            text = _read_text(path, manifest)
        base = manifest.rsplit("/", 1)[0]
    else:
        text = _read_text(manifest, manifest)
        base = os.path.dirname(os.path.abspath(manifest))
    places: List[Dict[str, Any]] = []
    failed: List[Dict[str, Any]] = []
    seen = set()
    # JSON lines end at "\n" only: U+2028 and friends may stand unescaped inside a string.
    for number, line in enumerate(text.split("\n"), 1):
        if not line.strip():
            continue
        where = f"{manifest}: line {number}"
        name = f"line {number}"
        try:
            obj = json.loads(line)
            given = obj.get("place") if isinstance(obj, dict) else None
            # Shown as given only when it is a place name (no control characters, bounded).
            if isinstance(given, str) and PLACE_NAME.match(given):
                name = given
            place = _parse_line(obj, number, base)
        except Exception as e:  # noqa: BLE001  (any bad line is that line's failure)
            if isinstance(e, json.JSONDecodeError):
                message = f"not JSON ({e.msg})"
            elif isinstance(e, ValueError):
                message = one_line(e)
            else:
                message = f"unreadable ({type(e).__name__})"
            failed.append(_failed(name, f"{where}: {message}", number))
            continue
        if place["place"] in seen:
            failed.append(_failed(name, f"{where}: place {name!r} is listed twice", number))
            continue
        seen.add(place["place"])
        places.append(place)
    return places, failed


def _read_text(path: str, shown: str) -> str:
    with open(path, "rb") as f:
        data = f.read(MAX_MANIFEST_BYTES + 1)
    if len(data) > MAX_MANIFEST_BYTES:
        raise ValueError(f"{shown}: a manifest over {MAX_MANIFEST_BYTES >> 20} MiB: split it")
    try:
        return data.decode("utf-8-sig")  # a byte order mark is not part of line 1
    except UnicodeDecodeError as e:
        raise ValueError(f"{shown}: not UTF-8 text (byte {e.start})") from None


def _list_places(prefix: str) -> Tuple[List[Dict[str, Any]], List[Dict[str, Any]]]:
    """The places under an ``s3://`` prefix: one per folder, listed by folder (not by object).
    A folder without a model or inputs fails in its task, naming what is missing; one whose
    name is no place name is a failed row here."""
    found: List[Dict[str, Any]] = []
    failed: List[Dict[str, Any]] = []
    for line, folder in enumerate(_sfpmap.object_list_folders(prefix, MAX_FILES), 1):
        name = folder[len(prefix):].rstrip("/")
        if not PLACE_NAME.match(name) or name in RESERVED_NAMES:
            failed.append(_failed(f"folder {line}", f"{folder[:300]}: not a place name (1 to 128 of "
                                  f"A-Z a-z 0-9 . _ -, not {', '.join(RESERVED_NAMES)})", line))
            continue
        database = f"{folder}database.db"
        has_database = _sfpmap.object_head(database) is not None
        found.append({"line": line, "place": name, "colmap": f"{folder}sparse",
                      "database": database if has_database else None,
                      "images": None if has_database else f"{folder}images",
                      "variants": [], "budget": None})
    return found, failed


# ---------------------------------------------------------------------------------------------
# One place (a Ray task)

Input = Tuple[str, str, int, str]  # (name in the work folder, path or URL, size, version)


def _checked_key(url: str) -> str:
    # Listed keys become URLs again: a character a URL reads otherwise would fetch another object.
    if any(c in url for c in "#?%"):
        raise ValueError(f"{url[:300]}: an object name with #, ? or %, which this job does not fetch")
    return url


def _objects(prefix: str) -> List[Tuple[str, int, str]]:
    """The objects under ``prefix``: URL, size and version (ETag, else Last-Modified)."""
    return [(url, size, etag or f"modified {modified}")
            for url, size, etag, modified in _sfpmap.object_list(prefix, MAX_FILES)]


def _local_version(path: str) -> Tuple[int, str]:
    st = os.stat(path)
    return st.st_size, f"modified {st.st_mtime_ns}"


def _inputs(place: Dict[str, Any]) -> List[Input]:
    """Every input file of ``place``."""
    out: List[Input] = []
    colmap = place["colmap"]
    if is_url(colmap):
        base = colmap.rstrip("/")
        if _scheme(colmap) == "s3":
            found = [(_checked_key(u), s, v) for u, s, v in _objects(base) if u[len(base) + 1:] in MODEL_FILES]
        else:  # a web server: by the model's file names
            found = []
            for ext in ("bin", "txt"):
                heads = [_sfpmap.object_head(f"{base}/{name}") for name in MODEL_FILES if name.endswith(ext)]
                if all(h is not None for h in heads):
                    found = [(u, s, e or f"modified {m}") for u, s, e, m in heads]
                    break
        out += [("colmap/" + u.rsplit("/", 1)[1], u, s, v) for u, s, v in found]
    elif os.path.isdir(colmap):
        for name in MODEL_FILES:
            path = os.path.join(colmap, name)
            if os.path.isfile(path):
                out.append(("colmap/" + name, path, *_local_version(path)))
    names = {n.split("/", 1)[1] for n, *_ in out}
    if not any({f"cameras.{e}", f"images.{e}", f"points3D.{e}"} <= names for e in ("bin", "txt")):
        raise FileNotFoundError(f"{colmap}: no COLMAP model (cameras, images and points3D, .bin or .txt)")
    if place["database"] is not None:
        db = place["database"]
        if is_url(db):
            head = _sfpmap.object_head(db)
            if head is None:
                raise FileNotFoundError(f"{db}: no such object (the database)")
            out.append(("database.db", db, head[1], head[2] or f"modified {head[3]}"))
        else:
            out.append(("database.db", db, *_local_version(db)))
    if place["images"] is not None:
        out += _image_inputs(place["images"])
    return out


def _image_inputs(images: str) -> List[Input]:
    if _scheme(images) in ("http", "https"):
        raise ValueError(f"{images}: images on a web server cannot be listed: use s3:// or a folder")
    found: List[Input] = []
    if is_url(images):
        base = images.rstrip("/")
        for url, size, version in _objects(base):
            rel = _checked_key(url)[len(base) + 1:]
            if any(part in ("", ".", "..") for part in rel.split("/")):
                raise ValueError(f"{url[:300]}: an image name with an empty, . or .. part")
            found.append(("images/" + rel, url, size, version))
        return found
    if not os.path.isdir(images):
        raise FileNotFoundError(f"{images}: no such folder (the images)")

    def unreadable(e: OSError) -> None:
        raise e  # a folder skipped silently would make a map of some of the images

    for root, dirs, files in os.walk(images, onerror=unreadable):
        dirs.sort()
        for f in sorted(files):
            path = os.path.join(root, f)
            found.append(("images/" + os.path.relpath(path, images), path, *_local_version(path)))
            if len(found) > MAX_FILES:
                raise ValueError(f"{images}: more than {MAX_FILES} files")
    return found


def _fingerprinted_options(place: Dict[str, Any]) -> Dict[str, Any]:
    return {"kind": "sfp" if place["images"] is not None else "features",
            "variants": place["variants"], "budget": place["budget"]}


def _fingerprint(inputs: List[Input], options: Dict[str, Any]) -> str:
    text = json.dumps({"inputs": [[n, loc, s, v] for n, loc, s, v in inputs], "options": options},
                      sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _outputs(place: Dict[str, Any]) -> List[Tuple[str, Optional[str]]]:
    """(file name, variant) of each output; the map's variant is None, the budget's "budget"."""
    names: List[Tuple[str, Optional[str]]] = [(MAP_NAME, None)]
    names += [(f"{v}.sfpm", v) for v in place["variants"]]
    if place["budget"] is not None:
        names.append((f"budget-{place['budget']}.sfpm", "budget"))
    return names


def _join(prefix: str, *parts: str) -> str:
    if is_url(prefix):
        return prefix.rstrip("/") + "/" + "/".join(parts)
    return os.path.join(prefix, *parts)


def job_of(metadata: Dict[str, Any]) -> Optional[Dict[str, Any]]:
    """The batch record a map carries: its operation's ``job``, else the latest in its
    history (a slice of a converted map)."""
    provenance = metadata.get("provenance") or {}
    job = (provenance.get("parameters") or {}).get("job")
    if isinstance(job, dict):
        return job
    for entry in reversed(provenance.get("history") or []):
        job = (entry.get("parameters") or {}).get("job") if isinstance(entry, dict) else None
        if isinstance(job, dict):
            return job
    return None


def _stored_job(location: str) -> Tuple[bool, Optional[Dict[str, Any]]]:
    """Whether something is at ``location``, and the batch record of the map there."""
    if is_url(location):
        if _sfpmap.object_head(location) is None:
            return False, None
    elif not os.path.lexists(location):
        return False, None
    try:
        return True, job_of(json.loads(_sfpmap.map_metadata(location)))
    except _MapError:
        return True, None  # not a map (a network or file error is raised: it says why)


def _check_apart(out: str, place: str, inputs: List[Input], images: Optional[str]) -> None:
    """A folder PREFIX never holds an input, never lies inside the images, and its place folder
    is no link: outputs are renamed into it."""
    root = os.path.realpath(out)
    folder = os.path.join(out, place)
    if os.path.islink(folder) or (os.path.exists(folder) and not os.path.isdir(folder)):
        raise ValueError(f"{folder}: not a folder of its own (a link or a file): outputs are not written through it")
    for _name, location, _s, _v in inputs:
        if not is_url(location) and os.path.realpath(location).startswith(root + os.sep):
            raise ValueError(f"{location}: an input inside the output folder {out}")
    if images is not None and not is_url(images):
        real = os.path.realpath(images)
        if root == real or root.startswith(real + os.sep):
            raise ValueError(f"{out}: the output folder is inside the images {images}")


def _node() -> str:
    """The Ray node running this task; "" outside Ray (asking there would start a Ray)."""
    ray = sys.modules.get("ray")
    if ray is None or not ray.is_initialized():
        return ""
    return str(ray.get_runtime_context().get_node_id())


def run_place(place: Dict[str, Any], out: str, work_dir: Optional[str] = None,
              threads: int = 1, force: bool = False) -> Dict[str, Any]:
    """Converts, slices and stores one place; returns its report row. The place's own errors
    (any exception but an interrupt) are the row's one-line ``error``, never raised."""
    row = _row(str(place.get("place")), place.get("line"))
    row["node"] = _node()
    row["worker_pid"] = os.getpid()
    seconds: Dict[str, float] = row["seconds"]
    work = None
    try:
        began = time.perf_counter()
        inputs = _inputs(place)
        options = _fingerprinted_options(place)
        fingerprint = _fingerprint(inputs, options)
        outputs = _outputs(place)
        finals = [_join(out, place["place"], name) for name, _ in outputs]
        if not is_url(out):
            _check_apart(out, place["place"], inputs, place["images"])
        row.update(fingerprint=fingerprint, outputs=finals, bytes_in=sum(s for _, _, s, _ in inputs))
        # A catalog reads f16 descriptors: the first variant without PQ codes, else the map.
        plain = [i for i, (_, v) in enumerate(outputs) if v not in (None, "budget") and parse_variant(v)["pq"] is None]
        row["catalog_map"] = finals[plain[0] if plain else 0]
        stored = [_stored_job(f) for f in finals]
        seconds["list"] = time.perf_counter() - began
        if not force and all(job is not None and job.get("fingerprint") == fingerprint
                             and job.get("place") == place["place"] for _, job in stored):
            row.update(status="skipped", bytes_in=0)
            return row
        for final, (there, job) in zip(finals, stored):
            if there and not force and (job is None or job.get("place") != place["place"]):
                raise ValueError(f"{final}: exists and was not made by sfpmap.batch for this place "
                                 "(--force replaces it)")

        if is_url(out):
            work = tempfile.mkdtemp(prefix=f"sfpmap-batch-{place['place']}-", dir=work_dir)
        else:
            tmp = os.path.join(out, TMP_NAME)
            os.makedirs(tmp, exist_ok=True)
            work = tempfile.mkdtemp(prefix=f"{place['place']}-", dir=tmp)
        began = time.perf_counter()
        fetched = os.path.join(work, "in")
        _fetch([(loc, os.path.join(fetched, name)) for name, loc, _, _ in inputs if is_url(loc)])
        local = {name: (os.path.join(fetched, name) if is_url(loc) else loc) for name, loc, _, _ in inputs}
        colmap = os.path.dirname(local[next(n for n, *_ in inputs if n.startswith("colmap/"))])
        database = local.get("database.db")
        images = None
        if place["images"] is not None:
            images = os.path.join(fetched, "images") if is_url(place["images"]) else place["images"]
        seconds["fetch"] = time.perf_counter() - began

        began = time.perf_counter()
        job = {"place": place["place"], "fingerprint": fingerprint, "options": options,
               "sfpmap": __version__,
               "inputs": {"colmap": place["colmap"], "database": place["database"],
                          "images": place["images"], "files": len(inputs), "bytes": row["bytes_in"]}}
        made = os.path.join(work, MAP_NAME)
        _convert(colmap, database=database, images=images, out=made, job=job, threads=threads)
        seconds["convert"] = time.perf_counter() - began

        began = time.perf_counter()
        files = [made]
        every_level = None
        for name, variant in outputs[1:]:
            path = os.path.join(work, name)
            if variant == "budget":
                _slice(made, [], out=path, budget=place["budget"])
            else:
                v = parse_variant(variant)
                if v["levels"] is None and every_level is None:
                    every_level = [lv["level"] for lv in json.loads(_sfpmap.map_metadata(made)).get("levels", [])]
                _slice(made, v["levels"] or every_level or [], v["short"], out=path, minimal=v["minimal"], pq=v["pq"])
            files.append(path)
        seconds["slice"] = time.perf_counter() - began

        began = time.perf_counter()
        made_bytes = sum(os.path.getsize(f) for f in files)
        _store(files, finals, out, place["place"])
        seconds["store"] = time.perf_counter() - began
        row.update(status="done", bytes_out=made_bytes)
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as e:  # noqa: BLE001  (a Rust panic is a BaseException too)
        known = isinstance(e, (_SfpmapError, OSError, ValueError))
        row["error"] = one_line(e) if known else f"{type(e).__name__}: {one_line(e)}"
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
        # The worker's peak so far (Ray reuses workers): bounded by its largest place.
        row["worker_peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return row


def _fetch(pairs: List[Tuple[str, str]]) -> None:
    """Downloads each (URL, file), FETCHES_IN_FLIGHT at a time (the calls release the GIL; a
    place of thousands of images waits on round trips, not on bandwidth). The first error is
    raised once those in flight are done; the rest are not started."""
    for _, dest in pairs:
        os.makedirs(os.path.dirname(dest), exist_ok=True)
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=FETCHES_IN_FLIGHT)
    try:
        for done in [pool.submit(_sfpmap.object_download, url, dest, MAX_OBJECT_BYTES) for url, dest in pairs]:
            done.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _store(files: List[str], finals: List[str], out: str, place: str) -> None:
    """Puts each output in place, the map last. Each appears whole or not at all. Nothing is
    removed on an error: an attempt's outputs are whole, and a place is skipped only when all of
    them carry its fingerprint (a rollback could delete what a retried attempt stored)."""
    order = list(range(1, len(files))) + [0]
    if is_url(out):
        for i in order:
            _sfpmap.object_upload(files[i], finals[i])
        return
    folder = os.path.join(out, place)
    os.makedirs(folder, exist_ok=True)
    for i in order:
        os.replace(files[i], finals[i])
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------------------------
# The job


def _catalog(rows: List[Dict[str, Any]], out: str, work_dir: Optional[str], force: bool = False) -> Dict[str, Any]:
    """``PREFIX/catalog.sfpc`` over the places done or skipped, and a failed place's entry of the
    catalog there whose map still carries that entry's fingerprint (a transient failure does
    not drop a good place). Not written again when its places and fingerprints are the same,
    unless ``force``, which also replaces a catalog the job did not make."""
    target = _join(out, CATALOG_NAME)
    entries = {r["place"]: [r["place"], r["fingerprint"],
                            r["catalog_map"] if is_url(out) else os.path.relpath(r["catalog_map"], out)]
               for r in rows if r["status"] in ("done", "skipped")}
    began = time.perf_counter()
    there, previous = _stored_job(target)
    failed = {r["place"] for r in rows if r["status"] == "failed"}
    for name, fingerprint, location in (previous or {}).get("places", []):
        if name in failed and name not in entries:
            kept = _stored_job(location if is_url(location) else os.path.join(out, location))[1]
            if kept is not None and kept.get("fingerprint") == fingerprint:
                entries[name] = [name, fingerprint, location]
    if not entries:
        return {"status": "none", "places": 0}
    places = [entries[k] for k in sorted(entries)]
    fingerprint = hashlib.sha256(json.dumps(places).encode()).hexdigest()
    if not force and previous is not None and previous.get("fingerprint") == fingerprint:
        return {"status": "unchanged", "places": len(places), "url": target,
                "seconds": time.perf_counter() - began}
    if there and not force and not (previous is not None and "places" in previous):
        raise ValueError(f"{target}: exists and was not made by sfpmap.batch")
    record = json.dumps({"fingerprint": fingerprint, "places": places})
    names = [p[0] for p in places]
    locations = [p[2] for p in places]
    if is_url(out):
        with tempfile.TemporaryDirectory(prefix="sfpmap-catalog-", dir=work_dir) as tmp:
            path = os.path.join(tmp, CATALOG_NAME)
            report = json.loads(_sfpmap.build_catalog(locations, names, out=path, job=record))
            _sfpmap.object_upload(path, target)
    else:
        maps = [os.path.join(out, loc) for loc in locations]
        report = json.loads(_sfpmap.build_catalog(maps, names, out=target, locations=locations,
                                                  job=record, force=True))
    return {"status": "written", "places": len(places), "url": target, "bytes": report["bytes"],
            "seconds": time.perf_counter() - began}


def _table(report: Dict[str, Any]) -> str:
    lines = [f"{'place':<24} {'status':<8} {'MB in':>8} {'MB out':>8} "
             + " ".join(f"{s:>8}" for s in STAGES) + "  error"]
    for r in report["rows"]:
        secs = " ".join(f"{r['seconds'][s]:8.2f}" if s in r["seconds"] else f"{'':>8}" for s in STAGES)
        lines.append(f"{r['place'][:24]:<24} {r['status']:<8} {r['bytes_in'] / 1e6:8.2f} "
                     f"{r['bytes_out'] / 1e6:8.2f} {secs}  {r.get('error') or ''}")
    p = report["places"]
    lines.append(f"{p['total']} places: {p['done']} done, {p['skipped']} skipped, {p['failed']} failed; "
                 f"{report['bytes_in'] / 1e6:.1f} MB in, {report['bytes_out'] / 1e6:.1f} MB out, "
                 f"{report['seconds']['wall']:.1f} s ({report['places_per_minute']:.1f} places/min)")
    c = report["catalog"]
    lines.append(f"catalog: {c['status']}" + (f" ({c['url']}, {c['places']} places)" if "url" in c else "")
                 + (f": {c['error']}" if "error" in c else ""))
    return "\n".join(lines)


def _write_report(path: str, report: Dict[str, Any]) -> None:
    fd, tmp = tempfile.mkstemp(prefix=".report-", dir=os.path.dirname(os.path.abspath(path)))
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(report, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _passed_env(credentials: bool) -> Dict[str, str]:
    return {k: v for k, v in os.environ.items()
            if k.startswith(("AWS_", "SFPMAP_")) and (credentials or not SECRET.search(k))}


def _summary(rows: List[Dict[str, Any]], began: float, catalog: Dict[str, Any], **head: Any) -> Dict[str, Any]:
    wall = time.perf_counter() - began
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "skipped", "failed")}
    return {
        **head,
        "places": {"total": len(rows), **counts},
        "bytes_in": sum(r["bytes_in"] for r in rows),
        "bytes_out": sum(r["bytes_out"] for r in rows),
        "seconds": {"wall": wall, **{s: round(sum(r["seconds"].get(s, 0.0) for r in rows), 3) for s in STAGES}},
        "places_per_minute": counts["done"] * 60.0 / wall if wall > 0 else 0.0,
        "catalog": catalog,
        "rows": rows,
    }


def run(manifest: str, out: str, *, address: Optional[str] = None, cpus_per_place: int = 1,
        retries: int = 3, work_dir: Optional[str] = None, force: bool = False,
        pass_credentials: bool = False, report_path: Optional[str] = None,
        progress: Optional[Callable[[int, int, Dict[str, Any]], None]] = None) -> Dict[str, Any]:
    """The job: every place of ``manifest`` as a Ray task, then the catalog. Returns the report
    (``rows`` per place, totals, ``catalog``), also written to ``report_path`` once the places
    are done (the catalog ``pending``) and again at the end. ``progress(done, total, row)`` is
    called as each place ends. Raises ``sfpmap.Error``, ``OSError``, ``ValueError`` or
    ``ConnectionError`` when the job cannot start (the manifest, the cluster)."""
    began = time.perf_counter()
    if is_url(out):
        if _scheme(out) != "s3" or any(c in out for c in "#?%"):
            raise ValueError(f"{out}: outputs go to a folder or an s3:// prefix (no #, ? or %)")
        out = _normal_url(out)
    places, rows = read_manifest(manifest)
    import ray

    if not is_url(out):
        out = os.path.abspath(out)
        os.makedirs(out, exist_ok=True)
        shutil.rmtree(os.path.join(out, TMP_NAME), ignore_errors=True)
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    # A worker is replaced after PLACES_PER_WORKER places: Ray's worker grows by about 10 MB
    # per task of its own (the same calls in a plain loop level off after two places), so
    # a worker's memory stays that of its largest place, not of how many it ran. SPREAD: places
    # go to every node from the start, not first to the driver's until it is full.
    task = ray.remote(num_cpus=cpus_per_place, max_retries=retries, retry_exceptions=False,
                      max_calls=PLACES_PER_WORKER, scheduling_strategy="SPREAD",
                      runtime_env={"env_vars": _passed_env(pass_credentials)})(run_place)
    total = len(places) + len(rows)
    for done, row in enumerate(rows, 1):
        if progress:
            progress(done, total, row)
    # A few tasks per CPU in flight: the driver's bookkeeping stays small at any city size.
    window = max(8, 4 * int(ray.cluster_resources().get("CPU", 1)))
    queue = list(reversed(places))
    pending: Dict[Any, Dict[str, Any]] = {}
    while queue or pending:
        while queue and len(pending) < window:
            p = queue.pop()
            pending[task.remote(p, out, work_dir, cpus_per_place, force)] = p
        ready, _ = ray.wait(list(pending), num_returns=min(len(pending), 16), timeout=1.0)
        for ref in ready:
            p = pending.pop(ref)
            try:
                row = ray.get(ref)
            except ray.exceptions.RayError as e:
                lost = isinstance(e, (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError))
                why = f"its worker or node was lost {retries + 1} times" if lost else "its task failed"
                row = _failed(p["place"], f"{why}: {one_line(e)}", p["line"])
            rows.append(row)
            if progress:
                progress(len(rows), total, row)
    rows.sort(key=lambda r: (r["line"] or 0, r["place"]))
    head = {"manifest": manifest, "out": out, "address": address}
    if report_path:
        _write_report(report_path, _summary(rows, began, {"status": "pending"}, **head))
    try:
        catalog = _catalog(rows, out, work_dir, force)
    except (_SfpmapError, OSError, ValueError) as e:
        catalog = {"status": "failed", "error": one_line(e)}
    if not is_url(out):
        shutil.rmtree(os.path.join(out, TMP_NAME), ignore_errors=True)
    report = _summary(rows, began, catalog, **head)
    if report_path:
        _write_report(report_path, report)
    return report


def main(argv: Optional[List[str]] = None) -> int:
    """``python -m sfpmap.batch``. Exit 0 when every place is done or skipped, 1 when a place
    (or the catalog) failed, 2 when the job could not start (one ``error:`` line)."""
    parser = argparse.ArgumentParser(
        prog="python -m sfpmap.batch",
        description="Convert and slice many places' COLMAP models into sfpmap maps and a catalog, on Ray.")
    parser.add_argument("manifest", help="JSON lines, one place each (file or URL), or an s3:// prefix ending in /")
    parser.add_argument("--out", required=True, help="output folder or s3:// prefix")
    parser.add_argument("--address", help="a Ray cluster (default: RAY_ADDRESS, else a local Ray)")
    parser.add_argument("--report", help="write the report (JSON) here")
    parser.add_argument("--cpus-per-place", type=int, default=1, help="CPUs (and threads) per place (default 1)")
    parser.add_argument("--retries", type=int, default=3, help="retries of a task whose worker is lost (default 3)")
    parser.add_argument("--work-dir", help="where an s3:// job fetches inputs (default: the system's temp folder)")
    parser.add_argument("--force", action="store_true", help="make every place again, replacing what is stored")
    parser.add_argument("--pass-credentials", action="store_true",
                        help="give the tasks the driver's AWS keys and tokens too (default: only AWS_* and "
                             "SFPMAP_* settings without KEY, SECRET, TOKEN, PASSWORD or CREDENTIAL in their name)")
    parser.add_argument("--json", action="store_true", help="print the report as JSON instead of a table")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    args = parser.parse_args(argv)
    if args.cpus_per_place < 1 or args.retries < 0:
        parser.error("--cpus-per-place is at least 1 and --retries at least 0")
    if args.report and not os.path.isdir(os.path.dirname(os.path.abspath(args.report))):
        print(f"error: {args.report}: its folder does not exist", file=sys.stderr)
        return 2

    def progress(done: int, total: int, row: Dict[str, Any]) -> None:
        if not args.quiet and not args.json:
            tail = f": {row['error']}" if row["status"] == "failed" else ""
            print(f"[{done}/{total}] {row['place']} {row['status']}{tail}", file=sys.stderr, flush=True)

    # Ray prints its own notices (a node lost, a task retried) to standard output: they go to
    # standard error while the job runs, so standard output holds the table or JSON alone.
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    try:
        report = run(args.manifest, args.out, address=args.address, cpus_per_place=args.cpus_per_place,
                     retries=args.retries, work_dir=args.work_dir, force=args.force,
                     pass_credentials=args.pass_credentials, report_path=args.report, progress=progress)
    except ImportError as e:
        print(f"error: sfpmap.batch runs on Ray: pip install 'sfpmap[ray]' ({one_line(e)})", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001  (the job could not start or finish: one line)
        known = isinstance(e, (_SfpmapError, OSError, ValueError, ConnectionError))
        print(f"error: {one_line(e) if known else f'{type(e).__name__}: {one_line(e)}'}", file=sys.stderr)
        return 2
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
    if args.json:
        print(json.dumps(report))
    elif not args.quiet:
        print(_table(report).encode("ascii", "backslashreplace").decode())
    failed = report["places"]["failed"] > 0 or report["catalog"]["status"] == "failed"
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
